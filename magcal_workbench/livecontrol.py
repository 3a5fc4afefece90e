"""The Files tab's live source: Start (one of the sources the server offers, :class:`magcal_workbench.live.SourceMenu`),
Pause, Resume, and Stop, which opens the recording like any file. The live view itself is
:class:`magcal_workbench.live.LiveView`."""

from __future__ import annotations

import threading

from magcal.core.errors import MagcalError

from .actions import action
from .controller import MESSAGE_LEN
from .dataio import load_dataset
from .live import LiveView, SourceMenu, default_recording_path, recording_folder, shown_name
from .markup import safe_code, safe_text
from .parts import PagePart


class LiveControl(PagePart):
    """Starts and stops the live session; :attr:`view` is the session while one is open or after it stopped.

    Handed what it uses.

    Parameters
    ----------
    ctrl, panels, scene_control, scene_view : callable
        Getters, made or replaced after this part: the open data's
        :class:`~magcal_workbench.controller.Controller`, the :class:`~magcal_workbench.panels.Panels`, the
        :class:`~magcal_workbench.view.SceneControl` (redraws the live samples, resets the cameras) and the
        :class:`~magcal_workbench.scene.SceneView` (cleared when a session starts).
    values : magcal_workbench.checks.PageValues
        What each input widget may send (the source's options are checked before they are read).
    local : bool
        Whether the page is served to this machine only (:class:`~magcal_workbench.live.SourceMenu`).
    store : magcal_workbench.session.SessionStore or None
        The sessions' folder (recordings are written in it), None without one.
    server : viser.ViserServer
        Where the live samples are drawn.
    ui : magcal_workbench.uiqueue.UiQueue
        The page's thread: the live session's updates go through it.
    load : callable
        ``load(dataset, content, name, resume=False)``: opens the stopped recording
        (:meth:`magcal_workbench.app.Workbench.load`).
    say_after_load : callable
        ``say_after_load(text)``: says what opening it found (:meth:`magcal_workbench.app.Workbench.say_after_load`).
    live_allow : sequence of str
        Sources the command line allowed the page to start (``--live-allow``).
    """

    def __init__(
        self,
        *,
        ctrl,
        panels,
        scene_control,
        scene_view,
        values,
        local: bool,
        store,
        server,
        ui,
        load,
        say_after_load,
        live_allow=(),
    ) -> None:
        self._ctrl, self._panels, self._scene_control, self._scene_view = ctrl, panels, scene_control, scene_view
        self.values, self.store, self.server, self.ui = values, store, server, ui
        self.load, self.say_after_load = load, say_after_load
        #: What the page may start (never a URL it sends).
        self.menu = SourceMenu(local, lambda: None if store is None else recording_folder(store), live_allow)
        #: The live session (:class:`~magcal_workbench.live.LiveView`) while one is open or after it stopped.
        self.view: LiveView | None = None
        self._claim = threading.Lock()
        self._starting = False

    @property
    def running(self) -> bool:
        return self.view is not None and self.view.active

    @property
    def recording_in_use(self):
        """The recording a live session is writing, or None: the session folder's bound never
        deletes it (:meth:`magcal_workbench.session.SessionStore.prune`)."""
        return self.view.path if self.running else None

    def start(self, url: str, path=None) -> LiveView:
        """Open a live source (:mod:`magcal_workbench.live`); its samples are recorded to ``path`` (default a new
        file in the session folder's ``recordings``, or the current folder without sessions).

        One live session at a time, decided before the source opens: a Start while another is running or still
        opening (a slow serial port, several presses of the button) is refused, and leaves no recording."""
        with self._claim:
            if self._starting or self.running:
                raise MagcalError("a live session is running or starting; stop it first")
            self._starting = True
        try:
            path = default_recording_path(recording_folder(self.store)) if path is None else path
            self.view = LiveView(
                url,
                path,
                self.server,
                self.ui,
                redraw=self._scene_control().update_scene,
                refresh=lambda: self.panels.refresh_live(),
                reference_nT=lambda: self.ctrl.state.reference_nT,  # typed, or IGRF at the typed location
                name=shown_name(path, self.store),  # recordings/live-....csv: the page never sees the server's path
            )
        finally:
            with self._claim:
                self._starting = False
        self._scene_view().clear()
        self._scene_control().reset_cameras()
        self.panels.refresh_live()
        return self.view

    def page_url(self) -> str:
        """The URL of the source the page chose, built here from the offered list and its checked options."""
        p, check = self.panels, self.values.check
        return self.menu.url(
            check(p.live_source),
            rate_hz=check(p.live_rate),
            n_samples=check(p.live_samples),
            speed=check(p.live_speed),
            port=check(p.live_port),
            baud=check(p.live_baud),
            columns=check(p.live_columns),
            units=check(p.live_units),
            template=check(p.live_template),
        )

    @action
    def do_live_list(self, event):
        """List the sources again (a serial port plugged in, a new recording)."""
        p = self.panels
        p.live_source.options = self.menu.labels()

    @action
    def do_live_start(self, event):
        url = self.page_url()
        live = self.start(url)
        self.ctrl.say(f"live from {safe_code(url)}: recording to {safe_code(live.name)}")

    @action
    def do_live_pause(self, event):
        if self.running:
            self.view.pause()
        self.panels.refresh_live()

    @action
    def do_live_resume(self, event):
        if self.running:
            self.view.resume()
        self.panels.refresh_live()

    @action
    def do_live_stop(self, event):
        """Stop the live session and open its recording like any file (Calibrate and Model work on it); say how
        many samples it holds and where (inside the session folder), and why it stopped early if it did."""
        if not self.running:
            raise MagcalError("no live session is running")
        live = self.view
        try:
            path = live.stop()
        finally:
            self.panels.refresh_live()
        summary = live.stop_summary()
        self.ctrl.say(summary)

        def job():
            ds, notes = load_dataset(path, live.name)
            self.load(ds, path.read_bytes(), path.name, resume=False)
            self.say_after_load(
                f"{summary}  \nopened the recording {safe_code(live.name)}: "
                f"{safe_text(ds.describe(), MESSAGE_LEN)}"
                + "".join(f"  \n- {safe_text(n, MESSAGE_LEN)}" for n in notes)
            )

        self.ctrl.run_job("open the recording", job)
