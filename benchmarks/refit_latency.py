"""The page's buttons in-process, without a browser: where a click's wait goes, BLAS threads before/after (issue 44).

    python benchmarks/refit_latency.py [--file CSV | --n 100000] [--repeat 3] [--effects bias_step ...]

What it shows: the workbench (:class:`magcal_workbench.app.Workbench`, a real viser server, no browser) built on a
four-sensor record, and the buttons the page's benchmark clicks (``benchmarks/page_latency.py``) pressed as the page
presses them (``button.value = True``, then the job and its pending parts waited for): *Run the chosen method*
(:meth:`Controller.step_calibrate`: :func:`magcal.fitting.pipeline.calibrate`), *Diagnose*
(:meth:`Controller.step_diagnose`: :func:`magcal.diagnosis.diagnose`), *Add the candidate and refit* (the top
candidate, :meth:`Controller.step_add` -> :meth:`Controller.step_refine`: :func:`magcal.fitting.fitter.fit` of the
grown model, warm from the current calibration) and *Exclude range* (40-50 % of the record, the page's default;
:meth:`Controller.select` then the refit, :meth:`Controller.step_refine` on the kept samples). For each click: the
wall time to the result (the job's end), and the engine's spans inside it (``fit``, ``diagnose``: the same spans
``MAGCAL_TIMING=1`` logs, :mod:`magcal_workbench.timing`) and the held-out check that follows.

Rows ``before`` run the fits on OpenBLAS's default threads (one per core, what every fit did before issue 44's
change: :data:`magcal.fitting.fitter.ONE_BLAS_THREAD_READINGS` set out of reach), ``after`` as shipped (BLAS on one
thread inside a large fit, :func:`magcal.core.blas.one_blas_thread`); the two alternate launch by launch so that the
machine's load weighs on both alike. The load average (``/proc/loadavg``) is printed beside the table: on a busy
machine OpenBLAS's spinning threads are what made the refits 3-30x slower than the base fit.

A second table, engine only (no workbench): :func:`magcal.fitting.fitter.fit` of the base calibration grown by each
effect of ``--effects`` (the Add), then of that fit with 10 % of the samples excluded (the Exclude), before/after,
with the RMS each reaches (the same, to the fit's tolerance).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
import warnings
from pathlib import Path

import numpy as np

import magcal
from magcal.data.io import read_csv
from magcal.fitting import fitter, pipeline
from magcal.model.terms import Model

#: The two settings compared: the largest fit BLAS is kept on one thread from (readings), before and after.
SETTINGS = {"before": 10**15, "after": fitter.ONE_BLAS_THREAD_READINGS}
CLICKS = ("Run", "Diagnose", "Add-and-refit", "Exclude range")


def _load() -> str:
    return " ".join(Path("/proc/loadavg").read_text().split()[:3])


def _spans():
    """Collect the workbench's timing spans in this process (instead of its standard error)."""
    from magcal_workbench import timing

    got: list = []
    timing.enable(True)
    timing.log = lambda name, start_s, seconds: got.append((name, start_s, seconds))  # type: ignore[assignment]
    return got


def one_launch(ds, setting: str) -> dict:
    """Build the workbench on ``ds`` and press the four buttons; seconds per click and per span inside it."""
    from magcal_workbench.app import Workbench

    fitter.ONE_BLAS_THREAD_READINGS = SETTINGS[setting]
    spans = _spans()
    wb = Workbench(ds, port=0, store=None)
    out: dict = {}
    try:
        p = wb.panels
        buttons = (p.btn_run, p.btn_diagnose, p.btn_add, p.btn_exclude_range)
        for label, button in zip(CLICKS, buttons):
            wb.worker.pending.wait(600)  # as the page's benchmark: the previous click's slow parts ended first
            spans.clear()
            t0 = time.perf_counter()
            button.value = True
            time.sleep(0.05)  # the callback hands the job to the worker
            wb.worker.wait(600)
            out[label] = time.perf_counter() - t0
            wb.worker.pending.wait(600)
            out[f"{label}: all parts"] = time.perf_counter() - t0
            for name, _start, sec in spans:
                if name in ("fit", "diagnose", "heldout"):
                    out[f"{label} {name}"] = out.get(f"{label} {name}", 0.0) + sec
            out[f"{label}: line"] = wb.ctrl.message.split("\n")[0][:90]
    finally:
        wb.stop()
        fitter.ONE_BLAS_THREAD_READINGS = SETTINGS["after"]
    return out


