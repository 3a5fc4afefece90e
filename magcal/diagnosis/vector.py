"""The diagnosis of a vector calibration: where the model of a mounted magnetometer fails, and which effect is missing.

A magnetometer on a drone, an aircraft, a car or a ship cannot tumble, but its attitude and the Earth's field
vector are known (:mod:`magcal.fitting.vector`). Its residuals are then vectors in the world frame (north, east,
down) and the total field ``|B| - F``, and the interference a vehicle carries shows in them: a motor's current, the
eddy currents of turns, a time offset between the attitude and the magnetometer, the temperature, a bias step.
:func:`diagnose_vector` closes the loop on such a record:

1. **Base model.** The vector fit of the base terms (bias, ``C^-1``, mounting) plus the effects asked for.
2. **Candidates.** Every catalogue effect the vector fit can take (stage ``raw``, ``"vector"`` in
   :attr:`~magcal.model.terms.Effect.modes`) whose channels the record has: the ``current_field``, ``eddy_currents``
   and ``attitude_time_offset`` of the platform, temperature, drift, steps, nonlinearity, hysteresis, periodic
   interference and a user's own effects, one per sensor. Each is refitted with the base model and scored by the
   change of the Bayesian information criterion of the vector likelihood: per sensor
   ``n [ln sigma_F^2 + 2 ln sigma_perp^2]`` at the fitted noises (the total-field residual and the two components
   perpendicular to the field, each at its own noise, as the fit weighs them), plus ``q ln(3 n)``.
3. **Judged as it will be used.** A candidate supported in-sample (delta-BIC below
   :data:`DELTA_BIC_THRESHOLD`) is fitted again on the earlier part of the record and applied to its later part as
   ``magcal apply`` applies it (record-only terms dropped, the level they keep folded into the bias), beside the base
   model fitted the same way; with other flights of the same vehicle (``also``), both calibrations of the whole
   record are applied to each of them. The score is the residual's weighted RMS (the total field over ``sigma_F``,
   the perpendicular components over ``sigma_perp``, the white noise of the diagnosed fit's residuals: 1 at the
   noise): a candidate is recommended only if it lowers it by :data:`MIN_GAIN` or more, and by more than chance
   (the gains of ten stretches, a signed-rank test below :data:`GAIN_P`: :func:`significant_gain`), on the later
   part and on every other flight.
   An effect that describes the record (a bias step, an interference) but does not improve the later part or the
   other flights is reported in ``record_holds``, with what to do when recording.
4. **Forward selection.** The best recommended candidate joins the model and the candidates are tried again, up
   to ``max_effects``.
5. **What is left.** The final residuals (world components and ``|B|``) are regressed on what a vehicle's
   interference follows: the turn rate, the heading, the tilt, the current or throttle, the temperature, the time.
   What explains a significant part of them is named (:class:`LeftStructure`), so a structure outside the
   catalogue still says what it follows.

The verdict: ``missing_effect`` (effects recommended), ``adequate`` (nothing recommended and the residuals at
their noise: weighted RMS within :data:`ADEQUATE_RATIO` of 1 after the white noise of the record's own differences)
or ``unexplained`` (structure that no candidate removes, or a base fit that the record does not determine).
"""

from __future__ import annotations

import time as _time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import stats

from magcal.core.errors import CalibrationError, MagcalError
from magcal.core.jsonable import jsonable
from magcal.core.notes import Note
from magcal.core.stats import robust_sigma
from magcal.data.attitude import attitude_rows, turn_rate_dps
from magcal.diagnosis.uniformity import field_uniformity
from magcal.fitting.vector import VectorFitResult, fit_vector
from magcal.model.effects import CURRENT_COLUMNS, current_column
from magcal.model.terms import EFFECTS, EffectTexts, Model, term_label

#: A candidate is supported in-sample when its delta-BIC is below this (very strong evidence), as in scalar mode.
DELTA_BIC_THRESHOLD = -10.0

#: Least relative fall of the weighted held-out RMS for a candidate to be recommended ...
MIN_GAIN = 0.01

#: ... and by more than chance: the one-sided p-value of the gains of stretches of the held-out samples
#: (:func:`significant_gain`).
GAIN_P = 0.02

#: The contiguous stretches the held-out gain is judged over.
GAIN_BLOCKS = 10

#: The later part of a record that the earlier part's fits are judged on.
LATER_FRACTION = 0.3

#: The residuals are at their noise when their weighted RMS is within this factor of the white noise's.
ADEQUATE_RATIO = 1.25

#: A structure left is named when it explains at least this share of a residual's variance (and is significant).
STRUCTURE_MIN_SHARE = 0.05

#: ... and its F-test's p-value is below this.
STRUCTURE_P = 1e-6

#: Verdicts (the same as the scalar diagnosis's).
VERDICTS = ("adequate", "missing_effect", "unexplained")

#: Fewest fitted samples in the later part (and in the earlier one) for the held-out judgement.
MIN_LATER_SAMPLES = 60

#: The supported candidates of a round judged held out (best delta-BIC first).
JUDGE_TOP = 4

#: A longer record's candidates are fitted and judged on every k-th sample, k the smallest that leaves at most this
#: many (the rate and step bases are taken from the whole record, so the subsample's fits are exact); the advice
#: is then fitted on every sample.
MAX_SAMPLES = 8000


@dataclass
class Flight:
    """A record of the same vehicle the candidates are judged on (``also``).

    Attributes
    ----------
    dataset : Dataset
    reference : VectorReference
        Its field vector (nT, NED).
    name : str
        For reports (a file name).
    """

    dataset: object
    reference: object
    name: str = "another flight"


@dataclass
class Scores:
    """Residual figures of one calibration on some samples (nT; ``weighted``: 1 at the noise)."""

    world_nT: float
    total_nT: float
    weighted: float
    n: int
    #: Per scored sample, the squared weighted residual averaged over the sensors and components (its mean is
    #: ``weighted ** 2``): what the significance of a gain is computed from.
    per_sample: np.ndarray | None = field(default=None, repr=False, compare=False)

    def to_dict(self) -> dict:
        return {
            "world_rms_nT": self.world_nT,
            "total_rms_nT": self.total_nT,
            "weighted_rms": self.weighted,
            "n": self.n,
        }


