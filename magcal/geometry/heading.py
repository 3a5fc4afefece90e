"""The tilt-compensated compass: heading, dip and tilt from an accelerometer and a magnetometer.

Frames. The board's (the accelerometer's) axes: ``x`` forward, ``y`` right, ``z`` down when level. A still
accelerometer reads the specific force, ``+g`` up, so down is ``d = -a / |a|``. With ``m`` the field in the same
axes::

    east  = d x m / |d x m|,    north = east x d,    heading = atan2(east_x, north_x)

is the magnetic heading of the board's ``x`` axis (deg, clockwise from magnetic north, in [0, 360)), whatever the
tilt, and ``dip = asin(m . d / |m|)`` is the field's inclination as the board measures it (deg, positive down):
the same in every attitude. A tilt error ``e`` (the accelerometer's, or the magnetometer's rotation from it) turns
the vertical field into the horizontal one: a heading error of about ``e tan(I)`` (``I`` the inclination: 1 deg of
misalignment is 2 deg of heading at 64 deg of inclination). The functions take arrays of shape (..., 3) in any
units (the directions matter).
"""

from __future__ import annotations

import numpy as np


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        return v / np.linalg.norm(v, axis=-1, keepdims=True)


def tilt_heading_deg(accel, field) -> np.ndarray:
    """Tilt-compensated magnetic heading (deg, [0, 360)) of the board's ``x`` axis.

    Parameters
    ----------
    accel : array_like, shape (..., 3)
        Specific force (up when still), any unit.
    field : array_like, shape (..., 3)
        The magnetic field in the same axes, any unit.

    Returns
    -------
    numpy.ndarray, shape (...)
        NaN where either vector is missing.
    """
    down = -_unit(accel)
    east = _unit(np.cross(down, np.asarray(field, dtype=float)))
    north = np.cross(east, down)
    return np.degrees(np.arctan2(east[..., 0], north[..., 0])) % 360.0


def dip_deg(accel, field) -> np.ndarray:
    """The angle of the field below the horizontal (deg, positive down), from the accelerometer's down."""
    s = np.sum(-_unit(accel) * _unit(field), axis=-1)
    return np.degrees(np.arcsin(np.clip(s, -1.0, 1.0)))


def tilt_deg(accel) -> np.ndarray:
    """The board's tilt (deg): the angle between its ``z`` axis and down."""
    return np.degrees(np.arccos(np.clip(-_unit(accel)[..., 2], -1.0, 1.0)))


def angle_difference_deg(a, b) -> np.ndarray:
    """``a - b`` (deg) wrapped into [-180, 180)."""
    return (np.asarray(a, dtype=float) - np.asarray(b, dtype=float) + 180.0) % 360.0 - 180.0


def heading_noise_deg(accel_noise_rad, field_noise_fraction, inclination_deg) -> float:
    """Heading error per sample (deg, 1 sigma) from the sensors' noise at an inclination.

    Parameters
    ----------
    accel_noise_rad : float
        The accelerometer's direction error per axis (rad): its noise per axis over ``g``.
    field_noise_fraction : float
        The magnetometer's noise per axis over the total field.
    inclination_deg : float

    Returns
    -------
    float
        ``sqrt((e_a tan I)^2 + (e_m / cos I)^2)`` in deg: a tilt error about the north axis moves the vertical field
        into the east component (``tan I``); the magnetometer's east noise against the horizontal field
        (``1 / cos I``).
    """
    inc = np.radians(float(inclination_deg))
    return float(
        np.degrees(np.hypot(accel_noise_rad * np.tan(abs(inc)), field_noise_fraction / max(np.cos(inc), 1e-6)))
    )
