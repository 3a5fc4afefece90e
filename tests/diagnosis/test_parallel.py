"""Independent fits of a diagnosis side by side (magcal.diagnosis._parallel): the same diagnosis as one by one."""

import threading
import time

import numpy as np
import pytest

from magcal.diagnosis import _parallel, diagnose
from tests.helpers.two_effects import two_hidden


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
    ds, res = two_hidden()
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


def _watch_fits(monkeypatch, refit_waits_s=0.0):
    """Record every refit and held-out fit as ``(kind, effect labels, event)``; with ``refit_waits_s``, each refit
    waits (that long at most) for a held-out fit of its model to start before it fits."""
    from magcal.diagnosis import scores, verdict

    log, lock = [], threading.Lock()
    started: dict = {}  # effect labels -> Event set when a held-out fit of that model starts

    def event(labels):
        with lock:
            return started.setdefault(labels, threading.Event())

    real_refit, real_validate = scores.refit_task, verdict.validate_task

    def refit_task(dataset, model, *args):
        labels = tuple(model.effect_labels)
        seen = event(labels).wait(refit_waits_s) if refit_waits_s else None
        log.append(("refit", labels, seen))
        return real_refit(dataset, model, *args)

    def validate_task(dataset, kept_mask, model, *args):
        labels = tuple(model.effect_labels)
        event(labels).set()
        log.append(("held_out", labels, None))
        return real_validate(dataset, kept_mask, model, *args)

    monkeypatch.setattr(scores, "refit_task", refit_task)
    monkeypatch.setattr(verdict, "validate_task", validate_task)
    return log


def test_a_candidates_held_out_fits_run_beside_its_refit(monkeypatch):
    """With cores to spare, the held-out fits of a candidate predicted to be supported start from its predicted
    start while its refit runs, in the first round and in the next (each refit here waits for them: were they
    handed over only after it, it would wait in vain); the diagnosis reads as the sequential one."""
    ds, res = two_hidden()
    monkeypatch.setattr(_parallel, "PARALLEL_FITS", 1)
    serial_log = _watch_fits(monkeypatch)
    one = diagnose(ds, res)
    monkeypatch.undo()
    monkeypatch.setattr(_parallel, "PARALLEL_FITS", 12)  # threads enough for every refit and held-out fit at once
    log = _watch_fits(monkeypatch, refit_waits_s=10.0)
    two = diagnose(ds, res)
    validated = {c.label for c in one.candidates if c.held_out_after_nT is not None}
    assert "temperature_bias" in validated
    refits_seen = {labels[-1]: seen for kind, labels, seen in log if kind == "refit" and len(labels) == 1}
    for label in validated:
        assert refits_seen[label] is True, f"the held-out fits of {label} waited for its refit"
    # the second round's too: its candidate added to the first round's choice
    assert one.explained_by == ["temperature_bias", "bias_step:3"] == two.explained_by
    second = [seen for kind, labels, seen in log if kind == "refit" and labels == ("temperature_bias", "bias_step:3")]
    assert second == [True]
    assert [c.label for c in one.candidates] == [c.label for c in two.candidates]
    for a, b in zip(one.candidates, two.candidates):
        assert a.holds == b.holds and a.transfers == b.transfers
        for name in ("held_out_before_nT", "held_out_after_nT", "later_before_nT", "later_after_nT"):
            x, y = getattr(a, name), getattr(b, name)
            assert (x is None and y is None) or x == pytest.approx(y, rel=1e-9), name
    assert one.summary == two.summary
    # one by one, no held-out fit is made for a candidate its refit does not support
    made = {labels[-1] for kind, labels, _ in serial_log if kind == "held_out" and len(labels) == 1}
    assert made == validated


def test_held_out_fits_start_where_the_refit_starts_and_agree_with_the_refits_start(monkeypatch):
    """The held-out fits of a candidate start from its score test's predicted start, not from its refit: the
    held-out RMS agree with those warm-started from the refit (the one-step estimator reaches the training
    samples' minimum from either) to well within their spread."""
    from magcal.diagnosis import verdict

    ds, res = two_hidden(4000)
    monkeypatch.setattr(_parallel, "PARALLEL_FITS", 1)
    now = diagnose(ds, res)

    def from_the_refit(self, base_fit, c, scheme):
        return self._validate(c.fit.model, c.fit.calibration, scheme)

    monkeypatch.setattr(verdict._HeldOut, "with_effect", from_the_refit)
    before = diagnose(ds, res)
    pairs = [(a, b) for a, b in zip(now.candidates, before.candidates) if a.held_out_after_nT is not None]
    assert len(pairs) >= 2 and [a.label for a, _ in pairs] == [b.label for _, b in pairs]
    for a, b in pairs:
        assert a.holds == b.holds
        for name in ("held_out_after_nT", "later_after_nT"):
            x, y = getattr(a, name), getattr(b, name)
            assert x == pytest.approx(y, rel=2e-3), (a.label, name)


