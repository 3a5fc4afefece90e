"""Fields of the platform a vector calibration fits beside the soft and hard iron.

Every term adds to a sensor's raw reading, in the sensor's own axes (nT), and is linear in its parameters, as the
catalogue effects of the ``raw`` stage are (:mod:`magcal.model.terms`): the corrected body-frame field is
``B_body = R C^-1 (y - b - sum basis @ theta)``. They are written so that they can join the catalogue
(:data:`magcal.model.terms.EFFECTS`) for the diagnosis to propose and judge; today the vector fit
(:mod:`magcal.fitting.vector`) fits them and :class:`PlatformTerms` carries them in a calibration.

``eddy``
    Eddy currents in the airframe: a field proportional to the rate of change of the field the platform sees
    (Tolles-Lawson's eddy terms), ``y += E dy/dt`` with ``E`` a 3 x 3 matrix in ms (nT per nT/s, times 1000).
    ``dy/dt`` is the smoothed rate of the sensor's own reading (:func:`magcal.model.effects.time_derivative`),
    which is ``C R^T dB_body/dt`` to first order, so ``E`` is the eddy field per body-field rate in the sensor's
    axes. Needs the ``t`` column.
``current``
    A field per unit of a current or throttle column (``current_A`` in A, else ``throttle`` in its own unit,
    typically 0-1 or percent): ``y += k u``, ``k`` per axis in nT per unit: what ArduPilot's ``COMPASS_MOT_*``
    (per ampere or per throttle) and PX4's ``CAL_MAGn_[XYZ]COMP`` hold.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from magcal.core.errors import MagcalError
from magcal.model.effects import CURRENT_COLUMNS, current_column, time_derivative

#: Platform term names.
TERMS = ("eddy", "current")

__all__ = ["CURRENT_COLUMNS", "PlatformTerms", "TERMS", "available_terms", "current_column", "term_basis"]


def available_terms(dataset) -> list[str]:
    """The platform terms the dataset's channels support: ``eddy`` with times, ``current`` with a current or
    throttle column."""
    out = []
    if dataset.time_s is not None and dataset.n_samples >= 7:
        out.append("eddy")
    if current_column(dataset) is not None:
        out.append("current")
    return out


def reading_rate_nT_per_s(dataset, sensor) -> np.ndarray:
    """Smoothed ``dy/dt`` (N, 3) of one sensor's raw reading, nT/s (zeros without times)."""
    if dataset.time_s is None:
        return np.zeros_like(dataset.readings_nT[sensor])
    return time_derivative(dataset.readings_nT[sensor], dataset.time_s)


def term_basis(name, dataset, sensor, column=None) -> np.ndarray:
    """The basis (N, 3, q) of one term for one sensor: the reading moves by ``basis @ theta`` (nT).

    ``eddy``: q = 9, ``theta`` the matrix ``E`` row by row in ms. ``current``: q = 3, ``theta`` in nT per unit
    of ``column`` (default :func:`current_column`).
    """
    n = dataset.n_samples
    if name == "eddy":
        if dataset.time_s is None:
            raise MagcalError("the eddy-current term needs sample times (a t column)")
        rate = 1e-3 * reading_rate_nT_per_s(dataset, sensor)
        basis = np.zeros((n, 3, 9))
        for j in range(3):
            basis[:, j, 3 * j : 3 * j + 3] = rate
        return basis
    if name == "current":
        column = column or current_column(dataset)
        if column is None or column not in dataset.extra:
            raise MagcalError(
                f"{dataset.source or 'data'}: the current term needs a current_A or throttle column; the data lack it"
            )
        u = np.asarray(dataset.extra[column], dtype=float)
        basis = np.zeros((n, 3, 3))
        basis[:, [0, 1, 2], [0, 1, 2]] = u[:, None]
        return basis
    raise MagcalError(f"unknown platform term {name!r}: use {', '.join(TERMS)}")


