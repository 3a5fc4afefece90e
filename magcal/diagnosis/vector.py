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
   the perpendicular components over ``sigma_perp``, the white noise of the diagnosed fit's residuals, each other
   flight's its own: 1 at the noise): a candidate is recommended only if it lowers it by :data:`MIN_GAIN` or more,
   and by more than chance (the gains of ten stretches, a signed-rank test below :data:`GAIN_P`:
   :func:`significant_gain`), on the later part and on every other flight, and raises no world component nor
   ``|B|`` there beyond its noise (:func:`raised_components`). Without a later part (a record too short or too
   slow: :func:`judging_needs`) and without another flight long enough, nothing is recommended.
   An effect that describes the record (a bias step, an interference) but does not improve the later part or the
   other flights is reported in ``record_holds``, with what to do when recording.
4. **Forward selection.** The best recommended candidate joins the model and the candidates are tried again, up
   to ``max_effects``.
5. **What is left.** The final residuals (world components and ``|B|``) are regressed on what a vehicle's
   interference follows: the turn rate, the heading, the tilt, the current or throttle, the temperature, the time.
   What explains a significant part of them is named (:class:`LeftStructure`), so a structure outside the
   catalogue still says what it follows.

The verdict: ``missing_effect`` (effects recommended), ``adequate`` (nothing recommended and the residuals at
their noise: weighted RMS within :data:`ADEQUATE_RATIO` of 1 after the white noise of the record's own differences,
and the same on every other flight at its own noise), ``unexplained`` (structure that no candidate removes, a
residual or another flight far above its noise, or a base fit that the record does not determine: why, the geometry
or a misfit, from :func:`magcal.fitting.vector.undetermined_cause`) or ``not_judged`` (no held-out judgement could be
made: the summary says what would let it judge).
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
from magcal.diagnosis.base import DiagnosisBase, progress_reporter
from magcal.diagnosis.selection import first_that_holds, forward_selection
from magcal.diagnosis.uniformity import field_uniformity
from magcal.fitting.vector import VectorFitResult, attitude_error_deg, fit_vector, position_basis, positions_m
from magcal.model.effects import CURRENT_COLUMNS, current_column
from magcal.model.terms import EFFECTS, EffectTexts, Model, fitted_outside_domain, term_label

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

#: The world components each sensor's residual is judged on, and ``|B|``.
COMPONENTS = ("north", "east", "down", "|B|")

#: A component of a held-out part may rise within its noise (twice the standard error of its RMS over
#: :data:`GAIN_BLOCKS` stretches), at least by this share ...
MIN_COMPONENT_RISE = 0.02

#: ... and never by more than this: an advice that raises one world component of the next part or flight by more is
#: not advised, whatever it does to the others.
MAX_COMPONENT_RISE = 0.10

#: ... and a rise within that bound whose added part, ``sqrt(after^2 - before^2)``, is within this fraction of the
#: component's white noise is no rise (a component at its noise that moves by a hair).
NOISE_ALLOWANCE = 0.3

#: A compass logged slower than this (Hz) is named as the reason a record is too short to judge.
SLOW_RATE_HZ = 5.0

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
    #: Per scored sensor, the RMS of the north, east, down and |B| residuals (n_sensors, 4), nT (:data:`COMPONENTS`).
    components_nT: np.ndarray | None = field(default=None, repr=False, compare=False)
    #: Their squared residuals per sample (n, n_sensors * 4), nT^2: what a component's noise is computed from.
    per_component: np.ndarray | None = field(default=None, repr=False, compare=False)
    #: The scored sensors (0-based), in the order of ``components_nT``.
    sensors: tuple = field(default=(), repr=False, compare=False)
    #: The white noise of each component (n_sensors, 4), nT: a world component's ``sqrt((2 sigma_perp^2 +
    #: sigma_F^2) / 3)``, |B|'s ``sigma_F``.
    component_noise_nT: np.ndarray | None = field(default=None, repr=False, compare=False)

    def component_labels(self) -> list[str]:
        """``north of sensor 2``... in the order of ``components_nT.ravel()``."""
        one = len(self.sensors) == 1
        return [f"{c}" + ("" if one else f" of sensor {s + 1}") for s in self.sensors for c in COMPONENTS]

    def to_dict(self) -> dict:
        out: dict[str, Any] = {
            "world_rms_nT": self.world_nT,
            "total_rms_nT": self.total_nT,
            "weighted_rms": self.weighted,
            "n": self.n,
        }
        if self.components_nT is not None:
            out["components_nT"] = {
                f"sensor {s + 1}": dict(zip(COMPONENTS, map(float, row)))
                for s, row in zip(self.sensors, self.components_nT)
            }
        return out


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
    not_physical : str
        Why the fitted effect is not physical here (a parameter held at a bound of its domain,
        :func:`magcal.model.terms.outside_domain`: a negative loop width, a nonlinearity of 1e5 ppm), or ``""``.
        Such a candidate is not supported, never judged and never recommended: the record holds something else.
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
    not_physical: str = ""

    @property
    def supported(self) -> bool:
        """Lowers the BIC by more than :data:`DELTA_BIC_THRESHOLD` with physical parameters."""
        return bool(self.delta_bic < DELTA_BIC_THRESHOLD) and not self.not_physical

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
            "not_physical": self.not_physical or None,
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
    "position": "a magnet or steel near the path (the field differs from place to place): not the instrument's, "
    "record away from it",
}


