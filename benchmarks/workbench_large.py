"""A million-row four-sensor file in the workbench: server memory, bytes sent per browser, time to first picture,
fit time against the CLI on the same file.

    python benchmarks/workbench_large.py [--n 1000000] [--max-points 20000] [--no-browser]

Steps (each a separate process, as a user would run them):

1. a simulated recording (``chi2017`` errors, four sensors, 50 Hz, seed 1) is written once to
   ``$TMPDIR/magcal_bench/workbench_<n>.csv`` (reused on the next run);
2. ``magcal calibrate FILE --json``: wall time and peak memory of the CLI (ML, the default);
3. ``magcal-workbench FILE --port 0 --no-session``: the time until it prints its address (file read, first scene)
   and its resident memory;
4. a raw websocket client with the page's Origin (what a browser's tab receives): the bytes of every message until
   the server is quiet for 3 s;
5. headless Chromium (Debian's /usr/bin/chromium, software WebGL): the time from ``goto`` until the canvas shows the
   clouds (pixels that are not background), then a click on *Run the chosen method* and the time until the page
   shows the fitted RMS; the fit's own time is the one the page reports (``(... s)``), the same engine call as the
   CLI (:func:`magcal.fitting.pipeline.calibrate`, no per-sample Python loop); the websocket client of step 4, still
   connected, counts the bytes the fit's redraw sends;
6. the server's peak memory (``VmHWM``) at the end.

Prints one table; the figures and the command go to ``benchmarks/notes/workbench_large.md`` (the headline in
``benchmarks/README.md``).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import re
import resource
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

CHROMIUM = "/usr/bin/chromium"
ARGS = ["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--disable-background-networking"]
ENV = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}


def data_file(n: int) -> Path:
    import magcal
    from magcal.data import io as mio

    folder = Path(tempfile.gettempdir()) / "magcal_bench"
    folder.mkdir(exist_ok=True)
    path = folder / f"workbench_{n}.csv"
    if not path.exists():
        t0 = time.perf_counter()
        ds = magcal.simulate_timeseries("chi2017", n_samples=n, seed=1, rate_hz=50.0)
        mio.write_csv(path, ds)
        print(f"wrote {path} ({path.stat().st_size / 1e6:.0f} MB) in {time.perf_counter() - t0:.1f} s", flush=True)
    return path


def run_cli(path: Path) -> dict:
    t0 = time.perf_counter()
    out = subprocess.run(
        [
            sys.executable,
            "-c",
            "import sys; from magcal.cli import main; sys.exit(main())",
            "calibrate",
            str(path),
            "--json",
        ],
        env=ENV,
        capture_output=True,
        text=True,
        timeout=600,
    )
    wall = time.perf_counter() - t0
    if out.returncode != 0:
        raise SystemExit(f"magcal calibrate failed: {out.stderr[-2000:]}")
    doc = json.loads(out.stdout)
    peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1e3  # MB (Linux: KiB)
    rms = doc.get("rms_nT") or doc.get("fit", {}).get("rms_nT")
    return {"wall_s": wall, "peak_MB": peak, "rms": rms}


_FIT_CODE = """
import sys, time, warnings, magcal
from magcal.data import io
from magcal_workbench.controller import Controller
ds = io.read_csv(sys.argv[1])
warnings.simplefilter("ignore")
import numpy as np
small = ds.subset(np.arange(ds.n_samples) < 2000)  # warm up: imports and first-call costs out of the timings
magcal.calibrate(small); Controller(small).step_calibrate()
t = time.perf_counter(); magcal.calibrate(ds); engine = time.perf_counter() - t
ctrl = Controller(ds)
t = time.perf_counter(); ctrl.worker.run_now("calibrate", ctrl.step_calibrate); step = time.perf_counter() - t
print(engine, step)
"""


def fit_times_s(path: Path) -> tuple[float, float]:
    """Wall times, s, on the file's data in one quiet process (no server, no browser): the CLI's engine call
    (:func:`magcal.calibrate`, ML) and the workbench's *Run the chosen method* step
    (:meth:`magcal_workbench.controller.Controller.step_calibrate`: the same call on the kept mask, then the residuals of
    every sample and the history row)."""
    out = subprocess.run(
        [sys.executable, "-c", _FIT_CODE, str(path)], env=ENV, capture_output=True, text=True, timeout=900, check=True
    )
    engine, step = out.stdout.split()[-2:]
    return float(engine), float(step)


def proc_memory_MB(pid: int) -> tuple[float, float]:
    """(resident, peak resident) of a process, MB."""
    fields = {}
    with open(f"/proc/{pid}/status") as fh:
        for line in fh:
            key, _, value = line.partition(":")
            fields[key] = value.strip()
    kb = lambda k: float(fields[k].split()[0]) / 1e3
    return kb("VmRSS"), kb("VmHWM")


class WebsocketCounter:
    """A websocket client with the page's Origin that counts the bytes it receives (in a thread)."""

    def __init__(self, port: int, token: str = ""):
        self.port = port
        self.token = token
        self.bytes = 0
        self.messages = 0
        self.last = time.perf_counter()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=lambda: asyncio.run(self._run()), daemon=True)
        self._thread.start()

    async def _run(self):
        import viser
        from websockets.asyncio.client import connect

        async with connect(
            f"ws://127.0.0.1:{self.port}/?token={self.token}",
            origin=f"http://127.0.0.1:{self.port}",
            max_size=None,
            subprotocols=[f"viser-v{viser.__version__}"],
            open_timeout=60,
        ) as ws:
            while not self._stop.is_set():
                try:
                    msg = await asyncio.wait_for(ws.recv(), 0.5)
                except TimeoutError:
                    continue
                self.bytes += len(msg)
                self.messages += 1
                self.last = time.perf_counter()

    def wait_quiet(self, quiet_s=3.0, timeout_s=300.0) -> int:
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < timeout_s:
            if self.messages and time.perf_counter() - self.last > quiet_s:
                return self.bytes
            time.sleep(0.2)
        return self.bytes

    def stop(self):
        self._stop.set()
        self._thread.join(5)


