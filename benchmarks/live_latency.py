"""Live view latency: from a sample's arrival to the scene update that shows it, server side.

    python benchmarks/live_latency.py [--seconds 30]

A simulated instrument (``sim://chi2017``, four sensors) streams in real time into a workbench with a real viser
server and no browser; :class:`magcal_workbench.live.LiveView` redraws the growing clouds and coverage spheres at most
every ``DRAW_INTERVAL_S`` and refits in the background. For every sample, the latency is the time from the moment
the source emits it (its due time, on the host's monotonic clock) to the end of the scene update that first shows
it. viser then sends the point arrays to the browsers; network and WebGL time are not included.

Printed per rate (50 and 500 Hz): latency median, 95th percentile and maximum; the floor set by the throttle (a
sample waits on average half the draw interval, at most all of it, plus one update); the cost of one update (scene
plus coverage) at the end of the run, when the clouds are largest; the refit count and its last duration. The
seed has no live mode, so the comparison is with the floor.
"""

from __future__ import annotations

import argparse
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np


def run(rate_hz: float, seconds: float):
    from magcal.data import io as mio
    from magcal_workbench.app import Workbench
    from magcal_workbench.lessons import DEMO

    wb = Workbench(mio.read_csv(DEMO), host="127.0.0.1", port=0, store=None)
    update_s = []
    plain = wb.view.update_scene

    def timed_update():
        t0 = time.perf_counter()
        plain()
        update_s.append(time.perf_counter() - t0)

    wb.view.update_scene = timed_update
    fit_s = []
    try:
        n = int(rate_hz * seconds)
        path = Path(tempfile.mkdtemp()) / "live.csv"
        live = wb.livectl.start(f"sim://chi2017?rate={rate_hz:g}&n={n}", path)
        plain_refit = live._refit

        def timed_refit(ds):
            t0 = time.perf_counter()
            plain_refit(ds)
            fit_s.append(time.perf_counter() - t0)

        live._refit = timed_refit
        source = live.session.source
        end = time.monotonic() + seconds + 30
        while time.monotonic() < end and (live.session.running or live.n_drawn < live.n_samples):
            time.sleep(0.1)
        log = list(live.draw_log)
        live.stop()
        due = source._start + source._times[:n] / source.speed
        lat, prev = [], 0
        for t_draw, n_drawn in log:
            lat.append(t_draw - due[prev:n_drawn])
            prev = n_drawn
        lat = np.concatenate(lat) if lat else np.zeros(0)
        return {
            "rate": rate_hz,
            "n": n,
            "received": prev,
            "latency": lat,
            "updates": len(log),
            "update_last_s": float(np.median(update_s[-5:])) if update_s else float("nan"),
            "fits": len(fit_s),
            "fit_last_s": fit_s[-1] if fit_s else float("nan"),
        }
    finally:
        wb.stop()


def main(argv=None) -> int:
    from magcal_workbench.live import DRAW_INTERVAL_S

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=30.0, help="length of each stream, s")
    args = p.parse_args(argv)
    warnings.simplefilter("ignore")
    rows = [run(rate, args.seconds) for rate in (50.0, 500.0)]
    print(
        f"\nLive latency, sample emitted -> scene updated (server side), four sensors, {args.seconds:g} s streams; "
        f"draw interval {DRAW_INTERVAL_S * 1e3:.0f} ms"
    )
    print(
        f"{'rate':>7} {'samples':>8} {'updates':>8} {'median':>9} {'p95':>9} {'max':>9} {'floor mean':>11} "
        f"{'update':>9} {'fits':>5} {'last fit':>9}"
    )
    for r in rows:
        lat = r["latency"] * 1e3
        floor = (0.5 * DRAW_INTERVAL_S + r["update_last_s"]) * 1e3
        print(
            f"{r['rate']:>5.0f}Hz {r['received']:>8d} {r['updates']:>8d} {np.median(lat):>7.0f}ms "
            f"{np.percentile(lat, 95):>7.0f}ms {lat.max():>7.0f}ms {floor:>9.0f}ms "
            f"{r['update_last_s'] * 1e3:>7.0f}ms {r['fits']:>5d} {r['fit_last_s'] * 1e3:>7.0f}ms"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
