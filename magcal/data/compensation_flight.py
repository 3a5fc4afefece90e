"""A simulated compensation flight: the box an aeromagnetic or drone survey flies before it starts.

Four headings (0, 90, 180, 270 deg by default); on each, after a straight stretch, rolls of +-10 deg, pitches of
+-5 deg and yaws of +-5 deg, a few cycles each, with straight stretches between, and a banked turn to the next
heading. A platform carries a permanent field, an induced field and eddy currents (and, hidden from the
Tolles-Lawson model if asked, a field per ampere of a current, a permanent field that drifts with the temperature
and a fluxgate that lags the scalar). It records a scalar magnetometer, a fluxgate's vector in the body frame and
the platform's temperature (it warms through the flight).

Physics, in the body frame (nT), written from the fields themselves, not from the Tolles-Lawson design::

    B_e(t)   = R(t)^T B_ned                      (R: body -> NED, aerospace ZYX roll, pitch, yaw)
    B_p(t)   = p + A B_e + E dB_e/dt + k I(t) + q (T(t) - T_ref)
                                                  (p nT, A dimensionless, E s, k nT/A, q nT/degC)
    scalar   = |B_e + B_p| + background(t) + noise
    fluxgate = W B_e(t - lag) + b + noise        (W, b: the fluxgate's own scale, non-orthogonality and bias)

with ``background`` a slow drift (diurnal, below the band-pass). The truth's :meth:`CompensationTruth.tl18` is
the platform in Tolles-Lawson's linear terms (first order in ``B_p / |B_e|``), in MagNav.jl's order and scaling.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

#: The Earth field at the box (nT, north-east-down): |B| about 50 000 nT, inclination 65 deg.
DEFAULT_FIELD_NED_nT = (20_500.0, 1_000.0, 45_500.0)

#: Maneuver kinds, in the order a box flies them on each heading, and their default amplitudes (deg).
MANEUVERS = ("roll", "pitch", "yaw")
DEFAULT_AMPLITUDES_DEG = {"roll": 10.0, "pitch": 5.0, "yaw": 5.0}

#: Samples per output sample in the internal grid the fields are computed on (their rates exact to the filter).
_OVERSAMPLE = 5


@dataclass
class CompensationPlatform:
    """The platform's fields.

    Attributes
    ----------
    permanent_nT : numpy.ndarray, shape (3,)
        Body-fixed field ``p``.
    induced : numpy.ndarray, shape (3, 3)
        ``A``: the induced field per field (dimensionless; only its symmetric part shows in a scalar).
    eddy_s : numpy.ndarray, shape (3, 3)
        ``E``: the eddy field per body-field rate (nT per nT/s = s).
    current_nT_per_A : numpy.ndarray, shape (3,), or None
        ``k``: a field per ampere of the ``current_A`` series, hidden from the Tolles-Lawson terms.
    currents_nT_per_A : dict, optional
        Further currents by column name (MagNav.jl's ``cur_strb`` ...): each its own switched series
        (:attr:`CompensationFlight.currents_A`) and its own field per ampere (nT/A, body frame; a wire's field is
        its current times a fixed vector). A zero vector records a current whose wire is far from the sensor.
    temperature_nT_per_C : numpy.ndarray, shape (3,), or None
        ``q``: the permanent field's drift per degC of the platform's temperature away from
        :data:`REFERENCE_TEMPERATURE_C` (magnetised steel loses magnetisation as it warms), hidden from the
        Tolles-Lawson terms.
    """

    permanent_nT: np.ndarray = field(default_factory=lambda: np.array([60.0, -35.0, 80.0]))
    induced: np.ndarray = field(
        default_factory=lambda: np.array([[8e-4, 2e-4, -3e-4], [2e-4, -5e-4, 1e-4], [-3e-4, 1e-4, 6e-4]])
    )
    eddy_s: np.ndarray = field(
        default_factory=lambda: np.array([[2e-4, -5e-5, 8e-5], [3e-5, 1.5e-4, -6e-5], [-4e-5, 7e-5, 2.5e-4]])
    )
    current_nT_per_A: np.ndarray | None = None
    currents_nT_per_A: dict = field(default_factory=dict)
    temperature_nT_per_C: np.ndarray | None = None


#: The temperature the platform's permanent field ``p`` is at (degC).
REFERENCE_TEMPERATURE_C = 20.0


@dataclass(frozen=True)
class FlownManeuver:
    """One maneuver as flown: nominal heading (deg), kind (``roll``, ``pitch``, ``yaw``), samples
    ``[start, stop)``."""

    heading_deg: float
    kind: str
    start: int
    stop: int


@dataclass
class CompensationTruth:
    """What :func:`simulate_compensation_flight` hid.

    Attributes
    ----------
    platform : CompensationPlatform
    field_ned_nT : numpy.ndarray, shape (3,)
    fluxgate_lag_s : float
        How far the fluxgate lags the scalar (s).
    maneuvers : list of FlownManeuver
    platform_scalar_nT : numpy.ndarray, shape (N,)
        ``|B_e + B_p| - |B_e|``: exactly what a perfect compensation removes.
    earth_total_nT : numpy.ndarray, shape (N,)
        ``|B_e|`` plus the background: the perfectly compensated scalar, noise aside.
    noise_nT : numpy.ndarray, shape (N,)
        The scalar's noise.
    """

    platform: CompensationPlatform
    field_ned_nT: np.ndarray
    fluxgate_lag_s: float
    maneuvers: list[FlownManeuver]
    platform_scalar_nT: np.ndarray
    earth_total_nT: np.ndarray
    noise_nT: np.ndarray

    def tl18(self, sample_rate_hz: float, scale_nT: float = 50_000.0) -> np.ndarray:
        """The platform as TL's 18 coefficients (first order), MagNav.jl's order and scaling: ``p``; the induced
        ``A``'s symmetric part (``xx, 2xy, 2xz, yy, 2yz, zz`` times ``scale_nT``); ``E`` row by row times the
        sample rate and ``scale_nT`` (per-sample rates)."""
        a = self.platform.induced
        induced = [a[0, 0], a[0, 1] + a[1, 0], a[0, 2] + a[2, 0], a[1, 1], a[1, 2] + a[2, 1], a[2, 2]]
        eddy = self.platform.eddy_s.ravel() * sample_rate_hz
        return np.concatenate([self.platform.permanent_nT, np.array(induced) * scale_nT, eddy * scale_nT])

    def compensated_nT(self, scalar_nT) -> np.ndarray:
        """The true compensation of the recorded scalar: the scalar minus the platform's exact scalar field."""
        return np.asarray(scalar_nT, dtype=float) - self.platform_scalar_nT


@dataclass
class CompensationFlight:
    """A simulated compensation flight.

    Attributes
    ----------
    time_s : numpy.ndarray, shape (N,)
    sample_rate_hz : float
    scalar_nT : numpy.ndarray, shape (N,)
        The scalar magnetometer, uncompensated.
    flux_nT : numpy.ndarray, shape (N, 3)
        The fluxgate's vector, body frame.
    attitude_deg : numpy.ndarray, shape (N, 3)
        Roll, pitch, yaw (aerospace ZYX, deg).
    current_A : numpy.ndarray, shape (N,)
        The platform's current (A), zero without a current field.
    temperature_C : numpy.ndarray, shape (N,)
        The platform's temperature (degC): it warms by ``warming_C`` through the flight, with a slow swing.
    truth : CompensationTruth
    currents_A : dict
        The further currents by column name (A; :attr:`CompensationPlatform.currents_nT_per_A`).
    """

    time_s: np.ndarray
    sample_rate_hz: float
    scalar_nT: np.ndarray
    flux_nT: np.ndarray
    attitude_deg: np.ndarray
    current_A: np.ndarray
    temperature_C: np.ndarray
    truth: CompensationTruth
    currents_A: dict = field(default_factory=dict)


def _smooth_step(frac):
    """0 -> 1 with zero slope at both ends."""
    return 0.5 - 0.5 * np.cos(np.pi * np.clip(frac, 0.0, 1.0))


def _schedule(headings, periods_s, cycles, straight_s, turn_s, turn_bank_deg, amplitudes_deg, rate_hz):
    """Roll, pitch, yaw (deg) on a uniform grid at ``rate_hz``, and the maneuvers' [start, stop) on it."""
    pieces, maneuvers = [], []
    n = 0
    dt = 1.0 / rate_hz

    def add(duration_s, shape):
        nonlocal n
        m = max(1, round(duration_s * rate_hz))
        frac = np.arange(m) * dt / duration_s
        pieces.append(shape(frac, m))
        n += m
        return n - m, n

    for k, heading in enumerate(headings):
        add(straight_s, lambda f, m, h=heading: np.column_stack([np.zeros(m), np.zeros(m), np.full(m, h)]))
        for axis, kind in enumerate(MANEUVERS):
            duration = cycles * periods_s[kind]

            def oscillate(f, m, h=heading, a=axis, amp=amplitudes_deg[kind]):
                out = np.column_stack([np.zeros(m), np.zeros(m), np.full(m, h)])
                out[:, a] += amp * np.sin(2 * np.pi * cycles * f)
                return out

            start, stop = add(duration, oscillate)
            maneuvers.append(FlownManeuver(float(heading % 360), kind, start, stop))
            add(straight_s, lambda f, m, h=heading: np.column_stack([np.zeros(m), np.zeros(m), np.full(m, h)]))
        if k + 1 < len(headings):
            h0, h1 = heading, headings[k + 1]
            add(
                turn_s,
                lambda f, m, h0=h0, h1=h1: np.column_stack(
                    [turn_bank_deg * np.sin(np.pi * f), np.zeros(len(f)), h0 + (h1 - h0) * _smooth_step(f)]
                ),
            )
    return np.vstack(pieces), maneuvers


def _body_field(attitude_deg, field_ned):
    """``R^T B_ned`` per sample (N, 3), nT."""
    rot = Rotation.from_euler("ZYX", attitude_deg[:, ::-1], degrees=True)
    return rot.inv().apply(field_ned)


def _current(n, rate_hz, rng):
    """A platform current (A): a base load with switched loads every 8-20 s (steps, smoothed over 0.3 s)."""
    current = np.full(n, 8.0)
    k = 0
    while k < n:
        length = int(rng.uniform(8, 20) * rate_hz)
        current[k : k + length] += rng.choice([0.0, 3.0, 6.0])
        k += length
    width = max(1, int(0.3 * rate_hz))
    return np.convolve(current, np.ones(width) / width, mode="same")


def _temperature(time_s, warming_C: float, seed: int) -> np.ndarray:
    """The platform's temperature (degC): from 15 degC it warms by ``warming_C`` over the flight (an engine's and
    the avionics' heat), with a swing of a quarter of that over a few minutes; its own random stream, so the
    flight's other draws do not depend on it."""
    rng = np.random.default_rng([int(seed), 7])
    frac = time_s / max(float(time_s[-1]), 1.0)
    swing = 0.25 * warming_C * np.sin(2 * np.pi * time_s / rng.uniform(240.0, 360.0) + rng.uniform(0, 2 * np.pi))
    return 15.0 + warming_C * (1.0 - np.exp(-3.0 * frac)) / (1.0 - np.exp(-3.0)) + swing


def simulate_compensation_flight(
    seed: int = 0,
    *,
    sample_rate_hz: float = 10.0,
    platform: CompensationPlatform | None = None,
    field_ned_nT=DEFAULT_FIELD_NED_nT,
    headings_deg=(0.0, 90.0, 180.0, 270.0),
    periods_s=None,
    cycles: int = 3,
    straight_s: float = 8.0,
    turn_s: float = 30.0,
    turn_bank_deg: float = 15.0,
    amplitudes_deg=None,
    scalar_noise_nT: float = 0.02,
    fluxgate_noise_nT: float = 0.2,
    drift_nT: float = 3.0,
    fluxgate_lag_s: float = 0.0,
    fluxgate_matrix=None,
    fluxgate_bias_nT=None,
    warming_C: float = 12.0,
) -> CompensationFlight:
    """Simulate a compensation flight with known platform fields.

    Parameters
    ----------
    seed : int
        Noise, current and the maneuvers' periods (each within +-10 % of ``periods_s``).
    sample_rate_hz : float
        The recorded rate (Hz).
    platform : CompensationPlatform, optional
        The platform's fields (default :class:`CompensationPlatform`'s values); give ``current_nT_per_A`` for a
        current's field TL does not model.
    field_ned_nT : array_like, shape (3,)
        The Earth field (nT, NED).
    headings_deg : sequence of float
        The legs' headings (deg), flown in this order.
    periods_s : dict, optional
        Each maneuver's period (s), default roll 6, pitch 5, yaw 7: inside the 0.1-0.9 Hz band.
    cycles : int
        Cycles of each maneuver.
    straight_s, turn_s, turn_bank_deg : float
        Straight stretch before and after each maneuver (s), a turn's duration (s) and its peak bank (deg).
    amplitudes_deg : dict, optional
        Each maneuver's amplitude (deg), default roll 10, pitch 5, yaw 5.
    scalar_noise_nT, fluxgate_noise_nT : float
        White noise (nT, one sigma) of the scalar and of each fluxgate axis.
    drift_nT : float
        The slow background's amplitude (nT): a diurnal-like drift over the flight.
    fluxgate_lag_s : float
        The fluxgate's lag behind the scalar (s), hidden from the Tolles-Lawson terms.
    fluxgate_matrix : array_like, shape (3, 3), optional
        ``W``: the fluxgate's scale and non-orthogonality (the identity by default): it reads ``W B_e + b``.
    fluxgate_bias_nT : array_like, shape (3,), optional
        ``b``: the fluxgate's bias (nT, zeros by default).
    warming_C : float
        How much the platform warms through the flight (degC); its temperature is recorded whether or not the
        platform's field follows it (``platform.temperature_nT_per_C``).

    Returns
    -------
    CompensationFlight
    """
    rng = np.random.default_rng(seed)
    platform = platform if platform is not None else CompensationPlatform()
    field_ned = np.asarray(field_ned_nT, dtype=float)
    base_periods = {"roll": 6.0, "pitch": 5.0, "yaw": 7.0} | dict(periods_s or {})
    periods = {kind: p * rng.uniform(0.9, 1.1) for kind, p in base_periods.items()}
    amplitudes = DEFAULT_AMPLITUDES_DEG | dict(amplitudes_deg or {})
    fine_rate = sample_rate_hz * _OVERSAMPLE
    args = (list(headings_deg), periods, cycles, straight_s, turn_s, turn_bank_deg, amplitudes)
    attitude_fine, maneuvers_fine = _schedule(*args, fine_rate)
    t_fine = np.arange(attitude_fine.shape[0]) / fine_rate
    earth_fine = _body_field(attitude_fine, field_ned)
    rate_fine = np.gradient(earth_fine, t_fine, axis=0)

    keep = slice(0, None, _OVERSAMPLE)
    t = t_fine[keep]
    n = t.size
    earth = earth_fine[keep]
    platform_field = platform.permanent_nT + earth @ platform.induced.T + rate_fine[keep] @ platform.eddy_s.T
    current = np.zeros(n)
    if platform.current_nT_per_A is not None:
        current = _current(n, sample_rate_hz, rng)
        platform_field = platform_field + current[:, None] * np.asarray(platform.current_nT_per_A)[None, :]
    currents = {}
    for j, (name, k) in enumerate(platform.currents_nT_per_A.items()):  # each wire its own switched loads
        currents[name] = _current(n, sample_rate_hz, np.random.default_rng([seed, 7, j]))
        platform_field = platform_field + currents[name][:, None] * np.asarray(k, dtype=float)[None, :]
    temperature = _temperature(t, warming_C, seed)
    if platform.temperature_nT_per_C is not None:
        warmer = (temperature - REFERENCE_TEMPERATURE_C)[:, None]
        platform_field = platform_field + warmer * np.asarray(platform.temperature_nT_per_C, dtype=float)[None, :]
    earth_total = np.linalg.norm(earth, axis=1)
    platform_scalar = np.linalg.norm(earth + platform_field, axis=1) - earth_total
    background = drift_nT * np.sin(2 * np.pi * t / (2.5 * t[-1]) + rng.uniform(0, 2 * np.pi))
    noise = rng.normal(0.0, scalar_noise_nT, n)
    scalar = earth_total + platform_scalar + background + noise
    lagged = np.column_stack([np.interp(t_fine[keep] - fluxgate_lag_s, t_fine, earth_fine[:, j]) for j in range(3)])
    if fluxgate_matrix is not None:
        lagged = lagged @ np.asarray(fluxgate_matrix, dtype=float).T
    if fluxgate_bias_nT is not None:
        lagged = lagged + np.asarray(fluxgate_bias_nT, dtype=float)
    flux = lagged + rng.normal(0.0, fluxgate_noise_nT, (n, 3))
    maneuvers = [
        FlownManeuver(m.heading_deg, m.kind, -(-m.start // _OVERSAMPLE), -(-m.stop // _OVERSAMPLE))
        for m in maneuvers_fine
    ]
    truth = CompensationTruth(
        platform=platform,
        field_ned_nT=field_ned,
        fluxgate_lag_s=float(fluxgate_lag_s),
        maneuvers=maneuvers,
        platform_scalar_nT=platform_scalar,
        earth_total_nT=earth_total + background,
        noise_nT=noise,
    )
    attitude = attitude_fine[keep].copy()
    attitude[:, 2] = np.mod(attitude[:, 2], 360.0)
    return CompensationFlight(t, float(sample_rate_hz), scalar, flux, attitude, current, temperature, truth, currents)
