"""The workbench's logic without a browser: state, selection, sessions, lessons, scene geometry, the worker, and
the page's handles driven from Python on a real (browserless) viser server."""

from __future__ import annotations

import json
import re
import threading
import time
from pathlib import Path

import numpy as np
import pytest

import magcal
from magcal.core.registry import Loaded
from magcal.data import io as mio
from magcal.data.simulation import chi2017_truth
from magcal_workbench import scene as scn
from magcal_workbench.jobs import Worker
from magcal_workbench.lessons import list_lessons
from magcal_workbench.markup import safe_text
from magcal_workbench.session import SessionStore, session_id
from magcal_workbench.sessionfile import read_session_document
from magcal_workbench.state import Selection, SessionState, StepRecord, pack_mask, unpack_mask

SIGMA = 3.0


# ---------------------------------------------------------------------------------------------------------------
# selection and state
# ---------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("n", [1, 7, 8, 1001])
def test_mask_packing_round_trip(n):
    rng = np.random.default_rng(n)
    mask = rng.random(n) < 0.3
    assert np.array_equal(unpack_mask(pack_mask(mask), n), mask)


def test_selection_reject_restore_undo_redo_reset():
    sel = Selection(10)
    assert sel.n_rejected == 0 and not sel.can_undo
    assert sel.reject([1, 2, 3]) == 3
    assert sel.reject([3, 4]) == 1  # 3 was already rejected
    assert list(sel.rejected_indices) == [1, 2, 3, 4]
    assert sel.restore([2, 9]) == 1
    assert list(sel.rejected_indices) == [1, 3, 4]
    assert sel.undo() is not None
    assert list(sel.rejected_indices) == [1, 2, 3, 4]
    assert sel.undo() is not None and sel.undo() is not None
    assert sel.n_rejected == 0 and sel.undo() is None
    assert sel.redo() is not None
    assert list(sel.rejected_indices) == [1, 2, 3]
    sel.reject([0])  # a new change clears the redo stack
    assert not sel.can_redo
    assert sel.reset() and sel.n_rejected == 0
    assert sel.undo() == "reset" and sel.n_rejected == 4
    with pytest.raises(IndexError):
        sel.reject([10])


def test_selection_no_op_is_not_an_undo_step():
    sel = Selection(5)
    sel.restore([0, 1])
    assert not sel.can_undo
    sel.reject([])
    assert not sel.can_undo


def test_selection_survives_the_session_file():
    sel = Selection(50)
    sel.reject(range(5, 15))
    sel.restore([7])
    doc = json.loads(json.dumps(sel.to_dict()))
    back = Selection.from_dict(doc, 50)
    assert np.array_equal(back.kept, sel.kept)
    back.undo()
    assert list(back.rejected_indices) == list(range(5, 15))
    with pytest.raises(ValueError):
        Selection.from_dict(doc, 51)


def test_effects_all_sensors_replaces_per_sensor_terms():
    st = SessionState(100, 4)
    assert st.add_effect("temperature_bias:2")
    assert st.add_effect("bias_drift")
    assert not st.add_effect("temperature_bias:2")
    assert st.add_effect("temperature_bias")
    assert st.effects == ["bias_drift", "temperature_bias"]
    assert not st.add_effect("temperature_bias:3")  # already in for all sensors
    assert st.remove_effect("temperature_bias") and st.effects == ["bias_drift"]
    assert not st.remove_effect("temperature_bias")


def test_session_state_round_trip():
    st = SessionState(20, 2, "x.csv", lesson="warm-sensor")
    st.selection.reject([3, 4])
    st.add_effect("bias_step:1")
    st.method, st.reference_nT, st.robust, st.sensor = "de", 51000.0, True, 1
    st.record(StepRecord("fit ellipsoid", 3.2, 2.9, [], 18, "RMS 700 -> 3.2 nT", 0.1), {"format": "x"})
    st.record(
        StepRecord(
            "refine (ML)",
            3.1,
            2.9,
            [],
            18,
            "RMS 3.2 -> 3.1 nT",
            0.2,
            fit={"success": False, "status": 0, "message": "maximum number of evaluations reached", "nfev": 2},
        )
    )
    back = read_session_document(json.loads(json.dumps(st.to_dict())))
    assert back.to_dict() == st.to_dict()
    x, y, f = back.rms_series()
    assert list(y) == [3.2, 3.1] and list(f) == [2.9, 2.9]
    assert back.history[0].fit is None and back.history[1].fit["success"] is False


# ---------------------------------------------------------------------------------------------------------------
# sessions on disk
# ---------------------------------------------------------------------------------------------------------------
def test_session_store_saves_atomically_and_lists(tmp_path):
    store = SessionStore(tmp_path)
    content = b"x,y,z\n1,2,3\n"
    sid = store.create("my data.csv", content)
    assert sid == session_id("my data.csv", content) and sid.startswith("my_data-")
    assert store.create("my data.csv", content) == sid  # same bytes, same session
    assert store.create("my data.csv", content + b"4,5,6\n") != sid
    st = SessionState(1, 1)
    st.add_effect("bias_drift")
    store.save(sid, st)
    assert not list((tmp_path / sid).glob(".tmp-*"))  # no temporary file left behind
    back = store.load(sid)
    assert back.effects == ["bias_drift"] and back.data_path == str(store.data_path(sid))
    assert store.data_path(sid).read_bytes() == content
    assert [s["id"] for s in store.list()] == [sid]
    store.delete(sid)
    assert store.list() == []


# ---------------------------------------------------------------------------------------------------------------
# lessons
# ---------------------------------------------------------------------------------------------------------------
def test_lessons_hide_their_answers():
    lessons = list_lessons()
    assert len(lessons) >= 4
    n_hidden = []
    for lesson in lessons:
        assert lesson.data_path.is_file()
        answer = lesson.answer()
        n_hidden.append(len(answer["effects"]) + len(answer.get("mounting", [])))
        guide = lesson.guide()
        for label in answer["effects"] + answer.get("mounting", []):
            assert label.partition(":")[0] not in guide  # the guide never names the answer
        ds = mio.read_csv(lesson.data_path)
        assert ds.time_s is not None
        if "source" not in lesson._doc() and not answer.get("mounting"):
            assert (
                ds.temperature_C is not None
            )  # the catalogue's lessons carry temperature; a vehicle's, a real one need not
    assert max(n_hidden) >= 2 and min(n_hidden) == 1


