"""``magcal-workbench [FILE.csv] [--live SOURCE] [--host 127.0.0.1] [--port 8080] [--effects-file MY.py]``: the
browser workbench.

:class:`Workbench` wires the parts together: one :class:`viser.ViserServer` (every browser shares its scene and
GUI), the :class:`~magcal_workbench.controller.Controller` (engine actions and session state), the
:class:`~magcal_workbench.scene.SceneView` and the :class:`~magcal_workbench.panels.Panels`. With no file it opens the bundled
demo (``assets/demo.csv``). It binds to 127.0.0.1 unless another host is asked for, and then warns.

A user's own effects (:mod:`magcal.model.plugins`) join the catalogue at start -- installed packages' entry points and
every ``--effects-file`` -- or later from the Model tab; the session remembers the files and loads them again when
it reopens. A damaged session file is moved aside and the data open afresh.

Hostile pages and careless input (issue 14): only the app's own page may open its websocket
(:mod:`workbench.guard`); every value a browser sends is checked against what the server offers before it is read
or saved (:meth:`Workbench.check_value`); every callback, pointer events included, goes through
:meth:`Workbench.handle`; a job fits the mask it started with and a rejection made meanwhile is refitted after it;
uploads are bounded (``--max-upload-mb``), the session folder too (``--max-sessions-mb``), and a large file is
drawn decimated (``--max-points``) and fitted whole.
"""

from __future__ import annotations

import argparse
import os
import sys
import threading
import time
import traceback

import numpy as np

from magcal.core.errors import MagcalError

from . import scene as scn
from .controller import MESSAGE_LEN, Controller, error_markdown, load_dataset, load_session_effects, read_bytes_dataset
from .guard import LOOPBACK_NAMES, guarded_viser_server, is_loopback, page_url
from .jobs import Worker
from .lessons import DEMO, get_lesson
from .markup import clean_text, error_text, hide_paths, safe_code, safe_text
from .session import MAX_STORE_BYTES, SessionStore
from .sessionfile import SessionFileError
from .state import SessionState

LOOPBACK = LOOPBACK_NAMES
#: Default upload limit, MB (``--max-upload-mb``).
DEFAULT_MAX_UPLOAD_MB = 100.0
#: Longest text a text box may hold, characters (a path).
MAX_TEXT_CHARS = 4096
#: Longest uploaded file name kept, characters (the rest is cut; a file system allows 255 bytes).
MAX_NAME_CHARS = 120


def clean_upload_name(name) -> str:
    """An uploaded file's name made safe to show and to key a session: its last path part, control characters
    removed, cut to :data:`MAX_NAME_CHARS`; ``upload.csv`` when nothing usable is left (``..``, ``.``, empty)."""
    text = clean_text(name if isinstance(name, str) else "", 4 * MAX_NAME_CHARS)
    base = text.replace("\\", "/").rsplit("/", 1)[-1].strip()
    if base.strip(".") == "":
        return "upload.csv"
    if len(base) > MAX_NAME_CHARS:
        stem, dot, ext = base.rpartition(".")
        ext = ext if dot and len(ext) <= 8 else ""
        base = base[: MAX_NAME_CHARS - len(ext) - 1].rstrip() + ("." + ext if ext else "")
    return base


