"""The vector model in the workbench: the attitude-aided fit beside the
total-field fit, the reference from a location typed in the page, the vehicle view's geometry and nodes, and the
lesson judged on the vector fit.

Controller-level tests run headless on simulated vehicles whose mounting is set here; the vehicle view is driven
through the panels' own widgets on a real server (loopback); one Chromium test drives the page.
"""

from __future__ import annotations

import json
import re
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from magcal.core.errors import MagcalError
from magcal.data.vehicle import simulate_vehicle
from magcal.geometry.orientations import RIGHT_ANGLES, describe_right_angle
from magcal_workbench import vehicleview as vv
from magcal_workbench.controller import Controller
from magcal_workbench.lessons import get_lesson
from magcal_workbench.sessionfile import SessionFileError, read_session_document

#: A second right-angle mounting beside the simulator's default (ROLL_180_YAW_90): x -> body z, y -> body x,
#: z -> body y (the columns are where the sensor's axes point in the body).
OTHER_MOUNTING = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])


def _vehicle(mounting=None, n=1500, seed=4, attitude_noise_deg=0.05, **kw):
    return simulate_vehicle(n=n, seed=seed, attitude_noise_deg=attitude_noise_deg, mounting=mounting, **kw)


def _name(right_angle) -> str:
    return describe_right_angle(right_angle).split(" ")[0]


# --- the controller's vector step -------------------------------------------------------------------------------
@pytest.mark.parametrize("mounting", [None, OTHER_MOUNTING], ids=["roll180yaw90", "permuted"])
def test_the_vector_step_finds_the_mounting_and_the_world_components(mounting):
    ds, truth = _vehicle(mounting)
    ctrl = Controller(ds)
    assert ctrl.vector.available and ctrl.vector.attitude_kind() == "quaternion"
    ctrl.step_calibrate("ml")
    total_before = ctrl.residual_rms_nT()
    ctrl.step_vector()
    row = ctrl.vector.vector_row()
    true_r = truth.sensors[0].mounting
    expected = RIGHT_ANGLES[np.argmin([np.linalg.norm(a - true_r) for a in RIGHT_ANGLES])]
    assert row.mounting[0].startswith(_name(expected))
    off = float(row.mounting[0].split(", ")[1].split()[0])
    assert off == pytest.approx(2.0, abs=0.05)
    found = ctrl.vector.result.sensors[0].mounting
    assert np.degrees(Rotation.from_matrix(found @ true_r.T).magnitude()) < 0.05
    # the world residual sits at the attitude error's floor: sqrt(2/3) * sigma_att * |B| per component
    floor = np.sqrt(2.0 / 3.0) * np.radians(0.05) * np.linalg.norm(truth.field_ned_nT)
    world = float(np.sqrt(np.mean(row.world_rms_nT**2)))
    assert 0.8 * floor < world < 1.2 * floor
    assert row.total_field_rms_nT == pytest.approx(3.0, rel=0.15)  # the sensor noise
    assert "estimated" in row.attitude_noise[0]
    assert float(row.attitude_noise[0].split()[0]) == pytest.approx(0.05, rel=0.15)
    # the total-field calibration is left as it was
    assert ctrl.residual_rms_nT() == total_before and ctrl.calibration.mode != "vector"


def test_the_total_field_fit_is_said_undetermined_on_a_cone_and_not_on_a_tumble():
    cone, _ = _vehicle()
    ctrl = Controller(cone)
    ctrl.step_calibrate("ml")
    warned = ctrl.vector.scalar_row().undetermined
    assert warned and "coverage" in warned[0]
    from magcal_workbench.vectorpanel import comparison_markdown

    assert "undetermined here" in comparison_markdown(ctrl.vector)
    tumble, _ = _vehicle(roll_max_deg=180.0, pitch_max_deg=85.0, turns=6.0, n=3000)
    assert Controller(tumble).vector.scalar_row().undetermined == []
    assert "undetermined" not in comparison_markdown(Controller(tumble).vector)


def test_the_vector_fit_uses_the_kept_samples_only():
    ds, _ = _vehicle(n=800)
    spoiled = ds.readings_nT.copy()
    spoiled[0, 100:140] += 5000.0  # a burst of interference
    ctrl = Controller(ds.replace(readings_nT=spoiled))
    ctrl.step_vector()
    bad = ctrl.vector.vector_row().total_field_rms_nT
    ctrl.state.selection.reject(np.arange(100, 140))
    ctrl.step_vector()
    assert ctrl.vector.result.n_samples == 760
    assert ctrl.vector.vector_row().total_field_rms_nT < bad / 10


