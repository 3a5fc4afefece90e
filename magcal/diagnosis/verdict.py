"""The verdict of a diagnosis and :func:`diagnose`, which reaches it.

:func:`diagnose` fits (or takes) a model, runs the score tests (:mod:`.scores`), confirms the best candidates
by refitting, adds supported effects one after the other while the structure tests (:mod:`.structure`) still
find something, and gives a :class:`Diagnosis` with one of the :data:`~magcal.diagnosis.base.VERDICTS`: ``adequate`` (no significant
structure left, or only an excess over the floor of at most :data:`AT_FLOOR_FRACTION`: "at the noise floor within
x %"), ``missing_effect`` (catalogue terms bring the residuals down to the noise) or ``unexplained``
(significant structure no catalogue term removes, described). A candidate is supported when its delta-BIC is
below :data:`DELTA_BIC_THRESHOLD`. :func:`_warnings_for` says when candidates are confounded.

Held-out judgement
    With ``validate=True`` (default) every supported candidate that is refitted is also fitted on part of the
    record and scored on the rest (:mod:`magcal.fitting.validation`, warm-started where the refit starts): the
    ``blocks`` scheme (alternating blocks in time, every term interpolated) and the ``later`` scheme (the last
    quarter of the record; record-only terms held at their fitted average). A candidate is *recommended* -- it may enter
    ``explained_by``, the ``missing_effect`` verdict and the advice -- only if its held-out RMS falls by at least
    :data:`magcal.fitting.validation.MIN_RELATIVE_GAIN` on ``blocks`` and does not rise on ``later`` by more than
    :data:`magcal.fitting.validation.LATER_TOLERANCE_SE` standard errors (:func:`magcal.fitting.validation.judge`). A candidate
    whose in-sample gain does not hold is ranked below those that hold and its evidence says so. A record too
    short to split (:func:`magcal.fitting.validation.split_problem`) is judged in-sample only, with a note.
"""

from __future__ import annotations

import threading
import time as _time
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from magcal.checks.noise import NoiseEstimate, estimate_noise, is_smooth_sequence
from magcal.checks.quality import TEMP_TIME_CORR_WARN, EARTH_FIELD_RANGE_nT
from magcal.core import notes as _notes
from magcal.core.errors import CalibrationError, MagcalError
from magcal.core.jsonable import jsonable
from magcal.core.notes import row_runs
from magcal.data.attitude import attitude_present
from magcal.diagnosis import _parallel
from magcal.diagnosis._fitted import _consistency_rms, _fit_of, _floor, _kept, _reference_override, _sensor_directions
from magcal.diagnosis._parallel import CHAIN, FILLER, SHARED, Pool
from magcal.diagnosis.base import DiagnosisBase, progress_reporter
from magcal.diagnosis.evidence import (
    _effect_extra,
    _evidence_line,
    _sensor_evidence,
    _temperature_evidence,
    _time_evidence,
)
from magcal.diagnosis.jitter import jitter_estimates, jitter_words
from magcal.diagnosis.scores import (
    PREDICTED_SUPPORT_DELTA_BIC,
    _confirm,
    _num,
    _score_round,
    candidate_model,
    candidate_start,
    gram_task,
    refit_task,
)
from magcal.diagnosis.selection import forward_selection
from magcal.diagnosis.statistics import SH_MAX_SAMPLES, SHAPE_JUDGED_MIN_EIGEN, resolves_degree, sh_analysis, spectrum
from magcal.diagnosis.structure import _describe, _structure_tests
from magcal.diagnosis.uniformity import field_uniformity
from magcal.fitting import validation as _validation
from magcal.fitting.pipeline import calibrate
from magcal.geometry.ellipsoid import WEAK_DIRECTION_SPREAD, direction_spread
from magcal.model.terms import EFFECTS, EffectTexts

#: A candidate (or a refit) is supported when its delta-BIC is below this.
DELTA_BIC_THRESHOLD = PREDICTED_SUPPORT_DELTA_BIC

#: A fit whose only structure left is an excess of the RMS over the noise floor of at most this fraction is
#: ``adequate``, "at the floor within x %": the floor itself is known to about that (white and low-frequency noise,
#: filtering, a stream's resolution), and no catalogue term would be advice for so little.
AT_FLOOR_FRACTION = 0.10


@dataclass
class Diagnosis(DiagnosisBase):
    """What :func:`diagnose` found.

    Attributes
    ----------
    verdict : str
        ``adequate``, ``missing_effect`` or ``unexplained``.
    summary : str
        One or two sentences for people.
    effects : list of str
        Candidate effects already in the diagnosed model.
    rms_nT : float
        Total-field RMS of the diagnosed model.
    rms_per_sensor_nT : numpy.ndarray
    noise : NoiseEstimate
    floor_nT : float
        Total-field RMS floor ``sigma sqrt(1 - p/N)``.
    candidates : list of Candidate
        Best first.
    explained_by : list of str
        The advice for a calibration: labels of the effects that, added, bring the residuals to the noise
        (``missing_effect``) *and* improve the calibration for new data (fitted on the earlier part of the
        record, applied to its later stretch as ``magcal apply`` does).
    partially_explained_by : list of str
        The same for supported effects that reduce the residuals without bringing them to the noise
        (``unexplained``).
    record_holds : list of str
        What this record holds that is not advice for the calibration: record-only terms (drifts, steps,
        interference, a changing or non-uniform field: :attr:`magcal.model.terms.Effect.transferable` False)
        and terms that describe the record but do not improve it on its later part. The summary says what to do
        about each when recording.
    variance_terms : list of dict
        Variance terms estimated from the residuals' variance (:mod:`magcal.diagnosis.jitter`): per sensor 2-4 of an
        array with time stamps, ``sensor_jitter`` with ``jitter_rms_ms`` and ``significant`` (named in the summary
        and the warnings when significant).
    record_details : list of dict
        Per ``record_holds`` entry: ``label``, ``record_only``, ``describes_record``, ``improves_new_data``, the
        later stretch's RMS before and after (nT), ``kept_for_new_data`` (what the calibration keeps when the
        term is fitted with the base terms) and ``when_recording``.
    warnings : list of str
    structure : list of Structure
        Significant structure left in the diagnosed model's residuals.
    remaining : list of Structure
        Structure still left after adding ``explained_by`` (or ``partially_explained_by``).
    evidence : dict
        Plot data and statistics (plain numpy arrays): ``time``, ``temperature``, ``direction``, ``spectrum``,
        ``sensors``, ``noise``.
    result : FitResult
        The fit diagnosed.
    fits : dict of str to FitResult
        Refits by candidate label (and ``"+".join(explained_by)`` for the final model).
    elapsed_s : float
        Wall-clock seconds the diagnosis took.
    ran_on : dict
        Where its fits ran: ``where`` (``"threads"``, ``"processes"`` or ``"dask"``) and ``workers`` (threads or
        worker processes of this machine; a cluster's worker threads for Dask), so that ``elapsed_s`` can be read.
    rms_final_nT : float or None
        Total-field RMS with ``explained_by`` (or ``partially_explained_by``) added, nT.
    validation : dict
        The held-out judgement: ``validated`` (bool), ``skipped`` (why not, or None), ``schemes`` (per scheme:
        ``n_train``, ``n_test``, ``base_held_out_rms_nT``), ``min_relative_gain``, ``later_tolerance_se``,
        and ``held_out_rms_before_nT`` / ``held_out_rms_after_nT`` of the recommended effects (blocks scheme).
    notes : list of Note
        What the diagnosis's own fits said (:mod:`magcal.core.notes`): the fit of the model when no result was
        given (weak coverage, ...), any refit or held-out fit that did not converge (those run on the pool's
        threads: each returns its notes with its fit). :func:`magcal.diagnose` raises them as warnings; this
        function never does. (``warnings`` are the diagnosis's findings, as its table lists them.)
    """

    verdict: str
    summary: str
    effects: list
    rms_nT: float
    rms_per_sensor_nT: np.ndarray
    noise: NoiseEstimate
    floor_nT: float
    candidates: list
    explained_by: list
    partially_explained_by: list
    warnings: list
    structure: list
    remaining: list
    evidence: dict
    result: object = field(repr=False, default=None)
    fits: dict = field(repr=False, default_factory=dict)
    elapsed_s: float = 0.0
    ran_on: dict = field(default_factory=dict)
    rms_final_nT: float | None = None
    validation: dict = field(default_factory=dict)
    notes: list = field(default_factory=list)
    record_holds: list = field(default_factory=list)
    record_details: list = field(default_factory=list)
    variance_terms: list = field(default_factory=list)

    def _own_dict(self) -> dict:
        """The keys of ``magcal diagnose --json`` beside the shared ones (:meth:`DiagnosisBase.to_dict`)."""
        return {
            "effects": list(self.effects),
            "rms_nT": _num(self.rms_nT),
            "noise_nT": _num(self.noise.sigma_nT),
            "noise_source": self.noise.source,
            "floor_nT": _num(self.floor_nT),
            "rms_per_sensor_nT": [float(v) for v in self.rms_per_sensor_nT],
            "partially_explained_by": list(self.partially_explained_by),
            "rms_after_nT": _num(self.rms_final_nT),
            "structure": [s.to_dict() for s in self.structure],
            "ran_on": dict(self.ran_on),
            "validation": jsonable(self.validation),
            "record_holds": list(self.record_holds),
            "record_details": jsonable(self.record_details),
            "variance_terms": jsonable(self.variance_terms),
        }

    def where_text(self) -> str:
        """How long the diagnosis took and where its fits ran, in words (``"4.3 s on 2 worker processes"``)."""
        where, workers = self.ran_on.get("where"), int(self.ran_on.get("workers") or 1)
        if where == "dask":
            on = f"a Dask cluster ({workers} worker thread{'s' if workers != 1 else ''})"
        elif where == "processes":
            on = f"{workers} worker processes"
        else:
            on = "one core" if workers <= 1 else f"{workers} threads"
        return f"{float(self.elapsed_s):.1f} s on {on}"

    def text(self, limit=12) -> str:
        """The verdict, the summary and a readable ranked table of the candidates."""
        lines = [
            f"verdict: {self.verdict}",
            f"  {self.summary}",
            f"total-field RMS {self.rms_nT:.3g} nT; noise {self.noise.text()}; floor {self.floor_nT:.3g} nT",
        ]
        v = self.validation or {}
        if v.get("validated"):
            blocks = v["schemes"]["blocks"]
            later = v["schemes"].get("later")
            line = (
                f"held-out validation: blocks ({blocks['n_test']} of {blocks['n_train'] + blocks['n_test']} "
                f"samples held out, base model {blocks['base_held_out_rms_nT']:.4g} nT)"
            )
            if later:
                line += f", later (last {later['n_test']} samples, base {later['base_held_out_rms_nT']:.4g} nT)"
            lines.append(line)
        elif v.get("skipped"):
            lines.append(f"held-out validation skipped: {v['skipped']}")
        if self.effects:
            lines.append(f"model effects: {', '.join(self.effects)}")
        lines.append("")
        lines.append(
            f"{'rank':>4}  {'effect':<24} {'sensor':>6} {'dBIC':>10} {'RMS after':>10} "
            f"{'held-out':>17} {'later':>17} {'holds':>5}  evidence"
        )
        for i, c in enumerate(self.candidates[:limit], 1):
            mark = "" if c.refitted else "*"
            sensor = "-" if len(self.rms_per_sensor_nT) == 1 else "all" if c.sensor is None else str(c.sensor + 1)
            holds = "-" if c.holds is None else "yes" if c.holds else "NO"
            if c.refitted and not c.converged:
                lines.append(f"{i:>4}  {c.effect:<24} {sensor:>6}  did not converge  {c.evidence}")
                continue
            lines.append(
                f"{i:>4}  {c.effect:<24} {sensor:>6} {c.delta_bic:>9.1f}{mark:1} {c.rms_after_nT:>9.3g} "
                f"{_pair(c.held_out_before_nT, c.held_out_after_nT):>17} "
                f"{_pair(c.later_before_nT, c.later_after_nT):>17} {holds:>5}  {c.evidence}"
            )
        if any(not c.refitted for c in self.candidates[:limit]):
            lines.append("  * predicted by the score test (not refitted)")
        if v.get("validated"):
            lines.append(
                "  held-out, later: total-field RMS without -> with the effect on samples the fit did not "
                "see (nT); holds: the gain holds on them (recommended only then)"
            )
        if self.warnings:
            lines.append("")
            lines.extend(f"warning: {w}" for w in self.warnings)
        return "\n".join(lines)


