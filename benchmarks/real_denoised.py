"""Noise is not an effect: the readings-dependent terms on simulated records that hold noise and nothing else.

A hand-tumbled record of one sensor (the simulator's trajectory, 6000 samples at 10 Hz, no reference) with white
noise of 0.5 to 2 % of the field and no effect: the diagnosis's verdict, and the delta-BIC of every candidate whose
basis is a function of the readings (supported below -10). For the nonlinearities the same fit with the basis
evaluated on the noisy readings (the earlier basis) is shown beside the one on the denoised readings
(:class:`magcal.model.effects._PowerNonlinearity`): a power of a noisy reading compresses the noise along the field,
and that gain also shows on held-out blocks, so a gate on held-out data does not stop it; a noise-only simulation of
the record's own trajectory would (the gate the issue proposed), and the denoised basis makes that gate unneeded.

Usage::

    python benchmarks/real_denoised.py            # about 1 min on 2 shared cores
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from magcal.data.simulation import chi2017_truth, simulate_timeseries
from magcal.diagnosis import diagnose
from magcal.fitting.pipeline import calibrate
from magcal.model import effects as _effects
from magcal.model.terms import EFFECTS

FIELD_NT = chi2017_truth(1).total_nT
FRACTIONS = (0.005, 0.01, 0.015, 0.02)
SEEDS = (3, 4)
NONLINEAR = ("nonlinearity_quadratic", "nonlinearity_cubic")


def tumbled(noise_nT, seed, n=6000):
    """The record of tests/test_diagnosis_floor.py: no effect, the noise to be estimated."""
    ds = simulate_timeseries(
        chi2017_truth(1),
        n_samples=n,
        noise_nT=noise_nT,
        seed=seed,
        rate_hz=10.0,
        with_reference=False,
        with_attitude=False,
    )
    return ds.replace(noise_nT=None)


def delta_bic(base, fit) -> float:
    """``m ln(RSS1/RSS0) + k ln m`` of ``fit`` over ``base`` (the samples both used)."""
    m = int(base.mask.sum())
    k = fit.n_params - base.n_params
    return float(m * np.log((fit.rms_nT / base.rms_nT) ** 2) + k * np.log(m))


def noisy_basis_fit(ds, name):
    """The term fitted with its basis a power of the noisy reading (``ellipsoid_cinv`` None)."""
    original = _effects._PowerNonlinearity.configure

    def configure(self, dataset, residuals_nT=None):
        original(self, dataset, residuals_nT)
        self.ellipsoid_cinv = None

    _effects._PowerNonlinearity.configure = configure
    try:
        return calibrate(ds, effects=[name]).fit
    finally:
        _effects._PowerNonlinearity.configure = original


def main() -> int:
    t0 = time.perf_counter()
    print(
        "| noise (% of F) | seed | verdict | readings-dependent candidates: delta-BIC (most supported first) |"
        " cubic: denoised / noisy basis (dBIC) | quadratic: denoised / noisy basis (dBIC) |"
    )
    print("|---|---|---|---|---|---|")
    for fraction in FRACTIONS:
        for seed in SEEDS:
            ds = tumbled(fraction * FIELD_NT, seed)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                d = diagnose(ds, workers=1)
                base = calibrate(ds).fit
                cols = []
                for name in reversed(NONLINEAR):
                    clean = calibrate(ds, effects=[name]).fit
                    noisy = noisy_basis_fit(ds, name)
                    cols.append(f"{delta_bic(base, clean):+.0f} / {delta_bic(base, noisy):+.0f}")
            dependent = sorted(
                (c.delta_bic, c.label)
                for c in d.candidates
                if getattr(EFFECTS.get(c.effect), "basis_uses_readings", False)
            )
            words = ", ".join(f"{label} {v:+.0f}" for v, label in dependent[:4])
            print(f"| {100 * fraction:g} | {seed} | {d.verdict} | {words} | {cols[0]} | {cols[1]} |")
    print(f"\n{time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
