"""Study of the real recordings: what magcal's model leaves in the residuals of real sensors.

For each converted recording (``convert.py --all``) this prints, and writes as JSON to
``data/out/<name>.study.json``:

* the record: N, rate from the time stamps (median interval and N / duration), jitter, gaps, stale samples;
* the quantization step per axis (nT and LSB) from the spacing of the distinct values;
* noise: magcal's estimate, the scatter of the static stretches magcal's quality report finds, a known still
  interval (QMC: the logger's first 60 s) and a robust second-difference estimate of the raw axes;
* in-sample and held-out total-field RMS (fit on the odd 10-s blocks, evaluate on the even ones) for the base
  model and for each effect ``magcal diagnose`` ranks with a negative dBIC;
* the residual of the base fit against time (trend, spectrum peak), temperature, field direction (spherical-
  harmonic power per degree) and the rate of change of the axes (axis timing skew).

Usage: ``python benchmarks/real/study.py [NAME ...]`` (default: every CSV in ``data/``).
"""

from __future__ import annotations

import json
import sys
import warnings
from pathlib import Path

import numpy as np

from magcal.checks.quality import assess
from magcal.core.errors import MagcalError
from magcal.data.io import read_csv
from magcal.diagnosis import diagnose
from magcal.diagnosis.statistics import sh_analysis
from magcal.fitting.pipeline import calibrate

HERE = Path(__file__).resolve().parent
DATA = HERE / "data"
OUT = DATA / "out"

#: Length of the alternating fit / evaluation blocks, s (samples when the record has no rate).
BLOCK_S = 10.0
BLOCK_SAMPLES_NO_RATE = 200
#: Still interval known from the logger (QMC recordings: 60 s "initialization time").
KNOWN_STILL_S = {"qmc_filtered": 60.0, "qmc_noisy": 60.0}


def quantization(values_nT: np.ndarray, lsb_nT: float | None) -> dict:
    """Most common spacing of the distinct values per axis (nT, and in LSB when known), and the mean spacing."""
    out = {"step_nT": [], "mean_step_nT": [], "step_lsb": []}
    for v in values_nT.T:
        u = np.unique(v)
        d = np.diff(u)
        d = d[d > 1e-9 * max(1.0, abs(u).max())]
        vals, counts = np.unique(np.round(d, 6), return_counts=True)
        step = float(vals[np.argmax(counts)]) if vals.size else float("nan")
        # mean spacing within dense runs (gaps under 3 steps): the effective resolution
        dense = d[d < 3 * step] if vals.size else d
        out["step_nT"].append(step)
        out["mean_step_nT"].append(float(dense.mean()) if dense.size else float("nan"))
        out["step_lsb"].append(step / lsb_nT if lsb_nT else None)
    return out


def timing(t: np.ndarray | None, n: int) -> dict:
    if t is None:
        return {"has_time": False}
    dt = np.diff(t)
    med = float(np.median(dt))
    return {
        "has_time": True,
        "duration_s": float(t[-1] - t[0]),
        "rate_mean_Hz": float((n - 1) / (t[-1] - t[0])),
        "median_interval_s": med,
        "interval_p5_p95_s": [float(np.percentile(dt, 5)), float(np.percentile(dt, 95))],
        "jitter_rel": float(np.std(dt) / np.mean(dt)),
        "gaps_over_3_mean": int(np.sum(dt > 3 * np.mean(dt))),
        "longest_interval_s": float(dt.max()),
    }


def second_difference_noise(y: np.ndarray) -> list:
    """Robust per-axis sigma from second differences (MAD / 0.6745 / sqrt(6)); motion inflates it, stale
    samples deflate it."""
    d2 = np.diff(y, n=2, axis=0)
    mad = np.median(np.abs(d2 - np.median(d2, axis=0)), axis=0)
    return (mad / 0.6745 / np.sqrt(6.0)).tolist()


def blocks(ds) -> np.ndarray:
    """Block index per sample: 10-s blocks by time, or fixed sample counts without time."""
    if ds.time_s is not None:
        return np.floor((ds.time_s - ds.time_s[0]) / BLOCK_S).astype(int)
    return np.arange(ds.n_samples) // BLOCK_SAMPLES_NO_RATE


def rms(x) -> float:
    x = np.asarray(x, dtype=float)
    return float(np.sqrt(np.mean(x[np.isfinite(x)] ** 2)))


