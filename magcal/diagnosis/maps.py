"""Residual patterns on the direction sphere: where on the sphere a model fails, and what a candidate would explain.

The diagnosis tests the residual's dependence on the field direction with real spherical harmonics
(:func:`magcal.diagnosis.statistics.sh_analysis`). Here the same expansion is evaluated on the vertices of a sphere
mesh, so a degree-3 nonlinearity or a one-sided temperature effect is seen as a smooth coloured surface rather than
guessed from 1500 noisy dots:

* :func:`direction_pattern`: the least-squares expansion of any per-sample quantity (nT) over the field directions,
  up to the highest degree the directions resolve (:func:`~magcal.diagnosis.statistics.sh_resolved_degrees`), at
  given unit vectors; vertices farther than ``cap_deg`` from every sample direction are marked unsupported
  (an expansion there is an extrapolation);
* :func:`residual_patterns`: the total-field residual's pattern per sensor, in the array frame (the directions of the
  corrected field, as the corrected clouds are drawn);
* :func:`candidate_change` and :func:`candidate_patterns`: what adding a candidate effect removes from the residual
  (base residual minus the residual with the effect refitted), and its pattern: the shape of what is missing, before
  adding it.

Values are in nT; directions are unit vectors.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from magcal.core.rows import row_norm
from magcal.diagnosis.scores import _refit
from magcal.diagnosis.statistics import SH_DEGREE, SH_MAX_SAMPLES, real_sph_harm, sh_resolved_degrees

#: A vertex farther than this from every sample direction is not supported by the data (deg).
SUPPORT_CAP_DEG = 30.0


@dataclass
class DirectionPattern:
    """A quantity's direction pattern evaluated at unit vectors.

    Attributes
    ----------
    vertices : numpy.ndarray, shape (V, 3)
        Unit vectors where the pattern is evaluated.
    value_nT : numpy.ndarray, shape (V,)
        The expansion at the vertices, nT (also where unsupported: see ``supported``).
    supported : numpy.ndarray of bool, shape (V,)
        A sample direction lies within :data:`SUPPORT_CAP_DEG` of the vertex.
    max_degree : int
        Highest spherical-harmonic degree used (the highest the sample directions resolve; -1: none).
    explained_rms_nT : float
        RMS over the samples of the part of the quantity the expansion explains, nT.
    """

    vertices: np.ndarray
    value_nT: np.ndarray
    supported: np.ndarray
    max_degree: int
    explained_rms_nT: float

    @property
    def amplitude_nT(self) -> float:
        """Largest absolute value over the supported vertices, nT (0 when none is supported)."""
        v = np.abs(self.value_nT[self.supported])
        return float(v.max()) if v.size else 0.0


def _even_pick(n: int, m: int) -> np.ndarray:
    return np.arange(n) if n <= m else np.linspace(0, n - 1, m).round().astype(int)


def direction_pattern(
    directions,
    values_nT,
    vertices,
    lmax: int = SH_DEGREE,
    max_samples: int = SH_MAX_SAMPLES,
    cap_deg: float = SUPPORT_CAP_DEG,
) -> DirectionPattern:
    """The least-squares spherical-harmonic expansion of ``values_nT(directions)`` evaluated at ``vertices``.

    Parameters
    ----------
    directions : array_like, shape (N, 3)
        Unit field directions of the samples.
    values_nT : array_like, shape (N,)
        The quantity per sample, nT (NaN samples are left out).
    vertices : array_like, shape (V, 3)
        Unit vectors to evaluate at.
    lmax : int
        Highest degree tried; the expansion stops at the highest degree the directions resolve.
    max_samples : int
        An even subsample of at most this many samples is expanded (the pattern is smooth).
    cap_deg : float
        Support radius around each sample direction, deg.

    Returns
    -------
    DirectionPattern
    """
    u = np.asarray(directions, float).reshape(-1, 3)
    r = np.asarray(values_nT, float).ravel()
    verts = np.asarray(vertices, float).reshape(-1, 3)
    ok = np.isfinite(r) & np.all(np.isfinite(u), axis=1)
    u, r = u[ok], r[ok]
    if r.size == 0:
        return DirectionPattern(verts, np.zeros(len(verts)), np.zeros(len(verts), bool), -1, 0.0)
    pick = _even_pick(r.size, int(max_samples))
    u, r = u[pick], r[pick]
    y = real_sph_harm(u, lmax)
    resolved = sh_resolved_degrees(y)
    top = int(np.flatnonzero(resolved)[-1]) if resolved.any() else -1
    dist, _ = cKDTree(u).query(verts)
    supported = np.degrees(2.0 * np.arcsin(np.clip(dist / 2.0, 0.0, 1.0))) <= cap_deg
    if top < 0:
        return DirectionPattern(verts, np.zeros(len(verts)), supported, -1, 0.0)
    k = (top + 1) ** 2
    coef, *_ = np.linalg.lstsq(y[:, :k], r, rcond=None)
    explained = y[:, :k] @ coef
    value = real_sph_harm(verts, top) @ coef
    return DirectionPattern(verts, value, supported, top, float(np.sqrt(np.mean(explained**2))))


def corrected_directions(dataset, calibration) -> np.ndarray:
    """Unit directions of the corrected field, array frame, (n_sensors, N, 3)."""
    b = calibration.correct(dataset, warn=False, force=True)  # record-only terms on their own record: nothing to say
    norm = row_norm(b)[..., None]
    return b / np.where(norm > 0, norm, 1.0)


def residual_patterns(dataset, calibration, residual_nT, vertices, kept=None, **kw) -> list[DirectionPattern]:
    """The direction pattern of each sensor's total-field residual, array frame.

    Parameters
    ----------
    dataset : Dataset
    calibration : Calibration
        The fit whose residuals these are (its corrected directions place the samples on the sphere).
    residual_nT : array_like, shape (n_sensors, N)
        Total-field residuals, nT (NaN where not fitted).
    vertices : array_like, shape (V, 3)
    kept : array_like of bool, shape (N,), optional
        Samples to use (default: every finite residual).
    **kw
        Passed to :func:`direction_pattern`.
    """
    u = corrected_directions(dataset, calibration)
    r = np.asarray(residual_nT, float)
    if kept is not None:
        r = np.where(np.asarray(kept, bool)[None, :], r, np.nan)
    return [direction_pattern(u[s], r[s], vertices, **kw) for s in range(dataset.n_sensors)]


def candidate_change(dataset, diagnosis, candidate) -> np.ndarray:
    """What adding ``candidate`` removes from the total-field residual: base residual minus the residual with the
    effect refitted, (n_sensors, N) nT, NaN for samples the fit left out. Uses the diagnosis's own refit when it
    made one, else refits (the same refit the diagnosis would make)."""

    fit1 = candidate.fit if candidate.fit is not None else _refit(dataset, diagnosis.result, candidate)
    return np.asarray(diagnosis.result.residuals_nT, float) - np.asarray(fit1.residuals_nT, float)


def candidate_patterns(dataset, diagnosis, candidate, vertices, **kw) -> list[DirectionPattern]:
    """The direction pattern per sensor of what ``candidate`` would explain (:func:`candidate_change`), on the
    directions of the diagnosed fit."""
    change = candidate_change(dataset, diagnosis, candidate)
    return residual_patterns(dataset, diagnosis.result.calibration, change, vertices, **kw)


def pattern_correlation(a: DirectionPattern, b: DirectionPattern) -> float:
    """Correlation of two patterns over the vertices both support (nan when fewer than 3 are shared)."""
    both = a.supported & b.supported
    if both.sum() < 3:
        return float("nan")
    x, y = a.value_nT[both], b.value_nT[both]
    x, y = x - x.mean(), y - y.mean()
    den = np.sqrt(np.sum(x * x) * np.sum(y * y))
    return float(np.sum(x * y) / den) if den > 0 else float("nan")
