"""The control panel: tabs for calibration steps, the model loop, outliers, the view, files and lessons.

Every GUI element lives on ``server.gui`` so all connected browsers share one state. Each widget's callback is
wired where the widget is made: buttons call the :class:`~magcal_workbench.app.Workbench` (which calls the controller);
a setting's widget is *bound* to the session state (:meth:`Panels._bind`), and its callback does nothing when the
widget already shows what the state holds, so :meth:`Panels.refresh` writes the state back into the widgets
without re-running anything. Text shown is built by small pure functions (``*_markdown``) that the tests call
directly. Text the workbench did not write (file names and contents, session fields, a user's effects) goes
through :mod:`workbench.markup` before it joins markdown.
"""

from __future__ import annotations

import threading
from contextlib import contextmanager

import numpy as np

from magcal.core import conventions

from . import scene as scn
from .controller import candidate_label, format_number
from .exporting import ExportSection
from .guide import guide_markdown, next_step
from .lessons import lesson_slugs, list_lessons
from .live import BAUDS, LINE_UNITS, PAGE_PORT, PAGE_RATE_HZ, PAGE_SAMPLES, PAGE_SPEED, TEMPLATE_CHARS
from .maps import SURFACE_CHOICES
from .markup import clean_text, hide_paths, safe_code, safe_text
from .pending import PENDING
from .plots import log_axis_scales
from .sessionfile import NOISE_RANGE_nT
from .state import METHODS
from .uploads import UPLOAD_UNITS
from .vectorpanel import (
    VectorPanel,
    vector_candidate_markdown,
    vector_candidates_markdown,
    vector_history_markdown,
    vector_model_markdown,
    vector_status_markdown,
)

METHOD_LABELS = {
    "ml": "ml: ellipsoid, align, maximum likelihood",
    "ellipsoid": "ellipsoid: the seed's two steps",
    "pso": "pso: particle swarm (global search)",
    "ipso": "ipso: improved particle swarm",
    "de": "de: differential evolution",
}
ALL_SENSORS = "all sensors"


# --- text builders ------------------------------------------------------------------------------------------
def fmt(v, unit="", digits=4) -> str:
    """A number for the page (:func:`magcal_workbench.controller.format_number`) with its unit, or ``-``."""
    text = format_number(v, digits)
    return text if text == "-" else f"{text}{(' ' + unit) if unit else ''}"


def convergence_markdown(record) -> str:
    """A warning when a step's fit stopped before converging (the engine's ``FitResult.success``); else ``""``."""
    fit = getattr(record, "fit", None)
    if not fit or fit.get("success", True):
        return ""
    return (
        f"⚠ **Warning: the fit did not converge** ({fit.get('message') or 'no reason given'}, "
        f"{fit.get('nfev', '?')} evaluations): its figures are not a minimum. Press *3. Refine* to continue "
        "from where it stopped, or check the data (outliers, attitude coverage, units, reference field)."
    )


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
    text = (
        f"**Total-field RMS: {rms_text}** (floor {fmt(floor, 'nT', 3)})  \n"
        f"Rejected: {sel.n_rejected} of {sel.n_samples} samples  \n"
        f"Model: {effects}"
    )
    if ctrl.vector_loop():  # Diagnose and Add work on the vector model: its figures too
        vector = vector_status_markdown(ctrl.vector)
        text += f"  \n{vector}" if vector else "  \n_Vector model: not fitted yet (Diagnose fits it)_"
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


def summary_markdown(figures: dict, rms_nT=None, floor_nT=None, sensors=(), sensor: int = 0) -> str:
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
        rows.append(
            f"| **corrected** | **{fmt(rms_nT, digits=4)}**{ratio} | " + " | ".join(pct(wc[b]) for b in bands) + " |"
        )
    kept = f"{figures['n_kept']} of {figures['n_samples']} samples kept"
    text = f"**Now**: {kept}; noise floor {fmt(floor_nT, 'nT', 3)}\n\n" + "\n".join(rows)
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


def history_markdown(state, last: int = 6, pending=frozenset()) -> str:
    """The last steps: in-sample RMS of the kept samples and, after a maximum-likelihood fit, the held-out RMS
    (the model fitted on alternating blocks of time, scored on the blocks between: :func:`magcal.fitting.validation.
    validate`); ``pending`` holds the ``id`` of the records whose held-out check still runs (shown
    ``pending...``)."""
    if not state.history:
        return "_No step yet._"
    rows = ["| # | step | RMS nT | held-out nT | what changed |", "|---|---|---|---|---|"]
    start = max(0, len(state.history) - last)
    for i, r in enumerate(state.history[start:], start=start):
        flag = " (did not converge)" if convergence_markdown(r) else ""
        held = PENDING if id(r) in pending else fmt(getattr(r, "held_out_rms_nT", None))
        rows.append(
            f"| {i} | {safe_text(r.step, 120)} | {fmt(r.rms_nT)}{flag} | {held} | {safe_text(r.changes, 400)} |"
        )
    return "\n".join(rows)


#: Under the step history: what its held-out column means.
HELD_OUT_NOTE = (
    "_held-out: the same model fitted on alternating blocks of time and scored on the blocks between; "
    "an added effect is real when it lowers this too._"
)


