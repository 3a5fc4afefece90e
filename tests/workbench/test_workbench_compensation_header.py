"""The header on a compensation flight: the compact table shows the compensation's FOM (the scalar's in nT, the
cross's tensor in nT/m) before and after with its improvement ratio, and the floor the noise leaves once diagnosed,
not the total-field fit's raw RMS of ``|y| - F``; the scene's colour legend says what its colours are and that the
FOM in the table judges the compensation; a record that is no compensation flight keeps the usual table."""

from __future__ import annotations

import time

from magcal.data.cross_flight import simulate_cross_flight
from magcal_workbench.dataio import load_dataset
from magcal_workbench.figures import fmt
from tests.helpers.cross_flights import write_cross_flight
from tests.workbench.test_workbench_compensation import flight_csv


def _click(wb, button):
    button.value = True  # what a click does: the callbacks run in the worker
    time.sleep(0.05)
    assert wb.worker.wait(180)
    wb.ui.wait()


def test_the_scalar_flights_header_shows_the_fom_not_the_total_field_rms(bench, tmp_path):
    path, _ = flight_csv(tmp_path / "box.csv")
    ds, _ = load_dataset(path)
    wb = bench(ds=ds, name="box.csv")
    p, session = wb.panels, wb.ctrl.compensation
    wb.ui.wait()
    text = p.summary.content
    assert "not fitted yet" in text and "RMS nT" not in text and "C⁻¹" not in text and "Coverage" not in text
    assert "raw fluxgate |y| - F" in p.legend.content and "once fitted" in p.legend.content

    _click(wb, wb.added["compensation"].btn_fit)
    before, after, ratio, n = session.fom_figures(session.result)
    text = p.summary.content
    assert "scalar FOM nT" in text and f"| raw | {fmt(before, digits=4)} |" in text
    assert f"**{fmt(after, digits=4)}** | {ratio:.3g} |" in text and f"{n} maneuvers" in text
    assert "RMS nT" not in text and "|y|" not in text
    assert f"band-passed compensated scalar (compensation, FOM {fmt(after, 'nT', 3)})" in p.legend.content

    wb.ctrl.step_diagnose()
    wb.ui.wait()
    floor = session.diagnosis_figures(session.diagnosis)[1]
    assert f"the scalar's noise leaves {fmt(floor, 'nT', 3)}" in p.summary.content


def test_the_cross_flights_header_shows_the_tensor_fom(bench, tmp_path):
    ds, _ = load_dataset(write_cross_flight(simulate_cross_flight(3, platform="drone_current"), tmp_path / "c.csv"))
    wb = bench(ds=ds, name="cross.csv")
    session = wb.ctrl.cross_compensation
    assert wb.ctrl.model_session is session
    _click(wb, wb.added["compensation"].btn_fit)
    before, after, _, _ = session.fom_figures(session.result)
    text = wb.panels.summary.content
    assert "tensor FOM nT/m" in text and f"**{fmt(after, digits=4)}**" in text and "RMS nT" not in text
    assert f"its FOM {fmt(after, 'nT/m', 3)} in the table" in wb.panels.legend.content


def test_a_record_that_is_no_compensation_flight_keeps_the_usual_table(bench):
    wb = bench()
    wb.ui.wait()
    assert "RMS nT" in wb.panels.summary.content and "FOM" not in wb.panels.summary.content
