"""The serial-port source: text lines from a serial port (pyserial), opened again when it disappears, or MAVLink
over the port (``serial:///dev/ttyUSB0?baud=115200&columns=x,y,z``, ``serial:///dev/ttyACM0?mavlink``); the
ports found on this machine. Registered as the live source ``serial``."""

from __future__ import annotations

from magcal.data.live.lines import LineSource
from magcal.data.live.mavlink import MAVLINK_OPTIONS, MavlinkSource, attitude_max_dt, raw_lsb
from magcal.data.live.registry import LINE_OPTIONS, SourceKind, SourceURL, register_source
from magcal.data.live.source import RECONNECT_DEFAULT_S, RECONNECT_RANGE_S, LiveError, _ReopensPort

#: Serial speeds accepted (bit/s).
BAUD_RANGE = (50, 10_000_000)


class SerialSource(_ReopensPort, LineSource):
    """Text lines from a serial port (pyserial), reopened when it disappears.

    When the port fails (a board reset, a USB re-enumeration, a cable pulled), the source closes it and tries to
    open the same path again, after 0.1 s, then at doubling intervals up to :data:`RECONNECT_MAX_INTERVAL_S`, for
    at most ``reconnect_s`` in all; reads meanwhile return no samples (within their own timeout), so a
    :class:`LiveSession` goes on recording across the gap. Each reopening is counted in
    ``stats.n_reconnects``; the samples read before the loss are kept, a line cut by it is counted as bad, and
    whatever cannot be read before the first sample after it (the board's boot banner) is skipped. When the port
    has not come back within ``reconnect_s`` (or with ``reconnect_s=0``) the read raises :class:`LiveError`.

    Parameters
    ----------
    url : str
    port : str
        The device path (a udev name such as ``/dev/serial/by-id/...`` survives a re-enumeration that renames
        ``/dev/ttyACM0`` to ``/dev/ttyACM1``).
    baud : int
    parser : LineParser
    reconnect_s : float
        Longest total wait for the port to come back after it is lost (s); 0 for none.
    """

    def __init__(self, url, port, baud, parser, reconnect_s=RECONNECT_DEFAULT_S):
        super().__init__(url, parser)
        try:
            import serial
        except ImportError:
            raise LiveError(f'{url}: serial ports need pyserial: pip install "magcal-workbench[instruments]"') from None
        self._serial = serial
        self.baud = baud
        self._init_reopen(port, reconnect_s, (serial.SerialException, OSError, ValueError))
        try:
            self._open_port()
        except (serial.SerialException, OSError, ValueError) as exc:
            raise LiveError(
                f"{url}: cannot open the serial port {port} ({exc}); check the device path and that no "
                "other program holds it"
            ) from None

    def _open_port(self):
        self._port = self._serial.Serial(self.device, baudrate=self.baud, timeout=0.1)

    def _close_port(self):
        self._port.close()

    def _port_lost(self):
        if self._buffer:  # a line cut by the loss: never joined to what comes after
            self._line_no += 1
            self.stats.bad("cut line: the port was lost in the middle of it", f"line {self._line_no}")
            self._buffer = b""
        self._overlong = None

    def _port_back(self):
        self._seen_data = False  # the board's banner comes first
        self._clock.restart_possible = True  # and its clock may start again from 0

    def _receive(self, timeout_s):
        if not self.connected:
            self._reopen(timeout_s)
            return b""
        try:
            self._port.timeout = max(timeout_s, 0.001)
            return self._port.read(max(1, self._port.in_waiting))
        except (OSError, TypeError) as exc:  # TypeError: pyserial reading a closed descriptor
            self._lose(exc)
            return b""

    def close(self):
        super().close()
        try:
            self._port.close()
        except Exception:  # a port that has gone: nothing left to release
            pass


def serial_ports() -> list[str]:
    """The serial ports found on this machine (pyserial's ``list_ports``), sorted; none without pyserial."""
    try:
        from serial.tools import list_ports
    except ImportError:
        return []
    try:
        return sorted({p.device for p in list_ports.comports() if p.device})
    except Exception:  # a platform whose enumeration fails offers no port
        return []


def open_serial(url: SourceURL):
    """A ``serial://DEVICE`` URL's source: text lines (:class:`SerialSource`), or MAVLink with ``?mavlink``."""
    attitude_dt = attitude_max_dt(url)
    device = url.target
    baud = url.number("baud", 115200, int, BAUD_RANGE)
    reconnect_s = url.number("reconnect", RECONNECT_DEFAULT_S, float, RECONNECT_RANGE_S)
    if url.mavlink:
        return MavlinkSource(
            url.url, device, url.params.get("message"), baud, raw_lsb(url), attitude_dt, reconnect_s=reconnect_s
        )
    return SerialSource(url.url, device, baud, url.line_parser(), reconnect_s=reconnect_s)


SERIAL = register_source(
    SourceKind(
        name="serial",
        schemes=("serial",),
        description="text lines from a serial port (pyserial), reopened when it disappears; MAVLink with ?mavlink",
        forms=("serial://DEVICE",),
        example="serial:///dev/ttyUSB0?baud=115200&columns=x,y,z",
        options=("baud", "reconnect", *LINE_OPTIONS, *MAVLINK_OPTIONS),
        opener=open_serial,
    )
)
