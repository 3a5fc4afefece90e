"""Live sources: time-stamped magnetometer samples as they arrive, and a recorder that keeps every one on disk.

One interface for every instrument (``docs/export.md`` has the URL forms):

``serial:///dev/ttyUSB0?baud=115200&columns=x,y,z``
    Text lines from a serial port (pyserial), opened again when it disappears (a board reset, a USB
    re-enumeration) for up to ``reconnect`` s (default 30), with nothing received lost (:class:`SerialSource`).
    Also ``&mavlink`` for MAVLink over the port, reopened the same way.
``udp://127.0.0.1:14550?format=lines`` / ``tcp://127.0.0.1:5760``
    Text lines in UDP datagrams (listening on the address) or from a TCP server (connecting to it).
``udp://127.0.0.1:14550?mavlink`` (also ``tcp://...?mavlink``, connected again for up to ``reconnect`` s when closed)
    MAVLink (pymavlink): the magnetometer fields of ``RAW_IMU``, ``SCALED_IMU``, ``SCALED_IMU2``, ``SCALED_IMU3``
    or ``HIGHRES_IMU`` in the units the message definition declares (mgauss, gauss), converted to nT, with the
    temperature where the message sends one, ``ATTITUDE`` merged onto each sample (nearest in time within
    ``attitude_max_dt`` s) and the position of ``GPS_RAW_INT`` / ``GLOBAL_POSITION_INT`` (:class:`MavlinkSource`).
``sim://chi2017?rate=50`` / ``sim://path/to/file.csv?rate=50``
    A simulated instrument playing a preset (:func:`magcal.data.simulation.simulate_timeseries`, deterministic for a
    given ``seed``) or a magcal CSV file in real time: for tests, teaching and demonstrations without hardware.

Text-line options: ``columns`` (comma-separated names of the fields of a line: ``x,y,z`` or ``mx,my,mz`` or
``s1x..s4z``, ``t`` in s (``t_ms``, ``t_us``), ``temp`` in degC, the channels ``roll, pitch, yaw`` (deg), ``gx,
gy, gz`` (deg/s), ``ax, ay, az``, ``lat, lon, alt``, ``_`` for a field to skip; default ``x,y,z``), or
``template`` (the line with its fields in braces: ``x={x} y={y} z={z}``), ``sep`` (the separator; default commas,
semicolons, tabs or spaces), ``units`` (``nT`` default, ``uT``, ``G``, ``mG``, ``counts`` with ``lsb`` in nT per
count), ``prefix`` (only lines starting with it are data, e.g. ``Raw:``), ``checksum`` (``off``: a trailing ``*hh``
is not checked). Framed lines (``|...*``, ``$...*hh``) and bracketed lists (``[x, y, z]`` anywhere in a line) are
read as they come (:mod:`magcal.data.lineformats`). Without a ``t`` column the samples are stamped with the host's
monotonic clock, in s since the source opened.

Channels other than the readings and the temperature (attitude, gyro, accelerometer, position) travel in
:attr:`LiveChunk.channels`, into :meth:`LiveChunk.to_dataset`'s ``extra`` and the recording's columns under the
names :mod:`magcal.data.attitude` and :mod:`magcal.checks.reference` read (``roll_deg``, ``lat``, ...).

:meth:`LiveSource.read` returns a :class:`LiveChunk` of whatever arrived within a timeout (possibly empty);
iterating a source yields non-empty chunks until it ends or is closed. Lines or messages that cannot be read are
counted in :attr:`LiveSource.stats` (with the last reason), never raised; lines that are not data (comments, a
boot banner before the first sample) are counted as skipped. Every wait is bounded, and so is every line's work
(at most :data:`MAX_LINE_BYTES`, a template matched in linear time): a read returns by its timeout whatever
arrives, the lines it did not reach waiting for the next, so ``magcal record --seconds S`` ends after S seconds.

:class:`Recorder` appends the samples to a magcal CSV as they arrive: whole lines only, flushed to disk (``fsync``)
at least every ``flush_interval_s``, so a recording cut by a crash or a kill reopens with
:func:`magcal.read_csv` holding every sample up to the last flush. :class:`LiveSession` runs a source and a
recorder in a thread with pause, resume, stop and listeners (the workbench's live view).

``magcal record URL OUT.csv --seconds 60`` records from the command line (:mod:`magcal.cli.record`).
"""

from __future__ import annotations

import collections
import datetime as _dt
import os
import re
import socket
import threading
import time
import urllib.parse
import warnings
from dataclasses import dataclass, field

import numpy as np

from magcal.core.errors import MagcalError
from magcal.data import lineformats
from magcal.data.dataset import BAD_VALUE_TEXT, MAX_ABS_VALUE, SENSOR_AXES, Dataset, bad_values
from magcal.data.io import format_column, is_counts, metadata_text, parse_units, read_csv
from magcal.data.simulation import PRESETS, simulate_timeseries

#: URL schemes and what they read.
SCHEMES = ("serial", "udp", "tcp", "sim")

#: Longest text line accepted (bytes); longer ones are counted as bad and skipped.
MAX_LINE_BYTES = 4096

#: A device's time stamps going back by more than this (s) mean its clock restarted (a reboot); later samples are
#: shifted to follow on. A smaller step back is a bad sample.
CLOCK_RESET_S = 1.0

#: Longest total wait for a lost serial port to come back (s) unless ``reconnect`` says otherwise, the bounds of
#: ``reconnect``, and the longest interval between two tries.
RECONNECT_DEFAULT_S = 30.0
RECONNECT_RANGE_S = (0.0, 3600.0)
RECONNECT_MAX_INTERVAL_S = 2.0

#: Bounds of a simulated source's options (``sim://PRESET?n=..&rate=..&speed=..``): samples of a preset, samples
#: per second, and how much faster than real time it plays. The workbench offers these and nothing beyond.
SIM_MAX_SAMPLES = 100_000  # about 1.5 s to simulate; ``loop`` plays a preset for as long as wanted
SIM_RATE_RANGE_HZ = (0.1, 10_000.0)
SIM_SPEED_RANGE = (0.01, 100.0)
#: Most samples per second a simulated source sends (``rate`` times ``speed``): a recording grows at most
#: about 1 MB/s.
SIM_MAX_SAMPLES_PER_S = 20_000.0
#: Largest seed of a simulated source (numpy's seeds are unsigned 32-bit here).
SIM_MAX_SEED = 2**32 - 1
#: Serial speeds accepted (bit/s).
BAUD_RANGE = (50, 10_000_000)
#: Connect timeout of a TCP source (s).
TIMEOUT_RANGE_S = (0.01, 60.0)

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


class LiveError(MagcalError):
    """A live source cannot be opened or has failed (a bad URL, a port that does not open, a lost device).

    Its message is one line whatever the URL holds: control characters (a line end in a URL parameter) are
    shown escaped.
    """

    def __init__(self, message=""):
        text = str(message)
        if not text.isprintable():
            text = "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)
        super().__init__(text)


