"""magcal.fitting.platform: level-table alignment of every sensor into the platform frame (patent S5-S8)."""

import dataclasses
import warnings

import numpy as np
import pytest

from magcal.calibration.calibration import Calibration, SensorCalibration
from magcal.core.errors import DataWarning
from magcal.data import simulation as sim
from magcal.data.dataset import DatasetError
from magcal.fitting import platform as pf

SIGMA = 3.0  # the seed's noise (Chi et al. 2017)


@pytest.fixture(scope="module")
def truth():
    return pf.platform_truth()


def true_calibration(truth, frame="sensor1"):
    """The exact intrinsic calibration (C^-1, b) with R = identity."""
    return Calibration(
        [SensorCalibration(s.Cinv, s.bias_nT) for s in truth.sensors],
        reference_total_nT=truth.total_nT,
        baseline_m=truth.baseline_m,
        frame=frame,
    )


def true_R(truth):
    return np.array([s.R for s in truth.sensors])


def true_angles(truth):
    return np.array([[s.alpha, s.beta, s.gamma] for s in truth.sensors])


def test_platform_truth_misaligns_every_sensor(truth):
    assert all(np.linalg.norm([s.alpha, s.beta, s.gamma]) > 0.01 for s in truth.sensors)


def test_simulated_procedure_has_a_constant_vertical_component(truth):
    ds = pf.simulate_level_table(truth, n_per_group=50, noise_nT=0.0, seed=1)
    from scipy.spatial.transform import Rotation

    q = ds.attitude_wxyz
    att = Rotation.from_quat(np.column_stack([q[:, 1:], q[:, :1]]))
    b_platform = att.inv().apply(truth.field_world_nT)
    for g, axis in (("x_up", 0), ("y_up", 1), ("z_up", 2)):
        m = ds.group == g
        up_in_platform = att[m].inv().apply([0.0, 0.0, -1.0])
        np.testing.assert_allclose(up_in_platform[:, axis], 1.0, atol=1e-12)  # that axis points up
        np.testing.assert_allclose(b_platform[m, axis], -truth.field_world_nT[2], atol=1e-9)  # U = -Z


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_angles_recovered_within_the_cramer_rao_bound(truth, seed):
    ds = pf.simulate_level_table(truth, n_per_group=100, noise_nT=SIGMA, seed=seed)
    new, res = pf.align(ds, true_calibration(truth))
    z = (res.angles_rad - true_angles(truth)) / res.angles_std_rad
    assert np.max(np.abs(z)) < 4.5, z
    # the bound itself: ~ sigma / (H sqrt(N_g)) with H the horizontal field, about 1e-5 rad here
    h = truth.total_nT * np.cos(np.radians(truth.inclination_deg))
    np.testing.assert_allclose(res.angles_std_rad, SIGMA / (h * np.sqrt(100)), rtol=0.35)
    np.testing.assert_allclose(res.residual_rms_nT, SIGMA, rtol=0.25)
    np.testing.assert_allclose(res.axis_angles_deg, 90.0, atol=0.01)
    assert new.frame == "platform"
    for c, R in zip(new.sensors, res.R):
        np.testing.assert_array_equal(c.R, R)


def test_the_bound_is_the_real_spread(truth):
    """Monte Carlo: the estimator is efficient (empirical spread ~ the reported Cramer-Rao sd)."""
    one = dataclasses.replace(truth, sensors=truth.sensors[:1])
    cal = Calibration([SensorCalibration(one.sensors[0].Cinv, one.sensors[0].bias_nT)], reference_total_nT=50_000.0)
    errs, stds = [], []
    for seed in range(40):
        ds = pf.simulate_level_table(one, n_per_group=60, noise_nT=SIGMA, seed=100 + seed)
        _, res = pf.align(ds, cal, noise_nT=SIGMA)
        errs.append(pf.rotation_error_vector_rad(res.R, true_R(one))[0])
        stds.append(res.rotation_std_rad[0])
    ratio = np.std(errs, axis=0) / np.mean(stds, axis=0)
    assert np.all((ratio > 0.7) & (ratio < 1.35)), ratio
    assert np.all(np.abs(np.mean(errs, axis=0)) < 4 * np.mean(stds, axis=0) / np.sqrt(40))  # unbiased


def test_full_procedure_with_a_scalar_calibration_first(truth):
    """S3-S4 (scalar calibration on free rotations) then S7-S8, with the intrinsic uncertainty propagated."""
    from magcal.fitting.pipeline import calibrate

    free = sim.simulate(truth, n_samples=200, noise_nT=SIGMA, seed=5)
    cal = calibrate(free).calibration
    icov = np.array(
        [pf.intrinsic_covariance(free.readings_nT[i], c.cinv, c.bias_nT, SIGMA) for i, c in enumerate(cal.sensors)]
    )
    ds = pf.simulate_level_table(truth, n_per_group=100, noise_nT=SIGMA, seed=6)
    _, alone = pf.align(ds, cal, noise_nT=SIGMA)
    new, res = pf.align(ds, cal, noise_nT=SIGMA, intrinsic_cov=icov)
    assert res.intrinsic_included and np.all(res.angles_std_rad > alone.angles_std_rad)
    z = (res.angles_rad - true_angles(truth)) / res.angles_std_rad
    assert np.max(np.abs(z)) < 4.5, z


