"""A registry of named pieces: magcal's own, and those installed packages declare in an entry-point group.

The export formats (:mod:`magcal.output.formats`), the live sources (:mod:`magcal.data.live.registry`) and the
command line's commands (:mod:`magcal.cli.commands`) are each one :class:`Registry`: magcal registers its built-in
pieces when their module is imported, and :meth:`Registry.load_entry_points` adds those of installed packages
(``[project.entry-points."GROUP"] NAME = "my_pkg.module:OBJECT"``). An entry point names a piece (an instance of
the registry's kind, registered here) or a module that registers its pieces when imported. They are loaded once,
by the command line and the workbench where the pieces are listed, never at ``import magcal`` (the import stays
light and runs no third party's code unasked); a failing entry point is a note (a warning) and is skipped.

The effect catalogue keeps its own registry (:mod:`magcal.model.terms`, :mod:`magcal.model.plugins`): an effect
is a class checked by a dry run on a synthetic record, and may also come from a file given on the command line.
"""

from __future__ import annotations

import importlib.metadata
import inspect
import re
import threading
from collections.abc import Callable, Iterator, Mapping
from typing import Any, Generic, TypeVar

from magcal.core.errors import MagcalError
from magcal.core.notes import Note

T = TypeVar("T")


class Loaded(list):
    """The names an entry-point loader added (a ``list`` of str), with :attr:`notes`: what it has to say, a
    :class:`~magcal.core.notes.Note` (``UserWarning``) for each entry point skipped (it failed to import or to
    register) or for entry points that could not be listed. Returned by :meth:`Registry.load_entry_points` and
    :func:`magcal.model.plugins.load_entry_points`; the command line prints the notes, the workbench shows them.
    """

    def __init__(self, names=(), notes=()):
        super().__init__(names)
        #: What the loader has to say, in order (:class:`~magcal.core.notes.Note`).
        self.notes: list[Note] = list(notes)


#: What a piece's name may look like: it is typed on the command line (``--format NAME``, ``magcal NAME``).
NAME_PATTERN = re.compile(r"^[a-z][a-z0-9_-]{0,31}$")


