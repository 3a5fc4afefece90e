"""What every diagnosis is: its verdicts, defined once with their meanings, and the names it answers to.

The total-field diagnosis (:class:`magcal.diagnosis.verdict.Diagnosis`), the vector diagnosis
(:class:`magcal.diagnosis.vector.VectorDiagnosis`) and the gravity calibration's dip evidence
(:class:`magcal.diagnosis.gravity.DipEvidence`) derive from :class:`DiagnosisBase`, so that a caller (the command
line, the workbench, a benchmark) reads any of them by one set of names:

``verdict``
    One of :data:`VERDICTS`.
``summary``
    One or two sentences for people.
``candidates``
    The candidate effects, best first.
``explained_by``
    The advice: the labels of the effects to add to the calibration (judged on held-out data).
``remaining``
    The structure still left in the residuals once ``explained_by`` is added.
``noise``
    The noise the verdict is stated against: an object with ``sigma_nT`` (nT), ``source``, ``text()`` and
    ``to_dict()`` (:class:`NoiseLevel`), or None where a diagnosis has no noise figure.
``notes``
    What the diagnosis's own fits said (:mod:`magcal.core.notes`).
``to_dict()``, ``text()``
    The JSON document and the readable report.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol, runtime_checkable

from magcal.core.jsonable import jsonable

#: The verdicts of a diagnosis and what each means. Every diagnosis gives one of these names.
VERDICTS: dict[str, str] = {
    "adequate": "the residuals are at their noise (or within a stated fraction of the floor): nothing to add",
    "missing_effect": "catalogue effects, judged on data the fit did not see, bring the residuals down to the noise: "
    "they are the advice (explained_by)",
    "unexplained": "significant structure is left that no catalogue effect removes (or the record does not determine "
    "the base calibration): it is described, and nothing is advised for it",
    "not_judged": "no held-out judgement could be made (a record too short to hold a part out, no other flight): "
    "nothing is advised; the summary says what would let it judge",
}


@runtime_checkable
class NoiseLevel(Protocol):
    """The noise a diagnosis states its verdict against (:class:`magcal.checks.noise.NoiseEstimate` for the total
    field, :class:`magcal.diagnosis.vector.VectorNoise` for the vector fit)."""

    @property
    def sigma_nT(self) -> float:
        """The noise of the total field, nT."""
        ...

    @property
    def source(self) -> str:
        """Where it came from, in a word."""
        ...

    def text(self) -> str:
        """In words, for a report."""
        ...

    def to_dict(self) -> dict:
        """JSON-ready figures."""
        ...


class DiagnosisBase:
    """The names every diagnosis answers to (module docstring); a subclass (a dataclass) holds the values.

    A subclass sets ``verdict``, ``summary``, ``candidates``, ``explained_by``, ``remaining``, ``noise``,
    ``notes``, ``warnings``, ``evidence`` and ``elapsed_s`` and writes :meth:`text`; :meth:`to_dict` gives the keys
    they share and a subclass adds its own (:meth:`_own_dict`).
    """

    verdict: str
    summary: str
    candidates: list
    explained_by: list
    remaining: list
    noise: Any
    notes: list
    warnings: list
    evidence: dict
    elapsed_s: float

    #: The diagnosis's kind in the JSON document (``"mode"``); None: the key is not written.
    mode: str | None = None

    @property
    def best(self) -> Any:
        """The best candidate, or None."""
        return self.candidates[0] if self.candidates else None

    @property
    def noise_nT(self) -> float | None:
        """The noise of the total field the verdict is stated against, nT (None without a noise figure)."""
        return None if self.noise is None else float(self.noise.sigma_nT)

    @property
    def verdict_meaning(self) -> str:
        """What the verdict means (:data:`VERDICTS`)."""
        return VERDICTS.get(self.verdict, "")

    def where_text(self) -> str:
        """How long the diagnosis took, in words (``"4.3 s"``)."""
        return f"{float(self.elapsed_s):.1f} s"

    def plot_data(self) -> dict:
        """:attr:`evidence` with arrays turned into lists (JSON-ready), for the workbench."""
        return jsonable(self.evidence)

    def to_dict(self) -> dict:
        """The JSON document (``magcal diagnose --json``): the shared keys, then the diagnosis's own."""
        out: dict[str, Any] = {} if self.mode is None else {"mode": self.mode}
        out.update(
            verdict=self.verdict,
            summary=self.summary,
            candidates=[c.to_dict() for c in self.candidates],
            explained_by=list(self.explained_by),
            remaining_structure=[s.to_dict() for s in self.remaining],
            noise=None if self.noise is None else jsonable(self.noise.to_dict()),
            warnings=list(self.warnings),
            elapsed_s=round(float(self.elapsed_s), 3),
        )
        out.update(self._own_dict())
        return out

    def _own_dict(self) -> dict:
        """The keys of this diagnosis's JSON document beside the shared ones."""
        return {}

    def text(self, limit: int = 12) -> str:
        """The readable report: the verdict, the summary and the candidates (at most ``limit``)."""
        raise NotImplementedError

    def table(self, limit: int = 12) -> str:
        """:meth:`text` (the name the command line reads)."""
        return self.text(limit)


def progress_reporter(progress: Callable[[str, float], Any] | None) -> Callable[[str, float], None]:
    """``report(message, fraction)``: a diagnosis's progress handed to ``progress`` (a caller's callback), or
    nowhere when it is None."""

    def report(message: str, fraction: float) -> None:
        if progress is not None:
            progress(message, fraction)

    return report
