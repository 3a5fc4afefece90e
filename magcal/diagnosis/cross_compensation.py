"""The cross's compensation fitted on a record and judged: its report with the tensor FOM before and after, and its
diagnosis (which platform term beyond Tolles-Lawson the array sees), on held-out maneuvers or a second flight.

:func:`cross_record` takes what :func:`magcal.fitting.cross_compensation.fit_cross_compensation` needs from a
:class:`~magcal.data.dataset.Dataset` of four sensors (the readings, the time, the attitude, the baseline and a
platform current's column). :func:`cross_compensation_result` fits and judges it by the tensor FOM
(:mod:`magcal.diagnosis.cross_fom`) in the maneuvers found from the attitude: before is the raw readings' tensor,
after the compensated one.

The diagnosis follows the scalar compensation's (:mod:`magcal.diagnosis.compensation`): the maneuvers dealt into
:data:`~magcal.diagnosis.compensation.FOLDS` folds, each fold's maneuvers (with a guard of
``GUARD_S``, 2 s) left out of the fit and the compensated tensor's band-passed
peak-to-peak taken in them (the held-out tensor FOM, nT/m), or the fit on the whole record judged on ``also``'s
maneuvers; candidates (:data:`CROSS_CANDIDATES`: the platform's current, each current column the record has its own
candidate ``current (col)`` as in the scalar's diagnosis, and the sensors' lag against the attitude) taken one a round
when they lower it, or the held-out FOM of the sensors'
total fields, by :data:`~magcal.diagnosis.compensation.MIN_GAIN` without raising the other as much: a lag of all
four is an eddy term to first order, which each sensor's eddy matrix takes, so the tensor barely shows it while each
sensor's field keeps its second order. The floor is the tensor FOM the sensors' white noise alone leaves
(its sigma from the compensated vectors' second differences). The verdicts are the scalar compensation's.
"""

from __future__ import annotations

import time as _time
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from magcal.core.errors import MagcalError
from magcal.core.jsonable import jsonable
from magcal.core.notes import Note
from magcal.data.attitude import attitude as dataset_attitude
from magcal.data.current_columns import CurrentTerm, current_columns, current_series
from magcal.data.dataset import Dataset
from magcal.data.flight_columns import CURRENT_COLUMNS as FLIGHT_CURRENT_COLUMNS
from magcal.diagnosis.compensation import (
    ADEQUATE_RATIO,
    FOLDS,
    GUARD_S,
    MAX_CURRENT_COLUMNS,
    MAX_EFFECTS,
    MIN_GAIN,
    _fold_masks,
    diagnosis_document,
    diagnosis_table,
    held_out_words,
    noise_sigma_nT,
)
from magcal.diagnosis.cross_fom import CrossFOMReport, cross_fom_report, sensor_fom, tensor_fom
from magcal.diagnosis.fom import find_maneuvers
from magcal.fitting.cross_compensation import CrossCompensation, fit_cross_compensation
from magcal.fitting.result import ModeResult
from magcal.fitting.tolles_lawson import sample_rate_from_times

__all__ = [
    "CROSS_CANDIDATES",
    "CROSS_EFFECTS",
    "CURRENT_COLUMNS",
    "LAG_FLAGS",
    "LAG_NEEDS_FIELD",
    "CrossCandidate",
    "CrossCompensationDiagnosis",
    "CrossCompensationResult",
    "CrossRecord",
    "check_cross_effects",
    "cross_compensation_result",
    "cross_maneuvers",
    "cross_record",
    "diagnose_cross_compensation",
    "held_out_foms",
    "held_out_tensor_fom",
]

#: The terms beyond Tolles-Lawson the cross's fit takes (``--effects``): a platform current's field per ampere, and
#: the sensors' samples late against the attitude's (the scalar compensation's time offset, found the same way).
CROSS_EFFECTS = ("current", "time_offset")

#: The candidates the diagnosis tries.
CROSS_CANDIDATES = CROSS_EFFECTS

#: A platform current's columns found by name (A, or a throttle's fraction): the first the current term's, the others
#: the diagnosis's candidates (the scalar compensation's, :data:`magcal.data.flight_columns.CURRENT_COLUMNS`, and
#: ``current``).
CURRENT_COLUMNS = tuple(dict.fromkeys(("current_A", "current", "throttle") + FLIGHT_CURRENT_COLUMNS))


