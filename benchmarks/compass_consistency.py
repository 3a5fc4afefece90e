"""Several compasses on one vehicle (issue 40, item 5): how consistent their fields are before and after a
calibration, against the flight controllers' "inconsistent compasses" limits, and the cause named
(:mod:`magcal.diagnosis.compasses`).

Run::

    python benchmarks/compass_consistency.py           # the simulated cases and the real log (about a minute)
    python benchmarks/compass_consistency.py --sim     # the simulated cases only

Simulated (:func:`magcal.data.vehicle.simulate_vehicle`, 6000 samples at 10 Hz, three yaw turns, roll +-20 deg, pitch
+-10 deg, 3 nT noise, 0.02 deg attitude error), each with one cause hidden, found against the truth it was given:

* **current**: compass 2 sees 25 nT per A of the motor current (``current_nT_per_unit``), compass 1 none; the base
  vector fit (no platform terms) leaves it: the field per ampere, the angle and |B| per ampere it makes, and which
  compass the reference field says sees it; then the fit with the current term;
* **mounting**: ideal compasses, compass 2 mounted 5 deg off its bracket's right angle;
* **temperature**: three compasses, compass 3 with 40 and -30 nT/K on two axes (the temperature going up and down
  three times, so that it does not follow time);
* **timing**: compass 2 reads the field 40 ms later than compass 1 (its samples paired with compass 1's times).

Real: ``dk_log171.bin`` (dronekit/dronekit-la-testdata ``log171.bin``, CC BY-SA 3.0; ``python
benchmarks/real/fetch.py [--mirror DIR]`` puts it in ``benchmarks/real/data/raw/``): ArduCopter 3.3-dev, 2015-11,
three compasses (an external HMC5883 and two internal ones, the third not used for yaw and never calibrated), no
motor compensation, the current measured (0.5-27 A). Samples tilted beyond 60 deg (the vehicle ends on its back)
are left out. Before: the field the flight controller logged (its calibration of the time); after: the vector fit
(IGRF along the GPS track, on the log's date) without and with the current term, on the whole log, and fitted on
the first 60 % and compared on the last 40 %. The attitude's yaw comes from the EKF that uses compass 1: the
heading reference is not independent (docs/vector.md).
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from magcal.checks.reference import resolve_vector_reference
from magcal.data.logs import read_log
from magcal.data.vehicle import simulate_vehicle, vehicle_truth
from magcal.diagnosis.compasses import angle_deg, compass_consistency
from magcal.fitting.vector import fit_vector

RAW = Path(__file__).resolve().parent / "real" / "data" / "raw" / "dk_log171.bin"
N = 6000
MAX_TILT_DEG = 60.0


def _body_fields(tr):
    return np.stack([Rotation.from_quat(q[[1, 2, 3, 0]]).inv().apply(tr.field_ned_nT) for q in tr.attitude_wxyz])


def _per_unit_body(tr, sensor, k_raw):
    s = tr.sensors[sensor]
    return s.mounting @ np.linalg.inv(s.matrix) @ k_raw


def _named(pair, state):
    return {c.kind: c for c in pair.named(state)}


def _consistency(ds, terms, mask=None, compare=None, reference=None):
    ref = resolve_vector_reference(ds, reference=reference)
    fit = fit_vector(ds, ref, terms=terms, mask=mask, warn=False)
    where = fit.fitted if compare is None else compare
    return fit, compass_consistency(ds, fit.calibration, reference=ref, mask=where)


def sim_current() -> list[str]:
    truth = vehicle_truth(n_sensors=2, seed=3)
    k2 = np.array([20.0, -15.0, 10.0])
    truth.sensors[1].current_nT_per_unit = k2
    ds, tr = simulate_vehicle(truth, seed=3, n=N)
    _, cc = _consistency(ds, [])
    pair = cc.pair(0, 1)
    cause = _named(pair, "after")["current_A"]
    k = _per_unit_body(tr, 1, k2)
    bhat = _body_fields(tr) / np.linalg.norm(tr.field_ned_nT)
    deg = np.degrees(np.sqrt(np.mean(np.sum(np.cross(bhat, k) ** 2, axis=1))) / np.linalg.norm(tr.field_ned_nT))
    dtot = float(np.mean(bhat @ k))
    v = cause.values
    _, with_term = _consistency(ds, ["current"])
    return [
        "current (compass 2 sees 25 nT/A; base fit, no platform terms):",
        f"  named after the calibration: {', '.join(_named(pair, 'after'))}",
        f"  field per A (body): found {np.round(v['per_unit_nT'], 2)}, true {np.round(k, 2)} nT/A",
        f"  angle per A: found {v['angle_deg_per_unit']:.4f}, true {deg:.4f} deg/A; |B| per A: found "
        f"{v['total_diff_nT_per_unit']:+.2f}, true {dtot:+.2f} nT/A; correlation {v['correlation']:.3f}",
        f"  angle 1-2 before {pair.before.angle_deg.text()} deg, after {pair.after.angle_deg.text()} deg "
        "(median / p95 / max)",
        f"  seen by compass (reference field): before {[s + 1 for s in cc.seeing('before')]}, after "
        f"{[s + 1 for s in cc.seeing('after')]}",
        f"  with the current term: angle after {with_term.pair(0, 1).after.angle_deg.text()} deg; named after: "
        f"{', '.join(_named(with_term.pair(0, 1), 'after')) or 'none'}",
    ]


def sim_mounting() -> list[str]:
    truth = vehicle_truth(n_sensors=2, off_deg=0.0, seed=4)
    for s in truth.sensors:
        s.matrix, s.bias_nT = np.eye(3), np.zeros(3)
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    truth.sensors[1].mounting = truth.sensors[1].mounting @ Rotation.from_rotvec(np.radians(5.0) * axis).as_matrix()
    ds, tr = simulate_vehicle(truth, seed=4, n=N)
    _, cc = _consistency(ds, [])
    pair = cc.pair(0, 1)
    rel = truth.sensors[1].mounting @ truth.sensors[0].mounting.T
    true_vec = np.degrees(Rotation.from_matrix(rel).as_rotvec())
    body = _body_fields(tr)
    named = _named(pair, "before")
    return [
        "mounting (compass 2 5 deg off its right angle, ideal compasses):",
        f"  named before: {', '.join(named)}; after: {', '.join(_named(pair, 'after')) or 'none'}",
        f"  compass 2 off its right angle: found {cc.mountings[1]['angle_off_deg']:.3f} deg, true 5.000 deg",
        f"  relative rotation (data): found {np.round(named['mounting'].values['mounting_rotvec_deg'], 3)}, true "
        f"{np.round(true_vec, 3)} deg",
        f"  angle 1-2 before: median {pair.before.angle_deg.median:.3f} deg, true "
        f"{float(np.median(angle_deg(body, body @ rel))):.3f} deg; after {pair.after.angle_deg.text()} deg",
    ]


def sim_temperature() -> list[str]:
    truth = vehicle_truth(n_sensors=3, seed=6)
    ds, tr = simulate_vehicle(truth, seed=6, n=N)
    t = ds.time_s
    temp = 20.0 + 12.0 * np.sin(2 * np.pi * t / (t[-1] / 2.3))
    per_k = np.array([0.0, 40.0, -30.0])
    readings = np.array(ds.readings_nT)
    readings[2] += (temp - 20.0)[:, None] * per_k[None]
    ds = ds.replace(readings_nT=readings, temperature_C=temp)
    _, cc = _consistency(ds, [])
    k = _per_unit_body(tr, 2, per_k)
    lines = ["temperature (compass 3 sees 50 nT/K, three compasses):"]
    for p in cc.pairs:
        named = _named(p, "after")
        text = ", ".join(named) or "none"
        if "temperature" in named:
            found = named["temperature"].values["per_unit_nT"]
            text += f" (found {np.round(found, 2)}, true {np.round(k if p.j == 2 else -k, 2)} nT/K)"
        lines.append(f"  pair {p.label}: named after: {text}")
    return lines


def sim_timing() -> list[str]:
    truth = vehicle_truth(n_sensors=2, seed=5)
    ds, tr = simulate_vehicle(truth, seed=5, n=N)
    t = ds.time_s
    readings = np.array(ds.readings_nT)
    readings[1] = np.column_stack([np.interp(t + 0.040, t, readings[1][:, a]) for a in range(3)])
    ds = ds.replace(readings_nT=readings).masked(t < t[-1])  # the last sample has no field 40 ms later
    _, cc = _consistency(ds, [])
    pair = cc.pair(0, 1)
    named = _named(pair, "after")
    found = named["timing"].values["delay_ms"] if "timing" in named else float("nan")
    return [
        "timing (compass 2 reads the field 40 ms later):",
        f"  named after: {', '.join(named) or 'none'}; delay found {found:+.1f} ms, true +40.0 ms",
        f"  angle 1-2 after {pair.after.angle_deg.text()} deg",
    ]


def real_log() -> list[str]:
    if not RAW.exists():
        return [f"{RAW}: missing; run python benchmarks/real/fetch.py [--mirror DIR] first"]
    ds = read_log(RAW, name=RAW.name, warn=False)  # its notes (ds.notes) are not what this benchmark reports
    level = (np.abs(ds.extra["att_roll_deg"]) <= MAX_TILT_DEG) & (np.abs(ds.extra["att_pitch_deg"]) <= MAX_TILT_DEG)
    ds = ds.masked(level)
    out = [
        f"{RAW.name}: {ds.n_sensors} compasses, {ds.n_samples} samples ({ds.time_s[-1] - ds.time_s[0]:.0f} s) "
        f"with tilt within {MAX_TILT_DEG:g} deg, current {np.min(ds.extra['current_A']):.1f}-"
        f"{np.max(ds.extra['current_A']):.1f} A, date {ds.metadata.get('date')}",
    ]
    for terms in ([], ["current"]):
        start = time.perf_counter()
        fit, cc = _consistency(ds, terms, reference="igrf")
        out += [
            "",
            f"== after: the vector fit, platform terms {terms or 'none'}, whole log "
            f"({time.perf_counter() - start:.1f} s; determined: {[s.determined for s in fit.sensors]})",
            cc.text().rstrip(),
        ]
    n = ds.n_samples
    first = np.arange(n) < int(0.6 * n)
    for terms in ([], ["current"]):
        _, cc = _consistency(ds, terms, mask=first, compare=~first, reference="igrf")
        out += [
            "",
            f"== held out: fitted on the first 60 % (platform terms {terms or 'none'}), compared on the last 40 %",
        ]
        for p in cc.pairs:
            out.append(
                f"  {p.label}: angle before {p.before.angle_deg.text()} deg, after {p.after.angle_deg.text()} deg; "
                f"|B| diff before {p.before.total_diff_nT.text(0)}, after {p.after.total_diff_nT.text(0)} nT; "
                f"refused (ArduPilot) before {100 * p.before.fail_fraction['ardupilot']:.1f} %, after "
                f"{100 * p.after.fail_fraction['ardupilot']:.1f} %"
            )
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sim", action="store_true", help="the simulated cases only")
    args = parser.parse_args(argv)
    warnings.simplefilter("ignore")
    start = time.perf_counter()
    for case in (sim_current, sim_mounting, sim_temperature, sim_timing):
        print("\n".join(case()))
        print()
    if not args.sim:
        print("\n".join(real_log()))
    print(f"\n({time.perf_counter() - start:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
