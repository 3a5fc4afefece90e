"""The subcommands of ``magcal``, in the order ``magcal --help`` lists them, with their one-line help.

The table is all the command line reads to list them: ``magcal --help`` imports no subcommand, and ``magcal
COMMAND ...`` imports only ``magcal.cli.COMMAND`` (the command line starts in about the time of
``import magcal``). A new command is a module ``magcal/cli/NAME.py`` with ``register(subparsers)`` and ``run(args)``
and a line here; its parser takes its help from this table (``help=HELP["NAME"]``).

An installed package adds a command in the entry-point group ``magcal.commands``
(``[project.entry-points."magcal.commands"] NAME = "my_pkg.magcal_command"``, a module with the same
``register(subparsers)`` and ``run(args)``). ``magcal --help`` lists it after magcal's own with its distribution's
one-line summary, without importing it (:func:`installed_commands`); ``magcal NAME ...`` imports it then
(:func:`load_command`). Entry points are looked up only when the command line does not name one of magcal's own
commands, so ``magcal calibrate ...`` starts as before. A name that is magcal's own, or that the command line cannot
take, is skipped with a warning.
"""

from __future__ import annotations

import re

#: Subcommand name -> its one-line help (the module is ``magcal.cli.<name>``).
HELP = {
    "simulate": "write simulated readings with known errors (a preset of a paper) to a CSV file",
    "calibrate": "calibrate one to four sensors from readings taken while turning them in a uniform field",
    "diagnose": "find structure the model leaves in the residuals and the physical effect that explains it",
    "align": "level-table alignment: each sensor's rotation into the carrier platform's frame (patent S5-S8)",
    "apply": "correct a survey file with a calibration: corrected vectors, tensor and invariants",
    "effects": "list the effect catalogue: built-in terms and your own (--effects-file), with their parameters",
    "export": "write a calibration as ArduPilot or PX4 parameters, or a C header",
    "send": "write a calibration's compass parameters to a vehicle (MAVLink PARAM_SET) and read them back",
    "record": "record a live source (serial port, UDP/MAVLink, simulated) into a magcal CSV file",
}

#: The entry-point group installed packages declare their commands in.
ENTRY_POINT_GROUP = "magcal.commands"

#: What a command's name may look like.
NAME_PATTERN = re.compile(r"^[a-z][a-z0-9_-]{0,31}$")


def installed_commands(warnings=None) -> dict:
    """The commands installed packages declare (``name -> importlib.metadata.EntryPoint``), none of them imported.

    Parameters
    ----------
    warnings : list of str, optional
        Where an entry point skipped is said (a name of magcal's own, or one the command line cannot take).
    """
    import importlib.metadata

    try:
        found = importlib.metadata.entry_points(group=ENTRY_POINT_GROUP)
    except Exception:  # a broken installation must not stop magcal
        return {}
    commands = {}
    for ep in found:
        if ep.name in HELP or not NAME_PATTERN.match(ep.name) or ep.name in commands:
            if warnings is not None:
                warnings.append(
                    f"skipped the command entry point {ep.name} = {ep.value}: the name is taken or not a command name"
                )
            continue
        commands[ep.name] = ep
    return commands


def installed_help(ep) -> str:
    """The one-line help of an installed command: its distribution's summary (nothing is imported)."""
    dist = getattr(ep, "dist", None)
    name = getattr(dist, "name", None) or "an installed package"
    try:
        summary = (dist.metadata["Summary"] or "").strip() if dist is not None else ""
    except Exception:
        summary = ""
    return f"{summary} ({name})" if summary else f"a command of {name}"


def load_command(name: str, ep):
    """The module of the installed command ``name``, imported now; it must have ``register(subparsers)``.

    Raises
    ------
    ValueError
        When it cannot be imported or has no ``register``: the message names the entry point and why.
    """
    try:
        module = ep.load()
    except Exception as exc:
        raise ValueError(f"the command {name} ({ep.value}) cannot be imported: {type(exc).__name__}: {exc}") from None
    if not callable(getattr(module, "register", None)):
        raise ValueError(f"the command {name} ({ep.value}) has no register(subparsers) function")
    return module
