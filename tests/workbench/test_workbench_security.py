"""Untrusted text and files in the workbench (items 1 and 3).

viser renders markdown with raw HTML: every text the workbench did not write (uploaded file names and contents,
session fields, a user's effects) must reach the page escaped and cut to a sane length. A damaged session file
must not stop the workbench: one reader checks every field and says which one is wrong, the folder is moved
aside and the data open afresh. Session names never leave the session folder.
"""

from __future__ import annotations

import copy
import json
import textwrap
from html.parser import HTMLParser

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import magcal
from magcal.data import io as mio
from magcal_workbench.markup import ELLIPSIS, clean_text, safe_code, safe_text
from magcal_workbench.session import SessionStore, check_session_name
from magcal_workbench.sessionfile import SessionError, SessionFileError, read_session_bytes, read_session_document
from magcal_workbench.state import SessionState, StepRecord

XSS = "<img src=x onerror=alert(1)>"


# ---------------------------------------------------------------------------------------------------------------
# the escaping helper, checked by a CommonMark renderer with raw HTML on (as viser's client renders)
# ---------------------------------------------------------------------------------------------------------------
markdown_it = pytest.importorskip("markdown_it")
MD = markdown_it.MarkdownIt("commonmark", {"html": True}).enable(["table", "strikethrough"])


class _Parsed(HTMLParser):
    def __init__(self, html):
        super().__init__(convert_charrefs=True)
        self.tags, self.text = [], []
        self.feed(html)
        self.close()

    def handle_starttag(self, tag, attrs):
        self.tags.append(tag)

    def handle_startendtag(self, tag, attrs):
        self.tags.append(tag)

    def handle_data(self, data):
        self.text.append(data)


def rendered(markdown: str) -> tuple[list, str]:
    """The HTML elements and the text a markdown string renders to."""
    p = _Parsed(MD.render(markdown))
    return p.tags, "".join(p.text)


#: Where the workbench puts untrusted text, and the elements that context makes by itself.
CONTEXTS = [
    ("{}", ["p"]),
    ("**Error:** {}", ["p", "strong"]),
    ("- {}", ["ul", "li"]),
    ("| step | what |\n|---|---|\n| 1 | {} |", ["table", "thead", "tr", "th", "th", "tbody", "tr", "td", "td"]),
]
HOSTILE = [
    XSS,
    "<script>alert(1)</script>",
    "[click](javascript:alert(1))",
    "![x](http://evil.example/t.png)",
    "**bold** _it_ `code` ~~gone~~",
    "a | b | c",
    "# heading",
    "1. item",
    "- item",
    "<http://evil.example>",
    "&lt;img src=x onerror=alert(1)&gt;",
    "line one\nline two\r\n<b>three</b>",
    "\x1b[31mred\x00\x7f",
    "back\\slash \\<b>",
    "\u202egnp.exe",
]


@pytest.mark.parametrize("context, elements", CONTEXTS)
@pytest.mark.parametrize("text", HOSTILE)
def test_safe_text_renders_as_the_characters_it_holds(text, context, elements):
    tags, shown = rendered(context.format(safe_text(text)))
    assert tags == elements  # no element from the text: no img, script, a, em, h1, extra cell...
    assert clean_text(text) in shown  # and every character of it is shown as itself


@settings(max_examples=300, deadline=None)
@given(st.text(max_size=80) | st.text(alphabet="<>&*_[]()!`|#~-+=.\\ 1aA:/\"'{}$\n\t", max_size=80))
def test_no_text_becomes_markup(text):
    for context, elements in CONTEXTS:
        if not clean_text(text):
            continue
        tags, shown = rendered(context.format(safe_text(text)))
        assert tags == elements and clean_text(text) in shown


@pytest.mark.parametrize("max_len", [1, 40, 300])
def test_long_text_is_cut_with_an_ellipsis(max_len):
    header = "<" + "a" * 3_000_000
    out = clean_text(header, max_len)
    assert len(out) == max_len and out.endswith(ELLIPSIS)
    assert rendered(safe_text(header, max_len))[1].strip() == out
    assert safe_text("short", max_len=300) == "short" and clean_text(None) == ""


def test_control_characters_and_direction_overrides_are_removed():
    assert clean_text("a\x00b\x1bc\u202ed\ne\tf") == "a b c d e f"
    assert safe_code("a`b<c>") == "`a'b<c>`"  # in a code span nothing is markup: only the backtick matters
    assert rendered(f"x {safe_code('`' + XSS)}")[0] == ["p", "code"]


