"""magcal.data.io.read_csv_preview: a large CSV's quick look, lines spread through the file."""

from __future__ import annotations

import io

import numpy as np
import pytest

from magcal.data import io as mio


def _write(path, n, newline="\n", bad_row=None):
    rng = np.random.default_rng(1)
    b = rng.normal(size=(n, 3))
    b = 50_000.0 * b / np.linalg.norm(b, axis=1, keepdims=True)
    rows = ["# units: nT", "t,s1x,s1y,s1z"]
    for i in range(n):
        rows.append(f"{i * 0.1:.1f},{b[i, 0]:.3f},{b[i, 1]:.3f},{b[i, 2]:.3f}")
    if bad_row is not None:
        rows[2 + bad_row] = f"{bad_row * 0.1:.1f},oops,1,2"
    path.write_bytes((newline.join(rows) + newline).encode())
    return path


@pytest.mark.parametrize("by_offsets", [False, True])
@pytest.mark.parametrize("newline", ["\n", "\r\n"])
def test_the_preview_is_an_even_ordered_sample_of_the_file_s_own_rows(tmp_path, monkeypatch, newline, by_offsets):
    if by_offsets:  # the file is read as a large one: by seeking to evenly spaced offsets
        monkeypatch.setattr(mio, "PREVIEW_WHOLE_BYTES", 0)
    path = _write(tmp_path / "big.csv", 20_000, newline)
    full = mio.read_csv(path)
    ds = mio.read_csv_preview(path, max_rows=500, min_bytes=0)
    assert ds is not None and 450 <= ds.n_samples <= 500
    rows = np.rint(ds.time_s / 0.1).astype(int)  # which of the file's rows were taken
    assert rows[0] == 0 and rows[-1] >= 20_000 - 2 * 20_000 // 500  # from the first row to the end
    assert np.all(np.diff(rows) > 0)  # in the file's order, none twice
    gaps = np.diff(rows)
    assert gaps.max() <= 2 * gaps.min() + 2  # evenly spread (the lines' lengths vary a little)
    np.testing.assert_allclose(ds.readings_nT[0], full.readings_nT[0][rows])  # the rows' own values
    assert ds.source == str(path)


def test_no_preview_of_a_small_file_a_file_object_or_a_file_the_reader_refuses(tmp_path):
    path = _write(tmp_path / "small.csv", 2_000)
    assert mio.read_csv_preview(path) is None  # below PREVIEW_MIN_BYTES: read it whole
    assert mio.read_csv_preview(io.BytesIO(path.read_bytes()), min_bytes=0) is None
    bad = _write(tmp_path / "bad.csv", 2_000, bad_row=0)  # the first row is always taken
    assert mio.read_csv_preview(bad, max_rows=100, min_bytes=0) is None
    with pytest.raises(mio.DatasetError, match="line 3"):
        mio.read_csv(bad)  # the whole read names the line
    missing = tmp_path / "missing.csv"
    assert mio.read_csv_preview(missing, min_bytes=0) is None


def test_a_preview_asking_for_more_rows_than_the_file_has_reads_every_row_once(tmp_path):
    path = _write(tmp_path / "few.csv", 300)
    ds = mio.read_csv_preview(path, max_rows=10_000, min_bytes=0)
    assert ds is not None and ds.n_samples == 300
    np.testing.assert_allclose(ds.readings_nT, mio.read_csv(path).readings_nT)


@pytest.mark.parametrize("n_rows", [1_000, 1_001, 3_000])
def test_a_file_of_about_max_rows_lines_of_unequal_lengths_gives_exactly_max_rows_of_them(tmp_path, n_rows):
    """A record of at most ``max_rows`` lines is previewed whole however long its lines are (the workbench then
    sends none of its points again); a longer one gives exactly ``max_rows`` rows, evenly spaced by index."""
    path = _write(tmp_path / "few.csv", n_rows)  # times 0.0 ... 99.9 then 100.0 ...: lines of unequal lengths
    ds = mio.read_csv_preview(path, max_rows=1_000, min_bytes=0)
    assert ds is not None and ds.n_samples == 1_000
    rows = np.rint(ds.time_s / 0.1).astype(int)
    expected = np.linspace(0, n_rows - 1, 1_000).round().astype(int)
    np.testing.assert_array_equal(rows, expected)  # the first and last rows, the rest evenly between
    np.testing.assert_allclose(ds.readings_nT[0], mio.read_csv(path).readings_nT[0][expected])
