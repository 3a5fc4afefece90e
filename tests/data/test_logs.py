"""Flight-controller logs in (magcal.data.logs): ArduPilot DataFlash .bin and PX4 .ulg, written here with known truth.

The writers below follow each format's documentation: DataFlash is a stream of messages ``A3 95 type payload``
described by FMT messages (pymavlink's DFReader reads them); ULog is a 16-byte header, then messages
``uint16 size, uint8 type, payload`` (B flags, F formats, A subscriptions, D data), as PX4's ULog file format
page describes.
"""

from __future__ import annotations

import struct

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import magcal
from magcal.cli import main
from magcal.core.errors import MagcalError
from magcal.data.dataset import DatasetError
from magcal.data.logs import read_log

pytest.importorskip("pymavlink")
pytest.importorskip("pyulog")

FIELD_NED_nT = np.array([19_000.0, 1_500.0, 45_000.0])  # |F| about 48.8 uT


def _attitudes(n, seed=3):
    return Rotation.random(n, random_state=seed)


# -- DataFlash writer ------------------------------------------------------------------------------------------------
_DF_FORMATS = {  # name: (type id, struct format chars, columns)
    "PARM": (64, "QNf", "TimeUS,Name,Value"),
    "MAG": (65, "QBhhhhhhhhhBI", "TimeUS,I,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOX,MOY,MOZ,Health,S"),
    "IMU": (66, "QBf", "TimeUS,I,T"),
    "ATT": (67, "Qffffff", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw"),
}
_DF_STRUCT = {"Q": "Q", "B": "B", "h": "h", "I": "I", "f": "f", "N": "16s", "n": "4s", "Z": "64s"}


def _df_message(type_id, fmt, values):
    return struct.pack("<BBB", 0xA3, 0x95, type_id) + struct.pack("<" + "".join(_DF_STRUCT[c] for c in fmt), *values)


def write_dataflash(path, messages):
    """A DataFlash log: the FMT messages, then ``messages`` as (name, values) in order."""
    out = bytearray()
    fmt_self = "BBnNZ"
    out += _df_message(128, fmt_self, (128, 89, b"FMT", b"BBnNZ", b"Type,Length,Name,Format,Columns"))
    for name, (type_id, fmt, cols) in _DF_FORMATS.items():
        length = 3 + struct.calcsize("<" + "".join(_DF_STRUCT[c] for c in fmt))
        out += _df_message(128, fmt_self, (type_id, length, name.encode(), fmt.encode(), cols.encode()))
    for name, values in messages:
        type_id, fmt, _ = _DF_FORMATS[name]
        out += _df_message(type_id, fmt, values)
    path.write_bytes(bytes(out))


def ardupilot_case(n=400, compasses=2):
    """Raw compass fields (mG, body frame) from known sensor errors, the firmware's logged (corrected) values and
    its parameters; returns the message list and the truth."""
    rng = np.random.default_rng(7)
    att = _attitudes(n)
    body = att.inv().apply(FIELD_NED_nT)  # field in the body frame, nT
    t_us = 20_000 * np.arange(n) + 1_000_000
    truth = []
    params = [
        ("COMPASS_OFS_X", 30.0),
        ("COMPASS_DIA_X", 1.02),
        ("COMPASS_DIA_Y", 0.98),
        ("COMPASS_DIA_Z", 1.01),
        ("COMPASS_ODI_X", 0.01),
        ("COMPASS_ODI_Y", -0.02),
        ("COMPASS_ODI_Z", 0.015),
        ("COMPASS_SCALE", 1.0),
        ("COMPASS_OFS2_Y", -12.0),
    ]
    messages = [("PARM", (0, name.encode(), value)) for name, value in params]
    m1 = np.array([[1.02, 0.01, -0.02], [0.01, 0.98, 0.015], [-0.02, 0.015, 1.01]])
    matrices = [m1, np.eye(3)]
    offsets = [np.array([30.0, 0.0, 0.0]), np.array([0.0, -12.0, 0.0])]
    sensors = []
    for k in range(compasses):
        c = np.eye(3) + rng.normal(0, 0.03, (3, 3))
        b = rng.normal(0, 3000, 3)
        raw_nT = body @ c.T + b + rng.normal(0, 20, body.shape)
        sensors.append((c, b))
        truth.append(raw_nT)
    for i in range(n):
        messages.append(("IMU", (int(t_us[i]) - 5000, 0, 25.0 + 0.01 * i)))
        roll, pitch, yaw = att[i].as_euler("ZYX", degrees=True)[::-1]
        messages.append(("ATT", (int(t_us[i]), 0.0, roll, 0.0, pitch, 0.0, yaw)))  # at compass 1's times
        for k in range(compasses):
            raw_mG = truth[k][i] / 100.0
            logged = matrices[k] @ (raw_mG + offsets[k])
            mo = np.array([2.0, -1.0, 0.0]) if k == 0 else np.zeros(3)  # motor offsets, added after the matrix
            logged = np.round(logged + mo)
            messages.append(
                (
                    "MAG",
                    (
                        int(t_us[i]) + 100 * k,
                        k,
                        *logged.astype(int),
                        *np.round(offsets[k]).astype(int),
                        *mo.astype(int),
                        1,
                        0,
                    ),
                )
            )
    return messages, truth, att, sensors


@pytest.fixture(scope="module")
def ardupilot_log(tmp_path_factory):
    path = tmp_path_factory.mktemp("bin") / "flight.bin"
    messages, truth, att, sensors = ardupilot_case()
    write_dataflash(path, messages)
    return path, truth, att, sensors


def test_dataflash_compasses_raw_field_recovered(ardupilot_log):
    path, truth, att, _ = ardupilot_log
    ds = read_log(path)
    assert ds.n_sensors == 2 and ds.n_samples == len(truth[0])
    # the firmware logged M (raw + OFS) + MO rounded to 1 mG; undoing it gives the raw field to within that step
    for k in range(2):
        assert np.max(np.abs(ds.readings_nT[k] - truth[k])) < 1.2 * 100
    assert np.allclose(ds.time_s[1:] - ds.time_s[:-1], 0.02)
    assert ds.temperature_C is not None and np.allclose(ds.temperature_C[[0, -1]], [25.0, 25.0 + 0.01 * 399], atol=0.01)
    # attitude: body -> NED; the true field rotated by it comes back within the rounding
    q = ds.attitude_wxyz
    rot = Rotation.from_quat(np.column_stack([q[:, 1:], q[:, :1]]))
    assert np.max((rot * att.inv()).magnitude()) < 1e-5
    assert {"att_roll_deg", "att_pitch_deg", "att_yaw_deg"} <= set(ds.extra)


def test_dataflash_logged_field_kept_when_asked(ardupilot_log):
    path, truth, _, _ = ardupilot_log
    logged = read_log(path, undo_calibration=False)
    raw = read_log(path)
    assert np.max(np.abs(logged.readings_nT[0] - raw.readings_nT[0])) > 1000  # the calibration of the time differs
    assert logged.metadata["log_field"].startswith("as logged")


def test_dataflash_one_compass_chosen(ardupilot_log):
    path, truth, _, _ = ardupilot_log
    ds = read_log(path, sensors=[1])
    assert ds.n_sensors == 1
    assert np.max(np.abs(ds.readings_nT[0] - truth[1])) < 1.2 * 100


def test_cli_calibrate_reads_a_dataflash_log(ardupilot_log, tmp_path):
    path, truth, _, _ = ardupilot_log
    one = tmp_path / "one.bin"
    messages, *_ = ardupilot_case(compasses=1)
    write_dataflash(one, messages)
    cal = tmp_path / "cal.json"
    assert main(["calibrate", str(one), "-o", str(cal)]) == 0
    c = magcal.Calibration.load(cal)
    ds = read_log(one)
    field = np.linalg.norm(c.correct(ds)[0], axis=1)
    # the calibrated magnitude is flat to the noise (20 nT) and the 1 mG rounding of the log (29 nT rms)
    assert np.std(field) < 60
    assert (
        abs(np.mean(field) - np.linalg.norm(FIELD_NED_nT)) < 0.05 * np.linalg.norm(FIELD_NED_nT) or c.reference_fitted
    )


def test_dataflash_without_compass_is_refused(tmp_path):
    path = tmp_path / "nomag.bin"
    write_dataflash(path, [("ATT", (1000, 0.0, 1.0, 0.0, 2.0, 0.0, 3.0))])
    with pytest.raises(DatasetError, match=r"nomag\.bin: no MAG messages"):
        read_log(path)


def test_damaged_logs_are_refused(tmp_path):
    bad = tmp_path / "junk.ulg"
    bad.write_bytes(b"not a ulog at all" * 10)
    with pytest.raises(DatasetError, match=r"junk\.ulg: not a readable PX4 ULog"):
        magcal.read_csv(bad)
    with pytest.raises(DatasetError, match="no such file"):
        magcal.read_csv(tmp_path / "missing.bin")


# -- ULog writer -----------------------------------------------------------------------------------------------------
def _ulog_msg(kind, payload):
    return struct.pack("<HB", len(payload), ord(kind)) + payload


def write_ulog(path, topics):
    """A ULog file: ``topics`` is a list of (name, multi_id, fields [(type, name)], rows [tuple]) with rows in
    time order per topic; data messages are interleaved by their first field (the timestamp)."""
    out = bytearray(b"ULog\x01\x12\x35" + bytes([1]) + struct.pack("<Q", 0))
    out += _ulog_msg("B", bytes(16) + struct.pack("<QQQ", 0, 0, 0))
    codes = {"uint64_t": "Q", "uint32_t": "I", "float": "f", "uint8_t": "B", "bool": "?"}
    defined = set()
    for name, _, fields, _ in topics:
        if name in defined:
            continue
        defined.add(name)
        text = name + ":" + "".join(f"{t} {f};" for t, f in fields)
        out += _ulog_msg("F", text.encode())
    data = []
    for msg_id, (name, multi_id, fields, rows) in enumerate(topics):
        out += _ulog_msg("A", struct.pack("<BH", multi_id, msg_id) + name.encode())
        fmt = "<" + "".join(codes[t.split("[")[0]] * (int(t.split("[")[1][:-1]) if "[" in t else 1) for t, _ in fields)
        for row in rows:
            data.append((row[0], msg_id, struct.pack("<H", msg_id) + struct.pack(fmt, *row)))
    for _, _, payload in sorted(data, key=lambda d: (d[0], d[1])):
        out += _ulog_msg("D", payload)
    path.write_bytes(bytes(out))


MAG_FIELDS = [
    ("uint64_t", "timestamp"),
    ("uint64_t", "timestamp_sample"),
    ("uint32_t", "device_id"),
    ("float", "x"),
    ("float", "y"),
    ("float", "z"),
    ("float", "temperature"),
    ("uint32_t", "error_count"),
    ("bool", "is_external"),
]
ATT_FIELDS = [("uint64_t", "timestamp"), ("float[4]", "q")]


def px4_case(n=300):
    rng = np.random.default_rng(11)
    att = _attitudes(n, seed=5)
    body = att.inv().apply(FIELD_NED_nT)
    c = np.eye(3) + rng.normal(0, 0.02, (3, 3))
    b = np.array([12_000.0, -4_000.0, 7_000.0])
    raw_nT = body @ c.T + b
    t_us = 1_000_000 + 10_000 * np.arange(n)
    mag_rows = [
        (int(t) + 50, int(t), 197_130, *(raw_nT[i] / 1e5), 30.0 + 0.02 * i, 0, False) for i, t in enumerate(t_us)
    ]
    q = att.as_quat()
    att_rows = [(int(t) - 2_000, q[i, 3], q[i, 0], q[i, 1], q[i, 2]) for i, t in enumerate(t_us)]
    topics = [("sensor_mag", 0, MAG_FIELDS, mag_rows), ("vehicle_attitude", 0, ATT_FIELDS, att_rows)]
    return topics, raw_nT, att, c, b


def test_ulog_sensor_mag_and_attitude(tmp_path):
    topics, raw_nT, att, _, _ = px4_case()
    path = tmp_path / "flight.ulg"
    write_ulog(path, topics)
    ds = magcal.read_csv(path)  # the one reading entry point dispatches on .ulg
    assert ds.n_sensors == 1 and ds.n_samples == len(raw_nT)
    assert np.max(np.abs(ds.readings_nT[0] - raw_nT)) < 0.01 * 1e5 * 1e-4  # float32 gauss: well under 1 nT
    assert np.allclose(ds.temperature_C[[0, -1]], [30.0, 30.0 + 0.02 * (len(raw_nT) - 1)], atol=1e-4)
    q = ds.attitude_wxyz
    rot = Rotation.from_quat(np.column_stack([q[:, 1:], q[:, :1]]))
    # 2 ms of interpolation error at most along a random sequence: the rotation at the mag time is near the truth
    world = rot.apply(ds.readings_nT[0] * 0 + att.inv().apply(FIELD_NED_nT))
    assert np.median(np.linalg.norm(world - FIELD_NED_nT, axis=1)) < 0.5 * np.linalg.norm(FIELD_NED_nT)
    assert ds.metadata["log_device_ids"] == "197130"


def test_ulog_two_magnetometers_paired(tmp_path):
    topics, raw_nT, *_ = px4_case()
    name, _, fields, rows = topics[0]
    second = [(r[0] + 300, r[1] + 300, 655_000, r[3] * 0.5, r[4], r[5], float("nan"), 0, True) for r in rows[:-10]]
    path = tmp_path / "two.ulg"
    write_ulog(path, [topics[0], (name, 1, fields, second), topics[1]])
    with pytest.warns(magcal.core.errors.DataWarning, match="no sample of every other one"):
        ds = read_log(path)
    assert ds.n_sensors == 2 and ds.n_samples == len(rows) - 10
    assert np.allclose(ds.readings_nT[1, :, 0], 0.5 * raw_nT[:-10, 0], atol=1)


def test_ulog_without_sensor_mag_is_refused(tmp_path):
    topics, *_ = px4_case(n=5)
    path = tmp_path / "noatt.ulg"
    write_ulog(path, [topics[1]])
    with pytest.raises(DatasetError, match="no sensor_mag"):
        read_log(path)


def test_dead_compass_left_out_and_unhealthy_samples_dropped(tmp_path):
    """A compass that logs one constant vector (zero: none fitted, as in public 2014 ArduPilot logs) is left out;
    samples the firmware marked unhealthy are dropped; a log with only dead compasses is refused."""
    messages, truth, _, _ = ardupilot_case(n=120)
    edited = []
    for name, values in messages:
        if name == "MAG" and values[1] == 1:
            values = (values[0], 1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1, 0)  # compass 2 reads zero throughout
        elif name == "MAG" and values[1] == 0 and values[0] < 1_000_000 + 20_000 * 10:
            values = values[:11] + (0, 0)  # the first 10 samples of compass 1 unhealthy
        edited.append((name, values))
    path = tmp_path / "dead.bin"
    write_dataflash(path, edited)
    with pytest.warns(magcal.core.errors.DataWarning) as caught:
        ds = read_log(path)
    text = " ".join(str(w.message) for w in caught)
    assert "compass 2 reads the same vector (0, 0, 0)" in text and "10 sample(s) the firmware marked unhealthy" in text
    assert ds.n_sensors == 1 and ds.n_samples == 110
    assert np.max(np.abs(ds.readings_nT[0] - truth[0][10:])) < 1.2 * 100
    only_dead = tmp_path / "alldead.bin"
    write_dataflash(only_dead, [(n, v) for n, v in edited if not (n == "MAG" and v[1] == 0)])
    # refused: the message names the compass (the note a dataset would carry goes with the refusal)
    with pytest.raises(DatasetError, match=r"every magnetometer in the log reads one constant vector \(compass 2\)"):
        read_log(only_dead)


def test_log_to_firmware_parameters_end_to_end(tmp_path, capsys):
    """An ArduPilot log in, calibrated, exported as ArduPilot parameters: the firmware's correction of the raw
    compass field with them is flat (the Earth's field is constant), where the raw field varies by kilo-nT."""
    from magcal.output.export import parse_parameter_file

    path = tmp_path / "one.bin"
    messages, truth, _, _ = ardupilot_case(compasses=1)
    write_dataflash(path, messages)
    cal = tmp_path / "cal.json"
    params = tmp_path / "compass.param"
    assert main(["calibrate", str(path), "-o", str(cal)]) == 0
    assert main(["export", str(cal), "--format", "ardupilot", "-o", str(params)]) == 0
    p = parse_parameter_file(params.read_text())
    raw_mG = truth[0] / 100.0  # the compass's raw body-frame field, before any calibration
    m = np.array(
        [
            [p["COMPASS_DIA_X"], p["COMPASS_ODI_X"], p["COMPASS_ODI_Y"]],
            [p["COMPASS_ODI_X"], p["COMPASS_DIA_Y"], p["COMPASS_ODI_Z"]],
            [p["COMPASS_ODI_Y"], p["COMPASS_ODI_Z"], p["COMPASS_DIA_Z"]],
        ]
    )
    ofs = np.array([p[f"COMPASS_OFS_{a}"] for a in "XYZ"])
    field_nT = np.linalg.norm((p["COMPASS_SCALE"] * (raw_mG + ofs)) @ m.T, axis=1) * 100.0
    assert np.std(np.linalg.norm(truth[0], axis=1)) > 1000
    assert np.std(field_nT) < 60  # 20 nT noise and the log's 1 mG (100 nT) rounding


def test_apply_corrects_a_log_as_the_calibration_corrects_its_dataset(ardupilot_log, tmp_path):
    """``magcal apply cal.json flight.bin``: the log's channels plus the corrected columns, the same numbers as
    ``Calibration.correct`` on the log read directly."""
    from magcal.cli import main

    path = ardupilot_log[0]
    cal_path, out = tmp_path / "cal.json", tmp_path / "out.csv"
    assert main(["calibrate", str(path), "-o", str(cal_path)]) == 0
    assert main(["apply", str(cal_path), str(path), "-o", str(out)]) == 0
    ds = magcal.read_csv(path)
    expected = magcal.Calibration.load(cal_path).correct(ds)
    got = magcal.read_csv(out)
    assert got.n_samples == ds.n_samples and got.n_sensors == ds.n_sensors
    import csv

    with open(out) as fh:
        rows = [r for r in csv.reader(line for line in fh if not line.startswith("#"))]
    header, body = rows[0], np.array(rows[1:], dtype=float)
    for s in range(ds.n_sensors):
        for k, a in enumerate("xyz"):
            np.testing.assert_allclose(body[:, header.index(f"s{s + 1}{a}_cal")], expected[s, :, k], atol=1e-6)
    np.testing.assert_allclose(got.readings_nT, ds.readings_nT, atol=1e-6)


# -- the NumPy scan gives what pymavlink's reader gives -----------------------------------------------------------
def _gathered_equal(fast, slow):
    """Every list the two DataFlash readers gather, equal to the bit."""
    assert fast is not None
    assert sorted(fast["mags"]) == sorted(slow["mags"])
    for k in slow["mags"]:
        np.testing.assert_array_equal(np.asarray(fast["mags"][k]), np.asarray(slow["mags"][k], dtype=float))
    for key in ("params", "bad_params", "seen", "unhealthy"):
        assert fast[key] == slow[key], key
    for key in ("imu", "att", "bat", "curr", "gps", "thr", "acc"):
        a, b = np.asarray(fast.get(key, []), dtype=float), np.asarray(slow.get(key, []), dtype=float)
        assert a.size == b.size, key
        np.testing.assert_array_equal(a.reshape(b.shape) if a.size else a, b if a.size else a)


def _damaged_flight(path):
    """The two-compass flight with what a real log holds besides: samples marked unhealthy, a parameter changed in
    flight (the matrix undone changes with it), a damaged stretch (bytes that begin like a message), a message
    of a type no FMT defines, and a last message cut by the file's end."""
    messages, *_ = ardupilot_case(n=300, compasses=2)
    edited = []
    for k, (name, values) in enumerate(messages):
        if name == "MAG" and k % 37 == 0:
            values = (*values[:-2], 0, values[-1])  # Health 0
        edited.append((name, values))
        if k == 600:
            edited.append(("PARM", (0, b"COMPASS_DIA_X", 1.05)))
    write_dataflash(path, edited)
    data = bytearray(path.read_bytes())
    cut = data.index(b"\xa3\x95\x43", len(data) // 2)  # an ATT message half-way
    data[cut:cut] = b"\xa3\x95\x41\x00\x01" + b"\xa3\x95\x99" + bytes(range(40))  # a cut MAG, an unknown type
    path.write_bytes(bytes(data[:-7]))


@pytest.mark.parametrize("case", ["clean", "damaged"])
@pytest.mark.parametrize("undo", [True, False])
def test_the_numpy_dataflash_scan_gives_what_pymavlink_gives(tmp_path, case, undo):
    from magcal.data import logs

    path = tmp_path / "flight.bin"
    if case == "clean":
        messages, *_ = ardupilot_case(n=200, compasses=2)
        write_dataflash(path, messages)
    else:
        _damaged_flight(path)
    fast = logs._gather_fast(path, "f", undo)
    slow = logs._gather_pymavlink(path, "f", undo, None)
    _gathered_equal(fast, slow)
    if case == "damaged":
        assert sum(slow["unhealthy"].values()) > 0 and slow["params"]["COMPASS_DIA_X"] == pytest.approx(1.05)


def test_a_log_the_scan_cannot_follow_is_read_by_pymavlink(tmp_path, monkeypatch):
    """A type defined twice with different formats: the scan declines and pymavlink's reader reads the log."""
    from magcal.data import dataflash_scan, logs

    messages, *_ = ardupilot_case(n=100, compasses=1)
    write_dataflash(tmp_path / "f.bin", messages)
    data = (tmp_path / "f.bin").read_bytes()
    fmt = _df_message(128, "BBnNZ", (66, 3 + 8 + 1 + 4, b"IMU", b"QBf", b"TimeUS,I,T"))
    redefined = _df_message(128, "BBnNZ", (66, 3 + 8 + 1 + 4, b"IMU", b"QBI", b"TimeUS,I,T"))
    assert fmt in data
    (tmp_path / "g.bin").write_bytes(data + redefined)
    assert dataflash_scan.scan(tmp_path / "g.bin") is None
    calls = []
    real = logs._gather_pymavlink
    monkeypatch.setattr(logs, "_gather_pymavlink", lambda *a: calls.append(a) or real(*a))
    assert read_log(tmp_path / "g.bin").n_samples == 100 and len(calls) == 1
    assert read_log(tmp_path / "f.bin").n_samples == 100 and len(calls) == 1  # the scan read this one


@pytest.mark.parametrize("damaged", [b"Tzpe,Length,Name", b",Length,Name"])
def test_a_log_whose_fmt_names_other_columns_is_not_scanned(tmp_path, damaged):
    """The FMT message's own format with its columns renamed or one unnamed (a damaged FMT): the scan cannot learn
    the types from it and declines; the log is read by pymavlink's path or refused with a message, never a KeyError."""
    from magcal.data import dataflash_scan

    messages, *_ = ardupilot_case(n=100, compasses=1)
    write_dataflash(tmp_path / "f.bin", messages)
    data = (tmp_path / "f.bin").read_bytes()
    assert b"Type,Length,Name,Format,Columns" in data
    columns = b"Type,Length,Name,Format,Columns"
    (tmp_path / "g.bin").write_bytes(
        data.replace(columns, (damaged + b",Format,Columns").ljust(len(columns), b"\0"), 1)
    )
    assert dataflash_scan.scan(tmp_path / "f.bin") is not None
    assert dataflash_scan.scan(tmp_path / "g.bin") is None
    try:
        read_log(tmp_path / "g.bin")
    except MagcalError as exc:
        assert "g.bin" in str(exc)


@pytest.mark.parametrize("reader", ["scan", "pymavlink"])
def test_a_log_whose_compass_parameters_make_a_singular_matrix_is_refused_with_a_message(tmp_path, reader):
    """DIA and ODI all 1 (a damaged log: ArduPilot keeps DIA near 1 and ODI within 0.2): the logged calibration
    cannot be undone; both readers say so naming the file and the parameters, and the logged field can be read."""
    from magcal.data import logs

    messages, *_ = ardupilot_case(n=100, compasses=1)
    damaged = [("PARM", (0, f"COMPASS_{p}_{a}".encode(), 1.0)) for p in ("DIA", "ODI") for a in "XYZ"]
    first_mag = next(k for k, (name, _) in enumerate(messages) if name == "MAG")
    write_dataflash(tmp_path / "f.bin", messages[:first_mag] + damaged + messages[first_mag:])
    if reader == "pymavlink":
        with pytest.raises(DatasetError, match=r"f\.bin: the logged calibration of compass 0 .*COMPASS_ODI_"):
            logs._gather_pymavlink(tmp_path / "f.bin", "f.bin", True, None)
        return
    with pytest.raises(DatasetError, match=r"f\.bin: the logged calibration of compass 0 .*singular"):
        read_log(tmp_path / "f.bin", name="f.bin")
    assert read_log(tmp_path / "f.bin", undo_calibration=False, warn=False).n_samples == 100