# ---------------------------------------------------------------------------------------------------------------
# the page's code paths, headless (real viser server, no browser)
# ---------------------------------------------------------------------------------------------------------------
BENCH_SAMPLES = 200  # the bench fixture (tests/conftest.py) opens this many samples by default


def _upload(wb, name, content):
    class Upload:
        pass

    up = Upload()
    up.name, up.content = name, content
    wb.panels.upload._impl.value = up  # what the browser's upload sets
    wb.uploads.do_upload(None)
    assert wb.worker.wait(60)
    wb.panels.refresh(("message",))
    return wb.panels.message.content


def _no_markup(markdown: str, allowed=("p", "strong", "code", "br", "ul", "li")):
    tags, shown = rendered(markdown)
    assert set(tags) <= set(allowed), (tags, markdown)
    return shown


@pytest.mark.parametrize(
    "name, content, shown",
    [
        ("data.csv", f"{XSS},s1y,s1z\n1,2,3\n".encode(), XSS),  # echoed header
        ("data.csv", b"s1x,s1y,s1z\n1,<b onmouseover=alert(1)>x</b>,3\n", "<b onmouseover=alert(1)>x</b>"),  # cell
        (f"{XSS}.csv", b"s1x,s1y\n1,2\n", f"{XSS}.csv"),  # the upload's name
    ],
)
def test_file_names_and_contents_reach_the_page_escaped(bench, name, content, shown):
    wb = bench(store=False)
    message = _upload(wb, name, content)
    assert "**Error:**" in message and "<img" not in message and "<b " not in message
    assert shown in _no_markup(message)  # the user sees what the file holds, as text


def test_an_uploaded_file_name_is_escaped_when_it_opens(bench, tmp_path):
    wb = bench(store=False)
    ds = magcal.simulate("chi2017", n_samples=60, seed=2)
    path = tmp_path / "ok.csv"
    mio.write_csv(path, ds)
    message = _upload(wb, f"{XSS}*.csv", path.read_bytes())
    assert f"{XSS}*.csv" in _no_markup(message) and wb.ctrl.dataset.n_samples == 60
    wb.panels.refresh(("all", "data"))
    assert XSS in _no_markup(wb.panels.data_info.content)


def test_a_3_megabyte_header_is_cut(bench):
    wb = bench(store=False)
    # 900 KB of column names, echoed by the reader ("no magnetometer columns; the header is ..."): within the CSV
    # reader's limits (a line of at most 1 MiB, 1000 columns; a 3 MB header is now refused before it is read whole)
    header = ",".join(f"<c{i}>" + "x" * 890 for i in range(1000))
    assert len(header) > 890_000
    message = _upload(wb, "wide.csv", (header + "\n" + ",".join("1" * 1000) + "\n").encode())
    assert "wide.csv" in message and len(message) < 3000 and (ELLIPSIS in message or "..." in message)
    assert "<c0>" in _no_markup(message)  # the columns quoted, each cut short (at most 40 characters)


def test_session_fields_reach_the_page_escaped(bench, tmp_path):
    wb = bench()
    st_ = wb.ctrl.state
    st_.record(StepRecord(f"fit {XSS}", 3.0, 2.9, [], 200, "| a | b | [x](javascript:alert(1))", 0.1))
    wb.store.save(wb.ctrl.session_id, st_)
    wb.stop()
    again = bench()
    again.panels.refresh(("all", "data"))
    # (the table may be followed by the workbench's own italic note: p, em)
    shown = _no_markup(again.panels.history.content, allowed=("table", "thead", "tbody", "tr", "th", "td", "p", "em"))
    assert f"fit {XSS}" in shown and "[x](javascript:alert(1))" in shown


def test_a_user_effect_description_is_escaped(bench, tmp_path, clean_catalogue):
    path = tmp_path / "hostile.py"
    path.write_text(
        textwrap.dedent(f'''
        from dataclasses import dataclass
        from typing import ClassVar
        import numpy as np
        from magcal.model.terms import Effect, register

        @register
        @dataclass
        class Hostile(Effect):
            """{XSS} a constant offset."""
            name: ClassVar[str] = "hostile_offset"
            description: ClassVar[str] = "{XSS} **offset** | cell"
            def param_names(self):
                return ["h_x_nT", "h_y_nT", "h_z_nT"]
            def raw_basis(self, z0, ctx):
                return np.broadcast_to(np.eye(3), (len(z0), 3, 3)).copy()
    ''')
    )
    wb = bench(store=False, effects_files=[str(path)])
    wb.panels.effects_path.value = str(path)
    wb.panels.btn_load_effects.value = True
    assert wb.worker.wait(60)
    assert "hostile_offset" in wb.panels.effect_boxes  # the new effect got its checkbox
    assert XSS in wb.panels.effect_boxes["hostile_offset"].hint  # a tooltip is plain text (React escapes it)
    shown = _no_markup(wb.panels.user_effects.content)
    assert f"{XSS} **offset** | cell" in shown and "<img" not in wb.panels.user_effects.content


