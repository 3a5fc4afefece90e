"""The Files tab, a panel of the panel recipe (:mod:`magcal_workbench.panelkit`): opening a file, the downloads,
the export section, the saved sessions and the live source.

:class:`FilesTab` is built at its place by :class:`~magcal_workbench.panels.Panels` (``build(panels, gui)``) and
refreshed with the other tabs (the downloads follow the fit, the sessions the data). Its widgets call the handlers of
the parts that own what they act on, each shared with more than this tab: the uploads
(:class:`~magcal_workbench.uploads.Uploads`, which also bound every upload's size), the downloads
(:class:`~magcal_workbench.downloads.Downloads`, also the exports'), the exports
(:class:`~magcal_workbench.exporting.Exporting`), the session folder (:class:`~magcal_workbench.sessions.Sessions`,
which also opens the data at start) and the live session (:class:`~magcal_workbench.livecontrol.LiveControl`, also
started from the command line).
"""

from __future__ import annotations

from .events import Change
from .exporting import ExportSection
from .live import BAUDS, LINE_UNITS, PAGE_PORT, PAGE_RATE_HZ, PAGE_SAMPLES, PAGE_SPEED, TEMPLATE_CHARS
from .markup import safe_code
from .panels import download_markdown, sessions_markdown
from .uploads import UPLOAD_UNITS


