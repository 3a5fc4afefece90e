"""Score (Lagrange multiplier) tests of candidate effects, and their confirmation by refitting.

From the base model's Jacobian alone (no refit), :func:`_score_round` tests every catalogue effect whose
channels are present -- per sensor where it applies and for all sensors together -- and ranks the
:class:`Candidate` s by the predicted change of the Bayesian information criterion
``BIC = m ln(RSS/m) + k ln m``, with ``m`` the number of independent residuals
(:func:`effective_residual_count`). :func:`_confirm` refits the best few and replaces the prediction by the
actual delta-BIC. The cross-products of the Jacobian are accumulated once (:func:`_grams`) and every candidate
is tested against the base block by a Schur complement (:class:`_Projector`).

Effects are read through the :class:`magcal.model.terms.Effect` interface only (a user's own effect works); the
optional ``extra_dof`` class attribute (parameters found by a scan, such as a step time) defaults to 0.
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import stats

from magcal.calibration.calibration import is_transferable
from magcal.core.errors import CalibrationError
from magcal.core.jsonable import jsonable
from magcal.data.attitude import attitude_present
from magcal.diagnosis import _parallel
from magcal.diagnosis._fitted import _consistency_rms, _reference_override
from magcal.diagnosis._parallel import CHAIN, SHARED, in_parallel
from magcal.fitting.fitter import COMPARISON_COST_TOLERANCE, Problem, fit
from magcal.model.effects import readings_facts, seed_readings_facts
from magcal.model.terms import EFFECTS, Model, block_label, fitted_outside_domain, term_label


def _extra_dof(cls) -> int:
    """Parameters an effect finds by a scan rather than by the fit (e.g. a step time); 0 unless it declares them."""
    return getattr(cls, "extra_dof", 0)


def _copy_effect(effect):
    """A fresh copy of an effect instance (its constructor fields), as :func:`dataclasses.replace` makes it.

    Falls back to a shallow copy for an effect whose constructor does not take its dataclass fields.
    """
    try:
        return dataclasses.replace(effect)
    except TypeError:
        return copy.copy(effect)


@dataclass
class Candidate:
    """One candidate effect (optionally on one sensor) and the evidence for it.

    Attributes
    ----------
    effect : str
        Catalogue name.
    sensor : int or None
        0-based sensor (as :attr:`magcal.model.terms.Effect.sensor`), or None for all sensors (or a shared /
        single-sensor term). :meth:`to_dict` writes it 1-based, as the command line and the JSON count.
    label : str
        ``name`` or ``name:S`` (S 1-based, :func:`magcal.model.terms.term_label`).
    n_params : int
        Parameters added (identifiable ones).
    lm : float
        Score (Lagrange multiplier) statistic.
    p_value : float
        Chi-square p-value of ``lm``.
    predicted_delta_bic : float
        From the score test.
    delta_bic : float
        From the refit when ``refitted``, else the predicted one.
    rms_after_nT : float
        Total-field RMS with the effect added (refit, or first-order prediction).
    consistency_rms_after_nT : float or None
        Consistency residual RMS per component with the effect added (coupled arrays).
    refitted : bool
    evidence : str
        One line.
    params : dict
        Fitted parameters (refit only).
    held_out_before_nT, held_out_after_nT : float or None
        Total-field RMS on held-out samples without and with the effect, ``blocks`` scheme (interpolation in
        time; :mod:`magcal.fitting.validation`; for arrays the inter-sensor consistency is judged too, and quoted in the
        evidence), nT; None when not validated.
    later_before_nT, later_after_nT : float or None
        The same on the last stretch of the record (``later`` scheme: fitted on the earlier part, applied to the
        later stretch as ``magcal apply`` does: record-only terms dropped, nothing re-levelled), nT.
    holds : bool or None
        Whether the effect *describes this record*: its in-sample gain holds on interleaved held-out blocks
        (:func:`magcal.fitting.validation.judge`); None when not validated (not supported in-sample, validation
        skipped or refused).
    converged : bool
        False when the refit stopped above the base model's RMS (a diverged refit): its figures mean nothing and
        the table says "did not converge".
    transfers : bool or None
        Whether the effect *improves the calibration for new data* on the later stretch, scored as ``magcal
        apply`` scores it: an instrument term must not raise it, a record-only term must lower it
        (:func:`magcal.fitting.validation.transfers`); None when not validated.
    confounded : str
        Why the effect cannot be told from another on this record, whatever the held-out figures ("" when it can):
        a temperature term on a record whose temperature follows time is a drift as much as a temperature effect,
        and a calibration would carry its slope to temperatures the record never had.
    record_only : bool
        The term describes the recording, not the instrument (:attr:`magcal.model.terms.Effect.transferable`
        False: drifts, steps, interference, a changing or non-uniform field): ``magcal apply`` drops it on new data.
    not_physical : str
        Why the refitted effect is not physical here (a parameter held at a bound of its domain,
        :func:`magcal.model.terms.outside_domain`: a negative loop width, a nonlinearity of 1e5 ppm), or ``""``.
        Such a candidate is never recommendable: the record holds something else.
    """

    effect: str
    sensor: int | None
    label: str
    n_params: int
    lm: float
    p_value: float
    predicted_delta_bic: float
    delta_bic: float
    rms_after_nT: float
    consistency_rms_after_nT: float | None = None
    refitted: bool = False
    evidence: str = ""
    params: dict = field(default_factory=dict)
    held_out_before_nT: float | None = None
    held_out_after_nT: float | None = None
    later_before_nT: float | None = None
    later_after_nT: float | None = None
    holds: bool | None = None
    converged: bool = True
    transfers: bool | None = None
    confounded: str = ""
    record_only: bool = False
    not_physical: str = ""
    instances: list = field(default_factory=list, repr=False)
    columns: np.ndarray | None = field(default=None, repr=False)
    fit: object = field(default=None, repr=False)
    start: Any = field(default=None, repr=False)  # a Calibration: the refit's predicted start
    projector: object = field(default=None, repr=False)

    def to_dict(self) -> dict:
        return {
            "effect": self.effect,
            "sensor": None if self.sensor is None else self.sensor + 1,
            "delta_bic": _num(self.delta_bic),
            "rms_after_nT": _num(self.rms_after_nT),
            "evidence": self.evidence,
            "label": self.label,
            "predicted_delta_bic": _num(self.predicted_delta_bic),
            "refitted": self.refitted,
            "lm": _num(self.lm),
            "p_value": _num(self.p_value),
            "n_params": self.n_params,
            "consistency_rms_after_nT": _num(self.consistency_rms_after_nT),
            "params": self.params,
            "held_out_rms_before_nT": _num(self.held_out_before_nT),
            "held_out_rms_after_nT": _num(self.held_out_after_nT),
            "later_rms_before_nT": _num(self.later_before_nT),
            "later_rms_after_nT": _num(self.later_after_nT),
            "holds": self.holds,
            "transfers": self.transfers,
            "confounded": self.confounded or None,
            "record_only": self.record_only,
            "converged": self.converged,
            "not_physical": self.not_physical or None,
        }

    @property
    def recommendable(self) -> bool:
        """Refitted (and converged) with physical parameters, and not refuted on held-out data (holds, or was not
        validated)."""
        return self.refitted and self.converged and not self.not_physical and self.holds is not False


#: A refit whose RMS (of every residual it minimises) exceeds the base model's by more than this factor did not
#: converge (an added term cannot raise it at the minimum; 1 % leaves room for the fits' tolerance).
DIVERGED_RMS_RATIO = 1.01


def _num(x):
    if x is None:
        return None
    x = float(x)
    return x if np.isfinite(x) else None


def effective_residual_count(n_sensors, n_samples, coupled) -> int:
    """Independent residuals: total field, plus ``2 (n_sensors - 1)`` consistency ones per sample if coupled."""
    return int(n_sensors * n_samples + (2 * (n_sensors - 1) * n_samples if coupled else 0))


def _candidate_effects(dataset, model, names=None):
    """Effect instances to test, grouped by name: ``{name: [instance per sensor or one shared]}``.

    An effect that needs each sample's attitude (``site_gradient``) is not tested when some fitted samples have
    none: its refit would leave them out and be judged on other samples than the model it is compared with (the
    verdict says so, :func:`magcal.diagnosis.verdict._warnings_for`)."""
    out = {}
    present = attitude_present(dataset) if dataset.attitude_wxyz is not None else None
    gaps = present is not None and not present.all()
    for name, cls in EFFECTS.items():
        if names is not None and name not in names:
            continue
        if "scalar" not in getattr(cls, "modes", ("scalar",)):
            continue  # invisible in the total field (magcal.diagnosis.vector judges it)
        if getattr(cls, "variance_term", False):
            continue  # seen in the residuals' variance (magcal.diagnosis.jitter estimates it)
        probe = cls()
        if probe.missing_channels(dataset):
            continue
        if gaps and "attitude" in getattr(cls, "channels", ()):
            continue
        existing = [e for e in model.effects if e.name == name]
        if any(e.sensor is None for e in existing):
            continue
        if not cls.per_sensor:
            out[name] = [cls()]
            continue
        covered = {e.sensor for e in existing}
        sensors = [s for s in range(dataset.n_sensors) if probe.applies_to(s) and s not in covered]
        if sensors:
            out[name] = [cls(sensor=s) for s in sensors] if dataset.n_sensors > 1 else [cls()]
    return out


@dataclass
class _Grams:
    """Cross-products of the all-candidates Jacobian and residuals at the fitted base model."""

    g_all: np.ndarray
    v_all: np.ndarray
    rr_all: float
    g_tf: np.ndarray
    v_tf: np.ndarray
    rr_tf: float
    blocks: dict
    m_tf: int
    problem: object = None
    #: The parameters (the problem's layout) the Gram matrix is taken at (None: ``problem.x0``), and the problem's
    #: column each of its rows stands for (None: all, in order): a round's Gram matrix carried to the next round
    #: keeps a subset of the columns, moved along the step the chosen effect took (:func:`_carried`).
    x: np.ndarray | None = None
    index: np.ndarray | None = None
    #: Labels of the round's candidate terms (the rest are the fitted model's), the fitted samples, the reference.
    candidate_labels: frozenset = frozenset()
    mask: np.ndarray | None = None
    reference: float | None = None


def _chunk_terms(sub, model, init, reference_total_nT):
    """The normal-equation terms of one chunk of samples and its Problem."""
    problem = Problem(sub, model, init, reference_total_nT)
    r, jtj, jtr, (jtj_tf, jtr_tf) = problem.normal_equations(problem.x0, with_total_field=True)
    rt = r[: sub.n_sensors * sub.n_samples]
    return [jtj, jtr, float(r @ r), jtj_tf, jtr_tf, float(rt @ rt)], problem


def gram_task(dataset, kept_mask, start, stop, model, init, reference_total_nT):
    """(A worker's task.) The normal-equation terms of the kept samples ``start:stop`` of ``dataset``
    (``kept_mask``: the samples the fit kept, None for all)."""
    kept = _parallel.subset(dataset, kept_mask)
    return _chunk_terms(kept.subset(np.arange(start, stop)), model, init, reference_total_nT)[0]


#: Residual rows per chunk of a score round's normal equations (:func:`_grams`): 16 chunks for 4 x 1e5 samples, so
#: that many cores share them; the chunks are the same whatever the cores, so is the sum.
GRAM_CHUNK_ROWS = 75_000


def _grams(kept, model, init, reference_total_nT, chunk_rows=GRAM_CHUNK_ROWS, pool=None, kept_mask=None) -> _Grams:
    """Accumulate ``J^T J``, ``J^T r`` (all rows and total-field rows) over chunks of samples.

    The chunks bound the memory of the per-sample derivatives of every candidate's parameters; their number does
    not depend on the workers, and their terms are summed in order, so the result is the same wherever they ran.
    With a ``pool`` whose fits run elsewhere (:attr:`magcal.diagnosis._parallel.Pool.is_remote`), every chunk but
    the last goes to the workers (``kept_mask``: the samples of the dataset the pool shares that ``kept`` holds).
    """

    n = kept.n_samples
    rows_per_sample = kept.n_sensors * (3 if kept.n_sensors > 1 else 1)
    chunk_samples = max(2_000, chunk_rows // rows_per_sample)
    parts = np.array_split(np.arange(n), max(1, int(np.ceil(n / chunk_samples))))

    def chunk(idx):
        sub = kept if len(parts) == 1 else kept.subset(idx)
        return _chunk_terms(sub, model, init, reference_total_nT)

    if pool is not None and pool.is_remote and len(parts) > 1:
        futures = [
            pool.remote_future(gram_task, kept_mask, int(idx[0]), int(idx[-1]) + 1, model, init, reference_total_nT)
            for idx in parts[:-1]
        ]
        last, problem = chunk(parts[-1])  # here, meanwhile: its problem carries the blocks
        chunks = [(f.result(), None) for f in futures] + [(last, problem)]
    else:
        # chunks side by side on threads; the last chunk's problem carries the blocks
        chunks = in_parallel([lambda idx=idx: chunk(idx) for idx in parts], pool)
    acc: list = []
    for terms, problem in chunks:  # noqa: B007
        acc = terms if not acc else [a + t for a, t in zip(acc, terms)]
    return _Grams(acc[0], acc[1], acc[2], acc[3], acc[4], acc[5], problem.blocks, kept.n_sensors * n, problem)


def _carried(previous, kept, fit, groups):
    """The score round at ``fit`` from the previous round's Gram matrix, or None when it cannot be carried.

    ``previous`` is the candidate chosen in the previous round, whose refit is ``fit``. To first order the Jacobian
    does not change along the step its refit took, and the residuals change by ``J delta``: the previous Gram
    matrix, its columns restricted to the previous base model, the chosen term and the candidates whose
    data-derived constants (``Effect.state``) are those of the previous round, with ``J^T r`` and ``r^T r``
    moved along ``delta`` (the score test's own predicted step, :meth:`_Projector.step`), is the Gram matrix at
    ``fit`` (the score of a candidate against the enlarged base does not depend on ``delta`` at all; the
    predicted residual RMS does). Candidates whose constants changed with the residuals (a step time, an
    interference frequency) get a Gram matrix of their own.

    Returns
    -------
    (reusable groups, carried grams, changed groups) or None
        None when the refit does not describe the previous round's model (other samples, another reference, or
        the chosen term's constants changed in its refit).
    """
    proj = previous.projector
    g = None if proj is None else proj.g
    if (
        g is None
        or g.problem is None
        or g.mask is None
        or not np.array_equal(g.mask, fit.mask)
        or g.reference != _reference_override(fit)
    ):
        return None

    before = {block_label(e, s): e for e, s in g.problem.model.instances()}

    def same(e, s):
        old = before.get(block_label(e, s))
        return old is not None and old.name == e.name and jsonable(old.state()) == jsonable(e.state())

    chosen_columns = set(previous.columns.tolist())
    chosen = {label for label, sl in g.blocks.items() if sl.start in chosen_columns}
    model_labels = {block_label(e, s) for e, s in fit.model.instances()}
    if not chosen <= model_labels or not all(same(e, s) for e, s in fit.model.instances()):
        return None
    base = [label for label in g.blocks if label not in g.candidate_labels] + sorted(chosen)
    if {label for label in base if "/" not in label and label != "F0"} != model_labels:
        return None
    reusable, changed = {}, {}
    for name, instances in groups.items():
        labels = [block_label(e, s) for e in instances for s in _sensors_of(e, kept.n_sensors)]
        ok = all(label in g.blocks for label in labels) and all(
            same(e, s) for e in instances for s in _sensors_of(e, kept.n_sensors)
        )
        (reusable if ok else changed)[name] = instances
    keep_labels = sorted(
        set(base) | {block_label(e, s) for v in reusable.values() for e in v for s in _sensors_of(e, kept.n_sensors)},
        key=lambda label: g.blocks[label].start,
    )
    keep = np.concatenate([np.arange(g.blocks[label].start, g.blocks[label].stop) for label in keep_labels])
    blocks, at = {}, 0
    for label in keep_labels:
        width = g.blocks[label].stop - g.blocks[label].start
        blocks[label] = slice(at, at + width)
        at += width
    delta = proj.step(previous.columns)[keep]
    sub = np.ix_(keep, keep)
    g_all, g_tf = g.g_all[sub], g.g_tf[sub]
    v_all, v_tf = g.v_all[keep], g.v_tf[keep]
    index = keep if g.index is None else g.index[keep]
    x = (g.problem.x0 if g.x is None else g.x).copy()
    x[index] += delta
    carried = _Grams(
        g_all,
        v_all + g_all @ delta,
        float(g.rr_all + 2 * delta @ v_all + delta @ g_all @ delta),
        g_tf,
        v_tf + g_tf @ delta,
        float(g.rr_tf + 2 * delta @ v_tf + delta @ g_tf @ delta),
        blocks,
        g.m_tf,
        g.problem,
        x=x,
        index=index,
        mask=g.mask,
        reference=g.reference,
    )
    return reusable, carried, changed


def _sensors_of(effect, n_sensors):
    """The sensors (0-based, or None for a shared term) of an effect instance's parameter blocks."""
    if not effect.per_sensor:
        return [None]
    if effect.sensor is not None:
        return [effect.sensor]
    return [s for s in range(n_sensors) if effect.applies_to(s)]


def _columns(blocks, labels):
    cols = []
    for label in labels:
        sl = blocks[label]
        cols.extend(range(sl.start, sl.stop))
    return np.asarray(cols, dtype=int)


class _Projector:
    """Solves with the base block of the Gram matrix (Jacobi-scaled, pseudo-inverse)."""

    def __init__(self, grams: _Grams, base_cols):
        self.g = grams
        self.base = np.asarray(base_cols, dtype=int)
        g00 = grams.g_all[np.ix_(self.base, self.base)]
        d = np.sqrt(np.maximum(np.diag(g00), 1e-300))
        w, v = np.linalg.eigh(g00 / np.outer(d, d))
        keep = w > 1e-12 * w.max()
        self.g00_inv = (v[:, keep] / w[keep]) @ v[:, keep].T / np.outer(d, d)

    def schur(self, a, b=None):
        """``Jt_a^T Jt_b`` with ``Jt = (I - P_base) J``."""
        b = a if b is None else b
        g = self.g.g_all
        return g[np.ix_(a, b)] - g[np.ix_(a, self.base)] @ self.g00_inv @ g[np.ix_(self.base, b)]

    def score(self, cols, rss0, dof0, m_eff, extra_dof=0):
        g = self.g
        base = self.base
        bmat = self.g00_inv @ g.g_all[np.ix_(base, cols)]  # regression of Je on J0
        s = g.g_all[np.ix_(cols, cols)] - g.g_all[np.ix_(cols, base)] @ bmat
        v = g.v_all[cols] - bmat.T @ g.v_all[base]
        d = np.sqrt(np.maximum(np.diag(g.g_all)[cols], 1e-300))
        ss = s / np.outer(d, d)
        ss = 0.5 * (ss + ss.T)
        w, vec = np.linalg.eigh(ss)
        keep = w > 1e-7
        q = int(keep.sum())
        if q == 0:
            return None
        s_pinv = (vec[:, keep] / w[keep]) @ vec[:, keep].T / np.outer(d, d)
        coef = s_pinv @ v
        reduction = float(max(v @ coef, 0.0))
        reduction = min(reduction, 0.999999 * rss0)
        s2 = rss0 / max(dof0, 1)
        lm = reduction / s2
        p = float(stats.chi2.sf(lm, q))
        dbic = m_eff * np.log(1.0 - reduction / rss0) + (q + extra_dof) * np.log(m_eff)
        # first-order total-field residual after adding the effect (the base re-adjusting included)
        jt_r = g.v_tf[cols] - bmat.T @ g.v_tf[base]
        jt_j = (
            g.g_tf[np.ix_(cols, cols)]
            - bmat.T @ g.g_tf[np.ix_(base, cols)]
            - g.g_tf[np.ix_(cols, base)] @ bmat
            + bmat.T @ g.g_tf[np.ix_(base, base)] @ bmat
        )
        rss_tf = g.rr_tf - 2 * coef @ jt_r + coef @ jt_j @ coef
        rms_tf = float(np.sqrt(max(rss_tf, 0.0) / g.m_tf))
        rss_v = (g.rr_all - g.rr_tf) - 2 * coef @ (v - jt_r) + coef @ (s - jt_j) @ coef
        return {
            "q": q,
            "lm": lm,
            "p": p,
            "dbic": float(dbic),
            "rms_tf": rms_tf,
            "rss_consistency": float(max(rss_v, 0.0)),
            "reduction": reduction,
        }

    def step(self, cols):
        """The Gauss-Newton step (one value per row of the Gram matrix) with the columns ``cols`` (a candidate's
        parameters) added to the base model: the base and the candidate's parameters solved jointly
        (Jacobi-scaled pseudo-inverse), the other candidates' left at zero."""
        g = self.g
        sel = np.concatenate([self.base, np.asarray(cols, dtype=int)])
        d = np.sqrt(np.maximum(np.diag(g.g_all)[sel], 1e-300))
        w, v = np.linalg.eigh(g.g_all[np.ix_(sel, sel)] / np.outer(d, d))
        keep = w > 1e-12 * w.max()
        out = np.zeros(len(g.v_all))
        out[sel] = -((v[:, keep] / w[keep]) @ (v[:, keep].T @ (g.v_all[sel] / d))) / d
        return out

    def start(self, cols):
        """The calibration one Gauss-Newton step from the fitted base model predicts with the columns ``cols``
        added (:meth:`step`), kept in the parameters' bounds. A candidate's refit starts there, next to its
        minimum, so it needs about one pass over the data."""
        g, problem = self.g, self.g.problem
        x = (problem.x0 if g.x is None else g.x).copy()
        x[np.arange(x.size) if g.index is None else g.index] += self.step(cols)
        return problem.calibration(np.clip(x, problem.lower, problem.upper))

    def canonical_correlation(self, a, b):
        """Largest canonical correlation between the projected columns ``a`` and ``b`` (0..1)."""
        whiten = []
        for cols in (a, b):
            s = self.schur(cols)
            d = np.sqrt(np.maximum(np.diag(s), 1e-300))
            w, v = np.linalg.eigh(0.5 * (s + s.T) / np.outer(d, d))
            keep = w > 1e-7
            if not keep.any():
                return 0.0
            whiten.append((v[:, keep] / np.sqrt(w[keep])) / d[:, None])
        m = whiten[0].T @ self.schur(a, b) @ whiten[1]
        return float(np.clip(np.linalg.norm(m, 2), 0.0, 1.0))


def _score_round(dataset, kept, fit, names=None, previous=None, pool=None):
    """Score tests for every candidate (per sensor and all sensors) at the fitted model ``fit``.

    ``previous``: the candidate of the previous round whose refit ``fit`` is; the candidates whose data-derived
    constants did not change are then scored from that round's Gram matrix carried along the step
    (:func:`_carried`), and only the others from a new one.

    ``pool``: a :class:`~magcal.diagnosis._parallel.Pool` sharing ``dataset``, whose workers take the chunks of the
    normal equations (:func:`_grams`).

    Returns ``(candidates, projector, grams)``; candidates are sorted by predicted delta-BIC.
    """
    model = fit.model
    groups = _candidate_effects(kept, model, names)
    if not groups:
        return [], None, None
    base_resid = fit.residuals_nT[:, fit.mask]
    in_parallel(
        [
            lambda e=e: e.configure(kept, base_resid)  # each candidate's data-derived constants, side by side
            for instances in groups.values()
            for e in instances
        ],
        pool,
    )
    carried = _carried(previous, kept, fit, groups) if previous is not None else None
    if carried is not None and carried[0]:
        reusable, grams, changed = carried
        grams.candidate_labels = _labels_of(reusable, kept.n_sensors)
        cands, proj, _ = _score_from_grams(kept, fit, reusable, grams)
        if changed:
            more, _, _ = _score_round_fresh(kept, fit, changed, pool)
            cands = sorted(cands + more, key=lambda c: c.predicted_delta_bic)
        return cands, proj, grams
    return _score_round_fresh(kept, fit, groups, pool)


def _labels_of(groups, n_sensors) -> frozenset:

    return frozenset(block_label(e, s) for v in groups.values() for e in v for s in _sensors_of(e, n_sensors))


def _score_round_fresh(kept, fit, groups, pool=None):
    """The score round of ``groups`` (configured) from a Gram matrix at ``fit``."""
    model = fit.model
    all_model = Model(
        model.n_sensors, model.base, [_copy_effect(e) for e in model.effects] + [e for v in groups.values() for e in v]
    )
    ref = _reference_override(fit)
    try:
        grams = _grams(kept, all_model, fit.calibration, ref, pool=pool, kept_mask=None if fit.mask.all() else fit.mask)
    except CalibrationError:
        # too few samples for every candidate at once: test them one effect at a time
        return _score_round_separately(kept, fit, groups)
    grams.candidate_labels, grams.mask, grams.reference = _labels_of(groups, kept.n_sensors), fit.mask, ref
    return _score_from_grams(kept, fit, groups, grams)


def _score_round_separately(kept, fit, groups):
    out = []
    for name, instances in groups.items():
        m = Model(fit.model.n_sensors, fit.model.base, [_copy_effect(e) for e in fit.model.effects] + instances)
        try:
            grams = _grams(kept, m, fit.calibration, _reference_override(fit))
        except CalibrationError:
            continue
        cands, _, _ = _score_from_grams(kept, fit, {name: instances}, grams)
        out.extend(cands)
    out.sort(key=lambda c: c.predicted_delta_bic)
    return out, None, None


def _score_from_grams(kept, fit, groups, grams):

    cand_labels = {
        block_label(e, s)
        for v in groups.values()
        for e in v
        for s in (
            [None]
            if not e.per_sensor
            else [e.sensor]
            if e.sensor is not None
            else [q for q in range(kept.n_sensors) if e.applies_to(q)]
        )
    }
    all_cols = np.arange(grams.g_all.shape[0])
    cand_cols = _columns(grams.blocks, sorted(cand_labels))
    base_cols = np.setdiff1d(all_cols, cand_cols)
    proj = _Projector(grams, base_cols)
    ns, n = kept.n_sensors, kept.n_samples
    coupled = fit.consistency_residuals_nT is not None
    m_eff = effective_residual_count(ns, n, coupled)
    rss0 = grams.rr_all
    dof0 = m_eff - len(base_cols)
    cands = []
    for name, instances in groups.items():
        cls = EFFECTS[name]
        variants = []
        if not cls.per_sensor:
            variants.append((None, instances))
        elif ns == 1:
            variants.append((None, instances))
        else:
            for e in instances:
                variants.append((e.sensor, [e]))
            if len(instances) > 1:
                variants.append((None, instances))
        for sensor, inst in variants:
            labels = []
            for e in inst:
                if not e.per_sensor:
                    labels.append(block_label(e, None))
                elif e.sensor is not None:
                    labels.append(block_label(e, e.sensor))
                else:
                    labels.extend(block_label(e, q) for q in range(ns) if e.applies_to(q))
            cols = _columns(grams.blocks, labels)
            extra = _extra_dof(cls) * len(inst)
            sc = proj.score(cols, rss0, dof0, m_eff, extra)
            if sc is None:
                continue
            label = term_label(name, sensor)
            consistency_after = None
            if coupled:
                consistency_after = float(np.sqrt(sc["rss_consistency"] / (ns * n * 2)))
            c = Candidate(
                effect=name,
                sensor=sensor,
                label=label,
                n_params=sc["q"],
                lm=sc["lm"],
                p_value=sc["p"],
                predicted_delta_bic=sc["dbic"],
                delta_bic=sc["dbic"],
                rms_after_nT=sc["rms_tf"],
                consistency_rms_after_nT=consistency_after,
                instances=inst,
                columns=cols,
                projector=proj,
                record_only=not is_transferable(cls),
            )
            cands.append(c)
    cands.sort(key=lambda c: c.predicted_delta_bic)
    return cands, proj, grams


def refit_task(dataset, model, init, mask, reference_total_nT, facts=()):
    """(A worker's task.) The comparison fit of ``model`` on ``dataset``'s samples ``mask`` from ``init``.

    ``facts``: ``(sensor, key, value)`` worked out from those samples' readings by the process that handed the
    fit over (:func:`_readings_facts_of`), kept here first so that this process does not work them out again (a
    bias step's scan: 0.13 s at 4 x 1e5 samples, 1.3 s at 4 x 1e6)."""
    kept = dataset.masked(mask)  # held while the fit runs: the fit's samples are these very arrays
    for s, key, value in facts:
        seed_readings_facts(kept.readings_nT[s], [(key, value)])
    return fit(
        dataset,
        model,
        init=init,
        mask=mask,
        reference_total_nT=reference_total_nT,
        cost_tolerance=COMPARISON_COST_TOLERANCE,
        warn=False,
    )


def _readings_facts_of(dataset, mask) -> list:
    """``(sensor, key, value)``: the single numbers worked out here from the readings of ``dataset``'s samples
    ``mask`` (:func:`magcal.model.effects.readings_facts`), for a fit of the same samples in a worker."""
    kept = dataset.masked(mask)
    return [(s, key, value) for s in range(kept.n_sensors) for key, value in readings_facts(kept.readings_nT[s])]


def candidate_model(fit, candidate: Candidate) -> Model:
    """The model of ``fit`` with the candidate's effect instances added: the model its refit and its held-out
    fits fit (one term for all sensors where the candidate is all sensors' and the model lacks the effect)."""
    model = fit.model
    if (
        candidate.sensor is None
        and len(candidate.instances) > 1
        and not any(e.name == candidate.effect for e in model.effects)
    ):
        new = [EFFECTS[candidate.effect]()]  # one term for all sensors
    else:
        new = [_copy_effect(e) for e in candidate.instances]
    for e in new:
        model = model.with_effect(e)
    return model


def candidate_start(fit, candidate: Candidate):
    """Where the fits of :func:`candidate_model` start: the calibration the candidate's score test predicts
    (:meth:`_Projector.start`, set by :func:`_confirm`), else ``fit``'s own."""
    return candidate.start or fit.calibration


def _refit(dataset, fit, candidate: Candidate, pool=None):
    """Refit the model with the candidate's effect instances added (:func:`candidate_model`), from the score
    test's predicted start (:func:`candidate_start`); returns the FitResult. With ``pool`` (sharing ``dataset``)
    the fit runs on its workers."""
    args = (candidate_model(fit, candidate), candidate_start(fit, candidate), fit.mask, _reference_override(fit))
    if pool is None:
        return refit_task(dataset, *args)
    return pool.remote(refit_task, *args, _readings_facts_of(dataset, fit.mask))


def _delta_bic(fit0, fit1, extra_dof, coupled):
    ns = fit0.residuals_nT.shape[0]
    n = int(fit0.mask.sum())
    m_eff = effective_residual_count(ns, n, coupled)
    dk = fit1.n_params - fit0.n_params + extra_dof
    return float(m_eff * np.log(fit1.rss / fit0.rss) + dk * np.log(m_eff))


#: A candidate whose score test predicts a delta-BIC below this is predicted to be supported (the diagnosis's
#: threshold of very strong evidence, :data:`magcal.diagnosis.verdict.DELTA_BIC_THRESHOLD`).
PREDICTED_SUPPORT_DELTA_BIC = -10.0


def search_order(cands, top) -> list:
    """The ``top`` distinct effects to refit, from candidates ranked by their predicted delta-BIC.

    The ranking, except that the best instrument term predicted to be supported (a nonlinearity, a temperature
    coefficient, a timing skew, hysteresis: a term that carries to new data) always has a place, the last one if
    the ranking leaves it out: record-only terms (a drift, a step, the reference's change) take whatever changes in
    time, the noise's wander included, and often rank first; an instrument term that would hold, ranked below
    three of them, was never refitted at the default ``top``. Giving every instrument term precedence instead let
    temperature terms that follow time take a strong drift's place. A single place (``top`` 1: the forward
    selection's later rounds) goes to the best predicted, whatever it is.
    """
    distinct, seen = [], set()
    for c in cands:
        if c.effect not in seen:
            seen.add(c.effect)
            distinct.append(c)
    chosen = distinct[:top]
    if top < 2:
        return chosen
    instrument = next(
        (c for c in distinct if not c.record_only and c.predicted_delta_bic < PREDICTED_SUPPORT_DELTA_BIC), None
    )
    if instrument is not None and all(c is not instrument for c in chosen):
        chosen[-1] = instrument
    return chosen


def _confirm(dataset, fit, cands, top, coupled, fits, alongside=(), pool=None, after_refit=None, beside_refit=None):
    """Refit the best variant of the ``top`` best distinct effects (from the start their score test predicts,
    :meth:`_Projector.start`); re-rank.

    ``alongside``: other independent work (functions of no argument, their results dropped) run side by side
    with the refits. ``pool``: a :class:`~magcal.diagnosis._parallel.Pool` to run the refits and that work on
    (by default a batch of its own); ``after_refit(c)``, called in the refit's thread as soon as candidate ``c``
    is refitted and its figures are set, may hand the pool the work that needed the refit. ``beside_refit(c)``,
    called with ``pool`` for each candidate to refit (its start set) before the refits are handed over, may hand
    the pool work that needs the candidate but not its refit, to run beside it (below the refits' priority).
    """
    chosen = search_order(cands, top)
    for c in chosen:
        if c.projector is not None and c.projector.g.problem is not None:
            try:
                c.start = c.projector.start(c.columns)
            except (CalibrationError, np.linalg.LinAlgError, ValueError):
                c.start = None  # the refit starts from the base fit instead

    def refit(c):
        try:
            f1 = _refit(dataset, fit, c, pool)
        except (CalibrationError, np.linalg.LinAlgError) as exc:
            c.evidence = (c.evidence + "; " if c.evidence else "") + f"refit failed: {exc}"
            return None
        extra = _extra_dof(EFFECTS[c.effect]) * len(c.instances)
        c.delta_bic = _delta_bic(fit, f1, extra, coupled)
        c.rms_after_nT = float(f1.rms_nT)
        c.consistency_rms_after_nT = _consistency_rms(f1)
        c.refitted = True
        # a term added to the model cannot raise the RMS at the minimum: a refit above the base model's RMS (or not
        # finite) stopped far from it, and its figures say nothing about the term
        c.converged = bool(np.isfinite(f1.rss) and f1.rss <= DIVERGED_RMS_RATIO**2 * fit.rss)
        if not c.converged:
            c.evidence = (c.evidence + "; " if c.evidence else "") + (
                f"the refit did not converge (it stopped at {c.rms_after_nT:.3g} nT RMS, above the model without "
                f"the term, {float(fit.rms_nT):.3g} nT): no evidence either way"
            )
        c.params = {p["term"]: p["params"] for p in f1.effect_params if p["effect"] == c.effect}
        c.fit = f1
        model = f1.calibration.model
        c.not_physical = (
            ""
            if model is None
            else fitted_outside_domain(model, f1.calibration.effect_values, c.effect, f1.bound_pull_z)
        )
        if c.not_physical:
            c.evidence = (c.evidence + "; " if c.evidence else "") + f"not physical here ({c.not_physical})"
        if after_refit is not None:
            after_refit(c)
        return f1

    calls = [lambda c=c: refit(c) for c in chosen]
    if pool is None:
        in_parallel(calls + list(alongside))  # independent refits
    else:
        if beside_refit is not None:
            for c in chosen:
                beside_refit(c)
        futures = [pool.submit(call, CHAIN) for call in calls] + [pool.submit(call, SHARED) for call in alongside]
        for future in futures:
            future.result()
    for c in chosen:
        if c.refitted:
            fits[c.label] = c.fit
    refitted = sorted([c for c in cands if c.refitted], key=lambda c: c.delta_bic)
    rest = [c for c in cands if not c.refitted]
    return refitted + rest
