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
``OFS = -A b``. The C header holds the whole ``R C^-1``. Platform terms (eddy currents, field per ampere) are
not written (listed as dropped).
"""

from __future__ import annotations

from dataclasses import dataclass, field

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

#: Export formats and what each writes.
FORMATS = {
    "ardupilot": "ArduPilot parameter file (NAME,VALUE lines: COMPASS_OFS*, COMPASS_DIA*, COMPASS_ODI*, "
    "COMPASS_SCALE*)",
    "px4": "PX4/QGroundControl parameter file (CAL_MAGn_[XYZ]OFF, [XYZ]SCALE, [XYZ]ODIAG)",
    "c": "C header with the correction matrix, offset and formula per sensor",
}

#: nT per unit of the firmwares' magnetometer parameters (ArduPilot milligauss, PX4 gauss).
NT_PER_MILLIGAUSS = 100.0
NT_PER_GAUSS = 1.0e5

#: Length of the offsets (milligauss) above which ArduPilot's arming check may refuse them: the smaller of the
#: defaults of COMPASS_OFFS_MAX seen across versions (1250 and 1800 mG).
ARDUPILOT_OFFSETS_MAX_mG = 1250.0

#: Compass slots each firmware calibrates (ArduPilot COMPASS, COMPASS2, COMPASS3; PX4 CAL_MAG0..3).
MAX_SLOTS = {"ardupilot": 3, "px4": 4, "c": 4}

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

    def firmware_corrected_nT(self, raw_nT) -> np.ndarray:
        """The firmware's corrected field ``S (y - b)`` (nT) for raw readings ``y`` (N, 3) in nT; with a right-angle
        mounting (a vector calibration) ``A S (y - b)``, in the body frame."""
        out = (np.asarray(raw_nT, dtype=float) - self.bias_nT) @ self.matrix.T
        return out if self.right_angle is None else out @ self.right_angle.T


@dataclass
class Export:
    """An export: the text to write, the parameters by name, and what could not be carried."""

    format: str
    text: str
    parameters: dict
    sensors: list
    dropped: list = field(default_factory=list)
    notes: list = field(default_factory=list)


def rotation_angle_deg(rotation) -> float:
    """Angle (deg) of a rotation matrix."""
    cos = (np.trace(np.asarray(rotation, dtype=float)) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


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


def sensor_exports(calibration, sensors=None, slots=None, fmt="c"):
    """Per sensor, the firmware's offset and symmetric matrix and the frame rotation left out.

    Parameters
    ----------
    calibration : Calibration
    sensors : sequence of int, optional
        magcal sensor numbers (1-based) to export; default all.
    slots : sequence of int, optional
        Firmware compass numbers for them (ArduPilot 1-3, PX4 0-3); default sensor ``i`` -> ArduPilot compass
        ``i``, PX4 ``CAL_MAG{i-1}``.
    fmt : str
        The format (for the slot numbering and the number of slots).
    """
    n = calibration.n_sensors
    sensors = list(range(1, n + 1)) if sensors is None else [int(s) for s in sensors]
    for s in sensors:
        if not 1 <= s <= n:
            raise MagcalError(f"--sensor {s}: the calibration has sensor(s) 1 to {n}")
    first = 0 if fmt == "px4" else 1
    if slots is None:
        slots = [s - 1 + first for s in sensors]
    slots = [int(k) for k in slots]
    if len(slots) != len(sensors):
        raise MagcalError("give one --slot per exported sensor")
    last = first + MAX_SLOTS[fmt] - 1
    for s, k in zip(sensors, slots):
        if not first <= k <= last:
            where = (
                "ArduPilot calibrates compasses 1 to 3 (COMPASS_, COMPASS2_, COMPASS3_)"
                if fmt == "ardupilot"
                else "PX4 has CAL_MAG0 to CAL_MAG3"
                if fmt == "px4"
                else "slots 1 to 4"
            )
            raise MagcalError(
                f"sensor {s} would go to slot {k}, but {where}; export it alone with --sensor {s} --slot {first}"
            )
    field_nT = float(calibration.reference_total_nT or 50_000.0)
    out = []
    kept = calibration.sensors_for_new_data()  # a record-only term's kept level (the bias after a step) folded in
    for s, k in zip(sensors, slots):
        cal = kept[s - 1]
        if getattr(calibration, "mode", "scalar") == "vector":
            out.append(_vector_export(cal, s, k, fmt, field_nT))
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


def _vector_export(cal, sensor, slot, fmt, field_nT) -> SensorExport:
    """A vector calibration's sensor: its right-angle mounting as the firmware's orientation, the rest split."""
    w = cal.R @ cal.cinv
    if fmt == "c":  # the header holds the whole matrix
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


def unsupported(calibration, exports) -> list[str]:
    """What magcal's model holds that no firmware parameter can carry, one line each (empty: nothing)."""
    lost = []
    platform = getattr(calibration, "platform", None)
    if platform is not None:
        for name in platform.names:
            lost.append(
                f"platform term {name}: not written (the firmware's motor compensation, COMPASS_MOT_* or "
                "CAL_MAGn_xCOMP, is left as it is); its correction is dropped"
                if name == "current"
                else f"platform term {name}: the firmware has no parameter for it (its correction is dropped)"
            )
    if getattr(calibration, "mode", "scalar") == "vector":
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
    if calibration.model is not None:
        for label in calibration.model.effect_labels:
            lost.append(f"effect {label}: the firmware has no parameter for it (its correction is dropped)")
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


