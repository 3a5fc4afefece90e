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


# --- one seam from the library to the page: fits and diagnoses through the fit modes ----------------------------
ENGINE = PACKAGE.parent / "magcal"

#: The engine's layers whose names the workbench reaches only through :mod:`magcal.modes` (a fit mode's ``fit``,
#: ``validate``, ``diagnose`` and the options and methods it documents), so that the page and
#: ``magcal.calibrate(ds, mode=...)`` run one code path.
BEHIND_THE_MODES = ("magcal.fitting", "magcal.diagnosis")

#: What the workbench may still use of those layers, ``(workbench module, the engine's dotted name)``, each with why.
#: A name not here fails the rule: call the fit mode (extend its documented options when the page needs more).
SEAM_ALLOWED = {
    # display facts and names, no physics runs
    ("gravitymodel", "magcal.fitting.gravity.HEADING_MAX_PITCH_DEG"): "where a heading means something (a constant)",
    ("compensationmodel", "magcal.fitting.compensation.COMPENSATION_EFFECTS"): "the terms beyond TL, by name",
    ("sessionfile", "magcal.fitting.compensation.COMPENSATION_EFFECTS"): "the session file's terms checked by name",
    ("compensationmodel", "magcal.fitting.compensation.check_effects"): "terms' names checked before the mode fits",
    ("plots", "magcal.diagnosis.vector.evidence_channel"): "the channel a candidate is plotted against (a name)",
    # the record the compensation mode fits, made once: the page draws its band-passed traces too
    ("compensationmodel", "magcal.fitting.compensation.compensation_record"): "the flight's record the mode fits",
    # the cross's page: the same as the scalar's, by the cross's names
    ("crosscompensationmodel", "magcal.fitting.compensation.COMPENSATION_EFFECTS"): "what each term is, in words",
    ("crosscompensationmodel", "magcal.diagnosis.cross_compensation.CROSS_EFFECTS"): "the cross's terms, by name",
    ("crosscompensationmodel", "magcal.diagnosis.cross_compensation.check_cross_effects"): "terms' names checked",
    ("crosscompensationmodel", "magcal.diagnosis.cross_compensation.cross_record"): "the flight's record, made once",
    # the diagnosis's worker processes, started when the page opens a record so that the first Diagnose is quick
    ("controller", "magcal.diagnosis.start_workers"): "the diagnosis's pool started ahead",
    # the maps draw the diagnosis's patterns on the sphere of directions (no fit)
    ("maps", "magcal.diagnosis.residual_patterns"): "the residual's pattern the map draws",
    ("maps", "magcal.diagnosis.candidate_patterns"): "a candidate's pattern the map draws",
    # the total-field page's own stages, which the total-field mode does not offer (its fit is the whole pipeline,
    # its refine the maximum likelihood from a calibration, its validate the base model against the effects):
    # step 1, an ellipsoid per sensor with the rotations reset
    ("totalfield", "magcal.fitting.fitter.fit_reference"): "step 1: the reference the ellipsoids are fitted to",
    ("totalfield", "magcal.fitting.pipeline.ellipsoid_step"): "step 1: an ellipsoid per sensor",
    ("totalfield", "magcal.fitting.pipeline.two_step_calibration"): "step 1: its calibration, rotations the identity",
    # step 2, the Procrustes rotations of the current calibration
    ("totalfield", "magcal.fitting.pipeline.align_sensors"): "step 2: sensors 2-4 turned into sensor 1's frame",
    # the history's held-out RMS: the blocks scheme warm-started from the fit, in the background
    ("totalfield", "magcal.fitting.validation.split_problem"): "why a record cannot be split in blocks",
    ("totalfield", "magcal.fitting.validation.validate"): "the held-out RMS of the fit's own model on blocks",
}


def _is_engine_module(dotted: str) -> bool:
    path = ENGINE.parent.joinpath(*dotted.split("."))
    return path.with_suffix(".py").is_file() or (path / "__init__.py").is_file()


def _dotted(node) -> list[str] | None:
    """``a.b.c`` of an attribute chain on a name, as ``["a", "b", "c"]``; None for any other expression."""
    parts = []
    while isinstance(node, ast.Attribute):
        parts.append(node.attr)
        node = node.value
    if not isinstance(node, ast.Name):
        return None
    return [node.id, *reversed(parts)]


