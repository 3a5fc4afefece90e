"""A simulated compensation flight of the four-sensor cross: the seed's gradiometer on a moving platform.

The cross (four triaxial fluxgates, sensor 1 at +x, 2 at +y, 3 at -x, 4 at -y, :mod:`magcal.core.conventions`)
flies the compensation box of :mod:`magcal.data.compensation_flight` (its schedule, attitude and maneuvers, reused
as they are). The array's frame is the platform's body frame. Each sensor has its own calibration errors (scale,
non-orthogonality, bias, misalignment: the seed's Table 1 by default) and sees its own platform field, because the
platform's sources sit at different distances from it:

* permanent: a magnetised part, a point dipole of moment ``m`` (A m^2) at ``r_p`` (m, body frame): at sensor
  ``i`` a constant field ``p_i``;
* induced: a soft-iron part at ``r_a`` whose moment follows the Earth field, ``K_a B_e`` (``K_a`` in A m^2 per
  nT): at sensor ``i`` the field ``A_i B_e`` with ``A_i = D(r_i - r_a) K_a`` (dimensionless);
* eddy: a conducting part at ``r_e`` whose moment follows the body-frame field's rate, ``K_e dB_e/dt`` (``K_e``
  in A m^2 per nT/s): at sensor ``i`` the field ``E_i dB_e/dt`` with ``E_i = D(r_i - r_e) K_e`` (s);
* optionally, a current loop at ``r_c`` whose moment follows the platform's current ``I(t)`` (the box's switched
  loads): at sensor ``i`` the field ``k_i I`` (nT/A), which the Tolles-Lawson terms do not hold.

``D(r)`` is the point dipole's field per moment (nT per A m^2). Per sensor, in its own frame (nT)::

    B_e(t)   = R(t)^T (B_ned + drift(t)) + G_body(t) r_i     (R: body -> NED; G: an optional uniform gradient)
    y_i(t)   = C_i M_i (B_e + p_i + A_i B_e + E_i dB_e/dt + k_i I) + b_i + n_i

with ``C_i = S C_NO`` and ``M_i`` the misalignment of :mod:`magcal.core.conventions`, and ``drift`` a slow
uniform field change (diurnal: the tensor does not see it). The truth (:class:`CrossTruth`) keeps every part: the
Earth field at each sensor, the platform field per sensor, the calibration, and the exact compensation.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy.interpolate import make_interp_spline
from scipy.spatial.transform import Rotation

from magcal.core import conventions
from magcal.data.attitude import euler_to_wxyz
from magcal.data.compensation_flight import (
    CompensationPlatform,
    DEFAULT_FIELD_NED_nT,
    FlownManeuver,
    _body_field,
    _current,
    simulate_compensation_flight,
)
from magcal.data.dataset import Dataset
from magcal.data.lab import DIPOLE_NT_M3_PER_AM2
from magcal.data.simulation import SensorErrors, chi2017_truth

__all__ = [
    "CROSS_PLATFORMS",
    "CrossFlight",
    "CrossPlatform",
    "CrossTruth",
    "dipole_matrix",
    "simulate_cross_flight",
]


def dipole_matrix(offset_m) -> np.ndarray:
    """The field of a point dipole per unit moment, ``D(r) = 100 (3 r r^T / |r|^5 - I / |r|^3)`` (nT per A m^2),
    at ``offset_m`` (m, from the dipole to the point)."""
    r = np.asarray(offset_m, dtype=float)
    dist = float(np.linalg.norm(r))
    if dist <= 0:
        raise ValueError("a dipole's field is not defined at the dipole itself: move the source off the sensor")
    return DIPOLE_NT_M3_PER_AM2 * (3.0 * np.outer(r, r) / dist**5 - np.eye(3) / dist**3)


@dataclass
class CrossPlatform:
    """The platform's field sources, body frame (x forward, y right, z down; the cross's centre at the origin).

    Attributes
    ----------
    permanent_Am2 : numpy.ndarray, shape (3,)
        The magnetised part's moment ``m`` (A m^2).
    permanent_at_m : numpy.ndarray, shape (3,)
        Where it sits (m).
    induced_Am2_per_nT : numpy.ndarray, shape (3, 3)
        ``K_a``: the soft-iron part's moment per Earth field (A m^2 per nT).
    induced_at_m : numpy.ndarray, shape (3,)
    eddy_Am2_per_nT_per_s : numpy.ndarray, shape (3, 3)
        ``K_e``: the conducting part's moment per body-frame field rate (A m^2 per nT/s).
    eddy_at_m : numpy.ndarray, shape (3,)
    current_Am2_per_A : numpy.ndarray, shape (3,), or None
        A current loop's moment per ampere (A m^2 per A: its area and orientation) of the platform's current
        (a battery's or a motor's), hidden from the Tolles-Lawson terms; none by default.
    current_at_m : numpy.ndarray, shape (3,)
    currents_Am2_per_A : dict, optional
        Further currents by column name (MagNav.jl's ``cur_strb`` ...): each a loop at :attr:`current_at_m` with
        its own moment per ampere (A m^2 per A; zeros: a recorded current that carries no field at the cross) and
        its own switched series (:attr:`CrossFlight.currents_A`).
    """

    permanent_Am2: np.ndarray = field(default_factory=lambda: np.array([1.2, -0.7, 1.6]))
    permanent_at_m: np.ndarray = field(default_factory=lambda: np.array([-1.6, 0.3, 0.5]))
    induced_Am2_per_nT: np.ndarray = field(
        default_factory=lambda: np.array([[9e-6, 2e-6, -1e-6], [2e-6, 5e-6, 1e-6], [-1e-6, 1e-6, 7e-6]])
    )
    induced_at_m: np.ndarray = field(default_factory=lambda: np.array([-1.2, -0.4, 0.3]))
    eddy_Am2_per_nT_per_s: np.ndarray = field(
        default_factory=lambda: np.array([[2.5e-6, -4e-7, 6e-7], [3e-7, 1.8e-6, -5e-7], [-4e-7, 7e-7, 3e-6]])
    )
    eddy_at_m: np.ndarray = field(default_factory=lambda: np.array([0.9, 0.8, 0.4]))
    current_Am2_per_A: np.ndarray | None = None
    current_at_m: np.ndarray = field(default_factory=lambda: np.array([0.2, -0.6, 0.3]))
    currents_Am2_per_A: dict = field(default_factory=dict)

    def sensor_fields(self, positions_m) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Each sensor's platform terms at ``positions_m`` (n, 3): ``p`` (n, 3) nT, ``A`` (n, 3, 3)
        dimensionless, ``E`` (n, 3, 3) s."""
        pos = np.asarray(positions_m, dtype=float)
        p = np.array([dipole_matrix(r - self.permanent_at_m) @ self.permanent_Am2 for r in pos])
        a = np.array([dipole_matrix(r - self.induced_at_m) @ self.induced_Am2_per_nT for r in pos])
        e = np.array([dipole_matrix(r - self.eddy_at_m) @ self.eddy_Am2_per_nT_per_s for r in pos])
        return p, a, e

    def current_fields(self, positions_m) -> np.ndarray:
        """Each sensor's field per ampere of the platform's current (n, 3), nT/A (zeros without a current loop)."""
        pos = np.asarray(positions_m, dtype=float)
        if self.current_Am2_per_A is None:
            return np.zeros_like(pos)
        return np.array([dipole_matrix(r - self.current_at_m) @ self.current_Am2_per_A for r in pos])

    def further_current_fields(self, positions_m) -> dict:
        """Each further current's field per ampere at each sensor, name -> (n, 3) nT/A."""
        pos = np.asarray(positions_m, dtype=float)
        return {
            name: np.array([dipole_matrix(r - self.current_at_m) @ np.asarray(m, dtype=float) for r in pos])
            for name, m in self.currents_Am2_per_A.items()
        }


#: Named platforms: an aircraft's tail stinger (sources 1-2 m away), a drone (a battery and motors closer, but
#: smaller) and the drone with its battery's current.
CROSS_PLATFORMS: dict[str, CrossPlatform] = {
    "aircraft": CrossPlatform(),
    "drone": CrossPlatform(
        permanent_Am2=np.array([0.25, 0.15, -0.3]),
        permanent_at_m=np.array([0.1, -0.2, 0.7]),
        induced_Am2_per_nT=np.array([[1.2e-6, 3e-7, 0.0], [3e-7, 1.6e-6, -2e-7], [0.0, -2e-7, 2.2e-6]]),
        induced_at_m=np.array([-0.3, 0.5, 0.6]),
        eddy_Am2_per_nT_per_s=np.array([[4e-7, 1e-7, -1e-7], [0.0, 5e-7, 1e-7], [1e-7, 0.0, 6e-7]]),
        eddy_at_m=np.array([0.6, -0.1, 0.5]),
    ),
}
#: The drone with its battery's current in a loop 0.4-0.8 m from the sensors (a few nT per ampere).
CROSS_PLATFORMS["drone_current"] = replace(
    CROSS_PLATFORMS["drone"],
    current_Am2_per_A=np.array([0.002, -0.0012, 0.003]),
    current_at_m=np.array([0.2, -0.6, 0.3]),
)


@dataclass
class CrossTruth:
    """What :func:`simulate_cross_flight` hid.

    Attributes
    ----------
    sensors : list of SensorErrors
        Each sensor's calibration errors (its ``C``, ``M``, ``bias_nT``).
    platform : CrossPlatform
    positions_m : numpy.ndarray, shape (4, 3)
        The sensors' positions (m, body frame).
    permanent_nT : numpy.ndarray, shape (4, 3)
        ``p_i``: each sensor's permanent platform field (nT, body frame).
    induced : numpy.ndarray, shape (4, 3, 3)
        ``A_i`` (dimensionless).
    eddy_s : numpy.ndarray, shape (4, 3, 3)
        ``E_i`` (s).
    current_nT_per_A : numpy.ndarray, shape (4, 3)
        Each sensor's field per ampere of the platform's current (nT/A, body frame; zeros without one).
    currents_nT_per_A : dict
        Each further current's field per ampere at each sensor (name -> (4, 3) nT/A, body frame).
    earth_body_nT : numpy.ndarray, shape (4, N, 3)
        The Earth field (with the drift and any gradient) at each sensor, body frame: what a perfect
        compensation returns, noise aside.
    platform_body_nT : numpy.ndarray, shape (4, N, 3)
        The platform's field at each sensor, body frame.
    field_ned_nT : numpy.ndarray, shape (3,)
        The Earth field at the cross's centre without the drift (nT, NED): what IGRF gives.
    field_ned_series_nT : numpy.ndarray, shape (N, 3)
        With the drift: what a base station records (nT, NED).
    gradient_ned_nT_per_m : numpy.ndarray, shape (3, 3)
    maneuvers : list of FlownManeuver
    """

    sensors: list[SensorErrors]
    platform: CrossPlatform
    positions_m: np.ndarray
    permanent_nT: np.ndarray
    induced: np.ndarray
    eddy_s: np.ndarray
    current_nT_per_A: np.ndarray
    earth_body_nT: np.ndarray
    platform_body_nT: np.ndarray
    field_ned_nT: np.ndarray
    field_ned_series_nT: np.ndarray
    gradient_ned_nT_per_m: np.ndarray
    maneuvers: list[FlownManeuver]
    currents_nT_per_A: dict = field(default_factory=dict)

    def calibrated_nT(self, readings_nT) -> np.ndarray:
        """The readings (4, N, 3) through each sensor's true calibration, ``M_i^T C_i^-1 (y_i - b_i)``: the body
        frame field, the platform's field still in it (nT)."""
        y = np.asarray(readings_nT, dtype=float)
        return np.stack([(y[i] - s.bias_nT) @ (s.R @ s.Cinv).T for i, s in enumerate(self.sensors)])

    def compensated_nT(self, readings_nT) -> np.ndarray:
        """The true compensation of the readings (4, N, 3): the true calibration, then the exact platform field
        taken out (nT, body frame)."""
        return self.calibrated_nT(readings_nT) - self.platform_body_nT


@dataclass
class CrossFlight:
    """A simulated compensation flight of the cross.

    Attributes
    ----------
    time_s : numpy.ndarray, shape (N,)
    sample_rate_hz : float
    readings_nT : numpy.ndarray, shape (4, N, 3)
        The four sensors' raw readings, each in its own frame (nT).
    attitude_deg : numpy.ndarray, shape (N, 3)
        Roll, pitch, yaw as recorded (aerospace ZYX, deg; with the attitude noise).
    baseline_m : float
    truth : CrossTruth
    current_A : numpy.ndarray, shape (N,)
        The platform's current (A): base load and switched loads, zero without a current loop.
    currents_A : dict
        The further currents by column name (A; :attr:`CrossPlatform.currents_Am2_per_A`), each its own switched
        loads.
    """

    time_s: np.ndarray
    sample_rate_hz: float
    readings_nT: np.ndarray
    attitude_deg: np.ndarray
    baseline_m: float
    truth: CrossTruth
    current_A: np.ndarray = field(default_factory=lambda: np.zeros(0))
    currents_A: dict = field(default_factory=dict)

    def dataset(self) -> Dataset:
        """The flight as a :class:`~magcal.data.dataset.Dataset`: the readings, the times, the recorded attitude
        (quaternions, body -> NED) and the baseline, and the further currents' columns (:attr:`currents_A`)."""
        roll, pitch, yaw = self.attitude_deg.T
        return Dataset(
            self.readings_nT,
            time_s=self.time_s,
            attitude_wxyz=euler_to_wxyz(roll, pitch, yaw),
            baseline_m=self.baseline_m,
            source="simulated cross flight",
            extra={name: np.asarray(values) for name, values in self.currents_A.items()},
        )


def _rate_nT_per_s(time_s, values) -> np.ndarray:
    """The time derivative (nT/s) of a smooth series (N, 3), from a quintic spline through it."""
    return make_interp_spline(time_s, values, k=5, axis=0).derivative()(time_s)


def simulate_cross_flight(
    seed: int = 0,
    *,
    platform: CrossPlatform | str | None = None,
    sensors: list[SensorErrors] | None = None,
    baseline_m: float = 0.5,
    sample_rate_hz: float = 10.0,
    field_ned_nT=DEFAULT_FIELD_NED_nT,
    gradient_ned_nT_per_m=None,
    noise_nT: float = 0.1,
    attitude_noise_deg: float = 0.0,
    drift_nT: float = 3.0,
    sensor_lag_s: float = 0.0,
    **box,
) -> CrossFlight:
    """Simulate the cross flying a compensation box, with known calibration errors and platform fields.

    Parameters
    ----------
    seed : int
        The box's periods (as :func:`~magcal.data.compensation_flight.simulate_compensation_flight`), the noise
        and the drift.
    platform : CrossPlatform or str, optional
        The platform's sources, or a name of :data:`CROSS_PLATFORMS` (default ``"aircraft"``).
    sensors : list of SensorErrors, optional
        The four sensors' calibration errors (default the seed's Table 1,
        :func:`~magcal.data.simulation.chi2017_truth`); their hard and soft iron are ignored (the platform's sources
        are given by ``platform``).
    baseline_m : float
        The cross's baseline (m): sensors 1 and 3 (2 and 4) are this far apart.
    sample_rate_hz : float
        The recorded rate (Hz).
    field_ned_nT : array_like, shape (3,)
        The Earth field at the cross's centre (nT, NED).
    gradient_ned_nT_per_m : array_like, shape (3, 3), optional
        A uniform gradient of the Earth field (nT/m, NED; symmetric and traceless for a source-free field); none
        by default (a box flown high).
    noise_nT : float
        White noise per axis of each fluxgate (nT, one sigma).
    attitude_noise_deg : float
        White noise of each recorded attitude angle (deg, one sigma).
    drift_nT : float
        Amplitude of the slow uniform field change (nT).
    sensor_lag_s : float
        How late the four sensors' samples are against the attitude's and the current's (s): each reads the field
        of ``sensor_lag_s`` earlier (the attitude through a quintic spline, so that the lag is exact to the
        filter), hidden from the Tolles-Lawson terms.
    **box
        Passed to :func:`~magcal.data.compensation_flight.simulate_compensation_flight`: ``headings_deg``,
        ``periods_s``, ``cycles``, ``straight_s``, ``turn_s``, ``turn_bank_deg``, ``amplitudes_deg``.

    Returns
    -------
    CrossFlight
    """
    if isinstance(platform, str):
        if platform not in CROSS_PLATFORMS:
            raise ValueError(f"unknown platform {platform!r}: use one of " + ", ".join(CROSS_PLATFORMS))
        platform = CROSS_PLATFORMS[platform]
    platform = platform if platform is not None else CROSS_PLATFORMS["aircraft"]
    sensors = list(sensors) if sensors is not None else chi2017_truth(4).sensors
    if len(sensors) != 4:
        raise ValueError(f"the cross has four sensors, got {len(sensors)}")
    # the box's schedule, and its current series when the platform carries a current loop
    with_current = None if platform.current_Am2_per_A is None else CompensationPlatform(current_nT_per_A=np.ones(3))
    box_flight = simulate_compensation_flight(
        seed, sample_rate_hz=sample_rate_hz, field_ned_nT=field_ned_nT, platform=with_current, **box
    )
    t, recorded_attitude = box_flight.time_s, box_flight.attitude_deg
    attitude = _lagged(t, recorded_attitude, sensor_lag_s)  # what the sensors felt when they were sampled
    rng = np.random.default_rng([seed, 4])
    field_ned = np.asarray(field_ned_nT, dtype=float)
    gradient = np.zeros((3, 3)) if gradient_ned_nT_per_m is None else np.asarray(gradient_ned_nT_per_m, float)
    positions = conventions.sensor_positions(baseline_m)

    drift_dir = rng.normal(size=3)
    drift = drift_nT * np.sin(2 * np.pi * (t - sensor_lag_s) / (2.5 * t[-1]) + rng.uniform(0, 2 * np.pi))
    centre_ned = field_ned[None, :] + np.outer(drift, drift_dir / np.linalg.norm(drift_dir))
    centre = _body_field(attitude, centre_ned)
    body_to_ned = Rotation.from_euler("ZYX", attitude[:, ::-1], degrees=True)  # the sensors' offsets turn with it
    earth = np.stack([_body_field(attitude, centre_ned + body_to_ned.apply(r) @ gradient.T) for r in positions])
    rate = _rate_nT_per_s(t, centre)

    p, a, e = platform.sensor_fields(positions)
    k = platform.current_fields(positions)
    current = np.interp(t - sensor_lag_s, t, box_flight.current_A)
    platform_field = np.stack([p[i] + centre @ a[i].T + rate @ e[i].T + np.outer(current, k[i]) for i in range(4)])
    further = platform.further_current_fields(positions)
    currents = {}
    for j, (name, k_name) in enumerate(further.items()):  # each wire its own switched loads
        currents[name] = _current(t.size, sample_rate_hz, np.random.default_rng([seed, 9, j]))
        lagged = np.interp(t - sensor_lag_s, t, currents[name])
        platform_field = platform_field + np.stack([np.outer(lagged, k_name[i]) for i in range(4)])
    readings = np.empty_like(earth)
    for i, s in enumerate(sensors):
        readings[i] = (earth[i] + platform_field[i]) @ (s.C @ s.M).T + s.bias_nT
    readings += rng.normal(0.0, noise_nT, readings.shape)
    recorded = recorded_attitude + rng.normal(0.0, attitude_noise_deg, attitude.shape)
    recorded[:, 2] = np.mod(recorded[:, 2], 360.0)
    truth = CrossTruth(
        sensors=sensors,
        platform=platform,
        positions_m=positions,
        permanent_nT=p,
        induced=a,
        eddy_s=e,
        current_nT_per_A=k,
        earth_body_nT=earth,
        platform_body_nT=platform_field,
        field_ned_nT=field_ned,
        field_ned_series_nT=centre_ned,
        gradient_ned_nT_per_m=gradient,
        maneuvers=box_flight.truth.maneuvers,
        currents_nT_per_A=further,
    )
    return CrossFlight(
        t, float(sample_rate_hz), readings, recorded, float(baseline_m), truth, box_flight.current_A, currents
    )


def _lagged(time_s, attitude_deg, lag_s: float) -> np.ndarray:
    """Roll, pitch, yaw (deg) ``lag_s`` earlier, through a quintic spline (the yaw unwrapped first)."""
    if not lag_s:
        return attitude_deg
    angles = np.asarray(attitude_deg, dtype=float).copy()
    angles[:, 2] = np.rad2deg(np.unwrap(np.deg2rad(angles[:, 2])))
    earlier = make_interp_spline(time_s, angles, k=5, axis=0)(np.asarray(time_s) - lag_s)
    earlier[:, 2] = np.mod(earlier[:, 2], 360.0)
    return earlier