def test_without_attitude_or_reference_the_vector_fit_says_what_is_missing():
    import magcal

    ds = magcal.simulate_timeseries("chi2017", n_samples=200, seed=1).replace(attitude_wxyz=None)
    ctrl = Controller(ds)
    assert not ctrl.vector.available and "attitude" in ctrl.vector.missing()[0]
    with pytest.raises(MagcalError, match="needs the attitude"):
        ctrl.step_vector()
    ds, _ = _vehicle(n=300)
    bare = ds.replace(extra={})  # attitude, but no field vector
    ctrl = Controller(bare)
    missing = ctrl.vector.missing()
    assert len(missing) == 1 and "field vector" in missing[0]
    with pytest.raises(MagcalError, match="field vector"):
        ctrl.step_vector()


# --- the location typed in the page ------------------------------------------------------------------------------
def test_a_location_sets_both_references_and_the_session_remembers_it():
    from magcal.checks.reference import igrf_ned_nT

    ds, _ = _vehicle(n=300)
    ctrl = Controller(ds.replace(extra={}))
    loc = ctrl.vector.set_location(53.0, 4.5, 1500.0, "2024-06-01")
    ned = igrf_ned_nT(53.0, 4.5, 1.5, "2024-06-01")[0]
    np.testing.assert_allclose(loc.ned_nT, ned)
    assert ctrl.state.reference_nT == pytest.approx(np.linalg.norm(ned), abs=0.06)
    ref = ctrl.vector.reference()
    assert ref.kind == "igrf" and np.allclose(ref.ned_nT, ned)
    # the session file keeps it, and a controller reopened on it uses it
    doc = json.loads(json.dumps(ctrl.state.to_dict()))
    state = read_session_document(doc)
    assert state.location == {"lat_deg": 53.0, "lon_deg": 4.5, "alt_m": 1500.0, "date": "2024-06-01"}
    again = Controller(ds.replace(extra={}), state=state)
    assert again.vector.location is not None and np.allclose(again.vector.reference().ned_nT, ned)
    ctrl.vector.clear_location()
    assert ctrl.state.location is None and ctrl.state.reference_nT is None and ctrl.vector.reference() is None


def test_the_session_remembers_the_vector_fit_and_reopening_runs_it_again(tmp_path, monkeypatch):
    from magcal_workbench.session import SessionStore

    ds, truth = _vehicle(n=800)
    store = SessionStore(tmp_path / "sessions")
    sid = store.create("flight.csv", b"the data's copy")
    ctrl = Controller(ds, store=store, session_id=sid)
    ctrl.configure(robust=True)
    ctrl.state.selection.reject(np.arange(100, 140))
    ctrl.step_vector()
    fitted = ctrl.vector.result
    assert fitted.n_samples == 760
    # the selection and the settings change after the fit: the fit reopened is the one that was run
    ctrl.state.selection.restore(np.arange(100, 140))
    ctrl.configure(robust=False)
    saved = store.load(sid)
    assert saved.vector_fit is not None and saved.vector_fit["robust"] is True
    again = Controller(ds, state=saved, store=store, session_id=sid)
    res = again.vector.result
    assert res is not None and res.n_samples == 760 and np.array_equal(res.fitted, fitted.fitted)
    for a, b in zip(res.sensors, fitted.sensors):
        assert np.allclose(a.W, b.W, rtol=1e-12, atol=1e-12) and np.allclose(a.bias_nT, b.bias_nT, atol=1e-9)
    assert np.allclose(res.sensors[0].mounting, truth.sensors[0].mounting, atol=1e-3)  # the truth it found
    assert "run again" in again.message and again.vector.vector_row().world_rms_nT is not None
    # a record too large to fit on every opening keeps the settings and says to press the button
    import magcal_workbench.vectormodel as vm

    monkeypatch.setattr(vm, "RESTORE_MAX_SAMPLES", 799)
    big = Controller(ds, state=store.load(sid))
    assert big.vector.result is None and big.state.vector_fit is not None and "press Run the vector fit" in big.message
    monkeypatch.undo()
    # a new reference forgets the fit, and the session with it
    again.vector.set_location(53.0, 4.5, 1500.0, "2024-06-01")
    assert again.vector.result is None and store.load(sid).vector_fit is None
    assert Controller(ds, state=store.load(sid)).vector.result is None
    # a saved fit that cannot run any more (its samples now too few) is said, and the session goes on
    doc = json.loads(json.dumps(ctrl.state.to_dict()))
    doc["vector_fit"]["kept"] = _packed_few(800)
    late = Controller(ds, state=read_session_document(doc))
    assert late.vector.result is None and late.state.vector_fit is None
    assert "could not be run again" in late.message and "too few" in late.message


