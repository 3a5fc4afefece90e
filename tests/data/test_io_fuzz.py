"""Fuzzing every reader: generated and mutated inputs give a result or a one-line error, within a time bound.

The readers: CSV (whole-file and streaming), Parquet (mutated, and built from its structure: row groups, declared
rows against ``max_rows``, text widths; and text columns as dictionaries of entries up to beyond the longest cell), ArduPilot DataFlash ``.bin``, PX4 ``.ulg`` (mutated, and built from its
grammar: formats nesting, wide, cyclic, subscribed many times), the calibration JSON (loaded, then applied; and
every number replaced by extreme values, then every output written and checked finite), the workbench's session
document (mutated, and built around its bounds: history rows, undo masks, values), the live sources' line parser (bytes in, chunks out, the recording read back) and live URLs. Each target takes a hypothesis-drawn case: valid files built here
with known content, then mutated (bytes flipped, inserted, deleted, truncated, format fields overwritten), or
generated from the format's own grammar (headers, metadata lines, numbers from NaN to 1e308, JSON values of
every type at every key).

The contract checked on every case (:func:`outcome`):

* it returns, or raises :class:`~magcal.core.errors.MagcalError` (``DatasetError``, ``LiveError``,
  ``SessionFileError`` are kinds of it) whose message is one line: any other exception is a *traceback*;
* it ends within :data:`TIME_BOUND_S` (run in a thread; one still running then is a *hang*).

``MAGCAL_FUZZ_EXAMPLES`` sets the examples per target (default 600, a tenth of it for the Parquet dictionary and
session-rows targets: the file runs in about two minutes on two cores); ``benchmarks/fuzz_readers.py`` runs many more
and prints the counts.
"""

from __future__ import annotations

import contextlib
import io as _stdio
import json
import os
import re
import signal
import socket
import string
import struct
import threading
import time
import warnings
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import magcal
from magcal.calibration.calibration import Calibration
from magcal.core.errors import MagcalError
from magcal.data import io
from magcal.data.dataset import MAX_ABS_VALUE
from magcal.data.lineformats import LineTemplate
from magcal.data.live import LineParser, Recorder, _LineSource, open_source
from magcal.data.logs import read_log

pytest.importorskip("pymavlink")
pytest.importorskip("pyulog")
pytest.importorskip("pyarrow")

#: Examples per target (env ``MAGCAL_FUZZ_EXAMPLES``).
N_EXAMPLES = int(os.environ.get("MAGCAL_FUZZ_EXAMPLES", "600"))
#: Longest a case may run (s) before it counts as a hang: far above any case's time on a loaded machine.
TIME_BOUND_S = float(os.environ.get("MAGCAL_FUZZ_TIME_BOUND_S", "20"))


# -- the contract ------------------------------------------------------------------------------------------------
@dataclass
class Tally:
    """What a target's cases gave."""

    tried: int = 0
    results: int = 0
    messages: int = 0
    tracebacks: int = 0
    hangs: int = 0
    slowest_s: float = 0.0
    first_failure: str | None = None
    kinds: Counter = field(default_factory=Counter)


TALLIES: dict[str, Tally] = {}


def outcome(name, fn):
    """Run ``fn()`` in a thread within :data:`TIME_BOUND_S`; tally it; fail on a traceback, a hang or a message
    of several lines."""
    tally = TALLIES.setdefault(name, Tally())
    box = {}

    def run():
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                box["value"] = fn()
        except BaseException as exc:  # judged below
            box["error"] = exc

    thread = threading.Thread(target=run, daemon=True)
    t0 = time.monotonic()
    thread.start()
    thread.join(TIME_BOUND_S)
    seconds = time.monotonic() - t0
    tally.tried += 1
    tally.slowest_s = max(tally.slowest_s, seconds)
    if thread.is_alive():
        tally.hangs += 1
        tally.first_failure = tally.first_failure or f"hang (> {TIME_BOUND_S:g} s)"
        raise AssertionError(f"{name}: still running after {TIME_BOUND_S:g} s (a hang)")
    error = box.get("error")
    if error is None:
        tally.results += 1
        return box["value"]
    if isinstance(error, MagcalError) and "\n" not in str(error).strip() and str(error).strip():
        tally.messages += 1
        tally.kinds[type(error).__name__] += 1
        return None
    tally.tracebacks += 1
    text = f"{type(error).__name__}: {str(error)[:300]}"
    tally.first_failure = tally.first_failure or text
    raise AssertionError(f"{name}: {text}") from error


@pytest.fixture(scope="module", autouse=True)
def _report_tallies():
    """With ``MAGCAL_FUZZ_REPORT=DIR`` (benchmarks/fuzz_readers.py), write this process's tallies there."""
    yield
    folder = os.environ.get("MAGCAL_FUZZ_REPORT")
    if folder:
        doc = {name: {**t.__dict__, "kinds": dict(t.kinds)} for name, t in TALLIES.items()}
        Path(folder, f"tally-{os.getpid()}.json").write_text(json.dumps(doc))


FUZZ = settings(
    max_examples=N_EXAMPLES,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.function_scoped_fixture],
)


# -- mutations of bytes --------------------------------------------------------------------------------------------
_INTERESTING = [
    b"\x00",
    b"\xff",
    b"\x7f",
    b"\x80",
    b"\x00\x00\x00\x00",
    b"\xff\xff\xff\xff",
    struct.pack("<f", float("nan")),
    struct.pack("<f", float("inf")),
    struct.pack("<f", 3e38),
    struct.pack("<d", float("nan")),
    struct.pack("<d", 1e308),
    struct.pack("<Q", 2**64 - 1),
    b"\n",
    b"\r",
    b",",
    b'"',
    b"nan",
    b"1e999",
]

