"""The loop on a vehicle (issue 40): diagnose a flight, add what it names, and compare the next flight's error.

Simulated flights of one vehicle (``magcal.data.vehicle``: three yaw turns, roll +-20 deg, pitch +-10 deg, 10 Hz,
3 nT sensor noise, 0.02 deg attitude error, a motor current and a temperature channel), each with one hidden effect:
none, a motor current's field, a temperature bias, eddy currents, an attitude-magnetometer time offset (the
magnetometer sampled 80 ms after its attitude) and a bias step mid-flight (the next flight after the step: the
sensor stays permed). For each vehicle seed and case:

* what ``magcal diagnose`` (vector mode, :func:`magcal.diagnosis.vector.diagnose_vector`) names on flight 1;
* the world components' RMS per component on flight 2 (nT) of the vector calibration of flight 1 with the advice
  (``ours``), of the base vector model (the seed's method has no vector fit: the base model is the comparison),
  of the previous default of ``magcal calibrate --mode vector`` (every platform term the data support: eddy
  currents and the current's field, fitted whether the data need them or not), and of the true calibration on the
  same flight simulated without the hidden effect (the same noise: the physical floor);
* ``ours / floor``: the issue's bound is 1.25.

``--real`` adds the public vehicle logs of ``benchmarks/real`` (``python benchmarks/real/fetch.py --mirror ...``
then ``python benchmarks/real/vector_logs.py`` writes their parts): each calibration part is diagnosed (alone,
then with the other parts as ``--also`` flights), and the world RMS of the base model and of the advice is
compared on the next part and the next flights: the advice must never raise them.

    python benchmarks/vehicle_loop.py              # about 2-4 minutes on 2 cores
    python benchmarks/vehicle_loop.py --real       # + the real logs
"""

from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path

import numpy as np

from magcal.checks.reference import resolve_vector_reference
from magcal.data.vehicle import simulate_vehicle, vehicle_truth
from magcal.diagnosis.vector import Flight, diagnose_vector
from magcal.fitting.vector import fit_vector, true_calibration
from magcal.model.terms import EFFECTS

HERE = Path(__file__).resolve().parent

CASES = [
    ("none", None, None, {}),
    ("current", "current_field", 25.0, {}),
    ("temperature", "temperature_bias", 20.0, {}),
    ("eddy", "eddy_currents", 12.0, {}),
    ("time offset", "attitude_time_offset", -80.0, {}),
    ("bias step", "bias_step", 60.0, {"at_fraction": 0.0}),
]


#: The flights' conditions (``--attitude-noise-deg``, ``--turns``) and the hidden effects' sizes (``--scale``).
CONDITIONS = {"attitude_noise_deg": 0.02, "turns": 3.0}


def _flight(truth, seed, name, size, n, **options):
    hidden = [] if name is None else [EFFECTS[name]().perturbation(size, None, **options)]
    ds, _ = simulate_vehicle(
        truth, seed=seed, n=n, perturbations=hidden, log_current=True, temperature=True, **CONDITIONS
    )
    return ds


def _world_rms(calibration, ds) -> float:
    world = calibration.world(ds, record_terms="drop")[0]
    return float(np.sqrt(np.nanmean((world - resolve_vector_reference(ds).ned_nT) ** 2)))


def simulated(seeds, n, scale=1.0):
    print(
        f"{'case':<12} {'seed':>4}  {'named':<22} {'ours':>7} {'base':>7} {'old default':>11} {'floor':>7} "
        f"{'ours/floor':>10} {'s':>5}"
    )
    worst = 0.0
    for label, name, size, next_options in CASES:
        size = None if size is None else size * scale
        for seed in seeds:
            truth = vehicle_truth(seed=seed)
            one = _flight(truth, 1, name, size, n)
            two = _flight(truth, 2, name, size, n, **next_options)
            t0 = time.perf_counter()
            d = diagnose_vector(one, resolve_vector_reference(one))
            took = time.perf_counter() - t0
            ref = resolve_vector_reference(one)
            ours = fit_vector(one, ref, effects=d.explained_by, warn=False).calibration
            base = fit_vector(one, ref, warn=False).calibration
            old = fit_vector(one, ref, terms=["eddy", "current"], warn=False).calibration
            clean = _flight(truth, 2, None, None, n)
            floor = _world_rms(true_calibration(simulate_vehicle(truth, seed=2, n=n, **CONDITIONS)[1]), clean)
            ratio = _world_rms(ours, two) / floor
            worst = max(worst, ratio)
            named = ",".join(d.explained_by) or "-"
            print(
                f"{label:<12} {seed:>4}  {named:<22} {_world_rms(ours, two):>7.1f} {_world_rms(base, two):>7.1f} "
                f"{_world_rms(old, two):>11.1f} {floor:>7.1f} {ratio:>10.3f} {took:>5.1f}"
            )
    print(f"worst ours/floor: {worst:.3f} (bound 1.25)")


