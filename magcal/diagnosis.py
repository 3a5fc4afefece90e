"""Diagnosis: where does the model fail, and which physical effect is missing?

:func:`diagnose` takes a dataset and a fitted model (or fits the base model) and

1. looks at the total-field residuals (and, for arrays, the inter-sensor consistency residuals) against
   **time** (Durbin-Watson, Ljung-Box, a change-point scan, the spectrum), **temperature**, **field direction**
   (least-squares real spherical harmonics up to degree 6: RMS and F-test per degree) and **between sensors**
   (common mode and differences), keeping plain arrays for plotting in ``Diagnosis.evidence``;
2. runs a **score (Lagrange multiplier) test** for every catalogue effect whose channels are present, per sensor
   where it applies and for all sensors together, from the base model's Jacobian alone (no refit), and ranks them
   by the predicted change of the Bayesian information criterion;
3. **confirms** the best few by refitting (actual delta-BIC, RMS after) and, if structure remains, looks for a
   second effect the same way;
4. warns when candidates are **confounded** (canonical correlation of their projected Jacobians, temperature
   following time, cubic nonlinearity versus cross-field coupling...);
5. gives a **verdict**: ``adequate`` (no significant structure left), ``missing_effect`` (catalogue terms bring the
   residuals down to the noise) or ``unexplained`` (significant structure no catalogue term removes, described).

Noise
    The verdict needs the noise level independently of the model's misfit. Along a smooth trajectory a missing
    effect changes slowly from sample to sample while the noise does not, so the noise is estimated from the
    second differences of the residuals in time order (``var(d2 r) = 6 sigma^2`` for white noise), with gross
    jumps clipped. When the samples are not in a smooth order (random attitudes), the dataset's declared
    ``noise_nT`` is used, and failing that the residual RMS itself (then a misfit cannot be told from noise by
    its size, only by its structure; a warning says so).

Information criterion
    ``BIC = m ln(RSS/m) + k ln m`` with ``m`` the number of *independent* residuals: the total-field ones plus, for
    coupled arrays, ``2 (n_sensors - 1)`` per sample for the consistency residuals (they sum to zero over the
    sensors). A candidate is supported when its delta-BIC is below ``-10`` (very strong evidence). A step time
    found by a scan counts as one more parameter.
"""

from __future__ import annotations

import dataclasses
import time as _time
from dataclasses import dataclass, field

import numpy as np
from scipy import stats
from scipy.signal import periodogram
from scipy.special import comb, sph_harm_y

from . import conventions
from .calibration import jsonable
from .errors import CalibrationError, MagcalError
from .model import EFFECTS, Model, term_label
from .noise import robust_sigma

#: Verdicts of :func:`diagnose`.
VERDICTS = ("adequate", "missing_effect", "unexplained")

#: A candidate (or a refit) is supported when its delta-BIC is below this.
DELTA_BIC_THRESHOLD = -10.0

#: Significance level of each structure test (before the Bonferroni factor over sensors and tests).
STRUCTURE_P = 1e-4

#: Smallest share of the residual variance a structure must carry to count (practical significance).
STRUCTURE_MIN_FRACTION = 0.02

#: Samples beyond this many noise sigmas count as isolated glitches in the structure tests ...
GLITCH_SIGMA = 5.0
#: ... unless they are more than this fraction of the samples (then they are structure).
GLITCH_MAX_FRACTION = 0.01

#: Highest spherical-harmonic degree of the direction analysis.
SH_DEGREE = 6

#: The direction analysis uses at most this many samples (evenly spread) per sensor.
SH_MAX_SAMPLES = 6_000


# ================================================================================================================
# statistics of one residual series
# ================================================================================================================


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


# ================================================================================================================
# noise
# ================================================================================================================


@dataclass
class NoiseEstimate:
    """The per-axis noise level used for floors and the verdict.

    Attributes
    ----------
    sigma_nT : float
        Noise standard deviation (nT), pooled over the sensors.
    per_sensor_nT : numpy.ndarray, shape (n_sensors,)
    source : str
        ``"differences"`` (second differences of the residuals along a smooth trajectory), ``"dataset"``
        (declared ``noise_nT``) or ``"residuals"`` (residual RMS; cannot tell misfit from noise by size).
    relative_variance_error : float
        Relative standard error of ``sigma^2`` per sensor (for the excess test).
    """

    sigma_nT: float
    per_sensor_nT: np.ndarray
    source: str
    relative_variance_error: float
    note: str = ""


def is_smooth_sequence(dataset) -> bool:
    """True if consecutive samples are close in attitude (a smooth trajectory in time order).

    Compares the typical step between consecutive raw readings with their spread: about 1.4 for independent
    random attitudes, a few percent for a sensor turned continuously and sampled at several Hz.
    """
    y = dataset.readings_nT[0]
    if len(y) < 20:
        return False
    step = np.median(np.linalg.norm(np.diff(y, axis=0), axis=1))
    spread = np.sqrt(np.sum(np.var(y, axis=0)))
    return bool(step < 0.25 * spread)


def _difference_variance(r, order=2):
    """Noise variance from the ``order``-th differences of ``r``: trimmed mean square / C(2k, k)."""
    d = np.diff(np.asarray(r, dtype=float), n=order)
    if len(d) < 10:
        return float("nan")
    med, mad = np.median(d), robust_sigma(d)
    if mad > 0:
        d = d[np.abs(d - med) < 6.0 * mad]
    return float(np.mean(d**2) / comb(2 * order, order))


def _difference_variance_error(n, order=2):
    """Relative standard error of :func:`_difference_variance` for white Gaussian noise of ``n`` samples."""
    c = np.array([comb(2 * order, order + k) for k in range(-order, order + 1)], dtype=float)
    return float(np.sqrt(2.0 * np.sum(c**2) / comb(2 * order, order) ** 2 / max(n, 1)))


