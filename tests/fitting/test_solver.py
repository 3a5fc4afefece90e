"""magcal.fitting.solver (the weighted fits' core), magcal.fitting.truth and the one held-out split of the mode fits,
against simulated truth."""

import numpy as np
import pytest

from magcal.checks.reference import resolve_vector_reference
from magcal.core.errors import CalibrationError
from magcal.data.board import simulate_board
from magcal.data.vehicle import simulate_vehicle, vehicle_truth
from magcal.fitting import solver
from magcal.fitting.gravity import validate_gravity
from magcal.fitting.truth import true_calibration
from magcal.fitting.validation import MIN_BLOCK_S, held_out_blocks
from magcal.fitting.vector import validate_vector


def _two_groups(sigma_a, sigma_b, n=4000, seed=0):
    """A straight line seen twice, with white noise ``sigma_a`` on one set of samples and ``sigma_b`` on the other:
    ``(design_a, y_a, design_b, y_b, truth)``."""
    rng = np.random.default_rng(seed)
    truth = np.array([2.0, -0.5])
    t_a, t_b = rng.uniform(-1, 1, n), rng.uniform(-1, 1, n)
    d_a, d_b = np.column_stack([np.ones(n), t_a]), np.column_stack([np.ones(n), t_b])
    return d_a, d_a @ truth + rng.normal(0, sigma_a, n), d_b, d_b @ truth + rng.normal(0, sigma_b, n), truth


def _line_fit(sigma_a, sigma_b, groups, **options):
    d_a, y_a, d_b, y_b, truth = _two_groups(sigma_a, sigma_b)

    def parts(x):
        return [d_a @ x - y_a, d_b @ x - y_b]

    def solve(x, sigmas):
        sol = solver.weighted_least_squares(
            lambda v: np.concatenate([(d_a @ v - y_a) / sigmas[0], (d_b @ v - y_b) / sigmas[1]]), x, np.ones(2)
        )
        return sol.x, sol

    return solver.reweighted_fit(solve, parts, groups, np.zeros(2), **options), truth


@pytest.mark.parametrize("sigma_a, sigma_b", [(1.0, 10.0), (3.0, 3.0), (0.2, 50.0)])
def test_reweighting_finds_each_groups_noise(sigma_a, sigma_b):
    found, truth = _line_fit(sigma_a, sigma_b, [solver.NoiseGroup(1e-6), solver.NoiseGroup(1e-6)], rounds=5)
    assert found.sigmas[0] == pytest.approx(sigma_a, rel=0.05)
    assert found.sigmas[1] == pytest.approx(sigma_b, rel=0.05)
    assert np.allclose(found.x, truth, atol=5 * sigma_a / np.sqrt(4000))  # carried by the quieter group
    assert found.rounds < 5  # settled before the rounds ran out


def test_a_given_noise_is_kept_and_a_floor_holds():
    found, _ = _line_fit(1.0, 10.0, [solver.NoiseGroup(1e-6, given=2.5), solver.NoiseGroup(1e-6)], rounds=3)
    assert found.sigmas[0] == 2.5 and found.sigmas[1] == pytest.approx(10.0, rel=0.05)
    assert solver.NoiseGroup(0.7).sigma(np.zeros(50)) == 0.7  # identical samples: the floor
    assert solver.NoiseGroup(0.7).sigma(None, current=4.0) == 4.0  # a part not fitted keeps its noise


@pytest.mark.parametrize(
    "rounds, most, asked, expected",
    [(2, 5, 0, 2), (2, 5, 1, 2), (2, 5, 2, 3), (2, 5, 3, 4), (2, 3, 9, 3), (1, 1, 9, 1)],
)
def test_again_asks_for_more_rounds_within_the_most(rounds, most, asked, expected):
    """A model whose constants moved (``again`` True) is solved once more, up to ``most_rounds``; once it no longer
    asks, the loop stops after ``rounds`` solves in all (the noises never settle at tolerance 0)."""
    d_a, y_a, _, _, _ = _two_groups(1.0, 1.0)
    calls = []

    def solve(x, sigmas):
        calls.append(1)
        return np.linalg.lstsq(d_a, y_a, rcond=None)[0], None

    found = solver.reweighted_fit(
        solve,
        lambda x: [d_a @ x - y_a],
        [solver.NoiseGroup(1e-6)],
        np.zeros(2),
        rounds=rounds,
        most_rounds=most,
        again=lambda rnd, x: rnd < asked,
        tolerance=0.0,
    )
    assert len(calls) == found.rounds == expected


