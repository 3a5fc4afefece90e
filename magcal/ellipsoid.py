"""Step 1 of the two-step calibration, per sensor: fit an ellipsoid to the raw readings.

In a uniform field of magnitude ``F`` the raw readings ``y = C B + b`` of one sensor lie on the ellipsoid
``(y - b)^T A (y - b) = F^2`` with ``A = C^-T C^-1`` (Chi et al. 2017, eqs. 6-7). Writing it as the general
quadric of eq. (8)::

    a x^2 + b y^2 + c z^2 + 2f yz + 2g xz + 2h xy + 2p x + 2q y + 2r z + d = 0,
    M = [[a, h, g], [h, b, f], [g, f, c]],   n = (p, q, r)

the centre is ``b = -M^-1 n`` (eq. 12) and the ellipsoid is ``(y - b)^T M (y - b) = b^T M b - d`` (eq. 13), so
the unit-field matrix ``A_1 = M / (b^T M b - d)`` does not depend on the scale (or sign) of the coefficient vector.
``A = F^2 A_1`` and its Cholesky factor (:func:`magcal.conventions.cinv_from_quadric`) is the upper-triangular
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

The fit refuses (:class:`magcal.errors.CalibrationError`) too few samples, readings that do not lie on an
ellipsoid, and coverage too poor to determine one (e.g. rotation about one axis only).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import scipy.linalg

from . import conventions
from .errors import CalibrationError

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
class Coverage:
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
    coverage : Coverage
        Direction coverage of the samples.
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
    coverage: Coverage
    warnings: list = field(default_factory=list)

    def correct(self, readings_nT) -> np.ndarray:
        """Corrected vectors ``C^-1 (y - b)`` (N, 3) in nT in the sensor's ideal frame."""
        return (np.asarray(readings_nT, dtype=float) - self.bias_nT) @ self.cinv.T

    def with_field(self, field_nT: float, fitted: bool | None = None, readings_nT=None) -> "EllipsoidFit":
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
            new.rms_nT = _rms(np.linalg.norm(new.correct(readings_nT), axis=1) - new.field_nT)
        return new


def _rms(x) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


def _design(points):
    """Rows ``[x^2, y^2, z^2, 2yz, 2xz, 2xy, 2x, 2y, 2z, 1]`` of eq. (8)."""
    x, y, z = points.T
    return np.column_stack([x * x, y * y, z * z, 2 * y * z, 2 * x * z, 2 * x * y, 2 * x, 2 * y, 2 * z,
                            np.ones_like(x)])


def _coefficients_algebraic(points):
    """Linear least squares for eq. (8) with the trace ``a + b + c`` fixed to 3."""
    d = _design(points)
    # a x^2 + b y^2 + (3 - a - b) z^2 + ... = 0  ->  a (x^2 - z^2) + b (y^2 - z^2) + ... = -3 z^2
    lhs = np.column_stack([d[:, 0] - d[:, 2], d[:, 1] - d[:, 2], d[:, 3:]])
    rhs = -3.0 * d[:, 2]
    sol, *_ = np.linalg.lstsq(lhs, rhs, rcond=None)
    a, b = sol[0], sol[1]
    return np.concatenate([[a, b, 3.0 - a - b], sol[2:]])


#: Li & Griffiths' constraint matrix for k = 4: v1^T C1 v1 = 4J - I^2.
_LI_GRIFFITHS_C1 = np.block([
    [np.array([[-1.0, 1.0, 1.0], [1.0, -1.0, 1.0], [1.0, 1.0, -1.0]]), np.zeros((3, 3))],
    [np.zeros((3, 3)), -4.0 * np.eye(3)],
])


def _coefficients_li_griffiths(points):
    """Li & Griffiths (2004) ellipsoid-specific fit: generalised eigenproblem ``S_red v1 = lambda C1 v1``."""
    d = _design(points)
    s = d.T @ d
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


def _fibonacci_sphere(n):
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = np.pi * (1.0 + 5.0**0.5) * i
    rho = np.sqrt(1.0 - z * z)
    return np.column_stack([rho * np.cos(phi), rho * np.sin(phi), z])


