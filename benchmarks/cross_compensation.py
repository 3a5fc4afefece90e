"""The cross on a platform: the four-sensor gradiometer's compensation, its tensor FOM before / ours / the true
compensation (the floor).

Run: ``PYTHONPATH=$PWD python benchmarks/cross_compensation.py`` (about half a minute on a busy 2-core machine; with
``--diagnosis`` only the diagnosis of the hidden current and lag; with ``--two-currents`` only the last table, two
current-carrying wires among four recorded current columns).

Simulated flights (:func:`magcal.data.cross_flight.simulate_cross_flight`): the seed's cross (baseline 0.5 m, the
seed's Table 1 calibration errors per sensor) flies the compensation box of :mod:`magcal.data.compensation_flight`
on two platforms whose sources (a permanent dipole, a soft-iron part, a conducting part) sit 0.6-1.7 m from the
sensors, fluxgate noise 0.1 nT per axis, a 3 nT diurnal drift. Fitted on flight A (seed s), judged on flight B
(seed s + 100) with the box's 12 maneuvers. Before: the raw readings' tensor, and the tensor after each sensor's
true calibration alone (the platform still in: what a ground calibration leaves); ours; the true compensation
(the exact calibration and platform field taken out: the noise floor). Last, the drone with its battery's current
in a loop 0.4-0.8 m from the sensors (1-5 nT/A, 8-17 A): hidden from the fit, and given to it; and the aircraft
whose four sensors are 100 ms late against the attitude (and the current): hidden, and fitted (``time_offset``).
The diagnosis table adds the lagged aircraft. The tensor FOM is the root sum of squares of
the seven components' FOMs (nT/m, :mod:`magcal.diagnosis.cross_fom`); a sensor's FOM is the scalar FOM of its
total field (nT), the mean over the four shown.
"""

from __future__ import annotations

import time

import numpy as np

from magcal.data.cross_flight import simulate_cross_flight
from magcal.diagnosis.cross_compensation import cross_compensation_result, cross_record, diagnose_cross_compensation
from magcal.diagnosis.cross_fom import cross_fom_report, sensor_fom, tensor_fom
from magcal.fitting.cross_compensation import fit_cross_compensation

CASES = [
    # (label, platform, reference, attitude noise deg, magnitude passes)
    ("aircraft, attitude + IGRF", "aircraft", "attitude", 0.0, 2),
    ("aircraft, attitude 0.1 deg noise", "aircraft", "attitude", 0.1, 2),
    ("aircraft, attitude 0.1 deg, no magnitude pass", "aircraft", "attitude", 0.1, 0),
    ("aircraft, no attitude (the four's mean)", "aircraft", "mean", 0.0, 2),
    ("aircraft, the four's mean, no magnitude pass", "aircraft", "mean", 0.0, 0),
    ("drone, attitude + IGRF", "drone", "attitude", 0.0, 2),
    ("drone, no attitude (the four's mean)", "drone", "mean", 0.0, 2),
    ("drone + battery current, hidden", "drone_current", "attitude", 0.0, 2),
    ("drone + battery current, given", "drone_current", "attitude+current", 0.0, 2),
    ("aircraft, sensors 100 ms late, hidden", "aircraft@0.1", "attitude", 0.0, 2),
    ("aircraft, sensors 100 ms late, time_offset", "aircraft@0.1", "attitude+lag", 0.0, 2),
]


def _platform(name):
    """(platform, the sensors' lag in s) of a case's ``platform@lag``."""
    platform, _, lag = name.partition("@")
    return platform, float(lag or 0.0)