@dataclass
class LiveChunk:
    """Samples that arrived together.

    Attributes
    ----------
    time_s : numpy.ndarray, shape (n,)
        Sample times in s, strictly increasing within and across the chunks of one source.
    readings_nT : numpy.ndarray, shape (n_sensors, n, 3)
        Raw readings in nT.
    temperature_C : numpy.ndarray, shape (n,), optional
        Temperature in degC, when the source sends one.
    channels : dict of str to numpy.ndarray, shape (n,)
        Other channels the source sends, by the name of the Dataset column they become
        (:data:`magcal.data.lineformats.CHANNEL_UNITS`): ``roll_deg, pitch_deg, yaw_deg`` (deg, body ->
        north-east-down, the columns :mod:`magcal.data.attitude` reads), ``gyro_x_dps..`` (deg/s), ``accel_x..``,
        ``lat, lon`` (deg), ``alt_m`` (m). NaN where a sample has no value (e.g. no MAVLink ``ATTITUDE`` near it).
    """

    time_s: np.ndarray
    readings_nT: np.ndarray
    temperature_C: np.ndarray | None = None
    channels: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.time_s.size)

    @property
    def n_sensors(self) -> int:
        return int(self.readings_nT.shape[0])

    def to_dataset(self, source=None) -> Dataset:
        """The samples as a :class:`Dataset` (readings nT, ``time_s``, ``temperature_C``; the channels as ``extra``
        columns of the same names, so the attitude reads as :func:`magcal.data.attitude.attitude` expects and the
        position as :func:`magcal.checks.reference.resolve_vector_reference` does)."""
        return Dataset(
            readings_nT=self.readings_nT,
            time_s=self.time_s,
            temperature_C=self.temperature_C,
            extra={k: np.asarray(v, dtype=float) for k, v in self.channels.items()},
            source=source,
        )

    def subset(self, keep) -> LiveChunk:
        """The samples selected by a boolean mask or an index array."""
        return LiveChunk(
            self.time_s[keep],
            self.readings_nT[:, keep],
            None if self.temperature_C is None else self.temperature_C[keep],
            {k: v[keep] for k, v in self.channels.items()},
        )


def _empty_chunk(n_sensors, temperature, channels=()):
    return LiveChunk(
        np.zeros(0),
        np.zeros((max(n_sensors or 1, 1), 0, 3)),
        np.zeros(0) if temperature else None,
        {k: np.zeros(0) for k in channels or ()},
    )


def concatenate_chunks(chunks) -> LiveChunk | None:
    """One chunk from several of the same source (None for none)."""
    chunks = [c for c in chunks if len(c)]
    if not chunks:
        return None
    temps = [c.temperature_C for c in chunks]
    names = list(chunks[0].channels)
    same = all(list(c.channels) == names for c in chunks)
    return LiveChunk(
        np.concatenate([c.time_s for c in chunks]),
        np.concatenate([c.readings_nT for c in chunks], axis=1),
        None if any(t is None for t in temps) else np.concatenate(temps),
        {k: np.concatenate([c.channels[k] for c in chunks]) for k in names} if same else {},
    )


@dataclass
class SourceStats:
    """What a source has received: samples kept, lines or messages refused and why, lines skipped and why, and the
    times the port was lost and opened again.

    A line is *bad* when it should be data and is not (a wrong field count, not a number, a line that departs from
    the template, a failed checksum); it is *skipped* when it is not data: an empty line, a comment, a line without
    the ``prefix``, and whatever cannot be read before the first sample since the source opened or reconnected (a
    boot banner, the cut first line). Neither ever gives a sample.
    """

    n_samples: int = 0
    n_bad: int = 0
    last_bad: str | None = None
    reasons: collections.Counter = field(default_factory=collections.Counter)
    n_skipped: int = 0
    last_skipped: str | None = None
    skipped: collections.Counter = field(default_factory=collections.Counter)
    #: Times the source lost its port and opened it again (:class:`SerialSource`, :class:`MavlinkSource` on a serial
    #: device).
    n_reconnects: int = 0
    #: Why the port was last lost, or None.
    last_disconnect: str | None = None

    def bad(self, reason: str, where: str = "") -> None:
        """Count one refused line or message."""
        self.n_bad += 1
        key = reason.split(":")[0]
        self.reasons[key] += 1
        self.last_bad = f"{where}: {reason}" if where else reason

    def skip(self, reason: str, where: str = "") -> None:
        """Count one line that is not data."""
        self.n_skipped += 1
        self.skipped[reason.split(":")[0]] += 1
        self.last_skipped = f"{where}: {reason}" if where else reason

    def summary(self) -> str:
        """``1200 samples, 3 bad (2 not a number, 1 field count); last: ...; 2 skipped (...); 1 reconnect``."""
        text = f"{self.n_samples} samples, {self.n_bad} bad"
        if self.n_bad:
            text += " (" + ", ".join(f"{n} {k}" for k, n in self.reasons.most_common()) + f"); last: {self.last_bad}"
        if self.n_skipped:
            text += (
                f"; {self.n_skipped} skipped ("
                + ", ".join(f"{n} {k}" for k, n in self.skipped.most_common())
                + f"); last: {self.last_skipped}"
            )
        if self.n_reconnects:
            text += f"; {self.n_reconnects} reconnect{'s' if self.n_reconnects > 1 else ''} ({self.last_disconnect})"
        return text


# -- the source interface ----------------------------------------------------------------------------------------
class LiveSource:
    """A live source of magnetometer samples (the base of every kind; open one with :func:`open_source`).

    Attributes
    ----------
    url : str
    n_sensors : int or None
        Number of triaxial sensors per sample (None until known).
    has_temperature : bool or None
        Whether samples carry a temperature (None until known).
    channel_names : tuple of str or None
        The channels of every sample (:attr:`LiveChunk.channels`; None until known).
    stats : SourceStats
    ended : bool
        True when a finite source (a file, a closed TCP connection) has nothing more to give.
    """

    def __init__(self, url):
        self.url = url
        self.n_sensors = None
        self.has_temperature = None
        self.channel_names = None
        self.stats = SourceStats()
        self.ended = False
        self.closed = False
        self._last_t = None
        self._t0 = time.monotonic()

    # subclasses implement _poll(deadline, max_samples) -> list of (t or None, readings (n_sensors, 3), temp) or
    # (t or None, readings, temp, channels {name: value})
    def _poll(self, deadline, max_samples):  # pragma: no cover - abstract
        raise NotImplementedError

    def read(self, timeout_s: float = 1.0, max_samples: int = 10_000) -> LiveChunk:
        """The samples that arrive within ``timeout_s`` seconds (returns as soon as some have), possibly none.

        Samples whose time does not increase, or whose sensor count, temperature or channels differ from the first
        sample's, are counted as bad and left out. A channel may be NaN (no value for that sample); one infinite
        or beyond :data:`magcal.data.dataset.MAX_ABS_VALUE` makes the sample bad.
        """
        if self.closed:
            raise LiveError(f"{self.url}: the source is closed")
        deadline = time.monotonic() + max(0.0, float(timeout_s))
        samples = [] if self.ended else self._poll(deadline, int(max_samples))
        return self._accept(samples)

    def _held(self):
        """Samples received but held back (a MAVLink sample waiting for its attitude); none by default."""
        return []

    def drain(self) -> LiveChunk:
        """The samples received but not yet returned (held for a merge), without waiting: call it before
        :meth:`close` so that nothing received is lost."""
        if self.closed:
            return _empty_chunk(self.n_sensors, self.has_temperature, self.channel_names)
        return self._accept(self._held())

    def _accept(self, samples) -> LiveChunk:
        """The samples that pass the stream's checks, as a chunk (the others counted as bad)."""
        times, readings, temps, chans = [], [], [], []
        for sample in samples:
            t, r, temp = sample[:3]
            channels = sample[3] if len(sample) > 3 else {}
            if t is None:  # host clock, at arrival; lines that came together are 1 us apart
                t = time.monotonic() - self._t0
                if self._last_t is not None and t <= self._last_t:
                    t = self._last_t + 1e-6
            r = np.asarray(r, dtype=float).reshape(-1, 3)
            if self.n_sensors is None:
                self.n_sensors = r.shape[0]
            if self.has_temperature is None:
                self.has_temperature = temp is not None
            if self.channel_names is None:
                self.channel_names = tuple(channels)
            if r.shape[0] != self.n_sensors:
                self.stats.bad(f"sensor count: {r.shape[0]} sensor(s), the stream has {self.n_sensors}")
                continue
            if (temp is not None) != self.has_temperature:
                self.stats.bad("temperature: present in some samples only (the first decides)")
                continue
            if tuple(channels) != self.channel_names:
                self.stats.bad(
                    f"channels: {', '.join(channels) or 'none'}, the stream has {', '.join(self.channel_names) or 'none'}"
                )
                continue
            if bad_values(r).any() or bad_values(t) or (temp is not None and bad_values(temp)):
                self.stats.bad(f"bad value: {BAD_VALUE_TEXT} (time {t!r})")
                continue
            values = np.asarray(list(channels.values()), dtype=float)
            if np.any(bad_values(values) & ~np.isnan(values)):  # NaN: no value for this sample
                self.stats.bad(f"bad value: a channel is infinite or beyond +-{MAX_ABS_VALUE:g} (time {t!r})")
                continue
            if self._last_t is not None and t <= self._last_t:
                self.stats.bad(f"time going back: {t:.6g} s after {self._last_t:.6g} s")
                continue
            self._last_t = t
            times.append(t)
            readings.append(r)
            temps.append(temp)
            chans.append(values)
        self.stats.n_samples += len(times)
        if not times:
            return _empty_chunk(self.n_sensors, self.has_temperature, self.channel_names)
        values = np.asarray(chans, dtype=float).reshape(len(times), len(self.channel_names or ()))
        return LiveChunk(
            np.asarray(times, dtype=float),
            np.stack(readings, axis=1),
            np.asarray(temps, dtype=float) if self.has_temperature else None,
            {name: values[:, j].copy() for j, name in enumerate(self.channel_names or ())},
        )

    def __iter__(self):
        while not self.closed:
            chunk = self.read(timeout_s=0.5)
            if len(chunk):
                yield chunk
            elif self.ended:
                return

    def close(self) -> None:
        """Release the port or socket; further reads raise :class:`LiveError`."""
        self.closed = True

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def describe(self) -> str:
        """One line: the URL and what was received."""
        return f"{self.url}: {self.stats.summary()}"


