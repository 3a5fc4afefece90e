"""How long the cockpit takes to redraw (the compact table's figures, |B| against time and the error histogram as
plotly JSON) for records of growing size: every sample counts in the table and histogram, the |B| plot is
decimated to ``magcal_workbench.plots.MAX_POINTS`` per trace.

    PYTHONPATH=$PWD python benchmarks/workbench_cockpit.py [--page]

Prints one row per record size: the seconds of each part (best of three) and the bytes the two figures send.
``--page`` also times the whole page's redraw in a served workbench (no browser) on a simulated four-sensor record
of 1e6 samples with attitude (the chi2017 preset): after a selection (a threshold rejection) and after a fit, best
of three each, beside one computation of the turn rate from the attitude (:func:`magcal.data.attitude.
turn_rate_dps`), which the redraw reads once per dataset.
"""

from __future__ import annotations

import sys
import time
import warnings

import numpy as np

from magcal_workbench import plots


def record(n: int, n_sensors: int = 4, seed: int = 0) -> plots.FieldRecord:
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n_sensors, n, 3))
    u /= np.linalg.norm(u, axis=2, keepdims=True)
    corrected = 50_000.0 * u + rng.normal(scale=3.0, size=u.shape)
    raw = corrected * [1.02, 0.99, 1.01] + [300.0, -200.0, 100.0]
    kept = np.ones(n, bool)
    kept[n // 3 : n // 3 + n // 20] = False
    return plots.FieldRecord(np.arange(n) * 0.01, raw, corrected, np.full(n, 50_000.0), kept)


def best(func, repeat: int = 3) -> tuple[float, object]:
    times, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = func()
        times.append(time.perf_counter() - t0)
    return min(times), out


def main() -> None:
    print("| samples x 4 sensors | table s | |B| plot s | histogram s | |B| JSON kB | histogram JSON kB |")
    print("|---|---|---|---|---|---|")
    for n in (10_000, 100_000, 1_000_000):
        rec = record(n)
        t_table, _ = best(lambda: plots.table_figures(rec))
        t_field, fig = best(lambda: plots.magnitude_figure(rec, (10.0, 20.0)).to_json())
        t_hist, hist = best(lambda: plots.histogram_figure(rec).to_json())
        print(
            f"| {n:,} | {t_table:.3f} | {t_field:.3f} | {t_hist:.3f} | {len(fig) / 1e3:.0f} | {len(hist) / 1e3:.0f} |"
        )


def page_redraw(n: int = 1_000_000) -> None:
    """The served page's redraw after a selection and after a fit (see the module docstring)."""
    import magcal
    from magcal.data.attitude import turn_rate_dps
    from magcal_workbench.app import Workbench

    warnings.simplefilter("ignore")
    ds = magcal.simulate_timeseries("chi2017", n_samples=n, seed=1, rate_hz=50.0)
    t_rate, _ = best(lambda: turn_rate_dps(ds), repeat=1)
    wb = Workbench(ds, host="127.0.0.1", port=0, store=None, max_points=20_000)
    try:
        wb.ctrl.step_calibrate("ml")
        wb.ui.wait()
        wb.ctrl.reject_threshold(4.0)
        wb.ui.wait()
        t_sel, _ = best(lambda: wb.ui.run(lambda: wb._changed(wb.ctrl, "selection")))
        t_fit, _ = best(lambda: wb.ui.run(lambda: wb._changed(wb.ctrl, "result")))
    finally:
        wb.stop()
    print(f"\npage redraw, {n:,} samples x 4 sensors with attitude (served, no browser; best of 3):")
    print(f"after a selection {t_sel:.2f} s; after a fit {t_fit:.2f} s; the turn rate from the attitude {t_rate:.2f} s")


if __name__ == "__main__":
    main()
    if "--page" in sys.argv[1:]:
        page_redraw()
