"""CONTRIBUTING.md's recipes, each walked through from a temporary file: a toy effect, a toy export format, a toy
live source, a toy fit mode and a toy command, added the way the recipe says and then used through the command line
(the fit mode also through :func:`magcal.calibrate`), and a toy workbench panel, built in a headless workbench and
driven.

The effect comes from a file given with ``--effects-file``; the export format, the live source, the fit mode and the
command from a temporary *installed distribution* (a folder on ``PYTHONPATH`` with a ``.dist-info`` holding
``entry_points.txt``), which is how a package outside magcal adds them: the entry-point groups
``magcal.export_formats``, ``magcal.live_sources``, ``magcal.fit_modes`` and ``magcal.commands``. The commands run in a fresh process,
as a user runs them. Each toy's output is checked against what it must be (the calibration's own numbers, the
synthetic lines' values), not against a recorded copy. The panel comes from an installed distribution too (the
entry-point group ``magcal_workbench.panels``), loaded in this process as ``magcal-workbench`` loads it at start.
"""

from __future__ import annotations

import json
import os
import pathlib
import subprocess
import sys
import textwrap

import numpy as np
import pytest

import magcal
from magcal.calibration.calibration import Calibration
from magcal.data.io import read_csv

ROOT = pathlib.Path(__file__).resolve().parents[2]


def install_distribution(site: pathlib.Path, modules: dict, entry_points: dict, summary: str) -> pathlib.Path:
    """A distribution ``magcal-toys`` installed into the folder ``site``: its modules (``name -> source``) and a
    ``.dist-info`` declaring ``entry_points`` (``group -> {name: value}``)."""
    site.mkdir(parents=True, exist_ok=True)
    for name, source in modules.items():
        (site / f"{name}.py").write_text(textwrap.dedent(source), encoding="utf-8")
    info = site / "magcal_toys-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(
        f"Metadata-Version: 2.1\nName: magcal-toys\nVersion: 0.1\nSummary: {summary}\n", encoding="utf-8"
    )
    lines = []
    for group, points in entry_points.items():
        lines.append(f"[{group}]")
        lines += [f"{name} = {value}" for name, value in points.items()]
        lines.append("")
    (info / "entry_points.txt").write_text("\n".join(lines), encoding="utf-8")
    return site


