"""The diagnosis on every core: its independent fits in worker processes sharing the readings through one
shared-memory segment, or on a Dask cluster, give the same candidates, scores and verdict as one after the other;
the segment is gone after a run, after a worker's error and after a worker's crash."""

from __future__ import annotations

import dataclasses
import json
import multiprocessing
import operator
import os
import re
import sys
import time
import warnings

import numpy as np
import pytest

from magcal.core.errors import ConvergenceWarning
from magcal.diagnosis import _parallel, diagnose
from magcal.fitting.fitter import fit
from tests.helpers.two_effects import two_hidden

pytestmark = pytest.mark.skipif(not os.path.isdir("/dev/shm"), reason="shared memory is seen in /dev/shm on Linux")

FIGURES = ("delta_bic", "rms_after_nT", "held_out_before_nT", "held_out_after_nT", "later_before_nT", "later_after_nT")


def _segments():
    """This process's shared-memory segments still in /dev/shm."""
    prefix = f"{_parallel.SEGMENT_PREFIX}{os.getpid()}_"
    return sorted(name for name in os.listdir("/dev/shm") if name.startswith(prefix))


@pytest.fixture(scope="module")
def record():
    """Four sensors, a temperature bias and a bias step on sensor 3 hidden; the base fit."""
    return two_hidden()


@pytest.fixture(scope="module")
def serial(record):
    """The diagnosis with every fit one after the other, in this thread."""
    ds, res = record
    mp = pytest.MonkeyPatch()
    mp.setattr(_parallel, "PARALLEL_FITS", 1)
    mp.setattr(_parallel, "BACKEND", "threads")
    try:
        return diagnose(ds, res)
    finally:
        mp.undo()


def _same(one, two):
    assert one.verdict == two.verdict
    assert [c.label for c in one.candidates] == [c.label for c in two.candidates]
    for a, b in zip(one.candidates, two.candidates):
        assert (a.refitted, a.holds, a.transfers) == (b.refitted, b.holds, b.transfers), a.label
        assert a.predicted_delta_bic == pytest.approx(b.predicted_delta_bic, rel=1e-9, abs=1e-9), a.label
        for name in FIGURES:
            x, y = getattr(a, name), getattr(b, name)
            assert (x is None and y is None) or x == pytest.approx(y, rel=1e-9, abs=1e-9), (a.label, name)
    assert one.explained_by == two.explained_by and one.record_holds == two.record_holds
    assert one.summary == two.summary
    assert [n.text for n in one.notes] == [n.text for n in two.notes]


@pytest.mark.parametrize("workers", [1, 2])
def test_fits_in_worker_processes_give_the_serial_diagnosis(record, serial, monkeypatch, workers):
    ds, res = record
    monkeypatch.setattr(_parallel, "PARALLEL_FITS", workers)
    monkeypatch.setattr(_parallel, "BACKEND", "processes")
    made = []
    real = _parallel._Processes

    def counted(*args, **kwargs):
        made.append(real(*args, **kwargs))
        return made[-1]

    monkeypatch.setattr(_parallel, "_Processes", counted)
    got = diagnose(ds, res)
    assert len(made) == 1 and made[0].workers == workers  # the fits did run in processes
    assert got.ran_on == {"where": "processes", "workers": workers}  # and the diagnosis says so
    assert got.where_text().endswith(f"on {workers} worker processes")
    assert serial.ran_on == {"where": "threads", "workers": 1} and serial.where_text().endswith("on one core")
    assert serial.verdict == "missing_effect" and "temperature_bias" in serial.explained_by
    _same(serial, got)
    assert _segments() == []  # unlinked when the diagnosis ended