@dataclass
class LeftStructure:
    """A significant structure in the residuals and what it follows.

    Attributes
    ----------
    sensor : int
        0-based.
    follows : str
        The channel: ``turn rate``, ``heading``, ``tilt``, ``current_A``/``throttle``, ``temperature``, ``time``,
        ``position`` (the record's ``pos_n_m, pos_e_m, pos_d_m``).
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
class VectorNoise:
    """The white noise of a vector fit's residuals (their differences in time), per sensor: what no model removes,
    and what the normalized RMS divides by (:func:`_white_noise`).

    Attributes
    ----------
    total_nT : list of float
        Per sensor the total field's.
    perpendicular_nT : list of float
        Per sensor the components' across the field.
    white_attitude_deg : float
        The attitude error the perpendicular white noise implies, deg.
    world_floor_nT : float
        The world components' floor ``sqrt((2 sigma_perp^2 + sigma_F^2) / 3)``, nT.
    attitude_deg : float
        The attitude error as the vector fit estimates it, deg (NaN until set).
    """

    total_nT: list
    perpendicular_nT: list
    white_attitude_deg: float
    world_floor_nT: float
    attitude_deg: float = float("nan")

    #: Where the noise came from (:class:`magcal.diagnosis.base.NoiseLevel`).
    source = "differences"

    @property
    def sigma_nT(self) -> float:
        """The total field's white noise over the sensors (RMS), nT."""
        return float(np.sqrt(np.mean(np.square(self.total_nT))))

    @property
    def weights(self) -> tuple[np.ndarray, np.ndarray]:
        """Per sensor the total-field and perpendicular noises the scores are weighed with, nT."""
        return np.asarray(self.total_nT), np.asarray(self.perpendicular_nT)

    def text(self) -> str:
        """``"world floor 3.1 nT, |B| 2.0 nT (white, from the differences in time)"``."""
        return (
            f"world floor {self.world_floor_nT:.3g} nT, |B| {self.sigma_nT:.3g} nT (white, from the residuals' "
            "differences in time)"
        )

    def to_dict(self) -> dict:
        return {
            "total_nT": [float(v) for v in self.total_nT],
            "perpendicular_nT": [float(v) for v in self.perpendicular_nT],
            "white_attitude_deg": float(self.white_attitude_deg),
            "world_floor_nT": float(self.world_floor_nT),
            "attitude_deg": float(self.attitude_deg),
        }


