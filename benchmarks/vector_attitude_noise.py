"""What attitude accuracy buys a vector calibration (issue 29 item 9; docs/vector.md).

Run: ``python benchmarks/vector_attitude_noise.py`` (about half a minute).

A simulated vehicle (:func:`magcal.data.vehicle.simulate_vehicle`): one fluxgate mounted ``ROLL_180_YAW_90`` and
2 deg off it, scale/non-orthogonality/soft iron a few per cent, hard iron ~1.5 uT per axis, sensor noise 3 nT per
axis; the Earth's field scaled to |B| = 50 000 nT (inclination 64 deg); a calibration flight of 6000 samples at
10 Hz, three full yaw turns, roll within +-20 deg, pitch within +-10 deg. For each attitude error (white, per axis,
1 sigma: 0.01, 0.1 and 1 deg) the vector fit (:func:`magcal.fitting.vector.fit_vector`, noises estimated) is
applied to another flight of the same vehicle, and scored against the field there:

* world (north-east-down) components, RMS per component, of the vector fit and of the true calibration;
* the floor ``sqrt((2/3) (sigma_att |B|)^2 + sigma_n^2)``: an attitude error moves the field by ``sigma_att |B|``
  in each of the two directions perpendicular to it, two of three components' worth;
* |B| RMS (the sensor noise's figure: the attitude does not enter it);
* the mounting's error against the true one (deg), and the attitude error the fit estimated.

Mean over :data:`SEEDS`. The total-field fit of the same flights gives no world components at all (its rotation is
a gauge) and is warned undetermined on this cone of directions (benchmarks/vector_calibration.py).
"""

from __future__ import annotations

import time

import numpy as np
from scipy.spatial.transform import Rotation

from magcal.checks.reference import resolve_vector_reference
from magcal.data.vehicle import DEFAULT_FIELD_NED_nT, simulate_vehicle, vehicle_truth
from magcal.fitting.vector import fit_vector, true_calibration

SEEDS = range(5)
N = 6000
FIELD_nT = 50_000.0
NOISE_nT = 3.0
ATTITUDE_NOISES_DEG = (0.01, 0.1, 1.0)


def field_ned() -> np.ndarray:
    """The simulator's field direction at |B| = :data:`FIELD_nT`."""
    f = np.asarray(DEFAULT_FIELD_NED_nT, dtype=float)
    return f / np.linalg.norm(f) * FIELD_nT


def world_rms(cal, ds) -> float:
    ref = resolve_vector_reference(ds).ned_nT
    return float(np.sqrt(np.mean((cal.world(ds)[0] - ref) ** 2)))


def total_rms(cal, ds) -> float:
    ref = np.linalg.norm(resolve_vector_reference(ds).ned_nT, axis=1)
    return float(np.sqrt(np.mean((cal.total_field(ds)[0] - ref) ** 2)))


def run_one(sigma_deg: float, seed: int) -> dict:
    truth = vehicle_truth(seed=seed, field_ned_nT=field_ned())
    common = {"truth": truth, "n": N, "noise_nT": NOISE_nT, "attitude_noise_deg": sigma_deg}
    flight, _ = simulate_vehicle(seed=seed, **common)
    other, _ = simulate_vehicle(seed=seed + 1000, **common)
    fit = fit_vector(flight, resolve_vector_reference(flight), warn=False)
    true = true_calibration(truth)
    s = fit.sensors[0]
    err = Rotation.from_matrix(s.mounting @ truth.sensors[0].mounting.T).magnitude()
    return {
        "world_fit": world_rms(fit.calibration, other),
        "world_true": world_rms(true, other),
        "total_fit": total_rms(fit.calibration, other),
        "mount_err_deg": float(np.degrees(err)),
        "att_est_deg": float(s.attitude_noise_deg),
    }


def main() -> int:
    t0 = time.perf_counter()
    print(
        f"vector calibration against the attitude error: |B| {FIELD_nT:.0f} nT, sensor noise {NOISE_nT:g} nT, "
        f"{N} samples, mean of {len(SEEDS)} seeds, scored on another flight"
    )
    print(
        "  attitude error | world RMS per component: fit   truth   floor | |B| RMS | mounting error | "
        "attitude error estimated"
    )
    for sigma in ATTITUDE_NOISES_DEG:
        rows = [run_one(sigma, seed) for seed in SEEDS]
        m = {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}
        floor = float(np.sqrt((2.0 / 3.0) * (np.radians(sigma) * FIELD_nT) ** 2 + NOISE_nT**2))
        print(
            f"  {sigma:8.2f} deg    |            {m['world_fit']:8.1f} {m['world_true']:7.1f} {floor:7.1f} nT | "
            f"{m['total_fit']:5.2f} nT | {m['mount_err_deg']:10.4f} deg | {m['att_est_deg']:.3f} deg"
        )
    print(f"({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
