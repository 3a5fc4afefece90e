"""Hardening II, the files' side: bombs refused before they allocate, bad values never written.

Each test crafts its hostile input itself, small: a ULog whose formats nest (``t0:t1[2] a;`` ... flattening into 2^N
fields inside pyulog), a Parquet file whose footer declares millions of constant rows, a CSV cell whose padding
would take gigabytes, a calibration whose finite values overflow (``C^-1 = 1e308 I``), an LSB of 1e308, a FIFO
named as a file. Each checks the exact outcome: one line naming the file and what to do, within seconds, and
nothing written. Waits are bounded (a reader that would hang fails the test instead of hanging it).
"""

from __future__ import annotations

import json
import os
import struct
import threading
import time
import warnings

import numpy as np
import pytest

import magcal
from magcal.calibration.calibration import Calibration, SensorCalibration
from magcal.core.errors import MagcalError
from magcal.data import io, logs
from magcal.data.dataset import DatasetError
from magcal.data.logs import read_log
from tests.data.test_logs import ardupilot_case, px4_case, write_dataflash, write_ulog

pytest.importorskip("pymavlink")
pytest.importorskip("pyulog")
pytest.importorskip("pyarrow")


def finishes(fn, seconds=10.0):
    """``fn()``'s result or exception (``{"value"|"error": ..., "seconds": ...}``), or a test failure if it has not
    ended within ``seconds``."""
    box = {}

    def run():
        try:
            box["value"] = fn()
        except BaseException as exc:  # handed back to the test
            box["error"] = exc

    thread = threading.Thread(target=run, daemon=True)
    t0 = time.monotonic()
    thread.start()
    thread.join(seconds)
    if thread.is_alive():
        pytest.fail(f"still running after {seconds} s (a hang)")
    box["seconds"] = time.monotonic() - t0
    return box


def refused(box, error=MagcalError, *needles):
    """The message of the ``error`` ``box`` holds: one line, holding every needle."""
    assert "error" in box, f"accepted: {box.get('value')!r}"
    exc = box["error"]
    assert isinstance(exc, error), repr(exc)
    text = str(exc)
    assert "\n" not in text and text.strip(), text
    for needle in needles:
        assert needle in text, text
    return text


def _cli(argv, capsys):
    from magcal.cli import main

    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def one_line_refusal(code, err, *needles):
    assert code == 2, err
    assert "Traceback" not in err and err.count("\n") == 1, err
    for needle in needles:
        assert needle in err, err


# -- ULog: formats that nest ---------------------------------------------------------------------------------------
def _ulog_msg(kind, payload: bytes) -> bytes:
    return struct.pack("<HB", len(payload), ord(kind)) + payload


def _ulog_head() -> bytearray:
    return bytearray(b"ULog\x01\x12\x35" + bytes([1]) + struct.pack("<Q", 0))


def nested_ulog(depth, subscriptions=1, topic="t0", before=b"", after=b"") -> bytes:
    """``t0:t1[2] a;`` ... ``t{depth}:uint8_t x;``: t0 flattens into 2^depth fields; ``subscriptions`` A messages
    of ``topic``; ``before`` put between the header and the formats, ``after`` at the end."""
    out = _ulog_head() + before
    for k in range(depth):
        out += _ulog_msg("F", f"t{k}:t{k + 1}[2] a;".encode())
    out += _ulog_msg("F", f"t{depth}:uint8_t x;".encode())
    for s in range(subscriptions):
        out += _ulog_msg("A", struct.pack("<BH", 0, s) + topic.encode())
    return bytes(out + after)


def test_ulog_nesting_beyond_the_bound_is_refused_from_the_definitions(tmp_path):
    path = tmp_path / "nest.ulg"
    path.write_bytes(nested_ulog(logs.ULOG_MAX_NESTING + 2))  # 1024 fields: pyulog read it, without the bound
    box = finishes(lambda: read_log(path), 10)
    refused(box, DatasetError, "nest.ulg: byte 16", f"nest more than {logs.ULOG_MAX_NESTING} levels", "crafted")
    assert box["seconds"] < 2


