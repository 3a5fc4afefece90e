"""The maximum-likelihood fitter against simulated truth."""

import numpy as np
import pytest

from magcal.core import conventions
from magcal.data.simulation import ArrayTruth, SensorErrors, chi2017_truth, simulate
from magcal.fitting.fitter import Problem, crude_initial_calibration, fit
from magcal.model.terms import EFFECTS as EFFECTS_BY_NAME
from magcal.model.terms import Model


def _random_truth(rng, n_sensors):
    sensors = []
    for s in range(n_sensors):
        sensors.append(
            SensorErrors(
                scale=rng.uniform(0.95, 1.05, 3),
                psi=rng.uniform(-0.03, 0.03),
                phi=rng.uniform(-0.03, 0.03),
                theta=rng.uniform(-0.03, 0.03),
                bias_nT=rng.uniform(-200, 200, 3),
                alpha=0 if s == 0 else rng.uniform(-0.05, 0.05),
                beta=0 if s == 0 else rng.uniform(-0.05, 0.05),
                gamma=0 if s == 0 else rng.uniform(-0.05, 0.05),
            )
        )
    return ArrayTruth(
        sensors,
        baseline_m=0.4,
        total_nT=rng.uniform(30_000, 60_000),
        declination_deg=rng.uniform(-20, 20),
        inclination_deg=rng.uniform(-70, 70),
    )


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("n_sensors", [1, 4])
def test_recovers_truth_within_cramer_rao(seed, n_sensors):
    rng = np.random.default_rng(100 + seed)
    truth = _random_truth(rng, n_sensors)
    sigma, n = 2.0, 600
    ds = simulate(truth, n_samples=n, noise_nT=sigma, seed=seed)
    result = fit(ds)
    for cal, true in zip(result.calibration.sensors, truth.sensors):
        # Cramer-Rao: sd(b) ~ sigma sqrt(3/N), sd(C^-1 entries) ~ (sigma/F) sqrt(6/N); allow 5 sd
        assert np.abs(cal.bias_nT - true.bias_nT).max() < 5 * sigma * np.sqrt(3 / n) * 1.5
        assert np.abs(cal.cinv - true.Cinv).max() < 5 * sigma / truth.total_nT * np.sqrt(15 / n)
        assert np.abs(cal.R - true.R).max() < 5 * sigma / truth.total_nT * np.sqrt(15 / n)
    p = 9 + (3 if n_sensors > 1 else 0)
    floor = conventions.total_field_floor_nT(sigma, n, p)
    assert result.rms_per_sensor_nT == pytest.approx(np.full(n_sensors, floor), rel=0.12)


def test_covariance_matches_scatter_over_seeds():
    """The reported standard deviations agree with the spread of estimates over independent noise."""
    truth = chi2017_truth(1)
    estimates, stds = [], []
    for seed in range(40):
        result = fit(simulate(truth, n_samples=200, noise_nT=3.0, seed=seed))
        estimates.append(result.x[:9])
        stds.append(result.std[:9])
    spread = np.std(estimates, axis=0, ddof=1)
    ratio = spread / np.mean(stds, axis=0)
    assert np.all((ratio > 0.6) & (ratio < 1.5)), ratio


def test_unknown_reference_is_fitted_with_unit_determinant_gauge():
    truth = chi2017_truth()
    ds = simulate(truth, seed=3).replace(reference_total_nT=None)
    result = fit(ds)
    assert result.reference_kind == "fitted"
    assert np.linalg.det(result.calibration.sensors[0].cinv) == pytest.approx(1.0, abs=1e-9)
    # the fitted C1^-1 is lambda * C1^-1(true) with det = 1, so F0 = lambda * F_true
    expected = truth.total_nT * np.linalg.det(truth.sensors[0].Cinv) ** (-1 / 3)
    assert result.calibration.reference_total_nT == pytest.approx(expected, rel=2e-4)
    assert result.rms_nT < 3.3


def test_per_sample_reference_column():
    truth = chi2017_truth()
    ds = simulate(truth, seed=4)
    ref = np.full(ds.n_samples, truth.total_nT)
    result = fit(ds.replace(reference_total_nT=None, ref_total_nT=ref))
    assert result.reference_kind == "column"
    assert np.abs(result.calibration.sensors[1].bias_nT - truth.sensors[1].bias_nT).max() < 2.0


