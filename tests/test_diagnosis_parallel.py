"""Independent fits of a diagnosis side by side (magcal.diagnosis._parallel): the same diagnosis as one by one."""

import threading
import time

import pytest

from magcal.data.simulation import chi2017_truth, simulate_timeseries
from magcal.diagnosis import _parallel, diagnose
from magcal.fitting.pipeline import calibrate
from magcal.model import perturbations


@pytest.mark.parametrize("workers", [None, 1, 3])
def test_results_come_back_in_the_order_of_the_calls(monkeypatch, workers):
    monkeypatch.setattr(_parallel, "PARALLEL_FITS", workers)
    delays = [0.03, 0.0, 0.02, 0.01]

    def call(k):
        time.sleep(delays[k])
        return k, threading.current_thread().name

    out = _parallel.in_parallel([lambda k=k: call(k) for k in range(4)])
    assert [k for k, _ in out] == [0, 1, 2, 3]
    if workers == 1:
        assert {name for _, name in out} == {threading.current_thread().name}


def test_an_exception_of_one_call_is_raised(monkeypatch):
    monkeypatch.setattr(_parallel, "PARALLEL_FITS", 2)

    def bad():
        raise ValueError("boom")

    with pytest.raises(ValueError, match="boom"):
        _parallel.in_parallel([lambda: 1, bad])


@pytest.mark.parametrize("workers", [1, 2])
def test_a_pool_runs_follow_ups_and_waits_for_everything(monkeypatch, workers):
    """A call may hand the pool further calls (a candidate's held-out fits when its refit returns); leaving the
    pool waits for all of them, and each future gives its call's result or raises its exception."""
    monkeypatch.setattr(_parallel, "PARALLEL_FITS", workers)
    follow = {}

    def refit(k):
        time.sleep(0.01 * (3 - k))
        follow[k] = pool.submit(lambda: 10 * k, _parallel.CHAIN)
        return k

    def bad():
        raise ValueError("boom")

    with _parallel.Pool() as pool:
        firsts = [pool.submit(lambda k=k: refit(k)) for k in range(3)]
        failing = pool.submit(bad, _parallel.FILLER)
    assert [f.result() for f in firsts] == [0, 1, 2]
    assert all(follow[k].done() and follow[k].result() == 10 * k for k in range(3))
    with pytest.raises(ValueError, match="boom"):
        failing.result()


def test_a_pool_starts_work_by_priority(monkeypatch):
    """Queued work starts by priority, then in the order submitted: the longest chain of fits is never queued
    behind evidence that can wait. (One thread is held back, so the other takes the queue one call at a time.)"""
    monkeypatch.setattr(_parallel, "PARALLEL_FITS", 2)
    started, held, busy = [], threading.Event(), threading.Event()
    with _parallel.Pool() as pool:
        blockers = [pool.submit(held.wait), pool.submit(busy.wait)]  # both threads busy while the queue fills
        time.sleep(0.05)
        for name, priority in [
            ("filler", _parallel.FILLER),
            ("shared", _parallel.SHARED),
            ("chain 1", _parallel.CHAIN),
            ("chain 2", _parallel.CHAIN),
        ]:
            pool.submit(lambda name=name: started.append(name), priority)
        busy.set()
        deadline = time.monotonic() + 10
        while len(started) < 4 and time.monotonic() < deadline:
            time.sleep(0.01)
        held.set()
    assert all(b.result() for b in blockers)
    assert started == ["chain 1", "chain 2", "shared", "filler"]


def test_a_diagnosis_with_fits_side_by_side_reads_the_same_as_one_by_one(monkeypatch):
    """Two hidden effects on four sensors: the confirming refits, the held-out fits and the score chunks run on
    threads; the candidates, their figures and the verdict are those of the sequential run."""
    ds = simulate_timeseries(
        chi2017_truth(4),
        n_samples=3000,
        noise_nT=3.0,
        seed=4,
        perturbations=[
            perturbations.parse_hidden("temperature_bias=2", 4),
            perturbations.parse_hidden("bias_step:3", 4),
        ],
    )
    res = calibrate(ds)
    results = {}
    for workers in (1, 2):
        monkeypatch.setattr(_parallel, "PARALLEL_FITS", workers)
        results[workers] = diagnose(ds, res)
    one, two = results[1], results[2]
    assert one.verdict == two.verdict and one.verdict == "missing_effect"
    assert [c.label for c in one.candidates] == [c.label for c in two.candidates]
    for a, b in zip(one.candidates, two.candidates):
        assert a.holds == b.holds
        for name in ("delta_bic", "rms_after_nT", "held_out_after_nT", "later_after_nT"):
            x, y = getattr(a, name), getattr(b, name)
            assert (x is None and y is None) or x == pytest.approx(y, rel=1e-9, abs=1e-9), name
    assert one.explained_by == two.explained_by and "temperature_bias" in one.explained_by
    assert one.summary == two.summary


def test_the_default_number_of_threads_is_one_per_core_and_bounded(monkeypatch):
    monkeypatch.setattr(_parallel, "PARALLEL_FITS", None)
    monkeypatch.setattr(_parallel, "cores", lambda: 64)
    assert _parallel._workers() == _parallel.MAX_THREADS
    assert _parallel._workers(3) == 3
    monkeypatch.setattr(_parallel, "cores", lambda: 2)
    assert _parallel._workers() == 2
    monkeypatch.setattr(_parallel, "PARALLEL_FITS", 16)  # asked for explicitly: as asked
    assert _parallel._workers() == 16


def test_leaving_a_pool_on_an_error_cancels_what_has_not_started(monkeypatch):
    """An error (or Ctrl-C) in the diagnosis does not wait for the queued work: what has not started is cancelled,
    what runs finishes."""
    monkeypatch.setattr(_parallel, "PARALLEL_FITS", 2)
    with pytest.raises(RuntimeError, match="stop"):
        with _parallel.Pool() as pool:
            running = [pool.submit(lambda: time.sleep(0.3) or True) for _ in range(2)]  # both threads busy
            time.sleep(0.05)
            queued = [pool.submit(lambda: time.sleep(5)) for _ in range(4)]
            raise RuntimeError("stop")
    assert all(f.result() for f in running)
    assert all(f.cancelled() for f in queued)
