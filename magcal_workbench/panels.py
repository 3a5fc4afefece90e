"""The control panel: the status, the guide, the compact table, and the tab group whose tabs (Calibrate, Model,
Quality, Outliers, View, Files, Lessons) are panels of the panel recipe (:mod:`magcal_workbench.panelkit`), built
here at their place and refreshed with the page.

Every GUI element lives on ``server.gui`` so all connected browsers share one state. Each widget's callback is
wired where the widget is made: buttons call their handler by name (``on.NAME``, :mod:`magcal_workbench.actions`);
a setting's widget is *bound* to the session state (:meth:`Panels.bind`), and its callback does nothing when the
widget already shows what the state holds, so :meth:`Panels.refresh` writes the state back into the widgets
without re-running anything. Text shown is built by small pure functions (``*_markdown``) that the tests call
directly. Text the workbench did not write (file names and contents, session fields, a user's effects) goes
through :mod:`workbench.markup` before it joins markdown.
"""

from __future__ import annotations

from contextlib import contextmanager

import numpy as np

from magcal.core import conventions

from . import scene as scn
from .events import Change
from .figures import fmt
from .guide import gravity_status_markdown, guide_markdown, lesson_markdown, next_step, vector_reference_markdown
from .looptext import (  # the loop's texts; the names stay importable from here
    HELD_OUT_NOTE,
    TRANSFER_WORDS,
    StatusFigures,
    candidate_evidence_markdown,
    candidates_markdown,
    convergence_markdown,
    held_out_pair,
    history_markdown,
    holds_words,
    loop_text,
    model_terms_markdown,
)
from .markup import clean_text, hide_paths, safe_code, safe_text
from .plots import one_step_history
from .qualitytab import noise_markdown, quality_markdown
from .vectorpanel import VectorPanel

#: The loop's texts moved to :mod:`magcal_workbench.looptext`, importable from here as before.
__all__ = [
    "HELD_OUT_NOTE",
    "TRANSFER_WORDS",
    "Panels",
    "candidate_evidence_markdown",
    "candidates_markdown",
    "convergence_markdown",
    "fmt",
    "held_out_pair",
    "history_markdown",
    "holds_words",
    "model_terms_markdown",
    "noise_markdown",
    "quality_markdown",
    "status_markdown",
    "summary_markdown",
]

METHOD_LABELS = {
    "ml": "ml: ellipsoid, align, maximum likelihood",
    "ellipsoid": "ellipsoid: the seed's two steps",
    "pso": "pso: particle swarm (global search)",
    "ipso": "ipso: improved particle swarm",
    "de": "de: differential evolution",
}
ALL_SENSORS = "all sensors"


# --- text builders ------------------------------------------------------------------------------------------
def status_markdown(ctrl) -> str:
    """The always-visible summary: RMS, floor, rejected count, model, and a warning if the fit did not converge."""
    rms = ctrl.residual_rms_nT()
    floor = ctrl.floor_nT()
    sel = ctrl.state.selection
    effects = ", ".join(safe_code(e, 80) for e in ctrl.state.effects) or "base terms only"
    if sel.n_rejected == sel.n_samples:
        rms_text = "no kept samples"
    else:
        rms_text = fmt(rms, "nT") if np.isfinite(rms) else "not fitted yet"
    figures = StatusFigures(
        rms=rms_text,
        floor=fmt(floor, "nT", 3),
        rejected=f"Rejected: {sel.n_rejected} of {sel.n_samples} samples",
        model=effects,
    )
    text = loop_text(ctrl).status(ctrl, figures)  # the model Diagnose and Add work on, its figures first
    gravity = gravity_status_markdown(ctrl)  # a board with an accelerometer: its first fit's figures first
    text = f"{gravity}  \n{text}" if gravity else text
    warning = convergence_markdown(ctrl.state.history[-1] if ctrl.state.history else None)
    return f"{text}\n\n{warning}" if warning else text


def alarm_markdown(ctrl, live) -> str:
    """The failures the page shows until they are resolved, whatever message comes meanwhile: a failed autosave
    (:attr:`Controller.save_problem`) and a live recording stopped for want of a disk
    (:attr:`LiveView.recording_problem`); empty when all is well."""
    problems = [ctrl.save_problem, None if live is None else live.recording_problem]
    return "\n\n".join(f"⚠ {p}" for p in problems if p)


def pct(v) -> str:
    """A share (0-1) as a percentage for the compact table: ``99.7 %``, ``100 %``, ``-``."""
    if v is None or not np.isfinite(v):
        return "-"
    return "100 %" if v >= 1.0 else f"{100.0 * v:.3g} %"