def test_robust_loss_keeps_inliers_at_floor_and_names_outliers():
    truth = chi2017_truth()
    ds = simulate(truth, seed=7)
    rng = np.random.default_rng(0)
    bad = rng.choice(ds.n_samples, 10, replace=False)  # 5% gross outliers
    readings = ds.readings_nT.copy()
    readings[:, bad] += rng.normal(0, 500, (4, 10, 3))
    noisy = ds.replace(readings_nT=readings)
    plain = fit(noisy)
    robust = fit(noisy, loss="soft_l1")
    good = np.setdiff1d(np.arange(ds.n_samples), bad)
    inlier_rms = np.sqrt(np.mean(robust.residuals_all_nT[:, good] ** 2))
    assert inlier_rms < 1.1 * conventions.total_field_floor_nT(3.0, 190, 12)
    assert np.sqrt(np.mean(plain.residuals_all_nT[:, good] ** 2)) > 3 * inlier_rms
    assert set(np.flatnonzero(robust.outliers)) == set(bad)


def test_mask_excludes_samples():
    truth = chi2017_truth()
    ds = simulate(truth, seed=8)
    readings = ds.readings_nT.copy()
    readings[:, :5] += 3000.0
    mask = np.ones(ds.n_samples, bool)
    mask[:5] = False
    result = fit(ds.replace(readings_nT=readings), mask=mask)
    assert np.isnan(result.residuals_nT[:, :5]).all()
    assert np.all(np.abs(result.residuals_all_nT[:, :5]) > 1000)
    assert result.rms_nT < 3.3


@pytest.mark.parametrize("reference", [50_000.0, None])
@pytest.mark.parametrize("n_sensors", [1, 4])
def test_analytic_jacobian_matches_finite_differences_near_solution(reference, n_sensors):
    ds = simulate(chi2017_truth(), n_samples=60, seed=5).sensors(range(n_sensors)).replace(reference_total_nT=reference)
    problem = Problem(ds, Model.base_model(n_sensors), crude_initial_calibration(ds))
    x = problem.x0 + problem.x_scale * np.random.default_rng(1).normal(0, 3, problem.x0.size)
    jac = problem.jacobian(x)
    r0 = problem.residuals(x)
    numeric = np.empty_like(jac)
    for k in range(x.size):
        step = 1e-3 * problem.x_scale[k]
        xp = x.copy()
        xp[k] += step
        numeric[:, k] = (problem.residuals(xp) - r0) / step
    assert np.abs(jac - numeric).max() < 2e-2 * np.abs(numeric).max()


def test_information_criteria_prefer_true_model():
    """Dropping non-orthogonality from a sensor that has it raises AIC and BIC."""
    ds = simulate(chi2017_truth(), seed=9).sensors([0])
    full = fit(ds)
    reduced = fit(ds, model=Model(1, base=("bias", "scale")))
    assert full.bic < reduced.bic and full.aic < reduced.aic
    assert reduced.n_params == full.n_params - 3


# --- the normal-equations solver ---------------------------------------------------------------------------------


def _timeseries_problem(n_sensors, effects, reference, seed=3, n=400):
    from magcal.data.simulation import simulate_timeseries

    truth = chi2017_truth(n_sensors)
    ds = simulate_timeseries(truth, n_samples=n, noise_nT=2.0, seed=seed).replace(reference_total_nT=reference)
    model = Model.from_names(list(effects), n_sensors)
    init = crude_initial_calibration(ds)
    for e in model.effects:
        e.configure(ds, np.zeros((n_sensors, ds.n_samples)))
    return ds, model, Problem(ds, model, init)


PROBLEMS = [
    (1, (), 50_000.0),
    (1, ("temperature_bias", "nonlinearity_quadratic"), None),
    (4, (), 50_000.0),
    (4, (), None),
    (4, ("temperature_bias", "sensor_timing_skew:2", "reference_drift", "bias_drift:3"), 50_000.0),
]


