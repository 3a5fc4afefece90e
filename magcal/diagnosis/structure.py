"""Significant structure left in a fit's residuals: the reasons a model is not adequate.

:func:`_structure_tests` compares each sensor's total-field residuals (nT) with the noise floor (excess), and
looks for correlation in time (Ljung-Box), a periodic component (Fisher's g-test), a pattern over the field
direction (spherical harmonics of degree 3 and above) and, for coupled arrays, disagreement between the sensors.
Each test runs at :data:`STRUCTURE_P` (Bonferroni-corrected over the sensors) and must carry at least
:data:`STRUCTURE_MIN_FRACTION` of the residual variance; isolated glitches beyond :data:`GLITCH_SIGMA` are set
aside first. What is found is a list of :class:`Structure`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from magcal.checks.noise import NoiseEstimate
from magcal.diagnosis._fitted import _floor
from magcal.diagnosis.scores import _num
from magcal.diagnosis.statistics import SH_MAX_SAMPLES, durbin_watson, ljung_box, sh_analysis, spectrum

#: Significance level of each structure test (before the Bonferroni factor over sensors and tests).
STRUCTURE_P = 1e-4

#: Smallest share of the residual variance a structure must carry to count (practical significance).
STRUCTURE_MIN_FRACTION = 0.02

#: Samples beyond this many noise sigmas count as isolated glitches in the structure tests ...
GLITCH_SIGMA = 5.0
#: ... unless they are more than this fraction of the samples (then they are structure).
GLITCH_MAX_FRACTION = 0.01


@dataclass
class Structure:
    """One significant structure found in residuals (a reason the model is not adequate).

    Attributes
    ----------
    kind : str
        ``excess``, ``time``, ``periodic``, ``direction``, ``consistency`` or ``consistency_time``.
    sensor : int or None
        0-based sensor (:meth:`to_dict` writes it 1-based).
    p : float
        p-value of the test that found it.
    size : float
        Its effect size: variance ratio to the noise floor (excess, consistency) or share of the residual variance.
    text : str
        One line for people.
    """

    kind: str
    sensor: int | None  # 0-based; to_dict writes it 1-based
    p: float
    size: float
    text: str

    def to_dict(self):
        return {
            "kind": self.kind,
            "sensor": None if self.sensor is None else self.sensor + 1,
            "p": _num(self.p),
            "size": _num(self.size),
            "text": self.text,
        }


#: A spectral line at this many cycles per record or fewer is a trend, not a period.
MIN_PERIOD_CYCLES = 2.0


def _structure_tests(kept, fit, noise: NoiseEstimate, ordered, directions, n_tests_factor=1):
    """Significant structure in a fit's residuals: excess over the noise, time, spectrum, direction, consistency.

    Returns ``(structures, stats)`` with ``stats`` the per-sensor numbers behind them. Each sensor's residuals go
    through the tests in turn (:func:`_excess_test`, :func:`_time_tests`, :func:`_direction_test`,
    :func:`_consistency_tests`), after its isolated glitches are set aside (:func:`_glitches`).
    """
    r_all = fit.residuals_nT[:, fit.mask]
    ns, n = r_all.shape
    alpha = STRUCTURE_P / max(ns, 1) / n_tests_factor
    found, per = [], []
    vec = fit.consistency_residuals_nT
    for s in range(ns):
        r = r_all[s].copy()
        st: dict = {}
        glitch = _glitches(r, None if vec is None else vec[s].reshape(n, -1), noise.per_sensor_nT[s])
        st["glitches"] = int(glitch.sum())
        keep = ~glitch
        r[glitch] = 0.0
        found += _excess_test(s, r, keep, noise, fit.n_params / ns, alpha, st)
        if ordered:
            found += _time_tests(s, r, kept.time_s, alpha, st)
        found += _direction_test(s, r, keep, directions[s], alpha, st)
        if vec is not None:
            found += _consistency_tests(s, vec[s].reshape(n, -1).copy(), glitch, noise, ordered, alpha, st)
        per.append(st)
    return found, per


def _glitches(r, v, sigma) -> np.ndarray:
    """Isolated glitches of a sensor's residuals ``r`` (nT; ``v``: its inter-sensor consistency residuals or None;
    ``sigma`` its noise, nT): a few samples beyond 5 sigma (a transient, a jerk of the motion), counted and set
    aside, so that they do not pass for a systematic structure; more than 1 % of them is structure (none set
    aside)."""
    n = r.size
    glitch = np.abs(r) > GLITCH_SIGMA * sigma
    if v is not None:
        glitch |= np.linalg.norm(v, axis=1) > (GLITCH_SIGMA + 0.5) * sigma
    if glitch.sum() > GLITCH_MAX_FRACTION * n:
        glitch[:] = False
    return glitch


def _excess_test(s, r, keep, noise, p_per_sensor, alpha, st) -> list:
    """Sensor ``s``'s residual variance over its noise floor (``st`` gets its figures)."""
    n = r.size
    floor = _floor(noise.per_sensor_nT[s], n, p_per_sensor)
    ratio = float(np.mean(r[keep] ** 2) / floor**2)
    se = np.sqrt(2.0 / n + noise.relative_variance_error**2)
    z = (ratio - 1.0) / se
    st.update(rms_nT=float(np.sqrt(np.mean(r[keep] ** 2))), floor_nT=floor, variance_ratio=ratio, excess_z=float(z))
    if noise.source != "residuals" and z > stats.norm.isf(alpha) and ratio > 1.0 + 2 * STRUCTURE_MIN_FRACTION:
        return [
            Structure(
                "excess",
                s,
                float(stats.norm.sf(z)),
                ratio,
                f"sensor {s + 1}: RMS {st['rms_nT']:.3g} nT is {np.sqrt(ratio):.2f}x the noise floor {floor:.3g} nT",
            )
        ]
    return []