def estimate_noise(dataset, residuals_nT, n_params=9, ordered=None) -> NoiseEstimate:
    """Noise level from the residuals' second differences (smooth trajectories) or the dataset.

    Parameters
    ----------
    dataset : Dataset
    residuals_nT : numpy.ndarray, shape (n_sensors, N)
        Total-field residuals in time order (NaN for samples left out).
    n_params : int
        Parameters of the fit (for the residual-RMS fallback).
    ordered : bool, optional
        Whether the samples follow a smooth trajectory (default :func:`is_smooth_sequence`).
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


# ================================================================================================================
# candidates and score tests
# ================================================================================================================


@dataclass
class Candidate:
    """One candidate effect (optionally on one sensor) and the evidence for it.

    Attributes
    ----------
    effect : str
        Catalogue name.
    sensor : int or None
        0-based sensor (as :attr:`magcal.model.Effect.sensor`), or None for all sensors (or a shared /
        single-sensor term). :meth:`to_dict` writes it 1-based, as the command line and the JSON count.
    label : str
        ``name`` or ``name:S`` (S 1-based, :func:`magcal.model.term_label`).
    n_params : int
        Parameters added (identifiable ones).
    lm : float
        Score (Lagrange multiplier) statistic.
    p_value : float
        Chi-square p-value of ``lm``.
    predicted_delta_bic : float
        From the score test.
    delta_bic : float
        From the refit when ``refitted``, else the predicted one.
    rms_after_nT : float
        Total-field RMS with the effect added (refit, or first-order prediction).
    vector_rms_after_nT : float or None
        Consistency residual RMS per component with the effect added (coupled arrays).
    refitted : bool
    evidence : str
        One line.
    params : dict
        Fitted parameters (refit only).
    """

    effect: str
    sensor: int | None
    label: str
    n_params: int
    lm: float
    p_value: float
    predicted_delta_bic: float
    delta_bic: float
    rms_after_nT: float
    vector_rms_after_nT: float | None = None
    refitted: bool = False
    evidence: str = ""
    params: dict = field(default_factory=dict)
    instances: list = field(default_factory=list, repr=False)
    columns: np.ndarray | None = field(default=None, repr=False)
    fit: object = field(default=None, repr=False)

    def to_dict(self) -> dict:
        return {
            "effect": self.effect, "sensor": None if self.sensor is None else self.sensor + 1,
            "delta_bic": _num(self.delta_bic),
            "rms_after_nT": _num(self.rms_after_nT), "evidence": self.evidence, "label": self.label,
            "predicted_delta_bic": _num(self.predicted_delta_bic), "refitted": self.refitted,
            "lm": _num(self.lm), "p_value": _num(self.p_value), "n_params": self.n_params,
            "vector_rms_after_nT": _num(self.vector_rms_after_nT), "params": self.params,
        }


def _num(x):
    if x is None:
        return None
    x = float(x)
    return x if np.isfinite(x) else None


def effective_residual_count(n_sensors, n_samples, coupled) -> int:
    """Independent residuals: total field, plus ``2 (n_sensors - 1)`` consistency ones per sample if coupled."""
    return int(n_sensors * n_samples + (2 * (n_sensors - 1) * n_samples if coupled else 0))


def _candidate_effects(dataset, model, names=None):
    """Effect instances to test, grouped by name: ``{name: [instance per sensor or one shared]}``."""
    out = {}
    for name, cls in EFFECTS.items():
        if names is not None and name not in names:
            continue
        probe = cls()
        if probe.missing_channels(dataset):
            continue
        existing = [e for e in model.effects if e.name == name]
        if any(e.sensor is None for e in existing):
            continue
        if not cls.per_sensor:
            out[name] = [cls()]
            continue
        covered = {e.sensor for e in existing}
        sensors = [s for s in range(dataset.n_sensors) if probe.applies_to(s) and s not in covered]
        if sensors:
            out[name] = [cls(sensor=s) for s in sensors] if dataset.n_sensors > 1 else [cls()]
    return out


@dataclass
class _Grams:
    """Cross-products of the all-candidates Jacobian and residuals at the fitted base model."""

    g_all: np.ndarray
    v_all: np.ndarray
    rr_all: float
    g_tf: np.ndarray
    v_tf: np.ndarray
    rr_tf: float
    blocks: dict
    m_tf: int


def _grams(kept, model, init, reference_total_nT, chunk_rows=60_000) -> _Grams:
    """Accumulate ``J^T J``, ``J^T r`` (all rows and total-field rows) over chunks of samples.

    The chunks bound the memory of the per-sample derivatives of every candidate's parameters.
    """
    from .fit import Problem

    n = kept.n_samples
    rows_per_sample = kept.n_sensors * (3 if kept.n_sensors > 1 else 1)
    chunk = max(2_000, chunk_rows // rows_per_sample)
    parts = np.array_split(np.arange(n), max(1, int(np.ceil(n / chunk))))
    acc = None
    blocks = None
    for idx in parts:
        sub = kept if len(parts) == 1 else kept.subset(idx)
        problem = Problem(sub, model, init, reference_total_nT)
        r, jtj, jtr, (jtj_tf, jtr_tf) = problem.normal_equations(problem.x0, with_total_field=True)
        rt = r[: sub.n_sensors * sub.n_samples]
        terms = [jtj, jtr, float(r @ r), jtj_tf, jtr_tf, float(rt @ rt)]
        acc = terms if acc is None else [a + t for a, t in zip(acc, terms)]
        blocks = problem.blocks
    return _Grams(acc[0], acc[1], acc[2], acc[3], acc[4], acc[5], blocks, kept.n_sensors * n)


def _columns(blocks, labels):
    cols = []
    for label in labels:
        sl = blocks[label]
        cols.extend(range(sl.start, sl.stop))
    return np.asarray(cols, dtype=int)


class _Projector:
    """Solves with the base block of the Gram matrix (Jacobi-scaled, pseudo-inverse)."""

    def __init__(self, grams: _Grams, base_cols):
        self.g = grams
        self.base = np.asarray(base_cols, dtype=int)
        g00 = grams.g_all[np.ix_(self.base, self.base)]
        d = np.sqrt(np.maximum(np.diag(g00), 1e-300))
        w, v = np.linalg.eigh(g00 / np.outer(d, d))
        keep = w > 1e-12 * w.max()
        self.g00_inv = (v[:, keep] / w[keep]) @ v[:, keep].T / np.outer(d, d)

    def schur(self, a, b=None):
        """``Jt_a^T Jt_b`` with ``Jt = (I - P_base) J``."""
        b = a if b is None else b
        g = self.g.g_all
        return g[np.ix_(a, b)] - g[np.ix_(a, self.base)] @ self.g00_inv @ g[np.ix_(self.base, b)]

    def score(self, cols, rss0, dof0, m_eff, extra_dof=0):
        g = self.g
        base = self.base
        bmat = self.g00_inv @ g.g_all[np.ix_(base, cols)]  # regression of Je on J0
        s = g.g_all[np.ix_(cols, cols)] - g.g_all[np.ix_(cols, base)] @ bmat
        v = g.v_all[cols] - bmat.T @ g.v_all[base]
        d = np.sqrt(np.maximum(np.diag(g.g_all)[cols], 1e-300))
        ss = s / np.outer(d, d)
        ss = 0.5 * (ss + ss.T)
        w, vec = np.linalg.eigh(ss)
        keep = w > 1e-7
        q = int(keep.sum())
        if q == 0:
            return None
        s_pinv = (vec[:, keep] / w[keep]) @ vec[:, keep].T / np.outer(d, d)
        coef = s_pinv @ v
        reduction = float(max(v @ coef, 0.0))
        reduction = min(reduction, 0.999999 * rss0)
        s2 = rss0 / max(dof0, 1)
        lm = reduction / s2
        p = float(stats.chi2.sf(lm, q))
        dbic = m_eff * np.log(1.0 - reduction / rss0) + (q + extra_dof) * np.log(m_eff)
        # first-order total-field residual after adding the effect (the base re-adjusting included)
        jt_r = g.v_tf[cols] - bmat.T @ g.v_tf[base]
        jt_j = (g.g_tf[np.ix_(cols, cols)] - bmat.T @ g.g_tf[np.ix_(base, cols)]
                - g.g_tf[np.ix_(cols, base)] @ bmat + bmat.T @ g.g_tf[np.ix_(base, base)] @ bmat)
        rss_tf = g.rr_tf - 2 * coef @ jt_r + coef @ jt_j @ coef
        rms_tf = float(np.sqrt(max(rss_tf, 0.0) / g.m_tf))
        rss_v = (g.rr_all - g.rr_tf) - 2 * coef @ (v - jt_r) + coef @ (s - jt_j) @ coef
        return {"q": q, "lm": lm, "p": p, "dbic": float(dbic), "rms_tf": rms_tf, "rss_vec": float(max(rss_v, 0.0)),
                "reduction": reduction}

    def canonical_correlation(self, a, b):
        """Largest canonical correlation between the projected columns ``a`` and ``b`` (0..1)."""
        whiten = []
        for cols in (a, b):
            s = self.schur(cols)
            d = np.sqrt(np.maximum(np.diag(s), 1e-300))
            w, v = np.linalg.eigh(0.5 * (s + s.T) / np.outer(d, d))
            keep = w > 1e-7
            if not keep.any():
                return 0.0
            whiten.append((v[:, keep] / np.sqrt(w[keep])) / d[:, None])
        m = whiten[0].T @ self.schur(a, b) @ whiten[1]
        return float(np.clip(np.linalg.norm(m, 2), 0.0, 1.0))


# ================================================================================================================
# the diagnosis
# ================================================================================================================


@dataclass
class Structure:
    """One significant structure found in residuals (a reason the model is not adequate)."""

    kind: str
    sensor: int | None  # 0-based; to_dict writes it 1-based
    p: float
    size: float
    text: str

    def to_dict(self):
        return {"kind": self.kind, "sensor": None if self.sensor is None else self.sensor + 1, "p": _num(self.p), "size": _num(self.size),
                "text": self.text}


@dataclass
class Diagnosis:
    """What :func:`diagnose` found.

    Attributes
    ----------
    verdict : str
        ``adequate``, ``missing_effect`` or ``unexplained``.
    summary : str
        One or two sentences for people.
    effects : list of str
        Candidate effects already in the diagnosed model.
    rms_nT : float
        Total-field RMS of the diagnosed model.
    rms_per_sensor_nT : numpy.ndarray
    noise : NoiseEstimate
    floor_nT : float
        Total-field RMS floor ``sigma sqrt(1 - p/N)``.
    candidates : list of Candidate
        Best first.
    explained_by : list of str
        Labels of the effects that, added, bring the residuals to the noise (``missing_effect``).
    partially_explained_by : list of str
        Supported effects that reduce the residuals without bringing them to the noise (``unexplained``).
    warnings : list of str
    structure : list of Structure
        Significant structure left in the diagnosed model's residuals.
    remaining : list of Structure
        Structure still left after adding ``explained_by`` (or ``partially_explained_by``).
    evidence : dict
        Plot data and statistics (plain numpy arrays): ``time``, ``temperature``, ``direction``, ``spectrum``,
        ``sensors``, ``noise``.
    result : FitResult
        The fit diagnosed.
    fits : dict of str to FitResult
        Refits by candidate label (and ``"+".join(explained_by)`` for the final model).
    elapsed_s : float
    """

    verdict: str
    summary: str
    effects: list
    rms_nT: float
    rms_per_sensor_nT: np.ndarray
    noise: NoiseEstimate
    floor_nT: float
    candidates: list
    explained_by: list
    partially_explained_by: list
    warnings: list
    structure: list
    remaining: list
    evidence: dict
    result: object = field(repr=False, default=None)
    fits: dict = field(repr=False, default_factory=dict)
    elapsed_s: float = 0.0
    rms_final_nT: float | None = None

    @property
    def noise_nT(self) -> float:
        return self.noise.sigma_nT

    @property
    def best(self) -> Candidate | None:
        return self.candidates[0] if self.candidates else None

    def to_dict(self) -> dict:
        """The JSON document of ``magcal diagnose --json`` (issue 4), best candidate first."""
        return {
            "effects": list(self.effects),
            "rms_nT": _num(self.rms_nT),
            "noise_nT": _num(self.noise.sigma_nT),
            "verdict": self.verdict,
            "warnings": list(self.warnings),
            "candidates": [c.to_dict() for c in self.candidates],
            "summary": self.summary,
            "noise_source": self.noise.source,
            "floor_nT": _num(self.floor_nT),
            "rms_per_sensor_nT": [float(v) for v in self.rms_per_sensor_nT],
            "explained_by": list(self.explained_by),
            "partially_explained_by": list(self.partially_explained_by),
            "rms_after_nT": _num(self.rms_final_nT),
            "structure": [s.to_dict() for s in self.structure],
            "remaining_structure": [s.to_dict() for s in self.remaining],
            "elapsed_s": round(float(self.elapsed_s), 3),
        }

    def plot_data(self) -> dict:
        """:attr:`evidence` with arrays turned into lists (JSON-ready), for the workbench."""
        return jsonable(self.evidence)

    def table(self, limit=12) -> str:
        """A readable ranked table of the candidates."""
        lines = [
            f"verdict: {self.verdict}",
            f"  {self.summary}",
            f"total-field RMS {self.rms_nT:.3g} nT; noise {self.noise.sigma_nT:.3g} nT ({self.noise.source}); "
            f"floor {self.floor_nT:.3g} nT",
        ]
        if self.effects:
            lines.append(f"model effects: {', '.join(self.effects)}")
        lines.append("")
        lines.append(f"{'rank':>4}  {'effect':<24} {'sensor':>6} {'dBIC':>10} {'RMS after':>10}  evidence")
        for i, c in enumerate(self.candidates[:limit], 1):
            mark = "" if c.refitted else "*"
            sensor = "-" if len(self.rms_per_sensor_nT) == 1 else "all" if c.sensor is None else str(c.sensor + 1)
            lines.append(f"{i:>4}  {c.effect:<24} {sensor:>6} {c.delta_bic:>9.1f}{mark:1} {c.rms_after_nT:>9.3g}  "
                         f"{c.evidence}")
        if any(not c.refitted for c in self.candidates[:limit]):
            lines.append("  * predicted by the score test (not refitted)")
        if self.warnings:
            lines.append("")
            lines.extend(f"warning: {w}" for w in self.warnings)
        return "\n".join(lines)




# ----------------------------------------------------------------------------------------------------------------


def _fit_of(result):
    """A FitResult from a FitResult or a pipeline CalibrationResult."""
    if result is None:
        return None
    if hasattr(result, "residuals_nT") and hasattr(result, "problem"):
        return result
    fit = getattr(result, "fit", None)
    if fit is None:
        raise MagcalError("diagnosis needs a maximum-likelihood fit (method 'ml'); the result has none")
    return fit


def _reference_override(fit):
    return fit.calibration.reference_total_nT if fit.reference_kind == "given" else None


def _kept(dataset, fit):
    return dataset if fit.mask.all() else dataset.subset(fit.mask)


def _model_fields(kept, fit):
    from .calibration import contexts, corrected_fields

    cal = fit.calibration
    return corrected_fields(kept, cal.sensors, cal.model, cal.effect_values, contexts(kept, cal.baseline_m))


def _sensor_directions(kept, fit):
    """Unit field directions in each sensor's own axes (n_sensors, N, 3)."""
    b = _model_fields(kept, fit)
    out = np.empty_like(b)
    for s, cal in enumerate(fit.calibration.sensors):
        v = b[s] @ cal.R  # R^T applied to rows: array frame -> sensor frame
        out[s] = v / np.linalg.norm(v, axis=1, keepdims=True)
    return out, b


