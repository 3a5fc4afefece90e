"""The controller's events are one enum: every kind sent is a member, every member is sent, every
kind a handler names is a member, and a kind nobody knows is refused where it is sent.

Read from the workbench's source with :mod:`ast`, so a handler of a kind that is never sent (the dead ``"view"``
this test found) fails here rather than staying unnoticed.
"""

from __future__ import annotations

import ast
import pathlib

import pytest

import magcal_workbench
from magcal_workbench.events import Change

PACKAGE = pathlib.Path(magcal_workbench.__file__).parent
#: Functions that receive the kinds: the workbench's router, the parts it hands them to, the panels' refresh.
HANDLERS = {"_changed", "changed", "refresh"}
#: Names a handler holds the kind(s) in.
KIND_NAMES = {"kind", "kinds"}
#: What a refresh may be asked for besides the kinds: everything.
NOT_KINDS = {"all"}


def _trees():
    for path in sorted(PACKAGE.glob("*.py")):
        yield path, ast.parse(path.read_text(encoding="utf-8"))


def _sent() -> list[tuple[str, int, ast.expr]]:
    """Every ``emit(...)`` call's argument, with its file and line."""
    out = []
    for path, tree in _trees():
        for node in ast.walk(tree):
            if isinstance(node, ast.Call) and getattr(node.func, "attr", getattr(node.func, "id", None)) == "emit":
                for arg in node.args:
                    out.append((path.name, node.lineno, arg))
    return out


def _named_by_handlers() -> list[tuple[str, int, str]]:
    """String constants a handler compares its kind(s) with (``kind == "x"``, ``kind in (...)``, ``kinds & {...}``,
    ``"x" in kinds``)."""
    out = []
    for path, tree in _trees():
        for fn in ast.walk(tree):
            if not (isinstance(fn, ast.FunctionDef) and fn.name in HANDLERS):
                continue
            for node in ast.walk(fn):
                if not isinstance(node, (ast.Compare, ast.BinOp)):
                    continue
                names = {n.id for n in ast.walk(node) if isinstance(n, ast.Name)}
                if not names & KIND_NAMES:
                    continue
                for const in ast.walk(node):
                    if isinstance(const, ast.Constant) and isinstance(const.value, str):
                        out.append((path.name, const.lineno, const.value))
    return out


def _member(arg: ast.expr) -> str | None:
    """``Change.X`` -> X's value; anything else None."""
    if isinstance(arg, ast.Attribute) and isinstance(arg.value, ast.Name) and arg.value.id == "Change":
        return Change[arg.attr].value
    return None


def test_every_kind_sent_is_a_member():
    bad = [(f, line, ast.unparse(arg)) for f, line, arg in _sent() if _member(arg) is None]
    assert not bad, f"emit with something other than Change.X: {bad}"


def test_every_member_is_sent():
    sent = {_member(arg) for _, _, arg in _sent()}
    sent.add(Change.DATA.value)  # the workbench's redraw after a record is opened (Workbench.redraw)
    assert {c.value for c in Change} - sent == set()


def test_every_kind_a_handler_names_is_a_member():
    known = {c.value for c in Change} | NOT_KINDS
    bad = [(f, line, value) for f, line, value in _named_by_handlers() if value not in known]
    assert not bad, f"handled kinds that are never sent: {bad}"


def test_the_checks_see_what_they_look_for():
    """The readers above find a string kind and a member (they can fail)."""
    tree = ast.parse("def changed(self, kind):\n    if kind in ('result', 'vieww'):\n        pass\n")
    fn = tree.body[0]
    found = [
        c.value for n in ast.walk(fn) if isinstance(n, ast.Compare) for c in ast.walk(n) if isinstance(c, ast.Constant)
    ]
    assert found == ["result", "vieww"]
    assert _member(ast.parse("Change.RESULT", mode="eval").body) == "result"
    assert _member(ast.parse("'result'", mode="eval").body) is None


def test_an_unknown_kind_is_refused_where_it_is_sent():
    from magcal.data.simulation import chi2017_truth, simulate_timeseries
    from magcal_workbench.controller import Controller

    ctrl = Controller(simulate_timeseries(chi2017_truth(1), n_samples=200, noise_nT=3.0, seed=1))
    seen = []
    ctrl.on_change(seen.append)
    ctrl.emit(Change.MODEL)
    ctrl.emit("selection")  # its text is the member
    assert seen == [Change.MODEL, Change.SELECTION] and all(isinstance(k, Change) for k in seen)
    with pytest.raises(ValueError):
        ctrl.emit("view")
    assert len(seen) == 2


def test_changes_are_sent_only_through_the_controllers_public_emit():
    """No module calls a private ``_emit`` (the model sessions and the panels send through ``Controller.emit``)."""
    private = [
        (path.name, node.lineno)
        for path, tree in _trees()
        for node in ast.walk(tree)
        if isinstance(node, ast.Call) and getattr(node.func, "attr", getattr(node.func, "id", None)) == "_emit"
    ]
    assert private == []
    assert any(f == "totalfield.py" for f, _, _ in _sent()) and any(f == "gravitymodel.py" for f, _, _ in _sent())