@dataclass
class VectorCandidate:
    """One candidate effect on one sensor and the evidence for it.

    Attributes
    ----------
    effect : str
        Catalogue name.
    sensor : int or None
        0-based sensor, None for every sensor of a one-sensor record.
    label : str
        ``name`` or ``name:S`` (S 1-based).
    n_params : int
    delta_bic : float
        Of the vector likelihood (module docstring), refit against the base model.
    in_sample : tuple of Scores
        The base model's and the candidate's figures on the fitted samples.
    later : tuple of Scores or None
        Fitted on the earlier part, applied to the later part as ``magcal apply`` applies them.
    flights : list of (str, Scores, Scores)
        Per other flight: its name and the base's and the candidate's figures (each fitted on the whole record).
    record_only : bool
        The effect describes the record, not the instrument (dropped on new data).
    recommended : bool
        Supported, improves the later part and every other flight.
    why : str
        Why it is or is not recommended, in words.
    params : dict
        The fitted parameters by block label.
    quote : str
        What they do, in words.
    evidence : str
        One line.
    when_recording : str
        What to do about it when recording (effects that describe the record only).
    """

    effect: str
    sensor: int | None
    label: str
    n_params: int
    delta_bic: float
    in_sample: tuple
    later: tuple | None = None
    flights: list = field(default_factory=list)
    record_only: bool = False
    recommended: bool = False
    why: str = ""
    params: dict = field(default_factory=dict)
    quote: str = ""
    evidence: str = ""
    when_recording: str = ""
    holds: bool | None = None
    round: int = 1
    replaces: list = field(default_factory=list)

    @property
    def supported(self) -> bool:
        return bool(self.delta_bic < DELTA_BIC_THRESHOLD)

    def to_dict(self) -> dict:
        return {
            "effect": self.effect,
            "sensor": None if self.sensor is None else self.sensor + 1,
            "label": self.label,
            "n_params": self.n_params,
            "delta_bic": float(self.delta_bic),
            "in_sample_before": self.in_sample[0].to_dict(),
            "in_sample_after": self.in_sample[1].to_dict(),
            "later_before": None if self.later is None else self.later[0].to_dict(),
            "later_after": None if self.later is None else self.later[1].to_dict(),
            "flights": [{"name": n, "before": b.to_dict(), "after": a.to_dict()} for n, b, a in self.flights],
            "record_only": self.record_only,
            "round": self.round,
            "replaces": list(self.replaces),
            "holds": self.holds,
            "supported": self.supported,
            "recommended": self.recommended,
            "why": self.why,
            "params": {k: np.asarray(v, dtype=float).tolist() for k, v in self.params.items()},
            "quote": self.quote,
            "evidence": self.evidence,
        }


#: What a residual that follows a channel may mean, when no catalogue effect removes it.
_FOLLOWS_HINTS = {
    "heading": "soft iron the model lacks, a yaw estimated from this very compass (its own calibration's error), "
    "or a declination set wrong",
    "turn rate": "a delay or eddy currents beyond the catalogue's (per axis, filtered), or an attitude that lags in "
    "turns",
    "tilt": "an attitude error that grows with tilt, or a field the vehicle's own iron bends as it tilts",
    "current": "a current field the linear term does not capture (per motor, saturating, delayed)",
    "temperature": "a temperature effect beyond a bias and a scale (delayed, per axis)",
    "time": "a drift or a changing field (the daily variation, a base station would show it), or a wandering "
    "attitude error",
}


@dataclass
class LeftStructure:
    """A significant structure in the residuals and what it follows.

    Attributes
    ----------
    sensor : int
        0-based.
    follows : str
        The channel: ``turn rate``, ``heading``, ``tilt``, ``current_A``/``throttle``, ``temperature``, ``time``.
    residual : str
        Which residual: ``north``, ``east``, ``down`` or ``|B|``.
    explained_nT : float
        RMS of the part it explains, nT.
    share : float
        Share of that residual's variance.
    p_value : float
        F-test of the regression.
    """

    sensor: int
    follows: str
    residual: str
    explained_nT: float
    share: float
    p_value: float

    def text(self) -> str:
        hint = _FOLLOWS_HINTS.get(self.follows, _FOLLOWS_HINTS["current"] if self.follows in CURRENT_COLUMNS else "")
        return (
            f"sensor {self.sensor + 1}: the {self.residual} residual follows the {self.follows} "
            f"({self.explained_nT:.3g} nT RMS, {100 * self.share:.0f} % of its variance)"
            + (f": {hint}" if hint else "")
        )

    def to_dict(self) -> dict:
        return {
            "sensor": self.sensor + 1,
            "follows": self.follows,
            "residual": self.residual,
            "explained_nT": float(self.explained_nT),
            "share": float(self.share),
            "p_value": float(self.p_value),
        }


