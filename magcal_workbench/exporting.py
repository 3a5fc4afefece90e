"""The Files tab's Export section: every file ``magcal export`` and ``magcal apply`` write, one click each, and
*Send to vehicle* for a MAVLink live source.

Each file is built by the engine's own function (:mod:`magcal.output.bundle`) from the calibration as its
``calibration.json`` holds it (the page's calibration written and read back), so a download is byte for byte what
the command line writes from that file:

==========================  ====================================================================================
button                      the command it equals
==========================  ====================================================================================
calibration.json            (the file itself)
ArduPilot .parm             ``magcal export calibration.json --format ardupilot -o compass.parm``
PX4 .params                 ``magcal export calibration.json --format px4 -o mag.params``
C header                    ``magcal export calibration.json --format c -o magcal_calibration.h``
(a format's button)         ``magcal export calibration.json --format NAME``: every registered format
Corrected CSV / Parquet     ``magcal apply calibration.json DATA -o corrected.csv`` (``.parquet``)
Raw data + mask             ``magcal export calibration.json --format mask --data DATA --mask raw_mask.csv``
Export all (.zip)           ``magcal export calibration.json --format all --data DATA``, plus ``session.json``
==========================  ====================================================================================

Nothing the page downloads holds a path of the server: the zip's ``session.json`` names the data file by
its name and leaves the effects files out (the README names them), and every reason or note is shown with
absolute paths cut to the file's name.

``DATA`` is the data the session works on (the session folder's ``data.csv``). *Send to vehicle*
(:mod:`magcal.output.vehicle_params`) is shown only while the chosen live source is a MAVLink one the server
offers (:class:`magcal_workbench.live.SourceMenu`): the first click reads the vehicle's values and shows old -> new,
the second (*Confirm*) writes them, after saving the old values in the session folder; the read-back table follows.
"""

from __future__ import annotations

import io
import json
import os
import sys
import tempfile
import threading
import time
import urllib.parse
import zipfile
from functools import partial
from pathlib import Path, PurePath

from magcal.core.errors import MagcalError
from magcal.output import bundle, formats
from magcal.output.vehicle_params import default_backup_path, send_parameters, values_to_send

from .actions import action
from .dataio import canonical_csv
from .live import recording_folder
from .markup import hide_paths, safe_code, safe_text
from .parts import PagePart

#: The firmwares *Send to vehicle* offers.
FIRMWARES = ("ardupilot", "px4")
#: A preview older than this is shown again before anything is written, s.
PREVIEW_LIFETIME_S = 300.0
#: The session file's name in the zip (without the server's paths: :func:`session_for_download`).
SESSION_FILE = "session.json"
#: The zip's README (its absolute paths hidden: :func:`without_paths`).
README = "README.txt"


def session_for_download(state) -> tuple[bytes, list[str]]:
    """The session's ``session.json`` as the page downloads it (Export all), and the names of the effects files the
    session names: no path of the server in it -- the data file by its name only, the effects files left out
    (the document stays one the workbench reads: :func:`magcal_workbench.sessionfile.read_session_document`)."""
    doc = state.to_dict()
    if doc.get("data_path"):
        doc["data_path"] = PurePath(doc["data_path"]).name or None
    names = [PurePath(p).name for p in doc.get("effects_files") or ()]
    doc["effects_files"] = []
    return (json.dumps(doc, indent=1) + "\n").encode("utf-8"), names


def without_paths(content: bytes) -> bytes:
    """The zip ``content`` (:func:`magcal.output.bundle.export_all`) with every absolute path in its README cut to
    the file's name (:func:`magcal_workbench.markup.hide_paths`): a file the engine could not write says why, and
    the reason may name where the data lie on the server."""
    with zipfile.ZipFile(io.BytesIO(content)) as zf:
        files = {name: zf.read(name) for name in zf.namelist()}
    readme = files.get(README)
    if readme is None:
        return content
    shown = hide_paths(readme.decode("utf-8")).encode("utf-8")
    if shown == readme:
        return content
    files[README] = shown
    return bundle.zip_bytes(files)


def _refusal(note: str) -> bool:
    """Whether an export's note says a sensor not determined was left out or forced
    (:func:`magcal.output.export.determined_sensors`)."""
    return note.startswith(("not exported:", "exported although not determined"))


def report_markdown(report, title: str) -> str:
    """A send report (:class:`magcal.output.vehicle_params.SendReport`) as a markdown table."""
    rows = ["| parameter | old | new | read back | status |", "|---|---|---|---|---|"]
    rows += [f"| {safe_code(n, 20)} | {o} | {w} | {b} | {safe_text(s, 120)} |" for n, o, w, b, s in report.rows()]
    lines = [f"**{title}**", "", "\n".join(rows)]
    if report.backup_path:
        lines.append(f"\nOld values saved to {safe_code(Path(report.backup_path).name)} in the session folder.")
    return "\n".join(lines)