_op = st.one_of(
    st.tuples(st.just("flip"), st.floats(0, 1), st.integers(0, 7)),
    st.tuples(st.just("set"), st.floats(0, 1), st.sampled_from(_INTERESTING)),
    st.tuples(st.just("insert"), st.floats(0, 1), st.binary(min_size=1, max_size=64)),
    st.tuples(st.just("delete"), st.floats(0, 1), st.integers(1, 200)),
    st.tuples(st.just("truncate"), st.floats(0, 1), st.none()),
    st.tuples(st.just("repeat"), st.floats(0, 1), st.integers(1, 300)),
)


def mutate(data: bytes, ops) -> bytes:
    """Apply the byte mutations ``ops`` (positions as fractions of the length)."""
    b = bytearray(data)
    for kind, where, arg in ops:
        k = min(int(where * len(b)), max(len(b) - 1, 0))
        if kind == "flip" and b:
            b[k] ^= 1 << arg
        elif kind == "set":
            b[k : k + len(arg)] = arg
        elif kind == "insert":
            b[k:k] = arg
        elif kind == "delete":
            del b[k : k + arg]
        elif kind == "truncate":
            del b[k:]
        elif kind == "repeat":
            b[k:k] = b[k : k + arg]
    return bytes(b)


def mutated(seeds):
    """A seed with a few mutations (three times in four), or bytes from nowhere."""
    few = st.builds(mutate, st.sampled_from(seeds), st.lists(_op, min_size=1, max_size=2))
    many = st.builds(mutate, st.sampled_from(seeds), st.lists(_op, min_size=1, max_size=6))
    return st.one_of(few, few, many, st.binary(max_size=2048))


# -- the seed files -----------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def seeds(tmp_path_factory):
    """Valid files of each kind, built here with known content."""
    from tests.data.test_logs import ardupilot_case, px4_case, write_dataflash, write_ulog

    d = tmp_path_factory.mktemp("fuzz_seeds")
    ds = magcal.simulate_timeseries("chi2017", n_samples=60, seed=1, rate_hz=10.0)
    whole = magcal.simulate_timeseries("chi2017", n_samples=300, seed=2, rate_hz=1.0)
    one = whole.replace(readings_nT=whole.readings_nT[:1], baseline_m=None)  # its first sensor alone
    out = {"dataset": ds, "one": one}
    io.write_csv(d / "a.csv", ds)
    io.write_csv(d / "b.csv", one)
    out["csv"] = [(d / "a.csv").read_bytes(), (d / "b.csv").read_bytes()]
    io.write_parquet(d / "a.parquet", ds)
    out["parquet"] = [(d / "a.parquet").read_bytes()]
    messages, *_ = ardupilot_case(n=40, compasses=2)
    write_dataflash(d / "a.bin", messages)
    out["bin"] = [(d / "a.bin").read_bytes()]
    topics, *_ = px4_case(n=40)
    write_ulog(d / "a.ulg", topics)
    out["ulg"] = [(d / "a.ulg").read_bytes()]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fit = magcal.calibrate(one, effects=["temperature_bias"])  # a calibration with an effect block
        out["calibration"] = [fit.calibration.to_dict(), magcal.calibrate(whole).calibration.to_dict()]
    from magcal_workbench.state import SessionState

    st_ = SessionState(60, 4, "/tmp/a.csv", None)
    out["session"] = [st_.to_dict()]
    return out


def _write(tmp_path, name, data: bytes) -> Path:
    path = tmp_path / name
    path.write_bytes(data)
    return path


# -- CSV -----------------------------------------------------------------------------------------------------------
_number_text = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-(10**20), 10**20).map(str),
    st.sampled_from(["nan", "NaN", "inf", "-inf", "1e308", "1e-308", "3e38", "1e31", "", " ", "1_000", "0x10", "١٢"]),
    st.text(max_size=8),
)
_column_name = st.one_of(
    st.sampled_from(["s1x", "s1y", "s1z", "s2x", "s2y", "s2z", "x", "y", "z", "t", "temp", "qw", "qx", "qy", "qz"]),
    st.sampled_from(["ref_total", "group", "s5x", "s0x", "S1X", ""]),
    st.text(max_size=6),
)
_meta_line = st.builds(
    lambda k, v: f"# {k}: {v}",
    st.sampled_from(["units", "lsb_nT", "baseline_m", "reference_total_nT", "noise_nT", "site"]),
    st.one_of(_number_text, st.sampled_from(["nT", "uT", "G", "mG", "counts", "furlongs"])),
)


_LAYOUTS = [["s1x", "s1y", "s1z"], ["t", "x", "y", "z", "temp"], ["t", "s1x", "s1y", "s1z", "s2x", "s2y", "s2z"]]


@st.composite
def csv_text(draw):
    if draw(st.booleans()):  # a layout magcal reads, perhaps with more columns
        header = draw(st.sampled_from(_LAYOUTS)) + draw(st.lists(_column_name, max_size=2))
    else:
        header = draw(st.lists(_column_name, min_size=1, max_size=9))
    cell = st.one_of(st.floats(-1e5, 1e5).map(repr), st.floats(-1e5, 1e5).map(repr), _number_text)
    width = st.one_of(st.just(len(header)), st.just(len(header)), st.integers(max(len(header) - 1, 0), len(header) + 1))
    rows = draw(st.lists(width.flatmap(lambda w: st.lists(cell, min_size=w, max_size=w)), max_size=8))
    meta = draw(st.lists(_meta_line, max_size=3))
    end = draw(st.sampled_from(["\n", "\r\n", "\r"]))
    lines = meta + [",".join(header)] + [",".join(r) for r in rows]
    return end.join(lines).encode("utf-8", "surrogatepass")


