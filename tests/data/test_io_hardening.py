"""Hardening (the engine's side): readers that end, one rule for bad values, bounds, messages instead of
tracebacks, outputs checked before the work and never left half-written.

Each test builds its hostile input itself (a crafted log, a NaN time stamp, a URL...) and checks the exact outcome:
the message, what was dropped and counted, what is on disk. Waits are bounded (a reader that would hang fails the
test after a few seconds instead of hanging it).
"""

from __future__ import annotations

import os
import struct
import sys
import threading
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

import magcal
from magcal.calibration.calibration import Calibration
from magcal.core.errors import DataWarning, MagcalError
from magcal.data import io
from magcal.data import simulation as sim
from magcal.data.dataset import MAX_ABS_VALUE, DatasetError, bad_values
from magcal.data.live import (
    SIM_MAX_SAMPLES,
    LineParser,
    LiveChunk,
    LiveError,
    LiveSource,
    Recorder,
    _LineSource,
    open_source,
    record,
)
from magcal.data.logs import read_log
from magcal.fitting import platform as pf
from tests.data.test_logs import (  # the writers of known-truth logs (the tests are one package)
    MAG_FIELDS,
    ardupilot_case,
    px4_case,
    write_dataflash,
    write_ulog,
)

pytest.importorskip("pymavlink")
pytest.importorskip("pyulog")


def finishes(fn, seconds=10.0):
    """``fn()``'s result or exception, or a test failure if it has not ended within ``seconds``."""
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


# -- the one rule ----------------------------------------------------------------------------------------------------
def test_bad_values_is_one_rule():
    v = np.array([0.0, -1e30, 1e30, np.nextafter(1e30, 2e30), 3e38, np.nan, np.inf, -np.inf, 1e300, -1e-300])
    assert bad_values(v).tolist() == [False, False, False, True, True, True, True, True, True, False]
    rows = np.array([[1.0, 2.0], [np.nan, 0.0], [1e31, 1.0]])
    assert bad_values(rows, axis=1).tolist() == [False, True, True]
    assert io.MAX_ABS_VALUE == MAX_ABS_VALUE  # the CSV reader's cap is the same constant


# -- DataFlash: crafted formats end at once with a message --------------------------------------------------------------
@pytest.fixture(scope="module")
def dataflash_bytes(tmp_path_factory):
    path = tmp_path_factory.mktemp("df") / "good.bin"
    messages, *_ = ardupilot_case(n=120, compasses=1)
    write_dataflash(path, messages)
    return path.read_bytes()


def _fmt_offset(data, name):
    """Byte offset of the FMT message that defines ``name``."""
    k = 0
    while True:
        k = data.index(b"\xa3\x95\x80", k)
        if data[k + 5 : k + 9].rstrip(b"\0") == name.encode():
            return k
        k += 1


@pytest.mark.parametrize("name", ["FMT", "PARM", "MAG", "IMU", "ATT"])
@pytest.mark.parametrize("length", [0, 1, 2])
def test_a_format_shorter_than_its_header_ends_in_seconds_with_a_message(tmp_path, dataflash_bytes, name, length):
    """pymavlink loops forever on a format of length 0 (and misreads below 3): refused before it reads."""
    data = bytearray(dataflash_bytes)
    k = _fmt_offset(data, name)
    data[k + 4] = length
    path = tmp_path / "crafted.bin"
    path.write_bytes(bytes(data + bytes(36_000)))  # the size of the log that hung the workbench
    box = finishes(lambda: read_log(path), seconds=10)
    assert isinstance(box.get("error"), DatasetError)
    assert f"byte {k}: the format of message {name}" in str(box["error"])
    assert f"length of {length} byte(s), less than the 3-byte message header" in str(box["error"])
    assert box["seconds"] < 5


