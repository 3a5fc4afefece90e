"""Right-angle mountings: the 24 proper rotations that permute a sensor's axes (with signs), and the names and
numbers flight controllers store them under.

A sensor bolted to a vehicle with its axes along the vehicle's (but permuted, or pointing backwards) is turned
into the body frame by one of 24 rotation matrices whose entries are 0 and +-1. ArduPilot (``COMPASS_ORIENT``)
and PX4 (``CAL_MAGn_ROT``) store that rotation as a number of the same enumeration (MAVLink's
``MAV_SENSOR_ORIENTATION``): a name ``ROLL_r_PITCH_p_YAW_y`` means ``R = Rz(y) Ry(p) Rx(r)`` (the roll turned
first), and the matrix takes a vector in the sensor's axes into the body frame, ``v_body = R v_sensor``.

:func:`nearest_right_angle` finds the right angle nearest to any rotation and the angle between them (a sensor
mounted 2 deg off its bracket); :func:`firmware_rotation` gives the enumeration's number of a right angle.
"""

from __future__ import annotations

import itertools

import numpy as np
from scipy.spatial.transform import Rotation

from magcal.geometry.procrustes import rotation_angle_deg

#: The firmwares' rotation enumeration (ArduPilot ``enum Rotation``, MAVLink ``MAV_SENSOR_ORIENTATION``, PX4's
#: ``CAL_MAGn_ROT``), the entries that are right angles: number -> (roll, pitch, yaw) in degrees. Numbers that
#: repeat a matrix (26 = 14, 27 = 10) are listed; :func:`firmware_rotation` returns the first.
FIRMWARE_ROTATIONS = {
    0: (0, 0, 0),
    2: (0, 0, 90),
    4: (0, 0, 180),
    6: (0, 0, 270),
    8: (180, 0, 0),
    10: (180, 0, 90),
    12: (0, 180, 0),
    14: (180, 0, 270),
    16: (90, 0, 0),
    18: (90, 0, 90),
    20: (270, 0, 0),
    22: (270, 0, 90),
    24: (0, 90, 0),
    25: (0, 270, 0),
    26: (0, 180, 90),
    27: (0, 180, 270),
    28: (90, 90, 0),
    29: (180, 90, 0),
    30: (270, 90, 0),
    31: (90, 180, 0),
    32: (270, 180, 0),
    33: (90, 270, 0),
    34: (180, 270, 0),
    35: (270, 270, 0),
    36: (90, 180, 90),
    37: (90, 0, 270),
}


def euler_matrix(roll_deg, pitch_deg, yaw_deg) -> np.ndarray:
    """``Rz(yaw) Ry(pitch) Rx(roll)`` (3, 3): the aerospace (ZYX) convention of the firmwares' names."""
    return Rotation.from_euler("ZYX", [yaw_deg, pitch_deg, roll_deg], degrees=True).as_matrix()


def rotation_name(number: int) -> str:
    """``ROLL_90_YAW_270`` for a firmware rotation number (``NONE`` for 0)."""
    roll, pitch, yaw = FIRMWARE_ROTATIONS[number]
    parts = [f"{axis}_{angle}" for axis, angle in (("ROLL", roll), ("PITCH", pitch), ("YAW", yaw)) if angle]
    return "_".join(parts) or "NONE"


def right_angle_rotations() -> np.ndarray:
    """The 24 proper rotations with entries 0 and +-1, shape (24, 3, 3), the identity first."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            m = np.zeros((3, 3))
            m[np.arange(3), perm] = signs
            if np.linalg.det(m) > 0:
                out.append(m)
    out.sort(key=lambda m: -np.trace(m))  # the identity (trace 3) first
    return np.array(out)


RIGHT_ANGLES = right_angle_rotations()


def nearest_right_angle(rotation):
    """The right-angle rotation nearest to ``rotation`` and the angle between them.

    Parameters
    ----------
    rotation : array_like, shape (3, 3)
        A proper rotation (sensor axes -> body frame).

    Returns
    -------
    right_angle : numpy.ndarray, shape (3, 3)
        One of :data:`RIGHT_ANGLES`.
    angle_off_deg : float
        Angle of ``right_angle^T rotation`` (deg): how far the mounting is from that right angle.
    """
    r = np.asarray(rotation, dtype=float)
    traces = np.einsum("kij,ij->k", RIGHT_ANGLES, r)  # trace(A^T R): largest for the nearest
    best = RIGHT_ANGLES[int(np.argmax(traces))]
    return best.copy(), rotation_angle_deg(best.T @ r)


def firmware_rotation(right_angle) -> int | None:
    """The firmware rotation number (ArduPilot ``COMPASS_ORIENT``, PX4 ``CAL_MAGn_ROT``) of a right-angle matrix,
    or None when it has none."""
    m = np.asarray(right_angle, dtype=float)
    for number, angles in FIRMWARE_ROTATIONS.items():
        if np.allclose(euler_matrix(*angles), m, atol=1e-9):
            return number
    return None


def describe_right_angle(right_angle) -> str:
    """``ROLL_180_YAW_90 (rotation 10): sensor x -> body y, y -> body x, z -> body -z`` for a right angle."""
    m = np.rint(np.asarray(right_angle, dtype=float)).astype(int)
    number = firmware_rotation(m)
    axes = []
    for k, a in enumerate("xyz"):
        j = int(np.argmax(np.abs(m[:, k])))
        axes.append(f"{a} -> body {'-' if m[j, k] < 0 else ''}{'xyz'[j]}")
    head = f"{rotation_name(number)} (rotation {number})" if number is not None else "no firmware rotation number"
    return f"{head}: sensor " + ", ".join(axes)


def split_mounting(matrix):
    """``W = R C^-1`` split by a QR decomposition: ``R`` a proper rotation (the mounting), ``C^-1`` upper
    triangular with a positive diagonal (the seed's gauge).

    Parameters
    ----------
    matrix : array_like, shape (3, 3)
        ``W``, with a positive determinant.

    Returns
    -------
    rotation, cinv : numpy.ndarray, shape (3, 3)

    Raises
    ------
    ValueError
        When ``det W <= 0`` (a mirrored axis: no rotation turns it into the frame).
    """
    w = np.asarray(matrix, dtype=float)
    if not np.linalg.det(w) > 0:
        raise ValueError("the matrix mirrors an axis (its determinant is not positive)")
    q, u = np.linalg.qr(w)
    d = np.sign(np.diag(u))
    return q * d[None, :], d[:, None] * u


def mounting_sd_deg(matrix, covariance) -> np.ndarray:
    """Standard deviations (deg) of the mounting's small rotations about the frame's x, y, z axes, from the
    covariance of ``W = R C^-1`` (9 x 9, row by row), carried through the QR split (:func:`split_mounting`) by
    finite differences.

    Parameters
    ----------
    matrix : array_like, shape (3, 3)
        ``W``.
    covariance : array_like, shape (9, 9)
        Its covariance, row by row.
    """
    w = np.asarray(matrix, dtype=float)
    r0, _ = split_mounting(w)
    jac = np.empty((3, 9))
    h = 1e-7 * max(float(np.abs(w).max()), 1e-12)
    for k in range(9):
        dw = np.zeros(9)
        dw[k] = h
        r1, _ = split_mounting(w + dw.reshape(3, 3))
        jac[:, k] = Rotation.from_matrix(r1 @ r0.T).as_rotvec() / h
    return np.degrees(np.sqrt(np.clip(np.diag(jac @ np.asarray(covariance, dtype=float) @ jac.T), 0.0, None)))
