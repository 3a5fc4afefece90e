"""Only the workbench's own page may talk to the workbench: every request shows the page's token, and the
websocket handshake checks Origin and Host.

**The token**: a browser page is not the only thing that can open the websocket -- any process or user
of this machine can, and send the right ``Origin``. So the workbench makes a secret at start
(:func:`secrets.token_urlsafe`) and prints the page's address with it (``http://127.0.0.1:8080/?token=...``, as
notebook servers do). Every HTTP request and every websocket handshake must show it in the URL's query
(``?token=``), whatever the host served. ``--no-token`` turns it off (with a warning). :class:`Gate` holds the
token and the names the server answers to.

**Only this page holds it**: no cookie -- cookies belong to a host, not a port, so every other server of
127.0.0.1 the browser visits would receive it. The page's first script (:data:`PAGE_SCRIPT`, put first in viser's
page by :meth:`Gate.after`) takes the token from the address, keeps it in the tab's ``sessionStorage`` (which
belongs to this origin: scheme, host *and port*), clears the address bar (``history.replaceState``: no token, and
no viser parameter such as ``?websocket=`` from a link), and adds ``?token=`` to the address of the page's own
websocket (:data:`magcal_workbench.viser_adapter.WEBSOCKET_TOKEN_JS`; never to another server's). A **reload**
asks for the bare address: the refusal the server answers is a small page (:data:`RELOAD_SCRIPT`) that, for a
reload or a back/forward visit of a top-level tab, opens the address again with the token the tab kept; a new tab
at the bare address gets the refusal. Every answer forbids framing (``frame-ancestors 'none'``, so another page
cannot show the workbench under its own clicks), sends no referrer and is not cached.

**Beyond loopback** (``--host 0.0.0.0``) the Host header must be one of this machine's names or addresses
(:func:`served_names`; ``--allow-host`` adds one, e.g. a proxy's name): a Host/Origin pair of any other name (DNS
rebinding) is refused.

A browser lets any web page open a websocket to ``ws://127.0.0.1:8080``; the page then receives the whole scene
(the user's data) and may press every button. Browsers always send the page's ``Origin`` with a websocket
handshake and a page cannot forge it, so the server refuses (HTTP 403, before any message is sent) a websocket
whose ``Origin`` is not the address the page was served from. DNS rebinding (``evil.example`` resolving to
127.0.0.1, so that Origin and Host agree) is refused by checking ``Host`` too: when the workbench serves this
machine only, Host must be a loopback name (``127.0.0.1``, ``localhost``, ``[::1]``); its port is not checked, so
an SSH tunnel (``localhost:9000`` forwarded to the served port) works.

viser 1.1.1 has no public hook for the handshake: it passes its own ``process_request`` (the static-file server)
to :func:`websockets.asyncio.server.serve` inside its server thread. :func:`guarded_viser_server` chains the
check in front of it (:mod:`magcal_workbench.viser_adapter`) by wrapping ``serve`` *only while the viser server
starts* (:class:`viser.ViserServer` returns once the port is bound), and refuses to start when the wrapper was not
used -- so a viser that changes how it serves fails loudly instead of running unprotected
(``tests/workbench/test_workbench_guard.py`` checks both).
"""

from __future__ import annotations

import hmac
import html
import ipaddress
import socket
from urllib.parse import parse_qs, urlsplit

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


def page_url(host: str, port: int, token: str | None = None) -> str:
    """The address to open: ``http://127.0.0.1:8080``, ``http://[::1]:8080``; a wildcard bind shows 127.0.0.1;
    with ``token``, ``http://127.0.0.1:8080/?token=...``."""
    shown = "127.0.0.1" if host in ("0.0.0.0", "") else "::1" if host == "::" else host
    url = f"http://{url_host(shown)}:{int(port)}"
    return url if token is None else f"{url}/?token={token}"


def served_names(host: str, extra=()) -> frozenset:
    """The Host names a server bound to ``host`` answers to beyond loopback (lower case, IPv6 without brackets):
    the bound address (unless a wildcard), this machine's names (:func:`socket.gethostname`, its FQDN), the
    addresses they resolve to, the address of the default route, the loopback names, and ``extra``
    (``--allow-host``, e.g. a second interface's address or a proxy's name)."""
    names = {n.lower() for n in LOOPBACK_NAMES}
    names.update(str(e).strip("[]").lower() for e in extra if str(e).strip())
    if host not in ("", "0.0.0.0", "::"):
        names.add(host.strip("[]").lower())
    for name in {socket.gethostname(), socket.getfqdn()}:
        if not name:
            continue
        names.add(name.lower())
        try:
            names.update(str(info[4][0]).split("%")[0].lower() for info in socket.getaddrinfo(name, None))
        except OSError:
            pass
    try:  # the default route's address (connect() on a UDP socket sends nothing)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.connect(("192.0.2.1", 9))
            names.add(s.getsockname()[0])
    except OSError:
        pass
    return frozenset(names)


def _split_host(value: str) -> tuple[str, int | None]:
    """``(host, port)`` of a Host header or URL netloc (``[::1]:80`` -> ``('::1', 80)``); port None if absent."""
    parts = urlsplit(f"//{value}")
    try:
        return (parts.hostname or ""), parts.port
    except ValueError:  # a port that is not a number
        return "", -1


