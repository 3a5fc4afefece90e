"""The loop on a vehicle in the workbench: Diagnose and Add on the vector model of a record with
attitude and a field vector, the RMS history in world components, the evidence plots against the candidate's
channel, the vehicle view's residual after Add, and the lesson of a drone whose compass sees its battery current.

The flights are simulated here with a motor current's field hidden by the catalogue's own perturbation
(:func:`magcal.model.perturbations.parse_hidden`); the true calibration is the simulator's truth with that field
(25, -17.5, 12.5 nT per ampere, the effect's pattern at 25) as its ``current_field``.
"""

from __future__ import annotations

import dataclasses
import json
import time

import numpy as np
import pytest

from magcal.core.errors import MagcalError
from magcal.data.vehicle import simulate_vehicle, vehicle_truth
from magcal.diagnosis.vector import VectorDiagnosis
from magcal.fitting.vector import true_calibration
from magcal.model.perturbations import parse_hidden
from magcal_workbench.controller import Controller
from magcal_workbench.lessons import get_lesson
from magcal_workbench.plots import evidence_image, evidence_panels
from magcal_workbench.sessionfile import SessionFileError, read_session_document

#: The hidden current field of the flights (nT per ampere per sensor axis): the perturbation ``current_field=25``.
K_nT_PER_A = np.array([25.0, -17.5, 12.5])


def _flight(n=1500, seed=11, hidden=True):
    """A flight with the battery current's field hidden, and the true calibration with that field."""
    truth = vehicle_truth(seed=seed, off_deg=1.0)
    ds, tr = simulate_vehicle(
        truth,
        n=n,
        seed=seed,
        attitude_noise_deg=0.02,
        perturbations=[parse_hidden("current_field=25", 1)] if hidden else [],
        log_current=True,
        temperature=True,
    )
    with_current = dataclasses.replace(tr, sensors=[dataclasses.replace(tr.sensors[0], current_nT_per_unit=K_nT_PER_A)])
    return ds, true_calibration(with_current)


def _world_rms(calibration, ds) -> float:
    ned = np.column_stack([ds.extra[c] for c in ("ref_n", "ref_e", "ref_d")])
    return float(np.sqrt(np.mean((calibration.world(ds, record_terms="apply")[0] - ned) ** 2)))


# --- the controller ----------------------------------------------------------------------------------------------
def test_diagnose_and_add_on_a_vector_record_name_the_hidden_current_and_reach_the_true_calibration():
    ds, truth_cal = _flight()
    ctrl = Controller(ds)
    assert ctrl.vector_loop()
    d = ctrl.step_diagnose()  # fits the vector model first: there is none yet
    assert isinstance(d, VectorDiagnosis) and d is ctrl.vector.diagnosis
    assert d.verdict == "missing_effect" and d.explained_by == ["current_field"]
    assert ctrl.vector.candidate_labels()[0] == "current_field"
    assert "current" in ctrl.message and "missing" in ctrl.message
    ctrl.step_add()  # the recommended candidate
    assert ctrl.vector.effects == ["current_field"] and ctrl.vector.diagnosis is None
    k = ctrl.vector.result.calibration.effect_values["current_field:1"]
    np.testing.assert_allclose(k, K_nT_PER_A, atol=0.5)
    # the world residual falls to within 1.25x of the true calibration's on the same record
    truth = _world_rms(truth_cal, ds)
    ours = _world_rms(ctrl.vector.result.calibration, ds)
    assert ours <= 1.25 * truth, (ours, truth)
    # the history in world components: the base fit, then the one with the current
    steps = ctrl.state.vector_history
    assert [s.step for s in steps] == ["vector fit", "vector: add current_field"]
    assert steps[1].effects == ["current_field"] and steps[1].world_nT == pytest.approx(ours, rel=1e-6)
    assert all(a < b / 4 for a, b in zip(steps[1].world_rms_nT, steps[0].world_rms_nT))
    assert steps[1].total_rms_nT < 1.25 * 3.0 < steps[0].total_rms_nT  # |B| at the sensor's 3 nT noise
    # the total-field loop is untouched: its model, its diagnosis
    assert ctrl.state.effects == [] and ctrl.diagnosis is None
    with pytest.raises(MagcalError, match="already in the vector model"):
        ctrl.step_add("current_field")
    ctrl.vector.remove()
    assert ctrl.vector.effects == [] and ctrl.state.vector_history[-1].step == "vector: remove current_field"


