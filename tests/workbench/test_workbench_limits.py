"""The workbench against a careless user, a hostile client and large files (4, 5 and 6).

Values a browser sends are checked against what the server offers; state changes from many threads all count;
a job's history row says what it fitted even when the selection changes meanwhile, and the refit asked for
follows; uploads and the session folder are bounded; a large file is drawn decimated and fitted whole; bad files
give one clear message without a server path.
"""

from __future__ import annotations

import importlib
import sys
import threading

import numpy as np
import pytest

import magcal
from magcal.core.errors import MagcalError
from magcal.data import io as mio

pytest.importorskip("viser")

from magcal_workbench.session import SessionStore
from magcal_workbench.state import Selection, SessionState
from magcal_workbench.uploads import clean_upload_name
from tests.conftest import page_socket

WAIT_S = 60
BENCH_SAMPLES = 200  # the bench fixture (tests/conftest.py) opens this many samples by default


def _as_browser(handle, value):
    """What a browser's update does: the value is set (viser checks nothing), then the widget's callbacks run."""
    from viser import GuiEvent

    handle._impl.value = value
    for cb in list(handle._impl.update_cb):
        cb(GuiEvent(None, None, handle))


def _click(wb, button):
    _as_browser(button, True)
    assert wb.worker.wait(WAIT_S)


def _upload(wb, name, content):
    class Upload:
        pass

    up = Upload()
    up.name, up.content = name, content
    wb.panels.upload._impl.value = up
    wb.handle(wb.uploads.do_upload, None)
    assert wb.worker.wait(WAIT_S)
    return wb.ctrl.message


# ---------------------------------------------------------------------------------------------------------------
# values from the page
# ---------------------------------------------------------------------------------------------------------------
def test_a_sensor_outside_the_choices_is_refused_and_nothing_saved(bench, tmp_path):
    wb = bench()
    path = tmp_path / "sessions" / wb.ctrl.session_id / "session.json"
    before = path.read_bytes()
    _as_browser(wb.panels.sensor_choice, "sensor 9")
    assert "not one of the choices" in wb.ctrl.message and "sensor 9" in wb.ctrl.message
    assert wb.ctrl.state.sensor is None and path.read_bytes() == before
    assert wb.panels.sensor_choice.value == "all sensors"  # put back for every browser
    wb.stop()
    again = bench()  # and the next start is clean
    assert again.ctrl.state.sensor is None


@pytest.mark.parametrize("choice", ["../../../evil", "../evil", "evil-0123456789"])
def test_a_session_outside_the_folder_is_refused_even_if_the_client_changed_the_options(bench, tmp_path, choice):
    secret = tmp_path / "evil"
    secret.mkdir()
    (secret / "session.json").write_text("{}")
    (secret / "data.csv").write_text("s1x,s1y,s1z\n1,2,3\n")
    wb = bench()
    n = wb.ctrl.dataset.n_samples
    (tmp_path / "sessions" / "evil-0123456789").mkdir()  # a folder with a valid name but no session in it
    wb.panels.session_choice._impl.options = (choice,)  # a hostile client may send options too
    _as_browser(wb.panels.session_choice, choice)
    _click(wb, wb.panels.btn_reopen)
    assert "not one of the choices" in wb.ctrl.message and wb.ctrl.dataset.n_samples == n
    assert str(tmp_path) not in wb.ctrl.message


@pytest.mark.parametrize(
    "widget, value",
    [
        ("lesson_choice", "../../etc"),
        ("candidate_choice", "bias_drift:9"),
        ("box_mode", "delete everything"),
        ("method", "magic"),
    ],
)
def test_other_dropdowns_outside_their_choices_are_refused(bench, widget, value):
    wb = bench()
    handle = getattr(wb.panels, widget)
    handle._impl.value = value  # as a browser sets it; read by a button or the widget's own callback
    with pytest.raises(MagcalError, match="not one of the choices"):
        wb.values.check(handle)
    assert handle.value != value  # put back


