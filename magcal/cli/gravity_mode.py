"""``magcal calibrate --mode gravity``: a magnetometer beside an accelerometer (docs/gravity.md).

Example::

    magcal calibrate board.csv --mode gravity -o cal.json            # ax, ay, az columns beside x, y, z
    magcal calibrate board.csv --inclination 64.2                     # the field's inclination known (deg)
    magcal calibrate board.csv --reference igrf --lat 45.1 --lon 7.6 --date 2025-06-01   # ... from IGRF there
    magcal apply cal.json later.csv -o out.csv                         # + s1_heading_deg, s1_dip_deg, tilt_deg

``--mode auto`` (the default) takes it when the file has accelerometer columns and no full attitude
(:func:`magcal.cli.calibrate.choose_mode`). The options are added to ``magcal calibrate`` by
:func:`add_gravity_arguments`; :func:`run_gravity` is its gravity branch.
"""

from __future__ import annotations

import math
import sys

import numpy as np

from magcal.checks.reference import vector_reference_from_args
from magcal.cli.fit_report import report_fit
from magcal.core.errors import CalibrationError, MagcalError
from magcal.data.accelerometer import parse_accel_units
from magcal.fitting.gravity import fit_gravity, validate_gravity


def add_gravity_arguments(parser) -> None:
    """The options of the gravity mode (``--inclination``, ``--accel-units``, ``--accel-fit``)."""
    parser.add_argument(
        "--inclination",
        type=float,
        default=None,
        metavar="DEG",
        help="gravity mode: the field's inclination (deg, positive down); default from --reference igrf with "
        "--lat/--lon (or --reference-vector), else fitted from the dip",
    )
    parser.add_argument(
        "--accel-units",
        default=None,
        metavar="UNIT",
        help="gravity mode: unit of the ax, ay, az columns (g, mg or m/s^2); default the file's '# accel_units:' "
        "line, else what their magnitude says",
    )
    parser.add_argument(
        "--accel-fit",
        default="auto",
        choices=("auto", "full", "none"),
        help="gravity mode: fit the accelerometer's bias and scale too (full), take it as it reads (none: a "
        "firmware's calibration), or auto (default): fit it when its still samples span the attitudes",
    )


def gravity_reference(args, ds) -> tuple[float | None, str, float | None]:
    """``(inclination_deg, source, total_nT)`` from ``--inclination``, ``--reference``, ``--reference-vector`` or
    IGRF at a location; ``(None, "fitted", total)`` when only the dip can tell."""
    total = None
    ref = getattr(args, "reference", None)
    if ref is not None and str(ref).strip().lower() not in ("igrf", "column", "fit"):
        try:
            total = float(ref)
        except ValueError:
            raise MagcalError(f"--reference {ref!r}: a number of nT, igrf, column or fit") from None
    given = getattr(args, "inclination", None)
    if given is not None:
        if not (math.isfinite(given) and -90.0 < given < 90.0):
            raise MagcalError(f"--inclination must be an angle between -90 and 90 deg, got {given}")
        return float(given), "given", total
    vref = None
    if ref is not None or getattr(args, "reference_vector", None) is not None:
        vref = vector_reference_from_args(args, ds)
    if vref is None:
        return None, "fitted", total
    ned = np.nanmedian(np.asarray(vref.ned_nT, float), axis=0)
    inclination = float(np.degrees(np.arctan2(ned[2], np.hypot(ned[0], ned[1]))))
    return inclination, vref.text, total if total is not None else float(np.linalg.norm(ned))


def run_gravity(args, ds, notes) -> int:
    """``magcal calibrate`` in gravity mode (:func:`magcal.fitting.gravity.fit_gravity`)."""
    if getattr(args, "effects", None):
        raise MagcalError("--effects: the gravity fit takes no catalogue effects (yet); leave --effects out")
    units = getattr(args, "accel_units", None)
    if units is not None:
        parse_accel_units(units, "--accel-units")
    inclination, source, total = gravity_reference(args, ds)
    noise = getattr(args, "noise", None)
    if noise is not None and not (math.isfinite(noise) and noise > 0):
        raise MagcalError(f"--noise must be a positive noise per axis in nT, got {noise}")
    options = {
        "inclination_deg": inclination,
        "reference_total_nT": total,
        "noise_nT": noise,
        "accel_fit": getattr(args, "accel_fit", "auto"),
        "accel_units": units,
        "robust": bool(getattr(args, "robust", False)),
    }
    print(
        "magcal calibrate: gravity mode (magnetometer beside an accelerometer); inclination: "
        + (f"{inclination:.3f} deg ({source})" if inclination is not None else "fitted from the dip"),
        file=sys.stderr,
    )
    try:
        result = fit_gravity(ds, inclination_source=source, **options)
    except CalibrationError as exc:
        raise MagcalError(f"{args.data}: {exc}") from None
    result.calibration.fitted_on(ds)
    validation = None
    if getattr(args, "validate", True):
        try:
            validation = validate_gravity(ds, **options)
        except (CalibrationError, MagcalError) as exc:
            notes.append(f"held-out validation not done: {exc}")
    return report_fit(args, result, validation, notes)
