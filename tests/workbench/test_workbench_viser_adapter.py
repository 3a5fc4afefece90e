"""viser's internals the workbench relies on (magcal_workbench/viser_adapter.py): this file fails when viser
changes them, the page's one update thread, and the registry of what each widget may send."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

pytest.importorskip("viser")

from magcal.core.errors import MagcalError
from magcal_workbench import viser_adapter
from magcal_workbench.checks import PageValues, Widgets
from magcal_workbench.uiqueue import UiQueue


def test_the_installed_viser_has_every_internal_the_adapter_uses():
    assert viser_adapter.missing_internals() == []


def test_the_internals_check_fails_when_one_is_gone(monkeypatch):
    from viser import _messages

    monkeypatch.delattr(_messages, "FileTransferStartUpload")
    assert any("FileTransferStartUpload" in p for p in viser_adapter.missing_internals())


@pytest.fixture
def server():
    refused = []

    def check(request):
        return "refused: test" if request.headers.get("X-Refuse") else None

    srv = viser_adapter.start_server("127.0.0.1", 0, check)
    yield srv, refused
    srv.stop()


def test_the_handshake_check_runs_before_viser_serves(server):
    import http.client

    srv, _ = server
    conn = http.client.HTTPConnection("127.0.0.1", srv.get_port(), timeout=10)
    conn.request("GET", "/", headers={"X-Refuse": "1"})
    refused = conn.getresponse()
    assert refused.status == 403 and b"refused: test" in refused.read()
    conn = http.client.HTTPConnection("127.0.0.1", srv.get_port(), timeout=10)
    conn.request("GET", "/")
    assert conn.getresponse().status == 200


def test_an_upload_start_over_the_bound_is_dropped_before_its_parts(server):
    from viser import _messages

    srv, _ = server
    upload = srv.gui.add_upload_button("file")
    seen = []
    handler = viser_adapter.watch_upload_starts(
        srv, upload, lambda name, size, client: seen.append((name, size)) or size > 1000
    )
    assert handler is not None
    gui, uuid = srv.gui, viser_adapter.widget_id(upload)
    for tid, size in (("small", 500), ("big", 5_000_000)):
        message = _messages.FileTransferStartUpload(uuid, tid, "x.csv", "text/csv", 3, size)
        gui._handle_file_transfer_start(0, message)
        handler(0, message)
    assert seen == [("x.csv", 500), ("x.csv", 5_000_000)]
    assert "small" in gui._current_file_upload_states and "big" not in gui._current_file_upload_states
    other = _messages.FileTransferStartUpload("another-widget", "t3", "y.csv", "text/csv", 3, 9_000_000)
    handler(0, other)  # another widget's upload is not this watcher's
    assert len(seen) == 2


def test_widgets_are_registered_where_they_are_made(server):
    srv, _ = server
    values = PageValues()
    w = Widgets(srv.gui, values)
    offered = ["a", "b"]
    choice = w.dropdown("Choice", ("a", "b"), allowed=lambda: tuple(offered), initial_value="a")
    gain = w.slider("Gain", min=1.0, max=5.0, step=1.0, initial_value=2.0)
    text = w.text("Path", "", max_chars=10)
    loose = srv.gui.add_number("Loose", 1.0)  # made without registering what it may send
    assert values.range(gain) == (1.0, 5.0) and values.allowed(choice) == ("a", "b")
    choice._impl.value = "b"  # as a browser sets it
    assert values.check(choice) == "b"
    offered.remove("b")  # the server no longer offers it
    with pytest.raises(MagcalError, match="not one of the choices"):
        values.check(choice)
    assert choice.value == "a"  # put back
    for bad in (0.5, 6.0, float("nan"), True):
        gain._impl.value = bad
        with pytest.raises(MagcalError, match=r"(outside|a number in) 1 \.\.\. 5"):
            values.check(gain)
        assert 1.0 <= gain.value <= 5.0
    text._impl.value = "x" * 11
    with pytest.raises(MagcalError, match="at most 10 characters"):
        values.check(text)
    with pytest.raises(MagcalError, match="did not register"):
        values.check(loose)


def test_the_ui_queue_runs_posts_in_order_on_one_thread():
    ui = UiQueue()
    try:
        seen, threads = [], set()

        def post_many(k):
            for i in range(50):
                ui.post(lambda k=k, i=i: (seen.append((k, i)), threads.add(threading.current_thread().name)))

        workers = [threading.Thread(target=post_many, args=(k,)) for k in range(4)]
        for t in workers:
            t.start()
        for t in workers:
            t.join()
        assert ui.wait(10)
        assert len(seen) == 200 and threads == {"workbench-ui"}
        for k in range(4):  # each thread's updates in the order it posted them
            assert [i for kk, i in seen if kk == k] == list(range(50))
        # run() returns after the update ran; a post from the UI thread itself runs at once (no self-wait)
        order = []
        ui.run(lambda: (ui.post(lambda: order.append("inner")), order.append("outer")))
        assert order == ["inner", "outer"]
        # a failing update does not stop the ones after it
        ui.post(lambda: 1 / 0)
        done = []
        ui.run(lambda: done.append(time.monotonic()))
        assert done and np.isfinite(done[0])
    finally:
        ui.stop()
