"""End-to-end test of the workbench in a real headless Chromium (Debian's /usr/bin/chromium via playwright).

The test starts the workbench itself on 127.0.0.1 (port 0), opens the page, waits for the connection, runs a
fit from a click and checks the shown RMS changes, shift-drags a box over the scene and checks the rejected
count changes, and keeps a screenshot under ``test-artifacts/``. A CSV whose header or file name holds
``<script>``, ``<img onerror>`` or ``<svg onload>`` is uploaded through the page and runs nothing (window flags stay
unset, no such element appears), and a page served from another origin cannot open the workbench's websocket.
Scenes are kept small (software WebGL is slow) and every wait is bounded. Without chromium or playwright the tests
skip with the reason, unless ``MAGCAL_REQUIRE_BROWSER=1`` (CI), where they fail.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

import magcal
from magcal.data import io as mio

ARTIFACTS = Path(__file__).resolve().parents[2] / "test-artifacts"

pytestmark = [pytest.mark.e2e, pytest.mark.slow]


@pytest.fixture
def workbench(tmp_path):
    from magcal_workbench.app import Workbench
    from magcal_workbench.session import SessionStore

    ds = magcal.simulate_timeseries("chi2017", n_samples=240, seed=3, rate_hz=1.0)
    path = tmp_path / "e2e.csv"
    mio.write_csv(path, ds)
    data = mio.read_csv(path)
    wb = Workbench(
        data,
        host="127.0.0.1",
        port=0,
        store=SessionStore(tmp_path / "sessions"),
        content=path.read_bytes(),
        name="e2e.csv",
    )
    try:
        yield wb
    finally:
        wb.stop()


def _dismiss_toasts(page) -> None:
    """Close viser's notifications (e.g. "software WebGL rendering detected") so screenshots show the scene."""
    for close in page.locator(".mantine-Notification-closeButton").all():
        try:
            close.click(timeout=2000)
        except Exception:  # already gone
            pass


def _open(browser, wb):
    """Open the workbench ``wb``'s page at the address it prints (with its token) and wait until it is connected."""
    page = browser.new_page(viewport={"width": 1400, "height": 900})
    page.goto(wb.url, wait_until="domcontentloaded")
    page.wait_for_function("() => document.body && document.body.innerText.includes('Total-field RMS')", timeout=90_000)
    page.wait_for_function("() => !document.body.innerText.includes('Connecting')", timeout=90_000)
    return page


def _status(page) -> str:
    return page.inner_text("body")


def _rms_text(page):
    m = re.search(r"Total-field RMS: ([^\n(]+)", _status(page))
    return m.group(1).strip() if m else None


def _rejected(page):
    m = re.search(r"Rejected: (\d+) of (\d+)", _status(page))
    return int(m.group(1)) if m else None


def test_page_connects_fits_and_box_selects(browser, workbench):
    page = _open(browser, workbench)
    assert "Connecting" not in _status(page)
    assert len(workbench.server.get_clients()) == 1

    # a fit from a click: the shown RMS changes from "not fitted yet" to a number
    before = _rms_text(page)
    assert before is not None and "not fitted" in before
    page.get_by_role("button", name="Run the chosen method").click()
    page.wait_for_function("() => /Total-field RMS: [0-9.]+ nT/.test(document.body.innerText)", timeout=120_000)
    after = _rms_text(page)
    assert after != before
    rms = float(after.split()[0])
    assert 1.0 < rms < 10.0, after  # sigma = 3 nT: the fit reached the noise

    # shift-drag a box over the middle of the canvas: the rejected count changes
    assert _rejected(page) == 0
    workbench.worker.wait(60)
    canvas = page.locator("canvas").first
    box = canvas.bounding_box()
    assert box is not None
    # aim at sensor 1's raw cloud: project its shown points with the browser's own camera
    client = next(iter(workbench.server.get_clients().values()))
    cam = client.camera
    from magcal_workbench.scene import project_points

    d = workbench.scene_view.displayed
    uv, front = project_points(d.positions, cam.wxyz, cam.position, cam.fov, cam.aspect)
    pts = uv[(d.sensors == 0) & front]
    target = pts[np.argmin(pts[:, 1])]  # the top of sensor 1's first cloud: a box there holds part of it
    half = 0.03
    x0 = box["x"] + box["width"] * (target[0] - half)
    y0 = box["y"] + box["height"] * (target[1] - half)
    x1 = box["x"] + box["width"] * (target[0] + half)
    y1 = box["y"] + box["height"] * (target[1] + half)
    page.mouse.move(x0, y0)
    page.keyboard.down("Shift")
    page.mouse.down()
    page.mouse.move((x0 + x1) / 2, (y0 + y1) / 2, steps=5)
    page.mouse.move(x1, y1, steps=5)
    page.mouse.up()
    page.keyboard.up("Shift")
    page.wait_for_function(
        "() => { const m = document.body.innerText.match(/Rejected: (\\d+) of/); return m && +m[1] > 0; }",
        timeout=60_000,
    )
    n_rejected = _rejected(page)
    assert 0 < n_rejected < 240
    assert workbench.ctrl.state.selection.n_rejected == n_rejected
    workbench.worker.wait(60)

    page.wait_for_function("() => /Total-field RMS: [0-9.]+ nT/.test(document.body.innerText)", timeout=60_000)
    _dismiss_toasts(page)
    ARTIFACTS.mkdir(exist_ok=True)
    shot = ARTIFACTS / "workbench_e2e.png"
    page.screenshot(path=str(shot))
    assert shot.stat().st_size > 10_000

    # a second browser sees the same state: the same RMS and the same rejected count
    other = _open(browser, workbench)
    other.wait_for_function(f"() => document.body.innerText.includes('Rejected: {n_rejected} of 240')", timeout=60_000)
    assert _rms_text(other) == _rms_text(page)
    assert len(workbench.server.get_clients()) == 2
    other.close()
    page.close()