def _time_tests(s, r, t, alpha, st) -> list:
    """Sensor ``s``'s residuals in time (a smooth sequence; ``t`` the times, s, or None): correlation (Ljung-Box),
    and the spectrum's strongest line, a slow trend or a period (``st`` gets their figures)."""
    found = []
    n = r.size
    q, p, frac = ljung_box(r)
    st.update(ljung_box_q=q, ljung_box_p=p, autocorrelated_fraction=frac, durbin_watson=durbin_watson(r))
    if p < alpha and frac > STRUCTURE_MIN_FRACTION:
        found.append(
            Structure(
                "time",
                s,
                p,
                frac,
                f"sensor {s + 1}: residuals correlated in time (Ljung-Box p={p:.2g}, "
                f"Durbin-Watson {st['durbin_watson']:.2f})",
            )
        )
    spec = spectrum(r, t)
    st.update(
        peak_hz=spec["peak_hz"],
        peak_fraction=spec["peak_fraction"],
        peak_p=spec["p"],
        peak_amplitude_nT=spec["amplitude_nT"],
    )
    span = float(np.max(t) - np.min(t)) if t is not None else float(n)  # the spectrum's frequency grid
    cycles = spec["peak_hz"] * span if np.isfinite(spec["peak_hz"]) else float("nan")
    st["peak_cycles_per_record"] = cycles
    if spec["p"] < alpha and spec["peak_fraction"] > STRUCTURE_MIN_FRACTION and cycles <= MIN_PERIOD_CYCLES + 1e-6:
        # two cycles per record or fewer: a trend, not a period (a drift, or a field that changed)
        found.append(
            Structure(
                "time",
                s,
                spec["p"],
                spec["peak_fraction"],
                f"sensor {s + 1}: slow trend over the record (about {cycles:.1f} cycle(s) per record, "
                f"amplitude {spec['amplitude_nT']:.2g} nT, {100 * spec['peak_fraction']:.0f}% of the residual "
                "variance): a drift or a change of the field, too slow to be called a period",
            )
        )
    elif spec["p"] < alpha and spec["peak_fraction"] > STRUCTURE_MIN_FRACTION:
        unit = "Hz" if t is not None else "cycles/sample"
        found.append(
            Structure(
                "periodic",
                s,
                spec["p"],
                spec["peak_fraction"],
                f"sensor {s + 1}: periodic component at {spec['peak_hz']:.3g} {unit} "
                f"(amplitude {spec['amplitude_nT']:.2g} nT, {100 * spec['peak_fraction']:.0f}% "
                "of the residual variance)",
            )
        )
    return found


