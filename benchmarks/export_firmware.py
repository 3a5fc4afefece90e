"""What a flight controller's compass gives with magcal's export, on the vehicle's next flight (issue 40, item 6).

Run: ``python benchmarks/export_firmware.py`` (about 20 s).

Setup (:func:`magcal.data.vehicle.simulate_vehicle`): two compasses mounted ``ROLL_180_YAW_90`` and about 2 deg off
it, scale/non-orthogonality/soft iron a few per cent, hard iron ~1.5 uT per axis, a motor current's field of ~25 nT
per ampere per compass (the current 4 to 28 A); |B| 48 769 nT, sensor noise 3 nT, attitude noise 0.02 deg; the
vector calibration (``fit_vector`` with its current term) fitted on one flight of 3000 samples and exported, each
firmware's correction applied to the raw readings of another flight of 3000 samples (``apply_ardupilot`` /
``apply_px4``, the firmwares' formulas with the battery current: ArduPilot in A, PX4 in kA).

Printed, mean over 3 seeds (both compasses): the corrected field against the true body-frame field (RMS per
component, the largest error, and |B| RMS), and the largest difference between the firmware's field and magcal's,
for

* magcal itself (``Calibration.correct``): the floor an export can reach,
* ArduPilot now (custom rotation and ``COMPASS_MOT*``), and with ``--no-custom-rotation`` (the nearest right angle,
  the remainder dropped under ``--force``),
* PX4 now (``CAL_MAGn_ROT`` with the remainder dropped under ``--force``, and ``CAL_MAGn_[XYZ]COMP``),
* the export before (the same for both firmwares: the nearest right angle; the current term refused, and dropped
  under ``--force``).
"""

from __future__ import annotations

import copy

import numpy as np
from scipy.spatial.transform import Rotation

from magcal.checks.reference import resolve_vector_reference
from magcal.data.vehicle import simulate_vehicle, vehicle_truth
from magcal.fitting.vector import fit_vector
from magcal.output.export import apply_ardupilot, apply_px4, export_calibration

SEEDS = range(3)
N = 3000


def firmware_fields(cal, ds, fmt, current=True, custom_rotation=True):
    """Each compass's field (nT) as the firmware corrects the raw readings with the exported parameters."""
    if not current:  # the export before: the current term dropped
        cal = copy.deepcopy(cal)
        cal.platform = None
    result = export_calibration(cal, fmt, force=True, custom_rotation=custom_rotation)
    amps = np.asarray(ds.extra["current_A"], dtype=float)
    out = []
    for e in result.sensors:
        raw = ds.readings_nT[e.sensor - 1]
        if fmt == "ardupilot":
            out.append(apply_ardupilot(result.parameters, raw / 100.0, slot=e.slot, motor=amps) * 100.0)
        else:
            out.append(apply_px4(result.parameters, raw / 1e5, slot=e.slot, power=amps * 1e-3) * 1e5)
    return np.array(out)


def main():
    rows: dict[str, list] = {}
    for seed in SEEDS:
        truth = vehicle_truth(n_sensors=2, seed=seed, current=True)
        one, _ = simulate_vehicle(truth, seed=seed, n=N)
        two, tr = simulate_vehicle(truth, seed=seed + 100, n=N)
        cal = fit_vector(one, resolve_vector_reference(one), terms=["current"], warn=False).calibration
        q = tr.attitude_wxyz
        body = Rotation.from_quat(q[:, [1, 2, 3, 0]]).inv().apply(tr.field_ned_nT)  # the true body-frame field
        magcal_nT = cal.correct(two)
        cases = {"magcal (floor)": magcal_nT}
        cases["ArduPilot now: custom rotation, COMPASS_MOT*"] = firmware_fields(cal, two, "ardupilot")
        cases["ArduPilot --no-custom-rotation: right angle, COMPASS_MOT*"] = firmware_fields(
            cal, two, "ardupilot", custom_rotation=False
        )
        cases["PX4 now: right angle (remainder dropped), CAL_MAGn_xCOMP"] = firmware_fields(cal, two, "px4")
        cases["before (both): right angle, current dropped"] = firmware_fields(
            cal, two, "ardupilot", current=False, custom_rotation=False
        )
        true_total = np.linalg.norm(body, axis=1)
        for name, fields in cases.items():
            err = fields - body[None]
            rows.setdefault(name, []).append(
                (
                    float(np.sqrt(np.mean(err**2))),
                    float(np.max(np.linalg.norm(err, axis=2))),
                    float(np.sqrt(np.mean((np.linalg.norm(fields, axis=2) - true_total[None]) ** 2))),
                    float(np.max(np.linalg.norm(fields - magcal_nT, axis=2))),
                )
            )
    print(
        "| export | vector vs the true body field, RMS per component (nT) | largest (nT) | \\|B\\| RMS (nT) "
        "| largest \\|firmware - magcal\\| (nT) |"
    )
    print("|---|---|---|---|---|")
    for name, values in rows.items():
        rms, worst, total, diff = np.mean(values, axis=0)
        print(f"| {name} | {rms:.2f} | {worst:.1f} | {total:.2f} | {diff:.3g} |")


if __name__ == "__main__":
    main()