def summary_markdown(
    figures: dict, rms_nT=None, floor_nT=None, sensors=(), sensor: int = 0, floor_what: str = ""
) -> str:
    """The compact table the panel opens with: what matters now.

    Parameters
    ----------
    figures : dict
        :func:`magcal_workbench.plots.table_figures` of the open data or the live session.
    rms_nT, floor_nT : float or None
        The current fit's total-field RMS of the kept samples and its noise floor, nT (None before a fit).
    sensors : sequence of (cinv, bias_nT)
        The calibration's correction matrix ``C^-1`` (3 x 3) and bias (nT) per sensor; empty before a fit.
    sensor : int
        Which sensor's matrix and bias are shown (0-based; the View tab's choice).
    floor_what : str
        What ``floor_nT`` is the floor of when it is not the total-field fit's (``world components``: the vector
        mode's, :func:`magcal_workbench.floors.mode_floor`); the corrected row is then not divided by it.

    The first table: the RMS of ``|B| - reference`` raw and corrected, against the floor (and their ratio), and the
    share of samples within +-1, +-2 and +-5 % of the reference; the second: the chosen sensor's ``C^-1`` with its
    bias per axis (nT); then the coverage of the sphere of directions per sensor.
    """
    wr, wc = figures["within_raw"], figures.get("within_corrected")
    bands = list(wr)
    head = "| | RMS nT | " + " | ".join(f"±{b:g} %" for b in bands) + " |"
    rows = [head, "|---|---|" + "---|" * len(bands)]
    rows.append(f"| raw | {fmt(figures['rms_raw_nT'], digits=4)} | " + " | ".join(pct(wr[b]) for b in bands) + " |")
    if wc is not None:
        ratio = f" ({rms_nT / floor_nT:.2f}× floor)" if rms_nT and floor_nT and np.isfinite(rms_nT) else ""
        ratio = "" if floor_what else ratio
        rows.append(
            f"| **corrected** | **{fmt(rms_nT, digits=4)}**{ratio} | " + " | ".join(pct(wc[b]) for b in bands) + " |"
        )
    kept = f"{figures['n_kept']} of {figures['n_samples']} samples kept"
    floor = (
        f"noise floor ({floor_what}) {fmt(floor_nT, 'nT', 4)}"
        if floor_what
        else f"noise floor {fmt(floor_nT, 'nT', 3)}"
    )
    text = f"**Now**: {kept}; {floor}\n\n" + "\n".join(rows)
    if sensors:
        s = min(max(int(sensor), 0), len(sensors) - 1)
        cinv, bias = np.asarray(sensors[s][0], float), np.asarray(sensors[s][1], float)
        who = f"sensor {s + 1} of {len(sensors)}" if len(sensors) > 1 else "the sensor"
        mrows = [f"| C⁻¹ ({who}) | x | y | z | bias nT |", "|---|---|---|---|---|"]
        for i, axis in enumerate("xyz"):
            mrows.append(f"| {axis} | " + " | ".join(f"{v:.5f}" for v in cinv[i]) + f" | {bias[i]:.1f} |")
        text += "\n\n" + "\n".join(mrows)
    cov = figures.get("coverage") or []
    if cov:
        parts = [f"s{i + 1} {pct(c)}" for i, c in enumerate(cov)] if len(cov) > 1 else [pct(cov[0])]
        text += "\n\nCoverage of the sphere of directions: " + ", ".join(parts)
    return text


def live_data_markdown(live) -> str:
    """The Calibrate tab's data line during a live session: the source and what has arrived (not the file that
    was open before)."""
    ds = live.dataset()
    head = f"**Data:** live from {safe_code(live.url)}, recording to {safe_code(live.path.name)}"
    if ds is None:
        return head + "  \n_waiting for the first samples_"
    return f"{head}  \n{safe_text(ds.describe(), 1000)}"


def live_sensors_markdown(live) -> str:
    """Per-sensor figures of the live session's latest fit (bias nT, gauge-free scale and axis angles)."""
    fit = live.fit
    if fit is None:
        return "_The live fit starts after the first samples._"
    rows = ["| sensor | scale | axis angles deg | bias nT |", "|---|---|---|---|"]
    for s, c in enumerate(fit.calibration.sensors):
        scale, angles = conventions.gauge_free(c.cinv)
        rows.append(
            f"| {s + 1} | {', '.join(f'{v:.5f}' for v in scale)} | {', '.join(f'{v:.3f}' for v in angles)} | "
            f"{', '.join(f'{v:.1f}' for v in c.bias_nT)} |"
        )
    return f"Live fit on {fit.n_samples} samples, RMS {fmt(fit.rms_nT, 'nT')}\n\n" + "\n".join(rows)


