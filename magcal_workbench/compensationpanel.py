"""The compensation in the page: a scalar magnetometer beside a fluxgate, or a four-sensor cross on a moving platform,
compensated by Tolles-Lawson and the terms beyond it, judged by the figure of merit (FOM) in the maneuvers.

Calibrate tab, one section titled by the compensation the engine chose for the record (*Compensation (a scalar
magnetometer beside a fluxgate)* or *Cross compensation (four sensors on a moving platform)*): **Run the
compensation fit**, the FOM before and after with the improvement ratio, a figure (the scalar's: the band-passed
scalar before and after against time with the maneuvers shaded; the cross's: the tensor FOM per maneuver before and
after) and the FOM table (one row per heading and maneuver). Model tab, section *Compensation's steps*: the FOM per
step and **Take the last term out**. The loop's texts of both compensation modes (status, candidates with their
held-out FOM, history, terms) are here too, for :data:`magcal_workbench.looptext.LOOP_TEXTS`; each asks the active
session (:class:`~magcal_workbench.compensationmodel.CompensationBase`) for its figures and unit, never the mode.
:class:`CompensationPage` is a panel of the recipe (:data:`magcal_workbench.panelkit.PANELS`) and follows the
controller's events; the figures and tables are pure functions the tests call.
"""

from __future__ import annotations

from magcal.core.errors import MagcalError

from .actions import action
from .compensationmodel import CompensationBase, CompensationSession, band_passed_traces, model_of, split_label
from .events import Change
from .figures import fmt
from .markup import safe_code, safe_text
from .plots import add_figure

#: Colours of the traces: the scalar as recorded, and compensated.
BEFORE_COLOUR = "#ff7f0e"
AFTER_COLOUR = "#1f77b4"
#: Fill of the maneuvers' spans by kind.
MANEUVER_FILL = {"roll": "rgba(44,160,44,0.22)", "pitch": "rgba(148,103,189,0.22)", "yaw": "rgba(140,86,75,0.22)"}


def fom_table_markdown(session: CompensationBase | None) -> str:
    """The FOM table: per heading and maneuver the FOM's part before and after (the session's unit), the sums and
    the improvement ratio; what to press before a fit."""
    if session is None or not session.available:
        return ""
    result = session.result
    if result is None:
        return "_Run the compensation fit (the Step 1 button) to see the FOM per maneuver._"
    figures = session.fom_figures(result)
    if figures is None:
        return "_No maneuvers found in the record, so no FOM: " + safe_text("; ".join(result.warnings), 400) + "_"
    before, after, ratio, n = figures
    unit = session.unit
    rows = [f"| heading deg | maneuver | before {unit} | after {unit} |", "|---|---|---|---|"]
    for heading, kind, b, a in session.fom_rows():
        rows.append(f"| {heading:.0f} | {safe_text(kind, 20)} | {fmt(b)} | {fmt(a)} |")
    rows.append(f"| **FOM** | {n} maneuvers | **{fmt(before)}** | **{fmt(after)}** |")
    where = (
        "In the plot above, the maneuvers are shaded: roll green, pitch violet, yaw brown."
        if session.mode == "compensation"
        else "A maneuver's part is the root sum of squares of the seven tensor components' band-passed "
        "peak-to-peak values; the FOM sums each component over the maneuvers."
    )
    return "\n".join(rows) + f"\n\nImprovement ratio **{ratio:.3g}**. {where}"


