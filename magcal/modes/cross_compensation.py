"""The cross compensation fit mode: the four-sensor cross flown through a compensation box on a platform
(``--mode cross_compensation``, docs/compensation.md).

Each sensor's platform field (Tolles-Lawson's permanent, induced and eddy terms of a vector sensor, with its own
calibration) fitted against the attitude's Earth field, or the four's mean field without one, then the magnitude
passes (:func:`magcal.fitting.cross_compensation.fit_cross_compensation`); judged by the tensor FOM (nT/m) per
maneuver before and after (:func:`magcal.diagnosis.cross_compensation.cross_compensation_result`); diagnosed on
held-out maneuvers or another flight (:func:`magcal.diagnosis.cross_compensation.diagnose_cross_compensation`).

A mode of its own beside the scalar compensation: its record (four vector sensors, no scalar), its fit, its result
(a :class:`~magcal.fitting.cross_compensation.CrossCompensation`, the tensor's FOM) and its apply differ. ``mode="auto"``
takes it for a four-sensor record with a baseline only when the attitude holds a compensation box's maneuvers
(:data:`MIN_MANEUVERS` or more): a cross turned for its calibration (the total-field fit's record) has none.
"""

from __future__ import annotations

import numpy as np

from magcal.core.errors import MagcalError
from magcal.data.current_columns import current_names
from magcal.data.dataset import Dataset
from magcal.diagnosis.compensation import FOLDS
from magcal.diagnosis.cross_compensation import (
    CrossCompensationDiagnosis,
    CrossCompensationResult,
    CrossRecord,
    cross_compensation_result,
    cross_maneuvers,
    cross_record,
    diagnose_cross_compensation,
    held_out_tensor_fom,
)
from magcal.modes.base import FIT_MODES, FitMode

#: Maneuvers ``mode="auto"`` needs in the attitude to take a four-sensor record for a compensation flight.
MIN_MANEUVERS = 4


def _record(data, current=None) -> CrossRecord:
    """The record of a dataset (its current term taking ``current``: one column, several (``"a,b"`` or a list), else
    the first found); a record as it is, its current term taking ``current`` when given."""
    if not isinstance(data, CrossRecord):
        return cross_record(data, current)
    return data.taking_currents(current_names(current)) if current is not None else data


def field_vector(reference, n: int):
    """The Earth field vector (nT, NED; (3,) or (N, 3)) from ``reference``: a
    :class:`~magcal.checks.reference.VectorReference` (None when its vector is unknown: a fitted one) or an array;
    None for the four's mean field."""
    if reference is None:
        return None
    ned = getattr(reference, "ned_nT", reference)
    ned = np.asarray(ned, dtype=float)
    if not np.isfinite(ned).all():
        return None
    if ned.ndim == 2 and ned.shape[0] != n:
        raise MagcalError(f"the field vector has {ned.shape[0]} rows, the record {n} samples")
    return ned


class CrossCompensationMode(FitMode):
    """The four-sensor cross's compensation, judged by the tensor FOM."""

    name = "cross_compensation"
    title = "cross compensation (the four-sensor cross flown through a compensation box: per-sensor Tolles-Lawson)"
    priority = 35

    def needs(self) -> str:
        return (
            "needs four sensors' columns (s1x .. s4z), the time t, the cross's baseline ('# baseline_m: 0.5') and, "
            "for the maneuvers, the attitude (qw .. qz or roll, pitch, yaw)"
        )

    def applicable(self, dataset, reference=None, **options):
        if isinstance(dataset, CrossRecord):
            return None
        if not isinstance(dataset, Dataset) or dataset.n_sensors != 4:
            return self.needs()
        if dataset.time_s is None or not dataset.baseline_m:
            return self.needs()
        return None

    def chosen_by_auto(self, dataset, **options) -> bool:
        """Only for a compensation flight: four sensors whose attitude holds a box's maneuvers."""
        if self.applicable(dataset, **options) is not None:
            return False
        try:
            record = _record(dataset)
        except MagcalError:
            return False
        return record.attitude_deg is not None and len(cross_maneuvers(record)) >= MIN_MANEUVERS

    def fit(
        self, dataset, reference=None, effects=(), current=None, ridge=0.0, magnitude_passes=2, mask=None
    ) -> CrossCompensationResult:
        """The cross's compensation of a flight (a dataset or a
        :class:`~magcal.diagnosis.cross_compensation.CrossRecord`) with its tensor FOM report; ``reference``: the
        Earth field vector (a :class:`~magcal.checks.reference.VectorReference` or nT NED), else the four's mean;
        ``mask``: the samples the fit may use (bool, (N,); the FOM is taken in every maneuver)."""
        record = _record(dataset, current)
        ned = field_vector(reference, record.n_samples)
        return cross_compensation_result(
            record, effects, field_ned_nT=ned, ridge=ridge, magnitude_passes=magnitude_passes, mask=mask
        )

    def validate(self, dataset, result, reference=None, effects=(), current=None, **options):
        """The held-out tensor FOM of TL alone and with the effects (maneuver folds); None without effects."""
        effects = tuple(effects or result.effects)
        record = _record(dataset, current)
        maneuvers = cross_maneuvers(record)
        if not effects or len(maneuvers) < FOLDS:
            return None
        ned = field_vector(reference, record.n_samples)
        return CrossValidation(
            list(effects),
            held_out_tensor_fom(record, (), maneuvers, field_ned_nT=ned),
            held_out_tensor_fom(record, effects, maneuvers, field_ned_nT=ned),
            len(maneuvers),
        )

    def diagnose(
        self, dataset, result=None, reference=None, effects=(), current=None, also=None, also_reference=None, **options
    ) -> CrossCompensationDiagnosis:
        """The terms beyond TL judged on held-out maneuvers, or on ``also`` (another flight)."""
        record = _record(dataset, current)
        if result is not None and not effects:
            effects = result.effects
        other = None if also is None else _record(also[0] if isinstance(also, (list, tuple)) else also, current)
        ned = field_vector(reference, record.n_samples)
        return diagnose_cross_compensation(record, effects, field_ned_nT=ned, also=other)


class CrossValidation:
    """The held-out tensor FOM (nT/m) of TL alone and with the effects."""

    def __init__(self, effects, fom_tl, fom_effects, n_maneuvers):
        self.effects, self.fom_tl, self.fom_effects, self.n_maneuvers = effects, fom_tl, fom_effects, n_maneuvers

    def to_dict(self) -> dict:
        return {
            "scheme": "maneuvers",
            "folds": FOLDS,
            "n_maneuvers": self.n_maneuvers,
            "effects": list(self.effects),
            "held_out_tensor_fom_tl_nT_per_m": float(self.fom_tl),
            "held_out_tensor_fom_nT_per_m": float(self.fom_effects),
        }

    def text(self) -> str:
        return (
            f"\nHeld-out tensor FOM ({self.n_maneuvers} maneuvers in {FOLDS} folds, each held out of its fit): TL "
            f"alone {self.fom_tl:.3f} nT/m, with {', '.join(self.effects)} {self.fom_effects:.3f} nT/m\n"
        )


#: The cross compensation fit mode.
CROSS_COMPENSATION = FIT_MODES.register(CrossCompensationMode())
