"""The whole calibration (ellipsoid -> Procrustes -> ML) against known truth.

Statistical statements are tested honestly: a single N = 200 realisation's RMS fluctuates by about
1/sqrt(2(N-9)) = 5% around its expectation, so "within 3% of the floor" is tested on the *mean over many seeds*
(24 chi2017 realisations, 16 independent files), where the fluctuation of the mean is about 1%. Parameter
tolerances (C^-1 2e-4, b 2 nT, R 1.5e-3) are several standard errors wide and are checked on *every* realisation.
Those many-realisation tests are marked slow (a few seconds each on an idle core; they still run in CI).
"""

import csv

import numpy as np
import pytest

from magcal.core import conventions
from magcal.core.errors import CalibrationError
from magcal.data import io
from magcal.data.simulation import chi2017_truth, simulate, simulate_timeseries
from magcal.fitting.pipeline import calibrate

CHI_SEEDS = range(1000, 1024)
SIGMA = 3.0


def _param_errors(calibration, cinv_true, bias_true, r_true):
    return (
        max(np.max(np.abs(c.cinv - t)) for c, t in zip(calibration.sensors, cinv_true)),
        max(np.max(np.abs(c.bias_nT - t)) for c, t in zip(calibration.sensors, bias_true)),
        max(np.max(np.abs(c.R - t)) for c, t in zip(calibration.sensors, r_true)),
    )


def _tensor_rms(result):
    return np.array([result.tensor_rms_nT_per_m[k] for k in conventions.TENSOR_COMPONENTS])


def _tensor_floor(sigma, d):
    return np.array([2 * sigma / d if k == "Gzz" else np.sqrt(2) * sigma / d for k in conventions.TENSOR_COMPONENTS])


@pytest.fixture(scope="module")
def chi_runs():
    truth = chi2017_truth()
    runs = [calibrate(simulate("chi2017", seed=s)) for s in CHI_SEEDS]
    return truth, runs


@pytest.mark.slow
def test_chi2017_parameters_every_realisation(chi_runs):
    truth, runs = chi_runs
    cinv = [s.Cinv for s in truth.sensors]
    bias = [s.bias_nT for s in truth.sensors]
    rot = [s.R for s in truth.sensors]
    for r in runs:
        e_c, e_b, e_r = _param_errors(r.calibration, cinv, bias, rot)
        assert e_c < 2e-4 and e_b < 2.0 and e_r < 1.5e-3, (e_c, e_b, e_r)
        assert np.allclose(r.calibration.sensors[0].R, np.eye(3))


@pytest.mark.slow
def test_chi2017_total_field_rms_at_floor(chi_runs):
    _, runs = chi_runs
    n = 200
    floor = SIGMA * np.sqrt(1 - 9 / n)
    per_sensor = np.array([r.rms_after_per_sensor_nT for r in runs])  # (seeds, 4)
    assert np.all(np.abs(per_sensor.mean(axis=0) / floor - 1) < 0.03), per_sensor.mean(axis=0) / floor
    # a single realisation: within 4 standard deviations of its sampling spread (5% each)
    assert np.all(np.abs(per_sensor / floor - 1) < 0.2)
    assert runs[0].total_field_floor_nT == pytest.approx(floor)


@pytest.mark.slow
def test_chi2017_tensor_rms_at_floor(chi_runs):
    _, runs = chi_runs
    floor = _tensor_floor(SIGMA, 0.5)
    mean = np.mean([_tensor_rms(r) for r in runs], axis=0)
    assert np.all(np.abs(mean / floor - 1) < 0.10), mean / floor
    assert np.allclose([runs[0].tensor_floor_nT_per_m[k] for k in conventions.TENSOR_COMPONENTS], floor)


