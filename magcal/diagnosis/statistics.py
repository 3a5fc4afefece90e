"""Statistics of one residual series, used by the diagnosis to find structure the model leaves.

In time order: :func:`durbin_watson`, :func:`autocorrelation`, the Ljung-Box whiteness test :func:`ljung_box`, the
CUSUM change-point scan :func:`cusum_test` and the periodogram with Fisher's g-test :func:`spectrum`. Over the
field direction: real orthonormal spherical harmonics :func:`real_sph_harm` and the least-squares expansion with
an F-test per degree :func:`sh_analysis` (degree up to :data:`SH_DEGREE`). Residuals are in nT, times in s.
"""

from __future__ import annotations

import numpy as np
from scipy import stats
from scipy.signal import periodogram
from scipy.special import sph_harm_y

#: Highest spherical-harmonic degree of the direction analysis.
SH_DEGREE = 6

#: The direction analysis uses at most this many samples (evenly spread) per sensor.
SH_MAX_SAMPLES = 6_000


def durbin_watson(r) -> float:
    """Durbin-Watson statistic ``sum (r_i - r_{i-1})^2 / sum r_i^2`` (2 for white noise, < 2 for a trend)."""
    r = np.asarray(r, dtype=float)
    r = r - r.mean()
    return float(np.sum(np.diff(r) ** 2) / max(np.sum(r**2), 1e-300))


def autocorrelation(r, lags) -> np.ndarray:
    """Sample autocorrelation at lags ``1..lags``."""
    r = np.asarray(r, dtype=float)
    r = r - r.mean()
    n = len(r)
    denom = max(float(r @ r), 1e-300)
    return np.array([float(r[:-k] @ r[k:]) / denom for k in range(1, lags + 1)]) if n > lags else np.zeros(lags)


