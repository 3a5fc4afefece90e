"""Step 1 of the two-step calibration, per sensor: fit an ellipsoid to the raw readings.

In a uniform field of magnitude ``F`` the raw readings ``y = C B + b`` of one sensor lie on the ellipsoid
``(y - b)^T A (y - b) = F^2`` with ``A = C^-T C^-1`` (Chi et al. 2017, eqs. 6-7). Writing it as the general
quadric of eq. (8)::

    a x^2 + b y^2 + c z^2 + 2f yz + 2g xz + 2h xy + 2p x + 2q y + 2r z + d = 0,
    M = [[a, h, g], [h, b, f], [g, f, c]],   n = (p, q, r)

the centre is ``b = -M^-1 n`` (eq. 12) and the ellipsoid is ``(y - b)^T M (y - b) = b^T M b - d`` (eq. 13), so
the unit-field matrix ``A_1 = M / (b^T M b - d)`` does not depend on the scale (or sign) of the coefficient vector.
``A = F^2 A_1`` and its Cholesky factor (:func:`magcal.core.conventions.cinv_from_quadric`) is the upper-triangular
``C^-1`` of the seed's convention.

Two estimators of the coefficients:

``"algebraic"``
    The seed's linear least squares on eq. (8). The seed divides eq. (8) by ``p`` (eq. 9), which is unstable
    when the bias' x component is near zero; here the trace ``a + b + c`` is fixed instead. The trace of an
    ellipsoid's matrix cannot vanish and is unchanged by rotating or translating the data, so the fit does not
    depend on the sensor's orientation or bias.
``"li-griffiths"``
    Li & Griffiths (2004), "Least squares ellipsoid specific fitting": minimise the algebraic distance subject to
    ``4J - I^2 = 1`` (``I = a+b+c``, ``J = ab+bc+ca-f^2-g^2-h^2``). ``4J - I^2 > 0`` implies an ellipsoid, and
    every ellipsoid whose short semi-axis is at least half its long one (every magnetometer's) satisfies it, so the
    constraint costs nothing here and the result is always an ellipsoid. Solved as a generalised eigenproblem with
    :func:`scipy.linalg.eig`.

Both fits run on centred, scaled coordinates (mean removed, divided by the RMS radius) for conditioning; the
result is mapped back to nT.

Field magnitude: with a known reference ``F`` the fit uses it. Without one the magnitude is *fitted*: ``F`` is
set to the geometric mean of the ellipsoid's semi-axes, ``det(A_1)^(-1/6)``, so that ``det C^-1 = 1`` (the
three sensitivities average to one in the geometric-mean sense). Total-field data cannot separate a common gain
from the field magnitude; the result says ``field_fitted=True`` and the reports say so.

The fit refuses (:class:`magcal.core.errors.CalibrationError`) too few samples, readings that do not lie on an
ellipsoid, and coverage too poor to determine one (e.g. rotation about one axis only).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import scipy.linalg

from magcal.core import conventions
from magcal.core.errors import CalibrationError
from magcal.core.rows import row_norm, unit_rows
from magcal.core.stats import robust_sigma
from magcal.geometry.sphere import direction_cover, sphere_centre

#: Fewest samples accepted: 9 parameters plus one degree of freedom to measure a residual.
MIN_SAMPLES = 10

#: Refuse when the thinnest spread of the corrected field directions (smallest eigenvalue of their covariance,
#: 1/3 for full-sphere coverage, 0 when the directions lie on one circle) is below this.
MIN_DIRECTION_SPREAD = 1e-3

#: Warn (but fit) when the thinnest direction spread is below this: the fit extrapolates to unseen directions.
WEAK_DIRECTION_SPREAD = 2e-2

#: Refuse when the readings deviate from the fitted ellipsoid by more than this fraction of the field (RMS).
MAX_RELATIVE_RMS = 0.05

#: Names of the estimators.
METHODS = ("algebraic", "li-griffiths")

#: Number of equal-area sky cells used for the coverage fraction.
SKY_CELLS = 32


@dataclass
class DirectionSpread:
    """How well the samples cover the sphere of field directions (in the corrected sensor frame).

    Attributes
    ----------
    spread_eigenvalues : numpy.ndarray, shape (3,)
        Eigenvalues of the covariance of the unit field directions, descending. Full-sphere coverage gives
        1/3 each; directions on one circle (rotation about one axis) give a smallest value near 0.
    sky_fraction : float
        Fraction of :data:`SKY_CELLS` equal-area cells of the sphere that hold at least one sample.
    """

    spread_eigenvalues: np.ndarray
    sky_fraction: float

    @property
    def thinnest_spread(self) -> float:
        """Smallest eigenvalue of the direction covariance (1/3 for full coverage)."""
        return float(self.spread_eigenvalues[-1])


@dataclass
class EllipsoidFit:
    """Result of the step-1 ellipsoid fit of one sensor.

    Attributes
    ----------
    cinv : numpy.ndarray, shape (3, 3)
        Upper-triangular correction matrix ``C^-1`` (positive diagonal), dimensionless.
    bias_nT : numpy.ndarray, shape (3,)
        Bias ``b`` (ellipsoid centre) in nT.
    field_nT : float
        Field magnitude the correction maps to, nT.
    field_fitted : bool
        True if ``field_nT`` was fitted (no reference given): then ``det C^-1 = 1`` fixes the common gain.
    method : str
        ``"algebraic"`` or ``"li-griffiths"``.
    A : numpy.ndarray, shape (3, 3)
        Ellipsoid matrix ``C^-T C^-1``, so that ``(y - b)^T A (y - b) = field_nT^2`` on the ellipsoid (1/nT^0).
    rms_nT : float
        RMS of ``|C^-1 (y - b)| - field_nT`` over the fitted samples, nT.
    n_samples : int
        Number of samples used.
    coverage : DirectionSpread
        How the samples' directions spread over the sphere.
    warnings : list of str
        Non-fatal concerns (weak coverage).
    """

    cinv: np.ndarray
    bias_nT: np.ndarray
    field_nT: float
    field_fitted: bool
    method: str
    A: np.ndarray
    rms_nT: float
    n_samples: int
    coverage: DirectionSpread
    warnings: list = field(default_factory=list)

    def correct(self, readings_nT) -> np.ndarray:
        """Corrected vectors ``C^-1 (y - b)`` (N, 3) in nT in the sensor's ideal frame."""
        return (np.asarray(readings_nT, dtype=float) - self.bias_nT) @ self.cinv.T

    def with_field(self, field_nT: float, fitted: bool | None = None, readings_nT=None) -> EllipsoidFit:
        """The same ellipsoid mapped to another field magnitude (``C^-1`` scales with ``field_nT``).

        Parameters
        ----------
        field_nT : float
            New field magnitude in nT.
        fitted : bool, optional
            New ``field_fitted`` flag (unchanged if omitted).
        readings_nT : array_like, shape (N, 3), optional
            Samples to recompute ``rms_nT`` on; without them ``rms_nT`` is scaled.
        """
        ratio = float(field_nT) / self.field_nT
        new = replace(
            self,
            cinv=self.cinv * ratio,
            A=self.A * ratio**2,
            field_nT=float(field_nT),
            field_fitted=self.field_fitted if fitted is None else bool(fitted),
            rms_nT=self.rms_nT * ratio,
            warnings=list(self.warnings),
        )
        if readings_nT is not None:
            new.rms_nT = _rms(row_norm(new.correct(readings_nT)) - new.field_nT)
        return new


