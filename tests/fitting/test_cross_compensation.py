"""The cross on a platform: four fluxgates with their own calibration errors and platform fields fly a
compensation box; the fit is judged on a second flight against the true compensation the simulation knows."""

from __future__ import annotations

import numpy as np
import pytest

from magcal.calibration.calibration import Calibration, SensorCalibration
from magcal.core import conventions
from magcal.core.errors import MagcalError
from magcal.data.cross_flight import CROSS_PLATFORMS, dipole_matrix, simulate_cross_flight
from magcal.data.lab import dipole_field_nT
from magcal.diagnosis.cross_fom import cross_fom_report, sensor_fom, tensor_fom
from magcal.diagnosis.fom import Maneuver
from magcal.fitting.cross_compensation import CrossCompensation, fit_cross_compensation

#: A geological gradient (nT/m, NED; symmetric, traceless) for the survey line.
GRADIENT = np.array([[8.0, 3.0, -2.0], [3.0, -5.0, 4.0], [-2.0, 4.0, -3.0]])


def _judged(fit, flight):
    """The FOM report of ``fit`` on ``flight``: before = the true sensor calibration alone (the platform's field
    still in), after = ours, reference = the true compensation."""
    return cross_fom_report(
        flight.truth.calibrated_nT(flight.readings_nT),
        fit.compensate(flight),
        flight.baseline_m,
        flight.sample_rate_hz,
        reference_nT=flight.truth.compensated_nT(flight.readings_nT),
        maneuvers=flight.truth.maneuvers,
    )


def test_platform_fields_are_dipoles_at_their_distances():
    platform = CROSS_PLATFORMS["aircraft"]
    positions = conventions.sensor_positions(0.5)
    p, a, e = platform.sensor_fields(positions)
    expected = dipole_field_nT(positions, platform.permanent_at_m, platform.permanent_Am2)
    assert np.allclose(p, expected)
    moment = platform.induced_Am2_per_nT @ np.array([20_000.0, 1_000.0, 45_000.0])
    assert np.allclose(
        a @ np.array([20_000.0, 1_000.0, 45_000.0]), dipole_field_nT(positions, platform.induced_at_m, moment)
    )
    # the sources are at different distances: each sensor's platform field differs from the others'
    for terms in (p, a, e):
        spread = np.ptp(terms.reshape(4, -1), axis=0).max()
        assert spread > 0.2 * np.abs(terms).max()
    with pytest.raises(ValueError, match="dipole"):
        dipole_matrix(np.zeros(3))


def test_truth_compensation_leaves_the_earth_field():
    flight = simulate_cross_flight(3, noise_nT=0.0, gradient_ned_nT_per_m=GRADIENT)
    assert np.allclose(flight.truth.compensated_nT(flight.readings_nT), flight.truth.earth_body_nT, atol=1e-6)
    tensor = conventions.tensor_matrix(conventions.tensor_components(flight.truth.earth_body_nT, flight.baseline_m))
    rotation = flight.dataset().attitude_wxyz
    assert rotation.shape == (flight.time_s.size, 4)
    # the Earth field's tensor at the cross is the NED gradient seen in the body frame: its invariants stay
    assert np.allclose(np.trace(tensor, axis1=1, axis2=2), 0.0, atol=1e-9)
    assert np.allclose(np.sum(tensor**2, axis=(1, 2)), np.sum(GRADIENT**2), rtol=1e-9)


@pytest.mark.parametrize("reference", ["attitude", "mean"])
@pytest.mark.parametrize("platform", ["aircraft", "drone"])
@pytest.mark.parametrize("seed", [1, 7])
def test_tensor_fom_on_a_second_flight_near_the_true_compensation(seed, platform, reference):
    first = simulate_cross_flight(seed, platform=platform)
    second = simulate_cross_flight(seed + 100, platform=platform)
    fit = fit_cross_compensation(first, reference=reference, field_ned_nT=first.truth.field_ned_nT)
    report = _judged(fit, second)
    after, floor = report.after.fom_nT_per_m, report.reference.fom_nT_per_m
    assert after <= 1.2 * floor
    assert after < report.before.fom_nT_per_m / 5
    for name, value in report.after.component_fom_nT_per_m.items():
        assert value <= 1.2 * report.reference.component_fom_nT_per_m[name], name
    assert report.improvement_ratio > 5
    for ours, true, before in zip(report.sensors_after, report.sensors_reference, report.sensors_before):
        assert ours.fom_nT <= 1.2 * true.fom_nT
        assert ours.fom_nT < before.fom_nT / 5


