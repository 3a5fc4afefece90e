"""Every bad input we could think of, through the real CLI: what each one got.

Run: ``python benchmarks/bad_inputs.py`` (about 20 s). Prints one row per case: the command, the verdict, the
seconds it took and the first line of what magcal said. Verdicts:

* ``refused``  - exit status 2 with a one-line message (no traceback) of at most 1000 characters;
* ``warned``   - went on, with a warning printed (a problem magcal could work around);
* ``accepted`` - exit 0 and nothing said: **silently accepted** (should not happen for a bad input);
* ``LONG``     - refused, but with a message longer than 1000 characters;
* ``HANG``     - still running after :data:`CASE_LIMIT_S` (a FIFO's reader is then let go);
* ``CRASH``    - any other exception (a traceback): a bug.

The script exits non-zero if any case was silently accepted, crashed, hung or said too much. The last rows are
issue 41's bombs and bad values, then issue 51's Parquet dictionary bombs; ``benchmarks/notes/bad_inputs.md`` has the table before and after it.
"""

from __future__ import annotations

import contextlib
import io as _io
import json
import os
import struct
import sys
import tempfile
import textwrap
import threading
import time
import warnings
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from magcal.calibration.calibration import Calibration, SensorCalibration
from magcal.cli import main
from magcal.data import io
from magcal.data import simulation as sim
from magcal.fitting import platform as pf

#: Longest a case may run (s) before it counts as a hang.
CASE_LIMIT_S = 60.0
#: Longest message a refusal may print (characters).
MESSAGE_LIMIT = 1000


def run_cli(argv, folder=None):
    """The verdict, the seconds and the first line of what ``magcal ARGV`` said, the command run in a thread: one
    still running after :data:`CASE_LIMIT_S` is a hang (a reader blocked on a FIFO of ``folder`` is let go)."""
    box = {}
    thread = threading.Thread(target=lambda: box.update(result=_run_cli(argv)), daemon=True)
    t0 = time.perf_counter()
    thread.start()
    thread.join(CASE_LIMIT_S)
    hung = thread.is_alive()
    while thread.is_alive():
        for path in Path(folder).iterdir() if folder is not None else ():
            if path.is_fifo():  # a reader blocked opening a FIFO is let go: it reads the FIFO's end
                with contextlib.suppress(OSError):
                    os.close(os.open(path, os.O_WRONLY | os.O_NONBLOCK))
        thread.join(1.0)
    seconds = time.perf_counter() - t0
    verdict, message = box["result"]
    return ("HANG" if hung else verdict), seconds, message


def _run_cli(argv):
    err, out = _io.StringIO(), _io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out), warnings.catch_warnings():
            warnings.simplefilter("always")
            code = main([str(a) for a in argv])
    except SystemExit as exc:  # argparse usage errors
        code = exc.code
    except BaseException as exc:  # MemoryError included
        return "CRASH", f"{type(exc).__name__}: {exc}"
    text = err.getvalue().strip()
    if code == 2 and "error:" in text and "Traceback" not in text:
        line = next(line for line in text.splitlines() if "error:" in line)
        return ("refused" if len(line) <= MESSAGE_LIMIT else "LONG"), line
    if code == 0 and "warning:" in text:
        first = next(line for line in text.splitlines() if "warning:" in line)
        return "warned", first
    if code == 0:
        return "accepted", out.getvalue().strip().splitlines()[0] if out.getvalue().strip() else ""
    return "CRASH", f"exit {code}: {text[:200]}"


