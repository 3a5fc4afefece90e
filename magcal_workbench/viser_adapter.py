"""Every use of viser's internals, in one place.

viser (1.1.1) offers no public hook for the things the workbench needs below; each is reached here and nowhere
else, and ``tests/workbench/test_workbench_viser_adapter.py`` fails when viser changes what they rely on
(:func:`missing_internals`):

* **the handshake check** (:func:`start_server`): viser serves its page and its websocket through
  ``websockets.asyncio.server.serve(process_request=viser_http_server)``; while the server starts, ``serve`` is
  wrapped so that ``check(request)`` (:meth:`magcal_workbench.guard.Gate.refusal`: Host, Origin and the page's
  token) runs before viser's own hook on every HTTP request and websocket upgrade, and ``after(request, response)``
  may change every HTTP answer, viser's or the refusal (:meth:`magcal_workbench.guard.Gate.after`: headers, the
  page's script).
* **a script in viser's page** (:func:`add_to_page`): viser serves one HTML file (gzip-compressed when the browser
  accepts it); a ``<script>`` is put first in its ``<head>``, so it runs before viser's own code.
* **the page's websocket address** (:data:`WEBSOCKET_TOKEN_JS`): viser's page derives it from its own address
  without the query and hands it to a web worker (``worker.postMessage({type: "set_server", server})``), which
  opens the websocket; the script wraps the page's ``Worker`` so that this one message's address carries
  ``?token=`` -- only when it is the page's own server.
* **an upload's declared size** (:func:`watch_upload_starts`): viser buffers an upload's parts in
  ``gui._current_file_upload_states``; a handler of ``FileTransferStartUpload`` registered on the websocket
  server sees the size the browser declares and drops the entry, so viser ignores the parts that follow.
* **an upload's bytes as they arrive** (:func:`watch_upload_parts`): a handler of ``FileTransferPart`` put
  *before* viser's own sees each part's size before viser buffers it, and drops the upload (the same entry) once
  the bytes received pass the bound, whatever size was declared.
* **a widget's value before viser casts it** (:func:`watch_updates`): a handler of ``GuiUpdateMessage`` put
  *before* viser's own finds the widget (``gui._gui_input_handle_from_uuid``) and may refuse the update; a refused
  message's ``uuid`` is blanked, so viser's handler finds no widget and drops it (viser casts the value with the
  widget's type first: ``int(nan)`` would raise in its event loop, ``int(14551.5)`` truncate). :func:`show_value`
  sends a widget's value to the browsers again (viser's setter sends nothing when the value did not change).
* **a widget's kind and id** (:func:`widget_kind`, :func:`widget_id`).
"""

from __future__ import annotations

import gzip
import http
import inspect
import re
import threading
from collections.abc import Callable
from pathlib import Path

#: The name of viser's ``process_request`` function (its static-file server) the check is chained before.
VISER_HOOK = "viser_http_server"

_START_LOCK = threading.Lock()


class HandshakeHookMissing(RuntimeError):
    """viser started its server without the handshake check (its way of serving changed)."""


