"""Screenshots of the workbench for the README (run from the repository root; needs chromium and playwright).

    python assets/make_screenshots.py

Opens the bundled demo in headless Chromium and saves, under ``docs/img/``:

* ``workbench-scene.png`` - the four sensors after calibration: raw clouds on their fitted ellipsoids, corrected
  clouds on the reference sphere coloured by residual, the cross with each sensor's axes, the step tables;
* ``workbench-loop-before.png`` - Diagnose on the base model: the ranked candidates and their evidence;
* ``workbench-loop-after.png`` - after Add and a second Diagnose: the verdict, the RMS history falling to the
  noise-floor line, the evidence plots.

``python assets/make_screenshots.py live`` saves the live view instead (a simulated instrument streamed in):

* ``live-growing.png`` - part way: the growing clouds, each sensor's coverage sphere (visited green, missing grey,
  the largest gap's centre orange) and the advice on where to turn;
* ``live-enough.png`` - at the end: the directions covered, the fit at the noise floor, "enough".

``python assets/make_screenshots.py vehicle`` saves the vector model (issue 29), on the lesson ``cannot-tumble``:

* ``vector-table.png`` - the total-field fit and the vector fit side by side (Calibrate tab);
* ``vehicle-view.png`` - the vehicle view: the body by its attitude, the model and measured field in N, E, D, the
  residual exaggerated.

``python assets/make_screenshots.py loop`` saves the loop on a vehicle (issue 40), on the lesson ``drone-current``:

* ``vector-loop-diagnose.png`` - Diagnose on the vector model: the verdict against the world noise floor, the
  candidates with their world RMS in-sample and on the later part, the advice;
* ``vector-loop-evidence.png`` - the evidence plots at full size: the world residuals north, east, down and |B|
  against the battery current, before Add;
* ``vector-loop-after.png`` - after Add: the same plots flat, the world RMS per step falling to the floor.

``python assets/make_screenshots.py see`` saves where a model fails (issue 15):

* ``see-scrubber.png`` - the two-effect lesson with its temperature term added, a time window after the bias step;
* ``see-residual-map.png`` - the bent-response lesson: the residual pattern surfaces (sensor 3 stands out);
* ``see-candidate.png`` - the same with the top candidate's pattern: what adding it would explain;
* ``see-evidence.png`` - after Add: the evidence plots at full size over the canvas, with each sensor's RMS before
  the last fit.

``python assets/make_screenshots.py newcomer`` saves the first screens a newcomer meets:

* ``guide-first.png`` - the demo as it opens: what the data are, the fits they allow, and Step 1 as a button;
* ``guide-lesson.png`` - the drone lesson as it opens: its text first, then the data and Step 1 (the vector fit);
* ``guide-vehicle.png`` - after the vector fit: the vehicle view, a quadcopter by its attitude, the fields in
  N, E, D (the body's axes grey, no colour shared with a field);
* ``guide-vector-scene.png`` - the same record's scene: the raw cloud and the cloud the vector fit corrected, the
  Quality tab's one noise floor with its source;
* ``guide-gravity.png`` - the accelerometer board after its first step, the gravity fit: the corrected cloud, the
  guide pointing to the total-field loop one choice away.

``python assets/make_screenshots.py compensation`` saves the compensation on the lesson ``survey-drone-current``:

* ``compensation-first.png`` - the lesson as it opens: its text, the data (a scalar magnetometer beside the
  fluxgate) and Step 1 (the Tolles-Lawson fit);
* ``compensation-view.png`` - after Step 1, 2 and 3: the FOM before -> after in the status, the Calibrate tab's
  band-passed scalar before and after with the maneuvers shaded, the FOM table per heading and maneuver.

``python assets/make_screenshots.py cockpit`` saves the cockpit (issue 32):

* ``cockpit-calibrate.png`` - the demo after a fit: the compact table (RMS against the floor, % within +-1/2/5 %,
  C^-1 and bias, coverage) above the tabs, the scene filling the canvas left of the panel;
* ``cockpit-field.png`` - |B| against time with an excluded time range (grey band) and the next range (blue);
* ``cockpit-histogram.png`` - the error histogram before and after calibration;
* ``cockpit-single.png`` - a single-sensor recording: two clouds, no cross, the tilt ring of the time window's
  current sample, the fast-turning samples ringed red;
* ``cockpit-live.png``, ``cockpit-live-plots.png`` - a live session (paused for the picture, so the software-
  rendered page catches up): the table, |B| and the histogram following the stream.
"""