#: What the tabs that act on an opened recording say during a live session.
LIVE_TAB_NOTE = (
    "_Live session: these figures are the stream's. Stop (Files tab) opens the recording here, and the engine's "
    "steps, the diagnosis and the outlier tools then work on it._"
)


def data_markdown(ctrl) -> str:
    ds = ctrl.dataset
    src = (
        f"lesson {safe_code(ctrl.state.lesson)}"
        if ctrl.state.lesson
        else safe_text(hide_paths(str(ds.source)), 200)
        if ds.source
        else "simulated data"
    )
    return f"**Data:** {src}  \n{safe_text(ds.describe(), 1000)}"


def sensors_markdown(ctrl) -> str:
    """Per-sensor RMS and the calibration's gauge-free figures, plus the tensor before/after."""

    rows = ["| sensor | RMS nT | scale | axis angles deg | bias nT |", "|---|---|---|---|---|"]
    per = ctrl.rms_per_sensor_nT()
    for s in range(ctrl.dataset.n_sensors):
        if ctrl.calibration is not None:
            c = ctrl.calibration.sensors[s]
            scale, angles = conventions.gauge_free(c.cinv)
            rows.append(
                f"| {s + 1} | {fmt(per[s], digits=4)} | {', '.join(f'{v:.5f}' for v in scale)} | "
                f"{', '.join(f'{v:.3f}' for v in angles)} | {', '.join(f'{v:.1f}' for v in c.bias_nT)} |"
            )
        else:
            rows.append(f"| {s + 1} | - | - | - | - |")
    text = "\n".join(rows)
    t = ctrl.tensor_rms()
    if t is not None:
        trows = ["| tensor nT/m | before | after | floor |", "|---|---|---|---|"]
        for c in t["before"]:
            after = t["after"][c] if t["after"] else None
            floor = t["floor"][c] if t["floor"] else None
            trows.append(f"| {c} | {fmt(t['before'][c])} | {fmt(after)} | {fmt(floor, digits=3)} |")
        text += "\n\n" + "\n".join(trows)
    return text


def inspect_markdown(info: dict | None) -> str:
    if info is None:
        return "_Click a point to inspect its sample._"
    parts = [f"**Sample {info['index']}** ({'kept' if info['kept'] else 'rejected'})"]
    if "time_s" in info:
        parts.append(f"t = {info['time_s']:.3f} s")
    if "temperature_C" in info:
        parts.append(f"T = {info['temperature_C']:.2f} degC")
    if "residual_nT" in info:
        parts.append("residual " + ", ".join(f"s{i + 1} {r:+.2f}" for i, r in enumerate(info["residual_nT"])) + " nT")
    return "  \n".join(parts)


def effect_hint(entry: dict) -> str:
    """The tooltip of an effect's checkbox (plain text): what it models, where it comes from, why it is greyed."""
    origin = entry.get("origin", "built-in")
    where = "" if origin == "built-in" else f" [your effect: {origin} {entry.get('source', '')}]"
    transferable = entry.get("transferable")
    carry = f" {TRANSFER_WORDS[transferable]}." if isinstance(transferable, bool) else ""
    text = (entry["description"] or entry["name"]) + where + carry
    if entry["missing"]:
        text = f"Unavailable: the data lack {', '.join(entry['missing'])}. {text}"
    return clean_text(text, 600)


def user_effects_markdown(entries) -> str:
    """The list of the user's effects in the Model tab: name, origin and description, escaped."""
    mine = [e for e in entries if e.get("origin", "built-in") != "built-in"]
    if not mine:
        return "_No effect of your own is loaded._"
    rows = ["**Your effects**"]
    for e in mine:
        rows.append(
            f"- {safe_code(e['name'], 80)} ({safe_text(e['origin'])} {safe_code(e.get('source', ''), 200)})"
            f": {safe_text(e.get('description', ''), 300)}"
        )
    return "\n".join(rows)


