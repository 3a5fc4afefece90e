"""``magcal apply`` throughput (rows/s) and peak memory for survey files of 1e5, 1e6 and 1e7 rows.

Run: ``python benchmarks/apply_throughput.py [--sizes 1e5,1e6,1e7] [--dir DIR]``. The 1e7-row file is ~1.3 GB in
and ~3 GB out and takes several minutes; files are written to a temporary directory and deleted afterwards.

Each size: a four-sensor survey (time + 12 readings, 3 decimals) is generated in blocks, then ``magcal apply`` runs
in a fresh process (the real console command path, progress bar off) and the table reports its wall time, rows/s
and peak resident memory (``VmHWM`` of that process). Flat memory means the peak does not grow with the rows.
With ``--parquet`` the same survey is also converted to Parquet (streamed) and applied CSV -> Parquet and
Parquet -> Parquet, side by side.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from magcal.calibration.calibration import Calibration, SensorCalibration
from magcal.data import simulation as sim
from magcal.fitting import platform as pf

BLOCK = 200_000


def write_survey(path: Path, n_rows: int, truth) -> None:
    """A 4-sensor survey of ``n_rows`` random attitudes, written in blocks (memory stays small)."""
    rng = np.random.default_rng(0)
    header = "t," + ",".join(f"s{i}{a}" for i in range(1, 5) for a in "xyz")
    fmt = ",".join(["%.2f"] + ["%.3f"] * 12)
    with open(path, "w", encoding="utf-8") as fh:
        fh.write("# units: nT\n# baseline_m: 0.5\n" + header + "\n")
        done = 0
        while done < n_rows:
            n = min(BLOCK, n_rows - done)
            att = Rotation.random(n, random_state=rng)
            fields = sim.true_fields(truth, att)
            y = np.stack([s.measure(f) for s, f in zip(truth.sensors, fields)]) + rng.normal(0, 3.0, (4, n, 3))
            table = np.column_stack([(done + np.arange(n)) * 0.01, y.transpose(1, 0, 2).reshape(n, 12)])
            fh.write("\n".join(fmt % tuple(row) for row in table.tolist()) + "\n")
            done += n


def to_parquet(survey: Path, out: Path) -> None:
    """The survey CSV as Parquet, streamed chunk by chunk (one row group each)."""
    import pyarrow.parquet as pq

    from magcal.data import io as mio

    writer = None
    with mio.CsvSource(survey) as src:
        meta = dict(src.metadata)
        for chunk in src.chunks(BLOCK, text_columns=False):
            table = mio.parquet_table(mio.dataset_columns(chunk.dataset), meta)
            writer = writer or pq.ParquetWriter(out, table.schema)
            writer.write_table(table)
    writer.close()


def run_apply(cal: Path, survey: Path, out: Path, extra=()):
    # VmHWM (peak resident set of this program image): ru_maxrss would carry over the parent's peak across exec
    code = (
        "import sys, time; from magcal.cli import main; t0 = time.perf_counter(); "
        "rc = main(sys.argv[1:]); dt = time.perf_counter() - t0; "
        "hwm = [l.split()[1] for l in open('/proc/self/status') if l.startswith('VmHWM')][0]; "
        "print('RESULT', rc, dt, hwm, file=sys.stderr)"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code, "apply", str(cal), str(survey), "-o", str(out), "--no-progress", *extra],
        capture_output=True,
        text=True,
    )
    line = next(x for x in proc.stderr.splitlines() if x.startswith("RESULT"))
    _, rc, dt, maxrss_kb = line.split()
    return int(rc), float(dt), int(maxrss_kb) / 1024.0


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="1e5,1e6,1e7")
    parser.add_argument("--dir", default=None)
    parser.add_argument("--parquet", action="store_true", help="also CSV -> Parquet and Parquet -> Parquet")
    parser.add_argument(
        "--dask", action="store_true", help="also Parquet -> Parquet partitions on a local Dask cluster of two workers"
    )
    args = parser.parse_args()
    sizes = [int(float(s)) for s in args.sizes.split(",")]
    truth = pf.platform_truth()
    cal = Calibration(
        [SensorCalibration(s.Cinv, s.bias_nT, s.R) for s in truth.sensors],
        reference_total_nT=50_000.0,
        baseline_m=0.5,
        frame="platform",
    )
    baseline = subprocess.run(
        [
            sys.executable,
            "-c",
            "import magcal.output.apply, magcal.cli; "
            "print([l.split()[1] for l in open('/proc/self/status') if l.startswith('VmHWM')][0])",
        ],
        capture_output=True,
        text=True,
    )
    idle_mb = int(baseline.stdout.strip()) / 1024.0
    print(f"python + magcal imported, idle: {idle_mb:.0f} MB resident")
    print(
        f"{'rows':>10} {'path':>17} {'in MB':>8} {'out MB':>8} {'write s':>8} {'apply s':>8} {'rows/s':>10} "
        f"{'peak MB':>8}"
    )
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        d = Path(tmp)
        cal.save(d / "cal.json")
        for n in sizes:
            survey = d / f"survey_{n}.csv"
            t0 = time.perf_counter()
            write_survey(survey, n, truth)
            t_write = time.perf_counter() - t0
            runs = [("csv -> csv", survey, d / f"out_{n}.csv")]
            if args.parquet:
                t1 = time.perf_counter()
                to_parquet(survey, d / f"survey_{n}.parquet")
                t_pq = time.perf_counter() - t1
                runs += [
                    ("csv -> parquet", survey, d / f"out_{n}.parquet"),
                    ("parquet -> parquet", d / f"survey_{n}.parquet", d / f"out2_{n}.parquet"),
                ]
            if args.dask and args.parquet:
                runs.append(("dask 2 workers", d / f"survey_{n}.parquet", d / f"parts_{n}"))
            for label, src, out in runs:
                extra = ("--workers", "2") if label.startswith("dask") else ()
                rc, dt, peak = run_apply(d / "cal.json", src, out, extra)
                assert rc == 0
                made = t_pq if src.suffix == ".parquet" else t_write
                size = sum(f.stat().st_size for f in out.iterdir()) if out.is_dir() else out.stat().st_size
                print(
                    f"{n:>10d} {label:>17} {src.stat().st_size / 2**20:>8.0f} {size / 2**20:>8.0f} "
                    f"{made:>8.1f} {dt:>8.1f} {n / dt:>10,.0f} {peak:>8.0f}",
                    flush=True,
                )
                if out.is_dir():
                    import shutil

                    shutil.rmtree(out)
                else:
                    os.unlink(out)
            for f in d.glob(f"survey_{n}.*"):
                os.unlink(f)


if __name__ == "__main__":
    main()
