"""Level-table platform alignment (patent S5-S8): recovered angles vs truth vs the Cramer-Rao bound vs the patent.

Run: ``python benchmarks/platform_alignment.py`` (about a minute).

Setup: the Chi et al. (2017) Table 1 sensors with sensor 1 also misaligned to the platform
(:func:`magcal.fitting.platform.platform_truth`), F = 50 000 nT, I = 55 deg, Gaussian sigma = 3 nT per axis (the seed's
noise), three level-table groups (x_up, y_up, z_up) of N_g samples each, the array turned to random headings.

Printed:

1. per sensor and angle: the truth, the RMS error over Monte Carlo runs with the exact intrinsic calibration,
   the mean reported Cramer-Rao sd, their ratio (1 = efficient), and the patent's "1/1000 level" read as
   1e-3 x |angle|, with the share of estimates inside it;
2. the whole procedure (scalar calibration on N = 200 free rotations first, S3-S4, then S7-S8): RMS error against
   the sd with the intrinsic uncertainty propagated;
3. what the seed's frame (sensor 1, Chi's Procrustes) would leave: sensor 1's own misalignment to the platform;
4. the bound against N_g.
"""

from __future__ import annotations

import time
import warnings

import numpy as np

from magcal.calibration.calibration import Calibration, SensorCalibration
from magcal.data import simulation as sim
from magcal.fitting import platform as pf

SIGMA = 3.0
NAMES = ("alpha", "beta", "gamma")


def exact_intrinsic(truth):
    return Calibration(
        [SensorCalibration(s.Cinv, s.bias_nT) for s in truth.sensors],
        reference_total_nT=truth.total_nT,
        baseline_m=truth.baseline_m,
    )


def monte_carlo(truth, n_group, runs, seed0=1000):
    cal = exact_intrinsic(truth)
    est, std, times = [], [], []
    for k in range(runs):
        ds = pf.simulate_level_table(truth, n_per_group=n_group, noise_nT=SIGMA, seed=seed0 + k)
        t0 = time.perf_counter()
        _, res = pf.align(ds, cal, noise_nT=SIGMA)
        times.append(time.perf_counter() - t0)
        est.append(res.angles_rad)
        std.append(res.angles_std_rad)
    return np.array(est), np.array(std), float(np.median(times))


def main():
    truth = pf.platform_truth()
    true = np.array([[s.alpha, s.beta, s.gamma] for s in truth.sensors])
    runs, n_group = 200, 100
    est, std, t_align = monte_carlo(truth, n_group, runs)
    err = est - true
    rms = np.sqrt(np.mean(err**2, axis=0))
    bound = std.mean(axis=0)
    claim = 1e-3 * np.abs(true)
    inside = np.mean(np.abs(err) < claim, axis=0)
    print(
        f"1. exact intrinsic calibration, {runs} runs, N_g = {n_group} per group, sigma = {SIGMA} nT "
        f"(median {1e3 * t_align:.1f} ms per 4-sensor alignment)"
    )
    print(
        f"{'sensor':>6} {'angle':>6} {'truth mrad':>11} {'RMS err urad':>13} {'CRLB urad':>10} {'RMS/CRLB':>9} "
        f"{'1e-3|angle| urad':>17} {'share inside':>13}"
    )
    for i in range(4):
        for j in range(3):
            print(
                f"{i + 1:>6} {NAMES[j]:>6} {1e3 * true[i, j]:>11.1f} {1e6 * rms[i, j]:>13.2f} {1e6 * bound[i, j]:>10.2f} "
                f"{rms[i, j] / bound[i, j]:>9.2f} {1e6 * claim[i, j]:>17.1f} {100 * inside[i, j]:>12.0f}%"
            )
    print(
        f"   over all 12 angles: RMS/CRLB {np.mean(rms / bound):.3f}; median relative RMS error "
        f"{np.median(rms / np.abs(true)):.1e}; share of estimates within 1e-3 x |angle|: {100 * np.mean(inside):.0f}%; "
        f"largest error {1e6 * np.max(np.abs(err)):.1f} urad = {np.degrees(np.max(np.abs(err))):.5f} deg"
    )

    from magcal.fitting.pipeline import calibrate

    runs2 = 30
    errs2, std2 = [], []
    for k in range(runs2):
        free = sim.simulate(truth, n_samples=200, noise_nT=SIGMA, seed=5000 + k)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            cal = calibrate(free).calibration
        icov = np.array(
            [pf.intrinsic_covariance(free.readings_nT[i], c.cinv, c.bias_nT, SIGMA) for i, c in enumerate(cal.sensors)]
        )
        ds = pf.simulate_level_table(truth, n_per_group=n_group, noise_nT=SIGMA, seed=6000 + k)
        _, res = pf.align(ds, cal, noise_nT=SIGMA, intrinsic_cov=icov)
        errs2.append(res.angles_rad - true)
        std2.append(res.angles_std_rad)
    errs2, std2 = np.array(errs2), np.array(std2)
    rms2 = np.sqrt(np.mean(errs2**2, axis=0))
    print(f"\n2. whole procedure: scalar calibration (ML, N = 200 free rotations) then alignment, {runs2} runs")
    print(
        f"   RMS error {1e6 * rms2.mean():.1f} urad (angles' mean), reported sd with the intrinsic uncertainty "
        f"{1e6 * std2.mean():.1f} urad, ratio {np.mean(rms2 / std2.mean(axis=0)):.2f}; alignment-only bound "
        f"{1e6 * bound.mean():.1f} urad"
    )
    print(f"   share within the patent's 1e-3 x |angle|: {100 * np.mean(np.abs(errs2) < 1e-3 * np.abs(true)):.0f}%")

    print(
        "\n3. sensor 1's frame instead of the platform's (Chi 2017 Procrustes): every vector keeps sensor 1's "
        "misalignment"
    )
    s1 = truth.sensors[0]
    print(
        f"   sensor 1 to platform: {pf.rotation_error_rad(s1.R, np.eye(3))[0] * 1e3:.1f} mrad "
        f"(alpha, beta, gamma = {1e3 * s1.alpha:.0f}, {1e3 * s1.beta:.0f}, {1e3 * s1.gamma:.0f} mrad) against "
        f"{1e6 * bound.mean():.0f} urad after the level-table alignment"
    )

    print("\n4. Cramer-Rao sd (urad, mean over angles) against samples per group; sigma/(H sqrt(N_g)) beside it")
    h = truth.total_nT * np.cos(np.radians(truth.inclination_deg))
    for n in (10, 25, 100, 400):
        _, s, _ = monte_carlo(truth, n, 5, seed0=9000)
        print(
            f"   N_g = {n:4d}: {1e6 * s.mean():7.2f} urad   sigma/(H sqrt(N_g)) = {1e6 * SIGMA / (h * np.sqrt(n)):7.2f} "
            f"urad; patent 1e-3 x median |angle| = {1e6 * 1e-3 * np.median(np.abs(true)):.1f} urad"
        )


if __name__ == "__main__":
    main()
