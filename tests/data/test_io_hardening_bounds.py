"""Text cells bounded in every table reader before they are made, Parquet dictionaries included.

Each test crafts its hostile file itself, small on disk: a Parquet text column whose dictionary holds one long value
for every row (a few kB that decode to gigabytes), the same value in plain pages compressed, many rows of one
moderately long value, a nested column. Each checks the exact outcome: one message naming the file, the column and
the limit, within seconds, and that a clean file with dictionary text reads exactly as its decoded cells do.
"""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

import magcal
from magcal.data import io
from magcal.data.dataset import DatasetError

pa = pytest.importorskip("pyarrow")
pq = pytest.importorskip("pyarrow.parquet")


def finishes(fn, seconds=20.0):
    """``fn()``'s exception, or a test failure if it has not ended within ``seconds`` or raised nothing."""
    box = {}

    def run():
        try:
            box["value"] = fn()
        except Exception as exc:  # the outcome under test
            box["error"] = exc

    thread = threading.Thread(target=run, daemon=True)
    t0 = time.monotonic()
    thread.start()
    thread.join(seconds)
    assert not thread.is_alive(), f"still running after {seconds} s"
    box["seconds"] = time.monotonic() - t0
    return box


def refused(box, *needles) -> str:
    assert "error" in box, f"read, not refused: {box.get('value')}"
    assert isinstance(box["error"], DatasetError), repr(box["error"])
    text = str(box["error"])
    assert "\n" not in text and len(text) < 1000
    for needle in needles:
        assert needle in text, text
    return text


def readings(n):
    return {a: np.full(n, v) for a, v in (("s1x", 20_000.0), ("s1y", 1_000.0), ("s1z", 40_000.0))}


def text_parquet(path, rows, value, column="junk", dictionary=True, **options):
    """A Parquet file of ``rows`` readings whose text ``column`` holds ``value`` in every row."""
    if dictionary:  # made as a dictionary: the decoded column is never built here either
        cells = pa.DictionaryArray.from_arrays(pa.array(np.zeros(rows, np.int32)), pa.array([value]))
    else:
        cells = pa.array([value] * rows)
    table = pa.table({**readings(rows), column: cells})
    pq.write_table(table, path, compression="zstd", use_dictionary=dictionary, **options)
    return path


@pytest.mark.parametrize("column", ["junk", "group"])
def test_a_dictionary_of_one_long_value_for_every_row_is_refused_before_it_is_decoded(tmp_path, column):
    """30 rows of one 20 MB value: 3 kB on disk, 600 MB decoded, 2.4 GB as numpy text; refused from the
    dictionary's lengths, in any column (one magcal keeps as a channel, or the groups)."""
    path = text_parquet(tmp_path / "bomb.parquet", 30, "x" * 20_000_000, column)
    assert path.stat().st_size < 10_000
    box = finishes(lambda: io.read_csv(path))
    refused(
        box,
        "bomb.parquet: row 1, ",
        f"column '{column}': a text cell of 20,000,000 characters, more than the 1,048,576 magcal reads",
    )
    assert box["seconds"] < 10


