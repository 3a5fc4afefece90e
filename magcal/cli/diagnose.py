"""``magcal diagnose``: where the calibration model fails and which physical effect is missing.

Example::

    magcal simulate --hidden temperature_bias:2 -o hidden.csv
    magcal diagnose hidden.csv
    magcal diagnose hidden.csv --effects temperature_bias:2 --json
    magcal diagnose field.csv --effects-file my_effects.py      # your own effects are candidates too
    magcal diagnose field.csv --noise 80                         # the noise per axis is known: 80 nT

Fits the base model (plus ``--effects``), then prints a ranked table of candidate effects (score test, confirmed
by refitting the best ones) and a verdict: ``adequate``, ``missing_effect`` or ``unexplained``. With ``--json``
it prints one JSON object: ``effects``, ``rms_nT``, ``noise_nT``, ``noise_source``, ``noise`` (the method and its
checks), ``verdict``, ``warnings``, ``candidates`` (``effect``, ``sensor``, ``delta_bic``, ``rms_after_nT``,
``held_out_rms_before_nT`` / ``_after_nT``, ``later_rms_before_nT`` / ``_after_nT``, ``holds``, ``evidence``, best
first), ``validation`` (the held-out judgement: a candidate is recommended only if its gain holds on samples the
fit did not see; ``--no-validate`` skips it), ``quality`` (every finding of
:func:`magcal.checks.quality.assess`; its warnings are also in ``warnings``) and more. The table is followed by a "Data
quality" section with the notable findings.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

from magcal.checks.coverage import calibration_input_checks
from magcal.checks.quality import assess, field_magnitude_finding
from magcal.cli.calibrate import (
    add_input_arguments,
    add_noise_argument,
    checked_effect_names,
    checked_noise,
    compass_report,
    named_error,
    read_input,
)
from magcal.core.errors import CalibrationError, MagcalError
from magcal.core.notes import unique
from magcal.diagnosis import diagnose, start_workers
from magcal.diagnosis._parallel import cores
from magcal.fitting.pipeline import calibrate


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``diagnose`` subcommand."""
    parser = subparsers.add_parser(
        "diagnose",
        help="find structure the model leaves in the residuals and the physical effect that explains it",
        description="Calibrate (base model plus --effects), test every catalogue effect whose channels the file "
        "has (score test, then refits of the best), and give a verdict: adequate, missing_effect or "
        "unexplained. See docs/effects.md for the effects.",
    )
    add_arguments(parser)
    parser.set_defaults(func=run)
    return parser


def add_arguments(parser) -> None:
    """The options of ``magcal diagnose``."""

    add_input_arguments(parser)
    parser.add_argument(
        "--effects",
        action="append",
        default=None,
        metavar="LIST",
        help="effects already in the model, comma-separated NAME or NAME:SENSOR (e.g. "
        "temperature_bias,bias_step:2); repeatable. Every catalogue effect, and your own "
        "from --effects-file, is a candidate of the diagnosis",
    )
    parser.add_argument(
        "--reference",
        type=float,
        default=None,
        metavar="NT",
        help="known total field in nT (default: the file's ref_total column or reference_total_nT "
        "line; without either the magnitude is fitted)",
    )
    parser.add_argument(
        "--top", type=int, default=3, metavar="K", help="number of candidate effects confirmed by refitting (default 3)"
    )
    parser.add_argument("--robust", action="store_true", help="robust (soft-L1) loss for the fits")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of the table")
    parser.add_argument(
        "--no-validate",
        dest="validate",
        action="store_false",
        help="skip the held-out validation of the supported candidates (by default each is fitted on "
        "alternating blocks in time and on the first part of the record, and recommended only "
        "if its gain holds on the samples held out)",
    )

    parser.add_argument(
        "--workers",
        type=int,
        default=None,
        metavar="N",
        help="cores for the independent fits (default: every core; a large record's fits run in worker "
        "processes, a small one's on threads; 1: one after the other)",
    )
    parser.add_argument(
        "--scheduler",
        default=None,
        metavar="ADDRESS",
        help="run the independent fits on an existing dask.distributed cluster (e.g. tcp://host:8786)",
    )
    add_noise_argument(parser)


