"""No silent data loss on a full disk (item 6): a recording that cannot be written stops with every
sample of its last flush on disk, says "the disk is full" and counts what was lost, with no traceback; the
workbench shows a failed autosave or recording until it is resolved (not a message the next one overwrites),
never with the server's paths, and Stop says how many samples were recorded and where.

The full disk is simulated: writes to the files under test fail with ``ENOSPC`` (after a partial write, as a
real disk does), or the session's writer raises it.
"""

from __future__ import annotations

import errno
import os
import threading
import time
from pathlib import Path

import numpy as np
import pytest

import magcal
from magcal.data.live import LiveChunk, LiveError, LiveSession, Recorder, SimSource

NO_SPACE = os.strerror(errno.ENOSPC)


class FullDisk:
    """``os.write`` to the files opened (``os.open``) under ``where`` fails with ENOSPC once ``room`` bytes have
    gone to them, the last write cut short; ``full = False`` lets every write through until set again."""

    def __init__(self, monkeypatch, where, room=0, full=True):
        self.where, self.room, self.full = os.fspath(where), room, full
        self.fds: set = set()
        self.refused = 0
        real_open, real_write, real_close = os.open, os.write, os.close

        def opened(path, flags, *args, **kwargs):
            fd = real_open(path, flags, *args, **kwargs)
            if os.fspath(path).startswith(self.where):
                self.fds.add(fd)
            return fd

        def write(fd, data):
            if fd not in self.fds or not self.full:
                return real_write(fd, data)
            if self.room <= 0:
                self.refused += 1
                raise OSError(errno.ENOSPC, NO_SPACE)
            n = min(len(data), self.room)
            self.room -= n
            return real_write(fd, bytes(data[:n]))

        def close(fd):
            self.fds.discard(fd)
            return real_close(fd)

        monkeypatch.setattr(os, "open", opened)
        monkeypatch.setattr(os, "write", write)
        monkeypatch.setattr(os, "close", close)


def _chunk(start, n, rate=50.0):
    src = SimSource("sim://chi2017", "chi2017", rate_hz=rate)
    samples = [src.sample(k) for k in range(start, start + n)]
    return LiveChunk(
        np.array([s[0] for s in samples]), np.stack([s[1] for s in samples], axis=1), np.array([s[2] for s in samples])
    )


def _wait(condition, timeout_s=30.0, step_s=0.05):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(step_s)
    return bool(condition())


# -- the engine's recorder -----------------------------------------------------------------------------------------
def test_a_recording_that_fills_the_disk_keeps_its_last_flush_and_says_the_disk_is_full(tmp_path, monkeypatch):
    path = tmp_path / "rec.csv"
    first = _chunk(0, 100)
    rec = Recorder(path, flush_interval_s=0.0)
    rec.write(first)  # flushed at once: header and 100 lines
    size = path.stat().st_size
    disk = FullDisk(monkeypatch, tmp_path, room=1000)  # the next flush gets 1000 bytes: some lines and a part
    disk.fds.add(rec._fd)
    with pytest.raises(LiveError, match=r"rec\.csv: the disk is full: the recording stopped with 100 samples on disk"):
        rec.write(_chunk(100, 100))
    assert rec.disk_full and rec.n_written == 100 and rec.n_lost == 100 and "the 100 received since" in rec.failure
    assert path.stat().st_size == size  # cut back to the last flush: no line of the failed one, whole or in part
    with pytest.raises(LiveError, match="the disk is full"):  # the recording has stopped
        rec.write(_chunk(200, 10))
    rec.close()  # closing after the failure raises nothing
    ds = magcal.read_csv(path)
    np.testing.assert_array_equal(ds.time_s, first.time_s)
    np.testing.assert_allclose(ds.readings_nT, first.readings_nT)


def test_a_recordings_last_flush_failing_at_close_is_raised_by_the_with_block(tmp_path, monkeypatch):
    path = tmp_path / "rec.csv"
    FullDisk(monkeypatch, path)
    with pytest.raises(LiveError, match="the disk is full: the recording stopped with 0 samples on disk and the 30"):
        with Recorder(path) as rec:
            rec.write(_chunk(0, 30))  # kept for the flush at close
    assert rec.n_lost == 30 and path.stat().st_size == 0
    again = Recorder(tmp_path / "other.csv", flush_interval_s=0.0)
    FullDisk(monkeypatch, tmp_path / "other.csv").fds.add(again._fd)
    with pytest.raises(LiveError):
        again.write(_chunk(0, 5))
    again.close()  # a caller's ``finally`` is not interrupted


def test_a_live_session_on_a_full_disk_ends_with_the_reason_and_no_traceback(tmp_path, monkeypatch):
    """The session's thread records; a full disk ends it with its error set and the source closed, instead of an
    exception escaping the thread (a traceback on the terminal) from the recorder's second try at close."""
    escaped = []
    monkeypatch.setattr(threading, "excepthook", lambda args: escaped.append(args.exc_value))
    FullDisk(monkeypatch, tmp_path)
    session = LiveSession("sim://chi2017?rate=200", tmp_path / "live.csv", flush_interval_s=0.2)
    try:
        assert _wait(lambda: not session.running, 30)
        assert session.n_samples > 0 and session.n_recorded == 0
        assert session.error and "the disk is full" in session.error
        assert f"the {session.n_samples} received since not written" in session.error
    finally:
        session.stop()
    assert escaped == []