def traces_figure(data):
    """The band-passed scalar as recorded (top) and compensated (bottom, its own scale: it is far smaller) against
    time, the maneuvers shaded by kind and each heading named once (plotly)."""
    import plotly.graph_objects as go
    from plotly.subplots import make_subplots

    fig = make_subplots(
        rows=2,
        cols=1,
        shared_xaxes=True,
        vertical_spacing=0.12,
        subplot_titles=("recorded, band-passed (nT)", "compensated, band-passed (nT)"),
    )
    if data is not None:
        t = data["time_s"]
        # the traces first: a shape is put only on a subplot that holds one
        traces = ((1, "before_nT", BEFORE_COLOUR, "recorded"), (2, "after_nT", AFTER_COLOUR, "compensated"))
        for row, key, colour, name in traces:
            line = {"color": colour, "width": 1}
            fig.add_trace(go.Scattergl(x=t, y=data[key], mode="lines", line=line, name=name), row=row, col=1)
        named = set()
        for m in data["maneuvers"]:
            x0, x1 = float(t[m.start]), float(t[min(m.stop, len(t)) - 1])
            fill = MANEUVER_FILL.get(m.kind, "rgba(0,0,0,0.08)")
            for row in (1, 2):
                fig.add_vrect(x0=x0, x1=x1, fillcolor=fill, line_width=0, layer="above", row=row, col=1)
            heading = (round(m.heading_deg / 10.0) * 10) % 360
            if heading not in named:  # each heading named once, at its first maneuver
                named.add(heading)
                label = f"heading {heading:.0f}°"
                fig.add_annotation(
                    x=x0, y=1.0, yref="y domain", text=label, showarrow=False, xanchor="left", row=1, col=1
                )
        fig.update_xaxes(title_text="time (s)", row=2, col=1)
    fig.update_layout(
        height=380,
        margin={"l": 45, "r": 10, "t": 30, "b": 45},
        showlegend=False,
        template="plotly_white",
    )
    fig.update_annotations(font_size=10)
    return fig


def maneuvers_figure(session: CompensationBase | None):
    """The FOM per maneuver before and after the compensation (bars on a log scale, the session's unit; the
    noise's floor is the diagnosis's, in the candidates' text) (plotly): the cross's figure."""
    import plotly.graph_objects as go

    fig = go.Figure()
    rows = [] if session is None else session.fom_rows()
    labels = [f"{heading:.0f}° {kind}" for heading, kind, _, _ in rows]
    for k, (name, colour) in enumerate((("before", BEFORE_COLOUR), ("compensated", AFTER_COLOUR))):
        if rows:
            fig.add_trace(go.Bar(x=labels, y=[row[2 + k] for row in rows], name=name, marker_color=colour))
    unit = "nT" if session is None else session.unit
    fig.update_layout(
        height=360,
        barmode="group",
        margin={"l": 50, "r": 10, "t": 20, "b": 70},
        yaxis={"type": "log", "title": f"tensor FOM per maneuver ({unit})"},
        legend={"orientation": "h", "y": 1.08, "x": 0.0},
        template="plotly_white",
    )
    fig.update_xaxes(tickangle=-60, tickfont={"size": 9})
    return fig


def figure_of(session: CompensationBase):
    """The section's figure for ``session`` after a fit: the scalar's traces, the cross's maneuvers."""
    if isinstance(session, CompensationSession):
        return traces_figure(band_passed_traces(session))
    return maneuvers_figure(session)


# --- the loop's texts of the compensation modes (magcal_workbench.looptext.LOOP_TEXTS) ----------------------------
def status_markdown(ctrl, figures=None) -> str:
    """The status: the FOM before -> after and the improvement ratio, the terms beyond TL; what to press before."""
    session = model_of(ctrl)
    if session is None or session.result is None:
        return "_Compensation: not fitted yet (the Step 1 button fits Tolles-Lawson)._"
    result = session.result
    terms = ", ".join(session.result_labels(result)) or "none"
    found = session.fom_figures(result)
    if found is None:
        return f"**Compensation fitted**, no maneuvers found (no FOM)  \nTerms beyond Tolles-Lawson: {safe_text(terms)}"
    before, after, ratio, n = found
    what = "Compensation FOM" if session.unit == "nT" else "Cross compensation, tensor FOM"
    return (
        f"**{what}: {fmt(before)} -> {fmt(after)} {session.unit}** (improvement ratio {ratio:.3g}, {n} maneuvers)  \n"
        f"Terms beyond Tolles-Lawson: {safe_text(terms)}"
    )


def header_markdown(ctrl, n_kept: int, n_samples: int) -> str:
    """The compact table the panel opens with, on a compensation flight: the compensation's FOM before (the raw
    scalar, or the cross's raw tensor) and after, its improvement ratio and the floor the noise leaves (after a
    diagnosis), in place of the total-field fit's ``|y| - F`` figures, which do not judge a compensation."""
    session = model_of(ctrl)
    kept = f"{n_kept} of {n_samples} samples kept"
    if session is None or session.result is None:
        return (
            f"**Now**: {kept}; {session.words if session else 'compensation'} not fitted yet (the Step 1 button fits "
            "Tolles-Lawson; its figure of merit, the FOM in the maneuvers, shows here)"
        )
    unit, figures = session.unit, session.fom_figures(session.result)
    if figures is None:
        return f"**Now**: {kept}; {session.words} fitted, no maneuvers found (no FOM)"
    before, after, ratio, n = figures
    what = "scalar" if unit == "nT" else "tensor"
    rows = [
        f"| | {what} FOM {unit} | improvement ratio |",
        "|---|---|---|",
        f"| raw | {fmt(before, digits=4)} | |",
        f"| **compensated** | **{fmt(after, digits=4)}** | {ratio:.3g} |",
    ]
    floor = ""
    if session.diagnosis is not None:
        floor = f"; {session.noise_words} leaves {fmt(session.diagnosis_figures(session.diagnosis)[1], unit, 3)}"
    return f"**Now**: {kept}; {session.words}, {n} maneuvers{floor}\n\n" + "\n".join(rows)


