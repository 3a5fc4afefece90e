"""Values from the page, checked against what the server offers.

A browser may send any value for any widget (viser checks none). Every input widget is made through
:class:`Widgets`, which records, where the widget is made, what values it may send: a dropdown's choices (what the
server offers *now*: the session folder, the lessons, the diagnosis, the data), a slider's or number's range as
made, a text's length. :meth:`PageValues.check` refuses anything else before it is read or saved, and puts the
widget back to a valid value so every browser shows one. The widget's own ``options``, ``min`` or ``max`` are
never trusted: a client may change those too.

A value reaches the server twice: viser first casts it to the widget's type (``int(nan)`` raises in viser's event
loop, ``int(14551.5)`` is ``14551``, ``bool([1])`` is ``True``), then the callback reads it. So every value is
screened *before* viser sees it (:meth:`PageValues.screen`, through
:func:`magcal_workbench.viser_adapter.watch_updates`): a number must be finite, in range and, for a whole-number
widget, integral (:func:`number_problem`, the one check every number goes through); any other value must be of the
widget's type; a change of anything but a widget's value is refused. A refused update never reaches viser: the
page gets a message and the widget shows the server's value again.
"""

from __future__ import annotations

import math
import reprlib
import traceback
from collections.abc import Callable
from typing import Any

from magcal.core.errors import MagcalError

from . import viser_adapter
from .markup import clean_text

#: Longest text a text box may hold, characters (a path).
MAX_TEXT_CHARS = 4096


class PageValues:
    """What every input widget may send (registered where it is made), and the check of a value against it."""

    def __init__(self):
        self._rules: dict[int, tuple[str, Any]] = {}
        self._shown: dict[int, Callable[[], object]] = {}

    # --- registration -------------------------------------------------------------------------------------
    def choices(self, handle, allowed: Callable[[], tuple]):
        """``handle`` (a dropdown) may send one of ``allowed()`` (its first is the default)."""
        self._rules[id(handle)] = ("choice", allowed)
        return handle

    def number(self, handle, lo: float | None, hi: float | None, integral: bool | None = None):
        """``handle`` (a slider or number) may send a finite number in ``lo ... hi`` (None: unbounded), a whole one
        when ``integral`` (default: when the widget holds an ``int``, which viser casts every value to)."""
        if integral is None:
            integral = _is_int(handle.value)
        self._rules[id(handle)] = ("number", (lo, hi, integral))
        return handle

    def text(self, handle, max_chars: int = MAX_TEXT_CHARS):
        """``handle`` may send a text of at most ``max_chars`` characters."""
        self._rules[id(handle)] = ("text", max_chars)
        return handle

    def shown_by(self, handle, shown: Callable[[], object]) -> None:
        """A refused value of ``handle`` is put back to ``shown()`` (the session state's value)."""
        self._shown[id(handle)] = shown

    # --- checks -------------------------------------------------------------------------------------------
    def allowed(self, handle) -> tuple:
        """The values a dropdown may hold now."""
        kind, rule = self._rules.get(id(handle), ("", None))
        if kind != "choice":
            raise MagcalError(f"{clean_text(getattr(handle, 'label', 'value'), 60)}: not a choice the page offers")
        return tuple(rule())

    def range(self, handle) -> tuple[float | None, float | None]:
        """The range a slider or number was made with."""
        kind, rule = self._rules.get(id(handle), ("", None))
        return rule[:2] if kind == "number" else (None, None)

    def check(self, handle):
        """The value of ``handle`` if the page could have sent it, else a :class:`MagcalError` saying so (and the
        widget is put back to the state's value or the first choice).

        A widget made outside :class:`Widgets` that takes a choice, number or text is refused: the server did
        not say what it may send."""
        value = handle.value
        label = clean_text(getattr(handle, "label", "value"), 60)
        kind, rule = self._rules.get(id(handle), (None, None))
        made = viser_adapter.widget_kind(handle)
        if made is not None and kind != made:
            raise MagcalError(f"{label}: a widget the server did not register; refused")
        if kind == "choice":
            allowed = tuple(rule())
            if value not in allowed:
                self.put_back(handle, allowed[0])
                raise MagcalError(
                    f"{label}: {clean_text(repr(value), 60)} is not one of the choices offered; "
                    "refused (nothing was read or saved)"
                )
        elif kind == "number":
            lo, hi, integral = rule
            why = number_problem(value, lo, hi, integral)
            if why is not None:
                good = lo if lo is not None else 0.0
                if _is_number(value) and math.isfinite(value):
                    good = min(max(value, lo if lo is not None else value), hi if hi is not None else value)
                self.put_back(handle, round(good) if integral else good)
                raise MagcalError(f"{label}: {why}; refused")
        elif kind == "text":
            if not isinstance(value, str) or len(value) > rule:
                self.put_back(handle, "")
                raise MagcalError(f"{label}: a text of at most {rule} characters; refused")
        return value

    def screen(self, handle, updates: dict) -> str | None:
        """Why the page's raw ``updates`` of ``handle`` (``{property: value}``, before viser casts them) are
        refused, or None: only ``value`` may change; a number widget's value is checked as :meth:`check` checks it
        (:func:`number_problem`), a text's must be a text of its length, any other widget's must be of the type
        it holds (a checkbox a bool, a dropdown a text). A choice is checked against what the server offers when
        the callback reads it (:meth:`check`)."""
        label = clean_text(getattr(handle, "label", "value"), 60)
        others = sorted(str(k) for k in updates if k != "value")
        if others:
            return f"{label}: the page may change only a widget's value, not {clean_text(', '.join(others), 60)}"
        if "value" not in updates:
            return None
        value = updates["value"]
        kind, rule = self._rules.get(id(handle), ("", None))
        if kind == "number":
            why = number_problem(value, *rule)
        elif kind == "text":
            why = None if isinstance(value, str) and len(value) <= rule else f"a text of at most {rule} characters"
        else:
            why = type_problem(value, handle.value)
        return None if why is None else f"{label}: {why}"

    def put_back(self, handle, default) -> None:
        shown = self._shown.get(id(handle))
        if shown is not None:
            default = shown()
        try:
            handle.value = default
        except Exception:  # a widget that refuses even that: leave it, the value was refused anyway
            traceback.print_exc()


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _is_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _shown_value(value) -> str:
    return clean_text(reprlib.repr(value), 40)  # reprlib: a list of a million numbers is not written out first