def test_the_bomb_is_refused_by_the_streaming_readers_too(tmp_path, capsys):
    from magcal.cli import main

    path = text_parquet(tmp_path / "bomb.parquet", 30, "x" * 5_000_000)
    ds = magcal.simulate("chi2017", n_samples=400, seed=1)
    cal = tmp_path / "cal.json"
    magcal.calibrate(ds).calibration.save(cal)
    assert main(["apply", str(cal), str(path), "-o", str(tmp_path / "out.parquet")]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "column 'junk': a text cell of 5,000,000 characters" in err, err
    assert not (tmp_path / "out.parquet").exists()


def test_compressed_plain_text_pages_beyond_the_bound_are_refused_from_the_footer(tmp_path, monkeypatch):
    """The same value in plain pages, zstd-compressed: the footer says what they decompress to."""
    path = text_parquet(tmp_path / "plain.parquet", 30, "y" * 2_000_000, dictionary=False)
    monkeypatch.setattr(io, "MAX_PARQUET_CHUNK_BYTES", 50_000_000)
    refused(
        finishes(lambda: io.read_csv(path)),
        "plain.parquet: column 'junk', row group 1: 60 MB once decompressed, more than the 50 MB",
        "smaller row groups",
    )
    monkeypatch.setattr(io, "MAX_PARQUET_CHUNK_BYTES", 1 << 30)
    refused(finishes(lambda: io.read_csv(path)), "row 1, column 'junk': a text cell of 2,000,000 characters")


def test_many_rows_of_a_moderate_value_are_refused_against_the_memory(tmp_path, monkeypatch):
    """100 000 rows of one 250-character value: 100 MB as numpy text, over a 100 MB machine's budget (half of it);
    the whole file's budget is spent block by block (25 MB blocks, each under a 150 MB machine's 75 MB budget,
    together over it)."""
    path = text_parquet(tmp_path / "wide.parquet", 100_000, "z" * 250)
    monkeypatch.setattr(io, "available_bytes", lambda: 100_000_000)
    monkeypatch.setattr(io, "READ_BYTES_PER_VALUE", 1)  # the numbers fit: only the text is over
    text = refused(finishes(lambda: io.read_csv(path)), "wide.parquet: column 'junk': its text (100,000 cells)")
    assert "would take 100 MB" in text and "more than the 50 MB left for text (half the memory free)" in text
    monkeypatch.setattr(io, "available_bytes", lambda: 150_000_000)
    refused(finishes(lambda: io.read_parquet(path, chunk_rows=25_000)), "its text (25,000 cells)", "left for text")
    monkeypatch.setattr(io, "available_bytes", lambda: 1_000_000_000)
    assert io.read_parquet(path, chunk_rows=25_000).extra["junk"].shape == (100_000,)


def test_a_csv_whose_text_is_over_the_memory_is_refused(tmp_path, monkeypatch):
    lines = ["s1x,s1y,s1z,note"] + [f"{30000 + k},{k % 5},{k % 3},{'n' * 200}" for k in range(5000)]
    path = tmp_path / "notes.csv"
    path.write_text("\n".join(lines) + "\n")
    monkeypatch.setattr(io, "available_bytes", lambda: 2_000_000)
    monkeypatch.setattr(io, "READ_BYTES_PER_VALUE", 0)
    for read in (lambda: io.read_csv(path), lambda: io.read_csv(path, drop_bad=True)):
        refused(finishes(read), "notes.csv: column 'note': its text (", "left for text")


def test_a_nested_column_is_refused_from_the_schema(tmp_path):
    table = pa.table({**readings(10), "tags": pa.array([["a", "b"]] * 10)})
    pq.write_table(table, tmp_path / "nested.parquet")
    refused(
        finishes(lambda: io.read_csv(tmp_path / "nested.parquet")),
        "nested.parquet: column 'tags' holds list<element: string> values; magcal reads flat columns",
    )


@pytest.mark.parametrize(
    "cells",
    [
        ["alpha", None, "b", "alpha", "ccc" * 40, None],
        [b"raw", b"bytes", None, b"raw", b"x", b"y"],
        ["é", "日本", "", "é", None, ""],
    ],
    ids=["text", "bytes", "unicode"],
)
def test_dictionary_text_reads_as_its_decoded_cells(tmp_path, cells):
    """A dictionary column's text (the Parquet reader reads every text and bytes column so) is exactly what the
    decoded column gives: nulls 'None', bytes as numpy writes them, the same width."""
    array = pa.array(cells * 50)
    dictionary = array.dictionary_encode()
    row = lambda k: f"row {k + 1}"
    got = io._arrow_text(dictionary, "f", "c", row)
    assert got.dtype == io._arrow_text(array, "f", "c", row).dtype
    np.testing.assert_array_equal(got, io._arrow_text(array, "f", "c", row))
    chunked = pa.chunked_array([dictionary[:100], dictionary[100:]])
    np.testing.assert_array_equal(io._arrow_text(chunked, "f", "c", row), io._arrow_text(array, "f", "c", row))
    if all(isinstance(c, str) or c is None for c in cells):  # through a file: the groups and a channel
        table = pa.table({**readings(len(array)), "note": array, "group": array})
        pq.write_table(table, tmp_path / "plain.parquet", use_dictionary=False)
        pq.write_table(table, tmp_path / "dict.parquet", use_dictionary=True)
        a, b = io.read_parquet(tmp_path / "plain.parquet"), io.read_parquet(tmp_path / "dict.parquet")
        np.testing.assert_array_equal(a.extra["note"], b.extra["note"])
        np.testing.assert_array_equal(a.extra["note"], io._arrow_text(array, "f", "c", row))
        np.testing.assert_array_equal(a.group, b.group)


def test_numbers_written_as_dictionary_text_read_as_numbers(tmp_path):
    """A reading column written as text (dictionary-encoded) reads as the numbers it spells, nulls NaN-refused."""
    n = 300
    table = pa.table(
        {
            "s1x": pa.array([f"{20_000 + k % 7}" for k in range(n)]).dictionary_encode(),
            "s1y": np.full(n, 1_000.0),
            "s1z": np.full(n, 40_000.0),
        }
    )
    pq.write_table(table, tmp_path / "t.parquet")
    ds = io.read_parquet(tmp_path / "t.parquet")
    np.testing.assert_array_equal(ds.readings_nT[0, :, 0], 20_000 + np.arange(n) % 7)