def judged(platform, reference, attitude_noise_deg, passes, seed=1):
    platform, lag = _platform(platform)
    kwargs = {"platform": platform, "attitude_noise_deg": attitude_noise_deg, "sensor_lag_s": lag}
    first, second = simulate_cross_flight(seed, **kwargs), simulate_cross_flight(seed + 100, **kwargs)
    with_current = reference.endswith("+current")
    with_lag = reference.endswith("+lag")
    reference = reference.removesuffix("+current").removesuffix("+lag")
    started = time.perf_counter()
    fit = fit_cross_compensation(
        first,
        reference=reference,
        field_ned_nT=first.truth.field_ned_nT,
        magnitude_passes=passes,
        current_A=first.current_A if with_current else None,
        time_offset=with_lag,
    )
    elapsed = time.perf_counter() - started
    args = (second.baseline_m, second.sample_rate_hz)
    report = cross_fom_report(
        second.truth.calibrated_nT(second.readings_nT),
        fit.compensate(second, current_A=second.current_A if with_current else None),
        *args,
        reference_nT=second.truth.compensated_nT(second.readings_nT),
        maneuvers=second.truth.maneuvers,
    )
    raw = cross_fom_report(second.readings_nT, second.readings_nT, *args, maneuvers=second.truth.maneuvers)
    return fit, report, raw.before.fom_nT_per_m, elapsed


