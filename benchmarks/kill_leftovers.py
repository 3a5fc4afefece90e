"""What a SIGKILL leaves behind (issue 41, item 5): ``magcal diagnose --workers 4`` and a Dask ``magcal apply``,
each killed while its worker processes run, then watched for a while.

Run: ``python benchmarks/kill_leftovers.py [--repeats 3] [--watch 10]`` (Linux: processes are found in /proc by the
killed command's session, segments in /dev/shm; about 15 s a repeat). Prints, per command and repeat: the processes
it had started and their resident memory at the kill, the seconds from the kill until none of them ran any more
(``never`` within ``--watch`` s) and until its shared-memory segment was gone, what stayed in its temporary folder
(each command gets one of its own, ``TMPDIR``: multiprocessing's ``pymp-*``, magcal's run folder, Dask's scratch
space), and what the next run removed.
``PYTHONPATH=OLD_TREE python benchmarks/kill_leftovers.py`` measures another tree's magcal (the commands inherit
the path). Before issue 41
the diagnosis's fork server, workers (about 240 MB each at 4 x 1e5 samples) and resource tracker stayed for ever,
its segment too, and the apply's hidden work folder was never removed. Anything still running at the end is killed
(each process by its id) and the segments it left are unlinked, so the script leaves nothing either.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import magcal
from magcal.data import io as mio


def session(sid: int) -> dict:
    """Processes of session ``sid`` still running (zombies left out): pid -> resident bytes."""
    out = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat", "rb") as fh:
                fields = fh.read().rsplit(b")", 1)[1].split()
        except OSError:
            continue
        if int(fields[3]) == sid and fields[0] not in (b"Z", b"X"):
            out[int(entry)] = int(fields[21]) * os.sysconf("SC_PAGE_SIZE")
    return out


def segments(pid: int) -> list:
    return [n for n in os.listdir("/dev/shm") if n.startswith(f"magcal_{pid}_")]


def wait(condition, timeout_s: float, step_s: float = 0.02):
    """Seconds until ``condition()``, or None within ``timeout_s``."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        if condition():
            return time.monotonic() - t0
        time.sleep(step_s)
    return None


def clean(sid: int, pid: int) -> None:
    """Kill what is left of session ``sid`` (each process by its id; the resource tracker last, so that it can
    unlink what the others registered first) and unlink the segments of process ``pid``."""

    def tracker(p):
        try:
            with open(f"/proc/{p}/cmdline", "rb") as fh:
                return b"resource_tracker" in fh.read()
        except OSError:
            return False

    for last in (False, True):
        for p in session(sid):
            if tracker(p) == last:
                try:
                    os.kill(p, signal.SIGKILL)
                except OSError:
                    pass
        wait(lambda: not session(sid), 5)
    for name in segments(pid):
        os.unlink(os.path.join("/dev/shm", name))