def candidates_markdown(diagnosis) -> str:
    if diagnosis is None:
        return "_Press Diagnose to rank the effects the data may hide in the current fit's residuals._"
    d = diagnosis.to_dict() if hasattr(diagnosis, "to_dict") else dict(diagnosis)
    lines = [
        f"**Verdict:** {safe_code(d.get('verdict'))}  (RMS {fmt(d.get('rms_nT'), 'nT')}, "
        f"noise {fmt(d.get('noise_nT'), 'nT', 3)}, floor {fmt(d.get('floor_nT'), 'nT', 3)})"
    ]
    if d.get("summary"):
        lines.append(f"_{safe_text(d['summary'], 1000)}_")
    validation = d.get("validation") or {}
    blocks = (validation.get("schemes") or {}).get("blocks") if validation.get("validated") else None
    if blocks:
        base = fmt(blocks.get("base_held_out_rms_nT"), "nT")
        lines.append(
            f"\nHeld-out check: each candidate refitted on alternating blocks of time and scored on the "
            f"{blocks.get('n_test')} samples between (base model {base}); only candidates whose gain holds "
            "there are recommended."
        )
    elif validation.get("skipped"):
        lines.append(f"\nHeld-out check not done: {safe_text(validation['skipped'], 300)}")
    for w in d.get("warnings", []) or []:
        lines.append(f"- warning: {safe_text(w, 1000)}")
    cands = d.get("candidates", []) or []
    if cands:
        lines += ["", "| # | effect | dBIC | RMS after nT | held-out nT | holds? |", "|---|---|---|---|---|---|"]
        for i, c in enumerate(cands[:8]):
            mark = "" if c.get("refitted", True) else "*"
            lines.append(
                f"| {i + 1} | {safe_code(candidate_label(c))} | {fmt(c.get('delta_bic'), digits=4)}{mark} | "
                f"{fmt(c.get('rms_after_nT'))}{mark} | {held_out_pair(c)} | {holds_words(c)} |"
            )
        if any(not c.get("refitted", True) for c in cands[:8]):
            lines.append("\n\\* predicted by the score test, not refitted")
        if any(c.get("holds") is False for c in cands[:8]):
            lines.append(
                "\n⚠ A candidate that **does not hold on held-out data** lowers the error only on the "
                "samples it was fitted to: it describes something of this record (or its noise), not the "
                "instrument. You may still add it to see."
            )
    else:
        lines.append("_No candidate explains the residual._")
    return "\n".join(lines)


def held_out_pair(candidate: dict) -> str:
    """``"12.1 -> 10.4"``: the held-out RMS (nT) without and with a candidate (``blocks`` scheme), or ``-``."""
    before, after = candidate.get("held_out_rms_before_nT"), candidate.get("held_out_rms_after_nT")
    if before is None or after is None:
        return "-"
    return f"{fmt(before)}→{fmt(after)}"


def holds_words(candidate: dict) -> str:
    """Whether a candidate's in-sample gain holds on held-out data (:attr:`magcal.diagnosis.Candidate.holds`), in
    words for the table; when the blocks' figure falls but the gain still does not hold, the later stretch's RMS
    rose (quoted, nT)."""
    holds = candidate.get("holds")
    if holds is None:
        return "-"
    if holds:
        return "holds"
    before, after = candidate.get("held_out_rms_before_nT"), candidate.get("held_out_rms_after_nT")
    later_before, later_after = candidate.get("later_rms_before_nT"), candidate.get("later_rms_after_nT")
    blocks_fall = before is not None and after is not None and after < before
    if blocks_fall and later_before is not None and later_after is not None and later_after > later_before:
        return f"⚠ **does not hold**: later {fmt(later_before)}→{fmt(later_after)}"
    return "⚠ **does not hold**"


def candidate_evidence_markdown(diagnosis, label: str) -> str:
    """The evidence of the chosen candidate, with a warning when its gain does not hold on held-out data."""
    if diagnosis is None:
        return ""
    for c in diagnosis.candidates:
        if candidate_label(c) == label:
            refit = "refitted" if getattr(c, "refitted", False) else "predicted by the score test"
            text = f"**{safe_text(label)}** ({refit}): {safe_text(getattr(c, 'evidence', ''), 1000)}"
            if getattr(c, "holds", None) is False:
                text = (
                    "⚠ **This candidate does not hold on held-out data**: its gain is on the fitted samples "
                    "only. Adding it is allowed, but it will not carry.  \n" + text
                )
            return text
    return ""


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


#: What a term's :attr:`magcal.model.terms.Effect.transferable` means, one line each.
TRANSFER_WORDS = {
    True: "Instrument term: a property of the sensor, carried to new data by the calibration",
    False: "Record-only term: describes this recording (a drift, a step, the site's field); fitted so the "
    "instrument terms stay unbiased, applied to this record only, never carried to new data",
}


def model_terms_markdown(terms) -> str:
    """The model's effects marked instrument (carried to new data) or record-only (this record only)."""
    if not terms:
        return "_The model has the base terms only (bias, scale, non-orthogonality, misalignment): all instrument._"
    rows = ["**In the model**"]
    for t in terms:
        kind = "instrument" if t["transferable"] else "record-only"
        why = (
            "carried to new data"
            if t["transferable"]
            else "this record only: not carried to new data without an external reference"
        )
        rows.append(f"- {safe_code(t['label'], 80)} **{kind}**: {why}")
    return "\n".join(rows)


