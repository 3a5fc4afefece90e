"""Values from the page, checked against what the server offers.

A browser may send any value for any widget (viser checks none). Every input widget is made through
:class:`Widgets`, which records, where the widget is made, what values it may send: a dropdown's choices (what the
server offers *now*: the session folder, the lessons, the diagnosis, the data), a slider's or number's range as
made, a text's length. :meth:`PageValues.check` refuses anything else before it is read or saved, and puts the
widget back to a valid value so every browser shows one. The widget's own ``options``, ``min`` or ``max`` are
never trusted: a client may change those too.
"""

from __future__ import annotations

import math
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

    def number(self, handle, lo: float | None, hi: float | None):
        """``handle`` (a slider or number) may send a finite number in ``lo ... hi`` (None: unbounded)."""
        self._rules[id(handle)] = ("number", (lo, hi))
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
        return rule if kind == "number" else (None, None)

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
            lo, hi = rule
            ok = (
                isinstance(value, (int, float))
                and not isinstance(value, bool)
                and math.isfinite(value)
                and (lo is None or value >= lo)
                and (hi is None or value <= hi)
            )
            if not ok:
                good = lo if lo is not None else 0.0
                if isinstance(value, (int, float)) and math.isfinite(value):
                    good = min(max(value, lo if lo is not None else value), hi if hi is not None else value)
                self.put_back(handle, good)
                span = f"{'-inf' if lo is None else f'{lo:g}'} ... {'inf' if hi is None else f'{hi:g}'}"
                raise MagcalError(f"{label}: {clean_text(repr(value), 40)} is outside {span}; refused")
        elif kind == "text":
            if not isinstance(value, str) or len(value) > rule:
                self.put_back(handle, "")
                raise MagcalError(f"{label}: a text of at most {rule} characters; refused")
        return value

    def put_back(self, handle, default) -> None:
        shown = self._shown.get(id(handle))
        if shown is not None:
            default = shown()
        try:
            handle.value = default
        except Exception:  # a widget that refuses even that: leave it, the value was refused anyway
            traceback.print_exc()


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