def _vector_rms(fit):
    v = fit.vector_residuals_nT
    if v is None:
        return None
    ns, n = v.shape[:2]
    comps = v.shape[2]
    return float(np.sqrt(np.sum(v**2) / (ns * n * min(comps, 2))))


def _vector_rms_per_sensor(fit):
    v = fit.vector_residuals_nT
    if v is None:
        return None
    comps = min(v.shape[2], 2)
    return np.sqrt(np.sum(v**2, axis=(1, 2)) / (v.shape[1] * comps))


def _floor(sigma, n_samples, n_params_per_sensor):
    return conventions.total_field_floor_nT(sigma, n_samples, min(n_params_per_sensor, n_samples - 1))


def _structure_tests(kept, fit, noise: NoiseEstimate, ordered, directions, n_tests_factor=1):
    """Significant structure in a fit's residuals: excess over the noise, time, spectrum, direction, consistency.

    Returns ``(structures, stats)`` with ``stats`` the per-sensor numbers behind them.
    """
    r_all = fit.residuals_nT[:, fit.mask]
    ns, n = r_all.shape
    alpha = STRUCTURE_P / max(ns, 1) / n_tests_factor
    found, per = [], []
    t = kept.time_s
    p_per_sensor = fit.n_params / ns
    vec = fit.vector_residuals_nT
    for s in range(ns):
        r = r_all[s].copy()
        st = {}
        # isolated glitches (a few samples beyond 5 sigma: a transient, a jerk of the motion) are counted and set
        # aside, so that they do not pass for a systematic structure; more than 1 % of them is structure
        sigma = noise.per_sensor_nT[s]
        glitch = np.abs(r) > GLITCH_SIGMA * sigma
        if vec is not None:
            glitch |= np.linalg.norm(vec[s].reshape(n, -1), axis=1) > (GLITCH_SIGMA + 0.5) * sigma
        if glitch.sum() > GLITCH_MAX_FRACTION * n:
            glitch[:] = False
        st["glitches"] = int(glitch.sum())
        keep = ~glitch
        r[glitch] = 0.0
        floor = _floor(noise.per_sensor_nT[s], n, p_per_sensor)
        ratio = float(np.mean(r[keep] ** 2) / floor**2)
        se = np.sqrt(2.0 / n + noise.relative_variance_error**2)
        z = (ratio - 1.0) / se
        st.update(rms_nT=float(np.sqrt(np.mean(r[keep] ** 2))), floor_nT=floor, variance_ratio=ratio,
                  excess_z=float(z))
        if noise.source != "residuals" and z > stats.norm.isf(alpha) and ratio > 1.0 + 2 * STRUCTURE_MIN_FRACTION:
            found.append(Structure("excess", s, float(stats.norm.sf(z)), ratio,
                                   f"sensor {s + 1}: RMS {st['rms_nT']:.3g} nT is {np.sqrt(ratio):.2f}x "
                                   f"the noise floor {floor:.3g} nT"))
        if ordered:
            q, p, frac = ljung_box(r)
            st.update(ljung_box_q=q, ljung_box_p=p, autocorrelated_fraction=frac, durbin_watson=durbin_watson(r))
            if p < alpha and frac > STRUCTURE_MIN_FRACTION:
                found.append(Structure("time", s, p, frac,
                                       f"sensor {s + 1}: residuals correlated in time (Ljung-Box p={p:.2g}, "
                                       f"Durbin-Watson {st['durbin_watson']:.2f})"))
            spec = spectrum(r, t)
            st.update(peak_hz=spec["peak_hz"], peak_fraction=spec["peak_fraction"], peak_p=spec["p"],
                      peak_amplitude_nT=spec["amplitude_nT"])
            if spec["p"] < alpha and spec["peak_fraction"] > STRUCTURE_MIN_FRACTION:
                unit = "Hz" if t is not None else "cycles/sample"
                found.append(Structure("periodic", s, spec["p"], spec["peak_fraction"],
                                       f"sensor {s + 1}: periodic component at {spec['peak_hz']:.3g} {unit} "
                                       f"(amplitude {spec['amplitude_nT']:.2g} nT, {100 * spec['peak_fraction']:.0f}% "
                                       "of the residual variance)"))
        sh = sh_analysis(directions[s][keep], r[keep], max_samples=SH_MAX_SAMPLES)
        hi = sh["degree"] >= 3
        p_sh = float(np.nanmin(sh["p"][hi])) if np.any(np.isfinite(sh["p"][hi])) else 1.0
        deg = int(sh["degree"][hi][np.nanargmin(sh["p"][hi])]) if np.isfinite(p_sh) else -1
        size = float(np.sum(sh["rms_nT"][hi] ** 2) / max(np.mean(r[keep] ** 2), 1e-300))
        st.update(sh_p=p_sh, sh_degree=deg, sh_fraction=size)
        if p_sh < alpha / 4 and size > STRUCTURE_MIN_FRACTION:
            found.append(Structure("direction", s, p_sh, size,
                                   f"sensor {s + 1}: pattern over the field direction, strongest at spherical-harmonic "
                                   f"degree {deg} ({sh['rms_nT'][deg]:.2g} nT)"))
        if vec is not None:
            v = vec[s].reshape(n, -1).copy()
            v[glitch] = 0.0
            comps = min(v.shape[1], 2)
            vr = float(np.sum(v**2) / (keep.sum() * comps))
            ratio_v = vr / noise.per_sensor_nT.mean() ** 2
            zv = (ratio_v - 1.0) / np.sqrt(1.0 / n + noise.relative_variance_error**2)
            st.update(vector_rms_nT=float(np.sqrt(vr)), vector_variance_ratio=ratio_v)
            if noise.source != "residuals" and zv > stats.norm.isf(alpha) and ratio_v > 1 + 2 * STRUCTURE_MIN_FRACTION:
                found.append(Structure("consistency", s, float(stats.norm.sf(zv)), ratio_v,
                                       f"sensor {s + 1}: disagrees with the others in direction by "
                                       f"{np.sqrt(vr):.3g} nT RMS per component ({np.sqrt(ratio_v):.2f}x the noise)"))
            if ordered:
                pv = min(ljung_box(v[:, k])[1] for k in range(comps))
                fv = max(ljung_box(v[:, k])[2] for k in range(comps))
                if pv < alpha / comps and fv > STRUCTURE_MIN_FRACTION:
                    found.append(Structure("consistency_time", s, pv, fv,
                                           f"sensor {s + 1}: the inter-sensor disagreement is correlated in time "
                                           f"(Ljung-Box p={pv:.2g})"))
        per.append(st)
    return found, per


