"""The lesson cut from a real recording (assets/lessons/real-qmc5883l): small, attributed under its licence, and
its answer is what holds on held-out data of the shipped file."""

import json
from pathlib import Path

import pytest

import magcal
from magcal.fitting.validation import compare
from magcal.model.terms import EFFECTS

FOLDER = Path(__file__).resolve().parent.parent / "assets" / "lessons" / "real-qmc5883l"


def test_the_data_are_small_and_carry_source_and_licence():
    data = FOLDER / "data.csv"
    assert data.stat().st_size < 400_000
    head = [line for line in data.read_text(encoding="utf-8").splitlines()[:20] if line.startswith("#")]
    text = "\n".join(head)
    assert "tomisuarez2/MagnetometerCalibration" in text and "MIT" in text and "LICENSE.md" in text
    licence = (FOLDER / "LICENSE.md").read_text(encoding="utf-8")
    assert licence.startswith("MIT License") and "Copyright (c) 2025 Tom" in licence
    assert "The above copyright notice and this permission notice shall be included" in licence


def test_the_lesson_file_names_catalogue_terms_and_the_guide_hides_nothing_it_cannot_back():
    doc = json.loads((FOLDER / "lesson.json").read_text(encoding="utf-8"))
    assert doc["data"] == "data.csv" and doc["guide"] == "guide.md"
    assert all(e.partition(":")[0] in EFFECTS for e in doc["answer"]["effects"])
    ds = magcal.read_csv(FOLDER / "data.csv")
    assert ds.n_sensors == 1 and ds.n_samples == 5687 and ds.has("time")


@pytest.mark.parametrize("scheme", ["blocks", "later"])
def test_the_answer_holds_on_held_out_data_and_the_quadratic_does_not(scheme):
    """The guide's claim: the cubic term's gain holds on unseen samples (about 5 %), the quadratic's does not."""
    ds = magcal.read_csv(FOLDER / "data.csv")
    cubic = compare(ds, [], "nonlinearity_cubic", scheme=scheme)
    assert cubic.holds and cubic.with_effect.held_out_rms_nT < 0.97 * cubic.base.held_out_rms_nT
    quadratic = compare(ds, [], "nonlinearity_quadratic", scheme=scheme, base=cubic.base)
    assert not quadratic.holds