def check_cross_effects(names) -> tuple:
    """``names`` checked against :data:`CROSS_EFFECTS` (a :class:`~magcal.core.errors.MagcalError` naming the known ones)."""
    names = tuple(dict.fromkeys(str(n) for n in (names or ())))
    unknown = [n for n in names if n not in CROSS_EFFECTS]
    if unknown:
        raise MagcalError(
            f"the cross's compensation has no term {', '.join(map(repr, unknown))}; it takes {', '.join(CROSS_EFFECTS)}"
        )
    return names


@dataclass
class CrossRecord(CurrentTerm):
    """What the cross's compensation takes from a record.

    Attributes
    ----------
    readings_nT : numpy.ndarray, shape (4, N, 3)
        Raw readings, each sensor in its own frame (nT).
    sample_rate_hz : float
    attitude_deg : numpy.ndarray, shape (N, 3), or None
        Roll, pitch, yaw (deg, aerospace ZYX, body -> NED).
    baseline_m : float
    current_A : numpy.ndarray, shape (N,), or None
        The platform's current (its column :attr:`current_column`): the current term's first column.
    current_column : str or None
    source : str
    more_currents : dict
        The current term's further columns (name -> values, A), each its own field per ampere at each sensor.
    other_currents : dict
        The record's current columns the term does not take (name -> values): the diagnosis's candidates.
    """

    _CURRENT_FIELD = "current_A"

    readings_nT: np.ndarray
    sample_rate_hz: float
    attitude_deg: np.ndarray | None
    baseline_m: float
    current_A: np.ndarray | None = None
    current_column: str | None = None
    source: str = ""
    more_currents: dict = field(default_factory=dict)
    other_currents: dict = field(default_factory=dict)

    @property
    def currents_A(self) -> np.ndarray | None:
        """The current term's columns (N, K), A (None without a current)."""
        term = self.term_currents
        return np.column_stack(list(term.values())) if term else None

    @property
    def n_samples(self) -> int:
        return int(self.readings_nT.shape[1])


def _attitude_deg(dataset: Dataset) -> np.ndarray | None:
    rotation = dataset_attitude(dataset)
    if rotation is None:
        return None
    att = rotation.as_euler("ZYX", degrees=True)[:, ::-1]
    att[:, 2] = np.mod(att[:, 2], 360.0)
    return att


def cross_record(dataset: Dataset, current=None) -> CrossRecord:
    """The :class:`CrossRecord` of a dataset of four sensors with times, a baseline and (for the maneuvers) an
    attitude; ``current`` names the current term's columns (``"a,b"`` or a list; default the first of
    :data:`CURRENT_COLUMNS` it has, the others kept for the diagnosis:
    :func:`magcal.data.current_columns.current_columns`)."""
    where = dataset.source or "the record"
    if dataset.n_sensors != 4:
        raise MagcalError(
            f"{where}: the cross's compensation needs four sensors (s1x .. s4z); it has {dataset.n_sensors}"
        )
    if dataset.time_s is None:
        raise MagcalError(f"{where}: the cross's compensation needs the samples' times (a column t, in s)")
    if not dataset.baseline_m:
        raise MagcalError(
            f"{where}: the tensor needs the cross's baseline: add '# baseline_m: 0.5' (m) to the file's head"
        )
    term, others = current_columns(dataset, current, where, CURRENT_COLUMNS)
    term_values, other_values = current_series(dataset, term, others, where)
    name = term[0] if term else None
    values = None if name is None else term_values[name]
    return CrossRecord(
        np.asarray(dataset.readings_nT, dtype=float),
        sample_rate_from_times(dataset.time_s),
        _attitude_deg(dataset),
        float(dataset.baseline_m),
        values,
        name,
        dataset.source or "",
        {c: term_values[c] for c in term[1:]},
        other_values,
    )


def cross_maneuvers(record: CrossRecord) -> list:
    """The box's maneuvers, found in the attitude (else in sensor 1's direction)."""
    flux = None if record.attitude_deg is not None else record.readings_nT[0]
    return find_maneuvers(record.sample_rate_hz, attitude_deg=record.attitude_deg, flux_nT=flux)


