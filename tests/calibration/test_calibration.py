"""Calibration objects: apply, tensor, JSON round trip and refusals."""

import json
import warnings

import numpy as np
import pytest

from magcal.calibration.calibration import Calibration, SensorCalibration, is_transferable, record_fingerprint
from magcal.core import conventions
from magcal.core.errors import MagcalError, RecordTermWarning
from magcal.data.simulation import chi2017_truth, simulate, simulate_timeseries
from magcal.fitting.fitter import fit
from magcal.model.terms import EFFECTS, Model


def test_truth_calibration_corrects_to_the_field():
    truth = chi2017_truth()
    ds = simulate(truth, seed=1, noise_nT=0.0)
    cal = Calibration(
        [SensorCalibration(s.Cinv, s.bias_nT, s.R) for s in truth.sensors], truth.total_nT, baseline_m=truth.baseline_m
    )
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


# --- record-only terms (bias drift, reference drift...) act on the fitted record only -------------------------------
def _one_sensor():
    truth = chi2017_truth(1)
    return truth


def _record(hidden, seed):
    effect = EFFECTS[hidden]()
    return simulate_timeseries(
        _one_sensor(),
        n_samples=800,
        noise_nT=2.0,
        seed=seed,
        perturbations=[effect.perturbation(2 * effect.default_magnitude)],
    )


@pytest.fixture(scope="module", params=["bias_drift", "reference_drift"])
def drifting(request):
    """A calibration with one record-only term (and a transferable one) fitted on a record that has it, and
    another record of the same instrument (same duration and start time, another drift)."""
    name = request.param
    fitted = _record(name, seed=3)
    other = _record(name, seed=4)
    cal = fit(fitted, Model.from_names([name, "temperature_bias"], 1)).calibration.fitted_on(fitted)
    return name, cal, fitted, other


def _evaluate(cal, name, ds, **kwargs):
    """What the term changes: corrected vectors for a raw-stage term, the expected field for a reference one."""
    if EFFECTS[name].stage == "reference":
        return cal.expected_total_field(ds, **kwargs)
    return cal.correct(ds, **kwargs)


def test_the_four_record_terms_are_not_transferable():
    record = {n for n, cls in EFFECTS.items() if not is_transferable(cls)}
    assert {"bias_drift", "bias_step", "reference_drift", "site_gradient"} <= record
    assert is_transferable(EFFECTS["temperature_bias"]) and is_transferable(EFFECTS["hysteresis"])


def test_record_terms_act_silently_on_the_fitted_record(drifting):
    name, cal, fitted, other = drifting
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        default = _evaluate(cal, name, fitted)
        cal.total_field_residuals(fitted)
    np.testing.assert_array_equal(default, _evaluate(cal, name, fitted, record_terms="apply"))
    assert np.max(np.abs(default - _evaluate(cal, name, fitted, record_terms="drop"))) > 1.0  # the term acts


def test_record_terms_are_dropped_on_another_record_with_a_warning(drifting):
    name, cal, fitted, other = drifting
    with pytest.warns(RecordTermWarning) as caught:
        default = _evaluate(cal, name, other)
    text = str(caught[0].message)
    assert len(caught) == 1 and name in text and "temperature_bias" not in text  # only the record-only term
    assert "describe the recording" in text and "record_terms='apply'" in text and "800 samples" in text
    np.testing.assert_array_equal(default, _evaluate(cal, name, other, record_terms="drop"))
    assert np.max(np.abs(default - _evaluate(cal, name, other, record_terms="apply"))) > 1.0


@pytest.mark.parametrize("choice", ["apply", "drop"])
def test_an_explicit_choice_is_silent(drifting, choice):
    name, cal, fitted, other = drifting
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _evaluate(cal, name, other, record_terms=choice)


def test_residuals_warn_once_naming_the_terms(drifting):
    name, cal, fitted, other = drifting
    with pytest.warns(RecordTermWarning) as caught:
        cal.total_field_residuals(other)
    assert len(caught) == 1 and name in str(caught[0].message)


def test_a_term_that_does_not_change_the_vectors_is_not_reported_by_correct():
    ds = _record("reference_drift", seed=3)
    cal = fit(ds, Model.from_names(["reference_drift"], 1)).calibration.fitted_on(ds)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        cal.correct(_record("reference_drift", seed=4))  # the reference drift acts on the expected field only


def test_transferable_terms_apply_to_new_data_silently():
    ds = _record("temperature_bias", seed=3)
    cal = fit(ds, Model.from_names(["temperature_bias"], 1)).calibration.fitted_on(ds)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        cal.total_field_residuals(_record("temperature_bias", seed=4))


def test_a_bad_record_terms_choice_is_refused(drifting):
    name, cal, fitted, other = drifting
    with pytest.raises(MagcalError, match="record_terms must be 'apply' or 'drop'"):
        cal.correct(other, record_terms="keep")


