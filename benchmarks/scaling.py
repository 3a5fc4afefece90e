"""Scaling on a many-core machine (issue 30): apply rows/s against workers and the disk, diagnosis time against
cores, and the fitter against the fastest peer, in one run, with the machine named.

Usage::

    python benchmarks/scaling.py                         # the 2-core development machine: about 10 minutes
    python benchmarks/scaling.py --rows 2e7 --diagnosis-n 1e5 --big   # a 16-core machine (the issue's sizes)
    python benchmarks/scaling.py --parts apply           # one part: apply, diagnosis, big, fitter (comma-separated)

Machine: ``nproc``, the CPU model (``/proc/cpuinfo``) and the memory are printed first; worker counts are
1, 2, 4, 8, 16 capped at ``nproc``.

**apply** -- a four-sensor Parquet survey of ``--rows`` rows (random attitudes, 3 nT noise, row groups of
``--row-group`` rows) is written to ``--dir``; then, one after the other: ``magcal apply`` in one process
(:func:`magcal.output.apply.apply_file`, Parquet -> Parquet) and the Dask apply
(:func:`magcal.output.survey.apply_partitioned`, a local cluster of ``W`` worker processes, partitions sized to the
workers) for every worker count. Each row reports the wall time, rows/s, the cluster's start (within the wall time)
and rows/s once started. **The disk's own bandwidth in the same run**: a file of the output's size written with
numpy (``tofile``, then ``fsync``) and read back (``fromfile``), and the input's size the same way; ``disk rows/s``
is the rows a process could move if it did nothing but read the input's bytes and write the output's at that
bandwidth -- the limit no apply can pass. (The read comes from the page cache when the file fits in memory: the
benchmark does not drop the machine's caches.)

**diagnosis** -- four sensors of ``--diagnosis-n`` samples with a temperature bias hidden (as
``benchmarks/diagnosis.py``, part 2): ``diagnose`` timed with its fits one after the other (1 core), then for every
worker count on threads and in worker processes (:mod:`magcal.diagnosis._parallel`); every run must give the same
verdict and candidates. ``--big`` (or the part ``big``) adds one diagnosis of 4 x 1e6 samples (processes on every core): its time and
the peak resident memory of the process and of its largest worker. What the diagnosis allows on any number of
cores (its work and critical path, measured on one) is ``benchmarks/diagnosis_span.py``.

**fitter** -- ``benchmarks/fitter_speed.py`` (one sensor, N = 1e6, magcal's ML against magyc's fits in their own
virtual environment, ``--magyc-python``) run as it is, its table printed here.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
WORKER_COUNTS = (1, 2, 4, 8, 16)


def machine() -> dict:
    """nproc, the CPU model and the memory of this machine."""
    model = "unknown"
    try:
        for line in open("/proc/cpuinfo", encoding="utf-8"):
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem_gb = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    return {
        "nproc": cores,
        "cpu": model,
        "memory_GB": round(mem_gb, 1),
        "python": platform.python_version(),
        "load_1min_at_start": round(load, 2),
    }


def worker_counts(nproc: int) -> list:
    return [w for w in WORKER_COUNTS if w <= nproc] or [1]


# -- apply --------------------------------------------------------------------------------------------------------
def write_survey(path: Path, rows: int, row_group: int, seed=0):
    """A four-sensor Parquet survey (time + 12 readings in nT) and the calibration that corrects it."""
    import pyarrow.parquet as pq
    from scipy.spatial.transform import Rotation

    from magcal.calibration.calibration import Calibration, SensorCalibration
    from magcal.data import io as mio
    from magcal.data import simulation as sim
    from magcal.fitting import platform as pf

    truth = pf.platform_truth()
    cal = Calibration(
        [SensorCalibration(s.Cinv, s.bias_nT, s.R) for s in truth.sensors],
        reference_total_nT=50_000.0,
        baseline_m=0.5,
        frame="platform",
    )
    rng = np.random.default_rng(seed)
    writer = None
    done = 0
    while done < rows:
        n = min(row_group, rows - done)
        att = Rotation.random(n, random_state=rng)
        fields = sim.true_fields(truth, att)
        y = np.stack([s.measure(f) for s, f in zip(truth.sensors, fields)]) + rng.normal(0, 3.0, (4, n, 3))
        cols = {"t": (done + np.arange(n)) * 0.01}
        for i in range(4):
            for a, axis in enumerate("xyz"):
                cols[f"s{i + 1}{axis}"] = y[i, :, a]
        table = mio.parquet_table(cols, {"units": "nT", "baseline_m": "0.5"})
        if writer is None:
            writer = pq.ParquetWriter(path, table.schema, **mio.parquet_write_options(table))
        writer.write_table(table)
        done += n
    writer.close()
    return cal


def disk_bandwidth(directory: Path, nbytes: int) -> dict:
    """Bytes/s of writing (``tofile`` then ``fsync``) and reading (``fromfile``) a file of ``nbytes`` with numpy."""
    path = directory / "disk_probe.bin"
    block = np.random.default_rng(1).random(min(nbytes, 64 << 20) // 8)
    t0 = time.perf_counter()
    with open(path, "wb") as fh:
        written = 0
        while written < nbytes:
            part = block[: max(1, min(block.size, (nbytes - written) // 8))]
            part.tofile(fh)
            written += part.nbytes
        fh.flush()
        os.fsync(fh.fileno())
    t_write = time.perf_counter() - t0
    t0 = time.perf_counter()
    with open(path, "rb") as fh:
        while True:
            got = np.fromfile(fh, dtype=np.uint8, count=64 << 20)
            if got.size == 0:
                break
    t_read = time.perf_counter() - t0
    os.unlink(path)
    return {"bytes": written, "write_Bps": written / t_write, "read_Bps": written / t_read}


def dir_bytes(path: Path) -> int:
    return sum(f.stat().st_size for f in path.iterdir()) if path.is_dir() else path.stat().st_size


def part_apply(args, info, report):
    from magcal.output.apply import apply_file
    from magcal.output.survey import apply_partitioned

    rows = int(float(args.rows))
    base = Path(tempfile.mkdtemp(prefix="magcal_scaling_", dir=args.dir))
    try:
        survey = base / "survey.parquet"
        t0 = time.perf_counter()
        cal = write_survey(survey, rows, int(float(args.row_group)))
        t_make = time.perf_counter() - t0
        in_bytes = survey.stat().st_size
        print(
            f"\napply: {rows:,} rows, four sensors, Parquet in ({in_bytes / 2**20:.0f} MB, written in {t_make:.1f} s)"
        )
        runs = []
        single = base / "single.parquet"
        t0 = time.perf_counter()
        apply_file(cal, survey, single, progress=False)
        dt = time.perf_counter() - t0
        out_bytes = dir_bytes(single)
        runs.append({"path": "one process (magcal apply)", "workers": 1, "seconds": dt, "start_s": 0.0, "parts": 1})
        os.unlink(single)
        for w in worker_counts(info["nproc"]):
            out = base / f"parts_{w}"
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                summary = apply_partitioned(cal, [survey], out, workers=w, progress=False)
            runs.append(
                {
                    "path": f"dask, {w} worker(s)",
                    "workers": w,
                    "seconds": summary.seconds,
                    "start_s": summary.start_s,
                    "parts": summary.partitions,
                }
            )
            shutil.rmtree(out)
        disk_out = disk_bandwidth(base, out_bytes)
        disk_in = disk_bandwidth(base, in_bytes)
        # seconds a process would need only to write the output's bytes and read the input's at the disk's pace
        disk_s = out_bytes / disk_out["write_Bps"] + in_bytes / disk_in["read_Bps"]
        disk_rows = rows / disk_s
        print(
            f"disk (same run, numpy): write {disk_out['write_Bps'] / 2**20:,.0f} MB/s ({out_bytes / 2**20:.0f} MB, "
            f"fsync), read {disk_in['read_Bps'] / 2**20:,.0f} MB/s ({in_bytes / 2**20:.0f} MB); "
            f"output {out_bytes / 2**20:.0f} MB -> disk limit {disk_rows:,.0f} rows/s"
        )
        one = runs[0]["seconds"]
        print(
            f"{'path':<28}{'parts':>6}{'wall s':>8}{'start s':>8}{'rows/s':>12}{'started':>12}{'x 1 proc':>9}"
            f"{'of disk':>8}"
        )
        for r in runs:
            started = rows / max(r["seconds"] - r["start_s"], 1e-9)
            r.update(
                rows_per_s=rows / r["seconds"], started_rows_per_s=started, of_disk=rows / r["seconds"] / disk_rows
            )
            print(
                f"{r['path']:<28}{r['parts']:>6}{r['seconds']:>8.2f}{r['start_s']:>8.2f}{r['rows_per_s']:>12,.0f}"
                f"{started:>12,.0f}{one / r['seconds']:>9.2f}{r['of_disk']:>8.0%}"
            )
        report["apply"] = {
            "rows": rows,
            "in_bytes": in_bytes,
            "out_bytes": out_bytes,
            "disk": {"write": disk_out, "read": disk_in, "rows_per_s": disk_rows},
            "runs": runs,
        }
    finally:
        shutil.rmtree(base, ignore_errors=True)


# -- diagnosis ----------------------------------------------------------------------------------------------------
def _record(n, seed=1):
    from magcal.data.simulation import chi2017_truth, simulate_timeseries
    from magcal.model import perturbations

    return simulate_timeseries(
        chi2017_truth(4),
        n_samples=n,
        noise_nT=3.0,
        seed=seed,
        perturbations=[perturbations.parse_hidden("temperature_bias=0.5", 4)],
    )


class DescendantsPeak:
    """The largest peak resident memory (``VmHWM``, MB) of this process's descendants while it is open: the worker
    processes are children of the fork server, not of this process, so ``RUSAGE_CHILDREN`` does not see them.
    Linux (``/proc``); read every 0.2 s."""

    def __init__(self):
        import threading

        self.mb = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, daemon=True)

    @staticmethod
    def _parents():
        out = {}
        for entry in os.listdir("/proc"):
            if entry.isdigit():
                try:
                    with open(f"/proc/{entry}/stat", encoding="ascii", errors="replace") as fh:
                        out[int(entry)] = int(fh.read().rsplit(")", 1)[1].split()[1])
                except (OSError, IndexError, ValueError):
                    continue
        return out

    def _watch(self):
        me = os.getpid()
        while not self._stop.wait(0.2):
            parents = self._parents()
            for pid in parents:
                p, seen = parents.get(pid), 0
                while p not in (None, 0, 1, me) and seen < 16:
                    p, seen = parents.get(p), seen + 1
                if p != me:
                    continue
                try:
                    with open(f"/proc/{pid}/status", encoding="ascii", errors="replace") as fh:
                        for line in fh:
                            if line.startswith("VmHWM:"):
                                self.mb = max(self.mb, int(line.split()[1]) / 1024)
                except OSError:
                    continue

    def __enter__(self):
        if os.path.isdir("/proc"):
            self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()


def _diagnose_timed(ds, res, workers, backend):
    from magcal.diagnosis import _parallel, diagnose

    _parallel.BACKEND = backend
    try:
        t0 = time.perf_counter()
        d = diagnose(ds, res, workers=workers)
        return time.perf_counter() - t0, d
    finally:
        _parallel.BACKEND = None


def part_diagnosis(args, info, report):
    from magcal.fitting.pipeline import calibrate

    n = int(float(args.diagnosis_n))
    ds = _record(n)
    res = calibrate(ds)
    print(f"\ndiagnosis: 4 x {n:,} samples, temperature_bias hidden (calibrate {res.wall_s:.2f} s first)")
    print(f"{'cores':>6}{'where':>12}{'seconds':>9}{'x 1 core':>9}  verdict / candidates")
    runs, first = [], None
    t1, d1 = _diagnose_timed(ds, res, 1, "threads")  # one core: BLAS on one thread too (_parallel.one_blas_thread)
    runs.append({"workers": 1, "backend": "serial", "seconds": t1})
    first = (d1.verdict, [c.label for c in d1.candidates])
    print(f"{1:>6}{'serial':>12}{t1:>9.2f}{1.0:>9.2f}  {d1.verdict} / {', '.join(first[1][:3])}")
    # the same record with 0.5 % of its samples rejected (as by hand in the workbench): every fit keeps the same
    # samples, so it should cost what the whole record costs (Dataset.masked)
    rejected = np.ones(ds.n_samples, bool)
    rejected[::200] = False
    tr, dr = _diagnose_timed(ds, calibrate(ds, mask=rejected), 1, "threads")
    runs.append({"workers": 1, "backend": "serial, 0.5 % rejected", "seconds": tr})
    print(f"{1:>6}{'0.5% out':>12}{tr:>9.2f}{t1 / tr:>9.2f}  {dr.verdict} / {dr.candidates[0].label} (serial)")
    for w in worker_counts(info["nproc"]):
        if w == 1:
            continue
        for backend in ("threads", "processes"):
            t, d = _diagnose_timed(ds, res, w, backend)
            same = (d.verdict, [c.label for c in d.candidates]) == first
            runs.append({"workers": w, "backend": backend, "seconds": t, "same_as_serial": same})
            print(f"{w:>6}{backend:>12}{t:>9.2f}{t1 / t:>9.2f}  {'same' if same else 'DIFFERENT: ' + d.verdict}")
    # what `magcal diagnose` does when not told: every core, processes or threads as _parallel.backend_for decides
    t, d = _diagnose_timed(ds, res, None, None)
    same = (d.verdict, [c.label for c in d.candidates]) == first
    runs.append({"workers": info["nproc"], "backend": "default", "seconds": t, "same_as_serial": same})
    print(f"{info['nproc']:>6}{'default':>12}{t:>9.2f}{t1 / t:>9.2f}  {'same' if same else 'DIFFERENT: ' + d.verdict}")
    report["diagnosis"] = {"n": n, "sensors": 4, "runs": runs}


def part_big(args, info, report):
    """One diagnosis of 4 x 1e6 samples on every core: its time and peak memories."""
    from magcal.fitting.pipeline import calibrate

    big = _record(1_000_000, seed=2)
    t0 = time.perf_counter()
    res_big = calibrate(big)
    t_cal = time.perf_counter() - t0
    with DescendantsPeak() as peak:
        t, d = _diagnose_timed(big, res_big, None, None)
    self_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    child_mb = peak.mb
    print(
        f"4 x 1,000,000: calibrate {t_cal:.1f} s, diagnose {t:.1f} s on {info['nproc']} core(s) ({d.verdict}, "
        f"{d.candidates[0].label}); peak resident {self_mb:,.0f} MB (this process), {child_mb:,.0f} MB (largest "
        "worker)"
    )
    report["big"] = {
        "n": 1_000_000,
        "calibrate_s": t_cal,
        "diagnose_s": t,
        "verdict": d.verdict,
        "best": d.candidates[0].label,
        "peak_MB": self_mb,
        "worker_peak_MB": child_mb,
    }


# -- fitter -------------------------------------------------------------------------------------------------------
def part_fitter(args, info, report):
    cmd = [sys.executable, str(HERE / "fitter_speed.py"), "--magyc-python", args.magyc_python]
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    print(f"\nfitter: {' '.join(cmd[1:])} (OPENBLAS_NUM_THREADS=1)")
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
    print(proc.stdout.strip() or proc.stderr.strip()[-2000:])
    report["fitter"] = {"stdout": proc.stdout, "rc": proc.returncode}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--parts", default="apply,diagnosis,fitter")
    p.add_argument("--rows", default="2e6", help="rows of the apply survey (the issue's: 2e7)")
    p.add_argument("--row-group", default="2e5", help="rows per row group of the survey file")
    p.add_argument("--dir", default=None, help="folder for the survey files (default: the system's temp)")
    p.add_argument("--diagnosis-n", default="1e5", help="samples per sensor of the diagnosis record")
    p.add_argument("--big", action="store_true", help="also diagnose 4 x 1e6 samples")
    p.add_argument("--magyc-python", default="/work/venvs/magyc/bin/python")
    p.add_argument("--json", default=None, help="also write the figures to this JSON file")
    args = p.parse_args(argv)
    info = machine()
    print(
        f"machine: {info['nproc']} core(s) (nproc), {info['cpu']}, {info['memory_GB']} GB, Python {info['python']}, "
        f"load {info['load_1min_at_start']} at start"
    )
    report = {"machine": info, "args": vars(args)}
    parts = {"apply": part_apply, "diagnosis": part_diagnosis, "big": part_big, "fitter": part_fitter}
    names = [name for name in args.parts.split(",") if name.strip()]
    if args.big and "big" not in names:
        names.insert(names.index("diagnosis") + 1 if "diagnosis" in names else len(names), "big")
    for name in names:
        parts[name.strip()](args, info, report)
    report["machine"]["load_1min_at_end"] = round(os.getloadavg()[0], 2)
    print(f"\nload (1 min) at the end: {report['machine']['load_1min_at_end']}")
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump(report, fh, indent=2, default=float)
    return 0


if __name__ == "__main__":
    sys.exit(main())
