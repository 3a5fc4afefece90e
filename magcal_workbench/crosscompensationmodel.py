"""The compensation of a four-sensor cross on a moving platform: each sensor's Tolles-Lawson terms (and the platform
current's field beyond them) fitted on a compensation flight, judged by the tensor FOM (nT/m) in the maneuvers (the
engine's fit mode ``"cross_compensation"``, :mod:`magcal.modes.cross_compensation`).

:class:`CrossCompensationSession` is the scalar's :class:`~magcal_workbench.compensationmodel.CompensationSession`
with the cross's engine calls: the loop (fit, diagnose, add, remove, history, the session file's
``compensation_fit``) is their base's, :class:`~magcal_workbench.compensationmodel.CompensationBase`. The fit is
taken against the attitude's Earth field when the page has a field vector (the file's ``ref_n, ref_e, ref_d``, a
location), as ``magcal diagnose --mode cross_compensation`` does, so that the sensors' lag (``time_offset``) is a
candidate; else against the four sensors' mean field (the record's own Earth field: no field vector needed). The
FOM, the maneuvers and the diagnosis are the engine's
(:func:`magcal.diagnosis.cross_compensation.cross_compensation_result`,
:func:`~magcal.diagnosis.cross_compensation.diagnose_cross_compensation`).
"""

from __future__ import annotations

from magcal.core.errors import MagcalError
from magcal.diagnosis.cross_compensation import CROSS_EFFECTS, check_cross_effects, cross_record
from magcal.fitting.compensation import COMPENSATION_EFFECTS
from magcal.modes import CROSS_COMPENSATION

from .compensationmodel import CompensationBase
from .markup import safe_text
from .modelsession import register_session

#: The terms beyond TL the cross's compensation offers, with what each is (the engine's words).
CROSS_TERMS = {name: COMPENSATION_EFFECTS[name] for name in CROSS_EFFECTS}


@register_session
class CrossCompensationSession(CompensationBase):
    """The compensation of a four-sensor cross flown through a compensation box (the model session of the fit mode
    ``"cross_compensation"``, the controller's ``cross_compensation``): the engine's
    :data:`~magcal.modes.CROSS_COMPENSATION`, its FOM the tensor's in nT/m."""

    mode = "cross_compensation"
    title = "cross compensation model"
    words = "cross compensation"
    unit = "nT/m"
    section_title = "Cross compensation (four sensors on a moving platform)"
    step_text = (
        "The record is a four-sensor cross flown through a compensation box: fit each sensor's platform field "
        "(permanent, induced and eddy: Tolles-Lawson) and judge it by the tensor FOM in the maneuvers."
    )
    terms = CROSS_TERMS
    noise_words = "the sensors' noise"

    def missing(self) -> list[str]:
        """What the record lacks for the cross's compensation (empty for four sensors with times and a baseline)."""
        why = CROSS_COMPENSATION.applicable(self.dataset)
        return [] if why is None else [why]

    def make_record(self):
        """The engine's :class:`~magcal.diagnosis.cross_compensation.CrossRecord` of the open data."""
        return cross_record(self.dataset)

    def check_terms(self, names) -> list[str]:
        return list(check_cross_effects(names))

    def field_reference(self):
        """The Earth field vector the fit takes against the attitude, as ``magcal diagnose --mode
        cross_compensation`` does: the page's vector reference (the location typed, the file's ``ref_n, ref_e,
        ref_d``, IGRF along its ``lat, lon``; :meth:`~magcal_workbench.vectormodel.VectorSession.reference`); None
        without the attitude or a vector (the four's mean field: the sensors' lag cannot be judged)."""
        if self.record().attitude_deg is None:
            return None
        vector = getattr(self.ctrl, "vector", None)
        try:
            return None if vector is None else vector.reference()
        except MagcalError:  # IGRF not installed, a damaged column: the four's mean field
            return None

    def engine_fit(self, names, kept, current=None):
        return CROSS_COMPENSATION.fit(
            self.record(), reference=self.field_reference(), effects=names, mask=kept, current=current
        )

    def engine_diagnose(self):
        # the model's current columns named: the record's others stay candidates, each of its own
        return CROSS_COMPENSATION.diagnose(
            self.record(),
            reference=self.field_reference(),
            effects=tuple(self.effects),
            current=self.current_columns or None,
        )

    def result_effects(self, result) -> list[str]:
        return list(result.effects)

    def tl_words(self) -> str:
        comp = self.result.calibration
        return (
            f"Tolles-Lawson per sensor (each of the {len(comp.sensors)} sensors' calibration with its permanent, "
            f"induced and eddy terms; against the {safe_text(comp.reference, 20)} field, "
            f"{comp.magnitude_passes} magnitude passes)"
        )