def magcal_cli(args, site=None, code=None, timeout=180):
    """Run ``magcal ARGS`` (or ``python -c CODE ARGS``) in a fresh process that sees the distribution in ``site``."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(p) for p in (site, ROOT) if p] + [env.get("PYTHONPATH", "")])
    command = [sys.executable, "-m", "magcal"] if code is None else [sys.executable, "-c", code]
    return subprocess.run(
        command + [str(a) for a in args], capture_output=True, text=True, timeout=timeout, env=env, cwd=site or ROOT
    )


@pytest.fixture(scope="module")
def calibration_file(tmp_path_factory):
    """A calibration of the chi2017 array (four sensors), saved as JSON."""
    path = tmp_path_factory.mktemp("recipes") / "cal.json"
    magcal.calibrate(magcal.simulate("chi2017", seed=1)).calibration.save(path)
    return path


# ----------------------------------------------------------------------------------------------------------------
# an effect (CONTRIBUTING: "an effect"; a user's own in their file, docs/user-effects.md)
# ----------------------------------------------------------------------------------------------------------------

TOY_EFFECT = '''
    """A toy effect: a bias that grows linearly with time, y += r (t / 60 s), r per axis in nT/min."""

    from dataclasses import dataclass
    from typing import ClassVar

    import numpy as np

    from magcal.model import Context, Effect, register

    DIRECTION = np.array([0.6, -0.48, 0.64])


    @register
    @dataclass
    class ToyRamp(Effect):
        """A bias growing with time: ``y += r t / 60``, ``r`` per axis in nT/min."""

        name: ClassVar[str] = "toy_ramp"
        stage: ClassVar[str] = "raw"
        channels: ClassVar[tuple] = ("time",)
        per_sensor: ClassVar[bool] = True
        description: ClassVar[str] = "a bias growing linearly with time [nT/min per axis]"
        transferable: ClassVar[bool] = False

        def param_names(self):
            return [f"r_{a}_nT_per_min" for a in "xyz"]

        def param_scale(self):
            return np.ones(3)

        def raw_basis(self, z0, ctx: Context):
            basis = np.zeros((len(ctx.time_s), 3, 3))
            for axis in range(3):
                basis[:, axis, axis] = ctx.time_s / 60.0
            return basis

        def perturbation(self, magnitude=None, sensor=None):
            rate = 20.0 if magnitude is None else float(magnitude)

            def perturb(readings, context, rng):
                readings = np.array(readings, dtype=float)
                for s in range(readings.shape[0]) if sensor is None else [sensor]:
                    readings[s] += rate * (context["time_s"] / 60.0)[:, None] * DIRECTION
                return readings

            perturb.description = f"toy_ramp {rate} nT/min"
            perturb.effect, perturb.sensor, perturb.magnitude = self.name, sensor, rate
            return perturb
'''


def test_recipe_effect_from_a_file_is_listed_and_its_fit_finds_the_hidden_ramp(tmp_path, clean_catalogue):
    from magcal.model import plugins
    from magcal.model.terms import EFFECTS

    path = tmp_path / "toy_effects.py"
    path.write_text(textwrap.dedent(TOY_EFFECT), encoding="utf-8")
    listed = magcal_cli(["effects", "--effects-file", path])
    assert listed.returncode == 0, listed.stderr
    assert "toy_ramp" in listed.stdout and "file" in listed.stdout

    assert plugins.load_effects_file(path) == ["toy_ramp"]
    rate = 20.0  # nT/min along DIRECTION, hidden in sensor 2
    ds = magcal.simulate_timeseries(
        "chi2017", n_samples=3000, seed=3, perturbations=[EFFECTS["toy_ramp"]().perturbation(rate, 1)]
    )
    result = magcal.calibrate(ds, effects=["toy_ramp:2"])
    params = {p["term"]: p["params"] for p in result.fit.effect_params}["toy_ramp:2"]
    found = np.array([params[f"r_{a}_nT_per_min"] for a in "xyz"])
    np.testing.assert_allclose(found, rate * np.array([0.6, -0.48, 0.64]), atol=1.5)
    assert result.fit.rms_nT < 1.02 * ds.noise_nT


# ----------------------------------------------------------------------------------------------------------------
# an export format (CONTRIBUTING: "an export format")
# ----------------------------------------------------------------------------------------------------------------

TOY_FORMAT = '''
    """A toy export format: each sensor's bias (nT) as JSON."""

    import json

    from magcal.core.errors import MagcalError
    from magcal.output.formats import Export, ExportFormat


    def write(calibration, sensors=None, slots=None, force=False, source="calibration", **options):
        if calibration.model is not None and calibration.model.effects and not force:
            raise MagcalError(f"{source}: toy-json holds biases only; pass --force to leave the effects out")
        chosen = sensors or range(1, calibration.n_sensors + 1)
        biases = {f"s{s}": [float(v) for v in calibration.sensors[s - 1].bias_nT] for s in chosen}
        return Export("toy-json", json.dumps(biases) + "\\n", {}, list(chosen))


    TOY = ExportFormat(
        name="toy-json",
        title="toy JSON biases",
        description="each sensor's bias in nT as one JSON object",
        file_name="biases.json",
        button="Biases (JSON)",
        refuses="candidate effects (unless forced)",
        writer=write,
    )