def test_lesson_check_without_revealing():
    lesson = next(l for l in list_lessons() if len(l.answer()["effects"]) >= 2)
    want = lesson.answer()["effects"]
    first = lesson.check([want[0]])
    assert not first["solved"] and first["missing"] == len(want) - 1
    assert all(w.partition(":")[0] not in first["message"] for w in want[1:])
    assert lesson.check(want)["solved"]
    names = [w.partition(":")[0] for w in want]
    assert lesson.check(names)["missing"] == 0  # the all-sensor term covers a per-sensor answer
    extra = lesson.check(want + ["hysteresis"])
    assert not extra["solved"] and extra["extra"] == ["hysteresis"]


# ---------------------------------------------------------------------------------------------------------------
# scene geometry (known truth)
# ---------------------------------------------------------------------------------------------------------------
def _camera_looking_along_y(distance=10.0):
    # camera frame (OpenCV): x right, y down, z forward; world: looking along +y with z up
    r = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])  # columns: camera x, y, z in world
    from scipy.spatial.transform import Rotation

    xyzw = Rotation.from_matrix(r).as_quat()
    return np.array([xyzw[3], *xyzw[:3]]), np.array([0.0, -distance, 0.0])


@pytest.mark.parametrize("aspect", [1.0, 1.6])
def test_projection_matches_a_pinhole_camera(aspect):
    wxyz, pos = _camera_looking_along_y(10.0)
    fov = np.radians(60.0)
    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 0, 1], [0, -20, 0]], float)
    uv, front = scn.project_points(pts, wxyz, pos, fov, aspect)
    assert np.allclose(uv[0], [0.5, 0.5])
    t = np.tan(fov / 2)
    assert np.isclose(uv[1, 0], 0.5 + 0.5 * 0.1 / (t * aspect)) and np.isclose(uv[1, 1], 0.5)
    assert np.isclose(uv[2, 1], 0.5 - 0.5 * 0.1 / t)  # up in the world is up on the screen (smaller v)
    assert list(front) == [True, True, True, False]
    inside = scn.points_in_rect(pts, wxyz, pos, fov, aspect, (0.45, 0.45), (0.55, 0.55))
    assert list(inside) == [True, False, False, False]


def test_nearest_to_ray():
    pts = np.array([[0, 0, 0], [0.3, 0, 0], [0, 0, 5.0]])
    i, d = scn.nearest_to_ray(pts, (0.29, -10, 0), (0, 1, 0))
    assert i == 1 and np.isclose(d, 0.01)
    assert scn.nearest_to_ray(pts, (3, -10, 3), (0, 1, 0), max_distance=0.5) == (None, np.inf)
    assert scn.nearest_to_ray(pts, (0, 10, 0), (0, 1, 0))[0] is None  # all points behind the origin


def test_colours_mark_rejected_and_unfitted():
    r = np.array([-10.0, 0.0, 10.0, np.nan, 1.0])
    kept = np.array([True, True, True, True, False])
    c = scn.residual_colors(r, 5.0, kept)
    assert c[0, 2] > c[0, 0] and c[2, 0] > c[2, 2]  # negative blue, positive red
    assert tuple(c[3]) == scn.SPHERE_RGB and tuple(c[4]) == scn.REJECTED_RGB


@pytest.mark.parametrize("sensor", range(4))
def test_ellipsoid_mesh_lies_on_the_true_ellipsoid(sensor):
    truth = chi2017_truth().sensors[sensor]
    F = 50_000.0
    v, f = scn.ellipsoid_mesh(truth.Cinv, truth.bias_nT, F, gain=1.0)
    corrected = (v * F - truth.bias_nT) @ truth.Cinv.T
    assert np.allclose(np.linalg.norm(corrected, axis=1), F, rtol=1e-12)
    assert f.shape[1] == 3 and f.max() < len(v)
    v10, _ = scn.ellipsoid_mesh(truth.Cinv, truth.bias_nT, F, gain=10.0)
    dev1 = np.abs(np.linalg.norm(v, axis=1) - 1)
    dev10 = np.abs(np.linalg.norm(v10, axis=1) - 1)
    assert np.allclose(dev10, 10 * dev1)


@pytest.mark.parametrize("sensor", range(1, 4))
def test_sensor_axes_follow_the_calibration(sensor):
    truth = chi2017_truth().sensors[sensor]
    axes = scn.sensor_axes(truth.Cinv, truth.R, gain=1.0)
    expected = (truth.R @ truth.C.T).T
    expected /= np.linalg.norm(expected, axis=1, keepdims=True)
    assert np.allclose(axes, expected)
    assert np.allclose(scn.sensor_axes(np.eye(3), np.eye(3), 50.0), np.eye(3))
    big = scn.sensor_axes(truth.Cinv, truth.R, gain=20.0)
    angle = lambda a: np.degrees(np.arccos(np.sum(a * np.eye(3), axis=1)))
    assert np.all(angle(big) > angle(axes))


def test_cross_has_real_proportions():
    p = scn.cross_positions(4)
    assert np.allclose(np.linalg.norm(p[0] - p[2]), scn.CROSS_SPAN)
    assert np.allclose(p[0] / np.linalg.norm(p[0]), [1, 0, 0]) and np.allclose(p[1] / np.linalg.norm(p[1]), [0, 1, 0])


@pytest.mark.parametrize("n_groups", [1, 2, 4])
def test_camera_frames_every_group(n_groups):
    fov, aspect = np.radians(75.0), 1.6
    pos, look = scn.camera_pose(n_groups, fov, aspect)
    from scipy.spatial.transform import Rotation

    fwd = (look - pos) / np.linalg.norm(look - pos)
    right = np.cross(fwd, [0, 0, 1.0])
    down = np.cross(fwd, right)
    r = Rotation.from_matrix(np.column_stack([right, down, fwd])).as_quat()
    wxyz = np.array([r[3], *r[:3]])
    centres = np.array([scn.group_offset(k, n_groups) for k in range(n_groups)])
    corners = np.concatenate([centres + [dx, 0, dz] for dx in (-2.8, 2.8) for dz in (-1.3, 1.3)])
    uv, front = scn.project_points(corners, wxyz, pos, fov, aspect)
    assert front.all() and np.all(uv >= 0) and np.all(uv[:, 0] <= 0.72) and np.all(uv[:, 1] <= 1)


