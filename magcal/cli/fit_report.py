"""What ``magcal calibrate`` prints of a fit in a mode other than the total-field fit (vector, gravity, an installed
package's: :mod:`magcal.modes`): one place for its warnings, the saved calibration and the report or JSON document."""

from __future__ import annotations

import json
import sys

from magcal.core.jsonable import jsonable


def report_fit(args, result, validation, notes, sections=None) -> int:
    """What ``magcal calibrate`` prints of a fit (a :class:`~magcal.fitting.result.ModeResult`): its notes as warnings, the calibration saved
    (``-o``), and the result's report or JSON document with its held-out ``validation`` and any ``sections`` (name
    -> an object with ``text()`` and ``to_dict()``)."""
    sections = sections or {}
    for note in dict.fromkeys(notes):
        print(f"magcal calibrate: warning: {note}", file=sys.stderr)
    if args.output:
        result.calibration.save(args.output)
    if args.json:
        doc = result.to_dict()
        doc["calibration"] = result.calibration.to_dict()
        if validation is not None:
            doc["validation"] = validation.to_dict()
        for name, section in sections.items():
            doc[name] = section.to_dict()
        doc["warnings"] = list(dict.fromkeys(list(notes) + list(result.warnings)))
        json.dump(jsonable(doc), sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        sys.stdout.write(result.text())
        if validation is not None:
            sys.stdout.write(validation.text())
        for section in sections.values():
            sys.stdout.write(section.text())
        if args.output:
            print(f"\nsaved the calibration to {args.output}")
    return 0