def number_problem(value, lo: float | None = None, hi: float | None = None, integral: bool = False) -> str | None:
    """What is wrong with ``value`` as the number of a widget (a slider, a number box), or None: it must be an int
    or a float (not a bool, a text or a list), finite, in ``lo ... hi`` (None: unbounded) and, when ``integral``,
    a whole number. The one check of every number the page sends; the text says what to give.

    Examples
    --------
    >>> number_problem(14551.5, 1024, 65535, integral=True)
    '14551.5 is not a whole number; give 1024 ... 65535'
    >>> number_problem(float("nan"), 0, 1) is not None, number_problem(0.5, 0, 1)
    (True, None)
    """
    span = f"{'-inf' if lo is None else f'{lo:g}'} ... {'inf' if hi is None else f'{hi:g}'}"
    if not _is_number(value):
        return f"{_shown_value(value)} is not a number; give a number in {span}"
    if not math.isfinite(value):
        return f"{_shown_value(value)} is not a finite number; give a number in {span}"
    if integral and value != int(value):
        return f"{_shown_value(value)} is not a whole number; give {span}"
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        return f"{_shown_value(value)} is outside {span}"
    return None


def type_problem(value, current) -> str | None:
    """What is wrong with ``value`` as the new value of a widget that holds ``current``, or None: the same type (a
    number for a number, finite)."""
    if _is_number(current):
        return number_problem(value, integral=_is_int(current))
    if isinstance(current, (bool, str)) and type(value) is not type(current):
        return f"{_shown_value(value)} is not a {'bool' if isinstance(current, bool) else 'text'}"
    if isinstance(current, tuple):
        if not isinstance(value, (list, tuple)) or len(value) != len(current):
            return f"{_shown_value(value)} is not a list of {len(current)}"
        return next((type_problem(v, c) for v, c in zip(value, current) if type_problem(v, c)), None)
    return None


class Widgets:
    """Makes the input widgets on ``gui`` and registers, there and then, what each may send (:class:`PageValues`).

    Widgets that send no free value (buttons, checkboxes, uploads) are made on ``gui`` directly."""

    def __init__(self, gui, values: PageValues):
        self.gui = gui
        self.values = values

    def dropdown(self, label: str, options, allowed: Callable[[], tuple] | None = None, **kw):
        """A dropdown; ``allowed()`` (default: the options it is made with) is what it may send."""
        options = tuple(options)
        handle = self.gui.add_dropdown(label, options, **kw)
        return self.values.choices(handle, allowed or (lambda: options))

    def slider(self, label: str, min: float, max: float, **kw):
        return self.values.number(self.gui.add_slider(label, min=min, max=max, **kw), min, max)

    def number(self, label: str, initial_value, min: float | None = None, max: float | None = None, **kw):
        return self.values.number(self.gui.add_number(label, initial_value, min=min, max=max, **kw), min, max)

    def text(self, label: str, initial_value: str, max_chars: int = MAX_TEXT_CHARS, **kw):
        return self.values.text(self.gui.add_text(label, initial_value, **kw), max_chars)
