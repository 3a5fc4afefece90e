"""End-to-end test of the workbench in a real headless Chromium (Debian's /usr/bin/chromium via playwright).

The test starts the workbench itself on 127.0.0.1 (port 0), opens the page, waits for the connection, runs a
fit from a click and checks the shown RMS changes, shift-drags a box over the scene and checks the rejected
count changes, and keeps a screenshot under ``test-artifacts/``. Without chromium or playwright it skips with the
reason, unless ``MAGCAL_REQUIRE_BROWSER=1`` (CI), where it fails.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
import pytest

import magcal
from magcal import io as mio

CHROMIUM = "/usr/bin/chromium"
ARGS = ["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--disable-background-networking"]
ARTIFACTS = Path(__file__).resolve().parent.parent / "test-artifacts"

pytestmark = [pytest.mark.e2e, pytest.mark.slow]


def _unavailable(reason: str):
    if os.environ.get("MAGCAL_REQUIRE_BROWSER") == "1":
        pytest.fail(f"MAGCAL_REQUIRE_BROWSER=1 but {reason}")
    pytest.skip(reason)


@pytest.fixture
def browser():
    if not os.path.exists(CHROMIUM):
        _unavailable(f"no browser at {CHROMIUM} (apt-get install chromium)")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        _unavailable("the playwright package is not installed (pip install playwright)")
    with sync_playwright() as p:
        try:
            b = p.chromium.launch(executable_path=CHROMIUM, args=ARGS, headless=True)
        except Exception as exc:  # a browser that cannot start is the same as none
            _unavailable(f"chromium could not be started: {exc}")
        try:
            yield b
        finally:
            b.close()


@pytest.fixture
def workbench(tmp_path):
    from workbench.app import Workbench
    from workbench.session import SessionStore

    ds = magcal.simulate_timeseries("chi2017", n_samples=240, seed=3, rate_hz=1.0)
    path = tmp_path / "e2e.csv"
    mio.write_csv(path, ds)
    data = mio.read_csv(path)
    wb = Workbench(data, host="127.0.0.1", port=0, store=SessionStore(tmp_path / "sessions"),
                   content=path.read_bytes(), name="e2e.csv")
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


def _open(browser, port):
    page = browser.new_page(viewport={"width": 1400, "height": 900})
    page.goto(f"http://127.0.0.1:{port}/", wait_until="domcontentloaded")
    page.wait_for_function("() => document.body && document.body.innerText.includes('Total-field RMS')",
                           timeout=90_000)
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
    page = _open(browser, workbench.port)
    assert "Connecting" not in _status(page)
    assert len(workbench.server.get_clients()) == 1

    # a fit from a click: the shown RMS changes from "not fitted yet" to a number
    before = _rms_text(page)
    assert before is not None and "not fitted" in before
    page.get_by_role("button", name="Run the chosen method").click()
    page.wait_for_function(
        "() => /Total-field RMS: [0-9.]+ nT/.test(document.body.innerText)", timeout=120_000)
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
    from workbench.scene import project_points

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
        timeout=60_000)
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
    other = _open(browser, workbench.port)
    other.wait_for_function(f"() => document.body.innerText.includes('Rejected: {n_rejected} of 240')",
                            timeout=60_000)
    assert _rms_text(other) == _rms_text(page)
    assert len(workbench.server.get_clients()) == 2
    other.close()
    page.close()
