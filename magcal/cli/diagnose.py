"""``magcal diagnose``: where the calibration model fails and which physical effect is missing.

Example::

    magcal simulate --hidden temperature_bias:2 -o hidden.csv
    magcal diagnose hidden.csv
    magcal diagnose hidden.csv --effects temperature_bias:2 --json
    magcal diagnose field.csv --effects-file my_effects.py      # your own effects are candidates too
    magcal diagnose field.csv --noise 80                         # the noise per axis is known: 80 nT
    magcal diagnose flight1.csv --also flight2.csv              # a vehicle: attitude and the field vector
    magcal diagnose flight.bin --reference igrf --also next.bin  # a flight log, IGRF along the track

Fits the base model (plus ``--effects``), then prints a ranked table of candidate effects (score test, confirmed
by refitting the best ones) and a verdict: ``adequate``, ``missing_effect`` or ``unexplained``. With ``--json``
it prints one JSON object: ``effects``, ``rms_nT``, ``noise_nT``, ``noise_source``, ``noise`` (the method and its
checks), ``verdict``, ``warnings``, ``candidates`` (``effect``, ``sensor``, ``delta_bic``, ``rms_after_nT``,
``held_out_rms_before_nT`` / ``_after_nT``, ``later_rms_before_nT`` / ``_after_nT``, ``holds``, ``evidence``, best
first), ``validation`` (the held-out judgement: a candidate is recommended only if its gain holds on samples the
fit did not see; ``--no-validate`` skips it), ``quality`` (every finding of
:func:`magcal.checks.quality.assess`; its warnings are also in ``warnings``) and more. The table is followed by a "Data
quality" section with the notable findings.

Vector mode. A record with the attitude and the field vector (``ref_n, ref_e, ref_d`` columns,
``--reference-vector``, ``--reference igrf`` at ``--lat/--lon`` or along ``lat, lon, alt_m``) is diagnosed on the
vector fit (:func:`magcal.diagnosis.vector.diagnose_vector`): the candidates are judged on the world north/east/down
residuals and ``|B|``, fitted on the earlier part and applied to the later part (and to every ``--also`` flight of
the same vehicle, each weighed at its own noise) as ``magcal apply`` applies them; an effect that raises one world
component or ``|B|`` there beyond its noise is not advised, and a record too short or too slow to hold out a later
part (without a long enough ``--also`` flight) gets the verdict ``not_judged`` with what would let it judge (samples,
minutes, the compass's logging rate). ``--mode NAME`` forces a fit mode (:mod:`magcal.modes`; ``auto``, the
default, chooses as ``magcal calibrate`` does: the vector fit when the record has both); ``--json`` then prints the
vector diagnosis's document (``mode``: ``vector``). A record with an accelerometer and no attitude (the gravity
mode) is diagnosed on the total-field fit, with the gravity fit's dip residual as evidence beside it
(``dip_evidence``).
"""

from __future__ import annotations

import argparse
import json
import os
import sys