def test_chi2017_steps_tell_the_story():
    truth = chi2017_truth()
    r = calibrate(simulate("chi2017", seed=1000))
    e_c, e_b, e_r = _param_errors(
        r.calibration, [s.Cinv for s in truth.sensors], [s.bias_nT for s in truth.sensors], [s.R for s in truth.sensors]
    )
    assert e_c < 2e-4 and e_b < 2.0 and e_r < 1.5e-3
    assert [s.name for s in r.steps] == ["raw", "ellipsoid", "procrustes", "ml"]
    raw, ell, pro, ml = r.steps
    # paper: total field off by up to ~2600 nT before, within ~10 nT after; tensor up to ~16000 nT/m before
    assert np.max(raw.max_abs_per_sensor_nT) > 1000
    assert np.all(ell.rms_per_sensor_nT < 1.2 * SIGMA)
    assert max(raw.tensor_max_abs_nT_per_m.values()) > 5000
    # step 1 fixes each sensor's total field but not the tensor; step 2 leaves the total field and fixes the tensor
    assert max(ell.tensor_rms_nT_per_m.values()) > 100 * max(pro.tensor_rms_nT_per_m.values())
    assert np.allclose(pro.rms_per_sensor_nT, ell.rms_per_sensor_nT)
    assert np.max(ell.sensor_difference_rms_nT) > 500 and np.max(pro.sensor_difference_rms_nT) < 5 * SIGMA
    assert r.fit is not None and r.method == "ml"


def test_ellipsoid_method_is_the_seed_two_steps():
    truth = chi2017_truth()
    r = calibrate(simulate("chi2017", seed=3), method="ellipsoid")
    assert r.fit is None and [s.name for s in r.steps] == ["raw", "ellipsoid", "procrustes"]
    e_c, e_b, e_r = _param_errors(
        r.calibration, [s.Cinv for s in truth.sensors], [s.bias_nT for s in truth.sensors], [s.R for s in truth.sensors]
    )
    assert e_c < 2e-4 and e_b < 2.0 and e_r < 1.5e-3


def test_unknown_reference_is_fitted():
    truth = chi2017_truth()
    ds = simulate("chi2017", seed=4, n_samples=400).replace(reference_total_nT=None)
    r = calibrate(ds)
    assert r.reference_kind == "fitted" and r.calibration.reference_fitted
    assert np.linalg.det(r.calibration.sensors[0].cinv) == pytest.approx(1.0, abs=1e-9)
    # only a common gain is lost: F_fit / F = det(C_1)^(1/3), and every C^-1 is the truth times that ratio
    ratio = r.reference_total_nT / truth.total_nT
    assert ratio == pytest.approx(np.linalg.det(truth.sensors[0].C) ** (1 / 3), rel=2e-5)
    for c, s in zip(r.calibration.sensors, truth.sensors):
        assert np.max(np.abs(c.cinv - s.Cinv * ratio)) < 2e-4
    assert np.all(r.rms_after_per_sensor_nT < 1.2 * SIGMA)


def test_reference_argument_overrides_file():
    ds = simulate("chi2017", seed=5).replace(reference_total_nT=None)
    r = calibrate(ds, reference_total_nT=50_000.0, method="ellipsoid")
    assert r.reference_kind == "given" and r.reference_total_nT == 50_000.0


def test_mask_and_single_sensor():
    truth = chi2017_truth()
    ds = simulate("chi2017", seed=6, n_samples=250).sensors([2]).replace(baseline_m=None)
    mask = np.ones(250, bool)
    mask[::5] = False
    r = calibrate(ds, mask=mask)
    assert r.n_samples == 200 and [s.name for s in r.steps] == ["raw", "ellipsoid", "ml"]
    assert r.tensor_rms_nT_per_m is None and r.tensor_floor_nT_per_m is None
    assert np.max(np.abs(r.calibration.sensors[0].cinv - truth.sensors[2].Cinv)) < 2e-4