def sessions_markdown(sessions, max_bytes=None, last: int = 10) -> str:
    """The saved sessions (newest first) with their sizes, and the folder's total against its bound."""
    if not sessions:
        return "_No saved session._"
    rows = ["| session | saved | MB |", "|---|---|---|"]
    rows += [
        f"| {safe_text(s['id'], 80)} | {safe_text(s.get('saved_at', ''), 20)} | {s.get('bytes', 0) / 1e6:.2f} |"
        for s in sessions[:last]
    ]
    total = sum(s.get("bytes", 0) for s in sessions)
    bound = f" of {max_bytes / 1e6:.0f} MB kept (the oldest go first)" if max_bytes else ""
    more = f", {len(sessions) - last} older not listed" if len(sessions) > last else ""
    return "\n".join(rows) + f"\n\n{len(sessions)} session(s), {total / 1e6:.1f} MB{bound}{more}"


def reference_markdown(ctrl) -> str:
    """The reference field the fits use, and where it comes from (the box above shows 0 for "not typed"): the
    vector fit's field vector first where the loop works on it, then the total-field fit's."""
    vector = vector_reference_markdown(ctrl)
    total = _total_reference_markdown(ctrl)
    return f"{vector}  \n{total.replace('_Reference used:_', '_Total-field fit:_')}" if vector else total


def _total_reference_markdown(ctrl) -> str:
    ds, state, cal = ctrl.dataset, ctrl.state, ctrl.calibration
    fitted = (
        f"; the last fit found {fmt(cal.reference_total_nT, 'nT', 6)}"
        if cal is not None and cal.reference_total_nT
        else ""
    )
    if state.fit_reference:
        return f"_Reference used:_ fitted (you asked to fit the field magnitude){fitted}"
    if state.reference_nT:
        loc = ctrl.vector.location
        if loc is not None and state.reference_nT == round(loc.total_nT, 1):  # what the location set
            where = "the file's `# site:` line" if ctrl.vector.from_site() else "the location below"
            return f"_Reference used:_ {fmt(state.reference_nT, 'nT', 6)}, IGRF's |B| at {where}"
        return f"_Reference used:_ {fmt(state.reference_nT, 'nT', 6)}, typed here"
    if ds.ref_total_nT is not None:
        return (
            f"_Reference used:_ per sample, the file's `ref_total` column (median "
            f"{fmt(float(np.median(ds.ref_total_nT)), 'nT', 6)})"
        )
    if ds.reference_total_nT:
        return f"_Reference used:_ {fmt(ds.reference_total_nT, 'nT', 6)} from the file (`# reference_total_nT`)"
    return f"_Reference used:_ none given, so the field magnitude is fitted{fitted}"


def download_markdown(ctrl) -> str:
    """What the corrected-CSV download holds: the model and the record-only terms applied to it."""
    if ctrl.calibration is None:
        return "_Fit first to download a calibration or corrected data._"
    applied = ctrl.record_only_applied()
    if not applied:
        return "The corrected CSV applies instrument terms only: the calibration JSON corrects new data the same way."
    return (
        f"The corrected CSV applies the record-only term(s) {', '.join(safe_code(a, 80) for a in applied)}: "
        "right for this record; the calibration JSON drops them on other data (magcal apply says so)."
    )


#: Shown next to the control that loads an effects file.
EFFECTS_FILE_WARNING = (
    "⚠ **Loading a file runs its Python code** on the machine serving this page, with your "
    "permissions: load only files you wrote or trust. The page loads a file named with `--effects-file` when the "
    "workbench started, or one you confirm in the terminal it runs in (it asks). Its `@register` effects join the "
    "list above, Diagnose and the calibration JSON (docs/user-effects.md)."
)


def rms_plot_data(ctrl):
    """``(step, in-sample RMS, floor, held-out RMS)`` arrays (nT) for the history plot. The floor is a property of
    the noise: the current one (given or estimated) is drawn across every step, else the steps' own."""
    state = ctrl.state
    x, y, f = state.rms_series()
    held = np.array(
        [np.nan if getattr(r, "held_out_rms_nT", None) is None else r.held_out_rms_nT for r in state.history],
        dtype=float,
    )
    # the plot cannot leave a gap (uPlot draws NaN as a value): a step without a held-out figure is drawn at its
    # in-sample RMS (exact for the raw readings, where nothing is fitted; the table shows "-" for it)
    held = np.where(np.isfinite(held), held, y)
    floor = ctrl.floor_nT()
    if floor:
        f = np.full_like(y, float(floor))
    elif np.isfinite(f).any():
        f = np.where(np.isfinite(f), f, f[np.isfinite(f)][0])
    return one_step_history(x, (y, f, held), floors=(1,))  # one step: its floor spans the frame


#: Largest default residual gain of the View tab (that of a fit near a clean sensor's noise).
RESIDUAL_GAIN_MAX = 1000.0
#: Drawn radial deviation the default residual gain aims for: the residual RMS.
DRAWN_RESIDUAL = 0.05


