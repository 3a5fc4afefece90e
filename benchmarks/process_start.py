"""What the worker processes cost to start and run, for the diagnosis and the local Dask cluster (issue 30).

Each measurement runs in a fresh program (a child of this script), so that every "first" is really the first:

- ``pools``: a diagnosis's worker pool (two workers, a small record) made twice in one program, started with
  ``spawn`` (every worker a new interpreter importing numpy, scipy and magcal) and forked from the fork server
  (:func:`magcal.diagnosis._parallel.process_context`): seconds until both workers answer.
- ``allocator``: a diagnosis of 4 x 1e5 samples in two worker processes, with Dask's ``MALLOC_TRIM_THRESHOLD_`` in
  the environment the workers inherit and without it (:func:`magcal.core.memory.keep_large_blocks` undoes it).
- ``threshold``: threads against processes (two workers) at 4 x 5e4, 4 x 1e5 and 4 x 2e5 samples, the fork server
  cold (where :data:`magcal.diagnosis._parallel.PROCESS_MIN_READINGS` comes from).
- ``cluster``: ``apply_partitioned`` of a 2e6-row four-sensor Parquet survey on a local cluster of two workers, twice
  in one program, spawned and forked (:data:`magcal.output.survey.LOCAL_START_METHOD`).
- ``source``: one survey partition of 8e5 rows corrected in this process with ``source_file`` written as text and as
  a dictionary-encoded column.
- ``blas``: a diagnosis on two threads (4 x 5e4), on two worker processes (4 x 1e5) and on one core (4 x 1e5), the
  calling process's BLAS left at OpenBLAS's default threads and held to one while the pool lives
  (:func:`magcal.diagnosis._parallel.one_blas_thread`); twice in one program, wall and the caller's processor time
  of the second.
- ``memory``: a diagnosis on two worker processes at 4 x 1e5, 2e5 and 4e5 samples: the calling process's peak
  resident memory before and after, and the largest worker's (``scaling.DescendantsPeak``), where
  :data:`magcal.diagnosis._parallel.WORKER_BYTES_PER_READING` and ``CALLER_BYTES_PER_READING`` come from.
- ``early``: the first diagnosis of a program (4 x 1e5, a worker process per core) after the record's calibration,
  with the fork server started as the record is read (:func:`magcal.diagnosis.start_workers`, as the workbench
  does), without (as ``magcal diagnose`` does), and started 5 s before anything is timed (what the server's start
  costs the diagnosis at most): the calibration's and the diagnosis's seconds.
- ``again``: in one fresh program, a diagnosis of 4 x 1e5 on threads (4 workers) twice, then in worker processes
  (one per core) three times, then one of another record: what the first diagnosis of a program pays that later
  ones do not (on 16 cores the first in processes took 3.5 s, the later 1.8-2.0 s).
- ``cli``: ``magcal diagnose`` of a 4 x 1e5 CSV (``magcal.cli.main``) in fresh programs, with the fork server
  started before the file is read (as shipped) and without: the command's seconds and its diagnosis's.
- ``gil``: two threads against one on the two kinds of work a fit's sums over blocks hold: matrix products of a
  56 x 8 738 block (BLAS releases the interpreter) and the short numpy calls on 4 369-row columns between them
  (each holds it): why threads inside one fit did not pay.

Usage::

    python benchmarks/process_start.py                       # every part, about 4 minutes on 2 cores
    python benchmarks/process_start.py --parts pools,cluster
    python benchmarks/process_start.py --parts blas,memory,gil   # the late session's figures
    python benchmarks/process_start.py --parts early,again,cli
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
PARTS = ("pools", "allocator", "threshold", "cluster", "source", "blas", "memory", "gil", "early", "again", "cli")


def _record(n):
    sys.path.insert(0, str(HERE))
    import scaling

    return scaling._record(n)


def child_pools(method):
    import multiprocessing

    from magcal.diagnosis import _parallel

    if method == "spawn":
        _parallel.process_context = lambda: multiprocessing.get_context("spawn")
    _parallel.BACKEND = "processes"  # a small record would stay on threads
    ds = _record(2000)
    out = []
    for _ in range(2):
        t0 = time.perf_counter()
        with _parallel.Pool(ds, workers=2) as pool:
            pool.remote(_parallel._ready)
            out.append(time.perf_counter() - t0)
    return out


def _parallel_cores():
    from magcal.diagnosis._parallel import cores

    return cores()


def child_early(n, early):
    from magcal.diagnosis import _parallel, diagnose, start_workers
    from magcal.fitting.pipeline import calibrate

    ds = _record(n)
    _parallel.BACKEND = "processes"
    if early == "ready":  # started, and given 5 s to import its modules before anything is timed
        start_workers(ds)
        time.sleep(5.0)
    t0 = time.perf_counter()
    if early is True:
        start_workers(ds)
    res = calibrate(ds)
    t1 = time.perf_counter()
    d = diagnose(ds, res)  # a worker per core
    return t1 - t0, time.perf_counter() - t1, d.verdict


def child_again(n):
    from magcal.diagnosis import _parallel, diagnose
    from magcal.fitting.pipeline import calibrate

    ds = _record(n)
    res = calibrate(ds)
    out = []
    for backend, workers, repeats in (("threads", 4, 2), (None, None, 3)):
        _parallel.BACKEND = backend
        for _ in range(repeats):
            t0 = time.perf_counter()
            d = diagnose(ds, res, workers=workers)
            out.append([f"{backend or 'processes'}", time.perf_counter() - t0, d.verdict])
    sys.path.insert(0, str(HERE))
    import scaling

    other = scaling._record(n, seed=5)
    res_other = calibrate(other)
    t0 = time.perf_counter()
    d = diagnose(other, res_other)
    out.append(["processes, another record", time.perf_counter() - t0, d.verdict])
    return out


def child_cli(path, early):
    import contextlib
    import io

    from magcal.cli import diagnose as command
    from magcal.cli import main

    if not early:
        command._start_workers_while_reading = lambda args: False
    out = io.StringIO()
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(out):
        rc = main(["diagnose", path, "--json"])
    wall = time.perf_counter() - t0
    doc = json.loads(out.getvalue())
    return wall, doc["elapsed_s"], doc["verdict"], rc


def child_diagnosis(n, backend, poison=False):
    from magcal.diagnosis import _parallel, diagnose
    from magcal.fitting.pipeline import calibrate

    ds = _record(n)
    res = calibrate(ds)
    if poison:
        os.environ["MALLOC_TRIM_THRESHOLD_"] = "65536"  # as Dask's fork server passes it on
    _parallel.BACKEND = backend
    t0 = time.perf_counter()
    d = diagnose(ds, res, workers=2)
    return [time.perf_counter() - t0, d.verdict]


def child_blas(n, backend, workers, limit):
    import contextlib

    from magcal.diagnosis import _parallel, diagnose
    from magcal.fitting.pipeline import calibrate

    ds = _record(n)
    res = calibrate(ds)
    if not limit:
        _parallel.one_blas_thread = lambda active=True: contextlib.nullcontext()
    _parallel.BACKEND = backend
    out = []
    for _ in range(2):
        c0, t0 = time.process_time(), time.perf_counter()
        diagnose(ds, res, workers=workers)
        out.append([time.perf_counter() - t0, time.process_time() - c0])
    return out


def child_memory(n):
    import resource

    import scaling

    from magcal.diagnosis import _parallel, diagnose
    from magcal.fitting.pipeline import calibrate

    ds = _record(n)
    res = calibrate(ds)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    _parallel.BACKEND = "processes"
    with scaling.DescendantsPeak() as peak:
        diagnose(ds, res, workers=2)
    return [before, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, peak.mb]


def child_gil():
    from concurrent.futures import ThreadPoolExecutor

    import numpy as np
    from threadpoolctl import threadpool_limits

    block = np.random.default_rng(1).random((56, 8738))
    column = np.random.default_rng(2).random(4369)

    def products(k):
        for _ in range(k):
            block @ block.T

    def short_calls(k):
        out = np.empty_like(column)  # each thread its own
        for _ in range(k):
            np.multiply(column, column, out=out)
            np.add(out, column, out=out)
            np.negative(out, out=out)

    got = {}
    with threadpool_limits(limits=1), ThreadPoolExecutor(2) as pool:
        for name, fn, k in (("products", products, 200), ("short calls", short_calls, 20_000)):
            t0 = time.perf_counter()
            fn(k)
            one = time.perf_counter() - t0
            t0 = time.perf_counter()
            list(pool.map(fn, [k // 2, k // 2]))
            got[name] = [one, time.perf_counter() - t0]
    return got


def child_cluster(method, survey, cal_json):
    import warnings

    from magcal.calibration.calibration import Calibration
    from magcal.output import survey as sv

    sv.LOCAL_START_METHOD = method
    cal = Calibration.from_dict(json.loads(Path(cal_json).read_text()))
    out = []
    for k in range(2):
        target = Path(survey).with_name(f"parts_{method}_{k}")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            s = sv.apply_partitioned(cal, [survey], target, workers=2, progress=False)
        out.append([s.seconds, s.start_s])
    return out


def child_source(survey, cal_json):
    import numpy as np

    from magcal.output import survey as sv

    doc = json.loads(Path(cal_json).read_text())
    part = sv.partitions([survey], 800_000, 1)[1]
    real = sv._source_column
    out = {}
    with tempfile.TemporaryDirectory() as d:
        for name, column in (("text", lambda n, rows, fmt: np.full(rows, n)), ("dictionary", real)):
            sv._source_column = column
            times = []
            for _ in range(3):
                t0 = time.perf_counter()
                sv.correct_partition(doc, part, d, "parquet", "apply")
                times.append(time.perf_counter() - t0)
            out[name] = sorted(times)[1]
    sv._source_column = real
    return out


def run_child(*args, env=None, clean=False):
    """Run one measurement in a fresh program; ``env`` added to this one's environment (or, ``clean``, instead of
    it)."""
    cmd = [sys.executable, __file__, "--child", json.dumps(args)]
    full = dict(env or {}) if clean else {**os.environ, **(env or {})}
    proc = subprocess.run(cmd, capture_output=True, text=True, env=full, timeout=900)
    if proc.returncode != 0:
        raise SystemExit(proc.stderr[-3000:])
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--parts", default=",".join(PARTS))
    p.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child is not None:
        kind, *rest = json.loads(args.child)
        fn = {
            "pools": child_pools,
            "diagnosis": child_diagnosis,
            "cluster": child_cluster,
            "source": child_source,
            "blas": child_blas,
            "memory": child_memory,
            "gil": child_gil,
            "early": child_early,
            "again": child_again,
            "cli": child_cli,
        }
        print(json.dumps(fn[kind](*rest)))
        return
    parts = args.parts.split(",")
    print(f"{os.cpu_count()} core(s), load {os.getloadavg()[0]:.2f} at the start")
    if "pools" in parts:
        for method in ("spawn", "forkserver"):
            first, second = run_child("pools", method)
            print(f"pools    {method:>10}: two workers ready in {first:.2f} s (first pool), {second:.2f} s (second)")
    if "allocator" in parts:
        for poison in (True, False):
            t, verdict = run_child("diagnosis", 100_000, "processes", poison)
            what = "with Dask's MALLOC_TRIM_THRESHOLD_" if poison else "without it"
            print(f"allocator  4 x 100,000, 2 processes {what}: {t:.2f} s ({verdict})")
    if "threshold" in parts:
        for n in (50_000, 100_000, 200_000):
            row = [run_child("diagnosis", n, backend)[0] for backend in ("threads", "processes")]
            print(f"threshold  4 x {n:>7,}: 2 threads {row[0]:.2f} s, 2 processes {row[1]:.2f} s (fork server cold)")
    if "cluster" in parts or "source" in parts:
        import shutil

        import scaling

        base = Path(tempfile.mkdtemp(prefix="magcal_start_"))
        try:
            survey = base / "survey.parquet"
            cal = scaling.write_survey(survey, 2_000_000, 200_000)
            (base / "cal.json").write_text(json.dumps(cal.to_dict()))
            if "cluster" in parts:
                for method in ("spawn", "forkserver"):
                    (a, a_start), (b, b_start) = run_child("cluster", method, str(survey), str(base / "cal.json"))
                    print(
                        f"cluster  {method:>10}: 2e6 rows x 4 on 2 workers {a:.2f} s (start {a_start:.2f}), "
                        f"again {b:.2f} s (start {b_start:.2f})"
                    )
            if "source" in parts:
                got = run_child("source", str(survey), str(base / "cal.json"))
                print(
                    f"source   a partition of 8e5 rows: source_file as text {got['text']:.2f} s, "
                    f"dictionary-encoded {got['dictionary']:.2f} s (median of 3)"
                )
        finally:
            shutil.rmtree(base, ignore_errors=True)
    if "early" in parts:
        for early in (False, True, "ready", False, True, "ready"):
            cal, diag, verdict = run_child("early", 100_000, early)
            what = {False: "cold", True: "started as the record is read", "ready": "ready (5 s before)"}[early]
            print(
                f"early    4 x 100,000, {_parallel_cores()} processes, fork server {what:>29}: calibrate {cal:.2f} s, "
                "then the "
                f"diagnosis {diag:.2f} s ({verdict})"
            )
    if "again" in parts:
        for i, (where, seconds, verdict) in enumerate(run_child("again", 100_000)):
            print(f"again    4 x 100,000, diagnosis {i + 1} of one program, {where:<26}: {seconds:.2f} s ({verdict})")
    if "cli" in parts:
        from magcal.data import io as mio

        with tempfile.TemporaryDirectory() as folder:
            path = str(Path(folder) / "four_1e5.csv")
            mio.write_csv(path, _record(100_000))
            for early in (False, True, False, True, False, True):
                wall, diag, verdict, rc = run_child("cli", path, early)
                what = "before the file is read" if early else "not started early"
                print(
                    f"cli      magcal diagnose 4 x 100,000 CSV, fork server {what:>24}: {wall:.2f} s, of which the "
                    f"diagnosis {diag:.2f} s ({verdict}, exit {rc})"
                )
    if "blas" in parts:
        env = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS")}
        for n, backend, workers in ((50_000, "threads", 2), (100_000, "processes", 2), (100_000, "threads", 1)):
            where = f"{workers} {backend}" if workers > 1 else "1 core"
            row = []
            for limit in (False, True):
                (first, _), (wall, cpu) = run_child("blas", n, backend, workers, limit, env=env, clean=True)
                row.append(f"{wall:.2f} s (first {first:.2f}, caller's processor {cpu:.2f} s)")
            print(f"blas     4 x {n:>7,} on {where}: BLAS default {row[0]}; one thread {row[1]}")
    if "memory" in parts:
        for n in (100_000, 200_000, 400_000):
            before, after, worker = run_child("memory", n)
            print(
                f"memory   4 x {n:>7,} on 2 processes: caller {before:,.0f} MB before, {after:,.0f} MB peak; "
                f"largest worker {worker:,.0f} MB"
            )
    if "gil" in parts:
        for name, (one, two) in run_child("gil").items():
            print(f"gil      {name:>11}: one thread {one:.3f} s, the same work on two threads {two:.3f} s")
    print(f"load {os.getloadavg()[0]:.2f} at the end")


if __name__ == "__main__":
    sys.path.insert(0, str(HERE))
    main()