from __future__ import annotations

import sys
import time
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "docs" / "img"
CHROMIUM = "/usr/bin/chromium"
ARGS = ["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--disable-background-networking"]


def _wait_text(page, js_condition, timeout=180_000):
    page.wait_for_function(f"() => {js_condition}", timeout=timeout)


def _page(p, wb):
    browser = p.chromium.launch(executable_path=CHROMIUM, args=ARGS, headless=True)
    page = browser.new_page(viewport={"width": 1600, "height": 1000})
    page.goto(wb.url)
    _wait_text(page, "document.body.innerText.includes('Fits it allows')")
    time.sleep(2)
    for close in page.locator(".mantine-Notification-closeButton").all():
        close.click()
    return browser, page


def live() -> int:
    """The live view's screenshots (see the module docstring)."""
    import re
    import tempfile

    from playwright.sync_api import sync_playwright

    from magcal.data import io as mio
    from magcal_workbench.app import Workbench
    from magcal_workbench.lessons import DEMO

    warnings.simplefilter("ignore")
    wb = Workbench(mio.read_csv(DEMO), host="127.0.0.1", port=0, store=None)
    try:
        with sync_playwright() as p:
            browser, page = _page(p, wb)
            rec = Path(tempfile.mkdtemp()) / "live.csv"
            wb.livectl.start("sim://chi2017?rate=50&n=6000&speed=4", rec)

            def received():
                m = re.search(r"(\d+) samples received", page.inner_text("body"))
                return int(m.group(1)) if m else 0

            while received() < 1600:
                time.sleep(0.2)
            time.sleep(1)
            page.screenshot(path=str(OUT / "live-growing.png"))
            _wait_text(page, "document.body.innerText.includes('enough:')", timeout=300_000)
            time.sleep(3)
            page.screenshot(path=str(OUT / "live-enough.png"))
            browser.close()
    finally:
        if wb.live is not None and wb.live.active:
            wb.live.stop()
        wb.stop()
    print(f"wrote live-growing.png, live-enough.png in {OUT}")
    return 0


def see() -> int:
    """The screenshots of where a model fails (see the module docstring)."""
    from playwright.sync_api import sync_playwright

    from magcal.data import io as mio
    from magcal_workbench.app import Workbench
    from magcal_workbench.lessons import get_lesson

    warnings.simplefilter("ignore")
    with sync_playwright() as p:
        wb = Workbench(mio.read_csv(get_lesson("two-culprits").data_path), host="127.0.0.1", port=0, store=None)
        try:
            wb.ctrl.step_calibrate("ml")
            wb.ctrl.step_diagnose()
            wb.ctrl.step_add(None)
            browser, page = _page(p, wb)
            page.get_by_role("tab", name="View").click()
            wb.panels.window_width.value = 10.0
            wb.panels.window_start.value = 70.0
            wb.panels.window_on.value = True
            time.sleep(3)
            page.screenshot(path=str(OUT / "see-scrubber.png"))
            browser.close()
        finally:
            wb.stop()
        wb = Workbench(mio.read_csv(get_lesson("bent-response").data_path), host="127.0.0.1", port=0, store=None)
        try:
            wb.ctrl.step_calibrate("ml")
            wb.ctrl.step_diagnose()
            browser, page = _page(p, wb)
            page.get_by_role("tab", name="View").click()
            wb.panels.surface_choice.value = "residual pattern"
            time.sleep(3)
            page.screenshot(path=str(OUT / "see-residual-map.png"))
            wb.panels.surface_choice.value = "candidate's pattern"
            time.sleep(3)
            page.screenshot(path=str(OUT / "see-candidate.png"))
            page.get_by_role("tab", name="Model").click()
            page.get_by_role("button", name="Add the candidate and refit").click()
            _wait_text(page, "document.body.innerText.includes('Model: nonlinearity')")
            wb.worker.wait(120)
            page.get_by_role("button", name="Full-size evidence").click()
            time.sleep(3)
            page.screenshot(path=str(OUT / "see-evidence.png"))
            browser.close()
        finally:
            wb.stop()
    print(f"wrote {', '.join(sorted(p.name for p in OUT.glob('see-*.png')))} in {OUT}")
    return 0


