"""What a killed run leaves behind, and worker processes that end with the run that started them.

A program killed outright (SIGKILL, the out-of-memory killer, a closed container) runs no cleanup of its own:

* its worker processes go on waiting for work that never comes. A diagnosis's workers are forked by
  :mod:`multiprocessing`'s fork server, not by the diagnosis, and each holds the fork server's and the resource
  tracker's pipes open, so those two wait for the workers in turn (a Dask cluster's workers watch their nanny's
  pipe and end). :func:`exit_with` makes a worker end when the process that started its pool ends: the kernel
  says so through a process file descriptor (Linux 5.3 and later: ``pidfd_open``; no polling, and the number
  cannot be reused while the descriptor is open), elsewhere a thread asks every :data:`POLL_S` seconds. Once
  the workers are gone, the fork server and the resource tracker see their pipes close and end, and the tracker
  unlinks the shared memory registered with it. ``prctl(PR_SET_PDEATHSIG)`` would not do: it fires when the
  *parent* ends, and a worker's parent is the fork server, which outlives the diagnosis as long as a worker does.
* the files it was writing stay where they were: a diagnosis's shared-memory segment (``/dev/shm/magcal_<pid>_*``,
  when the resource tracker was killed too), a survey correction's hidden work folder beside its output. Their
  names hold the process number of the run that made them; :func:`remove_stale` removes those whose process no
  longer runs, and :func:`removed_text` says what was removed, for the next run's output.
"""

from __future__ import annotations

import hashlib
import os
import re
import select
import shutil
import socket
import threading
import time
from dataclasses import dataclass

#: Seconds between two looks at the owner where the kernel cannot tell (no ``pidfd_open``).
POLL_S = 0.5


def pid_running(pid: int) -> bool:
    """Whether process ``pid`` runs on this machine (a zombie, ended but not yet reaped, does not run; another
    user's process does, though this one may not signal it). Where it cannot be asked without harm (Windows, whose
    ``os.kill(pid, 0)`` sends Ctrl-C), every process is taken to run: nothing is removed there."""
    if pid <= 0:
        return False
    if os.name == "nt":
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    except OSError:
        return False
    try:
        with open(f"/proc/{pid}/stat", "rb") as fh:
            state = fh.read().rsplit(b")", 1)[1].split()[0]
    except (OSError, IndexError):
        return True  # no /proc (macOS): os.kill is all there is
    return state not in (b"Z", b"X")


def exit_with(owner_pid: int, code: int = 1) -> str:
    """End this process (``os._exit(code)``) as soon as process ``owner_pid`` ends; returns how it is watched:
    ``"pidfd"`` (the kernel says when), ``"poll"`` (a thread asks every :data:`POLL_S` seconds) or ``"self"``
    (``owner_pid`` is this process: nothing to watch).

    Called in a worker process as it starts, with the number of the process that started its pool. A worker
    whose owner has already ended exits here, at once.
    """
    owner_pid = int(owner_pid)
    if owner_pid == os.getpid():
        return "self"
    fd = None
    pidfd_open = getattr(os, "pidfd_open", None)
    if pidfd_open is not None:
        try:
            fd = pidfd_open(owner_pid)
        except ProcessLookupError:
            os._exit(code)
        except OSError:  # a kernel before 5.3, or a sandbox that forbids it
            fd = None
    if fd is None and not pid_running(owner_pid):
        os._exit(code)
    parent = os.getppid()
    how = "pidfd" if fd is not None else "poll"
    threading.Thread(target=_watch, args=(owner_pid, fd, parent, code), name="magcal-owner-watch", daemon=True).start()
    return how


def _watch(owner_pid: int, fd, parent: int, code: int) -> None:
    if fd is not None:
        while True:
            try:
                ready, _, _ = select.select([fd], [], [])
            except InterruptedError:
                continue
            if ready:  # a process file descriptor reads ready once its process has ended
                os._exit(code)
    while pid_running(owner_pid) and not (parent == owner_pid and os.getppid() != parent):
        time.sleep(POLL_S)
    os._exit(code)


def host_tag() -> str:
    """Six hex digits of this machine's name: a work folder on a file system several machines share names the
    machine whose process made it (a process number means nothing on another machine)."""
    return hashlib.sha1(socket.gethostname().encode("utf-8", "replace")).hexdigest()[:6]


@dataclass(frozen=True)
class Leftover:
    """A file or folder removed because the run that made it no longer runs."""

    path: str
    pid: int
    nbytes: int


def _size(path: str) -> int:
    if not os.path.isdir(path) or os.path.islink(path):
        return os.lstat(path).st_size
    total = 0
    for root, _, files in os.walk(path):
        for name in files:
            try:
                total += os.lstat(os.path.join(root, name)).st_size
            except OSError:
                continue
    return total


def remove_stale(directory, pattern: re.Pattern, host: str | None = None) -> list[Leftover]:
    """Remove the entries of ``directory`` whose name matches ``pattern`` and whose process no longer runs.

    Parameters
    ----------
    directory : str or os.PathLike
    pattern : re.Pattern
        Matches a leftover's whole name; its group ``pid`` is the number of the process that made it, and an
        optional group ``host`` must equal ``host``.
    host : str, optional
        This machine's :func:`host_tag`, where names carry one.

    Returns
    -------
    list of Leftover
        What was removed. Entries of another user, of a process still running, of another machine, and those
        that cannot be removed (their error) are left as they are.
    """
    directory = os.fspath(directory)
    try:
        names = os.listdir(directory)
    except OSError:
        return []
    uid = os.getuid() if hasattr(os, "getuid") else None
    out = []
    for name in sorted(names):
        m = pattern.fullmatch(name)
        if m is None or ("host" in pattern.groupindex and m.group("host") != host):
            continue
        pid = int(m.group("pid"))
        path = os.path.join(directory, name)
        try:
            if uid is not None and os.lstat(path).st_uid != uid:
                continue
            if pid == os.getpid() or pid_running(pid):
                continue
            nbytes = _size(path)
            if os.path.isdir(path) and not os.path.islink(path):
                shutil.rmtree(path)
            else:
                os.unlink(path)
        except OSError:
            continue
        out.append(Leftover(path, pid, nbytes))
    return out


def _megabytes(nbytes: int) -> str:
    return f"{nbytes / 1e6:,.0f} MB" if nbytes >= 10e6 else f"{nbytes / 1e6:.2g} MB"


def removed_text(leftovers, what: str, by: str) -> str | None:
    """One line naming what :func:`remove_stale` removed (None when nothing was), e.g. ``removed what a killed
    diagnosis left behind: 1 shared-memory segment, 240 MB (process 4711, no longer running):
    /dev/shm/magcal_4711_...``.

    Parameters
    ----------
    leftovers : sequence of Leftover
    what : str
        What each is, singular (``"shared-memory segment"``).
    by : str
        The kind of run that made them (``"diagnosis"``).
    """
    leftovers = list(leftovers)
    if not leftovers:
        return None
    n = len(leftovers)
    pids = list(dict.fromkeys(x.pid for x in leftovers))
    return (
        f"removed what a killed {by} left behind: {n} {what}{'s' if n > 1 else ''}, "
        f"{_megabytes(sum(x.nbytes for x in leftovers))} (process{'es' if len(pids) > 1 else ''} "
        f"{', '.join(map(str, pids))}, no longer running): {', '.join(x.path for x in leftovers)}"
    )
