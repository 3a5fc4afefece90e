"""magcal.coverage: covered fraction, expected extrapolation error, refusing a rotation about one axis."""

import warnings

import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from magcal import coverage as cv
from magcal import simulation as sim
from magcal.dataset import DatasetError
from magcal.errors import CoverageWarning

SIGMA = 3.0


def readings(attitudes, rng, truth=None, sigma=SIGMA):
    truth = truth or sim.chi2017_truth()
    fields = sim.true_fields(truth, attitudes)
    clean = np.stack([s.measure(f) for s, f in zip(truth.sensors, fields)])
    return clean + rng.normal(0.0, sigma, clean.shape)


def tilted(n, tilt_deg, rng):
    """Free heading, roll and pitch limited to +-tilt_deg (a sensor kept roughly level)."""
    t = np.radians(tilt_deg)
    return Rotation.from_euler("ZYX", np.column_stack([rng.uniform(-np.pi, np.pi, n), rng.uniform(-t, t, n),
                                                       rng.uniform(-t, t, n)]))


def test_fibonacci_sphere_is_even():
    u = cv.fibonacci_sphere(2000)
    np.testing.assert_allclose(np.linalg.norm(u, axis=1), 1.0)
    np.testing.assert_allclose(u.mean(axis=0), 0.0, atol=2e-3)
    np.testing.assert_allclose(u.T @ u / len(u), np.eye(3) / 3, atol=2e-3)


def test_sphere_centre_finds_the_offset():
    rng = np.random.default_rng(1)
    u = cv.fibonacci_sphere(300)
    centre = np.array([120.0, -340.0, 80.0])
    y = 50_000 * u + centre + rng.normal(0, 3, u.shape)
    np.testing.assert_allclose(cv.sphere_centre(y), centre, atol=2.0)


@pytest.mark.parametrize("offset_fraction", [0.0, 0.8, 1.5, 3.0])
def test_a_hard_iron_offset_larger_than_the_field_keeps_the_fitted_centre(offset_fraction):
    """Issue 10: MEMS parts carry offsets above the field; the whole sphere must still read as covered."""
    rng = np.random.default_rng(5)
    u = Rotation.random(600, random_state=rng).apply([0.0, 0.0, 1.0])
    soft = np.array([[1.1, 0.05, 0.0], [0.05, 0.92, 0.03], [0.0, 0.03, 1.0]])  # MEMS-like soft iron
    centre = offset_fraction * 30_000.0 * np.array([0.6, -0.64, 0.48])
    y = 30_000.0 * u @ soft.T + centre + rng.normal(0, 50, u.shape)
    np.testing.assert_allclose(cv.sphere_centre(y), centre, atol=0.03 * 30_000)
    assert cv.field_magnitude_nT(y) == pytest.approx(30_000, rel=0.1)
    with warnings.catch_warnings():
        warnings.simplefilter("error", CoverageWarning)
        cov = cv.check_coverage(y)
    assert cov.fraction[0] > 0.95


def test_a_small_cap_far_from_the_origin_is_not_called_covered():
    """A cap of readings does not determine a centre: the quick fit must not invent full coverage."""
    rng = np.random.default_rng(6)
    u = Rotation.random(400, random_state=rng).apply([0.0, 0.0, 1.0])
    u = u[u[:, 2] > np.cos(np.radians(35))]
    y = 30_000.0 * u + np.array([40_000.0, 0.0, 0.0]) + rng.normal(0, 300, u.shape)
    assert cv.coverage(y).fraction[0] < 0.5


def test_full_sphere_is_covered_and_at_the_even_coverage_error():
    rng = np.random.default_rng(2)
    y = readings(Rotation.random(400, random_state=rng), rng)
    cov = cv.coverage(y, noise_nT=SIGMA)
    assert np.all(cov.fraction > 0.99)
    assert np.all(cov.largest_gap_deg < 25)
    np.testing.assert_allclose(cov.extrapolation_factor, cov.full_factor, rtol=0.25)
    # the even-coverage figure is the in-sample p/N law: sqrt(9/N) per unit noise, within a few %
    assert cov.full_factor == pytest.approx(np.sqrt(9 / 400), rel=0.1)
    with warnings.catch_warnings():
        warnings.simplefilter("error", CoverageWarning)
        cv.check_coverage(y, noise_nT=SIGMA)


