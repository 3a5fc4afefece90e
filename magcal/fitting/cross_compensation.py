"""The compensation of the four-sensor cross on a moving platform: each sensor's platform field, and with it the
gradient tensor's platform signature, fitted on a compensation box and taken out of any line.

Each fluxgate ``i`` reads, in its own frame, its calibration (``C_i``, misalignment ``M_i``, bias ``b_i``) applied to
the Earth field plus the platform's field at its place (:mod:`magcal.data.cross_flight`)::

    y_i = C_i M_i (B + p_i + A_i B + E_i dB/dt) + b_i + n_i = W_i B + E'_i dB/dt + o_i + n_i

The Tolles-Lawson terms of a vector sensor: the permanent field and the bias merge into the offset ``o_i`` (nT),
the induced field and the sensor's scale, non-orthogonality and misalignment into the matrix ``W_i = C_i M_i (I +
A_i)`` (the platform's soft iron and the sensor's calibration are one linear map, as in Ding 2024, eq. 8), and the
eddy currents into ``E'_i`` (s, per nT/s of the field's rate). All are linear, so the fit is a least squares per
sensor against a reference field ``B`` (body frame) and its rate:

* ``reference="attitude"``: the Earth field's direction from the attitude, ``B = R(q)^T B_ned``, with the Earth
  field vector given (an IGRF value, or one per sample with a base station's diurnal record): the sensor's
  calibration and its platform field are fitted jointly, in the body frame;
* ``reference="mean"``: the array's own mean field, without attitude: each sensor is balanced against the mean of
  the four (calibrated first when a calibration is given). The gradients between the four go; the field common to
  all four stays, in the frame of their mean.

The fit is the anchors' (MagNav.jl, the Tolles-Lawson fit of :mod:`magcal.fitting.tolles_lawson`): the reference's
three components and their rates (the design), and each sensor's three axes (the targets), band-passed alike
(0.1-0.9 Hz), the filter's start-up trimmed, the maneuvers optionally selected, then linear least squares; the
offset is the unfiltered residual's mean. The band-pass removes the diurnal drift and any slow error of the
reference; the box's maneuvers turn the field about every body axis at four headings, so the band-passed design
determines all of ``W_i`` and ``E'_i``.

What the reference gets wrong is common to the four sensors, and the tensor does not see it: an attitude's error
(a regressor with noise biases each fit towards zero alike: errors in variables), a diurnal drift the reference
lacks (a uniform field that turns with the platform), the mean's own calibration. Each sensor's total field does.
So the magnitude passes (``magnitude_passes``, two by default) fit the compensated four's mean field as its own
fluxgate and scalar: a Tolles-Lawson fit of its magnitude (band-passed, so the Earth field's size need not be
known) on its own direction cosines, without the two diagonal terms a constant ``|B|`` cannot fix
(:data:`MAGNITUDE_TERMS`) and with a small ridge on what it sees only to second order, and the vector field that fit holds (:func:`magnitude_pass`) is taken out of every
sensor. The second pass takes what the first's linearisation left (a percent's distortion leaves ``(0.01 B)^2 /
2 B``, 2.5 nT at 50 000 nT). Then each sensor's total field is at its noise floor whatever the reference.

A platform current (a battery's, a motor's) is a field per ampere the Tolles-Lawson terms do not hold: given its
series (``current_A``), each sensor's field per ampere ``k_i`` (nT/A) is one more column of its fit, and the
magnitude passes fit the four's common one.

A line is compensated (:meth:`CrossCompensation.compensate`) by taking out the current's field when there is one and
inverting each sensor's model: first ``B_i = W_i^-1
(y_i - o_i)``, the rate from the four's mean, then ``B_i = W_i^-1 (y_i - o_i - E'_i dB/dt)``. The compensated tensor
is the tensor of the compensated sensors (eq. 1, :func:`magcal.core.conventions.tensor_components`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from magcal.core import conventions
from magcal.core.errors import MagcalError
from magcal.core.jsonable import jsonable
from magcal.data.attitude import attitude as dataset_attitude
from magcal.data.dataset import Dataset
from magcal.fitting.compensation import best_time_offset, shifted
from magcal.fitting.tolles_lawson import sample_rate_from_times, solve_ridge
from magcal.model.tolles_lawson import (
    DEFAULT_PASSBAND_HZ,
    Conditioning,
    bandpass,
    bandpass_columns,
    conditioning,
    design_matrix,
    per_sample_difference,
    term_labels,
)

__all__ = [
    "KIND",
    "MAGNITUDE_RIDGE",
    "MAGNITUDE_TERMS",
    "REFERENCES",
    "CrossArrays",
    "CrossCompensation",
    "SensorCompensation",
    "cross_arrays",
    "fit_cross_compensation",
    "is_cross_compensation_document",
    "magnitude_pass",
]

#: The Tolles-Lawson terms of a magnitude pass (the induced and eddy diagonals' last terms left out: their gauges).
MAGNITUDE_TERMS = ("permanent", "induced5", "eddy8")

#: A magnitude pass's ridge (:func:`magnitude_pass`).
MAGNITUDE_RIDGE = 1e-5

#: The ``kind`` of the cross compensation's JSON document.
KIND = "cross_compensation"


def is_cross_compensation_document(doc) -> bool:
    """Whether a parsed JSON document is the cross's compensation (``kind: "cross_compensation"``)."""
    return isinstance(doc, dict) and doc.get("kind") == KIND