def _pair(before, after) -> str:
    """``"1011 -> 963"`` (nT), or ``"-"``."""
    if before is None or after is None:
        return "-"
    return f"{before:.4g} -> {after:.4g}"


def _warnings_for(cands, proj, kept, fit, noise, significant):
    """The diagnosis's warnings on its noise (:func:`_noise_warnings`), on candidates the data cannot tell apart
    (:func:`_confounded_warnings`) and on the channels a candidate needs but some samples lack
    (:func:`_channel_warnings`)."""
    top = [c for c in cands if c.delta_bic < DELTA_BIC_THRESHOLD][:4]
    return (
        _noise_warnings(kept, fit, noise) + _confounded_warnings(cands, proj, kept, top) + _channel_warnings(kept, fit)
    )


def _noise_warnings(kept, fit, noise) -> list[str]:
    """(Part of :func:`_warnings_for`.) A noise that stands in for an estimate, or a given noise that differs from
    the noise seen in the data by more than 20 %."""
    out = []
    if noise.source == "residuals":
        out.append(noise.note)
    if noise.source == "given":
        seen = estimate_noise(kept.replace(noise_nT=None), fit.residuals_nT[:, fit.mask], fit.n_params)
        ratio = noise.sigma_nT / seen.sigma_nT if seen.sigma_nT > 0 else 1.0
        if seen.source != "residuals" and abs(ratio - 1.0) > 0.2:
            out.append(
                f"the given noise {noise.sigma_nT:.3g} nT ({noise.note}) differs from the noise seen in the "
                f"data: {seen.text()}"
            )
    return out


def _confounded_warnings(cands, proj, kept, top) -> list[str]:
    """(Part of :func:`_warnings_for`.) Candidates the data can hardly tell apart: the best and another with a
    canonical correlation above 0.9 and a close delta-BIC, temperature terms and drifts on a record whose
    temperature follows time, and the pairs of effects known to leave the same pattern."""
    out = []
    if proj is not None and len(top) >= 1:
        best = top[0]
        for other in cands[1:8]:
            if other.effect == best.effect or other.delta_bic >= DELTA_BIC_THRESHOLD:
                continue
            try:
                cc = proj.canonical_correlation(best.columns, other.columns)
            except (np.linalg.LinAlgError, ValueError):
                continue
            gap = other.delta_bic - best.delta_bic
            if cc > 0.9 and gap < max(10.0, 0.1 * abs(best.delta_bic)):
                out.append(
                    f"{best.label} and {other.label} are confounded in these data (canonical correlation "
                    f"{cc:.2f}): the data can hardly tell them apart"
                )
    names = {c.effect for c in top}
    if kept.temperature_C is not None and kept.time_s is not None:
        rho = abs(np.corrcoef(kept.temperature_C, kept.time_s)[0, 1])
        temp = names & {"temperature_bias", "temperature_scale"}
        timed = names & {"bias_drift", "reference_drift"}
        if rho > 0.9 and (temp or timed):
            out.append(
                f"temperature follows time (|corr| = {rho:.2f}, e.g. a warm-up): temperature effects and drifts "
                "are confounded; record with the temperature varying independently of time to separate them"
            )
    if cands and cands[0].effect == "nonlinearity_cubic" and cands[0].delta_bic < DELTA_BIC_THRESHOLD:
        out.append(
            "nonlinearity_cubic cannot be told from cross-field coupling l_j B_j (|B|^2 - B_j^2) at constant "
            "|B|; both leave the same degree-4 direction pattern"
        )
    if top and top[0].effect in ("axis_timing_skew", "hysteresis") and {"axis_timing_skew", "hysteresis"} <= names:
        out.append(
            "axis_timing_skew and hysteresis both depend on the direction of rotation; vary the rotation "
            "speed to separate them (a delay scales with speed, hysteresis does not)"
        )
    return out


def _channel_warnings(kept, fit) -> list[str]:
    """(Part of :func:`_warnings_for`.) The effects that need the attitude and were not tested: samples without
    it, or an array without attitude columns."""
    out = []
    present = attitude_present(kept) if kept.attitude_wxyz is not None else None
    if present is not None and not present.all():
        needing = [
            n
            for n, cls in EFFECTS.items()
            if "attitude" in getattr(cls, "channels", ()) and kept.n_sensors >= cls.min_sensors
        ]
        if needing:
            missing = np.zeros(fit.mask.size, bool)
            missing[np.flatnonzero(fit.mask)[~present]] = True
            out.append(
                f"{int(missing.sum())} of the {kept.n_samples} samples fitted have no attitude ({row_runs(missing)}): "
                f"{', '.join(needing)} {'was' if len(needing) == 1 else 'were'} not tested (a gradient fixed in the "
                "world has no predicted value where the array's rotation is unknown); exclude those samples to test it"
            )
    if kept.n_sensors > 1 and kept.attitude_wxyz is None:
        out.append(
            "no attitude columns (qw, qx, qy, qz): site_gradient cannot be tested; the array alone sees a site "
            "gradient only as a tensor rotating with it (constant invariants) and as biases"
        )
    return out


