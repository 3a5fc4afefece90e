"""Numbers as the page writes them, and the one RMS of a residual the page shows (no physics: formatting).

Used by the controller, the model sessions (:mod:`magcal_workbench.modelsession`) and the panels' texts.
"""

from __future__ import annotations

import numpy as np

#: Longest untrusted text (an exception's message, a warning) shown in the page, characters.
MESSAGE_LEN = 1000


def format_number(v, digits: int = 4) -> str:
    """``v`` to ``digits`` significant digits, written out in full from 10^4 to 10^7 (``24010``, not
    ``2.401e+04``: raw readings of a MEMS part are tens of thousands of nT); ``"-"`` for None or not finite."""
    if v is None:
        return "-"
    v = float(v)
    if not np.isfinite(v):
        return "-"
    if 10.0**digits <= abs(v) < 1e7:
        return f"{v:.0f}"
    return f"{v:.{digits}g}"


def fmt_nT(v) -> str:
    """``"12.3 nT"`` (four significant digits, see :func:`format_number`) or ``"-"``."""
    text = format_number(v)
    return text if text == "-" else f"{text} nT"


def rms(a) -> float:
    """Root mean square of the finite values of ``a`` (its unit), NaN when there are none."""
    a = np.asarray(a, dtype=float)
    a = a[np.isfinite(a)]
    return float(np.sqrt(np.mean(a**2))) if a.size else float("nan")


def candidate_label(candidate) -> str:
    """``effect`` or ``effect:S`` (S 1-based) for a diagnosis candidate (object or its dict)."""
    return candidate["label"] if isinstance(candidate, dict) else candidate.label


def fmt(v, unit="", digits=4) -> str:
    """A number for the page (:func:`format_number`) with its unit, or ``-``."""
    text = format_number(v, digits)
    return text if text == "-" else f"{text}{(' ' + unit) if unit else ''}"