def test_one_worker_runs_everything_in_the_calling_thread(monkeypatch):
    """``workers=1`` (``--workers 1``) is one core: the candidates' data-derived constants and the score round's
    chunks, which run side by side on threads otherwise, run in the calling thread too, whatever the cores."""
    from magcal.model.terms import EFFECTS

    ds, res = two_hidden(2000)
    monkeypatch.setattr(_parallel, "cores", lambda: 8)
    seen = set()
    for name in ("bias_step", "temperature_bias", "bias_drift"):
        cls = EFFECTS[name]

        def configure(self, *args, real=cls.configure, **kwargs):
            seen.add(threading.get_ident())
            return real(self, *args, **kwargs)

        monkeypatch.setattr(cls, "configure", configure)
    diagnose(ds, res, workers=1)
    assert seen == {threading.get_ident()}
    seen.clear()
    diagnose(ds, res, workers=3)
    assert len(seen) > 1  # the test sees threads where they are allowed


def test_a_rounds_base_held_out_fit_is_made_once_whoever_asks(monkeypatch):
    """The base model's held-out fit of a round is prepared ahead (beside the refits) and asked for again by the
    judgement: a second caller while the first is still fitting waits for it instead of fitting again, and a
    failure reaches both."""
    from magcal.diagnosis import verdict

    ds, res = two_hidden(1500)
    held_out = verdict._HeldOut(ds, res.fit)
    made = []

    def slow_validate(self, model, init, scheme):
        made.append(scheme)
        time.sleep(0.3)
        if scheme == "later":
            raise np.linalg.LinAlgError("singular")
        return object()

    monkeypatch.setattr(verdict._HeldOut, "_validate", slow_validate)
    got = {}

    def ask(name, scheme):
        try:
            got[name] = held_out.base(res.fit, scheme)
        except np.linalg.LinAlgError as exc:
            got[name] = exc

    threads = [threading.Thread(target=ask, args=(f"{s}{k}", s)) for s in ("blocks", "later") for k in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(10)
    assert sorted(made) == ["blocks", "later"]  # one fit per scheme
    assert got["blocks0"] is got["blocks1"]
    assert isinstance(got["later0"], np.linalg.LinAlgError) and got["later0"] is got["later1"]


def test_a_refit_handed_to_a_worker_takes_the_step_times_found_here(monkeypatch):
    """A refit in a worker process would scan its readings for a bias step again (the worker keeps its own
    readings cache: 0.13 s at 4 x 1e5); the caller hands it the step indices it found (small numbers), and the
    refit scans nothing and fits the same."""
    from magcal.diagnosis import scores
    from magcal.model import effects
    from magcal.model.terms import EFFECTS

    ds, res = two_hidden(2000)
    fit = res.fit
    for s in range(ds.n_sensors):
        effects.step_index(ds.readings_nT[s])
    facts = scores._readings_facts_of(ds, fit.mask)
    assert sorted(s for s, key, _ in facts if key[0] == "step index") == list(range(ds.n_sensors))

    class Remote:  # a pool whose fits run elsewhere: what it is handed
        is_remote = True
        handed: list = []

        def remote(self, fn, *args):
            self.handed.append(args)
            effects._READINGS_CACHE.clear()  # as a worker that has not seen these readings
            return fn(ds, *args)

    scans = []
    real = effects._step_scan
    monkeypatch.setattr(effects, "_step_scan", lambda *a: scans.append(1) or real(*a))
    cand = scores.Candidate(
        effect="bias_step",
        sensor=None,
        label="bias_step",
        n_params=3,
        lm=0.0,
        p_value=1.0,
        predicted_delta_bic=0.0,
        delta_bic=0.0,
        rms_after_nT=0.0,
        instances=[EFFECTS["bias_step"]()],
    )
    there = scores._refit(ds, fit, cand, Remote())
    assert Remote.handed[0][-1] == facts and scans == []
    effects._READINGS_CACHE.clear()
    here = scores._refit(ds, fit, cand)  # no facts: it scans
    assert len(scans) == ds.n_sensors
    assert there.rss == pytest.approx(here.rss, rel=1e-12)
    np.testing.assert_allclose(there.x, here.x, rtol=1e-10, atol=1e-9)
