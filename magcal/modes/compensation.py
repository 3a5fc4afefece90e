"""The compensation fit mode: a scalar magnetometer beside a fluxgate on a platform (``--mode compensation``,
docs/compensation.md).

Tolles-Lawson's permanent, induced and eddy terms from the fluxgate's direction cosines, band-passed, and the terms
beyond it (:data:`magcal.fitting.compensation.COMPENSATION_EFFECTS`), fitted on the compensation flight
(:func:`magcal.fitting.compensation.fit_compensation`) and judged by the figure of merit in its maneuvers
(:func:`magcal.diagnosis.compensation.compensation_result`); held out by maneuver folds
(:func:`magcal.diagnosis.compensation.validate_compensation`); diagnosed by the terms beyond TL judged on held-out
maneuvers or another flight (:func:`magcal.diagnosis.compensation.diagnose_compensation`). ``mode="auto"`` takes
it, above every other mode, for a record with a scalar magnetometer's column (by name,
:data:`magcal.fitting.compensation.SCALAR_COLUMNS`, or ``scalar=``).
"""

from __future__ import annotations

from magcal.core.errors import MagcalError
from magcal.diagnosis.compensation import (
    CompensationDiagnosis,
    compensation_result,
    diagnose_compensation,
    validate_compensation,
)
from magcal.fitting.compensation import (
    SCALAR_COLUMNS,
    CompensationRecord,
    CompensationResult,
    compensation_record,
    current_names,
    find_scalar_column,
)
from magcal.model.tolles_lawson import DEFAULT_PASSBAND_HZ, DEFAULT_TERMS
from magcal.modes.base import FIT_MODES, FitMode


def _record(data, scalar, current=None) -> CompensationRecord:
    """The record of a dataset (its current term taking ``current``: one column or several, else the first found);
    a record as it is, its current term taking ``current`` when given."""
    if not isinstance(data, CompensationRecord):
        return compensation_record(data, scalar, current)
    return data.taking_currents(current_names(current)) if current is not None else data


class CompensationMode(FitMode):
    """Tolles-Lawson and the terms beyond it, judged by the figure of merit."""

    name = "compensation"
    title = "compensation fit (a scalar magnetometer beside a fluxgate on a platform: Tolles-Lawson and beyond)"
    priority = 40

    def needs(self) -> str:
        return (
            "needs a scalar magnetometer's column (" + ", ".join(SCALAR_COLUMNS[:3]) + " ... or --scalar NAME) "
            "beside the fluxgate's x, y, z and the time t"
        )

    def applicable(self, dataset, scalar=None, **options):
        if isinstance(dataset, CompensationRecord):
            return None
        try:
            found = find_scalar_column(dataset, scalar)
        except MagcalError as exc:
            return str(exc)
        return None if found is not None else self.needs()

    def fit(
        self,
        dataset,
        scalar=None,
        effects=(),
        terms=DEFAULT_TERMS,
        ridge=0.0,
        passband_hz=DEFAULT_PASSBAND_HZ,
        order=4,
        trim=20,
        mask=None,
        current=None,
    ) -> CompensationResult:
        """The compensation of a flight (a :class:`~magcal.data.dataset.Dataset` or a
        :class:`~magcal.fitting.compensation.CompensationRecord`) with its FOM table; ``current``: the current
        term's column(s) (``"cur_strb,cur_com_1"``, a diagnosis's ``current_columns``)."""
        record = _record(dataset, scalar, current)
        options = {"terms": terms, "ridge": ridge, "passband_hz": passband_hz, "order": order, "trim": trim}
        return compensation_result(record, effects, mask=mask, **options)

    def validate(
        self, dataset, result, scalar=None, effects=(), terms=DEFAULT_TERMS, ridge=0.0, current=None, **options
    ):
        """The held-out FOM of TL alone and with the effects (maneuver folds); None without effects."""
        if current is None and result is not None and "current" in result.calibration.effects:
            current = list(result.calibration.current_columns) or None
        record = _record(dataset, scalar, current)
        return validate_compensation(record, effects or result.calibration.effects, terms=terms, ridge=ridge)

    def diagnose(
        self,
        dataset,
        result=None,
        scalar=None,
        effects=(),
        also=None,
        terms=DEFAULT_TERMS,
        ridge=0.0,
        current=None,
        **options,
    ) -> CompensationDiagnosis:
        """The terms beyond TL judged on held-out maneuvers, or on ``also`` (another flight: a dataset or a
        record); each current column of the record a candidate of its own unless ``current`` names the term's."""
        record = _record(dataset, scalar, current)
        if result is not None and not effects:
            effects = result.calibration.effects
            if current is None and "current" in effects and result.calibration.current_columns:
                record = record.taking_currents(result.calibration.current_columns)  # the others stay candidates
        other = None if also is None else _record(also[0] if isinstance(also, (list, tuple)) else also, scalar, current)
        return diagnose_compensation(record, effects, also=other, terms=terms, ridge=ridge)


#: The compensation fit mode.
COMPENSATION = FIT_MODES.register(CompensationMode())