'''


def test_recipe_export_format_from_an_installed_package(tmp_path, calibration_file):
    site = install_distribution(
        tmp_path / "site",
        {"toy_format": TOY_FORMAT},
        {"magcal.export_formats": {"toy-json": "toy_format:TOY"}},
        "toy export format",
    )
    help_text = magcal_cli(["export", "--help"], site).stdout
    assert "toy-json" in help_text and "ardupilot" in help_text

    out = magcal_cli(["export", calibration_file, "--format", "toy-json"], site)
    assert out.returncode == 0, out.stderr
    calibration = Calibration.load(calibration_file)
    written = json.loads(out.stdout)
    assert sorted(written) == [f"s{s}" for s in range(1, calibration.n_sensors + 1)]
    for s, sensor in enumerate(calibration.sensors, start=1):
        np.testing.assert_allclose(written[f"s{s}"], sensor.bias_nT, rtol=1e-12)

    # the bundle lists the registry: the toy's file is in the zip, with its title in the README
    data = tmp_path / "data.csv"
    magcal_cli(["simulate", "--preset", "chi2017", "--seed", "1", "-o", data], site)
    zipped = magcal_cli(["export", calibration_file, "--format", "all", "--data", data, "-o", tmp_path / "a.zip"], site)
    assert zipped.returncode == 0, zipped.stderr
    import zipfile

    with zipfile.ZipFile(tmp_path / "a.zip") as zf:
        assert json.loads(zf.read("biases.json")) == written
        assert "biases.json: toy JSON biases" in zf.read("README.txt").decode()


# ----------------------------------------------------------------------------------------------------------------
# a live source (CONTRIBUTING: "a live source")
# ----------------------------------------------------------------------------------------------------------------

TOY_SOURCE = '''
    """A toy live source: ``toy://?n=N`` sends N synthetic text lines ``t,x,y,z`` from a pseudo-file in memory."""

    import io

    from magcal.data.live import LineSource, SourceKind, register_source


    def line(k):
        return f"{0.02 * k:.2f},{1000.0 + k},{-2000.0 + 2 * k},{40000.0 - 3 * k}\\n"


    class ToySource(LineSource):
        def __init__(self, url, parser, n):
            super().__init__(url, parser)
            self._file = io.BytesIO("".join(line(k) for k in range(n)).encode())

        def _receive(self, timeout_s):
            data = self._file.read(64)  # a few lines at a time, as a port delivers them
            if not data:
                self._eof = True
            return data


    def open_toy(url):
        url.params.setdefault("columns", "t,x,y,z")
        return ToySource(url.url, url.line_parser(), url.number("n", 10, int, (1, 100000)))


    TOY = register_source(
        SourceKind(
            name="toy",
            schemes=("toy",),
            description="synthetic lines from memory",
            forms=("toy://",),
            example="toy://?n=10",
            options=("n", "columns"),
            opener=open_toy,
        )
    )
'''


def test_recipe_live_source_from_an_installed_package_records_its_lines(tmp_path):
    site = install_distribution(
        tmp_path / "site",
        {"toy_source": TOY_SOURCE},
        {"magcal.live_sources": {"toy": "toy_source"}},  # a module that registers its source
        "toy live source",
    )
    assert "toy://" in magcal_cli(["record", "--help"], site).stdout
    out = magcal_cli(["record", "toy://?n=120", tmp_path / "rec.csv", "--seconds", "20"], site)
    assert out.returncode == 0, out.stderr
    ds = read_csv(tmp_path / "rec.csv")
    k = np.arange(120)
    np.testing.assert_allclose(ds.time_s, 0.02 * k, atol=1e-9)
    np.testing.assert_allclose(ds.readings_nT[0], np.c_[1000.0 + k, -2000.0 + 2 * k, 40000.0 - 3 * k], rtol=1e-9)
    # without the package the scheme is unknown, and the message lists the built-in forms
    refused = magcal_cli(["record", "toy://?n=5", tmp_path / "no.csv", "--seconds", "1"])
    assert refused.returncode == 2 and "unknown source" in refused.stderr and "sim://PRESET" in refused.stderr


# ----------------------------------------------------------------------------------------------------------------
# a command (CONTRIBUTING: "a command"; from outside magcal: the entry-point group magcal.commands)
# ----------------------------------------------------------------------------------------------------------------

TOY_COMMAND = '''
    """``magcal toy-biases CAL.json``: print each sensor's bias length (nT)."""

    import numpy as np


    def register(subparsers):
        parser = subparsers.add_parser("toy-biases", help="print each sensor's bias length")
        parser.add_argument("calibration")
        parser.set_defaults(func=run)
        return parser


    def run(args):
        from magcal.calibration.calibration import Calibration

        cal = Calibration.load(args.calibration)
        for s, sensor in enumerate(cal.sensors, start=1):
            print(f"s{s} {float(np.linalg.norm(sensor.bias_nT)):.6f}")
        return 0
