"""The compensation model of the opened data: a scalar magnetometer beside a fluxgate on a platform, compensated by
Tolles-Lawson and the terms beyond it (the engine's fit mode ``"compensation"``, :mod:`magcal.modes.compensation`).

:class:`CompensationSession` runs the mode's fit on the kept samples, its diagnosis (the terms beyond TL judged on
held-out maneuvers), adds and removes those terms, keeps a history of the figure of merit per step, and what the
session file keeps of it (``compensation_fit``). The FOM, the maneuvers and the band-passed traces are the engine's
(:func:`magcal.diagnosis.compensation.compensation_result`); the functions here only pick what the page shows.
"""

from __future__ import annotations

import time
from typing import Any, ClassVar

import numpy as np

from magcal.core.errors import MagcalError
from magcal.fitting.compensation import COMPENSATION_EFFECTS, check_effects, compensation_record
from magcal.model.tolles_lawson import bandpass
from magcal.modes import COMPENSATION

from .events import Change
from .markup import clean_text, safe_text
from .modelsession import ModelSession, register_session
from .state import MAX_HISTORY_ROWS, JobInputs, pack_mask, unpack_mask

#: Largest record (samples) whose saved compensation is run again when its session opens; a larger one keeps its
#: settings and the page says to press the button.
RESTORE_MAX_SAMPLES = 2_000_000


def model_of(ctrl) -> CompensationBase | None:
    """The compensation session the page shows for ``ctrl``'s data: the active one on a compensation flight (the
    scalar's or the cross's, as the engine's ``choose_mode`` decides), else the scalar's; None for a controller
    without one."""
    active = getattr(ctrl, "model_session", None)
    if isinstance(active, CompensationBase):
        return active
    sessions = getattr(ctrl, "model_sessions", None) or {}
    return sessions.get("compensation")


