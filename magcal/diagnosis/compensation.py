"""The diagnosis of a compensation: which term beyond Tolles-Lawson the platform has, judged on held-out
maneuvers or on a second flight.

A compensation flight's Tolles-Lawson fit (:mod:`magcal.fitting.compensation`) leaves a figure of merit (FOM:
:mod:`magcal.diagnosis.fom`); what it leaves above the scalar's noise is a term TL lacks. The candidates
(:data:`CANDIDATES`, the terms of :data:`magcal.fitting.compensation.COMPENSATION_EFFECTS`) are each added to the
model and judged as the compensation will be used, on samples its fit did not see:

* **held-out maneuvers** (one flight): the maneuvers are dealt into :data:`FOLDS` folds (maneuver ``i`` into fold
  ``i mod FOLDS``, so each fold holds maneuvers of several headings and kinds); each fold's maneuvers (and
  :data:`GUARD_S` on either side, where the band-pass spreads them) are left out of the fit, and the compensated
  signal's band-passed peak-to-peak is taken in them. Their sum over the folds is the held-out FOM: every maneuver
  judged once, by a fit that did not see it.
* **another flight** (``also``): the fit on the whole record compensates the other flight, whose FOM is taken in
  its own maneuvers.

A candidate is recommended when it lowers the held-out FOM by :data:`MIN_GAIN` or more; the best joins the model
and the rest are judged again (forward selection, at most :data:`MAX_EFFECTS`). The floor is the FOM the scalar's
white noise alone leaves in the same maneuvers (the noise from the compensated signal's second differences;
:func:`noise_floor_fom`).

The verdict: ``missing_effect`` (terms recommended: ``explained_by``), ``adequate`` (nothing recommended and the
held-out FOM within :data:`ADEQUATE_RATIO` of the floor), ``unexplained`` (nothing recommended and the FOM far
above the floor: the platform has a term no candidate follows) or ``not_judged`` (fewer maneuvers than folds and
no other flight: nothing could be held out).
"""

from __future__ import annotations

import time as _time
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from magcal.core.errors import MagcalError
from magcal.core.jsonable import jsonable
from magcal.core.notes import Note
from magcal.core.stats import robust_sigma
from magcal.diagnosis.fom import figure_of_merit, find_maneuvers, fom_report
from magcal.fitting.compensation import (
    COMPENSATION_EFFECTS,
    Compensation,
    CompensationRecord,
    CompensationResult,
    check_effects,
    fit_compensation,
)
from magcal.model.tolles_lawson import bandpass

#: The candidates, in the order they are tried.
CANDIDATES = tuple(COMPENSATION_EFFECTS)

#: Folds the maneuvers are dealt into for the held-out judgement.
FOLDS = 4

#: Samples on either side of a held-out maneuver also left out of the fit (s): the band-pass's reach.
GUARD_S = 2.0

#: Least relative fall of the held-out FOM for a candidate to be recommended.
MIN_GAIN = 0.10

#: Most terms the forward selection adds.
MAX_EFFECTS = 3

#: Most current columns the current term takes (each a round of its own).
MAX_CURRENT_COLUMNS = 4

#: The compensation is at its floor when its held-out FOM is within this factor of the noise's.
ADEQUATE_RATIO = 1.3

#: Verdicts, as the other diagnoses'.
VERDICTS = ("adequate", "missing_effect", "unexplained", "not_judged")

__all__ = [
    "ADEQUATE_RATIO",
    "CANDIDATES",
    "FOLDS",
    "MIN_GAIN",
    "VERDICTS",
    "CompensationCandidate",
    "CompensationDiagnosis",
    "CompensationValidation",
    "compensation_result",
    "diagnose_compensation",
    "held_out_fom",
    "noise_floor_fom",
    "validate_compensation",
]


