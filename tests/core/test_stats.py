"""magcal.core.stats and the diagnosis's FFT periodogram: the same numbers as scipy.signal, which the engine no
longer loads (it is half a second of every command's start)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.signal import periodogram, savgol_filter

from magcal.core.stats import moving_mean, robust_sigma, savgol, savgol_derivative
from magcal.diagnosis.statistics import fft_periodogram


@pytest.mark.parametrize(
    "shape, window",
    [((50,), 11), ((200, 3), 21), ((31,), 31), ((31, 2, 3), 31), ((40, 2, 3), 29), ((5,), 5)],
)
def test_savgol_derivative_is_scipys_savgol_filter(shape, window):
    y = np.random.default_rng(sum(shape)).normal(size=shape).cumsum(axis=0)
    expected = savgol_filter(y, window, 3, deriv=1, delta=0.1, axis=0, mode="interp")
    np.testing.assert_allclose(savgol_derivative(y, window, 0.1), expected, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("shape, window", [((50,), 11), ((31, 2, 3), 31), ((200, 3), 51)])
def test_savgol_smoothing_is_scipys_savgol_filter(shape, window):
    y = np.random.default_rng(7 + sum(shape)).normal(size=shape).cumsum(axis=0)
    expected = savgol_filter(y, window, 3, axis=0, mode="interp")
    np.testing.assert_allclose(savgol(y, window), expected, rtol=1e-9, atol=1e-9)


def test_savgol_derivative_of_a_cubic_is_exact():
    t = np.arange(60) * 0.05
    y = 2.0 - 3.0 * t + 0.5 * t**2 - 0.25 * t**3  # nT; its derivative in nT/s
    np.testing.assert_allclose(savgol_derivative(y, 9, 0.05), -3.0 + t - 0.75 * t**2, atol=1e-9)


@pytest.mark.parametrize("window", [4, 1, 61])
def test_savgol_derivative_refuses_a_bad_window(window):
    with pytest.raises(ValueError, match="window"):
        savgol_derivative(np.zeros(60), window, 1.0)


@pytest.mark.parametrize("n, fs", [(7, 1.0), (8, 3.5), (101, 10.0), (256, 0.2)])
def test_fft_periodogram_is_scipys_periodogram(n, fs):
    r = np.random.default_rng(n).normal(size=n)
    freq, power = fft_periodogram(r, fs)
    f_ref, p_ref = periodogram(r, fs=fs, detrend=False)
    np.testing.assert_allclose(freq, f_ref, rtol=0, atol=1e-12)
    np.testing.assert_allclose(power, p_ref, rtol=1e-10, atol=1e-14)


def test_robust_sigma_of_gaussian_noise():
    assert robust_sigma(np.random.default_rng(3).normal(0.0, 3.0, 200_000)) == pytest.approx(3.0, rel=0.01)


def _moving_mean_by_hand(y, window):
    n = y.shape[-1]
    out = np.empty_like(y, dtype=float)
    for i in range(n):
        lo, hi = max(0, i - window // 2), min(n, i + (window - 1) // 2 + 1)
        out[..., i] = y[..., lo:hi].mean(axis=-1)
    return out


@settings(max_examples=60, deadline=None)
@given(n=st.integers(1, 300), window=st.integers(1, 400), seed=st.integers(0, 2**16))
def test_moving_mean_is_the_mean_of_each_window_cut_at_the_ends(n, window, seed):
    y = np.random.default_rng(seed).normal(10.0, 3.0, size=(2, n))
    np.testing.assert_allclose(moving_mean(y, window), _moving_mean_by_hand(y, window), rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("window", [1, 2, 5, 60])
def test_moving_mean_is_numpys_convolution_away_from_the_ends(window):
    y = np.random.default_rng(window).normal(size=1000)
    inside = slice(window, 1000 - window)
    np.testing.assert_allclose(
        moving_mean(y, window)[inside], np.convolve(y, np.ones(window) / window, mode="same")[inside], atol=1e-12
    )


def test_moving_mean_refuses_an_empty_window():
    with pytest.raises(ValueError, match="window"):
        moving_mean(np.ones(5), 0)
