"""Which effects files the page may load (issue 41): those named on the command line, or confirmed in the terminal.

An effects file is Python code that runs with the user's rights (:func:`magcal.model.plugins.load_effects_file`).
Whoever holds the page -- the user, or anyone who got its token -- could otherwise type any path of this machine
into the Model tab, or send a session whose effects list names one. So the page loads a file only when the user
said so where the page cannot reach: on the command line (``--effects-file PATH``), or by typing ``yes`` in the
terminal the workbench runs in, which asks (:class:`Terminal`; :data:`CONFIRM_TIMEOUT_S` to answer). A confirmed
file is remembered while the workbench runs. Without a terminal (started from a script, in the background), every
other file is refused with a message that says how to name it. :class:`EffectsFiles` holds the list.
"""

from __future__ import annotations

import os
import select
import stat
import sys
import threading
import time
from collections.abc import Callable

from magcal.core.errors import MagcalError

from .markup import safe_code

#: How long the terminal waits for the user's answer, s.
CONFIRM_TIMEOUT_S = 60.0

#: Answers that confirm (anything else, or none, refuses).
YES = ("y", "yes")


def _shown(path: str) -> str:
    """``path`` as the terminal shows it: quoted, control characters and other unprintable ones escaped (a file
    name may hold a terminal's escape sequences)."""
    return ascii(path) if not path.isprintable() else repr(path)


class Terminal:
    """The terminal the workbench runs in: asks the user a question the page cannot answer.

    Parameters
    ----------
    fd : int
        The terminal's file descriptor the answer is read from.
    out : text stream
        Where the question is written (the terminal).
    """

    def __init__(self, fd: int, out):
        self.fd = fd
        self.out = out

    @classmethod
    def of_stdin(cls) -> Terminal | None:
        """The standard input's terminal when the workbench runs in its foreground (questions then go to standard
        error), else None: no terminal (a pipe, a service), or a background job (which would be stopped when it
        reads)."""
        try:
            fd = sys.stdin.fileno()
            if not os.isatty(fd) or os.tcgetpgrp(fd) != os.getpgrp():
                return None
        except (AttributeError, OSError, ValueError):  # no stdin, or one that is not a file
            return None
        return cls(fd, sys.stderr)

    def ask(self, question: str, timeout_s: float, cancel: threading.Event) -> str | None:
        """Write ``question`` and return the line typed (stripped, lower case), or None when no line came within
        ``timeout_s`` seconds or ``cancel`` was set. What was typed before the question is discarded first."""
        try:
            import termios

            termios.tcflush(self.fd, termios.TCIFLUSH)  # a "yes" typed earlier does not answer this question
        except (ImportError, OSError):
            pass
        self.out.write(question)
        self.out.flush()
        got = b""
        end = time.monotonic() + timeout_s
        while not cancel.is_set():
            left = end - time.monotonic()
            if left <= 0:
                break
            ready, _, _ = select.select([self.fd], [], [], min(left, 0.25))
            if not ready:
                continue
            chunk = os.read(self.fd, 1024)
            if not chunk:  # the terminal closed
                break
            got += chunk
            if b"\n" in got or b"\r" in got:
                return got.splitlines()[0].decode("utf-8", "replace").strip().lower()
            if len(got) > 4096:
                break
        self.out.write("\n")
        self.out.flush()
        return None


def full_path(path) -> str:
    """The absolute path the page's text ``path`` names (``~`` expanded, relative to the current directory), as
    :meth:`magcal_workbench.controller.Controller.load_effects_file` loads it."""
    text = os.fspath(path).strip() if isinstance(path, (str, os.PathLike)) else ""
    if not text:
        raise MagcalError("type the path of a Python file (.py) that defines your effect")
    return os.path.abspath(os.path.expanduser(text))


class EffectsFiles:
    """The effects files the page may load: those named on the command line and those confirmed in the terminal.

    Parameters
    ----------
    named : sequence of str
        The files of the command line (``--effects-file``).
    terminal : Terminal or None
        Where a file not named is confirmed (None: nowhere, such a file is refused).
    timeout_s : float
        How long the terminal waits for an answer, s.
    """

    def __init__(self, named=(), terminal: Terminal | None = None, timeout_s: float = CONFIRM_TIMEOUT_S):
        self._allowed = {os.path.realpath(full_path(p)) for p in named}
        self.terminal = terminal
        self.timeout_s = timeout_s
        self._lock = threading.Lock()  # one question at a time
        self._cancel = threading.Event()

    def allowed(self, path) -> bool:
        """Whether ``path`` was named on the command line or confirmed (symbolic links followed)."""
        return os.path.realpath(full_path(path)) in self._allowed

    def refusal(self, path) -> str | None:
        """Why the page may not load ``path``: it is no regular file (missing, a folder, a pipe that would block
        the reader), or it was not named and there is no terminal to ask. None when it was named or a terminal
        will be asked."""
        full = full_path(path)
        name = os.path.basename(full)
        try:
            mode = os.stat(full).st_mode
        except OSError:
            return f"{name}: no such effects file; check the path"
        if not stat.S_ISREG(mode):
            return f"{name}: not a regular file; give the Python file (.py) that defines your effect"
        if self.allowed(full) or self.terminal is not None:
            return None
        return (
            f"{name} not loaded: the page loads only the effects files the workbench was started with, or that you "
            "confirm in its terminal, and this workbench has no terminal to ask. Start it with --effects-file "
            f"PATH/{name} to load this file"
        )

    def permit(self, path, say: Callable[[str], None] | None = None) -> str:
        """The full path of ``path`` if the page may load it; asks the terminal (waiting for the answer) when it
        was not named. ``say(markdown)`` tells the page it waits.

        Raises
        ------
        MagcalError
            The file is no regular file (:meth:`refusal`), or was not named and is not confirmed (no terminal, the
            answer was not yes, or none came).
        """
        full = full_path(path)
        why = self.refusal(full)
        if why is not None:
            raise MagcalError(why)
        key = os.path.realpath(full)
        name = os.path.basename(full)
        if key in self._allowed:
            return full
        assert self.terminal is not None  # refusal() said so
        if say is not None:
            say(
                f"The terminal where the workbench runs asks whether to load {safe_code(name)} (it runs its "
                f"Python code): type yes there within {self.timeout_s:g} s."
            )
        with self._lock:
            if key in self._allowed:  # confirmed while this one waited
                return full
            question = (
                f"\nmagcal-workbench: the page asks to load the effects file {_shown(full)}; loading it runs its "
                f"Python code with your rights. Load it? Type yes and Enter within {self.timeout_s:g} s: "
            )
            answer = self.terminal.ask(question, self.timeout_s, self._cancel)
            if answer in YES:
                self._allowed.add(key)
                return full
        said = "no answer came" if answer is None else "the answer was not yes"
        raise MagcalError(
            f"{name} not loaded: it was not confirmed in the workbench's terminal ({said}). Start the workbench "
            "with --effects-file PATH, or answer yes in its terminal"
        )

    def close(self) -> None:
        """End a question that waits (the workbench stops)."""
        self._cancel.set()