def test_a_worker_process_shares_the_readings_and_returns_a_fits_notes(record, monkeypatch):
    """The dataset a worker maps is the caller's to the bit (read-only); a fit made there comes back with its notes
    (a fit stopped after one evaluation says it did not converge), as the diagnosis gathers them
    (tests/core/test_notes.py: notes are values that travel with their fits)."""
    ds, _ = record
    monkeypatch.setattr(_parallel, "PARALLEL_FITS", 1)
    monkeypatch.setattr(_parallel, "BACKEND", "processes")
    with _parallel.Pool(ds) as pool:
        assert pool.is_remote and len(_segments()) == 1
        shared = pool.remote(operator.attrgetter("readings_nT", "temperature_C", "time_s"))
        assert not pool.remote(operator.attrgetter("readings_nT.flags.writeable"))
        limits = pool.remote(_blas_threads)
        heap_kept = pool.remote(_heap_kept)
        fitted = pool.remote(fit, None, None, "linear", None, None, None, 1, None, None, False)

    for a, b in zip(shared, (ds.readings_nT, ds.temperature_C, ds.time_s)):
        np.testing.assert_array_equal(a, b)
    assert limits and set(limits) == {1}  # BLAS on one thread in the worker, numpy's and scipy's alike
    assert heap_kept  # the allocator's thresholds raised (tests/core/test_memory.py), whatever Dask left in the env
    assert fitted.problem is None and fitted.notes and fitted.notes[0].is_a(ConvergenceWarning)
    assert _segments() == []


def _parent(dataset):
    return os.getppid()


@pytest.mark.skipif("forkserver" not in multiprocessing.get_all_start_methods(), reason="no fork server here")
def test_the_workers_of_every_pool_are_forked_from_one_fork_server(record, monkeypatch):
    """The workers are not new interpreters importing magcal for each pool: every pool's workers are children of the
    same fork server (not of this process), which imported magcal once; BLAS still runs one thread in them, and
    this process's own BLAS setting is left as it was."""
    ds, _ = record
    monkeypatch.setattr(_parallel, "PARALLEL_FITS", 2)
    monkeypatch.setattr(_parallel, "BACKEND", "processes")
    monkeypatch.delenv("OPENBLAS_NUM_THREADS", raising=False)
    parents, limits = set(), []
    for _ in range(2):
        with _parallel.Pool(ds) as pool:
            parents.add(pool.remote(_parent))
            limits += pool.remote(_blas_threads)
    assert len(parents) == 1 and os.getpid() not in parents
    assert set(limits) == {1}
    assert "OPENBLAS_NUM_THREADS" not in os.environ
    assert _segments() == []


@pytest.mark.parametrize("backend", ["threads", "processes"])
def test_this_process_runs_blas_on_one_thread_while_a_pool_lives(record, monkeypatch, backend):
    """While a diagnosis's pool lives, this process's BLAS runs one thread (its fits share the cores with the pool's
    others); the user's own setting comes back when the last of two overlapping pools closes, whichever order they
    close in (two sessions of the workbench diagnosing at once)."""
    from threadpoolctl import threadpool_limits

    ds, _ = record
    monkeypatch.setattr(_parallel, "PARALLEL_FITS", 2)
    monkeypatch.setattr(_parallel, "BACKEND", backend)
    with threadpool_limits(limits=2, user_api="blas"):
        before = set(_blas_threads(None))
        if before == {1}:
            pytest.skip("this BLAS runs one thread whatever it is asked")
        first = _parallel.Pool(ds)
        second = _parallel.Pool(ds)
        try:
            in_pool = first.submit(lambda: _blas_threads(None)).result()
            first.close()  # the first to open closes first: the second still runs
            still = set(_blas_threads(None))
        finally:
            first.close()
            second.close()
        after = set(_blas_threads(None))
    assert set(in_pool) == {1} and still == {1}
    assert after == before


