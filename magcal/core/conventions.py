"""The seed's conventions, defined once.

Everything in magcal that builds a sensor matrix, a misalignment rotation, a sensor position or a tensor
component calls this module. The conventions are those of Chi, Lü & Huang (2017), "Error calibration of
cross magnetic gradiometer" (the ``chi2017`` seed):

Single sensor, eq. (2)
    ``y = C B + b + n`` with ``C = S C_NO``, ``S = diag(k_x, k_y, k_z)`` (dimensionless scale factors) and the
    upper-triangular non-orthogonality matrix::

        C_NO = [[cos(theta) cos(phi), cos(theta) sin(phi), sin(theta)],
                [0,                   cos(psi),            sin(psi)  ],
                [0,                   0,                   1         ]]

    The z axis is the reference axis, the y axis lies in the ideal y-z plane. ``y`` and ``b`` (``bias_nT``)
    are in nT, ``B`` is the field in the sensor's ideal orthogonal frame in nT. The correction, eq. (5), is
    ``B = C^-1 (y - b)``; ``C^-1`` is upper triangular with a positive diagonal and is what the Cholesky factor
    of ``A = C^-T C^-1`` gives. Total-field data determine only ``A`` (6 numbers) and ``b`` (3): the
    upper-triangular form is a gauge choice. The gauge-free figures are the per-axis sensitivities
    ``k_j = sqrt((A^-1)_jj)`` (the norms of the rows of ``C``) and the angles between the sensing axes
    (the angles between the rows of ``C``); see :func:`gauge_free`.

Misalignment between sensors, eq. (3)
    ``B_i = R1(gamma) R2(beta) R3(alpha) B_ref``: the reference frame is turned by ``alpha`` about z, then
    ``beta`` about the new x, then ``gamma`` about the new y (angles in rad, matrices exactly as printed).
    :func:`misalignment_matrix` returns ``M = R1 R2 R3``; the *correction* matrix that takes sensor ``i``'s
    corrected vector into the reference frame is ``R = M^T`` (this is the ``R`` printed in Table 2 and the
    ``R`` stored in a calibration file).

Array frame and geometry, eq. (1)
    The array (platform) frame is sensor 1's ideal frame unless a platform alignment has been estimated.
    Sensor 1 sits at +x, sensor 2 at +y, sensor 3 at -x, sensor 4 at -y; the baseline ``d`` (``baseline_m``)
    is the distance between sensors 1 and 3 (and 2 and 4), so each sits ``d/2`` from the centre.
    Tensor by finite differences (nT/m)::

        Gxx = (B1x - B3x)/d   Gxy = (B2x - B4x)/d   Gxz = (B1z - B3z)/d
        Gyx = (B1y - B3y)/d   Gyy = (B2y - B4y)/d   Gyz = (B2z - B4z)/d
        Gzx = Gxz             Gzy = Gyz             Gzz = (B4y - B2y + B3x - B1x)/d

Attitude
    An attitude quaternion ``(qw, qx, qy, qz)`` rotates array-frame vectors into the world frame
    (world = north, east, down). The Earth field in the world frame comes from :func:`earth_field`.
"""

from __future__ import annotations

import numpy as np

#: Names of the tensor components in the order magcal reports them.
TENSOR_COMPONENTS = ("Gxx", "Gxy", "Gxz", "Gyx", "Gyy", "Gyz", "Gzz")

#: Index pairs (i, j) of the upper triangle of C^-1, in the order of its 6 free parameters.
UPPER_TRIANGLE = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))

#: Axis pairs for :func:`gauge_free` angles: x-y, x-z, y-z.
AXIS_PAIRS = ((0, 1), (0, 2), (1, 2))


def nonorthogonality_matrix(psi, phi, theta):
    """Upper-triangular non-orthogonality matrix ``C_NO`` of eq. (2).

    Parameters
    ----------
    psi, phi, theta : float
        Non-orthogonality angles in rad: ``psi`` is the angle between the real and ideal y axes,
        ``theta`` the angle of the real x axis out of the ideal x-y plane, ``phi`` the angle of its
        projection from the ideal x axis.

    Returns
    -------
    numpy.ndarray, shape (3, 3)
    """
    ct = np.cos(theta)
    return np.array(
        [
            [ct * np.cos(phi), ct * np.sin(phi), np.sin(theta)],
            [0.0, np.cos(psi), np.sin(psi)],
            [0.0, 0.0, 1.0],
        ]
    )


