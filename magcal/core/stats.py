"""Robust statistics of a sample, shared by every stage (the one MAD helper)."""

from __future__ import annotations

import numpy as np

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


def savgol(values, window: int, deriv: int = 0, step: float = 1.0, order: int = 3) -> np.ndarray:
    """A Savitzky-Golay filter along axis 0: the least-squares polynomial over ``window`` samples, or its first
    derivative.

    The same values as ``scipy.signal.savgol_filter(values, window, order, deriv=deriv, delta=step, axis=0,
    mode="interp")``: inside, the fitted polynomial (or its derivative) at the centre of each window; in the first
    and last ``window // 2`` samples, the polynomial fitted to the first or last window. Written with numpy alone so
    that the model layer does not load ``scipy.signal`` (half a second of every command's start).

    Parameters
    ----------
    values : array_like, shape (N, ...)
        Samples on a regular grid (any unit).
    window : int
        Odd number of samples, at most N and more than ``order``.
    deriv : {0, 1}
        0 for the smoothed values, 1 for the first derivative.
    step : float
        Sample spacing (e.g. s): a derivative is in units of ``values`` per unit of ``step``.
    order : int
        Polynomial order.

    Returns
    -------
    numpy.ndarray
        Same shape as ``values``.
    """
    y = np.asarray(values, dtype=float)
    n, half = y.shape[0], window // 2
    if window % 2 != 1 or window <= order or window > n:
        raise ValueError(f"savgol: window {window} must be odd, above order {order} and at most {n}")
    if deriv not in (0, 1):
        raise ValueError(f"savgol: deriv must be 0 or 1, got {deriv}")
    x = np.arange(-half, half + 1, dtype=float)
    fit = np.linalg.pinv(np.vander(x, order + 1, increasing=True))  # (order + 1, window): samples -> coefficients
    flat = y.reshape(n, -1)
    out = np.empty_like(flat)
    windows = np.lib.stride_tricks.sliding_window_view(flat, window, axis=0)  # (n - window + 1, m, window)
    out[half : n - half] = windows @ fit[deriv]
    powers = np.arange(order + 1)

    def at_offsets(rows, at):  # the polynomial fitted to ``rows`` (or its derivative) at the offsets ``at``
        coefficients = fit @ flat[rows]  # (order + 1, m)
        if deriv == 0:
            return (at[:, None] ** powers) @ coefficients
        return (powers[1:] * at[:, None] ** (powers[1:] - 1)) @ coefficients[1:]

    out[:half] = at_offsets(slice(0, window), x[:half])
    out[n - half :] = at_offsets(slice(n - window, n), x[half + 1 :])
    return (out / step**deriv).reshape(y.shape)


def savgol_derivative(values, window: int, step: float, order: int = 3) -> np.ndarray:
    """First derivative along axis 0 by a Savitzky-Golay filter: :func:`savgol` with ``deriv=1``."""
    return savgol(values, window, deriv=1, step=step, order=order)


def moving_mean(values, window: int) -> np.ndarray:
    """The mean of the ``window`` samples around each sample, along the last axis, by running sums (O(N)).

    Sample ``i``'s window is ``[i - window // 2, i + (window - 1) // 2]`` (``numpy.convolve(values, ones(window) /
    window, mode="same")``'s away from the ends), cut at the ends: there the mean is over the samples the window
    still holds (no zero padding pulls it towards zero).

    Parameters
    ----------
    values : array_like, shape (..., N)
        Samples in order (any unit).
    window : int
        Samples per window, at least 1.

    Returns
    -------
    numpy.ndarray
        Same shape as ``values``.
    """
    y = np.asarray(values, dtype=float)
    if window < 1:
        raise ValueError(f"moving_mean: window must be at least 1, got {window}")
    n = y.shape[-1]
    sums = np.concatenate([np.zeros(y.shape[:-1] + (1,)), np.cumsum(y, axis=-1)], axis=-1)
    i = np.arange(n)
    lo = np.clip(i - window // 2, 0, n)
    hi = np.clip(i + (window - 1) // 2 + 1, 0, n)
    return (sums[..., hi] - sums[..., lo]) / (hi - lo)


def lag1_correlation(*streams) -> float:
    """The largest lag-1 correlation, clipped to [0, 0.9999], of residual sequences in record order: each stream an
    (N,) or (N, k) array, a column one sequence (0 for a sequence too short or constant). A fit's standard deviations
    are widened by ``sqrt((1 + r) / (1 - r))`` for it: correlated residuals hold fewer independent samples."""
    best = 0.0
    for stream in streams:
        a = np.asarray(stream, dtype=float).reshape(len(stream), -1)
        a = a - a.mean(axis=0)
        den = np.sum(a * a, axis=0)
        ok = den > 0
        if a.shape[0] > 2 and ok.any():
            best = max(best, float(np.max(np.sum(a[1:] * a[:-1], axis=0)[ok] / den[ok])))
    return float(np.clip(best, 0.0, 0.9999))


def explained_share(values, regressors) -> float:
    """The share of the variance of ``values`` that a least-squares fit of ``regressors`` (plus a constant)
    explains: R^2 in [0, 1] (0 for fewer samples than columns, or a constant series).

    Parameters
    ----------
    values : array_like, shape (N,) or (N, k)
        The series (any unit); the columns of a 2-D array are explained together (their variances summed).
    regressors : array_like, shape (N, m)
        What they may follow (a smooth basis of time, positions...).
    """
    y = np.asarray(values, dtype=float).reshape(len(values), -1)
    X = np.column_stack([np.ones(len(y)), np.asarray(regressors, dtype=float).reshape(len(y), -1)])
    y = y - y.mean(axis=0)
    tss = float(np.sum(y * y))
    if len(y) <= X.shape[1] or tss <= 0:
        return 0.0
    coef, *_ = np.linalg.lstsq(X, y, rcond=None)
    fit = X @ coef
    return float(np.clip(np.sum(fit * fit) / tss, 0.0, 1.0))


def smooth_in_time(time_s, n_terms=None) -> np.ndarray:
    """A smooth basis of time: the cosines ``cos(pi k x)``, ``k = 1..K``, of the time scaled to ``x`` in [0, 1]
    (N, K); ``K = min(20, N // 10)`` by default (at least 1). A white series keeps about ``K / N`` of its variance
    on it, one that wanders over the record most of it (:func:`explained_share`).

    Parameters
    ----------
    time_s : array_like, shape (N,)
        Sample times (s) or indices, in record order.
    n_terms : int, optional
        ``K``.

    Examples
    --------
    >>> t = np.linspace(0.0, 60.0, 600)
    >>> round(explained_share(np.sin(t / 10.0), smooth_in_time(t)), 3)
    1.0
    >>> explained_share(np.random.default_rng(0).normal(size=600), smooth_in_time(t)) < 0.1
    True
    """
    t = np.asarray(time_s, dtype=float)
    k = int(n_terms) if n_terms is not None else max(1, min(20, len(t) // 10))
    x = (t - t.min()) / max(float(np.ptp(t)), 1e-12)
    return np.cos(np.pi * np.outer(x, np.arange(1, k + 1)))