def test_the_issues_ulog_bomb_ends_at_once(tmp_path):
    """Depth 22 (4 million fields, a few hundred bytes): 24 s and 3 GB inside pyulog before the bound."""
    path = tmp_path / "bomb.ulg"
    path.write_bytes(nested_ulog(22))
    assert path.stat().st_size < 600
    box = finishes(lambda: read_log(path), 10)
    refused(box, DatasetError, "bomb.ulg", "levels deep")
    assert box["seconds"] < 2


def test_a_format_of_too_many_fields_and_a_format_that_nests_itself(tmp_path):
    wide = _ulog_head() + _ulog_msg("F", f"wide:uint8_t[{logs.ULOG_MAX_FIELDS + 1}] x;".encode())
    (tmp_path / "wide.ulg").write_bytes(bytes(wide) + _ulog_msg("A", struct.pack("<BH", 0, 0) + b"wide"))
    text = refused(finishes(lambda: read_log(tmp_path / "wide.ulg")), DatasetError, "byte 16")
    assert f"format wide flattens into {logs.ULOG_MAX_FIELDS + 1:,} fields" in text
    loop = _ulog_head() + _ulog_msg("F", b"t0:t1 a;") + _ulog_msg("F", b"t1:t0 b;")
    (tmp_path / "loop.ulg").write_bytes(bytes(loop) + _ulog_msg("A", struct.pack("<BH", 0, 0) + b"t0"))
    refused(finishes(lambda: read_log(tmp_path / "loop.ulg")), DatasetError, "format t0 nests itself (t0 -> t1 -> t0)")


def test_formats_behind_a_damaged_stretch_are_bounded_inside_pyulog(tmp_path):
    """The pre-scan stops at a damaged stretch; pyulog steps over it byte by byte and finds the formats after it:
    the subscription is sized before pyulog flattens it."""
    damaged = b"\x20\x4e\xee"  # a message of 20000 bytes of an unknown type: damaged, by pyulog's own test
    padding = _ulog_msg("I", b"\x0cchar[1] pad" + b"x" * 40_000) * 3  # enough bytes after it for pyulog's reads
    path = tmp_path / "hidden.ulg"
    path.write_bytes(nested_ulog(22, before=damaged, after=padding))
    assert logs.check_ulog_definitions(path) == 0  # the pre-scan saw no format
    box = finishes(lambda: read_log(path), 10)
    refused(box, DatasetError, "hidden.ulg", "levels deep")


def test_many_subscriptions_of_a_large_format_are_bounded_in_total(tmp_path):
    """Each A message is flattened anew by pyulog (kept or not): 60 subscriptions of a 9000-field format pass
    each bound but not the total."""
    out = _ulog_head() + _ulog_msg("F", b"big:uint8_t[9000] x;")
    for s in range(60):
        out += _ulog_msg("A", struct.pack("<BH", 0, s) + b"big")
    path = tmp_path / "many.ulg"
    path.write_bytes(bytes(out))
    text = refused(finishes(lambda: read_log(path)), DatasetError, "many.ulg", "subscriptions flatten into more than")
    assert f"{logs.ULOG_MAX_SUBSCRIBED_FIELDS:,} fields" in text


def test_a_ulog_read_stops_at_its_deadline(tmp_path):
    """pyulog steps over damaged bytes one by one, reading up to 64 kB at each: 2 MB of 0xFF took about 10 s."""
    topics, *_ = px4_case(n=40)
    write_ulog(tmp_path / "good.ulg", topics)
    path = tmp_path / "slow.ulg"
    path.write_bytes((tmp_path / "good.ulg").read_bytes() + b"\xff" * 2_000_000)
    box = finishes(lambda: read_log(path, timeout_s=0.3), 10)
    refused(box, DatasetError, "slow.ulg: reading stopped after 0.3 s")
    assert box["seconds"] < 3


