"""``magcal calibrate``: calibrate from a data file and print a report (or JSON), optionally saving the result.

Example::

    magcal calibrate chi2017.csv -o cal.json
    magcal calibrate chi2017.csv --reference 50000 --json
    magcal calibrate field.csv --robust --method ml
    magcal calibrate field.csv --effects-file my_effects.py --effects pump_interference -o cal.json
    magcal calibrate mems.csv --units counts --lsb 150        # raw counts of 150 nT (0.15 uT/LSB)
    magcal calibrate field.csv --effects temperature_bias --noise 80   # held-out RMS beside the in-sample one

With ``--effects`` the report and ``--json`` (``validation``) also give the held-out total-field RMS (blocks
scheme of :mod:`magcal.fitting.validation`) of the base model and of the model with the effects, beside the in-sample
RMS, so that a gain that only fits this record shows; and, per effect, whether it is an instrument term (carried to
new data) or record-only (applied only to this record).

Before the fit the data's quality is assessed (:mod:`magcal.checks.quality`: sample rate, gaps, stale readings,
quantization, clipping, static stretches, temperature): the report gets a "Data quality" section with the notable
findings, ``--json`` gets all of them under ``quality`` and each warning also under ``warnings``.

Other subcommands reuse :func:`add_input_arguments` / :func:`read_input` for the data file options. To add an
option, add it in :func:`add_arguments` and map it in :func:`calibrate_options`.
"""

from __future__ import annotations

import argparse
import json
import sys

