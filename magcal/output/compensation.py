"""What a flight controller holds beyond offsets and a matrix: the field of the platform's current (motor
compensation) and, in ArduPilot, a mounting at any angle (a custom rotation). ``docs/export.md`` gives the sources.

Motor compensation
    magcal's current term adds ``k u`` to a sensor's raw reading, in the sensor's own axes (``k`` in nT per unit of
    the ``current_A`` or ``throttle`` column): ``B = R C^-1 (y - b - k u)``. It lives in a calibration's
    ``platform`` (:class:`magcal.model.platform_terms.PlatformTerms`) or, as the catalogue effect
    ``current_field``, in its model and ``effect_values``; :func:`current_compensation` reads both.

    ArduPilot (``AP_Compass_Backend::correct_field``) adds ``COMPASS_MOT * u`` *after* its matrix, in the body frame,
    in milligauss per ampere of the battery monitor's current (``COMPASS_MOTCT`` 2) or per full throttle
    (``COMPASS_MOTCT`` 1, the throttle 0 to 1): with the matrix ``M`` and the rotation ``A`` the raw reading is
    turned by first, ``COMPASS_MOT = -M A k / 100``.

    PX4 (``calibration::Magnetometer::Correct``) adds ``power * CAL_MAGn_[XYZ]COMP`` to the raw reading *before*
    its offsets, in the sensor's axes, ``power`` the battery current in kA (``CAL_MAG_COMP_TYP`` 2, battery_status
    instance 0) or the throttle 0 to 1 (``CAL_MAG_COMP_TYP`` 1): ``CAL_MAGn_[XYZ]COMP = -k / 10^5`` gauss per
    firmware unit.

    Each firmware has one compensation type for all its compasses; :func:`current_export` refuses sensors whose
    terms follow different columns.

ArduPilot's custom rotation
    ``COMPASS_ORIENT`` 101 or 102 (``ROTATION_CUSTOM_1``, ``_2``) turns an external compass's raw reading by
    ``from_euler(CUST_ROTn_ROLL, _PITCH, _YAW)`` (degrees, ``Rz(yaw) Ry(pitch) Rx(roll)``,
    ``AP_CustomRotations``), enabled by ``CUST_ROT_ENABLE``. With it the whole ``W = R C^-1`` is held: ``W = U S``
    (``U`` a rotation, ``S`` symmetric), the rotation ``U`` and the body-frame matrix ``U S U^T``.
    :func:`custom_rotation_number` gives compass 1 the first and compass 2 the second, so that files exported
    one compass at a time never share one.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from magcal.calibration.calibration import current_term
from magcal.core.errors import MagcalError
from magcal.geometry.orientations import euler_matrix

#: The catalogue effect of a field per unit of a current or throttle column.
CURRENT_EFFECT = "current_field"

#: The parameter that says what each firmware's motor compensation follows, and its value per magcal column.
COMPENSATION_TYPE = {
    "ardupilot": ("COMPASS_MOTCT", {"throttle": 1, "current_A": 2}),
    "px4": ("CAL_MAG_COMP_TYP", {"throttle": 1, "current_A": 2}),
}

#: The firmware's input per unit of magcal's ``current_A`` column: ArduPilot takes amperes, PX4 kiloamperes.
CURRENT_INPUT = {"ardupilot": (1.0, "A"), "px4": (1.0e-3, "kA")}

#: ArduPilot's custom rotations (``ROTATION_CUSTOM_1``, ``ROTATION_CUSTOM_2``): ``COMPASS_ORIENT`` value by compass.
ARDUPILOT_CUSTOM_ROTATIONS = {1: 101, 2: 102}

#: ArduPilot's documented range of ``COMPASS_MOT*`` (mG per A or at full throttle).
ARDUPILOT_MOT_RANGE_mG = 1000.0


#: The field per unit of current a calibration holds, wherever it holds it (it lives with the calibration).
current_compensation = current_term


@dataclass
class CurrentExport:
    """The current term as one firmware holds it.

    Attributes
    ----------
    column : str or None
        The column the firmware's compensation follows (``current_A`` or ``throttle``); None: nothing to write.
    k_per_input : dict of int to numpy.ndarray
        magcal sensor (1-based) -> ``k`` (3,) in nT per unit of the firmware's input (:attr:`input_unit`), in the
        sensor's own axes; zeros for an exported sensor without the term (its old value must not stay active).
    input_unit : str
        ``A`` (ArduPilot), ``kA`` (PX4), ``full throttle``, or, in the C header, the column's own unit.
    columns : dict of int to str
        The C header: each sensor's own column (the firmwares: :attr:`column` for every sensor with the term).
    dropped, notes : list of str
        What could not be written (one line each) and what to know.
    """

    column: str | None = None
    k_per_input: dict = field(default_factory=dict)
    input_unit: str = ""
    columns: dict = field(default_factory=dict)
    dropped: list = field(default_factory=list)
    notes: list = field(default_factory=list)


def compensation_type(fmt: str, column: str) -> tuple[str, int]:
    """``(parameter, value)`` of a firmware's compensation type for a column (``COMPASS_MOTCT`` 2 for
    ``current_A`` in ArduPilot ...)."""
    name, values = COMPENSATION_TYPE[fmt]
    return name, values[column]


def current_export(calibration, sensors, fmt, throttle_full_scale=None) -> CurrentExport:
    """The current term of the exported sensors in a firmware's units, and what it cannot hold.

    Parameters
    ----------
    calibration : Calibration
    sensors : sequence of int
        The exported magcal sensors (1-based), in the export's order.
    fmt : {'ardupilot', 'px4', 'c'}
    throttle_full_scale : float, optional
        What the ``throttle`` column reads at full throttle (the firmwares' throttle runs 0 to 1): 1 (default, as
        ArduPilot's ``CTUN.ThO`` that magcal reads from a ``.bin``), 100 for a column in percent.

    Raises
    ------
    MagcalError
        A ``throttle_full_scale`` that is not a positive number, or given for a calibration whose term does not
        follow a throttle column; a damaged term (:func:`current_compensation`).
    """
    if throttle_full_scale is not None:
        scale = float(throttle_full_scale)
        if not np.isfinite(scale) or scale <= 0:
            raise MagcalError(
                f"--throttle-full-scale {throttle_full_scale!r}: give what the throttle column reads at full "
                "throttle, a positive number (1 for 0-1, 100 for percent)"
            )
    k, columns = current_compensation(calibration)
    with_term = [s for s in sensors if columns[s - 1] is not None]
    if throttle_full_scale is not None and "throttle" not in {columns[s - 1] for s in with_term}:
        raise MagcalError(
            "--throttle-full-scale: the exported sensors hold no field per unit of a throttle column"
            + (f" (theirs follows {columns[with_term[0] - 1]})" if with_term else "")
        )
    out = CurrentExport()
    if k is None or not with_term:
        return out
    if fmt == "c":  # each sensor its own column, in the column's own unit
        out.column = columns[with_term[0] - 1]
        out.columns = {s: columns[s - 1] for s in with_term}
        out.k_per_input = {s: k[s - 1].copy() for s in with_term}
        out.input_unit = "unit of the column"
        return out
    first = with_term[0]
    column = columns[first - 1]
    type_name, _ = COMPENSATION_TYPE[fmt]
    firmware = {"ardupilot": "ArduPilot", "px4": "PX4"}[fmt]
    kept = []
    for s in with_term:
        if columns[s - 1] == column:
            kept.append(s)
            continue
        out.dropped.append(
            f"sensor {s}: its field follows {columns[s - 1]} but sensor {first}'s follows {column}, and {firmware} "
            f"has one compensation type ({type_name}) for every compass: sensor {s}'s current term is dropped "
            "(written as 0)"
        )
    if column == "throttle":
        per_column, unit = 1.0 if throttle_full_scale is None else float(throttle_full_scale), "full throttle"
        if throttle_full_scale is None:
            out.notes.append(
                "the throttle column is taken to read 0 at idle and 1 at full throttle, as the firmware's throttle "
                "(and ArduPilot's CTUN.ThO, which magcal reads from a .bin); for a column in percent give "
                "--throttle-full-scale 100"
            )
    else:
        input_per_ampere, unit = CURRENT_INPUT[fmt]
        per_column = 1.0 / input_per_ampere  # nT per A -> nT per firmware unit (kA: x 1000)
    out.column, out.input_unit = column, unit
    out.columns = {s: column for s in kept}
    out.k_per_input = {s: (k[s - 1] * per_column if s in kept else np.zeros(3)) for s in sensors}
    if len(sensors) < calibration.n_sensors:
        out.notes.append(
            f"{type_name} acts on every compass of the vehicle: check the compensation of the compasses not in this "
            "file"
        )
    return out


def custom_rotation_number(slot: int) -> int | None:
    """ArduPilot's ``COMPASS_ORIENT`` value for a custom rotation of compass ``slot`` (1: 101, 2: 102), or None for
    a compass that has none (ArduPilot has two custom rotations)."""
    return ARDUPILOT_CUSTOM_ROTATIONS.get(int(slot))


def custom_rotation_angles(rotation) -> tuple[float, float, float]:
    """``(roll, pitch, yaw)`` in degrees whose ``from_euler`` (``Rz(yaw) Ry(pitch) Rx(roll)``,
    :func:`magcal.geometry.orientations.euler_matrix`) is ``rotation`` (3, 3), sensor axes -> body."""
    with warnings.catch_warnings():  # at pitch +-90 deg the split of roll and yaw is free: any one does
        warnings.simplefilter("ignore", UserWarning)
        yaw, pitch, roll = Rotation.from_matrix(np.asarray(rotation, dtype=float)).as_euler("ZYX", degrees=True)
    angles = (float(roll), float(pitch), float(yaw))
    if not np.allclose(euler_matrix(*angles), rotation, atol=1e-9):  # pragma: no cover - scipy's own guarantee
        raise MagcalError("the mounting's Euler angles do not reproduce it; please report this calibration")
    return angles


def custom_rotation_parameters(number: int, rotation) -> dict:
    """``CUST_ROT_ENABLE`` and ``CUST_ROTn_ROLL/PITCH/YAW`` (deg) for custom rotation ``number`` (101 or 102)."""
    index = number - 100
    roll, pitch, yaw = custom_rotation_angles(rotation)
    return {
        "CUST_ROT_ENABLE": 1.0,
        f"CUST_ROT{index}_ROLL": roll,
        f"CUST_ROT{index}_PITCH": pitch,
        f"CUST_ROT{index}_YAW": yaw,
    }


def ardupilot_motor_parameters(tag: str, body_matrix, k_per_input) -> dict:
    """``COMPASS_MOT{tag}_X/Y/Z`` (mG per firmware unit): ``-M A k / 100``, ``body_matrix = M A`` the firmware's
    matrix times the rotation it turns the raw reading by, ``k`` in nT per firmware unit (sensor axes)."""
    mot = -(np.asarray(body_matrix, dtype=float) @ np.asarray(k_per_input, dtype=float)) / 100.0
    return {f"COMPASS_MOT{tag}_{axis}": float(mot[i]) for i, axis in enumerate("XYZ")}


def px4_compensation_parameters(slot: int, k_per_input) -> dict:
    """``CAL_MAG{slot}_XCOMP/YCOMP/ZCOMP`` (G per firmware unit): ``-k / 10^5``, in the sensor's axes (PX4 adds
    them to the raw reading before its offsets)."""
    comp = -np.asarray(k_per_input, dtype=float) / 1.0e5
    return {f"CAL_MAG{slot}_{axis}COMP": float(comp[i]) for i, axis in enumerate("XYZ")}