def canvas_drawn(page) -> int:
    """Pixels of the 3-D canvas that are not its background (the clouds, meshes and labels drawn)."""
    from io import BytesIO

    from PIL import Image

    png = page.locator("canvas").first.screenshot(timeout=30_000)
    img = np.asarray(Image.open(BytesIO(png)).convert("RGB"), dtype=int)
    background = np.median(img.reshape(-1, 3), axis=0)
    return int(np.count_nonzero(np.abs(img - background).sum(axis=2) > 60))


def browser_timings(port: int, n: int, token: str = "", timeout_s=240.0) -> dict:
    from playwright.sync_api import sync_playwright

    out = {}
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=ARGS, headless=True)
        try:
            page = b.new_page(viewport={"width": 1400, "height": 900})
            t0 = time.perf_counter()
            page.goto(f"http://127.0.0.1:{port}/?token={token}", wait_until="domcontentloaded", timeout=60_000)
            page.wait_for_function(
                "() => document.body && document.body.innerText.includes('Total-field RMS')", timeout=timeout_s * 1000
            )
            out["gui_s"] = time.perf_counter() - t0
            while time.perf_counter() - t0 < timeout_s:
                if canvas_drawn(page) > 5000:
                    break
                page.wait_for_timeout(250)
            out["first_picture_s"] = time.perf_counter() - t0
            t1 = time.perf_counter()
            page.get_by_role("button", name="Run the chosen method").click(timeout=60_000)
            page.wait_for_function(
                "() => /Total-field RMS: [0-9.]+ nT/.test(document.body.innerText)", timeout=timeout_s * 1000
            )
            out["click_to_rms_s"] = time.perf_counter() - t1
            page.wait_for_function(
                r"() => /calibrate \(ML\): RMS .*\([0-9.]+ s\)/.test(document.body.innerText)", timeout=timeout_s * 1000
            )  # the step's message follows the status
            text = page.inner_text("body")
            m = re.search(r"calibrate \(ML\): RMS ([0-9.]+) -> ([0-9.]+) nT[^\n]*?\(([0-9.]+) s\)", text)
            if m:
                out["rms_after_nT"], out["fit_s"] = float(m.group(2)), float(m.group(3))
            else:
                print("the page's fit message was not found", flush=True)
            # a threshold rejection (Outliers tab, k = 4 sigma) and the warm refit it starts
            page.get_by_role("tab", name="Outliers").click(timeout=30_000)
            t2 = time.perf_counter()
            page.get_by_role("button", name="Reject beyond k sigma").click(timeout=60_000)
            page.wait_for_function(
                r"() => /Rejected: [1-9][0-9]* of/.test(document.body.innerText)", timeout=timeout_s * 1000
            )
            out["reject_s"] = time.perf_counter() - t2
            page.wait_for_function(
                r"() => /refine \(ML\): RMS .*\([0-9.]+ s\)/.test(document.body.innerText)", timeout=timeout_s * 1000
            )
            out["reject_refit_s"] = time.perf_counter() - t2
            m = re.search(r"refine \(ML\): RMS [^\n]*?\(([0-9.]+) s\)", page.inner_text("body"))
            if m:
                out["refit_s"] = float(m.group(1))
            page.close()
        finally:
            b.close()
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=1_000_000, help="samples (rows) of the four-sensor file")
    ap.add_argument("--max-points", type=int, default=20_000, help="the workbench's --max-points")
    ap.add_argument("--no-browser", action="store_true", help="skip Chromium (memory and bytes only)")
    args = ap.parse_args(argv)
    t_all = time.perf_counter()
    path = data_file(args.n)
    cli = run_cli(path)
    print(f"CLI: {cli['wall_s']:.1f} s, peak {cli['peak_MB']:.0f} MB", flush=True)
    cli["engine_s"], cli["step_s"] = fit_times_s(path)
    print(
        f"quiet process: magcal.calibrate {cli['engine_s']:.2f} s, the workbench's step {cli['step_s']:.2f} s",
        flush=True,
    )

    t0 = time.perf_counter()
    server = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "magcal_workbench._launch",
            str(path),
            "--port",
            "0",
            "--no-session",
            "--max-points",
            str(args.max_points),
        ],
        env=ENV,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    port = None
    log = []
    try:
        for line in server.stdout:
            log.append(line)
            m = re.search(r"open http://127\.0\.0\.1:(\d+)/\?token=([\w-]+)", line)
            if m:
                port, token = int(m.group(1)), m.group(2)
                break
            if time.perf_counter() - t0 > 300:
                break
        if port is None:
            raise SystemExit("the workbench did not start:\n" + "".join(log[-30:]))
        threading.Thread(target=lambda: [None for _ in server.stdout], daemon=True).start()  # drain its output
        start_s = time.perf_counter() - t0
        rss_start, _ = proc_memory_MB(server.pid)
        counter = WebsocketCounter(port, token)
        sent_connect = counter.wait_quiet()
        counter.bytes = 0
        row = {"start_s": start_s, "rss_start_MB": rss_start, "sent_connect_MB": sent_connect / 1e6}
        if not args.no_browser and os.path.exists(CHROMIUM):
            row.update(browser_timings(port, args.n, token))
            row["sent_fit_MB"] = counter.wait_quiet() / 1e6
        counter.stop()
        row["rss_end_MB"], row["peak_MB"] = proc_memory_MB(server.pid)
    finally:
        server.terminate()
        server.wait(30)

    fmt = lambda k, f="{:.1f}": f.format(row[k]) if k in row else "-"
    print()
    print(f"| {args.n:,} rows x 4 sensors, --max-points {args.max_points} | workbench | CLI |")
    print("|---|---|---|")
    print(f"| start (read + first scene), s | {fmt('start_s')} | - |")
    print(
        f"| server memory after start / peak, MB | {fmt('rss_start_MB', '{:.0f}')} / {fmt('peak_MB', '{:.0f}')} | "
        f"peak {cli['peak_MB']:.0f} |"
    )
    print(f"| sent to a browser on connect, MB | {fmt('sent_connect_MB')} | - |")
    print(f"| sent to a browser by the fit's redraw, MB | {fmt('sent_fit_MB')} | - |")
    print(f"| Chromium: panel shown / first picture, s | {fmt('gui_s')} / {fmt('first_picture_s')} | - |")
    print(
        f"| ML fit in a quiet process, s | {cli['step_s']:.2f} (Controller.step_calibrate) | "
        f"{cli['engine_s']:.2f} (magcal.calibrate) |"
    )
    print(
        f"| ML fit in the served workbench, browser rendering beside it, s | {fmt('fit_s', '{:.2f}')} "
        "(the page's figure) | - |"
    )
    print(f"| whole CLI run (start, read, fit, report), s | - | {cli['wall_s']:.1f} |")
    print(f"| click -> RMS shown, s | {fmt('click_to_rms_s')} | - |")
    print(
        f"| threshold reject shown / its warm ML refit done, s | {fmt('reject_s')} / {fmt('reject_refit_s')} "
        f"(refit {fmt('refit_s', '{:.2f}')}) | - |"
    )
    cli_rms = f"{cli['rms']:.3f}" if isinstance(cli["rms"], (int, float)) else "-"
    print(f"| RMS after, nT | {fmt('rms_after_nT', '{:.3f}')} | {cli_rms} |")
    print(f"\n(whole benchmark {time.perf_counter() - t_all:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
