"""``magcal calibrate|diagnose --mode compensation``: a scalar magnetometer beside a fluxgate on a platform
(Tolles-Lawson and the terms beyond it, docs/compensation.md).

Example::

    magcal calibrate box.csv --mode compensation -o comp.json --figure fom.png   # scalar_nT beside x, y, z
    magcal calibrate Flt1002.csv                                 # MagNav.jl's names: mag_1_uc, flux_a_*, tt
    magcal calibrate Flt1002.csv --scalar mag_4_uc --fluxgate flux_d --current cur_strb
    magcal calibrate Flt1002.csv --effects current --current cur_strb,cur_com_1   # two wires, a field each
    magcal diagnose box.csv --mode compensation                  # candidates judged on held-out maneuvers
    magcal diagnose box.csv --mode compensation --also box2.csv  # ... or on a second flight
    magcal calibrate box.csv --mode compensation --effects current,time_offset -o comp.json
    magcal apply comp.json line.csv -o line_comp.csv             # + <scalar>_comp
    magcal export comp.json --format magnav-tl -o tl.json        # TL_coef in MagNav.jl's order
    magcal calibrate cross_box.csv --mode cross_compensation --reference igrf -o cross.json  # the four-sensor cross
    magcal diagnose cross_box.csv --mode cross_compensation      # the current the per-sensor TL misses
    magcal apply cross.json cross_line.csv -o cross_line_comp.csv    # + s1x_comp ..., Gxx ... of the compensated

``--mode auto`` (the default) takes it when the record has a scalar magnetometer's column
(:data:`magcal.fitting.compensation.SCALAR_COLUMNS`, or ``--scalar NAME``) beside the fluxgate's x, y, z. The
fluxgate, the time, the attitude and a current are found by name too, MagNav.jl's included
(:mod:`magcal.data.flight_columns`).
"""

from __future__ import annotations

import copy
import json
import sys

from magcal.checks.reference import vector_reference_from_args
from magcal.cli.fit_report import report_fit
from magcal.core.errors import MagcalError
from magcal.core.jsonable import jsonable
from magcal.data.flight_columns import flight_mapping, header_names
from magcal.data.io import parse_column_mapping
from magcal.diagnosis.cross_compensation import (
    LAG_FLAGS,
    LAG_NEEDS_FIELD,
    CrossCompensationResult,
    check_cross_effects,
    cross_record,
)
from magcal.fitting.compensation import (
    COMPENSATION_EFFECTS,
    SCALAR_COLUMNS,
    CompensationResult,
    check_effects,
    compensation_record,
)
from magcal.model.tolles_lawson import DEFAULT_TERMS, check_terms
from magcal.modes.compensation import COMPENSATION
from magcal.modes.cross_compensation import CROSS_COMPENSATION, field_vector
from magcal.output.compensation_figure import write_compensation_figure


def add_compensation_arguments(parser, figure: bool = True) -> None:
    """The options of the compensation mode (``--scalar``, ``--tl-terms``, ``--ridge``, ``--figure``)."""
    parser.add_argument(
        "--scalar",
        default=None,
        metavar="NAME",
        help="compensation mode: the scalar magnetometer's column (default the first of scalar_nT, scalar, "
        "mag_1_uc ... the file has)",
    )
    parser.add_argument(
        "--fluxgate",
        default=None,
        metavar="NAME",
        help="compensation mode: the fluxgate, by its columns' prefix (flux_b for flux_b_x, flux_b_y, flux_b_z); "
        "default x, y, z, else the first fluxgate the file names (flux_a_x ..., flux_x ..., fluxgate_x ...)",
    )
    parser.add_argument(
        "--current",
        default=None,
        metavar="NAME",
        help="compensation modes: the current term's column, or several comma-separated (cur_strb,cur_com_1: each "
        "its own field per ampere); default current_A, throttle, else MagNav.jl's cur_outpwr, cur_strb, cur_com_1 "
        "... the first the file has (magcal diagnose judges each current column the file has)",
    )
    parser.add_argument(
        "--tl-terms",
        default=",".join(DEFAULT_TERMS),
        metavar="LIST",
        help="compensation mode: Tolles-Lawson's term groups (default permanent,induced,eddy: 18 terms; "
        "induced5, eddy8 drop the two a constant |B| leaves undetermined)",
    )
    parser.add_argument(
        "--ridge",
        type=float,
        default=0.0,
        metavar="LAMBDA",
        help="compensation mode: ridge on the band-passed normal matrix (MagNav.jl's lambda; default 0)",
    )
    if figure:
        parser.add_argument(
            "--figure",
            default=None,
            metavar="PNG",
            help="compensation mode: draw the band-passed scalar before and after and the FOM per maneuver here",
        )


