"""Where a candidate's held-out fits start: from its refit (until 2026-11-26) or from its predicted start (now).

The diagnosis judges a supported candidate by fits on part of the record scored on the rest
(:mod:`magcal.fitting.validation`): one Gauss-Newton step (the one-step estimator) from a start next to the
whole-record minimum. They used to start from the candidate's refit, so they waited for it: on many cores that
wait was the diagnosis's longest chain (``benchmarks/diagnosis_span.py``). They now start where the refit starts,
the calibration the candidate's score test predicts, and run beside it. This script diagnoses simulated records
with hidden effects of every kind and size both ways and prints, per validated candidate, the held-out RMS of the
``blocks`` and ``later`` splits from either start, their largest relative difference, and whether the verdict,
the ranking and every candidate's judgement (holds, transfers) are the same.

Usage::

    OPENBLAS_NUM_THREADS=1 python benchmarks/held_out_start.py            # 19 records, about 1 minute
    OPENBLAS_NUM_THREADS=1 python benchmarks/held_out_start.py --quick    # 5 of them
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

#: (hidden effects, sensors, samples, seed): every catalogue effect that a record can hide, at its default size
#: and at a large one, and a record hiding none.
CASES = [
    (["temperature_bias=0.5"], 4, 100_000, 1),
    (["bias_step"], 4, 20_000, 2),
    (["bias_step=50"], 1, 20_000, 3),
    (["temperature_scale"], 4, 20_000, 4),
    (["bias_drift"], 4, 20_000, 5),
    (["hysteresis"], 1, 20_000, 6),
    ([], 4, 20_000, 7),
    (["nonlinearity_cubic"], 1, 20_000, 8),
    (["sensor_timing_skew"], 4, 20_000, 9),
    (["temperature_bias", "bias_step"], 4, 20_000, 10),
    (["bias_step=500"], 4, 20_000, 11),
    (["bias_step=2000"], 1, 20_000, 12),
    (["temperature_scale=0.01"], 4, 20_000, 13),
    (["temperature_bias=5"], 4, 20_000, 14),
    (["bias_drift=500"], 4, 20_000, 15),
    (["hysteresis=200"], 1, 20_000, 16),
    (["current_field=100"], 4, 20_000, 17),
    (["nonlinearity_quadratic=1e-5"], 1, 20_000, 18),
    (["periodic_interference=50"], 4, 20_000, 19),
]
QUICK = (1, 2, 5, 11, 15)


def _from_the_refit(self, base_fit, c, scheme):
    """The held-out fit as it was made before: from the candidate's refit."""
    return self._validate(c.fit.model, c.fit.calibration, scheme)


def _run(hidden, ns, n, seed):
    from magcal.data.simulation import chi2017_truth, simulate_timeseries
    from magcal.diagnosis import diagnose, verdict
    from magcal.fitting.pipeline import calibrate
    from magcal.model import perturbations

    ds = simulate_timeseries(
        chi2017_truth(ns),
        n_samples=n,
        noise_nT=3.0,
        seed=seed,
        perturbations=[perturbations.parse_hidden(h, ns) for h in hidden],
    )
    res = calibrate(ds)
    now = verdict._HeldOut.with_effect
    out = {}
    try:
        for way in ("refit", "predicted"):
            verdict._HeldOut.with_effect = _from_the_refit if way == "refit" else now  # type: ignore[method-assign]
            t0 = time.perf_counter()
            d = diagnose(ds, res, workers=1)
            out[way] = (d, time.perf_counter() - t0)
    finally:
        verdict._HeldOut.with_effect = now  # type: ignore[method-assign]
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="five records only")
    args = p.parse_args(argv)
    cases = [c for c in CASES if not args.quick or c[3] in QUICK]
    worst, same_all, rows = 0.0, True, 0
    print(f"{'record':44} {'candidate':24} {'blocks refit -> predicted':>27} {'later refit -> predicted':>27} same")
    for hidden, ns, n, seed in cases:
        out = _run(hidden, ns, n, seed)
        (a, ta), (b, tb) = out["refit"], out["predicted"]
        same = (
            a.verdict == b.verdict
            and [c.label for c in a.candidates] == [c.label for c in b.candidates]
            and all((x.holds, x.transfers) == (y.holds, y.transfers) for x, y in zip(a.candidates, b.candidates))
        )
        same_all &= same
        name = f"{'+'.join(hidden) or 'nothing'} ({ns} x {n:,})"
        print(f"{name:44} verdict {a.verdict} / {b.verdict} ({ta:.1f} / {tb:.1f} s)")
        for x, y in zip(a.candidates, b.candidates):
            if x.held_out_after_nT is None or y.held_out_after_nT is None:
                continue
            rows += 1
            rel = max(
                abs(y.held_out_after_nT - x.held_out_after_nT) / x.held_out_after_nT,
                abs(y.later_after_nT - x.later_after_nT) / x.later_after_nT,
            )
            worst = max(worst, rel)
            print(
                f"{'':44} {x.label:24} {x.held_out_after_nT:12.5g} -> {y.held_out_after_nT:<12.5g}"
                f"{x.later_after_nT:12.5g} -> {y.later_after_nT:<12.5g} {'yes' if same else 'NO'}"
            )
    print(
        f"\n{len(cases)} records, {rows} validated candidates: largest relative difference of a held-out RMS "
        f"{worst:.1e}; verdicts, rankings and judgements the same: {'yes' if same_all else 'NO'}"
    )


if __name__ == "__main__":
    main()