@dataclass
class VectorDiagnosis(DiagnosisBase):
    """What :func:`diagnose_vector` found (the names every diagnosis answers to:
    :class:`magcal.diagnosis.base.DiagnosisBase`).

    Attributes
    ----------
    verdict : str
        One of :data:`magcal.diagnosis.base.VERDICTS`.
    summary : str
    effects : list of str
        Effects already in the diagnosed model.
    reference_text : str
        Where the field vector came from.
    base : Scores
        The diagnosed model's figures on its fitted samples.
    noise : VectorNoise
        The white noise of the residuals (their differences in time), per sensor, and the attitude error.
    candidates : list of VectorCandidate
        Best (lowest delta-BIC) first, every round's.
    explained_by : list of str
        The advice: labels to fit (``magcal calibrate --mode vector --effects ...``).
    record_holds : list of str
        Effects that describe this record only (the summary says what to do when recording).
    final : Scores or None
        The figures with ``explained_by`` added.
    remaining : list of LeftStructure
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
    noise: VectorNoise
    candidates: list
    explained_by: list
    record_holds: list
    final: Scores | None
    remaining: list
    warnings: list
    notes: list
    validation: dict
    evidence: dict = field(repr=False, default_factory=dict)
    result: VectorFitResult | None = field(repr=False, default=None)
    fits: dict = field(repr=False, default_factory=dict)
    elapsed_s: float = 0.0
    mode: str = "vector"

    def _own_dict(self) -> dict:
        """The keys of ``magcal diagnose --mode vector --json`` beside the shared ones."""
        return {
            "effects": list(self.effects),
            "reference": self.reference_text,
            "rms_world_nT": self.base.world_nT,
            "rms_total_field_nT": self.base.total_nT,
            "weighted_rms": self.base.weighted,
            "record_holds": list(self.record_holds),
            "after": None if self.final is None else self.final.to_dict(),
            "validation": jsonable(self.validation),
        }

    def text(self, limit=12) -> str:
        """The header, the verdict and a ranked table of the candidates, round by round."""
        lines = self._header_lines() + self._round_lines(limit)
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
        if self.remaining:
            lines.append("")
            lines.append("structure left in the residuals:")
            lines.extend(f"  {s.text()}" for s in self.remaining)
        if self.warnings:
            lines.append("")
            lines.extend(f"warning: {w}" for w in self.warnings)
        return "\n".join(lines)

    def _header_lines(self) -> list[str]:
        """(Part of :meth:`text`.) The verdict, the summary, the base model's figures against the noise, how the
        candidates were judged and the model's effects."""
        v = self.validation
        noise = self.noise
        lines = [
            f"verdict: {self.verdict}",
            f"  {self.summary}",
            "mode: vector (the fit with attitude and the field vector); candidates judged on the world "
            "north/east/down residuals and |B|, each at its own noise",
            f"reference field vector: {self.reference_text}",
            f"world components RMS {self.base.world_nT:.4g} nT (white noise floor {noise.world_floor_nT:.3g} nT; "
            f"attitude error {noise.attitude_deg:.3g} deg as the vector fit estimates it, white part "
            f"{noise.white_attitude_deg:.3g} deg), |B| RMS {self.base.total_nT:.4g} nT (noise "
            f"{noise.sigma_nT:.3g} nT); normalized RMS "
            f"{self.base.weighted:.3g} (1 is the noise)",
        ]
        if v.get("n_later"):
            lines.append(
                f"held out: fitted on the first {100 * (1 - v['later_fraction']):.0f} %, applied to the last "
                f"{v['n_later']} samples as magcal apply does"
                + (f"; other flights: {', '.join(v['flights'])}" if v.get("flights") else "")
            )
        elif v.get("skipped"):
            lines.append(f"not judged: {v['skipped']}")
        for name, sc in (v.get("flights_base") or {}).items():
            lines.append(
                f"the diagnosed calibration on {name}: world components {sc['world_rms_nT']:.4g} nT, |B| "
                f"{sc['total_rms_nT']:.4g} nT, normalized {sc['weighted_rms']:.3g} at that flight's own noise"
            )
        if v.get("subsample"):
            lines.append(
                f"candidates fitted and judged on every k-th sample ({v['subsample']['samples']} of "
                f"{v['subsample']['of']}); the advice fitted on all"
            )
        if self.effects:
            lines.append(f"model effects: {', '.join(self.effects)}")
        return lines

    def _round_lines(self, limit) -> list[str]:
        """(Part of :meth:`text`.) The candidates' table, round by round: the first round's best ``limit``, a later
        round's supported ones (else its best three)."""
        flights = bool(self.validation.get("flights"))
        head = (
            f"{'rank':>4}  {'effect':<24} {'dBIC':>10} {'world in-sample':>17} {'world later':>17} {'norm. later':>13}"
        )
        if flights:
            head += f" {'norm. flights':>16}"
        lines: list[str] = []
        added: list[str] = []
        for r in sorted({c.round for c in self.candidates}):
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
                lines.append(_candidate_row(i, c, flights))
                if c.evidence and (c.supported or i <= 3):
                    lines.append(f"{'':>6}{c.evidence}")
            added += [c.label for c in cands if c.recommended]
        return lines


def _candidate_row(rank, c, flights) -> str:
    """A candidate's row of :meth:`VectorDiagnosis.text`: world RMS in-sample and later, normalized later (and on
    the other ``flights``), the advice."""
    later = "-" if c.later is None else _pair(c.later[0].world_nT, c.later[1].world_nT)
    nlater = "-" if c.later is None else _pair(c.later[0].weighted, c.later[1].weighted, "{:.3g}")
    row = (
        f"{rank:>4}  {c.label:<24} {c.delta_bic:>10.1f} "
        f"{_pair(c.in_sample[0].world_nT, c.in_sample[1].world_nT):>17} {later:>17} {nlater:>13}"
    )
    if flights:
        fl = "; ".join(_pair(b.weighted, a.weighted, "{:.3g}") for _, b, a in c.flights) or "-"
        row += f" {fl:>16}"
    advice = ("RECOMMENDED" + (f"; {c.why}" if c.why else "")) if c.recommended else c.why
    return row + f"  {advice}"


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
        body = calibration.correct(self.dataset, record_terms, warn=False, force=True)
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
        return _scores(record, err[k], total[k], where, weights[0][k], weights[1][k], tuple(k))
    return _scores(record, err, total, where, weights[0], weights[1])


