"""``magcal send``: write a calibration's compass parameters to a vehicle over MAVLink and read every one back.

Example::

    magcal send cal.json --format ardupilot --url udp://127.0.0.1:14550?mavlink      # asks before writing
    magcal send cal.json --format px4 --url serial:///dev/ttyACM0?baud=57600 --yes
    magcal send vehicle-backup-20260101-120000.parm --url udp://127.0.0.1:14550?mavlink   # restore the old values

The values are those ``magcal export --format FMT`` writes; before anything is written the vehicle's current values
are read, shown old -> new, and saved to a backup parameter file (``--backup``). Every value is read back after
writing; the command fails (exit 3) when one differs (:mod:`magcal.output.vehicle_params`).
"""

from __future__ import annotations

import argparse
import os
import sys

from magcal.cli.commands import HELP
from magcal.core.errors import MagcalError
from magcal.model.plugins import check_calibration_effects
from magcal.output.apply import load_calibration
from magcal.output.bundle import parameter_bytes
from magcal.output.vehicle_params import (
    ANSWER_TIMEOUT_S,
    FIRMWARE_PREFIXES,
    RETRIES,
    default_backup_path,
    firmware_of,
    read_parameter_text,
    send_parameters,
    values_to_send,
)

#: Exit status when a value was not read back equal.
EXIT_NOT_VERIFIED = 3


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``send`` subcommand."""
    parser = subparsers.add_parser(
        "send",
        help=HELP["send"],
        description="Write the compass parameters of a calibration (as magcal export writes them) or of a "
        "parameter file to a vehicle over MAVLink; the old values are read first, shown, and saved to a backup "
        "file; every value is read back. Conventions: docs/export.md.",
    )
    parser.add_argument(
        "source",
        metavar="CAL.json|PARAMS",
        help="a calibration file, or a parameter file (.parm, .params: e.g. a backup, to restore it)",
    )
    parser.add_argument(
        "--url",
        required=True,
        help="the vehicle: udp://127.0.0.1:14550?mavlink (listen), tcp://127.0.0.1:5760 (connect), "
        "serial:///dev/ttyACM0?baud=115200, or a pymavlink string (udpin:, udpout:, tcp:, DEVICE)",
    )
    parser.add_argument(
        "--format", choices=tuple(FIRMWARE_PREFIXES), default=None, help="the firmware (with a calibration file)"
    )
    parser.add_argument("--sensor", type=int, action="append", default=None, metavar="N", help="as magcal export")
    parser.add_argument("--slot", type=int, action="append", default=None, metavar="K", help="as magcal export")
    parser.add_argument("--force", action="store_true", help="as magcal export: write what the firmware can hold")
    parser.add_argument("--yes", action="store_true", help="write without asking")
    parser.add_argument(
        "--backup",
        default=None,
        metavar="FILE",
        help="where the vehicle's old values go (default vehicle-backup-DATE.parm beside the source file)",
    )
    parser.add_argument("--retries", type=int, default=RETRIES, help=f"tries per read and write (default {RETRIES})")
    parser.add_argument(
        "--timeout",
        type=float,
        default=ANSWER_TIMEOUT_S,
        metavar="S",
        help=f"wait for each answer, s (default {ANSWER_TIMEOUT_S:g})",
    )
    parser.set_defaults(func=run)
    return parser


def _values(args):
    """``(values, firmware)`` to send, from a calibration (as magcal export writes them) or a parameter file."""
    if args.source.lower().endswith(".json"):
        if args.format is None:
            raise MagcalError("--format ardupilot or --format px4: which firmware the vehicle runs")
        check_calibration_effects(args.source)
        calibration = load_calibration(args.source)
        content, result = parameter_bytes(
            calibration, args.format, sensors=args.sensor, slots=args.slot, force=args.force, source=args.source
        )
        for line in result.dropped:
            print(f"magcal send: warning: dropped {line}", file=sys.stderr)
        return values_to_send(content.decode("utf-8"), args.format), args.format
    if args.sensor or args.slot or args.force:
        raise MagcalError("--sensor, --slot and --force are for a calibration file; a parameter file is sent as is")
    try:
        with open(args.source, encoding="utf-8") as fh:
            text = fh.read()
    except FileNotFoundError:
        raise MagcalError(f"{args.source}: no such file; check the path") from None
    except UnicodeDecodeError:
        raise MagcalError(f"{args.source}: not a text parameter file") from None
    firmware = args.format or firmware_of(read_parameter_text(text))
    return values_to_send(text, firmware), firmware


def run(args) -> int:
    if args.retries < 1 or not 0 < args.timeout <= 60:
        raise MagcalError("--retries at least 1, --timeout in 0 ... 60 s")
    values, firmware = _values(args)
    backup = args.backup or default_backup_path(os.path.dirname(os.path.abspath(args.source)), firmware)

    def confirm(report):
        print(report.text())
        if args.yes:
            return True
        if not sys.stdin.isatty():
            raise MagcalError("not a terminal to ask on: pass --yes to write without asking")
        answer = input(f"write these {len(report.results)} parameter(s) to the vehicle? [y/N] ")
        return answer.strip().lower() in ("y", "yes")

    report = send_parameters(
        args.url,
        values,
        firmware,
        backup_path=backup,
        confirm=confirm,
        retries=args.retries,
        answer_timeout_s=args.timeout,
    )
    if report.declined:
        print("magcal send: nothing written", file=sys.stderr)
        return 1
    print(report.text())
    return 0 if report.ok else EXIT_NOT_VERIFIED