def _fit(record: CrossRecord, effects, field_ned_nT, mask=None, **options) -> CrossCompensation:
    current = record.currents_A if "current" in effects else None
    if "time_offset" in effects and (field_ned_nT is None or record.attitude_deg is None):
        raise MagcalError(
            f"{record.source or 'the record'}: the time offset term needs the attitude and the Earth field vector "
            "(ref_n, ref_e, ref_d, --reference igrf or --reference-vector): the four's mean field lags with them"
        )
    if "current" in effects and current is None:
        raise MagcalError(
            f"{record.source or 'the record'}: the current term needs the platform's current (a column "
            f"{', '.join(CURRENT_COLUMNS)}, or --current NAME)"
        )
    comp = fit_cross_compensation(
        record.readings_nT,
        reference="attitude" if field_ned_nT is not None else "mean",
        field_ned_nT=field_ned_nT,
        sample_rate_hz=record.sample_rate_hz,
        attitude_deg=record.attitude_deg,
        baseline_m=record.baseline_m,
        current_A=current,
        mask=mask,
        time_offset="time_offset" in effects,
        **options,
    )
    comp.current_column = record.current_column if current is not None else None
    comp.current_columns = tuple(record.term_currents) if current is not None else ()
    return comp


def _compensated(comp: CrossCompensation, record: CrossRecord) -> np.ndarray:
    return comp.compensate(
        record.readings_nT,
        sample_rate_hz=record.sample_rate_hz,
        current_A=record.all_currents if comp.current else None,
    )


@dataclass
class CrossCompensationResult(ModeResult):
    """The cross's compensation fitted on a record, with its FOM report: the ``cross_compensation`` mode's result.

    Attributes
    ----------
    calibration : CrossCompensation
    record : CrossRecord
    fom : CrossFOMReport or None
        The tensor and sensor FOM before (the raw readings) and after (None, with a note, without maneuvers).
    effects : tuple of str
    notes : list of Note
    source : str
    """

    calibration: CrossCompensation  # type: ignore[assignment]  # a compensation, not a magnetometer's calibration
    record: CrossRecord | None = field(repr=False, default=None)
    fom: CrossFOMReport | None = None
    effects: tuple = ()
    notes: list = field(default_factory=list)
    source: str = ""
    validation: Any = None

    mode = "cross_compensation"

    @property
    def warnings(self) -> list[str]:
        return [note.text for note in self.notes]

    def text(self) -> str:
        """The fit per sensor, then the FOM per maneuver before and after, the components', the sensors' and the
        improvement ratio."""
        head = (
            f"Cross compensation of {self.source or 'the record'}: four sensors, "
            f"{self.record.n_samples if self.record is not None else '?'} samples; beyond TL: "
            + (", ".join(self.effects) or "none")
        )
        parts = [head, self.calibration.text()]
        if self.fom is not None:
            parts.append(self.fom.text())
        return "\n".join(parts) + "\n"

    def to_dict(self) -> dict:
        """``mode``, ``effects``, ``tensor_fom_nT_per_m`` (before, after, per maneuver), ``fom_nT`` (each sensor's
        before and after), ``improvement_ratio`` and the full ``fom`` report."""
        doc: dict = {"mode": self.mode, "source": self.source, "effects": list(self.effects)}
        if self.fom is not None:
            f = self.fom
            doc["tensor_fom_nT_per_m"] = {
                "before": f.before.fom_nT_per_m,
                "after": f.after.fom_nT_per_m,
                "per_maneuver": [
                    {"heading_deg": round(m.heading_deg, 1), "kind": m.kind, "before": float(b), "after": float(a)}
                    for m, b, a in zip(f.after.maneuvers, f.before.maneuver_nT_per_m, f.after.maneuver_nT_per_m)
                ],
            }
            doc["fom_nT"] = [
                {"sensor": k + 1, "before": b.fom_nT, "after": a.fom_nT}
                for k, (b, a) in enumerate(zip(f.sensors_before, f.sensors_after))
            ]
            doc["improvement_ratio"] = float(f.improvement_ratio)
            doc["fom"] = f.to_dict()
        return jsonable(doc)


def cross_compensation_result(
    record: CrossRecord, effects=(), *, field_ned_nT=None, source: str = "", **options
) -> CrossCompensationResult:
    """Fit the cross's compensation (against the attitude's Earth field when ``field_ned_nT`` is given, else the
    four's mean field) and judge it by the tensor FOM in the record's maneuvers (``options``: ``ridge``,
    ``magnitude_passes``, ``passband_hz``, ``trim``)."""
    effects = check_cross_effects(effects)
    comp = _fit(record, effects, field_ned_nT, **options)
    notes = [Note(text, UserWarning, "cross compensation") for text in comp.notes]
    comp.notes = []
    fom = None
    maneuvers = cross_maneuvers(record)
    if maneuvers:
        fom = cross_fom_report(
            record.readings_nT,
            _compensated(comp, record),
            record.baseline_m,
            record.sample_rate_hz,
            maneuvers=maneuvers,
            passband_hz=comp.passband_hz,
        )
    else:
        notes.append(Note("no FOM: no roll, pitch or yaw maneuver found in the attitude", UserWarning, "fom"))
    return CrossCompensationResult(comp, record, fom, effects, notes, source or record.source)


