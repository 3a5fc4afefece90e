"""One registry rule: a name in the catalogue is never replaced by accident, and every effect -- built-in,
from a file or from an entry point -- passes the same checks (magcal.model.plugins.validate_effect)."""

from __future__ import annotations

import pathlib

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

    example = Path(__file__).resolve().parents[1] / "helpers" / "user_effects_example.py"
    first = plugins.load_effects_file(example)
    classes = {n: EFFECTS[n] for n in first}
    again = plugins.load_effects_file(example)
    assert again == first
    assert all(EFFECTS[n] is not classes[n] for n in first)  # the new classes, from the file run again


# ----------------------------------------------------------------------------------------------------------------
# the export formats' and the live sources' registries (magcal.output.formats, magcal.data.live.registry)
# ----------------------------------------------------------------------------------------------------------------


def test_every_built_in_export_format_is_listed_by_the_cli_the_bundle_and_the_page():
    import magcal_workbench.exporting as wexporting
    from magcal.cli import build_parser
    from magcal.output import bundle
    from magcal.output.formats import EXPORT_FORMATS

    assert list(EXPORT_FORMATS) == ["ardupilot", "px4", "c"]
    assert {EXPORT_FORMATS.origin(n) for n in EXPORT_FORMATS} == {"built-in"}
    parser = build_parser(only="export")
    sub = next(a for a in parser._actions if a.dest == "command").choices["export"]
    choices = next(a for a in sub._actions if a.dest == "format").choices
    assert tuple(choices) == ("ardupilot", "px4", "c", "mask", "all", "magnav-tl")  # magnav-tl: a compensation's
    assert dict(bundle.PARAMETER_FILES) == {
        "ardupilot": "compass.parm",
        "px4": "mag.params",
        "c": "magcal_calibration.h",
    }
    assert "formats.EXPORT_FORMATS" in pathlib.Path(wexporting.__file__).read_text(encoding="utf-8")


def test_an_entry_point_format_joins_and_a_broken_or_clashing_one_is_skipped(monkeypatch, tmp_path):
    import importlib.metadata

    from magcal.output import formats

    (tmp_path / "toy_fmt.py").write_text(
        "from magcal.output.formats import Export, ExportFormat\n"
        "TOY = ExportFormat('toy', 'toy', 'a toy', 'toy.txt', 'Toy', 'nothing',\n"
        "    lambda cal, **kw: Export('toy', f'{cal.n_sensors}\\n', {}, []))\n"
        "CLASH = ExportFormat('px4', 'x', 'x', 'x.txt', 'x', 'x', lambda cal, **kw: None)\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    group = formats.ENTRY_POINT_GROUP
    points = [
        importlib.metadata.EntryPoint("toy", "toy_fmt:TOY", group),
        importlib.metadata.EntryPoint("clash", "toy_fmt:CLASH", group),
        importlib.metadata.EntryPoint("broken", "no_such_module_xyz:X", group),
    ]
    monkeypatch.setattr(
        importlib.metadata, "entry_points", lambda group=None: points if group == formats.ENTRY_POINT_GROUP else []
    )
    try:
        loaded = formats.load_entry_points(force=True)
        notes = loaded.notes
        assert loaded == ["toy"]
        assert list(formats.EXPORT_FORMATS) == ["ardupilot", "px4", "c", "toy"]
        assert formats.EXPORT_FORMATS["px4"].file_name == "mag.params"  # the clash changed nothing
        assert "entry point toy = toy_fmt:TOY" in formats.EXPORT_FORMATS.origin("toy")
        texts = " ".join(n.text for n in notes)
        assert "clash" in texts and "already registered" in texts and "broken" in texts
        cal = magcal.calibrate(magcal.simulate("chi2017", seed=1)).calibration
        from magcal.output.export import export_calibration

        assert export_calibration(cal, "toy").text == "4\n"
        with pytest.raises(MagcalError, match="built in"):
            formats.EXPORT_FORMATS.unregister("px4")
    finally:
        formats.EXPORT_FORMATS.unregister("toy")
    assert list(formats.EXPORT_FORMATS) == ["ardupilot", "px4", "c"]


@pytest.mark.parametrize(
    "fields, message",
    [
        (("mask", "t", "d", "m.txt", "b", "r"), "magcal export's own"),
        (("Bad Name", "t", "d", "m.txt", "b", "r"), "lower-case"),
        (("fine", "t", "d", "sub/m.txt", "b", "r"), "plain file name"),
        (("fine", "t", "d", "raw_mask.csv", "b", "r"), "the bundle"),
        (("fine", "t", "", "m.txt", "b", "r"), "description"),
    ],
)
def test_a_format_that_breaks_the_rules_is_refused_naming_what_to_change(fields, message):
    from magcal.output.formats import EXPORT_FORMATS, Export, ExportFormat, register_format

    with pytest.raises(MagcalError, match=message):
        register_format(ExportFormat(*fields, writer=lambda cal, **kw: Export("x", "", {}, [])))
    assert list(EXPORT_FORMATS) == ["ardupilot", "px4", "c"]


def test_every_built_in_live_source_is_registered_and_open_source_is_a_lookup(tmp_path):
    from magcal.data import live

    assert list(live.LIVE_SOURCES) == ["serial", "network", "sim"]
    assert live.schemes() == ("serial", "udp", "tcp", "sim")
    assert live.source_for("tcp").name == "network" and live.source_for("nope") is None
    with pytest.raises(live.LiveError, match="unknown source; use serial://DEVICE, udp://HOST:PORT"):
        live.open_source("nope://x")
    seen = []

    def opener(url):
        seen.append((url.target, url.number("n", 1, int), url.params))
        return live.open_source(f"sim://chi2017?n={url.number('n', 1, int)}&rate=1000")

    toy = live.register_source(live.SourceKind("toy", ("toy",), "a toy", ("toy://NAME",), "toy://a", ("n",), opener))
    try:
        with live.open_source("toy://here?n=7") as source:
            assert isinstance(source, live.SimSource) and source.dataset.n_samples == 7
        assert seen == [("here", 7, {"n": "7"})]
        with pytest.raises(MagcalError, match="scheme 'sim' is 'sim'"):
            live.register_source(live.SourceKind("other", ("sim",), "d", ("sim://",), "sim://", (), opener))
        assert live.LIVE_SOURCES["toy"] is toy
    finally:
        live.LIVE_SOURCES.unregister("toy")
    assert live.schemes() == ("serial", "udp", "tcp", "sim")