class _HeldOut:
    """Held-out judgement of refitted candidates (:mod:`magcal.fitting.validation`) on the samples a fit used (a
    :class:`magcal.diagnosis.selection.HeldOutJudge`).

    The base model of each round is validated once per scheme and reused for every candidate of that round,
    warm-started from the round's full-record fit. A candidate's held-out fits start where its refit starts, from
    the calibration its score test predicts (:func:`~magcal.diagnosis.scores.candidate_start`), not from the
    refit's result: they need nothing the refit computes, so on a machine with cores to spare they run beside it
    instead of after it (the one-step estimator from either start reaches the training samples' minimum to first
    order: the held-out RMS agree to about 1e-4 relative).
    """

    def __init__(self, kept, fit0, pool=None):
        self.kept = kept
        self.pool = pool  # sharing the whole dataset, of which kept holds fit0.mask
        self.kept_mask = None if fit0.mask.all() else fit0.mask
        self.reference = _reference_override(fit0)
        self.masks = {scheme: _validation.holdout_masks(kept, scheme) for scheme in _validation.SCHEMES}
        self.bases = {}  # (id of the base fit, scheme) -> Future of its held-out fit
        self._lock = threading.Lock()
        self.schemes = {}

    def base(self, fit, scheme):
        """The held-out fit of the round's base model ``fit`` on ``scheme``'s split (computed once)."""
        return self._base(fit, scheme)

    def _base(self, fit, scheme):
        # made once, whichever thread asks first (prepare's, ahead of time, or the judgement's); another asking
        # meanwhile waits for it, and a failure is met again by every caller
        key = (id(fit), scheme)
        with self._lock:
            made = self.bases.get(key)
            mine = made is None
            if mine:
                made = self.bases[key] = Future()
        if mine:
            try:
                made.set_result(self._validate(fit.model, fit.calibration, scheme))
            except BaseException as exc:
                made.set_exception(exc)
        return made.result()

    def _validate(self, model, init, scheme):
        args = (self.kept_mask, model, init, self.reference, scheme, self.masks[scheme])
        if self.pool is None:
            return validate_task(self.kept, None, *args[1:])
        return self.pool.remote(validate_task, *args, local=lambda: validate_task(self.kept, None, *args[1:]))

    def prepare(self, fit, scheme):
        """:meth:`base`, ahead of time; a failure is left for :meth:`base` to meet again and report."""
        try:
            self._base(fit, scheme)
        except (CalibrationError, MagcalError, np.linalg.LinAlgError):
            pass

    def with_effect(self, base_fit, c, scheme):
        """The held-out fit on ``scheme``'s split of the round's base model ``base_fit`` with the candidate's
        effect added, from the candidate's predicted start."""
        return self._validate(candidate_model(base_fit, c), candidate_start(base_fit, c), scheme)

    def judge(self, base_fit, c, fitted=None) -> str | None:
        """Fill the candidate's held-out figures and ``holds``; append to its evidence. Returns a warning when
        the gain does not hold. ``fitted``: the candidate's held-out fits per scheme (:meth:`with_effect`),
        when already made."""
        comparisons = {}
        for scheme in _validation.SCHEMES:
            base = self._base(base_fit, scheme)
            comparisons[scheme] = _validation.compare(
                self.kept,
                added_effect=c.label,
                scheme=scheme,
                base=base,
                with_model=candidate_model(base_fit, c),
                with_init=candidate_start(base_fit, c),
                reference_total_nT=self.reference,
                with_effect=(fitted or {}).get(scheme),
            )
            if base_fit is not None and scheme not in self.schemes:
                self.schemes[scheme] = {
                    "n_train": base.n_train,
                    "n_test": base.n_test,
                    "base_held_out_rms_nT": base.held_out_rms_nT,
                    "base_in_sample_rms_nT": base.in_sample_rms_nT,
                }
        blocks, later = comparisons["blocks"], comparisons["later"]
        c.held_out_before_nT = float(blocks.base.held_out_rms_nT)
        c.held_out_after_nT = float(blocks.with_effect.held_out_rms_nT)
        c.later_before_nT = float(later.base.held_out_rms_nT)
        c.later_after_nT = float(later.with_effect.held_out_rms_nT)
        # describes this record: the blocks' gain holds; an instrument term must also not make the later stretch
        # worse (it stays in the calibration); a record-only term is dropped there, so the later stretch only says
        # whether it improves the calibration for new data
        c.holds = _validation.judge(blocks) and (c.record_only or later.does_not_rise)
        c.transfers = _validation.transfers(later, c.record_only)
        c.confounded = _confounded(self.kept, c)
        if c.confounded:
            c.transfers = False  # the later stretch cannot tell: it follows the same clock
        held = (
            f"held-out {c.held_out_before_nT:.4g} -> {c.held_out_after_nT:.4g} nT (blocks), later "
            f"{c.later_before_nT:.4g} -> {c.later_after_nT:.4g} nT (fitted before, applied as magcal apply does"
            + (": record-only terms dropped)" if later.with_effect.dropped else ")")
        )
        if blocks.base.held_out_consistency_rms_nT is not None:
            held += (
                f", inter-sensor consistency (blocks) {blocks.base.held_out_consistency_rms_nT:.4g} -> "
                f"{blocks.with_effect.held_out_consistency_rms_nT:.4g} nT"
            )
        if c.holds:
            if c.record_only:
                carries = (
                    "; fitted with the base terms it improves the calibration kept for new data"
                    if c.transfers
                    else "; dropped on new data, it leaves no measurably better calibration (later stretch)"
                )
            else:
                carries = (
                    "; carries to new data (the later stretch does not get worse)"
                    if c.transfers
                    else "; makes the calibration worse on the later stretch"
                )
            if c.confounded:
                carries = f"; not advised for new data: {c.confounded}"
            c.evidence += f"; {held}: describes this record (holds on held-out data){carries}"
        else:
            why = (
                f"the blocks' RMS does not fall by {_validation.MIN_RELATIVE_GAIN:.0%}"
                if not blocks.holds
                else "the later stretch's RMS rises"
            )
            text = (
                f"in-sample {float(base_fit.rms_nT):.4g} -> {c.rms_after_nT:.4g} nT, {held}: does not hold on "
                f"held-out data ({why})"
            )
            c.evidence += "; " + text
            return f"{c.label}: {text}; not recommended"
        return None


def validate_task(dataset, kept_mask, model, init, reference_total_nT, scheme, masks):
    """(A worker's task.) The held-out fit of ``model`` from ``init`` on the samples ``kept_mask`` of ``dataset``
    (None: all), split by ``masks`` (:func:`magcal.fitting.validation.validate`)."""
    return _validation.validate(
        _parallel.subset(dataset, kept_mask),
        model=model,
        init=init,
        reference_total_nT=reference_total_nT,
        scheme=scheme,
        masks=masks,
    )


def _undetermined(fit, directions) -> str | None:
    """Why the fitted base calibration is not determined by the data, or None.

    An effect can only be judged against a base calibration the data fix. Two signs that they do not: the
    directions cover too little of the sphere (thinnest direction spread below
    :data:`magcal.geometry.ellipsoid.WEAK_DIRECTION_SPREAD`: the calibration extrapolates), and, with such weak
    coverage, a fitted field magnitude outside the geomagnetic range (the scale and the field trade off along the
    directions not seen). Then adding a term mostly moves the poorly fixed base parameters, and no candidate is
    recommended. With good coverage a field outside the range is a units question (:func:`_units_question`), and
    the effects are still judged: a common scale error does not change which effect is missing.
    """

    reasons = []
    for s, u in enumerate(directions):
        spread = direction_spread(u).thinnest_spread
        if spread < WEAK_DIRECTION_SPREAD:
            reasons.append(f"sensor {s + 1}: weak coverage (thinnest direction spread {spread:.3f}, full sphere 0.33)")
    field_nT = fit.calibration.reference_total_nT
    lo, hi = EARTH_FIELD_RANGE_nT
    if reasons and fit.reference_kind == "fitted" and field_nT and not lo <= field_nT <= hi:
        reasons.append(f"fitted field {field_nT / 1000:.3g} uT, outside the Earth's {lo / 1000:.0f}-{hi / 1000:.0f} uT")
    return "; ".join(reasons) or None


#: Scale factors tried, simplest first, when a well-covered record's fitted field lies outside the Earth's range
#: (a logger's LSB off by a power of two or ten, gauss or milligauss read as microtesla...).
UNIT_FACTORS = (0.5, 2.0, 0.1, 10.0, 0.25, 4.0, 0.01, 100.0, 0.001, 1000.0, 1e-5, 1e5, 1e-6, 1e6)


def _units_question(fit, directions) -> str | None:
    """The units or LSB question a well-covered record raises when its fitted field magnitude lies outside the
    Earth's range (:data:`magcal.checks.quality.EARTH_FIELD_RANGE_nT`), with the simplest scale factor that
    brings it inside; None otherwise (the field is given, in range, or the coverage is weak: :func:`_undetermined`)."""
    field_nT = fit.calibration.reference_total_nT
    lo, hi = EARTH_FIELD_RANGE_nT
    if fit.reference_kind != "fitted" or not field_nT or lo <= field_nT <= hi:
        return None
    if any(direction_spread(u).thinnest_spread < WEAK_DIRECTION_SPREAD for u in directions):
        return None
    factor = next((f for f in UNIT_FACTORS if lo <= f * field_nT <= hi), None)
    hint = f"x{factor:g} gives {factor * field_nT / 1000:.3g} uT; " if factor is not None else ""
    return (
        f"the fitted field is {field_nT / 1000:.3g} uT, outside the Earth's {lo / 1000:.0f}-{hi / 1000:.0f} uT, although "
        f"the directions cover the sphere: the units or the LSB of the readings are likely off ({hint}pass --units "
        "or --lsb with the right scale). A common scale does not change which effect is missing: the effects are "
        "judged as they are"
    )


def _changes_the_field(base_fit, c) -> str | None:
    """Why a candidate's refit is not a finding because it moves the fitted field magnitude out of the Earth's
    range or by more than 5 % (the term trades off with the base parameters the data barely fix), or None."""

    if c.fit is None or base_fit.reference_kind != "fitted":
        return None
    before, after = base_fit.calibration.reference_total_nT, c.fit.calibration.reference_total_nT
    if not before or not after:
        return None
    lo, hi = EARTH_FIELD_RANGE_nT
    if lo <= before <= hi and (not lo <= after <= hi or abs(after / before - 1.0) > 0.05):
        return (
            f"{c.label}: its refit moves the fitted field from {before / 1000:.4g} to {after / 1000:.4g} uT: "
            "the term trades off with the base calibration; not recommended"
        )
    return None


_FAILURES = (CalibrationError, MagcalError, np.linalg.LinAlgError)


def _attempt(call):
    """``call()``, or the failure it raised (a failed held-out fit is reported, not raised)."""
    try:
        return call()
    except _FAILURES as exc:
        return exc


def _to_validate(c) -> bool:
    """Whether a candidate's held-out fits are wanted: refitted, supported in-sample, not yet judged, physical, and a
    term that can predict a held-out block (:func:`_in_sample_only`)."""
    return (
        c.refitted
        and c.delta_bic < DELTA_BIC_THRESHOLD
        and c.fit is not None
        and c.holds is None
        and not c.not_physical
        and not _in_sample_only(c)
    )


#: A candidate judged in-sample only (:func:`_in_sample_only`) ranks before the candidates that hold on held-out data
#: when its delta-BIC is at least this multiple of the best of theirs: a series with knots every few seconds follows
#: part of anything that changes in time (a temperature bias on a smooth temperature, a nonlinearity along a slow
#: turn), so a term that holds is preferred unless the series explains clearly more (on the simulated records a
#: hidden series leads by 1.9-2.1x, a series standing in for a temperature bias and a nonlinearity by 1.45x).
SERIES_LEAD = 1.5


