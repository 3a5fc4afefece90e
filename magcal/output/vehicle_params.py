"""Send a calibration's parameters to a vehicle over MAVLink, read every one back, keep the old values.

``magcal send`` and the workbench's *Send to vehicle* call :func:`send_parameters`, which

1. opens the MAVLink connection (pymavlink) and waits for the vehicle's ``HEARTBEAT`` (bounded);
2. reads the current value of every parameter to write (``PARAM_REQUEST_READ`` -> ``PARAM_VALUE``); one the
   vehicle does not answer for stops everything before anything is written (a calibration is written whole or
   not at all);
3. asks ``confirm(rows)`` with the old -> new table (the command line's prompt, the page's second click) and
   writes the old values to a backup parameter file, atomically, before the first ``PARAM_SET``;
4. sends ``PARAM_SET`` for each parameter and waits for the vehicle's ``PARAM_VALUE`` echo, retrying a bounded
   number of times when none comes or it holds another value;
5. reads every parameter back once more (``PARAM_REQUEST_READ``) and reports, per parameter, old, new, read
   back and whether the read-back equals the value sent as the vehicle stores it (a float32).

The values sent are those of the parameter file ``magcal export`` writes (:func:`values_to_send` parses its text),
so the vehicle ends up holding exactly what the file says. Restoring is sending the backup file
(``magcal send BACKUP.parm --url ...``).

Encoding: ``PARAM_SET`` carries a float. ArduPilot converts it to the parameter's type (a C cast); PX4 copies the
bytes of an integer parameter into the float (``MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE``), so an integer
parameter (``CAL_MAGn_ROT``) is sent and read as its bytes there.

Connection strings: magcal's live-source URLs (``udp://127.0.0.1:14550?mavlink``: listening there;
``tcp://127.0.0.1:5760``: connecting; ``serial:///dev/ttyACM0?baud=115200``) or pymavlink's own (``udpin:``,
``udpout:``, ``tcp:``, a serial device). A path to a regular file is refused (pymavlink would run an executable
one as a program, or read a log).
"""

from __future__ import annotations

import datetime as _dt
import math
import os
import struct
import time
import urllib.parse
from dataclasses import dataclass, field

import numpy as np

from magcal.core.errors import MagcalError
from magcal.data.io import atomic_write
from magcal.data.live import mavlink_address
from magcal.output.export import parse_parameter_file

#: Firmwares whose parameters are sent, and the prefixes of the names each takes (ArduPilot's custom rotations,
#: ``CUST_ROT*``, hold a compass's mounting off the right angles).
FIRMWARE_PREFIXES = {"ardupilot": ("COMPASS_", "CUST_ROT"), "px4": ("CAL_MAG",)}
#: MAV_PARAM_TYPE numbers of the integer types (UINT8 .. INT64) and of REAL32.
INTEGER_TYPES = {1: "B", 2: "b", 3: "H", 4: "h", 5: "I", 6: "i"}
REAL32 = 9
#: Longest wait for the vehicle's heartbeat, s.
HEARTBEAT_TIMEOUT_S = 5.0
#: Wait for one answer (a PARAM_VALUE) before asking again, s.
ANSWER_TIMEOUT_S = 1.0
#: Times a read or a write is tried before the parameter counts as failed.
RETRIES = 3
#: Longest parameter name MAVLink carries.
PARAM_ID_CHARS = 16


@dataclass
class ParamResult:
    """One parameter's fate.

    Attributes
    ----------
    name : str
    new : float
        The value to write (as the parameter file holds it).
    old : float or None
        The vehicle's value before (None: not read).
    sent : bool
        Whether a PARAM_SET went out.
    read_back : float or None
        The vehicle's value read after writing (None: no answer).
    attempts : int
        PARAM_SET messages sent.
    ok : bool
        ``read_back`` equals ``new`` as a float32 (the vehicle's storage).
    reason : str
        Why not, when not ok.
    """

    name: str
    new: float
    old: float | None = None
    sent: bool = False
    read_back: float | None = None
    attempts: int = 0
    ok: bool = False
    reason: str = ""


