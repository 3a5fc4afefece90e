"""``magcal-workbench [FILE.csv] [--live SOURCE] [--host 127.0.0.1] [--port 8080] [--effects-file MY.py]``: the
browser workbench; it prints the page's address with its token (``http://127.0.0.1:8080/?token=...``).

:class:`Workbench` composes the parts and starts them; each concern lives in its own module:

* one :class:`viser.ViserServer` (every browser shares its scene and GUI), started through
  :mod:`~magcal_workbench.viser_adapter` with :mod:`~magcal_workbench.guard`'s handshake check;
* the :class:`~magcal_workbench.controller.Controller` (engine actions and session state), opened by
  :class:`~magcal_workbench.sessions.Sessions` (the session folder, autosave);
* the :class:`~magcal_workbench.panels.Panels`, whose input widgets are registered with what they may send
  (:mod:`~magcal_workbench.checks`), and the actions they call: :class:`~magcal_workbench.steps.Steps`,
  :class:`~magcal_workbench.uploads.Uploads`, :class:`~magcal_workbench.downloads.Downloads`,
  :class:`~magcal_workbench.livecontrol.LiveControl`, the panels of :mod:`~magcal_workbench.panelkit` (the tabs
  built as panels, the gravity page),
  :class:`~magcal_workbench.evidence.Evidence`, :class:`~magcal_workbench.cockpit.Cockpit` (the compact table,
  |B| against time with its region editor, the error histogram) and :class:`~magcal_workbench.view.SceneControl`
  (scene, camera, pointer events, View tab);
* :class:`~magcal_workbench.uiqueue.UiQueue`: background threads (the worker, live sessions, playback) hand
  every page update to one thread.

With no file it opens the bundled demo (``assets/demo.csv``). It binds to 127.0.0.1 unless another host is asked
for, and then warns. A user's own effects (:mod:`magcal.model.plugins`) join the catalogue at start -- installed
packages' entry points and every ``--effects-file`` -- or later from the Model tab; the session remembers the
files, and when it reopens the page offers to load them again (opening a session never runs code). A damaged
session file is moved aside and the data open afresh.

Hostile pages and careless input: only the app's own page may open its websocket
(:mod:`magcal_workbench.guard`); every value a browser sends is checked against what the server offers before it
is read or saved (:class:`magcal_workbench.checks.PageValues`); every callback, pointer events included, goes
through :meth:`Workbench.handle`; a job fits the mask it started with and a rejection made meanwhile is refitted
after it; uploads are bounded (``--max-upload-mb``), the session folder too (``--max-sessions-mb``), and a large
file is drawn decimated (``--max-points``) and fitted whole.

A local process or a hostile page: every request shows the secret token of the printed address
(:class:`magcal_workbench.guard.Gate`; ``--no-token`` warns), beyond loopback Host must name this machine
(``--allow-host``); the page starts only live sources the server offers (:class:`magcal_workbench.live.SourceMenu`,
``--live-allow``), one at a time; the sessions' bound keeps the recordings; uploads are counted by the bytes
received.

Another server of this machine, a page's holder: the token is in no cookie (every port of the host would
receive it) -- the page keeps it in its tab and gives it to its own websocket (:mod:`magcal_workbench.guard`); the
page runs an effects file only when the command line named it or the user confirms it in the terminal
(:mod:`magcal_workbench.consent`); nothing the page downloads names a path of the server.
"""

from __future__ import annotations

import os
import secrets
import sys
import time
from typing import cast

from magcal.core.errors import MagcalError
from magcal.core.files import check_regular_file
from magcal.model import plugins

