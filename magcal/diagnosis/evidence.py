"""The evidence shown with a diagnosis: one line per candidate, and the plot data of the residuals.

:data:`SIGNATURES` says in one line how each catalogue effect shows in the residuals; :func:`_evidence_line` and
:func:`_effect_extra` write the evidence column of the candidate table. :func:`_time_evidence`,
:func:`_temperature_evidence` and :func:`_sensor_evidence` collect plain arrays (residuals in nT against time in
s, temperature in degC, between sensors) for ``Diagnosis.evidence`` and the workbench plots.
"""

from __future__ import annotations

import numpy as np
from scipy import stats

from magcal.core import conventions
from magcal.core.stats import moving_mean
from magcal.diagnosis._fitted import _consistency_rms_per_sensor
from magcal.diagnosis.scores import Candidate
from magcal.diagnosis.statistics import (
    REVISIT_CLOSER_KNOTS,
    REVISIT_MAX_ELEMENTS,
    cusum_test,
    durbin_watson,
    ljung_box,
    revisit_forms,
)
from magcal.model.effects import hat_columns, series_spacing_s, step_scan, wander_knots
from magcal.model.terms import EffectTexts

#: One-line signature of each effect, for the evidence column: what each registered effect says of itself
#: (:attr:`magcal.model.terms.Effect.signature`).
SIGNATURES = EffectTexts("signature")


def _evidence_line(c: Candidate, extra: str = "") -> str:
    p_text = f"p={c.p_value:.1g}" if c.p_value > 1e-300 else "p<1e-300"
    parts = [f"score LM={c.lm:.1f} on {c.n_params} parameter(s) ({p_text})"]
    if extra:
        parts.append(extra)
    parts.append(SIGNATURES.get(c.effect, ""))
    if c.instances and getattr(c.instances[0], "ellipsoid_cinv", None) is not None:
        parts.append(DENOISED_WORDS)
    return "; ".join(p for p in parts if p)


#: What the evidence line says of a term whose basis is evaluated on the denoised readings
#: (:class:`magcal.model.effects._PowerNonlinearity`): its gain is not the noise's. On simulated tumbled records of
#: noise alone (0.5-2 % of the field) its delta-BIC is its parameter penalty, +19 to +25, where a power of the noisy
#: reading reached -26 to -72 (``benchmarks/real_denoised.py``): a gain compared with a noise-only simulation of the
#: record would be compared with nothing.
DENOISED_WORDS = (
    "basis from the denoised readings (the noise along the field is not fitted: on a record of noise alone the term "
    "gains nothing, so no noise-only comparison is needed)"
)


#: The terms of a change within seconds: their evidence line says what same-direction revisits tell of the change
#: (:func:`revisit_words`).
CHANGE_EFFECTS = ("field_change", "offset_wander")

#: Why an offset series' fitted size is not a measurement (:class:`magcal.model.effects.OffsetWander`).
OFFSET_SIZE_WORDS = (
    "its fitted size is not determined: between two knots the field direction sweeps a short arc, and on it an "
    "offset trades against the arc's curvature (a record without any wander fits hundreds of nT of it), so the "
    "series says that the residual changes within seconds and follows the direction, not by how much the offset "
    "moved"
)


def revisit_words(kept, fit, directions) -> str:
    """What samples revisiting one field direction say of a change in time, or "": each sensor's residuals of
    ``fit`` against hat functions at the series' knots, and on knots :data:`REVISIT_CLOSER_KNOTS` times closer for
    a change faster than them (:func:`~magcal.diagnosis.statistics.revisit_forms`)."""
    if kept.time_s is None or fit is None:
        return ""
    t = np.asarray(kept.time_s, dtype=float)
    try:
        knots = wander_knots(t, series_spacing_s(kept))
        columns = hat_columns(t, knots)[:, 1:]
        finer = np.linspace(knots[0], knots[-1], REVISIT_CLOSER_KNOTS * (len(knots) - 1) + 1)
        # the pace test's series, where its design stays small (a long record keeps the series' knots alone)
        fine = hat_columns(t, finer)[:, 1:] if 4 * len(t) * len(finer) <= REVISIT_MAX_ELEMENTS else None
    except ValueError:
        return ""
    r = np.asarray(fit.residuals_nT, dtype=float)[:, fit.mask]
    parts = []
    for s, u in enumerate(directions):
        found = revisit_forms(u, r[s], t, columns, fine_columns=fine) if r.shape[1] == len(t) else None
        if found is not None:
            parts.append((f"sensor {s + 1}: " if len(directions) > 1 else "") + found.text())
    return "; ".join(parts)


