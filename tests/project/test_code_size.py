"""Functions of the engine stay short enough to read (item 3): none longer than :data:`MAX_LINES` lines
of body (its docstring left out) unless a comment ``# long: <why>`` says why, directly above its ``def`` (or its
first decorator) or on the first line of its body. Their cyclomatic complexity is held by ruff (C901,
``max-complexity`` in ruff.toml), which ``ruff check .`` runs in .ci/run."""

from __future__ import annotations

import ast
import pathlib
import textwrap

import pytest

ENGINE = pathlib.Path(__file__).resolve().parents[2] / "magcal"

#: Most lines of a function's body, its docstring left out.
MAX_LINES = 120

#: The comment that lets a function be longer, with its reason after the colon.
LONG = "# long:"

FUNCTIONS = (ast.FunctionDef, ast.AsyncFunctionDef)


def body_lines(node: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    """Lines from the first statement of ``node``'s body after its docstring to its last line (blank lines and
    comments inside count; a nested function counts towards the one that holds it)."""
    body = node.body
    if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
        if isinstance(body[0].value.value, str):
            body = body[1:]
    if not body:
        return 0
    assert node.end_lineno is not None
    return node.end_lineno - body[0].lineno + 1


def marked_long(node: ast.FunctionDef | ast.AsyncFunctionDef, lines: list[str]) -> bool:
    """Whether a ``# long: <why>`` comment (a reason given; it may wrap onto further comment lines) sits directly
    above the function's ``def`` (or its first decorator) or on the first line of its body (after the signature,
    before or after the docstring)."""
    top = min([node.lineno] + [d.lineno for d in node.decorator_list])
    places = [top - 1]  # 1-based line numbers
    first = node.body[0]
    places.append(first.lineno - 1)  # the line just above the first statement (the docstring, or the code)
    if len(node.body) > 1:
        places.append(node.body[1].lineno - 1)  # just above the first statement after the docstring
    for place in places:
        # the comment ending on that line: its lines up to the first that is not a comment (a reason may wrap)
        while 1 <= place <= len(lines) and lines[place - 1].strip().startswith("#"):
            text = lines[place - 1].strip()
            if text.startswith(LONG) and text[len(LONG) :].strip():
                return True
            place -= 1
    return False


def too_long(source: str, name: str = "<source>") -> list[str]:
    """``module:line function (n lines)`` for every function of ``source`` longer than :data:`MAX_LINES` lines of
    body and not marked :data:`LONG`."""
    lines = source.splitlines()
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, FUNCTIONS):
            n = body_lines(node)
            if n > MAX_LINES and not marked_long(node, lines):
                out.append(f"{name}:{node.lineno} {node.name} ({n} lines)")
    return out


def _function(lines: int, above: str = "", first: str = "", docstring: bool = True) -> str:
    """A function of ``lines`` body lines (after its docstring), ``above`` its ``def`` and ``first`` in its body."""
    body = [first] if first else []
    if docstring:
        body.append('"""A docstring\n\nof three lines."""')
    body += [f"x{i} = {i}" for i in range(lines - (1 if first and not docstring else 0))]
    text = "def f():\n" + textwrap.indent("\n".join(body), "    ") + "\n"
    return (above + "\n" if above else "") + text


def test_the_count_leaves_the_docstring_out_and_the_marker_needs_a_reason():
    assert too_long(_function(MAX_LINES)) == []
    assert too_long(_function(MAX_LINES + 1)) == ["<source>:1 f (121 lines)"]
    assert too_long(_function(MAX_LINES + 1, docstring=False)) == ["<source>:1 f (121 lines)"]
    assert too_long(_function(MAX_LINES + 5, above="# long: one table of cases, read top to bottom")) == []
    assert too_long(_function(MAX_LINES + 5, first="# long: one table of cases")) == []
    assert too_long(_function(MAX_LINES + 5, first="# long: one table", docstring=False)) == []
    assert too_long(_function(MAX_LINES + 5, above="# long:"))  # no reason given
    assert too_long(_function(MAX_LINES + 5, above="# long: why\n"))  # not directly above
    assert too_long(_function(MAX_LINES + 5, above="# long: a reason that\n# wraps")) == []
    assert too_long(_function(MAX_LINES + 5, above="# a comment\n# of something else"))
    decorated = "# long: a reason\n@staticmethod\n" + _function(MAX_LINES + 5)
    assert too_long(decorated) == []
    nested = "def outer():\n" + textwrap.indent(_function(MAX_LINES + 5), "    ")
    found = too_long(nested)
    assert len(found) == 2 and "outer" in found[0] + found[1]


@pytest.mark.parametrize("path", sorted(ENGINE.rglob("*.py")), ids=lambda p: str(p.relative_to(ENGINE)))
def test_no_engine_function_is_longer_than_the_limit_without_saying_why(path):
    found = too_long(path.read_text(encoding="utf-8"), str(path.relative_to(ENGINE.parent)))
    assert not found, (
        f"functions longer than {MAX_LINES} lines (docstring left out): split them, or put '# long: <why>' "
        "directly above the def: " + "; ".join(found)
    )


def test_ruff_holds_every_function_to_a_complexity_of_25():
    """.ci/run's ``ruff check .`` enforces C901 with ``max-complexity`` 25 (ruff.toml), for the engine too."""
    import tomllib

    config = tomllib.loads((ENGINE.parent / "ruff.toml").read_text(encoding="utf-8"))
    lint = config["lint"]
    assert "C901" in lint["select"]
    assert lint["mccabe"]["max-complexity"] <= 25
    for pattern, ignored in lint.get("per-file-ignores", {}).items():
        assert not ("C901" in ignored and "magcal" in pattern), pattern
    assert "ruff check ." in (ENGINE.parent / ".ci" / "run").read_text(encoding="utf-8")
