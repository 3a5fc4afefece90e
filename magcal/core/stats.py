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
