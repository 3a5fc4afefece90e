"""Nothing left after a kill (item 5): a ``magcal diagnose --workers N`` or a Dask ``magcal apply`` killed
with SIGKILL leaves no process running, and what it could not remove (a shared-memory segment, a hidden work
folder) is removed by the next run, which names it.

Each killed command runs in a session of its own, so that every process it started (the fork server, the resource
tracker, the workers) is found by its session id in /proc after the kill, wherever it was reparented. Records are
small and every wait is bounded.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

import magcal
from magcal.core import leftovers
from magcal.data import io as mio

pytestmark = pytest.mark.skipif(
    not (sys.platform.startswith("linux") and os.path.isdir("/proc") and os.path.isdir("/dev/shm")),
    reason="processes are found in /proc and segments in /dev/shm (Linux)",
)

ENV = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}


def _session(sid: int) -> list[int]:
    """The processes of session ``sid`` still running (zombies left out)."""
    out = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat", "rb") as fh:
                fields = fh.read().rsplit(b")", 1)[1].split()
        except OSError:
            continue
        if int(fields[3]) == sid and fields[0] not in (b"Z", b"X"):
            out.append(int(entry))
    return out


def _wait(condition, timeout_s: float, step_s: float = 0.05) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(step_s)
    return bool(condition())


def _kill_session(sid: int) -> None:
    """Kill what is left of a test's own session (each process by its id), so a failing test leaves nothing: the
    resource tracker last, so that it can first unlink what the others registered with it."""

    def tracker(pid):
        try:
            with open(f"/proc/{pid}/cmdline", "rb") as fh:
                return b"resource_tracker" in fh.read()
        except OSError:
            return False

    for last in (False, True):
        for pid in _session(sid):
            if tracker(pid) == last:
                try:
                    os.kill(pid, signal.SIGKILL)
                except OSError:
                    pass
        if not last:
            _wait(lambda: not _session(sid), 5)


def _ended_pid() -> int:
    """The number of a process that has ended (started and reaped here)."""
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


@pytest.fixture
def env_tmp():
    """The commands' environment with a temporary folder of the test's own (``TMPDIR``, in /tmp: short enough
    for the fork server's socket): what a killed command leaves there (``pymp-*``, a run folder, Dask's scratch
    space) is its own."""
    tmp = Path(tempfile.mkdtemp(prefix="kill-"))
    try:
        yield {**ENV, "TMPDIR": str(tmp)}, tmp
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _segments(pid: int) -> list[str]:
    return sorted(n for n in os.listdir("/dev/shm") if n.startswith(f"magcal_{pid}_"))


# -- a worker follows its owner ------------------------------------------------------------------------------------
WORKER = """
import os, sys, time
if sys.argv[2] == "poll":
    del os.pidfd_open  # the portable watch: a thread that looks every half second
