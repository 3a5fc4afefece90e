"""MAVLink (pymavlink): the magnetometer fields of the IMU messages in nT with ``ATTITUDE`` and the position merged
onto each sample (:class:`MavlinkSource`), over a serial port or the network (``?mavlink`` on a ``serial``,
``udp`` or ``tcp`` URL); pymavlink's address for a URL and the options the openers read."""

from __future__ import annotations

import collections
import re
import socket
import time

import numpy as np

from magcal.data.live.source import (
    RECONNECT_DEFAULT_S,
    RECONNECT_MAX_INTERVAL_S,
    LiveError,
    LiveSource,
    _DeviceClock,
    _ReopensPort,
)

#: nT per unit of the magnetometer fields as MAVLink message definitions declare them.
MAVLINK_FIELD_UNITS_nT = {"mgauss": 100.0, "mG": 100.0, "gauss": 1.0e5, "G": 1.0e5, "uT": 1.0e3, "nT": 1.0}

#: MAVLink messages carrying a magnetometer, and the time field of each.
MAVLINK_MESSAGES = {
    "RAW_IMU": "time_usec",
    "SCALED_IMU": "time_boot_ms",
    "SCALED_IMU2": "time_boot_ms",
    "SCALED_IMU3": "time_boot_ms",
    "HIGHRES_IMU": "time_usec",
}

#: The channels a MAVLink source merges from ``ATTITUDE`` (deg, deg/s) and from the GPS messages (deg, deg, m).
MAVLINK_ATTITUDE_CHANNELS = ("roll_deg", "pitch_deg", "yaw_deg", "gyro_x_dps", "gyro_y_dps", "gyro_z_dps")
POSITION_CHANNELS = ("lat", "lon", "alt_m")
#: ``ATTITUDE`` messages kept for the merge; how long (s, host clock) beyond the bound a magnetometer sample waits
#: for its attitude; the oldest fix (s, host clock) a sample still carries.
MAVLINK_ATTITUDE_BUFFER = 512
MAVLINK_HOLD_S = 0.3
POSITION_MAX_AGE_S = 10.0

#: pymavlink connection strings that are not a serial device (any other device string is one).
_MAVLINK_NETWORK = re.compile(r"(tcp|tcpin|udp|udpin|udpout|udpbcast|mcast|uds|unix|ws|wss|wsserver|csv):", re.I)

#: HIGHRES_IMU ``fields_updated`` bits of xmag, ymag, zmag and of the temperature.
_HIGHRES_MAG_BITS = 0b111 << 6
_HIGHRES_TEMP_BIT = 1 << 12


