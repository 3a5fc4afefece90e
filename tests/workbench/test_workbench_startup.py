"""The launcher starts fast: the page is served and its address printed before the engine's heavy
parts are imported; a CSV's preview is drawn as the raw clouds before the whole file is read, and the
workbench then takes over the same server, token and scene.

No timed assertion here: the times are in ``benchmarks/page_latency.py``.
"""

from __future__ import annotations

import subprocess
import sys
import urllib.error
import urllib.request

import numpy as np
import pytest

import magcal
from magcal.data import io as mio
from magcal_workbench import app, startup


def _csv(tmp_path, n=600):
    path = tmp_path / "big.csv"
    mio.write_csv(path, magcal.simulate_timeseries("chi2017", n_samples=n, seed=5, rate_hz=2.0))
    return path


def _status(url: str) -> int:
    try:
        with urllib.request.urlopen(url, timeout=30) as r:
            return r.status
    except urllib.error.HTTPError as exc:
        return exc.code


def test_the_page_is_served_before_the_engine_and_the_page_s_parts_are_imported(tmp_path):
    path = _csv(tmp_path)
    code = (
        "import sys\n"
        "from magcal_workbench import startup\n"
        f"early = startup.begin([{str(path)!r}, '--port', '0', '--no-session'])\n"
        "heavy = [m for m in ('magcal_workbench.app', 'magcal_workbench.controller', 'magcal.fitting', 'plotly',"
        " 'matplotlib', 'trimesh') if m in sys.modules]\n"
        "import urllib.request\n"
        "with urllib.request.urlopen(early.url, timeout=60) as r: status = r.status\n"
        "print('HEAVY', heavy, 'STATUS', status)\n"
        "early.stop()\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert "open http://127.0.0.1:" in done.stdout and "?token=" in done.stdout  # the address, printed first
    assert "HEAVY [] STATUS 200" in done.stdout, done.stdout


def test_a_preview_is_drawn_then_the_workbench_takes_over_its_server_token_and_scene(tmp_path):
    path = _csv(tmp_path)
    early = startup.begin([str(path), "--port", "0", "--no-session", "--max-points", "200"])
    wb = None
    try:
        assert early.token and early.url.endswith(f"?token={early.token}")
        assert "loading `big.csv`..." in early._status.content
        early.show_preview()
        view = early.scene_view
        assert view is not None and "a preview of 200 samples" in early._status.content
        raw = {name: h for name, h in view._clouds.items() if name.endswith("/raw")}
        assert len(raw) == 4 and all(len(h.points) == 200 for h in raw.values())  # one raw cloud per sensor
        assert not any(name.endswith("/corrected") for name in view._clouds)  # nothing fitted yet
        assert view._static == {}  # the clouds alone: the labels and the cross come with the workbench
        before = {name: np.array(h.points) for name, h in raw.items()}

        ds = mio.read_csv(path)
        wb = app.Workbench(ds, store=None, token=early.token, server=early.server, scene_view=view, max_points=200)
        early.done()
        assert wb.server is early.server and wb.url == early.url and wb.scene_view is view
        assert _status(wb.url) == 200 and _status(wb.url.split("?")[0]) != 200  # the same token guards it
        # the workbench drew its own scene over the preview: every sample's raw cloud, at the fitted gains
        assert len(view.shown_samples) <= 200 and view.shown_samples[-1] == ds.n_samples - 1  # the whole record
        assert set(before) <= set(view._clouds)
        assert {"/data/s1/raw_label", "/cross/label", "/cross/arms"} <= set(view._static)
        after = {n: np.asarray(view._clouds[n].points) for n in before}
        assert any(before[n].shape != after[n].shape or not np.allclose(before[n], after[n]) for n in before)
    finally:
        if wb is not None:
            wb.stop()
        else:
            early.stop()


def test_a_small_file_is_previewed_whole_and_its_raw_clouds_are_not_sent_again(tmp_path):
    """A file within ``--max-points`` is previewed whole, before the engine's other parts are imported: the
    workbench's scene then holds the same raw clouds and sends none of their points again."""
    path = _csv(tmp_path, n=300)
    early = startup.begin([str(path), "--port", "0", "--no-session"])
    wb = None
    try:
        early.show_preview()
        view = early.scene_view
        assert view is not None and "a preview of 300 samples" in early._status.content
        raw = {name: np.array(h.points) for name, h in view._clouds.items() if name.endswith("/raw")}
        assert len(raw) == 4 and all(len(p) == 300 for p in raw.values())
        sent = view.n_points_sent
        wb = app.Workbench(mio.read_csv(path), store=None, token=early.token, server=early.server, scene_view=view)
        early.done()
        for name, points in raw.items():  # the same clouds, at the same gains
            np.testing.assert_allclose(np.asarray(view._clouds[name].points), points)
        assert view.n_points_sent == sent  # nothing sent again (a refit's corrected clouds are new, not these)
    finally:
        if wb is not None:
            wb.stop()
        else:
            early.stop()


def test_no_preview_for_a_lesson_and_a_failed_start_stops_the_early_server(tmp_path, capsys):
    path = _csv(tmp_path)
    early = startup.begin([str(path), "--port", "0", "--no-session", "--lesson", "no-such-lesson"])
    early.show_preview()
    assert early.scene_view is None  # a lesson's data are its own: no preview of the file
    url = early.url
    assert app.main(None, early=early) == 2
    assert "no lesson 'no-such-lesson'" in capsys.readouterr().err
    with pytest.raises(urllib.error.URLError):
        urllib.request.urlopen(url, timeout=10)


def test_a_file_that_cannot_be_read_gets_no_early_server(tmp_path):
    assert startup.begin([str(tmp_path / "missing.csv"), "--port", "0"]) is None  # app.main says why
    assert startup.begin([str(_csv(tmp_path)), "--port", "0", "--max-points", "0"]) is None


def test_the_loading_line_shows_a_file_name_as_text_not_markup(tmp_path):
    """A file name is untrusted text: the status line quotes it as code (no markup, no HTML, no backtick that
    would end the span)."""
    hostile = tmp_path / "<img src=x onerror=alert(1)>`*b*`[l](javascript:x).csv"
    hostile.write_bytes(_csv(tmp_path).read_bytes())
    early = startup.begin([str(hostile), "--port", "0", "--no-session"])
    try:
        assert early._status.content == "**loading `<img src=x onerror=alert(1)>'*b*'[l](javascript:x).csv`...**"
    finally:
        early.stop()
