"""docs/architecture.md lists every module of the engine and of the workbench, one table row each, and nothing that
no longer exists: a module added without its line, or removed with its line left, fails here."""

from __future__ import annotations

import pathlib
import re

ROOT = pathlib.Path(__file__).resolve().parents[2]
DOC = ROOT / "docs" / "architecture.md"


def _modules(package: str) -> set[str]:
    """Dotted names of the package's modules (``__init__`` and ``__main__`` files are their package's)."""
    base = ROOT / package
    names = set()
    for path in base.rglob("*.py"):
        if "__pycache__" in path.parts or path.name in ("__init__.py", "__main__.py"):
            continue
        names.add(".".join(path.relative_to(ROOT).with_suffix("").parts))
    return names


def _packages(package: str) -> set[str]:
    return {".".join(p.parent.relative_to(ROOT).parts) for p in (ROOT / package).rglob("__init__.py")}


def _table_rows(text: str, heading: str) -> list[str]:
    """The table rows (``| ... |`` lines) of the section under ``## heading``."""
    section = text.split(f"## {heading}\n", 1)[1].split("\n## ", 1)[0]
    return [line for line in section.splitlines() if line.startswith("|") and not line.startswith("|---")]


def engine_listed(text: str) -> set[str]:
    """Modules named in the first two columns of the engine's table (``| layer | `magcal.x.y` | what |``)."""
    found = set()
    for row in _table_rows(text, "Modules (one concept each)"):
        cells = row.strip("|").split("|")
        if len(cells) >= 2:
            found |= set(re.findall(r"`(magcal(?:\.\w+)+)`", cells[1]))
    return found


def workbench_listed(text: str) -> set[str]:
    """Modules named in the first column of the workbench's table (``| `app` | what |``)."""
    found = set()
    for row in _table_rows(text, "Workbench modules"):
        first = row.strip("|").split("|")[0]
        found |= {f"magcal_workbench.{name}" for name in re.findall(r"`(\w+)`", first)}
    return found


def test_every_engine_module_is_listed_and_every_listed_one_exists():
    text = DOC.read_text(encoding="utf-8")
    listed = engine_listed(text)
    modules = _modules("magcal")
    missing = sorted(modules - listed)
    stale = sorted(listed - modules - _packages("magcal"))
    assert not missing, f"docs/architecture.md's module table lacks: {missing}"
    assert not stale, f"docs/architecture.md lists modules that do not exist: {stale}"


def test_every_workbench_module_is_listed_and_every_listed_one_exists():
    text = DOC.read_text(encoding="utf-8")
    listed = workbench_listed(text)
    modules = _modules("magcal_workbench")
    missing = sorted(modules - listed)
    stale = sorted(listed - modules)
    assert not missing, f"docs/architecture.md's workbench table lacks: {missing}"
    assert not stale, f"docs/architecture.md lists workbench modules that do not exist: {stale}"


def test_the_check_finds_a_missing_and_a_stale_module():
    """The rule itself: a table without a module's row, or with a row for a module that does not exist."""
    text = DOC.read_text(encoding="utf-8")
    without = "\n".join(line for line in text.splitlines() if "`magcal.core.errors`" not in line)
    assert "magcal.core.errors" in _modules("magcal") - engine_listed(without)
    stale = text.replace("| | `magcal.core.errors` |", "| | `magcal.core.nowhere` |", 1)
    assert "magcal.core.nowhere" in engine_listed(stale) - _modules("magcal")
    assert "magcal_workbench.app" in workbench_listed(text)
