"""The vector model's widgets: the reference from a location (Calibrate tab), the
vector fit beside the total-field fit with their comparison table (Calibrate tab), and the vehicle view's toggle
(View tab).

:class:`VectorPanel` is made by :class:`~magcal_workbench.panels.Panels` and builds into its tabs where the panels
call it; like the panels it is given what it needs (the panels' widget maker, callback runner and actions), never
the app. The text is built by pure functions (``*_markdown``) the tests call directly.
"""

from __future__ import annotations

import datetime as _dt

import numpy as np

from magcal.calibration.calibration import is_transferable
from magcal.model.terms import EFFECTS

from .controller import format_number
from .markup import safe_code, safe_text
from .plots import log_axis_scales, one_step_history
from .sessionfile import ALT_RANGE_M, DATE_CHARS, LAT_RANGE_DEG, LON_RANGE_DEG
from .vectormodel import NED


def _nT(v) -> str:
    return "-" if v is None or not np.isfinite(v) else f"{v:.4g} nT"


def comparison_markdown(vm) -> str:
    """The two fits side by side (:class:`~magcal_workbench.vectormodel.VectorModel`): total-field RMS, world RMS per
    N/E/D, the mounting, the attitude noise, and the total-field fit's undetermined warning where it applies."""
    if vm.attitude_kind() is None:
        return ""
    scalar, vector = vm.scalar_row(), vm.vector_row()
    fitted = vm.result is not None
    sc_total = _nT(scalar.total_field_rms_nT) if scalar.total_field_rms_nT is not None else "not fitted yet"
    rows = [
        "| on the kept samples | total-field fit | vector fit (attitude-aided) |",
        "|---|---|---|",
        f"| total-field RMS | {sc_total} | {_nT(vector.total_field_rms_nT) if fitted else 'not run yet'} |",
    ]
    if fitted:
        rows.append(f"| samples fitted | - | {safe_text(vector.samples, 200)} |")
    for k, c in enumerate(NED):
        world = _nT(vector.world_rms_nT[k]) if vector.world_rms_nT is not None else "-"
        rows.append(f"| world {c} RMS | n/a: its rotation is unknown | {world} |")
    mounting = safe_text("; ".join(vector.mounting), 400) if vector.mounting else "-"
    rows.append(f"| mounting found | not determined (a gauge) | {mounting} |")
    noise = safe_text("; ".join(vector.attitude_noise), 300) if vector.attitude_noise else "-"
    rows.append(f"| attitude noise | - | {noise} |")
    text = "\n".join(rows)
    if scalar.undetermined:
        text += "\n\n⚠ **The total-field fit is undetermined here**: " + safe_text(scalar.undetermined[0], 600)
    for w in vector.warnings:
        text += f"\n- vector fit: {safe_text(w, 600)}"
    return text


def _pair(before, after) -> str:
    return f"{_num(before)}→{_num(after)}"


def _num(v) -> str:
    return "-" if v is None or not np.isfinite(v) else f"{v:.4g}"


