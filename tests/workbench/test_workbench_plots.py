"""magcal_workbench.plots: the history plots of one step draw their floor across the frame, and every plotly figure
the page draws is configured without plotly's mode bar (it covered the figures' titles on hover)."""

import json
import re
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from magcal_workbench.plots import PLOTLY_CONFIG, log_axis_scales, one_step_history
from magcal_workbench.state import VectorStep
from magcal_workbench.vectorpanel import vector_rms_plot_data

WORKBENCH = Path(__file__).resolve().parents[2] / "magcal_workbench"


def _click(wb, button):
    button.value = True  # what a click does: the callbacks run
    time.sleep(0.05)
    assert wb.worker.wait(120)
    wb.ui.wait()


def _frame(data) -> list:
    return log_axis_scales(data)["x"]["range"]


def test_the_first_step_draws_the_noise_floor_across_the_plot(bench):
    wb = bench(store=False)
    history = wb.ctrl.state.history
    assert len(history) == 1  # the raw readings only
    floor_nT = wb.ctrl.floor_nT()
    assert floor_nT is not None  # the file gives the noise: the floor is known before a fit
    x, y, floor, held = wb.panels.rms_plot.data
    assert (x[0], x[-1]) == tuple(wb.panels.rms_plot.scales["x"]["range"])  # the floor reaches both edges
    assert np.allclose(floor, floor_nT) and len(floor) >= 2  # a line, not a point
    step = x == 0.0
    assert step.sum() == 1 and y[step][0] == pytest.approx(history[0].rms_nT) and held[step][0] == y[step][0]
    assert np.all(np.isinf(y[~step])) and np.all(np.isinf(held[~step]))  # nothing drawn off the step
    _click(wb, wb.panels.btn_run)
    x, y, floor, held = wb.panels.rms_plot.data
    assert list(x) == [0.0, 1.0] and np.all(np.isfinite(y)) and np.allclose(floor, wb.ctrl.floor_nT())
    assert wb.panels.rms_plot.scales["x"]["range"] == [-0.5, 1.5]


def test_the_vector_models_first_fit_draws_its_world_floor_once_known():
    steps = [VectorStep("vector fit", [40.0, 38.0, 12.0], 3.1)]
    vm = SimpleNamespace(ctrl=SimpleNamespace(state=SimpleNamespace(vector_history=steps)), floor_nT=None)
    x, n, e, d, total, floor = vector_rms_plot_data(vm)
    assert np.all(np.isnan(floor))  # before a diagnosis it is not known: nothing to draw
    vm.floor_nT = 36.5
    x, n, e, d, total, floor = vector_rms_plot_data(vm)
    assert (x[0], x[-1]) == tuple(_frame((x, n, e, d, total, floor))) and np.allclose(floor, 36.5)
    assert n[x == 0.0][0] == 40.0 and total[x == 0.0][0] == 3.1 and np.isinf(n[x != 0.0]).all()
    steps.append(VectorStep("vector: add current_field", [36.0, 36.0, 11.0], 3.0))
    x, *_, floor = vector_rms_plot_data(vm)
    assert list(x) == [0.0, 1.0] and np.allclose(floor, 36.5)


def test_one_step_history_leaves_longer_histories_alone():
    x, y = np.arange(3.0), np.array([5.0, 4.0, 3.0])
    out = one_step_history(x, (y, np.full(3, 2.0)), floors=(1,))
    assert out[0] is x and out[1] is y


def test_every_plotly_figure_is_added_without_the_mode_bar():
    """One place adds plotly figures to the page (``plots.add_figure``, with ``PLOTLY_CONFIG``)."""
    assert PLOTLY_CONFIG["displayModeBar"] is False
    calls = {
        path.name: len(re.findall(r"\.add_plotly\(", path.read_text(encoding="utf-8")))
        for path in WORKBENCH.glob("*.py")
    }
    assert {name: n for name, n in calls.items() if n} == {"plots.py": 1}


def test_the_figures_the_page_draws_carry_the_setting(bench, monkeypatch):
    """Every plotly handle the page makes, at start and as it draws (|B| against time, the histogram, the evidence
    after Diagnose, the gravity and compensation panels' figures), sends the browser a figure whose configuration
    hides the mode bar; a figure drawn again keeps it."""
    from viser._gui_api import GuiApi

    made = []
    real = GuiApi.add_plotly

    def spy(self, figure, **kw):
        handle = real(self, figure, **kw)
        made.append(handle)
        return handle

    monkeypatch.setattr(GuiApi, "add_plotly", spy)
    wb = bench(store=False)
    _click(wb, wb.panels.btn_run)
    _click(wb, wb.panels.btn_diagnose)
    assert wb.evidence.plot is not None and wb.evidence.plot in made
    assert len(made) >= 6  # Calibrate tab's two, the evidence, the gravity page's two, the compensation's traces
    for handle in made:
        sent = json.loads(handle._plotly_json_str)
        assert sent["config"]["displayModeBar"] is False, sent.get("layout", {}).get("title")
    drawn = [h for h in made if json.loads(h._plotly_json_str)["data"]]
    assert len(drawn) >= 3  # the figures drawn after the fit, not only the empty ones built at start
