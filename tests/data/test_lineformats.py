"""The line formats sensor sketches print (magcal.data.lineformats through LineParser and the live sources), their
channels (attitude, gyro, position) through LiveChunk, Dataset and the recording, MAVLink ATTITUDE and GPS merged
onto the magnetometer samples, and the serial port reopened after it disappears.

Known numbers in, the same numbers out; malformed and partial lines give their reason and never a sample. Every
wait is bounded; loopback addresses and pseudo-terminals only.
"""

from __future__ import annotations

import os
import socket
import time
import urllib.parse

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

import magcal
from magcal.data import lineformats
from magcal.data.attitude import EULER_COLUMNS, attitude
from magcal.data.live import LineParser, LiveError, LiveSession, open_source

pytest.importorskip("serial")
pytest.importorskip("pymavlink")

from tests.data.test_live import collect, free_udp_port

SKETCH_COLUMNS = "t_ms,ax,ay,az,gx,gy,gz,mx,my,mz,roll,pitch,yaw"


def framed(body, start="|", checksum=True):
    """A framed line with its NMEA-like checksum (XOR of the characters between the start mark and '*')."""
    return f"{start}{body}*{lineformats.nmea_checksum(body):02X}" if checksum else f"{start}{body}*"


# -- one line, every format --------------------------------------------------------------------------------------
# (parser options, line, expected: readings nT (sensor 1), t s or None, temperature or None, channels)
GOOD = [
    pytest.param({"template": "x={x} y={y} z={z}"}, "x=1.5 y=-2.25 z=3e2", [1.5, -2.25, 300], None, None, {}, id="kv"),
    pytest.param(
        {"template": "x={x} y={y} z={z}"},
        "  x = 1.5   y=-2.25  z= 3E+2 ",
        [1.5, -2.25, 300],
        None,
        None,
        {},
        id="kv-ws",
    ),
    pytest.param(
        {"template": "x={x} y={y} z={z}", "units": "uT"},
        "x=.5 y=+2. z=-1e-3",
        [500, 2000, -1],
        None,
        None,
        {},
        id="floats",
    ),
    pytest.param(
        {"template": "Magnetometer reading: [{x}, {y}, {z}]", "units": "uT"},
        "Magnetometer reading: [21.5, -3.25, 40.125]",
        [21_500, -3_250, 40_125],
        None,
        None,
        {},
        id="reading-template",
    ),
    pytest.param(
        {"template": "Magnetometer reading: [{x}, {y}, {z}]"},
        "Magnetometer   reading :[ 21.5,-3.25 ,40.125 ]",
        [21.5, -3.25, 40.125],
        None,
        None,
        {},
        id="reading-template-ws",
    ),
    pytest.param(
        {"template": "X{x}Y{y}Z{z}uT", "units": "uT"},
        "X12.5Y-3Z4e1uT",
        [12_500, -3_000, 40_000],
        None,
        None,
        {},
        id="packed",
    ),
    pytest.param(
        {"template": "id={_} t={t} mag={x},{y},{z} T={temp}"},
        "id=board-7 t=12.25 mag=100,200,300 T=21.5",
        [100, 200, 300],
        12.25,
        21.5,
        {},
        id="skip-t-temp",
    ),
    pytest.param(
        {"template": "{t_ms}: m {mx} {my} {mz} rpy {roll} {pitch} {yaw} g {gx} {gy} {gz}"},
        "1500: m 1 2 3 rpy 10.5 -4.25 170 g 0.5 -1 2",
        [1, 2, 3],
        1.5,
        None,
        {
            "roll_deg": 10.5,
            "pitch_deg": -4.25,
            "yaw_deg": 170,
            "gyro_x_dps": 0.5,
            "gyro_y_dps": -1,
            "gyro_z_dps": 2,
        },
        id="attitude-template",
    ),
    pytest.param({"template": "{{{x};{y};{z}}}"}, "{7;8;9}", [7, 8, 9], None, None, {}, id="literal-braces"),
    pytest.param(
        {"columns": SKETCH_COLUMNS},
        "|1234,0.01,0.02,1.0,0.1,0.2,0.3,21500,-3200,40100,1.5,-0.5,87.0*",
        [21_500, -3_200, 40_100],
        1.234,
        None,
        {
            "roll_deg": 1.5,
            "pitch_deg": -0.5,
            "yaw_deg": 87.0,
            "gyro_x_dps": 0.1,
            "gyro_y_dps": 0.2,
            "gyro_z_dps": 0.3,
            "accel_x": 0.01,
            "accel_y": 0.02,
            "accel_z": 1.0,
        },
        id="pipe-star",
    ),
    pytest.param(
        {"columns": SKETCH_COLUMNS, "units": "uT"},
        framed("20,0,0,1,0,0,0,21.5,-3.2,40.1,0,0,-90"),
        [21_500, -3_200, 40_100],
        0.02,
        None,
        {"roll_deg": 0, "pitch_deg": 0, "yaw_deg": -90, "gyro_z_dps": 0},
        id="pipe-checksum",
    ),
    pytest.param({"columns": "_,x,y,z"}, framed("PMAG,4,5,6", start="$"), [4, 5, 6], None, None, {}, id="nmea-like"),
    pytest.param({"columns": "x,y,z", "checksum": False}, "|4,5,6*00", [4, 5, 6], None, None, {}, id="checksum-off"),
    pytest.param({}, "[1, 2, 3]", [1, 2, 3], None, None, {}, id="square"),
    pytest.param({}, "(1,2,3)", [1, 2, 3], None, None, {}, id="round"),
    pytest.param(
        {"units": "uT"},
        "Magnetometer reading: [21.5, -3.25, 40.125] uT",
        [21_500, -3_250, 40_125],
        None,
        None,
        {},
        id="list-in-text",
    ),
    pytest.param({}, "mag (1 2 3) acc [4,5]", [1, 2, 3], None, None, {}, id="the-list-that-fits"),
    pytest.param({"columns": "t,x,y,z"}, "t: [0.5, 1, 2, 3]", [1, 2, 3], 0.5, None, {}, id="list-with-time"),
    pytest.param(
        {"columns": "lat,lon,alt,x,y,z"},
        "52.1,-1.5,120,1,2,3",
        [1, 2, 3],
        None,
        None,
        {"lat": 52.1, "lon": -1.5, "alt_m": 120},
        id="position-columns",
    ),
    pytest.param({"prefix": "Raw:"}, "Raw: 1 2 3", [1, 2, 3], None, None, {}, id="prefix"),
]


