"""Global-search scalar calibration (pso, ipso, de) against known truth and the exact least-squares minimum."""

import csv

import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

import magcal
from magcal.core import conventions
from magcal.core.errors import MagcalError
from magcal.data.io import read_csv
from magcal.data.simulation import SensorErrors, ding2024_fluxgate_truth, ding2024_truth
from magcal.fitting import search

FAST = {"pop_size": 30, "max_iter": 400}


def _identifiable_start(sensor):
    """The true 9 numbers in magcal's gauge: upper-triangular C^-1 of (M M^T)^-1 and the offset I."""
    m = sensor.total_matrix
    return conventions.cinv_from_quadric(np.linalg.inv(m @ m.T)), sensor.total_offset_nT


def _least_squares_minimum(readings, reference, cinv0, bias0):
    """Exact minimum of eq. (17) by Levenberg-Marquardt from the truth (written here, independent of search)."""

    def residuals(p):
        u = np.zeros((3, 3))
        u[np.triu_indices(3)] = p[:6]
        return np.linalg.norm((readings - p[6:]) @ u.T, axis=1) - reference

    p0 = np.concatenate([cinv0[np.triu_indices(3)], bias0])
    sol = least_squares(
        residuals, p0, method="lm", x_scale=np.r_[np.full(6, 1e-5), np.ones(3)], xtol=1e-15, ftol=1e-15, gtol=1e-15
    )
    u = np.zeros((3, 3))
    u[np.triu_indices(3)] = sol.x[:6]
    return float(np.sqrt(np.mean(sol.fun**2))), u, sol.x[6:]


@pytest.fixture(scope="module")
def small_problem():
    """Ding simulation 1, 120 attitudes, uniform noise of full width 2 nT."""
    truth = ding2024_truth()
    ds = magcal.simulate(truth, n_samples=120, noise_nT=2.0, noise_kind="uniform", seed=5)
    cinv0, bias0 = _identifiable_start(truth.sensors[0])
    rms_min, u_min, b_min = _least_squares_minimum(ds.readings_nT[0], truth.total_nT, cinv0, bias0)
    return truth, ds, rms_min, u_min, b_min


@pytest.mark.parametrize("method", search.METHODS)
def test_each_method_reaches_the_least_squares_minimum(small_problem, method):
    truth, ds, rms_min, u_min, b_min = small_problem
    res = search.search(ds.readings_nT[0], truth.total_nT, method=method, seed=3, **FAST)
    assert res.rms_nT <= rms_min * 1.001
    assert res.rms_nT >= rms_min * (1 - 1e-9)  # nothing beats the exact minimum
    assert np.max(np.abs(res.cinv - u_min)) < 1e-5
    assert np.max(np.abs(res.bias_nT - b_min)) < 0.05
    # and that minimum is the physical floor for uniform noise of full width 2 nT, 9 parameters, N = 120
    floor = conventions.total_field_floor_nT(2.0 / np.sqrt(12.0), 120)
    assert rms_min == pytest.approx(floor, rel=0.2)
    assert np.allclose(np.tril(res.cinv, -1), 0.0) and np.all(np.diag(res.cinv) > 0)


@pytest.mark.parametrize("method", search.METHODS)
@pytest.mark.parametrize("truth_factory", [ding2024_truth, ding2024_fluxgate_truth])
def test_noise_free_data_are_fitted_to_rounding(method, truth_factory):
    truth = truth_factory()
    ds = magcal.simulate(truth, n_samples=60, noise_nT=0.0, seed=2)
    res = search.search(ds.readings_nT[0], truth.total_nT, method=method, seed=0, pop_size=30, max_iter=800)
    assert res.rms_nT < 1e-6  # nT, in a 51 500 nT field
    cinv0, bias0 = _identifiable_start(truth.sensors[0])
    assert np.max(np.abs(res.cinv - cinv0)) < 1e-9
    assert np.max(np.abs(res.bias_nT - bias0)) < 1e-4


