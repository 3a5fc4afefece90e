"""The wheel carries the bundled demo and lessons (``assets/`` installed as ``workbench/assets``)."""

import fnmatch
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def _setuptools_config():
    return tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["setuptools"]


def test_assets_are_mapped_into_the_workbench_package():
    cfg = _setuptools_config()
    assert cfg["package-dir"]["workbench.assets"] == "assets"
    assert "workbench.assets" in cfg["packages"]


@pytest.mark.parametrize("path", sorted(p.relative_to(ROOT / "assets").as_posix()
                                        for p in (ROOT / "assets").rglob("*")
                                        if p.is_file() and p.suffix != ".py" and "__pycache__" not in p.parts))
def test_every_data_file_of_assets_is_package_data(path):
    patterns = _setuptools_config()["package-data"]["workbench.assets"]
    assert any(fnmatch.fnmatch(path, pat) and path.count("/") == pat.count("/") for pat in patterns), (
        f"assets/{path} would be left out of the wheel: add a pattern for it to pyproject.toml")


def test_the_workbench_finds_the_demo_and_the_lessons():
    from workbench import lessons

    assert lessons.DEMO.is_file()
    assert len(lessons.list_lessons()) >= 4


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
    return names - set(sys.stdlib_module_names) - {"magcal", "workbench"}


def _requirement_names(requirements):
    import re

    return {re.split(r"[<>=!~\[; ]", r, maxsplit=1)[0].strip().lower() for r in requirements}


def test_every_package_the_engine_and_workbench_import_is_a_dependency():
    """A fresh install must bring what the code imports (plotly was once missing)."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    declared = _requirement_names(project["dependencies"])
    missing = _third_party_imports(["magcal", "workbench"]) - declared
    assert not missing, f"imported but not in [project] dependencies: {sorted(missing)}"


def test_every_package_the_tests_import_is_a_test_dependency():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    declared = _requirement_names(project["dependencies"] + project["optional-dependencies"]["test"])
    local = {p.stem for p in (ROOT / "tests").glob("*.py")}
    missing = _third_party_imports(["tests"]) - declared - local
    assert not missing, f"imported by the tests but not declared: {sorted(missing)}"
