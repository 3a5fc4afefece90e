"""A part of the page handed what it uses.

The workbench's parts (the steps, the scene control, the cockpit, the exports, the live control...) are not handed
the :class:`~magcal_workbench.app.Workbench`: each takes what it uses as arguments. The open data's
:class:`~magcal_workbench.controller.Controller` is replaced when other data are opened, and the
:class:`~magcal_workbench.panels.Panels` are made after the parts, so both come as getters; :class:`PagePart` reads
them when used.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any


class PagePart:
    """Base of a part handed the controller and the panels as getters (``self._ctrl``, ``self._panels``, set by
    the part's constructor): :attr:`ctrl` and :attr:`panels` are the ones of now."""

    _ctrl: Callable[[], Any]
    _panels: Callable[[], Any]

    @property
    def ctrl(self) -> Any:
        """The open data's :class:`~magcal_workbench.controller.Controller`."""
        return self._ctrl()

    @property
    def panels(self) -> Any:
        """The page's :class:`~magcal_workbench.panels.Panels`."""
        return self._panels()
