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
warns (:class:`~magcal.errors.CoverageWarning`) when the expected extrapolation error is more than
``factor_warn`` times the full-coverage value or the covered fraction is small.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from .dataset import Dataset, DatasetError
from .errors import CoverageWarning
from .vectors import row_norm

#: Number of parameters of the full single-sensor model seen by total-field data: A (6) and b (3).
FULL_MODEL_PARAMS = 9


def fibonacci_sphere(n):
    """``n`` nearly evenly spread unit vectors (Fibonacci lattice), shape (n, 3)."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    phi = np.pi * (1.0 + 5.0**0.5) * k
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def sphere_centre(points_nT):
    """Centre (nT) of the best sphere through the points (linear least squares); zeros if it is not determined.

    The fallback of :func:`field_shape` when no ellipsoid is determined. The fitted
    centre is used when it is small (under half the radius: any fit will do) or when the readings determine it:
    they spread over a good part of the sphere (RMS distance from their mean at least half the radius) and lie on
    it (radial residual under 15 % of the radius). MEMS parts on a platform often carry a hard-iron offset larger
    than the Earth's field, and the origin is then a poor centre; a small cap of readings does not determine a
    centre, and the origin is then as good a guess as any.
    """
    y = np.asarray(points_nT, dtype=float)
    if y.shape[0] < 4:
        return np.zeros(3)
    scale = float(np.median(row_norm(y))) or 1.0
    ys = y / scale
    design = np.column_stack([2.0 * ys, np.ones(len(ys))])
    rhs = np.einsum("ij,ij->i", ys, ys)
    sol, _, rank, sv = np.linalg.lstsq(design, rhs, rcond=None)
    if rank < 4 or sv[-1] < 1e-6 * sv[0]:
        return np.zeros(3)
    centre = sol[:3]
    r2 = float(sol[3] + centre @ centre)
    if not np.all(np.isfinite(centre)) or r2 <= 0:
        return np.zeros(3)
    radius = np.sqrt(r2)
    if np.linalg.norm(centre) <= 0.5 * radius:
        return centre * scale
    spread = np.sqrt(np.mean(np.sum((ys - ys.mean(axis=0)) ** 2, axis=1)))
    radial = np.sqrt(np.mean((row_norm(ys - centre) - radius) ** 2))
    if spread >= 0.5 * radius and radial <= 0.15 * radius:
        return centre * scale
    return np.zeros(3)


#: A record covering this fraction of the sphere (caps of 30 deg) is warned for uneven density only when...
COVERED_FRACTION = 0.95
#: ...the expected error off its densest directions is at least this many times the per-axis noise.
UNEVEN_FACTOR_WARN = 0.5

#: The quick ellipsoid is trusted when its centre is determined to this fraction of the field (1 sigma)...
SHAPE_CENTRE_TOLERANCE = 0.01
#: ...and its axes differ by at most this factor (a magnetometer's sensitivities differ by far less).
SHAPE_MAX_AXIS_RATIO = 4.0


@dataclass
class FieldShape:
    """The surface one sensor's readings lie on, as the checks before a fit take it.

    Attributes
    ----------
    centre_nT : numpy.ndarray, shape (3,)
        Centre (hard iron), nT.
    cinv : numpy.ndarray, shape (3, 3)
        Maps ``y - centre`` to a vector of the field's magnitude (the ellipsoid's correction, normalised to
        ``det = 1``); the identity for a sphere or the origin.
    field_nT : float
        The field magnitude the shape implies, nT: the ellipsoid's geometric-mean radius, or the sphere's radius,
        or the median ``|y|`` about the origin.
    source : str
        ``"ellipsoid"`` (a trusted ellipsoid fit), ``"sphere"`` (the quick sphere, :func:`sphere_centre`) or
        ``"origin"`` (nothing determines a centre, e.g. a small cap of directions).
    """

    centre_nT: np.ndarray
    cinv: np.ndarray
    field_nT: float
    source: str

    def corrected(self, readings_nT) -> np.ndarray:
        """``C^-1 (y - centre)`` (N, 3), nT."""
        return (np.asarray(readings_nT, dtype=float) - self.centre_nT) @ self.cinv.T

    def directions(self, readings_nT) -> np.ndarray:
        """Unit field directions (N, 3) in the shape's frame."""
        z = self.corrected(readings_nT)
        norm = row_norm(z)
        norm[norm == 0] = 1.0
        return z / norm[:, None]


#: Most samples the checks before a fit take the field's shape from (an even subsample of longer records).
SHAPE_MAX_SAMPLES = 20_000