# -- text lines ------------------------------------------------------------------------------------------------------
_SPLIT_DEFAULT = re.compile(r"[,;\t ]+")


class LineParser:
    """Turns one text line into a sample: separated numbers, a framed line, a bracketed list or a template
    (:mod:`magcal.data.lineformats` has the formats).

    Parameters
    ----------
    columns : str or sequence of str, optional
        Names of the fields in order (default ``x,y,z``): ``x,y,z`` or ``mx,my,mz`` (sensor 1), ``s1x..s4z``,
        ``t`` (s; ``t_ms``, ``t_us``), ``temp`` (degC), the channels ``roll, pitch, yaw`` (deg), ``gx, gy, gz``
        (deg/s), ``ax, ay, az``, ``lat, lon`` (deg), ``alt`` (m), ``_`` (skipped).
    sep : str, optional
        Field separator; default any run of commas, semicolons, tabs or spaces.
    units : str
        Unit of the readings (``nT``, ``uT``, ``G``, ``mG``, or ``counts`` with ``lsb_nT``).
    lsb_nT : float, optional
        nT per count for ``counts``.
    prefix : str, optional
        Only lines starting with it are data (it is removed); other lines are skipped, not counted as bad.
    template : str, optional
        The line written out with its fields in braces, e.g. ``x={x} y={y} z={z}`` (instead of ``columns``).
    checksum : bool
        Check a trailing ``*hh`` checksum of a framed line (it is stripped either way).

    Attributes
    ----------
    n_sensors : int
    channel_names : tuple of str
        The channels each sample carries (:attr:`LiveChunk.channels`).
    last_skip : str or None
        Why the last line :meth:`parse` returned None for was not data.
    """

    def __init__(self, columns=None, sep=None, units="nT", lsb_nT=None, prefix=None, template=None, checksum=True):
        if template is not None and columns is not None:
            raise LiveError("give columns or a template, not both (a template names its own fields)")
        if template is not None:
            try:
                self.template = lineformats.LineTemplate(template)
            except ValueError as exc:
                raise LiveError(str(exc)) from None
            names = list(self.template.fields)
        else:
            self.template = None
            columns = "x,y,z" if columns is None else columns
            names = [c.strip() for c in (columns.split(",") if isinstance(columns, str) else columns)]
        self.columns = names
        self.sep = sep
        self.prefix = prefix or None
        self.checksum = bool(checksum)
        self.last_skip = None
        self.factor = parse_units(units, where="live source units", lsb_nT=lsb_nT if is_counts(units) else None)
        self.index_t = self.index_temp = None
        self.time_factor = 1.0
        axes, channels, seen, used = {}, {}, {}, []
        for j, name in enumerate(names):
            try:
                role = lineformats.column_role(name)
            except ValueError as exc:
                raise LiveError(f"columns: {exc}") from None
            kind = role[0]
            if kind == "skip":
                continue
            key = role if kind != "time" else ("time",)
            if key in seen:
                raise LiveError(
                    f"columns: {name!r} and {seen[key]!r} name the same field"
                    if seen[key] != name
                    else f"columns: {name!r} appears twice"
                )
            seen[key] = name
            used.append(j)
            if kind == "time":
                self.index_t, self.time_factor = j, role[1]
            elif kind == "temp":
                self.index_temp = j
            elif kind == "channel":
                channels[role[1]] = j
            else:
                axes[(role[1], role[2])] = j
        sensors = sorted({s for s, _ in axes})
        if not sensors or sensors != list(range(1, len(sensors) + 1)):
            raise LiveError(f"columns {','.join(names)}: name sensors 1.. without gaps (x,y,z or s1x,s1y,s1z,...)")
        for s in sensors:
            if any((s, a) not in axes for a in SENSOR_AXES):
                raise LiveError(f"columns {','.join(names)}: sensor {s} needs x, y and z")
        self.index_xyz = np.array([[axes[(s, a)] for a in SENSOR_AXES] for s in sensors])
        self.n_sensors = len(sensors)
        self.channel_names = tuple(channels)
        self._index_channels = np.array(list(channels.values()), dtype=int)
        self._used = used

    def _split(self, text):
        return text.split(self.sep) if self.sep else _SPLIT_DEFAULT.split(text)

    def _skip(self, reason):
        self.last_skip = reason
        return None

    def parse(self, text):
        """``(t or None, readings (n_sensors, 3) nT, temperature or None)``, or ``None`` for a line that is not data
        (:attr:`last_skip` says why).

        Raises
        ------
        ValueError
            With the reason, for a line that should be data but is not.
        """
        sample = self.parse_sample(text)
        return None if sample is None else sample[:3]

    def parse_sample(self, text):
        """:meth:`parse` with the channels: ``(t, readings, temperature, {channel: value})`` or None."""
        self.last_skip = None
        text = text.strip()
        if not text:
            return self._skip("empty line")
        if text.startswith("#"):
            return self._skip("comment")
        if self.prefix is not None:
            if not text.startswith(self.prefix):
                return self._skip(f"no prefix: the line does not start with {self.prefix!r}")
            text = text[len(self.prefix) :].strip()
        if self.template is not None:
            fields = self.template.match(text)  # raises "template: ..."
        else:
            text = lineformats.strip_frame(text, self.checksum)  # raises "checksum: ..."
            if lineformats.has_brackets(text):
                fields = lineformats.bracketed_fields(text, len(self.columns), self._split)
            else:
                fields = self._split(text)
            if len(fields) != len(self.columns):
                raise ValueError(
                    f"field count: {len(fields)} field(s), expected {len(self.columns)} ({','.join(self.columns)})"
                )
        values = np.full(len(fields), np.nan)
        for j in self._used:  # a skipped field may hold anything
            f = fields[j]
            try:
                values[j] = float(f) if f.strip() else np.nan
            except ValueError:
                raise ValueError(f"not a number: {f[:30]!r}") from None
        readings = values[self.index_xyz] * self.factor
        t = None if self.index_t is None else float(values[self.index_t]) * self.time_factor
        temp = None if self.index_temp is None else float(values[self.index_temp])
        channels = dict(zip(self.channel_names, values[self._index_channels].tolist()))
        return t, readings, temp, channels