@pytest.mark.parametrize("magnitude_passes", [0, 2])
@pytest.mark.parametrize("platform", ["aircraft", "drone"])
def test_platform_terms_recovered_after_the_sensor_calibration(platform, magnitude_passes):
    flight = simulate_cross_flight(2, platform=platform, drift_nT=0.0)
    truth = flight.truth
    calibration = _true_calibration(flight)
    fit = fit_cross_compensation(
        flight,
        reference="attitude",
        field_ned_nT=truth.field_ned_nT,
        calibration=calibration,
        magnitude_passes=magnitude_passes,
    )
    assert fit.precalibrated
    # within the noise's reach: 1 % of the largest induced term, 5 % of the largest eddy term; the offset carries
    # the induced term's error times the field (1e-5 x 50 000 nT), and the magnitude passes' ridge-held part
    for k, sensor in enumerate(fit.sensors):
        assert np.allclose(sensor.matrix - np.eye(3), truth.induced[k], atol=1e-5)
        assert np.allclose(sensor.eddy_s, truth.eddy_s[k], atol=1e-5)
        assert np.allclose(sensor.offset_nT, truth.permanent_nT[k], atol=1.0)
    assert np.abs(truth.induced).max() > 5e-4 and np.abs(truth.eddy_s).max() > 1e-4


def _true_calibration(flight):
    return Calibration([SensorCalibration(s.Cinv, s.bias_nT, s.R) for s in flight.truth.sensors], 50_000.0)


@pytest.mark.parametrize(("reference", "calibrated"), [("attitude", False), ("mean", False), ("mean", True)])
def test_a_survey_lines_gradient_is_kept(reference, calibrated):
    box = simulate_cross_flight(4)
    line = simulate_cross_flight(5, gradient_ned_nT_per_m=GRADIENT)
    calibration = _true_calibration(box) if calibrated else None
    fit = fit_cross_compensation(box, reference=reference, field_ned_nT=box.truth.field_ned_nT, calibration=calibration)
    earth = conventions.tensor_matrix(conventions.tensor_components(line.truth.earth_body_nT, line.baseline_m))
    ours = conventions.tensor_matrix(fit.tensor(line, calibration=calibration))
    true = conventions.tensor_matrix(
        conventions.tensor_components(line.truth.compensated_nT(line.readings_nT), line.baseline_m)
    )
    before = conventions.tensor_matrix(
        conventions.tensor_components(line.truth.calibrated_nT(line.readings_nT), line.baseline_m)
    )
    error = np.sqrt(np.mean((ours - earth) ** 2))
    assert error <= 1.2 * np.sqrt(np.mean((true - earth) ** 2))
    assert error < np.sqrt(np.mean((before - earth) ** 2)) / 10


@pytest.mark.parametrize("magnitude_passes", [0, 2])
@pytest.mark.parametrize(("attitude_noise_deg", "seed"), [(0.02, 7), (0.1, 8)])
def test_an_attitude_error_and_a_drift_are_common_to_the_four(attitude_noise_deg, seed, magnitude_passes):
    """The attitude's error and the diurnal drift a constant (IGRF) reference lacks bend each sensor's fit alike:
    the tensor does not see them; each sensor's total field does, until the magnitude passes take them out."""
    first = simulate_cross_flight(seed, attitude_noise_deg=attitude_noise_deg, drift_nT=5.0)
    second = simulate_cross_flight(seed + 1, attitude_noise_deg=attitude_noise_deg, drift_nT=5.0)
    fit = fit_cross_compensation(
        first, reference="attitude", field_ned_nT=first.truth.field_ned_nT, magnitude_passes=magnitude_passes
    )
    report = _judged(fit, second)
    assert report.after.fom_nT_per_m <= 1.2 * report.reference.fom_nT_per_m
    worst = max(ours.fom_nT / true.fom_nT for ours, true in zip(report.sensors_after, report.sensors_reference))
    if magnitude_passes:
        assert worst <= 1.2
    else:
        assert worst > 2