class MavlinkSource(_ReopensPort, LiveSource):
    """Magnetometer fields of MAVLink IMU messages (pymavlink), converted to nT, with the vehicle's attitude and
    position merged onto them.

    Parameters
    ----------
    url : str
    device : str
        pymavlink connection string (``udpin:127.0.0.1:14550``, ``tcp:host:port``), or else a serial device's path
        (``/dev/ttyACM0``, ``/dev/serial/by-path/pci-0000:00:14.0-usb-0:1:1.0``, ``COM3``), always opened as a
        serial port.
    message : str, optional
        Read only this message (``RAW_IMU``, ``SCALED_IMU``, ``SCALED_IMU2``, ``SCALED_IMU3``, ``HIGHRES_IMU``);
        default the first of them that arrives.
    baud : int
        For a serial device.
    raw_lsb_nT : float
        nT per unit of ``RAW_IMU``'s magnetometer fields when the message definition declares no unit (older
        dialects; ArduPilot sends milligauss: 100).
    attitude_max_dt_s : float
        Largest time (s) between a magnetometer sample and the ``ATTITUDE`` message merged onto it.
    reconnect_s : float
        On a serial device or a TCP connection (``tcp:host:port``): longest total wait for the port to come back
        after it is lost, or the connection after the other end closed it (s); 0 for none. UDP needs none: it is
        connectionless, a sender that restarts just sends again.
    connect_timeout_s : float
        Longest wait for a TCP connection to be accepted (s), when opening and at each try to reconnect.

    Notes
    -----
    Times are the vehicle's (``time_boot_ms``, ``time_usec``); when they jump back by more than 1 s (a reboot),
    or at all in the first message after the serial port was reopened, later samples are shifted to follow on by the
    time the host saw pass (:attr:`clock_resets` counts it), so a recording goes on.

    A serial device that disappears (an autopilot reset, a USB re-enumeration) is opened again as
    :class:`SerialSource` does: under the same path, at growing intervals, for at most ``reconnect_s`` in all
    (``stats.n_reconnects``, ``stats.last_disconnect``, :attr:`connected`), then :class:`LiveError`; the samples
    read before the loss are kept, and a packet cut by it is counted as bad (``cut packet``). A TCP connection that
    the other end closes (an ArduPilot SITL restarting, a telemetry bridge dropped) is connected again the same way,
    to the same ``host:port``, one try at a time (never pymavlink's own blocking retries); beyond ``reconnect_s``
    the :class:`LiveError` names ``host:port``, the wait and why the last try failed.

    ``ATTITUDE`` (roll, pitch, yaw and the body rates) is merged onto each magnetometer sample from the message
    nearest in vehicle time, within ``attitude_max_dt_s`` (NaN beyond), as the channels ``roll_deg, pitch_deg,
    yaw_deg`` (deg) and ``gyro_x_dps, gyro_y_dps, gyro_z_dps`` (deg/s); a sample is held until the attitude after
    it has arrived, the vehicle's time has passed it by more than the bound, or the bound plus
    :data:`MAVLINK_HOLD_S` has passed on the host's clock. ``GPS_RAW_INT`` (with a 2D or 3D fix) and
    ``GLOBAL_POSITION_INT`` (not 0, 0) give ``lat, lon`` (deg) and ``alt_m`` (m: above the ellipsoid where
    ``GPS_RAW_INT`` sends ``alt_ellipsoid``, else above mean sea level, which differs by the geoid's height, tens of
    m, a few nT of IGRF): every sample carries the latest fix received before it, when it is at most
    :data:`POSITION_MAX_AGE_S` old (NaN otherwise); :attr:`location` is the latest fix. Whether the samples carry
    the attitude and the position is decided when the first one is released: by whether an ``ATTITUDE`` or a GPS
    message has arrived by then. The two boots of a vehicle that rebooted are never mixed: a sample gets an
    ``ATTITUDE`` of its own boot only, and a position received since the serial port or the TCP connection was
    last (re)opened.
    """

    def __init__(
        self,
        url,
        device,
        message=None,
        baud=115200,
        raw_lsb_nT=100.0,
        attitude_max_dt_s=0.2,
        reconnect_s=RECONNECT_DEFAULT_S,
        connect_timeout_s=5.0,
    ):
        super().__init__(url)
        try:
            from pymavlink import mavutil
        except ImportError:
            raise LiveError(f'{url}: MAVLink needs pymavlink: pip install "magcal-workbench[instruments]"') from None
        self._mavutil = mavutil
        #: Whether the device is a serial port (reopened when it disappears), not a network connection.
        self.serial = not _MAVLINK_NETWORK.match(device)
        if self.serial:
            try:
                import serial  # noqa: F401 - pymavlink opens the port with it
            except ImportError:
                raise LiveError(
                    f'{url}: serial ports need pyserial: pip install "magcal-workbench[instruments]"'
                ) from None
        #: Whether the device is a TCP connection (``tcp:host:port``), connected again when the other end closes it.
        self.tcp = device.lower().startswith("tcp:")
        self.baud = baud
        self.connect_timeout_s = float(connect_timeout_s)
        # pyserial's SerialException is an OSError, and so are socket errors
        if self.tcp:
            what, hint = f"the TCP connection to {device[4:]}", "is the autopilot or simulator running and listening?"
        else:
            what, hint = f"the serial port {device}", "is the device connected?"
        self._init_reopen(device, reconnect_s if self.serial or self.tcp else 0.0, (OSError, ValueError), what, hint)
        self._link = 0  # losses of the port or connection: a fix is merged only onto samples read before the next loss
        if message is not None and message not in MAVLINK_MESSAGES:
            raise LiveError(f"{url}: message {message!r}: use one of {', '.join(MAVLINK_MESSAGES)}")
        self.message = message
        self.raw_lsb_nT = float(raw_lsb_nT)
        self.attitude_max_dt_s = float(attitude_max_dt_s)
        self.n_sensors = 1
        self._clock = _DeviceClock()  # the magnetometer's vehicle time; its resets number the boots
        self._att_clock = _DeviceClock()  # ATTITUDE's, for its boots only
        #: ATTITUDE messages as (boot, vehicle time s, roll, pitch, yaw deg, p, q, r deg/s), oldest first
        self._attitudes = collections.deque(maxlen=MAVLINK_ATTITUDE_BUFFER)
        #: magnetometer samples waiting for their attitude: (boot, raw t, sample, host time, position)
        self._pending = collections.deque()
        self._mag_latest = None  # (boot, raw t) of the newest magnetometer sample
        self._gps_seen = False
        self._position = None  # (lat, lon, alt_m, host time, link) of the latest fix
        self._with_attitude = self._with_position = None  # decided when the first sample is released
        try:
            self._open_port()
        except Exception as exc:  # pymavlink raises many kinds for a device that does not open
            if self.serial:
                raise LiveError(
                    f"{url}: cannot open the serial port {device} ({exc}); check the device path and that no other "
                    "program holds it"
                ) from None
            raise LiveError(f"{url}: cannot open the MAVLink connection {device} ({exc})") from None

    def _open_port(self):
        if self.serial:  # never pymavlink's guess from the name (a path with colons is no UDP address)
            self._conn = self._mavutil.mavserial(self.device, baud=self.baud, source_system=255, autoreconnect=False)
        elif self.tcp:
            # a try to reconnect waits at most as long as the interval between two tries
            timeout_s = (
                self.connect_timeout_s if self.connected else min(self.connect_timeout_s, RECONNECT_MAX_INTERVAL_S)
            )
            self._conn = _mavlink_tcp(self._mavutil, self.device[4:], timeout_s)
        else:
            self._conn = self._mavutil.mavlink_connection(
                self.device, baud=self.baud, source_system=255, autoreconnect=False
            )

    def _close_port(self):
        self._conn.close()

    def _port_lost(self):
        if self._conn.mav.buf_len():  # a packet cut by the loss: the reopened port's parser starts afresh
            self.stats.bad("cut packet: the port was lost in the middle of it")
        self._link += 1  # the fix received so far is not merged onto what comes after the loss

    def _port_back(self):
        self._clock.restart_possible = True  # the vehicle may have rebooted: its clocks start again from 0
        self._att_clock.restart_possible = True

    @property
    def clock_resets(self) -> int:
        """Vehicle reboots seen: its clock went back by more than 1 s, or at all after the port was reopened."""
        return self._clock.resets

    @property
    def location(self):
        """The vehicle's latest position ``(lat_deg, lon_deg, alt_m)`` from ``GPS_RAW_INT`` or
        ``GLOBAL_POSITION_INT``, or None before a fix (for the reference field: :mod:`magcal.checks.reference`)."""
        return None if self._position is None else self._position[:3]

    def _factor(self, msg, name):
        units = getattr(msg, "fieldunits_by_name", {}) or {}
        unit = units.get(name)
        if unit is None:
            return self.raw_lsb_nT
        if unit not in MAVLINK_FIELD_UNITS_nT:
            raise ValueError(f"unit: {msg.get_type()}.{name} is in {unit!r}, which magcal does not convert")
        return MAVLINK_FIELD_UNITS_nT[unit]

    def _sample(self, msg):
        kind = msg.get_type()
        if self.message is None:
            self.message = kind
        if kind != self.message:
            return None
        if kind == "HIGHRES_IMU" and not (int(msg.fields_updated) & _HIGHRES_MAG_BITS):
            return None  # no new magnetometer sample in this message
        factor = self._factor(msg, "xmag")
        readings = np.array([[msg.xmag, msg.ymag, msg.zmag]], dtype=float) * factor
        time_field = MAVLINK_MESSAGES[kind]
        raw = float(getattr(msg, time_field)) * (1e-3 if time_field == "time_boot_ms" else 1e-6)
        t = self._clock.follow(raw)
        boot = self._clock.resets
        temp = None
        if self.has_temperature is not False and hasattr(msg, "temperature"):
            units = (getattr(msg, "fieldunits_by_name", {}) or {}).get("temperature")
            value = float(msg.temperature)
            if units == "cdegC":
                temp = None if value == 0 else value * 0.01  # 0: the IMU sends no temperature
            elif kind == "HIGHRES_IMU":
                temp = value if int(msg.fields_updated) & _HIGHRES_TEMP_BIT or self.has_temperature else None
            else:
                temp = value
        self._mag_latest = (boot, raw)
        return boot, raw, (t, readings, temp)

    def _attitude(self, msg):
        raw = float(msg.time_boot_ms) * 1e-3
        self._att_clock.follow(raw)
        angles = np.degrees([msg.roll, msg.pitch, msg.yaw, msg.rollspeed, msg.pitchspeed, msg.yawspeed])
        if not np.all(np.isfinite(angles)):
            raise ValueError("bad value: ATTITUDE holds a value that is not a number")
        angles[2] = (angles[2] + 180.0) % 360.0 - 180.0
        self._attitudes.append((self._att_clock.resets, raw, *angles.tolist()))

    def _gps(self, msg):
        self._gps_seen = True
        kind = msg.get_type()
        if kind == "GPS_RAW_INT":
            if int(msg.fix_type) < 2:  # no fix
                return
            alt_mm = getattr(msg, "alt_ellipsoid", 0) or msg.alt
        else:
            alt_mm = msg.alt
        lat, lon = msg.lat * 1e-7, msg.lon * 1e-7
        if (lat == 0 and lon == 0) or not (-90 <= lat <= 90 and -180 <= lon <= 180):
            return  # no position yet (ArduPilot sends 0, 0), or not one
        self._position = (float(lat), float(lon), float(alt_mm) * 1e-3, time.monotonic(), self._link)

    def _nearest_attitude(self, boot, raw):
        best = None
        for a in self._attitudes:
            if a[0] == boot and (best is None or abs(a[1] - raw) < abs(best[1] - raw)):
                best = a
        if best is None or abs(best[1] - raw) > self.attitude_max_dt_s:
            return [np.nan] * 6
        return list(best[2:])

    def _release(self, flush=False):
        """The pending samples whose attitude is settled, with their channels, oldest first."""
        out = []
        now = time.monotonic()
        while self._pending:
            boot, raw, sample, host, position = self._pending[0]
            if self._with_attitude is False:
                ready = True
            else:  # the attitude after the sample has arrived
                last = self._attitudes[-1] if self._attitudes else None
                ready = last is not None and (last[0], last[1]) >= (boot, raw)
            ready = (
                ready
                or flush
                or (self._mag_latest is not None and self._mag_latest > (boot, raw + self.attitude_max_dt_s))
                or now - host > self.attitude_max_dt_s + MAVLINK_HOLD_S
            )
            if not ready:
                break
            self._pending.popleft()
            if self._with_attitude is None:  # the first sample decides the stream's channels
                self._with_attitude = bool(self._attitudes)
                self._with_position = self._gps_seen
            channels = {}
            if self._with_attitude:
                channels.update(zip(MAVLINK_ATTITUDE_CHANNELS, self._nearest_attitude(boot, raw)))
            if self._with_position:
                fresh = position is not None and host - position[3] <= POSITION_MAX_AGE_S
                channels.update(zip(POSITION_CHANNELS, position[:3] if fresh else [np.nan] * 3))
            out.append((*sample, channels))
        return out

    def _held(self):
        return self._release(flush=True)

    def _poll(self, deadline, max_samples):
        samples = []
        while len(samples) < max_samples:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                break
            wait = min(remaining, 0.05 if self._pending else 0.2)
            if not self.connected:  # a lost serial port or TCP connection: nothing to read until it is back
                self._reopen(wait)
                msg = None
            else:
                try:
                    msg = self._conn.recv_match(blocking=True, timeout=wait)
                except Exception as exc:
                    if (self.serial or self.tcp) and isinstance(exc, OSError):  # the port failed, the connection closed
                        self._lose(exc)
                        msg = None
                    else:  # a damaged packet pymavlink cannot decode
                        self.stats.bad(f"bad packet: {exc}")
                        continue
            if msg is not None:
                self._handle(msg)
            released = self._release()
            if released:
                if not samples:  # gather what follows within 50 ms, then return: low latency for viewers
                    deadline = min(deadline, time.monotonic() + 0.05)
                samples += released
            elif msg is None and samples:
                break
        return samples

    def _handle(self, msg):
        kind = msg.get_type()
        if kind == "BAD_DATA":
            self.stats.bad("bad packet: not MAVLink or a failed checksum")
            return
        try:
            if kind == "ATTITUDE":
                if self._with_attitude is False:
                    self.stats.skip("ATTITUDE: began after the first sample, so not in this stream's channels")
                else:
                    self._attitude(msg)
            elif kind in ("GPS_RAW_INT", "GLOBAL_POSITION_INT"):
                self._gps(msg)
            elif kind in MAVLINK_MESSAGES:
                found = self._sample(msg)
                if found is not None:
                    boot, raw, sample = found
                    fix = self._position if self._position is not None and self._position[4] == self._link else None
                    self._pending.append((boot, raw, sample, time.monotonic(), fix))
        except (ValueError, AttributeError, TypeError) as exc:
            self.stats.bad(str(exc), kind)

    def close(self):
        super().close()
        try:
            self._conn.close()
        except Exception:  # closing a dead connection: nothing left to release
            pass


