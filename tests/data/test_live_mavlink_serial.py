"""A MAVLink source on a serial port that disappears (an autopilot reset, a USB re-enumeration) and comes back.

A fake autopilot writes real MAVLink packets (pymavlink's encoder) on a pseudo-terminal behind a udev-like name (a
symlink); the test closes the pty and removes the name (the reset), and brings a new pty back under the same name,
its boot clock restarted from 0. Every sample sent before and after is recorded, in order, to the nT, the
attitude and the position of one boot never merged onto the samples of the other. Every wait is bounded;
pseudo-terminals only.
"""

from __future__ import annotations

import os
import threading
import time

import numpy as np
import pytest

import magcal
from magcal.data.live import LiveError, LiveSession, open_source

pytest.importorskip("serial")
pytest.importorskip("pymavlink")

from pymavlink.dialects.v20 import common as mavlink2

from tests.data.test_lineformats import BoardPort, wait_for


class Autopilot:
    """A fake autopilot's packets: RAW_IMU (milligauss, time in us) with ATTITUDE ``att_lag_ms`` after each, and a
    GPS fix; ``roll_deg`` of each ATTITUDE tells which one a sample got."""

    def __init__(self):
        self.mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)

    def imu(self, t_ms, mag_mgauss, temp_cdeg=2150):
        x, y, z = (int(v) for v in mag_mgauss)
        return self.mav.raw_imu_encode(int(t_ms) * 1000, 0, 0, 1000, 0, 0, 0, x, y, z, 0, temp_cdeg).pack(self.mav)

    def attitude(self, t_ms, roll_deg):
        return self.mav.attitude_encode(int(t_ms), np.radians(roll_deg), np.radians(-3.0), 0.5, 0, 0, 0).pack(self.mav)

    def fix(self, lat, lon, alt_m):
        return self.mav.gps_raw_int_encode(
            0, 3, round(lat * 1e7), round(lon * 1e7), round(alt_m * 1000), 0, 0, 0, 0, 9, round(alt_m * 1000)
        ).pack(self.mav)

    def stream(self, t_ms, mag_mgauss, roll_deg, att_lag_ms):
        return b"".join(
            self.imu(t, m) + self.attitude(t + att_lag_ms, r) for t, m, r in zip(t_ms, mag_mgauss, roll_deg)
        )

    # The two boots a reconnection test plays. Boot 1: 10 samples at 50 Hz from 100 ms, each ATTITUDE 5 ms after
    # its sample, a fix first, then the first CUT_BYTES of a packet the loss cuts. Boot 2, after the loss, its clock
    # from 0: times overlapping boot 1's, each ATTITUDE 8 ms after its sample (so that a boot-1 ATTITUDE, 5 ms away,
    # would be nearer were the boots mixed), a new fix after its 5th sample.
    T1 = 100 + 20 * np.arange(10)
    MAG1 = np.column_stack([150 + np.arange(10), -220 - 3 * np.arange(10), 410 + 2 * np.arange(10)])
    ROLL1 = 1.0 + np.arange(10)
    T2 = 20 + 20 * np.arange(20)
    MAG2 = np.column_stack([-90 - np.arange(20), 330 + 5 * np.arange(20), 275 - np.arange(20)])
    ROLL2 = -40.0 - np.arange(20)
    CUT_BYTES = 12

    def first_boot(self) -> bytes:
        cut = self.imu(300, (1, 2, 3))[: self.CUT_BYTES]
        return self.fix(52.2053, 0.1218, 77.0) + self.stream(self.T1, self.MAG1, self.ROLL1, 5) + cut

    def second_boot(self) -> list:
        """Boot 2's bytes in two writes: five samples, then the new fix and the rest."""
        return [
            self.stream(self.T2[:5], self.MAG2[:5], self.ROLL2[:5], 8),
            self.fix(-33.9, 18.4, 12.0) + self.stream(self.T2[5:], self.MAG2[5:], self.ROLL2[5:], 8),
        ]


def check_two_boots(path, src):
    """What a recording of :meth:`Autopilot.first_boot`, a loss of at least 0.6 s and :meth:`Autopilot.second_boot`
    must hold: every sample, in order, to the nT; the restarted clock followed on; each sample the ATTITUDE of its
    own boot and the fix received since the port (re)opened; one reconnect, one clock reset, one cut packet."""
    a = Autopilot
    recorded = magcal.read_csv(path)
    expected_nT = 100.0 * np.vstack([a.MAG1, a.MAG2])  # milligauss
    assert recorded.n_samples == 30
    assert np.allclose(recorded.readings_nT[0], expected_nT, atol=1e-6)
    t = recorded.time_s
    assert np.allclose(t[:10], a.T1 * 1e-3) and np.all(np.diff(t) > 0)
    assert t[10] - t[9] >= 0.6  # the restarted clock follows on after the gap the host saw
    assert np.allclose(np.diff(t[10:]), 0.02)
    roll = recorded.extra["roll_deg"]
    assert np.allclose(roll, np.concatenate([a.ROLL1, a.ROLL2]), atol=1e-4)  # float32 radians
    lat = recorded.extra["lat"]
    assert np.allclose(lat[:10], 52.2053) and np.all(np.isnan(lat[10:15])) and np.allclose(lat[15:], -33.9)
    stats = src.stats
    assert stats.n_reconnects == 1 and src.clock_resets == 1
    assert stats.n_bad == 1 and stats.reasons["cut packet"] == 1  # the loss itself is no bad packet
    assert "1 reconnect" in stats.summary() and "reopened after" in stats.last_disconnect
    return recorded