#: One-line signature of each effect, for the evidence column.
SIGNATURES = {
    "temperature_bias": "residual follows (T - T0) x field direction (degree 1)",
    "temperature_scale": "residual follows (T - T0) x direction degrees 0 and 2",
    "bias_drift": "slow trend in time times field direction",
    "bias_step": "step in the residual pattern",
    "nonlinearity_quadratic": "direction pattern of degree 3",
    "nonlinearity_cubic": "direction pattern of degree 4",
    "axis_timing_skew": "residual ~ rate of change of the axes; flips with the rotation direction",
    "sensor_timing_skew": "inter-sensor differences ~ dt dB/dt",
    "hysteresis": "residual flips sign with each axis's direction of change",
    "reference_drift": "common to all sensors, independent of direction, slow in time",
    "site_gradient": "inter-sensor differences follow the attitude (world-fixed gradient)",
}


def _evidence_line(c: Candidate, extra: str = "") -> str:
    p_text = f"p={c.p_value:.1g}" if c.p_value > 1e-300 else "p<1e-300"
    parts = [f"score LM={c.lm:.1f} on {c.n_params} parameter(s) ({p_text})"]
    if extra:
        parts.append(extra)
    parts.append(SIGNATURES.get(c.effect, ""))
    return "; ".join(p for p in parts if p)