@dataclass
class SendReport:
    """What :func:`send_parameters` did: per parameter, old -> new and the read-back; the backup's path."""

    target: str
    firmware: str
    results: list = field(default_factory=list)
    backup_path: str | None = None
    sent: bool = False
    declined: bool = False

    @property
    def ok(self) -> bool:
        """Every parameter was written and read back equal."""
        return self.sent and bool(self.results) and all(r.ok for r in self.results)

    @property
    def failed(self) -> list:
        return [r for r in self.results if not r.ok]

    def rows(self) -> list[tuple]:
        """``(name, old, new, read back, status)`` text per parameter, for a table."""
        out = []
        for r in self.results:
            status = "ok" if r.ok else (r.reason or "not sent") if self.sent else "to send"
            out.append((r.name, _text(r.old), _text(r.new), _text(r.read_back), status))
        return out

    def text(self) -> str:
        """The report as lines of text (the command line's output)."""
        lines = [f"{'parameter':<17} {'old':>14} {'new':>14} {'read back':>14}  status"]
        lines += [f"{n:<17} {o:>14} {w:>14} {b:>14}  {s}" for n, o, w, b, s in self.rows()]
        if self.backup_path:
            lines.append(f"old values saved to {self.backup_path} (restore: magcal send {self.backup_path} --url ...)")
        if self.sent:
            lines.append(
                f"{len(self.results) - len(self.failed)} of {len(self.results)} parameter(s) written and read back "
                "equal" + ("" if self.ok else f"; FAILED: {', '.join(r.name for r in self.failed)}")
            )
        return "\n".join(lines)


def _text(v) -> str:
    return "-" if v is None else f"{float(v):.9g}"


def equal_float32(a, b) -> bool:
    """Whether two values are the same float32 (what a vehicle stores a parameter as)."""
    if a is None or b is None:
        return False
    return bool(np.float32(a) == np.float32(b))


def read_parameter_text(text: str) -> dict:
    """``name -> value`` of a parameter file's text (:func:`magcal.output.export.parse_parameter_file`), with a
    clear :class:`MagcalError` for a value that is not a number."""
    try:
        return parse_parameter_file(text)
    except ValueError as exc:
        raise MagcalError(f"the parameter file holds a value that is not a number ({exc})") from None


def values_to_send(text: str, firmware: str) -> dict:
    """The parameters of a parameter file's text (ArduPilot ``.parm`` or PX4 ``.params``) for ``firmware``,
    in the file's order. Raises :class:`MagcalError` for an empty file or a name of another firmware."""
    if firmware not in FIRMWARE_PREFIXES:
        raise MagcalError(f"firmware {firmware!r}: use one of {', '.join(FIRMWARE_PREFIXES)}")
    values = read_parameter_text(text)
    if not values:
        raise MagcalError("the parameter file holds no parameter")
    prefixes = FIRMWARE_PREFIXES[firmware]
    wrong = [n for n in values if not n.startswith(prefixes)]
    if wrong:
        raise MagcalError(
            f"{', '.join(wrong[:4])}: not {firmware} compass parameters ({', '.join(p + '*' for p in prefixes)}); "
            "only those are sent to a vehicle"
        )
    long = [n for n in values if len(n) > PARAM_ID_CHARS]
    if long:
        raise MagcalError(f"{', '.join(long)}: longer than MAVLink's {PARAM_ID_CHARS} characters")
    bad = [n for n, v in values.items() if not math.isfinite(v)]
    if bad:
        raise MagcalError(f"{', '.join(bad)}: not a finite number; nothing is sent")
    return values


def firmware_of(values) -> str:
    """The firmware whose names a parameter set holds (``COMPASS_*``: ardupilot, ``CAL_MAG*``: px4)."""
    for fw, prefixes in FIRMWARE_PREFIXES.items():
        if values and all(str(n).startswith(prefixes) for n in values):
            return fw
    raise MagcalError("the parameters are neither ArduPilot's COMPASS_* nor PX4's CAL_MAG*: nothing to send")


def mavlink_device(url: str) -> tuple[str, int]:
    """pymavlink's connection string and baud for a magcal source URL or a pymavlink string (see the module)."""
    url = str(url).strip()
    if not url:
        raise MagcalError("give the vehicle's MAVLink connection (e.g. udp://127.0.0.1:14550?mavlink)")
    baud = 115200
    parsed = urllib.parse.urlsplit(url)
    scheme = parsed.scheme.lower() if "://" in url else ""
    if scheme in ("udp", "tcp"):
        try:
            host, port = parsed.hostname, parsed.port
        except ValueError as exc:
            raise MagcalError(f"{url}: {exc}; give {scheme}://HOST:PORT") from None
        if not host or not port:
            raise MagcalError(f"{url}: give the address as {scheme}://HOST:PORT")
        device = mavlink_address(url, scheme, host, port)
    elif scheme == "serial":
        device = urllib.parse.unquote(parsed.netloc + parsed.path)
        params = urllib.parse.parse_qs(parsed.query)
        if "baud" in params:
            try:
                baud = int(params["baud"][-1])
            except ValueError:
                raise MagcalError(f"{url}: baud={params['baud'][-1][:20]!r} is not a number") from None
    elif scheme:
        raise MagcalError(f"{url}: use udp://HOST:PORT, tcp://HOST:PORT or serial://DEVICE for a vehicle")
    else:
        device = url
        if "," in device:  # pymavlink's DEVICE,BAUD
            device, _, b = device.rpartition(",")
            try:
                baud = int(b)
            except ValueError:
                raise MagcalError(f"{url}: the baud after the comma is not a number") from None
    if not device.startswith(("udpin:", "udpout:", "udp:", "tcp:", "tcpin:")) and os.path.isfile(device):
        raise MagcalError(f"{device}: a file, not a serial port or a network address")
    return device, baud