def _packed_few(n):
    from magcal_workbench.state import pack_mask

    few = np.zeros(n, bool)
    few[:5] = True
    return pack_mask(few)


@pytest.mark.parametrize(
    "vector_fit, field",
    [
        ({"robust": True}, "vector_fit.kept"),
        ({"kept": "@@", "robust": True}, "vector_fit.kept"),
        ({"kept": None, "robust": True}, "vector_fit.kept"),
        ({"kept": "KEPT", "robust": "yes"}, "vector_fit.robust"),
        ({"kept": "KEPT", "robust": False, "noise_nT": -1.0}, "vector_fit.noise_nT"),
        ({"kept": "KEPT", "robust": False, "run": "rm -rf"}, "vector_fit"),
        ([1, 2], "vector_fit"),
    ],
)
def test_a_damaged_vector_fit_in_the_session_file_is_named(vector_fit, field):
    ds, _ = _vehicle(n=100)
    doc = json.loads(json.dumps(Controller(ds).state.to_dict()))
    if isinstance(vector_fit, dict) and vector_fit.get("kept") == "KEPT":
        vector_fit = dict(vector_fit, kept=doc["selection"]["kept"])
    doc["vector_fit"] = vector_fit
    with pytest.raises(SessionFileError) as err:
        read_session_document(doc)
    assert err.value.field == field


@pytest.mark.parametrize(
    "lat, lon, alt, date, words",
    [
        (91.0, 0.0, 0.0, "2024-06-01", "latitude"),
        (0.0, 181.0, 0.0, "2024-06-01", "longitude"),
        (0.0, 0.0, 5e6, "2024-06-01", "altitude"),
        (float("nan"), 0.0, 0.0, "2024-06-01", "latitude"),
        (0.0, 0.0, 0.0, "yesterday", "date"),
        (0.0, 0.0, 0.0, "", "date"),
        (0.0, 0.0, 0.0, "1850-01-01", "outside the IGRF"),
        (True, 0.0, 0.0, "2024-06-01", "latitude"),
    ],
)
def test_a_bad_location_is_refused_with_one_message_and_nothing_changes(lat, lon, alt, date, words):
    ds, _ = _vehicle(n=300)
    ctrl = Controller(ds)
    with pytest.raises(MagcalError, match=words):
        ctrl.vector.set_location(lat, lon, alt, date)
    assert ctrl.state.location is None and ctrl.state.reference_nT is None


@pytest.mark.parametrize(
    "location, field",
    [
        ({"lat_deg": 95.0, "lon_deg": 0.0, "alt_m": 0.0, "date": "2024-01-01"}, "location.lat_deg"),
        ({"lat_deg": 0.0, "lon_deg": 0.0, "alt_m": 0.0}, "location.date"),
        ({"lat_deg": 0.0, "lon_deg": 0.0, "alt_m": 0.0, "date": "x" * 40}, "location.date"),
        ({"lat_deg": 0.0, "lon_deg": 0.0, "alt_m": 0.0, "date": "2024", "cmd": 1}, "location"),
        ("53N", "location"),
    ],
)
def test_a_damaged_location_in_the_session_file_is_named(location, field):
    ds, _ = _vehicle(n=100)
    doc = json.loads(json.dumps(Controller(ds).state.to_dict()))
    doc["location"] = location
    with pytest.raises(SessionFileError) as err:
        read_session_document(doc)
    assert err.value.field == field


