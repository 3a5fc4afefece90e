"""The ``magcal`` command line: one module per subcommand.

Each subcommand module defines ``register(subparsers)`` (adds its parser and sets ``func``). User errors are
raised as :class:`magcal.errors.MagcalError` (or :class:`magcal.dataset.DatasetError`) and printed as one clear
message with exit status 2, never as a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys

#: Subcommand modules, in the order ``magcal --help`` lists them.
SUBCOMMANDS = ("simulate", "calibrate", "diagnose", "align", "apply")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="magcal",
        description="Calibrate triaxial fluxgate magnetometers and the cross magnetic gradient tensor system.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in SUBCOMMANDS:
        try:
            module = importlib.import_module(f"magcal.cli.{name}")
        except ModuleNotFoundError as exc:  # a subcommand still being written
            if exc.name != f"magcal.cli.{name}":
                raise
            continue
        module.register(sub)
    return parser


def main(argv=None) -> int:
    from ..errors import MagcalError

    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 1
    try:
        return int(args.func(args) or 0)
    except MagcalError as exc:
        print(f"magcal {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"magcal {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # e.g. `magcal calibrate --json | head`: the reader left, nothing to report
        sys.stderr.close()
        return 0


if __name__ == "__main__":
    sys.exit(main())