'''


def test_recipe_command_from_an_installed_package(tmp_path, calibration_file):
    site = install_distribution(
        tmp_path / "site",
        {"toy_command": TOY_COMMAND},
        {"magcal.commands": {"toy-biases": "toy_command"}},
        "print bias lengths",
    )
    code = (
        "import sys; from magcal.cli import main\n"
        "try:\n    main(sys.argv[1:])\nexcept SystemExit:\n    pass\n"
        "print('toy_command' in sys.modules)"
    )
    listed = magcal_cli(["--help"], site, code=code)
    assert "toy-biases" in listed.stdout and "print bias lengths (magcal-toys)" in listed.stdout
    assert listed.stdout.strip().splitlines()[-1] == "False"  # listed without importing it

    out = magcal_cli(["toy-biases", calibration_file], site)
    assert out.returncode == 0, out.stderr
    calibration = Calibration.load(calibration_file)
    expected = [f"s{s} {np.linalg.norm(c.bias_nT):.6f}" for s, c in enumerate(calibration.sensors, start=1)]
    assert out.stdout.split("\n")[: len(expected)] == expected
    # a built-in command never looks the entry points up, and a broken one is one clear line
    (site / "toy_command.py").write_text("raise RuntimeError('broken on purpose')\n", encoding="utf-8")
    broken = magcal_cli(["toy-biases", calibration_file], site)
    assert broken.returncode == 2 and "cannot be imported" in broken.stderr and "Traceback" not in broken.stderr
    assert magcal_cli(["effects"], site).returncode == 0


# ----------------------------------------------------------------------------------------------------------------
# a fit mode (CONTRIBUTING: "a fit mode")
# ----------------------------------------------------------------------------------------------------------------

TOY_MODE = '''
    """A toy fit mode: each sensor's bias alone, the centre of the sphere its readings lie on (linear least squares
    on |y|^2 = 2 y . b + (F^2 - |b|^2))."""

    import numpy as np

    from magcal.calibration.calibration import Calibration, SensorCalibration
    from magcal.core.errors import CalibrationError
    from magcal.fitting.result import ModeResult
    from magcal.modes import FIT_MODES, FitMode


    class CentreResult(ModeResult):
        mode = "toy"

        def __init__(self, calibration, field_nT):
            self.calibration = calibration
            self.field_nT = field_nT
            self.notes = []

        def text(self):
            lines = [f"toy fit: the field {self.field_nT:.1f} nT"]
            lines += [f"  s{k + 1} bias {np.round(s.bias_nT, 1).tolist()} nT" for k, s in enumerate(self.calibration.sensors)]
            return "\\n".join(lines) + "\\n"

        def to_dict(self):
            return {
                "mode": self.mode,
                "field_nT": self.field_nT,
                "bias_nT": [s.bias_nT.tolist() for s in self.calibration.sensors],
            }


    class CentreMode(FitMode):
        name = "toy"
        title = "bias-only fit (the centre of the sphere)"
        priority = -10  # auto never takes it: the total-field fit (0) is always applicable

        def needs(self):
            return "needs at least 4 samples per sensor, turned through many directions"

        def applicable(self, dataset, **options):
            return None if dataset.n_samples >= 4 else f"needs at least 4 samples (the record has {dataset.n_samples})"

        def fit(self, dataset):
            sensors, fields = [], []
            for y in np.asarray(dataset.readings_nT, float):
                design = np.c_[2 * y, np.ones(len(y))]
                solution, *_ = np.linalg.lstsq(design, np.sum(y**2, axis=1), rcond=None)
                bias = solution[:3]
                if not solution[3] + bias @ bias > 0:
                    raise CalibrationError("the readings do not lie on a sphere")
                sensors.append(SensorCalibration(np.eye(3), bias))
                fields.append(float(np.sqrt(solution[3] + bias @ bias)))
            field = float(np.mean(fields))
            return CentreResult(Calibration(sensors, reference_total_nT=field), field)


    TOY = FIT_MODES.register(CentreMode())