#: The reference fields a fit can take (``auto``: the attitude when there is one and an Earth field vector).
REFERENCES = ("auto", "attitude", "mean")


@dataclass
class CrossArrays:
    """The four sensors' readings and what goes with them, from whatever the caller gave.

    Attributes
    ----------
    readings_nT : numpy.ndarray, shape (4, N, 3)
    sample_rate_hz : float or None
    attitude : scipy.spatial.transform.Rotation or None
        Body -> NED, one per sample.
    baseline_m : float or None
    """

    readings_nT: np.ndarray
    sample_rate_hz: float | None
    attitude: Rotation | None
    baseline_m: float | None


def _attitude_from_deg(attitude_deg, n: int) -> Rotation:
    att = np.asarray(attitude_deg, dtype=float)
    if att.shape != (n, 3) or not np.isfinite(att).all():
        raise MagcalError(f"the attitude must be an ({n}, 3) array of finite roll, pitch, yaw in degrees")
    return Rotation.from_euler("ZYX", att[:, ::-1], degrees=True)


def cross_arrays(data, *, sample_rate_hz=None, time_s=None, attitude_deg=None, baseline_m=None) -> CrossArrays:
    """The readings (4, N, 3), rate, attitude and baseline of ``data``: a :class:`~magcal.data.dataset.Dataset`
    of four sensors, a simulated :class:`~magcal.data.cross_flight.CrossFlight`, or an array (4, N, 3) of nT; the
    keywords fill or override what ``data`` lacks."""
    rotation = None
    if isinstance(data, Dataset):
        readings = np.asarray(data.readings_nT, dtype=float)
        time_s = data.time_s if time_s is None else time_s
        rotation = dataset_attitude(data)
        baseline_m = data.baseline_m if baseline_m is None else baseline_m
    elif hasattr(data, "readings_nT") and hasattr(data, "sample_rate_hz"):
        readings = np.asarray(data.readings_nT, dtype=float)
        sample_rate_hz = data.sample_rate_hz if sample_rate_hz is None else sample_rate_hz
        attitude_deg = getattr(data, "attitude_deg", None) if attitude_deg is None else attitude_deg
        baseline_m = getattr(data, "baseline_m", None) if baseline_m is None else baseline_m
    else:
        readings = np.asarray(data, dtype=float)
    if readings.ndim != 3 or readings.shape[0] != 4 or readings.shape[2] != 3:
        raise MagcalError(
            f"the cross's compensation needs four sensors' readings, an array (4, N, 3) of nT; got shape "
            f"{readings.shape}"
        )
    bad = ~np.isfinite(readings).all(axis=(0, 2))
    if bad.any():
        raise MagcalError(
            f"{int(bad.sum())} sample(s) have a missing or non-finite reading (first at row {int(np.argmax(bad))}): "
            "fill or cut them before the compensation"
        )
    if attitude_deg is not None:
        rotation = _attitude_from_deg(attitude_deg, readings.shape[1])
    if sample_rate_hz is None and time_s is not None:
        sample_rate_hz = sample_rate_from_times(time_s)
    if sample_rate_hz is not None and (not np.isfinite(sample_rate_hz) or sample_rate_hz <= 0):
        raise MagcalError(f"the sample rate must be a positive number of Hz, got {sample_rate_hz!r}")
    return CrossArrays(readings, sample_rate_hz, rotation, None if baseline_m is None else float(baseline_m))