#: Each payload sets a window flag if the page ever runs it.
PAYLOADS = {
    "img": '<img src=x onerror="window.__magcal_pwned_img=1">',
    "script": "<script>window.__magcal_pwned_script=1</script>",
    "svg": '<svg onload="window.__magcal_pwned_svg=1">',
}
FLAGS = ["__magcal_pwned_img", "__magcal_pwned_script", "__magcal_pwned_svg"]


def _upload_in_page(page, name: str, content: bytes) -> None:
    """Choose a file in the page's upload button, as a user would (the browser sends it over the websocket)."""
    page.get_by_role("tab", name="Files").click(timeout=30_000)
    with page.expect_file_chooser(timeout=30_000) as chooser:
        page.get_by_text("Open a file (CSV, .bin, .ulg)").click(timeout=30_000)
    chooser.value.set_files(files=[{"name": name, "mimeType": "text/csv", "buffer": content}])


def _no_flag(page) -> bool:
    return page.evaluate(f"() => {FLAGS!r}.every(f => window[f] === undefined)")


@pytest.fixture
def small_workbench(tmp_path):
    from magcal_workbench.app import Workbench

    ds = magcal.simulate("chi2017", n_samples=40, seed=1)
    path = tmp_path / "small.csv"
    mio.write_csv(path, ds)
    wb = Workbench(mio.read_csv(path), host="127.0.0.1", port=0, store=None)
    try:
        yield wb
    finally:
        wb.stop()


@pytest.mark.parametrize("where", ["header", "file name"])
def test_a_hostile_csv_header_or_file_name_runs_nothing(browser, small_workbench, where):
    """A CSV someone sent you must not run their script in your page, whether the reader echoes its
    header in an error or the page shows its name."""
    page = _open(browser, small_workbench)
    assert _no_flag(page)
    hostile = " ".join(PAYLOADS.values())
    if where == "header":
        name, content = "header.csv", f"{hostile},s1y,s1z\n1,2,3\n".encode()
        shown = PAYLOADS["img"]
    else:
        name, content = f"{PAYLOADS['img']}{PAYLOADS['svg']}.csv", b"s1x,s1y,s1z\n1,2\n"
        shown = PAYLOADS["svg"]
    _upload_in_page(page, name, content)
    assert small_workbench.worker.wait(60)
    # the message shows the hostile text as text (escaped), and the flags stay unset
    page.wait_for_function("(t) => document.body.innerText.includes(t)", arg=shown, timeout=60_000)
    page.wait_for_timeout(1500)  # let an injected image fail to load (its onerror would fire now)
    assert _no_flag(page)
    assert page.locator("img[src='x']").count() == 0 and page.locator("svg[onload]").count() == 0
    assert "**Error:**" in small_workbench.ctrl.message
    page.close()


def test_a_page_from_another_origin_cannot_open_the_websocket(browser, small_workbench):
    """A web page the user visits (here served from another port of this machine) tries to open the
    workbench's websocket: the browser sends the page's Origin, the handshake is refused, no message arrives."""
    import http.server
    import threading

    import viser

    port = small_workbench.port
    hostile = f"""<!doctype html><title>evil</title><script>
      window.result = {{open: false, messages: 0, done: false}};
      const ws = new WebSocket("ws://127.0.0.1:{port}", ["viser-v{viser.__version__}"]);
      ws.onopen = () => {{ window.result.open = true; }};
      ws.onmessage = () => {{ window.result.messages += 1; }};
      ws.onerror = ws.onclose = () => {{ window.result.done = true; }};
    </script>""".encode()

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self):
            self.send_response(200)
            self.send_header("Content-Type", "text/html")
            self.end_headers()
            self.wfile.write(hostile)

        def log_message(self, *args):
            pass

    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    try:
        page = browser.new_page()
        page.goto(f"http://127.0.0.1:{httpd.server_address[1]}/", wait_until="load", timeout=30_000)
        page.wait_for_function("() => window.result.done", timeout=30_000)
        assert page.evaluate("() => window.result") == {"open": False, "messages": 0, "done": True}
        assert len(small_workbench.server.get_clients()) == 0
        # the workbench's own page still connects
        own = _open(browser, small_workbench)
        assert len(small_workbench.server.get_clients()) == 1
        own.close()
        page.close()
    finally:
        httpd.shutdown()


def test_the_page_opens_from_the_printed_url_only(browser, small_workbench):
    """The address without the token shows the refusal and connects nothing; the printed address (its
    token then carried by the page's script to its websocket) connects and shows the session."""
    wb = small_workbench
    page = browser.new_page()
    response = page.goto(f"http://127.0.0.1:{wb.port}/", wait_until="load", timeout=30_000)
    assert response.status == 403 and "token" in page.inner_text("body")
    page.wait_for_timeout(500)
    assert len(wb.server.get_clients()) == 0
    page.close()
    own = _open(browser, wb)
    assert len(wb.server.get_clients()) == 1
    own.close()
