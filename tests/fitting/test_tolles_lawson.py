"""Tolles-Lawson compensation against simulated compensation flights whose platform the test sets, and (when the
mirror of MagNav.jl is on the machine) against MagNav.jl's own test data."""

from __future__ import annotations

import json
import pathlib
import subprocess

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magcal.core.errors import MagcalError
from magcal.data.compensation_flight import CompensationPlatform, simulate_compensation_flight
from magcal.diagnosis.fom import figure_of_merit, find_maneuvers, fom_report
from magcal.fitting.tolles_lawson import TLCompensation, fit_tolles_lawson, solve_ridge
from magcal.model.tolles_lawson import bandpass, design_matrix, per_sample_difference, term_labels

RATE = 10.0


@pytest.fixture(scope="module")
def flights():
    return simulate_compensation_flight(1), simulate_compensation_flight(2)


@pytest.fixture(scope="module")
def fitted(flights):
    first, _ = flights
    return fit_tolles_lawson(first.flux_nT, first.scalar_nT, time_s=first.time_s)


def _traceless(tl18):
    """TL-18 with the two gauges of a constant |B| removed: the induced and the eddy diagonal's mean."""
    out = np.array(tl18, dtype=float)
    for diagonal in ((3, 6, 8), (9, 13, 17)):
        out[list(diagonal)] -= out[list(diagonal)].mean()
    return out


@pytest.mark.parametrize(
    ("terms", "count"),
    [
        (("permanent", "induced", "eddy"), 18),
        (("permanent", "induced5", "eddy8"), 16),
        (("induced3", "eddy3", "bias"), 7),
    ],
)
def test_design_matrix_columns(terms, count):
    rng = np.random.default_rng(0)
    flux = rng.normal(0, 30_000, (50, 3))
    a = design_matrix(flux, terms)
    labels = term_labels(terms)
    assert a.shape == (50, count) == (50, len(labels))
    u = flux / np.linalg.norm(flux, axis=1, keepdims=True)
    d = per_sample_difference(flux)
    expected = {"permanent_y": u[:, 1], "induced_xz": u[:, 0] * flux[:, 2] / 5e4, "eddy_zy": u[:, 2] * d[:, 1] / 5e4}
    expected |= {"induced_zz": u[:, 2] * flux[:, 2] / 5e4, "bias": np.ones(50), "eddy_yy": u[:, 1] * d[:, 1] / 5e4}
    for label, column in expected.items():
        if label in labels:
            np.testing.assert_allclose(a[:, labels.index(label)], column)


def test_bandpass_keeps_the_band_and_removes_the_rest():
    t = np.arange(3000) / RATE
    inside, below, above = np.sin(2 * np.pi * 0.3 * t), np.sin(2 * np.pi * 0.01 * t), np.sin(2 * np.pi * 3.0 * t)
    out = bandpass(inside + below + above, RATE)[200:-200]
    assert np.max(np.abs(out - inside[200:-200])) < 0.03


def test_fit_finds_the_platform_up_to_the_gauge(flights, fitted):
    first, _ = flights
    truth = first.truth.tl18(RATE)
    error = _traceless(fitted.tl18()) - _traceless(truth)
    np.testing.assert_allclose(fitted.tl18()[:3], truth[:3], atol=3.0)  # permanent, nT (second order ~1 nT)
    assert np.max(np.abs(error[3:9])) < 0.05 * np.max(np.abs(truth[3:9]))
    assert np.max(np.abs(error[9:])) < 0.05 * np.max(np.abs(truth[9:]))
    assert fitted.conditioning.condition_number > 1e3  # the terms are collinear, and the result says so


