"""Simulated magnetometer data whose true errors are known.

The forward model per sensor ``i`` (conventions in :mod:`magcal.core.conventions`) is::

    B_i   = M_i R_att^T B_world            field in sensor i's ideal frame (M_i: misalignment)
    y_i   = C_i ((I + S_soft) B_i + B_hard) + b_i + n

with ``C_i = S C_NO`` (or an explicit matrix), platform soft iron ``S_soft`` and hard iron ``B_hard`` (Ding 2024,
eqs. 7-8), bias ``b_i`` and noise ``n`` (Gaussian with ``sigma`` per axis, or uniform of full width ``a``).

Two ways of visiting attitudes:

* :func:`simulate` with random uniform attitudes (the seeds' simulations), and
* :func:`simulate_timeseries`, a smooth rotation trajectory that covers the direction sphere, with time and a
  temperature channel; ``perturbations`` are callables that change the readings with the ground truth at hand,
  which is how hidden effects are added.

Presets are registered in :data:`PRESETS` by name (``chi2017``: Chi et al. 2017, Table 1).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from magcal.core import conventions
from magcal.data.dataset import Dataset


@dataclass
class SensorErrors:
    """True error parameters of one triaxial sensor.

    Parameters
    ----------
    scale : array_like, shape (3,)
        Scale factors ``k_x, k_y, k_z`` (dimensionless).
    psi, phi, theta : float
        Non-orthogonality angles in rad (eq. 2).
    bias_nT : array_like, shape (3,)
        Bias (zero offset) in nT.
    alpha, beta, gamma : float
        Misalignment angles in rad relative to the array frame (eq. 3).
    hard_iron_nT : array_like, shape (3,)
        Platform hard iron in nT (constant field in the sensor's ideal frame).
    soft_iron : array_like, shape (3, 3)
        Platform soft iron (dimensionless induced-field matrix ``S``).
    matrix : array_like, shape (3, 3), optional
        Explicit sensor matrix ``C``; overrides ``scale`` and the non-orthogonality angles.
    """

    scale: np.ndarray = field(default_factory=lambda: np.ones(3))
    psi: float = 0.0
    phi: float = 0.0
    theta: float = 0.0
    bias_nT: np.ndarray = field(default_factory=lambda: np.zeros(3))
    alpha: float = 0.0
    beta: float = 0.0
    gamma: float = 0.0
    hard_iron_nT: np.ndarray = field(default_factory=lambda: np.zeros(3))
    soft_iron: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))
    matrix: np.ndarray | None = None

    @property
    def C(self) -> np.ndarray:
        """Sensor matrix ``C`` (dimensionless)."""
        if self.matrix is not None:
            return np.asarray(self.matrix, dtype=float)
        return conventions.sensor_matrix(self.scale, self.psi, self.phi, self.theta)

    @property
    def M(self) -> np.ndarray:
        """Misalignment ``M`` (array frame -> sensor ideal frame)."""
        return conventions.misalignment_matrix(self.alpha, self.beta, self.gamma)

    @property
    def R(self) -> np.ndarray:
        """Correction rotation ``R = M^T`` (sensor ideal frame -> array frame)."""
        return self.M.T

    @property
    def total_matrix(self) -> np.ndarray:
        """``C (I + S_soft)``: what total-field data can see of the linear part (up to a rotation)."""
        return self.C @ (np.eye(3) + np.asarray(self.soft_iron, dtype=float))

    @property
    def total_offset_nT(self) -> np.ndarray:
        """``C B_hard + b`` in nT: the identifiable offset."""
        return self.C @ np.asarray(self.hard_iron_nT, dtype=float) + np.asarray(self.bias_nT, dtype=float)

    @property
    def Cinv(self) -> np.ndarray:
        """True correction matrix ``C^-1`` (upper triangular when ``C`` is)."""
        return np.linalg.inv(self.C)

    def measure(self, field_nT: np.ndarray) -> np.ndarray:
        """Noise-free readings (N, 3) in nT for fields (N, 3) in the sensor's ideal frame."""
        return field_nT @ self.total_matrix.T + self.total_offset_nT


@dataclass
class ArrayTruth:
    """Ground truth for a simulation: sensors, geometry and the field.

    Parameters
    ----------
    sensors : list of SensorErrors
        One to four sensors.
    baseline_m : float
        Baseline ``d`` in m.
    total_nT, declination_deg, inclination_deg : float
        The uniform Earth field.
    """

    sensors: list
    baseline_m: float = 0.5
    total_nT: float = 50_000.0
    declination_deg: float = 0.0
    inclination_deg: float = 60.0

    @property
    def n_sensors(self) -> int:
        return len(self.sensors)

    @property
    def field_world_nT(self) -> np.ndarray:
        return conventions.earth_field(self.total_nT, self.declination_deg, self.inclination_deg)


def chi2017_truth(n_sensors: int = 4) -> ArrayTruth:
    """Chi, Lü & Huang (2017) Table 1: rows kx, ky, kz, psi, phi, theta, bx, by, bz, alpha, beta, gamma.

    Field 50 000 nT, declination -7 deg, inclination 55 deg, baseline 0.5 m. ``n_sensors`` (1-4) keeps the first
    sensors of the cross (sensor 1 is the reference of the misalignment).

    >>> [len(chi2017_truth(n).sensors) for n in (1, 4)]
    [1, 4]
    """
    if not 1 <= int(n_sensors) <= 4:
        raise ValueError(f"chi2017 has sensors 1-4: n_sensors={n_sensors} is not 1-4")
    table = np.array(
        [
            [1.013, 1.012, 1.019, 1.015],
            [0.991, 1.015, 1.011, 1.008],
            [1.007, 0.986, 0.982, 1.021],
            [0.017, 0.013, -0.018, -0.016],
            [0.024, 0.019, 0.025, 0.018],
            [-0.021, 0.015, 0.012, -0.028],
            [25, -54, -16, 45],
            [85, 31, -29, 21],
            [-32, 19, 55, -37],
            [0, -0.023, 0.021, -0.038],
            [0, 0.025, -0.026, -0.028],
            [0, 0.028, 0.031, 0.034],
        ],
        dtype=float,
    )
    sensors = [
        SensorErrors(
            scale=col[0:3],
            psi=col[3],
            phi=col[4],
            theta=col[5],
            bias_nT=col[6:9],
            alpha=col[9],
            beta=col[10],
            gamma=col[11],
        )
        for col in table.T
    ][: int(n_sensors)]
    return ArrayTruth(sensors, baseline_m=0.5, total_nT=50_000.0, declination_deg=-7.0, inclination_deg=55.0)


def _ding2024_sensor(bias_nT, scale, angles_deg, hard_iron_nT, soft_iron) -> SensorErrors:
    """One sensor of Ding (2024), eq. (7): ``Br = K C (B + B_h + S B) + b``.

    Ding's table lists the non-orthogonality angles as ``[phi, theta, psi]`` (deg) with his eq. (3)
    ``C = [[cos(theta) cos(phi), sin(theta) cos(phi), sin(phi)], [0, cos(psi), sin(psi)], [0, 0, 1]]``: his
    ``phi`` is the angle of the real x axis *out of* the ideal x-y plane and his ``theta`` the angle of its
    projection from the ideal x axis. That is Chi's matrix (:func:`magcal.core.conventions.nonorthogonality_matrix`)
    with the two letters swapped: Chi's ``theta`` = Ding's ``phi``, Chi's ``phi`` = Ding's ``theta``;
    ``psi`` means the same in both. ``K = diag(k_x, k_y, k_z)`` is ``scale``.
    """
    phi_ding, theta_ding, psi = np.radians(np.asarray(angles_deg, dtype=float))
    return SensorErrors(
        scale=np.asarray(scale, dtype=float),
        psi=float(psi),
        phi=float(theta_ding),  # in-plane angle (Ding's theta)
        theta=float(phi_ding),  # out-of-plane angle (Ding's phi)
        bias_nT=np.asarray(bias_nT, dtype=float),
        hard_iron_nT=np.asarray(hard_iron_nT, dtype=float),
        soft_iron=np.asarray(soft_iron, dtype=float),
    )


def ding2024_truth() -> ArrayTruth:
    """Ding (2024) simulation 1, Table 1: one fluxgate on a platform with hard and soft iron.

    ``b = [75.5, 57.3, -42.6]`` nT, ``k = [1.031, 0.988, 0.982]``, ``[phi, theta, psi] = [-1.01, -0.83, 1.20]`` deg
    (Ding's letters, see :func:`_ding2024_sensor`), hard iron ``[212, -367, 398]`` nT, soft iron ``S`` as printed.
    Field 51 500 nT, declination -7 deg, inclination 52 deg.
    """
    sensor = _ding2024_sensor(
        bias_nT=[75.5, 57.3, -42.6],
        scale=[1.031, 0.988, 0.982],
        angles_deg=[-1.01, -0.83, 1.20],
        hard_iron_nT=[212.0, -367.0, 398.0],
        soft_iron=[[0.11, 0.09, -0.13], [0.13, -0.06, 0.14], [-0.06, 0.13, 0.11]],
    )
    return ArrayTruth([sensor], baseline_m=0.0, total_nT=51_500.0, declination_deg=-7.0, inclination_deg=52.0)


def ding2024_fluxgate_truth() -> ArrayTruth:
    """Ding (2024) simulation 2, Table 2: a realistic (domestic fluxgate) sensor on a platform.

    ``b = [52.65, -35.5, 72.4]`` nT, ``k = [1.00002, 0.99997, 1.00005]``, ``[phi, theta, psi] = [0.08, 0.03, -0.02]``
    deg, hard iron ``[100, -200, 100]`` nT, soft iron ``S`` as printed. Field 51 500 nT, dec -7 deg, inc 52 deg.
    """
    sensor = _ding2024_sensor(
        bias_nT=[52.65, -35.5, 72.4],
        scale=[1.00002, 0.99997, 1.00005],
        angles_deg=[0.08, 0.03, -0.02],
        hard_iron_nT=[100.0, -200.0, 100.0],
        soft_iron=[[0.09, 0.05, 0.09], [0.15, -0.04, 0.10], [-0.04, 0.09, 0.15]],
    )
    return ArrayTruth([sensor], baseline_m=0.0, total_nT=51_500.0, declination_deg=-7.0, inclination_deg=52.0)


@dataclass
class Preset:
    """A named simulation setup: truth factory plus default sample count and noise."""

    truth: Callable[[], ArrayTruth]
    n_samples: int
    noise_nT: float
    noise_kind: str = "gaussian"
    description: str = ""


#: Simulation presets by name. Other modules register more (e.g. ``ding2024``).
PRESETS: dict[str, Preset] = {
    "chi2017": Preset(chi2017_truth, 200, 3.0, "gaussian", "Chi et al. 2017, Table 1: four sensors, N=200, sigma 3 nT"),
    "ding2024": Preset(
        ding2024_truth,
        300,
        2.0,
        "uniform",
        "Ding 2024, simulation 1 (Table 1): one sensor with hard/soft iron, N=300, uniform noise of full width 2 nT",
    ),
    "ding2024-fluxgate": Preset(
        ding2024_fluxgate_truth,
        300,
        2.0,
        "uniform",
        "Ding 2024, simulation 2 (Table 2): realistic fluxgate with hard/soft iron, N=300, uniform noise of full "
        "width 2 nT",
    ),
}


def random_attitudes(n, rng) -> Rotation:
    """``n`` attitudes drawn uniformly over SO(3)."""
    return Rotation.random(n, random_state=rng)


def smooth_trajectory(time_s, rates=(0.31, 0.11, 0.23)) -> Rotation:
    """A smooth rotation that sweeps the field direction over the whole sphere.

    Yaw and roll turn at constant rates (rad/s) while the pitch sine follows a triangle wave, so the
    direction density is nearly uniform; the attitude changes smoothly sample to sample.

    Parameters
    ----------
    time_s : numpy.ndarray, shape (N,)
    rates : tuple of float
        Yaw rate, pitch-sweep frequency scale and roll rate in rad/s.
    """
    t = np.asarray(time_s, dtype=float)
    yaw = rates[0] * t
    phase = (rates[1] * t / (2 * np.pi)) % 1.0
    tri = 4 * np.abs(phase - 0.5) - 1.0  # triangle wave in [-1, 1]
    pitch = np.arcsin(np.clip(tri, -1, 1))
    roll = rates[2] * t
    return Rotation.from_euler("ZYX", np.column_stack([yaw, pitch, roll]))


def _noise(rng, shape, noise_nT, noise_kind):
    if noise_nT <= 0:
        return np.zeros(shape)
    if noise_kind == "gaussian":
        return rng.normal(0.0, noise_nT, size=shape)
    if noise_kind == "uniform":  # full width noise_nT: values in [-a/2, a/2], RMS a/sqrt(12)
        return rng.uniform(-0.5 * noise_nT, 0.5 * noise_nT, size=shape)
    raise ValueError(f"unknown noise kind {noise_kind!r}: use 'gaussian' or 'uniform'")


def noise_sigma(noise_nT, noise_kind="gaussian") -> float:
    """Per-axis standard deviation (nT) of the simulator's noise option."""
    return float(noise_nT) / np.sqrt(12.0) if noise_kind == "uniform" else float(noise_nT)


def true_fields(truth: ArrayTruth, attitudes: Rotation) -> np.ndarray:
    """True field (n_sensors, N, 3) in each sensor's ideal frame, nT, for a uniform field."""
    b_array = attitudes.inv().apply(truth.field_world_nT)  # array frame
    return np.stack([b_array @ s.M.T for s in truth.sensors])


def _readings(truth, fields, rng, noise_nT, noise_kind):
    clean = np.stack([s.measure(f) for s, f in zip(truth.sensors, fields)])
    return clean + _noise(rng, clean.shape, noise_nT, noise_kind)


def simulate(
    truth: ArrayTruth | str,
    n_samples=None,
    noise_nT=None,
    noise_kind=None,
    seed=0,
    with_reference=True,
    with_attitude=False,
) -> Dataset:
    """Random-attitude simulation (the seeds' setup).

    Parameters
    ----------
    truth : ArrayTruth or str
        The truth, or a preset name from :data:`PRESETS`.
    n_samples : int, optional
        Number of attitudes N (preset default if omitted).
    noise_nT : float, optional
        Gaussian sigma, or uniform full width, per axis in nT (preset default if omitted).
    noise_kind : {'gaussian', 'uniform'}, optional
    seed : int
        Seed of the random generator; the same seed gives the same data.
    with_reference : bool
        Store the true total field as ``reference_total_nT`` metadata.
    with_attitude : bool
        Store the attitude quaternions.

    Returns
    -------
    Dataset
        With ``metadata['truth']`` left out; use the ``truth`` you passed for comparisons.
    """
    truth, n_samples, noise_nT, noise_kind = _resolve(truth, n_samples, noise_nT, noise_kind)
    rng = np.random.default_rng(seed)
    att = random_attitudes(n_samples, rng)
    fields = true_fields(truth, att)
    readings = _readings(truth, fields, rng, noise_nT, noise_kind)
    return _dataset(truth, readings, att if with_attitude else None, with_reference, noise_nT, noise_kind)


def simulate_timeseries(
    truth: ArrayTruth | str,
    n_samples=1500,
    noise_nT=None,
    noise_kind=None,
    seed=0,
    rate_hz=10.0,
    temperature_C=(20.0, 6.0),
    perturbations=(),
    with_reference=True,
    with_attitude=True,
    turn_rate=1.0,
) -> Dataset:
    """Time-series simulation along :func:`magcal.data.simulation.smooth_trajectory`, with time and temperature channels.

    Parameters
    ----------
    truth : ArrayTruth or str
        The truth or a preset name.
    n_samples : int
        Number of samples.
    noise_nT, noise_kind : see :func:`simulate`.
    seed : int
        Seed; the trajectory's phase and rates and the noise depend on it.
    rate_hz : float
        Sample rate in Hz.
    temperature_C : tuple of float
        Mean and half-range of the temperature channel (degC). Temperature is a smooth, non-monotonic curve
        (a slow sine plus a slower one), so it is not a linear function of time.
    perturbations : sequence of callables
        Each ``f(readings, context, rng)`` returns new readings (n_sensors, N, 3); ``context`` is a dict with
        ``fields_nT`` (true field in each sensor's ideal frame), ``time_s``, ``temperature_C``, ``attitudes``
        (a Rotation), ``truth``, ``positions_m`` and ``extra`` (a dict a perturbation may fill with columns the
        dataset then holds, e.g. a motor current). Applied in order, before the noise.
    turn_rate : float
        Multiplier of the trajectory's turn rates: 1 turns at about 17 deg/s, 5 at about 90 deg/s (a hand-held
        tumble, which sweeps many directions within a few seconds).
    """
    truth, n_samples, noise_nT, noise_kind = _resolve(truth, n_samples, noise_nT, noise_kind)
    rng = np.random.default_rng(seed)
    t = np.arange(n_samples) / float(rate_hz)
    rates = np.array((0.31, 0.11, 0.23)) * rng.uniform(0.85, 1.15, size=3) * float(turn_rate)
    att = Rotation.from_euler("ZYX", rng.uniform(-np.pi, np.pi, 3)) * smooth_trajectory(t + rng.uniform(0, 50), rates)
    duration = max(t[-1], 1e-9)
    mean, half = temperature_C
    phase = rng.uniform(0, 2 * np.pi)
    temp = mean + half * (
        0.7 * np.sin(2 * np.pi * 1.3 * t / duration + phase) + 0.3 * np.sin(2 * np.pi * 0.4 * t / duration + 2 * phase)
    )
    fields = true_fields(truth, att)
    clean = np.stack([s.measure(f) for s, f in zip(truth.sensors, fields)])
    context = {
        "fields_nT": fields,
        "time_s": t,
        "temperature_C": temp,
        "attitudes": att,
        "truth": truth,
        "positions_m": conventions.sensor_positions(truth.baseline_m, truth.n_sensors),
        "extra": {},
    }
    for perturb in perturbations:
        clean = perturb(clean, context, rng)
    readings = clean + _noise(rng, clean.shape, noise_nT, noise_kind)
    ds = _dataset(truth, readings, att if with_attitude else None, with_reference, noise_nT, noise_kind)
    return ds.replace(time_s=t, temperature_C=temp, extra=dict(context["extra"]))


def _resolve(truth, n_samples, noise_nT, noise_kind) -> tuple[ArrayTruth, int, float, str]:
    if isinstance(truth, str):
        if truth not in PRESETS:
            raise ValueError(f"unknown preset {truth!r}; known presets: {', '.join(sorted(PRESETS))}")
        preset = PRESETS[truth]
        n_samples = preset.n_samples if n_samples is None else n_samples
        noise_nT = preset.noise_nT if noise_nT is None else noise_nT
        noise_kind = preset.noise_kind if noise_kind is None else noise_kind
        truth = preset.truth()
    n_samples = 200 if n_samples is None else int(n_samples)
    noise_nT = 3.0 if noise_nT is None else float(noise_nT)
    noise_kind = noise_kind or "gaussian"
    return truth, n_samples, noise_nT, noise_kind


def _dataset(truth, readings, att, with_reference, noise_nT, noise_kind):
    q = None
    if att is not None:
        xyzw = att.as_quat()
        q = np.column_stack([xyzw[:, 3], xyzw[:, :3]])
    sigma = noise_sigma(noise_nT, noise_kind)
    return Dataset(
        readings_nT=readings,
        attitude_wxyz=q,
        reference_total_nT=truth.total_nT if with_reference else None,
        baseline_m=truth.baseline_m if truth.n_sensors > 1 else None,
        noise_nT=sigma,
        metadata={"simulated": "true", "noise_kind": noise_kind, "noise_setting_nT": str(noise_nT)},
    )