@pytest.mark.parametrize("options, line, readings, t, temp, channels", GOOD)
def test_each_format_reads_known_numbers(options, line, readings, t, temp, channels):
    parser = LineParser(**options)
    got_t, got_r, got_temp, got_channels = parser.parse_sample(line)
    assert np.allclose(got_r, [readings], rtol=1e-12, atol=1e-9)
    assert got_t == (None if t is None else pytest.approx(t))
    assert got_temp == (None if temp is None else pytest.approx(temp))
    for name, value in channels.items():
        assert got_channels[name] == pytest.approx(value)
    assert set(channels) <= set(got_channels) == set(parser.channel_names)
    assert parser.parse(line)[1].shape == (1, 3)  # the three-value form the older callers unpack


# (parser options, line, the reason the line is refused with)
BAD = [
    pytest.param({"template": "x={x} y={y} z={z}"}, "x=1 y=2", "template: expected 'z'", id="template-partial"),
    pytest.param(
        {"template": "x={x} y={y} z={z}"},
        "x=1 y=abc z=3",
        "template: expected a number for {y}",
        id="template-nan-text",
    ),
    pytest.param({"template": "x={x} y={y} z={z}"}, "x=1 y=2 z=3 w=4", "template: text after", id="template-extra"),
    pytest.param({"template": "x={x} y={y} z={z}"}, "x=1.2.3 y=2 z=3", "template: expected", id="template-two-dots"),
    pytest.param(
        {"template": "Magnetometer reading: [{x}, {y}, {z}]"}, "Magnetometer reading: [1, 2", "template", id="cut-list"
    ),
    pytest.param({"columns": SKETCH_COLUMNS}, "|1234,0.01,0.02,1.0,0.1,0.2", "field count", id="frame-partial"),
    pytest.param({"columns": "x,y,z"}, framed("1,2,3")[:-2] + "00", "checksum", id="checksum-wrong"),
    pytest.param({"columns": "x,y,z"}, "|1,2,3x*", "not a number", id="frame-not-a-number"),
    pytest.param({}, "[1, 2, 3] [4, 5, 6]", "brackets: 2 bracketed lists", id="two-lists"),
    pytest.param({}, "reading [1, 2]", "brackets: no bracketed list of 3", id="short-list"),
    pytest.param({}, "[1, 2, abc]", "not a number", id="list-not-a-number"),
    pytest.param({}, "1.0,2.0", "field count", id="cut-line"),
]


