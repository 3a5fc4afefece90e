"""The calibration's error bars carried to the corrected field and the tensor, sample by sample.

A maximum-likelihood fit has a parameter covariance (:attr:`magcal.fitting.fitter.FitResult.covariance`, ``s^2 (J^T J)^-1``).
Per sensor the base correction is ``B = M (y - b)`` with ``M = R C^-1``, so a small error in the parameters moves
the corrected field by ``dB = dM z - M db`` (``z = y - b``): linear in the 12 numbers ``theta_s = (M_s`` row by row,
``b_s)``. :func:`base_covariance` carries the fit's covariance to ``theta`` of every sensor (their joint
``12 n_s x 12 n_s`` covariance, cross-sensor terms included: the misalignment couples the sensors) through the
Jacobian of the fitted parameters' map to ``theta`` (numerical, by the fit's own parameterisation). The calibration
keeps it (:attr:`magcal.calibration.calibration.Calibration.base_covariance`, saved in the JSON), and
:func:`field_uncertainty` propagates it to each sample: the standard deviation of every corrected component and of
``|B|`` per sensor (nT), and of each tensor component (nT/m), from the same linear map.

With effect terms in the model the covariance is the joint one of ``theta`` and the effects' parameters (in the
order of the model's instances, :func:`effect_layout`), so their errors and their correlation with the base terms
are carried too: a raw-stage effect moves the corrected field by ``-M basis dp`` and shifts ``z`` in ``dM z``, a
array-stage effect by ``basis dp``; reference-stage effects change only the expected field, not the corrected
one. A record-only effect that ``correct`` drops on other data drops out of its error bars too. Not included: the
noise of the sample itself (these are the calibration's error bars, common to every survey it corrects).
"""

from __future__ import annotations

import numpy as np

from magcal.core import conventions
from magcal.core.rows import basis_times, unit_rows
from magcal.model.terms import CORRECTION_STAGES, block_label, contexts

#: Numbers per sensor in ``theta``: ``M`` row by row (9), then the bias (3).
THETA_PER_SENSOR = 12


def theta_of(sensors) -> np.ndarray:
    """``theta`` of a list of :class:`~magcal.calibration.calibration.SensorCalibration`: per sensor ``M = R C^-1`` row by row
    and the bias (nT), concatenated."""
    return np.concatenate([np.concatenate([(s.R @ s.cinv).ravel(), s.bias_nT]) for s in sensors])


def effect_layout(model) -> list:
    """``(label, effect, sensor, n_params)`` of every effect instance of ``model`` in the order their parameters
    follow ``theta`` in :attr:`~magcal.calibration.calibration.Calibration.base_covariance` (the fitter's own order)."""

    if model is None:
        return []
    return [(block_label(e, es), e, es, len(e.param_names())) for e, es in model.instances()]


def covariance_size(n_sensors, model) -> int:
    """Rows of a joint covariance of ``theta`` and the effects' parameters (:func:`base_covariance`)."""
    return THETA_PER_SENSOR * n_sensors + sum(q for *_, q in effect_layout(model))


def base_covariance(fit_result) -> np.ndarray | None:
    """The covariance of ``theta`` (:func:`theta_of`), followed by the effects' parameters (:func:`effect_layout`),
    implied by a fit's parameter covariance, or None.

    Parameters
    ----------
    fit_result : magcal.fitting.fitter.FitResult

    Returns
    -------
    numpy.ndarray, shape (12 n_sensors + q, 12 n_sensors + q) or None
        ``q`` the number of effect parameters (0 for the base model); None when the fit has no finite covariance.
    """
    cov = getattr(fit_result, "covariance", None)
    problem, x = getattr(fit_result, "problem", None), getattr(fit_result, "x", None)
    if cov is None or problem is None or x is None or not np.all(np.isfinite(cov)):
        return None
    x = np.asarray(x, float)
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    jac = np.zeros((THETA_PER_SENSOR * problem.n_sensors, x.size))
    for s in range(problem.n_sensors):  # sensor s's theta depends only on its own base columns
        theta_rows = slice(THETA_PER_SENSOR * s, THETA_PER_SENSOR * (s + 1))
        block = problem.blocks[f"sensor{s + 1}/base"]
        for p in range(block.start, block.stop):
            h = max(1e-3 * sd[p], 1e-9 * max(abs(x[p]), 1.0))
            if h == 0 or not np.isfinite(h):
                continue
            xp, xm = x.copy(), x.copy()
            xp[p] += h
            xm[p] -= h
            jac[theta_rows, p] = (theta_of([problem.sensor(xp, s)]) - theta_of([problem.sensor(xm, s)])) / (2 * h)
    rows = [jac]
    for label, *_ in effect_layout(problem.model):  # the effects' parameters are the fit's own
        block = problem.blocks[label]
        select = np.zeros((block.stop - block.start, x.size))
        select[np.arange(block.stop - block.start), np.arange(block.start, block.stop)] = 1.0
        rows.append(select)
    jac = np.vstack(rows)
    out = jac @ cov @ jac.T
    return 0.5 * (out + out.T)