@pytest.mark.parametrize("backend", ["processes", "threads"])
@pytest.mark.parametrize("room", [0, 1, 3, 8])
def test_the_workers_fit_in_the_free_memory(record, monkeypatch, backend, room):
    """With memory for ``room`` fits (beside this process's own share) the pool runs that many of the 8 workers
    asked for and says why; with room for one, processes give way to this process's thread; with room for all,
    or where the free memory cannot be read, nothing changes and nothing is said."""
    ds, _ = record
    readings = ds.n_sensors * ds.n_samples
    each = _parallel.WORKER_BYTES_PER_READING * readings + (
        _parallel.WORKER_BASE_BYTES if backend == "processes" else 0
    )
    free = ((room + 0.5) * each + _parallel.CALLER_BYTES_PER_READING * readings) / _parallel.MEMORY_SHARE
    monkeypatch.setattr(_parallel.memory, "available_bytes", lambda: free)
    monkeypatch.setattr(_parallel, "BACKEND", backend)
    with _parallel.Pool(ds, workers=8) as pool:
        workers, where, note = pool.workers, pool.backend, pool.note
    expected = min(max(room, 1), 8)
    assert workers == expected
    assert where == (backend if expected > 1 else "threads")
    if expected < 8:
        assert note and f"ran {expected} of the 8" in note and f"{readings:,} readings" in note
    else:
        assert note is None
    monkeypatch.setattr(_parallel.memory, "available_bytes", lambda: None)
    with _parallel.Pool(ds, workers=8) as pool:
        assert pool.workers == 8 and pool.note is None


def test_a_diagnosis_short_of_memory_says_so_and_reads_the_same(record, serial, monkeypatch):
    ds, res = record
    readings = ds.n_sensors * ds.n_samples
    each = _parallel.WORKER_BYTES_PER_READING * readings + _parallel.WORKER_BASE_BYTES
    free = (2.5 * each + _parallel.CALLER_BYTES_PER_READING * readings) / _parallel.MEMORY_SHARE
    monkeypatch.setattr(_parallel.memory, "available_bytes", lambda: free)
    monkeypatch.setattr(_parallel, "BACKEND", "processes")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        d = diagnose(ds, res, workers=4)
    said = [n for n in d.notes if "ran 2 of the 4 worker processes" in n.text]
    assert len(said) == 1
    d.notes = [n for n in d.notes if n not in said]
    _same(d, serial)  # the same diagnosis, on fewer workers


def test_a_pool_that_cannot_start_leaves_nothing_behind(record, monkeypatch):
    """A pool whose second thread does not start (the machine out of threads) closes what it had made: the worker
    processes, the shared memory, its first thread and the BLAS limit."""
    import threading

    from threadpoolctl import threadpool_limits

    ds, _ = record
    monkeypatch.setattr(_parallel, "PARALLEL_FITS", 2)
    monkeypatch.setattr(_parallel, "BACKEND", "processes")
    real_start, started = threading.Thread.start, []

    def start(self):
        if self.name.startswith("magcal-fit_") and started:
            raise RuntimeError("can't start new thread")
        if self.name.startswith("magcal-fit_"):
            started.append(self)
        real_start(self)

    monkeypatch.setattr(threading.Thread, "start", start)
    with threadpool_limits(limits=2, user_api="blas"):
        before = set(_blas_threads(None))
        with pytest.raises(RuntimeError, match="can't start new thread"):
            _parallel.Pool(ds)
        after = set(_blas_threads(None))
    assert after == before
    assert _segments() == []
    assert started and not started[0].is_alive()


def test_the_shared_memory_is_unlinked_after_a_workers_error(record, monkeypatch):
    ds, _ = record
    monkeypatch.setattr(_parallel, "PARALLEL_FITS", 1)
    monkeypatch.setattr(_parallel, "BACKEND", "processes")
    with pytest.raises(TypeError, match="not subscriptable"):
        with _parallel.Pool(ds) as pool:
            assert len(_segments()) == 1
            pool.remote(operator.getitem, 0)  # raised in the worker, raised here
    assert _segments() == []


