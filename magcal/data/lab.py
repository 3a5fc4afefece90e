"""A simulated lab record: a sensor turned by hand under motion capture, in a field of unknown vector.

The sensor (:func:`magcal.data.vehicle.vehicle_truth`: scale, non-orthogonality, soft and hard iron, a mounting
off a right angle) is carried along a path at a walking pace and turned, either through every direction
(``motion="tumble"``) or about the vertical only (``"yaw"``, a turntable); the optical attitude carries an error,
and the positions (``pos_n_m, pos_e_m, pos_d_m``, m, north-east-down) are recorded. The field is the lab's constant
``B_w`` plus, optionally, a uniform gradient ``G`` and a magnet near the path (a point dipole)::

    y = C R_m^T Q_t^T (B_w + G p_t + B_dip(p_t)) + b + n,     B_dip(p) = 100 (3 (m . r) r / |r|^5 - m / |r|^3)  nT

with ``r = p - p_dip`` in m and the moment ``m`` in A m^2 (``mu0 / 4 pi = 1e-7 T m / A`` is 100 nT m^3 per A m^2).
The dataset holds no field vector: the lab's is what a calibration with ``reference="fitted"`` finds.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from magcal.data.dataset import Dataset
from magcal.data.vehicle import VehicleTruth, vehicle_truth

#: nT m^3 per A m^2: ``mu0 / 4 pi`` in the units of :func:`dipole_field_nT`.
DIPOLE_NT_M3_PER_AM2 = 100.0


def lab_truth(seed=0, field_ned_nT=(19_500.0, 600.0, 45_000.0), **options) -> VehicleTruth:
    """A sensor of :func:`magcal.data.vehicle.vehicle_truth` whose gains' geometric mean is 1 (``det C^-1 = 1``: a
    sensor whose overall gain is right, the gauge a fit without a total field takes)."""
    truth = vehicle_truth(seed=seed, field_ned_nT=field_ned_nT, **options)
    for s in truth.sensors:
        s.matrix = s.matrix / np.linalg.det(s.matrix) ** (1.0 / 3.0)
    return truth


def dipole_field_nT(positions_m, where_m, moment_Am2) -> np.ndarray:
    """The field (N, 3) in nT of a point dipole at ``where_m`` (m; (3,) or one place per position, (N, 3)) of moment
    ``moment_Am2`` (A m^2), all NED (or all in one other frame)."""
    r = np.asarray(positions_m, dtype=float) - np.asarray(where_m, dtype=float)
    m = np.asarray(moment_Am2, dtype=float)
    dist = np.linalg.norm(r, axis=1)[:, None]
    return DIPOLE_NT_M3_PER_AM2 * (3.0 * r * (r @ m)[:, None] / dist**5 - m / dist**3)


def simulate_lab(
    truth=None,
    n=3000,
    rate_hz=50.0,
    motion="tumble",
    attitude_noise_deg=1.0,
    noise_nT=5.0,
    dipole=None,
    seed=0,
    tilt_deg=3.0,
    gradient_ned_nT_per_m=None,
    turns=1.0,
    carried_dipole=None,
):
    """A lab record: readings, optical attitude, positions; no field vector.

    Parameters
    ----------
    truth : VehicleTruth, optional
        The sensor and the lab's field (default :func:`lab_truth` with ``seed``); give the same one to two calls
        for a calibration record and the next record.
    n, rate_hz : int, float
        Samples and sample rate (Hz).
    motion : {"tumble", "yaw"}
        Turned through every direction, or about the vertical only (a turntable, or a hand that keeps the sensor
        nearly level: its tilts within ``tilt_deg``).
    attitude_noise_deg : float
        The optical attitude's error per axis (deg, 1 sigma, white).
    noise_nT : float
        Sensor noise per axis (nT).
    dipole : tuple, optional
        ``(where_m, moment_Am2)``: a magnet near the path (NED, m; A m^2). The path runs along north through the
        origin, within 0.05 m of the north axis.
    seed : int
    tilt_deg : float
        With ``motion="yaw"``: the tilts' amplitude (deg) about north and east.
    gradient_ned_nT_per_m : array_like, shape (3, 3), optional
        A uniform gradient of the field (nT/m, symmetric and traceless): ``B_w + G p`` at the position ``p``.
    turns : float
        How many times faster the hand turns the sensor than the default (two turns in yaw over the record, a few
        swings in pitch and roll: about 30 deg/s over 60 s); 4 is a hand-held tumble of about 100 deg/s.
    carried_dipole : tuple, optional
        ``(start_m, end_m, moment_Am2)``: a magnet carried with the sensor (in the sensor's axes, m; its moment in
        them, A m^2), moved in a straight line from ``start_m`` to ``end_m`` over the record (toward or away): its
        field at the sensor is an offset in the sensor's axes that changes as the magnet is moved, not a field of
        the lab.

    Returns
    -------
    dataset : Dataset
        ``time_s``, ``attitude_wxyz`` (measured, body -> NED), extra ``pos_n_m, pos_e_m, pos_d_m`` (m).
    truth : VehicleTruth
    """
    truth = lab_truth(seed=seed) if truth is None else truth
    rng = np.random.default_rng(seed + 20_000)
    t = np.arange(n) / rate_hz
    span = n / rate_hz
    ph = rng.uniform(0, 2 * np.pi, 8)
    turn = span / float(turns)  # the hand's motion repeats its pattern ``turns`` times faster
    yaw = 360.0 * 2 * t / turn + 40.0 * np.sin(2 * np.pi * t / (turn / 3.1) + ph[0])
    if motion == "tumble":
        pitch = 75.0 * np.sin(2 * np.pi * t / (turn / 2.3) + ph[1])
        roll = 180.0 * np.sin(2 * np.pi * t / (turn / 1.7) + ph[2])
    elif motion == "yaw":
        pitch = tilt_deg * np.sin(2 * np.pi * t / (turn / 2.3) + ph[1])
        roll = tilt_deg * np.sin(2 * np.pi * t / (turn / 1.7) + ph[2])
    else:
        raise ValueError(f"motion must be 'tumble' or 'yaw', got {motion!r}")
    true_att = Rotation.from_euler("ZYX", np.column_stack([yaw, pitch, roll]), degrees=True)
    measured = true_att * Rotation.from_rotvec(rng.normal(0.0, np.radians(attitude_noise_deg), (n, 3)))
    walk = 2 * np.pi * t / (span / 4.0)
    positions = np.column_stack(
        [
            0.5 * np.sin(walk + ph[3]),
            0.05 * np.sin(2 * np.pi * t / (span / 5.3) + ph[4]),
            0.05 * np.sin(2 * np.pi * t / (span / 6.7) + ph[5]),
        ]
    )
    world = np.tile(truth.field_ned_nT, (n, 1))
    if dipole is not None:
        world = world + dipole_field_nT(positions, *dipole)
    if gradient_ned_nT_per_m is not None:
        world = world + positions @ np.asarray(gradient_ned_nT_per_m, dtype=float).T
    b_body = true_att.inv().apply(world)
    if carried_dipole is not None:
        start, end, moment = (np.asarray(v, dtype=float) for v in carried_dipole)
        along = (t - t[0]) / max(t[-1] - t[0], 1e-12)
        magnet = start + along[:, None] * (end - start)  # in the sensor's axes, m
        b_body = b_body + dipole_field_nT(np.zeros_like(magnet), magnet, moment)  # the sensor at its axes' origin
    readings = []
    for s in truth.sensors:
        readings.append(b_body @ (s.matrix @ s.mounting.T).T + s.bias_nT + rng.normal(0.0, noise_nT, (n, 3)))
    q = measured.as_quat()
    ds = Dataset(
        readings_nT=np.array(readings),
        time_s=t,
        attitude_wxyz=np.column_stack([q[:, 3], q[:, :3]]),
        extra={name: positions[:, k] for k, name in enumerate(("pos_n_m", "pos_e_m", "pos_d_m"))},
        source=f"simulated lab ({motion})",
    )
    tq = true_att.as_quat()
    out = VehicleTruth(
        truth.field_ned_nT, truth.sensors, np.column_stack([tq[:, 3], tq[:, :3]]), float(noise_nT), attitude_noise_deg
    )
    return ds, out
