"""The calibration's error bars carried to the corrected field and the tensor (magcal.calibration.uncertainty), checked against
Monte Carlo draws of the fitted parameters from their covariance."""

from __future__ import annotations

import numpy as np
import pytest

import magcal
from magcal.core import conventions


@pytest.fixture(scope="module")
def fitted():
    ds = magcal.simulate("chi2017", n_samples=150, seed=3)
    result = magcal.calibrate(ds)
    new = magcal.simulate("chi2017", n_samples=60, seed=8)
    return result, new


def test_linear_propagation_matches_monte_carlo(fitted):
    result, new = fitted
    cal, fit = result.calibration, result.fit
    u = cal.uncertainty(new)
    rng = np.random.default_rng(0)
    draws = rng.multivariate_normal(fit.x, fit.covariance, size=600)
    vecs, tens = [], []
    for x in draws:
        c = fit.problem.calibration(x)
        b = c.correct(new)
        vecs.append(b)
        tens.append(np.array(list(conventions.tensor_components(b, cal.baseline_m).values())))
    vecs, tens = np.array(vecs), np.array(tens)
    mc_vec = vecs.std(axis=0)
    ratio = u["vector_sd_nT"] / mc_vec
    assert 0.85 < np.median(ratio) < 1.15 and np.percentile(ratio, 5) > 0.75 and np.percentile(ratio, 95) < 1.3
    mc_total = np.linalg.norm(vecs, axis=3).std(axis=0)
    assert 0.85 < np.median(u["total_sd_nT"] / mc_total) < 1.15
    names = list(conventions.tensor_components(vecs[0], cal.baseline_m))
    mc_tensor = tens.std(axis=0)
    for i, name in enumerate(names):
        assert 0.85 < np.median(u["tensor_sd_nT_per_m"][name] / mc_tensor[i]) < 1.15, name


def test_more_samples_smaller_error_bars():
    small = magcal.calibrate(magcal.simulate("chi2017", n_samples=100, seed=4)).calibration
    large = magcal.calibrate(magcal.simulate("chi2017", n_samples=1600, seed=4)).calibration
    new = magcal.simulate("chi2017", n_samples=50, seed=9)
    ratio = small.uncertainty(new)["total_sd_nT"].mean() / large.uncertainty(new)["total_sd_nT"].mean()
    assert 3.0 < ratio < 5.5  # ~ sqrt(16) = 4


@pytest.mark.parametrize("which, wrong_size", [("fitted", 2), ("fitted_with_effects", 50)])
def test_the_covariance_travels_in_the_json_and_old_files_still_load(request, tmp_path, which, wrong_size):
    """The base model's covariance, and the joint one with effect terms, saved and loaded; a file from before
    has no error bars; a matrix of the wrong size is refused."""
    result, new = request.getfixturevalue(which)
    cal = result.calibration
    cal.save(tmp_path / "cal.json")
    back = magcal.Calibration.load(tmp_path / "cal.json")
    np.testing.assert_allclose(back.base_covariance, cal.base_covariance)
    np.testing.assert_allclose(back.uncertainty(new)["vector_sd_nT"], cal.uncertainty(new)["vector_sd_nT"])
    doc = cal.to_dict()
    doc.pop("base_covariance")
    assert magcal.Calibration.from_dict(doc).uncertainty(new) is None  # a file from before: no error bars
    doc["base_covariance"] = {"matrix": np.eye(wrong_size).tolist()}
    with pytest.raises(magcal.MagcalError, match="base_covariance"):
        magcal.Calibration.from_dict(doc)


@pytest.mark.parametrize("out_name", ["out.csv", "out.parquet"])
def test_apply_writes_the_error_bars(fitted, tmp_path, out_name):
    from magcal.cli import main
    from magcal.data import io as mio

    result, new = fitted
    result.calibration.save(tmp_path / "cal.json")
    mio.write_csv(tmp_path / "survey.csv", new)
    out = tmp_path / out_name
    assert (
        main(
            [
                "apply",
                str(tmp_path / "cal.json"),
                str(tmp_path / "survey.csv"),
                "-o",
                str(out),
                "--uncertainty",
                "--no-progress",
            ]
        )
        == 0
    )
    got = magcal.read_csv(out)
    u = result.calibration.uncertainty(new)
    np.testing.assert_allclose(np.asarray(got.extra["s2y_cal_sd"], float), u["vector_sd_nT"][1, :, 1], rtol=1e-3)
    np.testing.assert_allclose(np.asarray(got.extra["s4_F_sd"], float), u["total_sd_nT"][3], rtol=1e-3)
    np.testing.assert_allclose(np.asarray(got.extra["Gzz_sd"], float), u["tensor_sd_nT_per_m"]["Gzz"], rtol=1e-3)


