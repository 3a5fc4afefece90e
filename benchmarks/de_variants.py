"""Which differential-evolution changes help on the scalar-calibration objective (eq. 17)?

Command::

    python benchmarks/de_variants.py          # ~1-2 min on 2 shared cores

For 8 records (both Ding presets x 4 noise realisations, N = 150, uniform noise of full width 2 nT) and 3 search
seeds each, every variant runs until its best RMS is within 0.1 % of the exact least-squares minimum (found by
Levenberg-Marquardt from the truth) or 1500 generations pass. Printed: how many runs got there, and the median and
90th-percentile objective evaluations they needed. ``magcal.fitting.search``'s ``de`` is the row ``ours``.
"""

from __future__ import annotations

import sys
import time

import numpy as np
from scipy.optimize import differential_evolution, least_squares
from scipy.stats import qmc

import magcal
from magcal.core import conventions
from magcal.fitting import search

FIELD_NT = 51_500.0
MAX_GEN = 1500


class Reached(Exception):
    pass


def records():
    out = []
    for preset in ("ding2024", "ding2024-fluxgate"):
        sensor = magcal.PRESETS[preset].truth().sensors[0]
        m = sensor.total_matrix
        p0 = search.pack(conventions.cinv_from_quadric(np.linalg.inv(m @ m.T)), sensor.total_offset_nT)
        for k in range(4):
            y = magcal.simulate(preset, n_samples=150, noise_nT=2.0, seed=k).readings_nT[0]
            f = search.ScalarObjective(y, FIELD_NT)
            sol = least_squares(
                lambda p: f.residuals(p)[0], p0, method="lm", x_scale=np.r_[np.full(6, 1e-5), np.ones(3)]
            )
            out.append((y, float(np.sqrt(np.mean(sol.fun**2))) * 1.001))
    return out


def scipy_de(y, target, seed, pop, strategy="best1bin", cr=0.9, init="lhs", falling_f=False):
    """scipy's DE with our settings; variants change one thing. Returns evaluations to the target or None."""
    objective = search.ScalarObjective(y, FIELD_NT)
    bounds = search.bounds_from_data(y, FIELD_NT)
    rng = np.random.default_rng(seed)
    if init == "scipy":
        start, popsize = "latinhypercube", 15  # scipy's default: 15 x 9 = 135 members
    elif init == "circle":
        start, popsize = bounds.to_params(search.circle_population(pop, 9, rng)), 15
    else:
        start, popsize = bounds.to_params(qmc.LatinHypercube(d=9, rng=rng).random(pop)), 15
    generation = [0]
    mutation = (0.5, 1.0)
    if falling_f:  # eq. (12) applied to F: 0.9 -> 0.3 over the generations, best/1/bin
        step_rng = np.random.default_rng(seed + 1)

        def strategy(candidate, population, rng=None):
            f = 0.3 + 0.6 * max(0.0, 1.0 - generation[0] / MAX_GEN)
            s, n = population.shape
            r1, r2 = step_rng.choice(np.delete(np.arange(s), candidate), 2, replace=False)
            mutant = population[0] + f * (population[r1] - population[r2])
            cross = step_rng.uniform(size=n) < cr
            cross[step_rng.integers(n)] = True
            return np.where(cross, mutant, population[candidate])

    def callback(intermediate_result):
        generation[0] += 1
        if intermediate_result.fun <= target:
            raise Reached

    try:
        differential_evolution(
            lambda x: objective(x.T),
            list(zip(bounds.lower, bounds.upper)),
            strategy=strategy,
            maxiter=MAX_GEN,
            popsize=popsize,
            init=start,
            mutation=mutation,
            recombination=cr,
            tol=0.0,
            atol=0.0,
            polish=False,
            updating="deferred",
            vectorized=True,
            rng=seed,
            callback=callback,
        )
    except Reached:
        return objective.n_evaluations
    return None


