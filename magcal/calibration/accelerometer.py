"""The accelerometer's own calibration, kept in a gravity calibration beside the magnetometers'.

A still accelerometer reads ``a = K f + b_a + n`` (``f`` the specific force, ``+g`` up); its correction is
``f = K^-1 (a - b_a)`` with ``K^-1`` upper triangular (the seed's gauge: the accelerometer's own axes define the
board's frame, a rotation of them is not seen by gravity) and ``b_a`` in m/s^2. :class:`AccelerometerCalibration`
holds them, corrects readings and is saved in the calibration file (``accelerometer``), every entry checked when
read back.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from magcal.core.errors import MagcalError
from magcal.core.jsonable import jsonable
from magcal.data.accelerometer import STANDARD_GRAVITY_M_S2


@dataclass
class AccelerometerCalibration:
    """The accelerometer's correction ``f = K^-1 (a - b_a)``.

    Attributes
    ----------
    kinv : numpy.ndarray, shape (3, 3)
        Upper-triangular ``K^-1`` (dimensionless).
    bias_m_s2 : numpy.ndarray, shape (3,)
        Bias ``b_a`` in m/s^2.
    gravity_m_s2 : float
        The magnitude a still, corrected accelerometer reads.
    fitted : bool
        False when the record could not determine it (the readings are then used as they are: ``K^-1 = I``,
        ``b_a = 0``).
    summary : dict
        Figures of its fit (RMS of ``|f| - g``, standard deviations...), saved with it.
    """

    kinv: np.ndarray
    bias_m_s2: np.ndarray
    gravity_m_s2: float = STANDARD_GRAVITY_M_S2
    fitted: bool = True
    summary: dict = field(default_factory=dict)

    def __post_init__(self):
        self.kinv = np.asarray(self.kinv, dtype=float)
        self.bias_m_s2 = np.asarray(self.bias_m_s2, dtype=float)

    @classmethod
    def identity(cls) -> AccelerometerCalibration:
        """The readings as they are (an accelerometer the firmware has calibrated, or one the record cannot)."""
        return cls(np.eye(3), np.zeros(3), fitted=False)

    def correct(self, accel_m_s2) -> np.ndarray:
        """Specific force (N, 3) in m/s^2 in the board's axes from readings (N, 3) in m/s^2."""
        return (np.asarray(accel_m_s2, dtype=float) - self.bias_m_s2) @ self.kinv.T

    def to_dict(self) -> dict:
        doc = {
            "Kinv": self.kinv.tolist(),
            "bias_m_s2": self.bias_m_s2.tolist(),
            "gravity_m_s2": float(self.gravity_m_s2),
            "fitted": bool(self.fitted),
        }
        doc.update(jsonable(self.summary))
        return doc

    @classmethod
    def from_dict(cls, doc, source="calibration") -> AccelerometerCalibration:
        """Rebuild from :meth:`to_dict`, refusing a damaged entry with one message.

        Raises
        ------
        MagcalError
            Not a mapping, wrong shapes, values that are not finite, a ``Kinv`` that is not upper triangular with a
            positive diagonal, a gravity that is not positive.
        """
        damaged = f"{source}: the 'accelerometer' entry is damaged ({{}}); recalibrate"
        if not isinstance(doc, dict):
            raise MagcalError(damaged.format("not a mapping"))
        try:
            kinv = np.array(doc["Kinv"], dtype=float)
            bias = np.array(doc["bias_m_s2"], dtype=float)
            gravity = float(doc.get("gravity_m_s2", STANDARD_GRAVITY_M_S2))
        except (KeyError, TypeError, ValueError) as exc:
            raise MagcalError(damaged.format(f"Kinv and bias_m_s2 must be numbers: {exc}")) from None
        if kinv.shape != (3, 3) or bias.shape != (3,):
            raise MagcalError(damaged.format("Kinv must be 3 x 3 and bias_m_s2 three numbers"))
        if not (np.all(np.isfinite(kinv)) and np.all(np.isfinite(bias)) and np.isfinite(gravity) and gravity > 0):
            raise MagcalError(damaged.format("values must be finite and gravity_m_s2 positive"))
        if np.any(np.tril(kinv, -1) != 0) or np.any(np.diag(kinv) <= 0):
            raise MagcalError(damaged.format("Kinv must be upper triangular with a positive diagonal"))
        summary = {k: v for k, v in doc.items() if k not in ("Kinv", "bias_m_s2", "gravity_m_s2", "fitted")}
        return cls(kinv, bias, gravity, bool(doc.get("fitted", True)), summary)
