"""The compensation page on a flight with several current columns: a simulated flight whose two hidden currents (the
strobe's and the radio's wires) point in different directions among five recorded current columns (three carry no
field). The page lists each current column as a candidate of its own (``current (cur_strb)``); its loop (fit,
diagnose, Add the advised candidate twice) takes both columns and reaches the FOM within 1.2x of the true
compensation's; Remove takes one column out; the history says which; the session file keeps the columns, and a
session file of before (one ``current``, no columns) still opens."""

from __future__ import annotations

import json
import time

import numpy as np
import pandas as pd
import pytest

from magcal.core.errors import MagcalError
from magcal.data.compensation_flight import simulate_compensation_flight
from magcal.diagnosis.fom import figure_of_merit
from magcal_workbench.compensationpanel import candidate_markdown, history_markdown, terms_markdown
from magcal_workbench.controller import Controller
from magcal_workbench.dataio import load_dataset
from magcal_workbench.guide import next_step
from magcal_workbench.looptext import loop_text
from magcal_workbench.sessionfile import read_session_document
from tests.fitting.test_compensation_fit_currents import TWO_CURRENTS

HIDDEN = ["cur_com_1", "cur_strb"]


def currents_csv(path, seed=1):
    """The two-current flight written as a CSV the workbench opens (the five ``cur_*`` columns), and the flight."""
    f = simulate_compensation_flight(seed, platform=TWO_CURRENTS)
    columns = {
        "t": f.time_s,
        "x": f.flux_nT[:, 0],
        "y": f.flux_nT[:, 1],
        "z": f.flux_nT[:, 2],
        "scalar_nT": f.scalar_nT,
        "roll_deg": f.attitude_deg[:, 0],
        "pitch_deg": f.attitude_deg[:, 1],
        "yaw_deg": f.attitude_deg[:, 2],
    }
    pd.DataFrame(columns | dict(f.currents_A)).to_csv(path, index=False)
    return path, f


def _true_fom(flight, session) -> float:
    maneuvers = session.result.fom.after.maneuvers
    return figure_of_merit(flight.truth.compensated_nT(flight.scalar_nT), maneuvers, flight.sample_rate_hz).fom_nT


def _click(wb, button):
    button.value = True  # what a click does: the callbacks run in the worker
    time.sleep(0.05)
    assert wb.worker.wait(180)
    wb.ui.wait()


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    return currents_csv(tmp_path_factory.mktemp("currents") / "box.csv")


def test_each_current_column_is_a_candidate_and_add_takes_the_advised_ones(bench, flight):
    path, truth = flight
    ds, _ = load_dataset(path)
    wb = bench(ds=ds, name="box.csv")
    ctrl, p = wb.ctrl, wb.panels
    session = ctrl.compensation
    assert ctrl.model_session is session and session.several_currents()

    session.fit()
    ctrl.step_diagnose()
    offered = ctrl.candidate_labels()
    currents = [label for label in offered if label.startswith("current")]
    assert sorted(currents) == sorted(f"current ({c})" for c in truth.currents_A)  # five rows, each named
    assert "current" not in offered
    assert sorted(ctrl.advice()) == sorted(f"current ({c})" for c in HIDDEN)
    step = next_step(ctrl)  # the guide's Step 3 names both columns (its one refit adds them together)
    assert step.key == "add" and sorted(step.effects) == sorted(f"current ({c})" for c in HIDDEN)
    text = loop_text(ctrl).candidates(ctrl)
    assert all(f"`current ({c})`" in text for c in truth.currents_A)
    assert "per A" in candidate_markdown(ctrl, "current (cur_strb)")

    # the page's Add, twice (a fit clears the diagnosis: diagnose again between): the advised candidate the choice
    # offers first, each a column of the current term
    for n in (1, 2):
        if n == 2:
            ctrl.step_diagnose()  # the model's column named: the other columns stay candidates of their own
            assert ctrl.advice() == [f"current ({c})" for c in HIDDEN if c not in session.current_columns]
        wb.ui.wait()
        assert p.candidate_choice.value in ctrl.advice()
        _click(wb, p.btn_add)
        assert session.effects == ["current"] and len(session.current_columns) == n
    assert sorted(session.current_columns) == HIDDEN
    true = _true_fom(truth, session)
    assert session.result.fom_nT < 1.2 * true and true < 10 * session.result.fom_nT
    assert sorted(session.result.calibration.current_columns) == HIDDEN
    history = session.history()
    assert [h["step"] for h in history[1:]] == [f"+ current ({c})" for c in session.current_columns]
    shown = history_markdown(ctrl)
    assert all(f"current ({c})" in shown.replace("\\_", "_") for c in HIDDEN)
    assert all(f"`current ({c})`" in terms_markdown(ctrl) for c in HIDDEN)
    two_columns_fom = session.result.fom_nT

    # Remove: the last column out, the other stays
    first, last = session.current_columns
    _click(wb, wb.added["compensation"].btn_remove)
    assert session.effects == ["current"] and session.current_columns == [first]
    assert session.history()[-1]["step"] == f"- current ({last})" and session.fom_now > 10 * two_columns_fom
    session.remove(f"current ({first})")
    assert session.effects == [] and session.current_columns == []
    with pytest.raises(MagcalError, match="no current column cur_fan"):
        session.add_all(["current (cur_fan)"])