class _DeviceClock:
    """A device's time stamps (s) put on the source's time line across restarts of the device's clock (a reboot).

    The clock restarted when a time stamp goes back by more than :data:`CLOCK_RESET_S`, or at all in the first one
    after :attr:`restart_possible` was set (the port was reopened: the device may have rebooted); the stamps from
    then on are shifted to follow on from the latest time given, by the time the host saw pass since the previous
    stamp (at least 1 ms). :attr:`resets` counts the restarts: the device's boots seen after the first.
    """

    def __init__(self):
        self.resets = 0
        self.restart_possible = False
        self._device_t = None  # the last time stamp the device sent, and the shift added to it
        self._offset = 0.0
        self._host_t = None  # host clock at that stamp
        self._out_max = None  # the latest time given so far on the source's time line

    def follow(self, t: float) -> float:
        """The device's time ``t`` (s, finite) on the source's time line (s)."""
        now = time.monotonic()
        restarted = self.restart_possible and self._device_t is not None and t <= self._device_t
        self.restart_possible = False
        if self._device_t is not None and (restarted or t < self._device_t - CLOCK_RESET_S):
            self._offset = self._out_max + max(now - self._host_t, 1e-3) - t
            self.resets += 1
        self._device_t, self._host_t = t, now
        out = t + self._offset
        self._out_max = out if self._out_max is None else max(self._out_max, out)
        return out


class _ReopensPort:
    """A :class:`LiveSource` on a serial port that reopens it when it disappears (:class:`SerialSource`, and
    :class:`MavlinkSource` on a serial device or a TCP connection, which is connected again when it closes).

    When a read fails the source calls :meth:`_lose`; while :attr:`connected` is False it calls :meth:`_reopen`
    instead of reading, which opens the same path again after 0.1 s, then at doubling intervals up to
    :data:`RECONNECT_MAX_INTERVAL_S`, for at most ``reconnect_s`` in all, and raises :class:`LiveError` (naming the
    device and the wait) beyond; with ``reconnect_s=0`` the loss itself raises. The source implements
    ``_open_port()`` (raising one of ``_port_errors`` while the port is absent), ``_close_port()``, and the hooks
    ``_port_lost()`` (what the loss cut) and ``_port_back()`` (what a reopened port starts afresh). ``what`` names
    the port in messages (``the serial port /dev/ttyACM0``, ``the TCP connection to 127.0.0.1:5760``) and ``hint``
    says what to check.
    """

    def _init_reopen(self, device, reconnect_s, errors, what=None, hint="is the device connected?"):
        self.device = device
        self.reconnect_s = float(reconnect_s)
        self._port_what = what or f"the serial port {device}"
        self._port_hint = hint
        self._port_errors = errors
        self._lost_at = None  # host time the port was lost, while it is
        self._next_try = 0.0
        self._interval = 0.1
        self._last_try = None  # why the last try to reopen the port failed

    @property
    def connected(self) -> bool:
        """False while the port is lost and being reopened."""
        return self._lost_at is None

    def _port_lost(self):
        """What the loss cut (a line, a packet): counted as bad, never joined to what comes after."""

    def _port_back(self):
        """The port was reopened: the device may have rebooted."""

    def _lose(self, exc):
        """The port failed: close it, keep what was read, and start reopening it (or raise)."""
        try:
            self._close_port()
        except Exception:  # a port that has gone: nothing left to release
            pass
        if self.reconnect_s <= 0:
            raise LiveError(f"{self.url}: {self._port_what} failed ({exc}); {self._port_hint}")
        self._port_lost()
        self.stats.last_disconnect = f"lost: {exc}"
        self._lost_at = time.monotonic()
        self._next_try = self._lost_at + 0.1
        self._interval = 0.1
        self._last_try = None

    def _reopen(self, timeout_s):
        """Try to open the port again when the next try is due (waiting at most ``timeout_s``)."""
        now = time.monotonic()
        if now - self._lost_at > self.reconnect_s:
            tried = f" (last try: {self._last_try})" if self._last_try else ""
            raise LiveError(
                f"{self.url}: {self._port_what} was lost ({self.stats.last_disconnect}) and did not come "
                f"back within {self.reconnect_s:g} s{tried}; {self._port_hint}"
            )
        if now < self._next_try:
            time.sleep(max(0.0, min(timeout_s, self._next_try - now)))
            return
        try:
            self._open_port()
        except self._port_errors as exc:
            self._last_try = exc
            self._interval = min(self._interval * 2.0, RECONNECT_MAX_INTERVAL_S)
            self._next_try = time.monotonic() + self._interval
            return
        gap = time.monotonic() - self._lost_at
        self.stats.n_reconnects += 1
        self.stats.last_disconnect = f"{self.stats.last_disconnect}; reopened after {gap:.1f} s"
        self._lost_at = None
        self._port_back()