def test_a_nameless_format_of_length_0_from_damaged_bytes_ends_with_a_message(tmp_path, dataflash_bytes):
    """A FMT whose name is not text passes no pre-check, yet pymavlink registers it and loops forever on the
    message after it (the code before this change hung here): the reader refuses a message that does not move it."""
    fmt = b"\xa3\x95\x80" + struct.pack("<BB4s16s64s", 70, 0, b"\x01\x02\x03\x04", b"", b"")
    k = 89 * 5  # after the five FMT messages
    path = tmp_path / "damaged.bin"
    path.write_bytes(dataflash_bytes[:k] + fmt + b"\xa3\x95\x46" * 3 + dataflash_bytes[k:])
    box = finishes(lambda: read_log(path), seconds=10)
    assert isinstance(box.get("error"), DatasetError), box
    assert f"byte {k + 89}: a message does not move the reader forward" in str(box["error"])


def test_a_library_error_on_a_damaged_log_is_one_line(tmp_path, dataflash_bytes):
    """pymavlink's error quotes the damaged byte (a line end in MAG's format): the message stays one line."""
    data = bytearray(dataflash_bytes)
    k = _fmt_offset(data, "MAG")
    data[k + 9] = ord("\n")  # the first character of the format
    path = tmp_path / "crafted.bin"
    path.write_bytes(bytes(data))
    with pytest.raises(DatasetError) as err:
        read_log(path)
    assert "\n" not in str(err.value) and "Unsupported format char" in str(err.value)


def test_a_format_not_the_size_of_its_fields_is_refused(tmp_path, dataflash_bytes):
    data = bytearray(dataflash_bytes)
    k = _fmt_offset(data, "MAG")
    data[k + 4] = 200
    path = tmp_path / "crafted.bin"
    path.write_bytes(bytes(data))
    with pytest.raises(DatasetError, match=r"MAG \(type 65\) declares 200 bytes but its fields \(QBhhhhhhhhhBI\)"):
        read_log(path)


def test_garbage_is_not_a_dataflash_log(tmp_path):
    path = tmp_path / "noise.bin"
    path.write_bytes(np.random.default_rng(1).integers(0, 256, 36_000, dtype=np.uint8).tobytes())
    with pytest.raises(DatasetError, match="noise.bin: not an ArduPilot DataFlash log: it holds no FMT message"):
        magcal.read_csv(path)
    (tmp_path / "tiny.bin").write_bytes(b"\xa3\x95\x80")
    with pytest.raises(DatasetError, match="not an ArduPilot DataFlash log"):
        magcal.read_csv(tmp_path / "tiny.bin")


def test_the_deadline_stops_a_slow_read(tmp_path, dataflash_bytes):
    path = tmp_path / "good.bin"
    path.write_bytes(dataflash_bytes)
    assert read_log(path).n_samples == 120
    with pytest.raises(DatasetError, match=r"good.bin: reading stopped after 0 s"):
        read_log(path, timeout_s=0)


def _nan_log(path, n=120):
    """A one-compass log whose ATT roll is NaN on samples 3, 4, IMU temperature inf on 5 and a PARM NaN."""
    messages, *_ = ardupilot_case(n=n, compasses=1)
    att = [i for i, (name, _) in enumerate(messages) if name == "ATT"]
    imu = [i for i, (name, _) in enumerate(messages) if name == "IMU"]
    for k in (3, 4):
        name, values = messages[att[k]]
        messages[att[k]] = (name, (values[0], values[1], float("nan"), *values[3:]))
    name, values = messages[imu[5]]
    messages[imu[5]] = (name, (values[0], values[1], float("inf")))
    messages.insert(0, ("PARM", (0, b"COMPASS_DIA_Y", float("nan"))))
    write_dataflash(path, messages)


def test_nan_fields_of_a_dataflash_log_are_dropped_with_a_count(tmp_path):
    path = tmp_path / "nan.bin"
    _nan_log(path)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ds = read_log(path)
    notes = [str(w.message) for w in caught if issubclass(w.category, DataWarning)]
    assert any("ATT: 2 of 120 sample(s) hold values NaN, infinite or beyond +-1e+30" in n for n in notes), notes
    assert any("IMU temperature: 1 of 120 sample(s)" in n for n in notes), notes
    assert any("1 parameter value(s) NaN, infinite or beyond +-1e+30 are ignored (COMPASS_DIA_Y)" in n for n in notes)
    assert ds.n_samples == 120
    for a in (ds.readings_nT, ds.attitude_wxyz, ds.temperature_C, *ds.extra.values()):
        assert np.all(np.isfinite(a))