@pytest.mark.parametrize("n_sensors, effects, reference", PROBLEMS)
def test_normal_equations_equal_the_dense_jacobian_products(n_sensors, effects, reference):
    _, _, problem = _timeseries_problem(n_sensors, effects, reference)
    x = problem.x0 + problem.x_scale * np.random.default_rng(2).normal(0, 3, problem.x0.size)
    jac = problem.jacobian(x)
    r_dense = problem.residuals(x)
    r, jtj, jtr = problem.normal_equations(x)
    np.testing.assert_allclose(r, r_dense, rtol=0, atol=1e-9 * np.abs(r_dense).max())
    np.testing.assert_allclose(jtj, jac.T @ jac, rtol=1e-9, atol=1e-9 * np.abs(jac.T @ jac).max())
    np.testing.assert_allclose(jtr, jac.T @ r_dense, rtol=1e-8, atol=1e-9 * np.abs(jac.T @ r_dense).max())


@pytest.mark.parametrize("n_sensors, effects, reference", PROBLEMS)
def test_levenberg_marquardt_reaches_the_minpack_minimum(n_sensors, effects, reference):
    """Our normal-equations solver and MINPACK's QR-based one find the same minimum from the same start."""
    from scipy.optimize import least_squares

    from magcal.fitting.fitter import _levenberg_marquardt

    _, _, problem = _timeseries_problem(n_sensors, effects, reference)
    ours = _levenberg_marquardt(problem, problem.x0)
    ref = least_squares(
        problem.residuals,
        problem.x0,
        jac=problem.jacobian,
        x_scale=problem.x_scale,
        method="lm",
        xtol=1e-12,
        ftol=1e-12,
        gtol=1e-12,
    )
    cost_ours, cost_ref = ours.r @ ours.r, ref.fun @ ref.fun
    assert cost_ours <= cost_ref * (1 + 1e-8)
    # parameters agree to a small fraction of their standard deviations
    std = np.sqrt(np.diag(np.linalg.pinv(ours.jtj)) * cost_ours / (ours.r.size - ours.x.size))
    assert np.max(np.abs(ours.x - ref.x) / std) < 1e-3
    assert "converged" in ours.message or "zero" in ours.message


def test_levenberg_marquardt_converges_from_a_crude_start_on_an_array():
    """Far from the solution (crude sphere start, 4 sensors) the damping carries it to the truth."""
    truth = chi2017_truth()
    ds = simulate(truth, n_samples=300, seed=11)
    result = fit(ds)
    floor = conventions.total_field_floor_nT(ds.noise_nT, ds.n_samples, 9)
    assert result.rms_nT < 1.1 * floor
    for s, sensor in enumerate(truth.sensors):
        np.testing.assert_allclose(result.calibration.sensors[s].bias_nT, sensor.bias_nT, atol=3.0)


@pytest.mark.parametrize("n_sensors, effects, reference", PROBLEMS[::2])
def test_weighted_normal_equations_equal_the_dense_products(n_sensors, effects, reference):
    _, _, problem = _timeseries_problem(n_sensors, effects, reference)
    rng = np.random.default_rng(4)
    x = problem.x0 + problem.x_scale * rng.normal(0, 3, problem.x0.size)
    weights = rng.uniform(0.1, 1.0, problem.n_residuals)
    jac, r_dense = problem.jacobian(x), problem.residuals(x)
    _, jtj, jtr = problem.normal_equations(x, weights=weights)
    expected_jtj, expected_jtr = jac.T @ (weights[:, None] * jac), jac.T @ (weights * r_dense)
    np.testing.assert_allclose(jtj, expected_jtj, rtol=1e-9, atol=1e-9 * np.abs(expected_jtj).max())
    np.testing.assert_allclose(jtr, expected_jtr, rtol=1e-8, atol=1e-9 * np.abs(expected_jtr).max())