class CompensationBase(ModelSession):
    """What a compensation's model session does whatever its sensors (the base of the scalar's
    :class:`CompensationSession` and the cross's
    :class:`~magcal_workbench.crosscompensationmodel.CrossCompensationSession`): the fit on the kept samples, the
    diagnosis (the terms beyond Tolles-Lawson judged on held-out maneuvers), add and remove, the FOM per step, the
    session file's ``compensation_fit``.

    A subclass names its engine's calls (:meth:`make_record`, :meth:`check_terms`, :meth:`engine_fit`,
    :meth:`engine_diagnose`, :meth:`result_effects`) and its :attr:`unit`; the FOM reads the same for both
    (:meth:`fom_figures`, :meth:`candidate_figures`, :meth:`diagnosis_figures`, :meth:`fom_rows`), through the
    engine's unit-neutral FOM protocol (:mod:`magcal.diagnosis.fom_protocol`: ``fom``, ``per_maneuver``,
    ``fom_before``, ``fom_held_out`` ...). The current term's columns are the base's too: the record's
    ``all_currents`` are the choices, a fit's compensation's ``current_columns`` what it took. The page's texts and
    figures ask these, never the mode.

    Attributes
    ----------
    result : object or None
        The last fit with its FOM report (the engine's mode result).
    diagnosis : object or None
        The last diagnosis (the terms beyond TL judged on held-out maneuvers).
    """

    #: What the messages call it (``"compensation"``: its fit, its diagnosis).
    words: ClassVar[str] = "compensation"
    #: The FOM's unit: ``"nT"`` (the scalar) or ``"nT/m"`` (the cross's tensor).
    unit: ClassVar[str] = "nT"
    #: The Calibrate tab's section title for this compensation.
    section_title: ClassVar[str] = "Compensation"
    #: Whose noise sets the floor, in words.
    noise_words: ClassVar[str] = "the noise"
    #: What the guide says the record is and its first step does.
    step_text: ClassVar[str] = ""
    #: The terms beyond TL this compensation offers, with what each is (the engine's words).
    terms: ClassVar[dict[str, str]] = {}

    def __init__(self, ctrl):
        super().__init__(ctrl)
        self.result: Any = None
        self._record: Any = None
        self._history: list[dict] = []
        self._current_columns: list[str] = []

    # --- what a subclass names -----------------------------------------------------------------------------
    def make_record(self):
        """The engine's record of the open data (what its fit and diagnosis take)."""
        raise NotImplementedError

    def check_terms(self, names) -> list[str]:
        """``names`` checked against the terms the engine takes (its one-line message otherwise)."""
        raise NotImplementedError

    def engine_fit(self, names: list[str], kept: np.ndarray, current: list[str] | None = None):
        """The engine's fit with ``names`` beyond TL on the ``kept`` samples (the current term taking the columns
        ``current``, the engine's default when None), with its FOM report."""
        raise NotImplementedError

    def current_choices(self) -> list[str]:
        """The record's current columns the current term may take (the engine record's ``all_currents``)."""
        return list(self.record().all_currents) if self.available else []

    def result_columns(self, result) -> list[str]:
        """The current columns a fit's current term took (its compensation's ``current_columns``; empty without
        the term)."""
        if "current" not in self.result_effects(result):
            return []
        comp = result.calibration
        return list(comp.current_columns or ([comp.current_column] if comp.current_column else []))

    def engine_diagnose(self):
        """The engine's diagnosis of the model's terms."""
        raise NotImplementedError

    def result_effects(self, result) -> list[str]:
        """The terms beyond TL a fit holds."""
        raise NotImplementedError

    def fom_figures(self, result) -> tuple[float, float, float, int] | None:
        """The FOM before and after (:attr:`unit`), the improvement ratio and the maneuvers' count; None without
        maneuvers."""
        fom = result.fom
        if fom is None:
            return None
        return fom.before.fom, fom.after.fom, fom.improvement_ratio, len(fom.after.maneuvers)

    def candidate_figures(self, candidate) -> tuple[float, float]:
        """A judged candidate's held-out FOM before and after (:attr:`unit`)."""
        return candidate.fom_before, candidate.fom_after

    def diagnosis_figures(self, found) -> tuple[float, float]:
        """A diagnosis's held-out FOM of the model and the FOM the noise alone leaves (:attr:`unit`)."""
        return found.fom_held_out, found.floor_fom

    def fom_rows(self) -> list[tuple[float, str, float, float]]:
        """Per maneuver of the last fit: the heading (deg), the kind, its FOM part before and after (:attr:`unit`)."""
        fom = None if self.result is None else self.result.fom
        if fom is None:
            return []
        return [
            (m.heading_deg, m.kind, float(b), float(a))
            for m, b, a in zip(fom.after.maneuvers, fom.before.per_maneuver, fom.after.per_maneuver)
        ]

    def tl_words(self) -> str:
        """Tolles-Lawson's part of the last fit, in words (markdown: its terms and coefficients)."""
        raise NotImplementedError

    # --- what the data offer -------------------------------------------------------------------------------
    def record(self):
        """The engine's record of the open data (made once)."""
        if self._record is None:
            self._record = self.make_record()
        return self._record

    @property
    def current_columns(self) -> list[str]:
        """The current columns the model's current term takes, in the order added (empty without the term, or before
        its fit when the engine chose the column)."""
        return list(self._current_columns) if "current" in self._effects else []

    def several_currents(self) -> bool:
        """Whether the record holds more than one current column (then each is a term of its own on the page)."""
        try:
            return len(self.current_choices()) > 1
        except MagcalError:
            return False

    def term_labels(self, effects, columns=()) -> list[str]:
        """The page's names of the terms ``effects`` with the current's ``columns``: ``current (cur_strb)`` per
        column on a record with several current columns, the engine's names otherwise."""
        several = self.several_currents()
        labels: list[str] = []
        for name in effects:
            if name == "current" and several and columns:
                labels += [current_label(c) for c in columns]
            else:
                labels.append(name)
        return labels

    def model_labels(self) -> list[str]:
        """The model's terms beyond TL as the page names them (:meth:`term_labels`)."""
        return self.term_labels(self.effects, self.current_columns)

    def candidate_label(self, candidate) -> str:
        """A diagnosis candidate as the page names it: with its current column on a record with several."""
        columns = tuple(getattr(candidate, "columns", ()) or ())
        if candidate.name == "current" and columns and self.several_currents():
            return current_label(*columns)
        return candidate.name

    def parse_labels(self, labels) -> tuple[list[str], list[str]]:
        """The engine's terms and the current columns that the page's ``labels`` name (``current (cur_strb)``:
        the current term taking that column; the columns checked against the record's)."""
        names: list[str] = []
        columns: list[str] = []
        for label in labels:
            name, named = split_label(str(label))
            if named:
                choices = self.current_choices()
                lacks = [c for c in named if c not in choices]
                if lacks:
                    raise MagcalError(
                        f"{clean_text(repr(str(label)), 80)}: the record has no current column "
                        f"{clean_text(', '.join(lacks), 200)} (its current columns: {clean_text(', '.join(choices), 300)})"
                    )
                columns += [c for c in named if c not in columns]
            names.append(name)
        return list(dict.fromkeys(self.check_terms(names))), columns

    @property
    def chosen(self) -> bool:
        """Whether the engine's choice of fit mode for the record is this compensation (the page shows it)."""
        return getattr(self.ctrl, "model_session", None) is self

    @property
    def calibration(self):
        """The last fit's compensation, or None."""
        return None if self.result is None else self.result.calibration

    @property
    def fom_now(self) -> float | None:
        """The last fit's FOM after (:attr:`unit`), None before a fit or without maneuvers."""
        figures = None if self.result is None else self.fom_figures(self.result)
        return None if figures is None else float(figures[1])

    # --- the loop ------------------------------------------------------------------------------------------
    def fit(
        self,
        *,
        inputs: JobInputs | None = None,
        effects=None,
        step: str = "",
        again: bool = False,
        current: list[str] | None = None,
    ):
        """The compensation (TL and the model's terms beyond it, or ``effects``; the current term taking the columns
        ``current``, default the model's) on the kept samples, its FOM before and after, a history row (``step``:
        what changed) and a message.

        Raises
        ------
        MagcalError
            The record lacks what this compensation needs, or the engine refuses the fit (its message).
        """
        if not self.available:
            raise MagcalError(f"the {self.words} fit " + "; ".join(self.missing()))
        ctrl = self.ctrl
        kept = np.asarray(ctrl.kept if inputs is None else inputs.kept, dtype=bool)
        names = self.check_terms(self.effects if effects is None else effects)
        columns = list(self.current_columns if current is None else current) if "current" in names else []
        t0 = time.perf_counter()
        said = self.term_labels(names, columns)
        ctrl.report_progress(f"{self.words} fit (Tolles-Lawson" + (" + " + ", ".join(said) if said else "") + ")")
        try:
            result = self.engine_fit(names, kept, columns or None)
        finally:
            ctrl.end_progress()
        elapsed = time.perf_counter() - t0
        with ctrl.state.lock:
            self.result, self.diagnosis = result, None
            self._effects = names
            self._current_columns = self.result_columns(result) if "current" in names else []
            if not again:
                self._history.append(self._history_row(step or "Tolles-Lawson fit", result, int(kept.sum()), elapsed))
                del self._history[:-MAX_HISTORY_ROWS]
            ctrl.state.compensation_fit = self.save_doc(kept)
            ctrl.state.touch()
        ctrl.autosave()
        ctrl.emit(Change.COMPENSATION)
        ctrl.emit(Change.DIAGNOSIS)  # the fit cleared the diagnosis of the one before
        ctrl.say(("the saved session's " if again else "") + self.fit_message(result, elapsed))
        return result

    def diagnose(self, *, inputs: JobInputs | None = None):
        """The terms beyond TL judged on held-out maneuvers (the engine's mode's ``diagnose``); the fit runs first
        when there is none."""
        if self.result is None:
            self.fit(inputs=inputs)
        ctrl = self.ctrl
        ctrl.report_progress(f"diagnosing the {self.words} (each term beyond TL on held-out maneuvers)")
        try:
            found = self.engine_diagnose()
        finally:
            ctrl.end_progress()
        with ctrl.state.lock:
            self.diagnosis = found
            ctrl.state.touch()
        ctrl.emit(Change.DIAGNOSIS)
        ctrl.say(f"**{self.words} diagnosis** ({found.elapsed_s:.1f} s): {safe_text(found.summary, 600)}")
        return found

    def candidate_labels(self) -> list[str]:
        """The advice first, then the other judged terms by their held-out FOM, none the model holds (a current
        column each a term of its own on a record with several: ``current (cur_strb)``)."""
        found = self.diagnosis
        if found is None:
            return []
        ranked = sorted((c for c in found.candidates if c.judged), key=lambda c: self.candidate_figures(c)[1])
        labels = list(self.advice()) + [self.candidate_label(c) for c in ranked]
        model = self.model_labels()
        return [label for label in dict.fromkeys(labels) if label not in model]

    def advice(self) -> list[str]:
        """What the last diagnosis advises that the model does not hold: its ``explained_by``, and on a record with
        several current columns each column its ``current_columns`` adds (``current (cur_com_1)``)."""
        found = self.diagnosis
        if found is None:
            return []
        names = list(getattr(found, "explained_by", None) or [])
        columns = list(getattr(found, "current_columns", None) or [])
        if columns and self.several_currents() and "current" not in names and "current" in self.effects:
            names.append("current")  # the model's current term takes more columns
        model = self.model_labels()
        return [label for label in self.term_labels(names, columns) if label not in model]

    def candidate_holds(self, label: str) -> bool:
        """Whether the diagnosis recommends ``label`` (its held-out FOM fell by the engine's margin)."""
        found = self.diagnosis
        if found is None:
            return False
        return label in self.advice() or any(
            self.candidate_label(c) == label and c.recommended for c in found.candidates
        )

    def add_all(self, labels, *, inputs: JobInputs | None = None, note: str = ""):
        """Put the terms ``labels`` into the model (``current (cur_strb)``: the current term taking that column
        besides the model's) and refit once."""
        names, columns = self.parse_labels(labels)
        effects = list(dict.fromkeys(self.effects + names))
        current = list(dict.fromkeys(self.current_columns + columns))
        said = ", ".join(self.term_labels(names, columns))
        step = "+ " + said + (f" ({note})" if note else "")
        return self.fit(inputs=inputs, effects=effects, step=step, current=current)

    def remove(self, label: str | None = None, *, inputs: JobInputs | None = None):
        """Take ``label`` (the last of :meth:`model_labels` by default; ``current (cur_strb)`` one current column)
        out of the model and refit."""
        model = self.model_labels()
        if not model:
            raise MagcalError(f"the {self.title} holds no term beyond Tolles-Lawson")
        label = model[-1] if label is None else label
        if label not in model:
            raise MagcalError(f"{clean_text(repr(str(label)), 80)} is not in the {self.title}")
        return self._refit_without(label, inputs)

    def _refit_without(self, label: str, inputs: JobInputs | None):
        name, columns = split_label(label)
        current = [c for c in self.current_columns if c not in columns]
        drop = bool(columns) and bool(current)  # the current term stays with its other columns
        effects = [e for e in self.effects if e != name or drop]
        return self.fit(inputs=inputs, effects=effects, step=f"- {label}", current=current)

    def history(self) -> list[dict]:
        """The fits of this session (``step``, ``effects``, ``current_columns``, ``fom_before_nT``, ``fom_nT``,
        ``improvement_ratio``, ``n_fitted``, ``elapsed_s``: the session file's keys, the FOM in :attr:`unit`),
        oldest first."""
        return list(self._history)

    def _history_row(self, step: str, result, n_fitted: int, elapsed_s: float) -> dict:
        figures = self.fom_figures(result)
        before, after, ratio = (None, None, None) if figures is None else figures[:3]
        return {
            "step": step,
            "effects": self.result_effects(result),
            "current_columns": self.result_columns(result),
            "fom_before_nT": None if before is None else float(before),
            "fom_nT": None if after is None else float(after),
            "improvement_ratio": None if ratio is None else float(ratio),
            "n_fitted": int(n_fitted),
            "elapsed_s": float(elapsed_s),
        }

    def fit_message(self, result, elapsed_s: float) -> str:
        """The page's line after a fit (markdown): the terms and the FOM before -> after."""
        terms = ", ".join(self.result_labels(result)) or "none"
        figures = self.fom_figures(result)
        if figures is None:
            said = "no maneuvers found, so no FOM"
        else:
            before, after, ratio, n = figures
            said = f"FOM {before:.3g} -> {after:.3g} {self.unit} (improvement ratio {ratio:.3g}, {n} maneuvers)"
        text = f"**{self.words} fit (Tolles-Lawson; beyond it: {safe_text(terms)})** ({elapsed_s:.2f} s): {said}"
        return text + "".join(f"  \n- {safe_text(w, 600)}" for w in result.warnings)

    def result_labels(self, result) -> list[str]:
        """A fit's terms beyond TL as the page names them (:meth:`term_labels`)."""
        return self.term_labels(self.result_effects(result), self.result_columns(result))

    def row_labels(self, row: dict) -> list[str]:
        """A history row's terms beyond TL as the page names them (a row of an earlier session file names no
        current column)."""
        return self.term_labels(row.get("effects", []), row.get("current_columns") or ())

    # --- the session file ----------------------------------------------------------------------------------
    def save_doc(self, kept: np.ndarray) -> dict:
        """What the session file keeps (``compensation_fit``): the samples, the terms beyond TL, the current term's
        columns, the history."""
        return {
            "kept": pack_mask(kept),
            "effects": list(self.effects),
            "current_columns": self.current_columns,
            "history": [dict(h) for h in self._history],
        }

    def save(self) -> dict | None:
        """The session file's ``compensation_fit``, or None before a fit (or on a record of the other
        compensation)."""
        return getattr(self.ctrl.state, "compensation_fit", None) if self.chosen else None

    def restore(self) -> str:
        """Run the saved compensation again (its samples and terms); a note for the page when it could not."""
        saved = getattr(self.ctrl.state, "compensation_fit", None)
        if not saved or not self.available or not self.chosen:
            return ""
        self._history = [dict(h) for h in saved.get("history", [])]
        if self.dataset.n_samples > RESTORE_MAX_SAMPLES:
            return f"the saved session ran the {self.words} fit: press the Step 1 button to see it again"
        try:
            kept = unpack_mask(saved["kept"], self.dataset.n_samples)
            columns = saved.get("current_columns") or None  # a file of before: the engine's first column
            self.fit(inputs=JobInputs(kept, ()), effects=saved.get("effects", []), again=True, current=columns)
        except (MagcalError, ValueError, KeyError, TypeError) as exc:
            with self.ctrl.state.lock:
                self.ctrl.state.compensation_fit = None
                self.ctrl.state.touch()
            return f"the saved {self.words} could not be run again ({safe_text(str(exc), 300)}); run it again"
        return ""

    def forget(self) -> None:
        super().forget()
        self.result = None
        self._current_columns = []
        if self.chosen:
            self.ctrl.state.compensation_fit = None

    def lesson_findings(self) -> dict | None:
        """The terms beyond TL and the FOM after (:attr:`unit`), None before a fit (what a lesson's check
        compares)."""
        if self.result is None:
            return None
        return {"effects": list(self.effects), "fom_nT": self.fom_now}


