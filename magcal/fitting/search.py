"""Global-search scalar calibration: standard PSO, improved PSO (Ding 2024) and improved differential evolution.

The three methods minimise the same objective, Ding (2024) eq. (17)::

    f = sqrt( mean_i ( |C^-1 (y_i - b)| - F_i )^2 )        (nT)

over the 9 numbers that total-field data can identify (see :mod:`magcal.model.identifiability`): the 6 entries of the
upper-triangular correction matrix ``C^-1`` (order :data:`magcal.core.conventions.UPPER_TRIANGLE`) and the 3 entries of
the offset ``b`` (nT; Ding's integrated zero offset ``I = K C B_h + b``). The searches work in the unit cube that
:class:`SearchBounds` maps onto the parameter box; the box comes from the data's extent (:func:`bounds_from_data`),
not from any preset.

Methods (:data:`METHODS`):

``pso``
    Standard global-best PSO, eqs. (10)-(11) with constant inertia ``w = 0.7298`` and learning factors
    ``c1 = c2 = 1.49618`` (the Clerc-Kennedy constriction values, the usual "standard PSO" settings), uniform random
    initial swarm, velocity clamped to 20 % of the box.
``ipso``
    Improved PSO of Ding (2024): inertia falling linearly ``0.9 -> 0.4`` (eq. 12), individual learning factor falling
    ``2.5 -> 0.5`` and social factor rising ``0.5 -> 2.5`` (eqs. 13-14; the paper gives the schedules but not the end
    values, these are Ratnaweera et al.'s 2004 TVAC values), initial swarm from the Circle chaotic map (eq. 15).
    Eq. (11) is printed as ``x(t+1) = x(t) + v(t)``; we use the new velocity ``v(t+1)`` as in Kennedy & Eberhart.
``de``
    Improved differential evolution for the patent's step S4, built on :func:`scipy.optimize.differential_evolution`
    (strategy ``best1bin`` with the scale factor ``F`` dithered in ``[0.5, 1)`` each generation). The patent says
    only that the DE "search strategy is improved". What we changed from scipy's defaults, and why (figures from
    ``benchmarks/reproduce_ding2024.py``, row ``de-scipy-default``, and ``benchmarks/de_variants.py``):

    * population of ``pop_size`` members (default 30) instead of ``15 x 9 = 135``, started from a Latin hypercube of
      exactly that size: the objective has one smooth basin in the positive-diagonal gauge, so a small population
      finds it as reliably with a quarter to a sixth of the evaluations (5 700 at 40 members, 3 300 at 20, against
      20 400 with 135, to come within 0.1 % of the minimum);
    * crossover rate ``CR = 0.9`` instead of 0.7: the offset and the ``C^-1`` entries are coupled, and crossover
      with a small ``CR`` mostly moves along the parameter axes (14 % fewer evaluations at 40 members, the same at
      20);
    * the stall test shared with the PSOs instead of scipy's ``std(energies) <= 0.01 mean(energies)``, which stops
      while the best member is still ~0.5 % above the minimum when the data are noisy;
    * vectorised evaluation of the whole population (``vectorized=True``, deferred updating) and no gradient
      polishing, so that the figures measure the evolutionary search itself.

    We also tried the published "improvements" a reader would expect - a linearly falling ``F`` (eq. 12 applied to
    DE), ``DE/current-to-best/1``, JADE's adaptive ``F``/``CR`` with an archive, eigenvector crossover and the
    Circle-map initial population; none reduced the evaluations to reach the minimum beyond the run-to-run scatter
    and several increased them (falling ``F`` by 45-85 %, ``rand/1`` 2.5-3.5 fold), so they are not used.

All three evaluate the whole population in one numpy call, are reproducible for a given ``seed``, report
``progress(iteration, best_rms_nT)`` once per iteration and stop early when the best RMS has not improved by a
relative ``tol`` over ``patience`` iterations.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import differential_evolution
from scipy.stats import qmc

from magcal.calibration.calibration import Calibration, SensorCalibration
from magcal.checks.coverage import check_coverage
from magcal.core import conventions
from magcal.core.errors import CalibrationError, MagcalError
from magcal.fitting.fitter import fit_reference
from magcal.geometry.procrustes import procrustes_rotation

#: Method names this module implements.
METHODS = ("pso", "ipso", "de")

#: Names of the 9 searched parameters, in order.
PARAM_NAMES = tuple(f"cinv_{i}{j}" for i, j in conventions.UPPER_TRIANGLE) + ("bias_x_nT", "bias_y_nT", "bias_z_nT")

#: Default population size and iteration limit per method.
DEFAULTS = {
    "pso": {"pop_size": 50, "max_iter": 800},
    "ipso": {"pop_size": 50, "max_iter": 800},
    "de": {"pop_size": 30, "max_iter": 1500},
}


# ----------------------------------------------------------------------------------------------------------------
# Objective
# ----------------------------------------------------------------------------------------------------------------


def unpack(params):
    """Split parameter vectors into ``C^-1`` and offsets.

    Parameters
    ----------
    params : array_like, shape (9,) or (P, 9)
        Upper-triangle entries of ``C^-1`` (dimensionless) then offset ``b`` (nT).

    Returns
    -------
    cinv : numpy.ndarray, shape (3, 3) or (P, 3, 3)
    bias_nT : numpy.ndarray, shape (3,) or (P, 3)
    """
    p = np.asarray(params, dtype=float)
    single = p.ndim == 1
    p = np.atleast_2d(p)
    cinv = np.zeros((p.shape[0], 3, 3))
    for k, (i, j) in enumerate(conventions.UPPER_TRIANGLE):
        cinv[:, i, j] = p[:, k]
    bias = p[:, 6:9].copy()
    return (cinv[0], bias[0]) if single else (cinv, bias)


def pack(cinv, bias_nT):
    """Inverse of :func:`unpack` for one sensor: a (9,) vector."""
    return np.concatenate([conventions.cinv_to_params(cinv), np.asarray(bias_nT, dtype=float)])


class ScalarObjective:
    """Ding (2024) eq. (17) for a whole population at once.

    Parameters
    ----------
    readings_nT : array_like, shape (N, 3)
        Raw readings of one sensor (nT).
    reference_nT : float or array_like, shape (N,)
        Reference total field ``B_a`` (nT), one value or one per sample.

    Attributes
    ----------
    n_evaluations : int
        Number of parameter vectors evaluated so far (one objective evaluation each).
    """

    def __init__(self, readings_nT, reference_nT):
        y = np.asarray(readings_nT, dtype=float)
        self.y = y
        self.reference_nT = np.broadcast_to(np.asarray(reference_nT, dtype=float), (y.shape[0],)).copy()
        self.n_evaluations = 0

    def residuals(self, params):
        """Total-field residuals ``|C^-1 (y - b)| - F`` (nT), shape (P, N) for params (P, 9)."""
        p = np.atleast_2d(np.asarray(params, dtype=float))
        zx = self.y[None, :, 0] - p[:, 6, None]
        zy = self.y[None, :, 1] - p[:, 7, None]
        zz = self.y[None, :, 2] - p[:, 8, None]
        # C^-1 is upper triangular: B = (u00 zx + u01 zy + u02 zz, u11 zy + u12 zz, u22 zz)
        bx = p[:, 0, None] * zx + p[:, 1, None] * zy + p[:, 2, None] * zz
        by = p[:, 3, None] * zy + p[:, 4, None] * zz
        bz = p[:, 5, None] * zz
        return np.sqrt(bx * bx + by * by + bz * bz) - self.reference_nT[None, :]

    def __call__(self, params):
        """RMS total-field residual (nT) of each parameter vector: shape (P,) for params (P, 9)."""
        r = self.residuals(params)
        self.n_evaluations += r.shape[0]
        return np.sqrt(np.mean(r * r, axis=1))


# ----------------------------------------------------------------------------------------------------------------
# Bounds
# ----------------------------------------------------------------------------------------------------------------


@dataclass
class SearchBounds:
    """A box for the 9 parameters; the searches work in the unit cube mapped onto it.

    Parameters
    ----------
    lower, upper : numpy.ndarray, shape (9,)
        Bounds in :data:`PARAM_NAMES` order (``C^-1`` entries dimensionless, offsets in nT).
    """

    lower: np.ndarray
    upper: np.ndarray

    def __post_init__(self):
        self.lower = np.asarray(self.lower, dtype=float)
        self.upper = np.asarray(self.upper, dtype=float)
        if self.lower.shape != (9,) or self.upper.shape != (9,) or np.any(self.upper <= self.lower):
            raise MagcalError("search bounds must be two 9-vectors with every upper bound above its lower bound")

    @property
    def width(self):
        return self.upper - self.lower

    def to_params(self, unit):
        """Map unit-cube points (P, 9) to parameters."""
        return self.lower + np.asarray(unit) * self.width

    def contains(self, params) -> bool:
        p = np.asarray(params, dtype=float)
        return bool(np.all(p >= self.lower) and np.all(p <= self.upper))


def bounds_from_data(readings_nT, reference_nT, offset_margin=0.5, diag_range=(0.5, 2.0), offdiag_margin=0.5):
    """A generous parameter box from the readings' extent alone (no model fit, nothing preset-specific).

    With ``c_j`` the middle of the readings' range on axis ``j`` and ``h_j`` half that range (nT), ``F`` the
    mean reference (nT) and ``g = F / mean(h)``:

    * offset ``b_j`` in ``c_j -/+ offset_margin * h_j`` (the default allows the centre anywhere in the middle half of
      the range: far more than any bias, hard iron, or the bounding-box error of a partial rotation);
    * diagonal ``C^-1_jj`` in ``diag_range * F / h_j`` (positive: this fixes the sign gauge, since flipping the sign
      of a row of ``C^-1`` leaves every total field unchanged);
    * off-diagonal ``C^-1_ij`` in ``-/+ offdiag_margin * g`` (non-orthogonality plus soft iron up to ~30 deg).

    Parameters
    ----------
    readings_nT : array_like, shape (N, 3)
    reference_nT : float or array_like, shape (N,)
    offset_margin, diag_range, offdiag_margin : float
        Margins as described above.

    Returns
    -------
    SearchBounds
    """
    y = np.asarray(readings_nT, dtype=float)
    lo, hi = y.min(axis=0), y.max(axis=0)
    centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    if np.any(half <= 0):
        raise CalibrationError("an axis reads a constant value: the sensor was not rotated (or the axis is dead)")
    f = float(np.mean(reference_nT))
    g = f / float(np.mean(half))
    lower = np.empty(9)
    upper = np.empty(9)
    for k, (i, j) in enumerate(conventions.UPPER_TRIANGLE):
        if i == j:
            lower[k], upper[k] = diag_range[0] * f / half[i], diag_range[1] * f / half[i]
        else:
            lower[k], upper[k] = -offdiag_margin * g, offdiag_margin * g
    lower[6:], upper[6:] = centre - offset_margin * half, centre + offset_margin * half
    return SearchBounds(lower, upper)


# ----------------------------------------------------------------------------------------------------------------
# Initial populations
# ----------------------------------------------------------------------------------------------------------------


def circle_map(x):
    """One step of Ding's Circle chaotic map, eq. (15): ``mod(2x + 0.2 - 0.7/(2 pi) cos(2 pi x + pi/2), 1)``."""
    return np.mod(2.0 * x + 0.2 - (0.7 / (2.0 * np.pi)) * np.cos(2.0 * np.pi * x + 0.5 * np.pi), 1.0)


