"""Which effects files the page may load: those named on the command line, or confirmed in the terminal.

An effects file is Python code that runs with the user's rights (:func:`magcal.model.plugins.load_effects_file`).
Whoever holds the page -- the user, or anyone who got its token -- could otherwise type any path of this machine
into the Model tab, or send a session whose effects list names one. So the page loads a file only when the user
said so where the page cannot reach: on the command line (``--effects-file PATH``), or by typing ``yes`` in the
terminal the workbench runs in, which asks (:class:`Terminal`; :data:`CONFIRM_TIMEOUT_S` to answer). Without a
terminal (started from a script, in the background), every other file is refused with a message that says how to
name it. :class:`EffectsFiles` holds the list.

The consent is bound to what runs: the file is read once (:func:`magcal.model.plugins.read_effects_file`: its
links resolved once, then opened without following any), and the bytes read are what is checked, shown by their
digest and run -- a symbolic link moved between the check and the run changes nothing. A file confirmed in the
terminal is confirmed with its content: new content at that path is asked again. A file of the command line is
the user's own, named there by path: it loads again after an edit without a question. The question names the
file escaped, every character outside printable ASCII written as its code and marked with the letter it looks like
(:func:`lookalikes`: a Cyrillic ``о`` in ``gооd.py``). One question is asked per file and content: a session that
names one file many ways asks once (:meth:`EffectsFiles.permit_all`), an answer other than yes ends its questions,
and a file answered no is not asked again while the workbench runs. While a question waits, the page says so in its
status line."""

from __future__ import annotations

import math
import os
import select
import stat
import sys
import threading
import time
import unicodedata
from collections.abc import Callable, Iterable

from magcal.core.errors import MagcalError
from magcal.model.plugins import EffectsSource, read_effects_file

from .markup import safe_code, safe_text

#: How long the terminal waits for the user's answer, s.
CONFIRM_TIMEOUT_S = 60.0

#: Answers that confirm (anything else, or none, refuses).
YES = ("y", "yes")

#: Longest look-alike note the page shows, characters.
MARK_CHARS = 600


#: What a Cyrillic or Greek letter that has no decomposition looks like in Latin script (by its Unicode name's
#: last word); letters that decompose (accented, full-width) are found by their compatibility decomposition.
_LOOKS_LIKE = {
    "A": "a", "O": "o", "IE": "e", "ES": "c", "ER": "p", "HA": "x", "U": "y", "I": "i", "JE": "j", "DZE": "s",
    "TE": "t", "EM": "m", "KA": "k", "VE": "b", "EN": "h", "EL": "n", "SHHA": "h", "KOMI DE": "d",
    "BYELORUSSIAN-UKRAINIAN I": "i", "ALPHA": "a", "OMICRON": "o", "RHO": "p", "NU": "v", "IOTA": "i",
    "KAPPA": "k", "TAU": "t", "UPSILON": "u", "CHI": "x", "EPSILON": "e", "BETA": "b", "ETA": "h", "ZETA": "z",
    "MU": "m", "GAMMA": "y",
}  # fmt: skip


def _looks_like(char: str) -> str | None:
    """The ASCII letter or sign ``char`` (not ASCII) may be taken for, or None."""
    plain = unicodedata.normalize("NFKD", char).encode("ascii", "ignore").decode("ascii")
    if len(plain) == 1 and plain.isprintable():
        return plain
    name = unicodedata.name(char, "")
    for script in ("CYRILLIC", "GREEK"):
        for case in ("SMALL", "CAPITAL"):
            head = f"{script} {case} LETTER "
            if name.startswith(head) and name[len(head) :] in _LOOKS_LIKE:
                latin = _LOOKS_LIKE[name[len(head) :]]
                return latin.upper() if case == "CAPITAL" else latin
    return None


def lookalikes(text: str) -> list[str]:
    """Every character of ``text`` outside ASCII, described: its escape, code point, Unicode name and the ASCII
    character it looks like when it looks like one (``\\u043e U+043E CYRILLIC SMALL LETTER O, looks like 'o'``),
    in order, each once."""
    out = []
    for char in dict.fromkeys(c for c in text if ord(c) > 127):
        like = _looks_like(char)
        name = unicodedata.name(char, "unnamed")
        out.append(f"{ascii(char)[1:-1]} U+{ord(char):04X} {name}" + (f", looks like {like!r}" if like else ""))
    return out


