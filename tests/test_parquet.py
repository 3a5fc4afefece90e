"""Parquet in and out (issue 13): the data CSV's columns and metadata in Parquet, DataFrames, apply to Parquet."""

from __future__ import annotations

import numpy as np
import pytest

import magcal
from magcal import io as mio
from magcal.apply import apply_file

pytest.importorskip("pyarrow")


@pytest.fixture
def survey(tmp_path):
    ds = magcal.simulate_timeseries("chi2017", n_samples=500, seed=2, rate_hz=10.0)
    path = tmp_path / "survey.csv"
    mio.write_csv(path, ds)
    return mio.read_csv(path), path


def test_parquet_round_trip_keeps_values_channels_and_metadata(survey, tmp_path):
    ds, _ = survey
    out = tmp_path / "survey.parquet"
    mio.write_parquet(out, ds)
    back = magcal.read_csv(out)  # the one reader dispatches on the ending
    np.testing.assert_array_equal(back.readings_nT, ds.readings_nT)
    np.testing.assert_array_equal(back.time_s, ds.time_s)
    np.testing.assert_array_equal(back.temperature_C, ds.temperature_C)
    np.testing.assert_allclose(back.attitude_wxyz, ds.attitude_wxyz, atol=1e-12)
    assert back.baseline_m == ds.baseline_m and back.noise_nT == ds.noise_nT
    assert back.reference_total_nT == ds.reference_total_nT and back.source == str(out)


def test_a_dataframe_out_and_back(survey):
    ds, _ = survey
    frame = ds.to_dataframe()
    assert list(frame.columns[:4]) == ["t", "s1x", "s1y", "s1z"] and frame.attrs["baseline_m"]
    back = magcal.api.calibrate(frame).calibration.correct(ds)
    np.testing.assert_allclose(back, magcal.calibrate(ds).calibration.correct(ds), atol=1e-6)


def test_a_bad_parquet_value_names_the_file_row_and_column(survey, tmp_path):
    ds, _ = survey
    cols = mio.dataset_columns(ds)
    cols["s2y"] = cols["s2y"].copy()
    cols["s2y"][41] = np.nan
    out = tmp_path / "bad.parquet"
    mio.write_parquet(out, cols, mio.dataset_metadata(ds))
    with pytest.raises(magcal.MagcalError) as err:
        magcal.read_csv(out)
    text = str(err.value)
    assert "bad.parquet" in text and "s2y" in text and "42" in text


@pytest.mark.parametrize("src, dst", [("csv", "parquet"), ("parquet", "parquet"), ("parquet", "csv")])
def test_apply_to_and_from_parquet_gives_the_numbers_of_the_csv_path(survey, tmp_path, src, dst):
    ds, csv_path = survey
    cal = magcal.calibrate(ds).calibration
    expected = tmp_path / "expected.csv"
    apply_file(cal, csv_path, expected, chunk_rows=170)
    want = mio.read_csv(expected, drop_bad=False)
    inp = csv_path
    if src == "parquet":
        inp = tmp_path / "survey.parquet"
        mio.write_parquet(inp, ds)
    out = tmp_path / f"out.{dst}"
    summary = apply_file(cal, inp, out, chunk_rows=170)  # several chunks
    assert summary.rows == ds.n_samples
    got = magcal.read_csv(out)
    np.testing.assert_allclose(got.readings_nT, want.readings_nT, atol=1e-9)
    for name in ("s1x_cal", "s4z_cal", "Gxx", "Gyz", "I1"):
        a, b = np.asarray(got.extra[name], float), np.asarray(want.extra[name], float)
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=2e-3)  # the CSV path rounds to 1 pT
