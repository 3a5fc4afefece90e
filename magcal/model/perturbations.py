"""How the simulator hides effects in data: one perturbation per catalogue effect, and a few outside it.

:mod:`magcal.model.effects` says what each effect adds to the *model* (its basis and parameters); this module says how
:func:`magcal.data.simulation.simulate_timeseries` puts the same effect into *data*. A perturbation is written from
the physics of the effect rather than from its fitted basis: a delay is an exact time shift of the signal,
hysteresis is a play operator, a site gradient moves the field with the sensor's world position, a
reference-field variation scales the field vector, and so on. The fit of the model to such data is then a real
test of the model, not of its own forward equation.

Each catalogue effect's perturbation is a function registered here under the effect's name with
:func:`hides`; :meth:`magcal.model.effects.CatalogueEffect.perturbation` looks it up (so a user's effect may still
override :meth:`magcal.model.terms.Effect.perturbation` itself). A registered function is called as
``f(effect, readings, context, magnitude, sensor, **options)`` and returns the new readings (n_sensors, N, 3) in
nT; ``context`` is the dict :func:`~magcal.data.simulation.simulate_timeseries` passes (``fields_nT``, ``time_s``,
``temperature_C``, ``attitudes``, ``truth``, ``positions_m``, ``extra``: columns a perturbation adds to the
dataset, such as the ``current_A`` of ``current_field``; ``rng``, the simulation's random generator).

:func:`periodic_interference` builds the perturbation of the ``periodic_interference`` effect with its frequency and
direction spelled out; :data:`EXTRA_PERTURBATIONS` lists perturbations *outside* the catalogue for ``magcal
simulate --hidden NAME`` (none at present); :func:`parse_hidden` reads ``EFFECT[:SENSOR][=MAGNITUDE]`` as that
option writes it.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.ndimage import gaussian_filter1d

from magcal.core.errors import MagcalError
from magcal.model.operators import NONLINEARITY_REFERENCE_NT, gradient_matrix, play_operator
from magcal.model.terms import EFFECTS, parse_effect, parse_sensor_number

#: Temperature (degC) at which the simulator's temperature effects vanish (a factory calibration temperature).
SIMULATION_REFERENCE_TEMPERATURE_C = 20.0

#: Perturbation of each catalogue effect, by effect name: ``f(effect, readings, context, magnitude, sensor,
#: **options)``. Filled by :func:`hides`.
PERTURBATIONS: dict[str, Callable] = {}


def hides(*names):
    """Decorator: register a function as the perturbation of the catalogue effects ``names``."""

    def decorate(function):
        for name in names:
            PERTURBATIONS[name] = function
        return function

    return decorate


def perturbation_function(effect) -> Callable | None:
    """The registered perturbation of ``effect``: by its name, else by the name of the nearest catalogue class it
    derives from (a subclass of a built-in effect hides the same way); ``None`` if there is none."""
    for klass in type(effect).__mro__:
        name = klass.__dict__.get("name")
        if isinstance(name, str) and name in PERTURBATIONS:
            return PERTURBATIONS[name]
    return None


def catalogue_perturbation(effect, magnitude=None, sensor=None, **options):
    """The callable ``f(readings, context, rng)`` that hides ``effect`` (a catalogue effect) in simulated data.

    Parameters
    ----------
    effect : magcal.model.effects.CatalogueEffect
    magnitude : float or array_like, optional
        Largest parameter value (in the effect's ``magnitude_unit``), or the whole parameter vector of one
        sensor. Defaults to the effect's ``default_magnitude``.
    sensor : int, optional
        0-based sensor to hide the effect in (default: the effect's ``sensor``, or every sensor).
    **options
        Passed to the registered function (e.g. ``at_fraction`` of a bias step).

    Returns
    -------
    callable
        With the attributes ``description``, ``effect``, ``sensor`` (0-based or None) and ``magnitude``.

    Raises
    ------
    NotImplementedError
        When no perturbation is registered for the effect.
    """
    function = perturbation_function(effect)
    if function is None:
        raise NotImplementedError(f"{effect.name}: the simulator has no perturbation for this effect")
    magnitude = effect.default_magnitude if magnitude is None else magnitude
    sensor = effect.sensor if sensor is None else sensor
    where = "all sensors" if sensor is None else f"sensor {sensor + 1}"

    def perturb(readings, context, rng):
        # the quote of the magnitude may depend on the simulated field (nonlinearity: nT at |B|)
        unit = effect.quote_unit(float(context["truth"].total_nT)) if "truth" in context else effect.magnitude_unit
        perturb.description = f"{effect.name} {magnitude} {unit} ({where})"
        context["rng"] = rng  # the simulation's generator, for a perturbation with a random part (a jitter)
        return function(effect, np.array(readings, dtype=float), context, magnitude, sensor, **options)

    perturb.description = f"{effect.name} {magnitude} {effect.magnitude_unit} ({where})"
    perturb.effect = effect.name
    perturb.sensor = sensor
    perturb.magnitude = magnitude
    return perturb


# ----------------------------------------------------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------------------------------------------------


def _sensor_list(sensor, n_sensors, skip_first=False):
    if sensor is None:
        return list(range(1 if skip_first else 0, n_sensors))
    if not 0 <= sensor < n_sensors:
        raise MagcalError(f"sensor {sensor + 1} does not exist (the simulation has {n_sensors})")
    return [sensor]


def _linear_outputs(context, s):
    """Noise-free linear output ``C (I + S) B`` (nT) of sensor ``s`` (no offset): what an axis 'sees'."""
    sensor = context["truth"].sensors[s]
    return context["fields_nT"][s] @ sensor.total_matrix.T


def _shift_in_time(values, time_s, delays_s):
    """``values(t - delay)`` per column by cubic-spline interpolation (an exact delay of a smooth signal)."""
    spline = CubicSpline(time_s, values, axis=0, extrapolate=True)
    out = np.empty_like(values)
    for j, d in enumerate(np.broadcast_to(delays_s, (values.shape[1],))):
        out[:, j] = spline(time_s - d)[:, j] if d else values[:, j]
    return out


def _simulated_field_nT(context) -> float:
    """The magnitude of the simulated field (nT): the truth's, else the nonlinearity fallback of 50 uT."""
    truth = context.get("truth")
    return float(getattr(truth, "total_nT", None) or NONLINEARITY_REFERENCE_NT)


# ----------------------------------------------------------------------------------------------------------------
# the catalogue's perturbations
# ----------------------------------------------------------------------------------------------------------------


@hides("temperature_bias")
def _temperature_bias(effect, readings, context, magnitude, sensor, **options):
    """``y += beta (T - 20 degC)``: the bias vanishes at the factory temperature."""
    dT = context["temperature_C"] - SIMULATION_REFERENCE_TEMPERATURE_C
    for s in _sensor_list(sensor, readings.shape[0]):
        readings[s] += dT[:, None] * effect.true_params(magnitude, s)
    return readings


@hides("current_field")
def _current_field(effect, readings, context, magnitude, sensor, **options):
    """``y += k u`` with ``u`` a motor current (A) the simulator adds as the ``current_A`` column: a slow swing
    and steps (throttle changes), neither a function of time's trend nor of the temperature."""
    extra = context.setdefault("extra", {})
    if "current_A" not in extra:
        t = np.asarray(context["time_s"], dtype=float)
        span = max(float(t[-1] - t[0]), 1e-9)
        extra["current_A"] = (
            12.0 + 6.0 * np.sin(2 * np.pi * 3.3 * (t - t[0]) / span) + 4.0 * (np.floor(7.0 * (t - t[0]) / span) % 2)
        )
    u = extra["current_A"]
    for s in _sensor_list(sensor, readings.shape[0]):
        readings[s] += u[:, None] * effect.true_params(magnitude, s)
    return readings


@hides("temperature_scale")
def _temperature_scale(effect, readings, context, magnitude, sensor, **options):
    """``y_j += alpha_j (T - 20 degC) (C B)_j``, alpha in ppm/K."""
    dT = context["temperature_C"] - SIMULATION_REFERENCE_TEMPERATURE_C
    for s in _sensor_list(sensor, readings.shape[0]):
        alpha = effect.true_params(magnitude, s)
        readings[s] += 1e-6 * dT[:, None] * alpha * _linear_outputs(context, s)
    return readings


@hides("bias_drift")
def _bias_drift(effect, readings, context, magnitude, sensor, **options):
    """``y += gamma (t - t_first)``: a drift since power-on, gamma in nT/h."""
    t = context["time_s"]
    elapsed_h = (t - t[0]) / 3600.0
    for s in _sensor_list(sensor, readings.shape[0]):
        readings[s] += elapsed_h[:, None] * effect.true_params(magnitude, s)
    return readings


@hides("bias_step")
def _bias_step(effect, readings, context, magnitude, sensor, at_fraction=0.6, **options):
    """``y += db H(t - te)`` with ``te`` at ``at_fraction`` of the record."""
    t = context["time_s"]
    te = t[0] + at_fraction * (t[-1] - t[0])
    after = (t >= te).astype(float)
    for s in _sensor_list(sensor, readings.shape[0]):
        readings[s] += after[:, None] * effect.true_params(magnitude, s)
    return readings


@hides("nonlinearity_quadratic", "nonlinearity_cubic")
def _power_nonlinearity(effect, readings, context, magnitude, sensor, **options):
    """``y_j += k_j ((C B)_j / |B|)^order``: ``k_j`` is the deviation (nT) of an axis reading the whole simulated
    field magnitude ``|B|`` (the truth's), as the fitted parameters are quoted at the data's own field."""
    field_nT = _simulated_field_nT(context)
    for s in _sensor_list(sensor, readings.shape[0]):
        lin = _linear_outputs(context, s)
        readings[s] += effect.true_params(magnitude, s) * (lin / field_nT) ** effect.order
    return readings


@hides("axis_timing_skew")
def _axis_timing_skew(effect, readings, context, magnitude, sensor, **options):
    """Each axis an exact delay of the signal: ``y_j(t) = (C B)_j(t - tau_j)``; z undelayed unless 3 delays are
    given."""
    t = context["time_s"]
    for s in _sensor_list(sensor, readings.shape[0]):
        m = np.atleast_1d(np.asarray(magnitude, dtype=float))
        delays_ms = m if m.size == 3 else np.append(effect.true_params(magnitude, s), 0.0)
        readings[s] = _shift_in_time(readings[s], t, 1e-3 * delays_ms)
    return readings


@hides("eddy_currents")
def _eddy_currents(effect, readings, context, magnitude, sensor, **options):
    """``y += E dy0/dt`` with ``dy0/dt`` the exact rate of the noise-free linear output (a spline's derivative),
    ``E`` in ms: the field of currents induced in the platform by the changing field it sees."""
    t = np.asarray(context["time_s"], dtype=float)
    for s in _sensor_list(sensor, readings.shape[0]):
        E = np.asarray(effect.true_params(magnitude, s), dtype=float).reshape(3, 3)
        rate = CubicSpline(t, _linear_outputs(context, s), axis=0)(t, 1)
        readings[s] += 1e-3 * rate @ E.T
    return readings


@hides("attitude_time_offset")
def _attitude_time_offset(effect, readings, context, magnitude, sensor, **options):
    """The magnetometer's readings an exact delay ``d`` (ms) of the field its attitude describes: ``y(t) =
    y(t - d)`` by a spline through the whole reading (a negative ``d``: sampled after the attitude)."""
    t = np.asarray(context["time_s"], dtype=float)
    for s in _sensor_list(sensor, readings.shape[0]):
        delay_ms = float(np.ravel(effect.true_params(magnitude, s))[0])
        readings[s] = _shift_in_time(readings[s], t, 1e-3 * delay_ms)
    return readings


@hides("sensor_timing_skew")
def _sensor_timing_skew(effect, readings, context, magnitude, sensor, **options):
    """Sensors 2-4 read the field late by ``dt_i`` (ms): an exact delay of the whole vector."""
    if sensor == 0:
        raise MagcalError("sensor_timing_skew: sensor 1 is the time reference; delay sensor 2, 3 or 4")
    t = context["time_s"]
    for s in _sensor_list(sensor, readings.shape[0], skip_first=True):
        delay = effect.true_params(magnitude, s)[0] if sensor is None else float(np.ravel(magnitude)[0])
        readings[s] = _shift_in_time(readings[s], t, 1e-3 * delay)
    return readings


@hides("hysteresis")
def _hysteresis(effect, readings, context, magnitude, sensor, **options):
    """Each axis a play (backlash) operator of half-width ``h_j`` nT on its linear output: the output lags the
    field. A loop width is a width: a negative one is refused."""
    for s in _sensor_list(sensor, readings.shape[0]):
        h = np.asarray(effect.true_params(magnitude, s), dtype=float)
        if np.any(h < 0):
            raise MagcalError(
                f"hysteresis: the loop half-width must be >= 0 nT on every axis, got "
                f"{h.tolist()}; a hysteretic output lags the field, it cannot lead it"
            )
        lin = _linear_outputs(context, s)
        for j in range(3):
            if h[j] > 0:
                readings[s][:, j] += play_operator(lin[:, j], h[j]) - lin[:, j]
    return readings


@hides("reference_drift")
def _reference_drift(effect, readings, context, magnitude, sensor, period_fraction=1.6, **options):
    """A slow variation of the field magnitude by ``magnitude`` nT (peak), e.g. the diurnal variation: the whole
    field vector scales by ``F(t)/F0`` (direction unchanged)."""
    t = context["time_s"]
    duration = max(t[-1] - t[0], 1e-9)
    amplitude = float(np.ravel(magnitude)[0])
    delta = amplitude * np.sin(2 * np.pi * (t - t[0]) / (period_fraction * duration) + 0.4)
    total = context["truth"].total_nT
    for s in range(readings.shape[0]):
        readings[s] += _linear_outputs(context, s) * (delta / total)[:, None]
    return readings


@hides("site_gradient")
def _site_gradient(effect, readings, context, magnitude, sensor, **options):
    """The field at each sensor's world position ``B0 + G p`` (G symmetric, traceless, nT/m)."""
    g = gradient_matrix(effect.true_params(magnitude))
    att = context["attitudes"]
    truth = context["truth"]
    for s, p in enumerate(context["positions_m"]):
        d_world = att.apply(p) @ g.T  # field change at the sensor's world position, nT
        d_sensor = att.inv().apply(d_world) @ truth.sensors[s].M.T  # into the sensor's ideal frame
        readings[s] += d_sensor @ truth.sensors[s].total_matrix.T
    return readings


@hides("periodic_interference")
def _periodic_interference(
    effect,
    readings,
    context,
    magnitude,
    sensor,
    frequency_hz=0.7,
    direction=None,
    phase_rad=0.3,
    harmonic_fraction=0.0,
    **options,
):
    """A sinusoidal field from a source on the platform (a motor, a pump), fixed in the sensor's axes:
    ``y += a [sin(2 pi f t + phase) + h sin(4 pi f t + 2 phase)] d``, ``a = magnitude`` nT peak along the unit
    direction ``d`` (default the effect's ``pattern``), ``h = harmonic_fraction``."""
    d = np.asarray(effect.pattern if direction is None else direction, dtype=float)
    d = d / np.linalg.norm(d)
    amplitude = float(np.ravel(magnitude)[0])
    if not np.isfinite(frequency_hz) or frequency_hz <= 0:
        raise MagcalError(f"periodic_interference: the frequency must be a positive number of Hz, got {frequency_hz}")
    phase = 2 * np.pi * frequency_hz * context["time_s"] + phase_rad
    wave = amplitude * (np.sin(phase) + harmonic_fraction * np.sin(2 * phase))
    for s in _sensor_list(sensor, readings.shape[0]):
        readings[s] += wave[:, None] * d
    return readings


#: Time scale (s) of the simulator's wander: a random walk smoothed by a Gaussian of this width.
WANDER_SMOOTHING_S = 5.0


def _wander(time_s, index=0) -> np.ndarray:
    """A smooth wander of peak 1 over the record, as a hand-held path or a part warming up gives: a random walk
    (its own for each ``index``, an axis or a sensor; the same for every simulation) smoothed over
    :data:`WANDER_SMOOTHING_S`, mean removed. Not periodic, so that no spectral line stands for it."""
    t = np.asarray(time_s, dtype=float)
    step = float(np.median(np.diff(t))) if len(t) > 1 else 1.0
    walk = np.cumsum(np.random.default_rng(1000 + int(index)).normal(size=len(t)))
    w = gaussian_filter1d(walk, WANDER_SMOOTHING_S / max(step, 1e-9), mode="nearest")
    w -= w.mean()
    return w / max(float(np.max(np.abs(w))), 1e-12)


@hides("field_change")
def _field_change(effect, readings, context, magnitude, sensor, **options):
    """The field magnitude wanders by ``magnitude`` nT (peak) within seconds, as along a hand-held path through a
    non-uniform field: every sensor's field vector scales by ``(F + g(t)) / F`` (direction unchanged)."""
    g = float(np.ravel(magnitude)[0]) * _wander(context["time_s"])
    total = context["truth"].total_nT
    for s in range(readings.shape[0]):
        readings[s] += _linear_outputs(context, s) * (g / total)[:, None]
    return readings


@hides("offset_wander")
def _offset_wander(effect, readings, context, magnitude, sensor, **options):
    """Each sensor's offset wanders on its own within seconds: ``y_j += m_j w_j(t)`` with ``m`` the magnitude (nT
    peak) over the axes in the effect's pattern and ``w_j`` a smooth wander of its own per axis and sensor."""
    t = context["time_s"]
    m = np.ravel(np.asarray(magnitude, dtype=float))
    for s in _sensor_list(sensor, readings.shape[0]):
        peak = m if m.size == 3 else m[0] * np.roll(np.asarray(effect.pattern, dtype=float), s)
        for j in range(3):
            readings[s][:, j] += peak[j] * _wander(t, 3 * s + j + 1)
    return readings


@hides("sensor_jitter")
def _sensor_jitter(effect, readings, context, magnitude, sensor, **options):
    """Sensors 2-4 sampled at ``t + dt`` with ``dt`` random (normal, RMS ``tau`` ms) at every sample: each reading
    is the signal at its own instant (a spline through the clean readings), sensor 1 on time."""
    if sensor == 0:
        raise MagcalError("sensor_jitter: sensor 1 is the time reference; give sensor 2, 3 or 4 a jitter")
    t = np.asarray(context["time_s"], dtype=float)
    rng = context.get("rng") or np.random.default_rng(0)
    for s in _sensor_list(sensor, readings.shape[0], skip_first=True):
        tau_ms = float(np.ravel(magnitude)[0]) * (effect.pattern[s % 4] if sensor is None else 1.0)
        if tau_ms < 0:
            raise MagcalError(f"sensor_jitter: the jitter is an RMS time in ms, >= 0; got {tau_ms}")
        spline = CubicSpline(t, readings[s], axis=0)
        readings[s] = spline(t - 1e-3 * rng.normal(0.0, tau_ms, size=t.size))
    return readings


def periodic_interference(
    amplitude_nT=5.0, frequency_hz=0.7, sensor=None, direction=(0.6, -0.5, 0.62), harmonic_fraction=0.0
):
    """The perturbation of the catalogue effect ``periodic_interference`` with its options spelled out: a
    sinusoidal field (e.g. from machinery on the platform) along a fixed direction of the sensor's axes,
    ``y += a sin(2 pi f t + 0.3) d`` (plus ``harmonic_fraction`` of it at ``2 f``).

    Parameters
    ----------
    amplitude_nT : float
        Peak amplitude, nT.
    frequency_hz : float
        Frequency, Hz.
    sensor : int, optional
        0-based sensor; default every sensor.
    direction : array_like, shape (3,)
        Direction in the sensor axes (normalised).
    harmonic_fraction : float
        Amplitude of the second harmonic relative to the fundamental.
    """

    perturb = EFFECTS["periodic_interference"]().perturbation(
        float(amplitude_nT),
        sensor,
        frequency_hz=float(frequency_hz),
        direction=direction,
        harmonic_fraction=float(harmonic_fraction),
    )
    perturb.description = f"periodic_interference {amplitude_nT} nT at {frequency_hz} Hz" + (
        "" if sensor is None else f" (sensor {sensor + 1})"
    )
    return perturb


#: Perturbations outside the catalogue that ``magcal simulate --hidden`` also knows (name -> factory taking
#: ``magnitude`` and ``sensor``). :func:`magcal.model.plugins.reserved_names` keeps a user's effect from taking them.
#: (Periodic interference was one until it joined the catalogue as ``periodic_interference``.)
EXTRA_PERTURBATIONS: dict[str, Callable] = {}


def parse_hidden(spec: str, n_sensors: int):
    """A perturbation from ``EFFECT[:SENSOR][=MAGNITUDE]`` (SENSOR 1-based), as ``magcal simulate --hidden``.

    Returns
    -------
    callable
        For :func:`magcal.data.simulation.simulate_timeseries`; it has ``description``, ``effect``, ``sensor``
        (0-based or None) and ``magnitude`` attributes.

    Raises
    ------
    MagcalError
        Unknown effect, bad sensor number or magnitude.
    NotImplementedError
        The effect (a user's) has no perturbation.
    """
    text = spec.strip()
    head, _, mag_text = text.partition("=")
    magnitude = None
    if mag_text.strip():
        try:
            values = [float(v) for v in mag_text.replace(";", ",").split(",") if v.strip()]
        except ValueError:
            raise MagcalError(
                f"--hidden {spec!r}: the magnitude after '=' must be a number (or comma-separated "
                "numbers, one per parameter)"
            ) from None
        magnitude = values[0] if len(values) == 1 else values
    name, _, sensor_text = head.partition(":")
    name = name.strip()
    if name in EXTRA_PERTURBATIONS:
        sensor = None
        if sensor_text.strip():
            sensor = parse_sensor_number(spec, sensor_text, n_sensors)
        return EXTRA_PERTURBATIONS[name](magnitude, sensor)
    effect = parse_effect(head, n_sensors)
    if effect.min_sensors > n_sensors:
        raise MagcalError(f"--hidden {spec!r}: {name} needs at least {effect.min_sensors} sensors")
    return effect.perturbation(magnitude, effect.sensor)
