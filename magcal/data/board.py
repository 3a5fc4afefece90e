"""A simulated board: a magnetometer beside an accelerometer, tumbled by hand with still moments.

A hand turns the board from one attitude to the next (smooth turns of about a second, with the hand's own
acceleration) and holds it still for a second or two at each: a phone, a flight controller or a cave-survey
instrument calibrated the way their users do it. The board's frame is the accelerometer's corrected frame
(``x`` forward, ``y`` right, ``z`` down when level); the magnetometer sits in it turned by ``mounting``
(a right angle, e.g. a part whose axes differ from the accelerometer's, times a small error of assembly)::

    y = C R_m^T B_board + b + n_m,                 B_board = R(q)^T B_ned
    a = K f_board + b_a + n_a,                     f_board = R(q)^T (a_hand - g_ned)

with ``C`` the magnetometer's scale, non-orthogonality and soft iron (``C^-1`` upper triangular, so that the
mounting is exactly what a calibration's ``R`` finds), ``b`` its bias with the board's hard iron, ``K`` and ``b_a``
the accelerometer's scale (``K^-1`` upper triangular: the accelerometer's own frame is the board's) and bias,
``g_ned = (0, 0, g)``. The gyro reads the body's turn rate (deg/s) with its noise. Optionally the magnetometer's
samples lag the accelerometer's (``mag_delay_s``: a timing offset between the two sensors) and a temperature
moves the magnetometer's bias.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from magcal.data.accelerometer import STANDARD_GRAVITY_M_S2
from magcal.data.dataset import Dataset

#: A right-angle mounting some boards have between their magnetometer and accelerometer axes (the magnetometer's x
#: and y swapped, its z reversed: ``x -> y, y -> x, z -> -z``).
SWAPPED_MOUNTING = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


def field_ned_nT(total_nT=48_700.0, inclination_deg=64.0, declination_deg=3.0) -> np.ndarray:
    """The Earth's field vector (north, east, down; nT) of a total field, an inclination and a declination."""
    inc, dec = np.radians(inclination_deg), np.radians(declination_deg)
    return total_nT * np.array([np.cos(inc) * np.cos(dec), np.cos(inc) * np.sin(dec), np.sin(inc)])


@dataclass
class BoardTruth:
    """What :func:`simulate_board` hid in the data.

    Attributes
    ----------
    mag_matrix : numpy.ndarray, shape (3, 3)
        ``C`` of the magnetometer (``C^-1`` upper triangular).
    mag_bias_nT : numpy.ndarray, shape (3,)
        Bias with the board's hard iron, nT.
    mounting : numpy.ndarray, shape (3, 3)
        ``R_m``: the magnetometer's corrected axes -> the board's (the accelerometer's) axes.
    accel_matrix : numpy.ndarray, shape (3, 3)
        ``K`` of the accelerometer (``K^-1`` upper triangular).
    accel_bias_m_s2 : numpy.ndarray, shape (3,)
    field_ned_nT : numpy.ndarray, shape (3,)
    mag_noise_nT, accel_noise_m_s2 : float
        Noise per axis (1 sigma).
    temperature_bias_nT_per_C : numpy.ndarray, shape (3,), or None
        The magnetometer's bias per degree of temperature, when the record has a temperature.
    """

    mag_matrix: np.ndarray
    mag_bias_nT: np.ndarray
    mounting: np.ndarray
    accel_matrix: np.ndarray
    accel_bias_m_s2: np.ndarray
    field_ned_nT: np.ndarray
    mag_noise_nT: float = 150.0
    accel_noise_m_s2: float = 0.03
    temperature_bias_nT_per_C: np.ndarray | None = None

    @property
    def inclination_deg(self) -> float:
        n, e, d = self.field_ned_nT
        return float(np.degrees(np.arctan2(d, np.hypot(n, e))))

    @property
    def declination_deg(self) -> float:
        return float(np.degrees(np.arctan2(self.field_ned_nT[1], self.field_ned_nT[0])))


@dataclass
class BoardRecord:
    """The true motion behind a simulated record (per sample).

    Attributes
    ----------
    attitude : scipy.spatial.transform.Rotation
        Board -> north-east-down, at the accelerometer's sample times.
    still : numpy.ndarray of bool, shape (N,)
        The samples taken while the hand held the board still.
    heading_deg : numpy.ndarray, shape (N,)
        The true magnetic heading of the board's ``x`` axis (deg, [0, 360)).
    """

    attitude: Rotation
    still: np.ndarray
    heading_deg: np.ndarray


