"""The compensation in the page: a scalar magnetometer beside a fluxgate, compensated by Tolles-Lawson and the terms
beyond it, judged by the figure of merit (FOM) in the maneuvers.

Calibrate tab, section *Compensation (a scalar beside a fluxgate)*: **Run the compensation fit**, the FOM before
and after with the improvement ratio, the band-passed scalar before and after against time with the maneuvers
marked (plotly), and the FOM table (one row per heading and maneuver). The loop's texts of the compensation mode
(status, candidates with their held-out FOM, history, terms) are here too, for
:data:`magcal_workbench.looptext.LOOP_TEXTS`. :class:`CompensationPage` is a panel of the recipe
(:data:`magcal_workbench.panelkit.PANELS`) and follows the controller's events; the figures and tables are pure
functions the tests call.
"""

from __future__ import annotations

from magcal.core.errors import MagcalError

from .actions import action
from .compensationmodel import TERMS, CompensationSession, band_passed_traces, model_of
from .events import Change
from .figures import fmt
from .markup import safe_code, safe_text
from .plots import add_figure

#: Colours of the traces: the scalar as recorded, and compensated.
BEFORE_COLOUR = "#ff7f0e"
AFTER_COLOUR = "#1f77b4"
#: Fill of the maneuvers' spans by kind.
MANEUVER_FILL = {"roll": "rgba(44,160,44,0.22)", "pitch": "rgba(148,103,189,0.22)", "yaw": "rgba(140,86,75,0.22)"}


def fom_table_markdown(session: CompensationSession | None) -> str:
    """The FOM table: per heading and maneuver the band-passed peak-to-peak before and after (nT), the sums and
    the improvement ratio; what to press before a fit."""
    if session is None or not session.available:
        return ""
    result = session.result
    if result is None:
        return "_Run the compensation fit (the Step 1 button) to see the FOM per maneuver._"
    fom = result.fom
    if fom is None:
        return "_No maneuvers found in the record, so no FOM: " + safe_text("; ".join(result.warnings), 400) + "_"
    rows = ["| heading deg | maneuver | before nT | after nT |", "|---|---|---|---|"]
    for m, b, a in zip(fom.after.maneuvers, fom.before.peak_to_peak_nT, fom.after.peak_to_peak_nT):
        rows.append(f"| {m.heading_deg:.0f} | {safe_text(m.kind, 20)} | {fmt(b)} | {fmt(a)} |")
    rows.append(f"| **FOM** | {len(fom.after.maneuvers)} maneuvers | **{fmt(fom.before.fom_nT)}** | "
                f"**{fmt(fom.after.fom_nT)}** |")  # fmt: skip
    return (
        "\n".join(rows)
        + f"\n\nImprovement ratio **{fom.improvement_ratio:.3g}**. In the plot above, the maneuvers are shaded: roll "
        "green, pitch violet, yaw brown."
    )


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


# --- the loop's texts of the compensation mode (magcal_workbench.looptext.LOOP_TEXTS) ----------------------------
def status_markdown(ctrl, figures=None) -> str:
    """The status: the FOM before -> after and the improvement ratio, the terms beyond TL; what to press before."""
    session = model_of(ctrl)
    if session is None or session.result is None:
        return "_Compensation: not fitted yet (the Step 1 button fits Tolles-Lawson)._"
    result = session.result
    terms = ", ".join(result.calibration.effects) or "none"
    if result.fom is None:
        return f"**Compensation fitted**, no maneuvers found (no FOM)  \nTerms beyond Tolles-Lawson: {safe_text(terms)}"
    fom = result.fom
    return (
        f"**Compensation FOM: {fmt(fom.before.fom_nT)} -> {fmt(fom.after.fom_nT)} nT** (improvement ratio "
        f"{fom.improvement_ratio:.3g}, {len(fom.after.maneuvers)} maneuvers)  \n"
        f"Terms beyond Tolles-Lawson: {safe_text(terms)}"
    )


def candidates_markdown(ctrl) -> str:
    """The diagnosis's verdict and the candidates with their held-out FOM, or what to press."""
    session = model_of(ctrl)
    found = None if session is None else session.diagnosis
    if found is None:
        return "_Press Diagnose to judge the terms beyond Tolles-Lawson on held-out maneuvers._"
    scheme = "held-out maneuvers" if found.validation.get("scheme") == "maneuvers" else "the other flight"
    lines = [
        f"**Verdict:** {safe_code(found.verdict)} (held-out FOM {fmt(found.fom_held_out_nT, 'nT')}, the scalar's "
        f"noise leaves {fmt(found.floor_fom_nT, 'nT')})",
        f"_{safe_text(found.summary, 1000)}_",
        "",
        f"Each term refitted and judged on {scheme} (held-out FOM, nT, without → with it); its evidence under "
        "*Candidate* below.",
        "",
        "| round | term | held-out FOM nT | advised? |",
        "|---|---|---|---|",
    ]
    for c in found.candidates:
        if not c.judged:
            lines.append(f"| - | {safe_code(c.name)} | not judged: {safe_text(c.reason, 160)} | - |")
            continue
        mark = "**advised**" if c.recommended else "no"
        lines.append(f"| {c.round} | {safe_code(c.name)} | {fmt(c.fom_before_nT)}→{fmt(c.fom_after_nT)} | {mark} |")
    lines += [f"- warning: {safe_text(w, 600)}" for w in found.warnings]
    return "\n".join(lines)


