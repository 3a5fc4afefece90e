"""The first screen's guide: it says what the data are and which fits they allow, and its one button walks the
loop (fit, diagnose, add the advice) to the floor, on the total-field model and on the vector model alike."""

import time

import numpy as np
import pytest

from magcal_workbench.dataio import load_dataset
from magcal_workbench.guide import next_step
from magcal_workbench.lessons import get_lesson


def _click(wb, button):
    button.value = True  # what a click does: the callbacks run
    time.sleep(0.05)
    assert wb.worker.wait(180)


def _lesson(slug):
    ds, notes = load_dataset(get_lesson(slug).data_path)
    return ds


@pytest.mark.parametrize(
    ("slug", "first", "words"),
    [
        ("warm-sensor", "run", ["4 sensors", "temperature", "the total-field fit"]),
        ("drone-current", "vector", ["attitude", "the vector fit (attitude and the field vector"]),
        ("tilted-compass", "gravity", ["an accelerometer", "the gravity fit"]),
    ],
)
def test_the_guide_says_what_the_data_are_and_the_first_step(bench, slug, first, words):
    wb = bench(ds=_lesson(slug))
    text = wb.panels.guide.content
    for word in words:
        assert word in text, (word, text)
    assert next_step(wb.ctrl).key == first and wb.panels.btn_next.visible
    listed = text.split("**Fits it allows:** ")[1]  # the first fit listed is the one Step 1 runs
    assert listed.startswith({"run": "the total-field", "vector": "the vector", "gravity": "the gravity"}[first])
    assert wb.panels.btn_next.label.startswith("Step 1: fit")


@pytest.mark.parametrize(
    ("slug", "effect"), [("warm-sensor", "temperature_bias:2"), ("drone-current", "current_field")]
)
def test_the_guides_button_walks_the_loop_to_the_floor(bench, slug, effect):
    """Each click runs the step the guide names; the hidden effect is added from the advice, and the loop ends with
    nothing left to press and the lesson solved."""
    wb = bench(ds=_lesson(slug))
    wb.ctrl.state.lesson = slug
    keys = []
    for _ in range(6):
        step = next_step(wb.ctrl)
        if step.key == "none":
            break
        keys.append(step.key)
        assert wb.panels.btn_next.label == step.label
        _click(wb, wb.panels.btn_next)
    model = wb.ctrl.vector.effects if wb.ctrl.vector_loop() else wb.ctrl.state.effects
    assert effect in model
    assert keys[:3] == [keys[0], "diagnose", "add"] and keys[-1] == "diagnose"
    assert not wb.panels.btn_next.visible and "adequate" in wb.panels.guide.content


@pytest.mark.e2e
@pytest.mark.slow
def test_a_newcomer_follows_the_guide_on_the_demo_in_chromium(browser, bench, tmp_path):
    """In Chromium, on the bundled demo: the first screen says what the data are and shows one button; pressing
    it, and each button it turns into, runs the loop (fit, diagnose, add the advice, diagnose) until the guide says
    the model is adequate. The screenshots are kept for a person to look at."""
    from magcal.data import io as mio
    from magcal_workbench.lessons import DEMO

    wb = bench(ds=mio.read_csv(DEMO))
    page = browser.new_page(viewport={"width": 1400, "height": 900})
    page.goto(wb.url, wait_until="domcontentloaded")
    page.wait_for_function("() => document.body && document.body.innerText.includes('Fits it allows')", timeout=90_000)
    text = page.inner_text("body")
    assert "4 sensors, 1500 samples" in text and "Next:" in text
    page.screenshot(path=str(tmp_path / "guide-first.png"))
    pressed = []
    for _ in range(6):
        step = next_step(wb.ctrl)
        if step.key == "none":
            break
        pressed.append(step.key)
        page.get_by_role("button", name=step.label).click()
        page.wait_for_function(
            "(label) => ![...document.querySelectorAll('button')].some(b => b.innerText.trim() === label)",
            arg=step.label,
            timeout=180_000,
        )
        assert wb.worker.wait(180)
    assert pressed[:3] == ["run", "diagnose", "add"] and pressed[-1] == "diagnose"
    page.wait_for_function("() => document.body.innerText.includes('the model is adequate')", timeout=60_000)
    assert wb.ctrl.state.effects  # the advice was added
    page.screenshot(path=str(tmp_path / "guide-solved.png"))


