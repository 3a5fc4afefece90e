"""The simulator: presets, reproducibility, noise levels and the time-series trajectory."""

import numpy as np
import pytest

from magcal.core import conventions
from magcal.data.simulation import PRESETS, chi2017_truth, noise_sigma, simulate, simulate_timeseries, true_fields


def test_seeded_and_reproducible():
    a = simulate("chi2017", seed=5)
    b = simulate("chi2017", seed=5)
    c = simulate("chi2017", seed=6)
    assert np.array_equal(a.readings_nT, b.readings_nT)
    assert not np.allclose(a.readings_nT, c.readings_nT)


def test_chi2017_preset_matches_the_paper_setup():
    ds = simulate("chi2017", seed=0)
    assert ds.n_sensors == 4 and ds.n_samples == 200
    assert ds.reference_total_nT == 50_000.0 and ds.baseline_m == 0.5 and ds.noise_nT == 3.0
    truth = PRESETS["chi2017"].truth()
    # noise-free readings lie on the ellipsoid |C^-1 (y - b)| = F
    clean = simulate(truth, n_samples=50, noise_nT=0.0, seed=1)
    for s, sensor in enumerate(truth.sensors):
        mag = np.linalg.norm((clean.readings_nT[s] - sensor.bias_nT) @ sensor.Cinv.T, axis=1)
        assert np.allclose(mag, 50_000.0)


@pytest.mark.parametrize("kind, width, sigma", [("gaussian", 3.0, 3.0), ("uniform", 10.0, 10 / np.sqrt(12))])
def test_noise_level(kind, width, sigma):
    truth = chi2017_truth()
    noisy = simulate(truth, n_samples=4000, noise_nT=width, noise_kind=kind, seed=2)
    clean = simulate(truth, n_samples=4000, noise_nT=0.0, noise_kind=kind, seed=2)
    # same seed draws the same attitudes first, so the difference is the noise
    diff = noisy.readings_nT - clean.readings_nT
    assert noise_sigma(width, kind) == pytest.approx(sigma)
    assert diff.std() == pytest.approx(sigma, rel=0.03)
    if kind == "uniform":
        assert np.abs(diff).max() <= width / 2


def test_misalignment_seen_between_sensors():
    truth = chi2017_truth()
    from scipy.spatial.transform import Rotation

    att = Rotation.random(10, random_state=1)
    fields = true_fields(truth, att)
    for s in range(1, 4):
        assert np.allclose(fields[s] @ truth.sensors[s].R.T, fields[0])


def test_timeseries_channels_and_coverage():
    ds = simulate_timeseries("chi2017", n_samples=1500, seed=3)
    assert ds.has("time") and ds.has("temperature") and ds.has("attitude")
    assert np.all(np.diff(ds.time_s) > 0)
    # temperature is not a monotonic function of time
    assert np.any(np.diff(ds.temperature_C) > 0) and np.any(np.diff(ds.temperature_C) < 0)
    # the field direction covers the sphere: every octant visited
    truth = chi2017_truth()
    u = (ds.readings_nT[0] - truth.sensors[0].bias_nT) @ truth.sensors[0].Cinv.T
    octants = {tuple(v) for v in (u > 0).astype(int)}
    assert len(octants) == 8
    # the trajectory is smooth: successive directions differ by a few degrees at most
    un = u / np.linalg.norm(u, axis=1, keepdims=True)
    steps = np.degrees(np.arccos(np.clip(np.sum(un[1:] * un[:-1], axis=1), -1, 1)))
    assert np.percentile(steps, 99) < 10


def test_perturbations_apply_before_noise():
    offset = np.array([10.0, -5.0, 2.0])

    def add_offset(readings, context, rng):
        assert set(context) >= {"fields_nT", "time_s", "temperature_C", "attitudes", "truth", "positions_m"}
        return readings + offset

    a = simulate_timeseries("chi2017", n_samples=200, noise_nT=0.0, seed=4)
    b = simulate_timeseries("chi2017", n_samples=200, noise_nT=0.0, seed=4, perturbations=[add_offset])
    assert np.allclose(b.readings_nT - a.readings_nT, offset)


def test_unknown_preset_is_named():
    with pytest.raises(ValueError, match="known presets"):
        simulate("nope")


def test_positions_follow_the_cross():
    pos = conventions.sensor_positions(0.5)
    assert np.allclose(pos[0], [0.25, 0, 0]) and np.allclose(pos[1], [0, 0.25, 0])
    assert np.linalg.norm(pos[0] - pos[2]) == pytest.approx(0.5)