def circle_population(pop_size, n_dim, rng):
    """Initial population in the unit cube from the Circle map, eq. (15).

    Each dimension starts from a random seed value in (0, 1) and the map is iterated once per particle, so
    particle ``i+1``'s coordinate is the map of particle ``i``'s. A short burn-in discards the seed's transient.

    Returns
    -------
    numpy.ndarray, shape (pop_size, n_dim), values in [0, 1)
    """
    x = rng.uniform(0.0, 1.0, size=n_dim)
    for _ in range(10):  # burn-in
        x = circle_map(x)
    out = np.empty((pop_size, n_dim))
    for i in range(pop_size):
        x = circle_map(x)
        out[i] = x
    return out


# ----------------------------------------------------------------------------------------------------------------
# Searches
# ----------------------------------------------------------------------------------------------------------------


@dataclass
class SearchResult:
    """Outcome of one global search for one sensor.

    Attributes
    ----------
    method : str
    cinv : numpy.ndarray, shape (3, 3)
        Upper-triangular correction matrix (dimensionless).
    bias_nT : numpy.ndarray, shape (3,)
        Offset ``b`` in nT (bias plus ``C`` times platform hard iron).
    rms_nT : float
        Final objective, eq. (17), in nT.
    history_rms_nT : numpy.ndarray, shape (n_iterations + 1,)
        Best RMS (nT) after the initial population and after every iteration.
    n_iterations : int
    n_evaluations : int
        Objective evaluations (one per parameter vector).
    wall_s : float
        Wall-clock time of the search in s.
    stopped_by_tolerance : bool
        True if the search stopped early because the best RMS stalled (rather than at ``max_iter``).
    bounds : SearchBounds
    reference_nT : float
        Mean reference field used (nT).
    """

    method: str
    cinv: np.ndarray
    bias_nT: np.ndarray
    rms_nT: float
    history_rms_nT: np.ndarray
    n_iterations: int
    n_evaluations: int
    wall_s: float
    stopped_by_tolerance: bool
    bounds: SearchBounds
    reference_nT: float
    seed: int | None = None
    extra: dict = field(default_factory=dict)


