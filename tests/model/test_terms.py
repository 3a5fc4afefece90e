"""The model: base terms, effect parsing and channel checks."""

import pytest

import magcal.model.effects  # noqa: F401  (registers the catalogue)
from magcal.core.errors import MagcalError
from magcal.data.simulation import simulate
from magcal.model.terms import BASE_TERMS, EFFECTS, Model, parse_effect


def test_base_model_drops_misalignment_for_one_sensor():
    assert Model.base_model(1).base == ("bias", "scale", "non_orthogonality")
    assert Model.base_model(4).base == BASE_TERMS


def test_without_removes_a_base_term():
    model = Model.base_model(4).without("non_orthogonality")
    assert "non_orthogonality" not in model.base and "scale" in model.base


@pytest.mark.parametrize(
    "spec, message",
    [
        ("bias", "base term"),
        ("no_such_effect", "unknown effect"),
        ("temperature_bias:9", "does not exist"),
        ("temperature_bias:x", "must be a number"),
    ],
)
def test_bad_effect_specs_are_explained(spec, message):
    with pytest.raises(MagcalError, match=message):
        parse_effect(spec, 4)


def test_missing_channels_are_reported():
    assert "temperature_bias" in EFFECTS
    ds = simulate("chi2017", seed=0)  # random attitudes: no time, no temperature
    model = Model.from_names(["temperature_bias"], 4)
    with pytest.raises(MagcalError, match="temperature"):
        model.check(ds)


def test_an_unknown_effect_may_be_a_users_effect_not_loaded():
    """The message says how to load a user's effect, and lists the catalogue."""
    with pytest.raises(MagcalError, match="unknown effect 'pump_interference'") as info:
        Model.from_names(["temperature_bias", "pump_interference:2"], 4)
    message = str(info.value)
    assert "--effects-file" in message and "temperature_bias" in message and "not loaded" in message