def _scores(record: _Record, err, total, where, sigma_f, sigma_p, sensors=None) -> Scores:
    """World RMS per component, |B| RMS and the weighted RMS over the samples ``where`` (the sensors given, 0-based:
    default all), and each sensor's north, east, down and |B| RMS."""
    ned = np.asarray(record.reference.ned_nT, dtype=float)
    u = ned / np.linalg.norm(ned, axis=1, keepdims=True)
    sel = where & record.usable
    n = int(sel.sum())
    sensors = tuple(range(err.shape[0])) if sensors is None else tuple(sensors)
    if n == 0:
        return Scores(float("nan"), float("nan"), float("nan"), 0, sensors=sensors)
    e, tf = err[:, sel], total[:, sel]
    along = np.einsum("snj,nj->sn", e, u[sel])
    perp2 = np.sum(e**2, axis=2) - along**2
    weighted = (tf / sigma_f[:, None]) ** 2 + np.clip(perp2, 0.0, None) / sigma_p[:, None] ** 2
    squares = np.concatenate([e**2, tf[:, :, None] ** 2], axis=2)  # (sensors, n, 4)
    return Scores(
        float(np.sqrt(np.mean(e**2))),
        float(np.sqrt(np.mean(tf**2))),
        float(np.sqrt(np.mean(weighted) / 3.0)),
        n,
        np.mean(weighted, axis=0) / 3.0,
        np.sqrt(np.mean(squares, axis=1)),
        squares.transpose(1, 0, 2).reshape(n, -1),
        sensors,
        np.column_stack([np.repeat(np.sqrt((2 * sigma_p**2 + sigma_f**2) / 3.0)[:, None], 3, axis=1), sigma_f]),
    )


def raised_components(before: Scores, after: Scores, blocks=GAIN_BLOCKS) -> list[tuple[str, float, float]]:
    """The components (north, east, down, |B| of each sensor) whose RMS ``after`` exceeds ``before`` (the same
    samples, in time order) by more than their noise allows: ``(label, before_nT, after_nT)``.

    A component's RMS may rise by twice its standard error (from the change of its mean square over ``blocks``
    contiguous stretches: neighbouring samples are not independent chances), at least :data:`MIN_COMPONENT_RISE`
    and at most :data:`MAX_COMPONENT_RISE` of it, or by an added part within :data:`NOISE_ALLOWANCE` of its white
    noise; the total may fall while one component rises, and an advice that raises one is not advised."""
    if before.components_nT is None or after.components_nT is None or before.per_component is None:
        return []
    if after.per_component is None or before.per_component.shape != after.per_component.shape:
        return []
    out = []
    labels = before.component_labels()
    noise = np.zeros(before.components_nT.size) if before.component_noise_nT is None else before.component_noise_nT
    for j, (b, a, sigma) in enumerate(zip(before.components_nT.ravel(), after.components_nT.ravel(), np.ravel(noise))):
        if not (np.isfinite(a) and np.isfinite(b)) or a <= b:
            continue
        if a <= (1.0 + MAX_COMPONENT_RISE) * b and a * a - b * b <= (NOISE_ALLOWANCE * sigma) ** 2:
            continue  # a hair on a component at its noise
        d = after.per_component[:, j] - before.per_component[:, j]
        means = np.array([part.mean() for part in np.array_split(d, min(blocks, len(d)))])
        se = float(np.std(means, ddof=1) / np.sqrt(len(means))) if len(means) > 1 else float("inf")
        rise = 2.0 * 0.5 * se / max(b * b, 1e-300)  # twice the standard error of the RMS's relative change
        allowed = float(np.clip(rise, MIN_COMPONENT_RISE, MAX_COMPONENT_RISE))
        if a > (1.0 + allowed) * b:
            out.append((labels[j], float(b), float(a)))
    return out


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
    report = progress_reporter(progress)
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

    def judged_round(rnd):
        return _vector_round(ctx, rnd, candidates, top, report, 0.1 + 0.8 * rnd / max(max_effects, 1))

    forward_selection(
        lambda: judged_round(0),
        first_that_holds,
        lambda step, best, judged: _take(ctx, best, judged),
        lambda step, best: judged_round(step + 1),
        max_effects if ctx.judged else 0,
    )
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
    noise : VectorNoise
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
    flight_base : list of (str, Scores)
        The diagnosed calibration on each other flight, at that flight's own noise.
    """

    dataset: Any
    reference: Any
    result: VectorFitResult
    record: _Record
    flights: list
    fitted: np.ndarray
    err: np.ndarray
    total: np.ndarray
    noise: VectorNoise
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
    flight_base: list = field(default_factory=list)

    @property
    def judging(self) -> bool:
        """Whether a held-out judgement can be made: a later part, or another flight long enough."""
        return bool(self.validate) and (
            self.judge.later is not None or any(sc.n >= MIN_LATER_SAMPLES for _, sc in self.flight_base)
        )


def _vector_base(dataset, reference, result, also, options, validate) -> VectorContext:
    """Stage 1, score the base model: its residuals, white noise and figures; the later part held out, the
    sensors the record determines, the subsample a long record's candidates are judged on."""
    options = dict(options)
    notes = [Note(w, UserWarning, "vector fit") for w in result.warnings]
    record = _Record.of(dataset, reference, options["reference_total_nT"])
    fitted = np.asarray(result.fitted, dtype=bool)
    err, total = record.residuals(result.calibration, "apply")
    noise = _white_noise(record, err, total, fitted, options["noise_nT"], options["attitude_noise_deg"])
    # the attitude error: the vector fit's own estimate, the one magcal calibrate reports
    noise.attitude_deg = float(np.sqrt(np.mean([s.attitude_noise_deg**2 for s in result.sensors])))
    weights = noise.weights
    base = _scores(record, err, total, fitted, *weights)
    flights = [_flight_at_its_noise(f, result, options) for f in also]
    later, validation = _later_split(fitted, validate, dataset)
    validation["flights"] = [f.name for f, _, _ in flights]
    flight_base = [(f.name, _flight_base(rec, result, w)) for f, rec, w in flights]
    validation["flights_base"] = {name: sc.to_dict() for name, sc in flight_base}
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
    judge = _Judge(
        dataset, reference, record, later, flights, options, weights, validate, judged, validation.get("needs", "")
    )
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
        flight_base=flight_base,
    )
    if not judged:
        ctx.warnings.append(
            "the vector fit is not determined by this record (see its warnings): no effect can be judged; "
            + _undetermined_text(result)
        )
    elif len(judged) < dataset.n_sensors:
        skipped = ", ".join(str(k + 1) for k in range(dataset.n_sensors) if k not in judged)
        ctx.warnings.append(
            f"the vector fit of sensor(s) {skipped} is not determined by this record (see its warnings): no effect on "
            "it is judged"
        )
    return ctx


