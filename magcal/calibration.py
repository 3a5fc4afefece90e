"""The calibration: apply a fitted model to new data, and save or load it as JSON.

:func:`corrected_fields` and :func:`expected_total_field` are *the* correction model (see :mod:`magcal.model`);
the fitter evaluates the same two functions, so what is fitted is exactly what is applied.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from . import conventions
from .errors import MagcalError
from .model import Context, Model, parse_effect, term_label

FORMAT = "magcal-calibration"
VERSION = 1


@dataclass
class SensorCalibration:
    """Calibration of one triaxial sensor.

    Attributes
    ----------
    cinv : numpy.ndarray, shape (3, 3)
        Correction matrix ``C^-1`` (dimensionless), upper triangular in the seed's gauge.
    bias_nT : numpy.ndarray, shape (3,)
        Bias in nT (in a platform-interference model it holds ``C B_hard + b``).
    R : numpy.ndarray, shape (3, 3)
        Rotation taking this sensor's corrected vector into the array frame (identity for the reference sensor).
    summary : dict
        Figures from the fit (e.g. ``rms_before_nT``, ``rms_nT``), written to JSON as they are.
    """

    cinv: np.ndarray
    bias_nT: np.ndarray
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    summary: dict = field(default_factory=dict)

    def __post_init__(self):
        self.cinv = np.asarray(self.cinv, dtype=float).reshape(3, 3)
        self.bias_nT = np.asarray(self.bias_nT, dtype=float).reshape(3)
        self.R = np.asarray(self.R, dtype=float).reshape(3, 3)


def block_label(effect, sensor) -> str:
    """Key of one effect instance's parameters: ``name`` (shared) or ``name:S`` (S 1-based)."""
    return term_label(effect.name, sensor)


def contexts(dataset, baseline_m=None):
    """One :class:`~magcal.model.Context` per sensor of the dataset."""
    baseline = baseline_m if baseline_m is not None else (dataset.baseline_m or 0.0)
    positions = conventions.sensor_positions(baseline, dataset.n_sensors)
    attitude = None
    if dataset.attitude_wxyz is not None:
        q = dataset.attitude_wxyz
        attitude = Rotation.from_quat(np.column_stack([q[:, 1:], q[:, :1]]))
    return [Context(dataset, s, positions[s], attitude) for s in range(dataset.n_sensors)]


def corrected_fields(dataset, sensors, model=None, effect_values=None, ctxs=None):
    """Corrected field vectors in the array frame, nT, shape (n_sensors, N, 3).

    Parameters
    ----------
    dataset : Dataset
    sensors : list of SensorCalibration
    model : Model, optional
        Candidate effects to undo (base terms are in ``sensors``).
    effect_values : dict of str to numpy.ndarray, optional
        Parameters of each effect instance by :func:`block_label`.
    ctxs : list of Context, optional
        Precomputed :func:`contexts` (the fitter passes them to save work).
    """
    if len(sensors) != dataset.n_sensors:
        raise MagcalError(
            f"the calibration is for {len(sensors)} sensor(s) but the data {dataset.source or ''} have "
            f"{dataset.n_sensors}; use a calibration made for this instrument"
        )
    ctxs = ctxs or contexts(dataset)
    effect_values = effect_values or {}
    instances = list(model.instances()) if model is not None else []
    out = np.empty_like(dataset.readings_nT)
    for s, cal in enumerate(sensors):
        z0 = dataset.readings_nT[s] - cal.bias_nT
        z = z0
        for e, es in instances:
            if e.stage == "raw" and (es == s or (es is None and e.applies_to(s))):
                z = z - e.raw_basis(z0, ctxs[s]) @ effect_values[block_label(e, es)]
        out[s] = z @ (cal.R @ cal.cinv).T
    for s in range(len(sensors)):
        b = out[s].copy()
        for e, es in instances:
            if e.stage == "vector" and (es == s or (es is None and e.applies_to(s))):
                out[s] = out[s] + e.vector_basis(b, ctxs[s]) @ effect_values[block_label(e, es)]
    return out


