"""Statistics of one residual series, used by the diagnosis to find structure the model leaves.

In time order: :func:`durbin_watson`, :func:`autocorrelation`, the Ljung-Box whiteness test :func:`ljung_box`, the
CUSUM change-point scan :func:`cusum_test` and the periodogram with Fisher's g-test :func:`spectrum` (Lomb-Scargle
on irregular stamps). Over the
field direction: real orthonormal spherical harmonics :func:`real_sph_harm` and the least-squares expansion with
an F-test per degree :func:`sh_analysis` (degree up to :data:`SH_DEGREE`). Both at once: samples that revisit one
field direction at other times, :func:`revisit_forms`, tell a field that changes from an offset that wanders.
Residuals are in nT, times in s.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import scipy.fft
from scipy import stats
from scipy.special import sph_harm_y

#: Stamps deviating from a uniform grid by more than this fraction of the mean interval are irregular: the
#: spectrum is then the Lomb-Scargle periodogram.
IRREGULAR_DEVIATION = 0.5

#: Highest spherical-harmonic degree of the direction analysis.
SH_DEGREE = 6

#: A spherical-harmonic degree is resolved by the sample directions when the smallest eigenvalue of the
#: column-normalised Gram matrix of the degrees up to it is at least this (1 for even coverage of the sphere).
SH_MIN_EIGEN = 0.01

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


def irregular_stamps(time_s) -> bool:
    """True when time stamps are too far from a uniform grid for an FFT periodogram.

    The stamps are compared with the straight line through them (sample index against time): a deviation of more
    than :data:`IRREGULAR_DEVIATION` of the mean interval anywhere (gaps, batches of host arrival times, a
    wandering interval) makes them irregular. Repeated or backward stamps do too.
    """
    t = np.asarray(time_s, dtype=float)
    if t.size < 3:
        return False
    dt = np.diff(t)
    if np.any(dt <= 0):
        return True
    i = np.arange(t.size, dtype=float)
    slope, intercept = np.polyfit(i, t, 1)
    return bool(np.max(np.abs(t - (intercept + slope * i))) > IRREGULAR_DEVIATION * slope)


#: Stamps lie on a regular grid with holes (:func:`stamp_grid`) when each is within this fraction of the grid's step
#: of its grid point (stamps written with a few digits: 75 Hz in whole milliseconds are within 0.04). The
#: Lomb-Scargle sums are then transforms of that grid; how far a stamp is from its point is corrected exactly
#: (:func:`_lomb_scargle_terms`), so this decides only which grid is used, not the values.
GRID_TOLERANCE = 0.25

#: Most grid points per sample :func:`stamp_grid` accepts (a few samples kept from a long record take the finer grid
#: of the frequencies instead of a grid mostly empty).
GRID_MAX_FILL = 64

#: Points per frequency of the grid that any other stamps are placed on (:func:`_lomb_scargle_terms`): the phase a
#: stamp's distance from its grid point adds is then at most ``pi / 4`` at twice the highest frequency.
GRID_PER_FREQUENCY = 8

#: The expansion in a stamp's distance from its grid point stops when its next term is below this (relative to the
#: sums' scale): the values agree with scipy's direct sums to about 1e-13 of the largest power.
EXPANSION_TOLERANCE = 1e-10


def stamp_grid(time_s):
    """Grid indices of stamps that lie on a regular grid with holes (a regular record with samples left out: an
    excluded time range, rejected outliers), or None.

    The step is the record's duration over the whole number of typical intervals it spans (the mean of the intervals
    shorter than 1.5 times the median, else the shortest), so the first and last stamps are grid points exactly;
    every other stamp must be within :data:`GRID_TOLERANCE` of a step of its grid point, one stamp per point, and
    the grid may hold at most :data:`GRID_MAX_FILL` points per stamp.

    Parameters
    ----------
    time_s : array_like, shape (N,)
        Sample times, s, increasing.

    Returns
    -------
    numpy.ndarray of int64, shape (N,), or None
        ``m`` with ``time_s ~= time_s[0] + m * (time_s[-1] - time_s[0]) / m[-1]``, ``m[0] = 0``; None when the
        stamps are not increasing, fewer than 3, or not on such a grid (jitter, batches of host arrival times).
    """
    t = np.asarray(time_s, dtype=float)
    if t.size < 3:
        return None
    dt = np.diff(t)
    if not np.all(dt > 0):
        return None
    duration = float(t[-1] - t[0])
    typical = dt[dt < 1.5 * float(np.median(dt))]
    for interval in (float(typical.mean()) if typical.size else float(dt.min()), float(dt.min())):
        cells = round(duration / interval)
        if cells < 1 or cells > GRID_MAX_FILL * t.size:
            continue
        step = duration / cells
        m = np.rint((t - t[0]) / step).astype(np.int64)
        if np.max(np.abs((t - t[0]) - m * step)) <= GRID_TOLERANCE * step and np.all(np.diff(m) > 0):
            return m
    return None


def _grid_sums(index, weights, cells):
    """``sum_j weights_j exp(+2 pi i q index_j / cells)`` for ``q = 0..cells-1``: the weights added on a grid of
    ``cells`` points (several on one point add up) and transformed (one FFT, ``O(cells log cells)``)."""
    return np.conj(scipy.fft.fft(np.bincount(index, weights=weights, minlength=cells)))


def _lomb_scargle_terms(t, r, df_hz, n_freq):
    """``sum r exp(i w t)`` and ``sum exp(2 i w t)`` (complex, shape (n_freq,)) at ``w = 2 pi k df_hz``,
    ``k = 1..n_freq``, for increasing ``t`` starting at 0, from transforms of a grid (no sum over every sample and
    frequency).

    The grid has ``L`` points per period ``1 / df_hz``: the stamps' own grid (:func:`stamp_grid`) when it spans a
    whole number of periods (the spectrum's ``k / T``), else :data:`GRID_PER_FREQUENCY` points per frequency. With
    ``m_j`` a stamp's grid point and ``d_j`` its distance from it (s), ``exp(i w t_j) = exp(2 pi i k m_j / L)
    sum_p (i w d_j)^p / p!``: term ``p`` is the transform of ``r d^p`` at index ``k mod L``. Terms are added until
    the next is below :data:`EXPANSION_TOLERANCE`: one or two for stamps on their grid (an excluded range; the second
    for the stamps' rounding in long records), about 8 for stamps rounded to whole milliseconds, 13 for random ones.
    """
    k = np.arange(1, int(n_freq) + 1)
    m = stamp_grid(t)
    periods = round(float(t[-1]) * df_hz) if t.size else 0
    on_grid = (
        m is not None
        and periods >= 1
        and abs(float(t[-1]) * df_hz - periods) <= 1e-9 * periods
        and int(m[-1]) % periods == 0
    )
    if on_grid and m is not None:
        cells = int(m[-1]) // periods
        step = 1.0 / (df_hz * cells)
    else:
        cells = scipy.fft.next_fast_len(GRID_PER_FREQUENCY * k.size)
        step = 1.0 / (df_hz * cells)
        m = np.rint(t / step).astype(np.int64)
    d = t - m * step  # s, at most half a step
    index = m % cells
    w = 2.0 * np.pi * df_hz * k
    largest = 2.0 * float(w[-1]) * float(np.max(np.abs(d)))  # the largest |2 w d|: the expansion's argument
    yz = np.zeros(k.size, dtype=complex)
    z2 = np.zeros(k.size, dtype=complex)
    weights_r, weights_1 = np.array(r, dtype=float), np.ones(t.size)
    factor_r, factor_2 = np.ones(k.size, dtype=complex), np.ones(k.size, dtype=complex)
    p, bound = 0, 1.0
    while True:
        yz += factor_r * _grid_sums(index, weights_r, cells)[k % cells]
        z2 += factor_2 * _grid_sums(index, weights_1, cells)[(2 * k) % cells]
        p += 1
        bound *= largest / p  # largest^p / p!
        if bound <= EXPANSION_TOLERANCE:
            return yz, z2
        factor_r = factor_r * (1j * w) / p
        factor_2 = factor_2 * (2j * w) / p
        weights_r = weights_r * d
        weights_1 = weights_1 * d


def lomb_scargle_grid(time_s, r, df_hz, n_freq) -> np.ndarray:
    """Lomb-Scargle periodogram of ``r`` at the frequencies ``df_hz, 2 df_hz, ... n_freq df_hz``.

    The classical (unnormalised) periodogram of :func:`scipy.signal.lombscargle` (same values to about 1e-13 of the
    largest), computed for a uniform frequency grid from FFTs of the samples placed on a grid
    (:func:`_lomb_scargle_terms`), not from sums over every sample and frequency (``N x n_freq`` products: for 9e4
    samples and half as many frequencies, 145 s on the 2-core development machine under load 4; scipy's own takes
    seconds for 1e4 samples). For 9e4 samples (same machine, load 3-5): 0.013-0.04 s on their regular grid with a
    range excluded, 0.27-0.3 s for stamps rounded to whole milliseconds with a range excluded, 0.4-1.2 s for 1e5
    random stamps.

    Parameters
    ----------
    time_s : array_like, shape (N,)
        Sample times, s (any order; irregular).
    r : array_like, shape (N,)
        Values (e.g. residuals in nT), mean removed by the caller.
    df_hz : float
        Frequency step and first frequency, Hz.
    n_freq : int
        Number of frequencies.

    Returns
    -------
    numpy.ndarray, shape (n_freq,)
        ``0.5 [ (sum r cos w(t - tau))^2 / sum cos^2 w(t - tau) + (sum r sin w(t - tau))^2 / sum sin^2 w(t - tau) ]``
        with ``tan 2 w tau = sum sin 2wt / sum cos 2wt``, nT^2.
    """
    t = np.asarray(time_s, dtype=float)
    r = np.asarray(r, dtype=float)
    order = np.argsort(t, kind="stable")  # the sums do not depend on the order; the grid is found in time order
    t, r = t[order], r[order]
    n = t.size
    if n == 0 or int(n_freq) < 1:
        return np.zeros(max(int(n_freq), 0))
    if not np.all(np.isfinite(t)):  # no grid holds a missing stamp: no value, as the sums over it would give
        return np.full(int(n_freq), np.nan)
    t = t - t[0]
    yz, z2 = _lomb_scargle_terms(t, r, float(df_hz), int(n_freq))
    rot = np.exp(-0.5j * np.angle(z2))
    yc, ys = (yz * rot).real, (yz * rot).imag
    cc = 0.5 * n + 0.5 * np.abs(z2)
    ss = n - cc
    return 0.5 * (yc * yc / np.maximum(cc, 1e-300) + ys * ys / np.maximum(ss, 1e-300))


def fft_periodogram(r, fs: float = 1.0):
    """One-sided power spectral density of ``r`` on a regular grid: ``scipy.signal.periodogram(r, fs,
    detrend=False)`` (a boxcar window, density scaling), written with :mod:`scipy.fft` so that the diagnosis does not
    load ``scipy.signal`` (half a second of every command's start).

    Parameters
    ----------
    r : array_like, shape (N,)
        Samples (unit U).
    fs : float
        Sampling frequency (Hz, or cycles per sample with 1).

    Returns
    -------
    freq : numpy.ndarray, shape (N // 2 + 1,)
        Frequencies in units of ``fs``.
    power : numpy.ndarray, shape (N // 2 + 1,)
        Power spectral density, U**2 per unit of ``fs``.
    """
    x = np.asarray(r, dtype=float)
    n = x.shape[0]
    power = np.abs(scipy.fft.rfft(x)) ** 2 / (fs * n)
    power[1 : (n + 1) // 2] *= 2.0  # one-sided: every frequency but 0 and (for even n) Nyquist twice
    return scipy.fft.rfftfreq(n, 1.0 / fs), power


def spectrum(r, time_s=None):
    """Power spectrum of ``r`` and Fisher's g-test for one dominant periodic component.

    Regular stamps (or none: then frequencies are in cycles per sample) give the FFT periodogram. Irregular
    stamps (:func:`irregular_stamps`: gaps, host arrival times in batches) give the Lomb-Scargle periodogram
    (:func:`scipy.signal.lombscargle`'s values, from FFTs: :func:`lomb_scargle_grid`; a time range excluded from a
    regular record leaves such stamps) at the stamps as they are, on a grid of frequencies ``k / T``
    (``T`` the duration) up to the mean Nyquist frequency ``N / (2 T)``: one independent frequency per bin, as for
    the FFT, so the g-test and the peak's share of the variance mean the same. A uniform periodogram of irregular
    samples puts the peak at the wrong frequency (the median interval is not the sampling interval).

    Returns
    -------
    dict
        ``freq_hz``, ``power`` (arrays, without the zero frequency), ``peak_hz``, ``peak_fraction`` (share of
        the variance in the three bins around the peak), ``amplitude_nT`` (of a sinusoid carrying it), ``p``
        (Fisher's g-test p-value) and ``method`` (``"periodogram"`` or ``"lomb-scargle"``).
    """
    r = np.asarray(r, dtype=float)
    r = r - r.mean()
    n = len(r)
    method = "periodogram"
    if time_s is not None and n > 2 and irregular_stamps(time_s):
        t = np.asarray(time_s, dtype=float)
        duration = float(t.max() - t.min())
        n_freq = max(n // 2, 1)
        freq = np.arange(1, n_freq + 1) / duration if duration > 0 else np.zeros(0)
        power = lomb_scargle_grid(t, r, freq[0], freq.size) if freq.size else np.zeros(0)
        method = "lomb-scargle"
    else:
        fs = 1.0
        if time_s is not None and n > 2:
            dt = float(np.median(np.diff(time_s)))
            fs = 1.0 / dt if dt > 0 else 1.0
        freq, power = fft_periodogram(r, fs)
        freq, power = freq[1:], power[1:]
    if len(power) < 3 or power.sum() <= 0:
        return {
            "freq_hz": freq,
            "power": power,
            "peak_hz": float("nan"),
            "peak_fraction": 0.0,
            "amplitude_nT": 0.0,
            "p": 1.0,
            "method": method,
        }
    i = int(np.argmax(power))
    g = float(power[i] / power.sum())
    nf = len(power)
    # Fisher's exact g-test, first term (accurate for small p)
    p = float(min(1.0, nf * (1.0 - g) ** (nf - 1)))
    lo, hi = max(0, i - 1), min(nf, i + 2)
    frac = float(power[lo:hi].sum() / power.sum())
    var = float(np.mean(r**2))
    return {
        "freq_hz": freq,
        "power": power,
        "peak_hz": float(freq[i]),
        "peak_fraction": frac,
        "amplitude_nT": float(np.sqrt(2 * frac * var)),
        "p": p,
        "method": method,
    }


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
    out = np.empty((len(u), (lmax + 1) ** 2))
    for degree in range(lmax + 1):
        centre = degree * (degree + 1)  # column of order 0
        for order in range(degree + 1):  # the complex harmonic of order |m| gives both real ones
            y = sph_harm_y(degree, order, theta, phi)
            if order == 0:
                out[:, centre] = y.real
            else:
                sign = np.sqrt(2.0) * (-1) ** order
                out[:, centre + order] = sign * y.real
                out[:, centre - order] = sign * y.imag
    return out


@functools.lru_cache(maxsize=4)
def _grid_harmonics(grid, lmax) -> np.ndarray:
    """:func:`real_sph_harm` on the latitude/longitude grid of :func:`sh_analysis`'s map (the same every time)."""
    la, lo = np.meshgrid(
        np.radians(np.linspace(-90, 90, grid[0])), np.radians(np.linspace(-180, 180, grid[1])), indexing="ij"
    )
    g = np.column_stack([(np.cos(la) * np.cos(lo)).ravel(), (np.cos(la) * np.sin(lo)).ravel(), np.sin(la).ravel()])
    out = real_sph_harm(g, lmax)
    out.setflags(write=False)
    return out


def sh_resolved_degrees(y, min_eigen=None) -> np.ndarray:
    """Which spherical-harmonic degrees a set of directions resolves.

    Degree ``l`` is resolved when the smallest eigenvalue of the column-normalised Gram matrix of the harmonics of
    degrees ``0..l`` at the sample directions is at least ``min_eigen`` (:data:`SH_MIN_EIGEN`): even coverage of
    the sphere gives 1 (the harmonics are orthogonal), and ``1 / eigenvalue`` is how much the worst combination's
    variance is inflated. Samples on a few great circles (a drone rolled, pitched and yawed) resolve degrees 0-2
    and no higher: an expansion to degree 6 on them is fitted to noise in the directions not visited. The
    eigenvalue can only fall as degrees are added, so the resolved degrees are ``0..L``.

    Parameters
    ----------
    y : numpy.ndarray, shape (N, (lmax + 1)^2)
        The harmonics at the sample directions (:func:`real_sph_harm`).
    min_eigen : float, optional
        Threshold; default :data:`SH_MIN_EIGEN`.

    Returns
    -------
    numpy.ndarray of bool, shape (lmax + 1,)
    """
    min_eigen = SH_MIN_EIGEN if min_eigen is None else float(min_eigen)
    lmax = int(round(np.sqrt(y.shape[1]))) - 1
    gram = y.T @ y
    scale = np.sqrt(np.maximum(np.diag(gram), 1e-300))
    g_s = gram / np.outer(scale, scale)
    out = np.zeros(lmax + 1, dtype=bool)
    for degree in range(lmax + 1):
        k = (degree + 1) ** 2
        if y.shape[0] <= k or np.linalg.eigvalsh(g_s[:k, :k])[0] < min_eigen:
            break
        out[degree] = True
    return out


#: The calibration's shape (degree 2) is fixed well enough to judge what a term fitted beside it does to it when the
#: worst degree-2 combination's variance is inflated at most ~33x over even coverage (1 / 0.03); :data:`SH_MIN_EIGEN`
#: (100x) only says the degree can be expanded. On the real records tried, a reference drift judged on directions
#: between the two (0.009, 0.011) raised the next half's error (benchmarks/notes/real.md).
SHAPE_JUDGED_MIN_EIGEN = 0.03


def resolves_degree(u, degree, min_eigen=None, max_samples=SH_MAX_SAMPLES) -> bool:
    """Whether the unit directions ``u`` (N, 3) resolve the spherical-harmonic degrees up to ``degree``
    (:func:`sh_resolved_degrees` with ``min_eigen``; an even subsample of at most ``max_samples``)."""
    u = np.asarray(u, dtype=float)
    u = u[np.all(np.isfinite(u), axis=1)]
    if len(u) > max_samples:
        u = u[np.linspace(0, len(u) - 1, int(max_samples)).astype(int)]
    if len(u) < (degree + 1) ** 2:
        return False
    return bool(sh_resolved_degrees(real_sph_harm(u, degree), min_eigen)[degree])


def sh_analysis(u, r, lmax=SH_DEGREE, grid=(19, 37), max_samples=None):
    """Least-squares real spherical-harmonic expansion of ``r(u)`` and the evidence per degree.

    The expansion and its F-tests go to ``lmax`` whatever the coverage (an F-test stays valid on an
    ill-conditioned design; it only loses power). The RMS over the sphere of a degree the directions do not
    resolve (:func:`sh_resolved_degrees`) is withheld (NaN): it would be an extrapolation to directions never
    visited (on three great circles the degree-4 part of a 300 nT residual came out at 5 uT). What the degrees
    3 and above explain at the directions visited is given instead (``high_rms_in_sample_nT``).

    Returns
    -------
    dict
        ``degree`` (0..lmax), ``rms_nT`` (RMS over the sphere of each degree's part; NaN where not resolved),
        ``F``, ``p`` (F-test of each degree against the full expansion), ``resolved`` (bool per degree),
        ``max_resolved_degree`` (-1 if none), ``high_rms_in_sample_nT`` (RMS over the samples of the reduction of
        the residual by degrees 3 and above: ``sqrt((RSS without them - RSS) / N)``), ``coverage_rank``
        (numerical rank of the design), ``n_functions``, and ``map``: the fitted function of the resolved degrees
        3 and above on a latitude/longitude grid (``lat_deg``, ``lon_deg``, ``value_nT``) for plotting.
    """
    u = np.asarray(u, dtype=float)
    r = np.asarray(r, dtype=float)
    if max_samples is not None and len(r) > max_samples:  # an even subsample keeps the analysis fast
        pick = np.linspace(0, len(r) - 1, int(max_samples)).astype(int)
        u, r = u[pick], r[pick]
    y = real_sph_harm(u, lmax)
    n, p = y.shape
    resolved = sh_resolved_degrees(y)
    top = int(np.flatnonzero(resolved)[-1]) if resolved.any() else -1

    def lstsq(design):
        gram = design.T @ design
        scale = np.sqrt(np.maximum(np.diag(gram), 1e-300))
        g_s = gram / np.outer(scale, scale)
        w, v = np.linalg.eigh(g_s)
        keep = w > 1e-8 * w.max()
        inv = (v[:, keep] / w[keep]) @ v[:, keep].T / np.outer(scale, scale)
        return inv @ (design.T @ r), inv, keep

    coef, inv, keep = lstsq(y)
    rss = float(np.sum((r - y @ coef) ** 2))
    dof = max(n - int(keep.sum()), 1)
    s2 = rss / dof
    low_coef, _, _ = lstsq(y[:, :9])
    rss_low = float(np.sum((r - y[:, :9] @ low_coef) ** 2))
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
        rms.append(float(np.sqrt(np.sum(c**2) / (4 * np.pi))) if resolved[degree] else float("nan"))
        fstat.append(f)
        pval.append(float(stats.f.sf(f, len(idx), dof)) if np.isfinite(f) else float("nan"))
    lat = np.linspace(-90, 90, grid[0])
    lon = np.linspace(-180, 180, grid[1])
    high = coef.copy()
    high[:9] = 0.0
    high[(top + 1) ** 2 :] = 0.0  # no map where the coverage does not resolve the pattern
    values = (_grid_harmonics(tuple(grid), lmax) @ high).reshape(len(lat), len(lon))
    return {
        "degree": np.array(degrees),
        "rms_nT": np.array(rms),
        "F": np.array(fstat),
        "p": np.array(pval),
        "resolved": resolved,
        "max_resolved_degree": top,
        "high_rms_in_sample_nT": float(np.sqrt(max(rss_low - rss, 0.0) / max(n, 1))),
        "coverage_rank": int(keep.sum()),
        "n_functions": p,
        "map": {"lat_deg": lat, "lon_deg": lon, "value_nT": values},
    }


#: Samples whose field directions fall in one cell of this size (deg, about) on the sphere revisit one direction.
REVISIT_ANGLE_DEG = 5.0
#: Pairs of visits at least this far apart in time (s) measure how the revisits drift apart (another pass).
REVISIT_APART_S = 1.0
#: At most this many pairs (drawn evenly at random) enter the figures of the drift with time.
REVISIT_MAX_PAIRS = 40_000
#: Significance of each form's part beyond the other's.
REVISIT_ALPHA = 1e-3
#: And its least share of what both forms explain together: a change that one form follows only roughly (a smooth
#: field between the knots of hat functions) leaves a small, significant part to the other form's freedom.
REVISIT_MIN_PART = 0.05
#: The change is faster than the series' knots when the offset form on closer knots explains at least this share of
#: what the offset form on the series' knots leaves (significantly): on simulated hand-held tumbles a magnet fixed
#: in the room, passed at a walking pace, gives 0.74-0.98, a magnet carried with the sensor and moved slowly
#: 0.11-0.29.
REVISIT_FASTER_PART = 0.5
#: The pace test is made when its design (revisited samples x 4 closer series) holds at most this many numbers (160
#: MB): a longer record keeps the answer on the series' knots.
REVISIT_MAX_ELEMENTS = 20_000_000
#: The closer knots of that comparison: this many intervals in each of the series'.
REVISIT_CLOSER_KNOTS = 3


@dataclass
class RevisitForms:
    """What samples revisiting one field direction say of a change in time (:func:`revisit_forms`).

    Visits of one direction ``u`` at different times see the same direction pattern (a misfit of the calibration,
    a nonlinearity), so the residual's variation among them holds only what changed in between: ``g(t)`` for a
    field that changes (the same in every direction), ``u . b(t)`` for an offset that wanders (its sign and size
    follow the direction). Fitting both forms to that variation tells them apart; a static direction pattern, which
    an offset series can trade against on a short arc of directions, is not in it.

    Attributes
    ----------
    n_samples, n_cells : int
        Samples in direction cells visited more than once, and those cells.
    gap_edges_s, gap_rms_nT : numpy.ndarray, shape (4,)
        Upper edge of each quartile of the time between two visits of a cell (s), and the RMS of the visits'
        residual difference in it (nT): a change in time makes it grow with the time between; white noise alone
        leaves ``sqrt(2) sigma``.
    share_field, share_offset, share_both : float
        Share of the variance within the cells that the field form, the offset form and both together explain.
    p_field, p_offset : float
        F-test of the field form beyond the offset form, and of the offset form beyond the field form (1 where that
        part is less than :data:`REVISIT_MIN_PART` of what both explain).
    form : str
        ``field`` (the offset form adds nothing beyond it), ``offset`` (it adds a significant part beyond the
        field form, and the field form nothing beyond it), ``both``, ``none`` (neither explains the variation)
        or ``undecided`` (the offset form's part beyond the field is large but not significant).
    faster_than_knots : bool
        The change is faster than the series' knots: a field on closer knots explains a significant part beyond both
        forms on them, and the forms were compared with the field on the closer knots.
    """

    n_samples: int
    n_cells: int
    gap_edges_s: np.ndarray
    gap_rms_nT: np.ndarray
    share_field: float
    share_offset: float
    share_both: float
    p_field: float
    p_offset: float
    form: str
    faster_than_knots: bool = False

    def text(self) -> str:
        """The finding in words."""
        growth = ", ".join(f"{v:.3g}" for v in self.gap_rms_nT)
        edges = ", ".join(f"{v:.3g}" for v in self.gap_edges_s)
        what = {
            "field": (
                "the change is the same in every direction: a field that changes (in time, or with the place as the "
                "sensor moves: a magnet or steel fixed in the room), not an offset"
            ),
            "offset": (
                "the change follows the direction: an offset that wanders (the sensor's own, or a magnet or steel "
                "carried with the sensor that was moved), not the field"
            ),
            "both": "both a field and an offset changed",
            "none": "no change in time between the visits",
            "undecided": "either form explains the change: the revisits cannot tell a field from an offset here",
        }[self.form]
        return (
            f"same-direction revisits ({self.n_samples} samples in {self.n_cells} cells of {REVISIT_ANGLE_DEG:g} deg): "
            f"their residuals differ by {growth} nT at time apart up to {edges} s; a field change explains "
            f"{100 * self.share_field:.0f} % of their spread, an offset wander {100 * self.share_offset:.0f} % "
            f"({what}"
            + (
                "; the change is faster than the series' knots: the forms compared on knots "
                f"{REVISIT_CLOSER_KNOTS} times closer"
                if self.faster_than_knots
                else ""
            )
            + ")"
        )


def _direction_cells(u) -> np.ndarray:
    """The cell (index) of each unit direction (N, 3): the nearest of a Fibonacci lattice on the sphere whose points
    are about :data:`REVISIT_ANGLE_DEG` apart."""
    from scipy.spatial import cKDTree

    n = int(np.ceil(4.0 * np.pi / np.radians(REVISIT_ANGLE_DEG) ** 2))
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    phi = np.pi * (1.0 + np.sqrt(5.0)) * k
    rho = np.sqrt(1.0 - z**2)
    lattice = np.column_stack([rho * np.cos(phi), rho * np.sin(phi), z])
    return cKDTree(lattice).query(u)[1]


def _within_cells(cells, x) -> np.ndarray:
    """``x`` (N,) or (N, k) less its mean over each cell."""
    x2 = x.reshape(len(x), -1)
    count = np.bincount(cells)
    means = np.stack([np.bincount(cells, weights=col) for col in x2.T], axis=1) / np.maximum(count, 1)[:, None]
    return (x2 - means[cells]).reshape(x.shape)


def _revisit_gaps(cells, r, t, seed) -> tuple:
    """Quartile edges of the time between two visits of a cell (s, at least :data:`REVISIT_APART_S`) and the RMS
    of the visits' residual difference in each (nT)."""
    order = np.argsort(cells, kind="stable")
    bounds = np.flatnonzero(np.diff(cells[order])) + 1
    rng = np.random.default_rng(seed)
    i_all, j_all = [], []
    for group in np.split(order, bounds):
        if len(group) > 1:
            i, j = np.triu_indices(len(group), 1)
            i_all.append(group[i])
            j_all.append(group[j])
    if not i_all:
        return np.full(4, np.nan), np.full(4, np.nan)
    i, j = np.concatenate(i_all), np.concatenate(j_all)
    apart = np.abs(t[j] - t[i]) >= REVISIT_APART_S
    i, j = i[apart], j[apart]
    if len(i) > REVISIT_MAX_PAIRS:
        pick = rng.choice(len(i), REVISIT_MAX_PAIRS, replace=False)
        i, j = i[pick], j[pick]
    if len(i) < 4:
        return np.full(4, np.nan), np.full(4, np.nan)
    gap, d = np.abs(t[j] - t[i]), r[j] - r[i]
    edges = np.quantile(gap, [0.25, 0.5, 0.75, 1.0])
    which = np.minimum(np.searchsorted(edges, gap, side="left"), 3)
    rms = np.array([np.sqrt(np.mean(d[which == q] ** 2)) if np.any(which == q) else np.nan for q in range(4)])
    return edges, rms


def _compare_forms(r_w, field_w, offset_w, n_free, alpha, same_knots) -> dict:
    """F-tests of the field form beyond the offset form and back on the variation within the cells (``r_w`` and the
    columns less their cell means; ``n_free`` the revisited samples less the cells) and the form they say."""

    def rss(design):
        coef, *_ = np.linalg.lstsq(design, r_w, rcond=None)
        return float(np.sum((r_w - design @ coef) ** 2))

    k_f, k_o = field_w.shape[1], offset_w.shape[1]
    dof = n_free - k_f - k_o
    total = float(np.sum(r_w**2))
    rss_f, rss_o, rss_b = rss(field_w), rss(offset_w), rss(np.hstack([field_w, offset_w]))
    s2 = rss_b / dof

    def p_beyond(rss_without, extra):
        f = (rss_without - rss_b) / extra / s2 if s2 > 0 else 0.0
        return float(stats.f.sf(max(f, 0.0), extra, dof))

    p_field, p_offset, p_any = p_beyond(rss_o, k_f), p_beyond(rss_f, k_o), p_beyond(total, k_f + k_o)
    explained = max(total - rss_b, 1e-300)
    offset_part, field_part = (rss_f - rss_b) / explained, (rss_o - rss_b) / explained
    if field_part < REVISIT_MIN_PART:
        p_field = 1.0
    if offset_part < REVISIT_MIN_PART:
        p_offset = 1.0
    if p_any >= alpha:
        form = "none"
    elif p_field < alpha and p_offset < alpha:
        form = "both"
    elif p_offset < alpha:
        form = "offset"
    elif p_field < alpha or (same_knots and offset_part < REVISIT_MIN_PART):
        # on the same knots an offset series can follow a field along the one direction visited at each moment, a
        # field cannot follow an offset: when the offset's freedom adds nothing, the change is the field's (a field
        # on closer knots can follow an offset along the path too: there it must add a part of its own)
        form = "field"
    else:
        form = "undecided"
    shares = [max(0.0, 1.0 - v / total) if total > 0 else 0.0 for v in (rss_f, rss_o, rss_b)]
    return {"form": form, "p_field": p_field, "p_offset": p_offset, "shares": shares, "rss_both": rss_b}


def revisit_forms(u, r, t, time_columns, alpha=REVISIT_ALPHA, seed=0, fine_columns=None) -> RevisitForms | None:
    """Tell a field that changes from an offset that wanders by the samples that revisit one field direction.

    The residual is split into a free constant per direction cell (any static direction pattern) and a change in
    time, fitted as a field ``g(t)`` (``time_columns``) and as an offset ``u . b(t)`` (each column times each axis
    of ``u``); F-tests of each form beyond the other, on the variation within the cells, decide.

    On the same knots the offset form has three times the field form's columns, and where the direction turns
    within a knot interval its columns follow a change faster than the knots (a field that changes with the place
    as the sensor is carried past a magnet fixed in the room, at a walking pace) that the field's hats cannot: such
    a field would read ``offset``. With ``fine_columns`` (the same series on closer knots, containing
    ``time_columns``'s) the pace is tested: when the offset form on the closer knots explains at least
    :data:`REVISIT_FASTER_PART` of what it leaves on the series' knots (significantly), the change is faster than
    those knots, and both forms are compared on the closer ones (``faster_than_knots``). A slow change (an offset
    that wanders, a magnet carried with the sensor and moved slowly) is judged on the series' knots.

    Parameters
    ----------
    u : numpy.ndarray, shape (N, 3)
        Unit field directions in the sensor's axes.
    r : numpy.ndarray, shape (N,)
        Total-field residuals, nT.
    t : numpy.ndarray, shape (N,)
        Sample times, s.
    time_columns : numpy.ndarray, shape (N, K)
        A series in time that the change follows (e.g. hat functions every few seconds), without its constant.
    alpha : float
        Significance of each form beyond the other.
    seed : int
        Seed of the draw of pairs for the drift with time (:data:`REVISIT_MAX_PAIRS`).
    fine_columns : numpy.ndarray, shape (N, L), optional
        The series on closer knots (L > K, spanning ``time_columns``'s columns), without its constant.

    Returns
    -------
    RevisitForms or None
        None when the revisited samples leave fewer degrees of freedom than both forms have columns (or 30).
    """
    u, r, t = np.asarray(u, float), np.asarray(r, float), np.asarray(t, float)
    h = np.asarray(time_columns, float)
    fine = None if fine_columns is None else np.asarray(fine_columns, float)
    ok = np.all(np.isfinite(u), axis=1) & np.isfinite(r) & np.isfinite(t) & np.all(np.isfinite(h), axis=1)
    if fine is not None:
        ok &= np.all(np.isfinite(fine), axis=1)
        fine = fine[ok]
    u, r, t, h = u[ok], r[ok], t[ok], h[ok]
    k = h.shape[1] if h.ndim == 2 else 0
    k_fine = 0 if fine is None else fine.shape[1]
    if len(r) < 2 or k == 0:
        return None
    cells = _direction_cells(u)
    count = np.bincount(cells)
    again = count[cells] > 1
    n_cells = int(np.sum(count > 1))
    n_free = int(again.sum()) - n_cells
    if n_free - 4 * k < max(30, 4 * k):
        return None
    cells_in = np.unique(cells[again], return_inverse=True)[1]
    offset = np.hstack([u[:, a : a + 1] * h for a in range(3)])
    r_w = _within_cells(cells_in, r[again])
    field_w = _within_cells(cells_in, h[again])
    offset_w = _within_cells(cells_in, offset[again])
    found = _compare_forms(r_w, field_w, offset_w, n_free, alpha, same_knots=True)
    faster = False
    dof_fine = n_free - 4 * k_fine
    small = int(again.sum()) * 4 * k_fine <= REVISIT_MAX_ELEMENTS
    if (
        fine is not None
        and k_fine > k
        and found["form"] not in ("none", "field")
        and dof_fine >= max(30, 4 * k_fine)
        and small
    ):
        # does the offset form need closer knots? (the closer knots' span contains the series' knots' columns)
        offset_fine = np.hstack([u[:, a : a + 1] * fine for a in range(3)])
        offset_fine_w = _within_cells(cells_in, offset_fine[again])
        closer = _compare_forms(r_w, _within_cells(cells_in, fine[again]), offset_fine_w, n_free, alpha, True)
        rss_coarse = float(np.sum((r_w - offset_w @ np.linalg.lstsq(offset_w, r_w, rcond=None)[0]) ** 2))
        rss_closer = float(np.sum((r_w - offset_fine_w @ np.linalg.lstsq(offset_fine_w, r_w, rcond=None)[0]) ** 2))
        extra, dof_o = 3 * (k_fine - k), n_free - 3 * k_fine
        f = (rss_coarse - rss_closer) / extra / (rss_closer / dof_o) if rss_closer > 0 else 0.0
        gain = (rss_coarse - rss_closer) / max(rss_coarse, 1e-300)
        faster = bool(stats.f.sf(max(f, 0.0), extra, dof_o) < alpha and gain >= REVISIT_FASTER_PART)
        if faster:
            found = closer
    edges, rms = _revisit_gaps(cells, r, t, seed)
    share_f, share_o, share_b = found["shares"]
    return RevisitForms(
        int(again.sum()),
        n_cells,
        edges,
        rms,
        share_f,
        share_o,
        share_b,
        found["p_field"],
        found["p_offset"],
        found["form"],
        faster,
    )