@dataclass
class VectorDiagnosis:
    """What :func:`diagnose_vector` found.

    Attributes
    ----------
    verdict : str
        ``adequate``, ``missing_effect`` or ``unexplained``.
    summary : str
    effects : list of str
        Effects already in the diagnosed model.
    reference_text : str
        Where the field vector came from.
    base : Scores
        The diagnosed model's figures on its fitted samples.
    noise : dict
        ``total_nT`` and ``perpendicular_nT``: the white noise of the residuals (their differences in time), per
        sensor; ``weighted``: the weighted RMS that noise alone gives; ``attitude_deg``: the attitude error it implies.
    candidates : list of VectorCandidate
        Best (lowest delta-BIC) first, every round's.
    explained_by : list of str
        The advice: labels to fit (``magcal calibrate --mode vector --effects ...``).
    record_holds : list of str
        Effects that describe this record only (the summary says what to do when recording).
    final : Scores or None
        The figures with ``explained_by`` added.
    left : list of LeftStructure
        Structure left in the final residuals, named by what it follows.
    warnings : list of str
    notes : list of Note
        What the fits said.
    validation : dict
        How the candidates were judged: ``later_fraction``, ``n_later``, ``flights``.
    evidence : dict
        Plot data (plain arrays): ``time_s``, per sensor ``world_residual_nT`` (N, 3; NaN where not fitted),
        ``total_residual_nT`` (N,), and the channels (``current``, ``temperature_C``, ``turn_rate_dps``).
    result : VectorFitResult
        The base fit.
    fits : dict of str to VectorFitResult
        The refits by label (and ``"+".join(explained_by)`` for the final model).
    elapsed_s : float
    """

    verdict: str
    summary: str
    effects: list
    reference_text: str
    base: Scores
    noise: dict
    candidates: list
    explained_by: list
    record_holds: list
    final: Scores | None
    left: list
    warnings: list
    notes: list
    validation: dict
    evidence: dict = field(repr=False, default_factory=dict)
    result: VectorFitResult | None = field(repr=False, default=None)
    fits: dict = field(repr=False, default_factory=dict)
    elapsed_s: float = 0.0
    mode: str = "vector"

    @property
    def best(self) -> VectorCandidate | None:
        return self.candidates[0] if self.candidates else None

    def where_text(self) -> str:
        return f"{self.elapsed_s:.1f} s"

    def plot_data(self) -> dict:
        return jsonable(self.evidence)

    def to_dict(self) -> dict:
        return {
            "mode": "vector",
            "verdict": self.verdict,
            "summary": self.summary,
            "effects": list(self.effects),
            "reference": self.reference_text,
            "rms_world_nT": self.base.world_nT,
            "rms_total_field_nT": self.base.total_nT,
            "weighted_rms": self.base.weighted,
            "noise": jsonable(self.noise),
            "candidates": [c.to_dict() for c in self.candidates],
            "explained_by": list(self.explained_by),
            "record_holds": list(self.record_holds),
            "after": None if self.final is None else self.final.to_dict(),
            "remaining_structure": [s.to_dict() for s in self.left],
            "warnings": list(self.warnings),
            "validation": jsonable(self.validation),
            "elapsed_s": round(float(self.elapsed_s), 3),
        }

    def table(self, limit=12) -> str:
        """The header, the verdict and a ranked table of the candidates, round by round."""
        v = self.validation
        floor = self.noise.get("world_floor_nT", float("nan"))
        lines = [
            f"verdict: {self.verdict}",
            f"  {self.summary}",
            "mode: vector (the fit with attitude and the field vector); candidates judged on the world "
            "north/east/down residuals and |B|, each at its own noise",
            f"reference field vector: {self.reference_text}",
            f"world components RMS {self.base.world_nT:.4g} nT (noise floor {floor:.3g} nT: attitude error "
            f"{self.noise.get('attitude_deg', float('nan')):.3g} deg), |B| RMS {self.base.total_nT:.4g} nT (noise "
            f"{float(np.sqrt(np.mean(np.square(self.noise.get('total_nT', [np.nan]))))):.3g} nT); normalized RMS "
            f"{self.base.weighted:.3g} (1 is the noise)",
        ]
        if v.get("n_later"):
            lines.append(
                f"held out: fitted on the first {100 * (1 - v['later_fraction']):.0f} %, applied to the last "
                f"{v['n_later']} samples as magcal apply does"
                + (f"; other flights: {', '.join(v['flights'])}" if v.get("flights") else "")
            )
        elif v.get("skipped"):
            lines.append(f"held-out judgement skipped: {v['skipped']}")
        if v.get("subsample"):
            lines.append(
                f"candidates fitted and judged on every k-th sample ({v['subsample']['samples']} of "
                f"{v['subsample']['of']}); the advice fitted on all"
            )
        if self.effects:
            lines.append(f"model effects: {', '.join(self.effects)}")
        flights = bool(v.get("flights"))
        head = (
            f"{'rank':>4}  {'effect':<24} {'dBIC':>10} {'world in-sample':>17} {'world later':>17} {'norm. later':>13}"
        )
        if flights:
            head += f" {'norm. flights':>16}"
        rounds = sorted({c.round for c in self.candidates})
        added: list[str] = []
        for r in rounds:
            cands = [c for c in self.candidates if c.round == r]
            lines.append("")
            lines.append(
                "candidates for the diagnosed model:"
                if r == 1
                else f"round {r}: candidates after adding {', '.join(added)}:"
            )
            lines.append(head + "  advice")
            shown = cands[:limit] if r == 1 else [c for c in cands if c.supported][:limit] or cands[:3]
            for i, c in enumerate(shown, 1):
                later = "-" if c.later is None else _pair(c.later[0].world_nT, c.later[1].world_nT)
                nlater = "-" if c.later is None else _pair(c.later[0].weighted, c.later[1].weighted, "{:.3g}")
                row = (
                    f"{i:>4}  {c.label:<24} {c.delta_bic:>10.1f} "
                    f"{_pair(c.in_sample[0].world_nT, c.in_sample[1].world_nT):>17} {later:>17} {nlater:>13}"
                )
                if flights:
                    fl = "; ".join(_pair(b.weighted, a.weighted, "{:.3g}") for _, b, a in c.flights) or "-"
                    row += f" {fl:>16}"
                advice = ("RECOMMENDED" + (f"; {c.why}" if c.why else "")) if c.recommended else c.why
                lines.append(row + f"  {advice}")
                if c.evidence and (c.supported or i <= 3):
                    lines.append(f"{'':>6}{c.evidence}")
            added += [c.label for c in cands if c.recommended]
        lines.append(
            "  world: RMS per north/east/down component (nT), without -> with the effect; norm.: |B| over its noise "
            "and the components across the field over theirs, RMS (1 is the noise); later: fitted on the earlier "
            "part, applied to the later"
        )
        if self.final is not None and self.explained_by:
            lines.append(
                f"with {', '.join(self.explained_by)}: world components {self.base.world_nT:.4g} -> "
                f"{self.final.world_nT:.4g} nT, |B| {self.base.total_nT:.4g} -> {self.final.total_nT:.4g} nT"
            )
        if self.left:
            lines.append("")
            lines.append("structure left in the residuals:")
            lines.extend(f"  {s.text()}" for s in self.left)
        if self.warnings:
            lines.append("")
            lines.extend(f"warning: {w}" for w in self.warnings)
        return "\n".join(lines)


def _pair(before, after, fmt="{:.4g}") -> str:
    return f"{fmt.format(before)} -> {fmt.format(after)}"


# ---- figures of a calibration on some samples ------------------------------------------------------------------


@dataclass
class _Record:
    """A record's attitude, field and the samples a vector fit can use."""

    dataset: Any
    reference: Any
    rotation: Any
    usable: np.ndarray
    f_ref: np.ndarray

    @classmethod
    def of(cls, dataset, reference, reference_total_nT=None) -> _Record:
        found = attitude_rows(dataset)
        if found is None:
            raise CalibrationError(f"{dataset.source or 'data'}: the vector diagnosis needs the attitude")
        rotation, have = found
        ned = np.asarray(reference.ned_nT, dtype=float)
        f_ref = np.linalg.norm(ned, axis=1)
        if reference_total_nT is not None:
            f_ref = np.broadcast_to(np.asarray(reference_total_nT, dtype=float), f_ref.shape)
        usable = have & np.all(np.isfinite(ned), axis=1) & np.isfinite(f_ref)
        return cls(dataset, reference, rotation, usable, f_ref)

    def residuals(self, calibration, record_terms=None) -> tuple[np.ndarray, np.ndarray]:
        """World residuals (n_sensors, N, 3) and total-field residuals (n_sensors, N), NaN where not usable."""
        body = calibration.correct(self.dataset, record_terms, warn=False)
        world = np.stack([self.rotation.apply(b) for b in body])
        err = world - np.asarray(self.reference.ned_nT, dtype=float)[None]
        total = np.linalg.norm(world, axis=2) - self.f_ref[None]
        err[:, ~self.usable] = np.nan
        total[:, ~self.usable] = np.nan
        return err, total


def _sigmas(result: VectorFitResult) -> tuple[np.ndarray, np.ndarray]:
    """Per sensor the noises the base fit weighed its residuals with: total field, perpendicular (nT)."""
    return (
        np.array([s.sigma_total_field_nT for s in result.sensors]),
        np.array([s.sigma_perpendicular_nT for s in result.sensors]),
    )