@pytest.mark.parametrize("loss", ["soft_l1", "huber", "cauchy"])
@pytest.mark.parametrize("n_sensors", [1, 4])
def test_robust_losses_reach_scipys_minimum(loss, n_sensors):
    """With gross outliers in the data, our reweighted solver and scipy's robust trust-region agree."""
    from scipy.optimize import least_squares

    from magcal.fitting.fitter import LOSSES, _levenberg_marquardt

    truth = chi2017_truth()
    ds = simulate(truth, n_samples=150, seed=21).sensors(range(n_sensors))
    readings = ds.readings_nT.copy()
    readings[:, :8] += np.random.default_rng(3).normal(0, 400.0, (n_sensors, 8, 3))
    ds = ds.replace(readings_nT=readings)
    problem = Problem(ds, Model.base_model(n_sensors), crude_initial_calibration(ds))
    f = 9.0
    ours = _levenberg_marquardt(problem, problem.x0, loss=loss, f_scale=f)
    ref = least_squares(
        problem.residuals,
        problem.x0,
        jac=problem.jacobian,
        x_scale=problem.x_scale,
        loss=loss,
        f_scale=f,
        method="trf",
        xtol=1e-12,
        ftol=1e-12,
        gtol=1e-12,
    )
    rho = LOSSES[loss][0]

    def cost(r):
        return 0.5 * f**2 * np.sum(rho(r**2 / f**2))

    assert cost(ours.r) <= cost(ref.fun) * (1 + 1e-7)
    std = np.sqrt(np.diag(np.linalg.pinv(ours.jtj)) * 9.0)
    assert np.max(np.abs(ours.x - ref.x) / std) < 1e-2


def test_unknown_loss_is_refused():
    from magcal.core.errors import CalibrationError

    with pytest.raises(CalibrationError, match="unknown loss"):
        fit(simulate(chi2017_truth(), n_samples=60, seed=1).sensors([0]), loss="l1")


@pytest.mark.parametrize("seed", [2, 3])
def test_hysteresis_shape_is_refined_within_fit(seed):
    """An effect with a data-derived shape (the hysteresis play width) gets its second pass inside fit()."""
    from magcal.data.simulation import simulate_timeseries
    from magcal.model import perturbations

    truth = chi2017_truth(1)
    ds = simulate_timeseries(
        truth, n_samples=1500, noise_nT=3.0, seed=seed, perturbations=[perturbations.parse_hidden("hysteresis=5", 1)]
    )
    base = fit(ds)
    result = fit(ds, Model.from_names(["hysteresis"], 1), init=base.calibration)
    floor = conventions.total_field_floor_nT(3.0, ds.n_samples, 12)
    assert base.rms_nT > 1.2 * floor  # the loop is visible above the noise
    assert result.rms_nT < 1.01 * floor
    assert result.calibration.model.effects[0].shape_half_width_nT is not None


@pytest.mark.parametrize("n_sensors, effects, reference", PROBLEMS[1:3])
def test_normal_equations_return_the_total_field_part(n_sensors, effects, reference):
    _, _, problem = _timeseries_problem(n_sensors, effects, reference)
    jac, r = problem.jacobian(problem.x0), problem.residuals(problem.x0)
    rows = problem.total_field_rows
    *_, (jtj_tf, jtr_tf) = problem.normal_equations(problem.x0, with_total_field=True)
    np.testing.assert_allclose(jtj_tf, jac[rows].T @ jac[rows], rtol=1e-10, atol=1e-12 * np.abs(jtj_tf).max())
    np.testing.assert_allclose(jtr_tf, jac[rows].T @ r[rows], rtol=1e-9, atol=1e-12 * np.abs(jtr_tf).max())


@pytest.mark.parametrize("seed", [104, 7])
def test_bias_step_time_is_rescanned_without_the_other_effects(seed):
    """A slow temperature change of scale moves the raw change point; the refine pass finds the true step."""
    from magcal.data.simulation import simulate_timeseries

    hidden = [
        EFFECTS_BY_NAME["temperature_scale"]().perturbation(30.0, None),
        EFFECTS_BY_NAME["bias_step"](sensor=3).perturbation(10.0, 3),
    ]
    ds = simulate_timeseries(chi2017_truth(), n_samples=1500, noise_nT=3.0, seed=seed, perturbations=hidden)
    true_time = ds.time_s[0] + 0.6 * (ds.time_s[-1] - ds.time_s[0])
    base = fit(ds)
    model = Model.from_names(["temperature_scale", "bias_step:4"], 4)
    result = fit(ds, model, init=base.calibration)
    step = result.calibration.model.effects[1]
    assert abs(step.step_time_s[3] - true_time) < 0.25  # within a few samples at 10 Hz
    floor = conventions.total_field_floor_nT(3.0, ds.n_samples, 9 + 3 + 3 / 4)
    assert result.rms_nT < 1.02 * floor