def test_real_formats_pass_the_bounds(tmp_path):
    """A log written like PX4's (nested arrays of basic types) reads as before; the sizes are the flattened ones."""
    from pyulog import ULog

    topics, raw_nT, *_ = px4_case(n=60)
    write_ulog(tmp_path / "ok.ulg", topics)
    assert logs.check_ulog_definitions(tmp_path / "ok.ulg") == 2
    assert read_log(tmp_path / "ok.ulg").n_samples == 60
    fmt = ULog.MessageFormat(b"esc_status:uint64_t timestamp;esc_report[8] esc;uint8_t[2] pad;", None)
    esc = ULog.MessageFormat(b"esc_report:int32_t esc_rpm;float esc_voltage;", None)
    sizes = logs.ulog_format_sizes({"esc_status": fmt.fields, "esc_report": esc.fields})
    assert sizes["esc_report"][0] == 2 and sizes["esc_status"][0] == 1 + 8 * 2 + 2
    assert sizes["esc_status"][2] == 2  # nested one level


def test_a_ulog_bomb_uploaded_in_the_page_is_a_message(bench):
    wb = bench()
    wb.uploads.last = ("bomb.ulg", nested_ulog(logs.ULOG_MAX_NESTING + 4))
    t0 = time.monotonic()
    wb.uploads.do_reread(None)
    assert wb.worker.wait(30) and time.monotonic() - t0 < 10
    msg = wb.ctrl.message
    assert "bomb.ulg" in msg and "levels deep" in msg and "Unexpected error" not in msg
    assert wb.ctrl.dataset.n_samples == 300  # the bench's own data stay open