@dataclass
class SensorCompensation:
    """One sensor's fitted model ``y = W B + E' dB/dt + o`` (its own frame, against the reference field).

    Attributes
    ----------
    matrix : numpy.ndarray, shape (3, 3)
        ``W``: the reading per reference field (dimensionless): the sensor's calibration and the induced field.
    eddy_s : numpy.ndarray, shape (3, 3)
        ``E'``: the reading per rate of the reference field (nT per nT/s = s).
    offset_nT : numpy.ndarray, shape (3,)
        ``o``: the permanent field and the bias (nT).
    residual_std_nT : numpy.ndarray, shape (3,)
        Each axis's band-passed residual's standard deviation over the fitted samples (nT).
    conditioning : Conditioning
        Of the band-passed design (the reference's components and rates).
    current_nT_per_A : numpy.ndarray, shape (3,) or (K, 3)
        ``k``: the reading per ampere of the platform's current (nT/A; zeros when the fit had no current), one row
        per current column when the fit had several (K).
    """

    matrix: np.ndarray
    eddy_s: np.ndarray
    offset_nT: np.ndarray
    residual_std_nT: np.ndarray
    conditioning: Conditioning | None = None
    current_nT_per_A: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def to_dict(self) -> dict:
        return jsonable(
            {
                "matrix": self.matrix,
                "eddy_s": self.eddy_s,
                "offset_nT": self.offset_nT,
                "residual_std_nT": self.residual_std_nT,
                "conditioning": None if self.conditioning is None else self.conditioning.to_dict(),
                "current_nT_per_A": self.current_nT_per_A,
            }
        )

    @property
    def per_ampere(self) -> np.ndarray:
        """``k`` as rows, one per current column (K, 3), nT/A."""
        return np.asarray(self.current_nT_per_A, dtype=float).reshape(-1, 3)

    @classmethod
    def from_dict(cls, d: dict) -> SensorCompensation:
        cond = d.get("conditioning")
        return cls(
            matrix=np.asarray(d["matrix"], dtype=float).reshape(3, 3),
            eddy_s=np.asarray(d["eddy_s"], dtype=float).reshape(3, 3),
            offset_nT=np.asarray(d["offset_nT"], dtype=float).reshape(3),
            residual_std_nT=np.asarray(d.get("residual_std_nT", [np.nan] * 3), dtype=float),
            conditioning=Conditioning.from_dict(cond) if cond else None,
            current_nT_per_A=_per_ampere(np.asarray(d.get("current_nT_per_A", [0.0] * 3), dtype=float)),
        )