def test_a_toast_is_plain_text_cut_to_length(bench):
    from magcal.core.errors import MagcalError

    wb = bench(store=False)
    toasts = []

    class Client:
        def add_notification(self, title, body, **kw):
            toasts.append(body)

    class Event:
        client = Client()

    def fail(event):
        raise MagcalError(XSS + "x" * 100_000)

    wb.handle(fail, Event())
    assert len(toasts) == 1 and toasts[0].startswith(XSS) and len(toasts[0]) <= 300
    assert "<img" not in wb.ctrl.message and len(wb.ctrl.message) < 1200


# ---------------------------------------------------------------------------------------------------------------
# session names stay inside the session folder
# ---------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "name",
    [
        "..",
        ".",
        "../x",
        "/etc",
        "/etc/passwd",
        "a/b",
        "a\\b",
        "",
        ".hidden",
        "x\n",
        "C:\\x",
        "a" * 121,
        None,
        3,
        "x\x00",
    ],
)
def test_session_names_outside_the_folder_are_refused(tmp_path, name):
    store = SessionStore(tmp_path / "sessions")
    with pytest.raises(SessionError, match="not a session name"):
        check_session_name(name)
    with pytest.raises(SessionError):
        store.load(name)
    with pytest.raises(SessionError):
        store.data_path(name)


def test_reopen_refuses_a_name_outside_the_folder(bench, tmp_path):
    secret = tmp_path / "secret"
    secret.mkdir()
    (secret / "data.csv").write_text("s1x,s1y,s1z\n1,2,3\n")
    wb = bench()
    n = wb.ctrl.dataset.n_samples
    wb.panels.session_choice._impl.value = "../secret"  # a browser may send any value
    wb.panels.btn_reopen.value = True
    assert wb.worker.wait(30)
    assert "not one of the choices" in wb.ctrl.message and wb.ctrl.dataset.n_samples == n


@pytest.mark.parametrize("stem", [".hidden", "..", "-x", "a b/c"])
def test_session_ids_are_valid_names(stem):
    from magcal_workbench.session import session_id

    assert check_session_name(session_id(f"{stem}.csv", b"x")) == session_id(f"{stem}.csv", b"x")


# ---------------------------------------------------------------------------------------------------------------
# the validating reader
# ---------------------------------------------------------------------------------------------------------------
def _valid_doc(n=30, n_sensors=2) -> dict:
    st_ = SessionState(n, n_sensors, "/data/x.csv", lesson="warm-sensor")
    st_.selection.reject([3, 4, 5])
    st_.selection.restore([4])
    st_.add_effect("temperature_bias:2")
    st_.effects_files = ["/home/me/effects.py"]
    st_.method, st_.reference_nT, st_.robust, st_.sensor = "de", 51_000.0, True, 1
    st_.record(
        StepRecord("fit ellipsoid", 3.2, 2.9, ["temperature_bias:2"], n - 2, "RMS 700 -> 3.2 nT", 0.1),
        {"format": "magcal-calibration"},
    )
    st_.record(
        StepRecord(
            "refine (ML)",
            3.1,
            None,
            [],
            n - 2,
            "",
            0.2,
            fit={"success": False, "status": 0, "message": "max nfev", "nfev": 2},
        )
    )
    return json.loads(json.dumps(st_.to_dict()))


def test_a_valid_document_reads_back_the_same():
    doc = _valid_doc()
    st_ = read_session_document(doc)
    assert st_.to_dict() == doc
    assert list(st_.selection.rejected_indices) == [3, 5] and st_.selection.can_undo
    assert st_.effects_files == ["/home/me/effects.py"]