from magcal.core import leftovers
print(leftovers.exit_with(int(sys.argv[1])), flush=True)
time.sleep(120)
"""


@pytest.mark.parametrize("how", ["pidfd", "poll"])
def test_a_worker_ends_when_the_process_that_started_it_ends(how):
    if how == "pidfd" and not hasattr(os, "pidfd_open"):
        pytest.skip("no pidfd_open here")
    owner = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
    worker = subprocess.Popen(
        [sys.executable, "-c", WORKER, str(owner.pid), how], stdout=subprocess.PIPE, text=True, env=ENV
    )
    try:
        assert worker.stdout is not None and worker.stdout.readline().strip() == how
        time.sleep(0.3)
        assert worker.poll() is None  # the owner runs: the worker waits
        owner.kill()
        owner.wait()
        worker.wait(timeout=5)  # the worker is not the owner's child: only its watch can end it
        assert worker.returncode == 1
    finally:
        for p in (owner, worker):
            if p.poll() is None:
                p.kill()
                p.wait()


def test_a_worker_whose_owner_has_already_ended_exits_at_once():
    worker = subprocess.run(
        [sys.executable, "-c", WORKER, str(_ended_pid()), "pidfd"], capture_output=True, text=True, env=ENV, timeout=60
    )
    assert worker.returncode == 1 and worker.stdout == ""


# -- magcal diagnose killed ----------------------------------------------------------------------------------------
def test_a_killed_diagnosis_leaves_no_process_and_no_shared_memory(tmp_path, env_tmp):
    """SIGKILL of ``magcal diagnose --workers 4`` while its fits run in worker processes: within a few seconds no
    worker, no fork server, no resource tracker runs, and its segment is gone from /dev/shm."""
    path = tmp_path / "four.csv"
    env, tmp = env_tmp
    # 4 x 12 500 readings: with 4 workers the fits go to worker processes (PROCESS_MIN_READINGS_MANY)
    mio.write_csv(path, magcal.simulate_timeseries("chi2017", n_samples=12_500, seed=7, rate_hz=10.0))
    proc = subprocess.Popen(
        [sys.executable, "-m", "magcal", "diagnose", str(path), "--workers", "4"],
        start_new_session=True,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        env=env,
    )
    sid = proc.pid
    try:
        # the segment made and a worker forked: the caller, the resource tracker, the fork server, the workers
        started = _wait(lambda: _segments(sid) and len(_session(sid)) >= 4 or proc.poll() is not None, 120)
        assert started and proc.poll() is None, "the diagnosis ended before its workers were seen"
        segments = _segments(sid)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
        assert _wait(lambda: not _session(sid), 15), f"still running after the kill: {_session(sid)}"
        assert _wait(lambda: not _segments(sid), 5), f"left in /dev/shm: {segments}"
        assert _wait(lambda: not list(tmp.iterdir()), 5), f"left in TMPDIR: {list(tmp.iterdir())}"
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        _kill_session(sid)
        for name in _segments(sid):
            os.unlink(os.path.join("/dev/shm", name))
        if proc.stderr is not None:
            proc.stderr.close()


def test_a_killed_diagnosis_with_only_its_fork_server_started_leaves_no_temporary_folder(tmp_path, env_tmp):
    """SIGKILL of ``magcal diagnose --workers 2`` while it reads a file large enough for its fork server to start
    early: the fork server ends, and with it the run folder that held its socket (where multiprocessing would
    have left ``pymp-*`` for ever)."""
    path = tmp_path / "big.csv"
    env, tmp = env_tmp
    # 5 MB: the file's size says more than 400 000 readings, so the fork server starts while it is read
    mio.write_csv(path, magcal.simulate_timeseries("chi2017", n_samples=15_000, seed=7, rate_hz=10.0))
    proc = subprocess.Popen(
        [sys.executable, "-m", "magcal", "diagnose", str(path), "--workers", "2"],
        start_new_session=True,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        env=env,
    )
    sid = proc.pid
    try:
        started = _wait(lambda: list(tmp.iterdir()) and len(_session(sid)) >= 3 or proc.poll() is not None, 120)
        assert started and proc.poll() is None, "the diagnosis ended before its fork server was seen"
        (run,) = tmp.iterdir()
        assert leftovers.RUN_DIR_NAME.fullmatch(run.name) and str(sid) in run.name
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
        assert _wait(lambda: not _session(sid), 15), f"still running after the kill: {_session(sid)}"
        assert _wait(lambda: not list(tmp.iterdir()), 5), f"left in TMPDIR: {list(tmp.iterdir())}"
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        _kill_session(sid)


def test_the_next_diagnosis_removes_a_killed_ones_segment_and_says_so(tmp_path, capsys, monkeypatch):
    """A segment left by a diagnosis killed with its resource tracker (``magcal_<pid>_<hex>``, the process gone) is
    unlinked by the next diagnosis, which names it; a running process's segment and other files stay. (The shared
    memory's folder is the test's own: a planted segment in /dev/shm would be removed by any diagnosis that runs
    meanwhile, another test's in another process too.)"""
    from magcal.cli import main
    from magcal.diagnosis import _parallel

    shm = tmp_path / "shm"
    shm.mkdir()
    monkeypatch.setattr(_parallel, "SHM_DIR", str(shm))
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(tmp))
    dead = _ended_pid()
    # a run folder of a process killed with its fork server, and one of a process still running
    stale_run = tmp / f"magcal-{leftovers.host_tag()}-{dead}-abcdefgh"
    stale = shm / f"magcal_{dead}_{'ab' * 8}"
    alive = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
    running = shm / f"magcal_{alive.pid}_{'cd' * 8}"
    running_run = tmp / f"magcal-{leftovers.host_tag()}-{alive.pid}-abcdefgh"
    for folder in (stale_run, running_run):
        folder.mkdir()
        (folder / "listener-abcdefgh").write_bytes(b"")
    other = shm / f"magcal_{dead}_notours"
    try:
        for name in (stale, running, other):
            name.write_bytes(b"\0" * 300_000)
        path = tmp_path / "small.csv"
        mio.write_csv(path, magcal.simulate_timeseries("chi2017", n_samples=400, seed=2, rate_hz=10.0))
        assert main(["diagnose", str(path), "--workers", "1", "--no-validate"]) == 0
        err = capsys.readouterr().err
        assert not stale.exists() and running.exists() and other.exists()
        assert not stale_run.exists() and running_run.exists()
        assert f"1 temporary folder, 0 MB (process {dead}, no longer running): {stale_run}" in err, err
        said = re.search(
            r"removed what a killed diagnosis left behind: 1 shared-memory segment, 0\.3 MB \(process "
            rf"{dead}, no longer running\): {re.escape(str(stale))}",
            err,
        )
        assert said, err
        # the next one finds nothing to say
        assert main(["diagnose", str(path), "--workers", "1", "--no-validate"]) == 0
        assert "left behind" not in capsys.readouterr().err
    finally:
        alive.kill()
        alive.wait()