def test_a_vector_only_effect_goes_into_the_vector_model_and_a_total_field_term_is_refused_there():
    ds, _ = _flight(n=400)
    ctrl = Controller(ds)
    ctrl.step_add("attitude_time_offset")  # vector-only: the total-field fit refuses it
    assert ctrl.vector.effects == ["attitude_time_offset"] and ctrl.state.effects == []
    with pytest.raises(MagcalError, match="vector fit cannot take"):
        ctrl.step_add("site_gradient")
    with pytest.raises(MagcalError, match="not an effect label"):
        ctrl.step_add("current_field; rm -rf")


def test_records_without_attitude_or_field_vector_keep_the_total_field_loop():
    import magcal

    tumble = magcal.simulate_timeseries("chi2017", n_samples=200, seed=1)  # attitude, but no field vector
    ds, _ = _flight(n=300)
    for data in (tumble, tumble.replace(attitude_wxyz=None), ds.replace(extra={"current_A": ds.extra["current_A"]})):
        ctrl = Controller(data)
        assert not ctrl.vector_loop()
        d = ctrl.step_diagnose()
        assert not isinstance(d, VectorDiagnosis) and ctrl.vector.diagnosis is None and ctrl.diagnosis is d


# --- the evidence plots ------------------------------------------------------------------------------------------
def test_the_evidence_plots_put_the_candidates_channel_on_their_axis_and_flatten_after_add():
    ds, _ = _flight(n=1200)
    ctrl = Controller(ds)
    ctrl.state.selection.reject(np.arange(100, 150))
    assert evidence_panels(ctrl) is None  # no vector fit yet
    ctrl.step_vector()
    kept = ctrl.kept
    panels = evidence_panels(ctrl, candidate="current_field", max_points=100_000)
    assert [p["title"] for p in panels[:4]] == [f"{c} residual vs current_A" for c in ("north", "east", "down", "|B|")]
    ev = ctrl.vector.plot_evidence()
    north = panels[0]["traces"][0]
    np.testing.assert_array_equal(north["x"], ds.extra["current_A"][kept])  # the kept samples, the engine's data
    np.testing.assert_array_equal(north["y"], ev["world_residual_nT"][0, kept, 0])
    mean_before = [np.ptp(p["traces"][1]["y"]) for p in panels[:4]]  # the binned mean follows the current
    assert min(mean_before) > 50.0
    temp = evidence_panels(ctrl, candidate="temperature_bias")
    assert temp[0]["title"] == "north residual vs temperature" and temp[0]["x_label"] == "degC"
    turns = evidence_panels(ctrl, candidate="eddy_currents")
    assert turns[0]["x_label"] == "turn rate (deg/s)"
    times = evidence_panels(ctrl, candidate="bias_step", window_s=(10.0, 20.0))
    assert times[0]["x_label"] == "time (s)" and times[0]["band"] == (10.0, 20.0)
    ctrl.vector.add("current_field")
    after = evidence_panels(ctrl)  # without a candidate: the channel of the effect added last
    assert after[0]["title"] == "north residual vs current_A"
    mean_after = [np.ptp(p["traces"][1]["y"]) for p in after[:4]]
    assert all(a < b / 5 for a, b in zip(mean_after, mean_before))
    bars = after[4]["traces"]
    assert [t["kind"] for t in bars] == ["bar", "before"]
    np.testing.assert_allclose(bars[1]["y"][:3], ctrl.state.vector_history[0].world_rms_nT)
    assert np.all(bars[0]["y"] < bars[1]["y"] / 4)
    png = evidence_image(ctrl, "png", candidate="current_field")
    assert png[:4] == b"\x89PNG" and len(png) > 20_000


