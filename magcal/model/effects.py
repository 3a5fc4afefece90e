"""The catalogue of candidate effects beyond the base model.

Every effect here is an :class:`magcal.model.terms.Effect` registered in :data:`magcal.model.terms.EFFECTS` under its name.
Each one says

* what it adds to the readings (its *basis*, the Jacobian of the correction with respect to its parameters, in
  the stage of :mod:`magcal.model.terms`: ``raw`` acts on one sensor's raw reading in its own axes, ``array`` on the
  corrected vector in the array frame, ``reference`` on the expected total field);
* its parameters, with units chosen so that the numbers read naturally (nT/K, ppm/K, nT/h, ms, nT/m...), and
  :meth:`~magcal.model.terms.Effect.param_scale`, the size of each parameter that moves the readings by about 1 nT;
* the data-derived constants it needs (reference temperature, reference time, step time, time span), set by
  :meth:`~magcal.model.terms.Effect.configure` and saved with a calibration by :meth:`~magcal.model.terms.Effect.state`;
* whether it describes the instrument and carries to new data (:attr:`~magcal.model.terms.Effect.transferable`), or
  one recording only.

How the simulator hides each effect in data (:meth:`~magcal.model.terms.Effect.perturbation`) is in
:mod:`magcal.model.perturbations`, written from the physics of the effect rather than from its fitted basis;
:meth:`CatalogueEffect.perturbation` looks the function up there by the effect's name.

Notation: for sensor ``s``, ``z0 = y - b`` is the raw reading minus the bias (nT, sensor axes, approximately
``C B``), ``T`` the temperature (degC), ``t`` the time (s). The signatures in the total-field residual and the
confounders of every effect are in ``docs/effects.md``.

A ``magnitude`` given to :meth:`CatalogueEffect.perturbation` is either one number, the largest parameter value (the
parameters follow a fixed pattern over the axes, different for each sensor), or the full parameter vector of
one sensor; :meth:`CatalogueEffect.true_params` returns the parameter vector the perturbation corresponds to, where the fitted
model can represent it exactly (``None`` otherwise).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
import scipy.fft
from scipy.interpolate import BSpline, CubicSpline
from scipy.special import eval_legendre

from magcal.core.errors import MagcalError
from magcal.core.readings_cache import ReadingsCache
from magcal.core.rows import row_norm
from magcal.core.stats import savgol, savgol_derivative
from magcal.data.attitude import turn_rate_dps
from magcal.geometry.shape import field_shape
from magcal.model.operators import GRADIENT_BASIS, NONLINEARITY_REFERENCE_NT, play_operator
from magcal.model.perturbations import catalogue_perturbation
from magcal.model.terms import Context, Domain, Effect, SingleAxisBasis, register, term_label

#: Multipliers of each effect's ``default_magnitude`` for a 1 500-sample record at 10 Hz with sigma = 3 nT
#: (:func:`magcal.data.simulation.simulate_timeseries`): barely detectable (score statistic of order 100-200, the RMS
#: only a few percent above the floor), moderate (RMS >~ 1.2x the floor) and strong (RMS 1.4-5x the floor). The
#: diagnosis tests and ``benchmarks/diagnosis.py`` hide each effect at these sizes.
DETECTION_LEVELS = {
    "temperature_bias": (0.27, 1.0, 3.0),
    "temperature_scale": (0.45, 1.5, 3.0),
    "bias_drift": (0.39, 1.0, 3.0),
    "bias_step": (0.34, 1.0, 3.0),
    "nonlinearity_quadratic": (0.31, 1.0, 3.0),
    "nonlinearity_cubic": (0.53, 1.5, 3.0),
    "axis_timing_skew": (1.0, 4.0, 6.0),
    "hysteresis": (0.34, 1.0, 2.0),
    "reference_drift": (0.39, 1.0, 3.0),
    "sensor_timing_skew": (0.35, 2.5, 5.0),
    "site_gradient": (0.15, 1.0, 3.0),
}

_AXES = "xyz"

#: The largest transfer nonlinearity a magnetometer has (ppm of its field, either sign): a fluxgate's is tens to
#: hundreds of ppm, a MEMS or AMR sensor's up to a few thousand; beyond this the fit has found something else.
NONLINEARITY_LIMIT_PPM = 5000.0

#: The largest change of a scale factor with temperature (ppm/K, either sign): a fluxgate's is tens of ppm/K, an AMR
#: or Hall sensor's up to a few thousand (0.3 %/K uncompensated).
TEMPERATURE_SCALE_LIMIT_PPM_PER_K = 10000.0

#: A time offset shows in a record only while the field turns less than this (rad) over it: beyond, the readings
#: pair with attitudes of another part of the turn and the offset found is an alias (:func:`record_delay_limit_ms`).
DELAY_TURN_LIMIT_RAD = 1.0


# ----------------------------------------------------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------------------------------------------------


def _field_text(field_nT) -> str:
    """``"35.7 uT"``: a field magnitude given in nT, as the quotes print it."""
    return f"{field_nT / 1000.0:.3g} uT"


def _axes_text(values, fmt="{:.3g}") -> str:
    """``"(1.2, -3, 0.5)"``: one number per axis."""
    return "(" + ", ".join(fmt.format(float(v)) for v in values) + ")"


def _diagonal_basis(columns):
    """(N, 3, 3) basis with ``columns[:, j]`` on the diagonal (one parameter per axis), a
    :class:`~magcal.model.terms.SingleAxisBasis`."""
    return SingleAxisBasis(columns, np.arange(3))


#: Span (s) of the smoothing that the hysteresis term's reversals are found on (:func:`smoothed_readings`).
REVERSAL_SMOOTHING_S = 0.2


def smoothed_readings(values, time_s, span_s=REVERSAL_SMOOTHING_S):
    """The readings fitted in time (a cubic Savitzky-Golay fit over ``span_s`` seconds, at least 7 samples, at
    most 51), for regularly sampled records; the readings themselves otherwise.

    The hysteresis term takes its reversals (the play operator's turning points) from this fitted field, not
    from the noisy readings: at 100 Hz the noise of a few nT turns the play operator of a few-nT loop back and
    forth while an axis changes slowly.
    """
    values = np.asarray(values, dtype=float)
    if time_s is None or len(time_s) < 7:
        return values
    t = np.asarray(time_s, dtype=float)
    n = len(t)
    dt = np.diff(t)
    step = float(np.median(dt))
    if not (step > 0 and np.all(np.abs(dt - step) <= 0.01 * step)):
        return values
    window = int(np.clip(round(span_s / step), 7, 51))
    window += 1 - window % 2
    if window > n:
        return values
    return savgol(values, window)


def time_derivative(values, time_s, window=7):
    """Smoothed time derivative along axis 0 (units of ``values`` per second).

    A Savitzky-Golay derivative (cubic, ``window`` samples) when the sampling is regular, otherwise
    :func:`numpy.gradient` with the actual sample times.

    Parameters
    ----------
    values : numpy.ndarray, shape (N, ...)
    time_s : numpy.ndarray, shape (N,)
    window : int
        Odd number of samples of the smoothing window.
    """
    values = np.asarray(values, dtype=float)
    t = np.asarray(time_s, dtype=float)
    n = len(t)
    if n < 3:
        return np.zeros_like(values)
    dt = np.diff(t)
    step = float(np.median(dt))
    regular = step > 0 and np.all(np.abs(dt - step) <= 0.01 * step)
    if regular and n >= window:
        return savgol_derivative(values, window, step)
    return np.gradient(values, t, axis=0)


def _state_number(effect, state, key, minimum=None, positive=False, what=""):
    """``state[key]`` as a float (None when absent), or a clear :class:`MagcalError` naming the term and the key if
    it is not a finite number, not above 0 (``positive``) or below ``minimum``: a calibration file's data-derived
    constants must be physical too."""
    value = state.get(key)
    if value is None:
        return None
    try:
        number = float(value)
    except (TypeError, ValueError):
        number = float("nan")
    bad = not np.isfinite(number) or (positive and number <= 0) or (minimum is not None and number < minimum)
    if bad:
        need = (
            "a positive number" if positive else "a finite number" + (f" >= {minimum:g}" if minimum is not None else "")
        )
        raise MagcalError(f"{effect.label}: {key} must be {need}{f' ({what})' if what else ''}, got {value!r}")
    return number


def _state_times(effect, state, key):
    """``state[key]``: a list of per-sensor times in s (finite numbers or None), or a clear error."""
    value = state.get(key)
    if value is None:
        return None
    if not isinstance(value, (list, tuple)):
        raise MagcalError(f"{effect.label}: {key} must be a list (one time in s per sensor, or null), got {value!r}")
    return [_state_number(effect, {key: v}, key, what="a time in s") for v in value]


class _Cache:
    """A small per-instance cache keyed by the identity of a dataset (the entry keeps the dataset alive)."""

    def __init__(self):
        self.entries = {}

    def get(self, dataset, key, compute):
        full = (id(dataset), key)
        hit = self.entries.get(full)
        if hit is not None and hit[0] is dataset:
            return hit[1]
        if len(self.entries) > 16:
            self.entries.clear()
        value = compute()
        self.entries[full] = (dataset, value)
        return value


@dataclass
class CatalogueEffect(Effect):
    """Shared machinery of the catalogue: parameter patterns for the simulator and a basis cache."""

    #: Default ``magnitude`` of :meth:`perturbation` (in :attr:`magnitude_unit`): clearly visible with
    #: 1 500 samples and 3 nT noise.
    default_magnitude: ClassVar[float] = 1.0
    #: Unit of ``magnitude``.
    magnitude_unit: ClassVar[str] = ""
    #: Pattern of the parameters over the axes (largest entry 1) used when ``magnitude`` is one number.
    pattern: ClassVar[tuple] = (1.0, -0.7, 0.5)
    #: Extra degrees of freedom searched in :meth:`configure` per instance (e.g. a step time), for the
    #: information criteria of the diagnosis.
    extra_dof: ClassVar[int] = 0

    _cache: object = field(default=None, repr=False, compare=False)

    def __post_init__(self):
        if self._cache is None:
            self._cache = _Cache()

    def _cached(self, dataset, key, compute):
        if self._cache is None:
            self._cache = _Cache()
        return self._cache.get(dataset, key, compute)

    def true_params(self, magnitude=None, sensor=0):
        """Parameter vector of one sensor's instance that :meth:`perturbation` hides (None if not exact)."""
        magnitude = self.default_magnitude if magnitude is None else magnitude
        m = np.atleast_1d(np.asarray(magnitude, dtype=float))
        q = len(self.param_names())
        if m.size == q:
            return m.copy()
        if m.size != 1:
            raise MagcalError(f"{self.name}: magnitude must be one number or {q} values, got {m.size}")
        pattern = np.asarray(self.pattern, dtype=float)[:q]
        return m[0] * np.roll(pattern, sensor or 0) if len(pattern) == 3 else m[0] * pattern

    def perturbation(self, magnitude=None, sensor=None, **options):
        """A callable ``f(readings, context, rng)`` for :func:`magcal.data.simulation.simulate_timeseries` that hides
        this effect in data: the function registered for this effect's name in :mod:`magcal.model.perturbations`
        (a subclass may override this method instead).

        Parameters
        ----------
        magnitude : float or array_like, optional
            Largest parameter value (in :attr:`magnitude_unit`), or the whole parameter vector of one sensor.
            Defaults to :attr:`default_magnitude`.
        sensor : int, optional
            0-based sensor to hide the effect in (default: this effect's ``sensor``, or every sensor).

        Raises
        ------
        NotImplementedError
            When the simulator has no perturbation for the effect.
        """

        return catalogue_perturbation(self, magnitude, sensor, **options)

    def quote_unit(self, field_nT=None) -> str:
        """The unit a magnitude or parameter of this effect is quoted in (:attr:`magnitude_unit`); effects whose
        parameters are quoted at a field magnitude say which (``field_nT``, nT, when known)."""
        return self.magnitude_unit


# ----------------------------------------------------------------------------------------------------------------
# temperature
# ----------------------------------------------------------------------------------------------------------------


@dataclass
class _TemperatureReferenced(CatalogueEffect):
    """Shared by the temperature terms: ``T0`` is the mean temperature of the fitted data, saved with the fit."""

    reference_temperature_C: float | None = None

    def configure(self, dataset, residuals_nT=None):
        self.reference_temperature_C = float(np.mean(dataset.temperature_C))

    def state(self):
        return {"reference_temperature_C": self.reference_temperature_C}

    def set_state(self, state):
        self.reference_temperature_C = _state_number(
            self, state, "reference_temperature_C", minimum=-273.15, what="a temperature in degC"
        )

    def _dT(self, ctx):
        """Temperature minus ``T0`` (K); before any fit, minus the mean temperature."""
        t0 = self.reference_temperature_C
        temp = ctx.temperature_C
        return temp - (np.mean(temp) if t0 is None else t0)


@register
@dataclass
class TemperatureBias(_TemperatureReferenced):
    """Bias that changes with temperature: ``y += beta (T - T0)``, ``beta`` per axis in nT/K."""

    name: ClassVar[str] = "temperature_bias"
    signature: ClassVar[str] = "residual follows (T - T0) x field direction (degree 1)"
    vector_signature: ClassVar[str] = "world residual follows the temperature"
    evidence_channel: ClassVar[str] = "temperature_C"
    basis_uses_readings: ClassVar[bool] = False  # a function of the channels only
    stage: ClassVar[str] = "raw"
    channels: ClassVar[tuple] = ("temperature",)
    description: ClassVar[str] = "bias changing with temperature, y += beta (T - T0) [nT/K per axis]"
    default_magnitude: ClassVar[float] = 2.0
    magnitude_unit: ClassVar[str] = "nT/K"

    def param_names(self):
        return [f"beta_{a}_nT_per_K" for a in _AXES]

    def param_scale(self):
        return np.full(3, 0.3)

    def raw_basis(self, z0, ctx: Context):
        return _diagonal_basis(np.repeat(self._dT(ctx)[:, None], 3, axis=1))


@register
@dataclass
class TemperatureScale(_TemperatureReferenced):
    """Scale factors that change with temperature: ``y_j += alpha_j (T - T0) (C B)_j``, ``alpha`` in ppm/K."""

    name: ClassVar[str] = "temperature_scale"
    signature: ClassVar[str] = "residual follows (T - T0) x direction degrees 0 and 2"
    vector_signature: ClassVar[str] = "world residual follows the temperature times the field"
    evidence_channel: ClassVar[str] = "temperature_C"
    stage: ClassVar[str] = "raw"
    channels: ClassVar[tuple] = ("temperature",)
    description: ClassVar[str] = "scale factors changing with temperature, y_j += alpha_j (T - T0) (CB)_j [ppm/K]"
    default_magnitude: ClassVar[float] = 30.0
    magnitude_unit: ClassVar[str] = "ppm/K"

    def param_names(self):
        return [f"alpha_{a}_ppm_per_K" for a in _AXES]

    def domain(self):
        """``|alpha| <= TEMPERATURE_SCALE_LIMIT_PPM_PER_K`` on every axis."""
        return Domain.symmetric(
            3,
            TEMPERATURE_SCALE_LIMIT_PPM_PER_K,
            "a scale factor's change with temperature: tens of ppm/K for a fluxgate, a few thousand for an AMR or "
            "Hall sensor",
        )

    def param_scale(self):
        return np.full(3, 6.0)

    def raw_basis(self, z0, ctx: Context):
        return _diagonal_basis(1e-6 * self._dT(ctx)[:, None] * z0)

    def quote(self, values, field_nT=None, sensor=None):
        """``alpha_j F`` in nT/K: how much an axis reading the whole field ``F`` changes per kelvin."""
        if not field_nT:
            return ""
        per_K = 1e-6 * np.asarray(values, dtype=float) * field_nT
        return (
            f"at the data's field {_field_text(field_nT)}: an axis reading the whole field changes by "
            f"{_axes_text(per_K)} nT/K"
        )


# ----------------------------------------------------------------------------------------------------------------
# the platform: a current's field
# ----------------------------------------------------------------------------------------------------------------

#: Columns (in ``Dataset.extra``) a current's field reads, the first present wins, and their units.
CURRENT_COLUMNS = {"current_A": "A", "throttle": "unit of throttle"}


def current_column(dataset) -> str | None:
    """The current or throttle column of the dataset (``current_A``, else ``throttle``), or None."""
    for name in CURRENT_COLUMNS:
        value = dataset.extra.get(name)
        if value is not None and np.asarray(value).dtype.kind in "fiu":
            return name
    return None


@register
@dataclass
class CurrentField(CatalogueEffect):
    """Field of a current on the platform (a motor, a bus, a pump): ``y += k u``, ``u`` the ``current_A`` column
    (A; else ``throttle``), ``k`` per axis in nT per unit: what ArduPilot's ``COMPASS_MOT_*`` and PX4's
    ``CAL_MAGn_[XYZ]COMP`` hold. The column is chosen when the term is configured and saved with it."""

    name: ClassVar[str] = "current_field"
    signature: ClassVar[str] = "residual follows the current (or throttle) column x field direction (degree 1)"
    vector_signature: ClassVar[str] = "world residual follows the current (or throttle) column"
    evidence_channel: ClassVar[str] = "current"
    basis_uses_readings: ClassVar[bool] = False  # a function of the current column only
    stage: ClassVar[str] = "raw"
    description: ClassVar[str] = (
        "field of a motor or bus current, y += k u (u: the current_A or throttle column) [nT per A]"
    )
    default_magnitude: ClassVar[float] = 5.0
    magnitude_unit: ClassVar[str] = "nT/A"

    column: str | None = None

    def _column_of(self, dataset):
        if self.column is not None:
            value = dataset.extra.get(self.column)
            return self.column if value is not None and np.asarray(value).dtype.kind in "fiu" else None
        return current_column(dataset)

    def missing_channels(self, dataset):
        missing = [] if self._column_of(dataset) else [self.column or "a current_A or throttle column"]
        if dataset.n_sensors < self.min_sensors:
            missing.append(f"at least {self.min_sensors} sensors")
        return missing

    def configure(self, dataset, residuals_nT=None):
        self.column = self._column_of(dataset)

    def state(self):
        return {"column": self.column}

    def set_state(self, state):
        column = state.get("column")
        if column is not None and column not in CURRENT_COLUMNS:
            raise MagcalError(f"{self.label}: column must be one of {', '.join(CURRENT_COLUMNS)}, got {column!r}")
        self.column = column

    def param_names(self):
        """``k_x_nT_per_A`` ... for a ``current_A`` column, ``k_x_nT_per_unit`` for ``throttle`` (or before the
        column is chosen)."""
        unit = "A" if self.column == "current_A" else "unit"
        return [f"k_{a}_nT_per_{unit}" for a in _AXES]

    def former_param_names(self):
        """The names calibrations saved before the current's unit was in them (read, never written)."""
        return [f"k_{a}_nT_per_unit" for a in _AXES]

    def param_scale(self):
        return np.full(3, 0.1)

    def raw_basis(self, z0, ctx: Context):
        column = self._column_of(ctx.dataset)
        u = np.asarray(ctx.dataset.extra[column], dtype=float)
        return _diagonal_basis(np.repeat(u[:, None], 3, axis=1))


@register
@dataclass
class EddyCurrents(CatalogueEffect):
    """Eddy currents in the platform (an airframe, a hull, a board's ground plane): a field proportional to the
    rate of change of the field the platform sees (Tolles-Lawson's eddy terms), ``y += E dy/dt``, ``E`` a 3 x 3
    matrix in ms (nT per nT/s, times 1000), row ``j`` moving axis ``j``.

    ``dy/dt`` is the smoothed rate of the sensor's own reading (:func:`time_derivative`), ``C R^T dB_body/dt`` to
    first order, so ``E`` is the eddy field per body-field rate in the sensor's axes. A delay common to the three
    axes is ``E = d I`` (:class:`AttitudeTimeOffset` is that one number); the total field cannot see the full
    matrix, so the term is judged in vector mode only.
    """

    name: ClassVar[str] = "eddy_currents"
    vector_signature: ClassVar[str] = "residual follows the rate of change of the field (turns), differently per axis"
    evidence_channel: ClassVar[str] = "turn_rate_dps"
    stage: ClassVar[str] = "raw"
    channels: ClassVar[tuple] = ("time",)
    modes: ClassVar[tuple] = ("vector",)
    description: ClassVar[str] = "eddy currents of the platform, y += E dy/dt (E a 3 x 3 matrix) [ms]"
    default_magnitude: ClassVar[float] = 10.0
    magnitude_unit: ClassVar[str] = "ms"
    pattern: ClassVar[tuple] = (1.0, -0.6, 0.3, 0.4, 0.8, -0.5, -0.2, 0.5, 0.9)
    signature: ClassVar[str] = "invisible in the total field (vector mode only)"
    when_recording: ClassVar[str] = (
        "eddy currents follow how fast the platform turns: fly the calibration pattern at the turn rates of the "
        "survey, keep the sensor away from large conducting plates (a boom, a tail stinger)"
    )

    def param_names(self):
        return [f"E_{a}{b}_ms" for a in _AXES for b in _AXES]

    def param_scale(self):
        return np.full(9, 0.1)

    def raw_basis(self, z0, ctx: Context):
        rate = 1e-3 * _platform_rate(self, ctx)
        basis = np.zeros((len(rate), 3, 9))
        for j in range(3):
            basis[:, j, 3 * j : 3 * j + 3] = rate
        return basis

    def true_params(self, magnitude=None, sensor=0):
        magnitude = self.default_magnitude if magnitude is None else magnitude
        m = np.atleast_1d(np.asarray(magnitude, dtype=float))
        if m.size == 9:
            return m.copy()
        return m[0] * np.roll(np.asarray(self.pattern), 3 * (sensor or 0))


#: The readings are fitted in time for the time offset's regressor only while the field turns less than this (rad)
#: over the smoothing's window (at its 95th percentile): a cubic fit bends faster turns by more than a few nT.
SMOOTH_TURN_RAD = 0.15


def _platform_rate(effect, ctx):
    """d y / d t (nT/s) of the context's sensor for the platform's rate terms (eddy currents, a time offset): the
    smoothed derivative (:func:`time_derivative`) while the field turns slowly over its window, else the derivative
    of a cubic spline through the readings (a fast turn that the smoothing would bend); cached per dataset."""

    def compute():
        y = np.asarray(ctx.reading_nT, dtype=float)
        t = np.asarray(ctx.time_s, dtype=float)
        if _unless_it_bends(y, t) is y and len(t) > 3 and np.all(np.diff(t) > 0):
            return CubicSpline(t, y, axis=0)(t, 1)
        return time_derivative(y, t)

    return effect._cached(ctx.dataset, ("platform rate", ctx.sensor), compute)


def _unless_it_bends(values, time_s):
    """The readings fitted in time (:func:`smoothed_readings`) when the field turns slowly over the smoothing's
    window (:data:`SMOOTH_TURN_RAD`), else the readings themselves: the fit would bend a fast turn."""
    smooth = smoothed_readings(values, time_s)
    if smooth is values:
        return values
    t = np.asarray(time_s, dtype=float)
    step = float(np.median(np.diff(t)))
    window = int(np.clip(round(REVERSAL_SMOOTHING_S / step), 7, 51)) * step
    turn = np.linalg.norm(np.gradient(smooth, t, axis=0), axis=1) / np.maximum(np.linalg.norm(smooth, axis=1), 1e-9)
    return smooth if float(np.percentile(turn, 95)) * window <= SMOOTH_TURN_RAD else values


def record_delay_limit_ms(dataset) -> float | None:
    """The largest time offset (ms) a record can show: the time its field takes to turn by
    :data:`DELAY_TURN_LIMIT_RAD` at the record's 95th-percentile turn rate (:func:`magcal.data.attitude.turn_rate_dps`:
    the gyro, else the attitude; else the turn of the readings), and no more than half the record. None without a
    time column.

    A delay beyond it pairs each reading with the attitude of another part of the turn: the fit may still lower the
    residuals with it, but the offset it finds is an alias, not the logging path's.
    """
    t = getattr(dataset, "time_s", None)
    if t is None or len(t) < 3:
        return None
    t = np.asarray(t, dtype=float)
    span_s = float(np.nanmax(t) - np.nanmin(t))
    if not np.isfinite(span_s) or span_s <= 0:
        return None
    rate_dps = turn_rate_dps(dataset)
    if rate_dps is None:
        y = np.asarray(dataset.readings_nT[0], dtype=float)
        rate_dps = np.degrees(row_norm(time_derivative(y, t)) / np.maximum(row_norm(y), 1e-9))
    rate_dps = np.asarray(rate_dps, dtype=float)
    rate_dps = rate_dps[np.isfinite(rate_dps)]
    turn_s = np.inf
    if rate_dps.size and float(np.percentile(rate_dps, 95)) > 0:
        turn_s = DELAY_TURN_LIMIT_RAD / np.radians(float(np.percentile(rate_dps, 95)))
    return float(1e3 * min(turn_s, 0.5 * span_s))


@register
@dataclass
class AttitudeTimeOffset(CatalogueEffect):
    """A time offset between the magnetometer's samples and the attitude they are paired with: the reading stamped
    ``t`` is the field of the attitude at ``t - d``, ``y(t) = y_true(t - d)``, ``d`` in ms (positive: the
    magnetometer lags its attitude; negative: it was sampled after it).

    A logging path, a filter or a bus that delays one stream more than the other does this; a vehicle that turns at
    ``w`` rad/s then sees an error of ``w d |B|`` perpendicular to the field (80 ms at 30 deg/s on 50 uT: 2 uT).
    The total field cannot see it (a delayed field has the same magnitude), so it is judged in vector mode only. It
    belongs to the logging path and carries to new data of the same vehicle.

    The correction is the reading moved in time, ``z(t) = y(t + d)``, linear in ``d`` about a shift ``s`` per
    sensor (:attr:`shift_ms`, a data-derived constant): ``z = y + d (y(t + s) - y(t)) / s``, the readings
    fitted in time (:func:`smoothed_readings`) while the field turns slowly over the smoothing's window, else the
    readings themselves (the smoothing would bend a fast turn), interpolated by a cubic spline and continued past the record's ends
    by it (the noise of the readings in the regressor would bias ``d`` towards 0 on a slow record); ``s = 0`` is the derivative, ``z = y + d dy/dt``, whose own error is ``(w d)^2 |B| / 2`` (0.1 nT at
    2 deg/s and 80 ms, 44 nT at 30 deg/s). :meth:`refine` sets ``s`` to the fitted ``d`` and the fit is repeated, so
    the correction is exact at the offset found.
    """

    name: ClassVar[str] = "attitude_time_offset"
    vector_signature: ClassVar[str] = "world residual perpendicular to the field, proportional to the turn rate"
    evidence_channel: ClassVar[str] = "turn_rate_dps"
    stage: ClassVar[str] = "raw"
    channels: ClassVar[tuple] = ("time",)
    modes: ClassVar[tuple] = ("vector",)
    nested_in: ClassVar[tuple] = ("eddy_currents",)
    description: ClassVar[str] = "time offset between the magnetometer and the attitude, y(t) = y_true(t - d) [ms]"
    default_magnitude: ClassVar[float] = 80.0
    magnitude_unit: ClassVar[str] = "ms"
    pattern: ClassVar[tuple] = (1.0,)
    signature: ClassVar[str] = "invisible in the total field (vector mode only)"
    when_recording: ClassVar[str] = (
        "stamp the magnetometer and the attitude on one clock (the autopilot's log does; a companion computer's "
        "merge may not), or give the offset found here to the logger"
    )

    shift_ms: list | None = None
    #: The largest offset the fitted record can show (ms, either sign; :func:`record_delay_limit_ms`), set by
    #: :meth:`configure`; None: unbounded.
    max_delay_ms: float | None = None

    def param_names(self):
        return ["delay_ms"]

    def param_scale(self):
        return np.array([0.1])

    def domain(self):
        """``|d| <= max_delay_ms``: within what the record can show."""
        if self.max_delay_ms is None:
            return Domain.free(1)
        return Domain.symmetric(
            1,
            self.max_delay_ms,
            f"an offset the record can show: its field turns less than {DELAY_TURN_LIMIT_RAD:g} rad over it, "
            "and it is shorter than half the record",
        )

    def configure(self, dataset, residuals_nT=None):
        self.max_delay_ms = record_delay_limit_ms(dataset)

    def state(self):
        return {"shift_ms": self.shift_ms, "max_delay_ms": self.max_delay_ms}

    def set_state(self, state):
        self.max_delay_ms = _state_number(
            self, state, "max_delay_ms", positive=True, what="of ms: the largest offset the record can show"
        )
        shifts = state.get("shift_ms")
        if shifts is None:
            self.shift_ms = None
            return
        if not isinstance(shifts, list) or not all(
            v is None or (isinstance(v, (int, float)) and np.isfinite(v) and abs(v) <= 1e5) for v in shifts
        ):
            raise MagcalError(f"{self.label}: shift_ms must be a list of delays in ms (or null), got {shifts!r}")
        self.shift_ms = [None if v is None else float(v) for v in shifts]

    def _shift(self, sensor) -> float:
        shifts = self.shift_ms or []
        value = shifts[sensor] if sensor < len(shifts) else None
        return 0.0 if value is None else float(value)

    def raw_basis(self, z0, ctx: Context):
        shift = self._shift(ctx.sensor)
        t = np.asarray(ctx.time_s, dtype=float)
        if shift == 0.0 or not np.all(np.diff(t) > 0):  # the derivative (a time column that repeats: no spline)
            rate = _platform_rate(self, ctx)
            return -1e-3 * rate[:, :, None]

        def moved():
            y = _unless_it_bends(np.asarray(ctx.reading_nT, dtype=float), t)
            later = CubicSpline(t, y, axis=0, extrapolate=True)(t + 1e-3 * shift)  # past the ends: by the spline
            return -(later - y) / shift

        return self._cached(ctx.dataset, ("moved", ctx.sensor, shift), moved)[:, :, None]

    def refine(self, effect_values, context=None):
        """Move each sensor's shift to its fitted delay (True when one moved by more than 0.2 ms and 1 %: the fit
        is then repeated with the bases at the new shifts)."""
        shifts = list(self.shift_ms or [])
        changed = False
        for label, values in effect_values.items():
            name, _, number = label.partition(":")
            if name != self.name:
                continue
            sensor = int(number) - 1 if number else 0
            shifts += [None] * (sensor + 1 - len(shifts))
            d = float(np.ravel(values)[0])
            now = self._shift(sensor)
            if np.isfinite(d) and abs(d - now) > max(0.2, 0.01 * abs(d)):
                shifts[sensor], changed = d, True
        if changed:
            self.shift_ms = shifts
        return changed

    def true_params(self, magnitude=None, sensor=0):
        magnitude = self.default_magnitude if magnitude is None else magnitude
        return np.atleast_1d(np.asarray(magnitude, dtype=float))[:1].copy()

    def quote(self, values, field_nT=None, sensor=None) -> str:
        d = float(np.ravel(values)[0])
        return f"the magnetometer {'lags' if d >= 0 else 'leads'} its attitude by {abs(d):.3g} ms"


# ----------------------------------------------------------------------------------------------------------------
# time
# ----------------------------------------------------------------------------------------------------------------


@register
@dataclass
class BiasDrift(CatalogueEffect):
    """Bias drifting linearly in time: ``y += gamma (t - t0)``, ``gamma`` per axis in nT/h."""

    name: ClassVar[str] = "bias_drift"
    signature: ClassVar[str] = "slow trend in time times field direction"
    vector_signature: ClassVar[str] = "slow trend in time of the body-frame residual"
    when_recording: ClassVar[str] = (
        "let the sensor and electronics reach a steady temperature before recording, record the temperature, and keep the rotation short (or repeat it at the start and end to measure the drift)"
    )
    basis_uses_readings: ClassVar[bool] = False  # a function of the channels only
    stage: ClassVar[str] = "raw"
    channels: ClassVar[tuple] = ("time",)
    description: ClassVar[str] = "bias drifting in time, y += gamma (t - t0) [nT/h per axis]"
    default_magnitude: ClassVar[float] = 300.0
    magnitude_unit: ClassVar[str] = "nT/h"
    transferable: ClassVar[bool] = False  # describes this recording, not the instrument
    kept_for_new_data: ClassVar[str] = "the bias at the fitted record's mean time (the drift's reference time)"

    reference_time_s: float | None = None
    duration_s: float | None = None

    def param_names(self):
        return [f"gamma_{a}_nT_per_h" for a in _AXES]

    def param_scale(self):
        span_h = (self.duration_s or 3600.0) / 3600.0
        return np.full(3, 3.5 / span_h)

    def configure(self, dataset, residuals_nT=None):
        t = dataset.time_s
        self.reference_time_s = float(np.mean(t))
        self.duration_s = float(max(t[-1] - t[0], 1e-9))

    def state(self):
        return {"reference_time_s": self.reference_time_s, "duration_s": self.duration_s}

    def set_state(self, state):
        self.reference_time_s = _state_number(self, state, "reference_time_s", what="a time in s")
        self.duration_s = _state_number(self, state, "duration_s", positive=True, what="the record length in s")

    def raw_basis(self, z0, ctx: Context):
        t = ctx.time_s
        t0 = np.mean(t) if self.reference_time_s is None else self.reference_time_s
        return _diagonal_basis(np.repeat(((t - t0) / 3600.0)[:, None], 3, axis=1))


#: One sensor's readings-only work for the candidates' constants (step scans, quadric residuals, field directions):
#: the candidates of every score round and the refits look at the same readings.
_READINGS_CACHE = ReadingsCache(32)


def quadric_residuals(readings_nT):
    """Total-field residuals (nT, Sampson distance) of an algebraic ellipsoid fit to one sensor's readings
    (read-only; computed once per readings array).

    The effects that search the residuals for a data-derived constant (a step time, a hysteresis width) use
    these when the residuals they are given are worse (a crude starting calibration).
    """
    y = np.asarray(readings_nT, dtype=float)

    def compute():
        r = _quadric_residuals(y)
        r.setflags(write=False)
        return r

    return _READINGS_CACHE.get(y, ("quadric",), compute)


def _quadric_residuals(y):
    centre = y.mean(axis=0)
    scale = np.sqrt(np.mean(np.sum((y - centre) ** 2, axis=1)))
    v = (y - centre) / scale
    x, yy, z = v.T
    design = np.column_stack(
        [x * x, yy * yy, z * z, 2 * x * yy, 2 * x * z, 2 * yy * z, 2 * x, 2 * yy, 2 * z, np.ones(len(v))]
    )
    # the right singular vector of the smallest singular value, as the eigenvector of the Gram matrix's smallest
    # eigenvalue (one product instead of an SVD of the tall design; the coordinates are centred and scaled, so
    # squaring the condition number costs nothing that matters here)
    _, vectors = np.linalg.eigh(design.T @ design)
    c = vectors[:, 0]
    m = np.array([[c[0], c[3], c[4]], [c[3], c[1], c[5]], [c[4], c[5], c[2]]])
    value = design @ c
    grad = 2 * (v @ m + c[6:9])
    r = value / np.maximum(row_norm(grad), 1e-300) * scale
    try:
        inside = c[9] - c[6:9] @ np.linalg.solve(m, c[6:9])  # the quadric's value at its centre
    except np.linalg.LinAlgError:
        inside = c[9]
    return -r if inside > 0 else r  # outside the ellipsoid (field too strong) is positive


def _better_residuals(readings_nT, residuals_nT):
    """The given residuals, or those of :func:`quadric_residuals` if they are much smaller (poor start)."""
    r = np.asarray(residuals_nT, dtype=float)
    alt = quadric_residuals(readings_nT)
    return alt if np.sqrt(np.mean(alt**2)) < 0.7 * np.sqrt(np.mean(r**2)) else r


def step_scan(readings_nT, margin=0.05, min_samples=10):
    """Change-point scan for a bias step in one sensor's readings.

    Readings of a calibrated-for sensor turning in a uniform field lie on an ellipsoid; a bias step after sample
    ``k`` moves the ellipsoid's centre. For every ``k`` the algebraic quadric fit of the (scaled) readings is
    extended by the columns ``H_k y`` and ``H_k`` (``H_k`` = 1 from sample ``k`` on), which represent a pure
    step exactly, and the smallest eigenvalue of the design's Gram matrix (the algebraic residual) is computed
    for all ``k`` at once from cumulative sums. The scan needs no starting calibration.

    Parameters
    ----------
    readings_nT : numpy.ndarray, shape (N, 3)
        Raw readings of the sensor, in time order.
    margin : float
        Fraction of the record at each end where no step is looked for.
    min_samples : int
        Fewest samples on either side of a step.

    Returns
    -------
    index : int
        First sample after the most likely step.
    improvement_nT2 : numpy.ndarray, shape (N,)
        Drop of the (approximate) residual sum of squares, nT^2, for a step before each sample (0 where not
        scanned).
    """
    y = np.asarray(readings_nT, dtype=float)
    # the same readings are scanned by several candidates and refits (_READINGS_CACHE)
    index, improvement = _READINGS_CACHE.get(
        y, ("step", margin, min_samples), lambda: _step_scan(y, margin, min_samples)
    )
    return index, improvement.copy()


def step_index(readings_nT, margin=0.05, min_samples=10) -> int:
    """The first sample after the most likely bias step in one sensor's readings (:func:`step_scan`'s index),
    kept as a number of its own: a worker process handed it (:func:`readings_facts`) needs no scan."""
    y = np.asarray(readings_nT, dtype=float)
    return _READINGS_CACHE.get(
        y, ("step index", margin, min_samples), lambda: int(step_scan(y, margin, min_samples)[0])
    )


def readings_facts(readings_nT) -> list:
    """The single numbers worked out from one sensor's readings alone and kept here (a step's index):
    ``[(key, value)]`` for :func:`seed_readings_facts` in another process holding the same readings."""
    return _READINGS_CACHE.small_facts(np.asarray(readings_nT))


def seed_readings_facts(readings_nT, facts) -> None:
    """Keep ``facts`` (:func:`readings_facts` of the same readings, worked out elsewhere) for these readings."""
    y = np.asarray(readings_nT)
    for key, value in facts:
        _READINGS_CACHE.seed(y, key, value)


def _step_scan(readings_nT, margin, min_samples):
    y = np.asarray(readings_nT, dtype=float)
    n = len(y)
    centre = y.mean(axis=0)
    scale = float(np.sqrt(np.mean(np.sum((y - centre) ** 2, axis=1))))
    v = (y - centre) / scale
    x, yy, z = v.T
    quad = np.column_stack([x * x, yy * yy, z * z, 2 * x * yy, 2 * x * z, 2 * yy * z, 2 * x, 2 * yy, 2 * z, np.ones(n)])
    w = np.column_stack([v, np.ones(n)])
    improvement = np.zeros(n)
    lo = max(int(np.ceil(margin * n)), min_samples)
    hi = min(int(np.floor((1 - margin) * n)), n - min_samples)
    if hi <= lo:
        return n // 2, improvement
    g_qq = quad.T @ quad
    lam0 = np.linalg.eigvalsh(g_qq)[0]
    x_all = np.column_stack([quad, w])  # (N, 14): the step columns' products with both blocks at once

    def suffix(ks):
        """``sum_{i >= k} x_i w_i^T`` (len(ks), 14, 4) for increasing, evenly spaced (or consecutive) ``ks``:
        the sums of the segments between them (one batched product), then their running sum from the end."""
        step_k = int(ks[1] - ks[0]) if len(ks) > 1 else 1
        m = len(ks)
        body = slice(int(ks[0]), int(ks[0]) + m * step_k)
        seg = np.matmul(x_all[body].reshape(m, step_k, 14).transpose(0, 2, 1), w[body].reshape(m, step_k, 4))
        tail = x_all[body.stop :].T @ w[body.stop :]
        return np.cumsum(seg[::-1], axis=0)[::-1] + tail

    def smallest(ks):
        s_k = suffix(ks)
        gram = np.empty((len(ks), 14, 14))
        gram[:, :10, :10] = g_qq
        gram[:, :10, 10:] = s_k[:, :10]
        gram[:, 10:, :10] = np.transpose(s_k[:, :10], (0, 2, 1))
        gram[:, 10:, 10:] = s_k[:, 10:]
        return np.linalg.eigvalsh(gram)[:, 0]

    # coarse grid, then every sample around the best coarse point (long records)
    stride = max(1, (hi - lo) // 2000)
    ks = np.arange(lo, hi, stride)
    # algebraic residual ~ (2 distance / scale)^2 per sample
    improvement[ks] = np.maximum(lam0 - smallest(ks), 0.0) * scale**2 / 4.0
    if stride > 1:
        best = int(ks[np.argmax(improvement[ks])])
        fine = np.arange(max(lo, best - stride), min(hi, best + stride + 1))
        improvement[fine] = np.maximum(lam0 - smallest(fine), 0.0) * scale**2 / 4.0
    return int(lo + np.argmax(improvement[lo:hi])), improvement


#: A reading's change from the previous sample above this many times the local median change is a jump; a
#: stretch of samples without one around a step time is still (:func:`_at_the_jump`).
JUMP_FACTOR = 4.0

#: Fewest samples on each side of a step time, without a jump, for the stretch to count as still.
STILL_MIN_SAMPLES = 10


def _at_the_jump(cost, lo, hi, readings_nT):
    """The step's first sample ``k`` in ``[lo, hi]`` from the profile ``cost[k]`` (nT^2) of a step before sample
    ``k``: its minimum, unless that falls inside a still stretch where the readings do not jump -- a step there
    would show as a jump of the readings, so it cannot be -- and then the edge of the still stretch (the first
    sample where the readings jump, before or after it) with the lower cost (a step was placed inside a
    still head, seconds before the visible jump)."""
    window = cost[lo : hi + 1]
    k = lo + int(np.argmin(window))
    y = np.asarray(readings_nT, dtype=float)
    change = np.r_[0.0, np.linalg.norm(np.diff(y, axis=0), axis=1)]  # change[j] = |y_j - y_(j-1)|
    around = change[max(k - STILL_MIN_SAMPLES, 1) : k + STILL_MIN_SAMPLES + 1]
    if around.size < 2 * STILL_MIN_SAMPLES:
        return k
    threshold = JUMP_FACTOR * float(np.median(around))
    if change[k] > threshold:
        return k  # the readings jump here
    a = k
    while a - 1 >= lo and change[a - 1] <= threshold:
        a -= 1
    b = k
    while b + 1 <= hi and change[b + 1] <= threshold:
        b += 1
    if k - a < STILL_MIN_SAMPLES or b - k < STILL_MIN_SAMPLES:
        return k  # not inside a still stretch
    edges = [j for j in (a - 1, b + 1) if lo <= j <= hi]
    return min(edges, key=lambda j: cost[j]) if edges else k


@register
@dataclass
class BiasStep(CatalogueEffect):
    """A bias step (perming after a shock): ``y += db H(t - te)``, ``db`` per axis in nT.

    The step time ``te`` of each sensor is found by :func:`step_scan` on its readings in :meth:`configure`
    (one extra degree of freedom per sensor for the information criteria).
    """

    name: ClassVar[str] = "bias_step"
    signature: ClassVar[str] = "step in the residual pattern"
    vector_signature: ClassVar[str] = "step in the body-frame residual"
    when_recording: ClassVar[str] = (
        "find what changed at that time (a shock, a cable, a power or load change, a magnetised tool near the sensor) and record again without it; a sensor permed by a shock keeps its new bias: calibrate after it"
    )
    basis_uses_readings: ClassVar[bool] = False  # a function of the channels only
    stage: ClassVar[str] = "raw"
    channels: ClassVar[tuple] = ("time",)
    description: ClassVar[str] = "bias step at a time te found by a change-point scan, y += db H(t - te) [nT]"
    default_magnitude: ClassVar[float] = 10.0
    magnitude_unit: ClassVar[str] = "nT"
    transferable: ClassVar[bool] = False  # describes this recording, not the instrument
    kept_for_new_data: ClassVar[str] = "the bias after the step (the sensor stays permed)"
    extra_dof: ClassVar[int] = 1

    step_time_s: list | None = None

    def param_names(self):
        return [f"step_{a}_nT" for a in _AXES]

    def configure(self, dataset, residuals_nT=None):
        t = dataset.time_s
        times = []
        for s in range(dataset.n_sensors):
            if not self.applies_to(s):
                times.append(None)
                continue
            ok = np.ones(len(t), bool) if residuals_nT is None else np.isfinite(residuals_nT[s])
            k = step_index(dataset.readings_nT[s] if ok.all() else dataset.readings_nT[s][ok])
            tk = t[ok]
            times.append(float(0.5 * (tk[k - 1] + tk[k])))
        self.step_time_s = times

    def state(self):
        return {"step_time_s": self.step_time_s}

    def set_state(self, state):
        self.step_time_s = _state_times(self, state, "step_time_s")

    def refine(self, effect_values, context=None, margin=0.05):
        """Move each step to the time that minimises the whole residual (profile over the step time).

        :meth:`configure` scans the raw readings, which sees only the total field and is confounded by slow
        changes of scale (temperature) or drift; where the field is nearly perpendicular to the step the scan is
        flat. With the fitted parameters held, the residual cost of every sample is computed with the step
        applied and not applied; the cost of a step before sample ``k`` is then a pair of cumulative sums, total
        field and inter-sensor consistency together, so every ``k`` is tried at once.
        """
        if context is None or self.step_time_s is None or not context.dataset.has("time"):
            return False
        t = context.dataset.time_s
        n = len(t)
        lo, hi = max(int(np.ceil(margin * n)), 1), min(int(np.floor((1 - margin) * n)), n - 1)
        times, changed = list(self.step_time_s), False
        # the step is linear in the corrected field: sensor s's field with its step at every sample ("on") or at
        # none ("off") is the fitted field plus a multiple of R C^-1 db, so every trial costs that sensor's
        # residuals only (RefineContext.cost_with_sensor_moved)
        shortcut = hasattr(context, "cost_with_sensor_moved")
        values = context.values() if shortcut else None
        for s in range(len(times)):
            if times[s] is None or hi <= lo:
                continue
            if not shortcut:  # a context without it: evaluate each trial whole
                on = context.cost_per_sample(self, {"step_time_s": times[:s] + [t[0] - 1.0] + times[s + 1 :]})
                off = context.cost_per_sample(self, {"step_time_s": times[:s] + [t[-1] + 1.0] + times[s + 1 :]})
            else:
                cal = context.sensors()[s]
                db = values[term_label(self.name, s if self.per_sensor else None)]
                shift = (cal.R @ cal.cinv) @ db  # the step's move of sensor s's corrected field, nT
                now = (t >= times[s]).astype(float)[:, None]
                off = context.cost_with_sensor_moved(s, now * shift)  # the current step taken out
                on = context.cost_with_sensor_moved(s, (now - 1.0) * shift)  # the step at every sample
            # cost of a step before sample k: samples < k without it, samples >= k with it
            cost = np.concatenate([[0.0], np.cumsum(off)]) + np.concatenate([np.cumsum(on[::-1])[::-1], [0.0]])
            k = _at_the_jump(cost, lo, hi, context.dataset.readings_nT[s])
            new = float(0.5 * (t[k - 1] + t[k]))
            if np.any((t >= new) != (t >= times[s])):
                times[s], changed = new, True
        if changed:
            self.step_time_s = times
        return changed

    def quote(self, values, field_nT=None, sensor=None) -> str:
        times = self.step_time_s or []
        te = times[sensor] if sensor is not None and sensor < len(times) else (times[0] if times else None)
        where = "" if te is None else f" at t = {te:.4g} s"
        return f"a step of {_axes_text(values)} nT{where}"

    def kept_raw_level(self, values):
        """The bias *after* the step is kept for new data: the sensor stays permed (measured on six real
        recordings, fitted on the first half and applied to the second, the level after the step transfers best;
        the level before it raised the held-out error up to 4.7x; benchmarks/notes/real.md, "kept level")."""
        return np.asarray(values, dtype=float).reshape(3)

    def raw_basis(self, z0, ctx: Context):
        t = ctx.time_s
        te = None
        if self.step_time_s is not None and ctx.sensor < len(self.step_time_s):
            te = self.step_time_s[ctx.sensor]
        if te is None:
            te = float(np.median(t))
        return _diagonal_basis(np.repeat((t >= te).astype(float)[:, None], 3, axis=1))


# ----------------------------------------------------------------------------------------------------------------
# nonlinearity
# ----------------------------------------------------------------------------------------------------------------


@dataclass
class _PowerNonlinearity(CatalogueEffect):
    """Transfer nonlinearity of one order per axis: ``y_j += k_j ((C B)_j / F)^order``, ``k`` in nT.

    ``k_j`` is quoted at the data's own field magnitude ``F``: it is the deviation (nT) of axis ``j`` when that
    axis reads the whole field, so the number is the size of the effect in these data (a coefficient quoted at
    50 uT would overstate a nonlinearity seen in a 9 uT field 30-fold for the quadratic term). ``F`` is a
    data-derived constant (:attr:`field_magnitude_nT`, saved with the calibration) set by :meth:`configure`;
    without it (an effect never configured, a calibration file written before) ``F`` is 50 uT
    (:data:`NONLINEARITY_REFERENCE_NT`).

    The basis is evaluated on the *denoised* reading, not the noisy sample: ``z0`` scaled along its own direction
    onto the readings' ellipsoid, ``z0 F / |M z0|`` (``M`` the ellipsoid's correction scaled to ``F``,
    :attr:`ellipsoid_cinv`, from :func:`magcal.geometry.shape.field_shape` in :meth:`configure`), i.e. the reading
    the fitted model predicts from the sample's field direction. A power of the noisy reading correlates with the
    reading's own noise along the field (``d(z^3)/dz = 3 z^2``), so a fit of it compresses the noise where an axis
    is large: at noise of ~1 % of the field it lowers the RMS, on held-out samples too, with no nonlinearity at
    all. The denoised reading keeps only the noise across the field, which the total field does not see to first
    order. An effect without :attr:`ellipsoid_cinv` (a calibration file written before it was kept) uses the
    readings themselves.
    """

    stage: ClassVar[str] = "raw"
    channels: ClassVar[tuple] = ()
    magnitude_unit: ClassVar[str] = "nT at |B|"
    order: ClassVar[int] = 2
    symbol: ClassVar[str] = "q"
    scale_nT: ClassVar[float] = 4.0

    #: The field magnitude (nT) the parameters are quoted at; None: 50 uT.
    field_magnitude_nT: float | None = None
    #: Per sensor, the 3x3 matrix ``M`` (dimensionless, nested lists, or None) with ``|M z0| = F`` on the
    #: readings' ellipsoid: the basis is a power of ``z0 / |M z0|`` (the denoised reading over ``F``). None: the
    #: noisy reading ``z0 / F``.
    ellipsoid_cinv: list | None = None

    def param_names(self):
        return [f"{self.symbol}_{a}_nT" for a in _AXES]

    def param_scale(self):
        return np.full(3, self.scale_nT)

    def domain(self):
        """``|k| <= NONLINEARITY_LIMIT_PPM`` of the field the parameters are quoted at (:attr:`quoted_at_nT`)."""
        limit = 1e-6 * NONLINEARITY_LIMIT_PPM * self.quoted_at_nT
        return Domain.symmetric(
            3,
            limit,
            f"{NONLINEARITY_LIMIT_PPM:g} ppm of the {_field_text(self.quoted_at_nT)} field: a fluxgate's "
            "nonlinearity is tens to hundreds of ppm, a MEMS sensor's up to a few thousand",
        )

    @property
    def quoted_at_nT(self) -> float:
        """The field magnitude (nT) the parameters are quoted at: the data's, or 50 uT if unknown."""
        return float(self.field_magnitude_nT or NONLINEARITY_REFERENCE_NT)

    def quote_unit(self, field_nT=None) -> str:
        """``"nT at 8.9 uT"``: the unit of the parameters, at ``field_nT`` or at :attr:`quoted_at_nT`."""
        return f"nT at {(field_nT or self.quoted_at_nT) / 1000.0:.3g} uT"

    def configure(self, dataset, residuals_nT=None):
        self.field_magnitude_nT = field = data_field_magnitude_nT(dataset)
        self.ellipsoid_cinv = [
            _READINGS_CACHE.get(y, ("denoising shape", field), lambda y=y: _denoising_cinv(y, field))
            for y in np.asarray(dataset.readings_nT, dtype=float)
        ]

    def state(self):
        return {"field_magnitude_nT": self.field_magnitude_nT, "ellipsoid_cinv": self.ellipsoid_cinv}

    def set_state(self, state):
        self.field_magnitude_nT = _state_number(
            self, state, "field_magnitude_nT", positive=True, what="of nT: the field the parameters are quoted at"
        )
        self.ellipsoid_cinv = _state_matrices(self, state, "ellipsoid_cinv")

    def _denoised_over_field(self, z0, sensor):
        """``z0 / |M z0|`` (the denoised reading over ``F``, class docstring) or ``z0 / F`` without ``M``."""
        shapes = self.ellipsoid_cinv
        m = shapes[sensor] if shapes is not None and sensor < len(shapes) else None
        if m is None:
            return z0 / self.quoted_at_nT
        norm = row_norm(z0 @ np.asarray(m, dtype=float).T)
        return z0 / np.maximum(norm, 1e-300)[:, None]

    def raw_basis(self, z0, ctx: Context):
        u = self._denoised_over_field(np.asarray(z0, dtype=float), ctx.sensor)
        power = u.copy()
        for _ in range(self.order - 1):  # repeated products: numpy's general power is ~10x slower for a cube
            power *= u
        return _diagonal_basis(power)

    def quote(self, values, field_nT=None, sensor=None):
        """The deviation (nT, and ppm of the field) of an axis reading the whole field of the data.

        The parameters are quoted at :attr:`quoted_at_nT`, the magnitude of the raw readings the basis divides
        (a sphere fit, before the scale correction, or the reference). An effect never configured (a file saved
        before the field was kept) is quoted at 50 uT; given the data's ``field_nT`` its deviation is then
        converted by ``(F / 50 uT)^order``.
        """
        k = np.asarray(values, dtype=float)
        field = self.quoted_at_nT
        note = ""
        if self.field_magnitude_nT is None and field_nT:
            k = k * (field_nT / field) ** self.order
            field, note = float(field_nT), f" (converted from the parameters, quoted at {_field_text(field)})"
        elif field_nT and abs(field_nT / field - 1.0) > 0.005:
            note = (
                f" (the readings' magnitude before the scale correction; the fitted field is {_field_text(field_nT)})"
            )
        return (
            f"an axis reading the whole field of the data, {_field_text(field)}, is off by {_axes_text(k)} nT = "
            f"{_axes_text(1e6 * k / field, '{:.0f}')} ppm{note}"
        )


def _denoising_cinv(readings_nT, field_nT) -> list:
    """``M`` of :class:`_PowerNonlinearity` for one sensor's readings (N, 3): the correction of their ellipsoid
    (:func:`magcal.geometry.shape.field_shape`; a sphere when no ellipsoid is determined) scaled so that
    ``|M (y - b)| = field_nT`` on it, as nested lists (dimensionless)."""
    shape = field_shape(readings_nT)
    if not (np.isfinite(shape.field_nT) and shape.field_nT > 0):
        return np.eye(3).tolist()
    return (np.asarray(shape.cinv, dtype=float) * (field_nT / shape.field_nT)).tolist()


def _state_matrices(effect, state, key):
    """``state[key]``: per sensor a 3x3 matrix of finite numbers (nested lists) or None; None when absent; else
    a clear error naming the term and the key."""
    value = state.get(key)
    if value is None:
        return None
    if not isinstance(value, (list, tuple)):
        raise MagcalError(f"{effect.label}: {key} must be a list (one 3x3 matrix per sensor, or null), got {value!r}")
    out = []
    for s, m in enumerate(value):
        if m is None:
            out.append(None)
            continue
        try:
            matrix = np.asarray(m, dtype=float)
        except (TypeError, ValueError):
            matrix = np.full(1, np.nan)
        if matrix.shape != (3, 3) or not np.all(np.isfinite(matrix)):
            raise MagcalError(f"{effect.label}: {key} of sensor {s + 1} must be a 3x3 matrix of numbers, got {m!r}")
        out.append(matrix.tolist())
    return out


def data_field_magnitude_nT(dataset) -> float:
    """The magnitude (nT) of the field the data were recorded in.

    The dataset's reference when it has one (the median of its ``ref_total`` column, else its
    ``reference_total_nT``); otherwise the radius of a sphere fitted to each sensor's readings, averaged over the
    sensors (the fitted field to within the sensors' scale errors, about 1 %).
    """
    column = getattr(dataset, "ref_total_nT", None)
    if column is not None:
        values = np.asarray(column, dtype=float)
        values = values[np.isfinite(values)]
        if values.size:
            return float(np.median(values))
    if getattr(dataset, "reference_total_nT", None):
        return float(dataset.reference_total_nT)
    return float(np.mean([_sphere_fit(y)[1] for y in np.asarray(dataset.readings_nT, dtype=float)]))


def _sphere_fit(readings_nT):
    """Centre (3,) and radius (nT) of the sphere fitted (algebraically, least squares) to one sensor's readings."""
    y = np.asarray(readings_nT, dtype=float)
    design = np.column_stack([2 * y, np.ones(len(y))])
    sol, *_ = np.linalg.lstsq(design, np.sum(y**2, axis=1), rcond=None)
    return sol[:3], float(np.sqrt(max(sol[3] + sol[:3] @ sol[:3], 1e-12)))


@register
@dataclass
class NonlinearityQuadratic(_PowerNonlinearity):
    """Second-order transfer nonlinearity per axis: ``y_j += q_j ((C B)_j / F)^2``, ``q`` in nT at the data's field
    magnitude ``F``."""

    name: ClassVar[str] = "nonlinearity_quadratic"
    signature: ClassVar[str] = "direction pattern of degree 3"
    vector_signature: ClassVar[str] = "residual follows the square of each axis's reading"
    description: ClassVar[str] = "quadratic nonlinearity, y_j += q_j (B_j / |B|)^2 [nT at the data's field |B|]"
    default_magnitude: ClassVar[float] = 20.0
    order: ClassVar[int] = 2
    symbol: ClassVar[str] = "q"
    scale_nT: ClassVar[float] = 4.0


@register
@dataclass
class NonlinearityCubic(_PowerNonlinearity):
    """Third-order transfer nonlinearity per axis: ``y_j += c_j ((C B)_j / F)^3``, ``c`` in nT at the data's field
    magnitude ``F``.

    At constant ``|B|`` it cannot be told from a cross-field effect ``l_j B_j (|B|^2 - B_j^2)``.
    """

    name: ClassVar[str] = "nonlinearity_cubic"
    signature: ClassVar[str] = "direction pattern of degree 4"
    vector_signature: ClassVar[str] = "residual follows the cube of each axis's reading"
    description: ClassVar[str] = "cubic nonlinearity, y_j += c_j (B_j / |B|)^3 [nT at the data's field |B|]"
    default_magnitude: ClassVar[float] = 25.0
    order: ClassVar[int] = 3
    symbol: ClassVar[str] = "c"
    scale_nT: ClassVar[float] = 6.0


# ----------------------------------------------------------------------------------------------------------------
# dynamics: timing and hysteresis
# ----------------------------------------------------------------------------------------------------------------


def _reading_rate(effect, ctx):
    """d y / d t (nT/s) of the context's sensor, cached per dataset (it does not depend on the bias)."""
    return effect._cached(ctx.dataset, ("rate", ctx.sensor), lambda: time_derivative(ctx.reading_nT, ctx.time_s))


@register
@dataclass
class AxisTimingSkew(CatalogueEffect):
    """Axes of one sensor sampled at different times: ``y_j(t) = (C B)_j(t - tau_j)``, ``tau`` in ms.

    A delay common to the three axes leaves the total field unchanged, so the delays of x and y are
    measured relative to the z axis (2 parameters per sensor).
    """

    name: ClassVar[str] = "axis_timing_skew"
    signature: ClassVar[str] = "residual ~ rate of change of the axes; flips with the rotation direction"
    vector_signature: ClassVar[str] = "residual follows each axis's rate of change, differently per axis"
    evidence_channel: ClassVar[str] = "turn_rate_dps"
    stage: ClassVar[str] = "raw"
    channels: ClassVar[tuple] = ("time",)
    description: ClassVar[str] = "x and y axes sampled late relative to z, y_j(t) = B_j(t - tau_j) [ms]"
    default_magnitude: ClassVar[float] = 0.2
    magnitude_unit: ClassVar[str] = "ms"
    pattern: ClassVar[tuple] = (1.0, -0.6)

    def param_names(self):
        return ["tau_x_ms", "tau_y_ms"]

    def param_scale(self):
        return np.full(2, 0.1)

    def raw_basis(self, z0, ctx: Context):
        rate = _reading_rate(self, ctx)
        return SingleAxisBasis(-1e-3 * rate[:, :2], [0, 1])

    def true_params(self, magnitude=None, sensor=0):
        magnitude = self.default_magnitude if magnitude is None else magnitude
        m = np.atleast_1d(np.asarray(magnitude, dtype=float))
        if m.size == 2:
            return m.copy()
        if m.size == 3:  # absolute delays: only the differences to z are visible
            return m[:2] - m[2]
        pattern = np.array(self.pattern) if (sensor or 0) % 2 == 0 else np.array(self.pattern[::-1])
        return m[0] * pattern


@register
@dataclass
class SensorTimingSkew(CatalogueEffect):
    """Sensors of an array sampled at different times: ``B_i(t - dt_i)``, ``dt`` in ms, sensor 1 the reference.

    Invisible in each sensor's total field (a delayed field has the same magnitude); it shows in the
    inter-sensor consistency as ``dt dB/dt`` perpendicular to the field.
    """

    name: ClassVar[str] = "sensor_timing_skew"
    signature: ClassVar[str] = "inter-sensor differences ~ dt dB/dt"
    stage: ClassVar[str] = "array"
    channels: ClassVar[tuple] = ("time",)
    min_sensors: ClassVar[int] = 2
    description: ClassVar[str] = "sensors 2-4 sampled late relative to sensor 1, B_i(t - dt_i) [ms]"
    default_magnitude: ClassVar[float] = 0.2
    magnitude_unit: ClassVar[str] = "ms"
    pattern: ClassVar[tuple] = (0.0, 1.0, -0.7, 0.5)

    def __post_init__(self):
        super().__post_init__()
        if self.sensor == 0:
            raise MagcalError("sensor_timing_skew: sensor 1 is the time reference; name sensor 2, 3 or 4")

    def applies_to(self, sensor):
        return sensor > 0 and (self.sensor is None or self.sensor == sensor)

    def param_names(self):
        return ["delay_ms"]

    def param_scale(self):
        return np.array([0.1])

    def array_basis(self, field_nT, ctx: Context):
        rate = time_derivative(field_nT, ctx.time_s)
        return 1e-3 * rate[:, :, None]

    def true_params(self, magnitude=None, sensor=1):
        magnitude = self.default_magnitude if magnitude is None else magnitude
        m = np.atleast_1d(np.asarray(magnitude, dtype=float))
        if m.size != 1:
            raise MagcalError(f"{self.name}: magnitude is one delay in ms")
        return np.array([m[0] * self.pattern[sensor % 4]])


@register
@dataclass
class Hysteresis(CatalogueEffect):
    """Magnetic hysteresis of each axis: the output lags behind the field by up to ``h_j`` nT, like a play
    (backlash) operator of half-width ``h_j``; away from reversals ``y_j += -h_j sign(dB_j/dt)``.

    The basis of axis ``j`` is ``(P(y_j) - y_j) / h0_j`` with ``P`` the play operator of a half-width ``h0_j``
    estimated from the residuals in :meth:`configure` (so that the transitions after each reversal have the
    right length); where no hysteresis is seen it is ``-sign(dy_j/dt)``. The parameter ``h_j`` (nT) scales it.
    """

    name: ClassVar[str] = "hysteresis"
    signature: ClassVar[str] = "residual flips sign with each axis's direction of change"
    vector_signature: ClassVar[str] = "residual flips sign with each axis's direction of change"
    stage: ClassVar[str] = "raw"
    channels: ClassVar[tuple] = ("time",)
    description: ClassVar[str] = "hysteresis, each axis lags by h_j behind the direction of change [nT]"
    default_magnitude: ClassVar[float] = 5.0
    magnitude_unit: ClassVar[str] = "nT"
    #: Loop half-widths are widths: every axis hides a non-negative one.
    pattern: ClassVar[tuple] = (1.0, 0.7, 0.5)
    #: Why :meth:`domain` holds ``h >= 0``, for the messages refusing a negative width.
    domain_why: ClassVar[str] = "a hysteresis loop half-width in nT: the output lags the field by it, it cannot lead it"

    #: Per sensor, the play half-widths (nT) that shape the basis (0: a plain sign).
    shape_half_width_nT: list | None = None

    def __post_init__(self):
        super().__post_init__()
        self.shape_half_width_nT = self._checked_widths(self.shape_half_width_nT)

    def _checked_widths(self, widths):
        """The per-sensor shape widths, refused with a clear message if one is negative or not a number."""
        if widths is None:
            return None
        if not isinstance(widths, (list, tuple)):
            raise MagcalError(
                f"{self.label}: shape_half_width_nT must be a list (one entry per sensor) of three "
                f"half-widths in nT or null, got {widths!r}"
            )
        out = []
        for s, w in enumerate(widths):
            if w is None:
                out.append(None)
                continue
            try:
                values = np.asarray(w, dtype=float).reshape(-1)
            except (TypeError, ValueError):
                values = np.array([np.nan])
            if values.size != 3 or not np.all(np.isfinite(values)) or np.any(values < 0):
                raise MagcalError(
                    f"{self.label}: shape_half_width_nT of sensor {s + 1} is {w!r}; it must be three "
                    f"numbers >= 0 ({self.domain_why})"
                )
            out.append(values.tolist())
        return out

    def param_names(self):
        return [f"h_{a}_nT" for a in _AXES]

    def domain(self):
        """``h >= 0`` on every axis: a loop half-width is not negative."""
        return Domain(np.zeros(3), np.full(3, np.inf), self.domain_why)

    def quote(self, values, field_nT=None, sensor=None):
        """The loop half-widths in ppm of the data's field."""
        if not field_nT:
            return ""
        h = np.asarray(values, dtype=float)
        return (
            f"loop half-widths {_axes_text(1e6 * h / field_nT, '{:.0f}')} ppm of the data's field "
            f"{_field_text(field_nT)}"
        )

    def configure(self, dataset, residuals_nT=None):
        widths = []
        for s in range(dataset.n_sensors):
            if residuals_nT is None or not self.applies_to(s):
                widths.append(None)
                continue
            r = np.asarray(residuals_nT[s], dtype=float)
            ok = np.isfinite(r)
            y = dataset.readings_nT[s]
            rate = time_derivative(y, dataset.time_s)
            y_ok = y if ok.all() else y[ok]  # the readings themselves when all are kept (quadric_residuals' cache)
            widths.append(_hysteresis_widths(y_ok, -np.sign(rate[ok]), _better_residuals(y_ok, r[ok])).tolist())
        self.shape_half_width_nT = widths

    def state(self):
        return {"shape_half_width_nT": self.shape_half_width_nT}

    def refine(self, effect_values, context=None):
        if self.shape_half_width_nT is None:
            return False
        changed = False
        widths = [None if w is None else list(w) for w in self.shape_half_width_nT]
        for s in range(len(widths)):
            label = (
                self.name
                if self.sensor is None and len(widths) == 1 and term_label(self.name, 0) not in effect_values
                else term_label(self.name, s)
            )
            values = effect_values.get(label)
            if values is None or widths[s] is None:
                continue
            new = np.abs(np.asarray(values, dtype=float))
            old = np.asarray(widths[s], dtype=float)
            if np.any(np.abs(new - old) > 0.1 * np.maximum(new, 0.5)):
                changed = True
            widths[s] = new.tolist()
        if changed:
            self.shape_half_width_nT = widths
        return changed

    def set_state(self, state):
        self.shape_half_width_nT = self._checked_widths(state.get("shape_half_width_nT"))

    def raw_basis(self, z0, ctx: Context):
        widths = None
        if self.shape_half_width_nT is not None and ctx.sensor < len(self.shape_half_width_nT):
            widths = self.shape_half_width_nT[ctx.sensor]
        key = ("hyst", ctx.sensor, tuple(widths) if widths else None)
        columns = self._cached(ctx.dataset, key, lambda: self._columns(ctx, widths))
        return _diagonal_basis(columns)

    def _columns(self, ctx, widths):
        # the reversals from the readings fitted in time, not from their noise (smoothed_readings)
        y = smoothed_readings(ctx.reading_nT, ctx.time_s)
        rate = _reading_rate(self, ctx)
        cols = -np.sign(rate)
        if widths:
            for j, h0 in enumerate(widths):
                if h0 and h0 > 0:
                    cols[:, j] = (play_operator(y[:, j], h0) - y[:, j]) / h0
        return cols


def _hysteresis_widths(y, signs, residuals):
    """Rough per-axis hysteresis half-widths (nT) from one sensor's total-field residuals.

    The residual of a hysteretic sensor is about ``sum_j u_j lag_j`` with ``lag_j = -h_j sign(dB_j/dt)``; ``u`` is
    approximated by the centred, scaled readings and ``r`` regressed on ``u_j sign_j``. (The terms the base
    model absorbs cannot be included: the residual is itself a function of the readings.) Widths not clearly
    above their standard error are 0.
    """
    v = y - y.mean(axis=0)
    v = v / np.sqrt(np.mean(np.sum(v**2, axis=1)))
    design = np.column_stack([np.ones(len(v)), v * signs])
    coef, *_ = np.linalg.lstsq(design, residuals, rcond=None)
    resid = residuals - design @ coef
    s2 = float(resid @ resid) / max(len(residuals) - design.shape[1], 1)
    cov = s2 * np.linalg.pinv(design.T @ design)
    h = coef[-3:]
    se = np.sqrt(np.maximum(np.diag(cov)[-3:], 1e-300))
    return np.where(np.abs(h) > 3 * se, np.abs(h), 0.0)


# ----------------------------------------------------------------------------------------------------------------
# periodic interference (a source on the platform: motor, pump, aliased mains)
# ----------------------------------------------------------------------------------------------------------------


def _sample_grid(time_s):
    """Sample indices on a regular grid and its step (s) when every interval is a whole number of one step (a
    regular record, or a subset of one with gaps); ``(None, None)`` for irregular time stamps."""
    t = np.asarray(time_s, dtype=float)
    dt = np.diff(t)
    if len(t) < 3 or np.any(dt <= 0):
        return None, None
    step = float(np.min(dt))
    ratio = dt / step
    if np.any(np.abs(ratio - np.round(ratio)) > 0.01) or float(np.sum(np.round(ratio))) > 64 * len(t):
        return None, None
    return np.concatenate([[0], np.cumsum(np.round(ratio).astype(np.int64))]), step


def interference_spectrum(time_s, readings_nT, residuals_nT, min_cycles=5.0, oversample=4):
    """Where in frequency a sinusoidal field fixed in the sensor's axes best explains total-field residuals.

    A field ``d(t) = a sin(w t) + b cos(w t)`` added to a sensor's axes changes its total field by about
    ``u(t) . d(t)`` (``u`` the field direction). For every trial frequency the statistic is the part of the
    residual sum of squares the six columns ``u_j sin(w t)``, ``u_j cos(w t)`` would remove,
    ``c^H G^-1 c`` with ``c_j = sum r u_j exp(-i w t)`` and ``G = U^T U / 2``: a periodogram of the residual
    weighted by the field direction, so that the rotation of the sensor does not smear the line. ``u`` is taken
    from a sphere fit to the readings. Regular sampling (gaps allowed) uses an FFT, zero-padded ``oversample``
    times; irregular time stamps a direct sum on a grid of at most 4 096 frequencies.

    Parameters
    ----------
    time_s : numpy.ndarray, shape (N,)
    readings_nT : numpy.ndarray, shape (N, 3)
        One sensor's raw readings.
    residuals_nT : numpy.ndarray, shape (N,)
        Its total-field residuals.
    min_cycles : float
        Lowest frequency searched, in cycles per record (slower changes are drifts, not interference).
    oversample : int
        Zero-padding factor of the FFT (frequency step ``1 / (oversample T)``).

    Returns
    -------
    freq_hz, statistic_nT2 : numpy.ndarray
        The frequencies searched (up to 0.98 of the Nyquist frequency) and the residual sum of squares (nT^2)
        a sinusoid at each would remove; empty when the record is too short.
    """
    t = np.asarray(time_s, dtype=float)
    r = np.asarray(residuals_nT, dtype=float)
    y = np.asarray(readings_nT, dtype=float)

    def directions():
        centre, _ = _sphere_fit(y)
        u = y - centre
        u /= np.maximum(row_norm(u)[:, None], 1e-300)
        u.setflags(write=False)
        return u, np.linalg.pinv(0.5 * (u.T @ u))

    u, gram_inv = _READINGS_CACHE.get(y, ("sphere directions",), directions)  # the readings' alone: once per record
    w = r[:, None] * u  # (N, 3)
    w = w - w.mean(axis=0)
    duration = float(t[-1] - t[0]) if len(t) > 1 else 0.0
    index, step = _sample_grid(t)
    empty = np.zeros(0), np.zeros(0)
    if duration <= 0 or len(t) < 16:
        return empty
    if index is not None:
        n_fft = scipy.fft.next_fast_len(oversample * (index[-1] + 1), real=True)
        padded = np.zeros((3, n_fft))  # axis by axis, each a contiguous row: the FFT runs along memory
        padded[:, index] = w.T
        coef = scipy.fft.rfft(padded, axis=1).T  # (F, 3), c_j at each frequency
        freq = np.fft.rfftfreq(n_fft, step)
        nyquist = 0.5 / step
    else:
        nyquist = 0.5 / float(np.median(np.diff(t)))
        freq = np.linspace(min_cycles / duration, 0.98 * nyquist, min(4096, oversample * len(t)))
        coef = np.empty((len(freq), 3), complex)
        for lo in range(0, len(freq), 256):
            phase = np.exp(-2j * np.pi * np.outer(freq[lo : lo + 256], t - t[0]))
            coef[lo : lo + 256] = phase @ w
    keep = (freq >= min_cycles / duration) & (freq <= 0.98 * nyquist)
    freq, coef = freq[keep], coef[keep]
    # c^H G^-1 c with G^-1 real symmetric: the real and imaginary parts' quadratic forms
    stat = np.sum((coef.real @ gram_inv) * coef.real, axis=1) + np.sum((coef.imag @ gram_inv) * coef.imag, axis=1)
    return freq, np.maximum(stat, 0.0)


def dominant_interference_hz(time_s, readings_nT, residuals_nT, min_cycles=5.0):
    """The frequency (Hz) of :func:`interference_spectrum`'s highest line, refined by a parabola through the
    three grid points around it; ``None`` when the record is too short to search."""
    freq, stat = interference_spectrum(time_s, readings_nT, residuals_nT, min_cycles)
    if len(freq) < 3:
        return None
    i = int(np.argmax(stat))
    if 0 < i < len(freq) - 1:
        a, b, c = stat[i - 1], stat[i], stat[i + 1]
        denom = a - 2 * b + c
        shift = 0.5 * (a - c) / denom if denom < 0 else 0.0
        return float(freq[i] + np.clip(shift, -0.5, 0.5) * (freq[1] - freq[0]))
    return float(freq[i])


@register
@dataclass
class PeriodicInterference(CatalogueEffect):
    """A periodic field from a source on the platform (a motor, a pump, mains pickup aliased by the sampling),
    fixed in the sensor's axes: ``y_j += sum_k a_jk sin(2 pi k f (t - t0)) + b_jk cos(2 pi k f (t - t0))``,
    amplitudes in nT, ``k = 1 .. harmonics``.

    The frequency ``f`` of each sensor is a data-derived constant: :meth:`configure` takes the highest line of
    :func:`interference_spectrum` of the residuals (at least three cycles per record: slower changes are
    drifts), and :meth:`refine` profiles the whole residual over ``f`` around it after the fit (one extra degree
    of freedom per sensor for the information criteria). ``t0`` is the mean time of the fitted record.

    It is a record-only term (:attr:`transferable` False): the source's frequency, phase and amplitude belong to
    the platform's state during this record (a motor's speed, the pump's duty), not to the instrument; applied to
    another record it would subtract a sinusoid of unknown phase. An interference source fixed in the *world*
    (building wiring) rather than on the platform changes the total field by the same ``B/|B| . d(t)`` at every
    attitude; a per-axis sinusoid represents it only while the sensor turns slowly compared with ``f``.
    """

    name: ClassVar[str] = "periodic_interference"
    signature: ClassVar[str] = (
        "a sinusoid in time at a frequency the residual's spectrum shows (a motor, PWM, mains), along the field direction"
    )
    vector_signature: ClassVar[str] = "a sinusoid in the residual"
    when_recording: ClassVar[str] = (
        "a periodic source near the sensor (a motor, PWM, mains, a blinking load) was on: switch it off or move away from it while recording"
    )
    basis_uses_readings: ClassVar[bool] = False  # a function of the channels only
    stage: ClassVar[str] = "raw"
    channels: ClassVar[tuple] = ("time",)
    description: ClassVar[str] = (
        "periodic interference (motor, pump, aliased mains) at a frequency f found in the "
        "residual spectrum, y_j += a_j sin(2 pi f t) + b_j cos(2 pi f t) [nT]"
    )
    default_magnitude: ClassVar[float] = 5.0
    magnitude_unit: ClassVar[str] = "nT"
    transferable: ClassVar[bool] = False  # the platform's state during this record, not the instrument
    kept_for_new_data: ClassVar[str] = "the base terms without the interference (a zero-mean sinusoid)"
    extra_dof: ClassVar[int] = 1
    #: Direction (sensor axes) of the simulated interference field (normalised by the perturbation).
    pattern: ClassVar[tuple] = (0.6, -0.5, 0.62)
    #: Fewest cycles per record the frequency search accepts.
    min_cycles: ClassVar[float] = 5.0

    #: Number of harmonics (1: the fundamental only; 2: also ``2 f``...).
    harmonics: int = 1
    #: Per sensor, the interference frequency (Hz) found in the data (None for a sensor without the term).
    frequency_hz: list | None = None
    #: Time origin of the phases (s): the mean time of the fitted record.
    reference_time_s: float | None = None

    def __post_init__(self):
        super().__post_init__()
        if (
            isinstance(self.harmonics, bool)
            or not isinstance(self.harmonics, (int, np.integer))
            or not 1 <= self.harmonics <= 5
        ):
            raise MagcalError(f"{self.label}: harmonics must be a whole number 1..5, got {self.harmonics!r}")
        self.frequency_hz = self._checked_frequencies(self.frequency_hz)

    def _checked_frequencies(self, values):
        if values is None:
            return None
        if not isinstance(values, (list, tuple)):
            raise MagcalError(
                f"{self.label}: frequency_hz must be a list (one frequency in Hz per sensor, or null), got {values!r}"
            )
        out = []
        for s, f in enumerate(values):
            if f is None:
                out.append(None)
                continue
            try:
                f = float(f)
            except (TypeError, ValueError):
                f = float("nan")
            if not np.isfinite(f) or f <= 0:
                raise MagcalError(
                    f"{self.label}: frequency_hz of sensor {s + 1} is {values[s]!r}; an interference "
                    "frequency must be a positive number of Hz"
                )
            out.append(f)
        return out

    def param_names(self):
        names = []
        for k in range(1, self.harmonics + 1):
            suffix = "" if k == 1 else str(k)
            names += [f"sin{suffix}_{a}_nT" for a in _AXES] + [f"cos{suffix}_{a}_nT" for a in _AXES]
        return names

    def configure(self, dataset, residuals_nT=None):
        t = dataset.time_s
        self.reference_time_s = float(np.mean(t))
        frequencies = []
        for s in range(dataset.n_sensors):
            if not self.applies_to(s):
                frequencies.append(None)
                continue
            y = dataset.readings_nT[s]
            if residuals_nT is None:
                ok, r = np.ones(len(t), bool), quadric_residuals(y)
            else:
                r = np.asarray(residuals_nT[s], dtype=float)
                ok = np.isfinite(r)
                r = _better_residuals(y if ok.all() else y[ok], r[ok])
            every = ok.all()  # the arrays themselves (the readings' directions are then cached)
            frequencies.append(
                dominant_interference_hz(t if every else t[ok], y if every else y[ok], r, self.min_cycles)
            )
        self.frequency_hz = frequencies

    def state(self):
        return {
            "frequency_hz": self.frequency_hz,
            "reference_time_s": self.reference_time_s,
            "harmonics": self.harmonics,
        }

    def set_state(self, state):
        harmonics = state.get("harmonics", self.harmonics)
        if harmonics != self.harmonics:
            self.harmonics = harmonics
            self.__post_init__()
        self.frequency_hz = self._checked_frequencies(state.get("frequency_hz"))
        self.reference_time_s = state.get("reference_time_s")

    def refine(self, effect_values, context=None, points=13):
        """Move each sensor's frequency to the one that minimises the whole residual, the fitted amplitudes held,
        on a grid of ``points`` frequencies within half a cycle per record of it; True if one moved by more than
        a twentieth of a cycle per record (then the fit is repeated)."""
        if context is None or not self.frequency_hz or not context.dataset.has("time"):
            return False
        t = context.dataset.time_s
        duration = max(float(t[-1] - t[0]), 1e-9)
        frequencies, changed = list(self.frequency_hz), False
        base = self.state()
        for s, f in enumerate(frequencies):
            if f is None:
                continue
            grid = f + np.linspace(-0.5, 0.5, points) / duration
            grid = grid[grid > 0]
            costs = [
                float(
                    np.sum(
                        context.cost_per_sample(
                            self, dict(base, frequency_hz=frequencies[:s] + [float(g)] + frequencies[s + 1 :])
                        )
                    )
                )
                for g in grid
            ]
            best = float(grid[int(np.argmin(costs))])
            if abs(best - f) * duration > 0.05:
                frequencies[s], changed = best, True
        if changed:
            self.frequency_hz = frequencies
        return changed

    def _frequency(self, ctx):
        f = None
        if self.frequency_hz is not None and ctx.sensor < len(self.frequency_hz):
            f = self.frequency_hz[ctx.sensor]
        if f is None:  # never configured: the line in the readings' own ellipsoid residuals
            f = self._cached(
                ctx.dataset,
                ("freq", ctx.sensor),
                lambda: dominant_interference_hz(
                    ctx.time_s, ctx.reading_nT, quadric_residuals(ctx.reading_nT), self.min_cycles
                ),
            )
        return f

    def raw_basis(self, z0, ctx: Context):
        f = self._frequency(ctx)
        t = ctx.time_s
        t0 = float(np.mean(t)) if self.reference_time_s is None else self.reference_time_s
        key = ("periodic", f, t0, self.harmonics)

        def compute():
            columns = []
            for k in range(1, self.harmonics + 1):
                phase = 2 * np.pi * k * (f or 0.0) * (t - t0)
                wave = [np.sin(phase), np.cos(phase)] if f else [np.zeros(len(t))] * 2
                columns += [w for w in wave for _ in range(3)]  # sin on x, y, z, then cos on x, y, z
            return SingleAxisBasis(np.column_stack(columns), np.tile(np.arange(3), 2 * self.harmonics))

        return self._cached(ctx.dataset, key, compute)

    def true_params(self, magnitude=None, sensor=0):
        return None  # the phases are measured from the fitted record's mean time

    def quote(self, values, field_nT=None, sensor=None):
        """The frequency of each harmonic and the peak amplitude per axis (nT) of the fitted sinusoids."""
        v = np.asarray(values, dtype=float).reshape(self.harmonics, 2, 3)
        peak = np.sqrt(v[:, 0] ** 2 + v[:, 1] ** 2)  # (harmonics, axes)
        known = [f for f in (self.frequency_hz or []) if f is not None]
        if sensor is not None and self.frequency_hz and sensor < len(self.frequency_hz):
            known = [self.frequency_hz[sensor]] if self.frequency_hz[sensor] is not None else []
        f = known[0] if len(known) == 1 else None
        parts = []
        for k in range(self.harmonics):
            at = f"{(k + 1) * f:.4g} Hz" if f else f"{k + 1} x the fitted frequency"
            parts.append(f"peak {_axes_text(peak[k])} nT at {at}")
        return "; ".join(parts) + (
            f" ({1e6 * float(np.max(peak)) / field_nT:.0f} ppm of the field {_field_text(field_nT)})"
            if field_nT
            else ""
        )


# ----------------------------------------------------------------------------------------------------------------
# reference field and site
# ----------------------------------------------------------------------------------------------------------------


@register
@dataclass
class ReferenceDrift(CatalogueEffect):
    """The reference field varies slowly during the record (diurnal variation, a drifting reference):
    ``F(t) = F0 + sum_k c_k P_k(tau)``, Legendre polynomials of the time scaled to [-1, 1], mean removed."""

    name: ClassVar[str] = "reference_drift"
    signature: ClassVar[str] = "common to all sensors, independent of direction, slow in time"
    when_recording: ClassVar[str] = (
        "the field at the sensor changed during the record (time of day, a vehicle or iron moving nearby, height): record where and when the field is quiet, in less time, or give the field's variation (a base-station ref_total column or --reference)"
    )
    basis_uses_readings: ClassVar[bool] = False  # a function of the channels only
    stage: ClassVar[str] = "reference"
    channels: ClassVar[tuple] = ("time",)
    per_sensor: ClassVar[bool] = False
    description: ClassVar[str] = "slow variation of the total field, F(t) = F0 + Legendre series in t [nT]"
    default_magnitude: ClassVar[float] = 5.0
    magnitude_unit: ClassVar[str] = "nT"
    transferable: ClassVar[bool] = False  # describes this recording, not the instrument
    kept_for_new_data: ClassVar[str] = "the field's mean over the fitted record"

    #: Legendre degrees used.
    order: ClassVar[int] = 4

    time_span_s: list | None = None
    offsets: list | None = None

    def param_names(self):
        return [f"P{k}_nT" for k in range(1, self.order + 1)]

    def configure(self, dataset, residuals_nT=None):
        t = dataset.time_s
        self.time_span_s = [float(t[0]), float(t[-1])]
        self.offsets = None
        self.offsets = self._raw(t).mean(axis=0).tolist()

    def state(self):
        return {"time_span_s": self.time_span_s, "offsets": self.offsets}

    def set_state(self, state):
        span, offsets = state.get("time_span_s"), state.get("offsets")
        if span is not None:
            ok = isinstance(span, (list, tuple)) and len(span) == 2
            values = _state_times(self, {"time_span_s": list(span)}, "time_span_s") if ok else None
            if not ok or None in values or values[1] <= values[0]:
                raise MagcalError(
                    f"{self.label}: time_span_s must be the first and last time of the record in s, "
                    f"the last after the first, got {span!r}"
                )
            span = values
        if offsets is not None:
            if not isinstance(offsets, (list, tuple)) or len(offsets) != self.order:
                raise MagcalError(f"{self.label}: offsets must be {self.order} numbers, got {offsets!r}")
            offsets = [_state_number(self, {"offsets": v}, "offsets") for v in offsets]
        self.time_span_s, self.offsets = span, offsets

    def _raw(self, t):
        t0, t1 = self.time_span_s or (float(t[0]), float(t[-1]))
        tau = 2.0 * (t - t0) / max(t1 - t0, 1e-9) - 1.0
        return np.column_stack([eval_legendre(k, tau) for k in range(1, self.order + 1)])

    def reference_basis(self, ctx: Context):
        def compute():
            p = self._raw(ctx.time_s)
            return p - (np.asarray(self.offsets) if self.offsets is not None else p.mean(axis=0))

        return self._cached(ctx.dataset, ("ref", tuple(self.time_span_s or ()), tuple(self.offsets or ())), compute)

    def true_params(self, magnitude=None, sensor=0):
        return None


@register
@dataclass
class SiteGradient(CatalogueEffect):
    """A field gradient at the calibration site (a nearby magnetic object): ``B(p) = B0 + G p`` in the world
    frame, ``G`` symmetric and traceless (5 parameters, nT/m). Needs the attitude (``qw, qx, qy, qz``).

    The sensors of an array sit at ``p_s`` (array frame); turned by the attitude ``R`` each sees
    ``R^T G R p_s`` on top of the uniform field. Without attitude the array alone measures, at every sample,
    the gradient tensor in its own frame (that is what a gradiometer does): a site gradient appears as a tensor
    that rotates with the array while its invariants stay constant, and its part along the field aliases into
    the biases (a fake constant tensor offset); its world-frame components cannot be fitted.

    A sample without attitude (a quaternion row of NaN: a recording's samples before its first attitude message,
    a gap in a log) has no predicted site field: the gradient is fixed in the world and the array's rotation into
    it is unknown. The basis is NaN there, so a correction that applies the term gives NaN for those samples (not
    the field rotated by a made-up attitude), and the fitter leaves them out with a note
    (:func:`magcal.model.terms.rows_without_attitude`).
    """

    name: ClassVar[str] = "site_gradient"
    signature: ClassVar[str] = "inter-sensor differences follow the attitude (world-fixed gradient)"
    when_recording: ClassVar[str] = (
        "the field is not uniform over the path of the array: turn it in place, away from iron, or record its attitude and position"
    )
    stage: ClassVar[str] = "array"
    channels: ClassVar[tuple] = ("attitude",)
    per_sensor: ClassVar[bool] = False
    min_sensors: ClassVar[int] = 2
    description: ClassVar[str] = "field gradient at the site (world frame), B(p) = B0 + G p [nT/m]; needs attitude"
    default_magnitude: ClassVar[float] = 20.0
    magnitude_unit: ClassVar[str] = "nT/m"
    transferable: ClassVar[bool] = False  # describes this recording, not the instrument
    kept_for_new_data: ClassVar[str] = "the base terms of the sensors, without the site's gradient"
    pattern: ClassVar[tuple] = (1.0, 0.4, -0.3, -0.6, 0.5)

    def param_names(self):
        return ["Gxx_nT_per_m", "Gxy_nT_per_m", "Gxz_nT_per_m", "Gyy_nT_per_m", "Gyz_nT_per_m"]

    def param_scale(self):
        return np.full(5, 4.0)

    def array_basis(self, field_nT, ctx: Context):
        def compute():
            att = ctx.attitude
            world_offset = att.apply(np.asarray(ctx.position_m, dtype=float))  # (N, 3) m
            cols = [-att.inv().apply(world_offset @ g.T) for g in GRADIENT_BASIS]
            basis = np.stack(cols, axis=-1)
            if ctx.attitude_present is not None and not ctx.attitude_present.all():
                basis[~ctx.attitude_present] = np.nan  # no attitude: no predicted site field (class docstring)
            return basis

        return self._cached(ctx.dataset, ("grad", ctx.sensor, tuple(np.round(ctx.position_m, 9))), compute)

    def true_params(self, magnitude=None, sensor=0):
        magnitude = self.default_magnitude if magnitude is None else magnitude
        m = np.atleast_1d(np.asarray(magnitude, dtype=float))
        return m.copy() if m.size == 5 else m[0] * np.asarray(self.pattern)


# ----------------------------------------------------------------------------------------------------------------
# a field or an offset that wanders during the record; sampling jitter between sensors
# ----------------------------------------------------------------------------------------------------------------

#: Spacing (s) of the hat functions (knots) of :class:`FieldChange` and :class:`OffsetWander`: a field along a
#: hand-held path or a wandering offset changes over a few seconds (on the real records a series every 2-5 s fits
#: what a record-long polynomial cannot).
WANDER_KNOT_SPACING_S = 3.0
#: Most knots of one series; a longer record gets a wider spacing (a raw-stage basis holds 3 columns per knot).
WANDER_MAX_KNOTS = 60
#: Fewest samples per knot interval: a short or sparse record gets a wider spacing.
WANDER_SAMPLES_PER_KNOT = 20
#: Knots of an effect not yet configured (what the catalogue lists; a fit sets them from the record).
WANDER_DEFAULT_KNOTS = 7
#: The field direction turns by at least this much (deg, median) between two knots: a series of knots closer than
#: the sensor turns follows any direction pattern times a slow function of time (a temperature bias on a slow turn),
#: so the knots are spread to this turn at least. What tells a field change from an offset wander, and both from
#: the direction patterns of the other terms, is the directions the sensor sweeps between two knots.
WANDER_TURN_PER_KNOT_DEG = 120.0
#: Lag (s) over which the turn rate of the field direction is measured (longer than the noise's sample-to-sample
#: wobble of the direction).
TURN_RATE_LAG_S = 0.5


def wander_knots(time_s, spacing_s=WANDER_KNOT_SPACING_S, max_knots=WANDER_MAX_KNOTS) -> np.ndarray:
    """Knot times (s) of a B-spline series over a record: evenly spaced from its first to its last sample,
    about ``spacing_s`` apart, at most ``max_knots`` and at least :data:`WANDER_SAMPLES_PER_KNOT` samples per
    interval (at least 3 knots)."""
    t = np.asarray(time_s, dtype=float)
    t0, t1 = float(np.min(t)), float(np.max(t))
    span = max(t1 - t0, 1e-9)
    intervals = int(np.ceil(span / max(float(spacing_s), 1e-9)))
    intervals = min(intervals, int(max_knots) - 1, max(len(t) // WANDER_SAMPLES_PER_KNOT, 2))
    return np.linspace(t0, t0 + span, max(intervals, 2) + 1)


def hat_columns(time_s, knots_s, degree=1) -> np.ndarray:
    """(N, K - 1 + degree) B-spline basis of ``degree`` on the K knots (the ends repeated): for ``degree`` 1 the
    piecewise-linear hat functions, column ``k`` 1 at knot ``k`` and 0 at its neighbours; for 3 the cubic
    B-splines, which follow a smooth wander without the hats' corners at every knot. The columns sum to 1 and stay
    flat beyond the first and last knot."""
    k = np.asarray(knots_s, dtype=float)
    t = np.clip(np.asarray(time_s, dtype=float), k[0], k[-1])
    full = np.concatenate([np.full(degree, k[0]), k, np.full(degree, k[-1])])
    return BSpline.design_matrix(t, full, int(degree)).toarray()


def median_turn_rate_dps(readings_nT, time_s) -> float:
    """The median rate (deg/s) at which the direction of the readings (about their mean) turns, measured over
    :data:`TURN_RATE_LAG_S`; NaN without two distinct times."""
    y = np.asarray(readings_nT, dtype=float)
    t = np.asarray(time_s, dtype=float)
    step = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
    if not step > 0:
        return float("nan")
    lag = int(np.clip(round(TURN_RATE_LAG_S / step), 1, max(len(t) - 1, 1)))
    u = y - y.mean(axis=0)
    u /= np.maximum(row_norm(u), 1e-12)[:, None]
    angle = np.degrees(np.arccos(np.clip(np.sum(u[lag:] * u[:-lag], axis=1), -1.0, 1.0)))
    dt = t[lag:] - t[:-lag]
    ok = dt > 0
    return float(np.median(angle[ok] / dt[ok])) if np.any(ok) else float("nan")


def series_spacing_s(dataset, spacing_s=WANDER_KNOT_SPACING_S) -> float:
    """The knot spacing (s) of a series on this record: ``spacing_s``, or the time the field direction takes to turn
    by :data:`WANDER_TURN_PER_KNOT_DEG` at its median rate when that is longer (sensor 1's readings)."""
    rate = median_turn_rate_dps(dataset.readings_nT[0], dataset.time_s)
    if not np.isfinite(rate) or rate <= 0:
        return float(spacing_s)
    return float(max(spacing_s, WANDER_TURN_PER_KNOT_DEG / rate))


@dataclass
class _KnotSeries(CatalogueEffect):
    """Shared by the terms that follow a quantity through the record as a B-spline series ``sum_k c_k h_k(t)``
    with knots about :data:`WANDER_KNOT_SPACING_S` apart (:func:`wander_knots`, :func:`hat_columns`): ``degree`` 1
    (default, hat functions) or 3 (cubic B-splines). The hats are the default: each coefficient acts on two knot
    intervals only, so an offset series stays local; a cubic series' wider, overlapping columns let an offset
    run away along a short arc of directions (on a slow turn, tens of uT on a record with none).

    The knots are :attr:`knot_spacing_s` apart, or further where the sensor turns slowly: the field direction turns
    by :data:`WANDER_TURN_PER_KNOT_DEG` between two knots at least (:func:`series_spacing_s`).

    The B-splines sum to 1, so a constant is the base model's (the bias, the field ``F0``): the first one is dropped
    and every other column has its mean over the fitted record removed (kept as ``offsets``), so that the series
    has zero mean on the record and the base terms are referred to the record's mean level. A parameter is then
    the series' coefficient near its knot relative to the first (nT; for hats its value at the knot).
    """

    basis_uses_readings: ClassVar[bool] = False  # a function of the time only
    channels: ClassVar[tuple] = ("time",)
    transferable: ClassVar[bool] = False
    #: A held-out block of 10 s holds knots the fit has no samples for: judged in-sample (its delta-BIC).
    held_out_blocks: ClassVar[bool] = False

    knot_spacing_s: float = WANDER_KNOT_SPACING_S
    max_knots: int = WANDER_MAX_KNOTS
    degree: int = 1
    knots_s: list | None = None
    offsets: list | None = None

    @property
    def n_columns(self) -> int:
        """Columns of the series after the first: knots - 2 + degree."""
        knots = WANDER_DEFAULT_KNOTS if self.knots_s is None else len(self.knots_s)
        return knots - 2 + int(self.degree)

    def configure(self, dataset, residuals_nT=None):
        spacing = series_spacing_s(dataset, self.knot_spacing_s)
        self.knots_s = wander_knots(dataset.time_s, spacing, self.max_knots).tolist()
        self.offsets = hat_columns(dataset.time_s, self.knots_s, self.degree)[:, 1:].mean(axis=0).tolist()

    def state(self):
        return {
            "knots_s": self.knots_s,
            "offsets": self.offsets,
            "knot_spacing_s": self.knot_spacing_s,
            "max_knots": self.max_knots,
            "degree": self.degree,
        }

    def set_state(self, state):
        degree = state.get("degree", 1)
        if degree not in (1, 2, 3):
            raise MagcalError(f"{self.label}: degree must be 1 (hats), 2 or 3 (cubic B-splines), got {degree!r}")
        self.degree = int(degree)
        knots, offsets = state.get("knots_s"), state.get("offsets")
        if knots is not None:
            values = _state_times(self, {"knots_s": knots}, "knots_s") or []
            if len(values) < 3 or None in values or np.any(np.diff(np.asarray(values, dtype=float)) <= 0):
                raise MagcalError(
                    f"{self.label}: knots_s must be at least 3 increasing times in s (the series' knots), got {knots!r}"
                )
            knots = values
        self.knots_s = knots
        if offsets is not None:
            if not isinstance(offsets, (list, tuple)) or len(offsets) != self.n_columns:
                raise MagcalError(f"{self.label}: offsets must be {self.n_columns} numbers (one per column)")
            offsets = [_state_number(self, {"offsets": v}, "offsets") for v in offsets]
        spacing = _state_number(self, state, "knot_spacing_s", positive=True, what="the knot spacing in s")
        most = _state_number(self, state, "max_knots", minimum=3, what="the most knots of the series")
        self.offsets = offsets
        self.knot_spacing_s = WANDER_KNOT_SPACING_S if spacing is None else spacing
        self.max_knots = WANDER_MAX_KNOTS if most is None else int(most)

    def _series(self, time_s) -> np.ndarray:
        """(N, :attr:`n_columns`) the zero-mean columns after the first (the class docstring)."""
        t = np.asarray(time_s, dtype=float)
        knots = self.knots_s
        if knots is None:  # not configured: the default count of knots over these samples
            knots = np.linspace(float(t.min()), float(t.max()) + 1e-9, WANDER_DEFAULT_KNOTS).tolist()
        h = hat_columns(t, knots, self.degree)[:, 1:]
        return h - (np.asarray(self.offsets) if self.offsets is not None else h.mean(axis=0))

    def _series_cached(self, ctx):
        key = ("series", self.degree, tuple(self.knots_s or ()), tuple(self.offsets or ()))
        return self._cached(ctx.dataset, key, lambda: self._series(ctx.time_s))

    def _values_over_knots(self, values) -> np.ndarray:
        """A fitted series' values (nT) at its knots, zero mean over them: for a quote."""
        t = np.asarray(self.knots_s if self.knots_s is not None else np.linspace(0.0, 1.0, WANDER_DEFAULT_KNOTS))
        g = hat_columns(t, t, self.degree)[:, 1:] @ np.asarray(values, dtype=float)
        return g - g.mean()

    def true_params(self, magnitude=None, sensor=0):
        return None  # the simulator's wander is smooth sines, not a spline series


@register
@dataclass
class FieldChange(_KnotSeries):
    """The total field changes during the record faster than a drift: ``F(t) = F0 + g(t)``, ``g`` a hat-function
    series with knots every few seconds (:class:`_KnotSeries`), shared by all sensors.

    A sensor carried along a path through a non-uniform field (a hand-held tumble that wanders, a magnet or steel
    fixed in the room, a vehicle nearby) or a field that changes in time sees every direction scaled alike: samples revisiting the same direction
    differ by the same amount whatever that direction, and sensors of an array see the same change. Record-only.

    Parameters ``g{k}_nT``: the field at knot ``k`` relative to the first knot, nT; physical range a few nT (a
    quiet site) to a few uT (a path near iron), signed.
    """

    name: ClassVar[str] = "field_change"
    signature: ClassVar[str] = (
        "common to all sensors and all directions, changing within seconds (same-direction revisits differ alike)"
    )
    when_recording: ClassVar[str] = (
        "the field at the sensor changed within seconds during the record (moved along a path through a non-uniform field, iron moving nearby): turn the sensor in place about its own centre, away from iron and moving objects"
    )
    stage: ClassVar[str] = "reference"
    per_sensor: ClassVar[bool] = False
    description: ClassVar[str] = "the total field changing within seconds, F(t) = F0 + g(t), hats every few s [nT]"
    default_magnitude: ClassVar[float] = 20.0
    magnitude_unit: ClassVar[str] = "nT"
    kept_for_new_data: ClassVar[str] = "the field's mean over the fitted record"

    def param_names(self):
        return [f"g{k}_nT" for k in range(1, self.n_columns + 1)]

    def reference_basis(self, ctx: Context):
        return self._series_cached(ctx)

    def quote(self, values, field_nT=None, sensor=None) -> str:
        g = self._values_over_knots(np.ravel(values))
        return f"the field moves over {float(np.ptp(g)):.3g} nT peak to peak (RMS over the knots {float(np.std(g)):.3g} nT)"


@register
@dataclass
class OffsetWander(_KnotSeries):
    """The instrument's offset wanders during the record: ``y += b(t)``, ``b`` per axis a B-spline series with
    knots every few seconds (:class:`_HatSeries`).

    An offset of the sensor itself (a warm-up, a supply, a part magnetised and relaxing), or of something magnetic
    carried with it and moved (a magnet, steel: a hard iron that changes; a magnet fixed in the room is a field that
    changes with the place instead, :class:`FieldChange`): in the total field it
    shows as ``u . C^-1 b(t)``, so samples revisiting the same direction differ by an amount that depends on
    the direction, and each sensor of an array wanders on its own. It belongs to the instrument, but a wander
    cannot be extrapolated to another record: record-only (the calibration keeps the record's mean offset).

    Parameters ``b{k}_{x,y,z}_nT``: the offset at knot ``k`` relative to the first knot, nT per axis; physical
    range a few nT (a settled fluxgate) to a few uT (a MEMS part warming up), signed.
    """

    name: ClassVar[str] = "offset_wander"
    signature: ClassVar[str] = (
        "u . b(t): a field-direction pattern of degree 1 changing within seconds, its own on each sensor"
    )
    when_recording: ClassVar[str] = (
        "the sensor's own offset wandered within seconds (warm-up, supply, a part relaxing after a field), or something magnetic carried with it moved (a magnet, steel, a battery shifting): let it settle powered before recording, keep the supply and the temperature steady, fasten what travels with the sensor, record shorter"
    )
    stage: ClassVar[str] = "raw"
    #: The vector calibration has its own drift terms; its diagnosis does not test this one.
    modes: ClassVar[tuple] = ("scalar",)
    description: ClassVar[str] = "the instrument's offset wandering within seconds, y += b(t), hats every few s [nT]"
    default_magnitude: ClassVar[float] = 20.0
    magnitude_unit: ClassVar[str] = "nT"
    kept_for_new_data: ClassVar[str] = "the bias at the fitted record's mean (the wander's mean over the record)"

    def param_names(self):
        return [f"b{k}_{a}_nT" for a in _AXES for k in range(1, self.n_columns + 1)]

    def raw_basis(self, z0, ctx: Context):
        h = self._series_cached(ctx)
        q = h.shape[1]
        return SingleAxisBasis(np.concatenate([h, h, h], axis=1), np.repeat(np.arange(3), q))

    def quote(self, values, field_nT=None, sensor=None) -> str:
        b = np.array([self._values_over_knots(v) for v in np.asarray(values, dtype=float).reshape(3, -1)])
        return (
            f"the offset moves over {_axes_text(np.ptp(b, axis=1))} nT peak to peak per axis (a size the total field "
            "does not determine: between two knots an offset trades against the curvature of the short arc of "
            "directions swept)"
        )


@register
@dataclass
class SensorJitter(CatalogueEffect):
    """Sensors of an array sampled with a random time error against sensor 1: ``B_i(t - dt)``, ``dt`` random with
    RMS ``tau`` (the jitter of two buses read by one host).

    A variance term: the inter-sensor residual's variance grows as ``sigma^2 + (tau |dB/dt|)^2``, so the diagnosis
    estimates ``tau`` (ms) from that variance against the turn rate (:func:`magcal.diagnosis.jitter.jitter_estimates`)
    rather than proposing it by a score test. Its mean is second order, ``B + (tau^2 / 2) d^2B/dt^2``: that is
    the basis of the term, with the parameter ``tau^2`` in ms^2, when it is fitted.

    Parameter ``jitter_variance_ms2`` = ``tau^2``, ``>= 0``; physical range 0 to about 100 ms^2 (0-10 ms RMS: a
    jitter beyond the sampling interval would be a skipped sample).
    """

    name: ClassVar[str] = "sensor_jitter"
    signature: ClassVar[str] = "inter-sensor residual variance grows with the turn rate squared"
    stage: ClassVar[str] = "array"
    channels: ClassVar[tuple] = ("time",)
    min_sensors: ClassVar[int] = 2
    variance_term: ClassVar[bool] = True
    evidence_channel: ClassVar[str] = "turn_rate_dps"
    description: ClassVar[str] = "random sampling-time error of sensors 2-4 against sensor 1, RMS tau [ms^2 = tau^2]"
    default_magnitude: ClassVar[float] = 2.0
    magnitude_unit: ClassVar[str] = "ms"
    pattern: ClassVar[tuple] = (0.0, 1.0, 0.7, 0.5)
    bounds_note: ClassVar[str] = "a variance: the square of the jitter's RMS in ms"

    def __post_init__(self):
        super().__post_init__()
        if self.sensor == 0:
            raise MagcalError("sensor_jitter: sensor 1 is the time reference; name sensor 2, 3 or 4")

    def applies_to(self, sensor):
        return sensor > 0 and (self.sensor is None or self.sensor == sensor)

    def param_names(self):
        return ["jitter_variance_ms2"]

    def param_scale(self):
        return np.array([10.0])

    def param_bounds(self):
        return np.zeros(1), np.full(1, np.inf)

    def array_basis(self, field_nT, ctx: Context):
        acceleration = time_derivative(time_derivative(field_nT, ctx.time_s), ctx.time_s)
        return 0.5e-6 * acceleration[:, :, None]

    def true_params(self, magnitude=None, sensor=1):
        magnitude = self.default_magnitude if magnitude is None else magnitude
        tau = float(np.ravel(magnitude)[0]) * self.pattern[sensor % 4]
        return np.array([tau**2])

    def quote(self, values, field_nT=None, sensor=None) -> str:
        return f"a sampling jitter of {np.sqrt(max(float(np.ravel(values)[0]), 0.0)):.3g} ms RMS"