def make_files(d: Path):
    truth = pf.platform_truth()
    rng = np.random.default_rng(0)
    io.write_csv(d / "free.csv", sim.simulate(truth, n_samples=200, noise_nT=3.0, seed=5))
    table = pf.simulate_level_table(truth, n_per_group=80, noise_nT=3.0, seed=1)
    io.write_csv(d / "table.csv", table)
    io.write_csv(d / "survey.csv", sim.simulate_timeseries(truth, n_samples=300, noise_nT=3.0, seed=3))
    cal = Calibration(
        [SensorCalibration(s.Cinv, s.bias_nT) for s in truth.sensors], reference_total_nT=50_000.0, baseline_m=0.5
    )
    cal.save(d / "cal.json")
    doc = cal.to_dict()
    (d / "v2.json").write_text(json.dumps({**doc, "version": 2}))
    (d / "two.json").write_text(json.dumps({**doc, "sensors": doc["sensors"][:2]}))
    bad_r = json.loads(json.dumps(doc))
    bad_r["sensors"][1]["R"] = [[1, 0, 0], [0, 1, 0], [0, 0, -1]]
    (d / "reflect.json").write_text(json.dumps(bad_r))
    (d / "notjson.json").write_text("format: magcal\n")
    one_axis = Rotation.from_euler("z", rng.uniform(-np.pi, np.pi, (200, 1)))
    y = np.stack([s.measure(f) for s, f in zip(truth.sensors, sim.true_fields(truth, one_axis))])
    io.write_csv(
        d / "oneaxis.csv", sim.simulate(truth, n_samples=200).replace(readings_nT=y + rng.normal(0, 3, y.shape))
    )
    t = np.radians(15)
    tilted = Rotation.from_euler(
        "ZYX", np.column_stack([rng.uniform(-np.pi, np.pi, 200), rng.uniform(-t, t, 200), rng.uniform(-t, t, 200)])
    )
    y = np.stack([s.measure(f) for s, f in zip(truth.sensors, sim.true_fields(truth, tilted))])
    io.write_csv(
        d / "tilt15.csv", sim.simulate(truth, n_samples=200).replace(readings_nT=y + rng.normal(0, 3, y.shape))
    )
    io.write_csv(d / "few.csv", sim.simulate(truth, n_samples=6, seed=2))
    io.write_csv(d / "onegroup.csv", table.subset(table.group == "z_up"))
    io.write_csv(d / "noturn.csv", pf.simulate_level_table(truth, n_per_group=60, seed=2, heading_range_deg=2))
    mislabel = table.group.astype("<U8")
    mislabel[mislabel == "y_up"] = "y_down"
    io.write_csv(d / "mislabel.csv", table.replace(group=mislabel))
    good = (d / "free.csv").read_text().splitlines()
    hdr = next(i for i, line in enumerate(good) if not line.startswith("#"))

    def edit(name, k, col, value):
        lines = list(good)
        cells = lines[hdr + k].split(",")
        cells[col] = value
        lines[hdr + k] = ",".join(cells)
        (d / name).write_text("\n".join(lines) + "\n")

    edit("text.csv", 5, 2, "n/a")
    edit("nan.csv", 7, 0, "NaN")
    edit("inf.csv", 9, 4, "inf")
    edit("emptycell.csv", 11, 1, "")
    lines = list(good)
    lines[hdr + 3] = ",".join(lines[hdr + 3].split(",")[:-2])
    (d / "ragged.csv").write_text("\n".join(lines) + "\n")
    (d / "uT.csv").write_text((d / "free.csv").read_text().replace("# units: nT", "# units: uT"))
    surv = (d / "survey.csv").read_text().splitlines()
    sh = next(i for i, line in enumerate(surv) if not line.startswith("#"))
    dup = list(surv)
    dup[sh + 6] = ",".join([dup[sh + 5].split(",")[0]] + dup[sh + 6].split(",")[1:])
    (d / "duptime.csv").write_text("\n".join(dup) + "\n")
    back = list(surv)
    back[sh + 6], back[sh + 7] = back[sh + 7], back[sh + 6]
    (d / "backtime.csv").write_text("\n".join(back) + "\n")
    raw = {
        "empty.csv": b"",
        "binary.csv": bytes(range(256)) * 16,
        "latin1.csv": "# site: M\xfcnchen\nx,y,z\n1,2,3\n".encode("latin-1"),
        "noheader.csv": b"30000,20000,30000\n30001,20001,30001\n",
        "nosensor.csv": b"a,b,c\n1,2,3\n",
        "missingaxis.csv": b"s1x,s1y,t\n1,2,3\n",
        "gap.csv": b"s1x,s1y,s1z,s3x,s3y,s3z\n1,2,3,4,5,6\n",
        "dupcol.csv": b"x,y,z,x\n1,2,3,4\n",
        "headeronly.csv": b"# units: nT\ns1x,s1y,s1z\n",
        "badmeta.csv": b"# baseline_m: half a metre\nx,y,z\n1,2,3\n",
        "badunits.csv": b"# units: furlongs\nx,y,z\n1,2,3\n",
        "partialq.csv": b"x,y,z,qw,qx,qy\n1,2,3,1,0,0\n",
    }
    for name, content in raw.items():
        (d / name).write_bytes(content)
    (d / "dir.csv").mkdir()
    (d / "outdir").mkdir()
    # issue 31: hostile logs, wide and endless lines, wrong types in a calibration file

    fmt = b"\xa3\x95\x80" + struct.pack("<BB4s16s64s", 128, 89, b"FMT", b"BBnNZ", b"Type,Length,Name,Format,Columns")
    mag0 = b"\xa3\x95\x80" + struct.pack("<BB4s16s64s", 65, 0, b"MAG", b"QBhhh", b"TimeUS,I,MagX,MagY,MagZ")
    (d / "fmt0.bin").write_bytes(fmt + mag0 + b"\xa3\x95\x41" * 12_000)  # 36 KB: hung the reader forever
    (d / "noise.bin").write_bytes(rng.integers(0, 256, 36_000, dtype=np.uint8).tobytes())
    (d / "wide.csv").write_text("s1x,s1y,s1z," + ",".join(f"c{k}" for k in range(100_000)) + "\n1,2,3\n")
    with open(d / "endless.csv", "wb") as fh:
        fh.write(b"s1x,s1y,s1z\n")
        fh.write(b"1" * (8 << 20))
    (d / "params_number.json").write_text(json.dumps({**doc, "effect_params": 5}))
    make_issue41_files(d, doc)


