"""magcal.checks.coverage: covered fraction, expected extrapolation error, refusing a rotation about one axis."""

import re
import warnings

import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from magcal.checks import coverage as cv
from magcal.core.errors import CoverageWarning
from magcal.data import simulation as sim
from magcal.data.dataset import DatasetError
from magcal.geometry import shape, sphere

SIGMA = 3.0


def readings(attitudes, rng, truth=None, sigma=SIGMA):
    truth = truth or sim.chi2017_truth()
    fields = sim.true_fields(truth, attitudes)
    clean = np.stack([s.measure(f) for s, f in zip(truth.sensors, fields)])
    return clean + rng.normal(0.0, sigma, clean.shape)


def tilted(n, tilt_deg, rng):
    """Free heading, roll and pitch limited to +-tilt_deg (a sensor kept roughly level)."""
    t = np.radians(tilt_deg)
    return Rotation.from_euler(
        "ZYX", np.column_stack([rng.uniform(-np.pi, np.pi, n), rng.uniform(-t, t, n), rng.uniform(-t, t, n)])
    )


def test_fibonacci_sphere_is_even():
    u = sphere.fibonacci_sphere(2000)
    np.testing.assert_allclose(np.linalg.norm(u, axis=1), 1.0)
    np.testing.assert_allclose(u.mean(axis=0), 0.0, atol=2e-3)
    np.testing.assert_allclose(u.T @ u / len(u), np.eye(3) / 3, atol=2e-3)


def test_sphere_centre_finds_the_offset():
    rng = np.random.default_rng(1)
    u = sphere.fibonacci_sphere(300)
    centre = np.array([120.0, -340.0, 80.0])
    y = 50_000 * u + centre + rng.normal(0, 3, u.shape)
    np.testing.assert_allclose(sphere.sphere_centre(y), centre, atol=2.0)


@pytest.mark.parametrize("offset_fraction", [0.0, 0.8, 1.5, 3.0])
def test_a_hard_iron_offset_larger_than_the_field_keeps_the_fitted_centre(offset_fraction):
    """MEMS parts carry offsets above the field; the whole sphere must still read as covered."""
    rng = np.random.default_rng(5)
    u = Rotation.random(600, random_state=rng).apply([0.0, 0.0, 1.0])
    soft = np.array([[1.1, 0.05, 0.0], [0.05, 0.92, 0.03], [0.0, 0.03, 1.0]])  # MEMS-like soft iron
    centre = offset_fraction * 30_000.0 * np.array([0.6, -0.64, 0.48])
    y = 30_000.0 * u @ soft.T + centre + rng.normal(0, 50, u.shape)
    np.testing.assert_allclose(sphere.sphere_centre(y), centre, atol=0.03 * 30_000)
    assert shape.field_magnitude_nT(y) == pytest.approx(30_000, rel=0.1)
    cov = cv.check_coverage(y)
    assert cov.notes == [] and cov.fraction[0] > 0.95


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
    assert cv.check_coverage(y, noise_nT=SIGMA).notes == []


@pytest.mark.parametrize("tilt_deg", [45, 20, 10])
def test_limited_tilts_warn_with_the_expected_error(tilt_deg):
    rng = np.random.default_rng(tilt_deg)
    y = readings(tilted(200, tilt_deg, rng), rng)
    cov = cv.check_coverage(y, noise_nT=SIGMA)
    assert [n.category for n in cov.notes] == [CoverageWarning]
    assert re.search(r"expected total-field error .* nT", cov.notes[0].text)
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

    p0 = np.array([1, 0, 0, 1, 0, 1, *sphere.sphere_centre(y)], float)
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
    predicted = shape.extrapolation_factor(shape.sensor_directions(clean)) * SIGMA
    test_u = sphere.fibonacci_sphere(400)
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
    assert [n.category for n in cv.check_coverage(y, noise_nT=SIGMA, full_model=False).notes] == [CoverageWarning]


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
    ds1 = ds.replace(
        readings_nT=readings(Rotation.from_euler("z", np.linspace(0, 6, 200)[:, None]), np.random.default_rng(0))
    )
    with pytest.raises(DatasetError, match="field.csv"):
        cv.check_coverage(ds1)


def _mems_readings(n, field_nT, gains, offset_fields, rng, noise_nT=300.0, tilt_deg=None):
    """Readings of a MEMS-like part: axis gains differing by ``max(gains)/min(gains)``, a few degrees of
    non-orthogonality and a hard iron ``offset_fields`` times the field (QMC5883L on a board: 2.2x, 6x)."""
    att = Rotation.random(n, random_state=rng) if tilt_deg is None else tilted(n, tilt_deg, rng)
    b = att.inv().apply(field_nT * np.array([0.4, 0.0, -0.9165]))
    shape = np.diag(gains) @ np.array([[1.0, 0.05, -0.02], [0.0, 1.0, 0.04], [0.0, 0.0, 1.0]])
    offset = offset_fields * field_nT * np.array([0.85, 0.03, 0.52])
    return b @ shape.T + offset + rng.normal(0.0, noise_nT, b.shape)


