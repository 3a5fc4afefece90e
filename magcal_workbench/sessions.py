"""The session folder's use: opening data into a :class:`~magcal_workbench.controller.Controller` (a saved session
resumed, a damaged one moved aside, autosave wired), and the Files tab's Reopen, Delete and Start afresh.

The folder itself (ids, bounds, atomic writes) is :mod:`magcal_workbench.session`; the file format
:mod:`magcal_workbench.sessionfile`.
"""

from __future__ import annotations

import os
import sys

from magcal.core.errors import MagcalError

from .actions import action
from .controller import MESSAGE_LEN, Controller, unsaved_problem
from .dataio import load_dataset
from .markup import clean_text, hide_paths, safe_code, safe_text
from .parts import PagePart
from .sessionfile import SessionFileError
from .state import SessionState


class Sessions(PagePart):
    """Opens data as a session of the store (or unsaved without one) and acts on the saved sessions.

    Handed what it uses.

    Parameters
    ----------
    ctrl, panels : callable
        Getters: the open data's :class:`~magcal_workbench.controller.Controller` (made by this part) and the
        :class:`~magcal_workbench.panels.Panels` (made after it).
    store : magcal_workbench.session.SessionStore or None
        The sessions' folder, None without one (the data open unsaved).
    effects_files : list of str
        The command line's effects files, remembered in every session opened.
    worker : magcal_workbench.jobs.Worker
        The one worker, handed to each controller made.
    values : magcal_workbench.checks.PageValues
        What each input widget may send (the session chosen is checked before it is read).
    load : callable
        ``load(dataset, content, name, resume=..., lesson=...)``: replaces the data
        (:meth:`magcal_workbench.app.Workbench.load`).
    say_after_load : callable
        ``say_after_load(text)``: says the session reopened (:meth:`magcal_workbench.app.Workbench.say_after_load`).
    """

    def __init__(self, *, ctrl, panels, store, effects_files, worker, values, load, say_after_load) -> None:
        self._ctrl, self._panels = ctrl, panels
        self.store, self.effects_files, self.worker, self.values = store, effects_files, worker, values
        self.load, self.say_after_load = load, say_after_load

    def make_controller(self, dataset, content, name, resume, lesson) -> Controller:
        """A controller for ``dataset``: its saved session when ``resume`` and one exists, else a fresh state;
        every effects file of the command line remembered; autosaved once. The session's other effects files are
        not run: the message says so, and the Model tab offers to load them (the user's choice)."""
        store = self.store
        sid, state, notes, unsaved = None, None, [], None
        if store is not None and content is not None:
            try:
                sid = store.create(name, content)
            except (OSError, MagcalError) as exc:  # a full disk: the data open all the same, unsaved, and the page
                unsaved = exc  # says so until other data are opened (Controller.save_problem)
                print(f"magcal-workbench: the session of {name} cannot be saved: {exc}", file=sys.stderr)
        if sid is not None:
            notes += [
                f"the session folder is bounded to {store.max_bytes / 1e6:g} MB: deleted the oldest "
                f"session {old} ({size / 1e6:.1f} MB)"
                for old, size in store.pruned
            ]
            if resume and store.exists(sid):
                state, note = self.read_session(sid, dataset)
                if note:
                    notes.append(note)
                    sid = store.create(name, content)  # the data's copy went with the damaged folder
                if state is not None and state.notes:  # rows over the bounds dropped as it was read
                    for said in state.notes:
                        print(f"magcal-workbench: session {sid}: {clean_text(said, MESSAGE_LEN)}", file=sys.stderr)
                    notes += state.notes
                    state.notes = []
            if state is None:
                state = SessionState(dataset.n_samples, dataset.n_sensors, str(store.data_path(sid)), lesson)
        if state is None:
            state = SessionState(dataset.n_samples, dataset.n_sensors, dataset.source, lesson)
        for path in self.effects_files:
            if path not in state.effects_files:
                state.effects_files.append(path)
        ctrl = Controller(dataset, state, store, sid, worker=self.worker)
        if unsaved is not None:
            ctrl.save_problem = unsaved_problem(unsaved)
        pending = ctrl.pending_effects_files()
        if pending:  # never run when a session opens: a session someone sends you would run their code
            notes.append(
                f"this session names {len(pending)} effects file(s) ({', '.join(os.path.basename(p) for p in pending)}),"
                " not loaded: an effects file is Python code that runs with your rights. Load them (Model tab, Your "
                "own effects, Load the session's effects files) only if you trust them"
            )
        if lesson is not None:
            ctrl.state.lesson = lesson
        if notes:
            ctrl.message = "  \n".join(
                f"**Note:** {safe_text(n, MESSAGE_LEN)}" for n in notes + ([ctrl.message] if ctrl.message else [])
            )
        ctrl.autosave()
        return ctrl

    def read_session(self, sid, dataset):
        """The saved state of ``sid`` and ``None``, or ``None`` and a one-line note: a damaged session file is
        moved aside (``<sid>.damaged-<time>``) and the data start afresh."""
        store = self.store
        try:
            return store.load(sid, expect=(dataset.n_samples, dataset.n_sensors)), None
        except SessionFileError as exc:
            note = f"the saved session {sid} is damaged ({exc}); {self._set_aside(sid)}; starting afresh"
        except (MemoryError, RecursionError) as exc:  # beyond what this machine holds: set aside all the same
            why = type(exc).__name__
            note = f"the saved session {sid} could not be opened ({why}); {self._set_aside(sid)}; starting afresh"
        except OSError as exc:
            note = f"the saved session {sid} could not be read ({exc.strerror or exc}); starting afresh"
        print(f"magcal-workbench: {clean_text(note, MESSAGE_LEN)}", file=sys.stderr)
        return None, hide_paths(note)

    def _set_aside(self, sid) -> str:
        """Move a session that cannot be opened aside (:meth:`SessionStore.set_aside`); says where, or why not."""
        try:
            return f"moved aside to {self.store.set_aside(sid).name}"
        except OSError as err:
            return f"could not be moved aside ({err.strerror or err})"

    def session_ids(self) -> tuple:
        """The Saved session choices the server offers: the folder's sessions and ``-``."""
        return (tuple(s["id"] for s in self.store.list()) if self.store is not None else ()) + ("-",)

    # --- the Files tab's actions --------------------------------------------------------------------------
    def _chosen(self) -> str:
        sid = self.values.check(self.panels.session_choice)
        if self.store is None or sid in ("-", None):
            raise MagcalError("no saved session chosen")
        return sid

    @action
    def do_reopen(self, event):
        sid = self._chosen()
        path = self.store.data_path(sid)  # refuses a name outside the session folder

        def job():
            if not path.is_file():
                raise MagcalError(f"session {sid} has no data file ({path.name}); it cannot be reopened")
            try:
                lesson = self.store.load(sid).lesson
            except (SessionFileError, OSError):
                lesson = None  # opening it says what is wrong and moves it aside
            ds, _ = load_dataset(path, f"{sid}/{path.name}")  # messages name the session, not the server's path
            content = path.read_bytes()
            self.load(ds, content, sid.rsplit("-", 1)[0] + ".csv", resume=True, lesson=lesson)
            self.say_after_load(f"reopened session {safe_code(sid)}")

        self.ctrl.run_job("reopen session", job)

    @action
    def do_delete_session(self, event):
        """Delete the chosen saved session's folder (not the one open now)."""
        sid = self._chosen()
        ctrl = self.ctrl
        if sid == ctrl.session_id:
            raise MagcalError(f"session {sid} is the one open; open other data first, or use Start this data afresh")
        freed = self.store.size_bytes(sid)
        self.store.delete(sid)
        self.panels.refresh_sessions()
        ctrl.say(f"deleted session {safe_code(sid)} ({freed / 1e6:.1f} MB)")

    @action
    def do_fresh(self, event):
        ctrl = self.ctrl

        def job():
            content = None
            if self.store is not None and ctrl.session_id is not None:
                content = self.store.data_path(ctrl.session_id).read_bytes()
                self.store.delete(ctrl.session_id)
            name = (ctrl.session_id.rsplit("-", 1)[0] + ".csv") if ctrl.session_id else "data.csv"
            self.load(ctrl.dataset, content, name, resume=False, lesson=ctrl.state.lesson)
            self.ctrl.say("started afresh: every sample kept, base model, no fit")

        ctrl.run_job("start afresh", job)
