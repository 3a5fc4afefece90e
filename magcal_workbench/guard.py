"""Only the workbench's own page may talk to the workbench: the websocket handshake checks Origin and Host.

A browser lets any web page open a websocket to ``ws://127.0.0.1:8080``; the page then receives the whole scene
(the user's data) and may press every button. Browsers always send the page's ``Origin`` with a websocket
handshake and a page cannot forge it, so the server refuses (HTTP 403, before any message is sent) a websocket
whose ``Origin`` is not the address the page was served from. DNS rebinding (``evil.example`` resolving to
127.0.0.1, so that Origin and Host agree) is refused by checking ``Host`` too: when the workbench serves this
machine only, Host must be a loopback name (``127.0.0.1``, ``localhost``, ``[::1]``); its port is not checked, so
an SSH tunnel (``localhost:9000`` forwarded to the served port) works.

viser 1.1.1 has no public hook for the handshake: it passes its own ``process_request`` (the static-file server)
to :func:`websockets.asyncio.server.serve` inside its server thread. :func:`guarded_viser_server` chains the
check in front of it (:mod:`magcal_workbench.viser_adapter`) by wrapping ``serve`` *only while the viser server starts* (:class:`viser.ViserServer`
returns once the port is bound), and refuses to start when the wrapper was not used -- so a viser that changes
how it serves fails loudly instead of running unprotected (``tests/test_workbench_guard.py`` checks both).
"""

from __future__ import annotations

import ipaddress
from urllib.parse import urlsplit

from . import viser_adapter

#: Host names that mean this machine.
LOOPBACK_NAMES = ("127.0.0.1", "localhost", "::1")


def is_loopback(host: str) -> bool:
    """Whether ``host`` (a name or an address, IPv6 with or without brackets) means this machine only."""
    host = host.strip("[]")
    if host in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def url_host(host: str) -> str:
    """``host`` as it is written in a URL: an IPv6 address in brackets (``[::1]``), others as they are."""
    host = host.strip("[]")
    try:
        return f"[{host}]" if ipaddress.ip_address(host).version == 6 else host
    except ValueError:
        return host


def page_url(host: str, port: int) -> str:
    """The address to open: ``http://127.0.0.1:8080``, ``http://[::1]:8080``; a wildcard bind shows 127.0.0.1."""
    shown = "127.0.0.1" if host in ("0.0.0.0", "") else "::1" if host == "::" else host
    return f"http://{url_host(shown)}:{int(port)}"


def _split_host(value: str) -> tuple[str, int | None]:
    """``(host, port)`` of a Host header or URL netloc (``[::1]:80`` -> ``('::1', 80)``); port None if absent."""
    parts = urlsplit(f"//{value}")
    try:
        return (parts.hostname or ""), parts.port
    except ValueError:  # a port that is not a number
        return "", -1


def refusal(headers, local: bool) -> str | None:
    """Why a request is refused, or None when it may proceed.

    Parameters
    ----------
    headers : mapping
        The request's HTTP headers (``Host``, ``Origin``, ``Upgrade``). The Host's port is not checked (an SSH
        tunnel forwards another port); a websocket's Origin must name the Host's host and port.
    local : bool
        The server serves this machine only: ``Host`` must then name the loopback interface.

    Returns
    -------
    str or None
        A one-line reason (sent to the refused client as the 403 body), or None.
    """
    try:
        host_header = headers.get("Host") or ""
        upgrade = headers.get("Upgrade") or ""
        origin = headers.get("Origin")
    except Exception:  # a header given twice (websockets' MultipleValuesError): not a browser's request
        return "refused: repeated Host, Upgrade or Origin header"
    host, host_port = _split_host(host_header)
    if host_port is None:
        host_port = 80
    # the Host's port may differ from ours (an SSH tunnel: localhost:9000 -> 127.0.0.1:8080); its name may not
    if not host or host_port == -1 or (local and not is_loopback(host)):
        return "refused: this page is served only to this machine (unexpected Host)"
    if upgrade.lower() != "websocket":
        return None  # the page's static files hold no data; only the websocket carries the session
    if not origin:
        return "refused: a websocket must come from the workbench's page (no Origin)"
    parts = urlsplit(origin)
    try:
        origin_port = parts.port or {"http": 80, "https": 443}.get(parts.scheme)
    except ValueError:
        origin_port = None
    if parts.scheme != "http" or (parts.hostname or "").lower() != host.lower() or origin_port != host_port:
        return "refused: a websocket must come from the workbench's page (cross-origin)"
    return None


def guarded_viser_server(host: str, port: int, verbose: bool = False):
    """A :class:`viser.ViserServer` whose websocket and HTTP handshakes pass :func:`refusal` first
    (:func:`magcal_workbench.viser_adapter.start_server`, which raises
    :class:`~magcal_workbench.viser_adapter.HandshakeHookMissing` when viser starts without the check)."""
    local = is_loopback(host)
    return viser_adapter.start_server(host, port, lambda headers: refusal(headers, local), verbose)