def _blas_threads(dataset):
    from threadpoolctl import threadpool_info

    return [lib["num_threads"] for lib in threadpool_info() if lib.get("user_api") == "blas"]


def _heap_kept(dataset):
    from magcal.core import memory

    return memory._SET


def _crash(dataset):
    os._exit(3)


def test_the_shared_memory_is_unlinked_after_a_worker_dies(record, monkeypatch):
    from concurrent.futures.process import BrokenProcessPool

    ds, _ = record
    monkeypatch.setattr(_parallel, "PARALLEL_FITS", 1)
    monkeypatch.setattr(_parallel, "BACKEND", "processes")
    with pytest.raises(BrokenProcessPool):
        with _parallel.Pool(ds) as pool:
            pool.remote(_crash)
    assert _segments() == []


def test_small_records_and_one_core_stay_on_threads(record, monkeypatch):
    ds, _ = record
    monkeypatch.setattr(_parallel, "BACKEND", None)
    assert _parallel.backend_for(ds, workers=16) == "threads"  # 4 x 3000 readings: below both thresholds
    monkeypatch.setattr(_parallel, "PROCESS_MIN_READINGS", 1000)
    assert _parallel.backend_for(ds, workers=2) == "processes"
    assert _parallel.backend_for(ds, workers=1) == "threads"


@pytest.mark.parametrize(
    ("workers", "expected"),
    [(1, "threads"), (2, "threads"), (3, "threads"), (4, "processes"), (16, "processes"), (None, "processes")],
)
def test_many_workers_take_processes_for_smaller_records(record, monkeypatch, workers, expected):
    """Between the two thresholds the worker count decides: threads stop paying beyond about four workers."""
    ds, _ = record
    readings = ds.n_sensors * ds.n_samples
    monkeypatch.setattr(_parallel, "BACKEND", None)
    monkeypatch.setattr(_parallel, "PROCESS_MIN_READINGS", readings + 1)
    monkeypatch.setattr(_parallel, "PROCESS_MIN_READINGS_MANY", readings)
    monkeypatch.setattr(_parallel, "PARALLEL_FITS", None)
    monkeypatch.setattr(_parallel, "cores", lambda: 16)  # None: one worker per core
    assert _parallel.backend_for(ds, workers=workers) == expected
    monkeypatch.setattr(_parallel, "PROCESS_MIN_READINGS_MANY", readings + 1)
    assert _parallel.backend_for(ds, workers=workers) == "threads"

    class Theirs:  # a user's effect (an effects file): a worker process could not import it
        pass

    assert _parallel.backend_for(ds, workers=16, effects=[Theirs]) == "threads"
    assert _parallel.backend_for(ds, workers=16, scheduler="tcp://127.0.0.1:1") == "dask"


def test_the_diagnosis_on_a_dask_cluster_reads_the_same(record, serial):
    """A local cluster on loopback (one worker process of two threads) by its address, as --scheduler gives it."""
    distributed = pytest.importorskip("distributed")
    ds, res = record
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the cluster's own start-up chatter
        with distributed.LocalCluster(
            n_workers=1,
            threads_per_worker=2,
            processes=True,
            host="127.0.0.1",
            dashboard_address=None,
            silence_logs=40,
        ) as cluster:
            got = diagnose(ds, res, scheduler=cluster.scheduler_address)
    _same(serial, got)


def test_too_little_shared_memory_keeps_the_fits_on_threads_and_says_so(record, serial, monkeypatch):
    """A container's /dev/shm (Docker: 64 MB) may not hold a large record: the diagnosis then runs its fits on
    threads, with the same results, and its notes say why and what to do."""
    monkeypatch.setattr(_parallel, "BACKEND", "processes")
    monkeypatch.setattr(_parallel, "shared_memory_free_bytes", lambda: 1000)
    ds, res = record
    with _parallel.Pool(ds, workers=2) as pool:
        assert pool.backend == "threads" and pool.workers == 2 and pool.concurrent
        assert "shared memory" in pool.note and "--shm-size" in pool.note
    got = diagnose(ds, res, workers=2)
    said = [n for n in got.notes if "--shm-size" in n.text]
    assert len(said) == 1
    _same(serial, dataclasses.replace(got, notes=[n for n in got.notes if n not in said]))
    assert [n for n in os.listdir("/dev/shm") if n.startswith(_parallel.SEGMENT_PREFIX + f"{os.getpid()}_")] == []


