"""The cross's compensation page on a flight with several current columns: a simulated four-sensor cross whose two
hidden wires (of four recorded current columns, two carrying no field at the cross) each carry a field. The page
lists each current column as a candidate of its own (``current (cur_strb)``), as the scalar's page does; Diagnose
advises both, the page's Add (clicked in a headless workbench) takes them, the tensor FOM reaches the true
compensation's within 1.2x; Remove takes one column out; the session file keeps the columns."""

from __future__ import annotations

import json

import numpy as np
import pytest

from magcal.data.cross_flight import simulate_cross_flight
from magcal.diagnosis.cross_fom import tensor_fom
from magcal_workbench.compensationpanel import history_markdown
from magcal_workbench.controller import Controller
from magcal_workbench.crosscompensationmodel import CrossCompensationSession
from magcal_workbench.dataio import load_dataset
from magcal_workbench.sessionfile import read_session_document
from tests.diagnosis.test_cross_compensation_currents import HIDDEN, PLATFORM
from tests.helpers.cross_flights import write_cross_flight
from tests.workbench.test_workbench_compensation_currents import _click


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    """The two-wire cross flight as the CSV the workbench opens (its four ``cur_*`` columns), and the flight."""
    f = simulate_cross_flight(33, platform=PLATFORM)
    path = write_cross_flight(f, tmp_path_factory.mktemp("cross_currents") / "cross.csv", current=False)
    text = open(path, encoding="utf-8").read().splitlines()
    head, rows = text[:2], text[2:]
    names = list(f.currents_A)
    lines = [head[0], head[1] + "," + ",".join(names)]
    lines += [row + "," + ",".join(f"{f.currents_A[c][i]:.9g}" for c in names) for i, row in enumerate(rows)]
    open(path, "w", encoding="utf-8").write("\n".join(lines) + "\n")
    return path, f


def _true_fom(flight, session) -> float:
    maneuvers = session.result.fom.after.maneuvers
    true = flight.truth.compensated_nT(flight.readings_nT)
    return tensor_fom(true, flight.baseline_m, maneuvers, flight.sample_rate_hz).fom_nT_per_m


def test_each_current_column_is_a_candidate_and_add_takes_both(bench, flight):
    path, truth = flight
    ds, _ = load_dataset(path)
    wb = bench(ds=ds, name="cross.csv")
    ctrl, p = wb.ctrl, wb.panels
    session = ctrl.model_session
    assert isinstance(session, CrossCompensationSession) and session.several_currents()
    assert sorted(session.current_choices()) == sorted(truth.currents_A)

    session.fit()
    tl_fom = session.fom_now
    ctrl.step_diagnose()
    offered = ctrl.candidate_labels()
    assert sorted(label for label in offered if label.startswith("current")) == sorted(
        f"current ({c})" for c in truth.currents_A
    )
    assert sorted(ctrl.advice()) == sorted(f"current ({c})" for c in HIDDEN)
    wb.ui.wait()
    assert p.candidate_choice.value in ctrl.advice()
    session.add_all(ctrl.advice())  # the guide's one refit adds both advised columns
    assert session.effects == ["current"] and sorted(session.current_columns) == sorted(HIDDEN)
    assert sorted(session.result.calibration.current_columns) == sorted(HIDDEN)
    true = _true_fom(truth, session)
    assert session.fom_now < 1.2 * true and session.fom_now < 0.2 * tl_fom
    assert all(f"current ({c})" in history_markdown(ctrl).replace("\\_", "_") for c in HIDDEN)

    # the page's Remove: the last column out, the other stays and its field's lack shows
    first, last = session.current_columns
    _click(wb, wb.added["compensation"].btn_remove)
    assert session.effects == ["current"] and session.current_columns == [first]
    assert session.history()[-1]["step"] == f"- current ({last})" and session.fom_now > 1.5 * true


def test_the_session_file_keeps_the_cross_current_columns(flight):
    path, _ = flight
    ds, _ = load_dataset(path)
    ctrl = Controller(ds)
    session = ctrl.model_session
    session.fit()
    session.add_all(["current (cur_com_1)", "current (cur_strb)"])
    saved = ctrl.state.compensation_fit
    assert saved["effects"] == ["current"] and saved["current_columns"] == ["cur_com_1", "cur_strb"]
    doc = json.loads(json.dumps(ctrl.state.to_dict()))
    again = Controller(ctrl.dataset, state=read_session_document(doc, "test session")).model_session
    assert isinstance(again, CrossCompensationSession) and again.current_columns == ["cur_com_1", "cur_strb"]
    assert np.isclose(again.fom_now, session.fom_now, rtol=1e-9)