class Workbench:
    """The running workbench.

    Parameters
    ----------
    dataset : magcal.Dataset
        Data to open.
    host, port : str, int
        Where to serve (port 0 picks a free port; read it back with :attr:`port`).
    store : SessionStore or None
        Session folder for autosave; None turns autosave off.
    content : bytes, optional
        The data file's bytes (to key and copy the session); without it the session is not saved.
    name : str
        File name used for the session id.
    resume : bool
        Reopen the saved session of the same data if there is one.
    effects_files : sequence of str, optional
        The user's effect files already loaded (``--effects-file``); every session opened remembers them.
    max_upload_mb : float
        Largest file the page may upload, MB (10^6 bytes); a larger one is refused with a message.
    max_points : int
        Most points drawn per cloud (one sensor's raw or corrected readings); larger data are shown decimated
        (:func:`magcal_workbench.scene.level_of_detail`), every sample is still fitted and selectable.
    """

    def __init__(
        self,
        dataset,
        host: str = "127.0.0.1",
        port: int = 8080,
        store: SessionStore | None = None,
        content: bytes | None = None,
        name: str = "data.csv",
        resume: bool = True,
        lesson: str | None = None,
        verbose: bool = False,
        effects_files=(),
        max_upload_mb: float = DEFAULT_MAX_UPLOAD_MB,
        max_points: int = scn.MAX_POINTS,
    ):
        self.max_upload_bytes = int(max_upload_mb * 1e6)
        self._refit_pending = False
        self._pending_lock = threading.Lock()
        self.server = guarded_viser_server(host, port, verbose)  # refuses other pages' websockets
        #: Whether the page may load effect files (it runs their code): only when served to this machine.
        self.local = is_loopback(host)
        self.effects_files = [os.path.abspath(p) for p in effects_files]
        self.store = store
        self.worker = Worker()
        self._last_progress = 0.0
        self.last_download: tuple[str, bytes] | None = None
        self.evidence_plot = None
        #: The live session (:class:`magcal_workbench.live.LiveView`) while one is open or after it stopped, else None.
        self.live = None
        from .timewindow import TimeWindow

        #: The time scrubber's window (View tab): the samples drawn and the evidence plots' shaded band.
        self.window = TimeWindow(self._window_moved)
        from .maps import SphereMaps

        #: The residual-map surfaces (View tab's Sphere surface).
        self.maps = SphereMaps(self)
        self._last_evidence_t = 0.0
        self._scene_lock = threading.RLock()
        self.ctrl = self._make_controller(dataset, content, name, resume, lesson)
        self.scene_view = scn.SceneView(self.server, max_points=max_points)
        from .panels import Panels

        self.panels = Panels(self)
        self._ranges = self._offered_ranges()
        self._watch_upload_sizes()
        self.worker.on_busy_change(self._busy_changed)
        # pointer events go through the error handler like every widget's callback
        self.server.scene.on_click()(lambda event: self.handle(self._on_click, event))
        self.server.scene.on_rect_select(modifier="shift")(lambda event: self.handle(self._on_rect_select, event))
        self.server.on_client_connect(lambda client: self.handle(lambda _: self._on_connect(client), None))
        self.server.scene.set_up_direction("+z")
        self._attach(self.ctrl)
        self.redraw()

    # ------------------------------------------------------------------------------------------------------
    @property
    def port(self) -> int:
        return self.server.get_port()

    def stop(self) -> None:
        self.worker.wait(30)
        self.server.stop()

    def _make_controller(self, dataset, content, name, resume, lesson) -> Controller:
        sid, state, notes = None, None, []
        if self.store is not None and content is not None:
            sid = self.store.create(name, content)
            notes += [
                f"the session folder is bounded to {self.store.max_bytes / 1e6:g} MB: deleted the oldest "
                f"session {old} ({size / 1e6:.1f} MB)"
                for old, size in self.store.pruned
            ]
            if resume and self.store.exists(sid):
                state, note = self._read_session(sid, dataset)
                if note:
                    notes.append(note)
                    sid = self.store.create(name, content)  # the data's copy went with the damaged folder
            if state is None:
                state = SessionState(dataset.n_samples, dataset.n_sensors, str(self.store.data_path(sid)), lesson)
        if state is None:
            state = SessionState(dataset.n_samples, dataset.n_sensors, dataset.source, lesson)
        for path in self.effects_files:
            if path not in state.effects_files:
                state.effects_files.append(path)
        _, problems = load_session_effects(state.effects_files)
        notes += [f"the effects file could not be loaded again: {p}" for p in problems]
        ctrl = Controller(dataset, state, self.store, sid, worker=self.worker)
        if lesson is not None:
            ctrl.state.lesson = lesson
        if notes:
            ctrl.message = "  \n".join(
                f"**Note:** {safe_text(n, MESSAGE_LEN)}" for n in notes + ([ctrl.message] if ctrl.message else [])
            )
        ctrl.autosave()
        return ctrl

    def _read_session(self, sid, dataset):
        """The saved state of ``sid`` and ``None``, or ``None`` and a one-line note: a damaged session file is
        moved aside (``<sid>.damaged-<time>``) and the data start afresh."""
        try:
            return self.store.load(sid, expect=(dataset.n_samples, dataset.n_sensors)), None
        except SessionFileError as exc:
            try:
                moved = f"moved aside to {self.store.set_aside(sid).name}"
            except OSError as err:
                moved = f"could not be moved aside ({err.strerror or err})"
            note = f"the saved session {sid} is damaged ({exc}); {moved}; starting afresh"
        except OSError as exc:
            note = f"the saved session {sid} could not be read ({exc.strerror or exc}); starting afresh"
        print(f"magcal-workbench: {clean_text(note, MESSAGE_LEN)}", file=sys.stderr)
        return None, hide_paths(note)

    def _say_after_load(self, text: str) -> None:
        """Say ``text`` (markdown, escaped) and keep what opening the session had to say."""
        prior = self.ctrl.message
        self.ctrl.say(text + (f"  \n{prior}" if prior else ""))

    def _attach(self, ctrl: Controller) -> None:
        ctrl.on_change(lambda kind, c=ctrl: self._changed(c, kind))

    def load(self, dataset, content: bytes | None, name: str, resume: bool = True, lesson: str | None = None):
        """Replace the data (upload, lesson, reopened session); the scene and panels follow."""
        self._refit_pending = False  # a refit asked for on the old data
        self.window.pause()  # the window's percentages carry over to the new data; playback does not
        self.ctrl = self._make_controller(dataset, content, name, resume, lesson)
        self._attach(self.ctrl)
        self.scene_view.clear()
        self.redraw()
        self.maps.fit_changed(self.ctrl)
        self.refresh_maps()
        self.reset_cameras()

    def redraw(self) -> None:
        self.update_scene()
        self.panels.refresh(("all", "data"))

    # ------------------------------------------------------------------------------------------------------
    # events from the controller
    # ------------------------------------------------------------------------------------------------------
    def _changed(self, ctrl: Controller, kind: str) -> None:
        if ctrl is not self.ctrl:
            return  # an old session still finishing
        if kind == "progress":
            now = time.perf_counter()
            if ctrl.progress is not None and (ctrl.progress[1] is not None or now - self._last_progress > 0.1):
                self._last_progress = now  # a search reports thousands of iterations: show ten a second
                self.panels.set_progress(*ctrl.progress)
            return
        if kind in ("result", "view", "data"):
            self.update_scene()
        elif kind == "selection":
            self.scene_view.recolor(self.scene_model())
            if self.ctrl.inspected is not None:
                self.scene_view.mark_inspected(self.ctrl.inspected)
        elif kind == "inspect":
            self.scene_view.mark_inspected(ctrl.inspected)
        if kind in ("result", "data"):
            self.maps.fit_changed(ctrl)  # before the panels: the evidence plots show the RMS before the last fit
        if kind in ("result", "data", "diagnosis") and self.maps.choice != "none":
            self.refresh_maps()
        self.panels.refresh((kind,))

    def _busy_changed(self, busy: bool, name) -> None:
        self.panels.set_busy(busy, name)
        if not busy and self._refit_pending:
            # the worker calls this before it is idle: start the refit from another thread once it is
            threading.Thread(target=self._run_pending_refit, name="workbench-pending-refit", daemon=True).start()

    def _run_pending_refit(self) -> None:
        """The refit asked for while a job ran (a rejection during a fit), now that the job has ended."""
        self.worker.wait()
        with self._pending_lock:
            if not self._refit_pending:
                return
            self._refit_pending = False
            ctrl = self.ctrl
            if ctrl.calibration is None or not self.panels.auto_refit.value:
                return
            if not ctrl.submit_job("refit", ctrl.step_refine):
                self._refit_pending = True  # another job started first: its end starts the refit

    # ------------------------------------------------------------------------------------------------------
    # scene
    # ------------------------------------------------------------------------------------------------------
    def scene_model(self) -> scn.SceneModel:
        live = self.live
        if live is not None and live.active:  # a live session owns the scene until it stops
            model = live.scene_model(self.panels.view_options())
            if model is not None:
                return model
        ctrl = self.ctrl
        ds = ctrl.dataset
        shown = range(ds.n_sensors) if ctrl.state.sensor is None else [ctrl.state.sensor]
        cal = ctrl.calibration
        views = []
        for s in shown:
            views.append(
                scn.SensorView(
                    sensor=s,
                    raw_nT=ds.readings_nT[s],
                    corrected_nT=None if ctrl.corrected_nT is None else ctrl.corrected_nT[s],
                    residual_nT=(ctrl.raw_residual_nT()[s] if ctrl.residual_nT is None else ctrl.residual_nT[s]),
                    cinv=None if cal is None else cal.sensors[s].cinv,
                    bias_nT=None if cal is None else cal.sensors[s].bias_nT,
                    R=None if cal is None else cal.sensors[s].R,
                )
            )
        from .timewindow import sample_times

        times = sample_times(ds)
        return scn.SceneModel(
            sensors=views,
            n_sensors=ds.n_sensors,
            field_nT=ctrl.field_nT,
            kept=ctrl.state.kept,  # live, even in a job
            floor_nT=ctrl.floor_nT(),
            baseline_m=ds.baseline_m,
            all_calibrations=[] if cal is None else [(c.cinv, c.R) for c in cal.sensors],
            inspected=ctrl.inspected,
            window=self.window.mask(times),
            current=self.window.current(times),
            **self.panels.view_options(),
        )

    def update_scene(self) -> None:
        with self._scene_lock:
            self.scene_view.update(self.scene_model())

    def legend_html(self) -> str:
        live = self.live
        fitted = (live.fit is not None) if live is not None and live.active else self.ctrl.calibration is not None
        title = "total-field residual" if fitted else "raw |y| - F"
        html = scn.legend_html(self.scene_view.last_limit_nT, title)
        if self.maps.patterns and not (live is not None and live.active):
            html += scn.legend_html(
                self.maps.limit_nT, f"sphere surface: {self.maps.choice}; grey: not visited", swatches=False
            )
        return html

    def draw_evidence(self) -> None:
        from .plots import evidence_figure

        fig = evidence_figure(
            self.ctrl, window_s=self._evidence_band(), before_rms_nT=self.maps.before_rms_nT(self.ctrl)
        )
        holder = self.panels.evidence_holder
        if fig is None:
            if self.evidence_plot is not None:
                self.evidence_plot.visible = False
            return
        if self.panels.evidence_overlay.visible:
            self.show_full_evidence(True)
        if self.evidence_plot is None:
            with holder:
                # viser's client draws plotly at height = width * aspect (the docstring says width/height)
                self.evidence_plot = self.server.gui.add_plotly(fig, aspect=3.0)
        else:
            self.evidence_plot.figure = fig
            self.evidence_plot.visible = True

    # evidence at full size
    def _evidence_band(self):
        from .timewindow import sample_times

        return self.window.bounds_s(sample_times(self.ctrl.dataset)) if self.window.enabled else None

    def _evidence_title(self) -> str:
        ctrl = self.ctrl
        model = ", ".join(ctrl.state.effects) or "base terms only"
        return f"{ctrl.dataset.source and os.path.basename(str(ctrl.dataset.source))}: model {model}"

    def show_full_evidence(self, on: bool) -> None:
        """Show (or hide) the evidence plots over the canvas, left of the panel: a PNG drawn by the engine's
        numbers (:func:`magcal_workbench.plots.evidence_image`), the same data as the Model tab's plots."""
        import base64

        from .plots import evidence_image

        overlay = self.panels.evidence_overlay
        if not on:
            overlay.visible = False
            self.panels.btn_full_evidence.label = "Full-size evidence"
            return
        png = evidence_image(
            self.ctrl, "png", self._evidence_band(), self._evidence_title(), self.maps.before_rms_nT(self.ctrl)
        )
        if png is None:
            raise MagcalError("fit first: the evidence plots show the residuals of a fit")
        data = base64.b64encode(png).decode("ascii")
        overlay.content = (
            '<div style="position:fixed;left:0;top:0;width:calc(100vw - 27em);height:100vh;'
            'background:white;z-index:50;overflow:auto;padding:0.5em;box-sizing:border-box">'
            f'<img alt="evidence plots" src="data:image/png;base64,{data}" '
            'style="width:100%;height:auto;display:block"></div>'
        )
        overlay.visible = True
        self.panels.btn_full_evidence.label = "Back to the scene"

    def do_full_evidence(self, event):
        self.show_full_evidence(not self.panels.evidence_overlay.visible)

    def _download_evidence(self, event, fmt: str):
        from .plots import evidence_image

        data = evidence_image(
            self.ctrl, fmt, self._evidence_band(), self._evidence_title(), self.maps.before_rms_nT(self.ctrl)
        )
        if data is None:
            raise MagcalError("fit first: the evidence plots show the residuals of a fit")
        self._download(event, f"evidence.{fmt}", data)

    def do_download_evidence_png(self, event):
        self._download_evidence(event, "png")

    def do_download_evidence_svg(self, event):
        self._download_evidence(event, "svg")

    def reset_cameras(self) -> None:
        for client in self.server.get_clients().values():
            self._place_camera(client)

    def _place_camera(self, client) -> None:
        n_groups = 1 if self.ctrl.state.sensor is not None else self.ctrl.dataset.n_sensors
        try:
            fov, aspect = float(client.camera.fov), float(client.camera.aspect)
        except (AssertionError, ZeroDivisionError):  # the browser has not reported its camera yet
            fov, aspect = np.radians(75.0), 1.6
        position, look_at = scn.camera_pose(n_groups, fov, aspect)
        with client.atomic():
            client.camera.up_direction = (0.0, 0.0, 1.0)
            client.camera.position = tuple(position)
            client.camera.look_at = tuple(look_at)

    def _on_connect(self, client) -> None:
        self._place_camera(client)

    # ------------------------------------------------------------------------------------------------------
    # pointer events
    # ------------------------------------------------------------------------------------------------------
    def _on_click(self, event) -> None:
        if self.live is not None and self.live.active:
            return  # the points of a stream are not the opened data's samples
        d = self.scene_view.displayed
        if d.positions.shape[0] == 0:
            return
        i, dist = scn.nearest_to_ray(
            d.positions, event.ray_origin, event.ray_direction, max_distance=4 * self.scene_view.point_size
        )
        self.ctrl.inspect(None if i is None else int(d.samples[i]))

    def _on_rect_select(self, event) -> None:
        cam = event.client.camera
        self.select_in_rect(cam.wxyz, cam.position, cam.fov, cam.aspect, event.screen_min, event.screen_max)

    def select_in_rect(self, wxyz, position, fov, aspect, screen_min, screen_max) -> int:
        """Reject (or restore, by the panel's mode) the samples whose shown points fall in a screen box."""
        if self.live is not None and self.live.active:
            raise MagcalError("stop the live session first: rejecting works on the recording once it is opened")
        samples = self.scene_view.samples_in_rect(wxyz, position, fov, aspect, screen_min, screen_max)
        if samples.size == 0:
            self.ctrl.say("the box holds no point")
            return 0
        n = self.ctrl.select(samples, self.check_value(self.panels.box_mode))
        self._maybe_refit()
        return n

    # ------------------------------------------------------------------------------------------------------
    # GUI callbacks (the panels wire them where the widgets are made; every one goes through handle)
    # ------------------------------------------------------------------------------------------------------
    def handle(self, func, event, *args):
        """Run a callback; an engine error becomes the message (and a toast in the browser that caused it).

        The widget that changed (``event.target``) is checked first (:meth:`check_value`): a value the page
        could not have offered is refused before anything reads or saves it."""
        try:
            target = getattr(event, "target", None)
            if target is not None:
                self.check_value(target)
            func(event, *args)
        except MagcalError as exc:
            self.ctrl.say(error_markdown(exc))
            client = getattr(event, "client", None)
            if client is not None:  # a toast shows plain text: only cut to length
                client.add_notification("magcal", clean_text(error_text(exc), 300), color="red", auto_close_seconds=8.0)
        except Exception as exc:  # never let a callback die silently (error_markdown logs the traceback)
            self.ctrl.say(error_markdown(exc))

    def _job(self, name, func) -> bool:
        return self.ctrl.run_job(name, func)

    # ------------------------------------------------------------------------------------------------------
    # values from the page: a browser may send any value for any widget (viser checks none); they are checked
    # against what the server offers -- the session folder, the lessons, the diagnosis, the data -- never
    # against the widget's own options or range, which a client may change too
    # ------------------------------------------------------------------------------------------------------
    def _offered_ranges(self) -> dict:
        """``id(widget) -> (min, max)`` of every slider and number as the panels made them."""
        import viser

        return {
            id(h): (h.min, h.max)
            for h in vars(self.panels).values()
            if isinstance(h, (viser.GuiSliderHandle, viser.GuiNumberHandle))
        }

    def allowed_choices(self, handle) -> tuple:
        """The values a dropdown may hold: what the server offers for it now (its first one is the default)."""
        from .controller import candidate_label
        from .lessons import list_lessons
        from .panels import Panels
        from .state import METHODS

        p, ctrl = self.panels, self.ctrl
        if handle is p.session_choice:
            ids = tuple(s["id"] for s in self.store.list()) if self.store is not None else ()
            return ids + ("-",)
        if handle is p.lesson_choice:
            return tuple(l.slug for l in list_lessons()) or ("-",)
        if handle is p.candidate_choice:
            cands = ctrl.diagnosis.candidates if ctrl.diagnosis is not None else []
            return tuple(dict.fromkeys(candidate_label(c) for c in cands)) + ("-",)
        if handle is p.sensor_choice:
            return Panels._sensor_options(ctrl.dataset.n_sensors)
        if handle is p.method:
            return tuple(METHODS)
        if handle is p.box_mode:
            return ("reject", "restore")
        if handle is p.surface_choice:
            from .maps import SURFACE_CHOICES

            return SURFACE_CHOICES
        if handle is p.upload_units:
            from .panels import UPLOAD_UNITS

            return UPLOAD_UNITS
        return tuple(handle.options)

    def check_value(self, handle):
        """The value of ``handle`` if the page could have sent it, else a :class:`MagcalError` saying so (and the
        widget is put back to the state's value or the first choice, so every browser shows a valid one).

        Checked: a dropdown's value is one of :meth:`allowed_choices`; a slider's or number's is a finite number
        within the range it was made with; a text is at most :data:`MAX_TEXT_CHARS` characters."""
        import math

        import viser

        value = handle.value
        label = clean_text(getattr(handle, "label", "value"), 60)
        if isinstance(handle, viser.GuiDropdownHandle):
            allowed = self.allowed_choices(handle)
            if value not in allowed:
                self._put_back(handle, allowed[0])
                raise MagcalError(
                    f"{label}: {clean_text(repr(value), 60)} is not one of the choices offered; "
                    "refused (nothing was read or saved)"
                )
        elif isinstance(handle, (viser.GuiSliderHandle, viser.GuiNumberHandle)):
            lo, hi = self._ranges.get(id(handle), (None, None))
            ok = (
                isinstance(value, (int, float))
                and not isinstance(value, bool)
                and math.isfinite(value)
                and (lo is None or value >= lo)
                and (hi is None or value <= hi)
            )
            if not ok:
                good = lo if lo is not None else 0.0
                if isinstance(value, (int, float)) and math.isfinite(value):
                    good = min(max(value, lo if lo is not None else value), hi if hi is not None else value)
                self._put_back(handle, good)
                span = f"{'-inf' if lo is None else f'{lo:g}'} ... {'inf' if hi is None else f'{hi:g}'}"
                raise MagcalError(f"{label}: {clean_text(repr(value), 40)} is outside {span}; refused")
        elif isinstance(handle, viser.GuiTextHandle):
            if not isinstance(value, str) or len(value) > MAX_TEXT_CHARS:
                self._put_back(handle, "")
                raise MagcalError(f"{label}: a text of at most {MAX_TEXT_CHARS} characters; refused")
        return value

    def _put_back(self, handle, default) -> None:
        for bound, shown in getattr(self.panels, "_bindings", ()):
            if bound is handle:
                default = shown()
                break
        try:
            handle.value = default
        except Exception:  # a widget that refuses even that: leave it, the value was refused anyway
            traceback.print_exc()

    # view
    def set_sensor(self, choice: str) -> None:
        """Show one sensor (``"sensor 2"``) or all of them (the panels' sensor choice)."""
        from .panels import ALL_SENSORS

        if choice not in self.allowed_choices(self.panels.sensor_choice):
            raise MagcalError(f"no sensor choice {clean_text(repr(choice), 40)}; refused")
        self.ctrl.configure(sensor=None if choice == ALL_SENSORS else int(choice.split()[-1]) - 1)
        self.update_scene()
        self.maps.draw()
        self.reset_cameras()

    def view_changed(self, event):
        self.update_scene()
        self.panels.legend.content = self.legend_html()

    # residual maps
    def refresh_maps(self) -> None:
        """Recompute and redraw the sphere surfaces for the current choice; an engine refusal becomes the note."""
        try:
            self.maps.refresh()
        except MagcalError as exc:
            self.maps.patterns, self.maps.note = [], str(exc)
            self.maps.clear()
        self.panels.maps_info.content = safe_text(self.maps.describe(), 600)
        self.panels.legend.content = self.legend_html()

    def surface_changed(self, event):
        self.maps.choice = self.check_value(self.panels.surface_choice)
        self.refresh_maps()

    # the time scrubber
    def window_changed(self, event):
        """A Time window widget moved: take its values (checked) into the window, which redraws."""
        p = self.panels
        self.window.set(
            enabled=bool(self.check_value(p.window_on)),
            start_pct=float(self.check_value(p.window_start)),
            width_pct=float(self.check_value(p.window_width)),
            speed=float(self.check_value(p.play_speed)),
        )

    def _window_moved(self) -> None:
        from .timewindow import sample_times

        self.update_scene()
        times = sample_times(self.ctrl.dataset)
        self.panels.window_info.content = safe_text(self.window.describe(times))
        now = time.monotonic()
        if not self.window.playing or now - self._last_evidence_t > 1.0:  # the plots' band: at most once a second
            self._last_evidence_t = now
            self.draw_evidence()

    def do_play(self, event):
        """Replay the recording: the window's start advances at the Play speed until the end or Pause."""
        from .timewindow import sample_times

        times = sample_times(self.ctrl.dataset)
        if not self.panels.window_on.value:
            self.panels.window_on.value = True  # its callback turns the window on
        self.window.play(
            float(np.nanmax(times) - np.nanmin(times)),
            advance=lambda pct: setattr(self.panels.window_start, "value", round(pct, 1)),
        )
        self.panels.window_info.content = safe_text(self.window.describe(times))

    def do_pause_play(self, event):

        self.window.pause()
        self._window_moved()

    def do_show_all(self, event):
        self.window.pause()
        self.panels.window_on.value = False  # its callback shows every sample

    # engine steps
    def _check_readings(self) -> None:
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

    def do_ellipsoid(self, event):
        self._check_readings()
        self._job("fit ellipsoid", self.ctrl.step_ellipsoid)

    def do_align(self, event):
        self._check_readings()
        self._job("align sensors", self.ctrl.step_align)

    def do_refine(self, event):
        self._check_readings()
        self._job("refine", self.ctrl.step_refine)

    def do_calibrate(self, event):
        self._check_readings()
        self._job(f"calibrate ({self.ctrl.state.method})", self.ctrl.step_calibrate)

    def do_diagnose(self, event):
        self._check_readings()
        self._job("diagnose", self.ctrl.step_diagnose)

    def do_add(self, event):
        self._check_readings()
        choice = self.check_value(self.panels.candidate_choice)
        label = None if choice == "-" else choice
        self._job("add effect", lambda: self.ctrl.step_add(label))

    # outliers
    def do_threshold(self, event):
        self.ctrl.reject_threshold(float(self.check_value(self.panels.k_sigma)))
        self._maybe_refit()

    def do_undo(self, event):
        self.ctrl.undo()
        self._maybe_refit()

    def do_redo(self, event):
        self.ctrl.redo()
        self._maybe_refit()

    def do_reset(self, event):
        self.ctrl.reset_selection()
        self._maybe_refit()

    def _maybe_refit(self):
        if self.panels.auto_refit.value and self.ctrl.calibration is not None:
            with self._pending_lock:
                busy = self.ctrl.worker.busy or self._refit_pending
                if busy:
                    self._refit_pending = True  # applied after the running job, with this change
            if busy:
                self.ctrl.say(
                    f"{self.ctrl.message}; the refit follows when "
                    f"{safe_text(self.ctrl.worker.current or 'the running step')} ends"
                )
                return
            if not self.ctrl.submit_job("refit", self.ctrl.step_refine):
                with self._pending_lock:  # a job started in between: the refit follows it
                    self._refit_pending = True
                if not self.worker.busy:  # ... unless it has already ended
                    threading.Thread(target=self._run_pending_refit, daemon=True).start()

    # files
    def _download(self, event, filename: str, content: bytes):
        self.last_download = (filename, content)
        client = getattr(event, "client", None)
        if client is not None:
            client.send_file_download(filename, content)

    def do_download_calibration(self, event):
        self._download(event, "calibration.json", self.ctrl.calibration_json())

    def do_download_corrected(self, event):
        self._download(event, "corrected.csv", self.ctrl.corrected_csv())

    def _watch_upload_sizes(self) -> None:
        """Refuse an upload over the limit when it starts (the browser declares its size), before its parts
        are buffered in memory. viser keeps an upload's parts in ``gui._current_file_upload_states`` (no public
        hook): dropping the entry makes viser ignore the parts that follow. :meth:`do_upload` checks the size
        again in any case."""
        from viser import _messages

        gui = self.server.gui
        if not hasattr(gui, "_current_file_upload_states"):
            return  # another viser: the check after the upload still refuses it

        def started(client_id, message) -> None:
            if message.source_component_uuid != self.panels.upload._impl.uuid:
                return
            if message.size_bytes <= self.max_upload_bytes:
                return
            gui._current_file_upload_states.pop(message.transfer_uuid, None)
            text = (
                f"{clean_upload_name(message.filename)}: {message.size_bytes / 1e6:.1f} MB is more than the "
                f"upload limit of {self.max_upload_bytes / 1e6:g} MB; refused"
            )

            def tell():  # off viser's event loop, like every callback
                self.ctrl.say(f"**Error:** {safe_text(text)}")
                client = self.server.get_clients().get(client_id)
                if client is not None:
                    client.add_notification("magcal", text, color="red", auto_close_seconds=8.0)

            threading.Thread(target=tell, name="workbench-upload-refused", daemon=True).start()

        self.server._websock_server.register_handler(_messages.FileTransferStartUpload, started)
        self._upload_started = started

    def do_upload(self, event):
        up = self.panels.upload.value
        name, content = clean_upload_name(up.name), up.content
        if not content:
            raise MagcalError(f"{name}: the file is empty")
        if len(content) > self.max_upload_bytes:
            raise MagcalError(
                f"{name}: {len(content) / 1e6:.1f} MB is more than the upload limit of "
                f"{self.max_upload_bytes / 1e6:g} MB; open it from the command line "
                "(magcal-workbench FILE.csv) or start the workbench with a larger --max-upload-mb"
            )
        self._last_upload = (name, content)
        self._open_upload(name, content)

    def do_reread(self, event):
        """Read the last upload again with the Files tab's Columns, Units and LSB (no new upload needed)."""
        if getattr(self, "_last_upload", None) is None:
            raise MagcalError("upload a file first (Open a file), then set Columns or Units and re-read it")
        self._open_upload(*self._last_upload)

    def read_options(self) -> dict:
        """The Files tab's reading options, checked (``columns``, ``units``, ``lsb_nT`` for the engine's reader)."""
        from .panels import UPLOAD_UNITS

        p = self.panels
        columns = self.check_value(p.upload_columns).strip() or None
        units = self.check_value(p.upload_units)
        lsb = float(self.check_value(p.upload_lsb))
        return {
            "columns": columns,
            "units": None if units == UPLOAD_UNITS[0] else units,
            "lsb_nT": lsb if lsb > 0 else None,
        }

    def _open_upload(self, name: str, content: bytes) -> None:
        from magcal.data.logs import is_log

        from .controller import canonical_csv, page_words

        options = self.read_options()
        mapped = is_log(name) or any(v is not None for v in options.values())

        def job():
            header = content[:4096].decode("utf-8", "replace").splitlines()
            found = next((line for line in header if line.strip() and not line.startswith("#")), "")
            self.panels.upload_info.content = (
                "" if is_log(name) else f"Columns in {safe_code(name)}: {safe_text(found, 400)}"
            )
            try:
                ds, notes = read_bytes_dataset(name, content, **options)
            except MagcalError as exc:
                raise MagcalError(page_words(str(exc))) from None
            # a session keeps data read through a mapping, units or a log reader as magcal's own CSV
            self.load(
                ds, canonical_csv(ds) if mapped else content, name if not mapped else os.path.splitext(name)[0] + ".csv"
            )
            self._say_after_load(
                f"opened {safe_code(name)}: {safe_text(ds.describe(), MESSAGE_LEN)}"
                + "".join(f"  \n- {safe_text(page_words(n), MESSAGE_LEN)}" for n in notes)
            )

        self._job("open file", job)

    def do_reopen(self, event):
        sid = self.check_value(self.panels.session_choice)
        if self.store is None or sid in ("-", None):
            raise MagcalError("no saved session chosen")

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
            self._say_after_load(f"reopened session {safe_code(sid)}")

        self._job("reopen session", job)

    def do_delete_session(self, event):
        """Delete the chosen saved session's folder (not the one open now)."""
        sid = self.check_value(self.panels.session_choice)
        if self.store is None or sid in ("-", None):
            raise MagcalError("no saved session chosen")
        if sid == self.ctrl.session_id:
            raise MagcalError(f"session {sid} is the one open; open other data first, or use Start this data afresh")
        freed = self.store.size_bytes(sid)
        self.store.delete(sid)
        self.panels.refresh_sessions()
        self.ctrl.say(f"deleted session {safe_code(sid)} ({freed / 1e6:.1f} MB)")

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

        self._job("start afresh", job)

    # live
    def start_live(self, url: str, path=None):
        """Open a live source (:mod:`workbench.live`); its samples are recorded to ``path`` (default a new file in
        the session folder's ``recordings``, or the current folder without sessions)."""
        from .live import LiveView, default_recording_path, recording_folder

        if self.live is not None and self.live.active:
            raise MagcalError("a live session is running; stop it first")
        path = default_recording_path(recording_folder(self.store)) if path is None else path
        self.live = LiveView(self, url, path)
        self.scene_view.clear()
        self.reset_cameras()
        self.panels.refresh_live()
        return self.live

    def do_live_start(self, event):
        from .live import check_page_source

        url = check_page_source(self.check_value(self.panels.live_url), self.local)
        live = self.start_live(url)
        self.ctrl.say(f"live from {safe_code(url)}: recording to {safe_code(live.path.name)}")

    def do_live_pause(self, event):
        if self.live is not None and self.live.active:
            self.live.pause()
        self.panels.refresh_live()

    def do_live_resume(self, event):
        if self.live is not None and self.live.active:
            self.live.resume()
        self.panels.refresh_live()

    def do_live_stop(self, event):
        """Stop the live session and open its recording like any file (Calibrate and Model work on it)."""
        live = self.live
        if live is None or not live.active:
            raise MagcalError("no live session is running")
        path = live.stop()
        self.panels.refresh_live()

        def job():
            ds, notes = load_dataset(path, path.name)
            self.load(ds, path.read_bytes(), path.name, resume=False)
            self._say_after_load(
                f"opened the recording {safe_code(path.name)}: "
                f"{safe_text(ds.describe(), MESSAGE_LEN)}"
                + "".join(f"  \n- {safe_text(n, MESSAGE_LEN)}" for n in notes)
            )

        self._job("open the recording", job)

    # lessons
    def do_open_lesson(self, event):
        slug = self.check_value(self.panels.lesson_choice)
        lesson = _get_lesson(slug)

        def job():
            ds, _ = load_dataset(lesson.data_path, f"lesson {slug}")
            content = lesson.data_path.read_bytes()
            self.load(ds, content, f"lesson-{slug}.csv", resume=True, lesson=slug)
            self.panels.lesson_guide.content = f"### {lesson.title}\n\n{lesson.guide()}"
            self.panels.lesson_feedback.content = lesson.answer_markdown() if self.ctrl.state.answer_revealed else ""
            self._say_after_load(f"lesson **{lesson.title}** opened")

        self._job("open lesson", job)

    def _lesson(self):
        if not self.ctrl.state.lesson:
            raise MagcalError("open a lesson first (Lessons tab)")
        return _get_lesson(self.ctrl.state.lesson)

    def do_check_lesson(self, event):
        result = self._lesson().check(self.ctrl.state.effects)
        self.panels.lesson_feedback.content = result["message"]
        self.ctrl.say(result["message"])

    def do_show_answer(self, event):
        lesson = self._lesson()
        self.ctrl.state.answer_revealed = True
        self.ctrl.state.touch()
        self.ctrl.autosave()
        self.panels.lesson_feedback.content = lesson.answer_markdown()

    # the user's effects
    def do_load_effects(self, event):
        """Load the effects file typed in the Model tab (runs its code: only when served to this machine)."""
        if not self.local:
            raise MagcalError(
                "loading an effects file runs its Python code on the server; it is allowed only when "
                "the workbench serves this machine (127.0.0.1). Start it with --effects-file instead"
            )
        path = self.check_value(self.panels.effects_path)
        self._job("load effects file", lambda: self.ctrl.load_effects_file(path))


