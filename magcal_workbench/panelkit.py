"""The workbench's added panels: a section of controls in a tab, written in one file.

A panel is a class whose instance has

* ``attach(panels)``: makes its widgets, each inside a section of a tab (``with panels.section("Files",
  "My panel"): ...``), its buttons with :meth:`Panels.button(label, panels.on.NAME)
  <magcal_workbench.panels.Panels.button>` and its inputs through ``panels.w`` (their values checked);
* its handlers, methods marked :func:`@action <magcal_workbench.actions.action>`, which the widgets call by name
  (``panels.on.NAME``; a name another part already offers stops the workbench at start);
* optionally ``changed(kind)``: the controller's events (:class:`magcal_workbench.events.Change`), on the page's
  thread, to follow the data, the fit and the selection.

A built-in tab made as a panel (:class:`~magcal_workbench.calibratetab.CalibrateTab`,
:class:`~magcal_workbench.modeltab.ModelTab`, :class:`~magcal_workbench.qualitytab.QualityTab`,
:class:`~magcal_workbench.outlierstab.OutliersTab`, :class:`~magcal_workbench.viewtab.ViewTab`,
:class:`~magcal_workbench.filestab.FilesTab`, :class:`~magcal_workbench.lessonstab.LessonsTab`) fills its own tab
instead: ``build(panels, gui)``, called by :class:`~magcal_workbench.panels.Panels` at the tab's place (or, when the
panels were not handed it, by its ``attach`` inside ``with panels.tab("Quality"): ...``); it joins
``panels.tab_panels`` and is refreshed with the other tabs (``refresh(kinds)``, :meth:`Panels.refresh
<magcal_workbench.panels.Panels.refresh>`); its widgets stay reachable as the panels' attributes
(``panels.btn_run``).

It is made by its :class:`PanelKind`'s ``make(context)`` from a :class:`PanelContext` (what a panel is handed: the
open data's controller, the steps, the server; never the whole workbench) and registered in :data:`PANELS`, the
one list of them: magcal's own (the built-in tabs made as panels, then the gravity model's page) below, another
package's through the entry-point group ``magcal_workbench.panels`` (loaded when the workbench starts), or a module that calls :func:`register_panel`
before a :class:`~magcal_workbench.app.Workbench` is made. Each panel is built in the order registered, after the
built-in tabs; the physics stays in the engine (a panel calls the controller, which calls it).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from magcal.core.registry import Registry

from .calibratetab import CalibrateTab
from .compensationpanel import CompensationPage
from .filestab import FilesTab
from .gravitypage import GravityPage
from .lessonstab import LessonsTab
from .modeltab import ModelTab
from .outlierstab import OutliersTab
from .qualitytab import QualityTab
from .viewtab import ViewTab


@dataclass(frozen=True)
class PanelContext:
    """What a panel is handed (a narrow interface, not the workbench).

    Parameters
    ----------
    ctrl : callable
        ``ctrl()``: the open data's :class:`~magcal_workbench.controller.Controller` (another one when other data
        open: call it each time).
    steps : callable
        ``steps()``: the :class:`~magcal_workbench.steps.Steps` (``check_readings``, ``maybe_refit``).
    server : viser.ViserServer
        The server (its scene, for a panel that draws in 3-D).
    ui : magcal_workbench.uiqueue.UiQueue or None
        The page's thread (a job's result shown through ``ui.post``).
    load : callable or None
        ``load(dataset, content, name, resume=True, lesson=None)``: opens other data
        (:meth:`magcal_workbench.app.Workbench.load`).
    say_after_load : callable or None
        ``say_after_load(text)``: says what was opened, keeping what opening it had to say.
    panel : callable or None
        ``panel(name)``: another panel of :data:`PANELS`, made (the Lessons tab judges a gravity lesson on the
        gravity page's model).
    """

    ctrl: Callable[[], Any]
    steps: Callable[[], Any]
    server: Any
    ui: Any = None
    load: Callable[..., Any] | None = None
    say_after_load: Callable[[str], Any] | None = None
    panel: Callable[[str], Any] | None = None


@dataclass(frozen=True)
class PanelKind:
    """A panel the workbench builds.

    Parameters
    ----------
    name : str
        Its name (lower-case letters, digits, ``_`` or ``-``).
    description : str
        One line: what it shows and does.
    make : callable
        ``make(context: PanelContext)``: the panel (``attach(panels)``, its ``@action`` handlers, optionally
        ``changed(kind)``).
    """

    name: str
    description: str
    make: Callable[[PanelContext], Any]


#: Every panel the workbench builds, in order: magcal's own, then those registered by a module or an installed
#: package (entry-point group ``magcal_workbench.panels``).
PANELS: Registry[PanelKind] = Registry("workbench panel", "magcal_workbench.panels", PanelKind)


def register_panel(kind: PanelKind, replace: bool = False) -> PanelKind:
    """Add ``kind`` to :data:`PANELS` (returns it); a name already registered is refused unless ``replace``."""
    return PANELS.register(kind, replace=replace, depth=2)


PANELS.register(
    PanelKind(
        name="calibrate",
        description="the Calibrate tab: Run, |B| against time, the error histogram, the settings, the seed's steps",
        make=lambda c: CalibrateTab(ctrl=c.ctrl, steps=c.steps),
    ),
    origin="built-in",
)
PANELS.register(
    PanelKind(
        name="model",
        description="the Model tab: the effects, Diagnose and Add on the active model session, RMS per step, evidence",
        make=lambda c: ModelTab(ctrl=c.ctrl, steps=c.steps),
    ),
    origin="built-in",
)
PANELS.register(
    PanelKind(
        name="quality",
        description="the Quality tab: the data's quality findings and the noise behind the floors",
        make=lambda c: QualityTab(ctrl=c.ctrl),
    ),
    origin="built-in",
)
PANELS.register(
    PanelKind(
        name="outliers",
        description="the Outliers tab: the box selection's mode, the threshold, undo, redo, reset, the inspected sample",
        make=lambda c: OutliersTab(ctrl=c.ctrl, steps=c.steps),
    ),
    origin="built-in",
)
PANELS.register(
    PanelKind(
        name="view",
        description="the View tab: the sensor shown, the scene's gains and clouds, the sphere surface, the time window",
        make=lambda c: ViewTab(ctrl=c.ctrl),
    ),
    origin="built-in",
)
PANELS.register(
    PanelKind(
        name="files",
        description="the Files tab: open a file, the downloads, the export, the saved sessions, the live source",
        make=lambda c: FilesTab(ctrl=c.ctrl),
    ),
    origin="built-in",
)
PANELS.register(
    PanelKind(
        name="lessons",
        description="the Lessons tab: open a lesson, check the model against its answer, show the answer",
        make=lambda c: LessonsTab(
            ctrl=c.ctrl,
            gravity=lambda: c.panel("gravity") if c.panel is not None else None,
            ui=c.ui,
            load=c.load,
            say_after_load=c.say_after_load,
        ),
    ),
    origin="built-in",
)
PANELS.register(
    PanelKind(
        name="gravity",
        description="the gravity model: a compass beside an accelerometer, its fit, plots and cloud",
        make=lambda c: GravityPage(ctrl=c.ctrl, steps=c.steps, server=c.server),
    ),
    origin="built-in",
)
PANELS.register(
    PanelKind(
        name="compensation",
        description=(
            "the compensation (a scalar beside a fluxgate, or a four-sensor cross on a platform): its fit, FOM "
            "table, figure and steps"
        ),
        make=lambda c: CompensationPage(ctrl=c.ctrl, steps=c.steps),
    ),
    origin="built-in",
)
