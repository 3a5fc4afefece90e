"""How long the calling process of a diagnosis holds Python's interpreter (issue 30): the part of its work no number
of cores can spread.

A diagnosis on worker processes still runs its orchestration, its structure tests and its evidence in the calling
process. Where that work holds the interpreter lock it runs on one core whatever the workers, a bound beside the
span of ``diagnosis_span.py``. ``py-spy record --gil`` samples only the threads holding the lock; the samples whose
stack is in the diagnosis (``magcal/diagnosis/``), not importing a module (once a program), at ``--rate`` per
second, give the seconds. The child program
diagnoses 4 x ``--n`` samples twice on two worker processes (the first warms the fork server) and the figure is
per diagnosis.

Usage (needs py-spy: ``pip install py-spy``; on Linux it may need ``ptrace`` rights)::

    python benchmarks/caller_gil.py              # 4 x 1e5
"""

from __future__ import annotations

import argparse
import collections
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent

CHILD = """
import sys, time
sys.path.insert(0, {here!r})
import scaling
from magcal.diagnosis import _parallel, diagnose
from magcal.fitting.pipeline import calibrate
ds = scaling._record({n})
res = calibrate(ds)
_parallel.BACKEND = "processes"
for _ in range(2):
    t0, c0 = time.perf_counter(), time.process_time()
    diagnose(ds, res, workers=2)
    print("diagnosis", time.perf_counter() - t0, time.process_time() - c0, flush=True)
"""


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--n", default="1e5", help="samples per sensor (four sensors)")
    p.add_argument("--rate", type=int, default=200, help="py-spy samples per second")
    args = p.parse_args(argv)
    spy = shutil.which("py-spy")
    if spy is None:
        raise SystemExit("caller_gil.py needs py-spy: pip install py-spy")
    with tempfile.TemporaryDirectory() as d:
        child, raw = Path(d) / "child.py", Path(d) / "gil.txt"
        child.write_text(CHILD.format(here=str(HERE), n=int(float(args.n))))
        cmd = [spy, "record", "--gil", "--rate", str(args.rate), "--format", "raw", "-o", str(raw), "--"]
        run = subprocess.run([*cmd, sys.executable, str(child)], capture_output=True, text=True, timeout=900)
        if run.returncode != 0 or not raw.exists():
            raise SystemExit(f"py-spy failed:\n{run.stderr[-2000:]}")
        times = [line.split()[1:] for line in run.stdout.splitlines() if line.startswith("diagnosis")]
        held = collections.Counter()
        total = 0
        for line in raw.read_text().splitlines():
            stack, _, count = line.rpartition(" ")
            frames = stack.split(";")
            if "magcal/diagnosis/" not in stack or any(f.strip().startswith("<module>") for f in frames[1:]):
                continue  # outside the diagnosis, or a module imported on the first one's way (once a program)
            total += int(count)
            leaf = [f for f in frames if "magcal" in f]
            held[(leaf[-1] if leaf else frames[-1]).strip()] += int(count)
    per = total / args.rate / 2
    print(f"diagnosis of 4 x {int(float(args.n)):,} samples on two worker processes, twice")
    for k, (wall, cpu) in enumerate(times, 1):
        print(f"  diagnosis {k}: wall {float(wall):.2f} s, the calling process's processor time {float(cpu):.2f} s")
    print(f"the calling process held the interpreter in the diagnosis's frames {per:.2f} s per diagnosis")
    print("where it held it most (seconds per diagnosis):")
    for where, count in held.most_common(6):
        print(f"  {count / args.rate / 2:6.3f}  {where[:100]}")


if __name__ == "__main__":
    main()
