"""Flight logs carry the position, the date and the throttle a vector calibration needs (found on real logs).

Real ArduPilot logs of 2014-2015 (erlerobot/logs) showed three gaps, reproduced here on logs written with known truth:

* the readers dropped the GPS, so IGRF along the track (``lat, lon, alt_m``) was not available from a log;
* in DataFlash logs before 2015 the ``GPS`` message's ``TimeMS`` is the GPS time of the week, not the board's clock
  (that is ``T``, in ms): taken as the board time it puts every fix days after the compass samples;
* without ``--date`` IGRF was evaluated today, not on the day of the record (a 2015 flight read in 2026 is ~800 nT
  off in the east component at 43 N): the readers now keep the GPS date and the reference uses it.
"""

from __future__ import annotations

import datetime as dt
import struct

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from magcal.checks.reference import igrf_ned_nT, record_date, resolve_vector_reference
from magcal.data.dataset import Dataset
from magcal.data.logs import gps_week_date, read_log
from magcal.fitting.vector import fit_vector

pytest.importorskip("pymavlink")
pytest.importorskip("pyulog")
pytest.importorskip("ppigrf")

DATE = "2015-02-11"
GPS_WEEK = 1831  # 2015-02-08 (Sunday) is the start of GPS week 1831
MS_OF_WEEK = 3 * 86_400_000 + 12 * 3_600_000  # Wednesday 2015-02-11, 12:00


def _track(n=1500, rate_hz=10.0, seed=4):
    """Times (s), attitude (yaw turns, roll +-15, pitch +-8 deg), a track 0.4 deg north, throttle, the IGRF field."""
    rng = np.random.default_rng(seed)
    t = 20.0 + np.arange(n) / rate_hz
    s = (t - t[0]) / (t[-1] - t[0])
    yaw = 3 * 360.0 * s + 20 * np.sin(7 * s)
    roll = 15 * np.sin(2 * np.pi * 5.3 * s)
    pitch = 8 * np.sin(2 * np.pi * 3.1 * s + 1)
    att = Rotation.from_euler("ZYX", np.column_stack([yaw, pitch, roll]), degrees=True)
    lat = 43.0 + 0.4 * s
    lon = -2.9 + 0.1 * s
    alt = 50.0 + 100 * s
    throttle = np.clip(0.5 + 0.2 * np.sin(2 * np.pi * 4 * s) + rng.normal(0, 0.01, n), 0, 1)
    ned = igrf_ned_nT(lat, lon, alt / 1000.0, DATE)
    return t, att, lat, lon, alt, throttle, ned


