"""Geometry of directions on the unit sphere: even test directions, the best sphere through readings,
and how much of the sphere a set of directions covers."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from magcal.core.rows import row_norm


def fibonacci_sphere(n):
    """``n`` nearly evenly spread unit vectors (Fibonacci lattice), shape (n, 3)."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    phi = np.pi * (1.0 + 5.0**0.5) * k
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def sphere_centre(points_nT):
    """Centre (nT) of the best sphere through the points (linear least squares); zeros if it is not determined.

    The fallback of :func:`magcal.geometry.shape.field_shape` when no ellipsoid is determined. The fitted
    centre is used when it is small (under half the radius: any fit will do) or when the readings determine it:
    they spread over a good part of the sphere (RMS distance from their mean at least half the radius) and lie on
    it (radial residual under 15 % of the radius). MEMS parts on a platform often carry a hard-iron offset larger
    than the Earth's field, and the origin is then a poor centre; a small cap of readings does not determine a
    centre, and the origin is then as good a guess as any.
    """
    y = np.asarray(points_nT, dtype=float)
    if y.shape[0] < 4:
        return np.zeros(3)
    scale = float(np.median(row_norm(y))) or 1.0
    ys = y / scale
    design = np.column_stack([2.0 * ys, np.ones(len(ys))])
    rhs = np.einsum("ij,ij->i", ys, ys)
    sol, _, rank, sv = np.linalg.lstsq(design, rhs, rcond=None)
    if rank < 4 or sv[-1] < 1e-6 * sv[0]:
        return np.zeros(3)
    centre = sol[:3]
    r2 = float(sol[3] + centre @ centre)
    if not np.all(np.isfinite(centre)) or r2 <= 0:
        return np.zeros(3)
    radius = np.sqrt(r2)
    if np.linalg.norm(centre) <= 0.5 * radius:
        return centre * scale
    spread = np.sqrt(np.mean(np.sum((ys - ys.mean(axis=0)) ** 2, axis=1)))
    radial = np.sqrt(np.mean((row_norm(ys - centre) - radius) ** 2))
    if spread >= 0.5 * radius and radial <= 0.15 * radius:
        return centre * scale
    return np.zeros(3)


def direction_cover(directions, cap_deg=30.0, n_test=2000):
    """How much of the sphere unit ``directions`` (N, 3) cover.

    Parameters
    ----------
    directions : array_like, shape (N, 3)
        Unit vectors.
    cap_deg : float
        A test direction counts as covered when a sample direction lies within this angle (deg).
    n_test : int
        Test directions (:func:`fibonacci_sphere`).

    Returns
    -------
    fraction : float
        Covered fraction of the test directions, 0..1.
    largest_gap_deg : float
        Angle (deg) from the least covered test direction to its nearest sample direction.
    """
    dist, _ = cKDTree(np.asarray(directions, dtype=float)).query(fibonacci_sphere(n_test))
    angle = np.degrees(2.0 * np.arcsin(np.clip(dist / 2.0, 0.0, 1.0)))
    return float(np.mean(angle <= cap_deg)), float(angle.max())