def start_server(
    host: str,
    port: int,
    check: Callable[[object], str | None],
    verbose: bool = False,
    after: Callable[[object, object], None] | None = None,
):
    """A :class:`viser.ViserServer` whose websocket and HTTP handshakes pass ``check(request)`` first.

    ``check`` gets websockets' request (``.path`` with its query, ``.headers``) and returns None to let it through
    or the reason (plain text) it is refused with 403. ``after(request, response)``, when given, sees every HTTP
    answer before it is sent -- viser's to a request let through, and the 403 of one refused -- and may change
    its headers and body (:func:`add_to_page`, :func:`set_body`); a websocket upgrade let through has none.

    Raises
    ------
    HandshakeHookMissing
        If viser did not start its server through ``websockets.asyncio.server.serve`` with its static-file hook
        (the server is stopped first): the workbench does not run without the check.
    """
    import viser
    import websockets.asyncio.server as ws_server

    chained = []

    def check_first(viser_hook):
        def process_request(connection, request):
            why = check(request)
            if why is not None:
                response = connection.respond(http.HTTPStatus.FORBIDDEN, why + "\n")
            else:
                response = viser_hook(connection, request)
            if response is not None and after is not None:
                after(request, response)
            return response

        return process_request

    original = ws_server.serve

    def serve(*args, **kwargs):
        hook = kwargs.get("process_request")
        if getattr(hook, "__name__", None) == VISER_HOOK:
            kwargs["process_request"] = check_first(hook)
            chained.append(hook)
        return original(*args, **kwargs)

    with _START_LOCK:  # one server starts at a time: the wrapper is in place only during its start
        ws_server.serve = serve  # type: ignore[misc,assignment]  # the one place viser's websockets serve is wrapped
        try:
            server = viser.ViserServer(host=host, port=port, verbose=verbose)
        finally:
            ws_server.serve = original  # type: ignore[misc]
    if not chained:
        server.stop()
        raise HandshakeHookMissing(
            f"viser {viser.__version__} no longer starts its server through websockets' serve(process_request="
            f"{VISER_HOOK}); the workbench cannot check who connects and does not start "
            "(see magcal_workbench/viser_adapter.py)"
        )
    return server


#: JavaScript for viser's page, run before viser's own code with the token in ``token`` (a string): the websocket
#: the page opens carries ``?token=`` -- added to the address the page hands its websocket worker, and only when
#: that address is the page's own server (viser also takes an address from ``?websocket=``; another server never
#: gets the token).
WEBSOCKET_TOKEN_JS = """
  var own = (location.protocol === "https:" ? "wss:" : "ws:") + "//" + location.host;
  var carry = function (address) {
    var url;
    try { url = new URL(address); } catch (e) { return address; }
    if (url.protocol + "//" + url.host !== own) return address;
    url.searchParams.set("token", token);
    return url.href;
  };
  var Base = window.Worker;
  window.Worker = class extends Base {
    postMessage(message, ...rest) {
      if (message && message.type === "set_server" && typeof message.server === "string") {
        message = Object.assign({}, message, {server: carry(message.server)});
      }
      return super.postMessage(message, ...rest);
    }
  };
"""

_HEAD = re.compile(rb"<head[^>]*>", re.IGNORECASE)
_PAGES: dict = {}  # (viser's body, snippet) -> the body with the snippet (viser keeps its file's bytes)


def set_body(response, body: bytes, content_type: str | None = None) -> None:
    """Replace an HTTP ``response``'s body (and its length; its type when given)."""
    response.body = body
    for name, value in (("Content-Length", str(len(body))), ("Content-Type", content_type)):
        if value is not None:
            if name in response.headers:
                del response.headers[name]
            response.headers[name] = value


def add_to_page(response, snippet: bytes) -> bool:
    """Put ``snippet`` (HTML, e.g. a ``<script>``) first in the ``<head>`` of viser's page ``response`` (a 200 HTML
    answer, gzip-compressed or not); other answers are left alone. Returns whether it was added."""
    if response.status_code != 200 or "text/html" not in (response.headers.get("Content-Type") or ""):
        return False
    key = (bytes(response.body), snippet)
    if key not in _PAGES:
        zipped = (response.headers.get("Content-Encoding") or "").lower() == "gzip"
        page = gzip.decompress(key[0]) if zipped else key[0]
        head = _HEAD.search(page)
        at = head.end() if head else 0
        page = page[:at] + snippet + page[at:]
        _PAGES[key] = gzip.compress(page, mtime=0) if zipped else page
    set_body(response, _PAGES[key])
    return True


def widget_id(handle) -> str:
    """The id viser's messages name a widget by."""
    return handle._impl.uuid


