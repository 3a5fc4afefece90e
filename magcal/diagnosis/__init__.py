"""Diagnosis: where does the model fail, and which physical effect is missing?

:func:`diagnose` takes a dataset and a fitted model (or fits the base model) and

1. looks at the total-field residuals (and, for arrays, the inter-sensor consistency residuals) against
   **time** (Durbin-Watson, Ljung-Box, a change-point scan, the spectrum), **temperature**, **field direction**
   (least-squares real spherical harmonics up to degree 6: RMS and F-test per degree) and **between sensors**
   (common mode and differences), keeping plain arrays for plotting in ``Diagnosis.evidence``;
2. runs a **score (Lagrange multiplier) test** for every catalogue effect whose channels are present, per sensor
   where it applies and for all sensors together, from the base model's Jacobian alone (no refit), and ranks them
   by the predicted change of the Bayesian information criterion;
3. **confirms** the best few by refitting (actual delta-BIC, RMS after) and, if structure remains, looks for a
   second effect the same way;
4. warns when candidates are **confounded** (canonical correlation of their projected Jacobians, temperature
   following time, cubic nonlinearity versus cross-field coupling...);
5. gives a **verdict**: ``adequate`` (no significant structure left, or the RMS at most 10 % over the floor and
   nothing else), ``missing_effect`` (catalogue terms bring the
   residuals down to the noise) or ``unexplained`` (significant structure no catalogue term removes, described).

Noise
    The verdict needs the noise level independently of the model's misfit. Along a smooth trajectory a missing
    effect changes slowly from sample to sample while the noise does not, so the noise is estimated from the
    second differences of the residuals in time order (``var(d2 r) = 6 sigma^2`` for white noise), with gross
    jumps clipped, over the samples that are real conversions (repeats and interpolated samples left out), with
    the slow part of the noise the still stretches show added (:mod:`magcal.checks.noise`). When the samples are
    not in a smooth order (random attitudes), the dataset's declared
    ``noise_nT`` is used, and failing that the residual RMS itself (then a misfit cannot be told from noise by
    its size, only by its structure; a warning says so).

Information criterion
    ``BIC = m ln(RSS/m) + k ln m`` with ``m`` the number of *independent* residuals: the total-field ones plus, for
    coupled arrays, ``2 (n_sensors - 1)`` per sample for the consistency residuals (they sum to zero over the
    sensors). A candidate is supported when its delta-BIC is below ``-10`` (very strong evidence). A step time
    found by a scan counts as one more parameter.

Modules
    :mod:`.statistics` (tests and transforms of one residual series), :mod:`magcal.checks.noise` (the noise estimate),
    :mod:`.scores` (candidates, score tests, refits), :mod:`.structure` (significant structure left),
    :mod:`.evidence` (evidence lines and plot data), :mod:`.verdict` (:class:`Diagnosis` and :func:`diagnose`).
    Everything is importable from :mod:`magcal.diagnosis` itself.
"""

from __future__ import annotations

from magcal.checks.noise import NoiseEstimate, estimate_noise, is_smooth_sequence
from magcal.diagnosis._parallel import start_workers
from magcal.diagnosis.base import VERDICTS, DiagnosisBase
from magcal.diagnosis.evidence import SIGNATURES
from magcal.diagnosis.maps import (
    DirectionPattern,
    candidate_change,
    candidate_patterns,
    direction_pattern,
    pattern_correlation,
    residual_patterns,
)
from magcal.diagnosis.scores import Candidate, effective_residual_count
from magcal.diagnosis.statistics import (
    SH_DEGREE,
    SH_MAX_SAMPLES,
    autocorrelation,
    cusum_test,
    durbin_watson,
    ljung_box,
    real_sph_harm,
    sh_analysis,
    spectrum,
)
from magcal.diagnosis.structure import GLITCH_MAX_FRACTION, GLITCH_SIGMA, STRUCTURE_MIN_FRACTION, STRUCTURE_P, Structure
from magcal.diagnosis.verdict import DELTA_BIC_THRESHOLD, Diagnosis, diagnose

__all__ = [
    # the diagnosis
    "diagnose",
    "start_workers",
    "Diagnosis",
    "DiagnosisBase",
    "Candidate",
    "Structure",
    "VERDICTS",
    "SIGNATURES",
    # thresholds
    "DELTA_BIC_THRESHOLD",
    "STRUCTURE_P",
    "STRUCTURE_MIN_FRACTION",
    "GLITCH_SIGMA",
    "GLITCH_MAX_FRACTION",
    "effective_residual_count",
    # statistics of a residual series
    "durbin_watson",
    "autocorrelation",
    "ljung_box",
    "cusum_test",
    "spectrum",
    "real_sph_harm",
    "sh_analysis",
    "SH_DEGREE",
    "SH_MAX_SAMPLES",
    # residual patterns on the direction sphere
    "DirectionPattern",
    "direction_pattern",
    "residual_patterns",
    "candidate_change",
    "candidate_patterns",
    "pattern_correlation",
    # noise (defined in magcal.checks.noise, re-exported for compatibility)
    "NoiseEstimate",
    "estimate_noise",
    "is_smooth_sequence",
]
