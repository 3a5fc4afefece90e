"""What a large record costs beyond its size, and what one core means (issue 30, the session of 2026-11-26).

Each part prints the figure before and after a change of that session, in the same run:

- ``malloc``: a bias-step refit and the calibration of 4 x N samples in a fresh program, with glibc's default
  allocator settings and with :func:`magcal.core.memory.keep_large_blocks` ``(every_size=True)`` (as the
  diagnosis's worker processes now run): seconds and peak resident memory. Above 32 MB glibc maps every array
  afresh, zeroed and faulted in.
- ``evidence``: the time evidence's smoothed residuals of 4 x N samples by the convolution it used
  (``numpy.convolve`` with a window of a sixtieth of the record: N^2/60 operations) and by
  :func:`magcal.core.stats.moving_mean` (running sums).
- ``one-core``: a diagnosis asked for one worker: its processor time against its wall time, with the score
  round's chunks and the candidates' constants on ``in_parallel``'s own threads (as before) and held to the pool's
  one worker (now).
- ``rejected``: a diagnosis of the whole record and of the record with 0.5 % of its samples rejected: seconds, and
  how often the bias-step scan and the noise's readings-only facts were computed, with the kept samples cut anew
  for every fit (as before: ``Dataset.masked`` made a plain subset) and shared (now).
- ``ready``: seconds until the first worker process of a program answers, the fork server cold and started
  1.5 s before (:func:`magcal.diagnosis.start_workers`).

Usage::

    python benchmarks/large_records.py                          # every part, about 3 minutes on 2 cores
    python benchmarks/large_records.py --parts evidence --n 1e6
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
PARTS = ("malloc", "evidence", "one-core", "rejected", "ready")


def _record(n, seed=2):
    sys.path.insert(0, str(HERE))
    import scaling

    return scaling._record(n, seed=seed)


def child_malloc(n, every_size):
    """(In a fresh program.) Calibration and bias-step refit seconds, peak resident MB."""
    import resource

    from magcal.core.memory import keep_large_blocks

    if every_size:
        keep_large_blocks(every_size=True)
    from magcal.diagnosis import scores
    from magcal.fitting.pipeline import calibrate
    from magcal.model import effects
    from magcal.model.terms import EFFECTS

    ds = _record(n)
    t0 = time.perf_counter()
    fit = calibrate(ds).fit
    t_cal = time.perf_counter() - t0
    for s in range(ds.n_sensors):
        effects.step_index(ds.readings_nT[s])  # the scans, as a diagnosis's score round leaves them
    model = fit.model.with_effect(EFFECTS["bias_step"]())
    t0 = time.perf_counter()
    scores.refit_task(ds, model, fit.calibration, fit.mask, None)
    t_refit = time.perf_counter() - t0
    return t_cal, t_refit, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def child_ready(early):
    """(In a fresh program.) Seconds until a pool's first worker answers."""
    from magcal.diagnosis import _parallel, start_workers

    _parallel.BACKEND = "processes"
    ds = _record(2000)
    if early:
        start_workers(ds, 2)
        time.sleep(1.5)  # what the caller does meanwhile (a user looking at the page)
    t0 = time.perf_counter()
    with _parallel.Pool(ds, workers=2) as pool:
        pool.remote(_parallel._ready)
        return time.perf_counter() - t0


def run_child(*args):
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}
    env = {k: v for k, v in env.items() if not k.startswith("MALLOC_")}
    out = subprocess.run(
        [sys.executable, __file__, "--child", json.dumps(list(args))], capture_output=True, text=True, env=env
    )
    if out.returncode != 0:
        raise SystemExit(out.stderr[-3000:])
    return json.loads(out.stdout.strip().splitlines()[-1])


