"""Notes are values (item 3): every step returns what it has to say, and only the API and the command line
raise or print it, so jobs running at once on threads each get exactly their own notes.

The records: one sensor turned through a cap of directions only (the field within a cone about its x axis), so the
fit says "weak coverage" with the cap's own figures; a record whose cap is wider gives other figures, and a record
covering the sphere gives no note at all.
"""

from __future__ import annotations

import threading
import warnings

import numpy as np
import pytest

import magcal
from magcal.cli import main
from magcal.core.errors import ConvergenceWarning, CoverageWarning, DataWarning
from magcal.core.notes import Note, unique, warn
from magcal.data import io
from magcal.data.simulation import chi2017_truth, simulate_timeseries
from magcal.diagnosis import _parallel, scores
from magcal.fitting import pipeline

ROUNDS = 5  # each pair of jobs is started together this many times: a note that could stray would, sooner or later


def _record(cos_cap, seed=4, n_samples=3000, name="record"):
    """A one-sensor time series whose field stays within ``arccos(cos_cap)`` of the sensor's x axis (all samples
    for ``cos_cap=-1``); no reference field."""
    truth = chi2017_truth(1)
    ds = simulate_timeseries(truth, n_samples=n_samples, noise_nT=3.0, seed=seed)
    y = ds.readings_nT[0] - truth.sensors[0].bias_nT
    inside = (y / np.linalg.norm(y, axis=1, keepdims=True))[:, 0] > cos_cap
    return ds.subset(inside).replace(reference_total_nT=None, source=name)


@pytest.fixture(scope="module")
def records():
    return {
        "narrow": _record(0.8, name="narrow"),
        "wide": _record(0.6, name="wide"),
        "full": _record(-1.0, name="full"),
    }


def _side_by_side(job, inputs):
    """``job(x)`` for each input, all started at once on threads of their own; their results in order."""
    barrier = threading.Barrier(len(inputs))
    results, errors = [None] * len(inputs), []

    def run(k, x):
        try:
            barrier.wait(timeout=60)
            results[k] = job(x)
        except BaseException as exc:  # reported in the test's thread
            errors.append(exc)

    threads = [threading.Thread(target=run, args=(k, x)) for k, x in enumerate(inputs)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=300)
    assert not errors, errors
    return results


def test_a_note_is_a_value_with_its_warning_class():
    note = Note("sensor 1: weak coverage", CoverageWarning, "calibrate")
    assert str(note) == note.text and note.is_a(DataWarning) and not note.is_a(ConvergenceWarning)
    assert Note("x") == Note("x", DataWarning) and hash(Note("x")) == hash(Note("x", DataWarning))
    with pytest.raises(TypeError, match="Warning subclass"):
        Note("x", ValueError)
    again = [note, Note("other", ConvergenceWarning), Note(note.text, CoverageWarning, "elsewhere")]
    assert unique(again) == again[:2]  # the same text and class once, whoever said it
    with pytest.warns(CoverageWarning, match="weak coverage") as caught:
        warn([note], stacklevel=1)
    assert caught[0].filename == __file__  # stacklevel 1: the line that called warn


