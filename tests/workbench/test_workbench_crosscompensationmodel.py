"""The cross's compensation in the workbench: a simulated four-sensor cross flown through a compensation box with a
hidden battery current opens on the cross compensation; the fit lowers the tensor FOM, Diagnose names the current
on held-out maneuvers, Add brings the FOM down to the noise's floor, Take out brings back TL's; the session reopens
with the same; the page shows the cross's section (its title, the FOM table per maneuver, the figure) and nothing
of the total-field, vector or gravity fits, and the demo opened after it has them back."""

from __future__ import annotations

import json

import numpy as np
import pytest

from magcal.data.cross_flight import simulate_cross_flight
from magcal_workbench.compensationpanel import fom_table_markdown, maneuvers_figure
from magcal_workbench.controller import Controller
from magcal_workbench.crosscompensationmodel import CrossCompensationSession
from magcal_workbench.dataio import load_dataset
from magcal_workbench.guide import next_step
from magcal_workbench.lessons import DEMO
from magcal_workbench.looptext import loop_text
from magcal_workbench.sessionfile import read_session_document
from tests.helpers.cross_flights import write_cross_flight


@pytest.fixture(scope="module")
def cross_csv(tmp_path_factory):
    """A cross flight with a battery current (its column recorded) as the CSV the workbench opens."""
    flight = simulate_cross_flight(3, platform="drone_current")
    return write_cross_flight(flight, tmp_path_factory.mktemp("cross") / "cross.csv")


def test_the_loop_names_the_current_and_falls_to_the_floor(cross_csv):
    ds, _ = load_dataset(cross_csv)
    ctrl = Controller(ds)
    session = ctrl.model_session
    assert isinstance(session, CrossCompensationSession) and session is ctrl.cross_compensation
    assert ctrl.compensation_loop() and ctrl.fit_mode_name() == "cross_compensation"
    step = next_step(ctrl)
    assert step.key == "compensation" and "cross" in step.why

    session.fit()
    before, tl_fom, ratio, n = session.fom_figures(session.result)
    assert n == 12 and tl_fom < before / 10 and ratio > 10
    table = fom_table_markdown(session)
    assert table.count("\n| ") == 1 + 12 and "after nT/m" in table  # 12 maneuvers and the sum, in nT/m
    assert "tensor FOM" in loop_text(ctrl).status(ctrl) and next_step(ctrl).key == "diagnose"

    found = ctrl.step_diagnose()
    floor = session.diagnosis_figures(found)[1]
    assert found.verdict == "missing_effect" and ctrl.advice() == ["current"] and tl_fom > 5 * floor
    text = loop_text(ctrl).candidates(ctrl)
    assert "**advised**" in text and "held-out FOM nT/m" in text
    assert "nT per ampere" in loop_text(ctrl).candidate(ctrl, "current")  # its evidence
    # the figure: the 12 maneuvers before and after, as the table has them
    fig = maneuvers_figure(session)
    assert len(fig.data) == 2 and [list(trace.y) for trace in fig.data] == [
        [row[2 + k] for row in session.fom_rows()] for k in (0, 1)
    ]
    assert sum(fig.data[1].y) < 0.1 * sum(fig.data[0].y)  # compensated: a tenth of the raw tensor, TL alone

    ctrl.step_add_advice()
    assert session.effects == ["current"] and session.fom_now < 1.5 * floor  # down to the noise's floor
    assert "current" in loop_text(ctrl).terms(ctrl) and next_step(ctrl).key == "diagnose"

    ctrl.step_remove("current")
    assert session.effects == [] and session.fom_now == pytest.approx(tl_fom, rel=1e-9)
    history = session.history()
    assert [h["step"] for h in history] == ["Tolles-Lawson fit", "+ current", "- current"]
    assert history[1]["fom_nT"] < 0.1 * history[0]["fom_nT"]
    assert "FOM after nT/m" in loop_text(ctrl).history(ctrl)

    # the session file (JSON, read back through the checked reader) reopens the same compensation
    ctrl.step_add("current")
    doc = json.loads(json.dumps(ctrl.state.to_dict()))
    again = Controller(ctrl.dataset, state=read_session_document(doc, "test session"))
    assert again.model_session is again.cross_compensation and again.cross_compensation.effects == ["current"]
    assert again.cross_compensation.fom_now == pytest.approx(session.fom_now, rel=1e-9)
    assert again.compensation.result is None and again.compensation.save() is None  # not the scalar's