def quality_markdown(report) -> str:
    """The data-quality findings (:func:`magcal.checks.quality.assess`), warnings first and marked, each with what it does
    to the fit; the findings with nothing to say are listed in one line at the end."""
    if report is None:
        return "_No quality report._"
    findings = list(report.findings)
    shown = [f for f in findings if f.severity == "warning" or f.notable or f.kind == "sample_rate"]
    shown.sort(key=lambda f: f.severity != "warning")
    lines = []
    for f in shown:
        where = f"sensor {f.sensor}: " if f.sensor is not None else ""
        head = f"{where}{f.summary}"
        if f.severity == "warning":
            lines.append(f"- ⚠ **Warning: {safe_text(head, 600)}**  \n  → {safe_text(f.effect, 600)}")
        else:
            lines.append(f"- {safe_text(head, 600)}  \n  → _{safe_text(f.effect, 600)}_")
    quiet = [f for f in findings if f not in shown]
    if quiet:
        seen = sorted({f.kind.replace("_", " ") for f in quiet})
        lines.append(f"\nChecked, nothing to say: {safe_text(', '.join(seen), 300)}.")
    n_warn = sum(f.severity == "warning" for f in findings)
    head = f"**Data quality**: {n_warn} warning(s)" if n_warn else "**Data quality**: no warning"
    return head + "\n\n" + "\n".join(lines)


def reference_markdown(ctrl) -> str:
    """The reference field the fits use, and where it comes from (the box above shows 0 for "not typed")."""
    ds, state, cal = ctrl.dataset, ctrl.state, ctrl.calibration
    fitted = (
        f"; the last fit found {fmt(cal.reference_total_nT, 'nT', 6)}"
        if cal is not None and cal.reference_total_nT
        else ""
    )
    if state.fit_reference:
        return f"_Reference used:_ fitted (you asked to fit the field magnitude){fitted}"
    if state.reference_nT:
        return f"_Reference used:_ {fmt(state.reference_nT, 'nT', 6)}, typed here"
    if ds.ref_total_nT is not None:
        return (
            f"_Reference used:_ per sample, the file's `ref_total` column (median "
            f"{fmt(float(np.median(ds.ref_total_nT)), 'nT', 6)})"
        )
    if ds.reference_total_nT:
        return f"_Reference used:_ {fmt(ds.reference_total_nT, 'nT', 6)} from the file (`# reference_total_nT`)"
    return f"_Reference used:_ none given, so the field magnitude is fitted{fitted}"


def noise_markdown(ctrl) -> str:
    """The noise behind the floors, the method that gave it, and the floor it sets."""
    floor = ctrl.floor_nT()
    text = (
        f"**Noise:** {safe_text(ctrl.noise_text(), 800)}  \nTotal-field floor of the current fit: {fmt(floor, 'nT', 3)}"
    )
    noise = ctrl.noise
    if noise is not None and noise.note:
        text += f"  \n_{safe_text(noise.note, 600)}_"
    return text


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
    if len(x) == 1:
        x, y, f, held = np.array([0.0, 0.0]), np.repeat(y, 2), np.repeat(f, 2), np.repeat(held, 2)
    return x, y, f, held


#: Largest default residual gain of the View tab (that of a fit near a clean sensor's noise).
RESIDUAL_GAIN_MAX = 1000.0
#: Drawn radial deviation the default residual gain aims for: the residual RMS.
DRAWN_RESIDUAL = 0.05