@pytest.mark.parametrize("effect", ["temperature_bias", "bias_step"])
def test_fit_leaves_the_callers_model_unchanged(effect):
    """One Model reused on two records: the first calibration must not move when the second is fitted."""
    from magcal.data.simulation import simulate_timeseries

    truth = chi2017_truth(1)
    hidden = [EFFECTS_BY_NAME[effect]().perturbation(20.0, None)]
    first = simulate_timeseries(truth, n_samples=800, noise_nT=3.0, seed=11, perturbations=hidden)
    second = simulate_timeseries(
        truth, n_samples=800, noise_nT=3.0, seed=12, perturbations=hidden, temperature_C=(35.0, 6.0)
    )
    second.time_s = second.time_s + 500.0  # another recording: other times, another temperature
    model = Model.from_names([effect], 1)
    states_before = [e.state() for e in model.effects]
    cal_first = fit(first, model).calibration
    corrected_before = cal_first.correct(first).copy()
    fit(second, model)
    assert [e.state() for e in model.effects] == states_before
    np.testing.assert_array_equal(cal_first.correct(first), corrected_before)


def test_with_effect_copies_the_added_effect():

    effect = EFFECTS_BY_NAME["temperature_bias"]()
    m1 = Model.base_model(1).with_effect(effect)
    assert m1.effects[0] is not effect


def test_a_fit_that_stops_early_says_so():
    from magcal.core.errors import ConvergenceWarning

    ds = simulate(chi2017_truth(), n_samples=200, seed=3).sensors([0])
    with pytest.warns(ConvergenceWarning, match="did not converge"):
        result = fit(ds, max_nfev=2)
    assert not result.success and result.status == 0
    assert "maximum number of evaluations" in result.message
    assert result.summary()["success"] is False


def test_a_converged_fit_reports_success():
    import warnings

    from magcal.core.errors import ConvergenceWarning

    ds = simulate(chi2017_truth(), n_samples=200, seed=3)
    with warnings.catch_warnings():
        warnings.simplefilter("error", ConvergenceWarning)
        result = fit(ds)
    assert result.success and result.status in (1, 2, 3)
    assert result.summary()["message"].startswith(("converged", "gradient"))


@pytest.fixture
def small_blocks(monkeypatch):
    """Row blocks of a few dozen samples, so that a 400-sample problem is accumulated in many blocks."""
    import importlib

    fit_module = importlib.import_module("magcal.fitting.fitter")
    monkeypatch.setattr(fit_module, "BLOCK_ROWS", 97)
    monkeypatch.setattr(fit_module, "MIN_BLOCK_ROWS", 13)
    monkeypatch.setattr(fit_module, "ROW_BLOCK_ELEMENTS", 600)
    return fit_module


@pytest.mark.parametrize("weighted", [False, True])
@pytest.mark.parametrize("n_sensors, effects, reference", PROBLEMS)
def test_normal_equations_in_row_blocks_equal_the_dense_products(small_blocks, n_sensors, effects, reference, weighted):
    """Accumulated over many row blocks (and, for base terms, evaluated block by block) the normal equations are
    the dense Jacobian's."""
    _, model, problem = _timeseries_problem(n_sensors, effects, reference)
    rng = np.random.default_rng(5)
    x = problem.x0 + problem.x_scale * rng.normal(0, 3, problem.x0.size)
    weights = rng.uniform(0.1, 1.0, problem.n_residuals) if weighted else None
    if not model.effects:
        assert problem._sample_blocks() is not None and len(problem._sample_blocks()) > 3
    jac, r_dense = problem.jacobian(x), problem.residuals(x)
    w = np.ones(r_dense.size) if weights is None else weights
    r, jtj, jtr, (jtj_tf, jtr_tf) = problem.normal_equations(x, weights=weights, with_total_field=True)
    expected_jtj, expected_jtr = jac.T @ (w[:, None] * jac), jac.T @ (w * r_dense)
    np.testing.assert_allclose(r, r_dense, rtol=0, atol=1e-9 * np.abs(r_dense).max())
    np.testing.assert_allclose(jtj, expected_jtj, rtol=1e-9, atol=1e-9 * np.abs(expected_jtj).max())
    np.testing.assert_allclose(jtr, expected_jtr, rtol=1e-8, atol=1e-9 * np.abs(expected_jtr).max())
    tf = problem.total_field_rows
    tf_jtj = jac[tf].T @ (w[tf, None] * jac[tf])
    np.testing.assert_allclose(jtj_tf, tf_jtj, rtol=1e-9, atol=1e-9 * np.abs(tf_jtj).max())


