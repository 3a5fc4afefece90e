"""Survey correction with Dask: partitions corrected in parallel give the single-process numbers."""

from __future__ import annotations

import re
import time
import warnings

import numpy as np
import pytest

import magcal
from magcal.data import io as mio
from magcal.output.apply import apply_file
from tests.helpers import line_ends

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


def test_partitions_split_csv_by_lines_and_parquet_by_rows(surveys):
    from magcal.output.survey import partitions

    d, cal, a, b = surveys
    parts = partitions([a, b], partition_rows=120)
    csv_parts = [p for p in parts if p.kind == "csv"]
    assert len(csv_parts) == 5 and csv_parts[1].first_line - csv_parts[0].first_line == 120
    assert [p.index for p in parts] == list(range(len(parts))) and parts[-1].kind == "parquet"
    # the partitions hold every data line once: their byte ranges tile the file after its head
    assert all(p.stop == q.start for p, q in zip(csv_parts, csv_parts[1:])) and csv_parts[-1].stop == a.stat().st_size
    # the Parquet file's one row group of 400 rows is split into ranges of about 120 rows that tile it
    pq_parts = [p for p in parts if p.kind == "parquet"]
    assert [(p.start, p.stop) for p in pq_parts] == [(0, 133), (133, 266), (266, 400)]
    assert [p.first_line for p in pq_parts] == [1, 134, 267]


def _grouped(path, ds, group_rows):
    """``ds`` written as Parquet with row groups of ``group_rows`` (a list: one size per group)."""
    import pyarrow.parquet as pq

    table = mio.parquet_table(mio.dataset_columns(ds), mio.dataset_metadata(ds))
    with pq.ParquetWriter(path, table.schema) as writer:
        start = 0
        for n in group_rows:
            writer.write_table(table.slice(start, n))
            start += n
    return path


