"""Step 2: orthogonal Procrustes with det +1 (eq. 14)."""

import numpy as np
import pytest
import scipy.linalg
from scipy.spatial.transform import Rotation

from magcal.core.errors import CalibrationError
from magcal.data.simulation import chi2017_truth, simulate
from magcal.geometry.procrustes import procrustes_rotation, rotation_angle_deg


def _field_vectors(n, seed, total_nT=50_000.0):
    u = np.random.default_rng(seed).normal(size=(n, 3))
    return total_nT * u / np.linalg.norm(u, axis=1, keepdims=True)


@pytest.mark.parametrize("rotvec", [(0.0, 0.0, 0.0), (0.02, -0.03, 0.01), (0.5, 1.0, -0.7), (0.0, 3.0, 0.0)])
def test_recovers_a_rotation_exactly(rotvec):
    r_true = Rotation.from_rotvec(rotvec).as_matrix()
    b_i = _field_vectors(50, 1)
    b_1 = b_i @ r_true.T  # sensor 1 sees R B_i
    r = procrustes_rotation(b_1, b_i)
    assert np.allclose(r, r_true, atol=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0)


def test_noise_gives_small_error():
    r_true = Rotation.from_rotvec([0.03, 0.02, -0.04]).as_matrix()
    rng = np.random.default_rng(2)
    b_i = _field_vectors(200, 3)
    b_1 = b_i @ r_true.T + rng.normal(0, 3.0, b_i.shape)
    b_i = b_i + rng.normal(0, 3.0, b_i.shape)
    r = procrustes_rotation(b_1, b_i)
    # each component of the angular error has sd ~ sqrt(2) sigma / (F sqrt(N)) = 6e-6 rad; the 3-D angle is about
    # twice that on average; allow 10 times the per-component sd
    per_component = np.sqrt(2) * 3.0 / (5e4 * np.sqrt(200))
    angle = np.radians(rotation_angle_deg(r @ r_true.T))
    assert 0 < angle < 10 * per_component


def test_agrees_with_scipy_when_the_optimum_is_proper():
    r_true = Rotation.from_rotvec([0.2, -0.1, 0.4]).as_matrix()
    rng = np.random.default_rng(4)
    b_i = _field_vectors(80, 5)
    b_1 = b_i @ r_true.T + rng.normal(0, 50.0, b_i.shape)
    omega, _ = scipy.linalg.orthogonal_procrustes(b_i, b_1)  # b_i @ omega ~ b_1, so omega = R^T
    assert np.allclose(procrustes_rotation(b_1, b_i), omega.T, atol=1e-12)


def test_never_returns_a_reflection():
    # Mirror-image data: the unconstrained optimum (the seed's R = U V^T) is a reflection; ours is a rotation.
    b_i = _field_vectors(60, 6) * np.array([1.0, 1.0, 0.3])
    b_1 = b_i * np.array([1.0, 1.0, -1.0])
    u, _, vt = np.linalg.svd(b_1.T @ b_i)
    assert np.linalg.det(u @ vt) < 0
    r = procrustes_rotation(b_1, b_i)
    assert np.allclose(r @ r.T, np.eye(3), atol=1e-12) and np.linalg.det(r) == pytest.approx(1.0)
    # and it is the best proper rotation: no random rotation does better
    cost = np.sum((b_1 - b_i @ r.T) ** 2)
    others = Rotation.random(500, random_state=7).as_matrix()
    assert all(cost <= np.sum((b_1 - b_i @ q.T) ** 2) + 1e-6 * cost for q in others)


@pytest.mark.parametrize("sensor", [1, 2, 3])
def test_chi2017_truth_corrected_vectors(sensor):
    truth = chi2017_truth()
    ds = simulate("chi2017", seed=8)
    s1, si = truth.sensors[0], truth.sensors[sensor]
    b_1 = (ds.readings_nT[0] - s1.bias_nT) @ s1.Cinv.T
    b_i = (ds.readings_nT[sensor] - si.bias_nT) @ si.Cinv.T
    assert np.max(np.abs(procrustes_rotation(b_1, b_i) - si.R)) < 1e-4


def test_refuses_directions_in_a_plane():
    u = np.linspace(0, 2 * np.pi, 40)
    b = 5e4 * np.column_stack([np.cos(u), np.sin(u), np.zeros_like(u)])
    with pytest.raises(CalibrationError, match="degenerate coverage"):
        procrustes_rotation(b, b)


@pytest.mark.parametrize(
    "a,b,message",
    [
        (np.ones((10, 3)), np.ones((9, 3)), "same shape"),
        (np.eye(3)[:2], np.eye(3)[:2], "at least 3"),
        (np.full((5, 3), np.nan), np.ones((5, 3)), "non-finite"),
    ],
)
def test_refuses_bad_input(a, b, message):
    with pytest.raises(CalibrationError, match=message):
        procrustes_rotation(a, b)
