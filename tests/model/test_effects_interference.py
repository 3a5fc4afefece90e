"""The periodic_interference effect: a sinusoidal field from a source on the platform, found in the residual
spectrum, fitted, judged on held-out data, saved and refused when non-physical."""

import json

import numpy as np
import pytest

import magcal.model.effects as fx
from magcal import calibrate, diagnose
from magcal.calibration.calibration import Calibration
from magcal.core.errors import MagcalError
from magcal.data.simulation import chi2017_truth, simulate_timeseries
from magcal.fitting.fitter import fit
from magcal.model import perturbations
from magcal.model.terms import EFFECTS, Model

SIGMA = 3.0
N = 1500
DIRECTION = np.array([0.6, -0.5, 0.62]) / np.linalg.norm([0.6, -0.5, 0.62])  # the perturbation's default


def _hum(amplitude_nT, frequency_hz, sensor=None, n_sensors=1, seed=3, harmonic_fraction=0.0, n=N):
    return simulate_timeseries(
        chi2017_truth(n_sensors),
        n_samples=n,
        noise_nT=SIGMA,
        seed=seed,
        perturbations=[
            perturbations.periodic_interference(amplitude_nT, frequency_hz, sensor, harmonic_fraction=harmonic_fraction)
        ],
    )


def _peaks(params, harmonic=1):
    """Peak amplitude per axis (nT) of one harmonic from fitted sin/cos parameters."""
    k = "" if harmonic == 1 else str(harmonic)
    return np.array([np.hypot(params[f"sin{k}_{a}_nT"], params[f"cos{k}_{a}_nT"]) for a in "xyz"])


@pytest.mark.parametrize(
    "frequency_hz, n_sensors, sensor", [(0.7, 1, None), (2.1, 1, None), (0.23, 4, 2), (4.37, 1, None)]
)
def test_diagnose_finds_the_interference_and_adding_it_reaches_the_floor(frequency_hz, n_sensors, sensor):
    """Before the term existed this read `unexplained` (a periodic component no catalogue term removed)."""
    d = diagnose(_hum(8.0, frequency_hz, sensor, n_sensors))
    label = "periodic_interference" if sensor is None else f"periodic_interference:{sensor + 1}"
    assert d.verdict == "missing_effect" and d.record_holds == [label], d.summary  # record-only
    assert "switch it off or move away from it while recording" in d.summary
    best = d.candidates[0]
    assert best.label == label and best.refitted and best.delta_bic < -100 and best.holds
    assert d.fits[label].rms_nT <= 1.02 * d.floor_nT
    fitted = d.fits[label].calibration.model.effects[-1]
    f = fitted.frequency_hz[sensor or 0]
    duration = N / 10.0
    assert abs(f - frequency_hz) < 0.05 / duration, f  # within a twentieth of a cycle per record
    assert np.allclose(_peaks(best.params[label]), 8.0 * np.abs(DIRECTION), atol=0.6)


def test_the_frequency_is_found_where_the_time_has_gaps():
    """Held-out validation fits alternating blocks: the spectrum then places the samples on their grid."""
    ds = _hum(8.0, 0.7)
    keep = (np.arange(N) // 100) % 2 == 0
    result = fit(ds, Model.from_names(["periodic_interference"], 1), mask=keep)
    assert abs(result.calibration.model.effects[0].frequency_hz[0] - 0.7) < 0.005
    assert result.rms_nT < 1.05 * SIGMA


def test_irregular_time_stamps_use_the_direct_sum():
    ds = _hum(8.0, 0.7)
    rng = np.random.default_rng(1)
    jittered = ds.replace(time_s=ds.time_s + rng.uniform(-0.002, 0.002, N))  # 2 % of the interval
    assert fx._sample_grid(jittered.time_s) == (None, None)
    r = fit(jittered).residuals_nT[0]
    f = fx.dominant_interference_hz(jittered.time_s, jittered.readings_nT[0], r)
    assert abs(f - 0.7) < 0.01


def test_a_harmonic_is_fitted_when_asked_for():
    ds = _hum(8.0, 0.7, harmonic_fraction=0.5)
    one = fit(ds, Model(1, effects=[EFFECTS["periodic_interference"]()]))
    two = fit(ds, Model(1, effects=[EFFECTS["periodic_interference"](harmonics=2)]))
    assert one.rms_nT > 1.1 * SIGMA and two.rms_nT < 1.03 * SIGMA
    params = two.effect_params[0]["params"]
    assert len(params) == 12 and "sin2_x_nT" in params
    assert np.allclose(_peaks(params, 2), 4.0 * np.abs(DIRECTION), atol=0.6)


def test_clean_data_do_not_support_it():
    ds = simulate_timeseries(chi2017_truth(1), n_samples=N, noise_nT=SIGMA, seed=11)
    d = diagnose(ds)
    c = next(c for c in d.candidates if c.effect == "periodic_interference")
    assert d.verdict == "adequate" and c.delta_bic > 0


def test_it_is_record_only_and_its_state_survives_a_file(tmp_path):
    ds = _hum(8.0, 0.7)
    result = calibrate(ds, effects=["periodic_interference"])
    path = tmp_path / "cal.json"
    result.calibration.save(path)
    doc = json.loads(path.read_text())
    entry = doc["effect_params"][0]
    assert entry["transferable"] is False
    assert entry["state"]["frequency_hz"][0] == pytest.approx(0.7, abs=0.005) and entry["state"]["harmonics"] == 1
    loaded = Calibration.load(path)
    assert loaded.model.effects[0].frequency_hz == result.calibration.model.effects[0].frequency_hz
    entry["state"]["frequency_hz"] = [-0.7]
    path.write_text(json.dumps(doc))
    with pytest.raises(MagcalError, match="frequency_hz of sensor 1 .* positive number of Hz"):
        Calibration.load(path)


@pytest.mark.parametrize("harmonics", [0, 6, 1.5, True])
def test_a_bad_number_of_harmonics_is_refused(harmonics):
    with pytest.raises(MagcalError, match="harmonics must be a whole number 1..5"):
        EFFECTS["periodic_interference"](harmonics=harmonics)


def test_the_report_quotes_the_frequency_and_the_peak():
    import re

    from magcal.calibration.report import text_report

    result = calibrate(_hum(8.0, 0.7), effects=["periodic_interference"])
    line = next(x for x in text_report(result).splitlines() if x.strip().startswith("peak ("))
    peaks = [float(v) for v in re.search(r"peak \(([^)]*)\) nT", line).group(1).split(",")]
    assert np.allclose(peaks, 8.0 * np.abs(DIRECTION), atol=0.6), line
    assert abs(float(re.search(r"at ([0-9.]+) Hz", line).group(1)) - 0.7) < 0.005, line
    assert re.search(r"ppm of the field 50 uT\)$", line), line