# --- the lesson --------------------------------------------------------------------------------------------------
def test_the_vehicle_lesson_is_solved_by_the_vector_fit_with_the_right_reference():
    from magcal_workbench.dataio import load_dataset

    lesson = get_lesson("cannot-tumble")
    ds, notes = load_dataset(lesson.data_path)
    assert notes == [] and ds.n_sensors == 1 and "yaw_deg" in ds.extra and "ref_n" not in ds.extra
    guide = lesson.guide()
    assert "ROLL" not in guide and "rotation 10" not in guide  # the guide never names the answer
    ctrl = Controller(ds)
    site = (53.0, 4.5, 1500.0, "2024-06-01")  # the file's `# site:` line, which the guide's text gives too
    assert ctrl.vector.available and ctrl.vector.from_site()  # the reference comes from the place and date
    assert tuple(ctrl.state.location.values()) == site
    ctrl.step_calibrate("ml")
    assert ctrl.vector.scalar_row().undetermined  # the total-field fit is undetermined here
    first = lesson.check(ctrl.state.effects, ctrl.vector.lesson_findings())
    assert not first["solved"] and "vector fit" in first["message"]
    ctrl.step_vector()
    result = lesson.check(ctrl.state.effects, ctrl.vector.lesson_findings())
    assert result["solved"], result
    assert "ROLL" not in result["message"]
    # ten years off: IGRF's secular change turns the field, the mounting found is off by more than the tolerance
    ctrl.vector.set_location(53.0, 4.5, 1500.0, "2014-06-01")
    ctrl.step_vector()
    wrong = lesson.check(ctrl.state.effects, ctrl.vector.lesson_findings())
    assert not wrong["solved"] and "not the one hidden" in wrong["message"]


def test_an_ordinary_lesson_is_checked_as_before():
    lesson = get_lesson("warm-sensor")
    assert lesson.check(["temperature_bias:2"], None)["solved"]
    assert lesson.check(["temperature_bias:2"], {"mounting": ["NONE"], "angle_off_deg": [0.0]})["solved"]


# --- the vehicle view's geometry ---------------------------------------------------------------------------------
quaternions = st.lists(st.floats(-1, 1, allow_nan=False), min_size=4, max_size=4).filter(
    lambda q: np.linalg.norm(q) > 0.1
)


@settings(max_examples=60, deadline=None)
@given(q=quaternions, v=st.lists(st.floats(-6e4, 6e4, allow_nan=False), min_size=3, max_size=3))
def test_world_vectors_are_the_attitude_times_the_body_vectors(q, v):
    q = np.asarray(q) / np.linalg.norm(q)
    w, x, y, z = q
    R = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
    np.testing.assert_allclose(vv.world_vectors(q, v), R @ np.asarray(v), atol=1e-6)


def test_the_arrows_are_drawn_in_the_world_frame_at_one_scale():
    rng = np.random.default_rng(0)
    q = Rotation.random(random_state=rng).as_quat()
    wxyz = np.r_[q[3], q[:3]]
    body = np.array([12_000.0, -3_000.0, 44_000.0])
    model = np.array([21_000.0, 1_200.0, 44_000.0])
    measured = vv.world_vectors(wxyz, body)
    F = float(np.linalg.norm(model))
    arrows = vv.field_arrows(model, measured, F, gain=100.0)
    L = vv.ARROW_LENGTH
    np.testing.assert_allclose(arrows["model"][0], [np.zeros(3), model * L / F])
    np.testing.assert_allclose(arrows["measured"][0, 1], Rotation.from_quat(q).as_matrix() @ body * L / F)
    np.testing.assert_allclose(arrows["residual"][0, 0], arrows["model"][0, 1])
    np.testing.assert_allclose(arrows["residual"][0, 1] - arrows["residual"][0, 0], 100.0 * (measured - model) * L / F)
    assert set(vv.field_arrows(model, None, F, 1.0)) == {"model"}


def test_the_ned_frame_is_a_proper_rotation_to_a_z_up_scene():
    w, x, y, z = vv.NED_FRAME_WXYZ
    R = Rotation.from_quat([x, y, z, w]).as_matrix()
    np.testing.assert_allclose(R, vv.NED_TO_SCENE, atol=1e-12)
    assert np.linalg.det(vv.NED_TO_SCENE) == pytest.approx(1.0)
    assert (vv.NED_TO_SCENE @ [0, 0, 1])[2] == -1.0  # down is down


@pytest.mark.parametrize("value, gain", [(0.5, 1.0), (1.0, 1.0), (3.7, 2.0), (49.0, 20.0), (363.0, 200.0), (5e3, 5e3)])
def test_the_residual_exaggeration_is_a_round_number(value, gain):
    assert vv.nice_gain(value) == gain


