"""The page's steps beside the tabs' own: the check of the readings before an engine step, the refit that follows a
change of the selection (:meth:`Steps.changing_selection`), and loading a user's effects file. The fits, Diagnose,
Add and the outliers' buttons are the Calibrate, Model and Outliers tabs' (:mod:`magcal_workbench.calibratetab`,
:mod:`magcal_workbench.modeltab`, :mod:`magcal_workbench.outlierstab`).

Each step runs in the worker (:class:`magcal_workbench.jobs.Worker`) with the kept mask it started with; a
rejection made while a job runs is refitted after it (:meth:`Steps.maybe_refit`)."""

from __future__ import annotations

import threading
from contextlib import contextmanager

import numpy as np

from magcal.core.errors import MagcalError

from .actions import action
from .markup import safe_text
from .parts import PagePart


class Steps(PagePart):
    """The refit that follows a change of the selection, the effects files' loading, and the check of the
    readings.

    Handed what it uses.

    Parameters
    ----------
    ctrl, panels : callable
        Getters: the open data's :class:`~magcal_workbench.controller.Controller` and the
        :class:`~magcal_workbench.panels.Panels` (made after this part).
    values : magcal_workbench.checks.PageValues
        What each input widget may send (checked before it is read).
    worker : magcal_workbench.jobs.Worker
        The one worker (a refit follows the running job).
    local : callable
        ``local()``: whether the page is served to this machine only (an effects file may load only then; asked
        at each load, as the workbench's :attr:`~magcal_workbench.app.Workbench.local` may change).
    effects_gate : magcal_workbench.consent.EffectsFiles
        Which effects files the page may load.
    """

    def __init__(self, *, ctrl, panels, values, worker, local, effects_gate):
        self._ctrl, self._panels, self._local = ctrl, panels, local
        self.values, self.worker, self.effects_gate = values, worker, effects_gate
        self.refit_pending = False
        self._pending_lock = threading.Lock()

    def check_readings(self) -> None:
        """Refuse an engine step on a sensor whose kept readings are all one vector (a zero-filled file, a
        disconnected sensor): no fit or diagnosis can say anything true about them."""
        ctrl = self.ctrl
        kept = ctrl.kept
        for s, r in enumerate(ctrl.dataset.readings_nT):
            r = r[kept]
            if r.shape[0] and np.all(r == r[0]):
                raise MagcalError(
                    f"sensor {s + 1}: every kept reading is the same vector ({', '.join(f'{v:g}' for v in r[0])}) "
                    "nT, so the data hold no field measurement to fit or diagnose (a zero-filled file or a "
                    "disconnected sensor?); check the sensor's output"
                )

    @action
    def do_load_effects(self, event):
        """Load the effects file typed in the Model tab (runs its code: only when served to this machine, and only
        a file named on the command line or confirmed in the terminal, :class:`magcal_workbench.consent.EffectsFiles`)."""
        if not self._local():
            raise MagcalError(
                "loading an effects file runs its Python code on the server; it is allowed only when "
                "the workbench serves this machine (127.0.0.1). Start it with --effects-file instead"
            )
        path = self.values.check(self.panels.effects_path)
        gate = self.effects_gate  # only a file of the command line, or one confirmed in the terminal
        why = gate.refusal(path)
        if why is not None:
            raise MagcalError(why)
        ctrl = self.ctrl
        status = ctrl.report_progress  # the page's status line says while the terminal waits for the answer
        ctrl.run_job("load effects file", lambda: ctrl.load_effects_file(gate.permit(path, ctrl.say, status)))

    @action
    def do_load_session_effects(self, event):
        """Load the effects files the open session names (runs their code: the user asked; only when served to
        this machine, and each only if named on the command line or confirmed in the terminal)."""
        if not self._local():
            raise MagcalError(
                "loading an effects file runs its Python code on the server; it is allowed only when "
                "the workbench serves this machine (127.0.0.1). Start it with --effects-file instead"
            )
        ctrl, gate = self.ctrl, self.effects_gate
        refused = [gate.refusal(p) for p in ctrl.pending_effects_files()]
        if refused and all(refused):  # none may load: said at once
            raise MagcalError("; ".join(str(r) for r in refused))
        ctrl.run_job(
            "load the session's effects files",
            lambda: ctrl.load_session_effects_files(
                permit=lambda paths: gate.permit_all(paths, ctrl.say, ctrl.report_progress)
            ),
        )

    # --- the refit after a rejection ----------------------------------------------------------------------
    def forget_pending(self) -> None:
        """New data: a refit asked for on the old data is dropped."""
        self.refit_pending = False

    def refit_follows(self) -> bool:
        """Whether a change of the selection is followed by a refit (:meth:`maybe_refit`)."""
        return bool(self.panels.auto_refit.value and self.ctrl.calibration is not None)

    @contextmanager
    def changing_selection(self):
        """A change of the selection, then the refit that follows it (:meth:`maybe_refit`). The cockpit's
        figures wait for the refit's result instead of being drawn twice (:meth:`Panels.figures_held`)."""
        with self.panels.figures_held(self.refit_follows()):
            yield
        self.maybe_refit()

    def maybe_refit(self):
        """Refit after a change of the selection when Refit after each change is on and there is a fit; while a
        job runs, the refit follows it."""
        ctrl, worker = self.ctrl, self.worker
        if not self.refit_follows():
            return
        with self._pending_lock:
            busy = worker.busy or self.refit_pending
            if busy:
                self.refit_pending = True  # applied after the running job, with this change
        if busy:
            ctrl.say(f"{ctrl.message}; the refit follows when {safe_text(worker.current or 'the running step')} ends")
            return
        if not ctrl.submit_step("refit", ctrl.step_refine):
            with self._pending_lock:  # a job started in between: the refit follows it
                self.refit_pending = True
            if not worker.busy:  # ... unless it has already ended
                threading.Thread(target=self.run_pending_refit, daemon=True).start()

    def job_ended(self) -> None:
        """The worker has ended a job: start the refit asked for meanwhile (from another thread: the worker calls
        this before it is idle)."""
        if self.refit_pending:
            threading.Thread(target=self.run_pending_refit, name="workbench-pending-refit", daemon=True).start()

    def run_pending_refit(self) -> None:
        """The refit asked for while a job ran (a rejection during a fit), now that the job has ended."""
        self.worker.wait()
        with self._pending_lock:
            if not self.refit_pending:
                return
            self.refit_pending = False
            ctrl = self.ctrl
            if ctrl.calibration is None or not self.panels.auto_refit.value:
                return
            if not ctrl.submit_step("refit", ctrl.step_refine):
                self.refit_pending = True  # another job started first: its end starts the refit
