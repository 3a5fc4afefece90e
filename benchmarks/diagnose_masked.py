"""Diagnose after Exclude range (issue 44): the diagnosis of a fit with a time range left out, against the same
record's diagnosis without it, on simulated four-sensor records (``magcal simulate --timeseries --n N --seed 3``).

    PYTHONPATH=$PWD python benchmarks/diagnose_masked.py [--n 10000 100000] [--repeat 3] [--before] [--workbench]

What the workbench's Exclude range does, in the engine: the samples from 40 % to 50 % of the record (the sliders'
defaults) are rejected and the model is fitted on the rest (``pipeline.calibrate(..., mask=kept)``); Diagnose then
calls :func:`magcal.diagnosis.diagnose` on that fit. The kept stamps have a hole, so the diagnosis's spectra are
Lomb-Scargle periodograms (:func:`magcal.diagnosis.statistics.spectrum`). Before the fix these were direct sums over
every sample and frequency (``N x N/2`` complex products per spectrum, eight spectra per diagnosis): 68-95 s at
4 x 1e5 against 2-8 s without the hole. They now come from FFTs of the samples placed on a grid
(:func:`magcal.diagnosis.statistics.lomb_scargle_grid`): two of the record's own grid here.

Prints one markdown row per record size and case: the diagnosis's wall time (min and median of ``--repeat``), its
verdict and top candidate, and the spectra's work: grid transforms (calls, points in all) and direct products
(samples x frequencies in all: the work the bug did). ``--before`` adds the masked case with the direct sums put
back (:func:`direct_terms`, the code before the fix; minutes at 4 x 1e5). ``--workbench`` adds the page's own
path, headless (no browser): the workbench on the record, Run, (Exclude range,) then the Diagnose button timed to
the end of its job, with the engine's ``diagnose`` span inside it.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
from page_latency import simulate  # the same simulated records (this folder is on the path when run)

#: The Exclude range sliders' defaults, as shares of the record.
RANGE = (0.40, 0.50)


def direct_terms(t, r, df_hz, n_freq):
    """The Lomb-Scargle sums as magcal computed them before the fix (for ``--before``): a recurrence over the
    frequencies, ``N`` products per frequency."""
    step = np.exp(2j * np.pi * df_hz * t)
    z = np.ones(t.size, dtype=complex)
    yz = np.empty(int(n_freq), dtype=complex)
    z2 = np.empty(int(n_freq), dtype=complex)
    for i in range(int(n_freq)):
        z *= step
        if i % 64 == 63:
            z /= np.abs(z)
        yz[i] = r @ z
        z2[i] = np.sum(z * z)
    return yz, z2


class SpectrumWork:
    """Counts the spectra's work while installed: grid transforms (``statistics._grid_sums``: calls, points) and,
    with ``direct``, the direct sums put back in place of the transforms (samples x frequencies)."""

    def __init__(self, direct: bool = False):
        from magcal.diagnosis import statistics as st

        self.st, self.direct = st, direct
        self.saved = st._grid_sums, st._lomb_scargle_terms
        self.transforms, self.points, self.products = 0, 0, 0

    def __enter__(self):
        grid_sums = self.saved[0]

        def counted_sums(index, weights, cells):
            self.transforms += 1
            self.points += int(cells)
            return grid_sums(index, weights, cells)

        def counted_direct(t, r, df_hz, n_freq):
            self.products += int(t.size) * int(n_freq)
            return direct_terms(t, r, df_hz, n_freq)

        self.st._grid_sums = counted_sums
        if self.direct:
            self.st._lomb_scargle_terms = counted_direct
        return self

    def __exit__(self, *exc):
        self.st._grid_sums, self.st._lomb_scargle_terms = self.saved

    def text(self) -> str:
        return f"{self.transforms}, {self.points:.3g} | {self.products:.3g}"


def kept_mask(n: int) -> np.ndarray:
    keep = np.ones(n, bool)
    keep[int(RANGE[0] * n) : int(RANGE[1] * n)] = False
    return keep


def engine_case(ds, mask, repeat: int, direct: bool = False) -> dict:
    """Fit with ``mask`` (None: every sample), then time ``diagnose`` ``repeat`` times (with ``direct``, the
    spectra's direct sums of before the fix)."""
    from magcal.diagnosis import diagnose
    from magcal.fitting import pipeline

    fit = pipeline.calibrate(ds, method="ml", mask=mask, seed=0).fit
    times = []
    for _ in range(repeat):
        with SpectrumWork(direct) as work:
            t0 = time.perf_counter()
            d = diagnose(ds, fit)
            times.append(time.perf_counter() - t0)
    top = d.candidates[0].label if d.candidates else "-"
    return {"times": times, "verdict": d.verdict, "top": top, "work": work.text()}


def workbench_case(ds, repeat: int, exclude: bool = True) -> dict:
    """The page's path, headless: Run, Exclude range (40-50 %; not with ``exclude`` False), then Diagnose timed to
    the end of its job (the page's updates after it included)."""
    from magcal_workbench import timing
    from magcal_workbench.app import Workbench

    spans: list = []
    was_on, original_log = timing.enabled(), timing.log
    timing.enable(True)
    timing.log = lambda name, start_s, seconds: spans.append((name, seconds)) if name == "diagnose" else None
    wb = Workbench(ds, port=0, store=None)
    try:
        wb.panels.btn_run.value = True
        assert wb.worker.wait(600), "Run did not finish"
        if exclude:
            wb.panels.range_from.value, wb.panels.range_to.value = 100 * RANGE[0], 100 * RANGE[1]
            wb.panels.btn_exclude_range.value = True
            assert wb.worker.wait(600), "Exclude range did not finish"
        kept = int(wb.ctrl.kept.sum())
        times = []
        with SpectrumWork() as work:
            for _ in range(repeat):
                t0 = time.perf_counter()
                wb.panels.btn_diagnose.value = True
                assert wb.worker.wait(900), "Diagnose did not finish"
                times.append(time.perf_counter() - t0)
        d = wb.ctrl.diagnosis
        top = d.candidates[0].label if d is not None and d.candidates else "-"
        verdict = d.verdict if d is not None else "(none: " + wb.ctrl.message[:80] + ")"
    finally:
        wb.stop()
        timing.log = original_log
        timing.enable(was_on)
    return {
        "engine": [seconds for _, seconds in spans],
        "times": times,
        "verdict": verdict,
        "top": top,
        "work": work.text(),
        "kept": kept,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, nargs="+", default=[10000, 100000], help="samples per sensor")
    ap.add_argument("--repeat", type=int, default=3, help="diagnoses per case (min and median shown)")
    ap.add_argument("--before", action="store_true", help="also the masked case with the grid path off (slow)")
    ap.add_argument("--workbench", action="store_true", help="also the workbench's Diagnose after Exclude range")
    ap.add_argument("--data", default=None, help="folder of the simulated records (default: a temporary folder)")
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    import magcal
    from magcal.diagnosis import start_workers

    print(f"load average before: {' '.join(f'{x:.2f}' for x in os.getloadavg())}; cores: {os.cpu_count()}")
    print()
    print(
        "| record | case | diagnose min s | median s | of which diagnose() s | verdict | top candidate | "
        "transforms (calls, points) | direct products |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(args.data) if args.data else Path(tmp)
        for n in args.n:
            ds = magcal.read_csv(simulate(n, folder))
            start_workers(ds)  # as the workbench does on opening: the fork server's imports not in the first case
            mask = kept_mask(ds.n_samples)
            cases = [("every sample", lambda: engine_case(ds, None, args.repeat))]
            cases.append((f"{RANGE[0]:.0%}-{RANGE[1]:.0%} excluded", lambda: engine_case(ds, mask, args.repeat)))
            if args.before:
                cases.append(("excluded, direct sums (before)", lambda: engine_case(ds, mask, 1, direct=True)))
            if args.workbench:
                cases.append(("workbench: Run, Diagnose", lambda: workbench_case(ds, args.repeat, exclude=False)))
                cases.append(("workbench: Run, Exclude range, Diagnose", lambda: workbench_case(ds, args.repeat)))
            for name, run in cases:
                r = run()
                t = r["times"]
                inner = f"{statistics.median(r['engine']):.2f}" if r.get("engine") else "-"
                print(
                    f"| {ds.n_sensors} x {ds.n_samples} | {name} | {min(t):.2f} | {statistics.median(t):.2f} | {inner} | "
                    f"{r['verdict']} | `{r['top']}` | {r['work']} |",
                    flush=True,
                )
    print()
    print(f"load average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