def test_robust_loss_with_gross_outliers():
    truth = chi2017_truth()
    n = 400
    ds = simulate("chi2017", seed=7, n_samples=n)
    rng = np.random.default_rng(70)
    bad = rng.choice(n, n // 20, replace=False)  # 5% gross outliers
    y = ds.readings_nT.copy()
    for i in bad:
        s = rng.integers(4)
        y[s, i] += rng.choice([-1, 1], 3) * rng.uniform(200, 3000, 3)
    ds = ds.replace(readings_nT=y)
    inliers = np.ones(n, bool)
    inliers[bad] = False

    plain = calibrate(ds)
    robust = calibrate(ds, robust=True)
    floor = SIGMA * np.sqrt(1 - 9 / n)
    rms_in = np.sqrt(np.mean(robust.fit.residuals_nT[:, inliers] ** 2, axis=1))
    assert np.all(np.abs(rms_in / floor - 1) < 0.12), rms_in / floor
    assert np.array_equal(robust.outliers, ~inliers)  # reports exactly the corrupted samples
    assert any("distrusted" in w for w in robust.remarks)
    e_c, e_b, e_r = _param_errors(
        robust.calibration,
        [s.Cinv for s in truth.sensors],
        [s.bias_nT for s in truth.sensors],
        [s.R for s in truth.sensors],
    )
    assert e_c < 2e-4 and e_b < 2.0 and e_r < 1.5e-3
    # the figures leave the distrusted samples out and sit at the floor
    assert np.all(robust.rms_after_per_sensor_nT < 1.15 * floor)
    assert np.all(_tensor_rms(robust) < 1.15 * _tensor_floor(SIGMA, 0.5))
    # without the robust loss the same data pull the fit far off the floor
    rms_in_plain = np.sqrt(np.mean(plain.fit.residuals_nT[:, inliers] ** 2, axis=1))
    assert np.max(rms_in_plain) > 3 * floor


@pytest.mark.parametrize(
    "kwargs,message",
    [
        ({"method": "magic"}, "unknown method"),
        ({"method": "ellipsoid", "effects": ["temperature_bias"]}, "only be fitted with method 'ml'"),
        ({"mask": np.ones(3, bool)}, "mask has shape"),
    ],
)
def test_refusals(kwargs, message):
    with pytest.raises(CalibrationError, match=message):
        calibrate(simulate("chi2017", seed=1, n_samples=50), **kwargs)


def test_degenerate_array_coverage_is_refused():
    from scipy.spatial.transform import Rotation

    from magcal.data.dataset import Dataset
    from magcal.data.simulation import true_fields

    truth = chi2017_truth()
    att = Rotation.from_euler("z", np.linspace(0, 2 * np.pi, 100, endpoint=False)[:, None])  # yaw only
    fields = true_fields(truth, att)
    y = np.stack([s.measure(f) for s, f in zip(truth.sensors, fields)])
    y += np.random.default_rng(0).normal(0, 3, y.shape)
    with pytest.raises(CalibrationError, match="degenerate coverage"):
        calibrate(Dataset(y, reference_total_nT=5e4, baseline_m=0.5))


# ---------------------------------------------------------------------------------------------------------------
# Files from an independent simulator: the seed's equations written out here, other error values, written with
# the csv module (readings in uT, extra columns), read back through magcal.data.io.
# ---------------------------------------------------------------------------------------------------------------

IND_F_nT, IND_DEC, IND_INC = 47_500.0, 12.0, -38.0  # a southern-hemisphere site
IND_D = 0.3
IND_SIGMA = 2.5
IND_N = 300
# k_x, k_y, k_z, psi, phi, theta (rad), b_x, b_y, b_z (nT), alpha, beta, gamma (rad)
IND_ERRORS = [
    (0.985, 1.022, 1.004, -0.011, 0.031, 0.008, -140.0, 62.0, 93.0, 0.0, 0.0, 0.0),
    (1.031, 0.978, 0.993, 0.024, -0.015, -0.019, 210.0, -35.0, 7.0, 0.041, -0.017, 0.012),
    (0.969, 1.008, 1.027, -0.006, 0.012, 0.027, -18.0, -160.0, 120.0, -0.015, 0.033, -0.026),
    (1.012, 0.991, 0.975, 0.019, -0.028, -0.009, 75.0, 44.0, -210.0, 0.022, 0.009, 0.038),
]


def _ind_C(kx, ky, kz, psi, phi, theta):
    """Eq. (2): C = diag(k) C_NO."""
    c_no = np.array(
        [
            [np.cos(theta) * np.cos(phi), np.cos(theta) * np.sin(phi), np.sin(theta)],
            [0.0, np.cos(psi), np.sin(psi)],
            [0.0, 0.0, 1.0],
        ]
    )
    return np.diag([kx, ky, kz]) @ c_no


def _ind_M(alpha, beta, gamma):
    """Eq. (3): M = R1(gamma) R2(beta) R3(alpha), B_i = M B_1."""
    ca, sa, cb, sb, cg, sg = np.cos(alpha), np.sin(alpha), np.cos(beta), np.sin(beta), np.cos(gamma), np.sin(gamma)
    r1 = np.array([[cg, 0, -sg], [0, 1, 0], [sg, 0, cg]])
    r2 = np.array([[1, 0, 0], [0, cb, sb], [0, -sb, cb]])
    r3 = np.array([[ca, sa, 0], [-sa, ca, 0], [0, 0, 1]])
    return r1 @ r2 @ r3


def _ind_quaternion_matrices(rng, n):
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        1,
    )