def _mavlink_tcp(mavutil, address, timeout_s):
    """A pymavlink TCP connection to ``host:port``: one try to connect, within ``timeout_s`` (pymavlink's own tries
    sleep 1 s between them and print), and a close by the other end raised as :class:`ConnectionResetError`
    (pymavlink prints ``EOF on TCP socket`` and reads nothing, again and again, when it does not reconnect itself).
    """

    class _Tcp(mavutil.mavtcp):
        def do_connect(self):
            self.port = socket.create_connection(self.destination_addr, timeout=timeout_s)
            self.port.setblocking(False)
            mavutil.set_close_on_exec(self.port.fileno())
            self.port.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

        def handle_eof(self):
            raise ConnectionResetError("closed by the other end")

        def handle_disconnect(self):  # a reset: recv raises its error next
            pass

    return _Tcp(address, source_system=255)


def mavlink_address(url: str, scheme: str, host: str, port: int) -> str:
    """pymavlink's connection string for a ``udp://HOST:PORT`` (listened on) or ``tcp://HOST:PORT`` URL.

    Raises
    ------
    LiveError
        For an IPv6 address: pymavlink reads ``host:port`` by its one colon and opens IPv4 sockets only.
    """
    if ":" in host:
        raise LiveError(
            f"{url}: MAVLink over IPv6 ({host}) is not supported (pymavlink takes IPv4 addresses and host names); "
            f"give the vehicle's IPv4 address or a host name, e.g. {scheme}://127.0.0.1:{port}?mavlink"
        )
    return f"udpin:{host}:{port}" if scheme == "udp" else f"tcp:{host}:{port}"


#: The URL options a MAVLink source reads (on a ``serial``, ``udp`` or ``tcp`` URL).
MAVLINK_OPTIONS = ("mavlink", "format", "message", "raw_lsb_nT", "attitude_max_dt")


def attitude_max_dt(url) -> float:
    """``attitude_max_dt`` of a source URL (:class:`~magcal.data.live.registry.SourceURL`), s: default 0.2."""
    return url.number("attitude_max_dt", 0.2, float, (0.001, 10.0))


def raw_lsb(url) -> float:
    """``raw_lsb_nT`` of a source URL, nT per unit of ``RAW_IMU``'s fields without a declared unit: default 100."""
    return url.number("raw_lsb_nT", 100.0, float, (1e-6, 1e9))
