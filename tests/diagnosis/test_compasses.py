"""Several compasses on one vehicle (item 5): magcal.diagnosis.compasses against simulated truth, and the
flight-log readers that bring the compasses in (each one's logged calibration undone, its logged field kept).

Every case sets its truth: a simulated vehicle (magcal.data.vehicle) whose second compass sees a motor current
(``VehicleSensorTruth.current_nT_per_unit``) or sits 5 deg off its bracket, a temperature field one compass sees,
and DataFlash logs written here the way ArduPilot writes them (``AP_Compass_Backend::correct_field``: the logged
field is ``M (raw + OFS) + MOT * current`` in milligauss, the compasses logged in their priority order).
"""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from magcal.checks.reference import resolve_vector_reference
from magcal.cli import main
from magcal.core.errors import MagcalError
from magcal.data.dataset import Dataset
from magcal.data.io import write_csv
from magcal.data.vehicle import simulate_vehicle, vehicle_truth
from magcal.diagnosis.compasses import (
    ARDUPILOT_MAX_XY_LENGTH_nT,
    angle_deg,
    before_fields,
    compass_consistency,
    pair_figures,
)
from magcal.fitting.vector import fit_vector

pytest.importorskip("pymavlink")

K2_nT_PER_A = np.array([20.0, -15.0, 10.0])  # the current's field in compass 2's raw axes


def _body_per_unit(truth, sensor, k_raw):
    """The field ``k_raw`` (raw axes) in the body frame, as a calibration into the body frame reads it: ``R C^-1 k``."""
    s = truth.sensors[sensor]
    return s.mounting @ np.linalg.inv(s.matrix) @ k_raw


@pytest.fixture(scope="module")
def current_flight():
    """Two compasses; the second sees the motor current (25 nT/A), the first does not."""
    truth = vehicle_truth(n_sensors=2, seed=3)
    truth.sensors[1].current_nT_per_unit = K2_nT_PER_A.copy()
    ds, tr = simulate_vehicle(truth, seed=3, n=3000)
    return ds, tr, resolve_vector_reference(ds)


def test_a_current_one_compass_sees_is_named_with_its_size(current_flight):
    ds, tr, ref = current_flight
    fit = fit_vector(ds, ref, terms=[], warn=False)  # the base fit: the current is left in compass 2's field
    cc = compass_consistency(ds, fit.calibration, reference=ref, mask=fit.fitted)
    pair = cc.pair(0, 1)
    named = {c.kind: c for c in pair.named("after")}
    assert list(named) == ["current_A"]  # the current, and nothing else, explains what the calibration left
    cause = named["current_A"]
    k_body = _body_per_unit(tr, 1, K2_nT_PER_A)
    assert np.allclose(cause.values["per_unit_nT"], k_body, atol=0.03 * np.linalg.norm(k_body))
    # the angle and |B| the current makes per ampere, from the true field per ampere and the fields flown
    body = np.stack([Rotation.from_quat(q[[1, 2, 3, 0]]).inv().apply(tr.field_ned_nT) for q in tr.attitude_wxyz])
    bhat = body / np.linalg.norm(body, axis=1)[:, None]
    deg = np.degrees(np.sqrt(np.mean(np.sum(np.cross(bhat, k_body) ** 2, axis=1))) / np.linalg.norm(tr.field_ned_nT))
    assert cause.values["angle_deg_per_unit"] == pytest.approx(deg, rel=0.03)
    assert cause.values["total_diff_nT_per_unit"] == pytest.approx(float(np.mean(bhat @ k_body)), abs=0.5)
    assert cause.values["correlation"] > 0.95
    # the reference field tells which compass sees it: the second, before and after
    assert cc.seeing("before") == [1] and cc.seeing("after") == [1]
    assert "seen by compass 2" in cc.text() and "follows the current" in cc.text()


def test_with_the_current_term_the_compasses_agree_and_the_term_is_credited(current_flight):
    ds, tr, ref = current_flight
    fit = fit_vector(ds, ref, terms=["current"], warn=False)
    cc = compass_consistency(ds, fit.calibration, reference=ref, mask=fit.fitted)
    pair = cc.pair(0, 1)
    assert pair.named("after") == []
    assert pair.after.angle_deg.p95 < 0.05 and pair.before.angle_deg.median > 1.0
    after = [s for s in cc.sensitivities if s.state == "after"]
    k_body = _body_per_unit(tr, 1, K2_nT_PER_A)
    assert np.allclose(after[1].compensated_nT, k_body, atol=0.03 * np.linalg.norm(k_body))
    assert np.linalg.norm(after[0].total_nT) < 1.0 and cc.seeing("after") == [1]