def held_out_foms(
    record: CrossRecord, effects=(), maneuvers=None, *, field_ned_nT=None, also=None, **options
) -> tuple[float, float]:
    """(the held-out tensor FOM, nT/m; the held-out FOM of the sensors' total fields, nT, the four's mean) of the
    cross's compensation with ``effects``: on ``also`` (another flight, in its own maneuvers) fitted on the whole
    record, else summed over the folds of ``maneuvers`` each left out of its fit (as
    :func:`magcal.diagnosis.compensation.held_out_fom`)."""
    if also is not None:
        comp = _fit(record, effects, field_ned_nT, **options)
        on = _compensated(comp, also)
        found = cross_maneuvers(also)
        tensor = tensor_fom(on, also.baseline_m, found, also.sample_rate_hz).fom_nT_per_m
        return float(tensor), _sensors_fom(on, found, also.sample_rate_hz)
    guard = int(round(GUARD_S * record.sample_rate_hz))
    tensor = sensors = 0.0
    for held, mask in _fold_masks(record.n_samples, maneuvers, FOLDS, guard):
        comp = _fit(record, effects, field_ned_nT, mask=mask, **options)
        on = _compensated(comp, record)
        tensor += tensor_fom(on, record.baseline_m, held, record.sample_rate_hz).fom_nT_per_m
        sensors += _sensors_fom(on, held, record.sample_rate_hz)
    return float(tensor), float(sensors)


def _sensors_fom(vectors_nT, maneuvers, sample_rate_hz) -> float:
    """The four sensors' total-field FOM (nT), their mean."""
    return float(np.mean([t.fom_nT for t in sensor_fom(vectors_nT, maneuvers, sample_rate_hz)]))


def held_out_tensor_fom(
    record: CrossRecord, effects=(), maneuvers=None, *, field_ned_nT=None, also=None, also_field_ned_nT=None, **options
) -> float:
    """The held-out tensor FOM (nT/m) of the cross's compensation with ``effects`` (:func:`held_out_foms`)."""
    return held_out_foms(record, effects, maneuvers, field_ned_nT=field_ned_nT, also=also, **options)[0]


def _floor(compensated_nT, baseline_m, maneuvers, sample_rate_hz, draws: int = 8) -> tuple[float, float]:
    """The sensors' white noise (nT, 1 sigma) and the mean tensor FOM (nT/m) it alone leaves in ``maneuvers``.

    The noise is taken from the differences of the opposite sensors (1 - 3, 2 - 4: the Earth field's turning, common
    to both, cancels; their noise adds in quadrature), the median over their six axes."""
    v = np.asarray(compensated_nT, dtype=float)
    pairs = (v[0] - v[2], v[1] - v[3])
    sigma = float(np.median([noise_sigma_nT(d[:, k]) for d in pairs for k in range(3)]) / np.sqrt(2.0))
    rng = np.random.default_rng(12345)
    shape = np.shape(compensated_nT)
    values = [
        tensor_fom(rng.normal(0.0, sigma, shape), baseline_m, maneuvers, sample_rate_hz).fom_nT_per_m
        for _ in range(draws)
    ]
    return sigma, float(np.mean(values))