def test_a_hard_iron_far_beyond_the_field_with_unequal_gains_is_full_coverage():
    """qmc_filtered: gains differing 2.2x put the readings 16 % off any sphere; the quick sphere was then
    rejected and the origin used (hard iron 6x the field): '12 % of the sphere, gap 167 deg'. The ellipsoid fit is
    the centre and the shape: the whole sphere reads as covered and the magnitude is the field."""
    rng = np.random.default_rng(21)
    y = _mems_readings(3000, 35_700.0, [1.0, 0.67, 1.48], 6.0, rng)
    fitted = shape.field_shape(y)
    assert fitted.source == "ellipsoid"
    np.testing.assert_allclose(fitted.centre_nT, 6.0 * 35_700.0 * np.array([0.85, 0.03, 0.52]), atol=300.0)
    # the gains' geometric mean is 0.995: the magnitude through the fitted shape is the field times it
    assert shape.field_magnitude_nT(y) == pytest.approx(35_700.0 * np.cbrt(0.67 * 1.48), rel=0.01)
    cov = cv.check_coverage(y, noise_nT=300.0)
    assert cov.notes == [] and cov.fraction[0] > 0.97 and cov.largest_gap_deg[0] < 30
    # the directions go through the shape: they spread evenly (covariance I/3), not squeezed along the weak axis
    u = shape.sensor_directions(y)
    np.testing.assert_allclose(u.T @ u / len(u), np.eye(3) / 3, atol=0.03)


def test_limited_tilts_still_warn_with_a_large_hard_iron():
    """The ellipsoid centre must not turn a genuinely partial record into a covered one."""
    rng = np.random.default_rng(22)
    y = _mems_readings(300, 50_000.0, [1.0, 0.9, 1.1], 3.0, rng, noise_nT=30.0, tilt_deg=15)
    cov = cv.check_coverage(y, noise_nT=30.0)
    assert len(cov.notes) == 1 and cov.notes[0].is_a(CoverageWarning) and "poor direction coverage" in cov.notes[0].text
    assert cov.fraction[0] < 0.8


@pytest.mark.parametrize("cap_deg, noise_nT", [(35, 30.0), (35, 300.0), (20, 300.0)])
def test_an_ellipsoid_through_a_cap_is_not_trusted(cap_deg, noise_nT):
    """A cap of directions does not determine an ellipsoid (its centre slides along the cap's axis): the shape
    falls back to the quick sphere or the origin, and the cap is not called covered."""
    rng = np.random.default_rng(cap_deg)
    u = Rotation.random(4000, random_state=rng).apply([0.0, 0.0, 1.0])
    u = u[u[:, 2] > np.cos(np.radians(cap_deg))][:400]
    y = 30_000.0 * u + np.array([40_000.0, 0.0, 0.0]) + rng.normal(0, noise_nT, u.shape)
    assert shape.field_shape(y).source != "ellipsoid"
    assert cv.coverage(y).fraction[0] < 0.5


def test_the_unit_check_uses_the_fitted_magnitude(tmp_path):
    """magcal.data.io.check_units (it calls field_magnitude_nT): no unit warning for a 6x hard iron with 2.2x gains."""
    from magcal.core.errors import DataWarning
    from magcal.data import io
    from magcal.data.dataset import Dataset

    rng = np.random.default_rng(23)
    y = _mems_readings(2000, 35_700.0, [1.0, 0.67, 1.48], 6.0, rng)
    ds = Dataset(readings_nT=y[None], source="qmc-like.csv")
    with warnings.catch_warnings():
        warnings.simplefilter("error", DataWarning)
        assert io.check_units(ds, "nT") is None
    assert "outside the Earth's field range" in io.check_units(ds.replace(readings_nT=0.2 * y[None]), "nT")  # 7 uT


def test_a_covered_sphere_with_uneven_density_is_not_poor_coverage():
    """A flight log (ads_flight_rm3100): 99 % of the sphere within 30 deg of a sample, but most samples level;
    the expected error off the dense directions is a tenth of the noise: 'poor direction coverage' was false."""
    rng = np.random.default_rng(24)
    level = readings(tilted(3900, 5, rng), rng)  # most of the record: near level
    spread = readings(Rotation.random(100, random_state=rng), rng)
    y = np.concatenate([level, spread], axis=1)
    cov = cv.coverage(y, noise_nT=SIGMA)
    assert np.all(cov.fraction > 0.95)
    assert np.all(cov.extrapolation_factor > 3 * cov.full_factor) and np.all(cov.extrapolation_factor < 0.5)
    assert cv.check_coverage(y, noise_nT=SIGMA).notes == []
