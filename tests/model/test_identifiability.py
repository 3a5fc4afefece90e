"""Total-field data determine M M^T and I only: different splits give identical data and identical calibrations."""

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import magcal
from magcal.core import conventions
from magcal.data.simulation import ArrayTruth, SensorErrors, ding2024_truth
from magcal.fitting import search
from magcal.model import identifiability

FAST = {"pop_size": 30, "max_iter": 400}


def _split_by_hand(sensor, scale, psi, phi, theta, bias_nT):
    """Another sensor/platform split of the same M and I, computed here without magcal.model.identifiability."""
    m = sensor.total_matrix
    offset = sensor.total_offset_nT
    ct, cp = np.cos(theta), np.cos(phi)
    c_no = np.array([[ct * cp, ct * np.sin(phi), np.sin(theta)], [0, np.cos(psi), np.sin(psi)], [0, 0, 1]])
    c = np.diag(scale) @ c_no
    soft = np.linalg.solve(c, m) - np.eye(3)
    hard = np.linalg.solve(c, offset - np.asarray(bias_nT))
    return SensorErrors(
        scale=np.asarray(scale),
        psi=psi,
        phi=phi,
        theta=theta,
        bias_nT=np.asarray(bias_nT),
        hard_iron_nT=hard,
        soft_iron=soft,
    )


@pytest.fixture(scope="module")
def two_splits():
    a = ding2024_truth()
    other = _split_by_hand(
        a.sensors[0], scale=[0.97, 1.06, 1.01], psi=0.02, phi=-0.035, theta=0.015, bias_nT=[-300.0, 40.0, 900.0]
    )
    b = dataclasses.replace(a, sensors=[other])
    return a, b


def test_the_splits_differ_in_every_physical_parameter(two_splits):
    a, b = two_splits
    sa, sb = a.sensors[0], b.sensors[0]
    assert np.max(np.abs(sa.soft_iron - sb.soft_iron)) > 0.02
    assert np.max(np.abs(sa.hard_iron_nT - sb.hard_iron_nT)) > 100.0
    assert np.max(np.abs(sa.bias_nT - sb.bias_nT)) > 100.0
    assert np.max(np.abs(sa.scale - sb.scale)) > 0.02


@pytest.mark.parametrize("noise_nT", [0.0, 2.0])
def test_two_splits_give_identical_data_and_identical_calibrations(two_splits, noise_nT):
    a, b = two_splits
    da = magcal.simulate(a, n_samples=150, noise_nT=noise_nT, noise_kind="uniform", seed=8)
    db = magcal.simulate(b, n_samples=150, noise_nT=noise_nT, noise_kind="uniform", seed=8)
    assert np.allclose(da.readings_nT, db.readings_nT, rtol=0, atol=1e-8)  # nT: identical up to rounding
    ca = search.search_calibrate(da, "ipso", seed=4, **FAST).calibration
    cb = search.search_calibrate(db, "ipso", seed=4, **FAST).calibration
    assert np.allclose(ca.sensors[0].cinv, cb.sensors[0].cinv, rtol=0, atol=1e-9)
    assert np.allclose(ca.sensors[0].bias_nT, cb.sensors[0].bias_nT, rtol=0, atol=1e-5)
    # and what both calibrations report is the same 9 identifiable numbers as both truths
    ia = identifiability.from_sensor_calibration(ca.sensors[0])
    ib = identifiability.from_sensor_calibration(cb.sensors[0])
    assert np.allclose(ia.as_vector(), ib.as_vector(), rtol=1e-9, atol=1e-5)
    ta, tb = identifiability.from_truth(a.sensors[0]), identifiability.from_truth(b.sensors[0])
    assert np.allclose(ta.as_vector(), tb.as_vector(), rtol=1e-12, atol=1e-9)
    err = ta.field_error_nT(ia, a.total_nT)
    limit = 1e-5 if noise_nT == 0 else 1.0  # nT; with noise, CRB ~ 0.1 nT for N = 150
    assert err["matrix_nT"] < limit and err["offset_nT"] < limit


