"""Motion seen by the page: how fast the instrument turns (for marking samples taken while turning fast) and the
*tilt ring*, the field directions a yaw sweep at the current tilt would visit.

Only display: nothing here changes what is fitted (a marked sample is fitted unless the user excludes it).

The tilt ring
-------------
The Earth field is fixed in the world frame (north, east, down; :mod:`magcal.core.conventions`). A platform at
attitude ``R = Rz(yaw) R_tilt`` (``R`` takes array-frame vectors into the world frame, ``R_tilt = Ry(pitch)
Rx(roll)``) sees the field ``b = R^T f``. Turning in yaw only, at the current roll and pitch, it sees

    ``b(beta) = R_tilt^T Rz(beta)^T f = |f| R_tilt^T (cos I cos beta, cos I sin beta, sin I)``,  ``beta`` in [0, 2 pi)

with ``I`` the field's inclination: a circle on the sphere of directions, about the array-frame vertical
``R_tilt^T e_down`` at the angle ``90 deg - I`` from it. The declination does not enter (a yaw sweep visits every
heading), so the ring needs the attitude's roll and pitch and the field's inclination only. The inclination is
taken from the data themselves: the sample directions turned into the world frame by their attitudes
(:func:`inclination_from_data`), which needs no location or field model.

Without attitude the array-frame vertical is unknown and no single sample says where the ring lies. What the data
do show: during a yaw sweep at constant tilt the directions just seen lie on that very circle, so a plane fitted to
the latest directions (:func:`ring_from_directions`) *is* the ring, when they do lie on a plane and spread along an
arc. When the latest motion was not such a sweep (they fit no plane, or cover too short an arc) no ring is drawn:
drawing one then would show a circle the instrument is not on.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from magcal.data.attitude import turn_rate_dps

#: Above this rate (deg/s) a sample is marked as taken while turning fast. A sensor whose axes (or whose readings
#: and their time stamps) are sampled ``dt`` apart sees an error of about ``omega dt F``: at 60 deg/s, 1 ms and
#: 50 000 nT that is 52 nT, far above a fluxgate's noise.
FAST_TURN_DPS = 60.0
#: Points drawn per ring.
RING_POINTS = 96
#: A plane through the latest directions is taken as the ring when their RMS distance from it is below this
#: (unit-sphere units, ~3 deg) ...
RING_PLANARITY = 0.05
#: ... and they spread along an arc of at least this many degrees.
RING_MIN_ARC_DEG = 40.0


#: The last dataset's turn rate: a :class:`~magcal.data.dataset.Dataset` never changes (its arrays are read-only),
#: and every redraw of the page asks again (0.5 s for 1e6 attitudes).
_last_rate: tuple = (None, None)


def fast_turning(dataset, limit_dps: float = FAST_TURN_DPS) -> np.ndarray | None:
    """Samples taken while turning faster than ``limit_dps`` (bool, N), or None without gyro or attitude."""
    global _last_rate
    seen, rate = _last_rate
    if seen is not dataset:
        rate = turn_rate_dps(dataset)
        _last_rate = (dataset, rate)
    if rate is None:
        return None
    fast = np.asarray(rate > float(limit_dps))
    fast.flags.writeable = False
    return fast


def _rotations(attitude_wxyz) -> Rotation:
    return Rotation.from_quat(np.asarray(attitude_wxyz, float).reshape(-1, 4)[:, [1, 2, 3, 0]])


def inclination_from_data(directions, attitude_wxyz) -> float:
    """The field's inclination (rad, positive down) from sample directions (array frame, (N, 3)) and their
    attitudes: the mean of the directions turned into the world frame (north, east, down)."""
    u = np.asarray(directions, float)
    u = u / np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-12)
    w = _rotations(attitude_wxyz).apply(u).mean(axis=0)
    return float(np.arctan2(w[2], np.hypot(w[0], w[1])))


def tilt_ring(attitude_wxyz, inclination_rad: float, n_points: int = RING_POINTS) -> np.ndarray:
    """Unit directions (array frame, (n_points, 3)) a yaw sweep at this attitude's roll and pitch would see (see
    the module's docstring): ``R_tilt^T (cos I cos beta, cos I sin beta, sin I)``."""
    r = _rotations(attitude_wxyz)[0]
    yaw = r.as_euler("ZYX")[0]
    tilt = Rotation.from_euler("Z", -yaw) * r  # R = Rz(yaw) R_tilt
    beta = np.linspace(0.0, 2 * np.pi, int(n_points), endpoint=False)
    c = np.cos(inclination_rad)
    world = np.column_stack([c * np.cos(beta), c * np.sin(beta), np.full_like(beta, np.sin(inclination_rad))])
    return tilt.inv().apply(world)


def ring_from_directions(directions, n_points: int = RING_POINTS) -> np.ndarray | None:
    """The circle on the unit sphere that the latest directions (array frame, (N, 3)) lie on, or None when they
    lie on none (see the module's docstring): the plane ``n . u = c`` fitted by least squares (the smallest
    principal axis of the directions), accepted when their RMS distance from it is below :data:`RING_PLANARITY`
    and they span an arc of :data:`RING_MIN_ARC_DEG` or more about its axis."""
    u = np.asarray(directions, float)
    u = u[np.all(np.isfinite(u), axis=1)]
    if len(u) < 10:
        return None
    u = u / np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-12)
    centre = u.mean(axis=0)
    _, s, vt = np.linalg.svd(u - centre, full_matrices=False)
    n = vt[2]
    c = float(centre @ n)
    if abs(c) >= 0.98 or s[2] / np.sqrt(len(u)) > RING_PLANARITY:
        return None
    a, b = vt[0], vt[1]
    radius = np.sqrt(1.0 - c * c)
    angles = np.arctan2((u - c * n) @ b, (u - c * n) @ a)
    # the arc covered: 360 deg less the largest gap between the sorted angles
    srt = np.sort(angles)
    gaps = np.diff(np.concatenate([srt, [srt[0] + 2 * np.pi]]))
    if np.degrees(2 * np.pi - gaps.max()) < RING_MIN_ARC_DEG:
        return None
    beta = np.linspace(0.0, 2 * np.pi, int(n_points), endpoint=False)
    return c * n + radius * (np.cos(beta)[:, None] * a + np.sin(beta)[:, None] * b)