def test_a_mounting_off_by_five_degrees_is_named():
    truth = vehicle_truth(n_sensors=2, off_deg=0.0, seed=4)
    for s in truth.sensors:  # ideal sensors: only the mounting differs
        s.matrix, s.bias_nT = np.eye(3), np.zeros(3)
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    truth.sensors[1].mounting = truth.sensors[1].mounting @ Rotation.from_rotvec(np.radians(5.0) * axis).as_matrix()
    ds, tr = simulate_vehicle(truth, seed=4, n=2000)
    ref = resolve_vector_reference(ds)
    fit = fit_vector(ds, ref, terms=[], warn=False)
    cc = compass_consistency(ds, fit.calibration, reference=ref, mask=fit.fitted)
    pair = cc.pair(0, 1)
    relative = truth.sensors[1].mounting @ truth.sensors[0].mounting.T  # compass 2's mounting from compass 1's
    true_rotvec = np.degrees(Rotation.from_matrix(relative).as_rotvec())
    named = {c.kind: c for c in pair.named("before")}
    assert {"mounting", "mounting_fit"} <= set(named)
    assert np.allclose(named["mounting_fit"].values["mounting_rotvec_deg"], true_rotvec, atol=0.02)
    assert np.allclose(named["mounting"].values["mounting_rotvec_deg"], true_rotvec, atol=0.05)
    assert cc.mountings[1]["angle_off_deg"] == pytest.approx(5.0, abs=0.02)
    assert cc.mountings[0]["angle_off_deg"] < 0.02
    # before (the readings in the right-angle orientation): a constant angle, the one the mounting makes
    body = np.stack([Rotation.from_quat(q[[1, 2, 3, 0]]).inv().apply(tr.field_ned_nT) for q in tr.attitude_wxyz])
    turned = body @ relative  # compass 2's field in the body frame when read with only the right angle
    assert pair.before.angle_deg.median == pytest.approx(float(np.median(angle_deg(body, turned))), abs=0.02)
    assert pair.after.angle_deg.p95 < 0.05 and pair.named("after") == []


def test_three_compasses_name_the_odd_one_and_a_temperature_field():
    truth = vehicle_truth(n_sensors=3, seed=6)
    ds, tr = simulate_vehicle(truth, seed=6, n=2000)
    t = ds.time_s
    temp = 20.0 + 12.0 * np.sin(2 * np.pi * t / (t[-1] / 2.3))  # up and down 2.3 times: neither a drift nor the turns
    per_k = np.array([0.0, 40.0, -30.0])  # nT per degC in compass 3's raw axes
    readings = np.array(ds.readings_nT)
    readings[2] += (temp - 20.0)[:, None] * per_k[None]
    ds = ds.replace(readings_nT=readings, temperature_C=temp)
    ref = resolve_vector_reference(ds)
    fit = fit_vector(ds, ref, terms=[], warn=False)
    cc = compass_consistency(ds, fit.calibration, reference=ref, mask=fit.fitted)
    assert len(cc.pairs) == 3
    assert cc.pair(0, 1).named("after") == []
    k_body = _body_per_unit(tr, 2, per_k)
    for i in (0, 1):
        named = {c.kind: c for c in cc.pair(i, 2).named("after")}
        assert list(named) == ["temperature"]
        assert np.allclose(named["temperature"].values["per_unit_nT"], k_body, atol=0.05 * np.linalg.norm(k_body))


