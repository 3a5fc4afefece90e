"""A simulated vehicle: a platform that turns in yaw but barely tilts, with attitude from an INS.

The vehicle flies full yaw turns with roll and pitch oscillating within a few degrees (a car, a ship, an aircraft's
compensation pattern); its magnetometers are bolted on with their axes permuted and a little off the right angle,
read through their own scale, non-orthogonality, soft and hard iron, and optionally eddy currents and a field per
ampere of a motor current. The recorded attitude carries an error; the Earth's field vector is known.

Model per sensor (nT)::

    y = C R_m^T B_body + b + k I + E dy0/dt * 1e-3 + n,     B_body = R(q_true)^T B_ned

with ``C = (C^-1)^-1`` (``C^-1`` upper triangular, the seed's gauge, so the mounting ``R_m`` is exactly what a
calibration's ``R`` should find), ``k`` in nT/A, ``E`` in ms and ``dy0/dt`` the rate of the noise-free reading.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from magcal.core.conventions import sensor_positions
from magcal.data.dataset import Dataset

#: A mid-latitude field (nT, north-east-down): |B| about 48 700 nT, inclination 64 deg.
DEFAULT_FIELD_NED_nT = (21_000.0, 1_200.0, 44_000.0)


@dataclass
class VehicleSensorTruth:
    """One sensor's true parameters.

    Attributes
    ----------
    matrix : numpy.ndarray, shape (3, 3)
        ``C``: scale, non-orthogonality and soft iron (``C^-1`` upper triangular).
    bias_nT : numpy.ndarray, shape (3,)
    mounting : numpy.ndarray, shape (3, 3)
        ``R_m``: sensor axes -> body frame.
    eddy_ms : numpy.ndarray, shape (3, 3), or None
    current_nT_per_unit : numpy.ndarray, shape (3,), or None
        Field per ampere of the ``current_A`` column.
    """

    matrix: np.ndarray
    bias_nT: np.ndarray
    mounting: np.ndarray
    eddy_ms: np.ndarray | None = None
    current_nT_per_unit: np.ndarray | None = None


@dataclass
class VehicleTruth:
    """What :func:`simulate_vehicle` hid in the data.

    Attributes
    ----------
    field_ned_nT : numpy.ndarray, shape (3,)
    sensors : list of VehicleSensorTruth
    attitude_wxyz : numpy.ndarray, shape (N, 4)
        The true attitude (the dataset holds the measured one).
    noise_nT : float
    attitude_noise_deg : float
    """

    field_ned_nT: np.ndarray
    sensors: list
    attitude_wxyz: np.ndarray
    noise_nT: float
    attitude_noise_deg: float
    extra: dict = field(default_factory=dict)


def vehicle_truth(
    n_sensors=1, mounting=None, off_deg=2.0, eddy=False, current=False, seed=0, field_ned_nT=DEFAULT_FIELD_NED_nT
):
    """Random but plausible sensor parameters for :func:`simulate_vehicle` (the same seed gives the same truth).

    ``mounting`` is a right-angle (3, 3) rotation (default: x -> body y, y -> body x, z -> body -z, ArduPilot's
    ``ROLL_180_YAW_90``); each sensor is turned ``off_deg`` from it about a random axis.
    """
    rng = np.random.default_rng(seed)
    base = (
        np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
        if mounting is None
        else np.asarray(mounting, dtype=float)
    )
    sensors = []
    for _ in range(n_sensors):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        r_m = base @ Rotation.from_rotvec(np.radians(off_deg) * axis).as_matrix()
        cinv = np.eye(3) + np.triu(rng.normal(0.0, 0.04, (3, 3)))
        cinv[np.diag_indices(3)] = 1.0 + rng.normal(0.0, 0.05, 3)
        sensors.append(
            VehicleSensorTruth(
                matrix=np.linalg.inv(cinv),
                bias_nT=rng.normal(0.0, 1500.0, 3),
                mounting=r_m,
                eddy_ms=rng.normal(0.0, 10.0, (3, 3)) if eddy else None,
                current_nT_per_unit=rng.normal(0.0, 25.0, 3) if current else None,
            )
        )
    return VehicleTruth(np.asarray(field_ned_nT, dtype=float), sensors, np.zeros((0, 4)), 0.0, 0.0)


def simulate_vehicle(
    truth=None,
    n=6000,
    rate_hz=10.0,
    turns=3.0,
    roll_max_deg=20.0,
    pitch_max_deg=10.0,
    noise_nT=3.0,
    attitude_noise_deg=0.02,
    seed=0,
    attitude_tau_s=0.0,
    baseline_m=None,
    gradient_ned_nT_per_m=None,
    perturbations=(),
    temperature=None,
    log_current=None,
    **truth_options,
):
    """A vehicle's record: readings, measured attitude, times, the field vector and (with a current term) the
    motor current.

    Parameters
    ----------
    truth : VehicleTruth, optional
        The sensors (default :func:`vehicle_truth` with ``seed`` and ``truth_options``). Give the same truth to
        two calls with different seeds for a calibration flight and a test flight.
    n, rate_hz : int, float
        Samples and sample rate (Hz).
    turns : float
        Full yaw turns over the record.
    roll_max_deg, pitch_max_deg : float
        Amplitudes of the roll and pitch oscillations (deg).
    noise_nT : float
        Sensor noise per axis (nT, 1 sigma).
    attitude_noise_deg : float
        Attitude error per axis (deg, 1 sigma) of the recorded attitude.
    attitude_tau_s : float
        Correlation time (s) of the attitude error: 0 (default) for white errors, otherwise a first-order
        Gauss-Markov process of that time constant and ``attitude_noise_deg`` standard deviation (an INS's slowly
        wandering error).
    seed : int
        Seed of the trajectory's phases and of the noise.
    baseline_m : float, optional
        For four sensors: the cross's baseline (m); the sensors sit at +x, +y, -x, -y of the cross's frame, which is
        sensor 1's mounting in the body (:func:`magcal.core.conventions.sensor_positions`). Stored in the dataset.
    gradient_ned_nT_per_m : array_like, shape (3, 3), optional
        A uniform gradient of the field in the world frame (nT/m, symmetric and traceless for a source-free field):
        the field at a sensor is ``B_ned + G r``, ``r`` its position in NED relative to the cross's centre.
    perturbations : sequence of callables
        Effects hidden in the readings, as :func:`magcal.data.simulation.simulate_timeseries` takes them
        (:func:`magcal.model.perturbations.parse_hidden`, ``Effect.perturbation``): each is applied to the
        noise-free readings (bias, current and eddy fields included) before the noise, with the body-frame field
        as the sensors' field, the vehicle's temperature and motor current as channels.
    temperature : bool, optional
        Record a ``temperature_C`` channel (degC): the electronics warming by 8 K over the first minutes and
        following the motor current's heating by +-2 K, so that it is neither a function of time alone nor of the
        current alone. Default: only when a perturbation needs it.
    log_current : bool, optional
        Record the motor current (``current_A``, A). Default: when a sensor sees it or a perturbation uses it.

    Returns
    -------
    dataset : Dataset
        Readings (nT), ``time_s``, ``attitude_wxyz`` (measured, body -> NED), extra columns ``ref_n, ref_e,
        ref_d`` (the field vector, nT) and, with a current term, ``current_A``.
    truth : VehicleTruth
    """
    truth = vehicle_truth(seed=seed, **truth_options) if truth is None else truth
    rng = np.random.default_rng(seed + 10_000)
    t = np.arange(n) / rate_hz
    span = n / rate_hz
    phase = rng.uniform(0, 2 * np.pi, 4)
    yaw = 360.0 * turns * t / span + 25.0 * np.sin(2 * np.pi * t / (span / 7.3) + phase[0])
    roll = roll_max_deg * np.sin(2 * np.pi * t / (span / (turns * 2.3)) + phase[1])
    pitch = pitch_max_deg * np.sin(2 * np.pi * t / (span / (turns * 1.7)) + phase[2])
    true_att = Rotation.from_euler("ZYX", np.column_stack([yaw, pitch, roll]), degrees=True)
    white = rng.normal(0.0, np.radians(attitude_noise_deg), (n, 3))
    if attitude_tau_s > 0:
        a = np.exp(-1.0 / (rate_hz * attitude_tau_s))
        err = np.empty_like(white)
        err[0] = white[0]
        for i in range(1, n):
            err[i] = a * err[i - 1] + np.sqrt(1.0 - a * a) * white[i]
        white = err
    noise_rot = Rotation.from_rotvec(white)
    measured = true_att * noise_rot
    n_sensors = len(truth.sensors)
    positions = np.zeros((n_sensors, 3)) if not baseline_m else sensor_positions(baseline_m, n_sensors)
    grad = np.zeros((3, 3)) if gradient_ned_nT_per_m is None else np.asarray(gradient_ned_nT_per_m, dtype=float)
    cross_in_body = truth.sensors[0].mounting
    current = 12.0 + 8.0 * np.sin(2 * np.pi * t / (span / 11.0) + phase[3]) + rng.normal(0.0, 0.5, n)
    current = np.clip(current + 4.0 * (np.floor(t / (span / 9.0)) % 2), 0.0, None)
    heating = np.convolve(current - current.mean(), np.full(int(rate_hz * 20) or 1, 1.0 / (int(rate_hz * 20) or 1)))
    temp_C = 18.0 + 8.0 * (1.0 - np.exp(-t / 120.0)) + 0.5 * heating[:n]
    readings = []
    fields = []
    for k, s in enumerate(truth.sensors):
        r_ned = true_att.apply(cross_in_body @ positions[k])  # the sensor's position in NED, m
        b_body = true_att.inv().apply(truth.field_ned_nT + r_ned @ grad.T)
        y0 = b_body @ (s.matrix @ s.mounting.T).T + s.bias_nT
        if s.current_nT_per_unit is not None:
            y0 = y0 + current[:, None] * s.current_nT_per_unit[None, :]
        y = y0.copy()
        if s.eddy_ms is not None:
            y = y + 1e-3 * np.gradient(y0, t, axis=0) @ s.eddy_ms.T
        readings.append(y)
        fields.append(b_body)
    readings_nT = np.array(readings)
    context = {
        "fields_nT": np.array(fields),
        "time_s": t,
        "temperature_C": temp_C,
        "truth": _PerturbationTruth(truth),
        "attitudes": true_att,
        "extra": {"current_A": current},
    }
    for perturb in perturbations:
        readings_nT = np.asarray(perturb(readings_nT, context, rng), dtype=float)
    readings_nT = readings_nT + rng.normal(0.0, noise_nT, readings_nT.shape)
    hidden = [getattr(p, "effect", "") for p in perturbations]
    q = measured.as_quat()
    extra = {name: np.full(n, truth.field_ned_nT[k]) for k, name in enumerate(("ref_n", "ref_e", "ref_d"))}
    for name, values in context["extra"].items():
        if name != "current_A":
            extra[name] = values
    if log_current or (
        log_current is None
        and (any(s.current_nT_per_unit is not None for s in truth.sensors) or "current_field" in hidden)
    ):
        extra["current_A"] = context["extra"]["current_A"]
    needs_temperature = any(h.startswith("temperature") for h in hidden)
    ds = Dataset(
        readings_nT=readings_nT,
        time_s=t,
        temperature_C=temp_C if (temperature or (temperature is None and needs_temperature)) else None,
        attitude_wxyz=np.column_stack([q[:, 3], q[:, :3]]),
        extra=extra,
        noise_nT=None,
        baseline_m=baseline_m,
        source="simulated vehicle",
    )
    tq = true_att.as_quat()
    out = VehicleTruth(
        truth.field_ned_nT,
        truth.sensors,
        np.column_stack([tq[:, 3], tq[:, :3]]),
        float(noise_nT),
        float(attitude_noise_deg),
    )
    return ds, out


class _PerturbationTruth:
    """What a catalogue perturbation (:mod:`magcal.model.perturbations`) reads of the truth: each sensor's linear
    map from the field it is given (here the body-frame field) to its axes, ``C R_m^T``, and the field's
    magnitude."""

    class _Sensor:
        def __init__(self, total_matrix):
            self.total_matrix = total_matrix

    def __init__(self, truth: VehicleTruth):
        self.sensors = [self._Sensor(s.matrix @ s.mounting.T) for s in truth.sensors]
        self.total_nT = float(np.linalg.norm(truth.field_ned_nT))