@pytest.mark.parametrize("method", ["ipso", "de"])
@pytest.mark.parametrize("preset", ["ding2024", "ding2024-fluxgate"])
def test_pooled_rms_is_at_the_floor(method, preset):
    """Over several N = 300 records the search RMS is the floor (a/sqrt 12) sqrt(1 - 9/N) within 5 %."""
    a = 5.0
    rms = [
        search.search(
            magcal.simulate(preset, noise_nT=a, seed=k).readings_nT[0], 51_500.0, method=method, seed=k
        ).rms_nT
        for k in range(6)
    ]
    pooled = np.sqrt(np.mean(np.square(rms)))
    assert pooled == pytest.approx(a / np.sqrt(12.0) * np.sqrt(1 - 9 / 300), rel=0.05)


@pytest.mark.parametrize("method", search.METHODS)
def test_same_seed_same_result_other_seed_other_path(small_problem, method):
    truth, ds, *_ = small_problem
    y = ds.readings_nT[0]
    a = search.search(y, truth.total_nT, method=method, seed=11, pop_size=20, max_iter=60)
    b = search.search(y, truth.total_nT, method=method, seed=11, pop_size=20, max_iter=60)
    c = search.search(y, truth.total_nT, method=method, seed=12, pop_size=20, max_iter=60)
    assert np.array_equal(a.history_rms_nT, b.history_rms_nT)
    assert np.array_equal(a.cinv, b.cinv) and np.array_equal(a.bias_nT, b.bias_nT)
    assert not np.array_equal(a.history_rms_nT, c.history_rms_nT)


@pytest.mark.parametrize("method", search.METHODS)
def test_progress_callback_reports_every_iteration(small_problem, method):
    truth, ds, *_ = small_problem
    calls = []
    res = search.search(
        ds.readings_nT[0],
        truth.total_nT,
        method=method,
        seed=1,
        pop_size=20,
        max_iter=50,
        progress=lambda it, best: calls.append((it, best)),
    )
    iterations = [c[0] for c in calls]
    best = np.array([c[1] for c in calls])
    assert iterations == list(range(res.n_iterations + 1))
    assert np.all(np.diff(best) <= 0)  # the best RMS never gets worse
    assert best[-1] == pytest.approx(res.rms_nT)
    assert np.array_equal(best, res.history_rms_nT)
    assert res.n_evaluations == 20 * (res.n_iterations + 1)


@pytest.mark.parametrize("method", search.METHODS)
def test_stopping_tolerance_ends_a_stalled_search(small_problem, method):
    truth, ds, *_ = small_problem
    y = ds.readings_nT[0]
    loose = search.search(y, truth.total_nT, method=method, seed=4, pop_size=20, max_iter=2000, tol=1e-3, patience=20)
    assert loose.stopped_by_tolerance and loose.n_iterations < 2000
    h = loose.history_rms_nT
    assert h[-21] - h[-1] <= 1e-3 * h[-21]


def test_bounds_come_from_the_data_and_follow_it():
    truth = ding2024_truth()
    ds = magcal.simulate(truth, n_samples=200, noise_nT=2.0, seed=1)
    y = ds.readings_nT[0]
    b = search.bounds_from_data(y, truth.total_nT)
    cinv0, bias0 = _identifiable_start(truth.sensors[0])
    assert b.contains(search.pack(cinv0, bias0))
    # shifting the readings shifts only the offset box; scaling them scales the C^-1 box inversely
    shift = np.array([3000.0, -8000.0, 500.0])
    bs = search.bounds_from_data(y + shift, truth.total_nT)
    assert np.allclose(bs.lower[:6], b.lower[:6]) and np.allclose(bs.lower[6:], b.lower[6:] + shift)
    bk = search.bounds_from_data(2.0 * y, truth.total_nT)
    assert np.allclose(bk.upper[:6], b.upper[:6] / 2.0) and np.allclose(bk.upper[6:], 2.0 * b.upper[6:])


