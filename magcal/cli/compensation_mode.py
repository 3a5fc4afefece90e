"""``magcal calibrate|diagnose --mode compensation``: a scalar magnetometer beside a fluxgate on a platform
(Tolles-Lawson and the terms beyond it, docs/compensation.md).

Example::

    magcal calibrate box.csv --mode compensation -o comp.json --figure fom.png   # scalar_nT beside x, y, z
    magcal calibrate box.csv --scalar mag_1_uc --columns x=flux_a_x,y=flux_a_y,z=flux_a_z
    magcal diagnose box.csv --mode compensation                  # candidates judged on held-out maneuvers
    magcal diagnose box.csv --mode compensation --also box2.csv  # ... or on a second flight
    magcal calibrate box.csv --mode compensation --effects current,time_offset -o comp.json
    magcal apply comp.json line.csv -o line_comp.csv             # + <scalar>_comp
    magcal export comp.json --format magnav-tl -o tl.json        # TL_coef in MagNav.jl's order

``--mode auto`` (the default) takes it when the record has a scalar magnetometer's column
(:data:`magcal.fitting.compensation.SCALAR_COLUMNS`, or ``--scalar NAME``) beside the fluxgate's x, y, z.
"""

from __future__ import annotations

import copy
import json
import sys

from magcal.cli.fit_report import report_fit
from magcal.core.errors import MagcalError
from magcal.core.jsonable import jsonable
from magcal.data.io import CsvSource, is_parquet, parse_column_mapping
from magcal.fitting.compensation import (
    COMPENSATION_EFFECTS,
    SCALAR_COLUMNS,
    CompensationResult,
    check_effects,
    compensation_record,
)
from magcal.model.tolles_lawson import DEFAULT_TERMS, check_terms
from magcal.modes.compensation import COMPENSATION
from magcal.output.compensation_figure import write_compensation_figure


def add_compensation_arguments(parser, figure: bool = True) -> None:
    """The options of the compensation mode (``--scalar``, ``--tl-terms``, ``--ridge``, ``--figure``)."""
    parser.add_argument(
        "--scalar",
        default=None,
        metavar="NAME",
        help="compensation mode: the scalar magnetometer's column (default the first of scalar_nT, scalar, "
        "mag_1_uc ... the file has); the fluxgate is x, y, z (map it with --columns)",
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
    names = _column_names(args.data, args.columns, args.units)
    scalar = getattr(args, "scalar", None)
    return (scalar in names) if scalar is not None else any(name in names for name in SCALAR_COLUMNS)


def _column_names(path, columns, units) -> list:
    """The columns a CSV or Parquet file holds by name ([] when it cannot be read: the reader says why later)."""
    try:
        if is_parquet(path):
            import pyarrow.parquet as pq

            return list(pq.read_schema(path).names)
        mapping = parse_column_mapping(columns) if isinstance(columns, str) else columns
        with CsvSource(path, columns=mapping, units=units) as src:
            return list(src.header)
    except (MagcalError, OSError, ValueError, ImportError):
        return []


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
    ds, notes = read_input(args)
    try:
        return compensation_record(ds, getattr(args, "scalar", None)), notes
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
        f"magcal calibrate: compensation mode; scalar {record.scalar_column!r} beside the fluxgate (x, y, z), "
        f"{record.sample_rate_hz:g} Hz; terms beyond TL: {', '.join(effects) or 'none'}",
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