def coverage(vectors) -> Coverage:
    """Direction coverage of a set of field vectors (any frame close to orthonormal).

    Parameters
    ----------
    vectors : array_like, shape (N, 3)
        Field vectors (corrected, centred), any units.
    """
    v = np.asarray(vectors, dtype=float)
    u = v / np.linalg.norm(v, axis=1, keepdims=True)
    cov = np.cov(u.T, bias=True) if u.shape[0] > 1 else np.zeros((3, 3))
    spread = np.sort(np.linalg.eigvalsh(cov))[::-1]
    cells = _fibonacci_sphere(SKY_CELLS)
    visited = np.unique(np.argmax(u @ cells.T, axis=1))
    return Coverage(spread_eigenvalues=np.clip(spread, 0.0, None), sky_fraction=visited.size / SKY_CELLS)


def _check_planarity(points, label):
    """Refuse before fitting when the readings lie close to one plane (a circle: rotation about one axis)."""
    spread = np.sort(np.linalg.eigvalsh(np.cov(points.T, bias=True)))[::-1]
    if spread[0] <= 0 or spread[2] <= (1e-2) ** 2 * spread[0]:
        raise CalibrationError(
            f"{label}: degenerate coverage: the readings lie close to one plane (out-of-plane spread "
            f"{np.sqrt(max(spread[2], 0.0)):.3g} nT against {np.sqrt(max(spread[0], 0.0)):.3g} nT in plane), which "
            "is what rotation about one axis only gives. An ellipsoid is not determined: turn the sensor about at "
            "least two axes so the field visits directions all over the sphere."
        )


def fit_ellipsoid(readings_nT, method: str = "algebraic", reference_total_nT: float | None = None,
                  mask=None, label: str = "sensor") -> EllipsoidFit:
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

    Returns
    -------
    EllipsoidFit

    Raises
    ------
    CalibrationError
        Too few samples, non-finite readings, readings not on an ellipsoid, or degenerate coverage.
    """
    if method not in METHODS:
        raise CalibrationError(f"unknown ellipsoid method {method!r}; use one of {', '.join(METHODS)}")
    y = np.asarray(readings_nT, dtype=float)
    if y.ndim != 2 or y.shape[1] != 3:
        raise CalibrationError(f"{label}: readings must have shape (N, 3), got {y.shape}")
    if mask is not None:
        y = y[np.asarray(mask, dtype=bool)]
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
    _check_planarity(y, label)

    # Condition: centre on the mean and scale by the RMS radius; fit; map back (c = s c' + m, A = A' / s^2).
    mean = y.mean(axis=0)
    scale = float(np.sqrt(np.mean(np.sum((y - mean) ** 2, axis=1))))
    p = (y - mean) / scale
    v = _coefficients_algebraic(p) if method == "algebraic" else _coefficients_li_griffiths(p)
    centre_p, a1_p = _quadric_to_ellipsoid(v, label)
    bias = scale * centre_p + mean
    a1 = a1_p / scale**2

    field_fitted = reference_total_nT is None
    field_nT = float(np.linalg.det(a1) ** (-1.0 / 6.0)) if field_fitted else float(reference_total_nT)
    a_matrix = field_nT**2 * a1
    cinv = conventions.cinv_from_quadric(a_matrix)
    corrected = (y - bias) @ cinv.T
    rms = _rms(np.linalg.norm(corrected, axis=1) - field_nT)
    if rms > MAX_RELATIVE_RMS * field_nT:
        raise CalibrationError(
            f"{label}: the readings do not lie on an ellipsoid: they deviate from the best one by {rms:.4g} nT RMS "
            f"({100 * rms / field_nT:.1f}% of the field). Check that the field was uniform and constant during the "
            "rotation, that all three axes are in the same units and that no axis saturates."
        )
    cov = coverage(corrected)
    warnings = []
    if cov.thinnest_spread < MIN_DIRECTION_SPREAD:
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
    return EllipsoidFit(cinv=cinv, bias_nT=bias, field_nT=field_nT, field_fitted=field_fitted, method=method,
                        A=a_matrix, rms_nT=rms, n_samples=n, coverage=cov, warnings=warnings)
