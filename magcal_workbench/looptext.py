"""The texts of the model loop, per fit mode: what the page says of the active model session's fit, diagnosis,
candidates, history and terms (:data:`LOOP_TEXTS`, by the engine's mode name), so that the panels ask the active
session (:attr:`Controller.model_session <magcal_workbench.controller.Controller.model_session>`) instead of
branching on the mode; the total-field model's tables are here, the vector model's in
:mod:`magcal_workbench.vectorpanel`. Pure functions of what the controller holds (the tests call them directly);
text the workbench did not write goes through :mod:`magcal_workbench.markup`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from . import compensationpanel
from .figures import candidate_label, fmt
from .markup import safe_code, safe_text
from .pending import PENDING
from .vectorpanel import (
    vector_candidate_markdown,
    vector_candidates_markdown,
    vector_history_markdown,
    vector_model_markdown,
    vector_status_markdown,
)


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


@dataclass(frozen=True)
class LoopText:
    """What the page says of one mode's model loop.

    Parameters
    ----------
    status : callable
        ``status(ctrl, figures)``: the status's lines (markdown), given the total-field fit's
        :class:`StatusFigures`.
    candidates : callable
        ``candidates(ctrl)``: the diagnosis's verdict and candidates table, or what to press.
    candidate : callable
        ``candidate(ctrl, label)``: the evidence of the chosen candidate.
    history : callable
        ``history(ctrl)``: the step history.
    terms : callable
        ``terms(ctrl)``: the model's terms, instrument or record-only.
    evidence_per_candidate : bool
        The evidence plots put the chosen candidate's channel on their axis (choosing one redraws them).
    """

    status: Callable[..., str]
    candidates: Callable[..., str]
    candidate: Callable[..., str]
    history: Callable[..., str]
    terms: Callable[..., str]
    evidence_per_candidate: bool = False


def _total_field_history(ctrl) -> str:
    return history_markdown(ctrl.state, pending=ctrl.held_out_pending)


def _vector_history(ctrl) -> str:
    """The vector model's fits first (world RMS per N, E, D and |B|), then the total-field steps."""
    vector = vector_history_markdown(ctrl.state)
    text = _total_field_history(ctrl)
    return f"{vector}\n\n**Total-field fit:**\n\n{text}" if vector else text


@dataclass(frozen=True)
class StatusFigures:
    """The total-field fit's figures the status shows, as text: its RMS, floor, the rejected samples, its model."""

    rms: str
    floor: str
    rejected: str
    model: str


def _total_field_status(ctrl, figures: StatusFigures) -> str:
    return f"**Total-field RMS: {figures.rms}** (floor {figures.floor})  \n{figures.rejected}  \nModel: {figures.model}"


def _vector_status(ctrl, figures: StatusFigures) -> str:
    """The vector model's figures first, the total-field fit's after (one choice away)."""
    vector = vector_status_markdown(ctrl.vector) or "_Vector model: not fitted yet (the Step 1 button fits it)_"
    return (
        f"{vector}  \n{figures.rejected}  \n"
        f"Total-field RMS: {figures.rms} (the total-field fit, one choice away: Calibrate tab); model {figures.model}"
    )


def _vector_candidates(ctrl) -> str:
    d = ctrl.vector.diagnosis
    if d is None:
        return "_Press Diagnose to rank the effects the vector fit (attitude and field vector) may miss._"
    return vector_candidates_markdown(d, ctrl.vector.noise)


#: The compensations' texts (the scalar's and the cross's).
COMPENSATION_TEXTS = LoopText(
    status=compensationpanel.status_markdown,
    candidates=compensationpanel.candidates_markdown,
    candidate=compensationpanel.candidate_markdown,
    history=compensationpanel.history_markdown,
    terms=compensationpanel.terms_markdown,
)

#: The loop's texts by fit mode's name (a mode without an entry is shown as the total-field one).
LOOP_TEXTS: dict[str, LoopText] = {
    "total_field": LoopText(
        status=_total_field_status,
        candidates=lambda ctrl: candidates_markdown(ctrl.total_field.diagnosis),
        candidate=lambda ctrl, label: candidate_evidence_markdown(ctrl.total_field.diagnosis, label),
        history=_total_field_history,
        terms=lambda ctrl: model_terms_markdown(ctrl.model_terms()),
    ),
    "vector": LoopText(
        status=_vector_status,
        candidates=_vector_candidates,
        candidate=lambda ctrl, label: vector_candidate_markdown(ctrl.vector.diagnosis, label),
        history=_vector_history,
        terms=lambda ctrl: (
            vector_model_markdown(ctrl.vector)
            + "\n\n_Total-field model (the boxes above):_ "
            + model_terms_markdown(ctrl.model_terms())
        ),
        evidence_per_candidate=True,
    ),
    "compensation": COMPENSATION_TEXTS,
    "cross_compensation": COMPENSATION_TEXTS,  # the same texts: each asks the active session for its figures
}


def loop_text(ctrl) -> LoopText:
    """The texts of the model Diagnose and Add work on (the controller's active model session)."""
    return LOOP_TEXTS.get(ctrl.model_session.mode, LOOP_TEXTS["total_field"])
