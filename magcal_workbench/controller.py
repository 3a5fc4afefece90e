"""The workbench's actions: every button calls one method here, which calls the engine and updates the state.

The controller holds the loaded :class:`~magcal.Dataset`, the :class:`~magcal_workbench.state.SessionState` (the
selection, the settings), the jobs and the autosave, and one model session per fit mode
(:mod:`magcal_workbench.modelsession`: :attr:`Controller.total_field`, :attr:`Controller.vector`,
:attr:`Controller.gravity`); Diagnose and Add go to the active one (:attr:`Controller.model_session`). It never draws:
views subscribe with :meth:`Controller.on_change` and redraw; the controller and its model sessions tell them what
changed through :meth:`Controller.emit`. Engine work runs through one :class:`~magcal_workbench.jobs.Worker`, so a
second click while a fit runs starts nothing.

All physics is the engine's (:mod:`magcal.fitting.pipeline`, :mod:`magcal.fitting.fitter`, :mod:`magcal.diagnosis`,
:mod:`magcal.calibration.calibration`); this module only chooses what to run, on which samples, and reports what changed.
"""

from __future__ import annotations

import csv
import errno
import io
import json
import os
import sys
import threading
import time
import traceback
from collections.abc import Callable
from typing import Any, cast

import numpy as np

from magcal.calibration.calibration import Calibration, is_transferable
from magcal.checks import quality
from magcal.checks.noise import estimate_noise
from magcal.core import conventions
from magcal.core.errors import MagcalError
from magcal.core.stats import robust_sigma
from magcal.data import io as mio
from magcal.diagnosis import start_workers
from magcal.model import plugins
from magcal.model.terms import EFFECTS, unknown_effect_message
from magcal.modes import mode_choice

from .compensationmodel import CompensationBase, CompensationSession
from .consent import full_path
from .crosscompensationmodel import CrossCompensationSession
from .events import Change
from .figures import MESSAGE_LEN, candidate_label, fmt_nT, format_number
from .figures import rms as _rms
from .gravitymodel import GravitySession
from .jobs import Worker
from .markup import clean_text, error_text, safe_code, safe_text
from .modelsession import ModelSession, session_kinds
from .plots import raw_reference_nT
from .scene import record_field_nT
from .session import SessionStore
from .sessionfile import LABEL
from .state import METHODS, JobInputs, SessionState, StepRecord
from .totalfield import TotalFieldSession
from .vectormodel import VectorSession

#: What other modules import from here (the page's numbers are :mod:`magcal_workbench.figures`').
__all__ = ["MESSAGE_LEN", "Controller", "candidate_label", "error_markdown", "fmt_nT", "format_number"]