def vehicle() -> int:
    """The vector model's screenshots (see the module docstring)."""
    from playwright.sync_api import sync_playwright

    from magcal_workbench.app import Workbench
    from magcal_workbench.dataio import load_dataset
    from magcal_workbench.lessons import get_lesson

    warnings.simplefilter("ignore")
    ds, _ = load_dataset(get_lesson("cannot-tumble").data_path)
    wb = Workbench(ds, host="127.0.0.1", port=0, store=None)
    try:
        assert wb.ctrl.vector.from_site()  # the place and date of the file's `# site:` line are the reference
        wb.ctrl.step_calibrate("ml")
        wb.ctrl.step_vector()
        with sync_playwright() as p:
            browser, page = _page(p, wb)
            page.get_by_text("Vector model (attitude-aided)").first.scroll_into_view_if_needed()
            time.sleep(1)
            page.screenshot(path=str(OUT / "vector-table.png"))
            page.get_by_role("tab", name="View").click()
            wb.panels.window_width.value = 2.0
            wb.panels.window_start.value = 55.0
            wb.panels.vector_panel.vehicle_on.value = True
            page.locator("label", has_text="Show the vehicle view").scroll_into_view_if_needed()
            time.sleep(4)
            page.screenshot(path=str(OUT / "vehicle-view.png"))
            browser.close()
    finally:
        wb.stop()
    print(f"wrote vector-table.png and vehicle-view.png in {OUT}")
    return 0


def loop() -> int:
    """The loop on a vehicle's screenshots (see the module docstring)."""
    from playwright.sync_api import sync_playwright

    from magcal_workbench.app import Workbench
    from magcal_workbench.dataio import load_dataset
    from magcal_workbench.lessons import get_lesson

    warnings.simplefilter("ignore")
    ds, _ = load_dataset(get_lesson("drone-current").data_path)
    wb = Workbench(ds, host="127.0.0.1", port=0, store=None)
    try:
        with sync_playwright() as p:
            browser, page = _page(p, wb)
            page.get_by_role("tab", name="Model").click()
            page.get_by_role("button", name="Diagnose").click()
            _wait_text(page, "document.body.innerText.includes('on the vector fit')")
            time.sleep(2)
            page.get_by_text("Verdict:").scroll_into_view_if_needed()
            time.sleep(1)
            page.screenshot(path=str(OUT / "vector-loop-diagnose.png"))
            page.get_by_role("button", name="Full-size evidence").click()
            page.wait_for_selector("img[alt='evidence plots']", timeout=120_000)
            time.sleep(2)
            page.screenshot(path=str(OUT / "vector-loop-evidence.png"))
            page.get_by_role("button", name="Add the candidate and refit").click()
            _wait_text(page, "document.body.innerText.includes('Vector model: current_field')")
            page.get_by_text("World RMS per step").scroll_into_view_if_needed()
            time.sleep(3)
            page.screenshot(path=str(OUT / "vector-loop-after.png"))
            browser.close()
    finally:
        wb.stop()
    print(f"wrote {', '.join(sorted(p.name for p in OUT.glob('vector-loop-*.png')))} in {OUT}")
    return 0