def shown_name(text: str) -> str:
    """``text`` (a path or a file name) as a question or a message shows it: as it is when it holds printable ASCII
    only, else quoted in ASCII, every control character and every character outside ASCII written as its escape
    (a terminal's escape sequence cannot act, a Cyrillic ``о`` shows as ``\\u043e``)."""
    plain = text.isascii() and text.isprintable()
    return text if plain else ascii(text)


def lookalike_note(text: str) -> str:
    """One line that marks the characters of ``text`` outside ASCII (:func:`lookalikes`), or ``""`` when it has
    none."""
    found = lookalikes(text)
    if not found:
        return ""
    return "CAUTION: the name holds characters outside ASCII, which may look like others: " + "; ".join(found)


class NotConfirmed(MagcalError):
    """The user did not confirm an effects file in the terminal (answered no, or not in time), or there is none."""


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
        The files of the command line (``--effects-file``): allowed by path, whatever they hold.
    terminal : Terminal or None
        Where a file not named is confirmed (None: nowhere, such a file is refused).
    timeout_s : float
        How long the terminal waits for an answer, s.
    """

    def __init__(self, named=(), terminal: Terminal | None = None, timeout_s: float = CONFIRM_TIMEOUT_S):
        self._named = {os.path.realpath(full_path(p)) for p in named}
        self._confirmed: set[tuple[str, str]] = set()  # (file read, SHA-256 of its content) the user said yes to
        self._refused: set[tuple[str, str]] = set()  # ... and those the user said no to: never asked again
        self._unanswered: dict[tuple[str, str], float] = {}  # ... -> when its question ended without an answer
        self.terminal = terminal
        self.timeout_s = timeout_s
        self._lock = threading.Lock()  # one question at a time
        self._cancel = threading.Event()

    def allowed(self, path) -> bool:
        """Whether ``path`` was named on the command line, or confirmed with some content (symbolic links
        followed); :meth:`permit` checks the content."""
        real = os.path.realpath(full_path(path))
        return real in self._named or any(real == r for r, _ in self._confirmed)

    def refusal(self, path) -> str | None:
        """Why the page may not load ``path``: it is no regular file (missing, a folder, a pipe that would block
        the reader), or it was not named and there is no terminal to ask. None when it was named or a terminal
        will be asked."""
        full = full_path(path)
        name = shown_name(os.path.basename(full))
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
            f"PATH/{os.path.basename(full)} to load this file"
        )

    def permit(self, path, say: Callable[[str], None] | None = None, status=None) -> EffectsSource:
        """The file ``path`` read once (:func:`magcal.model.plugins.read_effects_file`), if the page may load what
        was read; asks the terminal (waiting for the answer) when it was not named and this content was not
        confirmed. ``say(markdown)`` tells the page it waits, ``status(text)`` puts it in the page's status line.

        Raises
        ------
        MagcalError
            The file is no regular file (:meth:`refusal`) or cannot be read; :class:`NotConfirmed`: it was not
            named and this content is not confirmed (no terminal, the answer was not yes, or none came).
        """
        full = full_path(path)
        why = self.refusal(full)
        if why is not None:
            raise MagcalError(why)
        return self._consent(read_effects_file(full), say, status, time.monotonic())

    def permit_all(self, paths: Iterable[str], say=None, status=None) -> dict[str, EffectsSource | MagcalError]:
        """:meth:`permit` for each of ``paths`` (a session's effects files), one question per file and content:
        paths that name one file (``a.py``, ``./a.py``, a link to it) are read and asked about once, and give the
        same :class:`~magcal.model.plugins.EffectsSource`; after an answer other than yes, no further file is
        asked about (each is refused, said).

        Returns
        -------
        dict
            path -> what it may load, or the :class:`MagcalError` that says why not.
        """
        since = time.monotonic()
        out: dict[str, EffectsSource | MagcalError] = {}
        seen: dict[tuple[str, str], EffectsSource | MagcalError] = {}
        stopped: NotConfirmed | None = None
        for path in paths:
            try:
                full = full_path(path)
                why = self.refusal(full)
                if why is not None:
                    raise MagcalError(why)
                source = read_effects_file(full)
            except MagcalError as exc:
                out[path] = exc
                continue
            key = (source.real, source.sha256)
            if key not in seen:
                if stopped is not None and not self._allows(key):
                    seen[key] = NotConfirmed(
                        f"{shown_name(os.path.basename(full))} not asked: an earlier file of this session was not "
                        "confirmed in the terminal, so its other files are not asked about either. Load each from the "
                        "Model tab, or start the workbench with --effects-file PATH"
                    )
                else:
                    try:
                        seen[key] = self._consent(source, say, status, since)
                    except NotConfirmed as exc:
                        seen[key] = stopped = exc
            out[path] = seen[key]
        return out

    def _allows(self, key: tuple[str, str]) -> bool:
        return key[0] in self._named or key in self._confirmed

    def _consent(self, source: EffectsSource, say, status, since: float) -> EffectsSource:
        """``source`` if it was named or its content confirmed; else the terminal's answer, asked once per file and
        content: a request that waited while the same question went unanswered, or for a file answered no, is
        refused without asking."""
        key = (source.real, source.sha256)
        if self._allows(key):
            return source
        name = os.path.basename(source.path)
        if self.terminal is None:  # the file read is not the one named (a link moved): no terminal to ask
            raise NotConfirmed(
                f"{shown_name(name)} not loaded: the file read is not one the workbench was started with, and this "
                "workbench has no terminal to ask. Start it with --effects-file PATH"
            )
        with self._lock:
            if self._allows(key):  # confirmed while this one waited
                return source
            if key in self._refused:
                said = "you answered no before: it is not asked again while the workbench runs"
            elif self._unanswered.get(key, -math.inf) >= since:  # asked while this one waited: nobody answered
                said = "no answer came"
            else:
                answer = self._ask(source, say, status)
                if answer in YES:
                    self._confirmed.add(key)
                    return source
                if answer is None:
                    self._unanswered[key] = time.monotonic()
                else:
                    self._refused.add(key)
                said = "no answer came" if answer is None else "the answer was not yes"
        raise NotConfirmed(
            f"{shown_name(name)} not loaded: it was not confirmed in the workbench's terminal ({said}). Start the "
            "workbench with --effects-file PATH, or answer yes in its terminal"
        )

    def _ask(self, source: EffectsSource, say, status) -> str | None:
        """Ask the terminal about ``source`` (its name escaped and marked, its digest), telling the page."""
        assert self.terminal is not None
        name = os.path.basename(source.path)
        mark = lookalike_note(source.path if source.real == source.path else f"{source.path} {source.real}")
        changed = any(source.real == r for r, _ in self._confirmed | self._refused)
        if say is not None:
            say(
                f"The terminal where the workbench runs asks whether to load {safe_code(shown_name(name))} (it runs "
                f"its Python code): type yes there within {self.timeout_s:g} s."
                + (f"  \n**{safe_text(mark, MARK_CHARS)}**" if mark else "")
            )
        if status is not None:
            status(f"waiting for your answer in the workbench's terminal: load {shown_name(name)}?")
        where = "" if source.real == source.path else f"\n  (the file read: {shown_name(source.real)})"
        question = (
            f"\nmagcal-workbench: the page asks to load the effects file {shown_name(source.path)}{where}"
            + (f"\n  {mark}" if mark else "")
            + ("\n  Its content CHANGED since you last answered about it." if changed else "")
            + f"\n  content SHA-256 {source.sha256}, {len(source.code)} bytes"
            + "\n  Loading it runs its Python code with your rights. Load it? Type yes and Enter within "
            + f"{self.timeout_s:g} s: "
        )
        answer = self.terminal.ask(question, self.timeout_s, self._cancel)
        if status is not None:
            status(f"{shown_name(name)}: " + ("confirmed, loading" if answer in YES else "not confirmed"))
        return answer

    def close(self) -> None:
        """End a question that waits (the workbench stops)."""
        self._cancel.set()
