"""Packaging: what the wheel carries (every package, the demo and lessons), what each install brings, the console
scripts, and the README's set-up commands (the ones .ci/run runs)."""

import fnmatch
import importlib
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _setuptools_config():
    return tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["setuptools"]


def test_assets_are_mapped_into_the_workbench_package():
    cfg = _setuptools_config()
    assert cfg["package-dir"]["magcal_workbench.assets"] == "assets"
    assert "magcal_workbench.assets" in cfg["packages"]


@pytest.mark.parametrize(
    "path",
    sorted(
        p.relative_to(ROOT / "assets").as_posix()
        for p in (ROOT / "assets").rglob("*")
        if p.is_file() and p.suffix != ".py" and "__pycache__" not in p.parts
    ),
)
def test_every_data_file_of_assets_is_package_data(path):
    patterns = _setuptools_config()["package-data"]["magcal_workbench.assets"]
    assert any(fnmatch.fnmatch(path, pat) and path.count("/") == pat.count("/") for pat in patterns), (
        f"assets/{path} would be left out of the wheel: add a pattern for it to pyproject.toml"
    )


def test_the_workbench_finds_the_demo_and_the_lessons():
    from magcal_workbench import lessons

    assert lessons.DEMO.is_file()
    assert len(lessons.list_lessons()) >= 4


#: Packages whose import name is not their distribution's name.
IMPORT_TO_DISTRIBUTION = {"serial": "pyserial"}


def _third_party_imports(folders):
    import ast
    import sys

    names = set()
    for folder in folders:
        for path in (ROOT / folder).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                if isinstance(node, ast.Import):
                    names.update(a.name.split(".")[0] for a in node.names)
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    names.add(node.module.split(".")[0])
    names = {IMPORT_TO_DISTRIBUTION.get(n, n) for n in names}
    return names - set(sys.stdlib_module_names) - {"magcal", "magcal_workbench"}


def _requirement_names(requirements):
    import re

    return {re.split(r"[<>=!~\[; ]", r, maxsplit=1)[0].strip().lower() for r in requirements}


def _project():
    return tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]


def _module_level_imports(folder):
    """Third-party packages imported at a module's top level (not inside a function) anywhere under ``folder``."""
    import ast

    names = set()
    for path in (ROOT / folder).rglob("*.py"):
        for node in ast.parse(path.read_text(encoding="utf-8")).body:
            if isinstance(node, ast.Import):
                names.update(a.name.split(".")[0] for a in node.names)
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names.add(node.module.split(".")[0])
    return {IMPORT_TO_DISTRIBUTION.get(n, n) for n in names}


def test_the_engine_needs_only_the_core_dependencies():
    """``pip install -e .`` must be enough for magcal itself (the API, the command line): every package it imports
    is core, except the ``instruments`` extra's (serial ports, MAVLink, flight logs), the ``survey`` extra's
    (Parquet, DataFrames) and the ``figures`` extra's (matplotlib), which are imported only inside the functions
    that need them, each with a message naming the extra."""
    project = _project()
    core = _requirement_names(project["dependencies"])
    optional = set()
    for extra in ("instruments", "survey", "figures"):
        optional |= _requirement_names(project["optional-dependencies"][extra])
    imported = _third_party_imports(["magcal"])
    assert not imported - core - optional, f"magcal imports undeclared packages: {sorted(imported - core - optional)}"
    assert not _module_level_imports("magcal") & optional, "an optional package is imported at module level"
    texts = " ".join(p.read_text(encoding="utf-8") for p in (ROOT / "magcal").rglob("*.py"))
    for extra in ("instruments", "survey", "figures"):
        assert f'pip install "magcal-workbench[{extra}]"' in texts, extra