def view_gains(ctrl, drawn_rms_nT: float | None = None) -> tuple[float, float]:
    """Default (distortion, residual) gains of the View tab for these data: the distortion gain of the kept
    samples' raw clouds (:func:`magcal_workbench.scene.distortion_gain`), the residual RMS drawn at about
    :data:`DRAWN_RESIDUAL` of the radius, not above :data:`RESIDUAL_GAIN_MAX`. Residuals of hundreds of nT would
    otherwise be drawn far outside the screen. ``drawn_rms_nT``: the RMS of the residual the scene draws (the
    vector or gravity fit's, :meth:`magcal_workbench.view.SceneControl.fit_drawn`), default the total-field fit's."""
    F = float(ctrl.field_nT)
    if not (np.isfinite(F) and F > 0):  # an all-zero file: nothing to scale by
        return scn.DISTORTION_GAIN_MAX, RESIDUAL_GAIN_MAX
    distortion = scn.distortion_gain(ctrl.dataset.readings_nT[:, ctrl.kept], F)
    rms = ctrl.residual_rms_nT() if drawn_rms_nT is None else float(drawn_rms_nT)
    residual = (
        RESIDUAL_GAIN_MAX
        if not np.isfinite(rms) or rms <= 0
        else float(np.clip(DRAWN_RESIDUAL * F / rms, 1.0, RESIDUAL_GAIN_MAX))
    )
    return distortion, float(round(residual))


#: The Units choices of an upload (the first keeps the file's own ``# units:`` line).


#: The status line while a live session owns the scene.
LIVE_STATUS = (
    "**Live session**: the Calibrate, Model and Outliers tabs work on the recording once it is stopped (Files tab)"
)