def jade(y, target, seed, pop, p_best=0.1, c=0.1):
    """JADE (Zhang & Sanderson 2009): current-to-pbest/1 with archive, adaptive F (Cauchy) and CR (normal)."""
    objective = search.ScalarObjective(y, FIELD_NT)
    bounds = search.bounds_from_data(y, FIELD_NT)
    rng = np.random.default_rng(seed)
    x = qmc.LatinHypercube(d=9, rng=rng).random(pop)
    f = objective(bounds.to_params(x))
    mu_f, mu_cr, archive, idx = 0.5, 0.5, np.empty((0, 9)), np.arange(pop)
    for _ in range(MAX_GEN):
        if f.min() <= target:
            return objective.n_evaluations
        cr = np.clip(rng.normal(mu_cr, 0.1, pop), 0, 1)
        fs = mu_f + 0.1 * rng.standard_cauchy(pop)
        while np.any(fs <= 0):
            bad = fs <= 0
            fs[bad] = mu_f + 0.1 * rng.standard_cauchy(int(bad.sum()))
        fs = np.minimum(fs, 1.0)
        top = np.argsort(f)[: max(2, int(round(p_best * pop)))]
        pbest = x[rng.choice(top, pop)]
        r1 = (idx + rng.integers(1, pop, pop)) % pop
        union = np.vstack([x, archive])
        r2 = rng.integers(0, len(union), pop)
        v = x + fs[:, None] * (pbest - x) + fs[:, None] * (x[r1] - union[r2])
        v = np.where(v < 0, x / 2, np.where(v > 1, (x + 1) / 2, v))
        cross = rng.uniform(size=(pop, 9)) < cr[:, None]
        cross[idx, rng.integers(0, 9, pop)] = True
        u = np.where(cross, v, x)
        fu = objective(bounds.to_params(u))
        ok = fu < f
        if ok.any():
            archive = np.vstack([archive, x[ok]])
            if len(archive) > pop:
                archive = archive[rng.choice(len(archive), pop, replace=False)]
            mu_f = (1 - c) * mu_f + c * np.sum(fs[ok] ** 2) / np.sum(fs[ok])
            mu_cr = (1 - c) * mu_cr + c * np.mean(cr[ok])
        x, f = np.where(ok[:, None], u, x), np.where(ok, fu, f)
    return None


VARIANTS = {
    "scipy defaults (135 members, CR 0.7)": lambda y, t, s, p: scipy_de(y, t, s, p, cr=0.7, init="scipy"),
    "ours (best1bin, F~U[0.5,1), CR 0.9)": lambda y, t, s, p: scipy_de(y, t, s, p),
    "ours with CR 0.7": lambda y, t, s, p: scipy_de(y, t, s, p, cr=0.7),
    "ours with current-to-best/1": lambda y, t, s, p: scipy_de(y, t, s, p, strategy="currenttobest1bin"),
    "ours with rand/1": lambda y, t, s, p: scipy_de(y, t, s, p, strategy="rand1bin"),
    "ours with Circle-map start (eq. 15)": lambda y, t, s, p: scipy_de(y, t, s, p, init="circle"),
    "ours with F falling 0.9 -> 0.3 (eq. 12)": lambda y, t, s, p: scipy_de(y, t, s, p, falling_f=True),
    "JADE (adaptive F, CR; archive)": jade,
}


def main():
    t0 = time.perf_counter()
    data = records()
    print(
        "evaluations until the best RMS is within 0.1 % of the least-squares minimum "
        f"({len(data)} records x 3 seeds, N = 150, a = 2 nT)"
    )
    print(f"  {'variant':42s} {'members':>7s} {'reached':>8s} {'median':>8s} {'90 %':>8s}")
    for name, run in VARIANTS.items():
        for pop in (135,) if name.startswith("scipy") else (20, 40):
            evals = [run(y, target, 1000 * rep + k, pop) for rep in range(3) for k, (y, target) in enumerate(data)]
            ok = [e for e in evals if e is not None]
            med = f"{np.median(ok):8.0f}" if ok else f"{'-':>8s}"
            q90 = f"{np.quantile(ok, 0.9):8.0f}" if ok else f"{'-':>8s}"
            print(f"  {name:42s} {pop:7d} {len(ok):4d}/{len(evals):<3d} {med} {q90}", flush=True)
    print(f"total {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