class _LineSource(LiveSource):
    """A source of text lines from a byte stream; subclasses implement ``_receive(timeout_s) -> bytes`` (and set
    ``_eof`` when the stream has ended).

    Lines that cannot be read before the first sample since the source opened (or reopened its port) are skipped
    as a boot banner or a cut first line (:meth:`SourceStats.skip`); after it, they are bad. When a line's time
    (a ``t`` column) jumps back by more than :data:`CLOCK_RESET_S`, or at all in the first sample after the port
    was reopened (the board restarted its clock), later samples are shifted to follow on from the last one by the
    time the host saw pass (:attr:`clock_resets` counts it).

    Every line costs a bounded time (at most :data:`MAX_LINE_BYTES` bytes; a template matches in linear time,
    :class:`magcal.data.lineformats.LineTemplate`), and a read returns by its deadline: the lines received but not
    yet parsed then wait for the next read (or :meth:`drain`). A stream without line ends is one over-long line,
    counted once however long it runs, and dropped up to its next line end.
    """

    def __init__(self, url, parser):
        super().__init__(url)
        self.parser = parser
        self.n_sensors = parser.n_sensors
        self.has_temperature = parser.index_temp is not None
        self.channel_names = parser.channel_names
        self._buffer = b""
        self._line_no = 0
        self._overlong = None  # bytes of the over-long line being dropped, while it lasts
        self._queue = collections.deque()  # lines received, not yet parsed (None: an over-long line's start)
        self._eof = False  # the stream has ended (what it held is still queued)
        self._seen_data = False  # a sample since the source opened or reconnected
        self._clock = _DeviceClock()

    @property
    def clock_resets(self) -> int:
        """Restarts of the device's clock seen (reboots)."""
        return self._clock.resets

    def _device_clock(self, t):
        """The device's time ``t`` (s) on the source's time line, across restarts of the device's clock."""
        if bad_values(t):  # refused later as a bad value; it says nothing about the device's clock
            return t
        return self._clock.follow(t)

    def _receive(self, timeout_s):  # pragma: no cover - abstract
        raise NotImplementedError

    def _lines(self, data):
        """The whole lines ``data`` completes (the rest is kept); an over-long line is counted once and dropped."""
        if self._overlong is not None:  # inside an over-long line (counted): dropped up to its end
            end = _LINE_END.search(data)
            self._overlong += len(data) if end is None else end.start()
            self.stats.last_bad = f"line {self._line_no}: {_overlong_reason(self._overlong, end is not None)}"
            if end is None:
                return []
            self._overlong = None
            data = data[end.end() :]
        self._buffer += data
        *lines, self._buffer = _LINE_END.split(self._buffer)
        if len(self._buffer) > MAX_LINE_BYTES:  # counted by _take after the lines before it: None stands for it
            self._overlong = len(self._buffer)
            self._buffer = b""
            lines.append(None)
        return lines

    def _take(self, raw):
        """The sample of one received line, or None (the line counted as bad or skipped); ``raw`` None is the
        start of an over-long line."""
        self._line_no += 1
        where = f"line {self._line_no}"
        if raw is None:
            self.stats.bad(_overlong_reason(self._overlong or MAX_LINE_BYTES, False), where)
            return None
        if len(raw) > MAX_LINE_BYTES:
            self.stats.bad(f"line too long: {len(raw)} bytes, over {MAX_LINE_BYTES}", where)
            return None
        try:
            sample = self.parser.parse_sample(raw.decode("utf-8"))
        except (UnicodeDecodeError, ValueError) as exc:
            reason = "not text: bytes that are not UTF-8" if isinstance(exc, UnicodeDecodeError) else str(exc)
            if self._seen_data:
                self.stats.bad(reason, where)
            else:  # a boot banner, or the first line cut by the opening
                self.stats.skip(f"before the first sample: {reason}", where)
            return None
        if sample is None:
            self.stats.skip(self.parser.last_skip or "not data", where)
            return None
        self._seen_data = True
        if sample[0] is not None:
            sample = (self._device_clock(sample[0]), *sample[1:])
        return sample

    def _poll(self, deadline, max_samples):
        samples = []
        while not samples:
            if not self._queue:
                if self._eof:
                    self.ended = True
                if self.ended:
                    break
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    break
                self._queue.extend(self._lines(self._receive(min(remaining, 0.2))))
            while self._queue and len(samples) < max_samples:
                sample = self._take(self._queue.popleft())
                if sample is not None:
                    samples.append(sample)
                if time.monotonic() >= deadline:  # the rest waits for the next read
                    break
            if len(samples) >= max_samples or time.monotonic() >= deadline:
                break
        if self._eof and not self._queue:
            self.ended = True
        return samples

    def _held(self):
        """The lines received but not yet parsed (a read that reached its deadline), parsed now."""
        samples = []
        while self._queue:
            sample = self._take(self._queue.popleft())
            if sample is not None:
                samples.append(sample)
        return samples


#: A line end in a byte stream: CR LF, LF or CR.
_LINE_END = re.compile(rb"\r\n|\n|\r")


def _overlong_reason(n_bytes, ended):
    """Why an over-long line (``n_bytes`` so far, ``ended`` or not) is bad: one line, however long it runs."""
    if ended:
        return (
            f"line too long: {n_bytes} bytes before its line end, over {MAX_LINE_BYTES}; dropped (a stream without "
            "line ends: binary data such as MAVLink, or a wrong baud rate?)"
        )
    return (
        f"line too long: no line end in {n_bytes} bytes (over {MAX_LINE_BYTES}); dropped up to the next line end "
        "(a stream without line ends: binary data such as MAVLink, or a wrong baud rate?)"
    )


class SerialSource(_ReopensPort, _LineSource):
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


class UdpLineSource(_LineSource):
    """Text lines in UDP datagrams received on ``host:port``."""

    def __init__(self, url, host, port, parser):
        super().__init__(url, parser)
        self._sock = _bind_udp(url, host, port)

    def _receive(self, timeout_s):
        self._sock.settimeout(max(timeout_s, 0.001))
        try:
            data, _ = self._sock.recvfrom(65536)
        except (TimeoutError, BlockingIOError):
            return b""
        except OSError as exc:
            raise LiveError(f"{self.url}: receiving failed ({exc})") from None
        return data if data.endswith((b"\n", b"\r")) else data + b"\n"  # a datagram holds whole lines

    def close(self):
        super().close()
        self._sock.close()


class TcpLineSource(_LineSource):
    """Text lines from a TCP server at ``host:port`` (magcal connects to it)."""

    def __init__(self, url, host, port, parser, connect_timeout_s=5.0):
        super().__init__(url, parser)
        try:
            self._sock = socket.create_connection((host, port), timeout=connect_timeout_s)
        except (OSError, UnicodeError, ValueError) as exc:  # UnicodeError: a host name the IDNA codec refuses
            raise LiveError(f"{url}: cannot connect to {host}:{port} ({exc}); is the server running?") from None

    def _receive(self, timeout_s):
        self._sock.settimeout(max(timeout_s, 0.001))
        try:
            data = self._sock.recv(65536)
        except (TimeoutError, BlockingIOError):
            return b""
        except OSError as exc:
            raise LiveError(f"{self.url}: the connection failed ({exc})") from None
        if not data:
            self._eof = True
            return b"\n" if self._buffer else b""
        return data

    def close(self):
        super().close()
        self._sock.close()


def _bind_udp(url, host, port):
    """A UDP socket listening on ``host:port``: IPv4 (a name as ``localhost`` too), or IPv6 for an IPv6 address
    (``udp://[::1]:14550``, ``udp://[::]:14550``)."""
    sock = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sock.bind((host, port))
    except (OSError, UnicodeError, ValueError) as exc:
        sock.close()
        raise LiveError(
            f"{url}: cannot listen on UDP {host}:{port} ({exc}); is another program using the port?"
        ) from None
    return sock


# -- MAVLink ---------------------------------------------------------------------------------------------------------
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


