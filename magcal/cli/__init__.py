"""The ``magcal`` command line: one module per subcommand.

Each subcommand module defines ``register(subparsers)`` (adds its parser and sets ``func``). User errors are
raised as :class:`magcal.core.errors.MagcalError` (or :class:`magcal.data.dataset.DatasetError`) and printed as one clear
message with exit status 2, never as a traceback.

Every subcommand takes ``--effects-file FILE.py`` (repeatable): a user's own effects (``docs/user-effects.md``),
loaded before the command runs -- the file is Python code executed with the user's rights, as its help says, so that ``--effects NAME``, the diagnosis, a calibration JSON naming the effect,
``apply`` and ``simulate --hidden NAME`` know them. Effects that installed packages declare in the entry-point
group ``magcal.effects`` are loaded once at start (:func:`magcal.model.plugins.load_entry_points`; a failing one is a
warning). An exception raised later inside a user's effect code is reported as its file, line and error.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from magcal.cli.commands import HELP, installed_commands, installed_help, load_command
from magcal.core.errors import MagcalError

#: The subcommands' names, in the order ``magcal --help`` lists them (their modules are ``magcal.cli.<name>``,
#: imported only when the command runs: :data:`magcal.cli.commands.HELP`).
SUBCOMMANDS = tuple(HELP)


def subcommand_module(name):
    """The module of subcommand ``name`` (``magcal.cli.<name>``), imported now."""
    return importlib.import_module(f"magcal.cli.{name}")


def add_effects_file_argument(parser) -> None:
    """``--effects-file FILE.py`` (repeatable): a user's effect file to load before the command runs."""
    parser.add_argument(
        "--effects-file",
        action="append",
        default=None,
        metavar="FILE.py",
        dest="effects_file",
        help="Python file defining your own effects (Effect subclasses decorated with @register; "
        "see docs/user-effects.md); repeatable. The file is Python code and RUNS with your rights "
        "(it can read, change or delete anything you can): give only a file you wrote or trust. Needed "
        "again wherever the effect is used: calibrate, diagnose, and apply or align with a calibration "
        "that includes it",
    )


def load_plugins(args, command="magcal") -> None:
    """Load the entry-point effects (once; failures printed as warnings) and the ``--effects-file`` files."""
    from magcal.model import plugins

    for note in plugins.load_entry_points(warn=False).notes:
        print(f"{command}: warning: {note.text}", file=sys.stderr)
    plugins.load_effects_files(getattr(args, "effects_file", None))


def build_parser(only=None) -> argparse.ArgumentParser:
    """The ``magcal`` parser: every subcommand's full parser, or (``only``: a name) that one's and a one-line
    entry for each other (what ``magcal --help`` lists), so that only the command that runs is imported."""
    parser = argparse.ArgumentParser(
        prog="magcal",
        description="Calibrate triaxial fluxgate magnetometers and the cross magnetic gradient tensor system.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in SUBCOMMANDS:
        if only is not None and name != only:
            sub.add_parser(name, help=HELP[name], add_help=False)
            continue
        sub_parser = subcommand_module(name).register(sub)
        if sub_parser is not None and not any(a.dest == "effects_file" for a in sub_parser._actions):
            add_effects_file_argument(sub_parser)
    if only in HELP:  # one of magcal's own runs: no installed command is looked up
        return parser
    warnings: list[str] = []
    for name, ep in installed_commands(warnings).items():  # magcal.commands entry points (magcal.cli.commands)
        if only is not None and name != only:
            sub.add_parser(name, help=installed_help(ep), add_help=False)
            continue
        try:
            sub_parser = load_command(name, ep).register(sub)
        except ValueError as exc:
            raise MagcalError(str(exc)) from None
        if sub_parser is not None and not any(a.dest == "effects_file" for a in sub_parser._actions):
            add_effects_file_argument(sub_parser)
    for text in warnings:
        print(f"magcal: warning: {text}", file=sys.stderr)
    return parser


def _command_in(argv) -> str:
    """The subcommand ``argv`` names (its first word that is not an option), or "" for none."""
    for word in argv:
        if not word.startswith("-"):
            return word
    return ""


def main(argv=None) -> int:

    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        parser = build_parser(only=_command_in(argv))
    except MagcalError as exc:  # an installed command that cannot be loaded
        print(f"magcal: error: {exc}", file=sys.stderr)
        return 2
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 1
    try:
        if getattr(args, "output", None) and args.command != "apply":  # apply checks its own (file or folder)
            from magcal.data.io import check_output_path

            check_output_path(args.output, "-o")  # before any work, not after a long fit
        load_plugins(args, f"magcal {args.command}")
        return int(args.func(args) or 0)
    except MagcalError as exc:
        print(f"magcal {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except Exception as exc:  # a bug in a user's effect code: its file and line, not a traceback into magcal
        from magcal.model.plugins import user_code_error

        message = user_code_error(exc)
        if message is None:
            raise
        print(f"magcal {args.command}: error: {message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"magcal {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # e.g. `magcal calibrate --json | head`: the reader left, nothing to report
        sys.stderr.close()
        return 0
