"""How far the diagnosis can scale, measured on one core: its work, its critical path, and the speedups they allow.

A diagnosis is a graph of fits and tests: some wait for others (a candidate's held-out fits need its refit; the
second round needs the first's verdict), the rest could run side by side. Two numbers bound what any number of
cores can do with it (the work-span model):

- the **work** ``W``: the processor time of everything it computes, one piece after the other;
- the **span** ``S``: the longest chain of pieces that wait for one another -- the time on infinitely many cores.

No machine runs it faster than ``S``, so ``W / S`` bounds the speedup whatever the cores; and a scheduler that
never leaves a core idle while work is ready finishes on ``P`` cores within ``W / P + S`` (Brent's bound), a speedup
of at least ``W / (W / P + S)``. Both hold for the pieces as the diagnosis cuts them, before any cost of moving work
to other processes (their start, the results' trip back), so they are what the code allows, not what a machine
gives: ``benchmarks/scaling.py`` measures that.

How: the diagnosis runs with every piece in the calling thread (``workers=1``), BLAS on one thread, and each piece
handed to its :class:`~magcal.diagnosis._parallel.Pool` (or to ``in_parallel``) is timed in processor seconds
(``time.thread_time``) on a clock of its own that starts where its submitter's stood when it was handed over; a
wait for a piece's result moves the waiter's clock to that piece's end. The waiter's clock at the end is the span.

Usage::

    OPENBLAS_NUM_THREADS=1 python benchmarks/diagnosis_span.py             # 4 x 1e5 samples, the issue's size
    OPENBLAS_NUM_THREADS=1 python benchmarks/diagnosis_span.py --n 1e6 --pieces 12
    OPENBLAS_NUM_THREADS=1 python benchmarks/diagnosis_span.py --hidden "temperature_bias=0.5 bias_step:3=30"
"""

from __future__ import annotations

import argparse
import os
import sys
import threading
import time
from concurrent.futures import Future
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # processor time of this thread is all the work
HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))


class Clock:
    """The virtual clocks: one per chain of work, carried by the thread running it."""

    def __init__(self):
        self.local = threading.local()
        self.pieces = []  # (name, virtual start, processor seconds of its own)

    def _state(self):
        st = self.local
        if not hasattr(st, "now"):
            st.now, st.cpu = 0.0, time.thread_time()
        return st

    def tick(self):
        st = self._state()
        cpu = time.thread_time()
        st.now += cpu - st.cpu
        st.cpu = cpu
        return st

    def run_piece(self, name, call, future: Future):
        """Run ``call`` as a piece of its own: from its submitter's clock, which is left where it was."""
        st = self.tick()
        saved = st.now
        start = st.now
        try:
            result, error = call(), None
        except BaseException as exc:  # the diagnosis handles its pieces' failures
            result, error = None, exc
        st = self.tick()
        future.virtual_end = st.now  # type: ignore[attr-defined]
        self.pieces.append((name, start, st.now - start))
        st.now, st.cpu = saved, time.thread_time()
        if error is not None:
            future.set_exception(error)
        else:
            future.set_result(result)
        return future

    def wait(self, future):
        end = getattr(future, "virtual_end", None)
        if end is not None:
            st = self.tick()
            st.now = max(st.now, end)