# -- Parquet: rows from the footer ---------------------------------------------------------------------------------
def constant_parquet(path, groups, rows_per_group=1_000_000):
    """A Parquet file of ``groups`` row groups of one constant reading each: tiny on disk, any number of rows."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    col = pa.array(np.full(rows_per_group, 30_000.0))
    table = pa.table({"s1x": col, "s1y": col, "s1z": col})
    with pq.ParquetWriter(path, table.schema, compression="zstd") as writer:
        for _ in range(groups):
            writer.write_table(table, row_group_size=rows_per_group)
    return groups * rows_per_group


def test_a_parquet_file_of_more_rows_than_the_default_is_refused_before_reading(tmp_path, capsys):
    path = tmp_path / "many.parquet"
    rows = constant_parquet(path, io.MAX_READ_ROWS // 1_000_000 + 1)
    assert path.stat().st_size < 1_000_000  # 11 million rows in some hundred kB
    t0 = time.monotonic()
    code, _, err = _cli(["calibrate", path], capsys)
    one_line_refusal(code, err, f"many.parquet: {rows:,} rows, more than the {io.MAX_READ_ROWS:,}", "--max-rows N")
    assert time.monotonic() - t0 < 5  # read from the footer: no row was decoded


def test_max_rows_limits_every_whole_file_read(tmp_path, capsys):
    path = tmp_path / "small.parquet"
    constant_parquet(path, 1, rows_per_group=5000)
    for command in (["calibrate"], ["diagnose"], ["align"]):
        code, _, err = _cli([*command, path, "--max-rows", 1000], capsys)
        one_line_refusal(code, err, "small.parquet: 5,000 rows, more than the 1,000 read at once")
    ds = magcal.simulate("chi2017", n_samples=300, seed=3)
    io.write_csv(tmp_path / "rec.csv", ds)
    with pytest.raises(DatasetError, match=r"rec\.csv: 300 rows, more than the 100 read"):
        io.read_csv(tmp_path / "rec.csv", max_rows=100)  # a CSV: counted as it is read, when asked
    assert io.read_csv(tmp_path / "rec.csv", max_rows=300).n_samples == 300
    with pytest.raises(DatasetError, match=r"rec\.csv \(at line 3\d\d\): 300 rows, more than the 100 read"):
        io.read_csv(tmp_path / "rec.csv", max_rows=100, drop_bad=True)  # the line reader too
    code, _, err = _cli(["calibrate", tmp_path / "rec.csv", "--max-rows", -1], capsys)
    one_line_refusal(code, err, "--max-rows must be a number of rows")


def test_a_parquet_file_larger_than_the_free_memory_is_refused_before_reading(tmp_path, monkeypatch):
    path = tmp_path / "big.parquet"
    constant_parquet(path, 1, rows_per_group=200_000)
    monkeypatch.setattr(io, "available_bytes", lambda: 10_000_000)  # 10 MB free
    text = refused(finishes(lambda: io.read_csv(path)), DatasetError, "big.parquet: 200,000 rows would take about")
    assert "more than the 0.01 GB of memory free" in text
    refused(finishes(lambda: io.read_csv(path, max_rows=0)), DatasetError, "memory free")  # 0: no row limit
    monkeypatch.setattr(io, "available_bytes", lambda: None)  # not known (not Linux): only the rows
    assert io.read_csv(path).n_samples == 200_000


def test_dataflash_messages_are_counted_against_the_free_memory(tmp_path, monkeypatch):
    messages, *_ = ardupilot_case(n=200, compasses=1)
    write_dataflash(tmp_path / "f.bin", messages)
    monkeypatch.setattr(logs, "available_bytes", lambda: 1000)
    text = refused(finishes(lambda: read_log(tmp_path / "f.bin")), DatasetError, "f.bin: ")
    assert "messages of the kinds magcal reads" in text and "memory free" in text
    monkeypatch.setattr(logs, "available_bytes", lambda: 1 << 40)
    assert read_log(tmp_path / "f.bin").n_samples == 200


# -- text columns: padding -----------------------------------------------------------------------------------------
def test_one_long_text_cell_among_short_ones_is_refused(tmp_path):
    """Every cell of a text column is held as wide as the longest: a 20 000-character cell above 2000 short ones
    would take 160 MB from a 24 kB file."""
    lines = ["s1x,s1y,s1z,note", "30000,1,2," + "a" * 20_000] + [f"{30000 + k},{k % 5},{k % 3},b" for k in range(2000)]
    path = tmp_path / "notes.csv"
    path.write_text("\n".join(lines) + "\n")
    for read in (lambda: io.read_csv(path), lambda: io.read_csv(path, drop_bad=True)):
        text = refused(finishes(read), DatasetError, "notes.csv: line 2, column 'note': a text cell of 20,000")
        assert "160 MB" in text
    import pyarrow as pa
    import pyarrow.parquet as pq

    cols = {a: np.full(2001, 30_000.0) for a in ("s1x", "s1y", "s1z")}
    pq.write_table(pa.table({**cols, "group": ["a" * 20_000] + ["b"] * 2000}), tmp_path / "notes.parquet")
    refused(finishes(lambda: io.read_csv(tmp_path / "notes.parquet")), DatasetError, "row 1, column 'group'")
    ok = ["s1x,s1y,s1z,note"] + [f"{30000 + k},{k % 5},{k % 3},{'c' * 30}" for k in range(2000)]
    (tmp_path / "even.csv").write_text("\n".join(ok) + "\n")  # cells of one width: no padding, read
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert io.read_csv(tmp_path / "even.csv").extra["note"].dtype == np.dtype("<U30")


def test_joining_blocks_of_long_and_short_text_is_refused():
    ds = magcal.simulate("chi2017", n_samples=3010, seed=1)
    one = ds.replace(readings_nT=ds.readings_nT[:1], baseline_m=None)
    wide = one.subset(np.arange(3010) < 10).replace(extra={"note": np.array(["w" * 20_000] * 10)})
    narrow = one.subset(np.arange(3010) >= 10).replace(extra={"note": np.array(["n"] * 3000)})
    refused(finishes(lambda: io.concatenate([wide, narrow])), DatasetError, "column 'note': a text cell of 20,000")


# -- messages quote little -----------------------------------------------------------------------------------------
def test_a_message_quotes_at_most_a_short_piece_of_each_value(tmp_path, capsys):
    lines = ["s1x,s1y,s1z"] + ["9" * 5000 + ",1,2"] * 5 + ["1,2,3"]
    (tmp_path / "long.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError) as err:
        io.read_csv(tmp_path / "long.csv")
    text = str(err.value)
    assert len(text) < 1000 and text.count("(5,000 characters)") == 5 and "not a finite number" in text
    header = ",".join(f"{'c' * 3000}{k}" for k in range(50))
    (tmp_path / "names.csv").write_text(header + "\n1\n")
    with pytest.raises(DatasetError) as err:
        io.read_csv(tmp_path / "names.csv")
    assert "no magnetometer columns" in str(err.value) and len(str(err.value)) < 1200
    (tmp_path / "meta.csv").write_text("# units: " + "u" * 9000 + "\nx,y,z\n1,2,3\n")
    code, _, err_text = _cli(["calibrate", tmp_path / "meta.csv"], capsys)
    one_line_refusal(code, err_text, "unknown unit", "(9,000 characters)")
    assert len(err_text) < 600


# -- the LSB -------------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def counts_file(tmp_path_factory):
    d = tmp_path_factory.mktemp("counts")
    ds = magcal.simulate("chi2017", n_samples=200, seed=1)
    one = ds.replace(readings_nT=np.round(ds.readings_nT[:1] / 150.0), baseline_m=None)
    io.write_csv(d / "counts.csv", one, metadata={"units": "counts", "lsb_nT": "150"})
    return d / "counts.csv"


@pytest.mark.parametrize("lsb", ["1e308", "1e-300", "1e10", "1e-7", "-150", "nan"])
def test_an_extreme_lsb_is_refused_with_one_line(counts_file, tmp_path, capsys, lsb):
    path = tmp_path / "c.csv"
    path.write_text(counts_file.read_text().replace("lsb_nT: 150", f"lsb_nT: {lsb}"))
    code, _, err = _cli(["calibrate", path], capsys)
    one_line_refusal(code, err, "c.csv: line", "metadata lsb_nT", "positive number of nT per count", "from 1e-06")
    code, _, err = _cli(["calibrate", counts_file, "--lsb", lsb], capsys)
    one_line_refusal(code, err, "--lsb", "positive number of nT per count")


def test_the_lsb_range_reads_every_real_part(counts_file, tmp_path):
    lo, hi = io.LSB_RANGE_nT
    for lsb in (lo, 0.012, 150.0, 91.74, hi):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ds = io.read_csv(counts_file, lsb_nT=lsb)
        assert float(ds.metadata["lsb_nT"]) == lsb and np.all(np.isfinite(ds.readings_nT))


def test_an_extreme_lsb_in_the_page_is_a_message(bench, counts_file):
    wb = bench()
    content = counts_file.read_bytes().replace(b"lsb_nT: 150", b"lsb_nT: 1e-300")
    wb.uploads.last = ("counts.csv", content)
    wb.uploads.do_reread(None)
    assert wb.worker.wait(60)
    msg = wb.ctrl.message
    assert "counts.csv" in msg and "nT per count" in msg and "Unexpected error" not in msg
    wb.uploads.last = ("counts.csv", counts_file.read_bytes())
    wb.panels.upload_units.value = "counts"
    wb.panels.upload_lsb.value = 1e-300  # within the box's own range (0 ... 1e9)
    wb.uploads.do_reread(None)
    assert wb.worker.wait(60)
    msg = wb.ctrl.message
    assert "LSB box" in msg and "nT per count" in msg and "Unexpected error" not in msg


# -- calibration files: every parameter bounded --------------------------------------------------------------------
@pytest.fixture(scope="module")
def calibrations(tmp_path_factory):
    """One sensor with a temperature effect, and four with a baseline; their data."""
    d = tmp_path_factory.mktemp("cals")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        whole = magcal.simulate_timeseries("chi2017", n_samples=300, seed=2, rate_hz=1.0)
        one = whole.replace(readings_nT=whole.readings_nT[:1], baseline_m=None)
        single = magcal.calibrate(one, effects=["temperature_bias"]).calibration.to_dict()
        four = magcal.calibrate(whole).calibration.to_dict()
    io.write_csv(d / "one.csv", one)
    io.write_csv(d / "four.csv", whole)
    return d, single, four


def _edited(doc, edit):
    doc = json.loads(json.dumps(doc))
    edit(doc)
    return doc


_HUGE_EDITS = {
    "Cinv": (lambda d: d["sensors"][0].update(Cinv=(np.eye(3) * 1e308).tolist()), "sensors[0].Cinv[0][0] = 1e+308"),
    "bias": (lambda d: d["sensors"][0].update(bias_nT=[1e300, 0.0, 0.0]), "sensors[0].bias_nT[0] = 1e+300"),
    "effect parameter": (
        lambda d: d["effect_params"][0]["params"].update(beta_x_nT_per_K=1e300),
        "effect_params[0].params.beta_x_nT_per_K = 1e+300",
    ),
    "effect constant": (
        lambda d: d["effect_params"][0]["state"].update(reference_temperature_C=-1e300),
        "effect_params[0].state.reference_temperature_C = -1e+300",
    ),
    "platform term": (
        lambda d: d.update(platform_terms={"eddy_ms": [[[1e300, 0, 0], [0, 0, 0], [0, 0, 0]]]}),
        "platform_terms.eddy_ms[0][0][0] = 1e+300",
    ),
    "covariance": (
        lambda d: d["base_covariance"]["matrix"][0].__setitem__(0, 1e100),
        "base_covariance.matrix[0][0] = 1e+100 is beyond +-1e+60",
    ),
    "a damaged key's line end": (
        lambda d: d["effect_params"][0]["state"].update({"a\nb": 1e300}),
        "effect_params[0].state.'a\\nb' = 1e+300 is beyond",
    ),
    "a reference field beyond any float": (
        lambda d: d.update(reference_total_nT=10**400),
        "'reference_total_nT' must be a number of nT from",
    ),
    "an integer beyond any float": (
        lambda d: d["sensors"][0].update(bias_nT=[10**400, 0, 0]),
        "sensors[0].bias_nT[0] = an integer of 401 digits is beyond +-1e+30",
    ),
}


@pytest.mark.parametrize("what", list(_HUGE_EDITS))
def test_a_calibration_parameter_beyond_the_bound_is_refused(calibrations, tmp_path, what):
    _, single, _ = calibrations
    edit, needle = _HUGE_EDITS[what]
    path = tmp_path / "cal.json"
    path.write_text(json.dumps(_edited(single, edit)))
    text = refused(finishes(lambda: Calibration.load(path)), MagcalError, f"{path}: {needle}", "recalibrate")
    assert len(text) < 400


@pytest.mark.parametrize("baseline", [1e-300, 1e300])
def test_a_baseline_beyond_the_bound_is_refused(calibrations, tmp_path, baseline):
    _, _, four = calibrations
    path = tmp_path / "cal.json"
    path.write_text(json.dumps({**four, "baseline_m": baseline}))
    refused(finishes(lambda: Calibration.load(path)), MagcalError, "baseline_m", "from 1e-30 to 1e+30")


def test_the_issues_huge_calibration_exports_and_applies_nothing(calibrations, tmp_path, capsys):
    """C^-1 = 1e308 I: ArduPilot's COMPASS_DIA were nan, PX4's XSCALE inf, apply's rows inf, all with exit 0."""
    d, single, _ = calibrations
    doc = {**single, "effect_params": [], "effects": [], "base_covariance": None}
    doc["sensors"] = [{**single["sensors"][0], "Cinv": (np.eye(3) * 1e308).tolist()}]
    cal = tmp_path / "huge.json"
    cal.write_text(json.dumps(doc))
    for fmt in ("ardupilot", "px4", "c"):
        code, out, err = _cli(["export", cal, "--format", fmt, "-o", tmp_path / f"p.{fmt}"], capsys)
        one_line_refusal(code, err, "huge.json: sensors[0].Cinv[0][0] = 1e+308 is beyond +-1e+30")
    for name in ("o.csv", "o.parquet"):
        code, _, err = _cli(["apply", cal, d / "one.csv", "-o", tmp_path / name], capsys)
        one_line_refusal(code, err, "beyond +-1e+30")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["huge.json"]