def _ulog_msg(kind, payload):
    return struct.pack("<HB", len(payload), ord(kind)) + payload


def nested_ulog(depth, before=b"", after=b""):
    """Formats ``t0:t1[2] a;`` ... ``t{depth}:uint8_t x;`` and a subscription of t0: 2^depth fields in pyulog."""
    out = bytearray(b"ULog\x01\x12\x35" + bytes([1]) + struct.pack("<Q", 0)) + before
    for k in range(depth):
        out += _ulog_msg("F", f"t{k}:t{k + 1}[2] a;".encode())
    out += _ulog_msg("F", f"t{depth}:uint8_t x;".encode()) + _ulog_msg("A", struct.pack("<BH", 0, 0) + b"t0")
    return bytes(out + after)


def make_issue41_files(d: Path, doc):
    """Issue 41's bombs and bad values."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    (d / "nest22.ulg").write_bytes(nested_ulog(22))  # 4 million fields from 558 bytes
    padding = _ulog_msg("I", b"\x0cchar[1] pad" + b"x" * 40_000) * 3
    (d / "hidden.ulg").write_bytes(nested_ulog(22, before=b"\x20\x4e\xee", after=padding))
    col = pa.array(np.full(1_000_000, 30_000.0))
    table = pa.table({"s1x": col, "s1y": col, "s1z": col})
    with pq.ParquetWriter(d / "rows1e8.parquet", table.schema, compression="zstd") as writer:
        for _ in range(100):  # 1e8 constant rows
            writer.write_table(table)
    with open(d / "padding.csv", "w") as fh:
        fh.write("s1x,s1y,s1z,note\n30000,1,2," + "a" * 100_000 + "\n")
        fh.writelines(f"{30000 + k % 7},{k % 5},{k % 3},b\n" for k in range(200_000))
    good = (d / "free.csv").read_text().splitlines()
    hdr = next(i for i, line in enumerate(good) if not line.startswith("#"))
    lines = list(good)
    for k in range(1, 6):
        lines[hdr + k] = "9" * 5000 + "," + lines[hdr + k].split(",", 1)[1]
    (d / "longcells.csv").write_text("\n".join(lines) + "\n")
    counts = sim.simulate(pf.platform_truth(), n_samples=200, noise_nT=3.0, seed=5)
    counts = counts.replace(readings_nT=np.round(counts.readings_nT[:1] / 150.0), baseline_m=None)
    io.write_csv(d / "counts.csv", counts, metadata={"units": "counts", "lsb_nT": "150"})
    for name, lsb in (("lsb1e308.csv", "1e308"), ("lsb1e-300.csv", "1e-300")):
        (d / name).write_text((d / "counts.csv").read_text().replace("lsb_nT: 150", f"lsb_nT: {lsb}"))
    big = pa.array(["x" * 100_000_000])  # a Parquet text column's dictionary: one 100 MB value for every row
    for rows in (30, 8):
        cols = {a: pa.array(np.full(rows, 30_000.0 + k)) for k, a in enumerate(("s1x", "s1y", "s1z"))}
        note = pa.DictionaryArray.from_arrays(pa.array(np.zeros(rows, np.int32)), big)
        pq.write_table(pa.table({**cols, "note": note}), d / f"dict{rows}.parquet", compression="zstd")
    huge = json.loads(json.dumps(doc))
    huge["sensors"] = [{**s, "Cinv": (np.eye(3) * 1e308).tolist()} for s in doc["sensors"]]
    (d / "huge.json").write_text(json.dumps(huge))
    for name in ("fifo_effects.py", "fifo.csv", "fifo.json"):
        os.mkfifo(d / name)


def cases(d: Path):
    c, s, o = d / "cal.json", d / "survey.csv", d / "out.csv"
    return [
        ("data file", "empty file", ["calibrate", d / "empty.csv"]),
        ("data file", "binary file", ["calibrate", d / "binary.csv"]),
        ("data file", "not UTF-8 (Latin-1)", ["calibrate", d / "latin1.csv"]),
        ("data file", "missing file", ["calibrate", d / "absent.csv"]),
        ("data file", "a directory", ["calibrate", d / "dir.csv"]),
        ("data file", "no header row", ["calibrate", d / "noheader.csv"]),
        ("data file", "no sensor columns", ["calibrate", d / "nosensor.csv"]),
        ("data file", "sensor without z", ["calibrate", d / "missingaxis.csv"]),
        ("data file", "sensors 1 and 3, no 2", ["calibrate", d / "gap.csv"]),
        ("data file", "duplicate column name", ["calibrate", d / "dupcol.csv"]),
        ("data file", "3 of 4 quaternion columns", ["calibrate", d / "partialq.csv"]),
        ("data file", "header only", ["calibrate", d / "headeronly.csv"]),
        ("data file", "metadata baseline not a number", ["calibrate", d / "badmeta.csv"]),
        ("data file", "unknown unit", ["calibrate", d / "badunits.csv"]),
        ("data file", "ragged row", ["calibrate", d / "ragged.csv"]),
        ("data file", "text in a number column", ["calibrate", d / "text.csv"]),
        ("data file", "NaN", ["calibrate", d / "nan.csv"]),
        ("data file", "inf", ["calibrate", d / "inf.csv"]),
        ("data file", "empty cell", ["calibrate", d / "emptycell.csv"]),
        ("data file", "NaN with --drop-bad", ["calibrate", d / "nan.csv", "--drop-bad"]),
        ("data file", "repeated time stamp", ["apply", c, d / "duptime.csv", "-o", o]),
        ("data file", "time going back", ["apply", c, d / "backtime.csv", "-o", o]),
        ("data file", "readings in nT labelled uT", ["calibrate", d / "uT.csv"]),
        ("data file", "--units furlong", ["calibrate", d / "free.csv", "--units", "furlong"]),
        ("data file", "--columns to a missing column", ["calibrate", d / "free.csv", "--columns", "x=magX"]),
        ("calibration", "6 samples", ["calibrate", d / "few.csv"]),
        ("calibration", "rotation about one axis", ["calibrate", d / "oneaxis.csv"]),
        ("calibration", "tilts within +-15 deg (poor coverage)", ["calibrate", d / "tilt15.csv"]),
        ("calibration", "--reference 52.2 (uT given)", ["calibrate", d / "free.csv", "--reference", "52.2"]),
        ("cal file", "missing", ["apply", d / "absent.json", s, "-o", o]),
        ("cal file", "not JSON", ["apply", d / "notjson.json", s, "-o", o]),
        ("cal file", "version 2", ["apply", d / "v2.json", s, "-o", o]),
        ("cal file", "2-sensor file for 4-sensor data", ["apply", d / "two.json", s, "-o", o]),
        ("cal file", "R a reflection", ["apply", d / "reflect.json", s, "-o", o]),
        ("cal file", "a data file given as calibration", ["apply", s, s, "-o", o]),
        ("apply", "output = input", ["apply", c, s, "-o", s]),
        ("apply", "output directory missing", ["apply", c, s, "-o", d / "nodir" / "o.csv"]),
        ("apply", "--chunk-rows 0", ["apply", c, s, "-o", o, "--chunk-rows", "0"]),
        ("align", "no group column", ["align", d / "free.csv", "--cal", c]),
        ("align", "one group only", ["align", d / "onegroup.csv", "--cal", c]),
        ("align", "array not turned in a group", ["align", d / "noturn.csv", "--cal", c]),
        ("align", "y_up labelled y_down", ["align", d / "mislabel.csv", "--cal", c]),
        ("align", "--reference igrf without --lat", ["align", d / "table.csv", "--reference", "igrf"]),
        (
            "align",
            "--reference igrf, date 1850",
            ["align", d / "table.csv", "--reference", "igrf", "--lat", "36", "--lon", "120", "--date", "1850-01-01"],
        ),
        ("align", "--noise -1", ["align", d / "table.csv", "--noise", "-1"]),
        ("log", "DataFlash format of length 0 (36 KB)", ["calibrate", d / "fmt0.bin"]),
        ("log", "random bytes named .bin", ["calibrate", d / "noise.bin"]),
        ("data file", "100 000 header columns", ["calibrate", d / "wide.csv"]),
        ("data file", "an 8 MB line", ["calibrate", d / "endless.csv"]),
        ("calibration", "--reference 1e308", ["calibrate", d / "free.csv", "--reference", "1e308"]),
        ("calibration", "--reference 1e-308", ["calibrate", d / "free.csv", "--reference", "1e-308"]),
        ("calibration", "-o an existing directory", ["calibrate", d / "free.csv", "-o", d / "outdir"]),
        ("cal file", "effect_params a number", ["apply", d / "params_number.json", s, "-o", o]),
        ("apply", "-o an existing directory", ["apply", c, s, "-o", d / "outdir"]),
        ("apply", "missing input, existing output", ["apply", c, d / "absent.parquet", "-o", s]),
        ("apply", "--workers 10000", ["apply", c, s, "-o", d / "parts", "--workers", "10000"]),
        # issue 41: bombs and bad values
        ("log", "ULog formats nesting 22 deep (558 bytes)", ["calibrate", d / "nest22.ulg"]),
        ("log", "the same behind a damaged stretch", ["calibrate", d / "hidden.ulg"]),
        ("data file", "Parquet of 1e8 constant rows (1.3 MB)", ["calibrate", d / "rows1e8.parquet"]),
        ("data file", "a 100 000-character cell above 200 000 short", ["calibrate", d / "padding.csv"]),
        ("data file", "five 5000-character values", ["calibrate", d / "longcells.csv"]),
        ("data file", "# lsb_nT: 1e308", ["calibrate", d / "lsb1e308.csv"]),
        ("data file", "# lsb_nT: 1e-300", ["calibrate", d / "lsb1e-300.csv"]),
        ("data file", "--lsb 1e-300", ["calibrate", d / "counts.csv", "--lsb", "1e-300"]),
        ("data file", "a FIFO", ["calibrate", d / "fifo.csv"]),
        (
            "cal file",
            "Cinv = 1e308 I, ArduPilot",
            ["export", d / "huge.json", "--format", "ardupilot", "--sensor", "1"],
        ),
        ("cal file", "Cinv = 1e308 I, PX4", ["export", d / "huge.json", "--format", "px4"]),
        ("cal file", "Cinv = 1e308 I, apply", ["apply", d / "huge.json", s, "-o", d / "huge_out.csv"]),
        ("cal file", "a FIFO", ["apply", d / "fifo.json", s, "-o", o]),
        ("effects", "a FIFO as --effects-file", ["calibrate", d / "free.csv", "--effects-file", d / "fifo_effects.py"]),
        # issue 51: text cells bounded before they are made
        ("data file", "Parquet dictionary: 30 rows of one 100 MB value (5 kB)", ["calibrate", d / "dict30.parquet"]),
        ("data file", "the same, 8 rows", ["calibrate", d / "dict8.parquet"]),
        ("apply", "the same, corrected", ["apply", c, d / "dict30.parquet", "-o", d / "dict_out.parquet"]),
    ]


# -- issue 41: line templates against hostile lines ------------------------------------------------------------------
#: How the templates matched before issue 41 (0312ad1): one pattern, ``{_}`` a lazy ``.*?``, numbers that give back
#: digits, whitespace ``\s*`` between tokens (:func:`_old_matcher`); kept here to measure what a line cost then.
_OLD_NUMBER = (
    r"(?<![\d.])(?<![\d.][eE])(?<![\d.][eE][-+])[-+]?(?:(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?|(?i:nan|inf(?:inity)?))"
    r"(?![\d.]|[eE][-+]?\d)"
)
#: Longest a line may run under the old patterns here before it is stopped (s).
OLD_CAP_S = 5.0


def _old_matcher(template):
    """``match(line)`` as a live source ran it before issue 41: the whole pattern, and on failure the pattern of each
    start of the template in turn (to say where the line departs)."""
    import re
    import string

    parts = []
    for literal, name, _, _ in string.Formatter().parse(template):
        parts += [re.escape(w) for w in re.findall(r"\w+|\S", literal)]
        if name is not None:
            parts.append(".*?" if name.strip() in ("_", "-", "") else f"({_OLD_NUMBER})")
    whole = re.compile(r"\s*" + r"\s*".join(parts) + r"\s*")
    starts = [re.compile(r"\s*" + r"\s*".join(parts[:k])) for k in range(1, len(parts) + 1)]

    def match(line):
        if whole.fullmatch(line) is None:
            for start in starts:
                if start.match(line) is None:
                    break
            raise ValueError("template: the line departs from it")

    return match


def _seconds(fn, cap_s=None):
    """CPU seconds of ``fn()`` (one call), or None when it ran past ``cap_s`` (stopped by an alarm)."""
    import signal
    import time

    def expired(signum, frame):
        raise TimeoutError

    previous = signal.signal(signal.SIGALRM, expired)
    if cap_s:
        signal.setitimer(signal.ITIMER_REAL, cap_s)
    t0 = time.thread_time()
    try:
        fn()
    except TimeoutError:
        return None
    except ValueError:  # the line refused: what the live source counts as bad
        pass
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
    return time.thread_time() - t0


def template_attacks():
    """Rows ``(attack, line bytes, before s or None, after s)``: one line's match, the old pattern and ours."""
    from magcal.data.lineformats import LineTemplate

    skips = "{_}{_}{_}{x}{y}{z}Q"
    readme = "Magnetometer reading: [{x}, {y}, {z}]"
    docs = "mag ({x} {y} {z}) acc ({_} {_} {_})"
    attacks = [
        ("audit's skips, a 120-byte datagram of '1 1 1 ...'", skips, "1 " * 60),
        ("audit's skips, the 600-byte datagram", skips, "1 " * 300),
        ("audit's skips, 4 KB", skips, "1 " * 2048),
        ("README template, 4000 digits", readme, "Magnetometer reading: [" + "1" * 4000),
        ("docs' skips (mag ... acc ({_} {_} {_})), 4 KB", docs, "mag (1 2 3) acc (" + "1 " * 2035),
        ("x={x} y={y} z={z}, 4000 digits", "x={x} y={y} z={z}", "x=" + "1" * 4000),
    ]
    rows = []
    for name, template, line in attacks:
        old = _old_matcher(template)
        new = LineTemplate(template)
        before = _seconds(lambda old=old, line=line: old(line), OLD_CAP_S)
        after = min(_seconds(lambda new=new, line=line: new.match(line)) for _ in range(5))
        rows.append((name, len(line), before, after))
    return rows


