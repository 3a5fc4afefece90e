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
    """Readings quantized to 40 nT are calibrated; the same array is then filled in place with the
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


def _record(n=400, seed=3):
    return magcal.simulate_timeseries("chi2017", n_samples=n, seed=seed)


def test_the_same_mask_gives_the_same_masked_dataset_while_it_is_held():
    import gc
    import pickle

    ds = _record()
    mask = np.ones(ds.n_samples, bool)
    mask[::7] = False
    kept = ds.masked(mask)
    assert kept.n_samples == mask.sum()
    np.testing.assert_array_equal(kept.readings_nT, ds.readings_nT[:, mask])
    np.testing.assert_array_equal(kept.time_s, ds.time_s[mask])
    assert ds.masked(mask.copy()) is kept  # equal masks, not the same array
    other = mask.copy()
    other[1] = False
    assert ds.masked(other) is not kept and ds.masked(other).n_samples == kept.n_samples - 1
    assert _record().masked(mask) is not kept  # another dataset with the same values
    assert ds.masked(np.ones(ds.n_samples, bool)) is ds
    assert pickle.loads(pickle.dumps(kept)).n_samples == kept.n_samples  # travels alone, without its parent
    del kept
    gc.collect()
    again = ds.masked(mask)  # nothing held it: made anew (the cache itself holds none)
    np.testing.assert_array_equal(again.readings_nT, ds.readings_nT[:, mask])
    assert ds.masked(mask) is again


@pytest.mark.parametrize("shape", [(3,), (400, 1)])
def test_a_mask_of_the_wrong_shape_is_refused(shape):
    from magcal.data.dataset import DatasetError

    with pytest.raises(DatasetError, match="mask has shape"):
        _record().masked(np.ones(shape, bool))


def test_a_record_with_rejected_samples_is_scanned_once_per_sample_set(monkeypatch):
    """The diagnosis of a record with rejected samples fits the same kept samples many times; each fit used to cut
    them anew, so what is computed from the readings alone (a bias step's scan) was computed again for every fit.
    Now it is computed as often as for the whole record."""
    from magcal.data.simulation import chi2017_truth, simulate_timeseries
    from magcal.diagnosis import _parallel, diagnose
    from magcal.model import effects, perturbations

    ds = simulate_timeseries(
        chi2017_truth(1),
        n_samples=3000,
        noise_nT=3.0,
        seed=5,
        perturbations=[perturbations.parse_hidden("bias_step=40", 1)],  # refitted: its refit scans again
    )
    counts = {}
    now = ["whole"]
    real = effects._step_scan

    def counting(*args):
        counts[now[0]] = counts.get(now[0], 0) + 1
        return real(*args)

    monkeypatch.setattr(effects, "_step_scan", counting)
    monkeypatch.setattr(_parallel, "PARALLEL_FITS", 1)
    mask = np.ones(ds.n_samples, bool)
    mask[::50] = False
    for now[0], m in (("whole", None), ("rejected", mask)):
        effects._READINGS_CACHE.clear()
        d = diagnose(ds, magcal.calibrate(ds, mask=m), workers=1)
        assert any(c.effect == "bias_step" and c.refitted for c in d.candidates)
    assert counts["whole"] >= 1 and counts["rejected"] == counts["whole"]