@dataclass
class CompensationCandidate:
    """One candidate term judged.

    Attributes
    ----------
    name : str
    round : int
        The forward selection's round (1 first).
    judged : bool
        False when the record lacks what it needs (``reason`` says what).
    fom_before_nT, fom_after_nT : float
        Held-out FOM without and with it (nT).
    recommended : bool
    evidence : str
        What its fit on the whole record found (its coefficients, the offset, the fluxgate's errors).
    reason : str
    columns : tuple of str
        For the current term: the current column(s) this trial adds (``cur_strb``).
    """

    name: str
    round: int = 1
    judged: bool = True
    fom_before_nT: float = float("nan")
    fom_after_nT: float = float("nan")
    recommended: bool = False
    evidence: str = ""
    reason: str = ""
    columns: tuple = ()

    @property
    def label(self) -> str:
        """The name, with the current's column(s): ``current (cur_strb)``."""
        return f"{self.name} ({', '.join(self.columns)})" if self.columns else self.name

    unit: ClassVar[str] = "nT"

    @property
    def fom_before(self) -> float:
        """:attr:`fom_before_nT` (nT; :class:`magcal.diagnosis.fom_protocol.CandidateFOM`)."""
        return self.fom_before_nT

    @property
    def fom_after(self) -> float:
        """:attr:`fom_after_nT` (nT)."""
        return self.fom_after_nT

    @property
    def gain(self) -> float:
        """Relative fall of the held-out FOM (1 - after / before)."""
        return float(1.0 - self.fom_after_nT / self.fom_before_nT) if self.judged else float("nan")

    def to_dict(self) -> dict:
        return jsonable(
            {
                "name": self.name,
                "round": self.round,
                "judged": self.judged,
                "fom_before_nT": self.fom_before_nT if self.judged else None,
                "fom_after_nT": self.fom_after_nT if self.judged else None,
                "gain": self.gain if self.judged else None,
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
            f"  {self.label:<22} {self.fom_before_nT:8.3f} -> {self.fom_after_nT:8.3f} nT ({-100 * self.gain:+.0f} %)"
            f"  {mark:<11}  {self.evidence}"
        )


def held_out_words(validation: dict) -> str:
    """How a compensation's candidates were held out, in words: the maneuver folds, another flight, or nothing."""
    if validation.get("scheme") == "maneuvers":
        return f"{validation.get('n_maneuvers', 0)} maneuvers in {validation.get('folds', FOLDS)} folds, each held out of its fit"
    if validation.get("scheme") == "flight":
        return "the other flight's maneuvers, compensated by the fit of this one"
    return "nothing held out"


def diagnosis_table(diagnosis, figure: str, header: str) -> str:
    """A compensation diagnosis's text (the scalar's or the cross's): its verdict, summary, held-out ``figure``
    line, model, the candidates under ``header`` and the warnings."""
    lines = [f"verdict: {diagnosis.verdict}", f"  {diagnosis.summary}", figure]
    if diagnosis.effects:
        lines.append(f"model effects: {', '.join(diagnosis.effects)}")
    lines += ["", header] + [c.text() for c in diagnosis.candidates]
    if diagnosis.warnings:
        lines += [""] + [f"warning: {w}" for w in diagnosis.warnings]
    return "\n".join(lines)


def diagnosis_document(diagnosis, figures: dict) -> dict:
    """A compensation diagnosis's JSON document: the keys every one has, and its held-out ``figures``."""
    return jsonable(
        {
            "mode": diagnosis.mode,
            "verdict": diagnosis.verdict,
            "summary": diagnosis.summary,
            "effects": list(diagnosis.effects),
            "explained_by": list(diagnosis.explained_by),
            "candidates": [c.to_dict() for c in diagnosis.candidates],
            **figures,
            "noise_nT": diagnosis.noise_nT,
            "validation": dict(diagnosis.validation),
            "warnings": list(diagnosis.warnings),
            "elapsed_s": round(float(diagnosis.elapsed_s), 3),
        }
    )


@dataclass
class CompensationDiagnosis:
    """What :func:`diagnose_compensation` found.

    Attributes
    ----------
    verdict : str
        One of :data:`VERDICTS`.
    summary : str
    effects : list of str
        The terms already in the diagnosed model.
    candidates : list of CompensationCandidate
        Every round's, in order.
    explained_by : list of str
        The advice: ``magcal calibrate --mode compensation --effects ...``.
    fom_held_out_nT : float
        The diagnosed model's held-out FOM.
    fom_final_nT : float or None
        With ``explained_by`` added.
    floor_fom_nT : float
        The FOM the scalar's white noise alone leaves in the judged maneuvers.
    noise_nT : float
        The scalar's white noise (nT, 1 sigma).
    validation : dict
        ``scheme`` (``maneuvers`` or ``flight``), ``folds``, ``n_maneuvers``.
    warnings : list of str
    notes : list of Note
    result : Compensation
        The diagnosed model fitted on the whole record.
    elapsed_s : float
    current_columns : list of str
        The current columns the current term takes (those whose field the held-out FOM showed), when it is in the
        model or the advice.
    """

    verdict: str
    summary: str
    effects: list
    candidates: list
    explained_by: list
    fom_held_out_nT: float
    fom_final_nT: float | None
    floor_fom_nT: float
    noise_nT: float
    validation: dict
    warnings: list = field(default_factory=list)
    notes: list = field(default_factory=list)
    result: Compensation | None = field(repr=False, default=None)
    elapsed_s: float = 0.0
    current_columns: list = field(default_factory=list)

    mode = "compensation"
    unit: ClassVar[str] = "nT"

    @property
    def fom_held_out(self) -> float:
        """:attr:`fom_held_out_nT` (nT; :class:`magcal.diagnosis.fom_protocol.DiagnosisFOM`)."""
        return self.fom_held_out_nT

    @property
    def fom_final(self) -> float | None:
        """:attr:`fom_final_nT` (nT)."""
        return self.fom_final_nT

    @property
    def floor_fom(self) -> float:
        """:attr:`floor_fom_nT` (nT)."""
        return self.floor_fom_nT

    @property
    def partially_explained_by(self) -> list:
        return []

    def to_dict(self) -> dict:
        """The JSON document of ``magcal diagnose --mode compensation --json``."""
        figures = {
            "fom_held_out_nT": self.fom_held_out_nT,
            "fom_final_nT": self.fom_final_nT,
            "floor_fom_nT": self.floor_fom_nT,
            "current_columns": list(self.current_columns),
        }
        return diagnosis_document(self, figures)

    def table(self) -> str:
        """The verdict, the summary and the candidates, one line each."""
        figure = (
            f"held-out FOM {self.fom_held_out_nT:.3f} nT ({held_out_words(self.validation)}); the scalar's noise "
            f"{self.noise_nT:.3g} nT leaves {self.floor_fom_nT:.3f} nT"
        )
        header = f"  {'candidate':<22} {'held-out FOM before -> after':>30}  {'advice':<11}  evidence"
        return diagnosis_table(self, figure, header)

    def text(self) -> str:
        return self.table() + "\n"


def _fold_masks(n: int, maneuvers, folds: int, guard: int):
    for k in range(folds):
        held = [m for i, m in enumerate(maneuvers) if i % folds == k]
        mask = np.ones(n, dtype=bool)
        for m in held:
            mask[max(0, m.start - guard) : m.stop + guard] = False
        yield held, mask


def held_out_fom(
    record: CompensationRecord, effects=(), maneuvers=None, *, also=None, also_maneuvers=None, folds=FOLDS, **options
) -> float:
    """The held-out FOM (nT) of a compensation with ``effects``: on ``also`` (another flight, in its
    ``also_maneuvers``) fitted on the whole record, else summed over the folds of ``maneuvers`` each left out of
    its fit (module docstring). ``options`` go to :func:`magcal.fitting.compensation.fit_compensation`."""
    rate = record.sample_rate_hz
    if also is not None:
        comp = fit_compensation(record, effects, **options)
        return figure_of_merit(comp.compensate(also), also_maneuvers, also.sample_rate_hz).fom_nT
    guard = int(round(GUARD_S * rate))
    total = 0.0
    for held, mask in _fold_masks(record.n_samples, maneuvers, folds, guard):
        comp = fit_compensation(record, effects, mask=mask, **options)
        total += figure_of_merit(comp.compensate(record), held, rate).fom_nT
    return float(total)


def noise_sigma_nT(compensated_nT) -> float:
    """The white noise (nT, 1 sigma) of a compensated scalar, from its second differences (robust)."""
    d2 = np.diff(np.asarray(compensated_nT, float), 2)
    return float(robust_sigma(d2) / np.sqrt(6.0))


def noise_floor_fom(sigma_nT: float, maneuvers, n: int, sample_rate_hz: float, draws: int = 8) -> float:
    """The mean FOM (nT) that white noise of ``sigma_nT`` alone leaves in ``maneuvers`` (``draws`` draws)."""
    rng = np.random.default_rng(12345)
    values = [
        figure_of_merit(rng.normal(0.0, sigma_nT, n), maneuvers, sample_rate_hz).fom_nT for _ in range(int(draws))
    ]
    return float(np.mean(values))


def _unusable(name: str, record: CompensationRecord, column: str | None = None) -> str:
    """Why the record cannot judge a candidate ('' when it can): the current's ``column`` of it."""
    if name == "current":
        every = record.all_currents
        if not every:
            return "the record has no current_A or throttle column"
        if column is not None and column not in every:
            return f"the record has no {column} column"
        if column is not None and np.ptp(every[column]) == 0:
            return f"its {column} column does not change"
    if name == "temperature":
        if record.temperature_C is None:
            return "the record has no temperature (temp column)"
        if np.ptp(record.temperature_C) < 0.1:
            return "its temperature changes by less than 0.1 degC"
    return ""


def _evidence(name: str, comp: Compensation, record: CompensationRecord, options: dict) -> str:
    """What the fit on the whole record with the candidate found, in words."""
    labels = comp.extra_labels
    values = dict(zip(labels, comp.extra_coefficients))
    if name == "current":
        parts = []
        for column, labels in _current_blocks(comp):
            k = [values[label] for label in labels]
            unit = "unit of throttle" if column == "throttle" else "A"
            named = f" of {column}" if len(comp.current_columns) > 1 else ""
            parts.append(f"({k[0]:+.3g}, {k[1]:+.3g}, {k[2]:+.3g}) nT per {unit}{named}")
        return "a field of " + "; ".join(parts) + " in the fluxgate's axes"
    if name == "time_offset":
        late = "late" if comp.time_offset_s >= 0 else "early"
        return f"the fluxgate {abs(comp.time_offset_s) * 1e3:.0f} ms {late} against the scalar"
    if name == "fluxgate_calibration":
        rate = record.sample_rate_hz
        swing = np.ptp(bandpass(np.linalg.norm(record.flux_nT, axis=1), rate, comp.tl.passband_hz)[20:-20])
        b = comp.fluxgate_bias_nT
        m = comp.fluxgate_matrix
        scale = np.linalg.svd(m, compute_uv=False)
        return (
            f"the fluxgate's band-passed magnitude swings {swing:.1f} nT where the Earth field's does not; fitted "
            f"bias ({b[0]:.0f}, {b[1]:.0f}, {b[2]:.0f}) nT, scale spread {100 * (scale.max() / scale.min() - 1):.2f} %"
        )
    if name == "heading":
        a1 = np.hypot(values["heading_cos"], values["heading_sin"])
        a2 = np.hypot(values["heading_cos2"], values["heading_sin2"])
        return f"{a1:.3g} nT once and {a2:.3g} nT twice per turn of the heading"
    if name == "temperature":
        k = [values[f"temperature_{a}"] for a in "xyz"]
        return f"a field of ({k[0]:+.3g}, {k[1]:+.3g}, {k[2]:+.3g}) nT per degC"
    return ""


def _current_blocks(comp: Compensation):
    """(column, its three labels) of a compensation's current term."""
    columns = comp.current_columns or (comp.current_column or "current",)
    labels = [label for label in comp.extra_labels if label.startswith("current_")]
    return [(c, labels[3 * i : 3 * i + 3]) for i, c in enumerate(columns)]


def _maneuvers(record: CompensationRecord):
    return find_maneuvers(record.sample_rate_hz, attitude_deg=record.attitude_deg, flux_nT=record.flux_nT)


def diagnose_compensation(
    record: CompensationRecord,
    effects=(),
    *,
    also: CompensationRecord | None = None,
    candidates=None,
    maneuvers=None,
    **options,
) -> CompensationDiagnosis:
    """Judge the terms beyond Tolles-Lawson on held-out maneuvers (or on ``also``, another flight of the same
    platform) and name those the platform has.

    Parameters
    ----------
    record : CompensationRecord
        The compensation flight.
    effects : sequence of str
        Terms already in the model (:data:`magcal.fitting.compensation.COMPENSATION_EFFECTS`).
    also : CompensationRecord, optional
        Another flight: candidates are judged on its FOM instead of held-out maneuvers.
    candidates : sequence of str, optional
        The candidates to try (default :data:`CANDIDATES`, less those in ``effects``).
    maneuvers : list of Maneuver, optional
        The record's maneuvers (found from the attitude or the fluxgate when not given).
    options
        For :func:`magcal.fitting.compensation.fit_compensation` (``terms``, ``ridge``, ``passband_hz``...).

    Returns
    -------
    CompensationDiagnosis
    """
    started = _time.perf_counter()
    effects = list(check_effects(effects))
    pool = [c for c in check_effects(candidates if candidates is not None else CANDIDATES) if c not in effects]
    maneuvers = _maneuvers(record) if maneuvers is None else list(maneuvers)
    judge = _Judge(record, also, maneuvers, options)
    columns = list(record.term_currents) if "current" in effects else []
    base = fit_compensation(record, effects, **options)
    judge.set_floor(base)
    if not judge.can_judge():
        cands = [CompensationCandidate(name, judged=False, reason="nothing to judge on") for name in pool]
        return CompensationDiagnosis(
            "not_judged", judge.not_judged_summary(), effects, cands, [], float("nan"), None, judge.floor,
            judge.sigma, judge.validation("none"), [], [], base, _time.perf_counter() - started, columns,
        )  # fmt: skip
    judged, open_names, open_columns = judge.usable(pool, effects, columns)
    initial_columns = list(columns)
    current = list(effects)
    base_fom = current_fom = judge.score(current, columns)
    for round_ in range(1, MAX_EFFECTS + MAX_CURRENT_COLUMNS):
        added = len(current) - len(effects)
        names = [n for n in open_names if added < MAX_EFFECTS and n not in current]
        more = open_columns if len(columns) < MAX_CURRENT_COLUMNS else []
        trials = [judge.trial(current, columns, name, current_fom, round_) for name in names if name != "current"]
        if "current" in current or "current" in names:
            trials += [judge.trial(current, columns, "current", current_fom, round_, (c,)) for c in more]
        trials.sort(key=_after)
        judged.extend(trials)
        if not trials or trials[0].gain < MIN_GAIN:
            break
        best = trials[0]
        best.recommended = True
        if best.name not in current:
            current.append(best.name)
        columns += list(best.columns)
        open_columns = [c for c in open_columns if c not in columns]
        current_fom = best.fom_after_nT
        open_names = [n for n in open_names if n not in current or (n == "current" and open_columns)]
        judge.set_floor(fit_compensation(judge.taking(record, columns), current, **options))
        if not (open_names or open_columns) or current_fom <= ADEQUATE_RATIO * judge.floor:
            break
    explained = current[len(effects) :]
    grew = columns[len(initial_columns) :]
    advice = columns if "current" in current and len(record.all_currents) > 1 else []
    verdict, summary = _verdict(explained, base_fom, current_fom, judge.floor, judge.scheme, effects, advice, grew)
    changed = bool(explained or grew)
    warnings = []
    if changed and current_fom > ADEQUATE_RATIO * judge.floor:
        named = ", ".join(explained) if explained else "the current's " + ", ".join(grew)
        warnings.append(
            f"with {named} the held-out FOM is {current_fom:.3f} nT, still "
            f"{current_fom / judge.floor:.1f}x what the scalar's noise leaves: the platform has more than the "
            "candidates follow"
        )
    return CompensationDiagnosis(
        verdict, summary, effects, judged, explained, base_fom, current_fom if changed else None, judge.floor,
        judge.sigma, judge.validation(judge.scheme), warnings, [], base, _time.perf_counter() - started,
        columns if "current" in current else [],
    )  # fmt: skip


def _after(candidate: CompensationCandidate) -> float:
    return candidate.fom_after_nT


class _Judge:
    """What the rounds of :func:`diagnose_compensation` share: the record, the other flight, the maneuvers, the
    floor."""

    def __init__(self, record, also, maneuvers, options):
        self.record, self.also, self.maneuvers, self.options = record, also, maneuvers, options
        self.also_maneuvers = _maneuvers(also) if also is not None else None
        self.judge_on = also if also is not None else record
        self.judged_maneuvers = self.also_maneuvers if also is not None else maneuvers
        self.scheme = "flight" if also is not None else "maneuvers"
        self.sigma, self.floor = float("nan"), float("nan")

    @staticmethod
    def taking(record, columns):
        """``record`` whose current term takes ``columns`` (as it is without any)."""
        return record.taking_currents(columns) if columns and record is not None else record

    def set_floor(self, comp: Compensation) -> None:
        """The noise and the floor from a fit's compensation of the flight judged on."""
        on = self.taking(self.judge_on, comp.current_columns if "current" in comp.effects else ())
        self.sigma = noise_sigma_nT(comp.compensate(on))
        if self.judged_maneuvers:
            self.floor = noise_floor_fom(self.sigma, self.judged_maneuvers, on.n_samples, on.sample_rate_hz)

    def can_judge(self) -> bool:
        if self.also is not None:
            return bool(self.also_maneuvers)
        return len(self.maneuvers) >= FOLDS

    def not_judged_summary(self) -> str:
        where = "the other flight" if self.also is not None else "the record"
        return (
            f"not judged: {where} holds {len(self.judged_maneuvers or [])} maneuvers, too few to hold any out; fly "
            "a full box (4 headings, a roll, a pitch and a yaw on each) or give another flight (--also)"
        )

    def validation(self, scheme: str) -> dict:
        return {"scheme": scheme, "folds": FOLDS, "n_maneuvers": len(self.judged_maneuvers or [])}

    def unusable(self, name: str, column: str | None = None) -> str:
        also = _unusable(name, self.also, column) if self.also is not None else ""
        return _unusable(name, self.record, column) or also

    def usable(self, pool, effects, columns) -> tuple[list, list, list]:
        """(the candidates not judged, with why; the names to try; the current columns to try): each current column
        is a candidate of its own (the term takes those whose field shows), one not judged when it does not change."""
        judged = [CompensationCandidate(n, judged=False, reason=r) for n in pool if (r := self.unusable(n))]
        names = [n for n in pool if not self.unusable(n)]
        wants = "current" in names or "current" in effects
        every = [c for c in self.record.all_currents if c not in columns] if wants else []
        judged += [
            CompensationCandidate("current", judged=False, reason=r, columns=(c,))
            for c in every
            if (r := self.unusable("current", c))
        ]
        return judged, names, [c for c in every if not self.unusable("current", c)]

    def score(self, names, columns) -> float:
        columns = columns if "current" in names else []
        return held_out_fom(
            self.taking(self.record, columns),
            names,
            self.maneuvers,
            also=self.taking(self.also, columns),
            also_maneuvers=self.also_maneuvers,
            **self.options,
        )

    def trial(self, current, columns, name, current_fom, round_, added=()) -> CompensationCandidate:
        names = current + [name] if name not in current else list(current)
        with_columns = list(columns) + list(added)
        fom = self.score(names, with_columns)
        fit = fit_compensation(
            self.taking(self.record, with_columns if "current" in names else []), names, **self.options
        )
        evidence = _evidence(name, fit, self.record, self.options)
        return CompensationCandidate(name, round_, True, current_fom, fom, False, evidence, columns=tuple(added))


def _verdict(explained, base_fom, final_fom, floor, scheme, effects, columns=(), grew=()) -> tuple[str, str]:
    on = "on held-out maneuvers" if scheme == "maneuvers" else "on the other flight"
    model = "Tolles-Lawson" + (" with " + ", ".join(effects) if effects else "")
    if explained or grew:
        added = list(explained) + ([f"the current's {', '.join(grew)}"] if "current" not in explained and grew else [])
        return "missing_effect", (
            f"{model} leaves a held-out FOM of {base_fom:.3f} nT {on}; adding {', '.join(added)} brings it to "
            f"{final_fom:.3f} nT (the noise's {floor:.3f} nT): magcal calibrate --mode compensation --effects "
            + ",".join(list(effects) + list(explained))
            + (f" --current {','.join(columns)}" if columns else "")
        )
    if base_fom <= ADEQUATE_RATIO * floor:
        return "adequate", (
            f"{model} leaves a held-out FOM of {base_fom:.3f} nT {on}, within {ADEQUATE_RATIO}x of what the "
            f"scalar's noise leaves ({floor:.3f} nT); no candidate lowers it by {100 * MIN_GAIN:.0f} %"
        )
    return "unexplained", (
        f"{model} leaves a held-out FOM of {base_fom:.3f} nT {on}, {base_fom / floor:.1f}x what the scalar's noise "
        f"leaves ({floor:.3f} nT), and no candidate lowers it by {100 * MIN_GAIN:.0f} %: the platform has a term "
        "none of them follows"
    )


def check_record(record) -> CompensationRecord:
    """``record`` if it is a :class:`CompensationRecord` (a :class:`MagcalError` otherwise)."""
    if not isinstance(record, CompensationRecord):
        raise MagcalError("give a CompensationRecord (magcal.fitting.compensation.compensation_record)")
    return record


def compensation_result(record: CompensationRecord, effects=(), *, source: str = "", **options):
    """Fit a compensation (:func:`magcal.fitting.compensation.fit_compensation` with ``options``) and judge it by
    the FOM in the record's maneuvers: a :class:`magcal.fitting.compensation.CompensationResult` with its
    :class:`magcal.diagnosis.fom.FOMReport` (None, with a note, when no maneuver is found)."""
    comp = fit_compensation(record, effects, **options)
    notes = []
    fom = None
    try:
        fom = fom_report(
            record.scalar_nT,
            comp.tl.compensated_nT,
            record.sample_rate_hz,
            attitude_deg=record.attitude_deg,
            flux_nT=record.flux_nT,
            passband_hz=comp.tl.passband_hz,
        )
    except MagcalError as exc:
        notes.append(Note(f"no FOM: {exc}", UserWarning, "compensation"))
    if fom is not None:
        comp.fitted["fom_nT"] = float(fom.after.fom_nT)
        comp.fitted["fom_before_nT"] = float(fom.before.fom_nT)
        comp.fitted["improvement_ratio"] = float(fom.improvement_ratio)
    return CompensationResult(comp, record, fom, notes, source or record.source)


@dataclass
class CompensationValidation:
    """A compensation judged on held-out maneuvers: the held-out FOM of TL alone and with the effects.

    Attributes
    ----------
    effects : list of str
    fom_tl_nT, fom_effects_nT : float
        Held-out FOM (:func:`held_out_fom`) of TL alone and with the effects (nT).
    floor_fom_nT : float
        What the scalar's noise leaves in the maneuvers.
    n_maneuvers : int
    """

    effects: list
    fom_tl_nT: float
    fom_effects_nT: float
    floor_fom_nT: float
    n_maneuvers: int

    def to_dict(self) -> dict:
        return jsonable(
            {
                "scheme": "maneuvers",
                "folds": FOLDS,
                "n_maneuvers": self.n_maneuvers,
                "effects": list(self.effects),
                "held_out_fom_tl_nT": self.fom_tl_nT,
                "held_out_fom_nT": self.fom_effects_nT,
                "floor_fom_nT": self.floor_fom_nT,
            }
        )

    def text(self) -> str:
        return (
            f"\nHeld-out FOM ({self.n_maneuvers} maneuvers in {FOLDS} folds, each held out of its fit): TL alone "
            f"{self.fom_tl_nT:.3f} nT, with {', '.join(self.effects)} {self.fom_effects_nT:.3f} nT; the scalar's "
            f"noise leaves {self.floor_fom_nT:.3f} nT\n"
        )


def validate_compensation(record: CompensationRecord, effects=(), maneuvers=None, **options):
    """:class:`CompensationValidation` of a compensation with ``effects``; None without effects or with fewer
    maneuvers than folds."""
    effects = list(check_effects(effects))
    maneuvers = _maneuvers(record) if maneuvers is None else list(maneuvers)
    if not effects or len(maneuvers) < FOLDS:
        return None
    with_effects = held_out_fom(record, effects, maneuvers, **options)
    tl = held_out_fom(record, (), maneuvers, **options)
    sigma = noise_sigma_nT(fit_compensation(record, effects, **options).compensate(record))
    floor = noise_floor_fom(sigma, maneuvers, record.n_samples, record.sample_rate_hz)
    return CompensationValidation(effects, tl, with_effects, floor, len(maneuvers))