#: Bytes of a data file per reading (sensor x sample), at least: a CSV's "49871.23," is 9 and a file has a time
#: column besides (a Parquet float64, compressed, a little less). The file's size over this overstates its readings,
#: which only decides whether the worker processes' fork server starts while the file is read.
FILE_BYTES_PER_READING = 8


def _start_workers_while_reading(args) -> bool:
    """Start the diagnosis's worker processes' fork server now, if its fits will likely run in worker processes,
    so that its imports run while the file is read and the record calibrated
    (:func:`magcal.diagnosis.start_workers`). Not with a user's effects file (their fits stay on threads)."""
    if getattr(args, "effects_file", None) or getattr(args, "scheduler", None):
        return False
    try:
        size = os.path.getsize(args.data)
    except (OSError, TypeError, ValueError):
        return False
    return start_workers(workers=getattr(args, "workers", None), readings=size // FILE_BYTES_PER_READING)


def run(args) -> int:

    if args.reference is not None and not args.reference > 0:
        raise MagcalError(f"--reference must be a positive field in nT, got {args.reference}")
    if args.top < 1:
        raise MagcalError(f"--top must be at least 1, got {args.top}")
    if getattr(args, "workers", None) is not None and not 1 <= args.workers <= 4 * cores():
        raise MagcalError(f"--workers {args.workers}: give 1 to {4 * cores()} (this machine has {cores()} cores)")

    checked_noise(args)
    names = checked_effect_names(args)
    _start_workers_while_reading(args)
    ds, notes = read_input(args)
    quality = assess(ds)  # data quality, read before the fit (issue 10)
    notes += calibration_input_checks(ds, args.reference)  # coverage and reference, as calibrate
    try:
        result = calibrate(
            ds, effects=names, robust=args.robust, reference_total_nT=args.reference, noise_nT=args.noise
        )
        diagnosis = diagnose(
            ds,
            result,
            top=args.top,
            validate=args.validate,
            noise_nT=args.noise,
            workers=getattr(args, "workers", None),
            scheduler=getattr(args, "scheduler", None),
        )
    except CalibrationError as exc:
        raise MagcalError(named_error(args.data, exc)) from None
    notes += [note.text for note in unique(result.notes + diagnosis.notes)]  # what the fits said, as values
    notes += [w for w in result.warnings if w not in notes]
    quality.add(field_magnitude_finding(result.reference_total_nT, result.reference_kind))
    notes += [w for w in quality.warnings if w not in notes]
    compasses = compass_report(ds, notes=notes, args=args)  # several compasses on one vehicle (issue 40, item 5)
    for note in notes:
        if args.json or note not in quality.warnings:  # the text output shows those in its Data quality section
            print(f"magcal diagnose: warning: {note}", file=sys.stderr)
    if args.json:
        doc = diagnosis.to_dict()
        doc["warnings"] = list(dict.fromkeys(notes + list(doc.get("warnings", []))))  # every warning of the run
        doc["quality"] = quality.to_dict()
        if compasses is not None:
            doc["compass_consistency"] = compasses.to_dict()
        json.dump(doc, sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        title = f"magcal diagnosis of {args.data}"
        shown = ds if args.reference is None else ds.replace(reference_total_nT=args.reference)  # the field used
        sys.stdout.write(f"{title}\n{'=' * len(title)}\n{shown.describe()}\n\n{diagnosis.table()}\n")
        sys.stdout.write(f"Diagnosed in {diagnosis.where_text()}.\n")
        sys.stdout.write("\n" + quality.section())
        if compasses is not None:
            sys.stdout.write("\n" + compasses.text())
    return 0
