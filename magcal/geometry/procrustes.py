"""Step 2 of the two-step calibration: the rotation between two sensors by orthogonal Procrustes.

After step 1 every sensor reports the field in its own ideal orthogonal frame. Chi et al. (2017), eq. (14),
find the rotation ``R_i`` that takes sensor ``i``'s corrected vectors into sensor 1's frame::

    min over rotations R of  sum_j |B_1j - R B_ij|^2,     M_1 M_i^T = U S V^T,   R = U V^T

(``M_i`` is the 3 x N matrix of sensor ``i``'s corrected vectors). The seed takes ``R = U V^T``, which may be
a reflection when the data are poor; here the determinant is forced to +1 (Kabsch/Umeyama sign fix:
``R = U diag(1, 1, det(U V^T)) V^T``), so ``R`` is always a proper rotation.
"""

from __future__ import annotations

import numpy as np

from magcal.core.errors import CalibrationError

#: Refuse when the smallest singular value of ``M_1 M_i^T`` is below this fraction of the largest: the field
#: directions then span less than three dimensions and the rotation about the missing axis is not determined.
MIN_SINGULAR_RATIO = 1e-3


def procrustes_rotation(reference_vectors, vectors, label: str = "sensor") -> np.ndarray:
    """Proper rotation ``R`` (det +1) minimising ``sum_j |reference_j - R vectors_j|^2`` (eq. 14).

    Parameters
    ----------
    reference_vectors : array_like, shape (N, 3)
        Sensor 1's corrected field vectors (nT), the target frame.
    vectors : array_like, shape (N, 3)
        Sensor ``i``'s corrected field vectors (nT) at the same samples.
    label : str
        Name used in error messages (e.g. ``"sensor 3"``).

    Returns
    -------
    numpy.ndarray, shape (3, 3)
        ``R`` with ``reference ~ vectors @ R.T``; the correction matrix of :mod:`magcal.core.conventions`.

    Raises
    ------
    CalibrationError
        Different sample counts, fewer than 3 samples, non-finite values, or field directions that do not span
        three dimensions (the rotation is then not determined).
    """
    b1 = np.asarray(reference_vectors, dtype=float)
    bi = np.asarray(vectors, dtype=float)
    if b1.shape != bi.shape or b1.ndim != 2 or b1.shape[1] != 3:
        raise CalibrationError(
            f"{label}: Procrustes needs two (N, 3) arrays of the same shape, got {b1.shape} and {bi.shape}"
        )
    if b1.shape[0] < 3:
        raise CalibrationError(f"{label}: the rotation between sensors needs at least 3 samples, got {b1.shape[0]}")
    if not (np.all(np.isfinite(b1)) and np.all(np.isfinite(bi))):
        raise CalibrationError(f"{label}: non-finite corrected vectors; remove the bad samples first")
    cross = b1.T @ bi  # M_1 M_i^T
    u, s, vt = np.linalg.svd(cross)
    if s[0] <= 0 or s[2] < MIN_SINGULAR_RATIO * s[0]:
        raise CalibrationError(
            f"{label}: degenerate coverage: the field directions do not span three dimensions (singular values of "
            f"M1 Mi^T in ratio {s[2] / s[0] if s[0] > 0 else 0:.2g}), so the rotation between the sensors is not "
            "determined. Turn the array about at least two axes."
        )
    sign = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, sign]) @ vt


def rotation_angle_deg(r) -> float:
    """Angle (deg) of a rotation matrix, e.g. of ``R_fit R_true^T`` to compare two rotations."""
    r = np.asarray(r, dtype=float)
    return float(np.degrees(np.arccos(np.clip(0.5 * (np.trace(r) - 1.0), -1.0, 1.0))))