# -- the workbench's autosave --------------------------------------------------------------------------------------
def _no_space(path, data):
    raise OSError(errno.ENOSPC, NO_SPACE, os.fspath(path))


def _page(wb) -> str:
    p = wb.panels
    return "\n".join(w.content for w in (getattr(p, "alarm", p.status), p.status, p.message, p.live_status))


def test_a_failed_autosave_stays_shown_until_an_autosave_succeeds(bench, tmp_path, monkeypatch, capsys):
    from magcal_workbench import session as wsession

    wb = bench()
    ctrl, saved = wb.ctrl, tmp_path / "sessions" / wb.ctrl.session_id / "session.json"
    monkeypatch.setattr(wsession, "write_json_atomic", _no_space)  # the autosave streams its document
    ctrl.select([1, 2, 3])  # a change: its autosave fails, then the change says what it did
    assert "Autosave failed: the disk is full" in _page(wb)
    ctrl.select([4])  # another change, another message: the warning is still shown
    ctrl.say("something else")
    assert "Autosave failed: the disk is full" in _page(wb) and "something else" in wb.panels.message.content
    assert wb.panels.alarm.visible
    assert "changes since" in wb.panels.alarm.content
    assert str(tmp_path) not in _page(wb) and "Errno" not in _page(wb)
    assert "[1, 2, 3]" not in saved.read_text()  # indeed not saved
    monkeypatch.undo()  # space freed: the next change saves everything, and the warning goes
    ctrl.select([5])
    assert "Autosave failed" not in _page(wb) and not wb.panels.alarm.visible
    assert wb.ctrl.store.load(ctrl.session_id).selection.rejected_indices.tolist() == [1, 2, 3, 4, 5]
    assert "Traceback" not in capsys.readouterr().err


def test_data_opened_on_a_full_disk_open_unsaved_and_say_so(bench, tmp_path, monkeypatch):
    from magcal_workbench import session as wsession

    monkeypatch.setattr(wsession, "write_bytes_atomic", _no_space)
    wb = bench()  # the session's copy of the data cannot be written: the data open all the same
    assert wb.ctrl.dataset.n_samples == 300 and wb.ctrl.session_id is None
    assert "This session is not saved: the disk is full" in _page(wb) and wb.panels.alarm.visible
    assert str(tmp_path) not in _page(wb)
    wb.ctrl.select([1])
    assert "This session is not saved" in _page(wb)


# -- the workbench's live recording ----------------------------------------------------------------------------------
@pytest.mark.parametrize("first_flush", ["fails", "written"])
def test_a_live_recording_on_a_full_disk_is_shown_until_stop_which_says_what_was_kept(
    bench, tmp_path, monkeypatch, capsys, first_flush
):
    """The audit's case: 530 samples arrived, the disk full; the page said nothing useful and Stop said "nothing
    was recorded". Now the page says the recording stopped because the disk is full until Stop, with the
    recording named inside the session folder, and Stop says how many samples are on disk (none, or those of
    the flushes before) and where."""
    escaped = []
    monkeypatch.setattr(threading, "excepthook", lambda args: escaped.append(args.exc_value))
    wb = bench()
    folder = Path(wb.store.root) / "recordings"
    disk = FullDisk(monkeypatch, folder, full=first_flush == "fails")
    live = wb.livectl.start("sim://chi2017?rate=200&n=100000")
    if first_flush == "written":
        assert _wait(lambda: live.session.n_recorded > 0, 30)
        disk.full = True
    assert _wait(lambda: not live.session.running, 30)
    kept = live.session.n_recorded
    assert live.n_samples > kept and (kept > 0) == (first_flush == "written")
    wb.panels.refresh_live()
    assert "the disk is full" in _page(wb) and str(tmp_path) not in _page(wb)
    assert wb.panels.alarm.visible and "The live recording stopped" in wb.panels.alarm.content
    assert "the disk is full" in wb.panels.alarm.content and f"recordings/{live.path.name}" in wb.panels.alarm.content
    wb.ctrl.say("another message")
    assert "the disk is full" in _page(wb)  # still shown
    assert str(tmp_path) not in _page(wb)
    wb.handle(lambda e: wb.livectl.do_live_stop(e), None)  # the page's Stop button
    assert wb.worker.wait(60)
    assert wb.ui.wait(30)
    text = wb.panels.message.content
    assert f"recordings/{live.path.name}" in text and "the disk is full" in text and str(tmp_path) not in text
    if kept:
        assert f"recorded {kept} samples in" in text and f"of the {live.n_samples} received" in text
        assert wb.ctrl.dataset.n_samples == kept == magcal.read_csv(live.path).n_samples  # what is on disk, opened
    else:
        assert "0 samples on disk" in text and f"the {live.n_samples} received since not written" in text
        assert "nothing to open" in text and "no sample arrived" not in text
    assert not wb.panels.alarm.visible  # stopped: resolved
    assert escaped == [] and "Traceback" not in capsys.readouterr().err
