"""The workbench answers at once, driven through the page's handles on a real (browserless) viser
server: the fit's result is on the page before its held-out check, which shows ``pending...`` until it comes; a
newer fit makes an older fit's held-out check stale (dropped unseen); a refit sends the corrected clouds, not the
raw ones again; the |B| plot's envelope keeps every stretch's extremes; ``--timing`` logs named spans.

No timed assertion here: the times are in ``benchmarks/page_latency.py``.
"""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from magcal_workbench import timing
from magcal_workbench.pending import PENDING, Pending
from magcal_workbench.plots import envelope_indices


def _press(wb, button):
    """A click, without waiting for the slow parts: returns once the job (the fit itself) has ended and the page
    has shown what it handed on."""
    button.value = True
    deadline = time.monotonic() + 120
    time.sleep(0.05)
    while wb.worker.busy:
        assert time.monotonic() < deadline, "the job did not end"
        time.sleep(0.01)
    wb.ui.wait()


@pytest.fixture
def gated_validation(monkeypatch):
    """The held-out check waits until the test opens its gate (one gate per call, in call order)."""
    from magcal.fitting import validation

    real = validation.validate
    gates: list[threading.Event] = []
    calls: list[int] = []

    def gated(*args, **kwargs):
        gate = threading.Event()
        gates.append(gate)
        calls.append(len(gates))
        assert gate.wait(120), "the test never opened the gate"
        return real(*args, **kwargs)

    monkeypatch.setattr(validation, "validate", gated)

    def wait_for_calls(n):
        deadline = time.monotonic() + 60
        while len(gates) < n:
            assert time.monotonic() < deadline, "the held-out check never started"
            time.sleep(0.01)
        return gates

    return wait_for_calls


def test_the_result_is_shown_before_the_held_out_check_which_is_pending_until_it_comes(bench, gated_validation):
    wb = bench(store=False)
    _press(wb, wb.panels.btn_run)
    gates = gated_validation(1)  # the held-out check runs, and waits
    rec = wb.ctrl.state.history[-1]
    assert rec.step == "calibrate (ML)" and rec.held_out_rms_nT is None
    # the result is on the page: the status's RMS, the message line, the history row marked pending
    assert f"Total-field RMS: {rec.rms_nT:.4g} nT" in wb.panels.status.content
    assert wb.ctrl.message.startswith("**calibrate (ML)**: RMS") and f"held-out RMS {PENDING}" in wb.ctrl.message
    assert PENDING in wb.panels.history.content
    assert not wb.worker.busy and wb.worker.pending.busy()  # the next click may start: the buttons are enabled
    assert not wb.panels.btn_run.disabled
    gates[0].set()
    assert wb.worker.wait(120)  # waits for the slow parts too
    assert rec.held_out_rms_nT is not None and rec.held_out_rms_nT > 0
    assert PENDING not in wb.ctrl.message and f"held-out RMS {rec.held_out_rms_nT:.4g} nT" in wb.ctrl.message
    assert PENDING not in wb.panels.history.content
    assert f"| {rec.held_out_rms_nT:.4g} |" in wb.panels.history.content


def test_a_newer_fit_makes_the_older_held_out_check_stale(bench, gated_validation):
    wb = bench(store=False)
    _press(wb, wb.panels.btn_run)
    gates = gated_validation(1)
    first = wb.ctrl.state.history[-1]
    _press(wb, wb.panels.btn_refine)  # a new click while the first fit's check still runs
    second = wb.ctrl.state.history[-1]
    assert second is not first and second.step == "refine (ML)"
    gates = gated_validation(2)
    gates[0].set()  # the stale check ends first: nothing of it is published
    deadline = time.monotonic() + 60
    while wb.worker.pending.n_stale < 1:
        assert time.monotonic() < deadline
        time.sleep(0.01)
    wb.ui.wait()
    assert first.held_out_rms_nT is None
    assert wb.ctrl.message.startswith("**refine (ML)**") and PENDING in wb.ctrl.message
    gates[1].set()
    assert wb.worker.wait(120)
    assert first.held_out_rms_nT is None and second.held_out_rms_nT is not None
    assert wb.ctrl.message.startswith("**refine (ML)**") and PENDING not in wb.ctrl.message


def test_pending_parts_of_an_old_generation_do_not_run():
    p = Pending()
    ran: list[str] = []
    old = p.next_generation()
    p.next_generation()
    p.start(old, "old", lambda current: ran.append("old"))
    assert p.wait(10)
    assert ran == [] and p.n_stale == 1 and not p.busy()
    p.start(p.generation, "new", lambda current: ran.append("new") if current() else None)
    assert p.wait(10) and ran == ["new"] and p.n_stale == 1