def vector_candidates_markdown(d, held=None) -> str:
    """The vector diagnosis (:class:`magcal.diagnosis.vector.VectorDiagnosis`) as the Model tab shows it, the
    counterpart of the total-field diagnosis's: verdict with the world and |B| figures against their noise, the
    summary, how candidates were judged, and the candidates for the model as it is (the first round), each with
    its world RMS in-sample and on the later part, without -> with it."""
    floor = d.noise.world_floor_nT
    noise_f = d.noise.sigma_nT
    if held is not None:  # the record's floor (magcal_workbench.floors), the figure every place shows
        floor, noise_f = held.world_floor_nT, held.total_noise_nT
    lines = [
        f"**Verdict:** {safe_code(d.verdict, 40)} on the vector fit (world RMS {_nT(d.base.world_nT)}, noise floor "
        f"{_nT(floor)}; |B| {_nT(d.base.total_nT)}, noise {_nT(noise_f)})",
        f"_{safe_text(d.summary, 1500)}_",
    ]
    v = d.validation or {}
    if v.get("n_later"):
        lines.append(
            f"\nHeld-out check: each candidate fitted on the first {100 * (1 - v['later_fraction']):.0f} % of the "
            f"kept samples and applied to the last {v['n_later']} as `magcal apply` applies it; only candidates "
            "whose gain holds there are recommended."
        )
    elif v.get("skipped"):
        lines.append(f"\nHeld-out check not done: {safe_text(v['skipped'], 300)}")
    for w in d.warnings:
        lines.append(f"- warning: {safe_text(w, 1000)}")
    first = [c for c in d.candidates if c.round == 1][:8]
    if first:
        lines += ["", "| effect | dBIC | world nT | later nT | advice |", "|---|---|---|---|---|"]
        for c in first:
            later = "-" if c.later is None else _num(c.later[1].world_nT)
            lines.append(
                f"| {safe_code(c.label, 80)} | {format_number(c.delta_bic)} | {_num(c.in_sample[1].world_nT)} | "
                f"{later} | {advice_words(c)} |"
            )
        judged = next((c for c in first if c.later is not None), None)
        without = f"{_nT(d.base.world_nT)} in-sample" + (
            f", {_nT(judged.later[0].world_nT)} on the later part" if judged is not None else ""
        )
        lines.append(
            "\n_world: RMS per north/east/down component with the effect; later: fitted on the earlier part, "
            f"applied to the later; without any: {without}. Choose a candidate below for why._"
        )
    else:
        lines.append("_No candidate: the catalogue has no effect the vector fit can take on these data._")
    if d.final is not None and d.explained_by:
        lines.append(
            f"\nWith {', '.join(f'{safe_code(e, 80)}' for e in d.explained_by)}: world {_nT(d.base.world_nT)} → "
            f"{_nT(d.final.world_nT)}, |B| {_nT(d.base.total_nT)} → {_nT(d.final.total_nT)}"
        )
    if d.remaining:
        lines.append("\n**Structure left:** " + "; ".join(safe_text(s.text(), 300) for s in d.remaining[:3]))
    return "\n".join(lines)


def advice_words(c) -> str:
    """A vector candidate's advice in a word or two for the table (:class:`magcal.diagnosis.vector.VectorCandidate`;
    the whole reason is shown when it is chosen)."""
    if c.recommended:
        return "**recommended**"
    if c.holds is False:
        return "⚠ does not hold"
    if c.holds:
        return "holds"
    return "not judged" if c.supported else "not supported"


def vector_candidate_markdown(d, label: str) -> str:
    """The evidence of the chosen candidate of a vector diagnosis, and why it is (not) recommended."""
    if d is None:
        return ""
    c = next((c for c in d.candidates if c.label == label and c.round == 1), None)
    if c is None:
        return ""
    text = f"**{safe_text(label)}** (dBIC {format_number(c.delta_bic)}): {safe_text(c.evidence or c.quote, 1000)}"
    if c.recommended:
        text += "  \n**Recommended**: it improves the later part of the record as `magcal apply` applies it."
    elif c.why:
        text += f"  \n{'⚠ ' if c.holds is False else ''}{safe_text(c.why, 400)}"
    return text


def vector_model_markdown(vm) -> str:
    """The vector model's effects (what Diagnose and Add work on for these data), each marked instrument or
    record-only."""
    if not vm.effects:
        return (
            "**Vector model** (Diagnose and Add work on it): the base terms only (bias, matrix, mounting into the "
            "body frame)."
        )
    rows = ["**Vector model** (Diagnose and Add work on it): the base terms and"]
    for label in vm.effects:
        cls = EFFECTS.get(label.partition(":")[0])
        carried = True if cls is None else is_transferable(cls)
        rows.append(
            f"- {safe_code(label, 80)} **{'instrument' if carried else 'record-only'}**: "
            + ("carried to new data" if carried else "this record only: dropped on new data")
        )
    return "\n".join(rows)