def _scroll_panel(page, dy: float) -> None:
    """Scroll the control panel (the mouse over it) by ``dy`` pixels."""
    page.mouse.move(1400, 600)
    page.mouse.wheel(0, dy)
    time.sleep(1.5)


def _look_from_above(wb, elevation_deg: float = 25.0) -> None:
    """Raise every browser's camera by ``elevation_deg`` about its look-at point (a ring seen edge-on is a line)."""
    import numpy as np

    for client in wb.server.get_clients().values():
        look = np.asarray(client.camera.look_at, float)
        d = np.asarray(client.camera.position, float) - look
        e = np.radians(elevation_deg)
        horizontal = np.hypot(d[0], d[1])
        d = np.array([d[0], d[1] * np.cos(e) - 0.0, horizontal * np.sin(e) + d[2] * np.cos(e)])
        with client.atomic():
            client.camera.position = tuple(look + d)
            client.camera.look_at = tuple(look)


def _single_sensor_demo():
    """The demo's sensor 1 alone, its second minute turned twice as fast (times halved there), for the
    single-sensor view."""
    import numpy as np

    from magcal.data import io as mio
    from magcal_workbench.lessons import DEMO

    ds = mio.read_csv(DEMO)
    t = np.asarray(ds.time_s, float).copy()
    fast = (t > 60) & (t <= 90)
    dt = np.diff(t, prepend=t[0])
    dt[fast] *= 0.25  # the same attitudes in a quarter of the time: turning four times as fast
    return ds.replace(readings_nT=ds.readings_nT[:1], time_s=np.cumsum(dt), baseline_m=None, source="single.csv")


def cockpit() -> int:
    """The cockpit's screenshots (see the module docstring)."""
    import tempfile

    from playwright.sync_api import sync_playwright

    from magcal.data import io as mio
    from magcal_workbench.app import Workbench
    from magcal_workbench.lessons import DEMO

    warnings.simplefilter("ignore")
    OUT.mkdir(parents=True, exist_ok=True)
    with sync_playwright() as p:
        wb = Workbench(mio.read_csv(DEMO), host="127.0.0.1", port=0, store=None)
        try:
            wb.ctrl.step_calibrate("ml")
            browser, page = _page(p, wb)
            time.sleep(2)
            page.screenshot(path=str(OUT / "cockpit-calibrate.png"))
            wb.panels.range_from.value, wb.panels.range_to.value = 30.0, 38.0
            wb.cockpit.do_exclude_range(None)
            wb.worker.wait(120)
            wb.ui.wait()
            wb.panels.range_from.value, wb.panels.range_to.value = 70.0, 76.0
            _scroll_panel(page, 520)
            page.screenshot(path=str(OUT / "cockpit-field.png"))
            _scroll_panel(page, 520)
            page.screenshot(path=str(OUT / "cockpit-histogram.png"))
            browser.close()
        finally:
            wb.stop()
        wb = Workbench(_single_sensor_demo(), host="127.0.0.1", port=0, store=None)
        try:
            wb.ctrl.step_calibrate("ml")
            wb.panels.window_width.value = 8.0
            wb.panels.window_start.value = 44.0
            wb.panels.window_on.value = True
            browser, page = _page(p, wb)
            _look_from_above(wb)
            time.sleep(2)
            page.screenshot(path=str(OUT / "cockpit-single.png"))
            browser.close()
        finally:
            wb.stop()
        wb = Workbench(mio.read_csv(DEMO), host="127.0.0.1", port=0, store=None)
        try:
            browser, page = _page(p, wb)
            rec = Path(tempfile.mkdtemp()) / "live.csv"
            wb.livectl.start("sim://chi2017?rate=50&n=6000&speed=4", rec)
            while wb.live.n_samples < 1500 or wb.live.fit is None:
                time.sleep(0.2)
            # software WebGL lags behind the redraws (five a second): pause the stream so the page settles
            wb.live.pause()
            wb.ui.run(lambda: wb.cockpit.draw(force=True))
            time.sleep(4)
            page.screenshot(path=str(OUT / "cockpit-live.png"))
            _scroll_panel(page, 900)
            page.screenshot(path=str(OUT / "cockpit-live-plots.png"))
            browser.close()
        finally:
            if wb.live is not None and wb.live.active:
                wb.live.stop()
            wb.stop()
    print(f"wrote {', '.join(sorted(p.name for p in OUT.glob('cockpit-*.png')))} in {OUT}")
    return 0


