"""Nothing the page downloads names a place on the server (item 10): every file of *Export all* (its
``session.json`` included), every other download and every message that goes with them are searched for the data's
folder, the effects file's folder and the working directory. Real workbenches on loopback (no browser)."""

from __future__ import annotations

import io
import json
import os
import zipfile
from pathlib import Path

import pytest

pytest.importorskip("viser")

from magcal.core.errors import MagcalError
from magcal.output import bundle
from magcal_workbench.sessionfile import read_session_document

EXAMPLE = Path(__file__).resolve().parents[1] / "helpers" / "user_effects_example.py"
BENCH_SAMPLES = 200


def _unzip(content: bytes) -> dict:
    with zipfile.ZipFile(io.BytesIO(content)) as zf:
        return {n: zf.read(n) for n in zf.namelist()}


def _places(tmp_path) -> list[bytes]:
    """The server's folders a download must not name."""
    return [os.fsencode(p) for p in (tmp_path, EXAMPLE.resolve().parent, os.getcwd(), Path.home())]


def _downloads(wb) -> dict:
    """Every file the page downloads after a fit, by name (the zip's files as ``zip:NAME``), and the messages."""
    out, messages = {}, []
    actions = [getattr(wb.exporting, n) for n in dir(wb.exporting) if n.startswith("do_export")]
    actions += [wb.downloads.do_download_calibration, wb.downloads.do_download_corrected]
    actions += [wb.evidence.do_download_evidence_svg]
    for action in actions:
        wb.handle(action, None)
        messages.append(wb.ctrl.message)
        if wb.downloads.last is not None:
            name, content = wb.downloads.last
            out[name] = content
    for name, content in _unzip(out.pop("magcal_export.zip")).items():
        out[f"zip:{name}"] = content
    out["messages"] = "\n".join(messages).encode()
    return out


@pytest.mark.parametrize("store", [True, False])
def test_no_download_names_a_folder_of_the_server(bench, tmp_path, store):
    wb = bench(store=store, effects_files=[str(EXAMPLE)])  # the session names the user's effects file
    wb.actions.do_calibrate(None)
    assert wb.worker.wait(120) and wb.ctrl.calibration is not None
    assert wb.ctrl.state.effects_files == [str(EXAMPLE.resolve())]  # the session itself keeps the full path
    files = _downloads(wb)
    assert {"zip:session.json", "zip:README.txt", "calibration.json", "corrected.csv", "messages"} <= set(files)
    for name, content in files.items():
        for place in _places(tmp_path):
            assert place not in content, (name, place)
    # the zip's session is still a session document: the data by its name, the effects file named in the README
    state = read_session_document(json.loads(files["zip:session.json"]))
    assert state.data_path == "data.csv" and state.effects_files == []
    assert state.n_samples == BENCH_SAMPLES and state.calibration is not None
    assert "not included: user_effects_example.py" in files["zip:README.txt"].decode()


def test_a_reason_naming_the_data_file_is_shown_by_its_name(bench, tmp_path, monkeypatch):
    """The engine's reasons name the file they could not read (its full path, as the command line needs): in the
    zip's README and the page's message only the file's name remains."""
    wb = bench()
    wb.actions.do_calibrate(None)
    assert wb.worker.wait(120)

    def unreadable(calibration, data_path, kind, *args, **kw):
        raise MagcalError(f"{data_path}: cannot read the file (permission denied)")

    monkeypatch.setattr(bundle, "corrected_bytes", unreadable)
    wb.handle(wb.exporting.do_export_all, None)
    name, content = wb.downloads.last
    readme = _unzip(content)["README.txt"].decode()
    assert "corrected.csv: not written: …/data.csv: cannot read the file" in readme
    message = wb.ctrl.message
    assert "not written" in message and "data.csv" in message
    for place in _places(tmp_path):
        assert os.fsdecode(place) not in readme and os.fsdecode(place) not in message
