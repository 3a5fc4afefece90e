"""The gravity model in the workbench: the gravity fit beside the total-field fit on the opened data, its
table, the dip over time and against the tilt, the compass rose, the accelerometer's cloud, and the lesson "the
compass that points wrong when tilted" judged on the gravity fit; one Chromium test drives the page."""

from __future__ import annotations

import time

import numpy as np
import pytest

from magcal.data.board import SWAPPED_MOUNTING, simulate_board
from magcal_workbench.controller import Controller
from magcal_workbench.dataio import load_dataset
from magcal_workbench.gravitymodel import GravityModel, accel_cloud, dip_series, rose, table_markdown
from magcal_workbench.gravitypage import dip_figure, rose_figure
from magcal_workbench.lessons import get_lesson


def _board(n_poses=20, seed=21, **kw):
    ds, truth, record = simulate_board(seed=seed, n_poses=n_poses, mounting=SWAPPED_MOUNTING, rate_hz=25.0, **kw)
    return ds, truth, record


def test_the_gravity_model_finds_the_mounting_and_what_the_total_field_fit_leaves():
    ds, truth, record = _board()
    gm = GravityModel(Controller(ds))
    assert gm.available and gm.result is None
    assert "run the gravity fit" in table_markdown(gm)
    gm.fit()
    s = gm.result.sensors[0]
    assert s.right_angle_text.startswith("ROLL_180_YAW_90") and s.angle_off_deg == pytest.approx(2.0, abs=0.1)
    text = table_markdown(gm)
    assert "ROLL\\_180\\_YAW\\_90" in text and "heading difference" in text
    series = dip_series(gm)
    still = np.flatnonzero(gm.still)
    assert series["dip_deg"].shape == still.shape
    # the gravity fit's dip is the inclination at every still sample; the total-field fit's scatters with attitude
    assert np.std(series["dip_deg"]) < 0.5 * np.std(series["dip_separate_deg"])
    assert np.mean(series["dip_deg"]) == pytest.approx(truth.inclination_deg, abs=0.1)
    r = rose(gm)
    assert r["centre_deg"].shape == (12,) and r["n"].sum() == int(gm.level().sum())
    assert 1.0 < float(np.sqrt(np.sum(r["n"] * r["rms_deg"] ** 2) / r["n"].sum())) < 6.0  # the 2 deg, x ~tan(I)
    cloud = accel_cloud(gm)
    assert np.allclose(np.linalg.norm(cloud["directions"], axis=1), 1.0)
    assert cloud["still"].any() and not cloud["still"].all()
    # the figures build from the data (and from nothing before a fit)
    assert len(dip_figure(series).data) == 4 and len(rose_figure(r).data) == 1
    assert len(dip_figure(None).data) == 0 and len(rose_figure(None).data) == 0


def test_data_without_an_accelerometer_say_so():
    ds, _, _ = _board(n_poses=6)
    gm = GravityModel(Controller(ds.replace(extra={})))
    assert not gm.available and "no accelerometer columns" in table_markdown(gm)
    with pytest.raises(Exception, match="needs the accelerometer"):
        gm.fit()


def test_the_compass_lesson_is_solved_by_the_gravity_fit():
    lesson = get_lesson("tilted-compass")
    assert lesson.judged_on == "gravity"
    ds, _ = load_dataset(lesson.data_path)
    gm = GravityModel(Controller(ds))
    first = lesson.check([], gm.lesson_findings())
    assert not first["solved"] and "gravity fit" in first["message"]
    gm.fit()
    assert lesson.check([], gm.lesson_findings())["solved"]
    wrong = lesson.check([], {"mounting": ["NONE"], "angle_off_deg": [2.0]})
    assert not wrong["solved"] and "gravity fit ran" in wrong["message"]
    assert "the gravity fit's mounting `ROLL_180_YAW_90`" in lesson.answer_markdown()


def _wait(cond, timeout=60):
    end = time.monotonic() + timeout
    while not cond() and time.monotonic() < end:
        time.sleep(0.05)
    return cond()