def held_out(ds, effects=(), robust=False) -> dict:
    """Fit on the odd blocks, RMS on the fitted (odd) and the held-out (even) samples."""
    b = blocks(ds)
    fit_mask = (b % 2) == 1
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = calibrate(ds, effects=list(effects), robust=robust, mask=fit_mask)
        r = res.calibration.total_field_residuals(ds, record_terms="apply")[0]
    return {
        "fit_rms_nT": rms(r[fit_mask]),
        "heldout_rms_nT": rms(r[~fit_mask]),
        "n_fit": int(fit_mask.sum()),
        "n_heldout": int((~fit_mask).sum()),
    }


def spectrum_peak(r: np.ndarray, t: np.ndarray | None) -> dict:
    """Strongest spectral line of the residual (Lomb-Scargle on the time stamps, or per sample)."""
    from scipy.signal import lombscargle

    x = r - r.mean()
    if t is None:
        t = np.arange(len(r), dtype=float)
        unit = "cycles/sample"
    else:
        unit = "Hz"
    span = t[-1] - t[0]
    f = np.linspace(2.0 / span, 0.5 / np.median(np.diff(t)) if unit == "Hz" else 0.5, 4000)
    p = lombscargle(t, x, 2 * np.pi * f, normalize=True)
    k = int(np.argmax(p))
    amp = 2 * np.sqrt(p[k] * np.var(x) / 1.0) / np.sqrt(2)  # rough amplitude of the line, nT
    top = np.argsort(p)[::-1]
    peaks = []
    for i in top:
        if all(abs(f[i] - f[j]) > 3 * (f[1] - f[0]) for j in peaks):
            peaks.append(int(i))
        if len(peaks) == 3:
            break
    return {
        "unit": unit,
        "peaks": [{"f": float(f[i]), "power_fraction": float(p[i])} for i in peaks],
        "amplitude_nT": float(amp),
    }


def residual_structure(ds, res) -> dict:
    """Residual of the base fit against time, temperature, direction and the axes' rate of change."""
    cal = res.calibration
    B = cal.correct(ds)[0]
    r = cal.total_field_residuals(ds, corrected=B[None])[0]
    u = B / np.linalg.norm(B, axis=1)[:, None]
    out = {"rms_nT": rms(r)}
    t = ds.time_s
    tt = t if t is not None else np.arange(len(r), dtype=float)
    A = np.c_[np.ones_like(tt), tt - tt.mean()]
    coef = np.linalg.lstsq(A, r, rcond=None)[0]
    out["trend_nT_per_min" if t is not None else "trend_nT_per_1000_samples"] = float(
        coef[1] * (60.0 if t is not None else 1000.0)
    )
    out["spectrum"] = spectrum_peak(r, t)
    if ds.temperature_C is not None:
        T = ds.temperature_C
        out["temperature_span_K"] = float(T.max() - T.min())
        out["corr_residual_temperature"] = float(np.corrcoef(r, T)[0, 1]) if T.std() > 0 else None
        # residual ~ (T - T0) x degree-1 pattern (temperature bias) by least squares
        X = (T - T.mean())[:, None] * u
        c = np.linalg.lstsq(X, r, rcond=None)[0]
        out["temperature_bias_nT_per_K"] = c.tolist()
        out["corr_temperature_time"] = float(np.corrcoef(T, tt)[0, 1]) if T.std() > 0 else None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sh = sh_analysis(u, r)
    out["sh"] = {
        k: (np.asarray(v).tolist() if hasattr(v, "__len__") else v)
        for k, v in sh.items()
        if k in ("degree", "rms_nT", "p")
    }
    if t is not None:
        # axis timing skew: r ~ sum_j tau_j u_j dB_j/dt  (first-order; tau in s)
        dB = np.gradient(B, t, axis=0)
        X = u * dB
        ok = np.all(np.isfinite(X), axis=1)
        tau, *_ = np.linalg.lstsq(X[ok], r[ok], rcond=None)
        fit = X[ok] @ tau
        out["timing_skew_tau_ms"] = (1e3 * tau).tolist()
        out["timing_skew_rms_explained_nT"] = rms(fit)
        out["field_rate_rms_nT_per_s"] = rms(np.linalg.norm(dB, axis=1))
    # residual size against the field rate of change (motion) in quartiles
    if t is not None:
        speed = np.linalg.norm(np.gradient(u, t, axis=0), axis=1)  # rad/s of the field direction
        qs = np.quantile(speed, [0, 0.25, 0.5, 0.75, 1.0])
        out["rms_by_turn_rate_quartile_nT"] = [rms(r[(speed >= qs[i]) & (speed <= qs[i + 1])]) for i in range(4)]
        out["turn_rate_quartiles_deg_s"] = np.degrees(qs).tolist()
    return out