class Panels:
    """Builds the GUI on ``server.gui`` and keeps it in step with the workbench.

    The panels know nothing of the workbench: they are given what they call and what they read.

    Parameters
    ----------
    widgets : magcal_workbench.checks.Widgets
        Makes the input widgets and registers what each may send.
    handle : callable
        ``handle(func, event)`` runs a widget's callback (errors become the page's message).
    on : object
        The actions the widgets call, as attributes: ``do_*(event)`` handlers, ``set_sensor(choice)``,
        ``view_changed``, ``surface_changed``, ``window_changed``, ``range_changed`` (``(event)``),
        ``refresh_maps()``, ``legend_html()``, ``draw_evidence()``, ``draw_cockpit()`` (the compact table and the
        Calibrate tab's plots, :mod:`magcal_workbench.cockpit`).
    ctrl : callable
        Returns the current :class:`~magcal_workbench.controller.Controller` (it changes with the data).
    live : callable
        Returns the live session (:class:`~magcal_workbench.live.LiveView`) or None.
    busy : callable
        Whether the engine's worker runs a job.
    maps_choice : callable
        The sphere surface shown now.
    session_ids : callable
        The saved sessions the server offers (the Saved session choices).
    store : magcal_workbench.session.SessionStore or None
        The session folder (None: autosave off).
    local : bool
        Whether the page is served to this machine only (loading an effects file is allowed).
    live_sources : callable
        The live sources the server offers (labels of :meth:`magcal_workbench.live.SourceMenu.labels`).
    tabs : dict, optional
        The panels of the recipe (:data:`magcal_workbench.panelkit.PANELS`, made) by name: those that fill a
        built-in tab (``build(panels, gui)``: the Calibrate tab's run and settings, the Model tab's Diagnose and
        Add, the Quality tab) are built at their place in it, with their handlers beside their widgets.
    """

    def __init__(
        self,
        widgets,
        handle,
        on,
        ctrl,
        live,
        busy,
        maps_choice,
        session_ids,
        store,
        local: bool,
        live_sources,
        tabs: dict | None = None,
    ):
        self.w = widgets
        self.values = widgets.values
        self.handle = handle
        self.on = on
        self.ctrl = ctrl
        self.live = live
        self.busy = busy
        self.maps_choice = maps_choice
        self.session_ids = session_ids
        self.store = store
        self.local = local
        self.live_sources = live_sources
        self._tab_parts = dict(tabs or {})
        gui = widgets.gui
        self.gui = gui
        gui.configure_theme(control_width="large", dark_mode=False)
        self.title = gui.add_markdown("## magcal workbench")
        #: What failed and stays shown until resolved (:func:`alarm_markdown`): a failed autosave, a recording
        #: stopped by a full disk.
        self.alarm = gui.add_markdown("", visible=False)
        # the status (Total-field RMS, floor, model) first: the page shows it while the tabs are built
        self.status = gui.add_markdown(status_markdown(ctrl()))
        #: What the data are, the fits they allow and the loop's next step (:mod:`magcal_workbench.guide`), with
        #: that step as a button.
        self.guide = gui.add_markdown("")
        self._engine_buttons: list = []
        self.btn_next = self._button(gui, "Step 1: fit the model", self._do_next_step, color="green")
        #: An open lesson's title and text, under the guide's button (:func:`~magcal_workbench.guide.lesson_markdown`).
        self.lesson_intro = gui.add_markdown("")
        #: The compact table of what matters now (RMS against the floor, % within, the matrix, coverage).
        self.summary = gui.add_markdown("")
        self.progress = gui.add_progress_bar(0.0, visible=False, animated=True)
        self.progress_text = gui.add_markdown("", visible=False)
        self.message = gui.add_markdown("")
        #: The live session's figures (source, samples, coverage, fit), shown while one is open.
        self.live_status = gui.add_markdown("", visible=False)
        self.legend = gui.add_html("")
        #: The full-size evidence: an image over the canvas left of this panel (Model tab's Full-size evidence).
        self.evidence_overlay = gui.add_html("", visible=False)
        tab_group = gui.add_tab_group()
        self.vector_panel = VectorPanel(self)  # the vector model's widgets, built into the tabs below
        #: A change of the selection leaves the cockpit's figures to the refit that follows (:meth:`figures_held`),
        #: and whether some were left.
        self._figures_held = False
        self._figures_stale = False
        self._bindings: list = []  # (widget, the state's value as the widget shows it)
        self._live_shown = False  # the tabs describe a live session's stream
        #: The built-in tabs made as panels of the panel recipe (:mod:`magcal_workbench.panelkit`), which fill their
        #: tab when attached (:meth:`tab`) and are refreshed with the others.
        self.tab_panels: list = []
        #: The tabs by name (:meth:`section` adds to them).
        self.tab_by_name: dict = {}
        for name, build in (
            ("Calibrate", lambda gui: self._built_in("calibrate", gui)),  # magcal_workbench.calibratetab
            ("Model", lambda gui: self._built_in("model", gui)),  # magcal_workbench.modeltab
            ("Quality", lambda gui: self._built_in("quality", gui)),  # magcal_workbench.qualitytab
            ("Outliers", lambda gui: self._built_in("outliers", gui)),  # magcal_workbench.outlierstab
            ("View", lambda gui: self._built_in("view", gui)),  # magcal_workbench.viewtab
            ("Files", lambda gui: self._built_in("files", gui)),  # magcal_workbench.filestab
            ("Lessons", lambda gui: self._built_in("lessons", gui)),  # magcal_workbench.lessonstab
        ):
            tab = tab_group.add_tab(name, icon=None)
            self.tab_by_name[name] = tab
            with tab:
                build(gui)
        self.tabs = tab_group

    def _built_in(self, name: str, gui) -> None:
        """Build the panel ``name`` of the recipe here, in the tab being built (its ``build(panels, gui)``); a
        panel not handed to the panels builds itself into its tab when attached."""
        part = self._tab_parts.get(name)
        if part is not None:
            part.build(self, gui)

    def _do_next_step(self, event) -> None:
        """The guide's button: the step :func:`~magcal_workbench.guide.next_step` names, through the same handler
        as that step's own button (Add: *Add the advice*, everything the diagnosis advises)."""
        step = next_step(self.ctrl())
        handler = {
            "run": self.on.do_calibrate,
            "vector": self.on.do_vector_fit,
            "gravity": self.on.do_gravity_fit,
            "compensation": self.on.do_compensation_fit,
            "diagnose": self.on.do_diagnose,
            "add": self.on.do_add_advice,
        }.get(step.key)
        if handler is not None:
            handler(event)

    def show_guide(self) -> None:
        """The guide's text and its button, for the session as it is now."""
        ctrl = self.ctrl()
        self.guide.content = guide_markdown(ctrl)
        self.lesson_intro.content = lesson_markdown(ctrl)
        step = next_step(ctrl)
        self.btn_next.visible = step.key != "none"
        if step.label:
            self.btn_next.label = step.label

    def tab(self, name: str):
        """The tab ``name`` (``"Quality"``, ...) to build into: ``with panels.tab("Quality"): ...`` (a built-in
        tab made as a panel of the recipe, :mod:`magcal_workbench.panelkit`)."""
        return self.tab_by_name[name]

    def __getattr__(self, name: str):
        """A widget of a built-in tab made as a panel (``panels.noise_input``), as when the panels made it."""
        if name.startswith("__") or name == "tab_panels":
            raise AttributeError(name)
        for tab in self.__dict__.get("tab_panels", ()):
            if name in vars(tab):
                return vars(tab)[name]
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    def section(self, tab: str, title: str, expand: bool = False):
        """A new collapsible section at the end of the tab ``tab`` (``"Files"``, ...): its widgets are made inside
        ``with panels.section("Files", "Export"): ...``; input widgets through :attr:`w` (checked values)."""
        with self.tab_by_name[tab]:
            return self.gui.add_folder(title, expand_by_default=expand)

    # --- construction --------------------------------------------------------------------------------------
    def bind(self, handle, shown, apply):
        """Wire a setting's widget to the session state, where the widget is made.

        ``shown()`` is the state's value as the widget shows it; ``apply(value)`` puts the value the user chose
        into the state. A callback whose value the state already holds does nothing, so :meth:`show_state` may
        write the state into every widget without re-triggering anything.
        """

        def changed(event):
            if handle.value != shown():
                self.handle(lambda _: apply(handle.value), event)

        handle.on_update(changed)
        self._bindings.append((handle, shown))
        self.values.shown_by(handle, shown)
        return handle

    def button(self, label: str, handler, engine: bool = False, **kw):
        """A button in the section being built (an added panel's, :mod:`magcal_workbench.panelkit`): a click calls
        ``handler(event)`` through the workbench's error handling; ``engine``: disabled while a job runs (a button
        that starts an engine step); ``kw`` go to viser's ``add_button`` (``color``, ``hint``, ``visible``)."""
        return self._button(self.gui, label, handler, engine=engine, **kw)

    def _button(self, gui, label, handler, engine=True, **kw):
        b = gui.add_button(label, **kw)
        b.on_click(lambda event: self.handle(handler, event))
        if engine:
            self._engine_buttons.append(b)
        return b

    def show_alarm(self) -> None:
        """Show what failed and is not resolved yet (:func:`alarm_markdown`), or hide the warning."""
        text = alarm_markdown(self.ctrl(), self.live())
        if text != self.alarm.content:
            self.alarm.content = text
        self.alarm.visible = bool(text)

    def refresh_live(self) -> None:
        """Show the live session's state (called by the live view's thread after each update)."""
        live = self.live()
        self.show_alarm()
        running = live is not None and live.active
        if running:
            self.status.content = LIVE_STATUS
            self.legend.content = self.on.legend_html()
        self.live_status.visible = live is not None
        if live is not None:
            self.live_status.content = live.status_markdown()
        if running:
            self.show_live_texts(live)
            self.on.draw_cockpit()  # the table and the plots follow the stream (throttled there)
            self._live_shown = True
        elif self._live_shown:  # stopped: the tabs describe the open data again
            self._live_shown = False
            self.refresh(("all",))
        files = self._tab_parts.get("files")
        if files is not None:
            files.show_live(live)
        for b in self._engine_buttons:  # the engine steps act on the opened data, not on the stream
            b.disabled = running or self.busy()

    # --- refresh -------------------------------------------------------------------------------------------
    def set_busy(self, busy: bool, name: str | None) -> None:
        for b in self._engine_buttons:
            b.disabled = busy
        self.progress.visible = busy
        self.progress_text.visible = busy
        if busy:
            self.progress.value = 0.0
            self.progress.animated = True
            self.progress_text.content = f"Running: {safe_text(name)}..."
        else:  # a refit that failed, or never came, leaves no figure stale (figures_held)
            self._catch_up_figures()

    def set_progress(self, message: str, fraction) -> None:
        self.progress_text.content = safe_text(message)
        if fraction is not None:
            self.progress.animated = False
            self.progress.value = float(np.clip(100.0 * fraction, 0, 100))
        else:
            self.progress.animated = True

    def refresh(self, kinds=("all",)) -> None:
        """Show what changed (``kinds``: :class:`~magcal_workbench.events.Change` members, or ``"all"``); the
        texts of the model loop are the active model session's (:func:`magcal_workbench.looptext.loop_text`)."""
        ctrl = self.ctrl()
        kinds = set(kinds)
        live = self.live()
        self.show_alarm()
        self.status.content = status_markdown(ctrl) if live is None or not live.active else LIVE_STATUS
        self.show_guide()
        if _asks(kinds, Change.MESSAGE):
            self.message.content = ctrl.message
        self.legend.content = self.on.legend_html()
        for tab in self.tab_panels:  # the built-in tabs made as panels: their texts, the loop's (the catalogue's
            tab.refresh(kinds)  # boxes before the state is shown in them)
        if _asks(kinds, Change.MODEL, Change.DATA, Change.EFFECTS):
            self.show_state()
        self.vector_panel.refresh(kinds)
        self._refresh_figures(kinds, live)

    def _refresh_figures(self, kinds: set, live) -> None:
        """The cockpit's figures (left to the refit that follows a change of the selection, :meth:`figures_held`)."""
        if live is not None and live.active:
            self.show_live_texts(live)  # the tabs describe the stream, not the file open before it
        elif kinds == {Change.SELECTION} and self._figures_held:
            self._figures_stale = True  # the refit that follows draws them
        elif _asks(
            kinds, Change.RESULT, Change.SELECTION, Change.DATA, Change.SETTINGS, Change.MODEL, Change.VECTOR
        ) or (_asks(kinds, Change.COMPENSATION, Change.DIAGNOSIS) and self.ctrl().compensation_loop()):
            # (vector: the table shows the vector mode's floor; a compensation: its FOM; unchanged figures stay)
            self._figures_stale = False
            self.on.draw_cockpit()

    @contextmanager
    def figures_held(self, held: bool = True):
        """Within: a change of the selection leaves the cockpit's figures (the table, |B| against time, the
        histogram) to the refit that follows it, which redraws them with its result (at 4 x 1e5 samples
        the figures take about as long as the refit). The scene's colours and the texts follow at once.

        Figures left are drawn when the next job ends (:meth:`set_busy`), whatever its outcome, or at once if the
        block fails, so they never stay stale.
        """
        self._figures_held = held
        try:
            yield
        except BaseException:
            self._figures_held = False
            self._catch_up_figures()
            raise
        finally:
            self._figures_held = False

    def _catch_up_figures(self) -> None:
        if self._figures_stale:
            self._figures_stale = False
            self.on.draw_cockpit()

    def show_live_texts(self, live) -> None:
        """During a live session every tab's figures are the stream's: the data line, the per-sensor figures of
        the live fit, and a note where a tab's tools wait for the recording to be opened."""
        self.data_info.content = live_data_markdown(live)
        self.sensors_table.content = live_sensors_markdown(live)
        self.history.content = LIVE_TAB_NOTE
        self.candidates.content = LIVE_TAB_NOTE
        self.candidate_evidence.content = ""
        self.quality.content = LIVE_TAB_NOTE
        fit = live.fit
        self.noise_info.content = (
            f"**Noise (live fit):** {fmt(fit.noise_nT, 'nT', 3)} per axis, from {safe_text(fit.noise_source, 80)}  \n"
            f"Total-field floor: {fmt(fit.floor_nT, 'nT', 3)}"
            if fit is not None
            else "**Noise:** estimated with the first live fit"
        )
        self.inspect.content = LIVE_TAB_NOTE
        self.range_info.content = LIVE_TAB_NOTE
        self.reference_info.content = (
            f"_Reference used by the live fit:_ {fmt(fit.calibration.reference_total_nT, 'nT', 6)}"
            if fit is not None and fit.calibration.reference_total_nT
            else "_Reference used by the live fit:_ fitted from the stream"
        )
        for b in (self.btn_exclude_range, self.btn_include_range, self.btn_exclude_fast):
            b.disabled = True

    def show_state(self) -> None:
        """Write the session state into every bound widget (their callbacks see nothing to change)."""
        for handle, shown in self._bindings:
            handle.value = shown()

    # --- what other parts ask of the tabs built as panels --------------------------------------------------
    def view_options(self) -> dict:
        """The View tab's settings (:meth:`magcal_workbench.viewtab.ViewTab.view_options`)."""
        return self._tab_parts["view"].view_options()

    def fit_view_to_data(self) -> None:
        """Set the View tab's gains to suit the data and fit (:meth:`magcal_workbench.viewtab.ViewTab.fit_view_to_data`)."""
        self._tab_parts["view"].fit_view_to_data()

    def refresh_sessions(self) -> None:
        """The Files tab's saved sessions (:meth:`magcal_workbench.filestab.FilesTab.refresh_sessions`)."""
        self._tab_parts["files"].refresh_sessions()


def _asks(kinds: set, *wanted: Change) -> bool:
    """Whether a refresh of ``kinds`` covers one of ``wanted`` (``"all"`` covers every kind)."""
    return "all" in kinds or any(kind in kinds for kind in wanted)