#: One damage per field, and the field the message must name.
DAMAGE = [
    ("n_samples", "30", "n_samples"),
    ("n_samples", 0, "n_samples"),
    ("n_samples", True, "n_samples"),
    ("n_sensors", 9, "n_sensors"),
    ("selection", [1, 2, 3], "selection"),
    ("selection.kept", 17, "selection.kept"),
    ("selection.kept", "not base64!", "selection.kept"),
    ("selection.kept", "AAAA", "selection.kept"),
    ("selection.n_samples", 31, "selection.n_samples"),
    ("selection.undo", [["AAAA"]], "selection.undo[0]"),
    ("sensor", 2, "sensor"),
    ("sensor", -1, "sensor"),
    ("sensor", 1.0, "sensor"),
    ("reference_nT", "51000", "reference_nT"),
    ("reference_nT", float("nan"), "reference_nT"),
    ("reference_nT", -5.0, "reference_nT"),
    ("history", {"step": "x"}, "history"),
    ("history", ["x"], "history[0]"),
    ("history.0.rms_nT", "3.2", "history[0].rms_nT"),
    ("history.0.n_kept", 31, "history[0].n_kept"),
    ("history.1.fit", {"success": "no"}, "history[1].fit.success"),
    ("effects", "temperature_bias", "effects"),
    ("effects", [1], "effects[0]"),
    ("effects", ["<img>"], "effects[0]"),
    ("effects", ["temperature_bias:3"], "effects[0]"),
    ("effects_files", ["relative.py"], "effects_files[0]"),
    ("method", "magic", "method"),
    ("robust", "yes", "robust"),
    ("lesson", "../x", "lesson"),
    ("format", "other", "format"),
    ("version", 2, "version"),
    ("calibration", [], "calibration"),
]


def _damage(doc, where, value):
    doc = copy.deepcopy(doc)
    *parents, last = where.split(".")
    node = doc
    for key in parents:
        node = node[int(key)] if isinstance(node, list) else node[key]
    node[int(last) if isinstance(node, list) else last] = value
    return doc


@pytest.mark.parametrize("where, value, field", DAMAGE)
def test_a_damaged_field_is_named(where, value, field):
    with pytest.raises(SessionFileError) as info:
        read_session_document(_damage(_valid_doc(), where, value), "s/session.json")
    assert info.value.field == field
    message = str(info.value)
    assert message.startswith(f"s/session.json: field '{field}': ") and "\n" not in message


@pytest.mark.parametrize(
    "data, problem",
    [
        (b"", "not JSON"),
        (b'{"format": ', "not JSON"),
        (b"\xff\xfe", "not UTF-8"),
        (b"[" * 100_000, "not JSON"),
        (b"[]", "must be an object"),
        (b"null", "must be an object"),
    ],
)
def test_undecodable_bytes_are_one_clear_error(data, problem):
    with pytest.raises(SessionFileError, match=problem):
        read_session_bytes(data)


JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**40), 2**40) | st.floats(allow_nan=True) | st.text(max_size=12),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=12,
)
FIELDS = [
    "format",
    "version",
    "data_path",
    "lesson",
    "n_samples",
    "n_sensors",
    "selection",
    "selection.kept",
    "selection.n_samples",
    "selection.undo",
    "selection.redo",
    "effects",
    "effects_files",
    "method",
    "reference_nT",
    "fit_reference",
    "robust",
    "sensor",
    "history",
    "history.0",
    "history.0.rms_nT",
    "history.0.effects",
    "history.0.n_kept",
    "history.1.fit",
    "history.1.fit.nfev",
    "calibration",
    "answer_revealed",
]


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(changes=st.lists(st.tuples(st.sampled_from(FIELDS), JSON_VALUES | st.just("DELETE")), max_size=4))
def test_fuzzed_session_documents_read_or_raise_the_one_error(changes):
    doc = _valid_doc()
    for where, value in changes:
        try:
            if value == "DELETE":
                *parents, last = where.split(".")
                node = doc
                for key in parents:
                    node = node[int(key)] if isinstance(node, list) else node[key]
                if isinstance(node, dict):
                    node.pop(last, None)
            else:
                doc = _damage(doc, where, value)
        except (KeyError, IndexError, TypeError, ValueError):
            continue  # an earlier change replaced the parent: this path no longer exists
    try:
        st_ = read_session_document(doc)
    except SessionFileError as exc:
        assert exc.field and "\n" not in str(exc)
        return
    # what it returns is a usable state: it writes a document the reader takes back unchanged
    again = read_session_document(json.loads(json.dumps(st_.to_dict())))
    # compared as JSON text: a NaN kept inside the calibration object reads back as NaN (NaN != NaN in Python)
    assert json.dumps(again.to_dict(), sort_keys=True) == json.dumps(st_.to_dict(), sort_keys=True)
    assert st_.kept.shape == (st_.n_samples,) and (st_.sensor is None or 0 <= st_.sensor < st_.n_sensors)