def _in_sample_only(c) -> bool:
    """A term that follows the record within seconds (``Effect.held_out_blocks`` False: a series with knots every
    few seconds) has nothing to say inside a held-out block of 10 s or more: it is judged in-sample by its
    delta-BIC, and ranks after the candidates that hold on held-out data unless it explains clearly more
    (:data:`SERIES_LEAD`)."""
    cls = EFFECTS.get(c.effect)
    return cls is not None and not getattr(cls, "held_out_blocks", True) and c.refitted and c.converged


def _held_out_fits(pool, held_out, base_fit, c, priority=CHAIN, skip=()) -> dict:
    """The candidate's held-out fits per scheme (:meth:`_HeldOut.with_effect`) but those in ``skip``, handed to
    ``pool`` at ``priority`` (futures; each gives the fit or its failure)."""
    return {
        scheme: pool.submit(lambda scheme=scheme: _attempt(lambda: held_out.with_effect(base_fit, c, scheme)), priority)
        for scheme in _validation.SCHEMES
        if scheme not in skip
    }


class _BesideRefits:
    """The held-out fits of a round's candidates, handed to ``pool`` beside their refits where it can.

    A candidate's held-out fits need its predicted start, not its refit (:class:`_HeldOut`). With cores to spare
    (:attr:`~magcal.diagnosis._parallel.Pool.concurrent`) those of a candidate predicted to be supported are handed
    over with its refit (:meth:`beside`, below the refits' priority), so that the refit, a few passes over the whole
    record, no longer waits for them: on many cores the diagnosis's longest chain. Once the refit has returned
    (:meth:`after`) they are cancelled if not wanted, and those not yet started are moved ahead if wanted; on one
    core they are handed over only then. :attr:`pending` (by label, futures per scheme) goes to
    :func:`_judge_round`. ``held_out`` None: nothing is validated.
    """

    def __init__(self, pool, held_out, base_fit):
        self.pool, self.held_out, self.base_fit = pool, held_out, base_fit
        self.pending: dict = {}
        self._lock = threading.Lock()

    def beside(self, c) -> None:
        """(``_confirm``'s ``beside_refit``.)"""
        if self.held_out is None or not self.pool.concurrent or c.predicted_delta_bic >= DELTA_BIC_THRESHOLD:
            return
        with self._lock:
            self.pending[c.label] = _held_out_fits(self.pool, self.held_out, self.base_fit, c, SHARED)

    def after(self, c) -> None:
        """(Called from ``_confirm``'s ``after_refit``, in the refit's thread.)"""
        if self.held_out is None:
            return
        with self._lock:
            if not _to_validate(c):
                _cancel(self.pending.pop(c.label, {}))
                return
            handed = self.pending.get(c.label, {})
            started = [s for s, f in handed.items() if not f.cancel()]
            self.pending[c.label] = {
                **handed,
                **_held_out_fits(self.pool, self.held_out, self.base_fit, c, CHAIN, started),
            }

    def settle(self, cands) -> dict:
        """:attr:`pending`, less the fits of candidates whose refit failed (it never said whether they were
        wanted)."""
        for c in cands:
            if c.label in self.pending and not _to_validate(c):
                _cancel(self.pending.pop(c.label))
        return self.pending


def _cancel(futures) -> None:
    """Cancel the held-out fits ``futures`` (per scheme) not yet started; those under way finish, unread."""
    for future in futures.values():
        future.cancel()


def _refit_supports(c) -> bool:
    """Whether the candidate's refit converged and supports it in-sample with physical parameters: the forward
    selection may take it next."""
    return c.converged and c.delta_bic < DELTA_BIC_THRESHOLD and c.fit is not None and not c.not_physical


def _predicted_best(cands):
    """The candidate whose score test predicts the lowest delta-BIC, or None."""
    return min(cands, key=lambda c: c.predicted_delta_bic) if cands else None


def _in_sample_best(cands):
    """The refitted, converged candidate with the lowest delta-BIC below the threshold, or None: the one the
    forward selection takes first unless the held-out judgement refutes it or ranks another above it."""
    supported = [c for c in cands if _refit_supports(c) and c.refitted]
    return min(supported, key=lambda c: c.delta_bic) if supported else None


def _judge_round(held_out, base_fit, cands, notes, pool, pending=None, fit_notes=None):
    """Validate the supported refitted candidates of a round (:func:`_held_out_round`); re-rank them
    (:func:`_ranked`). ``pending``: the held-out fits already handed to ``pool`` (by candidate label, futures per
    scheme, :func:`_held_out_fits`). ``fit_notes``: a list the held-out fits' notes are added to, in the
    candidates' order (whichever thread made them)."""
    if held_out is not None:
        todo = [c for c in cands if _to_validate(c)]
        if todo:
            warnings, said = _held_out_round(held_out, base_fit, todo, pool, pending)
            notes.extend(warnings)
            if fit_notes is not None:
                fit_notes.extend(said)
    return _ranked(cands)


def _held_out_round(held_out, base_fit, todo, pool, pending) -> tuple[list, list]:
    """(Part of :func:`_judge_round`.) The held-out judgement of the candidates ``todo``: each one's ``holds``.
    Returns the warnings (a gain that does not hold, a held-out fit that failed) and what the held-out fits said
    (their notes, in the candidates' order)."""
    warnings: list = []
    said: list = []
    # every held-out fit of the round side by side on the machine's cores (numpy releases the interpreter in its
    # loops): the base model's per scheme, shared by every candidate, and each candidate's per scheme (those
    # handed over when its refit returned already under way); then the comparisons, in the candidates' order
    pending = dict(pending or {})
    bases = [
        pool.submit(lambda scheme=scheme: _attempt(lambda: held_out.base(base_fit, scheme)), SHARED)
        for scheme in _validation.SCHEMES
    ]
    for c in todo:
        if c.label not in pending:
            pending[c.label] = _held_out_fits(pool, held_out, base_fit, c)
    for future in bases:
        _add_fit_notes(said, future.result())
    for c in todo:
        fitted = {scheme: future.result() for scheme, future in pending[c.label].items()}
        for f in fitted.values():
            _add_fit_notes(said, f)
        failed = next((f for f in fitted.values() if isinstance(f, Exception)), None)
        try:
            if failed is not None:
                raise failed
            warning = held_out.judge(base_fit, c, fitted)
        except _FAILURES as exc:
            warning = f"held-out validation of {c.label} failed ({exc}); judged in-sample only"
        if warning:
            warnings.append(warning)
    return warnings, said


def _ranked(cands) -> list:
    """(Part of :func:`_judge_round`.) The candidates re-ranked: the refitted ones that hold on held-out data by
    delta-BIC, then the other refitted ones (not validated, or not holding) by delta-BIC, then the predictions; a
    series judged in-sample only leads when it clearly explains more (:data:`SERIES_LEAD`)."""
    held = sorted([c for c in cands if c.refitted and c.holds], key=lambda c: c.delta_bic)
    series = sorted([c for c in cands if c.refitted and not c.holds and _in_sample_only(c)], key=lambda c: c.delta_bic)
    rest = sorted(
        [c for c in cands if c.refitted and not c.holds and not _in_sample_only(c)], key=lambda c: c.delta_bic
    )
    # a series judged in-sample leads only when it clearly explains more than the best term that holds (or, when
    # none was found to hold, e.g. a record too short to hold samples out, than the best of the others)
    top = (held or rest)[:1]
    lead = [c for c in series if not top or c.delta_bic < SERIES_LEAD * top[0].delta_bic]
    trailing = [c for c in series if c not in lead]
    unrefitted = [c for c in cands if not c.refitted]
    if held:
        return lead + held + trailing + rest + unrefitted
    return lead + sorted(rest + trailing, key=lambda c: c.delta_bic) + unrefitted


def _add_fit_notes(fit_notes, outcome) -> None:
    """Add the notes of a fit's outcome (a FitResult, a ValidationResult or the failure it raised) to
    ``fit_notes`` (a list, or None to drop them)."""
    if fit_notes is None or outcome is None or isinstance(outcome, BaseException):
        return
    if isinstance(outcome, _validation.ValidationResult):
        fit_notes.extend(outcome.fit_notes)
    else:
        fit_notes.extend(outcome.notes)