def export_calibration(calibration, fmt, sensors=None, slots=None, force=False, source="calibration") -> Export:
    """The parameters of ``calibration`` for a firmware, or a refusal naming what would be lost.

    Parameters
    ----------
    calibration : Calibration
    fmt : {'ardupilot', 'px4', 'c'}
    sensors, slots : sequence of int, optional
        See :func:`sensor_exports`.
    force : bool
        Export even when effects or misalignments are dropped (they are listed in ``Export.dropped`` and in the
        file's comments).
    source : str
        The calibration's file name, for the file header and messages.

    Raises
    ------
    MagcalError
        Unknown format, bad sensor or slot, or (without ``force``) anything the firmware cannot hold.
    """
    if fmt not in FORMATS:
        raise MagcalError(f"--format {fmt!r}: use one of {', '.join(FORMATS)}")
    exports = sensor_exports(calibration, sensors, slots, fmt)
    dropped = unsupported(calibration, exports)
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
    builder = {"ardupilot": _ardupilot, "px4": _px4, "c": _c_header}[fmt]
    parameters, text = builder(exports, calibration, source, dropped, notes)
    _check_storable(parameters, exports, fmt, source)
    if fmt == "ardupilot":
        for e in exports:
            length = float(np.linalg.norm(e.bias_nT)) / NT_PER_MILLIGAUSS
            if length > ARDUPILOT_OFFSETS_MAX_mG:
                notes.append(
                    f"compass {e.slot}: the offsets are {length:.0f} mG long; ArduPilot's arming check "
                    "refuses offsets longer than COMPASS_OFFS_MAX (1250 or 1800 mG by default): move the "
                    "compass away from the interference, or check the units"
                )
    return Export(fmt, text, parameters, exports, dropped, notes)


#: Largest magnitude the firmwares' parameters (ArduPilot ``AP_Float``, PX4 ``REAL32``) and the C header's
#: ``float`` can hold.
FLOAT32_MAX = float(np.finfo(np.float32).max)