def _read_csv_both(path):
    """The whole-file reader (pyarrow first, then the line reader), strict; then the streaming reader of ``apply``
    dropping bad rows. A message from the strict reader is fine; the streaming one gives the result."""
    try:
        magcal.read_csv(path)
    except MagcalError:
        pass
    with io.CsvSource(path) as src:
        parts = [chunk.dataset for chunk in src.chunks(7, drop_bad=True)]
    return io.concatenate(parts) if parts else None


def test_csv(seeds, tmp_path):
    @FUZZ
    @given(st.one_of(mutated(seeds["csv"]), csv_text()))
    def check(data):
        path = _write(tmp_path, "case.csv", data)
        ds = outcome("CSV", lambda: _read_csv_both(path))
        if ds is not None:  # whatever it read is finite and within the rule
            assert np.all(np.abs(ds.readings_nT) <= MAX_ABS_VALUE)

    check()


# -- Parquet -------------------------------------------------------------------------------------------------------
_cell = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.none(), st.integers(-(2**63), 2**63 - 1))


@st.composite
def parquet_bytes(draw):
    import pyarrow as pa
    import pyarrow.parquet as pq

    names = draw(st.lists(_column_name, min_size=1, max_size=6, unique=True))
    n = draw(st.integers(0, 5))
    cols = {}
    for name in names:
        kind = draw(st.sampled_from(["float", "int", "text", "mixed"]))
        if kind == "float":
            cols[name] = pa.array(draw(st.lists(st.floats(allow_nan=True), min_size=n, max_size=n)), pa.float64())
        elif kind == "int":
            cols[name] = pa.array(draw(st.lists(st.integers(-(2**63), 2**63 - 1), min_size=n, max_size=n)), pa.int64())
        elif kind == "text":
            cols[name] = pa.array(draw(st.lists(st.text(max_size=5), min_size=n, max_size=n)), pa.string())
        else:
            cols[name] = pa.array(
                draw(st.lists(st.one_of(st.floats(), st.none()), min_size=n, max_size=n)), pa.float64()
            )
    table = pa.table(cols)
    meta = draw(
        st.one_of(st.none(), st.binary(max_size=40), st.dictionaries(st.text(max_size=8), _number_text, max_size=3))
    )
    if meta is not None:
        raw = meta if isinstance(meta, bytes) else json.dumps(meta).encode()
        table = table.replace_schema_metadata({b"magcal": raw})
    buf = _stdio.BytesIO()
    pq.write_table(table, buf)
    return buf.getvalue()


def test_parquet(seeds, tmp_path):
    @FUZZ
    @given(st.one_of(mutated(seeds["parquet"]), parquet_bytes()))
    def check(data):
        path = _write(tmp_path, "case.parquet", data)
        outcome("Parquet", lambda: magcal.read_csv(path))

    check()


# -- DataFlash .bin ------------------------------------------------------------------------------------------------
_fmt_op = st.tuples(st.just("fmt"), st.integers(0, 4), st.integers(0, 255), st.sampled_from([4, 3, 5]))


def mutate_bin(data, ops):
    """Byte mutations, and ``("fmt", k, value, field)``: overwrite a field byte (Type 3, Length 4) of FMT number k."""
    b = bytearray(data)
    plain = []
    for op in ops:
        if op[0] == "fmt":
            _, k, value, offset = op
            starts = [m for m in range(len(b) - 2) if b[m : m + 3] == b"\xa3\x95\x80"][: k + 1]
            if starts:
                b[starts[-1] + offset] = value
        else:
            plain.append(op)
    return mutate(bytes(b), plain)


def test_dataflash(seeds, tmp_path):
    ops = st.lists(st.one_of(_op, _fmt_op), min_size=1, max_size=5)

    @FUZZ
    @given(st.one_of(st.builds(mutate_bin, st.sampled_from(seeds["bin"]), ops), st.binary(max_size=2048)))
    def check(data):
        path = _write(tmp_path, "case.bin", data)
        outcome("DataFlash .bin", lambda: read_log(path))

    check()


# -- ULog .ulg -----------------------------------------------------------------------------------------------------
def test_ulog(seeds, tmp_path):
    @FUZZ
    @given(mutated(seeds["ulg"]))
    def check(data):
        path = _write(tmp_path, "case.ulg", data)
        outcome("PX4 .ulg", lambda: read_log(path))

    check()


# -- ULog structure: formats, nesting, subscriptions drawn from the format's grammar ----------------------------------
_ULOG_BASIC = ["uint8_t", "int16_t", "uint32_t", "uint64_t", "float", "double", "bool", "char"]


def _ulog_message(kind, payload: bytes) -> bytes:
    return struct.pack("<HB", len(payload) & 0xFFFF, ord(kind)) + payload[:0xFFFF]