@dataclass
class CrossCompensation:
    """The cross's compensation: four sensors' fitted models, and the lines they compensate.

    Attributes
    ----------
    sensors : list of SensorCompensation
    reference : str
        ``"attitude"`` or ``"mean"`` (module docstring).
    sample_rate_hz : float
        The compensation flight's rate (Hz).
    baseline_m : float or None
        The cross's baseline (m), for the tensor.
    passband_hz : (float, float)
    trim : int
    precalibrated : bool
        True when the fit was made on vectors a calibration had corrected (:meth:`compensate` then takes the same
        calibration; it is not stored here).
    magnitude_passes : int
        The magnitude passes made (already folded into each sensor's model).
    current : bool
        True when the fit had the platform's current (a line then needs its current too).
    current_column : str or None
        The record's column the current was read from (a line's is looked up by the same name): the first of
        :attr:`current_columns`.
    current_columns : tuple of str
        The record's current columns the fit took, in the order of each sensor's ``current_nT_per_A`` rows (empty
        for one unnamed current).
    notes : list of str
    time_offset_s : float
        How late the sensors' samples are against the attitude's (and the current's), s: a line's readings are read
        this much later (:func:`magcal.fitting.compensation.shifted`) before their models are inverted.
    """

    sensors: list[SensorCompensation]
    reference: str
    sample_rate_hz: float
    baseline_m: float | None = None
    passband_hz: tuple[float, float] = DEFAULT_PASSBAND_HZ
    trim: int = 20
    precalibrated: bool = False
    magnitude_passes: int = 0
    current: bool = False
    current_column: str | None = None
    notes: list[str] = field(default_factory=list)
    time_offset_s: float = 0.0
    current_columns: tuple = ()

    def compensate(self, data, *, sample_rate_hz=None, time_s=None, calibration=None, current_A=None) -> np.ndarray:
        """The compensated vectors (4, N, 3) of a line (nT, body frame for an ``attitude`` fit, the four's mean
        frame for a ``mean`` fit).

        Parameters
        ----------
        data : Dataset, CrossFlight or array_like, shape (4, N, 3)
            The line's raw readings (nT).
        sample_rate_hz, time_s : optional
            The line's rate (else the data's, else the fit's): the eddy term needs the field's rate in nT/s.
        calibration : magcal.calibration.calibration.Calibration, optional
            The calibration the fit was made after (:attr:`precalibrated`), applied to the readings first.
        current_A : array_like, shape (N,) or (N, K), or dict, optional
            The platform's current along the line (A), needed when the fit had one (:attr:`current`): one column
            per current the fit took, or a dict of the line's columns by name (:attr:`current_columns` are taken).
        """
        arrays = cross_arrays(data, sample_rate_hz=sample_rate_hz, time_s=time_s)
        rate = arrays.sample_rate_hz or self.sample_rate_hz
        if self.precalibrated and calibration is None:
            raise MagcalError(
                "this compensation was fitted on calibrated vectors: give the same calibration (calibration=...)"
            )
        if calibration is not None and not self.precalibrated:
            raise MagcalError("this compensation was fitted on raw readings: give no calibration")
        y = arrays.readings_nT if calibration is None else np.asarray(calibration.correct(arrays.readings_nT))
        y = read_later(y, self.time_offset_s * rate)
        if self.current and current_A is None:
            raise MagcalError("this compensation was fitted with the platform's current: give the line's (current_A)")
        if current_A is not None:
            current = _checked_current(self._line_currents(current_A), y.shape[1])
            y = y - self.current_field(current)
        return self.inverted(y, rate)

    def _line_currents(self, current_A):
        if not isinstance(current_A, dict):
            return current_A
        names = self.current_columns or (self.current_column or "current_A",)
        missing = [c for c in names if c not in current_A]
        if missing:
            raise MagcalError(
                f"the line has no current column {missing[0]!r} (the compensation took {', '.join(names)}); its "
                "currents: " + (", ".join(current_A) or "none")
            )
        return np.column_stack([np.asarray(current_A[c], dtype=float) for c in names])

    def current_field(self, current_A) -> np.ndarray:
        """Each sensor's field of the platform's currents (4, N, 3), nT: ``current_A`` (N, K) A times each
        sensor's rows of ``current_nT_per_A``."""
        current = np.asarray(current_A, dtype=float).reshape(np.shape(current_A)[0], -1)
        return np.stack([current @ s.per_ampere for s in self.sensors])

    def inverted(self, vectors_nT, sample_rate_hz: float) -> np.ndarray:
        """Each sensor's model inverted on vectors (4, N, 3) as the fit saw them (raw, or calibrated when
        :attr:`precalibrated`), nT: ``W^-1 (y - o - E' dB/dt)``, the rate (nT/s at ``sample_rate_hz``) from the
        four's mean after a first ``W^-1 (y - o)``."""
        y, rate = np.asarray(vectors_nT, dtype=float), float(sample_rate_hz)
        inverses = [np.linalg.inv(s.matrix) for s in self.sensors]
        first = np.stack([(y[i] - s.offset_nT) @ inverses[i].T for i, s in enumerate(self.sensors)])
        field_rate = per_sample_difference(first.mean(axis=0)) * rate
        return np.stack(
            [(y[i] - s.offset_nT - field_rate @ s.eddy_s.T) @ inverses[i].T for i, s in enumerate(self.sensors)]
        )

    def tensor(self, data, *, sample_rate_hz=None, time_s=None, calibration=None, current_A=None) -> dict:
        """The compensated gradient tensor's components (eq. 1, nT/m) of a line (the arguments as in
        :meth:`compensate`)."""
        if not self.baseline_m:
            raise MagcalError("the tensor needs the cross's baseline: fit with baseline_m (m)")
        compensated = self.compensate(
            data, sample_rate_hz=sample_rate_hz, time_s=time_s, calibration=calibration, current_A=current_A
        )
        return conventions.tensor_components(compensated, self.baseline_m)

    def to_dict(self) -> dict:
        """A JSON-ready document of the compensation (:meth:`from_dict` reads it back)."""
        return jsonable(
            {
                "kind": "cross_compensation",
                "reference": self.reference,
                "sample_rate_hz": self.sample_rate_hz,
                "baseline_m": self.baseline_m,
                "passband_hz": list(self.passband_hz),
                "trim": self.trim,
                "precalibrated": self.precalibrated,
                "magnitude_passes": self.magnitude_passes,
                "current": self.current,
                "current_column": self.current_column,
                "current_columns": list(self.current_columns),
                "time_offset_s": self.time_offset_s,
                "sensors": [s.to_dict() for s in self.sensors],
                "notes": list(self.notes),
            }
        )

    def to_json(self) -> str:
        return json.dumps(self.to_dict())

    @classmethod
    def from_dict(cls, d: dict) -> CrossCompensation:
        """The compensation a :meth:`to_dict` document holds."""
        if d.get("kind") != "cross_compensation":
            raise MagcalError("not a cross compensation document (its 'kind' is not 'cross_compensation')")
        if len(d.get("sensors", [])) != 4:
            raise MagcalError("a cross compensation document holds four sensors' models")
        return cls(
            sensors=[SensorCompensation.from_dict(s) for s in d["sensors"]],
            reference=str(d["reference"]),
            sample_rate_hz=float(d["sample_rate_hz"]),
            baseline_m=None if d.get("baseline_m") is None else float(d["baseline_m"]),
            passband_hz=(float(d["passband_hz"][0]), float(d["passband_hz"][1])),
            trim=int(d["trim"]),
            precalibrated=bool(d.get("precalibrated", False)),
            magnitude_passes=int(d.get("magnitude_passes", 0)),
            current=bool(d.get("current", False)),
            current_column=d.get("current_column"),
            current_columns=tuple(map(str, d.get("current_columns") or ())),
            notes=list(d.get("notes", [])),
            time_offset_s=float(d.get("time_offset_s", 0.0)),
        )

    @classmethod
    def from_json(cls, text: str) -> CrossCompensation:
        return cls.from_dict(json.loads(text))

    def save(self, path) -> None:
        """Write the JSON document (:meth:`to_dict`) to ``path``."""
        with open(path, "w", encoding="utf-8") as fh:
            json.dump(self.to_dict(), fh, indent=2)
            fh.write("\n")

    @classmethod
    def load(cls, path) -> CrossCompensation:
        """The compensation a JSON file written by :meth:`save` holds (a :class:`~magcal.core.errors.MagcalError` naming the file
        otherwise)."""
        try:
            with open(path, encoding="utf-8") as fh:
                doc = json.load(fh)
        except (OSError, ValueError) as exc:
            raise MagcalError(f"{path}: cannot read the cross compensation: {exc}") from None
        try:
            return cls.from_dict(doc)
        except (KeyError, TypeError, ValueError) as exc:
            raise MagcalError(f"{path}: not a complete cross compensation document ({exc})") from None

    def text(self) -> str:
        """Per sensor: the matrix's departure from the identity (ppm), the eddy terms' largest (ms), the offset (nT),
        the band-passed residual (nT); the current's field per ampere, the design's conditioning, the magnitude
        passes."""
        where = "the attitude's Earth field" if self.reference == "attitude" else "the four sensors' mean field"
        lines = [f"cross compensation against {where}, {self.sample_rate_hz:g} Hz, band {self.passband_hz} Hz"]
        lines.append(f"{'sensor':>6} {'|W-I| max ppm':>14} {'|E| max ms':>11} {'offset nT':>26} {'residual nT':>20}")
        for k, s in enumerate(self.sensors, start=1):
            w = np.max(np.abs(s.matrix - np.eye(3))) * 1e6
            e = np.max(np.abs(s.eddy_s)) * 1e3
            off = " ".join(f"{v:8.1f}" for v in s.offset_nT)
            res = " ".join(f"{v:6.3f}" for v in s.residual_std_nT)
            lines.append(f"{k:>6} {w:14.0f} {e:11.3f} {off:>26} {res:>20}")
        if self.time_offset_s:
            lines.append(
                f"the sensors' time offset {self.time_offset_s * 1e3:+.1f} ms (positive: late against the attitude)"
            )
        if self.current:
            names = self.current_columns or (self.current_column or "the current",)
            for j, name in enumerate(names):
                lines.append(
                    f"field per ampere of {name} (nT/A): "
                    + "; ".join(" ".join(f"{v:.3f}" for v in s.per_ampere[j]) for s in self.sensors)
                )
        cond = [s.conditioning.condition_number_scaled for s in self.sensors if s.conditioning is not None]
        if cond:
            lines.append(f"condition number of the band-passed design (columns scaled) {max(cond):.3g}")
        lines.append(f"magnitude passes: {self.magnitude_passes}")
        return "\n".join(lines + self.notes)