def test_the_firmware_figures_of_known_fields():
    n = 400
    t = np.arange(n) * 0.05
    bi = np.tile([50_000.0, 0.0, 10_000.0], (n, 1))
    bj = bi.copy()
    turn = Rotation.from_euler("z", np.where(np.arange(n) < n // 2, 10.0, 70.0)[:, None], degrees=True)
    bj = turn.apply(bj)  # 10 deg, then 70 deg apart in the body x-y plane
    fig = pair_figures(bi, bj, t)
    assert fig.xy_angle_deg.max == pytest.approx(70.0, abs=1e-6) and fig.xy_angle_deg.median == pytest.approx(40.0)
    expected_3d = angle_deg(bi[-1:], bj[-1:])[0]
    assert fig.angle_deg.max == pytest.approx(expected_3d, abs=1e-6)
    assert fig.fail_fraction["ardupilot"] == pytest.approx(0.5)  # the x-y angle beyond 60 deg, in the second half
    # PX4 filters the 3-D angle (about 1 s) and compares it with 60 deg: it refuses a little after the change
    assert expected_3d > 60.0 and 0.40 < fig.fail_fraction["px4"] < 0.5
    # the x-y length difference alone: the same direction, one compass reads 25 000 nT more along x
    longer = bi + np.array([25_000.0, 0.0, 0.0])
    fig = pair_figures(bi, longer, t)
    assert fig.xy_length_nT.max == pytest.approx(25_000.0) and 25_000.0 > ARDUPILOT_MAX_XY_LENGTH_nT
    assert fig.fail_fraction["ardupilot"] == 1.0 and fig.fail_fraction["px4"] == 0.0
    assert fig.total_diff_nT.median > 0


def test_one_compass_is_refused_with_a_message(current_flight):
    ds, _, ref = current_flight
    one = Dataset(readings_nT=ds.readings_nT[:1], time_s=ds.time_s, attitude_wxyz=ds.attitude_wxyz, extra=ds.extra)
    cal = fit_vector(one, ref, terms=[], warn=False).calibration
    with pytest.raises(MagcalError, match="needs two or more"):
        compass_consistency(one, cal)


def test_cli_calibrate_and_diagnose_print_the_consistency(current_flight, tmp_path, capsys):
    ds, _, _ = current_flight
    path = tmp_path / "two.csv"
    write_csv(path, ds)
    assert main(["calibrate", str(path), "--mode", "vector", "--platform-terms", "none", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    pair = doc["compass_consistency"]["pairs"][0]
    assert pair["pair"] == [1, 2]
    assert [c["kind"] for c in pair["causes_after"] if c["named"]] == ["current_A"]
    assert main(["calibrate", str(path), "--mode", "vector", "--platform-terms", "none"]) == 0
    text = capsys.readouterr().out
    assert "Compass consistency (2 compasses" in text and "COM_ARM_MAG_ANG" in text
    assert main(["diagnose", str(path), "--json", "--no-validate", "--workers", "1"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["compass_consistency"]["pairs"][0]["causes_after"][0]["kind"] == "current_A"


# -- DataFlash logs with several compasses -----------------------------------------------------------------------
_STRUCT = {"Q": "Q", "I": "I", "B": "B", "h": "h", "H": "H", "f": "f", "N": "16s", "n": "4s", "Z": "64s"}


def _message(type_id, fmt, values):
    return struct.pack("<BBB", 0xA3, 0x95, type_id) + struct.pack("<" + "".join(_STRUCT[c] for c in fmt), *values)


def write_dataflash(path, formats, messages):
    """A DataFlash log: FMT messages for ``formats`` {name: (type, format chars, columns)}, then ``messages``."""
    out = bytearray(_message(128, "BBnNZ", (128, 89, b"FMT", b"BBnNZ", b"Type,Length,Name,Format,Columns")))
    for name, (type_id, fmt, cols) in formats.items():
        length = 3 + struct.calcsize("<" + "".join(_STRUCT[c] for c in fmt))
        out += _message(128, "BBnNZ", (type_id, length, name.encode(), fmt.encode(), cols.encode()))
    for name, values in messages:
        type_id, fmt, _ = formats[name]
        out += _message(type_id, fmt, values)
    path.write_bytes(bytes(out))


#: The messages of a Copter 3.3 log (TimeMS, MAG/MAG2 with MOfs*, CURR in centiamperes).
OLD_FORMATS = {
    "PARM": (64, "Nf", "Name,Value"),
    "MAG": (65, "IhhhhhhhhhB", "TimeMS,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOfsX,MOfsY,MOfsZ,Health"),
    "MAG2": (66, "IhhhhhhhhhB", "TimeMS,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOfsX,MOfsY,MOfsZ,Health"),
    "ATT": (67, "Iffffff", "TimeMS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw"),
    "CURR": (68, "IhhhHfh", "TimeMS,Throttle,Volt,Curr,Vcc,CurrTot,Volt2"),
}
C1_mG_PER_A = np.array([-1.0, 2.0, 0.5])  # compass 1 sees this, and the firmware's COMPASS_MOT removes it
K2_mG_PER_A = np.array([3.0, -2.0, 1.5])  # compass 2 sees this, uncompensated


@pytest.fixture(scope="module")
def old_log(tmp_path_factory):
    """A Copter 3.3 log of a simulated flight: compass 1 calibrated (offsets and motor compensation), compass 2
    calibrated for offsets only and seeing the current."""
    truth = vehicle_truth(n_sensors=1, seed=8)
    ds, tr = simulate_vehicle(truth, seed=8, n=1500)  # its attitude, times and current
    t = ds.time_s
    current = 12.0 + 10.0 * np.sin(2 * np.pi * t / 37.0) + 3.0 * np.sin(2 * np.pi * t / 11.0)
    body_mG = np.stack([Rotation.from_quat(q[[1, 2, 3, 0]]).inv().apply(tr.field_ned_nT) for q in tr.attitude_wxyz])
    body_mG /= 100.0
    b1, b2 = np.array([40.0, -25.0, 60.0]), np.array([-70.0, 15.0, -30.0])
    raw1 = body_mG + b1 + current[:, None] * C1_mG_PER_A
    raw2 = body_mG + b2 + current[:, None] * K2_mG_PER_A
    messages = [("PARM", (name.encode(), value)) for name, value in (("COMPASS_MOTCT", 2.0), ("COMPASS_USE2", 1.0))]
    q = tr.attitude_wxyz
    angles = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_euler("ZYX", degrees=True)
    for k in range(len(t)):
        ms = int(1000 + 1000 * t[k])
        yaw, pitch, roll = angles[k]
        messages.append(("ATT", (ms, 0.0, roll, 0.0, pitch, 0.0, yaw)))
        messages.append(("CURR", (ms, 0, 1600, int(round(100 * current[k])), 5000, 0.0, 0)))
        mot1 = -C1_mG_PER_A * current[k]  # COMPASS_MOT * current: added after the offsets
        logged1 = np.round(raw1[k] - b1 + mot1)
        logged2 = np.round(raw2[k] - b2)
        messages.append(("MAG", (ms, *logged1.astype(int), *(-b1).astype(int), *np.round(mot1).astype(int), 1)))
        messages.append(("MAG2", (ms, *logged2.astype(int), *(-b2).astype(int), 0, 0, 0, 1)))
    path = tmp_path_factory.mktemp("old") / "copter33.bin"
    write_dataflash(path, OLD_FORMATS, messages)
    return path, tr, current, body_mG * 100.0, (raw1 * 100.0, raw2 * 100.0)


def test_an_old_log_keeps_both_compasses_their_logged_field_and_the_current(old_log):
    from magcal.data.logs import read_log

    path, tr, current, body_nT, raws = old_log
    ds = read_log(path, warn=False)
    assert ds.n_sensors == 2
    assert np.allclose(ds.extra["current_A"], current, atol=0.006)  # CURR's centiamperes
    # the raw field of compass 1 has its motor compensation (MOfs*) undone: it follows the current again
    for k in range(2):
        assert np.max(np.abs(ds.readings_nT[k] - raws[k])) < 1.6 * 100  # whole milligauss, twice rounded
    logged = before_fields(ds)[0]
    assert np.max(np.abs(logged[0] - body_nT)) < 0.9 * 100  # compass 1 logged as the firmware corrected it
    assert np.max(np.abs(logged[1] - (body_nT + 100 * current[:, None] * K2_mG_PER_A))) < 0.9 * 100


def test_cli_names_the_current_in_the_logged_field_of_an_old_log(old_log, capsys):
    path, tr, current, *_ = old_log
    n, e, d = tr.field_ned_nT
    args = ["calibrate", str(path), "--mode", "vector", "--reference-vector", f"{n},{e},{d}", "--json"]
    assert main(args) == 0
    doc = json.loads(capsys.readouterr().out)["compass_consistency"]
    assert doc["before_source"].startswith("the flight controller's calibration")
    named = {c["kind"]: c for c in doc["pairs"][0]["causes_before"] if c["named"]}
    assert "current_A" in named
    assert np.allclose(named["current_A"]["values"]["per_unit_nT"], 100 * K2_mG_PER_A, atol=15)
    before = {s["sensor"]: s for s in doc["sensitivities"] if s["state"] == "before"}
    assert before[2]["sees"] and not before[1]["sees"]  # the firmware compensated compass 1, not compass 2


# the compasses of ArduPilot 4.1 and later: logged in priority order, their parameters by device
NEW_FORMATS = {
    "PARM": (64, "QNf", "TimeUS,Name,Value"),
    "MAG": (65, "QBhhhhhhhhhBI", "TimeUS,I,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOX,MOY,MOZ,Health,S"),
    "ATT": (67, "Qffffff", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw"),
}


def test_each_logged_compass_takes_the_parameters_of_its_device(tmp_path):
    from magcal.data.logs import read_log

    rng = np.random.default_rng(2)
    n = 200
    att = Rotation.random(n, random_state=4)
    body_mG = att.inv().apply([190.0, 15.0, 450.0])
    dev_a, dev_b = 97539.0, 131874.0
    dia = {dev_a: np.array([1.05, 0.95, 1.0]), dev_b: np.array([0.9, 1.1, 1.02])}
    params = [
        ("COMPASS_DEV_ID", dev_a),
        ("COMPASS_DEV_ID2", dev_b),
        ("COMPASS_PRIO1_ID", dev_b),  # the second detected compass has the first priority: logged as I = 0
        ("COMPASS_PRIO2_ID", dev_a),
    ]
    for tag, dev in (("", dev_a), ("2", dev_b)):
        params += [(f"COMPASS_DIA{tag}_{a}", float(v)) for a, v in zip("XYZ", dia[dev])]
    messages = [("PARM", (0, name.encode(), value)) for name, value in params]
    raws = {dev: body_mG + rng.normal(0, 30, 3) for dev in (dev_a, dev_b)}
    for k in range(n):
        us = 1_000_000 + 20_000 * k
        yaw, pitch, roll = att[k].as_euler("ZYX", degrees=True)
        messages.append(("ATT", (us, 0.0, roll, 0.0, pitch, 0.0, yaw)))
        for instance, dev in enumerate((dev_b, dev_a)):  # priority order
            logged = np.round(dia[dev] * raws[dev][k])
            messages.append(("MAG", (us + 100 * instance, instance, *logged.astype(int), 0, 0, 0, 0, 0, 0, 1, 0)))
    path = tmp_path / "prio.bin"
    write_dataflash(path, NEW_FORMATS, messages)
    ds = read_log(path, warn=False)
    for instance, dev in enumerate((dev_b, dev_a)):
        assert np.max(np.abs(ds.readings_nT[instance] - 100 * raws[dev])) < 0.6 * 100 / 0.9


# -- PX4 logs: each magnetometer's field as PX4 computed it, from the log's CAL_MAGn_* parameters ----------------
def test_px4_logged_field_is_rebuilt_from_each_devices_parameters(tmp_path):
    from magcal.data.logs import read_log
    from magcal.geometry.orientations import euler_matrix
    from tests.data.test_logs import ATT_FIELDS, MAG_FIELDS, _ulog_msg, write_ulog

    n = 300
    att = Rotation.random(n, random_state=9)
    body_G = att.inv().apply([0.21, 0.012, 0.44])  # gauss, body frame
    level = euler_matrix(1.5, -0.8, 0.0)  # SENS_BOARD_X_OFF, _Y_OFF
    internal = {"dev": 111, "rot": level, "off": np.array([0.05, -0.02, 0.11])}
    internal["scale"] = np.array([[1.02, 0.01, 0.0], [0.01, 0.97, -0.02], [0.0, -0.02, 1.01]])
    external = {"dev": 222, "rot": level @ euler_matrix(180, 0, 90), "off": np.array([-0.1, 0.07, 0.02])}
    external["scale"] = np.array([[0.95, 0.0, 0.03], [0.0, 1.04, 0.0], [0.03, 0.0, 1.0]])
    t_us = 1_000_000 + 10_000 * np.arange(n)
    topics = []
    for multi_id, m in enumerate((internal, external)):
        # the raw reading that PX4's R S (raw - OFF) turns into the body field
        raw = body_G @ np.linalg.inv(m["rot"] @ m["scale"]).T + m["off"]
        rows = [(int(t) + 40, int(t), m["dev"], *raw[k], 25.0, 0, multi_id == 1) for k, t in enumerate(t_us)]
        topics.append(("sensor_mag", multi_id, MAG_FIELDS, rows))
    q = att.as_quat()
    topics.append(
        ("vehicle_attitude", 0, ATT_FIELDS, [(int(t) - 1000, *q[k, [3, 0, 1, 2]]) for k, t in enumerate(t_us)])
    )
    params = {"SENS_BOARD_ROT": 0, "SENS_BOARD_X_OFF": 1.5, "SENS_BOARD_Y_OFF": -0.8, "CAL_MAG0_ROT": 10}
    params.update({"CAL_MAG0_ID": 222, "CAL_MAG1_ID": 111, "CAL_MAG1_ROT": -1})  # the external one calibrated first
    for index, m in ((0, external), (1, internal)):
        for k, a in enumerate("XYZ"):
            params[f"CAL_MAG{index}_{a}OFF"] = float(m["off"][k])
            params[f"CAL_MAG{index}_{a}SCALE"] = float(m["scale"][k, k])
        for k, (r, c) in enumerate(((0, 1), (0, 2), (1, 2))):
            params[f"CAL_MAG{index}_{'XYZ'[k]}ODIAG"] = float(m["scale"][r, c])
    path = tmp_path / "two_mags.ulg"
    write_ulog(path, topics)
    blob = path.read_bytes()
    head = 16 + 3 + 40  # the file header and the flag-bits message: the parameters follow them
    pmsgs = b""
    for name, value in params.items():
        kind = "int32_t" if isinstance(value, int) else "float"
        key = f"{kind} {name}".encode()
        pmsgs += _ulog_msg(
            "P", struct.pack("<B", len(key)) + key + struct.pack("<i" if kind == "int32_t" else "<f", value)
        )
    path.write_bytes(blob[:head] + pmsgs + blob[head:])
    ds = read_log(path, warn=False)
    assert ds.n_sensors == 2
    logged = before_fields(ds)[0]
    for k in range(2):
        assert np.max(np.abs(logged[k] - 1e5 * body_G)) < 2.0  # float32 gauss and parameters: about 1 nT
    assert "CAL_MAGn" in ds.metadata["log_logged_field"]


def test_a_battery_monitor_without_a_current_sensor_gives_no_current_channel(tmp_path):
    """A battery monitor that measures only the voltage logs a current of 0 throughout (BAT or CURR): no channel,
    else the vector fit's current term would fit a column of zeros."""
    from magcal.data.logs import read_log

    formats = {**NEW_FORMATS, "BAT": (68, "QBff", "TimeUS,Inst,Volt,Curr")}
    att = Rotation.random(60, random_state=1)
    body_mG = att.inv().apply([190.0, 15.0, 450.0])
    messages = []
    for k in range(60):
        us = 1_000_000 + 100_000 * k
        yaw, pitch, roll = att[k].as_euler("ZYX", degrees=True)
        messages += [("ATT", (us, 0.0, roll, 0.0, pitch, 0.0, yaw)), ("BAT", (us, 0, 12.4, 0.0))]
        messages.append(("MAG", (us, 0, *np.round(body_mG[k]).astype(int), 0, 0, 0, 0, 0, 0, 1, 0)))
    path = tmp_path / "volts_only.bin"
    write_dataflash(path, formats, messages)
    assert "current_A" not in read_log(path, warn=False).extra


def test_a_delay_between_two_compasses_is_named_in_ms():
    truth = vehicle_truth(n_sensors=2, seed=5)
    ds, _ = simulate_vehicle(truth, seed=5, n=2000)
    t = ds.time_s
    readings = np.array(ds.readings_nT)
    readings[1] = np.column_stack([np.interp(t + 0.040, t, readings[1][:, a]) for a in range(3)])  # 40 ms later
    keep = t < t[-1]  # the last sample has no field 40 ms later
    ds = ds.replace(readings_nT=readings).masked(keep)
    ref = resolve_vector_reference(ds)
    fit = fit_vector(ds, ref, terms=[], warn=False)
    named = {c.kind: c for c in compass_consistency(ds, fit.calibration, mask=fit.fitted).pair(0, 1).named("after")}
    assert list(named) == ["timing"]
    assert named["timing"].values["delay_ms"] == pytest.approx(40.0, abs=1.0)