def test_fom_on_a_second_flight_within_1p2_of_the_true_compensation(flights, fitted):
    _, second = flights
    ours = fom_report(
        second.scalar_nT, fitted.compensate(second.scalar_nT, second.flux_nT), RATE, attitude_deg=second.attitude_deg
    )
    best = figure_of_merit(second.truth.compensated_nT(second.scalar_nT), second.truth.maneuvers, RATE)
    assert len(ours.after.maneuvers) == 12
    assert ours.after.fom_nT <= 1.2 * best.fom_nT
    assert ours.before.fom_nT > 50 * ours.after.fom_nT
    assert ours.improvement_ratio > 50


@pytest.mark.parametrize(
    "hidden",
    [{"fluxgate_lag_s": 0.1}, {"platform": CompensationPlatform(current_nT_per_A=np.array([1.5, -1.0, 0.8]))}],
    ids=["fluxgate-late", "current-field"],
)
def test_a_hidden_term_leaves_a_worse_fom(hidden):
    """What TL lacks shows: the fit cannot reach the true compensation's FOM."""
    flight = simulate_compensation_flight(3, **hidden)
    fit = fit_tolles_lawson(flight.flux_nT, flight.scalar_nT, sample_rate_hz=RATE)
    ours = figure_of_merit(fit.compensated_nT, flight.truth.maneuvers, RATE).fom_nT
    best = figure_of_merit(flight.truth.compensated_nT(flight.scalar_nT), flight.truth.maneuvers, RATE).fom_nT
    assert ours > 1.2 * best


@pytest.mark.parametrize("source", ["attitude", "fluxgate"])
@pytest.mark.parametrize("seed", [4, 5])
def test_maneuvers_found(source, seed):
    flight = simulate_compensation_flight(seed)
    found = find_maneuvers(
        RATE, attitude_deg=flight.attitude_deg if source == "attitude" else None, flux_nT=flight.flux_nT
    )
    assert [(m.kind) for m in found] == [m.kind for m in flight.truth.maneuvers]
    for m, t in zip(found, flight.truth.maneuvers):
        assert abs(m.start - t.start) <= 5 and abs(m.stop - t.stop) <= 5
        assert abs((m.heading_deg - t.heading_deg + 180) % 360 - 180) < 10


def test_json_round_trip(flights, fitted):
    _, second = flights
    back = TLCompensation.from_json(json.dumps(json.loads(fitted.to_json())))
    np.testing.assert_allclose(back.coefficients, fitted.coefficients)
    np.testing.assert_allclose(back.compensated_nT, fitted.compensated_nT)
    assert back.conditioning.condition_number == pytest.approx(fitted.conditioning.condition_number)
    np.testing.assert_allclose(
        back.compensate(second.scalar_nT, second.flux_nT), fitted.compensate(second.scalar_nT, second.flux_nT)
    )


def test_ridge_shrinks_the_weak_direction(flights):
    first, _ = flights
    plain = fit_tolles_lawson(first.flux_nT, first.scalar_nT, sample_rate_hz=RATE)
    ridged = fit_tolles_lawson(first.flux_nT, first.scalar_nT, sample_rate_hz=RATE, ridge=1e-3)
    assert np.linalg.norm(ridged.coefficients) < np.linalg.norm(plain.coefficients)


def _nan_scalar(flight):
    return {"scalar_nT": np.where(np.arange(flight.scalar_nT.size) == 7, np.nan, flight.scalar_nT)}


def _time_jump(flight):
    return {"time_s": flight.time_s + np.where(np.arange(flight.time_s.size) >= 100, 0.5, 0.0)}


@pytest.mark.parametrize(
    ("change", "words"),
    [
        (_nan_scalar, "scalar magnetometer has 1 missing .* row 7"),
        (lambda flight: {"terms": ("magic",)}, "unknown Tolles-Lawson term 'magic'"),
        (_time_jump, "not evenly spaced .* row 100"),
        (lambda flight: {"time_s": None}, "give the sample rate"),
    ],
)
def test_bad_input_one_message(flights, change, words):
    first, _ = flights
    kwargs = {"scalar_nT": first.scalar_nT, "time_s": first.time_s} | change(first)
    with pytest.raises(MagcalError, match=words):
        fit_tolles_lawson(first.flux_nT, **kwargs)


