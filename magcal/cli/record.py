"""``magcal record``: record a live magnetometer source into a magcal CSV file.

Example::

    magcal record "sim://chi2017?rate=50" walk.csv --seconds 60
    magcal record "serial:///dev/ttyUSB0?baud=115200&columns=x,y,z&units=uT" board.csv --progress

The file is flushed to disk at least every ``--flush`` seconds, so a recorder that is killed leaves every sample
up to its last flush (:class:`magcal.data.live.Recorder`).
"""

from __future__ import annotations

import argparse
import sys

from magcal.data.live import record


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``record`` subcommand."""
    parser = subparsers.add_parser(
        "record",
        help="record a live source (serial port, UDP/MAVLink, simulated) into a magcal CSV file",
        description="Record a live magnetometer source into a magcal CSV file (flushed to disk at least every "
        "--flush seconds).",
    )
    parser.add_argument(
        "url",
        help="the source, e.g. serial:///dev/ttyUSB0?baud=115200&columns=x,y,z, "
        "udp://127.0.0.1:14550?mavlink, sim://chi2017?rate=50",
    )
    parser.add_argument("output", help="the recording (a new file)")
    parser.add_argument("--seconds", type=float, default=None, help="stop after this long")
    parser.add_argument("--samples", type=int, default=None, help="stop after this many samples")
    parser.add_argument("--flush", type=float, default=1.0, help="longest time between flushes to disk, s")
    parser.add_argument("--progress", action="store_true", help="print 'flushed N' after each flush")
    parser.set_defaults(func=run)
    return parser


def run(args) -> int:
    def progress(n):
        print(f"flushed {n}", flush=True)

    stats = record(
        args.url, args.output, args.seconds, args.samples, args.flush, on_flush=progress if args.progress else None
    )
    print(f"magcal record: {args.output}: {stats.summary()}", file=sys.stderr)
    return 0
