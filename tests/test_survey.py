"""Survey correction with Dask (issue 13): partitions corrected in parallel give the single-process numbers."""

from __future__ import annotations

import time

import numpy as np
import pytest

import magcal
from magcal.data import io as mio
from magcal.output.apply import apply_file

pytest.importorskip("distributed")
pytest.importorskip("pyarrow")


@pytest.fixture(scope="module")
def surveys(tmp_path_factory):
    d = tmp_path_factory.mktemp("survey")
    ds = magcal.simulate_timeseries("chi2017", n_samples=900, seed=12, rate_hz=10.0)
    cal = magcal.calibrate(ds).calibration
    a, b = d / "day1.csv", d / "day2.parquet"
    mio.write_csv(a, ds.subset(np.arange(0, 500)))
    mio.write_parquet(b, ds.subset(np.arange(500, 900)))
    return d, cal, a, b


def _table(path):
    return magcal.read_csv(path)


def test_partitions_split_csv_by_lines_and_parquet_by_row_groups(surveys):
    from magcal.output.survey import partitions

    d, cal, a, b = surveys
    parts = partitions([a, b], partition_rows=120)
    csv_parts = [p for p in parts if p.kind == "csv"]
    assert len(csv_parts) == 5 and csv_parts[1].first_line - csv_parts[0].first_line == 120
    assert [p.index for p in parts] == list(range(len(parts))) and parts[-1].kind == "parquet"
    # the partitions hold every data line once: their byte ranges tile the file after its head
    assert all(p.stop == q.start for p, q in zip(csv_parts, csv_parts[1:])) and csv_parts[-1].stop == a.stat().st_size


@pytest.mark.slow
def test_a_local_cluster_gives_the_single_process_numbers(surveys, tmp_path):
    """dask.distributed's LocalCluster (two worker processes) against apply_file on each file."""
    from magcal.output.survey import apply_partitioned

    d, cal, a, b = surveys
    out = tmp_path / "parts"
    summary = apply_partitioned(cal, [a, b], out, workers=2, partition_rows=150, progress=False, compression="zstd")
    assert summary.rows == 900 and len(summary.files) == 5  # 4 CSV partitions + 1 row group
    import pyarrow.parquet as pq

    meta = pq.ParquetFile(summary.files[0]).metadata  # the codec asked for reaches the workers
    assert meta.row_group(0).column(meta.schema.names.index("s1x_cal")).compression == "ZSTD"
    got = [_table(f) for f in summary.files]
    want = []
    for src in (a, b):
        path = tmp_path / f"single_{src.stem}.parquet"
        apply_file(cal, src, path)
        want.append(_table(path))
    g = mio.concatenate(got)
    w = mio.concatenate(want)
    np.testing.assert_array_equal(g.readings_nT, w.readings_nT)
    np.testing.assert_array_equal(g.time_s, w.time_s)
    for name in ("s1x_cal", "s3z_cal", "Gxx", "Gzz", "I2"):
        np.testing.assert_allclose(np.asarray(g.extra[name], float), np.asarray(w.extra[name], float), rtol=1e-12)
    assert set(np.asarray(g.extra["source_file"]).astype(str)) == {"day1.csv", "day2.parquet"}


def test_the_command_line_corrects_several_files_in_parallel(surveys, tmp_path, capsys):
    from magcal.cli import main

    d, cal, a, b = surveys
    cal.save(tmp_path / "cal.json")
    out = tmp_path / "corrected"
    assert (
        main(
            [
                "apply",
                str(tmp_path / "cal.json"),
                str(a),
                str(b),
                "-o",
                str(out),
                "--workers",
                "1",
                "--format",
                "csv",
                "--no-progress",
            ]
        )
        == 0
    )
    assert "corrected 900 rows" in capsys.readouterr().out
    assert sorted(p.name for p in out.iterdir()) == ["part-00000.csv", "part-00001.csv"]


def test_an_unreachable_scheduler_is_said_in_bounded_time(surveys, tmp_path):
    from magcal.output.survey import CONNECT_TIMEOUT_S, apply_partitioned

    d, cal, a, b = surveys
    t0 = time.monotonic()
    with pytest.raises(magcal.MagcalError, match="cannot reach the Dask scheduler"):
        apply_partitioned(cal, [a], tmp_path / "x", scheduler="tcp://127.0.0.1:9", progress=False)
    assert time.monotonic() - t0 < CONNECT_TIMEOUT_S + 20


def test_the_output_directory_must_be_new_or_empty(surveys, tmp_path):
    from magcal.output.survey import apply_partitioned

    d, cal, a, b = surveys
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "keep.txt").write_text("mine")
    with pytest.raises(magcal.MagcalError, match="not an empty directory"):
        apply_partitioned(cal, [a], tmp_path / "full", progress=False)


def test_a_codec_with_csv_partitions_is_refused_before_any_work(surveys, tmp_path):
    from magcal.output.survey import apply_partitioned

    d, cal, a, b = surveys
    with pytest.raises(magcal.MagcalError, match="for Parquet partitions"):
        apply_partitioned(cal, [a], tmp_path / "x", fmt="csv", compression="zstd", progress=False)
    assert not (tmp_path / "x").exists()