@dataclass
class CrossCandidate:
    """One candidate term judged by the held-out tensor FOM (nT/m) and the held-out FOM of the sensors' total
    fields (nT, the four's mean): a term common to the four (a lag of all four against the attitude) moves each
    sensor's field and barely the tensor."""

    name: str
    round: int = 1
    judged: bool = True
    fom_before_nT_per_m: float = float("nan")
    fom_after_nT_per_m: float = float("nan")
    recommended: bool = False
    evidence: str = ""
    reason: str = ""
    sensor_fom_before_nT: float = float("nan")
    sensor_fom_after_nT: float = float("nan")
    columns: tuple = ()

    unit: ClassVar[str] = "nT/m"

    @property
    def fom_before(self) -> float:
        """:attr:`fom_before_nT_per_m` (the held-out tensor FOM, nT/m;
        :class:`magcal.diagnosis.fom_protocol.CandidateFOM`)."""
        return self.fom_before_nT_per_m

    @property
    def fom_after(self) -> float:
        """:attr:`fom_after_nT_per_m` (nT/m)."""
        return self.fom_after_nT_per_m

    @property
    def label(self) -> str:
        """The name, with the current's column(s): ``current (cur_strb)``."""
        return f"{self.name} ({', '.join(self.columns)})" if self.columns else self.name

    @property
    def tensor_gain(self) -> float:
        """Relative fall of the held-out tensor FOM (1 - after / before)."""
        return float(1.0 - self.fom_after_nT_per_m / self.fom_before_nT_per_m) if self.judged else float("nan")

    @property
    def sensor_gain(self) -> float:
        """Relative fall of the held-out sensors' FOM."""
        return float(1.0 - self.sensor_fom_after_nT / self.sensor_fom_before_nT) if self.judged else float("nan")

    @property
    def gain(self) -> float:
        """The larger of the two falls, when neither figure rises by :data:`~magcal.diagnosis.compensation.MIN_GAIN`
        or more (else the larger rise, negative)."""
        if not self.judged:
            return float("nan")
        gains = (self.tensor_gain, self.sensor_gain) if np.isfinite(self.sensor_gain) else (self.tensor_gain,)
        return float(max(gains) if min(gains) > -MIN_GAIN else min(gains))

    @property
    def holds(self) -> bool:
        """Whether its gain on held-out data reaches :data:`~magcal.diagnosis.compensation.MIN_GAIN`."""
        return bool(self.judged and self.gain >= MIN_GAIN)

    def to_dict(self) -> dict:
        return jsonable(
            {
                "name": self.name,
                "round": self.round,
                "judged": self.judged,
                "fom_before_nT_per_m": self.fom_before_nT_per_m if self.judged else None,
                "fom_after_nT_per_m": self.fom_after_nT_per_m if self.judged else None,
                "gain": self.gain if self.judged else None,
                "sensor_fom_before_nT": self.sensor_fom_before_nT if self.judged else None,
                "sensor_fom_after_nT": self.sensor_fom_after_nT if self.judged else None,
                "recommended": self.recommended,
                "evidence": self.evidence,
                "reason": self.reason,
                "columns": list(self.columns),
            }
        )

    def text(self) -> str:
        if not self.judged:
            return f"  {self.label:<22} not judged: {self.reason}"
        mark = "RECOMMENDED" if self.recommended else "no"
        return (
            f"  {self.label:<22} {self.fom_before_nT_per_m:9.3f} -> {self.fom_after_nT_per_m:9.3f} nT/m "
            f"({-100 * self.tensor_gain:+.0f} %), sensors {self.sensor_fom_before_nT:7.3f} -> "
            f"{self.sensor_fom_after_nT:7.3f} nT ({-100 * self.sensor_gain:+.0f} %)  {mark:<11}  {self.evidence}"
        )


@dataclass
class CrossCompensationDiagnosis:
    """What :func:`diagnose_cross_compensation` found (the verdicts of
    :data:`magcal.diagnosis.compensation.VERDICTS`)."""

    verdict: str
    summary: str
    effects: list
    candidates: list
    explained_by: list
    fom_held_out_nT_per_m: float
    fom_final_nT_per_m: float | None
    floor_fom_nT_per_m: float
    noise_nT: float
    validation: dict
    warnings: list = field(default_factory=list)
    notes: list = field(default_factory=list)
    result: CrossCompensation | None = field(repr=False, default=None)
    elapsed_s: float = 0.0
    current_columns: list = field(default_factory=list)

    mode = "cross_compensation"
    unit: ClassVar[str] = "nT/m"

    @property
    def fom_held_out(self) -> float:
        """:attr:`fom_held_out_nT_per_m` (the held-out tensor FOM, nT/m;
        :class:`magcal.diagnosis.fom_protocol.DiagnosisFOM`)."""
        return self.fom_held_out_nT_per_m

    @property
    def fom_final(self) -> float | None:
        """:attr:`fom_final_nT_per_m` (nT/m)."""
        return self.fom_final_nT_per_m

    @property
    def floor_fom(self) -> float:
        """:attr:`floor_fom_nT_per_m` (nT/m)."""
        return self.floor_fom_nT_per_m

    @property
    def partially_explained_by(self) -> list:
        return []

    def to_dict(self) -> dict:
        """The JSON document of ``magcal diagnose --mode cross_compensation --json``."""
        figures = {
            "tensor_fom_held_out_nT_per_m": self.fom_held_out_nT_per_m,
            "tensor_fom_final_nT_per_m": self.fom_final_nT_per_m,
            "floor_tensor_fom_nT_per_m": self.floor_fom_nT_per_m,
            "current_columns": list(self.current_columns),
        }
        return diagnosis_document(self, figures)

    def table(self) -> str:
        """The verdict, the summary and the candidates, one line each."""
        figure = (
            f"held-out tensor FOM {self.fom_held_out_nT_per_m:.3f} nT/m ({held_out_words(self.validation)}); the "
            f"sensors' noise {self.noise_nT:.3g} nT leaves {self.floor_fom_nT_per_m:.3f} nT/m"
        )
        header = (
            f"  {'candidate':<22} {'held-out tensor FOM before -> after':>36}, {'the sensors held out':>34}  "
            f"{'advice':<11}  evidence"
        )
        return diagnosis_table(self, figure, header)

    def text(self) -> str:
        return self.table() + "\n"