def test_calibrate_and_apply_a_log_with_nan_fields(tmp_path, capsys):
    """Today: a traceback in calibrate, NaN rows with exit 0 in apply."""
    from magcal.cli import main

    path = tmp_path / "nan.bin"
    _nan_log(path, n=400)
    assert main(["calibrate", str(path), "-o", str(tmp_path / "cal.json")]) == 0
    assert main(["apply", str(tmp_path / "cal.json"), str(path), "-o", str(tmp_path / "out.csv"), "--no-progress"]) == 0
    out = magcal.read_csv(tmp_path / "out.csv")  # the reader refuses any NaN: every row is finite
    assert out.n_samples == 400


def test_ulog_without_x_y_z_is_a_message(tmp_path):
    topics, *_ = px4_case(n=50)
    fields = [f for f in MAG_FIELDS if f[1] != "z"]
    rows = [tuple(v for (_, name), v in zip(MAG_FIELDS, row) if name != "z") for row in topics[0][3]]
    path = tmp_path / "noz.ulg"
    write_ulog(path, [("sensor_mag", 0, fields, rows), topics[1]])
    with pytest.raises(DatasetError, match=r"noz.ulg: sensor_mag 0 has no field z \(its fields:"):
        read_log(path)


def test_ulog_values_beyond_the_rule_are_dropped(tmp_path):
    """3e38 G (a float32 near its largest) passed the log readers; the CSV reader capped at 1e30."""
    topics, raw_nT, *_ = px4_case(n=200)
    mag = list(topics[0][3])
    for k, value in ((10, 3e38), (11, float("nan")), (12, float("inf"))):
        row = list(mag[k])
        row[3] = value  # x, gauss
        mag[k] = tuple(row)
    path = tmp_path / "big.ulg"
    write_ulog(path, [("sensor_mag", 0, MAG_FIELDS, mag), topics[1]])
    with pytest.warns(DataWarning, match=r"sensor_mag 0: 3 of 200 sample\(s\) hold values NaN, infinite or beyond"):
        ds = read_log(path)
    assert ds.n_samples == 197
    assert np.allclose(ds.readings_nT[0], np.delete(raw_nT, [10, 11, 12], axis=0), rtol=1e-6)


