"""The field a record gives itself: a vector calibration with the lab's field fitted, and a field that is not uniform.

Simulated (truth known, :func:`magcal.data.lab.simulate_lab`: a hand-held sensor under motion capture, 1 deg
optical attitude, 5 nT sensor noise, 3000 samples):

* tumbled, the lab's field unknown: the fitted field against the truth in its own standard deviations, and the
  next record's world RMS with the fitted calibration and field against the true calibration's;
* turned about the vertical only: what the report names;
* a magnet (0.5 A m^2) 0.3 m from the path: the diagnosis's finding, what the calibration file carries.

Real (``benchmarks/real/data/broad_*.csv``, the BROAD motion-capture records, when present): per trial the fitted
field against the converter's estimate (its header's ``lab_field_ned_nT``: the trial's ellipsoid fit turned into NED
and averaged), the next trial's world RMS with the calibration and field of this one against the same with the
estimate typed in (``--reference-vector``: what a user did before), and the uniformity finding on the stationary
magnet trials (28-31), the translations (10-18) and the attached magnet (32-36), each judged with the calibration
and field of trial 01.

    python benchmarks/lab_field.py              # simulated and, when present, BROAD
    python benchmarks/lab_field.py --no-real    # simulated only
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from magcal.checks.reference import VectorReference, resolve_vector_reference
from magcal.data.io import read_csv
from magcal.data.lab import lab_truth, simulate_lab
from magcal.diagnosis.uniformity import field_uniformity
from magcal.diagnosis.vector import diagnose_vector
from magcal.fitting.vector import fit_vector, true_calibration

DATA = os.path.join(os.path.dirname(os.path.abspath(__file__)), "real", "data")
MAGNET = ((0.0, 0.35, 0.0), (0.0, 0.0, 0.5))


def world_rms(calibration, dataset, field_ned_nT) -> float:
    world = calibration.world(dataset)[0]
    ok = np.all(np.isfinite(world), axis=1)
    return float(np.sqrt(np.mean((world[ok] - field_ned_nT) ** 2)))


def simulated(seeds, n):
    print(f"Simulated lab, tumbled, field unknown ({n} samples, 1 deg attitude, 5 nT noise):")
    print("seed | fitted - true field (N, E, D) / its sd | next record's world RMS: fitted / true calibration")
    for seed in seeds:
        truth = lab_truth(seed=seed)
        ds, _ = simulate_lab(truth, n=n, seed=seed)
        res = fit_vector(ds, "fitted", warn=False)
        z = (res.field.ned_nT - truth.field_ned_nT) / res.field.sd_nT
        nxt, _ = simulate_lab(truth, n=n, seed=seed + 100)
        ours = world_rms(res.calibration, nxt, res.field.ned_nT)
        best = world_rms(true_calibration(truth), nxt, truth.field_ned_nT)
        print(
            f"{seed} | {z[0]:+.2f}, {z[1]:+.2f}, {z[2]:+.2f} (sd {np.array2string(res.field.sd_nT, precision=1)} nT) "
            f"| {ours:.1f} / {best:.1f} nT = {ours / best:.3f}x"
        )
    truth = lab_truth(seed=5)
    ds, _ = simulate_lab(truth, n=n, seed=5, motion="yaw")
    res = fit_vector(ds, "fitted", warn=False)
    print("\nTurned about the vertical only (tilts within 3 deg):")
    for g in res.field.gauges:
        print(f"  - {g}")
    print("\nA magnet (0.5 A m^2) 0.3 m from the path:")
    magnet, _ = simulate_lab(truth, n=n, seed=6, dipole=MAGNET)
    d = diagnose_vector(magnet, resolve_vector_reference(magnet, "fitted"), max_effects=0, validate=False)
    named = [w for w in d.warnings if "not uniform" in w]
    print(f"  named: {bool(named)}: {named[0][:220] if named else '-'}")
    cal = fit_vector(magnet, "fitted", field_gradient=True, warn=False).calibration
    print(f"  with --field-gradient the calibration's effects: {cal.model.effect_labels if cal.model else []} (apply)")
    clean, _ = simulate_lab(truth, n=n, seed=7)
    d = diagnose_vector(clean, resolve_vector_reference(clean, "fitted"), max_effects=0, validate=False)
    print(f"  the same lab without the magnet named: {any('not uniform' in w for w in d.warnings)}")


def estimate_of(ds) -> np.ndarray:
    return np.array([float(v) for v in str(ds.metadata["lab_field_ned_nT"]).split(",")])


def given(ds, ned) -> VectorReference:
    return VectorReference(np.tile(ned, (ds.n_samples, 1)), "estimate", "vector")


def real_rotations(trials):
    print("\nBROAD rotation trials: fitted field vs the converter's estimate; the next trial's world RMS")
    print("trial | fitted N, E, D +- sd (nT) | estimate N, E, D | dec / inc (deg) | next: fitted / estimate typed")
    sets = {k: read_csv(os.path.join(DATA, f"broad_{k}.csv"), warn=False) for k in trials}
    for k, nxt in zip(trials, trials[1:] + [None]):
        ds = sets[k]
        t0 = time.perf_counter()
        res = fit_vector(ds, "fitted", warn=False)
        f, est = res.field, estimate_of(ds)
        line = (
            f"{k} | {f.ned_nT[0]:.0f}, {f.ned_nT[1]:.0f}, {f.ned_nT[2]:.0f} +- {f.sd_nT[0]:.0f}, {f.sd_nT[1]:.0f}, "
            f"{f.sd_nT[2]:.0f} | {est[0]:.0f}, {est[1]:.0f}, {est[2]:.0f} | {f.declination_deg:.2f} / "
            f"{f.inclination_deg:.2f}" + ("" if f.determined else " NOT DETERMINED")
        )
        if nxt is not None:
            old = fit_vector(ds, given(ds, est), warn=False)
            line += (
                f" | {world_rms(res.calibration, sets[nxt], f.ned_nT):.0f} / "
                f"{world_rms(old.calibration, sets[nxt], est):.0f} nT"
            )
        print(line + f" ({time.perf_counter() - t0:.0f} s)")


def real_uniformity(trials, base="01"):
    ds0 = read_csv(os.path.join(DATA, f"broad_{base}.csv"), warn=False)
    res = fit_vector(ds0, "fitted", warn=False)
    sigma = res.sensors[0].sigma_total_field_nT
    print(
        f"\nBROAD: judged with trial {base}'s calibration and field (|B| {res.field.total_nT:.0f} nT, noise {sigma:.0f})"
    )
    print("trial | |B| RMS (nT) | same place / same attitude share | named not uniform | own fit's field N, E, D")
    for k in trials:
        path = os.path.join(DATA, f"broad_{k}.csv")
        if not os.path.exists(path):
            continue
        ds = read_csv(path, warn=False)
        total = np.linalg.norm(res.calibration.correct(ds, warn=False), axis=2) - res.field.total_nT
        u = field_uniformity(ds, total, np.ones(ds.n_samples, bool), sigma)
        rms = float(np.sqrt(np.nanmean(total**2)))
        try:
            own_field = fit_vector(ds, "fitted", warn=False).field
            own = own_field.ned_nT
            own_text = f"{own[0]:.0f}, {own[1]:.0f}, {own[2]:.0f}" + ("" if own_field.determined else " NOT DETERMINED")
        except Exception as exc:  # a translation barely turns: refused, said
            own_text = f"not fitted ({str(exc).split(':')[1].strip()[:40]})"
        print(
            f"{k} | {rms:.0f} | {u.share_position:.2f} / {u.share_attitude:.2f} | "
            f"{'yes' if not u.uniform else 'no'} ({u.anomaly_rms_nT:.0f} nT) | {own_text}"
        )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--no-real", action="store_true", help="simulated records only")
    parser.add_argument("--seeds", type=int, default=5, help="simulated seeds (default 5)")
    parser.add_argument("-n", type=int, default=3000, help="simulated samples (default 3000)")
    args = parser.parse_args()
    simulated(range(args.seeds), args.n)
    if not args.no_real and os.path.exists(os.path.join(DATA, "broad_01.csv")):
        real_rotations([f"{k:02d}" for k in range(1, 10)])
        real_uniformity([f"{k:02d}" for k in (2, 10, 11, 12, 14, 15, 16, 18, 28, 29, 30, 31, 32, 33, 34, 35, 36)])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