@register_session
class CompensationSession(CompensationBase):
    """The compensation of a scalar magnetometer beside a fluxgate (the model session of the fit mode
    ``"compensation"``): the engine's :data:`~magcal.modes.COMPENSATION`, its FOM in nT."""

    mode = "compensation"
    title = "compensation model"
    unit = "nT"
    section_title = "Compensation (a scalar magnetometer beside a fluxgate)"
    step_text = (
        "The record has a scalar magnetometer beside a fluxgate: fit the platform's permanent, induced and "
        "eddy fields (Tolles-Lawson) and judge it by the FOM in the maneuvers."
    )
    terms = dict(COMPENSATION_EFFECTS)
    noise_words = "the scalar's noise"

    def missing(self) -> list[str]:
        """What the record lacks for a compensation (empty when it holds a scalar column beside the fluxgate)."""
        try:
            why = COMPENSATION.applicable(self.dataset)
        except MagcalError as exc:
            why = str(exc)
        return [] if why is None else [why]

    @property
    def chosen(self) -> bool:
        """Whether the record holds a scalar beside the fluxgate (the mode ``auto`` takes first)."""
        return self.available

    def make_record(self):
        """The engine's :class:`~magcal.fitting.compensation.CompensationRecord` of the open data."""
        return compensation_record(self.dataset)

    def check_terms(self, names) -> list[str]:
        return list(check_effects(names))

    def engine_fit(self, names, kept, current=None):
        return COMPENSATION.fit(self.record(), effects=names, mask=kept, current=current)

    def engine_diagnose(self):
        # the model's current columns named: the record's others stay candidates, each of its own
        return COMPENSATION.diagnose(self.record(), effects=tuple(self.effects), current=self.current_columns or None)

    def result_effects(self, result) -> list[str]:
        return list(result.calibration.effects)

    def tl_words(self) -> str:
        tl = self.result.calibration.tl
        return f"Tolles-Lawson ({safe_text(', '.join(tl.terms))}: {len(tl.labels)} coefficients)"


