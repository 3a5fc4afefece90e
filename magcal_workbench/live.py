"""The live view: an instrument's samples drawn as they arrive, with the coverage and the fit following them.

``magcal-workbench --live SOURCE`` (or the Files tab's *Live source*) opens a :class:`magcal.data.live.LiveSession`:
the source is read in the session's thread and every sample is appended to a CSV recording (flushed to disk at
least every second). :class:`LiveView` then, in a thread of its own,

* redraws the raw cloud as it grows (at most :data:`DRAW_INTERVAL_S` apart), through the same
  :class:`~magcal_workbench.scene.SceneView` as a file, so every browser watching sees it;
* draws per sensor a coverage sphere: the directions the field has taken in the sensor frame (green), the ones
  still missing (grey) and the centre of the largest gap (orange), from :func:`magcal.checks.coverage.direction_map`,
  with the engine's advice on where to turn next;
* refits (:func:`magcal.calibrate`, maximum likelihood) in a background thread as samples accumulate, showing the
  residual RMS against the noise floor and the parameters' standard errors, and says when coverage and residuals
  suffice (:func:`magcal.checks.coverage.live_sufficient`).

Pause keeps the source read but drops what arrives; Stop closes the recording and opens it like any file, so the
Calibrate and Model tabs work on what was recorded, and says how many samples it holds and where (inside the session
folder: ``recordings/live-....csv``, never the server's path). A recording that cannot be written (a full disk) stops
with every sample of its last flush kept (:class:`magcal.data.live.Recorder`); the page says so, "the disk is full"
where it is, until Stop (:attr:`LiveView.recording_problem`). The physics (coverage, fit, noise) is the engine's; this
module schedules and draws.
"""

from __future__ import annotations

import datetime as _dt
import os
import threading
import time
import urllib.parse
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

import magcal
from magcal.checks.coverage import direction_map, live_sufficient
from magcal.core.errors import MagcalError
from magcal.data.live import LiveSession, serial_ports
from magcal.data.simulation import PRESETS
from magcal.geometry.shape import FieldShape

from . import scene as scn
from .checks import number_problem
from .markup import clean_text, hide_paths, safe_code, safe_text

#: Shortest time between two scene updates while samples arrive, s.
DRAW_INTERVAL_S = 0.2
#: Refit when the samples have grown by this factor since the last fit (or :data:`REFIT_INTERVAL_S` has passed).
REFIT_GROWTH = 1.15
#: Longest time between two refits while samples arrive, s.
REFIT_INTERVAL_S = 3.0
#: Fewest samples before the first fit.
MIN_FIT_SAMPLES = 60
#: Cells of a coverage sphere.
COVERAGE_CELLS = 300
#: Radius of a coverage sphere in scene units (the corrected cloud has radius 1).
COVERAGE_RADIUS = 0.55
VISITED_RGB = (60, 170, 90)
MISSING_RGB = (205, 205, 205)
NEXT_RGB = (240, 140, 20)
#: Bounds of what the page may ask of a simulated source (within :mod:`magcal.data.live`'s own): samples per
#: second, samples simulated, play speed (rate x speed at most 20 000 samples a second).
PAGE_RATE_HZ = (1.0, 1000.0)
PAGE_SAMPLES = (100, 100_000)
PAGE_SPEED = (0.1, 20.0)
#: Ports the page may name for a UDP or TCP source on 127.0.0.1 (not the privileged ones).
PAGE_PORT = (1024, 65535)
#: Serial speeds offered.
BAUDS = ("115200", "57600", "38400", "19200", "9600", "230400", "460800", "921600")
#: Units offered for text lines.
LINE_UNITS = ("nT", "uT", "mG", "G")
#: Longest Columns text the page may send (e.g. ``s1x,s1y,s1z,t``).
COLUMNS_CHARS = 200
#: Longest line template the page may send (e.g. ``Magnetometer reading: [{x}, {y}, {z}]``).
TEMPLATE_CHARS = 200