def _get_lesson(slug):
    try:
        return get_lesson(slug)
    except KeyError:
        raise MagcalError(f"no lesson {clean_text(repr(slug), 80)}; choose one in the Lessons tab") from None


# ------------------------------------------------------------------------------------------------------------
# command line
# ------------------------------------------------------------------------------------------------------------
def host_warning(host: str) -> str | None:
    """The warning printed when the workbench is served beyond this machine (None for loopback)."""
    if is_loopback(host):
        return None
    return (
        f"WARNING: serving on {host}: anyone who can reach this address can see and change the session "
        "(data, model, files). Use the default 127.0.0.1 unless you mean to share it."
    )


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="magcal-workbench", description="Calibrate magnetometers in the browser: fit, diagnose, add effects."
    )
    p.add_argument("file", nargs="?", help="data CSV (default: the bundled demo)")
    p.add_argument("--host", default="127.0.0.1", help="address to serve on (default 127.0.0.1, this machine only)")
    p.add_argument("--port", type=int, default=8080, help="port (default 8080; 0 picks a free one)")
    p.add_argument("--session-dir", default=None, help="where sessions are saved (default ~/.magcal/sessions)")
    p.add_argument("--no-session", action="store_true", help="do not save or reopen sessions")
    p.add_argument("--fresh", action="store_true", help="ignore a saved session of the same file")
    p.add_argument("--lesson", default=None, help="open a lesson by name (see assets/lessons)")
    p.add_argument(
        "--max-upload-mb",
        type=float,
        default=DEFAULT_MAX_UPLOAD_MB,
        metavar="MB",
        help=f"largest file the page may upload, MB (default {DEFAULT_MAX_UPLOAD_MB:g})",
    )
    p.add_argument(
        "--max-sessions-mb",
        type=float,
        default=MAX_STORE_BYTES / 1e6,
        metavar="MB",
        help="bound of the session folder, MB: the oldest sessions are deleted to stay within it "
        f"(default {MAX_STORE_BYTES / 1e6:g})",
    )
    p.add_argument(
        "--max-points",
        type=int,
        default=scn.MAX_POINTS,
        metavar="N",
        help=f"most points drawn per sensor's cloud; larger files are shown decimated, fitted whole "
        f"(default {scn.MAX_POINTS})",
    )
    p.add_argument(
        "--live",
        default=None,
        metavar="SOURCE",
        help="calibrate live from an instrument: serial:///dev/ttyUSB0?baud=115200&columns=x,y,z, "
        "udp://127.0.0.1:14550?mavlink, tcp://HOST:PORT, sim://chi2017?rate=50 (docs/export.md)",
    )
    p.add_argument(
        "--record",
        default=None,
        metavar="PATH",
        help="with --live: the CSV recording (a new file; default live-DATE-TIME.csv in the session "
        "folder's recordings, or here with --no-session)",
    )
    p.add_argument(
        "--effects-file",
        action="append",
        default=[],
        metavar="PATH",
        help="a Python file defining your own effects (runs its code; repeat for several files); docs/user-effects.md",
    )
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    from magcal.model import plugins

    skipped: list = []  # a broken installed effect package is reported, skipped
    plugins.load_entry_points(notes=skipped)
    for note in skipped:
        print(f"magcal-workbench: {note.text}", file=sys.stderr)
    try:
        plugins.load_effects_files(args.effects_file)
        store = None if args.no_session else SessionStore(args.session_dir, int(args.max_sessions_mb * 1e6))
        lesson = None
        if args.lesson:
            try:
                lesson_obj = get_lesson(args.lesson)
            except KeyError:
                raise MagcalError(f"no lesson {args.lesson!r}; see the Lessons tab for the list") from None
            path, lesson = lesson_obj.data_path, args.lesson
        else:
            path = args.file or DEMO
        try:
            content = open(path, "rb").read()
        except OSError as exc:
            raise MagcalError(f"{path}: cannot read the file ({exc.strerror or exc})") from None
        dataset, notes = load_dataset(path)
        for n in notes:
            print(f"magcal-workbench: {n}", file=sys.stderr)
        warning = host_warning(args.host)
        if warning:
            print(f"magcal-workbench: {warning}", file=sys.stderr)
        if not args.max_upload_mb > 0 or args.max_points < 1:
            raise MagcalError("--max-upload-mb and --max-points must be positive")
        wb = Workbench(
            dataset,
            args.host,
            args.port,
            store,
            content,
            os.path.basename(str(path)),
            resume=not args.fresh,
            lesson=lesson,
            effects_files=args.effects_file,
            max_upload_mb=args.max_upload_mb,
            max_points=args.max_points,
        )
        if lesson:
            wb.panels.lesson_guide.content = f"### {lesson_obj.title}\n\n{lesson_obj.guide()}"
        if args.live:
            live = wb.start_live(args.live, args.record)
            print(f"magcal-workbench: live from {args.live}, recording to {live.path}", file=sys.stderr)
        elif args.record:
            raise MagcalError("--record goes with --live SOURCE")
    except MagcalError as exc:
        print(f"magcal-workbench: {exc}", file=sys.stderr)
        return 2
    print(f"magcal-workbench: open {page_url(args.host, wb.port)} in a browser (Ctrl-C stops)", flush=True)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        wb.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