def test_a_calibration_without_covariance_refuses_error_bars(fitted, tmp_path):
    from magcal.data import io as mio
    from magcal.output.apply import apply_file

    result, new = fitted
    doc = result.calibration.to_dict()
    doc.pop("base_covariance")
    mio.write_csv(tmp_path / "survey.csv", new)
    with pytest.raises(magcal.MagcalError, match="recalibrate to get error bars"):
        apply_file(magcal.Calibration.from_dict(doc), tmp_path / "survey.csv", tmp_path / "o.csv", uncertainty=True)


@pytest.fixture(scope="module")
def fitted_with_effects():
    """Four sensors along a time series with a temperature bias (raw stage) and a sensor timing skew (array
    stage) hidden and fitted; new data from the same instrument."""
    from magcal.data.simulation import chi2017_truth, simulate_timeseries
    from magcal.model import perturbations

    hidden = [
        perturbations.parse_hidden("temperature_bias=2", 4),
        perturbations.parse_hidden("sensor_timing_skew:3", 4),
    ]
    ds = simulate_timeseries(chi2017_truth(4), n_samples=400, noise_nT=3.0, seed=5, perturbations=hidden)
    result = magcal.calibrate(ds, effects=["temperature_bias", "sensor_timing_skew:3"])
    new = simulate_timeseries(chi2017_truth(4), n_samples=80, noise_nT=3.0, seed=9, perturbations=hidden)
    return result, new


def test_the_effects_parameters_are_carried_with_their_correlations(fitted_with_effects):
    """Linear propagation of the joint covariance (base terms and both effects) against Monte Carlo draws of every
    fitted parameter, and larger error bars than the base terms alone give."""
    result, new = fitted_with_effects
    cal, fit = result.calibration, result.fit
    q = sum(len(e.param_names()) for e, _ in cal.model.instances())
    assert cal.base_covariance.shape == (48 + q, 48 + q)
    u = cal.uncertainty(new)
    rng = np.random.default_rng(1)
    draws = rng.multivariate_normal(fit.x, fit.covariance, size=600, check_valid="ignore", method="eigh")
    vecs = np.array([fit.problem.calibration(x).correct(new) for x in draws])
    ratio = u["vector_sd_nT"] / vecs.std(axis=0)
    assert 0.85 < np.median(ratio) < 1.15 and np.percentile(ratio, 5) > 0.7 and np.percentile(ratio, 95) < 1.35
    assert 0.85 < np.median(u["total_sd_nT"] / np.linalg.norm(vecs, axis=3).std(axis=0)) < 1.15
    base_only = magcal.Calibration.from_dict(cal.to_dict())
    base_only.base_covariance = cal.base_covariance[:48, :48]
    assert np.median(u["vector_sd_nT"] / base_only.uncertainty(new)["vector_sd_nT"]) > 1.05


@pytest.mark.parametrize("which", ["fitted", "fitted_with_effects"])
def test_theta_covariance_is_the_whole_vectors_finite_difference(request, which):
    """base_covariance differentiates each sensor's theta by its own base columns only; differentiating theta of
    every sensor by every parameter gives the same covariance (the other columns do not move a sensor)."""
    from magcal.calibration.uncertainty import THETA_PER_SENSOR, base_covariance, theta_of

    result, _ = request.getfixturevalue(which)
    fit = result.fit
    problem, x = fit.problem, fit.x
    sd = np.sqrt(np.diag(fit.covariance))
    jac = np.zeros((THETA_PER_SENSOR * problem.n_sensors, x.size))
    for p in range(x.size):
        h = max(1e-3 * sd[p], 1e-9 * max(abs(x[p]), 1.0))
        xp, xm = x.copy(), x.copy()
        xp[p] += h
        xm[p] -= h
        jac[:, p] = (theta_of(problem.sensors(xp)) - theta_of(problem.sensors(xm))) / (2 * h)
    theta_cov = jac @ fit.covariance @ jac.T
    got = base_covariance(fit)[: jac.shape[0], : jac.shape[0]]
    np.testing.assert_allclose(got, 0.5 * (theta_cov + theta_cov.T), rtol=1e-9, atol=1e-12 * np.max(np.abs(theta_cov)))
