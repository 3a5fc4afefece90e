"""``magcal apply``: correct a survey file with a calibration (patent S9-S10), streaming.

Example::

    magcal apply platform.json survey.csv -o survey_cal.csv
    magcal apply cal.json survey.csv -o out.csv --effects-file my_effects.py   # a calibration with your own effect
    magcal apply cal.json calib_record.csv -o out.csv --record-terms apply    # keep its bias drift on that record
    magcal apply cal.json flight.bin -o flight_cal.csv                       # a flight-controller log (.bin, .ulg)
    magcal apply cal.json survey.csv -o survey_cal.parquet                   # Parquet out (or in)
    magcal apply cal.json day1.csv day2.csv -o corrected/ --workers 2        # Dask: partitions in parallel
    magcal apply cal.json big.parquet -o corrected/ --scheduler tcp://10.0.0.5:8786   # on a Dask cluster

A calibration with record-only terms (bias drift, bias step, reference drift, site gradient) applies them only to
the record it was fitted on; on any other file they are dropped, with one warning naming them.

A sensor whose calibration the fit marked not determined by its record (a vector or gravity fit's "NOT DETERMINED")
is refused: its columns are left out, a warning names it and why, and the other sensors are corrected; ``--force``
applies it too and the output's header says so (``magcal_forced``).

Writes every input line plus ``s{i}x_cal, s{i}y_cal, s{i}z_cal`` (nT) and, for a four-sensor array, the tensor
``Gxx .. Gzz, Gyx`` (nT/m) and its invariants ``I0, I1, I2`` (see docs/formats.md).
"""

from __future__ import annotations

import os
import sys

from magcal.cli.commands import HELP
from magcal.core.errors import MagcalError
from magcal.data.dataset import DatasetError
from magcal.data.io import PARQUET_CODECS, check_output_path
from magcal.model.plugins import check_calibration_effects
from magcal.output.apply import apply_file, load_calibration
from magcal.output.compensated_line import apply_compensation_file, is_compensation_file
from magcal.output.compensated_survey import apply_compensation_partitioned
from magcal.output.cross_compensated_line import apply_cross_compensation_file, is_cross_compensation_file
from magcal.output.survey import TASKS_PER_WORKER, WORKERS_PER_CORE, apply_partitioned, check_workers


def register(subparsers):
    """Add the ``apply`` subcommand."""
    parser = subparsers.add_parser(
        "apply",
        help=HELP["apply"],
        description="Apply a calibration to a survey CSV, streaming (memory stays flat for any length), and write "
        "the input columns plus the corrected ones.",
    )
    parser.add_argument("calibration", metavar="CAL.json", help="calibration file (magcal calibrate / align)")
    parser.add_argument(
        "data",
        metavar="SURVEY.csv",
        nargs="+",
        help="survey data file (see docs/formats.md; .parquet too), or an ArduPilot .bin / PX4 .ulg "
        "flight log; several files (or --workers/--scheduler) are corrected in parallel",
    )
    parser.add_argument(
        "-o",
        "--output",
        required=True,
        metavar="OUT.csv",
        help="output file (written atomically; .parquet for Parquet), or with several files or "
        "--workers/--scheduler a new directory of partitions",
    )
    parser.add_argument(
        "--uncertainty",
        action="store_true",
        help="also write the calibration's standard deviation of every corrected component, of |B| "
        "per sensor and of each tensor component (s1x_cal_sd .., s1_F_sd, Gxx_sd ..; from its "
        "parameter covariance)",
    )
    parser.add_argument(
        "--workers",
        type=int,
        default=None,
        metavar="N",
        help="correct in parallel on a local Dask cluster of N worker processes (at most "
        f"{WORKERS_PER_CORE} per CPU core)",
    )
    parser.add_argument(
        "--scheduler",
        default=None,
        metavar="ADDRESS",
        help="correct in parallel on an existing dask.distributed cluster (e.g. tcp://host:8786)",
    )
    parser.add_argument(
        "--format",
        choices=("parquet", "csv"),
        default="parquet",
        help="partition files written in parallel mode (default parquet)",
    )
    parser.add_argument(
        "--compression",
        choices=PARQUET_CODECS,
        default=None,
        help="codec of the float columns of Parquet output (default snappy; float64 survey "
        "values shrink by only about 11%% with it: none writes faster, zstd smaller; text "
        "columns are always snappy)",
    )
    parser.add_argument(
        "--partition-rows",
        type=int,
        default=None,
        metavar="N",
        help="rows per partition in parallel mode (default: sized to the workers, "
        f"{TASKS_PER_WORKER} partitions per worker, whatever the file's row groups)",
    )
    parser.add_argument(
        "--columns",
        default=None,
        metavar="MAP",
        help="map your column names onto magcal's, e.g. x=magX,y=magY,z=magZ,t=time",
    )
    parser.add_argument("--units", default=None, help="unit of the readings (nT, uT, G, mG); overrides the file")
    parser.add_argument(
        "--drop-bad",
        action="store_true",
        help="drop rows with missing or non-numeric values (with a warning) instead of refusing",
    )
    parser.add_argument("--chunk-rows", type=int, default=20_000, metavar="N", help="rows per block (memory)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument(
        "--record-terms",
        choices=("apply", "drop"),
        default=None,
        help="the calibration's record-only terms (bias_drift, bias_step, reference_drift, "
        "site_gradient...: they describe the recording it was fitted on, not the instrument). "
        "Default: applied on that very recording, dropped with a warning on any other. "
        "'apply' forces them (the same record, or you have a reference for it); 'drop' leaves "
        "them out",
    )
    parser.add_argument(
        "--force",
        action="store_true",
        help="also apply the sensors whose calibration the fit marked not determined by its record (by default "
        "their columns are left out, with a warning naming them and why); the output's header says it was forced",
    )
    parser.set_defaults(func=run)
    return parser