# -- simulation ------------------------------------------------------------------------------------------------------
class SimSource(LiveSource):
    """A preset or a magcal CSV file played in real time.

    Sample ``k`` is always the same (deterministic): time ``t_k`` (``k / rate`` for a preset, the file's own times
    for a file unless ``rate`` is given) and the ``k``-th reading (modulo the length when looping).

    Parameters
    ----------
    url : str
    name : str
        A preset of :data:`magcal.data.simulation.PRESETS` or a path to a magcal CSV file.
    rate_hz : float, optional
        Samples per second (default 50 for a preset; the file's own times, or 10 Hz, for a file).
    n_samples : int
        Samples simulated for a preset.
    seed : int
        Seed of the preset's noise.
    loop : bool
        Start again at the end (times go on increasing); otherwise the source ends.
    speed : float
        Play faster (> 1) or slower than real time.
    """

    def __init__(self, url, name, rate_hz=None, n_samples=3000, seed=0, loop=False, speed=1.0):
        super().__init__(url)

        lo, hi = SIM_RATE_RANGE_HZ
        if rate_hz is not None and not lo <= float(rate_hz) <= hi:
            raise LiveError(f"{url}: rate={rate_hz!r}: give {lo:g} to {hi:g} samples per second")
        lo, hi = SIM_SPEED_RANGE
        if not lo <= float(speed) <= hi:
            raise LiveError(f"{url}: speed={speed!r}: give {lo:g} to {hi:g} (times real time)")
        pace = (50.0 if rate_hz is None else float(rate_hz)) * float(speed)
        if name in PRESETS and pace > SIM_MAX_SAMPLES_PER_S:
            raise LiveError(
                f"{url}: rate x speed = {pace:g} samples per second; at most {SIM_MAX_SAMPLES_PER_S:g} (lower rate or "
                "speed)"
            )
        if not 1 <= int(n_samples) <= SIM_MAX_SAMPLES:
            raise LiveError(f"{url}: n={n_samples!r}: give 1 to {SIM_MAX_SAMPLES:,} samples")
        if not 0 <= int(seed) <= SIM_MAX_SEED:
            raise LiveError(f"{url}: seed={seed!r}: give 0 to {SIM_MAX_SEED}")
        if name in PRESETS:
            rate = 50.0 if rate_hz is None else float(rate_hz)
            ds = simulate_timeseries(name, n_samples=int(n_samples), seed=int(seed), rate_hz=rate)
            times = np.arange(ds.n_samples) / rate
        else:
            if not os.path.exists(name):
                raise LiveError(f"{url}: {name!r} is neither a preset ({', '.join(PRESETS)}) nor a file")
            ds = read_csv(name)
            if rate_hz is not None:
                times = np.arange(ds.n_samples) / float(rate_hz)
            elif ds.time_s is not None:
                times = ds.time_s - ds.time_s[0]
            else:
                times = np.arange(ds.n_samples) / 10.0
        self.dataset = ds
        self._times = times
        self._period = float(times[-1] + (np.median(np.diff(times)) if times.size > 1 else 0.1))
        self.loop = bool(loop)
        self.speed = float(speed)
        self.n_sensors = ds.n_sensors
        self.has_temperature = ds.temperature_C is not None
        #: a recording's channels (attitude, gyro, position: :data:`magcal.data.lineformats.CHANNEL_UNITS`), played too
        self._channels = {
            k: np.asarray(ds.extra[k], dtype=float)
            for k in lineformats.CHANNEL_UNITS
            if k in ds.extra and np.asarray(ds.extra[k]).dtype.kind in "fiu"
        }
        self.channel_names = tuple(self._channels)
        self._k = 0
        self._start = None

    def sample(self, k):
        """Sample ``k`` as the source sends it: ``(t_s, readings (n_sensors, 3) nT, temperature or None)``."""
        n = self._times.size
        i = k % n
        t = float(self._times[i] + (k // n) * self._period)
        temp = None if self.dataset.temperature_C is None else float(self.dataset.temperature_C[i])
        return t, self.dataset.readings_nT[:, i], temp

    def _poll(self, deadline, max_samples):
        now = time.monotonic()
        if self._start is None:
            self._start = now
        n = self._times.size
        samples = []
        while len(samples) < max_samples:
            if not self.loop and self._k >= n:
                self.ended = True
                break
            t, r, temp = self.sample(self._k)
            i = self._k % n
            due = self._start + t / self.speed
            now = time.monotonic()
            if due > now:
                if samples or due > deadline:
                    if not samples:
                        time.sleep(max(0.0, deadline - now))
                    break
                time.sleep(due - now)
            samples.append((t, r, temp, {k: float(v[i]) for k, v in self._channels.items()}))
            self._k += 1
        return samples


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


# -- opening a URL ---------------------------------------------------------------------------------------------------
def _flag(params, name):
    return name in params and params[name] in ("", "1", "true", "yes", "on")


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


def open_source(url: str, **options) -> LiveSource:
    """Open a live source from its URL (see the module docstring); ``options`` override URL parameters.

    Raises
    ------
    LiveError
        A malformed URL, an unknown scheme or option, or a port that cannot be opened.
    """
    try:
        parsed = urllib.parse.urlsplit(str(url))
    except ValueError as exc:  # e.g. tcp://[::1 (an unclosed IPv6 bracket)
        raise LiveError(f"{url}: not a valid source URL ({exc})") from None
    scheme = parsed.scheme.lower()
    if scheme not in SCHEMES:
        raise LiveError(
            f"{url}: unknown source; use serial://DEVICE, udp://HOST:PORT, tcp://HOST:PORT or "
            "sim://PRESET (e.g. sim://chi2017?rate=50)"
        )
    params = {k: v[-1] for k, v in urllib.parse.parse_qs(parsed.query, keep_blank_values=True).items()}
    if options.get("template") is not None:  # a template given as an option replaces the URL's columns
        params.pop("columns", None)
    if options.get("columns") is not None:  # and the reverse
        params.pop("template", None)
    params.update({k: str(v) for k, v in options.items() if v is not None})
    known = {
        "baud",
        "columns",
        "sep",
        "units",
        "lsb",
        "prefix",
        "format",
        "mavlink",
        "message",
        "rate",
        "seed",
        "n",
        "loop",
        "speed",
        "raw_lsb_nT",
        "timeout",
        "template",
        "checksum",
        "reconnect",
        "attitude_max_dt",
    }
    unknown = sorted(set(params) - known)
    if unknown:
        raise LiveError(f"{url}: unknown option(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}")
    mavlink = _flag(params, "mavlink") or params.get("format", "").lower() == "mavlink"

    def number(name, default, kind=float, bounds=None):
        try:
            value = kind(params[name]) if name in params else default
        except (ValueError, OverflowError):
            what = "a whole number" if kind is int else "a number"  # 14551.5 is refused, never truncated
            raise LiveError(f"{url}: {name}={params[name][:40]!r} is not {what}") from None
        if bounds is not None and value is not None and not bounds[0] <= value <= bounds[1]:
            raise LiveError(f"{url}: {name}={params[name][:40]!r}: give {bounds[0]:g} to {bounds[1]:g}")
        return value

    def parser():
        check = params.get("checksum", "on").lower()
        if check not in ("on", "off", "1", "0", "true", "false", "yes", "no", ""):
            raise LiveError(f"{url}: checksum={params['checksum'][:20]!r}: give checksum=on or checksum=off")
        try:
            return LineParser(
                params.get("columns") or None,
                params.get("sep") or None,
                params.get("units", "nT"),
                params.get("lsb"),
                params.get("prefix"),
                template=params.get("template") or None,
                checksum=check not in ("off", "0", "false", "no"),
            )
        except MagcalError as exc:
            raise LiveError(f"{url}: {exc}") from None

    attitude_dt = number("attitude_max_dt", 0.2, float, (0.001, 10.0))

    if scheme == "sim":
        name = (parsed.netloc + parsed.path) if parsed.netloc else parsed.path
        return SimSource(
            url,
            urllib.parse.unquote(name),
            rate_hz=number("rate", None),
            n_samples=number("n", 3000, int),
            seed=number("seed", 0, int),
            loop=_flag(params, "loop"),
            speed=number("speed", 1.0),
        )
    if scheme == "serial":
        device = urllib.parse.unquote(parsed.path if not parsed.netloc else parsed.netloc + parsed.path)
        baud = number("baud", 115200, int, BAUD_RANGE)
        reconnect_s = number("reconnect", RECONNECT_DEFAULT_S, float, RECONNECT_RANGE_S)
        if mavlink:
            return MavlinkSource(
                url,
                device,
                params.get("message"),
                baud,
                number("raw_lsb_nT", 100.0, float, (1e-6, 1e9)),
                attitude_dt,
                reconnect_s=reconnect_s,
            )
        return SerialSource(url, device, baud, parser(), reconnect_s=reconnect_s)
    try:
        host, port = parsed.hostname, parsed.port
    except ValueError as exc:  # a port that is not a number, or beyond 65535
        raise LiveError(f"{url}: {exc}; give the address as {scheme}://HOST:PORT with a port of 1 to 65535") from None
    if not host or not port:
        raise LiveError(f"{url}: give the address as {scheme}://HOST:PORT (e.g. {scheme}://127.0.0.1:14550)")
    if mavlink:  # a TCP connection that closes is connected again; UDP is connectionless and needs nothing
        device = mavlink_address(url, scheme, host, port)
        return MavlinkSource(
            url,
            device,
            params.get("message"),
            raw_lsb_nT=number("raw_lsb_nT", 100.0, float, (1e-6, 1e9)),
            attitude_max_dt_s=attitude_dt,
            reconnect_s=number("reconnect", RECONNECT_DEFAULT_S, float, RECONNECT_RANGE_S),
            connect_timeout_s=number("timeout", 5.0, float, TIMEOUT_RANGE_S),
        )
    if params.get("format", "lines").lower() != "lines":
        raise LiveError(f"{url}: format={params['format']!r}: use format=lines or mavlink")
    if scheme == "udp":
        return UdpLineSource(url, host, port, parser())
    return TcpLineSource(url, host, port, parser(), connect_timeout_s=number("timeout", 5.0, float, TIMEOUT_RANGE_S))


# -- recording -------------------------------------------------------------------------------------------------------
class Recorder:
    """Append live samples to a magcal CSV file, crash-safe.

    The header (metadata lines and column names) is written when the first chunk fixes the layout. Samples are
    kept in memory and written at :meth:`flush` (called by :meth:`write` at least every ``flush_interval_s``):
    whole lines only, each ``write`` system call confined to one page of the file so that a kill cannot leave
    part of one (a line that would cross a page boundary is preceded by a blank padding line, which readers
    skip), then ``fsync``. A recording cut at any moment reopens with :func:`magcal.read_csv` holding every
    sample of the last flush.

    A flush that cannot write (a full disk, an I/O error) stops the recording: the file is cut back to the end of
    the last flush (whole lines, every one of them counted in :attr:`n_written`), the samples not written are
    counted in :attr:`n_lost`, :attr:`failure` says why (``the disk is full`` for ``ENOSPC``) and a
    :class:`LiveError` with that text is raised, once; a later :meth:`write` raises it again, and :meth:`flush`
    and :meth:`close` do not (a caller that closes the recording in a ``finally`` is not interrupted). A failure
    of the flush that :meth:`close` makes is kept in :attr:`failure`, and raised when a ``with`` block is left.

    Parameters
    ----------
    path : str or os.PathLike
        The CSV file; an existing file is refused (a recording is never overwritten).
    metadata : dict, optional
        ``# key: value`` lines (``units: nT`` is added).
    flush_interval_s : float
        Longest time between flushes to disk (s).
    """

    def __init__(self, path, metadata=None, flush_interval_s=1.0):
        self.path = os.fspath(path)
        self.metadata = dict(metadata or {})
        self.flush_interval_s = float(flush_interval_s)
        self.n_written = 0  # samples on disk (flushed)
        self.n_pending = 0
        self.n_refused = 0  # samples with a value NaN, infinite or beyond MAX_ABS_VALUE: never written
        self.n_lost = 0  # samples received but not written: the recording stopped before (``failure``)
        #: Why the recording stopped (a flush could not write; the file's name first), or None while it works.
        self.failure: str | None = None
        #: Whether it stopped because the disk is full (``ENOSPC``) or the user's disk quota is used up.
        self.disk_full = False
        self._pending = []
        self._fd = None
        self._columns = None
        self._channels = ()
        self._last_flush = time.monotonic()
        self._page = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096
        try:
            self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0), 0o644)
        except FileExistsError:
            raise LiveError(
                f"{self.path}: already exists; a recording is never overwritten: choose another name"
            ) from None
        except OSError as exc:
            raise LiveError(f"{self.path}: cannot create the recording ({exc.strerror or exc})") from None
        self._offset = 0

    def _header(self, chunk):
        cols = ["t"] + [f"s{i + 1}{a}" for i in range(chunk.n_sensors) for a in SENSOR_AXES]
        if chunk.temperature_C is not None:
            cols.append("temp")
        cols += list(chunk.channels)  # roll_deg, gyro_x_dps, lat, ...: NaN written as nan where a sample has none
        self._columns = cols
        self._channels = tuple(chunk.channels)
        meta = {
            "recorded_by": "magcal.data.live",
            "started_utc": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        }
        meta.update(self.metadata)
        meta["units"] = "nT"
        return (metadata_text(meta) + ",".join(cols) + "\n").encode("utf-8")

    def write(self, chunk: LiveChunk) -> None:
        """Add the chunk's samples; flushes to disk when ``flush_interval_s`` has passed since the last flush."""
        if self.failure is not None:
            raise LiveError(self.failure)
        if self._fd is None:
            raise LiveError(f"{self.path}: the recording is closed")
        chunk = self._usable(chunk) if len(chunk) else chunk
        if len(chunk):
            if self._columns is None:
                self._pending.append(self._header(chunk))
            elif (
                (chunk.temperature_C is not None) != ("temp" in self._columns)
                or 3 * chunk.n_sensors != sum(c[0] == "s" and c[1:2].isdigit() for c in self._columns)
                or tuple(chunk.channels) != self._channels
            ):
                raise LiveError(
                    f"{self.path}: the samples changed layout (sensors, temperature or channels) mid-recording"
                )
            parts = [format_column(chunk.time_s)]
            for i in range(chunk.n_sensors):
                parts += [format_column(chunk.readings_nT[i, :, k]) for k in range(3)]
            if chunk.temperature_C is not None:
                parts.append(format_column(chunk.temperature_C))
            parts += [format_column(np.asarray(v, dtype=float)) for v in chunk.channels.values()]
            self._pending.append(("\n".join(",".join(row) for row in zip(*parts)) + "\n").encode("ascii"))
            self.n_pending += len(chunk)
        if time.monotonic() - self._last_flush >= self.flush_interval_s:
            self.flush()

    def _usable(self, chunk):
        """The chunk without the samples a reader would refuse (the one rule: NaN, infinite or beyond
        :data:`magcal.data.dataset.MAX_ABS_VALUE`, time included), counted in :attr:`n_refused`."""
        bad = bad_values(chunk.time_s) | bad_values(chunk.readings_nT, axis=(0, 2))
        if chunk.temperature_C is not None:
            bad |= bad_values(chunk.temperature_C)
        for v in chunk.channels.values():  # a channel may be NaN (no value), never infinite or huge
            v = np.asarray(v, dtype=float)
            bad |= bad_values(v) & ~np.isnan(v)
        if not bad.any():
            return chunk
        self.n_refused += int(bad.sum())
        return chunk.subset(~bad)

    def _write_page_confined(self, data: bytes) -> None:
        """Write whole lines so that no ``write`` call spans a page boundary of the file."""
        page = self._page
        batch = bytearray()
        for line in data.splitlines(keepends=True):
            pos = self._offset + len(batch)
            if batch and (len(line) > page - pos % page or pos % page == 0):
                self._put(bytes(batch))  # the batch ends inside (or exactly at the end of) its page
                batch = bytearray()
            room = page - self._offset % page
            if not batch and len(line) > room and room < page and len(line) <= page:
                self._put(b" " * (room - 1) + b"\n")  # a blank line up to the page boundary; readers skip it
            batch += line
        if batch:
            self._put(bytes(batch))

    def _put(self, data):
        view = memoryview(data)
        while view:
            n = os.write(self._fd, view)
            self._offset += n
            view = view[n:]

    def flush(self) -> int:
        """Write the pending samples as whole lines and ``fsync``; returns the samples now on disk.

        Raises
        ------
        LiveError
            The samples could not be written (:attr:`failure`; the recording stops, the file keeps every sample
            of the flushes before).
        """
        if self._fd is None or self.failure is not None:
            return self.n_written
        if self._pending:
            start = self._offset
            try:
                self._write_page_confined(b"".join(self._pending))
                os.fsync(self._fd)
            except OSError as exc:
                self._fail(exc, start)
            self._pending = []
            self.n_written += self.n_pending
            self.n_pending = 0
        self._last_flush = time.monotonic()
        return self.n_written

    def _fail(self, exc: OSError, start: int):
        """Stop the recording after a flush that could not write from byte ``start``: cut the file back there (no
        part of a line left), count the samples not written, and raise :class:`LiveError` saying why."""
        import errno

        try:
            os.ftruncate(self._fd, start)  # a full disk still lets a file shrink
        except OSError:
            pass
        self._offset = start
        self._pending = []
        self.n_lost += self.n_pending
        self.n_pending = 0
        self.disk_full = exc.errno in (errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC))
        if exc.errno == errno.ENOSPC:
            why = "the disk is full"
        elif self.disk_full:
            why = "the disk quota is used up"
        else:
            why = f"cannot write the recording ({exc.strerror or type(exc).__name__})"
        self.failure = (
            f"{self.path}: {why}: the recording stopped with {self.n_written} samples on disk and the "
            f"{self.n_lost} received since not written. "
            + ("Free some space, then record again" if self.disk_full else "Check the disk, then record again")
        )
        raise LiveError(self.failure) from None

    def close(self) -> None:
        """Flush and close the file. Never raises: a failure of this last flush is kept in :attr:`failure` (the
        recording is closed either way)."""
        if self._fd is not None:
            try:
                self.flush()
            except LiveError:
                pass  # kept in self.failure
            finally:
                fd, self._fd = self._fd, None
                try:
                    os.close(fd)
                except OSError as exc:  # a network file system reports a failed write at the latest here
                    if self.failure is None:
                        self.failure = f"{self.path}: cannot close the recording ({exc.strerror or exc})"

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        failed = self.failure
        self.close()
        if exc_type is None and failed is None and self.failure is not None:
            raise LiveError(self.failure)  # the last flush failed: the block's caller must hear it