def main():
    print("## The cross's tensor FOM on a second flight (nT/m; sensors' FOM in nT, mean of four)\n")
    print(
        "| case | raw | calibrated only | ours | true compensation | ours / true | sensors: calibrated only / ours "
        "/ true | fit s |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for label, platform, reference, noise, passes in CASES:
        _, report, raw, elapsed = judged(platform, reference, noise, passes)
        before, after, floor = (t.fom_nT_per_m for t in (report.before, report.after, report.reference))
        sensors = [np.mean([t.fom_nT for t in ts]) for ts in (report.sensors_before, report.sensors_after)]
        sensors.append(np.mean([t.fom_nT for t in report.sensors_reference]))
        print(
            f"| {label} | {raw:.0f} | {before:.1f} | {after:.2f} | {floor:.2f} | **{after / floor:.3f}** | "
            f"{sensors[0]:.1f} / {sensors[1]:.2f} / {sensors[2]:.2f} | {elapsed:.2f} |"
        )
    fit, report, _, _ = judged("aircraft", "attitude", 0.0, 2)
    print("\n## aircraft, attitude + IGRF, flight B per maneuver (before = calibrated only)\n")
    print("```")
    print(report.text())
    print("```\n")
    print("```")
    print(fit.text())
    print("```\n")
    tensor, sensor = [], []
    for seed in range(10, 18):
        for platform, reference in (("aircraft", "attitude"), ("drone", "mean")):
            _, report, _, _ = judged(platform, reference, 0.05, 2, seed=seed)
            tensor.append(report.after.fom_nT_per_m / report.reference.fom_nT_per_m)
            sensor += [a.fom_nT / r.fom_nT for a, r in zip(report.sensors_after, report.sensors_reference)]
    print(
        "8 more pairs of flights (seeds 10-17 fitted, 110-117 judged), aircraft against the attitude and drone "
        f"against the mean, 0.05 deg attitude noise: tensor FOM ours / true mean {np.mean(tensor):.3f}, max "
        f"{np.max(tensor):.3f}; sensors' FOM ours / true mean {np.mean(sensor):.3f}, max {np.max(sensor):.3f}"
    )
    diagnosis()


def diagnosis():
    """The diagnosis (``magcal diagnose --mode cross_compensation``) of flights with and without the hidden current:
    its verdict, the held-out tensor FOM of TL alone and with what it names against the noise's floor, and the
    named model's tensor FOM on the second flight over the true compensation's."""
    print("\n## The diagnosis: held-out tensor FOM (nT/m), 12 maneuvers in 4 folds; the named model on flight B\n")
    print(
        "| platform | seed | verdict | named | TL alone | with it | noise floor | flight B ours / true | sensors' "
        "FOM B, ours / true |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for name in ("drone_current", "drone", "aircraft", "aircraft@0.1"):
        platform, lag = _platform(name)
        for seed in (1, 2):
            kwargs = {"platform": platform, "sensor_lag_s": lag}
            a, b = simulate_cross_flight(seed, **kwargs), simulate_cross_flight(seed + 100, **kwargs)
            records = []
            for flight in (a, b):
                ds = flight.dataset()
                ds.extra["current_A"] = flight.current_A
                records.append(cross_record(ds))
            ned = a.truth.field_ned_nT
            d = diagnose_cross_compensation(records[0], field_ned_nT=ned)
            fit = cross_compensation_result(records[0], d.explained_by, field_ned_nT=ned).calibration
            ours = fit.compensate(b.readings_nT, sample_rate_hz=10.0, current_A=b.current_A if fit.current else None)
            true = b.truth.compensated_nT(b.readings_nT)
            ratio = (
                tensor_fom(ours, 0.5, b.truth.maneuvers, 10.0).fom_nT_per_m
                / tensor_fom(true, 0.5, b.truth.maneuvers, 10.0).fom_nT_per_m
            )
            final = d.fom_final_nT_per_m if d.fom_final_nT_per_m is not None else d.fom_held_out_nT_per_m
            sensors = [np.mean([t.fom_nT for t in sensor_fom(v, b.truth.maneuvers, 10.0)]) for v in (ours, true)]
            label = platform + (f", {lag * 1e3:.0f} ms late" if lag else "")
            print(
                f"| {label} | {seed} | {d.verdict} | {', '.join(d.explained_by) or '-'} | "
                f"{d.fom_held_out_nT_per_m:.1f} | {final:.1f} | {d.floor_fom_nT_per_m:.1f} | {ratio:.3f} | "
                f"{sensors[0]:.2f} / {sensors[1]:.2f} |"
            )


def two_currents():
    """Two wires that carry a field at the cross among four recorded currents (two carry none there): the
    diagnosis's rounds, the columns it names, and the named model's tensor FOM on flight B over the truth's."""
    from dataclasses import replace

    from magcal.data.cross_flight import CROSS_PLATFORMS

    hidden = {"cur_strb": np.array([0.003, 0.001, -0.002]), "cur_com_1": np.array([-0.001, 0.0025, 0.002])}
    currents = {"cur_outpwr": np.zeros(3), **hidden, "cur_ac_lo": np.zeros(3)}
    platform = replace(CROSS_PLATFORMS["drone"], currents_Am2_per_A=currents)
    print("\n## Two currents among four recorded columns: held-out tensor FOM (nT/m) per round; flight B\n")
    print("| seed | verdict | named columns | rounds (held-out) | noise floor | flight B ours / true (nT/m) |")
    print("|---|---|---|---|---|---|")
    for seed in (31, 41):
        a, b = simulate_cross_flight(seed, platform=platform), simulate_cross_flight(seed + 1, platform=platform)
        ned = a.truth.field_ned_nT
        d = diagnose_cross_compensation(cross_record(a.dataset()), field_ned_nT=ned)
        taken = (
            cross_record(a.dataset(), ",".join(d.current_columns)) if d.current_columns else cross_record(a.dataset())
        )
        fit = cross_compensation_result(taken, d.explained_by, field_ned_nT=ned).calibration
        ours = fit.compensate(b.readings_nT, sample_rate_hz=10.0, current_A=b.currents_A)
        maneuvers, baseline = b.truth.maneuvers, b.baseline_m
        ours_fom = tensor_fom(ours, baseline, maneuvers, 10.0).fom_nT_per_m
        true_fom = tensor_fom(b.truth.compensated_nT(b.readings_nT), baseline, maneuvers, 10.0).fom_nT_per_m
        steps = [d.fom_held_out_nT_per_m] + [c.fom_after_nT_per_m for c in d.candidates if c.recommended]
        print(
            f"| {seed} | {d.verdict} | {', '.join(d.current_columns) or '-'} | "
            f"{' -> '.join(f'{v:.1f}' for v in steps)} | {d.floor_fom_nT_per_m:.1f} | "
            f"{ours_fom:.2f} / {true_fom:.2f} = **{ours_fom / true_fom:.3f}** |"
        )


if __name__ == "__main__":
    import sys

    if sys.argv[1:] == ["--diagnosis"]:
        diagnosis()
    elif sys.argv[1:] == ["--two-currents"]:
        two_currents()
    else:
        main()
        two_currents()