def test_the_arrow_mesh_runs_from_start_to_end():
    start, end = np.array([0.1, -0.2, 0.3]), np.array([1.0, 2.0, -0.5])
    v, f = vv.arrow_mesh(start, end)
    d = (end - start) / np.linalg.norm(end - start)
    along = (v - start) @ d
    assert along.min() == pytest.approx(0.0, abs=1e-9) and along.max() == pytest.approx(np.linalg.norm(end - start))
    assert f.max() < len(v)


def test_the_body_mesh_points_forward_and_its_fin_up():
    (hull, _), (nose, _) = vv.vehicle_mesh()
    assert nose[:, 0].min() > 0.3 * hull[:, 0].max()  # the nose is at +x, the front
    assert hull[:, 2].min() < -0.2 and hull[:, 2].max() < 0.15  # the fin stands at -z: up in a z-down body


# --- the vehicle view on a running workbench ---------------------------------------------------------------------
def test_the_vehicle_view_draws_the_body_and_the_fields_at_the_scrubbers_sample(bench):
    ds, _ = _vehicle(n=600)
    wb = bench(ds=ds)
    p = wb.panels.vector_panel
    assert p.btn_vector.visible and "quaternions" in p.info.content
    wb.ctrl.step_vector()
    assert "ROLL\\_180\\_YAW\\_90" in p.table.content
    (off,) = re.findall(r"([0-9.]+) deg off", p.table.content)  # the simulated sensor sits 2 deg off the right angle
    assert float(off) == pytest.approx(2.0, abs=0.05)
    p.vehicle_on.value = True
    assert wb.window.enabled and wb.vehicle.enabled
    for name in ("/vehicle", "/vehicle/body", "/vehicle/body/hull", "/vehicle/model_field", "/vehicle/measured_field"):
        assert name in wb.vehicle.nodes, name
    for name in ("/vehicle/residual", "/vehicle/axis_N", "/vehicle/axis_E", "/vehicle/axis_D"):
        assert name in wb.vehicle.nodes, name
    d = wb.ctrl.dataset
    first = wb.vehicle.shown["sample"]
    assert first == wb.window.current(d.time_s)
    wb.panels.window_start.value = 60.0
    i = wb.vehicle.shown["sample"]
    assert i != first and i == wb.window.current(d.time_s)
    # the body is turned by that sample's attitude (a quaternion up to its sign), and the measured arrow is
    # R(q) B_body at the drawn scale
    q_drawn = np.asarray(wb.vehicle.nodes["/vehicle/body"].wxyz)
    assert abs(float(q_drawn @ d.attitude_wxyz[i])) == pytest.approx(1.0, abs=1e-9)
    body = wb.ctrl.vector.result.calibration.correct(d)[0, i]
    shown = wb.vehicle.shown
    expected = vv.world_vectors(d.attitude_wxyz[i], body) * vv.ARROW_LENGTH / shown["field_nT"]
    np.testing.assert_allclose(shown["arrows"]["measured"][0, 1], expected, rtol=1e-9)
    np.testing.assert_allclose(wb.vehicle.nodes["/vehicle/measured_field"].points[0, 1], expected, rtol=1e-5)
    assert f"x{shown['gain']:g}" in p.vehicle_info.content
    p.vehicle_gain.value = 1000.0
    assert wb.vehicle.gain == 1000.0
    p.vehicle_on.value = False
    assert wb.vehicle.nodes == {} and not wb.vehicle.enabled


def test_play_flies_the_vehicle_through_the_record(bench):
    ds, _ = _vehicle(n=600)
    wb = bench(ds=ds)
    wb.ctrl.step_vector()
    wb.panels.window_width.value = 2.0
    wb.panels.play_speed.value = 100.0  # 60 s at 100x: the window crosses the record in about half a second
    wb.panels.vector_panel.vehicle_on.value = True
    seen = [wb.vehicle.shown["sample"]]
    wb.view.do_play(None)
    last = wb.ctrl.dataset.n_samples - 1
    end = time.monotonic() + 30
    while (wb.window.playing or seen[-1] != last) and time.monotonic() < end:  # the last move may land late
        if wb.vehicle.shown["sample"] != seen[-1]:
            seen.append(wb.vehicle.shown["sample"])
        time.sleep(0.02)
    assert not wb.window.playing
    assert len(seen) >= 3 and seen == sorted(seen) and seen[-1] == wb.ctrl.dataset.n_samples - 1


