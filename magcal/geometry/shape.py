"""The shape of one sensor's readings in a uniform field: the centre and unit-field matrix that turn them
into field directions (an ellipsoid fit when one is determined, else the best sphere), the field magnitude they
imply, and the total-field error a fit extrapolates off the directions it saw."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magcal.core.errors import CalibrationError
from magcal.core.rows import row_norm
from magcal.geometry.ellipsoid import MIN_SAMPLES, fit_ellipsoid
from magcal.geometry.sphere import fibonacci_sphere, sphere_centre

#: Number of parameters of the full single-sensor model seen by total-field data: A (6) and b (3).
FULL_MODEL_PARAMS = 9


#: The quick ellipsoid is trusted when its centre is determined to this fraction of the field (1 sigma)...
SHAPE_CENTRE_TOLERANCE = 0.01


#: ...and its axes differ by at most this factor (a magnetometer's sensitivities differ by far less).
SHAPE_MAX_AXIS_RATIO = 4.0


@dataclass
class FieldShape:
    """The surface one sensor's readings lie on, as the checks before a fit take it.

    Attributes
    ----------
    centre_nT : numpy.ndarray, shape (3,)
        Centre (hard iron), nT.
    cinv : numpy.ndarray, shape (3, 3)
        Maps ``y - centre`` to a vector of the field's magnitude (the ellipsoid's correction, normalised to
        ``det = 1``); the identity for a sphere or the origin.
    field_nT : float
        The field magnitude the shape implies, nT: the ellipsoid's geometric-mean radius, or the sphere's radius,
        or the median ``|y|`` about the origin.
    source : str
        ``"ellipsoid"`` (a trusted ellipsoid fit), ``"sphere"`` (the quick sphere, :func:`sphere_centre`) or
        ``"origin"`` (nothing determines a centre, e.g. a small cap of directions).
    """

    centre_nT: np.ndarray
    cinv: np.ndarray
    field_nT: float
    source: str

    def corrected(self, readings_nT) -> np.ndarray:
        """``C^-1 (y - centre)`` (N, 3), nT."""
        return (np.asarray(readings_nT, dtype=float) - self.centre_nT) @ self.cinv.T

    def directions(self, readings_nT) -> np.ndarray:
        """Unit field directions (N, 3) in the shape's frame."""
        z = self.corrected(readings_nT)
        norm = row_norm(z)
        norm[norm == 0] = 1.0
        return z / norm[:, None]


#: Most samples the checks before a fit take the field's shape from (an even subsample of longer records).
SHAPE_MAX_SAMPLES = 20_000


def _trusted_ellipsoid(y):
    """The ellipsoid fit of ``y`` (N, 3) if it is determined, else None.

    Determined: the fit is an ellipsoid with axes within :data:`SHAPE_MAX_AXIS_RATIO` of each other, and the
    centre's standard error from the linearised fit (its RMS and the Jacobian of :func:`_jacobian` at the fitted
    directions) is below :data:`SHAPE_CENTRE_TOLERANCE` of the field. A cap of directions passes neither: an
    ellipsoid through a cap slides along the cap's axis.
    """
    if y.shape[0] < max(MIN_SAMPLES, FULL_MODEL_PARAMS + 1):
        return None
    try:
        with np.errstate(all="ignore"):  # a degenerate cloud: the checks below turn it down
            fit = fit_ellipsoid(y, strict=False)
    except (CalibrationError, np.linalg.LinAlgError, ValueError):
        return None
    eig = np.linalg.eigvalsh(fit.A)
    if not (np.all(np.isfinite(eig)) and eig[0] > 0 and np.sqrt(eig[-1] / eig[0]) <= SHAPE_MAX_AXIS_RATIO):
        return None
    z = fit.correct(y)
    u = z / np.maximum(row_norm(z)[..., None], 1e-300)
    j = _jacobian(u)
    try:
        cov = np.linalg.inv(j.T @ j)
    except np.linalg.LinAlgError:
        return None
    centre_se = fit.rms_nT * float(np.sqrt(max(np.trace(cov[6:, 6:]), 0.0)))
    if not np.isfinite(centre_se) or centre_se > SHAPE_CENTRE_TOLERANCE * fit.field_nT:
        return None
    return fit


