"""The record decision of ``magcal apply`` on a large CSV survey: counting its rows against parsing them.

Run: ``python benchmarks/csv_count.py [--rows 2e6] [--repeats 3] [--dir DIR]``.

A four-sensor survey (time + 12 readings, 3 decimals, ``apply_throughput.write_survey``) and a calibration holding
a bias drift (a record-only term) fitted on a short record of its own. Timed, alternating, median of the repeats:

* ``before``: what :func:`magcal.output.apply.record_choice` did for a CSV until the row count: every row parsed
  and hashed (:class:`~magcal.calibration.calibration.RecordHasher` over ``survey_chunks``), to find that the
  survey is not the calibration record;
* ``after, another length``: ``record_choice`` now (the rows counted from the line ends, nothing parsed);
* ``after, the record's length``: the survey told to be the calibration record (its fingerprint set as the
  record's): counted, then hashed, as it must be;
* ``count_rows`` alone and ``read``: the file's bytes read in the same blocks, nothing done with them (the floor);
* ``apply CSV -> Parquet`` with the old decision and with the new one (``--apply``): the whole command's time;
* ``partitions``: the Dask path's cutting of the survey for 16 workers (:func:`magcal.output.survey.partitions`):
  one pass that counts the lines and marks where to cut, against the two it replaced (count, then cut while
  reading again); the partitions are checked to be the same.

The decision is checked to be the same both ways.
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

from magcal.calibration.calibration import RecordHasher
from magcal.data import io as mio
from magcal.data import simulation as sim
from magcal.fitting import platform as pf
from magcal.fitting.fitter import fit
from magcal.model.terms import CORRECTION_STAGES, EFFECTS, Model
from magcal.output import apply as ap


def old_record_choice(calibration, path):
    """``record_choice`` for a CSV as it was: the whole file parsed and hashed for its fingerprint."""
    hasher = RecordHasher()
    for ds in ap.survey_chunks(path)[1]:
        hasher.update(ds)
    dropped, note = calibration.record_decision(None, None, CORRECTION_STAGES, fingerprint=hasher.fingerprint())
    return ("drop" if dropped else "apply"), note


def read_only(path):
    with open(path, "rb") as fh:
        while fh.read(mio.COUNT_BLOCK_BYTES):
            pass


def count_only(path):
    with mio.CsvSource(path) as src:
        return src.count_rows()


def drift_calibration(truth):
    """A four-sensor calibration with a bias drift, fitted on a short record of its own."""
    drift = EFFECTS["bias_drift"]()
    record = sim.simulate_timeseries(
        truth, n_samples=2000, noise_nT=3.0, seed=2, perturbations=[drift.perturbation(drift.default_magnitude)]
    )
    return fit(record, Model.from_names(["bias_drift"], 4)).calibration.fitted_on(record)


def timed(fn, *args):
    t0 = time.perf_counter()
    out = fn(*args)
    return time.perf_counter() - t0, out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=float, default=2e6)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--apply", action="store_true", help="also time the whole apply, CSV -> Parquet")
    parser.add_argument("--dir", default=None)
    args = parser.parse_args()
    n = int(args.rows)
    truth = pf.platform_truth()
    with tempfile.TemporaryDirectory(dir=args.dir) as d:
        path = Path(d) / "survey.csv"
        t0 = time.perf_counter()
        write_survey(path, n, truth)
        print(
            f"survey: {n:,} rows, four sensors, {path.stat().st_size / 1e6:.0f} MB CSV (written in "
            f"{time.perf_counter() - t0:.1f} s)"
        )
        cal = drift_calibration(truth)
        same = drift_calibration(truth)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            same.record = ap.file_fingerprint(path)  # the survey as the calibration record
            cases = {
                "read (the floor)": lambda: read_only(path),
                "count_rows": lambda: count_only(path),
                "before: parse + hash": lambda: old_record_choice(cal, path),
                "after, another length": lambda: ap.record_choice(cal, path),
                "after, the record's length": lambda: ap.record_choice(same, path),
            }
            times = {k: [] for k in cases}
            results = {}
            for _ in range(args.repeats):
                for name, fn in cases.items():
                    dt, results[name] = timed(fn)
                    times[name].append(dt)
            assert results["count_rows"] == n
            assert results["before: parse + hash"][0] == results["after, another length"][0] == "drop"
            assert results["after, the record's length"] == ("apply", None)
            print(f"record decision ({args.repeats} repeats, alternating; median, min-max s):")
            for name, ts in times.items():
                print(
                    f"  {name:28s} {statistics.median(ts):7.3f}  ({min(ts):.3f}-{max(ts):.3f})   "
                    f"{n / statistics.median(ts) / 1e6:8.2f} M rows/s"
                )
            print(f"  decision: {results['after, another length'][0]} (the same both ways)")
            if args.apply:
                out = Path(d) / "out.parquet"
                real = ap.record_choice
                ap_times = {"apply, before": [], "apply, after": []}
                for _ in range(args.repeats):
                    for name in ap_times:
                        ap.record_choice = (lambda c, p, *a: old_record_choice(c, p)) if "before" in name else real
                        try:
                            dt, _ = timed(ap.apply_file, cal, path, out)
                        finally:
                            ap.record_choice = real
                        ap_times[name].append(dt)
                        os.remove(out)
                print("apply CSV -> Parquet (median, min-max s):")
                for name, ts in ap_times.items():
                    print(f"  {name:28s} {statistics.median(ts):7.3f}  ({min(ts):.3f}-{max(ts):.3f})")
        from magcal.output import survey

        part_times: dict = {"partitions, one pass": [], "partitions, two passes": []}
        got = {}
        for _ in range(args.repeats):
            dt, got["one"] = timed(survey.partitions, [path], None, 16)
            part_times["partitions, one pass"].append(dt)
            rows = survey.partition_rows_for(n, 16)
            stride = survey._csv_scan(path).stride  # (not timed) the size the one pass rounds to
            t0 = time.perf_counter()
            survey._csv_scan(path)  # the old first pass: count the lines
            got["two"] = survey.partitions([path], partition_rows=-(-rows // stride) * stride)  # then cut
            part_times["partitions, two passes"].append(time.perf_counter() - t0)
        assert got["one"] == got["two"]
        print(f"partitions for 16 workers ({len(got['one'])} parts; median, min-max s):")
        for name, ts in part_times.items():
            print(f"  {name:28s} {statistics.median(ts):7.3f}  ({min(ts):.3f}-{max(ts):.3f})")
    print(f"machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f} at the end")


if __name__ == "__main__":
    main()
