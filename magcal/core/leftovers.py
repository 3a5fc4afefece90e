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
* the temporary folder of :mod:`multiprocessing` (``/tmp/pymp-XXXXXXXX``, which holds the fork server's socket):
  the process that made it removes it at its exit, which a killed one never reaches. :func:`run_dir` gives
  :mod:`multiprocessing` a folder of magcal's instead (``magcal-HOST-PID-XXXXXXXX`` in the temporary folder),
  which the fork server removes as it ends (it ends once the process that started it and its workers have: the
  folder's path reaches it in :data:`RUN_DIR_ENV` as it starts), and which the next run removes where the fork
  server was killed too (:func:`remove_stale_run_dirs`).
"""

from __future__ import annotations

import atexit
import hashlib
import os
import re
import select
import shutil
import socket
import sys
import tempfile
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


#: The name of a run's temporary folder (:func:`run_dir`) in the temporary folder (``tempfile.gettempdir()``):
#: ``magcal-HOST-PID-XXXXXXXX``, with six hex digits of the machine's name (:func:`host_tag`) and the number
#: of the process that made it.
RUN_DIR_NAME = re.compile(r"magcal-(?P<host>[0-9a-f]{6})-(?P<pid>[0-9]+)-[a-z0-9_]{8}")
#: The longest path of a Unix socket that every platform takes (Linux 107 bytes, macOS 103), less the
#: ``/listener-XXXXXXXX`` :mod:`multiprocessing` adds: a run folder further down (a long ``TMPDIR``) is made in
#: ``/tmp`` instead, where the fork server's socket can be bound.
RUN_DIR_MAX_PATH = 103 - len("/listener-XXXXXXXX")
#: The environment variable that names a run's temporary folder to the fork server as it starts: the server
#: removes that folder as it ends (:func:`_removed_by_the_fork_server`).
RUN_DIR_ENV = "MAGCAL_RUN_DIR"

_RUN_DIR_LOCK = threading.Lock()


def run_dir() -> str:
    """This process's temporary folder for :mod:`multiprocessing` (its fork server's socket, Dask's scratch space),
    made once per process: ``magcal-HOST-PID-XXXXXXXX`` (:data:`RUN_DIR_NAME`) in the temporary folder.

    :mod:`multiprocessing` would make ``pymp-XXXXXXXX`` there and remove it at this process's exit, which a process
    killed outright never reaches. This folder is removed at a normal exit too; after a kill, by the fork server
    as it ends (the folder is named to it in :data:`RUN_DIR_ENV` while it starts: :func:`fork_server_environment`)
    or, where that was killed too, by the next run (:func:`remove_stale_run_dirs`). A process whose
    :mod:`multiprocessing` already has a folder (made before magcal was asked) keeps it.
    """
    import multiprocessing.process
    import multiprocessing.util

    with _RUN_DIR_LOCK:
        config = multiprocessing.process.current_process()._config  # type: ignore[attr-defined]
        folder = config.get("tempdir")
        if folder is None:
            folder = tempfile.mkdtemp(prefix=f"magcal-{host_tag()}-{os.getpid()}-", dir=_run_dir_base())
            # as multiprocessing does for its own: removed after every other finaliser at exit
            multiprocessing.util.Finalize(
                None, shutil.rmtree, args=(folder,), kwargs={"ignore_errors": True}, exitpriority=-100
            )
            config["tempdir"] = folder
        return folder


def _run_dir_bases() -> list[str]:
    """Where run folders are made: the temporary folder, and ``/tmp`` where that is too deep for a socket."""
    base = tempfile.gettempdir()
    deepest = len(os.path.join(base, f"magcal-{host_tag()}-{os.getpid()}-XXXXXXXX"))
    if deepest > RUN_DIR_MAX_PATH and os.path.isdir("/tmp") and os.path.realpath(base) != "/tmp":
        return ["/tmp", base]
    return [base]


def _run_dir_base() -> str:
    return _run_dir_bases()[0]


def fork_server_environment() -> dict[str, str]:
    """The environment variables a fork server started now needs so that it removes :func:`run_dir` as it ends
    (:data:`RUN_DIR_ENV`); the fork server must preload this module."""
    return {RUN_DIR_ENV: run_dir()}


def remove_stale_run_dirs() -> list[Leftover]:
    """Remove the run folders (:func:`run_dir`) of processes that no longer run on this machine, in the temporary
    folder (and ``/tmp``, where run folders go when that is too deep); returns what was removed
    (:func:`remove_stale`)."""
    out = []
    for base in _run_dir_bases():
        out += remove_stale(base, RUN_DIR_NAME, host=host_tag())
    return out


def _removed_by_the_fork_server() -> None:
    """In a fork server started with :data:`RUN_DIR_ENV` (it imports this module as it starts): remove that run
    folder as the server ends, which it does once the process that started it and all its workers have ended, a
    killed one too. Only a fork server (``python -c`` running :mod:`multiprocessing.forkserver`) takes the
    variable: another program started meanwhile and importing magcal leaves it."""
    folder = os.environ.get(RUN_DIR_ENV)
    if not folder or sys.argv[:1] != ["-c"] or "multiprocessing.forkserver" not in sys.modules:
        return
    os.environ.pop(RUN_DIR_ENV, None)  # the workers forked from here do not take it on
    if RUN_DIR_NAME.fullmatch(os.path.basename(folder)):
        atexit.register(shutil.rmtree, folder, True)


_removed_by_the_fork_server()