def _check_storable(parameters, exports, fmt, source) -> None:
    """Refuse an export holding a value that is not a finite 32-bit float (NaN, infinite, or beyond
    :data:`FLOAT32_MAX`): the firmware or the compiler would take it for something else, so nothing is written."""
    values = list(parameters.items())
    if fmt == "c":  # the header also holds each sensor's frame rotation
        values += [(f"MAGCAL_S{e.sensor}_FRAME", v) for e in exports for v in np.ravel(e.frame_rotation)]
    for name, value in values:
        if not abs(float(value)) <= FLOAT32_MAX:
            raise MagcalError(
                f"{source}: {name} would be {float(value):g}, which no {fmt} parameter can hold (a finite 32-bit "
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
    for e in exports:
        tag = "" if e.slot == 1 else str(e.slot)
        # ArduPilot rotates the raw reading by COMPASS_ORIENT first: offsets and matrix in the body frame
        a = np.eye(3) if e.right_angle is None else e.right_angle
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
    head = _header_lines(
        calibration,
        source,
        dropped,
        notes,
        "corrected_mG = [DIA_X ODI_X ODI_Y; ODI_X DIA_Y ODI_Z; ODI_Y ODI_Z DIA_Z] "
        "(SCALE (raw_mG + OFS)), OFS in milligauss",
    )
    body = [f"# {line}" for line in head]
    body += [f"# magcal sensor {e.sensor} -> compass {e.slot}" for e in exports]
    body += [f"{name},{_fmt(value)}" for name, value in params.items()]
    return params, "\n".join(body) + "\n"


def _px4(exports, calibration, source, dropped, notes):
    params = {}
    for e in exports:
        pre = f"CAL_MAG{e.slot}_"
        params.update(
            _offset_and_matrix(e.bias_nT / NT_PER_GAUSS, e.matrix, pre + "{}OFF", pre + "{}SCALE", pre + "{}ODIAG")
        )
        if e.rotation_number is not None:
            params[pre + "ROT"] = e.rotation_number
    head = _header_lines(
        calibration,
        source,
        dropped,
        notes,
        "corrected_G = rot ([XSCALE XODIAG YODIAG; XODIAG YSCALE ZODIAG; YODIAG ZODIAG ZSCALE] "
        "(raw_G - [XOFF YOFF ZOFF])), offsets in gauss",
    )
    body = [f"# {line}" for line in head]
    body += [
        f"# magcal sensor {e.sensor} -> CAL_MAG{e.slot} (check that CAL_MAG{e.slot}_ID is that magnetometer)"
        for e in exports
    ]
    body += ["# Vehicle-Id\tComponent-Id\tName\tValue\tType"]
    body += [f"1\t1\t{name}\t{_fmt(value)}\t9" for name, value in params.items()]  # 9: MAV_PARAM_TYPE_REAL32
    return params, "\n".join(body) + "\n"


def _c_header(exports, calibration, source, dropped, notes):
    params = {}
    head = _header_lines(
        calibration, source, dropped, notes, "corrected_nT = MAGCAL_Sn_MATRIX * (raw_nT - MAGCAL_Sn_BIAS_NT)"
    )
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
        rows = ",\n    ".join("{" + ", ".join(f"{_fmt(v)}f" for v in row) + "}" for row in m)
        return [f"static const float {name}[3][3] = {{\n    {rows}\n}};"]

    for e in exports:
        tag = f"MAGCAL_S{e.sensor}"
        lines.append(f"/* magcal sensor {e.sensor} */")
        lines.append(f"static const float {tag}_BIAS_NT[3] = {{" + ", ".join(f"{_fmt(v)}f" for v in e.bias_nT) + "};")
        lines += matrix(f"{tag}_MATRIX", e.matrix)
        lines += matrix(f"{tag}_FRAME", e.frame_rotation)
        lines.append("")
        for k, axis in enumerate("xyz"):
            params[f"{tag}_BIAS_NT_{axis}"] = float(e.bias_nT[k])
        for i in range(3):
            for j in range(3):
                params[f"{tag}_MATRIX_{i}{j}"] = float(e.matrix[i, j])
    lines += ["#endif /* MAGCAL_CALIBRATION_H */", ""]
    return params, "\n".join(lines)


def apply_ardupilot(parameters, raw_mG, slot=1) -> np.ndarray:
    """ArduPilot's correction of raw readings (milligauss) with exported parameters, as
    ``AP_Compass_Backend::correct_field`` does it (motor compensation off): ``M (SCALE (raw + OFS))``, the raw
    reading first turned by ``COMPASS_ORIENT`` when the parameters hold one (a right angle of
    :data:`magcal.geometry.orientations.FIRMWARE_ROTATIONS`).

    Returns the corrected field (N, 3) in milligauss.
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
    if orient is not None:
        raw = raw @ euler_matrix(*FIRMWARE_ROTATIONS[int(orient)]).T
    return (scale * (raw + ofs)) @ m.T


def apply_px4(parameters, raw_G, slot=0, rotation=None) -> np.ndarray:
    """PX4's correction of raw readings (gauss) with exported parameters, as ``calibration::Magnetometer::
    Correct`` does it (power compensation off): ``rot (S (raw - OFF))``, ``rot`` the given matrix, else
    ``CAL_MAGn_ROT`` when the parameters hold one. Returns (N, 3) gauss."""
    pre = f"CAL_MAG{slot}_"
    p = parameters
    off = np.array([p[f"{pre}{a}OFF"] for a in "XYZ"])
    d = np.array([p[f"{pre}{a}SCALE"] for a in "XYZ"])
    o = np.array([p[f"{pre}{a}ODIAG"] for a in "XYZ"])
    s = np.array([[d[0], o[0], o[1]], [o[0], d[1], o[2]], [o[1], o[2], d[2]]])
    if rotation is None and p.get(f"{pre}ROT") is not None and int(p[f"{pre}ROT"]) in FIRMWARE_ROTATIONS:
        rotation = euler_matrix(*FIRMWARE_ROTATIONS[int(p[f"{pre}ROT"])])
    rot = np.eye(3) if rotation is None else np.asarray(rotation, dtype=float)
    return (np.asarray(raw_G, dtype=float) - off) @ s.T @ rot.T


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
