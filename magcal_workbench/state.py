"""Session state of the workbench, free of the engine and of viser.

Everything a person changes in the workbench lives here: which samples are kept, the model's extra effects, the
method and reference field, the selected sensor, the history of steps with their RMS, and the lesson being
worked on. The state is plain data (numpy arrays, lists, strings), serialises to a JSON-ready dict for the session
file, and is tested without a browser.

The rejection of samples is a per-*sample* mask shared by all sensors (a sample is one row of the file: every
sensor's reading at one instant). Every change to the mask goes through :class:`Selection`, which keeps an
undo/redo history.

Threads: viser runs callbacks in a thread pool and engine steps run in a worker thread, so one re-entrant lock
(:attr:`SessionState.lock`, shared by its :class:`Selection`) guards every change of the state, its version
and its serialisation (the autosave holds it while it writes): two rejections at once both count.
"""

from __future__ import annotations

import base64
import threading
from dataclasses import dataclass, field

import numpy as np

#: Largest number of mask snapshots kept for undo.
UNDO_DEPTH = 200
#: Most mask snapshots a session file holds of each of undo and redo.
SAVED_UNDO = 50
#: Most samples of all the masks a session file holds together (the kept samples, the vector fit's, undo and redo;
#: a mask is a bit a sample in the file, a byte a sample once read): 4e8, 50 MB in the file and 400 MB read. Undo
#: and redo keep their most recent masks within it (a record of 10^8 samples: one of each).
MAX_MASK_SAMPLES = 400_000_000
#: Most steps a session keeps of each history (the fits and the vector fits): the oldest go first, and the page
#: says so. A step is a click; a thousand is far beyond a calibration's, and a session file stays small.
MAX_HISTORY_ROWS = 1000

#: Methods the workbench offers, in the order shown (names as :func:`magcal.fitting.pipeline.calibrate` takes them).
METHODS = ("ml", "ellipsoid", "pso", "ipso", "de")


def pack_mask(mask: np.ndarray) -> str:
    """A boolean mask as compact text (bit-packed, base64) for the session file."""
    mask = np.asarray(mask, dtype=bool)
    return base64.b64encode(np.packbits(mask).tobytes()).decode("ascii")


def unpack_mask(text: str, n: int) -> np.ndarray:
    """Inverse of :func:`pack_mask` for a mask of ``n`` samples."""
    bits = np.unpackbits(np.frombuffer(base64.b64decode(text.encode("ascii")), dtype=np.uint8))
    if bits.size < n:
        raise ValueError(f"mask holds {bits.size} samples, expected {n}")
    return bits[:n].astype(bool)


