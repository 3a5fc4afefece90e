"""The live-source interface: :class:`LiveSource` (``read``, ``drain``, iteration, ``close``), the samples that
arrived together (:class:`LiveChunk`), what a source counted (:class:`SourceStats`), :class:`LiveError`, and what
the sources share: a device's clock followed across its restarts and a port opened again when it is lost."""

from __future__ import annotations

import collections
import time
from dataclasses import dataclass, field

import numpy as np

from magcal.core.errors import MagcalError
from magcal.data.dataset import BAD_VALUE_TEXT, MAX_ABS_VALUE, Dataset, bad_values

#: A device's time stamps going back by more than this (s) mean its clock restarted (a reboot); later samples are
#: shifted to follow on. A smaller step back is a bad sample.
CLOCK_RESET_S = 1.0

#: Longest total wait for a lost serial port to come back (s) unless ``reconnect`` says otherwise, the bounds of
#: ``reconnect``, and the longest interval between two tries.
RECONNECT_DEFAULT_S = 30.0
RECONNECT_RANGE_S = (0.0, 3600.0)
RECONNECT_MAX_INTERVAL_S = 2.0


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