# -- a minimal DataFlash writer (formats as pymavlink's DFReader scales them: c int16 x 0.01, C uint16 x 0.01,
#    e int32 x 0.01, E uint32 x 0.01, L int32 x 1e-7) ---------------------------------------------------------------
_STRUCT = {"Q": "Q", "B": "B", "h": "h", "H": "H", "I": "I", "i": "i", "f": "f", "c": "h", "C": "H", "e": "i"}
_STRUCT.update({"E": "I", "L": "i", "N": "16s", "n": "4s", "Z": "64s"})
OLD_FORMATS = {  # ArduCopter 3.2 (2014-2015): times in ms
    "MAG": (65, "Ihhhhhhhhh", "TimeMS,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOfsX,MOfsY,MOfsZ"),
    "ATT": (66, "IccccCCCC", "TimeMS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw,ErrRP,ErrYaw"),
    "GPS": (67, "BIHBcLLeeEefI", "Status,TimeMS,Week,NSats,HDop,Lat,Lng,RelAlt,Alt,Spd,GCrs,VZ,T"),
    "CTUN": (68, "Ih", "TimeMS,ThrOut"),
}
NEW_FORMATS = {  # ArduPilot 4.x: times in us, instances
    "PARM": (64, "QNf", "TimeUS,Name,Value"),
    "MAG": (65, "QBhhhhhhhhhBI", "TimeUS,I,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOX,MOY,MOZ,Health,S"),
    "ATT": (66, "Qccccff", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw"),
    "GPS": (67, "QBBIHBcLLeffffB", "TimeUS,I,Status,GMS,GWk,NSats,HDop,Lat,Lng,Alt,Spd,GCrs,VZ,Yaw,U"),
    "CTUN": (68, "Qf", "TimeUS,ThO"),
}


def _msg(type_id, fmt, values):
    return struct.pack("<BBB", 0xA3, 0x95, type_id) + struct.pack("<" + "".join(_STRUCT[c] for c in fmt), *values)


def _write_dataflash(path, formats, messages):
    out = bytearray(_msg(128, "BBnNZ", (128, 89, b"FMT", b"BBnNZ", b"Type,Length,Name,Format,Columns")))
    for name, (type_id, fmt, cols) in formats.items():
        length = 3 + struct.calcsize("<" + "".join(_STRUCT[c] for c in fmt))
        out += _msg(128, "BBnNZ", (type_id, length, name.encode(), fmt.encode(), cols.encode()))
    for name, values in messages:
        type_id, fmt, _ = formats[name]
        out += _msg(type_id, fmt, values)
    path.write_bytes(bytes(out))


def _truth_readings(att, ned, seed=1):
    """Raw compass readings (nT, body frame as ArduPilot logs them) through a known soft and hard iron."""
    rng = np.random.default_rng(seed)
    c = np.eye(3) + rng.normal(0, 0.03, (3, 3))
    b = np.array([2500.0, -1800.0, 4200.0])
    body = att.inv().apply(ned)
    return body @ c.T + b, c, b


def _old_log(path):
    t, att, lat, lon, alt, throttle, ned = _track()
    raw, c, b = _truth_readings(att, ned)
    ypr = att.as_euler("ZYX", degrees=True)
    messages = []
    for i in range(len(t)):
        ms = int(round(t[i] * 1000))
        roll, pitch, yaw = ypr[i, 2], ypr[i, 1], ypr[i, 0] % 360
        angles = (int(round(roll * 100)), 0, int(round(pitch * 100)), 0, int(round(yaw * 100)), 0, 0)
        messages.append(("ATT", (ms - 3, 0, *angles)))
        mg = np.round(raw[i] / 100.0).astype(int)
        messages.append(("MAG", (ms, *mg, 0, 0, 0, 0, 0, 0)))
        messages.append(("CTUN", (ms + 1, int(round(throttle[i] * 1000)))))
        if i % 2 == 0:  # 5 Hz GPS; TimeMS is the GPS time of the week, T the board's ms
            status = 1 if i < 20 else 3  # no fix for the first 2 s: those samples are not positions
            la, lo = (0.0, 0.0) if status < 3 else (lat[i], lon[i])
            gps = (status, MS_OF_WEEK + ms, GPS_WEEK, 9, 150, int(round(la * 1e7)), int(round(lo * 1e7)), 0)
            messages.append(("GPS", (*gps, int(round(alt[i] * 100)), 0, 0, 0.0, ms + 2)))
    _write_dataflash(path, OLD_FORMATS, messages)
    return t, att, lat, lon, alt, throttle, ned, b


def test_old_dataflash_gps_timed_by_the_board_clock_and_dated(tmp_path):
    path = tmp_path / "copter_2015.bin"
    t, _, lat, lon, alt, throttle, _, _ = _old_log(path)
    ds = read_log(path, warn=False)
    assert ds.metadata["date"] == DATE
    fixed = (t >= t[20]) & (t <= t[-2])  # before the first fix and after the last the reader holds the nearest fix
    assert np.max(np.abs(ds.extra["lat"][fixed] - lat[fixed])) < 1e-5  # deg: within a metre
    assert np.max(np.abs(ds.extra["lon"][fixed] - lon[fixed])) < 1e-5
    assert np.max(np.abs(ds.extra["alt_m"][fixed] - alt[fixed])) < 0.2
    assert np.allclose(ds.extra["lat"][t < t[20]], lat[20], atol=1e-6)
    assert np.max(np.abs(ds.extra["throttle"] - throttle)) < 2e-3  # ThrOut / 1000, 1 ms apart


def test_igrf_along_a_logged_track_on_the_record_s_date_calibrates_the_vector(tmp_path):
    path = tmp_path / "copter_2015.bin"
    t, att, lat, lon, alt, _, ned, bias = _old_log(path)
    ds = read_log(path, warn=False)
    ref = resolve_vector_reference(ds, reference="igrf")
    assert ref.kind == "igrf-track" and DATE in ref.text
    fixed = t >= t[20]
    assert np.max(np.abs(ref.ned_nT[fixed] - ned[fixed])) < 1.0  # nT: IGRF at the truth's place and day
    fit = fit_vector(ds, ref, terms=[], warn=False)
    s = fit.sensors[0]
    assert np.allclose(s.right_angle, np.eye(3))  # ArduPilot logs the compass in the body frame
    assert np.max(np.abs(s.bias_nT - bias)) < 60.0  # 100 nT (1 mG) steps of the log
    world = fit.calibration.world(ds)[0]
    assert np.sqrt(np.mean((world - ned) ** 2)) < 60.0
    # the same record with IGRF of today (what the reference gave before): hundreds of nT off in the components
    today = resolve_vector_reference(ds, reference="igrf", date=dt.date.today().isoformat())
    assert np.sqrt(np.mean((today.ned_nT - ned) ** 2)) > 150.0


def test_new_dataflash_first_receiver_3d_fixes_only(tmp_path):
    t, att, lat, lon, alt, throttle, ned = _track(n=400)
    raw, _, _ = _truth_readings(att, ned)
    ypr = att.as_euler("ZYX", degrees=True)
    messages = []
    for i in range(len(t)):
        us = int(round(t[i] * 1e6))
        messages.append(
            ("ATT", (us - 500, 0, int(round(ypr[i, 2] * 100)), 0, int(round(ypr[i, 1] * 100)), 0.0, ypr[i, 0]))
        )
        messages.append(("MAG", (us, 0, *np.round(raw[i] / 100).astype(int), 0, 0, 0, 0, 0, 0, 1, us)))
        messages.append(("CTUN", (us + 100, float(throttle[i]))))
        gms = MS_OF_WEEK + us // 1000
        la, lo = int(round(lat[i] * 1e7)), int(round(lon[i] * 1e7))
        messages.append(
            ("GPS", (us + 200, 0, 3 if i % 10 else 2, gms, GPS_WEEK, 12, 80, la, lo, int(alt[i] * 100), 0, 0, 0, 0, 1))
        )
        messages.append(("GPS", (us + 300, 1, 3, gms, GPS_WEEK, 12, 80, la + 10_000_000, lo, 0, 0, 0, 0, 0, 1)))
    path = tmp_path / "plane.bin"
    _write_dataflash(path, NEW_FORMATS, messages)
    ds = read_log(path, warn=False)
    assert ds.metadata["date"] == DATE
    # the second receiver (1 deg north) is not mixed in; no-fix samples (status 2) are left out
    assert np.max(np.abs(ds.extra["lat"][1:] - lat[1:])) < 1e-5  # (sample 0 has no fix: it holds the first)
    assert np.max(np.abs(ds.extra["throttle"] - throttle)) < 1e-4


def test_gps_week_date():
    assert gps_week_date(GPS_WEEK, MS_OF_WEEK) == DATE
    assert gps_week_date(0, 12345) is None  # week 0: the receiver has no time yet


# -- PX4: vehicle_gps_position ------------------------------------------------------------------------------------
def _ulog_msg(kind, payload):
    return struct.pack("<HB", len(payload), ord(kind)) + payload


def _write_ulog(path, topics):
    out = bytearray(b"ULog\x01\x12\x35" + bytes([1]) + struct.pack("<Q", 0))
    out += _ulog_msg("B", bytes(16) + struct.pack("<QQQ", 0, 0, 0))
    codes = {"uint64_t": "Q", "uint32_t": "I", "int32_t": "i", "float": "f", "uint8_t": "B", "bool": "?"}
    for name, fields, _ in topics:
        out += _ulog_msg("F", (name + ":" + "".join(f"{t} {f};" for t, f in fields)).encode())
    data = []
    for msg_id, (name, fields, rows) in enumerate(topics):
        out += _ulog_msg("A", struct.pack("<BH", 0, msg_id) + name.encode())
        fmt = "<" + "".join(codes[t.split("[")[0]] * (int(t.split("[")[1][:-1]) if "[" in t else 1) for t, _ in fields)
        data += [(row[0], msg_id, struct.pack("<H", msg_id) + struct.pack(fmt, *row)) for row in rows]
    for _, _, payload in sorted(data, key=lambda d: (d[0], d[1])):
        out += _ulog_msg("D", payload)
    path.write_bytes(bytes(out))


def test_ulog_vehicle_gps_position(tmp_path):
    t, att, lat, lon, alt, _, ned = _track(n=300)
    raw, _, _ = _truth_readings(att, ned)
    t_us = (t * 1e6).astype(np.int64)
    mag_fields = [("uint64_t", "timestamp"), ("uint32_t", "device_id"), ("float", "x"), ("float", "y"), ("float", "z")]
    mag = [(int(u), 1, *(raw[i] / 1e5)) for i, u in enumerate(t_us)]
    q = att.as_quat()
    att_rows = [(int(u) - 1000, q[i, 3], q[i, 0], q[i, 1], q[i, 2]) for i, u in enumerate(t_us)]
    utc0 = int(dt.datetime(2015, 2, 11, 12, tzinfo=dt.UTC).timestamp() * 1e6)
    gps_fields = [
        ("uint64_t", "timestamp"),
        ("uint64_t", "time_utc_usec"),
        ("int32_t", "lat"),
        ("int32_t", "lon"),
        ("int32_t", "alt"),
        ("uint8_t", "fix_type"),
    ]
    gps = [
        (int(u) + 300, utc0 + int(u), int(round(lat[i] * 1e7)), int(round(lon[i] * 1e7)), int(alt[i] * 1000), 3)
        for i, u in enumerate(t_us)
    ]
    path = tmp_path / "px4.ulg"
    _write_ulog(
        path,
        [
            ("sensor_mag", mag_fields, mag),
            ("vehicle_attitude", [("uint64_t", "timestamp"), ("float[4]", "q")], att_rows),
            ("vehicle_gps_position", gps_fields, gps),
        ],
    )
    ds = read_log(path, warn=False)
    assert ds.metadata["date"] == DATE
    assert np.max(np.abs(ds.extra["lat"] - lat)) < 1e-5 and np.max(np.abs(ds.extra["alt_m"] - alt)) < 0.01


def test_record_date_only_takes_a_date_igrf_can_read():
    ds = Dataset(readings_nT=np.zeros((1, 3, 3)), metadata={"date": "spring, outdoors"})
    assert record_date(ds) is None  # free text in a header: today, as before, not an error
    assert record_date(ds.replace(metadata={"date": DATE})) == DATE
    assert record_date(ds.replace(metadata={"date": DATE}), "2020-01-01") == "2020-01-01"  # --date wins


@pytest.mark.parametrize("wrong_by_deg", [0.0, 11.0])
def test_a_wrong_declination_setting_is_named(tmp_path, wrong_by_deg):
    """ArduPilot's ATT yaw is the magnetic heading plus COMPASS_DEC: set 11 deg wrong (as on a real model aircraft's
    log, COMPASS_DEC 11.08 deg where IGRF gives 0.07 deg), the logged yaw is 11 deg off true north."""
    t, att, lat, lon, alt, _, ned = _track(n=600)
    raw, _, _ = _truth_readings(att, ned)
    true_dec = float(np.degrees(np.arctan2(np.median(ned[:, 1]), np.median(ned[:, 0]))))
    setting = true_dec + wrong_by_deg
    ypr = att.as_euler("ZYX", degrees=True)
    messages = [("PARM", (0, b"COMPASS_DEC", float(np.radians(setting))))]
    for i in range(len(t)):
        us = int(round(t[i] * 1e6))
        yaw = ypr[i, 0] + wrong_by_deg
        messages.append(("ATT", (us - 500, 0, int(round(ypr[i, 2] * 100)), 0, int(round(ypr[i, 1] * 100)), 0.0, yaw)))
        messages.append(("MAG", (us, 0, *np.round(raw[i] / 100).astype(int), 0, 0, 0, 0, 0, 0, 1, us)))
        la, lo = int(round(lat[i] * 1e7)), int(round(lon[i] * 1e7))
        gps = (us + 200, 0, 3, MS_OF_WEEK + us // 1000, GPS_WEEK, 12, 80, la, lo, int(alt[i] * 100), 0, 0, 0, 0, 1)
        messages.append(("GPS", gps))
    path = tmp_path / "declination.bin"
    _write_dataflash(path, NEW_FORMATS, messages)
    ds = read_log(path, warn=False)
    assert float(ds.metadata["log_declination_deg"]) == pytest.approx(setting, abs=1e-3)
    fit = fit_vector(ds, resolve_vector_reference(ds, reference="igrf"), terms=[], warn=False)
    named = [w for w in fit.warnings if "COMPASS_DEC" in w]
    if wrong_by_deg:
        assert len(named) == 1 and "+11.0 deg off true north" in named[0]
    else:
        assert not named