def _score_of(record: _Record, calibration, record_terms, where, weights, sensors=None) -> Scores:
    """:func:`_scores` of ``calibration`` applied to the record (``record_terms`` as :meth:`_Record.residuals`), on
    ``sensors`` (0-based; default all)."""
    err, total = record.residuals(calibration, record_terms)
    if sensors is not None:
        k = list(sensors)
        return _scores(record, err[k], total[k], where, weights[0][k], weights[1][k])
    return _scores(record, err, total, where, weights[0], weights[1])


def _scores(record: _Record, err, total, where, sigma_f, sigma_p) -> Scores:
    """World RMS per component, |B| RMS and the weighted RMS over the samples ``where`` (the sensors given)."""
    ned = np.asarray(record.reference.ned_nT, dtype=float)
    u = ned / np.linalg.norm(ned, axis=1, keepdims=True)
    sel = where & record.usable
    n = int(sel.sum())
    if n == 0:
        return Scores(float("nan"), float("nan"), float("nan"), 0)
    e, tf = err[:, sel], total[:, sel]
    along = np.einsum("snj,nj->sn", e, u[sel])
    perp2 = np.sum(e**2, axis=2) - along**2
    weighted = (tf / sigma_f[:, None]) ** 2 + np.clip(perp2, 0.0, None) / sigma_p[:, None] ** 2
    return Scores(
        float(np.sqrt(np.mean(e**2))),
        float(np.sqrt(np.mean(tf**2))),
        float(np.sqrt(np.mean(weighted) / 3.0)),
        n,
        np.mean(weighted, axis=0) / 3.0,
    )


def significant_gain(before: Scores, after: Scores, blocks=GAIN_BLOCKS) -> bool:
    """Whether ``after`` improves on ``before`` (the same samples, in time order) by more than chance: the mean
    per-sample gains of ``blocks`` contiguous stretches, a one-sided Wilcoxon signed-rank test of them below
    :data:`GAIN_P`. A real record's residuals wander, so neighbouring samples are not independent chances; a model
    that is better improves nearly every stretch (by however much the stretch shows the effect), a gain by chance
    only some."""
    if before.per_sample is None or after.per_sample is None or len(before.per_sample) != len(after.per_sample):
        return True
    d = before.per_sample - after.per_sample
    if len(d) < 2 * blocks:
        return bool(d.mean() > 0)
    means = np.array([part.mean() for part in np.array_split(d, blocks)])
    if np.all(means == 0.0):
        return False
    return bool(d.mean() > 0 and stats.wilcoxon(means, alternative="greater").pvalue < GAIN_P)


def _log_likelihood_terms(result: VectorFitResult) -> float:
    """``sum_s n [ln RMS_F^2 + 2 ln RMS_perp^2]``: -2 ln L of the vector fit at its maximum-likelihood noises (up to a
    constant), the BIC's misfit term."""
    out = 0.0
    for s in result.sensors:
        out += result.n_samples * (
            np.log(max(s.rms_total_field_nT, 1e-9) ** 2) + 2.0 * np.log(max(s.rms_perpendicular_nT, 1e-9) ** 2)
        )
    return float(out)


def _sensors_of(effect, judged) -> tuple:
    """The sensors a candidate is scored on: its own, or every judged one for an effect of every sensor."""
    return tuple(judged) if effect.sensor is None else (effect.sensor,)


def _same_sensors(a, b) -> bool:
    """Whether two effect instances act on a common sensor."""
    return a.sensor is None or b.sensor is None or a.sensor == b.sensor


def _n_params(effect, model) -> int:
    """Parameters the effect adds to ``model`` (every instance of it), a searched constant (a step time) counting
    as one more per instance."""
    return sum(len(e.param_names()) + int(getattr(e, "extra_dof", 0)) for e, _ in model.instances() if e is effect)


# ---- candidates ------------------------------------------------------------------------------------------------


def vector_candidates(dataset, model, names=None, sensors=None) -> list:
    """The effects a vector diagnosis tries on ``dataset`` beside ``model``: every registered effect the vector
    fit can take whose channels the record has, one instance per sensor (one for a one-sensor record), not
    already in the model; only on ``sensors`` (0-based) when given."""
    out = []
    have = {e.label for e in model.effects}
    names_in = {e.name for e in model.effects if e.sensor is None}
    for name, cls in EFFECTS.items():
        if names is not None and name not in names:
            continue
        if "vector" not in getattr(cls, "modes", ("scalar", "vector")) or cls.stage != "raw":
            continue
        if not cls.per_sensor and dataset.n_sensors > 1:
            continue
        if name in names_in:
            continue
        probe = cls()
        if probe.missing_channels(dataset):
            continue
        on = [s for s in range(dataset.n_sensors) if probe.applies_to(s) and (sensors is None or s in sensors)]
        for s in [None] if on == [0] and dataset.n_sensors == 1 else on:
            e = cls(sensor=s)
            holders = [x for x in model.effects if x.name in getattr(cls, "nested_in", ())]
            if e.label not in have and not any(s is None or x.applies_to(s) for x in holders):
                out.append(e)
    return out


def _describe(effect, calibration) -> tuple[str, str]:
    """``(quote, evidence)`` of a fitted effect: what its parameters do, and how it shows."""
    quotes = []
    for e, es in calibration.model.instances() if calibration.model is not None else []:
        if e.name != effect.name or (effect.sensor is not None and es != effect.sensor):
            continue
        values = calibration.effect_values.get(term_label(e.name, es))
        q = e.quote(values, calibration.reference_total_nT, es)
        size = ", ".join(f"{n} {v:.3g}" for n, v in zip(e.param_names(), np.ravel(values)))
        quotes.append(q or size)
    signature = getattr(type(effect), "vector_signature", "")
    return "; ".join(quotes), signature


#: The channel of the evidence (:attr:`VectorDiagnosis.evidence`) each catalogue effect's residual follows: what its
#: evidence plot puts on the horizontal axis (the others follow the time).
EVIDENCE_CHANNELS = EffectTexts("evidence_channel")


def evidence_channel(effect: str, evidence: dict | None = None) -> str:
    """The key of the evidence's channel that the residual of ``effect`` (a catalogue name or label) follows:
    ``current`` (the current or throttle column), ``temperature_C``, ``turn_rate_dps`` or ``time_s``. A user's
    effect that needs the temperature follows it; ``time_s`` for the rest, and wherever ``evidence`` lacks the
    channel."""
    name = str(effect).partition(":")[0]
    key = EVIDENCE_CHANNELS.get(name)
    if key == "time_s" and "temperature" in getattr(EFFECTS.get(name), "channels", ()):
        key = "temperature_C"  # a user's effect that needs the temperature follows it
    if key is None or (evidence is not None and evidence.get(key) is None):
        return "time_s"
    return key