def expected_total_field(dataset, reference_total_nT, model=None, effect_values=None, ctxs=None):
    """Expected total field (n_sensors, N) in nT: the reference plus reference-stage effects.

    ``reference_total_nT`` is a number, or ``None`` to use the dataset's per-sample ``ref_total_nT`` column.
    """
    n = dataset.n_samples
    if reference_total_nT is None:
        if dataset.ref_total_nT is None:
            raise MagcalError("no reference field: give one, add a ref_total column, or let it be fitted")
        base = dataset.ref_total_nT
    else:
        base = np.full(n, float(reference_total_nT))
    total = np.tile(base, (dataset.n_sensors, 1))
    if model is not None:
        ctxs = ctxs or contexts(dataset)
        effect_values = effect_values or {}
        for e, es in model.instances():
            if e.stage != "reference":
                continue
            for s in range(dataset.n_sensors):
                if es is None or es == s:
                    total[s] = total[s] + e.reference_basis(ctxs[s]) @ effect_values[block_label(e, es)]
    return total


@dataclass
class Calibration:
    """A fitted calibration of one to four sensors, ready to apply to new data.

    Attributes
    ----------
    sensors : list of SensorCalibration
    reference_total_nT : float or None
        The total field used (given or fitted) in nT; ``None`` when a per-sample reference column was used.
    reference_fitted : bool
        True if the field magnitude was fitted because no reference was given.
    baseline_m : float or None
        Array baseline in m (for the tensor).
    model : Model or None
        The candidate effects included (their data-derived constants travel with them).
    effect_values : dict of str to numpy.ndarray
        Fitted parameters of each effect instance, keyed by :func:`block_label`.
    frame : str
        The array frame: ``"sensor1"`` (the seed's) or ``"platform"`` (after a level-table alignment).
    summary : dict
        Figures from the fit (``n_samples``, ``rms_nT``, ``tensor_rms_nT_per_m``, ...), saved with the file.
    """

    sensors: list
    reference_total_nT: float | None = None
    reference_fitted: bool = False
    baseline_m: float | None = None
    model: Model | None = None
    effect_values: dict = field(default_factory=dict)
    frame: str = "sensor1"
    summary: dict = field(default_factory=dict)

    @property
    def n_sensors(self) -> int:
        return len(self.sensors)

    def check(self, dataset) -> None:
        """Raise a clear error if this calibration cannot be applied to the dataset."""
        where = f" ({dataset.source})" if dataset.source else ""
        if dataset.n_sensors != self.n_sensors:
            raise MagcalError(
                f"the calibration is for {self.n_sensors} sensor(s) but the data{where} have {dataset.n_sensors}; "
                "use a calibration made for this instrument"
            )
        if self.model is not None:
            missing = {c for e in self.model.effects for c in e.missing_channels(dataset)}
            if missing:
                raise MagcalError(
                    f"the calibration includes {', '.join(self.model.effect_labels)}, which need "
                    f"{', '.join(sorted(missing))}; the data{where} lack them"
                )

    def correct(self, dataset) -> np.ndarray:
        """Corrected field vectors (n_sensors, N, 3) in nT, in the array frame."""
        self.check(dataset)
        return corrected_fields(dataset, self.sensors, self.model, self.effect_values,
                                contexts(dataset, self.baseline_m))

    def total_field(self, dataset) -> np.ndarray:
        """Corrected total field (n_sensors, N) in nT."""
        return np.linalg.norm(self.correct(dataset), axis=2)

    def expected_total_field(self, dataset) -> np.ndarray:
        """The total field (n_sensors, N) in nT this calibration expects on ``dataset``: its reference (the
        dataset's ``ref_total`` column when it has none) plus its reference-stage effects."""
        return expected_total_field(dataset, self.reference_total_nT, self.model, self.effect_values,
                                    contexts(dataset, self.baseline_m))

    def total_field_residuals(self, dataset, corrected=None) -> np.ndarray:
        """Total-field residuals ``|B| - F`` (n_sensors, N) in nT; ``corrected`` reuses :meth:`correct`'s output."""
        vectors = self.correct(dataset) if corrected is None else corrected
        return np.linalg.norm(vectors, axis=2) - self.expected_total_field(dataset)

    def tensor(self, dataset, corrected=None) -> dict:
        """Gradient tensor components (eq. 1) in nT/m from corrected vectors; needs four sensors and a baseline."""
        if self.n_sensors != 4 or not self.baseline_m:
            raise MagcalError("the gradient tensor needs four sensors and a baseline (baseline_m)")
        vectors = self.correct(dataset) if corrected is None else corrected
        return conventions.tensor_components(vectors, self.baseline_m)

    # --- JSON -----------------------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        """The versioned JSON document (``format``, ``version``, per-sensor ``Cinv``, ``bias_nT``, ``R``...)."""
        sensors = []
        for i, cal in enumerate(self.sensors):
            scale, angles = conventions.gauge_free(cal.cinv)
            entry = {
                "id": i + 1,
                "Cinv": cal.cinv.tolist(),
                "bias_nT": cal.bias_nT.tolist(),
                "R": cal.R.tolist(),
                "scale": scale.tolist(),
                "axis_angles_deg": angles.tolist(),
            }
            entry.update(jsonable(cal.summary))
            sensors.append(entry)
        effects = []
        if self.model is not None:
            for e, s in self.model.instances():
                label = block_label(e, s)
                values = np.asarray(self.effect_values.get(label, np.zeros(len(e.param_names()))), dtype=float)
                effects.append({
                    "effect": e.name,
                    "sensor": None if s is None else s + 1,
                    "term": e.label,
                    "params": dict(zip(e.param_names(), values.tolist())),
                    "state": jsonable(e.state()),
                })
        doc = {
            "format": FORMAT,
            "version": VERSION,
            "reference_total_nT": self.reference_total_nT,
            "reference_fitted": self.reference_fitted,
            "baseline_m": self.baseline_m,
            "frame": self.frame,
            "base_terms": list(self.model.base) if self.model is not None else None,
            "effects": self.model.effect_labels if self.model is not None else [],
            "effect_params": effects,
            "sensors": sensors,
        }
        doc.update(jsonable(self.summary))
        return doc

    @classmethod
    def from_dict(cls, doc: dict, source: str = "calibration", n_sensors=None) -> "Calibration":
        """Rebuild a calibration from :meth:`to_dict` output, refusing anything else with one clear message.

        Parameters
        ----------
        doc : dict
            The JSON document.
        source : str
            Where it came from (a file name), for the messages.
        n_sensors : int, optional
            Refuse a calibration made for a different number of sensors.

        Raises
        ------
        MagcalError
            Wrong format or version, wrong sensor count, a damaged sensor entry (shapes, finite values, a singular
            ``Cinv``, an ``R`` that is not a proper rotation), a damaged effect entry or a bad baseline.
        """
        if not isinstance(doc, dict) or doc.get("format") != FORMAT:
            raise MagcalError(f"{source}: not a magcal calibration file (expected \"format\": \"{FORMAT}\")")
        if doc.get("version") != VERSION:
            raise MagcalError(
                f"{source}: calibration file version {doc.get('version')!r} is not supported by this magcal "
                f"(it reads version {VERSION}); upgrade magcal or recalibrate"
            )
        entries = doc.get("sensors")
        if not isinstance(entries, list) or not 1 <= len(entries) <= 4:
            raise MagcalError(f"{source}: 'sensors' must list 1 to 4 sensors; the file is damaged, recalibrate")
        if n_sensors is not None and len(entries) != int(n_sensors):
            raise MagcalError(
                f"{source}: this calibration is for {len(entries)} sensor(s) but the data have {n_sensors}; use the "
                "calibration made for this instrument"
            )
        for i, entry in enumerate(entries):
            _check_sensor_entry(source, i, entry)
        baseline = doc.get("baseline_m")
        if baseline is not None:
            try:
                ok = float(baseline) > 0 and np.isfinite(float(baseline))
            except (TypeError, ValueError):
                ok = False
            if not ok:
                raise MagcalError(f"{source}: baseline_m {baseline!r} must be a positive number of metres")
        derived = {"id", "Cinv", "bias_nT", "R", "scale", "axis_angles_deg"}  # recomputed by to_dict
        sensors = [
            SensorCalibration(np.array(s["Cinv"], float), np.array(s["bias_nT"], float),
                              np.array(s.get("R", np.eye(3)), float),
                              summary={k: v for k, v in s.items() if k not in derived})
            for s in entries
        ]
        try:
            model, values = _effects_from_dict(doc, len(sensors))
        except MagcalError:
            raise
        except Exception as exc:  # a damaged effect entry: any failure of the rebuild is the file's fault
            raise MagcalError(f"{source}: damaged effect entry ({type(exc).__name__}: {exc}); recalibrate") from None
        known = {"format", "version", "reference_total_nT", "reference_fitted", "baseline_m", "frame", "base_terms",
                 "effects", "effect_params", "sensors"}
        return cls(
            sensors=sensors,
            reference_total_nT=doc.get("reference_total_nT"),
            reference_fitted=bool(doc.get("reference_fitted", False)),
            baseline_m=baseline,
            model=model,
            effect_values=values,
            frame=doc.get("frame", "sensor1"),
            summary={k: v for k, v in doc.items() if k not in known},
        )

    def save(self, path) -> None:
        """Write the JSON file atomically (a temporary file renamed over the target)."""
        write_json_atomic(path, self.to_dict())

    @classmethod
    def load(cls, path, n_sensors=None) -> "Calibration":
        """Read a calibration file written by :meth:`save`, with one clear :class:`MagcalError` for any problem.

        Parameters
        ----------
        path : str or os.PathLike
        n_sensors : int, optional
            Refuse a calibration made for a different number of sensors.
        """
        path = os.fspath(path)
        try:
            with open(path, "rb") as fh:
                raw = fh.read()
        except FileNotFoundError:
            raise MagcalError(f"{path}: no such calibration file; check the path") from None
        except IsADirectoryError:
            raise MagcalError(f"{path}: is a directory, not a calibration file") from None
        except OSError as exc:
            raise MagcalError(f"{path}: cannot read the calibration file ({exc.strerror or exc})") from None
        try:
            doc = json.loads(raw.decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
            raise MagcalError(f"{path}: not a JSON calibration file ({type(exc).__name__}: {exc}); give the file "
                              "written by magcal calibrate or magcal align") from None
        return cls.from_dict(doc, source=path, n_sensors=n_sensors)


def _check_sensor_entry(source, i, s) -> None:
    """Refuse a damaged sensor entry of a calibration document, naming the sensor and the key."""
    where = f"{source}: sensor {i + 1}"
    if not isinstance(s, dict):
        raise MagcalError(f"{where}: entry is not an object; the file is damaged, recalibrate")
    for key, shape in (("Cinv", (3, 3)), ("bias_nT", (3,)), ("R", (3, 3))):
        if key not in s:
            if key == "R":
                continue
            raise MagcalError(f"{where}: missing {key}; the file is damaged, recalibrate")
        try:
            a = np.array(s[key], dtype=float)
        except (TypeError, ValueError):
            raise MagcalError(f"{where}: {key} is not numeric; the file is damaged, recalibrate") from None
        if a.shape != shape or not np.all(np.isfinite(a)):
            raise MagcalError(f"{where}: {key} must be {shape} finite numbers; the file is damaged, recalibrate")
        if key == "Cinv" and abs(np.linalg.det(a)) < 1e-9:
            raise MagcalError(f"{where}: Cinv is singular; the file is damaged, recalibrate")
        if key == "R" and (not np.allclose(a @ a.T, np.eye(3), atol=1e-6) or np.linalg.det(a) < 0):
            raise MagcalError(f"{where}: R is not a proper rotation; the file is damaged, recalibrate")


def _effects_from_dict(doc, n_sensors):
    """The model and effect values saved in a calibration document (None, {} when it has none)."""
    model, values = None, {}
    if doc.get("effect_params") or doc.get("base_terms"):
        from .model import BASE_TERMS

        model = Model(n_sensors, base=tuple(doc.get("base_terms") or BASE_TERMS))
        seen = {}
        for entry in doc.get("effect_params", []):
            term = entry.get("term", entry["effect"])
            if term not in seen:
                effect = parse_effect(term, n_sensors)
                effect.set_state(entry.get("state") or {})
                seen[term] = effect
                model.effects.append(effect)
            effect = seen[term]
            sensor = entry.get("sensor")
            label = block_label(effect, None if sensor is None or not effect.per_sensor else sensor - 1)
            values[label] = np.array([entry["params"][n] for n in effect.param_names()], dtype=float)
    return model, values


def write_json_atomic(path, document) -> None:
    """Write ``document`` as indented JSON to ``path`` atomically (:func:`magcal.io.atomic_write`)."""
    from .io import atomic_write

    with atomic_write(path, "w", newline=None) as fh:
        json.dump(document, fh, indent=2)
        fh.write("\n")


def jsonable(value):
    """``value`` with numpy arrays and scalars turned into JSON types; non-finite floats become gaps."""
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        if value.dtype == object:
            return [jsonable(v) for v in value.tolist()]
        if value.dtype.kind == "f":  # inf is not JSON; show it as a gap like NaN
            return np.where(np.isfinite(value), value, np.nan).tolist()
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value