def _rms(x) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


def _design(points):
    """Rows ``[x^2, y^2, z^2, 2yz, 2xz, 2xy, 2x, 2y, 2z, 1]`` of eq. (8)."""
    x, y, z = points.T
    return np.column_stack([x * x, y * y, z * z, 2 * y * z, 2 * x * z, 2 * x * y, 2 * x, 2 * y, 2 * z, np.ones_like(x)])


#: Samples an ellipsoid start takes at most (an even subsample) when maximum likelihood refines it on every sample:
#: its parameters' scatter is then sqrt(N / 1e5) times the full fit's, far inside the refinement's reach.
START_MAX_SAMPLES = 100_000

#: Rows per block when a design matrix is reduced to its Gram matrix: a block's rows stay in cache, so a
#: million samples cost two passes over the readings instead of a dozen over (N, 10) temporaries.
BLOCK_ROWS = 1 << 14


def _blockwise(points, rows, reduce):
    """``sum_blocks reduce(rows(points[block]))`` over blocks of :data:`BLOCK_ROWS` samples."""
    total = None
    for start in range(0, len(points), BLOCK_ROWS):
        part = reduce(rows(points[start : start + BLOCK_ROWS]))
        total = part if total is None else total + part
    return total


def _algebraic_rows(points):
    """Rows ``[x^2 - z^2, y^2 - z^2, 2yz, 2xz, 2xy, 2x, 2y, 2z, 1 | -3 z^2]`` of eq. (8) with ``a + b + c = 3``."""
    x, y, z = points.T
    out = np.empty((len(points), 10))
    zz = z * z
    np.subtract(x * x, zz, out=out[:, 0])
    np.subtract(y * y, zz, out=out[:, 1])
    np.multiply(y, 2 * z, out=out[:, 2])
    np.multiply(x, 2 * z, out=out[:, 3])
    np.multiply(x, 2 * y, out=out[:, 4])
    np.multiply(points, 2.0, out=out[:, 5:8])
    out[:, 8] = 1.0
    np.multiply(zz, -3.0, out=out[:, 9])
    return out