# ---------------------------------------------------------------------------------------------------------------
# the worker
# ---------------------------------------------------------------------------------------------------------------
def test_worker_runs_one_job_at_a_time():
    w = Worker()
    gate, events, done = threading.Event(), [], []
    w.on_busy_change(lambda busy, name: events.append((busy, name)))
    assert w.submit("slow", gate.wait, on_done=lambda r: done.append(r))
    assert w.busy and w.current == "slow"
    assert not w.submit("second", lambda: done.append("second ran"))
    with pytest.raises(RuntimeError):
        w.run_now("third", lambda: None)
    gate.set()
    assert w.wait(5)
    assert done == [True] and events == [(True, "slow"), (False, "slow")]
    assert w.submit("after", lambda: 1 / 0) and w.wait(5)
    assert isinstance(w.last_error, ZeroDivisionError) and not w.busy


# ---------------------------------------------------------------------------------------------------------------
# the page, driven through its handles (real viser server, no browser)
# ---------------------------------------------------------------------------------------------------------------
def _csv(tmp_path, ds, name="data.csv"):
    path = tmp_path / name
    mio.write_csv(path, ds)
    return path


def _click(wb, button):
    button.value = True  # what a click does: the callbacks run
    time.sleep(0.05)
    assert wb.worker.wait(120)


def _rms_shown(wb):
    text = wb.panels.status.content
    return text.split("Total-field RMS: ")[1].split("**")[0]


def test_binds_loopback_by_default(bench):
    from magcal_workbench.app import build_parser
    from magcal_workbench.guard import is_loopback

    assert build_parser().parse_args([]).host == "127.0.0.1"
    assert is_loopback("127.0.0.1") and is_loopback("::1") and not is_loopback("0.0.0.0")
    wb = bench(store=False)
    assert wb.server.get_host() == "127.0.0.1"


def test_fit_from_a_click_changes_the_shown_rms(bench):
    wb = bench()
    assert "not fitted" in _rms_shown(wb)
    _click(wb, wb.panels.btn_run)
    shown = _rms_shown(wb)
    rms = float(shown.split()[0])
    assert SIGMA * 0.85 < rms < SIGMA * 1.1
    steps = [r.step for r in wb.ctrl.state.history]
    assert steps[0] == "raw readings" and steps[-1] == "calibrate (ML)"
    assert wb.ctrl.state.history[0].rms_nT > 50 * rms
    # the scene shows raw and corrected clouds of all four sensors, scaled to radius ~1
    d = wb.scene_view.displayed
    assert d.positions.shape[0] == 2 * 4 * 300
    assert np.all(np.abs(np.linalg.norm(d.positions - d.positions.mean(0), axis=1)) < 20)
    # one sensor at a time
    wb.panels.sensor_choice.value = "sensor 2"
    d = wb.scene_view.displayed
    assert d.positions.shape[0] == 2 * 300 and set(d.sensors) == {1}
    assert wb.ctrl.state.sensor == 1


@pytest.mark.parametrize("method", ["ipso", "ellipsoid"])
def test_other_methods_run_with_progress(bench, method):
    wb = bench(store=False)
    shown = []
    real = wb.panels.set_progress
    wb.panels.set_progress = lambda msg, frac: (shown.append(msg), real(msg, frac))
    wb.panels.method.value = method
    assert wb.ctrl.state.method == method
    _click(wb, wb.panels.btn_run)
    rec = wb.ctrl.state.history[-1]
    assert rec.step == ("two steps (seed)" if method == "ellipsoid" else f"global search ({method})")
    assert SIGMA * 0.85 < rec.rms_nT < SIGMA * 1.15
    assert shown and not wb.panels.progress.visible


def test_steps_one_by_one_report_what_changed(bench):
    wb = bench()
    _click(wb, wb.panels.btn_ellipsoid)
    after1 = wb.ctrl.state.history[-1]
    assert after1.step == "fit ellipsoid" and after1.rms_nT < 2 * SIGMA
    t1 = wb.ctrl.tensor_rms()["after"]["Gxx"]
    _click(wb, wb.panels.btn_align)
    after2 = wb.ctrl.state.history[-1]
    assert np.isclose(after2.rms_nT, after1.rms_nT, rtol=1e-9)  # a rotation leaves the total field alone
    floor = wb.ctrl.tensor_rms()["floor"]["Gxx"]
    assert wb.ctrl.tensor_rms()["after"]["Gxx"] < min(t1 / 10, 1.5 * floor)  # ... and fixes the tensor
    assert "tensor" in after2.changes and "R up to" in after2.changes
    _click(wb, wb.panels.btn_refine)
    assert wb.ctrl.state.history[-1].step == "refine (ML)"
    assert "| Gzz |" in wb.panels.sensors_table.content


def test_second_click_while_a_fit_runs_starts_nothing(bench):
    wb = bench(store=False)
    gate = threading.Event()
    calls = []
    real = wb.ctrl.step_calibrate

    def slow(**kw):  # the step's JobInputs (the kept mask and model of the click)
        gate.wait(30)
        calls.append("fit")
        return real(**kw)

    wb.ctrl.step_calibrate = slow
    wb.panels.btn_run.value = True
    time.sleep(0.05)
    assert wb.worker.busy and all(b.disabled for b in wb.panels._engine_buttons)
    wb.actions.do_calibrate(None)  # a second click (a disabled button's callback cannot fire; call it directly)
    assert "Busy" in wb.ctrl.message
    gate.set()
    assert wb.worker.wait(60)
    assert calls == ["fit"] and not any(b.disabled for b in wb.panels._engine_buttons)


