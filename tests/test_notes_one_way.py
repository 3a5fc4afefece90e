"""Notes travel one way (issue 43, item 4): a step of the engine returns what it has to say in its result's
``notes``; only :mod:`magcal.core.notes` turns notes into Python warnings, called by the public functions and the
command line. The engine's source holds no ``warnings.warn`` elsewhere and no ``*_with_notes`` twin.
"""

from __future__ import annotations

import ast
import pathlib
import re

import magcal

ENGINE = pathlib.Path(magcal.__file__).parent
ONE_PLACE = ENGINE / "core" / "notes.py"


def _engine_files():
    return sorted(p for p in ENGINE.rglob("*.py") if p != ONE_PLACE)


def _warn_calls(tree) -> list[int]:
    """Lines of ``warnings.warn(...)`` calls (or ``warn`` imported from :mod:`warnings`)."""
    direct = {
        alias.asname or alias.name
        for node in ast.walk(tree)
        if isinstance(node, ast.ImportFrom) and node.module == "warnings"
        for alias in node.names
        if alias.name in ("warn", "warn_explicit")
    }
    lines = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        f = node.func
        if isinstance(f, ast.Attribute) and f.attr in ("warn", "warn_explicit"):
            if isinstance(f.value, ast.Name) and f.value.id == "warnings":
                lines.append(node.lineno)
        elif isinstance(f, ast.Name) and f.id in direct:
            lines.append(node.lineno)
    return lines


def test_only_core_notes_raises_warnings():
    found = {}
    for path in _engine_files():
        lines = _warn_calls(ast.parse(path.read_text(encoding="utf-8")))
        if lines:
            found[str(path.relative_to(ENGINE))] = lines
    assert found == {}, f"warnings.warn outside magcal/core/notes.py: {found}; return a Note in the step's result"


def test_the_check_sees_a_warning_call():
    """The check above can fail: it finds both spellings."""
    assert _warn_calls(ast.parse("import warnings\nwarnings.warn('x')\n")) == [2]
    assert _warn_calls(ast.parse("from warnings import warn as w\nw('x')\n")) == [2]
    assert _warn_calls(ast.parse("import warnings\nwith warnings.catch_warnings():\n    pass\n")) == []


def test_no_with_notes_twins():
    twins = {
        str(path.relative_to(ENGINE)): names
        for path in _engine_files() + [ONE_PLACE]
        if (names := re.findall(r"^\s*def (\w+_with_notes)\(", path.read_text(encoding="utf-8"), re.M))
    }
    assert twins == {}, f"one function per step, its notes in its result: {twins}"