# --- the session ------------------------------------------------------------------------------------------------
def test_the_session_keeps_the_vector_models_effects_and_history(tmp_path):
    from magcal_workbench.session import SessionStore

    ds, _ = _flight(n=600)
    store = SessionStore(tmp_path / "sessions")
    sid = store.create("flight.csv", b"the data's copy")
    ctrl = Controller(ds, store=store, session_id=sid)
    ctrl.vector.fit()
    ctrl.vector.add("current_field")
    saved = store.load(sid)
    assert saved.vector_fit["effects"] == ["current_field"]
    assert [s.step for s in saved.vector_history] == ["vector fit", "vector: add current_field"]
    again = Controller(ds, state=saved)  # runs the saved vector fit again, with its effect
    assert again.vector.effects == ["current_field"] and again.vector.result.calibration.model.effect_labels == [
        "current_field"
    ]
    assert len(again.state.vector_history) == 2  # the reopening adds no step
    assert again.vector.vector_row().world_rms_nT == pytest.approx(ctrl.vector.vector_row().world_rms_nT, rel=1e-6)


@pytest.mark.parametrize(
    "key, value, field",
    [
        ("vector_history", [{"step": "vector fit", "world_rms_nT": [1.0, 2.0]}], "vector_history[0].world_rms_nT"),
        ("vector_history", [{"step": "x", "world_rms_nT": [1.0, -2.0, 3.0]}], "vector_history[0].world_rms_nT[1]"),
        ("vector_history", [{"world_rms_nT": [1.0, 2.0, 3.0]}], "vector_history[0].step"),
        ("vector_history", {"step": "x"}, "vector_history"),
        ("vector_fit", {"kept": None, "effects": ["Current"]}, "vector_fit.effects[0]"),
        ("vector_fit", {"kept": None, "effects": ["current_field", "current_field"]}, "vector_fit.effects"),
    ],
)
def test_a_damaged_vector_model_in_the_session_file_is_named(key, value, field):
    from magcal_workbench.state import pack_mask

    ds, _ = _flight(n=100)
    doc = json.loads(json.dumps(Controller(ds).state.to_dict()))
    if key == "vector_fit":
        value = {**value, "kept": pack_mask(np.ones(100, bool))}
    doc[key] = value
    with pytest.raises(SessionFileError) as err:
        read_session_document(doc)
    assert err.value.field == field


# --- the page (a real server on loopback, no browser) ------------------------------------------------------------
def _click(wb, button):
    button.value = True  # what a click does: the callbacks run
    time.sleep(0.05)
    assert wb.worker.wait(120)


def test_diagnose_and_add_through_the_page_and_the_vehicle_views_arrows_shorten(bench):
    ds, _ = _flight(n=1200)
    wb = bench(ds=ds)
    p, vp = wb.panels, wb.panels.vector_panel
    assert vp.rms_plot.visible and not p.rms_plot.visible  # the world components' history replaces |B|'s
    vp.vehicle_on.value = True
    wb.ctrl.step_vector()
    samples = (100, 300, 500, 700, 900)

    def arrows():
        out = []
        for i in samples:
            p.window_start.value = float(ds.time_s[i])
            assert wb.vehicle.shown["sample"] == wb.window.current(ds.time_s)
            start, end = wb.vehicle.shown["arrows"]["residual"][0]
            out.append(np.linalg.norm(end - start))
        return np.array(out), wb.vehicle.gain

    before, gain = arrows()
    _click(wb, p.btn_diagnose)  # Steps.do_diagnose in the worker
    assert "**Verdict:** `missing_effect` on the vector fit" in p.candidates.content
    assert "**recommended**" in p.candidates.content and "`current_field`" in p.candidates.content
    assert p.candidate_choice.options[0] == p.candidate_choice.value == "current_field"
    assert "north residual vs current_A" in [a.text for a in wb.evidence.plot.figure.layout.annotations]
    assert "Recommended" in p.candidate_evidence.content
    _click(wb, p.btn_add)
    assert wb.ctrl.vector.effects == ["current_field"]
    assert "vector: add current" in p.history.content and "Vector model: world RMS N/E/D" in p.status.content
    after, gain_after = arrows()
    assert gain_after == gain  # the exaggeration of the base model: the arrows show the fall
    assert after.mean() < before.mean() / 3
    x, *series = vp.rms_plot.data
    assert len(x) == 2 and all(s[1] < s[0] / 4 for s in series[:4])