MAGNAV = pathlib.Path("/work/.mirror/MIT-AI-Accelerator+MagNav.jl/repo")


def _magnav_tl_data(tmp_path):
    if not MAGNAV.exists():
        pytest.skip("MagNav.jl's mirror is not on this machine")
    scipy_io = pytest.importorskip("scipy.io")
    path = tmp_path / "test_data_TL.mat"
    path.write_bytes(
        subprocess.run(
            ["git", "-C", str(MAGNAV), "show", "HEAD:test/test_data/test_data_TL.mat"], capture_output=True, check=True
        ).stdout
    )
    return scipy_io.loadmat(path, squeeze_me=True, struct_as_record=False)["TL_data"]


def test_magnav_test_data(tmp_path):
    data = _magnav_tl_data(tmp_path)
    rate = float(data.fs)
    flux = np.column_stack([data.flux_a_x, data.flux_a_y, data.flux_a_z])
    np.testing.assert_allclose(design_matrix(flux), data.A_a, atol=1e-12)
    # their band-passed design and scalar give their coefficients: the same terms, scaling and ridge
    np.testing.assert_allclose(solve_ridge(data.A_a_f_t, data.mag_1_uc_f_t, 1e-3), data.TL_a_1, rtol=1e-8)
    ours = fit_tolles_lawson(flux, data.mag_1_uc, sample_rate_hz=rate)
    theirs_bp = np.std(bandpass(data.mag_1_c, rate)[20:-20])
    assert np.std(bandpass(ours.compensated_nT, rate)[20:-20]) <= theirs_bp
    same_ridge = fit_tolles_lawson(flux, data.mag_1_uc, sample_rate_hz=rate, ridge=1e-3)
    assert np.std(same_ridge.compensated_nT - data.mag_1_c) < 0.1  # MagNav's own test of its compensation


@settings(max_examples=25, deadline=None)
@given(factor=st.floats(0.2, 5.0), seed=st.integers(0, 1000))
def test_design_scales_with_the_field(factor, seed):
    """The direction cosines do not change with the field's size; the induced and eddy columns grow with it."""
    flux = np.random.default_rng(seed).normal(0, 30_000, (20, 3))
    base, scaled = design_matrix(flux), design_matrix(factor * flux)
    np.testing.assert_allclose(scaled[:, :3], base[:, :3], atol=1e-12)
    np.testing.assert_allclose(scaled[:, 3:], factor * base[:, 3:], rtol=1e-9, atol=1e-12)


def test_fit_on_the_maneuvers_only(flights, fitted):
    first, second = flights
    mask = np.zeros(first.time_s.size, dtype=bool)
    for m in first.truth.maneuvers:
        mask[m.start : m.stop] = True
    masked = fit_tolles_lawson(first.flux_nT, first.scalar_nT, sample_rate_hz=RATE, mask=mask)
    found = second.truth.maneuvers
    ours = figure_of_merit(masked.compensate(second.scalar_nT, second.flux_nT), found, RATE).fom_nT
    assert ours <= 1.2 * figure_of_merit(second.truth.compensated_nT(second.scalar_nT), found, RATE).fom_nT
    assert masked.residual_bp_nT.size == mask.sum()


def test_fom_report_is_json(flights, fitted):
    first, _ = flights
    report = fom_report(first.scalar_nT, fitted.compensated_nT, RATE, flux_nT=first.flux_nT)
    document = json.loads(json.dumps(report.to_dict()))
    assert len(document["after"]["rows"]) == 12
    assert document["fom_before_nT"] == pytest.approx(sum(r["p2p_nT"] for r in document["before"]["rows"]))
    assert "fluxgate" in report.text()


def test_maneuvers_need_attitude_or_fluxgate():
    with pytest.raises(MagcalError, match="give the attitude"):
        find_maneuvers(RATE)