class _Stall:
    """Stopping rule shared by all methods: stop when the best RMS has not fallen by a relative ``tol`` (or by
    ``atol_nT``) over the last ``patience`` iterations."""

    def __init__(self, tol, patience, atol_nT):
        self.tol, self.patience, self.atol = float(tol), int(patience), float(atol_nT)
        self.history = []

    def update(self, best):
        self.history.append(float(best))
        h = self.history
        if len(h) <= self.patience:
            return False
        old = h[-1 - self.patience]
        return old - h[-1] <= self.tol * abs(old) + self.atol


def _pso(objective, bounds, rng, pop_size, max_iter, improved, progress, stall, coefficients):
    n_dim = 9
    if improved:
        x = circle_population(pop_size, n_dim, rng)
    else:
        x = rng.uniform(0.0, 1.0, size=(pop_size, n_dim))
    v = np.zeros_like(x)
    vmax = coefficients["vmax"]
    f = objective(bounds.to_params(x))
    pbest, pbest_f = x.copy(), f.copy()
    g = int(np.argmin(f))
    gbest, gbest_f = x[g].copy(), float(f[g])
    stall.update(gbest_f)
    if progress:
        progress(0, gbest_f)
    stopped, it = False, 0
    for it in range(1, max_iter + 1):
        if improved:  # eqs. (12)-(14)
            frac = (max_iter - it) / max_iter
            w = coefficients["w_min"] + (coefficients["w_max"] - coefficients["w_min"]) * frac
            c1 = coefficients["c1_min"] + (coefficients["c1_max"] - coefficients["c1_min"]) * frac
            c2 = coefficients["c2_min"] + (coefficients["c2_max"] - coefficients["c2_min"]) * (it / max_iter)
        else:
            w, c1, c2 = coefficients["w"], coefficients["c1"], coefficients["c2"]
        r1 = rng.uniform(size=x.shape)
        r2 = rng.uniform(size=x.shape)
        v = w * v + c1 * r1 * (pbest - x) + c2 * r2 * (gbest - x)  # eq. (10)
        np.clip(v, -vmax, vmax, out=v)
        x = x + v  # eq. (11) with the new velocity
        out = (x < 0.0) | (x > 1.0)
        x = np.clip(x, 0.0, 1.0)
        v[out] = 0.0  # absorbing walls
        f = objective(bounds.to_params(x))
        better = f < pbest_f
        pbest[better], pbest_f[better] = x[better], f[better]
        g = int(np.argmin(pbest_f))
        if pbest_f[g] < gbest_f:
            gbest, gbest_f = pbest[g].copy(), float(pbest_f[g])
        if progress:
            progress(it, gbest_f)
        if stall.update(gbest_f):
            stopped = True
            break
    return bounds.to_params(gbest), gbest_f, it, stopped


