"""Readable reports of a calibration, and its JSON document.

:func:`text_report` is what ``magcal calibrate`` prints: what happened step by step, each sensor's total-field
RMS before and after, its ``C^-1``, ``b`` and ``R``, the gauge-free scale factors and inter-axis angles, the tensor
RMS, and the physical floors the figures should be compared with. :func:`calibration_json` is the JSON object of
``magcal calibrate --json``; the saved calibration file (``Calibration.save``) holds the same fields.
"""

from __future__ import annotations

import numpy as np

from magcal.calibration.calibration import is_transferable
from magcal.core import conventions
from magcal.model.terms import EFFECTS

_REFERENCE_WORDS = {
    "given": "given",
    "column": "per-sample reference column (ref_total)",
    "fitted": "unknown, fitted (the common gain is fixed by det C^-1 = 1 for sensor 1)",
}


def calibration_json(result) -> dict:
    """The JSON object of ``magcal calibrate --json``: ``format``, ``version``, ``reference_total_nT``,
    ``baseline_m``, ``n_samples``, ``effects``, ``rms_nT``, ``tensor_rms_nT_per_m`` (arrays), ``sensors`` with
    ``id``, ``Cinv``, ``bias_nT``, ``R``, ``scale``, ``axis_angles_deg``, ``rms_before_nT``, ``rms_nT``.

    It is :meth:`magcal.calibration.calibration.Calibration.to_dict` of ``result.calibration``, whose summary :func:`magcal.fitting.pipeline.calibrate`
    filled, so it equals the saved file.
    """
    return result.calibration.to_dict()


#: How the report says whether an effect term carries to new data (:attr:`magcal.model.terms.Effect.transferable`).
SCOPE_WORDS = {
    True: "instrument term: carried to new data",
    False: "record-only term: describes this recording; applied only to it (magcal apply drops it on other "
    "data, with a warning)",
}


def effect_scope(name) -> str:
    """Whether the catalogue effect ``name`` is an instrument term or a record-only one, in words."""

    cls = EFFECTS.get(name)
    words = SCOPE_WORDS[is_transferable(cls if cls is not None else type("_", (), {"name": name}))]
    kept = getattr(cls, "kept_for_new_data", None)
    return f"{words}; new data keep {kept}" if kept else words


def _effect_quote(model, entry, field_nT) -> str:
    """What a fitted effect's parameters do at the data's own field magnitude (:meth:`magcal.model.terms.Effect.quote`)."""
    effect = next((e for e in (model.effects if model is not None else []) if e.label == entry["term"]), None)
    if effect is None:
        return ""
    sensor = None if entry["sensor"] is None else entry["sensor"] - 1
    return effect.quote(list(entry["params"].values()), field_nT, sensor)


def _matrix_lines(m, indent, fmt="{:+.6f}"):
    return [indent + "[" + "  ".join(fmt.format(v) for v in row) + "]" for row in np.asarray(m)]


def _fmt(v, digits=3):
    return "-" if v is None else f"{v:.{digits}f}"


def text_report(result, source: str | None = None) -> str:
    """A readable report of a :class:`~magcal.fitting.pipeline.CalibrationResult`, read top to bottom: the header,
    the steps, the noise floors, each sensor, the tensor, the fit, the distrusted samples and the warnings.

    Parameters
    ----------
    result : CalibrationResult
    source : str, optional
        Name of the data (file path) for the header.
    """
    out = _header_lines(result, source)
    out += _step_lines(result)
    out += _floor_lines(result)
    for s in range(result.calibration.n_sensors):
        out += _sensor_lines(result, s)
    out += _tensor_lines(result)
    out += _fit_lines(result)
    out += _closing_lines(result)
    return "\n".join(out).rstrip() + "\n"