def _huge(calibration_doc):
    """A calibration made in memory (no file, so no bound) whose C^-1 overflows every correction."""
    cal = Calibration.from_dict(calibration_doc)
    sensors = [SensorCalibration(np.eye(3) * 1e308, s.bias_nT, s.R) for s in cal.sensors]
    return Calibration(sensors, reference_total_nT=cal.reference_total_nT, baseline_m=cal.baseline_m)


def test_no_output_holds_a_value_that_is_not_finite(calibrations, tmp_path):
    """A calibration no file gave (made in code, so never bounded): every writer refuses its infinities."""
    from magcal.output import bundle
    from magcal.output.apply import apply_file
    from magcal.output.export import export_calibration

    d, single, four = calibrations
    huge = _huge({**single, "effect_params": [], "effects": [], "base_covariance": None})
    for fmt in ("ardupilot", "px4", "c"):
        refused(finishes(lambda fmt=fmt: export_calibration(huge, fmt)), MagcalError, "would be ", "32-bit float")
    for name in ("o.csv", "o.parquet"):
        text = refused(finishes(lambda name=name: apply_file(huge, d / "one.csv", tmp_path / name)), MagcalError)
        assert "one.csv: " in text and "s1x_cal would be " in text and "nothing is written" in text
    text = refused(finishes(lambda: apply_file(_huge(four), d / "four.csv", tmp_path / "o4.csv")), MagcalError)
    assert "four.csv: line " in text and "not a finite number" in text
    one = io.read_csv(d / "one.csv")
    refused(finishes(lambda: bundle.raw_mask_bytes(huge, one)), MagcalError, "sample 1: s1_residual_nT would be inf")
    refused(finishes(lambda: bundle.calibration_bytes(huge)), MagcalError, "sensors[0].Cinv[0][0] = 1e+308 is beyond")
    with pytest.raises(MagcalError, match="it is not written"):
        huge.save(tmp_path / "cal.json")
    content, readme = bundle.export_all(huge, dataset=one, data_path=d / "one.csv", parquet=False)
    assert sum("not written" in line for line in readme) == 6  # the calibration, 3 parameter files, 2 data files
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_rows_without_attitude_keep_their_documented_nan(tmp_path):
    """The finite check keeps the world columns' NaN of a sample without attitude (their documented gap)."""
    from magcal.output.apply import refuse_non_finite

    ds = magcal.simulate("chi2017", n_samples=4, seed=1)
    q = np.tile([1.0, 0.0, 0.0, 0.0], (4, 1))
    q[2] = np.nan
    ds = ds.replace(attitude_wxyz=q)
    values = np.ones((4, 2))
    values[2, 1] = np.nan
    refuse_non_finite(values, ["a", "b"], "s.csv", ds)  # row 3 has no attitude: its NaN is the gap
    values[1, 0] = np.nan
    with pytest.raises(MagcalError, match=r"s\.csv: row 2: a would be nan"):
        refuse_non_finite(values, ["a", "b"], "s.csv", ds)
    values[1, 0] = 1.0
    values[2, 1] = np.inf  # an infinity is never a gap
    with pytest.raises(MagcalError, match="row 3: b would be inf"):
        refuse_non_finite(values, ["a", "b"], "s.csv", ds)