class Selection:
    """The kept-samples mask with undo and redo.

    Parameters
    ----------
    n_samples : int
        Number of samples N.
    kept : numpy.ndarray of bool, shape (N,), optional
        Initial mask (all kept if omitted).
    lock : threading.RLock, optional
        The lock every read-modify-write of the mask takes (the owning state's; a new one if omitted).
    """

    def __init__(self, n_samples: int, kept=None, lock=None):
        self.lock = lock if lock is not None else threading.RLock()
        self.n_samples = int(n_samples)
        self._kept = np.ones(self.n_samples, bool) if kept is None else np.array(kept, dtype=bool).copy()
        if self._kept.shape != (self.n_samples,):
            raise ValueError(f"kept mask has shape {self._kept.shape}, expected ({self.n_samples},)")
        self._undo: list[tuple[np.ndarray, str]] = []
        self._redo: list[tuple[np.ndarray, str]] = []

    # --- reading ---------------------------------------------------------------------------------------------
    @property
    def kept(self) -> np.ndarray:
        """A copy of the mask: True = sample used by the fits."""
        return self._kept.copy()

    @property
    def n_rejected(self) -> int:
        return int(self.n_samples - np.count_nonzero(self._kept))

    @property
    def rejected_indices(self) -> np.ndarray:
        return np.flatnonzero(~self._kept)

    @property
    def can_undo(self) -> bool:
        return bool(self._undo)

    @property
    def can_redo(self) -> bool:
        return bool(self._redo)

    # --- changing --------------------------------------------------------------------------------------------
    def _apply(self, new: np.ndarray, what: str) -> bool:
        # callers hold self.lock: the mask they changed is the one replaced
        if np.array_equal(new, self._kept):
            return False
        self._undo.append((self._kept.copy(), what))
        del self._undo[:-UNDO_DEPTH]
        self._redo.clear()
        self._kept = new
        return True

    def reject(self, indices, what: str = "reject") -> int:
        """Reject samples by index; returns how many changed from kept to rejected."""
        idx = self._check(indices)
        with self.lock:
            new = self._kept.copy()
            new[idx] = False
            changed = int(np.count_nonzero(self._kept[np.unique(idx)]))
            self._apply(new, what)
        return changed

    def restore(self, indices, what: str = "restore") -> int:
        """Restore (keep again) samples by index; returns how many changed from rejected to kept."""
        idx = self._check(indices)
        with self.lock:
            new = self._kept.copy()
            new[idx] = True
            changed = int(np.count_nonzero(~self._kept[np.unique(idx)]))
            self._apply(new, what)
        return changed

    def reset(self) -> bool:
        """Keep every sample again (one undo step)."""
        with self.lock:
            return self._apply(np.ones(self.n_samples, bool), "reset")

    def undo(self) -> str | None:
        """Go back one change; returns its description, or None if there was nothing to undo."""
        with self.lock:
            if not self._undo:
                return None
            previous, what = self._undo.pop()
            self._redo.append((self._kept, what))
            self._kept = previous
            return what

    def redo(self) -> str | None:
        """Redo the last undone change; returns its description, or None."""
        with self.lock:
            if not self._redo:
                return None
            nxt, what = self._redo.pop()
            self._undo.append((self._kept, what))
            self._kept = nxt
            return what

    def _check(self, indices) -> np.ndarray:
        idx = np.asarray(indices, dtype=int).reshape(-1)
        if idx.size and (idx.min() < 0 or idx.max() >= self.n_samples):
            raise IndexError(f"sample index out of range 0..{self.n_samples - 1}")
        return idx

    # --- session file ----------------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        with self.lock:
            return {
                "n_samples": self.n_samples,
                "kept": pack_mask(self._kept),
                "undo": [[pack_mask(m), w] for m, w in self._undo[-saved_masks(self.n_samples) :]],
                "redo": [[pack_mask(m), w] for m, w in self._redo[-saved_masks(self.n_samples) :]],
            }

    @classmethod
    def from_dict(cls, doc: dict, n_samples: int) -> Selection:
        if int(doc.get("n_samples", -1)) != n_samples:
            raise ValueError(f"the saved selection is for {doc.get('n_samples')} samples, the data have {n_samples}")
        sel = cls(n_samples, unpack_mask(doc["kept"], n_samples))
        sel._undo = [(unpack_mask(m, n_samples), w) for m, w in doc.get("undo", [])]
        sel._redo = [(unpack_mask(m, n_samples), w) for m, w in doc.get("redo", [])]
        return sel