def test_box_selection_threshold_undo_and_refit_on_kept_points(bench):
    wb = bench()
    _click(wb, wb.panels.btn_run)
    fov, aspect = np.radians(75.0), 1.6
    pos, look = scn.camera_pose(4, fov, aspect)
    wxyz, cam = _camera_looking_along_y(-pos[1])
    cam = cam + [pos[0], 0, 0]
    d = wb.scene_view.displayed
    uv, _ = scn.project_points(d.positions, wxyz, cam, fov, aspect)
    s1 = uv[d.sensors == 0]
    lo, hi = np.percentile(s1, 20, axis=0), np.percentile(s1, 45, axis=0)
    n = wb.view.select_in_rect(wxyz, cam, fov, aspect, tuple(lo), tuple(hi))
    assert wb.worker.wait(60)
    sel = wb.ctrl.state.selection
    assert n > 0 and sel.n_rejected == n
    assert f"Rejected: {n} of 300" in wb.panels.status.content
    assert wb.ctrl.fit_result.mask.sum() == 300 - n  # the refit used the kept points only
    assert wb.ctrl.state.history[-1].n_kept == 300 - n
    # restore mode puts them back
    wb.panels.box_mode.value = "restore"
    wb.view.select_in_rect(wxyz, cam, fov, aspect, tuple(lo), tuple(hi))
    assert wb.worker.wait(60) and sel.n_rejected == 0
    _click(wb, wb.panels.btn_undo)
    assert sel.n_rejected == n
    _click(wb, wb.panels.btn_redo)
    assert sel.n_rejected == 0
    # threshold: gross outliers planted in the data are the ones rejected
    _click(wb, wb.panels.btn_reset)


def test_threshold_rejects_planted_outliers(bench):
    ds = magcal.simulate_timeseries("chi2017", n_samples=300, seed=6, rate_hz=2.0)
    bad = np.array([10, 50, 200])
    r = ds.readings_nT.copy()
    along = r[2, bad] / np.linalg.norm(r[2, bad], axis=1, keepdims=True)
    r[2, bad] += along * np.array([300.0, -250.0, 200.0])[:, None]  # gross errors along the field
    wb = bench(ds.replace(readings_nT=r))
    _click(wb, wb.panels.btn_run)
    before = wb.ctrl.residual_rms_nT()
    wb.panels.k_sigma.value = 6.0
    _click(wb, wb.panels.btn_threshold)
    assert list(wb.ctrl.state.selection.rejected_indices) == list(bad)
    assert wb.ctrl.residual_rms_nT() < before and wb.ctrl.residual_rms_nT() < 1.1 * SIGMA


def test_click_inspects_the_nearest_sample(bench):
    wb = bench(store=False)
    _click(wb, wb.panels.btn_run)
    d = wb.scene_view.displayed
    k = 123
    target = d.positions[k]

    class Event:
        ray_origin = tuple(target + [0.004, -30, 0])
        ray_direction = (0.0, 1.0, 0.0)

    wb.view.on_click(Event())
    assert wb.ctrl.inspected == d.samples[k]
    text = wb.panels.inspect.content
    assert f"Sample {d.samples[k]}" in text and "t = " in text and "residual" in text


def test_model_panel_disables_effects_the_data_cannot_support(bench):
    ds = magcal.simulate("chi2017", n_samples=200, seed=1)  # no time, no temperature
    wb = bench(ds)
    boxes = wb.panels.effect_boxes
    assert "temperature_bias" in boxes and "nonlinearity_quadratic" in boxes
    assert boxes["temperature_bias"].disabled and "temperature" in boxes["temperature_bias"].hint
    assert boxes["bias_drift"].disabled and "time" in boxes["bias_drift"].hint
    assert not boxes["nonlinearity_quadratic"].disabled
    boxes["nonlinearity_quadratic"].value = True
    assert wb.ctrl.state.effects == ["nonlinearity_quadratic"]
    assert "nonlinearity_quadratic" in wb.panels.status.content


def test_session_autosaves_and_reopens(bench, tmp_path):
    wb = bench()
    _click(wb, wb.panels.btn_run)
    wb.ctrl.select([1, 2, 3, 250])
    wb.panels.effect_boxes["temperature_bias"].value = True
    rms = wb.ctrl.residual_rms_nT()
    sid = wb.ctrl.session_id
    saved = json.loads((tmp_path / "sessions" / sid / "session.json").read_text())
    assert saved["effects"] == ["temperature_bias"]
    wb.stop()
    again = bench()  # the same file: its session comes back
    assert again.ctrl.session_id == sid
    assert list(again.ctrl.state.selection.rejected_indices) == [1, 2, 3, 250]
    assert again.ctrl.state.effects == ["temperature_bias"]
    assert again.ctrl.calibration is not None and np.isfinite(again.ctrl.residual_rms_nT())
    assert len(again.ctrl.state.history) == len(wb.ctrl.state.history)
    assert "Rejected: 4 of 300" in again.panels.status.content
    assert abs(again.ctrl.residual_rms_nT() - rms) < 0.5
    again.panels.session_choice.value = sid
    assert sid in again.panels.session_choice.options


def test_downloads(bench):
    wb = bench(store=False)
    _click(wb, wb.panels.btn_run)
    wb.panels.btn_dl_cal.value = True
    name, content = wb.downloads.last
    doc = json.loads(content)
    assert name == "calibration.json" and doc["format"] == "magcal-calibration" and len(doc["sensors"]) == 4
    wb.ctrl.select([0, 1])
    assert wb.worker.wait(60)
    wb.panels.btn_dl_csv.value = True
    name, content = wb.downloads.last
    assert name == "corrected.csv"
    path = wb.ctrl.dataset.source + ".corrected.csv"
    with open(path, "wb") as fh:
        fh.write(content)
    back = mio.read_csv(path)
    total = np.linalg.norm(back.readings_nT, axis=2)
    kept = back.extra["kept"].astype(bool)
    assert list(np.flatnonzero(~kept)) == [0, 1]
    assert np.sqrt(np.mean((total[:, kept] - 50_000.0) ** 2)) < 1.2 * SIGMA