from . import scene as scn
from . import timing, viser_adapter
from .actions import Actions
from .checks import PageValues, Widgets
from .cockpit import Cockpit
from .consent import EffectsFiles, Terminal
from .controller import Controller, error_markdown
from .dataio import load_dataset
from .defaults import DEFAULT_MAX_UPLOAD_MB
from .downloads import Downloads
from .events import Change
from .evidence import Evidence
from .exporting import Exporting
from .gravitypage import GravityPage
from .guard import Gate, guarded_viser_server, is_loopback, page_url
from .jobs import Worker
from .lessons import DEMO, get_lesson
from .lessonstab import LessonsTab
from .livecontrol import LiveControl
from .maps import SphereMaps
from .markup import clean_text, error_text, safe_text
from .panelkit import PANELS, PanelContext
from .panels import Panels
from .session import SessionStore
from .sessions import Sessions
from .startup import NO_TOKEN_WARNING, Early, build_parser, host_warning
from .steps import Steps
from .timewindow import TimeWindow, sample_times
from .uiqueue import UiQueue
from .uploads import Uploads
from .vehicleview import VehicleView
from .view import SceneControl


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
        The user's effect files already loaded (``--effects-file``); every session opened remembers them, and the
        page may load them again. Any other file the page asks for is confirmed in ``terminal`` first
        (:class:`magcal_workbench.consent.EffectsFiles`).
    server : viser.ViserServer or None
        A server already started with ``token``'s gate (the launcher's, :class:`magcal_workbench.startup.Early`);
        None starts one on ``host``/``port``.
    scene_view : magcal_workbench.scene.SceneView or None
        The scene already drawn on ``server`` (the launcher's preview), redrawn in place; None makes one.
    terminal : magcal_workbench.consent.Terminal or None
        Where the user confirms an effects file the page asks for that the command line did not name (the
        workbench's terminal, :meth:`~magcal_workbench.consent.Terminal.of_stdin`); None refuses every such file.
    max_upload_mb : float
        Largest file the page may upload, MB (10^6 bytes); a larger one is refused with a message.
    max_points : int
        Most points drawn per cloud (one sensor's raw or corrected readings); larger data are shown decimated
        (:func:`magcal_workbench.scene.level_of_detail`), every sample is still fitted and selectable.
    token : str or None
        The secret every request must show (:class:`magcal_workbench.guard.Gate`); ``"auto"`` (default) makes one
        (:func:`secrets.token_urlsafe`), None asks for none (``--no-token``). :attr:`url` is the page's address
        with it.
    allow_hosts : sequence of str
        Beyond loopback, Host names accepted besides this machine's own (``--allow-host``).
    live_allow : sequence of str
        Live sources the page may start besides those it is offered (``--live-allow``,
        :class:`magcal_workbench.live.SourceMenu`).
    """

    # made in __init__ after the parts whose callbacks reach them (the callbacks run later)
    view: SceneControl
    ctrl: Controller
    panels: Panels
    scene_view: scn.SceneView
    steps: Steps
    vehicle: VehicleView
    gravity: GravityPage

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
        token: str | None = "auto",
        allow_hosts=(),
        live_allow=(),
        terminal: Terminal | None = None,
        server=None,
        scene_view: scn.SceneView | None = None,
    ):
        #: The page's thread: every update a background thread makes goes through it.
        self.ui = UiQueue()
        #: What each input widget may send (registered where the panels make it).
        self.values = PageValues()
        #: The secret in the page's address (None with ``--no-token``).
        self.token = secrets.token_urlsafe(32) if token == "auto" else token
        self.host = host
        # refuses requests without the token, other pages' websockets, and (beyond loopback) foreign Host names
        if server is None:
            self.server = guarded_viser_server(host, port, verbose, Gate(host, self.token, allow_hosts))
        else:  # started by the launcher before the engine was imported, with this token (magcal_workbench.startup)
            self.server = server
        #: Whether the page may load effect files (it runs their code): only when served to this machine.
        self.local = is_loopback(host)
        self.effects_files = [os.path.abspath(p) for p in effects_files]
        #: The effects files the page may load: the command line's, and those confirmed in the terminal.
        self.effects_gate = EffectsFiles(self.effects_files, terminal)
        self.store = store
        self.worker = Worker(settle=self.ui.wait)
        self._last_progress = 0.0
        #: The time scrubber's window (View tab): the samples drawn and the evidence plots' shaded band.
        self.window = TimeWindow(lambda: self.view.window_moved())
        #: The residual-map surfaces (View tab's Sphere surface).
        self.maps = SphereMaps(
            self.server, ctrl=lambda: self.ctrl, candidate=lambda: self.panels.candidate_choice.value
        )
        self.sessions = Sessions(
            ctrl=lambda: self.ctrl,
            panels=lambda: self.panels,
            store=self.store,
            effects_files=self.effects_files,
            worker=self.worker,
            values=self.values,
            load=self.load,
            say_after_load=self.say_after_load,
        )
        self.uploads = Uploads(
            ctrl=lambda: self.ctrl,
            panels=lambda: self.panels,
            values=self.values,
            server=self.server,
            ui=self.ui,
            notify=self.notify,
            load=self.load,
            say_after_load=self.say_after_load,
            max_upload_bytes=int(max_upload_mb * 1e6),
        )
        self.downloads = Downloads(lambda: self.ctrl)
        self.livectl = LiveControl(
            ctrl=lambda: self.ctrl,
            panels=lambda: self.panels,
            scene_control=lambda: self.view,
            scene_view=lambda: self.scene_view,
            values=self.values,
            local=self.local,
            store=self.store,
            server=self.server,
            ui=self.ui,
            load=self.load,
            say_after_load=self.say_after_load,
            live_allow=live_allow,
        )
        self.exporting = Exporting(
            ctrl=lambda: self.ctrl,
            panels=lambda: self.panels,
            handle=self.handle,
            livectl=self.livectl,
            downloads=self.downloads,
            values=self.values,
            store=self.store,
            ui=self.ui,
        )
        if store is not None:  # the size bound never deletes the recording being written
            store.in_use = lambda: [p for p in (self.livectl.recording_in_use,) if p is not None]
        self.evidence = Evidence(
            ctrl=lambda: self.ctrl,
            panels=lambda: self.panels,
            window=self.window,
            maps=self.maps,
            downloads=self.downloads,
            server=self.server,
        )
        #: The compact table, |B| against time with its region editor, the error histogram.
        self.cockpit = Cockpit(
            ctrl=lambda: self.ctrl,
            panels=lambda: self.panels,
            live=lambda: self.live,
            steps=lambda: self.steps,
            values=self.values,
        )
        self.view = SceneControl(
            ctrl=lambda: self.ctrl,
            panels=lambda: self.panels,
            scene_view=lambda: self.scene_view,
            live=lambda: self.live,
            steps=lambda: self.steps,
            vehicle=lambda: self.vehicle,
            maps=self.maps,
            window=self.window,
            values=self.values,
            ui=self.ui,
            server=self.server,
            evidence=self.evidence,
        )
        self.steps = Steps(
            ctrl=lambda: self.ctrl,
            panels=lambda: self.panels,
            values=self.values,
            worker=self.worker,
            local=lambda: self.local,
            effects_gate=self.effects_gate,
        )
        #: The vehicle view and the vector model's page actions.
        self.vehicle = VehicleView(
            ctrl=lambda: self.ctrl,
            panels=lambda: self.panels,
            steps=self.steps,
            view=self.view,
            values=self.values,
            window=self.window,
            server=self.server,
        )
        #: The gravity model: a compass beside an accelerometer, its fit, plots and cloud.
        #: The added panels (:data:`magcal_workbench.panelkit.PANELS`, in order): the gravity model's page
        #:, then those a module or an installed package registered.
        context = PanelContext(
            ctrl=lambda: self.ctrl,
            steps=lambda: self.steps,
            server=self.server,
            ui=self.ui,
            load=self.load,
            say_after_load=self.say_after_load,
            panel=lambda name: self.added[name],
        )
        self.added = {name: kind.make(context) for name, kind in PANELS.items()}
        self.gravity = cast(GravityPage, self.added["gravity"])
        #: The Lessons tab (open a lesson, check the model, show the answer).
        self.lessons = cast(LessonsTab, self.added["lessons"])
        self.ctrl = self.sessions.make_controller(dataset, content, name, resume, lesson)
        # the launcher's preview is redrawn in place (magcal_workbench.preview)
        self.scene_view = scene_view if scene_view is not None else scn.SceneView(self.server, max_points=max_points)
        #: Every handler the page's widgets call, by name (``on.do_refine``).
        self.actions = self._actions()
        self.panels = Panels(
            Widgets(self.server.gui, self.values),
            handle=self.handle,
            on=self.actions,
            ctrl=lambda: self.ctrl,
            live=lambda: self.live,
            busy=lambda: self.worker.busy,
            maps_choice=lambda: self.maps.choice,
            session_ids=self.sessions.session_ids,
            store=self.store,
            local=self.local,
            live_sources=self.livectl.menu.labels,
            tabs=self.added,  # the built-in tabs made as panels are built at their place
        )
        self.uploads.watch_sizes(self.panels.upload)
        #: Every change a browser sends to a widget is screened before viser casts it (PageValues.screen).
        self.update_screen = viser_adapter.watch_updates(self.server, self._screen)
        self.exporting.attach(self.panels.export, self.panels.live_source)
        for panel in self.added.values():
            panel.attach(self.panels)
        self.worker.on_busy_change(lambda busy, job: self.ui.post(lambda: self._busy_changed(busy, job)))
        # pointer events go through the error handler like every widget's callback
        self.server.scene.on_click()(lambda event: self.handle(lambda e: self.view.on_click(e), event))
        self.server.scene.on_rect_select(modifier="shift")(
            lambda event: self.handle(lambda e: self.view.on_rect_select(e), event)
        )
        self.server.on_client_connect(lambda client: self.handle(lambda _: self.view.place_camera(client), None))
        self.server.scene.set_up_direction("+z")
        self._attach(self.ctrl)
        self._forget_view_state()  # the first record's time-window text, as every record opened later has it
        self.redraw()

    def _actions(self) -> Actions:
        """What the panels' widgets call (:class:`~magcal_workbench.panels.Panels`' ``on``): the handlers each part
        marks with :func:`~magcal_workbench.actions.action`; two parts offering one name stop the start."""
        return Actions(self.parts())

    def parts(self) -> tuple:
        """The parts whose :func:`~magcal_workbench.actions.action` handlers the page's widgets call."""
        return (
            self.steps,
            self.uploads,
            self.downloads,
            self.sessions,
            self.livectl,
            self.evidence,
            self.exporting,
            self.vehicle,
            self.cockpit,
            self.view,
            *self.added.values(),
        )

    # ------------------------------------------------------------------------------------------------------
    @property
    def port(self) -> int:
        return self.server.get_port()

    @property
    def url(self) -> str:
        """The page's address, with its token (what is printed at start): ``http://127.0.0.1:PORT/?token=...``."""
        return page_url(self.host, self.port, self.token)

    @property
    def live(self):
        """The live session (:class:`magcal_workbench.live.LiveView`) while one is open or after it stopped."""
        return self.livectl.view

    def stop(self) -> None:
        self.effects_gate.close()  # a question waiting in the terminal ends
        self.worker.wait(30)
        self.server.stop()
        self.ui.stop()

    def load(self, dataset, content: bytes | None, name: str, resume: bool = True, lesson: str | None = None):
        """Replace the data (upload, lesson, reopened session); the scene and panels follow."""
        self.steps.forget_pending()  # a refit asked for on the old data
        self.window.pause()  # no playback over the data being replaced
        self.ctrl = self.sessions.make_controller(dataset, content, name, resume, lesson)
        self._attach(self.ctrl)
        self.ui.run(self._redraw_all)

    def _added_follow(self, kind: Change) -> None:
        """Tell the added panels (:data:`magcal_workbench.panelkit.PANELS`) what changed."""
        for panel in self.added.values():
            follow = getattr(panel, "changed", None)  # optional for an added panel
            if follow is not None:
                follow(kind)

    def _forget_view_state(self) -> None:
        """The views' state that belonged to the data open before starts anew (the one place that resets it):
        the time window is off and at the start (its percentages would pick another stretch of other data, and its
        text described the old record) and the vehicle view is off (the new data may have no attitude, and the
        cameras looked at the old body), and the location inputs hold no place of the old record. Each widget's
        callback then agrees with the state set here."""
        self.panels.vector_panel.clear_location_inputs()
        self.window.pause()
        self.window.enabled, self.window.start_pct = False, 0.0
        self.vehicle.enabled = False
        for widget, value in (
            (self.panels.vector_panel.vehicle_on, False),
            (self.panels.window_on, False),
            (self.panels.window_start, 0.0),
        ):
            if widget.value != value:
                widget.value = value
        self.panels.window_info.content = safe_text(self.window.describe(sample_times(self.ctrl.dataset)))

    def _redraw_all(self) -> None:
        self._forget_view_state()
        self.scene_view.clear()
        self.vehicle.clear()
        self.redraw()
        self._added_follow(Change.DATA)  # other data opened: the gravity page forgets the old data's fit
        self.maps.fit_changed(self.ctrl)
        self.view.refresh_maps()
        self.view.reset_cameras()
        self.vehicle.redraw()

    def redraw(self) -> None:
        self.panels.fit_view_to_data()  # the gains first: the scene is then drawn once, at them
        self.view.update_scene()
        self.panels.refresh(("all", Change.DATA))

    def say_after_load(self, text: str) -> None:
        """Say ``text`` (markdown, escaped) and keep what opening the session had to say."""
        prior = self.ctrl.message
        self.ctrl.say(text + (f"  \n{prior}" if prior else ""))

    def notify(self, client_id, text: str) -> None:
        """A red toast (plain text) in the browser ``client_id``, if it is still connected."""
        client = self.server.get_clients().get(client_id)
        if client is not None:
            client.add_notification("magcal", text, color="red", auto_close_seconds=8.0)

    # ------------------------------------------------------------------------------------------------------
    # events from the controller and the worker: handed to the page's thread
    # ------------------------------------------------------------------------------------------------------
    def _attach(self, ctrl: Controller) -> None:
        def changed(kind, c=ctrl):
            update = lambda: self._changed(c, kind)
            if self.worker.in_job():
                self.ui.post(update)  # the job goes on; the page follows
            else:
                self.ui.run(update)  # a callback's change is shown before the callback returns

        ctrl.on_change(changed)

    def _changed(self, ctrl: Controller, kind: Change) -> None:
        if ctrl is not self.ctrl:
            return  # an old session still finishing
        if kind == Change.PROGRESS:
            now = time.perf_counter()
            if ctrl.progress is not None and (ctrl.progress[1] is not None or now - self._last_progress > 0.1):
                self._last_progress = now  # a search reports thousands of iterations: show ten a second
                self.panels.set_progress(*ctrl.progress)
            return
        if kind in (Change.RESULT, Change.DATA, Change.VECTOR, Change.GRAVITY, Change.COMPENSATION):  # the scene draws
            with timing.span("scene"):
                # the gains first: a gain that changes redraws the scene (its callback) once
                self.panels.fit_view_to_data()
                self.view.update_scene()  # nothing is sent again when the gains' redraw has drawn it
        elif kind == Change.SELECTION:
            with timing.span("scene"):
                self.view.recolor()
        elif kind == Change.INSPECT:
            self.scene_view.mark_inspected(ctrl.inspected)
        self.vehicle.changed(kind)
        self._added_follow(kind)
        if kind in (Change.RESULT, Change.DATA):
            self.maps.fit_changed(ctrl)  # before the panels: the evidence plots show the RMS before the last fit
        if kind in (Change.RESULT, Change.DATA, Change.DIAGNOSIS) and self.maps.choice != "none":
            with timing.span("maps"):
                self.view.refresh_maps()
        with timing.span("panels" if kind == Change.MESSAGE else "plots"):  # the texts, the cockpit's plotly figures
            self.panels.refresh((kind,))

    def _busy_changed(self, busy: bool, name) -> None:
        self.panels.set_busy(busy, name)
        if not busy:
            self.steps.job_ended()

    def _screen(self, handle, updates: dict, client_id) -> bool:
        """Whether a browser's change of ``handle`` is refused before viser applies it
        (:meth:`magcal_workbench.checks.PageValues.screen`): then it is said in the page and in that browser's
        toast, and the widget shows the server's value again. Runs on viser's event loop: never raises."""
        try:
            why = self.values.screen(handle, updates)
        except Exception as exc:  # a value the check itself cannot read: refused
            why = f"{clean_text(getattr(handle, 'label', 'value'), 60)}: unreadable value ({type(exc).__name__})"
        if why is None:
            return False
        text = f"{why}; refused (nothing was read or saved)"

        def tell():
            self.ctrl.say(f"**Error:** {safe_text(text)}")
            self.notify(client_id, text)
            viser_adapter.show_value(handle)

        self.ui.post(tell)  # off viser's event loop
        return True

    # ------------------------------------------------------------------------------------------------------
    def handle(self, func, event, *args):
        """Run a callback; an engine error becomes the message (and a toast in the browser that caused it).

        The widget that changed (``event.target``) is checked first (:meth:`PageValues.check`): a value the page
        could not have offered is refused before anything reads or saves it."""
        try:
            target = getattr(event, "target", None)
            if target is not None:
                self.values.check(target)
            func(event, *args)
        except MagcalError as exc:
            self.ctrl.say(error_markdown(exc))
            client = getattr(event, "client", None)
            if client is not None:  # a toast shows plain text: only cut to length
                client.add_notification("magcal", clean_text(error_text(exc), 300), color="red", auto_close_seconds=8.0)
        except Exception as exc:  # never let a callback die silently (error_markdown logs the traceback)
            self.ctrl.say(error_markdown(exc))


# ------------------------------------------------------------------------------------------------------------
# command line
# ------------------------------------------------------------------------------------------------------------
def _workbench(args, early: Early | None, dataset, store, content, path, lesson) -> Workbench:
    """The :class:`Workbench` the command line asks for (on the launcher's server when ``early`` is given)."""
    return Workbench(
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
        token=early.token if early is not None else (None if args.no_token else "auto"),
        allow_hosts=args.allow_host,
        live_allow=args.live_allow,
        terminal=Terminal.of_stdin(),
        server=None if early is None else early.server,
        scene_view=None if early is None else early.scene_view,
    )


def main(argv=None, early: Early | None = None) -> int:
    """Start the workbench from the command line ``argv``. ``early``: the launcher's server, already serving the
    page with its address printed (:func:`magcal_workbench.startup.begin`); the workbench is built on it."""
    args = early.args if early is not None else build_parser().parse_args(argv)
    if args.timing:
        timing.enable()
    # a broken installed effect package is reported, skipped
    for note in plugins.load_entry_points(warn=False).notes:
        print(f"magcal-workbench: {note.text}", file=sys.stderr)
    for note in PANELS.load_entry_points().notes:  # another package's panels (magcal_workbench.panelkit)
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
            check_regular_file(path, "data file")  # a FIFO would block the start, a device never end
            with open(path, "rb") as fh:
                content = fh.read()
        except OSError as exc:
            raise MagcalError(f"{path}: cannot read the file ({exc.strerror or exc})") from None
        with timing.span("read"):
            dataset, notes = load_dataset(path)
        for n in notes:
            print(f"magcal-workbench: {n}", file=sys.stderr)
        warning = host_warning(args.host)
        if warning and early is None:  # the launcher said it before the address
            print(f"magcal-workbench: {warning}", file=sys.stderr)
        if args.no_token and early is None:
            print(f"magcal-workbench: {NO_TOKEN_WARNING}", file=sys.stderr)
        if not args.max_upload_mb > 0 or args.max_points < 1:
            raise MagcalError("--max-upload-mb and --max-points must be positive")
        with timing.span("build"):
            wb = _workbench(args, early, dataset, store, content, path, lesson)
        if lesson:
            wb.lessons.show_guide(lesson_obj)
        if args.live:
            live = wb.livectl.start(args.live, args.record)
            print(f"magcal-workbench: live from {args.live}, recording to {live.path}", file=sys.stderr)
        elif args.record:
            raise MagcalError("--record goes with --live SOURCE")
    except MagcalError as exc:
        print(f"magcal-workbench: {exc}", file=sys.stderr)
        if early is not None:
            early.stop()
        return 2
    if early is None:
        print(f"magcal-workbench: open {wb.url} in a browser (Ctrl-C stops)", flush=True)
    else:
        early.done()
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        wb.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