def newcomer() -> int:
    """The first screens a newcomer meets (see the module docstring)."""
    from playwright.sync_api import sync_playwright

    from magcal.data import io as mio
    from magcal_workbench.app import Workbench
    from magcal_workbench.dataio import load_dataset
    from magcal_workbench.lessons import DEMO, get_lesson

    warnings.simplefilter("ignore")
    OUT.mkdir(parents=True, exist_ok=True)
    with sync_playwright() as p:
        wb = Workbench(mio.read_csv(DEMO), host="127.0.0.1", port=0, store=None, name="demo.csv")
        try:
            browser, page = _page(p, wb)
            time.sleep(2)
            page.screenshot(path=str(OUT / "guide-first.png"))
            browser.close()
        finally:
            wb.stop()
        lesson = get_lesson("drone-current")
        ds, _ = load_dataset(lesson.data_path)
        wb = Workbench(ds, host="127.0.0.1", port=0, store=None, lesson="drone-current")
        try:
            wb.lessons.show_guide(lesson)
            browser, page = _page(p, wb)
            time.sleep(2)
            page.screenshot(path=str(OUT / "guide-lesson.png"))
            page.get_by_role("button", name="Step 1: fit with the attitude and the field vector").click()
            _wait_text(page, "document.body.innerText.includes('Step 2')")
            wb.worker.wait(120)
            page.get_by_role("tab", name="View").click()
            wb.panels.window_width.value = 2.0
            wb.panels.window_start.value = 40.0
            wb.panels.vector_panel.vehicle_on.value = True
            time.sleep(4)
            page.locator("label", has_text="Show the vehicle view").scroll_into_view_if_needed()
            time.sleep(1)
            page.screenshot(path=str(OUT / "guide-vehicle.png"))
            wb.panels.vector_panel.vehicle_on.value = False
            wb.panels.window_on.value = False
            wb.view.reset_cameras()
            time.sleep(4)
            page.get_by_role("tab", name="Quality").click()
            time.sleep(1)
            page.screenshot(path=str(OUT / "guide-vector-scene.png"))
            browser.close()
        finally:
            wb.stop()
        ds, _ = load_dataset(get_lesson("tilted-compass").data_path)
        wb = Workbench(ds, host="127.0.0.1", port=0, store=None, lesson="tilted-compass")
        try:
            browser, page = _page(p, wb)
            page.get_by_role("button", name="Step 1: fit with the accelerometer (the gravity fit)").click()
            _wait_text(page, "document.body.innerText.includes('The gravity fit ran')")
            wb.worker.wait(120)
            time.sleep(4)
            page.screenshot(path=str(OUT / "guide-gravity.png"))
            browser.close()
        finally:
            wb.stop()
    print(f"wrote {', '.join(sorted(p.name for p in OUT.glob('guide-*.png')))} in {OUT}")
    return 0