def _score_round(dataset, kept, fit, names=None):
    """Score tests for every candidate (per sensor and all sensors) at the fitted model ``fit``.

    Returns ``(candidates, projector, grams)``; candidates are sorted by predicted delta-BIC.
    """
    model = fit.model
    groups = _candidate_effects(kept, model, names)
    if not groups:
        return [], None, None
    base_resid = fit.residuals_nT[:, fit.mask]
    for instances in groups.values():
        for e in instances:
            e.configure(kept, base_resid)
    all_model = Model(model.n_sensors, model.base,
                      [dataclasses.replace(e) for e in model.effects] + [e for v in groups.values() for e in v])
    ref = _reference_override(fit)
    try:
        grams = _grams(kept, all_model, fit.calibration, ref)
    except CalibrationError:
        # too few samples for every candidate at once: test them one effect at a time
        return _score_round_separately(dataset, kept, fit, groups)
    return _score_from_grams(kept, fit, groups, grams)


def _score_round_separately(dataset, kept, fit, groups):
    out = []
    for name, instances in groups.items():
        m = Model(fit.model.n_sensors, fit.model.base, [dataclasses.replace(e) for e in fit.model.effects] + instances)
        try:
            grams = _grams(kept, m, fit.calibration, _reference_override(fit))
        except CalibrationError:
            continue
        cands, _, _ = _score_from_grams(kept, fit, {name: instances}, grams)
        out.extend(cands)
    out.sort(key=lambda c: c.predicted_delta_bic)
    return out, None, None


