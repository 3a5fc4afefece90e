"""The Outliers tab, a panel of the panel recipe (:mod:`magcal_workbench.panelkit`): the box selection's mode, the
threshold rejection, Refit after each change, Undo, Redo, Reset, and the inspected sample, with the handlers of its
buttons beside them.

:class:`OutliersTab` is built at its place by :class:`~magcal_workbench.panels.Panels` (``build(panels, gui)``),
refreshed with the other tabs, and offers ``do_threshold``, ``do_undo``, ``do_redo`` and ``do_reset`` to the page's
widgets like every part's :func:`~magcal_workbench.actions.action`. A change of the selection goes through the
steps' :meth:`~magcal_workbench.steps.Steps.changing_selection` (the refit that follows it); the box selection and
the click in the scene are the scene control's (:mod:`magcal_workbench.view`).
"""

from __future__ import annotations

from .actions import action
from .events import Change
from .panels import inspect_markdown


class OutliersTab:
    """The Outliers tab's widgets, their handlers and their refresh.

    Parameters
    ----------
    ctrl, steps : callable
        ``ctrl()``: the open data's :class:`~magcal_workbench.controller.Controller`; ``steps()``: the
        :class:`~magcal_workbench.steps.Steps` (the refit that follows a change of the selection).
    """

    #: The tab it fills.
    tab = "Outliers"

    def __init__(self, *, ctrl, steps):
        self._ctrl, self._steps = ctrl, steps
        self.values = None

    def attach(self, panels) -> None:
        """Follow the open data (built already at its place, else into its tab now)."""
        if self.values is None:
            with panels.tab(self.tab):
                self.build(panels, panels.gui)
        self.refresh(("all",))

    def build(self, panels, gui) -> None:
        """Make the widgets (in the tab being built)."""
        self.values = panels.values
        on, w = panels.on, panels.w
        gui.add_markdown(
            "**Shift-drag** a box in the scene to reject (or restore) the samples inside it; "
            "**click** a point to inspect its sample. Rejected points turn magenta."
        )
        self.box_mode = w.dropdown("Box selection", ("reject", "restore"), initial_value="reject")
        self.k_sigma = w.slider("Threshold k (x sigma)", min=2.0, max=10.0, step=0.5, initial_value=4.0)
        self.btn_threshold = panels.button("Reject beyond k sigma", on.do_threshold)
        self.auto_refit = gui.add_checkbox(
            "Refit after each change", True, hint="Refit (ML) on the kept samples after every rejection"
        )
        with gui.add_folder("History", expand_by_default=True):
            self.btn_undo = panels.button("Undo", on.do_undo)
            self.btn_redo = panels.button("Redo", on.do_redo)
            self.btn_reset = panels.button("Reset (keep all)", on.do_reset)
        self.inspect = gui.add_markdown(inspect_markdown(None))
        panels.tab_panels.append(self)

    # --- page actions --------------------------------------------------------------------------------------
    @action
    def do_threshold(self, event):
        """Reject the kept samples whose residual is beyond k robust standard deviations."""
        with self._steps().changing_selection():
            self._ctrl().reject_threshold(float(self.values.check(self.k_sigma)))

    @action
    def do_undo(self, event):
        with self._steps().changing_selection():
            self._ctrl().undo()

    @action
    def do_redo(self, event):
        with self._steps().changing_selection():
            self._ctrl().redo()

    @action
    def do_reset(self, event):
        """Keep every sample again."""
        with self._steps().changing_selection():
            self._ctrl().reset_selection()

    # --- following the data --------------------------------------------------------------------------------
    def refresh(self, kinds) -> None:
        """The inspected sample (``Change.INSPECT``, ``Change.SELECTION``) and the selection's history."""
        if self.values is None:
            return
        ctrl = self._ctrl()
        if "all" in kinds or Change.INSPECT in kinds or Change.SELECTION in kinds:
            info = ctrl.sample_info(ctrl.inspected) if ctrl.inspected is not None else None
            self.inspect.content = inspect_markdown(info)
        self.btn_undo.disabled = not ctrl.state.selection.can_undo
        self.btn_redo.disabled = not ctrl.state.selection.can_redo
