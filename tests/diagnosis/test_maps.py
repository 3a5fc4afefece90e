"""Residual patterns on the direction sphere (magcal.diagnosis.maps) against known truth."""

from __future__ import annotations

import numpy as np
import pytest

import magcal
from magcal.diagnosis import (
    candidate_patterns,
    direction_pattern,
    pattern_correlation,
    real_sph_harm,
    residual_patterns,
)
from magcal.geometry.sphere import fibonacci_sphere

VERTS = fibonacci_sphere(400)


@pytest.mark.parametrize("degree", [1, 2, 3, 4])
def test_a_known_harmonic_is_recovered_where_the_samples_are(degree):
    rng = np.random.default_rng(degree)
    u = fibonacci_sphere(3000)
    truth = 5.0 * real_sph_harm(u, degree)[:, degree**2 + 1]  # one harmonic of that degree, a few nT
    p = direction_pattern(u, truth + rng.normal(0, 1.0, len(u)), VERTS)
    expect = 5.0 * real_sph_harm(VERTS, degree)[:, degree**2 + 1]
    assert p.supported.all() and p.max_degree >= degree
    assert np.corrcoef(p.value_nT, expect)[0, 1] > 0.97
    assert np.sqrt(np.mean((p.value_nT - expect) ** 2)) < 0.3


def test_unvisited_directions_are_not_supported_and_degrees_not_resolved_are_not_used():
    u = fibonacci_sphere(3000)
    ring = u[np.abs(u[:, 2]) < 0.05]  # one great circle: degree 1 and up are not all resolved
    p = direction_pattern(ring, ring[:, 0] * 3.0, VERTS)
    assert not p.supported[np.abs(VERTS[:, 2]) > 0.9].any()
    assert p.max_degree < 2


def _bent(seed=3):
    hidden = magcal.parse_hidden("nonlinearity_cubic:2=8", n_sensors=4)
    return magcal.simulate_timeseries("chi2017", n_samples=3000, seed=seed, perturbations=[hidden])


def test_the_map_of_a_hidden_nonlinearity_is_large_on_its_sensor_and_noise_elsewhere():
    ds = _bent()
    result = magcal.calibrate(ds)
    maps = residual_patterns(ds, result.calibration, result.fit.residuals_nT, VERTS)
    amp = [m.amplitude_nT for m in maps]
    assert amp[1] > 2.0 * max(amp[0], amp[2], amp[3])
    assert max(amp[0], amp[2], amp[3]) < 3.0  # noise 3 nT per axis, averaged over the sphere


def test_the_true_candidates_pattern_is_the_residual_map():
    ds = _bent()
    result = magcal.calibrate(ds)
    diagnosis = magcal.diagnose(ds, result)
    best = diagnosis.candidates[0]
    assert best.effect == "nonlinearity_cubic"
    residual = residual_patterns(ds, result.calibration, result.fit.residuals_nT, VERTS)
    explained = candidate_patterns(ds, diagnosis, best, VERTS)
    assert pattern_correlation(residual[1], explained[1]) > 0.9
    # and a candidate that does not fit explains little of it
    other = next(c for c in diagnosis.candidates if c.effect.startswith("temperature"))
    weak = candidate_patterns(ds, diagnosis, other, VERTS)
    assert weak[1].amplitude_nT < 0.5 * explained[1].amplitude_nT


def test_clean_data_map_at_the_noise_level():
    ds = magcal.simulate_timeseries("chi2017", n_samples=3000, seed=4)
    result = magcal.calibrate(ds)
    maps = residual_patterns(ds, result.calibration, result.fit.residuals_nT, VERTS)
    assert max(m.amplitude_nT for m in maps) < 3.0