@pytest.mark.parametrize("options, line, reason", BAD)
def test_malformed_and_partial_lines_say_why(options, line, reason):
    with pytest.raises(ValueError, match=reason.replace("[", r"\[").replace("{", r"\{")):
        LineParser(**options).parse_sample(line)


@pytest.mark.parametrize(
    "options, line, reason",
    [({}, "# header", "comment"), ({}, "   ", "empty line"), ({"prefix": "Raw:"}, "Init done", "no prefix")],
)
def test_lines_that_are_not_data_are_skipped_with_a_reason(options, line, reason):
    parser = LineParser(**options)
    assert parser.parse_sample(line) is None
    assert parser.last_skip.startswith(reason)


@pytest.mark.parametrize(
    "options, message",
    [
        ({"template": "x={x} y={y}"}, "sensor 1 needs x, y and z"),
        ({"template": "x={x} y={y} z={z} w={w}"}, "'w' is not a known field"),
        ({"template": "x={x:.2f} y={y} z={z}"}, "without ':'"),
        ({"template": "x={x} y={y} z={z"}, "literal braces"),
        ({"template": "x={x} y={y} z={z} x={x}"}, "appears twice"),
        ({"template": "no fields"}, "no field"),
        ({"template": "{x} {y} {z}", "columns": "x,y,z"}, "not both"),
        ({"columns": "x,y,z,mx"}, "name the same field"),
        ({"columns": "t,t_ms,x,y,z"}, "name the same field"),
    ],
)
def test_bad_templates_and_columns_are_one_clear_error(options, message):
    with pytest.raises(LiveError, match=message):
        LineParser(**options)


def test_number_syntax_matches_what_python_reads():
    pattern = __import__("re").compile(lineformats.NUMBER)
    for text in ["0", "-12", "+3.", ".5", "1e3", "-1.5E-03", "nan", "-inf", "Infinity"]:
        m = pattern.fullmatch(text)
        assert m is not None and float(m.group(0)) == pytest.approx(float(text), nan_ok=True)
    for text in ["1.2.3", "e5", "1e", "--1", "."]:
        assert pattern.fullmatch(text) is None


_FLOATS = st.floats(min_value=-1e6, max_value=1e6, allow_nan=False, allow_infinity=False)


@settings(max_examples=200, deadline=None)
@given(
    values=st.tuples(_FLOATS, _FLOATS, _FLOATS, _FLOATS),
    spaces=st.lists(st.sampled_from(["", " ", "  ", "\t"]), min_size=8, max_size=8),
    style=st.sampled_from(["repr", "e", "g", "f3"]),
)
def test_a_template_reads_back_any_number_as_printed(values, spaces, style):
    """Whatever float a sketch prints, in whatever syntax and spacing, the template reads exactly that number."""
    fmt = {"repr": repr, "e": lambda v: f"{v:.6e}", "g": lambda v: f"{v:g}", "f3": lambda v: f"{v:.3f}"}[style]
    texts = [fmt(float(v)) for v in values]
    a = spaces
    line = f"{a[0]}T{a[1]}={a[2]}{texts[0]};{a[3]}mag{a[4]}({texts[1]},{a[5]}{texts[2]}{a[6]},{texts[3]}){a[7]}"
    parser = LineParser(template="T={t}; mag({x}, {y}, {z})")
    t, readings, _, _ = parser.parse_sample(line)
    assert t == float(texts[0])
    assert readings.tolist() == [[float(x) for x in texts[1:]]]


# -- a stream of lines -------------------------------------------------------------------------------------------
def test_a_stream_skips_the_boot_banner_counts_bad_lines_and_reads_the_template_from_the_url():
    port = free_udp_port()
    template = "Magnetometer reading: [{x}, {y}, {z}]"
    src = open_source(f"udp://127.0.0.1:{port}?units=uT&template={urllib.parse.quote(template)}")
    lines = [
        "ets Jun  8 2016 00:22:57",  # an ESP32's boot banner: skipped, never a sample
        "rst:0x1 (POWERON_RESET),boot:0x13",
        "Magnetometer found!",
        "Magnetometer reading: [21.5, -3.25, 40.125]",
        "Magnetometer reading: [21.6, -3.2",  # cut: bad
        "Magnetometer reading: [21.7, -3.15, 40.5]",
        "Magnetometer reading: [nan, -3.15, 40.5]",  # a number, but not a reading: bad value
        "Calibrating gyro...",  # after the first sample: bad
        "Magnetometer reading: [21.8, -3.1, 40.75]",
    ]
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
        tx.sendto(("\n".join(lines) + "\n").encode(), ("127.0.0.1", port))
        chunk = collect(src, 3, timeout_s=10)
    src.close()
    assert np.allclose(
        chunk.readings_nT[0], [[21_500, -3_250, 40_125], [21_700, -3_150, 40_500], [21_800, -3_100, 40_750]]
    )
    stats = src.stats
    assert stats.n_skipped == 3 and stats.skipped["before the first sample"] == 3
    assert stats.n_bad == 3 and stats.reasons["template"] == 2 and stats.reasons["bad value"] == 1
    assert "skipped" in stats.summary() and "template" in stats.summary()