class ParamLink:
    """A MAVLink connection to one vehicle for its parameters (bounded waits everywhere).

    Parameters
    ----------
    url : str
        The connection (:func:`mavlink_device`).
    firmware : {'ardupilot', 'px4'}
        How integer parameters are encoded (ArduPilot: the value; PX4: its bytes).
    heartbeat_timeout_s, answer_timeout_s : float
        Longest waits for the vehicle's heartbeat and for one answer.
    """

    def __init__(self, url, firmware, heartbeat_timeout_s=HEARTBEAT_TIMEOUT_S, answer_timeout_s=ANSWER_TIMEOUT_S):
        try:
            from pymavlink import mavutil
        except ImportError:
            raise MagcalError('sending to a vehicle needs pymavlink: pip install "magcal[instruments]"') from None
        self.url = str(url)
        self.firmware = firmware
        self.answer_timeout_s = float(answer_timeout_s)
        self.types: dict[str, int] = {}
        device, baud = mavlink_device(url)
        try:
            self.conn = mavutil.mavlink_connection(device, baud=baud, source_system=255, autoreconnect=False)
        except Exception as exc:  # pymavlink raises many kinds for a device that does not open
            raise MagcalError(f"{self.url}: cannot open the MAVLink connection ({exc})") from None
        try:
            self._wait_heartbeat(float(heartbeat_timeout_s))
        except BaseException:
            self.close()
            raise

    def _wait_heartbeat(self, timeout_s):
        deadline = time.monotonic() + timeout_s
        gcs = 6  # MAV_TYPE_GCS: another ground station's heartbeat is not the vehicle
        while time.monotonic() < deadline:
            msg = self._recv("HEARTBEAT", deadline)
            if msg is not None and int(getattr(msg, "type", 0)) != gcs:
                self.target_system = msg.get_srcSystem()
                self.target_component = msg.get_srcComponent()
                return
        raise MagcalError(
            f"{self.url}: no vehicle heartbeat within {timeout_s:g} s; check the connection (is the vehicle sending "
            "to this address, and no other program holding it, e.g. a live session?)"
        )

    def _recv(self, kind, deadline):
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            return None
        try:
            return self.conn.recv_match(type=kind, blocking=True, timeout=min(remaining, 0.2))
        except Exception:  # a damaged packet: skip it
            return None

    def close(self):
        try:
            self.conn.close()
        except Exception:  # closing a dead connection: nothing left to release
            pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # --- values as the vehicle encodes them --------------------------------------------------------------
    def _decode(self, msg) -> float:
        value, ptype = float(msg.param_value), int(msg.param_type)
        if self.firmware == "px4" and ptype in INTEGER_TYPES:
            return float(struct.unpack("<i", struct.pack("<f", value))[0])
        return value

    def _encode(self, name, value) -> tuple[float, int]:
        ptype = self.types.get(name, REAL32)
        if self.firmware == "px4" and ptype in INTEGER_TYPES:
            return struct.unpack("<f", struct.pack("<i", int(round(value))))[0], ptype
        return float(value), ptype

    def _await_value(self, name, deadline):
        """The next PARAM_VALUE for ``name`` before ``deadline`` (decoded), or None."""
        while time.monotonic() < deadline:
            msg = self._recv("PARAM_VALUE", deadline)
            if msg is None:
                continue
            pid = msg.param_id if isinstance(msg.param_id, str) else msg.param_id.decode("ascii", "replace")
            if pid.rstrip("\x00") == name:
                self.types[name] = int(msg.param_type)
                return self._decode(msg)
        return None

    def read(self, name, retries=RETRIES) -> float | None:
        """The vehicle's value of ``name`` (PARAM_REQUEST_READ), or None after ``retries`` unanswered asks."""
        for _ in range(max(1, int(retries))):
            self.conn.mav.param_request_read_send(self.target_system, self.target_component, name.encode("ascii"), -1)
            value = self._await_value(name, time.monotonic() + self.answer_timeout_s)
            if value is not None:
                return value
        return None

    def write(self, name, value, retries=RETRIES) -> tuple[float | None, int]:
        """PARAM_SET ``name`` until the vehicle's echo equals ``value`` (float32) or ``retries`` are spent.
        Returns the last echoed value (None: no echo) and the number of PARAM_SET sent."""
        echoed = None
        for attempt in range(1, max(1, int(retries)) + 1):
            wire, ptype = self._encode(name, value)
            self.conn.mav.param_set_send(self.target_system, self.target_component, name.encode("ascii"), wire, ptype)
            echoed = self._await_value(name, time.monotonic() + self.answer_timeout_s)
            if equal_float32(echoed, value):
                return echoed, attempt
        return echoed, max(1, int(retries))


