"""The Calibrate tab follows the record's fit mode, in Chromium: a compensation flight (a scalar beside a fluxgate)
opens with the compensation's section and one line naming the mode, without the vector-fit and gravity-fit
sections or the total-field fit's Run; a four-sensor cross flown through a compensation box opens with the cross's
section alike, and its guide's steps fit, diagnose and add the current; the demo opened after them has the usual
tab back. Screenshots of each view are kept under ``test-artifacts/``.

Marked ``e2e`` (about a minute on two cores).
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

from magcal.data.cross_flight import simulate_cross_flight
from magcal_workbench.guide import next_step
from magcal_workbench.lessons import DEMO
from tests.helpers.cross_flights import write_cross_flight
from tests.workbench.test_workbench_compensation import flight_csv

ARTIFACTS = Path(__file__).resolve().parents[2] / "test-artifacts"

#: What the Calibrate tab shows of the fits a compensation flight does not have.
OTHER_FITS = ("Vector model (attitude-aided)", "Gravity model (beside an accelerometer)", "Run the chosen method")


@pytest.fixture
def page_on(tmp_path):
    """A workbench on a scalar compensation flight and one Chromium page on it."""
    from magcal.data import io as mio
    from magcal_workbench.app import Workbench
    from tests import conftest

    if not os.path.exists(conftest.CHROMIUM):
        conftest._unavailable(f"no browser at {conftest.CHROMIUM} (apt-get install chromium)")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        conftest._unavailable("the playwright package is not installed (pip install playwright)")
    path, _ = flight_csv(tmp_path / "box.csv")
    wb = Workbench(mio.read_csv(path), host="127.0.0.1", port=0, store=None, content=path.read_bytes(), name="box.csv")
    with sync_playwright() as p:
        try:
            browser = p.chromium.launch(executable_path=conftest.CHROMIUM, args=conftest.ARGS, headless=True)
        except Exception as exc:  # a browser that cannot start is the same as none
            wb.stop()
            conftest._unavailable(f"chromium could not be started: {exc}")
        page = browser.new_page(viewport={"width": 1400, "height": 1000})
        page.goto(wb.url, wait_until="domcontentloaded")
        _wait_text(page, "Fits it allows")
        try:
            yield wb, page, tmp_path
        finally:
            browser.close()
            wb.stop()


def _wait_text(page, words: str, timeout_ms: int = 120_000) -> None:
    page.wait_for_function("(t) => document.body.innerText.includes(t)", arg=words, timeout=timeout_ms)


def _idle(wb) -> None:
    time.sleep(0.1)
    assert wb.worker.wait(300)
    wb.ui.wait()


def _upload(wb, page, name: str, content: bytes) -> None:
    page.get_by_role("tab", name="Files").click(timeout=30_000)
    with page.expect_file_chooser(timeout=30_000) as chooser:
        page.get_by_text("Open a file (CSV, .bin, .ulg)").click(timeout=30_000)
    chooser.value.set_files(files=[{"name": name, "mimeType": "text/csv", "buffer": content}])
    _wait_text(page, f"{name}: ")
    _idle(wb)


def _press_guide(wb, page) -> str:
    step = next_step(wb.ctrl)
    _wait_text(page, step.label, 60_000)
    page.get_by_role("button", name=step.label).click(timeout=30_000)
    page.wait_for_function(
        "(label) => ![...document.querySelectorAll('button')].some(b => b.innerText.trim() === label)",
        arg=step.label,
        timeout=240_000,
    )
    _idle(wb)
    return step.key


def _calibrate_text(page) -> str:
    page.get_by_role("tab", name="Calibrate").click(timeout=30_000)
    time.sleep(0.5)
    return page.inner_text("body")


def _shot(page, name: str, anchor: str | None = None) -> None:
    """A screenshot of the page, the panel scrolled to ``anchor``'s text when given."""
    if anchor is not None:
        page.get_by_text(anchor, exact=False).first.evaluate("(e) => e.scrollIntoView({block: 'start'})")
        time.sleep(1.0)  # plotly draws after the scroll
    for close in page.locator(".mantine-Notification-closeButton").all():
        try:
            close.click(timeout=2000)
        except Exception:  # a toast gone already
            pass
    ARTIFACTS.mkdir(exist_ok=True)
    page.screenshot(path=str(ARTIFACTS / name))


@pytest.mark.e2e
@pytest.mark.slow
def test_a_compensation_flight_shows_its_compensation_only_and_the_demo_its_usual_tab(page_on):
    wb, page, folder = page_on
    text = _calibrate_text(page)
    assert "Compensation (a scalar magnetometer beside a fluxgate)" in text and "Fit mode: compensation fit" in text
    assert [words for words in OTHER_FITS if words in text] == []
    assert _press_guide(wb, page) == "compensation"
    _wait_text(page, "Improvement ratio")
    _shot(page, "calibrate_compensation.png")
    _shot(page, "calibrate_compensation_section.png", "Run the compensation fit")

    flight = simulate_cross_flight(3, platform="drone_current")
    cross = write_cross_flight(flight, folder / "cross.csv", reference=False)
    _upload(wb, page, "cross.csv", cross.read_bytes())
    text = _calibrate_text(page)
    assert "Cross compensation (four sensors on a moving platform)" in text and "Fit mode: cross compensation" in text
    assert [words for words in OTHER_FITS if words in text] == []
    assert [_press_guide(wb, page) for _ in range(3)] == ["compensation", "diagnose", "add"]
    assert wb.ctrl.cross_compensation.effects == ["current"]
    _wait_text(page, "after nT/m")
    _shot(page, "calibrate_cross_compensation.png")
    _shot(page, "calibrate_cross_compensation_section.png", "Run the compensation fit")
    _shot(page, "calibrate_cross_compensation_table.png", "A maneuver's part is the root sum")
    page.get_by_role("tab", name="Model").click(timeout=30_000)
    _wait_text(page, "Compensation's steps")
    assert "Your own effects" not in page.inner_text("body")
    _shot(page, "model_cross_compensation.png", "Compensation's steps")

    _upload(wb, page, "demo.csv", DEMO.read_bytes())
    text = _calibrate_text(page)
    assert [words for words in OTHER_FITS if words not in text] == []
    assert "Fit mode:" not in text and "Compensation (" not in text and "Cross compensation (" not in text
    _shot(page, "calibrate_demo.png")