@pytest.mark.filterwarnings("ignore:.*outside the Earth's field range")
def test_a_board_clock_that_restarts_is_followed_on_and_a_small_step_back_is_bad():
    port = free_udp_port()
    src = open_source(f"udp://127.0.0.1:{port}?columns=t,x,y,z")
    lines = ["10.0,1,2,3", "10.1,4,5,6", "9.8,0,0,0", "0.05,7,8,9", "0.15,10,11,12", "nan,1,1,1", "0.25,13,14,15"]
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
        tx.sendto(("\n".join(lines) + "\n").encode(), ("127.0.0.1", port))
        chunk = collect(src, 5, timeout_s=10)
    src.close()
    assert np.array_equal(chunk.readings_nT[0, :, 0], [1, 4, 7, 10, 13])
    t = chunk.time_s
    assert np.allclose(t[:2], [10.0, 10.1]) and np.all(np.diff(t) > 0)
    assert np.allclose(np.diff(t[2:]), 0.1)  # the restarted clock's own steps
    assert src.clock_resets == 1
    assert src.stats.reasons["time going back"] == 1 and src.stats.reasons["bad value"] == 1


def test_options_given_as_keywords_and_a_bad_checksum_option():
    port = free_udp_port()
    src = open_source(f"udp://127.0.0.1:{port}", template="x={x} y={y} z={z}")
    assert src.parser.template is not None and src.parser.columns == ["x", "y", "z"]
    src.close()
    with pytest.raises(LiveError, match="checksum=on or checksum=off"):
        open_source(f"udp://127.0.0.1:{free_udp_port()}?checksum=maybe")
    with pytest.raises(LiveError, match="reconnect"):
        open_source("serial:///dev/null?reconnect=-1")
    with pytest.raises(LiveError, match="not a known field"):
        open_source(f"udp://127.0.0.1:{free_udp_port()}?template=a%3D%7Ba%7D")


# -- channels: a vehicle's attitude through the stream, the recording and the vector fit ------------------------------
def test_attitude_columns_reach_the_recording_and_the_vector_fit(tmp_path):
    from magcal.checks.reference import VectorReference
    from magcal.data.vehicle import simulate_vehicle
    from magcal.fitting.vector import fit_vector

    flight, truth = simulate_vehicle(n=1200, rate_hz=20.0, noise_nT=3.0, attitude_noise_deg=0.02, seed=3)
    ypr = Rotation.from_quat(flight.attitude_wxyz[:, [1, 2, 3, 0]]).as_euler("ZYX", degrees=True)
    roll, pitch, yaw = ypr[:, 2].tolist(), ypr[:, 1].tolist(), ypr[:, 0].tolist()
    rows = [
        framed(f"{round(t * 1000)},0,0,1,0.1,0.2,0.3,{b[0]!r},{b[1]!r},{b[2]!r},{r!r},{p!r},{y!r}")
        for t, b, r, p, y in zip(flight.time_s, flight.readings_nT[0].tolist(), roll, pitch, yaw)
    ]
    port = free_udp_port()
    path = tmp_path / "flight.csv"
    session = LiveSession(f"udp://127.0.0.1:{port}?columns={SKETCH_COLUMNS}", path, flush_interval_s=0.1)
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
            tx.sendto(b"IMU ready\n", ("127.0.0.1", port))
            for k in range(0, len(rows), 40):
                tx.sendto(("\n".join(rows[k : k + 40]) + "\n").encode(), ("127.0.0.1", port))
                time.sleep(0.002)
        end = time.monotonic() + 20
        while session.n_samples < len(rows) and time.monotonic() < end:
            time.sleep(0.05)
    finally:
        session.stop()
    assert session.error is None and session.source.stats.n_bad == 0
    live = session.dataset()
    recorded = magcal.read_csv(path)
    for ds in (live, recorded):
        assert ds.n_samples == flight.n_samples
        assert np.array_equal(ds.readings_nT, flight.readings_nT)
        assert np.allclose(ds.time_s, flight.time_s)
        assert all(c in ds.extra for c in EULER_COLUMNS + ("gyro_z_dps", "accel_z"))
        assert np.allclose(ds.extra["gyro_z_dps"], 0.3)
        # the attitude read back is the one sent
        back = attitude(ds)
        sent = Rotation.from_quat(flight.attitude_wxyz[:, [1, 2, 3, 0]])
        assert np.degrees((back.inv() * sent).magnitude()).max() < 1e-9
    ref = VectorReference(np.tile(truth.field_ned_nT, (flight.n_samples, 1)), "simulated", "vector")
    direct = fit_vector(flight, ref, terms=[], warn=False)
    from_recording = fit_vector(recorded, ref, terms=[], warn=False)
    for a, b in zip(direct.calibration.sensors, from_recording.calibration.sensors):
        assert np.allclose(a.bias_nT, b.bias_nT, atol=1e-6)
    assert np.allclose(from_recording.calibration.sensors[0].bias_nT, truth.sensors[0].bias_nT, atol=15.0)


