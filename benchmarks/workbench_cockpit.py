"""How long the cockpit takes to redraw (the compact table's figures, |B| against time and the error histogram as
plotly JSON) for records of growing size: every sample counts in the table and histogram, the |B| plot is
decimated to ``magcal_workbench.plots.MAX_POINTS`` per trace.

    PYTHONPATH=$PWD python benchmarks/workbench_cockpit.py

Prints one row per record size: the seconds of each part (best of three) and the bytes the two figures send.
"""

from __future__ import annotations

import time

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


if __name__ == "__main__":
    main()
