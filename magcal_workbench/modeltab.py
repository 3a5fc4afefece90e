"""The Model tab, a panel of the panel recipe (:mod:`magcal_workbench.panelkit`): the model's effects (the catalogue's
boxes, a user's own effects), Refit, **Diagnose** and **Add** on the active model session, the RMS per step and the
evidence plots, with the handlers of the loop's buttons beside them.

:class:`ModelTab` is built at its place by :class:`~magcal_workbench.panels.Panels` (``build(panels, gui)``),
refreshed with the other tabs, and offers ``do_diagnose``, ``do_add`` and ``do_add_advice`` to the page's widgets
like every part's :func:`~magcal_workbench.actions.action`. Diagnose and Add go to the controller's active model
session (:attr:`Controller.model_session <magcal_workbench.controller.Controller.model_session>`: the vector model
on a record with attitude and a field vector, else the total-field model); the texts are the session's mode's
(:func:`magcal_workbench.looptext.loop_text`). Loading an effects file stays the steps' (it asks the terminal).
"""

from __future__ import annotations

import threading

import numpy as np

from magcal.core.errors import MagcalError

from .actions import action
from .calibratetab import fit_mode_markdown
from .events import Change
from .looptext import loop_text, model_terms_markdown
from .markup import clean_text, safe_code
from .panels import EFFECTS_FILE_WARNING, effect_hint, rms_plot_data, user_effects_markdown
from .plots import log_axis_scales


