"""One registry rule (issue 27): a name in the catalogue is never replaced by accident, and every effect -- built-in,
from a file or from an entry point -- passes the same checks (magcal.model.plugins.validate_effect)."""

from __future__ import annotations

import numpy as np
import pytest

import magcal
from magcal.core.errors import MagcalError
from magcal.model import EFFECTS, Effect, plugins, register


def _effect_named(name):
    class Impostor(Effect):
        stage = "raw"
        description = "a constant offset on x"

        def param_names(self):
            return ["a_x_nT"]

        def param_scale(self):
            return np.ones(1)

        def raw_basis(self, z0, ctx):
            basis = np.zeros((z0.shape[0], 3, 1))
            basis[:, 0, 0] = 1.0
            return basis

    Impostor.name = name
    return Impostor


@pytest.mark.parametrize("name", sorted(EFFECTS))
def test_every_built_in_effect_passes_the_checks_a_users_effect_must_pass(name):
    assert plugins.validate_effect(EFFECTS[name]) == name


@pytest.mark.parametrize("name", ["bias_drift", "temperature_bias"])
def test_register_refuses_a_taken_name(clean_catalogue, name):
    built_in = EFFECTS[name]
    with pytest.raises(MagcalError, match=r"already a built-in effect \(magcal\.model\.effects\..*replace=True"):
        register(_effect_named(name))
    assert EFFECTS[name] is built_in
    with pytest.raises(MagcalError, match="already a built-in"):
        magcal.register(_effect_named(name))  # the public name is the same rule


def test_register_replaces_only_when_asked(clean_catalogue):
    impostor = _effect_named("bias_drift")
    assert register(replace=True)(impostor) is impostor
    assert EFFECTS["bias_drift"] is impostor


def test_registering_the_same_class_again_changes_nothing(clean_catalogue):
    cls = register(_effect_named("my_offset"))
    assert register(cls) is cls and EFFECTS["my_offset"] is cls


@pytest.mark.parametrize("thing", [int, object(), Effect])
def test_register_refuses_what_is_not_an_effect_class(thing):
    with pytest.raises(MagcalError, match="not a subclass"):
        register(thing)


def test_an_effects_file_may_not_take_a_built_in_name(clean_catalogue, tmp_path):
    path = tmp_path / "clash.py"
    path.write_text(
        "import numpy as np\nfrom magcal.model import Effect, register\n\n\n@register\nclass Drift(Effect):\n"
        '    name = "bias_drift"\n    stage = "raw"\n\n    def param_names(self):\n        return ["a_nT"]\n'
    )
    before = dict(EFFECTS)
    with pytest.raises(plugins.UserEffectError, match=r"clash\.py.*already a built-in effect"):
        plugins.load_effects_file(path)
    assert EFFECTS == before


def test_an_effects_file_loaded_again_replaces_its_own_effects(clean_catalogue):
    from pathlib import Path

    example = Path(__file__).with_name("user_effects_example.py")
    first = plugins.load_effects_file(example)
    classes = {n: EFFECTS[n] for n in first}
    again = plugins.load_effects_file(example)
    assert again == first
    assert all(EFFECTS[n] is not classes[n] for n in first)  # the new classes, from the file run again