def test_add_asks_before_a_candidate_that_does_not_hold_and_the_history_marks_it(bench):
    """On a record with nothing hidden, a candidate the diagnosis does not find holding is added only at the
    second press, with a message in between, and its step in the history says so."""
    import magcal

    wb = bench(ds=magcal.simulate_timeseries("chi2017", n_samples=400, seed=3, rate_hz=2.0))
    wb.ctrl.step_refine()
    wb.ctrl.step_diagnose()
    p = wb.panels
    weak = [label for label in wb.ctrl.candidate_labels() if not wb.ctrl.candidate_holds(label)]
    assert weak, "the diagnosis of a record with nothing hidden should offer a candidate that does not hold"
    assert not p.btn_add_advice.visible and wb.ctrl.advice() == []
    p.candidate_choice.value = weak[0]
    _click(wb, p.btn_add)
    assert wb.ctrl.state.effects == [] and "does not hold" in wb.ctrl.message
    _click(wb, p.btn_add)
    assert wb.ctrl.state.effects == [weak[0]]
    assert "(does not hold)" in p.history.content


def test_add_the_advice_adds_all_of_it_in_one_refit(bench):
    wb = bench(ds=_lesson("warm-sensor"))
    wb.ctrl.step_refine()
    wb.ctrl.step_diagnose()
    advice = wb.ctrl.advice()
    assert advice and wb.panels.btn_add_advice.visible and all(a in wb.panels.btn_add_advice.label for a in advice)
    steps = len(wb.ctrl.state.history)
    _click(wb, wb.panels.btn_add_advice)
    assert wb.ctrl.state.effects == advice and len(wb.ctrl.state.history) == steps + 1
    assert wb.ctrl.advice() == [] and not wb.panels.btn_add_advice.visible


@pytest.mark.parametrize(
    ("series", "lo", "hi"),
    [([[700.0, 1300.0], [800.0, 900.0]], 700.0, 1300.0), ([[3.0, np.nan], [2.9, 2.9]], 2.9, 3.0)],
)
def test_a_history_plots_log_axis_spans_its_data_not_the_decades(series, lo, hi):
    from magcal_workbench.plots import LOG_AXIS_MARGIN, log_axis_scales

    data = (np.arange(2.0), *[np.array(s) for s in series])
    y = log_axis_scales(data)["y"]
    assert y["distr"] == 3 and y["range"] == pytest.approx([lo / LOG_AXIS_MARGIN, hi * LOG_AXIS_MARGIN])
    assert log_axis_scales(data)["x"]["range"] == [-0.5, 1.5]  # every step inside the frame
    assert "range" not in log_axis_scales((np.arange(2.0), np.array([np.nan, np.nan])))["y"]


def test_a_verdict_that_could_not_judge_advises_nothing_and_says_why():
    """The guide reads the diagnosis's verdict: ``not_judged`` offers no button to press and says why."""
    from types import SimpleNamespace

    from magcal_workbench.guide import next_step as step_of

    diagnosis = SimpleNamespace(verdict="not_judged", explained_by=[])
    vm = SimpleNamespace(result=object(), diagnosis=diagnosis, effects=[])
    ctrl = SimpleNamespace(vector_loop=lambda: True, vector=vm, loop_diagnosis=lambda: diagnosis, advice=lambda: [])
    step = step_of(ctrl)
    assert step.key == "none" and "not_judged" in step.why and "longer record" in step.why


@pytest.mark.parametrize("slug", ["drone-current", "tilted-compass"])
def test_a_lesson_opens_on_its_text_and_the_list_shows_titles(bench, slug):
    """The Lessons tab lists the lessons by title; opening one puts its title and text on the first screen, under
    the data and the next step's button, without the answer."""
    from magcal_workbench.lessons import list_lessons

    wb = bench(store=False)
    lesson = get_lesson(slug)
    titles = tuple(wb.panels.lesson_choice.options)
    assert titles == tuple(l.title for l in list_lessons()) and slug not in titles
    wb.panels.lesson_choice.value = lesson.title
    _click(wb, wb.panels.btn_lesson)
    wb.ui.wait()
    text = wb.panels.lesson_intro.content
    assert wb.ctrl.state.lesson == slug and f"lesson `{slug}`" in wb.panels.guide.content
    assert text.startswith(f"### Lesson: {lesson.title}") and lesson.guide().strip() in text
    assert all(e.partition(":")[0] not in text for e in lesson.answer()["effects"])
    wb.lessons.load(_lesson("warm-sensor"), None, "other.csv")  # other data: the lesson's text goes
    wb.ui.wait()
    assert wb.panels.lesson_intro.content == ""
