"""Notes: what a step has to say besides its result, passed back as values.

A step of the engine (reading, checking, fitting, diagnosing, applying) that has something to tell the user -- weak
coverage, a fit that stopped early, record-only terms dropped -- returns it as a :class:`Note` in its result (a
``notes`` field: :attr:`magcal.fitting.pipeline.CalibrationResult.notes`, :attr:`magcal.fitting.fitter.FitResult.notes`,
:attr:`magcal.diagnosis.Diagnosis.notes`...) or as a second return value. Notes are raised as Python warnings only at
the boundary a user calls (:func:`magcal.calibrate`, :func:`magcal.diagnose`, :func:`magcal.read_csv`,
:func:`magcal.read_log`, :meth:`magcal.Calibration.correct`...: their ``warn=True``), with :func:`warn`, and the
command line prints them. The readers' notes are their dataset's :attr:`~magcal.data.dataset.Dataset.notes` (a
streaming reader's, :attr:`magcal.data.io.CsvSource.notes`); no step takes a list to fill.

Why not warnings all the way: :func:`warnings.catch_warnings` swaps process-wide state, so a step run on a thread
(the diagnosis's pool, the noise prefetch, the workbench's worker and live refits) could lose a note or hand it to
another job's report. A note held in its step's result goes where the result goes.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from magcal.core.errors import DataWarning


@dataclass(frozen=True)
class Note:
    """One thing a step says besides its result.

    Attributes
    ----------
    text : str
        The message, as the user reads it (the warning's text at the boundary).
    category : type of Warning
        The warning class it is raised as at the boundary (:mod:`magcal.core.errors`: :class:`DataWarning`,
        :class:`CoverageWarning`, :class:`ConvergenceWarning`, :class:`RecordTermWarning`; or a standard one).
    where : str
        The step that said it (``"fit"``, ``"coverage"``, ``"calibrate"``...), for people reading a log.
    """

    text: str
    category: type = DataWarning
    where: str = ""

    def __post_init__(self):
        if not (isinstance(self.category, type) and issubclass(self.category, Warning)):
            raise TypeError(f"a note's category must be a Warning subclass, got {self.category!r}")

    def __str__(self) -> str:
        return self.text

    def is_a(self, category) -> bool:
        """Whether the note is raised as ``category`` (or a subclass of it)."""
        return issubclass(self.category, category)


def unique(notes: Iterable[Note]) -> list[Note]:
    """``notes`` in their order, each text and category once (a note two fits make alike is said once)."""
    seen, out = set(), []
    for note in notes:
        key = (note.text, note.category)
        if key not in seen:
            seen.add(key)
            out.append(note)
    return out


def texts(notes: Iterable[Note], category=Warning) -> list[str]:
    """The texts of the notes raised as ``category`` (default all), in order."""
    return [n.text for n in notes if n.is_a(category)]


def warn(notes: Iterable[Note], stacklevel: int = 2) -> None:
    """Raise each note as a Python warning of its category: the API boundary's one use of :mod:`warnings`.

    ``stacklevel`` as in :func:`warnings.warn`, counted from the caller of :func:`warn` (2: the line that called
    the function calling :func:`warn`).
    """
    for note in notes:
        warnings.warn(note.text, note.category, stacklevel=stacklevel + 1)


def runs(missing, first_row: int = 1) -> list[tuple[int, int]]:
    """The runs of consecutive flagged rows in ``missing`` (bool, one per sample) as ``(first, last)`` row numbers,
    the first sample being row ``first_row``."""
    idx = np.flatnonzero(np.asarray(missing, dtype=bool))
    if idx.size == 0:
        return []
    breaks = np.flatnonzero(np.diff(idx) > 1)
    starts = np.concatenate([idx[:1], idx[breaks + 1]]) + first_row
    ends = np.concatenate([idx[breaks], idx[-1:]]) + first_row
    return list(zip(starts.tolist(), ends.tolist()))


def runs_text(row_runs_: list[tuple[int, int]], most: int = 3) -> str:
    """``"rows 1-300, 1201-1212, 4000 and 2 more runs"``: the first ``most`` runs of :func:`runs`."""
    if not row_runs_:
        return "no rows"
    parts = [f"{a}" if a == b else f"{a}-{b}" for a, b in row_runs_[:most]]
    more = len(row_runs_) - most
    single = len(row_runs_) == 1 and row_runs_[0][0] == row_runs_[0][1]
    text = ("row " if single else "rows ") + ", ".join(parts)
    return text + (f" and {more} more run{'s' if more > 1 else ''}" if more > 0 else "")


def row_runs(missing, first_row: int = 1, most: int = 3) -> str:
    """The rows flagged in ``missing`` (bool, one per sample) as a user counts them: runs of consecutive rows,
    ``"rows 1-300, 1201-1212, 4000 and 2 more runs"`` (the first ``most`` runs); ``first_row`` is the number of the
    first sample (1: data rows counted from 1, as the CSV readers' messages do)."""
    return runs_text(runs(missing, first_row), most)