@pytest.mark.parametrize(
    "widget, value, says",
    [
        ("k_sigma", 1e308, "outside 2 ... 10"),
        ("k_sigma", float("nan"), "not a finite number"),
        ("distortion_gain", -1.0, "outside"),
        ("residual_gain", float("inf"), "not a finite number"),
        ("reference", -5.0, "outside 0 ... inf"),
    ],
)
def test_numbers_out_of_range_are_refused(bench, widget, value, says):
    wb = bench()
    handle = getattr(wb.panels, widget)
    _as_browser(handle, value)
    assert says in wb.ctrl.message or widget == "k_sigma"  # the slider without a callback: refused when read
    if widget == "k_sigma":
        wb.panels.k_sigma._impl.value = value
        wb.handle(wb.actions.do_threshold, None)
        assert says in wb.ctrl.message and wb.ctrl.state.selection.n_rejected == 0
    lo, hi = wb.values.range(handle)
    assert np.isfinite(handle.value) and lo <= handle.value <= (hi if hi is not None else np.inf)


def test_pointer_callbacks_go_through_the_error_handler(bench, monkeypatch):
    wb = bench()

    def broken(event):
        raise ValueError("boom")

    monkeypatch.setattr(wb.view, "on_click", broken)
    monkeypatch.setattr(wb.view, "on_rect_select", broken)
    entries = wb.server.scene._scene_pointer_cb
    assert len(entries) == 2
    for entry in entries:
        wb.ctrl.message = ""
        entry.callback(object())  # no exception escapes into viser's thread pool
        assert "Unexpected error" in wb.ctrl.message and "boom" in wb.ctrl.message


# ---------------------------------------------------------------------------------------------------------------
# concurrency
# ---------------------------------------------------------------------------------------------------------------
@pytest.fixture
def racy():
    """Switch threads as often as possible, so that an unguarded read-modify-write loses updates."""
    old = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)
    yield
    sys.setswitchinterval(old)