from magcal.checks.coverage import calibration_input_checks
from magcal.checks.quality import assess, field_magnitude_finding
from magcal.checks.reference import (
    add_reference_arguments,
    add_vector_reference_arguments,
    reference_from_args,
    vector_reference_from_args,
)
from magcal.cli.calibrate import (
    add_input_arguments,
    add_mode_argument,
    add_noise_argument,
    checked_attitude_noise,
    checked_effect_names,
    checked_noise,
    choose_mode,
    compass_report,
    effect_names_before_mode,
    mode_options,
    named_error,
    read_input,
    vector_effects,
)
from magcal.cli.commands import HELP
from magcal.cli.compensation_mode import (
    add_compensation_arguments,
    run_compensation_diagnosis,
    run_cross_compensation_diagnosis,
    wants_compensation,
    wants_cross_compensation,
)
from magcal.core.errors import CalibrationError, MagcalError
from magcal.core.notes import unique
from magcal.data.attitude import attitude_source
from magcal.diagnosis import start_workers
from magcal.diagnosis._parallel import cores
from magcal.diagnosis.vector import JUDGE_TOP, Flight
from magcal.modes import CROSS_COMPENSATION, GRAVITY, TOTAL_FIELD, VECTOR


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``diagnose`` subcommand."""
    parser = subparsers.add_parser(
        "diagnose",
        help=HELP["diagnose"],
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
    add_reference_arguments(parser)
    add_vector_reference_arguments(parser)
    add_mode_argument(parser, "diagnose")
    add_compensation_arguments(parser, figure=False)
    parser.add_argument(
        "--also",
        action="append",
        default=None,
        metavar="FILE",
        help="vector mode: another flight of the same vehicle (read with the same options); a candidate is "
        "recommended only if it improves it too (repeatable)",
    )
    parser.add_argument(
        "--attitude-noise-deg",
        type=float,
        default=None,
        metavar="DEG",
        help="vector mode: the attitude's error per axis (deg, 1 sigma); estimated if not given",
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
        "if its gain holds on the samples held out; in vector mode nothing is recommended without it: verdict "
        "not_judged)",
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


def _scalar_reference(args, ds):
    """``(dataset, number or None)`` for the scalar diagnosis from ``--reference``: a number in nT is passed on as
    before; ``igrf``, ``column`` or ``fit`` are resolved into the dataset as ``magcal calibrate`` does."""
    text = getattr(args, "reference", None)
    if text is None:
        return ds, None
    try:
        value = float(text)
    except (TypeError, ValueError):
        value = None
    if value is not None:
        if not value > 0 or value != value:
            raise MagcalError(f"--reference must be a positive field in nT, got {text}")
        return ds, value
    reference = reference_from_args(args, ds)
    ds = reference.apply(ds)
    if reference.kind == "fitted":
        ds = ds.replace(ref_total_nT=None)
    return ds, None


def run(args) -> int:

    if args.top < 1:
        raise MagcalError(f"--top must be at least 1, got {args.top}")
    if getattr(args, "workers", None) is not None and not 1 <= args.workers <= 4 * cores():
        raise MagcalError(f"--workers {args.workers}: give 1 to {4 * cores()} (this machine has {cores()} cores)")
    ref_text = getattr(args, "reference", None)
    if ref_text is not None and str(ref_text).strip().lower() not in ("igrf", "column", "fit", "fitted"):
        try:
            if not float(ref_text) > 0:
                raise ValueError
        except (TypeError, ValueError):
            raise MagcalError(
                f"--reference must be a positive field in nT, or igrf, column, fit or fitted; got {ref_text}"
            ) from None

    checked_noise(args)
    checked_attitude_noise(args)
    if wants_compensation(args):  # its --effects are its own terms, not the catalogue's: before their check
        return run_compensation_diagnosis(args, read_input)
    if wants_cross_compensation(args):  # its --effects are its own terms too
        ds, notes = read_input(args)
        return run_cross_compensation_diagnosis(args, ds, notes, read_input)
    effect_names_before_mode(args)  # an unknown name fails before reading
    if getattr(args, "mode", "auto") != "vector":
        _start_workers_while_reading(args)
    ds, notes = read_input(args)
    mode, vref = choose_mode(args, ds, "diagnose")
    if mode is CROSS_COMPENSATION:  # its --effects are checked against its own terms
        return run_cross_compensation_diagnosis(args, ds, notes, read_input)
    names = checked_effect_names(args)  # the chosen mode's catalogue
    if mode is VECTOR:
        return run_vector(args, ds, vref, notes)
    if getattr(args, "also", None):
        raise MagcalError(
            "--also: other flights judge a vector calibration; this record is diagnosed in scalar mode (it lacks the "
            "attitude or the field vector, or --mode scalar was given)"
        )
    if mode is not TOTAL_FIELD and mode is not GRAVITY:
        return run_mode(args, ds, mode, notes)
    ds, reference = _scalar_reference(args, ds)
    quality = assess(ds)  # data quality, read before the fit
    notes += calibration_input_checks(ds, reference)  # coverage and reference, as calibrate
    # the gravity mode's diagnosis is the total-field one, with the gravity fit's dip residual beside it
    extra = {"robust": bool(args.robust)} if mode is GRAVITY else {}
    try:
        result = TOTAL_FIELD.fit(
            ds, effects=names, robust=args.robust, reference_total_nT=reference, noise_nT=args.noise
        )
        diagnosis = mode.diagnose(
            ds,
            result,
            top=args.top,
            validate=args.validate,
            noise_nT=args.noise,
            workers=getattr(args, "workers", None),
            scheduler=getattr(args, "scheduler", None),
            **extra,
        )
    except CalibrationError as exc:
        raise MagcalError(named_error(args.data, exc)) from None
    dip = getattr(diagnosis, "dip_evidence", None)
    notes += [note.text for note in unique(result.notes + diagnosis.notes)]  # what the fits said, as values
    notes += [w for w in result.remarks if w not in notes]
    quality.add(field_magnitude_finding(result.reference_total_nT, result.reference_kind))
    notes += [w for w in quality.warnings if w not in notes]
    for note in notes:
        if args.json or note not in quality.warnings:  # the text output shows those in its Data quality section
            print(f"magcal diagnose: warning: {note}", file=sys.stderr)
    if args.json:
        doc = diagnosis.to_dict()
        doc["warnings"] = list(dict.fromkeys(notes + list(doc.get("warnings", []))))  # every warning of the run
        doc["quality"] = quality.to_dict()
        json.dump(doc, sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        title = f"magcal diagnosis of {args.data}"
        shown = ds if reference is None else ds.replace(reference_total_nT=reference)  # the field used
        sys.stdout.write(f"{title}\n{'=' * len(title)}\n{shown.describe()}\n\n{diagnosis.table()}\n")
        sys.stdout.write(f"Diagnosed in {diagnosis.where_text()}.\n")
        if dip is not None:
            sys.stdout.write("\n" + dip.text() + "\n")
        sys.stdout.write("\n" + quality.section())
    return 0


def run_mode(args, ds, mode, notes) -> int:
    """``magcal diagnose`` in an installed package's fit mode: its diagnosis (:meth:`magcal.modes.base.FitMode.diagnose`,
    with those of ``--effects``, ``--robust``, ``--noise``, ``--top`` and ``--no-validate`` it takes) as a table, or
    its document with ``--json``."""
    _, options = mode_options(args, mode, "diagnose")
    known = mode.accepts("diagnose")
    options.update({k: v for k, v in (("top", args.top), ("validate", args.validate)) if known is None or k in known})
    print(f"magcal diagnose: {mode.name} mode ({mode.title})", file=sys.stderr)
    try:
        diagnosis = mode.diagnose(ds, **options)
    except CalibrationError as exc:
        raise MagcalError(named_error(args.data, exc)) from None
    except NotImplementedError as exc:
        raise MagcalError(f"--mode {mode.name}: {exc}") from None
    notes += [note.text for note in unique(diagnosis.notes)]
    for note in dict.fromkeys(notes):
        print(f"magcal diagnose: warning: {note}", file=sys.stderr)
    if args.json:
        doc = diagnosis.to_dict()
        doc["warnings"] = list(dict.fromkeys(notes + list(doc.get("warnings", []))))
        json.dump(doc, sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        title = f"magcal diagnosis of {args.data}"
        sys.stdout.write(f"{title}\n{'=' * len(title)}\n{ds.describe()}\n\n{diagnosis.table()}\n")
    return 0


def _also_flights(args) -> list:
    """The ``--also`` flights, each read with the data options and its own field vector."""
    flights = []
    for path in getattr(args, "also", None) or ():
        other = argparse.Namespace(**{**vars(args), "data": path})
        ds, _ = read_input(other)
        if attitude_source(ds) is None:
            raise MagcalError(
                f"{path}: --also needs a flight with the attitude (qw..qz or roll_deg, pitch_deg, yaw_deg)"
            )
        vref = vector_reference_from_args(other, ds)
        if vref is None:
            raise MagcalError(
                f"{path}: --also needs the field vector of that flight: ref_n, ref_e, ref_d columns, --reference-vector, "
                "or --reference igrf (along its lat, lon, alt_m columns or at --lat/--lon)"
            )
        flights.append(Flight(ds, vref, os.path.basename(path)))
    return flights


def run_vector(args, ds, vref, notes) -> int:
    """``magcal diagnose`` in vector mode (:func:`magcal.diagnosis.vector.diagnose_vector`)."""
    effects = vector_effects(args, ds)
    flights = _also_flights(args)
    quality = assess(ds)
    print(f"magcal diagnose: vector mode; reference: {vref.text}", file=sys.stderr)
    try:
        diagnosis = VECTOR.diagnose(
            ds,
            reference=vref,
            effects=effects,
            also=flights,
            attitude_noise_deg=args.attitude_noise_deg,
            noise_nT=args.noise,
            reference_total_nT=ds.ref_total_nT,
            robust=args.robust,
            validate=args.validate,
            top=max(args.top, JUDGE_TOP),
        )
    except CalibrationError as exc:
        raise MagcalError(named_error(args.data, exc)) from None
    notes += [note.text for note in unique(diagnosis.notes)]
    # several compasses on one vehicle: their consistency after the diagnosed (base) vector fit
    fitted = diagnosis.result
    compasses = compass_report(
        ds, vref=vref if fitted is None else fitted.reference, fit=fitted, notes=notes, args=args
    )
    notes += [w for w in quality.warnings if w not in notes]
    for note in dict.fromkeys(notes):
        if args.json or note not in quality.warnings:
            print(f"magcal diagnose: warning: {note}", file=sys.stderr)
    if args.json:
        doc = diagnosis.to_dict()
        doc["warnings"] = list(dict.fromkeys(notes + list(doc.get("warnings", []))))
        doc["quality"] = quality.to_dict()
        if compasses is not None:
            doc["compass_consistency"] = compasses.to_dict()
        json.dump(doc, sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        title = f"magcal diagnosis of {args.data}"
        described = ds.describe(reference=f"vector ({vref.kind})")
        sys.stdout.write(f"{title}\n{'=' * len(title)}\n{described}\n\n{diagnosis.table()}\n")
        sys.stdout.write(f"Diagnosed in {diagnosis.where_text()}.\n")
        if compasses is not None:
            sys.stdout.write("\n" + compasses.text())
        sys.stdout.write("\n" + quality.section())
    return 0