def test_the_fit_keeps_only_the_kept_samples(cross_csv):
    """A stretch left out of the fit (the selection) changes the fit, and the history counts the samples fitted."""
    ds, _ = load_dataset(cross_csv)
    ctrl = Controller(ds)
    ctrl.cross_compensation.fit()
    whole = ctrl.cross_compensation.fom_now
    kept = np.ones(ds.n_samples, bool)
    kept[: ds.n_samples // 3] = False
    ctrl.select(np.flatnonzero(~kept), "reject")
    ctrl.cross_compensation.fit()
    assert ctrl.cross_compensation.history()[-1]["n_fitted"] == int(kept.sum())
    assert ctrl.cross_compensation.fom_now != pytest.approx(whole, rel=1e-6)


def test_the_page_shows_the_cross_and_the_demo_after_it_its_own_fits(bench, cross_csv):
    ds, _ = load_dataset(cross_csv)
    wb = bench(ds=ds, name="cross.csv")
    page = wb.added["compensation"]
    calibrate, model = wb.added["calibrate"], wb.added["model"]
    assert page.folder.visible and page.folder.label.startswith("Cross compensation")
    assert calibrate.mode_note.visible and "cross compensation" in calibrate.mode_note.content
    assert not calibrate.btn_run.visible and not calibrate.field_folder.visible
    assert not wb.panels.vector_panel.folder.visible and not wb.added["gravity"].folder.visible
    assert model.mode_note.visible and not model.effects_folder.visible and not model.btn_refit.visible

    page.do_compensation_fit(None)  # the section's button: the fit in the worker
    assert wb.worker.wait(120)
    wb.ui.wait()
    assert page.traces.visible and "after nT/m" in page.table.content and not page.btn_remove.visible
    wb.ctrl.cross_compensation.add("current")
    wb.ui.wait()
    assert page.btn_remove.visible and "+ current" in page.history.content
    page.do_remove_compensation_term(None)  # the Model tab's Take out
    assert wb.worker.wait(120)
    wb.ui.wait()
    assert wb.ctrl.cross_compensation.effects == [] and not page.btn_remove.visible

    other, _ = load_dataset(DEMO)
    wb.load(other, DEMO.read_bytes(), "demo.csv", resume=False)
    wb.ui.wait()
    assert not page.folder.visible and not page.steps_folder.visible and page.table.content == ""
    assert not calibrate.mode_note.visible and calibrate.btn_run.visible and calibrate.field_folder.visible
    assert wb.panels.vector_panel.folder.visible and wb.added["gravity"].folder.visible
    assert model.effects_folder.visible and model.btn_refit.visible and not model.mode_note.visible
    assert wb.ctrl.model_session is wb.ctrl.total_field and wb.ctrl.cross_compensation.result is None


def test_the_page_judges_the_sensors_lag_against_the_files_field_vector(tmp_path):
    """The four sensors 100 ms late against the attitude, the file with its field vector (ref_n, ref_e, ref_d): the
    page's cross takes the attitude's Earth field, as ``magcal diagnose --mode cross_compensation`` does, and its
    diagnosis names the lag; the same file without the vector judges against the four's mean field, where the lag
    cannot be judged and the page says why."""
    flight = simulate_cross_flight(21, platform="aircraft", sensor_lag_s=0.1)
    ds, _ = load_dataset(write_cross_flight(flight, tmp_path / "lagged.csv"))
    ctrl = Controller(ds)
    session = ctrl.cross_compensation
    assert ctrl.model_session is session and session.field_reference() is not None
    session.fit()
    assert session.result.calibration.reference == "attitude"
    found = ctrl.step_diagnose()
    assert found.explained_by == ["time_offset"] and ctrl.advice() == ["time_offset"]
    assert "`time_offset`" in loop_text(ctrl).candidates(ctrl)
    assert "100 ms late" in loop_text(ctrl).candidate(ctrl, "time_offset")
    tl_fom = session.fom_now
    ctrl.step_add_advice()
    assert session.effects == ["time_offset"] and session.result.calibration.time_offset_s == pytest.approx(
        0.1, abs=0.01
    )
    assert session.fom_now < tl_fom

    bare, _ = load_dataset(write_cross_flight(flight, tmp_path / "bare.csv", reference=False))
    mean = Controller(bare)
    assert mean.cross_compensation.field_reference() is None
    mean.cross_compensation.fit()
    assert mean.cross_compensation.result.calibration.reference == "mean"
    lag = next(c for c in mean.step_diagnose().candidates if c.name == "time_offset")
    page = loop_text(mean).candidates(mean)
    assert not lag.judged and "a \\# site: line, or a location" in page and "--reference" not in page
