"""``magcal record``: record a live magnetometer source into a magcal CSV file.

Example::

    magcal record "sim://chi2017?rate=50" walk.csv --seconds 60
    magcal record "serial:///dev/ttyUSB0?baud=115200&columns=x,y,z&units=uT" board.csv --progress
    magcal record serial:///dev/ttyACM0 board.csv --template "Magnetometer reading: [{x}, {y}, {z}]" --units uT
    magcal record serial:///dev/ttyUSB0 imu.csv --columns t_ms,ax,ay,az,gx,gy,gz,mx,my,mz,roll,pitch,yaw

The file is flushed to disk at least every ``--flush`` seconds, so a recorder that is killed leaves every sample
up to its last flush (:class:`magcal.data.live.Recorder`). The line options (``--template``, ``--columns``,
``--units``, ``--prefix``, ``--no-checksum``), ``--reconnect`` and ``--attitude-max-dt`` override the URL's own
parameters of the same meaning (:func:`magcal.data.live.open_source`).
"""

from __future__ import annotations

import argparse
import math
import sys

from magcal.cli.commands import HELP
from magcal.core.errors import MagcalError
from magcal.data.live import LIVE_SOURCES, load_entry_points, open_source, record


def add_source_arguments(parser) -> None:
    """The options that say how to read a live source's lines, its reconnects and its MAVLink merge."""
    group = parser.add_argument_group("live source options (override the URL's parameters)")
    group.add_argument(
        "--template",
        default=None,
        help="text lines: the line written out with its fields in braces, e.g. 'x={x} y={y} z={z}' or "
        "'Magnetometer reading: [{x}, {y}, {z}]'; {t}, {temp}, {roll}, {pitch}, {yaw}, {gx}.., {_} to skip",
    )
    group.add_argument(
        "--columns",
        default=None,
        help="text lines: the fields of a line in order, e.g. x,y,z or t_ms,ax,ay,az,gx,gy,gz,mx,my,mz,roll,pitch,yaw",
    )
    group.add_argument("--units", default=None, help="text lines: nT (default), uT, G, mG or counts (with lsb=)")
    group.add_argument("--prefix", default=None, help="text lines: only lines starting with this are data")
    group.add_argument(
        "--no-checksum",
        action="store_true",
        help="text lines: strip a trailing *hh checksum without checking it",
    )
    group.add_argument(
        "--reconnect",
        type=float,
        default=None,
        metavar="S",
        help="serial (text lines or MAVLink) and MAVLink over TCP: longest total wait for a lost port or a closed "
        "connection to come back, s (default 30; 0: stop at once)",
    )
    group.add_argument(
        "--attitude-max-dt",
        type=float,
        default=None,
        metavar="S",
        help="MAVLink: largest time between a magnetometer sample and the ATTITUDE merged onto it, s (default 0.2)",
    )


def source_options(args) -> dict:
    """The keyword options of :func:`magcal.data.live.open_source` from :func:`add_source_arguments`'s options."""
    options = {
        "template": args.template,
        "columns": args.columns,
        "units": args.units,
        "prefix": args.prefix,
        "reconnect": args.reconnect,
        "attitude_max_dt": args.attitude_max_dt,
    }
    options = {k: v for k, v in options.items() if v is not None}
    if args.no_checksum:
        options["checksum"] = "off"
    return options


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``record`` subcommand; its description lists the registered live sources
    (:data:`magcal.data.live.LIVE_SOURCES`, installed packages' included)."""
    for note in load_entry_points().notes:
        print(f"magcal record: warning: {note.text}", file=sys.stderr)
    sources = "; ".join(f"{' or '.join(k.forms)}: {k.description}" for k in LIVE_SOURCES.values())
    parser = subparsers.add_parser(
        "record",
        help=HELP["record"],
        description="Record a live magnetometer source into a magcal CSV file (flushed to disk at least every "
        f"--flush seconds). Sources: {sources}.",
    )
    parser.add_argument(
        "url",
        help="the source, e.g. serial:///dev/ttyUSB0?baud=115200&columns=x,y,z, "
        "udp://127.0.0.1:14550?mavlink, sim://chi2017?rate=50",
    )
    parser.add_argument("output", help="the recording (a new file)")
    parser.add_argument("--seconds", type=float, default=None, help="stop after this long, whatever arrives")
    parser.add_argument("--samples", type=int, default=None, help="stop after this many samples")
    parser.add_argument("--flush", type=float, default=1.0, help="longest time between flushes to disk, s")
    parser.add_argument("--progress", action="store_true", help="print 'flushed N' after each flush")
    add_source_arguments(parser)
    parser.set_defaults(func=run)
    return parser


def run(args) -> int:
    def progress(n):
        print(f"flushed {n}", flush=True)

    for option, value in (("--seconds", args.seconds), ("--flush", args.flush)):  # nan would never end or flush
        if value is not None and not (math.isfinite(value) and value > 0):
            raise MagcalError(f"{option} must be a positive number of seconds, got {value}")
    if args.samples is not None and args.samples < 1:
        raise MagcalError(f"--samples must be at least 1, got {args.samples}")

    source = open_source(args.url, **source_options(args))
    try:
        stats = record(
            source, args.output, args.seconds, args.samples, args.flush, on_flush=progress if args.progress else None
        )
    finally:
        source.close()
    print(f"magcal record: {args.output}: {stats.summary()}", file=sys.stderr)
    return 0
