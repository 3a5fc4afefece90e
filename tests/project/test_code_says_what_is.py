"""The packages say what is and why, not their history: no line of ``magcal/`` or ``magcal_workbench/`` cites an
issue number ("issue 40", "issues 31, 41"). History lives in git and in ``benchmarks/notes``; a reader of the code
cannot follow a number to anything.
"""

from __future__ import annotations

import pathlib
import re

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2]

#: "issue 40", "Issue 43 item 5", "issues 31, 41", "issue #12".
ISSUE_NUMBER = re.compile(r"\b[Ii]ssues? ?#?\d+")


def issue_citations(path: pathlib.Path) -> list[str]:
    """``"LINE: text"`` for each line of ``path`` that cites an issue number."""
    lines = path.read_text(encoding="utf-8").splitlines()
    return [f"{i}: {line.strip()}" for i, line in enumerate(lines, 1) if ISSUE_NUMBER.search(line)]


@pytest.mark.parametrize("package", ["magcal", "magcal_workbench"])
def test_no_line_of_the_package_cites_an_issue_number(package):
    found = {
        str(path.relative_to(ROOT)): hits
        for path in sorted((ROOT / package).rglob("*.py"))
        if (hits := issue_citations(path))
    }
    assert not found, f"say what is and why instead of citing issues: {found}"


@pytest.mark.parametrize(
    ("line", "cites"),
    [
        ("# coverage (issue 6)", True),
        ('"""The vehicle view (Issue 29 item 3): ..."""', True),
        ("Who may connect (issues 31, 41)", True),
        ("see issue #12", True),
        ("the tissue 3 layers", False),
        ("a stale issue: nothing is cited", False),
    ],
)
def test_the_rule_finds_a_citation(tmp_path, line, cites):
    path = tmp_path / "m.py"
    path.write_text(line + "\n", encoding="utf-8")
    assert bool(issue_citations(path)) is cites
