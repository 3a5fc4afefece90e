"""The workbench's modules: no import circle, the engine imported at the top of each module and only by its
public names, the panels given what they need (never the app), and viser's internals reached in one module."""

from __future__ import annotations

import ast
import pathlib
import re

import pytest

PACKAGE = pathlib.Path(__file__).resolve().parents[2] / "magcal_workbench"
MODULES = {p.stem: p for p in sorted(PACKAGE.glob("*.py")) if p.stem != "__init__"}


def _tree(name: str) -> ast.Module:
    return ast.parse(MODULES[name].read_text(encoding="utf-8"))


def _imports(name: str):
    """``(node, at_top)`` for every import statement of the module ``name``."""
    tree = _tree(name)
    top = set(map(id, tree.body))
    for node in ast.walk(tree):
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node, id(node) in top


def _workbench_targets(node) -> list[str]:
    """The workbench modules an import statement names (relative or absolute)."""
    if isinstance(node, ast.ImportFrom):
        if node.level == 1:
            if node.module:
                return [node.module.split(".")[0]]
            return [a.name for a in node.names]
        if (node.module or "").startswith("magcal_workbench"):
            rest = node.module.split(".")[1:]
            return rest[:1] if rest else [a.name for a in node.names]
        return []
    return [a.name.split(".")[1] for a in node.names if a.name.startswith("magcal_workbench.")]


GRAPH = {m: sorted({t for n, _ in _imports(m) for t in _workbench_targets(n) if t in MODULES}) for m in MODULES}


def _cycles(graph) -> list[list[str]]:
    """Every strongly connected set of more than one module (Tarjan), each sorted."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1 or v in graph.get(v, ()):
                out.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    return out


def test_the_cycle_finder_finds_a_circle():
    assert _cycles({"a": ["b"], "b": ["c"], "c": ["a"], "d": ["a"]}) == [["a", "b", "c"]]
    assert _cycles({"a": ["b"], "b": []}) == []


def test_no_import_circle_in_the_workbench():
    """Counting imports inside functions too."""
    assert GRAPH["app"], "the graph is empty: the parser missed the imports"
    assert _cycles(GRAPH) == []


@pytest.mark.parametrize("name", sorted(MODULES))
def test_the_engine_is_imported_at_the_top_and_by_public_names(name):
    for node, at_top in _imports(name):
        if isinstance(node, ast.ImportFrom):
            if node.level or not (node.module or "").split(".")[0] == "magcal":
                continue
            names = [node.module, *(a.name for a in node.names)]
        else:
            names = [a.name for a in node.names if a.name.split(".")[0] == "magcal"]
            if not names:
                continue
        where = f"{name}.py:{node.lineno}"
        assert at_top, f"{where}: the engine is imported inside a function"
        private = [n for n in names for part in n.split(".") if part.startswith("_")]
        assert not private, f"{where}: imports the engine's private name(s) {private}"


def test_the_panels_never_reach_into_the_app():
    text = MODULES["panels"].read_text(encoding="utf-8")
    assert "self.app" not in text and "Workbench(" not in text
    assert "app" not in GRAPH["panels"]
    # nothing but the composition imports the app
    assert [m for m, targets in GRAPH.items() if "app" in targets] in ([], ["_launch"])


#: What reaches viser's internals: private attributes of its objects and its private modules.
VISER_INTERNALS = re.compile(r"\._impl\b|_websock_server|_current_file_upload_states|viser\._|from viser import _")


@pytest.mark.parametrize("name", sorted(set(MODULES) - {"viser_adapter"}))
def test_viser_internals_are_reached_only_in_the_adapter(name):
    text = MODULES[name].read_text(encoding="utf-8")
    found = [m.group(0) for m in VISER_INTERNALS.finditer(text)]
    assert not found, f"{name}.py reaches viser's internals {found}: go through magcal_workbench/viser_adapter.py"


@pytest.mark.parametrize("name", ["live", "jobs", "timewindow", "steps"])
def test_background_threads_do_not_touch_the_panels(name):
    """Their updates go through the page's one thread (magcal_workbench.uiqueue)."""
    text = MODULES[name].read_text(encoding="utf-8")
    assert ".refresh_live(" not in text and ".set_busy(" not in text and ".set_progress(" not in text


#: How many times the workbench's parts reach through the whole workbench (``wb.`` or ``self.wb.``) rather than a
#: narrow interface handed to them. A ratchet: lower it when a part is given what it needs; it
#: may not grow. 235 on 2026-11-29 (about 190 when the issue was filed); 132 after the scene control (view.py 63 -> 0),
#: the steps, the evidence plots and the gravity page were handed what they use; then 108 (the vehicle view),
#: 85 (the export section), 61 (the live control), 45 (the lessons desk),
#: 31 (the uploads), 18 (the sessions), 4 (the cockpit).
WB_REACHES_AT_MOST = 4


def _wb_reaches() -> dict[str, int]:
    counts = {}
    for path in sorted(PACKAGE.glob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        n = sum(
            1
            for node in ast.walk(tree)
            if isinstance(node, ast.Attribute)
            and (
                (isinstance(node.value, ast.Name) and node.value.id == "wb")
                or (isinstance(node.value, ast.Attribute) and node.value.attr == "wb")
            )
        )
        if n:
            counts[path.name] = n
    return counts


def test_the_parts_reach_through_the_workbench_no_more_than_before():
    counts = _wb_reaches()
    total = sum(counts.values())
    worst = sorted(counts.items(), key=lambda kv: -kv[1])[:5]
    assert total <= WB_REACHES_AT_MOST, (
        f"{total} reaches through the workbench (wb.X), at most {WB_REACHES_AT_MOST}: hand the part what it needs "
        f"instead (most: {worst})"
    )
    assert counts, "the count found no reach at all: the reader is broken"