def vector_evidence(dataset, reference, calibration, reference_total_nT=None) -> dict:
    """The plot data of :attr:`VectorDiagnosis.evidence` for any vector calibration of ``dataset`` (a refit's, or
    the workbench's after an effect was added): the world and |B| residuals (record-only terms applied, NaN where a
    sample has no attitude or reference) and the channels."""
    record = _Record.of(dataset, reference, reference_total_nT)
    return _evidence(record, *record.residuals(calibration, "apply"))


# ---- the diagnosis ----------------------------------------------------------------------------------------------


def diagnose_vector(
    dataset,
    reference,
    result: VectorFitResult | None = None,
    effects=(),
    candidates=None,
    also=(),
    max_effects=3,
    attitude_noise_deg=None,
    noise_nT=None,
    reference_total_nT=None,
    robust=False,
    validate=True,
    top=JUDGE_TOP,
    progress: Callable | None = None,
) -> VectorDiagnosis:
    """Diagnose a vector calibration: structure left, ranked candidate effects judged held out, verdict.

    The stages of :func:`magcal.diagnosis.verdict.diagnose`, over one :class:`VectorContext`: the base model's
    figures (:func:`_vector_base`), then rounds (:func:`_vector_round`) that list the candidates, refit each,
    judge the supported ones held out and take the best; then the chosen model on every sample, what is left and
    the verdict (:func:`_vector_explain`).

    Parameters
    ----------
    dataset : Dataset
        Readings (nT) with the attitude (body -> NED).
    reference : VectorReference
        The field vector (nT, NED) per sample (:func:`magcal.checks.reference.resolve_vector_reference`).
    result : VectorFitResult, optional
        The fit to diagnose; without it the base model plus ``effects`` is fitted.
    effects : sequence of str
        Effects in the diagnosed model (when ``result`` is not given).
    candidates : sequence of str, optional
        Restrict the candidates to these catalogue names.
    also : sequence of Flight
        Other records of the same vehicle (their own reference vectors): a candidate is recommended only if it
        improves each of them too.
    max_effects : int
        Most effects added one after the other.
    attitude_noise_deg, noise_nT, reference_total_nT, robust
        As for :func:`magcal.fitting.vector.fit_vector`.
    validate : bool
        Judge the supported candidates on the later part of the record (and ``also``); without it a supported
        candidate is recommended on its in-sample gain alone (with a warning).
    top : int
        The supported candidates of a round judged held out, best first.
    progress : callable, optional
        ``progress(message, fraction)``.

    Returns
    -------
    VectorDiagnosis
    """
    t0 = _time.perf_counter()

    def report(msg, frac):
        if progress is not None:
            progress(msg, frac)

    options = {
        "attitude_noise_deg": attitude_noise_deg,
        "noise_nT": noise_nT,
        "reference_total_nT": reference_total_nT,
        "robust": robust,
    }
    report("fitting the vector model", 0.0)
    if result is None:
        result = fit_vector(dataset, reference, effects=list(effects or ()), warn=False, **options)
    if reference.kind == "fitted":
        reference = result.reference  # the field the fit found: the candidates are judged at it
    ctx = _vector_base(dataset, reference, result, also, options, validate)
    for rnd in range(max_effects if ctx.judged else 0):
        if not _vector_round(ctx, rnd, candidates, top, report, 0.1 + 0.8 * rnd / max(max_effects, 1)):
            break
    diagnosis = _vector_explain(ctx, t0)
    _uniformity_finding(ctx, diagnosis)
    return diagnosis


def _uniformity_finding(ctx: VectorContext, diagnosis: VectorDiagnosis) -> None:
    """Add the finding "the field is not uniform where you recorded" to the diagnosis's warnings when the base fit's
    total-field residual follows position (or, without positions, time at a walking pace):
    :func:`magcal.diagnosis.uniformity.field_uniformity`."""
    sigma_f = float(np.median(np.atleast_1d(ctx.weights[0])))
    found = field_uniformity(ctx.dataset, ctx.total, ctx.fitted, sigma_f)
    if not found.uniform:
        diagnosis.warnings.append(found.text)


@dataclass
class VectorContext:
    """What the stages of :func:`diagnose_vector` share, filled in as they run.

    Attributes
    ----------
    dataset : Dataset
    reference : VectorReference
    result : VectorFitResult
        The fit diagnosed.
    record : _Record
        The record's attitude, field and usable samples.
    flights : list of (Flight, _Record)
        The other flights (``also``).
    fitted : numpy.ndarray of bool
        The samples the diagnosed fit used.
    err, total : numpy.ndarray
        The diagnosed fit's world residuals (n_sensors, N, 3) and total-field residuals (n_sensors, N), nT.
    noise : dict
        :func:`_white_noise` of the residuals.
    weights : tuple of numpy.ndarray
        Per sensor the total-field and perpendicular noises the scores are weighted with, nT.
    base : Scores
        The diagnosed model's figures on its fitted samples.
    validation : dict
        :attr:`VectorDiagnosis.validation`.
    judged : list of int
        The sensors the record determines (0-based): only their effects are judged.
    options : dict
        The refits' options for :func:`magcal.fitting.vector.fit_vector` (``mask``: the samples they use).
    validate : bool
    judge : _Judge
        The held-out judgement.
    current : VectorFitResult
        The fit with the chosen effects (on the subsample for a long record).
    fits : dict
        Refits by candidate label.
    all_cands, chosen : list of VectorCandidate
        Every candidate refitted, and those taken, in order.
    warnings : list of str
    notes : list of Note
    """

    dataset: Any
    reference: Any
    result: VectorFitResult
    record: _Record
    flights: list
    fitted: np.ndarray
    err: np.ndarray
    total: np.ndarray
    noise: dict
    weights: tuple
    base: Scores
    validation: dict
    judged: list
    options: dict
    validate: bool
    judge: Any
    current: VectorFitResult
    fits: dict = field(default_factory=dict)
    all_cands: list = field(default_factory=list)
    chosen: list = field(default_factory=list)
    warnings: list = field(default_factory=list)
    notes: list = field(default_factory=list)