def compensation() -> int:
    """The compensation's first screen and its view after the loop (see the module docstring)."""
    from playwright.sync_api import sync_playwright

    from magcal_workbench.app import Workbench
    from magcal_workbench.dataio import load_dataset
    from magcal_workbench.guide import next_step
    from magcal_workbench.lessons import get_lesson

    warnings.simplefilter("ignore")
    OUT.mkdir(parents=True, exist_ok=True)
    slug = "survey-drone-current"
    lesson = get_lesson(slug)
    ds, _ = load_dataset(lesson.data_path)
    with sync_playwright() as p:
        wb = Workbench(ds, host="127.0.0.1", port=0, store=None, lesson=slug)
        try:
            wb.lessons.show_guide(lesson)
            browser, page = _page(p, wb)
            time.sleep(2)
            page.screenshot(path=str(OUT / "compensation-first.png"))
            while next_step(wb.ctrl).key != "none":
                page.get_by_role("button", name=next_step(wb.ctrl).label).click()
                time.sleep(0.5)
                wb.worker.wait(300)
                wb.ui.wait()
                time.sleep(2)
            page.get_by_role("tab", name="Calibrate").click()
            time.sleep(1)
            page.get_by_text(
                "Compensation (a scalar magnetometer beside a fluxgate)"
            ).first.scroll_into_view_if_needed()
            _scroll_panel(page, 250)
            time.sleep(3)
            page.screenshot(path=str(OUT / "compensation-view.png"))
            browser.close()
        finally:
            wb.stop()
    print(f"wrote compensation-first.png, compensation-view.png in {OUT}")
    return 0


def main() -> int:
    if sys.argv[1:] == ["compensation"]:
        return compensation()
    if sys.argv[1:] == ["newcomer"]:
        return newcomer()
    if sys.argv[1:] == ["vehicle"]:
        return vehicle()
    if sys.argv[1:] == ["cockpit"]:
        return cockpit()
    if sys.argv[1:] == ["loop"]:
        return loop()
    if sys.argv[1:] == ["live"]:
        return live()
    if sys.argv[1:] == ["see"]:
        return see()
    from playwright.sync_api import sync_playwright

    from magcal.data import io as mio
    from magcal_workbench.app import Workbench
    from magcal_workbench.lessons import DEMO

    warnings.simplefilter("ignore")
    OUT.mkdir(parents=True, exist_ok=True)
    wb = Workbench(mio.read_csv(DEMO), host="127.0.0.1", port=0, store=None)
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=ARGS, headless=True)
            page = browser.new_page(viewport={"width": 1600, "height": 1000})
            page.goto(wb.url)
            _wait_text(
                page,
                "document.body.innerText.includes('Total-field RMS') && "
                "!document.body.innerText.includes('Connecting')",
            )
            page.get_by_role("button", name="Run the chosen method").click()
            _wait_text(page, "/Total-field RMS: [0-9.]+ nT/.test(document.body.innerText)")
            wb.worker.wait(120)
            time.sleep(3)
            for close in page.locator(".mantine-Notification-closeButton").all():
                close.click()
            time.sleep(1)
            page.screenshot(path=str(OUT / "workbench-scene.png"))

            page.get_by_role("tab", name="Model").click()
            page.get_by_role("button", name="Diagnose").click()
            _wait_text(page, "document.body.innerText.includes('Verdict:')")
            wb.worker.wait(300)
            time.sleep(4)
            page.get_by_text("Verdict:").scroll_into_view_if_needed()
            time.sleep(1)
            page.screenshot(path=str(OUT / "workbench-loop-before.png"))

            page.get_by_role("button", name="Add the candidate and refit").click()
            _wait_text(page, "document.body.innerText.includes('Model: temperature_bias')")
            wb.worker.wait(300)
            time.sleep(4)
            page.get_by_role("button", name="Diagnose").click()  # diagnose again: the verdict now reads adequate
            _wait_text(page, "document.body.innerText.includes('Verdict:')")
            wb.worker.wait(300)
            time.sleep(4)
            page.get_by_text("Candidate", exact=True).scroll_into_view_if_needed()
            time.sleep(1)
            page.screenshot(path=str(OUT / "workbench-loop-after.png"))
            browser.close()
    finally:
        wb.stop()
    print(f"wrote {', '.join(sorted(p.name for p in OUT.glob('workbench-*.png')))} in {OUT}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