def _direction_test(s, r, keep, directions, alpha, st) -> list:
    """Sensor ``s``'s residuals over the field direction: spherical-harmonic degrees 3 and above (``st`` gets
    their figures)."""
    sh = sh_analysis(directions[keep], r[keep], max_samples=SH_MAX_SAMPLES)
    hi = sh["degree"] >= 3
    p_sh = float(np.nanmin(sh["p"][hi])) if np.any(np.isfinite(sh["p"][hi])) else 1.0
    deg = int(sh["degree"][hi][np.nanargmin(sh["p"][hi])]) if np.isfinite(p_sh) else -1
    variance = max(np.mean(r[keep] ** 2), 1e-300)
    if np.all(sh["resolved"][hi]):  # the sphere is resolved: the degrees' RMS over the whole sphere
        size = float(np.sum(sh["rms_nT"][hi] ** 2) / variance)
    else:  # only what degrees 3+ explain at the directions visited (their RMS over the sphere is not known)
        size = float(sh["high_rms_in_sample_nT"] ** 2 / variance)
    st.update(sh_p=p_sh, sh_degree=deg, sh_fraction=size, sh_max_resolved_degree=sh["max_resolved_degree"])
    if not (p_sh < alpha / 4 and size > STRUCTURE_MIN_FRACTION):
        return []
    if deg >= 0 and sh["resolved"][deg]:
        what = f"strongest at spherical-harmonic degree {deg} ({sh['rms_nT'][deg]:.2g} nT)"
    else:
        what = (
            f"strongest at spherical-harmonic degree {deg}; degrees 3 and above explain "
            f"{sh['high_rms_in_sample_nT']:.2g} nT RMS at the directions visited (the coverage resolves "
            f"degrees up to {sh['max_resolved_degree']} only, so their size elsewhere is not known)"
        )
    return [Structure("direction", s, p_sh, size, f"sensor {s + 1}: pattern over the field direction, {what}")]


def _consistency_tests(s, v, glitch, noise, ordered, alpha, st) -> list:
    """Sensor ``s``'s inter-sensor consistency residuals ``v`` (N, k) nT: their size over the noise and, on a smooth
    sequence, their correlation in time (``st`` gets their figures)."""
    found = []
    n = v.shape[0]
    keep = ~glitch
    v[glitch] = 0.0
    comps = min(v.shape[1], 2)
    vr = float(np.sum(v**2) / (keep.sum() * comps))
    # against the RMS of the sensors' noise: a consistency residual is the deviation from the mean of the sensors'
    # fields, whose variance is the mean of their variances (the mean sigma understates it for unequal sensors)
    ratio_v = vr / float(np.mean(np.square(noise.per_sensor_nT)))
    zv = (ratio_v - 1.0) / np.sqrt(1.0 / n + noise.relative_variance_error**2)
    st.update(consistency_rms_nT=float(np.sqrt(vr)), consistency_variance_ratio=ratio_v)
    if noise.source != "residuals" and zv > stats.norm.isf(alpha) and ratio_v > 1 + 2 * STRUCTURE_MIN_FRACTION:
        found.append(
            Structure(
                "consistency",
                s,
                float(stats.norm.sf(zv)),
                ratio_v,
                f"sensor {s + 1}: disagrees with the others in direction by "
                f"{np.sqrt(vr):.3g} nT RMS per component ({np.sqrt(ratio_v):.2f}x the noise)",
            )
        )
    if ordered:
        pv = min(ljung_box(v[:, k])[1] for k in range(comps))
        fv = max(ljung_box(v[:, k])[2] for k in range(comps))
        if pv < alpha / comps and fv > STRUCTURE_MIN_FRACTION:
            found.append(
                Structure(
                    "consistency_time",
                    s,
                    pv,
                    fv,
                    f"sensor {s + 1}: the inter-sensor disagreement is correlated in time (Ljung-Box p={pv:.2g})",
                )
            )
    return found


def _describe(structures) -> str:
    kinds: dict = {}
    for s in structures:
        kinds.setdefault(s.kind, []).append(s)
    parts = []
    for kind in ("periodic", "direction", "time", "excess", "consistency", "consistency_time"):
        if kind in kinds:
            parts.append(max(kinds[kind], key=lambda s: s.size).text)
    return "; ".join(parts)
