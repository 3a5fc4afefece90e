"""What the look for a carriage return inside a line costs ``read_csv``'s fast path (pyarrow) on a large CSV.

Run: ``python benchmarks/csv_line_ends.py [--rows 2e6] [--repeats 5] [--dir DIR]``.

A four-sensor survey (time + 12 readings, ``apply_throughput.write_survey``) written with LF and with CRLF line ends.
Timed in one process, alternating, median of the repeats, wall clock and CPU (all threads):

* ``read_csv``: as it is, the look for a CR inside a line (:func:`magcal.data.io.stray_cr`) running beside
  pyarrow's parse, in a thread;
* ``without the look``: the same with ``stray_cr`` replaced by one that finds nothing (the fast path as it was);
* ``stray_cr alone``: the look by itself, over the memory-mapped file.
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

sys.path.insert(0, str(Path(__file__).resolve().parent))
from apply_throughput import write_survey

from magcal.data import io as mio
from magcal.fitting import platform as pf


def timed(fn):
    w0, c0 = time.perf_counter(), time.process_time()
    out = fn()
    return time.perf_counter() - w0, time.process_time() - c0, out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=float, default=2e6)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--dir", default=None)
    args = parser.parse_args()
    n = int(args.rows)
    real = mio.stray_cr
    with tempfile.TemporaryDirectory(dir=args.dir) as d:
        lf, crlf = Path(d) / "lf.csv", Path(d) / "crlf.csv"
        write_survey(lf, n, pf.platform_truth())
        crlf.write_bytes(lf.read_bytes().replace(b"\n", b"\r\n"))
        print(
            f"survey: {n:,} rows, four sensors, {lf.stat().st_size / 1e6:.0f} MB (LF), {crlf.stat().st_size / 1e6:.0f} MB (CRLF)"
        )

        def read(path, look):
            mio.stray_cr = real if look else (lambda data, start=0: -1)
            try:
                ds = mio.read_csv(path)
            finally:
                mio.stray_cr = real
            assert ds.n_samples == n
            return ds

        def alone(path):
            import pyarrow as pa

            return real(pa.memory_map(os.fspath(path), "r").read_buffer())

        cases = {}
        for name, path in (("LF", lf), ("CRLF", crlf)):
            cases[f"{name}: read_csv"] = lambda p=path: read(p, True)
            cases[f"{name}: without the look"] = lambda p=path: read(p, False)
            cases[f"{name}: stray_cr alone"] = lambda p=path: alone(p)
        walls, cpus = {k: [] for k in cases}, {k: [] for k in cases}
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            for _ in range(args.repeats):
                for name, fn in cases.items():
                    wall, cpu, out = timed(fn)
                    walls[name].append(wall)
                    cpus[name].append(cpu)
                    if "alone" in name:
                        assert out == -1
        print(f"({args.repeats} repeats, alternating; median wall s (min-max), median CPU s)")
        for name in cases:
            w = walls[name]
            print(
                f"  {name:28s} {statistics.median(w):7.3f}  ({min(w):.3f}-{max(w):.3f})  cpu {statistics.median(cpus[name]):7.3f}"
            )
    print(f"machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f} at the end")


if __name__ == "__main__":
    main()