def _score_from_grams(kept, fit, groups, grams):
    from .calibration import block_label

    cand_labels = {block_label(e, s) for v in groups.values() for e in v
                   for s in ([None] if not e.per_sensor else [e.sensor] if e.sensor is not None
                             else [q for q in range(kept.n_sensors) if e.applies_to(q)])}
    all_cols = np.arange(grams.g_all.shape[0])
    cand_cols = _columns(grams.blocks, sorted(cand_labels))
    base_cols = np.setdiff1d(all_cols, cand_cols)
    proj = _Projector(grams, base_cols)
    ns, n = kept.n_sensors, kept.n_samples
    coupled = fit.vector_residuals_nT is not None
    m_eff = effective_residual_count(ns, n, coupled)
    rss0 = grams.rr_all
    dof0 = m_eff - len(base_cols)
    cands = []
    for name, instances in groups.items():
        cls = EFFECTS[name]
        variants = []
        if not cls.per_sensor:
            variants.append((None, instances))
        elif ns == 1:
            variants.append((None, instances))
        else:
            for e in instances:
                variants.append((e.sensor, [e]))
            if len(instances) > 1:
                variants.append((None, instances))
        for sensor, inst in variants:
            labels = []
            for e in inst:
                if not e.per_sensor:
                    labels.append(block_label(e, None))
                elif e.sensor is not None:
                    labels.append(block_label(e, e.sensor))
                else:
                    labels.extend(block_label(e, q) for q in range(ns) if e.applies_to(q))
            cols = _columns(grams.blocks, labels)
            extra = cls.extra_dof * len(inst) if hasattr(cls, "extra_dof") else 0
            sc = proj.score(cols, rss0, dof0, m_eff, extra)
            if sc is None:
                continue
            label = term_label(name, sensor)
            vec_after = None
            if coupled:
                vec_after = float(np.sqrt(sc["rss_vec"] / (ns * n * 2)))
            c = Candidate(effect=name, sensor=sensor, label=label, n_params=sc["q"],
                          lm=sc["lm"], p_value=sc["p"], predicted_delta_bic=sc["dbic"], delta_bic=sc["dbic"],
                          rms_after_nT=sc["rms_tf"], vector_rms_after_nT=vec_after, instances=inst, columns=cols)
            cands.append(c)
    cands.sort(key=lambda c: c.predicted_delta_bic)
    return cands, proj, grams


def _refit(dataset, fit, candidate: Candidate):
    """Refit the model with the candidate's effect instances added; returns the FitResult."""
    from .fit import fit as ml_fit

    model = fit.model
    if candidate.sensor is None and len(candidate.instances) > 1 and not any(e.name == candidate.effect
                                                                            for e in model.effects):
        new = [EFFECTS[candidate.effect]()]  # one term for all sensors
    else:
        new = [dataclasses.replace(e) for e in candidate.instances]
    for e in new:
        model = model.with_effect(e)
    ref = _reference_override(fit)
    return ml_fit(dataset, model, init=fit.calibration, mask=fit.mask, reference_total_nT=ref)


def _delta_bic(fit0, fit1, extra_dof, coupled):
    ns = fit0.residuals_nT.shape[0]
    n = int(fit0.mask.sum())
    m_eff = effective_residual_count(ns, n, coupled)
    dk = fit1.n_params - fit0.n_params + extra_dof
    return float(m_eff * np.log(fit1.rss / fit0.rss) + dk * np.log(m_eff))


def _confirm(dataset, fit, cands, top, coupled, fits):
    """Refit the best variant of the ``top`` best distinct effects; re-rank."""
    chosen, seen = [], set()
    for c in cands:
        if c.effect in seen:
            continue
        seen.add(c.effect)
        chosen.append(c)
        if len(chosen) >= top:
            break
    for c in chosen:
        try:
            f1 = _refit(dataset, fit, c)
        except (CalibrationError, np.linalg.LinAlgError) as exc:
            c.evidence = (c.evidence + "; " if c.evidence else "") + f"refit failed: {exc}"
            continue
        extra = EFFECTS[c.effect].extra_dof * len(c.instances) if hasattr(EFFECTS[c.effect], "extra_dof") else 0
        c.delta_bic = _delta_bic(fit, f1, extra, coupled)
        c.rms_after_nT = float(f1.rms_nT)
        c.vector_rms_after_nT = _vector_rms(f1)
        c.refitted = True
        c.params = {p["term"]: p["params"] for p in f1.effect_params if p["effect"] == c.effect}
        c.fit = f1
        fits[c.label] = f1
    refitted = sorted([c for c in cands if c.refitted], key=lambda c: c.delta_bic)
    rest = [c for c in cands if not c.refitted]
    return refitted + rest


def _effect_extra(c: Candidate, kept, fit, directions, sh_stats) -> str:
    """Effect-specific numbers for the evidence line."""
    if c.effect == "bias_step":
        times = []
        for e in c.instances:
            if e.step_time_s:
                times.extend(t for t in e.step_time_s if t is not None)
        if times:
            return "step near t = " + ", ".join(f"{t:.4g} s" for t in sorted(set(np.round(times, 3))))
    if c.effect in ("nonlinearity_quadratic", "nonlinearity_cubic") and sh_stats:
        degree = 3 if c.effect == "nonlinearity_quadratic" else 4
        sensors = [c.sensor] if c.sensor is not None else range(len(sh_stats))
        rms = [sh_stats[s]["rms_nT"][degree] for s in sensors]
        return f"direction degree {degree}: {max(rms):.2g} nT"
    if c.effect in ("temperature_bias", "temperature_scale", "bias_drift", "reference_drift") and \
            kept.temperature_C is not None and kept.time_s is not None:
        rho = abs(np.corrcoef(kept.temperature_C, kept.time_s)[0, 1])
        return f"|corr(T, t)| = {rho:.2f}"
    return ""


