"""What the page's widgets call, registered where each handler is written.

A part of the workbench (:class:`~magcal_workbench.steps.Steps`, :class:`~magcal_workbench.uploads.Uploads`, a
panel of :mod:`magcal_workbench.panelkit` ...) marks each method a widget calls with :func:`action`; the workbench
gathers the marked methods of its parts into one :class:`Actions` (the panels' ``on``), by name. Grep ``@action``
to find every handler, and ``on.NAME`` to find the widget that calls it; two parts offering one name is an error
when the workbench starts (:class:`DuplicateAction`), a name nobody offers an error where a widget asks for it.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any, TypeVar

F = TypeVar("F", bound=Callable[..., Any])

#: The attribute :func:`action` sets on a handler: the name it is registered under.
MARK = "_workbench_action"


def action(func: F | None = None, *, name: str | None = None) -> Any:
    """Mark a method as a handler the page's widgets may call (``on.NAME``).

    Parameters
    ----------
    func : callable
        The method (``@action``).
    name : str, optional
        The name it is registered under (``@action(name="draw_cockpit")``); default: the method's name.
    """

    def mark(f: F) -> F:
        setattr(f, MARK, name or f.__name__)
        return f

    return mark(func) if func is not None else mark


def handlers_of(part: object) -> dict[str, Callable[..., Any]]:
    """The handlers ``part``'s class (and its bases) marked with :func:`action`, by name, bound to ``part``."""
    out: dict[str, Callable[..., Any]] = {}
    for cls in reversed(type(part).__mro__):
        for attr, value in vars(cls).items():
            name = getattr(value, MARK, None)
            if isinstance(name, str):
                out[name] = getattr(part, attr)
    return out


class DuplicateAction(RuntimeError):
    """Two parts of the workbench offer a handler of the same name: which one a widget would call is unclear."""


class Actions:
    """Every handler of the workbench's parts, by name: ``on.do_refine(event)``.

    Parameters
    ----------
    parts : iterable of object
        The parts whose :func:`action` handlers are gathered.

    Raises
    ------
    DuplicateAction
        Two parts offer the same name (the message names both).
    """

    _by_name: dict[str, Callable[..., Any]]
    _owner: dict[str, str]

    def __init__(self, parts: Iterable[object]):
        by_name: dict[str, Callable[..., Any]] = {}
        owner: dict[str, str] = {}
        for part in parts:
            part_name = type(part).__name__
            for name, func in handlers_of(part).items():
                if name in by_name:
                    raise DuplicateAction(
                        f"two handlers named {name!r}: {owner[name]}.{name} and {part_name}.{name}; rename one "
                        "(a widget calls its handler by name, on.NAME)"
                    )
                by_name[name], owner[name] = func, part_name
        self.__dict__["_by_name"] = by_name
        self.__dict__["_owner"] = owner

    def __getattr__(self, name: str) -> Callable[..., Any]:
        try:
            return self.__dict__["_by_name"][name]
        except KeyError:
            raise AttributeError(
                f"no workbench handler {name!r}: mark the method the widget calls with @action "
                "(magcal_workbench.actions) in a part the workbench gathers"
            ) from None

    def __setattr__(self, name: str, value: object) -> None:
        raise AttributeError("the handlers are registered with @action, not set")

    def names(self) -> frozenset[str]:
        """Every registered handler's name."""
        return frozenset(self._by_name)

    def owner(self, name: str) -> str:
        """The class name of the part that offers ``name``."""
        return self._owner[name]