def _behind(dotted: str) -> bool:
    return any(dotted == layer or dotted.startswith(layer + ".") for layer in BEHIND_THE_MODES)


def seam_uses(source: str) -> set[str]:
    """The engine's names behind the modes (:data:`BEHIND_THE_MODES`) that a workbench module's ``source`` uses:
    names it imports from them, and attributes it reaches on a module of them (``pipeline.calibrate`` after ``from
    magcal.fitting import pipeline``, ``magcal.fitting.vector.fit_vector`` after ``import magcal``), fully dotted."""
    tree = ast.parse(source)
    modules: dict[str, str] = {}  # a local name -> the engine module it is bound to
    used = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and not node.level and (node.module or "").split(".")[0] == "magcal":
            for alias in node.names:
                full = f"{node.module}.{alias.name}"
                if _is_engine_module(full):
                    modules[alias.asname or alias.name] = full
                elif _behind(full):
                    used.add(full)
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] == "magcal":
                    local = alias.asname or alias.name.split(".")[0]
                    modules[local] = alias.name if alias.asname else "magcal"
    for node in ast.walk(tree):
        parts = _dotted(node) if isinstance(node, ast.Attribute) else None
        if not parts or parts[0] not in modules:
            continue
        names = modules[parts[0]].split(".") + parts[1:]
        # the longest engine module the chain names, and the name reached on it
        for cut in range(len(names) - 1, 0, -1):
            if _is_engine_module(".".join(names[:cut])):
                full = ".".join(names[: cut + 1])
                if _behind(full) and not _is_engine_module(full):
                    used.add(full)
                break
    return used


SEAM_USES = {(m, name) for m, path in MODULES.items() for name in seam_uses(path.read_text(encoding="utf-8"))}


@pytest.mark.parametrize("name", sorted(MODULES))
def test_the_page_fits_and_diagnoses_through_the_fit_modes(name):
    """A workbench module uses no fitter or diagnosis of the engine but through ``magcal.modes`` (``VECTOR.fit``,
    ``GRAVITY.separate_calibration``, ``TOTAL_FIELD.diagnose``...), except what :data:`SEAM_ALLOWED` lists."""
    reached = sorted(full for m, full in SEAM_USES if m == name and (m, full) not in SEAM_ALLOWED)
    assert not reached, (
        f"{name}.py uses {reached} of the engine's fitting or diagnosis layer: call the fit mode instead "
        "(magcal.modes; extend its documented options when the page needs more), or add the name to SEAM_ALLOWED "
        "with why"
    )


def test_the_seams_allow_list_holds_only_what_is_used():
    """An allowed name the workbench no longer uses leaves the list (it only shrinks as the modes cover more)."""
    stale = sorted(set(SEAM_ALLOWED) - SEAM_USES)
    assert not stale, f"SEAM_ALLOWED lists names the workbench does not use: {stale}"


def test_the_seam_rule_finds_a_fitter_reached_past_the_mode():
    found = seam_uses(
        "import magcal\n"
        "import magcal.diagnosis.vector as dv\n"
        "from magcal.fitting.vector import fit_vector\n"
        "from magcal.fitting import pipeline\n"
        "from magcal.modes import VECTOR\n"
        "from magcal.checks.reference import parse_date\n"
        "def f(ds):\n"
        "    pipeline.calibrate(ds)\n"
        "    magcal.fitting.gravity.fit_gravity(ds)\n"
        "    dv.diagnose_vector(ds)\n"
        "    VECTOR.fit(ds)\n"
        "    magcal.calibrate(ds)\n"
    )
    assert found == {
        "magcal.fitting.vector.fit_vector",
        "magcal.fitting.pipeline.calibrate",
        "magcal.fitting.gravity.fit_gravity",
        "magcal.diagnosis.vector.diagnose_vector",
    }
    assert not (set(SEAM_ALLOWED) & {("vectormodel", f) for f in found})
    with pytest.raises(AssertionError, match="call the fit mode"):
        SEAM_USES.add(("vectormodel", "magcal.fitting.vector.fit_vector"))
        try:
            test_the_page_fits_and_diagnoses_through_the_fit_modes("vectormodel")
        finally:
            SEAM_USES.discard(("vectormodel", "magcal.fitting.vector.fit_vector"))