# ---------------------------------------------------------------------------------------------------------------
# a damaged session at start: moved aside, the data open afresh
# ---------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "damage, field",
    [
        (lambda doc: b'{"format": "magcal-workbench-session", "n_samp', "(file)"),
        (lambda doc: json.dumps(_damage(doc, "selection.kept", [1, 2])).encode(), "selection.kept"),
        (lambda doc: json.dumps(_damage(doc, "sensor", 99)).encode(), "sensor"),
        (lambda doc: json.dumps(_damage(doc, "history", [None])).encode(), "history[0]"),
        (lambda doc: json.dumps(_damage(doc, "n_sensors", 1)).encode(), "n_sensors"),  # another data's session
    ],
)
def test_a_damaged_session_is_moved_aside_and_the_data_open_afresh(bench, tmp_path, capsys, damage, field):
    wb = bench()
    wb.ctrl.select([1, 2])
    sid = wb.ctrl.session_id
    folder = tmp_path / "sessions" / sid
    doc = json.loads((folder / "session.json").read_text())
    wb.stop()
    broken = damage(doc)
    (folder / "session.json").write_bytes(broken)
    again = bench()
    assert again.ctrl.session_id == sid and again.ctrl.state.selection.n_rejected == 0  # afresh
    aside = [p for p in (tmp_path / "sessions").iterdir() if p.name.startswith(f"{sid}.damaged-")]
    assert len(aside) == 1 and (aside[0] / "session.json").read_bytes() == broken  # kept, not deleted
    assert (folder / "session.json").is_file() and (folder / "data.csv").is_file()  # a new session
    err = capsys.readouterr().err
    line = next(l for l in err.splitlines() if "damaged" in l)
    assert f"field '{field}'" in line and aside[0].name in line and "starting afresh" in line
    assert f"field '{field}'" in _no_markup(again.ctrl.message) and "Traceback" not in err
    assert sid in again.panels.session_choice.options and aside[0].name not in again.panels.session_choice.options


def test_a_damaged_calibration_in_a_valid_session_is_dropped_with_a_message(bench, tmp_path):
    wb = bench()
    wb.ctrl.step_ellipsoid()
    sid = wb.ctrl.session_id
    path = tmp_path / "sessions" / sid / "session.json"
    doc = json.loads(path.read_text())
    wb.stop()
    doc["calibration"] = {"format": "magcal-calibration", "sensors": [{"cinv": "x"}]}
    path.write_text(json.dumps(doc))
    again = bench()
    assert again.ctrl.calibration is None and "could not be restored" in again.ctrl.message
    assert np.isfinite(again.ctrl.raw_residual_nT()).all()


#: The damaged sessions the issue lists (each crashed the start with a traceback; only --fresh recovered).
ISSUE_DAMAGE = [
    ("n_samples", None),
    ("selection", []),
    ("sensor", 7),
    ("reference_nT", "abc"),
    ("history", [1, 2]),
    ("effects", [3.5]),
]


@pytest.mark.parametrize("field, value", ISSUE_DAMAGE)
def test_each_damaged_session_of_the_issue_starts_cleanly(bench, tmp_path, capsys, field, value):
    wb = bench()
    wb.ctrl.select([4, 5])
    sid = wb.ctrl.session_id
    path = tmp_path / "sessions" / sid / "session.json"
    doc = json.loads(path.read_text())
    wb.stop()
    doc[field] = value
    path.write_text(json.dumps(doc))
    again = bench()  # no exception: the app starts
    assert again.ctrl.state.selection.n_rejected == 0 and again.ctrl.dataset.n_samples == 200
    shown = _no_markup(again.ctrl.message)
    assert f"field '{field}" in shown and "moved aside" in shown
    assert str(tmp_path) not in again.ctrl.message  # the page is not told where the folder lives
    assert "Traceback" not in capsys.readouterr().err


def test_the_data_line_names_the_file_not_where_the_server_keeps_it(bench, tmp_path):
    wb = bench(store=False)
    wb.panels.refresh(("all", "data"))
    text = wb.panels.data_info.content
    assert "data.csv" in text and str(tmp_path) not in text