def field_shape(readings_nT) -> FieldShape:
    """The centre, shape and field magnitude of one sensor's readings (N, 3) in nT, for the checks before a fit.

    In order of preference: the ellipsoid fit (:func:`magcal.geometry.ellipsoid.fit_ellipsoid`, not refusing readings a
    little off the ellipsoid) when it is determined (:func:`_trusted_ellipsoid`); else the quick sphere of
    :func:`sphere_centre` when it is determined; else the origin. The ellipsoid matters for MEMS parts: a
    hard-iron offset several times the field and axis gains differing by 2x put the readings far from any sphere
    about the origin and off any sphere at all, yet on an ellipsoid. Records longer than
    :data:`SHAPE_MAX_SAMPLES` are represented by an even subsample of that size.
    """
    y = np.asarray(readings_nT, dtype=float)
    if y.ndim == 2 and y.shape[0] > SHAPE_MAX_SAMPLES:  # an even subsample: the shape of a million samples is
        y = y[:: int(np.ceil(y.shape[0] / SHAPE_MAX_SAMPLES))]  # that of twenty thousand of them
    fit = _trusted_ellipsoid(y) if y.ndim == 2 and y.shape[0] else None
    if fit is not None:
        cinv = fit.cinv / np.cbrt(np.linalg.det(fit.cinv))  # det 1: the magnitude is the fitted field
        z = (y - fit.bias_nT) @ cinv.T
        return FieldShape(fit.bias_nT.copy(), cinv, float(np.median(row_norm(z))), "ellipsoid")
    centre = sphere_centre(y) if y.ndim == 2 else np.zeros(3)
    source = "sphere" if np.any(centre != 0) else "origin"
    magnitude = float(np.median(row_norm(y - centre))) if y.size else float("nan")
    return FieldShape(centre, np.eye(3), magnitude, source)


def field_magnitude_nT(readings_nT):
    """The field magnitude (nT) one sensor's readings (N, 3) imply: the median ``|C^-1 (y - c)|`` through the
    shape of :func:`field_shape` (an ellipsoid fit when one is determined).

    The figure to compare with the Earth's field or a reference: hard iron removed and the axes' gains
    averaged (the raw magnitude, offset included, can be far from either).
    """
    y = np.asarray(readings_nT, dtype=float)
    if y.size == 0:
        return float("nan")
    return field_shape(y).field_nT


def _jacobian(directions):
    """Jacobian (N, 9) of ``|z|_A - 1`` in ``A`` (upper triangle) and ``b`` at ``A = I``, ``z = u`` (unit radius)."""
    u = np.asarray(directions, dtype=float)
    ux, uy, uz = u.T
    return np.column_stack([0.5 * ux * ux, ux * uy, ux * uz, 0.5 * uy * uy, uy * uz, 0.5 * uz * uz, -ux, -uy, -uz])


def extrapolation_factor(directions, n_test=600):
    """RMS over the whole sphere of the noise-propagated total-field error, per unit of per-axis noise.

    Parameters
    ----------
    directions : array_like, shape (N, 3)
        Unit field directions in the sensor frame of the calibration samples.
    n_test : int
        Test directions on the sphere.

    Returns
    -------
    float
        ``K = sqrt(mean_u g(u)^T (J^T J)^-1 g(u))``; multiply by the noise sigma (nT) for nT. ``inf`` when the
        samples do not determine the 9 parameters.
    """
    j = _jacobian(directions)
    info = j.T @ j
    try:
        w, v = np.linalg.eigh(info)
    except np.linalg.LinAlgError:
        return float("inf")
    if w[0] <= 1e-12 * max(w[-1], 1e-300):
        return float("inf")
    g = _jacobian(fibonacci_sphere(n_test)) @ v
    return float(np.sqrt(np.mean(np.sum(g * g / w, axis=1))))


def sensor_directions(readings_nT):
    """Unit field directions (N, 3) of one sensor's readings (N, 3): ``C^-1 (y - c)`` normalised, through the
    shape of :func:`field_shape` (the ellipsoid fit when one is determined, else about the quick centre)."""
    y = np.asarray(readings_nT, dtype=float)
    return field_shape(y).directions(y)