def diagnose(
    dataset,
    result=None,
    model=None,
    top=3,
    effects=None,
    candidates=None,
    max_effects=2,
    progress=None,
    validate=True,
    noise_nT=None,
    scheduler=None,
    workers=None,
) -> Diagnosis:
    """Diagnose a calibration model on a dataset: structure left, ranked candidate effects, verdict.

    The diagnosis runs in named stages over one :class:`DiagnosisContext`: :func:`_score` (the score tests, and
    the base fit's own analyses handed to the pool), :func:`_refit` (the best candidates refitted),
    :func:`_validate` (their held-out judgement), :func:`_judge` (the forward selection and the verdict) and
    :func:`_explain` (summary, warnings, evidence: the :class:`Diagnosis`).

    Parameters
    ----------
    dataset : Dataset
    result : FitResult or CalibrationResult, optional
        The fitted model to diagnose. Without it the model (``model``, or the base model plus ``effects``) is
        fitted with :func:`magcal.fitting.pipeline.calibrate`.
    model : Model, optional
        Model to fit when ``result`` is not given.
    top : int
        Number of distinct candidate effects confirmed by refitting.
    effects : sequence of str, optional
        Effects (``NAME`` or ``NAME:SENSOR``) to add to the base model when neither ``result`` nor ``model`` is
        given (as ``magcal diagnose --effects``).
    candidates : sequence of str, optional
        Restrict the score tests to these catalogue names (default: every effect whose channels are present).
    max_effects : int
        Most effects added one after the other to explain the residuals (greedy forward selection).
    progress : callable, optional
        ``progress(message, fraction)``.
    validate : bool
        Judge the supported candidates on held-out samples (module docstring); skipped, with a note, when the
        record is too short to split (:func:`magcal.fitting.validation.split_problem`).
    noise_nT : float, optional
        Noise per axis in nT given by the user; takes precedence over the dataset's ``noise_nT`` and over any
        estimate (:func:`magcal.checks.noise.estimate_noise`).
    scheduler : str or distributed.Client, optional
        Run the independent fits (refits, held-out fits, chunks of the score tests) on this Dask cluster
        (``tcp://host:8786``, or a client); by default they run on this machine's cores, in worker processes
        for a large record and on threads for a small one (:mod:`magcal.diagnosis._parallel`). The result is
        the same wherever they run.
    workers : int, optional
        Cores to use on this machine (default: every one; :data:`magcal.diagnosis._parallel.PARALLEL_FITS`).

    Returns
    -------
    Diagnosis
        Its ``notes`` hold what its fits said; never raised as warnings here (:func:`magcal.diagnose` does).
    """
    t_start = _time.perf_counter()
    report = progress_reporter(progress)
    fit0, fit_notes = _model_fit(dataset, result, model, effects, report)
    kept = _kept(dataset, fit0)
    directions, fields = _sensor_directions(kept, fit0)

    report("score tests", 0.2)
    in_play = [fit0.model] + [cls for name, cls in EFFECTS.items() if candidates is None or name in candidates]
    warm = (refit_task, validate_task, gram_task)
    with Pool(dataset, scheduler=scheduler, effects=in_play, warm=warm, workers=workers) as pool:
        if scheduler is not None and pool.backend != "dask":
            fit_notes.append(_notes.Note(_parallel.ELSEWHERE_NOTE, UserWarning, "diagnose"))
        for text in (pool.removed, pool.note):
            if text:
                fit_notes.append(_notes.Note(text, UserWarning, "diagnose"))
        ctx = DiagnosisContext(
            dataset=dataset,
            kept=kept,
            fit0=fit0,
            directions=directions,
            fields=fields,
            pool=pool,
            report=report,
            options=DiagnosisOptions(top, candidates, max_effects, validate, noise_nT),
            t_start=t_start,
            fit_notes=fit_notes,
        )
        _score(ctx)
        _refit(ctx)
        _validate(ctx)
        _judge(ctx)
        return _explain(ctx)


def _model_fit(dataset, result, model, effects, report) -> tuple:
    """The fit to diagnose (``result``'s, or the model fitted here) and the notes of the fit made here (a given
    result's notes are its caller's)."""
    fit0 = _fit_of(result)
    fit_notes: list = []
    if fit0 is None:
        report("fitting the model", 0.0)
        if model is not None:
            res = calibrate(dataset, effects=list(model.effects), base_terms=model.base)
        else:
            res = calibrate(dataset, effects=list(effects or ()))
        fit0 = res.fit
        fit_notes += res.notes
    return fit0, fit_notes


# ---- the stages of the diagnosis ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class DiagnosisOptions:
    """The choices of :func:`diagnose` the stages read (its parameters of the same names)."""

    top: int
    candidates: object
    max_effects: int
    validate: bool
    noise_nT: float | None


@dataclass
class DiagnosisContext:
    """What the stages of :func:`diagnose` share, filled in as they run (score -> refit -> validate -> judge ->
    explain). Each stage reads what the ones before it set and sets its own part; work handed to the pool is
    held as futures until a stage needs it.

    Attributes
    ----------
    dataset : Dataset
        The whole record (the pool shares it).
    kept : Dataset
        The samples the diagnosed fit used.
    fit0 : FitResult
        The fit diagnosed.
    directions, fields : list of numpy.ndarray
        Per sensor the field directions (unit vectors) and magnitudes (nT) of the kept samples.
    pool : Pool
        Where the independent fits run (:mod:`magcal.diagnosis._parallel`).
    report : callable
        ``report(message, fraction)``, the progress.
    options : DiagnosisOptions
    t_start : float
        :func:`time.perf_counter` when the diagnosis began, s.
    fit_notes : list of Note
        What the diagnosis's own fits said, in order.
    ordered : bool
        Whether the kept samples are a smooth sequence in time (:func:`magcal.checks.noise.is_smooth_sequence`).
    coupled : bool
        Whether the model has inter-sensor consistency residuals.
    r0 : numpy.ndarray
        The diagnosed fit's total-field residuals on its kept samples, (n_sensors, N) nT.
    cands, proj
        The candidates (best first, re-ranked by each stage) and the first score round's projector.
    futures : dict
        The base fit's analyses handed to the pool by :func:`_score`: ``sh`` (per sensor), ``structure``,
        ``undetermined``, ``evidence`` (time, temperature, spectrum, sensors).
    fits : dict
        Refits by candidate label.
    early : _HeldOut or None
        The held-out judgement started beside the first refits.
    ahead : dict
        The first forward-selection round's work started at a refit (label -> (structure, scores) futures).
    pending : dict
        Held-out fits handed to the pool beside the first refits (label -> futures per scheme).
    sh_stats : list of dict
        Per sensor the spherical-harmonic analysis of ``r0``.
    held_out : _HeldOut or None
        The held-out judgement used (None: not validated).
    skipped : str or None
        Why the held-out judgement was skipped.
    validation_notes : list of str
        Warnings of the held-out judgement and of the base checks.
    undetermined, units : str or None
        :func:`_undetermined` and :func:`_units_question` of the base fit.
    noise0, structure0, stats0
        Noise, significant structure and test statistics of the diagnosed fit's residuals.
    explained, chosen : list
        Labels and candidates the forward selection took, in order.
    current : FitResult
        The fit with ``chosen`` added (``fit0`` when none).
    current_noise, remaining, stats_final
        Noise, structure and statistics of ``current``'s residuals.
    noise_final : NoiseEstimate
        The noise the verdict is stated against.
    verdict, summary : str
        Set by :func:`_judge`; :func:`_explain` adds to the summary.
    """

    dataset: Any
    kept: Any
    fit0: Any
    directions: list
    fields: list
    pool: Any
    report: Callable
    options: DiagnosisOptions
    t_start: float
    fit_notes: list
    ordered: bool = False
    coupled: bool = False
    r0: Any = None
    cands: list = field(default_factory=list)
    proj: Any = None
    futures: dict = field(default_factory=dict)
    fits: dict = field(default_factory=dict)
    early: Any = None
    ahead: dict = field(default_factory=dict)
    pending: dict = field(default_factory=dict)
    sh_stats: list = field(default_factory=list)
    held_out: Any = None
    skipped: str | None = None
    validation_notes: list = field(default_factory=list)
    undetermined: str | None = None
    units: str | None = None
    noise0: Any = None
    structure0: list = field(default_factory=list)
    stats0: list = field(default_factory=list)
    explained: list = field(default_factory=list)
    chosen: list = field(default_factory=list)
    current: Any = None
    current_noise: Any = None
    remaining: list = field(default_factory=list)
    stats_final: list = field(default_factory=list)
    noise_final: Any = None
    verdict: str = ""
    summary: str = ""


def _noise_and_structure(ctx, kept, fit, directions=None) -> tuple:
    """Noise, significant structure and test statistics of ``fit``'s residuals on its kept samples ``kept``
    (``directions``: its sensors' field directions, computed when not given)."""
    if directions is None:
        directions, _ = _sensor_directions(kept, fit)
    noise = estimate_noise(
        kept, fit.residuals_nT[:, fit.mask], fit.n_params, ctx.ordered, noise_nT=ctx.options.noise_nT
    )
    return (noise,) + tuple(_structure_tests(kept, fit, noise, ctx.ordered, directions))


def _next_round(ctx, c, scores) -> tuple:
    """The forward selection's round if it takes ``c``, handed to the pool: (structure, score tests) futures;
    ``scores``: whether that round will look for a further effect (else None for them)."""
    kept_c = _kept(ctx.dataset, c.fit)
    structure = ctx.pool.submit(lambda: _noise_and_structure(ctx, kept_c, c.fit), SHARED)
    if not scores:
        return structure, None
    return structure, ctx.pool.submit(
        lambda: _score_round(ctx.dataset, kept_c, c.fit, ctx.options.candidates, previous=c, pool=ctx.pool), SHARED
    )


def _score(ctx: DiagnosisContext) -> None:
    """Stage 1, score: the first round's score tests (:func:`~magcal.diagnosis.scores._score_round`); what depends
    on the base fit alone (its noise and structure, spherical harmonics, whether it is determined, the evidence) is
    handed to the pool to be worked out while the refits run."""
    kept, fit0, pool, directions = ctx.kept, ctx.fit0, ctx.pool, ctx.directions
    ctx.cands, ctx.proj, _ = _score_round(ctx.dataset, kept, fit0, ctx.options.candidates, pool=pool)
    ctx.coupled = fit0.consistency_residuals_nT is not None
    ctx.ordered = ordered = is_smooth_sequence(kept)
    ctx.r0 = r0 = fit0.residuals_nT[:, fit0.mask]
    ctx.futures["sh"] = [
        pool.submit(lambda s=s: sh_analysis(directions[s], r0[s], max_samples=SH_MAX_SAMPLES), SHARED)
        for s in range(kept.n_sensors)
    ]
    ctx.futures["structure"] = pool.submit(lambda: _noise_and_structure(ctx, kept, fit0, directions), SHARED)
    ctx.futures["undetermined"] = pool.submit(lambda: _undetermined(fit0, directions), FILLER)
    ctx.futures["evidence"] = [
        pool.submit(call, FILLER)
        for call in (
            lambda: _time_evidence(kept, r0, ordered),
            lambda: _temperature_evidence(kept, r0, directions),
            lambda: [spectrum(row, kept.time_s) for row in r0] if ordered else None,
            lambda: _sensor_evidence(kept, fit0, r0, ctx.fields),
        )
    ]