def _reference_field(arrays: CrossArrays, vectors, reference: str, field_ned_nT) -> tuple[str, np.ndarray]:
    """The reference's name and field (N, 3) nT, body frame."""
    if reference not in REFERENCES:
        raise MagcalError(f"unknown reference {reference!r}: use one of " + ", ".join(REFERENCES))
    if reference == "auto":
        reference = "attitude" if arrays.attitude is not None and field_ned_nT is not None else "mean"
    if reference == "mean":
        return reference, vectors.mean(axis=0)
    if arrays.attitude is None:
        raise MagcalError("reference='attitude' needs the attitude (roll, pitch, yaw, or a dataset's quaternions)")
    if field_ned_nT is None:
        raise MagcalError("reference='attitude' needs the Earth field vector (field_ned_nT, nT north-east-down)")
    ned = np.asarray(field_ned_nT, dtype=float)
    n = vectors.shape[1]
    if ned.shape not in ((3,), (n, 3)) or not np.isfinite(ned).all():
        raise MagcalError(
            f"the Earth field vector must be three finite nT (north, east, down), or one such row per sample ({n}, 3); "
            f"got shape {ned.shape}"
        )
    return reference, arrays.attitude.inv().apply(ned)


def read_later(vectors_nT, samples: float) -> np.ndarray:
    """Each sensor's readings (4, N, 3) read ``samples`` later (:func:`magcal.fitting.compensation.shifted`)."""
    v = np.asarray(vectors_nT, dtype=float)
    return v if samples == 0 else np.stack([shifted(sensor, samples) for sensor in v])


def _sensor_fits(vectors, design, design_bp, kept, rate, passband_hz, ridge, cond) -> tuple[list, float]:
    """Each sensor's least-squares fit on the band-passed design, and the sum of squares of their band-passed
    residuals (nT^2)."""
    n = design.shape[0]
    targets = np.asarray(vectors, dtype=float).transpose(1, 0, 2).reshape(n, -1)  # the four's twelve axes
    targets_bp = bandpass(targets, rate, passband_hz)
    coefficients = solve_ridge(design_bp[kept], targets_bp[kept], float(ridge))  # one design for every axis
    residual = targets_bp[kept] - design_bp[kept] @ coefficients
    offsets = np.mean(targets[kept] - design[kept] @ coefficients, axis=0)
    sensors = []
    for i in range(len(vectors)):
        c = coefficients[:, 3 * i : 3 * i + 3]
        current = _per_ampere(c[6:]) if design.shape[1] > 6 else np.zeros(3)
        std = residual[:, 3 * i : 3 * i + 3].std(axis=0)
        sensors.append(SensorCompensation(c[:3].T, c[3:6].T, offsets[3 * i : 3 * i + 3], std, cond, current))
    return sensors, float(np.sum(residual**2))


