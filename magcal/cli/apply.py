"""``magcal apply``: correct a survey file with a calibration (patent S9-S10), streaming.

Example::

    magcal apply platform.json survey.csv -o survey_cal.csv
    magcal apply cal.json survey.csv -o out.csv --effects-file my_effects.py   # a calibration with your own effect
    magcal apply cal.json calib_record.csv -o out.csv --record-terms apply    # keep its bias drift on that record
    magcal apply cal.json flight.bin -o flight_cal.csv                       # a flight-controller log (.bin, .ulg)

A calibration with record-only terms (bias drift, bias step, reference drift, site gradient) applies them only to
the record it was fitted on; on any other file they are dropped, with one warning naming them.

Writes every input line plus ``s{i}x_cal, s{i}y_cal, s{i}z_cal`` (nT) and, for a four-sensor array, the tensor
``Gxx .. Gzz, Gyx`` (nT/m) and its invariants ``I0, I1, I2`` (see docs/formats.md).
"""

from __future__ import annotations

import sys
import warnings

from ..errors import MagcalError


def register(subparsers):
    """Add the ``apply`` subcommand."""
    parser = subparsers.add_parser(
        "apply",
        help="correct a survey file with a calibration: corrected vectors, tensor and invariants",
        description="Apply a calibration to a survey CSV, streaming (memory stays flat for any length), and write "
                    "the input columns plus the corrected ones.",
    )
    parser.add_argument("calibration", metavar="CAL.json", help="calibration file (magcal calibrate / align)")
    parser.add_argument("data", metavar="SURVEY.csv", help="survey data file (see docs/formats.md), or an ArduPilot "
                                                            ".bin / PX4 .ulg flight log")
    parser.add_argument("-o", "--output", required=True, metavar="OUT.csv", help="output file (written atomically)")
    parser.add_argument("--columns", default=None, metavar="MAP",
                        help="map your column names onto magcal's, e.g. x=magX,y=magY,z=magZ,t=time")
    parser.add_argument("--units", default=None, help="unit of the readings (nT, uT, G, mG); overrides the file")
    parser.add_argument("--drop-bad", action="store_true",
                        help="drop rows with missing or non-numeric values (with a warning) instead of refusing")
    parser.add_argument("--chunk-rows", type=int, default=20_000, metavar="N", help="rows per block (memory)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--record-terms", choices=("apply", "drop"), default=None,
                        help="the calibration's record-only terms (bias_drift, bias_step, reference_drift, "
                             "site_gradient...: they describe the recording it was fitted on, not the instrument). "
                             "Default: applied on that very recording, dropped with a warning on any other. "
                             "'apply' forces them (the same record, or you have a reference for it); 'drop' leaves "
                             "them out")
    parser.set_defaults(func=run)
    return parser


def run(args) -> int:
    from ..apply import apply_file, load_calibration
    from ..plugins import check_calibration_effects

    if args.chunk_rows < 1:
        raise MagcalError(f"--chunk-rows must be at least 1, got {args.chunk_rows}")
    check_calibration_effects(args.calibration)  # a user's effect in the file needs --effects-file
    calibration = load_calibration(args.calibration)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        summary = apply_file(calibration, args.data, args.output, columns=args.columns, units=args.units,
                             drop_bad=args.drop_bad, chunk_rows=args.chunk_rows,
                             progress=False if args.no_progress else None, calibration_name=args.calibration,
                             record_terms=args.record_terms)
    for note in dict.fromkeys(str(w.message) for w in caught):
        print(f"magcal apply: warning: {note}", file=sys.stderr)
    print(summary.text())
    return 0