def _early_held_out(ctx: DiagnosisContext):
    """The held-out judgement started beside the first refits when a candidate is predicted to be supported (the
    base model's held-out fits need the base fit alone), or None."""
    if (
        ctx.options.validate
        and any(c.predicted_delta_bic < DELTA_BIC_THRESHOLD for c in ctx.cands)
        and _validation.split_problem(ctx.kept) is None
    ):
        try:
            return _HeldOut(ctx.kept, ctx.fit0, ctx.pool)
        except MagcalError:
            return None
    return None


def _refit(ctx: DiagnosisContext) -> None:
    """Stage 2, refit: the ``top`` best distinct candidates refitted (:func:`~magcal.diagnosis.scores._confirm`),
    each candidate's evidence line written.

    Beside the refits run the base model's held-out fits and, for a candidate predicted to be supported, its own
    (:class:`_BesideRefits`); with cores to spare the next round of the candidate predicted best starts as soon as
    its refit supports it (the in-sample best, known once every refit has returned, is nearly always that one)."""
    pool, fit0, opts = ctx.pool, ctx.fit0, ctx.options
    ctx.report("refitting the best candidates", 0.4)
    early = ctx.early = _early_held_out(ctx)
    predicted_best = _predicted_best(ctx.cands) if opts.max_effects > 0 else None
    beside = _BesideRefits(pool, early, fit0)

    def after_refit(c):
        if c is predicted_best and pool.concurrent and _refit_supports(c):
            ctx.ahead[c.label] = _next_round(ctx, c, opts.max_effects >= 2)
        beside.after(c)

    ctx.cands = _confirm(
        ctx.dataset,
        fit0,
        ctx.cands,
        opts.top,
        ctx.coupled,
        ctx.fits,
        alongside=[] if early is None else [lambda s=s: early.prepare(fit0, s) for s in _validation.SCHEMES],
        pool=pool,
        after_refit=after_refit,
        beside_refit=beside.beside,
    )
    ctx.pending = beside.settle(ctx.cands)
    ctx.sh_stats = [future.result() for future in ctx.futures["sh"]]
    for c in ctx.cands:
        _add_fit_notes(ctx.fit_notes, c.fit)
    for c in ctx.cands:
        note = c.evidence  # e.g. a failed refit
        c.evidence = _evidence_line(c, _effect_extra(c, ctx.kept, fit0, ctx.directions, ctx.sh_stats))
        if note:
            c.evidence += "; " + note


def _validate(ctx: DiagnosisContext) -> None:
    """Stage 3, validate: the held-out judgement of the supported refits (:func:`_judge_round`, which re-ranks the
    candidates), then the checks of the base fit itself: whether the data determine it (:func:`_undetermined`),
    its units (:func:`_units_question`), and a refit that moves the fitted field (:func:`_changes_the_field`)."""
    opts, kept, fit0 = ctx.options, ctx.kept, ctx.fit0
    skipped = None if opts.validate else "not asked for (validate=False, --no-validate)"
    if opts.validate and any(c.refitted and c.delta_bic < DELTA_BIC_THRESHOLD for c in ctx.cands):
        skipped = _validation.split_problem(kept)
    held_out = None
    if opts.validate and skipped is None:
        ctx.report("held-out validation of the supported candidates", 0.5)
        try:
            held_out = ctx.early if ctx.early is not None else _HeldOut(kept, fit0, ctx.pool)
        except MagcalError as exc:
            skipped = str(exc)
    if skipped and opts.validate:
        ctx.validation_notes.append(f"held-out validation skipped: {skipped}; the candidates are judged in-sample only")
    ctx.held_out, ctx.skipped = held_out, skipped

    # the first round of the forward selection (the structure of the chosen fit's residuals, the next score
    # tests), started at the in-sample best's refit while the held-out fits run: used only if the judgement keeps
    # that candidate first (they are then what the selection would compute, from the same inputs), else computed
    # anew
    guess = _in_sample_best(ctx.cands) if opts.max_effects > 0 else None
    if guess is not None and guess.label not in ctx.ahead:
        ctx.ahead[guess.label] = _next_round(ctx, guess, opts.max_effects >= 2)
    pending = ctx.pending if held_out is ctx.early else None
    ctx.cands = _judge_round(held_out, fit0, ctx.cands, ctx.validation_notes, ctx.pool, pending, ctx.fit_notes)
    _check_base(ctx)


def _check_base(ctx: DiagnosisContext) -> None:
    """(Part of :func:`_validate`.) The base fit's own checks; a candidate whose refit moves the fitted field is
    not recommended."""
    ctx.undetermined = ctx.futures["undetermined"].result()
    ctx.units = _units_question(ctx.fit0, ctx.directions)
    if ctx.units:
        ctx.validation_notes.append(ctx.units)
    if ctx.undetermined:
        ctx.validation_notes.append(
            f"the base calibration is not determined by these data ({ctx.undetermined}): no effect "
            "is recommended until the record covers more directions"
        )
    for c in ctx.cands:
        changed = _changes_the_field(ctx.fit0, c)
        if changed and c.holds is not False:
            c.holds = False
            c.evidence += "; " + changed
            ctx.validation_notes.append(changed)


def _judge(ctx: DiagnosisContext) -> None:
    """Stage 4, judge: the forward selection (:func:`_select`) and the verdict with its summary
    (:func:`_verdict`)."""
    # noise and structure of the model as given
    ctx.noise0, ctx.structure0, ctx.stats0 = ctx.futures["structure"].result()
    _select(ctx)
    _verdict(ctx)


def _select(ctx: DiagnosisContext) -> None:
    """Greedy forward selection (:func:`magcal.diagnosis.selection.forward_selection`) while the best candidate is
    recommendable: each round takes the best, then scores, refits and judges held out the candidates beside it
    (:func:`_further_round`). Sets ``explained``, ``chosen``, ``current`` and the noise and structure of
    ``current``'s residuals."""
    ctx.current, ctx.current_noise = ctx.fit0, ctx.noise0
    ctx.remaining, ctx.stats_final = ctx.structure0, ctx.stats0
    # this round's work, started ahead: the first round's at the refit of the candidate predicted best or once the
    # in-sample best is known, a later one's at the refit of the previous round's candidate
    state: dict = {"ahead": ctx.ahead}

    def eligible(c) -> bool:
        return c.recommendable and c.delta_bic < DELTA_BIC_THRESHOLD and not ctx.undetermined

    def pick(cands):
        best = next((c for c in cands if eligible(c)), None)
        return best if best is not None and best.fit is not None else None

    def take(step, best, cands) -> None:
        ctx.explained.append(best.label)
        ctx.chosen.append(best)
        ctx.current = best.fit
        state["kept"] = kept_c = _kept(ctx.dataset, ctx.current)
        structure, state["scores"] = state["ahead"].get(best.label, (None, None))
        if structure is None:  # beside the scores
            structure = ctx.pool.submit(lambda k=kept_c, c=ctx.current: _noise_and_structure(ctx, k, c), SHARED)
        state["structure"] = structure

    def further(step, best):
        found = _further_round(ctx, step, best, state["kept"], state["scores"], state["structure"])
        if found is None:
            return None
        cands, state["ahead"] = found
        return cands

    forward_selection(lambda: ctx.cands, pick, take, further, ctx.options.max_effects)
    if "structure" in state:  # the noise and structure of the last fit taken
        ctx.current_noise, ctx.remaining, ctx.stats_final = state["structure"].result()


def _further_round(ctx: DiagnosisContext, step, best, kept_c, ahead_scores, structure_c):
    """One round of :func:`_select` after it took ``best`` (its fit ``ctx.current`` on the samples ``kept_c``):
    score tests for a further effect, refits and held-out judgement of the supported ones. Returns the round's
    candidates re-ranked and the next round's work started ahead (by label), or None when no candidate is
    predicted to be supported. Sets the noise and structure of ``current``'s residuals (``structure_c``)."""
    pool, held_out, current = ctx.pool, ctx.held_out, ctx.current
    ctx.report("looking for a further effect", 0.6 + 0.2 * step)
    if ahead_scores is not None:
        more, _, _ = ahead_scores.result()
    else:
        more, _, _ = _score_round(ctx.dataset, kept_c, current, ctx.options.candidates, previous=best, pool=pool)
    more = [c for c in more if c.predicted_delta_bic < DELTA_BIC_THRESHOLD]
    if not more:
        ctx.current_noise, ctx.remaining, ctx.stats_final = structure_c.result()
        return None
    # as in the first round, with cores to spare: the held-out fits of the candidate and of this round's base
    # model run beside its refit, and the next round's work starts when the refit supports it (the structure
    # of the chosen fit's residuals, still running, is not waited for until then)
    round_beside = _BesideRefits(pool, held_out, current)
    round_ahead: dict = {}
    scores = step + 2 < ctx.options.max_effects

    def after(c):
        if pool.concurrent and _refit_supports(c):
            round_ahead[c.label] = _next_round(ctx, c, scores)
        round_beside.after(c)

    base_ahead = (
        [lambda s=s, base=current: held_out.prepare(base, s) for s in _validation.SCHEMES]
        if held_out is not None and pool.concurrent
        else []
    )
    more = _confirm(
        ctx.dataset,
        current,
        more,
        1,
        ctx.coupled,
        ctx.fits,
        base_ahead,
        pool=pool,
        after_refit=after,
        beside_refit=round_beside.beside,
    )
    for c in more:
        _add_fit_notes(ctx.fit_notes, c.fit)
    pending = round_beside.settle(more)
    ctx.current_noise, ctx.remaining, ctx.stats_final = structure_c.result()
    judged = _judge_round(held_out, current, more, ctx.validation_notes, pool, pending, fit_notes=ctx.fit_notes)
    return judged, round_ahead