def test_one_rule_in_csv_and_parquet(tmp_path):
    ds = sim.simulate(pf.platform_truth(), n_samples=50, seed=1)
    io.write_csv(tmp_path / "a.csv", ds)
    lines = (tmp_path / "a.csv").read_text().splitlines()
    h = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    cells = lines[h + 4].split(",")
    cells[0] = "3e38"
    lines[h + 4] = ",".join(cells)
    (tmp_path / "b.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match="line .*beyond \\+-1e\\+30"):
        magcal.read_csv(tmp_path / "b.csv")
    with pytest.warns(DataWarning, match="dropped 1 row"):
        assert magcal.read_csv(tmp_path / "b.csv", drop_bad=True).n_samples == 49
    pytest.importorskip("pyarrow")
    cols = io.dataset_columns(ds)
    cols["s1x"] = np.where(np.arange(50) == 4, 3e38, cols["s1x"])
    io.write_parquet(tmp_path / "b.parquet", cols)
    with pytest.raises(DatasetError, match=r"row 5, column s1x: 3e\+38 is NaN, infinite or beyond \+-1e\+30"):
        magcal.read_csv(tmp_path / "b.parquet")


# -- live: the same rule, and bounded URLs ---------------------------------------------------------------------------
class _Lines(_LineSource):
    """A line source fed from a list of byte strings (one per read)."""

    def __init__(self, blocks, columns="t,x,y,z"):
        super().__init__("test://lines", LineParser(columns))
        self._blocks = list(blocks)

    def _receive(self, timeout_s):
        if not self._blocks:
            self.ended = True
            return b""
        return self._blocks.pop(0)


def test_live_bad_time_stamps_and_values_never_reach_the_recording(tmp_path):
    lines = [
        b"0.1,30000,1000,40000\n",
        b"nan,30000,1000,40000\n",
        b"inf,30000,1000,40000\n",
        b"1e300,30000,1000,40000\n",
        b"0.2,3e38,1000,40000\n",
        b"0.3,30000,nan,40000\n",
        b"0.4,30000,1000,40000\n",
    ]
    source = _Lines([b"".join(lines)])
    stats = record(source, tmp_path / "rec.csv")
    assert stats.n_samples == 2 and stats.n_bad == 5
    assert stats.reasons["bad value"] == 5
    ds = magcal.read_csv(tmp_path / "rec.csv")
    assert ds.time_s.tolist() == [0.1, 0.4]


def test_recorder_refuses_bad_samples_handed_to_it(tmp_path):
    chunk = LiveChunk(
        np.array([0.0, np.nan, 2.0, 3.0]),
        np.array([[[30e3, 2e3, 4e4], [30e3, 2e3, 4e4], [np.inf, 2e3, 4e4], [30e3, 2e3, 4e4]]]),
        np.array([20.0, 20.0, 20.0, 1e300]),
    )
    with Recorder(tmp_path / "r.csv") as rec:
        rec.write(chunk)
    assert rec.n_refused == 3 and rec.n_written == 1
    assert magcal.read_csv(tmp_path / "r.csv").time_s.tolist() == [0.0]


class _Pushed(LiveSource):
    """A source whose samples are given (the MAVLink path: times from the vehicle)."""

    def __init__(self, samples):
        super().__init__("test://pushed")
        self._samples = samples

    def _poll(self, deadline, max_samples):
        out, self._samples = self._samples, []
        self.ended = not out
        return out


def test_live_source_applies_the_rule_to_every_kind():
    r = np.array([[30000.0, 1000.0, 40000.0]])
    src = _Pushed(
        [(1.0, r, 20.0), (float("nan"), r, 20.0), (2.0, r, float("inf")), (3.0, r * 1e27, 20.0), (4.0, r, 20)]
    )
    chunk = src.read(timeout_s=0.1)
    assert chunk.time_s.tolist() == [1.0, 4.0]
    assert src.stats.reasons["bad value"] == 3


@pytest.mark.parametrize(
    "url, message",
    [
        ("tcp://[::1", "not a valid source URL"),
        ("tcp://127.0.0.1:99999", "port of 1 to 65535"),
        ("udp://127.0.0.1:x", "port of 1 to 65535"),
        ("tcp://127.0.0.1", "give the address as tcp://HOST:PORT"),
        ("sim://chi2017?n=0", f"n=0: give 1 to {SIM_MAX_SAMPLES:,} samples"),
        ("sim://chi2017?n=100000000", "give 1 to"),
        ("sim://chi2017?rate=10000&speed=10", "rate x speed = 100000 samples per second; at most 20000"),
        ("sim://chi2017?rate=-5", "rate=-5.0: give 0.1 to 10000 samples per second"),
        ("sim://chi2017?rate=nan", "rate=nan: give"),
        ("sim://chi2017?speed=0", "speed=0.0: give 0.01 to 100"),
        ("sim://chi2017?speed=1e9", "speed=1000000000.0: give"),
        ("sim://chi2017?seed=-1", "seed=-1: give 0 to"),
        ("serial:///dev/null?baud=-3", "baud='-3': give 50 to"),
        ("tcp://127.0.0.1:9?timeout=1e9", "timeout='1e9': give 0.01 to 60"),
        ("tcp://" + "a" * 300 + ":80", "cannot connect"),
    ],
)
def test_malformed_live_urls_are_one_line_errors(url, message):
    with pytest.raises(LiveError) as err:
        open_source(url).close()
    assert message in str(err.value)
    assert "\n" not in str(err.value)


# -- bounds of the CSV reader --------------------------------------------------------------------------------------
def test_an_endless_line_is_refused_with_bounded_memory(tmp_path):
    """A 2 GB line exhausted the memory; here 40 MB without a line end: refused once 1 MiB has come, naming it."""
    import tracemalloc

    path = tmp_path / "long.csv"
    with open(path, "wb") as fh:
        fh.write(b"# units: nT\ns1x,s1y,s1z\n30000,1000,40000\n")
        block = b"1" * (1 << 20)
        for _ in range(40):
            fh.write(block)
    tracemalloc.start()
    try:
        with pytest.raises(DatasetError, match=r"long.csv: line 4 is longer than 1,048,576 bytes"):
            magcal.read_csv(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 16 * (1 << 20), peak
    with pytest.raises(DatasetError, match=r"line 4 is longer"):  # the streaming reader (apply) too
        with io.CsvSource(path) as src:
            list(src.chunks(1000))


def test_a_header_of_a_million_columns_is_refused(tmp_path):
    path = tmp_path / "wide.csv"
    path.write_text("s1x,s1y,s1z," + ",".join(f"c{k}" for k in range(1_000_000)) + "\n1,2,3\n")
    with pytest.raises(DatasetError, match=r"wide.csv: line 1 is longer than|the header names 1,000,003 columns"):
        magcal.read_csv(path)
    path.write_text("s1x,s1y,s1z," + ",".join(f"c{k}" for k in range(2000)) + "\n")
    with pytest.raises(DatasetError, match=r"line 1: the header names 2,003 columns, more than the 1,000 magcal reads"):
        magcal.read_csv(path)


# -- bounds and checks before the work ---------------------------------------------------------------------------
@pytest.fixture(scope="module")
def survey_files(tmp_path_factory):
    d = tmp_path_factory.mktemp("survey")
    ds = magcal.simulate_timeseries("chi2017", n_samples=600, seed=12, rate_hz=10.0)
    cal = magcal.calibrate(ds).calibration
    cal.save(d / "cal.json")
    io.write_csv(d / "survey.csv", ds)
    return d, cal, ds


def _cli(argv, capsys):
    from magcal.cli import main

    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def test_workers_are_bounded_by_the_cores(survey_files, tmp_path, capsys):
    from magcal.output.survey import WORKERS_PER_CORE, max_workers

    d, *_ = survey_files
    cores = os.cpu_count() or 1
    assert max_workers() == WORKERS_PER_CORE * cores
    t0 = time.monotonic()
    code, _, err = _cli(["apply", d / "cal.json", d / "survey.csv", "-o", tmp_path / "out", "--workers", 10000], capsys)
    assert code == 2 and time.monotonic() - t0 < 5  # refused before any cluster starts
    assert f"--workers 10000: give 1 to {WORKERS_PER_CORE * cores} (at most {WORKERS_PER_CORE} per CPU core" in err
    assert not (tmp_path / "out").exists()
    code, _, err = _cli(["apply", d / "cal.json", d / "survey.csv", "-o", tmp_path / "out", "--workers", 0], capsys)
    assert code == 2 and "--workers 0: give 1 to" in err
    assert "at most 4 per CPU core" in _help(capsys)


def _help(capsys):
    from magcal.cli import main

    with pytest.raises(SystemExit):
        main(["apply", "--help"])
    return " ".join(capsys.readouterr().out.split())


def test_outputs_are_checked_before_any_work(survey_files, tmp_path, capsys):
    """Each refused at once, with one line, and nothing written: the fit or the correction never ran."""
    d, *_ = survey_files
    (tmp_path / "folder").mkdir()
    (tmp_path / "parts").mkdir()
    (tmp_path / "parts" / "part-00000.parquet").write_text("an earlier run")
    (tmp_path / "exists.parquet").write_text("keep me")
    cal, survey = d / "cal.json", d / "survey.csv"
    cases = [
        (["calibrate", survey, "-o", tmp_path / "folder"], "is a directory; name a file in it"),
        (["calibrate", survey, "-o", tmp_path / "nodir" / "cal.json"], "the folder"),
        (["apply", cal, survey, "-o", tmp_path / "folder"], "is a directory; name a file in it"),
        (["apply", cal, survey, "-o", tmp_path / "nodir" / "o.csv"], "does not exist"),
        (["apply", cal, survey, "-o", tmp_path / "parts", "--workers", 1], "exists and is not an empty directory"),
        (["apply", cal, survey, "-o", tmp_path / "nodir" / "parts", "--workers", 1], "does not exist"),
        (
            ["apply", cal, tmp_path / "absent.parquet", "-o", tmp_path / "exists.parquet"],
            "absent.parquet: no such file",
        ),
        (["apply", cal, tmp_path / "absent.bin", "-o", tmp_path / "exists.parquet"], "absent.bin: no such file"),
        (["simulate", "--preset", "chi2017", "-o", tmp_path / "folder"], "is a directory"),
    ]
    for argv, needle in cases:
        t0 = time.monotonic()
        code, _, err = _cli(argv, capsys)
        assert code == 2, (argv, err)
        assert needle in err and "Traceback" not in err and err.count("\n") == 1, (argv, err)
        assert time.monotonic() - t0 < 5, argv
    assert sorted(p.name for p in tmp_path.iterdir()) == ["exists.parquet", "folder", "parts"]
    assert (tmp_path / "exists.parquet").read_text() == "keep me" and not any((tmp_path / "folder").iterdir())


def test_api_apply_checks_the_output_first(survey_files, tmp_path):
    from magcal.output.apply import apply_file

    d, cal, _ = survey_files
    (tmp_path / "folder").mkdir()
    for out in (tmp_path / "folder", tmp_path / "nodir" / "o.parquet"):
        with pytest.raises(MagcalError, match="is a directory|does not exist"):
            apply_file(cal, d / "survey.csv", out)
    with pytest.raises(DatasetError, match="absent.csv: no such file"):
        apply_file(cal, tmp_path / "absent.csv", tmp_path / "o.csv")


@pytest.mark.parametrize("umask", [0o022, 0o002, 0o077])
def test_written_files_respect_the_umask(survey_files, tmp_path, umask):
    """atomic_write made every output 0600 whatever the umask (tempfile.mkstemp); now 0666 less the umask."""
    from magcal.output.apply import apply_file

    d, cal, ds = survey_files
    old = os.umask(umask)
    try:
        io.write_csv(tmp_path / "a.csv", ds)
        cal.save(tmp_path / "cal.json")
        apply_file(cal, d / "survey.csv", tmp_path / "o.csv", progress=False)
        apply_file(cal, d / "survey.csv", tmp_path / "o.parquet", progress=False)
    finally:
        os.umask(old)
    for name in ("a.csv", "cal.json", "o.csv", "o.parquet"):
        assert stat_mode(tmp_path / name) == 0o666 & ~umask, name
    os.chmod(tmp_path / "cal.json", 0o640)  # a file replaced keeps its permissions
    cal.save(tmp_path / "cal.json")
    assert stat_mode(tmp_path / "cal.json") == 0o640


def stat_mode(path):
    return os.stat(path).st_mode & 0o777


def test_the_reference_and_calibration_values_are_messages(survey_files, tmp_path, capsys):
    import json

    d, *_ = survey_files
    for value in ("1e308", "1e-308", "2e7", "0.05"):
        code, _, err = _cli(["calibrate", d / "survey.csv", "--reference", value], capsys)
        assert code == 2 and "outside what any magnetometer magcal calibrates measures" in err, err
    doc = json.loads((d / "cal.json").read_text())
    for key, value in [
        ("effect_params", 5),
        ("effect_params", [5]),
        ("effect_params", [{"effect": "temperature_bias", "params": 3}]),
        ("effects", 1e308),
        ("effects", [1]),
        ("base_terms", "scale"),
        ("reference_total_nT", "50000"),
        ("reference_total_nT", 1e308),
        ("reference_fitted", "no"),
        ("frame", 3),
    ]:
        (tmp_path / "bad.json").write_text(json.dumps({**doc, key: value}))
        code, _, err = _cli(["apply", tmp_path / "bad.json", d / "survey.csv", "-o", tmp_path / "o.csv"], capsys)
        assert code == 2 and f"bad.json: '{key}' must be" in err and "Traceback" not in err, (key, value, err)
    assert not (tmp_path / "o.csv").exists()


# -- parallel apply: all or nothing under the final name -------------------------------------------------------------
def _leftovers(folder):
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


@pytest.mark.slow
def test_a_bad_row_in_a_parallel_apply_leaves_no_partial_output(survey_files, tmp_path):
    """Today some partitions stayed under the final name; now the temporary folder is removed."""
    from magcal.output.survey import apply_partitioned

    d, cal, _ = survey_files
    lines = (d / "survey.csv").read_text().splitlines()
    lines[-10] = ",".join(["NaN"] + lines[-10].split(",")[1:])  # in the last partition: the others are written first
    (tmp_path / "bad.csv").write_text("\n".join(lines) + "\n")
    out = tmp_path / "parts"
    line = len(lines) - 9  # the file's line, not the partition's (it named line 91 of the last 100)
    with pytest.raises(DatasetError, match=rf"bad.csv: 1 row\(s\) with bad values: line {line}, column t:"):
        apply_partitioned(cal, [tmp_path / "bad.csv"], out, workers=1, partition_rows=100, progress=False)
    assert not out.exists() and _leftovers(tmp_path) == []
    summary = apply_partitioned(cal, [d / "survey.csv"], out, workers=1, partition_rows=100, progress=False)
    assert summary.rows == 600 and len(os.listdir(out)) == 6 and _leftovers(tmp_path) == []
    assert [Path(f).parent for f in summary.files] == [out] * 6
    assert stat_mode(out) == 0o777 & ~io.current_umask()


@pytest.mark.slow
def test_ctrl_c_during_a_parallel_apply_leaves_no_partial_output(survey_files, tmp_path):
    """SIGINT once the first partitions are written: exit 130, nothing under the final name, no temporary folder."""
    import signal
    import subprocess

    d, cal, ds = survey_files
    big = tmp_path / "big.csv"
    io.write_csv(big, magcal.simulate_timeseries("chi2017", n_samples=60_000, seed=3, rate_hz=10.0))
    out = tmp_path / "parts"
    code = "import sys; from magcal.cli import main; sys.exit(main(sys.argv[1:]))"
    argv = [sys.executable, "-c", code, "apply", str(d / "cal.json"), str(big), "-o", str(out)]
    argv += ["--workers", "1", "--partition-rows", "500", "--format", "csv", "--no-progress"]
    env = {**os.environ, "PYTHONPATH": str(Path(magcal.__file__).parent.parent)}
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, text=True)
    try:
        end = time.monotonic() + 120
        while time.monotonic() < end and proc.poll() is None:
            temps = [p for p in tmp_path.iterdir() if p.name.startswith(".parts.")]
            if temps and any(name.startswith("part-") for name in os.listdir(temps[0])):
                break
            time.sleep(0.05)
        assert proc.poll() is None, proc.communicate()
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err
    assert "interrupted" in err
    assert not out.exists() and _leftovers(tmp_path) == []


# -- effects files are code ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("command", ["calibrate", "diagnose", "apply", "align", "simulate", "export", "effects"])
def test_every_effects_file_help_says_it_runs_code(command, capsys):
    from magcal.cli import main

    with pytest.raises(SystemExit):
        main([command, "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "The file is Python code and RUNS with your rights" in text


def test_the_user_effects_page_says_it_runs_code():
    page = (Path(__file__).resolve().parents[2] / "docs" / "user-effects.md").read_text()
    head = page[: page.index("## 1.")]
    assert "**An effects file is Python code, and it runs with your rights.**" in head
    assert "never one that came with" in head


def test_an_effect_block_without_parameters_is_a_message(tmp_path):
    """Found by the fuzz suite: an effect entry moved to another sensor left a block without parameters, a KeyError
    when the calibration was applied."""
    import json

    whole = magcal.simulate_timeseries("chi2017", n_samples=300, seed=2, rate_hz=1.0)
    one = whole.replace(readings_nT=whole.readings_nT[:1], baseline_m=None)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        doc = magcal.calibrate(one, effects=["temperature_bias"]).calibration.to_dict()
    for sensor, needle in ((2, "sensor 2, but the calibration has 1 sensor"), (None, "no parameters for the effect")):
        bad = json.loads(json.dumps(doc))
        bad["effect_params"][0]["sensor"] = sensor
        bad["effect_params"][0]["term"] = "temperature_bias:1" if sensor is None else "temperature_bias"
        (tmp_path / "bad.json").write_text(json.dumps(bad))
        with pytest.raises(MagcalError, match=needle):
            Calibration.load(tmp_path / "bad.json")