def test_the_page_location_inputs_are_checked_and_set_the_reference(bench):
    ds, _ = _vehicle(n=300)
    wb = bench(ds=ds.replace(extra={}))
    p = wb.panels.vector_panel
    assert not wb.ctrl.vector.available and "field vector" in p.info.content
    p.lat.value, p.lon.value, p.alt.value, p.date.value = 53.0, 4.5, 1500.0, "2024-06-01"
    wb.vehicle.do_use_location(None)
    assert wb.ctrl.vector.available and "IGRF" in p.location_info.content
    assert wb.panels.reference.value == pytest.approx(wb.ctrl.state.reference_nT)
    p.lat.value = 123.0  # a value the page could not have offered
    with pytest.raises(MagcalError, match="Latitude"):
        wb.vehicle.do_use_location(None)
    assert wb.ctrl.state.location["lat_deg"] == 53.0 and p.lat.value == 90.0  # put back within range


def test_the_vehicle_lesson_opens_with_the_files_site_as_the_reference(bench):
    """The Lessons tab opens the lesson: the location inputs hold the file's `# site:` line, IGRF there is the
    reference (scalar and vector), the page says where the values came from; the student may change them, and a
    location forgotten stays forgotten when the lesson's session reopens."""
    lesson = get_lesson("cannot-tumble")
    wb = bench()
    wb.panels.lesson_choice.value = lesson.title
    wb.lessons.do_open_lesson(None)
    assert wb.worker.wait(60)
    wb.ui.wait()
    ctrl, p = wb.ctrl, wb.panels.vector_panel
    assert ctrl.state.lesson == "cannot-tumble"
    assert (p.lat.value, p.lon.value, p.alt.value, p.date.value) == (53.0, 4.5, 1500.0, "2024-06-01")
    assert ctrl.vector.available and ctrl.vector_loop() and ctrl.vector.reference().kind == "igrf"
    total = ctrl.vector.location.total_nT
    assert 45_000 < total < 55_000 and ctrl.state.reference_nT == pytest.approx(total, abs=0.05)
    assert wb.panels.reference.value == pytest.approx(ctrl.state.reference_nT)
    assert "From the file's `# site:` line" in p.location_info.content
    shown = wb.panels.reference_info.content  # the Calibrate tab's reference says where both come from
    assert "IGRF at the file's `# site:` line" in shown and "IGRF's |B| at the file's `# site:` line" in shown
    said = ctrl.message.replace("\\", "")  # markdown escapes taken out
    assert "reference from the file's `# site:` line** (53.0 N, 4.5 E, 1500 m, 2024-06-01)" in said
    assert "type where and when" not in wb.panels.guide.content  # the guide goes on to the vector fit
    p.date.value = "2014-06-01"  # the student changes the date
    wb.vehicle.do_use_location(None)
    assert ctrl.state.location["date"] == "2014-06-01" and not ctrl.vector.from_site()
    assert "From the file's" not in p.location_info.content
    assert "IGRF's |B| at the location below" in wb.panels.reference_info.content
    wb.vehicle.do_forget_location(None)
    wb.lessons.do_open_lesson(None)  # its saved session reopens: the student's choice holds
    assert wb.worker.wait(60)
    wb.ui.wait()
    assert wb.ctrl is not ctrl and wb.ctrl.state.location is None and not wb.ctrl.vector.available


def test_a_site_igrf_cannot_take_is_said_and_the_record_opens_without_it(tmp_path):
    from magcal_workbench.dataio import load_dataset

    ds, _ = load_dataset(get_lesson("cannot-tumble").data_path)
    meta = dict(ds.metadata, site="53.0 N, 4.5 E, 1500 m, 1850-01-01", site_date="1850-01-01")
    ctrl = Controller(ds.replace(metadata=meta))
    assert ctrl.state.location is None and not ctrl.vector.available
    assert "could not be used" in ctrl.message and "type the place and date" in ctrl.vector.location_note