@st.composite
def ulog_structure(draw):
    """A ULog built from its grammar: formats of basic and nested fields (arrays up to and past pyulog's 65535,
    chains and cycles of nesting, long names), subscriptions (``A``) of any of them, some data and damaged bytes."""
    names = [f"m{k}" for k in range(draw(st.integers(1, 6)))] + ["sensor_mag", "vehicle_attitude"]
    out = bytearray(b"ULog\x01\x12\x35" + bytes([1]) + struct.pack("<Q", 0))
    if draw(st.booleans()):
        out += _ulog_message("B", bytes(16) + struct.pack("<QQQ", 0, 0, 0))
    chain = draw(st.sampled_from([True, False]))  # each format nests the next: flattened sizes multiply
    for k, name in enumerate(names):
        fields = []
        if chain and k + 1 < len(names):
            size = draw(st.sampled_from([4096, 255, 8, 2, 0]))
            fields.append(f"{names[k + 1]}{f'[{size}]' if size else ''} n{k};")
        for _ in range(draw(st.integers(1 if k + 1 == len(names) else 0, 4))):
            kind = draw(st.one_of(st.sampled_from(_ULOG_BASIC), st.sampled_from(names), st.text("abt_[]0", max_size=5)))
            size = draw(st.sampled_from([0, 0, 0, 1, 2, 3, 8, 255, 4096, 9000, 65535, 70000]))
            field_name = draw(
                st.one_of(st.sampled_from(["x", "y", "z", "timestamp", "q"]), st.integers(1, 3000).map("n".__mul__))
            )
            fields.append(f"{kind}{f'[{size}]' if size else ''} {field_name};")
        out += _ulog_message("F", f"{name}:{''.join(fields)}".encode())
    if draw(st.booleans()):
        out += draw(st.binary(max_size=64))  # a damaged stretch before the subscriptions
    subscriptions = [names[0]] + draw(st.lists(st.sampled_from(names), max_size=11))
    for k, name in enumerate(subscriptions):
        out += _ulog_message("A", struct.pack("<BH", draw(st.integers(0, 3)), k) + name.encode())
    for _ in range(draw(st.integers(0, 20))):
        msg_id = draw(st.integers(0, max(len(subscriptions), 1)))
        out += _ulog_message("D", struct.pack("<H", msg_id) + draw(st.binary(max_size=80)))
    return bytes(out)


def test_ulog_structure(tmp_path):
    @FUZZ
    @given(ulog_structure())
    def check(data):
        path = _write(tmp_path, "structure.ulg", data)
        outcome("PX4 .ulg structure", lambda: read_log(path))

    check()


# -- Parquet structure: row groups, declared rows, text widths -------------------------------------------------------
@st.composite
def parquet_structure(draw):
    """A Parquet file of a few row groups (constant or varied readings, a text column with one long cell among
    short ones, nulls) and the ``max_rows`` it is read with."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    groups = draw(st.lists(st.integers(0, 4000), min_size=1, max_size=4))
    width = draw(st.sampled_from([0, 1, 100, 5000, 40_000]))
    tables = []
    for g, n in enumerate(groups):
        if draw(st.booleans()):
            cols = {a: pa.array(np.full(n, 30_000.0 + g)) for a in ("s1x", "s1y", "s1z")}
        else:
            rng = np.random.default_rng(g)
            cols = {a: pa.array(rng.normal(0, 30_000.0, n)) for a in ("s1x", "s1y", "s1z")}
        text = ["b"] * n
        if n and width:
            text[draw(st.integers(0, n - 1))] = "a" * width
        if draw(st.booleans()):
            cols["note"] = pa.array([None if k % 7 == 3 else t for k, t in enumerate(text)], pa.string())
        tables.append(pa.table(cols))
    schema = tables[0].schema
    buf = _stdio.BytesIO()
    with pq.ParquetWriter(buf, schema, compression=draw(st.sampled_from(["none", "snappy", "zstd"]))) as writer:
        for table in tables:
            if table.schema.equals(schema):
                writer.write_table(table, row_group_size=draw(st.sampled_from([1000, 1 << 20])))
    return buf.getvalue(), draw(st.sampled_from([None, 0, 1, 500, 5000]))


def test_parquet_structure(tmp_path):
    @FUZZ
    @given(parquet_structure())
    def check(case):
        data, max_rows = case
        path = _write(tmp_path, "structure.parquet", data)
        ds = outcome("Parquet structure", lambda: magcal.read_csv(path, max_rows=max_rows))
        if ds is not None:  # what it read is within the limit and the rule
            assert not max_rows or ds.n_samples <= max_rows
            assert np.all(np.abs(ds.readings_nT) <= MAX_ABS_VALUE)

    check()


@st.composite
def parquet_dictionary(draw):
    """A Parquet file whose text columns are dictionaries: entries of drawn lengths (a few beyond the longest
    cell read, :data:`magcal.data.io.MAX_TEXT_CELL_CHARS`) for any number of rows, nulls among them, in a kept
    column, the groups or a reading column (numbers written as text), written as dictionaries or plain."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    n = draw(st.integers(0, 3000))
    lengths = draw(
        st.lists(st.sampled_from([0, 1, 30, 5000, io.MAX_TEXT_CELL_CHARS, 2_500_000]), min_size=1, max_size=4)
    )
    if max(lengths) > 100_000:  # a few rows of the long entries: the writer decodes a column it cannot keep whole
        n = min(n, 40)
    entries = pa.array(["x" * k for k in lengths])
    rng = np.random.default_rng(draw(st.integers(0, 99)))
    index = rng.integers(0, len(lengths), n).astype(np.int32)
    nulls = rng.random(n) < draw(st.sampled_from([0.0, 0.1, 1.0]))
    text = pa.DictionaryArray.from_arrays(pa.array(index, mask=nulls), entries)
    cols = {a: pa.array(rng.normal(0, 30_000.0, n)) for a in ("s1x", "s1y", "s1z")}
    where = draw(st.sampled_from(["note", "group", "s1x"]))
    if where == "s1x":  # readings spelled as text, one long entry among them
        text = pa.DictionaryArray.from_arrays(pa.array(index), pa.array([f"{30_000 + k}" for k in lengths]))
    cols[where] = text
    buf = _stdio.BytesIO()
    pq.write_table(
        pa.table(cols),
        buf,
        use_dictionary=draw(st.booleans()),
        compression=draw(st.sampled_from(["none", "zstd"])),
        row_group_size=draw(st.sampled_from([700, 1 << 20])),
    )
    return buf.getvalue()