@pytest.mark.filterwarnings("ignore:.*outside the Earth's field range")
def test_mavlink_serial_port_reopened_after_an_autopilot_reboot_and_the_recording_goes_on(tmp_path):
    # a udev by-path name holds colons: still a serial port, not a UDP address
    board = BoardPort(tmp_path / "pci-0000:00:14.0-usb-0:1:1.0")
    path = tmp_path / "autopilot.csv"
    session = LiveSession(f"serial://{board.path}?mavlink&baud=57600&reconnect=20", path, flush_interval_s=0.05)
    src = session.source
    ap = Autopilot()
    try:
        board.write(ap.first_boot())
        assert wait_for(lambda: session.n_samples == 10)
        assert wait_for(lambda: src._conn.mav.buf_len() == ap.CUT_BYTES)  # the cut packet's start has been read
        board.reset(session)
        for part in ap.second_boot():
            board.write(part)
        assert wait_for(lambda: session.n_samples == 30)
        assert wait_for(lambda: session.n_recorded == 30)
    finally:
        session.stop()
        board.close()
    assert session.error is None
    recorded = check_two_boots(path, src)
    assert np.allclose(session.dataset().readings_nT[0], recorded.readings_nT[0])
    assert np.allclose(recorded.temperature_C, 21.5)
    assert src.location == pytest.approx((-33.9, 18.4, 12.0))


def test_mavlink_serial_port_that_does_not_come_back_raises_naming_the_device(tmp_path):
    port = tmp_path / "ttyAUTOPILOT"
    master, slave = os.openpty()
    port.symlink_to(os.ttyname(slave))
    src = open_source(f"serial://{port}?mavlink&reconnect=0.5")
    os.write(master, Autopilot().imu(1000, (100, 200, 300)))
    assert wait_for(lambda: len(src.read(timeout_s=0.2)) > 0, timeout_s=5)
    os.close(master)
    os.close(slave)
    port.unlink()
    start = time.monotonic()
    with pytest.raises(LiveError, match=f"{port}.*did not come back within 0.5 s") as err:
        while time.monotonic() - start < 10:
            src.read(timeout_s=0.2)
    assert "last try:" in str(err.value) and "\n" not in str(err.value)  # why the port does not open, one line
    assert time.monotonic() - start < 5
    assert src.stats.n_samples == 1 and src.stats.n_bad == 0  # the lost port was never counted as bad packets
    src.close()
    # reconnect=0: the first read after the loss fails
    master, slave = os.openpty()
    try:
        src = open_source(f"serial://{os.ttyname(slave)}?mavlink", reconnect=0)
        os.close(master)
        master = None
        start = time.monotonic()
        with pytest.raises(LiveError, match="the serial port .* failed"):
            src.read(timeout_s=0.5)
        assert time.monotonic() - start < 1.0
        src.close()
    finally:
        os.close(slave)
        if master is not None:
            os.close(master)


def n_recorded(path):
    """Samples on disk in a recording being written (0 before its first flush)."""
    try:
        return magcal.read_csv(path).n_samples
    except (OSError, magcal.MagcalError):
        return 0


def test_magcal_record_reconnect_applies_to_mavlink_on_a_serial_port(tmp_path, capsys):
    from magcal.cli import main

    port = tmp_path / "ttyACM-by-id"
    master, slave = os.openpty()
    port.symlink_to(os.ttyname(slave))
    out = tmp_path / "rec.csv"
    ap = Autopilot()
    result = {}

    def record():  # --reconnect 0.4: the recording ends soon after the port is lost, not 30 s later
        args = [f"serial://{port}?mavlink", str(out), "--reconnect", "0.4", "--seconds", "20", "--flush", "0.05"]
        result["rc"] = main(["record", *args])

    recorder = threading.Thread(target=record, daemon=True)
    recorder.start()
    k, end = 0, time.monotonic() + 15
    try:  # one RAW_IMU every 20 ms (the port flushes what came before it opened) until 5 are on disk
        while n_recorded(out) < 5 and time.monotonic() < end:
            os.write(master, ap.imu(1000 + 20 * k, (100 + k, 200, 300)))
            k += 1
            time.sleep(0.02)
    finally:
        os.close(master)
        os.close(slave)
        port.unlink()
    recorder.join(10)
    assert not recorder.is_alive() and result["rc"] != 0
    err = capsys.readouterr().err
    assert "did not come back within 0.4 s" in err and str(port) in err and "Traceback" not in err
    x_nT = magcal.read_csv(out).readings_nT[0, :, 0]
    assert len(x_nT) >= 5 and np.all(np.diff(x_nT) == 100.0)  # consecutive packets, 1 mgauss apart: none lost