class ExportSection:
    """The Export widgets (made inside the Files tab by :class:`~magcal_workbench.panels.Panels`).

    Parameters
    ----------
    gui : viser GUI API
    widgets : magcal_workbench.checks.Widgets
        Makes the input widgets and registers what each may send.
    button : callable
        ``button(gui, label, handler, engine=False, **kw)``: the panels' button maker (errors become messages).
    on : object
        The actions: ``do_export_*`` and ``do_send_*`` of :class:`Exporting`.
    """

    def __init__(self, gui, widgets, button, on):
        gui.add_markdown(
            "**Export**: each file is what the command line writes from the downloaded calibration.json "
            "(`magcal export`, `magcal apply`); *Export all* zips every file the calibration allows, with a "
            "README.txt saying what was not written and why."
        )
        self.force = gui.add_checkbox(
            "Force (leave out what the firmware cannot hold)",
            False,
            hint="As --force: effects and rotations between sensors the firmware cannot store are left out (listed "
            "in the file), and a sensor whose calibration is not determined by its record is exported, corrected "
            "and sent anyway (without it such a sensor is left out and named)",
        )
        self.buttons = {"calibration": button(gui, "calibration.json", on.do_export_calibration, engine=False)}
        for note in formats.load_entry_points().notes:  # one button per registered format (magcal.output.formats)
            print(f"magcal-workbench: {note.text}", file=sys.stderr)
        for fmt, spec in formats.EXPORT_FORMATS.items():
            self.buttons[fmt] = button(gui, spec.button, partial(on.do_export_format, fmt=fmt), engine=False)
        self.buttons["csv"] = button(gui, "Corrected CSV (magcal apply)", on.do_export_csv, engine=False)
        self.buttons["parquet"] = button(gui, "Corrected Parquet", on.do_export_parquet, engine=False)
        self.buttons["mask"] = button(gui, "Raw data + fit mask (CSV)", on.do_export_mask, engine=False)
        self.buttons["all"] = button(gui, "Export all (.zip)", on.do_export_all, engine=False, color="blue")
        self.info = gui.add_markdown("")
        self.send_title = gui.add_markdown(
            "**Send to vehicle** (the live source's MAVLink connection): the first click reads the vehicle's "
            "values and shows old -> new; *Confirm* writes them and reads every one back.",
            visible=False,
        )
        self.firmware = widgets.dropdown(
            "Vehicle firmware", FIRMWARES, initial_value=FIRMWARES[0], visible=False, hint="ArduPilot or PX4"
        )
        self.btn_send = button(gui, "Send to vehicle", on.do_send_preview, engine=False, visible=False)
        self.btn_confirm = button(
            gui, "Confirm: write to the vehicle", on.do_send_confirm, engine=False, visible=False, color="red"
        )
        self.btn_cancel = button(gui, "Cancel", on.do_send_cancel, engine=False, visible=False)
        self.send_info = gui.add_markdown("", visible=False)

    def refresh(self, has_calibration: bool, mavlink: bool, pending: bool) -> None:
        """Enable the buttons with a calibration; show *Send to vehicle* for a MAVLink source, *Confirm* and
        *Cancel* while a preview waits."""
        for b in self.buttons.values():
            b.disabled = not has_calibration
        for w in (self.send_title, self.firmware, self.btn_send, self.send_info):
            w.visible = mavlink
        self.btn_send.disabled = not has_calibration
        self.btn_confirm.visible = self.btn_cancel.visible = mavlink and pending