def test_upload_replaces_the_data(bench, tmp_path):
    wb = bench(store=False)
    other = magcal.simulate("chi2017", n_samples=150, seed=9)
    path = _csv(tmp_path, other, "other.csv")

    class Upload:
        name = "other.csv"
        content = path.read_bytes()

    wb.panels.upload._impl.value = Upload()  # what the browser's upload sets
    wb.uploads.do_upload(None)
    assert wb.worker.wait(60)
    assert wb.ctrl.dataset.n_samples == 150 and "Rejected: 0 of 150" in wb.panels.status.content
    bad = b"s1x,s1y\n1,2\n"

    class Broken:
        name = "broken.csv"
        content = bad

    wb.panels.upload._impl.value = Broken()
    wb.uploads.do_upload(None)
    assert wb.worker.wait(60)
    assert "broken.csv" in wb.ctrl.message and wb.ctrl.dataset.n_samples == 150


def test_lesson_answer_stays_hidden_until_asked(bench):
    wb = bench()
    lesson = list_lessons()[0]
    wb.panels.lesson_choice.value = lesson.title  # the list shows titles
    _click(wb, wb.panels.btn_lesson)
    assert wb.ctrl.state.lesson == lesson.slug
    assert lesson.title in wb.panels.lesson_guide.content
    answer = lesson.answer()["effects"]
    assert all(a.partition(":")[0] not in wb.panels.lesson_guide.content for a in answer)
    assert wb.panels.lesson_feedback.content == ""
    wb.panels.btn_check.value = True
    assert "Keep looking" in wb.panels.lesson_feedback.content
    wb.panels.btn_answer.value = True
    assert all(a in wb.panels.lesson_feedback.content for a in answer)
    assert wb.ctrl.state.answer_revealed


def test_two_browsers_share_one_state(bench):
    from magcal_workbench.app import Workbench

    wb = bench(store=False)
    assert isinstance(wb, Workbench)
    # every widget and scene node lives on the server (not on one client), so every browser sees them
    assert wb.panels.status._impl.gui_api is wb.server.gui
    assert all(h._impl.api is wb.server.scene for h in wb.scene_view._clouds.values())


def test_diagnose_then_add_brings_the_rms_to_the_floor(bench):
    from magcal.model.terms import EFFECTS

    hidden = EFFECTS["temperature_bias"](sensor=1).perturbation(4.0, 1)
    ds = magcal.simulate_timeseries("chi2017", n_samples=600, seed=11, rate_hz=4.0, perturbations=[hidden])
    wb = bench(ds, store=False)
    _click(wb, wb.panels.btn_run)
    floor = wb.ctrl.floor_nT()
    before = wb.ctrl.residual_rms_nT()
    assert before > 1.15 * floor  # the base model is not enough
    _click(wb, wb.panels.btn_diagnose)
    assert wb.ctrl.diagnosis.verdict == "missing_effect"
    assert safe_text(wb.ctrl.diagnosis.where_text(), 120) in wb.ctrl.message  # how long, and on which cores
    assert wb.panels.candidate_choice.value == "temperature_bias:2"
    assert "temperature_bias:2" in wb.panels.candidates.content
    assert wb.evidence.plot is not None and wb.evidence.plot.visible
    _click(wb, wb.panels.btn_add)
    after = wb.ctrl.residual_rms_nT()
    assert wb.ctrl.state.effects == ["temperature_bias:2"]
    assert wb.ctrl.state.history[-1].step == "add temperature_bias:2"
    assert after < 1.1 * wb.ctrl.floor_nT() and after < before
    assert wb.panels.effect_boxes["temperature_bias"].value  # the model panel follows
    x, y, f = wb.ctrl.state.rms_series()
    assert y[-1] < y[-2] < y[0] and np.isfinite(f[-1])
    data = wb.panels.rms_plot.data
    assert np.allclose(data[1], y, equal_nan=True)


def test_command_line_serves_the_demo_on_loopback(tmp_path):
    import subprocess
    import sys

    from magcal_workbench.app import host_warning, main

    assert host_warning("127.0.0.1") is None and "0.0.0.0" in host_warning("0.0.0.0")
    assert main([str(tmp_path / "missing.csv"), "--no-session"]) == 2
    proc = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "from magcal_workbench.app import main; main()",
            "--port",
            "0",
            "--session-dir",
            str(tmp_path / "s"),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        line = ""
        deadline = time.time() + 120
        while "open http" not in line and time.time() < deadline:
            line = proc.stdout.readline()
        assert re.search(r"open http://127\.0\.0\.1:\d+/\?token=[\w-]{40,} ", line), line
        assert list((tmp_path / "s").iterdir())[0].name.startswith("demo-")  # the bundled demo, autosaved
    finally:
        proc.terminate()
        proc.wait(30)


@pytest.mark.parametrize("fit_magnitude", [False, True])
def test_reference_field_entry(bench, fit_magnitude):
    wb = bench(store=False)
    wb.panels.reference.value = 50_000.0
    wb.panels.fit_reference.value = fit_magnitude
    assert wb.ctrl.state.reference_nT == 50_000.0 and wb.ctrl.state.fit_reference == fit_magnitude
    _click(wb, wb.panels.btn_run)
    cal = wb.ctrl.calibration
    assert cal.reference_fitted == fit_magnitude
    if fit_magnitude:  # det C^-1 = 1 for sensor 1: the field comes out within the sensor's mean gain error
        assert abs(cal.reference_total_nT - 50_000.0) < 0.02 * 50_000.0
    else:
        assert cal.reference_total_nT == 50_000.0
    assert wb.ctrl.residual_rms_nT() < 1.1 * SIGMA


def test_single_sensor_data(bench):
    ds = magcal.simulate("ding2024", n_samples=300, seed=2)
    wb = bench(ds, store=False)
    assert wb.panels.sensor_choice.options == ("sensor 1",) and not wb.panels.btn_align.visible
    _click(wb, wb.panels.btn_run)
    sigma = ds.noise_nT
    assert 0.8 * sigma < wb.ctrl.residual_rms_nT() < 1.2 * sigma
    assert wb.scene_view.displayed.positions.shape[0] == 2 * 300
    assert wb.ctrl.tensor_rms() is None and "| Gzz |" not in wb.panels.sensors_table.content
    wb.actions.do_align(None)
    assert wb.worker.wait(30) and "at least two sensors" in wb.ctrl.message


