"""``magcal export``: a calibration as the parameters a flight controller loads (docs/export.md).

Example::

    magcal export cal.json --format ardupilot -o compass.param     # COMPASS_OFS*, COMPASS_DIA*, COMPASS_ODI*
    magcal export cal.json --format px4 -o mag.params --sensor 2   # CAL_MAG1_*, for QGroundControl
    magcal export cal.json --format c                              # a C header on standard output
    magcal export cal.json --format mask --data rec.csv -o raw_mask.csv   # raw readings, kept mask, residuals
    magcal export cal.json --format all --data rec.csv -o magcal_export.zip   # every file and a README.txt

A calibration holding more than the firmware can store (candidate effects, a rotation between sensors) is refused
with the list of what would be lost; ``--force`` exports without it and writes the list into the file. The field of
the platform's current is written as the firmwares' motor compensation (``COMPASS_MOT*``, ``CAL_MAGn_xCOMP``), a
vector calibration's mounting off the right angles as ArduPilot's custom rotation (docs/export.md).

The files are built by :mod:`magcal.output.bundle`, the functions the workbench's Export section calls: the same
calibration gives the same bytes from either.
"""

from __future__ import annotations

import sys

from magcal.cli.calibrate import add_max_rows_argument, checked_max_rows
from magcal.cli.commands import HELP
from magcal.core.errors import MagcalError
from magcal.data.io import atomic_write, read_csv
from magcal.fitting.compensation import Compensation
from magcal.model.plugins import check_calibration_effects
from magcal.output.apply import load_calibration
from magcal.output.bundle import export_all, mask_from_file, parameter_bytes, raw_mask_bytes
from magcal.output.compensated_line import is_compensation_file
from magcal.output.formats import EXPORT_FORMATS, load_entry_points
from magcal.output.magnav_tl import COMPENSATION_FORMATS, magnav_tl_text

#: Formats that need the data (--data): the raw readings with the fit's mask, and every file in a zip.
DATA_FORMATS = {
    "mask": "the raw readings with a kept column (the fit's mask, --mask) and the total-field residuals, as CSV",
    "all": "a zip of every file (calibration, each firmware's parameters it allows, the corrected data, raw + "
    "mask) with a README.txt saying what was not written and why",
}


def register(subparsers):
    """Add the ``export`` subcommand: its ``--format`` choices are the registered formats
    (:data:`magcal.output.formats.EXPORT_FORMATS`, installed packages' included) and :data:`DATA_FORMATS`."""
    for note in load_entry_points().notes:
        print(f"magcal export: warning: {note.text}", file=sys.stderr)
    formats = {name: spec.description for name, spec in EXPORT_FORMATS.items()}
    parser = subparsers.add_parser(
        "export",
        help=HELP["export"],
        description="Write a calibration as the parameters a flight controller loads: "
        + "; ".join(f"{k}: {v}" for k, v in {**formats, **DATA_FORMATS}.items())
        + ". Conventions and formulas: docs/export.md.",
    )
    parser.add_argument("calibration", metavar="CAL.json", help="calibration file (magcal calibrate / align)")
    parser.add_argument(
        "--format",
        required=True,
        choices=tuple(formats) + tuple(DATA_FORMATS) + tuple(COMPENSATION_FORMATS),
        help="what to write (magnav-tl: a compensation's TL-18 vector in MagNav.jl's term order, docs/compensation.md)",
    )
    parser.add_argument(
        "-o", "--output", default=None, metavar="FILE", help="output file (written atomically); default standard output"
    )
    parser.add_argument(
        "--sensor",
        type=int,
        action="append",
        default=None,
        metavar="N",
        help="export only magcal sensor N (1-based); repeatable. Default: every sensor, sensor i "
        "going to ArduPilot compass i / PX4 CAL_MAG(i-1)",
    )
    parser.add_argument(
        "--slot",
        type=int,
        action="append",
        default=None,
        metavar="K",
        help="the firmware's compass number for each --sensor (ArduPilot 1-3, PX4 0-3)",
    )
    parser.add_argument(
        "--force",
        action="store_true",
        help="export even if effects or rotations between sensors must be dropped (listed in the "
        "file and on standard error)",
    )
    parser.add_argument(
        "--throttle-full-scale",
        type=float,
        default=None,
        metavar="X",
        help="what the calibration's throttle column reads at full throttle (default 1: 0-1, as ArduPilot's "
        "CTUN.ThO; 100 for percent): the firmwares' motor compensation is per full throttle",
    )
    parser.add_argument(
        "--no-custom-rotation",
        action="store_true",
        help="ArduPilot: write a mounting off the right angles as its nearest right angle (and refuse the rest) "
        "instead of a custom rotation (COMPASS_ORIENT 101/102, CUST_ROT*; ArduPilot 4.2 and later)",
    )
    parser.add_argument(
        "--data",
        default=None,
        metavar="DATA.csv",
        help="the data (formats mask and all): the record the calibration was fitted on, or any other",
    )
    parser.add_argument(
        "--mask",
        default=None,
        metavar="FILE.csv",
        help="format mask/all: a CSV with a kept column (1 kept, 0 rejected), one row per sample, e.g. the "
        "workbench's raw_mask.csv; default every sample kept",
    )
    add_max_rows_argument(parser)
    parser.set_defaults(func=run)
    return parser


