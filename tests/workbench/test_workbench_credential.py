"""The page's credential in a real browser (items 1 and 10): nothing the browser sends to another server of
this machine lets that server open the workbench's websocket or fetch its page; the address bar loses the token
after the first load, and a reload still connects.

Headless Chromium (Debian's, through playwright) loads the workbench from its printed address; a second HTTP server
on another loopback port (another user's, say) records every request the browser makes to it: the same tab
navigated there, another tab, the page's own ``fetch`` of the workbench with credentials, its attempt to frame the
workbench, an address with viser's ``?websocket=`` pointing at it. Then, as a local process, that server tries
every header and value it received against the workbench's websocket and page: all are refused. Scenes are small
and every wait bounded; without chromium or playwright the tests skip (``MAGCAL_REQUIRE_BROWSER=1`` fails them).
"""

from __future__ import annotations

import http.client
import http.server
import re
import threading

import pytest

import magcal
from magcal.data import io as mio

pytest.importorskip("viser")
pytest.importorskip("websockets")

from tests.conftest import ws_handshake

pytestmark = [pytest.mark.e2e, pytest.mark.slow]


@pytest.fixture
def workbench(tmp_path):
    from magcal_workbench.app import Workbench

    ds = magcal.simulate("chi2017", n_samples=40, seed=1)
    path = tmp_path / "small.csv"
    mio.write_csv(path, ds)
    wb = Workbench(mio.read_csv(path), host="127.0.0.1", port=0, store=None)
    try:
        yield wb
    finally:
        wb.stop()


class Recorder:
    """Another local user's HTTP server: records what the browser sends it (request line, headers) and answers
    ``page`` (HTML, ``{port}`` and ``{me}`` filled in) to every GET."""

    def __init__(self, page: str, port: int):
        self.requests: list[str] = []
        recorder = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_GET(self):
                recorder.requests.append(f"{self.requestline}\n{self.headers}")
                body = page.format(port=port, me=self.server.server_address[1]).encode()
                self.send_response(200)
                self.send_header("Content-Type", "text/html")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, *args):
                pass

        self.httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.port = self.httpd.server_address[1]
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()

    def close(self):
        self.httpd.shutdown()
        self.httpd.server_close()

    def received(self) -> str:
        return "\n".join(self.requests)


#: What the other server's page does in the browser: fetch the workbench's page with credentials (an opaque
#: answer, but the browser sends what it holds), frame it, and say when done.
HOSTILE = """<!doctype html><title>other</title><body><script>
  window.done = false;
  fetch("http://127.0.0.1:{port}/", {{credentials: "include", mode: "no-cors"}}).catch(() => 0)
    .finally(() => {{ window.done = true; }});
  const f = document.createElement("iframe");
  f.src = "http://127.0.0.1:{port}/";
  document.body.appendChild(f);
</script></body>"""


def _connected(page, timeout_ms=90_000):
    page.wait_for_function(
        "() => document.body && document.body.innerText.includes('Total-field RMS')", timeout=timeout_ms
    )
    page.wait_for_function("() => !document.body.innerText.includes('Connecting')", timeout=timeout_ms)


def _get(port, path, headers):
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    conn.request("GET", path, headers=headers)
    response = conn.getresponse()
    response.read()
    return response.status