def n_params(name) -> int:
    """Parameters per sensor of a term."""
    return {"eddy": 9, "current": 3}[name]


@dataclass
class PlatformTerms:
    """Fitted platform terms of every sensor.

    Attributes
    ----------
    eddy_ms : numpy.ndarray, shape (n_sensors, 3, 3), or None
        Eddy-current matrices ``E`` (ms): ``y += E dy/dt``.
    current_nT_per_unit : numpy.ndarray, shape (n_sensors, 3), or None
        Field per unit of :attr:`current_column` (nT per A, or per unit of throttle): ``y += k u``.
    current_column : str or None
        ``current_A`` or ``throttle``.
    """

    eddy_ms: np.ndarray | None = None
    current_nT_per_unit: np.ndarray | None = None
    current_column: str | None = None
    extra: dict = field(default_factory=dict)

    @property
    def names(self) -> list[str]:
        return [n for n, v in (("eddy", self.eddy_ms), ("current", self.current_nT_per_unit)) if v is not None]

    def missing(self, dataset) -> list[str]:
        """The channels these terms need that the dataset lacks."""
        out = []
        if self.eddy_ms is not None and dataset.time_s is None:
            out.append("t (sample times, for the eddy-current term)")
        if self.current_nT_per_unit is not None and self.current_column not in dataset.extra:
            out.append(f"{self.current_column} (for the current term)")
        return out

    def offsets_nT(self, dataset) -> np.ndarray:
        """The platform's field in every sensor's raw reading (n_sensors, N, 3), nT: subtract it from the readings."""
        missing = self.missing(dataset)
        if missing:
            raise MagcalError(
                f"the calibration holds the platform term(s) {', '.join(self.names)}, which need "
                f"{', '.join(missing)}; the data {dataset.source or ''} lack them"
            )
        out = np.zeros_like(dataset.readings_nT)
        for s in range(dataset.n_sensors):
            if self.eddy_ms is not None:
                out[s] += 1e-3 * reading_rate_nT_per_s(dataset, s) @ np.asarray(self.eddy_ms[s]).T
            if self.current_nT_per_unit is not None:
                u = np.asarray(dataset.extra[self.current_column], dtype=float)
                out[s] += u[:, None] * np.asarray(self.current_nT_per_unit[s])[None, :]
        return out

    def to_dict(self) -> dict:
        doc = {}
        if self.eddy_ms is not None:
            doc["eddy_ms"] = np.asarray(self.eddy_ms, float).tolist()
        if self.current_nT_per_unit is not None:
            doc["current_nT_per_unit"] = np.asarray(self.current_nT_per_unit, float).tolist()
            doc["current_column"] = self.current_column
        return doc

    @classmethod
    def from_dict(cls, doc, n_sensors, source="calibration") -> PlatformTerms:
        """Rebuild from :meth:`to_dict`, refusing damaged entries with one message naming the key."""
        if not isinstance(doc, dict):
            raise MagcalError(f"{source}: 'platform_terms' must be an object; the file is damaged, recalibrate")
        out = cls()
        for key, shape in (("eddy_ms", (n_sensors, 3, 3)), ("current_nT_per_unit", (n_sensors, 3))):
            if doc.get(key) is None:
                continue
            try:
                a = np.array(doc[key], dtype=float)
            except (TypeError, ValueError):
                a = np.zeros(0)
            if a.shape != shape or not np.all(np.isfinite(a)):
                raise MagcalError(
                    f"{source}: platform_terms.{key} must be {shape} finite numbers; the file is damaged, recalibrate"
                )
            setattr(out, key, a)
        if out.current_nT_per_unit is not None:
            out.current_column = doc.get("current_column")
            if out.current_column not in CURRENT_COLUMNS:
                raise MagcalError(
                    f"{source}: platform_terms.current_column must be one of {', '.join(CURRENT_COLUMNS)}; the file "
                    "is damaged, recalibrate"
                )
        return out