def sensor_matrix(scale, psi, phi, theta):
    """Sensor matrix ``C = S C_NO`` (dimensionless) of eq. (2).

    Parameters
    ----------
    scale : array_like, shape (3,)
        Scale factors ``k_x, k_y, k_z``.
    psi, phi, theta : float
        Non-orthogonality angles in rad (see :func:`nonorthogonality_matrix`).
    """
    return np.diag(np.asarray(scale, dtype=float)) @ nonorthogonality_matrix(psi, phi, theta)


def misalignment_matrix(alpha, beta, gamma):
    """Misalignment ``M = R1(gamma) R2(beta) R3(alpha)`` of eq. (3): ``B_i = M B_ref``.

    Parameters
    ----------
    alpha, beta, gamma : float
        Misalignment angles in rad (about z, then the new x, then the new y).

    Returns
    -------
    numpy.ndarray, shape (3, 3)
        A proper rotation. Its transpose is the correction matrix ``R`` (sensor frame -> reference frame).
    """
    ca, sa = np.cos(alpha), np.sin(alpha)
    cb, sb = np.cos(beta), np.sin(beta)
    cg, sg = np.cos(gamma), np.sin(gamma)
    r1 = np.array([[cg, 0.0, -sg], [0.0, 1.0, 0.0], [sg, 0.0, cg]])
    r2 = np.array([[1.0, 0.0, 0.0], [0.0, cb, sb], [0.0, -sb, cb]])
    r3 = np.array([[ca, sa, 0.0], [-sa, ca, 0.0], [0.0, 0.0, 1.0]])
    return r1 @ r2 @ r3


def misalignment_angles(m):
    """Invert :func:`misalignment_matrix`: angles ``(alpha, beta, gamma)`` in rad from ``M``.

    Parameters
    ----------
    m : array_like, shape (3, 3)
        ``M = R1(gamma) R2(beta) R3(alpha)``. To read angles from a correction matrix ``R`` pass ``R.T``.
    """
    m = np.asarray(m, dtype=float)
    # M[1] = (-cb sa, cb ca, sb); M[0,1] / M[2,1] carry gamma through (cg sa + sg sb ca ...) - use the
    # closed forms below, derived from the product of the three printed matrices.
    beta = np.arcsin(np.clip(m[1, 2], -1.0, 1.0))
    alpha = np.arctan2(-m[1, 0], m[1, 1])
    gamma = np.arctan2(-m[0, 2], m[2, 2])
    return np.array([alpha, beta, gamma])


def cinv_from_quadric(a_matrix):
    """Upper-triangular ``C^-1`` with positive diagonal such that ``C^-T C^-1 = A``.

    Parameters
    ----------
    a_matrix : array_like, shape (3, 3)
        Symmetric positive definite ellipsoid matrix, normalised so that the corrected field has the
        wanted magnitude.

    Raises
    ------
    numpy.linalg.LinAlgError
        If ``A`` is not positive definite.
    """
    lower = np.linalg.cholesky(np.asarray(a_matrix, dtype=float))
    return lower.T


def cinv_to_params(cinv):
    """The 6 free entries of an upper-triangular ``C^-1`` in :data:`UPPER_TRIANGLE` order."""
    cinv = np.asarray(cinv, dtype=float)
    return np.array([cinv[i, j] for i, j in UPPER_TRIANGLE])


def params_to_cinv(params):
    """Upper-triangular ``C^-1`` from its 6 free entries (:data:`UPPER_TRIANGLE` order)."""
    cinv = np.zeros((3, 3))
    for value, (i, j) in zip(params, UPPER_TRIANGLE):
        cinv[i, j] = value
    return cinv