def _header_lines(result, source) -> list[str]:
    """The report's title, the sensors, samples and reference field, the baseline and the method."""
    cal = result.calibration
    title = f"magcal calibration{(' of ' + source) if source else ''}"
    out = [title, "=" * len(title)]
    ref_text = _REFERENCE_WORDS.get(result.reference_kind, result.reference_kind)
    ref_value = f"{result.reference_total_nT:.2f} nT, " if result.reference_total_nT is not None else ""
    out.append(f"{cal.n_sensors} sensor(s), {result.n_samples} samples; reference field: {ref_value}{ref_text}")
    if cal.baseline_m:
        out.append(f"baseline d = {cal.baseline_m:g} m")
    method = {
        "ml": "ellipsoid -> Procrustes -> maximum likelihood",
        "ellipsoid": "ellipsoid -> Procrustes (the seed's two steps)",
    }.get(result.method, f"global search ({result.method})")
    extras = []
    if result.robust:
        extras.append("robust soft-L1 loss")
    if result.effects:
        extras.append("effects: " + ", ".join(result.effects))
    out.append(f"method: {method}{'; ' + '; '.join(extras) if extras else ''}; {result.wall_s * 1e3:.0f} ms")
    out.append("")
    return out


def _step_lines(result) -> list[str]:
    """The steps' table: total-field RMS per sensor, the sensors' disagreement, the worst tensor RMS, the time."""
    ns = result.calibration.n_sensors
    out = ["Steps (total-field RMS per sensor, nT; sensor disagreement RMS |B_s - B_1|, nT; worst tensor RMS, nT/m)"]
    header = f"  {'step':<11}" + "".join(f"{'s' + str(s + 1):>10}" for s in range(ns))
    if ns > 1:
        header += f"{'disagree':>10}"
    if result.tensor_rms_nT_per_m is not None:
        header += f"{'tensor':>10}"
    out.append(header + "   time")
    for step in result.steps:
        line = f"  {step.name:<11}" + "".join(f"{v:>10.3f}" for v in step.rms_per_sensor_nT)
        if ns > 1:
            line += f"{np.max(step.sensor_difference_rms_nT):>10.3f}"
        if step.tensor_rms_nT_per_m is not None:
            line += f"{max(step.tensor_rms_nT_per_m.values()):>10.2f}"
        out.append(line + (f"   {step.wall_s * 1e3:.0f} ms" if step.name != "raw" else ""))
    out.append("")
    return out


def _floor_lines(result) -> list[str]:
    """The noise, the total-field floor against the RMS after calibration, and the held-out validation."""
    out = []
    noise = result.noise
    if noise is not None:
        out.append(f"Noise sigma = {noise.text()}")
        if noise.note and noise.source != "given":
            out.append(f"  ({noise.note})")
    else:
        out.append(f"Noise sigma = {result.noise_nT:.3g} nT per axis ({result.noise_source})")
    line = (
        f"Total-field floor sigma*sqrt(1-p/N) = {result.total_field_floor_nT:.3f} nT; after calibration: "
        f"{result.rms_nT:.3f} nT over all sensors"
    )
    if result.noise_source != "residuals" and result.total_field_floor_nT > 0:
        line += f" ({result.rms_nT / result.total_field_floor_nT:.2f} x floor)"
    else:
        line += " (the floor comes from the same residuals, so this is no independent check; give --noise NT)"
    out.append(line)
    validation = getattr(result, "validation", None)
    if validation is not None:
        out.append("")
        out += validation.text().rstrip("\n").split("\n")
    out.append("")
    return out


