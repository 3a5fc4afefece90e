"""The figure of merit of the cross's compensation: SEG's 12-signature FOM applied to the gradient tensor's
components and to each sensor's total field, before and after.

Tensor FOM
    Each component of eq. (1) (:func:`magcal.core.conventions.tensor_components`: ``Gxx, Gxy, Gxz, Gyx, Gyy,
    Gyz, Gzz``, nT/m) is band-passed as the scalar is (0.1-0.9 Hz, :func:`magcal.model.tolles_lawson.bandpass`)
    and its peak-to-peak values in the box's maneuvers summed: the component's FOM (nT/m). The tensor FOM is the
    root sum of squares of the seven components' FOMs (nT/m). A permanent platform field gives a constant tensor
    and the band-pass removes it; what the FOM sees is the platform's induced and eddy gradients, the sensors'
    unbalanced calibration (a scale or an axis off in one sensor turns the Earth field's rotation into a false
    gradient) and the noise.
Sensor FOM
    The scalar FOM of each sensor's total field ``|B_i|`` (nT): what a vector sensor's own compensation leaves.
Improvement ratio
    The standard deviation of the band-passed components before over that after, over the maneuvers' samples and
    the seven components together.

The floor: a perfect compensation leaves the noise. The tensor's band-passed noise is ``sqrt(2) sigma_bp / d``
per pair (``2 sigma_bp / d`` for Gzz; ``sigma_bp`` the band-passed noise per axis), and a maneuver's peak-to-peak
value is about five of those.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from magcal.core import conventions
from magcal.core.errors import MagcalError
from magcal.diagnosis.fom import FOMTable, figure_of_merit, find_maneuvers
from magcal.model.tolles_lawson import DEFAULT_PASSBAND_HZ, bandpass

__all__ = ["CrossFOMReport", "TensorFOMTable", "cross_fom_report", "sensor_fom", "tensor_fom"]


@dataclass
class TensorFOMTable:
    """Peak-to-peak values (nT/m) of each band-passed tensor component per maneuver.

    The unit-neutral accessors of :class:`magcal.diagnosis.fom_protocol.FOMFigures`: :attr:`fom` is
    :attr:`fom_nT_per_m`, :attr:`per_maneuver` is :attr:`maneuver_nT_per_m`, :attr:`unit` ``"nT/m"``.

    Attributes
    ----------
    maneuvers : list of Maneuver
    peak_to_peak_nT_per_m : numpy.ndarray, shape (n_maneuvers, 7)
        Columns in :data:`magcal.core.conventions.TENSOR_COMPONENTS` order.
    """

    maneuvers: list
    peak_to_peak_nT_per_m: np.ndarray

    unit: ClassVar[str] = "nT/m"

    @property
    def fom(self) -> float:
        """:attr:`fom_nT_per_m` (nT/m)."""
        return self.fom_nT_per_m

    @property
    def per_maneuver(self) -> np.ndarray:
        """:attr:`maneuver_nT_per_m` (nT/m per maneuver)."""
        return self.maneuver_nT_per_m

    @property
    def component_fom_nT_per_m(self) -> dict[str, float]:
        """Each component's FOM: its peak-to-peak values summed over the maneuvers (nT/m)."""
        sums = self.peak_to_peak_nT_per_m.sum(axis=0)
        return {name: float(v) for name, v in zip(conventions.TENSOR_COMPONENTS, sums)}

    @property
    def fom_nT_per_m(self) -> float:
        """The tensor FOM: the root sum of squares of the components' FOMs (nT/m)."""
        return float(np.sqrt(np.sum(self.peak_to_peak_nT_per_m.sum(axis=0) ** 2)))

    @property
    def maneuver_nT_per_m(self) -> np.ndarray:
        """Each maneuver's root sum of squares over the components of their peak-to-peak values (nT/m)."""
        return np.sqrt(np.sum(self.peak_to_peak_nT_per_m**2, axis=1))

    def to_dict(self) -> dict:
        return {
            "fom_nT_per_m": self.fom_nT_per_m,
            "component_fom_nT_per_m": self.component_fom_nT_per_m,
            "rows": [
                {
                    "heading_deg": round(m.heading_deg, 1),
                    "kind": m.kind,
                    "start": m.start,
                    "stop": m.stop,
                    "p2p_nT_per_m": {c: float(v) for c, v in zip(conventions.TENSOR_COMPONENTS, row)},
                }
                for m, row in zip(self.maneuvers, self.peak_to_peak_nT_per_m)
            ],
        }