def saved_masks(n_samples: int) -> int:
    """How many masks of undo, and of redo, a session of ``n_samples`` samples saves: :data:`SAVED_UNDO`, fewer
    where the masks would hold more than :data:`MAX_MASK_SAMPLES` samples together (the kept and the vector fit's
    masks first)."""
    room = MAX_MASK_SAMPLES // max(int(n_samples), 1) - 2
    return int(min(SAVED_UNDO, max(room // 2, 0)))


def trimmed(rows: list, what: str) -> str | None:
    """Drop the oldest of ``rows`` (in place) beyond :data:`MAX_HISTORY_ROWS`; returns the note that says so, or
    None."""
    over = len(rows) - MAX_HISTORY_ROWS
    if over <= 0:
        return None
    del rows[:over]
    return f"the {what} keeps its last {MAX_HISTORY_ROWS:,} steps: the oldest {over:,} were dropped"


@dataclass
class StepRecord:
    """One engine step as the history shows it.

    Attributes
    ----------
    step : str
        What ran (``"fit ellipsoid"``, ``"align sensors"``, ``"refine (ml)"``, ``"add temperature_bias"`` ...).
    rms_nT : float
        Total-field RMS over all sensors and kept samples after the step, nT.
    floor_nT : float or None
        The noise floor to compare with (estimated or known), nT.
    effects : list of str
        The model's extra effects at that step.
    n_kept : int
        Samples used.
    changes : str
        One line saying what changed.
    elapsed_s : float
        Wall time of the step, s.
    fit : dict or None
        The solver's outcome when the step ran a fit: ``success``, ``status``, ``message``, ``nfev`` (as
        :meth:`magcal.fitting.fitter.FitResult.summary` gives them); None for steps without one.
    """

    #: The keys of :attr:`fit`.
    FIT_KEYS = ("success", "status", "message", "nfev")

    step: str
    rms_nT: float
    floor_nT: float | None = None
    effects: list = field(default_factory=list)
    n_kept: int = 0
    changes: str = ""
    elapsed_s: float = 0.0
    fit: dict | None = None
    held_out_rms_nT: float | None = None

    def to_dict(self) -> dict:
        return {
            "step": self.step,
            "rms_nT": _num(self.rms_nT),
            "floor_nT": _num(self.floor_nT),
            "effects": list(self.effects),
            "n_kept": int(self.n_kept),
            "changes": self.changes,
            "elapsed_s": float(self.elapsed_s),
            "fit": None if self.fit is None else dict(self.fit),
            "held_out_rms_nT": _num(self.held_out_rms_nT),
        }

    @classmethod
    def from_dict(cls, doc: dict) -> StepRecord:
        return cls(
            step=doc["step"],
            rms_nT=_num(doc["rms_nT"]),
            floor_nT=_num(doc.get("floor_nT")),
            effects=list(doc.get("effects", [])),
            n_kept=int(doc.get("n_kept", 0)),
            changes=doc.get("changes", ""),
            elapsed_s=float(doc.get("elapsed_s", 0.0)),
            fit=doc.get("fit"),
            held_out_rms_nT=_num(doc.get("held_out_rms_nT")),
        )


@dataclass
class VectorStep:
    """One fit of the vector model (attitude-aided) as its history shows it.

    Attributes
    ----------
    step : str
        What ran (``"vector fit"``, ``"vector: add current_field"`` ...).
    world_rms_nT : list of float
        RMS of the world residual ``B_world - B_ref`` per component north, east, down (all sensors, the samples
        fitted), nT.
    total_rms_nT : float or None
        RMS of ``|B| - F`` over the same samples, nT.
    effects : list of str
        The vector model's effects at that step.
    n_fitted : int
        Samples fitted.
    changes : str
        One line saying what changed.
    elapsed_s : float
        Wall time of the step, s.
    """

    step: str
    world_rms_nT: list
    total_rms_nT: float | None = None
    effects: list = field(default_factory=list)
    n_fitted: int = 0
    changes: str = ""
    elapsed_s: float = 0.0

    @property
    def world_nT(self) -> float:
        """RMS over the three world components, nT (NaN when none is known)."""
        w = np.array([np.nan if v is None else v for v in self.world_rms_nT], dtype=float)
        return float(np.sqrt(np.mean(w**2))) if w.size else float("nan")

    def to_dict(self) -> dict:
        return {
            "step": self.step,
            "world_rms_nT": [_num(v) for v in self.world_rms_nT],
            "total_rms_nT": _num(self.total_rms_nT),
            "effects": list(self.effects),
            "n_fitted": int(self.n_fitted),
            "changes": self.changes,
            "elapsed_s": float(self.elapsed_s),
        }


def _num(v):
    if v is None:
        return None
    v = float(v)
    return v if np.isfinite(v) else None


def effect_name(label: str) -> str:
    """``temperature_bias:2`` -> ``temperature_bias``."""
    return label.partition(":")[0]


def with_effect(effects, label: str) -> list[str]:
    """``effects`` with ``label`` added as :meth:`SessionState.add_effect` adds it (unchanged if it, or the same
    effect for all sensors, is in already; an all-sensor label replaces the per-sensor ones of its effect)."""
    label = label.strip()
    effects = list(effects)
    name = effect_name(label)
    if label in effects or name in effects:
        return effects
    if ":" not in label:
        effects = [e for e in effects if effect_name(e) != name]
    return effects + [label]


@dataclass(frozen=True)
class JobInputs:
    """What an engine step works on, fixed when the step is asked for (:meth:`SessionState.job_inputs`) and handed
    to it as an argument: a rejection or a ticked effect made while the step runs in the worker changes neither
    what it fits nor what its history row says it fitted (no thread-local or other hidden state).

    Parameters
    ----------
    kept : numpy.ndarray of bool, shape (N,)
        The samples the step fits (copied, read-only).
    effects : sequence of str
        The model's effect labels beyond the base terms (a tuple).
    """

    kept: np.ndarray
    effects: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        kept = np.array(self.kept, dtype=bool)  # its own copy: the state's mask goes on changing
        kept.setflags(write=False)
        object.__setattr__(self, "kept", kept)
        object.__setattr__(self, "effects", tuple(self.effects))

    def with_effect(self, label: str) -> JobInputs:
        """The same samples, with ``label`` added to the model (:func:`with_effect`)."""
        return JobInputs(self.kept, tuple(with_effect(self.effects, label)))


class SessionState:
    """All user-facing state of one workbench session.

    Parameters
    ----------
    n_samples, n_sensors : int
        Size of the loaded data.
    data_path : str, optional
        The data file (CSV) the session works on.
    lesson : str, optional
        Name of the lesson, when the data come from one.

    Attributes
    ----------
    selection : Selection
        Kept samples with undo/redo.
    effects : list of str
        Extra effect labels in the model (``NAME`` or ``NAME:SENSOR``, SENSOR 1-based), in the order added.
    effects_files : list of str
        Absolute paths of the user's effect files loaded in this session (offered, never run, when it reopens).
    method : str
        One of :data:`METHODS`.
    reference_nT : float or None
        Reference total field in nT typed by the user; None = use the file's or fit it.
    fit_reference : bool
        Fit the field magnitude even when a reference is known.
    robust : bool
        Use the robust loss.
    sensor : int or None
        Selected sensor (0-based) for the scene; None shows all.
    history : list of StepRecord
    calibration : dict or None
        The last calibration as its JSON document (``Calibration.to_dict``).
    answer_revealed : bool
        Whether the lesson's answer has been shown.
    location : dict or None
        The place and date typed in the page for the IGRF reference (``lat_deg``, ``lon_deg``, ``alt_m``,
        ``date``: :class:`magcal_workbench.vectormodel.Location`); None when none was typed.
    vector_fit : dict or None
        The last vector fit's settings (``kept``: the samples it was asked to use, a packed mask; ``robust``;
        ``noise_nT`` or None; ``effects``: the vector model's effect labels), so that a reopened session runs it
        again (:meth:`magcal_workbench.vectormodel.VectorModel.restore`); None when none was run (or its reference
        changed since).
    vector_history : list of VectorStep
        The vector model's fits, in order: their world RMS per component and |B| RMS.
    gravity_fit : dict or None
        The last gravity fit's settings (``kept``: a packed mask; ``robust``), so that a reopened session runs it
        again (:meth:`magcal_workbench.gravitymodel.GravitySession.restore`); None when none was run.
    compensation_fit : dict or None
        The last compensation's settings (``kept``: a packed mask; ``effects``: the terms beyond Tolles-Lawson;
        ``history``: the FOM per step), run again when the session reopens
        (:meth:`magcal_workbench.compensationmodel.CompensationSession.restore`); None when none was run.
    """

    def __init__(self, n_samples: int, n_sensors: int, data_path: str | None = None, lesson: str | None = None):
        self._lock = threading.RLock()
        self.n_samples = int(n_samples)
        self.n_sensors = int(n_sensors)
        self.data_path = data_path
        self.lesson = lesson
        self.selection = Selection(self.n_samples)
        self.effects: list[str] = []
        self.effects_files: list[str] = []
        self.method = "ml"
        self.reference_nT: float | None = None
        self.fit_reference = False
        self.robust = False
        self.sensor: int | None = None
        self.history: list[StepRecord] = []
        self.calibration: dict | None = None
        self.answer_revealed = False
        self.noise_nT: float | None = None  # per-axis noise given by the user (nT); None = the data's or estimated
        self.location: dict | None = None  # the place and date typed for IGRF (vectormodel.Location.to_dict)
        self.vector_fit: dict | None = None  # the last vector fit's settings: kept (packed mask), robust, noise_nT,
        # effects
        self.vector_history: list[VectorStep] = []  # the vector model's fits (world N/E/D and |B| RMS)
        self.gravity_fit: dict | None = None  # the last gravity fit's settings: kept (packed mask), robust
        self.compensation_fit: dict | None = None  # the last compensation: kept (packed mask), effects, history
        self.version = 0  # bumped on every change; the autosave and the views compare it
        #: What bounding the session changed, to say once (the oldest steps dropped: :data:`MAX_HISTORY_ROWS`).
        self.notes: list[str] = []
        #: When the session file read was saved (its ``saved_at``; empty for a new session).
        self.saved_at = ""

    @property
    def lock(self) -> threading.RLock:
        """The one lock of the session: changes, the version and the autosave's serialisation take it."""
        return self._lock

    @property
    def selection(self) -> Selection:
        return self._selection

    @selection.setter
    def selection(self, sel: Selection) -> None:
        sel.lock = self._lock  # a selection read from a session file joins the state's lock
        self._selection = sel

    # --- model ----------------------------------------------------------------------------------------------
    def add_effect(self, label: str) -> bool:
        """Add an effect label; returns False if it (or the same effect for all sensors) is already in."""
        with self._lock:
            effects = with_effect(self.effects, label)  # an all-sensor term replaces per-sensor ones of its effect
            if effects == self.effects:
                return False
            self.effects = effects
            self.touch()
            return True

    def job_inputs(self) -> JobInputs:
        """The kept mask and the model's effects of this moment, fixed for a step (:class:`JobInputs`)."""
        with self._lock:
            return JobInputs(self._selection.kept, tuple(self.effects))

    def remove_effect(self, name: str) -> bool:
        """Remove every label of an effect (``name``) or one exact label; returns True if any went."""
        with self._lock:
            keep = [e for e in self.effects if e != name and effect_name(e) != name]
            changed = len(keep) != len(self.effects)
            self.effects = keep
            if changed:
                self.touch()
            return changed

    def has_effect(self, name: str) -> bool:
        return any(effect_name(e) == name for e in self.effects)

    # --- steps ---------------------------------------------------------------------------------------------
    def record(self, record: StepRecord, calibration: dict | None = None) -> None:
        """Append a step to the history (and keep the calibration it produced)."""
        with self._lock:
            self.history.append(record)
            self._note(trimmed(self.history, "history"))
            if calibration is not None:
                self.calibration = calibration
            self.touch()

    def record_vector(self, step: VectorStep) -> None:
        """Append a vector fit to :attr:`vector_history` (its oldest dropped beyond :data:`MAX_HISTORY_ROWS`)."""
        with self._lock:
            self.vector_history.append(step)
            self._note(trimmed(self.vector_history, "vector history"))
            self.touch()

    def _note(self, text: str | None) -> None:
        if text and not any(n.split(":")[0] == text.split(":")[0] for n in self.notes):  # said once per history
            self.notes.append(text)

    def rms_series(self):
        """(step index, RMS nT, floor nT or NaN) arrays for the history plot."""
        x = np.arange(len(self.history), dtype=float)
        y = np.array([np.nan if r.rms_nT is None else r.rms_nT for r in self.history], dtype=float)
        f = np.array([np.nan if r.floor_nT is None else r.floor_nT for r in self.history], dtype=float)
        return x, y, f

    # --- selection shortcuts -------------------------------------------------------------------------------
    @property
    def kept(self) -> np.ndarray:
        return self.selection.kept

    def touch(self) -> None:
        with self._lock:
            self.version += 1

    # --- session file ---------------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        with self._lock:
            return {
                "format": "magcal-workbench-session",
                "version": 1,
                "data_path": self.data_path,
                "lesson": self.lesson,
                "n_samples": self.n_samples,
                "n_sensors": self.n_sensors,
                "selection": self.selection.to_dict(),
                "effects": list(self.effects),
                "effects_files": list(self.effects_files),
                "method": self.method,
                "reference_nT": self.reference_nT,
                "fit_reference": self.fit_reference,
                "robust": self.robust,
                "sensor": self.sensor,
                "history": [r.to_dict() for r in self.history],
                "calibration": self.calibration,
                "answer_revealed": self.answer_revealed,
                "noise_nT": self.noise_nT,
                "location": None if self.location is None else dict(self.location),
                "vector_fit": None if self.vector_fit is None else dict(self.vector_fit),
                "vector_history": [r.to_dict() for r in self.vector_history],
                "gravity_fit": None if self.gravity_fit is None else dict(self.gravity_fit),
                "compensation_fit": None if self.compensation_fit is None else dict(self.compensation_fit),
            }
