"""What every fit returns: :class:`ModeResult`, the base of the results of the fit modes (:mod:`magcal.modes`).

The total-field pipeline's :class:`~magcal.fitting.pipeline.CalibrationResult`, the vector fit's
:class:`~magcal.fitting.vector.VectorFitResult` and the gravity fit's :class:`~magcal.fitting.gravity.GravityFitResult`
derive from it, so that the command line, :func:`magcal.calibrate` and the workbench read any fit the same way: its
:attr:`~ModeResult.mode`, its ``calibration``, what it has to say (``notes``, ``warnings``), its report
(``text()``) and its JSON document (``to_dict()``). Each result keeps its own figures beside these.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar

if TYPE_CHECKING:
    import numpy as np

    from magcal.calibration.calibration import Calibration
    from magcal.core.notes import Note


class _NoteTexts:
    """The ``warnings`` of a result that keeps only its ``notes``: their texts, read each time.

    A non-data descriptor: a result that stores its ``warnings`` (a dataclass field of that name) keeps them in the
    instance, which this then leaves alone; its ``notes`` are then made from them, so that the two agree either way.
    """

    def __get__(self, result, owner=None):
        if result is None:
            return self
        return [note.text for note in result.notes]


class ModeResult:
    """The outcome of a fit mode (:class:`magcal.modes.base.FitMode`): what every mode's result has.

    Attributes
    ----------
    mode : str
        The name of the fit mode that made it (``"total_field"``, ``"vector"``, ``"gravity"``...), a class
        attribute.
    calibration : Calibration
        The calibration to apply to new data (``.correct``, ``.world``, ``.heading``, ``.save``).
    notes : list of Note
        What the fit said that a user must hear (:mod:`magcal.core.notes`): raised as Python warnings by the public
        functions (:func:`magcal.calibrate` unless ``warn=False``), printed by the command line.
    warnings : list of str
        The texts of ``notes``, in order: one meaning for every mode. (The total-field report's wider list of
        lines, which also says what is only information, is its ``remarks``.)
    validation : object or None
        The fit judged on held-out samples when asked for (:meth:`magcal.modes.base.FitMode.validate`, an object with
        ``text()`` and ``to_dict()``), else None.
    """

    mode: ClassVar[str] = ""
    calibration: Calibration
    warnings = _NoteTexts()
    validation: Any = None

    if TYPE_CHECKING:  # a stored list in one result, made from the stored warnings in another

        @property
        def notes(self) -> list[Note]: ...

    def text(self) -> str:
        """The readable report of the fit (ends with a newline)."""
        raise NotImplementedError(f"{type(self).__name__} has no text report")

    def to_dict(self) -> dict:
        """The fit as a JSON-ready document, with ``"mode"``."""
        raise NotImplementedError(f"{type(self).__name__} has no JSON document")


@dataclass(kw_only=True)
class SampleFitResult(ModeResult):
    """A mode result that keeps what it said and which samples it fitted: the vector and gravity fits' results.

    Attributes
    ----------
    warnings : list of str
        What the fit said (its ``notes`` are made from these).
    n_samples : int
        The samples fitted.
    wall_s : float
        The fit's wall-clock time in s.
    fitted : numpy.ndarray of bool, shape (N,), or None
        One entry per sample of the dataset: True where the sample was fitted.
    """

    warnings: list = field(default_factory=list)
    n_samples: int = 0
    wall_s: float = 0.0
    fitted: np.ndarray | None = None
