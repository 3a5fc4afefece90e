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