def vector_status_markdown(vm) -> str:
    """The status line of the vector model: its world RMS per N/E/D and |B| on the kept samples, and its
    effects; empty before a vector fit."""
    if vm.result is None:
        return ""
    row = vm.vector_row()
    world = " / ".join(_num(v) for v in row.world_rms_nT) if row.world_rms_nT is not None else "-"
    floor = f" (floor {_nT(vm.floor_nT)})" if vm.floor_nT else ""
    effects = ", ".join(f"{safe_code(e, 80)}" for e in vm.effects) or "base terms only"
    return (
        f"**Vector model: world RMS N/E/D {world} nT**{floor}, |B| {_nT(row.total_field_rms_nT)}  \n"
        f"Vector model: {effects}"
    )


def vector_history_markdown(state, last: int = 6) -> str:
    """The vector model's last fits: world RMS per N, E, D and |B| (nT, the samples fitted), and what changed."""
    steps = state.vector_history
    if not steps:
        return ""
    rows = [
        "**Vector model** (attitude-aided):",
        "",
        "| # | step | N nT | E nT | D nT | \\|B\\| nT | what changed |",
        "|---|---|---|---|---|---|---|",
    ]
    start = max(0, len(steps) - last)
    for i, r in enumerate(steps[start:], start=start):
        n, e, dn = (_num(v) for v in r.world_rms_nT)
        rows.append(
            f"| {i} | {safe_text(r.step, 120)} | {n} | {e} | {dn} | {_num(r.total_rms_nT)} | "
            f"{safe_text(r.changes, 300)} |"
        )
    return "\n".join(rows)


def vector_rms_plot_data(vm):
    """``(step, N, E, D, |B|, floor)`` arrays (nT) for the vector model's history plot: the world RMS per component
    and |B| of each fit, and the world noise floor the last diagnosis found (drawn across every step; NaN before
    one)."""
    steps = vm.ctrl.state.vector_history
    x = np.arange(len(steps), dtype=float)
    world = np.array([[np.nan if v is None else v for v in r.world_rms_nT] for r in steps], dtype=float).reshape(-1, 3)
    total = np.array([np.nan if r.total_rms_nT is None else r.total_rms_nT for r in steps], dtype=float)
    floor = np.full(len(steps), np.nan if not vm.floor_nT else float(vm.floor_nT))
    return one_step_history(x, (world[:, 0], world[:, 1], world[:, 2], total, floor), floors=(4,))


def availability_markdown(vm) -> str:
    """What the data offer the vector fit: the attitude and where the reference vector comes from, or what is
    missing."""
    kind = vm.attitude_kind()
    if kind is None:
        return (
            "_**Vector model**: these data have no attitude (`qw, qx, qy, qz` or `roll_deg, pitch_deg, yaw_deg`), "
            "so only the total-field fit applies._"
        )
    att = "quaternions `qw..qz`" if kind == "quaternion" else "`roll_deg, pitch_deg, yaw_deg`"
    missing = vm.missing()
    if missing:
        return f"**Vector model**: attitude from {att}; the fit also needs {safe_text(' and '.join(missing), 400)}"
    try:
        ref = vm.reference()
        where = "?" if ref is None else safe_text(ref.text, 400)
    except Exception as exc:  # an IGRF failure is said, not raised, in a status line
        where = f"not available ({safe_text(str(exc), 300)})"
    return f"**Vector model**: attitude from {att}; reference vector: {where}"


def location_markdown(vm) -> str:
    """The location in use (or none), and why a saved one could not be used."""
    loc = vm.location
    text = (
        f"_Location in use:_ {safe_text(loc.text(), 400)}"
        if loc is not None
        else "_No location typed: the file's reference is used (or the field magnitude is fitted)._"
    )
    if vm.from_site():
        text += (
            "  \n_From the file's `# site:` line._ Change the values above and press *Use this location (IGRF)* to "
            "use another place or date, or *Forget the location*."
        )
    if vm.location_note:
        text += f"  \n{vm.location_note}"
    return text


