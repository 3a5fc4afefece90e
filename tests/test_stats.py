"""magcal.core.stats and the diagnosis's FFT periodogram: the same numbers as scipy.signal, which the engine no
longer loads (it is half a second of every command's start)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import periodogram, savgol_filter

from magcal.core.stats import robust_sigma, savgol, savgol_derivative
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