def refusal(headers, local: bool, allowed=None) -> str | None:
    """Why a request is refused, or None when it may proceed.

    Parameters
    ----------
    headers : mapping
        The request's HTTP headers (``Host``, ``Origin``, ``Upgrade``). The Host's port is not checked (an SSH
        tunnel forwards another port); a websocket's Origin must name the Host's host and port.
    local : bool
        The server serves this machine only: ``Host`` must then name the loopback interface.
    allowed : collection of str, optional
        Beyond loopback, the names ``Host`` may give (:func:`served_names`); None accepts any.

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
    if not local and allowed is not None and host.lower().strip("[]") not in allowed:
        return "refused: this server does not answer to that name (unexpected Host; see --allow-host)"
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


NO_TOKEN = (
    "refused: open the address printed when the workbench started (it ends in ?token=...); "
    "this request did not show the workbench's token"
)


#: The key under which the page keeps its token in the tab's ``sessionStorage`` (per origin: per port).
STORAGE_KEY = "magcal-workbench-token"

#: The page's first script: the token from the address into the tab's storage, the address bar cleared, the token
#: on the page's own websocket (:data:`magcal_workbench.viser_adapter.WEBSOCKET_TOKEN_JS`).
PAGE_SCRIPT = (
    """<script>
(function () {
  "use strict";
  var token = new URLSearchParams(location.search).get("token");
  try { if (token) sessionStorage.setItem("STORAGE_KEY", token); } catch (e) {}
  history.replaceState(null, "", location.pathname);
  if (!token) return;
WEBSOCKET_TOKEN_JS
})();
</script>""".replace("STORAGE_KEY", STORAGE_KEY)
    .replace("WEBSOCKET_TOKEN_JS", viser_adapter.WEBSOCKET_TOKEN_JS)
    .encode()
)

#: The refusal page's script: a reload (or back/forward) of a top-level tab that kept the token opens the address
#: again with it; an address with a token (a stale one) forgets it.
RELOAD_SCRIPT = """<script>
(function () {
  "use strict";
  try {
    if (new URLSearchParams(location.search).has("token")) { sessionStorage.removeItem("STORAGE_KEY"); return; }
    var nav = performance.getEntriesByType("navigation")[0];
    var again = nav && (nav.type === "reload" || nav.type === "back_forward");
    var token = sessionStorage.getItem("STORAGE_KEY");
    if (token && again && window.top === window.self) {
      location.replace(location.pathname + "?token=" + encodeURIComponent(token));
    }
  } catch (e) {}
})();
</script>""".replace("STORAGE_KEY", STORAGE_KEY)

#: Headers of every HTTP answer: no framing by another page, no referrer, no cache.
SECURITY_HEADERS = {
    "Content-Security-Policy": "frame-ancestors 'none'",
    "X-Frame-Options": "DENY",
    "Referrer-Policy": "no-referrer",
    "Cache-Control": "no-store",
}


def refusal_page(why: str) -> bytes:
    """The HTML a browser is shown for a request refused for want of the token: ``why`` and
    :data:`RELOAD_SCRIPT`."""
    return (
        '<!doctype html><html><head><meta charset="utf-8"><title>magcal workbench</title></head><body>'
        f"<p>{html.escape(why)}</p>{RELOAD_SCRIPT}</body></html>\n"
    ).encode()


class Gate:
    """Who may talk to the server: the token (None: no token asked, ``--no-token``) and, beyond loopback, the Host
    names it answers to.

    Parameters
    ----------
    host : str
        The address served.
    token : str or None
        The secret every request must show in its query (``?token=``).
    allow_hosts : sequence of str
        Extra Host names accepted beyond loopback (``--allow-host``).
    """

    def __init__(self, host: str, token: str | None, allow_hosts=()):
        self.local = is_loopback(host)
        self.token = token
        self.allowed = None if self.local else served_names(host, allow_hosts)

    def _query_token(self, path: str) -> str | None:
        values = parse_qs(urlsplit(path or "").query).get("token")
        return values[0] if values else None

    def _shows(self, value) -> bool:
        return (
            isinstance(value, str)
            and self.token is not None
            and hmac.compare_digest(value.encode(), self.token.encode())
        )

    def has_token(self, request) -> bool:
        """Whether ``request`` shows the token in its query (always True without one). A cookie is no credential:
        the browser would send it to every port of the host."""
        return self.token is None or self._shows(self._query_token(request.path))

    def refusal(self, request) -> str | None:
        """Why ``request`` (websockets' request: ``.path``, ``.headers``) is refused, or None."""
        why = refusal(request.headers, self.local, self.allowed)
        if why is None and not self.has_token(request):
            why = NO_TOKEN
        return why

    def after(self, request, response) -> None:
        """What every HTTP answer gets before it is sent: :data:`SECURITY_HEADERS`; viser's page, :data:`PAGE_SCRIPT`
        first in its head; a request refused only for want of the token, :func:`refusal_page` (a reload opens the
        page again with the token its tab kept)."""
        for name, value in SECURITY_HEADERS.items():
            response.headers[name] = value
        if response.status_code == 200:
            viser_adapter.add_to_page(response, PAGE_SCRIPT)
        elif (
            response.status_code == 403
            and refusal(request.headers, self.local, self.allowed) is None  # the headers are sound: the token lacks
            and (request.headers.get("Upgrade") or "").lower() != "websocket"
        ):
            viser_adapter.set_body(response, refusal_page(NO_TOKEN), "text/html; charset=utf-8")


def guarded_viser_server(host: str, port: int, verbose: bool = False, gate: Gate | None = None):
    """A :class:`viser.ViserServer` whose websocket and HTTP handshakes pass ``gate``'s :meth:`Gate.refusal` first
    (:func:`magcal_workbench.viser_adapter.start_server`, which raises
    :class:`~magcal_workbench.viser_adapter.HandshakeHookMissing` when viser starts without the check).
    Without ``gate``, Host and Origin are checked and no token is asked."""
    gate = Gate(host, None) if gate is None else gate
    return viser_adapter.start_server(host, port, gate.refusal, verbose, after=gate.after)