def engine_refits(ds, effects, repeat: int) -> list[tuple]:
    """(effect, setting, add s, exclude s, add RMS, exclude RMS) of :func:`fitter.fit`, best of ``repeat``."""
    base = pipeline.calibrate(ds, method="ml")
    n = ds.n_samples
    kept = np.ones(n, bool)
    kept[int(0.4 * n) : int(0.5 * n)] = False
    rows = []
    for name in effects:
        model = Model.from_names([name], ds.n_sensors)
        best: dict = {}
        for _ in range(repeat):
            for setting in SETTINGS:
                fitter.ONE_BLAS_THREAD_READINGS = SETTINGS[setting]
                t0 = time.perf_counter()
                add = fitter.fit(ds, model, init=base.calibration, warn=False)
                t1 = time.perf_counter()
                exc = fitter.fit(ds, model, init=add.calibration, mask=kept, warn=False)
                t2 = time.perf_counter()
                a, e = best.get(setting, (np.inf, np.inf, 0, 0))[:2]
                best[setting] = (min(a, t1 - t0), min(e, t2 - t1), add.rms_nT, exc.rms_nT)
        fitter.ONE_BLAS_THREAD_READINGS = SETTINGS["after"]
        rows += [(name, s, *best[s]) for s in SETTINGS]
    return rows


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--file", default=None, help="a four-sensor record (default: simulate --n samples, seed 3)")
    ap.add_argument("--n", type=int, default=100_000)
    ap.add_argument("--repeat", type=int, default=3, help="launches per setting (alternating)")
    ap.add_argument("--effects", nargs="*", default=["sensor_timing_skew:2", "bias_step", "temperature_bias"])
    ap.add_argument("--no-workbench", action="store_true", help="only the engine's table")
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    if args.file:
        ds = read_csv(args.file)
    else:
        ds = magcal.simulate_timeseries("chi2017", n_samples=args.n, seed=3)
    print(f"{ds.n_sensors} x {ds.n_samples} samples; load average before: {_load()}")
    if not args.no_workbench:
        runs: dict = {s: [] for s in SETTINGS}
        for i in range(args.repeat):
            for setting in SETTINGS:
                out = one_launch(ds, setting)
                runs[setting].append(out)
                brief = ", ".join(f"{c} {out[c]:.2f}" for c in CLICKS if c in out)
                print(f"  launch {i + 1} {setting}: {brief} (load {_load()})", file=sys.stderr)
        print("\nClick to result (min / median of the launches, s); the engine's span inside it\n")
        print("| click | before: result | before: engine | after: result | after: engine | held-out after |")
        print("|---|---|---|---|---|---|")
        for c in CLICKS:
            cells = []
            for s in SETTINGS:
                res = [r[c] for r in runs[s] if c in r]
                eng = [r.get(f"{c} fit", r.get(f"{c} diagnose", np.nan)) for r in runs[s] if c in r]
                cells += [
                    f"{min(res):.2f} / {statistics.median(res):.2f}",
                    f"{min(eng):.2f} / {statistics.median(eng):.2f}",
                ]
            held = [r.get(f"{c} heldout", np.nan) for r in runs["after"]]
            cells.append(f"{np.nanmin(held):.2f}" if np.isfinite(held).any() else "-")
            print(f"| {c} | " + " | ".join(cells) + " |")
        print("\nresult lines (after, last launch):")
        for c in CLICKS:
            print(f"  {c}: {runs['after'][-1].get(f'{c}: line', '')}")
    rows = engine_refits(ds, args.effects, args.repeat)
    print("\nEngine only, fitter.fit (best of the repeats, s): the Add (base + effect, warm from the base")
    print("calibration) and the Exclude (40-50 % of the record left out, warm from the Add)\n")
    print("| effect | BLAS | Add s | Exclude s | Add RMS nT | Exclude RMS nT |")
    print("|---|---|---|---|---|---|")
    for name, s, a, e, ra, re in rows:
        print(f"| {name} | {s} | {a:.2f} | {e:.2f} | {ra:.6f} | {re:.6f} |")
    print(f"\nload average after: {_load()}")


if __name__ == "__main__":
    main()