def test_the_fingerprint_round_trips_through_json(drifting, tmp_path):
    name, cal, fitted, other = drifting
    path = tmp_path / "cal.json"
    cal.save(path)
    doc = json.loads(path.read_text())
    assert doc["record"] == record_fingerprint(fitted)
    assert doc["record"]["n_samples"] == 800 and doc["record"]["time_end_s"] == pytest.approx(79.9)
    loaded = Calibration.load(path)
    assert loaded.record == cal.record
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        np.testing.assert_allclose(_evaluate(loaded, name, fitted), _evaluate(cal, name, fitted), atol=1e-9)
    with pytest.warns(RecordTermWarning, match=name):
        loaded.total_field_residuals(other)


def test_the_fingerprint_tells_records_apart():
    a, b = _record("bias_drift", seed=3), _record("bias_drift", seed=4)
    assert record_fingerprint(a) == record_fingerprint(a.subset(np.arange(a.n_samples)))
    assert record_fingerprint(a)["readings_sha256"] != record_fingerprint(b)["readings_sha256"]
    shifted = a.replace(readings_nT=a.readings_nT + 1e-3)  # 1 pT: below the noise, still another record
    assert record_fingerprint(a)["readings_sha256"] != record_fingerprint(shifted)["readings_sha256"]


def test_an_old_file_without_fingerprint_loads_and_says_so(drifting, tmp_path):
    name, cal, fitted, other = drifting
    doc = cal.to_dict()
    del doc["record"]
    path = tmp_path / "old.json"
    path.write_text(json.dumps(doc))
    old = Calibration.load(path)
    assert old.record == {}
    with pytest.warns(RecordTermWarning, match="does not say which record"):
        applied = _evaluate(old, name, other)  # the terms act as they did before fingerprints, with a caution
    np.testing.assert_allclose(applied, _evaluate(cal, name, other, record_terms="apply"), atol=1e-9)
    # a file without record-only terms never mentions it
    plain = fit(fitted, Model.from_names(["temperature_bias"], 1)).calibration.to_dict()
    del plain["record"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        Calibration.from_dict(plain).correct(other)


def test_a_calibration_never_told_its_record_applies_its_terms(drifting):
    name, cal, fitted, other = drifting
    fresh = fit(fitted, Model.from_names([name], 1)).calibration
    assert fresh.record is None and fresh.to_dict()["record"] is None
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _evaluate(fresh, name, other)


@pytest.mark.parametrize("record", ["abc", {"n_samples": "many", "readings_sha256": "x"}, {"n_samples": 3}])
def test_a_damaged_fingerprint_is_refused(drifting, tmp_path, record):
    doc = drifting[1].to_dict()
    doc["record"] = record
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(MagcalError, match="bad.json: 'record' must be the fingerprint"):
        Calibration.load(path)


def test_an_unknown_effect_names_the_file_and_the_option(drifting, tmp_path):
    doc = drifting[1].to_dict()
    for entry in doc["effect_params"]:
        entry["effect"], entry["term"] = "pump_noise", "pump_noise"
    path = tmp_path / "theirs.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(MagcalError) as err:
        Calibration.load(path)
    text = str(err.value)
    assert str(path) in text and "'pump_noise'" in text and "--effects-file" in text and "damaged" not in text


@pytest.mark.parametrize("n_sensors", [1, 4])
def test_correct_and_tensor_take_what_calibrate_takes(n_sensors):
    """Arrays in, arrays out: an array of readings (and t=, temp=) is accepted like a dataset; one
    sensor's (N, 3) array gives (N, 3) corrected vectors and (N,) total field."""
    import magcal

    ds = magcal.simulate("chi2017", seed=5)
    readings = ds.readings_nT[0] if n_sensors == 1 else ds.readings_nT
    cal = magcal.calibrate(readings, reference_total_nT=ds.reference_total_nT).calibration
    from_array = cal.correct(readings)
    from_dataset = cal.correct(magcal.as_dataset(readings))
    assert from_array.shape == readings.shape
    np.testing.assert_allclose(np.reshape(from_array, from_dataset.shape), from_dataset, rtol=0, atol=0)
    field = cal.total_field(readings, t=np.arange(readings.shape[-2]) * 0.1)
    assert field.shape == readings.shape[:-1]
    assert np.all(np.abs(field - ds.reference_total_nT) < 8 * 3.0)  # sigma 3 nT per axis
    residuals = cal.total_field_residuals(readings)
    np.testing.assert_allclose(residuals.ravel(), (field - ds.reference_total_nT).ravel(), atol=1e-6)
    if n_sensors == 4:
        cal.baseline_m = ds.baseline_m
        tensor = cal.tensor(readings)
        assert set(tensor) >= {"Gxx", "Gyy", "Gzz"} and tensor["Gxx"].shape == (readings.shape[1],)