def _lag_cost(vectors, design_bp_kept, kept, rate, passband_hz, ridge):
    """The four sensors' band-passed residual's sum of squares (nT^2) with their readings read ``tau`` (s) later:
    the design's orthonormal basis is taken once (``|y|^2 - |Q^T y|^2``), for the search over ``tau``."""
    q = design_bp_kept.shape[1]
    augmented = np.vstack([design_bp_kept, np.sqrt(float(ridge)) * np.eye(q)]) if ridge > 0 else design_bp_kept
    basis = np.linalg.qr(augmented)[0][: design_bp_kept.shape[0]]
    n = vectors.shape[1]

    def cost(tau: float) -> float:
        later = read_later(vectors, tau * rate).transpose(1, 0, 2).reshape(n, -1)
        targets = bandpass(later, rate, passband_hz)[kept]
        return float(np.sum(targets**2) - np.sum((basis.T @ targets) ** 2))

    return cost


def _per_ampere(rows) -> np.ndarray:
    """A sensor's field per ampere: (3,) for one current, (K, 3) for several."""
    k = np.asarray(rows, dtype=float).reshape(-1, 3)
    return k[0] if k.shape[0] == 1 else k


def _checked_current(current_A, n: int) -> np.ndarray:
    """The currents as (N, K), A."""
    current = np.asarray(current_A, dtype=float)
    if current.ndim == 1:
        current = current[:, None]
    if current.ndim != 2 or current.shape[0] != n:
        raise MagcalError(
            f"the current has shape {np.shape(current_A)}; the readings have {n} samples: one ampere value each "
            "(a column per current)"
        )
    bad = ~np.isfinite(current)
    if bad.any():
        raise MagcalError(
            f"the current has {int(bad.sum())} missing or non-finite value(s) (first at row {int(np.argmax(bad))}): "
            "fill or cut them before the compensation"
        )
    return current


def _kept(n: int, trim: int, mask, q: int) -> np.ndarray:
    if n <= 2 * trim + q:
        raise MagcalError(f"{n} samples are too few for the cross's compensation after trimming {trim} at each end")
    kept = np.zeros(n, dtype=bool)
    kept[trim : n - trim] = True
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != (n,):
            raise MagcalError(f"the mask has shape {mask.shape}, the readings {n} samples")
        kept &= mask
    if kept.sum() <= 3 * q:
        raise MagcalError(f"only {int(kept.sum())} samples are kept for {q} terms per axis: widen the mask")
    return kept


