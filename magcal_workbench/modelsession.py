"""One fit mode's model in the page: :class:`ModelSession`, the one shape the total-field, vector and gravity fits take.

A model session belongs to one :class:`~magcal_workbench.controller.Controller` (which keeps the data, the selection,
the jobs and the autosave) and holds one fit mode's model: its last fit and calibration, its effects beyond the base
terms, its diagnosis, its history of fits, and what the session file keeps of it. Every mode offers the same calls:

=====================  ==============================================================================================
``fit(inputs=)``       the mode's fit on the kept samples (``inputs``: the step's
                       :class:`~magcal_workbench.state.JobInputs`, default those of now)
``diagnose(inputs=)``  the mode's diagnosis of its fit (the candidate effects, judged on held-out data)
``add(label)``         a candidate (the top one by default) put into the model, and the refit; ``add_all(labels)``
``remove(label)``      an effect (the last added by default) taken out, and the refit
``history()``          the fits of this session, oldest first (the session file's rows)
``save()``             the mode's fit as the session file keeps it (written into the session state), or None
``restore()``          the saved fit run again when the session reopens; a note for the page when it could not be
=====================  ==============================================================================================

and the loop's questions the page asks without knowing the mode: ``candidate_labels()``, ``advice()``,
``candidate_holds(label)``, ``effects``, ``diagnosis``, ``calibration``. The mode names are the engine's fit modes'
(``magcal.modes``: ``"total_field"``, ``"vector"``, ``"gravity"``, ``"compensation"``, ``"cross_compensation"``), so that another mode's page is one more class
registered in :data:`MODEL_SESSIONS` (:func:`register_session`). The physics is the engine's: a session only chooses
what to run on which samples and tells the controller what changed (:meth:`Controller.emit
<magcal_workbench.controller.Controller.emit>`, a :class:`~magcal_workbench.events.Change`).
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from magcal.core.errors import MagcalError

from .figures import candidate_label
from .markup import clean_text
from .state import JobInputs


class ModelSession:
    """The model of one fit mode on a controller's data (the base of every mode's session).

    Parameters
    ----------
    ctrl : magcal_workbench.controller.Controller
        Gives the dataset, the session state (kept mask, settings, the session file's fields), the page's message
        (``say``), progress (``report_progress``) and change events (``emit``).

    Attributes
    ----------
    mode : str
        The fit mode's name (the engine's: ``"total_field"``, ``"vector"``, ``"gravity"``).
    title : str
        What the page calls the model (``"total-field model"``).
    diagnosis : object or None
        The last diagnosis of this mode's fit (None after a fit: it diagnosed the one before).
    """

    mode: ClassVar[str] = ""
    title: ClassVar[str] = ""

    def __init__(self, ctrl):
        self.ctrl = ctrl
        self.diagnosis: Any = None
        self._effects: list[str] = []

    @property
    def effects(self) -> list[str]:
        """The model's effect labels beyond the base terms, in the order added."""
        return list(self._effects)

    @effects.setter
    def effects(self, labels) -> None:
        self._effects = list(labels)

    # --- what the data offer -------------------------------------------------------------------------------
    @property
    def dataset(self):
        """The controller's dataset (the open data)."""
        return self.ctrl.dataset

    def missing(self) -> list[str]:
        """What this mode's fit lacks in the data (empty when it can run), in words for the page."""
        return []

    @property
    def available(self) -> bool:
        """Whether the data hold what this mode needs (:meth:`missing` is empty)."""
        return not self.missing()

    # --- the model -----------------------------------------------------------------------------------------
    @property
    def calibration(self):
        """The last fit's :class:`~magcal.calibration.calibration.Calibration`, or None before a fit."""
        return None

    def inputs(self, inputs: JobInputs | None = None, kept: np.ndarray | None = None) -> JobInputs:
        """The step's inputs: ``inputs`` when given, else the kept samples ``kept`` (default: those of now) with the
        model's effects of now."""
        if inputs is not None:
            return inputs
        now = self.ctrl.job_inputs()
        if kept is None:
            return JobInputs(now.kept, tuple(self.effects))
        return JobInputs(np.asarray(kept, dtype=bool), tuple(self.effects))

    # --- the loop ------------------------------------------------------------------------------------------
    def fit(self, *, inputs: JobInputs | None = None):
        """The mode's fit on ``inputs``' kept samples (default: those of now)."""
        raise NotImplementedError

    def diagnose(self, *, inputs: JobInputs | None = None):
        """The mode's diagnosis of its fit; a mode without one says so."""
        raise MagcalError(f"the {self.title} has no diagnosis of its effects")

    def add_all(self, labels, *, inputs: JobInputs | None = None, note: str = ""):
        """Put ``labels`` into the model and refit once; ``note`` is appended to the history's step."""
        raise MagcalError(f"the {self.title} takes no effects beyond its base terms")

    def add(self, label: str | None = None, *, inputs: JobInputs | None = None, note: str = ""):
        """Put a candidate (the top one of :meth:`candidate_labels` by default) into the model and refit."""
        if label is None:
            labels = self.candidate_labels()
            if not labels:
                raise MagcalError("diagnose first: there is no suggested effect to add")
            label = labels[0]
        return self.add_all([label], inputs=inputs, note=note)

    def remove(self, label: str | None = None, *, inputs: JobInputs | None = None):
        """Take ``label`` (the last added by default) out of the model and refit."""
        effects = self.effects
        if not effects:
            raise MagcalError(f"the {self.title} holds no effect beyond the base terms")
        label = effects[-1] if label is None else label
        if label not in effects:
            raise MagcalError(f"{clean_text(repr(label), 80)} is not in the {self.title}")
        return self._refit_without(label, inputs)

    def _refit_without(self, label: str, inputs: JobInputs | None):
        raise NotImplementedError

    def candidate_labels(self) -> list[str]:
        """What Add may put into the model from the last diagnosis, the first to add first."""
        return []

    def advice(self) -> list[str]:
        """What the last diagnosis advises (its ``explained_by``: judged on held-out data) that the model does not
        hold yet; empty before a diagnosis."""
        advised = getattr(self.diagnosis, "explained_by", None) or []
        model = self.effects
        return [label for label in advised if label not in model]

    def candidate_holds(self, label: str) -> bool:
        """Whether the last diagnosis found that the candidate ``label``'s gain holds on data the fit did not see
        (or advises it); False for a candidate it did not judge or judged not to hold."""
        if label in self.advice():
            return True
        candidates = getattr(self.diagnosis, "candidates", None) or []
        return any(candidate_label(c) == label and getattr(c, "holds", None) is True for c in candidates)

    def history(self) -> list:
        """The fits of this model, oldest first."""
        return []

    # --- the session file ----------------------------------------------------------------------------------
    def save(self) -> dict | None:
        """The mode's fit as the session file keeps it (also written into the controller's session state), or None
        before a fit."""
        return None

    def restore(self) -> str:
        """Run the saved fit again (a reopened session); a note for the page when it could not (empty otherwise:
        the fit's own message says what it did)."""
        return ""

    def forget(self) -> None:
        """Drop the last fit and its diagnosis."""
        self.diagnosis = None

    def lesson_findings(self) -> dict | None:
        """What a lesson's check compares with the fit (:meth:`magcal_workbench.lessons.Lesson.check`), or None."""
        return None


#: The built-in fit modes' names (the engine's, ``magcal.modes``), in the order a controller makes and restores them.
MODES = ("total_field", "vector", "gravity", "compensation", "cross_compensation")

#: The model sessions by fit mode's name (:func:`register_session`).
MODEL_SESSIONS: dict[str, type[ModelSession]] = {}


def session_kinds() -> list[tuple[str, type[ModelSession]]]:
    """The registered model sessions, the built-in modes first in the order of :data:`MODES`, then the others in
    the order registered."""
    order = {name: i for i, name in enumerate(MODES)}
    return sorted(MODEL_SESSIONS.items(), key=lambda item: order.get(item[0], len(order)))


def register_session(cls: type[ModelSession]) -> type[ModelSession]:
    """Add a mode's session class to :data:`MODEL_SESSIONS` under its :attr:`ModelSession.mode` (a class
    decorator); a name already taken by another class is refused."""
    if not cls.mode:
        raise ValueError(f"{cls.__name__} names no mode")
    known = MODEL_SESSIONS.get(cls.mode)
    if known is not None and known is not cls:
        raise ValueError(f"the mode {cls.mode!r} has a session already ({known.__name__})")
    MODEL_SESSIONS[cls.mode] = cls
    return cls