class Controller:
    """Actions of one workbench session (shared by every connected browser).

    Parameters
    ----------
    dataset : magcal.Dataset
    state : SessionState, optional
        A reopened session's state; a fresh one is made if omitted.
    store : SessionStore, optional
        Where to autosave; None disables autosave.
    session_id : str, optional
        Folder of this session in ``store``.
    """

    def __init__(
        self,
        dataset,
        state: SessionState | None = None,
        store: SessionStore | None = None,
        session_id: str | None = None,
        worker: Worker | None = None,
    ):
        self.dataset = dataset
        self.state = state or SessionState(dataset.n_samples, dataset.n_sensors, dataset.source)
        if (self.state.n_samples, self.state.n_sensors) != (dataset.n_samples, dataset.n_sensors):
            raise MagcalError("the saved session does not match the data (different size); start a fresh session")
        self.store = store
        self.session_id = session_id
        self.worker = worker or Worker()
        #: Per-axis noise (nT) behind the floors: the user's (:attr:`SessionState.noise_nT`), the file's, else
        #: estimated after each fit (:attr:`noise` says how).
        self.noise_nT: float | None = self.state.noise_nT or dataset.noise_nT
        self.noise: Any = None  # NoiseEstimate of the last fit (magcal.checks.noise.estimate_noise)
        self._quality = None  # QualityReport of the data (magcal.checks.quality.assess), made when first asked
        self.inspected: int | None = None
        self.message = ""
        #: Why the last autosave failed (markdown, escaped), or None: the page shows it, whatever other message
        #: comes, until an autosave succeeds (:meth:`autosave`).
        self.save_problem: str | None = None
        self._saved_at: str | None = None  # when the session was last saved, HH:MM:SS
        self.progress: tuple[str, float | None] | None = None
        self._listeners: list[Callable[[Change], None]] = []
        self._lock = threading.RLock()
        #: One model session per fit mode (:data:`magcal_workbench.modelsession.MODEL_SESSIONS`), by mode name.
        self._mode: tuple | None = None  # the engine's choice of fit mode for the record and its notes, asked once
        self.model_sessions: dict[str, ModelSession] = {name: cls(self) for name, cls in session_kinds()}
        #: The total-field model: the fit every record allows (:mod:`.totalfield`).
        self.total_field = cast(TotalFieldSession, self.model_sessions["total_field"])
        #: The attitude-aided vector model: its fit, reference and location (:mod:`.vectormodel`).
        self.vector = cast(VectorSession, self.model_sessions["vector"])
        #: The gravity model: a compass beside an accelerometer (:mod:`.gravitymodel`).
        self.gravity = cast(GravitySession, self.model_sessions["gravity"])
        #: The compensation: a scalar magnetometer beside a fluxgate on a platform (:mod:`.compensationmodel`).
        self.compensation = cast(CompensationSession, self.model_sessions["compensation"])
        #: The four-sensor cross's compensation on a moving platform (:mod:`.crosscompensationmodel`).
        self.cross_compensation = cast(CrossCompensationSession, self.model_sessions["cross_compensation"])
        # a record large enough for the diagnosis's worker processes: their fork server starts its imports now, so
        # that the first Diagnose does not wait for them
        start_workers(dataset, effects=tuple(EFFECTS.values()))
        if not self.state.history:  # a fresh session: the file's site, if it names one, is the reference
            self.message = self.vector.take_site()
            raw = self.raw_residual_nT()
            self.state.history.append(
                StepRecord(
                    "raw readings", _rms(raw[:, self.kept]), None, [], int(self.kept.sum()), "no correction: |y| - F"
                )
            )
        for session in self.model_sessions.values():  # the saved session's fits (their messages, or why not)
            kept_message = self.message
            note = session.restore()
            said = self.message if self.message != kept_message else ""
            self.message = "  \n".join(m for m in (kept_message, note or said) if m)

    # ------------------------------------------------------------------------------------------------------
    # the model sessions
    # ------------------------------------------------------------------------------------------------------
    @property
    def model_session(self) -> ModelSession:
        """The model Diagnose and Add work on: a compensation on a record the engine's ``choose_mode`` gives a
        compensation mode (the scalar's: a scalar magnetometer's column beside the fluxgate; the cross's: four
        sensors flown through a compensation box), the vector model on a record with attitude and a field vector
        (columns, or the location typed in the page), else the total-field model."""
        chosen = self.model_sessions.get(self.fit_mode_name())
        if isinstance(chosen, CompensationBase):
            return chosen
        return self.vector if self.vector.available else self.total_field

    def fit_mode(self) -> tuple:
        """The engine's choice of fit mode for the record (``magcal.modes.mode_choice``): ``(mode, notes)``, the
        mode None when no mode takes the record; asked once per record."""
        if self._mode is None:
            try:
                self._mode = mode_choice(self.dataset)
            except MagcalError:
                self._mode = (None, [])
        return self._mode

    def fit_mode_name(self) -> str:
        """The name of the engine's fit mode for the record (``""`` when none takes it)."""
        mode = self.fit_mode()[0]
        return "" if mode is None else mode.name

    def compensation_loop(self) -> bool:
        """Whether the record is a compensation flight: the engine's ``choose_mode`` names a compensation mode (the
        scalar's or the cross's), whose session the loop works on."""
        return isinstance(self.model_sessions.get(self.fit_mode_name()), CompensationBase)

    def vector_loop(self) -> bool:
        """Whether the active model session (:attr:`model_session`) is the vector model."""
        return self.model_session is self.vector

    # the total-field model's fit, read by the views (its session holds it)
    calibration = property(
        lambda self: self.total_field.calibration,
        lambda self, cal: setattr(self.total_field, "calibration", cal),
        doc="The total-field model's calibration (:attr:`TotalFieldSession.calibration`), or None.",
    )
    fit_result = property(
        lambda self: self.total_field.fit_result,
        lambda self, fit: setattr(self.total_field, "fit_result", fit),
        doc="The total-field model's last maximum-likelihood fit, or None.",
    )
    corrected_nT = property(
        lambda self: self.total_field.corrected_nT,
        doc="Every sample corrected by the total-field calibration, (n_sensors, N, 3) nT, or None.",
    )
    residual_nT = property(
        lambda self: self.total_field.residual_nT,
        doc="The total-field residual of every sample, (n_sensors, N) nT, or None.",
    )
    diagnosis = property(
        lambda self: self.total_field.diagnosis,
        lambda self, d: setattr(self.total_field, "diagnosis", d),
        doc="The total-field model's last diagnosis (:func:`magcal.diagnosis.diagnose`), or None.",
    )
    held_out_pending = property(
        lambda self: self.total_field.held_out_pending,
        doc="``id`` of the history rows whose held-out check runs in the background (shown ``pending...``).",
    )

    # ------------------------------------------------------------------------------------------------------
    # notification
    # ------------------------------------------------------------------------------------------------------
    def on_change(self, func: Callable[[Change], None]) -> None:
        """``func(kind)`` after a change; kind is a :class:`magcal_workbench.events.Change` (``saved``: an autosave
        failed, or succeeded again, :attr:`save_problem`)."""
        self._listeners.append(func)

    def emit(self, kind: Change) -> None:
        """Tell the listeners (:meth:`on_change`) that ``kind`` changed; the model sessions send their changes
        here too."""
        kind = Change(kind)  # a kind no handler knows is refused here, where it is sent (ValueError)
        for func in list(self._listeners):
            try:
                func(kind)
            except Exception:
                traceback.print_exc()

    def say(self, text: str) -> None:
        """Show ``text`` (markdown) as the page's message; untrusted parts must already be escaped
        (:func:`magcal_workbench.markup.safe_text`)."""
        self.message = text
        self.emit(Change.MESSAGE)

    #: Session settings :meth:`configure` changes (attributes of :class:`SessionState`).
    SETTINGS = ("method", "reference_nT", "fit_reference", "robust", "sensor")

    def configure(self, **settings) -> None:
        """Change session settings (``method``, ``reference_nT``, ``fit_reference``, ``robust``, ``sensor``) and
        autosave; they apply to the next step."""
        unknown = set(settings) - set(self.SETTINGS)
        if unknown:
            raise ValueError(f"unknown setting(s) {sorted(unknown)}; known: {', '.join(self.SETTINGS)}")
        self._check_settings(settings)
        for key, value in settings.items():
            setattr(self.state, key, value)
        self.state.touch()
        self.autosave()
        self.emit(Change.SETTINGS)

    def _check_settings(self, settings: dict) -> None:
        """Refuse a setting the page could not have sent (a value comes from a browser: check it)."""
        from .sessionfile import REFERENCE_RANGE_nT

        if "method" in settings and settings["method"] not in METHODS:
            raise MagcalError(f"unknown method {clean_text(repr(settings['method']), 40)}; one of {', '.join(METHODS)}")
        ref = settings.get("reference_nT")
        if ref is not None:
            try:
                ok = REFERENCE_RANGE_nT[0] <= float(ref) <= REFERENCE_RANGE_nT[1]
            except (TypeError, ValueError):
                ok = False
            if not ok:
                raise MagcalError(
                    f"reference field {clean_text(ref, 40)} nT: give a number in "
                    f"{REFERENCE_RANGE_nT[0]:g} ... {REFERENCE_RANGE_nT[1]:g} nT, or 0 for none"
                )
        sensor = settings.get("sensor")
        if sensor is not None and (
            isinstance(sensor, bool)
            or not isinstance(sensor, (int, np.integer))
            or not 0 <= sensor < self.dataset.n_sensors
        ):
            raise MagcalError(f"no sensor {clean_text(sensor, 40)}; the data have {self.dataset.n_sensors}")

    # ------------------------------------------------------------------------------------------------------
    # data views
    # ------------------------------------------------------------------------------------------------------
    @property
    def kept(self) -> np.ndarray:
        """The kept mask of this moment (a copy). A job reads the mask it started with from its
        :class:`~magcal_workbench.state.JobInputs` (:meth:`run_step`), never this: a rejection made meanwhile
        neither changes what the job fits nor what its history row says it fitted."""
        return self.state.kept

    @property
    def field_nT(self) -> float:
        """Field used to scale the display (nT): the calibration's, the user's, the file's, or the median |raw|."""
        if self.calibration is not None and self.calibration.reference_total_nT:
            return float(self.calibration.reference_total_nT)
        if self.state.reference_nT:
            return float(self.state.reference_nT)
        return record_field_nT(self.dataset)

    def fit_dataset(self):
        """The dataset the engine sees: without its reference when the user asks to fit the magnitude."""
        if self.state.fit_reference:
            return self.dataset.replace(reference_total_nT=None, ref_total_nT=None)
        return self.dataset

    @property
    def reference_arg(self):
        return None if self.state.fit_reference else self.state.reference_nT

    def floor_nT(self, kept: np.ndarray | None = None) -> float | None:
        """Total-field floor for the kept samples (``kept``, default: those of now): ``sigma sqrt(1 - p/N)`` with
        the known or estimated noise."""
        if not self.noise_nT:
            return None
        n = int((self.kept if kept is None else kept).sum())
        p = 9
        if self.calibration is not None and self.calibration.model is not None:
            p += sum(len(e.param_names()) for e, _ in self.calibration.model.instances()) / self.dataset.n_sensors
        return conventions.total_field_floor_nT(self.noise_nT, max(n, 1), p)

    def residual_rms_nT(self, kept: np.ndarray | None = None) -> float:
        """The current fit's total-field RMS (nT) on the kept samples (``kept``, default: those of now)."""
        if self.residual_nT is None:
            return float("nan")
        return _rms(self.residual_nT[:, self.kept if kept is None else kept])

    def rms_per_sensor_nT(self) -> np.ndarray:
        if self.residual_nT is None:
            return np.full(self.dataset.n_sensors, np.nan)
        return np.array([_rms(r[self.kept]) for r in self.residual_nT])

    def raw_residual_nT(self) -> np.ndarray:
        """``|y| - F`` of the raw readings (n_sensors, N): the starting point of the history; ``F`` the raw data's
        own reference (:func:`magcal_workbench.plots.raw_reference_nT`, no fit in it), as the table's raw row."""
        return np.linalg.norm(self.dataset.readings_nT, axis=2) - raw_reference_nT(
            self.dataset, self.state.reference_nT
        )

    def tensor_rms(self, kept: np.ndarray | None = None) -> dict | None:
        """Tensor component RMS (nT/m) over the kept samples (``kept``, default: those of now), before (raw) and
        after, with the floor."""
        ds = self.dataset
        if ds.n_sensors != 4 or not ds.baseline_m:
            return None
        k = self.kept if kept is None else kept
        before = conventions.tensor_components(ds.readings_nT[:, k], ds.baseline_m)
        out = {"before": {c: _rms(v) for c, v in before.items()}, "after": None, "floor": None}
        if self.corrected_nT is not None:
            after = conventions.tensor_components(self.corrected_nT[:, k], ds.baseline_m)
            out["after"] = {c: _rms(v) for c, v in after.items()}
        if self.noise_nT:
            out["floor"] = conventions.tensor_floor_nT_per_m(self.noise_nT, ds.baseline_m)
        return out

    def sample_info(self, index: int) -> dict:
        """What a click on a sample shows: index, time, temperature, kept, residual per sensor (nT)."""
        ds = self.dataset
        i = int(index)
        info: dict = {"index": i, "kept": bool(self.kept[i])}
        if ds.time_s is not None:
            info["time_s"] = float(ds.time_s[i])
        if ds.temperature_C is not None:
            info["temperature_C"] = float(ds.temperature_C[i])
        if self.residual_nT is not None:
            info["residual_nT"] = [float(r) for r in self.residual_nT[:, i]]
        info["raw_nT"] = ds.readings_nT[:, i].tolist()
        return info

    # ------------------------------------------------------------------------------------------------------
    # data quality, noise, held-out validation, transferable terms (all the engine's)
    # ------------------------------------------------------------------------------------------------------
    def quality_report(self):
        """The data's quality findings (:func:`magcal.checks.quality.assess`, with the given noise if any), made once per
        data and noise setting."""
        if self._quality is None:
            self._quality = quality.assess(self.dataset, noise_nT=self.state.noise_nT)
        return self._quality

    def quality_with_fit(self):
        """:meth:`quality_report` plus what the current fit adds: a fitted field magnitude outside the Earth's
        range (:func:`magcal.checks.quality.field_magnitude_finding`: a wrong unit or LSB, or a record near iron)."""

        report = self.quality_report()
        cal = self.calibration
        if cal is None or not cal.reference_fitted or not cal.reference_total_nT:
            return report
        finding = quality.field_magnitude_finding(float(cal.reference_total_nT))
        if finding is None:
            return report
        return quality.QualityReport(
            list(report.findings) + [finding], report.n_sensors, report.n_samples, report.source
        )

    @property
    def noise_given_nT(self) -> float | None:
        """The noise the user typed (nT per axis), else the one declared in the file (``# noise_nT:``), else None."""
        return self.state.noise_nT or self.dataset.noise_nT or None

    def _n_params_total(self, fit=None) -> int:
        """Parameters of the current fit, all sensors together (the floors' and the noise's degrees of freedom)."""
        if fit is not None:
            return int(fit.n_params)
        p = 9 * self.dataset.n_sensors
        if self.calibration is not None and self.calibration.model is not None:
            p += sum(len(e.param_names()) for e, _ in self.calibration.model.instances())
        return p

    def update_noise(self, fit=None, kept: np.ndarray | None = None) -> None:
        """The noise behind the floors, from the current fit's kept residuals (:func:`magcal.checks.noise.estimate_noise`:
        the given one, else differences in time order or still stretches, never below the quantization floor)."""

        if self.residual_nT is None:
            self.noise, self.noise_nT = None, self.noise_given_nT
            return
        k = self.kept if kept is None else kept
        try:
            self.noise = estimate_noise(
                self.fit_dataset().subset(k),
                self.residual_nT[:, k],
                self._n_params_total(fit),
                noise_nT=self.state.noise_nT,
            )
        except MagcalError:
            self.noise = None
        self.noise_nT = self.noise.sigma_nT if self.noise is not None else self.noise_given_nT

    def set_noise(self, noise_nT) -> None:
        """Give the noise per axis (nT), or ``None`` / 0 to estimate it again; the floors follow at once and the
        session saves it.

        Raises
        ------
        MagcalError
            A value that is not a number in :data:`magcal_workbench.sessionfile.NOISE_RANGE_nT` (a value comes from a
            browser: check it).
        """
        from .sessionfile import NOISE_RANGE_nT

        value = None
        if noise_nT is not None:
            try:
                value = float(noise_nT)
            except (TypeError, ValueError):
                value = float("nan")
            if value == 0.0:
                value = None
            elif not NOISE_RANGE_nT[0] <= value <= NOISE_RANGE_nT[1]:
                raise MagcalError(
                    f"noise {clean_text(noise_nT, 40)} nT: give a number in {NOISE_RANGE_nT[0]:g} ... "
                    f"{NOISE_RANGE_nT[1]:g} nT per axis, or 0 to estimate it"
                )
        with self._lock:
            self.state.noise_nT = value
            self.state.touch()
            self._quality = None  # the still-stretch test uses the noise
            self.update_noise(self.fit_result)
        self.autosave()
        self.emit(Change.RESULT)
        floor = self.floor_nT()
        what = f"noise given: {fmt_nT(value)} per axis" if value else "noise estimated again"
        self.say(f"{what}; {self.noise_text()}; total-field floor {fmt_nT(floor)}")

    def noise_text(self) -> str:
        """Plain text: the noise behind the floors and the method that gave it (untrusted-free: engine words)."""
        if self.noise is not None:
            return f"noise {self.noise.text()}"
        given = self.noise_given_nT
        if given:
            where = "given in the workbench" if self.state.noise_nT else "declared in the file (noise_nT)"
            return f"noise {given:.3g} nT per axis ({where})"
        return "noise not known yet: fit first (it is estimated from the fit's residuals) or give it"

    def model_terms(self) -> list[dict]:
        """The model's effects, each ``{"label", "name", "transferable" (bool), "description"}``: an instrument
        term carries to new data, a record-only term describes this record only (:func:`magcal.calibration.calibration.
        is_transferable`). Descriptions of a user's effect are untrusted text."""

        out = []
        for label in self.state.effects:
            name = label.partition(":")[0]
            cls = EFFECTS.get(name)
            out.append(
                {
                    "label": label,
                    "name": name,
                    "transferable": True if cls is None else is_transferable(cls),
                    "description": "" if cls is None else (cls.description or ""),
                }
            )
        return out

    def record_only_applied(self) -> list[str]:
        """Labels of the record-only terms the current calibration applies to this record's corrected data."""
        return [] if self.calibration is None else self.calibration.record_terms()

    # ------------------------------------------------------------------------------------------------------
    # engine steps (synchronous; the page runs them through run_step, which hands each its JobInputs)
    # ------------------------------------------------------------------------------------------------------
    def run_job(self, name: str, job: Callable[[], object]) -> bool:
        """Run an action in the worker; False (and a message) if another one is running."""
        started = self.submit_job(name, job)
        if not started:
            self.say(f"Busy: {safe_text(self.worker.current)} is still running; wait for it to finish.")
        return started

    def submit_job(self, name: str, job: Callable[[], object]) -> bool:
        """Start ``job`` in the worker; False, silently, if another job runs."""
        return self.worker.submit(name, job, on_error=self._job_failed)

    def job_inputs(self) -> JobInputs:
        """The kept mask and the model's effects of this moment, fixed (:meth:`SessionState.job_inputs`)."""
        return self.state.job_inputs()

    def run_step(self, name: str, step: Callable[..., object]) -> bool:
        """Run ``step(inputs=...)`` in the worker with the :class:`~magcal_workbench.state.JobInputs` of this moment
        (the kept mask and the model's effects as the user left them when the step was asked for); False (and a
        message) if another job runs."""
        inputs = self.job_inputs()
        return self.run_job(name, lambda: step(inputs=inputs))

    def submit_step(self, name: str, step: Callable[..., object]) -> bool:
        """:meth:`run_step`, False silently if another job runs (the refit that follows a rejection)."""
        inputs = self.job_inputs()
        return self.submit_job(name, lambda: step(inputs=inputs))

    def _job_failed(self, exc: BaseException) -> None:
        self.end_progress()
        self.say(error_markdown(exc))

    def report_progress(self, message: str, fraction=None) -> None:
        """Show a long step's progress: ``message`` and the fraction done (0 ... 1, None: not known)."""
        self.progress = (message, fraction)
        self.emit(Change.PROGRESS)

    def end_progress(self) -> None:
        """The long step ended: its progress is no longer shown."""
        self.progress = None
        self.emit(Change.PROGRESS)

    # ------------------------------------------------------------------------------------------------------
    # engine steps (synchronous; the page runs them through run_step, which hands each its JobInputs)
    # ------------------------------------------------------------------------------------------------------
    def step_ellipsoid(self, *, inputs: JobInputs | None = None) -> StepRecord:
        """Step 1 of the total-field model (:meth:`TotalFieldSession.ellipsoid`)."""
        return self.total_field.ellipsoid(inputs=inputs)

    def step_align(self, *, inputs: JobInputs | None = None) -> StepRecord:
        """Step 2 of the total-field model (:meth:`TotalFieldSession.align`)."""
        return self.total_field.align(inputs=inputs)

    def step_refine(self, label: str = "refine (ML)", *, inputs: JobInputs | None = None) -> StepRecord:
        """Step 3 of the total-field model (:meth:`TotalFieldSession.refine`)."""
        return self.total_field.refine(label, inputs=inputs)

    def step_calibrate(self, method: str | None = None, *, inputs: JobInputs | None = None) -> StepRecord:
        """The total-field model's whole pipeline with the chosen method (:meth:`TotalFieldSession.fit`)."""
        return self.total_field.fit(method, inputs=inputs)

    def step_gravity(self, *, inputs: JobInputs | None = None):
        """The gravity fit beside the total-field fit (:meth:`GravitySession.fit`)."""
        return self.gravity.fit(inputs=inputs)

    def step_vector(self, *, inputs: JobInputs | None = None):
        """The attitude-aided vector fit beside the total-field fit (:meth:`VectorModel.fit`, the engine's
        :func:`magcal.fitting.vector.fit_vector`) on the kept samples (``inputs``', default those of now); the
        total-field calibration is left as it is."""
        return self.vector.fit(inputs=inputs)

    # ------------------------------------------------------------------------------------------------------
    # the loop: model, diagnose, add
    # ------------------------------------------------------------------------------------------------------
    def available_effects(self) -> list[dict]:
        """The catalogue (:func:`magcal.model.plugins.catalogue`: built-ins first, then the user's effects), each
        ``{"name", "description", "channels", "missing" (reasons, empty if usable), "origin", "source",
        "transferable"}`` (True: an instrument term, carried to new data; False: record-only; None: not said).

        ``origin`` is ``built-in``, ``file``, ``entry point`` or ``python``; the text is untrusted for a user's
        effect (escape it before it joins markdown)."""

        out = []
        for entry in plugins.catalogue():
            cls = EFFECTS[entry["name"]]
            try:
                missing = cls().missing_channels(self.dataset)
            except Exception as exc:  # an effect that cannot even be made is shown as unusable
                missing = [plugins.user_code_error(exc) or f"{type(exc).__name__}: {exc}"]
            if entry.get("error"):
                missing = list(missing) + [entry["error"]]
            out.append(
                {
                    "name": entry["name"],
                    "description": entry.get("description") or "",
                    "channels": list(entry.get("channels", ())),
                    "missing": [str(m) for m in missing],
                    "origin": entry.get("origin", "built-in"),
                    "source": entry.get("source", ""),
                    "transferable": entry.get("transferable"),
                }
            )
        return out

    def load_effects_file(self, path) -> list[str]:
        """Load a user's effect file (:func:`magcal.model.plugins.load_effects_file`: *runs the Python code in it*);
        its effects join the catalogue, and the session remembers the file to load it again when it reopens.

        Parameters
        ----------
        path : str, os.PathLike or magcal.model.plugins.EffectsSource
            The ``.py`` file (``~`` is expanded; a relative path is taken from the current directory), or the file
            read already (what the page's consent was given to, :meth:`magcal_workbench.consent.EffectsFiles.permit`):
            exactly its bytes run.

        Returns
        -------
        list of str
            The names of the effects the file registers.

        Raises
        ------
        MagcalError
            A clear message naming the file and line (:class:`magcal.model.plugins.UserEffectError`).
        """
        source = path if isinstance(path, plugins.EffectsSource) else plugins.read_effects_file(full_path(path))
        names = plugins.load_effects_file(source)
        full = source.path
        with self._lock:
            if full not in self.state.effects_files:
                self.state.effects_files.append(full)
            self.state.touch()
        self.autosave()
        self.emit(Change.EFFECTS)
        listed = ", ".join(safe_code(n) for n in names)
        self.say(f"loaded {listed} from {safe_code(full)}; tick it in the Model tab or let Diagnose rank it")
        return names

    def pending_effects_files(self) -> list[str]:
        """The effects files this session names that are not loaded in this process (a path that leads to a loaded
        file, through ``..`` or a symbolic link, is loaded): never run when the session opens (a session someone
        sends you would run their code), only by :meth:`load_session_effects_files`."""
        loaded = {os.path.realpath(p) for p in plugins.user_files()}
        return [p for p in self.state.effects_files if os.path.realpath(p) not in loaded]

    def load_session_effects_files(self, permit: Callable[[list[str]], dict] | None = None) -> list[str]:
        """Load the effects files this session names (*runs the Python code in them*; the user asked), each file
        once however many paths name it, then restore the saved calibration if it needed their effects. Returns
        the effects loaded; a file that fails is said in the message (the others load).

        Parameters
        ----------
        permit : callable, optional
            ``permit(paths)`` -> ``{path: EffectsSource or MagcalError}``: what each path may run, read once, or why
            not (the page's rule, :meth:`magcal_workbench.consent.EffectsFiles.permit_all`); default: every file
            read (:func:`magcal.model.plugins.read_effects_file`).
        """
        names, problems = [], []
        pending = self.pending_effects_files()
        if not pending:
            raise MagcalError("this session names no effects file that is not loaded already")
        sources = permit(pending) if permit is not None else {p: _read_or_error(p) for p in pending}
        done: set = set()
        repeats = 0
        for path in pending:
            got = sources.get(path) or MagcalError(f"{path}: not permitted")
            if isinstance(got, MagcalError):
                problems.append(str(got))
                continue
            if (got.real, got.sha256) in done:
                repeats += 1  # the same file, named again another way: it runs once
                continue
            done.add((got.real, got.sha256))
            try:
                names += plugins.load_effects_file(got)
            except MagcalError as exc:
                problems.append(str(exc))
        if repeats:
            problems.append(f"{repeats} more path(s) of the session name a file loaded from another: it ran once")
        restored = ""
        if self.state.calibration and self.calibration is None and names:
            try:
                self.total_field.set_calibration(Calibration.from_dict(self.state.calibration, "saved session"))
                self.update_noise()
                restored = "; the saved calibration is restored"
            except Exception as exc:  # still not restorable: the session goes on without it
                restored = f"; the saved calibration could not be restored ({safe_text(str(exc), 300)})"
        self.emit(Change.EFFECTS)
        self.emit(Change.RESULT)
        text = f"loaded {', '.join(safe_code(n) for n in names) or 'no effect'} from the session's effects files"
        text += restored + "".join(f"  \n**Note:** {safe_text(p, MESSAGE_LEN)}" for p in problems)
        self.say(text)
        return names

    def check_label(self, label) -> str:
        """``label`` (``NAME`` or ``NAME:S``) if it names a loaded effect and an existing sensor, else a clear
        :class:`MagcalError` (a label may come from a browser)."""

        label = label.strip() if isinstance(label, str) else label
        m = LABEL.fullmatch(label) if isinstance(label, str) else None
        if m is None:
            raise MagcalError(f"{clean_text(repr(label), 80)} is not an effect label (NAME or NAME:SENSOR)")
        name = label.partition(":")[0]
        if name not in EFFECTS:
            raise MagcalError(unknown_effect_message(name, option="Load effects file (Model tab)"))
        if m.group(1) is not None and not 1 <= int(m.group(1)) <= self.dataset.n_sensors:
            raise MagcalError(f"{label}: no sensor {m.group(1)}; the data have {self.dataset.n_sensors}")
        return label

    def set_effect(self, name: str, on: bool) -> bool:
        if on:
            name = self.check_label(name)
        changed = self.state.add_effect(name) if on else self.state.remove_effect(name)
        if changed:
            self.autosave()
            self.emit(Change.MODEL)
        return changed

    def step_diagnose(self, *, inputs: JobInputs | None = None):
        """Rank the candidate effects for the active model's fit (:attr:`model_session`'s ``diagnose``; its fit of
        ``inputs`` runs first when there is none)."""
        return self.model_session.diagnose(inputs=inputs)

    def loop_diagnosis(self):
        """The diagnosis Diagnose and Add work from (the active model's); None before one."""
        return self.model_session.diagnosis

    def loop_effects(self) -> list[str]:
        """The effects of the model the loop works on."""
        return list(self.model_session.effects)

    def candidate_labels(self) -> list[str]:
        """What Add may put into the active model from its diagnosis, the first to add first."""
        return self.model_session.candidate_labels()

    def advice(self) -> list[str]:
        """What the active model's diagnosis advises (judged on held-out data) that the model does not hold yet;
        empty before a diagnosis."""
        return self.model_session.advice()

    def candidate_holds(self, label: str) -> bool:
        """Whether the active model's diagnosis found that the candidate ``label``'s gain holds on data the fit did
        not see (or advises it)."""
        return self.model_session.candidate_holds(label)

    def step_add(self, label: str | None = None, *, inputs: JobInputs | None = None, note: str = ""):
        """Put a candidate (the top one by default) into the active model and refit (the kept samples and the model
        of ``inputs``, default those of now, with the candidate); ``note`` is appended to the history's step."""
        return self.model_session.add(label, inputs=inputs, note=note)

    def step_add_advice(self, *, inputs: JobInputs | None = None):
        """Put everything the active model's diagnosis advises (:meth:`advice`) into it and refit once."""
        labels = self.advice()
        if not labels:
            raise MagcalError("nothing is advised: diagnose first, or the diagnosis advises nothing that holds")
        return self.model_session.add_all(labels, inputs=inputs)

    def step_remove(self, label: str | None = None, *, inputs: JobInputs | None = None):
        """Take an effect (the last added by default) out of the active model and refit."""
        return self.model_session.remove(label, inputs=inputs)

    # ------------------------------------------------------------------------------------------------------
    # outlier rejection
    # ------------------------------------------------------------------------------------------------------
    def threshold_mask(self, k_sigma: float) -> np.ndarray:
        """Samples (kept ones) whose residual on any sensor is beyond k robust standard deviations."""
        if self.residual_nT is None:
            raise MagcalError("fit first: the threshold is in units of the residual's standard deviation")
        k = self.kept
        r = self.residual_nT
        med = np.median(r[:, k], axis=1, keepdims=True)
        mad = robust_sigma(r[:, k], axis=1, keepdims=True, floor=1e-12)
        out = np.any(np.abs(r - med) > float(k_sigma) * mad, axis=0)
        return out & k

    def reject_threshold(self, k_sigma: float) -> int:
        bad = self.threshold_mask(k_sigma)
        n = self.state.selection.reject(np.flatnonzero(bad), what=f"threshold {k_sigma:g} sigma")
        self._selection_changed(f"threshold {k_sigma:g} sigma rejected {n} sample(s)")
        return n

    def select(self, indices, mode: str = "reject", what: str | None = None) -> int:
        """Reject or restore samples (a box selection, or ``what`` says which: a time range, the fast-turning
        samples); one undo step."""
        idx = np.unique(np.asarray(indices, dtype=int))
        if mode == "restore":
            n = self.state.selection.restore(idx, what=what or f"box restore {idx.size}")
            self._selection_changed(f"{what or 'box selection'}: restored {n} sample(s)")
        else:
            n = self.state.selection.reject(idx, what=what or f"box reject {idx.size}")
            self._selection_changed(f"{what or 'box selection'}: rejected {n} sample(s)")
        return n

    def undo(self):
        what = self.state.selection.undo()
        self._selection_changed(f"undid: {what}" if what else "nothing to undo")

    def redo(self):
        what = self.state.selection.redo()
        self._selection_changed(f"redid: {what}" if what else "nothing to redo")

    def reset_selection(self):
        self.state.selection.reset()
        self._selection_changed("every sample kept again")

    def _selection_changed(self, text: str) -> None:
        self.state.touch()
        self.autosave()
        self.emit(Change.SELECTION)
        self.say(f"{text}; {self.state.selection.n_rejected} of {self.dataset.n_samples} rejected")

    def inspect(self, index: int | None) -> None:
        self.inspected = None if index is None else int(index)
        self.emit(Change.INSPECT)

    # ------------------------------------------------------------------------------------------------------
    # files
    # ------------------------------------------------------------------------------------------------------
    def calibration_json(self) -> bytes:
        if self.calibration is None:
            raise MagcalError("nothing to download yet: run a fit first")
        return (json.dumps(self.calibration.to_dict(), indent=2) + "\n").encode("utf-8")

    def corrected_csv(self) -> bytes:
        """The data corrected by the current calibration (array frame, nT) plus kept flag and residuals."""

        if self.calibration is None:
            raise MagcalError("nothing to download yet: run a fit first")
        extra = dict(self.dataset.extra)
        extra["kept"] = self.kept.astype(int)
        residual = self.residual_nT
        assert residual is not None  # set with every calibration
        for s in range(self.dataset.n_sensors):
            extra[f"s{s + 1}_residual_nT"] = residual[s]
        ds = self.dataset.replace(readings_nT=self.corrected_nT, extra=extra)
        record_only = self.record_only_applied()
        meta = {
            "corrected_by": "magcal workbench",
            "frame": self.calibration.frame,
            "effects": ",".join(self.state.effects) or "none",
            # record-only terms describe this recording: applied here, they would not carry to another one
            "record_only_terms_applied": ",".join(record_only) or "none",
        }
        # in memory from the writer's own parts (write_csv writes only to a path, atomically)
        columns = mio.dataset_columns(ds)
        out = io.StringIO(newline="")
        out.write(mio.metadata_text({**mio.dataset_metadata(ds), **meta}))
        csv.writer(out, lineterminator="\n").writerow(list(columns))
        mio.write_rows(out, columns)
        return out.getvalue().encode("utf-8")

    def autosave(self) -> None:
        """Save the session (:meth:`SessionStore.save`). A failure (a full disk) is kept in :attr:`save_problem`,
        which the page shows until a later autosave succeeds; it is never raised (the change itself stands) and
        never shows the server's paths. Listeners hear ``saved`` when the problem comes or goes."""
        if self.store is None or self.session_id is None:
            return
        for note in self.state.notes:  # the oldest steps dropped (MAX_HISTORY_ROWS): said once, here
            print(f"magcal-workbench: session {self.session_id}: {note}", file=sys.stderr)
        self.state.notes = []
        try:
            self.store.save(self.session_id, self.state)
        except (OSError, MagcalError, MemoryError) as exc:
            problem = autosave_problem(exc, self._saved_at)
            if problem != self.save_problem:
                self.save_problem = problem
                print(f"magcal-workbench: autosave of session {self.session_id} failed: {exc}", file=sys.stderr)
                self.emit(Change.SAVED)
            return
        self._saved_at = time.strftime("%H:%M:%S")
        if self.save_problem is not None:
            self.save_problem = None
            print(f"magcal-workbench: session {self.session_id} saved again", file=sys.stderr)
            self.emit(Change.SAVED)