@pytest.mark.skipif(not os.path.exists("/usr/bin/unshare"), reason="needs unshare to mount a small /dev/shm")
def test_a_shared_memory_full_while_written_is_an_error_not_a_bus_error(tmp_path):
    """Past the statvfs check (another program may take the room meanwhile), the segment's pages are reserved as
    it is made: in an 8 MB /dev/shm a 14 MB record raises SharedMemoryFull, where writing it killed the process
    with a bus error. Runs in a mount namespace of its own (root, Linux); skipped where that is not allowed."""
    import subprocess

    script = tmp_path / "small_shm.py"
    script.write_text(
        "import os\n"
        "from magcal.data.simulation import chi2017_truth, simulate_timeseries\n"
        "from magcal.diagnosis import _parallel\n"
        "_parallel.shared_memory_free_bytes = lambda: None  # as if the room were taken after the check\n"
        "ds = simulate_timeseries(chi2017_truth(4), n_samples=100_000, noise_nT=3.0, seed=1)\n"
        "try:\n"
        "    _parallel.SharedDataset(ds)\n"
        "except _parallel.SharedMemoryFull as full:\n"
        "    print('full', full.needed, os.listdir('/dev/shm'))\n"
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}
    probe = subprocess.run(
        ["unshare", "-m", "sh", "-c", "mount -t tmpfs -o size=8m tmpfs /dev/shm"], capture_output=True, timeout=30
    )
    if probe.returncode != 0:
        pytest.skip("this machine does not allow a mount namespace here")
    proc = subprocess.run(
        [
            "unshare",
            "-m",
            "sh",
            "-c",
            f'mount -t tmpfs -o size=8m tmpfs /dev/shm && exec "{sys.executable}" "{script}"',
        ],
        capture_output=True,
        text=True,
        timeout=120,
        env=env,
    )
    assert proc.returncode == 0, (proc.returncode, proc.stderr[-2000:])
    assert proc.stdout.split()[:1] == ["full"] and proc.stdout.strip().endswith("[]"), proc.stdout


def _nap(dataset, seconds):
    time.sleep(seconds)
    return os.getpid()


#: Per worker start: whether the caller's script showed, and BLAS's thread setting (_SlowStart).
_STARTS: list = []


class _SlowStart(multiprocessing.get_context("spawn").Process):  # type: ignore[name-defined,misc]
    """A worker process whose start takes a while (the first worker is idle before the next is asked for)."""

    _start_method = "forkserver"

    @staticmethod
    def _Popen(process_obj):
        return multiprocessing.get_context("forkserver").Process._Popen(process_obj)

    def start(self):
        _STARTS.append(("__file__" in sys.modules["__main__"].__dict__, os.environ.get("OPENBLAS_NUM_THREADS")))
        super().start()
        time.sleep(1.5)