def _trusted_ellipsoid(y):
    """The ellipsoid fit of ``y`` (N, 3) if it is determined, else None.

    Determined: the fit is an ellipsoid with axes within :data:`SHAPE_MAX_AXIS_RATIO` of each other, and the
    centre's standard error from the linearised fit (its RMS and the Jacobian of :func:`_jacobian` at the fitted
    directions) is below :data:`SHAPE_CENTRE_TOLERANCE` of the field. A cap of directions passes neither: an
    ellipsoid through a cap slides along the cap's axis.
    """
    from .ellipsoid import MIN_SAMPLES, fit_ellipsoid
    from .errors import CalibrationError

    if y.shape[0] < max(MIN_SAMPLES, FULL_MODEL_PARAMS + 1):
        return None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fit = fit_ellipsoid(y, strict=False)
    except (CalibrationError, np.linalg.LinAlgError, ValueError):
        return None
    eig = np.linalg.eigvalsh(fit.A)
    if not (np.all(np.isfinite(eig)) and eig[0] > 0 and np.sqrt(eig[-1] / eig[0]) <= SHAPE_MAX_AXIS_RATIO):
        return None
    z = fit.correct(y)
    u = z / np.maximum(row_norm(z)[..., None], 1e-300)
    j = _jacobian(u)
    try:
        cov = np.linalg.inv(j.T @ j)
    except np.linalg.LinAlgError:
        return None
    centre_se = fit.rms_nT * float(np.sqrt(max(np.trace(cov[6:, 6:]), 0.0)))
    if not np.isfinite(centre_se) or centre_se > SHAPE_CENTRE_TOLERANCE * fit.field_nT:
        return None
    return fit


def field_shape(readings_nT) -> FieldShape:
    """The centre, shape and field magnitude of one sensor's readings (N, 3) in nT, for the checks before a fit.

    In order of preference: the ellipsoid fit (:func:`magcal.ellipsoid.fit_ellipsoid`, not refusing readings a
    little off the ellipsoid) when it is determined (:func:`_trusted_ellipsoid`); else the quick sphere of
    :func:`sphere_centre` when it is determined; else the origin. The ellipsoid matters for MEMS parts: a
    hard-iron offset several times the field and axis gains differing by 2x put the readings far from any sphere
    about the origin and off any sphere at all, yet on an ellipsoid. Records longer than
    :data:`SHAPE_MAX_SAMPLES` are represented by an even subsample of that size.
    """
    y = np.asarray(readings_nT, dtype=float)
    if y.ndim == 2 and y.shape[0] > SHAPE_MAX_SAMPLES:  # an even subsample: the shape of a million samples is
        y = y[::int(np.ceil(y.shape[0] / SHAPE_MAX_SAMPLES))]  # that of twenty thousand of them
    fit = _trusted_ellipsoid(y) if y.ndim == 2 and y.shape[0] else None
    if fit is not None:
        cinv = fit.cinv / np.cbrt(np.linalg.det(fit.cinv))  # det 1: the magnitude is the fitted field
        z = (y - fit.bias_nT) @ cinv.T
        return FieldShape(fit.bias_nT.copy(), cinv, float(np.median(row_norm(z))), "ellipsoid")
    centre = sphere_centre(y) if y.ndim == 2 else np.zeros(3)
    source = "sphere" if np.any(centre != 0) else "origin"
    magnitude = float(np.median(row_norm(y - centre))) if y.size else float("nan")
    return FieldShape(centre, np.eye(3), magnitude, source)


def field_magnitude_nT(readings_nT):
    """The field magnitude (nT) one sensor's readings (N, 3) imply: the median ``|C^-1 (y - c)|`` through the
    shape of :func:`field_shape` (an ellipsoid fit when one is determined).

    The figure to compare with the Earth's field or a reference: hard iron removed and the axes' gains
    averaged (the raw magnitude, offset included, can be far from either).
    """
    y = np.asarray(readings_nT, dtype=float)
    if y.size == 0:
        return float("nan")
    return field_shape(y).field_nT


def _jacobian(directions):
    """Jacobian (N, 9) of ``|z|_A - 1`` in ``A`` (upper triangle) and ``b`` at ``A = I``, ``z = u`` (unit radius)."""
    u = np.asarray(directions, dtype=float)
    ux, uy, uz = u.T
    return np.column_stack([0.5 * ux * ux, ux * uy, ux * uz, 0.5 * uy * uy, uy * uz, 0.5 * uz * uz, -ux, -uy, -uz])


def extrapolation_factor(directions, n_test=600):
    """RMS over the whole sphere of the noise-propagated total-field error, per unit of per-axis noise.

    Parameters
    ----------
    directions : array_like, shape (N, 3)
        Unit field directions in the sensor frame of the calibration samples.
    n_test : int
        Test directions on the sphere.

    Returns
    -------
    float
        ``K = sqrt(mean_u g(u)^T (J^T J)^-1 g(u))``; multiply by the noise sigma (nT) for nT. ``inf`` when the
        samples do not determine the 9 parameters.
    """
    j = _jacobian(directions)
    info = j.T @ j
    try:
        w, v = np.linalg.eigh(info)
    except np.linalg.LinAlgError:
        return float("inf")
    if w[0] <= 1e-12 * max(w[-1], 1e-300):
        return float("inf")
    g = _jacobian(fibonacci_sphere(n_test)) @ v
    return float(np.sqrt(np.mean(np.sum(g * g / w, axis=1))))