def _evidence(name: str, comp: CrossCompensation) -> str:
    if name == "time_offset":
        late = "late" if comp.time_offset_s >= 0 else "early"
        return f"the sensors {abs(comp.time_offset_s) * 1e3:.0f} ms {late} against the attitude"
    if name == "current":
        names = comp.current_columns or (comp.current_column or "the current",)
        parts = []
        for j, column in enumerate(names):
            k = np.array([np.linalg.norm(s.per_ampere[j]) for s in comp.sensors])
            of = f" of {column}" if len(names) > 1 else ""
            parts.append(", ".join(f"{v:.3g}" for v in k) + f" nT per ampere{of}")
        return "a field of " + "; ".join(parts) + " at sensors 1-4"
    return ""


def _verdict(explained, base, final, floor, scheme, effects, columns=(), grew=()) -> tuple[str, str]:
    on = "on held-out maneuvers" if scheme == "maneuvers" else "on the other flight"
    model = "Tolles-Lawson per sensor" + (" with " + ", ".join(effects) if effects else "")
    if explained or grew:
        added = list(explained) + ([f"the current's {', '.join(grew)}"] if "current" not in explained and grew else [])
        return "missing_effect", (
            f"{model} leaves a held-out tensor FOM of {base:.3f} nT/m {on}; adding {', '.join(added)} brings it "
            f"to {final:.3f} nT/m (the noise's {floor:.3f} nT/m): magcal calibrate --mode cross_compensation "
            "--effects "
            + ",".join(list(effects) + list(explained))
            + (f" --current {','.join(columns)}" if columns else "")
        )
    if base <= ADEQUATE_RATIO * floor:
        return "adequate", (
            f"{model} leaves a held-out tensor FOM of {base:.3f} nT/m {on}, within {ADEQUATE_RATIO}x of what the "
            f"sensors' noise leaves ({floor:.3f} nT/m); no candidate lowers it by {100 * MIN_GAIN:.0f} %"
        )
    return "unexplained", (
        f"{model} leaves a held-out tensor FOM of {base:.3f} nT/m {on}, {base / floor:.1f}x what the sensors' noise "
        f"leaves ({floor:.3f} nT/m), and no candidate lowers it by {100 * MIN_GAIN:.0f} %: the platform has a term "
        "none of them follows"
    )


def _not_judged(other, effects, pool, maneuvers, floor, sigma, base, started) -> CrossCompensationDiagnosis:
    """The diagnosis of a record (or another flight, ``other``) with too few maneuvers to hold any out."""
    cands = [CrossCandidate(name, judged=False, reason="nothing to judge on") for name in pool]
    summary = (
        f"not judged: {'the other flight' if other else 'the record'} holds {len(maneuvers)} maneuvers, too few "
        "to hold any out; fly a full box or give another flight (--also)"
    )
    validation = {"scheme": "none", "folds": FOLDS, "n_maneuvers": len(maneuvers)}
    return CrossCompensationDiagnosis(
        "not_judged", summary, effects, cands, [], float("nan"), None, floor, sigma, validation, [], [], base,
        _time.perf_counter() - started,
    )  # fmt: skip


#: Why the lag (``time_offset``) is not judged, in the data's words (the command line adds its options: it
#: prints :data:`LAG_FLAGS` after it; the page its location inputs).
LAG_NEEDS_FIELD = (
    "the sensors' lag needs the Earth's field vector: the record's attitude with ref_n/ref_e/ref_d columns, "
    "a # site: line, or a location"
)
#: The command line's words for :data:`LAG_NEEDS_FIELD`: the options that give the field vector.
LAG_FLAGS = (
    "give --reference igrf (at --lat/--lon, the # site: line or the lat, lon columns) or --reference-vector N,E,D"
)