# -- FIFOs and devices ---------------------------------------------------------------------------------------------
@pytest.fixture
def fifo(tmp_path):
    """A FIFO nobody writes to (opening it for reading blocks for ever); unblocked after the test."""
    if not hasattr(os, "mkfifo"):
        pytest.skip("no FIFOs here")
    made = []

    def make(name):
        path = tmp_path / name
        os.mkfifo(path)
        made.append(path)
        return path

    yield make
    for path in made:  # a reader still blocked in open() (a failing test) is let go
        try:
            fd = os.open(path, os.O_WRONLY | os.O_NONBLOCK)
            os.close(fd)
        except OSError:
            pass


def test_an_effects_file_that_is_a_fifo_is_refused_at_once(fifo):
    from magcal.model.plugins import load_effects_file

    path = fifo("effects.py")
    refused(finishes(lambda: load_effects_file(path), 5), MagcalError, "effects.py: is a FIFO", "Python file")


def test_a_sessions_effects_file_that_is_a_fifo_is_a_message(bench, fifo):
    wb = bench()
    path = str(fifo("mine.py"))
    wb.ctrl.state.effects_files.append(path)
    box = finishes(lambda: wb.ctrl.load_session_effects_files(), 5)
    said = str(box.get("error", "")) + " " + str(wb.ctrl.message)
    assert "is a FIFO" in said and "mine.py" in said