class FilesTab:
    """The Files tab's widgets and their refresh.

    Parameters
    ----------
    ctrl : callable
        ``ctrl()``: the open data's :class:`~magcal_workbench.controller.Controller`.
    """

    #: The tab it fills.
    tab = "Files"

    def __init__(self, *, ctrl):
        self._ctrl = ctrl
        self.on = None

    def attach(self, panels) -> None:
        """Follow the open data (built already at its place, else into its tab now)."""
        if self.on is None:
            with panels.tab(self.tab):
                self.build(panels, panels.gui)
            self.refresh(("all",))

    def build(self, panels, gui) -> None:
        """Make the widgets (in the tab being built)."""
        self.on = on = panels.on
        w = panels.w
        self.store = panels.store
        self.upload = gui.add_upload_button(
            "Open a file (CSV, .bin, .ulg)", mime_type=".csv,.txt,.bin,.ulg,text/csv,text/plain"
        )
        self.upload.on_upload(lambda e: panels.handle(on.do_upload, e))
        self.upload_columns = w.text(
            "Columns",
            "",
            hint="Your column names mapped onto magcal's, as the command line's --columns: "
            "x=magX,y=magY,z=magZ,t=time,temp=T (empty: the file's own names)",
        )
        self.upload_units = w.dropdown(
            "Units",
            UPLOAD_UNITS,
            initial_value=UPLOAD_UNITS[0],
            hint="Unit of the readings; 'from the file' reads its '# units:' line (nT without one)",
        )
        self.upload_lsb = w.number(
            "LSB nT/count",
            0.0,
            min=0.0,
            max=1e9,
            step=0.001,
            hint="nT per count for raw counts (0: the file's '# lsb_nT:' line)",
        )
        self.btn_reread = panels.button("Re-read the last upload with these", on.do_reread, engine=True)
        self.upload_info = gui.add_markdown("")
        self.btn_dl_cal = panels.button("Download calibration JSON", on.do_download_calibration)
        self.btn_dl_csv = panels.button("Download corrected CSV", on.do_download_corrected)
        self.download_info = gui.add_markdown("")
        with gui.add_folder("Export", expand_by_default=True):  # magcal_workbench.exporting
            self.export = ExportSection(gui, w, panels._button, on)
        gui.add_markdown("**Sessions** (saved automatically after every change)")
        self.session_info = gui.add_markdown("")
        self.session_choice = w.dropdown("Saved session", ("-",), allowed=panels.session_ids, initial_value="-")
        self.btn_reopen = panels.button("Reopen the session", on.do_reopen, engine=True)
        self.btn_fresh = panels.button("Start this data afresh", on.do_fresh, engine=True)
        self.btn_delete_session = panels.button("Delete the chosen session", on.do_delete_session, engine=True)
        self._build_live(panels, gui)
        panels.tab_panels.append(self)

    def _build_live(self, panels, gui) -> None:
        """The live source: one of the sources the server offers and its bounded options, Start, Pause/Resume,
        Stop (:mod:`magcal_workbench.live`, :class:`~magcal_workbench.live.SourceMenu`)."""
        w, on = panels.w, panels.on
        gui.add_markdown(
            "**Live from the instrument**: every sample is recorded to a CSV as it arrives; Stop "
            "opens the recording here. Other sources start from the command line (--live SOURCE)."
        )
        offered = panels.live_sources()
        first = next((o for o in offered if o == "simulated chi2017"), offered[0])
        self.live_source = w.dropdown(
            "Live source",
            offered,
            allowed=panels.live_sources,
            initial_value=first,
            hint="a simulated preset, a serial port found on this machine, UDP/TCP on 127.0.0.1, a recording "
            "of the session folder played again, or a source the command line allowed (--live-allow)",
        )
        self.live_rate = w.number("Rate (Hz)", 50.0, min=PAGE_RATE_HZ[0], max=PAGE_RATE_HZ[1], step=1.0)
        self.live_samples = w.number("Samples (simulated)", 3000, min=PAGE_SAMPLES[0], max=PAGE_SAMPLES[1], step=100)
        self.live_speed = w.number("Speed (x real time)", 1.0, min=PAGE_SPEED[0], max=PAGE_SPEED[1], step=0.1)
        self.live_port = w.number("Port (UDP/TCP)", 14550, min=PAGE_PORT[0], max=PAGE_PORT[1], step=1)
        self.live_baud = w.dropdown("Baud (serial)", BAUDS, initial_value=BAUDS[0])
        self.live_columns = w.text(
            "Columns (text lines)", "x,y,z", max_chars=200, hint="e.g. x,y,z or t,s1x,s1y,s1z,s2x,s2y,s2z"
        )
        self.live_template = w.text(
            "Template (text lines)",
            "",
            max_chars=TEMPLATE_CHARS,
            hint="e.g. x={x} y={y} z={z} or Magnetometer reading: [{x}, {y}, {z}]; blank: the columns",
        )
        self.live_units = w.dropdown("Units (text lines)", LINE_UNITS, initial_value=LINE_UNITS[0])
        self.btn_live_list = panels.button("List the sources again", on.do_live_list)
        self.btn_live_start = panels.button("Start live", on.do_live_start)
        self.btn_live_pause = panels.button("Pause", on.do_live_pause, visible=False)
        self.btn_live_resume = panels.button("Resume", on.do_live_resume, visible=False)
        self.btn_live_stop = panels.button("Stop and open the recording", on.do_live_stop, visible=False)

    # --- following the data --------------------------------------------------------------------------------
    def show_live(self, live) -> None:
        """The live buttons for the live session ``live`` (:class:`~magcal_workbench.live.LiveView` or None)."""
        running = live is not None and live.active
        paused = running and live.session.paused
        self.btn_live_start.disabled = running
        self.btn_live_pause.visible = running and not paused
        self.btn_live_resume.visible = running and paused
        self.btn_live_stop.visible = running

    def refresh_sessions(self) -> None:
        """The saved sessions and the Saved session choices (the newest first)."""
        store = self.store
        if store is None:
            self.session_info.content = "_Autosave is off._"
            return
        sessions = store.list()
        ctrl = self._ctrl()
        self.session_info.content = (
            f"This session: {safe_code(ctrl.session_id)} in {safe_code(store.root)}"
            if ctrl.session_id
            else "_This session is not saved._"
        )
        self.session_info.content += "\n\n" + sessions_markdown(sessions, store.max_bytes)
        opts = tuple(s["id"] for s in sessions[:30]) or ("-",)
        self.session_choice.options = opts
        self.session_choice.value = opts[0]

    def refresh(self, kinds) -> None:
        """The downloads follow the fit, the sessions other data; the export section its state."""
        if self.on is None:
            return
        ctrl = self._ctrl()
        every = "all" in kinds
        if every or any(k in kinds for k in (Change.RESULT, Change.SELECTION, Change.MODEL)):
            self.download_info.content = download_markdown(ctrl)
        if every or Change.DATA in kinds:
            self.refresh_sessions()
        has_cal = ctrl.calibration is not None
        self.btn_dl_cal.disabled = not has_cal
        self.btn_dl_csv.disabled = not has_cal
        self.on.refresh_export()