def _vector_base(dataset, reference, result, also, options, validate) -> VectorContext:
    """Stage 1, score the base model: its residuals, white noise and figures; the later part held out, the
    sensors the record determines, the subsample a long record's candidates are judged on."""
    options = dict(options)
    notes = [Note(w, UserWarning, "vector fit") for w in result.warnings]
    record = _Record.of(dataset, reference, options["reference_total_nT"])
    flights = [(f, _Record.of(f.dataset, f.reference)) for f in also]
    fitted = np.asarray(result.fitted, dtype=bool)
    err, total = record.residuals(result.calibration, "apply")
    noise = _white_noise(record, err, total, fitted, options["noise_nT"], options["attitude_noise_deg"])
    weights = (np.asarray(noise["total_nT"]), np.asarray(noise["perpendicular_nT"]))
    base = _scores(record, err, total, fitted, *weights)
    later, validation = _later_split(fitted, validate)
    validation["flights"] = [f.name for f, _ in flights]
    judged = [k for k, s in enumerate(result.sensors) if s.determined]  # a sensor the record does not fix: not judged
    current = result
    sub = _even_subsample(fitted, MAX_SAMPLES)
    if sub.sum() < fitted.sum():  # a long record: the candidates are judged on every k-th sample, the advice on all
        validation["subsample"] = {"samples": int(sub.sum()), "of": int(fitted.sum())}
        if judged:
            current = fit_vector(
                dataset, reference, effects=_model_of(result, dataset), mask=sub, warn=False, **options
            )
    options["mask"] = sub
    judge = _Judge(dataset, reference, record, later, flights, options, weights, validate, judged)
    ctx = VectorContext(
        dataset=dataset,
        reference=reference,
        result=result,
        record=record,
        flights=flights,
        fitted=fitted,
        err=err,
        total=total,
        noise=noise,
        weights=weights,
        base=base,
        validation=validation,
        judged=judged,
        options=options,
        validate=validate,
        judge=judge,
        current=current,
        notes=notes,
    )
    if not judged:
        ctx.warnings.append(
            "the vector fit is not determined by this record (see its warnings): no effect can be judged; record "
            "banked turns and pitch changes over several minutes"
        )
    elif len(judged) < dataset.n_sensors:
        skipped = ", ".join(str(k + 1) for k in range(dataset.n_sensors) if k not in judged)
        ctx.warnings.append(
            f"the vector fit of sensor(s) {skipped} is not determined by this record (see its warnings): no effect on "
            "it is judged"
        )
    return ctx


def _vector_round(ctx: VectorContext, rnd, names, top, report, fraction) -> bool:
    """One round of the forward selection: the candidates beside the current model (score), each refitted on the
    whole record (refit, :func:`_refit_round`), the ``top`` supported ones judged held out (validate, :class:`_Judge`),
    the best that holds taken (judge). Returns whether one was taken (the next round may look further)."""
    dataset = ctx.dataset
    model = ctx.current.calibration.model or Model(dataset.n_sensors)
    cands = vector_candidates(dataset, model, names, sensors=ctx.judged)
    if not cands:
        return False
    report(f"round {rnd + 1}: refitting {len(cands)} candidates", fraction)
    tried = _refit_round(ctx, model, cands)
    for c, fit in tried:
        c.round = rnd + 1
        ctx.fits[c.label] = fit
    supported = [(c, fit) for c, fit in tried if c.supported]
    for c, _ in tried:
        if not c.supported:
            c.why = "not supported in-sample (delta-BIC above -10)"
    for c, _ in supported[top:]:
        c.why = f"supported, not judged (only the best {top} are)"
    for c, fit in supported[:top]:
        ctx.judge(c, ctx.current, fit)
    ctx.all_cands.extend(c for c, _ in tried)
    best = next((c for c, _ in supported[:top] if c.holds), None)
    if best is None:
        return False
    best.recommended = True
    for c, _ in supported[:top]:
        if c.holds and c is not best:
            c.why = f"holds, but {best.label} explains more: see the next round"
    ctx.chosen = [c for c in ctx.chosen if c.label not in best.replaces] + [best]
    ctx.current = ctx.fits[best.label]
    if not ctx.validate:
        ctx.warnings.append(
            f"{best.label}: recommended on its in-sample gain alone (held-out judgement off): check it on "
            "another flight"
        )
    return True


def _vector_explain(ctx: VectorContext, t0) -> VectorDiagnosis:
    """The last stages: the chosen model refitted on every sample (a long record's rounds used a subsample), the
    structure left, the verdict (:func:`_verdict`) and the :class:`VectorDiagnosis`."""
    record, fitted, current, chosen = ctx.record, ctx.fitted, ctx.current, ctx.chosen
    final = None
    if chosen:
        if "subsample" in ctx.validation:
            options = dict(ctx.options, mask=fitted)
            current = fit_vector(ctx.dataset, ctx.reference, effects=current.calibration.model, warn=False, **options)
        final = _score_of(record, current.calibration, "apply", fitted, ctx.weights)
        ctx.fits["+".join(c.label for c in chosen)] = current
    err_f, total_f = record.residuals(current.calibration, "apply")
    left = _left_structure(record, err_f, total_f, fitted)
    last = max((c.round for c in ctx.all_cands), default=0)
    record_holds = [
        c for c in ctx.all_cands if c.round == last and c.supported and c.record_only and not c.recommended and c.later
    ]
    verdict, summary = _verdict(ctx.base, final, chosen, left, bool(ctx.judged), record_holds, ctx.all_cands)
    return VectorDiagnosis(
        verdict=verdict,
        summary=summary,
        effects=list(ctx.result.terms),
        reference_text=ctx.reference.text,
        base=ctx.base,
        noise=ctx.noise,
        candidates=ctx.all_cands,
        explained_by=[c.label for c in chosen],
        record_holds=list(dict.fromkeys(c.label for c in record_holds)),
        final=final,
        left=left,
        warnings=ctx.warnings,
        notes=ctx.notes,
        validation=ctx.validation,
        evidence=_evidence(record, ctx.err, ctx.total),
        result=ctx.result,
        fits=ctx.fits,
        elapsed_s=_time.perf_counter() - t0,
    )


def _refit_round(ctx: VectorContext, model, cands) -> list:
    """Every candidate refitted with ``model`` (the current fit's) on the whole record (``ctx.options``' samples):
    ``[(VectorCandidate, VectorFitResult)]``, lowest delta-BIC first; a failed refit leaves a note."""
    dataset, reference, record, current = ctx.dataset, ctx.reference, ctx.record, ctx.current
    fitted, weights, options, notes, judged = ctx.fitted, ctx.weights, ctx.options, ctx.notes, ctx.judged
    base_ll = _log_likelihood_terms(current)
    base_in = {}
    tried = []
    for e in cands:
        # an effect of the model that the candidate holds as a special case (a common delay in an eddy matrix) is
        # replaced by it: both together would leave a direction the data cannot fix
        nested = [x for x in model.effects if e.name in getattr(x, "nested_in", ()) and _same_sensors(x, e)]
        trial = model
        for x in nested:
            trial = trial.without(x.label)
        try:
            fit = fit_vector(dataset, reference, effects=trial.with_effect(e), warn=False, **options)
        except (CalibrationError, MagcalError, np.linalg.LinAlgError) as exc:
            notes.append(Note(f"{e.label}: the refit failed ({exc})", UserWarning, "vector diagnosis"))
            continue
        fitted_model = fit.calibration.model
        assert fitted_model is not None  # it holds the candidate
        added = fitted_model.effects[-1]
        q = _n_params(added, fitted_model) - sum(_n_params(x, model) for x in nested)
        n_res = 3 * fit.n_samples * dataset.n_sensors
        dbic = _log_likelihood_terms(fit) - base_ll + q * np.log(max(n_res, 2))
        on = _sensors_of(e, judged)
        if on not in base_in:
            base_in[on] = _score_of(record, current.calibration, "apply", fitted, weights, on)
        after = _score_of(record, fit.calibration, "apply", fitted, weights, on)
        quote, signature = _describe(added, fit.calibration)
        c = VectorCandidate(
            effect=e.name,
            sensor=e.sensor,
            label=e.label,
            n_params=q,
            delta_bic=float(dbic),
            in_sample=(base_in[on], after),
            record_only=not getattr(e, "transferable", True),
            params={k: v for k, v in fit.calibration.effect_values.items() if k.split(":")[0] == e.name},
            quote=quote,
            evidence="; ".join(p for p in (quote, signature) if p),
            when_recording=getattr(type(e), "when_recording", ""),
            replaces=[x.label for x in nested],
        )
        if nested:
            c.evidence = f"replaces {', '.join(c.replaces)}, which it holds; " + c.evidence
        tried.append((c, fit))
    tried.sort(key=lambda cf: cf[0].delta_bic)
    return tried


