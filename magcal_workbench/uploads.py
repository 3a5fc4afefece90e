"""The Files tab's uploads: a file from the browser (CSV or a flight-controller log) read with the tab's Columns,
Units and LSB, bounded in size (``--max-upload-mb``): by the size declared when it starts, by the bytes received as
its parts arrive (a client that declares a small size and sends a large one is dropped as soon as it passes the
bound, before viser buffers the part), and again when it has arrived."""

from __future__ import annotations

import os
import threading

from magcal.core.errors import MagcalError
from magcal.data.logs import is_log

from . import viser_adapter
from .actions import action
from .controller import MESSAGE_LEN
from .dataio import canonical_csv, page_words, read_bytes_dataset
from .markup import clean_text, safe_code, safe_text
from .parts import PagePart

#: Longest uploaded file name kept, characters (the rest is cut; a file system allows 255 bytes).
MAX_NAME_CHARS = 120
#: The Units choices of an upload (the first keeps the file's own ``# units:`` line).
UPLOAD_UNITS = ("from the file", "nT", "uT", "G", "mG", "counts")


def clean_upload_name(name) -> str:
    """An uploaded file's name made safe to show and to key a session: its last path part, control characters
    removed, cut to :data:`MAX_NAME_CHARS`; ``upload.csv`` when nothing usable is left (``..``, ``.``, empty)."""
    text = clean_text(name if isinstance(name, str) else "", 4 * MAX_NAME_CHARS)
    base = text.replace("\\", "/").rsplit("/", 1)[-1].strip()
    if base.strip(".") == "":
        return "upload.csv"
    if len(base) > MAX_NAME_CHARS:
        stem, dot, ext = base.rpartition(".")
        ext = ext if dot and len(ext) <= 8 else ""
        base = base[: MAX_NAME_CHARS - len(ext) - 1].rstrip() + ("." + ext if ext else "")
    return base


