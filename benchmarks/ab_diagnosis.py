"""Two (or more) versions of magcal side by side on the 4 x 1e5 diagnosis, run in alternation.

This machine's speed wanders by a third from hour to hour, so two runs of ``diagnosis.py`` made an hour apart do
not tell which code is faster. Running the versions one after the other, round after round, exposes them to the
same wander; the medians then compare the code. Each run is a fresh process (four sensors, N = 1e5, chi2017
truth, 3 nT noise, a 0.5 nT/K temperature bias hidden, ``OPENBLAS_NUM_THREADS=1``) timing ``calibrate`` and
``diagnose`` and reading the CPU time (user + system) and minor page faults of the diagnosis.

Usage::

    git worktree add /tmp/before <commit>          # the version to compare against
    python benchmarks/ab_diagnosis.py /tmp/before . --rounds 6
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys

RUN = r"""
import os, resource, time
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
import magcal.model.effects as fx
from magcal.model import perturbations
from magcal import calibrate, diagnose
from magcal.data.simulation import chi2017_truth, simulate_timeseries

ds = simulate_timeseries(chi2017_truth(4), n_samples=100_000, noise_nT=3.0, seed=1,
                         perturbations=[perturbations.parse_hidden("temperature_bias=0.5", 4)])
t0 = time.perf_counter()
res = calibrate(ds)
t1 = time.perf_counter()
r1 = resource.getrusage(resource.RUSAGE_SELF)
d = diagnose(ds, res)
t2 = time.perf_counter()
r2 = resource.getrusage(resource.RUSAGE_SELF)
cpu = (r2.ru_utime - r1.ru_utime) + (r2.ru_stime - r1.ru_stime)
print("RESULT", t1 - t0, t2 - t1, cpu, r2.ru_minflt - r1.ru_minflt, d.verdict, d.explained_by[0])
"""


def run_once(checkout: str) -> tuple:
    env = dict(os.environ, PYTHONPATH=os.path.abspath(checkout), OPENBLAS_NUM_THREADS="1")
    out = subprocess.run([sys.executable, "-c", RUN], capture_output=True, text=True, env=env, cwd="/", check=False)
    line = next((x for x in out.stdout.splitlines() if x.startswith("RESULT")), None)
    if line is None:
        raise SystemExit(f"{checkout}: the run failed:\n{out.stderr[-2000:]}")
    _, cal, diag, cpu, faults, verdict, best = line.split()
    return float(cal), float(diag), float(cpu), int(faults), f"{verdict} / {best}"


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkouts", nargs="+", help="directories holding a magcal package (a worktree, a clone)")
    parser.add_argument("--rounds", type=int, default=5, help="runs of each version, in alternation")
    args = parser.parse_args()
    for path in args.checkouts:
        if not os.path.isfile(os.path.join(path, "magcal", "__init__.py")):
            raise SystemExit(f"{path}: no magcal package there (expected {path}/magcal/__init__.py)")
    runs = {path: [] for path in args.checkouts}
    for _ in range(args.rounds):
        for path in args.checkouts:
            runs[path].append(run_once(path))
    print(f"4 x 1e5 diagnosis, {args.rounds} runs of each version in alternation (medians; min in brackets)")
    print(f"{'version':<28}{'calibrate s':>12}{'diagnose s':>18}{'CPU s':>8}{'faults':>9}  verdict / best")
    for path, rows in runs.items():
        cal, diag, cpu, faults = ([r[k] for r in rows] for k in range(4))
        verdicts = sorted({r[4] for r in rows})
        print(
            f"{path:<28}{statistics.median(cal):>12.3f}{statistics.median(diag):>10.3f} ({min(diag):.3f})"
            f"{statistics.median(cpu):>8.2f}{int(statistics.median(faults)):>9d}  {', '.join(verdicts)}"
        )


if __name__ == "__main__":
    main()
