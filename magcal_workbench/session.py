"""Sessions on disk: autosave and reopen.

A session is a folder ``<root>/<id>/`` holding ``session.json`` (the :class:`~magcal_workbench.state.SessionState`)
and ``data.csv`` (a copy of the data it works on, so the session reopens even if the original file moves or
was uploaded from a browser). The id is the data file's name plus the start of its SHA-1, so opening the same
file again finds its session. Every write is atomic (temporary file, then :func:`os.replace`).

The default root is ``~/.magcal/sessions`` (``MAGCAL_SESSION_DIR`` or ``--session-dir`` override it).

The folder is bounded: when a new session's copy of its data would take the sessions past
:attr:`SessionStore.max_bytes`, the least recently saved sessions are deleted (:meth:`SessionStore.prune`; the
open one never, folders set aside never; the live recordings in ``recordings`` are not sessions and are neither
counted nor deleted, nor is any folder holding a recording being written) and the page and the terminal say
which. :meth:`SessionStore.list` gives each
session's size, and the page deletes one on request.

A session's name (its id) is only ever a folder *directly inside* the root: :func:`check_session_name` refuses
``..``, absolute paths and path separators (a name may come from a browser's dropdown). ``session.json`` is read
by the one validating reader (:mod:`workbench.sessionfile`); a damaged one is moved aside with
:meth:`SessionStore.set_aside` (renamed ``<id>.damaged-<time>``, never deleted) and the session starts afresh.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import sys
import threading
import time
import weakref
from collections.abc import Callable, Iterable
from pathlib import Path

from magcal.core.files import not_regular_reason
from magcal.data.io import atomic_write

from .defaults import MAX_STORE_BYTES
from .sessionfile import MAX_BYTES as MAX_READ
from .sessionfile import SessionError, SessionFileError, read_session_bytes
from .state import SessionState

SESSION_FILE = "session.json"
DATA_FILE = "data.csv"
#: What a session name may look like: one folder name, no separator, not ``.``/``..``, no leading dot.
SESSION_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,119}$")
#: Marks a folder moved aside because its session file was damaged.
DAMAGED = ".damaged-"
#: The folder of live recordings inside the session folder: not a session, never pruned.
RECORDINGS = "recordings"


def check_session_name(sid) -> str:
    """``sid`` if it names a folder directly inside the session root, else :class:`SessionError`.

    Refused: anything but text, ``.`` and ``..``, absolute paths, ``/`` or ``\\`` separators, a leading dot,
    characters other than letters, digits, ``_ . -``, and names longer than 120 characters.
    """
    if not isinstance(sid, str) or not SESSION_NAME.fullmatch(sid) or sid in (".", ".."):
        from .markup import clean_text

        raise SessionError(
            f"{clean_text(repr(sid), 80)} is not a session name: a name is one folder inside the "
            "session folder (letters, digits, _ . -; no '..', no path)"
        )
    return sid


def default_root() -> Path:
    """``$MAGCAL_SESSION_DIR`` or ``~/.magcal/sessions``."""
    env = os.environ.get("MAGCAL_SESSION_DIR")
    return Path(env) if env else Path.home() / ".magcal" / "sessions"


def write_bytes_atomic(path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (the engine's :func:`magcal.data.io.atomic_write`), making its folder
    readable by this user only (0700: a session holds the user's data; its files follow the umask)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
    with atomic_write(path, "wb") as fh:
        fh.write(data)


def write_json_atomic(path, doc) -> None:
    """Write ``doc`` as JSON (indented by one space) to ``path`` atomically, encoded piece by piece into the file:
    never the whole text in memory at once (:func:`write_bytes_atomic`'s folder and rights)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
    with atomic_write(path, "w", encoding="utf-8") as fh:
        for piece in json.JSONEncoder(indent=1).iterencode(doc):
            fh.write(piece)
        fh.write("\n")


def session_id(name: str, content: bytes) -> str:
    """Folder name of a session: a safe form of the file's name plus 10 hex digits of its SHA-1."""
    stem = re.sub(r"[^A-Za-z0-9_.-]+", "_", Path(name).stem)[:40].lstrip(".-") or "data"
    return f"{stem}-{hashlib.sha1(content).hexdigest()[:10]}"


class SessionStore:
    """The folder of saved sessions.

    Parameters
    ----------
    root : path-like, optional
        Where sessions live (:func:`default_root` if omitted).
    max_bytes : int
        Bound of the sessions' total size, bytes (:meth:`prune`).

    Attributes
    ----------
    pruned : list of (str, int)
        The sessions the last :meth:`create` deleted to stay within :attr:`max_bytes`, with their sizes in bytes.
    """

    def __init__(self, root=None, max_bytes: int = MAX_STORE_BYTES):
        self.root = Path(root) if root is not None else default_root()
        self.max_bytes = int(max_bytes)
        self.pruned: list[tuple[str, int]] = []
        #: Returns the files in use that pruning must keep (the live recording being written); set by the app.
        self.in_use: Callable[[], Iterable] = lambda: ()
        self._save_lock = threading.Lock()
        self._saved_versions: weakref.WeakKeyDictionary = (
            weakref.WeakKeyDictionary()
        )  # state -> {session id: version last written}

    def folder(self, sid: str) -> Path:
        """The folder of session ``sid`` (directly inside :attr:`root`; :func:`check_session_name` first)."""
        return self.root / check_session_name(sid)

    def create(self, name: str, content: bytes) -> str:
        """Make (or find) the session folder for a data file's bytes; returns its id. The data are copied in."""
        sid = session_id(name, content)
        data = self.folder(sid) / DATA_FILE
        self.pruned = []
        if not data.exists():
            self.pruned = self.prune(self.max_bytes - len(content), protect=(sid,))
            write_bytes_atomic(data, content)
        return sid

    def size_bytes(self, sid: str) -> int:
        """Bytes a session's folder takes (its files, not the folder entries)."""
        return sum(p.stat().st_size for p in self.folder(sid).rglob("*") if p.is_file())

    def prune(self, budget_bytes: int, protect=()) -> list[tuple[str, int]]:
        """Delete the least recently saved sessions until the others take at most ``budget_bytes``.

        Only sessions count and go: folders set aside as damaged, the sessions in ``protect``, the ``recordings``
        folder, folders holding neither a session file nor a data copy, and any folder holding a file of
        :attr:`in_use` are never deleted. Each deletion is printed (stderr). Returns the deleted ``(id, bytes)``,
        oldest first."""
        if not self.root.is_dir():
            return []
        keep = set()
        for path in self.in_use() or ():
            try:
                keep.add(Path(path).resolve())
            except OSError:
                continue
        folders = []
        for folder in self.root.iterdir():
            if not folder.is_dir() or DAMAGED in folder.name or not SESSION_NAME.fullmatch(folder.name):
                continue
            if folder.name == RECORDINGS or not any((folder / f).is_file() for f in (SESSION_FILE, DATA_FILE)):
                continue  # not a session
            here = folder.resolve()
            if any(here == p or here in p.parents for p in keep):
                continue
            try:
                size = self.size_bytes(folder.name)
                mtime = max((p.stat().st_mtime for p in folder.iterdir()), default=folder.stat().st_mtime)
            except OSError:
                continue
            folders.append((mtime, folder.name, size))
        total = sum(f[2] for f in folders)
        removed = []
        for _, name, size in sorted(folders):
            if total <= budget_bytes:
                break
            if name in protect:
                continue
            self.delete(name)
            total -= size
            removed.append((name, size))
            print(
                f"magcal-workbench: the session folder is bounded to {self.max_bytes / 1e6:g} MB "
                f"(--max-sessions-mb): deleted the session {name} ({size / 1e6:.1f} MB)",
                file=sys.stderr,
            )
        return removed

    def data_path(self, sid: str) -> Path:
        return self.folder(sid) / DATA_FILE

    def exists(self, sid: str) -> bool:
        return (self.folder(sid) / SESSION_FILE).exists()

    def save(self, sid: str, state: SessionState, extra: dict | None = None) -> Path:
        """Write the session atomically; returns the file written."""
        path = self.folder(sid) / SESSION_FILE
        with state.lock:  # the document is one consistent moment of the state
            doc = state.to_dict()
            version = state.version
        doc["saved_at"] = time.strftime("%Y-%m-%d %H:%M:%S")
        if extra:
            doc.update(extra)
        with self._save_lock:  # one writer at a time; an older document never replaces a newer one
            written = self._saved_versions.setdefault(state, {})
            if version < written.get(sid, -1):
                return path
            write_json_atomic(path, doc)  # streamed: the document's rows are bounded, its text never held whole
            written[sid] = version
        return path

    def load(self, sid: str, expect: tuple[int, int] | None = None) -> SessionState:
        """Read a saved session (its ``data_path`` points at the session's copy of the data).

        Parameters
        ----------
        sid : str
            The session's name.
        expect : (int, int), optional
            ``(n_samples, n_sensors)`` of the data it must describe.

        Raises
        ------
        SessionFileError
            The file is damaged (the field is named) or describes other data.
        SessionError
            ``sid`` is not a session name.
        OSError
            The file cannot be read.
        """
        path = self.folder(sid) / SESSION_FILE
        where = f"{sid}/{SESSION_FILE}"  # messages reach the page: no absolute path
        why = not_regular_reason(path)  # a FIFO would block the reader, a device never end
        if why is not None and path.exists():
            raise SessionFileError(where, "(the file itself)", f"not a regular file ({why})")
        with open(path, "rb") as fh:
            data = fh.read(MAX_READ + 1)
        state = read_session_bytes(data, where)
        if expect is not None and (state.n_samples, state.n_sensors) != tuple(expect):
            field = "n_samples" if state.n_samples != expect[0] else "n_sensors"
            raise SessionFileError(
                where,
                field,
                f"the session is for {state.n_samples} samples of "
                f"{state.n_sensors} sensor(s), the data have {expect[0]} of {expect[1]}",
            )
        copy = self.data_path(sid)
        if copy.exists():
            state.data_path = str(copy)
        return state

    def set_aside(self, sid: str) -> Path:
        """Rename a session's folder to ``<sid>.damaged-<YYYYmmdd-HHMMSS>`` (kept for inspection, never deleted);
        returns the new folder."""
        old = self.folder(sid)
        stamp = time.strftime("%Y%m%d-%H%M%S")
        new = self.root / f"{sid}{DAMAGED}{stamp}"
        k = 1
        while new.exists():
            k += 1
            new = self.root / f"{sid}{DAMAGED}{stamp}-{k}"
        os.replace(old, new)
        return new

    def list(self) -> list[dict]:
        """Saved sessions that can be reopened, newest first: ``{"id", "saved_at", "lesson", "n_samples",
        "effects", "rms_nT", "mtime", "bytes"}`` (folders set aside, badly named or with a damaged file are left
        out; ``bytes`` is the folder's size)."""
        out: list = []
        if not self.root.exists():
            return out
        for folder in self.root.iterdir():
            path = folder / SESSION_FILE
            if DAMAGED in folder.name or not SESSION_NAME.fullmatch(folder.name) or not path.is_file():
                continue
            try:
                with open(path, "rb") as fh:
                    data = fh.read(MAX_READ + 1)
                state = read_session_bytes(data, str(path))
                saved_at = state.saved_at
                mtime = path.stat().st_mtime
                size = self.size_bytes(folder.name)
            except (OSError, SessionError, MemoryError, RecursionError):  # not listed; opening it says why
                continue
            hist = state.history
            out.append(
                {
                    "id": folder.name,
                    "saved_at": saved_at,
                    "lesson": state.lesson,
                    "n_samples": state.n_samples,
                    "effects": list(state.effects),
                    "rms_nT": hist[-1].rms_nT if hist else None,
                    "mtime": mtime,
                    "bytes": size,
                }
            )
        out.sort(key=lambda d: d["mtime"], reverse=True)
        return out

    def delete(self, sid: str) -> None:
        shutil.rmtree(self.folder(sid), ignore_errors=True)