def _warnings_for(cands, proj, kept, fit, noise, significant):
    out = []
    if noise.source == "residuals":
        out.append(noise.note)
    if kept.noise_nT and noise.source == "differences":
        ratio = noise.sigma_nT / float(kept.noise_nT)
        if abs(ratio - 1.0) > 0.2:
            out.append(f"the declared noise_nT {float(kept.noise_nT):.3g} nT differs from the noise seen in the data "
                       f"({noise.sigma_nT:.3g} nT)")
    top = [c for c in cands if c.delta_bic < DELTA_BIC_THRESHOLD][:4]
    if proj is not None and len(top) >= 1:
        best = top[0]
        for other in cands[1:8]:
            if other.effect == best.effect or other.delta_bic >= DELTA_BIC_THRESHOLD:
                continue
            try:
                cc = proj.canonical_correlation(best.columns, other.columns)
            except (np.linalg.LinAlgError, ValueError):
                continue
            gap = other.delta_bic - best.delta_bic
            if cc > 0.9 and gap < max(10.0, 0.1 * abs(best.delta_bic)):
                out.append(f"{best.label} and {other.label} are confounded in these data (canonical correlation "
                           f"{cc:.2f}): the data can hardly tell them apart")
    names = {c.effect for c in top}
    if kept.temperature_C is not None and kept.time_s is not None:
        rho = abs(np.corrcoef(kept.temperature_C, kept.time_s)[0, 1])
        temp = names & {"temperature_bias", "temperature_scale"}
        timed = names & {"bias_drift", "reference_drift"}
        if rho > 0.9 and (temp or timed):
            out.append(f"temperature follows time (|corr| = {rho:.2f}, e.g. a warm-up): temperature effects and drifts "
                       "are confounded; record with the temperature varying independently of time to separate them")
    if cands and cands[0].effect == "nonlinearity_cubic" and cands[0].delta_bic < DELTA_BIC_THRESHOLD:
        out.append("nonlinearity_cubic cannot be told from cross-field coupling l_j B_j (|B|^2 - B_j^2) at constant "
                   "|B|; both leave the same degree-4 direction pattern")
    if top and top[0].effect in ("axis_timing_skew", "hysteresis") and {"axis_timing_skew", "hysteresis"} <= names:
        out.append("axis_timing_skew and hysteresis both depend on the direction of rotation; vary the rotation "
                   "speed to separate them (a delay scales with speed, hysteresis does not)")
    if kept.n_sensors > 1 and kept.attitude_wxyz is None:
        out.append("no attitude columns (qw, qx, qy, qz): site_gradient cannot be tested; the array alone sees a site "
                   "gradient only as a tensor rotating with it (constant invariants) and as biases")
    return out


def _describe(structures) -> str:
    kinds = {}
    for s in structures:
        kinds.setdefault(s.kind, []).append(s)
    parts = []
    for kind in ("periodic", "direction", "time", "excess", "consistency", "consistency_time"):
        if kind in kinds:
            parts.append(max(kinds[kind], key=lambda s: s.size).text)
    return "; ".join(parts)