# --- the lesson --------------------------------------------------------------------------------------------------
def test_the_drone_lesson_is_solved_by_the_loop_on_the_vector_model():
    """The guide's steps: Diagnose names the current's field, Add brings the world error to the noise floor, the
    next diagnosis finds the model adequate, and the lesson is judged on the vector model's effects."""
    from magcal_workbench.dataio import load_dataset

    lesson = get_lesson("drone-current")
    ds, notes = load_dataset(lesson.data_path)
    assert notes == [] and ds.n_sensors == 1 and ds.n_samples <= 5000
    assert {"ref_n", "ref_e", "ref_d", "current_A"} <= set(ds.extra) and ds.temperature_C is not None
    assert "current_field" not in lesson.guide()  # the guide never names the answer
    ctrl = Controller(ds)
    assert ctrl.vector_loop()
    first = lesson.check(ctrl.state.effects, ctrl.vector.lesson_findings())
    assert not first["solved"] and "vector model" in first["message"]
    d = ctrl.step_diagnose()
    assert d.verdict == "missing_effect" and d.explained_by == ["current_field"]
    not_yet = lesson.check(["current_field"], ctrl.vector.lesson_findings())  # the total-field model does not count
    assert not not_yet["solved"] and not_yet["missing"] == 1
    ctrl.step_add()
    floor = ctrl.vector.floor_nT  # the world noise floor the diagnosis found (attitude error and sensor noise)
    assert floor == pytest.approx(d.noise.world_floor_nT)
    assert ctrl.state.vector_history[-1].world_nT < 1.1 * floor < ctrl.state.vector_history[0].world_nT / 5
    assert lesson.check(ctrl.state.effects, ctrl.vector.lesson_findings())["solved"]
    assert ctrl.step_diagnose().verdict == "adequate"
    extra = lesson.check([], {**ctrl.vector.lesson_findings(), "effects": ["current_field", "temperature_bias"]})
    assert not extra["solved"] and extra["extra"] == ["temperature_bias"]


@pytest.mark.e2e
@pytest.mark.slow
def test_the_drone_lesson_in_the_page(browser, bench, tmp_path):
    """In Chromium: open the lesson's data, press Diagnose and Add in the Model tab, read the verdict, the candidate
    and the world figures the page shows, and take a screenshot."""
    from magcal_workbench.dataio import load_dataset
    from tests.workbench.test_workbench_e2e import _dismiss_toasts, _open

    ds, _ = load_dataset(get_lesson("drone-current").data_path)
    wb = bench(ds=ds, max_points=300)  # software WebGL: a small scene keeps the page responsive
    page = _open(browser, wb)
    page.get_by_role("tab", name="Model").click()
    page.get_by_role("button", name="Diagnose").click()
    page.wait_for_function("() => document.body.innerText.includes('on the vector fit')", timeout=180_000)
    text = page.inner_text("body", timeout=60_000)
    assert "missing_effect" in text and "current_field" in text and "recommended" in text
    assert "World RMS per step (vector fit)" in text
    page.get_by_role("button", name="Add the candidate and refit").click()
    page.wait_for_function(  # the refit's message, said after the page shows its figures
        "() => document.body.innerText.includes('vector: add current_field')", timeout=180_000
    )
    text = page.inner_text("body", timeout=60_000)
    assert "Vector model: current_field" in text  # the status line above the tabs
    assert wb.ctrl.vector.effects == ["current_field"]
    world = wb.ctrl.state.vector_history[-1].world_rms_nT
    assert "world RMS N/E/D " + " / ".join(f"{v:.4g}" for v in world) in text
    _dismiss_toasts(page)
    shot = tmp_path / "vector_loop.png"
    page.screenshot(path=str(shot), timeout=120_000)
    assert shot.stat().st_size > 10_000
    page.close()