def measure(n, seed=1, cold=False, hidden=None):
    """Work, span and pieces of the diagnosis of four sensors of ``n`` samples with a temperature bias hidden
    (as ``benchmarks/scaling.py``). ``cold``: every fit handed to a worker starts with none of the readings' facts
    this process has worked out (a worker process that has not seen them: the bound for the processes backend)."""
    import scaling

    from magcal.diagnosis import _parallel, diagnose, scores
    from magcal.fitting.pipeline import calibrate
    from magcal.model import effects

    if hidden:
        from magcal.data.simulation import chi2017_truth, simulate_timeseries
        from magcal.model import perturbations

        ds = simulate_timeseries(
            chi2017_truth(4),
            n_samples=n,
            noise_nT=3.0,
            seed=seed,
            perturbations=[perturbations.parse_hidden(h, 4) for h in hidden],
        )
    else:
        ds = scaling._record(n, seed=seed)
    res = calibrate(ds)
    clock = Clock()

    def name_of(call):
        return getattr(call, "__qualname__", repr(call)).replace("<locals>.", "").replace("<lambda>", "λ")

    real_result = Future.result

    def result(self, timeout=None):
        clock.wait(self)
        return real_result(self, timeout)

    def submit(self, call, priority=_parallel.CHAIN):
        return clock.run_piece(name_of(call), call, Future())

    def remote_future(self, fn, *args, local=None):
        call = local if local is not None else (lambda: fn(self.dataset, *args))
        if cold:  # as a worker process that has not seen these readings: its step scans are its own
            warm_call = call

            def call():
                saved = dict(effects._READINGS_CACHE._entries)
                effects._READINGS_CACHE.clear()
                try:
                    return warm_call()
                finally:
                    effects._READINGS_CACHE._entries.clear()
                    effects._READINGS_CACHE._entries.update(saved)

        model = next((a for a in args if hasattr(a, "effect_labels")), None)  # the fit's model: say its terms
        name = fn.__name__ + (f" ({', '.join(model.effect_labels) or 'base'})" if model is not None else "")
        return clock.run_piece(name, call, Future())

    def in_parallel(calls, pool=None):
        futures = [clock.run_piece(name_of(c), c, Future()) for c in calls]
        return [f.result() for f in futures]

    real_init = _parallel.Pool.__init__

    def init(self, *args, **kwargs):
        real_init(self, *args, **kwargs)
        self.concurrent = True  # as on many cores: the work a pool with threads hands over ahead is done (and timed)

    saved = (Future.result, _parallel.Pool.submit, _parallel.Pool.remote_future, scores.in_parallel, real_init)
    Future.result = result  # type: ignore[method-assign]
    _parallel.Pool.submit = submit  # type: ignore[method-assign]
    _parallel.Pool.remote_future = remote_future  # type: ignore[method-assign]
    _parallel.Pool.__init__ = init  # type: ignore[method-assign]
    scores.in_parallel = in_parallel
    try:
        clock.local.__dict__.clear()
        cpu0, t0 = time.thread_time(), time.perf_counter()
        clock.tick()
        d = diagnose(ds, res, workers=1)
        span = clock.tick().now
        work = time.thread_time() - cpu0
        wall = time.perf_counter() - t0
    finally:
        (Future.result, _parallel.Pool.submit, _parallel.Pool.remote_future, scores.in_parallel) = saved[:4]
        _parallel.Pool.__init__ = saved[4]  # type: ignore[method-assign]
    return {"work_s": work, "span_s": span, "wall_s": wall, "diagnosis": d, "pieces": clock.pieces}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--n", default="1e5", help="samples per sensor (four sensors)")
    p.add_argument("--pieces", type=int, default=8, help="longest pieces to list")
    p.add_argument(
        "--cold", action="store_true", help="each fit handed to a worker without the readings' facts worked out here"
    )
    p.add_argument(
        "--hidden",
        default=None,
        help="effects hidden in the record instead of the temperature bias, as magcal simulate --hidden takes them, "
        "separated by spaces (e.g. 'temperature_bias=0.5 bias_step:3')",
    )
    args = p.parse_args(argv)
    n = int(float(args.n))
    hidden = args.hidden.split() if args.hidden else None
    m = measure(n, cold=args.cold, hidden=hidden)
    d, work, span = m["diagnosis"], m["work_s"], m["span_s"]
    print(
        f"diagnosis of 4 x {n:,} samples, {' and '.join(hidden or ['temperature_bias'])} hidden: {d.verdict} "
        f"({', '.join(d.explained_by) or d.candidates[0].label}); "
        f"{len(m['pieces'])} pieces"
    )
    print(f"work W {work:.2f} s (processor, one thread; wall {m['wall_s']:.2f} s), span S {span:.2f} s")
    print(f"speedup bound W/S (any number of cores): {work / span:.2f}")
    print(f"{'cores P':>8}{'W/P + S (s)':>13}{'speedup at least':>18}{'at most':>9}")
    for cores in (1, 2, 4, 8, 16, 32):
        t = work / cores + span
        print(f"{cores:>8}{t:>13.2f}{work / t:>18.2f}{min(cores, work / span):>9.2f}")
    print("longest pieces (seconds on their own clock, waits included; virtual start):")
    for name, start, own in sorted(m["pieces"], key=lambda r: -r[2])[: args.pieces]:
        print(f"  {own:6.2f}  at {start:6.2f}  {name[:90]}")


if __name__ == "__main__":
    main()
