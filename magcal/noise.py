"""The noise of a recording: robust spread and the noise floor a fit is judged against.

:func:`robust_sigma` is the one robust standard deviation of magcal (fit, outlier rejection, robust starts,
diagnosis): the median absolute deviation about the median, scaled by 1.4826 so that it equals the standard
deviation for Gaussian noise, and insensitive to the few gross outliers that real recordings have.

:func:`estimate_noise` gives the per-axis noise level (nT) a fit's residuals are judged against
(:class:`NoiseEstimate`), independently of the model's misfit. Along a smooth trajectory a missing effect
changes slowly from sample to sample while the noise does not, so the noise is estimated from the second
differences of the residuals in time order (``var(d2 r) = 6 sigma^2`` for white noise), with gross jumps clipped.
When the samples are not in a smooth order (random attitudes, :func:`is_smooth_sequence`), the dataset's declared
``noise_nT`` is used, and failing that the residual RMS itself (then a misfit cannot be told from noise by its
size, only by its structure).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import comb

#: MAD -> standard deviation for Gaussian data: 1 / Phi^-1(3/4).
MAD_TO_SIGMA = 1.4826


def robust_sigma(values, axis=None, keepdims=False, floor=0.0):
    """Normal-consistent median absolute deviation about the median.

    Parameters
    ----------
    values : array_like
        Samples (any unit; the result has the same unit, e.g. nT).
    axis : int or None
        Axis along which to take it; None uses every value.
    keepdims : bool
        Keep the reduced axis (for broadcasting against ``values``).
    floor : float
        Smallest value returned (avoids dividing by zero when most values are equal, as for stale samples).

    Returns
    -------
    float or numpy.ndarray
        ``1.4826 * median(|x - median(x)|)``, at least ``floor``.

    Examples
    --------
    >>> round(robust_sigma(np.random.default_rng(0).normal(0.0, 3.0, 100_000)), 1)
    3.0
    >>> float(robust_sigma([0.0, 0.0, 0.0, 1e6], floor=1e-9))  # one outlier among equal values
    1e-09
    """
    x = np.asarray(values, dtype=float)
    if axis is None:
        x = x.ravel()
        out = MAD_TO_SIGMA * float(np.median(np.abs(x - np.median(x))))
        return max(out, floor)
    med = np.median(x, axis=axis, keepdims=True)
    out = MAD_TO_SIGMA * np.median(np.abs(x - med), axis=axis, keepdims=keepdims)
    return np.maximum(out, floor)


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
        ``"differences"`` (second differences of the residuals along a smooth trajectory), ``"dataset"``
        (declared ``noise_nT``) or ``"residuals"`` (residual RMS; cannot tell misfit from noise by size).
    relative_variance_error : float
        Relative standard error of ``sigma^2`` per sensor (dimensionless, for the excess test).
    note : str
        Why a fallback source was used (empty for ``"differences"``).
    """

    sigma_nT: float
    per_sensor_nT: np.ndarray
    source: str
    relative_variance_error: float
    note: str = ""


def is_smooth_sequence(dataset) -> bool:
    """True if consecutive samples are close in attitude (a smooth trajectory in time order).

    Compares the typical step between consecutive raw readings of the first sensor with their spread: about 1.4
    for independent random attitudes, a few percent for a sensor turned continuously and sampled at several Hz.

    Parameters
    ----------
    dataset : magcal.dataset.Dataset
        The recording; its ``readings_nT`` (n_sensors, N, 3) in nT.

    Returns
    -------
    bool
        True when the median step is below a quarter of the spread; False for fewer than 20 samples.
    """
    y = dataset.readings_nT[0]
    if len(y) < 20:
        return False
    step = np.median(np.linalg.norm(np.diff(y, axis=0), axis=1))
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
    med, mad = np.median(d), robust_sigma(d)
    if mad > 0:
        d = d[np.abs(d - med) < 6.0 * mad]
    return float(np.mean(d**2) / comb(2 * order, order))


def _difference_variance_error(n, order=2):
    """Relative standard error of :func:`_difference_variance` for white Gaussian noise of ``n`` samples.

    The differences are correlated (binomial weights ``C(2k, k + j)``), so the error is larger than the
    ``sqrt(2 / n)`` of independent samples: ``sqrt(70 / 18 / n)`` ~ ``1.97 / sqrt(n)`` for ``k = 2``.
    """
    c = np.array([comb(2 * order, order + k) for k in range(-order, order + 1)], dtype=float)
    return float(np.sqrt(2.0 * np.sum(c**2) / comb(2 * order, order) ** 2 / max(n, 1)))


def estimate_noise(dataset, residuals_nT, n_params=9, ordered=None) -> NoiseEstimate:
    """Noise level from the residuals' second differences (smooth trajectories) or the dataset.

    Parameters
    ----------
    dataset : magcal.dataset.Dataset
        The fitted samples (its ``noise_nT``, if declared, is the fallback for unordered samples).
    residuals_nT : numpy.ndarray, shape (n_sensors, N)
        Total-field residuals in time order (nT; NaN for samples left out).
    n_params : int
        Parameters of the fit, all sensors together (for the residual-RMS fallback's degrees of freedom).
    ordered : bool, optional
        Whether the samples follow a smooth trajectory (default :func:`is_smooth_sequence`).

    Returns
    -------
    NoiseEstimate
        ``source`` says which estimate was used: ``"differences"``, ``"dataset"`` or ``"residuals"``.
    """
    r = np.asarray(residuals_nT, dtype=float)
    ns = r.shape[0]
    ordered = is_smooth_sequence(dataset) if ordered is None else ordered
    if ordered:
        per = np.array([np.sqrt(_difference_variance(row[np.isfinite(row)])) for row in r])
        n = int(np.isfinite(r[0]).sum())
        return NoiseEstimate(float(np.sqrt(np.mean(per**2))), per, "differences", _difference_variance_error(n))
    if dataset.noise_nT:
        sigma = float(dataset.noise_nT)
        return NoiseEstimate(sigma, np.full(ns, sigma), "dataset", 0.0,
                             "declared noise_nT (samples not in a smooth time order)")
    n = np.isfinite(r).sum(axis=1)
    per = np.sqrt(np.nansum(r**2, axis=1) / np.maximum(n - n_params / ns, 1))
    return NoiseEstimate(float(np.sqrt(np.mean(per**2))), per, "residuals", float(np.sqrt(2.0 / max(n.min(), 1))),
                         "no smooth time order and no declared noise: the noise is taken from the residual RMS, "
                         "so only structure (not size) can reveal a misfit")