def _flight_at_its_noise(flight, result, options) -> tuple:
    """``(Flight, _Record, weights)``: another flight and the noises its scores are weighed with, its own (the white
    noise of the base calibration's residuals there), so that each flight is judged at its noise."""
    rec = _Record.of(flight.dataset, flight.reference)
    err, total = rec.residuals(result.calibration, "drop")
    noise = _white_noise(rec, err, total, rec.usable, options["noise_nT"], options["attitude_noise_deg"])
    return flight, rec, noise.weights


def _flight_base(rec, result, weights) -> Scores:
    """The diagnosed calibration's figures on another flight, at that flight's noise."""
    return _score_of(rec, result.calibration, "drop", np.ones(rec.dataset.n_samples, bool), weights)


def _undetermined_text(result) -> str:
    """Why the record does not determine the fit, per sensor (the fit's :class:`UndeterminedCause`), in words."""
    causes = [(k, s.undetermined_cause) for k, s in enumerate(result.sensors) if not s.determined]
    texts = [f"sensor {k + 1}: {c.text}" if len(result.sensors) > 1 else c.text for k, c in causes if c is not None]
    return "; ".join(texts) or "record banked turns and pitch changes (+-20 deg or more) over several minutes"


def _vector_round(ctx: VectorContext, rnd, names, top, report, fraction) -> list | None:
    """One round of the forward selection (:func:`magcal.diagnosis.selection.forward_selection`): the candidates
    beside the current model (score), each refitted on the whole record (refit, :func:`_refit_round`), the ``top``
    supported ones judged held out (validate, :class:`_Judge`). Returns those judged, best delta-BIC first (the
    selection takes the first that holds: :func:`_take`), or None when there is no candidate."""
    dataset = ctx.dataset
    model = ctx.current.calibration.model or Model(dataset.n_sensors)
    cands = vector_candidates(dataset, model, names, sensors=ctx.judged)
    if not cands:
        return None
    report(f"round {rnd + 1}: refitting {len(cands)} candidates", fraction)
    tried = _refit_round(ctx, model, cands)
    for c, fit in tried:
        c.round = rnd + 1
        ctx.fits[c.label] = fit
    supported = [(c, fit) for c, fit in tried if c.supported]
    for c, _ in tried:
        if c.not_physical:
            c.why = f"not physical here ({c.not_physical})"
        elif not c.supported:
            c.why = "not supported in-sample (delta-BIC above -10)"
    for c, _ in supported[top:]:
        c.why = f"supported, not judged (only the best {top} are)"
    for c, fit in supported[:top]:
        ctx.judge.judge(ctx.current, c, fit)
    ctx.all_cands.extend(c for c, _ in tried)
    return [c for c, _ in supported[:top]]


