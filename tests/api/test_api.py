"""The one-call API (``magcal.calibrate``, ``magcal.diagnose``, ``magcal.read_csv``) on whatever the user holds.

Arrays, (n_sensors, N, 3) stacks, DataFrames and datasets all go through :func:`magcal.data.dataset.as_dataset`; the
results must recover the simulated truth and equal what the engine gives on the dataset itself.
"""

import subprocess
import sys

import numpy as np
import pandas as pd
import pytest

import magcal
from magcal.data import io
from magcal.data.dataset import DatasetError
from magcal.data.inputs import as_dataset
from magcal.data.simulation import chi2017_truth, simulate, simulate_timeseries
from magcal.model import plugins
from magcal.model.perturbations import parse_hidden

SIGMA = 3.0


def _frame(ds):
    frame = pd.DataFrame(io.dataset_columns(ds))
    frame.attrs.update(io.dataset_metadata(ds))
    return frame


# each form a user may hold the same record in
FORMS = {
    "dataset": lambda ds: ds,
    "array": lambda ds: ds.readings_nT[0] if ds.n_sensors == 1 else ds.readings_nT,
    "nested list": lambda ds: ds.readings_nT.tolist(),
    "DataFrame": _frame,
}


@pytest.mark.parametrize("n_sensors", [1, 4])
@pytest.mark.parametrize("form", sorted(FORMS))
def test_calibrate_takes_any_form_and_recovers_the_truth(form, n_sensors):
    truth = chi2017_truth(n_sensors)
    ds = simulate(truth, n_samples=400, noise_nT=SIGMA, seed=5)
    result = magcal.calibrate(FORMS[form](ds), reference_total_nT=truth.total_nT)
    assert result.calibration.n_sensors == n_sensors
    for cal, sensor in zip(result.calibration.sensors, truth.sensors):
        assert np.max(np.abs(cal.cinv - sensor.Cinv)) < 2e-3
        assert np.max(np.abs(cal.bias_nT - sensor.bias_nT)) < 3.0  # nT, sigma 3 nT over 400 samples
        assert np.max(np.abs(cal.R - sensor.R)) < 2e-3
    np.testing.assert_array_less(result.rms_after_per_sensor_nT, 1.15 * SIGMA)


def test_a_plain_array_is_what_the_engine_gives_on_the_dataset():
    """It used to fail with "'numpy.ndarray' object has no attribute 'n_samples'"."""
    ds = simulate(chi2017_truth(1), n_samples=300, noise_nT=SIGMA, seed=3)
    from_array = magcal.calibrate(ds.readings_nT[0], reference_total_nT=ds.reference_total_nT)
    from_dataset = magcal.fitting.pipeline.calibrate(ds)
    np.testing.assert_allclose(
        from_array.calibration.sensors[0].cinv, from_dataset.calibration.sensors[0].cinv, rtol=0, atol=1e-9
    )
    np.testing.assert_allclose(
        from_array.calibration.sensors[0].bias_nT, from_dataset.calibration.sensors[0].bias_nT, rtol=0, atol=1e-6
    )


def test_without_a_reference_the_field_is_fitted_from_an_array():
    ds = simulate(chi2017_truth(1), n_samples=300, noise_nT=SIGMA, seed=3)
    result = magcal.calibrate(ds.readings_nT[0])
    assert result.reference_kind == "fitted"
    assert magcal.calibrate(ds.readings_nT[0], reference_total_nT=50000.0).reference_kind == "given"


def _hidden_temperature_bias(n_sensors=1, sensor=1, magnitude=2.0, seed=1):
    spec = f"temperature_bias:{sensor}={magnitude}"
    return simulate_timeseries(
        chi2017_truth(n_sensors),
        n_samples=1500,
        noise_nT=SIGMA,
        seed=seed,
        perturbations=[parse_hidden(spec, n_sensors)],
    )


@pytest.mark.parametrize("n_sensors, sensor", [(1, 1), (4, 3)])
def test_diagnose_an_array_with_its_temperature_names_the_hidden_effect(n_sensors, sensor):
    ds = _hidden_temperature_bias(n_sensors, sensor)
    readings = ds.readings_nT[0] if n_sensors == 1 else ds.readings_nT
    d = magcal.diagnose(readings, t=ds.time_s, temp=ds.temperature_C, reference_total_nT=ds.reference_total_nT)
    assert d.verdict == "missing_effect", d.summary
    label = "temperature_bias" if n_sensors == 1 else f"temperature_bias:{sensor}"
    assert d.explained_by == [label]
    # adding it, through the same API, brings the fit to the noise
    fixed = magcal.calibrate(
        readings, effects=d.explained_by, t=ds.time_s, temp=ds.temperature_C, reference_total_nT=ds.reference_total_nT
    )
    assert fixed.rms_nT < 1.1 * SIGMA < magcal.calibrate(readings, reference_total_nT=ds.reference_total_nT).rms_nT