class VectorPanel:
    """The vector model's widgets, built into the panels' tabs.

    Parameters
    ----------
    panels : magcal_workbench.panels.Panels
        Gives ``w`` (the checked widget maker), ``_button``, ``handle``, ``on`` (the actions: ``do_use_location``,
        ``do_forget_location``, ``do_vector_fit``, ``do_vehicle_view``, ``do_vehicle_options``, ``vehicle_text``)
        and ``ctrl``.
    """

    def __init__(self, panels):
        self.p = panels

    # --- construction --------------------------------------------------------------------------------------
    def build_location(self, gui) -> None:
        """Calibrate tab, under the reference: a place and date -> IGRF (the scalar and the vector reference)."""
        p = self.p
        with gui.add_folder("Reference from a location (IGRF)", expand_by_default=False):
            self.lat = p.w.number(
                "Latitude deg", 0.0, min=LAT_RANGE_DEG[0], max=LAT_RANGE_DEG[1], step=0.0001, hint="north positive"
            )
            self.lon = p.w.number(
                "Longitude deg", 0.0, min=LON_RANGE_DEG[0], max=LON_RANGE_DEG[1], step=0.0001, hint="east positive"
            )
            self.alt = p.w.number(
                "Altitude m",
                0.0,
                min=ALT_RANGE_M[0],
                max=ALT_RANGE_M[1],
                step=1.0,
                hint="height above the WGS84 ellipsoid, m",
            )
            self.date = p.w.text(
                "Date",
                _dt.date.today().isoformat(),
                max_chars=DATE_CHARS,
                hint="YYYY-MM-DD or a decimal year (2024.5), within the IGRF model's years",
            )
            self.btn_location = p._button(gui, "Use this location (IGRF)", p.on.do_use_location, engine=False)
            self.btn_forget = p._button(gui, "Forget the location", p.on.do_forget_location, engine=False)
            self.location_info = gui.add_markdown("")

    def clear_location_inputs(self) -> None:
        """The location inputs as they start (0 N, 0 E, 0 m, today): other data opened, whose location (the
        session's, or its file's site) the next refresh shows if it has one; the old record's place is not shown as
        the new one's."""
        for widget, value in (
            (self.lat, 0.0),
            (self.lon, 0.0),
            (self.alt, 0.0),
            (self.date, _dt.date.today().isoformat()),
        ):
            if widget.value != value:
                widget.value = value

    def build_calibrate(self, gui) -> None:
        """Calibrate tab, after the total-field steps: the vector fit and the two fits side by side."""
        p = self.p
        self.folder = gui.add_folder("Vector model (attitude-aided)", expand_by_default=True)
        with self.folder:
            self.info = gui.add_markdown("")
            self.btn_vector = p._button(
                gui,
                "Run the vector fit (attitude-aided)",
                p.on.do_vector_fit,
                color="teal",
                hint="magcal's fit_vector: bias, matrix and the sensor's mounting into the body frame, from the "
                "attitude and the field vector; shown beside the total-field fit",
            )
            self.table = gui.add_markdown("")

    def build_model(self, gui) -> None:
        """Model tab, under Add: the vector model's Take out, and its history plot (world RMS per N, E, D and |B|
        per fit, with the world noise floor), shown instead of the total-field one when the loop works on the vector
        model."""
        p = self.p
        self.btn_remove = p._button(
            gui,
            "Take the last effect out (vector model)",
            p.on.do_remove_vector_effect,
            visible=False,
            hint="Refit the vector model without the effect added last",
        )
        self.rms_plot = gui.add_uplot(
            data=tuple(np.array([0.0, 1.0]) if k == 0 else np.array([np.nan, np.nan]) for k in range(6)),
            series=(
                {"label": "step"},
                {"label": "N nT", "stroke": "#1f77b4", "width": 2, "points": {"show": True, "size": 6}},
                {"label": "E nT", "stroke": "#2ca02c", "width": 2, "points": {"show": True, "size": 6}},
                {"label": "D nT", "stroke": "#9467bd", "width": 2, "points": {"show": True, "size": 6}},
                {"label": "|B| nT", "stroke": "#ff7f0e", "width": 2, "points": {"show": True, "size": 6}},
                {
                    "label": "world floor nT",
                    "stroke": "#d62728",
                    "dash": [6, 4],
                    "width": 1.5,
                    "points": {"show": False},
                },
            ),
            scales={"x": {"time": False}, "y": {"distr": 3, "log": 10}},
            axes=({"label": "vector step (see the step history)", "incrs": [1, 2, 5, 10, 20, 50]}, {"label": "nT"}),
            padding=(14, 16, 0, 0),
            title="World RMS per step (vector fit)",
            aspect=1.4,
            visible=False,
        )

    def build_view(self, gui) -> None:
        """View tab: the vehicle view's toggle and its residual exaggeration."""
        p = self.p
        with gui.add_folder("Vehicle view", expand_by_default=True):
            self.vehicle_on = gui.add_checkbox(
                "Show the vehicle view",
                False,
                hint="The body turned by its attitude, the model and the measured field in world axes N, E, D, and "
                "their difference; the time window's Play flies it through the record",
            )
            self.vehicle_gain = p.w.number(
                "Residual arrows x (0: auto)",
                0.0,
                min=0.0,
                max=1e7,
                step=1.0,
                hint="exaggeration of the red arrow; 0 = automatic",
            )
            self.vehicle_info = gui.add_markdown("")
        self.vehicle_on.on_update(lambda e: p.handle(p.on.do_vehicle_view, e))
        self.vehicle_gain.on_update(lambda e: p.handle(p.on.do_vehicle_options, e))

    # --- refresh -------------------------------------------------------------------------------------------
    def refresh(self, kinds) -> None:
        """Write what changed into the widgets (``kinds`` as :meth:`Panels.refresh` takes them)."""
        kinds = set(kinds)
        everything = "all" in kinds
        vm = self.p.ctrl().vector
        has_attitude = vm.attitude_kind() is not None
        if "vector" in kinds:  # a location sets the Reference field box: show it
            self.p.show_state()
        if everything or kinds & {"data", "vector", "settings"}:
            self.folder.visible = not self.p.ctrl().compensation_loop()  # a compensation flight: not this fit
            self.info.content = availability_markdown(vm)
            self.location_info.content = location_markdown(vm)
            self.btn_vector.visible = has_attitude
        if everything or kinds & {"data", "vector", "result", "selection", "settings"}:
            self.table.content = comparison_markdown(vm)
            self.table.visible = vm.available or vm.result is not None
            loop = self.p.ctrl().vector_loop()
            self.rms_plot.visible = loop
            # the total-field history plot: its counterpart (neither on a compensation flight)
            self.p.rms_plot.visible = not loop and not self.p.ctrl().compensation_loop()
            self.btn_remove.visible = loop and bool(vm.effects)
            if loop:
                data = vector_rms_plot_data(vm)
                if len(data[0]):
                    self.rms_plot.data = data
                    self.rms_plot.scales = log_axis_scales(data)
        if everything or "data" in kinds:
            loc = vm.location
            if loc is not None:  # show the session's place (the widgets' callbacks do nothing)
                self.lat.value, self.lon.value, self.alt.value, self.date.value = (
                    loc.lat_deg,
                    loc.lon_deg,
                    loc.alt_m,
                    loc.date,
                )
            self.refresh_vehicle()

    def refresh_vehicle(self) -> None:
        self.vehicle_info.content = self.p.on.vehicle_text()
