"""Click-to-result time of the workbench, as a person waits (issue 44): a real ``magcal-workbench`` process and a
headless Chromium (software WebGL) driven by playwright, on simulated four-sensor records
(``magcal simulate --timeseries --n N --seed 3``).

    PYTHONPATH=$PWD python benchmarks/page_latency.py [--n 10000 100000] [--first-picture 1000000] [--repeat 3]

For each record size it times, from the click (or the launch) to what the page shows:

* launch -> address printed, launch -> page with the Total-field RMS, launch -> first picture (the scene's
  points drawn: stamped by the page at the frame after the one that applied the clouds and their status line;
  also as it was timed before, polled by playwright and two frames later), launch -> whole page (the
  workbench built, the Calibrate tab's two plotly figures drawn, and the first picture);
* launch -> the page's first line (the launcher sends "loading FILE..." when it prints the address: the time the
  page shows it is the browser's own start), and the megabytes the page received before the RMS (as playwright
  hands them on, to within its polling);
* the page at rest after the clicks: the cores the browser uses (viser redraws the scene once a second; with
  software WebGL that costs CPU beside every fit) and the server's;
* Run -> the new ``calibrate (ML)`` message line; Exclude range -> the refit's line; Diagnose -> the verdict's
  line; Add (the top candidate) -> the refit's line; and, for each, until the slow parts (held-out RMS) are shown.

The workbench runs with ``--timing``: its spans (fit, held-out, uncertainty, coverage, scene, plots, ...) are
summed per click from its standard error, so the table splits the server's work from the rest (the messages, the
browser's plotly and WebGL). ``--first-picture N`` only launches and waits for the first picture on N samples.
Prints one markdown row per record and click: min and median of ``--repeat`` launches.
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

CHROMIUM = "/usr/bin/chromium"
ARGS = ["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--disable-background-networking"]

#: The message line of a finished step: ``**calibrate (ML)**: RMS a -> b nT ...`` as the page's text shows it.
STEP_LINE = r"(calibrate \(ML\)|refine \(ML\)|add \S+|diagnose): [^\n]*"


def simulate(n: int, folder: Path) -> Path:
    path = folder / f"sim{n}.csv"
    if not path.exists():
        subprocess.run(
            [sys.executable, "-m", "magcal", "simulate", "--timeseries", "--n", str(n), "--seed", "3", "-o", str(path)],
            check=True,
            capture_output=True,
        )
    return path


class Server:
    """``magcal-workbench FILE --port 0 --no-session --timing`` as a subprocess; its spans read from stderr."""

    def __init__(self, path: Path):
        self.t0 = time.perf_counter()
        self.epoch0 = time.time()  # the launch on the wall clock, which the page's own timestamps share
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        # as a user's install runs it: Python keeps the modules' compiled bytecode (this sandbox sets
        # PYTHONDONTWRITEBYTECODE=1, which compiles magcal's sources again at each launch: 0.35 s of the import)
        env.pop("PYTHONDONTWRITEBYTECODE", None)
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "magcal_workbench._launch", str(path), "--port", "0", "--no-session", "--timing"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
        )
        self.spans: list[tuple[float, str, float]] = []  # (arrival on our clock, name, seconds)
        self._lock = threading.Lock()
        threading.Thread(target=self._read_spans, daemon=True).start()
        self.url = None
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            m = re.search(r"open (http\S+)", line)
            if m:
                self.url = m.group(1)
                break
        if self.url is None:
            raise RuntimeError("the workbench did not print its address")
        self.t_url = time.perf_counter() - self.t0

    def _read_spans(self):
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            m = re.match(r"magcal-timing: (\S+) (\S+) (\S+)", line)
            if m:
                with self._lock:
                    self.spans.append((time.perf_counter(), m.group(1), float(m.group(3))))

    def spans_since(self, t: float) -> dict[str, float]:
        out: dict[str, float] = {}
        with self._lock:
            for arrived, name, sec in self.spans:
                if arrived >= t:
                    out[name] = out.get(name, 0.0) + sec
        return out

    def stop(self):
        self.proc.terminate()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()


def _lines(page) -> list[str]:
    """The step lines the page shows, whole (the page's own check compares whole lines: ``re.findall`` would give
    only the step's name, and a line shown before the click would then count as new)."""
    return [m.group(0) for m in re.finditer(STEP_LINE, page.inner_text("body"))]


def _wait_new_line(page, before: list[str], prefix: str, timeout_s: float = 240) -> float:
    """Seconds until a step line starting with ``prefix`` that was not shown before appears."""
    t0 = time.perf_counter()
    js = (
        "([re, before, prefix]) => { const m = document.body.innerText.match(new RegExp(re, 'g')) || [];"
        " return m.some(l => l.startsWith(prefix) && !before.includes(l)); }"
    )
    page.wait_for_function(js, arg=[STEP_LINE, before, prefix], timeout=timeout_s * 1000, polling=20)
    return time.perf_counter() - t0


def _wait_idle(page, timeout_s: float = 240) -> float:
    """Seconds until the page is at rest: it shows no job running (the progress text gone) and no part pending,
    and it has painted two frames since (what it was sent is drawn: the next click does not wait for the last
    one's figures)."""
    t0 = time.perf_counter()
    page.wait_for_function(
        "() => !/Running: |pending\\.\\.\\./.test(document.body.innerText)", timeout=timeout_s * 1000, polling=50
    )
    page.evaluate(PAINT_HOOK)
    page.wait_for_function("() => !!window.__magcalPainted", timeout=timeout_s * 1000, polling=20)
    return time.perf_counter() - t0


def _click(page, name: str) -> None:
    page.get_by_role("button", name=name, exact=True).first.click()


FIRST_PICTURE_JS = """() => {
  const c = document.querySelector('canvas');
  if (!c || document.body.innerText.includes('Connecting')) return false;
  return !!window.__magcalPainted;
}"""

PAINT_HOOK = """() => { window.__magcalPainted = false;
  requestAnimationFrame(() => requestAnimationFrame(() => { window.__magcalPainted = true; })); }"""


#: Stamps (wall clock, ms) the moment the Total-field RMS is first visible: a mutation observer, cheap
#: (textContent first; innerText, which lays the page out, only once the text is there), not a poller.
RMS_SEEN_JS = """(() => {
  const look = () => {
    if (window.__magcalRmsSeen || !document.body) return;
    if (!document.body.textContent.includes('Total-field RMS')) return;
    if (/Total-field RMS/.test(document.body.innerText)) {
      window.__magcalRmsSeen = performance.timeOrigin + performance.now();
      observer.disconnect();
    }
  };
  const picture = () => {  // the clouds' message applied (its line shown): the next frame begins once it is painted
    if (window.__magcalPictureAsked || !document.body || !document.querySelector('canvas')) return;
    if (!/a preview of|\\braw\\b/.test(document.body.textContent)) return;
    if (!/a preview of|\\braw\\b/.test(document.body.innerText)) return;  // shown, not only in the page
    window.__magcalPictureAsked = true;
    requestAnimationFrame(() => { window.__magcalPictureSeen = performance.timeOrigin + performance.now(); });
  };
  new MutationObserver(picture).observe(document, {childList: true, subtree: true, characterData: true});
  const first = () => {  // the page's first line from the server (the launcher's "loading ..."): its own start
    if (!window.__magcalFirstLine && document.body && /loading|Total-field RMS/.test(document.body.textContent)) {
      window.__magcalFirstLine = performance.timeOrigin + performance.now();
    }
  };
  new MutationObserver(first).observe(document, {childList: true, subtree: true, characterData: true});
  const observer = new MutationObserver(look);
  const start = () => observer.observe(document.documentElement, {childList: true, subtree: true, characterData: true});
  if (document.documentElement) start(); else document.addEventListener('readystatechange', start, {once: true});
})();"""


#: The Calibrate tab's figures (|B| against time, the error histogram) drawn by plotly: each has its axes' layer.
PLOTS_DRAWN_JS = """() => [...document.querySelectorAll('.js-plotly-plot')].filter(
  p => p.querySelector('.main-svg .cartesianlayer .xy')).length >= 2"""


def open_page(browser, server: Server) -> tuple:
    """Open the page as soon as the address is printed; seconds from the launch to the page with the
    Total-field RMS (the status line, sent before the tabs are built), to the first picture (the raw clouds
    painted: the workbench's scene, or a large file's preview, which the status line announces) and to the whole
    page (the workbench built, the Calibrate tab's figures drawn, the clouds painted)."""
    page = browser.new_page(viewport={"width": 1400, "height": 900})
    page.add_init_script(RMS_SEEN_JS)
    frames: list[tuple[float, int]] = []  # (arrival since the launch, bytes) of the server's websocket messages
    page.on(
        "websocket",
        lambda ws: ws.on("framereceived", lambda data: frames.append((time.perf_counter() - server.t0, len(data)))),
    )
    page.goto(server.url, wait_until="domcontentloaded")
    page.wait_for_function("() => !document.body.innerText.includes('Connecting')", timeout=600_000)
    # the scene's clouds: viser draws points once the scene messages have arrived; two frames after that
    page.wait_for_function(
        "() => document.querySelectorAll('canvas').length > 0 && "
        "/\\braw\\b|a preview of/.test(document.body.innerText)",
        timeout=600_000,
        polling=20,
    )
    page.evaluate(PAINT_HOOK)
    page.wait_for_function(FIRST_PICTURE_JS, timeout=600_000, polling=20)
    t_pic_polled = time.perf_counter() - server.t0
    # stamped by the page itself: the frame after the one that applied the clouds and their line (the polled time
    # above adds playwright's polling and two more frames, which may be the workbench's build: 1 s at 4 x 1e4)
    pic_ms = page.evaluate("window.__magcalPictureSeen")
    t_pic = pic_ms / 1000 - server.epoch0 if pic_ms else t_pic_polled
    page.wait_for_function(
        "() => document.body && /Total-field RMS/.test(document.body.innerText)", timeout=600_000, polling=20
    )
    # when the text first became visible, stamped by the page itself (the waits above run one after the other:
    # the RMS may have been shown before the picture was painted)
    seen_ms = page.evaluate("window.__magcalRmsSeen")
    t_rms = seen_ms / 1000 - server.epoch0 if seen_ms else time.perf_counter() - server.t0
    first_ms = page.evaluate("window.__magcalFirstLine")
    timeline = {
        # the browser's own start: the launcher sends this line at the address, the page shows it this late
        "page's first line": first_ms / 1000 - server.epoch0 if first_ms else float("nan"),
        "MB received before the RMS": sum(n for t, n in frames if t <= t_rms) / 1e6,
        "first picture, polled + 2 frames": t_pic_polled,
    }
    # the launcher's status line ("loading FILE...") goes once the workbench is built: the clicks start then
    page.wait_for_function(
        "() => !/loading [^\\n]*\\.\\.\\./.test(document.body.innerText)", timeout=600_000, polling=50
    )
    # the whole page: built (the line above gone), the Calibrate tab's two figures drawn, the clouds painted
    page.wait_for_function(PLOTS_DRAWN_JS, timeout=600_000, polling=20)
    t_whole = max(time.perf_counter() - server.t0, t_pic)
    return page, t_rms, t_pic, t_whole, timeline


#: Seconds the page at rest is watched after the clicks (after a settling second).
REST_S = 5.0


def _cpu_seconds(pids) -> float:
    """User plus system CPU seconds used so far by the processes ``pids`` (Linux ``/proc``; gone ones count 0)."""
    total = 0
    for pid in pids:
        try:
            with open(f"/proc/{pid}/stat") as fh:
                fields = fh.read().rsplit(")", 1)[1].split()
            total += int(fields[11]) + int(fields[12])
        except (OSError, IndexError, ValueError):
            pass
    return total / os.sysconf("SC_CLK_TCK")


def _chromium_pids() -> list[int]:
    pids = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/cmdline", "rb") as fh:
                    if b"chromium" in fh.read():
                        pids.append(int(entry))
            except OSError:
                pass
    return pids


def cores_at_rest(server_pid: int, seconds: float = REST_S) -> tuple[float, float]:
    """Cores used by the browser (every Chromium process: its renderer, and the GPU process that runs WebGL in
    software) and by the server while the only page open sits at rest, over the same ``seconds``: viser redraws
    the scene once a second (issue 44)."""
    time.sleep(1.0)
    browser = _chromium_pids()
    before = _cpu_seconds(browser), _cpu_seconds([server_pid])
    time.sleep(seconds)
    after = _cpu_seconds(browser), _cpu_seconds([server_pid])
    return (after[0] - before[0]) / seconds, (after[1] - before[1]) / seconds


def one_launch(browser, path: Path, clicks: bool) -> dict[str, float]:
    server = Server(path)
    out: dict[str, float] = {"address printed": server.t_url}
    page = None
    try:
        page, out["first page with the RMS"], out["first picture"], out["whole page"], timeline = open_page(
            browser, server
        )
        out.update(timeline)
        print(f"  launch: {out}", file=sys.stderr)
        if not clicks:
            return out
        # Diagnose before Exclude range: the engine's diagnosis of a fit with an excluded stretch took 79 s at
        # 4 x 1e5 (1.8 s without; notes/page_latency.md), which would hide the page's own times
        steps = (
            ("Run", "Calibrate", "Run the chosen method", "calibrate (ML)"),
            ("Diagnose", "Model", "Diagnose", "diagnose"),
            ("Add-and-refit", "Model", "Add the candidate and refit", "add "),
            ("Exclude range", "Calibrate", "Exclude range", "refine (ML)"),
        )
        for label, tab, button, prefix in steps:
            _wait_idle(page)
            page.get_by_role("tab", name=tab).first.click()
            page.get_by_role("button", name=button).first.wait_for(state="visible", timeout=60_000)
            before = _lines(page)
            t = time.perf_counter()
            _click(page, button)
            out[label] = _wait_new_line(page, before, prefix)
            out[f"{label}: all parts"] = out[label] + _wait_idle(page)
            print(f"  {label}: {out[label]:.2f} s, all parts {out[f'{label}: all parts']:.2f} s", file=sys.stderr)
            time.sleep(0.3)  # the last spans' lines reach us
            for name, sec in server.spans_since(t).items():
                out[f"{label} server {name}"] = sec
        _wait_idle(page)
        out["page at rest: browser CPU, cores"], out["page at rest: server CPU, cores"] = cores_at_rest(server.proc.pid)
    except Exception as exc:  # a step that never answered: the row says so, the other launches go on
        print(f"  failed: {type(exc).__name__}: {str(exc)[:200]}", file=sys.stderr)
    finally:
        if page is not None:  # a page left open keeps drawing (and reconnecting): the next launch would pay for it
            page.close()
        server.stop()
    return out


def main(argv=None) -> None:
    from playwright.sync_api import sync_playwright

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, nargs="*", default=[10_000, 100_000])
    ap.add_argument("--first-picture", type=int, nargs="*", default=[1_000_000])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--data", default=None, help="folder of the simulated records (default: a temporary folder)")
    args = ap.parse_args(argv)
    folder = Path(args.data or tempfile.mkdtemp(prefix="magcal-latency-"))
    folder.mkdir(parents=True, exist_ok=True)
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=ARGS, headless=True)
        runs = [(n, True) for n in args.n] + [(n, False) for n in args.first_picture]
        for n, clicks in runs:
            path = simulate(n, folder)
            results = [one_launch(browser, path, clicks) for _ in range(args.repeat)]
            keys = list(dict.fromkeys(k for r in results for k in r))
            print(f"\n4 x {n:,} samples ({args.repeat} launches): seconds, min / median")
            print("| what | min s | median s |")
            print("|---|---|---|")
            for k in keys:
                vals = [r[k] for r in results if k in r]
                print(f"| {k} | {min(vals):.2f} | {statistics.median(vals):.2f} |")
            sys.stdout.flush()
        browser.close()


if __name__ == "__main__":
    main()