def test_import_magcal_needs_no_optional_package():
    """``import magcal`` (and its command line) loads none of the workbench's or the instruments' packages."""
    code = (
        "import sys, magcal, magcal.cli, magcal.data.live, magcal.data.logs, magcal.output.export; "
        "print(sorted(m for m in ('viser', 'trimesh', 'plotly', 'serial', 'pymavlink', 'pyulog', 'pyarrow') "
        "if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]", out


def test_every_package_the_workbench_imports_is_in_its_extra():
    """A fresh ``pip install -e ".[workbench]"`` must bring what the app imports (plotly was once missing)."""
    from magcal_workbench import _launch

    project = _project()
    core = _requirement_names(project["dependencies"])
    extra = _requirement_names(project["optional-dependencies"]["workbench"])
    imported = _third_party_imports(["magcal_workbench"])
    assert not imported - core - extra, f"imported but not declared: {sorted(imported - core - extra)}"
    # the launcher checks exactly the extra's packages
    assert set(_launch.WORKBENCH_PACKAGES) == extra == imported - core


def test_the_workbench_packages_are_not_core_dependencies():
    declared = _requirement_names(_project()["dependencies"])
    assert not declared & {"viser", "trimesh", "plotly"}, declared


def test_every_package_the_tests_import_is_a_test_dependency():
    project = _project()
    test = project["optional-dependencies"]["test"]
    assert (
        "magcal-workbench[workbench,instruments,survey]" in test
    )  # the tests drive the workbench, instruments, Parquet
    extras = project["optional-dependencies"]
    declared = _requirement_names(
        project["dependencies"] + extras["workbench"] + extras["instruments"] + extras["survey"] + test
    )
    local = {"tests"} | {p.stem for p in (ROOT / "tests").rglob("*.py")}  # the tests import each other as a package
    missing = _third_party_imports(["tests"]) - declared - local
    assert not missing, f"imported by the tests but not declared: {sorted(missing)}"


def test_every_python_package_is_in_the_wheel():
    """A package folder left out of ``packages`` is missing from the wheel (magcal.diagnosis became one)."""
    listed = set(_setuptools_config()["packages"])
    found = {
        ".".join(p.parent.relative_to(ROOT).parts)
        for folder in ("magcal", "magcal_workbench")
        for p in (ROOT / folder).rglob("__init__.py")
        if "__pycache__" not in p.parts
    }
    assert found <= listed, f"not in [tool.setuptools] packages: {sorted(found - listed)}"


@pytest.mark.parametrize(
    "script, target", [("magcal", "magcal.cli:main"), ("magcal-workbench", "magcal_workbench._launch:main")]
)
def test_console_scripts_point_at_callables(script, target):
    assert _project()["scripts"][script] == target
    module, _, name = target.partition(":")
    assert callable(getattr(importlib.import_module(module), name))


def _bash_blocks(text):
    return [block.strip() for block in re.findall(r"```bash\n(.*?)```", text, re.S)]


def _setup_section():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    return text[text.index("## Set-up") : text.index("\n## ", text.index("## Set-up") + 1)]


def test_readme_first_command_installs_the_workbench_extra_and_starts_it():
    assert _bash_blocks(_setup_section())[0] == 'pip install -e ".[workbench]" && magcal-workbench'


def test_readme_test_command_is_what_ci_runs():
    test_command = 'pip install -e ".[test]" && python -m pytest'
    assert test_command in _bash_blocks(_setup_section())
    ci_lines = [line.strip() for line in (ROOT / ".ci" / "run").read_text(encoding="utf-8").splitlines()]
    assert test_command in ci_lines


def test_the_test_command_runs_the_doctests_of_magcal():
    options = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["pytest"]["ini_options"]
    assert options["testpaths"] == ["tests", "magcal"]
    assert "--doctest-modules" in options["addopts"]


def _launch(hide=()):
    """Run the magcal-workbench entry point in a fresh Python with some packages made unimportable."""
    code = (
        "import sys\n"
        f"for name in {tuple(hide)!r}: sys.modules[name] = None  # import raises ImportError\n"
        "from magcal_workbench._launch import main\n"
        "sys.exit(main(['--help']))\n"
    )
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT)


@pytest.mark.parametrize("hide", [("viser",), ("trimesh",), ("plotly",), ("viser", "trimesh", "plotly")])
def test_without_the_workbench_extra_the_launcher_says_what_to_install(hide):
    done = _launch(hide)
    assert done.returncode == 1
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert lines[0].startswith('magcal-workbench needs the workbench extra: pip install -e ".[workbench]"')
    assert all(name in lines[0] for name in hide)
    assert done.stdout == ""


def test_with_the_extra_the_launcher_starts_the_app():
    done = _launch()
    assert done.returncode == 0, done.stderr
    assert "usage" in done.stdout and "needs the workbench extra" not in done.stderr


def test_the_launcher_hands_its_arguments_to_the_app(monkeypatch):
    from magcal_workbench import _launch, app, startup

    seen = []
    monkeypatch.setattr(app, "main", lambda argv=None, early=None: seen.append((argv, early)) or 7)
    monkeypatch.setattr(startup, "begin", lambda argv=None: None)  # no server started early: the app is handed argv
    assert _launch.main(["--port", "9"]) == 7
    assert seen == [(["--port", "9"], None)]
