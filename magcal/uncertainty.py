"""The calibration's error bars carried to the corrected field and the tensor, sample by sample.

A maximum-likelihood fit has a parameter covariance (:attr:`magcal.fit.FitResult.covariance`, ``s^2 (J^T J)^-1``).
Per sensor the base correction is ``B = M (y - b)`` with ``M = R C^-1``, so a small error in the parameters moves
the corrected field by ``dB = dM z - M db`` (``z = y - b``): linear in the 12 numbers ``theta_s = (M_s`` row by row,
``b_s)``. :func:`base_covariance` carries the fit's covariance to ``theta`` of every sensor (their joint
``12 n_s x 12 n_s`` covariance, cross-sensor terms included: the misalignment couples the sensors) through the
Jacobian of the fitted parameters' map to ``theta`` (numerical, by the fit's own parameterisation). The calibration
keeps it (:attr:`magcal.calibration.Calibration.base_covariance`, saved in the JSON), and
:func:`field_uncertainty` propagates it to each sample: the standard deviation of every corrected component and of
``|B|`` per sensor (nT), and of each tensor component (nT/m), from the same linear map.

The effect terms' own parameter errors are not included (their Jacobians are the effects' bases; the base terms
carry most of the error of a well-covered calibration). Nor is the noise of the sample itself: these are the
calibration's error bars, common to every survey it corrects.
"""

from __future__ import annotations

import numpy as np

from . import conventions
from .vectors import row_norm

#: Numbers per sensor in ``theta``: ``M`` row by row (9), then the bias (3).
THETA_PER_SENSOR = 12


def theta_of(sensors) -> np.ndarray:
    """``theta`` of a list of :class:`~magcal.calibration.SensorCalibration`: per sensor ``M = R C^-1`` row by row
    and the bias (nT), concatenated."""
    return np.concatenate([np.concatenate([(s.R @ s.cinv).ravel(), s.bias_nT]) for s in sensors])


def base_covariance(fit_result) -> np.ndarray | None:
    """The covariance of ``theta`` (:func:`theta_of`) implied by a fit's parameter covariance, or None.

    Parameters
    ----------
    fit_result : magcal.fit.FitResult

    Returns
    -------
    numpy.ndarray, shape (12 n_sensors, 12 n_sensors) or None
        None when the fit has no finite covariance.
    """
    cov = getattr(fit_result, "covariance", None)
    problem, x = getattr(fit_result, "problem", None), getattr(fit_result, "x", None)
    if cov is None or problem is None or x is None or not np.all(np.isfinite(cov)):
        return None
    x = np.asarray(x, float)
    t0 = theta_of(problem.sensors(x))
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    jac = np.zeros((t0.size, x.size))
    for p in range(x.size):
        h = max(1e-3 * sd[p], 1e-9 * max(abs(x[p]), 1.0))
        if h == 0 or not np.isfinite(h):
            continue
        xp, xm = x.copy(), x.copy()
        xp[p] += h
        xm[p] -= h
        jac[:, p] = (theta_of(problem.sensors(xp)) - theta_of(problem.sensors(xm))) / (2 * h)
    out = jac @ cov @ jac.T
    return 0.5 * (out + out.T)


def _factor(cov) -> np.ndarray:
    """``L`` with ``L L^T = cov`` (eigen-decomposition, negative rounding clipped)."""
    w, v = np.linalg.eigh(np.asarray(cov, float))
    keep = w > 1e-15 * max(w.max(), 1e-300)
    return v[:, keep] * np.sqrt(w[keep])


def tensor_map(n_sensors: int, baseline_m: float) -> tuple[list, np.ndarray]:
    """The tensor components as a linear map of the stacked corrected vectors: ``(names, T)``, ``T`` of shape
    (components, 3 n_sensors), from :func:`magcal.conventions.tensor_components` itself."""
    cols = []
    names = None
    for j in range(3 * n_sensors):
        e = np.zeros((n_sensors, 1, 3))
        e.flat[j] = 1.0
        comps = conventions.tensor_components(e, baseline_m)
        names = list(comps) if names is None else names
        cols.append([float(np.asarray(comps[k]).ravel()[0]) for k in names])
    return names, np.array(cols).T


def field_uncertainty(calibration, dataset, corrected_nT=None) -> dict | None:
    """Standard deviations of the corrected field and the tensor from the calibration's base covariance.

    Parameters
    ----------
    calibration : Calibration
        With :attr:`~magcal.calibration.Calibration.base_covariance` (an ML fit's); None is returned without it.
    dataset : Dataset
        The data corrected (raw readings nT).
    corrected_nT : numpy.ndarray, shape (n_sensors, N, 3), optional
        ``calibration.correct(dataset)`` if already computed (for the direction of ``|B|``).

    Returns
    -------
    dict or None
        ``vector_sd_nT`` (n_sensors, N, 3), ``total_sd_nT`` (n_sensors, N) and, for a four-sensor array with a
        baseline, ``tensor_sd_nT_per_m``: {component: (N,)}.
    """
    cov = getattr(calibration, "base_covariance", None)
    if cov is None:
        return None
    ns = calibration.n_sensors
    L = _factor(cov)                                  # (12 ns, r)
    y = np.asarray(dataset.readings_nT, float)
    n = y.shape[1]
    if corrected_nT is None:
        corrected_nT = calibration.correct(dataset)
    H = np.empty((n, 3 * ns, L.shape[1]))
    for s, sc in enumerate(calibration.sensors):
        z = y[s] - sc.bias_nT                          # (N, 3)
        M = sc.R @ sc.cinv
        rows = L[THETA_PER_SENSOR * s: THETA_PER_SENSOR * (s + 1)]   # (12, r)
        # dB_k = sum_j z_j dM_kj - sum_j M_kj db_j
        for k in range(3):
            H[:, 3 * s + k] = z @ rows[3 * k: 3 * k + 3] - (M[k] @ rows[9:12])[None, :]
    vector_sd = np.sqrt(np.sum(H * H, axis=2)).reshape(n, ns, 3).transpose(1, 0, 2)
    unit = corrected_nT / row_norm(corrected_nT)[..., None]
    total = np.einsum("snk,nskr->snr", unit, H.reshape(n, ns, 3, -1))
    out = {"vector_sd_nT": vector_sd, "total_sd_nT": np.sqrt(np.sum(total * total, axis=2))}
    if ns == 4 and calibration.baseline_m:
        names, T = tensor_map(ns, float(calibration.baseline_m))
        G = np.einsum("ck,nkr->ncr", T, H)
        sd = np.sqrt(np.sum(G * G, axis=2))
        out["tensor_sd_nT_per_m"] = {name: sd[:, i] for i, name in enumerate(names)}
    return out