def test_reopen_a_saved_session_and_start_afresh(bench, tmp_path):
    wb = bench()
    first = wb.ctrl.session_id
    _click(wb, wb.panels.btn_run)
    wb.ctrl.select([5, 6, 7])
    assert wb.worker.wait(60)
    other = magcal.simulate("chi2017", n_samples=120, seed=4)
    path = _csv(tmp_path, other, "other.csv")

    class Upload:
        name = "other.csv"
        content = path.read_bytes()

    wb.panels.upload._impl.value = Upload()
    wb.uploads.do_upload(None)
    assert wb.worker.wait(60) and wb.ctrl.dataset.n_samples == 120
    assert first in wb.panels.session_choice.options
    wb.panels.session_choice.value = first
    _click(wb, wb.panels.btn_reopen)
    assert wb.ctrl.session_id == first and wb.ctrl.dataset.n_samples == 300
    assert list(wb.ctrl.state.selection.rejected_indices) == [5, 6, 7]
    assert wb.ctrl.calibration is not None
    _click(wb, wb.panels.btn_fresh)
    assert wb.ctrl.state.selection.n_rejected == 0 and wb.ctrl.calibration is None
    assert [r.step for r in wb.ctrl.state.history] == ["raw readings"]


def test_the_two_effect_lesson_can_be_followed_to_adequate(bench):
    """The lesson's guide: calibrate, diagnose, add the top candidate, refit, repeat until `adequate`."""
    lesson = next(l for l in list_lessons() if len(l.answer()["effects"]) >= 2)
    wb = bench(mio.read_csv(lesson.data_path), store=False)
    _click(wb, wb.panels.btn_run)
    for _ in range(3):
        _click(wb, wb.panels.btn_diagnose)
        if wb.ctrl.diagnosis.verdict == "adequate":
            break
        assert wb.ctrl.diagnosis.verdict == "missing_effect"
        _click(wb, wb.panels.btn_add)
    assert wb.ctrl.diagnosis.verdict == "adequate"
    assert lesson.check(wb.ctrl.state.effects)["solved"]
    assert wb.ctrl.residual_rms_nT() < 1.02 * wb.ctrl.floor_nT()


def test_a_fit_that_does_not_converge_says_so(bench, monkeypatch):
    """The engine's FitResult.success/message reach the status, the history and the session file."""
    import importlib

    fitter = importlib.import_module("magcal.fitting.fitter")
    real = fitter.fit
    # the pipeline's maximum-likelihood step calls the fitter by the name it imported
    monkeypatch.setattr("magcal.fitting.pipeline.fit", lambda *a, **kw: real(*a, **{**kw, "max_nfev": 2}))
    wb = bench()
    _click(wb, wb.panels.btn_run)
    status = wb.panels.status.content
    assert "did not converge" in status and "maximum number of evaluations" in status and "Refine" in status
    assert "did not converge" in wb.panels.history.content and "did not converge" in wb.ctrl.message
    saved = json.loads((wb.store.root / wb.ctrl.session_id / "session.json").read_text())
    fit = saved["history"][-1]["fit"]
    assert fit["success"] is False and fit["status"] == 0 and fit["nfev"] >= 2
    monkeypatch.undo()
    _click(wb, wb.panels.btn_refine)  # continues from where it stopped, with the full budget
    assert "did not converge" not in wb.panels.status.content
    assert wb.ctrl.state.history[-1].fit["success"] is True
    assert wb.ctrl.residual_rms_nT() < 1.1 * SIGMA


def test_writing_the_state_into_the_widgets_changes_nothing(bench):
    """Refresh writes the state into bound widgets; their callbacks see nothing to do (no per-sensor effect widened
    to all sensors, no autosave), while a user's change still goes through."""
    wb = bench(store=False)
    st = wb.ctrl.state
    st.add_effect("temperature_bias:2")
    st.method, st.reference_nT, st.robust, st.sensor = "de", 51_000.0, True, 2
    version = st.version
    wb.panels.refresh(("all", "data"))
    p = wb.panels
    assert p.effect_boxes["temperature_bias"].value and p.method.value == "de" and p.robust.value
    assert p.reference.value == 51_000.0 and p.sensor_choice.value == "sensor 3"
    assert st.effects == ["temperature_bias:2"] and st.version == version
    p.effect_boxes["temperature_bias"].value = False  # the user unticks it
    assert st.effects == [] and st.version > version
    p.sensor_choice.value = "all sensors"
    assert st.sensor is None and wb.scene_view.displayed.positions.shape[0] == 4 * 300


def test_upload_and_download_use_no_temporary_file(bench, tmp_path, monkeypatch):
    import tempfile

    wb = bench(store=False)
    _click(wb, wb.panels.btn_run)

    def refuse(*a, **kw):
        raise AssertionError("a temporary file was made")

    for name in ("mkstemp", "TemporaryDirectory", "NamedTemporaryFile", "mkdtemp"):
        monkeypatch.setattr(tempfile, name, refuse)
    wb.downloads.do_download_corrected(None)
    name, content = wb.downloads.last

    class Broken:
        name = "rows.csv"
        content = b"s1x,s1y,s1z\n50000,1,2\n50001,oops,2\n"

    wb.panels.upload._impl.value = Broken()
    wb.uploads.do_upload(None)
    assert wb.worker.wait(60)
    assert "rows.csv: 1 row(s) with bad values: line 3, column s1y" in wb.ctrl.message
    monkeypatch.undo()
    assert name == "corrected.csv" and content == _csv_bytes(tmp_path, wb)


def _csv_bytes(tmp_path, wb):
    """What write_csv makes of the workbench's corrected data (the download must be the same file)."""
    ctrl = wb.ctrl
    extra = dict(ctrl.dataset.extra, kept=ctrl.kept.astype(int))
    extra.update({f"s{s + 1}_residual_nT": ctrl.residual_nT[s] for s in range(ctrl.dataset.n_sensors)})
    path = tmp_path / "expected.csv"
    mio.write_csv(
        path,
        ctrl.dataset.replace(readings_nT=ctrl.corrected_nT, extra=extra),
        metadata={
            "corrected_by": "magcal workbench",
            "frame": ctrl.calibration.frame,
            "effects": "none",
            "record_only_terms_applied": "none",
        },
    )
    return path.read_bytes()