def _unusable(name: str, record: CrossRecord, field_ned_nT=None, column: str | None = None) -> str:
    """Why the record cannot judge a candidate ('' when it can): the current's ``column`` of it."""
    if name == "time_offset" and (field_ned_nT is None or record.attitude_deg is None):
        return LAG_NEEDS_FIELD
    if name == "current":
        every = record.all_currents
        if not every:
            return f"the record has no current column ({', '.join(CURRENT_COLUMNS[:3])} ...)"
        if column is not None and column not in every:
            return f"the record has no {column} column"
        if column is not None and np.ptp(every[column]) == 0:
            return f"its {column} column does not change"
    return ""


def _taking(record: CrossRecord, columns) -> CrossRecord:
    """``record`` whose current term takes ``columns`` (as it is without any)."""
    return record.taking_currents(columns) if columns else record


class _Search:
    """The forward search of :func:`diagnose_cross_compensation`: the terms and current columns taken so far, the
    held-out (tensor, sensors') FOM they reach (nT/m, nT), and the trials of each round."""

    def __init__(self, record, also, maneuvers, field_ned_nT, options, effects, base):
        self.record, self.also, self.maneuvers = record, also, maneuvers
        self.field_ned_nT, self.options = field_ned_nT, options
        self.effects = list(effects)
        self.current = list(effects)
        self.columns = list(record.term_currents) if "current" in effects else []
        self.initial_columns = list(self.columns)
        self.open_names: list[str] = []
        self.open_columns: list[str] = []
        self.now = self.score(self.current, self.columns)
        self.fit = base  # the fit of the model taken so far

    def score(self, names, with_columns) -> tuple[float, float]:
        """The held-out tensor and sensors' FOM of the model ``names`` with the current ``with_columns``."""
        taken = with_columns if "current" in names else []
        also = None if self.also is None else _taking(self.also, taken)
        return held_out_foms(
            _taking(self.record, taken), names, self.maneuvers, field_ned_nT=self.field_ned_nT, also=also,
            **self.options,
        )  # fmt: skip

    def why(self, name, column=None) -> str:
        """Why the flight (or the other flight) cannot judge ``name`` ('' when both can)."""
        record, also, field_ned_nT = self.record, self.also, self.field_ned_nT
        return _unusable(name, record, field_ned_nT, column) or (
            _unusable(name, also, field_ned_nT, column) if also else ""
        )

    def unjudged(self, pool) -> list[CrossCandidate]:
        """The candidates the flight cannot judge, with why; sets the terms and current columns still open."""
        unusable = {n: r for n in pool if (r := self.why(n))}
        out = [CrossCandidate(n, judged=False, reason=r) for n, r in unusable.items()]
        wants = ("current" in pool and "current" not in unusable) or "current" in self.effects
        every = [c for c in self.record.all_currents if c not in self.columns] if wants else []
        out += [
            CrossCandidate("current", judged=False, reason=r, columns=(c,))
            for c in every
            if (r := self.why("current", c))
        ]
        self.open_columns = [c for c in every if not self.why("current", c)]
        self.open_names = [n for n in pool if n not in unusable]
        return out

    def trial(self, name, round_, added=()) -> CrossCandidate:
        """``name`` (with the current's ``added`` columns) added to the model: its held-out FOMs and evidence."""
        names = self.current + [name] if name not in self.current else list(self.current)
        with_columns = self.columns + list(added)
        tensor, sensors = self.score(names, with_columns)
        taken = _taking(self.record, with_columns if "current" in names else [])
        evidence = _evidence(name, _fit(taken, names, self.field_ned_nT, **self.options))
        before = self.now
        return CrossCandidate(
            name, round_, True, before[0], tensor, False, evidence, "", before[1], sensors, columns=tuple(added)
        )

    def rounds(self, floor) -> list[CrossCandidate]:
        """Add the best candidate that holds, round after round, until none holds, none is left or the tensor FOM
        is at the floor; every trial, the taken ones marked recommended."""
        out: list[CrossCandidate] = []
        for round_ in range(1, MAX_EFFECTS + MAX_CURRENT_COLUMNS):
            trials = self._trials(round_)
            out.extend(trials)
            best = next((c for c in trials if c.holds), None)
            if best is None:
                break
            self._take(best)
            if not (self.open_names or self.open_columns) or self.now[0] <= ADEQUATE_RATIO * floor:
                break
        return out

    def _trials(self, round_) -> list[CrossCandidate]:
        added_terms = len(self.current) - len(self.effects)
        names = [n for n in self.open_names if added_terms < MAX_EFFECTS and n not in self.current]
        more = self.open_columns if len(self.columns) < MAX_CURRENT_COLUMNS else []
        trials = [self.trial(name, round_) for name in names if name != "current"]
        if "current" in self.current or "current" in names:
            trials += [self.trial("current", round_, (c,)) for c in more]
        trials.sort(key=lambda c: -c.gain)
        return trials

    def _take(self, best: CrossCandidate) -> None:
        best.recommended = True
        if best.name not in self.current:
            self.current.append(best.name)
        self.columns += list(best.columns)
        self.open_columns = [c for c in self.open_columns if c not in self.columns]
        self.now = (best.fom_after_nT_per_m, best.sensor_fom_after_nT)
        self.open_names = [
            n for n in self.open_names if n not in self.current or (n == "current" and self.open_columns)
        ]
        taken = _taking(self.record, self.columns if "current" in self.current else [])
        self.fit = _fit(taken, self.current, self.field_ned_nT, **self.options)


