"""Live text sources under hostile input: line templates that match in linear time, reads that end by
their deadline, a stream without line ends counted as the one over-long line it is, and ``magcal record
--seconds`` that ends whatever arrives.

The attacks are the audit's: the template ``{_}{_}{_}{x}{y}{z}Q`` (the page allows it) and a 600-byte datagram of
``1 1 1 ...`` froze the whole workbench for about 4.5 minutes; the README's template spent about 7 s on a line of
4000 digits. Times are CPU seconds of the test's own thread (:func:`time.thread_time`, the least of several
tries), compared between line lengths (linear: four times the line, about four times the time) under bounds far
above what they measure, so a loaded machine does not fail them; a case that runs away is stopped by an alarm and
fails instead of hanging the suite. Every wait is bounded; loopback addresses only.
"""

from __future__ import annotations

import contextlib
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

import magcal
from magcal.data.lineformats import MAX_TEMPLATE_CHARS, LineTemplate
from magcal.data.live import MAX_LINE_BYTES, LineParser, LiveError, LiveSession, _LineSource, record

ROOT = Path(__file__).resolve().parents[2]

#: The audit's template (skips the page allows) and the README's.
SKIPS = "{_}{_}{_}{x}{y}{z}Q"
README = "Magnetometer reading: [{x}, {y}, {z}]"


@contextlib.contextmanager
def time_limit(seconds):
    """Fail (instead of hanging) when the block runs longer than ``seconds``: a regular expression that backtracks
    holds the interpreter, but it checks for signals, so an alarm stops it."""

    def expired(signum, frame):
        raise AssertionError(f"still running after {seconds} s: not linear time")

    if threading.current_thread() is not threading.main_thread():  # no alarm outside the main thread
        yield
        return
    previous = signal.signal(signal.SIGALRM, expired)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def cpu_per_line(template, line, budget_s=0.05, tries=3):
    """CPU seconds one ``template.match(line)`` costs (the least of ``tries`` batches of at least ``budget_s``)."""
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


# -- templates: linear time ------------------------------------------------------------------------------------------
ATTACKS = [  # each took seconds to minutes (or for ever) before, at 1 to 4 KB
    pytest.param(SKIPS, lambda n: ("1 " * n)[:n], id="audit-skips"),
    pytest.param(README, lambda n: ("Magnetometer reading: [" + "1" * n)[:n], id="readme-digits"),
    pytest.param(README, lambda n: ("Magnetometer reading: [1, 2, " + "1" * n)[:n], id="readme-digits-last"),
    pytest.param("x={x} y={y} z={z}", lambda n: ("x=" + "1" * n)[:n], id="key-value-digits"),
    pytest.param("{_}{x}{_}{y}{_}{z}{_}Q", lambda n: ("1 " * n)[:n], id="interleaved-skips"),
    pytest.param("{_},{x},{_},{y},{_},{z}Q", lambda n: (",1" * n)[:n], id="comma-skips"),
    pytest.param("mag ({x} {y} {z}) acc ({_} {_} {_})", lambda n: ("mag (1 2 3) acc (" + "1 " * n)[:n], id="docs"),
    pytest.param("{_}a" * 30 + "{x}{y}{z}", lambda n: "a" * n, id="thirty-skips"),
]


