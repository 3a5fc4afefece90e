"""The page's handlers are registered where they are written: each is marked ``@action`` in its
part, the workbench gathers them by name (no ``dir()`` scan), two parts offering one name stop the start, every
``on.NAME`` a widget calls is registered and every registered handler is called by some widget.

The widgets' calls are read from the workbench's source with :mod:`ast`; the registered names from a running
workbench.
"""

from __future__ import annotations

import ast
import pathlib

import pytest

import magcal_workbench
from magcal_workbench.actions import Actions, DuplicateAction, action, handlers_of

pytest.importorskip("viser")

PACKAGE = pathlib.Path(magcal_workbench.__file__).parent
BENCH_SAMPLES = 120


def _trees():
    for path in sorted(PACKAGE.glob("*.py")):
        yield path, ast.parse(path.read_text(encoding="utf-8"))


def _called_by_widgets() -> dict[str, str]:
    """Every ``on.NAME`` / ``self.on.NAME`` / ``p.on.NAME`` in the workbench's modules: NAME -> where."""
    out: dict[str, str] = {}
    for path, tree in _trees():
        for node in ast.walk(tree):
            if not isinstance(node, ast.Attribute):
                continue
            base = node.value
            if (isinstance(base, ast.Name) and base.id == "on") or (
                isinstance(base, ast.Attribute) and base.attr == "on"
            ):
                out.setdefault(node.attr, f"{path.name}:{node.lineno}")
    return out


def _is_action(decorator: ast.expr) -> bool:
    target = decorator.func if isinstance(decorator, ast.Call) else decorator
    return isinstance(target, ast.Name) and target.id == "action"


def test_the_reader_finds_the_widgets_calls():
    called = _called_by_widgets()
    assert "do_refine" in called and "do_export_format" in called and "legend_html" in called


def test_every_do_method_is_marked_as_a_handler():
    unmarked = [
        f"{path.name}:{node.lineno} {node.name}"
        for path, tree in _trees()
        for node in ast.walk(tree)
        if isinstance(node, ast.FunctionDef)
        and node.name.startswith("do_")
        and not any(_is_action(d) for d in node.decorator_list)
    ]
    assert not unmarked, f"handlers not registered with @action: {unmarked}"


def test_the_handlers_are_not_found_by_scanning_names():
    text = (PACKAGE / "app.py").read_text(encoding="utf-8")
    assert "dir(" not in text and 'startswith("do_")' not in text


def test_every_widgets_handler_is_registered_and_every_handler_has_a_widget(bench):
    wb = bench()
    registered = wb.actions.names()
    called = _called_by_widgets()
    unregistered = {name: where for name, where in called.items() if name not in registered}
    assert not unregistered, f"widgets call handlers nobody registers: {unregistered}"
    dead = sorted(registered - set(called))
    assert not dead, f"registered handlers no widget calls: {dead}"
    # the panels were handed these very handlers: a widget's call reaches its part's method
    assert wb.panels.on is wb.actions
    assert wb.actions.owner("do_refine") == "CalibrateTab" and wb.actions.do_refine == wb.added["calibrate"].do_refine
    assert wb.actions.owner("do_add") == "ModelTab" and wb.actions.owner("do_apply_noise") == "QualityTab"
    assert wb.actions.owner("draw_cockpit") == "Cockpit" and wb.actions.draw_cockpit == wb.cockpit.draw


def test_a_name_nobody_registered_is_refused_where_it_is_asked_for(bench):
    wb = bench()
    with pytest.raises(AttributeError, match="no workbench handler 'do_nothing'.*@action"):
        _ = wb.actions.do_nothing


class _One:
    @action
    def do_x(self, event):
        return "one"

    @action(name="draw_y")
    def draw(self):
        return "drawn"

    def do_helper_not_registered(self):  # not marked: not a handler
        return None


class _Two:
    @action
    def do_x(self, event):
        return "two"


class _Child(_One):
    @action
    def do_z(self, event):
        return "z"


def test_handlers_are_those_marked_by_their_names_inherited_too():
    assert set(handlers_of(_One())) == {"do_x", "draw_y"}
    child = _Child()
    assert set(handlers_of(child)) == {"do_x", "draw_y", "do_z"}
    on = Actions([child])
    assert on.do_x(None) == "one" and on.draw_y() == "drawn" and on.do_z(None) == "z"
    with pytest.raises(AttributeError):
        on.do_x = lambda e: None


def test_two_parts_offering_one_name_is_an_error_naming_both():
    with pytest.raises(DuplicateAction, match=r"'do_x': _One\.do_x and _Two\.do_x"):
        Actions([_One(), _Two()])


def test_a_duplicate_handler_stops_the_workbench_at_start(monkeypatch):
    import magcal
    from magcal_workbench.app import Workbench
    from magcal_workbench.guard import guarded_viser_server
    from magcal_workbench.steps import Steps

    # the Steps part offers a second do_upload (the Uploads part has one)
    monkeypatch.setattr(Steps, "do_upload_twice", action(name="do_upload")(lambda self, event: None), raising=False)
    server = guarded_viser_server("127.0.0.1", 0)
    try:
        ds = magcal.simulate_timeseries("chi2017", n_samples=BENCH_SAMPLES, seed=5, rate_hz=2.0)
        with pytest.raises(DuplicateAction, match=r"'do_upload': Steps\.do_upload and Uploads\.do_upload"):
            Workbench(ds, port=0, store=None, server=server)
    finally:
        server.stop()
