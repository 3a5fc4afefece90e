"""A temperature term is not advised for new data when the record's temperature follows time.

On such a record a temperature term fits a drift as well as a temperature effect, and a calibration carries its
slope to temperatures the record never had: on a real bench recording (cl_imu_gnss, temperature r = 0.999 with
time) a temperature bias advised on the first half tripled the error on the second.
"""

from __future__ import annotations

import numpy as np
import pytest

import magcal
from magcal.data.simulation import chi2017_truth, simulate_timeseries

SLOPE_nT = np.array([2.0, -1.5, 1.0])  # sensor 1's bias change per K (or per tenth of the record), nT


def _record(temperature, hidden, seed=3):
    """A four-sensor record whose sensor 1 carries a bias that moves with the temperature (``temperature_bias``) or
    with time (``bias_drift``); the temperature either rises steadily with time (``ramp``) or wanders on its own
    (the simulator's)."""
    ds = simulate_timeseries(chi2017_truth(1), n_samples=3000, noise_nT=3.0, seed=seed)
    t = ds.time_s
    temp = 20.0 + 10.0 * (t - t[0]) / (t[-1] - t[0]) if temperature == "ramp" else ds.temperature_C
    driver = temp - temp.mean() if hidden == "temperature_bias" else 10.0 * (t - t.mean()) / (t[-1] - t[0])
    readings = ds.readings_nT.copy()
    readings[0] += np.outer(driver, 3.0 * SLOPE_nT)
    return ds.replace(readings_nT=readings, temperature_C=temp)


@pytest.mark.parametrize("hidden", ["temperature_bias", "bias_drift"])
def test_on_a_record_whose_temperature_follows_time_no_temperature_term_is_advised(hidden):
    """Whether the truth is a temperature bias or a drift, the record cannot tell them apart (the two records are the
    same numbers): a temperature term is named as what this record holds (with why), never as advice for new data."""
    ds = _record("ramp", hidden)
    assert abs(np.corrcoef(ds.temperature_C, ds.time_s)[0, 1]) > 0.99
    d = magcal.diagnose(ds, magcal.calibrate(ds, warn=False), warn=False)
    assert not any(label.startswith("temperature") for label in d.explained_by + d.partially_explained_by)
    for c in d.candidates:
        if c.effect.startswith("temperature") and c.holds:
            assert c.transfers is False and "follows time" in c.confounded
    judged = [c for c in d.candidates if c.effect == "temperature_bias" and c.holds is not None]
    assert judged and judged[0].holds  # the term describes this record (as well as a drift does) ...
    assert judged[0].transfers is False  # ... but is not advice for new data
    chosen = [label for label in d.record_holds if label.startswith("temperature")]
    if chosen:
        assert "follows time" in d.summary


@pytest.mark.parametrize("hidden", ["temperature_bias"])
def test_a_temperature_effect_with_its_own_temperature_is_still_advised(hidden):
    ds = _record("own", hidden)
    assert abs(np.corrcoef(ds.temperature_C, ds.time_s)[0, 1]) < 0.9
    d = magcal.diagnose(ds, magcal.calibrate(ds, warn=False), warn=False)
    assert hidden in d.explained_by
    assert all(not c.confounded for c in d.candidates)
