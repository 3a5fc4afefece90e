"""The noise of a recording (magcal.checks.noise): the estimate a fit is judged against, and the robust spread.

The truth is known: magcal's simulator adds Gaussian noise of a given sigma per axis (nT), and the tests below
check that :func:`estimate_noise` finds it from the residuals of a fitted model -- with a smooth misfit left in,
for one sensor and for an array of four -- and that :func:`robust_sigma` ignores a few gross outliers.
"""

import numpy as np
import pytest

from magcal.checks.noise import (
    NoiseEstimate,
    _difference_variance,
    _difference_variance_error,
    estimate_noise,
    is_smooth_sequence,
)
from magcal.core.readings_cache import ReadingsCache
from magcal.core.stats import robust_sigma
from magcal.data.simulation import chi2017_truth, simulate, simulate_timeseries
from magcal.fitting.pipeline import calibrate

N = 3000


@pytest.mark.parametrize("n_sensors", [1, 4])
@pytest.mark.parametrize("sigma_nT", [0.5, 3.0])
def test_noise_of_a_fitted_recording_is_the_simulated_sigma(n_sensors, sigma_nT):
    ds = simulate_timeseries(chi2017_truth(n_sensors), n_samples=N, noise_nT=sigma_nT, seed=11).replace(noise_nT=None)
    fit = calibrate(ds).fit
    noise = estimate_noise(ds, fit.residuals_nT, fit.n_params)
    assert isinstance(noise, NoiseEstimate) and noise.source == "differences"
    assert noise.per_sensor_nT.shape == (n_sensors,)
    # relative standard error of sigma: half that of sigma^2, 1.97 / sqrt(N) / 2 ~ 1.8 %
    assert noise.relative_variance_error == pytest.approx(1.97 / np.sqrt(N), rel=0.01)
    assert noise.per_sensor_nT == pytest.approx(np.full(n_sensors, sigma_nT), rel=0.08)
    assert noise.sigma_nT == pytest.approx(sigma_nT, rel=0.06)


@pytest.mark.parametrize("n_sensors", [1, 4])
def test_a_smooth_misfit_does_not_pass_for_noise(n_sensors):
    """Leaving out a temperature effect inflates the residual RMS, not the noise estimate."""
    sigma_nT = 2.0
    ds = simulate_timeseries(chi2017_truth(n_sensors), n_samples=N, noise_nT=sigma_nT, seed=3).replace(noise_nT=None)
    rng = np.random.default_rng(3)
    t = ds.time_s
    misfit_nT = 20.0 * np.sin(2 * np.pi * t / 60.0) + 6.0 * np.cos(2 * np.pi * t / 17.0)  # slow along the path
    scale = np.linspace(1.0, 2.0, n_sensors)[:, None]  # a different noise level per sensor
    residuals_nT = misfit_nT[None] + rng.normal(0.0, sigma_nT, (n_sensors, N)) * scale
    residuals_nT[:, ::97] = np.nan  # samples left out of the fit
    noise = estimate_noise(ds, residuals_nT)
    assert noise.source == "differences"
    assert noise.per_sensor_nT == pytest.approx(sigma_nT * scale.ravel(), rel=0.08)
    assert np.all(np.sqrt(np.nanmean(residuals_nT**2, axis=1)) > 3 * noise.per_sensor_nT)  # RMS: misfit


@pytest.mark.parametrize("declared_nT, source", [(2.0, "given"), (None, "residuals")])
def test_random_attitudes_fall_back_on_the_declared_noise_or_the_residuals(declared_nT, source):
    ds = simulate(chi2017_truth(4), n_samples=800, noise_nT=2.0, seed=4).replace(noise_nT=declared_nT)
    assert not is_smooth_sequence(ds)
    fit = calibrate(ds).fit
    noise = estimate_noise(ds, fit.residuals_nT, fit.n_params)
    assert noise.source == source
    assert noise.sigma_nT == pytest.approx(2.0, rel=0.1)
    assert bool(noise.note) == (source != "differences")


@pytest.mark.parametrize("seed", [0, 1])
def test_time_series_is_smooth_and_random_attitudes_are_not(seed):
    assert is_smooth_sequence(simulate_timeseries(chi2017_truth(1), n_samples=500, noise_nT=1.0, seed=seed))
    assert not is_smooth_sequence(simulate(chi2017_truth(1), n_samples=500, noise_nT=1.0, seed=seed))


@pytest.mark.parametrize("order", [1, 2, 3])
def test_difference_variance_and_its_standard_error_match_monte_carlo(order):
    sigma_nT, n, trials = 1.5, 1000, 400
    rng = np.random.default_rng(order)
    estimates = np.array([_difference_variance(rng.normal(0.0, sigma_nT, n), order) for _ in range(trials)])
    # mean within 4 standard errors of the mean (the 6-sigma clipping removes almost nothing from Gaussian data)
    error = _difference_variance_error(n, order)
    assert np.mean(estimates) == pytest.approx(sigma_nT**2, abs=4 * error * sigma_nT**2 / np.sqrt(trials))
    assert np.std(estimates) / sigma_nT**2 == pytest.approx(error, rel=0.15)
    assert np.isnan(_difference_variance(np.zeros(5), order))