# ---------------------------------------------------------------------------------------------------------------
# the user's own effects (item 7): loaded from a file, in the Model tab, Diagnose and the session
# ---------------------------------------------------------------------------------------------------------------
EXAMPLE = Path(__file__).resolve().parents[1] / "helpers" / "user_effects_example.py"
PUMP = "pump_interference"
PUMP_SENSOR = 1  # 0-based: the pump is hidden in sensor 2


class Yes:
    """A terminal where the user confirms every effects file asked for (:class:`magcal_workbench.consent.Terminal`'s
    ``ask``); tests/workbench/test_workbench_consent.py asks a real pseudo-terminal."""

    def ask(self, question, timeout_s, cancel):
        return "yes"


@pytest.fixture(scope="module")
def pump_data():
    """chi2017 time series (four sensors, 3 nT noise, 10 Hz) hiding a 4 nT pump field at 1.3 Hz in sensor 2 (made
    with the example file's own perturbation, as tests/model/test_plugins.py does)."""
    from magcal.model import plugins
    from magcal.model.terms import EFFECTS

    before = dict(EFFECTS)
    try:
        plugins.load_effects_file(EXAMPLE)
        pump = EFFECTS[PUMP]().perturbation(4.0, PUMP_SENSOR)
        return magcal.simulate_timeseries("chi2017", n_samples=600, seed=3, perturbations=[pump])
    finally:
        EFFECTS.clear()
        EFFECTS.update(before)
        plugins._ORIGINS.clear(), plugins._SOURCES.clear(), plugins._USER_FILES.clear()


@pytest.mark.parametrize("how", ["diagnose and add", "tick and refit"])
def test_a_user_effect_from_a_file_joins_the_loop(clean_catalogue, pump_data, how):
    from magcal_workbench.controller import Controller

    ctrl = Controller(pump_data)
    assert PUMP not in [e["name"] for e in ctrl.available_effects()]
    ctrl.step_calibrate()
    base = ctrl.residual_rms_nT()
    assert base > 1.04 * SIGMA  # the pump is not explained by the base model
    assert ctrl.load_effects_file(EXAMPLE) == [PUMP]
    entry = {e["name"]: e for e in ctrl.available_effects()}[PUMP]
    assert entry["origin"] == "file" and entry["source"] == str(EXAMPLE.resolve()) and entry["missing"] == []
    assert ctrl.state.effects_files == [str(EXAMPLE.resolve())]
    if how == "diagnose and add":
        d = ctrl.step_diagnose()
        assert d.verdict == "missing_effect" and d.candidates[0].label == f"{PUMP}:{PUMP_SENSOR + 1}"
        ctrl.step_add()  # the top candidate, refitted
        label = f"{PUMP}:{PUMP_SENSOR + 1}"
    else:
        assert ctrl.set_effect(PUMP, True)
        ctrl.step_refine()
        label = PUMP
    after = ctrl.residual_rms_nT()
    assert ctrl.state.effects == [label] and ctrl.calibration.model.effect_labels == [label]
    assert after < base / 1.03 and after < 1.01 * SIGMA  # down to the noise


@pytest.mark.parametrize(
    "label, says",
    [
        ("not_loaded", "Load effects file"),
        ("<img src=x>", "not an effect label"),
        ("temperature_bias:5", "no sensor 5"),
    ],
)
def test_an_effect_label_the_page_could_not_offer_is_refused(clean_catalogue, pump_data, label, says):
    from magcal.core.errors import MagcalError
    from magcal_workbench.controller import Controller

    ctrl = Controller(pump_data)
    for action in (lambda: ctrl.set_effect(label, True), lambda: ctrl.step_add(label)):
        with pytest.raises(MagcalError, match=says):
            action()
    assert ctrl.state.effects == []


def test_the_session_loads_its_effects_files_again(bench, clean_catalogue, pump_data, tmp_path):
    from magcal.model import plugins
    from magcal.model.terms import EFFECTS

    wb = bench(pump_data, effects_files=[str(EXAMPLE)])  # the page loads a file of the command line
    assert PUMP not in wb.panels.effect_boxes
    assert "runs its Python code" in wb.panels.effects_warning.content and not wb.panels.btn_load_effects.disabled
    wb.panels.effects_path.value = str(EXAMPLE)
    _click(wb, wb.panels.btn_load_effects)
    assert PUMP in wb.panels.effect_boxes  # the Model tab's list grows without a restart
    assert "pump" in wb.panels.user_effects.content and str(EXAMPLE.resolve()) in wb.ctrl.message
    wb.panels.effect_boxes[PUMP].value = True
    _click(wb, wb.panels.btn_refine)
    assert wb.ctrl.calibration.model.effect_labels == [PUMP]
    saved = json.loads((tmp_path / "sessions" / wb.ctrl.session_id / "session.json").read_text())
    assert saved["effects_files"] == [str(EXAMPLE.resolve())] and saved["effects"] == [PUMP]
    rms = wb.ctrl.residual_rms_nT()
    wb.stop()
    plugins.unregister(PUMP)  # as in a new process: the effect is not loaded
    plugins._USER_FILES.clear()
    again = bench(pump_data, terminal=Yes())  # the user confirms the file in the terminal
    # reopening runs no code: the page says the session names the file and offers to load it
    assert PUMP not in EFFECTS and again.ctrl.calibration is None
    assert "effects\\_example.py" in again.ctrl.message and "not loaded" in again.ctrl.message
    assert again.panels.btn_session_effects.visible and "runs with your rights" in again.panels.session_effects.content
    _click(again, again.panels.btn_session_effects)  # the user's choice
    assert PUMP in EFFECTS and again.panels.effect_boxes[PUMP].value and not again.panels.btn_session_effects.visible
    assert again.ctrl.calibration.model.effect_labels == [PUMP]  # the saved calibration, with the effect
    assert abs(again.ctrl.residual_rms_nT() - rms) < 1e-6


