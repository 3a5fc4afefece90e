"""A source of text lines from a byte stream (:class:`LineSource`, also importable by its old name ``_LineSource``):
lines cut at their ends and bounded in length, parsed by a :class:`~magcal.data.live.parser.LineParser`, a boot
banner skipped, a device's clock followed. The serial and network sources are made of it, and so may a source
written outside magcal (CONTRIBUTING.md)."""

from __future__ import annotations

import collections
import re
import time

from magcal.data.dataset import bad_values
from magcal.data.live.source import LiveSource, _DeviceClock

#: Longest text line accepted (bytes); longer ones are counted as bad and skipped.
MAX_LINE_BYTES = 4096


class LineSource(LiveSource):
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


#: The name the tests and older code import.
_LineSource = LineSource