def _sensor_lines(result, s) -> list[str]:
    """Sensor ``s`` (0-based): its RMS before and after, ``C^-1``, ``b``, ``R``, the gauge-free scale and axis
    angles, the misalignment and the coverage."""
    cal = result.calibration
    sc = cal.sensors[s]
    scale, angles = conventions.gauge_free(sc.cinv)
    out = [
        f"Sensor {s + 1}: total-field RMS {result.rms_before_per_sensor_nT[s]:.2f} nT before -> "
        f"{result.rms_after_per_sensor_nT[s]:.3f} nT after"
    ]
    out.append("  C^-1 =")
    out += _matrix_lines(sc.cinv, "    ")
    out.append("  b = [" + "  ".join(f"{v:+.3f}" for v in sc.bias_nT) + "] nT")
    out.append("  R =" + ("  (identity: sensor 1 defines the array frame)" if s == 0 and cal.n_sensors > 1 else ""))
    out += _matrix_lines(sc.R, "    ")
    out.append("  scale (gauge-free) = [" + "  ".join(f"{v:.6f}" for v in scale) + "]")
    out.append("  axis angles x-y, x-z, y-z = [" + "  ".join(f"{v:.4f}" for v in angles) + "] deg")
    if s > 0:
        alpha, beta, gamma = conventions.misalignment_angles(sc.R.T)
        out.append(f"  misalignment alpha, beta, gamma = [{alpha:+.5f}  {beta:+.5f}  {gamma:+.5f}] rad")
    if result.ellipsoids:
        cov = result.ellipsoids[s].coverage
        out.append(
            f"  coverage: {100 * cov.sky_fraction:.0f}% of the sky visited, thinnest direction spread "
            f"{cov.thinnest_spread:.3f} (full sphere 0.333)"
        )
    out.append("")
    return out


def _tensor_lines(result) -> list[str]:
    """The tensor's RMS per component before and after, against its floor (an array with a baseline)."""
    if result.tensor_rms_nT_per_m is None:
        return []
    out = ["Tensor RMS in the uniform calibration field (true tensor zero), nT/m"]
    out.append(f"  {'':<6}{'before':>12}{'after':>10}{'floor':>10}")
    for k in conventions.TENSOR_COMPONENTS:
        out.append(
            f"  {k:<6}{result.tensor_rms_before_nT_per_m[k]:>12.1f}{result.tensor_rms_nT_per_m[k]:>10.2f}"
            f"{result.tensor_floor_nT_per_m[k]:>10.2f}"
        )
    out.append("  floor: sqrt(2) sigma/d per sensor pair, 2 sigma/d for Gzz")
    out.append("")
    return out


def _fit_lines(result) -> list[str]:
    """The fit: parameters, AIC and BIC, whether it converged, and each effect's parameters in words."""
    f = result.fit
    if f is None:
        return []
    out = [
        f"Fit: {f.n_params} parameters, AIC {f.aic:.1f}, BIC {f.bic:.1f}; "
        + (
            f"converged ({f.message}, {f.nfev} evaluations)"
            if f.success
            else f"DID NOT CONVERGE ({f.message}, {f.nfev} evaluations): the figures above are not a minimum; "
            "look at the data (outliers, coverage, units) or refit"
        )
    ]
    for e in f.effect_params:
        params = ", ".join(f"{k} = {v:.4g} +- {e['std'][k]:.2g}" for k, v in e["params"].items())
        where = "" if e["sensor"] is None or ":" in e["term"] else f" (sensor {e['sensor']})"
        out.append(f"  {e['term']}{where}: {params}")
        quote = _effect_quote(f.model, e, getattr(result, "field_magnitude_nT", None))
        if quote:
            out.append(f"    {quote}")
        out.append(f"    {effect_scope(e['effect'])}")
    out.append("")
    return out


def _closing_lines(result) -> list[str]:
    """The distrusted samples (1-based rows) and the warnings."""
    out = []
    if result.outliers is not None and result.outliers.any():
        idx = np.flatnonzero(result.outliers)
        shown = ", ".join(str(i + 1) for i in idx[:20]) + (" ..." if idx.size > 20 else "")
        out.append(f"Distrusted samples ({idx.size}, 1-based data rows): {shown}")
    if result.remarks:
        out.append("Warnings:")
        out += [f"  - {w}" for w in result.remarks]
    return out
