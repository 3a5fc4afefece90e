"""The total-field model in the page: :class:`TotalFieldSession`, the fit of ``|B| - F`` and its loop.

The steps of the seed (an ellipsoid per sensor, the Procrustes alignment), the maximum-likelihood refinement, the
whole pipeline with the chosen method, the diagnosis of the fit and the effects added from it, each on the kept
samples and the model of the step's :class:`~magcal_workbench.state.JobInputs`. The calibration, the corrected
readings and the residuals of every sample are kept for the page; the history's row of each step (its RMS, the
floor, the held-out RMS that follows in the background) goes into the session state, whose ``calibration`` and
``history`` fields the session file keeps. The physics is the engine's: the whole fit, the maximum likelihood
started from the page's calibration (step 3, the loop's Add and Remove) and the diagnosis are the total-field fit
mode's (:data:`magcal.modes.TOTAL_FIELD`: ``fit``, ``refine``, ``diagnose``, as ``magcal.calibrate(ds,
mode="total_field")`` and ``magcal.diagnose`` run them); the page's own stages, which the mode does not offer, call
the fitting layer (the seed's ellipsoid per sensor with the rotations reset, :mod:`magcal.fitting.pipeline`; the
Procrustes alignment of the current calibration, :func:`magcal.fitting.pipeline.align_sensors`; the history's
held-out RMS of the fit's own model on blocks warm-started from it, :func:`magcal.fitting.validation.validate`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

from magcal.calibration.calibration import Calibration
from magcal.core.errors import ConvergenceWarning, MagcalError
from magcal.fitting import fitter, pipeline, validation
from magcal.fitting.pipeline import align_sensors
from magcal.geometry.procrustes import rotation_angle_deg
from magcal.model import plugins
from magcal.modes import TOTAL_FIELD

from . import timing
from .events import Change
from .figures import MESSAGE_LEN, candidate_label, fmt_nT, format_number, rms
from .markup import error_text, safe_code, safe_text
from .modelsession import ModelSession, register_session
from .pending import PENDING
from .state import JobInputs, StepRecord

#: The history's names of the pipeline's methods.
METHOD_STEPS = {"ml": "calibrate (ML)", "ellipsoid": "two steps (seed)"}


@register_session
class TotalFieldSession(ModelSession):
    """The total-field model of one controller's data (the fit every record allows).

    Attributes
    ----------
    calibration : magcal.calibration.calibration.Calibration or None
        The last fit's calibration.
    fit_result : magcal.fitting.fitter.FitResult or None
        The last maximum-likelihood fit (None after the seed's steps).
    corrected_nT : numpy.ndarray, shape (n_sensors, N, 3), or None
        Every sample corrected (array frame, nT).
    residual_nT : numpy.ndarray, shape (n_sensors, N), or None
        The total-field residual of every sample (nT).
    diagnosis : magcal.diagnosis.Diagnosis or None
        The last diagnosis of the fit.
    held_out_pending : set of int
        ``id`` of the history rows whose held-out check runs in the background (shown ``pending...``).
    """

    mode = "total_field"
    title = "total-field model"

    #: Fewest kept samples a fit is run on (the base model of one sensor has 9 parameters).
    MIN_KEPT = 20

    def __init__(self, ctrl):
        super().__init__(ctrl)
        self._calibration: Calibration | None = None
        self.fit_result: Any = None
        self.corrected_nT: np.ndarray | None = None
        self.residual_nT: np.ndarray | None = None
        self.held_out_pending: set[int] = set()

    @property
    def calibration(self) -> Calibration | None:
        return self._calibration

    @calibration.setter
    def calibration(self, cal: Calibration | None) -> None:
        self._calibration = cal

    @property
    def effects(self) -> list[str]:
        """The session's effects (the session file's ``effects``; the Model tab's boxes)."""
        return list(self.ctrl.state.effects)

    @effects.setter
    def effects(self, labels) -> None:
        with self.ctrl.state.lock:
            self.ctrl.state.effects = list(labels)
            self.ctrl.state.touch()

    def history(self) -> list[StepRecord]:
        return list(self.ctrl.state.history)

    # --- the session file ----------------------------------------------------------------------------------
    def save(self) -> dict | None:
        """The calibration's document (the session file's ``calibration``; the state keeps it with each step)."""
        return self.ctrl.state.calibration

    def restore(self) -> str:
        """The saved calibration put back (no fit runs); a note when it could not be (a damaged or foreign
        document, or one whose effects are not loaded)."""
        saved = self.ctrl.state.calibration
        if not saved:
            return ""
        try:
            self.set_calibration(Calibration.from_dict(saved, "saved session"))
            self.ctrl.update_noise()
        except Exception as exc:  # a damaged or foreign calibration document: the session goes on without it
            why = exc if isinstance(exc, MagcalError) else f"{type(exc).__name__}: {exc}"
            return f"the saved calibration could not be restored ({safe_text(why, 500)}); run a fit"
        return ""

    def forget(self) -> None:
        super().forget()
        self._calibration = self.fit_result = self.corrected_nT = self.residual_nT = None

    # --- the calibration and its residuals -----------------------------------------------------------------
    def _residuals_of(self, cal: Calibration) -> tuple[np.ndarray, np.ndarray]:
        # the workbench corrects the very record it fitted: its record-only terms (drift, steps...) hold here
        ds = self.ctrl.fit_dataset()
        # an effect that needs the attitude leaves NaN on samples without one; the fit's own note says so
        fields = cal.correct(ds, record_terms="apply", warn=False, force=True)
        return cal.total_field_residuals(ds, fields, record_terms="apply"), fields

    def set_calibration(self, cal: Calibration, residual_nT=None) -> None:
        """Make ``cal`` the model's calibration: every sample corrected and its residual (``residual_nT`` when the
        fit gave it)."""
        if cal.record is None:  # the downloaded JSON names the record its record-only terms describe
            cal.fitted_on(self.dataset)
        res, fields = self._residuals_of(cal)
        self._calibration = cal
        self.corrected_nT = fields
        self.residual_nT = res if residual_nT is None else np.asarray(residual_nT, float)

    # --- the history's row ---------------------------------------------------------------------------------
    def _held_out_rms(self, fit, kept=None, report: bool = True) -> tuple[float | None, str | None]:
        """Total-field RMS (nT) on held-out samples of the current model (:func:`magcal.fitting.validation.validate`,
        ``blocks`` scheme: fitted on alternating blocks of time, warm-started from ``fit``, scored on the blocks
        between); ``(None, why)`` when the record cannot be split, ``(None, None)`` without a maximum-likelihood
        fit. ``kept`` is the fit's mask (default: the kept samples now); ``report`` shows the progress (not from
        the background, where a job after it shows its own)."""
        ctrl = self.ctrl
        if fit is None or getattr(fit, "model", None) is None:
            return None, None
        kept = ctrl.fit_dataset().subset(ctrl.kept if kept is None else kept)
        problem = validation.split_problem(kept)
        if problem:
            return None, f"held-out validation not done: {problem}"
        if report:
            ctrl.report_progress("held-out validation (blocks)", None)
        try:
            v = validation.validate(  # its fit's notes stay in v.fit_notes: the fit itself has said them
                kept,
                model=fit.model,
                scheme="blocks",
                init=fit.calibration,
                robust=ctrl.state.robust,
                reference_total_nT=ctrl.reference_arg,
            )
        except Exception as exc:  # the fit stands and is recorded; its held-out figure is missing, and says why
            why = plugins.user_code_error(exc) or (
                error_text(exc) if isinstance(exc, MagcalError) else f"{type(exc).__name__}: {error_text(exc)}"
            )
            return None, f"held-out validation failed: {why}"
        finally:
            if report:
                ctrl.end_progress()
        return float(v.held_out_rms_nT), None

    def _changes(
        self,
        old: Calibration | None,
        new: Calibration,
        rms_before: float,
        rms_after: float,
        tensor_before=None,
        kept: np.ndarray | None = None,
    ) -> str:
        """One line: RMS before -> after, and how much each parameter group moved."""
        parts = [f"RMS {format_number(rms_before)} -> {format_number(rms_after)} nT"]
        if old is not None and old.n_sensors == new.n_sensors:
            db = max(float(np.max(np.abs(a.bias_nT - b.bias_nT))) for a, b in zip(old.sensors, new.sensors))
            dc = max(float(np.max(np.abs(a.cinv - b.cinv))) for a, b in zip(old.sensors, new.sensors))

            dr = max(rotation_angle_deg(b.R @ a.R.T) for a, b in zip(old.sensors, new.sensors))
            moved = f"bias moved up to {format_number(db, 3)} nT, C^-1 up to {format_number(dc * 1e6, 3)} ppm"
            if new.n_sensors > 1:  # one sensor's rotation is the identity: nothing to say
                moved += f", R up to {format_number(dr * 3600, 3)} arcsec"
            parts.append(moved)
        t = self.ctrl.tensor_rms(kept)
        if t is not None and t["after"] is not None:
            worst = max(t["after"].values())
            prev = max(tensor_before.values()) if tensor_before else max(t["before"].values())
            parts.append(f"worst tensor RMS {prev:.4g} -> {worst:.4g} nT/m")
        return "; ".join(parts)

    def _record(
        self,
        step: str,
        inputs: JobInputs,
        old: Calibration | None,
        rms_before: float,
        t0: float,
        tensor_before=None,
        fit=None,
        notes=(),
    ) -> StepRecord:
        """The history's row of a step that fitted ``inputs`` (its kept mask and model), and the message."""
        ctrl = self.ctrl
        kept = inputs.kept
        rms_after = ctrl.residual_rms_nT(kept)
        ctrl.update_noise(fit, kept)
        cal = self._calibration
        assert cal is not None  # every step leaves a calibration
        outcome = None if fit is None else fit.summary()
        rec = StepRecord(
            step=step,
            rms_nT=rms_after,
            floor_nT=ctrl.floor_nT(kept),
            effects=list(inputs.effects),
            n_kept=int(kept.sum()),
            changes=self._changes(old, cal, rms_before, rms_after, tensor_before, kept),
            elapsed_s=time.perf_counter() - t0,
            fit=None if outcome is None else {k: outcome[k] for k in StepRecord.FIT_KEYS},
        )
        ctrl.state.record(rec, cal.to_dict())
        text = f"**{safe_text(step)}**: {safe_text(rec.changes, MESSAGE_LEN)} ({rec.elapsed_s:.2f} s)"
        conv = " - **the fit did not converge** (see above)" if fit is not None and not fit.success else ""
        tail = "".join(f"  \n- {safe_text(n, MESSAGE_LEN)}" for n in dict.fromkeys(notes))
        has_held_out = fit is not None and getattr(fit, "model", None) is not None
        background = has_held_out and ctrl.worker.in_job()
        generation = ctrl.worker.pending.next_generation()  # an older fit's slow parts are stale now
        if background:  # the result first: the held-out check follows, marked pending until then
            self.held_out_pending.add(id(rec))
            ctrl.say(text + f"; held-out RMS {PENDING}" + conv + tail)
        with timing.span("publish"):
            ctrl.emit(Change.RESULT)  # the refit is shown first: the held-out check below is a second, slower stage
            ctrl.emit(Change.DIAGNOSIS)  # a new fit: the old diagnosis no longer applies (or was just cleared)

        def slow(still_current: Callable[[], bool] = lambda: True) -> None:
            with timing.span("heldout"):
                held_out, held_note = self._held_out_rms(fit, kept, report=not background)
            if not still_current():  # a newer fit came first: this figure is dropped unseen
                self.held_out_pending.discard(id(rec))
                return
            all_notes = list(notes) + ([held_note] if held_note else [])
            with ctrl.state.lock:
                if held_out is not None:
                    rec.held_out_rms_nT = held_out
                    ctrl.state.touch()
                self.held_out_pending.discard(id(rec))
            ctrl.emit(Change.MODEL)  # the history table and the RMS plot gain the held-out figure (or lose "pending")
            with timing.span("autosave"):
                ctrl.autosave()
            final = text + (f"; held-out RMS {fmt_nT(held_out)} (blocks)" if held_out is not None else "") + conv
            final += "".join(f"  \n- {safe_text(n, MESSAGE_LEN)}" for n in dict.fromkeys(all_notes))
            ctrl.say(final)

        if background:
            ctrl.worker.pending.start(generation, "heldout", slow)
        elif has_held_out:
            slow()
        else:
            ctrl.autosave()
            ctrl.say(text + conv + tail)
        return rec

    def _check_kept(self, kept: np.ndarray) -> None:
        n = int(kept.sum())
        if n < self.MIN_KEPT:
            raise MagcalError(
                f"only {n} sample(s) are kept; a fit needs at least {self.MIN_KEPT}. Undo the last "
                "rejection or restore samples (Outliers tab)"
            )

    def _before(self, inputs: JobInputs):
        ctrl = self.ctrl
        self._check_kept(inputs.kept)
        before = ctrl.residual_rms_nT(inputs.kept)
        if not np.isfinite(before):
            before = rms(ctrl.raw_residual_nT()[:, inputs.kept])
        t = ctrl.tensor_rms(inputs.kept)
        tb = (t["after"] or t["before"]) if t else None
        return self._calibration, before, tb

    # --- the steps -----------------------------------------------------------------------------------------
    def ellipsoid(self, *, inputs: JobInputs | None = None) -> StepRecord:
        """Step 1: an ellipsoid per sensor (kept samples: ``inputs``', default those of now); the rotations between
        sensors are reset."""
        ctrl = self.ctrl
        inputs = self.inputs(inputs)
        t0 = time.perf_counter()
        old, rms0, tb = self._before(inputs)
        kept_ds = ctrl.fit_dataset().subset(inputs.kept)
        ref, kind = fitter.fit_reference(kept_ds, ctrl.reference_arg)
        fits, _ = pipeline.ellipsoid_step(kept_ds, "algebraic", ref, kind)
        cal = pipeline.two_step_calibration(kept_ds, fits, [np.eye(3)] * len(fits), kind)
        notes = [w for f in fits for w in f.warnings]
        self.fit_result = None
        self.diagnosis = None
        self.set_calibration(cal)
        return self._record("fit ellipsoid", inputs, old, rms0, t0, tb, notes=notes)

    def align(self, *, inputs: JobInputs | None = None) -> StepRecord:
        """Step 2: Procrustes rotations of sensors 2-4 into sensor 1's frame, from the current C^-1 and b (kept
        samples: ``inputs``', default those of now)."""
        inputs = self.inputs(inputs)
        if self.dataset.n_sensors < 2:
            raise MagcalError("aligning needs at least two sensors; this file has one")
        if self._calibration is None:
            raise MagcalError("fit the ellipsoids first (step 1): alignment works on corrected vectors")
        old, rms0, tb = self._before(inputs)
        t0 = time.perf_counter()
        self.set_calibration(align_sensors(self.dataset.subset(inputs.kept), self._calibration))
        return self._record("align sensors", inputs, old, rms0, t0, tb)

    def refine(self, label: str = "refine (ML)", *, inputs: JobInputs | None = None) -> StepRecord:
        """Step 3: maximum likelihood of the model (base + chosen effects) on the kept samples (both ``inputs``',
        default those of now), started from the calibration on the page (the total-field mode's
        :meth:`~magcal.modes.total_field.TotalFieldMode.refine`)."""
        ctrl = self.ctrl
        inputs = self.inputs(inputs)
        t0 = time.perf_counter()
        old, rms0, tb = self._before(inputs)
        with timing.span("fit"):
            result = TOTAL_FIELD.refine(
                ctrl.fit_dataset(),
                self._calibration,
                effects=inputs.effects,
                robust=ctrl.state.robust,
                mask=inputs.kept,
                reference_total_nT=ctrl.reference_arg,
            )
        notes = [n.text for n in result.notes if not n.is_a(ConvergenceWarning)]  # the status says it
        self.fit_result = result
        self.diagnosis = None
        self.set_calibration(result.calibration, result.residuals_all_nT)
        return self._record(label, inputs, old, rms0, t0, tb, fit=result, notes=notes)

    def fit(self, method: str | None = None, *, inputs: JobInputs | None = None) -> StepRecord:
        """The whole pipeline (the total-field mode's fit, :meth:`magcal.modes.total_field.TotalFieldMode.fit`) with the
        chosen method (ML, the two seed steps, or a global search), on the kept samples with the model's effects (both ``inputs``', default those
        of now)."""
        ctrl = self.ctrl
        inputs = self.inputs(inputs)
        method = method or ctrl.state.method
        t0 = time.perf_counter()
        old, rms0, tb = self._before(inputs)
        ctrl.report_progress(f"{method}: starting", 0.0)
        effects = list(inputs.effects) if method == "ml" else []
        with timing.span("fit"):
            result = TOTAL_FIELD.fit(  # never warns: its report lines are result.remarks, its notes result.notes
                ctrl.fit_dataset(),
                method=method,
                effects=effects,
                robust=ctrl.state.robust,
                reference_total_nT=ctrl.reference_arg,
                seed=0,
                progress=ctrl.report_progress,
                mask=inputs.kept,
                noise_nT=ctrl.state.noise_nT,
            )
        self.fit_result = result.fit
        self.diagnosis = None
        self.set_calibration(result.calibration, None if result.fit is None else result.fit.residuals_all_nT)
        ctrl.end_progress()
        name = METHOD_STEPS.get(method, f"global search ({method})")
        return self._record(name, inputs, old, rms0, t0, tb, fit=result.fit, notes=list(result.remarks))

    # --- the loop ------------------------------------------------------------------------------------------
    def diagnose(self, *, inputs: JobInputs | None = None):
        """Rank the candidate effects for the current fit (the total-field mode's diagnosis,
        :meth:`magcal.modes.total_field.TotalFieldMode.diagnose`; a maximum-likelihood fit of ``inputs`` runs first
        when there is none)."""
        ctrl = self.ctrl
        if self.fit_result is None:
            self.refine(inputs=inputs)
        ctrl.report_progress("diagnosing", None)
        with timing.span("diagnose"):
            d = TOTAL_FIELD.diagnose(
                ctrl.fit_dataset(), self.fit_result, progress=ctrl.report_progress, noise_nT=ctrl.state.noise_nT
            )
        self.diagnosis = d
        ctrl.end_progress()
        ctrl.emit(Change.DIAGNOSIS)
        top = d.candidates[0] if getattr(d, "candidates", None) else None
        extra = f"; top candidate {safe_code(candidate_label(top))}" if top is not None else ""
        ctrl.say(
            f"**diagnose**: verdict {safe_code(d.verdict)}{extra} ({safe_text(d.where_text(), 120)})  \n"
            f"{safe_text(d.summary, MESSAGE_LEN)}"
        )
        return d

    def candidate_labels(self) -> list[str]:
        cands = self.diagnosis.candidates if self.diagnosis is not None else []
        return list(dict.fromkeys(candidate_label(c) for c in cands))

    def add_all(self, labels, *, inputs: JobInputs | None = None, note: str = ""):
        """Put ``labels`` into the model (the session's effects) and refit once (:meth:`refine`); ``note`` is
        appended to the history's step."""
        ctrl = self.ctrl
        inputs = self.inputs(inputs)
        checked = [ctrl.check_label(label) for label in labels]
        added = [label for label in checked if ctrl.state.add_effect(label)]
        if len(checked) == 1 and not added:
            raise MagcalError(f"{checked[0]} is already in the model")
        for label in checked:
            inputs = inputs.with_effect(label)
        ctrl.emit(Change.MODEL)
        return self.refine(label=f"add {', '.join(checked)}{note}", inputs=inputs)

    def _refit_without(self, label: str, inputs: JobInputs | None):
        ctrl = self.ctrl
        inputs = self.inputs(inputs)
        ctrl.state.remove_effect(label)
        ctrl.emit(Change.MODEL)
        effects = tuple(e for e in inputs.effects if e != label)
        return self.refine(label=f"remove {label}", inputs=JobInputs(inputs.kept, effects))

    def lesson_findings(self) -> dict | None:
        """The model's effects (what a lesson of the total-field model checks)."""
        return {"effects": self.effects}
