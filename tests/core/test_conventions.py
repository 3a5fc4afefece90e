"""The seed's conventions: round trips and the published tables of Chi et al. (2017)."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from magcal.core import conventions
from magcal.data.simulation import chi2017_truth

# Chi et al. (2017) Table 2, as printed (the calibrated matrices of their simulation; R for sensors 2-4).
TABLE2_CINV = [
    [[0.9877, -0.0212, 0.0213], [0, 1.0092, -0.0169], [0, 0, 0.9931]],
    [[0.9884, -0.0187, -0.015], [0, 0.9853, -0.0131], [0, 0, 1.014]],
    [[0.9817, -0.0247, -0.0127], [0, 0.9893, 0.0183], [0, 0, 1.0183]],
    [[0.9858, -0.0179, 0.0272], [0, 0.9922, 0.0157], [0, 0, 0.9794]],
]
TABLE2_R = [
    [[0.9994, 0.023, 0.0274], [-0.0223, 0.9994, -0.0257], [-0.028, 0.025, 0.9993]],
    [[0.9993, -0.021, 0.0304], [0.0202, 0.9994, 0.0266], [-0.031, -0.026, 0.9992]],
    [[0.9987, 0.038, 0.035], [-0.0389, 0.9989, 0.0266], [-0.034, -0.028, 0.999]],
]


@pytest.mark.parametrize("angles", [(0.0, 0.0, 0.0), (-0.023, 0.025, 0.028), (0.3, -0.4, 0.5), (2.0, 1.2, -2.5)])
def test_misalignment_angles_round_trip(angles):
    m = conventions.misalignment_matrix(*angles)
    assert np.allclose(m @ m.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(m) == pytest.approx(1.0, abs=1e-12)
    assert np.allclose(conventions.misalignment_angles(m), angles, atol=1e-12)


def test_misalignment_matrix_is_the_printed_product():
    # eq. (3) written out: R1(gamma) about y, R2(beta) about x, R3(alpha) about z, each as printed.
    a, b, g = 0.1, -0.2, 0.3
    r1 = np.array([[np.cos(g), 0, -np.sin(g)], [0, 1, 0], [np.sin(g), 0, np.cos(g)]])
    r2 = np.array([[1, 0, 0], [0, np.cos(b), np.sin(b)], [0, -np.sin(b), np.cos(b)]])
    r3 = np.array([[np.cos(a), np.sin(a), 0], [-np.sin(a), np.cos(a), 0], [0, 0, 1]])
    assert np.allclose(conventions.misalignment_matrix(a, b, g), r1 @ r2 @ r3, atol=1e-15)


@pytest.mark.parametrize("sensor", [1, 2, 3])
def test_table2_R_is_the_transpose_of_table1_misalignment(sensor):
    s = chi2017_truth().sensors[sensor]
    r = conventions.misalignment_matrix(s.alpha, s.beta, s.gamma).T
    # Table 2 is a fit to noisy data printed to 4 decimals: agreement to a few 1e-4.
    assert np.max(np.abs(r - np.array(TABLE2_R[sensor - 1]))) < 2e-4


@pytest.mark.parametrize("sensor", [0, 1, 2, 3])
def test_table2_cinv_is_the_inverse_of_table1_errors(sensor):
    s = chi2017_truth().sensors[sensor]
    cinv = np.linalg.inv(conventions.sensor_matrix(s.scale, s.psi, s.phi, s.theta))
    printed = np.array(TABLE2_CINV[sensor])
    diff = np.abs(cinv - printed)
    if sensor == 0:
        # Sensor 1's entry (1,2) is printed -0.0212; the exact inverse is -0.0242 (a misprint).
        assert cinv[0, 1] == pytest.approx(-0.0242, abs=1e-4)
        diff[0, 1] = 0.0
    assert np.max(diff) < 3e-4
    assert np.allclose(np.tril(cinv, -1), 0.0)
    assert np.all(np.diag(cinv) > 0)


@pytest.mark.parametrize(
    "scale,psi,phi,theta",
    [
        ((1.0, 1.0, 1.0), 0.0, 0.0, 0.0),
        ((1.013, 0.991, 1.007), 0.017, 0.024, -0.021),
        ((0.9, 1.1, 1.05), -0.05, 0.03, 0.04),
    ],
)
def test_gauge_free_recovers_scale_and_axis_angles(scale, psi, phi, theta):
    c = conventions.sensor_matrix(scale, psi, phi, theta)
    # Rows of C are the sensing axes (times their sensitivity): compute the expected figures directly.
    rows = c / np.linalg.norm(c, axis=1, keepdims=True)
    expected_angles = [np.degrees(np.arccos(rows[i] @ rows[j])) for i, j in ((0, 1), (0, 2), (1, 2))]
    cinv = np.linalg.inv(c)
    for gauge in (np.eye(3), Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()):
        k, angles = conventions.gauge_free(gauge @ cinv)  # any rotation of C^-1 gives the same figures
        assert np.allclose(k, scale, atol=1e-12)
        assert np.allclose(angles, expected_angles, atol=1e-9)


def test_x_axis_angles_follow_eq2():
    # The real x axis makes angle theta with the ideal x-y plane and its projection angle phi with x.
    psi, phi, theta = 0.02, 0.03, -0.04
    k, angles = conventions.gauge_free(np.linalg.inv(conventions.sensor_matrix((1, 1, 1), psi, phi, theta)))
    assert angles[1] == pytest.approx(90.0 - np.degrees(theta), abs=1e-9)  # x-z: z is the reference axis
    assert angles[2] == pytest.approx(90.0 - np.degrees(psi), abs=1e-9)  # y-z


def test_cholesky_gives_upper_triangular_inverse():
    s = chi2017_truth().sensors[2]
    a = s.Cinv.T @ s.Cinv
    assert np.allclose(conventions.cinv_from_quadric(a), s.Cinv, atol=1e-12)
    assert np.allclose(conventions.params_to_cinv(conventions.cinv_to_params(s.Cinv)), s.Cinv)


@pytest.mark.parametrize("d", [0.5, 1.2])
def test_tensor_of_a_linear_field(d):
    # Field B(p) = B0 + G p with a symmetric, traceless G (a source-free field): eq. (1) must return G.
    rng = np.random.default_rng(4)
    g = rng.normal(0, 200, (3, 3))
    g = 0.5 * (g + g.T)
    g -= np.trace(g) / 3 * np.eye(3)
    b0 = rng.normal(0, 3e4, (5, 3))
    pos = conventions.sensor_positions(d)
    assert np.allclose(pos, [[d / 2, 0, 0], [0, d / 2, 0], [-d / 2, 0, 0], [0, -d / 2, 0]])
    vectors = np.stack([b0 + g @ p for p in pos])
    comp = conventions.tensor_components(vectors, d)
    expected = {
        "Gxx": g[0, 0],
        "Gxy": g[0, 1],
        "Gxz": g[0, 2],
        "Gyx": g[1, 0],
        "Gyy": g[1, 1],
        "Gyz": g[1, 2],
        "Gzz": g[2, 2],
    }
    # Eq. (1) reads column j of G from sensors displaced along j: Gxy = dBx/dy, Gyx = dBy/dx.
    for name, value in expected.items():
        assert np.allclose(comp[name], value, atol=1e-9), name
    assert np.allclose(conventions.tensor_matrix(comp), g, atol=1e-9)


def test_tensor_floor():
    floor = conventions.tensor_floor_nT_per_m(3.0, 0.5)
    assert floor["Gxx"] == pytest.approx(np.sqrt(2) * 6.0)
    assert floor["Gzz"] == pytest.approx(12.0)
    assert conventions.total_field_floor_nT(3.0, 200) == pytest.approx(3.0 * np.sqrt(1 - 9 / 200))