def _checked_vectors(vectors_nT, what: str) -> np.ndarray:
    v = np.asarray(vectors_nT, dtype=float)
    if v.ndim != 3 or v.shape[0] != 4 or v.shape[2] != 3:
        raise MagcalError(f"{what} must be the four sensors' vectors, an array (4, N, 3) of nT, got shape {v.shape}")
    if not np.isfinite(v).all():
        raise MagcalError(f"{what} hold NaN or infinite values: fill or cut those samples before judging them")
    return v


def _bandpassed_tensor(vectors, baseline_m, sample_rate_hz, passband_hz) -> np.ndarray:
    """The seven components of eq. (1), band-passed, (N, 7) nT/m in :data:`~magcal.core.conventions.TENSOR_COMPONENTS`
    order."""
    components = conventions.tensor_components(vectors, baseline_m)
    g = np.column_stack([components[name] for name in conventions.TENSOR_COMPONENTS])
    return bandpass(g, sample_rate_hz, passband_hz)


def tensor_fom(
    vectors_nT, baseline_m: float, maneuvers, sample_rate_hz: float, passband_hz=DEFAULT_PASSBAND_HZ
) -> TensorFOMTable:
    """The tensor FOM table of four sensors' vectors (4, N, 3) in one frame (nT), baseline ``d`` (m)."""
    if not maneuvers:
        raise MagcalError("no maneuvers: the record has no roll, pitch or yaw stretch to judge the compensation on")
    g_bp = _bandpassed_tensor(_checked_vectors(vectors_nT, "the vectors"), baseline_m, sample_rate_hz, passband_hz)
    p2p = np.array([np.ptp(g_bp[m.start : m.stop], axis=0) for m in maneuvers])
    return TensorFOMTable(list(maneuvers), p2p)


def sensor_fom(vectors_nT, maneuvers, sample_rate_hz: float, passband_hz=DEFAULT_PASSBAND_HZ) -> list[FOMTable]:
    """The scalar FOM (:func:`magcal.diagnosis.fom.figure_of_merit`) of each sensor's total field ``|B_i|``."""
    vectors = _checked_vectors(vectors_nT, "the vectors")
    return [figure_of_merit(np.linalg.norm(v, axis=1), maneuvers, sample_rate_hz, passband_hz) for v in vectors]


@dataclass
class CrossFOMReport:
    """The cross's FOM before and after a compensation (and, when given, a reference such as the true
    compensation's), the improvement ratio and notes (the tensor's in nT/m:
    :class:`magcal.diagnosis.fom_protocol.FOMComparison`)."""

    before: TensorFOMTable
    after: TensorFOMTable
    sensors_before: list[FOMTable]
    sensors_after: list[FOMTable]
    improvement_ratio: float
    reference: TensorFOMTable | None = None
    sensors_reference: list[FOMTable] | None = None
    notes: list[str] = field(default_factory=list)

    unit: ClassVar[str] = "nT/m"

    def to_dict(self) -> dict:
        out = {
            "fom_before_nT_per_m": self.before.fom_nT_per_m,
            "fom_after_nT_per_m": self.after.fom_nT_per_m,
            "improvement_ratio": float(self.improvement_ratio),
            "sensor_fom_before_nT": [t.fom_nT for t in self.sensors_before],
            "sensor_fom_after_nT": [t.fom_nT for t in self.sensors_after],
            "before": self.before.to_dict(),
            "after": self.after.to_dict(),
            "notes": list(self.notes),
        }
        if self.reference is not None:
            out["fom_reference_nT_per_m"] = self.reference.fom_nT_per_m
            out["reference"] = self.reference.to_dict()
        if self.sensors_reference is not None:
            out["sensor_fom_reference_nT"] = [t.fom_nT for t in self.sensors_reference]
        return out

    def text(self) -> str:
        """One line per maneuver (the components' root sum of squares, nT/m), the components' FOMs, the tensor
        FOM, each sensor's FOM (nT) and the improvement ratio."""
        ref = self.reference
        head = f"{'heading':>8} {'maneuver':>8} {'before':>9} {'after':>9}" + (f" {'reference':>9}" if ref else "")
        lines = ["tensor, per maneuver (nT/m, root sum of squares over the components)", head]
        columns = [self.before.maneuver_nT_per_m, self.after.maneuver_nT_per_m]
        columns += [ref.maneuver_nT_per_m] if ref else []
        for k, m in enumerate(self.after.maneuvers):
            lines.append(f"{m.heading_deg:8.0f} {m.kind:>8} " + " ".join(f"{c[k]:9.3f}" for c in columns))
        lines.append("component FOM (nT/m)")
        tables = [self.before, self.after] + ([ref] if ref else [])
        for name in conventions.TENSOR_COMPONENTS:
            lines.append(f"{name:>17} " + " ".join(f"{t.component_fom_nT_per_m[name]:9.3f}" for t in tables))
        lines.append(f"{'tensor FOM':>17} " + " ".join(f"{t.fom_nT_per_m:9.3f}" for t in tables))
        sensor_tables = [self.sensors_before, self.sensors_after]
        sensor_tables += [self.sensors_reference] if self.sensors_reference else []
        for s in range(len(self.sensors_after)):
            lines.append(f"{f'sensor {s + 1} FOM nT':>17} " + " ".join(f"{t[s].fom_nT:9.3f}" for t in sensor_tables))
        lines.append(f"improvement ratio {self.improvement_ratio:.1f}")
        return "\n".join(lines + self.notes)


