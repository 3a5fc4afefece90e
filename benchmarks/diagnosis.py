"""Benchmark of the diagnosis (issue 4): does it find a hidden effect, how much does adding it help, how fast?

Part 1, effect x magnitude: for every catalogue effect, at three magnitudes (barely detectable, moderate,
strong), hide it in a 1 500-sample time series (chi2017 sensors, sigma = 3 nT; one sensor, or four for the
inter-sensor effects) and report the rank of the true effect among the candidates, the delta-BIC of adding it,
the total-field RMS of the seed's two-step calibration (ellipsoid + Procrustes), of the ML base model and of the
ML model with the effect found, next to the noise floor, and the verdict.

Part 2, speed: wall time of a full diagnosis (base calibration included) for N = 1e3, 1e4, 1e5 samples, one
sensor and four, and of ``read_csv`` + diagnosis of a four-sensor 1 500-sample file (issue 4: well under 10 s).

Usage::

    python benchmarks/diagnosis.py            # about 3-4 minutes on 2 shared cores
    python benchmarks/diagnosis.py --quick    # one seed, no N = 1e5
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
import warnings

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # one BLAS thread: faster on a shared 2-core machine

import numpy as np

import magcal.model.effects as fx
from magcal.core import conventions
from magcal.data import io
from magcal.data.simulation import chi2017_truth, simulate_timeseries
from magcal.diagnosis import diagnose
from magcal.fitting.pipeline import calibrate
from magcal.model import perturbations
from magcal.model.terms import EFFECTS

SIGMA = 3.0
N = 1500
LEVELS = fx.DETECTION_LEVELS  # barely detectable, moderate, strong (x default magnitude)


def consistency_rms(vectors):
    """RMS per component of the inter-sensor consistency (as the fitter defines it) of corrected vectors."""
    ns = vectors.shape[0]
    mean = vectors.mean(axis=0)
    u = mean / np.linalg.norm(mean, axis=1, keepdims=True)
    diff = vectors - mean
    perp = diff - np.einsum("sni,ni->sn", diff, u)[..., None] * u
    return float(np.sqrt(np.sum(perp**2) * ns / (ns - 1) / (2 * ns * vectors.shape[1])))


def rank_of(d, name):
    for i, c in enumerate(d.candidates, 1):
        if c.effect == name:
            return i, c
    return None, None


def part1(seeds):
    print("Part 1: hidden effect x magnitude (N = 1500, sigma = 3 nT; rank of the true effect, 1 = found first)")
    print(
        f"{'effect':<24}{'magnitude':>22}{'rank':>9}{'dBIC':>10}{'two-step':>10}{'ML base':>9}{'+effect':>9}"
        f"{'floor':>7}  verdicts"
    )
    for name, levels in LEVELS.items():
        cls = EFFECTS[name]
        ns = 4 if cls.min_sensors > 1 else 1
        for mult in levels:
            magnitude = mult * cls.default_magnitude
            ranks, dbics, rms2, rms0, rms1, floors, verdicts = [], [], [], [], [], [], []
            for seed in seeds:
                ds = simulate_timeseries(
                    chi2017_truth(ns),
                    n_samples=N,
                    noise_nT=SIGMA,
                    seed=seed,
                    perturbations=[cls().perturbation(magnitude)],
                )
                two = calibrate(ds, method="ellipsoid")
                base = calibrate(ds)
                d = diagnose(ds, base)
                rank, cand = rank_of(d, name)
                ranks.append(rank)
                dbics.append(cand.delta_bic)
                refit = d.fits.get(cand.label)
                if refit is None:  # not among the refitted: fit it for the table
                    refit = calibrate(ds, effects=[name]).fit
                if name == "sensor_timing_skew":  # invisible in the total field: the consistency residual

                    def vec(f):
                        v = f.consistency_residuals_nT
                        return float(np.sqrt(np.sum(v**2) / (2 * v.shape[0] * v.shape[1])))

                    rms0.append(vec(base.fit))
                    rms1.append(vec(refit))
                    rms2.append(consistency_rms(two.calibration.correct(ds)))
                else:
                    rms0.append(base.fit.rms_nT)
                    rms1.append(refit.rms_nT)
                    rms2.append(float(np.sqrt(np.mean(two.rms_after_per_sensor_nT**2))))
                floors.append(conventions.total_field_floor_nT(SIGMA, N, refit.n_params / ns))
                verdicts.append(d.verdict)
            counts = {v: verdicts.count(v) for v in sorted(set(verdicts))}
            print(
                f"{name:<24}{magnitude:>9.3g} {cls.magnitude_unit:<12}{','.join(str(r) for r in ranks):>9}"
                f"{np.median(dbics):>10.0f}{np.nanmedian(rms2):>10.2f}{np.median(rms0):>9.2f}{np.median(rms1):>9.2f}"
                f"{np.median(floors):>7.2f}  {counts}"
            )
    print(
        "(sensor_timing_skew: RMS of the inter-sensor consistency residual per component; it does not change the"
        " total field)"
    )
    print(
        "Periodic interference 8 nT at 0.7 Hz, one sensor: with its catalogue term, and with the term left out"
        " (an effect outside the catalogue must read unexplained, not be attributed to another term):"
    )
    outside = [n for n in EFFECTS if n != "periodic_interference"]
    found, unnamed = [], []
    for seed in seeds:
        ds = simulate_timeseries(
            chi2017_truth(1),
            n_samples=N,
            noise_nT=SIGMA,
            seed=seed,
            perturbations=[perturbations.periodic_interference(8.0, 0.7)],
        )
        d = diagnose(ds)
        found.append(
            f"{d.verdict} {'+'.join(d.explained_by) or '-'}"
            + (f" (record holds {'+'.join(d.record_holds)})" if d.record_holds else "")
        )
        unnamed.append(diagnose(ds, candidates=outside).verdict)
    print(f"  in the catalogue: {found}")
    print(f"  left out of the candidates: {unnamed}")
    print("Clean data (no hidden effect):")
    for ns in (1, 4):
        verdicts = [
            diagnose(simulate_timeseries(chi2017_truth(ns), n_samples=N, noise_nT=SIGMA, seed=200 + s)).verdict
            for s in range(10 if len(seeds) > 1 else 3)
        ]
        print(f"  {ns} sensor(s): {verdicts.count('adequate')}/{len(verdicts)} adequate")


def timed(fn, repeats):
    times = []
    out = None
    for _ in range(repeats):
        start = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - start)
    return float(np.median(times)), out


def part2(sizes):
    print()
    print("Part 2: wall time of a full diagnosis (base calibration + score tests + refits), temperature_bias hidden")
    print(f"{'sensors':>8}{'N':>9}{'calibrate s':>13}{'diagnose s':>12}{'total s':>9}  verdict / best")
    for ns in (1, 4):
        for n in sizes:
            ds = simulate_timeseries(
                chi2017_truth(ns),
                n_samples=n,
                noise_nT=SIGMA,
                seed=1,
                perturbations=[perturbations.parse_hidden("temperature_bias=0.5", ns)],
            )
            repeats = 3 if n <= 10_000 else 1
            t_cal, res = timed(lambda: calibrate(ds), repeats)
            t_diag, d = timed(lambda: diagnose(ds, res), repeats)
            print(
                f"{ns:>8}{n:>9}{t_cal:>13.3f}{t_diag:>12.2f}{t_cal + t_diag:>9.2f}  {d.verdict} / "
                f"{d.candidates[0].label}"
            )
    ds = simulate_timeseries(
        chi2017_truth(4),
        n_samples=1500,
        noise_nT=SIGMA,
        seed=2,
        perturbations=[perturbations.parse_hidden("hysteresis:3", 4)],
    )
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "four.csv")
        io.write_csv(path, ds)

        def run():
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                data = io.read_csv(path)
            return diagnose(data)

        t_file, d = timed(run, 5)
    print(
        f"four-sensor 1500-sample file, read_csv + diagnose (median of 5): {t_file:.2f} s  ({d.verdict}, "
        f"{d.candidates[0].label})"
    )


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="one seed and N up to 1e4")
    args = parser.parse_args(argv)
    seeds = [1] if args.quick else [1, 2, 3]
    sizes = [1_000, 10_000] if args.quick else [1_000, 10_000, 100_000]
    start = time.perf_counter()
    part1(seeds)
    part2(sizes)
    print(f"\ntotal {time.perf_counter() - start:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