def test_the_status_with_the_rms_is_on_the_page_before_the_tabs_are_built(bench, monkeypatch):
    """The launch shows the Total-field RMS first: the status line is sent with its text when it is
    made, before the tabs' widgets, the scene and the figures, which follow."""
    from magcal_workbench import panels as pn
    from magcal_workbench.calibratetab import CalibrateTab

    seen = []
    real = CalibrateTab.build

    def spy(self, panels, gui):
        seen.append(panels.status.content)  # what the page has been sent when the first tab is built
        return real(self, panels, gui)

    monkeypatch.setattr(CalibrateTab, "build", spy)
    wb = bench(store=False)
    assert len(seen) == 1
    assert seen[0] == pn.status_markdown(wb.ctrl)
    assert "Total-field RMS" in seen[0] and "Rejected: 0 of 300 samples" in seen[0]


def test_a_refit_sends_the_corrected_clouds_not_the_raw_ones_again(bench):
    wb = bench(store=False)
    wb.panels.btn_run.value = True
    assert wb.worker.wait(120)
    sv = wb.scene_view
    raw = {k: np.array(h.points) for k, h in sv._clouds.items() if "raw" in k}
    corrected = {k: len(h.points) for k, h in sv._clouds.items() if "raw" not in k}
    assert raw and corrected
    before = sv.n_points_sent
    wb.ctrl.select(np.arange(10), "reject", what="ten samples")  # the fit changes a little
    wb.panels.btn_refine.value = True
    assert wb.worker.wait(120)
    sent = sv.n_points_sent - before
    assert 0 < sent <= sum(corrected.values())  # the corrected clouds moved; the raw ones were not sent again
    for k, pts in raw.items():
        assert np.array_equal(sv._clouds[k].points, pts)


def test_a_refit_leaves_the_unchanged_labels_and_lines_and_redraws_the_changed_axes(bench):
    wb = bench(store=False)
    wb.panels.btn_run.value = True
    assert wb.worker.wait(120)
    sv = wb.scene_view
    drawn = dict(sv._static)
    assert {"/data/s1/raw_label", "/data/s1/corr_label", "/cross/label", "/cross/s1/axes"} <= set(drawn)
    wb.ctrl.select(np.arange(10), "reject", what="ten samples")  # the fit, so each sensor's axes, change a little
    wb.panels.btn_refine.value = True
    assert wb.worker.wait(120)
    for name in ("/data/s1/raw_label", "/data/s1/corr_label", "/cross/label", "/cross/arms"):
        assert sv._static[name] is drawn[name]  # the same node: nothing sent to the page
    assert sv._static["/cross/s1/axes"] is not drawn["/cross/s1/axes"]  # the calibrated axes moved: redrawn


def test_no_figure_is_rebuilt_when_its_data_did_not_change(bench):
    wb = bench(store=False)
    cockpit, p = wb.cockpit, wb.panels
    wb.ui.run(lambda: cockpit.draw(force=True))
    built, field, hist = cockpit.n_built, p.field_plot.figure, p.histogram_plot.figure
    wb.ui.run(lambda: cockpit.draw(force=True))  # nothing changed: nothing built, nothing sent
    assert cockpit.n_built == built and p.field_plot.figure is field and p.histogram_plot.figure is hist
    wb.ctrl.select(np.arange(10), "reject", what="ten samples")  # the kept mask changed: every figure follows
    wb.ui.run(lambda: cockpit.draw(force=True))
    assert cockpit.n_built == built + 3 and p.field_plot.figure is not field
    assert cockpit.n_draws >= 3
    built = cockpit.n_built
    p.histogram_unit.value = "%" if p.histogram_unit.value == "nT" else "nT"  # only the histogram's input
    wb.ui.run(lambda: cockpit.draw(force=True))
    assert cockpit.n_built == built + 1 and p.histogram_plot.figure is not hist


def test_the_envelope_keeps_every_extreme_and_its_size_bound():
    rng = np.random.default_rng(4)
    n = 200_000
    values = 50_000 + rng.normal(scale=2.0, size=(3, n))
    spikes = {(1, 12_345): 400.0, (2, 150_001): -300.0, (0, 199_998): 250.0}
    for (row, i), v in spikes.items():
        values[row, i] += v
    idx = envelope_indices(values, 1500)
    assert len(idx) <= 1500 and np.all(np.diff(idx) > 0) and idx[0] == 0 and idx[-1] == n - 1
    for _, i in spikes:
        assert i in idx  # each spike, up or down, in any row, is drawn
    # the plot spans the record's whole range: its highest and lowest values are drawn
    assert values[:, idx].max() == values.max() and values[:, idx].min() == values.min()
    # a stride would have missed the spikes
    stride = np.linspace(0, n - 1, 1500).astype(int)
    assert not all(i in stride for _, i in spikes)
    assert np.array_equal(envelope_indices(values[:, :1000], 1500), np.arange(1000))  # small: every sample


