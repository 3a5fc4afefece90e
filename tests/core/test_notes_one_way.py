"""Notes travel one way (item 4): a step of the engine returns what it has to say in its result's
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


#: The engine's functions that take notes as a parameter, each with why (a step returns its notes
#: in its result; none takes a list to fill for its caller, nor warns when none is given). Keyed
#: ``module:function`` (module relative to magcal/, without ``.py``).
_LOGS_READ = (
    "a private step of one log read: appends to that read's own list, which read_dataflash / read_ulog return as "
    "the Dataset's notes"
)
_READS = "reads the notes it is given (to print, raise, move or keep); fills no list of its caller's"
TAKES_NOTES = {
    # the boundary: the command line prints the notes it is given
    "cli/calibrate:run_fit": "the command line: collects the texts it prints",
    "cli/calibrate:compass_report": "the command line: collects the texts it prints",
    "cli/diagnose:run_mode": "the command line: collects the texts it prints",
    "cli/compensation_mode:run_cross_compensation": "the command line: collects the texts it prints",
    "cli/compensation_mode:run_cross_compensation_diagnosis": "the command line: collects the texts it prints",
    "cli/diagnose:run_vector": "the command line: collects the texts it prints",
    "cli/fit_report:report_fit": "the command line: prints the texts it is given",
    # the one place notes become warnings, and its helpers
    "core/notes:unique": _READS,
    "core/notes:texts": _READS,
    "core/notes:warn": "the boundary's one use of warnings (magcal.read_csv, magcal.calibrate... call it)",
    "core/registry:__init__": "Loaded, the entry-point loaders' result: holds its notes",
    "data/io:_with_notes": "sets the notes of the dataset a read returns",
    "output/apply:_moved": "moves a streaming reader's notes (CsvSource.notes) to the apply run's, in order",
    "fitting/pipeline:take": "_Run.take: sorts a step's returned notes into the calibrate run's",
    "output/export:_header_lines": _READS,
    "output/export:_ardupilot": _READS,
    "output/export:_px4": _READS,
    "output/export:_c_header": _READS,
    # private pieces of one step that gather into that step's own list, returned in its result
    "data/logs:_strictly_increasing": _LOGS_READ,
    "data/logs:_drop_bad": _LOGS_READ,
    "data/logs:_pair_by_time": _LOGS_READ,
    "data/logs:_interp_attitude": _LOGS_READ,
    "data/logs:_build": _LOGS_READ,
    "data/logs:_alive": _LOGS_READ,
    "data/logs:_select": _LOGS_READ,
    "data/logs:_imu_channels": _LOGS_READ,
    "data/logs:_position": _LOGS_READ,
    "data/logs:_dataflash_dataset": _LOGS_READ,
    "data/logs:_ulog_dataset": _LOGS_READ,
    "data/logs:_px4_logged_fields": _LOGS_READ,
    "data/logs:_ulog_imu": _LOGS_READ,
    "data/logs:_ulog_position": _LOGS_READ,
    "data/logs:_ulog_attitude": _LOGS_READ,
    "data/logs:_ulog_calibrated_field": _LOGS_READ,
    "data/logs:_ulog_current": _LOGS_READ,
    "diagnosis/verdict:_judge_round": "a private round of one diagnosis: its list is returned in Diagnosis.notes",
    "diagnosis/verdict:_add_fit_notes": "a private round of one diagnosis: its list is returned in Diagnosis.notes",
    "fitting/vector:_fit_sensor": "one sensor of one vector fit: its list is returned in VectorFitResult.warnings",
}


def _takes_notes(tree) -> list[str]:
    """Names of the functions in ``tree`` with a parameter ``notes`` or ``*_notes``."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            a = node.args
            params = [p.arg for p in a.posonlyargs + a.args + a.kwonlyargs]
            if any(p == "notes" or p.endswith("_notes") for p in params):
                found.append(node.name)
    return found


def test_no_step_takes_a_list_of_notes_to_fill():
    found = {
        f"{path.relative_to(ENGINE).with_suffix('').as_posix()}:{name}"
        for path in _engine_files() + [ONE_PLACE]
        for name in _takes_notes(ast.parse(path.read_text(encoding="utf-8")))
    }
    unlisted = sorted(found - set(TAKES_NOTES))
    assert unlisted == [], f"these take notes as a parameter: return them in the step's result instead: {unlisted}"
    gone = sorted(set(TAKES_NOTES) - found)
    assert gone == [], f"listed in TAKES_NOTES but no longer taking notes: remove them from the list: {gone}"
    public = sorted(k for k in found if not k.split(":")[1].startswith("_") and not k.startswith(("cli/", "core/")))
    assert public == ["fitting/pipeline:take"], f"a public step takes notes: {public}"


def test_the_check_sees_a_notes_parameter():
    """The check above can fail: it finds the parameter wherever it stands."""
    tree = ast.parse(
        "def read(path, notes=None):\n    pass\ndef f(*, fit_notes):\n    pass\ndef g(notebook):\n    pass\n"
    )
    assert _takes_notes(tree) == ["read", "f"]


def test_the_readers_return_their_notes_and_warn_only_when_asked(tmp_path):
    """magcal.read_csv and magcal.read_log: the notes in the dataset's ``notes``; raised only with ``warn``."""
    import warnings

    from magcal.core.errors import DataWarning

    path = tmp_path / "twice.csv"
    path.write_text("# noise_nT: 1\n# noise_nT: 2\nx,y,z\n" + "".join(f"{50000 + k},{k},{-k}\n" for k in range(20)))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        quiet = magcal.read_csv(path, warn=False)
    said = [(n.text, n.category) for n in quiet.notes]
    assert said == [(f"{path}: line 2: metadata 'noise_nT' given twice; the last value '2' is used", DataWarning)]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        loud = magcal.read_csv(path)
    assert [(str(w.message), w.category) for w in caught] == said and loud.notes == quiet.notes
    assert caught[0].filename == __file__  # the warning points at the user's call


def test_a_calibrations_remarks_are_report_lines_never_raised():
    """CalibrationResult.remarks: the report's "Warnings" lines (the JSON's ``"warnings"``), information that is
    never raised; what is raised is ``notes``."""
    import warnings

    from magcal.calibration.report import text_report

    ds = magcal.simulate("chi2017", seed=2)
    ds.noise_nT = None  # the floors then use an estimate, which the report says
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a remark is never a Python warning
        result = magcal.calibrate(ds, reference_total_nT=50000)
    assert any(r.startswith("noise not given: the floors use sigma = ") for r in result.remarks), result.remarks
    assert result.notes == [] and result.warnings == []  # the raised notes' texts: none here
    assert result.calibration.summary["warnings"] == result.remarks
    report = text_report(result)
    assert report.split("Warnings:\n")[1].splitlines()[: len(result.remarks)] == [f"  - {r}" for r in result.remarks]
