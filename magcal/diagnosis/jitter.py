"""Sampling-time jitter between the sensors of an array, from the variance of the inter-sensor residual.

Two sensors read by one host at slightly different, random instants see the field at different moments: sensor
``s`` reads ``B(t - dt)`` with ``dt`` random, RMS ``tau``. Their difference is then ``dt dB/dt``, across the field
(a turning field keeps its magnitude), with mean zero: no term of the mean model holds it, but its variance grows
with the turn rate squared::

    E |d_perp|^2 = a + tau^2 |dB/dt|^2,

``a`` the noise of the two sensors (and what else is left, independent of the rate). :func:`jitter_estimates`
takes the perpendicular part of each sensor's corrected field minus sensor 1's, removes a constant delay (the
catalogue's ``sensor_timing_skew``, whose difference ``dt dB/dt`` has a mean), and fits ``a`` and ``tau^2`` by
weighted least squares (weights ``1 / E^2``: a squared Gaussian residual's spread is its mean). The diagnosis
names the catalogue's ``sensor_jitter`` with ``tau`` in ms when ``tau^2`` is significant (a likelihood ratio) and
the jitter is a visible part of the fastest quartile's residual (:data:`JITTER_MIN_Z`, :data:`JITTER_MIN_SHARE`).
"""

from __future__ import annotations

import numpy as np

from magcal.core.rows import row_norm, unit_rows
from magcal.diagnosis._fitted import _model_fields
from magcal.model.effects import time_derivative

#: Least likelihood-ratio statistic (the square root of the ratio, standard normal without a jitter) of ``tau^2``
#: for a jitter to be named.
JITTER_MIN_Z = 6.0
#: ...and the least share of the fastest turn-rate quartile's residual variance the jitter must make.
JITTER_MIN_SHARE = 0.1
#: Fewest samples for an estimate.
JITTER_MIN_SAMPLES = 40


def _perpendicular(v, u):
    return v - np.sum(v * u, axis=1, keepdims=True) * u


def _weighted_line(x, y, iterations=4):
    """``y ~ a + c x`` by weighted least squares with weights ``1 / (a + c x)^2`` (a squared residual's spread is
    its mean), ``a > 0`` and ``c >= 0``. Returns ``a``, ``c`` and the standard error of ``c``."""
    a, c = max(float(np.mean(y)), 1e-12), 0.0
    design = np.column_stack([np.ones_like(x), x])
    se = np.inf
    for _ in range(iterations):
        w = 1.0 / np.maximum(a + c * x, 1e-12) ** 2
        normal = design.T @ (design * w[:, None])
        try:
            cov = np.linalg.inv(normal)
        except np.linalg.LinAlgError:
            return a, c, np.inf
        a, c = cov @ (design.T @ (w * y))
        a, c = max(float(a), 1e-12), max(float(c), 0.0)
        fitted = a + c * x
        dispersion = float(np.sum(w * (y - fitted) ** 2) / max(len(y) - 2, 1))
        se = float(np.sqrt(max(cov[1, 1] * dispersion, 0.0)))
    return a, c, se


def _exponential_loglik(y, mean) -> float:
    """Log-likelihood of squared residuals ``y`` exponential about ``mean`` (the weighted fit's model)."""
    mean = np.maximum(mean, 1e-12)
    return float(-np.sum(np.log(mean) + y / mean))


def _by_quartile(rate, values):
    """Edges of the turn-rate quartiles and the RMS of ``values`` (per-sample vectors' lengths) in each."""
    edges = np.quantile(rate, [0.0, 0.25, 0.5, 0.75, 1.0])
    which = np.clip(np.searchsorted(edges, rate, side="right") - 1, 0, 3)
    rms = [float(np.sqrt(np.mean(values[which == q] ** 2))) if np.any(which == q) else float("nan") for q in range(4)]
    return edges, which, rms


