"""The compass beside an accelerometer: heading error held out, ours against the truth and the total-field fit
(issue 42; docs/gravity.md).

Run: ``python benchmarks/gravity_heading.py`` (about a minute; ``--no-real`` for the simulations alone).

Simulated (:func:`magcal.data.board.simulate_board`): a MEMS board tumbled by hand through 40 attitudes, held still
1-2.5 s at each, 50 Hz; the magnetometer turned 2 deg (random axis) from the accelerometer, soft iron (``C^-1``
5 % off the identity), hard iron 15 uT per axis, noise 150 nT per axis; the accelerometer's bias 0.03 g and gain
2 % per axis, noise 3 mg; |B| 48 700 nT. Each calibration is scored on another record of the same board (another
seed), on its still samples whose x axis is within 60 deg of the horizontal, against the true magnetic heading:

* ``ours``: :func:`magcal.fitting.gravity.fit_gravity` (the joint fit, the inclination fitted);
* ``true``: the true calibration (what the sensors' noise alone leaves: the floor);
* ``total-field fit``: the magnetometer's total-field fit (:func:`magcal.fitting.pipeline.calibrate`) beside the
  accelerometer's own fit, the right angle between them given (:func:`magcal.fitting.gravity.separate_calibration`):
  what a user gets without the dip;
* ``raw``: no calibration at all.

Mean over :data:`SEEDS`. A second table shows what a heading of 0.5 deg needs: attitudes (poses), tilts and the
accelerometer's noise, against the calibration's own heading error the fit predicts from its covariance.

Real (``benchmarks/real``: ``python benchmarks/real/fetch.py`` and ``convert.py``): every recording with an
accelerometer beside the magnetometer. Fitted on the 1st, 3rd, ... of an odd number of blocks in time (at least 10 s
each: :func:`magcal.fitting.validation.held_out_blocks`), scored on the still samples of the others
(:func:`magcal.fitting.gravity.validate_gravity`): the dip's spread (deg) of the raw readings, of the
total-field fit (with the accelerometer's own fit) and of ours; the RMS heading difference between the two fits
(the heading error the total-field fit leaves if ours is right: no recording has a heading reference); and the
calibration's own heading error from its covariance (fitted on the whole record).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from magcal.calibration.accelerometer import AccelerometerCalibration
from magcal.calibration.calibration import Calibration, SensorCalibration
from magcal.core.errors import CalibrationError, MagcalError
from magcal.data.board import simulate_board
from magcal.data.io import read_csv
from magcal.data.logs import read_log
from magcal.fitting.gravity import (
    fit_gravity,
    heading_figures,
    separate_calibration,
    true_calibration,
    validate_gravity,
)
from magcal.geometry.orientations import split_mounting

SEEDS = range(5)
INCLINATIONS = (64.0, 20.0, 75.0)
REAL = Path(__file__).resolve().parent / "real" / "data"
REAL_CSV = ("ck_lsm9ds1", "cl_imu_gnss")
REAL_LOGS = ("px4_sample.ulg", "ap_erlebrain3.bin", "ap_pxf_rpi.bin", "ap_pxf_flip.bin", "ap_erle_218.bin")


def raw_calibration(n_sensors=1) -> Calibration:
    """No calibration: the readings and the accelerometer as they are."""
    return Calibration(
        sensors=[SensorCalibration(np.eye(3), np.zeros(3), np.eye(3)) for _ in range(n_sensors)],
        frame="accelerometer",
        mode="gravity",
        accelerometer=AccelerometerCalibration.identity(),
    )


def simulated(inclination, seed, **options) -> dict:
    ds, truth, _ = simulate_board(seed=seed, inclination_deg=inclination, **options)
    same = {k: v for k, v in options.items() if k in ("max_tilt_deg",)}  # held out over the tilts calibrated
    later, _, rec = simulate_board(truth=truth, seed=seed + 1000, n_poses=40, **same)
    t0 = time.perf_counter()
    fit = fit_gravity(ds)
    wall = time.perf_counter() - t0
    sep = separate_calibration(ds, right_angle=fit.sensors[0].right_angle)
    out = {"wall_s": wall}
    for name, cal in (("ours", fit.calibration), ("true", true_calibration(truth)), ("sep", sep)):
        fig = heading_figures(cal, later, rec.still, rec.heading_deg)
        out[name] = fig["heading_rms_deg"][0]
        out[f"{name}_dip"] = fig["dip_sd_deg"][0]
    raw = heading_figures(raw_calibration(), later, rec.still, rec.heading_deg)
    out["raw"] = raw["heading_rms_deg"][0]
    true_mount, _ = split_mounting(truth.mounting @ np.linalg.inv(truth.mag_matrix))
    out["mount_err_deg"] = float(
        np.degrees(np.arccos(np.clip((np.trace(fit.sensors[0].mounting.T @ true_mount) - 1) / 2, -1, 1)))
    )
    out["predicted"] = fit.sensors[0].heading_sd_deg
    out["noise"] = fit.budget["noise_per_sample_deg"]
    out["determined"] = float(fit.sensors[0].determined)
    out["accel_fitted"] = float(fit.accel.fitted)
    return out


def table_simulated() -> None:
    print("Simulated board: held-out heading error (deg RMS), mean of", len(SEEDS), "seeds")
    print(
        "| inclination | ours | true calibration | ours / true | total-field fit | raw | dip spread ours / total-field "
        "(deg) | mounting error (deg) | fit (s) |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for inc in INCLINATIONS:
        rows = [simulated(inc, s) for s in SEEDS]
        m = {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}
        print(
            f"| {inc:.0f} deg | {m['ours']:.3f} | {m['true']:.3f} | {m['ours'] / m['true']:.3f} | {m['sep']:.2f} | "
            f"{m['raw']:.0f} | {m['ours_dip']:.3f} / {m['sep_dip']:.3f} | {m['mount_err_deg']:.4f} | {m['wall_s']:.2f} |"
        )
    print()
    print(
        "What a heading of 0.5 deg needs (inclination 64 deg): held-out heading error (deg RMS),", len(SEEDS), "seeds"
    )
    print(
        "| record | fits determined (accelerometer fitted) | ours: determined fits, mean (worst) | ours: the others | "
        "true | calibration's own error of the determined: predicted (covariance) / measured sqrt(ours^2 - true^2) "
        "| noise per sample, predicted |"
    )
    print("|---|---|---|---|---|---|---|")
    cases = (
        ("40 attitudes, any tilt (default)", {}),
        ("6 attitudes", {"n_poses": 6}),
        ("12 attitudes", {"n_poses": 12}),
        ("40 attitudes, tilts within 45 deg (held out within 45 deg)", {"max_tilt_deg": 45.0}),
        ("40 attitudes, tilts within 20 deg (held out within 20 deg)", {"max_tilt_deg": 20.0}),
        ("accelerometer noise 10 mg", {"accel_noise_g": 0.01}),
        ("magnetometer noise 500 nT", {"mag_noise_nT": 500.0}),
        ("no still moments (tremor 0.3 m/s^2)", {"tremor_m_s2": 0.3}),
    )
    for label, opts in cases:
        rows = [simulated(64.0, s, **opts) for s in SEEDS]
        good = [r for r in rows if r["determined"]]
        bad = [r for r in rows if not r["determined"]]
        true = float(np.mean([r["true"] for r in rows]))
        if good:
            ours = float(np.mean([r["ours"] for r in good]))
            worst = max(r["ours"] for r in good)
            pred = float(np.mean([r["predicted"] for r in good]))
            meas = float(np.mean([np.sqrt(max(r["ours"] ** 2 - r["true"] ** 2, 0.0)) for r in good]))
            det = f"{ours:.3f} ({worst:.3f})"
            own = f"{pred:.3f} / {meas:.3f}"
        else:
            det, own = "-", "-"
        others = f"{np.mean([r['ours'] for r in bad]):.1f}" if bad else "-"
        fitted = sum(int(r["accel_fitted"]) for r in rows)
        noise = float(np.mean([r["noise"] for r in rows]))
        print(
            f"| {label} | {len(good)} of {len(rows)} ({fitted}) | {det} | {others} | {true:.3f} | {own} | {noise:.2f} |"
        )
    print()


def _real_datasets():
    for name in REAL_CSV:
        path = REAL / f"{name}.csv"
        if path.exists():
            yield name, read_csv(path, warn=False)
    for name in REAL_LOGS:
        path = REAL / "raw" / name
        if path.exists():
            yield name, read_log(path, warn=False)


def table_real() -> None:
    print("Real recordings: held out (the 1st, 3rd, ... blocks fitted, still samples of the others scored; sensor 1)")
    print(
        "| recording | still samples (kind) | tilts (deg) | dip spread raw / total-field fit / ours (deg) | heading "
        "difference total-field fit - ours (deg RMS) | calibration's own heading error (deg) | mounting found |"
    )
    print("|---|---|---|---|---|---|---|")
    found = False
    for name, ds in _real_datasets():
        found = True
        try:
            fit = fit_gravity(ds)
        except (MagcalError, CalibrationError) as exc:
            print(f"| {name} | refused: {str(exc)[:90]} | | | | | |")
            continue
        s = fit.sensors[0]
        head = "n/a" if s.heading_sd_deg is None else f"{s.heading_sd_deg:.2f}"
        det = "" if s.determined else " (not determined)"
        try:
            val = validate_gravity(ds)
        except (MagcalError, CalibrationError) as exc:  # a record too short to split
            held, diff = f"not held out: {str(exc).split(': ', 1)[-1][:60]}", "-"
        else:
            raw = heading_figures(raw_calibration(ds.n_sensors), ds, fit.still.mask & ~val.train)["dip_sd_deg"][0]
            rows = {r["name"]: r for r in val.rows}
            sep = f"{rows['separate']['held_dip_sd_deg']:.2f}" if "separate" in rows else "(no ellipsoid)"
            held = f"{raw:.2f} / {sep} / {rows['gravity']['held_dip_sd_deg']:.2f}"
            diff = f"{val.heading_difference_deg:.2f}" if np.isfinite(val.heading_difference_deg) else "-"
        print(
            f"| {name} | {fit.still.n} ({fit.still.kind}) | {fit.tilt_range_deg[0]:.0f}-{fit.tilt_range_deg[1]:.0f} | "
            f"{held} | {diff} | {head}{det} | {s.right_angle_text.split(':')[0]} + {s.angle_off_deg:.2f} deg |"
        )
    if not found:
        print("(no real recordings here: python benchmarks/real/fetch.py; python benchmarks/real/convert.py --all)")
    print()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--no-real", action="store_true", help="the simulations only")
    parser.add_argument("--no-simulated", action="store_true", help="the real recordings only")
    args = parser.parse_args(argv)
    if not args.no_simulated:
        table_simulated()
    if not args.no_real:
        table_real()
    return 0


if __name__ == "__main__":
    sys.exit(main())