@pytest.mark.parametrize("rho", [0.0, 0.5, 0.9])
def test_the_covariance_is_widened_for_correlated_residuals(rho):
    """Residuals of a first-order autoregressive sequence: the mean's standard deviation is sqrt((1 + rho) / (1 -
    rho)) times the white one's, and the widening says so."""
    rng = np.random.default_rng(3)
    n = 20000
    e = rng.normal(0, 1, n)
    z = np.empty(n)
    z[0] = e[0]
    for i in range(1, n):
        z[i] = rho * z[i - 1] + np.sqrt(1 - rho**2) * e[i]
    jac = np.ones((n, 1))  # the mean of the residuals: one parameter
    cov = solver.correlated_covariance(jac, z - z.mean(), 1, [z], n)
    assert cov.lag1 == pytest.approx(rho, abs=0.02)
    assert cov.widening == pytest.approx(np.sqrt((1 + rho) / (1 - rho)), rel=0.05)
    assert cov.matrix[0, 0] == pytest.approx(cov.s2 / n * cov.widening**2)
    assert cov.s2 == pytest.approx(1.0, rel=0.05)


def test_a_singular_fit_has_no_covariance_and_outliers_are_beyond_five_sigma():
    cov = solver.correlated_covariance(np.zeros((10, 2)), np.ones(10), 2, [np.ones(10)], 10)
    assert cov.matrix is None and cov.jtj_inv is None
    r = np.array([[0.0, 1.0], [0.0, 5.1], [4.9, 0.0], [-6.0, 0.0]])
    assert solver.beyond(r, 1.0).tolist() == [False, True, False, True]
    assert solver.beyond(r[:, 0], 1.0).tolist() == [False, False, False, True]


def test_a_mirrored_matrix_is_refused_with_what_to_do():
    with pytest.raises(CalibrationError, match="sensor 2: the fitted matrix mirrors an axis.*negate that column"):
        solver.split_fitted(np.diag([1.0, 1.0, -1.0]), 1)


@pytest.mark.parametrize("kind", ["vehicle", "board"])
def test_the_true_calibration_reproduces_the_simulated_field(kind):
    """The calibration of the truth corrects the simulated readings to the field within the sensor's noise."""
    if kind == "vehicle":
        truth = vehicle_truth(seed=5, current=True)
        ds, tr = simulate_vehicle(truth, seed=5, n=1500)
        cal = true_calibration(tr)
        assert cal.mode == "vector" and cal.model is not None and cal.model.effect_labels == ["current_field"]
        noise = tr.noise_nT
    else:
        ds, tr, _ = simulate_board(seed=5)
        cal = true_calibration(tr)
        assert cal.mode == "gravity" and cal.accelerometer is not None
        noise = tr.mag_noise_nT
    total = cal.total_field(ds)
    total = total if total.ndim == 1 else total[0]
    field_nT = float(np.linalg.norm(tr.field_ned_nT))
    assert cal.reference_total_nT == pytest.approx(field_nT)
    assert np.sqrt(np.mean((total - field_nT) ** 2)) < 1.5 * noise


@pytest.mark.parametrize("n_blocks", [None, 5, 3])
def test_the_mode_checks_split_as_holdout_masks_does(n_blocks):
    """Blocks of equal duration in time order, the first and the last fitted, at least MIN_BLOCK_S long by default;
    the vector and the gravity checks both use that split."""
    ds, _ = simulate_vehicle(vehicle_truth(seed=2), seed=2, n=2000)
    rng = np.random.default_rng(0)
    ds = ds.replace(time_s=np.sort(rng.uniform(0.0, 200.0, ds.n_samples)))  # uneven sampling
    train, test, blocks = held_out_blocks(ds, n_blocks)
    assert blocks % 2 == 1 and not np.any(train & test) and np.all(train | test)
    assert train[0] and train[-1]
    edges = np.flatnonzero(np.diff(train.astype(int))) + 1  # where the blocks change, in time
    durations = np.diff(np.r_[ds.time_s[0], ds.time_s[edges], ds.time_s[-1]])
    assert len(durations) == blocks
    assert np.allclose(durations, durations.mean(), rtol=0.1)
    if n_blocks is None:
        assert durations.min() >= 0.95 * MIN_BLOCK_S
    v = validate_vector(ds, resolve_vector_reference(ds), terms=[], n_blocks=n_blocks)
    assert v.n_blocks == blocks and np.array_equal(v.train, train)


def test_the_gravity_check_splits_the_same_way_and_a_short_record_is_refused():
    ds, _, _ = simulate_board(seed=6, n_poses=50)
    train, _, blocks = held_out_blocks(ds)
    v = validate_gravity(ds)
    assert v.n_blocks == blocks and np.array_equal(v.train, train)
    short = ds.subset(np.arange(100))
    with pytest.raises(CalibrationError, match="too short to hold samples out"):
        validate_gravity(short)