@pytest.mark.skipif("forkserver" not in multiprocessing.get_all_start_methods(), reason="no fork server here")
def test_workers_started_late_start_with_the_callers_script_hidden(record, monkeypatch, tmp_path):
    """The executor starts a worker only when a task finds none idle, so a pool's workers can start in the middle
    of a diagnosis. Each start, early or late, must hide the caller's script (a worker would otherwise run a script
    without a ``__main__`` guard again) and tell BLAS one thread. Here each start is slowed, so that the first
    worker is idle before the second is asked for and the others start later, from the tasks."""
    script = tmp_path / "users_script.py"
    script.write_text("pass\n")
    monkeypatch.setattr(sys.modules["__main__"], "__file__", str(script), raising=False)
    base = multiprocessing.get_context("forkserver")

    class Context(type(base)):  # type: ignore[misc]
        Process = _SlowStart

    _STARTS.clear()
    seen = _STARTS
    monkeypatch.setattr(_parallel, "process_context", lambda: Context())
    monkeypatch.setattr(_parallel, "BACKEND", "processes")
    ds, _ = record
    with _parallel.Pool(ds, workers=3) as pool:
        pids = {f.result() for f in [pool.remote_future(_nap, 0.8) for _ in range(12)]}  # room for a slow start
    assert len(seen) == 3 and len(pids) == 3  # every worker started and worked
    assert seen == [(False, "1")] * 3, seen  # the third starts from a task, outside the start-up loop


def test_a_script_without_a_main_guard_is_not_run_again_in_the_workers(tmp_path):
    """``spawn`` runs the caller's ``__main__`` again in every worker; a user's script rarely has the
    ``if __name__ == "__main__":`` guard, and must still run once and diagnose in worker processes (workers that
    start late: the test above)."""
    import subprocess

    script = tmp_path / "unguarded.py"
    script.write_text(
        "from magcal.data.simulation import chi2017_truth, simulate_timeseries\n"
        "from magcal.diagnosis import _parallel, diagnose\n"
        "_parallel.BACKEND = 'processes'\n"
        "print('top level ran', flush=True)\n"
        "ds = simulate_timeseries(chi2017_truth(1), n_samples=1500, noise_nT=3.0, seed=2)\n"
        "d = diagnose(ds, workers=1)\n"
        "print('verdict', d.verdict)\n"
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}
    proc = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120, env=env)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.count("top level ran") == 1 and "verdict" in proc.stdout


def test_the_command_line_starts_the_fork_server_before_reading_a_large_file(tmp_path, monkeypatch):
    """magcal diagnose starts the worker processes' fork server before it reads the file when the file's size says
    the fits will run in processes, so that the server's imports run beside the reading; not for a small file, a
    user's effects file or a cluster."""
    import argparse

    from magcal.cli import diagnose as command

    monkeypatch.setattr(_parallel, "BACKEND", None)
    monkeypatch.setattr(_parallel, "PARALLEL_FITS", None)
    monkeypatch.setattr(_parallel, "cores", lambda: 2)
    started = []
    real = command.start_workers
    monkeypatch.setattr(command, "start_workers", lambda **kw: started.append(kw) or real(**kw))
    from multiprocessing import forkserver

    monkeypatch.setattr(forkserver, "ensure_running", lambda: None)  # the decision, not the server
    big, small = tmp_path / "big.csv", tmp_path / "small.csv"
    big.write_bytes(b"1" * (command.FILE_BYTES_PER_READING * _parallel.PROCESS_MIN_READINGS))
    small.write_bytes(b"1" * (command.FILE_BYTES_PER_READING * _parallel.PROCESS_MIN_READINGS - 8))

    def args(path, **kw):
        return argparse.Namespace(**{"data": str(path), "workers": None, "effects_file": None, "scheduler": None, **kw})

    assert command._start_workers_while_reading(args(big))
    assert started[-1]["readings"] == _parallel.PROCESS_MIN_READINGS
    assert not command._start_workers_while_reading(args(small))
    assert not command._start_workers_while_reading(args(big, workers=1))
    assert not command._start_workers_while_reading(args(big, effects_file=["mine.py"]))
    assert not command._start_workers_while_reading(args(big, scheduler="tcp://127.0.0.1:9"))
    assert not command._start_workers_while_reading(args(tmp_path / "missing.csv"))
    assert len(started) == 3  # big, small, one worker: the others decided before asking