@pytest.mark.parametrize("name", ["data.csv", "data.parquet", "log.ulg", "log.bin"])
def test_a_data_file_that_is_a_fifo_is_refused_at_once(fifo, name):
    path = fifo(name)
    refused(finishes(lambda: io.read_csv(path), 5), DatasetError, f"{name}: is a FIFO")


def test_a_calibration_or_survey_that_is_a_fifo_is_refused_at_once(calibrations, fifo, tmp_path, capsys):
    d, single, _ = calibrations
    cal = tmp_path / "cal.json"
    cal.write_text(json.dumps(single))
    pipe = fifo("pipe.json")
    box = finishes(lambda: _cli(["export", pipe, "--format", "px4"], capsys), 5)
    one_line_refusal(*box["value"][::2], "pipe.json: is a FIFO")
    survey = fifo("survey.csv")
    box = finishes(lambda: _cli(["apply", cal, survey, "-o", tmp_path / "o.csv"], capsys), 5)
    one_line_refusal(*box["value"][::2], "survey.csv: is a FIFO")
    if os.path.exists("/dev/zero"):  # a device, named like a log: it never ends
        (tmp_path / "zero.ulg").symlink_to("/dev/zero")
        refused(finishes(lambda: read_log(tmp_path / "zero.ulg"), 5), DatasetError, "is a character device")


def test_the_workbench_refuses_a_fifo_as_its_data_or_a_session_file(tmp_path, capsys):
    """A FIFO given as the workbench's data file, or standing in a session's folder as its session.json, would block
    the reader for ever: both are refused with one line."""
    from magcal_workbench.session import SessionStore
    from magcal_workbench.sessionfile import SessionFileError

    fifo = tmp_path / "data.csv"
    os.mkfifo(fifo)
    from magcal_workbench.app import main as workbench_main

    assert workbench_main([str(fifo), "--port", "0", "--no-session"]) == 2  # at once, not blocked
    assert "FIFO" in capsys.readouterr().err
    store = SessionStore(tmp_path / "sessions")
    folder = tmp_path / "sessions" / "s-20261127-000000-abcdef"
    folder.mkdir(parents=True)
    os.mkfifo(folder / "session.json")
    with pytest.raises(SessionFileError, match="not a regular file"):
        store.load(folder.name)