@pytest.mark.parametrize("template, line", ATTACKS)
def test_a_template_matches_any_line_in_linear_time(template, line):
    """Four times the line costs at most eight times the time (linear: four; the old patterns: sixteen times or, with
    skips, minutes), and the longest line a source takes costs well under a second."""
    tpl = LineTemplate(template)
    with time_limit(30):
        short = cpu_per_line(tpl, line(MAX_LINE_BYTES // 4))
        long = cpu_per_line(tpl, line(MAX_LINE_BYTES))
    assert long <= 8 * short + 1e-4, f"{short * 1e3:.3f} ms -> {long * 1e3:.3f} ms for 4x the line"
    assert long < 0.25, f"{long:.3f} s for one line of {MAX_LINE_BYTES} bytes"


def test_the_audit_datagram_is_refused_at_once_with_its_reason():
    """The 600-byte datagram that held the workbench for 4.5 minutes: one bad line, said where it departs."""
    with time_limit(10):
        with pytest.raises(ValueError, match=r"template: expected 'Q' at character 6"):
            LineTemplate(SKIPS).match("1 " * 300)
    assert LineTemplate(SKIPS).match("boot 7 1 2 3 Q") == ["1", "2", "3"]  # what the template means still reads


def test_a_template_longer_than_its_bound_is_one_clear_error():
    with pytest.raises(LiveError, match=f"at most {MAX_TEMPLATE_CHARS}"):
        LineParser(template="{x} {y} {z}" + " a" * MAX_TEMPLATE_CHARS)


# -- reads end by their deadline --------------------------------------------------------------------------------------
class _Blocks(_LineSource):
    """A line source fed from byte blocks, one per receive."""

    def __init__(self, blocks, parser):
        super().__init__("test://blocks", parser)
        self._blocks = list(blocks)

    def _receive(self, timeout_s):
        if not self._blocks:
            self._eof = True
            return b""
        return self._blocks.pop(0)


class _SlowParser(LineParser):
    """Every line costs 10 ms (a slow machine, a long template)."""

    def parse_sample(self, text):
        time.sleep(0.01)
        return super().parse_sample(text)


def test_a_read_returns_by_its_deadline_and_the_rest_waits_for_the_next():
    lines = b"".join(f"{k},{k},{k}\n".encode() for k in range(100))  # one block of 100 lines: 1 s to parse
    source = _Blocks([lines], _SlowParser("x,y,z"))
    t0 = time.monotonic()
    first = source.read(timeout_s=0.1)
    took = time.monotonic() - t0
    assert 0 < len(first) < 100 and took < 0.6, (len(first), took)
    assert len(source.read(timeout_s=0.1, max_samples=5)) == 5  # and never more than asked
    rest = [source.read(timeout_s=0.05) for _ in range(200) if not source.ended]
    got = [first.readings_nT[0, :, 0]] + [c.readings_nT[0, :, 0] for c in rest if len(c)]
    seen = sorted(int(v) for chunk in got for v in chunk)
    assert len(seen) == 95 and source.ended  # the 5 above and these: every line, once
    assert source.stats.n_samples == 100 and source.stats.n_bad == 0


def test_what_a_stopped_read_left_is_drained_not_lost(tmp_path):
    lines = b"".join(f"{k},{k},{k}\n".encode() for k in range(60))
    source = _Blocks([lines], _SlowParser("x,y,z"))
    first = source.read(timeout_s=0.05)
    held = source.drain()
    assert len(first) + len(held) == 60 and len(held) > 0


# -- a stream without line ends ---------------------------------------------------------------------------------------
def test_a_stream_without_line_ends_is_one_over_long_line_and_the_next_line_reads():
    blocks = [bytes([0xFE, 0x21, 0x01, 0x55]) * 16384] * 160 + [b"tail\n1,2,3\n4,5,6\n"]  # 10 MB of binary, then text
    source = _Blocks(blocks, LineParser("x,y,z"))
    chunks = [source.read(timeout_s=0.05) for _ in range(400) if not source.ended]
    assert sum(len(c) for c in chunks) == 2
    stats = source.stats
    assert stats.n_bad == 1 and stats.reasons["line too long"] == 1, stats.summary()
    assert "10485764 bytes before its line end" in stats.last_bad and "without line ends" in stats.last_bad


def test_a_stream_still_without_a_line_end_says_so_once():
    source = _Blocks([b"\x00" * 65536] * 50, LineParser("x,y,z"))
    for _ in range(60):
        source.read(timeout_s=0.01)
    assert source.stats.n_bad == 1 and "no line end in 3276800 bytes" in source.stats.last_bad


# -- the workbench's reader: never holds up another thread -----------------------------------------------------------
def test_a_live_session_parsing_hostile_lines_never_holds_up_another_thread():
    """The session's thread parses the audit's lines; a thread beside it (the server's event loop) still runs every
    few ms. Before, one line held the interpreter for seconds (600 bytes: minutes)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    session = LiveSession(f"udp://127.0.0.1:{port}?template={SKIPS.replace('{', '%7B').replace('}', '%7D')}")
    gaps = []
    stop = threading.Event()

    def ticker():
        last = time.monotonic()
        while not stop.is_set():
            time.sleep(0.002)
            now = time.monotonic()
            gaps.append(now - last)
            last = now

    beside = threading.Thread(target=ticker, daemon=True)
    beside.start()
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
            tx.sendto(
                b"7 30000 2000 40000 Q\n", ("127.0.0.1", port)
            )  # a sample first: what follows is bad, not a banner
            for n in (200, 240, 200, 240):  # (one line of 600 bytes held the old matcher for minutes)
                tx.sendto(b"1 " * (n // 2) + b"\n", ("127.0.0.1", port))
        stats = session.source.stats
        end = time.monotonic() + 30
        while stats.n_bad < 4 and time.monotonic() < end:
            time.sleep(0.05)
    finally:
        stop.set()
        beside.join(5)
        session.stop()
    assert session.n_samples == 1 and stats.n_bad == 4 and stats.reasons["template"] == 4, stats.summary()
    assert max(gaps) < 1.0, f"another thread waited {max(gaps):.2f} s"


# -- magcal record --seconds ---------------------------------------------------------------------------------------
def test_magcal_record_ends_after_its_seconds_whatever_arrives(tmp_path):
    """A TCP board sends one good line, then the audit's lines without pause: ``--seconds 2`` ends the recording
    (before, the first long line held it for minutes), keeping the sample and counting the bad lines."""
    server = socket.create_server(("127.0.0.1", 0))
    port = server.getsockname()[1]
    stop = threading.Event()

    def board():
        server.settimeout(20)
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
                time.sleep(0.01)

    thread = threading.Thread(target=board, daemon=True)
    thread.start()
    out = tmp_path / "rec.csv"
    argv = [sys.executable, "-m", "magcal", "record", f"tcp://127.0.0.1:{port}", str(out), "--template", SKIPS]
    t0 = time.monotonic()
    try:
        proc = subprocess.run(
            [*argv, "--seconds", "2"], cwd=ROOT, capture_output=True, text=True, timeout=60, env=_env()
        )
    except subprocess.TimeoutExpired:
        pytest.fail("magcal record --seconds 2 still running after 60 s")
    finally:
        stop.set()
        server.close()
        thread.join(5)
    took = time.monotonic() - t0
    assert proc.returncode == 0, proc.stderr
    assert took < 30, took  # 2 s, the interpreter's start and the recording's close
    assert magcal.read_csv(out).n_samples == 1
    assert "1 samples" in proc.stderr and "template" in proc.stderr and "Traceback" not in proc.stderr


def _env():
    import os

    return {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}


def test_record_ends_by_its_duration_while_lines_keep_coming(tmp_path):
    """In-process too: a source that always has more lines to parse is read until the duration, no longer."""
    endless = [b"1 " * 2000 + b"\n"] * 100_000
    source = _Blocks([b"7 30000 2000 40000 Q\n", *endless], LineParser(template=SKIPS))
    t0 = time.monotonic()
    with time_limit(20):
        stats = record(source, tmp_path / "r.csv", duration_s=1.0)
    assert time.monotonic() - t0 < 10
    assert stats.n_samples == 1 and stats.n_bad > 0


@pytest.mark.parametrize(
    "option, message",
    [
        (["--seconds", "nan"], "--seconds must be a positive number of seconds, got nan"),
        (["--seconds", "inf"], "--seconds must be a positive number of seconds, got inf"),
        (["--seconds", "-1"], "--seconds must be a positive number of seconds, got -1.0"),
        (["--flush", "nan"], "--flush must be a positive number of seconds, got nan"),
        (["--samples", "0"], "--samples must be at least 1, got 0"),
    ],
)
def test_magcal_record_refuses_a_duration_that_would_never_end(tmp_path, capsys, option, message):
    """``--seconds nan`` recorded for ever (every comparison with nan is false); now one line, before the source
    opens, and no file."""
    from magcal.cli import main

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    with time_limit(10):
        rc = main(["record", f"udp://127.0.0.1:{port}", str(tmp_path / "r.csv"), *option])
    err = capsys.readouterr().err
    assert rc == 2 and message in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "r.csv").exists()
