"""Step 1: ellipsoid fits against known truth, invariances, and the refusals."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from magcal.core import conventions
from magcal.core.errors import CalibrationError
from magcal.data.simulation import SensorErrors, chi2017_truth, simulate
from magcal.geometry.ellipsoid import METHODS, MIN_SAMPLES, fit_ellipsoid


def _single_sensor_readings(sensor, n, noise_nT, seed, total_nT=50_000.0):
    rng = np.random.default_rng(seed)
    directions = Rotation.random(n, random_state=rng).apply([0.0, 0.0, 1.0])
    return sensor.measure(total_nT * directions) + rng.normal(0.0, noise_nT, (n, 3))


@pytest.fixture(scope="module")
def chi_data():
    return chi2017_truth(), simulate("chi2017", seed=11)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("sensor", range(4))
def test_chi2017_step1_recovers_truth(chi_data, method, sensor):
    truth, ds = chi_data
    fit = fit_ellipsoid(ds.readings_nT[sensor], method=method, reference_total_nT=truth.total_nT)
    s = truth.sensors[sensor]
    assert np.max(np.abs(fit.cinv - s.Cinv)) < 2e-4
    assert np.max(np.abs(fit.bias_nT - s.bias_nT)) < 2.0
    assert np.allclose(np.tril(fit.cinv, -1), 0.0) and np.all(np.diag(fit.cinv) > 0)
    assert np.allclose(fit.cinv.T @ fit.cinv, fit.A)
    assert not fit.field_fitted and fit.field_nT == truth.total_nT
    assert fit.rms_nT == pytest.approx(3.0, rel=0.2)  # near the noise, sigma = 3 nT
    assert fit.coverage.thinnest_spread > 0.2 and not fit.warnings


@pytest.mark.parametrize("method", METHODS)
def test_noise_free_fit_is_exact(method):
    s = SensorErrors(
        scale=np.array([1.05, 0.97, 1.02]), psi=0.03, phi=-0.02, theta=0.04, bias_nT=np.array([310.0, -120.0, 45.0])
    )
    y = _single_sensor_readings(s, 40, 0.0, seed=3)
    fit = fit_ellipsoid(y, method=method, reference_total_nT=50_000.0)
    assert np.allclose(fit.cinv, s.Cinv, atol=1e-9)
    assert np.allclose(fit.bias_nT, s.bias_nT, atol=1e-5)
    assert fit.rms_nT < 1e-5


@pytest.mark.parametrize("method", METHODS)
def test_zero_bias_is_fine(method):
    # The seed divides eq. (8) by p, which vanishes when the bias' x component is zero; our normalisation does not.
    s = SensorErrors(bias_nT=np.zeros(3))
    fit = fit_ellipsoid(_single_sensor_readings(s, 100, 1.0, seed=5), method=method, reference_total_nT=5e4)
    assert np.max(np.abs(fit.bias_nT)) < 1.0
    assert np.max(np.abs(fit.cinv - np.eye(3))) < 1e-4


@pytest.mark.parametrize("method", METHODS)
def test_fit_moves_with_the_data(method):
    # Rotating and translating the readings rotates A and moves the centre; nothing else changes.
    s = chi2017_truth().sensors[2]
    y = _single_sensor_readings(s, 150, 3.0, seed=8)
    q = Rotation.from_rotvec([0.4, -1.1, 0.7]).as_matrix()
    shift = np.array([2000.0, -700.0, 5000.0])
    a = fit_ellipsoid(y, method=method, reference_total_nT=5e4)
    b = fit_ellipsoid(y @ q.T + shift, method=method, reference_total_nT=5e4)
    assert np.allclose(b.bias_nT, q @ a.bias_nT + shift, atol=1e-6)
    assert np.allclose(b.A, q @ a.A @ q.T, atol=1e-10)
    assert b.rms_nT == pytest.approx(a.rms_nT, rel=1e-8)


@pytest.mark.parametrize("method", METHODS)
def test_unknown_field_is_fitted_with_unit_determinant(method):
    truth = chi2017_truth()
    s = truth.sensors[1]
    y = _single_sensor_readings(s, 300, 3.0, seed=9, total_nT=48_000.0)
    fit = fit_ellipsoid(y, method=method)
    assert fit.field_fitted
    assert np.linalg.det(fit.cinv) == pytest.approx(1.0, abs=1e-12)
    # Only the common gain is unknown: C^-1 is the truth times F_fit / F_true, and F_fit = F det(C)^(1/3).
    ratio = fit.field_nT / 48_000.0
    assert ratio == pytest.approx(np.linalg.det(s.C) ** (1 / 3), rel=1e-4)
    assert np.max(np.abs(fit.cinv - s.Cinv * ratio)) < 2e-4
    known = fit.with_field(48_000.0, fitted=False, readings_nT=y)
    assert np.max(np.abs(known.cinv - s.Cinv)) < 2e-4 and not known.field_fitted
    assert known.rms_nT == pytest.approx(fit.rms_nT, rel=0.05)


def test_mask_excludes_samples():
    s = chi2017_truth().sensors[0]
    y = _single_sensor_readings(s, 120, 3.0, seed=12)
    y[:6] += 8000.0  # six wild samples
    mask = np.ones(120, bool)
    mask[:6] = False
    fit = fit_ellipsoid(y, reference_total_nT=5e4, mask=mask)
    assert fit.n_samples == 114
    assert np.max(np.abs(fit.bias_nT - s.bias_nT)) < 2.0


@pytest.mark.parametrize("n", [0, 5, MIN_SAMPLES - 1])
def test_refuses_too_few_samples(n):
    y = _single_sensor_readings(SensorErrors(), max(n, 1), 1.0, seed=1)[:n]
    with pytest.raises(CalibrationError, match="too few samples"):
        fit_ellipsoid(y, reference_total_nT=5e4)


def test_refuses_non_finite():
    y = _single_sensor_readings(SensorErrors(), 50, 1.0, seed=1)
    y[7, 1] = np.nan
    with pytest.raises(CalibrationError, match="non-finite"):
        fit_ellipsoid(y)


def test_algebraic_refuses_a_hyperboloid():
    rng = np.random.default_rng(0)
    u, t = rng.uniform(-1, 1, 300), rng.uniform(0, 2 * np.pi, 300)
    r = np.sqrt(1 + u**2)
    y = 5e4 * np.column_stack([r * np.cos(t), r * np.sin(t), u]) + rng.normal(0, 3, (300, 3))
    with pytest.raises(CalibrationError, match="hyperboloid"):
        fit_ellipsoid(y, method="algebraic")
    # The ellipsoid-specific fit always returns an ellipsoid, but this one misses the data by far too much.
    with pytest.raises(CalibrationError, match="do not lie on an ellipsoid"):
        fit_ellipsoid(y, method="li-griffiths")


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("wobble_deg", [0.0, 2.0])
def test_refuses_rotation_about_one_axis(method, wobble_deg):
    rng = np.random.default_rng(2)
    truth = chi2017_truth()
    n = 200
    angles = np.column_stack([rng.uniform(0, 2 * np.pi, n), np.radians(rng.uniform(-wobble_deg, wobble_deg, (n, 2)))])
    att = Rotation.from_euler("ZYX", angles)
    y = truth.sensors[1].measure(att.inv().apply(truth.field_world_nT)) + rng.normal(0, 3, (n, 3))
    with pytest.raises(CalibrationError, match="degenerate coverage"):
        fit_ellipsoid(y, method=method, reference_total_nT=truth.total_nT)


def test_weak_coverage_warns():
    # Full turns about z with +-20 deg tilts: determined, but poorly; the fit says so.
    rng = np.random.default_rng(6)
    truth = chi2017_truth()
    n = 300
    angles = np.column_stack([rng.uniform(0, 2 * np.pi, n), np.radians(rng.uniform(-20, 20, (n, 2)))])
    y = truth.sensors[0].measure(Rotation.from_euler("ZYX", angles).inv().apply(truth.field_world_nT))
    fit = fit_ellipsoid(y + rng.normal(0, 3, y.shape), reference_total_nT=truth.total_nT)
    assert fit.warnings and "weak coverage" in fit.warnings[0]
    assert fit.coverage.sky_fraction < 0.6


def test_unknown_method():
    with pytest.raises(CalibrationError, match="unknown ellipsoid method"):
        fit_ellipsoid(np.zeros((20, 3)), method="magic")


def test_gauge_free_figures_match_truth(chi_data):
    truth, ds = chi_data
    fit = fit_ellipsoid(ds.readings_nT[3], reference_total_nT=truth.total_nT)
    k, angles = conventions.gauge_free(fit.cinv)
    k_true, angles_true = conventions.gauge_free(truth.sensors[3].Cinv)
    assert np.allclose(k, truth.sensors[3].scale, atol=2e-4) and np.allclose(k, k_true, atol=2e-4)
    assert np.allclose(angles, angles_true, atol=0.02)


def _turning_record(n, rng, total_nT=50_000.0):
    """Readings of a sensor turned smoothly through all directions (the turn rate wanders), in time order."""
    k = np.arange(n)[:, None] + rng.uniform(0, 1000)
    rate = 0.02 * np.sin(k / np.array([150.0, 230.0, 310.0]) + np.array([0.0, 1.0, 2.0]))  # rad per sample
    att = [Rotation.identity()]
    for s in Rotation.from_rotvec(rate[1:]):
        att.append(s * att[-1])
    return np.array([a.inv().apply([0.0, 0.0, total_nT]) for a in att])


def test_refusal_names_a_centre_that_moves_between_parts():
    """qmc_noisy-like refusal, with a known cause: the hard iron jumps by 12000 nT halfway through the record."""
    rng = np.random.default_rng(31)
    b = _turning_record(4000, rng)
    y = b @ np.diag([1.05, 0.95, 1.0]).T + np.array([3000.0, -2000.0, 1000.0]) + rng.normal(0, 30.0, b.shape)
    y[2000:] += np.array([12_000.0, 0.0, 0.0])
    with pytest.raises(CalibrationError) as exc:
        fit_ellipsoid(y)
    text = str(exc.value)
    assert "do not lie on an ellipsoid" in text and "hard iron or the field at the sensor changed" in text
    move = float(text.split("centre (hard iron) moves by up to ")[1].split(" nT")[0])
    assert move == pytest.approx(12_000.0, rel=0.1)
    assert "own noise accounts for it" not in text


def test_refusal_names_the_readings_own_noise():
    """qmc_noisy: 2 uT of noise per axis on a 36 uT field is 6 % RMS; the message says the noise accounts for it."""
    rng = np.random.default_rng(32)
    b = _turning_record(4000, rng, total_nT=36_000.0)
    y = b + np.array([200_000.0, 8000.0, 115_000.0]) + rng.normal(0, 2000.0, b.shape)
    with pytest.raises(CalibrationError) as exc:
        fit_ellipsoid(y)
    text = str(exc.value)
    assert "own noise accounts for it" in text and "changed during the record" not in text
    scatter = float(text.split("the total field scatters by ")[1].split(" nT")[0])
    assert scatter == pytest.approx(2000.0, rel=0.1)  # isotropic noise: the total field gets sigma too


def test_a_lenient_fit_returns_the_best_ellipsoid():
    rng = np.random.default_rng(33)
    b = _turning_record(2000, rng, total_nT=36_000.0)
    y = b + rng.normal(0, 2000.0, b.shape)
    fit = fit_ellipsoid(y, strict=False)
    assert fit.field_nT == pytest.approx(36_000.0, rel=0.03)
    assert np.all(np.abs(fit.bias_nT) < 500.0)


@pytest.mark.parametrize("seed", [0, 1])
def test_refusal_of_a_cap_names_the_coverage(seed):
    """Flight logs (ap_erlebrain3, px4_sample): a cap of directions gives a hyperboloid or a poor fit; the refusal
    says how little of the sphere the readings cover."""
    rng = np.random.default_rng(seed)
    u = Rotation.random(6000, random_state=rng).apply([0.0, 0.0, 1.0])
    u = u[u[:, 2] > np.cos(np.radians(20))][:500]
    y = 50_000.0 * u + rng.normal(0, 500, u.shape)
    with pytest.raises(CalibrationError, match=r"cover only \d+% of the sphere of directions") as exc:
        fit_ellipsoid(y)
    assert "do not lie on an ellipsoid" in str(exc.value)


@pytest.mark.parametrize("method", METHODS)
def test_gram_matrix_accumulated_in_blocks_gives_the_whole_designs_solution(monkeypatch, method):
    """Block by block (a few dozen rows each) the quadric is the one of the whole design matrix: numpy's lstsq of
    it for the algebraic fit, the unblocked eigenproblem for Li-Griffiths."""
    import magcal.geometry.ellipsoid as ell

    y = _single_sensor_readings(chi2017_truth().sensors[2], 700, 3.0, seed=4)
    p = (y - y.mean(axis=0)) / 5e4
    whole = ell._coefficients_algebraic(p) if method == "algebraic" else ell._coefficients_li_griffiths(p)
    monkeypatch.setattr(ell, "BLOCK_ROWS", 37)
    blocked = ell._coefficients_algebraic(p) if method == "algebraic" else ell._coefficients_li_griffiths(p)
    scale = np.abs(whole).max()
    np.testing.assert_allclose(blocked / scale, whole / scale, rtol=0, atol=1e-12)
    if method == "algebraic":
        rows = ell._algebraic_rows(p)
        reference = np.linalg.lstsq(rows[:, :-1], rows[:, -1], rcond=None)[0]
        np.testing.assert_allclose(np.delete(blocked, 2), reference, rtol=0, atol=1e-12 * np.abs(reference).max())


def test_a_start_fits_an_even_subsample_of_at_most_max_samples():
    y = _single_sensor_readings(chi2017_truth().sensors[1], 1000, 3.0, seed=5)
    start = fit_ellipsoid(y, max_samples=300)
    every = int(np.ceil(1000 / 300))
    same = fit_ellipsoid(y[::every])
    assert start.n_samples == same.n_samples == len(y[::every])
    np.testing.assert_allclose(start.cinv, same.cinv, rtol=0, atol=1e-15)
    np.testing.assert_allclose(start.bias_nT, same.bias_nT, rtol=0, atol=1e-9)
    assert fit_ellipsoid(y, max_samples=5000).n_samples == 1000
