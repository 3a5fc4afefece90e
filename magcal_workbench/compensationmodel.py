"""The compensation model of the opened data: a scalar magnetometer beside a fluxgate on a platform, compensated by
Tolles-Lawson and the terms beyond it (the engine's fit mode ``"compensation"``, :mod:`magcal.modes.compensation`).

:class:`CompensationSession` runs the mode's fit on the kept samples, its diagnosis (the terms beyond TL judged on
held-out maneuvers), adds and removes those terms, keeps a history of the figure of merit per step, and what the
session file keeps of it (``compensation_fit``). The FOM, the maneuvers and the band-passed traces are the engine's
(:func:`magcal.diagnosis.compensation.compensation_result`); the functions here only pick what the page shows.
"""

from __future__ import annotations

import time

import numpy as np

from magcal.core.errors import MagcalError
from magcal.fitting.compensation import COMPENSATION_EFFECTS, check_effects, compensation_record
from magcal.model.tolles_lawson import bandpass
from magcal.modes import COMPENSATION

from .events import Change
from .markup import safe_text
from .modelsession import ModelSession, register_session
from .state import MAX_HISTORY_ROWS, JobInputs, pack_mask, unpack_mask

#: Largest record (samples) whose saved compensation is run again when its session opens; a larger one keeps its
#: settings and the page says to press the button.
RESTORE_MAX_SAMPLES = 2_000_000


def model_of(ctrl) -> CompensationSession | None:
    """The compensation session of ``ctrl``'s data, None for a controller without one."""
    sessions = getattr(ctrl, "model_sessions", None) or {}
    return sessions.get("compensation")


@register_session
class CompensationSession(ModelSession):
    """The compensation of one controller's data (the model session of the fit mode ``"compensation"``).

    Attributes
    ----------
    result : magcal.fitting.compensation.CompensationResult or None
        The last fit with its FOM before and after (:class:`magcal.diagnosis.fom.FOMReport`).
    diagnosis : magcal.diagnosis.compensation.CompensationDiagnosis or None
        The last diagnosis (the terms beyond TL judged on held-out maneuvers).
    """

    mode = "compensation"
    title = "compensation model"

    def __init__(self, ctrl):
        super().__init__(ctrl)
        self.result = None
        self._record = None
        self._history: list[dict] = []

    # --- what the data offer -------------------------------------------------------------------------------
    def missing(self) -> list[str]:
        """What the record lacks for a compensation (empty when it holds a scalar column beside the fluxgate)."""
        try:
            why = COMPENSATION.applicable(self.dataset)
        except MagcalError as exc:
            why = str(exc)
        return [] if why is None else [why]

    def record(self):
        """The engine's :class:`~magcal.fitting.compensation.CompensationRecord` of the open data (made once)."""
        if self._record is None:
            self._record = compensation_record(self.dataset)
        return self._record

    @property
    def calibration(self):
        """The last fit's :class:`~magcal.fitting.compensation.Compensation`, or None."""
        return None if self.result is None else self.result.calibration

    # --- the loop ------------------------------------------------------------------------------------------
    def fit(self, *, inputs: JobInputs | None = None, effects=None, step: str = "", again: bool = False):
        """The compensation (TL and the model's terms beyond it, or ``effects``) on the kept samples, its FOM before
        and after, a history row (``step``: what changed) and a message.

        Raises
        ------
        MagcalError
            The record has no scalar column beside the fluxgate, or the engine refuses the fit (its message).
        """
        if not self.available:
            raise MagcalError("the compensation fit " + "; ".join(self.missing()))
        ctrl = self.ctrl
        kept = np.asarray(ctrl.kept if inputs is None else inputs.kept, dtype=bool)
        names = list(check_effects(self.effects if effects is None else effects))
        t0 = time.perf_counter()
        ctrl.report_progress("compensation fit (Tolles-Lawson" + (" + " + ", ".join(names) if names else "") + ")")
        try:
            result = COMPENSATION.fit(self.record(), effects=names, mask=kept)
        finally:
            ctrl.end_progress()
        elapsed = time.perf_counter() - t0
        with ctrl.state.lock:
            self.result, self.diagnosis = result, None
            self._effects = names
            if not again:
                self._history.append(_history_row(step or "Tolles-Lawson fit", result, int(kept.sum()), elapsed))
                del self._history[:-MAX_HISTORY_ROWS]
            ctrl.state.compensation_fit = self.save_doc(kept)
            ctrl.state.touch()
        ctrl.autosave()
        ctrl.emit(Change.COMPENSATION)
        ctrl.emit(Change.DIAGNOSIS)  # the fit cleared the diagnosis of the one before
        ctrl.say(("the saved session's " if again else "") + fit_message(result, elapsed))
        return result

    def diagnose(self, *, inputs: JobInputs | None = None):
        """The terms beyond TL judged on held-out maneuvers (the engine's compensation mode's ``diagnose``); the fit
        runs first when there is none."""
        if self.result is None:
            self.fit(inputs=inputs)
        ctrl = self.ctrl
        ctrl.report_progress("diagnosing the compensation (each term beyond TL on held-out maneuvers)")
        try:
            found = COMPENSATION.diagnose(self.record(), effects=tuple(self.effects))
        finally:
            ctrl.end_progress()
        with ctrl.state.lock:
            self.diagnosis = found
            ctrl.state.touch()
        ctrl.emit(Change.DIAGNOSIS)
        ctrl.say(f"**compensation diagnosis** ({found.elapsed_s:.1f} s): {safe_text(found.summary, 600)}")
        return found

    def candidate_labels(self) -> list[str]:
        """The advice first, then the other judged terms by their held-out FOM, none the model holds."""
        found = self.diagnosis
        if found is None:
            return []
        ranked = sorted((c for c in found.candidates if c.judged), key=lambda c: c.fom_after_nT)
        labels = list(self.advice()) + [c.name for c in ranked]
        return [name for name in dict.fromkeys(labels) if name not in self.effects]

    def candidate_holds(self, label: str) -> bool:
        """Whether the diagnosis recommends ``label`` (its held-out FOM fell by the engine's margin)."""
        found = self.diagnosis
        return found is not None and any(c.name == label and c.recommended for c in found.candidates)

    def add_all(self, labels, *, inputs: JobInputs | None = None, note: str = ""):
        """Put the terms ``labels`` into the model and refit once."""
        names = list(check_effects(labels))
        effects = list(dict.fromkeys(self.effects + names))
        step = "+ " + ", ".join(names) + (f" ({note})" if note else "")
        return self.fit(inputs=inputs, effects=effects, step=step)

    def _refit_without(self, label: str, inputs: JobInputs | None):
        return self.fit(inputs=inputs, effects=[e for e in self.effects if e != label], step=f"- {label}")

    def history(self) -> list[dict]:
        """The fits of this session (``step``, ``effects``, ``fom_before_nT``, ``fom_nT``, ``improvement_ratio``,
        ``n_fitted``, ``elapsed_s``), oldest first."""
        return list(self._history)

    # --- the session file ----------------------------------------------------------------------------------
    def save_doc(self, kept: np.ndarray) -> dict:
        """What the session file keeps (``compensation_fit``): the samples, the terms beyond TL, the history."""
        return {"kept": pack_mask(kept), "effects": list(self.effects), "history": [dict(h) for h in self._history]}

    def save(self) -> dict | None:
        """The session file's ``compensation_fit``, or None before a fit."""
        return getattr(self.ctrl.state, "compensation_fit", None)

    def restore(self) -> str:
        """Run the saved compensation again (its samples and terms); a note for the page when it could not."""
        saved = getattr(self.ctrl.state, "compensation_fit", None)
        if not saved or not self.available:
            return ""
        self._history = [dict(h) for h in saved.get("history", [])]
        if self.dataset.n_samples > RESTORE_MAX_SAMPLES:
            return "the saved session ran the compensation fit: press the Step 1 button to see it again"
        try:
            kept = unpack_mask(saved["kept"], self.dataset.n_samples)
            self.fit(inputs=JobInputs(kept, ()), effects=saved.get("effects", []), again=True)
        except (MagcalError, ValueError, KeyError, TypeError) as exc:
            with self.ctrl.state.lock:
                self.ctrl.state.compensation_fit = None
                self.ctrl.state.touch()
            return f"the saved compensation could not be run again ({safe_text(str(exc), 300)}); run it again"
        return ""

    def forget(self) -> None:
        super().forget()
        self.result = None
        self.ctrl.state.compensation_fit = None

    def lesson_findings(self) -> dict | None:
        """The terms beyond TL and the FOM after (nT), None before a fit (what a lesson's check compares)."""
        if self.result is None:
            return None
        return {"effects": list(self.effects), "fom_nT": self.result.fom_nT}