def run(args) -> int:

    if args.slot and not args.sensor:
        raise MagcalError("--slot needs --sensor (one --slot per --sensor)")
    if is_compensation_file(args.calibration) or args.format in COMPENSATION_FORMATS:
        return _run_compensation(args)
    check_calibration_effects(args.calibration)
    calibration = load_calibration(args.calibration)
    if args.format in DATA_FORMATS:
        return _run_data(args, calibration)
    if args.data or args.mask:
        raise MagcalError(f"--data and --mask are for --format {' or '.join(DATA_FORMATS)}, not {args.format}")
    content, result = parameter_bytes(
        calibration,
        args.format,
        sensors=args.sensor,
        slots=args.slot,
        force=args.force,
        source=args.calibration,
        throttle_full_scale=args.throttle_full_scale,
        custom_rotation=not args.no_custom_rotation,
    )
    for line in result.dropped:
        print(f"magcal export: warning: dropped {line}", file=sys.stderr)
    for line in result.notes:
        print(f"magcal export: note: {line}", file=sys.stderr)
    if args.output:
        with atomic_write(args.output, "wb") as fh:
            fh.write(content)
        print(
            f"magcal export: wrote {len(result.parameters)} value(s) for {len(result.sensors)} sensor(s) to "
            f"{args.output}",
            file=sys.stderr,
        )
    else:
        sys.stdout.write(result.text)
    return 0


def _run_data(args, calibration) -> int:
    """``--format mask`` and ``--format all``: files built from the calibration and the data."""
    if args.sensor or args.slot or args.force or args.throttle_full_scale is not None or args.no_custom_rotation:
        raise MagcalError(
            f"--format {args.format}: --sensor, --slot, --force, --throttle-full-scale and --no-custom-rotation are "
            "for the firmware formats"
        )
    if not args.data:
        raise MagcalError(f"--format {args.format} needs the data: --data DATA.csv")
    if not args.output:
        raise MagcalError(f"--format {args.format} writes a file: give -o FILE")
    dataset = read_csv(args.data, max_rows=checked_max_rows(args))
    kept = mask_from_file(args.mask, dataset.n_samples) if args.mask else None
    if args.format == "mask":
        content, notes = raw_mask_bytes(calibration, dataset, kept, calibration_name=args.calibration)
        said = [f"wrote {dataset.n_samples} sample(s), {int(dataset.n_samples if kept is None else kept.sum())} kept"]
    else:
        content, readme = export_all(
            calibration, dataset=dataset, data_path=args.data, kept=kept, calibration_name=args.calibration
        )
        notes = [line.strip() for line in readme if "not written" in line]
        said = ["wrote the zip (its README.txt lists the files)"]
    for line in notes:
        print(f"magcal export: note: {line}", file=sys.stderr)
    with atomic_write(args.output, "wb") as fh:
        fh.write(content)
    print(f"magcal export: {said[0]} to {args.output}", file=sys.stderr)
    return 0


def _run_compensation(args) -> int:
    """``--format magnav-tl`` of a compensation file."""
    if args.format not in COMPENSATION_FORMATS:
        raise MagcalError(
            f"{args.calibration} is a compensation: export it with --format {' or '.join(COMPENSATION_FORMATS)}"
        )
    if not is_compensation_file(args.calibration):
        raise MagcalError(
            f"--format {args.format} writes a compensation (magcal calibrate --mode compensation -o comp.json); "
            f"{args.calibration} is not one"
        )
    text = magnav_tl_text(Compensation.load(args.calibration), force=args.force)
    if args.output:
        with atomic_write(args.output) as fh:
            fh.write(text)
        print(f"magcal export: wrote MagNav.jl's TL_coef (18 values) to {args.output}", file=sys.stderr)
    else:
        sys.stdout.write(text)
    return 0
