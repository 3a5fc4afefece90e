"""The readers' fuzz suite (tests/data/test_io_fuzz.py) with many more examples, and what every case gave.

Run: ``python benchmarks/fuzz_readers.py [EXAMPLES_PER_TARGET] [WORKERS] [SELECT]`` (defaults 1000, 2 and every
reader; SELECT is pytest's ``-k`` expression, e.g. ``template`` for the line templates alone). It runs the suite
under pytest with fresh random examples (``MAGCAL_HYPOTHESIS_RANDOM=1``; the suite's own are fixed),
``MAGCAL_FUZZ_EXAMPLES`` per reader, pytest-xdist with WORKERS processes, and prints, per reader: inputs tried,
results, one-line messages, tracebacks, hangs (a case still running after the time bound), the slowest case, and
the totals. Exit status 1 if any case gave a traceback or hung (pytest's report of it is printed too).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def main() -> int:
    examples = int(sys.argv[1]) if len(sys.argv) > 1 else 1000
    workers = int(sys.argv[2]) if len(sys.argv) > 2 else 2
    bound = os.environ.get("MAGCAL_FUZZ_TIME_BOUND_S", "20")
    with tempfile.TemporaryDirectory() as report:
        env = {
            **os.environ,
            "MAGCAL_FUZZ_EXAMPLES": str(examples),
            "MAGCAL_FUZZ_TIME_BOUND_S": bound,
            "MAGCAL_FUZZ_REPORT": report,
            "MAGCAL_HYPOTHESIS_RANDOM": "1",  # fresh examples each run (the suite's are fixed)
            "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""),
        }
        argv = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "tests/data/test_io_fuzz.py"]
        argv += ["-n", str(workers)] if workers > 1 else ["-n", "0"]
        if len(sys.argv) > 3:
            argv += ["-k", sys.argv[3]]
        t0 = time.perf_counter()
        proc = subprocess.run(argv, cwd=ROOT, env=env, capture_output=True, text=True)
        seconds = time.perf_counter() - t0
        tallies = {}
        for path in sorted(Path(report).glob("tally-*.json")):
            tallies.update(json.loads(path.read_text()))
    print(f"fuzz suite: {examples} examples per reader, time bound {float(bound):g} s per case, {workers} worker(s)")
    print(
        f"{'reader':20s} {'inputs':>7s} {'results':>8s} {'messages':>9s} {'tracebacks':>11s} {'hangs':>6s} {'slowest':>8s}"
    )
    total = {"tried": 0, "results": 0, "messages": 0, "tracebacks": 0, "hangs": 0}
    for name, t in tallies.items():
        print(
            f"{name:20s} {t['tried']:7d} {t['results']:8d} {t['messages']:9d} {t['tracebacks']:11d} {t['hangs']:6d} "
            f"{t['slowest_s']:7.2f}s"
        )
        for key in total:
            total[key] += t[key]
        if t["first_failure"]:
            print(f"    first failure: {t['first_failure']}")
    print(
        f"{'total':20s} {total['tried']:7d} {total['results']:8d} {total['messages']:9d} {total['tracebacks']:11d} "
        f"{total['hangs']:6d}   in {seconds:.0f} s"
    )
    print(f"pytest: {proc.stdout.strip().splitlines()[-1] if proc.stdout.strip() else proc.returncode}")
    if proc.returncode != 0:
        print(proc.stdout[-6000:], proc.stderr[-2000:], sep="\n")
    return 1 if proc.returncode != 0 or total["tracebacks"] or total["hangs"] else 0


if __name__ == "__main__":
    sys.exit(main())