#: Examples of the costlier targets (files of megabytes, documents of thousands of rows): a tenth.
FEW = settings(FUZZ, max_examples=max(N_EXAMPLES // 10, 10))


def test_parquet_dictionary(tmp_path):
    @FEW
    @given(parquet_dictionary())
    def check(data):
        path = _write(tmp_path, "dictionary.parquet", data)
        ds = outcome("Parquet dictionary", lambda: magcal.read_csv(path))
        if ds is not None:  # no cell beyond the bound was made
            for values in [*ds.extra.values(), *([ds.group] if ds.group is not None else [])]:
                if values.dtype.kind == "U":
                    assert values.dtype.itemsize // 4 <= io.MAX_TEXT_CELL_CHARS

    check()


# -- calibration JSON ----------------------------------------------------------------------------------------------
_json_value = st.recursive(
    st.one_of(
        st.none(),
        st.booleans(),
        st.integers(-(10**20), 10**20),
        st.floats(allow_nan=False, allow_infinity=False),
        st.sampled_from([1e308, -1e308, 1e-308, 0.0]),
        st.text(max_size=10),
    ),
    lambda inner: st.one_of(st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=6), inner, max_size=4)),
    max_leaves=12,
)


_leaf_number = st.one_of(
    st.floats(allow_nan=False, allow_infinity=False),
    st.sampled_from([0, -0.0, 1, -1, 1e308, -1e308, 1e-308, 5e-324, 2**63, 10**30]),
)


def _paths(doc, prefix=()):
    """Every key path of a JSON document."""
    yield prefix
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield from _paths(v, (*prefix, k))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            yield from _paths(v, (*prefix, i))


@st.composite
def mutated_document(draw, seeds):
    doc = json.loads(json.dumps(draw(st.sampled_from(seeds))))
    for _ in range(draw(st.integers(1, 2))):
        paths = [p for p in _paths(doc) if p]
        if not paths:
            break
        path = draw(st.sampled_from(paths))
        parent = doc
        for key in path[:-1]:
            parent = parent[key]
        choice = draw(st.integers(0, 3))
        if choice == 0 and isinstance(parent, dict):
            del parent[path[-1]]
        elif choice == 1 and isinstance(parent[path[-1]], (int, float)) and not isinstance(parent[path[-1]], bool):
            parent[path[-1]] = draw(_leaf_number)  # a number for a number: passes more checks, reaches further
        else:
            parent[path[-1]] = draw(_json_value)
    return json.dumps(doc).encode()


def _load_and_apply(path, dataset):
    cal = Calibration.load(path)
    if cal.n_sensors == dataset.n_sensors:
        corrected = cal.correct(dataset)
        assert np.asarray(corrected).size
    return cal


def test_calibration_json(seeds, tmp_path):
    raw = [json.dumps(d).encode() for d in seeds["calibration"]]

    @FUZZ
    @given(st.one_of(mutated_document(seeds["calibration"]), mutated(raw)))
    def check(data):
        path = _write(tmp_path, "case.json", data)
        datasets = {1: seeds["one"], 4: seeds["dataset"]}
        outcome("calibration JSON", lambda: _load_and_apply(path, datasets[_n_sensors(data)]))

    check()


def _n_sensors(data):
    try:
        return 1 if len(json.loads(data)["sensors"]) == 1 else 4
    except Exception:  # not a document with sensors: any dataset will do
        return 4


# -- calibration JSON values: every number at every place, then every output written ---------------------------------
_extreme_number = st.one_of(
    st.sampled_from([1e308, -1e308, 1e300, 1e61, 1e60, 1e31, 1e30, -1e30, 1e-30, 1e-300, 5e-324, 0.0, -0.0]),
    st.sampled_from([10**400, -(10**400), 2**63, 10**30, 1, -1]),
    st.floats(allow_nan=False, allow_infinity=False),
)


@st.composite
def valued_document(draw, seeds):
    """A seed calibration with one to three of its numbers (Cinv, bias, an effect's parameter or constant, the
    covariance, the baseline...) replaced by extreme ones."""
    doc = json.loads(json.dumps(draw(st.sampled_from(seeds))))
    numbers = [p for p in _paths(doc) if p and _is_number(_at(doc, p))]
    for path in draw(st.lists(st.sampled_from(numbers), min_size=1, max_size=3)):
        _at(doc, path[:-1])[path[-1]] = draw(_extreme_number)
    return json.dumps(doc).encode()


def _at(doc, path):
    for key in path:
        doc = doc[key]
    return doc


def _is_number(value):
    return isinstance(value, (int, float)) and not isinstance(value, bool)


#: A value that is not a finite number as a writer would print it: ``nan``, ``inf``, ``-inf``, ``Infinity`` (JSON),
#: ``inff`` (the C header's float suffix); not the words that hold the letters (``infinite``).
_NOT_FINITE = re.compile(r"(?<![a-z])(nan|inf|infinity)f?(?![a-z])")


def _every_output(path, survey, out):
    """Load the calibration, correct the survey to a CSV and export every firmware format: what is written holds
    no value that is not a finite number (a refusal is a message)."""
    from magcal.output.apply import apply_file
    from magcal.output.bundle import calibration_bytes
    from magcal.output.export import FORMATS, export_calibration

    cal = Calibration.load(path)
    written = [calibration_bytes(cal)]
    if cal.n_sensors == 1:  # the one-sensor seed's survey
        apply_file(cal, survey, out, progress=False)
        written.append(out.read_bytes())
    for fmt in FORMATS:
        try:
            written.append(export_calibration(cal, fmt, force=True).text.encode())
        except MagcalError:
            continue
    for content in written:
        found = _NOT_FINITE.search(content.decode().lower())
        assert found is None, content.decode()[max(found.start() - 200, 0) : found.end() + 50]