def test_timing_spans_are_logged_only_when_asked(capsys):
    timing.enable(False)
    with timing.span("fit"):
        pass
    assert "magcal-timing" not in capsys.readouterr().err
    timing.enable(True)
    try:
        with timing.span("fit"):
            time.sleep(0.01)
    finally:
        timing.enable(False)
    line = capsys.readouterr().err.strip()
    name, start, seconds = line.split()[1:]
    assert line.startswith("magcal-timing: fit ") and name == "fit" and float(seconds) >= 0.009


def _excluded_in_figures(wb) -> bool:
    """Whether the cockpit's last |B| figure was drawn from the record with its kept mask as it is now."""
    from magcal_workbench.cockpit import controller_record
    from magcal_workbench.plots import record_key

    return wb.cockpit._keys.get("field", "").startswith(record_key(controller_record(wb.ctrl)))


@pytest.mark.parametrize("refit_fails", [False, True])
def test_a_selection_a_refit_follows_draws_the_figures_once_with_the_refit(bench, monkeypatch, refit_fails):
    """Exclude range with Refit after each change on: the figures wait for the refit's result (one draw, not one
    for the selection and one for the result); a refit that fails still leaves them showing the exclusion."""
    wb = bench(store=False)
    _press(wb, wb.panels.btn_run)
    assert wb.worker.wait(120) and wb.panels.auto_refit.value
    if refit_fails:

        def broken(*args, **kwargs):
            raise RuntimeError("the refit broke")

        monkeypatch.setattr(wb.ctrl, "step_refine", broken)
    steps = len(wb.ctrl.state.history)
    wb.panels.range_from.value, wb.panels.range_to.value = 20.0, 30.0
    built = wb.cockpit.n_built  # after the sliders' own redraw (the shaded range)
    _press(wb, wb.panels.btn_exclude_range)
    assert wb.worker.wait(120)
    wb.ui.wait()
    assert wb.ctrl.state.selection.n_rejected > 0
    assert len(wb.ctrl.state.history) == steps + (0 if refit_fails else 1)
    # built once (the table, |B| against time, the histogram): with the refit's result, or when the failed job ended
    assert wb.cockpit.n_built == built + 3
    assert _excluded_in_figures(wb)


def test_a_selection_no_refit_follows_draws_the_figures_at_once(bench):
    wb = bench(store=False)
    _press(wb, wb.panels.btn_run)
    assert wb.worker.wait(120)
    wb.panels.auto_refit.value = False
    built = wb.cockpit.n_built
    _press(wb, wb.panels.btn_exclude_range)
    assert wb.ctrl.state.selection.n_rejected > 0 and not wb.worker.busy
    assert wb.cockpit.n_built == built + 3 and _excluded_in_figures(wb)


def test_the_scene_is_lit_as_a_plot_without_shadows_or_an_environment_map():
    """viser redraws the scene every second; in a software renderer the shadow map and the environment map's
    lighting made a page at rest take about a core. The scene has neither, and an ambient light in
    their place."""
    from magcal_workbench import scene as scn

    calls = []

    class Scene:
        def __getattr__(self, name):
            return lambda *args, **kwargs: calls.append((name, args, kwargs))

    class Server:
        scene = Scene()

    scn.SceneView(Server())
    by_name = {name: (args, kwargs) for name, args, kwargs in calls}
    assert by_name["configure_default_lights"][1]["cast_shadow"] is False
    assert by_name["configure_environment_map"][1]["hdri"] is None
    assert by_name["add_light_ambient"][1]["intensity"] > 0


def test_a_pattern_surface_is_matte_and_keeps_its_colours_without_an_environment_map():
    """A mesh with vertex colours alone reaches the page with glTF's default material, which is fully metallic:
    with the scene lit as a plot (no environment map) it was drawn black. The surfaces carry a matte material."""
    import json
    import struct

    import trimesh

    from magcal_workbench.maps import surface_visuals

    mesh = trimesh.creation.icosphere(subdivisions=1)
    rgba = np.tile(np.array([200, 40, 40, 255], np.uint8), (len(mesh.vertices), 1))
    rgba[::3] = (40, 40, 200, 255)
    mesh.visual = surface_visuals(rgba)
    glb = mesh.export(file_type="glb")  # what viser's add_mesh_trimesh sends
    n_json = struct.unpack("<I", glb[12:16])[0]
    gltf = json.loads(glb[20 : 20 + n_json])
    (primitive,) = gltf["meshes"][0]["primitives"]
    assert "COLOR_0" in primitive["attributes"]  # the pattern's colours, one per vertex
    pbr = gltf["materials"][primitive["material"]]["pbrMetallicRoughness"]
    assert pbr["metallicFactor"] == 0.0
    np.testing.assert_array_equal(np.asarray(mesh.visual.vertex_attributes["color"]), rgba)
