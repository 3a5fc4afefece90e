"""The diagnosis of a record with a time range excluded (Diagnose after the workbench's Exclude range).

An excluded stretch leaves the kept stamps a regular grid with a hole. The spectrum then needs the Lomb-Scargle
periodogram, whose direct sums cost ``N x N/2`` products (minutes at 4 x 1e5 samples, against seconds for the
same diagnosis without the hole). These tests check that such stamps take two FFTs of their grid (the same values
as scipy's periodogram), that other irregular stamps take a few FFTs of a grid no larger than a few points per
frequency, and that the diagnosis of a masked record still finds the effect hidden in it.
"""

import numpy as np
import pytest
from scipy.signal import lombscargle

from magcal.data.simulation import chi2017_truth, simulate_timeseries
from magcal.diagnosis import diagnose
from magcal.diagnosis import statistics as st
from magcal.fitting import pipeline
from magcal.model import perturbations
from magcal.model.terms import EFFECTS

SIGMA = 3.0
N = 1500
#: The catalogue without its periodic interference term: hidden interference is then an effect outside it.
OUTSIDE = [n for n in EFFECTS if n != "periodic_interference"]


def _excluded(n, start=0.4, stop=0.55):
    """What the workbench's Exclude range leaves kept: every sample but those from ``start`` to ``stop`` of the
    record."""
    keep = np.ones(n, bool)
    keep[int(start * n) : int(stop * n)] = False
    return keep


@pytest.fixture
def transforms(monkeypatch):
    """Records the grid transforms of the Lomb-Scargle sums (``statistics._grid_sums``): their sizes, in order; and
    the periodograms asked for (``lomb_scargle_grid``): their samples and frequencies."""
    seen = {"cells": [], "spectra": []}
    grid_sums, periodogram = st._grid_sums, st.lomb_scargle_grid

    def counted_sums(index, weights, cells):
        seen["cells"].append(int(cells))
        return grid_sums(index, weights, cells)

    def counted_periodogram(time_s, r, df_hz, n_freq):
        seen["spectra"].append((len(time_s), int(n_freq)))
        return periodogram(time_s, r, df_hz, n_freq)

    monkeypatch.setattr(st, "_grid_sums", counted_sums)
    monkeypatch.setattr(st, "lomb_scargle_grid", counted_periodogram)
    return seen


def _scipys(t, r):
    """The spectrum's frequencies (``k / T``) and scipy's periodogram there."""
    freq = np.arange(1, t.size // 2 + 1) / (t.max() - t.min())
    return freq, lombscargle(t - t.min(), r, 2 * np.pi * freq)


def test_stamp_grid_finds_the_grid_of_a_record_with_holes():
    t = 12.5 + 0.01 * np.arange(5000)
    keep = _excluded(t.size)
    keep[::7] = False  # single samples left out as well (rejected outliers)
    m = st.stamp_grid(t[keep])
    np.testing.assert_array_equal(m, np.flatnonzero(keep) - np.flatnonzero(keep)[0])
    # stamps written in whole milliseconds at 75 Hz (intervals of 13 and 14 ms) are on their grid of 1/75 s
    ms = np.round(np.arange(6000) / 75.0, 3)
    np.testing.assert_array_equal(st.stamp_grid(ms[_excluded(ms.size)]), np.flatnonzero(_excluded(ms.size)))
    rng = np.random.default_rng(0)
    assert st.stamp_grid(t + rng.uniform(-0.004, 0.004, t.size)) is None  # jitter of 0.4 of the step
    assert st.stamp_grid(t[::-1]) is None  # not increasing
    assert st.stamp_grid(np.r_[t[:10], t[-1] + 1e3]) is None  # ten samples on a grid of 1e5 points


@pytest.mark.parametrize("holes", ["range", "range and outliers"])
def test_lomb_scargle_on_a_grid_with_holes_is_two_ffts_of_the_grid(holes, transforms):
    rng = np.random.default_rng(3)
    t = 0.1 * np.arange(6000)
    keep = _excluded(t.size)
    if holes == "range and outliers":
        keep &= rng.random(t.size) > 0.05
    t = t[keep]
    r = 5.0 * np.sin(2 * np.pi * 0.37 * t + 0.2) + rng.normal(0, 3.0, t.size)
    r -= r.mean()
    freq, expected = _scipys(t, r)
    got = st.lomb_scargle_grid(t, r, freq[0], freq.size)
    np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-12 * expected.max())
    assert transforms["cells"] == [5999, 5999]  # the record's own grid, once for r and once for the weights
    # the order of the samples does not matter
    order = rng.permutation(t.size)
    np.testing.assert_allclose(st.lomb_scargle_grid(t[order], r[order], freq[0], freq.size), got, rtol=1e-9)
    spec = st.spectrum(r, t)
    assert spec["method"] == "lomb-scargle" and abs(spec["peak_hz"] - 0.37) <= freq[0]


