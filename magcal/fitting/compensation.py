"""The compensation of a scalar magnetometer on a platform: Tolles-Lawson and the terms beyond it, fitted on a
compensation flight, saved as a document, applied to survey lines.

A compensation flight records a scalar magnetometer (optically pumped, nT) beside a fluxgate (its x, y, z in nT,
the body frame): :func:`compensation_record` takes them from a :class:`~magcal.data.dataset.Dataset` (the
fluxgate is sensor 1's readings, the scalar a column found by name, :data:`SCALAR_COLUMNS`, or named), with the
attitude, a current or throttle and the temperature when the record has them.

:func:`fit_compensation` fits Tolles-Lawson's terms (:mod:`magcal.model.tolles_lawson`) on the band-passed record,
and with ``effects`` the terms TL lacks (:data:`COMPENSATION_EFFECTS`):

``current``
    a field per unit of the platform's current or throttle ``k I`` (nT per A), seen by the scalar as
    ``u . k I``: three columns ``u_i I``.
``time_offset``
    the fluxgate's samples late (or early) against the scalar by ``tau`` (s): the fluxgate is read at ``t + tau``
    (linear interpolation) before the design matrix is made; ``tau`` fitted by a bounded search on the band-passed
    residual.
``heading``
    a field that follows the heading (of the field's direction, ``atan2(-u_y, u_x)``): ``cos h, sin h, cos 2h,
    sin 2h``.
``temperature``
    a body-fixed field that changes with the temperature: ``u_i (T - T0)`` (nT per degC).
``fluxgate_calibration``
    the fluxgate's own bias, scale and non-orthogonality, fitted jointly against the scalar so that its errors do
    not bend the direction cosines: corrected ``g = M (f - b)`` (``M`` lower triangular) chosen so that the
    band-passed ``|g|`` follows the compensated scalar (the Earth field's magnitude does not move with the
    attitude, the miscalibrated fluxgate's does, by ``u . b`` and ``|B| u^T E u``); the overall scale (which the
    band cannot see) is set so that the median ``|g|`` is the scalar's, and a rotation of ``g`` is left to the TL
    coefficients (they are in the fluxgate's frame). TL alone cannot take this: a scale error of the fluxgate
    bends ``u`` by a pattern no linear term in ``u`` follows.

The result is a :class:`Compensation` (``kind: "compensation"``): the TL coefficients (:meth:`Compensation.tl18`,
MagNav.jl's order), the effects' coefficients, the fluxgate's calibration and the offset, the band-pass; its
:meth:`Compensation.compensate` gives a line's compensated scalar (the scalar minus the platform field along the
corrected fluxgate). :class:`CompensationResult` is the fit with its report (the FOM table of
:mod:`magcal.diagnosis.fom`, computed by the compensation mode, which sits above this layer).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import optimize

from magcal.calibration.calibration import write_json_atomic
from magcal.core.errors import MagcalError
from magcal.core.jsonable import jsonable
from magcal.data.attitude import attitude
from magcal.data.current_columns import CurrentTerm, current_columns, current_names, current_series
from magcal.data.dataset import Dataset
from magcal.data.flight_columns import ATTITUDE_COLUMNS, TEMPERATURE_COLUMNS
from magcal.fitting.result import ModeResult
from magcal.fitting.tolles_lawson import TLCompensation, sample_rate_from_times, solve_ridge
from magcal.model.tolles_lawson import (
    DEFAULT_PASSBAND_HZ,
    DEFAULT_TERMS,
    bandpass,
    bandpass_columns,
    check_terms,
    conditioning,
    design_matrix,
    term_labels,
)

#: Scalar magnetometer columns found by name, first match wins (MagNav.jl's uncompensated ``mag_N_uc`` too).
SCALAR_COLUMNS = (
    "scalar_nT",
    "scalar",
    "mag_1_uc",
    "mag_2_uc",
    "mag_3_uc",
    "mag_4_uc",
    "mag_5_uc",
    "mag_uc",
)

#: The terms beyond Tolles-Lawson, by name (``--effects``), and what each is.
COMPENSATION_EFFECTS = {
    "current": "a field per unit of the platform's current or throttle (current_A or throttle column)",
    "time_offset": "the fluxgate's samples late or early against the scalar's (s)",
    "heading": "a field that follows the heading (cos h, sin h, cos 2h, sin 2h)",
    "temperature": "a body-fixed field that changes with the temperature (temp column)",
    "fluxgate_calibration": "the fluxgate's bias, scale and non-orthogonality, fitted against the scalar",
}

#: The document's kind and version.
KIND = "compensation"
VERSION = 1

#: The largest fluxgate offset the time_offset search tries (s), either way.
MAX_TIME_OFFSET_S = 0.5

__all__ = [
    "COMPENSATION_EFFECTS",
    "SCALAR_COLUMNS",
    "Compensation",
    "CompensationRecord",
    "CompensationResult",
    "best_time_offset",
    "check_effects",
    "compensation_record",
    "current_labels",
    "current_names",
    "find_scalar_column",
    "fit_compensation",
    "is_compensation_document",
    "shifted",
]


def find_scalar_column(dataset: Dataset, scalar: str | None = None) -> str | None:
    """The scalar magnetometer's column of ``dataset``: ``scalar`` when given (a :class:`MagcalError` naming the
    columns when it is absent), else the first of :data:`SCALAR_COLUMNS` it holds as numbers, else None."""
    numeric = [k for k, v in dataset.extra.items() if np.asarray(v).dtype.kind in "fiu"]
    if scalar is not None:
        if scalar not in dataset.extra:
            where = dataset.source or "the record"
            raise MagcalError(
                f"{where}: no column {scalar!r} for the scalar magnetometer (--scalar); its other columns: "
                + (", ".join(numeric) or "none")
            )
        return scalar
    return next((name for name in SCALAR_COLUMNS if name in numeric), None)


def check_effects(effects) -> tuple[str, ...]:
    """The effect names as a tuple, each one of :data:`COMPENSATION_EFFECTS` (a :class:`MagcalError` naming the
    unknown one and the known ones)."""
    names = (effects,) if isinstance(effects, str) else tuple(effects or ())
    for name in names:
        if name not in COMPENSATION_EFFECTS:
            raise MagcalError(
                f"--effects: {name!r} is not a compensation term; use some of " + ", ".join(COMPENSATION_EFFECTS)
            )
    return tuple(dict.fromkeys(names))


@dataclass
class CompensationRecord(CurrentTerm):
    """What a compensation flight (or a survey line) holds for the compensation.

    Attributes
    ----------
    scalar_nT : numpy.ndarray, shape (N,)
        The scalar magnetometer, uncompensated.
    flux_nT : numpy.ndarray, shape (N, 3)
        The fluxgate's x, y, z (nT), body frame.
    sample_rate_hz : float
    scalar_column : str
    time_s : numpy.ndarray or None
    attitude_deg : numpy.ndarray, shape (N, 3), or None
        Roll, pitch, yaw (deg, aerospace ZYX), for finding the maneuvers.
    current : numpy.ndarray or None
        The ``current_A`` (A) or ``throttle`` column: the current term's first column.
    current_column : str or None
    more_currents : dict
        The current term's further columns (name -> values, A): a platform's wires each carry their own current,
        whose field at the sensor is that current times a fixed vector (one per column).
    other_currents : dict
        The record's current columns the term does not take (name -> values): the diagnosis's candidates.
    temperature_C : numpy.ndarray or None
    source : str
    fluxgate_columns : tuple of 3 str or None
        The file's fluxgate columns when they were found by name (``flux_a_x`` ...), kept in the compensation so
        that its lines are read with the same fluxgate.
    """

    scalar_nT: np.ndarray
    flux_nT: np.ndarray
    sample_rate_hz: float
    scalar_column: str = "scalar_nT"
    time_s: np.ndarray | None = None
    attitude_deg: np.ndarray | None = None
    current: np.ndarray | None = None
    current_column: str | None = None
    temperature_C: np.ndarray | None = None
    source: str = "the record"
    fluxgate_columns: tuple | None = None
    more_currents: dict = field(default_factory=dict)
    other_currents: dict = field(default_factory=dict)

    @property
    def n_samples(self) -> int:
        return int(self.scalar_nT.size)


def _numeric(dataset: Dataset, name: str) -> bool:
    value = dataset.extra.get(name)
    return value is not None and np.asarray(value).dtype.kind in "fiu"


def _attitude_deg(dataset: Dataset) -> np.ndarray | None:
    """Roll, pitch, yaw (deg): the first complete triple of :data:`magcal.data.flight_columns.ATTITUDE_COLUMNS`
    (magcal's, MagNav.jl's INS attitude ...), else from the quaternion; None when neither is there whole."""
    for names in ATTITUDE_COLUMNS:
        if all(_numeric(dataset, c) for c in names):
            values = np.column_stack([np.asarray(dataset.extra[c], float) for c in names])
            return values if np.isfinite(values).all() else None
    rotation = attitude(dataset) if dataset.attitude_wxyz is not None else None
    if rotation is None:
        return None
    yaw_pitch_roll = rotation.as_euler("ZYX", degrees=True)
    return yaw_pitch_roll[:, ::-1]


def _record_rate(dataset: Dataset, where: str) -> float:
    if dataset.time_s is not None:
        try:
            return sample_rate_from_times(dataset.time_s)
        except MagcalError as exc:
            raise MagcalError(f"{where}: {exc}") from None
    text = dataset.metadata.get("sample_rate_hz")
    try:
        rate = float(text) if text is not None else float("nan")
    except ValueError:
        rate = float("nan")
    if not (np.isfinite(rate) and rate > 0):
        raise MagcalError(
            f"{where}: the compensation needs the sample rate: a time column (t, s) or a '# sample_rate_hz:' line"
        )
    return rate


def _temperature_C(dataset: Dataset) -> np.ndarray | None:
    if dataset.temperature_C is not None:
        return np.asarray(dataset.temperature_C, float)
    name = next((n for n in TEMPERATURE_COLUMNS if _numeric(dataset, n)), None)
    return None if name is None else np.asarray(dataset.extra[name], float)


def compensation_record(
    dataset: Dataset, scalar: str | None = None, current=None, fluxgate_columns=None
) -> CompensationRecord:
    """The :class:`CompensationRecord` of a dataset: sensor 1's readings as the fluxgate, the scalar column
    (:func:`find_scalar_column`), the rate from the times (or a ``# sample_rate_hz:`` line), the attitude, a
    current or throttle and the temperature when present (found by name, MagNav.jl's too:
    :mod:`magcal.data.flight_columns`).

    Parameters
    ----------
    dataset : Dataset
    scalar : str, optional
        The scalar's column (found by name when not given).
    current : str or sequence of str, optional
        The current term's columns (``"cur_strb,cur_com_1"`` or a list: each its own field per ampere); when not
        given, the first current column found by name, the others kept for the diagnosis.
    fluxgate_columns : sequence of 3 str, optional
        The file's columns the fluxgate was read from, when they were found by name (kept in the compensation).

    Raises
    ------
    MagcalError
        No scalar column, non-finite values (the row named), uneven times, a named current column absent.
    """
    where = dataset.source or "the record"
    name = find_scalar_column(dataset, scalar)
    if name is None:
        raise MagcalError(
            f"{where}: no scalar magnetometer column ({', '.join(SCALAR_COLUMNS[:3])} ...): name it with --scalar NAME"
        )
    values = np.asarray(dataset.extra[name])
    if values.dtype.kind not in "fiu":
        raise MagcalError(f"{where}: column {name} (the scalar magnetometer) must hold numbers of nT")
    y = values.astype(float)
    bad = ~np.isfinite(y)
    if bad.any():
        raise MagcalError(
            f"{where}: column {name} has {int(bad.sum())} missing or non-finite value(s) (first at data row "
            f"{int(np.argmax(bad)) + 1}): fill or cut them (or read with --drop-bad)"
        )
    flux = np.asarray(dataset.readings_nT[0], float)
    rate = _record_rate(dataset, where)
    term, others = current_columns(dataset, current, where)
    term_values, other_values = current_series(dataset, term, others, where)
    currents = term_values | other_values
    column = term[0] if term else None
    temperature = _temperature_C(dataset)
    return CompensationRecord(
        scalar_nT=y,
        flux_nT=flux,
        sample_rate_hz=rate,
        scalar_column=name,
        time_s=None if dataset.time_s is None else np.asarray(dataset.time_s, float),
        attitude_deg=_attitude_deg(dataset),
        current=None if column is None else currents[column],  # the term's first; the others below
        current_column=column,
        more_currents={c: currents[c] for c in term[1:]},
        other_currents=other_values,
        temperature_C=temperature,
        source=where,
        fluxgate_columns=None if fluxgate_columns is None else tuple(map(str, fluxgate_columns)),
    )


def shifted(values, samples: float) -> np.ndarray:
    """``values`` (N, k) read ``samples`` later (linear interpolation; the ends held)."""
    x = np.asarray(values, float)
    if samples == 0:
        return x.copy()
    index = np.arange(x.shape[0], dtype=float)
    return np.column_stack([np.interp(index + samples, index, x[:, j]) for j in range(x.shape[1])])


def fluxgate_matrix(params) -> np.ndarray:
    """The lower-triangular fluxgate correction ``M`` of its five parameters (``M[0, 0]`` = 1 before the overall
    scale): ``[[1, 0, 0], [p0, 1 + p1, 0], [p2, p3, 1 + p4]]``."""
    p = np.asarray(params, float)
    return np.array([[1.0, 0.0, 0.0], [p[0], 1.0 + p[1], 0.0], [p[2], p[3], 1.0 + p[4]]])


def current_labels(columns) -> list[str]:
    """The current term's coefficients' names: ``current_x, current_y, current_z`` for one column (or none named),
    ``current_<column>_x`` ... for each of several."""
    columns = tuple(columns or ())
    if len(columns) <= 1:
        return ["current_x", "current_y", "current_z"]
    return [f"current_{c}_{a}" for c in columns for a in "xyz"]


def _effect_labels(name: str, current_columns=()) -> list[str]:
    if name == "current":
        return current_labels(current_columns)
    return {
        "heading": ["heading_cos", "heading_sin", "heading_cos2", "heading_sin2"],
        "temperature": ["temperature_x", "temperature_y", "temperature_z"],
    }.get(name, [])


def _line_currents(record: CompensationRecord, columns) -> list[np.ndarray]:
    """The series of the current term's ``columns`` in a record (by name; one column of an older compensation, or of
    a record whose column is named otherwise, takes the record's current)."""
    every = record.all_currents
    if len(columns) <= 1 and record.current is not None and (not columns or columns[0] not in every):
        return [record.current]
    missing = [c for c in columns if c not in every]
    if record.current is None or missing:
        need = ", ".join(missing or columns) or "current_A or throttle"
        raise MagcalError(f"{record.source}: the current term needs the column(s) {need} (A)")
    return [every[c] for c in columns]


def _effect_columns(
    name: str, record: CompensationRecord, corrected_nT, temperature_ref_C: float, current_columns=()
) -> np.ndarray:
    u = corrected_nT / np.linalg.norm(corrected_nT, axis=1, keepdims=True)
    if name == "current":
        return np.column_stack([u * current[:, None] for current in _line_currents(record, current_columns)])
    if name == "heading":
        h = np.arctan2(-u[:, 1], u[:, 0])
        return np.column_stack([np.cos(h), np.sin(h), np.cos(2 * h), np.sin(2 * h)])
    if name == "temperature":
        if record.temperature_C is None:
            raise MagcalError(f"{record.source}: the temperature term needs a temp column (degC)")
        return u * (record.temperature_C - temperature_ref_C)[:, None]
    return np.zeros((u.shape[0], 0))


@dataclass
class Compensation:
    """A fitted compensation: Tolles-Lawson and the terms beyond it (``kind: "compensation"``).

    Attributes
    ----------
    tl : TLCompensation
        The TL coefficients (its ``compensated_nT`` and ``residual_bp_nT`` those of the whole fit).
    effects : tuple of str
        The terms beyond TL (:data:`COMPENSATION_EFFECTS`).
    extra_labels : list of str
        The linear effects' coefficients' names (``current_x`` ...).
    extra_coefficients : numpy.ndarray
        Their values: ``current_*`` nT per unit of the current column, ``heading_*`` nT, ``temperature_*`` nT per
        degC.
    fluxgate_bias_nT : numpy.ndarray, shape (3,)
        ``b`` of the fluxgate's correction ``g = M (f - b)`` (zeros without ``fluxgate_calibration``).
    fluxgate_matrix : numpy.ndarray, shape (3, 3)
        ``M`` (the identity without it).
    time_offset_s : float
        How late the fluxgate is against the scalar: it is read ``time_offset_s`` later.
    scalar_column : str
    current_column : str or None
        The current term's first column.
    current_columns : tuple of str
        Every column of the current term, each with its own field per ampere (``current_<column>_x`` ... when
        there are several).
    temperature_ref_C : float
    sample_rate_hz : float
    fluxgate_columns : tuple of 3 str or None
        The flight file's fluxgate columns when found by name (``flux_b_x`` ...): a line is read with the same.
    """

    tl: TLCompensation
    effects: tuple = ()
    extra_labels: list = field(default_factory=list)
    extra_coefficients: np.ndarray = field(default_factory=lambda: np.zeros(0))
    fluxgate_bias_nT: np.ndarray = field(default_factory=lambda: np.zeros(3))
    fluxgate_matrix: np.ndarray = field(default_factory=lambda: np.eye(3))
    time_offset_s: float = 0.0
    scalar_column: str = "scalar_nT"
    current_column: str | None = None
    temperature_ref_C: float = 0.0
    fitted: dict = field(default_factory=dict)
    fluxgate_columns: tuple | None = None
    current_columns: tuple = ()

    mode = "compensation"

    def __post_init__(self):
        if not self.current_columns and self.current_column:
            self.current_columns = (self.current_column,)

    @property
    def sample_rate_hz(self) -> float:
        return self.tl.sample_rate_hz

    def tl18(self) -> np.ndarray:
        """TL's 18 coefficients in MagNav.jl's order (:meth:`TLCompensation.tl18`)."""
        return self.tl.tl18()

    def corrected_flux_nT(self, flux_nT) -> np.ndarray:
        """The fluxgate as the compensation reads it: corrected (``M (f - b)``) and shifted by the offset."""
        flux = np.asarray(flux_nT, float)
        g = (flux - self.fluxgate_bias_nT) @ self.fluxgate_matrix.T
        return shifted(g, self.time_offset_s * self.sample_rate_hz)

    def design(self, record: CompensationRecord) -> np.ndarray:
        """The full design matrix (TL's columns, then the effects') along a record, unfiltered."""
        g = self.corrected_flux_nT(record.flux_nT)
        total = record.scalar_nT if self.tl.use_scalar_total else None
        parts = [design_matrix(g, self.tl.terms, total, self.tl.scale_nT)]
        parts += [
            _effect_columns(name, record, g, self.temperature_ref_C, self.current_columns) for name in self.effects
        ]
        return np.column_stack(parts)

    @property
    def coefficients(self) -> np.ndarray:
        return np.concatenate([self.tl.coefficients, self.extra_coefficients])

    @property
    def labels(self) -> list[str]:
        return self.tl.labels + list(self.extra_labels)

    def platform_field_nT(self, record: CompensationRecord) -> np.ndarray:
        """The platform's scalar signature along a record (nT, N)."""
        return self.design(record) @ self.coefficients

    def compensate(self, record: CompensationRecord) -> np.ndarray:
        """A record's scalar minus the platform field (nT, N): the compensated scalar."""
        if record.sample_rate_hz and abs(record.sample_rate_hz / self.sample_rate_hz - 1) > 0.02:
            raise MagcalError(
                f"{record.source}: sampled at {record.sample_rate_hz:g} Hz, the compensation at "
                f"{self.sample_rate_hz:g} Hz (its eddy terms are per sample): resample the line to "
                f"{self.sample_rate_hz:g} Hz"
            )
        if "current" in self.effects:
            lacks = [c for c in self.current_columns if c not in record.all_currents]
            if record.current is None or (lacks and len(self.current_columns) > 1):
                need = ", ".join(lacks or self.current_columns) or "current"
                raise MagcalError(
                    f"{record.source}: the compensation has a current term: the line needs its {need} column(s)"
                )
        return record.scalar_nT - self.platform_field_nT(record)

    def to_dict(self) -> dict:
        """The documented JSON document (docs/compensation.md, "The compensation file")."""
        return jsonable(
            {
                "kind": KIND,
                "version": VERSION,
                "mode": "compensation",
                "scalar_column": self.scalar_column,
                "sample_rate_hz": self.sample_rate_hz,
                "tl18": self.tl18() if _tl_only(self.tl.terms) else None,
                "tl18_order": term_labels(DEFAULT_TERMS),
                "tolles_lawson": self.tl.to_dict(signals=False),
                "effects": list(self.effects),
                "extra_labels": list(self.extra_labels),
                "extra_coefficients": self.extra_coefficients,
                "fluxgate": {"bias_nT": self.fluxgate_bias_nT, "matrix": self.fluxgate_matrix},
                "time_offset_s": self.time_offset_s,
                "current_column": self.current_column,
                "current_columns": list(self.current_columns),
                "temperature_ref_C": self.temperature_ref_C,
                "fluxgate_columns": None if self.fluxgate_columns is None else list(self.fluxgate_columns),
                "fitted": self.fitted,
            }
        )

    @classmethod
    def from_dict(cls, doc: dict, source: str = "the compensation file") -> Compensation:
        """The compensation a :meth:`to_dict` document holds (a :class:`MagcalError` naming what is wrong)."""
        if not is_compensation_document(doc):
            raise MagcalError(f"{source}: not a compensation document (its 'kind' is not 'compensation')")
        try:
            tl = TLCompensation.from_dict(doc["tolles_lawson"])
            effects = check_effects(doc.get("effects", ()))
            labels = list(doc.get("extra_labels", []))
            values = np.asarray(doc.get("extra_coefficients", []), float)
            current_columns = tuple(map(str, doc.get("current_columns") or ()))
            if not current_columns and doc.get("current_column"):
                current_columns = (str(doc["current_column"]),)
            expected = [label for name in effects for label in _effect_labels(name, current_columns)]
            if labels != expected or values.shape != (len(labels),):
                raise MagcalError("its effects' coefficients do not match its effects")
            flux = doc.get("fluxgate") or {}
            bias = np.asarray(flux.get("bias_nT", [0.0, 0.0, 0.0]), float)
            matrix = np.asarray(flux.get("matrix", np.eye(3)), float)
            if bias.shape != (3,) or matrix.shape != (3, 3) or not np.isfinite(matrix).all():
                raise MagcalError("'fluxgate' must hold a bias of 3 nT and a 3 x 3 matrix")
            return cls(
                tl=tl,
                effects=effects,
                extra_labels=labels,
                extra_coefficients=values,
                fluxgate_bias_nT=bias,
                fluxgate_matrix=matrix,
                time_offset_s=float(doc.get("time_offset_s", 0.0)),
                scalar_column=str(doc.get("scalar_column", "scalar_nT")),
                current_column=doc.get("current_column"),
                current_columns=current_columns,
                temperature_ref_C=float(doc.get("temperature_ref_C", 0.0)),
                fitted=dict(doc.get("fitted") or {}),
                fluxgate_columns=_fluxgate_columns(doc.get("fluxgate_columns")),
            )
        except (KeyError, TypeError, ValueError, MagcalError) as exc:
            raise MagcalError(f"{source}: a damaged compensation document ({exc}); fit it again") from None

    def save(self, path) -> None:
        """Write the document (JSON) atomically."""
        write_json_atomic(path, self.to_dict())

    @classmethod
    def load(cls, path) -> Compensation:
        """Read a document :meth:`save` wrote."""
        path = os.fspath(path)
        try:
            with open(path, encoding="utf-8") as fh:
                doc = json.load(fh)
        except FileNotFoundError:
            raise MagcalError(f"{path}: no such compensation file; check the path") from None
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise MagcalError(f"{path}: not a JSON compensation file ({exc})") from None
        return cls.from_dict(doc, path)


def _fluxgate_columns(value) -> tuple | None:
    if value is None:
        return None
    names = tuple(map(str, value))
    if len(names) != 3:
        raise MagcalError("'fluxgate_columns' must name 3 columns")
    return names


def _tl_only(terms) -> bool:
    return set(terms) <= {"permanent", "induced", "induced5", "induced3", "eddy", "eddy8", "eddy3"}


def is_compensation_document(doc) -> bool:
    """Whether a parsed JSON document is a compensation's (``kind: "compensation"``)."""
    return isinstance(doc, dict) and doc.get("kind") == KIND


@dataclass
class _Setup:
    """What every trial fit of one record shares."""

    record: CompensationRecord
    effects: tuple
    terms: tuple
    ridge: float
    passband_hz: tuple
    order: int
    trim: int
    kept: np.ndarray
    y_bp: np.ndarray
    temperature_ref_C: float

    def trial(self, bias, matrix, offset_s) -> Compensation:
        tl = TLCompensation(
            terms=self.terms,
            coefficients=np.zeros(len(term_labels(self.terms))),
            sample_rate_hz=self.record.sample_rate_hz,
            passband_hz=self.passband_hz,
            order=self.order,
            trim=self.trim,
            ridge=self.ridge,
        )
        columns = tuple(self.record.term_currents)
        labels = [label for name in self.effects for label in _effect_labels(name, columns)]
        return Compensation(
            tl=tl,
            effects=self.effects,
            extra_labels=labels,
            extra_coefficients=np.zeros(len(labels)),
            fluxgate_bias_nT=np.asarray(bias, float),
            fluxgate_matrix=np.asarray(matrix, float),
            time_offset_s=float(offset_s),
            scalar_column=self.record.scalar_column,
            current_column=self.record.current_column,
            current_columns=columns,
            temperature_ref_C=self.temperature_ref_C,
            fluxgate_columns=self.record.fluxgate_columns,
        )

    def solve(self, comp: Compensation) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(coefficients, design, band-passed design, band-passed residual over the kept samples)."""
        design = comp.design(self.record)
        design_bp = bandpass_columns(design, self.record.sample_rate_hz, self.passband_hz, self.order)
        c = solve_ridge(design_bp[self.kept], self.y_bp[self.kept], self.ridge)
        return c, design, design_bp, self.y_bp[self.kept] - design_bp[self.kept] @ c


def _fit_fluxgate(setup: _Setup, rounds: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """(bias nT, matrix) of the fluxgate: the band-passed ``|g|`` follows the band-passed compensated scalar (the
    Earth field's magnitude as the scalar sees it), which is taken from the TL fit of the round before."""
    record = setup.record
    rate = record.sample_rate_hz
    bias, matrix = np.zeros(3), np.eye(3)
    params = np.zeros(8)
    scale = np.array([100.0, 100.0, 100.0, 0.01, 0.01, 0.01, 0.01, 0.01])
    for _ in range(rounds):
        c, design, _, _ = setup.solve(setup.trial(bias, matrix, 0.0))
        earth_bp = bandpass(record.scalar_nT - design @ c, rate, setup.passband_hz, setup.order)[setup.kept]

        def residual(p, earth_bp=earth_bp):
            g = (record.flux_nT - p[:3]) @ fluxgate_matrix(p[3:]).T
            magnitude = bandpass(np.linalg.norm(g, axis=1), rate, setup.passband_hz, setup.order)
            return magnitude[setup.kept] - earth_bp

        def jacobian(p):
            m = fluxgate_matrix(p[3:])
            d = record.flux_nT - p[:3]
            g = d @ m.T
            u = g / np.linalg.norm(g, axis=1, keepdims=True)
            columns = np.column_stack(
                [
                    -(u @ m),
                    u[:, 1] * d[:, 0],
                    u[:, 1] * d[:, 1],
                    u[:, 2] * d[:, 0],
                    u[:, 2] * d[:, 1],
                    u[:, 2] * d[:, 2],
                ]
            )
            return bandpass(columns, rate, setup.passband_hz, setup.order)[setup.kept]

        params = optimize.least_squares(residual, params, jac=jacobian, x_scale=scale, method="lm", xtol=1e-12).x
        bias, matrix = params[:3], fluxgate_matrix(params[3:])
        g = (record.flux_nT - bias) @ matrix.T
        matrix = matrix * (np.median(record.scalar_nT) / np.median(np.linalg.norm(g, axis=1)))
    return bias, matrix


def best_time_offset(cost, max_s: float = MAX_TIME_OFFSET_S) -> float:
    """The time offset (s) within ``+-max_s`` where ``cost(offset_s)`` is least: a grid of 11, then a bounded
    search between the best point's neighbours (to 0.5 ms). The scalar's fluxgate offset and the cross's sensors'
    lag are found by it."""
    grid = np.linspace(-max_s, max_s, 11)
    costs = [cost(offset) for offset in grid]
    best = grid[int(np.argmin(costs))]
    step = grid[1] - grid[0]
    bounds = (max(-max_s, best - step), min(max_s, best + step))
    found = optimize.minimize_scalar(cost, bounds=bounds, method="bounded", options={"xatol": 5e-4})
    return float(found.x)


def _fit_offset(setup: _Setup, bias, matrix) -> float:
    """The fluxgate's offset (s) that leaves the least band-passed residual."""

    def cost(offset_s):
        return float(np.sum(setup.solve(setup.trial(bias, matrix, offset_s))[3] ** 2))

    return best_time_offset(cost)


def fit_compensation(
    record: CompensationRecord,
    effects=(),
    *,
    terms=DEFAULT_TERMS,
    ridge: float = 0.0,
    passband_hz=DEFAULT_PASSBAND_HZ,
    order: int = 4,
    trim: int = 20,
    mask=None,
) -> Compensation:
    """Fit a compensation on a compensation flight: Tolles-Lawson's terms and ``effects`` beyond them.

    Parameters
    ----------
    record : CompensationRecord
    effects : sequence of str
        Terms of :data:`COMPENSATION_EFFECTS`.
    terms : sequence of str
        TL's term groups (:data:`magcal.model.tolles_lawson.TERM_GROUPS`; default the 18).
    ridge : float
        Added to the band-passed normal matrix's diagonal (MagNav's ``lambda``).
    passband_hz : (float, float)
        The band-pass (Hz).
    order : int
        Butterworth order per edge.
    trim : int
        Samples dropped at each end after the band-pass.
    mask : array_like of bool, optional
        Samples the fit uses (after the band-pass of the whole record): held-out maneuvers left out.

    Returns
    -------
    Compensation
        Its ``tl`` holds the conditioning of the fitted design, the band-passed residual and the flight's
        compensated scalar.
    """
    effects = check_effects(effects)
    terms = check_terms(terms)
    n = record.n_samples
    kept = np.zeros(n, dtype=bool)
    kept[trim : n - trim] = True
    if mask is not None:
        kept &= np.asarray(mask, dtype=bool)
    columns = tuple(record.term_currents)
    width = len(term_labels(terms)) + sum(len(_effect_labels(e, columns)) for e in effects)
    if kept.sum() <= 2 * width:
        raise MagcalError(f"{record.source}: {int(kept.sum())} samples are too few for {width} compensation terms")
    temperature_ref = float(np.mean(record.temperature_C)) if record.temperature_C is not None else 0.0
    y_bp = bandpass(record.scalar_nT, record.sample_rate_hz, passband_hz, order)
    setup = _Setup(
        record, effects, terms, float(ridge), tuple(map(float, passband_hz)), order, trim, kept, y_bp, temperature_ref
    )
    linear = tuple(e for e in effects if _effect_labels(e, columns))
    setup.effects = linear
    bias, matrix = np.zeros(3), np.eye(3)
    if "fluxgate_calibration" in effects:
        bias, matrix = _fit_fluxgate(setup)
    offset = _fit_offset(setup, bias, matrix) if "time_offset" in effects else 0.0
    comp = setup.trial(bias, matrix, offset)
    c, design, design_bp, residual = setup.solve(comp)
    q = len(comp.tl.labels)
    comp.effects = effects
    comp.tl.coefficients = c[:q]
    comp.extra_coefficients = c[q:]
    comp.tl.conditioning = conditioning(design_bp[kept])
    comp.tl.residual_bp_nT = residual
    comp.tl.compensated_nT = record.scalar_nT - design @ c
    comp.fitted = {"n_samples": n, "n_fitted": int(kept.sum()), "residual_std_nT": float(np.std(residual))}
    return comp


@dataclass
class CompensationResult(ModeResult):
    """A compensation fit with its report: the compensation mode's result.

    Attributes
    ----------
    calibration : Compensation
    record : CompensationRecord
    fom : object or None
        The FOM before and after (:class:`magcal.diagnosis.fom.FOMReport`), set by the compensation mode.
    notes : list of Note
    source : str
    """

    calibration: Compensation  # type: ignore[assignment]  # a compensation, not a magnetometer's calibration
    record: CompensationRecord | None = field(repr=False, default=None)
    fom: Any = None
    notes: list = field(default_factory=list)
    source: str = ""
    extra_text: str = ""
    validation: object = None

    mode = "compensation"

    @property
    def warnings(self) -> list[str]:
        return [note.text for note in self.notes]

    @property
    def fom_nT(self) -> float | None:
        return None if self.fom is None else float(self.fom.after.fom_nT)

    def text(self) -> str:
        """The report: the terms, the conditioning, the coefficients, the FOM table and the improvement ratio."""
        comp = self.calibration
        tl = comp.tl
        cond = tl.conditioning
        lines = [
            f"Compensation of {self.source or 'the record'}: scalar {comp.scalar_column!r} beside the fluxgate, "
            f"{self.record.n_samples if self.record is not None else '?'} samples at {comp.sample_rate_hz:g} Hz",
            f"  Tolles-Lawson terms: {', '.join(tl.terms)} ({len(tl.labels)} coefficients); beyond TL: "
            + (", ".join(comp.effects) or "none"),
            f"  band-pass {tl.passband_hz[0]:g}-{tl.passband_hz[1]:g} Hz (Butterworth {tl.order} per edge, zero "
            f"phase), {tl.trim} samples trimmed at each end, ridge {tl.ridge:g}",
        ]
        if cond is not None:
            lines.append(
                f"  conditioning: condition number {cond.condition_number:.3g} ({cond.condition_number_scaled:.3g} "
                "with the columns at unit norm): "
                + (
                    "the terms are strongly collinear; the band-passed residual, not the coefficients, is what "
                    "the data determine (try --ridge, or the terms induced5 and eddy8)"
                    if cond.condition_number_scaled > 1e3
                    else "the terms are determined"
                )
            )
        lines.append(f"  band-passed residual {tl.residual_std_nT:.4g} nT (std, fitted samples)")
        lines.append("")
        lines.append("Coefficients (MagNav.jl's order and scaling):")
        for label, value in zip(comp.labels, comp.coefficients):
            lines.append(f"  {label:<16} {value:12.4f}")
        if "fluxgate_calibration" in comp.effects:
            b = comp.fluxgate_bias_nT
            lines.append(
                f"  fluxgate bias ({b[0]:.1f}, {b[1]:.1f}, {b[2]:.1f}) nT, matrix diagonal "
                + ", ".join(f"{v:.5f}" for v in np.diag(comp.fluxgate_matrix))
            )
        if "time_offset" in comp.effects:
            lines.append(f"  fluxgate time offset {comp.time_offset_s * 1e3:+.1f} ms (positive: the fluxgate is late)")
        if self.fom is not None:
            lines += ["", "Figure of merit (band-passed peak-to-peak per maneuver, nT):", self.fom.text()]
        if self.extra_text:
            lines += ["", self.extra_text]
        if self.notes:
            lines += [""] + [f"warning: {note.text}" for note in self.notes]
        return "\n".join(lines) + "\n"

    def to_dict(self) -> dict:
        """JSON-ready: ``mode``, ``calibration`` (the document), ``fom_nT`` (after), ``fom_before_nT``,
        ``improvement_ratio``, ``fom`` (the table), ``conditioning``, ``warnings``."""
        comp = self.calibration
        out = {
            "mode": "compensation",
            "source": self.source,
            "calibration": comp.to_dict(),
            "fom_nT": self.fom_nT,
            "fom_before_nT": None if self.fom is None else float(self.fom.before.fom_nT),
            "improvement_ratio": None if self.fom is None else float(self.fom.improvement_ratio),
            "fom": None if self.fom is None else self.fom.to_dict(),
            "conditioning": None if comp.tl.conditioning is None else comp.tl.conditioning.to_dict(),
            "residual_std_nT": comp.tl.residual_std_nT,
            "warnings": self.warnings,
        }
        return jsonable(out)