def _take(ctx: VectorContext, best, judged) -> None:
    """The forward selection takes ``best``, the first of the round's ``judged`` candidates that holds: it is
    recommended, the others that hold wait for the next round, and the model takes it (in place of the effects
    it holds as special cases)."""
    best.recommended = True
    for c in judged:
        if c.holds and c is not best:
            c.why = f"holds, but {best.label} explains more: see the next round"
    ctx.chosen = [c for c in ctx.chosen if c.label not in best.replaces] + [best]
    ctx.current = ctx.fits[best.label]


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
    verdict, summary = _verdict(ctx, final, left, record_holds)
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
        remaining=left,
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
            not_physical=fitted_outside_domain(fitted_model, fit.calibration.effect_values, e.name, fit.bound_pull_z),
        )
        if nested:
            c.evidence = f"replaces {', '.join(c.replaces)}, which it holds; " + c.evidence
        tried.append((c, fit))
    tried.sort(key=lambda cf: cf[0].delta_bic)
    return tried


class _Judge:
    """The held-out judgement of a round's candidates: the base model fitted once on the earlier part (per base),
    each candidate fitted there too; both applied to the later part, and the whole-record fits to each other
    flight (weighed at that flight's own noise), as ``magcal apply`` applies them (record-only terms dropped, the
    level they keep folded in). ``flights``: ``(Flight, _Record, weights)``; ``not_judged``: why there is no
    held-out part, in words (the candidates are then not advised)."""

    def __init__(self, dataset, reference, record, later, flights, options, weights, validate, judged, not_judged=""):
        self.dataset, self.reference, self.record = dataset, reference, record
        self.later, self.flights, self.options, self.weights = later, flights, options, weights
        self.validate, self.judged, self.not_judged = validate, judged, not_judged
        self._train_base: dict = {}

    def _train_fit(self, model):
        options = dict(self.options)
        train = self.record.usable & ~self.later & options.pop("mask", True)
        return fit_vector(self.dataset, self.reference, effects=model, mask=train, warn=False, **options)

    def _later_part(self, c, base_fit, cand_fit):
        """``(before, after)`` on the later part, or a string: why the held-out fit failed."""
        base_model = base_fit.calibration.model or Model(self.dataset.n_sensors)
        key = tuple(base_model.effect_labels)
        try:
            if key not in self._train_base:
                self._train_base[key] = self._train_fit(base_model)
            fb = self._train_base[key]
            fc = self._train_fit(cand_fit.calibration.model)
        except (CalibrationError, MagcalError) as exc:
            return f"held-out fit failed ({exc})"
        on = _sensors_of(c, self.judged)
        before = _score_of(self.record, fb.calibration, "drop", self.later, self.weights, on)
        after = _score_of(self.record, fc.calibration, "drop", self.later, self.weights, on)
        return before, after

    def judge(self, base_fit, c, cand_fit) -> None:
        """Judge the candidate ``c`` (its fit on the whole record ``cand_fit``) against the round's base model
        ``base_fit`` on the later part and the other flights (:class:`magcal.diagnosis.selection.HeldOutJudge`):
        sets its ``holds``, its figures there and, when it does not hold, ``why``."""
        # the parts judged on their gain and their components, and those judged on their components only
        gains: list[tuple[str, Scores, Scores]] = []
        checked: list[tuple[str, Scores, Scores]] = []
        if self.validate and self.later is not None:
            found = self._later_part(c, base_fit, cand_fit)
            if isinstance(found, str):
                c.why = found
                return
            c.later = found
            gains.append(("the later part", *found))
        for flight, rec, weights in self.flights if self.validate else ():
            everywhere = np.ones(rec.dataset.n_samples, bool)
            try:
                on = _sensors_of(c, self.judged)
                before = _score_of(rec, base_fit.calibration, "drop", everywhere, weights, on)
                after = _score_of(rec, cand_fit.calibration, "drop", everywhere, weights, on)
            except MagcalError as exc:
                c.why = f"cannot be applied to {flight.name} ({exc})"
                return
            c.flights.append((flight.name, before, after))
            if before.n >= MIN_LATER_SAMPLES:  # a record-only term describes this record: others have their own
                (checked if c.record_only else gains).append((flight.name, before, after))
        if not gains:
            c.holds = None
            c.why = "not judged (no held-out part" + (
                ": see the verdict)" if self.not_judged else " and no other flight)"
            )
            return
        reasons = [r for r in (_part_verdict(name, b, a) for name, b, a in gains) if r]
        reasons += [r for r in (_part_verdict(name, b, a, gain=False) for name, b, a in checked) if r]
        c.holds = not reasons
        if reasons:
            c.why = "; ".join(reasons) + (" (describes this record only)" if c.record_only else "")


