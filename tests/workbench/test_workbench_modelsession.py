"""The page's model sessions (:mod:`magcal_workbench.modelsession`): one shape for the total-field, vector and gravity
fits. Each mode's session runs fit -> diagnose -> add -> remove -> save -> restore on simulated data with known
errors; taking out what was added gives the base model's calibration again, and the session file (through JSON and
its checked reader) restores the calibration the session had. A session saved before the gravity fit was kept
still opens.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

import magcal
from magcal.core.errors import MagcalError
from magcal.data.board import SWAPPED_MOUNTING, simulate_board
from magcal.data.vehicle import simulate_vehicle, vehicle_truth
from magcal.model.perturbations import parse_hidden
from magcal_workbench.compensationmodel import CompensationSession
from magcal_workbench.controller import Controller
from magcal_workbench.gravitymodel import GravitySession
from magcal_workbench.modelsession import MODEL_SESSIONS, MODES, ModelSession
from magcal_workbench.sessionfile import read_session_document
from magcal_workbench.state import pack_mask
from magcal_workbench.totalfield import TotalFieldSession
from magcal_workbench.vectormodel import VectorSession


def _total_field_record():
    """Three-axis readings with a temperature-driven bias hidden (what the diagnosis should find)."""
    return magcal.simulate_timeseries(
        "chi2017", n_samples=1500, seed=7, rate_hz=5.0, perturbations=[parse_hidden("temperature_bias=30", 1)]
    )


def _vehicle_record():
    """A flight with attitude and the field vector, a battery current's field hidden."""
    truth = vehicle_truth(seed=11, off_deg=1.0)
    ds, _ = simulate_vehicle(
        truth,
        n=900,
        seed=11,
        attitude_noise_deg=0.02,
        perturbations=[parse_hidden("current_field=25", 1)],
        log_current=True,
        temperature=True,
    )
    return ds


def _board_record():
    ds, truth, _ = simulate_board(seed=21, n_poses=20, mounting=SWAPPED_MOUNTING, rate_hz=25.0)
    return ds, truth


def _reopened(ctrl: Controller) -> Controller:
    """The controller's session saved (to JSON, read back through the checked reader) and reopened on its data."""
    doc = json.loads(json.dumps(ctrl.state.to_dict()))
    return Controller(ctrl.dataset, state=read_session_document(doc, "test session"))


def _same_calibration(a, b, bias_nT=1e-3, cinv=1e-8):
    assert a is not None and b is not None
    for sa, sb in zip(a.sensors, b.sensors, strict=True):
        np.testing.assert_allclose(sa.bias_nT, sb.bias_nT, atol=bias_nT)
        np.testing.assert_allclose(sa.cinv, sb.cinv, atol=cinv)


def test_every_built_in_mode_has_one_session_class_named_as_the_engines_mode():
    assert set(MODES) <= set(MODEL_SESSIONS)
    assert MODEL_SESSIONS["total_field"] is TotalFieldSession
    assert MODEL_SESSIONS["vector"] is VectorSession
    assert MODEL_SESSIONS["gravity"] is GravitySession
    assert MODEL_SESSIONS["compensation"] is CompensationSession
    ctrl = Controller(magcal.simulate_timeseries("chi2017", n_samples=200, seed=1))
    assert list(ctrl.model_sessions)[: len(MODES)] == list(MODES)
    assert not ctrl.compensation.available and "scalar" in ctrl.compensation.missing()[0]
    assert all(isinstance(s, ModelSession) and s.ctrl is ctrl for s in ctrl.model_sessions.values())
    assert ctrl.model_session is ctrl.total_field  # no attitude, no field vector: the total-field loop
    assert not ctrl.gravity.available and "ax, ay, az" in ctrl.gravity.missing()[0]