def test_calibration_json_values(seeds, tmp_path):
    survey = _write(tmp_path, "survey.csv", seeds["csv"][1])  # the one sensor the calibrations are made for

    @FUZZ
    @given(valued_document([seeds["calibration"][0]]))
    def check(data):
        path = _write(tmp_path, "values.json", data)
        outcome("calibration values", lambda: _every_output(path, survey, tmp_path / "out.csv"))

    check()


# -- the workbench's session document -------------------------------------------------------------------------------
def test_session_document(seeds):
    from magcal_workbench.sessionfile import read_session_bytes

    raw = [json.dumps(d).encode() for d in seeds["session"]]

    @FUZZ
    @given(st.one_of(mutated_document(seeds["session"]), mutated(raw)))
    def check(data):
        outcome("session document", lambda: read_session_bytes(data))

    check()


@st.composite
def session_rows(draw):
    """A session document with histories around their bound, undo masks around theirs, and (sometimes) a list of
    many values: the file's bytes and the rows it holds."""
    from magcal_workbench.state import MAX_HISTORY_ROWS, SessionState, StepRecord, VectorStep

    n = draw(st.sampled_from([8, 300]))
    st_ = SessionState(n, 1)
    for k in range(draw(st.sampled_from([0, 40, 120]))):
        st_.selection.reject([k % n])
    doc = st_.to_dict()
    counts = {key: draw(st.sampled_from([0, 3, MAX_HISTORY_ROWS, MAX_HISTORY_ROWS + 1, 2500])) for key in ("h", "v")}
    step = StepRecord("fit", 3.0, 2.0, [], 1, "x" * draw(st.sampled_from([0, 50])), 0.1).to_dict()
    vector = VectorStep("vector fit", [1.0, 2.0, None], 4.0, [], 1, "", 0.2).to_dict()
    doc["history"] = [dict(step, step=f"fit {k}") for k in range(counts["h"])]
    doc["vector_history"] = [dict(vector, step=f"vector {k}") for k in range(counts["v"])]
    if draw(st.booleans()):  # values beyond the count a session is read with, in a field the reader ignores
        doc["padding"] = [0] * draw(st.sampled_from([10, 1_100_000]))
    return json.dumps(doc, indent=draw(st.sampled_from([None, 1]))).encode(), counts


def test_session_rows():
    from magcal_workbench.sessionfile import read_session_bytes
    from magcal_workbench.state import MAX_HISTORY_ROWS

    @FEW
    @given(session_rows())
    def check(case):
        data, counts = case
        state = outcome("session rows", lambda: read_session_bytes(data))
        if state is not None:  # the newest rows within the bound, and a note for each history cut
            assert len(state.history) == min(counts["h"], MAX_HISTORY_ROWS)
            assert len(state.vector_history) == min(counts["v"], MAX_HISTORY_ROWS)
            if counts["h"]:
                assert state.history[-1].step == f"fit {counts['h'] - 1}"
            cut = sum(c > MAX_HISTORY_ROWS for c in counts.values())
            assert sum("steps: the oldest" in note for note in state.notes) == cut

    check()


# -- live lines: bytes in, chunks out, the recording read back ---------------------------------------------------
class _Bytes(_LineSource):
    def __init__(self, blocks, parser):
        super().__init__("fuzz://lines", parser)
        self._blocks = list(blocks)

    def _receive(self, timeout_s):
        if not self._blocks:
            self.ended = True
            return b""
        return self._blocks.pop(0)


def _line_bytes():
    line = st.lists(_number_text, min_size=0, max_size=6).map(lambda f: ",".join(f).encode("utf-8", "surrogatepass"))
    return st.lists(
        st.one_of(line.map(lambda b: b + b"\n"), st.binary(max_size=64), st.just(b"x" * 5000)), min_size=1, max_size=6
    )


def _live(columns, units, blocks, path):
    parser = LineParser(columns, units=units, lsb_nT="100" if units == "counts" else None)
    source = _Bytes(blocks, parser)
    chunks = []
    with Recorder(path) as rec:
        for _ in range(len(blocks) + 1):
            chunk = source.read(timeout_s=0.01)
            rec.write(chunk)
            chunks.append(chunk)
    if rec.n_written:  # what the live parser accepted, the CSV reader reads back
        back = magcal.read_csv(path)
        assert back.n_samples == rec.n_written
    return chunks


def test_live_lines(tmp_path):
    columns = st.one_of(
        st.sampled_from(["x,y,z", "t,x,y,z", "t,x,y,z,temp", "t,s1x,s1y,s1z,s2x,s2y,s2z", "_,x,y,z"]),
        st.lists(_column_name, max_size=6).map(",".join),
    )
    units = st.sampled_from(["nT", "uT", "G", "mG", "counts", "furlongs", ""])
    counter = iter(range(10**9))

    @FUZZ
    @given(columns, units, _line_bytes())
    def check(cols, unit, blocks):
        path = tmp_path / f"rec{next(counter)}.csv"
        outcome("live lines", lambda: _live(cols, unit, blocks, path))

    check()


# -- live templates: any template the page allows, against any line, in linear time --------------------------------
#: Longest one line may take to match (CPU s of the thread): lines of 4 KB take milliseconds; the old patterns took
#: seconds to for ever.
LINE_TIME_BOUND_S = float(os.environ.get("MAGCAL_FUZZ_LINE_BOUND_S", "0.5"))
#: A line and a template drawn from the same characters: numbers, signs, spaces, the marks sketches print.
_LINE_CHARS = "0123456789 ,;:=-+.eEinfa[]()|*$#Qxyz\t"
_FIELDS = ["{t}", "{temp}", "{roll}", "{gx}", "{lat}"]
_LITERAL = st.one_of(
    st.text(alphabet=_LINE_CHARS.replace("\t", ""), max_size=4),
    st.sampled_from(["{{", "}}", "mag", "acc", "x=", ": [", ", ", "] uT", "nan", "inf", "e", "1", "-", "  "]),
)