def _least_squares_blockwise(points, rows):
    """``argmin |a x - b|`` where ``rows(block)`` gives ``[a | b]`` for a block of points: normal equations on
    scaled columns, accumulated block by block, with one step of iterative refinement (the residual ``b - a x``
    recomputed from the rows, so the normal equations' rounding is removed; the same solution as an SVD of
    ``a`` to rounding); ``numpy.linalg.lstsq`` of the whole design when the scaled Gram matrix is
    ill-conditioned."""
    full = _blockwise(points, rows, lambda m: m.T @ m)
    gram, rhs = full[:-1, :-1], full[:-1, -1]
    scale = np.sqrt(np.diag(gram))
    scale[scale == 0] = 1.0
    gram_n = gram / np.outer(scale, scale)
    if np.linalg.cond(gram_n) > 1e10:
        m = rows(points)
        return np.linalg.lstsq(m[:, :-1], m[:, -1], rcond=None)[0]
    xn = np.linalg.solve(gram_n, rhs / scale)
    x = xn / scale
    correction = _blockwise(points, rows, lambda m: m[:, :-1].T @ (m[:, -1] - m[:, :-1] @ x))
    return x + np.linalg.solve(gram_n, correction / scale) / scale


def _coefficients_algebraic(points):
    """Linear least squares for eq. (8) with the trace ``a + b + c`` fixed to 3."""
    # a x^2 + b y^2 + (3 - a - b) z^2 + ... = 0  ->  a (x^2 - z^2) + b (y^2 - z^2) + ... = -3 z^2
    sol = _least_squares_blockwise(points, _algebraic_rows)
    a, b = sol[0], sol[1]
    return np.concatenate([[a, b, 3.0 - a - b], sol[2:]])


#: Li & Griffiths' constraint matrix for k = 4: v1^T C1 v1 = 4J - I^2.
_LI_GRIFFITHS_C1 = np.block(
    [
        [np.array([[-1.0, 1.0, 1.0], [1.0, -1.0, 1.0], [1.0, 1.0, -1.0]]), np.zeros((3, 3))],
        [np.zeros((3, 3)), -4.0 * np.eye(3)],
    ]
)


