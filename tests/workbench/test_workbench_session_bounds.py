"""Sessions bounded in what they hold as well as in bytes: history rows over the bound dropped with a note, a file
of too many values refused before it is decoded (and set aside at start, the workbench starting all the same),
undo masks within their bound, and the autosave streamed into the file (never the whole text in memory).

Each test builds its session itself, small (a few MB at most): the bounds are what is checked, not the size.
"""

from __future__ import annotations

import json
import time

import numpy as np
import pytest

from magcal_workbench import session as session_mod
from magcal_workbench import sessionfile, state
from magcal_workbench.session import SessionStore
from magcal_workbench.sessionfile import SessionFileError, read_session_bytes
from magcal_workbench.state import MAX_HISTORY_ROWS, SessionState, StepRecord, VectorStep

BENCH_SAMPLES = 200


def _step(k):
    return StepRecord(f"fit {k}", 3.0 + k * 1e-3, 2.5, [], 10, f"step {k}", 0.1)


def _vector(k):
    return VectorStep(f"vector fit {k}", [1.0, 2.0, 3.0], 4.0 + k * 1e-3, [], 10, f"v {k}", 0.2)


def _doc(n_rows, n_vector, n=20):
    st = SessionState(n, 1)
    doc = st.to_dict()
    doc["history"] = [_step(k).to_dict() for k in range(n_rows)]
    doc["vector_history"] = [_vector(k).to_dict() for k in range(n_vector)]
    return doc


@pytest.mark.parametrize("rows, vector", [(MAX_HISTORY_ROWS + 2500, 10), (3, MAX_HISTORY_ROWS + 7)])
def test_a_session_over_the_row_bound_keeps_its_last_rows_and_says_so(rows, vector):
    st = read_session_bytes(json.dumps(_doc(rows, vector)).encode())
    assert len(st.history) == min(rows, MAX_HISTORY_ROWS) and len(st.vector_history) == min(vector, MAX_HISTORY_ROWS)
    assert st.history[-1].step == f"fit {rows - 1}" and st.history[0].step == f"fit {max(rows - MAX_HISTORY_ROWS, 0)}"
    assert st.vector_history[-1].step == f"vector fit {vector - 1}"
    over = [(what, count - MAX_HISTORY_ROWS) for what, count in (("history", rows), ("vector history", vector))]
    expected = [
        f"the {what} keeps its last {MAX_HISTORY_ROWS:,} steps: the oldest {k:,} were dropped"
        for what, k in over
        if k > 0
    ]
    assert st.notes == expected


def test_a_damaged_row_is_named_by_its_place_in_the_file():
    doc = _doc(MAX_HISTORY_ROWS + 5, 0)
    doc["history"][-1]["rms_nT"] = "x"
    with pytest.raises(SessionFileError, match=rf"field 'history\[{MAX_HISTORY_ROWS + 4}\]\.rms_nT'"):
        read_session_bytes(json.dumps(doc).encode())


def test_a_file_of_too_many_values_is_refused_before_it_is_decoded(monkeypatch):
    """1.2 million values (100 000 vector rows) in 12 MB: refused from a count, json never called."""
    doc = _doc(1, 0)
    row = json.dumps(_vector(0).to_dict())
    head = json.dumps(doc)[:-1]
    data = (head + ', "vector_history": [' + ",".join([row] * 100_000) + "]}").encode()
    assert sessionfile.json_values(data) > sessionfile.MAX_VALUES
    monkeypatch.setattr(sessionfile.json, "loads", lambda *a, **k: pytest.fail("decoded"))
    t0 = time.monotonic()
    with pytest.raises(SessionFileError, match=r"holds about 1,[0-9,]+ values, more than the 1,000,000"):
        read_session_bytes(data)
    assert time.monotonic() - t0 < 5


def test_undo_masks_within_their_bound_on_save_and_on_read(monkeypatch):
    monkeypatch.setattr(state, "MAX_MASK_SAMPLES", 20 * 12)  # 12 masks of 20 samples: the kept, the vector fit's, 5+5
    st = SessionState(20, 1)
    for k in range(9):
        st.selection.reject([k])
    doc = st.to_dict()
    assert len(doc["selection"]["undo"]) == 5  # the 5 most recent
    saved_undo = [w for _, w in doc["selection"]["undo"]]
    monkeypatch.setattr(state, "MAX_MASK_SAMPLES", 20 * 6)
    back = read_session_bytes(json.dumps(doc).encode())
    assert [w for _, w in back.selection._undo] == saved_undo[-2:]
    assert back.notes == ["undo keeps its last 2 selection(s) of 20 samples: the oldest 3 were dropped"]