def _de(objective, bounds, rng, pop_size, max_iter, progress, stall, coefficients):
    n_dim = 9
    init = bounds.to_params(qmc.LatinHypercube(d=n_dim, rng=rng).random(pop_size))
    state = {"generation": 0, "stopped": False}

    def func(x):  # scipy's vectorised form: x has shape (9, S)
        return objective(np.asarray(x).T)

    def callback(intermediate_result):
        state["generation"] += 1
        best = float(intermediate_result.fun)
        if progress:
            progress(state["generation"], best)
        if stall.update(best):
            state["stopped"] = True
            raise StopIteration

    f0 = float(np.min(objective(init)))
    objective.n_evaluations -= init.shape[0]  # scipy evaluates the initial population itself
    stall.update(f0)
    if progress:
        progress(0, f0)
    res = differential_evolution(
        func,
        list(zip(bounds.lower, bounds.upper)),
        strategy=coefficients["strategy"],
        maxiter=max_iter,
        init=init,
        mutation=tuple(coefficients["F"]),
        recombination=coefficients["CR"],
        tol=0.0,
        atol=0.0,
        polish=False,
        updating="deferred",
        vectorized=True,
        rng=rng.integers(2**63),
        callback=callback,
    )
    return np.asarray(res.x), float(res.fun), state["generation"], state["stopped"]


