"""``magcal effects``: the effect catalogue -- built-in terms and the user's own -- with what each one needs.

Example::

    magcal effects                                   # every effect: stage, channels, parameters, source
    magcal effects temperature_bias                  # one effect in full (its docstring, parameter scales)
    magcal effects --effects-file my_effects.py      # check that a file loads, and see its effects listed
    magcal effects --json

For each effect: its name (as ``--effects NAME`` takes it), the stage it acts in (``raw``: the sensor's raw
reading; ``vector``: the corrected vector; ``reference``: the expected total field), the data channels it needs,
whether it has parameters per sensor or one set for the array, its parameters with their units, whether it
carries to new data (an instrument term) or describes one recording, whether the simulator can hide it, and where
it came from: ``built-in``, a ``file`` (``--effects-file``) or an ``entry point`` of an installed package.
"""

from __future__ import annotations

import argparse
import json
import sys
import textwrap

from magcal.cli.commands import HELP
from magcal.core.errors import MagcalError
from magcal.model.plugins import catalogue, describe_effect
from magcal.model.terms import EFFECTS, unknown_effect_message


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``effects`` subcommand."""
    parser = subparsers.add_parser(
        "effects",
        help=HELP["effects"],
        description="List the effects that calibrate --effects, diagnose and the workbench know: name, stage, "
        "channels, parameters and units, description and where each came from (built-in, a file "
        "given with --effects-file, or an installed package's entry point). See docs/effects.md and "
        "docs/user-effects.md.",
    )
    parser.add_argument("name", nargs="?", default=None, metavar="NAME", help="show one effect in full")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of the listing")
    parser.set_defaults(func=run)
    return parser


def _transfer_text(value) -> str:
    return {True: "instrument (carries to new data)", False: "record-only (this recording only)"}.get(
        value, "not stated"
    )


def _params_text(params) -> str:
    """``beta_x, beta_y, beta_z [nT/K]``: consecutive parameters of one unit share it."""
    groups: list = []
    for p in params:
        if groups and groups[-1][0] == p["unit"]:
            groups[-1][1].append(p["symbol"] if p["unit"] else p["name"])
        else:
            groups.append((p["unit"], [p["symbol"] if p["unit"] else p["name"]]))
    return "; ".join(", ".join(names) + (f" [{unit}]" if unit else "") for unit, names in groups) or "-"


def _entry_text(d, full=False) -> str:
    sensors = "per sensor" if d["per_sensor"] else "shared by the array"
    if d["min_sensors"] > 1:
        sensors += f", needs {d['min_sensors']}+ sensors"
    source = d["origin"] if d["origin"] == "built-in" else f"{d['origin']} {d['source']}"
    lines = [
        f"{d['name']}  ({source})",
        f"    {d['description'] or '(no description)'}",
        f"    stage {d['stage']}; channels: {', '.join(d['channels']) or '-'}; {sensors}",
        f"    parameters: {_params_text(d['params'])}",
        f"    carries to new data: {_transfer_text(d['transferable'])}; simulator: "
        f"{'yes (simulate --hidden ' + d['name'] + ')' if d['simulator'] else 'no'}",
    ]
    if d.get("error"):
        lines.append(f"    cannot be made: {d['error']}")
    if full:
        scales = ", ".join(f"{p['symbol']} {p['scale']:g}{(' ' + p['unit']) if p['unit'] else ''}" for p in d["params"])
        lines.append(f"    size moving the readings by ~1 nT: {scales or '-'}")
        if d["doc"]:
            lines.append("")
            lines += ["    " + para for para in d["doc"].splitlines()]
    wrapped = []
    for line in lines:
        wrapped += textwrap.wrap(line, 116, subsequent_indent="      ", break_on_hyphens=False) or [""]
    return "\n".join(wrapped)


def run(args) -> int:

    if args.name is not None:
        if args.name not in EFFECTS:
            raise MagcalError(unknown_effect_message(args.name))
        entries = [describe_effect(args.name)]
    else:
        entries = catalogue()
    if args.json:
        json.dump({"effects": entries}, sys.stdout, indent=2)
        sys.stdout.write("\n")
        return 0
    if args.name is not None:
        sys.stdout.write(_entry_text(entries[0], full=True) + "\n")
        return 0
    counts: dict = {}
    for d in entries:
        counts[d["origin"]] = counts.get(d["origin"], 0) + 1
    tally = ", ".join(f"{n} {kind}" for kind, n in counts.items())
    sys.stdout.write(
        f"magcal effects: {len(entries)} in the catalogue ({tally})\n"
        "use one with: magcal calibrate FILE --effects NAME[:SENSOR]; details: magcal effects NAME\n\n"
    )
    sys.stdout.write("\n\n".join(_entry_text(d) for d in entries) + "\n")
    return 0