def gauge_free(cinv):
    """Per-axis scale factors and inter-axis angles, independent of the rotation gauge of ``C^-1``.

    Parameters
    ----------
    cinv : array_like, shape (3, 3)
        Any correction matrix (upper triangular or not).

    Returns
    -------
    scale : numpy.ndarray, shape (3,)
        Sensitivity of each axis, ``k_j = sqrt((A^-1)_jj)`` with ``A = C^-T C^-1`` (dimensionless).
    axis_angles_deg : numpy.ndarray, shape (3,)
        Angles between the sensing axes x-y, x-z, y-z in degrees (90 for an orthogonal sensor).
    """
    c = np.linalg.inv(np.asarray(cinv, dtype=float))
    gram = c @ c.T  # = A^-1
    scale = np.sqrt(np.diag(gram))
    angles = np.array(
        [np.degrees(np.arccos(np.clip(gram[i, j] / (scale[i] * scale[j]), -1, 1))) for i, j in AXIS_PAIRS]
    )
    return scale, angles


def sensor_positions(baseline_m, n_sensors=4):
    """Sensor positions in the array frame (m), eq. (1): 1 at +x, 2 at +y, 3 at -x, 4 at -y.

    Parameters
    ----------
    baseline_m : float
        Distance between sensors 1 and 3 (and 2 and 4) in m.
    n_sensors : int
        1 to 4; a single sensor sits at the origin.

    Returns
    -------
    numpy.ndarray, shape (n_sensors, 3)
    """
    if n_sensors == 1:
        return np.zeros((1, 3))
    h = 0.5 * float(baseline_m)
    cross = np.array([[h, 0, 0], [0, h, 0], [-h, 0, 0], [0, -h, 0]], dtype=float)
    return cross[:n_sensors]


def tensor_components(vectors_nT, baseline_m):
    """Gradient tensor components of eq. (1) from four sensors' vectors in one frame.

    Parameters
    ----------
    vectors_nT : array_like, shape (4, N, 3)
        Field vectors of sensors 1-4 in nT, all in the same (array) frame.
    baseline_m : float
        Baseline ``d`` in m.

    Returns
    -------
    dict of str to numpy.ndarray, shape (N,)
        ``Gxx, Gxy, Gxz, Gyx, Gyy, Gyz, Gzz`` in nT/m (see :data:`TENSOR_COMPONENTS`).
    """
    b = np.asarray(vectors_nT, dtype=float)
    if b.shape[0] != 4:
        raise ValueError(f"the tensor needs four sensors, got {b.shape[0]}")
    b1, b2, b3, b4 = b
    d = float(baseline_m)
    return {
        "Gxx": (b1[:, 0] - b3[:, 0]) / d,
        "Gxy": (b2[:, 0] - b4[:, 0]) / d,
        "Gxz": (b1[:, 2] - b3[:, 2]) / d,
        "Gyx": (b1[:, 1] - b3[:, 1]) / d,
        "Gyy": (b2[:, 1] - b4[:, 1]) / d,
        "Gyz": (b2[:, 2] - b4[:, 2]) / d,
        "Gzz": (b4[:, 1] - b2[:, 1] + b3[:, 0] - b1[:, 0]) / d,
    }


def tensor_matrix(components):
    """Assemble the (N, 3, 3) tensor from :func:`tensor_components` (``Gzx = Gxz``, ``Gzy = Gyz``)."""
    c = components
    return np.stack(
        [
            np.stack([c["Gxx"], c["Gxy"], c["Gxz"]], axis=-1),
            np.stack([c["Gyx"], c["Gyy"], c["Gyz"]], axis=-1),
            np.stack([c["Gxz"], c["Gyz"], c["Gzz"]], axis=-1),
        ],
        axis=-2,
    )


def tensor_floor_nT_per_m(noise_nT, baseline_m):
    """Noise floor of the tensor components (nT/m): ``sqrt(2) sigma/d`` for one pair, ``2 sigma/d`` for Gzz."""
    pair = np.sqrt(2.0) * noise_nT / baseline_m
    return {name: (2.0 * noise_nT / baseline_m if name == "Gzz" else pair) for name in TENSOR_COMPONENTS}


def total_field_floor_nT(noise_nT, n_samples, n_params=9):
    """In-sample total-field RMS floor ``sigma sqrt(1 - p/N)`` (nT) for ``p`` fitted parameters."""
    return float(noise_nT) * np.sqrt(max(0.0, 1.0 - n_params / n_samples))


def earth_field(total_nT, declination_deg, inclination_deg):
    """Earth field vector in the world frame (north, east, down), nT."""
    d, i = np.radians(declination_deg), np.radians(inclination_deg)
    return float(total_nT) * np.array([np.cos(i) * np.cos(d), np.cos(i) * np.sin(d), np.sin(i)])