def wants_compensation(args) -> bool:
    """Whether ``--mode`` (``compensation``, or ``auto`` with a scalar magnetometer's column in the file) asks for
    the compensation mode; the file's head is read for ``auto``."""
    mode = getattr(args, "mode", "auto") or "auto"
    if mode == "compensation":
        return True
    if mode != "auto":
        return False
    names = header_names(args.data)
    scalar = getattr(args, "scalar", None)
    return (scalar in names) if scalar is not None else any(name in names for name in SCALAR_COLUMNS)


def compensation_options(args) -> dict:
    """The fit's keyword arguments from ``--tl-terms`` and ``--ridge`` (checked)."""
    terms = check_terms([t.strip() for t in str(args.tl_terms).split(",") if t.strip()])
    ridge = float(args.ridge)
    if not ridge >= 0:
        raise MagcalError(f"--ridge must be a number >= 0, got {args.ridge}")
    return {"terms": terms, "ridge": ridge}


def compensation_effects(args) -> tuple:
    """``--effects`` as compensation terms (:data:`magcal.fitting.compensation.COMPENSATION_EFFECTS`)."""
    names = [n.strip() for item in (getattr(args, "effects", None) or []) for n in str(item).split(",") if n.strip()]
    return check_effects(names)


def _record(args, read_input, path=None):
    if path is not None:
        args = _with_data(args, path)
    given = parse_column_mapping(args.columns) if isinstance(args.columns, str) else dict(args.columns or {})
    try:
        mapping = flight_mapping(header_names(args.data), given, getattr(args, "fluxgate", None))
    except MagcalError as exc:
        raise MagcalError(f"{args.data}: {exc}") from None
    found = tuple(mapping[k] for k in ("s1x", "s1y", "s1z")) if "s1x" in mapping and "s1x" not in given else None
    args = copy.copy(args)
    args.columns = mapping or None
    ds, notes = read_input(args)
    try:
        return compensation_record(ds, getattr(args, "scalar", None), getattr(args, "current", None), found), notes
    except MagcalError as exc:
        text = str(exc)
        raise MagcalError(text if text.startswith(f"{args.data}") else f"{args.data}: {text}") from None


def _with_data(args, path):
    other = copy.copy(args)
    other.data = path
    return other


def run_compensation(args, read_input) -> int:
    """``magcal calibrate`` in compensation mode."""
    effects = compensation_effects(args)
    options = compensation_options(args)
    record, notes = _record(args, read_input)
    print(
        f"magcal calibrate: compensation mode; scalar {record.scalar_column!r} beside the fluxgate "
        f"({', '.join(record.fluxgate_columns or ('x', 'y', 'z'))}), {record.sample_rate_hz:g} Hz"
        + (f", current {', '.join(map(repr, record.term_currents))}" if record.current_column else "")
        + f"; terms beyond TL: {', '.join(effects) or 'none'}",
        file=sys.stderr,
    )
    result = COMPENSATION.fit(record, effects=effects, **options)
    if isinstance(result, CompensationResult):
        result.source = args.data
    notes += [note.text for note in result.notes]
    result.notes.clear()  # printed with the run's own notes above
    validation = None
    if effects and getattr(args, "validate", True):
        validation = COMPENSATION.validate(record, result, effects=effects, **options)
    if getattr(args, "figure", None):
        write_compensation_figure(result, args.figure)
        print(f"magcal calibrate: drew the compensation to {args.figure}", file=sys.stderr)
    return report_fit(args, result, validation, notes)