def diagnose_cross_compensation(
    record: CrossRecord,
    effects=(),
    *,
    field_ned_nT=None,
    also: CrossRecord | None = None,
    also_field_ned_nT=None,
    **options,
) -> CrossCompensationDiagnosis:
    """Judge the terms beyond Tolles-Lawson (:data:`CROSS_CANDIDATES`) on the held-out tensor FOM and name those the
    platform has (module docstring).

    Parameters
    ----------
    record : CrossRecord
        The compensation flight.
    effects : sequence of str
        Terms already in the model.
    field_ned_nT : array_like, shape (3,) or (N, 3), optional
        The Earth field vector (nT, NED) for the attitude reference; None: the four's mean field.
    also : CrossRecord, optional
        Another flight of the same platform to judge on instead of held-out maneuvers.
    options
        For :func:`magcal.fitting.cross_compensation.fit_cross_compensation` (``ridge``, ``magnitude_passes``...).
    """
    started = _time.perf_counter()
    effects = list(check_cross_effects(effects))
    pool = [c for c in CROSS_CANDIDATES if c not in effects]
    maneuvers = cross_maneuvers(record)
    on = also if also is not None else record
    judged_maneuvers = cross_maneuvers(also) if also is not None else maneuvers
    scheme = "flight" if also is not None else "maneuvers"
    base = _fit(record, effects, field_ned_nT, **options)
    sigma, floor = (
        _floor(_compensated(base, on), on.baseline_m, judged_maneuvers, on.sample_rate_hz)
        if judged_maneuvers
        else (float("nan"), float("nan"))
    )
    validation = {"scheme": scheme, "folds": FOLDS, "n_maneuvers": len(judged_maneuvers)}
    enough = bool(judged_maneuvers) if also is not None else len(maneuvers) >= FOLDS
    if not enough:
        return _not_judged(also is not None, effects, pool, judged_maneuvers, floor, sigma, base, started)

    search = _Search(record, also, maneuvers, field_ned_nT, options, effects, base)
    candidates = search.unjudged(pool)
    base_fom = search.now[0]
    candidates += search.rounds(floor)
    current, columns, now, fit = search.current, search.columns, search.now, search.fit
    initial_columns = search.initial_columns
    explained = current[len(effects) :]
    grew = columns[len(initial_columns) :]
    final = now[0]
    advice = columns if "current" in current and len(record.all_currents) > 1 else []
    verdict, summary = _verdict(explained, base_fom, final, floor, scheme, effects, advice, grew)
    changed = bool(explained or grew)
    warnings = []
    if changed and final > ADEQUATE_RATIO * floor:
        named = ", ".join(explained) if explained else "the current's " + ", ".join(grew)
        warnings.append(
            f"with {named} the held-out tensor FOM is {final:.3f} nT/m, still {final / floor:.1f}x "
            "what the sensors' noise leaves: the platform has more than the candidates follow"
        )
    return CrossCompensationDiagnosis(
        verdict, summary, effects, candidates, explained, base_fom, final if changed else None, floor, sigma,
        validation, warnings, [], fit, _time.perf_counter() - started, columns if "current" in current else [],
    )  # fmt: skip