def board_truth(
    mounting=None,
    off_deg=2.0,
    field_nT=48_700.0,
    inclination_deg=64.0,
    declination_deg=3.0,
    hard_iron_nT=15_000.0,
    soft_iron=0.05,
    accel_bias_g=0.03,
    accel_scale=0.02,
    mag_noise_nT=150.0,
    accel_noise_g=0.003,
    seed=0,
) -> BoardTruth:
    """Random but plausible parameters of a MEMS board (the same seed gives the same truth).

    Parameters
    ----------
    mounting : array_like, shape (3, 3), optional
        The right angle between the magnetometer's axes and the accelerometer's (default the identity).
    off_deg : float
        The magnetometer is turned this far (deg) from ``mounting`` about a random axis.
    field_nT, inclination_deg, declination_deg : float
        The Earth's field.
    hard_iron_nT : float
        Scale (1 sigma per axis) of the magnetometer's bias with the board's hard iron, nT.
    soft_iron : float
        Scale of the off-diagonal (and the diagonal's departure from 1) of ``C^-1``.
    accel_bias_g, accel_scale : float
        Scale of the accelerometer's bias (g) and of its gain errors and non-orthogonality.
    mag_noise_nT, accel_noise_g : float
        Noise per axis (1 sigma).
    seed : int
    """
    rng = np.random.default_rng(seed)
    base = np.eye(3) if mounting is None else np.asarray(mounting, dtype=float)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    r_m = base @ Rotation.from_rotvec(np.radians(off_deg) * axis).as_matrix()
    cinv = np.eye(3) + np.triu(rng.normal(0.0, soft_iron, (3, 3)), 1)
    cinv[np.diag_indices(3)] = 1.0 + rng.normal(0.0, soft_iron, 3)
    kinv = np.eye(3) + np.triu(rng.normal(0.0, 0.2 * accel_scale, (3, 3)), 1)
    kinv[np.diag_indices(3)] = 1.0 + rng.normal(0.0, accel_scale, 3)
    return BoardTruth(
        mag_matrix=np.linalg.inv(cinv),
        mag_bias_nT=rng.normal(0.0, hard_iron_nT, 3),
        mounting=r_m,
        accel_matrix=np.linalg.inv(kinv),
        accel_bias_m_s2=rng.normal(0.0, accel_bias_g * STANDARD_GRAVITY_M_S2, 3),
        field_ned_nT=field_ned_nT(field_nT, inclination_deg, declination_deg),
        mag_noise_nT=float(mag_noise_nT),
        accel_noise_m_s2=float(accel_noise_g * STANDARD_GRAVITY_M_S2),
    )


def _poses(rng, n_poses, max_tilt_deg) -> Rotation:
    """Random attitudes: yaw uniform, the board's z axis within ``max_tilt_deg`` of down (180: any attitude)."""
    if max_tilt_deg >= 180:
        return Rotation.random(n_poses, random_state=rng)
    yaw = rng.uniform(0.0, 360.0, n_poses)
    cos_max = np.cos(np.radians(max_tilt_deg))
    tilt = np.degrees(np.arccos(rng.uniform(cos_max, 1.0, n_poses)))  # even over the cap of directions
    azimuth = rng.uniform(0.0, 2 * np.pi, n_poses)
    axis = np.column_stack([np.cos(azimuth), np.sin(azimuth), np.zeros(n_poses)])
    return Rotation.from_rotvec(np.radians(tilt)[:, None] * axis) * Rotation.from_euler("z", yaw[:, None], degrees=True)


