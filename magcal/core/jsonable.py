"""Numpy values made JSON-ready: the one conversion every document (calibration, diagnosis, quality) uses."""

from __future__ import annotations

import numpy as np


def jsonable(value):
    """``value`` with numpy arrays and scalars turned into JSON types; non-finite floats become gaps."""
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        if value.dtype == object:
            return [jsonable(v) for v in value.tolist()]
        if value.dtype.kind == "f":  # inf is not JSON; show it as a gap like NaN
            return np.where(np.isfinite(value), value, np.nan).tolist()
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value
