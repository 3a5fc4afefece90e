"""Only the workbench's own page may connect (item 2): the websocket handshake checks Origin and Host.

A raw websocket client (the ``websockets`` package, as a hostile page's browser would send it) speaks to a real
server: from another origin, without an origin, or through a rebound host name it is refused with HTTP 403 before
any message is sent; from the page's own origin it receives the scene.
"""

from __future__ import annotations

import asyncio
import socket

import numpy as np
import pytest

pytest.importorskip("viser")
websockets_client = pytest.importorskip("websockets.asyncio.client")
from websockets.exceptions import InvalidStatus

from magcal_workbench import guard, viser_adapter

TIMEOUT_S = 10.0


@pytest.fixture(scope="module")
def server():
    srv = guard.guarded_viser_server("127.0.0.1", 0)
    srv.scene.add_point_cloud("/secret", np.zeros((3, 3), np.float32), (255, 0, 0), point_size=0.1)
    yield srv
    srv.stop()


def _handshake(port, origin, host="127.0.0.1"):
    """What a websocket client gets: ``("accepted", first message bytes)`` or ``("refused", HTTP status)``."""
    import viser

    async def go():
        sock = socket.create_connection(("127.0.0.1", port), timeout=TIMEOUT_S)
        try:
            async with websockets_client.connect(
                f"ws://{host}:{port}",
                sock=sock,
                origin=origin,
                open_timeout=TIMEOUT_S,
                subprotocols=[f"viser-v{viser.__version__}"],
                max_size=None,  # the first message carries plotly.js (the page draws plots from the start)
            ) as ws:
                return "accepted", await asyncio.wait_for(ws.recv(), TIMEOUT_S)
        except InvalidStatus as exc:
            return "refused", exc.response.status_code

    return asyncio.run(asyncio.wait_for(go(), 3 * TIMEOUT_S))


@pytest.mark.parametrize(
    "origin, host",
    [
        ("http://evil.example", "127.0.0.1"),  # another site's page
        ("http://evil.example:{port}", "127.0.0.1"),
        ("http://127.0.0.1:1", "127.0.0.1"),  # another port of this machine (another local app)
        ("https://127.0.0.1:{port}", "127.0.0.1"),
        ("null", "127.0.0.1"),  # a sandboxed iframe or a file:// page
        (None, "127.0.0.1"),  # no Origin: not a browser page
        ("http://evil.example:{port}", "evil.example"),  # DNS rebinding: Origin and Host agree, Host is foreign
    ],
)
def test_a_foreign_page_cannot_open_the_websocket(server, origin, host):
    port = server.get_port()
    outcome, detail = _handshake(port, origin.format(port=port) if origin else None, host)
    assert (outcome, detail) == ("refused", 403)


@pytest.mark.parametrize("host", ["127.0.0.1", "localhost", "[::1]"])
def test_the_page_origin_is_accepted(server, host):
    port = server.get_port()
    outcome, first = _handshake(port, f"http://{host}:{port}", host)
    assert outcome == "accepted" and len(first) > 0  # the scene's messages follow


@pytest.mark.parametrize(
    "headers, local, refused",
    [
        ({"Host": "127.0.0.1:8080", "Upgrade": "websocket", "Origin": "http://127.0.0.1:8080"}, True, False),
        ({"Host": "localhost:8080", "Upgrade": "websocket", "Origin": "http://LOCALHOST:8080"}, True, False),
        ({"Host": "127.0.0.1:8080"}, True, False),  # the page itself (no data in it)
        ({"Host": "evil.example:8080"}, True, True),  # rebinding, even for the page
        ({"Host": "localhost:9000", "Upgrade": "websocket", "Origin": "http://localhost:9000"}, True, False),  # tunnel
        ({"Host": "localhost:9000", "Upgrade": "websocket", "Origin": "http://localhost:8080"}, True, True),
        ({"Host": "127.0.0.1", "Upgrade": "websocket", "Origin": "http://127.0.0.1"}, True, False),  # port 80
        ({"Host": "192.168.1.5:8080", "Upgrade": "websocket", "Origin": "http://192.168.1.5:8080"}, False, False),
        ({"Host": "192.168.1.5:8080", "Upgrade": "websocket", "Origin": "http://evil.example"}, False, True),
        ({"Host": "127.0.0.1:x", "Upgrade": "websocket", "Origin": "http://127.0.0.1:8080"}, True, True),
        ({}, True, True),
    ],
)
def test_refusal_rules(headers, local, refused):
    assert (guard.refusal(headers, local) is not None) == refused


def test_viser_still_starts_through_the_hooked_serve(monkeypatch):
    """If viser stops passing its own ``process_request`` to websockets' ``serve``, the check would silently be
    skipped: the workbench then refuses to start (this test fails first, naming the change)."""
    import websockets.asyncio.server as ws_server

    seen = []
    original = ws_server.serve

    def spy(*args, **kwargs):
        seen.append(getattr(kwargs.get("process_request"), "__name__", None))
        return original(*args, **kwargs)

    monkeypatch.setattr(ws_server, "serve", spy)
    srv = guard.guarded_viser_server("127.0.0.1", 0)
    srv.stop()
    assert seen and seen[0] == "process_request"  # ours, chained before viser's static-file server
    assert ws_server.serve is spy  # restored after the start


def test_a_viser_without_the_hook_does_not_start(monkeypatch):
    monkeypatch.setattr(viser_adapter, "VISER_HOOK", "a_function_viser_does_not_have")
    with pytest.raises(viser_adapter.HandshakeHookMissing, match="cannot check who connects"):
        guard.guarded_viser_server("127.0.0.1", 0)


@pytest.mark.parametrize(
    "host, url",
    [
        ("127.0.0.1", "http://127.0.0.1:8080"),
        ("::1", "http://[::1]:8080"),
        ("0.0.0.0", "http://127.0.0.1:8080"),
        ("::", "http://[::1]:8080"),
        ("localhost", "http://localhost:8080"),
        ("fe80::1", "http://[fe80::1]:8080"),
    ],
)
def test_the_printed_address_is_a_valid_url(host, url):
    assert guard.page_url(host, 8080) == url
