"""Residual maps on the sphere in the workbench: the residual pattern, a candidate's, the last change.

The bent-response lesson hides a quadratic nonlinearity in sensor 3: its residual surface is the strongest, the
surface of the true candidate matches it, and after Add-and-refit the change surface holds what was taken away.
"""

from __future__ import annotations

import numpy as np
import pytest

from magcal.diagnosis import pattern_correlation
from tests.workbench.test_workbench_e2e import _open


@pytest.fixture
def bent(bench):
    from magcal_workbench.dataio import load_dataset
    from magcal_workbench.lessons import get_lesson

    lesson = get_lesson("bent-response")
    ds, _ = load_dataset(lesson.data_path)
    return bench(ds=ds)


def test_residual_candidate_and_change_surfaces(bent):
    wb = bent
    p = wb.panels
    p.surface_choice.value = "residual pattern"
    assert wb.maps.patterns == [] and "fit first" in p.maps_info.content
    wb.ctrl.step_calibrate("ml")
    assert len(wb.maps.patterns) == 4  # redrawn when the fit arrived
    nodes = wb.maps._nodes
    assert all(f"/maps/s{s}/surface" in nodes for s in range(1, 5))
    amps = [m.amplitude_nT for m in wb.maps.patterns]
    assert int(np.argmax(amps)) == 2  # sensor 3 holds the hidden nonlinearity
    residual = wb.maps.patterns[2]

    wb.ctrl.step_diagnose()
    p.surface_choice.value = "candidate's pattern"
    label = p.candidate_choice.value
    assert label.startswith("nonlinearity") and label.endswith(":3")
    explained = wb.maps.patterns[2]
    assert pattern_correlation(residual, explained) > 0.8
    assert "what adding" in p.maps_info.content

    wb.ctrl.step_add(label)
    p.surface_choice.value = "change at the last step"
    change = wb.maps.patterns[2]
    assert pattern_correlation(residual, change) > 0.8  # the last step took away the pattern that was there
    p.surface_choice.value = "residual pattern"
    assert wb.maps.patterns[2].amplitude_nT < 0.5 * residual.amplitude_nT
    p.surface_choice.value = "none"
    assert not wb.maps._nodes


def test_the_surface_choice_is_checked_on_the_server(bench):
    wb = bench()
    wb.panels.surface_choice.value = "<img src=x onerror=alert(1)>"
    assert wb.panels.surface_choice.value == "none" and "not one of the choices" in wb.ctrl.message


@pytest.mark.e2e
@pytest.mark.slow
def test_a_candidates_pattern_appears_on_the_sphere_in_the_page(browser, bent):
    wb = bent
    wb.ctrl.step_calibrate("ml")
    wb.ctrl.step_diagnose()
    page = _open(browser, wb)
    page.get_by_role("tab", name="View").click(timeout=30_000)
    wb.panels.surface_choice.value = "candidate's pattern"  # a dropdown: set as the page would (checked the same)
    page.wait_for_function("() => document.body.innerText.includes('what adding')", timeout=30_000)
    assert all(f"/maps/s{s}/surface" in wb.maps._nodes for s in range(1, 5))
    page.get_by_role("tab", name="Model").click()
    page.get_by_role("button", name="Add the candidate and refit").click()
    page.wait_for_function("() => document.body.innerText.includes('Model: nonlinearity')", timeout=120_000)
    assert wb.worker.wait(120)
    wb.panels.surface_choice.value = "change at the last step"
    assert len(wb.maps.patterns) == 4 and wb.maps.patterns[2].amplitude_nT > 0


def test_the_evidence_plot_shows_the_rms_before_the_last_fit(bent):
    wb = bent
    wb.ctrl.step_calibrate("ml")
    before = wb.ctrl.rms_per_sensor_nT()
    wb.ctrl.step_diagnose()
    wb.ctrl.step_add(wb.panels.candidate_choice.value)
    traces = [t for t in wb.evidence.plot.figure.data if t.name == "before the last fit"]
    assert len(traces) == 1
    np.testing.assert_allclose(traces[0].y, before, rtol=1e-6)
    assert wb.ctrl.rms_per_sensor_nT()[2] < 0.9 * before[2]