@pytest.mark.parametrize("outlier_fraction, tolerance", [(0.0, 0.03), (0.01, 0.04), (0.05, 0.09)])
def test_robust_sigma_ignores_gross_outliers(outlier_fraction, tolerance):
    sigma_nT = 3.0
    rng = np.random.default_rng(7)
    x = rng.normal(0.0, sigma_nT, 20_000)
    bad = rng.random(x.size) < outlier_fraction
    x[bad] = rng.choice([-1.0, 1.0], bad.sum()) * rng.uniform(500.0, 5000.0, bad.sum())  # spikes, nT
    assert robust_sigma(x) == pytest.approx(sigma_nT, rel=tolerance)
    if outlier_fraction:
        assert np.std(x) > 10 * sigma_nT


@pytest.mark.parametrize("keepdims", [False, True])
@pytest.mark.parametrize("axis", [0, 1])
def test_robust_sigma_along_an_axis(axis, keepdims):
    sigmas_nT = np.array([0.5, 1.0, 2.0, 4.0])  # one per sensor
    rng = np.random.default_rng(8)
    x = rng.normal(0.0, 1.0, (4, 30_000)) * sigmas_nT[:, None]
    x[:, ::50] = 1e6  # 2 % outliers for every sensor
    x = x.T if axis == 0 else x
    out = robust_sigma(x, axis=axis, keepdims=keepdims)
    assert out.shape == ((1, 4) if axis == 0 else (4, 1)) if keepdims else (4,)
    assert out.ravel() == pytest.approx(sigmas_nT, rel=0.05)


def test_robust_sigma_floor_for_stale_samples():
    stale = np.full(100, 41_000.0)  # a frozen reading, nT
    stale[::10] += 5.0
    assert robust_sigma(stale) == 0.0
    assert robust_sigma(stale, floor=1e-6) == 1e-6
    assert robust_sigma(stale[None], axis=1, floor=1e-6) == pytest.approx([1e-6])


def test_the_readings_facts_are_computed_once_per_record(monkeypatch):
    """A diagnosis estimates the noise of one record several times: what depends on the readings alone (still
    stretches, quantization floors, stale samples) is computed once, and the estimate is the same."""
    import magcal.checks.noise as noise_module

    ds = simulate_timeseries(chi2017_truth(2), n_samples=600, noise_nT=2.0, seed=3).replace(noise_nT=None)
    fitted = calibrate(ds).fit
    residuals = fitted.residuals_nT
    calls = []
    original = noise_module.still_noise_nT
    monkeypatch.setattr(noise_module, "still_noise_nT", lambda *a, **k: calls.append(1) or original(*a, **k))
    monkeypatch.setattr(noise_module, "_READINGS_FACTS", ReadingsCache(4))
    first = estimate_noise(ds, residuals, fitted.n_params)
    second = estimate_noise(ds, residuals, fitted.n_params)
    assert len(calls) == 1
    assert first.sigma_nT == second.sigma_nT and first.source == second.source
    other = ds.subset(np.arange(ds.n_samples) < 500)  # other readings: computed anew
    estimate_noise(other, residuals[:, :500], fitted.n_params)
    assert len(calls) == 2


def test_calibrate_prefetches_the_readings_facts_beside_the_fit(monkeypatch):
    """calibrate starts the noise's readings-only work on another thread while it fits: the facts are computed
    once, and the noise and floors are those computed in line."""
    import magcal.checks.noise as noise_module

    ds = simulate_timeseries(chi2017_truth(4), n_samples=6000, noise_nT=2.0, seed=4).replace(noise_nT=None)
    assert ds.n_samples * ds.n_sensors >= noise_module.PREFETCH_FROM_READINGS
    calls = []
    original = noise_module.still_noise_nT
    monkeypatch.setattr(noise_module, "still_noise_nT", lambda *a, **k: calls.append(1) or original(*a, **k))
    monkeypatch.setattr(noise_module, "_READINGS_FACTS", ReadingsCache(4))
    prefetched = calibrate(ds)
    assert len(calls) == 1
    monkeypatch.setattr(noise_module, "PREFETCH_FROM_READINGS", 10**12)
    monkeypatch.setattr(noise_module, "_READINGS_FACTS", ReadingsCache(4))
    in_line = calibrate(ds)
    assert len(calls) == 2
    assert prefetched.noise.sigma_nT == in_line.noise.sigma_nT and prefetched.noise.source == in_line.noise.source
    assert prefetched.total_field_floor_nT == in_line.total_field_floor_nT