def _part_verdict(name, before: Scores, after: Scores, gain=True) -> str:
    """Why a candidate's calibration does not hold on a held-out part or flight (``""`` when it does): it raises
    a component beyond its noise (:func:`raised_components`), or (with ``gain``) it does not lower the residual
    weighed at its noise by :data:`MIN_GAIN`, or not by more than chance (:func:`significant_gain`). The words
    follow the numbers: a lower world RMS is said when it is lower."""
    raised = raised_components(before, after)
    if raised:
        return (
            f"raises on {name} "
            + ", ".join(f"the {label} residual {b:.4g} -> {a:.4g} nT" for label, b, a in raised[:3])
            + " (more than its noise allows)"
        )
    if not gain:
        return ""
    pair = (
        f"world {before.world_nT:.4g} -> {after.world_nT:.4g} nT, |B| {before.total_nT:.4g} -> {after.total_nT:.4g} nT"
    )
    if not after.weighted <= (1.0 - MIN_GAIN) * before.weighted:
        if after.world_nT < before.world_nT:
            return (
                f"lowers {name}'s world components but not its residual weighed at its noise ({pair}; normalized "
                f"{before.weighted:.3g} -> {after.weighted:.3g})"
            )
        return f"does not improve {name} ({pair})"
    if not significant_gain(before, after):
        return f"its gain on {name} ({pair}) is within chance: not on most stretches of it"
    return ""


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


def _later_split(fitted, validate, dataset=None) -> tuple[np.ndarray | None, dict]:
    """The later part's mask (the last :data:`LATER_FRACTION` of the fitted samples) and the validation's facts
    (``skipped`` and ``needs``, in words, when there is none: :func:`judging_needs`)."""
    idx = np.flatnonzero(fitted)
    n_later = int(round(LATER_FRACTION * len(idx)))
    if not validate:
        return None, {
            "skipped": "held-out judgement off (--no-validate)",
            "needs": "the held-out judgement (drop --no-validate)",
            "later_fraction": LATER_FRACTION,
        }
    if n_later < MIN_LATER_SAMPLES or len(idx) - n_later < MIN_LATER_SAMPLES:
        return None, {
            "skipped": f"too few samples to hold out a later part ({len(idx)} fitted)",
            "needs": judging_needs(dataset, fitted),
            "later_fraction": LATER_FRACTION,
        }
    later = np.zeros_like(fitted)
    later[idx[-n_later:]] = True
    return later, {"later_fraction": LATER_FRACTION, "n_later": n_later}


#: The fewest fitted samples with a later part held out: :data:`MIN_LATER_SAMPLES` in the smaller of the two parts.
MIN_JUDGED_SAMPLES = int(np.ceil(MIN_LATER_SAMPLES / min(LATER_FRACTION, 1.0 - LATER_FRACTION)))


def judging_needs(dataset, fitted) -> str:
    """What would let a record too short to judge be judged, in words: the samples (and minutes at its rate) more,
    and for a compass logged slowly (below :data:`SLOW_RATE_HZ`) the rate to log it at and how its firmware sets it
    (:func:`faster_logging`)."""
    idx = np.flatnonzero(fitted)
    more = max(MIN_JUDGED_SAMPLES - len(idx), 0)
    text = (
        f"a held-out judgement needs {MIN_JUDGED_SAMPLES} fitted samples (the last {100 * LATER_FRACTION:.0f} % held "
        f"out, at least {MIN_LATER_SAMPLES} there): {more} more"
    )
    t = None if dataset is None or dataset.time_s is None else np.asarray(dataset.time_s, dtype=float)[idx]
    duration = float(np.ptp(t)) if t is not None and len(t) > 1 else 0.0
    rate = (len(idx) - 1) / duration if duration > 0 else float("nan")
    if np.isfinite(rate):
        text += f", {more / rate / 60.0:.1f} minutes more at this record's {rate:.2g} Hz"
        if rate < SLOW_RATE_HZ:
            text += f"; the compass is logged at {rate:.2g} Hz: {faster_logging(dataset)}"
    return text + "; or another flight of the same vehicle (--also)"


def faster_logging(dataset) -> str:
    """How to log a compass faster on the firmware that wrote ``dataset`` (its ``log_format`` metadata)."""
    meta = getattr(dataset, "metadata", None) or {}
    fmt, mags = str(meta.get("log_format", "")), str(meta.get("log_magnetometers", ""))
    if "PX4" in fmt and "sensor_mag" in mags:
        return (
            "PX4's default logging profile keeps sensor_mag at 1 Hz; add the sensor-comparison profile to "
            "SDLOG_PROFILE (bit 6, +64: sensor_mag at 10 Hz) or list 'sensor_mag 50' (every 50 ms) in "
            "etc/logging/logger_topics.txt on the SD card"
        )
    if "PX4" in fmt:
        return "log the compass at 10 Hz or more (PX4: sensor_mag through SDLOG_PROFILE's sensor comparison, bit 6)"
    return "log the compass at 10 Hz or more (the logger's rate for the magnetometer)"


def _white_noise(record, err, total, fitted, noise_nT=None, attitude_noise_deg=None) -> VectorNoise:
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
    return VectorNoise(
        total_nT=out_f,
        perpendicular_nT=out_p,
        white_attitude_deg=attitude_error_deg(perp_white, sens, field_nT),
        world_floor_nT=float(np.sqrt((2 * perp_white**2 + sens**2) / 3.0)),
    )


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
    pos = positions_m(ds)
    if pos is not None and np.all(np.isfinite(pos[record.usable])) and np.ptp(pos[record.usable], axis=0).max() > 0:
        out["position"] = position_basis(np.where(record.usable[:, None], pos, pos[record.usable].mean(axis=0)))
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