def record(
    url_or_source, path, duration_s=None, max_samples=None, flush_interval_s=1.0, on_flush=None, stop=None
) -> SourceStats:
    """Record a live source into a magcal CSV until ``duration_s``, ``max_samples``, the source's end or ``stop``.

    Parameters
    ----------
    url_or_source : str or LiveSource
    path : str or os.PathLike
        The recording (must not exist).
    duration_s : float, optional
        Stop after this many seconds.
    max_samples : int, optional
        Stop after this many samples.
    flush_interval_s : float
        Longest time between flushes to disk (s).
    on_flush : callable, optional
        Called with the number of samples on disk after each flush that wrote some.
    stop : threading.Event, optional
        Set it to stop.

    Returns
    -------
    SourceStats
    """
    source = open_source(url_or_source) if isinstance(url_or_source, str) else url_or_source
    end = None if duration_s is None else time.monotonic() + float(duration_s)
    try:
        with Recorder(path, {"source": source.url}, flush_interval_s) as rec:
            written = 0
            while not (stop is not None and stop.is_set()):
                remaining = None if end is None else end - time.monotonic()
                if remaining is not None and remaining <= 0:
                    break
                want = 10_000 if max_samples is None else max_samples - rec.n_written - rec.n_pending
                if want <= 0:
                    break
                wait = min(0.25, max(flush_interval_s, 0.01), 0.25 if remaining is None else max(remaining, 0.01))
                chunk = source.read(timeout_s=wait, max_samples=want)
                rec.write(chunk)
                if on_flush is not None and rec.n_written != written:
                    written = rec.n_written
                    on_flush(written)
                if source.ended and not len(chunk):
                    break
            held = source.drain()  # what the source still held
            if max_samples is not None:
                held = held.subset(slice(0, max(0, max_samples - rec.n_written - rec.n_pending)))
            rec.write(held)
            rec.flush()
            if on_flush is not None and rec.n_written != written:
                on_flush(rec.n_written)
    finally:
        if isinstance(url_or_source, str):
            source.close()
    return source.stats