def test_the_command_line_takes_the_cores_and_refuses_too_many(tmp_path, record, capsys):
    from magcal.cli import main
    from magcal.data import io as mio

    ds, _ = record
    path = tmp_path / "four.csv"
    mio.write_csv(path, ds.subset(np.arange(1500)))
    assert main(["diagnose", str(path), "--workers", "2", "--json", "--no-validate"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["verdict"] and doc["ran_on"] == {"where": "threads", "workers": 2}  # a small record: threads
    assert main(["diagnose", str(path), "--workers", "1", "--no-validate"]) == 0
    assert re.search(r"Diagnosed in \d+\.\d s on one core\.", capsys.readouterr().out)
    assert main(["diagnose", str(path), "--workers", str(4 * _parallel.cores() + 1)]) != 0
    assert "--workers" in capsys.readouterr().err


@pytest.mark.parametrize(
    "guess, workers",
    [("none", 1), ("wrong", 1), ("none", 3), ("wrong", 3), ("wrong prediction", 3), ("no prediction", 3)],
)
def test_the_next_round_started_ahead_changes_nothing(record, serial, monkeypatch, guess, workers):
    """The forward selection's first round is started at the in-sample best's refit, beside the held-out fits
    (:func:`magcal.diagnosis.verdict._in_sample_best`), and with cores to spare at the refit of the candidate
    predicted best (:func:`~magcal.diagnosis.verdict._predicted_best`); the diagnosis is the same to the bit when
    nothing is started ahead, and when what was started is for another candidate than the one the judgement keeps
    first."""
    from magcal.diagnosis import verdict

    started = []

    def other(real):
        def pick(cands):
            best = real(cands)
            rest = [c for c in cands if c is not best and (guess == "wrong prediction" or c.refitted and c.fit)]
            started.append(rest[0] if rest else None)
            return started[-1]

        return pick

    if guess in ("none", "no prediction"):
        name = "_in_sample_best" if guess == "none" else "_predicted_best"
        monkeypatch.setattr(verdict, name, lambda cands: None)
    else:
        name = "_in_sample_best" if guess == "wrong" else "_predicted_best"
        monkeypatch.setattr(verdict, name, other(getattr(verdict, name)))
    monkeypatch.setattr(_parallel, "PARALLEL_FITS", workers)
    monkeypatch.setattr(_parallel, "BACKEND", "threads")
    ds, res = record
    _same(serial, diagnose(ds, res))
    assert "wrong" not in guess or any(c is not None for c in started)  # a round for the wrong one was started


@pytest.mark.parametrize("case", ["processes", "one worker", "threads", "a cluster", "a user's effect"])
def test_the_fork_server_starts_before_the_diagnosis_only_for_processes(record, monkeypatch, case):
    """:func:`magcal.diagnosis.start_workers` starts the worker processes' fork server as soon as the record is
    read, so that the diagnosis's first workers do not wait for its imports; the pool's workers are then its
    children. Where the fits would run on threads or on a cluster it starts nothing."""
    import multiprocessing.forkserver as forkserver

    from magcal.diagnosis import start_workers
    from magcal.model.terms import Effect

    class Mine(Effect):
        name = "mine_for_the_test"

    ds, _ = record
    monkeypatch.setattr(_parallel, "PROCESS_MIN_READINGS", 0 if case != "threads" else 10**9)
    args = {
        "processes": (2, None, ()),
        "one worker": (1, None, ()),
        "threads": (2, None, ()),
        "a cluster": (2, "tcp://127.0.0.1:9", ()),
        "a user's effect": (2, None, (Mine,)),
    }[case]
    started = start_workers(ds, *args)
    assert started == (case == "processes")
    if not started:
        return
    server = forkserver._forkserver._forkserver_pid
    assert server is not None and os.path.exists(f"/proc/{server}")
    assert start_workers(ds, *args) and forkserver._forkserver._forkserver_pid == server  # once
    monkeypatch.setattr(_parallel, "PARALLEL_FITS", 2)
    with _parallel.Pool(ds, workers=2) as pool:
        assert pool.backend == "processes"
        assert pool.remote(_parent) == server


@pytest.mark.skipif(not os.path.isdir("/proc"), reason="reads the fork server's environment in /proc")
def test_the_fork_server_started_early_runs_blas_on_one_thread(tmp_path):
    """start_workers starts the fork server as the pool would: BLAS and OpenMP told one thread (every core's
    threads would otherwise start in it and be torn down at every fork), the caller's own setting untouched. In a
    fresh program: the fork server is started once per program."""
    import subprocess

    script = tmp_path / "early.py"
    script.write_text(
        "import os\n"
        "from multiprocessing import forkserver\n"
        "from magcal.data.simulation import chi2017_truth, simulate_timeseries\n"
        "from magcal.diagnosis import _parallel, start_workers\n"
        "_parallel.BACKEND = 'processes'\n"
        "ds = simulate_timeseries(chi2017_truth(1), n_samples=500, noise_nT=3.0, seed=2)\n"
        "assert start_workers(ds, 2)\n"
        "import time\n"
        "pid, end = forkserver._forkserver._forkserver_pid, time.monotonic() + 30\n"
        # the server is forked, then exec'd: before the exec its /proc environ is this program's first one
        "while b'forkserver' not in open(f'/proc/{pid}/cmdline', 'rb').read() and time.monotonic() < end:\n"
        "    time.sleep(0.01)\n"
        "env = open(f'/proc/{forkserver._forkserver._forkserver_pid}/environ', 'rb').read().split(b'\\0')\n"
        "print(sorted(v.decode() for v in env if v.startswith((b'BLIS_NUM', b'OPENBLAS_NUM'))))\n"
        "print(os.environ.get('BLIS_NUM_THREADS'), os.environ.get('OPENBLAS_NUM_THREADS'))\n"
    )
    env = {k: v for k, v in os.environ.items() if not k.endswith("_NUM_THREADS")}
    env["PYTHONPATH"] = os.pathsep.join(p for p in sys.path if p)
    proc = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120, env=env)
    assert proc.returncode == 0, proc.stderr[-2000:]
    server, caller = proc.stdout.strip().splitlines()[-2:]
    assert server == "['BLIS_NUM_THREADS=1', 'OPENBLAS_NUM_THREADS=1']"
    assert caller == "None None"


_MALLINFO2 = ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks", "keepcost")


def _mapped_for_a_large_array(dataset):
    """(A worker's task.) Bytes of fresh mappings a 64 MB array (above glibc's largest mmap threshold) takes."""
    import ctypes

    class Info(ctypes.Structure):  # glibc's struct mallinfo2
        _fields_ = [(name, ctypes.c_size_t) for name in _MALLINFO2]

    libc = ctypes.CDLL("libc.so.6")
    libc.mallinfo2.restype = Info
    before = libc.mallinfo2().hblkhd
    a = np.ones(8 << 20)
    mapped = libc.mallinfo2().hblkhd - before
    del a
    return mapped


def test_a_worker_serves_a_large_records_temporaries_from_its_heap(record, monkeypatch):
    """A fit of 4 x 1e6 samples makes temporaries of 30-100 MB; in the worker processes they come from the heap
    (magcal.core.memory.keep_large_blocks(every_size=True)), not each from a fresh mapping faulted in anew."""
    ds, _ = record
    monkeypatch.setattr(_parallel, "PARALLEL_FITS", 2)
    monkeypatch.setattr(_parallel, "BACKEND", "processes")
    with _parallel.Pool(ds) as pool:
        try:
            mapped = pool.remote(_mapped_for_a_large_array)
        except AttributeError:
            pytest.skip("glibc before 2.33 has no mallinfo2")
    assert mapped == 0