def _ind_write(path, seed):
    rng = np.random.default_rng(seed)
    d, i = np.radians(IND_DEC), np.radians(IND_INC)
    b_world = IND_F_nT * np.array([np.cos(i) * np.cos(d), np.cos(i) * np.sin(d), np.sin(i)])
    q = _ind_quaternion_matrices(rng, IND_N)  # array -> world
    b_array = np.einsum("nji,j->ni", q, b_world)  # Q^T B_world
    columns = []
    for e in IND_ERRORS:
        c, m, b = _ind_C(*e[:6]), _ind_M(*e[9:12]), np.array(e[6:9])
        y = b_array @ m.T @ c.T + b + rng.normal(0, IND_SIGMA, (IND_N, 3))
        columns.append(y / 1000.0)  # written in uT
    with open(path, "w", newline="", encoding="utf-8") as fh:
        fh.write(f"# baseline_m: {IND_D}\n# reference_total_nT: {IND_F_nT}\n# units: uT\n# written by: test\n")
        w = csv.writer(fh)
        w.writerow(["sample"] + [f"s{s}{a}" for s in range(1, 5) for a in "xyz"] + ["t"])
        for k in range(IND_N):
            w.writerow([f"#{k}"] + [repr(float(v)) for col in columns for v in col[k]] + [repr(0.1 * k)])


@pytest.fixture(scope="module")
def independent_runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("independent")
    runs = []
    for seed in range(16):
        path = root / f"ind{seed}.csv"
        _ind_write(path, 500 + seed)
        ds = io.read_csv(path)
        assert ds.n_sensors == 4 and ds.n_samples == IND_N and ds.baseline_m == IND_D
        runs.append(calibrate(ds))
    return runs


@pytest.mark.slow
def test_independent_files_parameters(independent_runs):
    cinv = [np.linalg.inv(_ind_C(*e[:6])) for e in IND_ERRORS]
    bias = [np.array(e[6:9]) for e in IND_ERRORS]
    rot = [_ind_M(*e[9:12]).T for e in IND_ERRORS]
    for r in independent_runs:
        assert r.reference_kind == "given" and r.reference_total_nT == IND_F_nT
        e_c, e_b, e_r = _param_errors(r.calibration, cinv, bias, rot)
        assert e_c < 2e-4 and e_b < 2.0 and e_r < 1.5e-3, (e_c, e_b, e_r)


@pytest.mark.slow
def test_independent_files_floors(independent_runs):
    floor = IND_SIGMA * np.sqrt(1 - 9 / IND_N)
    per_sensor = np.mean([r.rms_after_per_sensor_nT for r in independent_runs], axis=0)
    assert np.all(np.abs(per_sensor / floor - 1) < 0.03), per_sensor / floor
    tensor = np.mean([_tensor_rms(r) for r in independent_runs], axis=0)
    assert np.all(np.abs(tensor / _tensor_floor(IND_SIGMA, IND_D) - 1) < 0.10)
    # the noise was not in the file: the result says the floors rest on an estimate, and the estimate is right
    assert independent_runs[0].noise_source == "residuals"  # random attitudes, no still stretch
    assert np.mean([r.noise_nT for r in independent_runs]) == pytest.approx(IND_SIGMA, rel=0.03)


def test_progress_is_reported():
    seen = []
    calibrate(simulate("chi2017", seed=9, n_samples=60), progress=lambda msg, frac: seen.append((msg, frac)))
    names = [m for m, _ in seen]
    assert names[0].startswith("step 1") and any(m.startswith("step 2") for m in names)
    assert any(m.startswith("step 3") for m in names) and seen[-1] == ("done", 1.0)