def ljung_box(r, lags=20):
    """Ljung-Box test of whiteness.

    Returns
    -------
    q : float
        ``N (N+2) sum rho_k^2 / (N - k)``.
    p : float
        Chi-square p-value with ``lags`` degrees of freedom.
    fraction : float
        ``sum rho_k^2``: roughly the share of the variance predictable from the past (effect size).
    """
    r = np.asarray(r, dtype=float)
    n = len(r)
    lags = int(max(1, min(lags, n // 5)))
    rho = autocorrelation(r, lags)
    q = n * (n + 2) * np.sum(rho**2 / (n - np.arange(1, lags + 1)))
    return float(q), float(stats.chi2.sf(q, lags)), float(np.sum(rho**2))


def cusum_test(r):
    """CUSUM change-point scan of the mean of ``r``.

    Returns
    -------
    index : int
        Sample after the most likely change of the mean.
    statistic : float
        ``max_k |S_k| / (s sqrt(N))`` with ``S_k`` the cumulative sum of ``r - mean``.
    p : float
        Kolmogorov (Brownian-bridge) p-value; valid for white residuals.
    """
    r = np.asarray(r, dtype=float)
    n = len(r)
    s = np.cumsum(r - r.mean())
    sd = max(float(np.std(r)), 1e-300)
    k = int(np.argmax(np.abs(s[:-1]))) + 1 if n > 1 else 0
    stat = float(np.max(np.abs(s)) / (sd * np.sqrt(n)))
    return k, stat, float(stats.kstwobign.sf(stat))


def spectrum(r, time_s=None):
    """Periodogram of ``r`` and Fisher's g-test for one dominant periodic component.

    Returns
    -------
    dict
        ``freq_hz``, ``power`` (arrays, without the zero frequency), ``peak_hz``, ``peak_fraction`` (share of
        the variance in the three bins around the peak), ``amplitude_nT`` (of a sinusoid carrying it) and ``p``
        (Fisher's g-test p-value).
    """
    r = np.asarray(r, dtype=float)
    r = r - r.mean()
    n = len(r)
    fs = 1.0
    if time_s is not None and n > 2:
        dt = float(np.median(np.diff(time_s)))
        fs = 1.0 / dt if dt > 0 else 1.0
    freq, power = periodogram(r, fs=fs, detrend=False)
    freq, power = freq[1:], power[1:]
    if len(power) < 3 or power.sum() <= 0:
        return {"freq_hz": freq, "power": power, "peak_hz": float("nan"), "peak_fraction": 0.0,
                "amplitude_nT": 0.0, "p": 1.0}
    i = int(np.argmax(power))
    g = float(power[i] / power.sum())
    nf = len(power)
    # Fisher's exact g-test, first term (accurate for small p)
    p = float(min(1.0, nf * (1.0 - g) ** (nf - 1)))
    lo, hi = max(0, i - 1), min(nf, i + 2)
    frac = float(power[lo:hi].sum() / power.sum())
    var = float(np.mean(r**2))
    return {"freq_hz": freq, "power": power, "peak_hz": float(freq[i]), "peak_fraction": frac,
            "amplitude_nT": float(np.sqrt(2 * frac * var)), "p": p}


def real_sph_harm(u, lmax=SH_DEGREE) -> np.ndarray:
    """Real orthonormal spherical harmonics of unit vectors.

    Parameters
    ----------
    u : numpy.ndarray, shape (N, 3)
        Unit vectors (directions).
    lmax : int
        Highest degree.

    Returns
    -------
    numpy.ndarray, shape (N, (lmax + 1)^2)
        Columns ordered by degree ``l`` then order ``m = -l..l``; each has mean square ``1/(4 pi)`` over the
        sphere.
    """
    u = np.asarray(u, dtype=float)
    theta = np.arccos(np.clip(u[:, 2], -1.0, 1.0))
    phi = np.arctan2(u[:, 1], u[:, 0])
    cols = []
    for degree in range(lmax + 1):
        for order in range(-degree, degree + 1):
            y = sph_harm_y(degree, abs(order), theta, phi)
            if order > 0:
                cols.append(np.sqrt(2.0) * (-1) ** order * y.real)
            elif order < 0:
                cols.append(np.sqrt(2.0) * (-1) ** order * y.imag)
            else:
                cols.append(y.real)
    return np.column_stack(cols)


def sh_analysis(u, r, lmax=SH_DEGREE, grid=(19, 37), max_samples=None):
    """Least-squares real spherical-harmonic expansion of ``r(u)`` and the evidence per degree.

    Returns
    -------
    dict
        ``degree`` (0..lmax), ``rms_nT`` (RMS over the sphere of each degree's part), ``F``, ``p`` (F-test of each
        degree against the full expansion), ``coverage_rank`` (numerical rank of the design), and ``map``: the
        fitted function of degrees 3 and above on a latitude/longitude grid (``lat_deg``, ``lon_deg``,
        ``value_nT``) for plotting.
    """
    u = np.asarray(u, dtype=float)
    r = np.asarray(r, dtype=float)
    if max_samples is not None and len(r) > max_samples:  # an even subsample keeps the analysis fast
        pick = np.linspace(0, len(r) - 1, int(max_samples)).astype(int)
        u, r = u[pick], r[pick]
    y = real_sph_harm(u, lmax)
    n, p = y.shape
    gram = y.T @ y
    scale = np.sqrt(np.maximum(np.diag(gram), 1e-300))
    g_s = gram / np.outer(scale, scale)
    w, v = np.linalg.eigh(g_s)
    keep = w > 1e-8 * w.max()
    inv = (v[:, keep] / w[keep]) @ v[:, keep].T / np.outer(scale, scale)
    coef = inv @ (y.T @ r)
    rss = float(np.sum((r - y @ coef) ** 2))
    dof = max(n - int(keep.sum()), 1)
    s2 = rss / dof
    degrees, rms, fstat, pval = [], [], [], []
    for degree in range(lmax + 1):
        idx = np.arange(degree**2, (degree + 1) ** 2)
        c = coef[idx]
        sub = inv[np.ix_(idx, idx)]
        try:
            drss = float(c @ np.linalg.solve(sub, c))
        except np.linalg.LinAlgError:
            drss = float("nan")
        f = drss / len(idx) / s2 if s2 > 0 else float("nan")
        degrees.append(degree)
        rms.append(float(np.sqrt(np.sum(c**2) / (4 * np.pi))))
        fstat.append(f)
        pval.append(float(stats.f.sf(f, len(idx), dof)) if np.isfinite(f) else float("nan"))
    lat = np.linspace(-90, 90, grid[0])
    lon = np.linspace(-180, 180, grid[1])
    la, lo = np.meshgrid(np.radians(lat), np.radians(lon), indexing="ij")
    g = np.column_stack([(np.cos(la) * np.cos(lo)).ravel(), (np.cos(la) * np.sin(lo)).ravel(), np.sin(la).ravel()])
    high = coef.copy()
    high[:9] = 0.0
    values = (real_sph_harm(g, lmax) @ high).reshape(la.shape)
    return {"degree": np.array(degrees), "rms_nT": np.array(rms), "F": np.array(fstat), "p": np.array(pval),
            "coverage_rank": int(keep.sum()), "n_functions": p,
            "map": {"lat_deg": lat, "lon_deg": lon, "value_nT": values}}
