"""Real recordings: the diagnose -> add -> refit loop of a user, judged on held-out data (issue 10).

For every converted real recording (``benchmarks/real/data/*.csv``; see ``benchmarks/real/README.md``) this
prints and writes:

* N, sample rate, the data-quality findings read before fitting (:func:`magcal.checks.quality.assess`, notable ones);
* the noise estimate with the method that gave it and its check (still stretches' scatter where there is one,
  the quantization floor);
* the loop followed exactly as a user would: base fit -> :func:`magcal.diagnose` -> add the effect it recommends
  (the first of ``explained_by``, else of ``partially_explained_by``: what the report advises; nothing when the
  diagnosis says the base calibration is not determined by the data) -> refit -> diagnose again ..., at most ``--steps`` effects. Per step: the effect added, its
  delta-BIC (from the diagnosis that recommended it), the in-sample total-field RMS, the held-out RMS of
  :func:`magcal.fitting.validation.validate` on the ``blocks`` scheme (alternating blocks in time) and on the ``later``
  scheme (last quarter), and the verdict of diagnosing the refitted model;
* beside it an independent ellipsoid fit written here (algebraic least-squares quadric, no magcal code) with its
  in-sample and held-out RMS on the same splits, in the same gauge (soft-iron matrix of unit determinant);
* the claim of issue 10 checked per recording: held-out RMS never rises with a recommended effect; it falls (or
  the verdict reads ``adequate``); the loop ends ``adequate`` or ``unexplained`` with the remaining structure named;
* the transfer test of issue 28 (:func:`run_transfer`): the advice followed as a user would on the record's
  *first half* (diagnose; add the first of ``explained_by``, else of ``partially_explained_by``; refit; diagnose
  again; at most ``--rounds``), each calibration written to JSON, read back and applied to the *second half*
  exactly as ``magcal apply`` applies it to another record (record-only terms dropped, nothing refitted or
  re-levelled): the held-out error is the RMS of ``|B|`` minus the field the calibration expects (the first half's
  fitted field magnitude), before and after each piece of advice; the claim: it never rises by more than 1 %,
  and falls by 2 % or more (or the first verdict is ``adequate``) on at least half of the recordings;
* with ``--kept``, which level a record-only term fitted with the base terms should leave in the calibration for
  new data (:func:`kept_level_study`: its level at the first half's start, mean or end, applied to the second).

All RMS values are total-field residuals in nT. The recordings' field is fitted (no reference given).

Usage::

    python benchmarks/real/fetch.py --mirror /work/.mirror     # or without --mirror: download (pinned commits)
    python benchmarks/real/convert.py --all                    # h5py for sf_*, pymavlink / pyulog for the logs
    OPENBLAS_NUM_THREADS=1 python benchmarks/real.py           # all recordings (30-70 s on 2 shared cores)
    python benchmarks/real.py --transfer-only --kept            # the transfer test and the kept levels only
    python benchmarks/real.py qmc_filtered sf_fullsphere --steps 2

Writes ``benchmarks/out/real_loop.json`` (everything) and ``benchmarks/out/real_loop.csv`` (one row per step);
with ``--transfer-only`` (no loop), ``real_transfer.json`` and ``.csv`` instead, so that the loop's committed
output is not replaced by a partial one;
``--figures`` adds ``benchmarks/out/real_<name>.png`` (residuals of the first and last model against time,
temperature and, for the balloon flight, altitude).
The independent fit needs nothing beyond numpy. (magyc, the obvious PyPI alternative, pins numpy < 2 and needs
gtsam and jax, so it is not used.)
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # the shared 2-core machine: a second BLAS thread only contends

import argparse
import csv
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's magcal, not an installed one

import magcal
from magcal.checks.noise import estimate_noise
from magcal.checks.quality import assess, field_magnitude_finding
from magcal.core.errors import MagcalError
from magcal.fitting import validation

HERE = Path(__file__).resolve().parent
DATA_DIR = HERE / "real" / "data"
OUT_DIR = HERE / "out"

#: A candidate is supported below this delta-BIC (as :data:`magcal.diagnosis.verdict.DELTA_BIC_THRESHOLD`).
DELTA_BIC_SUPPORTED = -10.0


# ---- the independent ellipsoid fit ----------------------------------------------------------------------------


class EllipsoidFailure(RuntimeError):
    """The quadric fitted is not an ellipsoid (the readings do not constrain one)."""


def fit_ellipsoid_independent(readings):
    """Algebraic least-squares ellipsoid through raw readings, written here without magcal's code.

    Solves ``a x^2 + b y^2 + c z^2 + 2d xy + 2e xz + 2f yz + 2g x + 2h y + 2i z = 1`` for the nine coefficients
    by least squares on readings centred and scaled for conditioning, then takes the centre ``c`` and the
    symmetric square root ``W`` of the shape matrix so that ``|W (y - c)| = 1`` on the ellipsoid.

    Parameters
    ----------
    readings : numpy.ndarray, shape (N, 3)
        Raw readings, nT.

    Returns
    -------
    centre_nT : numpy.ndarray, shape (3,)
    matrix : numpy.ndarray, shape (3, 3)
        Soft-iron correction of unit determinant (the gauge magcal's fit uses: ``det(C^-1) = 1``).
    field_nT : float
        Field magnitude in that gauge: ``|matrix (y - centre)|`` is ``field_nT`` on the ellipsoid.

    Raises
    ------
    EllipsoidFailure
        The fitted quadric is not an ellipsoid.
    """
    y = np.asarray(readings, float)
    mean = y.mean(axis=0)
    scale = float(np.sqrt(np.mean(np.sum((y - mean) ** 2, axis=1))))
    u = (y - mean) / scale
    x1, x2, x3 = u.T
    design = np.column_stack([x1 * x1, x2 * x2, x3 * x3, 2 * x1 * x2, 2 * x1 * x3, 2 * x2 * x3, 2 * x1, 2 * x2, 2 * x3])
    coef, *_ = np.linalg.lstsq(design, np.ones(len(u)), rcond=None)
    a, b, c, d, e, f, g, h, i = coef
    shape = np.array([[a, d, e], [d, b, f], [e, f, c]])
    linear = np.array([g, h, i])
    try:
        centre_u = -np.linalg.solve(shape, linear)
    except np.linalg.LinAlgError as exc:
        raise EllipsoidFailure("singular quadric") from exc
    k = 1.0 + centre_u @ shape @ centre_u
    m = shape / k
    vals, vecs = np.linalg.eigh(m)
    if not np.all(vals > 0) or not np.isfinite(k):
        raise EllipsoidFailure(f"quadric eigenvalues {np.round(vals, 4).tolist()}: not an ellipsoid")
    w = vecs @ np.diag(np.sqrt(vals)) @ vecs.T / scale  # |w (y - centre)| = 1, raw units
    det = float(np.linalg.det(w))
    matrix = w / det ** (1.0 / 3.0)
    return mean + scale * centre_u, matrix, det ** (-1.0 / 3.0)


def independent_residuals(readings, centre, matrix, field_nT):
    """Total-field residuals (nT) of the independent fit: ``|matrix (y - centre)| - field``."""
    return np.linalg.norm((np.asarray(readings, float) - centre) @ matrix.T, axis=1) - field_nT


def _rms(x) -> float:
    x = np.asarray(x, float)
    return float(np.sqrt(np.mean(x**2)))


def independent_fit(ds, masks) -> dict:
    """In-sample RMS on the whole record and held-out RMS of the independent fit on each scheme's split (nT),
    pooled over the sensors."""
    out = {}
    try:
        res_all, held = [], {s: [] for s in masks}
        for s in range(ds.n_sensors):
            y = ds.readings_nT[s]
            res_all.append(independent_residuals(y, *fit_ellipsoid_independent(y)))
            for scheme, (train, test) in masks.items():
                held[scheme].append(independent_residuals(y[test], *fit_ellipsoid_independent(y[train])))
        out["in_sample_rms_nT"] = _rms(np.concatenate(res_all))
        for scheme in masks:
            out[f"{scheme}_rms_nT"] = _rms(np.concatenate(held[scheme]))
    except EllipsoidFailure as exc:
        out["failed"] = str(exc)
    return out


def check_independent_fit(seed: int = 0) -> None:
    """The independent fit against a simulated ellipsoid of known centre, shape and field (raises if it fails).

    Readings ``y = F S u + b + noise`` with ``u`` uniform on the sphere: the fit must return ``b``, the matrix
    ``S^-1`` scaled to unit determinant and the field ``F det(S)^(1/3)`` (the gauge), and residuals at the noise.
    """
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(4000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    shape = np.array([[1.05, 0.02, -0.01], [0.02, 0.93, 0.03], [-0.01, 0.03, 1.10]])
    bias, field, sigma = np.array([3000.0, -1500.0, 800.0]), 50_000.0, 5.0
    y = field * u @ shape.T + bias + rng.normal(scale=sigma, size=u.shape)
    centre, matrix, field_fit = fit_ellipsoid_independent(y)
    expected = np.linalg.inv(shape) * np.linalg.det(shape) ** (1.0 / 3.0)
    rms = _rms(independent_residuals(y, centre, matrix, field_fit))
    problems = []
    if np.max(np.abs(centre - bias)) > 2.0:
        problems.append(f"centre off by {np.max(np.abs(centre - bias)):.3g} nT")
    if np.max(np.abs(matrix - expected)) > 1e-4:
        problems.append(f"matrix off by {np.max(np.abs(matrix - expected)):.3g}")
    if abs(field_fit - field * np.linalg.det(shape) ** (1.0 / 3.0)) > 2.0:
        problems.append(f"field {field_fit:.6g} nT")
    if not 0.9 * sigma < rms < 1.1 * sigma:
        problems.append(f"residual RMS {rms:.3g} nT for noise {sigma} nT")
    if problems:
        raise AssertionError("the independent ellipsoid fit fails on simulated data: " + "; ".join(problems))


def _calibrate(ds, **options):
    """The total-field calibration (a record with an accelerometer or an attitude would otherwise take its own
    mode): this benchmark judges the total-field calibration."""
    return magcal.calibrate(ds, **options, mode="total_field")


def _diagnose(ds, result, **options):
    return magcal.diagnose(ds, result, **options, mode="total_field")


# ---- the user's loop ------------------------------------------------------------------------------------------


def recommended(diagnosis):
    """The effect the diagnosis recommends adding next, as a user reads it, and its candidate (or None)."""
    by_label = {c.label: c for c in diagnosis.candidates}
    for label in list(diagnosis.explained_by) + list(diagnosis.partially_explained_by):
        return label, by_label.get(label)
    return None, None


def quality_lines(report) -> list:
    """The notable findings and warnings of a quality report, one short line each."""
    return [
        f"{f.kind}{' (warning)' if f.severity == 'warning' else ''}: {f.where}{f.summary}"
        for f in report.findings
        if f.notable or f.severity == "warning"
    ]


def rate_of(report):
    found = report.find("sample_rate")
    return found[0].values.get("rate_Hz") if found else None


def noise_record(noise) -> dict:
    """The noise estimate and its checks (nT)."""

    def values(v):
        return None if v is None else [round(float(x), 4) if np.isfinite(x) else None for x in np.asarray(v, float)]

    return {
        "sigma_nT": float(noise.sigma_nT),
        "source": noise.source,
        "note": noise.note,
        "static_noise_nT": values(noise.static_noise_nT),
        "static_scatter_nT": values(noise.static_scatter_nT),
        "quantization_floor_nT": values(noise.quantization_floor_nT),
        "text": noise.text(),
    }


def held_out(ds, effects, masks, init) -> dict:
    """Held-out RMS (nT) of the model with ``effects`` on each scheme's split (warm-started from ``init``)."""
    out = {}
    for scheme, mask_pair in masks.items():
        try:
            v = validation.validate(ds, effects=list(effects), scheme=scheme, masks=mask_pair, init=init)
            out[scheme] = float(v.held_out_rms_nT)
            out[f"{scheme}_in_sample"] = float(v.in_sample_rms_nT)
            relevelled = getattr(v, "relevelled_rms_nT", None)  # record's level on the held-out part taken out
            if relevelled is not None:
                out[f"{scheme}_relevelled"] = float(relevelled)
            out[f"{scheme}_dropped"] = list(v.dropped)
            out[f"{scheme}_n_test"] = int(v.n_test)
        except (MagcalError, np.linalg.LinAlgError) as exc:
            out[f"{scheme}_failed"] = str(exc)
    return out


def run_loop(ds, max_steps, masks, residuals=None) -> tuple[list, list]:
    """Steps of the loop (dicts) and the warnings magcal printed on the way; ``residuals`` (a list), if given,
    receives each step's total-field residuals (nT, NaN where the fit left a sample out) for the figures."""
    effects, steps, magcal_warnings = [], [], []
    added, added_cand = None, None
    for step in range(max_steps + 1):
        t0 = time.perf_counter()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            result = _calibrate(ds, effects=list(effects))
            diag = _diagnose(ds, result)
        magcal_warnings += [f"{type(w.message).__name__}: {w.message}" for w in caught]
        if residuals is not None and result.fit is not None:
            r = np.array(result.fit.residuals_nT[0], float)
            r[~result.fit.mask] = np.nan
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                v = np.asarray(result.calibration.correct(ds)[0], float)
            residuals.append((list(effects), r, v / np.linalg.norm(v, axis=1, keepdims=True)))
        if step == 0:
            magcal_warnings += [f"calibrate: {w}" for w in result.remarks]
        nxt, cand = recommended(diag)
        row = {
            "step": step,
            "added": added,
            "effects": list(effects),
            "delta_bic": None if added_cand is None else float(added_cand.delta_bic),
            "diag_held_out": None
            if added_cand is None
            else [
                added_cand.held_out_before_nT,
                added_cand.held_out_after_nT,
                added_cand.later_before_nT,
                added_cand.later_after_nT,
            ],
            "in_sample_rms_nT": float(result.rms_nT),
            "field_nT": None if result.field_magnitude_nT is None else float(result.field_magnitude_nT),
            **held_out(ds, effects, masks, result.calibration),
            "verdict": diag.verdict,
            "summary": diag.summary,
            "noise": noise_record(diag.noise if step == 0 else result.noise),
            "explained_by": list(diag.explained_by),
            "partially_explained_by": list(diag.partially_explained_by),
            "remaining": [
                s.text
                for s in _by_kind(
                    diag.remaining if diag.explained_by or diag.partially_explained_by else diag.structure
                )
            ],
            "next": nxt,
            "diagnosis_warnings": list(diag.warnings),
            "top": [
                {
                    "label": c.label,
                    "delta_bic": float(c.delta_bic),
                    "holds": c.holds,
                    "held_out": [c.held_out_before_nT, c.held_out_after_nT],
                    "later": [c.later_before_nT, c.later_after_nT],
                }
                for c in diag.candidates[:4]
            ],
            "seconds": time.perf_counter() - t0,
        }
        if step == 0:
            row["base_noise"] = noise_record(result.noise)
        steps.append(row)
        if nxt is None or nxt in effects or step == max_steps:
            break
        effects.append(nxt)
        added, added_cand = nxt, cand
    counts = {}
    for w in magcal_warnings:
        counts[w] = counts.get(w, 0) + 1
    return steps, [w if k == 1 else f"{w} (x{k})" for w, k in counts.items()]


# ---- the transfer test: advice followed on the first half, `magcal apply` on the second (issue 28) ---------------


def halves(ds):
    """The record's first and second half in time (by sample order without a time column)."""
    t = ds.time_s if ds.time_s is not None else np.arange(ds.n_samples, dtype=float)
    first = (
        t < 0.5 * (float(np.min(t)) + float(np.max(t)))
        if ds.time_s is not None
        else np.arange(ds.n_samples) < ds.n_samples // 2
    )
    return ds.subset(first), ds.subset(~first)


def applied_error(calibration, later) -> float:
    """Held-out total-field RMS (nT) of a saved calibration applied to ``later`` exactly as ``magcal apply`` does:
    the calibration written to JSON and read back, the record-only terms dropped (``later`` is another record
    than the fitted one), nothing refitted or re-levelled; the error is ``|B|`` minus the field the calibration
    expects (the first half's fitted field magnitude, or the reference given)."""
    saved = type(calibration).from_dict(json.loads(json.dumps(calibration.to_dict())))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the RecordTermWarning that names the dropped terms
        vectors = saved.correct(later)
        return _rms(saved.total_field_residuals(later, vectors))


def second_on_itself(second, effects, holds) -> dict:
    """What the second half allows: the last calibration's model fitted on the second half itself (in-sample RMS,
    nT: no calibration fitted on the first half does better there, but for the in-sample optimism of p/N), the
    same with the first record-only term the first half holds (the second half's own change, which nothing
    carries), and the second half's noise (the residuals' differences, :func:`magcal.checks.noise.estimate_noise`).
    A calibration whose held-out error is near the first figure carries as well as any fitted there: what lies
    above the floor is then the second half's own, not advice that was missed."""
    out = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            fit = _calibrate(second, effects=list(effects)).fit
            out["same_model_nT"] = float(fit.rms_nT)
            noise = estimate_noise(second.masked(fit.mask), fit.residuals_nT[:, fit.mask], fit.n_params)
            out["floor_nT"] = float(noise.sigma_nT)
            record = [h for h in holds if h.partition(":")[0] not in effects][:1]
            if record:
                out["record_term"] = record[0]
                out["with_record_term_nT"] = float(_calibrate(second, effects=list(effects) + record).fit.rms_nT)
        except (MagcalError, ValueError, np.linalg.LinAlgError) as exc:
            out["failed"] = f"{type(exc).__name__}: {exc}"
    return out


#: The second half fitted on itself, with the first half's record-only term, is at its own floor within this (the
#: diagnosis's "at the noise floor within x %", :data:`magcal.diagnosis.verdict.AT_FLOOR_FRACTION`).
SECOND_AT_FLOOR = 0.10


def second_at_floor(own) -> bool:
    """Whether the second half, fitted on itself with the last model and the first half's record-only term
    (:func:`second_on_itself`), is at its own floor within :data:`SECOND_AT_FLOOR`: a first half's verdict "at the
    floor, the rest is this record's" checked on data the diagnosis never saw."""
    best = own.get("with_record_term_nT", own.get("same_model_nT"))
    floor = own.get("floor_nT")
    return bool(best is not None and floor and best <= (1.0 + SECOND_AT_FLOOR) * floor)


def second_half_markdown(records) -> str:
    """Per recording: the second half's error with the advice followed on the first, against what the second half
    allows (:func:`second_on_itself`)."""
    lines = [
        "| recording | held-out (advice followed) | second half on itself: same model | + record term | floor | "
        "held-out / same model | second half at its floor |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in records:
        tr = r.get("transfer")
        if not tr or "refused" in tr or "second_on_itself" not in tr:
            continue
        own, held = tr["second_on_itself"], tr["rows"][-1]["held_out_rms_nT"]
        same = own.get("same_model_nT")
        extra = f"{own['with_record_term_nT']:.4g} ({own['record_term']})" if "with_record_term_nT" in own else "-"
        ratio = f"{held / same:.2f}" if same else "-"
        lines.append(
            f"| {r['name']} | {held:.4g} | {same:.4g} | {extra} | {own.get('floor_nT', float('nan')):.4g} | {ratio} | "
            f"{'yes' if second_at_floor(own) else 'no'} |"
            if same
            else f"| {r['name']} | {held:.4g} | - | - | - | - | - |"
        )
    return "\n".join(lines)


def run_transfer(ds, max_rounds=3) -> dict:
    """Follow the advice on the first half (add the first of ``explained_by``, else of ``partially_explained_by``;
    refit; diagnose again) and apply each calibration to the second half. One row per calibration: the effects,
    the verdict and advice of its diagnosis, what the record holds, and the held-out total-field RMS (nT)."""
    first, second = halves(ds)
    rows, effects = [], []
    for _ in range(max_rounds + 1):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            result = _calibrate(first, effects=list(effects))
            diag = _diagnose(first, result)
        nxt, _ = recommended(diag)
        rows.append(
            {
                "effects": list(effects),
                "in_sample_rms_nT": float(result.rms_nT),
                "held_out_rms_nT": applied_error(result.calibration, second),
                "verdict": diag.verdict,
                "next": nxt,
                "record_holds": list(getattr(diag, "record_holds", []) or []),
                "floor_nT": float(diag.floor_nT),
                "noise": diag.noise.text(),
            }
        )
        if nxt is None or nxt in effects:
            break
        effects.append(nxt)
    out = {"n_first": first.n_samples, "n_second": second.n_samples, "rows": rows}
    out["second_on_itself"] = second_on_itself(second, rows[-1]["effects"], rows[-1]["record_holds"])
    base = rows[0]["held_out_rms_nT"]
    changes = [(r["effects"][-1], r["held_out_rms_nT"] / p["held_out_rms_nT"] - 1) for p, r in zip(rows, rows[1:])]
    out["changes"] = changes
    out["never_rises_1pct"] = all(c <= 0.01 for _, c in changes)
    out["second_at_floor"] = second_at_floor(out["second_on_itself"])
    out["ends_at_floor"] = rows[-1]["verdict"] == "adequate" or bool(
        rows[-1]["verdict"] == "missing_effect" and rows[-1]["next"] is None and out["second_at_floor"]
    )
    out["falls_2pct_or_adequate"] = bool(
        rows[0]["verdict"] == "adequate" or out["ends_at_floor"] or rows[-1]["held_out_rms_nT"] <= 0.98 * base
    )
    return out


def _advice_words(tr) -> str:
    """``+effect held-out (change %); ...`` of one transfer test, or ``none``."""
    return (
        "; ".join(
            f"+{row['effects'][-1]} {row['held_out_rms_nT']:.4g} ({100 * c:+.1f} %)"
            for row, (_, c) in zip(tr["rows"][1:], tr["changes"])
        )
        or "none"
    )


def before_after_markdown(records, before) -> str:
    """The transfer test's advice before (``before``: the records of an earlier run's JSON) and now, per recording:
    the second half's error with the base calibration and with the advice followed, the last verdict and floor."""
    old = {r["name"]: r.get("transfer") for r in before}
    lines = [
        "| recording | base held-out | before: advice (held-out), last verdict | now: advice (held-out), last verdict "
        "[floor] | never +1 % | -2 % or at the floor |",
        "|---|---|---|---|---|---|",
    ]
    for r in records:
        tr, was = r.get("transfer"), old.get(r["name"])
        if not tr or "refused" in tr:
            continue
        last = tr["rows"][-1]
        was_words = "-" if not was or "refused" in was else f"{_advice_words(was)}, {was['rows'][-1]['verdict']}"
        lines.append(
            f"| {r['name']} | {tr['rows'][0]['held_out_rms_nT']:.4g} | {was_words} | {_advice_words(tr)}, "
            f"{last['verdict']} [{last['floor_nT']:.4g}] | {'yes' if tr['never_rises_1pct'] else 'NO'} | "
            f"{'yes' if tr['falls_2pct_or_adequate'] else 'no'} |"
        )
    return "\n".join(lines)


#: Record-only terms whose kept level for new data is measured by :func:`kept_level_study`.
KEPT_TERMS = ("bias_drift", "bias_step", "reference_drift")


def kept_level_study(ds) -> dict:
    """Which level of a record-only term the calibration for new data should keep (issue 28, item 3).

    Each term of :data:`KEPT_TERMS` is fitted with the base terms on the first half; the calibration is applied to
    the second half with the term dropped and its level at the first half's start, mean or end kept (a vector
    offset in the corrected frame for a bias term, the expected field for a reference drift). Returns the held-out
    total-field RMS (nT) per term and option, beside the base model's."""
    first, second = halves(ds)
    out = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        base = _calibrate(first).calibration
        out["base"] = _rms(base.total_field_residuals(second, base.correct(second, "drop"), "drop"))
        for term in KEPT_TERMS:
            if first.time_s is None:
                continue
            try:
                cal = _calibrate(first, effects=[term]).calibration
            except (MagcalError, ValueError, np.linalg.LinAlgError) as exc:
                out[term] = {"failed": str(exc)[:80]}
                continue
            offset = cal.correct(first, "apply") - cal.correct(first, "drop")  # (ns, N, 3)
            field = cal.expected_total_field(first, "apply")  # (ns, N)
            drop = cal.correct(second, "drop")
            res = {}
            for option, k in (("start", 0), ("end", first.n_samples - 1), ("mean", None)):
                v = drop + (offset.mean(axis=1, keepdims=True) if k is None else offset[:, k : k + 1])
                f = field.mean(axis=1, keepdims=True) if k is None else field[:, k : k + 1]
                res[option] = _rms(np.linalg.norm(v, axis=2) - f)
            res["as_dropped"] = _rms(cal.total_field_residuals(second, drop, "drop"))
            out[term] = res
    return out


def transfer_markdown(records) -> str:
    lines = [
        "| recording | N first / second | base: verdict, held-out | advice followed (held-out after, change) | "
        "record holds (not advised) | never +1 % | -2 % or adequate |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in records:
        tr = r.get("transfer")
        if not tr:
            continue
        if "refused" in tr:
            lines.append(f"| {r['name']} | - | refused: {tr['refused'][:120]} | | | | |")
            continue
        rows = tr["rows"]
        advice = _advice_words(tr)
        holds = ", ".join(sorted({h for row in rows for h in row["record_holds"]})) or "-"
        lines.append(
            f"| {r['name']} | {tr['n_first']} / {tr['n_second']} | {rows[0]['verdict']}, "
            f"{rows[0]['held_out_rms_nT']:.4g} | {advice} | {holds} | "
            f"{'yes' if tr['never_rises_1pct'] else 'NO'} | {'yes' if tr['falls_2pct_or_adequate'] else 'no'} |"
        )
    return "\n".join(lines)


#: Order in which the remaining structure is quoted: the physically specific kinds first.
STRUCTURE_ORDER = ("direction", "periodic", "consistency", "consistency_time", "time", "excess")


def _by_kind(structures) -> list:
    return sorted(structures, key=lambda s: STRUCTURE_ORDER.index(s.kind) if s.kind in STRUCTURE_ORDER else 99)


def judge_claim(steps) -> dict:
    """The issue's claim on one recording: held-out never rises with a recommended effect; it falls (or the
    verdict reads adequate); the loop ends adequate or unexplained with its remaining structure named.

    Rises are counted on the plain held-out RMS of both schemes (what the user's calibration does on samples it
    did not see); ``rises_beyond_half_se`` keeps those beyond :func:`magcal.fitting.validation.rise_tolerance_nT`;
    ``rises_relevelled`` judges the ``later`` scheme as magcal does when the model holds record-only terms
    (both models scored with the record's level on the later stretch taken out)."""
    rises, rises_beyond_tol, rises_relevelled, falls = [], [], [], []
    for prev, cur in zip(steps, steps[1:]):
        for scheme in validation.SCHEMES:
            if scheme not in prev or scheme not in cur:
                continue
            before, after = prev[scheme], cur[scheme]
            n_test = prev.get(f"{scheme}_n_test", 1)
            tol = validation.rise_tolerance_nT(before, n_test)
            if after > before:
                rises.append(f"{cur['added']} ({scheme}: {before:.4g} -> {after:.4g})")
                if after > before + tol:
                    rises_beyond_tol.append(f"{cur['added']} ({scheme}: {before:.4g} -> {after:.4g})")
            if scheme == "later" and cur.get("later_dropped") and "later_relevelled" in prev:
                b, a = prev["later_relevelled"], cur["later_relevelled"]
                if a > b + validation.rise_tolerance_nT(b, n_test):
                    rises_relevelled.append(f"{cur['added']} (later, relevelled: {b:.4g} -> {a:.4g})")
            elif after > before + tol:
                rises_relevelled.append(f"{cur['added']} ({scheme}: {before:.4g} -> {after:.4g})")
        if "blocks" in prev and "blocks" in cur:
            falls.append(cur["blocks"] <= (1 - validation.MIN_RELATIVE_GAIN) * prev["blocks"])
    last = steps[-1]
    return {
        "never_rises": not rises,
        "rises": rises,
        "rises_beyond_half_se": rises_beyond_tol,
        "rises_by_magcal_rule": rises_relevelled,
        "falls_or_adequate": bool(any(falls) or steps[0]["verdict"] == "adequate"),
        "end_verdict": last["verdict"],
        "end_named": bool(last["verdict"] == "adequate" or (last["verdict"] == "unexplained" and last["remaining"])),
    }


#: Most samples drawn as points in a figure (a random subset; the binned medians use every sample).
MAX_POINTS_SHOWN = 5000


def _binned_median(x, y, bins=20):
    """Bin centres and median ``y`` in equal-width bins of ``x`` (bins with under 10 finite samples left out)."""
    ok = np.isfinite(x) & np.isfinite(y)
    edges = np.linspace(np.min(x[ok]), np.max(x[ok]), bins + 1)
    which = np.clip(np.digitize(x[ok], edges) - 1, 0, bins - 1)
    centres, medians = [], []
    for k in range(bins):
        sel = y[ok][which == k]
        if sel.size >= 10:
            centres.append(0.5 * (edges[k] + edges[k + 1]))
            medians.append(float(np.median(sel)))
    return np.array(centres), np.array(medians)


def _direction_panel(fig, ax, direction, residual, model_label) -> None:
    """Mean residual (nT) of a model over the field direction it measured (azimuth, sine of elevation: equal-area
    cells); the pattern a direction term (nonlinearity, cross-field) would have to explain."""
    ok = np.isfinite(residual)
    az = np.degrees(np.arctan2(direction[ok, 1], direction[ok, 0]))
    sin_el = direction[ok, 2]
    total, xe, ye = np.histogram2d(az, sin_el, bins=(24, 12), range=((-180, 180), (-1, 1)), weights=residual[ok])
    count, _, _ = np.histogram2d(az, sin_el, bins=(24, 12), range=((-180, 180), (-1, 1)))
    mean = np.where(count >= 5, total / np.maximum(count, 1), np.nan)
    lim = np.nanpercentile(np.abs(mean), 95) if np.isfinite(mean).any() else 1.0
    image = ax.pcolormesh(xe, ye, mean.T, cmap="RdBu_r", vmin=-lim, vmax=lim)
    fig.colorbar(image, ax=ax, label="mean residual (nT)")
    ax.set_xlabel("field azimuth in the sensor frame (deg)")
    ax.set_ylabel("sin(field elevation)")
    ax.set_title(f"over the field direction: {model_label}", fontsize=8)


def figure(path: Path, ds, residuals, out_png: Path) -> None:
    """Residuals of the base model and of the loop's last model against time, temperature and (for a flight with
    a pressure column) altitude, and the last model's mean residual over the field direction, as PNG: the figure
    behind the physical reading of what is left."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = ds.time_s if ds.time_s is not None else np.arange(ds.n_samples, dtype=float)
    panels = [("time (s)" if ds.time_s is not None else "sample", t)]
    if ds.temperature_C is not None and np.ptp(ds.temperature_C) > 0.5:
        panels.append(("temperature (degC)", np.asarray(ds.temperature_C, float)))
    if "pressure_hPa" in ds.extra:
        p = np.clip(np.asarray(ds.extra["pressure_hPa"], float), 1.0, None)
        panels.append(("altitude (km, standard atmosphere from pressure)", 44.33 * (1 - (p / 1013.25) ** 0.1903)))
    fig, axes = plt.subplots(1, len(panels) + 1, figsize=(5.2 * (len(panels) + 1), 3.8), squeeze=False)
    (_, base, _), (last_effects, last, direction) = residuals[0], residuals[-1]
    _direction_panel(fig, axes[0][-1], direction, last, "+ " + ", ".join(last_effects) if last_effects else "base")
    shown = np.sort(np.random.default_rng(0).permutation(ds.n_samples)[:MAX_POINTS_SHOWN])  # the medians use all
    for ax, (label, x) in zip(axes[0], panels):
        ax.plot(x[shown], base[shown], ".", ms=1.5, color="0.75", label="base model (lines: binned medians)")
        if len(residuals) > 1:
            ax.plot(x[shown], last[shown], ".", ms=1.5, color="C0", alpha=0.4, label="+ " + ", ".join(last_effects))
        for r, colour in ((base, "0.3"), (last, "C0")) if len(residuals) > 1 else ((base, "0.3"),):
            centres, medians = _binned_median(x, r)
            ax.plot(centres, medians, "-", color=colour, lw=1.5)
        finite = base[np.isfinite(base)]
        if finite.size:
            lo, hi = np.percentile(finite, [0.5, 99.5])
            ax.set_ylim(lo - 0.1 * (hi - lo), hi + 0.1 * (hi - lo))
        if label.startswith("altitude"):
            field = float(np.nanmedian(np.linalg.norm(ds.readings_nT[0], axis=1)))
            h = np.linspace(0, np.nanmax(x), 20)
            ok = np.isfinite(base)
            offset = float(np.nanmean(base[ok] + 3 * field * x[ok] / 6371.0))
            ax.plot(h, offset - 3 * field * h / 6371.0, "r-", label="dipole: dF/dh = -3F/R")
        ax.set_xlabel(label)
        ax.set_ylabel("total-field residual (nT)")
        ax.legend(loc="best", fontsize=7, markerscale=5)
    fig.suptitle(f"{path.stem}: residuals of the loop's first and last model", fontsize=9)
    fig.tight_layout()
    out_png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_png, dpi=90)
    plt.close(fig)


def transfer_record(ds, rounds) -> dict:
    """:func:`run_transfer`, or why the record was refused."""
    try:
        return run_transfer(ds, rounds)
    except (MagcalError, ValueError, np.linalg.LinAlgError) as exc:
        return {"refused": f"{type(exc).__name__}: {exc}"}


def run_recording(
    path: Path, max_steps: int, figure_dir: Path | None = None, transfer_rounds: int = 3, loop: bool = True
) -> dict:
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            ds = magcal.read_csv(path)
        except ValueError as exc:  # DatasetError: the file is at fault; say so and go on with the others
            return {
                "name": path.stem,
                "n": 0,
                "sensors": 0,
                "refused": f"read_csv: {exc}",
                "steps": [],
                "quality": [],
                "independent": {},
                "seconds": time.perf_counter() - t0,
            }
    rec = {
        "name": path.stem,
        "n": int(ds.n_samples),
        "sensors": int(ds.n_sensors),
        "read_warnings": [str(w.message) for w in caught],
    }
    norm = np.linalg.norm(ds.readings_nT, axis=2)
    rec["raw_magnitude_nT"] = {
        "mean": float(norm.mean()),
        "rms_about_mean": float(norm.std()),
        "p5": float(np.percentile(norm, 5)),
        "p95": float(np.percentile(norm, 95)),
    }
    if transfer_rounds:
        rec["transfer"] = transfer_record(ds, transfer_rounds)
    if not loop:
        rec.update(steps=[], quality=[], independent={}, seconds=time.perf_counter() - t0, loop_run=False)
        return rec
    quality = assess(ds)
    rec["rate_Hz"] = rate_of(quality)
    rec["quality"] = quality_lines(quality)
    masks = {}
    problem = validation.split_problem(ds)
    if problem:
        rec["split_problem"] = problem
    else:
        masks = {scheme: validation.holdout_masks(ds, scheme) for scheme in validation.SCHEMES}
    residuals = []
    try:
        rec["steps"], rec["magcal_warnings"] = run_loop(ds, max_steps, masks, residuals)
    except (MagcalError, ValueError) as exc:
        rec["refused"] = f"{type(exc).__name__}: {exc}"
        rec["steps"], rec["magcal_warnings"] = [], []
    if rec["steps"]:
        field = rec["steps"][0]["field_nT"]
        found = field_magnitude_finding(field) if field else None
        rec["field_finding"] = None if found is None else found.summary
        rec["claim"] = judge_claim(rec["steps"])
    rec["independent"] = independent_fit(ds, masks) if masks else {}
    if not masks:  # too short to split: in-sample only
        try:
            rec["independent"] = {
                "in_sample_rms_nT": _rms(
                    np.concatenate(
                        [
                            independent_residuals(ds.readings_nT[s], *fit_ellipsoid_independent(ds.readings_nT[s]))
                            for s in range(ds.n_sensors)
                        ]
                    )
                )
            }
        except EllipsoidFailure as exc:
            rec["independent"] = {"failed": str(exc)}
    if figure_dir is not None and residuals:
        rec["figure"] = str(figure_dir / f"real_{path.stem}.png")
        figure(path, ds, residuals, Path(rec["figure"]))
    rec["seconds"] = time.perf_counter() - t0
    return rec


# ---- output ---------------------------------------------------------------------------------------------------


def _f(v, fmt="{:.4g}"):
    return "-" if v is None else fmt.format(v)


def markdown(records) -> str:
    """The tables of benchmarks/notes/real.md: one line per recording, one per loop step."""
    lines = [
        "| recording | N | rate (Hz) | field (uT) | noise (nT, method) | still scatter (nT) | quantization floor "
        "(nT) | independent ellipsoid in / blocks / later | data quality (notable) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in records:
        if not r["steps"]:
            raw = r.get("raw_magnitude_nT") or {}
            kinds = ", ".join(sorted({q.split(":")[0] for q in r["quality"]}))
            lines.append(
                f"| {r['name']} | {r['n']} | {_f(r.get('rate_Hz'))} | raw "
                f"{_f(raw.get('mean', 0) / 1000, '{:.1f}')} +- {_f(raw.get('rms_about_mean'), '{:.0f}')} nT | "
                f"refused: {r.get('refused', '')[:150]} | | | {_independent_text(r['independent'])} | "
                f"{kinds or '-'} |"
            )
            continue
        noise = r["steps"][0]["noise"]
        ind_text = _independent_text(r["independent"])
        kinds = sorted({q.split(":")[0] for q in r["quality"]})
        lines.append(
            f"| {r['name']} | {r['n']} | {_f(r.get('rate_Hz'))} | {_f(r['steps'][0]['field_nT'] / 1000, '{:.1f}')} | "
            f"{noise['sigma_nT']:.3g} ({noise['source']}) | {_list(noise['static_scatter_nT'])} | "
            f"{_list(noise['quantization_floor_nT'])} | {ind_text} | {', '.join(kinds) or '-'} |"
        )
    lines += [
        "",
        "| recording | step | effect added | dBIC | in-sample | held-out blocks | held-out later "
        "(relevelled) | verdict | next recommended |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in records:
        for s in r["steps"]:
            later = _f(s.get("later"))
            if s.get("later_relevelled") is not None:
                later += f" ({s['later_relevelled']:.4g})"
            lines.append(
                f"| {r['name']} | {s['step']} | {s['added'] or 'base'} | {_f(s['delta_bic'], '{:.0f}')} | "
                f"{s['in_sample_rms_nT']:.4g} | {_f(s.get('blocks'))} | {later} | "
                f"{s['verdict']} | {s['next'] or '-'} |"
            )
    lines += [
        "",
        "| recording | held-out never rises (plain RMS; rises beyond 0.5 SE in bold) | later relevelled for "
        "record-only terms (for reading: magcal judges the plain RMS since issue 28) | falls or adequate | loop "
        "ends | structure named at the end |",
        "|---|---|---|---|---|---|",
    ]
    for r in records:
        c = r.get("claim")
        if not c:
            continue
        rises = (
            "yes"
            if c["never_rises"]
            else "no: " + "; ".join(f"**{x}**" if x in c["rises_beyond_half_se"] else x for x in c["rises"])
        )
        rule = "yes" if not c["rises_by_magcal_rule"] else "NO: " + "; ".join(c["rises_by_magcal_rule"])
        named = "; ".join(t[:120] for t in r["steps"][-1]["remaining"][:3]) or (
            "(no structure test; supported candidates that do not hold)" if c["end_verdict"] == "unexplained" else "-"
        )
        lines.append(
            f"| {r['name']} | {rises} | {rule} | {'yes' if c['falls_or_adequate'] else 'no'} | "
            f"{c['end_verdict']} | {named} |"
        )
    return "\n".join(lines)


def _independent_text(ind):
    if not ind:
        return "-"
    return ind.get("failed") or " / ".join(
        _f(ind.get(k)) for k in ("in_sample_rms_nT", "blocks_rms_nT", "later_rms_nT")
    )


def _list(v):
    return "-" if not v else ", ".join("-" if x is None else f"{x:.3g}" for x in v)


def write_outputs(records, out_json: Path) -> None:
    out_json.parent.mkdir(parents=True, exist_ok=True)
    out_json.write_text(json.dumps(records, indent=1, default=lambda o: o.item() if hasattr(o, "item") else str(o)))
    fields = [
        "recording",
        "n",
        "rate_Hz",
        "step",
        "added",
        "delta_bic",
        "in_sample_rms_nT",
        "blocks_rms_nT",
        "later_rms_nT",
        "verdict",
        "next",
        "noise_nT",
        "noise_source",
        "independent_in_nT",
        "independent_blocks_nT",
        "independent_later_nT",
    ]
    with open(out_json.with_suffix(".csv"), "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(fields)
        for r in records:
            ind = r.get("independent", {})
            for s in r["steps"] or [{}]:
                w.writerow(
                    [
                        r["name"],
                        r["n"],
                        r.get("rate_Hz"),
                        s.get("step"),
                        s.get("added"),
                        s.get("delta_bic"),
                        s.get("in_sample_rms_nT"),
                        s.get("blocks"),
                        s.get("later"),
                        s.get("verdict", r.get("refused")),
                        s.get("next"),
                        (s.get("noise") or {}).get("sigma_nT"),
                        (s.get("noise") or {}).get("source"),
                        ind.get("in_sample_rms_nT"),
                        ind.get("blocks_rms_nT"),
                        ind.get("later_rms_nT"),
                    ]
                )


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("names", nargs="*", help="recordings (file stems in benchmarks/real/data); default all")
    parser.add_argument("--steps", type=int, default=3, help="most effects added by the loop (default 3)")
    parser.add_argument("--data-dir", type=Path, default=DATA_DIR)
    parser.add_argument(
        "--out",
        type=Path,
        default=None,
        help="JSON output (default benchmarks/out/real_loop.json; real_transfer.json with --transfer-only)",
    )
    parser.add_argument(
        "--figures",
        action="store_true",
        help="also draw each recording's residuals (first and last model) against time, temperature "
        "and altitude: <out dir>/real_<name>.png",
    )
    parser.add_argument(
        "--rounds", type=int, default=3, help="most pieces of advice followed by the transfer test (default 3; 0: none)"
    )
    parser.add_argument("--transfer-only", action="store_true", help="only the transfer test (first half -> second)")
    parser.add_argument(
        "--before",
        type=Path,
        default=None,
        help="an earlier run's real_transfer.json: print its advice beside this run's (before_after_markdown)",
    )
    parser.add_argument(
        "--kept",
        action="store_true",
        help="also measure which level a record-only term should leave for new data (kept_level_study)",
    )
    args = parser.parse_args(argv)
    if args.out is None:
        args.out = OUT_DIR / ("real_transfer.json" if args.transfer_only else "real_loop.json")
    paths = sorted(args.data_dir.glob("*.csv"))
    if args.names:
        paths = [p for p in paths if p.stem in args.names]
    if not paths:
        print(
            f"no recordings in {args.data_dir}: run python benchmarks/real/fetch.py --mirror DIR (or without) and "
            "python benchmarks/real/convert.py --all first",
            file=sys.stderr,
        )
        return 1
    check_independent_fit()
    records = []
    t0 = time.perf_counter()
    for path in paths:
        rec = run_recording(
            path, args.steps, args.out.parent if args.figures else None, args.rounds, not args.transfer_only
        )
        records.append(rec)
        tr = rec.get("transfer")
        if tr:
            print(
                f"{rec['name']} transfer: "
                + (
                    tr.get("refused")
                    or " -> ".join(
                        f"{'+'.join(r['effects']) or 'base'} {r['held_out_rms_nT']:.4g} [{r['verdict']}]"
                        + (f" holds {','.join(r['record_holds'])}" if r["record_holds"] else "")
                        for r in tr["rows"]
                    )
                ),
                flush=True,
            )
        steps = " -> ".join(
            f"{s['added'] or 'base'} {s['in_sample_rms_nT']:.4g}/{_f(s.get('blocks'))}/"
            f"{_f(s.get('later'))} [{s['verdict']}]"
            for s in rec["steps"]
        ) or rec.get("refused")
        print(f"{rec['name']}: N={rec['n']} ({rec['seconds']:.1f} s): {steps}", flush=True)
    if args.kept:
        print("\nkept level of record-only terms fitted on the first half, held-out RMS on the second (nT):")
        print("| recording | base | " + " | ".join(f"{t}: start / mean / end (as dropped)" for t in KEPT_TERMS) + " |")
        print("|---|---|" + "---|" * len(KEPT_TERMS))
        for path in paths:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                ds = magcal.read_csv(path)
            try:
                k = kept_level_study(ds)
            except (MagcalError, ValueError, np.linalg.LinAlgError) as exc:
                print(f"| {path.stem} | refused: {str(exc)[:60]} |" + " |" * len(KEPT_TERMS))
                continue
            cells = []
            for t in KEPT_TERMS:
                x = k.get(t)
                cells.append(
                    "-"
                    if x is None
                    else x.get("failed")
                    or f"{x['start']:.4g} / {x['mean']:.4g} / {x['end']:.4g} ({x['as_dropped']:.4g})"
                )
            print(f"| {path.stem} | {k['base']:.4g} | " + " | ".join(cells) + " |", flush=True)
    print()
    print(transfer_markdown(records))
    print()
    print(second_half_markdown(records))
    if args.before is not None:
        print()
        print(before_after_markdown(records, json.loads(args.before.read_text(encoding="utf-8"))))
    for group, keep in (
        ("all", lambda n: True),
        ("documented", lambda n: not n.startswith("broad_")),
        ("BROAD", lambda n: n.startswith("broad_")),
    ):
        done = [r["transfer"] for r in records if keep(r["name"]) and r.get("transfer") and "rows" in r["transfer"]]
        if done:
            print(
                f"\n{group}: advice never raises the held-out error by more than 1 %: "
                f"{sum(t['never_rises_1pct'] for t in done)}/{len(done)}; lowers it by 2 % or more, or the first "
                f"verdict is adequate, or it ends at the floor (checked on the second half): "
                f"{sum(t['falls_2pct_or_adequate'] for t in done)}/{len(done)}"
            )
    print()
    looped = [r for r in records if r.get("loop_run", True)]
    print(markdown(looped) if looped else "(the loop was not run: --transfer-only)")
    print(f"\ntotal {time.perf_counter() - t0:.0f} s; written {args.out} and {args.out.with_suffix('.csv')}")
    write_outputs(records, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