def cross_fom_report(
    before_nT,
    after_nT,
    baseline_m: float,
    sample_rate_hz: float,
    *,
    reference_nT=None,
    maneuvers=None,
    attitude_deg=None,
    passband_hz=DEFAULT_PASSBAND_HZ,
) -> CrossFOMReport:
    """The tensor and sensor FOM before and after, and the improvement ratio.

    Parameters
    ----------
    before_nT, after_nT : array_like, shape (4, N, 3)
        The four sensors' vectors before and after the compensation, each pair in one frame (nT).
    baseline_m : float
        The cross's baseline ``d`` (m).
    sample_rate_hz : float
    reference_nT : array_like, shape (4, N, 3), optional
        A third set judged alike, e.g. the true compensation (its FOM is the floor the fit is held to).
    maneuvers : list of Maneuver, optional
        The box's maneuvers; found from ``attitude_deg`` (:func:`magcal.diagnosis.fom.find_maneuvers`) or, without
        it, from sensor 1's direction after the compensation.
    attitude_deg : array_like, shape (N, 3), optional
        Roll, pitch, yaw (deg).
    passband_hz : (float, float)
        The band-pass's edges (Hz).

    Returns
    -------
    CrossFOMReport
    """
    before = _checked_vectors(before_nT, "the vectors before")
    after = _checked_vectors(after_nT, "the vectors after")
    if before.shape != after.shape:
        raise MagcalError(f"the vectors before {before.shape} and after {after.shape} must have the same shape")
    notes = []
    if maneuvers is None:
        flux = None if attitude_deg is not None else after[0]
        maneuvers = find_maneuvers(sample_rate_hz, attitude_deg=attitude_deg, flux_nT=flux)
        source = "the attitude" if attitude_deg is not None else "sensor 1's direction (named in flying order)"
        notes.append(f"{len(maneuvers)} maneuvers found from {source}")
    if len(maneuvers) != 12:
        notes.append(f"{len(maneuvers)} maneuvers, not a box's 12: the FOM is not comparable with a standard one")
    reference = None if reference_nT is None else _checked_vectors(reference_nT, "the reference vectors")
    keep = np.zeros(before.shape[1], dtype=bool)
    for m in maneuvers:
        keep[m.start : m.stop] = True
    g_before = _bandpassed_tensor(before, baseline_m, sample_rate_hz, passband_hz)[keep]
    g_after = _bandpassed_tensor(after, baseline_m, sample_rate_hz, passband_hz)[keep]
    return CrossFOMReport(
        before=tensor_fom(before, baseline_m, maneuvers, sample_rate_hz, passband_hz),
        after=tensor_fom(after, baseline_m, maneuvers, sample_rate_hz, passband_hz),
        sensors_before=sensor_fom(before, maneuvers, sample_rate_hz, passband_hz),
        sensors_after=sensor_fom(after, maneuvers, sample_rate_hz, passband_hz),
        improvement_ratio=float(np.std(g_before) / np.std(g_after)),
        reference=None
        if reference is None
        else tensor_fom(reference, baseline_m, maneuvers, sample_rate_hz, passband_hz),
        sensors_reference=None if reference is None else sensor_fom(reference, maneuvers, sample_rate_hz, passband_hz),
        notes=notes,
    )