def _coefficients_li_griffiths(points):
    """Li & Griffiths (2004) ellipsoid-specific fit: generalised eigenproblem ``S_red v1 = lambda C1 v1``."""
    s = _blockwise(points, _design, lambda d: d.T @ d)
    s11, s12, s22 = s[:6, :6], s[:6, 6:], s[6:, 6:]
    s22_inv_s21 = np.linalg.solve(s22, s12.T)
    s_red = s11 - s12 @ s22_inv_s21
    s_red = 0.5 * (s_red + s_red.T)
    values, vectors = scipy.linalg.eig(s_red, _LI_GRIFFITHS_C1)
    best, best_cost = None, np.inf
    for k in range(values.shape[0]):
        v = vectors[:, k]
        if not np.all(np.isfinite(v)) or np.max(np.abs(v.imag)) > 1e-9 * np.max(np.abs(v.real)):
            continue
        v = v.real
        q = v @ _LI_GRIFFITHS_C1 @ v
        if q <= 0:  # not an ellipsoid direction
            continue
        cost = (v @ s_red @ v) / q  # algebraic distance under the constraint 4J - I^2 = 1
        if cost < best_cost:
            best, best_cost = v, cost
    if best is None:
        raise CalibrationError("the ellipsoid-specific fit found no ellipsoid for these readings")
    v2 = -s22_inv_s21 @ best
    return np.concatenate([best, v2])


def _quadric_to_ellipsoid(v, label):
    """Centre and unit-field matrix ``A_1`` from quadric coefficients, independent of their scale."""
    a, b, c, f, g, h, p, q, r, d = v
    m = np.array([[a, h, g], [h, b, f], [g, f, c]])
    n = np.array([p, q, r])
    eig_m = np.linalg.eigvalsh(m)
    if np.min(np.abs(eig_m)) <= 1e-12 * np.max(np.abs(eig_m)):
        raise CalibrationError(
            f"{label}: the readings do not lie on an ellipsoid (the fitted quadric has no centre: a cylinder or "
            "paraboloid). Check the coverage (rotate the sensor through all directions) and the units."
        )
    centre = -np.linalg.solve(m, n)
    k = centre @ m @ centre - d
    a1 = m / k
    a1 = 0.5 * (a1 + a1.T)
    eig_a = np.linalg.eigvalsh(a1)
    if np.any(eig_a <= 0):
        signs = "".join("+" if e > 0 else "-" for e in eig_a[::-1])
        kind = "an imaginary ellipsoid" if np.all(eig_a < 0) else f"a hyperboloid (eigenvalue signs {signs})"
        raise CalibrationError(
            f"{label}: the readings do not lie on an ellipsoid (the fitted quadric is {kind}, its matrix A is "
            "not positive definite). Check that the field was uniform and constant during the rotation, that all "
            "three axes are in the same units, that no axis saturates, and that the sensor was turned through "
            "all directions."
        )
    return centre, a1


#: Most directions the sky fraction of :func:`magcal.checks.coverage.coverage` is counted from (an even subsample of longer records).
SKY_MAX_SAMPLES = 50_000


def _fibonacci_sphere(n):
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = np.pi * (1.0 + 5.0**0.5) * i
    rho = np.sqrt(1.0 - z * z)
    return np.column_stack([rho * np.cos(phi), rho * np.sin(phi), z])


def direction_spread(vectors) -> DirectionSpread:
    """How a set of field vectors' directions spread over the sphere (any frame close to orthonormal); the
    record-level coverage check with its extrapolation error is :func:`magcal.checks.coverage.check_coverage`.

    Parameters
    ----------
    vectors : array_like, shape (N, 3)
        Field vectors (corrected, centred), any units.
    """
    v = np.asarray(vectors, dtype=float)
    u = unit_rows(v)
    cov = _covariance(u) if u.shape[0] > 1 else np.zeros((3, 3))
    spread = np.sort(np.linalg.eigvalsh(cov))[::-1]
    cells = _fibonacci_sphere(SKY_CELLS)
    step = max(1, int(np.ceil(u.shape[0] / SKY_MAX_SAMPLES)))  # the cells a million directions visit are those
    visited = np.unique(np.argmax(u[::step] @ cells.T, axis=1))  # of an even subsample of them
    return DirectionSpread(spread_eigenvalues=np.clip(spread, 0.0, None), sky_fraction=visited.size / SKY_CELLS)


