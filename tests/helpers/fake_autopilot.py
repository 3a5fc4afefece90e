"""A tiny fake autopilot for tests: a pymavlink thread on loopback holding a parameter table.

It sends a HEARTBEAT every 0.2 s to ``udpout:127.0.0.1:PORT`` (where the code under test listens, as
``udp://127.0.0.1:PORT?mavlink``), and answers PARAM_REQUEST_READ and PARAM_SET with PARAM_VALUE and
PARAM_REQUEST_LIST with the whole table. ``drop`` names parameters whose PARAM_SET it ignores (echoing the old
value), ``alter`` ones it stores changed (times 1.01): a vehicle the sender must report as failed. Integer
parameters (``int_params``) are held and sent as PX4 does (``bytewise``: the int32's bytes in the float) or as
ArduPilot does (the value).
"""

from __future__ import annotations

import socket
import struct
import threading
import time

import numpy as np


def free_udp_port() -> int:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


class FakeAutopilot:
    """Run with ``with FakeAutopilot(params, port) as fake:``; ``fake.params`` is the vehicle's table (float32)."""

    def __init__(self, params: dict, port: int, drop=(), alter=(), int_params=(), bytewise=False, lifetime_s=300.0):
        from pymavlink import mavutil

        self.params = {k: float(np.float32(v)) for k, v in params.items()}
        self.int_params = set(int_params)
        self.bytewise = bytewise
        self.drop, self.alter = set(drop), set(alter)
        self.sets: list[tuple[str, float]] = []  # every PARAM_SET received (name, decoded value)
        self.conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
        self._stop = threading.Event()
        self._deadline = time.monotonic() + lifetime_s
        self._thread = threading.Thread(target=self._run, daemon=True, name="fake-autopilot")

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join(5.0)
        self.conn.close()

    def _wire(self, name) -> tuple[float, int]:
        value = self.params[name]
        if name in self.int_params:
            if self.bytewise:
                return struct.unpack("<f", struct.pack("<i", int(value)))[0], 6
            return float(value), 2  # ArduPilot's INT8 (COMPASS_ORIENT)
        return value, 9

    def _send_value(self, name, index=0):
        wire, ptype = self._wire(name)
        self.conn.mav.param_value_send(name.encode(), wire, ptype, len(self.params), index)

    def _decode(self, name, wire) -> float:
        if name in self.int_params and self.bytewise:
            return float(struct.unpack("<i", struct.pack("<f", wire))[0])
        return float(np.float32(wire))

    def _run(self):
        next_beat = 0.0
        while not self._stop.is_set() and time.monotonic() < self._deadline:
            now = time.monotonic()
            if now >= next_beat:
                self.conn.mav.heartbeat_send(2, 3, 0, 0, 0)  # MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_ARDUPILOTMEGA
                next_beat = now + 0.2
            msg = self.conn.recv_match(blocking=True, timeout=0.05)
            if msg is None:
                continue
            kind = msg.get_type()
            if kind == "PARAM_REQUEST_READ":
                name = msg.param_id
                if name in self.params:
                    self._send_value(name)
            elif kind == "PARAM_REQUEST_LIST":
                for k, name in enumerate(self.params):
                    self._send_value(name, k)
            elif kind == "PARAM_SET":
                name = msg.param_id
                if name not in self.params:
                    continue
                value = self._decode(name, msg.param_value)
                self.sets.append((name, value))
                if name in self.alter:
                    value = value * 1.01
                if name not in self.drop:
                    self.params[name] = float(np.float32(value))
                self._send_value(name)
