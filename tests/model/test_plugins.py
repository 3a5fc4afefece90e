"""The user's own effect (item 7): a file or an entry point adds an Effect that then works like a built-in
one in calibrate, diagnose, apply, the JSON and the command line; broken files give one clear message."""

import importlib.metadata
import importlib.util
import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

import magcal
from magcal.calibration.calibration import Calibration
from magcal.cli import main
from magcal.core.errors import MagcalError
from magcal.data import io
from magcal.model import plugins
from magcal.model.terms import EFFECTS

EXAMPLE = Path(__file__).resolve().parents[1] / "helpers" / "user_effects_example.py"
NAME = "pump_interference"
HIDDEN_SENSOR = 1  # 0-based: sensor 2
AMPLITUDE_NT = 4.0


@pytest.fixture(autouse=True)
def _own_catalogue(clean_catalogue):
    """Every test here starts and ends with magcal's own catalogue (tests/conftest.py)."""
    yield


@pytest.fixture(scope="module")
def hidden(tmp_path_factory):
    """chi2017 time series (four sensors, 3 nT noise) with the pump hidden in sensor 2, in memory and as CSV."""
    before = dict(EFFECTS)
    try:
        plugins.load_effects_file(EXAMPLE)
        effect = EFFECTS[NAME]()
        ds = magcal.simulate_timeseries(
            "chi2017", n_samples=1500, seed=3, perturbations=[effect.perturbation(AMPLITUDE_NT, HIDDEN_SENSOR)]
        )
        survey = magcal.simulate_timeseries(
            "chi2017", n_samples=300, seed=4, perturbations=[effect.perturbation(AMPLITUDE_NT, HIDDEN_SENSOR)]
        )
    finally:
        EFFECTS.clear()
        EFFECTS.update(before)
        plugins._ORIGINS.clear(), plugins._SOURCES.clear(), plugins._USER_FILES.clear()
    d = tmp_path_factory.mktemp("plugins")
    io.write_csv(d / "pump.csv", ds)
    io.write_csv(d / "survey.csv", survey)
    return {"ds": ds, "csv": d / "pump.csv", "survey": d / "survey.csv", "dir": d}