def watch_upload_starts(server, upload_handle, refuse: Callable[[str, int, object], bool]):
    """Call ``refuse(filename, size_bytes, client_id)`` when a browser starts an upload to ``upload_handle``;
    when it returns True the upload is dropped before its parts are buffered. Returns the handler registered
    (``handler(client_id, message)``), or None where this viser keeps no such state (the size is then checked
    after the upload only)."""
    from viser import _messages

    gui = server.gui
    if not hasattr(gui, "_current_file_upload_states"):
        return None
    uuid = widget_id(upload_handle)

    def started(client_id, message) -> None:
        if message.source_component_uuid != uuid:
            return
        if refuse(message.filename, message.size_bytes, client_id):
            gui._current_file_upload_states.pop(message.transfer_uuid, None)

    server._websock_server.register_handler(_messages.FileTransferStartUpload, started)
    return started


def watch_upload_parts(server, upload_handle, arrived: Callable[[str, int, object], bool]):
    """Call ``arrived(transfer_uuid, n_bytes, client_id)`` for every part of an upload to ``upload_handle``
    *before* viser buffers it; when it returns True the upload is dropped (its buffered parts freed, the parts
    that follow ignored). Returns the handler, or None where this viser keeps no such state."""
    from viser import _messages

    gui = server.gui
    handlers = getattr(server._websock_server, "_incoming_handlers", None)
    if not hasattr(gui, "_current_file_upload_states") or not isinstance(handlers, dict):
        return None
    uuid = widget_id(upload_handle)

    def part(client_id, message) -> None:
        if message.source_component_uuid != uuid:
            return
        if message.transfer_uuid not in gui._current_file_upload_states:
            return  # dropped already (or never started): viser ignores it too
        if arrived(message.transfer_uuid, len(message.content), client_id):
            gui._current_file_upload_states.pop(message.transfer_uuid, None)

    handlers.setdefault(_messages.FileTransferPart, []).insert(0, part)  # before viser's own buffering
    return part


def watch_updates(server, refuse: Callable[[object, dict, object], bool]):
    """Call ``refuse(handle, updates, client_id)`` for every change a browser sends to an input widget of the
    server's GUI (``updates``: ``{property: value}`` as sent), *before* viser casts and applies it; when it returns
    True the change is dropped (viser never sees it). Returns the handler registered, or None where this viser
    keeps no such state (the callbacks' checks then stand alone)."""
    from viser import _messages

    gui = server.gui
    handles = getattr(gui, "_gui_input_handle_from_uuid", None)
    handlers = getattr(server._websock_server, "_incoming_handlers", None)
    if not isinstance(handles, dict) or not isinstance(handlers, dict):
        return None

    def update(client_id, message) -> None:
        handle = handles.get(message.uuid)
        if handle is None:
            return  # viser ignores it too
        updates = message.updates if isinstance(message.updates, dict) else {"updates": message.updates}
        if refuse(handle, updates, client_id):
            message.uuid = ""  # viser's handler finds no widget of that id: the change is dropped

    handlers.setdefault(_messages.GuiUpdateMessage, []).insert(0, update)  # before viser's own
    return update


def show_value(handle) -> None:
    """Send ``handle``'s value to every browser again (after a refused change, the one who sent it shows the
    server's value, not what it typed)."""
    from viser import _messages

    handle._impl.gui_api._websock_interface.queue_message(
        _messages.GuiUpdateMessage(handle._impl.uuid, {"value": handle.value})
    )


def upload_in_flight(server, transfer_uuid: str) -> bool:
    """Whether viser still buffers the upload ``transfer_uuid`` (not finished, not dropped)."""
    return transfer_uuid in getattr(server.gui, "_current_file_upload_states", {})


def widget_kind(handle) -> str | None:
    """``"choice"`` (a dropdown), ``"number"`` (a slider or number box), ``"text"``, or None (others)."""
    import viser

    if isinstance(handle, viser.GuiDropdownHandle):
        return "choice"
    if isinstance(handle, (viser.GuiSliderHandle, viser.GuiNumberHandle)):
        return "number"
    if isinstance(handle, viser.GuiTextHandle):
        return "text"
    return None