def _covariance(points, mean=None):
    """Covariance (3, 3) of the rows of ``points`` (N, 3) about ``mean`` (default their mean), divided by N."""
    centred = points - (points.mean(axis=0) if mean is None else mean)
    return centred.T @ centred / len(points)


def _check_planarity(points, label, covariance=None):
    """Refuse before fitting when the readings lie close to one plane (a circle: rotation about one axis);
    ``covariance`` is the points' own (N-divided) when the caller has it."""
    cov = _covariance(points) if covariance is None else covariance
    spread = np.sort(np.linalg.eigvalsh(cov))[::-1]
    if spread[0] <= 0 or spread[2] <= (1e-2) ** 2 * spread[0]:
        raise CalibrationError(
            f"{label}: degenerate coverage: the readings lie close to one plane (out-of-plane spread "
            f"{np.sqrt(max(spread[2], 0.0)):.3g} nT against {np.sqrt(max(spread[0], 0.0)):.3g} nT in plane), which "
            "is what rotation about one axis only gives. An ellipsoid is not determined: turn the sensor about at "
            "least two axes so the field visits directions all over the sphere."
        )


#: Consecutive parts of the record fitted separately when the readings are off the ellipsoid.
CAUSE_SEGMENTS = 4

#: The readings' own noise explains an off-ellipsoid RMS when it predicts at least this share of it.
NOISE_EXPLAINS = 0.8

#: A centre or radius that moves explains it when fitting the parts separately brings the RMS down by this factor.
MOTION_EXPLAINS = 0.7


def _sphere_fit(z):
    """Centre (3,) and radius of the least-squares sphere through ``z`` (N, 3), or None if not determined."""
    design = np.column_stack([2.0 * z, np.ones(len(z))])
    rhs = np.einsum("ij,ij->i", z, z)
    sol, _, rank, sv = np.linalg.lstsq(design, rhs, rcond=None)
    if rank < 4 or sv[-1] < 1e-8 * sv[0]:
        return None
    r2 = float(sol[3] + sol[:3] @ sol[:3])
    return (sol[:3], np.sqrt(r2)) if r2 > 0 else None


def segment_drift(readings_nT, bias_nT, cinv, n_segments=CAUSE_SEGMENTS):
    """How the centre and radius of the ellipsoid move between consecutive parts of the record.

    The shape ``C^-1`` of the whole fit is kept and each part (the readings in the order given, split into
    ``n_segments`` runs of equal length) gets its own centre and radius: a sphere fit to the corrected
    readings ``C^-1 (y - b)``. A part whose field directions do not spread in three dimensions (a still
    warm-up, a rotation about one axis) is left out.

    Parameters
    ----------
    readings_nT : array_like, shape (N, 3)
        Raw readings in nT, in time order.
    bias_nT : array_like, shape (3,)
        Centre of the whole fit, nT.
    cinv : array_like, shape (3, 3)
        Correction matrix of the whole fit.
    n_segments : int
        Number of parts.

    Returns
    -------
    dict or None
        ``centres_nT`` (k, 3) raw-frame centres of the parts fitted, ``radii_nT`` (k,), ``segments`` (indices of
        the parts fitted, 0-based), ``centre_move_nT`` (largest distance between two centres, raw frame),
        ``radius_range_nT`` (min, max) and ``rms_nT`` (RMS of the parts' own total-field residuals, pooled);
        None when fewer than two parts can be fitted.
    """
    y = np.asarray(readings_nT, dtype=float)
    cinv = np.asarray(cinv, dtype=float)
    c_matrix = np.linalg.inv(cinv)
    z_all = (y - np.asarray(bias_nT, dtype=float)) @ cinv.T
    centres, radii, used, sq, count = [], [], [], 0.0, 0
    for k, idx in enumerate(np.array_split(np.arange(y.shape[0]), n_segments)):
        z = z_all[idx]
        if z.shape[0] < MIN_SAMPLES or direction_spread(z).thinnest_spread < WEAK_DIRECTION_SPREAD:
            continue
        fit = _sphere_fit(z)
        if fit is None:
            continue
        centre, radius = fit
        centres.append(c_matrix @ centre + bias_nT)
        radii.append(radius)
        used.append(k)
        sq += float(np.sum((row_norm(z - centre) - radius) ** 2))
        count += z.shape[0]
    if len(used) < 2:
        return None
    centres = np.array(centres)
    move = max(float(np.linalg.norm(a - b)) for i, a in enumerate(centres) for b in centres[i + 1 :])
    return {
        "centres_nT": centres,
        "radii_nT": np.array(radii),
        "segments": used,
        "centre_move_nT": move,
        "radius_range_nT": (float(min(radii)), float(max(radii))),
        "rms_nT": float(np.sqrt(sq / count)),
    }