def _verdict(ctx: DiagnosisContext) -> None:
    """(Part of :func:`_judge`.) The verdict, its summary and the noise it is stated against."""
    fit0, noise0, explained = ctx.fit0, ctx.noise0, ctx.explained
    supported0 = [c for c in ctx.cands if c.delta_bic < DELTA_BIC_THRESHOLD and c.holds is not False]
    ctx.noise_final = ctx.current_noise if explained else noise0
    at_floor = _within_floor(ctx.remaining if explained else ctx.structure0)
    small_left = ""
    if at_floor is None and explained:
        at_floor = _rms_at_floor(ctx)
        small_left = _describe(ctx.remaining) if at_floor is not None else ""
    if not ctx.structure0 and not supported0:
        ctx.verdict = "adequate"
        ctx.summary = (
            f"no significant structure: the residuals ({fit0.rms_nT:.3g} nT RMS) look like noise of "
            f"{noise0.sigma_nT:.3g} nT ({noise0.floor_words()})"
        )
    elif explained and (not ctx.remaining or at_floor is not None):
        ctx.verdict = "missing_effect"
        ctx.summary = _missing_summary(ctx)
        if at_floor is not None:
            ctx.summary += f" (at the noise floor within {100 * at_floor:.0f} %)"
        if small_left:
            ctx.summary += f"; what structure is left is smaller than the noise ({small_left})"
    elif not explained and at_floor is not None and not ctx.undetermined:
        ctx.verdict = "adequate"
        ctx.summary = (
            f"at the noise floor within {100 * at_floor:.0f} %: the residuals ({fit0.rms_nT:.3g} nT RMS) exceed the "
            f"floor of noise {noise0.sigma_nT:.3g} nT ({noise0.floor_words()}) by no more, with no structure in "
            "time or over the field direction, and no catalogue term that holds on held-out data brings them lower"
        )
    else:
        ctx.verdict = "unexplained"
        ctx.summary = _unexplained_summary(ctx)
    if ctx.units:
        ctx.summary = f"{ctx.units.split('. ')[0]}; {ctx.summary}"


def _within_floor(structures) -> float | None:
    """The largest excess of the RMS over the floor (a fraction) when every structure left is such an excess of
    at most :data:`AT_FLOOR_FRACTION`, else None."""
    if not structures or any(st.kind != "excess" for st in structures):
        return None
    excess = max(float(np.sqrt(st.size)) - 1.0 for st in structures)
    return excess if excess <= AT_FLOOR_FRACTION else None


def _rms_at_floor(ctx: DiagnosisContext) -> float | None:
    """After the chosen terms: the largest excess of a sensor's RMS over its floor (a fraction) when it is at most
    :data:`AT_FLOOR_FRACTION` on every sensor, else None; None also when the floor is the residual itself (no
    independent estimate). Structure the tests still find is then smaller than the noise: on a long record they find
    a few percent of the variance (the HMC5883L record's first half with its offset series: 151 nT against a floor
    of 153 nT, a direction pattern of 34 nT and a Durbin-Watson of 1.88 left), which no term would be advice for."""
    noise = ctx.current_noise
    if noise is None or noise.source == "residuals" or not ctx.stats_final:
        return None
    ratios = [st.get("variance_ratio") for st in ctx.stats_final]
    if any(r is None or not np.isfinite(r) for r in ratios):
        return None
    excess = max(float(np.sqrt(max(r, 0.0))) - 1.0 for r in ratios)
    return max(excess, 0.0) if excess <= AT_FLOOR_FRACTION else None


def _missing_summary(ctx: DiagnosisContext) -> str:
    """The summary of a ``missing_effect`` verdict."""
    explained, fit0 = ctx.explained, ctx.fit0
    summary = (
        f"missing {' and '.join(explained)}: adding {'them' if len(explained) > 1 else 'it'} brings "
        "the total-field RMS from "
        f"{fit0.rms_nT:.3g} to {ctx.current.rms_nT:.3g} nT (noise {ctx.noise_final.sigma_nT:.3g} nT)"
    )
    if ctx.coupled:
        summary += f" and the inter-sensor consistency RMS from {_consistency_rms(fit0):.3g} to {_consistency_rms(ctx.current):.3g} nT"
    return summary + _held_out_words(ctx.chosen)


def _unexplained_summary(ctx: DiagnosisContext) -> str:
    """The summary of an ``unexplained`` verdict: what is left, the best term tried, what the pattern means."""
    explained, left = ctx.explained, ctx.remaining if ctx.explained else ctx.structure0
    what = _describe(left) or "residual structure the score tests flag"
    tried = ""
    if ctx.cands and ctx.cands[0].refitted:
        b = ctx.cands[0]
        tried = (
            f"; the best catalogue term ({b.label}) only takes the RMS from {ctx.fit0.rms_nT:.3g} to "
            f"{b.rms_after_nT:.3g} nT"
        )
    summary = f"significant structure that no catalogue term brings down to the noise: {what}{tried}"
    meaning = _unexplained_meaning(left)
    if meaning:
        summary += f". {meaning}"
    if ctx.undetermined:
        summary = (
            f"the base calibration is not determined by these data ({ctx.undetermined}), so no effect can "
            f"be judged; {summary}"
        )
    if explained:
        summary += f"; {' and '.join(explained)} help(s)" + _held_out_words(ctx.chosen)
    return summary


def _explain(ctx: DiagnosisContext) -> Diagnosis:
    """Stage 5, explain: what this record holds against what is advice for a calibration, the
    warnings, the evidence, and the :class:`Diagnosis`."""
    chosen, fit0, kept = ctx.chosen, ctx.fit0, ctx.kept
    # a temperature term on a record whose temperature follows time is never advice, judged held out or not (the
    # later stretch follows the same clock)
    for c in chosen:
        c.confounded = c.confounded or _confounded(kept, c)
    holds_here = [c for c in chosen if c.record_only or c.transfers is False or c.confounded]
    summary = ctx.summary
    if holds_here:
        summary += "; " + _record_holds_words(holds_here, chosen)
    explained = [c.label for c in chosen if _advised(c)]
    partial: list = []
    if ctx.verdict != "missing_effect":
        partial, explained = explained, []
    if chosen:
        ctx.fits["+".join(c.label for c in chosen)] = ctx.current
    n_sensors = kept.n_sensors
    variance_terms = jitter_estimates(_kept(ctx.dataset, ctx.current), ctx.current)
    jitters = [jitter_words(v) for v in variance_terms if v["significant"]]
    if jitters:
        summary += "; " + "; ".join(jitters)
    return Diagnosis(
        verdict=ctx.verdict,
        summary=summary,
        effects=fit0.model.effect_labels,
        rms_nT=float(fit0.rms_nT),
        rms_per_sensor_nT=np.asarray(fit0.rms_per_sensor_nT),
        noise=ctx.noise_final,
        floor_nT=_floor(ctx.noise_final.sigma_nT, kept.n_samples, fit0.n_params / n_sensors),
        candidates=ctx.cands,
        explained_by=explained,
        partially_explained_by=partial,
        warnings=_diagnosis_warnings(ctx, explained, partial),
        structure=ctx.structure0,
        remaining=ctx.remaining,
        evidence=_evidence_of(ctx),
        result=fit0,
        fits=ctx.fits,
        elapsed_s=_time.perf_counter() - ctx.t_start,
        ran_on={"where": ctx.pool.backend, "workers": int(ctx.pool.workers)},
        rms_final_nT=float(ctx.current.rms_nT),
        validation=_validation_summary(ctx.held_out, ctx.skipped, chosen),
        notes=_notes.unique(ctx.fit_notes),
        record_holds=[c.label for c in holds_here],
        record_details=[_record_detail(c) for c in holds_here],
        variance_terms=variance_terms,
    )


def _diagnosis_warnings(ctx: DiagnosisContext, explained, partial) -> list:
    """(Part of :func:`_explain`.) The diagnosis's warnings: confounded candidates and missing channels
    (:func:`_warnings_for`), a partial explanation, glitches set aside, the held-out judgement's notes, more than
    one effect needed."""
    out = _warnings_for(ctx.cands, ctx.proj, ctx.kept, ctx.fit0, ctx.noise0, ctx.structure0)
    if partial:
        out.append(
            f"{', '.join(partial)} reduce(s) the residuals significantly but do(es) not bring them to "
            "the noise: not the (whole) explanation"
        )
    glitches = [(s + 1, st["glitches"]) for s, st in enumerate(ctx.stats_final) if st.get("glitches")]
    if glitches:
        out.append(
            "isolated samples beyond 5 sigma set aside from the structure tests (glitches or sharp "
            "motion): " + ", ".join(f"sensor {s}: {k}" for s, k in glitches)
        )
    out += ctx.validation_notes
    uniformity = _uniformity_words(ctx)
    if uniformity:
        out.append(uniformity)
    if len(explained) > 1 and ctx.verdict == "missing_effect":
        out.append(f"more than one effect was needed: {', '.join(explained)} (added in that order)")
    return out


def _uniformity_words(ctx: DiagnosisContext) -> str:
    """(Part of :func:`_diagnosis_warnings`.) "The field is not uniform where you recorded" when the base fit's
    total-field residual follows the record's positions rather than the field's direction
    (:func:`magcal.diagnosis.uniformity.field_uniformity`), or ""."""
    kept, fit0 = ctx.kept, ctx.fit0
    if kept.time_s is None or fit0.residuals_nT.shape[1] != len(fit0.mask):
        return ""
    r = np.asarray(fit0.residuals_nT, dtype=float)[:, fit0.mask]
    if r.shape[1] != kept.n_samples:
        return ""
    found = field_uniformity(
        kept, r, np.ones(kept.n_samples, bool), float(ctx.noise0.sigma_nT), directions=ctx.directions[0]
    )
    return "" if found.uniform else found.text