def study(name: str) -> dict:
    path = DATA / f"{name}.csv"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ds = read_csv(path)
    y = ds.readings_nT[0]
    lsb = float(ds.metadata["lsb_nT"]) if "lsb_nT" in ds.metadata else None
    rep = {
        "name": name,
        "N": ds.n_samples,
        "timing": timing(ds.time_s, ds.n_samples),
        "stale_fraction": float(np.mean(np.all(np.diff(y, axis=0) == 0, axis=1))),
        "quantization": quantization(y, lsb),
        "noise_second_difference_nT": second_difference_noise(y),
    }
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        q = assess(ds).to_dict()
    for f in q.get("findings", []):
        if f["kind"] == "static":
            rep["static_magcal"] = {k: f["values"].get(k) for k in ("count", "fraction", "longest_s", "scatter_nT")}
    if name in KNOWN_STILL_S and ds.time_s is not None:
        still = ds.time_s - ds.time_s[0] < KNOWN_STILL_S[name]
        seg = y[still]
        rep["known_still"] = {
            "seconds": KNOWN_STILL_S[name],
            "std_nT": seg.std(axis=0).tolist(),
            "second_difference_nT": second_difference_noise(seg),
        }
    robust = False
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            base = calibrate(ds)
    except MagcalError as exc:
        rep["base_error"] = str(exc)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                base = calibrate(ds, robust=True)
            robust = True
            rep["robust_used"] = True
        except MagcalError as exc2:
            rep["robust_error"] = str(exc2)
            return rep
    rep["field_nT"] = base.field_magnitude_nT
    rep["magcal_noise_nT"] = base.noise_nT
    rep["scale"] = base.calibration.to_dict()["sensors"][0]["scale"]
    rep["axis_angles_deg"] = base.calibration.to_dict()["sensors"][0]["axis_angles_deg"]
    rep["base"] = {"in_sample_rms_nT": base.rms_nT, **held_out(ds, robust=robust)}
    rep["residual"] = residual_structure(ds, base)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            dg = diagnose(ds, base, top=3).to_dict()
        rep["diagnose_verdict"] = dg["verdict"]
        rep["diagnose_noise_nT"] = dg["noise_nT"]
        cands = [c for c in dg["candidates"] if c["delta_bic"] is not None and c["delta_bic"] < 0]
    except MagcalError as exc:
        rep["diagnose_error"] = str(exc)
        cands = []
    rep["effects"] = {}
    for c in cands[:4]:
        label = c["effect"] if c["sensor"] is None else f"{c['effect']}:{c['sensor']}"
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                full = calibrate(ds, effects=[label], robust=robust)
            rep["effects"][label] = {
                "delta_bic": c["delta_bic"],
                "refitted": c["refitted"],
                "in_sample_rms_nT": full.rms_nT,
                **held_out(ds, [label], robust),
            }
        except MagcalError as exc:
            rep["effects"][label] = {"error": str(exc)}
    return rep


def summary_line(rep: dict) -> str:
    if "base" not in rep:
        return f"{rep['name']}: N={rep['N']} no fit: {rep.get('robust_error', rep.get('base_error'))}"
    b = rep["base"]
    eff = "; ".join(
        f"{k}: {v.get('in_sample_rms_nT', float('nan')):.1f}/{v.get('heldout_rms_nT', float('nan')):.1f}"
        for k, v in rep["effects"].items()
    )
    return (
        f"{rep['name']}: N={rep['N']} field {rep['field_nT']:.0f} nT, noise(magcal) {rep['magcal_noise_nT']:.1f}, "
        f"base in/held-out {b['in_sample_rms_nT']:.1f}/{b['heldout_rms_nT']:.1f} nT; {eff}"
    )


def main(argv=None) -> int:
    names = (argv if argv is not None else sys.argv[1:]) or sorted(p.stem for p in DATA.glob("*.csv"))
    OUT.mkdir(parents=True, exist_ok=True)
    for name in names:
        rep = study(name)
        (OUT / f"{name}.study.json").write_text(json.dumps(rep, indent=1, default=float))
        print(summary_line(rep), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