def field_noise_nT(readings_nT, bias_nT, cinv):
    """The readings' own noise on the total field, nT: ``robust_sigma`` of the second differences of the
    total-field residual ``|C^-1 (y - b)| - F`` in time order, over ``sqrt(6)``.

    Turning the sensor changes each axis but not the magnitude, so motion does not enter (as it does the per-axis
    differences of a swinging payload); a misfit that varies smoothly with the direction, a drifting centre or a
    changing field hardly does either. What is left is the sample-to-sample scatter: the noise.
    """

    y = np.asarray(readings_nT, dtype=float)
    if y.shape[0] < 3:
        return float("nan")
    e = row_norm((y - np.asarray(bias_nT, dtype=float)) @ np.asarray(cinv, dtype=float).T)
    return float(robust_sigma(e[2:] - 2.0 * e[1:-1] + e[:-2])) / np.sqrt(6.0)


def off_ellipsoid_cause(readings_nT, bias_nT, cinv, rms_nT, claim=True):
    """Why readings deviate from their ellipsoid by ``rms_nT``: sentences for the refusal, and whether they
    name a cause.

    Two causes are measured: the readings' own noise (:func:`field_noise_nT`: at least :data:`NOISE_EXPLAINS` of
    the RMS) and a centre (hard iron) or radius (field magnitude) that
    moves between parts of the record (:func:`segment_drift`: the parts fitted separately leave at most
    :data:`MOTION_EXPLAINS` of the RMS). The movement figures are quoted either way.

    Parameters
    ----------
    readings_nT : array_like, shape (N, 3)
        Raw readings in nT, in time order.
    bias_nT, cinv
        Centre (nT) and correction matrix of the whole fit.
    rms_nT : float
        The whole fit's total-field RMS, nT.
    claim : bool
        Name a cause; ``False`` (another cause is known, e.g. partial coverage) only quotes the figures.

    Returns
    -------
    text : str
        The measured figures and, when one is found, the cause and what to do ("" if nothing could be measured).
    explained : bool
        Whether noise or a moving centre or radius accounts for the RMS.
    """
    y = np.asarray(readings_nT, dtype=float)
    parts = []
    noise_rms = field_noise_nT(y, bias_nT, cinv)
    noise_explains = claim and np.isfinite(noise_rms) and noise_rms >= NOISE_EXPLAINS * rms_nT
    drift = segment_drift(y, bias_nT, cinv)
    motion_explains = claim and drift is not None and drift["rms_nT"] <= MOTION_EXPLAINS * rms_nT
    if not claim:
        if np.isfinite(noise_rms):
            parts.append(f"The total field scatters by {noise_rms:.0f} nT from one sample to the next.")
        if drift is not None:
            parts.append(
                f"Fitted separately on {len(drift['segments'])} consecutive parts, the centre moves by up "
                f"to {drift['centre_move_nT']:.0f} nT."
            )
        return " ".join(parts), False
    if drift is not None:
        lo, hi = drift["radius_range_nT"]
        moved = (
            f"Fitted separately on {len(drift['segments'])} consecutive parts of the record (same shape), the "
            f"centre (hard iron) moves by up to {drift['centre_move_nT']:.0f} nT and the radius (field) ranges "
            f"{lo:.0f}-{hi:.0f} nT, and the parts fit to {drift['rms_nT']:.0f} nT RMS"
        )
        if motion_explains and not noise_explains:
            parts.append(
                moved + ": the hard iron or the field at the sensor changed during the record (a cable, "
                "a battery current, a magnet or the temperature changed?); calibrate each part separately "
                "or record again."
            )
        else:
            parts.append(moved + ("." if not motion_explains else ": part of it changed during the record."))
    if noise_explains:
        parts.insert(
            0,
            f"The readings' own noise accounts for it: the total field scatters by {noise_rms:.0f} nT "
            "from one sample to the next (second differences in time order); average or low-pass "
            "filter the readings (or raise the sensor's oversampling) before calibrating.",
        )
    elif np.isfinite(noise_rms):
        parts.append(
            f"The readings' own noise (sample-to-sample scatter of the total field) accounts for only "
            f"{noise_rms:.0f} nT of it."
        )
    return " ".join(parts), bool(noise_explains or motion_explains)