@pytest.mark.parametrize("method", search.METHODS)
def test_far_from_preset_values_still_found(method):
    """A sensor unlike the presets (large bias, low gain, other field): the data-derived box still holds it."""
    sensor = SensorErrors(
        scale=np.array([0.8, 0.85, 0.78]), psi=0.04, phi=-0.03, theta=0.05, bias_nT=np.array([4000.0, -2500.0, 6000.0])
    )
    truth = magcal.ArrayTruth([sensor], total_nT=35_000.0, declination_deg=20.0, inclination_deg=-30.0)
    ds = magcal.simulate(truth, n_samples=80, noise_nT=1.0, noise_kind="gaussian", seed=3)
    res = search.search(ds.readings_nT[0], 35_000.0, method=method, seed=0, pop_size=30, max_iter=500)
    rms_min, u_min, b_min = _least_squares_minimum(ds.readings_nT[0], 35_000.0, sensor.Cinv, sensor.bias_nT)
    assert res.rms_nT <= rms_min * 1.001
    assert np.max(np.abs(res.bias_nT - sensor.bias_nT)) < 1.0


def test_unknown_method_and_bad_input_are_refused():
    y = np.random.default_rng(0).normal(size=(50, 3)) * 5e4
    with pytest.raises(MagcalError, match="unknown search method"):
        search.search(y, 5e4, method="ga")
    with pytest.raises(MagcalError, match="too few"):
        search.search(y[:5], 5e4, method="ipso")
    with pytest.raises(MagcalError, match="rotated"):
        search.search(np.ones((50, 3)), 5e4, method="ipso")


def test_objective_matches_eq17_for_a_population():
    rng = np.random.default_rng(0)
    y = rng.normal(size=(40, 3)) * 3e4
    params = rng.normal(size=(5, 9))
    params[:, 6:] *= 100
    f = search.ScalarObjective(y, 48_000.0)
    values = f(params)
    for p, v in zip(params, values):
        cinv, bias = search.unpack(p)
        expected = np.sqrt(np.mean((np.linalg.norm((y - bias) @ cinv.T, axis=1) - 48_000.0) ** 2))
        assert v == pytest.approx(expected, rel=1e-12)
    assert f.n_evaluations == 5


# ---- the Calibration entry point ----------------------------------------------------------------------------


def test_search_calibrate_returns_a_calibration(small_problem):
    truth, ds, rms_min, u_min, b_min = small_problem
    cal = search.search_calibrate(ds, "ipso", seed=2, **FAST).calibration
    assert isinstance(cal, magcal.calibration.calibration.Calibration)
    assert cal.reference_total_nT == truth.total_nT and not cal.reference_fitted
    rms = np.sqrt(np.mean((cal.total_field(ds)[0] - truth.total_nT) ** 2))
    assert rms <= rms_min * 1.001
    assert cal.summary["method"] == "ipso" and cal.summary["n_evaluations"] > 0


def test_search_calibrate_without_reference_uses_unit_determinant(small_problem):
    truth, ds, *_ = small_problem
    cal = search.search_calibrate(ds.replace(reference_total_nT=None), "de", seed=0, **FAST).calibration
    assert cal.reference_fitted
    assert np.linalg.det(cal.sensors[0].cinv) == pytest.approx(1.0, rel=1e-12)
    m = truth.sensors[0].total_matrix
    # C^-1 = s M^-1 (up to a rotation) maps the field F to s F; det C^-1 = 1 gives s = |det M|^(1/3)
    assert cal.reference_total_nT == pytest.approx(truth.total_nT * abs(np.linalg.det(m)) ** (1 / 3), rel=1e-5)


def test_mask_leaves_samples_out(small_problem):
    truth, ds, *_ = small_problem
    spoiled = ds.readings_nT.copy()
    spoiled[0, :10] += 5000.0  # ten wild samples
    bad = ds.replace(readings_nT=spoiled)
    mask = np.ones(ds.n_samples, bool)
    mask[:10] = False
    a = search.search_calibrate(bad, "pso", seed=1, mask=mask, **FAST).calibration
    b = search.search_calibrate(ds.subset(mask), "pso", seed=1, **FAST).calibration
    assert np.array_equal(a.sensors[0].cinv, b.sensors[0].cinv)
    assert np.array_equal(a.sensors[0].bias_nT, b.sensors[0].bias_nT)


