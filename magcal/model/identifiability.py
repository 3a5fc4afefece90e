"""What total-field data can and cannot determine about a sensor on a magnetic platform.

Ding (2024) eqs. (7)-(8) write the reading of one sensor as::

    Br = K C (B + B_h + S B) + b = M B + I,     M = K C (E + S),   I = K C B_h + b

with 21 numbers: scale ``K`` (3), non-orthogonality angles in ``C`` (3), soft iron ``S`` (9), hard iron ``B_h`` (3),
bias ``b`` (3). A scalar calibration sees only ``|B| = |M^-1 (Br - I)| = F``, i.e. the quadric::

    (Br - I)^T (M M^T)^-1 (Br - I) = F^2

so the data determine exactly the symmetric matrix ``M M^T`` (6 numbers) and the offset ``I`` (3 numbers) and
nothing else:

* any split of ``M`` into ``K C`` and ``E + S`` (and of ``I`` into ``K C B_h`` and ``b``) gives *identical
  readings*, sample for sample, so no method can separate sensor errors from platform interference;
* ``M`` and ``M Q`` (``Q`` any rotation) give the same total field for every attitude, so ``M`` itself is known only
  up to a rotation; magcal fixes that gauge by taking ``C^-1`` upper triangular with a positive diagonal (the
  Cholesky factor of ``(M M^T)^-1``, the seed's convention, :func:`magcal.core.conventions.cinv_from_quadric`).

The functions here therefore report the 9 identifiable numbers (and their gauge-free forms: per-axis
sensitivities and inter-axis angles of ``M``, :func:`magcal.core.conventions.gauge_free`), from a simulation truth or
from a calibration, and never 21 "recovered" parameters. :func:`equivalent_sensor` builds a different split with
the same ``M`` and ``I``: the test suite and the documentation use it to show that the data cannot tell them apart.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from magcal.core import conventions
from magcal.core.errors import MagcalError

#: Identifiable numbers per sensor from total-field data: M M^T (6) and I (3).
IDENTIFIABLE_PER_SENSOR = 9

#: Nominal parameters per sensor in Ding's integrated model: K 3, angles 3, S 9, B_h 3, b 3.
NOMINAL_PER_SENSOR = 21


@dataclass
class Identifiable:
    """The combinations of one sensor's errors that total-field data determine.

    Attributes
    ----------
    MMt : numpy.ndarray, shape (3, 3)
        ``M M^T`` (dimensionless, symmetric positive definite), with ``M = K C (E + S)``.
    offset_nT : numpy.ndarray, shape (3,)
        Integrated offset ``I = K C B_h + b`` in nT (the ``bias_nT`` of a calibration).
    """

    MMt: np.ndarray
    offset_nT: np.ndarray

    def __post_init__(self):
        self.MMt = np.asarray(self.MMt, dtype=float).reshape(3, 3)
        self.offset_nT = np.asarray(self.offset_nT, dtype=float).reshape(3)

    @property
    def cinv(self) -> np.ndarray:
        """The correction matrix in magcal's gauge: upper triangular, positive diagonal, ``C^-T C^-1 = (M M^T)^-1``."""
        return conventions.cinv_from_quadric(np.linalg.inv(self.MMt))

    @property
    def scale(self) -> np.ndarray:
        """Gauge-free sensitivity of each axis, ``sqrt((M M^T)_jj)`` (dimensionless)."""
        return conventions.gauge_free(self.cinv)[0]

    @property
    def axis_angles_deg(self) -> np.ndarray:
        """Gauge-free angles between the effective sensing axes x-y, x-z, y-z (deg)."""
        return conventions.gauge_free(self.cinv)[1]

    def as_vector(self) -> np.ndarray:
        """The 9 numbers: upper triangle of ``M M^T`` (:data:`magcal.core.conventions.UPPER_TRIANGLE` order), then ``I``."""
        return np.concatenate([[self.MMt[i, j] for i, j in conventions.UPPER_TRIANGLE], self.offset_nT])

    def field_error_nT(self, other: Identifiable, field_nT: float) -> dict:
        """How far two sets of identifiable numbers are apart, in nT for a field of ``field_nT``.

        Returns
        -------
        dict
            ``matrix_nT``: largest change of the corrected total field over all field directions caused by the
            difference in ``M M^T`` (``F`` times the largest |eigenvalue| of ``U_a U_b^-1`` minus 1, to first order),
            ``offset_nT``: length of the offset difference, ``scale``: largest sensitivity difference,
            ``axis_angles_deg``: largest inter-axis angle difference.
        """
        ua, ub = self.cinv, other.cinv
        # corrected field of b's readings through a's correction: |U_a U_b^-1 B|; its deviation from |B| over all
        # directions is bounded by the singular values of U_a U_b^-1.
        sv = np.linalg.svd(ua @ np.linalg.inv(ub), compute_uv=False)
        return {
            "matrix_nT": float(field_nT * np.max(np.abs(sv - 1.0))),
            "offset_nT": float(np.linalg.norm(self.offset_nT - other.offset_nT)),
            "scale": float(np.max(np.abs(self.scale - other.scale))),
            "axis_angles_deg": float(np.max(np.abs(self.axis_angles_deg - other.axis_angles_deg))),
        }

    def describe(self) -> str:
        """A short text report of the identifiable numbers and their gauge-free forms."""
        lines = [
            "identifiable from total-field data (9 numbers): M M^T (6) and offset I = K C B_h + b (3)",
            "  M M^T = " + np.array2string(self.MMt, precision=6, suppress_small=True).replace("\n", "\n          "),
            "  offset I [nT] = " + np.array2string(self.offset_nT, precision=3),
            "  C^-1 (upper-triangular gauge) = "
            + np.array2string(self.cinv, precision=6, suppress_small=True).replace("\n", "\n" + " " * 35),
            "  axis sensitivities = " + np.array2string(self.scale, precision=6),
            "  inter-axis angles x-y, x-z, y-z [deg] = " + np.array2string(self.axis_angles_deg, precision=4),
            "not identifiable: the split of M into K C and (E + S), of I into K C B_h and b, and the rotation of M",
        ]
        return "\n".join(lines)


