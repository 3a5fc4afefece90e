"""Sessions on disk: autosave and reopen.

A session is a folder ``<root>/<id>/`` holding ``session.json`` (the :class:`~workbench.state.SessionState`)
and ``data.csv`` (a copy of the data it works on, so the session reopens even if the original file moves or
was uploaded from a browser). The id is the data file's name plus the start of its SHA-1, so opening the same
file again finds its session. Every write is atomic (temporary file, then :func:`os.replace`).

The default root is ``~/.magcal/sessions`` (``MAGCAL_SESSION_DIR`` or ``--session-dir`` override it).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import time
from pathlib import Path

from magcal.io import atomic_write

from .state import SessionState

SESSION_FILE = "session.json"
DATA_FILE = "data.csv"


def default_root() -> Path:
    """``$MAGCAL_SESSION_DIR`` or ``~/.magcal/sessions``."""
    env = os.environ.get("MAGCAL_SESSION_DIR")
    return Path(env) if env else Path.home() / ".magcal" / "sessions"


def write_bytes_atomic(path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (the engine's :func:`magcal.io.atomic_write`), making its folder."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path, "wb") as fh:
        fh.write(data)


def session_id(name: str, content: bytes) -> str:
    """Folder name of a session: a safe form of the file's name plus 10 hex digits of its SHA-1."""
    stem = re.sub(r"[^A-Za-z0-9_.-]+", "_", Path(name).stem)[:40] or "data"
    return f"{stem}-{hashlib.sha1(content).hexdigest()[:10]}"


class SessionStore:
    """The folder of saved sessions.

    Parameters
    ----------
    root : path-like, optional
        Where sessions live (:func:`default_root` if omitted).
    """

    def __init__(self, root=None):
        self.root = Path(root) if root is not None else default_root()

    def folder(self, sid: str) -> Path:
        return self.root / sid

    def create(self, name: str, content: bytes) -> str:
        """Make (or find) the session folder for a data file's bytes; returns its id. The data are copied in."""
        sid = session_id(name, content)
        data = self.folder(sid) / DATA_FILE
        if not data.exists():
            write_bytes_atomic(data, content)
        return sid

    def data_path(self, sid: str) -> Path:
        return self.folder(sid) / DATA_FILE

    def exists(self, sid: str) -> bool:
        return (self.folder(sid) / SESSION_FILE).exists()

    def save(self, sid: str, state: SessionState, extra: dict | None = None) -> Path:
        """Write the session atomically; returns the file written."""
        doc = state.to_dict()
        doc["saved_at"] = time.strftime("%Y-%m-%d %H:%M:%S")
        if extra:
            doc.update(extra)
        path = self.folder(sid) / SESSION_FILE
        write_bytes_atomic(path, (json.dumps(doc, indent=1) + "\n").encode("utf-8"))
        return path

    def load(self, sid: str) -> SessionState:
        """Read a saved session (its ``data_path`` points at the session's copy of the data)."""
        path = self.folder(sid) / SESSION_FILE
        with open(path, encoding="utf-8") as fh:
            doc = json.load(fh)
        state = SessionState.from_dict(doc)
        copy = self.data_path(sid)
        if copy.exists():
            state.data_path = str(copy)
        return state

    def list(self) -> list[dict]:
        """Saved sessions, newest first: ``{"id", "saved_at", "lesson", "n_samples", "effects", "rms_nT"}``."""
        out = []
        if not self.root.exists():
            return out
        for folder in self.root.iterdir():
            path = folder / SESSION_FILE
            if not path.is_file():
                continue
            try:
                with open(path, encoding="utf-8") as fh:
                    doc = json.load(fh)
            except (OSError, json.JSONDecodeError):
                continue
            hist = doc.get("history") or []
            out.append({
                "id": folder.name, "saved_at": doc.get("saved_at", ""), "lesson": doc.get("lesson"),
                "n_samples": doc.get("n_samples"), "effects": doc.get("effects", []),
                "rms_nT": hist[-1]["rms_nT"] if hist else None, "mtime": path.stat().st_mtime,
            })
        out.sort(key=lambda d: d["mtime"], reverse=True)
        return out

    def delete(self, sid: str) -> None:
        shutil.rmtree(self.folder(sid), ignore_errors=True)
