"""One sensor, N = 1e6: magcal's maximum likelihood against magyc (PyPI) side by side, at held-out accuracy.

    python -m venv /work/venvs/magyc && /work/venvs/magyc/bin/pip install magyc    # once: magyc pins numpy<2, jax
    OPENBLAS_NUM_THREADS=1 python benchmarks/fitter_speed.py [--n 1000000] [--magyc-python /work/venvs/magyc/bin/python]

The same simulated readings (sensor 1 of the chi2017 preset: its scale, non-orthogonality and bias, random
attitudes in a 50 000 nT field, 3 nT noise per axis) are split at random 80/20. Each method fits the 80 % and is
timed in its own process (magyc in its own venv, since it needs numpy < 2); the corrected field of the held-out
20 % is then scored by its total-field RMS, made scale-free (``|B| / median|B| - 1``, times 50 000 nT) since magyc's
fits return the field on their own scale. The floor is the noise's: ``3 nT`` per axis gives a total-field RMS of
3 nT. magcal is timed end to end (``magcal.calibrate``: the data checks, the ellipsoid start, the ML fit, its
covariance, every step's figures and the noise estimate) and, on the same call, the fit proper (the wall time of
its ellipsoid and ML steps, as ``CalibrationResult.steps`` records them); the seed's two-step method
(``method="ellipsoid"``, every sample in the ellipsoid) is timed end to end beside them. Each magcal time is the
median of ``--repeat`` calls, each on a fresh copy of the record (magcal keeps what it learns from a record's
readings alone, such as its quantization step, for the next fit of the same record; a new file does not have it).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

MAGYC_SCRIPT = r"""
import json, sys, time
import numpy as np
import magyc
train = np.load(sys.argv[1]); test = np.load(sys.argv[2])
out = {}
for name in ("ellipsoid_fit_fang", "twostep_hsi"):
    fn = getattr(magyc, name)
    args = (train,) if name == "ellipsoid_fit_fang" else (train, np.array([0.0, 0.0, 50000.0]))
    fn(*args[:1] if name == "ellipsoid_fit_fang" else args)  # warm (imports, jit)
    t0 = time.perf_counter()
    res = fn(*args)
    dt = time.perf_counter() - t0
    hi, si = np.asarray(res[0], float).ravel(), np.asarray(res[1], float)
    cal = (np.linalg.inv(si) @ (test.T - hi[:, None])).T
    out[name] = {"seconds": dt, "test_norm": np.linalg.norm(cal, axis=1).tolist()}
print(json.dumps(out))
"""


def heldout_rms_nT(norms) -> float:
    """Scale-free total-field RMS of held-out corrected fields, nT at 50 000 nT."""
    norms = np.asarray(norms, float)
    return float(np.sqrt(np.mean((norms / np.median(norms) - 1.0) ** 2)) * 50_000.0)


def main(argv=None) -> int:
    import warnings

    import magcal

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=float, default=1e6)
    p.add_argument("--magyc-python", default="/work/venvs/magyc/bin/python")
    p.add_argument("--repeat", type=int, default=3, help="magcal calls timed (median)")
    args = p.parse_args(argv)
    warnings.simplefilter("ignore")
    n = int(args.n)
    ds = magcal.simulate("chi2017", n_samples=n, seed=1)
    one = ds.replace(readings_nT=ds.readings_nT[:1], baseline_m=None)
    rng = np.random.default_rng(0)
    test_mask = rng.random(n) < 0.2
    train, test = one.subset(np.flatnonzero(~test_mask)), one.subset(np.flatnonzero(test_mask))
    magcal.calibrate(train.subset(np.arange(5000)))  # warm the imports
    walls, fits, seeds = [], [], []
    for _ in range(max(1, args.repeat)):
        fresh = train.replace(readings_nT=train.readings_nT.copy())  # a new record each time: no cache reused
        t0 = time.perf_counter()
        result = magcal.calibrate(fresh)
        walls.append(time.perf_counter() - t0)
        fits.append(sum(s.wall_s for s in result.steps if s.name in ("ellipsoid", "ml")))
        t0 = time.perf_counter()
        seed = magcal.calibrate(train, method="ellipsoid")
        seeds.append(time.perf_counter() - t0)
    ours = heldout_rms_nT(np.linalg.norm(result.calibration.correct(test)[0], axis=1))
    seed_rms = heldout_rms_nT(np.linalg.norm(seed.calibration.correct(test)[0], axis=1))
    rows = [
        ("magcal ML fit (ellipsoid start + ML)", float(np.median(fits)), ours),
        ("magcal ML (calibrate, end to end)", float(np.median(walls)), ours),
        ("seed two-step (calibrate ellipsoid, e2e)", float(np.median(seeds)), seed_rms),
    ]
    if os.path.exists(args.magyc_python):
        with tempfile.TemporaryDirectory() as tmp:
            a, b, script = os.path.join(tmp, "train.npy"), os.path.join(tmp, "test.npy"), os.path.join(tmp, "m.py")
            np.save(a, train.readings_nT[0])
            np.save(b, test.readings_nT[0])
            with open(script, "w") as fh:
                fh.write(MAGYC_SCRIPT)
            proc = subprocess.run(
                [args.magyc_python, script, a, b],
                capture_output=True,
                text=True,
                env={**os.environ, "JAX_PLATFORMS": "cpu"},
            )
        if proc.returncode == 0:
            res = json.loads(proc.stdout.strip().splitlines()[-1])
            for name, r in res.items():
                rows.append((f"magyc {name}", r["seconds"], heldout_rms_nT(r["test_norm"])))
        else:
            rows.append((f"magyc failed: {proc.stderr.strip().splitlines()[-1][:80]}", float("nan"), float("nan")))
    else:
        rows.append(("magyc: not installed (see the docstring)", float("nan"), float("nan")))
    four = magcal.simulate("chi2017", n_samples=100_000, seed=1)
    four_walls, four_steps = [], {}
    for _ in range(max(1, args.repeat)):
        fresh = four.replace(readings_nT=four.readings_nT.copy())  # a new record each time: no cache reused
        t0 = time.perf_counter()
        res4 = magcal.calibrate(fresh)
        four_walls.append(time.perf_counter() - t0)
        for step in res4.steps:
            four_steps.setdefault(step.name, []).append(step.wall_s)
    print(
        f"\nFour sensors, N = 100,000 each: calibrate end to end {np.median(four_walls):.2f} s (median of "
        f"{len(four_walls)}; steps "
        + ", ".join(f"{k} {np.median(v):.3f} s" for k, v in four_steps.items() if k != "raw")
        + f"); total-field RMS {res4.rms_nT:.3f} nT"
    )
    print(
        f"\nOne sensor, N = {n:,} ({int((~test_mask).sum()):,} fitted, {int(test_mask.sum()):,} held out); "
        "noise floor 3.00 nT"
    )
    print(f"{'method':<42}{'time s':>8}{'held-out RMS nT':>17}")
    for name, t, rms in rows:
        print(f"{name:<42}{t:>8.2f}{rms:>17.3f}")
    peers = [(t, name) for name, t, rms in rows if name.startswith("magyc ") and np.isfinite(t)]
    if peers:
        fastest, peer = min(peers)
        print(
            f"against the fastest peer ({peer}, {fastest:.3f} s): magcal's fit proper {rows[0][1] / fastest:.1f}x, "
            f"calibrate end to end {rows[1][1] / fastest:.1f}x (issue 30: within 3x)"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
