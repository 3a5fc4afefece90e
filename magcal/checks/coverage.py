"""How much of the direction sphere a calibration record covers, and what that costs off the covered directions.

A scalar calibration fits the ellipsoid the readings ``y`` lie on. It is only determined in the directions the
field took in the sensor frame: fits from tilts limited to a band extrapolate badly to the rest of the sphere,
and a rotation about one axis (readings on one circle) does not determine a full model at all. This module gives

* the **covered fraction**: the share of the unit sphere lying within ``cap_deg`` of some sample direction
  ``u = C^-1 (y - c)`` normalised (``c``, ``C^-1`` a quick ellipsoid fit, :func:`field_shape`), measured on a
  Fibonacci lattice of test directions;
* the **largest gap**: the angular radius (deg) of the largest empty cap;
* the **planarity**: smallest over largest principal spread of the readings (0 for a rotation about one axis);
* the **expected extrapolation error**: the RMS over the whole sphere of the total-field error that the noise
  propagates into the 9 parameters of the ellipsoid (``A = C^-T C^-1`` and ``b``), from the linearised Fisher
  information of the samples actually taken. It is given per nT of noise (a factor ``K``) and, with a noise
  level, in nT; ``K_full`` is the same figure for the same number of samples spread evenly over the sphere.

:func:`check_coverage` refuses (``DatasetError``) a rotation about one axis or no rotation for a full model, and
notes (a :class:`~magcal.core.errors.CoverageWarning` note in its result) when the expected extrapolation error is more than
``factor_warn`` times the full-coverage value or the covered fraction is small.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from magcal.checks.reference import resolve_reference
from magcal.core.errors import CoverageWarning
from magcal.core.notes import Note
from magcal.data.dataset import Dataset, DatasetError
from magcal.geometry.shape import FULL_MODEL_PARAMS, FieldShape, extrapolation_factor, field_shape, sensor_directions
from magcal.geometry.sphere import direction_cover, fibonacci_sphere

#: A record covering this fraction of the sphere (caps of 30 deg) is warned for uneven density only when...
COVERED_FRACTION = 0.95
#: ...the expected error off its densest directions is at least this many times the per-axis noise.
UNEVEN_FACTOR_WARN = 0.5


@dataclass
class Coverage:
    """Coverage figures per sensor (arrays of length n_sensors), and what :func:`check_coverage` says of them
    (``notes``: a :class:`~magcal.core.notes.Note` list, empty from :func:`coverage`)."""

    fraction: np.ndarray
    largest_gap_deg: np.ndarray
    planarity: np.ndarray
    extrapolation_factor: np.ndarray
    full_factor: float
    cap_deg: float
    n_samples: int
    noise_nT: float | None = None
    notes: list = field(default_factory=list, compare=False)

    @property
    def extrapolation_nT(self):
        """Expected whole-sphere total-field error (nT) from the noise, or ``None`` without a noise level."""
        return None if self.noise_nT is None else self.extrapolation_factor * self.noise_nT

    @property
    def full_nT(self):
        """The same for even coverage with the same number of samples (nT), or ``None``."""
        return None if self.noise_nT is None else self.full_factor * self.noise_nT

    def text(self):
        """A readable multi-line summary."""
        lines = [f"direction coverage ({self.n_samples} samples, caps of {self.cap_deg:g} deg):"]
        for i in range(len(self.fraction)):
            k = self.extrapolation_factor[i]
            if self.noise_nT is not None:
                err = f"expected whole-sphere error {k * self.noise_nT:.3g} nT (even coverage: {self.full_nT:.3g} nT)"
            else:
                err = f"expected whole-sphere error {k:.3g} x noise (even coverage: {self.full_factor:.3g} x noise)"
            lines.append(
                f"  sensor {i + 1}: {100 * self.fraction[i]:.0f}% of the sphere, largest gap "
                f"{self.largest_gap_deg[i]:.0f} deg, planarity {self.planarity[i]:.3f}, {err}"
            )
        return "\n".join(lines)


def _planarity(points):
    centred = points - points.mean(axis=0)
    sv = np.linalg.svd(centred, compute_uv=False)
    return float(sv[-1] / sv[0]) if sv[0] > 0 else 0.0


def coverage(data, cap_deg=30.0, noise_nT=None, n_test=2000):
    """Coverage figures of a dataset (or readings (n_sensors, N, 3) / (N, 3) in nT).

    Parameters
    ----------
    data : Dataset or array_like
    cap_deg : float
        A test direction counts as covered when a sample direction lies within this angle.
    noise_nT : float, optional
        Per-axis noise sigma (nT) for the extrapolation error in nT; the dataset's ``noise_nT`` if omitted.
    n_test : int
        Test directions for the covered fraction.

    Returns
    -------
    Coverage
    """
    if isinstance(data, Dataset):
        readings = data.readings_nT
        noise_nT = data.noise_nT if noise_nT is None else noise_nT
    else:
        readings = np.asarray(data, dtype=float)
        if readings.ndim == 2:
            readings = readings[None]
    n = readings.shape[1]
    frac, gap, plan, fac = [], [], [], []
    for y in readings:
        u = sensor_directions(y)
        covered, largest_gap = direction_cover(u, cap_deg, n_test)
        frac.append(covered)
        gap.append(largest_gap)
        plan.append(_planarity(y))
        fac.append(extrapolation_factor(u) if n >= FULL_MODEL_PARAMS else float("inf"))
    full = extrapolation_factor(fibonacci_sphere(max(n, FULL_MODEL_PARAMS)))
    return Coverage(
        np.array(frac),
        np.array(gap),
        np.array(plan),
        np.array(fac),
        full,
        float(cap_deg),
        n,
        None if noise_nT is None else float(noise_nT),
    )


def check_coverage(
    data,
    full_model=True,
    cap_deg=30.0,
    noise_nT=None,
    factor_warn=3.0,
    fraction_warn=0.5,
    planarity_min=0.02,
    source=None,
):
    """Coverage figures, refusing data that cannot determine a full model; a note in them when coverage is poor.

    Parameters
    ----------
    data : Dataset or array_like
    full_model : bool
        The fit has bias, scale and non-orthogonality (9 parameters per sensor). A rotation about one axis only
        (readings on one circle: ``planarity < planarity_min``) or no rotation is then refused.
    factor_warn : float
        Warn when the expected extrapolation error exceeds this many times the even-coverage value (on a sphere
        covered to :data:`COVERED_FRACTION`, only if it is also over :data:`UNEVEN_FACTOR_WARN` times the noise).
    fraction_warn : float
        Warn when less than this fraction of the sphere is covered.

    Returns
    -------
    Coverage
        Its ``notes``: a :class:`~magcal.core.errors.CoverageWarning` note when the coverage is poor, else empty
        (never raised here: the public functions and the command line say it).

    Raises
    ------
    DatasetError
        For a full model on readings from a rotation about one axis or without rotation.
    """
    cov = coverage(data, cap_deg=cap_deg, noise_nT=noise_nT)
    where = source or (data.source if isinstance(data, Dataset) else None) or "dataset"
    if full_model:
        for i in range(len(cov.fraction)):
            if cov.largest_gap_deg[i] > 150.0 and cov.fraction[i] < 0.1:
                raise DatasetError(
                    f"{where}: sensor {i + 1}'s field direction hardly changes (it covers {100 * cov.fraction[i]:.0f}% "
                    "of the sphere); a calibration needs the sensor turned so that each axis points up and down"
                )
            if cov.planarity[i] < planarity_min:
                raise DatasetError(
                    f"{where}: sensor {i + 1}'s readings lie on one circle (planarity {cov.planarity[i]:.4f}): the sensor "
                    "was turned about one axis only, which does not determine bias, scale and non-orthogonality. "
                    "Record more attitudes with the sensor tilted so that each axis points up and down"
                )
    # uneven density (most samples in a few directions) matters on a sphere covered nearly everywhere only when
    # the error it leaves off those directions is a good part of the noise
    poor = [
        i
        for i in range(len(cov.fraction))
        if cov.fraction[i] < fraction_warn
        or (
            cov.extrapolation_factor[i] > factor_warn * cov.full_factor
            and (cov.fraction[i] < COVERED_FRACTION or cov.extrapolation_factor[i] > UNEVEN_FACTOR_WARN)
        )
    ]
    if poor:
        worst = max(poor, key=lambda i: cov.extrapolation_factor[i])
        k = cov.extrapolation_factor[worst]
        if cov.noise_nT is not None:
            err = (
                f"expected total-field error away from the covered directions ~{k * cov.noise_nT:.3g} nT "
                f"(even coverage with as many samples: {cov.full_nT:.3g} nT)"
            )
        else:
            err = (
                f"expected total-field error away from the covered directions ~{k:.3g} x the noise "
                f"(even coverage with as many samples: {cov.full_factor:.3g} x)"
            )
        text = (
            f"{where}: poor direction coverage for sensor(s) {', '.join(str(i + 1) for i in poor)}: "
            f"{100 * cov.fraction[worst]:.0f}% of the sphere within {cap_deg:g} deg of a sample, largest gap "
            f"{cov.largest_gap_deg[worst]:.0f} deg; {err}. Record attitudes that fill the gaps"
        )
        cov.notes = [Note(text, CoverageWarning, "coverage")]
    return cov


def calibration_input_checks(dataset, reference_nT=None):
    """Checks before a scalar calibration, as warning texts: poor coverage (with the expected extrapolation error)
    and a given reference far from the readings. Raises for a reference in the wrong unit (e.g. 52.2 meant uT).

    Used by ``magcal calibrate``; the fit itself refuses rotation about one axis and too few samples.
    """

    notes = []
    if reference_nT is not None:
        notes += resolve_reference(dataset, str(reference_nT)).notes
    if dataset.n_samples >= FULL_MODEL_PARAMS + 1:
        notes += check_coverage(dataset, full_model=False).notes
    return [note.text for note in notes]


# --- where to turn next (the live view) --------------------------------------------------------------------------
#: Covered fraction from which the direction coverage of a live recording counts as enough for a full model.
ENOUGH_FRACTION = 0.85

#: The scalar residual RMS counts as at the noise floor up to this multiple of the expected RMS.
ENOUGH_RMS_FACTOR = 1.5


@dataclass
class DirectionMap:
    """Which directions of the sphere one sensor's samples have visited, and where the largest gap lies.

    Directions are unit vectors in the sensor frame (``C^-1 (y - c)`` normalised, :func:`sensor_directions`).

    Attributes
    ----------
    cells : numpy.ndarray, shape (M, 3)
        Unit vectors spread evenly over the sphere (a Fibonacci lattice).
    visited : numpy.ndarray, shape (M,), bool
        A sample direction lies within ``cap_deg`` of the cell.
    nearest_deg : numpy.ndarray, shape (M,)
        Angle from each cell to the nearest sample direction, deg.
    cap_deg : float
    n_samples : int
    """

    cells: np.ndarray
    visited: np.ndarray
    nearest_deg: np.ndarray
    cap_deg: float
    n_samples: int

    @property
    def fraction(self) -> float:
        """Share of the sphere visited (0-1)."""
        return float(np.mean(self.visited)) if self.visited.size else 0.0

    @property
    def gap_deg(self) -> float:
        """Angular radius of the largest unvisited cap, deg (0 when there are no samples to speak of)."""
        return float(self.nearest_deg.max()) if self.nearest_deg.size else 180.0

    @property
    def next_direction(self) -> np.ndarray | None:
        """Centre of the largest unvisited cap (unit vector, sensor frame), or None when every cell is visited."""
        if self.visited.all():
            return None
        return self.cells[int(np.argmax(self.nearest_deg))]

    @property
    def enough(self) -> bool:
        """The covered fraction reaches :data:`ENOUGH_FRACTION`."""
        return self.fraction >= ENOUGH_FRACTION

    def summary(self) -> str:
        """``74 % of the directions visited, largest gap 67 deg (around the -x+z direction)``."""
        d = self.next_direction
        where = "" if d is None else f" (around the {axis_words(d)})"
        return f"{100 * self.fraction:.0f} % of the directions visited, largest gap {self.gap_deg:.0f} deg{where}"

    def advice(self) -> str:
        """What to do next, in words: where to turn the sensor, or that the sphere is covered."""
        d = self.next_direction
        if self.n_samples < FULL_MODEL_PARAMS:
            return "turn the sensor slowly through every orientation"
        if d is None or self.enough:
            return "the sphere is covered"
        return (
            f"turn the sensor so that its {axis_words(d)} points along the field (north and down in the "
            "northern hemisphere, north and up in the southern)"
        )


def axis_words(direction) -> str:
    """A sensor-frame direction named by its main axes, e.g. ``+x axis``, ``-y-z direction`` (components at least
    half the largest)."""
    d = np.asarray(direction, dtype=float)
    big = np.abs(d) >= 0.5 * np.abs(d).max()
    name = "".join(f"{'+' if d[k] >= 0 else '-'}{'xyz'[k]}" for k in range(3) if big[k])
    return f"{name} axis" if big.sum() == 1 else f"{name} direction"


def direction_map(
    readings_nT, n_cells: int = 400, cap_deg: float = 30.0, shape: FieldShape | None = None
) -> DirectionMap:
    """The visited and missing directions of one sensor's readings.

    Parameters
    ----------
    readings_nT : array_like, shape (N, 3)
        Raw readings, nT.
    n_cells : int
        Cells on the sphere.
    cap_deg : float
        A cell counts as visited when a sample direction lies within this angle (deg).
    shape : FieldShape, optional
        The centre and shape to take directions about (e.g. from the latest fit); default :func:`field_shape`
        of the readings.

    Returns
    -------
    DirectionMap
    """
    y = np.asarray(readings_nT, dtype=float).reshape(-1, 3)
    y = y[np.all(np.isfinite(y), axis=1)]
    cells = fibonacci_sphere(int(n_cells))
    if y.shape[0] == 0:
        return DirectionMap(cells, np.zeros(len(cells), bool), np.full(len(cells), 180.0), float(cap_deg), 0)
    u = (shape if shape is not None else field_shape(y)).directions(y)
    u = u[np.all(np.isfinite(u), axis=1)]
    if u.shape[0] == 0:
        return DirectionMap(cells, np.zeros(len(cells), bool), np.full(len(cells), 180.0), float(cap_deg), 0)
    dist, _ = cKDTree(u).query(cells)
    angle = np.degrees(2.0 * np.arcsin(np.clip(dist / 2.0, 0.0, 1.0)))
    return DirectionMap(cells, angle <= cap_deg, angle, float(cap_deg), int(y.shape[0]))


def live_sufficient(maps, rms_nT=None, expected_rms_nT=None) -> tuple[bool, str]:
    """Whether a live recording holds enough for a calibration: every sensor's direction coverage
    (:attr:`DirectionMap.enough`) and a fit whose residual RMS is within :data:`ENOUGH_RMS_FACTOR` of the RMS
    the noise alone would give.

    Parameters
    ----------
    maps : sequence of DirectionMap
        One per sensor.
    rms_nT : float, optional
        Total-field residual RMS of the latest fit, nT (None before a fit).
    expected_rms_nT : float, optional
        The RMS the noise alone gives, nT (the noise floor).

    Returns
    -------
    (bool, str)
        The verdict and a sentence saying why.
    """
    short = [i + 1 for i, m in enumerate(maps) if not m.enough]
    if short:
        who = "sensor " + ", ".join(map(str, short)) if len(maps) > 1 else "the sensor"
        return False, f"not yet: {who} has visited too few directions ({ENOUGH_FRACTION:.0%} needed)"
    if rms_nT is None:
        return False, "coverage is enough; waiting for the fit"
    if expected_rms_nT is None or not np.isfinite(expected_rms_nT) or expected_rms_nT <= 0:
        return True, f"coverage is enough and the fit's RMS is {rms_nT:.3g} nT (no noise level to judge it against)"
    if rms_nT <= ENOUGH_RMS_FACTOR * expected_rms_nT:
        return True, (
            f"enough: the directions are covered and the fit's RMS {rms_nT:.3g} nT is at the noise floor "
            f"({expected_rms_nT:.3g} nT); stop and calibrate"
        )
    return False, (
        f"coverage is enough but the fit's RMS {rms_nT:.3g} nT is above the noise floor "
        f"({expected_rms_nT:.3g} nT): stop and diagnose what the model is missing"
    )
