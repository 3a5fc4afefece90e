"""The README's "From Python" script runs as written, uses only the public API, and finds the effect it hides."""

import ast
import re
from pathlib import Path

import numpy as np
import pytest

import magcal

README = Path(__file__).resolve().parents[2] / "README.md"


def _from_python_block():
    text = README.read_text(encoding="utf-8")
    start = text.index("From Python")
    blocks = re.findall(r"```python\n(.*?)```", text[start:], re.S)
    assert blocks, "README: no ```python block after 'From Python'"
    return blocks[0]


def test_the_script_uses_only_the_public_api():
    tree = ast.parse(_from_python_block())
    imported = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            assert not (node.module or "").startswith("magcal"), f"README imports from {node.module}"
        elif isinstance(node, ast.Import):
            imported.update(a.name for a in node.names)
    assert imported <= {"magcal", "numpy"}, imported
    used = {
        node.attr
        for node in ast.walk(tree)
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "magcal"
    }
    assert used, "the script calls nothing of magcal"
    assert used <= set(magcal.__all__), f"not in magcal.__all__: {sorted(used - set(magcal.__all__))}"


@pytest.fixture(scope="module")
def ran(tmp_path_factory):
    """Run the block once in an empty folder; keep its variables and what it printed."""
    import contextlib
    import io
    import os

    folder = tmp_path_factory.mktemp("readme")
    code = compile(_from_python_block(), str(README) + ":From Python", "exec")
    namespace = {"__name__": "__readme__"}
    printed = io.StringIO()
    old = os.getcwd()
    os.chdir(folder)
    try:
        with contextlib.redirect_stdout(printed):
            exec(code, namespace)
    finally:
        os.chdir(old)
    return namespace, printed.getvalue(), folder


def test_the_diagnosis_names_the_hidden_effect(ran):
    namespace, printed, _ = ran
    hidden = namespace["hidden"]
    label = hidden.effect if hidden.sensor is None else f"{hidden.effect}:{hidden.sensor + 1}"
    assert namespace["diagnosis"].verdict == "missing_effect"
    assert namespace["diagnosis"].explained_by == [label]
    assert label in printed  # the reader sees it named


def test_the_calibration_with_the_effect_is_saved_and_applies_to_the_new_record(ran):
    namespace, printed, folder = ran
    saved = magcal.Calibration.load(folder / "cal.json")
    new = namespace["new"]
    np.testing.assert_allclose(saved.correct(new), namespace["corrected"], rtol=0, atol=1e-6)
    assert namespace["corrected"].shape == new.readings_nT.shape
    assert printed.count("\n") >= 5  # every step printed a line