def test_a_missing_effects_file_does_not_stop_the_session(bench, clean_catalogue, tmp_path):
    wb = bench()
    gone = tmp_path / "gone.py"
    wb.ctrl.state.effects_files.append(str(gone))
    wb.ctrl.autosave()
    wb.stop()
    again = bench()
    assert "gone.py" in again.ctrl.message and again.panels.btn_session_effects.visible
    _click(again, again.panels.btn_session_effects)
    assert "no such effects file" in again.ctrl.message
    assert again.ctrl.state.effects_files == [str(gone)]  # kept: the file may come back


def test_opening_a_session_runs_none_of_its_effects_files(bench, clean_catalogue, tmp_path):
    """A session (one someone sent you) whose effects file would write a marker: opening it, reopening it
    from the Files tab, writes nothing; the marker appears only when the user presses Load."""
    marker = tmp_path / "marker"
    evil = tmp_path / "evil.py"
    evil.write_text(f"open({str(marker)!r}, 'w').write('ran')\n")
    wb = bench()
    sid = wb.ctrl.session_id
    wb.ctrl.state.effects_files.append(str(evil))
    wb.ctrl.autosave()
    wb.stop()
    again = bench()
    assert again.ctrl.session_id == sid and again.ctrl.state.effects_files == [str(evil)]
    assert not marker.exists()
    assert "evil.py" in again.ctrl.message and "Python code that runs with your rights" in again.ctrl.message
    again.panels.session_choice.value = sid
    _click(again, again.panels.btn_reopen)
    assert not marker.exists() and again.panels.btn_session_effects.visible
    again.local = False  # served beyond this machine: the page may not run it at all
    _click(again, again.panels.btn_session_effects)
    assert not marker.exists() and "allowed only when" in again.ctrl.message
    again.local = True
    _click(again, again.panels.btn_session_effects)  # neither named on the command line nor confirmed
    assert not marker.exists() and "evil.py not loaded" in again.ctrl.message
    again.effects_gate.terminal = Yes()
    _click(again, again.panels.btn_session_effects)
    assert marker.read_text() == "ran"


def test_an_error_in_the_user_code_is_a_clear_message(bench, clean_catalogue, tmp_path, capsys):
    path = tmp_path / "warm.py"
    path.write_text(
        "from dataclasses import dataclass\n"
        "from typing import ClassVar\n"
        "import numpy as np\n"
        "from magcal.model.terms import Effect, register\n"
        "\n"
        "@register\n"
        "@dataclass\n"
        "class Warm(Effect):\n"
        "    name: ClassVar[str] = 'warm_offset'\n"
        "    def param_names(self):\n"
        "        return ['w_x_nT_per_K', 'w_y_nT_per_K', 'w_z_nT_per_K']\n"
        "    def raw_basis(self, z0, ctx):\n"
        "        dT = ctx.temperature_C - 20.0\n"  # line 13: the user forgot to declare the channel
        "        return np.eye(3)[None] * dT[:, None, None]\n"
    )
    ds = magcal.simulate_timeseries("chi2017", n_samples=300, seed=2, rate_hz=2.0).replace(temperature_C=None)
    wb = bench(ds, store=False, effects_files=[str(path)])
    wb.panels.effects_path.value = str(path)
    _click(wb, wb.panels.btn_load_effects)
    wb.panels.effect_boxes["warm_offset"].value = True
    _click(wb, wb.panels.btn_refine)
    message = wb.ctrl.message
    assert message.startswith("**Error in your effect's code:**") and "line 13, in raw\\_basis: TypeError" in message
    assert "dT = ctx.temperature\\_C - 20.0" in message and "Traceback" not in message
    assert "Traceback" not in capsys.readouterr().err


def test_loading_an_effects_file_is_refused_when_served_beyond_this_machine(bench, clean_catalogue):
    from magcal.core.errors import MagcalError

    wb = bench(store=False)
    wb.local = False  # as with --host 0.0.0.0
    wb.panels.effects_path.value = str(EXAMPLE)
    with pytest.raises(MagcalError, match="runs its Python code on the server"):
        wb.steps.do_load_effects(None)
    assert PUMP not in wb.panels.effect_boxes


def test_command_line_effects_files(tmp_path, capsys, clean_catalogue, monkeypatch):
    from magcal.model import plugins
    from magcal_workbench.app import build_parser, main

    args = build_parser().parse_args(["--effects-file", "a.py", "--effects-file", "b.py"])
    assert args.effects_file == ["a.py", "b.py"]
    calls = []
    monkeypatch.setattr(plugins, "load_entry_points", lambda *a, **kw: calls.append(1) or Loaded())
    missing = tmp_path / "missing.py"
    assert main(["--no-session", "--effects-file", str(missing)]) == 2
    err = capsys.readouterr().err
    assert f"{missing}: no such effects file" in err and "Traceback" not in err
    assert calls == [1]  # installed packages' effects are loaded at start


@pytest.mark.parametrize("large", [True, False])
def test_opening_a_large_record_starts_the_diagnosis_workers_fork_server(monkeypatch, large):
    """A session on a record whose diagnosis would run in worker processes starts their fork server as it opens
    (magcal.diagnosis.start_workers), so the first Diagnose does not wait for its imports; a small one does not."""
    import multiprocessing.forkserver as forkserver

    from magcal.diagnosis import _parallel
    from magcal_workbench import controller

    calls = []
    real = controller.start_workers
    monkeypatch.setattr(controller, "start_workers", lambda ds, **kw: calls.append(real(ds, **kw)) or calls[-1])
    monkeypatch.setattr(_parallel, "PARALLEL_FITS", 2)
    monkeypatch.setattr(_parallel, "PROCESS_MIN_READINGS", 100 if large else 10**9)
    ds = magcal.simulate_timeseries("chi2017", n_samples=300, seed=3)
    controller.Controller(ds)
    assert calls == [large]
    if large:
        pid = forkserver._forkserver._forkserver_pid
        assert pid is not None and Path(f"/proc/{pid}").exists()