def _evidence_of(ctx: DiagnosisContext) -> dict:
    """(Part of :func:`_explain`.) :attr:`Diagnosis.evidence`: the plot data and statistics."""
    noise0 = ctx.noise0
    time_ev, temperature_ev, spectra, sensors_ev = [future.result() for future in ctx.futures["evidence"]]
    return {
        "time": time_ev,
        "temperature": temperature_ev,
        "direction": {"u": ctx.directions, "y": ctx.r0, "per_sensor": [dict(sh) for sh in ctx.sh_stats]},
        "spectrum": spectra,
        "sensors": sensors_ev,
        "noise": {
            "sigma_nT": noise0.sigma_nT,
            "per_sensor_nT": noise0.per_sensor_nT,
            "source": noise0.source,
            "final_sigma_nT": ctx.noise_final.sigma_nT,
            "static_noise_nT": noise0.static_noise_nT,
            "static_scatter_nT": noise0.static_scatter_nT,
            "note": noise0.note,
        },
        "tests": ctx.stats0,
    }


#: What to do about a record-only finding when recording, by catalogue name (what each effect says of itself,
#: :attr:`magcal.model.terms.Effect.when_recording`); the fallback is for a term that describes the record but does
#: not carry to later data.
WHEN_RECORDING = EffectTexts("when_recording")
WHEN_RECORDING_OTHER = (
    "it describes this record but does not carry to its later part: repeat the recording with what it depends on "
    "(temperature, rotation speed) varied independently of time, so that it can be told from a drift"
)


#: What an unexplained direction pattern without time structure means, and the recording that tells its causes apart.
UNEXPLAINED_DIRECTION = (
    "What is left is a pattern over the field direction with no structure in time: the sensor saw a field that "
    "depends on its attitude beyond what the calibration terms describe. Likely causes: the sensor moved through "
    "a non-uniform field while it was turned (near iron, a building, a vehicle: its position changed with its "
    "attitude), or a magnetised object moved with it (on the mount, in the hand, a cable or battery). To separate "
    "them: turn it in place about its own centre, away from iron; record its attitude and position; repeat the "
    "rotation elsewhere -- a non-uniform field changes with the place, an object moving with the sensor does not"
)


#: An unexplained direction pattern is read as having no time structure of its own when its size is at least this
#: share of the time correlation's (:func:`_unexplained_meaning`).
DIRECTION_OVER_TIME = 0.3


def _unexplained_meaning(structures) -> str | None:
    """:data:`UNEXPLAINED_DIRECTION` when the structure left is a direction pattern (spherical-harmonic degree 3
    or more) with no structure in time of its own; None otherwise.

    Along a turned trajectory a direction pattern also correlates the residuals in time (the attitude changes
    smoothly), so "no time structure" means: the pattern is at least as large as any periodic component and at
    least :data:`DIRECTION_OVER_TIME` of the time correlation (a drift left in the residuals gives a time
    correlation ten times its direction pattern; a degree-4 pattern about twice)."""

    def size(kind):
        return max((float(s.size) for s in structures if s.kind == kind), default=0.0)

    direction = size("direction")
    if direction <= 0 or size("consistency_time") > 0:
        return None
    if direction >= size("periodic") and direction >= DIRECTION_OVER_TIME * size("time"):
        return UNEXPLAINED_DIRECTION
    return None


def _confounded(dataset, c) -> str:
    """Why ``c`` cannot be told from another effect on ``dataset``, or "": a temperature term on a record whose
    temperature follows time (:data:`magcal.checks.quality.TEMP_TIME_CORR_WARN`) fits a drift as well, and applied
    to new data it carries the record's slope to temperatures the record never had (on a real bench recording
    whose temperature rose with time, r = 0.999, a temperature bias advised on the first half tripled the error on
    the second; benchmarks/notes/real.md, "Real recordings II")."""
    unresolved = _shape_unresolved(dataset, c)
    if unresolved:
        return unresolved
    cls = EFFECTS.get(c.effect)
    if cls is None or "temperature" not in getattr(cls, "channels", ()):
        return ""
    temp, clock = dataset.temperature_C, dataset.time_s
    if temp is None:
        return ""
    clock = np.arange(temp.size, dtype=float) if clock is None else np.asarray(clock, dtype=float)
    if np.ptp(temp) <= 0 or np.ptp(clock) <= 0:
        return ""
    r = float(np.corrcoef(temp, clock)[0, 1])
    if abs(r) < TEMP_TIME_CORR_WARN:
        return ""
    return (
        f"the temperature follows time on this record (correlation {r:+.3f}), so a temperature term cannot be told "
        "from a drift, and a calibration would carry its slope to temperatures the record never had; record with "
        "the temperature changing on its own (warm and cool the sensor while turning it) to judge it"
    )


def _shape_unresolved(dataset, c) -> str:
    """Why a record-only term's gain for new data cannot be judged on ``dataset``, or "": its directions do not
    resolve the spherical-harmonic degree 2, the calibration's own pattern over the direction (the ellipsoid's
    shape), to :data:`~magcal.diagnosis.statistics.SHAPE_JUDGED_MIN_EIGEN`. A series in time fitted with the base terms then moves that shape along the path, and the later
    stretch, on the same few directions, cannot show whether the calibration kept is better in the others (on a
    real record a reference drift judged so raised the next half's error by 17 %; benchmarks/notes/real.md)."""
    if not c.record_only or c.fit is None:
        return ""
    try:
        directions, _ = _sensor_directions(dataset, c.fit)
    except (MagcalError, ValueError, np.linalg.LinAlgError):
        return ""
    unresolved = [s + 1 for s, u in enumerate(directions) if not resolves_degree(u, 2, SHAPE_JUDGED_MIN_EIGEN)]
    if not unresolved:
        return ""
    return (
        f"the directions of sensor {', '.join(map(str, unresolved))} do not fix the calibration's shape "
        "(spherical-harmonic degree 2) well, so whether the calibration kept for new data is better with this "
        "record-only term fitted beside it cannot be judged here (the later stretch visits the same few "
        "directions); turn the sensor through more directions to judge it"
    )


def _advised(c) -> bool:
    """Whether a chosen effect is advice for a calibration: it improves the calibration for new data (the later
    stretch, applied as magcal apply does). Without a held-out judgement (a record too short to split) an
    instrument term is advised on its in-sample evidence and a record-only term is not; a confounded term never."""
    if c.confounded:
        return False
    if c.transfers is None:
        return not c.record_only
    return bool(c.transfers)


def _kept_words(c) -> str:
    """What the calibration keeps for new data when the record-only candidate is fitted and dropped."""
    cls = EFFECTS.get(c.effect)
    return getattr(cls, "kept_for_new_data", None) or "its base terms"


def _record_detail(c) -> dict:
    """The JSON entry of a finding that describes this record (``record_holds``)."""
    return {
        "label": c.label,
        "record_only": c.record_only,
        "describes_record": c.holds,
        "improves_new_data": c.transfers,
        "later_rms_before_nT": _num(c.later_before_nT),
        "later_rms_after_nT": _num(c.later_after_nT),
        "kept_for_new_data": _kept_words(c) if c.record_only else None,
        "when_recording": WHEN_RECORDING.get(c.effect, WHEN_RECORDING_OTHER) if c.record_only else WHEN_RECORDING_OTHER,
    }


def _record_holds_words(holds_here, chosen) -> str:
    """The summary's sentence on what this record holds and what to do about it when recording."""
    parts = []
    for c in holds_here:
        what = (
            "a record-only term (it describes this recording, not the sensor; magcal apply drops it on new data)"
            if c.record_only
            else "it describes this record but does not improve the calibration on its later part"
        )
        if c.confounded:
            what = c.confounded
        text = f"this record holds {c.label}: {what}"
        if c.record_only and c.transfers:
            text += (
                f"; fitted with the base terms it improves the calibration kept for new data ({_kept_words(c)}; "
                f"later stretch {c.later_before_nT:.4g} -> {c.later_after_nT:.4g} nT)"
            )
        elif c.later_before_nT is not None and c.confounded:
            text += f" (later stretch {c.later_before_nT:.4g} -> {c.later_after_nT:.4g} nT: not a judgement here)"
        elif c.later_before_nT is not None:
            text += (
                f"; it does not improve the calibration for new data (later stretch {c.later_before_nT:.4g} -> "
                f"{c.later_after_nT:.4g} nT)"
            )
        advice = WHEN_RECORDING.get(c.effect, WHEN_RECORDING_OTHER) if c.record_only else WHEN_RECORDING_OTHER
        parts.append(f"{text}. When recording: {advice}")
    if not any(_advised(c) for c in chosen):
        parts.append("nothing needs adding to the calibration for new data")
    return "; ".join(parts)


def _held_out_words(chosen) -> str:
    """``"; held-out 1011 -> 963 nT"`` for the effects chosen (blocks scheme), or ``""`` when not validated."""
    if not chosen or chosen[0].held_out_before_nT is None or chosen[-1].held_out_after_nT is None:
        return ""
    return (
        f"; on held-out samples (blocks) from {chosen[0].held_out_before_nT:.3g} to "
        f"{chosen[-1].held_out_after_nT:.3g} nT"
    )


def _validation_summary(held_out, skipped, chosen) -> dict:
    out = {
        "validated": held_out is not None and bool(held_out.schemes),
        "skipped": skipped,
        "schemes": dict(held_out.schemes) if held_out is not None else {},
        "min_relative_gain": _validation.MIN_RELATIVE_GAIN,
        "later_tolerance_se": _validation.LATER_TOLERANCE_SE,
    }
    if chosen and chosen[0].held_out_before_nT is not None and chosen[-1].held_out_after_nT is not None:
        out["held_out_rms_before_nT"] = chosen[0].held_out_before_nT
        out["held_out_rms_after_nT"] = chosen[-1].held_out_after_nT
    return out