class Registry(Mapping, Generic[T]):
    """Named pieces of one kind, in the order they were registered (a read-only mapping ``name -> piece``).

    Parameters
    ----------
    what : str
        What a piece is, for messages (``"export format"``).
    group : str
        The entry-point group installed packages declare theirs in (``"magcal.export_formats"``).
    kind : type
        The class every piece is an instance of.
    check : callable, optional
        ``check(piece, registry)``: more rules, raising :class:`MagcalError` with what to change.
    """

    def __init__(self, what: str, group: str, kind: type, check: Callable | None = None):
        self.what = what
        self.group = group
        self.kind = kind
        self._check = check
        self._items: dict[str, T] = {}
        #: name -> where it came from: ``"built-in"``, ``"entry point NAME = VALUE (dist)"`` or a module name.
        self._origins: dict[str, str] = {}
        self._lock = threading.RLock()
        self._loaded = False

    # -- the mapping ---------------------------------------------------------------------------------------------
    def __getitem__(self, name: str) -> T:
        return self._items[name]

    def __iter__(self) -> Iterator[str]:
        return iter(list(self._items))

    def __len__(self) -> int:
        return len(self._items)

    def lookup(self, name: str, option: str = "") -> T:
        """The piece called ``name``, or a :class:`MagcalError` naming the known ones (``option``: how the user
        gave the name, e.g. ``--format``)."""
        try:
            return self._items[name]
        except (KeyError, TypeError):
            given = f"{option} {name!r}" if option else f"{self.what} {name!r}"
            raise MagcalError(f"{given}: use one of {', '.join(self._items)}") from None

    def origin(self, name: str) -> str:
        """Where the piece ``name`` came from: ``"built-in"``, an entry point, or the module that registered it."""
        return self._origins.get(name, "")

    # -- registering -------------------------------------------------------------------------------------------
    def register(self, piece: T, replace: bool = False, origin: str | None = None, depth: int = 1) -> T:
        """Add ``piece`` under its ``name``; returns it (so that it can be used as ``X = REGISTRY.register(...)``).

        ``origin`` says where it came from; by default the module ``depth`` calls up from here (a module of magcal:
        ``"built-in"``); a function that registers for its caller passes ``depth=2``.

        Raises
        ------
        MagcalError
            A piece of another kind, a name the command line cannot take, or a name already registered by another
            piece (unless ``replace``).
        """
        if not isinstance(piece, self.kind):
            raise MagcalError(f"{piece!r} is not a {self.kind.__name__}; a {self.what} is one")
        name = getattr(piece, "name", None)
        if not isinstance(name, str) or not NAME_PATTERN.match(name):
            raise MagcalError(
                f"{self.what} name {name!r}: give lower-case letters, digits, '_' or '-', starting with a letter "
                "(at most 32 characters)"
            )
        with self._lock:
            current = self._items.get(name)
            if current is not None and current is not piece and not replace:
                raise MagcalError(
                    f"{self.what} {name!r} is already registered ({self.origin(name)}); choose another name"
                )
            if self._check is not None:
                self._check(piece, self)
            self._items[name] = piece
            if origin is None:
                module = _caller_module(depth)
                origin = "built-in" if module == "magcal" or module.startswith("magcal.") else module
            self._origins[name] = origin
        return piece

    def unregister(self, name: str) -> None:
        """Remove a piece that is not built in (a test's toy, a package's piece)."""
        with self._lock:
            if self._origins.get(name) == "built-in":
                raise MagcalError(f"{self.what} {name!r} is built in; only an added one can be removed")
            self._items.pop(name, None)
            self._origins.pop(name, None)

    # -- installed packages --------------------------------------------------------------------------------------
    def load_entry_points(self, force: bool = False) -> Loaded:
        """Add the pieces installed packages declare in :attr:`group` (once; later calls return ``[]`` unless
        ``force``).

        Each entry point names a piece (registered) or a module that registers its pieces when imported.

        Parameters
        ----------
        force : bool
            Load again even if already loaded.

        Returns
        -------
        Loaded
            The names added (a list of str), and in its ``notes`` a ``UserWarning`` note for each entry point
            skipped (never raised here).
        """
        with self._lock:
            if self._loaded and not force:
                return Loaded()
            self._loaded = True
            try:
                found = list(importlib.metadata.entry_points(group=self.group))
            except Exception as exc:  # a broken installation must not stop magcal
                text = f"could not list the {self.group!r} entry points ({exc}); none loaded"
                return Loaded((), [Note(text, UserWarning)])
            added = Loaded()
            for ep in found:
                text = entry_point_text(ep)
                before = dict(self._items)
                try:
                    obj: Any = ep.load()
                    if isinstance(obj, self.kind):
                        piece: Any = obj
                        if self._items.get(piece.name) is not piece:
                            self.register(piece, origin=f"entry point {text}")
                    elif not inspect.ismodule(obj):
                        raise MagcalError(f"it names {obj!r}, neither a {self.kind.__name__} nor a module")
                    new = [n for n in self._items if n not in before or self._items[n] is not before[n]]
                    if not new:
                        raise MagcalError(f"it registers no {self.what}")
                    for n in new:
                        self._origins[n] = f"entry point {text}"
                    added += new
                except Exception as exc:
                    for n in [n for n in self._items if n not in before]:
                        self._items.pop(n)
                        self._origins.pop(n, None)
                    self._items.update(before)
                    added.notes.append(
                        Note(f"skipped the {self.what} entry point {text}: {exc}", UserWarning, "plugins")
                    )
            return added


def entry_point_text(ep) -> str:
    """``NAME = VALUE (distribution)``: an entry point as a message names it."""
    dist = getattr(ep, "dist", None)
    dist_name = getattr(dist, "name", None)
    return f"{ep.name} = {ep.value}" + (f" ({dist_name})" if dist_name else "")


def _caller_module(depth: int) -> str:
    """The module of the function ``depth`` calls up from the caller of this function (1: the caller's caller)."""
    frame = inspect.currentframe()
    for _ in range(depth + 1):
        frame = frame.f_back if frame is not None else None
    return frame.f_globals.get("__name__", "") if frame is not None else ""
