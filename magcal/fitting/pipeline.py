"""The calibration pipeline: ellipsoid per sensor -> Procrustes between sensors -> maximum likelihood.

:func:`calibrate` runs the seed's two steps (Chi et al. 2017) and then refines them with the one ML fitter
(:func:`magcal.fitting.fitter.fit`), recording what every step did, so that a user (or the workbench) sees the total-field
RMS of each sensor and the tensor RMS fall step by step:

``raw``
    The readings as they are: ``|y| - F``.
``ellipsoid``
    Step 1, per sensor (:func:`magcal.geometry.ellipsoid.fit_ellipsoid`): ``C^-1`` and ``b``; each sensor's total field is
    now right but the sensors still disagree about the direction, so the tensor is still wrong.
``procrustes``
    Step 2 (:func:`magcal.geometry.procrustes.procrustes_rotation`): the rotation ``R`` taking each sensor into sensor 1's
    frame; the total fields do not change, the inter-sensor differences and the tensor fall.
``ml``
    Step 3: all parameters (and any candidate effects) by maximum likelihood, started from steps 1-2, with an
    optional robust loss.

Global-search methods (``pso``, ``ipso``, ``de``) come from :mod:`magcal.fitting.search` when it is installed.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from magcal.calibration.calibration import Calibration, SensorCalibration, expected_total_field
from magcal.calibration.report import calibration_json, text_report
from magcal.checks.noise import NoiseEstimate, estimate_noise, prefetch_readings_facts
from magcal.core import conventions
from magcal.core import notes as _notes
from magcal.core.errors import CalibrationError, CoverageWarning, DataWarning
from magcal.core.notes import Note
from magcal.core.rows import row_norm
from magcal.core.stats import robust_sigma
from magcal.data.dataset import Dataset
from magcal.fitting import search
from magcal.fitting.fitter import FitResult, fit, fit_reference, leave_out_rows_without_attitude
from magcal.fitting.result import ModeResult
from magcal.geometry.ellipsoid import START_MAX_SAMPLES, fit_ellipsoid
from magcal.geometry.procrustes import procrustes_rotation
from magcal.model.terms import Effect, Model

#: Methods of :func:`calibrate`: the two seed steps alone, or followed by maximum likelihood.
METHODS = ("ml", "ellipsoid")

#: Global-search methods dispatched to :mod:`magcal.fitting.search`.
SEARCH_METHODS = ("pso", "ipso", "de")

#: Samples beyond this many robust standard deviations are left out of the robust ellipsoid start.
ROBUST_START_SIGMA = 5.0


@dataclass
class StepSummary:
    """What one step of the pipeline achieved.

    Attributes
    ----------
    name : str
        ``raw``, ``ellipsoid``, ``procrustes``, ``ml`` or a search method's name.
    description : str
        One line: what the step estimated.
    rms_per_sensor_nT : numpy.ndarray, shape (n_sensors,)
        Total-field RMS ``|B_s| - F`` per sensor after this step, nT (kept samples).
    max_abs_per_sensor_nT : numpy.ndarray, shape (n_sensors,)
        Largest ``| |B_s| - F |`` per sensor after this step, nT.
    sensor_difference_rms_nT : numpy.ndarray, shape (n_sensors,) or None
        RMS of ``|B_s - B_1|`` (nT) for arrays: how well the sensors agree on the vector (0 for sensor 1).
    tensor_rms_nT_per_m : dict or None
        RMS of each tensor component (nT/m) in the uniform calibration field (whose true tensor is zero);
        only for four sensors with a baseline.
    tensor_max_abs_nT_per_m : dict or None
        Largest absolute value of each tensor component (nT/m).
    wall_s : float
        Time the step took, s.
    """

    name: str
    description: str
    rms_per_sensor_nT: np.ndarray
    max_abs_per_sensor_nT: np.ndarray
    sensor_difference_rms_nT: np.ndarray | None = None
    tensor_rms_nT_per_m: dict | None = None
    tensor_max_abs_nT_per_m: dict | None = None
    wall_s: float = 0.0

    def to_dict(self) -> dict:
        """JSON-ready form."""
        return {
            "name": self.name,
            "description": self.description,
            "rms_per_sensor_nT": self.rms_per_sensor_nT.tolist(),
            "max_abs_per_sensor_nT": self.max_abs_per_sensor_nT.tolist(),
            "sensor_difference_rms_nT": None
            if self.sensor_difference_rms_nT is None
            else self.sensor_difference_rms_nT.tolist(),
            "tensor_rms_nT_per_m": self.tensor_rms_nT_per_m,
            "tensor_max_abs_nT_per_m": self.tensor_max_abs_nT_per_m,
            "wall_s": self.wall_s,
        }


@dataclass
class CalibrationResult(ModeResult):
    """Outcome of :func:`calibrate`: the total-field fit mode's result (:class:`~magcal.fitting.result.ModeResult`,
    ``mode = "total_field"``).

    Attributes
    ----------
    calibration : Calibration
        The final calibration (apply it with ``.correct(ds)``, ``.tensor(ds)``, save it with ``.save(path)``).
        Its ``summary`` holds the figures below, so the saved file carries them.
    fit : FitResult or None
        The maximum-likelihood fit (``method="ml"``), else None.
    steps : list of StepSummary
        ``raw`` first, then every step run, in order.
    remarks : list of str
        The report's lines: what the steps found worth a line under "Warnings" in the report and in the JSON
        document's ``"warnings"`` (weak coverage, the noise the floors use, samples distrusted as outliers, samples
        without attitude...), in the order found. Information for the report, never raised as Python warnings:
        what a user must hear is in ``notes`` (a coverage concern is in both), and their texts in ``warnings``.
    method : str
    reference_kind : str
        ``given`` (argument or file metadata), ``column`` (per-sample ``ref_total``) or ``fitted``.
    reference_total_nT : float or None
        The field magnitude used or fitted (None with a per-sample column).
    n_samples : int
        Samples used (after the mask).
    rms_before_per_sensor_nT, rms_after_per_sensor_nT : numpy.ndarray, shape (n_sensors,)
        Total-field RMS per sensor of the raw readings (``|y|`` against the reference) and after calibration, nT.
    rms_nT : float
        Total-field RMS after calibration over all sensors, nT.
    tensor_rms_before_nT_per_m, tensor_rms_nT_per_m : dict or None
        RMS of each tensor component before (raw readings) and after calibration, nT/m (four sensors only).
    noise_nT : float
        Per-axis noise used for the floors, nT: the one given (``noise_nT=`` or the dataset's ``noise_nT``), else
        estimated (:func:`magcal.checks.noise.estimate_noise`).
    noise_source : str
        Which method gave it (:data:`magcal.checks.noise.NOISE_SOURCES`): ``given``, ``differences``, ``static``,
        ``quantization`` or ``residuals``.
    total_field_floor_nT : float
        ``sigma sqrt(1 - p/N)``: the lowest in-sample total-field RMS any estimator can reach (p parameters per
        sensor).
    tensor_floor_nT_per_m : dict or None
        ``sqrt(2) sigma/d`` per component (``2 sigma/d`` for Gzz).
    ellipsoids : list of EllipsoidFit
        Step-1 fits per sensor (empty for search methods).
    outliers : numpy.ndarray of bool, shape (N,)
        Samples the fit distrusts (beyond 5 robust standard deviations). With ``robust=True`` the figures above
        (RMS, tensor RMS, steps) leave them out; without it they include them and a warning suggests the robust
        loss.
    mask : numpy.ndarray of bool, shape (N,)
        Samples used.
    wall_s : float
        Total time, s.
    robust : bool
        Whether the robust loss was used.
    effects : list of str
        Labels of the candidate effects in the model.
    field_magnitude_nT : float or None
        The field magnitude of the final calibration, nT: the total field it expects (its reference, given or
        fitted, or the data's ``ref_total`` column), averaged over the sensors and the samples used.
    noise : NoiseEstimate
        The noise with its method and checks (still stretches' figures, quantization floor).
    validation : EffectsValidation or None
        Held-out RMS of the base model and of the model with the effects
        (:func:`magcal.fitting.validation.validate_effects`), when asked for.
    notes : list of Note
        What the steps said that a user must hear (:mod:`magcal.core.notes`): weak coverage
        (:class:`~magcal.core.errors.CoverageWarning`, also a remark), a fit that did not converge
        (:class:`~magcal.core.errors.ConvergenceWarning`). :func:`magcal.calibrate` raises them as warnings; this
        function never does.
    """

    calibration: Calibration
    fit: FitResult | None
    steps: list
    remarks: list
    method: str
    reference_kind: str
    reference_total_nT: float | None
    n_samples: int
    rms_before_per_sensor_nT: np.ndarray
    rms_after_per_sensor_nT: np.ndarray
    rms_nT: float
    tensor_rms_before_nT_per_m: dict | None
    tensor_rms_nT_per_m: dict | None
    noise_nT: float
    noise_source: str
    total_field_floor_nT: float
    tensor_floor_nT_per_m: dict | None
    ellipsoids: list = field(default_factory=list)
    outliers: np.ndarray | None = None
    mask: np.ndarray | None = None
    wall_s: float = 0.0
    robust: bool = False
    effects: list = field(default_factory=list)
    field_magnitude_nT: float | None = None
    noise: NoiseEstimate | None = None
    validation: Any = None  # magcal.fitting.validation.EffectsValidation (that module imports this one)
    notes: list = field(default_factory=list)

    mode = "total_field"

    def text(self, source: str | None = None) -> str:
        """The readable report (:func:`magcal.calibration.report.text_report`; ``source``: the data's name)."""
        return text_report(self, source=source)

    def to_dict(self) -> dict:
        """The calibration's document (the saved file's, :func:`magcal.calibration.report.calibration_json`) with
        ``"mode"`` and, when made, the held-out ``"validation"``."""
        doc = {"mode": self.mode, **calibration_json(self)}
        if self.validation is not None:
            doc["validation"] = self.validation.to_dict()
        return doc

    @property
    def n_sensors(self) -> int:
        return self.calibration.n_sensors

    def step(self, name: str) -> StepSummary:
        """The summary of the step with that name."""
        for s in self.steps:
            if s.name == name:
                return s
        raise KeyError(name)


# ------------------------------------------------------------------------------------------------------------
# figures of merit
# ------------------------------------------------------------------------------------------------------------


def _has_tensor(dataset) -> bool:
    return dataset.n_sensors == 4 and bool(dataset.baseline_m)


def _evaluate(name, description, vectors_nT, expected_nT, dataset, wall_s) -> StepSummary:
    """Figures of one step from the array-frame vectors (n_sensors, N, 3) of the kept samples."""
    dev = row_norm(vectors_nT) - expected_nT
    diff = None
    if vectors_nT.shape[0] > 1:
        diff = np.sqrt(np.mean(np.sum((vectors_nT - vectors_nT[0]) ** 2, axis=2), axis=1))
    t_rms = t_max = None
    if _has_tensor(dataset):
        comp = conventions.tensor_components(vectors_nT, dataset.baseline_m)
        t_rms = {k: float(np.sqrt(np.mean(v**2))) for k, v in comp.items()}
        t_max = {k: float(np.max(np.abs(v))) for k, v in comp.items()}
    return StepSummary(
        name,
        description,
        np.sqrt(np.mean(dev**2, axis=1)),
        np.max(np.abs(dev), axis=1),
        diff,
        t_rms,
        t_max,
        float(wall_s),
    )


def _evaluate_deviations(name, description, dev, wall_s) -> StepSummary:
    """Figures of one sensor's step from its total-field deviations (1, N), nT."""
    return StepSummary(
        name,
        description,
        np.sqrt(np.mean(dev**2, axis=1)),
        np.max(np.abs(dev), axis=1),
        None,
        None,
        None,
        float(wall_s),
    )


def _expected(dataset, calibration, reference_kind):
    """Expected total field (n_sensors, N) of the base model (reference value or column)."""
    value = None if reference_kind == "column" else calibration.reference_total_nT
    return expected_total_field(dataset, value)


# ------------------------------------------------------------------------------------------------------------
# steps 1 and 2
# ------------------------------------------------------------------------------------------------------------


def ellipsoid_step(
    dataset,
    ellipsoid_method="algebraic",
    reference_total_nT=None,
    reference_kind="given",
    robust=False,
    max_samples=None,
):
    """Step 1 for every sensor; with an unknown field, all sensors share sensor 1's fitted magnitude.

    Parameters
    ----------
    dataset : Dataset
        Kept samples only.
    ellipsoid_method : {"algebraic", "li-griffiths"}
    reference_total_nT : float or None
        Field magnitude (nT); None when it is fitted or comes from a per-sample column.
    reference_kind : str
        ``given``, ``column`` or ``fitted`` (see :func:`magcal.fitting.fitter.fit_reference`).
    robust : bool
        Refit once without samples beyond :data:`ROBUST_START_SIGMA` robust standard deviations.
    max_samples : int, optional
        Fit each ellipsoid to an even subsample of at most this many samples (a start for maximum likelihood,
        :data:`magcal.geometry.ellipsoid.START_MAX_SAMPLES`); the inliers are still judged on every sample.

    Returns
    -------
    fits : list of EllipsoidFit
    inliers : numpy.ndarray of bool, shape (N,)
        Samples the step kept (all True unless ``robust``).
    """
    if reference_kind == "column":
        field_nT = float(np.median(dataset.ref_total_nT))
    else:
        field_nT = reference_total_nT
    inliers = np.ones(dataset.n_samples, bool)
    fits = [
        fit_ellipsoid(y, ellipsoid_method, field_nT, label=f"sensor {s + 1}", max_samples=max_samples)
        for s, y in enumerate(dataset.readings_nT)
    ]
    if robust:
        for f, y in zip(fits, dataset.readings_nT):
            dev = row_norm(f.correct(y)) - f.field_nT
            inliers &= np.abs(dev - np.median(dev)) <= ROBUST_START_SIGMA * robust_sigma(dev, floor=1e-9)
        if not inliers.all():
            fits = [
                fit_ellipsoid(
                    y, ellipsoid_method, field_nT, mask=inliers, label=f"sensor {s + 1}", max_samples=max_samples
                )
                for s, y in enumerate(dataset.readings_nT)
            ]
    if reference_kind == "fitted" and len(fits) > 1:
        common = fits[0].field_nT  # det C^-1 = 1 for sensor 1, the fitter's gauge
        fits = [fits[0]] + [
            f.with_field(common, fitted=True, readings_nT=y[inliers]) for f, y in zip(fits[1:], dataset.readings_nT[1:])
        ]
    return fits, inliers


def procrustes_step(dataset, fits, inliers=None):
    """Step 2: rotations ``R_s`` taking each sensor's corrected vectors into sensor 1's frame (``R_1 = I``)."""
    idx = slice(None) if inliers is None else np.asarray(inliers, bool)
    return _rotations_onto_first([f.correct(y[idx]) for f, y in zip(fits, dataset.readings_nT)])


def align_sensors(dataset, calibration: Calibration) -> Calibration:
    """Step 2 on a given calibration: a copy whose ``R_s`` come from Procrustes of each sensor's ``C^-1 (y - b)``
    onto sensor 1's (the seed's step 2 after any step 1, e.g. one the user refined)."""
    if dataset.n_sensors < 2:
        raise CalibrationError("aligning needs at least two sensors; these data have one")
    corrected = [(y - c.bias_nT) @ c.cinv.T for c, y in zip(calibration.sensors, dataset.readings_nT)]
    aligned = Calibration.from_dict(calibration.to_dict(), "current calibration")
    for sensor, rotation in zip(aligned.sensors, _rotations_onto_first(corrected)):
        sensor.R = rotation
    return aligned


def _rotations_onto_first(corrected):
    """Procrustes rotations of each sensor's corrected vectors (list of (N, 3), nT) onto sensor 1's."""
    return [np.eye(3)] + [
        procrustes_rotation(corrected[0], c, label=f"sensor {s + 1}") for s, c in enumerate(corrected[1:], start=1)
    ]


def two_step_calibration(dataset, fits, rotations, reference_kind) -> Calibration:
    """A :class:`Calibration` from step-1 fits and step-2 rotations."""
    sensors = [SensorCalibration(f.cinv, f.bias_nT, r) for f, r in zip(fits, rotations)]
    return Calibration(
        sensors=sensors,
        reference_total_nT=None if reference_kind == "column" else fits[0].field_nT,
        reference_fitted=reference_kind == "fitted",
        baseline_m=dataset.baseline_m,
    )


# ------------------------------------------------------------------------------------------------------------
# the pipeline
# ------------------------------------------------------------------------------------------------------------


def _build_model(dataset, effects):

    names = [e for e in effects if isinstance(e, str)]
    model = Model.from_names(names, dataset.n_sensors)
    for e in effects:
        if isinstance(e, Effect):
            model = model.with_effect(e)
        elif not isinstance(e, str):
            raise CalibrationError(f"effects must be names (e.g. 'temperature_bias') or Effect objects, got {e!r}")
    vector_only = [e.label for e in model.effects if "scalar" not in getattr(e, "modes", ("scalar",))]
    if vector_only:
        raise CalibrationError(
            f"{', '.join(vector_only)}: the total field cannot see this term; fit it in vector mode (attitude and the "
            "field vector: magcal calibrate --mode vector --effects ..., docs/vector.md)"
        )
    return model


def _search(dataset, method, seed, progress, mask, reference_total_nT):
    # the iteration counts on across sensors, sensor s from s * max_iter: a fraction of the most it can run
    # (a sensor whose search stalls early makes the bar jump to the next sensor's share)
    total = dataset.n_sensors * search.DEFAULTS[method]["max_iter"]

    def callback(iteration, best_rms_nT):
        progress(f"{method}: iteration {iteration}, best RMS {best_rms_nT:.4g} nT", min(iteration / total, 1.0))

    return search.search_calibrate(
        dataset,
        method,
        seed=seed,
        progress=None if progress is None else callback,
        mask=mask,
        reference_total_nT=reference_total_nT,
    )


@dataclass
class _Run:
    """What the steps of one :func:`calibrate` call share: the data, the reference, the notes and the steps run.

    Attributes
    ----------
    dataset : Dataset
        The whole dataset, as given.
    mask : numpy.ndarray of bool, shape (N,)
        Samples used.
    kept : Dataset
        The samples used (later, with ``robust``, only the trusted ones).
    ref_value : float or None
        The reference total field (nT) the fit uses, or None (a per-sample column, or fitted).
    ref_kind : str
        ``given``, ``column`` or ``fitted``.
    progress : callable or None
        ``progress(message, fraction_or_None)``.
    remarks : list of str
        The report's lines, in the order found (the result's ``remarks``).
    raised : list of Note
        Notes for the user that are not data concerns (a fit that did not converge), in the order found; with the
        coverage concerns among the remarks they become the result's ``notes``.
    steps_timed : list of tuple
        ``(name, description, calibration, wall_s)`` of every step run.
    ellipsoids : list of EllipsoidFit
        Step-1 fits per sensor (empty for search methods).
    inliers : numpy.ndarray of bool
        Kept samples the ellipsoid start trusted.
    fit : FitResult or None
        The ML fit.
    calibration : Calibration or None
        The calibration of the last step run.
    """

    dataset: Dataset
    mask: np.ndarray
    kept: Dataset
    ref_value: float | None
    ref_kind: str
    progress: Callable | None = None
    remarks: list = field(default_factory=list)
    raised: list = field(default_factory=list)
    steps_timed: list = field(default_factory=list)
    ellipsoids: list = field(default_factory=list)
    inliers: Any = None  # numpy.ndarray of bool once the ellipsoid step ran
    fit: FitResult | None = None
    calibration: Any = None  # Calibration once the first step ran

    def report(self, message, fraction=None):
        if self.progress is not None:
            self.progress(message, fraction)

    def take(self, notes):
        """A step's notes (:class:`~magcal.core.notes.Note`): data concerns join the result's ``remarks``, any
        other note its ``notes``."""
        for note in notes:
            if note.is_a(DataWarning):
                self.remarks.append(note.text)
            else:
                self.raised.append(note)

    def result_notes(self) -> list:
        """The result's ``notes``: the steps' other notes, then each coverage concern as a
        :class:`~magcal.core.errors.CoverageWarning`."""
        coverage = [Note(n, CoverageWarning, "calibrate") for n in self.remarks if "coverage" in n]
        return _notes.unique(self.raised + coverage)

    def add_step(self, name, description, calibration, t0):
        """Record a step that started at ``t0`` (``time.perf_counter()``) and made ``calibration``."""
        self.steps_timed.append((name, description, calibration, time.perf_counter() - t0))
        self.calibration = calibration


def calibrate(
    dataset,
    method: str = "ml",
    effects=(),
    robust: bool = False,
    reference_total_nT=None,
    seed=None,
    progress: Callable | None = None,
    mask=None,
    ellipsoid_method: str = "algebraic",
    base_terms=None,
    noise_nT=None,
) -> CalibrationResult:
    """Calibrate one to four sensors from readings taken while turning them in a uniform field.

    Parameters
    ----------
    dataset : Dataset
        Raw readings (and optional channels).
    method : {"ml", "ellipsoid", "pso", "ipso", "de"}
        ``ml`` (default): ellipsoid -> Procrustes -> maximum likelihood. ``ellipsoid``: the seed's two steps
        only. ``pso``, ``ipso``, ``de``: global search of :mod:`magcal.fitting.search` (then Procrustes for arrays).
    effects : sequence of str or Effect
        Candidate effects to add to the base model, by name (``"temperature_bias"``, ``"bias_drift:2"``); only
        with ``method="ml"``.
    robust : bool
        Use scipy's soft-L1 loss in the ML step and leave gross outliers out of the ellipsoid start; the samples
        the fit distrusts are reported in ``outliers``.
    reference_total_nT : float, optional
        Known total field in nT. Otherwise the dataset's ``ref_total`` column, its ``reference_total_nT``
        metadata, or (if neither) the magnitude is fitted with ``det C^-1 = 1`` for sensor 1.
    seed : int, optional
        Seed for the stochastic search methods.
    progress : callable, optional
        ``progress(message, fraction_or_None)`` called as the steps run.
    mask : array_like of bool, shape (N,), optional
        Samples to use (True = use). With an effect that needs each sample's attitude (``site_gradient``), the
        samples without one are left out of every step, with a line in ``remarks``.
    ellipsoid_method : {"algebraic", "li-griffiths"}
        Estimator of step 1.
    base_terms : sequence of str, optional
        Base terms of the ML model (default all of :data:`magcal.model.terms.BASE_TERMS`).
    noise_nT : float, optional
        Noise per axis in nT, given by the user: used for the floors instead of the dataset's ``noise_nT`` or any
        estimate (:func:`magcal.checks.noise.estimate_noise`).

    Returns
    -------
    CalibrationResult
        What the steps had to say is in its ``notes`` (and its report lines in ``remarks``), never raised as a warning here: the
        steps may run on threads (:mod:`magcal.core.notes`); :func:`magcal.calibrate` raises them.

    Raises
    ------
    CalibrationError
        Unknown method, too few samples, non-ellipsoidal readings, degenerate coverage.
    """
    t_start = time.perf_counter()
    method, effects, mask = _checked_arguments(dataset, method, effects, mask)
    gap_note = None
    if method == "ml" and effects:  # an effect that needs each sample's attitude: every step fits the same samples
        mask, gap_note = leave_out_rows_without_attitude(
            dataset, _build_model(dataset, effects), mask, "the calibration"
        )
    run = _resolve_reference_step(dataset, mask, reference_total_nT, progress)
    if gap_note is not None:
        run.take([gap_note])
    noise_facts = prefetch_readings_facts(run.kept)  # the noise's readings-only work, beside the fit
    model = _model_for(dataset, run.kept, effects, base_terms) if method == "ml" else None
    if method in SEARCH_METHODS:
        _search_steps(run, method, seed, reference_total_nT)
    else:
        _start_steps(run, ellipsoid_method, robust, start_only=method == "ml")
        if method == "ml":
            _ml_step(run, model, robust, reference_total_nT)
    run.report("evaluating", 0.9)
    outliers = _robust_pass(run, robust)
    steps = _step_figures(run)
    noise_facts()
    result = _summary(run, steps, model, method, robust, outliers, t_start, noise_nT)
    _store_summary(result)
    result.notes = run.result_notes()
    run.report("done", 1.0)
    return result


# ---- the steps of calibrate, in order ----------------------------------------------------------------------


def _checked_arguments(dataset, method, effects, mask):
    """``(method, effects, mask)`` checked: a known method, effects only with ``ml``, a mask of one per sample."""
    method = str(method).lower()
    if method not in METHODS + SEARCH_METHODS:
        raise CalibrationError(f"unknown method {method!r}; use one of {', '.join(METHODS + SEARCH_METHODS)}")
    effects = list(effects or ())
    if effects and method != "ml":
        raise CalibrationError(f"effects can only be fitted with method 'ml', not {method!r}")
    n_all = dataset.n_samples
    mask = np.ones(n_all, bool) if mask is None else np.asarray(mask, bool)
    if mask.shape != (n_all,):
        raise CalibrationError(f"mask has shape {mask.shape}, expected ({n_all},)")
    return method, effects, mask


def _resolve_reference_step(dataset, mask, reference_total_nT, progress) -> _Run:
    """The samples used and the reference they are fitted to (given, a per-sample column, or fitted)."""
    kept = dataset.masked(mask)
    ref_value, ref_kind = fit_reference(kept, reference_total_nT)
    return _Run(
        dataset=dataset,
        mask=mask,
        kept=kept,
        ref_value=ref_value,
        ref_kind=ref_kind,
        progress=progress,
        inliers=np.ones(kept.n_samples, bool),
    )


def _model_for(dataset, kept, effects, base_terms):
    """The ML model: the base terms (all, or ``base_terms``) and the effects, checked against the data's
    channels."""
    model = _build_model(dataset, effects)
    if base_terms is not None:
        model = Model(model.n_sensors, base=tuple(base_terms), effects=model.effects)
    model.check(kept)
    return model


def _search_steps(run: _Run, method, seed, reference_total_nT) -> None:
    """A global search of ``C^-1`` and ``b`` per sensor, then Procrustes between the sensors when the search left
    them unrotated."""
    run.report(f"{method}: global search", 0.0)
    t0 = time.perf_counter()
    found = _search(run.dataset, method, seed, run.progress and run.report, run.mask, reference_total_nT)
    run.take(found.notes)
    calibration = found.calibration
    if calibration.n_sensors > 1 and all(np.allclose(c.R, np.eye(3)) for c in calibration.sensors[1:]):
        run.add_step(method, f"global search ({method}) of C^-1 and b per sensor", calibration, t0)
        t0 = time.perf_counter()
        vectors = [(y - c.bias_nT) @ c.cinv.T for c, y in zip(calibration.sensors, run.kept.readings_nT)]
        for s in range(1, calibration.n_sensors):
            calibration.sensors[s].R = procrustes_rotation(vectors[0], vectors[s], label=f"sensor {s + 1}")
        run.add_step("procrustes", "rotation of each sensor into sensor 1's frame (eq. 14)", calibration, t0)
    else:
        run.add_step(method, f"global search ({method})", calibration, t0)


def _start_steps(run: _Run, ellipsoid_method, robust, start_only=False) -> None:
    """The seed's two steps: an ellipsoid per sensor, then (arrays) Procrustes between the sensors.

    ``start_only``: the steps only start maximum likelihood, so each ellipsoid is fitted to an even subsample of
    at most :data:`magcal.geometry.ellipsoid.START_MAX_SAMPLES` samples (ML then fits every sample)."""
    kept = run.kept
    run.report("step 1: ellipsoid fit per sensor", 0.0)
    t0 = time.perf_counter()
    run.ellipsoids, run.inliers = ellipsoid_step(
        kept,
        ellipsoid_method,
        run.ref_value,
        run.ref_kind,
        robust=robust,
        max_samples=START_MAX_SAMPLES if start_only else None,
    )
    for f in run.ellipsoids:
        run.remarks.extend(f.warnings)
    step1 = two_step_calibration(kept, run.ellipsoids, [np.eye(3)] * len(run.ellipsoids), run.ref_kind)
    run.add_step("ellipsoid", f"C^-1 and b per sensor ({ellipsoid_method} ellipsoid fit, eqs. 8-13)", step1, t0)
    if kept.n_sensors > 1:
        run.report("step 2: Procrustes between sensors", 0.3)
        t0 = time.perf_counter()
        rotations = procrustes_step(kept, run.ellipsoids, run.inliers)
        calibration = two_step_calibration(kept, run.ellipsoids, rotations, run.ref_kind)
        run.add_step("procrustes", "rotation of each sensor into sensor 1's frame (eq. 14)", calibration, t0)


def _ml_step(run: _Run, model, robust, reference_total_nT) -> None:
    """Step 3: every parameter of the model by maximum likelihood, started from the two steps."""

    run.report("step 3: maximum-likelihood refinement", 0.5)
    t0 = time.perf_counter()
    run.fit = fit(
        run.dataset,
        model,
        init=run.calibration,
        loss="soft_l1" if robust else "linear",
        mask=run.mask,
        reference_total_nT=reference_total_nT,
        warn=False,
    )
    run.take(run.fit.notes)
    terms = ", ".join(list(model.base) + model.effect_labels)
    run.add_step(
        "ml", f"maximum likelihood of {terms}" + (" (robust soft-L1 loss)" if robust else ""), run.fit.calibration, t0
    )


def _robust_pass(run: _Run, robust) -> np.ndarray:
    """The samples distrusted as outliers (N,); with ``robust`` the figures then leave them out (``run.kept``)."""
    outliers = np.zeros(run.dataset.n_samples, bool)
    if run.fit is not None:
        outliers = np.asarray(run.fit.outliers, bool)
    elif robust:
        outliers[np.flatnonzero(run.mask)[~run.inliers]] = True
    if outliers.any():
        run.remarks.append(
            f"{int(outliers.sum())} sample(s) distrusted as outliers"
            + (
                " and down-weighted by the robust loss; the figures leave them out"
                if robust
                else "; consider the robust loss"
            )
        )
    if robust and outliers.any():
        run.kept = run.kept.subset(~outliers[run.mask])
    return outliers


def _step_figures(run: _Run) -> list:
    """Figures before (raw readings) and after every step, on the kept (and, if robust, trusted) samples."""
    kept, ref_kind = run.kept, run.ref_kind
    expected = _expected(kept, run.calibration, ref_kind)
    raw = _evaluate("raw", "raw readings, no correction", kept.readings_nT, expected, kept, 0.0)
    steps = [raw]
    fit = run.fit
    for name, description, cal, wall in run.steps_timed:
        if (
            name == "ml"
            and fit is not None
            and kept.n_sensors == 1
            and fit.calibration is cal
            and int(fit.mask.sum()) == kept.n_samples
        ):
            # one sensor's figures need only its total-field deviations: the fit's own residuals of these samples
            # (no second pass over the record to correct it again)
            steps.append(_evaluate_deviations(name, description, fit.residuals_nT[:, fit.mask], wall))
            continue
        if cal.model is not None and cal.model.effects:
            vectors = cal.correct(kept)
            exp = expected_total_field(
                kept, None if ref_kind == "column" else cal.reference_total_nT, cal.model, cal.effect_values
            )
        else:
            vectors = _base_correct(cal, kept)
            exp = _expected(kept, cal, ref_kind)
        steps.append(_evaluate(name, description, vectors, exp, kept, wall))
    return steps


def _noise_and_floors(run: _Run, model, final: StepSummary, noise_nT=None):
    """``(noise, total_field_floor_nT, tensor_floor_nT_per_m)``: the noise given (``noise_nT``, else the
    dataset's) or estimated from the final residuals (:func:`magcal.checks.noise.estimate_noise`: differences in time
    order, still stretches, quantization floor), and the floors it sets."""
    dataset, kept = run.dataset, run.kept
    n_params: float = 9
    if model is not None:
        n_params += sum(len(e.param_names()) for e, s in model.instances()) / dataset.n_sensors
    if run.fit is not None:
        fit = run.fit
        samples = dataset.masked(fit.mask)
        residuals = fit.residuals_nT[:, fit.mask]
    else:
        samples = kept
        residuals = run.calibration.total_field_residuals(kept, record_terms="apply")
    noise = estimate_noise(samples, residuals, int(round(n_params * dataset.n_sensors)), noise_nT=noise_nT)
    if noise.source != "given":
        run.remarks.append(f"noise not given: the floors use sigma = {noise.text()}")
    if noise.source == "residuals":
        run.remarks.append(noise.note)
    tf_floor = conventions.total_field_floor_nT(noise.sigma_nT, kept.n_samples, n_params)
    t_floor = None
    if _has_tensor(dataset):
        t_floor = {
            k: float(v) for k, v in conventions.tensor_floor_nT_per_m(noise.sigma_nT, dataset.baseline_m).items()
        }
    return noise, tf_floor, t_floor


def _summary(run: _Run, steps, model, method, robust, outliers, t_start, noise_nT=None) -> CalibrationResult:
    """The :class:`CalibrationResult` of the run: the final calibration, the steps' figures, noise and floors."""
    raw, final = steps[0], steps[-1]
    noise, tf_floor, t_floor = _noise_and_floors(run, model, final, noise_nT)
    calibration = run.calibration
    return CalibrationResult(
        calibration=calibration,
        fit=run.fit,
        steps=steps,
        remarks=run.remarks,
        method=method,
        reference_kind=run.ref_kind,
        reference_total_nT=calibration.reference_total_nT,
        n_samples=int(run.mask.sum()),
        rms_before_per_sensor_nT=raw.rms_per_sensor_nT,
        rms_after_per_sensor_nT=final.rms_per_sensor_nT,
        rms_nT=float(np.sqrt(np.mean(final.rms_per_sensor_nT**2))),
        tensor_rms_before_nT_per_m=raw.tensor_rms_nT_per_m,
        tensor_rms_nT_per_m=final.tensor_rms_nT_per_m,
        noise_nT=noise.sigma_nT,
        noise_source=noise.source,
        total_field_floor_nT=tf_floor,
        tensor_floor_nT_per_m=t_floor,
        ellipsoids=run.ellipsoids,
        outliers=outliers,
        mask=run.mask,
        wall_s=time.perf_counter() - t_start,
        robust=robust,
        effects=model.effect_labels if model is not None else [],
        field_magnitude_nT=_field_magnitude_nT(run.kept, calibration, run.ref_kind),
        noise=noise,
    )


def _field_magnitude_nT(kept, calibration, ref_kind) -> float:
    """The field magnitude (nT) of the final calibration, averaged over the sensors and the kept samples: the
    total field it expects (its reference, given or fitted, with any reference-stage effect, or the data's
    ``ref_total`` column)."""
    if calibration.model is not None and calibration.model.effects:
        expected = expected_total_field(
            kept,
            None if ref_kind == "column" else calibration.reference_total_nT,
            calibration.model,
            calibration.effect_values,
        )
    else:
        expected = _expected(kept, calibration, ref_kind)
    return float(np.mean(np.broadcast_to(expected, (kept.n_sensors, kept.n_samples))))


def _base_correct(calibration, dataset):
    """Array-frame vectors of the base terms only: ``R C^-1 (y - b)`` per sensor."""
    return np.stack([(y - c.bias_nT) @ (c.R @ c.cinv).T for c, y in zip(calibration.sensors, dataset.readings_nT)])


def _store_summary(result: CalibrationResult) -> None:
    """Write the figures into the calibration's summaries, so the saved JSON carries them."""
    cal = result.calibration
    cal.summary = dict(cal.summary or {})
    cal.summary.update(
        {
            "method": result.method,
            "robust": result.robust,
            "reference_kind": result.reference_kind,
            "n_samples": result.n_samples,
            "rms_nT": result.rms_nT,
            "rms_before_nT": float(np.sqrt(np.mean(result.rms_before_per_sensor_nT**2))),
            "tensor_rms_nT_per_m": result.tensor_rms_nT_per_m,
            "tensor_rms_before_nT_per_m": result.tensor_rms_before_nT_per_m,
            "noise_nT": result.noise_nT,
            "noise_source": result.noise_source,
            "noise": result.noise.to_dict() if result.noise is not None else None,
            "total_field_floor_nT": result.total_field_floor_nT,
            "tensor_floor_nT_per_m": result.tensor_floor_nT_per_m,
            "n_outliers": int(np.sum(result.outliers)) if result.outliers is not None else 0,
            "steps": [s.to_dict() for s in result.steps],
            "warnings": list(result.remarks),
        }
    )
    if result.fit is not None:
        cal.summary.update(
            {
                "aic": float(result.fit.aic),
                "bic": float(result.fit.bic),
                "noise_estimate_nT": float(result.fit.noise_nT),
                "field_magnitude_nT": result.field_magnitude_nT,
            }
        )
    if result.tensor_rms_nT_per_m is None:
        cal.summary.pop("tensor_rms_nT_per_m")
        cal.summary.pop("tensor_rms_before_nT_per_m")
        cal.summary.pop("tensor_floor_nT_per_m")
    for s, sensor in enumerate(cal.sensors):
        sensor.summary = dict(sensor.summary or {})
        sensor.summary.update(
            {
                "rms_before_nT": float(result.rms_before_per_sensor_nT[s]),
                "rms_nT": float(result.rms_after_per_sensor_nT[s]),
            }
        )
        if result.ellipsoids:
            cov = result.ellipsoids[s].coverage
            sensor.summary["coverage"] = {"thinnest_spread": cov.thinnest_spread, "sky_fraction": cov.sky_fraction}