def test_another_local_server_the_browser_visits_gets_nothing_that_opens_the_workbench(browser, workbench):
    wb = workbench
    other = Recorder(HOSTILE, wb.port)
    try:
        context = browser.new_context()
        page = context.new_page()
        page.goto(wb.url, wait_until="domcontentloaded")
        _connected(page)
        assert len(wb.server.get_clients()) == 1
        # another tab of the same browser visits the other server, whose page fetches and frames the workbench
        tab = context.new_page()
        tab.goto(f"http://127.0.0.1:{other.port}/", wait_until="load", timeout=30_000)
        tab.wait_for_function("() => window.done", timeout=30_000)
        tab.wait_for_timeout(1000)  # let the frame load (or be refused)
        # the workbench's own tab goes there too (a link followed in the same tab)
        page.goto(f"http://127.0.0.1:{other.port}/same-tab", wait_until="load", timeout=30_000)
        page.wait_for_function("() => window.done", timeout=30_000)
        page.wait_for_timeout(1000)
        # the framed workbench never connected: only the first page ever did, and it is gone
        page.wait_for_timeout(500)
        assert len(wb.server.get_clients()) == 0
        context.close()
    finally:
        other.close()

    received = other.received()
    assert "GET /same-tab" in received and "GET / " in received  # the browser did visit it
    assert wb.token not in received
    # what an attacker would try with what it got: every Cookie header, and every long token-like value, as the
    # websocket's cookie or query and as the page's
    cookies = re.findall(r"^Cookie: (.*)$", received, flags=re.MULTILINE)
    values = set(re.findall(r"[A-Za-z0-9_\-]{30,}", received))
    for cookie in cookies:
        assert ws_handshake(wb.port, cookie=cookie)[0] == "refused", cookie
        assert _get(wb.port, "/", {"Cookie": cookie}) == 403
    for value in values:
        assert ws_handshake(wb.port, token=value)[0] == "refused"
        assert _get(wb.port, f"/?token={value}", {}) == 403


def _clients(wb, n, timeout_s=20.0):
    """Wait until ``wb`` has ``n`` connected browsers; return how many it has."""
    import time

    end = time.monotonic() + timeout_s
    while len(wb.server.get_clients()) != n and time.monotonic() < end:
        time.sleep(0.1)
    return len(wb.server.get_clients())


def test_an_address_naming_another_websocket_server_does_not_send_it_the_token(browser, workbench):
    """viser's page takes its websocket's address from ``?websocket=``: a link to the workbench naming another
    server's address must not hand that server the token; the page ignores it and connects to its own."""
    wb = workbench
    other = Recorder("<!doctype html><title>other</title>", wb.port)
    try:
        page = browser.new_page()
        page.goto(f"{wb.url}&websocket=ws://127.0.0.1:{other.port}", wait_until="domcontentloaded")
        _connected(page)
        page.wait_for_timeout(1500)  # a websocket to the other server would have been tried by now
        assert _clients(wb, 1) == 1
        assert "websocket" not in page.url and "token" not in page.url
        page.close()
    finally:
        other.close()
    assert wb.token not in other.received()


def test_the_address_bar_loses_the_token_and_a_reload_connects_again(browser, workbench):
    """Item 10: after the first load the address shows no token. A reload (and back after leaving) connects again
    from the token the tab kept; a new tab at the bare address is refused and connects nothing."""
    wb = workbench
    bare = f"http://127.0.0.1:{wb.port}/"
    context = browser.new_context()
    page = context.new_page()
    page.goto(wb.url, wait_until="domcontentloaded")
    _connected(page)
    assert page.url == bare
    assert page.evaluate("() => location.href") == bare
    assert _clients(wb, 1) == 1

    page.reload(wait_until="domcontentloaded")
    _connected(page)
    assert page.url == bare and _clients(wb, 1) == 1

    # a new tab at the address without the token: the refusal, no connection
    tab = context.new_page()
    response = tab.goto(bare, wait_until="load", timeout=30_000)
    assert response.status == 403 and "token" in tab.inner_text("body")
    tab.wait_for_timeout(1000)
    assert tab.url == bare and _clients(wb, 1) == 1
    tab.close()

    # leave for another page in the same tab, come back: connected again
    page.goto("data:text/html,<title>elsewhere</title>", wait_until="load")
    assert _clients(wb, 0) == 0
    page.go_back(wait_until="domcontentloaded")
    _connected(page)
    assert page.url == bare and _clients(wb, 1) == 1
    context.close()