class _Judge:
    """The held-out judgement of a round's candidates: the base model fitted once on the earlier part (per base),
    each candidate fitted there too; both applied to the later part, and the whole-record fits to each other
    flight, as ``magcal apply`` applies them (record-only terms dropped, the level they keep folded in)."""

    def __init__(self, dataset, reference, record, later, flights, options, weights, validate, judged):
        self.dataset, self.reference, self.record = dataset, reference, record
        self.later, self.flights, self.options, self.weights = later, flights, options, weights
        self.validate, self.judged = validate, judged
        self._train_base: dict = {}

    def _train_fit(self, model):
        options = dict(self.options)
        train = self.record.usable & ~self.later & options.pop("mask", True)
        return fit_vector(self.dataset, self.reference, effects=model, mask=train, warn=False, **options)

    def __call__(self, c, base_fit, cand_fit) -> None:
        gains = []
        if self.validate and self.later is not None:
            base_model = base_fit.calibration.model or Model(self.dataset.n_sensors)
            key = tuple(base_model.effect_labels)
            try:
                if key not in self._train_base:
                    self._train_base[key] = self._train_fit(base_model)
                fb = self._train_base[key]
                fc = self._train_fit(cand_fit.calibration.model)
            except (CalibrationError, MagcalError) as exc:
                c.why = f"held-out fit failed ({exc})"
                return
            rec = self.record
            on = _sensors_of(c, self.judged)
            before = _score_of(rec, fb.calibration, "drop", self.later, self.weights, on)
            after = _score_of(rec, fc.calibration, "drop", self.later, self.weights, on)
            c.later = (before, after)
            gains.append(("the later part", before, after))
        if self.validate:
            for flight, rec in self.flights:
                everywhere = np.ones(rec.dataset.n_samples, bool)
                try:
                    on = _sensors_of(c, self.judged)
                    before = _score_of(rec, base_fit.calibration, "drop", everywhere, self.weights, on)
                    after = _score_of(rec, cand_fit.calibration, "drop", everywhere, self.weights, on)
                except MagcalError as exc:
                    c.why = f"cannot be applied to {flight.name} ({exc})"
                    return
                c.flights.append((flight.name, before, after))
                if not c.record_only:  # a record-only term describes this record: other flights have their own
                    gains.append((flight.name, before, after))
        if not gains:
            c.holds = not c.record_only
            c.why = "" if c.holds else "describes this record only (dropped on new data)"
            return
        worse = [
            name for name, b, a in gains if not (a.weighted <= (1.0 - MIN_GAIN) * b.weighted and significant_gain(b, a))
        ]
        c.holds = not worse
        raised = [name for name, b, a in c.flights if a.weighted > b.weighted]
        if c.record_only and raised and not worse:
            c.why = (
                f"describes this record; applied to {', '.join(raised)} (dropped, the level it keeps folded in) it "
                "raises the error there: calibrate those flights without it"
            )
        if worse:
            c.why = (
                "does not improve "
                + ", ".join(worse)
                + (" (describes this record only)" if c.record_only else " (fits this record only)")
            )


def _even_subsample(fitted, most) -> np.ndarray:
    """Every k-th fitted sample, k the smallest that leaves at most ``most`` (all of them for a short record)."""
    idx = np.flatnonzero(fitted)
    if len(idx) <= most:
        return np.asarray(fitted, dtype=bool).copy()
    stride = int(np.ceil(len(idx) / most))
    out = np.zeros(len(fitted), bool)
    out[idx[::stride]] = True
    return out


def _model_of(result, dataset) -> Model:
    return result.calibration.model.copy() if result.calibration.model is not None else Model(dataset.n_sensors)


def _later_split(fitted, validate) -> tuple[np.ndarray | None, dict]:
    """The later part's mask (the last :data:`LATER_FRACTION` of the fitted samples) and the validation's facts."""
    idx = np.flatnonzero(fitted)
    n_later = int(round(LATER_FRACTION * len(idx)))
    if not validate:
        return None, {"skipped": "held-out judgement off (--no-validate)", "later_fraction": LATER_FRACTION}
    if n_later < MIN_LATER_SAMPLES or len(idx) - n_later < MIN_LATER_SAMPLES:
        return None, {
            "skipped": f"too few samples to hold out a later part ({len(idx)} fitted)",
            "later_fraction": LATER_FRACTION,
        }
    later = np.zeros_like(fitted)
    later[idx[-n_later:]] = True
    return later, {"later_fraction": LATER_FRACTION, "n_later": n_later}


def _white_noise(record, err, total, fitted, noise_nT=None, attitude_noise_deg=None) -> dict:
    """The white part of the residuals per sensor, from their first differences in time (``var(d r) = 2
    sigma^2``): what no model removes, and the noises the normalized RMS divides by (given ones take precedence:
    ``noise_nT`` for the total field, ``attitude_noise_deg`` for the perpendicular components)."""
    ned = np.asarray(record.reference.ned_nT, dtype=float)
    u = ned / np.linalg.norm(ned, axis=1, keepdims=True)
    idx = np.flatnonzero(fitted & record.usable)
    field_nT = float(np.nanmedian(record.f_ref))
    out_f, out_p = [], []
    for s in range(err.shape[0]):
        e, tf = err[s, idx], total[s, idx]
        along = np.sum(e * u[idx], axis=1)
        perp = e - along[:, None] * u[idx]
        sf = robust_sigma(np.diff(tf)) / np.sqrt(2.0) if len(idx) > 3 else float(np.std(tf))
        # the two components across the field: their differences per component (a third is along the field)
        sp = float(np.sqrt(1.5) * robust_sigma(np.diff(perp, axis=0).ravel()) / np.sqrt(2.0)) if len(idx) > 3 else sf
        if noise_nT is not None:
            sf = float(noise_nT)
        if attitude_noise_deg is not None:
            sp = float(np.hypot(np.radians(attitude_noise_deg) * field_nT, sf))
        out_f.append(max(float(sf), 1e-3))
        out_p.append(max(float(sp), 1e-3))
    perp_white = float(np.sqrt(np.mean(np.square(out_p))))
    sens = float(np.sqrt(np.mean(np.square(out_f))))
    return {
        "total_nT": out_f,
        "perpendicular_nT": out_p,
        "attitude_deg": float(np.degrees(np.sqrt(max(perp_white**2 - sens**2, 0.0)) / field_nT)),
        "world_floor_nT": float(np.sqrt((2 * perp_white**2 + sens**2) / 3.0)),
    }