def fit_cross_compensation(
    data,
    *,
    reference: str = "auto",
    field_ned_nT=None,
    calibration=None,
    sample_rate_hz: float | None = None,
    time_s=None,
    attitude_deg=None,
    baseline_m: float | None = None,
    passband_hz=DEFAULT_PASSBAND_HZ,
    trim: int = 20,
    ridge: float = 0.0,
    mask=None,
    magnitude_passes: int = 2,
    current_A=None,
    time_offset: bool = False,
) -> CrossCompensation:
    """Fit the cross's compensation on a compensation flight.

    Parameters
    ----------
    data : Dataset, CrossFlight or array_like, shape (4, N, 3)
        The four sensors' readings (nT, each in its own frame), evenly sampled; a dataset or a simulated flight
        brings its rate, attitude and baseline.
    reference : {"auto", "attitude", "mean"}
        The field each sensor is fitted against (module docstring); ``auto`` takes the attitude when there is one
        and ``field_ned_nT`` is given, else the mean.
    field_ned_nT : array_like, shape (3,) or (N, 3), optional
        The Earth field vector at the box (nT, north-east-down), for ``reference="attitude"``: a constant (IGRF),
        or one per sample (IGRF plus a base station's record of the diurnal variation). The diurnal variation is a
        uniform field: it turns with the platform in the body frame, so a reference without it leaves its turning
        (the drift's size times the maneuvers' angle, a few tenths of nT) in each sensor's total field; the tensor
        does not see it.
    calibration : magcal.calibration.calibration.Calibration, optional
        A calibration of the four sensors (the seed's, from turning the cross in a uniform field) applied to the
        readings before the fit; then the fitted matrices are ``I + A_i`` (the induced field alone), and
        :meth:`CrossCompensation.compensate` takes the same calibration.
    sample_rate_hz : float, optional
        Samples per second (else from ``time_s`` or the data).
    time_s : array_like, shape (N,), optional
    attitude_deg : array_like, shape (N, 3), optional
        Roll, pitch, yaw (deg, aerospace ZYX, body -> NED).
    baseline_m : float, optional
        The cross's baseline (m), for the tensor (else the data's).
    passband_hz : (float, float)
        The band-pass's edges (Hz).
    trim : int
        Samples dropped at each end after the band-pass.
    ridge : float
        Added to the band-passed normal matrix's diagonal (0: plain least squares).
    mask : array_like of bool, shape (N,), optional
        Samples the fit uses (after the band-pass over the whole flight), e.g. the maneuvers.
    magnitude_passes : int
        Tolles-Lawson fits on the compensated four's mean field, its magnitude against its own direction cosines,
        each taken out of every sensor as a vector field (0: none). They correct what the reference leaves in the
        field common to the four: an attitude's error (its errors-in-variables bias of each fit), a diurnal drift
        the reference lacks, and, for ``reference="mean"``, the mean sensor's own calibration, to first order.
    current_A : array_like, shape (N,) or (N, K), optional
        The platform's current (A), a battery's or a motor's, or K currents (a platform's wires each carry their
        own): each sensor's field per ampere of each is fitted with the other terms (Tolles-Lawson has no such
        term), and a line is compensated with its own currents.
    time_offset : bool
        Fit how late the sensors' samples are against the attitude (and the current), within
        +-0.5 s (:data:`magcal.fitting.compensation.MAX_TIME_OFFSET_S`): the readings are read that much later before the fit, the offset found as the
        scalar compensation's fluxgate offset is (:func:`magcal.fitting.compensation.best_time_offset`, the four
        sensors' band-passed residual). A lag's first order is an eddy term's (``-W tau dB/dt``) and the eddy
        matrices take it; its second order, and the current's lag, they cannot. Needs the attitude reference.

    Returns
    -------
    CrossCompensation
    """
    arrays = cross_arrays(
        data, sample_rate_hz=sample_rate_hz, time_s=time_s, attitude_deg=attitude_deg, baseline_m=baseline_m
    )
    if arrays.sample_rate_hz is None:
        raise MagcalError("give the sample rate (sample_rate_hz) or the samples' times (time_s)")
    rate = float(arrays.sample_rate_hz)
    vectors = arrays.readings_nT if calibration is None else np.asarray(calibration.correct(arrays.readings_nT))
    reference, b_ref = _reference_field(arrays, vectors, reference, field_ned_nT)
    columns = [b_ref, per_sample_difference(b_ref) * rate]
    if current_A is not None:
        columns.append(_checked_current(current_A, b_ref.shape[0]))
    design = np.column_stack(columns)
    kept = _kept(design.shape[0], int(trim), mask, design.shape[1])
    design_bp = bandpass_columns(design, rate, passband_hz)
    cond = conditioning(design_bp[kept])
    fits = (design, design_bp, kept, rate, passband_hz, ridge, cond)
    offset_s = 0.0
    if time_offset:
        if reference != "attitude":
            raise MagcalError(
                "the sensors' time offset is found against the attitude: it needs reference='attitude' and the "
                "Earth field vector (the four's mean field lags with them)"
            )
        offset_s = best_time_offset(_lag_cost(vectors, design_bp[kept], kept, rate, passband_hz, ridge))
        vectors = read_later(vectors, offset_s * rate)
    sensors, _ = _sensor_fits(vectors, *fits)
    result = CrossCompensation(
        sensors=sensors,
        reference=reference,
        sample_rate_hz=rate,
        baseline_m=arrays.baseline_m,
        passband_hz=(float(passband_hz[0]), float(passband_hz[1])),
        trim=int(trim),
        precalibrated=calibration is not None,
        magnitude_passes=int(magnitude_passes),
        current=current_A is not None,
        time_offset_s=offset_s,
    )
    current = design[:, 6:] if current_A is not None else np.zeros((design.shape[0], 1))
    for _ in range(int(magnitude_passes)):
        without_current = vectors - result.current_field(current)
        common = result.inverted(without_current, rate).mean(axis=0)
        field = magnitude_pass(
            common, rate, passband_hz=passband_hz, kept=kept, current_A=None if current_A is None else current
        )
        result.sensors = [_with_platform_residual(sensor, *field) for sensor in result.sensors]
    if reference == "mean":
        result.notes.append(
            "balanced against the four sensors' mean field"
            + (
                "; the field common to the four fitted from their mean's magnitude (Tolles-Lawson, to first order)"
                if magnitude_passes
                else ": the tensor is compensated, the field common to the four (the mean platform field) is not"
            )
        )
    return result