def _effect_extra(c: Candidate, kept, fit, directions, sh_stats) -> str:
    """Effect-specific numbers for the evidence line."""
    if c.effect == "bias_step":
        times: list = []
        for e in c.instances:
            step_times_s = getattr(e, "step_time_s", None)
            if step_times_s:
                times.extend(t for t in step_times_s if t is not None)
        if times:
            return "step near t = " + ", ".join(f"{t:.4g} s" for t in sorted(set(np.round(times, 3))))
    if c.effect in ("nonlinearity_quadratic", "nonlinearity_cubic") and sh_stats:
        degree = 3 if c.effect == "nonlinearity_quadratic" else 4
        sensors = [c.sensor] if c.sensor is not None else range(len(sh_stats))
        rms = [sh_stats[s]["rms_nT"][degree] for s in sensors]
        rms = [v for v in rms if np.isfinite(v)]
        if not rms:  # withheld by sh_analysis: the coverage does not resolve the degree
            top = max(int(sh_stats[s].get("max_resolved_degree", -1)) for s in sensors)
            return (
                f"direction degree {degree}: not resolved by the coverage (directions resolve degrees up to "
                f"{top}), so its size is not measured"
            )
        return f"direction degree {degree}: {max(rms):.2g} nT"
    if c.effect in CHANGE_EFFECTS:
        words = [revisit_words(kept, fit, directions)]
        if c.effect == "offset_wander":
            words.append(OFFSET_SIZE_WORDS)
        return "; ".join(w for w in words if w)
    if (
        c.effect in ("temperature_bias", "temperature_scale", "bias_drift", "reference_drift")
        and kept.temperature_C is not None
        and kept.time_s is not None
    ):
        rho = abs(np.corrcoef(kept.temperature_C, kept.time_s)[0, 1])
        return f"|corr(T, t)| = {rho:.2f}"
    return ""


def _time_evidence(kept, r, ordered):
    t = kept.time_s if kept.time_s is not None else np.arange(kept.n_samples, dtype=float)
    n = len(t)
    # a running mean over a sixtieth of the record (running sums: a convolution with the window was O(N^2 / 60),
    # 11 s of a 4 x 1e6 diagnosis)
    smooth = moving_mean(r, max(1, n // 60))
    ev = {
        "x": t,
        "y": r,
        "smooth": smooth,
        "x_label": "time (s)" if kept.time_s is not None else "sample",
        "durbin_watson": np.array([durbin_watson(row) for row in r]),
    }
    if ordered:
        lb = [ljung_box(row) for row in r]
        ev["ljung_box_p"] = np.array([x[1] for x in lb])
        cs = [cusum_test(row) for row in r]
        ev["cusum"] = {
            "index": np.array([c[0] for c in cs]),
            "statistic": np.array([c[1] for c in cs]),
            "p": np.array([c[2] for c in cs]),
            "time": np.array([t[c[0]] for c in cs]),
        }
        if kept.time_s is not None:
            scans = [step_scan(kept.readings_nT[s]) for s in range(r.shape[0])]
            ev["step_scan"] = {
                "rss_drop_nT2": np.array([sc[1] for sc in scans]),
                "time": np.array([t[sc[0]] for sc in scans]),
            }
    return ev


def _temperature_evidence(kept, r, directions):
    if kept.temperature_C is None:
        return None
    temp = kept.temperature_C
    d_t = temp - temp.mean()
    p_vals = []
    for s in range(r.shape[0]):
        u = directions[s]
        base = np.column_stack([np.ones(len(d_t)), u])
        full = np.column_stack([base, d_t[:, None] * base])
        rss0 = np.sum((r[s] - base @ np.linalg.lstsq(base, r[s], rcond=None)[0]) ** 2)
        rss1 = np.sum((r[s] - full @ np.linalg.lstsq(full, r[s], rcond=None)[0]) ** 2)
        f = (rss0 - rss1) / 4 / max(rss1 / (len(d_t) - 8), 1e-300)
        p_vals.append(float(stats.f.sf(f, 4, len(d_t) - 8)))
    order = np.argsort(temp)
    return {"x": temp, "y": r, "x_label": "temperature (degC)", "f_test_p": np.array(p_vals), "sorted_index": order}


def _sensor_evidence(kept, fit, r, fields):
    ns = r.shape[0]
    if ns < 2:
        return None
    common = r.mean(axis=0)
    diffs = r - common
    ev = {
        "common_mode_nT": common,
        "differences_nT": diffs,
        "common_mode_rms_nT": float(np.sqrt(np.mean(common**2))),
        "difference_rms_nT": np.sqrt(np.mean(diffs**2, axis=1)),
        "correlation": np.corrcoef(r),
    }
    vr = _consistency_rms_per_sensor(fit)
    if vr is not None:
        ev["consistency_rms_nT"] = vr
    if ns == 4 and fit.calibration.baseline_m:
        g = conventions.tensor_components(fields, fit.calibration.baseline_m)
        tensor = conventions.tensor_matrix(g)
        norm = np.sqrt(np.sum(tensor**2, axis=(1, 2)))
        ev["tensor_norm_nT_per_m"] = norm
        ev["tensor_mean_nT_per_m"] = {k: float(np.mean(v)) for k, v in g.items()}
    return ev