@pytest.mark.parametrize("n_sensors", [1, 4])
def test_derivative_projection_is_the_dense_derivative_on_a_direction(n_sensors):
    _, _, problem = _timeseries_problem(n_sensors, ("temperature_bias", "nonlinearity_quadratic"), None)
    fields, derivs = problem.field_derivatives(problem.x0)
    w = np.random.default_rng(6).normal(size=(problem.n_samples, 3))
    for d in derivs:
        np.testing.assert_allclose(d.project(w), np.einsum("ni,nik->nk", w, d.dense()), rtol=1e-12, atol=1e-9)
        rows = slice(31, 77)
        np.testing.assert_allclose(d.project(w[rows], rows=rows), d.project(w)[rows], rtol=1e-14, atol=0)


@pytest.mark.parametrize("name", [n for n, cls in EFFECTS_BY_NAME.items() if cls.stage in ("raw", "array")])
def test_projection_of_a_single_axis_basis_is_the_general_contraction(monkeypatch, name):
    """Bases whose parameters each move one axis (most raw-stage terms) are projected by products; every
    catalogue term's projection equals the general contraction's, and the shortcut is taken where it applies."""
    from magcal.fitting.fitter import _Derivative

    n_sensors = max(2, EFFECTS_BY_NAME[name].min_sensors) if name != "site_gradient" else 4
    ds, model, problem = _timeseries_problem(n_sensors, (name,), 50_000.0)
    if EFFECTS_BY_NAME[name]().missing_channels(ds):
        pytest.skip(f"{name} needs channels the simulated record lacks")
    w = np.random.default_rng(8).normal(size=(problem.n_samples, 3))
    rows = slice(40, 333)
    _, derivs = problem.field_derivatives(problem.x0)
    fast = [(d.project(w), d.project(w[rows], rows=rows)) for d in derivs]
    singles = [s for d in derivs for s in d._one_axis[0] + d._one_axis[1]]
    monkeypatch.setattr(_Derivative, "_single_axis", staticmethod(lambda basis: None))
    _, derivs = problem.field_derivatives(problem.x0)
    for (whole, part), d in zip(fast, derivs):
        np.testing.assert_allclose(whole, d.project(w), rtol=1e-13, atol=1e-12)
        np.testing.assert_allclose(part, d.project(w[rows], rows=rows), rtol=1e-13, atol=1e-12)
    if name in ("temperature_bias", "bias_drift", "nonlinearity_cubic", "bias_step"):
        assert any(s is not None for s in singles)


@pytest.mark.parametrize("n_sensors", [1, 4])
def test_a_large_record_converged_on_a_subsample_first_reaches_the_same_minimum(monkeypatch, n_sensors):
    """The warm-up on an even subsample only changes where the fit of every sample starts, not where it ends."""
    import importlib

    fit_module = importlib.import_module("magcal.fitting.fitter")
    ds = simulate(chi2017_truth(n_sensors), n_samples=1500, noise_nT=3.0, seed=8)
    init = crude_initial_calibration(ds)
    monkeypatch.setattr(fit_module, "WARMUP_SAMPLES", 10**9)
    direct = fit(ds, init=init)
    monkeypatch.setattr(fit_module, "WARMUP_SAMPLES", 200)
    warmed = fit(ds, init=init)
    assert warmed.rss <= direct.rss * (1 + 1e-9)
    assert np.max(np.abs(warmed.x - direct.x) / direct.std) < 1e-2
    assert warmed.success