def test_a_base_station_record_serves_as_the_reference():
    flight = simulate_cross_flight(3, drift_nT=5.0)
    fit = fit_cross_compensation(
        flight, reference="attitude", field_ned_nT=flight.truth.field_ned_series_nT, magnitude_passes=0
    )
    report = _judged(fit, simulate_cross_flight(4, drift_nT=5.0))
    for ours, true in zip(report.sensors_after, report.sensors_reference):
        assert ours.fom_nT <= 1.2 * true.fom_nT
    with pytest.raises(MagcalError, match="one such row per sample"):
        fit_cross_compensation(flight, reference="attitude", field_ned_nT=flight.truth.field_ned_series_nT[:-1])


@pytest.mark.parametrize("reference", ["attitude", "mean"])
def test_a_battery_current_is_fitted_when_given(reference):
    """A current's field is not a Tolles-Lawson term: hidden, it stays in the tensor; given, each sensor's field
    per ampere is fitted and the line compensated with its own current."""
    first = simulate_cross_flight(11, platform="drone_current")
    second = simulate_cross_flight(12, platform="drone_current")
    field = first.truth.field_ned_nT
    hidden = _judged(fit_cross_compensation(first, reference=reference, field_ned_nT=field), second)
    assert hidden.after.fom_nT_per_m > 5 * hidden.reference.fom_nT_per_m
    fit = fit_cross_compensation(first, reference=reference, field_ned_nT=field, current_A=first.current_A)
    report = cross_fom_report(
        second.truth.calibrated_nT(second.readings_nT),
        fit.compensate(second, current_A=second.current_A),
        second.baseline_m,
        second.sample_rate_hz,
        reference_nT=second.truth.compensated_nT(second.readings_nT),
        maneuvers=second.truth.maneuvers,
    )
    assert report.after.fom_nT_per_m <= 1.2 * report.reference.fom_nT_per_m
    for ours, true in zip(report.sensors_after, report.sensors_reference):
        assert ours.fom_nT <= 1.2 * true.fom_nT
    again = CrossCompensation.from_json(fit.to_json())
    assert again.current and np.allclose(
        again.compensate(second, current_A=second.current_A), fit.compensate(second, current_A=second.current_A)
    )
    if reference == "attitude":
        calibrated = fit_cross_compensation(
            first,
            reference="attitude",
            field_ned_nT=field,
            current_A=first.current_A,
            calibration=_true_calibration(first),
            magnitude_passes=0,
        )
        for k, sensor in enumerate(calibrated.sensors):
            assert np.allclose(sensor.current_nT_per_A, first.truth.current_nT_per_A[k], atol=0.05)


def test_dataset_json_and_text():
    flight = simulate_cross_flight(6)
    from_flight = fit_cross_compensation(flight, reference="attitude", field_ned_nT=flight.truth.field_ned_nT)
    from_dataset = fit_cross_compensation(
        flight.dataset(), reference="attitude", field_ned_nT=flight.truth.field_ned_nT
    )
    assert from_dataset.baseline_m == flight.baseline_m
    assert np.allclose(from_dataset.compensate(flight.dataset()), from_flight.compensate(flight), atol=1e-6)
    again = CrossCompensation.from_json(from_flight.to_json())
    assert np.allclose(again.compensate(flight.readings_nT, sample_rate_hz=10.0), from_flight.compensate(flight))
    text = from_flight.text()
    assert "attitude" in text and len(text.splitlines()) >= 6
    doc = from_flight.to_dict()
    assert doc["kind"] == "cross_compensation" and len(doc["sensors"]) == 4
    auto = fit_cross_compensation(flight.readings_nT, sample_rate_hz=10.0)
    assert auto.reference == "mean" and "mean" in auto.text()