from magcal.calibration.report import calibration_json, text_report
from magcal.checks.coverage import calibration_input_checks
from magcal.checks.quality import assess, field_magnitude_finding, without_other_field_parts
from magcal.checks.reference import (
    add_reference_arguments,
    add_vector_reference_arguments,
    reference_from_args,
    vector_reference_from_args,
)
from magcal.cli.commands import HELP
from magcal.cli.compensation_mode import (
    add_compensation_arguments,
    run_compensation,
    run_cross_compensation,
    wants_compensation,
    wants_cross_compensation,
)
from magcal.cli.fit_report import report_fit
from magcal.cli.gravity_mode import add_gravity_arguments, gravity_options
from magcal.core.errors import CalibrationError, MagcalError
from magcal.data import io
from magcal.data.attitude import attitude_present, attitude_source
from magcal.diagnosis.compasses import compass_consistency
from magcal.diagnosis.cross_compensation import CROSS_EFFECTS
from magcal.fitting.pipeline import METHODS, SEARCH_METHODS
from magcal.fitting.search import DEFAULTS
from magcal.fitting.vector import PLATFORM_EFFECTS, fit_vector, vector_model
from magcal.model.terms import check_effect_names
from magcal.modes import (
    CROSS_COMPENSATION,
    FIT_MODES,
    GRAVITY,
    TOTAL_FIELD,
    VECTOR,
    load_entry_points,
    mode_choice,
    mode_names,
)


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``calibrate`` subcommand."""
    parser = subparsers.add_parser(
        "calibrate",
        help=HELP["calibrate"],
        description="Calibrate from a magcal CSV file: ellipsoid fit per sensor, Procrustes between sensors, then "
        "maximum likelihood. Prints a readable report, or one JSON object with --json.",
    )
    add_arguments(parser)
    parser.set_defaults(func=run)
    return parser


def add_input_arguments(parser) -> None:
    """Data-file options shared by the subcommands that read a CSV file."""
    parser.add_argument("data", metavar="FILE.csv", help="data file (see docs/formats.md)")
    parser.add_argument(
        "--columns",
        default=None,
        metavar="MAP",
        help="map your column names onto magcal's, e.g. x=magX,y=magY,z=magZ,t=time",
    )
    parser.add_argument(
        "--units", default=None, help="unit of the readings (nT, uT, G, mG, or counts with --lsb); overrides the file"
    )
    parser.add_argument(
        "--lsb",
        default=None,
        metavar="NT_PER_COUNT",
        help="for --units counts (raw sensor counts): nT per count, e.g. 150 for 0.15 uT/LSB; "
        "overrides the file's '# lsb_nT:' line",
    )
    parser.add_argument(
        "--drop-bad",
        action="store_true",
        help="drop rows with missing or non-numeric values (with a warning) instead of refusing",
    )
    add_max_rows_argument(parser)
    parser.add_argument(
        "--exclude-part",
        action="store_true",
        help="leave out the part at the start or the end of the record that the data-quality check finds in another "
        "field (another run left in the file, a still phase where the field differs: the finding other_field)",
    )


def add_max_rows_argument(parser) -> None:
    """``--max-rows N``: the most rows a whole-file read takes (:func:`magcal.data.io.read_csv`'s ``max_rows``)."""
    parser.add_argument(
        "--max-rows",
        type=int,
        default=None,
        metavar="N",
        help=f"refuse a data file of more rows than N (0: no limit but the free memory); default "
        f"{io.MAX_READ_ROWS:,} for Parquet, whose rows are counted from its footer before reading, and no limit for "
        "CSV",
    )


def checked_max_rows(args):
    """``--max-rows`` checked: None (the default) or a number of rows >= 0."""
    value = getattr(args, "max_rows", None)
    if value is not None and value < 0:
        raise MagcalError(f"--max-rows must be a number of rows (0: no limit), got {value}")
    return value


def add_arguments(parser) -> None:
    """The options of ``magcal calibrate``."""

    add_input_arguments(parser)
    add_reference_arguments(parser)
    add_vector_reference_arguments(parser)
    add_mode_argument(parser, "calibrate")
    add_gravity_arguments(parser)
    add_compensation_arguments(parser)
    parser.add_argument(
        "--attitude-noise-deg",
        type=float,
        default=None,
        metavar="DEG",
        help="vector mode: the attitude's error per axis (deg, 1 sigma); estimated from the residuals if not given",
    )
    parser.add_argument(
        "--field-gradient",
        action="store_true",
        help="vector mode: also fit a gradient of the field along the path, B(p) = B0 + G (p - p0), from the "
        "positions (pos_n_m, pos_e_m, pos_d_m in m north-east-down, or lat, lon, alt_m): a magnet or steel near the "
        "path; record-only, never carried by apply (docs/vector.md)",
    )
    parser.add_argument(
        "--platform-terms",
        default="none",
        metavar="LIST",
        help="vector mode, the names of earlier versions: eddy (the effect eddy_currents) and current "
        "(current_field), comma-separated, auto (every one the data support) or none (default); --effects takes "
        "them and every other effect",
    )
    parser.add_argument(
        "--method",
        default="ml",
        choices=METHODS + SEARCH_METHODS,
        help="ml (default): ellipsoid, Procrustes, maximum likelihood; ellipsoid: the seed's two "
        "steps only; pso, ipso, de: global search",
    )
    parser.add_argument(
        "--ellipsoid",
        default="algebraic",
        choices=("algebraic", "li-griffiths"),
        help="step-1 estimator (default algebraic)",
    )
    parser.add_argument(
        "--robust",
        action="store_true",
        help="robust (soft-L1) loss: gross outliers do not pull the fit; they are reported",
    )
    parser.add_argument("--seed", type=int, default=None, help="seed of the global-search methods")
    parser.add_argument(
        "--effects",
        action="append",
        default=None,
        metavar="LIST",
        help="candidate effects to add to the base model, comma-separated NAME or NAME:SENSOR "
        "(e.g. temperature_bias,bias_step:2; see docs/effects.md, and magcal effects for the "
        "list); your own effects with --effects-file; repeatable",
    )
    parser.add_argument("-o", "--output", default=None, metavar="CAL.json", help="save the calibration here")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of the report")
    parser.add_argument(
        "--no-validate",
        dest="validate",
        action="store_false",
        help="with --effects (or vector mode with platform terms): skip the held-out RMS of the base model and "
        "of the model with the effects (fitted on alternating blocks in time, scored on the blocks between)",
    )
    add_noise_argument(parser)


def add_mode_argument(parser, command) -> None:
    """``--mode NAME``: the fit mode, one of :func:`magcal.modes.base.mode_names` (installed packages' modes included,
    loaded here; a failing one is a warning)."""
    for note in load_entry_points().notes:
        print(f"magcal {command}: warning: {note.text}", file=sys.stderr)
    ranked = [FIT_MODES[name] for name in mode_names() if name in FIT_MODES]
    parser.add_argument(
        "--mode",
        default="auto",
        choices=mode_names(),
        help="the fit: "
        + "; ".join(f"{m.name}: the {m.title}, {m.needs()}" for m in ranked)
        + "; scalar: total_field (docs/vector.md, docs/gravity.md); auto (default): the first of these the record "
        "holds what it needs for (compensation when the file has a scalar magnetometer's column beside the "
        "fluxgate, docs/compensation.md; vector when some rows have an attitude and the field vector is known: ref_n, "
        "ref_e, ref_d, --reference-vector or --reference igrf; gravity when the file has accelerometer columns "
        "and no attitude; else the total-field fit)",
    )


def add_noise_argument(parser) -> None:
    """``--noise NT``: the noise per axis, known (shared by calibrate and diagnose)."""
    parser.add_argument(
        "--noise",
        type=float,
        default=None,
        metavar="NT",
        help="noise per axis in nT, if you know it (e.g. from a still recording): used for the floors "
        "and the verdict instead of the file's '# noise_nT:' line or any estimate; the report "
        "says 'given'",
    )


def checked_noise(args):
    """``--noise`` checked: a positive finite number of nT, or None."""
    import math

    noise = getattr(args, "noise", None)
    if noise is not None and not (math.isfinite(noise) and noise > 0):
        raise MagcalError(f"--noise must be a positive noise per axis in nT, got {noise}")
    return noise


def read_input(args):
    """Read the data file named by :func:`add_input_arguments` options; returns ``(dataset, warning texts)``."""

    ds = io.read_csv(
        args.data,
        columns=args.columns,
        units=args.units,
        drop_bad=args.drop_bad,
        lsb_nT=getattr(args, "lsb", None),
        max_rows=checked_max_rows(args),
        warn=False,
    )
    notes = [note.text for note in ds.notes]
    if getattr(args, "exclude_part", False):
        ds, finding = without_other_field_parts(ds)
        notes.append(
            f"--exclude-part: left out {finding.summary.partition(': ')[2]}"
            if finding is not None
            else "--exclude-part: no part of the record is in another field; every sample is kept"
        )
    return ds, notes


def named_error(path, exc) -> str:
    """The message of a calibration failure with the data file in front (unless it already names it)."""
    text = str(exc)
    return text if text.startswith(f"{path}:") else f"{path}: {text}"


def effect_names(value) -> list:
    """Effect names from an ``--effects`` value: ``"a,b"``, ``["a", "b:2"]`` or ``["a,b"]``; None gives []."""
    if not value:
        return []
    items = [value] if isinstance(value, str) else list(value)
    return [name.strip() for item in items for name in str(item).split(",") if name.strip()]


def checked_effect_names(args) -> list:
    """:func:`effect_names` of ``--effects``, refusing a name not in the catalogue with a message that says how to
    load a user's own effect (``--effects-file``)."""

    names = effect_names(getattr(args, "effects", None))
    check_effect_names(names, "--effects")
    return names


def effect_names_before_mode(args) -> list:
    """``--effects`` checked as far as it can be before the record is read: against the catalogue for a named mode;
    with ``--mode auto`` the mode is chosen from the record first, so a name of the cross compensation's terms
    (:data:`magcal.diagnosis.cross_compensation.CROSS_EFFECTS`) waits for the chosen mode's check and any other
    unknown name fails now."""
    names = effect_names(getattr(args, "effects", None))
    if (getattr(args, "mode", "auto") or "auto") != "auto":
        return checked_effect_names(args)
    check_effect_names([n for n in names if n.partition(":")[0].strip() not in CROSS_EFFECTS], "--effects")
    return names


def calibrate_options(args) -> dict:
    """Keyword arguments of :func:`magcal.fitting.pipeline.calibrate` from the parsed options."""
    return {
        "method": args.method,
        "effects": checked_effect_names(args),
        "robust": args.robust,
        "reference_total_nT": None,  # resolved into the dataset by run() (number, igrf, column or fit)
        "seed": args.seed,
        "ellipsoid_method": args.ellipsoid,
        "noise_nT": checked_noise(args),
    }


def _platform_terms(args):
    text = str(getattr(args, "platform_terms", "none") or "none").strip().lower()
    if text == "auto":
        return list(PLATFORM_EFFECTS)
    if text == "none":
        return []
    names = [t.strip() for t in text.split(",") if t.strip()]
    for t in names:
        if t not in PLATFORM_EFFECTS:
            raise MagcalError(
                f"--platform-terms: unknown term {t!r}; use {', '.join(PLATFORM_EFFECTS)}, auto or none (or "
                "--effects eddy_currents,current_field)"
            )
    return names


def choose_mode(args, ds, command="calibrate"):
    """``(mode, field vector)``: the fit mode for the record from ``--mode`` and what the data hold
    (:func:`magcal.modes.base.mode_choice`, its notes printed), and the field vector the options give (None unless the
    record has an attitude and ``--mode`` could be the vector fit; the vector fit's reference)."""
    name = getattr(args, "mode", "auto") or "auto"
    present = attitude_present(ds)
    may_be_vector = name == VECTOR.name or (name == "auto" and present is not None and present.any())
    vref = vector_reference_from_args(args, ds) if may_be_vector and attitude_source(ds) is not None else None
    try:
        mode, said = mode_choice(ds, name, option="--mode", reference=vref)
    except MagcalError as exc:
        raise MagcalError(named_error(args.data, exc)) from None
    for note in said:
        print(f"magcal {command}: {args.data}: {note.text}", file=sys.stderr)
    return mode, vref if mode is VECTOR else None


def checked_attitude_noise(args):
    """``--attitude-noise-deg`` checked: an angle in [0, 90) deg, or None."""
    att = getattr(args, "attitude_noise_deg", None)
    if att is not None and not (att >= 0 and att < 90):
        raise MagcalError(f"--attitude-noise-deg must be an angle between 0 and 90 deg, got {att}")
    return att


def vector_effects(args, ds) -> list:
    """The effects of a vector fit from ``--effects`` and ``--platform-terms`` (its names of earlier versions),
    checked against the data (:func:`magcal.fitting.vector.vector_model`): one clear message otherwise."""
    names = checked_effect_names(args) + [PLATFORM_EFFECTS[t] for t in _platform_terms(args)]
    names = list(dict.fromkeys(names))
    try:
        vector_model(ds, names)
    except (CalibrationError, MagcalError) as exc:
        raise MagcalError(f"{args.data}: --effects: {exc}") from None
    return names


def vector_options(args, ds, vref) -> tuple[str, dict]:
    """What ``magcal calibrate`` says of a vector fit and its options (:meth:`magcal.modes.vector.VectorMode.fit`)
    from the parsed options."""
    options = {
        "reference": vref,
        "effects": vector_effects(args, ds),
        "attitude_noise_deg": checked_attitude_noise(args),
        "noise_nT": checked_noise(args),
        "reference_total_nT": ds.ref_total_nT,
        "robust": args.robust,
        "field_gradient": bool(getattr(args, "field_gradient", False)),
    }
    return f"vector mode; reference: {vref.text}", options


def mode_options(args, mode, method="fit") -> tuple[str, dict]:
    """What ``magcal calibrate`` says of a fit of an installed mode and its options: those of ``--effects``,
    ``--robust`` and ``--noise`` that the mode's ``method`` takes (:meth:`magcal.modes.base.FitMode.accepts`)."""
    known = mode.accepts(method)
    given = {"effects": checked_effect_names(args), "robust": args.robust, "noise_nT": checked_noise(args)}
    options = {k: v for k, v in given.items() if known is None or k in known}
    left = [k for k, v in given.items() if v and k not in options]
    if left:
        raise MagcalError(
            f"--mode {mode.name}: the {mode.label} takes no "
            + ", ".join({"effects": "--effects", "robust": "--robust", "noise_nT": "--noise"}[k] for k in left)
        )
    return f"{mode.name} mode ({mode.title})", options


def run_fit(args, ds, mode, notes, header, options) -> int:
    """``magcal calibrate`` in a mode other than the total-field fit: the mode's fit, its held-out judgement and
    the report (:func:`magcal.cli.fit_report.report_fit`); a vector fit adds its compasses' consistency."""
    print(f"magcal calibrate: {header}", file=sys.stderr)
    try:
        result = mode.fit(ds, **options)
    except CalibrationError as exc:
        raise MagcalError(named_error(args.data, exc)) from None
    validation = None
    if getattr(args, "validate", True):
        try:
            validation = mode.validate(ds, result, **options)
        except (CalibrationError, MagcalError) as exc:
            notes.append(f"held-out validation not done: {exc}")
    sections = {}
    if mode is VECTOR:  # several compasses on one vehicle: the field the fit used is the one they are judged on
        compasses = compass_report(ds, result.reference, result, notes)
        if compasses is not None:
            sections["compass_consistency"] = compasses
    return report_fit(args, result, validation, notes, sections)


def compass_report(ds, vref=None, fit=None, notes=None, args=None):
    """The consistency of a record's compasses (:func:`magcal.diagnosis.compasses.compass_consistency`) for a record
    with two or more sensors, an attitude and a reference field vector (``vref``, else the one ``args`` give);
    None otherwise. ``fit`` is the vector fit whose calibration is "after" (default: the base vector fit, no
    platform terms, so that a current one compass sees is left for the report to name). A failure becomes a note
    (appended to ``notes``)."""
    if ds.n_sensors < 2 or attitude_source(ds) is None:
        return None
    try:
        if vref is None and args is not None:
            vref = vector_reference_from_args(args, ds)
        if vref is None:
            return None
        if fit is None:
            robust = bool(getattr(args, "robust", False))
            fit = fit_vector(ds, vref, terms=[], robust=robust, reference_total_nT=ds.ref_total_nT, warn=False)
        return compass_consistency(ds, fit.calibration, reference=vref, mask=fit.fitted)
    except (CalibrationError, MagcalError) as exc:
        if notes is not None:
            notes.append(f"compass consistency not reported: {exc}")
        return None


def run(args) -> int:

    if wants_compensation(args):  # its --effects are its own terms, not the catalogue's: before their check
        return run_compensation(args, read_input)
    if wants_cross_compensation(args):  # its --effects are its own terms too
        ds, notes = read_input(args)
        return run_cross_compensation(args, ds, notes)
    effect_names_before_mode(args)  # before reading: an unknown name fails fast
    checked_noise(args)
    _platform_terms(args)
    ds, notes = read_input(args)
    mode, vref = choose_mode(args, ds)
    if mode is CROSS_COMPENSATION:  # its --effects are checked against its own terms
        return run_cross_compensation(args, ds, notes)
    names = checked_effect_names(args)  # the chosen mode's catalogue
    if mode is not TOTAL_FIELD:
        if mode is VECTOR:
            header, options = vector_options(args, ds, vref)
        elif mode is GRAVITY:
            header, options = gravity_options(args, ds)
        else:
            header, options = mode_options(args, mode)
        return run_fit(args, ds, mode, notes, header, options)
    reference = reference_from_args(args, ds)
    notes += [note.text for note in reference.notes]
    ds = reference.apply(ds)
    if reference.kind == "fitted":
        ds = ds.replace(ref_total_nT=None)
    print(f"magcal calibrate: reference: {reference.text}", file=sys.stderr)
    quality = assess(ds)  # data quality, read before the fit
    coverage_notes = calibration_input_checks(ds)  # coverage
    if coverage_notes and attitude_source(ds) is not None:
        coverage_notes.append(
            "the total-field fit is undetermined along the directions this record lacks (a platform that turns in "
            "yaw and barely tilts sees a cone of field directions); with its attitude, the field vector "
            "(ref_n, ref_e, ref_d, --reference-vector or --reference igrf) and --mode vector, a vector calibration "
            "is determined (docs/vector.md)"
        )
    notes += coverage_notes
    bar, progress = _search_progress_bar(args.method, ds.n_sensors)
    try:
        result = TOTAL_FIELD.fit(ds, **calibrate_options(args), progress=progress)
    except CalibrationError as exc:
        raise MagcalError(named_error(args.data, exc)) from None
    finally:
        if bar is not None:
            bar.close()
    notes += [note.text for note in result.notes if note.text not in result.remarks]
    if names and args.method == "ml" and getattr(args, "validate", True):
        notes += _attach_validation(result, ds)
    quality.add(field_magnitude_finding(result.reference_total_nT, result.reference_kind))
    notes += quality.warnings
    # each warning once: the text report lists the calibration's own warnings and the data-quality warnings, so
    # leave those to it
    in_report = set(result.remarks) | set(quality.warnings)
    printed = set()
    for note in dict.fromkeys(notes):
        if args.json or note not in in_report:
            print(f"magcal calibrate: warning: {note}", file=sys.stderr)
            printed.add(note)
    if args.output:
        result.calibration.save(args.output)
    if args.json:
        doc = calibration_json(result)
        if getattr(result, "validation", None) is not None:
            doc["validation"] = result.validation.to_dict()
        # every warning of the run, not only the calibration's own: reading, reference, coverage, fit
        doc["warnings"] = list(dict.fromkeys(list(notes) + list(result.remarks)))
        doc["quality"] = quality.to_dict()
        doc["reference_source"] = reference.text  # where the reference came from, in words
        json.dump(doc, sys.stdout, indent=2)
        sys.stdout.write("\n")
        for note in result.remarks:
            if note not in printed:
                print(f"magcal calibrate: warning: {note}", file=sys.stderr)
    else:
        sys.stdout.write(text_report(result, source=args.data))
        sys.stdout.write(f"\nreference: {reference.text}\n")
        sys.stdout.write("\n" + quality.section())
        if args.output:
            print(f"\nsaved the calibration to {args.output}")
    return 0


def _attach_validation(result, ds) -> list:
    """Held-out RMS of the base model and of the model with the effects (:meth:`TOTAL_FIELD.validate
    <magcal.modes.total_field.TotalFieldMode.validate>`), set as ``result.validation`` for the report and the JSON;
    returns warnings (a record too short to split)."""

    try:
        result.validation = TOTAL_FIELD.validate(ds, result)
    except (CalibrationError, MagcalError) as exc:
        result.validation = None
        return [f"held-out validation not done: {exc}"]
    return list(result.validation.notes_for_user)


def _search_progress_bar(method, n_sensors):
    """A tqdm bar for the global-search methods (pso, ipso, de), on stderr and only when it is a terminal.

    Returns ``(bar, progress)``; both None otherwise. Each search iteration the pipeline reports (a message with
    no fraction) advances the bar by one; the total is the iteration limit per sensor, so a search that stops
    early on its tolerance leaves the bar short of the end.
    """

    if method not in SEARCH_METHODS or not sys.stderr.isatty():
        return None, None
    from tqdm import tqdm

    bar = tqdm(
        total=n_sensors * (DEFAULTS[method]["max_iter"] + 1),
        desc=f"magcal calibrate ({method})",
        unit="it",
        file=sys.stderr,
        leave=False,
    )

    def progress(message, fraction):
        if fraction is None:  # one search iteration: "<method>: iteration K, best RMS X nT"
            bar.set_postfix_str(message.rsplit(", ", 1)[-1], refresh=False)
            bar.update(1)

    return bar, progress