def test_without_the_temperature_the_effect_cannot_be_named():
    ds = _hidden_temperature_bias()
    d = magcal.diagnose(ds.readings_nT[0], t=ds.time_s, reference_total_nT=ds.reference_total_nT)
    assert all(c.effect != "temperature_bias" for c in d.candidates)


@pytest.mark.parametrize("form", ["dataset", "DataFrame"])
def test_diagnose_takes_a_dataset_or_a_frame_with_a_fitted_result(form):
    ds = _hidden_temperature_bias()
    data = FORMS[form](ds)
    d = magcal.diagnose(data, magcal.calibrate(data))
    assert d.explained_by == ["temperature_bias"]


def test_the_engine_functions_still_take_datasets():
    from magcal.diagnosis import diagnose
    from magcal.fitting.pipeline import calibrate

    ds = _hidden_temperature_bias()
    assert diagnose(ds, calibrate(ds)).explained_by == ["temperature_bias"]


def test_read_csv_is_the_io_reader(tmp_path):
    ds = simulate("chi2017", seed=1)
    path = tmp_path / "chi.csv"
    io.write_csv(path, ds)
    assert magcal.read_csv is io.read_csv
    np.testing.assert_allclose(magcal.read_csv(path).readings_nT, ds.readings_nT, rtol=1e-12)


@pytest.mark.parametrize(
    "shape, hint",
    [
        ((3, 200), "transposed"),
        ((200, 6), "2 sensors"),
        ((6, 200, 3), "at most 4 sensors"),
        ((2, 3, 200), "axes look swapped"),
        ((200,), ""),
        ((200, 2), ""),
        ((1, 2, 200, 3), ""),
        ((0, 3), "no samples"),
    ],
)
def test_a_wrong_shape_says_the_shape_got_and_the_shapes_accepted(shape, hint):
    with pytest.raises(ValueError) as err:
        magcal.calibrate(np.ones(shape))
    message = str(err.value)
    assert f"shape {shape}" in message
    assert "(N, 3)" in message and "(n_sensors 1-4, N, 3)" in message
    assert hint in message


@pytest.mark.parametrize(
    "bad, where",
    [
        (lambda r: r.__setitem__((40, 1), np.nan), "sample 40 (0-based), axis y"),
        (lambda r: r.__setitem__((7, 2), np.inf), "sample 7 (0-based), axis z"),
    ],
)
def test_nan_readings_are_refused_naming_the_sample(bad, where):
    readings = simulate(chi2017_truth(1), seed=1).readings_nT[0].copy()
    bad(readings)
    with pytest.raises(DatasetError, match="NaN or infinite") as err:
        as_dataset(readings)
    assert where in str(err.value)


@pytest.mark.parametrize(
    "keywords, expected",
    [
        ({"t": np.arange(199.0)}, r"t: got shape \(199,\); accepted is \(200,\)"),
        ({"t": 1.0}, r"t: got shape \(\); accepted is \(200,\)"),
        ({"t": np.r_[np.arange(100.0), np.arange(100.0)]}, "strictly increasing; sample 100"),
        ({"temp": np.ones((200, 2))}, r"temp: got shape \(200, 2\)"),
        ({"temp": np.r_[np.ones(199), np.nan]}, "temp: 1 value.* NaN or infinite, the first at sample 199"),
        ({"reference_total_nT": -5}, "reference_total_nT: got -5; a positive number"),
        ({"reference_total_nT": "fifty"}, "reference_total_nT: got 'fifty'"),
    ],
)
def test_bad_channels_are_refused_with_what_was_expected(keywords, expected):
    readings = simulate(chi2017_truth(1), seed=1).readings_nT[0]
    with pytest.raises(ValueError, match=expected):
        as_dataset(readings, **keywords)


def test_a_single_temperature_applies_to_every_sample():
    ds = as_dataset(np.ones((10, 3)), temp=21.5, t=np.arange(10) * 0.1)
    np.testing.assert_array_equal(ds.temperature_C, np.full(10, 21.5))
    assert ds.channels == {"time", "temperature"}