def _factor(cov) -> np.ndarray:
    """``L`` with ``L L^T = cov`` (eigen-decomposition, negative rounding clipped)."""
    w, v = np.linalg.eigh(np.asarray(cov, float))
    keep = w > 1e-15 * max(w.max(), 1e-300)
    return v[:, keep] * np.sqrt(w[keep])


def tensor_map(n_sensors: int, baseline_m: float) -> tuple[list, np.ndarray]:
    """The tensor components as a linear map of the stacked corrected vectors: ``(names, T)``, ``T`` of shape
    (components, 3 n_sensors), from :func:`magcal.core.conventions.tensor_components` itself."""
    cols = []
    names: list = []
    for j in range(3 * n_sensors):
        e = np.zeros((n_sensors, 1, 3))
        e.flat[j] = 1.0
        comps = conventions.tensor_components(e, baseline_m)
        names = names or list(comps)
        cols.append([float(np.asarray(comps[k]).ravel()[0]) for k in names])
    return names, np.array(cols).T


def field_uncertainty(calibration, dataset, corrected_nT=None, record_terms=None) -> dict | None:
    """Standard deviations of the corrected field and the tensor from the calibration's covariance.

    Parameters
    ----------
    calibration : Calibration
        With :attr:`~magcal.calibration.calibration.Calibration.base_covariance` (an ML fit's); None is returned without it.
    dataset : Dataset
        The data corrected (raw readings nT).
    corrected_nT : numpy.ndarray, shape (n_sensors, N, 3), optional
        ``calibration.correct(dataset, record_terms)`` if already computed (for the direction of ``|B|``).
    record_terms : {None, 'apply', 'drop'}
        As in :meth:`~magcal.calibration.calibration.Calibration.correct`: the effects that act on these data are those whose
        errors count.

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
    L = _factor(cov)  # (12 ns [+ q], r)
    y = np.asarray(dataset.readings_nT, float)
    n = y.shape[1]
    if corrected_nT is None:
        corrected_nT = calibration.correct(dataset, record_terms, force=True)
    # the effects acting on these data, and where each one's parameters sit in the covariance (a covariance of
    # theta alone, from a file made before the effects' errors were kept, carries none of them)
    acting = calibration._model_for(dataset, record_terms, CORRECTION_STAGES, warn=False) if calibration.model else None
    acting_labels = {label for label, *_ in effect_layout(acting)}
    rows_of, at = {}, THETA_PER_SENSOR * ns
    for label, _e, _es, q in effect_layout(calibration.model):
        rows_of[label] = slice(at, at + q)
        at += q
    joint = cov.shape[0] == at and at > THETA_PER_SENSOR * ns
    effects = [
        (label, e, es)
        for label, e, es, _ in effect_layout(calibration.model)
        if joint and label in acting_labels and e.stage in ("raw", "array")
    ]
    ctxs = contexts(dataset, calibration.baseline_m) if effects else []
    values = calibration.effect_values or {}
    H = np.empty((n, 3 * ns, L.shape[1]))
    for s, sc in enumerate(calibration.sensors):
        z0 = y[s] - sc.bias_nT  # (N, 3)
        M = sc.R @ sc.cinv
        mine = [(label, e) for label, e, es in effects if es == s or (es is None and e.applies_to(s))]
        z = z0
        raw = []
        for label, e in mine:
            if e.stage == "raw":
                basis = e.raw_basis(z0, ctxs[s])
                z = z - basis_times(basis, values[label])
                raw.append((label, basis))
        rows = L[THETA_PER_SENSOR * s : THETA_PER_SENSOR * (s + 1)]  # (12, r)
        # dB_k = sum_j z_j dM_kj - sum_j M_kj db_j
        for k in range(3):
            H[:, 3 * s + k] = z @ rows[3 * k : 3 * k + 3] - (M[k] @ rows[9:12])[None, :]
        part = H[:, 3 * s : 3 * s + 3]
        for label, basis in raw:  # dB = -M basis dp
            part -= np.einsum("kj,njq,qr->nkr", M, basis, L[rows_of[label]], optimize=True)
        b_rot = z @ M.T
        for label, e in mine:
            if e.stage == "array":  # dB = basis dp
                part += np.einsum("nkq,qr->nkr", e.array_basis(b_rot, ctxs[s]), L[rows_of[label]], optimize=True)
    vector_sd = np.sqrt(np.sum(H * H, axis=2)).reshape(n, ns, 3).transpose(1, 0, 2)
    unit = unit_rows(corrected_nT)
    total = np.einsum("snk,nskr->snr", unit, H.reshape(n, ns, 3, -1))
    out = {"vector_sd_nT": vector_sd, "total_sd_nT": np.sqrt(np.sum(total * total, axis=2))}
    if ns == 4 and calibration.baseline_m:
        names, T = tensor_map(ns, float(calibration.baseline_m))
        G = np.einsum("ck,nkr->ncr", T, H)
        sd = np.sqrt(np.sum(G * G, axis=2))
        out["tensor_sd_nT_per_m"] = {name: sd[:, i] for i, name in enumerate(names)}
    return out
