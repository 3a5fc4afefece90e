"""Every registered effect describes itself: what the diagnosis, the report, the workbench and the
docs read of an effect lives on the effect, and a built-in effect that lacks a part fails here."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from magcal.diagnosis.evidence import SIGNATURES
from magcal.diagnosis.vector import EVIDENCE_CHANNELS, evidence_channel
from magcal.diagnosis.verdict import WHEN_RECORDING
from magcal.model.perturbations import perturbation_function
from magcal.model.terms import EFFECTS, Effect, register

BUILT_IN = sorted(name for name, cls in EFFECTS.items() if cls.__module__ == "magcal.model.effects")
DOCS = Path(__file__).resolve().parents[2] / "docs" / "effects.md"
#: A parameter name ends in its unit (``_nT``, ``_ms``, ``_nT_per_K``...), or is a dimensionless ratio.
UNIT = re.compile(
    r"_(nT|ms|ms2|K|ppm|h|unit|nT_per_K|ppm_per_K|nT_per_h|nT_per_m|nT_per_unit|nT_per_A|deg)$|^[A-Za-z]\w*_nT"
)


@pytest.mark.parametrize("name", BUILT_IN)
def test_every_built_in_effect_says_what_it_is_and_how_it_shows(name):
    cls = EFFECTS[name]
    effect = cls()
    assert cls.description, "a one-line description for the tables"
    assert set(cls.modes) <= {"scalar", "vector"} and cls.modes, "the fits that judge it"
    if "scalar" in cls.modes:
        assert cls.signature and SIGNATURES[name] == cls.signature, "how it shows in the total field"
    if "vector" in cls.modes and cls.stage == "raw":
        assert cls.vector_signature, "how it shows in a vector calibration's world residuals"
    if not cls.transferable:
        assert cls.when_recording and WHEN_RECORDING[name] == cls.when_recording, "what to do when recording"
        assert cls.kept_for_new_data, "what magcal apply keeps when it drops the term"
    assert cls.evidence_channel in ("current", "temperature_C", "turn_rate_dps", "time_s")
    assert EVIDENCE_CHANNELS[name] == cls.evidence_channel
    for other in cls.nested_in:
        assert other in EFFECTS, f"nested in an unknown effect {other}"
    names = effect.param_names()
    assert names and all(UNIT.search(n) for n in names), f"parameters with their units: {names}"
    assert len(effect.param_scale()) == len(names)
    assert perturbation_function(effect) is not None, "the simulator can hide it"
    assert f"`{name}`" in DOCS.read_text(encoding="utf-8"), "a row in docs/effects.md"


def test_a_users_effect_that_says_nothing_of_itself_still_runs_with_the_defaults():
    """The texts are optional for a user's effect: the tables then leave them out, and its residual is plotted
    against time (against the temperature when it needs the temperature)."""

    @register(replace=True)
    class QuietEffect(Effect):
        name = "quiet_effect_conformance"
        channels = ("temperature",)

        def param_names(self):
            return ["q_nT"]

        def raw_basis(self, z0, ctx):
            return np.zeros((len(z0), 3, 1))

    try:
        assert "quiet_effect_conformance" not in SIGNATURES and "quiet_effect_conformance" not in WHEN_RECORDING
        assert evidence_channel("quiet_effect_conformance", {"temperature_C": [1.0]}) == "temperature_C"
        assert evidence_channel("quiet_effect_conformance", {}) == "time_s"
    finally:
        EFFECTS.pop("quiet_effect_conformance", None)
