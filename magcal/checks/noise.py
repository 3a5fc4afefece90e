"""The noise of a recording: robust spread and the noise floor a fit is judged against.

:func:`robust_sigma` is the one robust standard deviation of magcal (fit, outlier rejection, robust starts,
diagnosis): the median absolute deviation about the median, scaled by 1.4826 so that it equals the standard
deviation for Gaussian noise, and insensitive to the few gross outliers that real recordings have.

:func:`estimate_noise` gives the per-axis noise level (nT) a fit's residuals are judged against
(:class:`NoiseEstimate`), independently of the model's misfit, and says which method gave it (``source``):

``given``
    A noise the user declared (``noise_nT=``, ``--noise NT``, or the data file's ``# noise_nT:`` line) always
    takes precedence over any estimate.
``differences``
    Along a smooth trajectory a missing effect changes slowly from sample to sample while the noise does not, so
    the noise is estimated from the differences of the residuals in time order (``var(d^k r) = C(2k, k) sigma^2``
    for white noise), with gross jumps clipped: the smaller of the 2nd- and 3rd-order estimates (a slow misfit
    leaks least into the higher order, content near the sampling rate least into the lower one). Samples that
    are not real conversions are dropped before differencing (:func:`fresh_samples`): those that repeat the
    previous reading exactly (stale: the host polled faster than the part converts) and those that lie on the
    straight line between their neighbours (a logger that upsampled the stream by interpolation,
    :func:`interpolated_mask`); their differences are zero and would bias the estimate low (a stream upsampled
    3x by a repeat and a midpoint gives 42 nT where the noise is 741 nT).
``static``
    The record has still stretches (:func:`magcal.checks.quality.static_stretches`) holding at least
    :data:`MIN_STATIC_SAMPLES` samples: the second differences of the readings in them, stale samples dropped.
    A direct measurement, free of any misfit of the model, so it is preferred to ``differences``; the stretches'
    scatter about a straight line (:func:`magcal.checks.quality.static_scatter_nT`, which a slow wander of the still
    sensor inflates) is reported beside it.
``quantization``
    The estimate fell below the quantization floor ``q / sqrt(12)`` (:func:`magcal.checks.quality.quantization_step`),
    which no noise estimate goes under.
``residuals``
    No smooth order, no still stretch, nothing declared: the residual RMS itself (then a misfit cannot be told
    from noise by its size, only by its structure).

Low-frequency noise
    The differences measure the noise at the sampling rate only. A sensor whose output also wanders slowly
    (flicker noise, an offset that wanders) or whose stream was filtered (correlated noise) leaves more in the
    residuals of any model; the still stretches measure it: their variance about the mean of windows as long as
    the record takes to turn through a radian (the time scale over which a missing effect and the noise compete),
    less the white noise, is added to the estimate in quadrature (:func:`low_frequency_noise_nT`,
    :attr:`NoiseEstimate.low_frequency_nT`, its scale :attr:`NoiseEstimate.low_frequency_scale_s`).

Every estimate reports the still stretches' figures and the quantization floor beside it
(:attr:`NoiseEstimate.static_noise_nT`, :attr:`NoiseEstimate.static_scatter_nT`,
:attr:`NoiseEstimate.quantization_floor_nT`), so a reader can check one against the other.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.special import comb, erf

from magcal.checks.quality import quantization_step, stale_mask, static_scatter_nT, static_stretches, static_window
from magcal.core.errors import MagcalError
from magcal.core.readings_cache import ReadingsCache
from magcal.core.rows import row_norm
from magcal.core.stats import robust_sigma
from magcal.geometry.shape import field_shape

#: Sources of :class:`NoiseEstimate`, in the order they are tried.
NOISE_SOURCES = ("given", "differences", "static", "quantization", "residuals")

#: Orders of the differences of :func:`estimate_noise` (the smaller estimate is kept).
DIFFERENCE_ORDERS = (2, 3)

#: Fewest samples in still stretches (per sensor) for their second differences to be the noise (``static``).
MIN_STATIC_SAMPLES = 100

_SOURCE_WORDS = {
    "given": "given",
    "differences": "estimated from the differences of the residuals in time order",
    "static": "estimated from the second differences of the readings in still stretches",
    "quantization": "the quantization floor q/sqrt(12): the estimate fell below it",
    "residuals": "estimated from the residual RMS itself (no independent check of the fit)",
}


@dataclass
class NoiseEstimate:
    """The per-axis noise level used for floors and the verdict of a diagnosis.

    Attributes
    ----------
    sigma_nT : float
        Noise standard deviation per axis (nT), pooled over the sensors (root mean square of ``per_sensor_nT``).
    per_sensor_nT : numpy.ndarray, shape (n_sensors,)
        Noise standard deviation of each sensor (nT).
    source : str
        One of :data:`NOISE_SOURCES`: ``"given"`` (declared by the user or the data file), ``"differences"``,
        ``"static"``, ``"quantization"`` (the floor ``q/sqrt(12)``) or ``"residuals"`` (residual RMS; cannot tell
        misfit from noise by size).
    relative_variance_error : float
        Relative standard error of ``sigma^2`` per sensor (dimensionless, for the excess test; 0 when given).
    note : str
        Where a given noise came from, or why a fallback source was used.
    static_noise_nT : numpy.ndarray or None, shape (n_sensors,)
        Noise per axis (nT, root mean square over the axes) from the second differences of each sensor's
        readings in its still stretches (NaN for a sensor without enough of them); None if no sensor has any.
    static_scatter_nT : numpy.ndarray or None, shape (n_sensors,)
        Scatter per axis (nT, root mean square over the axes) of the readings in the still stretches about a
        straight line (a slow wander of the still sensor included); None if no sensor has a still stretch.
    quantization_floor_nT : numpy.ndarray or None, shape (n_sensors,)
        ``q / sqrt(12)`` per sensor (nT, root mean square over the axes' steps q); None if the readings show no
        step.
    low_frequency_nT : numpy.ndarray or None, shape (n_sensors,)
        The slow part of the noise (nT per axis) the still stretches show over :attr:`low_frequency_scale_s`
        (:func:`low_frequency_noise_nT`), included in ``per_sensor_nT`` in quadrature; None when no still stretch
        measures it.
    low_frequency_scale_s : float or None
        The time scale (s) of ``low_frequency_nT``: the time the record takes to turn through a radian, at most
        half the longest still stretch.
    left_out : dict
        Samples left out of the differences because they are not real conversions, by kind (``repeated``,
        ``interpolated``): the most over the sensors.
    """

    sigma_nT: float
    per_sensor_nT: np.ndarray
    source: str
    relative_variance_error: float
    note: str = ""
    static_scatter_nT: np.ndarray | None = None
    quantization_floor_nT: np.ndarray | None = None
    static_noise_nT: np.ndarray | None = None
    low_frequency_nT: np.ndarray | None = None
    low_frequency_scale_s: float | None = None
    left_out: dict = field(default_factory=dict)

    def text(self) -> str:
        """``"3.02 nT (given)"``, ``"709 nT (estimated from the differences ...; still stretches scatter ...)"``."""
        out = f"{self.sigma_nT:.3g} nT per axis ({self.floor_words()}"
        left = [f"{n} {kind}" for kind, n in self.left_out.items() if n]
        if left:
            out += "; " + " and ".join(left) + " samples left out as not real conversions"
        if self.static_noise_nT is not None and self.source != "static":
            out += "; still stretches' differences " + _values(self.static_noise_nT) + " nT"
        if self.static_scatter_nT is not None:
            out += "; still stretches' scatter " + _values(self.static_scatter_nT) + " nT"
        if self.quantization_floor_nT is not None and self.source != "quantization":
            out += f"; quantization floor {np.max(self.quantization_floor_nT):.3g} nT"
        return out + ")"

    def floor_words(self) -> str:
        """Where the noise the floor is built on came from, in a few words: ``"estimated from the differences of the
        residuals in time order"``, with the low-frequency part when one was added."""
        words = _SOURCE_WORDS.get(self.source, self.source)
        if self.low_frequency_nT is not None and np.any(np.nan_to_num(self.low_frequency_nT) > 0):
            words += (
                f", with low-frequency noise of {_values(self.low_frequency_nT)} nT from the still stretches over "
                f"{self.low_frequency_scale_s:.3g} s"
            )
        return words

    def to_dict(self) -> dict:
        """JSON-ready figures: ``noise_nT``, ``per_sensor_nT``, ``source``, ``note``, ``static_scatter_nT``,
        ``quantization_floor_nT`` (nT; NaN written as None)."""

        def _list(v):
            return None if v is None else [float(x) if np.isfinite(x) else None for x in np.asarray(v, float)]

        return {
            "noise_nT": float(self.sigma_nT),
            "per_sensor_nT": _list(self.per_sensor_nT),
            "source": self.source,
            "note": self.note,
            "static_noise_nT": _list(self.static_noise_nT),
            "static_scatter_nT": _list(self.static_scatter_nT),
            "quantization_floor_nT": _list(self.quantization_floor_nT),
            "low_frequency_nT": _list(self.low_frequency_nT),
            "low_frequency_scale_s": self.low_frequency_scale_s,
            "left_out": {kind: int(n) for kind, n in self.left_out.items()},
        }


def is_smooth_sequence(dataset) -> bool:
    """True if consecutive samples are close in attitude (a smooth trajectory in time order).

    Compares the typical step between consecutive raw readings of the first sensor with their spread: about 1.4
    for independent random attitudes, a few percent for a sensor turned continuously and sampled at several Hz.

    Parameters
    ----------
    dataset : magcal.data.dataset.Dataset
        The recording; its ``readings_nT`` (n_sensors, N, 3) in nT.

    Returns
    -------
    bool
        True when the median step is below a quarter of the spread; False for fewer than 20 samples.
    """
    y = dataset.readings_nT[0]
    if len(y) < 20:
        return False
    step = np.median(row_norm(np.diff(y, axis=0)))
    spread = np.sqrt(np.sum(np.var(y, axis=0)))
    return bool(step < 0.25 * spread)


def _difference_variance(r, order=2):
    """Noise variance from the ``order``-th differences of ``r``.

    Parameters
    ----------
    r : array_like, shape (N,)
        Residuals in time order (nT), without NaN.
    order : int
        Order ``k`` of the differences.

    Returns
    -------
    float
        ``mean(d^2) / C(2k, k)`` (nT^2) over the differences within 6 robust sigmas of their median (gross jumps
        clipped); NaN for fewer than 10 differences.
    """
    d = np.diff(np.asarray(r, dtype=float), n=order)
    if len(d) < 10:
        return float("nan")
    return _clipped_mean_square(d) / comb(2 * order, order)


def _clipped_mean_square(d) -> float:
    """Mean square of ``d`` over the values within 6 robust sigmas of their median (gross jumps clipped)."""
    med, mad = np.median(d), robust_sigma(d)
    if mad > 0:
        d = d[np.abs(d - med) < 6.0 * mad]
    return float(np.mean(d**2))


def _difference_variance_error(n, order=2):
    """Relative standard error of :func:`_difference_variance` for white Gaussian noise of ``n`` samples.

    The differences are correlated (binomial weights ``C(2k, k + j)``), so the error is larger than the
    ``sqrt(2 / n)`` of independent samples: ``sqrt(70 / 18 / n)`` ~ ``1.97 / sqrt(n)`` for ``k = 2``.
    """
    c = np.array([comb(2 * order, order + k) for k in range(-order, order + 1)], dtype=float)
    return float(np.sqrt(2.0 * np.sum(c**2) / comb(2 * order, order) ** 2 / max(n, 1)))


def _values(v) -> str:
    return ", ".join("-" if not np.isfinite(x) else f"{x:.3g}" for x in np.asarray(v, float))


#: Least share of the fresh samples that must lie on the line between their neighbours, and the factor over the
#: share white noise would put there by chance, for :func:`interpolated_mask` to call them interpolated.
INTERPOLATED_MIN_FRACTION = 0.02
INTERPOLATED_CHANCE_FACTOR = 3.0


def interpolated_mask(readings_nT, steps_nT=None) -> np.ndarray:
    """True where a sample lies on the straight line between its neighbours (all three axes), shape (N,): the
    midpoints a logger inserts when it upsamples a stream by linear interpolation.

    Among the samples that do not repeat the previous one (:func:`magcal.checks.quality.stale_mask`), a sample is
    on the line when its second difference is within one quantization step of zero on every axis (``steps_nT``,
    the axes' steps, :func:`quantization_steps_nT`; a millionth of the field's spread without one: an
    interpolated value rounded to the logger's resolution). White noise puts some real samples there by chance;
    the samples are called interpolated only when they are at least :data:`INTERPOLATED_MIN_FRACTION` of the
    record and :data:`INTERPOLATED_CHANCE_FACTOR` times the share the second differences' own spread gives by
    chance (all False otherwise).
    """
    y = np.asarray(readings_nT, dtype=float)
    out = np.zeros(len(y), dtype=bool)
    index = np.flatnonzero(~stale_mask(y))
    if index.size < 20:
        return out
    x = y[index]
    steps = quantization_steps_nT(x) if steps_nT is None else steps_nT
    spread = float(np.sqrt(np.sum(np.var(x, axis=0))))
    tol = np.array([q if q else 1e-6 * spread for q in steps], dtype=float)
    d2 = np.abs(x[:-2] - 2.0 * x[1:-1] + x[2:])
    on_line = np.all(d2 <= tol + 1e-9 * max(spread, 1.0), axis=1)
    signed = x[:-2] - 2.0 * x[1:-1] + x[2:]
    # their spread; over the samples off the line when most are on it (the median deviation is then 0)
    spread_of = signed[~on_line] if on_line.mean() > 0.5 and (~on_line).sum() >= 10 else signed
    sigma = np.array([robust_sigma(d) for d in spread_of.T])
    with np.errstate(divide="ignore", invalid="ignore"):
        chance = float(np.prod(np.where(sigma > 0, erf_share(tol / np.maximum(sigma, 1e-300)), 1.0)))
    count = int(on_line.sum())
    if count < max(10, INTERPOLATED_MIN_FRACTION * len(x)) or count < INTERPOLATED_CHANCE_FACTOR * chance * len(x):
        return out
    out[index[1:-1][on_line]] = True
    return out


def erf_share(z):
    """Share of a Gaussian within ``z`` standard deviations of its mean (``erf(z / sqrt 2)``)."""
    return erf(np.asarray(z, dtype=float) / np.sqrt(2.0))


def fresh_samples(readings_nT, steps_nT=None) -> np.ndarray:
    """True for the samples that are real conversions, shape (N,): not an exact repeat of the previous reading
    (all three axes) and not on the straight line between its neighbours (:func:`interpolated_mask`).

    A stale sample (the host polled faster than the part converts) is the previous reading counted twice, an
    interpolated one the mean of its neighbours: their differences are zero, which biases a difference estimate of
    the noise low.
    """
    return ~(stale_mask(readings_nT) | interpolated_mask(readings_nT, steps_nT))


def _left_out(readings_nT, fresh) -> dict:
    """How many samples :func:`fresh_samples` left out, by kind (``repeated``, ``interpolated``)."""
    stale = stale_mask(readings_nT)
    return {"repeated": int(stale.sum()), "interpolated": int((~fresh & ~stale).sum())}


def quantization_steps_nT(readings_nT) -> list:
    """The quantization step (nT, or None) of each axis of one sensor's readings (N, 3)
    (:func:`magcal.checks.quality.quantization_step`)."""

    y = np.asarray(readings_nT, float)
    return [quantization_step(y[:, k]) for k in range(3)]


def quantization_floor_nT(readings_nT, steps_nT=None) -> float | None:
    """``q / sqrt(12)`` (nT) of one sensor's readings, ``q`` the root mean square over the axes of their
    quantization steps (:func:`quantization_steps_nT`, or ``steps_nT`` when the caller has them); None when no
    axis shows a step."""
    steps = quantization_steps_nT(readings_nT) if steps_nT is None else steps_nT
    steps = [q for q in steps if q is not None]
    if not steps:
        return None
    return float(np.sqrt(np.mean(np.square(steps)) / 12.0))


def still_noise_nT(dataset, steps_nT=None, low_frequency=False):
    """Noise of each sensor measured in its still stretches (:func:`magcal.checks.quality.static_stretches`).

    Parameters
    ----------
    dataset : magcal.data.dataset.Dataset
    steps_nT : list, optional
        Per sensor, the axes' quantization steps (:func:`quantization_steps_nT`) when the caller has them.
    low_frequency : bool
        Also return, per sensor, the low-frequency noise (nT, NaN without a measure,
        :func:`low_frequency_noise_nT`) and its longest time scale (s, or None), as two more values.

    Returns
    -------
    differences_nT, scatter_nT, samples : numpy.ndarray, shape (n_sensors,)
        Per-axis noise (nT, root mean square over the axes) from the second differences of the readings in the
        stretches, samples that are not real conversions dropped (:func:`fresh_samples`) and gross jumps clipped
        (NaN without 10 differences); their scatter about a straight line per stretch
        (:func:`magcal.checks.quality.static_scatter_nT`, NaN without a stretch); and the number of samples in the
        stretches.
    """
    figures = _still_figures(dataset, steps_nT)
    return figures if low_frequency else figures[:3]


def _interval_s(dataset) -> float | None:
    """The median sampling interval (s) of the dataset, or None without time stamps."""
    if dataset.time_s is None or dataset.n_samples < 2:
        return None
    dt = np.diff(np.asarray(dataset.time_s, float))
    dt = dt[np.isfinite(dt) & (dt > 0)]
    return float(np.median(dt)) if dt.size else None


def _still_figures(dataset, steps_nT=None):
    """:func:`still_noise_nT`'s figures and, per sensor, the low-frequency noise (nT, NaN without a measure) and
    its time scale (s, or None): :func:`low_frequency_noise_nT` of the still stretches."""

    interval = _interval_s(dataset)
    ns = dataset.n_sensors
    diff_nT, scatter_nT, samples = np.full(ns, np.nan), np.full(ns, np.nan), np.zeros(ns, int)
    low_nT, scales = np.full(ns, np.nan), []
    for s in range(ns):
        y = np.asarray(dataset.readings_nT[s], float)
        steps = None if steps_nT is None else steps_nT[s]
        stretches = static_stretches(y, window=static_window(len(y), interval), steps_nT=steps)
        scatter = static_scatter_nT(y, stretches)
        if scatter is not None:
            scatter_nT[s] = float(np.sqrt(np.mean(np.square(scatter))))
        fresh = fresh_samples(y, steps)
        d2 = [np.diff(y[a:b][fresh[a:b]], n=2, axis=0) for a, b in stretches]
        d2 = np.concatenate([d for d in d2 if len(d)], axis=0) if any(len(d) for d in d2) else np.empty((0, 3))
        samples[s] = sum(b - a for a, b in stretches)
        scale = None
        if len(d2) >= 10:
            variances = [_clipped_mean_square(d2[:, k]) / comb(4, 2) for k in range(3)]
            diff_nT[s] = float(np.sqrt(np.mean(variances)))
            scale = _turn_scale_samples(y, fresh, stretches)
            low_nT[s] = low_frequency_noise_nT(y, stretches, fresh, diff_nT[s], scale)
        scales.append(None if scale is None else scale * (interval or 1.0))
    return diff_nT, scatter_nT, samples, low_nT, max((x for x in scales if x is not None), default=None)


#: Fewest degrees of freedom (over the stretches and axes) the variance within windows is taken from.
WINDOW_MIN_DOF = 30


def _window_variance(magnitude, stretches, fresh, m) -> tuple:
    """Variance (nT^2) of the real samples of ``magnitude`` (N,) in the still ``stretches`` about the mean of each
    window of ``m`` of them, and its degrees of freedom."""
    total, dof = 0.0, 0
    for a, b in stretches:
        x = magnitude[a:b][fresh[a:b]]
        k = len(x) // m
        if k < 1:
            continue
        windows = x[: k * m].reshape(k, m)
        total += float(np.sum((windows - windows.mean(axis=1, keepdims=True)) ** 2))
        dof += k * (m - 1)
    return (total / dof if dof else float("nan")), dof


def low_frequency_noise_nT(y, stretches, fresh, white_nT, scale_samples) -> float:
    """The slow part of one sensor's noise (nT per axis) its still stretches show, up to ``scale_samples``.

    The variance of the still readings' field magnitude (through the readings' ellipsoid,
    :func:`magcal.geometry.shape.field_shape`: what a total-field residual sees) about its mean over windows of
    ``scale_samples`` real samples is all the noise a residual sees over that time (white, flicker, an offset that
    wanders, a filter's correlation); less the white noise of the second differences ``white_nT^2``, what is left
    is the slow part (the Allan variance's companion at that scale). The magnitude, not the axes, so that a slow
    turn of a sensor that was not quite still (it stays on the ellipsoid) does not pass for noise. Counted when
    clearly above its standard error (three times ``white_nT^2 sqrt(2 / dof)``), else 0; NaN when the stretches are
    too short to measure it.

    Parameters
    ----------
    y : numpy.ndarray, shape (N, 3)
        One sensor's readings, nT.
    stretches : list of tuple
        Still stretches ``(start, stop)``.
    fresh : numpy.ndarray of bool, shape (N,)
        The real samples (:func:`fresh_samples`).
    white_nT : float
        The white noise per axis (nT) from the second differences.
    scale_samples : float or None
        The window, in samples (:func:`_turn_scale_samples`).
    """
    if not scale_samples or not np.isfinite(white_nT):
        return float("nan")
    m = int(max(round(scale_samples), 3))
    shape = field_shape(y)
    variance, dof = _window_variance(row_norm((y - shape.centre_nT) @ shape.cinv.T), stretches, fresh, m)
    if dof < WINDOW_MIN_DOF or not np.isfinite(variance):
        return float("nan")
    excess = variance - white_nT**2
    return float(np.sqrt(excess)) if excess > 3.0 * white_nT**2 * np.sqrt(2.0 / dof) else 0.0


def _turn_scale_samples(y, fresh, stretches) -> float | None:
    """The samples the record takes to turn its field direction through one radian while it moves (the median
    angle between consecutive real samples outside the still stretches, about the readings' centre), at most half
    the longest still stretch; None when it cannot be told."""
    longest = max((b - a for a, b in stretches), default=0)
    if longest < 4:
        return None
    moving = fresh.copy()
    for a, b in stretches:
        moving[a:b] = False
    x = y[moving]
    if len(x) < 10:
        return 0.5 * longest
    u = x - field_shape(x).centre_nT
    u /= np.maximum(row_norm(u), 1e-300)[:, None]
    step = float(np.median(np.arccos(np.clip(np.sum(u[1:] * u[:-1], axis=1), -1.0, 1.0))))
    return float(min(1.0 / step if step > 0 else np.inf, 0.5 * longest))


#: Below this :func:`smoothing_ratio` the readings are taken as smoothed or filtered (white noise gives 1).
SMOOTHED_RATIO = 0.5


def smoothing_ratio(r, fresh=None) -> float:
    """How white a residual series is at the sampling rate: the noise variance its 3rd differences give over the
    one its 2nd differences give (:func:`_difference_variance`, each normalised for white noise).

    About 1 for white noise (a slow misfit leaks into neither); well below 1 when the readings were smoothed or
    low-pass filtered (their differences are correlated, the spectrum falls off towards the Nyquist frequency):
    0.04 for a 4th-order Butterworth at a tenth of the Nyquist frequency. NaN for too short a series.
    """
    r = np.asarray(r, dtype=float)
    keep = np.isfinite(r) if fresh is None else np.isfinite(r) & fresh
    v2, v3 = _difference_variance(r[keep], 2), _difference_variance(r[keep], 3)
    return float(v3 / v2) if np.isfinite(v2) and np.isfinite(v3) and v2 > 0 else float("nan")


def _difference_sigma(r, fresh):
    """Noise sigma (nT) of one residual series from its differences, stale samples dropped: the smallest of the
    :data:`DIFFERENCE_ORDERS` estimates, with the number of samples used."""
    keep = np.isfinite(r) & fresh
    x = r[keep]
    variances = [_difference_variance(x, k) for k in DIFFERENCE_ORDERS]
    variances = [v for v in variances if np.isfinite(v)]
    return (float(np.sqrt(min(variances))) if variances else float("nan")), int(x.size)


#: What :func:`estimate_noise` learns from the readings alone (still stretches, quantization floors, fresh samples),
#: kept for the last few records: a diagnosis estimates the noise of one record several times (before and after each
#: effect it adds), and these do not change with the residuals. Valid for the same readings with the same time
#: stamps (a dataset replaced with other metadata has a new time array of the same values).
_READINGS_FACTS = ReadingsCache(4)


@dataclass
class _Facts:
    """What :func:`estimate_noise` learns from a record's readings alone (per sensor)."""

    still_nT: np.ndarray
    scatter_nT: np.ndarray
    still_samples: np.ndarray
    floors: list
    fresh: list
    low_nT: np.ndarray
    low_scale_s: float | None
    left_out: dict


def _readings_facts(dataset) -> _Facts:
    """The still stretches' figures, quantization floors, real-sample masks and low-frequency noise of the
    dataset's readings (:class:`_Facts`), computed once per record (:data:`_READINGS_FACTS`)."""
    readings, time_s = dataset.readings_nT, dataset.time_s

    def compute():
        steps = [quantization_steps_nT(y) for y in readings]
        still_nT, scatter_nT, still_samples, low_nT, scale_s = still_noise_nT(dataset, steps, low_frequency=True)
        floors = [quantization_floor_nT(y, q) for y, q in zip(readings, steps)]
        fresh = [fresh_samples(y, q) for y, q in zip(readings, steps)]
        counts = [_left_out(y, f) for y, f in zip(readings, fresh)]
        left = {kind: max(c[kind] for c in counts) for kind in ("repeated", "interpolated")}
        return time_s, _Facts(still_nT, scatter_nT, still_samples, floors, fresh, low_nT, scale_s, left)

    def same_time(value):
        cached = value[0]
        return cached is time_s or (cached is not None and time_s is not None and np.array_equal(cached, time_s))

    return _READINGS_FACTS.get(readings, ("noise facts",), compute, valid=same_time)[1]


#: Readings (samples x sensors) from which :func:`prefetch_readings_facts` starts the work on another thread.
PREFETCH_FROM_READINGS = 20_000
_PREFETCH: list = []


def prefetch_readings_facts(dataset):
    """Start :func:`estimate_noise`'s readings-only work (still stretches, quantization) for ``dataset`` on a
    background thread, while the caller fits (:func:`magcal.fitting.pipeline.calibrate` does; the fit's passes use one
    core). Returns a function that waits for it (its failure is left for :func:`estimate_noise` to meet again), or
    one that returns at once for a small record."""
    if dataset.n_samples * dataset.n_sensors < PREFETCH_FROM_READINGS:
        return lambda: None
    if not _PREFETCH:
        from concurrent.futures import ThreadPoolExecutor

        _PREFETCH.append(ThreadPoolExecutor(max_workers=1, thread_name_prefix="magcal-noise"))
    future = _PREFETCH[0].submit(_readings_facts, dataset)

    def wait():
        try:
            future.result()
        except Exception:
            pass

    return wait


def estimate_noise(dataset, residuals_nT, n_params=9, ordered=None, noise_nT=None) -> NoiseEstimate:
    """Noise level: the declared one, else estimated from the residuals' differences (smooth trajectories), the
    still stretches' scatter or the residual RMS, never below the quantization floor.

    Parameters
    ----------
    dataset : magcal.data.dataset.Dataset
        The fitted samples (its ``noise_nT``, if declared, is used unless ``noise_nT`` is given; its readings give
        the stale samples, the quantization step and the still stretches).
    residuals_nT : numpy.ndarray, shape (n_sensors, N)
        Total-field residuals in time order (nT; NaN for samples left out).
    n_params : int
        Parameters of the fit, all sensors together (for the residual-RMS fallback's degrees of freedom).
    ordered : bool, optional
        Whether the samples follow a smooth trajectory (default :func:`is_smooth_sequence`).
    noise_nT : float, optional
        Noise per axis (nT) declared by the user; takes precedence over the dataset's and over any estimate.

    Returns
    -------
    NoiseEstimate
        ``source`` says which method gave it (:data:`NOISE_SOURCES`).

    Raises
    ------
    MagcalError
        A declared noise that is not a positive finite number.
    """

    r = np.asarray(residuals_nT, dtype=float)
    ns = r.shape[0]
    facts = _readings_facts(dataset)
    still_nT, scatter_nT, still_samples, floors, fresh = (
        facts.still_nT,
        facts.scatter_nT,
        facts.still_samples,
        facts.floors,
        facts.fresh,
    )
    static = None if np.all(np.isnan(still_nT)) else still_nT
    scatter = None if np.all(np.isnan(scatter_nT)) else scatter_nT
    q_floor = None if all(f is None for f in floors) else np.array([f or 0.0 for f in floors])
    declared, where = noise_nT, "given by the user"
    if declared is None and dataset.noise_nT:
        declared, where = dataset.noise_nT, "declared with the data (noise_nT)"
    if declared is not None:
        sigma = float(declared)
        if not (np.isfinite(sigma) and sigma > 0):
            raise MagcalError(f"the noise must be a positive number of nT, got {declared!r}")
        return NoiseEstimate(sigma, np.full(ns, sigma), "given", 0.0, where, scatter, q_floor, static)
    ordered = is_smooth_sequence(dataset) if ordered is None else ordered
    note = ""
    smoothing = [smoothing_ratio(r[s], fresh[s]) for s in range(ns)] if ordered else []
    smoothed = [x for x in smoothing if np.isfinite(x) and x < SMOOTHED_RATIO]
    if smoothed:
        # smoothed or filtered readings: their differences are correlated, so neither the differences nor a still
        # stretch measure the sensor's noise; no floor is claimed
        n = np.isfinite(r).sum(axis=1)
        per = np.sqrt(np.nansum(r**2, axis=1) / np.maximum(n - n_params / ns, 1))
        note = (
            f"the readings are smoothed or filtered (their residuals' 3rd differences carry {min(smoothed):.2g} "
            "of the variance that white noise would give them): the sensor's noise, hence the floor, is unknown; "
            "the residual RMS stands in for it, so only structure (not size) can reveal a misfit; give the "
            "sensor's noise if it is known (--noise NT)"
        )
        return NoiseEstimate(
            float(np.sqrt(np.mean(per**2))),
            per,
            "residuals",
            float(np.sqrt(2.0 / max(n.min(), 1))),
            note,
            scatter,
            q_floor,
            static,
        )
    if static is not None and np.all(np.isfinite(static)) and still_samples.min() >= MIN_STATIC_SAMPLES:
        per, source = static.copy(), "static"
        rel_error = _difference_variance_error(int(still_samples.min()), 2)
        note = (
            f"measured in the still stretches ({int(still_samples.min())}+ samples per sensor), free of any "
            "misfit of the model"
        )
        if ordered:
            moving = np.array([_difference_sigma(r[s], fresh[s])[0] for s in range(ns)])
            note += "; the residuals' differences give " + _values(moving) + " nT"
    elif ordered:
        per, counts = [], []
        for s in range(ns):
            sig, m = _difference_sigma(r[s], fresh[s])
            per.append(sig)
            counts.append(m)
        per, source = np.array(per), "differences"
        if facts.left_out["repeated"]:
            note = f"{facts.left_out['repeated']} stale sample(s) (exact repeats of the previous reading)"
        if facts.left_out["interpolated"]:
            note += (" and " if note else "") + (
                f"{facts.left_out['interpolated']} interpolated sample(s) (on the line between their neighbours: an "
                "upsampled stream)"
            )
        if note:
            note += " left out of the differences"
        rel_error = _difference_variance_error(min(counts), min(DIFFERENCE_ORDERS))
    else:
        n = np.isfinite(r).sum(axis=1)
        per = np.sqrt(np.nansum(r**2, axis=1) / np.maximum(n - n_params / ns, 1))
        source, rel_error = "residuals", float(np.sqrt(2.0 / max(n.min(), 1)))
        note = (
            "no smooth time order, no still stretch and no declared noise: the noise is taken from the "
            "residual RMS, so only structure (not size) can reveal a misfit; give it (--noise NT)"
        )
    slow = None
    if source in ("static", "differences") and np.any(np.nan_to_num(facts.low_nT) > 0):
        slow = np.nan_to_num(facts.low_nT)
        per = np.sqrt(per**2 + slow**2)
        note = (note + "; " if note else "") + (
            f"low-frequency noise of {_values(slow)} nT (the still stretches' variance within "
            f"{facts.low_scale_s:.3g} s, the time the record takes to turn through a radian, less the white noise) "
            "added in quadrature"
        )
    if q_floor is not None and np.any(per < q_floor):
        low = per < q_floor
        per = np.where(low, q_floor, per)
        if np.all(low):
            source = "quantization"
        note = (note + "; " if note else "") + (
            f"the estimate fell below the quantization floor q/sqrt(12) ({np.max(q_floor):.3g} nT) and is held at it"
        )
    return NoiseEstimate(
        float(np.sqrt(np.mean(per**2))),
        per,
        source,
        rel_error,
        note,
        scatter,
        q_floor,
        static,
        slow,
        facts.low_scale_s if slow is not None else None,
        dict(facts.left_out),
    )