def _verdict(ctx: VectorContext, final, left, record_holds) -> tuple[str, str]:
    """The verdict and its summary in words: the words follow the numbers (every flight at its own noise)."""
    base, chosen, cands = ctx.base, ctx.chosen, ctx.all_cands
    if not ctx.judged:
        return "unexplained", (
            "the vector fit is not determined by this record, so no effect can be judged: "
            + _undetermined_text(ctx.result)
        )
    in_sample = (
        f"in-sample the base model leaves world components {base.world_nT:.4g} nT, |B| {base.total_nT:.4g} nT "
        f"(normalized RMS {base.weighted:.3g}; 1 is the noise)"
    )
    supported = [c for c in cands if c.supported]
    if not ctx.judging:
        v = ctx.validation
        parts = [f"not judged: {v.get('skipped', 'no held-out part')}; what would let it judge: {v.get('needs', '')}"]
        parts.append(in_sample)
        if supported:
            parts.append(
                "supported in-sample, not advised until judged held out: " + ", ".join(c.label for c in supported[:4])
            )
        return "not_judged", ". ".join(parts)
    now = final if final is not None else base
    at_noise = bool(np.isfinite(now.weighted) and now.weighted <= ADEQUATE_RATIO)
    off = [(n, sc) for n, sc in ctx.flight_base if sc.n >= MIN_LATER_SAMPLES and not sc.weighted <= ADEQUATE_RATIO]
    parts = []
    if chosen:
        parts += _advice_parts(base, now, chosen)
        if not at_noise and left:
            parts.append("structure is still left: " + "; ".join(s.text() for s in left[:3]))
        verdict = "missing_effect"
    elif at_noise and not off:
        verdict = "adequate"
        parts.append(
            f"the base model leaves only noise: world components {base.world_nT:.4g} nT, |B| {base.total_nT:.4g} nT "
            f"(normalized RMS {base.weighted:.3g}; 1 is the noise)"
            + "".join(f"; on {n} {sc.world_nT:.4g} nT (normalized {sc.weighted:.3g})" for n, sc in ctx.flight_base)
        )
    else:
        verdict = "unexplained"
        if left:
            parts.append(
                "significant structure that no candidate removes on data the fit did not see: "
                + "; ".join(s.text() for s in left[:4])
            )
        elif not at_noise:
            parts.append(
                f"the residual is {base.weighted:.3g}x its noise (world components {base.world_nT:.4g} nT, |B| "
                f"{base.total_nT:.4g} nT) and follows none of the channels tried"
            )
        if supported:
            parts.append(
                "supported in-sample but not carried: " + ", ".join(f"{c.label} ({c.why})" for c in supported[:3])
            )
    parts += [_flight_off_text(name, sc, base) for name, sc in off]
    for c in record_holds[:2]:
        if c.when_recording:
            parts.append(f"{c.label} describes this record only: {c.when_recording}")
    return verdict, ". ".join(parts)


def _advice_parts(base, now, chosen) -> list[str]:
    """The summary's advice: what is added, its figures in-sample and held out, what magcal apply keeps."""
    best = chosen[0]
    held = ""
    if best.later is not None:
        held = f", on the later part {best.later[0].world_nT:.4g} -> {best.later[1].world_nT:.4g} nT"
    for name, b, a in best.flights:
        held += f", on {name} {b.world_nT:.4g} -> {a.world_nT:.4g} nT"
    parts = [
        f"the model misses {', '.join(c.label for c in chosen)} ({best.quote}): world components "
        f"{base.world_nT:.4g} -> {now.world_nT:.4g} nT in-sample{held}; add it (magcal calibrate --mode vector "
        f"--effects {','.join(c.label for c in chosen)})"
    ]
    for c in chosen:
        if c.record_only:
            parts.append(
                f"{c.label} describes this record only: magcal apply drops it on other data and keeps "
                f"{getattr(EFFECTS.get(c.effect), 'kept_for_new_data', None) or 'the base terms'}"
                + (f"; {c.when_recording}" if c.when_recording else "")
            )
    return parts


def _flight_off_text(name, sc: Scores, base: Scores) -> str:
    """The words for another flight where the diagnosed calibration leaves more than that flight's noise."""
    return (
        f"the diagnosed calibration (the base, without advice) does not carry to {name}: it leaves {sc.weighted:.3g}x "
        f"that flight's noise there (world "
        f"components {sc.world_nT:.4g} nT, |B| {sc.total_nT:.4g} nT; {base.world_nT:.4g} and {base.total_nT:.4g} nT "
        "on this record): something differs between the records (a hard iron that moved, another field or attitude "
        "source, an effect this record does not show)"
    )


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
