"""Physical operators shared by the effects' bases and the simulator's perturbations: the reference field of
the nonlinearity terms, the play (backlash) operator of hysteresis, and the site-gradient matrix."""

from __future__ import annotations

import numpy as np

#: Field magnitude (nT) nonlinearity coefficients are quoted at when the data's own is not known (an effect never
#: configured, a calibration saved before the field was recorded with it): ``q`` nT is then the deviation of an
#: axis reading ``50 000 nT``. Otherwise they are quoted at the data's field (:func:`magcal.model.effects.data_field_magnitude_nT`).
NONLINEARITY_REFERENCE_NT = 50_000.0


def play_operator(x, half_width):
    """Backlash (play) operator: the output follows ``x`` only when it is more than ``half_width`` away.

    Parameters
    ----------
    x : numpy.ndarray, shape (N,)
        Input signal.
    half_width : float
        Half-width of the hysteresis loop (units of ``x``).
    """
    out = np.empty(len(x))
    o = float(x[0])
    h = float(half_width)
    for i, v in enumerate(np.asarray(x, dtype=float).tolist()):
        if v - o > h:
            o = v - h
        elif o - v > h:
            o = v + h
        out[i] = o
    return out


def gradient_matrix(params_nT_per_m):
    """The symmetric traceless tensor (3, 3) in nT/m from ``Gxx, Gxy, Gxz, Gyy, Gyz``."""
    return np.tensordot(np.asarray(params_nT_per_m, dtype=float), GRADIENT_BASIS, axes=1)


#: Symmetric traceless basis matrices of a gradient tensor: Gxx, Gxy, Gxz, Gyy, Gyz (Gzz = -Gxx - Gyy).
GRADIENT_BASIS = np.array(
    [
        [[1, 0, 0], [0, 0, 0], [0, 0, -1]],
        [[0, 1, 0], [1, 0, 0], [0, 0, 0]],
        [[0, 0, 1], [0, 0, 0], [1, 0, 0]],
        [[0, 0, 0], [0, 1, 0], [0, 0, -1]],
        [[0, 0, 0], [0, 0, 1], [0, 1, 0]],
    ],
    dtype=float,
)
