"""Live sources and the recorder (magcal.data.live): serial through a pseudo-terminal, UDP and TCP lines, MAVLink over
loopback UDP, the simulated source's pace, and a recording that survives SIGKILL.

Every wait is bounded; loopback addresses only; no assertion depends on how fast the machine is, except generous
lower bounds on sample counts over a measured time (the upper bounds follow from the schedule itself).
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

import magcal
from magcal.data.live import (
    LineParser,
    LiveError,
    LiveSession,
    Recorder,
    SimSource,
    concatenate_chunks,
    open_source,
    record,
)

pytest.importorskip("serial")
pytest.importorskip("pymavlink")


def collect(source, n, timeout_s=20.0):
    """Read until ``n`` samples arrived or ``timeout_s`` passed; one chunk."""
    chunks = []
    end = time.monotonic() + timeout_s
    while sum(len(c) for c in chunks) < n and time.monotonic() < end:
        chunks.append(source.read(timeout_s=0.2))
    return concatenate_chunks(chunks)


def free_udp_port():
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# -- text lines ------------------------------------------------------------------------------------------------------
def test_line_parser_columns_units_and_bad_lines():
    p = LineParser("t,_,x,y,z,temp", units="uT")
    t, r, temp = p.parse("1.5, 99, 20.0 -3.5;40\t21.5")
    assert t == 1.5 and temp == 21.5
    assert np.allclose(r, [[20_000.0, -3_500.0, 40_000.0]])
    with pytest.raises(ValueError, match="field count"):
        p.parse("1,2,3")
    with pytest.raises(ValueError, match="not a number"):
        p.parse("1,2,abc,4,5,6")
    assert p.parse("# a comment") is None
    q = LineParser("x,y,z", units="counts", lsb_nT=150, prefix="Raw:")
    assert q.parse("hello") is None  # not data: ignored, not bad
    assert np.allclose(q.parse("Raw:1,2,3")[1], [[150, 300, 450]])
    two = LineParser("s1x,s1y,s1z,s2x,s2y,s2z")
    assert two.n_sensors == 2 and two.parse("1 2 3 4 5 6")[1].shape == (2, 3)
    with pytest.raises(LiveError, match="sensor 1 needs x, y and z"):
        LineParser("x,y")
    with pytest.raises(LiveError, match="unknown option"):
        open_source("udp://127.0.0.1:9?colums=x,y,z")
    with pytest.raises(LiveError, match="unknown source"):
        open_source("ftp://127.0.0.1:9")


def test_serial_source_through_a_pseudo_terminal():
    master, slave = os.openpty()
    path = os.ttyname(slave)
    try:
        src = open_source(f"serial://{path}?baud=115200&columns=t,x,y,z,temp&units=uT")
        lines = [
            "0.10,20.5,-3.25,41.0,22.5",
            "garbage line",
            "0.20,20.6,-3.20,41.1,22.5",
            "0.30,1e3,oops,3,22.5",
            "0.15,1,1,1,22.5",
            "0.40,20.7,-3.15,41.2,22.6",
        ]
        os.write(master, ("\r\n".join(lines) + "\r\n").encode())
        chunk = collect(src, 3)
        assert len(chunk) == 3
        assert np.allclose(chunk.time_s, [0.1, 0.2, 0.4])
        assert np.allclose(
            chunk.readings_nT[0], [[20_500, -3_250, 41_000], [20_600, -3_200, 41_100], [20_700, -3_150, 41_200]]
        )
        assert np.allclose(chunk.temperature_C, [22.5, 22.5, 22.6])
        # three bad lines counted, each with its reason: wrong field count, not a number, time going back
        assert src.stats.n_bad == 3
        assert set(src.stats.reasons) == {"field count", "not a number", "time going back"}
        # a line split across two writes is put back together
        os.write(master, b"0.50,20.8,-3.1")
        assert len(src.read(timeout_s=0.3)) == 0
        os.write(master, b"0,41.3,22.7\n")
        chunk = collect(src, 1)
        assert np.allclose(chunk.readings_nT[0, 0], [20_800, -3_100, 41_300])
        src.close()
        with pytest.raises(LiveError, match="closed"):
            src.read()
    finally:
        os.close(master)
        os.close(slave)


def test_serial_source_missing_device_is_a_clear_error(tmp_path):
    with pytest.raises(LiveError, match="cannot open the serial port"):
        open_source(f"serial://{tmp_path}/no-such-tty")


def test_udp_lines():
    port = free_udp_port()
    src = open_source(f"udp://127.0.0.1:{port}?format=lines&columns=x,y,z")
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
        tx.sendto(b"100,200,300\n400,500,600", ("127.0.0.1", port))
        tx.sendto(b"\xff\xfe bad bytes\n700,800,900\n", ("127.0.0.1", port))
        chunk = collect(src, 3)
    src.close()
    assert np.allclose(chunk.readings_nT[0], [[100, 200, 300], [400, 500, 600], [700, 800, 900]])
    assert np.all(np.diff(chunk.time_s) > 0)  # host clock stamps
    assert src.stats.n_bad == 1 and "not text" in src.stats.last_bad


def _ipv6_loopback() -> bool:
    try:
        with socket.socket(socket.AF_INET6, socket.SOCK_DGRAM) as probe:
            probe.bind(("::1", 0))
        return True
    except OSError:
        return False


@pytest.mark.skipif(not _ipv6_loopback(), reason="no IPv6 loopback on this machine")
def test_udp_lines_on_ipv6():
    """An IPv6 address in brackets (RFC 3986) listens on IPv6; a name stays IPv4, as before."""
    with socket.socket(socket.AF_INET6, socket.SOCK_DGRAM) as probe:
        probe.bind(("::1", 0))
        port = probe.getsockname()[1]
    src = open_source(f"udp://[::1]:{port}?format=lines&columns=x,y,z")
    with socket.socket(socket.AF_INET6, socket.SOCK_DGRAM) as tx:
        tx.sendto(b"100,200,300\n", ("::1", port))
        chunk = collect(src, 1)
    src.close()
    assert np.allclose(chunk.readings_nT[0], [[100, 200, 300]])


@pytest.mark.parametrize("scheme", ["udp", "tcp"])
def test_mavlink_over_ipv6_is_refused_clearly(scheme):
    with pytest.raises(LiveError, match=r"MAVLink over IPv6 \(::1\) is not supported.*IPv4"):
        open_source(f"{scheme}://[::1]:14550?mavlink")


def test_tcp_lines_until_the_server_closes():
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(1)
    port = server.getsockname()[1]

    def serve():
        conn, _ = server.accept()
        with conn:
            for k in range(5):
                conn.sendall(f"{k},{k + 1},{k + 2}\n".encode())

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    src = open_source(f"tcp://127.0.0.1:{port}")
    chunks = list(src)  # iterating ends when the server closes the connection
    thread.join(5)
    server.close()
    chunk = concatenate_chunks(chunks)
    assert src.ended and len(chunk) == 5
    assert np.allclose(chunk.readings_nT[0, :, 0], np.arange(5))


def test_tcp_refused_connection_is_a_clear_error():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # bound but not listening: the connection is refused
        with pytest.raises(LiveError, match="cannot connect"):
            open_source(f"tcp://127.0.0.1:{port}?timeout=2")


# -- MAVLink ---------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["SCALED_IMU", "SCALED_IMU2", "RAW_IMU", "HIGHRES_IMU"])
def test_mavlink_udp_magnetometer_in_nT(kind):
    from pymavlink.dialects.v20 import common as mavlink2

    port = free_udp_port()
    src = open_source(f"udp://127.0.0.1:{port}?mavlink")
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    mags_mG = [(212, -35, 410), (215, -30, 405), (-100, 250, 300)]
    packets = []
    for k, (x, y, z) in enumerate(mags_mG):
        t_ms = 1000 + 20 * k
        if kind == "SCALED_IMU":
            m = mav.scaled_imu_encode(t_ms, 0, 0, 1000, 0, 0, 0, x, y, z, 2512 + k)
        elif kind == "SCALED_IMU2":
            m = mav.scaled_imu2_encode(t_ms, 0, 0, 1000, 0, 0, 0, x, y, z, 0)  # 0: no temperature
        elif kind == "RAW_IMU":
            m = mav.raw_imu_encode(t_ms * 1000, 0, 0, 1000, 0, 0, 0, x, y, z, 0, 3000)
        else:
            m = mav.highres_imu_encode(
                t_ms * 1000,
                0,
                0,
                9.8,
                0,
                0,
                0,
                x / 1000,
                y / 1000,
                z / 1000,
                1013,
                0,
                0,
                24.5,
                (0b111 << 6) | (1 << 12),
                0,
            )
        packets.append(m.pack(mav))
    heartbeat = mav.heartbeat_encode(2, 3, 0, 0, 4).pack(mav)
    corrupted = bytearray(packets[0])
    corrupted[-1] ^= 0xFF  # a failed checksum
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
        for buf in [heartbeat, bytes(corrupted)] + packets:
            tx.sendto(buf, ("127.0.0.1", port))
        chunk = collect(src, 3, timeout_s=10)
    src.close()
    assert src.message == kind
    assert len(chunk) == 3
    assert np.allclose(chunk.readings_nT[0], np.array(mags_mG) * 100.0, atol=1e-3)  # mgauss (or gauss) -> nT
    assert np.allclose(chunk.time_s, 1.0 + 0.02 * np.arange(3))
    expected_temp = {
        "SCALED_IMU": 25.12 + 0.01 * np.arange(3),
        "SCALED_IMU2": None,
        "RAW_IMU": [30.0] * 3,
        "HIGHRES_IMU": [24.5] * 3,
    }[kind]
    if expected_temp is None:
        assert chunk.temperature_C is None
    else:
        assert np.allclose(chunk.temperature_C, expected_temp)


# -- simulation ------------------------------------------------------------------------------------------------------
def test_sim_source_plays_in_real_time_and_is_deterministic():
    src = open_source("sim://chi2017?rate=50")
    start = time.monotonic()
    chunks = []
    while time.monotonic() - start < 1.0:
        chunks.append(src.read(timeout_s=0.1))
    elapsed = time.monotonic() - start
    chunk = concatenate_chunks(chunks)
    n = len(chunk)
    # never ahead of its schedule (sample k is due at k/50 s), and not far behind it on a loaded machine
    assert n <= 50 * elapsed + 1
    assert n >= 0.3 * 50 * 1.0
    assert np.allclose(chunk.time_s, np.arange(n) / 50.0)
    again = SimSource("sim://chi2017", "chi2017", rate_hz=50)
    assert np.array_equal(chunk.readings_nT, np.stack([again.sample(k)[1] for k in range(n)], axis=1))
    assert chunk.n_sensors == 4 and chunk.temperature_C is not None


def test_sim_source_from_a_file_ends(tmp_path):
    ds = magcal.simulate("chi2017", n_samples=30, seed=4).sensors([0])
    path = tmp_path / "play.csv"
    magcal.data.io.write_csv(path, ds)
    src = open_source(f"sim://{path}?rate=1000")
    chunk = concatenate_chunks(list(src))
    assert src.ended and len(chunk) == 30
    assert np.allclose(chunk.readings_nT, ds.readings_nT)


# -- recording -------------------------------------------------------------------------------------------------------
def test_recorder_lines_never_cross_a_page(tmp_path):
    """Every page boundary of the file falls at the start of a line, so no kill can cut a line in two."""
    path = tmp_path / "rec.csv"
    src = SimSource("sim://chi2017", "chi2017", rate_hz=100)
    rec = Recorder(path, flush_interval_s=0.0)
    rec._page = 512  # small pages: many boundaries in a short file
    for start in range(0, 600, 37):
        samples = [src.sample(k) for k in range(start, min(start + 37, 600))]
        from magcal.data.live import LiveChunk

        rec.write(
            LiveChunk(
                np.array([s[0] for s in samples]),
                np.stack([s[1] for s in samples], axis=1),
                np.array([s[2] for s in samples]),
            )
        )
    rec.close()
    raw = path.read_bytes()
    assert all(raw[b - 1 : b] == b"\n" for b in range(512, len(raw), 512))
    ds = magcal.read_csv(path)
    assert ds.n_samples == 600
    assert np.allclose(ds.time_s, np.arange(600) / 100)
    with pytest.raises(LiveError, match="never overwritten"):
        Recorder(path)


def test_recording_survives_sigkill(tmp_path):
    """A recorder killed mid-stream leaves a file that reopens with every sample of its last flush, each exactly
    the sample the deterministic source sent."""
    path = tmp_path / "killed.csv"
    rate = 100
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "magcal",
            "record",
            f"sim://chi2017?rate={rate}",
            str(path),
            "--flush",
            "0.2",
            "--progress",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "OPENBLAS_NUM_THREADS": "1"},
    )
    flushed = []
    try:
        reader = threading.Thread(
            target=lambda: [flushed.append(int(line.split()[1])) for line in proc.stdout if line.startswith("flushed")],
            daemon=True,
        )
        reader.start()
        end = time.monotonic() + 60
        while (not flushed or flushed[-1] < 60) and time.monotonic() < end and proc.poll() is None:
            time.sleep(0.05)
        assert flushed and flushed[-1] >= 60, proc.stderr.read() if proc.poll() is not None else "no flush in 60 s"
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
        reader.join(5)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    last_reported = flushed[-1]
    raw = path.read_bytes()
    assert raw.endswith(b"\n")  # whole lines only
    ds = magcal.read_csv(path)
    assert ds.n_samples >= last_reported
    src = SimSource("sim://chi2017", "chi2017", rate_hz=rate)
    expected = np.stack([src.sample(k)[1] for k in range(ds.n_samples)], axis=1)
    assert np.array_equal(ds.readings_nT, expected)
    assert np.array_equal(ds.time_s, np.arange(ds.n_samples) / rate)


def test_record_function_counts_and_stops(tmp_path):
    path = tmp_path / "r.csv"
    stats = record("sim://chi2017?rate=2000", path, max_samples=150, flush_interval_s=0.05)
    assert stats.n_samples >= 150
    assert magcal.read_csv(path).n_samples == 150


def test_live_session_records_what_viewers_see(tmp_path):
    path = tmp_path / "session.csv"
    seen = []
    session = LiveSession(
        "sim://chi2017?rate=50&speed=10", path, flush_interval_s=0.1, listeners=[lambda chunk: seen.append(len(chunk))]
    )
    late = []
    session.subscribe(late.append)
    end = time.monotonic() + 30
    while session.n_samples < 200 and time.monotonic() < end:
        time.sleep(0.05)
    session.pause()
    time.sleep(0.3)
    paused_count = session.n_samples
    time.sleep(0.3)
    assert session.n_samples == paused_count  # nothing kept while paused
    session.resume()
    session.stop()
    assert not session.running and session.error is None
    ds = session.dataset()
    assert ds.n_samples >= 200 and sum(seen) == ds.n_samples
    assert 0 < sum(len(c) for c in late) <= ds.n_samples
    recorded = magcal.read_csv(path)
    assert recorded.n_samples == ds.n_samples == session.n_recorded
    assert np.array_equal(recorded.readings_nT, ds.readings_nT)


def test_a_failing_viewer_is_a_note_and_the_recording_goes_on(tmp_path):
    """A listener that raises on every chunk neither stops the session nor reaches Python's warnings: the session
    keeps a bounded list of notes (no warnings.warn inside the engine)."""

    def broken(chunk):
        raise ValueError("the viewer is gone")

    kept = []
    session = LiveSession("sim://chi2017?rate=200&speed=10", None, listeners=[broken, lambda c: kept.append(len(c))])
    end = time.monotonic() + 30
    while session.n_samples < 300 and time.monotonic() < end:
        time.sleep(0.05)
    session.stop()
    assert session.error is None and session.n_samples >= 300
    assert sum(kept) == session.n_samples  # the viewer after the broken one saw every sample
    assert 1 <= len(session.notes) <= 20
    assert all("live listener failed: the viewer is gone" == n.text for n in session.notes)


def test_serial_over_long_line_is_counted_and_skipped():
    master, slave = os.openpty()
    try:
        src = open_source(f"serial://{os.ttyname(slave)}?columns=x,y,z")
        writer = threading.Thread(target=lambda: os.write(master, b"9" * 6000 + b",1,1\n1,2,3\n"), daemon=True)
        writer.start()
        chunk = collect(src, 1)
        writer.join(5)
        src.close()
        assert len(chunk) == 1 and np.allclose(chunk.readings_nT[0], [[1, 2, 3]])
        assert src.stats.n_bad == 1 and src.stats.reasons["line too long"] == 1
    finally:
        os.close(master)
        os.close(slave)


def test_mavlink_vehicle_reboot_keeps_time_increasing():
    from pymavlink.dialects.v20 import common as mavlink2

    port = free_udp_port()
    src = open_source(f"udp://127.0.0.1:{port}?mavlink&message=SCALED_IMU")
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    times_ms = [50_000, 50_020, 300, 320]  # the vehicle rebooted after the second sample
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
        for k, t in enumerate(times_ms):
            tx.sendto(mav.scaled_imu_encode(t, 0, 0, 0, 0, 0, 0, 100 + k, 0, 0, 0).pack(mav), ("127.0.0.1", port))
        chunk = collect(src, 4, timeout_s=10)
    src.close()
    assert len(chunk) == 4 and src.clock_resets == 1 and src.stats.n_bad == 0
    assert np.all(np.diff(chunk.time_s) > 0)
    assert np.isclose(chunk.time_s[3] - chunk.time_s[2], 0.02)