def missing_internals() -> list[str]:
    """What this module relies on that the installed viser lacks (empty when all is there)."""
    import viser
    import websockets.asyncio.server as ws_server
    from viser import _messages
    from viser._gui_api import GuiApi
    from viser.infra import _infra

    problems = []
    serve_src = inspect.getsource(_infra)
    if f"def {VISER_HOOK}(" not in serve_src or "process_request=" not in serve_src:
        problems.append(f"viser.infra no longer serves through websockets serve(process_request={VISER_HOOK})")
    if not callable(getattr(ws_server, "serve", None)):
        problems.append("websockets.asyncio.server.serve is gone")
    msg = getattr(_messages, "FileTransferStartUpload", None)
    fields = set(getattr(msg, "__dataclass_fields__", {}) or {})
    need = {"source_component_uuid", "transfer_uuid", "filename", "size_bytes"}
    if msg is None or not need <= fields:
        problems.append(f"viser._messages.FileTransferStartUpload lacks {sorted(need - fields)}")
    if "_current_file_upload_states" not in inspect.getsource(GuiApi.__init__):
        problems.append("GuiApi no longer keeps _current_file_upload_states")
    part = getattr(_messages, "FileTransferPart", None)
    fields = set(getattr(part, "__dataclass_fields__", {}) or {})
    need = {"source_component_uuid", "transfer_uuid", "content"}
    if part is None or not need <= fields:
        problems.append(f"viser._messages.FileTransferPart lacks {sorted(need - fields)}")
    if "_incoming_handlers" not in inspect.getsource(_infra.WebsockServer.register_handler):
        problems.append("WebsockServer no longer keeps its handlers in _incoming_handlers")
    reg = getattr(_infra.WebsockServer, "register_handler", None)
    if reg is None or list(inspect.signature(reg).parameters)[:3] != ["self", "message_cls", "callback"]:
        problems.append("WebsockServer.register_handler(message_cls, callback) is gone")
    client = Path(viser.__file__).parent / "client"
    if not (client / "build" / "index.html").is_file():
        problems.append("viser no longer serves its page from client/build/index.html")
    sources = client / "src"
    if sources.is_dir():  # the client's sources ship with viser 1.1.1: what WEBSOCKET_TOKEN_JS relies on
        try:
            ui = (sources / "WebsocketInterface.tsx").read_text(encoding="utf-8")
            worker = (sources / "WebsocketClientWorker.ts").read_text(encoding="utf-8")
        except OSError:
            ui = worker = ""
        if 'type: "set_server", server' not in ui or "new WebsocketClientWorker()" not in ui:
            problems.append("viser's page no longer hands its websocket's address to a Worker (set_server)")
        if 'data.type === "set_server"' not in worker or "new WebSocket(server" not in worker:
            problems.append("viser's websocket worker no longer opens the address set_server gives")
    update = getattr(_messages, "GuiUpdateMessage", None)
    fields = set(getattr(update, "__dataclass_fields__", {}) or {})
    if update is None or not {"uuid", "updates"} <= fields:
        problems.append(f"viser._messages.GuiUpdateMessage lacks {sorted({'uuid', 'updates'} - fields)}")
    if "_gui_input_handle_from_uuid" not in inspect.getsource(GuiApi._handle_gui_updates):
        problems.append("GuiApi no longer finds a widget by _gui_input_handle_from_uuid")
    if "_websock_server" not in inspect.getsource(viser.ViserServer.__init__):
        problems.append("ViserServer no longer keeps _websock_server")
    for name in ("GuiDropdownHandle", "GuiSliderHandle", "GuiNumberHandle", "GuiTextHandle"):
        if not hasattr(viser, name):
            problems.append(f"viser.{name} is gone")
    return problems


def scene_node_names(server) -> list[str]:
    """The names of the scene nodes the server holds now (what every browser that connects is sent), sorted."""
    return sorted(server.scene._handle_from_node_name)