def record_attack(seconds=2.0):
    """``magcal record tcp://... --template SKIPS --seconds S`` against a board that sends one good line, then the
    audit's 600-byte lines without pause: ``(wall seconds, exit status, what it said)``."""
    import socket
    import threading
    import time

    server = socket.create_server(("127.0.0.1", 0))
    port = server.getsockname()[1]
    stop = threading.Event()

    def board():
        server.settimeout(30)
        try:
            conn, _ = server.accept()
        except OSError:
            return
        with conn:
            conn.sendall(b"7 30000 2000 40000 Q\n")
            while not stop.is_set():
                try:
                    conn.sendall(b"1 " * 300 + b"\n")
                except OSError:
                    return
                time.sleep(0.005)

    thread = threading.Thread(target=board, daemon=True)
    thread.start()
    with tempfile.TemporaryDirectory() as tmp:
        argv = ["record", f"tcp://127.0.0.1:{port}", f"{tmp}/r.csv", "--template", "{_}{_}{_}{x}{y}{z}Q"]
        err = _io.StringIO()
        t0 = time.monotonic()
        with contextlib.redirect_stderr(err):
            code = main([str(a) for a in argv] + ["--seconds", str(seconds)])
        wall = time.monotonic() - t0
    stop.set()
    server.close()
    thread.join(5)
    return wall, code, err.getvalue().strip().splitlines()[-1].replace(f"{tmp}/", "")