#: The real logs' parts that ``benchmarks/real/vector_logs.py`` writes: (calibration part, later part, other flights).
REAL = [
    ("copter", "copter_cal.csv", "copter_test0.csv", ["copter_test1.csv", "copter_test2.csv"]),
    (
        "copter, reversed",
        "copter_reversed_cal.csv",
        "copter_reversed_test0.csv",
        ["copter_reversed_test1.csv", "copter_reversed_test2.csv"],
    ),  # fmt: skip
    ("plane", "plane_cal.csv", "plane_test0.csv", []),
    ("plane, reversed", "plane_reversed_cal.csv", "plane_reversed_test0.csv", []),
]


def real():
    from magcal.data.io import read_csv

    folder = HERE / "real" / "data" / "vector_logs"
    if not (folder / REAL[0][1]).exists():
        print(f"\nreal logs: {folder} is empty; run benchmarks/real/fetch.py and benchmarks/real/vector_logs.py first")
        return
    print("\nreal vehicle logs (IGRF along the track): world RMS per component (nT) on the next part / flights")
    print(f"{'vehicle':<18} {'--also':<6} {'verdict':<15} {'advice':<22} {'part':<28} {'base':>8} {'advice':>8}")
    for label, cal_name, later_name, others in REAL:
        one = read_csv(folder / cal_name)
        ref = resolve_vector_reference(one, reference="igrf")
        tests = [(later_name, read_csv(folder / later_name))] + [(o, read_csv(folder / o)) for o in others]
        refs = {name: resolve_vector_reference(ds, reference="igrf") for name, ds in tests}
        for with_also in (False, True):
            if with_also and not others:
                continue
            also = [Flight(ds, refs[name], name) for name, ds in tests[1:]] if with_also else []
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                d = diagnose_vector(one, ref, also=also)
            base = fit_vector(one, ref, warn=False).calibration
            advised = fit_vector(one, ref, effects=d.explained_by, warn=False).calibration
            for name, ds in tests:
                b, a = _real_rms(base, ds, refs[name]), _real_rms(advised, ds, refs[name])
                flag = "" if a <= b * 1.001 else "  RAISED"
                print(
                    f"{label:<18} {'yes' if with_also else 'no':<6} {d.verdict:<15} "
                    f"{','.join(d.explained_by) or '-':<22} {name:<28} {b:>8.0f} {a:>8.0f}{flag}"
                )


def _real_rms(calibration, ds, ref) -> float:
    world = calibration.world(ds, record_terms="drop")[0]
    return float(np.sqrt(np.nanmean((world - ref.ned_nT) ** 2)))


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", default="3,7", help="vehicle seeds (comma-separated)")
    parser.add_argument("--n", type=int, default=6000, help="samples per flight (10 Hz)")
    parser.add_argument("--real", action="store_true", help="also the public vehicle logs")
    parser.add_argument("--attitude-noise-deg", type=float, default=0.02, help="attitude error (deg, 1 sigma)")
    parser.add_argument("--turns", type=float, default=3.0, help="full yaw turns per flight (600 s at 10 Hz)")
    parser.add_argument("--scale", type=float, default=1.0, help="the hidden effects' sizes times this")
    parser.add_argument("--real-only", action="store_true", help="only the public vehicle logs")
    args = parser.parse_args()
    CONDITIONS.update(attitude_noise_deg=args.attitude_noise_deg, turns=args.turns)
    if not args.real_only:
        print(f"conditions: {CONDITIONS}, hidden sizes x {args.scale}")
        simulated([int(s) for s in args.seeds.split(",")], args.n, args.scale)
    if args.real or args.real_only:
        real()


if __name__ == "__main__":
    main()