class ModelTab:
    """The Model tab's widgets, the loop's handlers and their refresh.

    Parameters
    ----------
    ctrl, steps : callable
        ``ctrl()``: the open data's :class:`~magcal_workbench.controller.Controller`; ``steps()``: the
        :class:`~magcal_workbench.steps.Steps` (their check of the readings).
    """

    #: The tab it fills.
    tab = "Model"

    def __init__(self, *, ctrl, steps):
        self._ctrl, self._steps = ctrl, steps
        self.panels = None
        self.effect_boxes: dict = {}
        self._boxes_lock = threading.Lock()
        #: A candidate the diagnosis does not advise that Add was pressed for once: the next press adds it.
        self.unadvised_asked: str | None = None

    # --- construction --------------------------------------------------------------------------------------
    def attach(self, panels) -> None:
        """Follow the open data (built already at its place, else into its tab now)."""
        if self.panels is None:
            with panels.tab(self.tab):
                self.build(panels, panels.gui)
        self.refresh(("all",))

    def build(self, panels, gui) -> None:
        """Make the widgets (in the tab being built)."""
        self.panels = panels
        on, ctrl = panels.on, self._ctrl()
        #: One line naming the fit mode in use and why, on a record whose mode is a compensation (else hidden).
        self.mode_note = gui.add_markdown("", visible=False)
        self.intro = gui.add_markdown(
            "Effects beyond bias, scale, non-orthogonality and misalignment. "
            "Greyed ones need a channel the data lack (hover for the reason)."
        )
        self.effects_folder = gui.add_folder("Effects", expand_by_default=True)
        self._add_effect_boxes(ctrl.available_effects())
        self.model_terms = gui.add_markdown(model_terms_markdown(ctrl.model_terms()))
        self.own_folder = gui.add_folder("Your own effects", expand_by_default=False)
        with self.own_folder:
            self._build_own_effects(panels, gui)
        self.btn_refit = panels.button("Refit with this model", on.do_refine, engine=True)
        self.btn_diagnose = panels.button("Diagnose", on.do_diagnose, engine=True, color="violet")
        self.candidates = gui.add_markdown("")
        self.candidate_choice = panels.w.dropdown(
            "Candidate", ("-",), allowed=self._candidate_options, initial_value="-"
        )
        self.candidate_evidence = gui.add_markdown("")
        self.candidate_choice.on_update(lambda e: panels.handle(self._candidate_chosen, e))
        self.btn_add = panels.button("Add the candidate and refit", on.do_add, engine=True, color="green")
        #: Everything the diagnosis advises, in one refit (shown when it advises something the model lacks).
        self.btn_add_advice = panels.button("Add the advice and refit", on.do_add_advice, engine=True, visible=False)
        panels.vector_panel.build_model(gui)  # the vector model's history plot and its Take out, for its loop
        self.rms_plot = gui.add_uplot(
            data=(
                np.array([0.0, 1.0]),
                np.array([np.nan, np.nan]),
                np.array([np.nan, np.nan]),
                np.array([np.nan, np.nan]),
            ),
            series=(
                {"label": "step"},
                {"label": "RMS nT", "stroke": "#1f77b4", "width": 2, "points": {"show": True, "size": 6}},
                {
                    "label": "noise floor nT",
                    "stroke": "#d62728",
                    "dash": [6, 4],
                    "width": 1.5,
                    "points": {"show": False},
                },
                {
                    "label": "held-out RMS nT",
                    "stroke": "#ff7f0e",
                    "width": 2,
                    "spanGaps": True,
                    "points": {"show": True, "size": 6},
                },
            ),
            scales={"x": {"time": False}, "y": {"distr": 3, "log": 10}},
            axes=({"label": "step (see the step history)", "incrs": [1, 2, 5, 10, 20, 50]}, {"label": "nT"}),
            padding=(14, 16, 0, 0),
            title="Total-field RMS per step",
            aspect=1.4,
        )
        self.btn_full_evidence = panels.button(
            "Full-size evidence",
            on.do_full_evidence,
            hint="The evidence plots over the scene, full size (press again to go back); the same data as below",
        )
        self.btn_evidence_png = panels.button("Download evidence PNG", on.do_download_evidence_png)
        self.btn_evidence_svg = panels.button("Download evidence SVG", on.do_download_evidence_svg)
        self.evidence_holder = gui.add_folder("Evidence", expand_by_default=True)
        self.evidence_plot = None
        panels.tab_panels.append(self)

    def _build_own_effects(self, panels, gui) -> None:
        """A user's effects: the file's path, Load (only when the page is served to this machine), the session's
        effects files not run."""
        self.user_effects = gui.add_markdown(user_effects_markdown(self._ctrl().available_effects()))
        self.effects_path = panels.w.text(
            "Effects file (.py)", "", hint="Path of a Python file on the machine serving this page"
        )
        self.btn_load_effects = panels.button("Load effects file", panels.on.do_load_effects, engine=True)
        self.effects_warning = gui.add_markdown(
            EFFECTS_FILE_WARNING
            if panels.local
            else "_Loading an effects file is off: the page is served beyond this machine. Start the workbench "
            "with `--effects-file PATH` instead._"
        )
        self.btn_load_effects.disabled = not panels.local
        self.effects_path.disabled = not panels.local
        #: The effects files the open session names, not loaded (never run when a session opens).
        self.session_effects = gui.add_markdown("", visible=False)
        self.btn_session_effects = panels.button(
            "Load the session's effects files", panels.on.do_load_session_effects, engine=True, visible=False
        )

    def _add_effect_boxes(self, entries) -> None:
        """A checkbox for every catalogue effect that has none yet (a user's effects loaded later join the end)."""
        panels = self.panels
        with self._boxes_lock, self.effects_folder:  # two refreshes at once must not add a box twice
            for entry in entries:
                name = entry["name"]
                if name in self.effect_boxes:
                    continue
                self.effect_boxes[name] = panels.bind(
                    # spaces, not underscores: the narrow label column wraps a long name at its words
                    panels.gui.add_checkbox(clean_text(name.replace("_", " "), 64), False, hint=effect_hint(entry)),
                    lambda n=name: self._ctrl().state.has_effect(n),
                    lambda on, n=name: self._ctrl().set_effect(n, bool(on)),
                )

    # --- page actions: the loop on the active model session ------------------------------------------------
    def _step(self, name: str, step) -> None:
        """Run the controller's ``step(inputs=...)`` in the worker, once the kept readings were checked."""
        self._steps().check_readings()
        self._ctrl().run_step(name, step)

    @action
    def do_diagnose(self, event):
        """Rank the candidate effects of the active model's fit."""
        self._step("diagnose", self._ctrl().step_diagnose)

    @action
    def do_add(self, event):
        """Add the chosen candidate (the first offered for ``-``) and refit; one the diagnosis did not find to hold
        on held-out data is added at the second press, marked in the history."""
        self._steps().check_readings()
        choice = self.panels.values.check(self.candidate_choice)
        ctrl = self._ctrl()
        offered = ctrl.candidate_labels()
        label = offered[0] if choice == "-" and offered else (None if choice == "-" else choice)
        note = ""
        if label is not None and not ctrl.candidate_holds(label):
            if self.unadvised_asked != label:
                self.unadvised_asked = label
                raise MagcalError(
                    f"{label} does not hold: the diagnosis did not find that its gain holds on data the fit did not "
                    "see (or could not judge it). Press Add again to add it anyway; the history will mark it"
                )
            note = " (does not hold)"
        self.unadvised_asked = None
        ctrl.run_step("add effect", lambda inputs: ctrl.step_add(label, inputs=inputs, note=note))

    @action
    def do_add_advice(self, event):
        """Add everything the diagnosis advises and refit once."""
        ctrl = self._ctrl()
        self._step("add the advice", lambda inputs: ctrl.step_add_advice(inputs=inputs))

    # --- the candidates ------------------------------------------------------------------------------------
    def _candidate_options(self) -> tuple:
        """The Candidate choices the server offers: the current diagnosis's candidates and ``-``."""
        return tuple(self._ctrl().candidate_labels()) + ("-",)

    def _candidate_chosen(self, event) -> None:
        self._show_candidate_evidence()
        on = self.panels.on
        if self.panels.maps_choice() == "candidate's pattern":
            on.refresh_maps()
        if loop_text(self._ctrl()).evidence_per_candidate:  # the plots put the candidate's channel on their axis
            on.draw_evidence()

    def _show_candidate_evidence(self) -> None:
        ctrl = self._ctrl()
        self.candidate_evidence.content = loop_text(ctrl).candidate(ctrl, self.candidate_choice.value)

    # --- following the data --------------------------------------------------------------------------------
    def refresh(self, kinds) -> None:
        """Show what changed (``kinds``: :class:`~magcal_workbench.events.Change` members, or ``"all"``)."""
        if self.panels is None:
            return
        ctrl = self._ctrl()
        every = "all" in kinds

        def asks(*wanted) -> bool:
            return every or any(k in kinds for k in wanted)

        if asks(Change.RESULT, Change.SELECTION, Change.MODEL):
            data = rms_plot_data(ctrl)
            if len(data[0]):
                self.rms_plot.data = data
                self.rms_plot.scales = log_axis_scales(data)
        if asks(Change.RESULT, Change.SELECTION, Change.MODEL, Change.VECTOR, Change.SETTINGS, Change.COMPENSATION):
            self.model_terms.content = loop_text(ctrl).terms(ctrl)
        if asks(Change.DATA, Change.EFFECTS):
            self._refresh_catalogue(ctrl)
        if asks(Change.DATA):
            self._show_mode(ctrl)
        if asks(Change.DIAGNOSIS, Change.DATA):
            self._refresh_diagnosis(ctrl)

    def _show_mode(self, ctrl) -> None:
        """On a record whose fit mode is a compensation, the catalogue's effects, Refit, the total-field plot and the
        evidence hidden (the compensation's terms, Diagnose and Add stay) and one line saying why; on any other
        record, the usual tab."""
        note = fit_mode_markdown(ctrl)
        self.mode_note.content = note
        self.mode_note.visible = bool(note)
        usual = not note
        parts = (self.intro, self.effects_folder, self.own_folder, self.btn_refit, self.evidence_holder)
        for part in (*parts, self.btn_full_evidence, self.btn_evidence_png, self.btn_evidence_svg):
            part.visible = usual
        if not usual:
            self.rms_plot.visible = False

    def _refresh_catalogue(self, ctrl) -> None:
        """The effects' boxes and the user's effects (the catalogue grew, or other data opened)."""
        catalogue = ctrl.available_effects()
        self._add_effect_boxes(catalogue)
        self.user_effects.content = user_effects_markdown(catalogue)
        pending = ctrl.pending_effects_files()
        self.session_effects.visible = self.btn_session_effects.visible = bool(pending)
        self.btn_session_effects.disabled = not self.panels.local
        self.session_effects.content = (
            "This session names effects files that were **not** run: "
            + ", ".join(safe_code(p) for p in pending)
            + ". An effects file is Python code that runs with your rights: load them only if you trust them."
            if pending
            else ""
        )
        entries = {e["name"]: e for e in catalogue}
        for name, box in self.effect_boxes.items():
            e = entries.get(name)
            if e is not None:
                box.disabled = bool(e["missing"])
                box.hint = effect_hint(e)
            else:  # no longer in the catalogue
                box.disabled = True
                box.hint = "Not loaded: load the file that defines it (Your own effects)"

    def _refresh_diagnosis(self, ctrl) -> None:
        """The active model's diagnosis: its candidates, the choice offered, the advice, the evidence."""
        self.candidates.content = loop_text(ctrl).candidates(ctrl)
        opts = tuple(ctrl.candidate_labels()) or ("-",)
        advised = ctrl.advice()
        self.candidate_choice.options = opts
        # an advised candidate is chosen first; Add asks before it adds one the diagnosis does not advise
        self.candidate_choice.value = next((o for o in opts if o in advised), opts[0])
        self.btn_add_advice.visible = bool(advised)
        self.btn_add_advice.label = f"Add the advice ({', '.join(advised)}) and refit" if advised else "Add the advice"
        self._show_candidate_evidence()
        self.panels.on.draw_evidence()