def _history_row(step: str, result, n_fitted: int, elapsed_s: float) -> dict:
    fom = result.fom
    return {
        "step": step,
        "effects": list(result.calibration.effects),
        "fom_before_nT": None if fom is None else float(fom.before.fom_nT),
        "fom_nT": None if fom is None else float(fom.after.fom_nT),
        "improvement_ratio": None if fom is None else float(fom.improvement_ratio),
        "n_fitted": int(n_fitted),
        "elapsed_s": float(elapsed_s),
    }


def fit_message(result, elapsed_s: float) -> str:
    """The page's line after a compensation fit (markdown): the terms and the FOM before -> after."""
    terms = ", ".join(result.calibration.effects) or "none"
    if result.fom is None:
        figures = "no maneuvers found, so no FOM"
    else:
        fom = result.fom
        figures = (
            f"FOM {fom.before.fom_nT:.3g} -> {fom.after.fom_nT:.3g} nT "
            f"(improvement ratio {fom.improvement_ratio:.3g}, {len(fom.after.maneuvers)} maneuvers)"
        )
    text = f"**compensation fit (Tolles-Lawson; beyond it: {safe_text(terms)})** ({elapsed_s:.2f} s): {figures}"
    return text + "".join(f"  \n- {safe_text(w, 600)}" for w in result.warnings)


def band_passed_traces(session: CompensationSession) -> dict | None:
    """The band-passed scalar before and after the compensation against time, and the maneuvers' spans (the
    engine's band-pass, as its FOM uses), for the compensation panel's figure; None before a fit."""
    result = session.result
    if result is None:
        return None
    record, tl = session.record(), result.calibration.tl
    rate = record.sample_rate_hz
    t = record.time_s if record.time_s is not None else np.arange(record.n_samples) / rate
    before = bandpass(record.scalar_nT, rate, tl.passband_hz, tl.order)
    after = bandpass(tl.compensated_nT, rate, tl.passband_hz, tl.order)
    maneuvers = [] if result.fom is None else result.fom.after.maneuvers
    return {"time_s": np.asarray(t, float), "before_nT": before, "after_nT": after, "maneuvers": maneuvers}


#: The terms beyond TL the page offers, with what each is (the engine's words).
TERMS = dict(COMPENSATION_EFFECTS)
