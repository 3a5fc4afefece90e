"""The engine's layers: imports point one way, down the data's stages, and there is no import circle.

The layers, lowest first, are the subpackages of :mod:`magcal` (docs/architecture.md draws them). A module may
import its own layer and the layers below it, at the top of the module; only optional dependencies (the
instruments, survey and workbench extras) are imported where they are used. The engine never imports the
workbench or viser.
"""

from __future__ import annotations

import ast
import pathlib

import pytest

ENGINE = pathlib.Path(__file__).resolve().parents[2] / "magcal"

#: The layers, lowest first; ``magcal`` is the package's own ``__init__`` (the public API).
LAYERS = (
    "core",
    "geometry",
    "data",
    "checks",
    "model",
    "calibration",
    "fitting",
    "diagnosis",
    "modes",
    "output",
    "api",
    "cli",
)

#: Third-party packages that belong to an extra, imported where they are used (never at a module's top).
OPTIONAL = (
    "pandas",
    "pyarrow",
    "dask",
    "distributed",
    "serial",
    "pymavlink",
    "pyulog",
    "viser",
    "trimesh",
    "plotly",
    "matplotlib",
    "websockets",
)


#: Modules of the package root that belong to a layer: ``python -m magcal`` is the command line.
ENTRY_POINTS = {"__main__": "cli"}


def _module_name(path: pathlib.Path) -> str:
    parts = list(path.relative_to(ENGINE.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


MODULES = {_module_name(p): p for p in sorted(ENGINE.rglob("*.py"))}


def layer_of(module: str) -> int:
    """Index in :data:`LAYERS` of an engine module (the package root counts as ``api``)."""
    parts = module.split(".")
    name = parts[1] if len(parts) > 1 else "api"
    return LAYERS.index(ENTRY_POINTS.get(name, name))


def _resolve(module: str, node: ast.ImportFrom, is_package: bool) -> list[str]:
    """The engine modules an ``import`` statement names (its module, or the submodules it imports)."""
    if node.level:
        base = module.split(".") if is_package else module.split(".")[:-1]
        base = base[: len(base) - node.level + 1]
        target = ".".join(base + ([node.module] if node.module else []))
    else:
        target = node.module or ""
    if not target.startswith("magcal"):
        return []
    found = []
    for alias in node.names:
        sub = f"{target}.{alias.name}"
        found.append(sub if sub in MODULES else target)
    return found


def engine_imports(module: str):
    """``(target, line, at_top)`` for each engine module ``module`` imports."""
    path = MODULES[module]
    tree = ast.parse(path.read_text(encoding="utf-8"))
    top = set(map(id, tree.body))
    # statements at the top of the module, including those under ``if TYPE_CHECKING`` / ``try``
    for node in tree.body:
        if isinstance(node, (ast.If, ast.Try)):
            top |= set(map(id, ast.walk(node)))
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            targets = _resolve(module, node, path.name == "__init__.py")
        elif isinstance(node, ast.Import):
            targets = [a.name for a in node.names if a.name.startswith("magcal")]
        else:
            continue
        for target in targets:
            while target not in MODULES and "." in target:
                target = target.rsplit(".", 1)[0]
            if target != module:
                yield target, node.lineno, id(node) in top


def third_party_imports(module: str):
    tree = ast.parse(MODULES[module].read_text(encoding="utf-8"))
    for node in tree.body:
        if isinstance(node, ast.Import):
            yield from ((a.name.split(".")[0], node.lineno) for a in node.names)
        elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
            yield node.module.split(".")[0], node.lineno


def test_every_module_is_in_a_layer():
    stray = [m for m in MODULES if m != "magcal" and m.split(".")[1] not in LAYERS + tuple(ENTRY_POINTS)]
    assert not stray, f"modules outside the layers {LAYERS}: {stray}"


#: Modules whose engine imports may wait until a function runs: the command line's entry point, so that ``magcal
#: --help`` starts in about the time of ``import magcal`` and ``magcal COMMAND`` imports only that command.
LAZY_MODULES = ("magcal.cli",)


@pytest.mark.parametrize("module", sorted(MODULES))
def test_imports_point_down_and_sit_at_the_top(module):
    problems = []
    for target, line, at_top in engine_imports(module):
        if layer_of(target) > layer_of(module):
            problems.append(f"line {line}: {target} is in a higher layer")
        if not at_top and module not in LAZY_MODULES:
            problems.append(f"line {line}: {target} imported inside a function")
    assert not problems, f"{module}: " + "; ".join(problems)


@pytest.mark.parametrize("module", sorted(MODULES))
def test_optional_dependencies_are_imported_where_used(module):
    found = [f"line {line}: {name}" for name, line in third_party_imports(module) if name in OPTIONAL]
    assert not found, f"{module} imports an extra's package at its top: {found}"


def test_no_import_circle():
    graph = {m: {t for t, _, _ in engine_imports(m)} for m in MODULES}
    # a package's __init__ re-exporting its own modules is not a circle through them
    for m in graph:
        graph[m] = {t for t in graph[m] if not (m.startswith(t + ".") and MODULES[t].name == "__init__.py")}
    state, path = {}, []

    def visit(m):
        state[m] = "open"
        path.append(m)
        for t in sorted(graph[m]):
            if state.get(t) == "open":
                cycle = path[path.index(t) :] + [t]
                raise AssertionError("import circle: " + " -> ".join(cycle))
            if t not in state:
                visit(t)
        path.pop()
        state[m] = "done"

    for m in sorted(graph):
        if m not in state:
            visit(m)


def test_the_rule_finds_an_upward_import(tmp_path, monkeypatch):
    """The layer rule itself: a module of ``core`` importing ``fitting`` is reported."""
    fake = tmp_path / "magcal" / "core" / "bad.py"
    fake.parent.mkdir(parents=True)
    fake.write_text("from magcal.fitting import fitter\n\ndef f():\n    from magcal.data import io\n")
    monkeypatch.setitem(MODULES, "magcal.core.bad", fake)
    monkeypatch.setattr(pathlib.Path, "relative_to", pathlib.Path.relative_to)
    found = list(engine_imports("magcal.core.bad"))
    assert ("magcal.fitting.fitter", 1, True) in found
    assert ("magcal.data.io", 4, False) in found
    with pytest.raises(AssertionError, match="higher layer"):
        test_imports_point_down_and_sit_at_the_top("magcal.core.bad")