def from_matrix(m, offset_nT) -> Identifiable:
    """Identifiable combinations of ``Br = M B + I``: ``M M^T`` and ``I``.

    Parameters
    ----------
    m : array_like, shape (3, 3)
        Integrated error matrix ``M`` (dimensionless).
    offset_nT : array_like, shape (3,)
        Integrated offset ``I`` in nT.
    """
    m = np.asarray(m, dtype=float)
    return Identifiable(m @ m.T, offset_nT)


def from_truth(sensor) -> Identifiable:
    """Identifiable combinations of a simulation truth (:class:`magcal.data.simulation.SensorErrors`).

    ``M = C (E + S_soft)`` with ``C = K C_NO`` (or the explicit matrix), ``I = C B_hard + b``.
    """
    return from_matrix(sensor.total_matrix, sensor.total_offset_nT)


def from_calibration(cinv, bias_nT) -> Identifiable:
    """Identifiable combinations of a calibration ``B = C^-1 (y - b)``: ``M M^T = C C^T`` and ``I = b``.

    Any gauge of ``C^-1`` (upper triangular or rotated) gives the same result; the rotation ``R`` between sensors
    is a separate, vector-data quantity and is not used.

    Parameters
    ----------
    cinv : array_like, shape (3, 3)
    bias_nT : array_like, shape (3,)
    """
    c = np.linalg.inv(np.asarray(cinv, dtype=float))
    return Identifiable(c @ c.T, bias_nT)


def from_sensor_calibration(sensor_calibration) -> Identifiable:
    """:func:`from_calibration` for a :class:`magcal.calibration.calibration.SensorCalibration`."""
    return from_calibration(sensor_calibration.cinv, sensor_calibration.bias_nT)


def equivalent_sensor(sensor, scale=(1.0, 1.0, 1.0), psi=0.0, phi=0.0, theta=0.0, bias_nT=(0.0, 0.0, 0.0)):
    """A different split of the same ``M`` and ``I``: other sensor errors, other soft and hard iron.

    Keeps ``M = C (E + S)`` and ``I = C B_h + b`` of ``sensor`` while giving the sensor the scale factors,
    non-orthogonality angles (Chi's letters, rad, see :mod:`magcal.core.conventions`) and bias you choose; the soft and
    hard iron absorb the rest: ``S' = C'^-1 M - E``, ``B_h' = C'^-1 (I - b')``. The readings are identical sample for
    sample, so no calibration from these data can distinguish the two.

    Parameters
    ----------
    sensor : magcal.data.simulation.SensorErrors
    scale : array_like, shape (3,)
    psi, phi, theta : float
    bias_nT : array_like, shape (3,)

    Returns
    -------
    magcal.data.simulation.SensorErrors
        Same misalignment angles as ``sensor``.
    """
    m, offset = sensor.total_matrix, sensor.total_offset_nT
    c_new = conventions.sensor_matrix(scale, psi, phi, theta)
    c_inv = np.linalg.inv(c_new)
    if not np.all(np.isfinite(c_inv)):
        raise MagcalError("the chosen scale/angles give a singular sensor matrix")
    bias = np.asarray(bias_nT, dtype=float)
    return dataclasses.replace(
        sensor,
        scale=np.asarray(scale, dtype=float),
        psi=float(psi),
        phi=float(phi),
        theta=float(theta),
        matrix=None,
        bias_nT=bias,
        soft_iron=c_inv @ m - np.eye(3),
        hard_iron_nT=c_inv @ (offset - bias),
    )


def parameter_count(n_sensors=1, nominal_per_sensor=NOMINAL_PER_SENSOR) -> dict:
    """Nominal versus identifiable parameter counts for ``n_sensors`` calibrated from a uniform field.

    Per sensor 9 numbers are identifiable from total-field data; for an array, the 3 rotation angles of each sensor
    after the first relative to sensor 1 are identifiable from the vector data as well (3 x (n - 1)); the array's
    absolute orientation is not.
    """
    n = int(n_sensors)
    return {
        "nominal": n * nominal_per_sensor + (3 * (n - 1) if n > 1 else 0),
        "identifiable": n * IDENTIFIABLE_PER_SENSOR + 3 * (n - 1),
        "per_sensor_identifiable": IDENTIFIABLE_PER_SENSOR,
        "per_sensor_nominal": nominal_per_sensor,
    }