def print_template_attacks(markdown=False):
    rows = template_attacks()

    def shown(s):
        return f"> {OLD_CAP_S:g} s (stopped)" if s is None else f"{s * 1e3:.3g} ms" if s < 1 else f"{s:.3g} s"

    print(
        f"\nissue 41: one hostile line through a line template (CPU time of its match; old pattern capped at {OLD_CAP_S:g} s)"
    )
    print(f"{'attack':52s} {'bytes':>6s} {'before':>20s} {'after':>10s}")
    for name, n, before, after in rows:
        print(f"{name:52s} {n:6d} {shown(before):>20s} {shown(after):>10s}")
    wall, code, said = record_attack()
    print(
        f"magcal record --seconds 2 against a board sending the 600-byte lines: ended after {wall:.2f} s, exit {code}"
    )
    print(f"    {said}")
    if markdown:
        print("\n| attack | line bytes | before (old pattern) | after |\n|---|---|---|---|")
        for name, n, before, after in rows:
            print(f"| {name} | {n} | {shown(before)} | {shown(after)} |")
    return code == 0 and wall < 10


def main_():
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        make_files(d)
        rows = []
        for kind, name, argv in cases(d):
            verdict, seconds, message = run_cli(argv, d)
            message = message.replace(str(d) + "/", "")
            rows.append((kind, name, argv[0], verdict, seconds, message))
    width = 118
    print(f"{'input':52s} {'command':9s} {'verdict':9s} {'s':>6s} message")
    for kind, name, cmd, verdict, seconds, message in rows:
        short = textwrap.shorten(message.split(": error: ")[-1].split(": warning: ")[-1], width - 66, placeholder="...")
        print(f"{kind + ': ' + name:52s} {cmd:9s} {verdict:9s} {seconds:6.2f} {short}")
    counts = {v: sum(r[3] == v for r in rows) for v in ("refused", "warned", "accepted", "LONG", "HANG", "CRASH")}
    print(f"\n{len(rows)} cases: " + ", ".join(f"{n} {v}" for v, n in counts.items()))
    if "--markdown" in sys.argv:
        print("\n| input | command | result | s | message (shortened) |\n|---|---|---|---|---|")
        for kind, name, cmd, verdict, seconds, message in rows:
            short = textwrap.shorten(message.split(": error: ")[-1].split(": warning: ")[-1], 150, placeholder="...")
            print(f"| {kind}: {name} | {cmd} | {verdict} | {seconds:.2f} | {short.replace('|', '/')} |")
    lines_ok = print_template_attacks("--markdown" in sys.argv)
    return 1 if any(counts[v] for v in ("accepted", "LONG", "HANG", "CRASH")) or not lines_ok else 0


if __name__ == "__main__":
    sys.exit(main_())