def killed(argv, ready, watch_s: float) -> dict:
    """Start ``argv`` in a session of its own (and a temporary folder of its own, ``TMPDIR``), SIGKILL it once
    ``ready(pid, tmp)``, and watch what stays."""
    tmp = Path(tempfile.mkdtemp(prefix="kill-"))  # short: the fork server's socket path must fit
    try:
        got = _killed(argv, lambda sid: ready(sid, tmp), watch_s, tmp)
        end = time.monotonic() + watch_s
        while time.monotonic() < end and any(tmp.iterdir()):
            time.sleep(0.05)
        got["tmp_left"] = sorted(p.name for p in tmp.iterdir())
        return got
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _killed(argv, ready, watch_s: float, tmp: Path) -> dict:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p), "TMPDIR": str(tmp)}
    proc = subprocess.Popen(argv, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
    sid = proc.pid
    try:
        if wait(lambda: ready(sid) or proc.poll() is not None, 120) is None or proc.poll() is not None:
            return {"error": "ended or never ready before the kill"}
        procs = session(sid)
        had_segment = bool(segments(sid))
        os.kill(proc.pid, signal.SIGKILL)
        t0 = time.monotonic()
        proc.wait()
        gone = shm = None  # seconds from the kill until no process runs, until the segment is gone
        while time.monotonic() - t0 < watch_s and (gone is None or shm is None):
            now = time.monotonic() - t0
            if gone is None and not session(sid):
                gone = now
            if shm is None and not segments(sid):
                shm = now
            time.sleep(0.02)
        if not had_segment:
            shm = None
        return {
            "processes": len(procs) - 1,
            "mb": sum(v for p, v in procs.items() if p != sid) / 1e6,
            "gone_s": gone,
            "shm_s": shm,
            "left": len(session(sid)),
        }
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        clean(sid, sid)


def fmt(s) -> str:
    return "never" if s is None else f"{s:.2f}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--watch", type=float, default=10.0, help="seconds to watch after the kill")
    args = parser.parse_args()
    if not (os.path.isdir("/proc") and os.path.isdir("/dev/shm")):
        print("needs Linux (/proc, /dev/shm)")
        return 1
    with tempfile.TemporaryDirectory(prefix="magcal-kill-") as folder:
        d = Path(folder)
        ds = magcal.simulate_timeseries("chi2017", n_samples=12_500, seed=7, rate_hz=10.0)
        mio.write_csv(d / "four.csv", ds)
        magcal.calibrate(ds.subset(np.arange(1500))).calibration.save(d / "cal.json")
        py = [sys.executable, "-m", "magcal"]
        mio.write_csv(d / "five_mb.csv", magcal.simulate_timeseries("chi2017", n_samples=15_000, seed=7, rate_hz=10.0))
        print(f"{'command':<28} {'run':>3} {'processes':>9} {'MB':>7} {'all ended s':>11} {'segment gone s':>14}")
        for argv, label, ready in (
            (
                ["four.csv", "--workers", "4"],
                "diagnose --workers 4",
                lambda sid, tmp: segments(sid) and len(session(sid)) >= 7,
            ),
            # 5 MB: the fork server starts while the file is read; the fits then stay on threads
            (
                ["five_mb.csv", "--workers", "2"],
                "diagnose --workers 2",
                lambda sid, tmp: any(tmp.iterdir()) and len(session(sid)) >= 3,
            ),
        ):
            for k in range(args.repeats):
                got = killed(py + ["diagnose", str(d / argv[0]), *argv[1:]], ready, args.watch)
                print(
                    f"{label:<28} {k + 1:>3} {got.get('processes', '-'):>9} {got.get('mb', 0):>7.0f} "
                    f"{fmt(got.get('gone_s')):>11} {fmt(got.get('shm_s')):>14}   still running after "
                    f"{args.watch:g} s: {got.get('left', '-')}; left in TMPDIR: {got.get('tmp_left') or 'nothing'}"
                )
        for k in range(args.repeats):
            out = d / f"parts{k}"

            def started(sid, tmp, out=out):
                return any(any(p.iterdir()) for p in d.glob(f".{out.name}.*.tmp") if p.is_dir())

            got = killed(
                py
                + ["apply", str(d / "cal.json"), str(d / "four.csv"), "-o", str(out), "--workers", "2"]
                + ["--partition-rows", "500", "--no-progress"],
                started,
                args.watch,
            )
            left = sorted(p.name for p in d.glob(f".{out.name}.*.tmp"))
            print(
                f"{'apply --workers 2 (Dask)':<28} {k + 1:>3} {got.get('processes', '-'):>9} {got.get('mb', 0):>7.0f} "
                f"{fmt(got.get('gone_s')):>11} {'-':>14}   work folder left: {len(left)}; left in TMPDIR: "
                f"{got.get('tmp_left') or 'nothing'}"
            )
        err = subprocess.run(
            py
            + ["apply", str(d / "cal.json"), str(d / "four.csv"), "-o", str(d / "next"), "--no-progress"]
            + ["--workers", "1"],
            capture_output=True,
            text=True,
            env={**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)},
        ).stderr
        removed = [line for line in err.splitlines() if "left behind" in line]
        print(f"the next apply: {removed[0] if removed else 'removed nothing'}")
        print(f"work folders left after it: {len(list(d.glob('.parts*.tmp')))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
