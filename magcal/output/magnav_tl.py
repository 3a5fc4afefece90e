"""A compensation's coefficients for MagNav.jl: the TL-18 vector in its term order (``magcal export comp.json
--format magnav-tl``).

MagNav.jl compensates a scalar magnetometer as ``mag_c = mag_uc - create_TL_A(flux; terms) * TL_coef`` with
``TL_coef`` the coefficients of its design matrix (``create_TL_A``: the terms ``permanent``, ``induced``,
``eddy``, 18 columns, ``Bt_scale`` 50 000 nT, the fluxgate's change per sample). magcal's design matrix is the same
(:mod:`magcal.model.tolles_lawson`), so the vector carries over as it is. The file is JSON::

    {"format": "magnav-tl", "TL_coef": [18 numbers], "terms": ["permanent", "induced", "eddy"],
     "labels": ["permanent_x", ..., "eddy_zz"], "Bt_scale": 50000.0, "sample_rate_hz": 10.0,
     "passband_hz": [0.1, 0.9], "scalar_column": "mag_1_uc", "dropped": [...]}

In Julia: ``TL_coef = JSON.parsefile("tl.json")["TL_coef"]``; the fluxgate must be read at the same rate (the eddy
terms are per sample). What MagNav's TL-18 cannot hold (a term beyond TL, the fluxgate's own calibration, a time
offset) is refused unless forced, and then listed under ``dropped``.
"""

from __future__ import annotations

import json

import numpy as np

from magcal.core.errors import MagcalError
from magcal.fitting.compensation import Compensation
from magcal.model.tolles_lawson import DEFAULT_TERMS, term_labels

#: The compensation's export formats: name -> what it writes.
COMPENSATION_FORMATS = {
    "magnav-tl": "a compensation's TL-18 coefficient vector in MagNav.jl's term order (TL_coef), as JSON",
}

__all__ = ["COMPENSATION_FORMATS", "magnav_tl_document", "magnav_tl_text"]


def _dropped(compensation: Compensation) -> list[str]:
    out = [
        f"the term {name} (beyond Tolles-Lawson)"
        for name in compensation.effects
        if name not in ("fluxgate_calibration", "time_offset")
    ]
    if "fluxgate_calibration" in compensation.effects:
        out.append("the fluxgate's calibration (apply it to the fluxgate before create_TL_A: g = M (f - b))")
    if "time_offset" in compensation.effects:
        out.append(f"the fluxgate's time offset ({compensation.time_offset_s * 1e3:+.1f} ms: shift the fluxgate)")
    if compensation.tl.use_scalar_total:
        out.append("the direction cosines divided by the scalar's reading")
    return out


def magnav_tl_document(compensation: Compensation, force: bool = False) -> dict:
    """The JSON document of :mod:`magcal.output.magnav_tl` (a :class:`MagcalError` listing what MagNav's TL-18
    cannot hold, unless ``force``)."""
    if not isinstance(compensation, Compensation):
        raise MagcalError("--format magnav-tl writes a compensation (magcal calibrate --mode compensation)")
    dropped = _dropped(compensation)
    if dropped and not force:
        raise MagcalError(
            "MagNav.jl's TL-18 cannot hold " + "; ".join(dropped) + ": export with --force to write the TL vector "
            "without them (listed in the file), or fit without those effects"
        )
    return {
        "format": "magnav-tl",
        "TL_coef": [float(v) for v in np.asarray(compensation.tl18(), float)],
        "terms": list(DEFAULT_TERMS),
        "labels": term_labels(DEFAULT_TERMS),
        "Bt_scale": float(compensation.tl.scale_nT),
        "sample_rate_hz": float(compensation.sample_rate_hz),
        "passband_hz": [float(v) for v in compensation.tl.passband_hz],
        "ridge": float(compensation.tl.ridge),
        "scalar_column": compensation.scalar_column,
        "dropped": dropped,
    }


def magnav_tl_text(compensation: Compensation, force: bool = False) -> str:
    """:func:`magnav_tl_document` as indented JSON text (ends with a newline)."""
    return json.dumps(magnav_tl_document(compensation, force), indent=2) + "\n"