#: Coefficients of each method (see the module docstring).
COEFFICIENTS: dict[str, dict] = {
    "pso": {"w": 0.7298, "c1": 1.49618, "c2": 1.49618, "vmax": 0.2},
    "ipso": {"w_max": 0.9, "w_min": 0.4, "c1_max": 2.5, "c1_min": 0.5, "c2_max": 2.5, "c2_min": 0.5, "vmax": 0.2},
    "de": {"strategy": "best1bin", "F": (0.5, 1.0), "CR": 0.9},
}


def search(
    readings_nT,
    reference_nT,
    method="ipso",
    seed=None,
    progress=None,
    bounds=None,
    pop_size=None,
    max_iter=None,
    tol=1e-10,
    patience=None,
    atol_nT=0.0,
    coefficients=None,
) -> SearchResult:
    """Global search for one sensor's ``C^-1`` and offset against a reference total field, eq. (17).

    Parameters
    ----------
    readings_nT : array_like, shape (N, 3)
        Raw readings of one sensor (nT).
    reference_nT : float or array_like, shape (N,)
        Reference total field (nT).
    method : {'pso', 'ipso', 'de'}
    seed : int, optional
        Seed; the same seed and data give the same result.
    progress : callable, optional
        ``progress(iteration, best_rms_nT)``, called after the initial population (iteration 0) and every iteration.
    bounds : SearchBounds, optional
        Parameter box; default :func:`bounds_from_data`.
    pop_size, max_iter : int, optional
        Population size and iteration limit (defaults in :data:`DEFAULTS`).
    tol, patience, atol_nT : float, int, float
        Stop when the best RMS has fallen by no more than ``tol * rms + atol_nT`` over the last ``patience``
        iterations (default patience: ``max(50, max_iter // 10)``).
    coefficients : dict, optional
        Overrides of :data:`COEFFICIENTS` for this method.

    Returns
    -------
    SearchResult
    """
    if method not in METHODS:
        raise MagcalError(f"unknown search method {method!r}; choose one of {', '.join(METHODS)}")
    y = np.asarray(readings_nT, dtype=float)
    if y.ndim != 2 or y.shape[1] != 3:
        raise MagcalError(f"readings must have shape (N, 3), got {y.shape}")
    if y.shape[0] < 10:
        raise CalibrationError(f"{y.shape[0]} samples are too few for 9 parameters: record at least 10 attitudes")
    if not np.all(np.isfinite(y)):
        raise CalibrationError("the readings contain NaN or infinite values: remove those rows first")
    pop_size = int(pop_size or DEFAULTS[method]["pop_size"])
    max_iter = int(max_iter or DEFAULTS[method]["max_iter"])
    if pop_size < 4:
        raise MagcalError("the population needs at least 4 members")
    patience = int(patience or max(50, max_iter // 10))
    coeffs = dict(COEFFICIENTS[method], **(coefficients or {}))
    objective = ScalarObjective(y, reference_nT)
    bounds = bounds or bounds_from_data(y, objective.reference_nT)
    rng = np.random.default_rng(seed)
    stall = _Stall(tol, patience, atol_nT)
    t0 = time.perf_counter()
    if method == "de":
        best, best_f, n_it, stopped = _de(objective, bounds, rng, pop_size, max_iter, progress, stall, coeffs)
    else:
        best, best_f, n_it, stopped = _pso(
            objective, bounds, rng, pop_size, max_iter, method == "ipso", progress, stall, coeffs
        )
    wall = time.perf_counter() - t0
    cinv, bias = unpack(best)
    return SearchResult(
        method=method,
        cinv=cinv,
        bias_nT=bias,
        rms_nT=float(best_f),
        history_rms_nT=np.array(stall.history),
        n_iterations=int(n_it),
        n_evaluations=int(objective.n_evaluations),
        wall_s=wall,
        stopped_by_tolerance=bool(stopped),
        bounds=bounds,
        reference_nT=float(np.mean(objective.reference_nT)),
        seed=seed,
    )


# ----------------------------------------------------------------------------------------------------------------
# Public entry: a Calibration from a Dataset
# ----------------------------------------------------------------------------------------------------------------


@dataclass
class SearchCalibration:
    """What :func:`search_calibrate` found: the calibration and what its checks said.

    Attributes
    ----------
    calibration : magcal.calibration.calibration.Calibration
        ``summary`` holds ``method``, ``seed``, ``n_samples``, ``rms_nT`` (per sensor), ``n_evaluations``,
        ``n_iterations`` and ``search_wall_s``; each sensor's ``summary`` its own figures.
    notes : list of Note
        What the checks found (poor coverage: a :class:`~magcal.core.errors.CoverageWarning` note), never raised
        here: :func:`magcal.calibrate` (``method="pso"`` ...) and the command line say them.
    """

    calibration: Calibration
    notes: list = field(default_factory=list)


def search_calibrate(
    dataset,
    method="ipso",
    seed=None,
    progress=None,
    mask=None,
    reference_total_nT=None,
    max_iter=None,
    pop_size=None,
    tol=1e-10,
    patience=None,
    bounds=None,
) -> SearchCalibration:
    """Scalar calibration of every sensor by global search (eq. 17), then Procrustes alignment for arrays.

    Each sensor's ``C^-1`` (upper triangular) and offset are searched against the reference total field; for two
    or more sensors the rotations ``R`` into sensor 1's frame then come from orthogonal Procrustes on the corrected
    vectors (:func:`magcal.geometry.procrustes.procrustes_rotation`), as in the two-step method. Total-field data fix
    nothing else (see :mod:`magcal.model.identifiability`).

    Parameters
    ----------
    dataset : Dataset
    method : {'pso', 'ipso', 'de'}
    seed : int, optional
        Seed of the search (sensor ``s`` uses ``seed + s``); same seed and data give the same calibration.
    progress : callable, optional
        ``progress(iteration, best_rms_nT)``. For arrays the iteration counts on across sensors: sensor ``s``
        (0-based) reports ``s * max_iter + k``; so ``n_sensors * max_iter`` is an upper bound on the count.
    mask : array_like of bool, shape (N,), optional
        Samples to use (True = use).
    reference_total_nT : float, optional
        Reference field (nT). Default: the dataset's per-sample ``ref_total`` column, else its
        ``reference_total_nT`` metadata, else unknown: then sensor 1's ``C^-1`` is scaled to unit determinant
        (as :mod:`magcal.fitting.fitter` does) and the field magnitude that gives is the reference for the other sensors.
    max_iter, pop_size : int, optional
        Iteration limit and population size (method defaults in :data:`DEFAULTS`).
    tol, patience : see :func:`search`.
    bounds : SearchBounds or list of SearchBounds, optional
        Override the data-derived box (one for all sensors, or one per sensor).

    Raises
    ------
    MagcalError
        Unknown method, a mask of the wrong length, too few samples, or readings from a rotation about one axis
        (``DatasetError``: they do not determine the 9 numbers). Poor coverage is a note (below).

    Returns
    -------
    SearchCalibration
        ``.calibration`` and ``.notes``.
    """

    if method not in METHODS:
        raise MagcalError(f"unknown search method {method!r}; choose one of {', '.join(METHODS)}")
    ds = dataset
    if mask is not None:
        mask = np.asarray(mask, dtype=bool).reshape(-1)
        if mask.shape[0] != ds.n_samples:
            raise MagcalError(f"the mask has {mask.shape[0]} entries but the data have {ds.n_samples} samples")
        ds = ds.subset(mask)
    notes = check_coverage(ds, full_model=True).notes  # refuses rotation about one axis; notes poor coverage
    ref, kind = fit_reference(ds, reference_total_nT)
    if kind == "column":
        target = ds.ref_total_nT
    elif kind == "given":
        target = float(ref)
    else:  # fitted: provisional magnitude from sensor 1's extent, rescaled to det C^-1 = 1 after its search
        y0 = ds.readings_nT[0]
        target = float(np.prod(0.5 * (y0.max(axis=0) - y0.min(axis=0))) ** (1.0 / 3.0))
    max_iter = int(max_iter or DEFAULTS[method]["max_iter"])
    per_sensor_bounds = bounds if isinstance(bounds, (list, tuple)) else [bounds] * ds.n_sensors

    sensors, results = [], []
    for s in range(ds.n_sensors):
        offset = s * max_iter
        report = None if progress is None else (lambda it, best, _o=offset: progress(_o + it, best))
        res = search(
            ds.readings_nT[s],
            target,
            method=method,
            seed=None if seed is None else int(seed) + s,
            progress=report,
            bounds=per_sensor_bounds[s],
            pop_size=pop_size,
            max_iter=max_iter,
            tol=tol,
            patience=patience,
        )
        cinv, rms = res.cinv, res.rms_nT
        if kind == "fitted" and s == 0:
            gain = float(np.linalg.det(cinv)) ** (-1.0 / 3.0)
            cinv, rms, target = cinv * gain, rms * gain, target * gain
        results.append(res)
        sensors.append(
            SensorCalibration(
                cinv,
                res.bias_nT,
                np.eye(3),
                summary={
                    "rms_nT": rms,
                    "n_evaluations": res.n_evaluations,
                    "n_iterations": res.n_iterations,
                    "search_wall_s": res.wall_s,
                },
            )
        )
    if ds.n_sensors > 1:
        corrected = [(ds.readings_nT[s] - c.bias_nT) @ c.cinv.T for s, c in enumerate(sensors)]
        for s in range(1, ds.n_sensors):
            sensors[s].R = procrustes_rotation(corrected[0], corrected[s], label=f"sensor {s + 1}")
    summary = {
        "method": method,
        "seed": seed,
        "n_samples": int(ds.n_samples),
        "rms_nT": [c.summary["rms_nT"] for c in sensors],
        "n_evaluations": int(sum(r.n_evaluations for r in results)),
        "n_iterations": [r.n_iterations for r in results],
        "search_wall_s": float(sum(r.wall_s for r in results)),
    }
    calibration = Calibration(
        sensors=sensors,
        reference_total_nT=None if kind == "column" else float(target),
        reference_fitted=kind == "fitted",
        baseline_m=ds.baseline_m,
        summary=summary,
    )
    return SearchCalibration(calibration, notes)