# ---- what is left -----------------------------------------------------------------------------------------------


def _channels(record: _Record) -> dict:
    """What a vehicle's interference follows, as regressors (N, k) each: NaN-free columns only."""
    ds = record.dataset
    out = {}
    rate = turn_rate_dps(ds)
    if rate is not None and np.all(np.isfinite(rate[record.usable])):
        out["turn rate"] = np.column_stack([np.abs(rate), rate])
    ypr = record.rotation.as_euler("ZYX")
    out["heading"] = np.column_stack(
        [np.cos(ypr[:, 0]), np.sin(ypr[:, 0]), np.cos(2 * ypr[:, 0]), np.sin(2 * ypr[:, 0])]
    )
    out["tilt"] = np.column_stack([ypr[:, 1], ypr[:, 2]])
    col = current_column(ds)
    if col is not None:
        out[col] = np.asarray(ds.extra[col], dtype=float)[:, None]
    if ds.temperature_C is not None:
        out["temperature"] = np.asarray(ds.temperature_C, dtype=float)[:, None]
    if ds.time_s is not None:
        t = np.asarray(ds.time_s, dtype=float)
        x = (t - t.mean()) / max(float(np.ptp(t)), 1e-9)
        out["time"] = np.column_stack([x, x**2])
    return out


def _left_structure(record, err, total, fitted) -> list:
    """Significant structure in the residuals explained by one channel (an F-test of its regression)."""
    rows = fitted & record.usable
    n = int(rows.sum())
    if n < 30:
        return []
    found = []
    for name, X in _channels(record).items():
        Xr = X[rows]
        if not np.all(np.isfinite(Xr)):
            continue
        A = np.column_stack([np.ones(n), Xr])
        k = A.shape[1] - 1
        for s in range(err.shape[0]):
            series = {"north": err[s, rows, 0], "east": err[s, rows, 1], "down": err[s, rows, 2], "|B|": total[s, rows]}
            for label, r in series.items():
                r = r - r.mean()
                tss = float(r @ r)
                if tss <= 0:
                    continue
                coef, *_ = np.linalg.lstsq(A, r, rcond=None)
                fit = A @ coef
                ess = float(fit @ fit)
                share = ess / tss
                dof = max(n - k - 1, 1)
                f_stat = (ess / max(k, 1)) / max((tss - ess) / dof, 1e-300)
                p = float(stats.f.sf(f_stat, k, dof))
                if share >= STRUCTURE_MIN_SHARE and p < STRUCTURE_P:
                    found.append(LeftStructure(s, name, label, float(np.sqrt(ess / n)), share, p))
    found.sort(key=lambda x: -x.explained_nT)
    best: dict = {}
    for f in found:  # the strongest residual per (sensor, channel)
        best.setdefault((f.sensor, f.follows), f)
    return list(best.values())[:6]


def _verdict(base, final, chosen, left, determined, record_holds, cands) -> tuple[str, str]:
    """The verdict and its summary in words."""
    if not determined:
        return "unexplained", (
            "the vector fit is not determined by this record, so no effect can be judged: record banked turns and "
            "pitch changes (+-20 deg or more) over several minutes, with a better attitude"
        )
    now = final if final is not None else base
    at_noise = bool(np.isfinite(now.weighted) and now.weighted <= ADEQUATE_RATIO)
    parts = []
    if chosen:
        best = chosen[0]
        held = ""
        if best.later is not None:
            held = f", on the later part {best.later[0].world_nT:.4g} -> {best.later[1].world_nT:.4g} nT"
        for name, b, a in best.flights:
            held += f", on {name} {b.world_nT:.4g} -> {a.world_nT:.4g} nT"
        parts.append(
            f"the model misses {', '.join(c.label for c in chosen)} ({best.quote}): world components "
            f"{base.world_nT:.4g} -> {now.world_nT:.4g} nT in-sample{held}; add it (magcal calibrate --mode vector "
            f"--effects {','.join(c.label for c in chosen)})"
        )
        for c in chosen:
            if c.record_only:
                parts.append(
                    f"{c.label} describes this record only: magcal apply drops it on other data and keeps "
                    f"{getattr(EFFECTS.get(c.effect), 'kept_for_new_data', None) or 'the base terms'}"
                    + (f"; {c.when_recording}" if c.when_recording else "")
                )
        if not at_noise and left:
            parts.append("structure is still left: " + "; ".join(s.text() for s in left[:3]))
        verdict = "missing_effect"
    elif at_noise or not left:
        verdict = "adequate"
        parts.append(
            f"the base model leaves only noise: world components {base.world_nT:.4g} nT, |B| {base.total_nT:.4g} nT "
            f"(normalized RMS {base.weighted:.3g}; 1 is the noise)"
        )
    else:
        verdict = "unexplained"
        supported = [c for c in cands if c.supported]
        parts.append(
            "significant structure that no candidate removes on data the fit did not see: "
            + "; ".join(s.text() for s in left[:4])
        )
        if supported:
            parts.append(
                "supported in-sample but not carried: " + ", ".join(f"{c.label} ({c.why})" for c in supported[:3])
            )
    for c in record_holds[:2]:
        if c.when_recording:
            parts.append(f"{c.label} describes this record only: {c.when_recording}")
    return verdict, ". ".join(parts)


def _evidence(record, err, total) -> dict:
    """Plot data: the world residuals and |B| residuals of the diagnosed model against time and the channels."""
    ds = record.dataset
    out = {
        "time_s": None if ds.time_s is None else np.asarray(ds.time_s, dtype=float),
        "world_residual_nT": err,
        "total_residual_nT": total,
    }
    col = current_column(ds)
    if col is not None:
        out["current"] = {"column": col, "values": np.asarray(ds.extra[col], dtype=float)}
    if ds.temperature_C is not None:
        out["temperature_C"] = np.asarray(ds.temperature_C, dtype=float)
    rate = turn_rate_dps(ds)
    if rate is not None:
        out["turn_rate_dps"] = rate
    return out