def view_gains(ctrl) -> tuple[float, float]:
    """Default (distortion, residual) gains of the View tab for these data: the distortion gain of the kept
    samples' raw clouds (:func:`magcal_workbench.scene.distortion_gain`), the residual RMS drawn at about
    :data:`DRAWN_RESIDUAL` of the radius, not above :data:`RESIDUAL_GAIN_MAX`. Residuals of hundreds of nT would
    otherwise be drawn far outside the screen."""
    F = float(ctrl.field_nT)
    if not (np.isfinite(F) and F > 0):  # an all-zero file: nothing to scale by
        return scn.DISTORTION_GAIN_MAX, RESIDUAL_GAIN_MAX
    distortion = scn.distortion_gain(ctrl.dataset.readings_nT[:, ctrl.kept], F)
    rms = ctrl.residual_rms_nT()
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
    """

    def __init__(
        self, widgets, handle, on, ctrl, live, busy, maps_choice, session_ids, store, local: bool, live_sources
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
        tabs = gui.add_tab_group()
        self.vector_panel = VectorPanel(self)  # the vector model's widgets, built into the tabs below
        #: A change of the selection leaves the cockpit's figures to the refit that follows (:meth:`figures_held`),
        #: and whether some were left.
        self._figures_held = False
        self._figures_stale = False
        self._bindings: list = []  # (widget, the state's value as the widget shows it)
        self._live_shown = False  # the tabs describe a live session's stream
        #: The tabs by name (:meth:`section` adds to them).
        self.tab_by_name: dict = {}
        for name, build in (
            ("Calibrate", self._build_calibrate),
            ("Model", self._build_model),
            ("Quality", self._build_quality),
            ("Outliers", self._build_outliers),
            ("View", self._build_view),
            ("Files", self._build_files),
            ("Lessons", self._build_lessons),
        ):
            tab = tabs.add_tab(name, icon=None)
            self.tab_by_name[name] = tab
            with tab:
                build(gui)
        self.tabs = tabs

    def _do_next_step(self, event) -> None:
        """The guide's button: the step :func:`~magcal_workbench.guide.next_step` names, through the same handler
        as that step's own button (Add: *Add the advice*, everything the diagnosis advises)."""
        step = next_step(self.ctrl())
        handler = {
            "run": self.on.do_calibrate,
            "vector": self.on.do_vector_fit,
            "diagnose": self.on.do_diagnose,
            "add": self.on.do_add_advice,
        }.get(step.key)
        if handler is not None:
            handler(event)

    def show_guide(self) -> None:
        """The guide's text and its button, for the session as it is now."""
        ctrl = self.ctrl()
        self.guide.content = guide_markdown(ctrl)
        step = next_step(ctrl)
        self.btn_next.visible = step.key != "none"
        if step.label:
            self.btn_next.label = step.label

    def section(self, tab: str, title: str, expand: bool = False):
        """A new collapsible section at the end of the tab ``tab`` (``"Files"``, ...): its widgets are made inside
        ``with panels.section("Files", "Export"): ...``; input widgets through :attr:`w` (checked values)."""
        with self.tab_by_name[tab]:
            return self.gui.add_folder(title, expand_by_default=expand)

    # --- construction --------------------------------------------------------------------------------------
    def _bind(self, handle, shown, apply):
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

    def _build_calibrate(self, gui):
        """Run, the plots (|B| against time with its region editor, the error histogram), the settings, and the
        long texts folded away (data, per-sensor figures, step history)."""
        import plotly.graph_objects as go

        state, configure = (lambda: self.ctrl().state), (lambda **kw: self.ctrl().configure(**kw))
        self.btn_run = self._button(gui, "Run the chosen method", self.on.do_calibrate, color="blue")
        with gui.add_folder("|B| against time", expand_by_default=True):
            # viser's client draws plotly at height = width * aspect
            self.field_plot = gui.add_plotly(go.Figure(), aspect=0.85)
            self.range_from = self.w.slider(
                "From % of the record",
                min=0.0,
                max=100.0,
                step=0.1,
                initial_value=40.0,
                hint="Start of the time range to exclude or include (shaded blue on the plot)",
            )
            self.range_to = self.w.slider(
                "To % of the record",
                min=0.0,
                max=100.0,
                step=0.1,
                initial_value=50.0,
                hint="End of the time range to exclude or include",
            )
            for h in (self.range_from, self.range_to):
                h.on_update(lambda e: self.handle(self.on.range_changed, e))
            self.btn_exclude_range = self._button(
                gui,
                "Exclude range",
                self.on.do_exclude_range,
                engine=False,
                hint="Leave the samples in the range out of the fit (undo in the Outliers tab); the fit reruns",
            )
            self.btn_include_range = self._button(
                gui,
                "Include range",
                self.on.do_include_range,
                engine=False,
                hint="Put the range's excluded samples back into the fit; the fit reruns",
            )
            self.btn_exclude_fast = self._button(
                gui,
                "Exclude the fast-turning samples",
                self.on.do_exclude_fast,
                engine=False,
                visible=False,
                hint="Leave out the samples taken while turning fast (marked red); the fit reruns",
            )
            self.range_info = gui.add_markdown("")
        with gui.add_folder("Error histogram", expand_by_default=True):
            self.histogram_unit = self.w.dropdown(
                "Error in", ("nT", "%"), initial_value="nT", hint="|B| - reference in nT or in % of the reference"
            )
            self.histogram_unit.on_update(lambda e: self.handle(self.on.range_changed, e))
            self.histogram_plot = gui.add_plotly(go.Figure(), aspect=0.68)
        with gui.add_folder("Settings", expand_by_default=True):
            self.method = self._bind(
                self.w.dropdown(
                    "Method", tuple(METHODS), initial_value="ml", hint="; ".join(METHOD_LABELS[m] for m in METHODS)
                ),
                lambda: state().method,
                lambda v: configure(method=v),
            )
            self.reference = self._bind(
                self.w.number(
                    "Reference field nT",
                    0.0,
                    min=0.0,
                    step=1.0,
                    hint="Total field in nT; 0 = the file's reference (or fitted if none)",
                ),
                lambda: float(state().reference_nT or 0.0),
                lambda v: configure(reference_nT=float(v) if v and float(v) > 0 else None),
            )
            self.fit_reference = self._bind(
                gui.add_checkbox(
                    "Fit the field magnitude",
                    False,
                    hint="Ignore any reference and fit |B| (det C^-1 = 1 for sensor 1)",
                ),
                lambda: bool(state().fit_reference),
                lambda v: configure(fit_reference=bool(v)),
            )
            self.reference_info = gui.add_markdown("")
            self.vector_panel.build_location(gui)
            self.robust = self._bind(
                gui.add_checkbox("Robust loss (soft L1)", False, hint="Down-weight gross outliers in the ML step"),
                lambda: bool(state().robust),
                lambda v: configure(robust=bool(v)),
            )
        with gui.add_folder("Step by step", expand_by_default=False):
            self.btn_ellipsoid = self._button(gui, "1. Fit ellipsoid (per sensor)", self.on.do_ellipsoid)
            self.btn_align = self._button(gui, "2. Align sensors (Procrustes)", self.on.do_align)
            self.btn_refine = self._button(gui, "3. Refine (maximum likelihood)", self.on.do_refine)
        with gui.add_folder("Data", expand_by_default=False):
            self.data_info = gui.add_markdown("")
        with gui.add_folder("Per sensor", expand_by_default=False):
            self.sensors_table = gui.add_markdown("")
        self.vector_panel.build_calibrate(gui)
        with gui.add_folder("Step history", expand_by_default=False):
            self.history = gui.add_markdown("")
            self.history_note = gui.add_markdown(HELD_OUT_NOTE)

    def _build_model(self, gui):
        gui.add_markdown(
            "Effects beyond bias, scale, non-orthogonality and misalignment. "
            "Greyed ones need a channel the data lack (hover for the reason)."
        )
        self.effect_boxes = {}
        self._boxes_lock = threading.Lock()
        self.effects_folder = gui.add_folder("Effects", expand_by_default=True)
        self._add_effect_boxes(self.ctrl().available_effects())
        self.model_terms = gui.add_markdown(model_terms_markdown(self.ctrl().model_terms()))
        with gui.add_folder("Your own effects", expand_by_default=False):
            self.user_effects = gui.add_markdown(user_effects_markdown(self.ctrl().available_effects()))
            self.effects_path = self.w.text(
                "Effects file (.py)", "", hint="Path of a Python file on the machine serving this page"
            )
            self.btn_load_effects = self._button(gui, "Load effects file", self.on.do_load_effects)
            self.effects_warning = gui.add_markdown(
                EFFECTS_FILE_WARNING
                if self.local
                else "_Loading an effects file is off: the page is served beyond this machine. Start the workbench "
                "with `--effects-file PATH` instead._"
            )
            self.btn_load_effects.disabled = not self.local
            self.effects_path.disabled = not self.local
            #: The effects files the open session names, not loaded (never run when a session opens).
            self.session_effects = gui.add_markdown("", visible=False)
            self.btn_session_effects = self._button(
                gui, "Load the session's effects files", self.on.do_load_session_effects, visible=False
            )
        self.btn_refit = self._button(gui, "Refit with this model", self.on.do_refine)
        self.btn_diagnose = self._button(gui, "Diagnose", self.on.do_diagnose, color="violet")
        self.candidates = gui.add_markdown("")
        self.candidate_choice = self.w.dropdown("Candidate", ("-",), allowed=self._candidate_options, initial_value="-")
        self.candidate_evidence = gui.add_markdown("")
        self.candidate_choice.on_update(lambda e: self.handle(self._candidate_chosen, e))
        self.btn_add = self._button(gui, "Add the candidate and refit", self.on.do_add, color="green")
        #: Everything the diagnosis advises, in one refit (shown when it advises something the model lacks).
        self.btn_add_advice = self._button(gui, "Add the advice and refit", self.on.do_add_advice, visible=False)
        self.vector_panel.build_model(gui)  # the vector model's history plot and its Take out, for the vector loop
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
                {"label": "noise floor nT", "stroke": "#d62728", "dash": [6, 4], "width": 1.5},
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
        self.btn_full_evidence = self._button(
            gui,
            "Full-size evidence",
            self.on.do_full_evidence,
            engine=False,
            hint="The evidence plots over the scene, full size (press again to go back); the same data as below",
        )
        self.btn_evidence_png = self._button(
            gui, "Download evidence PNG", self.on.do_download_evidence_png, engine=False
        )
        self.btn_evidence_svg = self._button(
            gui, "Download evidence SVG", self.on.do_download_evidence_svg, engine=False
        )
        self.evidence_holder = gui.add_folder("Evidence", expand_by_default=True)
        self.evidence_plot = None

    def _build_quality(self, gui):
        """Data quality read before fitting, and the noise behind the floors (given or estimated)."""
        self.noise_info = gui.add_markdown("")
        self.noise_input = self.w.number(
            "Noise nT per axis",
            0.0,
            min=0.0,
            max=NOISE_RANGE_nT[1],
            step=0.1,
            hint="The sensor's noise per axis (standard deviation, nT) if you know it; 0 = estimate it from the "
            "data (differences in time, still stretches, never below the quantization floor)",
        )
        self.btn_noise = self._button(gui, "Use this noise for the floors", self.on.do_apply_noise, engine=False)
        self.quality = gui.add_markdown("")

    def _build_outliers(self, gui):
        gui.add_markdown(
            "**Shift-drag** a box in the scene to reject (or restore) the samples inside it; "
            "**click** a point to inspect its sample. Rejected points turn magenta."
        )
        self.box_mode = self.w.dropdown("Box selection", ("reject", "restore"), initial_value="reject")
        self.k_sigma = self.w.slider("Threshold k (x sigma)", min=2.0, max=10.0, step=0.5, initial_value=4.0)
        self.btn_threshold = self._button(gui, "Reject beyond k sigma", self.on.do_threshold, engine=False)
        self.auto_refit = gui.add_checkbox(
            "Refit after each change", True, hint="Refit (ML) on the kept samples after every rejection"
        )
        with gui.add_folder("History", expand_by_default=True):
            self.btn_undo = self._button(gui, "Undo", self.on.do_undo, engine=False)
            self.btn_redo = self._button(gui, "Redo", self.on.do_redo, engine=False)
            self.btn_reset = self._button(gui, "Reset (keep all)", self.on.do_reset, engine=False)
        self.inspect = gui.add_markdown(inspect_markdown(None))

    def _build_view(self, gui):
        options = self._sensor_options(self.ctrl().dataset.n_sensors)
        self.sensor_choice = self._bind(
            self.w.dropdown(
                "Sensor",
                options,
                allowed=lambda: self._sensor_options(self.ctrl().dataset.n_sensors),
                initial_value=options[0],
            ),
            self._sensor_shown,
            self.on.set_sensor,
        )
        self.distortion_gain = self.w.slider("Raw distortion x", min=0.1, max=50.0, step=0.1, initial_value=10.0)
        self.residual_gain = self.w.slider(
            "Residual x (radius 1 + x r/F)", min=0.0, max=5000.0, step=1.0, initial_value=1000.0
        )
        self.axes_gain = self.w.slider("Misalignment x (cross axes)", min=1.0, max=100.0, step=1.0, initial_value=20.0)
        self.show_raw = gui.add_checkbox("Raw cloud", True)
        self.show_ellipsoid = gui.add_checkbox("Fitted ellipsoid", True)
        self.show_corrected = gui.add_checkbox("Corrected cloud", True)
        #: The gains last set to suit the data (:func:`view_gains`); a gain the user moved is left alone.
        self._auto_gains = {id(self.distortion_gain): 10.0, id(self.residual_gain): 1000.0}
        for h in (
            self.distortion_gain,
            self.residual_gain,
            self.axes_gain,
            self.show_raw,
            self.show_ellipsoid,
            self.show_corrected,
        ):
            h.on_update(lambda e: self.handle(self.on.view_changed, e))
        self.surface_choice = self.w.dropdown(
            "Sphere surface",
            SURFACE_CHOICES,
            initial_value=SURFACE_CHOICES[0],
            hint="A smooth surface inside each corrected cloud, coloured by a direction pattern (nT): the residual's, "
            "the chosen candidate's (what adding it would explain), or what the last fit took away",
        )
        self.surface_choice.on_update(lambda e: self.handle(self.on.surface_changed, e))
        self.maps_info = gui.add_markdown("")
        with gui.add_folder("Time window", expand_by_default=True):
            self._build_time(gui)
        self.vector_panel.build_view(gui)

    def _build_time(self, gui):
        """The time scrubber (:mod:`workbench.timewindow`): a window of the recording on the sphere, replayed."""
        self.window_on = gui.add_checkbox(
            "Show a time window", False, hint="Draw only the samples in the window; the evidence plots shade it"
        )
        self.window_start = self.w.slider("Window start %", min=0.0, max=100.0, step=0.1, initial_value=0.0)
        self.window_width = self.w.slider("Window width %", min=0.5, max=100.0, step=0.5, initial_value=10.0)
        self.play_speed = self.w.slider(
            "Play speed x", min=1.0, max=100.0, step=1.0, initial_value=10.0, hint="Multiple of real time"
        )
        self.btn_play = self._button(gui, "Play", self.on.do_play, engine=False)
        self.btn_pause = self._button(gui, "Pause", self.on.do_pause_play, engine=False)
        self.btn_show_all = self._button(gui, "Show all", self.on.do_show_all, engine=False)
        self.window_info = gui.add_markdown("")
        for h in (self.window_on, self.window_start, self.window_width, self.play_speed):
            h.on_update(lambda e: self.handle(self.on.window_changed, e))

    def _build_files(self, gui):
        self.upload = gui.add_upload_button(
            "Open a file (CSV, .bin, .ulg)", mime_type=".csv,.txt,.bin,.ulg,text/csv,text/plain"
        )
        self.upload.on_upload(lambda e: self.handle(self.on.do_upload, e))
        self.upload_columns = self.w.text(
            "Columns",
            "",
            hint="Your column names mapped onto magcal's, as the command line's --columns: "
            "x=magX,y=magY,z=magZ,t=time,temp=T (empty: the file's own names)",
        )
        self.upload_units = self.w.dropdown(
            "Units",
            UPLOAD_UNITS,
            initial_value=UPLOAD_UNITS[0],
            hint="Unit of the readings; 'from the file' reads its '# units:' line (nT without one)",
        )
        self.upload_lsb = self.w.number(
            "LSB nT/count",
            0.0,
            min=0.0,
            max=1e9,
            step=0.001,
            hint="nT per count for raw counts (0: the file's '# lsb_nT:' line)",
        )
        self.btn_reread = self._button(gui, "Re-read the last upload with these", self.on.do_reread)
        self.upload_info = gui.add_markdown("")
        self.btn_dl_cal = self._button(gui, "Download calibration JSON", self.on.do_download_calibration, engine=False)
        self.btn_dl_csv = self._button(gui, "Download corrected CSV", self.on.do_download_corrected, engine=False)
        self.download_info = gui.add_markdown("")
        with gui.add_folder("Export", expand_by_default=True):  # magcal_workbench.exporting
            self.export = ExportSection(gui, self.w, self._button, self.on)
        gui.add_markdown("**Sessions** (saved automatically after every change)")
        self.session_info = gui.add_markdown("")
        self.session_choice = self.w.dropdown("Saved session", ("-",), allowed=self.session_ids, initial_value="-")
        self.btn_reopen = self._button(gui, "Reopen the session", self.on.do_reopen)
        self.btn_fresh = self._button(gui, "Start this data afresh", self.on.do_fresh)
        self.btn_delete_session = self._button(gui, "Delete the chosen session", self.on.do_delete_session)
        self._build_live(gui)

    def _build_live(self, gui):
        """The live source: one of the sources the server offers and its bounded options, Start, Pause/Resume,
        Stop (:mod:`magcal_workbench.live`, :class:`~magcal_workbench.live.SourceMenu`)."""

        gui.add_markdown(
            "**Live from the instrument**: every sample is recorded to a CSV as it arrives; Stop "
            "opens the recording here. Other sources start from the command line (--live SOURCE)."
        )
        offered = self.live_sources()
        first = next((o for o in offered if o == "simulated chi2017"), offered[0])
        self.live_source = self.w.dropdown(
            "Live source",
            offered,
            allowed=self.live_sources,
            initial_value=first,
            hint="a simulated preset, a serial port found on this machine, UDP/TCP on 127.0.0.1, a recording "
            "of the session folder played again, or a source the command line allowed (--live-allow)",
        )
        self.live_rate = self.w.number("Rate (Hz)", 50.0, min=PAGE_RATE_HZ[0], max=PAGE_RATE_HZ[1], step=1.0)
        self.live_samples = self.w.number(
            "Samples (simulated)", 3000, min=PAGE_SAMPLES[0], max=PAGE_SAMPLES[1], step=100
        )
        self.live_speed = self.w.number("Speed (x real time)", 1.0, min=PAGE_SPEED[0], max=PAGE_SPEED[1], step=0.1)
        self.live_port = self.w.number("Port (UDP/TCP)", 14550, min=PAGE_PORT[0], max=PAGE_PORT[1], step=1)
        self.live_baud = self.w.dropdown("Baud (serial)", BAUDS, initial_value=BAUDS[0])
        self.live_columns = self.w.text(
            "Columns (text lines)", "x,y,z", max_chars=200, hint="e.g. x,y,z or t,s1x,s1y,s1z,s2x,s2y,s2z"
        )
        self.live_template = self.w.text(
            "Template (text lines)",
            "",
            max_chars=TEMPLATE_CHARS,
            hint="e.g. x={x} y={y} z={z} or Magnetometer reading: [{x}, {y}, {z}]; blank: the columns",
        )
        self.live_units = self.w.dropdown("Units (text lines)", LINE_UNITS, initial_value=LINE_UNITS[0])
        self.btn_live_list = self._button(gui, "List the sources again", self.on.do_live_list, engine=False)
        self.btn_live_start = self._button(gui, "Start live", self.on.do_live_start, engine=False)
        self.btn_live_pause = self._button(gui, "Pause", self.on.do_live_pause, engine=False, visible=False)
        self.btn_live_resume = self._button(gui, "Resume", self.on.do_live_resume, engine=False, visible=False)
        self.btn_live_stop = self._button(
            gui, "Stop and open the recording", self.on.do_live_stop, engine=False, visible=False
        )

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
        paused = running and live.session.paused
        self.btn_live_start.disabled = running
        self.btn_live_pause.visible = running and not paused
        self.btn_live_resume.visible = running and paused
        self.btn_live_stop.visible = running
        for b in self._engine_buttons:  # the engine steps act on the opened data, not on the stream
            b.disabled = running or self.busy()

    def _build_lessons(self, gui):
        lessons = list_lessons()
        opts = lesson_slugs()
        gui.add_markdown(
            "Each lesson hides a physical effect in its data. Fit, diagnose, add what you think "
            "is missing, and check. The answer stays hidden until you ask."
        )
        self.lesson_choice = self.w.dropdown(
            "Lesson",
            opts,
            allowed=lesson_slugs,
            initial_value=opts[0],
            hint="; ".join(f"{l.slug}: {l.title}" for l in lessons),
        )
        self.btn_lesson = self._button(gui, "Open the lesson", self.on.do_open_lesson)
        self.lesson_guide = gui.add_markdown("")
        self.btn_check = self._button(gui, "Check my model", self.on.do_check_lesson, engine=False)
        self.btn_answer = self._button(gui, "Show the answer", self.on.do_show_answer, engine=False)
        self.lesson_feedback = gui.add_markdown("")

    def _add_effect_boxes(self, entries) -> None:
        """A checkbox for every catalogue effect that has none yet (a user's effects loaded later join the end)."""
        with self._boxes_lock, self.effects_folder:  # two refreshes at once must not add a box twice
            for entry in entries:
                name = entry["name"]
                if name in self.effect_boxes:
                    continue
                self.effect_boxes[name] = self._bind(
                    # spaces, not underscores: the narrow label column wraps a long name at its words
                    self.gui.add_checkbox(clean_text(name.replace("_", " "), 64), False, hint=effect_hint(entry)),
                    lambda n=name: self.ctrl().state.has_effect(n),
                    lambda on, n=name: self.ctrl().set_effect(n, bool(on)),
                )

    def _candidate_labels(self) -> list:
        """The current diagnosis's candidates (:meth:`Controller.candidate_labels`)."""
        return self.ctrl().candidate_labels()

    def _candidate_options(self) -> tuple:
        """The Candidate choices the server offers: the current diagnosis's candidates and ``-``."""
        return tuple(self._candidate_labels()) + ("-",)

    @staticmethod
    def _history_markdown(ctrl) -> str:
        """The step history; on a record whose loop works on the vector model, that model's fits first (world RMS
        per N, E, D and |B|)."""
        text = history_markdown(ctrl.state, pending=ctrl.held_out_pending)
        vector = vector_history_markdown(ctrl.state) if ctrl.vector_loop() else ""
        return f"{vector}\n\n**Total-field fit:**\n\n{text}" if vector else text

    @staticmethod
    def _model_terms_markdown(ctrl) -> str:
        text = model_terms_markdown(ctrl.model_terms())
        if ctrl.vector_loop():
            text = vector_model_markdown(ctrl.vector) + "\n\n_Total-field model (the boxes above):_ " + text
        return text

    @staticmethod
    def _sensor_options(n):
        return tuple([ALL_SENSORS] + [f"sensor {i + 1}" for i in range(n)]) if n > 1 else ("sensor 1",)

    def _sensor_shown(self) -> str:
        """The sensor choice the state holds, as the dropdown shows it."""
        ctrl = self.ctrl()
        s = ctrl.state.sensor
        return self._sensor_options(ctrl.dataset.n_sensors)[0] if s is None else f"sensor {s + 1}"

    def view_options(self) -> dict:
        """The View tab's settings, as :class:`~magcal_workbench.scene.SceneModel` fields."""
        return {
            "distortion_gain": float(self.distortion_gain.value),
            "residual_gain": float(self.residual_gain.value),
            "axes_gain": float(self.axes_gain.value),
            "show_raw": bool(self.show_raw.value),
            "show_corrected": bool(self.show_corrected.value),
            "show_ellipsoid": bool(self.show_ellipsoid.value),
        }

    def fit_view_to_data(self) -> None:
        """Set the View tab's gains to suit the data and fit (:func:`view_gains`), unless the user moved them."""
        distortion, residual = view_gains(self.ctrl())
        for handle, value in ((self.distortion_gain, distortion), (self.residual_gain, residual)):
            if handle.value == self._auto_gains.get(id(handle)) and handle.value != value:
                self._auto_gains[id(handle)] = value
                handle.value = value  # its callback redraws the scene

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
        ctrl = self.ctrl()
        kinds = set(kinds)
        everything = "all" in kinds
        live = self.live()
        self.show_alarm()
        self.status.content = status_markdown(ctrl) if live is None or not live.active else LIVE_STATUS
        self.show_guide()
        if everything or "message" in kinds:
            self.message.content = ctrl.message
        self.legend.content = self.on.legend_html()
        if everything or kinds & {"result", "data"}:
            self.fit_view_to_data()
        if everything or kinds & {"result", "selection", "model"}:
            self.sensors_table.content = sensors_markdown(ctrl)
            self.history.content = self._history_markdown(ctrl)
            data = rms_plot_data(ctrl)
            if len(data[0]):
                self.rms_plot.data = data
                self.rms_plot.scales = log_axis_scales(data)
            self.noise_info.content = noise_markdown(ctrl)
            self.quality.content = quality_markdown(ctrl.quality_with_fit())
            self.download_info.content = download_markdown(ctrl)
            self.model_terms.content = self._model_terms_markdown(ctrl)
        if everything or kinds & {"vector", "settings"}:  # the vector model's fit, or the loop it is on, changed
            self.history.content = self._history_markdown(ctrl)
            self.model_terms.content = self._model_terms_markdown(ctrl)
        if everything or kinds & {"data", "effects"}:
            catalogue = ctrl.available_effects()
            self._add_effect_boxes(catalogue)
            self.user_effects.content = user_effects_markdown(catalogue)
            pending = ctrl.pending_effects_files()
            self.session_effects.visible = self.btn_session_effects.visible = bool(pending)
            self.btn_session_effects.disabled = not self.local
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
        if everything or "data" in kinds:
            self.data_info.content = data_markdown(ctrl)
            self.noise_input.value = float(ctrl.state.noise_nT or 0.0)
            # the state's choice first: new options then never fall back to a stale one (which would apply it)
            self.sensor_choice.value = self._sensor_shown()
            self.sensor_choice.options = self._sensor_options(ctrl.dataset.n_sensors)
            self.refresh_sessions()
        if everything or kinds & {"model", "data", "effects"}:
            self.show_state()
        if everything or kinds & {"model", "data", "result", "settings"}:
            self.reference_info.content = reference_markdown(ctrl)
        if everything or "diagnosis" in kinds or "data" in kinds:
            if ctrl.vector_loop():  # the vector model's diagnosis, its counterpart
                vd = ctrl.vector.diagnosis
                self.candidates.content = (
                    vector_candidates_markdown(vd)
                    if vd is not None
                    else "_Press Diagnose to rank the effects the vector fit (attitude and field vector) may miss._"
                )
            else:
                self.candidates.content = candidates_markdown(ctrl.diagnosis)
            opts = tuple(self._candidate_labels()) or ("-",)
            advised = ctrl.advice()
            self.candidate_choice.options = opts
            # an advised candidate is chosen first; Add asks before it adds one the diagnosis does not advise
            self.candidate_choice.value = next((o for o in opts if o in advised), opts[0])
            self.btn_add_advice.visible = bool(advised)
            self.btn_add_advice.label = (
                f"Add the advice ({', '.join(advised)}) and refit" if advised else "Add the advice"
            )
            self._show_candidate_evidence()
            self.on.draw_evidence()
        if everything or "inspect" in kinds or "selection" in kinds:
            info = ctrl.sample_info(ctrl.inspected) if ctrl.inspected is not None else None
            self.inspect.content = inspect_markdown(info)
        self.btn_undo.disabled = not ctrl.state.selection.can_undo
        self.btn_redo.disabled = not ctrl.state.selection.can_redo
        has_cal = ctrl.calibration is not None
        self.btn_dl_cal.disabled = not has_cal
        self.btn_dl_csv.disabled = not has_cal
        self.btn_align.visible = ctrl.dataset.n_sensors > 1
        self.on.refresh_export()
        self.vector_panel.refresh(kinds)
        if live is not None and live.active:
            self.show_live_texts(live)  # the tabs describe the stream, not the file open before it
        elif kinds == {"selection"} and self._figures_held:
            self._figures_stale = True  # the refit that follows draws them
        elif everything or kinds & {"result", "selection", "data", "settings", "model"}:
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

    def _candidate_chosen(self, event) -> None:
        self._show_candidate_evidence()
        if self.maps_choice() == "candidate's pattern":
            self.on.refresh_maps()
        if self.ctrl().vector_loop():  # the evidence plots put the candidate's channel on their axis
            self.on.draw_evidence()

    def _show_candidate_evidence(self) -> None:
        ctrl = self.ctrl()
        if ctrl.vector_loop():
            self.candidate_evidence.content = vector_candidate_markdown(
                ctrl.vector.diagnosis, self.candidate_choice.value
            )
            return
        self.candidate_evidence.content = candidate_evidence_markdown(ctrl.diagnosis, self.candidate_choice.value)

    def refresh_sessions(self) -> None:
        store = self.store
        if store is None:
            self.session_info.content = "_Autosave is off._"
            return
        sessions = store.list()
        self.session_info.content = (
            f"This session: {safe_code(self.ctrl().session_id)} in {safe_code(store.root)}"
            if self.ctrl().session_id
            else "_This session is not saved._"
        )
        self.session_info.content += "\n\n" + sessions_markdown(sessions, store.max_bytes)
        opts = tuple(s["id"] for s in sessions[:30]) or ("-",)
        self.session_choice.options = opts
        self.session_choice.value = opts[0]