def default_recording_path(folder) -> Path:
    """A new recording's path in ``folder``: ``live-YYYYmmdd-HHMMSS.csv`` (a counter appended if it exists)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    path = folder / f"live-{stamp}.csv"
    k = 1
    while path.exists():
        path = folder / f"live-{stamp}-{k}.csv"
        k += 1
    return path


class LiveFit:
    """The figures of the latest live fit (what the panel shows)."""

    def __init__(self, result, n_samples: int):
        self.result = result
        self.calibration = result.calibration
        self.n_samples = int(n_samples)
        self.rms_nT = float(result.rms_nT)
        self.floor_nT = float(result.total_field_floor_nT)
        self.noise_nT = float(result.noise_nT)
        self.noise_source = result.noise_source
        fit = result.fit
        sd = (
            np.sqrt(np.clip(np.diag(fit.covariance), 0.0, None))
            if fit is not None and fit.covariance is not None
            else None
        )
        names = fit.param_names if fit is not None else []
        #: Largest standard error of a bias component (nT) and of a C^-1 entry, over the sensors.
        self.bias_sd_nT = self._largest(sd, names, "_bias_")
        self.cinv_sd = self._largest(sd, names, "_Cinv")

    @staticmethod
    def _largest(sd, names, key):
        if sd is None:
            return None
        vals = [s for s, n in zip(sd, names) if key in n and np.isfinite(s)]
        return float(max(vals)) if vals else None


class LiveView:
    """A live session drawn in the workbench.

    Its threads (the source's loop, the refits) change nothing on the page themselves: every drawing and panel
    update is handed to the page's thread (``ui``, :class:`magcal_workbench.uiqueue.UiQueue`).

    Parameters
    ----------
    url : str
        The source (:func:`magcal.data.live.open_source`).
    path : str or os.PathLike
        The recording (a new file).
    server : viser.ViserServer
        Where the coverage spheres are drawn.
    ui : magcal_workbench.uiqueue.UiQueue
        The page's thread.
    redraw : callable
        Redraws the scene (which asks :meth:`scene_model`).
    refresh : callable
        Shows the live session's state in the panels.
    reference_nT : callable, optional
        The reference total field (nT) the page holds now (typed, or IGRF at a typed location), or None: the live
        fits use it, else they fit the field's magnitude.
    name : str, optional
        The recording as the page names it (default its file name; :func:`shown_name`).
    """

    def __init__(self, url: str, path, server, ui, redraw, refresh, reference_nT=None, name=None):
        self._reference_nT = reference_nT or (lambda: None)
        self._server = server
        self._ui = ui
        self._redraw = redraw
        self._refresh = refresh
        self.url = url
        self.path = Path(path)
        #: The recording as the page names it (:func:`shown_name`: inside the session folder, or its file name).
        self.name = name or self.path.name
        self.session = LiveSession(url, self.path)
        self.maps: list = []
        self.fit: LiveFit | None = None
        self.fit_error: str | None = None
        self.verdict = (False, "waiting for samples")
        self.n_drawn = 0
        self.last_draw_monotonic = None  # when the scene last took new samples (for the latency benchmark)
        self.draw_log: list = []  # (monotonic time of the update, samples drawn)
        self._dataset: Any = None  # the session's Dataset once samples arrived
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._fitting = False
        self._last_fit_t = 0.0
        self._fit_tried = 0
        self._coverage_nodes: dict = {}
        self.stopped = False
        self._thread = threading.Thread(target=self._loop, name="workbench-live", daemon=True)
        self._thread.start()

    # --- state ------------------------------------------------------------------------------------------------
    @property
    def n_samples(self) -> int:
        return self.session.n_samples

    @property
    def active(self) -> bool:
        """True until :meth:`stop` (the view owns the scene)."""
        return not self.stopped

    def dataset(self):
        with self._lock:
            return self._dataset

    # --- the loop -------------------------------------------------------------------------------------------
    def _loop(self) -> None:
        ended_said = False
        while not self._stop.wait(DRAW_INTERVAL_S):
            try:
                if not self.tick():
                    ds = self.dataset()
                    if ds is not None:
                        self._maybe_refit(ds, idle=True)  # the last samples get their fit too
                if not self.session.running and not ended_said:
                    ended_said = True
                    self._ui.post(self._refresh)  # the source ended or failed: say so
            except Exception as exc:  # the live view must not die silently
                self.fit_error = f"{type(exc).__name__}: {exc}"
                self._ui.post(self._refresh)

    def tick(self) -> bool:
        """Take the samples received since the last call: redraw, refresh the coverage, maybe refit. Returns
        whether anything was new."""
        n = self.session.n_samples
        if n == self.n_drawn or self.stopped:
            return False
        ds = self.session.dataset()
        if ds is None:
            return False
        with self._lock:
            self._dataset = ds
        fit = self.fit
        shapes = [None] * ds.n_sensors
        if fit is not None:
            shapes = [self._shape_of(fit.calibration.sensors[s]) for s in range(ds.n_sensors)]
        self.maps = [direction_map(ds.readings_nT[s], COVERAGE_CELLS, shape=shapes[s]) for s in range(ds.n_sensors)]
        self.verdict = live_sufficient(
            self.maps, None if fit is None else fit.rms_nT, None if fit is None else fit.floor_nT
        )

        def draw():  # on the page's thread; this one waits for it
            self._redraw()
            self.draw_coverage()
            self.n_drawn = ds.n_samples
            self.last_draw_monotonic = time.monotonic()
            self.draw_log.append((self.last_draw_monotonic, self.n_drawn))
            del self.draw_log[:-1000]
            self._refresh()

        self._ui.run(draw)
        self._maybe_refit(ds)
        return True

    @staticmethod
    def _shape_of(sensor):

        return FieldShape(
            centre_nT=np.asarray(sensor.bias_nT, float),
            cinv=np.asarray(sensor.cinv, float),
            field_nT=float("nan"),
            source="fit",
        )

    def _maybe_refit(self, ds, idle: bool = False) -> None:
        """Start a refit in the background when the samples have grown enough since the last one, or some time
        has passed, or (``idle``) nothing new arrives and the last fit has not seen everything."""
        if self._fitting or ds.n_samples < MIN_FIT_SAMPLES:
            return
        newer = self.fit is None or ds.n_samples > self.fit.n_samples
        if idle and self.fit_error is not None and self._fit_tried == ds.n_samples:
            return  # that very data already failed to fit: wait for more
        last = self.fit.n_samples if self.fit is not None else self._fit_tried
        grown = ds.n_samples >= REFIT_GROWTH * last
        waited = time.monotonic() - self._last_fit_t
        due = newer and (waited >= REFIT_INTERVAL_S or (idle and waited >= DRAW_INTERVAL_S))
        if not (grown or due):
            return
        self._fitting = True
        self._fit_tried = ds.n_samples
        threading.Thread(target=self._refit, args=(ds,), name="workbench-live-fit", daemon=True).start()

    def _refit(self, ds) -> None:
        try:
            # weak coverage early on is the point of the live view: its notes stay in result.notes, unsaid
            result = magcal.calibrate(
                ds, method="ml", mode="total_field", warn=False, reference_total_nT=self._reference_nT()
            )
            self.fit = LiveFit(result, ds.n_samples)
            self.fit_error = None
            self.verdict = live_sufficient(self.maps, self.fit.rms_nT, self.fit.floor_nT)
        except MagcalError as exc:
            self.fit_error = str(exc)
        except Exception as exc:  # a fit that fails on partial data must not end the live view
            self.fit_error = f"{type(exc).__name__}: {exc}"
        finally:
            self._last_fit_t = time.monotonic()
            self._fitting = False
        if not self.stopped:
            self._ui.run(lambda: (self._redraw(), self._refresh()))

    # --- what is drawn ----------------------------------------------------------------------------------------
    def scene_model(self, options: dict) -> scn.SceneModel | None:
        """The scene of the samples received so far (raw cloud; corrected by the latest fit), or None before any."""
        ds = self.dataset()
        if ds is None:
            return None
        fit = self.fit
        corrected = residual = None
        F = float(np.median(np.linalg.norm(ds.readings_nT, axis=2)))
        if fit is not None:
            # the fit is of this recording (grown since): any record-only terms apply, silently
            corrected = fit.calibration.correct(ds, record_terms="apply", force=True)
            residual = fit.calibration.total_field_residuals(ds, corrected=corrected, record_terms="apply")
            if fit.calibration.reference_total_nT:
                F = float(fit.calibration.reference_total_nT)
        else:
            residual = np.linalg.norm(ds.readings_nT, axis=2) - F
        cal = None if fit is None else fit.calibration
        views = [
            scn.SensorView(
                sensor=s,
                raw_nT=ds.readings_nT[s],
                corrected_nT=None if corrected is None else corrected[s],
                residual_nT=residual[s],
                cinv=None if cal is None else cal.sensors[s].cinv,
                bias_nT=None if cal is None else cal.sensors[s].bias_nT,
                R=None if cal is None else cal.sensors[s].R,
            )
            for s in range(ds.n_sensors)
        ]
        return scn.SceneModel(
            sensors=views,
            n_sensors=ds.n_sensors,
            field_nT=F,
            kept=np.ones(ds.n_samples, bool),
            floor_nT=None if fit is None else fit.floor_nT,
            baseline_m=ds.baseline_m,
            all_calibrations=[] if cal is None else [(c.cinv, c.R) for c in cal.sensors],
            **options,
        )

    def draw_coverage(self) -> None:
        """One coverage sphere per sensor, where its corrected cloud is drawn: visited cells green, missing grey,
        the centre of the largest gap orange."""
        scene = self._server.scene
        n = len(self.maps)
        with self._server.atomic():
            for s, m in enumerate(self.maps):
                centre = scn.group_offset(s, n) + [scn.PAIR_OFFSET, 0, 0]
                colors = np.where(
                    m.visited[:, None], np.array(VISITED_RGB, np.uint8), np.array(MISSING_RGB, np.uint8)
                ).astype(np.uint8)
                pts = (COVERAGE_RADIUS * m.cells + centre).astype(np.float32)
                name = f"/live/s{s + 1}/coverage"
                handle = self._coverage_nodes.get(name)
                if handle is None:
                    self._coverage_nodes[name] = scene.add_point_cloud(
                        name,
                        pts,
                        colors,
                        point_size=0.05,
                        point_shape="circle",
                        precision="float32",
                        point_shading="flat",
                    )
                else:
                    handle.colors = colors
                d = m.next_direction
                mark = f"/live/s{s + 1}/next"
                old = self._coverage_nodes.pop(mark, None)
                if old is not None:
                    old.remove()
                if d is not None and not m.enough:
                    seg = np.array([[centre, centre + 1.3 * COVERAGE_RADIUS * d]], np.float32)
                    self._coverage_nodes[mark] = scene.add_line_segments(
                        mark, seg, colors=NEXT_RGB, thickness=6.0, thickness_units="screen"
                    )
                label = f"/live/s{s + 1}/label"
                old = self._coverage_nodes.pop(label, None)
                if old is not None:
                    old.remove()
                self._coverage_nodes[label] = scene.add_label(
                    label,
                    f"S{s + 1} directions {100 * m.fraction:.0f} %",
                    position=tuple(centre + [0, 0, -1.25]),
                    anchor="top-center",
                )

    def clear_coverage(self) -> None:
        for handle in self._coverage_nodes.values():
            handle.remove()
        self._coverage_nodes.clear()

    def status_markdown(self) -> str:
        """The Files tab's live panel: source, samples, recording, coverage, fit, verdict."""
        s = self.session
        state = "stopped" if self.stopped else ("paused" if s.paused else ("receiving" if s.running else "ended"))
        lines = [
            f"**Live** {safe_code(self.url)}: {state}; {s.n_samples} samples received, {s.n_recorded} "
            f"on disk in {safe_code(self.name)}"
        ]
        stats = s.source.stats
        if stats.n_bad:
            lines.append(
                f"- {stats.n_bad} lines or messages could not be read (last: {safe_text(stats.last_bad or '', 120)})"
            )
        if stats.n_skipped:
            lines.append(
                f"- {stats.n_skipped} lines were not data (a banner, comments; last: "
                f"{safe_text(stats.last_skipped or '', 120)})"
            )
        if getattr(s.source, "connected", True) is False:
            lines.append("- **the port was lost**: reopening it (the recording goes on)")
        if stats.n_reconnects:
            lines.append(
                f"- the port was reopened {stats.n_reconnects} time(s) ({safe_text(stats.last_disconnect or '', 120)})"
            )
        if s.error:
            what = "the recording stopped" if self.recording_failed else "the source stopped"
            lines.append(f"- **{what}:** {safe_text(self._shown(s.error), 300)}")
        for i, m in enumerate(self.maps):
            who = f"sensor {i + 1}: " if len(self.maps) > 1 else ""
            lines.append(f"- {who}{safe_text(m.summary(), 200)}")
        if self.maps:
            worst = min(self.maps, key=lambda m: m.fraction)
            lines.append(f"- **next:** {safe_text(worst.advice(), 300)}")
        fit = self.fit
        if fit is not None:
            sd = []
            if fit.bias_sd_nT is not None:
                sd.append(f"bias +-{fit.bias_sd_nT:.3g} nT")
            if fit.cinv_sd is not None:
                sd.append(f"C^-1 entries +-{fit.cinv_sd:.2g}")
            ref = fit.calibration.reference_total_nT
            if ref and not fit.calibration.reference_fitted:
                lines.append(f"- reference field {ref:.1f} nT, as the Calibrate tab gives it")
            lines.append(
                f"- fit on {fit.n_samples} samples: RMS **{fit.rms_nT:.3g} nT** (noise floor "
                f"{fit.floor_nT:.3g} nT, noise from {fit.noise_source}); standard errors "
                + (", ".join(sd) or "not available")
            )
        elif self.fit_error:
            lines.append(f"- no fit yet: {safe_text(self.fit_error, 300)}")
        ok, why = self.verdict
        lines.append(("**" if ok else "") + safe_text(why, 300) + ("**" if ok else ""))
        return "  \n".join(lines)

    def _shown(self, text: str) -> str:
        """``text`` as the page may show it: the recording named as the page names it, any other absolute path
        cut to its last part (:func:`magcal_workbench.markup.hide_paths`)."""
        return hide_paths(str(text).replace(os.fspath(self.path), self.name))

    @property
    def recording_failed(self) -> bool:
        """Whether the recording stopped because it could not be written (the session's error is the recorder's,
        which names the recording first: :class:`magcal.data.live.Recorder`)."""
        error = self.session.error
        return bool(error) and error.startswith(os.fspath(self.path) + ":")

    @property
    def recording_problem(self) -> str | None:
        """The page's lasting warning while the recording has stopped for want of a disk (markdown, escaped), or
        None: shown until Stop, whatever other message comes meanwhile."""
        if self.stopped or not self.recording_failed:
            return None
        s = self.session
        then = (
            f"Stop opens the {s.n_recorded} samples on disk."
            if s.n_recorded
            else "Nothing is on disk: Stop has nothing to open."
        )
        return f"**The live recording stopped:** {safe_text(self._shown(s.error), 400)}. {then}"

    def stop_summary(self) -> str:
        """What Stop says (markdown, escaped): how many samples the recording holds and where, and why it stopped
        early when it did."""
        s = self.session
        text = f"recorded {s.n_recorded} samples in {safe_code(self.name)}"
        if s.n_samples > s.n_recorded:
            text += f" of the {s.n_samples} received"
        if self.recording_failed:
            text += f"  \n**The recording had stopped early:** {safe_text(self._shown(s.error), 400)}"
        return text

    # --- control ----------------------------------------------------------------------------------------------
    def pause(self) -> None:
        self.session.pause()

    def resume(self) -> None:
        self.session.resume()

    def stop(self):
        """Stop the source, close the recording and return ``(dataset, content)`` of the file on disk, or raise
        :class:`MagcalError` when it holds no sample."""
        self.stopped = True
        self._stop.set()
        self.session.stop()
        self._thread.join(5.0)
        self.clear_coverage()
        s = self.session
        if s.n_recorded == 0:
            if self.recording_failed:
                raise MagcalError(f"{self._shown(s.error)}; nothing to open")
            if s.n_samples:
                raise MagcalError(f"{self.name}: none of the {s.n_samples} samples received was recorded")
            raise MagcalError(f"{self.name}: nothing was recorded (no sample arrived from {self.url})")
        return self.path


@dataclass(frozen=True)
class PageSource:
    """One source the server offers the page: what the dropdown shows and what it opens.

    ``kind`` is ``"sim"`` (a preset, ``target`` its name), ``"file"`` (a recording in the session folder, played
    again; ``target`` its path), ``"serial"`` (a port found on this machine, ``target`` its device), ``"udp"`` or
    ``"tcp"`` (on 127.0.0.1, the page gives the port) or ``"url"`` (a source the command line allowed,
    ``--live-allow``, opened as given).
    """

    label: str
    kind: str
    target: str = ""
    mavlink: bool = False


class SourceMenu:
    """The live sources the page may start: a list the server makes, never a URL the page sends.

    The page chooses an entry of :meth:`offered` and bounded options (rate, samples, speed, port, baud, columns,
    units); :meth:`url` builds the source's URL from them on the server. Offered: the simulated presets (bounded:
    :data:`PAGE_RATE_HZ`, :data:`PAGE_SAMPLES`, :data:`PAGE_SPEED`); when served to this machine only, also the
    serial ports found (:func:`serial_ports`), UDP and TCP on 127.0.0.1 (a port in :data:`PAGE_PORT`), and the
    recordings in the session folder's ``recordings`` played again; in every case the sources the command line
    allowed (``--live-allow URL``, e.g. ``udp://0.0.0.0:14550?mavlink``). A path, a program or another address
    typed in the page is never opened: pymavlink runs a "device" that looks like a program as a child process,
    so no page-given text reaches pymavlink or pyserial.

    Parameters
    ----------
    local : bool
        The workbench serves this machine only.
    recordings : callable
        Returns the session folder's ``recordings`` folder, or None (no sessions: no file is offered).
    allowed_urls : sequence of str
        Sources the command line allowed (``--live-allow``).
    """

    def __init__(self, local: bool, recordings, allowed_urls=()):
        self.local = bool(local)
        self.recordings = recordings
        self.allowed_urls = tuple(str(u) for u in allowed_urls)

    def offered(self) -> list[PageSource]:
        """The sources the page may start now (serial ports and recordings listed afresh)."""
        out = [PageSource(f"simulated {name}", "sim", name) for name in PRESETS]
        if self.local:
            for device in serial_ports():
                out.append(PageSource(f"serial {device} (text lines)", "serial", device))
                out.append(PageSource(f"serial {device} (MAVLink)", "serial", device, mavlink=True))
            out += [
                PageSource("UDP MAVLink on 127.0.0.1 (port below)", "udp", "127.0.0.1", mavlink=True),
                PageSource("UDP text lines on 127.0.0.1 (port below)", "udp", "127.0.0.1"),
                PageSource("TCP text lines from 127.0.0.1 (port below)", "tcp", "127.0.0.1"),
            ]
            folder = self.recordings()
            if folder is not None and Path(folder).is_dir():
                files = sorted(Path(folder).glob("*.csv"), key=lambda p: p.name)
                out += [PageSource(f"replay recordings/{f.name}", "file", str(f)) for f in files[-50:] if f.is_file()]
        out += [PageSource(f"allowed: {url}", "url", url) for url in self.allowed_urls]
        return out

    def labels(self) -> tuple:
        """The dropdown's choices (what :class:`~magcal_workbench.checks.PageValues` lets the page send)."""
        return tuple(s.label for s in self.offered())

    def url(
        self,
        label: str,
        rate_hz: float = 50.0,
        n_samples: int = 3000,
        speed: float = 1.0,
        port: int = 14550,
        baud: str = BAUDS[0],
        columns: str = "x,y,z",
        units: str = LINE_UNITS[0],
        template: str = "",
    ) -> str:
        """The URL of the offered source ``label`` with the page's options, checked against their bounds.

        A ``template`` (text lines, :mod:`magcal.data.lineformats`) replaces ``columns`` when it is not blank; like the
        columns, it is only ever a value of the URL's ``template`` parameter.

        Raises
        ------
        MagcalError
            ``label`` is not offered now, or an option is outside its bounds.
        """
        chosen = next((s for s in self.offered() if s.label == label), None)
        if chosen is None:
            raise MagcalError(
                f"{safe_text(str(label), 80)}: not a source this workbench offers; choose one from the list "
                "(other sources are started from the command line: magcal-workbench --live SOURCE)"
            )

        def bounded(name, value, lo, hi, kind=float):
            why = number_problem(value, lo, hi, integral=kind is int)  # a port or a count: never truncated
            if why is not None:
                raise MagcalError(f"{name}: {why}")
            return int(value) if kind is int else float(value)

        if chosen.kind == "url":
            return chosen.target
        if chosen.kind in ("sim", "file"):
            query = {
                "rate": f"{bounded('Rate', rate_hz, *PAGE_RATE_HZ):g}",
                "speed": f"{bounded('Speed', speed, *PAGE_SPEED):g}",
            }
            if chosen.kind == "sim":
                query["n"] = str(bounded("Samples", n_samples, *PAGE_SAMPLES, kind=int))
            return f"sim://{urllib.parse.quote(chosen.target)}?{urllib.parse.urlencode(query)}"
        query = {}
        if chosen.mavlink:
            query["mavlink"] = "1"
        else:
            cols = str(columns).strip()
            tmpl = str(template or "").strip()
            if len(tmpl) > TEMPLATE_CHARS or not tmpl.isprintable():
                raise MagcalError(
                    f"Template: one line of at most {TEMPLATE_CHARS} characters, e.g. x={{x}} y={{y}} z={{z}}"
                )
            if tmpl:
                query["template"] = tmpl
            elif not cols or len(cols) > COLUMNS_CHARS:
                raise MagcalError(
                    f"Columns: give the columns of a line, e.g. x,y,z (at most {COLUMNS_CHARS} characters)"
                )
            else:
                query["columns"] = cols
            if units not in LINE_UNITS:
                raise MagcalError(f"Units: one of {', '.join(LINE_UNITS)}")
            query["units"] = units
        if chosen.kind == "serial":
            if str(baud) not in BAUDS:
                raise MagcalError(f"Baud: one of {', '.join(BAUDS)}")
            if os.path.isfile(chosen.target):  # a device, never a file (pymavlink would run an executable one)
                raise MagcalError(f"{clean_text(chosen.target, 80)} is a file, not a serial port")
            query["baud"] = str(baud)
            return f"serial://{urllib.parse.quote(chosen.target)}?{urllib.parse.urlencode(query)}"
        p = bounded("Port", port, *PAGE_PORT, kind=int)
        return f"{chosen.kind}://127.0.0.1:{p}?{urllib.parse.urlencode(query)}"


def shown_name(path, store) -> str:
    """How the page names a recording: its path inside the session folder (``recordings/live-....csv``), else its
    file name (where a file lives on the server is not the page's business)."""
    path = Path(path)
    if store is not None:
        try:
            return path.resolve().relative_to(Path(store.root).resolve()).as_posix()
        except (ValueError, OSError):
            pass
    return path.name


def recording_folder(store) -> Path:
    """Where a live recording goes by default: the session folder's ``recordings``, else the current folder."""
    if store is not None:
        return Path(store.root) / "recordings"
    return Path(os.getcwd())