def _time_evidence(kept, r, ordered):
    t = kept.time_s if kept.time_s is not None else np.arange(kept.n_samples, dtype=float)
    n = len(t)
    w = max(1, n // 60)
    kernel = np.ones(w) / w
    smooth = np.array([np.convolve(row, kernel, mode="same") for row in r])
    ev = {"x": t, "y": r, "smooth": smooth, "x_label": "time (s)" if kept.time_s is not None else "sample",
          "durbin_watson": np.array([durbin_watson(row) for row in r])}
    if ordered:
        lb = [ljung_box(row) for row in r]
        ev["ljung_box_p"] = np.array([x[1] for x in lb])
        cs = [cusum_test(row) for row in r]
        ev["cusum"] = {"index": np.array([c[0] for c in cs]), "statistic": np.array([c[1] for c in cs]),
                       "p": np.array([c[2] for c in cs]), "time": np.array([t[c[0]] for c in cs])}
        if kept.time_s is not None:
            from .effects import step_scan

            scans = [step_scan(kept.readings_nT[s]) for s in range(r.shape[0])]
            ev["step_scan"] = {"rss_drop_nT2": np.array([sc[1] for sc in scans]),
                               "time": np.array([t[sc[0]] for sc in scans])}
    return ev


def _temperature_evidence(kept, r, directions):
    if kept.temperature_C is None:
        return None
    temp = kept.temperature_C
    d_t = temp - temp.mean()
    p_vals = []
    for s in range(r.shape[0]):
        u = directions[s]
        base = np.column_stack([np.ones(len(d_t)), u])
        full = np.column_stack([base, d_t[:, None] * base])
        rss0 = np.sum((r[s] - base @ np.linalg.lstsq(base, r[s], rcond=None)[0]) ** 2)
        rss1 = np.sum((r[s] - full @ np.linalg.lstsq(full, r[s], rcond=None)[0]) ** 2)
        f = (rss0 - rss1) / 4 / max(rss1 / (len(d_t) - 8), 1e-300)
        p_vals.append(float(stats.f.sf(f, 4, len(d_t) - 8)))
    order = np.argsort(temp)
    return {"x": temp, "y": r, "x_label": "temperature (degC)", "f_test_p": np.array(p_vals),
            "sorted_index": order}


def _sensor_evidence(kept, fit, r, fields):
    ns = r.shape[0]
    if ns < 2:
        return None
    common = r.mean(axis=0)
    diffs = r - common
    ev = {"common_mode_nT": common, "differences_nT": diffs,
          "common_mode_rms_nT": float(np.sqrt(np.mean(common**2))),
          "difference_rms_nT": np.sqrt(np.mean(diffs**2, axis=1)),
          "correlation": np.corrcoef(r)}
    vr = _vector_rms_per_sensor(fit)
    if vr is not None:
        ev["vector_rms_nT"] = vr
    if ns == 4 and fit.calibration.baseline_m:
        g = conventions.tensor_components(fields, fit.calibration.baseline_m)
        tensor = conventions.tensor_matrix(g)
        norm = np.sqrt(np.sum(tensor**2, axis=(1, 2)))
        ev["tensor_norm_nT_per_m"] = norm
        ev["tensor_mean_nT_per_m"] = {k: float(np.mean(v)) for k, v in g.items()}
    return ev


def diagnose(dataset, result=None, model=None, top=3, effects=None, candidates=None, max_effects=2,
             progress=None) -> Diagnosis:
    """Diagnose a calibration model on a dataset: structure left, ranked candidate effects, verdict.

    Parameters
    ----------
    dataset : Dataset
    result : FitResult or CalibrationResult, optional
        The fitted model to diagnose. Without it the model (``model``, or the base model plus ``effects``) is
        fitted with :func:`magcal.pipeline.calibrate`.
    model : Model, optional
        Model to fit when ``result`` is not given.
    top : int
        Number of distinct candidate effects confirmed by refitting.
    effects : sequence of str, optional
        Effects (``NAME`` or ``NAME:SENSOR``) to add to the base model when neither ``result`` nor ``model`` is
        given (as ``magcal diagnose --effects``).
    candidates : sequence of str, optional
        Restrict the score tests to these catalogue names (default: every effect whose channels are present).
    max_effects : int
        Most effects added one after the other to explain the residuals (greedy forward selection).
    progress : callable, optional
        ``progress(message, fraction)``.

    Returns
    -------
    Diagnosis
    """
    t_start = _time.perf_counter()

    def report(msg, frac):
        if progress is not None:
            progress(msg, frac)

    fit0 = _fit_of(result)
    if fit0 is None:
        from .pipeline import calibrate

        report("fitting the model", 0.0)
        if model is not None:
            res = calibrate(dataset, effects=list(model.effects), base_terms=model.base)
        else:
            res = calibrate(dataset, effects=list(effects or ()))
        fit0 = res.fit
    kept = _kept(dataset, fit0)
    ns = kept.n_sensors
    n = kept.n_samples
    coupled = fit0.vector_residuals_nT is not None
    ordered = is_smooth_sequence(kept)
    r0 = fit0.residuals_nT[:, fit0.mask]
    directions, fields = _sensor_directions(kept, fit0)

    report("score tests", 0.2)
    cands, proj, _ = _score_round(dataset, kept, fit0, candidates)
    sh_stats = [sh_analysis(directions[s], r0[s], max_samples=SH_MAX_SAMPLES) for s in range(ns)]
    fits = {}
    report("refitting the best candidates", 0.4)
    cands = _confirm(dataset, fit0, cands, top, coupled, fits)
    for c in cands:
        note = c.evidence  # e.g. a failed refit
        c.evidence = _evidence_line(c, _effect_extra(c, kept, fit0, directions, sh_stats))
        if note:
            c.evidence += "; " + note

    # noise and structure of the model as given
    noise0 = estimate_noise(kept, r0, fit0.n_params, ordered)
    structure0, stats0 = _structure_tests(kept, fit0, noise0, ordered, directions)

    # greedy forward selection while the best candidate is supported
    explained, current, current_noise = [], fit0, noise0
    remaining, stats_final = structure0, stats0
    round_cands = cands
    for step in range(max_effects):
        supported = [c for c in round_cands if c.refitted and c.delta_bic < DELTA_BIC_THRESHOLD]
        if not supported:
            break
        best = supported[0]
        nxt = best.fit
        if nxt is None:
            break
        explained.append(best.label)
        current = nxt
        kept_c = _kept(dataset, current)
        dirs_c, _ = _sensor_directions(kept_c, current)
        current_noise = estimate_noise(kept_c, current.residuals_nT[:, current.mask], current.n_params, ordered)
        remaining, stats_final = _structure_tests(kept_c, current, current_noise, ordered, dirs_c)
        if step + 1 >= max_effects:
            break
        report("looking for a further effect", 0.6 + 0.2 * step)
        more, _, _ = _score_round(dataset, kept_c, current, candidates)
        more = [c for c in more if c.predicted_delta_bic < DELTA_BIC_THRESHOLD]
        if not more:
            break
        more = _confirm(dataset, current, more, 1, coupled, fits)
        round_cands = more

    # verdict
    supported0 = [c for c in cands if c.delta_bic < DELTA_BIC_THRESHOLD]
    noise_final = current_noise if explained else noise0
    if not structure0 and not supported0:
        verdict = "adequate"
        summary = (f"no significant structure: the residuals ({fit0.rms_nT:.3g} nT RMS) look like noise of "
                   f"{noise0.sigma_nT:.3g} nT")
    elif explained and not remaining:
        verdict = "missing_effect"
        rms_after = current.rms_nT
        summary = (f"missing {' and '.join(explained)}: adding {'them' if len(explained) > 1 else 'it'} brings "
                   "the total-field RMS from "
                   f"{fit0.rms_nT:.3g} to {rms_after:.3g} nT (noise {noise_final.sigma_nT:.3g} nT)")
        if coupled:
            summary += (f" and the inter-sensor consistency RMS from {_vector_rms(fit0):.3g} to "
                        f"{_vector_rms(current):.3g} nT")
    else:
        verdict = "unexplained"
        what = _describe(remaining if explained else structure0) or "residual structure the score tests flag"
        tried = ""
        if cands:
            b = cands[0]
            tried = (f"; the best catalogue term ({b.label}) only takes the RMS from {fit0.rms_nT:.3g} to "
                     f"{b.rms_after_nT:.3g} nT") if b.refitted else ""
        summary = f"significant structure that no catalogue term brings down to the noise: {what}{tried}"
    partial = []
    if verdict != "missing_effect":
        partial, explained = explained, []
    warnings_ = _warnings_for(cands, proj, kept, fit0, noise0, structure0)
    if partial:
        warnings_.append(f"{', '.join(partial)} reduce(s) the residuals significantly but do(es) not bring them to "
                         "the noise: not the (whole) explanation")
    glitches = [(s + 1, st["glitches"]) for s, st in enumerate(stats_final) if st.get("glitches")]
    if glitches:
        warnings_.append("isolated samples beyond 5 sigma set aside from the structure tests (glitches or sharp "
                         "motion): " + ", ".join(f"sensor {s}: {k}" for s, k in glitches))
    if len(explained) > 1 and verdict == "missing_effect":
        warnings_.append(f"more than one effect was needed: {', '.join(explained)} (added in that order)")
    if explained or partial:
        fits["+".join(explained or partial)] = current

    floor = _floor(noise_final.sigma_nT, n, fit0.n_params / ns)
    evidence = {
        "time": _time_evidence(kept, r0, ordered),
        "temperature": _temperature_evidence(kept, r0, directions),
        "direction": {"u": directions, "y": r0, "per_sensor": [
            dict(sh) for sh in sh_stats]},
        "spectrum": [spectrum(row, kept.time_s) for row in r0] if ordered else None,
        "sensors": _sensor_evidence(kept, fit0, r0, fields),
        "noise": {"sigma_nT": noise0.sigma_nT, "per_sensor_nT": noise0.per_sensor_nT, "source": noise0.source,
                  "final_sigma_nT": noise_final.sigma_nT},
        "tests": stats0,
    }
    return Diagnosis(
        verdict=verdict, summary=summary, effects=fit0.model.effect_labels, rms_nT=float(fit0.rms_nT),
        rms_per_sensor_nT=np.asarray(fit0.rms_per_sensor_nT), noise=noise_final, floor_nT=floor,
        candidates=cands, explained_by=explained, partially_explained_by=partial, warnings=warnings_,
        structure=structure0, remaining=remaining,
        evidence=evidence, result=fit0, fits=fits, elapsed_s=_time.perf_counter() - t_start,
        rms_final_nT=float(current.rms_nT),
    )