def test_the_session_file_keeps_the_columns_and_one_of_before_still_opens(flight):
    path, truth = flight
    ds, _ = load_dataset(path)
    ctrl = Controller(ds)
    session = ctrl.compensation
    session.fit()
    session.add_all(["current (cur_com_1)"])  # the second of the columns: a restore must not take the first
    saved = ctrl.state.compensation_fit
    assert saved["effects"] == ["current"] and saved["current_columns"] == ["cur_com_1"]
    doc = json.loads(json.dumps(ctrl.state.to_dict()))
    again = Controller(ctrl.dataset, state=read_session_document(doc, "test session")).compensation
    assert again.current_columns == ["cur_com_1"]
    assert again.result.fom_nT == pytest.approx(session.result.fom_nT, rel=1e-9)
    assert [h["current_columns"] for h in again.history()] == [[], ["cur_com_1"]]
    assert "current (cur_com_1)" in history_markdown(again.ctrl).replace("\\_", "_")

    # a session file of before: one current, no columns (the engine's first current column, as it then fitted)
    old = json.loads(json.dumps(doc))
    del old["compensation_fit"]["current_columns"]
    for row in old["compensation_fit"]["history"]:
        del row["current_columns"]
    before = Controller(ctrl.dataset, state=read_session_document(old, "old session")).compensation
    assert before.effects == ["current"] and before.current_columns == ["cur_strb"]
    assert before.result.fom_nT > session.result.fom_nT  # the first column alone, as the file's fit took it
    assert "current" in history_markdown(before.ctrl)

    bad = json.loads(json.dumps(doc))
    bad["compensation_fit"]["current_columns"] = ["cur_com_1", "cur_com_1"]
    with pytest.raises(MagcalError, match="compensation_fit.current_columns.*names a column twice"):
        read_session_document(bad, "bad session")


def test_a_record_with_one_current_column_keeps_the_plain_name(tmp_path):
    f = simulate_compensation_flight(1, platform=TWO_CURRENTS)
    frame = pd.DataFrame(
        {"t": f.time_s, "x": f.flux_nT[:, 0], "y": f.flux_nT[:, 1], "z": f.flux_nT[:, 2], "scalar_nT": f.scalar_nT}
    )
    frame["current_A"] = f.currents_A["cur_strb"]
    frame.to_csv(tmp_path / "one.csv", index=False)
    ds, _ = load_dataset(tmp_path / "one.csv")
    session = Controller(ds).compensation
    assert not session.several_currents()
    session.add_all(["current"])
    assert session.model_labels() == ["current"] and session.current_columns == ["current_A"]
    assert np.isfinite(session.result.fom_nT)