def test_the_engine_returns_notes_and_the_api_raises_them(records):
    narrow = records["narrow"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the engine's steps never warn
        result = pipeline.calibrate(narrow)
    assert [n.category for n in result.notes] == [CoverageWarning] and "weak coverage" in result.notes[0].text
    with pytest.warns(CoverageWarning, match="weak coverage"):
        magcal.calibrate(narrow)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        quiet = magcal.calibrate(narrow, warn=False)
        assert magcal.calibrate(records["full"]).notes == []  # nothing to say: nothing raised
    assert quiet.notes == result.notes


def test_two_calibrations_at_once_each_get_their_own_notes(records):
    names = ["narrow", "wide", "full"]
    alone = {name: magcal.calibrate(records[name], warn=False).notes for name in names}
    assert alone["narrow"] and alone["wide"] and not alone["full"]
    assert alone["narrow"] != alone["wide"]  # the caps' own figures
    for _ in range(ROUNDS * 3):
        together = _side_by_side(lambda name: magcal.calibrate(records[name], warn=False).notes, names)
        assert dict(zip(names, together)) == alone


def test_two_diagnoses_at_once_each_get_their_own_notes(records):
    names = ["narrow", "wide"]
    alone = {name: magcal.diagnose(records[name], warn=False).notes for name in names}
    assert alone["narrow"] and alone["wide"] and alone["narrow"] != alone["wide"]
    assert all(n.is_a(CoverageWarning) for notes in alone.values() for n in notes)
    for _ in range(ROUNDS):
        together = _side_by_side(lambda name: magcal.diagnose(records[name], warn=False).notes, names)
        assert dict(zip(names, together)) == alone
    # and, raised at the boundary, each thread's warnings are its own diagnosis's notes
    with pytest.warns(CoverageWarning, match="weak coverage"):
        magcal.diagnose(records["narrow"])


def test_a_note_made_on_a_pool_thread_reaches_the_diagnosis(monkeypatch):
    """Every refit of a candidate runs on the diagnosis's pool; each says (here, by a wrapper of the fit) which
    thread it ran on. The notes come back with their fits, so the diagnosis holds every one of them."""
    monkeypatch.setattr(_parallel, "PARALLEL_FITS", 2)
    real = scores.fit
    threads = []

    def noting_fit(*args, **kwargs):
        fitted = real(*args, **kwargs)
        name = threading.current_thread().name
        threads.append(name)
        fitted.notes.append(Note(f"refit on {name}, {len(threads)}", ConvergenceWarning, "test"))
        return fitted

    monkeypatch.setattr(scores, "fit", noting_fit)
    truth = chi2017_truth(1)
    drift = magcal.EFFECTS["bias_drift"]
    ds = simulate_timeseries(
        truth, n_samples=1500, noise_nT=3.0, seed=2, perturbations=[drift().perturbation(drift.default_magnitude)]
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # nothing is raised inside the engine, on any thread
        d = magcal.diagnosis.diagnose(ds, magcal.calibrate(ds, warn=False), validate=False)
    assert threads and all(name.startswith("magcal-fit") for name in threads)  # the pool's threads
    said = [n.text for n in d.notes if n.where == "test"]
    assert sorted(said) == sorted(f"refit on {name}, {k + 1}" for k, name in enumerate(threads))
    assert "bias_drift" in d.explained_by + d.record_holds  # the refits were real (a drift is what the record holds)
    with pytest.warns(ConvergenceWarning, match="refit on magcal-fit"):
        magcal.diagnose(ds, magcal.calibrate(ds, warn=False), validate=False)


def test_the_command_line_prints_the_notes(tmp_path, records, capsys, monkeypatch):
    path = tmp_path / "narrow.csv"
    io.write_csv(path, records["narrow"])
    assert main(["calibrate", str(path), "--json"]) == 0
    err = capsys.readouterr().err
    assert "magcal calibrate: warning: sensor 1: weak coverage" in err
    assert main(["diagnose", str(path), "--no-validate"]) == 0
    assert "magcal diagnose: warning: sensor 1: weak coverage" in capsys.readouterr().err
    # a note that is no data concern (a fit that did not converge) is printed once, from the result's notes
    real = pipeline.fit

    def stopped_fit(*args, **kwargs):
        fitted = real(*args, **kwargs)
        fitted.notes.append(Note("the fit did not converge (test)", ConvergenceWarning, "fit"))
        return fitted

    monkeypatch.setattr(pipeline, "fit", stopped_fit)
    full = tmp_path / "full.csv"
    io.write_csv(full, records["full"])
    assert main(["calibrate", str(full)]) == 0
    err = capsys.readouterr().err
    assert err.count("magcal calibrate: warning: the fit did not converge (test)") == 1