'''


def test_recipe_fit_mode_from_an_installed_package(tmp_path):
    site = install_distribution(
        tmp_path / "site", {"toy_mode": TOY_MODE}, {"magcal.fit_modes": {"toy": "toy_mode:TOY"}}, "toy fit mode"
    )
    rng = np.random.default_rng(5)
    bias = np.array([1200.0, -800.0, 300.0])  # nT, the truth
    directions = rng.normal(size=(400, 3))
    readings = 50_000.0 * directions / np.linalg.norm(directions, axis=1, keepdims=True) + bias
    magcal.data.io.write_csv(tmp_path / "d.csv", magcal.as_dataset(readings + rng.normal(0, 3.0, readings.shape)))

    help_text = magcal_cli(["calibrate", "--help"], site).stdout
    assert "toy: the bias-only fit (the centre of the sphere), needs at least 4 samples" in " ".join(help_text.split())
    out = magcal_cli(["calibrate", tmp_path / "d.csv", "--mode", "toy", "-o", tmp_path / "cal.json", "--json"], site)
    assert out.returncode == 0, out.stderr
    doc = json.loads(out.stdout)
    assert doc["mode"] == "toy" and "toy mode (bias-only fit" in out.stderr
    np.testing.assert_allclose(doc["bias_nT"][0], bias, atol=1.0)  # noise 3 nT over 400 samples
    np.testing.assert_allclose(Calibration.load(tmp_path / "cal.json").sensors[0].bias_nT, doc["bias_nT"][0])

    # the API takes the same mode by name and gives the same calibration; auto keeps the total-field fit
    code = (
        "import json, sys, magcal\n"
        "ds = magcal.read_csv(sys.argv[1])\n"
        "print(json.dumps([magcal.calibrate(ds, mode='toy').to_dict(), magcal.calibrate(ds, warn=False).mode]))"
    )
    api = magcal_cli([tmp_path / "d.csv"], site, code=code)
    assert api.returncode == 0, api.stderr
    toy, auto = json.loads(api.stdout)
    assert toy["mode"] == "toy" and toy["bias_nT"] == doc["bias_nT"] and toy["field_nT"] == doc["field_nT"]
    assert auto == "total_field"

    # a mode the record cannot have says why, on the command line as in the API
    magcal.data.io.write_csv(tmp_path / "short.csv", magcal.as_dataset(readings[:3]))
    short = magcal_cli(["calibrate", tmp_path / "short.csv", "--mode", "toy"], site)
    assert short.returncode == 2 and "--mode toy needs at least 4 samples (the record has 3)" in short.stderr


# ----------------------------------------------------------------------------------------------------------------
# a workbench panel (CONTRIBUTING: "a workbench panel")
# ----------------------------------------------------------------------------------------------------------------

TOY_PANEL = '''
    """A toy workbench panel: a section of the Outliers tab that says how many samples are kept, with a button that
    rejects the first ten."""

    from magcal_workbench.actions import action
    from magcal_workbench.events import Change
    from magcal_workbench.panelkit import PanelKind, register_panel


    class KeptCount:
        def __init__(self, context):
            self.ctrl = context.ctrl  # a getter: the open data's controller
            self.text = self.button = None

        def attach(self, panels):
            with panels.section("Outliers", "Toy: kept samples"):
                self.text = panels.gui.add_markdown("")
                self.button = panels.button("Reject the first ten", panels.on.do_toy_reject_first)
            self.show()

        def show(self):
            ctrl = self.ctrl()
            self.text.content = f"{int(ctrl.kept.sum())} of {ctrl.dataset.n_samples} kept"

        def changed(self, kind):
            if kind in (Change.SELECTION, Change.DATA):
                self.show()

        @action
        def do_toy_reject_first(self, event):
            self.ctrl().select(range(10), what="the first ten")


    TOY = register_panel(PanelKind("toy-kept", "how many samples are kept", KeptCount))
'''


def test_recipe_panel_from_an_installed_package_is_built_and_its_button_works(tmp_path, monkeypatch):
    pytest.importorskip("viser")
    from viser import GuiEvent

    from magcal_workbench.app import Workbench
    from magcal_workbench.panelkit import PANELS

    site = install_distribution(
        tmp_path / "site",
        {"toy_panel": TOY_PANEL},
        {"magcal_workbench.panels": {"toy-kept": "toy_panel:TOY"}},
        "toy panel",
    )
    monkeypatch.syspath_prepend(str(site))
    try:
        loaded = PANELS.load_entry_points(force=True)  # what magcal-workbench does when it starts
        assert list(loaded) == ["toy-kept"] and not loaded.notes
        assert PANELS.origin("toy-kept").startswith("entry point toy-kept = toy_panel:TOY")
        assert list(PANELS) == [
            "calibrate",
            "model",
            "quality",
            "outliers",
            "view",
            "files",
            "lessons",
            "gravity",
            "compensation",
            "toy-kept",
        ]  # the built-in ones first
        n = 120
        wb = Workbench(magcal.simulate_timeseries("chi2017", n_samples=n, seed=5, rate_hz=2.0), port=0, store=None)
        try:
            panel = wb.added["toy-kept"]
            assert panel.text.content == f"{n} of {n} kept"  # built, and shown the open data
            assert wb.actions.owner("do_toy_reject_first") == "KeptCount"
            panel.button._impl.value = True  # a click, as a browser's arrives: the callbacks run
            for callback in list(panel.button._impl.update_cb):
                callback(GuiEvent(None, None, panel.button))
            assert wb.ctrl.state.selection.rejected_indices.tolist() == list(range(10))
            assert panel.text.content == f"{n - 10} of {n} kept"  # the panel follows the controller's events
            wb.ctrl.undo()
            assert panel.text.content == f"{n} of {n} kept"
        finally:
            wb.stop()
    finally:
        PANELS.unregister("toy-kept")
        sys.modules.pop("toy_panel", None)
