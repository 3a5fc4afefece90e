"""The page's token (item 1): a process of this machine that sends the page's Origin is still refused
without the secret printed at start; with it (in the URL's query: the page's address, and the address the page's
script gives its websocket) it is the page. No cookie carries it (item 1). Beyond loopback, Host must be
one of this machine's names. Real servers on 127.0.0.1, port 0."""

from __future__ import annotations

import gzip
import hashlib
import http.client
import socket
from types import SimpleNamespace

import pytest

pytest.importorskip("viser")
pytest.importorskip("websockets")

from websockets.datastructures import Headers

from magcal_workbench import guard
from magcal_workbench.app import NO_TOKEN_WARNING, build_parser
from tests.conftest import ws_handshake


def _get(port, path, headers=None):
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    conn.request("GET", path, headers=headers or {})
    response = conn.getresponse()
    return response.status, response.getheader("Set-Cookie"), response.read()


def test_a_local_process_with_the_right_origin_needs_the_token(bench):
    wb = bench(store=False)
    assert wb.token and len(wb.token) >= 40 and wb.url == f"http://127.0.0.1:{wb.port}/?token={wb.token}"
    assert ws_handshake(wb.port) == ("refused", 403)  # the page's own Origin, no token
    assert ws_handshake(wb.port, token="not-the-token") == ("refused", 403)
    assert ws_handshake(wb.port, token=wb.token[:-1]) == ("refused", 403)
    outcome, first = ws_handshake(wb.port, token=wb.token)
    assert outcome == "accepted" and len(first) > 0  # the scene follows
    # the token does not excuse a foreign Origin
    assert ws_handshake(wb.port, origin="http://evil.example", token=wb.token) == ("refused", 403)


def test_the_page_needs_the_token_and_its_load_sets_no_cookie(bench):
    """A cookie belongs to the host, not the port -- every other server of 127.0.0.1 the browser
    visits would receive it. The page's answer sets none, and no cookie opens the page or the websocket."""
    wb = bench(store=False)
    status, cookie, body = _get(wb.port, "/")
    assert status == 403 and b"token" in body and cookie is None
    assert guard.RELOAD_SCRIPT.encode() in body  # a reload of the bare address opens it again with the tab's token
    status, _, _ = _get(wb.port, "/?token=wrong")
    assert status == 403
    for encoding in ("identity", "gzip"):
        conn = http.client.HTTPConnection("127.0.0.1", wb.port, timeout=10)
        conn.request("GET", f"/?token={wb.token}", headers={"Accept-Encoding": encoding})
        response = conn.getresponse()
        raw = response.read()
        page = gzip.decompress(raw) if encoding == "gzip" else raw
        assert response.status == 200 and response.getheader("Set-Cookie") is None
        assert int(response.getheader("Content-Length")) == len(raw)
        # the page's own script comes first in its head: it keeps the token in the tab and clears the address
        head = page.lower().index(b"<head>") + len(b"<head>")
        assert page[head : head + len(guard.PAGE_SCRIPT)] == guard.PAGE_SCRIPT
        assert wb.token.encode() not in page  # the page holds no secret; its address does
        # no other page may frame it (clicks under another page's control), nothing sent as a referrer
        assert response.getheader("Content-Security-Policy") == "frame-ancestors 'none'"
        assert response.getheader("X-Frame-Options") == "DENY"
        assert response.getheader("Referrer-Policy") == "no-referrer"
    # the old cookie, or any other, is no credential
    digest = hashlib.sha256(wb.token.encode()).hexdigest()[:12]
    for cookie in (f"magcal_workbench_{digest}={wb.token}", f"token={wb.token}"):
        assert _get(wb.port, "/index.html", {"Cookie": cookie})[0] == 403
        assert ws_handshake(wb.port, cookie=cookie) == ("refused", 403)
    assert ws_handshake(wb.port, token=wb.token)[0] == "accepted"


def test_two_workbenches_keep_their_tokens_apart(bench):
    a, b = bench(store=False), bench(store=False, name="b.csv")
    assert a.token != b.token and a.server is not b.server
    assert ws_handshake(a.port, token=a.token)[0] == "accepted" and ws_handshake(b.port, token=b.token)[0] == "accepted"
    assert ws_handshake(a.port, token=b.token) == ("refused", 403)
    assert _get(b.port, f"/?token={a.token}")[0] == 403


def test_no_token_asks_for_none_and_warns(bench):
    wb = bench(store=False, token=None)
    assert wb.url == f"http://127.0.0.1:{wb.port}"
    assert ws_handshake(wb.port)[0] == "accepted"
    assert build_parser().parse_args(["--no-token"]).no_token
    assert "WARNING" in NO_TOKEN_WARNING and "any program" in NO_TOKEN_WARNING


def _request(host_header, origin=None, path="/?token=T"):
    headers = Headers(Host=host_header)
    if origin is not None:
        headers["Upgrade"] = "websocket"
        headers["Origin"] = origin
    return SimpleNamespace(path=path, headers=headers)


def test_beyond_loopback_only_this_machines_names_are_answered():
    gate = guard.Gate("0.0.0.0", "T", allow_hosts=["proxy.example"])
    me = socket.gethostname()
    assert gate.refusal(_request(f"{me}:8080", f"http://{me}:8080")) is None
    assert gate.refusal(_request("127.0.0.1:8080", "http://127.0.0.1:8080")) is None
    assert gate.refusal(_request("proxy.example:8080", "http://proxy.example:8080")) is None
    # DNS rebinding: evil.example resolves to this machine; Host and Origin agree, the name is foreign
    why = gate.refusal(_request("evil.example:8080", "http://evil.example:8080"))
    assert why is not None and "Host" in why
    assert gate.refusal(_request("evil.example:8080")) is not None  # the page too
    # a known name still needs the token
    assert gate.refusal(_request(f"{me}:8080", f"http://{me}:8080", path="/")) == guard.NO_TOKEN
    assert guard.Gate("192.0.2.7", "T").refusal(_request("192.0.2.7:80", "http://192.0.2.7")) is None