def is_disk_full(exc: BaseException) -> bool:
    """Whether ``exc`` says the disk is full (``ENOSPC``, or the user's quota: ``EDQUOT``), as an
    :class:`OSError` or as the text of an engine error that wrapped one."""
    codes = {errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC)}
    if isinstance(exc, OSError):
        return exc.errno in codes
    return any(os.strerror(code) in str(exc) for code in codes)


def unsaved_problem(exc: BaseException) -> str:
    """The page's lasting warning when opened data cannot become a saved session (their copy in the session
    folder failed): "the disk is full" when it is; no server path."""
    if is_disk_full(exc):
        head = "**This session is not saved: the disk is full.**"
    else:
        why = exc.strerror if isinstance(exc, OSError) and exc.strerror else error_text(exc)
        head = f"**This session is not saved** ({safe_text(why, 300)})."
    return (
        f"{head} Your work on these data is lost when the workbench stops; free some space, then open the data again."
    )


def autosave_problem(exc: BaseException, saved_at: str | None) -> str:
    """The page's lasting warning about a failed autosave (markdown, escaped, no server path): what failed,
    "the disk is full" when it is, since when the session's changes are not saved, what to do."""
    since = f"since {saved_at}" if saved_at else "since the session opened"
    if is_disk_full(exc):
        head = "**Autosave failed: the disk is full.**"
        todo = "free some space: your next change saves them"
    else:
        why = exc.strerror if isinstance(exc, OSError) and exc.strerror else error_text(exc)
        head = f"**Autosave failed** ({safe_text(why, 300)})."
        todo = "your next change tries again"
    return f"{head} The session's changes {since} are not saved; {todo}."


def _read_or_error(path) -> plugins.EffectsSource | MagcalError:
    """The effects file ``path`` read once (:func:`magcal.model.plugins.read_effects_file`), or why it cannot be."""
    try:
        return plugins.read_effects_file(full_path(path))
    except MagcalError as exc:
        return exc


def error_markdown(exc: BaseException) -> str:
    """The page's message for an exception: a user-facing :class:`MagcalError` as it is, an error raised in a
    user's effect code as its file, line and error (:func:`magcal.model.plugins.user_code_error`, no traceback),
    anything else as an unexpected error (its traceback goes to the server's log). Always escaped."""

    if isinstance(exc, MagcalError):
        return f"**Error:** {safe_text(error_text(exc), MESSAGE_LEN)}"
    user = plugins.user_code_error(exc)
    if user:
        return f"**Error in your effect's code:** {safe_text(user, MESSAGE_LEN)}"
    traceback.print_exception(exc)
    return f"**Unexpected error:** {safe_text(f'{type(exc).__name__}: {error_text(exc)}', MESSAGE_LEN)}"
