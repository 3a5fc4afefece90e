"""magcal.data.dataset: a dataset's arrays are read-only and its own, so what is computed from them never goes stale."""

from __future__ import annotations

import numpy as np
import pytest

import magcal
from magcal.data.dataset import Dataset

SIGMA_nT = 3.0


def _quantized_and_continuous(seed=4, step_nT=40.0, n_samples=3000):
    """The same record twice: readings on a 40 nT grid, and the continuous readings they were rounded from."""
    ds = magcal.simulate_timeseries("chi2017", n_samples=n_samples, seed=seed, rate_hz=10.0)
    continuous = ds.readings_nT[0].copy()
    return np.round(continuous / step_nT) * step_nT, continuous


@pytest.mark.parametrize("attr", ["readings_nT", "time_s", "temperature_C"])
def test_a_dataset_keeps_its_own_read_only_arrays(attr):
    n = 50
    given = {
        "readings_nT": np.random.default_rng(0).normal(size=(1, n, 3)),
        "time_s": np.arange(n, dtype=float),
        "temperature_C": np.linspace(10.0, 20.0, n),
    }
    ds = Dataset(**given)
    kept = getattr(ds, attr)
    assert not kept.flags.writeable
    before = kept.copy()
    given[attr][...] = -7.0  # the caller changes their array in place
    np.testing.assert_array_equal(getattr(ds, attr), before)
    with pytest.raises(ValueError, match="read-only"):
        kept[...] = 0.0


def test_a_read_only_array_is_not_copied_and_a_subset_is_read_only():
    readings = np.random.default_rng(1).normal(size=(2, 40, 3))
    readings.flags.writeable = False
    ds = Dataset(readings)
    assert np.shares_memory(ds.readings_nT, readings)
    part = ds.subset(np.arange(40) % 2 == 0)
    assert not part.readings_nT.flags.writeable and part.n_samples == 20


def test_an_array_changed_in_place_after_a_calibration_is_calibrated_afresh():
    """Issue 27: readings quantized to 40 nT are calibrated; the same array is then filled in place with the
    continuous readings and calibrated again. The second floor must be the continuous record's (~3 nT), not the
    first record's quantization floor kept by a cache keyed on the array's memory."""
    quantized, continuous = _quantized_and_continuous()
    array = quantized.copy()
    first = magcal.calibrate(array, reference_total_nT=None)
    array[...] = continuous
    second = magcal.calibrate(array, reference_total_nT=None)
    fresh = magcal.calibrate(continuous.copy(), reference_total_nT=None)
    assert first.noise_nT > 2 * SIGMA_nT  # 40 nT steps: the floor is the quantization's, ~11.5 nT
    assert second.noise_nT == pytest.approx(fresh.noise_nT, rel=1e-9)
    assert second.noise_nT == pytest.approx(SIGMA_nT, rel=0.15)
