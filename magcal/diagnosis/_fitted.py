"""What the diagnosis reads from a fitted model: the fit itself, its kept samples, field directions, RMS.

Shared by the score tests (:mod:`.scores`), the structure tests (:mod:`.structure`), the evidence
(:mod:`.evidence`) and the verdict (:mod:`.verdict`). Fields and residuals are in nT.
"""

from __future__ import annotations

import numpy as np

from magcal.calibration.calibration import corrected_fields
from magcal.core import conventions
from magcal.core.errors import MagcalError
from magcal.core.rows import unit_rows
from magcal.model.terms import contexts


def _fit_of(result):
    """A FitResult from a FitResult or a pipeline CalibrationResult."""
    if result is None:
        return None
    if hasattr(result, "residuals_nT") and hasattr(result, "problem"):
        return result
    fit = getattr(result, "fit", None)
    if fit is None:
        raise MagcalError("diagnosis needs a maximum-likelihood fit (method 'ml'); the result has none")
    return fit


def _reference_override(fit):
    return fit.calibration.reference_total_nT if fit.reference_kind == "given" else None


def _kept(dataset, fit):
    return dataset.masked(fit.mask)


def _model_fields(kept, fit):

    cal = fit.calibration
    return corrected_fields(kept, cal.sensors, cal.model, cal.effect_values, contexts(kept, cal.baseline_m))


def _sensor_directions(kept, fit):
    """Unit field directions in each sensor's own axes (n_sensors, N, 3)."""
    b = _model_fields(kept, fit)
    out = np.empty_like(b)
    for s, cal in enumerate(fit.calibration.sensors):
        v = b[s] @ cal.R  # R^T applied to rows: array frame -> sensor frame
        out[s] = unit_rows(v)
    return out, b


def _consistency_rms(fit):
    v = fit.consistency_residuals_nT
    if v is None:
        return None
    ns, n = v.shape[:2]
    comps = v.shape[2]
    return float(np.sqrt(np.sum(v**2) / (ns * n * min(comps, 2))))


def _consistency_rms_per_sensor(fit):
    v = fit.consistency_residuals_nT
    if v is None:
        return None
    comps = min(v.shape[2], 2)
    return np.sqrt(np.sum(v**2, axis=(1, 2)) / (v.shape[1] * comps))


def _floor(sigma, n_samples, n_params_per_sensor):
    return conventions.total_field_floor_nT(sigma, n_samples, min(n_params_per_sensor, n_samples - 1))