def test_total_field_session_fit_diagnose_add_remove_save_restore():
    ctrl = Controller(_total_field_record())
    session = ctrl.model_session
    assert session is ctrl.total_field
    session.fit()
    base = session.calibration
    d = session.diagnose()
    assert d is session.diagnosis and session.candidate_labels()
    assert "temperature_bias" in {label.partition(":")[0] for label in session.advice()}  # the hidden effect
    label = session.advice()[0]
    session.add(label)
    assert label in session.effects and session.diagnosis is None  # a refit: the diagnosis was of the fit before
    with_effect = session.calibration
    assert with_effect.model is not None and session.history()[-1].step == f"add {label}"
    session.remove()
    assert session.effects == [] and session.history()[-1].step == f"remove {label}"
    _same_calibration(session.calibration, base, bias_nT=0.05, cinv=1e-6)  # the base model again
    assert session.save() == ctrl.state.calibration
    reopened = _reopened(ctrl)
    _same_calibration(reopened.total_field.calibration, session.calibration)
    assert [r.step for r in reopened.total_field.history()] == [r.step for r in session.history()]
    with pytest.raises(MagcalError, match="holds no effect"):
        session.remove()


def test_vector_session_fit_diagnose_add_remove_save_restore():
    ctrl = Controller(_vehicle_record())
    session = ctrl.model_session
    assert session is ctrl.vector and ctrl.vector_loop()
    session.fit()
    base = session.calibration
    session.diagnose()
    assert "current_field" in session.advice()  # the hidden battery current
    session.add("current_field")
    assert session.effects == ["current_field"] and session.history()[-1].step == "vector: add current_field"
    session.remove("current_field")
    assert session.effects == [] and session.history()[-1].step == "vector: remove current_field"
    _same_calibration(session.calibration, base, bias_nT=1e-2, cinv=1e-7)
    saved = session.save()
    assert saved == ctrl.state.vector_fit and saved["effects"] == []
    reopened = _reopened(ctrl)
    _same_calibration(reopened.vector.calibration, session.calibration)
    assert len(reopened.vector.history()) == len(session.history())


def test_gravity_session_fit_save_restore_and_no_loop():
    ds, _ = _board_record()
    ctrl = Controller(ds)
    session = ctrl.gravity
    assert session.available and session.save() is None
    session.fit()
    found = session.lesson_findings()  # the simulated board's magnetometer: ROLL_180_YAW_90, 2 deg off it
    assert found["mounting"] == ["ROLL_180_YAW_90"] and found["angle_off_deg"][0] == pytest.approx(2.0, abs=0.1)
    with pytest.raises(MagcalError, match="no diagnosis"):
        session.diagnose()
    with pytest.raises(MagcalError, match="takes no effects"):
        session.add("temperature_bias")
    with pytest.raises(MagcalError, match="holds no effect"):
        session.remove()
    saved = session.save()
    assert saved == ctrl.state.gravity_fit and saved["kept"] == pack_mask(ctrl.kept)
    reopened = _reopened(ctrl)  # the gravity fit is run again when the session reopens
    assert "the saved session's **gravity fit" in reopened.message
    _same_calibration(reopened.gravity.calibration, session.calibration)
    assert reopened.gravity.history() == [] and len(session.history()) == 1  # a rerun is no new step


def test_a_session_saved_before_the_gravity_fit_was_kept_still_opens():
    ds = magcal.simulate_timeseries("chi2017", n_samples=300, seed=3)
    first = Controller(ds)
    first.step_calibrate()
    kept = np.ones(ds.n_samples, bool)
    kept[:10] = False
    old = {  # the session file's shape before the model sessions: no "gravity_fit"
        "format": "magcal-workbench-session",
        "version": 1,
        "data_path": None,
        "lesson": None,
        "n_samples": ds.n_samples,
        "n_sensors": ds.n_sensors,
        "selection": {"n_samples": ds.n_samples, "kept": pack_mask(kept), "undo": [], "redo": []},
        "effects": [],
        "effects_files": [],
        "method": "ml",
        "reference_nT": None,
        "fit_reference": False,
        "robust": False,
        "sensor": None,
        "history": [h.to_dict() for h in first.state.history],
        "calibration": first.state.calibration,
        "answer_revealed": False,
        "noise_nT": None,
        "location": None,
        "vector_fit": None,
        "vector_history": [],
    }
    state = read_session_document(json.loads(json.dumps(old)), "old session.json")
    assert state.gravity_fit is None
    ctrl = Controller(ds, state=state)
    _same_calibration(ctrl.calibration, first.calibration)
    assert ctrl.gravity.result is None and ctrl.gravity.save() is None
    assert int(ctrl.kept.sum()) == ds.n_samples - 10