def test_a_record_with_a_track_keeps_igrf_along_it_over_its_site():
    """A file with a ``# site:`` line and ``lat, lon`` columns: the page does not fill the location from the site;
    the vector reference is IGRF along the track, as ``--reference igrf`` gives it."""
    from magcal.checks.reference import resolve_vector_reference
    from magcal_workbench.dataio import load_dataset

    ds, _ = load_dataset(get_lesson("cannot-tumble").data_path)
    n = ds.n_samples
    track = {"lat": np.linspace(-20.0, -19.5, n), "lon": np.full(n, 140.0), "alt_m": np.zeros(n)}
    ctrl = Controller(ds.replace(extra={**ds.extra, **track}))
    assert ctrl.state.location is None and "site" not in ctrl.message
    ref = ctrl.vector.reference()
    expected = resolve_vector_reference(ctrl.dataset, "igrf")
    assert ref.kind == "igrf-track" and "# site: line" not in ref.text
    np.testing.assert_array_equal(ref.ned_nT, expected.ned_nT)


# --- in the page --------------------------------------------------------------------------------------------------
@pytest.mark.e2e
@pytest.mark.slow
def test_the_vehicle_lesson_in_the_page(browser, bench, tmp_path):
    """In Chromium: open the lesson's data, find the place and date of the file's `# site:` line in the location
    inputs, run the vector fit from the page, read the mounting it names, and show the vehicle view."""
    from magcal_workbench.dataio import load_dataset
    from tests.workbench.test_workbench_e2e import _dismiss_toasts, _open

    ds, _ = load_dataset(get_lesson("cannot-tumble").data_path)
    wb = bench(ds=ds, max_points=300)  # software WebGL: a small scene keeps the page responsive
    page = _open(browser, wb)
    folder = page.locator("div").filter(has_text=re.compile(r"^Reference from a location \(IGRF\)$")).first
    folder.click()  # the folder's title (the message above names it too)
    p = wb.panels.vector_panel
    page.wait_for_function("() => document.body.innerText.includes('Location in use')", timeout=60_000)
    filled = (("Latitude deg", "53", p.lat, 53.0), ("Longitude deg", "4.5", p.lon, 4.5))
    filled += (("Altitude m", "1500", p.alt, 1500.0), ("Date", "2024-06-01", p.date, "2024-06-01"))
    for label, text, handle, value in filled:  # the file's site, shown in the inputs: nothing to type
        box = page.locator(f"label:text-is('{label}')").locator("xpath=ancestor::div[.//input][1]//input").first
        assert box.input_value() == text and handle.value == value, label
    assert "From the file's # site: line" in page.inner_text("body")
    assert wb.ctrl.state.location == {"lat_deg": 53.0, "lon_deg": 4.5, "alt_m": 1500.0, "date": "2024-06-01"}
    page.get_by_role("button", name="Run the vector fit (attitude-aided)").click()
    page.wait_for_function("() => document.body.innerText.includes('deg off it')", timeout=120_000)
    text = page.inner_text("body", timeout=120_000)
    assert "ROLL_180_YAW_90" in text and "world N RMS" in text
    assert "undetermined" in text  # the total-field fit's warning, beside the vector fit
    page.get_by_role("tab", name="View").click()
    page.get_by_text("Show the vehicle view", exact=True).click()
    page.wait_for_function("() => document.body.innerText.includes('flies the record')", timeout=60_000)
    for name in ("/vehicle/body", "/vehicle/model_field", "/vehicle/measured_field", "/vehicle/residual"):
        assert name in wb.vehicle.nodes
    _dismiss_toasts(page)
    shot = tmp_path / "vehicle_view.png"
    page.screenshot(path=str(shot), timeout=120_000)
    assert shot.stat().st_size > 10_000
    page.close()


def test_a_live_session_fits_with_the_location_s_reference(bench, tmp_path):
    """The location typed in the page gives the live fits their reference field."""
    wb = bench()
    wb.ctrl.vector.set_location(45.0, 7.6, 300.0, "2024-06-01")
    wanted = wb.ctrl.state.reference_nT
    live = wb.livectl.start("sim://chi2017?speed=40&n=600", tmp_path / "rec.csv")
    end = time.monotonic() + 60
    while (live.fit is None or live.session.running) and time.monotonic() < end:
        time.sleep(0.1)
    end = time.monotonic() + 30
    while (live.fit is None or live.fit.n_samples < live.n_samples) and time.monotonic() < end:
        time.sleep(0.1)
    assert live.fit is not None
    cal = live.fit.calibration
    assert cal.reference_total_nT == pytest.approx(wanted) and not cal.reference_fitted
    assert f"reference field {wanted:.1f} nT" in live.status_markdown()
    live.stop()
