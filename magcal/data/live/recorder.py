"""Keeping what a live source sends: :class:`Recorder` appends the samples to a magcal CSV file, crash-safe (whole
lines, ``fsync`` at least every ``flush_interval_s``); :func:`record` records a URL for a time;
:class:`LiveSession` runs a source and a recorder on a thread with pause, resume, stop and listeners."""

from __future__ import annotations

import datetime as _dt
import os
import threading
import time

import numpy as np

from magcal.core.errors import MagcalError
from magcal.core.notes import Note
from magcal.data.dataset import SENSOR_AXES, Dataset, bad_values
from magcal.data.io import format_column, metadata_text
from magcal.data.live.registry import open_source
from magcal.data.live.source import LiveChunk, LiveError, SourceStats, concatenate_chunks


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

    Attributes
    ----------
    error : str or None
        Why the session ended early (the source failed), or None.
    notes : list of Note
        What went wrong without ending it: a listener (a viewer) that raised, at most 20 of them.
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
        self.notes: list[Note] = []  # what went wrong without ending the session (a viewer's failure)
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
                        except Exception as exc:  # a viewer's failure must not stop the recording: kept as a note
                            with self._lock:
                                if len(self.notes) < 20:  # a listener failing on every chunk says it once or so
                                    self.notes.append(Note(f"live listener failed: {exc}", RuntimeWarning, "live"))
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
