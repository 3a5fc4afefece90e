"""``magcal export``: a calibration as the parameters a flight controller loads (docs/export.md).

Example::

    magcal export cal.json --format ardupilot -o compass.param     # COMPASS_OFS*, COMPASS_DIA*, COMPASS_ODI*
    magcal export cal.json --format px4 -o mag.params --sensor 2   # CAL_MAG1_*, for QGroundControl
    magcal export cal.json --format c                              # a C header on standard output

A calibration holding more than the firmware can store (candidate effects, a rotation between sensors) is refused
with the list of what would be lost; ``--force`` exports without it and writes the list into the file.
"""

from __future__ import annotations

import sys

from magcal.core.errors import MagcalError
from magcal.data.io import atomic_write
from magcal.model.plugins import check_calibration_effects
from magcal.output.apply import load_calibration
from magcal.output.export import FORMATS, export_calibration


def register(subparsers):
    """Add the ``export`` subcommand."""

    parser = subparsers.add_parser(
        "export",
        help="write a calibration as ArduPilot or PX4 parameters, or a C header",
        description="Write a calibration as the parameters a flight controller loads: "
        + "; ".join(f"{k}: {v}" for k, v in FORMATS.items())
        + ". Conventions and formulas: docs/export.md.",
    )
    parser.add_argument("calibration", metavar="CAL.json", help="calibration file (magcal calibrate / align)")
    parser.add_argument("--format", required=True, choices=tuple(FORMATS), help="what to write")
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
    parser.set_defaults(func=run)
    return parser


def run(args) -> int:

    if args.slot and not args.sensor:
        raise MagcalError("--slot needs --sensor (one --slot per --sensor)")
    check_calibration_effects(args.calibration)
    calibration = load_calibration(args.calibration)
    result = export_calibration(
        calibration, args.format, sensors=args.sensor, slots=args.slot, force=args.force, source=args.calibration
    )
    for line in result.dropped:
        print(f"magcal export: warning: dropped {line}", file=sys.stderr)
    for line in result.notes:
        print(f"magcal export: note: {line}", file=sys.stderr)
    if args.output:
        with atomic_write(args.output) as fh:
            fh.write(result.text)
        print(
            f"magcal export: wrote {len(result.parameters)} value(s) for {len(result.sensors)} sensor(s) to "
            f"{args.output}",
            file=sys.stderr,
        )
    else:
        sys.stdout.write(result.text)
    return 0