def legend_title(ctrl, by: str) -> str:
    """The scene's colour legend's title on a compensation flight (plain text): the band-passed compensated scalar
    once the scalar's compensation is drawn (``by == "compensation"``), with its FOM; else what the colours are (the
    raw fluxgate's ``|y| - F``), and that the compensation is judged by its FOM in the table, not by them."""
    session = model_of(ctrl)
    figures = None if session is None or session.result is None else session.fom_figures(session.result)
    fom = "" if figures is None else f"FOM {fmt(figures[1], session.unit if session else '', 3)}"
    if by == "compensation":
        return "band-passed compensated scalar (compensation" + (f", {fom}" if fom else "") + ")"
    judged = f"its {fom} in the table" if fom else "by its FOM once fitted"
    return f"raw fluxgate |y| - F (not the compensation's figure: {judged})"


def candidates_markdown(ctrl) -> str:
    """The diagnosis's verdict and the candidates with their held-out FOM, or what to press."""
    session = model_of(ctrl)
    if session is None or session.diagnosis is None:
        return "_Press Diagnose to judge the terms beyond Tolles-Lawson on held-out maneuvers._"
    found = session.diagnosis
    unit = session.unit
    held_out, floor = session.diagnosis_figures(found)
    scheme = "held-out maneuvers" if found.validation.get("scheme") == "maneuvers" else "the other flight"
    lines = [
        f"**Verdict:** {safe_code(found.verdict)} (held-out FOM {fmt(held_out, unit)}, {session.noise_words} "
        f"leaves {fmt(floor, unit)})",
        f"_{safe_text(found.summary, 1000)}_",
        "",
        f"Each term refitted and judged on {scheme} (held-out FOM, {unit}, without → with it); its evidence under "
        "*Candidate* below.",
        "",
        f"| round | term | held-out FOM {unit} | advised? |",
        "|---|---|---|---|",
    ]
    for c in found.candidates:
        if not c.judged:
            lines.append(
                f"| - | {safe_code(session.candidate_label(c))} | not judged: {safe_text(c.reason, 160)} | - |"
            )
            continue
        mark = "**advised**" if c.recommended else "no"
        before, after = session.candidate_figures(c)
        lines.append(f"| {c.round} | {safe_code(session.candidate_label(c))} | {fmt(before)}→{fmt(after)} | {mark} |")
    lines += [f"- warning: {safe_text(w, 600)}" for w in found.warnings]
    return "\n".join(lines)


def candidate_markdown(ctrl, label: str) -> str:
    """The chosen term's evidence and what it is."""
    session = model_of(ctrl)
    if session is None or session.diagnosis is None:
        return ""
    found = session.diagnosis
    for c in found.candidates:
        if session.candidate_label(c) == label:
            what = safe_text(session.terms.get(c.name, ""), 300)
            said = safe_text(c.evidence or c.reason, 600)
            return f"**{safe_text(label)}** ({what}): {said}"
    return ""


def history_markdown(ctrl) -> str:
    """The compensation's fits: the terms and the FOM before -> after per step."""
    session = model_of(ctrl)
    rows = [] if session is None else session.history()
    if session is None or not rows:
        return "_No compensation fit yet._"
    unit = session.unit
    lines = [
        f"| # | step | terms beyond TL | FOM before {unit} | FOM after {unit} | ratio |",
        "|---|---|---|---|---|---|",
    ]
    for i, r in enumerate(rows[-8:], start=max(0, len(rows) - 8)):
        lines.append(
            f"| {i} | {safe_text(r['step'], 120)} | {safe_text(', '.join(session.row_labels(r)) or 'none', 200)} | "
            f"{fmt(r['fom_before_nT'])} | {fmt(r['fom_nT'])} | {fmt(r['improvement_ratio'], digits=3)} |"
        )
    return "\n".join(lines)