def current_label(*columns: str) -> str:
    """The page's name of the current term taking ``columns``: ``current (cur_strb)`` (the engine's candidate
    label)."""
    return f"current ({', '.join(columns)})"


def split_label(label: str) -> tuple[str, list[str]]:
    """A term's name and its current columns from the page's label (``current (cur_strb)`` -> ``current``,
    ``[cur_strb]``; ``heading`` -> ``heading``, ``[]``)."""
    text = label.strip()
    if text.startswith("current") and text.endswith(")") and "(" in text:
        head, _, inside = text[:-1].partition("(")
        if head.strip() == "current":
            return "current", [c.strip() for c in inside.split(",") if c.strip()]
    return text, []


def band_passed_traces(session: CompensationSession) -> dict | None:
    """The band-passed scalar before and after the compensation against time, and the maneuvers' spans (the
    engine's band-pass, as its FOM uses), for the compensation panel's figure; None before a fit."""
    result = session.result
    if result is None:
        return None
    record, tl = session.record(), result.calibration.tl
    rate = record.sample_rate_hz
    t = record.time_s if record.time_s is not None else np.arange(record.n_samples) / rate
    before = bandpass(record.scalar_nT, rate, tl.passband_hz, tl.order)
    after = bandpass(tl.compensated_nT, rate, tl.passband_hz, tl.order)
    maneuvers = [] if result.fom is None else result.fom.after.maneuvers
    return {"time_s": np.asarray(t, float), "before_nT": before, "after_nT": after, "maneuvers": maneuvers}


#: The terms beyond TL the scalar's compensation offers, with what each is (the engine's words).
TERMS = dict(COMPENSATION_EFFECTS)