# -- a live session for viewers ----------------------------------------------------------------------------------------
class LiveSession:
    """A source read in a background thread, recorded to disk and kept in memory for viewers.

    The workbench's live view is built on it: several browsers :meth:`subscribe` to the same session, the fit
    reruns on :meth:`dataset`, and :meth:`pause`, :meth:`resume`, :meth:`stop` act on it.

    Parameters
    ----------
    url_or_source : str or LiveSource
    path : str or os.PathLike, optional
        The recording; None keeps the samples in memory only.
    flush_interval_s : float
        Longest time between flushes to disk (s).
    listeners : sequence of callable, optional
        Subscribed before the first sample (see :meth:`subscribe`).
    """

    def __init__(self, url_or_source, path=None, flush_interval_s=1.0, listeners=()):
        self.source = open_source(url_or_source) if isinstance(url_or_source, str) else url_or_source
        self.path = None if path is None else os.fspath(path)
        self._recorder = None if path is None else Recorder(path, {"source": self.source.url}, flush_interval_s)
        self._chunks = []
        self._lock = threading.Lock()
        self._listeners = list(listeners)
        self._paused = threading.Event()
        self._stop = threading.Event()
        self.error = None
        self._thread = threading.Thread(target=self._run, name="magcal-live", daemon=True)
        self._thread.start()

    def _run(self):
        try:
            while not self._stop.is_set():
                chunk = self.source.read(timeout_s=0.2)
                if self._paused.is_set():  # paused: what arrives is dropped, and counted
                    continue
                if len(chunk):
                    with self._lock:
                        self._chunks.append(chunk)
                if self._recorder is not None:
                    self._recorder.write(chunk)
                if len(chunk):
                    for listener in list(self._listeners):
                        try:
                            listener(chunk)
                        except Exception as exc:  # a viewer's failure must not stop the recording
                            warnings.warn(f"live listener failed: {exc}", RuntimeWarning, stacklevel=1)
                if self.source.ended and not len(chunk):
                    break
            if not self._paused.is_set():
                self._keep(self.source.drain())  # what the source still held (a sample waiting for its attitude)
        except MagcalError as exc:
            self.error = str(exc)
        except Exception as exc:  # anything else ends the session too, and is reported rather than lost
            self.error = f"{type(exc).__name__}: {exc}"
        finally:
            if self._recorder is not None:
                self._recorder.close()
            self.source.close()

    def _keep(self, chunk):
        if not len(chunk):
            return
        with self._lock:
            self._chunks.append(chunk)
        if self._recorder is not None:
            self._recorder.write(chunk)

    @property
    def running(self) -> bool:
        """True while the thread reads the source."""
        return self._thread.is_alive()

    @property
    def n_samples(self) -> int:
        with self._lock:
            return sum(len(c) for c in self._chunks)

    @property
    def n_recorded(self) -> int:
        """Samples flushed to the recording."""
        return 0 if self._recorder is None else self._recorder.n_written

    def dataset(self) -> Dataset | None:
        """Everything received so far as a :class:`Dataset` (None before the first sample)."""
        with self._lock:
            chunk = concatenate_chunks(self._chunks)
            if chunk is not None and len(self._chunks) > 1:
                self._chunks = [chunk]
        return None if chunk is None else chunk.to_dataset(source=self.path or self.source.url)

    def subscribe(self, listener) -> None:
        """Call ``listener(chunk)`` (in the session's thread) for every chunk received from now on."""
        self._listeners.append(listener)

    def pause(self) -> None:
        """Stop keeping samples (the source is still read, so nothing piles up)."""
        self._paused.set()

    def resume(self) -> None:
        self._paused.clear()

    @property
    def paused(self) -> bool:
        return self._paused.is_set()

    def stop(self, timeout_s=5.0) -> None:
        """Stop reading, flush and close the recording (waits at most ``timeout_s``)."""
        self._stop.set()
        self._thread.join(timeout_s)
