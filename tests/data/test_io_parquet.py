"""Parquet in and out: the data CSV's columns and metadata in Parquet, DataFrames, apply to Parquet."""

from __future__ import annotations

import numpy as np
import pytest

import magcal
from magcal.data import io as mio
from magcal.output.apply import apply_file

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


SITE_LINE = "53.0 N, 4.5 E, 1500 m, 2024-06-01"


def test_a_site_in_the_parquet_metadata_is_read_as_the_csv_line(survey, tmp_path):
    """A ``site`` metadata entry (magcal's own, or a schema key another tool wrote) is read by the CSV's site
    reader: the same :class:`~magcal.data.site.Site` as the CSV's ``# site:`` line."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from magcal.data.site import parse_site, record_site

    ds, _ = survey
    csv = tmp_path / "sited.csv"
    mio.write_csv(csv, ds, metadata={"site": SITE_LINE})
    from_csv = record_site(mio.read_csv(csv))
    assert from_csv == parse_site(SITE_LINE)
    own = tmp_path / "sited.parquet"
    mio.write_parquet(own, ds, metadata={"site": SITE_LINE})
    back = mio.read_csv(own)
    assert record_site(back) == from_csv and back.metadata["site"] == SITE_LINE
    mio.write_parquet(tmp_path / "again.parquet", back)  # the keys it read go back out and read the same
    assert record_site(mio.read_csv(tmp_path / "again.parquet")) == from_csv
    foreign = tmp_path / "foreign.parquet"
    table = pa.table({"s1x": np.full(5, 5e4), "s1y": np.zeros(5), "s1z": np.zeros(5)})
    pq.write_table(table.replace_schema_metadata({b"site": SITE_LINE.encode()}), foreign)
    assert record_site(mio.read_csv(foreign)) == from_csv


def test_a_malformed_parquet_site_is_said_naming_the_schema_not_a_line(survey, tmp_path):
    ds, _ = survey
    path = tmp_path / "bad_site.parquet"
    mio.write_parquet(path, ds, metadata={"site": "53.0 Q, 4.5 E, 1500 m, 2024-06-01"})
    from magcal.core.errors import DataWarning

    with pytest.warns(DataWarning) as said:
        back = mio.read_csv(path)
    text = " ".join(str(w.message) for w in said)
    assert f"{path}: Parquet schema: metadata site:" in text and "'Q', not N or S" in text and "line" not in text
    from magcal.data.site import record_site

    assert record_site(back) is None


def test_a_dataframe_out_and_back(survey):
    ds, _ = survey
    frame = ds.to_dataframe()
    assert list(frame.columns[:4]) == ["t", "s1x", "s1y", "s1z"] and frame.attrs["baseline_m"]
    back = magcal.calibrate(frame, warn=False).calibration.correct(ds)
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


@pytest.mark.parametrize("compression, expected", [(None, "SNAPPY"), ("zstd", "ZSTD"), ("none", "UNCOMPRESSED")])
def test_apply_writes_float_columns_with_the_codec_asked_and_the_same_numbers(survey, tmp_path, compression, expected):
    """Float columns of a Parquet output use snappy by default or the codec asked for; the values are the same
    whatever the codec."""
    import pyarrow.parquet as pq

    ds, csv_path = survey
    cal = magcal.calibrate(ds).calibration
    out = tmp_path / "out.parquet"
    apply_file(cal, csv_path, out, chunk_rows=170, compression=compression)
    meta = pq.ParquetFile(out).metadata
    codecs = {meta.schema.column(j).name: meta.row_group(0).column(j).compression for j in range(meta.num_columns)}
    assert codecs["s1x_cal"] == codecs["Gxx"] == codecs["t"] == expected
    reference = tmp_path / "reference.parquet"
    apply_file(cal, csv_path, reference, chunk_rows=170, compression="gzip")
    got, want = pq.read_table(out).to_pydict(), pq.read_table(reference).to_pydict()
    assert got == want


def test_an_unknown_codec_is_refused_before_any_work(survey, tmp_path, capsys):
    from magcal.cli import main

    ds, csv_path = survey
    cal_path = tmp_path / "cal.json"
    magcal.calibrate(ds).calibration.save(cal_path)
    with pytest.raises(magcal.MagcalError, match="Parquet compression 'lzma'.*none, snappy, zstd"):
        apply_file(cal_path, csv_path, tmp_path / "out.parquet", compression="lzma")
    assert not (tmp_path / "out.parquet").exists()
    assert (
        main(
            [
                "apply",
                str(cal_path),
                str(csv_path),
                "-o",
                str(tmp_path / "o.parquet"),
                "--compression",
                "zstd",
                "--no-progress",
            ]
        )
        == 0
    )
    with pytest.raises(SystemExit):
        main(["apply", str(cal_path), str(csv_path), "-o", str(tmp_path / "p.parquet"), "--compression", "lzma"])
    assert "invalid choice: 'lzma'" in capsys.readouterr().err
    # a codec for a CSV output is a mistake worth saying (nothing would be compressed)
    assert main(["apply", str(cal_path), str(csv_path), "-o", str(tmp_path / "o.csv"), "--compression", "zstd"]) == 2
    err = capsys.readouterr().err
    assert "o.csv" in err and "for Parquet output" in err and "Traceback" not in err
    assert not (tmp_path / "o.csv").exists()


def test_blocks_are_written_in_order_behind_the_work_and_a_write_error_is_raised():
    from magcal.output.apply import _WriteBehind

    done = []
    behind = _WriteBehind(depth=2)
    for k in range(20):
        behind.put(lambda k=k: done.append(k))
    behind.close()
    assert done == list(range(20))

    def fail():
        raise OSError("disk full")

    behind = _WriteBehind()
    behind.put(fail)
    behind.put(lambda: done.append("after"))  # skipped: the file is already broken
    with pytest.raises(OSError, match="disk full"):
        behind.close()
    assert "after" not in done


def test_a_bad_row_late_in_the_survey_leaves_no_parquet_output_and_no_writing_thread(survey, tmp_path, corrupt_csv):
    """The write-behind thread is stopped and the temporary file removed when a block fails after others were
    written: nothing half-written is left under the output's name."""
    import threading

    ds, csv_path = survey
    cal = magcal.calibrate(ds).calibration
    lines = csv_path.read_text().splitlines()
    header = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    bad = corrupt_csv(csv_path, header + 400, 2, "oops")  # the 400th sample
    out = tmp_path / "out.parquet"
    with pytest.raises(magcal.MagcalError, match="bad.csv"):
        apply_file(cal, bad, out, chunk_rows=50)
    assert not out.exists() and not list(tmp_path.glob("out.parquet.tmp*"))
    assert not [t for t in threading.enumerate() if t.name == "magcal-write"]