def test_patent_claim_is_met_at_the_seed_noise(truth):
    """The patent's 'parameter estimation error at the 1/1000 level': the bound is below 1/1000 of the angles."""
    ds = pf.simulate_level_table(truth, n_per_group=100, noise_nT=SIGMA, seed=9)
    _, res = pf.align(ds, true_calibration(truth), noise_nT=SIGMA)
    relative_bound = res.angles_std_rad / np.abs(true_angles(truth))
    assert np.median(relative_bound) < pf.PATENT_CLAIM_RELATIVE
    assert np.all(res.angles_std_rad < 1e-3 / 50)  # an absolute 1e-3 rad reading of the claim is far weaker


def test_corrected_survey_is_the_platform_frame_field(truth):
    ds = pf.simulate_level_table(truth, n_per_group=100, noise_nT=SIGMA, seed=4)
    new, _ = pf.align(ds, true_calibration(truth))
    survey = sim.simulate(truth, n_samples=100, noise_nT=0.0, seed=8, with_attitude=True)
    from scipy.spatial.transform import Rotation

    q = survey.attitude_wxyz
    b_platform = Rotation.from_quat(np.column_stack([q[:, 1:], q[:, :1]])).inv().apply(truth.field_world_nT)
    corrected = new.correct(survey)
    for s in range(4):  # alignment errors ~1e-5 rad x 50 000 nT ~ 0.5 nT, plus the noise-free survey
        assert np.max(np.abs(corrected[s] - b_platform)) < 3.0


@pytest.mark.parametrize("groups", [("x_up", "z_up"), ("y_up", "z_up"), ("x_down", "y_up")])
def test_two_groups_are_enough(truth, groups):
    ds = pf.simulate_level_table(truth, n_per_group=120, noise_nT=SIGMA, seed=10, groups=groups)
    _, res = pf.align(ds, true_calibration(truth))
    z = (res.angles_rad - true_angles(truth)) / res.angles_std_rad
    assert np.max(np.abs(z)) < 4.5
    assert res.groups == [g for g in pf.GROUP_AXES if g in groups]


def test_other_labels_are_ignored_and_free_rows_serve_the_scalar_calibration(truth):
    ds = pf.simulate_level_table(truth, n_per_group=80, noise_nT=SIGMA, seed=12, n_free=300)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        new, res = pf.align(ds, None)  # scalar calibration fitted to the same file first
    assert res.counts == [80, 80, 80] and "free (300)" in res.text()
    err = pf.rotation_error_rad(res.R, true_R(truth))
    assert np.all(err < 1e-4)  # intrinsic errors from 540 samples add ~1e-5 rad; far below 1e-4


def test_a_seat_error_shows_in_the_axis_check(truth):
    """A platform seated 0.05 deg off the table's normal tilts the axes by about that: the 90-deg check sees it."""
    ds = pf.simulate_level_table(truth, n_per_group=100, noise_nT=SIGMA, seed=13, seat_error_deg=0.05)
    _, res = pf.align(ds, true_calibration(truth))
    err = pf.rotation_error_rad(res.R, true_R(truth))
    assert np.all(err > 10 * res.rotation_std_rad.max()) and np.all(err < np.radians(0.1))
    assert np.max(np.abs(res.axis_angles_deg - 90.0)) > 0.02


def test_mislabelled_group_is_reported(truth):
    ds = pf.simulate_level_table(truth, n_per_group=60, noise_nT=SIGMA, seed=14)
    wrong = ds.group.astype("<U8")
    wrong[wrong == "y_up"] = "y_down"
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a step of the engine says it in its result, never as a warning
        _, res = pf.align(ds.replace(group=wrong), true_calibration(truth))
    said = [n for n in res.notes if n.is_a(DataWarning)]
    assert said and all("check the group labels" in n.text for n in said)
    assert any("check the group labels" in r for r in res.remarks)  # and the report says it too


@pytest.mark.parametrize(
    "change,match",
    [
        (lambda ds: ds.replace(group=None), "needs a group column"),
        (lambda ds: ds.replace(group=np.array(["free"] * ds.n_samples)), "no level-table groups"),
        (lambda ds: ds.subset(ds.group == "z_up"), "only the group"),
        (lambda ds: ds.subset(np.r_[np.ones(ds.n_samples - 97, bool), np.zeros(97, bool)]), "at least"),
    ],
)
def test_unusable_records_are_refused(truth, change, match):
    ds = pf.simulate_level_table(truth, n_per_group=100, noise_nT=SIGMA, seed=15)
    with pytest.raises(DatasetError, match=match):
        pf.align(change(ds), true_calibration(truth))


def test_a_group_not_turned_is_refused(truth):
    ds = pf.simulate_level_table(truth, n_per_group=60, noise_nT=SIGMA, seed=16, heading_range_deg=2.0)
    with pytest.raises(DatasetError, match="hardly turned"):
        pf.align(ds, true_calibration(truth))


def test_wrong_sensor_count_is_refused(truth):
    ds = pf.simulate_level_table(truth, n_per_group=30, noise_nT=SIGMA, seed=17).sensors([0, 1])
    from magcal.core.errors import MagcalError

    with pytest.raises(MagcalError, match="4 sensor"):
        pf.align(ds, true_calibration(truth))


def test_saved_aligned_calibration_round_trips(tmp_path, truth):
    from magcal.output.apply import load_calibration

    ds = pf.simulate_level_table(truth, n_per_group=60, noise_nT=SIGMA, seed=18)
    new, res = pf.align(ds, true_calibration(truth))
    new.save(tmp_path / "p.json")
    back = load_calibration(tmp_path / "p.json", n_sensors=4)
    assert back.frame == "platform"
    np.testing.assert_allclose([c.R for c in back.sensors], res.R, atol=1e-15)
    assert back.summary["platform_alignment"]["groups"] == {"x_up": 60, "y_up": 60, "z_up": 60}