def test_the_page_runs_the_gravity_fit_and_draws_the_accelerometer(bench):
    ds, _, _ = _board(n_poses=12)
    wb = bench(ds=ds)
    page = wb.gravity
    assert page.btn_fit.visible and page.cloud_box.visible
    page.do_gravity_fit(None)
    assert _wait(lambda: page.model.result is not None and "ROLL\\_180\\_YAW\\_90" in page.table.content)
    assert _wait(lambda: page.dip_plot.visible and page.rose_plot.visible)
    page.cloud_box.value = True  # its callback draws the cloud
    assert _wait(lambda: "/gravity/accel_still" in page.nodes)
    assert "still (blue)" in page.cloud_info.content
    page.cloud_box.value = False
    assert _wait(lambda: page.nodes == {})


def test_the_page_hides_the_gravity_section_without_an_accelerometer(bench):
    ds, _, _ = _board(n_poses=6)
    wb = bench(ds=ds.replace(extra={}))
    assert not wb.gravity.btn_fit.visible and "no accelerometer columns" in wb.gravity.info.content


@pytest.mark.e2e
@pytest.mark.slow
def test_the_compass_lesson_in_the_page(browser, bench, tmp_path):
    """In Chromium: open the compass lesson's data, run the gravity fit from the page, read the mounting and the
    heading the total-field fit leaves, and show the accelerometer's cloud."""
    from tests.workbench.test_workbench_e2e import _dismiss_toasts, _open

    ds, _ = load_dataset(get_lesson("tilted-compass").data_path)
    wb = bench(ds=ds, max_points=300)  # software WebGL: a small scene keeps the page responsive
    page = _open(browser, wb)
    page.get_by_role("button", name="Run the gravity fit (beside the accelerometer)").click()
    page.wait_for_function(
        "() => document.body.innerText.includes('heading difference from the gravity fit')", timeout=120_000
    )
    text = page.inner_text("body", timeout=120_000)
    assert "ROLL_180_YAW_90" in text and "dip spread, still samples" in text
    assert "What a heading of 0.5 deg needs" in text
    shot = tmp_path / "gravity_table.png"
    _dismiss_toasts(page)
    page.get_by_text("heading difference from the gravity fit").scroll_into_view_if_needed()
    page.screenshot(path=str(shot), timeout=120_000)
    page.get_by_role("tab", name="View").click()
    page.get_by_text("Accelerometer", exact=True).click()  # its section opens
    page.get_by_text("Show the accelerometer's cloud and sphere", exact=True).click()
    page.wait_for_function("() => document.body.innerText.includes('still (blue)')", timeout=60_000)
    assert "/gravity/accel_still" in wb.gravity.nodes
    _dismiss_toasts(page)
    shot2 = tmp_path / "gravity_cloud.png"
    page.screenshot(path=str(shot2), timeout=120_000)
    page.get_by_role("tab", name="Calibrate").click()
    page.get_by_text("What a heading of 0.5 deg needs").scroll_into_view_if_needed()
    page.mouse.move(1150, 500)
    page.mouse.wheel(0, 500)  # the panel scrolls on to the plots
    time.sleep(1.0)
    shot3 = tmp_path / "gravity_plots.png"
    page.screenshot(path=str(shot3), timeout=120_000)
    assert shot.stat().st_size > 10_000 and shot2.stat().st_size > 10_000 and shot3.stat().st_size > 10_000
    page.close()


def test_the_page_judges_the_compass_lesson_on_the_gravity_fit(bench):
    """The Lessons tab opens the lesson's data, and Check reads the gravity page's fit (the lessons
    desk is handed the gravity page, not the workbench)."""
    wb = bench(store=False)
    assert not wb.gravity.btn_fit.visible  # the opening data have no accelerometer
    wb.panels.lesson_choice.value = get_lesson("tilted-compass").title
    wb.lessons.do_open_lesson(None)
    assert wb.worker.wait(60) and wb.ctrl.state.lesson == "tilted-compass"
    wb.ui.wait()
    assert wb.gravity.btn_fit.visible  # the page follows the lesson's data (it kept the old data's state before)
    wb.lessons.do_check_lesson(None)
    assert "has not been run" in wb.panels.lesson_feedback.content
    wb.gravity.do_gravity_fit(None)
    assert wb.worker.wait(120) and _wait(lambda: wb.gravity.model.result is not None)
    wb.lessons.do_check_lesson(None)
    assert wb.panels.lesson_feedback.content.startswith("Solved: the gravity fit found the mounting")
    assert wb.ctrl.message.startswith("Solved")