def test_search_methods_are_dispatched():
    pytest.importorskip("magcal.fitting.search").search_calibrate  # noqa: B018 (the helper's module must provide it)
    truth = chi2017_truth()
    ds = simulate("chi2017", seed=10, n_samples=150).sensors([1]).replace(baseline_m=None)
    seen, fractions = [], []
    r = calibrate(ds, method="de", seed=3, progress=lambda msg, frac: (seen.append(msg), fractions.append(frac)))
    assert r.fit is None and r.steps[-1].name == "de" and any(m.startswith("de: iteration") for m in seen)
    # the search reports how far it has gone: fractions that rise and stay within [0, 1]
    searching = [f for m, f in zip(seen, fractions) if m.startswith("de: iteration")]
    assert all(f is not None and 0.0 <= f <= 1.0 for f in searching)
    assert np.all(np.diff(searching) >= 0) and searching[-1] > searching[0]
    assert np.max(np.abs(r.calibration.sensors[0].cinv - truth.sensors[1].Cinv)) < 2e-4
    assert np.max(np.abs(r.calibration.sensors[0].bias_nT - truth.sensors[1].bias_nT)) < 2.0


def test_adding_the_hidden_effect_brings_the_fit_to_the_floor():
    from magcal.model.terms import parse_effect

    effect = parse_effect("temperature_bias", 4)
    ds = simulate_timeseries("chi2017", n_samples=600, seed=12, perturbations=[effect.perturbation(20.0)])
    base = calibrate(ds)
    full = calibrate(ds, effects=["temperature_bias"])
    floor = full.total_field_floor_nT
    assert floor == pytest.approx(SIGMA * np.sqrt(1 - 12 / 600))  # 9 base + 3 temperature parameters per sensor
    assert np.all(base.rms_after_per_sensor_nT > 5 * floor)
    assert np.all(np.abs(full.rms_after_per_sensor_nT / floor - 1) < 0.12)
    assert full.effects == ["temperature_bias"] and full.calibration.to_dict()["effects"] == ["temperature_bias"]
    assert full.fit.bic < base.fit.bic


def test_align_sensors_recovers_the_misalignment_from_a_given_step_one():
    """Step 2 alone, on the true C^-1 and b with every R reset to identity, finds the true rotations."""
    from magcal.calibration.calibration import Calibration, SensorCalibration
    from magcal.fitting.pipeline import align_sensors

    truth = chi2017_truth()
    ds = simulate(truth, seed=13)
    start = Calibration(
        [SensorCalibration(s.Cinv, s.bias_nT, np.eye(3)) for s in truth.sensors],
        reference_total_nT=truth.total_nT,
        baseline_m=ds.baseline_m,
    )
    aligned = align_sensors(ds, start)
    for got, want in zip(aligned.sensors, truth.sensors):
        assert np.max(np.abs(got.R - want.R)) < 2e-4
    assert all(np.allclose(s.R, np.eye(3)) for s in start.sensors)  # the input is left as it was


@pytest.mark.parametrize("total_nT", [50_000.0, 10_000.0])
@pytest.mark.parametrize("reference", ["given", "column", "fitted"])
def test_summary_carries_the_fitted_field_magnitude(tmp_path, total_nT, reference):
    """The field the calibration expects (nT): the given one, the column's, or the fitted F0 (the truth times
    det(C_1)^(1/3), the common gain total-field data cannot see); saved with the calibration."""
    from magcal.calibration.calibration import Calibration

    truth = chi2017_truth()
    truth.total_nT = total_nT
    ds = simulate(truth, seed=21, n_samples=300)
    if reference == "fitted":
        ds = ds.replace(reference_total_nT=None)
    elif reference == "column":
        ds = ds.replace(reference_total_nT=None, ref_total_nT=np.linspace(total_nT - 20.0, total_nT + 20.0, 300))
    r = calibrate(ds)
    assert r.reference_kind == reference
    expected = total_nT * (np.linalg.det(truth.sensors[0].C) ** (1 / 3) if reference == "fitted" else 1.0)
    assert r.field_magnitude_nT == pytest.approx(expected, rel=1e-4)  # the gain factor is 3e-3
    assert r.calibration.summary["field_magnitude_nT"] == r.field_magnitude_nT
    path = tmp_path / "cal.json"
    r.calibration.save(path)
    assert Calibration.load(path).summary["field_magnitude_nT"] == pytest.approx(r.field_magnitude_nT)