@pytest.mark.parametrize("tilt_deg", [45, 20, 10])
def test_limited_tilts_warn_with_the_expected_error(tilt_deg):
    rng = np.random.default_rng(tilt_deg)
    y = readings(tilted(200, tilt_deg, rng), rng)
    with pytest.warns(CoverageWarning, match=r"expected total-field error .* nT"):
        cov = cv.check_coverage(y, noise_nT=SIGMA)
    assert np.all(cov.extrapolation_factor > 3 * cov.full_factor)
    assert np.all(cov.fraction < 0.8)


def test_error_grows_as_the_tilt_range_shrinks():
    rng = np.random.default_rng(7)
    k = [cv.coverage(readings(tilted(200, t, rng), rng)).extrapolation_factor.mean() for t in (90, 45, 20, 10)]
    assert all(a < b for a, b in zip(k, k[1:]))


def _fit_ellipsoid(y, F):
    """Reference ML fit of |A^(1/2)(y - b)| = F by least squares (A symmetric, 9 parameters)."""
    def unpack(p):
        a = np.array([[p[0], p[1], p[2]], [p[1], p[3], p[4]], [p[2], p[4], p[5]]])
        return a, p[6:]

    def res(p):
        a, b = unpack(p)
        z = (y - b) / F
        return F * (np.sqrt(np.einsum("ij,jk,ik->i", z, a, z)) - 1.0)

    p0 = np.array([1, 0, 0, 1, 0, 1, *cv.sphere_centre(y)], float)
    sol = least_squares(res, p0, method="lm", x_scale=np.r_[np.full(6, 1e-4), np.full(3, 1.0)])
    return unpack(sol.x)


def test_predicted_extrapolation_error_matches_monte_carlo():
    """The figure the warning quotes is what fits from such data really do on the whole sphere."""
    rng = np.random.default_rng(11)
    F, n, tilt = 50_000.0, 150, 30
    att = tilted(n, tilt, rng)
    b_true = np.array([40.0, -25.0, 60.0])
    u_sensor = att.inv().apply(sim.conventions.earth_field(1.0, 0.0, 60.0))
    clean = F * u_sensor + b_true
    predicted = cv.extrapolation_factor(cv.sensor_directions(clean)) * SIGMA
    test_u = cv.fibonacci_sphere(400)
    errs = []
    for _ in range(40):
        a, b = _fit_ellipsoid(clean + rng.normal(0, SIGMA, clean.shape), F)
        z = F * test_u + b_true - b
        errs.append(np.sqrt(np.einsum("ij,jk,ik->i", z, a, z)) - F)
    rms = float(np.sqrt(np.mean(np.square(errs))))
    assert predicted == pytest.approx(rms, rel=0.3)


@pytest.mark.parametrize("axis", ["x", "y", "z"])
def test_rotation_about_one_axis_is_refused_for_a_full_model(axis):
    rng = np.random.default_rng(3)
    y = readings(Rotation.from_euler(axis, rng.uniform(-np.pi, np.pi, (200, 1))), rng)
    with pytest.raises(DatasetError, match="one axis"):
        cv.check_coverage(y, noise_nT=SIGMA)
    with pytest.warns(CoverageWarning):
        cv.check_coverage(y, noise_nT=SIGMA, full_model=False)


def test_no_rotation_is_refused():
    rng = np.random.default_rng(4)
    small = Rotation.from_rotvec(rng.normal(0, np.radians(1), (100, 3)))
    with pytest.raises(DatasetError, match="hardly changes|one axis"):
        cv.check_coverage(readings(small, rng), noise_nT=SIGMA)


def test_dataset_input_uses_its_noise_and_source():
    ds = sim.simulate("chi2017", n_samples=200, seed=5).replace(source="field.csv")
    cov = cv.coverage(ds)
    assert cov.noise_nT == 3.0 and cov.extrapolation_nT.shape == (4,)
    assert "sensor 4" in cov.text()
    ds1 = ds.replace(readings_nT=readings(Rotation.from_euler("z", np.linspace(0, 6, 200)[:, None]),
                                          np.random.default_rng(0)))
    with pytest.raises(DatasetError, match="field.csv"):
        cv.check_coverage(ds1)
