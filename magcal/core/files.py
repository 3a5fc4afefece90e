"""What a path a user gives names: magcal reads only regular files.

A FIFO (named pipe) blocks its reader until some other process writes to it, which may be never; a device such as
``/dev/zero`` or ``/dev/urandom`` never ends. Every path magcal opens for reading (data files, logs, calibrations,
effects files, masks) is checked here first, so that such a path is one clear message instead of a hang.
"""

from __future__ import annotations

import os
import stat

from magcal.core.errors import MagcalError

#: What each kind of non-regular file is called in messages (``stat.S_IFMT`` -> words).
_KINDS = {
    stat.S_IFIFO: "a FIFO (named pipe), which blocks its reader until another program writes to it",
    stat.S_IFCHR: "a character device, not a file: it may never end",
    stat.S_IFBLK: "a block device, not a file",
    stat.S_IFSOCK: "a socket, not a file",
    stat.S_IFDIR: "a directory",
}


def not_regular_reason(path) -> str | None:
    """Why ``path`` is not a regular file magcal may read (``"no such file"``, ``"a FIFO ..."``), or None when it
    is one. Symbolic links are followed (a link to a regular file is fine). Never opens the path."""
    try:
        mode = os.stat(os.fspath(path)).st_mode
    except FileNotFoundError:
        return "no such file"
    except OSError as exc:
        return f"cannot be read ({exc.strerror or exc})"
    if stat.S_ISREG(mode):
        return None
    return _KINDS.get(stat.S_IFMT(mode), "not a regular file")


def check_regular_file(path, what="file", error=MagcalError, source=None) -> str:
    """``path`` as text if it names a regular file, else ``error`` (a :class:`MagcalError` class) saying what it
    names instead and what to do.

    Parameters
    ----------
    path : str or os.PathLike
    what : str
        What the file should be, for the message (``"calibration file"``, ``"effects file"``).
    error : type
        The exception class raised (a subclass of :class:`MagcalError`, e.g. ``DatasetError``).
    source : str, optional
        What the message calls the path (default the path itself).
    """
    path = os.fspath(path)
    reason = not_regular_reason(path)
    if reason is None:
        return path
    name = source or path
    if reason == "no such file":
        raise error(f"{name}: no such {what}; check the path")
    if reason.startswith("cannot"):
        raise error(f"{name}: {reason}; check the path and its permissions")
    raise error(f"{name}: is {reason}; give the path of a regular {what}")