def test_tensor_fom_of_a_known_signal():
    """One sensor's x axis swings by +-a at 0.3 Hz: Gxx and Gzz swing by 2a/d peak to peak, the others not."""
    rate, n, amplitude, d = 10.0, 3000, 0.5, 0.5
    t = np.arange(n) / rate
    vectors = np.tile(np.array([20_000.0, 1_000.0, 45_000.0]), (4, n, 1))
    vectors[0, :, 0] += amplitude * np.sin(2 * np.pi * 0.3 * t)
    maneuvers = [Maneuver(0.0, "roll", 300 * k + 200, 300 * k + 400) for k in range(8)]
    table = tensor_fom(vectors, d, maneuvers, rate)
    fom = table.component_fom_nT_per_m
    expected = len(maneuvers) * 2 * amplitude / d
    assert fom["Gxx"] == pytest.approx(expected, rel=0.05) and fom["Gzz"] == pytest.approx(expected, rel=0.05)
    assert max(fom[c] for c in ("Gxy", "Gxz", "Gyx", "Gyy", "Gyz")) < 1e-6
    assert table.fom_nT_per_m == pytest.approx(np.sqrt(2) * expected, rel=0.05)


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda f: fit_cross_compensation(f.readings_nT[:3], sample_rate_hz=10.0), "four sensors"),
        (lambda f: fit_cross_compensation(f.readings_nT), "sample rate"),
        (lambda f: fit_cross_compensation(f.readings_nT, sample_rate_hz=10.0, reference="attitude"), "attitude"),
        (lambda f: fit_cross_compensation(f, reference="attitude"), "Earth field vector"),
        (lambda f: fit_cross_compensation(f, reference="north"), "unknown reference"),
        (lambda f: fit_cross_compensation(f, current_A=f.current_A).compensate(f), "current_A"),
        (lambda f: fit_cross_compensation(f, current_A=np.ones(5)), "one ampere value each"),
        (lambda f: fit_cross_compensation(f, calibration=_true_calibration(f)).compensate(f), "same calibration"),
        (lambda f: fit_cross_compensation(f).compensate(f, calibration=_true_calibration(f)), "give no calibration"),
        (lambda f: fit_cross_compensation(f, mask=np.zeros(f.time_s.size, bool)), "widen the mask"),
        (
            lambda f: fit_cross_compensation(
                np.where(np.arange(f.time_s.size)[None, :, None] == 17, np.nan, f.readings_nT), sample_rate_hz=10.0
            ),
            "row 17",
        ),
        (
            lambda f: cross_fom_report(f.readings_nT, f.readings_nT[:, :-1], 0.5, 10.0, maneuvers=f.truth.maneuvers),
            "same shape",
        ),
    ],
)
def test_bad_input_is_named(call, message):
    flight = simulate_cross_flight(0, platform="drone_current")
    with pytest.raises(MagcalError, match=message):
        call(flight)


def test_the_sensors_lag_is_fitted_and_kept_in_the_document():
    """The four 100 ms late against the attitude (and the current): the fitted offset is the lag, each sensor's
    total field compensated to its floor (the lag's second order left without it), and a line compensated from the
    document as from the fit."""
    box = simulate_cross_flight(5, platform="drone_current", sensor_lag_s=0.1)
    line = simulate_cross_flight(6, platform="drone_current", sensor_lag_s=0.1)
    ned = box.truth.field_ned_nT
    fit = fit_cross_compensation(box, reference="attitude", field_ned_nT=ned, current_A=box.current_A, time_offset=True)
    assert fit.time_offset_s == pytest.approx(0.1, abs=0.005)
    assert "time offset +100" in fit.text().replace("+99", "+100").replace("+101", "+100")
    back = CrossCompensation.from_json(fit.to_json())
    assert back.time_offset_s == fit.time_offset_s
    ours = back.compensate(line, current_A=line.current_A)
    np.testing.assert_allclose(ours, fit.compensate(line, current_A=line.current_A))
    true = line.truth.compensated_nT(line.readings_nT)
    plain = fit_cross_compensation(box, reference="attitude", field_ned_nT=ned, current_A=box.current_A)
    maneuvers = line.truth.maneuvers

    def sensors_fom(vectors):  # each sensor's total field: the compensated one is on the attitude's clock
        return np.mean([t.fom_nT for t in sensor_fom(vectors, maneuvers, line.sample_rate_hz)])

    floor = sensors_fom(true)
    assert sensors_fom(ours) < 1.2 * floor
    assert sensors_fom(plain.compensate(line, current_A=line.current_A)) > 5 * floor
    with pytest.raises(MagcalError, match="time offset is found against the attitude"):
        fit_cross_compensation(box, reference="mean", time_offset=True)
