"""The workbench's live view: a simulated instrument streamed into a real server and a real page.

The source plays a lesson recording (a temperature effect hidden in it) faster than real time, so that Stop,
Diagnose and Add-and-refit have something to find. Every wait is bounded; only loopback addresses are used.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

import magcal
from magcal.checks.coverage import direction_map, live_sufficient
from magcal.data.simulation import PRESETS
from magcal.geometry.sphere import fibonacci_sphere

LESSON = Path(__file__).resolve().parents[2] / "assets" / "lessons" / "warm-sensor" / "data.csv"


def _wait(condition, timeout_s=60.0, step_s=0.1):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(step_s)
    return False


# --- the engine's direction map -------------------------------------------------------------------------------
@pytest.mark.parametrize("axis", [0, 1, 2])
@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_the_gap_of_a_half_sphere_is_named_and_pointed_at(axis, sign):
    """Samples on one hemisphere only: the largest gap lies at the other pole, the advice names that axis."""
    u = fibonacci_sphere(3000)
    seen = u[sign * u[:, axis] > 0.1]
    hard_iron = np.array([800.0, -500.0, 300.0])
    m = direction_map(48_000.0 * seen + hard_iron)
    d = m.next_direction
    assert d is not None and sign * d[axis] < -0.9
    assert 0.5 < m.fraction < 0.8 and not m.enough
    assert f"{'-' if sign > 0 else '+'}{'xyz'[axis]} axis" in m.advice()


def test_a_covered_sphere_is_enough_and_empty_data_are_not():
    m = direction_map(50_000.0 * fibonacci_sphere(2000))
    assert m.enough and m.fraction > 0.99 and "covered" in m.advice()
    empty = direction_map(np.zeros((0, 3)))
    assert empty.fraction == 0.0 and not empty.enough


@pytest.mark.parametrize("rms, floor, ok", [(3.1, 3.0, True), (9.0, 3.0, False), (None, 3.0, False)])
def test_live_sufficiency_needs_coverage_and_residuals_at_the_floor(rms, floor, ok):
    full = direction_map(50_000.0 * fibonacci_sphere(2000))
    verdict, why = live_sufficient([full, full], rms, floor)
    assert verdict is ok
    u = fibonacci_sphere(2000)
    half = direction_map(50_000.0 * u[u[:, 2] > 0])
    verdict, why = live_sufficient([full, half], rms, floor)
    assert not verdict and "sensor 2" in why


# --- the live view on a real server, no browser ----------------------------------------------------------------
def test_live_view_grows_fits_records_every_sample_and_opens_the_recording(bench, tmp_path):
    wb = bench()
    path = tmp_path / "rec.csv"
    live = wb.livectl.start(f"sim://{LESSON}?speed=40", path)
    sent = live.session.source
    assert _wait(lambda: not live.session.running and live.n_drawn == live.n_samples, 60)
    assert _wait(lambda: live.fit is not None and live.fit.n_samples == live.n_samples, 30)
    assert wb.ui.wait(30)  # the live threads hand their drawing to the page's thread: let it finish
    n = sent.stats.n_samples
    assert n == 1500 == live.n_samples
    # the scene shows every sample received, raw and corrected, and a coverage sphere per sensor
    clouds = wb.scene_view._clouds
    assert sorted(len(h.points) for h in clouds.values()) == [n] * 8
    assert all(f"/live/s{s}/coverage" in live._coverage_nodes for s in range(1, 5))
    assert "samples received" in wb.panels.live_status.content and "RMS" in wb.panels.live_status.content
    # the live fit is a real fit: its RMS is at most a few times the simulated 3 nT noise (a temperature effect
    # is hidden, so not at the floor)
    assert 2.5 < live.fit.rms_nT < 30.0
    rec = live.stop()
    assert magcal.read_csv(rec).n_samples == n
    # Stop opens the recording (the page's button does this in a job): the engine steps work on it
    from magcal_workbench.dataio import load_dataset

    ds, _ = load_dataset(rec, rec.name)
    wb.load(ds, rec.read_bytes(), rec.name, resume=False)
    assert wb.ctrl.dataset.n_samples == n and wb.live.active is False
    wb.ctrl.step_calibrate("ml")
    wb.ctrl.step_diagnose()
    assert wb.ctrl.diagnosis.candidates and wb.ctrl.diagnosis.candidates[0].effect.startswith("temperature")
    rms_before = wb.ctrl.residual_rms_nT()
    wb.ctrl.step_add(None)
    after = wb.ctrl.residual_rms_nT()
    assert after < 0.95 * rms_before and after < 1.05 * wb.ctrl.floor_nT()  # down to the noise floor


def test_four_quick_starts_while_a_slow_source_opens_leave_one_recording(bench, monkeypatch):
    """Start pressed four times while the source takes half a second to open: one live session, one
    recording, which Stop ends; the other presses say a session is running and leave no file."""
    import threading

    from magcal.data.live import LiveSession
    from magcal_workbench import live as wlive

    opened = []

    class SlowSession(LiveSession):
        def __init__(self, *args, **kwargs):
            time.sleep(0.5)  # a serial port or a socket that is slow to open
            opened.append(1)
            super().__init__(*args, **kwargs)

    monkeypatch.setattr(wlive, "LiveSession", SlowSession)
    wb = bench()
    folder = Path(wb.store.root) / "recordings"
    errors, barrier = [], threading.Barrier(4)

    def press():
        barrier.wait()
        try:
            wb.livectl.start("sim://chi2017?rate=200&n=2000")
        except magcal.MagcalError as exc:
            errors.append(str(exc))

    threads = [threading.Thread(target=press) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    assert len(opened) == 1 and len(errors) == 3 and all("running or starting" in e for e in errors)
    assert wb.livectl.running and len(list(folder.iterdir())) == 1
    assert _wait(lambda: wb.live.session.n_recorded > 0, 30)
    path = wb.live.stop()
    assert not wb.livectl.running and not wb.live.session.running
    assert [p.name for p in folder.iterdir()] == [path.name] and magcal.read_csv(path).n_samples > 0
    # once stopped, a new session may start
    wb.livectl.start("sim://chi2017?rate=200&n=200")
    assert len(list(folder.iterdir())) == 2
    wb.live.stop()


def _menu(tmp_path, local=True, allow=()):
    from magcal_workbench.live import SourceMenu

    folder = tmp_path / "recordings"
    folder.mkdir(exist_ok=True)
    return SourceMenu(local, lambda: folder, allow), folder


def test_the_page_is_offered_sources_and_the_server_builds_their_urls(tmp_path, monkeypatch):
    from urllib.parse import parse_qs, urlsplit

    from magcal.data.live import open_source
    from magcal_workbench import live as wlive

    monkeypatch.setattr(wlive, "serial_ports", lambda: ["/dev/ttyFAKE0"])
    menu, folder = _menu(tmp_path)
    ds = magcal.simulate_timeseries("chi2017", n_samples=50, seed=1, rate_hz=10.0)
    from magcal.data import io as mio

    mio.write_csv(folder / "live-1.csv", ds)
    labels = menu.labels()
    assert "simulated chi2017" in labels and "replay recordings/live-1.csv" in labels
    assert "serial /dev/ttyFAKE0 (MAVLink)" in labels and "UDP MAVLink on 127.0.0.1 (port below)" in labels
    assert menu.url("simulated chi2017", rate_hz=50, n_samples=3000, speed=2) == "sim://chi2017?rate=50&speed=2&n=3000"
    replay = menu.url("replay recordings/live-1.csv", rate_hz=20, speed=1)
    assert replay == f"sim://{folder / 'live-1.csv'}?rate=20&speed=1"
    assert open_source(replay).dataset.n_samples == 50
    assert menu.url("UDP MAVLink on 127.0.0.1 (port below)", port=14551) == "udp://127.0.0.1:14551?mavlink=1"
    url = menu.url("serial /dev/ttyFAKE0 (text lines)", baud="57600", columns="x,y,z&mavlink=1&baud=1", units="uT")
    query = parse_qs(urlsplit(url).query)
    assert url.startswith("serial:///dev/ttyFAKE0?") and "mavlink" not in query  # the text cannot add options
    assert query["columns"] == ["x,y,z&mavlink=1&baud=1"] and query["baud"] == ["57600"] and query["units"] == ["uT"]
    # beyond this machine: the presets only (and what the command line allowed)
    remote, _ = _menu(tmp_path, local=False, allow=["udp://0.0.0.0:14550?mavlink"])
    assert set(remote.labels()) == {f"simulated {p}" for p in PRESETS} | {"allowed: udp://0.0.0.0:14550?mavlink"}
    assert remote.url("allowed: udp://0.0.0.0:14550?mavlink") == "udp://0.0.0.0:14550?mavlink"


@pytest.mark.parametrize(
    "label",
    [
        "/etc/passwd",
        "sim:///etc/passwd",
        "sim://chi2017?n=1000000000",
        "/usr/bin/python3",
        "serial:///usr/bin/python3?mavlink",
        "udp://0.0.0.0:14550?mavlink",
        "tcp://192.0.2.1:5760",
        "udp://127.0.0.1:14550?mavlink",  # even a loopback URL: the page names an entry, never a URL
        "replay recordings/../../etc/passwd",
        "allowed: udp://0.0.0.0:14550?mavlink",  # not allowed on this command line
    ],
)
def test_the_page_cannot_name_a_path_a_program_or_an_address(tmp_path, label):
    menu, _ = _menu(tmp_path)
    with pytest.raises(magcal.MagcalError, match="not a source this workbench offers"):
        menu.url(label)


@pytest.mark.parametrize(
    "options",
    [
        {"rate_hz": 1e9},
        {"rate_hz": float("nan")},
        {"n_samples": 10**9},
        {"speed": 1e6},
        {"speed": 0.0},
    ],
)
def test_a_preset_s_options_are_bounded(tmp_path, options):
    menu, _ = _menu(tmp_path)
    with pytest.raises(magcal.MagcalError, match="outside|not a finite number"):
        menu.url("simulated chi2017", **options)


@pytest.mark.parametrize("port", [0, 80, 70000, "14550; rm -rf"])
def test_a_port_is_bounded(tmp_path, port):
    menu, _ = _menu(tmp_path)
    with pytest.raises(magcal.MagcalError, match="Port"):
        menu.url("UDP text lines on 127.0.0.1 (port below)", port=port)


@pytest.mark.parametrize(
    "label, options",
    [
        ("UDP text lines on 127.0.0.1 (port below)", {"port": 14551.5}),
        ("TCP text lines from 127.0.0.1 (port below)", {"port": 5760.25}),
        ("simulated chi2017", {"n_samples": 3000.5}),
    ],
)
def test_a_port_or_a_count_with_a_fraction_is_refused_not_truncated(tmp_path, label, options):
    """``14551.5`` opened port 14551; it is refused with one line saying what to give."""
    menu, _ = _menu(tmp_path)
    with pytest.raises(magcal.MagcalError, match=r"is not a whole number; give \d+ \.\.\. \d+") as err:
        menu.url(label, **options)
    assert "\n" not in str(err.value)
    assert menu.url(label, **{k: round(v) for k, v in options.items()})  # the whole number is taken as it is


def test_the_start_button_refuses_a_port_with_a_fraction(bench):
    from viser import GuiEvent

    wb = bench()
    p = wb.panels
    p.live_source.value = "UDP text lines on 127.0.0.1 (port below)"
    p.live_port._impl.value = 14551.5  # within the widget's range: only the server's check sees the fraction
    wb.handle(wb.livectl.do_live_start, GuiEvent(None, None, p.btn_live_start))
    assert "Port (UDP/TCP): 14551.5 is not a whole number" in wb.ctrl.message and not wb.livectl.running


def test_hostile_lines_on_a_live_source_never_hold_up_the_page_s_server(bench):
    """A UDP text source started from the page with the skips the page allows; any local process sends it
    lines that the old patterns took seconds (600 bytes: minutes) to refuse. The server answers HTTP at once all
    along, and the lines are counted as bad."""
    import http.client
    import socket
    import threading

    from viser import GuiEvent

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    wb = bench()
    p = wb.panels
    p.live_source.value = "UDP text lines on 127.0.0.1 (port below)"
    p.live_port.value = port
    p.live_template.value = "{_}{_}{_}{x}{y}{z}Q"
    wb.handle(wb.livectl.do_live_start, GuiEvent(None, None, p.btn_live_start))
    assert wb.livectl.running, wb.ctrl.message
    stats = wb.live.session.source.stats
    waits = []
    done = threading.Event()

    def ask():  # the page's server, asked every 50 ms while the lines arrive
        while not done.is_set():
            t0 = time.monotonic()
            conn = http.client.HTTPConnection("127.0.0.1", wb.port, timeout=60)
            try:
                conn.request("GET", "/")
                conn.getresponse().read()
            finally:
                conn.close()
            waits.append(time.monotonic() - t0)
            time.sleep(0.05)

    asking = threading.Thread(target=ask, daemon=True)
    asking.start()
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
            tx.sendto(b"7 30000 2000 40000 Q\n", ("127.0.0.1", port))
            for n in (200, 240, 200, 240):
                time.sleep(0.2)
                tx.sendto(b"1 " * (n // 2) + b"\n", ("127.0.0.1", port))
        assert _wait(lambda: stats.n_bad >= 4, 60), stats.summary()
        time.sleep(0.2)
    finally:
        done.set()
        asking.join(70)
        wb.live.stop()
    assert stats.n_samples == 1 and stats.reasons["template"] == 4, stats.summary()
    assert len(waits) >= 5 and max(waits) < 2.0, waits


def test_a_serial_port_that_is_a_program_is_never_opened(tmp_path, monkeypatch):
    """pymavlink runs a "device" that looks like a program as a child process: a listed port that is a regular
    file is refused before pymavlink or pyserial see it."""
    from magcal_workbench import live as wlive

    marker = tmp_path / "ran"
    program = tmp_path / "bin" / "fake-port"
    program.parent.mkdir()
    program.write_text(f"#!/bin/sh\ntouch {marker}\n")
    program.chmod(0o755)
    monkeypatch.setattr(wlive, "serial_ports", lambda: [str(program)])
    menu, _ = _menu(tmp_path)
    for label in (f"serial {program} (MAVLink)", f"serial {program} (text lines)"):
        with pytest.raises(magcal.MagcalError, match="is a file, not a serial port"):
            menu.url(label)
    assert not marker.exists()


def test_the_start_button_refuses_what_the_page_was_not_offered(bench, tmp_path):
    """Through the page's handler: a value the page sends for the source (a path, a URL, a program) or an option out
    of bounds is refused before anything opens; no recording is made."""
    from viser import GuiEvent

    wb = bench()
    p = wb.panels
    folder = Path(wb.store.root) / "recordings"
    for widget, value in (
        (p.live_source, "sim:///etc/passwd"),
        (p.live_source, "/usr/bin/python3"),
        (p.live_source, "udp://0.0.0.0:14550?mavlink"),
        (p.live_samples, 10**9),
        (p.live_speed, 1e6),
        (p.live_port, 22),
        (p.live_baud, "115200&mavlink=1"),
        (p.live_units, "nT&x=1"),
        (p.live_columns, "x" * 5000),
    ):
        saved = widget.value
        widget._impl.value = value  # what a browser's message does (viser checks nothing)
        wb.handle(wb.livectl.do_live_start, GuiEvent(None, None, p.btn_live_start))
        assert "refused" in wb.ctrl.message or "not one of" in wb.ctrl.message, (value, wb.ctrl.message)
        assert not wb.livectl.running and not (folder.exists() and any(folder.iterdir()))
        widget.value = saved
    p.live_source.value = "simulated chi2017"
    p.live_samples.value, p.live_rate.value, p.live_speed.value = 200, 200.0, 1.0
    wb.handle(wb.livectl.do_live_start, GuiEvent(None, None, p.btn_live_start))
    assert wb.livectl.running and wb.live.url == "sim://chi2017?rate=200&speed=1&n=200"
    wb.live.stop()


# --- the page ------------------------------------------------------------------------------------------------
@pytest.mark.e2e
@pytest.mark.slow
def test_live_in_the_page_grows_records_stops_diagnoses_and_adds(browser, bench, tmp_path):
    """Start from the Files tab, watch the counts and the fit change on the page, stop, diagnose, add."""
    from tests.workbench.test_workbench_e2e import _dismiss_toasts, _open

    wb = bench(store=True)
    page = _open(browser, wb)
    page.get_by_role("tab", name="Files").click(timeout=30_000)
    # viser's label points at no input id: take the input of the label's own row
    # a file is played again only from the session folder's recordings: put the lesson there, list the sources
    recordings = Path(wb.store.root) / "recordings"
    recordings.mkdir(parents=True, exist_ok=True)
    (recordings / "warm.csv").write_bytes(LESSON.read_bytes())
    page.get_by_role("button", name="List the sources again").click()
    assert _wait(lambda: "replay recordings/warm.csv" in wb.panels.live_source.options, 20)
    wb.panels.live_source.value = "replay recordings/warm.csv"  # the choice and options, shown in the page
    wb.panels.live_rate.value, wb.panels.live_speed.value = 50.0, 6.0
    page.get_by_role("button", name="Start live").click()
    page.wait_for_function("() => /\\d+ samples received/.test(document.body.innerText)", timeout=30_000)

    def received():
        import re

        m = re.search(r"(\d+) samples received", page.inner_text("body"))
        return int(m.group(1)) if m else -1

    first = received()
    page.wait_for_function("() => /fit on \\d+ samples: RMS/.test(document.body.innerText)", timeout=60_000)
    assert _wait(lambda: received() > first, 20)  # the page follows the stream
    live = wb.live
    assert _wait(lambda: not live.session.running, 60)
    page.wait_for_function(
        "() => /ended; 1500 samples received, 1500 on disk/.test(document.body.innerText)", timeout=30_000
    )
    sent = live.session.source.stats.n_samples
    _dismiss_toasts(page)
    page.get_by_role("button", name="Stop and open the recording").click()
    page.wait_for_function("() => document.body.innerText.includes('opened the recording')", timeout=60_000)
    assert magcal.read_csv(live.path).n_samples == sent == 1500 and live.url.startswith("sim:///")
    assert wb.ctrl.dataset.n_samples == sent
    page.get_by_role("tab", name="Calibrate").click()
    page.get_by_role("button", name="Run the chosen method").click()
    page.wait_for_function("() => /Total-field RMS: [0-9.]+ nT/.test(document.body.innerText)", timeout=90_000)
    assert wb.worker.wait(120)
    page.get_by_role("tab", name="Model").click()
    page.get_by_role("button", name="Diagnose").click()
    page.wait_for_function("() => document.body.innerText.includes('Verdict:')", timeout=120_000)
    assert wb.worker.wait(120)
    before = wb.ctrl.residual_rms_nT()
    page.get_by_role("button", name="Add the candidate and refit").click()
    page.wait_for_function("() => document.body.innerText.includes('Model: temperature')", timeout=120_000)
    assert wb.worker.wait(120)
    after = wb.ctrl.residual_rms_nT()
    assert after < 0.95 * before and after < 1.05 * wb.ctrl.floor_nT()


def test_the_page_s_template_becomes_the_url_s_template_and_nothing_else(tmp_path, monkeypatch):
    from urllib.parse import parse_qs, urlsplit

    from magcal.data.live import open_source
    from magcal_workbench import live as wlive

    monkeypatch.setattr(wlive, "serial_ports", lambda: ["/dev/ttyFAKE0"])
    menu, _ = _menu(tmp_path)
    template = "Magnetometer reading: [{x}, {y}, {z}]&mavlink=1"
    url = menu.url(
        "UDP text lines on 127.0.0.1 (port below)", port=14999, columns="x,y,z", units="uT", template=template
    )
    query = parse_qs(urlsplit(url).query)
    assert query == {"template": [template], "units": ["uT"]}  # the text cannot add options; it replaces columns
    url = menu.url("UDP text lines on 127.0.0.1 (port below)", port=14999, columns="x,y,z", template="  ")
    assert parse_qs(urlsplit(url).query)["columns"] == ["x,y,z"]  # blank: the columns
    good = menu.url("UDP text lines on 127.0.0.1 (port below)", port=14999, template="x={x} y={y} z={z}")
    with open_source(good) as src:  # the engine reads it as a template
        assert src.parser.parse("x=1 y=2 z=3")[1].tolist() == [[1.0, 2.0, 3.0]]
    for bad in ["x" * 201, "x={x}\ny={y}"]:
        with pytest.raises(magcal.MagcalError, match="Template"):
            menu.url("UDP text lines on 127.0.0.1 (port below)", port=14999, template=bad)
