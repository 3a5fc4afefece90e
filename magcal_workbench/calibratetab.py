"""The Calibrate tab, a panel of the panel recipe (:mod:`magcal_workbench.panelkit`): Run, the plots (|B| against time
with its region editor, the error histogram), the settings, the seed's steps one by one, and the long texts folded
away (data, per-sensor figures, step history), with the handlers of its engine buttons beside them.

:class:`CalibrateTab` is built at its place by :class:`~magcal_workbench.panels.Panels` (``build(panels, gui)``),
refreshed with the other tabs, and offers ``do_calibrate``, ``do_ellipsoid``, ``do_align`` and ``do_refine`` to the
page's widgets like every part's :func:`~magcal_workbench.actions.action`. The plots' own handlers are the
cockpit's (:mod:`magcal_workbench.cockpit`); the fits are the controller's total-field model session
(:class:`~magcal_workbench.totalfield.TotalFieldSession`).
"""

from __future__ import annotations

from .actions import action
from .events import Change
from .looptext import HELD_OUT_NOTE, loop_text
from .markup import safe_text
from .panels import METHOD_LABELS, data_markdown, reference_markdown, sensors_markdown
from .plots import add_figure
from .state import METHODS


class CalibrateTab:
    """The Calibrate tab's widgets, their handlers and their refresh.

    Parameters
    ----------
    ctrl, steps : callable
        ``ctrl()``: the open data's :class:`~magcal_workbench.controller.Controller`; ``steps()``: the
        :class:`~magcal_workbench.steps.Steps` (their check of the readings).
    """

    #: The tab it fills.
    tab = "Calibrate"

    def __init__(self, *, ctrl, steps):
        self._ctrl, self._steps = ctrl, steps

    # --- construction --------------------------------------------------------------------------------------
    def attach(self, panels) -> None:
        """Follow the open data (built already at its place, else into its tab now)."""
        if not hasattr(self, "btn_run"):
            with panels.tab(self.tab):
                self.build(panels, panels.gui)
        self.refresh(("all",))

    def build(self, panels, gui) -> None:
        """Make the widgets (in the tab being built)."""
        import plotly.graph_objects as go

        on, w = panels.on, panels.w
        state = lambda: self._ctrl().state
        configure = lambda **kw: self._ctrl().configure(**kw)
        #: One line naming the fit mode in use and why, on a record whose mode is a compensation (else hidden).
        self.mode_note = gui.add_markdown("", visible=False)
        self.btn_run = panels.button("Run the chosen method", on.do_calibrate, engine=True, color="blue")
        self.field_folder = gui.add_folder("|B| against time", expand_by_default=True)
        with self.field_folder:
            # viser's client draws plotly at height = width * aspect
            self.field_plot = add_figure(gui, go.Figure(), aspect=0.85)
            self.range_from = w.slider(
                "From % of the record",
                min=0.0,
                max=100.0,
                step=0.1,
                initial_value=40.0,
                hint="Start of the time range to exclude or include (shaded blue on the plot)",
            )
            self.range_to = w.slider(
                "To % of the record",
                min=0.0,
                max=100.0,
                step=0.1,
                initial_value=50.0,
                hint="End of the time range to exclude or include",
            )
            for h in (self.range_from, self.range_to):
                h.on_update(lambda e: panels.handle(on.range_changed, e))
            self.btn_exclude_range = panels.button(
                "Exclude range",
                on.do_exclude_range,
                hint="Leave the samples in the range out of the fit (undo in the Outliers tab); the fit reruns",
            )
            self.btn_include_range = panels.button(
                "Include range",
                on.do_include_range,
                hint="Put the range's excluded samples back into the fit; the fit reruns",
            )
            self.btn_exclude_fast = panels.button(
                "Exclude the fast-turning samples",
                on.do_exclude_fast,
                visible=False,
                hint="Leave out the samples taken while turning fast (marked red); the fit reruns",
            )
            self.range_info = gui.add_markdown("")
        self.histogram_folder = gui.add_folder("Error histogram", expand_by_default=True)
        with self.histogram_folder:
            self.histogram_unit = w.dropdown(
                "Error in", ("nT", "%"), initial_value="nT", hint="|B| - reference in nT or in % of the reference"
            )
            self.histogram_unit.on_update(lambda e: panels.handle(on.range_changed, e))
            self.histogram_plot = add_figure(gui, go.Figure(), aspect=0.68)
        self.settings_folder = gui.add_folder("Settings", expand_by_default=True)
        with self.settings_folder:
            self._build_settings(panels, gui, state, configure)
        self.steps_folder = gui.add_folder("Step by step", expand_by_default=False)
        with self.steps_folder:
            self.btn_ellipsoid = panels.button("1. Fit ellipsoid (per sensor)", on.do_ellipsoid, engine=True)
            self.btn_align = panels.button("2. Align sensors (Procrustes)", on.do_align, engine=True)
            self.btn_refine = panels.button("3. Refine (maximum likelihood)", on.do_refine, engine=True)
        with gui.add_folder("Data", expand_by_default=False):
            self.data_info = gui.add_markdown("")
        self.sensors_folder = gui.add_folder("Per sensor", expand_by_default=False)
        with self.sensors_folder:
            self.sensors_table = gui.add_markdown("")
        panels.vector_panel.build_calibrate(gui)
        with gui.add_folder("Step history", expand_by_default=False):
            self.history = gui.add_markdown("")
            self.history_note = gui.add_markdown(HELD_OUT_NOTE)
        panels.tab_panels.append(self)

    def _build_settings(self, panels, gui, state, configure) -> None:
        """The settings, each bound to the session state (:meth:`Panels.bind`), and the location's inputs."""
        w = panels.w
        self.method = panels.bind(
            w.dropdown("Method", tuple(METHODS), initial_value="ml", hint="; ".join(METHOD_LABELS[m] for m in METHODS)),
            lambda: state().method,
            lambda v: configure(method=v),
        )
        self.reference = panels.bind(
            w.number(
                "Reference field nT",
                0.0,
                min=0.0,
                step=1.0,
                hint="Total field in nT; 0 = the file's reference (or fitted if none)",
            ),
            lambda: float(state().reference_nT or 0.0),
            lambda v: configure(reference_nT=float(v) if v and float(v) > 0 else None),
        )
        self.fit_reference = panels.bind(
            gui.add_checkbox(
                "Fit the field magnitude",
                False,
                hint="Ignore any reference and fit |B| (det C^-1 = 1 for sensor 1)",
            ),
            lambda: bool(state().fit_reference),
            lambda v: configure(fit_reference=bool(v)),
        )
        self.reference_info = gui.add_markdown("")
        panels.vector_panel.build_location(gui)
        self.robust = panels.bind(
            gui.add_checkbox("Robust loss (soft L1)", False, hint="Down-weight gross outliers in the ML step"),
            lambda: bool(state().robust),
            lambda v: configure(robust=bool(v)),
        )

    # --- page actions --------------------------------------------------------------------------------------
    def _step(self, name: str, step) -> None:
        """Run the controller's ``step(inputs=...)`` in the worker, once the kept readings were checked."""
        self._steps().check_readings()
        self._ctrl().run_step(name, step)

    @action
    def do_calibrate(self, event):
        """Run the chosen method on the total-field model (the whole pipeline)."""
        ctrl = self._ctrl()
        self._step(f"calibrate ({ctrl.state.method})", ctrl.step_calibrate)

    @action
    def do_ellipsoid(self, event):
        """Step 1: an ellipsoid per sensor."""
        self._step("fit ellipsoid", self._ctrl().step_ellipsoid)

    @action
    def do_align(self, event):
        """Step 2: the sensors aligned (Procrustes)."""
        self._step("align sensors", self._ctrl().step_align)

    @action
    def do_refine(self, event):
        """Step 3 (and the Model tab's Refit): maximum likelihood of the model."""
        self._step("refine", self._ctrl().step_refine)

    # --- following the data --------------------------------------------------------------------------------
    def refresh(self, kinds) -> None:
        """Show what changed (``kinds``: :class:`~magcal_workbench.events.Change` members, or ``"all"``)."""
        if not hasattr(self, "history"):
            return
        ctrl = self._ctrl()
        every = "all" in kinds

        def asks(*wanted) -> bool:
            return every or any(k in kinds for k in wanted)

        if asks(Change.RESULT, Change.SELECTION, Change.MODEL):
            self.sensors_table.content = sensors_markdown(ctrl)
        if asks(Change.RESULT, Change.SELECTION, Change.MODEL, Change.VECTOR, Change.SETTINGS, Change.COMPENSATION):
            self.history.content = loop_text(ctrl).history(ctrl)
        if asks(Change.DATA):
            self.data_info.content = data_markdown(ctrl)
        if asks(Change.MODEL, Change.DATA, Change.RESULT, Change.SETTINGS, Change.VECTOR):
            self.reference_info.content = reference_markdown(ctrl)
        self.btn_align.visible = ctrl.dataset.n_sensors > 1
        if asks(Change.DATA):
            self._show_mode(ctrl)

    def _show_mode(self, ctrl) -> None:
        """On a record whose fit mode is a compensation, the total-field fit's parts hidden and one line saying
        why; on any other record, the usual tab."""
        note = fit_mode_markdown(ctrl)
        self.mode_note.content = note
        self.mode_note.visible = bool(note)
        usual = not note
        parts = (self.btn_run, self.field_folder, self.histogram_folder, self.settings_folder, self.steps_folder)
        for part in (*parts, self.sensors_folder):
            part.visible = usual


def fit_mode_markdown(ctrl) -> str:
    """One line for a record whose fit mode (the engine's ``mode_choice``) is a compensation: the mode in use, why,
    and that the total-field, vector and gravity fits do not apply; empty for any other record."""
    if not ctrl.compensation_loop():
        return ""
    mode, notes = ctrl.fit_mode()
    why = mode.title.split(" (", 1)[1].rstrip(")") if " (" in mode.title else mode.needs()
    said = "".join(f" {safe_text(note.text, 300)}." for note in notes)
    return (
        f"**Fit mode: {safe_text(mode.label)}** (`{mode.name}`), the engine's choice for this record: {safe_text(why)}. "
        f"The total-field, vector and gravity fits do not apply to a compensation flight, so their sections are "
        f"not shown.{said}"
    )