@dataclass
class Coverage:
    """Coverage figures per sensor (arrays of length n_sensors)."""

    fraction: np.ndarray
    largest_gap_deg: np.ndarray
    planarity: np.ndarray
    extrapolation_factor: np.ndarray
    full_factor: float
    cap_deg: float
    n_samples: int
    noise_nT: float | None = None

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


def sensor_directions(readings_nT):
    """Unit field directions (N, 3) of one sensor's readings (N, 3): ``C^-1 (y - c)`` normalised, through the
    shape of :func:`field_shape` (the ellipsoid fit when one is determined, else about the quick centre)."""
    y = np.asarray(readings_nT, dtype=float)
    return field_shape(y).directions(y)


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
    test = fibonacci_sphere(n_test)
    frac, gap, plan, fac = [], [], [], []
    for y in readings:
        u = sensor_directions(y)
        dist, _ = cKDTree(u).query(test)
        angle = np.degrees(2.0 * np.arcsin(np.clip(dist / 2.0, 0.0, 1.0)))
        frac.append(float(np.mean(angle <= cap_deg)))
        gap.append(float(angle.max()))
        plan.append(_planarity(y))
        fac.append(extrapolation_factor(u) if n >= FULL_MODEL_PARAMS else float("inf"))
    full = extrapolation_factor(fibonacci_sphere(max(n, FULL_MODEL_PARAMS)))
    return Coverage(np.array(frac), np.array(gap), np.array(plan), np.array(fac), full, float(cap_deg), n,
                    None if noise_nT is None else float(noise_nT))


def check_coverage(data, full_model=True, cap_deg=30.0, noise_nT=None, factor_warn=3.0, fraction_warn=0.5,
                   planarity_min=0.02, source=None):
    """Coverage figures, refusing data that cannot determine a full model and warning when coverage is poor.

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
    poor = [i for i in range(len(cov.fraction))
            if cov.fraction[i] < fraction_warn
            or (cov.extrapolation_factor[i] > factor_warn * cov.full_factor
                and (cov.fraction[i] < COVERED_FRACTION or cov.extrapolation_factor[i] > UNEVEN_FACTOR_WARN))]
    if poor:
        worst = max(poor, key=lambda i: cov.extrapolation_factor[i])
        k = cov.extrapolation_factor[worst]
        if cov.noise_nT is not None:
            err = (f"expected total-field error away from the covered directions ~{k * cov.noise_nT:.3g} nT "
                   f"(even coverage with as many samples: {cov.full_nT:.3g} nT)")
        else:
            err = (f"expected total-field error away from the covered directions ~{k:.3g} x the noise "
                   f"(even coverage with as many samples: {cov.full_factor:.3g} x)")
        warnings.warn(
            f"{where}: poor direction coverage for sensor(s) {', '.join(str(i + 1) for i in poor)}: "
            f"{100 * cov.fraction[worst]:.0f}% of the sphere within {cap_deg:g} deg of a sample, largest gap "
            f"{cov.largest_gap_deg[worst]:.0f} deg; {err}. Record attitudes that fill the gaps",
            CoverageWarning, stacklevel=2,
        )
    return cov


def calibration_input_checks(dataset, reference_nT=None):
    """Checks before a scalar calibration, as warning texts: poor coverage (with the expected extrapolation error)
    and a given reference far from the readings. Raises for a reference in the wrong unit (e.g. 52.2 meant uT).

    Used by ``magcal calibrate``; the fit itself refuses rotation about one axis and too few samples.
    """
    from .reference import resolve_reference

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        if reference_nT is not None:
            resolve_reference(dataset, str(reference_nT))
        if dataset.n_samples >= FULL_MODEL_PARAMS + 1:
            check_coverage(dataset, full_model=False)
    return [str(w.message) for w in caught]


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
        return (f"turn the sensor so that its {axis_words(d)} points along the field (north and down in the "
                "northern hemisphere, north and up in the southern)")


def axis_words(direction) -> str:
    """A sensor-frame direction named by its main axes, e.g. ``+x axis``, ``-y-z direction`` (components at least
    half the largest)."""
    d = np.asarray(direction, dtype=float)
    big = np.abs(d) >= 0.5 * np.abs(d).max()
    name = "".join(f"{'+' if d[k] >= 0 else '-'}{'xyz'[k]}" for k in range(3) if big[k])
    return f"{name} axis" if big.sum() == 1 else f"{name} direction"


def direction_map(readings_nT, n_cells: int = 400, cap_deg: float = 30.0, shape: FieldShape | None = None
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
        return True, (f"enough: the directions are covered and the fit's RMS {rms_nT:.3g} nT is at the noise floor "
                      f"({expected_rms_nT:.3g} nT); stop and calibrate")
    return False, (f"coverage is enough but the fit's RMS {rms_nT:.3g} nT is above the noise floor "
                   f"({expected_rms_nT:.3g} nT): stop and diagnose what the model is missing")