def _coverage_note(readings_nT) -> str:
    """`` The readings cover X% of the sphere ...``: the likely cause of a quadric that is no ellipsoid, when the
    coverage is partial (directions about the best sphere's centre, :func:`magcal.geometry.sphere.direction_cover`);
    "" when the sphere is covered."""
    y = np.asarray(readings_nT, dtype=float)
    try:
        fraction, gap = direction_cover(unit_rows(y - sphere_centre(y)))
    except (ValueError, np.linalg.LinAlgError):
        return ""
    if fraction >= 0.5:
        return ""
    return (
        f" The readings cover only {100 * fraction:.0f}% of the sphere of directions (within 30 deg of a sample; "
        f"largest gap {gap:.0f} deg): too few directions to determine an ellipsoid, the likely cause here "
        "(a flight or a drive rather than a calibration rotation?)."
    )


def fit_ellipsoid(
    readings_nT,
    method: str = "algebraic",
    reference_total_nT: float | None = None,
    mask=None,
    label: str = "sensor",
    strict: bool = True,
    max_samples: int | None = None,
) -> EllipsoidFit:
    """Fit the ellipsoid of one sensor's raw readings in a uniform field (step 1).

    Parameters
    ----------
    readings_nT : array_like, shape (N, 3)
        Raw readings in nT.
    method : {"algebraic", "li-griffiths"}
        Estimator (see the module docstring).
    reference_total_nT : float, optional
        Known field magnitude in nT. Without it the magnitude is fitted (``det C^-1 = 1``).
    mask : array_like of bool, shape (N,), optional
        Samples to use (True = use).
    label : str
        Name used in error messages (e.g. ``"sensor 2"``).
    strict : bool
        Refuse readings that deviate from the ellipsoid by more than :data:`MAX_RELATIVE_RMS` of the field and
        field directions close to one circle. ``False`` returns the best ellipsoid anyway (still refusing readings
        on one plane and quadrics that are no ellipsoid): the quick shape that the coverage and unit checks take
        directions and the field magnitude from.

    Returns
    -------
    EllipsoidFit

    Raises
    ------
    CalibrationError
        Too few samples, non-finite readings, readings not on an ellipsoid, or degenerate coverage. When the
        readings are off the ellipsoid, the message says the likely cause (:func:`off_ellipsoid_cause`): the
        readings' own noise, or a centre or radius that moves between parts of the record.
    """
    if method not in METHODS:
        raise CalibrationError(f"unknown ellipsoid method {method!r}; use one of {', '.join(METHODS)}")
    y = np.asarray(readings_nT, dtype=float)
    if y.ndim != 2 or y.shape[1] != 3:
        raise CalibrationError(f"{label}: readings must have shape (N, 3), got {y.shape}")
    if mask is not None:
        y = y[np.asarray(mask, dtype=bool)]
    if max_samples is not None and y.shape[0] > max_samples:
        y = y[:: int(np.ceil(y.shape[0] / max_samples))]
    if not np.all(np.isfinite(y)):
        bad = int(np.sum(~np.all(np.isfinite(y), axis=1)))
        raise CalibrationError(f"{label}: {bad} sample(s) have missing or non-finite readings; remove them first")
    n = y.shape[0]
    if n < MIN_SAMPLES:
        raise CalibrationError(
            f"{label}: too few samples ({n}); the ellipsoid has 9 parameters and needs at least {MIN_SAMPLES} "
            "samples at well-spread attitudes (a few dozen or more is better)"
        )
    if reference_total_nT is not None and not reference_total_nT > 0:
        raise CalibrationError(f"{label}: the reference field must be positive (nT), got {reference_total_nT}")
    # Condition: centre on the mean and scale by the RMS radius; fit; map back (c = s c' + m, A = A' / s^2).
    mean = y.mean(axis=0)
    p = y - mean
    centred_cov = p.T @ p / n
    _check_planarity(y, label, centred_cov)
    scale = float(np.sqrt(np.trace(centred_cov)))
    p /= scale
    v = _coefficients_algebraic(p) if method == "algebraic" else _coefficients_li_griffiths(p)
    try:
        centre_p, a1_p = _quadric_to_ellipsoid(v, label)
    except CalibrationError as exc:
        if not strict:
            raise
        raise CalibrationError(f"{exc}{_coverage_note(y)}") from None
    bias = scale * centre_p + mean
    a1 = a1_p / scale**2

    field_fitted = reference_total_nT is None
    field_nT = float(np.linalg.det(a1) ** (-1.0 / 6.0)) if reference_total_nT is None else float(reference_total_nT)
    a_matrix = field_nT**2 * a1
    cinv = conventions.cinv_from_quadric(a_matrix)
    corrected = (y - bias) @ cinv.T
    rms = _rms(row_norm(corrected) - field_nT)
    if strict and rms > MAX_RELATIVE_RMS * field_nT:
        note = _coverage_note(y)  # partial coverage: the likely cause, and the other figures mean little then
        cause, explained = off_ellipsoid_cause(y, bias, cinv, rms, claim=not note)
        if note:
            cause, explained = f"{note.strip()} {cause}".strip(), True
        checks = (
            ""
            if explained
            else " Check that the field was uniform and constant during the rotation, that all three axes are in "
            "the same units and that no axis saturates."
        )
        raise CalibrationError(
            f"{label}: the readings do not lie on an ellipsoid: they deviate from the best one by {rms:.4g} nT RMS "
            f"({100 * rms / field_nT:.1f}% of the field, more than the {100 * MAX_RELATIVE_RMS:.0f}% accepted)."
            + (f" {cause}" if cause else "")
            + checks
        )
    cov = direction_spread(corrected)
    warnings = []
    if strict and cov.thinnest_spread < MIN_DIRECTION_SPREAD:
        raise CalibrationError(
            f"{label}: degenerate coverage: the field directions lie close to one circle (thinnest spread "
            f"{cov.thinnest_spread:.2g}, full sphere 0.33), as from rotation about one axis only; the ellipsoid is "
            "not determined. Turn the sensor about at least two axes."
        )
    if cov.thinnest_spread < WEAK_DIRECTION_SPREAD:
        warnings.append(
            f"{label}: weak coverage (thinnest direction spread {cov.thinnest_spread:.3f}, full sphere 0.33; "
            f"{100 * cov.sky_fraction:.0f}% of the sky visited): the calibration extrapolates to directions it "
            "has not seen, and its parameters can be off by tens to hundreds of nT; turn the sensor through more "
            "directions"
        )
    return EllipsoidFit(
        cinv=cinv,
        bias_nT=bias,
        field_nT=field_nT,
        field_fitted=field_fitted,
        method=method,
        A=a_matrix,
        rms_nT=rms,
        n_samples=n,
        coverage=cov,
        warnings=warnings,
    )
