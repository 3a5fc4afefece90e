"""The forward selection every diagnosis runs: take the best candidate whose gain holds on held-out data, refit,
look again, up to ``max_effects``.

A round's candidates come judged: refitted, and each supported one fitted on part of the record and scored on the
rest by the diagnosis's :class:`HeldOutJudge` (the total-field diagnosis's :class:`magcal.diagnosis.verdict._HeldOut`,
the vector diagnosis's :class:`magcal.diagnosis.vector._Judge`), so that ``holds`` says whether its gain holds on data the fit did not see.
:func:`forward_selection` takes the best of them that holds (:func:`first_that_holds`), lets the diagnosis add it to
its model, and asks for the next round beside the model with it; it stops when none holds, when a round finds no
candidate worth judging, or after ``max_effects``.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any, Protocol


class HeldOutJudge(Protocol):
    """The held-out judgement of a diagnosis's candidates: the total-field diagnosis's
    (:class:`magcal.diagnosis.verdict._HeldOut`: blocks of the record and its later stretch) and the vector
    diagnosis's (:class:`magcal.diagnosis.vector._Judge`: the later part and other flights, each component at its
    noise)."""

    def judge(self, base_fit: Any, c: Any, fitted: Any = None) -> str | None:
        """Judge candidate ``c`` against the round's base model ``base_fit`` (``fitted``: the candidate's fits,
        when already made): set its ``holds`` (True, False, or None when it could not be judged) and its held-out
        figures. Returns a warning for the diagnosis's list when its gain does not hold, or None."""
        ...


def first_that_holds(cands: Iterable, eligible: Callable[[Any], bool] = bool, in_sample_ok: bool = False) -> Any:
    """The first of ``cands`` (best first) that ``eligible`` accepts and whose gain holds on held-out data, or None.

    Parameters
    ----------
    cands : iterable of candidates
        Each with ``holds``: True (its gain holds held out), False (it does not) or None (not judged).
    eligible : callable
        Whether the diagnosis may take a candidate at all (refitted, supported in-sample, physical...).
    in_sample_ok : bool
        Whether a candidate that was not judged (``holds`` None: the record too short to hold samples out) may be
        taken on its in-sample evidence; else only one that holds is.
    """
    for c in cands:
        if not eligible(c):
            continue
        if c.holds or (in_sample_ok and c.holds is None):
            return c
    return None


def forward_selection(
    first: Callable[[], Any],
    pick: Callable[[Any], Any],
    take: Callable[[int, Any, Any], None],
    further: Callable[[int, Any], Any],
    max_effects: int,
) -> list:
    """Greedy forward selection judged held out; the candidates taken, in order.

    Parameters
    ----------
    first : callable
        ``first()``: the first round's candidates, judged (called only when ``max_effects`` is positive); None
        when there are none.
    pick : callable
        ``pick(cands)``: the round's candidate to take (usually :func:`first_that_holds`), or None to stop.
    take : callable
        ``take(step, best, cands)``: add ``best`` to the diagnosis's model (0-based ``step``).
    further : callable
        ``further(step, best)``: the next round's candidates beside the model with ``best``, judged; None when no
        candidate is worth judging (the selection stops).
    max_effects : int
        Most candidates taken.
    """
    chosen: list = []
    cands = first() if max_effects > 0 else None
    for step in range(max_effects):
        if cands is None:
            break
        best = pick(cands)
        if best is None:
            break
        chosen.append(best)
        take(step, best, cands)
        if step + 1 >= max_effects:
            break
        cands = further(step, best)
    return chosen