def jitter_estimate(field_ref_nT, field_nT, time_s) -> dict | None:
    """The sampling jitter of one sensor against a reference sensor (both corrected, array frame, nT).

    Parameters
    ----------
    field_ref_nT, field_nT : numpy.ndarray, shape (N, 3)
        The reference sensor's and the other sensor's corrected fields, nT.
    time_s : numpy.ndarray, shape (N,)

    Returns
    -------
    dict or None
        ``jitter_rms_ms`` (tau), ``jitter_se_ms``, ``z`` (the square root of the likelihood ratio of ``tau^2``
        against none, ``|e|^2`` exponential about its mean: standard normal without a jitter), ``delay_ms`` (the constant
        delay removed first), ``noise_nT`` (``sqrt(a / 2)``, per perpendicular component), the turn-rate quartiles
        (``rate_quartiles_dps``, edges) and the inter-sensor residual's RMS in each (``rms_by_rate_quartile_nT``),
        ``share_fastest`` (the jitter's share of the fastest quartile's residual variance) and ``significant``;
        None for too few samples or no time stamps.
    """
    if time_s is None or len(time_s) < JITTER_MIN_SAMPLES:
        return None
    b0 = np.asarray(field_ref_nT, dtype=float)
    u = unit_rows(b0)
    rate = _perpendicular(time_derivative(b0, time_s), u)  # nT/s, across the field
    d = np.asarray(field_nT, dtype=float) - b0
    d = _perpendicular(d - d.mean(axis=0), u)
    rr = float(np.sum(rate * rate))
    delay_s = float(np.sum(d * rate) / rr) if rr > 0 else 0.0
    e = d - delay_s * rate
    x = np.sum(rate * rate, axis=1)
    y = np.sum(e * e, axis=1)
    a, c, se = _weighted_line(x, y)
    turn_dps = np.degrees(row_norm(rate) / np.maximum(row_norm(b0), 1e-9))
    edges, which, rms = _by_quartile(turn_dps, row_norm(e))
    fastest = which == 3
    jitter_var = c * float(np.mean(x[fastest])) if np.any(fastest) else 0.0
    share = jitter_var / max(jitter_var + a, 1e-12)
    tau_ms = 1e3 * np.sqrt(c)
    # significance: the likelihood ratio of tau^2 against none, |e|^2 being exponential about its mean (two
    # Gaussian components across the field); sqrt of the ratio is standard normal without a jitter
    ratio = 2.0 * (_exponential_loglik(y, a + c * x) - _exponential_loglik(y, np.full_like(y, np.mean(y))))
    z = float(np.sqrt(max(ratio, 0.0)))
    return {
        "jitter_rms_ms": float(tau_ms),
        "jitter_se_ms": float(1e3 * se / (2.0 * np.sqrt(c))) if c > 0 and np.isfinite(se) else float("inf"),
        "z": float(z),
        "delay_ms": 1e3 * delay_s,
        "noise_nT": float(np.sqrt(a / 2.0)),
        "rate_quartiles_dps": [float(v) for v in edges],
        "rms_by_rate_quartile_nT": rms,
        "share_fastest": float(share),
        "significant": bool(z >= JITTER_MIN_Z and share >= JITTER_MIN_SHARE),
    }


def jitter_estimates(kept, fit) -> list:
    """:func:`jitter_estimate` of sensors 2-4 against sensor 1 under a fitted array model (its corrected fields on
    its kept samples ``kept``); each entry also holds ``sensor`` (1-based) and ``label`` (``sensor_jitter:S``).
    Empty for one sensor or a record without time stamps."""
    if kept.n_sensors < 2 or kept.time_s is None:
        return []
    fields = _model_fields(kept, fit)
    out = []
    for s in range(1, kept.n_sensors):
        est = jitter_estimate(fields[0], fields[s], kept.time_s)
        if est is not None:
            out.append({"effect": "sensor_jitter", "sensor": s + 1, "label": f"sensor_jitter:{s + 1}", **est})
    return out


def jitter_words(est) -> str:
    """One line for the diagnosis's warnings: the jitter in ms and the residual's growth with the turn rate."""
    rms = est["rms_by_rate_quartile_nT"]
    return (
        f"{est['label']}: sensor {est['sensor']} is sampled with {est['jitter_rms_ms']:.3g} +- "
        f"{est['jitter_se_ms']:.2g} ms RMS of jitter against sensor 1: the inter-sensor residual grows from "
        f"{rms[0]:.3g} to {rms[-1]:.3g} nT from the slowest to the fastest turn-rate quartile (a variance "
        f"sigma^2 + (tau |dB/dt|)^2, which no calibration term removes: read the sensors at one instant, or "
        f"stamp each sample)"
    )
