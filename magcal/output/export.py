"""Parameters out: a magcal calibration as the parameters a flight controller loads (``docs/export.md``).

magcal corrects sensor ``i`` as ``B = R C^-1 (y - b)`` (:mod:`magcal.core.conventions`), with ``y`` the raw reading
and ``b`` the bias in nT, ``C^-1`` upper triangular (the seed's gauge) and ``R`` the rotation into the array frame.
The firmwares store less:

ArduPilot (``AP_Compass_Backend::correct_field``)
    ``corrected = M (raw + OFS)`` with ``raw`` and ``OFS`` in milligauss, ``M`` the *symmetric* matrix with
    diagonal ``COMPASS_DIA_X/Y/Z`` and off-diagonal ``COMPASS_ODI_X`` (xy), ``_Y`` (xz), ``_Z`` (yz), times the
    scalar ``COMPASS_SCALE`` (written as 1). Compasses 2 and 3 use ``COMPASS_OFS2_*``, ``COMPASS_DIA2_*``...
PX4 (``calibration::Magnetometer::Correct``)
    ``corrected = rot (S (raw - OFF))`` with ``raw`` and ``CAL_MAGn_[XYZ]OFF`` in gauss, ``S`` the *symmetric*
    matrix with diagonal ``CAL_MAGn_[XYZ]SCALE`` and off-diagonal ``CAL_MAGn_XODIAG`` (xy), ``YODIAG`` (xz),
    ``ZODIAG`` (yz); ``rot`` is the board or ``CAL_MAGn_ROT`` rotation, left as the user set it.

Both hold an offset and a symmetric matrix. The polar decomposition ``C^-1 = Q S`` (``Q`` a rotation, ``S``
symmetric positive definite) gives ``S``, the one symmetric matrix with the same corrected magnitudes:
``|S (y - b)| = |C^-1 (y - b)|`` exactly, so the firmware's total field equals magcal's. Its corrected *vector*
is magcal's turned by ``(R Q)^T``: ``B_magcal = R Q B_firmware``. ``Q`` is a gauge (total-field data fix only
``C^-T C^-1 = S^2``: the upper-triangular form is a convention); ``R`` is a misalignment the firmware cannot
store, and is refused unless forced. Candidate effects (temperature, drift, ...) are refused the same way.

A vector calibration (``mode: vector``, :mod:`magcal.fitting.vector`) knows each sensor's mounting ``R`` into the
vehicle's body frame. Its nearest right angle ``A`` is what the firmwares store as an orientation (ArduPilot
``COMPASS_ORIENT``, PX4 ``CAL_MAGn_ROT``, :mod:`magcal.geometry.orientations`); the rest, ``A^T R C^-1 = Q S``, is
split as above, and ``Q`` (the mounting's angle off the right angle, plus the sensor's non-orthogonality) is no
longer a gauge: it is what the firmware cannot hold. PX4 rotates after its correction, ``B = A S (y - b)``;
ArduPilot rotates the raw reading first and corrects in the body frame, ``B = (A S A^T) (A y + OFS)`` with
``OFS = -A b``. The C header holds the whole ``R C^-1``. ArduPilot can also hold the whole mounting: a custom
rotation (``COMPASS_ORIENT`` 101/102 with ``CUST_ROTn_*``) turns the raw reading by the rotation ``U`` of
``R C^-1 = U S`` and nothing is left out (:mod:`magcal.output.compensation`).

A gravity calibration (``mode: gravity``, :mod:`magcal.fitting.gravity`) knows each magnetometer's rotation into the
accelerometer's frame, which is rarely a right angle (a part soldered 2 deg off): it is exported as a vector
calibration's mounting (the custom rotation for ArduPilot's compasses 1 and 2; the nearest right angle, the rest
refused unless forced, for PX4), and its C header also holds the accelerometer's correction.

The field of the platform's current (a vector fit's current term, or the catalogue effect ``current_field``) is
written as the firmwares' motor compensation, ArduPilot ``COMPASS_MOTCT`` and ``COMPASS_MOT*``, PX4
``CAL_MAG_COMP_TYP`` and ``CAL_MAGn_[XYZ]COMP``, and into the C header (:mod:`magcal.output.compensation` has the
formulas); eddy currents and the other effects are not written (listed as dropped).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.linalg

from magcal.core.errors import MagcalError
from magcal.geometry.orientations import (
    FIRMWARE_ROTATIONS,
    euler_matrix,
    firmware_rotation,
    nearest_right_angle,
    rotation_name,
)
from magcal.geometry.procrustes import rotation_angle_deg
from magcal.output.compensation import (
    CURRENT_EFFECT,
    ARDUPILOT_MOT_RANGE_mG,
    ardupilot_motor_parameters,
    compensation_type,
    current_export,
    custom_rotation_number,
    custom_rotation_parameters,
    px4_compensation_parameters,
)
from magcal.output.formats import DESCRIPTIONS, Export, ExportFormat, get_format, register_format

#: Export formats and what each writes: a view of :data:`magcal.output.formats.EXPORT_FORMATS` (the built-ins are
#: registered at the end of this module).
FORMATS = DESCRIPTIONS

#: nT per unit of the firmwares' magnetometer parameters (ArduPilot milligauss, PX4 gauss).
NT_PER_MILLIGAUSS = 100.0
NT_PER_GAUSS = 1.0e5

#: Length of the offsets (milligauss) above which ArduPilot's arming check may refuse them: the smaller of the
#: defaults of COMPASS_OFFS_MAX seen across versions (1250 and 1800 mG).
ARDUPILOT_OFFSETS_MAX_mG = 1250.0

#: A frame rotation below this angle (deg) counts as none (the upper-triangular gauge of a perfect sensor).
ROTATION_TOLERANCE_DEG = 1e-6


@dataclass
class SensorExport:
    """What one sensor becomes in a firmware that stores an offset and a symmetric matrix.

    Attributes
    ----------
    sensor : int
        magcal's sensor number (1-based).
    slot : int
        The firmware's compass number: ArduPilot 1-3 (COMPASS, COMPASS2, COMPASS3), PX4 0-3 (CAL_MAG0..3).
    bias_nT : numpy.ndarray, shape (3,)
        magcal's bias b (nT): the firmware subtracts it from the raw reading (ArduPilot adds ``OFS = -b``).
    matrix : numpy.ndarray, shape (3, 3)
        The symmetric positive definite ``S`` of ``C^-1 = Q S`` (dimensionless).
    frame_rotation : numpy.ndarray, shape (3, 3)
        ``R Q``: magcal's corrected vector is ``frame_rotation @`` the firmware's.
    gauge_angle_deg : float
        Angle of ``Q`` (the upper-triangular gauge turned into the symmetric one), deg.
    misalignment_angle_deg : float
        Angle of ``R`` (this sensor's rotation into the array frame), deg.
    vector_error_nT : float
        Largest difference between the firmware's corrected vector and magcal's at the reference field
        ``2 F sin(angle/2)`` for the angle of ``R Q`` (nT); the magnitudes agree exactly.
    right_angle : numpy.ndarray, shape (3, 3), or None
        A vector calibration's right-angle mounting the firmware turns the reading by (``COMPASS_ORIENT``,
        ``CAL_MAGn_ROT``).
    rotation_number : int or None
        Its firmware number (101/102: ArduPilot's custom rotation).
    custom_rotation : numpy.ndarray, shape (3, 3), or None
        ArduPilot's custom rotation ``U`` (``R C^-1 = U S``) in place of a right angle: nothing is left out.
    current_nT_per_input : numpy.ndarray, shape (3,), or None
        The field per unit of the firmware's compensation input (A, kA, full throttle; the C header: per unit of
        the column), nT, in the sensor's axes: the firmware subtracts ``k u`` from the raw reading, in effect.
    current_column : str or None
        The column that input is (``current_A`` or ``throttle``).
    """

    sensor: int
    slot: int
    bias_nT: np.ndarray
    matrix: np.ndarray
    frame_rotation: np.ndarray
    gauge_angle_deg: float
    misalignment_angle_deg: float
    vector_error_nT: float
    right_angle: np.ndarray | None = None
    rotation_number: int | None = None
    custom_rotation: np.ndarray | None = None
    current_nT_per_input: np.ndarray | None = None
    current_column: str | None = None

    @property
    def rotation(self) -> np.ndarray | None:
        """The rotation the firmware turns the reading by: the custom rotation, else the right angle (or None)."""
        return self.custom_rotation if self.custom_rotation is not None else self.right_angle

    def firmware_corrected_nT(self, raw_nT, current=None) -> np.ndarray:
        """The firmware's corrected field ``S (y - b - k u)`` (nT) for raw readings ``y`` (N, 3) in nT and the
        compensation's input ``u`` (N,) (A, kA or throttle 0-1; ignored without a current term); with a mounting
        (a vector calibration) ``A S (y - b - k u)``, in the body frame."""
        z = np.asarray(raw_nT, dtype=float) - self.bias_nT
        if self.current_nT_per_input is not None and current is not None:
            z = z - np.asarray(current, dtype=float)[:, None] * self.current_nT_per_input[None, :]
        out = z @ self.matrix.T
        return out if self.rotation is None else out @ self.rotation.T


@dataclass(frozen=True, eq=False)
class FirmwareFormat(ExportFormat):
    """A format that holds an offset and a symmetric matrix per compass (ArduPilot, PX4, the C header).

    Attributes
    ----------
    first_slot : int
        The firmware's first compass number (ArduPilot 1, PX4 0).
    n_slots : int
        How many compasses it calibrates.
    slots_text : str
        Its compass numbers as a refusal says them.
    whole_matrix : bool
        It holds the whole ``R C^-1`` (and the frame rotation): the C header.
    custom_rotations : bool
        It can hold a mounting off the right angles as a custom rotation (ArduPilot's ``COMPASS_ORIENT`` 101/102).
    build : callable
        ``build(exports, calibration, source, dropped, notes) -> (parameters, text)``.
    checks : callable
        ``checks(exports, parameters) -> list of str``: what the firmware may refuse when it loads the values.
    """

    first_slot: int = 1
    n_slots: int = 4
    slots_text: str = "slots 1 to 4"
    whole_matrix: bool = False
    custom_rotations: bool = False
    build: Callable = None  # type: ignore[assignment]
    checks: Callable = lambda exports, parameters: []

    def write(self, calibration, sensors=None, slots=None, force=False, source="calibration", **options) -> Export:
        """The firmware's parameters of ``calibration`` (:func:`export_calibration`)."""
        return _firmware_export(self, calibration, sensors, slots, force, source, **options)


def firmware_format(fmt) -> FirmwareFormat:
    """The firmware format ``fmt`` (a name or the format itself)."""
    spec = fmt if isinstance(fmt, FirmwareFormat) else get_format(fmt)
    if not isinstance(spec, FirmwareFormat):
        raise MagcalError(f"--format {spec.name!r} is not a firmware's offset-and-matrix format")
    return spec


def symmetric_factor(cinv):
    """Polar decomposition ``C^-1 = Q S`` of a correction matrix.

    Parameters
    ----------
    cinv : array_like, shape (3, 3)
        Correction matrix with a positive determinant.

    Returns
    -------
    q : numpy.ndarray, shape (3, 3)
        Proper rotation.
    s : numpy.ndarray, shape (3, 3)
        Symmetric positive definite, ``s = sqrtm(C^-T C^-1)``: the same corrected magnitudes as ``C^-1``.
    """
    cinv = np.asarray(cinv, dtype=float)
    if np.linalg.det(cinv) <= 0:
        raise MagcalError(
            "the correction matrix has a non-positive determinant (a mirrored axis); no firmware "
            "matrix can express it: check the sensor's axis signs"
        )
    q, s = scipy.linalg.polar(cinv, side="right")
    return q, 0.5 * (s + s.T)


def sensor_exports(calibration, sensors=None, slots=None, fmt="c", custom_rotation=True):
    """Per sensor, the firmware's offset and symmetric matrix and the frame rotation left out.

    Parameters
    ----------
    calibration : Calibration
    sensors : sequence of int, optional
        magcal sensor numbers (1-based) to export; default all.
    slots : sequence of int, optional
        Firmware compass numbers for them (ArduPilot 1-3, PX4 0-3); default sensor ``i`` -> ArduPilot compass
        ``i``, PX4 ``CAL_MAG{i-1}``.
    fmt : str or FirmwareFormat
        The firmware format (its slot numbering, its number of slots, whether it holds the whole matrix).
    custom_rotation : bool
        ArduPilot, vector calibration: a mounting off the right angles of compass 1 or 2 as a custom rotation
        (:func:`magcal.output.compensation.custom_rotation_number`); False keeps the nearest right angle.
    """
    spec = firmware_format(fmt)
    n = calibration.n_sensors
    sensors = list(range(1, n + 1)) if sensors is None else [int(s) for s in sensors]
    for s in sensors:
        if not 1 <= s <= n:
            raise MagcalError(f"--sensor {s}: the calibration has sensor(s) 1 to {n}")
    first = spec.first_slot
    if slots is None:
        slots = [s - 1 + first for s in sensors]
    slots = [int(k) for k in slots]
    if len(slots) != len(sensors):
        raise MagcalError("give one --slot per exported sensor")
    last = first + spec.n_slots - 1
    for s, k in zip(sensors, slots):
        if not first <= k <= last:
            raise MagcalError(
                f"sensor {s} would go to slot {k}, but {spec.slots_text}; export it alone with --sensor {s} "
                f"--slot {first}"
            )
    field_nT = float(calibration.reference_total_nT or 50_000.0)
    out = []
    kept = calibration.sensors_for_new_data()  # a record-only term's kept level (the bias after a step) folded in
    for s, k in zip(sensors, slots):
        cal = kept[s - 1]
        if getattr(calibration, "mode", "scalar") in ("vector", "gravity"):
            e = _vector_export(cal, s, k, spec, field_nT)
            if spec.custom_rotations and custom_rotation:
                e = _ardupilot_custom_export(cal, e)
            out.append(e)
            continue
        q, sym = symmetric_factor(cal.cinv)
        frame = cal.R @ q
        angle = rotation_angle_deg(frame)
        out.append(
            SensorExport(
                sensor=s,
                slot=k,
                bias_nT=cal.bias_nT.copy(),
                matrix=sym,
                frame_rotation=frame,
                gauge_angle_deg=rotation_angle_deg(q),
                misalignment_angle_deg=rotation_angle_deg(cal.R),
                vector_error_nT=2.0 * field_nT * np.sin(np.radians(angle) / 2.0),
            )
        )
    return out


def _vector_export(cal, sensor, slot, spec, field_nT) -> SensorExport:
    """A vector calibration's sensor: its right-angle mounting as the firmware's orientation, the rest split."""
    w = cal.R @ cal.cinv
    if spec.whole_matrix:  # the header holds the whole matrix
        return SensorExport(sensor, slot, cal.bias_nT.copy(), w, np.eye(3), 0.0, 0.0, 0.0)
    right, _ = nearest_right_angle(cal.R)
    q, sym = symmetric_factor(right.T @ w)
    angle = rotation_angle_deg(q)
    return SensorExport(
        sensor=sensor,
        slot=slot,
        bias_nT=cal.bias_nT.copy(),
        matrix=sym,
        frame_rotation=right @ q @ right.T,
        gauge_angle_deg=0.0,
        misalignment_angle_deg=angle,
        vector_error_nT=2.0 * field_nT * np.sin(np.radians(angle) / 2.0),
        right_angle=right,
        rotation_number=firmware_rotation(right),
    )


def _ardupilot_custom_export(cal, e) -> SensorExport:
    """A vector calibration's sensor for ArduPilot compass ``e.slot`` with its whole mounting as a custom rotation
    (``R C^-1 = U S``: ``COMPASS_ORIENT`` 101/102 turns the raw reading by ``U``), when the right angle leaves a
    remainder and the compass has a custom rotation; otherwise ``e`` unchanged."""
    number = custom_rotation_number(e.slot)
    if number is None or e.misalignment_angle_deg <= ROTATION_TOLERANCE_DEG:
        return e
    u, sym = symmetric_factor(cal.R @ cal.cinv)
    return SensorExport(
        sensor=e.sensor,
        slot=e.slot,
        bias_nT=cal.bias_nT.copy(),
        matrix=sym,
        frame_rotation=np.eye(3),
        gauge_angle_deg=0.0,
        misalignment_angle_deg=0.0,
        vector_error_nT=0.0,
        right_angle=None,
        rotation_number=number,
        custom_rotation=u,
    )


def unsupported(calibration, exports) -> list[str]:
    """What magcal's model holds that no firmware parameter can carry, one line each (empty: nothing). The
    current's field is not among them: :func:`magcal.output.compensation.current_export` says what of it is lost."""
    lost = []
    platform = getattr(calibration, "platform", None)
    if platform is not None:
        for name in platform.names:
            if name != "current":
                lost.append(f"platform term {name}: the firmware has no parameter for it (its correction is dropped)")
    if calibration.model is not None:
        for e in calibration.model.effects:
            if e.name != CURRENT_EFFECT:
                lost.append(f"effect {e.label}: the firmware has no parameter for it (its correction is dropped)")
    if getattr(calibration, "mode", "scalar") in ("vector", "gravity"):
        field_nT = float(calibration.reference_total_nT or 50_000.0)
        for e in exports:
            if e.right_angle is None:
                continue
            if e.rotation_number is None:
                lost.append(f"sensor {e.sensor}: its right-angle mounting has no firmware rotation number")
            if e.misalignment_angle_deg > ROTATION_TOLERANCE_DEG:
                lost.append(
                    f"sensor {e.sensor}: its mounting is the right angle {rotation_name(e.rotation_number)} "
                    f"(rotation {e.rotation_number}, written) turned by a further {e.misalignment_angle_deg:.4g} deg "
                    f"(the angle off the right angle and the axes' non-orthogonality; up to {e.vector_error_nT:.4g} "
                    f"nT on a {field_nT:.6g} nT field), which cannot be stored"
                )
        return lost
    field_nT = float(calibration.reference_total_nT or 50_000.0)
    for e in exports:
        if e.misalignment_angle_deg > ROTATION_TOLERANCE_DEG:
            err = 2.0 * field_nT * np.sin(np.radians(e.misalignment_angle_deg) / 2.0)
            lost.append(
                f"sensor {e.sensor}: its rotation R into the {calibration.frame} frame "
                f"({e.misalignment_angle_deg:.4g} deg, up to {err:.4g} nT on a {field_nT:.6g} nT field) "
                "cannot be stored; the firmware's vector stays in the sensor's own frame"
            )
    return lost


def export_calibration(
    calibration,
    fmt,
    sensors=None,
    slots=None,
    force=False,
    source="calibration",
    throttle_full_scale=None,
    custom_rotation=True,
) -> Export:
    """The parameters of ``calibration`` in the export format ``fmt`` (:data:`magcal.output.formats.EXPORT_FORMATS`:
    the built-ins ``ardupilot``, ``px4``, ``c``, and any a package added), or a refusal naming what would be lost.

    Parameters
    ----------
    calibration : Calibration
    fmt : str
        The format's name.
    sensors, slots : sequence of int, optional
        See :func:`sensor_exports`.
    force : bool
        Export even when effects or misalignments are dropped (they are listed in ``Export.dropped`` and in the
        file's comments), and the sensors whose calibration the fit marked not determined by its record. Without
        it such a sensor is left out when ``sensors`` is not given (the others are exported) and refused when it is
        named; ``Export.notes`` says which and why (:func:`determined_sensors`).
    source : str
        The calibration's file name, for the file header and messages.
    throttle_full_scale : float, optional
        What a ``throttle`` column reads at full throttle (default 1; 100 for percent): the firmwares' motor
        compensation is per full throttle (:func:`magcal.output.compensation.current_export`).
    custom_rotation : bool
        ArduPilot: write a vector calibration's mounting off the right angles as a custom rotation (compasses 1
        and 2); False writes the nearest right angle and refuses the rest, as PX4.

    Raises
    ------
    MagcalError
        Unknown format, bad sensor or slot, or (without ``force``) anything the firmware cannot hold or a sensor
        not determined.
    """
    sensors, slots, said = determined_sensors(calibration, sensors, slots, force, source)
    result = get_format(fmt).write(
        calibration,
        sensors=sensors,
        slots=slots,
        force=force,
        source=source,
        throttle_full_scale=throttle_full_scale,
        custom_rotation=custom_rotation,
    )
    if said:
        result.notes = [said] + list(result.notes)
    return result


def determined_sensors(calibration, sensors=None, slots=None, force=False, source="calibration"):
    """``(sensors, slots, note)``: the sensors (1-based) an export writes, without those whose calibration the fit
    marked not determined by its record (:meth:`magcal.calibration.calibration.Calibration.undetermined`) unless
    ``force``, their slots, and what was left out or forced and why (``""`` when nothing was).

    Raises
    ------
    MagcalError
        A sensor named in ``sensors`` is not determined, or none is left (without ``force``).
    """
    undetermined = calibration.undetermined()
    chosen = list(range(1, calibration.n_sensors + 1)) if sensors is None else [int(s) for s in sensors]
    bad = [s for s in chosen if s - 1 in undetermined]
    if not bad:
        return sensors, slots, ""
    said = "; ".join(f"sensor {s}: {undetermined[s - 1]}" for s in bad)
    if force:
        return sensors, slots, f"exported although not determined (forced): {said}"
    advice = "recalibrate on a record that determines it (docs/vector.md), or pass --force"
    if sensors is not None or len(bad) == len(chosen):
        raise MagcalError(f"{source}: not exported: {said}; {advice}")
    kept = [k for k, s in enumerate(chosen) if s not in bad]
    slots = None if slots is None else [list(slots)[k] for k in kept]
    return [chosen[k] for k in kept], slots, f"not exported: {said}; {advice}"


def _firmware_export(
    spec,
    calibration,
    sensors=None,
    slots=None,
    force=False,
    source="calibration",
    throttle_full_scale=None,
    custom_rotation=True,
    **options,
) -> Export:
    """A firmware format's export (:meth:`FirmwareFormat.write`): the offsets and symmetric matrices, what is
    dropped, the notes, the file."""
    fmt = spec.name
    exports = sensor_exports(calibration, sensors, slots, spec, custom_rotation=custom_rotation)
    current = _attach_current(calibration, exports, fmt, throttle_full_scale)
    dropped = unsupported(calibration, exports) + current.dropped
    if dropped and not force:
        raise MagcalError(
            f"{source}: the calibration holds more than {fmt} parameters can: "
            + "; ".join(dropped)
            + ". Recalibrate without effects (and per sensor, --sensor N) or pass --force to export without them"
        )
    notes = []
    for e in exports:
        if e.gauge_angle_deg > ROTATION_TOLERANCE_DEG:
            notes.append(
                f"sensor {e.sensor}: the symmetric matrix S of C^-1 = Q S is exported; magcal's "
                f"upper-triangular frame is turned from the firmware's by {e.gauge_angle_deg:.4g} deg "
                "(a gauge: total-field data do not fix it); the field magnitude is the same"
            )
    notes += current.notes + _mounting_notes(calibration, exports, spec, custom_rotation)
    parameters, text = spec.build(exports, calibration, source, dropped, notes)
    _check_storable(parameters, exports, spec, source)
    notes += spec.checks(exports, parameters)
    return Export(fmt, text, parameters, exports, dropped, notes, current.column)


def _ardupilot_checks(exports, parameters) -> list[str]:
    """What ArduPilot may refuse at arming, or read as a unit error: long offsets, motor compensation beyond its
    documented range."""
    notes = []
    for e in exports:
        length = float(np.linalg.norm(e.bias_nT)) / NT_PER_MILLIGAUSS
        if length > ARDUPILOT_OFFSETS_MAX_mG:
            notes.append(
                f"compass {e.slot}: the offsets are {length:.0f} mG long; ArduPilot's arming check "
                "refuses offsets longer than COMPASS_OFFS_MAX (1250 or 1800 mG by default): move the "
                "compass away from the interference, or check the units"
            )
    mot = {n: v for n, v in parameters.items() if n.startswith("COMPASS_MOT") and n != "COMPASS_MOTCT"}
    beyond = [n for n, v in mot.items() if abs(v) > ARDUPILOT_MOT_RANGE_mG]
    if beyond:
        notes.append(
            f"{', '.join(beyond)} beyond ArduPilot's documented range of -{ARDUPILOT_MOT_RANGE_mG:.0f} to "
            f"{ARDUPILOT_MOT_RANGE_mG:.0f} mG per unit: check the units of the current or throttle column"
        )
    return notes


# --- the current's field and the mounting (magcal.output.compensation) -----------------------------------------


def _attach_current(calibration, exports, fmt, throttle_full_scale):
    """The current term in the firmware's units (:func:`magcal.output.compensation.current_export`), set on each
    exported sensor (``current_nT_per_input``, ``current_column``)."""
    current = current_export(calibration, [e.sensor for e in exports], fmt, throttle_full_scale)
    for e in exports:
        k = current.k_per_input.get(e.sensor)
        if k is not None:
            e.current_nT_per_input = np.asarray(k, dtype=float)
            e.current_column = current.columns.get(e.sensor, current.column)
    return current


def _mounting_notes(calibration, exports, spec, custom_rotation) -> list[str]:
    """What to know about ArduPilot's custom rotations: how to load them, and a compass that has none."""
    if not spec.custom_rotations or getattr(calibration, "mode", "scalar") not in ("vector", "gravity"):
        return []
    notes = []
    for e in exports:
        tag = "" if e.slot == 1 else str(e.slot)
        if e.custom_rotation is not None:
            right, off = nearest_right_angle(e.custom_rotation)
            number = firmware_rotation(right)
            index = e.rotation_number - 100
            notes.append(
                f"compass {e.slot}: its mounting, the right angle {rotation_name(number) if number is not None else ''}"
                f" turned by {off:.4g} deg (with the axes' non-orthogonality), is written whole as ArduPilot's custom "
                f"rotation {index} (COMPASS_ORIENT{tag} {e.rotation_number}, CUST_ROT{index}_ROLL/PITCH/YAW), "
                "ArduPilot 4.2 or later: set CUST_ROT_ENABLE to 1 and reboot before loading this file (the "
                "CUST_ROT parameters appear then); COMPASS_ORIENT acts on an external compass only"
            )
        elif custom_rotation and e.right_angle is not None and e.misalignment_angle_deg > ROTATION_TOLERANCE_DEG:
            notes.append(
                f"compass {e.slot}: ArduPilot's two custom rotations are kept for compasses 1 and 2 (custom rotation "
                "k for compass k, so that files exported one compass at a time never share one); export this "
                "sensor to --slot 1 or 2 to write its whole mounting"
            )
    return notes


#: Largest magnitude the firmwares' parameters (ArduPilot ``AP_Float``, PX4 ``REAL32``) and the C header's
#: ``float`` can hold.
FLOAT32_MAX = float(np.finfo(np.float32).max)


def _check_storable(parameters, exports, spec, source) -> None:
    """Refuse an export holding a value that is not a finite 32-bit float (NaN, infinite, or beyond
    :data:`FLOAT32_MAX`): the firmware or the compiler would take it for something else, so nothing is written."""
    values = list(parameters.items())
    if spec.whole_matrix:  # the header also holds each sensor's frame rotation
        values += [(f"MAGCAL_S{e.sensor}_FRAME", v) for e in exports for v in np.ravel(e.frame_rotation)]
    for name, value in values:
        if not abs(float(value)) <= FLOAT32_MAX:
            raise MagcalError(
                f"{source}: {name} would be {float(value):g}, which no {spec.name} parameter can hold (a finite 32-bit "
                "float): the calibration's values are too large; recalibrate"
            )


def _header_lines(calibration, source, dropped, notes, formula):
    # no clock time: the same calibration gives the same file, from the command line or the workbench
    lines = [
        f"magcal export of {source}",
        f"firmware formula: {formula}",
        f"calibration frame: {calibration.frame}; reference field "
        f"{calibration.reference_total_nT if calibration.reference_total_nT is not None else 'per sample'} nT",
    ]
    lines += [f"DROPPED: {d}" for d in dropped]
    lines += [f"note: {n}" for n in notes]
    return lines


def _fmt(value) -> str:
    return f"{float(value):.9g}"


def _c_float(value) -> str:
    """A C ``float`` literal of 9 significant digits (``1.0f``, never ``1f``, which C refuses)."""
    text = _fmt(value)
    return (text if any(c in text for c in ".en") else text + ".0") + "f"


def _offset_and_matrix(offset, matrix, offset_name, diagonal_name, off_diagonal_name) -> dict:
    """Parameters of one compass: the offset per axis and the symmetric matrix's diagonal and off-diagonal
    (xy, xz, yz), each name a template whose ``{}`` is the axis letter (X, Y, Z; for the off-diagonal, X = xy,
    Y = xz, Z = yz, as both firmwares number them). The offset is in the firmware's unit and sign already."""
    params = {offset_name.format(axis): float(offset[k]) for k, axis in enumerate("XYZ")}
    params.update({diagonal_name.format(axis): float(matrix[k, k]) for k, axis in enumerate("XYZ")})
    params.update(
        {off_diagonal_name.format(axis): float(matrix[i, j]) for (i, j), axis in zip(((0, 1), (0, 2), (1, 2)), "XYZ")}
    )
    return params


def _ardupilot(exports, calibration, source, dropped, notes):
    params = {}
    column = next((e.current_column for e in exports if e.current_column is not None), None)
    if any(e.custom_rotation is not None for e in exports):
        params["CUST_ROT_ENABLE"] = 1.0  # first: the CUST_ROTn_* parameters exist once it is set (and rebooted)
    for e in exports:
        tag = "" if e.slot == 1 else str(e.slot)
        # ArduPilot rotates the raw reading by COMPASS_ORIENT first: offsets and matrix in the body frame
        a = np.eye(3) if e.rotation is None else e.rotation
        params.update(
            _offset_and_matrix(
                -(a @ e.bias_nT) / NT_PER_MILLIGAUSS,
                a @ e.matrix @ a.T,
                f"COMPASS_OFS{tag}_{{}}",
                f"COMPASS_DIA{tag}_{{}}",
                f"COMPASS_ODI{tag}_{{}}",
            )
        )
        params[f"COMPASS_SCALE{tag}"] = 1.0
        if e.rotation_number is not None:
            params[f"COMPASS_ORIENT{tag}"] = e.rotation_number
        if e.custom_rotation is not None:
            params.update(custom_rotation_parameters(e.rotation_number, e.custom_rotation))
        if column is not None:  # every exported compass: an old value must not stay active
            k = np.zeros(3) if e.current_nT_per_input is None else e.current_nT_per_input
            params.update(ardupilot_motor_parameters(tag, a @ e.matrix, k))
    formula = (
        "corrected_mG = [DIA_X ODI_X ODI_Y; ODI_X DIA_Y ODI_Z; ODI_Y ODI_Z DIA_Z] "
        "(SCALE (raw_mG + OFS)), OFS in milligauss"
    )
    if column is not None:
        name, value = compensation_type("ardupilot", column)
        params[name] = value
        formula += (
            " + MOT u, MOT in milligauss per "
            + ("ampere, u the battery current in A" if column == "current_A" else "full throttle, u the throttle 0-1")
            + f" ({name} {value})"
        )
    head = _header_lines(calibration, source, dropped, notes, formula)
    body = [f"# {line}" for line in head]
    body += [f"# magcal sensor {e.sensor} -> compass {e.slot}" for e in exports]
    body += [f"{name},{_fmt(value)}" for name, value in params.items()]
    return params, "\n".join(body) + "\n"


def _px4(exports, calibration, source, dropped, notes):
    params = {}
    column = next((e.current_column for e in exports if e.current_column is not None), None)
    for e in exports:
        pre = f"CAL_MAG{e.slot}_"
        params.update(
            _offset_and_matrix(e.bias_nT / NT_PER_GAUSS, e.matrix, pre + "{}OFF", pre + "{}SCALE", pre + "{}ODIAG")
        )
        if e.rotation_number is not None:
            params[pre + "ROT"] = e.rotation_number
        if column is not None:  # every exported compass: an old value must not stay active
            k = np.zeros(3) if e.current_nT_per_input is None else e.current_nT_per_input
            params.update(px4_compensation_parameters(e.slot, k))
    formula = (
        "corrected_G = rot ([XSCALE XODIAG YODIAG; XODIAG YSCALE ZODIAG; YODIAG ZODIAG ZSCALE] "
        "(raw_G - [XOFF YOFF ZOFF])), offsets in gauss"
    )
    if column is not None:
        name, value = compensation_type("px4", column)
        params[name] = value
        formula = formula.replace("(raw_G - ", "((raw_G + u [XCOMP YCOMP ZCOMP]) - ") + (
            ", COMP in gauss per "
            + ("kA, u the battery current in kA" if column == "current_A" else "full throttle, u the throttle 0-1")
            + f" ({name} {value})"
        )
    head = _header_lines(calibration, source, dropped, notes, formula)
    body = [f"# {line}" for line in head]
    body += [
        f"# magcal sensor {e.sensor} -> CAL_MAG{e.slot} (check that CAL_MAG{e.slot}_ID is that magnetometer)"
        for e in exports
    ]
    body += ["# Vehicle-Id\tComponent-Id\tName\tValue\tType"]
    body += [f"1\t1\t{name}\t{_px4_value(name, value)}" for name, value in params.items()]
    return params, "\n".join(body) + "\n"


#: PX4's integer parameters among those written (``PARAM_DEFINE_INT32``): QGroundControl skips a line whose type
#: is not the parameter's own.
PX4_INTEGER_PARAMETERS = ("_ROT", "CAL_MAG_COMP_TYP")


def _px4_value(name, value) -> str:
    """``VALUE\tTYPE`` of a QGroundControl parameter line: 6 (MAV_PARAM_TYPE_INT32) for an integer parameter, 9
    (REAL32) for the others."""
    if name.endswith(PX4_INTEGER_PARAMETERS[0]) or name == PX4_INTEGER_PARAMETERS[1]:
        return f"{int(value)}\t6"
    return f"{_fmt(value)}\t9"


def _c_header(exports, calibration, source, dropped, notes):
    params = {}
    formula = "corrected_nT = MAGCAL_Sn_MATRIX * (raw_nT - MAGCAL_Sn_BIAS_NT)"
    if any(e.current_nT_per_input is not None for e in exports):
        formula = (
            "corrected_nT = MAGCAL_Sn_MATRIX * (raw_nT - MAGCAL_Sn_BIAS_NT - MAGCAL_Sn_CURRENT_NT_PER_UNIT * u), "
            "u the value of the sensor's MAGCAL_Sn_CURRENT_COLUMN (a sensor without it: u = 0)"
        )
    head = _header_lines(calibration, source, dropped, notes, formula)
    lines = (
        ["/* " + head[0]]
        + [f" * {line}" for line in head[1:]]
        + [
            " * raw_nT: the sensor's reading in nT in its own axes; corrected_nT: the field in nT.",
            " * MAGCAL_Sn_FRAME turns it into magcal's frame: B_magcal = MAGCAL_Sn_FRAME * corrected_nT.",
            " */",
            "#ifndef MAGCAL_CALIBRATION_H",
            "#define MAGCAL_CALIBRATION_H",
            "",
            f"#define MAGCAL_N_SENSORS {len(exports)}",
            "",
        ]
    )

    def matrix(name, m):
        rows = ",\n    ".join("{" + ", ".join(_c_float(v) for v in row) + "}" for row in m)
        return [f"static const float {name}[3][3] = {{\n    {rows}\n}};"]

    for e in exports:
        tag = f"MAGCAL_S{e.sensor}"
        lines.append(f"/* magcal sensor {e.sensor} */")
        lines.append(f"static const float {tag}_BIAS_NT[3] = {{" + ", ".join(_c_float(v) for v in e.bias_nT) + "};")
        lines += matrix(f"{tag}_MATRIX", e.matrix)
        lines += matrix(f"{tag}_FRAME", e.frame_rotation)
        if e.current_nT_per_input is not None:
            lines.append(f'#define {tag}_CURRENT_COLUMN "{e.current_column}"')
            lines.append(
                f"static const float {tag}_CURRENT_NT_PER_UNIT[3] = {{"
                + ", ".join(_c_float(v) for v in e.current_nT_per_input)
                + "};"
            )
            for k, axis in enumerate("xyz"):
                params[f"{tag}_CURRENT_NT_PER_UNIT_{axis}"] = float(e.current_nT_per_input[k])
        lines.append("")
        for k, axis in enumerate("xyz"):
            params[f"{tag}_BIAS_NT_{axis}"] = float(e.bias_nT[k])
        for i in range(3):
            for j in range(3):
                params[f"{tag}_MATRIX_{i}{j}"] = float(e.matrix[i, j])
    accel = getattr(calibration, "accelerometer", None)
    if accel is not None:  # a gravity calibration: the accelerometer's correction and the compass
        lines += [
            "/* the accelerometer (a gravity calibration): f_m_s2 = MAGCAL_ACCEL_MATRIX * (raw_m_s2 - "
            "MAGCAL_ACCEL_BIAS_M_S2),",
            " * up when still. Tilt-compensated heading of the board's x axis from f and the corrected field m:",
            " * down = -f / |f|; east = down x m / |down x m|; north = east x down; heading = atan2(east.x, north.x) */",
            "static const float MAGCAL_ACCEL_BIAS_M_S2[3] = {" + ", ".join(_c_float(v) for v in accel.bias_m_s2) + "};",
        ]
        lines += matrix("MAGCAL_ACCEL_MATRIX", accel.kinv)
        lines.append("")
        for k, axis in enumerate("xyz"):
            params[f"MAGCAL_ACCEL_BIAS_M_S2_{axis}"] = float(accel.bias_m_s2[k])
        for i in range(3):
            for j in range(3):
                params[f"MAGCAL_ACCEL_MATRIX_{i}{j}"] = float(accel.kinv[i, j])
    lines += ["#endif /* MAGCAL_CALIBRATION_H */", ""]
    return params, "\n".join(lines)


# --- the built-in formats ----------------------------------------------------------------------------------------

ARDUPILOT = register_format(
    FirmwareFormat(
        name="ardupilot",
        title="ArduPilot parameters",
        description="ArduPilot parameter file (NAME,VALUE lines: COMPASS_OFS*, COMPASS_DIA*, COMPASS_ODI*, "
        "COMPASS_SCALE*; with a vector calibration COMPASS_ORIENT* and CUST_ROT*; with a current term COMPASS_MOTCT, "
        "COMPASS_MOT*)",
        file_name="compass.parm",
        button="ArduPilot .parm",
        refuses="candidate effects, rotations between sensors and a mounting beyond its custom rotations (unless "
        "forced); compasses 1 to 3",
        first_slot=1,
        n_slots=3,
        slots_text="ArduPilot calibrates compasses 1 to 3 (COMPASS_, COMPASS2_, COMPASS3_)",
        custom_rotations=True,
        build=_ardupilot,
        checks=_ardupilot_checks,
    )
)
PX4 = register_format(
    FirmwareFormat(
        name="px4",
        title="PX4 parameters",
        description="PX4/QGroundControl parameter file (CAL_MAGn_[XYZ]OFF, [XYZ]SCALE, [XYZ]ODIAG; CAL_MAGn_ROT; with "
        "a current term CAL_MAG_COMP_TYP, CAL_MAGn_[XYZ]COMP)",
        file_name="mag.params",
        button="PX4 .params",
        refuses="candidate effects, rotations between sensors and a mounting off the right angles (unless forced); "
        "CAL_MAG0 to CAL_MAG3",
        first_slot=0,
        n_slots=4,
        slots_text="PX4 has CAL_MAG0 to CAL_MAG3",
        build=_px4,
    )
)
C_HEADER = register_format(
    FirmwareFormat(
        name="c",
        title="C header",
        description="C header with the correction matrix, offset and formula per sensor",
        file_name="magcal_calibration.h",
        button="C header (.h)",
        refuses="candidate effects and rotations between sensors (unless forced); values beyond a 32-bit float",
        first_slot=1,
        n_slots=4,
        slots_text="slots 1 to 4",
        whole_matrix=True,
        build=_c_header,
    )
)


def apply_ardupilot(parameters, raw_mG, slot=1, motor=None) -> np.ndarray:
    """ArduPilot's correction of raw readings (milligauss) with exported parameters, as
    ``AP_Compass_Backend::correct_field`` does it: ``M (SCALE (raw + OFS)) + MOT u``, the raw reading first turned by
    ``COMPASS_ORIENT`` when the parameters hold one (a right angle of
    :data:`magcal.geometry.orientations.FIRMWARE_ROTATIONS`, or 101/102: ``CUST_ROTn_ROLL/PITCH/YAW``).

    ``motor`` (N,) is ``u``: the battery current in A (``COMPASS_MOTCT`` 2) or the throttle 0-1 (1); the motor
    compensation is off without it or without ``COMPASS_MOTCT``. Returns the corrected field (N, 3) in milligauss.
    """
    tag = "" if slot == 1 else str(slot)
    p = parameters
    ofs = np.array([p[f"COMPASS_OFS{tag}_{a}"] for a in "XYZ"])
    dia = np.array([p[f"COMPASS_DIA{tag}_{a}"] for a in "XYZ"])
    odi = np.array([p[f"COMPASS_ODI{tag}_{a}"] for a in "XYZ"])
    scale = p.get(f"COMPASS_SCALE{tag}", 1.0)
    m = np.array([[dia[0], odi[0], odi[1]], [odi[0], dia[1], odi[2]], [odi[1], odi[2], dia[2]]])
    raw = np.asarray(raw_mG, dtype=float)
    orient = p.get(f"COMPASS_ORIENT{tag}")
    if orient is not None and int(orient) in (101, 102):
        index = int(orient) - 100
        raw = raw @ euler_matrix(*(p[f"CUST_ROT{index}_{a}"] for a in ("ROLL", "PITCH", "YAW"))).T
    elif orient is not None:
        raw = raw @ euler_matrix(*FIRMWARE_ROTATIONS[int(orient)]).T
    out = (scale * (raw + ofs)) @ m.T
    if motor is not None and p.get("COMPASS_MOTCT", 0) in (1, 2):
        mot = np.array([p.get(f"COMPASS_MOT{tag}_{a}", 0.0) for a in "XYZ"])
        out = out + np.asarray(motor, dtype=float)[:, None] * mot[None, :]
    return out


def apply_px4(parameters, raw_G, slot=0, rotation=None, power=None) -> np.ndarray:
    """PX4's correction of raw readings (gauss) with exported parameters, as ``calibration::Magnetometer::
    Correct`` does it: ``rot (S ((raw + power COMP) - OFF))``, ``rot`` the given matrix, else ``CAL_MAGn_ROT`` when
    the parameters hold one; ``power`` (N,) the battery current in kA (``CAL_MAG_COMP_TYP`` 2) or the throttle 0-1
    (1), the compensation off without it. Returns (N, 3) gauss."""
    pre = f"CAL_MAG{slot}_"
    p = parameters
    off = np.array([p[f"{pre}{a}OFF"] for a in "XYZ"])
    d = np.array([p[f"{pre}{a}SCALE"] for a in "XYZ"])
    o = np.array([p[f"{pre}{a}ODIAG"] for a in "XYZ"])
    s = np.array([[d[0], o[0], o[1]], [o[0], d[1], o[2]], [o[1], o[2], d[2]]])
    if rotation is None and p.get(f"{pre}ROT") is not None and int(p[f"{pre}ROT"]) in FIRMWARE_ROTATIONS:
        rotation = euler_matrix(*FIRMWARE_ROTATIONS[int(p[f"{pre}ROT"])])
    rot = np.eye(3) if rotation is None else np.asarray(rotation, dtype=float)
    raw = np.asarray(raw_G, dtype=float)
    if power is not None and p.get("CAL_MAG_COMP_TYP", 0) in (1, 2, 3):
        comp = np.array([p.get(f"{pre}{a}COMP", 0.0) for a in "XYZ"])
        raw = raw + np.asarray(power, dtype=float)[:, None] * comp[None, :]
    return (raw - off) @ s.T @ rot.T


def parse_parameter_file(text) -> dict:
    """Parameters ``name -> value`` from an ArduPilot (``NAME,VALUE`` or ``NAME VALUE``) or a QGroundControl
    (``vehicle component NAME VALUE type``) parameter file; ``#`` lines are comments."""
    params = {}
    for line in str(text).splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        if len(parts) >= 5:
            name, value = parts[2], parts[3]
        elif len(parts) >= 2:
            name, value = parts[0], parts[1]
        else:
            continue
        params[name] = float(value)
    return params