@st.composite
def page_template(draw):
    """A template the page lets through (:data:`magcal_workbench.live.TEMPLATE_CHARS` printable characters): x, y
    and z among other fields, skips (several in a row too) and literals, in any order; one in ten with stray
    braces, an unknown field or a format spec (refused)."""
    from magcal_workbench.live import TEMPLATE_CHARS

    fields = ["{x}", "{y}", "{z}"] + draw(st.lists(st.sampled_from(_FIELDS), unique=True, max_size=3))
    parts = fields + draw(st.lists(st.one_of(st.just("{_}"), _LITERAL), max_size=20))
    if draw(st.integers(0, 9)) == 0:  # now and then what the page may send that is no template: one clear line
        parts.append(draw(st.text(alphabet="{}_xyzqt:!0 ", min_size=1, max_size=6)))
    order = draw(st.permutations(parts))
    text = "".join(order)[:TEMPLATE_CHARS]
    return text if text.isprintable() else text.replace("\t", " ")


@st.composite
def template_line(draw, template):
    """A line for ``template``: random text, the template filled in with numbers (then mutated), or a fragment
    repeated up to 4 KB (the attacks: digits, ``1 1 1``, signs, the template's own marks)."""
    kind = draw(st.sampled_from(["random", "filled", "filled", "repeated", "repeated"]))
    try:
        list(string.Formatter().parse(template))
    except ValueError:  # no template: nothing to fill in
        kind = "random"
    if kind == "random":
        return draw(st.text(alphabet=_LINE_CHARS, max_size=200))
    if kind == "filled":
        numbers = st.one_of(
            st.sampled_from(["1", "-2.5", "3e4", ".5", "+2.", "nan", "-inf", "infinity"]),
            st.floats(allow_nan=False).map(repr),
            st.sampled_from(["1.2.3", "--1", "1e", "", "x"]),
        )
        out = []
        for literal, name, _, _ in string.Formatter().parse(template):
            out.append(literal)
            if name is not None:  # a number between spaces (or not: two numbers then run together)
                gap = st.sampled_from(["", " ", " ", "  ", "\t"])
                value = draw(numbers) if name != "_" else draw(st.text(alphabet=_LINE_CHARS, max_size=6))
                out.append(draw(gap) + value + draw(gap))
        line = "".join(out)
        for op, where, text in draw(
            st.lists(st.tuples(st.sampled_from("idrr"), st.floats(0, 1), _LITERAL), max_size=2)
        ):
            k = int(where * len(line))
            line = line[:k] + text + line[k:] if op == "i" else line[:k] + line[k + 1 :] if op == "d" else line
        return line
    fragment = draw(
        st.one_of(
            st.sampled_from(["1", "1 ", "- ", ",1", "1e", "1.", " ", "a", "x=1 ", "[1, ", "{", "nan "]),
            st.text(alphabet=_LINE_CHARS, min_size=1, max_size=8),
            st.just(template[: draw(st.integers(1, 12))] or "1"),
        )
    )
    n = draw(st.sampled_from([64, 600, 4096]))
    head = draw(st.sampled_from(["", "7 ", "mag ", "Magnetometer reading: ["]))
    return (head + fragment * (n // len(fragment) + 1))[:n]


_WORD = re.compile(r"\w+|\S")
_NUM_CORE = re.compile(r"[-+]?(?:(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?|(?i:nan|inf(?:inity)?))")
_NUM_BEFORE = re.compile(r"(?<![\d.])(?<![\d.][eE])(?<![\d.][eE][-+])")
_NUM_AFTER = re.compile(r"(?![\d.]|[eE][-+]?\d)")


def reference_accepts(template, line):
    """Whether ``line`` fits ``template`` as the docs say (``docs/formats.md``), by brute force over every place each
    token could take: literals exactly, whitespace optional around each, ``{_}`` any text, a field the longest
    number starting there (not inside another, not followed by more of one). Slow and plainly right; short lines."""
    tokens = []
    for literal, name, _, _ in string.Formatter().parse(template):
        tokens += [("lit", w) for w in _WORD.findall(literal)]
        if name is not None:
            tokens.append(("skip", None) if name.strip() in ("_", "-", "") else ("num", None))
    n = len(line)
    ws_end = list(range(n + 1))
    for p in range(n - 1, -1, -1):
        ws_end[p] = ws_end[p + 1] if line[p].isspace() else p
    number_end = [None] * (n + 1)
    for p in range(n):
        if _NUM_BEFORE.match(line, p):
            number_end[p] = next(
                (q for q in range(n, p, -1) if _NUM_CORE.fullmatch(line, p, q) and _NUM_AFTER.match(line, q)), None
            )

    def spaces(places):
        return {q for p in places for q in range(p, ws_end[p] + 1)}

    places = spaces({0})
    for kind, word in tokens:
        if kind == "skip":
            places = set(range(min(places), n + 1)) if places else set()
        elif kind == "lit":
            places = {p + len(word) for p in places if line.startswith(word, p)}
        else:
            places = {number_end[p] for p in places if number_end[p] is not None}
        places = spaces(places)
    return n in places


@contextlib.contextmanager
def _alarm(seconds, what):
    """Stop a block that runs past ``seconds`` (a regular expression that backtracks holds the interpreter, so a
    thread cannot bound it, but it checks for signals): the case then counts as a hang."""

    def expired(signum, frame):
        raise TimeoutError(f"{what}: still running after {seconds:g} s")

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGALRM, expired)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def _template_case(template, lines):
    """Open the page's template as a parser (or refuse it in one line); every line within
    :data:`LINE_TIME_BOUND_S`, read or refused with its reason; a short line read exactly when the reference says it
    fits, its fields numbers. Tallied per template refused and per line."""
    tally = TALLIES.setdefault("live templates", Tally())
    try:
        parser = LineParser(template=template)
    except MagcalError as exc:  # a repeated or unknown field, a stray brace: one line
        tally.tried += 1
        assert "\n" not in str(exc).strip() and str(exc).strip()
        tally.messages += 1
        tally.kinds["template refused"] += 1
        return
    for line in lines:
        tally.tried += 1
        t0 = time.thread_time()
        try:
            with _alarm(TIME_BOUND_S, "live templates"):
                try:
                    sample = parser.parse_sample(line)
                    fields = parser.template.match(line.strip())
                except ValueError as exc:
                    sample, fields, reason = None, None, str(exc)
                    assert reason.startswith(("template: ", "not a number: ")), reason
                    assert "\n" not in reason
        except TimeoutError:
            tally.hangs += 1
            tally.first_failure = tally.first_failure or f"hang: {template!r} on {line[:60]!r}... ({len(line)})"
            raise AssertionError(tally.first_failure) from None
        seconds = time.thread_time() - t0
        tally.slowest_s = max(tally.slowest_s, seconds)
        assert seconds < LINE_TIME_BOUND_S, f"{seconds:.3f} s for {template!r} on a line of {len(line)}"
        if fields is not None:
            assert [float(v) for v in fields] and sample is not None or line.lstrip().startswith("#")
        if len(line) <= 64 and not line.strip().startswith("#") and line.strip():
            assert (fields is not None) == reference_accepts(template, line.strip()), (template, line)
        if sample is not None:
            tally.results += 1
        else:
            tally.messages += 1
            tally.kinds["line refused" if fields is None else "line skipped"] += 1


def test_live_templates():
    """Random templates the page allows against random, filled-in and repeated lines."""

    @FUZZ
    @given(st.data())
    def check(data):
        template = data.draw(page_template())
        lines = data.draw(st.lists(template_line(template), min_size=1, max_size=4))
        _template_case(template, lines)

    check()


def _cpu_per_line(template, line, budget_s=0.02, tries=3):
    """CPU seconds of one match (the least of ``tries`` batches of at least ``budget_s``)."""
    best = float("inf")
    for _ in range(tries):
        n, t0 = 0, time.thread_time()
        while True:
            with contextlib.suppress(ValueError):
                template.match(line)
            n += 1
            spent = time.thread_time() - t0
            if spent >= budget_s:
                break
        best = min(best, spent / n)
    return best


def test_live_template_time_is_linear_in_the_line():
    """The worst case stays linear: four times the line (1 KB -> 4 KB of a repeated fragment) costs at most eight
    times the CPU time (linear: four; the old patterns: sixteen times, or minutes with skips)."""

    @settings(FUZZ, max_examples=max(20, N_EXAMPLES // 20))
    @given(
        page_template(),
        st.one_of(
            st.sampled_from(["1", "1 ", "- ", ",1", "1e", " ", "a"]), st.text(_LINE_CHARS, min_size=1, max_size=6)
        ),
    )
    def check(text, fragment):
        try:
            template = LineTemplate(text)
        except ValueError:
            return
        line = (fragment * (4096 // len(fragment) + 1))[:4096]
        with _alarm(TIME_BOUND_S, "live templates"):
            short, long = _cpu_per_line(template, line[:1024]), _cpu_per_line(template, line)
        assert long <= 8 * short + 50e-6, f"{text!r} on {fragment!r}: {short * 1e3:.3f} -> {long * 1e3:.3f} ms"

    check()


# -- live URLs ----------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def closed_port():
    """A loopback TCP port held bound but not listening: a connection to it is refused at once."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.bind(("127.0.0.1", 0))
    yield sock.getsockname()[1]
    sock.close()


_param_value = st.one_of(_number_text, st.sampled_from(["1", "0", "-1", "1e12", "true", "lines", "mavlink"]))


@st.composite
def live_url(draw, closed_port, tmp):
    scheme = draw(st.sampled_from(["sim", "tcp", "udp", "serial", "http", "", "SIM"]))
    if scheme.lower() == "sim":
        where = draw(st.one_of(st.sampled_from(["chi2017", "ding2024", "nope"]), st.text(max_size=10)))
    elif scheme == "serial":
        where = str(tmp / draw(st.text(alphabet="abc/_.", max_size=8)))  # never a real device
    else:
        host = draw(st.sampled_from(["127.0.0.1", "[::1", "[::1]", "", "localhost", "a" * 300, "127.0.0.1:1:2"]))
        port = draw(st.one_of(st.just(closed_port), st.integers(-5, 70000).map(str), st.text(max_size=4)))
        where = f"{host}:{port}"
    keys = ["n", "rate", "speed", "seed", "loop", "baud", "columns", "units", "lsb", "timeout", "format", "sep", "x"]
    params = draw(st.dictionaries(st.sampled_from(keys), _param_value, max_size=4))
    if scheme in ("tcp", "udp") and draw(st.booleans()):
        params["timeout"] = "0.5"
    query = "&".join(f"{k}={v}" for k, v in params.items())
    return f"{scheme}://{where}" + (f"?{query}" if query else "")


def _open_and_read(url):
    source = open_source(url)
    try:
        source.read(timeout_s=0.05, max_samples=10)
    finally:
        source.close()


def test_live_urls(closed_port, tmp_path):
    @FUZZ
    @given(live_url(closed_port, tmp_path))
    def check(url):
        outcome("live URLs", lambda: _open_and_read(url))

    check()