class Uploads(PagePart):
    """Reads what the page uploads into the workbench (:meth:`Workbench.load`).

    Handed what it uses.

    Parameters
    ----------
    ctrl, panels : callable
        Getters: the open data's :class:`~magcal_workbench.controller.Controller` and the
        :class:`~magcal_workbench.panels.Panels` (made after this part).
    values : magcal_workbench.checks.PageValues
        What each input widget may send (the reading options are checked before they are read).
    server : viser.ViserServer
        Whose uploads are watched as they arrive.
    ui : magcal_workbench.uiqueue.UiQueue
        The page's thread: what a job or viser's event loop shows goes through it.
    notify : callable
        ``notify(client_id, text)``: a toast in that browser (:meth:`magcal_workbench.app.Workbench.notify`).
    load : callable
        ``load(dataset, content, name)``: opens the data read (:meth:`magcal_workbench.app.Workbench.load`).
    say_after_load : callable
        ``say_after_load(text)``: says what reading it found (:meth:`magcal_workbench.app.Workbench.say_after_load`).
    max_upload_bytes : int
        Largest upload accepted, bytes.
    """

    def __init__(
        self, *, ctrl, panels, values, server, ui, notify, load, say_after_load, max_upload_bytes: int
    ) -> None:
        self._ctrl, self._panels = ctrl, panels
        self.values, self.server, self.ui, self.notify = values, server, ui, notify
        self.load, self.say_after_load = load, say_after_load
        self.max_upload_bytes = int(max_upload_bytes)
        #: ``(name, content)`` of the last upload (Re-read reads it again with other options).
        self.last: tuple[str, bytes] | None = None
        #: viser's upload-start handler registered by :meth:`watch_sizes` (None where viser keeps no such state).
        self.start_handler = None
        #: The upload-part handler registered by :meth:`watch_sizes` (None where viser keeps no such state).
        self.part_handler = None
        self._received: dict[str, int] = {}  # bytes received so far per upload in flight
        self._received_lock = threading.Lock()

    def too_large(self, name: str, size_bytes: int) -> str | None:
        """Why an upload of ``size_bytes`` is refused, or None."""
        if size_bytes <= self.max_upload_bytes:
            return None
        return f"{name}: {size_bytes / 1e6:.1f} MB is more than the upload limit of {self.max_upload_bytes / 1e6:g} MB"

    def _tell(self, client_id, text: str) -> None:
        def tell():
            self.ctrl.say(f"**Error:** {safe_text(text)}")
            self.notify(client_id, text)

        self.ui.post(tell)  # off viser's event loop

    def watch_sizes(self, upload_handle) -> None:
        """Refuse an upload over the limit when it starts (the browser declares its size,
        :func:`magcal_workbench.viser_adapter.watch_upload_starts`) and as its parts arrive (the bytes received
        counted before viser buffers each part, :func:`magcal_workbench.viser_adapter.watch_upload_parts`): the
        uploads in flight together hold at most twice the limit. :meth:`do_upload` checks the size again."""

        def refuse(filename, size_bytes, client_id) -> bool:
            why = self.too_large(clean_upload_name(filename), size_bytes)
            if why is None:
                return False
            self._tell(client_id, f"{why}; refused")
            return True

        def arrived(transfer_uuid, n_bytes, client_id) -> bool:
            with self._received_lock:
                for old in [t for t in self._received if not viser_adapter.upload_in_flight(self.server, t)]:
                    del self._received[old]  # finished or dropped
                got = self._received.get(transfer_uuid, 0) + int(n_bytes)
                in_flight = sum(self._received.values()) + int(n_bytes)
                over = got > self.max_upload_bytes or in_flight > 2 * self.max_upload_bytes
                if over:
                    self._received.pop(transfer_uuid, None)
                else:
                    self._received[transfer_uuid] = got
            if over:
                self._tell(
                    client_id,
                    f"an upload passed the upload limit of {self.max_upload_bytes / 1e6:g} MB "
                    "(more bytes than it declared, or too many uploads at once); dropped",
                )
            return over

        self.start_handler = viser_adapter.watch_upload_starts(self.server, upload_handle, refuse)
        self.part_handler = viser_adapter.watch_upload_parts(self.server, upload_handle, arrived)

    @action
    def do_upload(self, event):
        up = self.panels.upload.value
        name, content = clean_upload_name(up.name), up.content
        if not content:
            raise MagcalError(f"{name}: the file is empty")
        why = self.too_large(name, len(content))
        if why:
            raise MagcalError(
                f"{why}; open it from the command line "
                "(magcal-workbench FILE.csv) or start the workbench with a larger --max-upload-mb"
            )
        self.last = (name, content)
        self.open(name, content)

    @action
    def do_reread(self, event):
        """Read the last upload again with the Files tab's Columns, Units and LSB (no new upload needed)."""
        if self.last is None:
            raise MagcalError("upload a file first (Open a file), then set Columns or Units and re-read it")
        self.open(*self.last)

    def read_options(self) -> dict:
        """The Files tab's reading options, checked (``columns``, ``units``, ``lsb_nT`` for the engine's reader)."""
        p, check = self.panels, self.values.check
        columns = check(p.upload_columns).strip() or None
        units = check(p.upload_units)
        lsb = float(check(p.upload_lsb))
        return {
            "columns": columns,
            "units": None if units == UPLOAD_UNITS[0] else units,
            "lsb_nT": lsb if lsb > 0 else None,
        }

    def open(self, name: str, content: bytes) -> None:
        """Read ``content`` (named ``name``) in the worker and open it; a session keeps data read through a
        mapping, units or a log reader as magcal's own CSV."""
        options = self.read_options()
        mapped = is_log(name) or any(v is not None for v in options.values())

        def job():
            header = content[:4096].decode("utf-8", "replace").splitlines()
            found = next((line for line in header if line.strip() and not line.startswith("#")), "")
            info = "" if is_log(name) else f"Columns in {safe_code(name)}: {safe_text(found, 400)}"
            self.ui.post(lambda: setattr(self.panels.upload_info, "content", info))
            try:
                ds, notes = read_bytes_dataset(name, content, **options)
            except MagcalError as exc:
                raise MagcalError(page_words(str(exc))) from None
            self.load(
                ds, canonical_csv(ds) if mapped else content, name if not mapped else os.path.splitext(name)[0] + ".csv"
            )
            self.say_after_load(
                f"opened {safe_code(name)}: {safe_text(ds.describe(), MESSAGE_LEN)}"
                + "".join(f"  \n- {safe_text(page_words(n), MESSAGE_LEN)}" for n in notes)
            )

        self.ctrl.run_job("open file", job)