def test_per_sample_reference_column_is_used(small_problem):
    truth, ds, *_ = small_problem
    ref = np.full(ds.n_samples, truth.total_nT)
    cal = search.search_calibrate(
        ds.replace(ref_total_nT=ref, reference_total_nT=None), "ipso", seed=0, **FAST
    ).calibration
    assert cal.reference_total_nT is None and not cal.reference_fitted
    rms = np.sqrt(np.mean((cal.total_field(ds)[0] - ref) ** 2))
    assert rms < 1.0


def test_rotation_about_one_axis_is_refused():
    truth = ding2024_truth()
    angles = np.linspace(0, 2 * np.pi, 90, endpoint=False)
    attitudes = Rotation.from_euler("z", angles[:, None])
    fields = attitudes.inv().apply(truth.field_world_nT)
    ds = magcal.Dataset(truth.sensors[0].measure(fields), reference_total_nT=truth.total_nT)
    with pytest.raises(MagcalError, match="one axis"):
        search.search_calibrate(ds, "ipso", seed=0, **FAST)


def test_array_sensors_are_searched_then_aligned():
    truth = magcal.data.simulation.chi2017_truth()
    ds = magcal.simulate(truth, n_samples=120, seed=4)
    cal = search.search_calibrate(ds, "ipso", seed=0, **FAST).calibration
    for fitted, s in zip(cal.sensors, truth.sensors):
        angle = np.degrees(np.arccos(np.clip(0.5 * (np.trace(fitted.R @ s.R.T) - 1), -1, 1)))
        assert angle < 0.05
        assert np.max(np.abs(fitted.cinv - s.Cinv)) < 5e-4


# ---- single-sensor files from an independent simulator ----------------------------------------------------


def _write_independent_file(path, seed, n, noise_nT, total_nT):
    """Simulate a sensor without magcal: random rotations by QR, a full 3x3 error matrix, offset; write CSV."""
    rng = np.random.default_rng(seed)
    m = np.eye(3) + rng.uniform(-0.08, 0.08, size=(3, 3))
    offset = rng.uniform(-400.0, 400.0, size=3)
    earth = total_nT * np.array([0.4, -0.1, 0.9]) / np.linalg.norm([0.4, -0.1, 0.9])
    rows = []
    for _ in range(n):
        q, r = np.linalg.qr(rng.normal(size=(3, 3)))
        q = q * np.sign(np.diag(r))
        reading = m @ (q @ earth) + offset + rng.normal(0.0, noise_nT, size=3)
        rows.append(reading)
    with open(path, "w", newline="") as fh:
        fh.write(f"# reference_total_nT: {total_nT}\n")
        writer = csv.writer(fh)
        writer.writerow(["s1x", "s1y", "s1z"])
        writer.writerows([[f"{v:.6f}" for v in row] for row in rows])
    return m, offset


@pytest.mark.parametrize("method", search.METHODS)
def test_single_sensor_file_from_another_simulator(tmp_path, method):
    path = tmp_path / "sensor.csv"
    m, offset = _write_independent_file(path, seed=21, n=150, noise_nT=1.5, total_nT=47_000.0)
    ds = read_csv(path)
    assert ds.n_sensors == 1 and ds.reference_total_nT == 47_000.0
    cal = search.search_calibrate(ds, method, seed=0, **FAST).calibration
    cinv0 = conventions.cinv_from_quadric(np.linalg.inv(m @ m.T))
    rms_min, *_ = _least_squares_minimum(ds.readings_nT[0], 47_000.0, cinv0, offset)
    rms = float(np.sqrt(np.mean((cal.total_field(ds)[0] - 47_000.0) ** 2)))
    assert rms <= rms_min * 1.001
    assert rms == pytest.approx(conventions.total_field_floor_nT(1.5, 150), rel=0.2)
    assert np.max(np.abs(cal.sensors[0].bias_nT - offset)) < 1.5  # CRB ~ sigma sqrt(3/N) = 0.2 nT
    assert np.max(np.abs(cal.sensors[0].cinv - cinv0)) < 1e-4
