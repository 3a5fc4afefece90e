"""A MAVLink source over TCP whose connection the other end closes (an ArduPilot SITL restarting, a telemetry bridge
dropped) and which comes back.

A fake autopilot is a TCP server on 127.0.0.1 (a free port) sending real MAVLink packets (pymavlink's encoder, the
:class:`Autopilot` of the serial test); it closes the connection and stops listening, then listens and accepts a new
connection after a pause, its boot clock restarted from 0. Every sample sent before and after is recorded, in
order, to the nT, the attitude and the position of one connection never merged onto the samples of the other. Every
wait is bounded; loopback only.
"""

from __future__ import annotations

import socket
import time

import pytest

from magcal.data.live import LiveError, LiveSession, open_source

pytest.importorskip("pymavlink")

from tests.data.test_lineformats import wait_for
from tests.data.test_live_mavlink_serial import Autopilot, check_two_boots


class AutopilotServer:
    """A fake autopilot's TCP server on 127.0.0.1: ``accept`` one connection, ``send`` to it, ``drop`` it and stop
    listening (the simulator exits), ``listen`` again on the same port (it restarts)."""

    def __init__(self):
        self.listener = self.conn = None
        self.port = 0
        self.listen()

    def listen(self):
        self.listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.listener.bind(("127.0.0.1", self.port))
        self.listener.listen(1)
        self.listener.settimeout(10.0)
        self.port = self.listener.getsockname()[1]

    def accept(self):
        self.conn, _ = self.listener.accept()

    def send(self, data: bytes):
        self.conn.sendall(data)

    def drop(self):
        for sock in (self.conn, self.listener):
            if sock is not None:
                sock.close()
        self.conn = self.listener = None

    close = drop


@pytest.mark.filterwarnings("ignore:.*outside the Earth's field range")
def test_mavlink_tcp_connection_closed_by_the_autopilot_is_reconnected_and_the_recording_goes_on(tmp_path):
    server = AutopilotServer()
    path = tmp_path / "sitl.csv"
    ap = Autopilot()
    session = None
    try:
        session = LiveSession(f"tcp://127.0.0.1:{server.port}?mavlink&reconnect=20", path, flush_interval_s=0.05)
        src = session.source
        server.accept()
        server.send(ap.first_boot())
        assert wait_for(lambda: session.n_samples == 10)
        assert wait_for(lambda: src._conn.mav.buf_len() == ap.CUT_BYTES)  # the cut packet's start has been read
        server.drop()
        assert wait_for(lambda: not src.connected)
        time.sleep(0.6)  # the source's tries meanwhile are refused and retried
        assert session.running and not src.connected and src.stats.n_reconnects == 0
        server.listen()
        server.accept()
        for part in ap.second_boot():
            server.send(part)
        assert wait_for(lambda: session.n_samples == 30)
        assert wait_for(lambda: session.n_recorded == 30)
    finally:
        if session is not None:
            session.stop()
        server.close()
    assert session.error is None
    check_two_boots(path, src)  # the simulator's second connection is its second boot


def test_mavlink_tcp_server_that_does_not_come_back_raises_naming_host_and_port():
    server = AutopilotServer()
    address = f"127.0.0.1:{server.port}"
    try:
        src = open_source(f"tcp://{address}?mavlink&reconnect=0.5")
        server.accept()
        server.send(Autopilot().imu(1000, (100, 200, 300)))
        assert wait_for(lambda: len(src.read(timeout_s=0.2)) > 0, timeout_s=5)
        server.drop()
        start = time.monotonic()
        with pytest.raises(LiveError, match=f"TCP connection to {address}.*did not come back within 0.5 s") as err:
            while time.monotonic() - start < 10:
                src.read(timeout_s=0.2)
        assert "last try:" in str(err.value) and "\n" not in str(err.value)  # why it does not connect, one line
        assert time.monotonic() - start < 5
        assert src.stats.n_samples == 1 and src.stats.n_bad == 0  # the close was never counted as bad packets
        src.close()
        # reconnect=0 (as magcal record --reconnect 0 passes it): the first read after the close fails
        server.listen()
        src = open_source(f"tcp://{address}?mavlink", reconnect=0)
        server.accept()
        server.drop()
        start = time.monotonic()
        with pytest.raises(LiveError, match=f"TCP connection to {address} failed \\(closed by the other end\\)"):
            src.read(timeout_s=0.5)
        assert time.monotonic() - start < 1.0
        src.close()
    finally:
        server.close()


def test_mavlink_tcp_with_nothing_listening_fails_at_once_naming_the_address():
    with socket.socket() as probe:  # a free port, nothing listening on it
        probe.bind(("127.0.0.1", 0))
        free = probe.getsockname()[1]
    start = time.monotonic()
    with pytest.raises(LiveError, match=f"cannot open the MAVLink connection tcp:127.0.0.1:{free}"):
        open_source(f"tcp://127.0.0.1:{free}?mavlink&reconnect=5")  # refused: one try, not pymavlink's retries
    assert time.monotonic() - start < 2.0