def run_compensation_diagnosis(args, read_input) -> int:
    """``magcal diagnose`` in compensation mode (``--also``: other flights judge the candidates)."""
    effects = compensation_effects(args)
    options = compensation_options(args)
    record, notes = _record(args, read_input)
    also = None
    others = list(getattr(args, "also", None) or [])
    if len(others) > 1:
        raise MagcalError("--also: the compensation diagnosis judges on one other flight; give one")
    if others:
        also, more = _record(args, read_input, others[0])
        notes += more
    diagnosis = COMPENSATION.diagnose(record, effects=effects, also=also, **options)
    for note in dict.fromkeys(notes + [n.text for n in diagnosis.notes]):
        print(f"magcal diagnose: warning: {note}", file=sys.stderr)
    if getattr(args, "json", False):
        json.dump(jsonable(diagnosis.to_dict()), sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        sys.stdout.write(diagnosis.text())
    return 0


#: The terms ``--effects`` takes in compensation mode, for the help texts.
EFFECT_NAMES = tuple(COMPENSATION_EFFECTS)


def wants_cross_compensation(args) -> bool:
    """Whether ``--mode cross_compensation`` was given (``auto`` reaches it after reading the record:
    :func:`magcal.modes.base.mode_choice`)."""
    return (getattr(args, "mode", "auto") or "auto") == CROSS_COMPENSATION.name


def cross_effects(args) -> tuple:
    """``--effects`` as the cross compensation's terms (:data:`magcal.diagnosis.cross_compensation.CROSS_EFFECTS`)."""
    names = [n.strip() for item in (getattr(args, "effects", None) or []) for n in str(item).split(",") if n.strip()]
    return check_cross_effects(names)


def _cross_setup(args, ds):
    """The record and the field vector of a cross compensation flight: ``--reference igrf``, ``--reference-vector``
    or the ``ref_n, ref_e, ref_d`` columns (None: the four's mean field)."""
    reason = CROSS_COMPENSATION.applicable(ds)
    if reason is not None:
        raise MagcalError(f"{args.data}: --mode {CROSS_COMPENSATION.name} {reason}")
    try:
        record = cross_record(ds, getattr(args, "current", None))
        vref = vector_reference_from_args(args, ds) if record.attitude_deg is not None else None
    except MagcalError as exc:
        text = str(exc)
        raise MagcalError(text if text.startswith(f"{args.data}") else f"{args.data}: {text}") from None
    record.source = args.data
    return record, vref


def _reference_words(vref, ned) -> str:
    return "the four sensors' mean field" if ned is None else f"the attitude's Earth field ({vref.text})"


def run_cross_compensation(args, ds, notes) -> int:
    """``magcal calibrate`` in cross compensation mode: the fit, its tensor FOM report, ``-o`` the JSON document."""
    effects = cross_effects(args)
    record, vref = _cross_setup(args, ds)
    ned = field_vector(vref, record.n_samples)
    print(
        f"magcal calibrate: cross compensation mode; four sensors, {record.sample_rate_hz:g} Hz, baseline "
        f"{record.baseline_m:g} m, against {_reference_words(vref, ned)}"
        + (
            f", current {', '.join(map(repr, record.term_currents))}"
            if record.current_column and "current" in effects
            else ""
        )
        + f"; terms beyond TL: {', '.join(effects) or 'none'}",
        file=sys.stderr,
    )
    ridge = float(getattr(args, "ridge", 0.0) or 0.0)
    result = CROSS_COMPENSATION.fit(record, reference=ned, effects=effects, ridge=ridge)
    if isinstance(result, CrossCompensationResult):
        result.source = args.data
    notes = list(notes) + [note.text for note in result.notes]
    result.notes.clear()  # printed with the run's own notes
    validation = None
    if effects and getattr(args, "validate", True):
        validation = CROSS_COMPENSATION.validate(record, result, reference=ned, effects=effects)
    return report_fit(args, result, validation, notes)


def run_cross_compensation_diagnosis(args, ds, notes, read_input) -> int:
    """``magcal diagnose`` in cross compensation mode (``--also``: another flight judges the candidates)."""
    effects = cross_effects(args)
    record, vref = _cross_setup(args, ds)
    others = list(getattr(args, "also", None) or [])
    if len(others) > 1:
        raise MagcalError("--also: the cross compensation's diagnosis judges on one other flight; give one")
    also = None
    if others:
        other_ds, more = read_input(_with_data(args, others[0]))
        notes = list(notes) + list(more)
        also, _ = _cross_setup(_with_data(args, others[0]), other_ds)
    ned = field_vector(vref, record.n_samples)
    diagnosis = CROSS_COMPENSATION.diagnose(record, reference=ned, effects=effects, also=also)
    for candidate in diagnosis.candidates:  # the engine says what the data lack; the command line, its options
        if candidate.reason == LAG_NEEDS_FIELD:
            candidate.reason = f"{LAG_NEEDS_FIELD}; {LAG_FLAGS}"
    for note in dict.fromkeys(list(notes) + [n.text for n in diagnosis.notes]):
        print(f"magcal diagnose: warning: {note}", file=sys.stderr)
    if getattr(args, "json", False):
        json.dump(jsonable(diagnosis.to_dict()), sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        sys.stdout.write(diagnosis.text())
    return 0