@pytest.mark.parametrize("max_marks", [3, 10, 1 << 16])
@pytest.mark.parametrize("rows", [7, 64, 150])
@pytest.mark.parametrize("final_newline", [True, False])
def test_partitions_sized_from_the_count_are_cut_in_that_one_pass(
    surveys, tmp_path, monkeypatch, max_marks, rows, final_newline
):
    """Sized to the workers, a CSV is read once: the pass that counts its lines keeps where every ``stride``-th
    ends (the stride doubling whenever more than ``MAX_LINE_MARKS`` are kept) and the partitions are cut there,
    the same partitions as cutting while reading the lines again, to the byte and the line number."""
    from magcal.output import survey

    d, _, a, _ = surveys
    path = tmp_path / "survey.csv"
    text = a.read_bytes()
    path.write_bytes(text if final_newline else text.rstrip(b"\n"))
    monkeypatch.setattr(survey, "MAX_LINE_MARKS", max_marks)
    monkeypatch.setattr(survey, "partition_rows_for", lambda total, workers: rows)
    passes = []
    real = survey._line_ends

    def counted(*args, **kwargs):
        passes.append(args)
        return real(*args, **kwargs)

    monkeypatch.setattr(survey, "_line_ends", counted)
    scan = survey._csv_scan(path)
    assert scan.lines == 500 and scan.marks.size <= max_marks
    passes.clear()
    one_pass = survey.partitions([path], workers=2)
    assert len(passes) == 1  # the count's pass, and no other
    size = -(-rows // scan.stride) * scan.stride  # rounded up to the marks' stride
    assert one_pass == survey.partitions([path], partition_rows=size)
    assert sum(len(list(survey._csv_part(p)[1])) > 0 for p in one_pass) == len(one_pass)
    assert one_pass[-1].stop == path.stat().st_size


@pytest.mark.parametrize("workers", [1, 2, 16])
def test_partitions_are_sized_to_the_workers_not_the_row_groups(tmp_path, workers, monkeypatch):
    """Many small row groups are joined and a large one split, on the groups' edges where they can be, into about
    four partitions per worker; the ranges tile the file's rows."""
    from magcal.output import survey

    monkeypatch.setattr(survey, "MIN_PARTITION_ROWS", 10)
    ds = magcal.simulate_timeseries("chi2017", n_samples=2000, seed=3, rate_hz=10.0)
    sizes = [50] * 20 + [1000]  # 20 small groups, then one large one
    path = _grouped(tmp_path / "g.parquet", ds, sizes)
    parts = survey.partitions([path], workers=workers)
    rows = survey.partition_rows_for(2000, workers)
    assert rows == max(10, -(-2000 // (4 * workers)))
    assert parts[0].start == 0 and parts[-1].stop == 2000
    assert all(p.stop == q.start for p, q in zip(parts, parts[1:]))
    edges = set(np.cumsum([0] + sizes).tolist())
    if rows >= 75:  # no small group needs splitting: every range among them ends on a group's edge
        assert all(p.start in edges and p.stop in edges for p in parts if p.stop <= 1000)
    assert max(p.rows for p in parts) <= 1.5 * rows + 1
    assert 3 * workers <= len(parts) <= 5 * workers


@pytest.mark.slow
def test_a_local_cluster_gives_the_single_process_numbers(surveys, tmp_path):
    """dask.distributed's LocalCluster (two worker processes) against apply_file on each file."""
    from magcal.output.survey import apply_partitioned

    d, cal, a, b = surveys
    out = tmp_path / "parts"
    summary = apply_partitioned(cal, [a, b], out, workers=2, partition_rows=150, progress=False, compression="zstd")
    assert summary.rows == 900 and len(summary.files) == 7  # 4 CSV partitions + 3 ranges of the row group
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


def _same_rows(got, want):
    """Every column of two apply outputs equal, row for row (magcal's own metadata aside)."""
    assert list(got.column_names) == list(want.column_names)
    for name in want.column_names:
        g, w = got.column(name).to_numpy(zero_copy_only=False), want.column(name).to_numpy(zero_copy_only=False)
        if g.dtype.kind == "f":
            np.testing.assert_array_equal(g, w, err_msg=name)
        else:
            assert (g.astype(str) == w.astype(str)).all(), name


@pytest.fixture(scope="module")
def grouped(tmp_path_factory):
    """A four-sensor survey in row groups of uneven sizes (30 small, then one large), its calibration and the
    single-process apply of it (the reference)."""
    import pyarrow.parquet as pq

    d = tmp_path_factory.mktemp("grouped")
    ds = magcal.simulate_timeseries("chi2017", n_samples=3000, seed=5, rate_hz=10.0)
    cal = magcal.calibrate(ds.subset(np.arange(1000))).calibration
    path = _grouped(d / "survey.parquet", ds, [40] * 30 + [1800])
    single = d / "single.parquet"
    apply_file(cal, path, single)
    return cal, path, pq.read_table(single)


@pytest.mark.slow
@pytest.mark.parametrize("workers", [1, 2])
def test_the_partitioned_apply_equals_the_single_process_row_for_row(grouped, tmp_path, workers, monkeypatch):
    """Partitions sized to the workers (row groups joined and split), each read and written by its own task: the
    output folder, read as one Parquet dataset, is the single-process output row for row, in order."""
    import pyarrow.dataset as pads

    from magcal.output import survey

    monkeypatch.setattr(survey, "MIN_PARTITION_ROWS", 100)
    cal, path, want = grouped
    out = tmp_path / "parts"
    summary = survey.apply_partitioned(cal, [path], out, workers=workers, progress=False)
    assert summary.rows == 3000 and summary.workers == workers
    assert summary.partitions == len(summary.files) >= 3 * workers  # sized to the workers, not the 31 row groups
    got = pads.dataset(str(out), format="parquet").to_table()  # the folder is one dataset, parts in order
    assert got.num_rows == 3000
    _same_rows(got.drop_columns(["source_file"]), want)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".parts")]  # no temporary folder left


@pytest.mark.slow
def test_the_same_code_runs_on_a_cluster_by_its_address(grouped, tmp_path):
    """A Dask cluster on loopback reached by its address (--scheduler): the partitions are sized to its worker
    threads and the output is the single-process one."""
    import pyarrow.dataset as pads

    from magcal.cli import main

    distributed = pytest.importorskip("distributed")
    cal, path, want = grouped
    cal.save(tmp_path / "cal.json")
    out = tmp_path / "parts"
    with distributed.LocalCluster(
        n_workers=1, threads_per_worker=2, processes=True, host="127.0.0.1", dashboard_address=None, silence_logs=40
    ) as cluster:
        t0 = time.monotonic()
        rc = main(
            [
                "apply",
                str(tmp_path / "cal.json"),
                str(path),
                "-o",
                str(out),
                "--scheduler",
                cluster.scheduler_address,
                "--partition-rows",
                "500",
                "--no-progress",
            ]
        )
        assert rc == 0 and time.monotonic() - t0 < 60
    got = pads.dataset(str(out), format="parquet").to_table()
    _same_rows(got.drop_columns(["source_file"]), want)


def test_partitions_of_a_csv_with_a_byte_order_mark_and_comments_read_as_the_whole_file(tmp_path):
    """A UTF-8 byte order mark before a ``#`` line, blank lines of any whitespace before the header: every
    partition is read with the whole head (a partition after the first took its first data line for the header)."""
    from magcal.output.survey import _csv_part, partitions

    ds = magcal.simulate_timeseries("chi2017", n_samples=700, seed=3, rate_hz=10.0)
    path = tmp_path / "bom.csv"
    mio.write_csv(path, ds)
    path.write_bytes(("\ufeff# from a spreadsheet\r\n\xa0\r\n" + path.read_text()).encode("utf-8"))
    parts = partitions([path], partition_rows=200)
    assert len(parts) == 4
    got = mio.concatenate([d for p in parts for d in _csv_part(p)[1]])
    np.testing.assert_array_equal(got.readings_nT, magcal.read_csv(path).readings_nT)


@pytest.mark.slow
def test_the_partitioned_apply_decides_the_record_terms_as_one_process(tmp_path, monkeypatch):
    """``magcal apply --workers``: the fitted record, saved again with CRLF, a byte order mark and blank lines,
    keeps its record-only terms; a file of another length is another record, decided in the client without a row
    hashed; each file's rows are the single-process apply's."""
    from magcal.core.errors import RecordTermWarning
    from magcal.data import simulation as sim
    from magcal.fitting.fitter import fit
    from magcal.model.terms import EFFECTS, Model
    from magcal.output import apply as ap
    from magcal.output.survey import apply_partitioned

    drift = EFFECTS["bias_drift"]()
    files = {}
    for name, n, seed in (("record", 600, 3), ("later", 700, 4)):
        ds = sim.simulate_timeseries(
            sim.chi2017_truth(1), n_samples=n, noise_nT=2.0, seed=seed, perturbations=[drift.perturbation(80.0)]
        )
        files[name] = tmp_path / f"{name}.csv"
        mio.write_csv(files[name], ds)
        text = files[name].read_text().replace("\n", "\r\n").replace("\r\n0.5,", "\r\n \r\n\r\n0.5,")
        files[name].write_bytes(("\ufeff" + text).encode("utf-8"))
    record = mio.read_csv(files["record"])
    cal = fit(record, Model.from_names(["bias_drift", "temperature_bias"], 1)).calibration.fitted_on(record)
    hashed = []
    real_update = ap.RecordHasher.update
    monkeypatch.setattr(ap.RecordHasher, "update", lambda self, d: hashed.append(d.n_samples) or real_update(self, d))
    out = tmp_path / "parts"
    summary = apply_partitioned(cal, [files["record"], files["later"]], out, workers=1, partition_rows=250)
    said = [n.text for n in summary.notes if n.is_a(RecordTermWarning)]
    assert len(said) == 1 and "(700 samples)" in said[0]  # the later file only
    assert sum(hashed) == 600  # the record alone was hashed, in the client
    got = mio.concatenate([mio.read_parquet(f) for f in summary.files])
    source = np.asarray(got.extra["source_file"]).astype(str)
    for name, choice in (("record", "apply"), ("later", "drop")):
        mine = source == files[name].name
        want = cal.correct(mio.read_csv(files[name]), record_terms=choice)[0]
        calc = np.column_stack([np.asarray(got.extra[f"s1{a}_cal"], float)[mine] for a in "xyz"])
        np.testing.assert_allclose(calc, want, atol=1e-9)


@pytest.mark.parametrize("variant", line_ends.VARIANTS)
def test_two_partitions_read_every_line_end_as_the_whole_file_or_refuse_alike(tmp_path, variant):
    """A CSV split into two partitions on its line ends: LF, CRLF, CRs before the LF or ending the file give the
    whole file's samples; CR-only line ends and a CR inside a line (in the second partition, three quarters through
    the rows) are refused with ``read_csv``'s own message, naming the file's line (a partition numbered its lines
    from its head: line 101 for the file's line 301)."""
    from magcal.output.survey import _csv_part, partitions

    ds = magcal.simulate_timeseries("chi2017", n_samples=400, seed=7, rate_hz=10.0)
    lf = tmp_path / "lf.csv"
    mio.write_csv(lf, ds)
    data, refusal = line_ends.line_end_variant(lf.read_text(), variant)
    path = tmp_path / "survey.csv"
    path.write_bytes(data)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            got = mio.concatenate([d for p in partitions([path], partition_rows=200) for d in _csv_part(p)[1]])
    except mio.DatasetError as exc:
        got = str(exc)
    if refusal is None:
        assert len(partitions([path], partition_rows=200)) == 2
        np.testing.assert_array_equal(got.readings_nT, magcal.read_csv(lf).readings_nT)
        np.testing.assert_array_equal(got.time_s, magcal.read_csv(lf).time_s)
        return
    with pytest.raises(mio.DatasetError) as whole:
        magcal.read_csv(path)
    assert got == str(whole.value) and re.search(refusal, got), got


def test_a_partitions_reader_notes_come_back_in_the_summary(surveys, tmp_path):
    """A task's reader notes (a bad row dropped with ``drop_bad``) come back in the summary's notes, naming the
    file's line: a worker's warnings would go nowhere the user looks."""
    from magcal.core.errors import DataWarning
    from magcal.output.survey import apply_partitioned

    d, cal, a, _ = surveys
    lines = a.read_text().splitlines(keepends=True)
    header = next(k for k, line in enumerate(lines) if not line.startswith("#"))
    bad = header + 1 + 321  # a data row in the third partition of 150
    cells = lines[bad].split(",")
    cells[0] = "nan"
    lines[bad] = ",".join(cells)
    path = tmp_path / "one_bad.csv"
    path.write_text("".join(lines))
    summary = apply_partitioned(
        cal, [path], tmp_path / "parts", workers=1, partition_rows=150, drop_bad=True, progress=False
    )
    dropped = [n for n in summary.notes if "dropped" in n.text]
    assert summary.rows == 499 and len(dropped) == 1 and dropped[0].category is DataWarning
    first = lines[header].split(",")[0]  # the column made nan
    assert f"{path}: dropped 1 row(s) with bad values: line {bad + 1}, column {first}: 'nan'" in dropped[0].text