def simulate_board(
    truth: BoardTruth | None = None,
    n_poses=40,
    rate_hz=50.0,
    still_s=(1.0, 2.5),
    move_s=(0.6, 1.4),
    hand_accel_m_s2=2.0,
    tremor_m_s2=0.0,
    max_tilt_deg=180.0,
    gyro_noise_dps=0.3,
    mag_delay_s=0.0,
    temperature_C=None,
    seed=0,
    **truth_options,
) -> tuple[Dataset, BoardTruth, BoardRecord]:
    """A hand-tumbled board's record.

    Parameters
    ----------
    truth : BoardTruth, optional
        Default :func:`board_truth` with ``seed`` and ``truth_options``; give the same truth to two calls with
        different seeds for a calibration record and a held-out one.
    n_poses : int
        Attitudes the hand holds still.
    rate_hz : float
        Sample rate (Hz) of both sensors.
    still_s, move_s : (float, float)
        Ranges (s) of the still moments and of the turns between them.
    hand_accel_m_s2 : float
        Peak acceleration of the hand during a turn (m/s^2).
    tremor_m_s2 : float
        RMS per axis of a hand's tremor (m/s^2), all the time: random accelerations smoothed over 0.1 s (a board
        waved without pause, or held by an unsteady hand).
    max_tilt_deg : float
        Largest tilt of the poses (180: any attitude; 30: a board that is only tipped).
    gyro_noise_dps : float
        Gyro noise per axis (deg/s).
    mag_delay_s : float
        The magnetometer's samples are this much older than the accelerometer's (s).
    temperature_C : (float, float), optional
        A temperature rising linearly from the first to the second value over the record, moving the
        magnetometer's bias by ``truth.temperature_bias_nT_per_C`` (default 40 nT/degC per axis).
    seed : int

    Returns
    -------
    dataset : Dataset
        Readings (nT), ``time_s``, extra columns ``ax, ay, az`` (m/s^2, ``accel_units: m/s^2``) and ``gx_dps, gy_dps,
        gz_dps``, with ``temperature_C`` when asked for.
    truth : BoardTruth
    record : BoardRecord
    """
    truth = board_truth(seed=seed, **truth_options) if truth is None else truth
    rng = np.random.default_rng(seed + 20_000)
    poses = _poses(rng, n_poses, max_tilt_deg)
    keys_t, keys_q, still_spans = [], [], []
    t = 0.0
    for k in range(n_poses):
        hold = rng.uniform(*still_s)
        keys_t += [t, t + hold]
        keys_q += [poses[k], poses[k]]
        still_spans.append((t, t + hold))
        t += hold + rng.uniform(*move_s)
    end = keys_t[-1]
    times = np.arange(0.0, end, 1.0 / rate_hz)
    n = times.size
    key_times = np.array(keys_t)
    # smooth turns: a slerp whose progress follows a raised cosine between each still moment and the next
    segment = np.clip(np.searchsorted(key_times, times, side="right") - 1, 0, len(keys_t) - 2)
    t0, t1 = key_times[segment], key_times[segment + 1]
    frac = np.where(t1 > t0, (times - t0) / np.where(t1 > t0, t1 - t0, 1.0), 0.0)
    smooth = 0.5 - 0.5 * np.cos(np.pi * np.clip(frac, 0.0, 1.0))
    slerp_t = np.arange(len(keys_t), dtype=float)
    all_q = Rotation.concatenate(keys_q)
    attitude = Slerp(slerp_t, all_q)(segment + smooth)
    still = segment % 2 == 0  # even segments hold a pose
    moving = ~still
    # the hand's acceleration: a smooth push and pull along a random direction during each turn
    hand = np.zeros((n, 3))
    for s in np.unique(segment[moving]):
        rows = segment == s
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        hand[rows] = hand_accel_m_s2 * np.sin(2 * np.pi * smooth[rows])[:, None] * direction
    if tremor_m_s2 > 0:
        width = max(int(round(0.1 * rate_hz)), 1)
        kernel = np.ones(width) / width
        shake = np.column_stack([np.convolve(rng.normal(size=n), kernel, mode="same") for _ in range(3)])
        hand += tremor_m_s2 * shake / np.sqrt(np.mean(shake**2, axis=0))
    g_ned = np.array([0.0, 0.0, STANDARD_GRAVITY_M_S2])
    f_board = attitude.inv().apply(hand - g_ned)
    accel = f_board @ truth.accel_matrix.T + truth.accel_bias_m_s2 + rng.normal(0.0, truth.accel_noise_m_s2, (n, 3))
    if mag_delay_s:
        mag_attitude = Slerp(slerp_t, all_q)(np.interp(times - mag_delay_s, times, segment + smooth))
    else:
        mag_attitude = attitude
    b_board = mag_attitude.inv().apply(truth.field_ned_nT)
    readings = b_board @ (truth.mag_matrix @ truth.mounting.T).T + truth.mag_bias_nT
    temperature = None
    if temperature_C is not None:
        temp = np.linspace(float(temperature_C[0]), float(temperature_C[1]), n)
        if truth.temperature_bias_nT_per_C is None:
            truth.temperature_bias_nT_per_C = np.full(3, 40.0)
        readings = readings + (temp - temp[0])[:, None] * truth.temperature_bias_nT_per_C
        temperature = temp
    readings = readings + rng.normal(0.0, truth.mag_noise_nT, (n, 3))
    dq = attitude[:-1].inv() * attitude[1:]  # the body's turn between samples, in body axes
    rate = np.degrees(dq.as_rotvec()) * rate_hz
    rate = np.vstack([rate, rate[-1:]]) + rng.normal(0.0, gyro_noise_dps, (n, 3))
    extra = {
        "ax": accel[:, 0],
        "ay": accel[:, 1],
        "az": accel[:, 2],
        "gx_dps": rate[:, 0],
        "gy_dps": rate[:, 1],
        "gz_dps": rate[:, 2],
    }
    ds = Dataset(
        readings_nT=readings[None],
        time_s=times,
        extra=extra,
        metadata={"accel_units": "m/s^2", "simulated": "hand-tumbled board (magcal.data.board)"},
        source="simulated board",
        temperature_C=temperature,
    )
    down_x = attitude.apply(np.array([1.0, 0.0, 0.0]))
    heading = (np.degrees(np.arctan2(down_x[:, 1], down_x[:, 0])) - truth.declination_deg) % 360.0
    return ds, truth, BoardRecord(attitude, still, heading)