class Exporting(PagePart):
    """The Export section's actions (``do_*``, found by :meth:`magcal_workbench.app.Workbench._actions`).

    Handed what it uses.

    Parameters
    ----------
    ctrl, panels : callable
        Getters: the open data's :class:`~magcal_workbench.controller.Controller` and the
        :class:`~magcal_workbench.panels.Panels` (made after this part).
    handle : callable
        ``handle(func, event)``: runs a widget's callback through the page's error handler
        (:meth:`magcal_workbench.app.Workbench.handle`).
    livectl : magcal_workbench.livecontrol.LiveControl
        The live session's control: the sources offered, whether one runs, the chosen source's URL.
    downloads : magcal_workbench.downloads.Downloads
        Sends the exported files.
    values : magcal_workbench.checks.PageValues
        What each input widget may send (checked before it is read).
    store : magcal_workbench.session.SessionStore or None
        The sessions' folder (the vehicle's values are backed up in the session's folder), None without one.
    ui : magcal_workbench.uiqueue.UiQueue
        The page's thread: a job's result is shown through it.
    """

    def __init__(self, *, ctrl, panels, handle, livectl, downloads, values, store, ui) -> None:
        self._ctrl, self._panels = ctrl, panels
        self.handle, self.livectl, self.downloads, self.values = handle, livectl, downloads, values
        self.store, self.ui = store, ui
        self.section: ExportSection | None = None
        #: The previewed send: url, firmware, values, and when (the Confirm click writes only these).
        self._pending: dict | None = None
        self._lock = threading.Lock()

    # --- wiring --------------------------------------------------------------------------------------------
    def attach(self, section: ExportSection, live_source) -> None:
        """Keep ``section`` in step: with the live source's choice (``live_source``, a dropdown) and the data."""
        self.section = section
        live_source.on_update(lambda event: self.handle(lambda e: self.refresh(), event))
        self.refresh()

    @action(name="refresh_export")
    def refresh(self) -> None:
        if self.section is None:
            return
        with self._lock:
            pending = self._pending is not None
        self.section.refresh(self.ctrl.calibration is not None, self.mavlink_chosen(), pending)

    def mavlink_chosen(self) -> bool:
        """Whether the Live source the page shows is a MAVLink source the server offers."""
        try:
            label = self.panels.live_source.value
        except AttributeError:  # the panels are being made
            return False
        if not isinstance(label, str) or not ("MAVLink" in label or label.startswith("allowed:")):
            return False  # decided without listing the sources (serial ports, recordings) on every refresh
        chosen = next((s for s in self.livectl.menu.offered() if s.label == label), None)
        if chosen is None:
            return False
        if chosen.kind == "url":  # a source the command line allowed: MAVLink when its URL says so
            query = urllib.parse.parse_qs(urllib.parse.urlsplit(chosen.target).query, keep_blank_values=True)
            return "mavlink" in query or query.get("format", [""])[-1].lower() == "mavlink"
        return chosen.mavlink

    # --- the files ---------------------------------------------------------------------------------------------
    def _calibration(self):
        """The calibration as its downloaded JSON holds it, and that JSON's bytes."""
        ctrl = self.ctrl
        if ctrl.calibration is None:
            raise MagcalError("nothing to export yet: run a fit first")
        content = bundle.calibration_bytes(ctrl.calibration)
        return bundle.calibration_from_bytes(content), content

    def _data_file(self, folder):
        """The data file the session works on (what ``magcal apply`` reads), or magcal's CSV of the data."""
        ctrl = self.ctrl
        path = ctrl.state.data_path
        if path and os.path.isfile(path):
            return path
        out = os.path.join(folder, "data.csv")
        with open(out, "wb") as fh:
            fh.write(canonical_csv(ctrl.dataset))
        return out

    def _send(self, event, name, content, notes=()):
        self.downloads.send(event, name, content)
        said = f"exported {safe_code(name)} ({len(content):,} bytes)"
        if notes:
            said += "".join(f"  \n- {safe_text(hide_paths(n), 400)}" for n in notes)
        self._say(said)

    def _say(self, text):
        if self.section is not None:
            self.section.info.content = text
        self.ctrl.say(text)

    @action
    def do_export_calibration(self, event):
        _, content = self._calibration()
        self._send(event, bundle.CALIBRATION_FILE, content)

    @action
    def do_export_format(self, event, fmt):
        """The file of the export format ``fmt`` (:data:`magcal.output.formats.EXPORT_FORMATS`)."""
        calibration, _ = self._calibration()
        content, result = bundle.parameter_bytes(calibration, fmt, force=self._forced())
        said = [n for n in result.notes if _refusal(n)] + [f"dropped: {d}" for d in result.dropped]
        self._send(event, formats.get_format(fmt).file_name, content, said)

    def _forced(self) -> bool:
        """The Force box: what the firmware cannot hold left out, sensors not determined applied anyway."""
        return bool(self.section.force.value) if self.section is not None else False

    def _export_corrected(self, event, kind):
        calibration, _ = self._calibration()
        with tempfile.TemporaryDirectory(prefix="magcal-page-export-") as folder:
            content, notes = bundle.corrected_bytes(calibration, self._data_file(folder), kind, force=self._forced())
        self._send(event, bundle.CORRECTED_FILES[kind], content, notes)

    @action
    def do_export_csv(self, event):
        self._export_corrected(event, "csv")

    @action
    def do_export_parquet(self, event):
        self._export_corrected(event, "parquet")

    @action
    def do_export_mask(self, event):
        calibration, _ = self._calibration()
        ctrl = self.ctrl
        content, notes = bundle.raw_mask_bytes(calibration, ctrl.dataset, ctrl.state.kept)
        self._send(event, bundle.MASK_FILE, content, notes)

    @action
    def do_export_all(self, event):
        calibration, _ = self._calibration()
        ctrl = self.ctrl
        session, effects_files = session_for_download(ctrl.state)
        what = "the workbench session (mask, model, history)"
        if effects_files:
            what += f"; the effects files it names, not included: {', '.join(effects_files)}"
        with tempfile.TemporaryDirectory(prefix="magcal-page-export-") as folder:
            content, readme = bundle.export_all(
                calibration,
                dataset=ctrl.dataset,
                data_path=self._data_file(folder),
                kept=ctrl.state.kept,
                extra_files={SESSION_FILE: (session, what)},
            )
        content = without_paths(content)
        refused = [hide_paths(line.strip()) for line in readme if "not written" in line]
        self._send(event, bundle.BUNDLE_FILE, content, refused)

    # --- send to vehicle -------------------------------------------------------------------------------------
    def _target(self):
        """``(url, firmware, values, refused)`` the page would send now: the chosen MAVLink source (built on the
        server from the offered list, :meth:`magcal_workbench.livecontrol.LiveControl.page_url`), the checked
        firmware, the parameters ``magcal export`` writes for it, and what it says of the sensors not determined
        (left out, or sent with Force)."""
        if not self.mavlink_chosen():
            raise MagcalError("choose a MAVLink live source (Files tab, Live source) to send to a vehicle")
        if self.livectl.running:
            raise MagcalError("stop the live session first: it holds the vehicle's connection")
        url = self.livectl.page_url()
        firmware = self.values.check(self.section.firmware)
        calibration, _ = self._calibration()
        content, result = bundle.parameter_bytes(calibration, firmware, force=self._forced())
        refused = [n for n in result.notes if _refusal(n)]
        return url, firmware, values_to_send(content.decode("utf-8"), firmware), refused

    def _backup_folder(self) -> Path:
        sid = self.ctrl.session_id
        if self.store is not None and sid:
            return Path(self.store.folder(sid))
        return recording_folder(self.store)

    @action
    def do_send_preview(self, event):
        """First click: read the vehicle's current values (nothing is written) and show old -> new."""
        url, firmware, values, refused = self._target()

        def job():
            report = send_parameters(url, values, firmware, confirm=lambda r: False)
            with self._lock:
                self._pending = {"url": url, "firmware": firmware, "values": values, "at": time.monotonic()}
            text = report_markdown(report, f"Read from the vehicle: {len(values)} parameter(s) to write")
            text += "".join(f"\n\n**{safe_text(hide_paths(n), 400)}**" for n in refused)
            self.ui.post(lambda: self._show_send(text))
            self.ctrl.say("read the vehicle's values: check old -> new (Files tab), then press Confirm to write them")

        self.ctrl.run_job("read the vehicle's parameters", job)

    @action
    def do_send_cancel(self, event):
        with self._lock:
            self._pending = None
        self._show_send("_Nothing was written._")

    @action
    def do_send_confirm(self, event):
        """Second click: write what was previewed, if nothing changed since, and show the read-back."""
        url, firmware, values, _ = self._target()
        with self._lock:
            pending, self._pending = self._pending, None
        if (
            pending is None
            or (pending["url"], pending["firmware"], pending["values"]) != (url, firmware, values)
            or time.monotonic() - pending["at"] > PREVIEW_LIFETIME_S
        ):
            self.refresh()
            raise MagcalError(
                "the source, the firmware or the calibration changed since the vehicle was read (or it was "
                "long ago): press Send to vehicle again to see old -> new"
            )
        backup = default_backup_path(self._backup_folder(), firmware)
        os.makedirs(os.path.dirname(backup), exist_ok=True, mode=0o700)

        def job():
            report = send_parameters(url, values, firmware, backup_path=backup)
            title = (
                f"Written and read back: all {len(values)} parameter(s) equal"
                if report.ok
                else f"NOT all written: {len(report.failed)} parameter(s) failed"
            )
            self.ui.post(lambda: self._show_send(report_markdown(report, title)))
            self.ctrl.say(
                f"sent {len(values)} parameter(s) to the vehicle: "
                + ("every value read back equal" if report.ok else f"{len(report.failed)} FAILED (Files tab)")
            )

        self.ctrl.run_job("send to the vehicle", job)

    def _show_send(self, text: str) -> None:
        if self.section is not None:
            self.section.send_info.content = text
        self.refresh()