def candidate_markdown(ctrl, label: str) -> str:
    """The chosen term's evidence and what it is."""
    session = model_of(ctrl)
    found = None if session is None else session.diagnosis
    if found is None:
        return ""
    for c in found.candidates:
        if c.name == label:
            what = safe_text(TERMS.get(label, ""), 300)
            said = safe_text(c.evidence or c.reason, 600)
            return f"**{safe_text(label)}** ({what}): {said}"
    return ""


def history_markdown(ctrl) -> str:
    """The compensation's fits: the terms and the FOM before -> after per step."""
    session = model_of(ctrl)
    rows = [] if session is None else session.history()
    if not rows:
        return "_No compensation fit yet._"
    lines = ["| # | step | terms beyond TL | FOM before nT | FOM after nT | ratio |", "|---|---|---|---|---|---|"]
    for i, r in enumerate(rows[-8:], start=max(0, len(rows) - 8)):
        lines.append(
            f"| {i} | {safe_text(r['step'], 120)} | {safe_text(', '.join(r['effects']) or 'none', 200)} | "
            f"{fmt(r['fom_before_nT'])} | {fmt(r['fom_nT'])} | {fmt(r['improvement_ratio'], digits=3)} |"
        )
    return "\n".join(lines)


def terms_markdown(ctrl) -> str:
    """The compensation's terms: Tolles-Lawson's, and those beyond it with what each is."""
    session = model_of(ctrl)
    result = None if session is None else session.result
    if result is None:
        return "_The compensation has Tolles-Lawson's permanent, induced and eddy terms only (not fitted yet)._"
    tl = result.calibration.tl
    lines = [
        f"**In the compensation:** Tolles-Lawson ({safe_text(', '.join(tl.terms))}: {len(tl.labels)} coefficients)"
    ]
    for name in result.calibration.effects:
        lines.append(f"- {safe_code(name)}: {safe_text(TERMS.get(name, ''), 300)}")
    return "\n".join(lines)


class CompensationPage:
    """The compensation's section, action and drawing.

    Parameters
    ----------
    ctrl, steps : callable
        Getters: the open data's :class:`~magcal_workbench.controller.Controller` and the
        :class:`~magcal_workbench.steps.Steps`.
    """

    def __init__(self, *, ctrl, steps):
        self._ctrl, self._steps = ctrl, steps

    @property
    def model(self) -> CompensationSession:
        """The compensation session of the opened data (the controller's ``compensation``)."""
        return self._ctrl().compensation

    def attach(self, panels) -> None:
        """Build the section into the Calibrate tab."""
        import plotly.graph_objects as go

        gui = panels.gui
        self.folder = panels.section("Calibrate", "Compensation (a scalar magnetometer beside a fluxgate)", True)
        with self.folder:
            self.status = gui.add_markdown("")
            self.btn_fit = panels.button(
                "Run the compensation fit (Tolles-Lawson)",
                panels.on.do_compensation_fit,
                engine=True,
                color="teal",
                hint="magcal's compensation mode: Tolles-Lawson's permanent, induced and eddy terms from the "
                "fluxgate's direction cosines, band-passed, with the terms beyond it the model holds; judged by "
                "the FOM (the 12 band-passed peak-to-peak values in the maneuvers)",
            )
            self.traces = add_figure(gui, go.Figure(), aspect=1.4)
            self.table = gui.add_markdown("")
        self.refresh()

    @action
    def do_compensation_fit(self, event):
        """Calibrate tab (and the guide's Step 1): the compensation fit, in the worker."""
        session = self.model
        if not session.available:
            raise MagcalError("the compensation fit " + "; ".join(session.missing()))
        self._ctrl().run_step("compensation fit", lambda inputs: session.fit(inputs=inputs))

    def changed(self, kind: Change) -> None:
        """The controller's event: a new record, a fit or a diagnosis redraws the section."""
        if kind in (Change.DATA, Change.COMPENSATION, Change.SELECTION, Change.DIAGNOSIS):
            self.refresh()

    def refresh(self) -> None:
        if not hasattr(self, "table"):
            return
        session = self.model
        shown = session.available
        self.folder.visible = shown
        self.status.content = status_markdown(self._ctrl()) if shown else ""
        self.table.content = fom_table_markdown(session) if shown else ""
        fitted = shown and session.result is not None
        self.traces.visible = fitted
        if fitted:
            self.traces.figure = traces_figure(band_passed_traces(session))
