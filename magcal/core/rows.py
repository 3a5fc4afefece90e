"""Row-wise operations on arrays of 3-vectors (field vectors in nT, directions), shaped ``(..., 3)``.

numpy's general forms reduce over a length-3 last axis slowly (``np.linalg.norm(v, axis=-1)`` is about four
times slower than adding the three squared components); the fitter and the checks call these on every sample.
"""

from __future__ import annotations

import numpy as np


def row_norm(vectors) -> np.ndarray:
    """Euclidean length of each 3-vector: shape ``(...)`` from ``(..., 3)``, in the vectors' units.

    Examples
    --------
    >>> row_norm(np.array([[3.0, 4.0, 0.0], [0.0, 0.0, 2.0]]))
    array([5., 2.])
    """
    v = np.asarray(vectors, dtype=float)
    if v.ndim == 1:
        return np.sqrt(v @ v)
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    out = x * x
    out += y * y
    out += z * z
    return np.sqrt(out, out=out)


def unit_rows(vectors) -> np.ndarray:
    """Each 3-vector divided by its length (``(..., 3)``; a zero vector gives NaN)."""
    v = np.asarray(vectors, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        return v / row_norm(v)[..., None]


def cross_rows(a, b) -> np.ndarray:
    """Cross product of each row of ``a`` with each row of ``b`` (``(N, 3)`` each, or broadcastable), ``(N, 3)``.

    Examples
    --------
    >>> cross_rows(np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    array([[0., 0., 1.]])
    """
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    for k, (i, j) in enumerate(((1, 2), (2, 0), (0, 1))):
        np.multiply(a[..., i], b[..., j], out=out[..., k])
        out[..., k] -= a[..., j] * b[..., i]
    return out


def basis_times(basis, theta) -> np.ndarray:
    """``basis @ theta`` for an effect's basis (N, 3, q) and its parameters (q,): the vectors (N, 3).

    One (3N, q) matrix-vector product (BLAS) instead of numpy's batched ``matmul`` over N small matrices, which is
    about six times slower; for a basis that keeps which axis each parameter moves (``axes`` and ``axis_values``,
    :class:`magcal.model.terms.SingleAxisBasis`), q products of its non-zero entries.

    Examples
    --------
    >>> basis_times(np.arange(12.0).reshape(2, 3, 2), np.array([1.0, -1.0]))
    array([[-1., -1., -1.],
           [-1., -1., -1.]])
    """
    axes = getattr(basis, "axes", None)
    if axes is not None:  # a basis whose parameters each move one axis (magcal.model.terms.SingleAxisBasis)
        theta = np.asarray(theta, dtype=float)
        out = np.zeros((basis.shape[0], 3))
        for k, a in enumerate(axes):
            out[:, a] += basis.axis_values[k] * theta[k]
        return out
    b = np.asarray(basis, dtype=float)
    return (b.reshape(-1, b.shape[-1]) @ np.asarray(theta, dtype=float)).reshape(b.shape[:-1])