def magnitude_pass(
    field_nT,
    sample_rate_hz: float,
    *,
    passband_hz=DEFAULT_PASSBAND_HZ,
    kept=None,
    ridge: float = MAGNITUDE_RIDGE,
    current_A=None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The platform field left in a compensated vector (N, 3), from its magnitude: a Tolles-Lawson fit of ``|B|``
    on its own direction cosines (:data:`MAGNITUDE_TERMS`), band-passed, returned as a vector field.

    Parameters
    ----------
    field_nT : array_like, shape (N, 3)
        The compensated field (nT), evenly sampled.
    sample_rate_hz : float
    passband_hz : (float, float)
    kept : array_like of bool, shape (N,), optional
        The samples fitted (all by default).
    ridge : float
        Tikhonov weight on the coefficients with the band-passed columns scaled to unit RMS, per sample: it holds
        the combinations the magnitude barely sees (a permanent field along the field moves ``|B|`` only to second
        order in the maneuvers' angles) and leaves the others.
    current_A : array_like, shape (N,) or (N, K), optional
        The platform's currents (A): a field per ampere ``k`` of each is fitted too (columns ``u_j I_k``).

    Returns
    -------
    permanent_nT : numpy.ndarray, shape (3,)
        ``p`` (nT).
    induced : numpy.ndarray, shape (3, 3)
        The symmetric ``A`` (dimensionless), its trace removed.
    eddy_s : numpy.ndarray, shape (3, 3)
        ``E`` (s), its trace removed: ``u . (p + A B + E dB/dt)`` is the fitted signature (a constant ``|B|``
        leaves the two traces undetermined: ``u . B = |B|``, ``u . dB = d|B|``).
    current_nT_per_A : numpy.ndarray, shape (3,) or (K, 3)
        ``k`` (nT/A; zeros without a current), a row per current when there are several.
    """
    b = np.asarray(field_nT, dtype=float)
    magnitude = np.linalg.norm(b, axis=1)
    design = design_matrix(b, MAGNITUDE_TERMS, scale_nT=1.0)
    n_currents = 0
    if current_A is not None:
        currents = np.asarray(current_A, dtype=float).reshape(b.shape[0], -1)
        n_currents = currents.shape[1]
        u = b / magnitude[:, None]
        design = np.column_stack([design] + [u * currents[:, [j]] for j in range(n_currents)])
    design_bp = bandpass_columns(design, sample_rate_hz, passband_hz)
    target_bp = bandpass(magnitude, sample_rate_hz, passband_hz)
    kept = np.ones(b.shape[0], dtype=bool) if kept is None else np.asarray(kept, dtype=bool)
    rms = np.sqrt(np.mean(design_bp[kept] ** 2, axis=0))
    rms = np.where(rms > 0, rms, 1.0)
    scaled = solve_ridge(design_bp[kept] / rms, target_bp[kept], float(ridge) * int(kept.sum()))
    labels = term_labels(MAGNITUDE_TERMS) + [f"current{j}_{a}" for j in range(n_currents) for a in "xyz"]
    values = dict(zip(labels, scaled / rms))
    permanent = np.array([values[f"permanent_{a}"] for a in "xyz"])
    induced = np.zeros((3, 3))
    eddy = np.zeros((3, 3))
    for i, a in enumerate("xyz"):
        for j, c in enumerate("xyz"):
            eddy[i, j] = values.get(f"eddy_{a}{c}", 0.0) / sample_rate_hz  # per nT per sample -> per nT/s
            if j >= i:  # the column u_x B_y holds A_xy + A_yx
                induced[i, j] = induced[j, i] = values.get(f"induced_{a}{c}", 0.0) / (1.0 if i == j else 2.0)
    induced -= np.trace(induced) / 3.0 * np.eye(3)
    eddy -= np.trace(eddy) / 3.0 * np.eye(3)
    current = np.array([[values[f"current{j}_{a}"] for a in "xyz"] for j in range(n_currents)])
    return permanent, induced, eddy, _per_ampere(current) if n_currents else np.zeros(3)


def _with_platform_residual(sensor: SensorCompensation, permanent, induced, eddy, current) -> SensorCompensation:
    """The sensor's model with a further vector field ``p + A B + E dB/dt + k I`` (:func:`magnitude_pass`) taken
    out: with ``B' = (I - A) B - p - E dB/dt - k I``, ``y = W (I - A)^-1 B' + o + W (I - A)^-1 p + (E' + W (I -
    A)^-1 E) dB/dt + (k' + W (I - A)^-1 k) I`` (the rates of ``B`` and ``B'`` equal to first order)."""
    matrix = sensor.matrix @ np.linalg.inv(np.eye(3) - induced)
    return SensorCompensation(
        matrix=matrix,
        eddy_s=sensor.eddy_s + matrix @ eddy,
        offset_nT=sensor.offset_nT + matrix @ permanent,
        residual_std_nT=sensor.residual_std_nT,
        conditioning=sensor.conditioning,
        current_nT_per_A=_per_ampere(sensor.per_ampere + np.asarray(current, dtype=float).reshape(-1, 3) @ matrix.T),
    )