def run(argv, capsys):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def write(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(textwrap.dedent(text))
    return path


# ----------------------------------------------------------------------------------------------------------------
# loading
# ----------------------------------------------------------------------------------------------------------------


def test_loading_the_file_registers_the_effect():
    assert NAME not in EFFECTS
    names = plugins.load_effects_file(EXAMPLE)
    assert names == [NAME] and NAME in EFFECTS
    assert plugins.origin(NAME) == ("file", str(EXAMPLE.resolve()))
    assert not plugins.is_builtin(NAME) and plugins.is_builtin("temperature_bias")
    d = plugins.describe_effect(NAME)
    assert d["stage"] == "raw" and d["channels"] == ["time"] and d["per_sensor"] and d["simulator"]
    assert d["transferable"] is False and len(d["params"]) == 12
    assert {p["unit"] for p in d["params"]} == {"nT"} and d["params"][0]["symbol"] == "sin1_x"
    # the model builds it like a built-in one, by name and by NAME:S
    model = magcal.Model.from_names([NAME, "temperature_bias:2"], 4)
    assert model.effect_labels == [NAME, "temperature_bias:2"]
    assert magcal.model.terms.parse_effect(f"{NAME}:3", 4).sensor == 2
    # loading it again (after an edit) replaces it: same name, new class, no clash with itself
    old = EFFECTS[NAME]
    assert plugins.load_effects_file(EXAMPLE) == [NAME] and EFFECTS[NAME] is not old


def test_import_magcal_stays_light():
    code = "import sys, magcal; print('magcal.model.plugins' in sys.modules, 'pump_interference' in magcal.EFFECTS)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["False", "False"]


def test_parameter_units_are_read_from_the_names():
    assert plugins.split_param_name("beta_x_nT_per_K") == ("beta_x", "nT/K")
    assert plugins.split_param_name("gamma_z_nT_per_h") == ("gamma_z", "nT/h")
    assert plugins.split_param_name("Gxx_nT_per_m") == ("Gxx", "nT/m")
    assert plugins.split_param_name("delay_ms") == ("delay", "ms")
    assert plugins.split_param_name("weight") == ("weight", "")


# ----------------------------------------------------------------------------------------------------------------
# the loop with a user's effect: diagnose, calibrate, JSON, apply
# ----------------------------------------------------------------------------------------------------------------


def test_diagnose_finds_the_hidden_user_effect(hidden):
    plugins.load_effects_file(EXAMPLE)
    ds = hidden["ds"]
    result = magcal.calibrate(ds)
    diagnosis = magcal.diagnose(ds, result)
    best = diagnosis.candidates[0]
    assert best.effect == NAME and best.sensor == HIDDEN_SENSOR and best.refitted
    assert best.delta_bic < -100
    assert diagnosis.verdict == "missing_effect"
    assert f"{NAME}:{HIDDEN_SENSOR + 1}" in diagnosis.summary
    # the example is record-only: named as what the record holds, advised only if it leaves a better calibration
    assert diagnosis.to_dict()["record_holds"] == [f"{NAME}:{HIDDEN_SENSOR + 1}"]
    assert diagnosis.to_dict()["explained_by"] == ([f"{NAME}:{HIDDEN_SENSOR + 1}"] if best.transfers else [])


def test_without_the_file_the_diagnosis_cannot_name_it(hidden):
    diagnosis = magcal.diagnose(hidden["ds"], magcal.calibrate(hidden["ds"]))
    assert all(c.effect != NAME for c in diagnosis.candidates)
    assert diagnosis.verdict != "adequate"


def test_calibrate_with_the_user_effect_reaches_the_noise(hidden):
    plugins.load_effects_file(EXAMPLE)
    ds = hidden["ds"]
    base = magcal.calibrate(ds)
    label = f"{NAME}:{HIDDEN_SENSOR + 1}"
    with_pump = magcal.calibrate(ds, effects=[label])
    sigma = ds.noise_nT
    assert base.fit.rms_nT > 1.03 * with_pump.fit.rms_nT
    assert with_pump.fit.rms_nT < 1.01 * sigma
    # the fitted amplitude of the fundamental on each axis is the hidden one (4 nT along a unit direction)
    params = {p["term"]: p["params"] for p in with_pump.fit.effect_params}[label]
    amp = np.hypot([params[f"sin1_{a}_nT"] for a in "xyz"], [params[f"cos1_{a}_nT"] for a in "xyz"])
    d1 = np.abs(np.roll([0.8, -0.5, 0.33], HIDDEN_SENSOR))
    np.testing.assert_allclose(amp, AMPLITUDE_NT * d1 / np.linalg.norm(d1), atol=0.4)


def test_the_calibration_json_round_trips_with_the_file_and_refuses_clearly_without(hidden, tmp_path):
    plugins.load_effects_file(EXAMPLE)
    ds = hidden["ds"]
    result = magcal.calibrate(ds, effects=[f"{NAME}:{HIDDEN_SENSOR + 1}"])
    path = tmp_path / "cal.json"
    result.calibration.save(path)
    doc = json.loads(path.read_text())
    entry = [e for e in doc["effect_params"] if e["effect"] == NAME][0]
    assert entry["state"]["reference_time_s"] == float(ds.time_s[0]) and len(entry["params"]) == 12
    loaded = Calibration.load(path)
    np.testing.assert_allclose(loaded.correct(ds), result.calibration.correct(ds), atol=1e-9)

    plugins.unregister(NAME)  # a new session that has not loaded the file
    with pytest.raises(MagcalError, match=NAME):
        Calibration.load(path)
    with pytest.raises(MagcalError) as err:
        plugins.check_calibration_effects(path)
    assert NAME in str(err.value) and "--effects-file" in str(err.value)
    with pytest.raises(MagcalError, match="built-in"):
        plugins.unregister("temperature_bias")


# ----------------------------------------------------------------------------------------------------------------
# the command line, in-process
# ----------------------------------------------------------------------------------------------------------------


def test_cli_diagnose_with_the_effects_file(hidden, capsys):
    code, out, err = run(["diagnose", hidden["csv"], "--effects-file", EXAMPLE], capsys)
    assert code == 0, err
    assert f"missing {NAME}:{HIDDEN_SENSOR + 1}" in out
    code, out, err = run(["diagnose", hidden["csv"], "--effects-file", EXAMPLE, "--json"], capsys)
    assert code == 0, err
    doc = json.loads(out)
    assert doc["verdict"] == "missing_effect" and doc["candidates"][0]["effect"] == NAME
    assert doc["candidates"][0]["sensor"] == HIDDEN_SENSOR + 1


def test_cli_calibrate_then_apply_with_the_effect(hidden, tmp_path, capsys):
    cal = tmp_path / "cal.json"
    label = f"{NAME}:{HIDDEN_SENSOR + 1}"
    code, out, err = run(
        ["calibrate", hidden["csv"], "--effects-file", EXAMPLE, "--effects", label, "-o", cal, "--json"], capsys
    )
    assert code == 0, err
    doc = json.loads(out)
    assert doc["effects"] == [label] and json.loads(cal.read_text())["effects"] == [label]
    out_csv = tmp_path / "survey_cal.csv"
    code, out, err = run(
        ["apply", cal, hidden["survey"], "-o", out_csv, "--no-progress", "--effects-file", EXAMPLE], capsys
    )
    assert code == 0, err
    header = [line for line in out_csv.read_text().splitlines() if not line.startswith("#")][0]
    assert "s2x_cal" in header.split(",")


def test_cli_refuses_the_effect_without_its_file(hidden, tmp_path, capsys):
    plugins.load_effects_file(EXAMPLE)
    cal = tmp_path / "cal.json"
    magcal.calibrate(hidden["ds"], effects=[NAME]).calibration.save(cal)
    plugins.unregister(NAME)
    code, out, err = run(["apply", cal, hidden["survey"], "-o", tmp_path / "o.csv", "--no-progress"], capsys)
    assert code == 2 and "Traceback" not in err
    assert f"'{NAME}'" in err and "--effects-file" in err and str(cal) in err
    assert not (tmp_path / "o.csv").exists()
    code, out, err = run(["calibrate", hidden["csv"], "--effects", NAME], capsys)
    assert code == 2 and "Traceback" not in err and f"'{NAME}'" in err and "--effects-file" in err


def test_cli_effects_lists_the_catalogue_with_the_source(capsys):
    code, out, err = run(["effects", "--effects-file", EXAMPLE], capsys)
    assert code == 0, err
    assert "temperature_bias  (built-in)" in out and f"{NAME}  (file {EXAMPLE.resolve()})" in out
    assert "beta_x, beta_y, beta_z [nT/K]" in out and "record-only" in out
    code, out, err = run(["effects", "--json", "--effects-file", EXAMPLE], capsys)
    entries = {e["name"]: e for e in json.loads(out)["effects"]}
    assert entries[NAME]["origin"] == "file" and entries["temperature_bias"]["origin"] == "built-in"
    assert set(entries) == set(EFFECTS)
    code, out, err = run(["effects", NAME, "--effects-file", EXAMPLE], capsys)
    assert code == 0 and "f0 = 1.3 Hz" in out and "t0" in out
    plugins.unregister(NAME)
    code, out, err = run(["effects", NAME], capsys)  # not loaded
    assert code == 2 and "--effects-file" in err


RECORD_ONLY = {"bias_drift", "bias_step", "reference_drift", "site_gradient"}


@pytest.mark.parametrize(
    "name",
    [
        "temperature_bias",
        "temperature_scale",
        "nonlinearity_quadratic",
        "nonlinearity_cubic",
        "axis_timing_skew",
        "sensor_timing_skew",
        "hysteresis",
        *sorted(RECORD_ONLY),
    ],
)
def test_catalogue_says_which_terms_carry_to_new_data(name, capsys):
    """Instrument terms carry to new data; a term of one recording (drift since power-on, a step, the field's
    drift, the site's gradient) does not: the class, describe_effect, the listing and its JSON agree."""
    expected = name not in RECORD_ONLY
    assert EFFECTS[name].transferable is expected
    assert plugins.describe_effect(name)["transferable"] is expected
    code, out, err = run(["effects", "--json"], capsys)
    assert code == 0, err
    assert {e["name"]: e for e in json.loads(out)["effects"]}[name]["transferable"] is expected
    code, out, err = run(["effects", name], capsys)
    assert code == 0, err
    assert ("instrument (carries to new data)" if expected else "record-only (this recording only)") in out


def test_an_effect_that_does_not_say_is_an_instrument_term(tmp_path):
    """The default of magcal.model.terms.Effect: a term describes the instrument unless its class says otherwise."""
    path = write(tmp_path, "offset.py", HEADER + GOOD_CLASS.format(name="offset", stage="raw"))
    plugins.load_effects_file(path)
    assert plugins.describe_effect("offset")["transferable"] is True
    plugins.load_effects_file(EXAMPLE)
    assert plugins.describe_effect(NAME)["transferable"] is False  # the example says it is record-only


def test_cli_simulate_can_hide_the_user_effect(tmp_path, capsys):
    path = tmp_path / "s.csv"
    code, out, err = run(
        ["simulate", "--hidden", f"{NAME}:2=3", "--n", "200", "-o", path, "--effects-file", EXAMPLE], capsys
    )
    assert code == 0, err
    assert f"hidden: {NAME} 3.0 nT at 1.3 Hz (sensor 2)" in out and io.read_csv(path).n_samples == 200


# ----------------------------------------------------------------------------------------------------------------
# broken files: one clear message, exit 2, no traceback, the catalogue unchanged
# ----------------------------------------------------------------------------------------------------------------

GOOD_CLASS = """
    @register
    @dataclass
    class Offset(Effect):
        name: ClassVar[str] = "{name}"
        stage: ClassVar[str] = "{stage}"
        def param_names(self):
            return ["o_x_nT", "o_y_nT", "o_z_nT"]
        def raw_basis(self, z0, ctx):
            return np.broadcast_to(np.eye(3), (len(z0), 3, 3)).copy()
"""
HEADER = """
    from dataclasses import dataclass
    from typing import ClassVar
    import numpy as np
    from magcal.model.terms import Effect, register
"""

BROKEN = {
    "syntax": (
        HEADER
        + """
    @register
    class Broken(Effect):
        name = "broken"
        def param_names(self)
            return ["a_nT"]
    """,
        ["line 10", "syntax error", "def param_names(self)"],
    ),
    "no_param_names": (
        HEADER
        + """
    @register
    @dataclass
    class NoParams(Effect):
        name: ClassVar[str] = "no_params"
        def raw_basis(self, z0, ctx):
            return np.zeros((len(z0), 3, 1))
    """,
        ["line 7", "effect class NoParams", "no param_names()"],
    ),
    "clash": (
        HEADER + GOOD_CLASS.format(name="temperature_bias", stage="raw"),
        ["line 7", "'temperature_bias' is already a built-in effect", "another name"],
    ),
    "base_term": (HEADER + GOOD_CLASS.format(name="bias", stage="raw"), ["'bias' is a base term"]),
    "bad_name": (HEADER + GOOD_CLASS.format(name="Pump-2", stage="raw"), ["cannot be typed", "lower-case"]),
    "bad_stage": (
        HEADER + GOOD_CLASS.format(name="offset", stage="field"),
        ["stage 'field' is not one of raw, array, reference"],
    ),
    "wrong_basis_method": (
        HEADER + GOOD_CLASS.format(name="offset", stage="array"),
        ["stage is 'array' but the class does not define array_basis()"],
    ),
    "wrong_basis_method_former_stage_name": (
        HEADER + GOOD_CLASS.format(name="offset", stage="vector"),
        ["stage is 'array' but the class does not define array_basis()"],
    ),
    "not_registered": (
        HEADER.replace("import Effect, register", "import Effect")
        + """
    class Lonely(Effect):
        name = "lonely"
    """,
        ["registers no effect", "Lonely", "@register"],
    ),
    "raises": (
        HEADER
        + """
    GAIN = 1 / 0
    """,
        ["line 7", "ZeroDivisionError", "GAIN = 1 / 0"],
    ),
    "missing_import": (
        """
    import numpy as np
    import pumpcontrol_sdk
    """,
        ["line 3", "cannot import", "pumpcontrol_sdk"],
    ),
    "basis_shape": (
        HEADER
        + """
    @register
    @dataclass
    class Flat(Effect):
        name: ClassVar[str] = "flat"
        def param_names(self):
            return ["a_nT", "b_nT"]
        def raw_basis(self, z0, ctx):
            return np.zeros((len(z0), 3))
    """,
        ["effect class Flat", "raw_basis returned shape (240, 3)", "(240, 3, 2)"],
    ),
    "unknown_channel": (
        HEADER
        + """
    @register
    @dataclass
    class Motor(Effect):
        name: ClassVar[str] = "motor"
        channels: ClassVar[tuple] = ("motor_current",)
        def param_names(self):
            return ["k_x_nT_per_A"]
        def raw_basis(self, z0, ctx):
            return np.zeros((len(z0), 3, 1))
    """,
        ["unknown channel(s) 'motor_current'", "time, temperature"],
    ),
    "basis_raises": (
        HEADER
        + """
    @register
    @dataclass
    class Typo(Effect):
        name: ClassVar[str] = "typo"
        def param_names(self):
            return ["a_nT"]
        def raw_basis(self, z0, ctx):
            return np.zeros((len(z0), 3, 1)) * ctx.temprature_C
    """,
        ["effect class Typo", "AttributeError", "temprature_C", "line 14"],
    ),
}


@pytest.mark.parametrize("case", sorted(BROKEN))
def test_a_broken_effects_file_gives_one_clear_message(case, tmp_path, capsys):
    text, needles = BROKEN[case]
    path = write(tmp_path, f"{case}.py", text)
    before = dict(EFFECTS)
    code, out, err = run(["effects", "--effects-file", path], capsys)
    assert code == 2, (out, err)
    assert "Traceback" not in err and err.startswith("magcal effects: error: ")
    assert str(path) in err
    for needle in needles:
        assert needle in err, (needle, err)
    assert EFFECTS == before  # nothing of the broken file stays in the catalogue
    with pytest.raises(plugins.UserEffectError):
        plugins.load_effects_file(path)
    assert EFFECTS == before


def test_missing_or_wrong_effects_file(tmp_path, capsys):
    code, out, err = run(["effects", "--effects-file", tmp_path / "nope.py"], capsys)
    assert code == 2 and "no such effects file" in err
    (tmp_path / "e.txt").write_text("x = 1\n")
    code, out, err = run(["effects", "--effects-file", tmp_path / "e.txt"], capsys)
    assert code == 2 and "must be a Python file" in err


def test_two_files_may_not_claim_one_name(tmp_path):
    a = write(tmp_path, "a.py", HEADER + GOOD_CLASS.format(name="offset", stage="raw"))
    b = write(tmp_path, "b.py", HEADER + GOOD_CLASS.format(name="offset", stage="raw"))
    assert plugins.load_effects_file(a) == ["offset"]
    with pytest.raises(plugins.UserEffectError, match=r"already taken by the effect from file .*a\.py"):
        plugins.load_effects_file(b)
    assert plugins.origin("offset") == ("file", str(a))


def test_an_error_in_the_user_code_during_a_fit_names_the_file_and_line(tmp_path, capsys):
    # the user forgot to declare the temperature channel: the dry run has it, this recording does not
    path = write(
        tmp_path,
        "warm.py",
        HEADER
        + """
    @register
    @dataclass
    class Warm(Effect):
        name: ClassVar[str] = "warm_offset"
        def param_names(self):
            return ["w_x_nT_per_K", "w_y_nT_per_K", "w_z_nT_per_K"]
        def raw_basis(self, z0, ctx):
            dT = ctx.temperature_C - 20.0
            return np.eye(3)[None] * dT[:, None, None]
    """,
    )
    ds = magcal.simulate_timeseries("chi2017", n_samples=300, seed=2)
    data = tmp_path / "no_temperature.csv"
    io.write_csv(data, ds.replace(temperature_C=None))
    code, out, err = run(["calibrate", data, "--effects-file", path, "--effects", "warm_offset"], capsys)
    assert code == 2 and "Traceback" not in err
    assert f"{path}, line 14, in raw_basis: TypeError" in err and "dT = ctx.temperature_C - 20.0" in err
    assert "your effect's code" in err


# ----------------------------------------------------------------------------------------------------------------
# entry points
# ----------------------------------------------------------------------------------------------------------------


class FakeEntryPoint:
    """What importlib.metadata returns for a package's ``[project.entry-points."magcal.model.effects"]`` line."""

    def __init__(self, name, value, load, dist="pump-effects"):
        self.name, self.value, self.group, self._load = name, value, plugins.ENTRY_POINT_GROUP, load
        self.dist = type("Dist", (), {"name": dist})()

    def load(self):
        return self._load()


def _import_example_as(module_name):
    spec = importlib.util.spec_from_file_location(module_name, EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    sys.modules[module_name] = module
    spec.loader.exec_module(module)  # its @register runs here, as when a package is imported
    return module


def test_entry_points_are_loaded_once_and_a_broken_one_is_skipped(monkeypatch, tmp_path, capsys):
    module_dir = tmp_path / "site"
    module_dir.mkdir()
    (module_dir / "coil_effects_pkg.py").write_text(
        textwrap.dedent(HEADER + GOOD_CLASS.format(name="coil_offset", stage="raw"))
    )
    monkeypatch.syspath_prepend(str(module_dir))
    monkeypatch.delitem(sys.modules, "coil_effects_pkg", raising=False)
    monkeypatch.delitem(sys.modules, "pump_effects_pkg", raising=False)

    def broken():
        raise ImportError("libpump.so: cannot open shared object file")

    eps = [
        FakeEntryPoint(
            "pump", "pump_effects_pkg:PumpInterference", lambda: _import_example_as("pump_effects_pkg").PumpInterference
        ),
        importlib.metadata.EntryPoint(name="coil", value="coil_effects_pkg", group=plugins.ENTRY_POINT_GROUP),
        FakeEntryPoint("broken", "broken_pkg:Effect", broken, dist="broken-pkg"),
        FakeEntryPoint("clash", "clash_pkg:X", lambda: type("X", (EFFECTS["temperature_bias"],), {})),
    ]
    calls = []

    def entry_points(**kw):
        calls.append(kw)
        return eps if kw.get("group") == plugins.ENTRY_POINT_GROUP else []

    monkeypatch.setattr(importlib.metadata, "entry_points", entry_points)
    with pytest.warns(UserWarning) as caught:
        names = plugins.load_entry_points()
    assert sorted(names) == ["coil_offset", NAME]
    messages = [str(w.message) for w in caught]
    assert any(
        "skipped the effect entry point broken = broken_pkg:Effect (broken-pkg)" in m and "libpump" in m
        for m in messages
    )
    assert any("clash" in m and "built-in" in m for m in messages)
    assert plugins.origin(NAME) == ("entry point", "pump = pump_effects_pkg:PumpInterference (pump-effects)")
    assert plugins.origin("coil_offset")[0] == "entry point"
    assert EFFECTS["temperature_bias"].__module__ == "magcal.model.effects"
    assert plugins.load_entry_points() == [] and len(calls) == 1  # once

    # the command line loads them at start (here already loaded) and lists where each came from
    code, out, err = run(["effects"], capsys)
    assert code == 0 and f"{NAME}  (entry point pump = pump_effects_pkg:PumpInterference (pump-effects))" in out


@pytest.mark.parametrize(
    "stage, method",
    [("array", "array_basis"), ("vector", "vector_basis")],  # the array stage's former names are read as it
)
def test_array_and_reference_stage_effects_load_and_fit(tmp_path, stage, method):
    path = write(
        tmp_path,
        "stages.py",
        HEADER
        + '''
    @register
    @dataclass
    class Lever(Effect):
        """A field along the array's z axis growing with time (an array-stage term)."""
        name: ClassVar[str] = "lever_field"
        stage: ClassVar[str] = "STAGE"
        channels: ClassVar[tuple] = ("time",)
        per_sensor: ClassVar[bool] = False
        def param_names(self):
            return ["kz_nT_per_h"]
        def METHOD(self, field_nT, ctx):
            basis = np.zeros((len(field_nT), 3, 1))
            basis[:, 2, 0] = (ctx.time_s - ctx.time_s.mean()) / 3600.0
            return basis

    @register
    @dataclass
    class Ramp(Effect):
        """The total field changes linearly in time (a reference-stage term)."""
        name: ClassVar[str] = "field_ramp"
        stage: ClassVar[str] = "reference"
        channels: ClassVar[tuple] = ("time",)
        per_sensor: ClassVar[bool] = False
        def param_names(self):
            return ["ramp_nT_per_h"]
        def reference_basis(self, ctx):
            return ((ctx.time_s - ctx.time_s.mean()) / 3600.0)[:, None]
    ''',
    )
    path.write_text(path.read_text().replace('"STAGE"', f'"{stage}"').replace("METHOD", method))
    assert plugins.load_effects_file(path) == ["lever_field", "field_ramp"]
    assert EFFECTS["lever_field"].stage == "array"
    ds = magcal.simulate_timeseries("chi2017", n_samples=300, seed=2)
    result = magcal.calibrate(ds, effects=["lever_field", "field_ramp"])
    assert result.fit.rms_nT < 1.05 * ds.noise_nT
    assert {p["term"] for p in result.fit.effect_params} == {"lever_field", "field_ramp"}
    # the file edited: one effect renamed; loading it again drops the old name
    path.write_text(path.read_text().replace('"field_ramp"', '"field_trend"'))
    assert plugins.load_effects_file(path) == ["lever_field", "field_trend"]
    assert "field_ramp" not in EFFECTS and "field_trend" in EFFECTS


# ----------------------------------------------------------------------------------------------------------------
# the user's effect in worker processes (magcal apply --workers)
# ----------------------------------------------------------------------------------------------------------------


def test_a_parallel_apply_loads_the_users_effect_in_its_workers(hidden, tmp_path, capsys):
    """The local cluster's workers do not share this process's catalogue: each task loads the effects file the
    calibration's effect came from, and the partitions equal the single-process apply row for row (on the fitted
    record itself, so the record-only pump term is evaluated in the workers)."""
    pytest.importorskip("distributed")
    pytest.importorskip("pyarrow")
    import pyarrow.dataset as pads
    import pyarrow.parquet as pq

    cal = tmp_path / "cal.json"
    opt = ["--effects-file", EXAMPLE]
    assert run(["calibrate", hidden["csv"], "--effects", NAME, "-o", cal, *opt], capsys)[0] == 0
    single, parts = tmp_path / "single.parquet", tmp_path / "parts"
    assert run(["apply", cal, hidden["csv"], "-o", single, "--no-progress", *opt], capsys)[0] == 0
    argv = ["apply", cal, hidden["csv"], "-o", parts, "--workers", "1", "--partition-rows", "500", "--no-progress"]
    code, out, err = run([*argv, *opt], capsys)
    assert code == 0 and "Traceback" not in err and "unknown effect" not in err, err
    got, want = pads.dataset(parts).to_table(), pq.read_table(single)
    assert got.num_rows == want.num_rows == hidden["ds"].n_samples
    for name in ("s1x_cal", "s2y_cal", "s4z_cal", "Gxy"):
        np.testing.assert_allclose(got.column(name).to_numpy(), want.column(name).to_numpy(), rtol=0, atol=1e-9)
    raw = want.column("s2y").to_numpy() - want.column("s2y_cal").to_numpy()
    assert np.ptp(raw) > 0  # the corrected column is not the reading


def test_a_worker_without_the_effects_file_says_where_it_must_be(tmp_path):
    with pytest.raises(plugins.UserEffectError, match="not on the file system of the worker on .*where every worker"):
        plugins.load_for_worker([NAME], [str(tmp_path / "elsewhere" / "my_effects.py")])


def test_a_worker_loads_an_effects_file_once_until_it_changes(tmp_path, monkeypatch):
    monkeypatch.setattr(plugins, "_WORKER_FILES", {})
    path = tmp_path / "mine.py"
    path.write_text(EXAMPLE.read_text())
    loads = []
    real = plugins.load_effects_file
    monkeypatch.setattr(plugins, "load_effects_file", lambda p: loads.append(p) or real(p))
    for _ in range(3):
        plugins.load_for_worker([NAME], [str(path)])
    assert NAME in EFFECTS and len(loads) == 1
    path.write_text(EXAMPLE.read_text() + "\n# edited\n")
    plugins.load_for_worker([NAME], [str(path)])
    assert len(loads) == 2


def test_a_diagnosis_given_a_cluster_keeps_a_users_effect_on_this_machine_and_says_so(hidden):
    """A cluster's workers could not unpickle the user's effect class: the fits run here (the unreachable address
    is never contacted) and the diagnosis says why; without the user's effect the same call means Dask."""
    from magcal.diagnosis import _parallel

    plugins.load_effects_file(EXAMPLE)
    res = magcal.calibrate(hidden["ds"])
    d = magcal.diagnosis.diagnose(hidden["ds"], res, scheduler="tcp://127.0.0.1:1")
    assert _parallel.ELSEWHERE_NOTE in [n.text for n in d.notes]
    assert d.candidates and d.candidates[0].effect == NAME  # the hidden pump, found by the fits made here
    assert _parallel.backend_for(hidden["ds"], scheduler="tcp://127.0.0.1:1", effects=[EFFECTS[NAME]]) == "threads"
    assert _parallel.backend_for(hidden["ds"], scheduler="tcp://127.0.0.1:1", effects=[EFFECTS["bias_drift"]]) == "dask"