def test_the_state_drops_its_oldest_rows_as_it_records(monkeypatch):
    monkeypatch.setattr(state, "MAX_HISTORY_ROWS", 5)
    st = SessionState(20, 1)
    for k in range(8):
        st.record(_step(k))
        st.record_vector(_vector(k))
    assert [r.step for r in st.history] == [f"fit {k}" for k in range(3, 8)]
    assert [r.step for r in st.vector_history] == [f"vector fit {k}" for k in range(3, 8)]
    assert st.notes == [
        "the history keeps its last 5 steps: the oldest 1 were dropped",
        "the vector history keeps its last 5 steps: the oldest 1 were dropped",
    ]


def test_the_save_is_streamed_into_the_file(tmp_path, monkeypatch):
    """Nothing makes the whole text: json.dumps is not called, and the file reads back the same."""
    store = SessionStore(tmp_path)
    sid = store.create("d.csv", b"s1x,s1y,s1z\n1,2,3\n")
    st = SessionState(20, 1)
    for k in range(50):
        st.record(_step(k))
    monkeypatch.setattr(session_mod.json, "dumps", lambda *a, **k: pytest.fail("the whole text made"))
    path = store.save(sid, st)
    text = path.read_text()
    assert text.endswith("}\n") and '\n "history": [\n  {\n' in text  # indented by one space, as before
    back = store.load(sid)
    assert [r.step for r in back.history] == [r.step for r in st.history] and back.saved_at


def test_a_session_over_the_bounds_is_set_aside_and_the_workbench_starts(bench, tmp_path, capsys, monkeypatch):
    wb = bench()
    sid = wb.ctrl.session_id
    path = tmp_path / "sessions" / sid / "session.json"
    doc = json.loads(path.read_text())
    wb.stop()
    monkeypatch.setattr(sessionfile, "MAX_VALUES", 1000)
    doc["vector_history"] = [_vector(k).to_dict() for k in range(200)]
    path.write_text(json.dumps(doc))
    again = bench()  # no exception: the app starts, afresh
    assert again.ctrl.session_id == sid and again.ctrl.state.vector_history == []
    aside = [p for p in (tmp_path / "sessions").iterdir() if p.name.startswith(f"{sid}.damaged-")]
    assert len(aside) == 1
    err = capsys.readouterr().err
    assert "more than the 1,000 a session is read with" in err and aside[0].name in err and "Traceback" not in err
    assert "moved aside" in again.ctrl.message and "more than the 1,000" in again.ctrl.message


def test_a_session_that_runs_out_of_memory_is_set_aside_and_the_workbench_starts(bench, tmp_path, capsys, monkeypatch):
    wb = bench()
    sid = wb.ctrl.session_id
    wb.stop()

    def no_memory(*a, **k):
        raise MemoryError

    monkeypatch.setattr(session_mod, "read_session_bytes", no_memory)
    again = bench()
    err = capsys.readouterr().err
    assert f"the saved session {sid} could not be opened (MemoryError); moved aside to {sid}.damaged-" in err
    assert "could not be opened (MemoryError)" in again.ctrl.message and "Traceback" not in err


def test_rows_over_the_bound_in_a_saved_session_are_said_at_start(bench, tmp_path, capsys):
    wb = bench()
    sid = wb.ctrl.session_id
    path = tmp_path / "sessions" / sid / "session.json"
    doc = json.loads(path.read_text())
    wb.stop()
    doc["history"] = [_step(k).to_dict() for k in range(MAX_HISTORY_ROWS + 30)]
    path.write_text(json.dumps(doc))
    again = bench()
    assert len(again.ctrl.state.history) == MAX_HISTORY_ROWS
    note = f"the history keeps its last {MAX_HISTORY_ROWS:,} steps: the oldest 30 were dropped"
    assert note in capsys.readouterr().err and note in again.ctrl.message
    saved = json.loads(path.read_text())
    assert len(saved["history"]) == MAX_HISTORY_ROWS and np.isfinite(saved["history"][-1]["rms_nT"])