def terms_markdown(ctrl) -> str:
    """The compensation's terms: Tolles-Lawson's, and those beyond it with what each is."""
    session = model_of(ctrl)
    if session is None or session.result is None:
        return "_The compensation has Tolles-Lawson's permanent, induced and eddy terms only (not fitted yet)._"
    lines = [f"**In the compensation:** {session.tl_words()}"]
    for label in session.result_labels(session.result):
        name, _ = split_label(label)
        lines.append(f"- {safe_code(label)}: {safe_text(session.terms.get(name, ''), 300)}")
    return "\n".join(lines)


class CompensationPage:
    """The compensation's sections, actions and drawing, for the compensation the engine chose for the record (the
    scalar's or the cross's: the same widgets, titled and filled by the active session).

    Parameters
    ----------
    ctrl, steps : callable
        Getters: the open data's :class:`~magcal_workbench.controller.Controller` and the
        :class:`~magcal_workbench.steps.Steps`.
    """

    def __init__(self, *, ctrl, steps):
        self._ctrl, self._steps = ctrl, steps

    @property
    def model(self) -> CompensationBase:
        """The compensation session of the opened data (the active one on a compensation flight, else the
        scalar's)."""
        session = model_of(self._ctrl())
        if session is None:
            raise MagcalError("the page has no compensation session")
        return session

    def attach(self, panels) -> None:
        """Build the sections into the Calibrate and Model tabs."""
        import plotly.graph_objects as go

        gui = panels.gui
        self.folder = panels.section("Calibrate", self.model.section_title, True)
        with self.folder:
            self.status = gui.add_markdown("")
            self.btn_fit = panels.button(
                "Run the compensation fit (Tolles-Lawson)",
                panels.on.do_compensation_fit,
                engine=True,
                color="teal",
                hint="magcal's compensation mode: Tolles-Lawson's permanent, induced and eddy terms (per sensor on "
                "a cross), band-passed, with the terms beyond it the model holds; judged by the FOM (the "
                "band-passed peak-to-peak values in the maneuvers: the scalar's, or the cross's tensor)",
            )
            self.traces = add_figure(gui, go.Figure(), aspect=1.4)
            self.table = gui.add_markdown("")
        self.steps_folder = panels.section("Model", "Compensation's steps", True)
        with self.steps_folder:
            self.history = gui.add_markdown("")
            self.btn_remove = panels.button(
                "Take the last term out (compensation)",
                panels.on.do_remove_compensation_term,
                engine=True,
                hint="Refit the compensation without the term beyond Tolles-Lawson added last",
            )
        self.refresh()

    @action
    def do_compensation_fit(self, event):
        """Calibrate tab (and the guide's Step 1): the compensation fit, in the worker."""
        session = self.model
        if not session.available:
            raise MagcalError(f"the {session.words} fit " + "; ".join(session.missing()))
        self._ctrl().run_step(f"{session.words} fit", lambda inputs: session.fit(inputs=inputs))

    @action
    def do_remove_compensation_term(self, event):
        """Model tab: the compensation refitted without its last term beyond TL, in the worker."""
        session = self.model
        if not session.model_labels():
            raise MagcalError(f"the {session.title} holds no term beyond Tolles-Lawson to take out")
        self._ctrl().run_step("take a term out", lambda inputs: session.remove(inputs=inputs))

    def changed(self, kind: Change) -> None:
        """The controller's event: a new record, a fit or a diagnosis redraws the sections."""
        if kind in (Change.DATA, Change.COMPENSATION, Change.SELECTION, Change.DIAGNOSIS):
            self.refresh()

    def refresh(self) -> None:
        if not hasattr(self, "table"):
            return
        ctrl = self._ctrl()
        session = self.model
        shown = ctrl.compensation_loop() and session.available
        self.folder.visible = self.steps_folder.visible = shown
        if shown:
            self.folder.label = session.section_title
        self.status.content = status_markdown(ctrl) if shown else ""
        self.table.content = fom_table_markdown(session) if shown else ""
        self.history.content = history_markdown(ctrl) if shown else ""
        self.btn_remove.visible = shown and bool(session.effects)
        fitted = shown and session.result is not None
        self.traces.visible = fitted
        if fitted:
            self.traces.figure = figure_of(session)
