"""The subcommands of ``magcal``, in the order ``magcal --help`` lists them, with their one-line help.

The table is all the command line reads to list them: ``magcal --help`` imports no subcommand, and ``magcal
COMMAND ...`` imports only ``magcal.cli.COMMAND`` (issue 43: the command line starts in about the time of
``import magcal``). A new command is a module ``magcal/cli/NAME.py`` with ``register(subparsers)`` and ``run(args)``
and a line here; its parser takes its help from this table (``help=HELP["NAME"]``).
"""

from __future__ import annotations

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
