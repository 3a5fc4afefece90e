"""Calibration objects: apply, tensor, JSON round trip and refusals."""

import json

import numpy as np
import pytest

from magcal import conventions
from magcal.calibration import Calibration, SensorCalibration
from magcal.errors import MagcalError
from magcal.fit import fit
from magcal.simulation import chi2017_truth, simulate


def test_truth_calibration_corrects_to_the_field():
    truth = chi2017_truth()
    ds = simulate(truth, seed=1, noise_nT=0.0)
    cal = Calibration([SensorCalibration(s.Cinv, s.bias_nT, s.R) for s in truth.sensors], truth.total_nT,
                      baseline_m=truth.baseline_m)
    corrected = cal.correct(ds)
    assert np.allclose(np.linalg.norm(corrected, axis=2), truth.total_nT, atol=1e-6)
    assert np.allclose(corrected, corrected[0], atol=1e-6)  # every sensor agrees in the array frame
    tensor = cal.tensor(ds)
    assert set(tensor) == set(conventions.TENSOR_COMPONENTS)
    assert max(np.abs(v).max() for v in tensor.values()) < 1e-5


def test_json_round_trip(tmp_path):
    ds = simulate("chi2017", seed=2)
    result = fit(ds)
    path = tmp_path / "cal.json"
    result.calibration.save(path)
    doc = json.loads(path.read_text())
    assert doc["format"] == "magcal-calibration" and doc["version"] == 1
    assert len(doc["sensors"]) == 4 and doc["sensors"][0]["id"] == 1
    loaded = Calibration.load(path)
    assert np.allclose(loaded.correct(ds), result.calibration.correct(ds))
    assert loaded.baseline_m == pytest.approx(0.5)


@pytest.mark.parametrize(
    "doc, message",
    [
        ({"format": "other"}, "not a magcal calibration"),
        ({"format": "magcal-calibration", "version": 99, "sensors": []}, "version 99"),
        ({"format": "magcal-calibration", "version": 1, "sensors": [{"Cinv": "x"}]}, "damaged"),
    ],
)
def test_bad_files_are_refused_clearly(tmp_path, doc, message):
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(MagcalError, match=message):
        Calibration.load(path)


def test_wrong_sensor_count_is_refused():
    ds = simulate("chi2017", seed=3)
    cal = fit(ds.sensors([0])).calibration
    with pytest.raises(MagcalError, match="for 1 sensor"):
        cal.correct(ds)


def test_atomic_save_leaves_no_temporary_files(tmp_path):
    cal = fit(simulate("chi2017", seed=4).sensors([0])).calibration
    cal.save(tmp_path / "a.json")
    cal.save(tmp_path / "a.json")
    assert [p.name for p in tmp_path.iterdir()] == ["a.json"]
