"""One verdict type, one set of names and one forward selection for every diagnosis (magcal.diagnosis.base,
magcal.diagnosis.selection): the total-field, vector and gravity diagnoses of simulated records whose truth is set
answer to the same names, with the noise the simulation put in; the forward selection takes, round after round, the
best candidate whose gain holds on held-out data and nothing else."""

from __future__ import annotations

import json
from types import SimpleNamespace

import pytest

from magcal.checks.reference import resolve_vector_reference
from magcal.data.board import simulate_board
from magcal.data.simulation import simulate
from magcal.data.vehicle import simulate_vehicle, vehicle_truth
from magcal.diagnosis import VERDICTS, diagnose
from magcal.diagnosis.base import DiagnosisBase, NoiseLevel
from magcal.diagnosis.gravity import dip_evidence
from magcal.diagnosis.selection import first_that_holds, forward_selection
from magcal.diagnosis.vector import diagnose_vector
from magcal.fitting.gravity import fit_gravity

#: The noise per axis the simulations put in, nT.
SIGMA_nT = 3.0


@pytest.fixture(scope="module")
def diagnoses():
    """A diagnosis of each kind on a record that hides nothing."""
    total = simulate("ding2024", n_samples=400, noise_nT=SIGMA_nT, noise_kind="gaussian", seed=1)
    flight, _ = simulate_vehicle(vehicle_truth(n_sensors=1, seed=3), seed=3, n=1200, noise_nT=SIGMA_nT)
    board, _, _ = simulate_board(seed=3)
    return {
        "total": diagnose(total, workers=1),
        "vector": diagnose_vector(flight, resolve_vector_reference(flight), max_effects=1),
        "gravity": dip_evidence(board, fit_gravity(board)),
    }


def test_the_verdicts_are_defined_once_with_their_meanings():
    assert list(VERDICTS) == ["adequate", "missing_effect", "unexplained", "not_judged"]
    assert all(len(meaning) > 40 for meaning in VERDICTS.values())


@pytest.mark.parametrize("kind, verdict", [("total", "adequate"), ("vector", "adequate"), ("gravity", "not_judged")])
def test_every_diagnosis_answers_to_the_same_names(diagnoses, kind, verdict):
    d = diagnoses[kind]
    assert isinstance(d, DiagnosisBase)
    assert d.verdict == verdict and d.verdict_meaning == VERDICTS[verdict]
    assert d.explained_by == [] and d.remaining == [] and isinstance(d.notes, list)
    assert d.best is (d.candidates[0] if d.candidates else None)
    doc = json.loads(json.dumps(d.to_dict()))
    shared = {"verdict", "summary", "candidates", "explained_by", "remaining_structure", "noise", "warnings"}
    assert shared <= set(doc)
    assert doc["verdict"] == verdict and doc["summary"] == d.summary and len(doc["candidates"]) == len(d.candidates)
    assert d.text() == d.table() and d.text()


@pytest.mark.parametrize("kind", ["total", "vector"])
def test_the_noise_has_one_shape_and_is_the_noise_simulated(diagnoses, kind):
    d = diagnoses[kind]
    assert isinstance(d.noise, NoiseLevel)
    assert d.noise_nT == pytest.approx(SIGMA_nT, rel=0.15)
    assert d.to_dict()["noise"] == json.loads(json.dumps(d.noise.to_dict()))
    assert f"{d.noise.sigma_nT:.3g}" in d.noise.text() or kind == "vector"


def test_the_dip_evidence_advises_nothing_and_says_why(diagnoses):
    d = diagnoses["gravity"]
    assert d.noise is None and d.noise_nT is None
    assert "in-sample only" in d.summary and d.warnings == d.skipped


def _cand(label, holds, supported=True):
    return SimpleNamespace(label=label, holds=holds, supported=supported)


@pytest.mark.parametrize(
    "holds, in_sample_ok, taken",
    [
        ((False, True, True), False, "b"),  # the best in-sample does not hold: the next that does
        ((None, True), False, "b"),  # not judged: not taken where a held-out judgement is required
        ((None, True), True, "a"),  # ... taken on its in-sample evidence where the record could not be split
        ((False, None, False), False, None),
    ],
)
def test_the_first_candidate_that_holds_is_taken(holds, in_sample_ok, taken):
    cands = [_cand(label, h) for label, h in zip("abc", holds)]
    best = first_that_holds(cands, lambda c: c.supported, in_sample_ok)
    assert (best.label if best else None) == taken


def test_an_unsupported_candidate_is_never_taken_even_when_it_holds():
    assert first_that_holds([_cand("a", True, supported=False)], lambda c: c.supported) is None


@pytest.mark.parametrize(
    "rounds, max_effects, chosen",
    [
        ([[True], [True], [True]], 2, ["r0", "r1"]),  # stops at max_effects
        ([[False, True], [False]], 3, ["r0b"]),  # the second round finds nothing that holds
        ([[True], None], 3, ["r0"]),  # the second round has no candidate worth judging
        ([[True]], 0, []),  # no round at all
    ],
)
def test_the_forward_selection_takes_one_candidate_per_round(rounds, max_effects, chosen):
    asked = []

    def judged(step):
        asked.append(step)
        if rounds[step] is None:
            return None
        return [_cand(f"r{step}" + ("b" if i else ""), h) for i, h in enumerate(rounds[step])]

    taken = []
    got = forward_selection(
        lambda: judged(0),
        first_that_holds,
        lambda step, best, cands: taken.append((step, best.label)),
        lambda step, best: judged(step + 1),
        max_effects,
    )
    assert [c.label for c in got] == chosen
    assert taken == list(enumerate(chosen))
    assert asked == list(range(min(len(chosen) + 1, max_effects, len(rounds))))
