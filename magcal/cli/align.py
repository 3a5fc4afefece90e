"""``magcal align``: level-table platform alignment (patent S5-S8) of every sensor into the platform frame.

Example::

    magcal align table.csv --cal intrinsic.json -o platform.json
    magcal align table.csv -o platform.json          # intrinsic calibration fitted to the same file

The file needs a ``group`` column labelling the samples ``x_up``, ``y_up``, ``z_up`` (the platform axis that was
vertical while the array was turned about the vertical); other labels are ignored by the alignment.
"""

from __future__ import annotations

import json
import sys

from magcal.checks.reference import add_reference_arguments, reference_from_args
from magcal.cli.calibrate import add_input_arguments, named_error, read_input
from magcal.cli.commands import HELP
from magcal.core.errors import CalibrationError, MagcalError
from magcal.fitting.platform import align
from magcal.model.plugins import check_calibration_effects
from magcal.output.apply import load_calibration


def register(subparsers):
    """Add the ``align`` subcommand."""

    parser = subparsers.add_parser(
        "align",
        help=HELP["align"],
        description="Estimate every sensor's rotation into the platform frame from level-table records (group "
        "column x_up, y_up, z_up), after the intrinsic calibration from --cal (or one fitted to the "
        "same file). Saves a calibration whose frame is 'platform'.",
    )
    add_input_arguments(parser)
    parser.add_argument(
        "--cal",
        default=None,
        metavar="CAL.json",
        help="intrinsic calibration (from magcal calibrate on a free-rotation record)",
    )
    add_reference_arguments(parser)
    parser.add_argument(
        "--noise",
        type=float,
        default=None,
        metavar="NT",
        help="per-axis noise sigma in nT for the uncertainties (default: the file's noise_nT, "
        "else estimated from the residuals)",
    )
    parser.add_argument("-o", "--output", default=None, metavar="CAL.json", help="save the aligned calibration here")
    parser.add_argument("--json", action="store_true", help="print the alignment figures as one JSON object")
    parser.set_defaults(func=run)
    return parser


def run(args) -> int:

    if args.noise is not None and not args.noise > 0:
        raise MagcalError(f"--noise must be a positive number of nT, got {args.noise}")
    ds, notes = read_input(args)
    calibration = None
    ref_value, ref_text = None, None
    if args.cal:
        check_calibration_effects(args.cal)  # a user's effect in the file needs --effects-file
        calibration = load_calibration(args.cal, n_sensors=ds.n_sensors)
    else:
        ref = reference_from_args(args, ds)
        notes += [note.text for note in ref.notes]
        ref_text = ref.text
        ds = ref.apply(ds)
        ref_value = ref.value_nT if ref.known and not hasattr(ref.value_nT, "__len__") else None
    try:
        new, result = align(ds, calibration, noise_nT=args.noise, reference_total_nT=ref_value, source=args.data)
    except CalibrationError as exc:
        raise MagcalError(named_error(args.data, exc)) from None
    notes += [note.text for note in result.notes]
    for note in dict.fromkeys(notes):
        print(f"magcal align: warning: {note}", file=sys.stderr)
    if args.output:
        new.save(args.output)
    if args.json:
        json.dump(result.to_dict(), sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        if ref_text:
            print(f"reference: {ref_text}")
        print(result.text())
        if args.output:
            print(f"\nsaved the platform-frame calibration to {args.output}")
        else:
            print("\n(not saved: give -o CAL.json to save the aligned calibration)")
    return 0