def test_a_rotated_matrix_gives_the_same_calibration():
    """M and M Q (Q a rotation) give the same total field for every attitude: the same upper-triangular C^-1."""
    s = ding2024_truth().sensors[0]
    q = Rotation.from_rotvec([0.3, -0.5, 0.2]).as_matrix()
    rotated = SensorErrors(matrix=s.total_matrix @ q, bias_nT=s.total_offset_nT)
    truths = [
        ArrayTruth([SensorErrors(matrix=s.total_matrix, bias_nT=s.total_offset_nT)], total_nT=51_500.0),
        ArrayTruth([rotated], total_nT=51_500.0),
    ]
    cals = [
        search.search_calibrate(
            magcal.simulate(t, n_samples=80, noise_nT=0.0, seed=k), "de", seed=1, **FAST
        ).calibration
        for k, t in enumerate(truths)
    ]
    assert np.allclose(cals[0].sensors[0].cinv, cals[1].sensors[0].cinv, rtol=0, atol=1e-9)
    assert np.allclose(
        identifiability.from_truth(truths[0].sensors[0]).MMt, identifiability.from_truth(truths[1].sensors[0]).MMt
    )


@pytest.mark.parametrize("seed", range(4))
def test_equivalent_sensor_keeps_m_and_i(seed):
    rng = np.random.default_rng(seed)
    s = ding2024_truth().sensors[0]
    e = identifiability.equivalent_sensor(
        s,
        scale=rng.uniform(0.9, 1.1, 3),
        psi=rng.uniform(-0.05, 0.05),
        phi=rng.uniform(-0.05, 0.05),
        theta=rng.uniform(-0.05, 0.05),
        bias_nT=rng.uniform(-500, 500, 3),
    )
    assert np.allclose(e.total_matrix, s.total_matrix, atol=1e-14)
    assert np.allclose(e.total_offset_nT, s.total_offset_nT, atol=1e-9)
    assert not np.allclose(e.soft_iron, s.soft_iron, atol=1e-3)
    field = rng.normal(size=(20, 3)) * 3e4
    assert np.allclose(e.measure(field), s.measure(field), atol=1e-8)


def test_identifiable_gauge_and_gauge_free_figures():
    s = ding2024_truth().sensors[0]
    ident = identifiability.from_truth(s)
    u = ident.cinv
    assert np.allclose(np.tril(u, -1), 0.0) and np.all(np.diag(u) > 0)
    assert np.allclose(np.linalg.inv(u.T @ u), ident.MMt)
    m = s.total_matrix
    assert np.allclose(ident.scale, np.linalg.norm(m, axis=1))  # rows of M: the effective sensing axes
    rows = m / np.linalg.norm(m, axis=1)[:, None]
    angles = [np.degrees(np.arccos(rows[i] @ rows[j])) for i, j in conventions.AXIS_PAIRS]
    assert np.allclose(ident.axis_angles_deg, angles)
    assert ident.as_vector().shape == (9,)
    text = ident.describe()
    assert "9 numbers" in text and "not identifiable" in text


def test_field_error_is_zero_for_a_rotated_gauge_and_sees_a_real_change():
    ident = identifiability.from_truth(ding2024_truth().sensors[0])
    q = Rotation.from_rotvec([0.1, 0.2, -0.3]).as_matrix()
    rotated = identifiability.from_calibration(q @ ident.cinv, ident.offset_nT)
    err = ident.field_error_nT(rotated, 51_500.0)
    assert err["matrix_nT"] < 1e-8 and err["offset_nT"] < 1e-9
    bumped = identifiability.from_calibration(ident.cinv * (1.0 + 1e-5), ident.offset_nT + 1.0)
    err = ident.field_error_nT(bumped, 51_500.0)
    assert err["matrix_nT"] == pytest.approx(0.515, rel=0.05)  # 1e-5 of 51 500 nT
    assert err["offset_nT"] == pytest.approx(np.sqrt(3.0))


@pytest.mark.parametrize("n_sensors, identifiable", [(1, 9), (2, 21), (4, 45)])
def test_parameter_count(n_sensors, identifiable):
    count = identifiability.parameter_count(n_sensors)
    assert count["identifiable"] == identifiable
    assert count["nominal"] > count["identifiable"]
    assert identifiability.parameter_count(1)["nominal"] == 21