def test_keywords_add_channels_to_a_dataset_without_changing_the_original():
    ds = simulate(chi2017_truth(1), seed=1)
    with_temp = as_dataset(ds, temp=np.linspace(10, 30, ds.n_samples))
    assert with_temp.has("temperature") and not ds.has("temperature")
    assert as_dataset(ds) is ds


def test_a_frame_reads_like_the_csv_file(tmp_path):
    ds = _hidden_temperature_bias(4, 2)
    path = tmp_path / "rec.csv"
    io.write_csv(path, ds)
    from_file = io.read_csv(path)
    from_frame = as_dataset(_frame(ds))
    for attr in ("readings_nT", "time_s", "temperature_C", "attitude_wxyz"):
        np.testing.assert_allclose(getattr(from_frame, attr), getattr(from_file, attr), rtol=1e-12)
    assert (from_frame.baseline_m, from_frame.noise_nT, from_frame.reference_total_nT) == (
        from_file.baseline_m,
        from_file.noise_nT,
        from_file.reference_total_nT,
    )


def test_a_frame_with_one_sensor_uses_x_y_z():
    ds = simulate(chi2017_truth(1), seed=1)
    frame = pd.DataFrame(ds.readings_nT[0], columns=["x", "y", "z"])
    np.testing.assert_allclose(as_dataset(frame).readings_nT, ds.readings_nT, rtol=1e-12)


@pytest.mark.parametrize(
    "damage, expected",
    [
        (lambda f: f.drop(columns="s3z"), "sensor 3 lacks column.* s3z"),
        (lambda f: f.assign(s2y=f["s2y"].where(f.index != 17)), "row 17, column s2y"),
        (
            lambda f: f.set_index(f.index + 100).assign(temp=lambda g: g["temp"].where(g.index != 105)),
            "row 105, column temp",
        ),
        (lambda f: f.assign(t=f["t"].where(f.index != 30, 0.0)), "row 30, column t"),
        (lambda f: f.iloc[:0], "no rows"),
    ],
)
def test_a_bad_frame_is_refused_naming_the_row_and_column(damage, expected):
    frame = damage(_frame(_hidden_temperature_bias(4, 2)))
    with pytest.raises(DatasetError, match=expected) as err:
        as_dataset(frame)
    assert str(err.value).startswith("DataFrame")
    assert "--drop-bad" not in str(err.value)


def test_a_frame_indexed_by_time_keeps_the_times():
    ds = _hidden_temperature_bias()
    frame = _frame(ds).set_index("t")
    from_frame = as_dataset(frame)
    np.testing.assert_allclose(from_frame.time_s, ds.time_s, rtol=1e-12)
    assert magcal.diagnose(frame).explained_by == ["temperature_bias"]


def test_frame_attrs_are_the_metadata_lines():
    frame = pd.DataFrame(simulate(chi2017_truth(1), seed=1).readings_nT[0], columns=["x", "y", "z"])
    frame.attrs = {"reference_total_nT": 48000, "site": "range B"}
    ds = as_dataset(frame)
    assert ds.reference_total_nT == 48000.0 and ds.metadata["site"] == "range B"
    frame.attrs = {"reference_total_nT": -1}
    with pytest.raises(DatasetError, match="reference_total_nT"):
        as_dataset(frame)


def test_the_public_names_are_there():
    from magcal.model import perturbations
    from magcal.model import terms as model

    for name in magcal.__all__:
        assert getattr(magcal, name) is not None, name
    assert magcal.register is model.register
    assert magcal.parse_hidden is perturbations.parse_hidden
    from magcal.diagnosis import Diagnosis

    assert magcal.Diagnosis is Diagnosis


HEAVY = ("viser", "trimesh", "plotly", "pandas", "matplotlib")


def _in_fresh_python(code):
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    return done.stdout.strip()


def test_importing_magcal_loads_none_of_the_heavy_packages():
    loaded = _in_fresh_python(f"import sys, magcal; print(sorted(m for m in {HEAVY!r} if m in sys.modules))")
    assert loaded == "[]"


def test_the_effects_catalogue_is_whole_at_import():
    """Nothing imported later (diagnosis, command line, hidden-effect simulation) adds a built-in effect."""
    code = (
        "import magcal; first = sorted(magcal.EFFECTS); import magcal.diagnosis, magcal.cli, magcal.model.perturbations,"
        " magcal.model.plugins, magcal.fitting.validation, magcal.checks.quality; print(first == sorted(magcal.EFFECTS), *first)"
    )
    same, *names = _in_fresh_python(code).split()
    assert same == "True"
    assert set(names) == {name for name in magcal.EFFECTS if plugins.is_builtin(name)}