def part_evidence(n):
    import numpy as np

    from magcal.core.stats import moving_mean

    r = np.random.default_rng(1).normal(0.0, 3.0, size=(4, n))
    w = max(1, n // 60)
    t0 = time.perf_counter()
    old = np.array([np.convolve(row, np.ones(w) / w, mode="same") for row in r])
    t_old = time.perf_counter() - t0
    t0 = time.perf_counter()
    new = moving_mean(r, w)
    t_new = time.perf_counter() - t0
    inside = slice(w, n - w)
    same = bool(np.allclose(old[:, inside], new[:, inside], atol=1e-9))
    print(
        f"evidence  4 x {n:,}: smoothing by convolution {t_old:.2f} s, by running sums {t_new:.3f} s "
        f"(the same away from the ends: {same})"
    )


def part_one_core(n):
    from magcal.diagnosis import diagnose, scores
    from magcal.fitting.pipeline import calibrate

    ds = _record(n, seed=1)
    res = calibrate(ds)
    real = scores.in_parallel
    for label, patched in (("own threads (before)", lambda calls, pool=None: real(calls)), ("held to it (now)", None)):
        scores.in_parallel = patched or real
        try:
            cpu, wall = time.process_time(), time.perf_counter()
            diagnose(ds, res, workers=1)
            cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
        finally:
            scores.in_parallel = real
        print(f"one-core  4 x {n:,}, workers=1, in_parallel {label:>20}: {cpu:.2f} s of processor in {wall:.2f} s")


def part_rejected(n):
    import numpy as np

    from magcal.checks import noise
    from magcal.data import dataset as dataset_module
    from magcal.diagnosis import diagnose
    from magcal.fitting.pipeline import calibrate
    from magcal.model import effects

    ds = _record(n, seed=1)
    rejected = np.ones(ds.n_samples, bool)
    rejected[::200] = False
    counts = {}
    real_scan, real_facts = effects._step_scan, noise.still_noise_nT  # the latter: once per computation of the facts

    def scan(*args):
        counts["scans"] = counts.get("scans", 0) + 1
        return real_scan(*args)

    def facts(*args, **kwargs):
        counts["noise"] = counts.get("noise", 0) + 1
        return real_facts(*args, **kwargs)

    real_masked = dataset_module.Dataset.masked

    def cut_anew(self, mask):  # as before Dataset.masked: every fit cut its samples anew
        mask = np.asarray(mask, bool)
        return self if mask.all() else self.subset(mask)

    effects._step_scan, noise.still_noise_nT = scan, facts
    try:
        for way, masked in (("cut anew (before)", cut_anew), ("shared (now)", real_masked)):
            dataset_module.Dataset.masked = masked  # type: ignore[method-assign]
            for what, mask in (("whole record", None), ("0.5 % rejected", rejected)):
                effects._READINGS_CACHE.clear()
                noise._READINGS_FACTS.clear()
                res = calibrate(ds, mask=mask)
                counts.clear()
                t0 = time.perf_counter()
                diagnose(ds, res, workers=1)
                print(
                    f"rejected  4 x {n:,}, {way:>17}, {what:>14}: {time.perf_counter() - t0:.2f} s, step scans "
                    f"{counts.get('scans', 0)}, the noise's readings facts {counts.get('noise', 0)}"
                )
    finally:
        effects._step_scan, noise.still_noise_nT = real_scan, real_facts
        dataset_module.Dataset.masked = real_masked  # type: ignore[method-assign]


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--parts", default=",".join(PARTS))
    p.add_argument("--n", default="1e6", help="samples per sensor of the malloc and evidence parts")
    p.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child is not None:
        kind, *rest = json.loads(args.child)
        print(json.dumps({"malloc": child_malloc, "ready": child_ready}[kind](*rest)))
        return
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    n = int(float(args.n))
    parts = args.parts.split(",")
    print(f"{os.cpu_count()} core(s), load {os.getloadavg()[0]:.2f} at the start")
    if "malloc" in parts:
        for every_size in (False, True, False, True):
            t_cal, t_refit, peak = run_child("malloc", n, every_size)
            how = "every size from the heap" if every_size else "glibc's default"
            print(
                f"malloc    4 x {n:,}, {how:>24}: calibrate {t_cal:.2f} s, refit {t_refit:.2f} s, peak {peak:,.0f} MB"
            )
    if "evidence" in parts:
        part_evidence(n)
    if "one-core" in parts:
        part_one_core(100_000)
    if "rejected" in parts:
        part_rejected(100_000)
    if "ready" in parts:
        for early in (False, True):
            t = run_child("ready", early)
            print(f"ready     first worker answers in {t:.2f} s, fork server {'started early' if early else 'cold'}")
    print(f"load {os.getloadavg()[0]:.2f} at the end")


if __name__ == "__main__":
    main()