def test_a_cost_tolerance_in_noise_variances_stops_within_a_fraction_of_a_standard_error():
    """``cost_tolerance`` (the diagnosis's comparison fits) stops earlier but still at the minimum to within
    sqrt(2 tolerance) standard errors, with the same residual sum of squares to the tolerance."""
    ds = simulate(chi2017_truth(4), n_samples=800, noise_nT=3.0, seed=12)
    init = crude_initial_calibration(ds)
    strict = fit(ds, init=init)
    loose = fit(ds, init=init, cost_tolerance=0.01)
    assert loose.nfev < strict.nfev  # from a crude start the last, tiny step is not taken
    sigma2 = strict.rss / (strict.n_residuals - strict.n_params)
    assert 0.0 <= 0.5 * (loose.rss - strict.rss) <= 0.01 * sigma2 * 1.5
    assert np.max(np.abs(loose.x - strict.x) / strict.std) < np.sqrt(2 * 0.01) * 1.5


@pytest.mark.parametrize("spec", ["bias_step:4", "bias_step"])
def test_bias_step_refinement_from_shifted_fields_equals_whole_evaluations(spec):
    """The step's refinement moves each sensor's corrected field by R C^-1 db instead of evaluating every trial
    whole, and costs the move from that sensor's samples: the costs, and so the refined times, are those of
    whole evaluations."""
    from magcal.data.simulation import simulate_timeseries
    from magcal.fitting.fitter import RefineContext

    ds = simulate_timeseries(
        chi2017_truth(),
        n_samples=900,
        noise_nT=3.0,
        seed=2,
        perturbations=[EFFECTS_BY_NAME["bias_step"](sensor=3).perturbation(10.0, 3)],
    )
    result = fit(ds, Model.from_names([spec], 4), init=fit(ds).calibration)
    step = result.model.effects[0]
    context = RefineContext(result.problem, result.x)

    class WholeOnly:  # the same context without the shortcut
        dataset = context.dataset
        cost_per_sample = staticmethod(context.cost_per_sample)

    times = list(step.step_time_s)
    fields = context.fields()
    for s, te in enumerate(times):
        if te is None:
            continue
        on = context.cost_per_sample(step, {"step_time_s": times[:s] + [ds.time_s[0] - 1.0] + times[s + 1 :]})
        label = f"bias_step:{s + 1}" if step.per_sensor else "bias_step"
        cal = context.sensors()[s]
        trial = fields.copy()
        trial[s] += (ds.time_s >= te)[:, None] * (
            cal.R @ cal.cinv @ context.values()[label]
        ) - cal.R @ cal.cinv @ context.values()[label]
        np.testing.assert_allclose(context.cost_of_fields(trial), on, rtol=1e-9, atol=1e-9)
        # the same trial from sensor s's samples alone (the consistency basis held at the fitted mean)
        moved_alone = context.cost_with_sensor_moved(s, trial[s] - fields[s])
        np.testing.assert_allclose(moved_alone, on, rtol=5e-4)
    saved = step.state()
    step.refine(result.calibration.effect_values, context)
    moved = list(step.step_time_s)
    step.set_state(saved)
    step.refine(result.calibration.effect_values, WholeOnly())
    assert moved == step.step_time_s


