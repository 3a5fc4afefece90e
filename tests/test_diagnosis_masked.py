"""The diagnosis of a record with a time range excluded (issue 44: Diagnose after the workbench's Exclude range).

An excluded stretch leaves the kept stamps a regular grid with a hole. The spectrum then needs the Lomb-Scargle
periodogram, whose direct sums cost ``N x N/2`` products (minutes at 4 x 1e5 samples, against seconds for the
same diagnosis without the hole). These tests check that such stamps take the FFT of their grid (the same values
as scipy's periodogram), that the direct sums are not computed at all in a masked diagnosis, and that the
diagnosis of a masked record still finds the effect hidden in it.
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
def direct_sums(monkeypatch):
    """Counts the direct (``O(N n_freq)``) Lomb-Scargle sums: a list of ``(samples, frequencies)`` per call."""
    calls = []
    direct = st._direct_terms

    def counted(t, r, df_hz, n_freq):
        calls.append((t.size, int(n_freq)))
        return direct(t, r, df_hz, n_freq)

    monkeypatch.setattr(st, "_direct_terms", counted)
    return calls


def test_stamp_grid_finds_the_grid_of_a_record_with_holes():
    t = 12.5 + 0.01 * np.arange(5000)
    keep = _excluded(t.size)
    keep[::7] = False  # single samples left out as well (rejected outliers)
    m = st.stamp_grid(t[keep])
    np.testing.assert_array_equal(m, np.flatnonzero(keep) - np.flatnonzero(keep)[0])
    # a stamp written with a few digits (0.01 s stamps rounded to 1e-6 s) is still on its grid
    assert st.stamp_grid(np.round(t[keep], 6)) is not None
    rng = np.random.default_rng(0)
    assert st.stamp_grid(t + rng.uniform(-0.002, 0.002, t.size)) is None  # jitter of a fifth of the step
    assert st.stamp_grid(t[::-1]) is None  # not increasing
    assert st.stamp_grid(np.r_[t[:10], t[-1] + 1e3]) is None  # ten samples on a grid of 1e5 points


@pytest.mark.parametrize("holes", ["range", "range and outliers"])
def test_lomb_scargle_on_a_grid_with_holes_is_scipys_without_the_direct_sums(holes, direct_sums):
    rng = np.random.default_rng(3)
    t = 0.1 * np.arange(6000)
    keep = _excluded(t.size)
    if holes == "range and outliers":
        keep &= rng.random(t.size) > 0.05
    t = t[keep]
    r = 5.0 * np.sin(2 * np.pi * 0.37 * t + 0.2) + rng.normal(0, 3.0, t.size)
    r -= r.mean()
    freq = np.arange(1, t.size // 2 + 1) / (t[-1] - t[0])  # the spectrum's grid: k / T
    expected = lombscargle(t, r, 2 * np.pi * freq)
    got = st.lomb_scargle_grid(t, r, freq[0], freq.size)
    np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-9 * expected.max())
    # the order of the samples does not matter
    order = rng.permutation(t.size)
    np.testing.assert_allclose(st.lomb_scargle_grid(t[order], r[order], freq[0], freq.size), got, rtol=1e-9)
    assert direct_sums == []
    spec = st.spectrum(r, t)
    assert spec["method"] == "lomb-scargle" and abs(spec["peak_hz"] - 0.37) <= freq[0]
    assert direct_sums == []


def test_jittered_stamps_keep_the_direct_sums(direct_sums):
    rng = np.random.default_rng(4)
    t = np.sort(rng.uniform(0, 40, 700))
    r = np.sin(2 * np.pi * 0.8 * t) + rng.normal(0, 1, t.size)
    r -= r.mean()
    freq = np.arange(1, 351) / (t[-1] - t[0])
    np.testing.assert_allclose(
        st.lomb_scargle_grid(t, r, freq[0], freq.size), lombscargle(t, r, 2 * np.pi * freq), rtol=1e-9, atol=1e-9
    )
    assert direct_sums == [(700, 350)]


def test_masked_diagnosis_finds_the_hidden_interference_without_the_direct_sums(direct_sums):
    """Periodic interference (outside the catalogue) at 0.23 Hz on sensor 3, a time range excluded: the
    spectrum of the kept samples still names the period, and computes no direct sum."""
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
    assert direct_sums == []  # every spectrum of the kept samples came from their grid


@pytest.mark.parametrize("name, sensor", [("temperature_bias", 2), ("sensor_timing_skew", None)])
def test_masked_diagnosis_ranks_the_hidden_effect_first_as_without_the_mask(name, sensor, direct_sums):
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
    assert direct_sums == []