def run(args) -> int:

    if args.chunk_rows < 1:
        raise MagcalError(f"--chunk-rows must be at least 1, got {args.chunk_rows}")
    parallel = len(args.data) > 1 or args.workers is not None or args.scheduler is not None
    if args.workers is not None:
        check_workers(args.workers)
    # every check on the paths before any work: the inputs first (a missing input is named even when -o exists)
    for path in args.data:
        if not os.path.exists(path):
            raise DatasetError(f"{path}: no such file; check the path")
        if os.path.isdir(path):
            raise DatasetError(f"{path}: is a directory, not a survey file")
    check_output_path(args.output, "-o", directory=parallel)
    if is_compensation_file(args.calibration):
        return _run_compensation(args, parallel)
    if is_cross_compensation_file(args.calibration):
        return _run_cross_compensation(args, parallel)
    check_calibration_effects(args.calibration)  # a user's effect in the file needs --effects-file
    calibration = load_calibration(args.calibration)
    if parallel:
        summary = apply_partitioned(
            calibration,
            args.data,
            args.output,
            fmt=args.format,
            workers=args.workers or 2,
            scheduler=args.scheduler,
            partition_rows=args.partition_rows,
            columns=args.columns,
            units=args.units,
            drop_bad=args.drop_bad,
            record_terms=args.record_terms,
            progress=False if args.no_progress else None,
            uncertainty=args.uncertainty,
            compression=args.compression,
            force=args.force,
        )
    else:
        summary = apply_file(
            calibration,
            args.data[0],
            args.output,
            columns=args.columns,
            units=args.units,
            drop_bad=args.drop_bad,
            chunk_rows=args.chunk_rows,
            progress=False if args.no_progress else None,
            calibration_name=args.calibration,
            record_terms=args.record_terms,
            uncertainty=args.uncertainty,
            compression=args.compression,
            force=args.force,
        )
    for note in dict.fromkeys(note.text for note in summary.notes):
        print(f"magcal apply: warning: {note}", file=sys.stderr)
    print(summary.text())
    lab = (calibration.summary or {}).get("lab_field")
    if isinstance(lab, dict) and lab.get("ned_nT") is not None:
        n, e, d = lab["ned_nT"]
        print(
            f"the lab's field fitted with this calibration: N {n:.1f}, E {e:.1f}, D {d:.1f} nT: the world columns of a "
            f"record of the same lab are that field plus what changed; `magcal diagnose NEW.csv --reference-vector "
            f"{args.calibration}` judges them against it"
            + (
                "; its gradient along the calibration's path is that record's and is not applied"
                if "gradient_nT_per_m" in lab
                else ""
            )
        )
    return 0


def _run_compensation(args, parallel) -> int:
    """``magcal apply`` of a compensation (``kind: "compensation"``): each line gets ``<scalar>_comp``; several
    lines go into the folder ``-o``, each as ``<name>_comp`` in ``--format``; with ``--workers``/``--scheduler``,
    Dask partitions each read with a margin of samples (:mod:`magcal.output.compensated_survey`) into ``-o``."""
    if args.uncertainty or args.record_terms or args.force:
        raise MagcalError(
            "--uncertainty, --record-terms and --force are for a magnetometer's calibration, not a compensation"
        )
    if args.workers is not None or args.scheduler is not None:  # partitions read with a margin of samples
        partitioned = apply_compensation_partitioned(
            args.calibration,
            args.data,
            args.output,
            fmt=args.format,
            workers=args.workers or 2,
            scheduler=args.scheduler,
            partition_rows=args.partition_rows,
            columns=args.columns,
            units=args.units,
            drop_bad=args.drop_bad,
            compression=args.compression,
        )
        print(partitioned.text())
        return 0
    return _compensate_lines(args, parallel, apply_compensation_file)


def _run_cross_compensation(args, parallel) -> int:
    """``magcal apply`` of the cross's compensation (``kind: "cross_compensation"``): each line gets its sensors'
    compensated vectors and the compensated tensor; several lines go into the folder ``-o``, each as
    ``<name>_comp`` in ``--format``."""
    if args.uncertainty or args.record_terms or args.force or args.workers is not None or args.scheduler is not None:
        raise MagcalError(
            "--uncertainty, --record-terms, --force, --workers and --scheduler are for a magnetometer's calibration, "
            "not the cross's compensation"
        )
    return _compensate_lines(args, parallel, apply_cross_compensation_file)


def _compensate_lines(args, parallel, apply_file) -> int:
    """Each line of ``args.data`` compensated by ``apply_file`` (a scalar's or the cross's compensation) into
    ``-o``, or into the folder ``-o`` as ``<name>_comp`` in ``--format`` when there are several."""
    targets = [args.output]
    if parallel:
        os.makedirs(args.output, exist_ok=True)
        stems = [os.path.splitext(os.path.basename(path))[0] for path in args.data]
        if len(set(stems)) < len(stems):
            raise MagcalError("the lines' file names must differ (their outputs share the folder -o)")
        targets = [os.path.join(args.output, f"{stem}_comp.{args.format}") for stem in stems]
    for path, target in zip(args.data, targets):
        summary = apply_file(
            args.calibration,
            path,
            target,
            columns=args.columns,
            units=args.units,
            drop_bad=args.drop_bad,
            compression=args.compression if target.endswith(".parquet") else None,
        )
        for note in dict.fromkeys(summary.notes):
            print(f"magcal apply: warning: {path}: {note}", file=sys.stderr)
        print(summary.text())
    return 0