@pytest.mark.parametrize("stamps", ["whole milliseconds, a range excluded", "random", "batched"])
def test_lomb_scargle_of_other_stamps_is_scipys_from_a_few_ffts(stamps, transforms):
    rng = np.random.default_rng(4)
    if stamps == "random":
        t = np.cumsum(rng.exponential(1 / 50.0, 4000))
    elif stamps == "batched":  # host arrival times: bursts of 4 samples 2 ms apart
        t = np.sort(np.concatenate([0.05 * np.arange(1000) + 0.002 * j for j in range(4)]))
    else:
        t = np.round(np.arange(4000) / 75.0, 3)[_excluded(4000)]
    r = np.sin(2 * np.pi * 1.3 * t) + rng.normal(0, 1, t.size)
    r -= r.mean()
    freq, expected = _scipys(t, r)
    got = st.lomb_scargle_grid(t, r, freq[0], freq.size)
    np.testing.assert_allclose(got, expected, rtol=1e-8, atol=1e-12 * expected.max())
    # a few transforms, each of the stamps' own grid (at most GRID_MAX_FILL points per stamp: the batches' 2 ms) or
    # of GRID_PER_FREQUENCY points per frequency, where the direct sums were N x n_freq products
    assert 2 <= len(transforms["cells"]) <= 2 * 20
    largest = max(st.GRID_MAX_FILL * t.size, 1.25 * st.GRID_PER_FREQUENCY * freq.size)
    assert max(transforms["cells"]) <= largest
    if stamps != "random":  # on their own grid: fewer terms
        assert len(transforms["cells"]) <= 2 * 12


def test_masked_diagnosis_finds_the_hidden_interference_from_two_ffts_per_spectrum(transforms):
    """Periodic interference (outside the catalogue) at 0.23 Hz on sensor 3, a time range excluded: the
    spectrum of the kept samples still names the period, each from two FFTs of the record's grid."""
    ds = simulate_timeseries(
        chi2017_truth(4),
        n_samples=N,
        noise_nT=SIGMA,
        seed=3,
        perturbations=[perturbations.periodic_interference(8.0, 0.23, 2)],
    )
    keep = _excluded(N)
    fit = pipeline.calibrate(ds, mask=keep).fit
    assert int(fit.mask.sum()) == int(keep.sum())
    d = diagnose(ds, fit, candidates=OUTSIDE)
    assert d.verdict == "unexplained", d.summary
    assert d.explained_by == []
    periodic = [s for s in d.structure if s.kind == "periodic"]
    assert any(abs(float(s.text.split(" at ")[1].split()[0]) - 0.23) < 0.1 for s in periodic), d.structure
    # every spectrum of the kept samples (per sensor, for the structure and for the evidence) from their grid
    kept = int(keep.sum())
    assert len(transforms["spectra"]) >= 4 and all(n == kept for n, _ in transforms["spectra"])
    assert transforms["cells"] == [N - 1] * (2 * len(transforms["spectra"]))


@pytest.mark.parametrize("name, sensor", [("temperature_bias", 2), ("sensor_timing_skew", None)])
def test_masked_diagnosis_ranks_the_hidden_effect_first_as_without_the_mask(name, sensor, transforms):
    magnitude = EFFECTS[name].default_magnitude * 3.0
    spec = name if sensor is None else f"{name}:{sensor + 1}"
    pert = perturbations.parse_hidden(f"{spec}={magnitude}", 4)
    ds = simulate_timeseries(chi2017_truth(4), n_samples=N, noise_nT=SIGMA, seed=1, perturbations=[pert])
    whole = diagnose(ds)
    masked = diagnose(ds, pipeline.calibrate(ds, mask=_excluded(N)).fit)
    for d in (whole, masked):
        best = d.candidates[0]
        assert d.verdict == "missing_effect", d.summary
        assert best.effect == name, [(c.label, round(c.delta_bic)) for c in d.candidates[:4]]
        if sensor is not None:
            assert best.sensor == sensor
        assert best.refitted and best.delta_bic < -10
    assert masked.explained_by == whole.explained_by
    assert len(transforms["cells"]) == 2 * len(transforms["spectra"])  # the whole record's spectra: no transform


def test_lomb_scargle_of_a_missing_stamp_is_no_value():
    t = np.r_[0.1 * np.arange(100), np.nan]
    power = st.lomb_scargle_grid(t, np.ones(t.size), 0.1, 50)
    assert power.shape == (50,) and np.all(np.isnan(power))