def test_the_panels_texts_follow_the_active_sessions_mode():
    from magcal_workbench.looptext import LOOP_TEXTS, StatusFigures, loop_text

    plain = Controller(magcal.simulate_timeseries("chi2017", n_samples=200, seed=1))
    vehicle = Controller(_vehicle_record())
    assert loop_text(plain) is LOOP_TEXTS["total_field"] and not loop_text(plain).evidence_per_candidate
    assert loop_text(vehicle) is LOOP_TEXTS["vector"] and loop_text(vehicle).evidence_per_candidate
    assert "vector fit" in loop_text(vehicle).candidates(vehicle)  # before a diagnosis: what to press
    figures = StatusFigures(rms="12.5 nT", floor="3 nT", rejected="Rejected: 0 of 200 samples", model="base terms only")
    plain_text, vehicle_text = loop_text(plain).status(plain, figures), loop_text(vehicle).status(vehicle, figures)
    assert plain_text.startswith("**Total-field RMS: 12.5 nT** (floor 3 nT)") and "Vector" not in plain_text
    # the vector model's figures first, the total-field fit's after it
    assert vehicle_text.index("Vector model: not fitted yet") < vehicle_text.index("Total-field RMS: 12.5 nT")


def _same_numbers(a, b, where="calibration"):
    """Two documents equal key by key, numbers to 1e-9 relative; the run's timing (``wall_s``) and the record a
    calibration names (a fit of every sample knows its record, the page's fit of the kept samples does not) aside."""
    if isinstance(a, dict):
        skip = {"wall_s", "record"}
        assert set(a) - skip == set(b) - skip, where
        for key in set(a) - skip:
            _same_numbers(a[key], b[key], f"{where}.{key}")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            _same_numbers(x, y, f"{where}[{i}]")
    elif isinstance(a, float):
        assert _close(a, b), f"{where}: {a!r} != {b!r}"
    else:
        assert a == b, where


def _close(a, b) -> bool:
    return bool(np.isclose(a, b, rtol=1e-9, atol=1e-12, equal_nan=True))


@pytest.mark.parametrize(
    "mode, effects",
    [("vector", ()), ("vector", ("current_field",)), ("gravity", ()), ("total_field", ("temperature_bias",))],
)
def test_the_page_and_magcal_calibrate_make_the_same_calibration(mode, effects):
    """The session fits through the engine's fit mode: on every sample kept, with the page's settings left as they
    open, its calibration is ``magcal.calibrate(ds, mode=...)``'s to 1e-9."""
    ds = {"vector": _vehicle_record, "gravity": lambda: _board_record()[0], "total_field": _total_field_record}[mode]()
    ctrl = Controller(ds)
    session = ctrl.model_sessions[mode]
    if mode == "total_field":
        ctrl.state.effects = list(effects)
        session.fit()
        options = {"effects": list(effects), "seed": 0}
    elif mode == "vector":
        session.fit(effects=list(effects))
        options = {"effects": list(effects)}
    else:
        session.fit()
        options = {}
    library = magcal.calibrate(ds, mode=mode, warn=False, **options)
    assert library.mode == mode and session.calibration.mode == library.calibration.mode
    _same_numbers(session.calibration.to_dict(), library.calibration.to_dict())


def test_the_pages_vector_diagnosis_is_magcal_diagnose_s():
    """Diagnose on the page (every sample kept) judges the same candidates as ``magcal.diagnose`` of the same fit;
    with samples rejected it is the diagnosis of the kept ones (the mode's ``mask=``)."""
    ds = _vehicle_record()
    ctrl = Controller(ds)
    page = ctrl.vector.diagnose()
    library = magcal.diagnose(ds, ctrl.vector.result, mode="vector", warn=False)
    assert (
        (page.verdict, page.explained_by)
        == (library.verdict, library.explained_by)
        == ("missing_effect", ["current_field"])
    )
    assert [(c.label, c.delta_bic) for c in page.candidates] == [(c.label, c.delta_bic) for c in library.candidates]
    ctrl.state.selection.reject(np.arange(100, 160))
    kept = ctrl.kept
    page = ctrl.vector.diagnose()
    library = magcal.diagnose(ds.subset(kept), mode="vector", warn=False)
    assert page.result.n_samples == library.result.n_samples == int(kept.sum())
    assert [(c.label, c.delta_bic) for c in page.candidates] == [(c.label, c.delta_bic) for c in library.candidates]
