"""What the terms of a field or an offset that changes within seconds, and the jitter between sensors, give on the
real recordings: each half of a record fitted on its own (first half, second half), so that a gain seen on one half
is seen again on the other.

Per recording and half it prints the total-field RMS (nT) of

* the base model (bias, scale, non-orthogonality; misalignment for the two-sensor board);
* the terms the catalogue had: ``reference_drift`` (a record-long Legendre series of the field) and ``bias_drift``;
* the new ones: ``field_change`` (the field as a hat series, knots every 3 s, wider on a long record) and
  ``offset_wander`` (each sensor's offset as a hat series per axis);

with the gain over the base model (percent of the RMS) and the delta-BIC of each term over the base model
(``m ln(RSS/m) + k ln m``, the diagnosis's criterion; the term is supported below -10), the floor (the noise from the
residuals' second differences, :func:`magcal.checks.noise.estimate_noise`), and, for the two-sensor board (ads_rm3100
and ads_icm20948 read on one payload), the sampling jitter of the ICM-20948 against the RM3100 under the base model
and under ``offset_wander`` (:func:`magcal.diagnosis.jitter.jitter_estimates`), and how samples revisiting one field
direction (within 5 deg) drift apart with the time between the visits under each model (:func:`revisit_drift`).
It also prints what the data-quality
check before the fit says of a part in another field (:func:`magcal.checks.quality.other_field_finding`).

Usage::

    python benchmarks/real_wander.py                    # the four records (about 2 min on 2 shared cores)
    python benchmarks/real_wander.py sf_fullsphere

The recordings are in ``benchmarks/real/data`` (``benchmarks/real/README.md``).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # the shared 2-core machine: a second BLAS thread only contends

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from magcal.checks.noise import estimate_noise
from magcal.checks.quality import other_field_finding
from magcal.data import io
from magcal.data.dataset import Dataset
from magcal.diagnosis._fitted import _sensor_directions
from magcal.diagnosis.jitter import jitter_estimates
from magcal.fitting.pipeline import calibrate

DATA = Path(__file__).resolve().parent / "real" / "data"
RECORDS = {
    "sf_fullsphere": ("HMC5883L", ["sf_fullsphere"]),
    "qmc_filtered": ("QMC5883L", ["qmc_filtered"]),
    "ads_rm3100": ("RM3100 alone", ["ads_rm3100"]),
    "ads_board": ("RM3100 + ICM-20948", ["ads_rm3100", "ads_icm20948"]),
}
TERMS = ("reference_drift", "bias_drift", "field_change", "offset_wander")


def load(name) -> Dataset:
    """One record, or the two-sensor board as one two-sensor dataset (the same rows and time stamps)."""
    parts = [io.read_csv(DATA / f"{file}.csv", warn=False) for file in RECORDS[name][1]]
    if len(parts) == 1:
        return parts[0]
    first = parts[0]
    readings = np.concatenate([p.readings_nT for p in parts], axis=0)
    return Dataset(readings, time_s=first.time_s, temperature_C=first.temperature_C, source=name)


def halves(ds) -> list:
    t = ds.time_s
    middle = 0.5 * (t[0] + t[-1])
    return [("first half", ds.subset(t <= middle)), ("second half", ds.subset(t > middle))]


def bic(fit) -> float:
    r = fit.residuals_nT[:, fit.mask]
    m = r.size
    return float(m * np.log(np.sum(r**2) / m) + fit.n_params * np.log(m))


def revisit_drift(fit, ds, max_angle_deg=5.0, most=200_000) -> list:
    """Samples revisiting one field direction (within ``max_angle_deg``, sensor 1's corrected field): the RMS (nT)
    of their total-field residuals' difference by quartile of the time between the two visits, and the quartiles'
    upper edges (s). A field or an offset that changes in time makes revisits drift apart with the time between."""
    kept = ds.masked(fit.mask)
    directions, _ = _sensor_directions(kept, fit)
    u, r, t = directions[0], fit.residuals_nT[0, fit.mask], kept.time_s
    chord = 2.0 * np.sin(np.radians(max_angle_deg) / 2.0)
    pairs = cKDTree(u).query_pairs(chord, output_type="ndarray")
    if len(pairs) > most:
        pairs = pairs[np.random.default_rng(0).choice(len(pairs), most, replace=False)]
    gap = np.abs(t[pairs[:, 1]] - t[pairs[:, 0]])
    far = gap > 1.0  # not the same pass
    gap, diff = gap[far], (r[pairs[:, 1]] - r[pairs[:, 0]])[far]
    edges = np.quantile(gap, [0.25, 0.5, 0.75, 1.0])
    which = np.searchsorted(edges, gap, side="left")
    return [(float(edges[q]), float(np.sqrt(np.mean(diff[which == q] ** 2)))) for q in range(4)]


def study_half(ds) -> dict:
    base = calibrate(ds).fit
    noise = estimate_noise(ds.masked(base.mask), base.residuals_nT[:, base.mask], base.n_params)
    row = {"n": ds.n_samples, "duration_s": float(ds.time_s[-1] - ds.time_s[0]), "base": base.rms_nT}
    row["revisits_base"] = revisit_drift(base, ds)
    row["floor"] = float(noise.sigma_nT)
    b0 = bic(base)
    fits = {}
    for term in TERMS:
        fit = calibrate(ds, effects=[term]).fit
        fits[term] = fit
        row[term] = fit.rms_nT
        row[f"{term}_dbic"] = bic(fit) - b0
        row[f"{term}_k"] = fit.n_params - base.n_params
    for term in ("field_change", "offset_wander"):
        row[f"revisits_{term}"] = revisit_drift(fits[term], ds)
    wander = fits["offset_wander"]
    effect = wander.model.effects[0]
    row["wander_quote"] = "; ".join(
        f"sensor {s + 1}: {effect.quote(wander.calibration.effect_values[f'offset_wander:{s + 1}'])}"
        for s in range(ds.n_sensors)
    )
    field = fits["field_change"]
    row["field_quote"] = field.model.effects[0].quote(field.calibration.effect_values["field_change"])
    if ds.n_sensors > 1:
        row["jitter_base"] = jitter_estimates(ds.masked(base.mask), base)[0]
        row["jitter_wander"] = jitter_estimates(ds.masked(wander.mask), wander)[0]
    return row


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("records", nargs="*", default=list(RECORDS), help=f"of {', '.join(RECORDS)}")
    args = parser.parse_args(argv)
    warnings.simplefilter("ignore")
    start = time.perf_counter()
    for name in args.records:
        ds = load(name)
        finding = other_field_finding(ds)
        print(f"\n## {name} ({RECORDS[name][0]}): {ds.n_samples} samples, {ds.time_s[-1] - ds.time_s[0]:.0f} s")
        print(f"part in another field: {finding.summary if finding else 'none'}")
        print(
            "| half | N | s | floor | base | "
            + " | ".join(f"+{t} (k, dBIC)" for t in TERMS)
            + " |\n|"
            + "---|" * (5 + len(TERMS))
        )
        for label, half in halves(ds):
            row = study_half(half)
            cells = [
                f"{row[t]:.4g} ({100 * (1 - row[t] / row['base']):+.1f} %; {row[f'{t}_k']}, {row[f'{t}_dbic']:.0f})"
                for t in TERMS
            ]
            print(
                f"| {label} | {row['n']} | {row['duration_s']:.0f} | {row['floor']:.4g} | {row['base']:.4g} | "
                + " | ".join(cells)
                + " |"
            )
            print(f"    field_change: {row['field_quote']}; offset_wander: {row['wander_quote']}")
            for key in ("base", "field_change", "offset_wander"):
                drift = ", ".join(f"{v:.0f}" for _, v in row[f"revisits_{key}"])
                tops = ", ".join(f"{e:.0f}" for e, _ in row[f"revisits_{key}"])
                print(f"    revisits within 5 deg ({key}): residual difference {drift} nT at time apart up to {tops} s")
            for key in ("jitter_base", "jitter_wander"):
                if key in row:
                    j = row[key]
                    print(
                        f"    jitter ({key.split('_')[1]} model): {j['jitter_rms_ms']:.3g} +- {j['jitter_se_ms']:.2g} ms "
                        f"(z {j['z']:.1f}, {'named' if j['significant'] else 'not named'}); inter-sensor residual by "
                        f"turn-rate quartile {', '.join(f'{v:.0f}' for v in j['rms_by_rate_quartile_nT'])} nT at "
                        f"{', '.join(f'{v:.0f}' for v in j['rate_quartiles_dps'][1:])} deg/s (quartile tops); "
                        f"constant delay {j['delay_ms']:.3g} ms"
                    )
    print(f"\n{time.perf_counter() - start:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