def default_backup_path(folder, firmware) -> str:
    """``vehicle-backup-YYYYmmdd-HHMMSS.parm`` (``.params`` for PX4) in ``folder``, a counter added if it exists."""
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    ext = ".params" if firmware == "px4" else ".parm"
    path = os.path.join(os.fspath(folder), f"vehicle-backup-{stamp}{ext}")
    k = 1
    while os.path.exists(path):
        path = os.path.join(os.fspath(folder), f"vehicle-backup-{stamp}-{k}{ext}")
        k += 1
    return path


def backup_text(old: dict, firmware: str, target: str) -> str:
    """A parameter file of the vehicle's old values, in the firmware's format (sent back to restore them)."""
    now = _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%d %H:%M:%S UTC")
    head = [
        f"# the values of {target} before magcal sent a calibration ({now})",
        "# restore: magcal send THIS --url ...",
    ]
    if firmware == "px4":
        body = ["# Vehicle-Id\tComponent-Id\tName\tValue\tType"]
        body += [f"1\t1\t{n}\t{v:.9g}\t9" for n, v in old.items()]
    else:
        body = [f"{n},{v:.9g}" for n, v in old.items()]
    return "\n".join(head + body) + "\n"


def send_parameters(
    url,
    values: dict,
    firmware: str | None = None,
    backup_path=None,
    confirm=None,
    retries: int = RETRIES,
    heartbeat_timeout_s: float = HEARTBEAT_TIMEOUT_S,
    answer_timeout_s: float = ANSWER_TIMEOUT_S,
) -> SendReport:
    """Write ``values`` (``name -> value``) to the vehicle at ``url`` and read each back (see the module).

    Parameters
    ----------
    url : str
        The MAVLink connection (:func:`mavlink_device`).
    values : dict
        What to write (:func:`values_to_send` of a parameter file).
    firmware : {'ardupilot', 'px4'}, optional
        Default: from the names.
    backup_path : str or os.PathLike, optional
        Where the old values are written (atomically) before anything is sent; None: no backup.
    confirm : callable, optional
        ``confirm(report)`` with the old -> new table read (``report.rows()``); False stops before anything is
        written (``report.declined``). None: send without asking.
    retries : int
        Tries per read and per write.
    heartbeat_timeout_s, answer_timeout_s : float
        Longest waits (s) for the vehicle's heartbeat and for one answer.

    Returns
    -------
    SendReport
        ``report.ok`` only when every value was read back equal.

    Raises
    ------
    MagcalError
        No pymavlink, a connection that does not open, no heartbeat, or a parameter the vehicle does not answer
        for before sending (then nothing was written).
    """
    values = {str(k): float(v) for k, v in values.items()}
    firmware = firmware or firmware_of(values)
    report = SendReport(str(url), firmware, [ParamResult(n, v) for n, v in values.items()])
    with ParamLink(url, firmware, heartbeat_timeout_s, answer_timeout_s) as link:
        for r in report.results:
            r.old = link.read(r.name, retries)
        missing = [r.name for r in report.results if r.old is None]
        if missing:
            raise MagcalError(
                f"{url}: the vehicle did not answer for {', '.join(missing)} ({retries} tries); nothing was sent. "
                "Check the firmware (ArduPilot or PX4) and the compass numbers (--sensor/--slot)"
            )
        if confirm is not None and not confirm(report):
            report.declined = True
            return report
        if backup_path is not None:
            with atomic_write(backup_path) as fh:
                fh.write(backup_text({r.name: r.old for r in report.results}, firmware, str(url)))
            report.backup_path = os.fspath(backup_path)
        report.sent = True
        for r in report.results:
            echoed, r.attempts = link.write(r.name, r.new, retries)
            r.sent = True
            if echoed is None:
                r.reason = "no echo from the vehicle"
        for r in report.results:  # every value read back once all are written
            r.read_back = link.read(r.name, retries)
            r.ok = equal_float32(r.read_back, r.new)
            if r.read_back is None:
                r.reason = "no answer when read back"
            elif not r.ok:
                r.reason = f"read back {r.read_back:.9g}, not {r.new:.9g}"
            else:
                r.reason = ""
    return report