# -- magcal apply on Dask killed -----------------------------------------------------------------------------------
def test_a_killed_parallel_apply_leaves_no_process_and_the_next_removes_its_work_folder(tmp_path, capsys, env_tmp):
    """SIGKILL of a Dask ``magcal apply`` while it writes partitions: no process of it runs after a few seconds;
    its hidden work folder stays (nothing is left to remove it) until the next apply into that folder removes it
    and says so. Folders of a running process or of another machine are not touched."""
    pytest.importorskip("distributed")
    pytest.importorskip("pyarrow")
    from magcal.cli import main
    from magcal.output import survey

    ds = magcal.simulate_timeseries("chi2017", n_samples=6000, seed=3, rate_hz=10.0)
    data, cal = tmp_path / "survey.csv", tmp_path / "cal.json"
    mio.write_csv(data, ds)
    magcal.calibrate(ds.subset(np.arange(1500))).calibration.save(cal)
    out = tmp_path / "parts"
    env, tmp = env_tmp
    proc = subprocess.Popen(
        [sys.executable, "-m", "magcal", "apply", str(cal), str(data), "-o", str(out), "--workers", "2"]
        + ["--partition-rows", "200", "--no-progress"],
        start_new_session=True,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        env=env,
    )
    sid = proc.pid

    def work_dirs():
        return sorted(p for p in tmp_path.iterdir() if p.name.startswith(".parts.") and p.is_dir())

    alive = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
    try:
        assert _wait(lambda: any(any(d.iterdir()) for d in work_dirs()) or proc.poll() is not None, 120)
        assert proc.poll() is None, "the apply ended before it was killed"
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
        assert _wait(lambda: not _session(sid), 15), f"still running after the kill: {_session(sid)}"
        # no pymp-* (the fork server's socket), no run folder, no Dask scratch space
        assert _wait(lambda: not list(tmp.iterdir()), 5), f"left in TMPDIR: {list(tmp.iterdir())}"
        (killed,) = work_dirs()
        assert str(sid) in killed.name and not out.exists()
        # beside it: a folder of a process still running and one of another machine, both to be kept
        host = leftovers.host_tag()
        keep = [
            tmp_path / f".other.magcal-{host}-{alive.pid}-abcdefgh.tmp",
            tmp_path / f".other.magcal-{'0' * 6 if host != '0' * 6 else '1' * 6}-{_ended_pid()}-abcdefgh.tmp",
        ]
        for folder in keep:
            folder.mkdir()
            (folder / "part-00000.parquet").write_bytes(b"x")
        assert survey.WORK_DIR_NAME.fullmatch(killed.name)
        assert main(["apply", str(cal), str(data), "-o", str(out), "--workers", "1", "--no-progress"]) == 0
        err = capsys.readouterr().err
        assert not killed.exists() and all(k.exists() for k in keep)
        assert "work folder, " in err and f"(process {sid}, no longer running): {killed}" in err, err
        assert len(list(out.iterdir())) >= 1
    finally:
        alive.kill()
        alive.wait()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        _kill_session(sid)