@pytest.mark.filterwarnings("ignore:.*outside the Earth's field range")
def test_recorder_writes_missing_channel_values_as_nan(tmp_path):
    from magcal.data.live import LiveChunk, Recorder

    chunk = LiveChunk(
        np.array([0.0, 0.1]),
        np.array([[[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]]),
        None,
        {"roll_deg": np.array([1.0, np.nan]), "lat": np.array([np.nan, np.inf])},
    )
    with Recorder(tmp_path / "c.csv", flush_interval_s=0) as rec:
        rec.write(chunk)
    assert rec.n_refused == 1  # an infinite channel value: refused like any other
    ds = magcal.read_csv(tmp_path / "c.csv")
    assert ds.n_samples == 1 and ds.extra["roll_deg"][0] == 1.0 and np.isnan(ds.extra["lat"][0])


# -- MAVLink: ATTITUDE and the position merged onto the magnetometer ----------------------------------------------
def test_mavlink_attitude_merged_nearest_within_the_bound_and_gps_gives_the_igrf_reference():
    from pymavlink.dialects.v20 import common as mavlink2

    from magcal.checks.reference import igrf_ned_nT, resolve_reference, resolve_vector_reference

    port = free_udp_port()
    src = open_source(f"udp://127.0.0.1:{port}?mavlink&message=SCALED_IMU&attitude_max_dt=0.03")
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    lat, lon, alt_m = 52.2053, 0.1218, 77.0
    mag_ms = 1000 + 20 * np.arange(20)  # 50 Hz
    att_ms = 1007 + 50 * np.arange(6)  # 20 Hz, then the attitude stream stops (last at 1257 ms)
    att_roll = 10.0 * np.arange(6)  # deg: which message was merged shows in the roll
    events = [(t, "mag", k) for k, t in enumerate(mag_ms)] + [(t, "att", j) for j, t in enumerate(att_ms)]
    packets = [
        mav.gps_raw_int_encode(0, 3, round(lat * 1e7), round(lon * 1e7), 30_000, 0, 0, 0, 0, 9, round(alt_m * 1000))
    ]
    for t, kind, k in sorted(events):
        if kind == "mag":
            packets.append(mav.scaled_imu_encode(int(t), 0, 0, 1000, 0, 0, 0, 200 + k, -30, 400, 0))
        else:
            r = np.radians(att_roll[k])
            packets.append(mav.attitude_encode(int(t), r, np.radians(-5.0), np.radians(190.0), 0.01 * k, 0.0, -0.02))
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
        for m in packets:
            tx.sendto(m.pack(mav), ("127.0.0.1", port))
        chunk = collect(src, len(mag_ms), timeout_s=10)
    src.close()
    assert len(chunk) == len(mag_ms) and src.stats.n_bad == 0
    assert np.allclose(chunk.readings_nT[0, :, 0], (200 + np.arange(20)) * 100.0)
    # each sample carries the nearest ATTITUDE within 30 ms; beyond (after the stream stopped) NaN, never a stale one
    gap = np.abs(mag_ms[:, None] - att_ms[None, :])
    nearest = np.argmin(gap, axis=1)
    within = gap.min(axis=1) <= 30
    assert within.sum() == 15 and not within[-4:].any()
    roll = chunk.channels["roll_deg"]
    assert np.allclose(roll[within], att_roll[nearest[within]], atol=1e-4)  # float32 radians
    assert np.all(np.isnan(roll[~within]))
    assert np.allclose(chunk.channels["pitch_deg"][within], -5.0)
    assert np.allclose(chunk.channels["yaw_deg"][within], -170.0)  # wrapped to -180..180
    assert np.allclose(chunk.channels["gyro_x_dps"][within], np.degrees(0.01 * nearest[within]))
    assert np.allclose(chunk.channels["gyro_z_dps"][within], np.degrees(-0.02))
    # the position: every sample (the fix came first), above the ellipsoid; and the reference field from it
    assert np.allclose(chunk.channels["lat"], lat) and np.allclose(chunk.channels["lon"], lon)
    assert np.allclose(chunk.channels["alt_m"], alt_m)
    assert src.location == pytest.approx((lat, lon, alt_m))
    ds = chunk.to_dataset(source="mavlink")
    ref = resolve_vector_reference(ds, "igrf", date="2026-01-01")
    expected = igrf_ned_nT(lat, lon, alt_m / 1000.0, date="2026-01-01")[0]
    assert ref.kind == "igrf-track" and np.allclose(ref.ned_nT, expected, atol=1e-6)
    total = resolve_reference(
        reference="igrf", lat=src.location[0], lon=src.location[1], alt_km=alt_m / 1000.0, date="2026-01-01"
    ).value_nT
    assert total == pytest.approx(np.linalg.norm(expected), abs=1e-6)


def test_mavlink_without_attitude_gets_position_only_and_no_fix_is_nan():
    from pymavlink.dialects.v20 import common as mavlink2

    port = free_udp_port()
    src = open_source(f"udp://127.0.0.1:{port}?mavlink")
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    packets = [mav.gps_raw_int_encode(0, 1, 0, 0, 0, 0, 0, 0, 0, 0)]  # no fix yet
    packets += [mav.scaled_imu_encode(1000 + 20 * k, 0, 0, 0, 0, 0, 0, 100, 0, 0, 0) for k in range(3)]
    packets.append(mav.global_position_int_encode(1100, round(-33.9 * 1e7), round(18.4 * 1e7), 12_000, 0, 0, 0, 0, 0))
    packets += [mav.scaled_imu_encode(1200 + 20 * k, 0, 0, 0, 0, 0, 0, 100, 0, 0, 0) for k in range(3)]
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
        for m in packets:
            tx.sendto(m.pack(mav), ("127.0.0.1", port))
        chunk = collect(src, 6, timeout_s=10)
    src.close()
    assert len(chunk) == 6 and set(chunk.channels) == {"lat", "lon", "alt_m"}
    assert np.all(np.isnan(chunk.channels["lat"][:3]))  # before the fix: unknown, not 0
    assert np.allclose(chunk.channels["lat"][3:], -33.9) and np.allclose(chunk.channels["alt_m"][3:], 12.0)


# -- the serial port disappears and comes back ----------------------------------------------------------------------
def wait_for(condition, timeout_s=15.0):
    end = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > end:
            return False
        time.sleep(0.02)
    return True


class BoardPort:
    """A board's serial port: a udev-like name (a symlink, ``path``) to a pseudo-terminal whose master end the test
    writes, which a reset takes away and brings back, a new pty under the same name."""

    def __init__(self, path):
        self.path = path
        self.master = self.slave = None
        self._plug()

    def _plug(self):
        self.master, self.slave = os.openpty()
        self.path.symlink_to(os.ttyname(self.slave))

    def write(self, data: bytes):
        os.write(self.master, data)

    def close(self):
        for fd in (self.master, self.slave):
            if fd is not None:
                os.close(fd)
        self.master = self.slave = None

    def reset(self, session, away_s=0.6):
        """The board resets: its pty closed and its name removed while ``session`` records; back after
        ``away_s`` (the source's tries meanwhile fail and are retried), and the source reopens it once."""
        src = session.source
        self.close()
        self.path.unlink()
        assert wait_for(lambda: not src.connected)
        time.sleep(away_s)
        assert session.running and not src.connected and src.stats.n_reconnects == 0
        self._plug()
        assert wait_for(lambda: src.stats.n_reconnects == 1)


@pytest.mark.filterwarnings("ignore:.*outside the Earth's field range")  # small numbers, easy to follow
def test_serial_port_reopened_after_a_board_reset_and_the_recording_goes_on(tmp_path):
    # The board's port is a udev-like name (a symlink) to a pseudo-terminal. The board resets: its pty goes away
    # (the test closes it and removes the name), and comes back as a new pty under the same name, printing its banner
    # and restarting its clock.
    board = BoardPort(tmp_path / "ttyBOARD")
    path = tmp_path / "board.csv"
    session = LiveSession(f"serial://{board.path}?columns=t,x,y,z&reconnect=20", path, flush_interval_s=0.05)
    src = session.source
    try:
        board.write(b"0.1,1,2,3\r\n0.2,4,5,6\r\n0.3,7,8,9\r\n0.4,10,")  # the last line is cut by the reset
        assert wait_for(lambda: session.n_samples == 3)
        board.reset(session)
        board.write(b"\r\nBoard v1.2 booting...\r\n0.05,11,12,13\r\n0.15,14,15,16\r\n")
        assert wait_for(lambda: session.n_samples == 5)
        assert wait_for(lambda: session.n_recorded == 5)
    finally:
        session.stop()
        board.close()
    assert session.error is None
    recorded = magcal.read_csv(path)
    expected = np.array([[1, 2, 3], [4, 5, 6], [7, 8, 9], [11, 12, 13], [14, 15, 16]], dtype=float)
    assert np.array_equal(recorded.readings_nT[0], expected)  # nothing before the gap lost, nothing after it
    assert np.array_equal(session.dataset().readings_nT[0], expected)
    t = recorded.time_s
    assert np.allclose(t[:3], [0.1, 0.2, 0.3]) and np.all(np.diff(t) > 0)
    assert t[3] - t[2] >= 0.6  # the board's restarted clock follows on after the gap the host saw
    assert t[4] - t[3] == pytest.approx(0.1)
    stats = src.stats
    assert stats.n_reconnects == 1 and src.clock_resets == 1
    assert stats.reasons["cut line"] == 1 and stats.n_bad == 1
    assert stats.skipped["before the first sample"] >= 1  # the banner
    assert "1 reconnect" in stats.summary()


def test_serial_port_that_does_not_come_back_ends_with_a_clear_error(tmp_path):
    port = tmp_path / "ttyGONE"
    master, slave = os.openpty()
    port.symlink_to(os.ttyname(slave))
    src = open_source(f"serial://{port}?reconnect=0.5")
    os.close(master)
    os.close(slave)
    port.unlink()
    start = time.monotonic()
    with pytest.raises(LiveError, match="did not come back within 0.5 s"):
        while time.monotonic() - start < 10:
            src.read(timeout_s=0.2)
    assert time.monotonic() - start < 5
    src.close()
    master, slave = os.openpty()
    try:
        src = open_source(f"serial://{os.ttyname(slave)}?reconnect=0")
        os.close(master)
        master = None
        with pytest.raises(LiveError, match="the serial port .* failed"):
            src.read(timeout_s=0.5)
        src.close()
    finally:
        os.close(slave)
        if master is not None:
            os.close(master)


# -- the command line ----------------------------------------------------------------------------------------------
def test_magcal_record_reads_a_template_given_on_the_command_line(tmp_path, capsys):
    import threading

    from magcal.cli import main

    port = free_udp_port()
    out = tmp_path / "rec.csv"
    stop = threading.Event()

    def board():  # prints its reading every 50 ms until the recorder has what it wants
        k = 0
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
            while not stop.is_set():
                tx.sendto(f"Magnetometer reading: [{20 + k}, -3.5, 40.25]\n".encode(), ("127.0.0.1", port))
                k += 1
                time.sleep(0.05)

    thread = threading.Thread(target=board, daemon=True)
    thread.start()
    try:
        rc = main(
            [
                "record",
                f"udp://127.0.0.1:{port}?columns=x,y,z",  # the URL's columns give way to --template
                str(out),
                "--template",
                "Magnetometer reading: [{x}, {y}, {z}]",
                "--units",
                "uT",
                "--samples",
                "5",
                "--seconds",
                "20",
            ]
        )
    finally:
        stop.set()
        thread.join(5)
    assert rc == 0
    ds = magcal.read_csv(out)
    assert ds.n_samples == 5
    assert np.allclose(ds.readings_nT[0, :, 1:], [-3_500, 40_250])
    assert np.all(np.diff(ds.readings_nT[0, :, 0]) == 1000)  # consecutive readings, 1 uT apart
    assert "5 samples" in capsys.readouterr().err


def test_magcal_record_bad_template_is_one_line(tmp_path, capsys):
    from magcal.cli import main

    rc = main(["record", f"udp://127.0.0.1:{free_udp_port()}", str(tmp_path / "r.csv"), "--template", "x={x} q={q}"])
    err = capsys.readouterr().err
    assert rc != 0 and "'q' is not a known field" in err and "Traceback" not in err
    assert not (tmp_path / "r.csv").exists()


def test_mavlink_samples_held_for_their_attitude_are_drained_not_lost():
    from pymavlink.dialects.v20 import common as mavlink2

    port = free_udp_port()
    src = open_source(f"udp://127.0.0.1:{port}?mavlink&attitude_max_dt=5")  # held up to 5.3 s for an attitude
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    packets = [mav.attitude_encode(1000, 0.1, 0, 0, 0, 0, 0)]
    packets += [mav.scaled_imu_encode(1000 + 20 * k, 0, 0, 0, 0, 0, 0, 100 + k, 0, 0, 0) for k in range(3)]
    packets.append(mav.attitude_encode(1045, 0.2, 0, 0, 0, 0, 0))
    packets += [mav.scaled_imu_encode(1060 + 20 * k, 0, 0, 0, 0, 0, 0, 103 + k, 0, 0, 0) for k in range(2)]
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
        for m in packets:
            tx.sendto(m.pack(mav), ("127.0.0.1", port))
        first = collect(src, 3, timeout_s=3)
    assert len(first) == 3  # released: the attitude after them has arrived
    rest = src.drain()  # the last two wait for an attitude that has not come; stopping keeps them
    src.close()
    assert len(rest) == 2 and np.allclose(rest.readings_nT[0, :, 0], [10_300, 10_400])
    assert np.allclose(rest.channels["roll_deg"], np.degrees(0.2), atol=1e-4)  # the nearest, 15 and 35 ms away
    assert np.allclose(first.channels["roll_deg"], np.degrees([0.1, 0.1, 0.2]), atol=1e-4)


@pytest.mark.parametrize(
    "line, options",
    [
        ("21.5,-3.2,40.1", {}),
        ("1234,21.5,-3.2,40.1,22.5", {"columns": "t_ms,x,y,z,temp"}),
        ("x=21.5 y=-3.2 z=40.1", {"template": "x={x} y={y} z={z}"}),
        ("Magnetometer reading: [21.5, -3.2, 40.1]", {}),
        ("Magnetometer reading: [21.5, -3.2, 40.1]", {"template": "Magnetometer reading: [{x}, {y}, {z}]"}),
        ("mag (21.5 -3.2 40.1) acc (0.01 0.02 0.98)", {"template": "mag ({x} {y} {z}) acc ({_} {_} {_})"}),
        ("|1234,0.01,0.02,0.98,0.1,0.2,0.3,21.5,-3.2,40.1,1.5,-0.5,87.0*", {"columns": SKETCH_COLUMNS}),
        ("$PMAG,21.5,-3.2,40.1*36", {"columns": "_,x,y,z"}),
    ],
)
def test_the_examples_of_docs_formats_read_as_documented(line, options):
    """The table of docs/formats.md's live section, line by line (each reads 21.5, -3.2, 40.1 uT)."""
    text = open(os.path.join(os.path.dirname(__file__), "..", "..", "docs", "formats.md"), encoding="utf-8").read()
    assert line.replace("|", "\\|") in text
    _, readings, _, _ = LineParser(units="uT", **options).parse_sample(line)
    assert np.allclose(readings, [[21_500, -3_200, 40_100]])


def test_a_recording_played_again_keeps_its_channels(tmp_path):
    from magcal.data.vehicle import simulate_vehicle

    flight, _ = simulate_vehicle(n=50, rate_hz=50.0, seed=4)
    ypr = Rotation.from_quat(flight.attitude_wxyz[:, [1, 2, 3, 0]]).as_euler("ZYX", degrees=True)
    ds = flight.replace(
        attitude_wxyz=None,
        extra={"roll_deg": ypr[:, 2], "pitch_deg": ypr[:, 1], "yaw_deg": ypr[:, 0], "lat": np.full(50, 45.0)},
    )
    from magcal.data.io import write_csv

    write_csv(tmp_path / "flight.csv", ds)
    src = open_source(f"sim://{tmp_path / 'flight.csv'}?speed=50")
    chunk = collect(src, 50, timeout_s=10)
    src.close()
    assert len(chunk) == 50 and set(chunk.channels) == {"roll_deg", "pitch_deg", "yaw_deg", "lat"}
    back = attitude(chunk.to_dataset())
    sent = Rotation.from_quat(flight.attitude_wxyz[:, [1, 2, 3, 0]])
    assert np.degrees((back.inv() * sent).magnitude()).max() < 1e-9