@pytest.mark.parametrize("through", ["selection", "controller"])
def test_eight_threads_of_disjoint_rejects_lose_nothing(racy, through):
    from magcal_workbench.controller import Controller

    n, per_call, calls = 32_000, 10, 400
    ds = magcal.simulate("chi2017", n_samples=n, seed=1)
    state = SessionState(n, ds.n_sensors)
    ctrl = Controller(ds, state)
    start = threading.Barrier(8)

    def work(k):
        start.wait()
        base = k * per_call * calls
        for c in range(calls):
            idx = np.arange(base + c * per_call, base + (c + 1) * per_call)
            if through == "selection":
                state.selection.reject(idx)
            else:
                ctrl.select(idx)

    threads = [threading.Thread(target=work, args=(k,)) for k in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(WAIT_S)
    assert state.selection.n_rejected == 8 * per_call * calls == n


def test_the_selection_and_its_state_share_one_lock():
    st = SessionState(10, 1)
    assert st.selection.lock is st.lock
    st.selection = Selection(10)
    assert st.selection.lock is st.lock


def test_a_jobs_history_row_matches_what_it_fitted_and_the_refit_follows(bench, monkeypatch):
    fit_module = importlib.import_module("magcal.fitting.fitter")  # (also the name of the API's function)

    wb = bench()
    ctrl = wb.ctrl
    ctrl.worker.run_now("ellipsoid", ctrl.step_ellipsoid)
    n = ctrl.dataset.n_samples
    entered, release = threading.Event(), threading.Event()
    fitted_masks = []
    original = fit_module.fit  # the controller's refine step calls it

    def slow_fit(*args, **kwargs):
        fitted_masks.append(np.array(kwargs["mask"], bool))
        if len(fitted_masks) == 1:
            entered.set()
            assert release.wait(WAIT_S)
        return original(*args, **kwargs)

    monkeypatch.setattr(fit_module, "fit", slow_fit)
    rows = len(ctrl.state.history)
    wb.handle(wb.actions.do_refine, None)
    assert entered.wait(WAIT_S)
    rejected = np.arange(10, 47)
    ctrl.select(rejected)  # another page rejects 37 samples while the fit runs
    wb.steps.maybe_refit()
    assert "refit follows" in ctrl.message
    release.set()
    assert wb.worker.wait(WAIT_S)
    for _ in range(200):  # the pending refit starts from its own thread once the worker is idle
        if len(ctrl.state.history) >= rows + 2 and not wb.worker.busy:
            break
        threading.Event().wait(0.05)
    assert wb.worker.wait(WAIT_S)
    first, refit = ctrl.state.history[rows], ctrl.state.history[rows + 1]
    assert fitted_masks[0].all() and first.n_kept == n  # the row says what the job fitted: every sample
    assert first.effects == [] and "RMS" in first.changes
    # the refit's fit ran on the live mask (other fits of a step, e.g. held-out ones, fit parts of its mask)
    assert any(m.sum() == n - 37 and not m[rejected].any() for m in fitted_masks[1:])
    assert refit.n_kept == n - 37  # the change was applied after, with the refit the user asked for
    assert ctrl.state.selection.n_rejected == 37


def test_a_job_fits_the_model_it_started_with_when_an_effect_is_ticked_meanwhile(bench, monkeypatch):
    fit_module = importlib.import_module("magcal.fitting.fitter")
    wb = bench()
    ctrl = wb.ctrl
    ctrl.worker.run_now("ellipsoid", ctrl.step_ellipsoid)
    entered, release = threading.Event(), threading.Event()
    fitted_models = []
    original = fit_module.fit

    def slow_fit(ds, model, *args, **kwargs):
        fitted_models.append([e.name for e, _ in model.instances()])
        if len(fitted_models) == 1:
            entered.set()
            assert release.wait(WAIT_S)
        return original(ds, model, *args, **kwargs)

    monkeypatch.setattr(fit_module, "fit", slow_fit)
    rows = len(ctrl.state.history)
    wb.handle(wb.actions.do_refine, None)
    assert entered.wait(WAIT_S)
    assert ctrl.set_effect("temperature_bias", True)  # another page ticks an effect while the fit runs
    release.set()
    assert wb.worker.wait(WAIT_S)
    row = ctrl.state.history[rows]
    assert fitted_models[0] == [] and row.effects == []  # the model of the moment Refine was clicked
    assert ctrl.state.effects == ["temperature_bias"]  # the tick stands, for the next step
    assert ctrl.calibration is not None and ctrl.calibration.model is not None
    assert [e.name for e, _ in ctrl.calibration.model.instances()] == []


def test_job_inputs_are_a_fixed_copy_and_add_an_effect_as_the_state_does():
    from magcal_workbench.state import JobInputs

    st = SessionState(10, 2)
    st.effects = ["temperature_bias:1", "bias_drift"]
    inputs = st.job_inputs()
    st.selection.reject([3, 4])
    st.add_effect("nonlinearity_cubic")
    assert inputs.kept.all() and inputs.effects == ("temperature_bias:1", "bias_drift")
    with pytest.raises(ValueError):
        inputs.kept[0] = False  # read-only: nothing downstream changes what the job fits
    for label in ("temperature_bias", "bias_drift", "temperature_bias:2", "bias_drift:1"):
        again = SessionState(10, 2)
        again.effects = list(inputs.effects)
        again.add_effect(label)
        assert list(inputs.with_effect(label).effects) == again.effects
    assert JobInputs(np.ones(3, bool)).effects == ()


def test_no_thread_local_state_in_the_workbench():
    import pathlib

    import magcal_workbench

    for path in sorted(pathlib.Path(magcal_workbench.__file__).parent.glob("*.py")):
        text = path.read_text(encoding="utf-8")
        assert "threading.local" not in text and "from threading import local" not in text, path.name


# ---------------------------------------------------------------------------------------------------------------
# limits
# ---------------------------------------------------------------------------------------------------------------
def test_an_upload_over_the_limit_is_refused_with_a_message(bench, tmp_path):
    wb = bench(max_upload_mb=0.001)  # 1000 bytes
    n = wb.ctrl.dataset.n_samples
    message = _upload(wb, "big.csv", b"s1x,s1y,s1z\n" + b"1,2,3\n" * 1000)
    assert "upload limit of 0.001 MB" in message and "--max-upload-mb" in message and wb.ctrl.dataset.n_samples == n


def test_an_upload_over_the_limit_is_dropped_when_it_starts(bench):
    """viser buffers an upload's parts in memory: the declared size refuses it before they arrive."""
    from viser import _messages

    wb = bench(max_upload_mb=0.001)
    gui = wb.server.gui
    uuid = wb.panels.upload._impl.uuid
    for tid, size in (("small", 500), ("big", 5_000_000)):
        gui._handle_file_transfer_start(0, _messages.FileTransferStartUpload(uuid, tid, "x.csv", "text/csv", 3, size))
        wb.uploads.start_handler(0, _messages.FileTransferStartUpload(uuid, tid, "x.csv", "text/csv", 3, size))
    assert "small" in gui._current_file_upload_states and "big" not in gui._current_file_upload_states


def test_an_upload_that_sends_more_than_it_declared_is_dropped_as_it_passes_the_limit(bench):
    """A crafted client (a local websocket client with the token) declares 1 KB and sends 64 KB parts:
    the upload is dropped as soon as the bytes received pass the 0.2 MB limit; viser never holds more than the
    limit of it, the parts that follow are ignored, nothing is opened."""
    import asyncio
    import time

    import msgspec
    from viser import _messages

    wb = bench(store=False, max_upload_mb=0.2)
    before = wb.ctrl.dataset
    gui, uuid = wb.server.gui, wb.panels.upload._impl.uuid
    peak = {"bytes": 0, "parts_seen": 0}

    def measure(client_id, message):  # runs after viser's own buffering: what it holds now
        state = gui._current_file_upload_states.get(message.transfer_uuid)
        peak["parts_seen"] += 1
        if state is not None:
            peak["bytes"] = max(peak["bytes"], sum(len(p) for p in state["parts"].values()))

    wb.server._websock_server.register_handler(_messages.FileTransferPart, measure)
    part, n_parts = b"x" * 65_536, 40  # 2.6 MB sent in all

    def encode(message):
        return msgspec.msgpack.encode(message.as_serializable_dict())

    async def go():
        async with page_socket(wb.port, token=wb.token) as ws:
            await ws.send(encode(_messages.FileTransferStartUpload(uuid, "t1", "a.csv", "text/csv", n_parts, 1000)))
            for i in range(n_parts):
                await ws.send(encode(_messages.FileTransferPart(uuid, "t1", i, part)))
            end = time.monotonic() + 20
            while peak["parts_seen"] < n_parts and time.monotonic() < end:
                await asyncio.sleep(0.05)

    asyncio.run(asyncio.wait_for(go(), 60))
    assert peak["parts_seen"] == n_parts  # every part reached the server
    assert "t1" not in gui._current_file_upload_states
    assert 0 < peak["bytes"] <= 200_000  # dropped at the part that passed the limit, never buffered whole
    assert wb.ui.wait(10)
    assert "passed the upload limit" in wb.ctrl.message and wb.ctrl.dataset is before
    assert wb.uploads._received == {}


def test_sessions_are_listed_with_sizes_deletable_and_bounded(bench, tmp_path):
    store = SessionStore(tmp_path / "s", max_bytes=60_000)
    ids = []
    for k in range(4):
        ds = magcal.simulate("chi2017", n_samples=150 + k, seed=k)
        path = tmp_path / f"d{k}.csv"
        mio.write_csv(path, ds)
        content = path.read_bytes()
        sid = store.create(path.name, content)
        store.save(sid, SessionState(ds.n_samples, ds.n_sensors))
        ids.append((sid, len(content)))
    listed = {s["id"]: s["bytes"] for s in store.list()}
    assert sum(listed.values()) <= 60_000  # the oldest went to keep the bound
    assert ids[-1][0] in listed and ids[0][0] not in listed
    assert all(b >= ids[-1][1] * 0.9 for b in listed.values())
    wb = bench()
    other = (
        next(s["id"] for s in wb.store.list() if s["id"] != wb.ctrl.session_id) if len(wb.store.list()) > 1 else None
    )
    assert other is None  # one session so far
    _upload(wb, "second.csv", (tmp_path / "d1.csv").read_bytes())
    first = next(s["id"] for s in wb.store.list() if s["id"] != wb.ctrl.session_id)
    assert "MB" in wb.panels.session_info.content and first in wb.panels.session_info.content
    _as_browser(wb.panels.session_choice, first)
    _click(wb, wb.panels.btn_delete_session)
    assert "deleted session" in wb.ctrl.message and first not in [s["id"] for s in wb.store.list()]
    _as_browser(wb.panels.session_choice, wb.ctrl.session_id)
    _click(wb, wb.panels.btn_delete_session)
    assert "is the one open" in wb.ctrl.message and wb.store.exists(wb.ctrl.session_id)


def test_the_sessions_bound_keeps_the_live_recording_and_stop_opens_it(bench, tmp_path, capsys):
    """A live stream, then an upload past --max-sessions-mb: the older sessions go (and the terminal
    says which), the recordings folder and the recording being written stay, and Stop opens the recording."""
    import time

    wb = bench()
    first = wb.ctrl.session_id
    wb.store.max_bytes = 1_000  # smaller than any upload: every other session must go
    live = wb.livectl.start("sim://chi2017?rate=400&n=4000")
    deadline = time.monotonic() + 30
    while live.session.n_recorded < 200 and time.monotonic() < deadline:
        time.sleep(0.05)
    assert live.session.n_recorded >= 200
    ds = magcal.simulate("chi2017", n_samples=120, seed=9)
    mio.write_csv(tmp_path / "up.csv", ds)
    _upload(wb, "up.csv", (tmp_path / "up.csv").read_bytes())
    said = capsys.readouterr().err
    assert f"deleted the session {first}" in said and "recordings" not in said
    assert not (wb.store.root / first).exists()  # the bound did act
    assert live.path.is_file() and live.path.parent == wb.store.root / "recordings"
    assert live.session.error is None and wb.livectl.running
    _click(wb, wb.panels.btn_live_stop)
    assert wb.ctrl.dataset.n_samples == live.session.n_recorded >= 200
    assert wb.ctrl.dataset.n_samples == magcal.read_csv(live.path).n_samples
    # a later prune with nothing in use still leaves the recordings alone
    wb.store.prune(0)
    assert live.path.is_file()


def test_a_large_file_is_drawn_decimated_and_fitted_whole(bench):
    n = 3000
    ds = magcal.simulate_timeseries("chi2017", n_samples=n, seed=2, rate_hz=5.0)
    wb = bench(ds, max_points=400)
    clouds = wb.scene_view._clouds
    assert clouds and all(len(h.points) <= 400 for h in clouds.values())
    wb.ctrl.worker.run_now("calibrate", wb.ctrl.step_calibrate)
    assert wb.ctrl.state.history[-1].n_kept == n  # the fit used every sample
    assert all(len(h.points) <= 400 for h in wb.scene_view._clouds.values())
    # the outliers are always drawn: the samples with the largest residual
    worst = np.argsort(np.abs(wb.ctrl.residual_nT).max(axis=0))[-20:]
    assert np.isin(worst, wb.scene_view.shown_samples).all()
    # a box over the whole scene selects every sample, drawn or not
    wb.panels.auto_refit.value = False
    cam = (1.0, 0.0, 0.0, 0.0)  # camera-to-world: looking along +z
    d = wb.scene_view.displayed
    pos = np.array([d.positions[:, 0].mean(), d.positions[:, 1].mean(), -50.0])
    picked = wb.scene_view.samples_in_rect(cam, pos, np.radians(60), 1.0, (0.0, 0.0), (1.0, 1.0))
    assert picked.size == n


@pytest.mark.parametrize("n, limit", [(100, 500), (10_000, 500), (1_000_000, 20_000)])
def test_level_of_detail_keeps_the_budget(n, limit):
    from magcal_workbench.scene import level_of_detail

    r = np.zeros((2, n))
    r[1, n // 3] = 50.0
    idx = level_of_detail(n, limit, r)
    assert idx.size <= limit and np.all(np.diff(idx) > 0) and idx[0] == 0
    assert n // 3 in idx


# ---------------------------------------------------------------------------------------------------------------
# the smaller items
# ---------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "name, shown",
    [
        ("..", "upload.csv"),
        (".", "upload.csv"),
        ("", "upload.csv"),
        ("a" * 300 + ".csv", "a" * 100),
        ("../../x.csv", "x.csv"),
        ("C:\\\\Users\\\\me\\\\x.csv", "x.csv"),
    ],
)
def test_awkward_upload_names_open_the_file(bench, tmp_path, name, shown):
    wb = bench()
    ds = magcal.simulate("chi2017", n_samples=60, seed=2)
    path = tmp_path / "ok.csv"
    mio.write_csv(path, ds)
    message = _upload(wb, name, path.read_bytes())
    assert "opened" in message and shown in message and wb.ctrl.dataset.n_samples == 60, message
    assert len(clean_upload_name(name)) <= 120 and wb.store.exists(wb.ctrl.session_id)


def test_a_huge_value_is_refused_at_reading_with_file_row_column(bench, tmp_path):
    ds = magcal.simulate("chi2017", n_samples=60, seed=2)
    path = tmp_path / "ok.csv"
    mio.write_csv(path, ds)
    lines = path.read_text().splitlines()
    header = next(i for i, l in enumerate(lines) if not l.startswith("#"))
    row = lines[header + 3].split(",")
    row[1] = "1e204"
    lines[header + 3] = ",".join(row)
    wb = bench()
    message = _upload(wb, "huge.csv", ("\n".join(lines) + "\n").encode())
    assert f"huge.csv: 1 row(s) with bad values: line {header + 4}, column s1y: '1e204'" in message
    assert "LinAlgError" not in message and wb.ctrl.dataset.n_samples == 200


def test_an_all_zero_file_is_diagnosed_truthfully(bench):
    wb = bench()
    _upload(wb, "zero.csv", b"s1x,s1y,s1z\n" + b"0,0,0\n" * 100)
    assert wb.ctrl.dataset.n_samples == 100
    for button in (wb.panels.btn_diagnose, wb.panels.btn_run, wb.panels.btn_refine):
        _click(wb, button)
        assert "every kept reading is the same vector (0, 0, 0) nT" in wb.ctrl.message
        assert "NaN" not in wb.ctrl.message and "LinAlgError" not in wb.ctrl.message


def test_errors_name_no_server_path(bench, tmp_path):
    wb = bench()
    sid = wb.ctrl.session_id
    _upload(wb, "other.csv", (tmp_path / "data.csv").read_bytes().replace(b"\n", b"\nx,", 1))
    (tmp_path / "sessions" / sid / "data.csv").write_bytes(b"s1x,s1y\n1\n")
    _as_browser(wb.panels.session_choice, sid)
    _click(wb, wb.panels.btn_reopen)
    assert "Error" in wb.ctrl.message and sid in wb.ctrl.message
    assert str(tmp_path) not in wb.ctrl.message and "/sessions/" not in wb.ctrl.message


def test_the_workbench_refuses_a_foreign_origin(bench):
    import asyncio
    import socket

    import viser
    from websockets.asyncio.client import connect
    from websockets.exceptions import InvalidStatus

    wb = bench(store=False)

    async def go(origin):
        sock = socket.create_connection(("127.0.0.1", wb.port), timeout=10)
        try:
            async with connect(
                f"ws://127.0.0.1:{wb.port}/?token={wb.token}",
                sock=sock,
                origin=origin,
                open_timeout=10,
                subprotocols=[f"viser-v{viser.__version__}"],
                max_size=None,  # the first message carries plotly.js (the page draws plots from the start)
            ) as ws:
                await asyncio.wait_for(ws.recv(), 10)
                return 101
        except InvalidStatus as exc:
            return exc.response.status_code

    assert asyncio.run(go("http://evil.example")) == 403
    assert asyncio.run(go(f"http://127.0.0.1:{wb.port}")) == 101


def test_the_command_line_prints_an_ipv6_url():
    from magcal_workbench.app import build_parser

    args = build_parser().parse_args(["--host", "::1", "--max-upload-mb", "5", "--max-points", "1000"])
    assert args.max_upload_mb == 5 and args.max_points == 1000
    from magcal_workbench.guard import page_url

    assert page_url(args.host, 8080) == "http://[::1]:8080"


def test_autosaves_from_many_threads_leave_the_newest_state(tmp_path, racy):
    store = SessionStore(tmp_path / "s")
    st = SessionState(4000, 1)
    sid = store.create("x.csv", b"s1x,s1y,s1z\n")
    start = threading.Barrier(4)

    def work(k):
        start.wait()
        for c in range(25):
            st.selection.reject([k * 1000 + c])
            st.touch()
            store.save(sid, st)

    threads = [threading.Thread(target=work, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(WAIT_S)
    saved = store.load(sid)
    assert saved.selection.n_rejected == 100 == st.selection.n_rejected
    fresh = SessionState(4000, 1)  # a new state of the same session (start afresh) is saved from version 0
    store.save(sid, fresh)
    assert store.load(sid).selection.n_rejected == 0


@pytest.mark.parametrize(
    ("departure", "gain"),
    [
        (0.0, 10.0),  # on the sphere: the largest default
        (0.001, 10.0),  # a clean sensor: capped at the default
        (0.03, 5.0),  # 0.15 / 0.03
        (0.5, 0.3),  # a hard iron half the field: drawn closer to the sphere than it is, 0.15 / 0.5
        (2.0, 0.1),  # far beyond the field: the floor
    ],
)
def test_the_distortion_gain_draws_the_typical_departure_at_a_set_share_of_the_radius(departure, gain):
    """scene.distortion_gain (the View tab's default and the launch preview's): raw readings on a sphere of radius
    F (1 + d) depart by d from the field's sphere; the gain draws that at 0.15 of the radius, within 0.1-10."""
    from magcal_workbench import scene as scn

    rng = np.random.default_rng(1)
    u = rng.normal(size=(2, 500, 3))
    u /= np.linalg.norm(u, axis=-1, keepdims=True)
    F = 50_000.0
    assert scn.distortion_gain(F * (1 + departure) * u, F) == pytest.approx(gain)
    # a few wild samples move neither the typical departure nor, below a 99th percentile, the gain
    wild = (F * (1 + departure) * u).copy()
    wild[0, :3] *= 3.0
    assert scn.distortion_gain(wild, F) == pytest.approx(gain)


@pytest.mark.parametrize("field_nT", [0.0, float("nan")])
def test_the_distortion_gain_without_a_field_to_scale_by_is_the_default(field_nT):
    """An all-zero file has no field: the preview and the View tab then draw at the largest default gain."""
    from magcal_workbench import scene as scn

    assert scn.distortion_gain(np.zeros((4, 10, 3)), field_nT) == scn.DISTORTION_GAIN_MAX