@pytest.mark.parametrize("n_sensors, effects", [(1, []), (4, []), (1, ["temperature_bias"]), (4, ["bias_drift"])])
def test_one_step_from_the_whole_record_reaches_the_training_minimum(n_sensors, effects):
    """``max_steps=1`` from the whole record's fit (the held-out fits of the validation, with their tolerance of
    0.01 noise variances) is the one-step estimator: one pass, status 4, and the training samples' converged
    minimum to a small fraction of a standard error, with the same residual sum of squares to a thousandth of a
    noise variance."""
    from magcal.data.simulation import simulate_timeseries

    hidden = [EFFECTS_BY_NAME[name]().perturbation(EFFECTS_BY_NAME[name].default_magnitude) for name in effects]
    ds = simulate_timeseries(chi2017_truth(n_sensors), n_samples=1500, noise_nT=3.0, seed=21, perturbations=hidden)
    model = Model.from_names(effects, n_sensors)
    whole = fit(ds, model)
    train = (np.arange(ds.n_samples) // 150) % 2 == 0  # alternate blocks, as the validation holds out
    converged = fit(ds, model, init=whole.calibration, mask=train)
    one = fit(ds, model, init=whole.calibration, mask=train, max_steps=1, cost_tolerance=0.01)  # as validate
    assert one.status == 4 and one.success and one.nfev == 2  # the start's equations and the step's residuals
    assert np.max(np.abs(one.x - converged.x) / converged.std) < 0.02
    sigma2 = converged.rss / (converged.n_residuals - converged.n_params)
    assert abs(one.rss - converged.rss) <= 1e-3 * sigma2


@pytest.mark.parametrize("n_sensors", [1, 4])
def test_one_step_from_afar_goes_on_to_the_minimum(n_sensors):
    """``max_steps=1`` stops only when the step lowered the cost as the quadratic model predicted; from a start
    far from the minimum (a crude sphere fit) it does not, and the fit goes on to the same minimum as without the
    limit."""
    ds = simulate(chi2017_truth(n_sensors), n_samples=600, noise_nT=3.0, seed=4)
    init = crude_initial_calibration(ds)
    full = fit(ds, init=init)
    limited = fit(ds, init=init, max_steps=1)
    assert limited.status in (1, 2, 3) and limited.nfev > 2
    sigma2 = full.rss / (full.n_residuals - full.n_params)
    assert abs(limited.rss - full.rss) <= 1e-3 * sigma2


@pytest.mark.parametrize("hidden, effect", [("temperature_bias", "temperature_bias"), ("bias_drift", "bias_drift")])
def test_a_warm_refit_after_add_or_exclude_reaches_the_cold_minimum(hidden, effect):
    """The workbench's Add (the model grown by one term, warm from the base calibration) and Exclude range (a tenth
    of the record left out, warm from the grown fit) land on the minimum a cold fit of the same model and samples
    (the two seed steps, then ML) reaches: the same residual sum of squares, every parameter within 0.01 of its
    standard error; and the added term takes up the hidden one (RMS at the noise floor). 4 x 6000 samples: large
    enough for the fits to run BLAS on one thread (ONE_BLAS_THREAD_READINGS)."""
    from scipy.spatial.transform import Rotation

    from magcal.data.simulation import simulate_timeseries
    from magcal.fitting import fitter, pipeline

    n, noise = 6000, 2.0
    assert 4 * n * 0.9 >= fitter.ONE_BLAS_THREAD_READINGS
    perturbation = EFFECTS_BY_NAME[hidden]().perturbation(40.0, None)
    ds = simulate_timeseries(chi2017_truth(), n_samples=n, noise_nT=noise, seed=21, perturbations=[perturbation])
    model = Model.from_names([effect], 4)
    kept = np.ones(n, bool)
    kept[int(0.4 * n) : int(0.5 * n)] = False
    base = fit(ds)
    floor = conventions.total_field_floor_nT(noise, n, 9 + 3 + 3 / 4)
    assert base.rms_nT > 1.1 * floor  # the hidden term shows without its effect
    warm_add = fit(ds, model, init=base.calibration)
    warm_exclude = fit(ds, model, init=warm_add.calibration, mask=kept)
    for warm, mask in ((warm_add, None), (warm_exclude, kept)):
        cold = pipeline.calibrate(ds, effects=[effect], mask=mask).fit
        assert warm.success and cold.success
        assert warm.rss == pytest.approx(cold.rss, rel=1e-9)
        assert warm.rms_nT < 1.03 * floor
        problem = warm.problem
        rotation = np.zeros(warm.x.size, bool)
        rotation[[i for i, name in enumerate(warm.param_names) if "_rotation_" in name]] = True
        # C^-1, biases and the effect's parameters are absolute; the rotations are relative to each fit's start
        assert np.max(np.abs(warm.x - cold.x)[~rotation] / warm.std[~rotation]) < 1e-2
        pairs = zip(warm.calibration.sensors, cold.calibration.sensors)
        angles_rad = [Rotation.from_matrix(a.R @ b.R.T).magnitude() for a, b in pairs]  # accurate when small
        assert max(angles_rad) < 1e-2 * warm.std[rotation].min()
        assert problem.n_samples == int((mask if mask is not None else np.ones(n, bool)).sum())
