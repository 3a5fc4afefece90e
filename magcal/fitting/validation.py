"""Held-out validation: does an effect term lower the error on samples the fit did not see?

A term added to the model always lowers the in-sample RMS a little (it has more parameters to fit the noise
with), so "watch the error fall" means something only on *held-out* samples. This module splits a record in time,
fits on one part (:func:`magcal.fitting.pipeline.calibrate` with ``mask=``) and scores the total-field residuals on the
other:

``scheme="blocks"``
    The record is cut into an odd number of contiguous blocks in time; the fit uses the odd-numbered ones
    (1, 3, 5, ... -- the first and the last), the score the even-numbered ones. Blocks last at least
    :data:`MIN_BLOCK_S` (10 s), so the residuals of neighbouring samples, which are correlated through the
    slow attitude and temperature, do not leak from training into testing. Every held-out time lies between
    training times, so the record-only terms (bias drift, bias step, reference drift, site gradient:
    :attr:`magcal.model.terms.Effect.transferable` False) are *interpolated* there, which is honest.
``scheme="later"``
    The fit uses the first part of the record, the score its last stretch (``test_fraction``): what a
    calibration does for later data, scored exactly as ``magcal apply`` uses it on another record:
    the record-only terms are fitted with the base terms (so that they do not bias them) and *dropped* on the
    later stretch (:meth:`magcal.calibration.calibration.Calibration.correct` with ``record_terms="drop"``), and
    nothing is refitted or re-levelled there. A record-only term is therefore judged on later data by what it
    leaves in the calibration kept for new data -- the instrument terms fitted jointly with it and the level its
    parametrisation refers the base terms to (:attr:`magcal.model.terms.Effect.transferable`). The record's level
    on the later stretch taken out (:func:`relevel`) is still reported as ``relevelled_rms_nT``, for reading only.

:func:`validate` scores one model; :func:`compare` tells whether an added effect's in-sample gain holds on
held-out data; :func:`judge` is the rule of :func:`magcal.diagnosis.diagnose` for "describes this record"
(:data:`MIN_RELATIVE_GAIN` on ``blocks``) and :func:`transfers` the rule for "improves the calibration for new
data" (on ``later``: no rise for an instrument term, a fall for a record-only one). :func:`split_problem` says when a record is too short to split.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from magcal.calibration.calibration import is_transferable
from magcal.core import notes as _notes
from magcal.core.errors import CalibrationError, MagcalError
from magcal.core.rows import unit_rows
from magcal.fitting.fitter import COMPARISON_COST_TOLERANCE, fit
from magcal.fitting.pipeline import _build_model, calibrate
from magcal.model.terms import Model

SCHEMES = ("blocks", "later")

#: Shortest block (s) of the ``blocks`` scheme by default: longer than the correlation of the residuals of a
#: slowly turned instrument (its attitude and temperature change over seconds).
MIN_BLOCK_S = 10.0

#: Most blocks used by default (the first and last train, so the count is odd).
MAX_BLOCKS = 11

#: Relative fall of the held-out RMS an added effect must bring for :attr:`Comparison.holds` (1 %).
MIN_RELATIVE_GAIN = 0.01

#: Largest rise of the ``later`` held-out RMS an added effect may bring and still hold, in standard errors of that
#: RMS (``rms / sqrt(2 n_test)`` for Gaussian residuals): a fraction of the statistical spread of the score, so
#: that a term which changes nothing on later data is not refused for the noise of the comparison.
LATER_TOLERANCE_SE = 0.5

#: Fewest samples per block: a record with fewer than three blocks' worth (``3 * MIN_BLOCK_SAMPLES``), or with
#: time stamps spanning less than three blocks of :data:`MIN_BLOCK_S`, is too short to split (:func:`split_problem`).
MIN_BLOCK_SAMPLES = 50


def _times(dataset) -> np.ndarray:
    """Sample times (s), or sample numbers when the record has no time column."""
    if dataset.time_s is not None:
        return np.asarray(dataset.time_s, dtype=float)
    return np.arange(dataset.n_samples, dtype=float)


def default_n_blocks(dataset) -> int:
    """Odd number of blocks of at least :data:`MIN_BLOCK_S` each, 3 to :data:`MAX_BLOCKS` (11 blocks of equal
    sample count without a time column)."""
    if dataset.time_s is None:
        return MAX_BLOCKS
    t = _times(dataset)
    duration = float(t.max() - t.min()) if t.size else 0.0
    n = int(np.clip(np.floor(duration / MIN_BLOCK_S), 3, MAX_BLOCKS))
    return n if n % 2 else n - 1


def split_problem(dataset) -> str | None:
    """Why the record is too short for held-out validation, or None when it can be split.

    Too short: fewer than ``3 * MIN_BLOCK_SAMPLES`` samples, or time stamps spanning less than three blocks of
    :data:`MIN_BLOCK_S` (shorter blocks would let the correlated residuals of neighbouring samples leak from
    training into testing).
    """
    n = dataset.n_samples
    if n < 3 * MIN_BLOCK_SAMPLES:
        return (
            f"the record has {n} samples, fewer than three blocks of {MIN_BLOCK_SAMPLES}: too short to hold samples out"
        )
    if dataset.time_s is not None:
        t = np.asarray(dataset.time_s, float)
        if not np.all(np.isfinite(t)):
            return "the time column has gaps (NaN): the record cannot be split in time"
        duration = float(t.max() - t.min())
        if duration < 3 * MIN_BLOCK_S:
            return (
                f"the record lasts {duration:.3g} s, less than three blocks of {MIN_BLOCK_S:g} s: too short to "
                "hold samples out without neighbouring samples leaking into the test"
            )
    return None


def holdout_masks(dataset, scheme: str = "blocks", n_blocks: int | None = None, test_fraction: float = 0.25):
    """Training and held-out samples of a record, split in time.

    Parameters
    ----------
    dataset : Dataset
        The record (its ``time_s`` orders the samples; without one, the sample order does).
    scheme : {'blocks', 'later'}
        ``blocks``: ``n_blocks`` contiguous blocks of equal duration, train on the odd-numbered (1st, 3rd, ...,
        last), test on the even-numbered. ``later``: train on the first part, test on the last ``test_fraction``
        of the duration.
    n_blocks : int, optional
        Odd, at least 3 (so the record starts and ends with training blocks). Default :func:`default_n_blocks`.
    test_fraction : float
        Share of the duration held out at the end by the ``later`` scheme, in (0, 1).

    Returns
    -------
    train, test : numpy.ndarray of bool, shape (N,)
        Disjoint masks covering every sample.

    Raises
    ------
    MagcalError
        Unknown scheme, an even or too small ``n_blocks``, a ``test_fraction`` outside (0, 1), or a split that
        leaves one side empty.
    """
    if scheme not in SCHEMES:
        raise MagcalError(f"unknown validation scheme {scheme!r}; use one of {', '.join(SCHEMES)}")
    t = _times(dataset)
    n = t.size
    if n < 2:
        raise MagcalError(f"held-out validation needs at least 2 samples; the record has {n}")
    if dataset.time_s is not None and not np.all(np.isfinite(t)):
        raise MagcalError("held-out validation splits the record in time; its time column has gaps (NaN)")
    span = float(t.max() - t.min())
    position = (t - t.min()) / span if span > 0 else np.arange(n) / max(n - 1, 1)
    if scheme == "blocks":
        n_blocks = default_n_blocks(dataset) if n_blocks is None else n_blocks
        if (
            isinstance(n_blocks, bool)
            or not isinstance(n_blocks, (int, np.integer))
            or n_blocks < 3
            or n_blocks % 2 == 0
        ):
            raise MagcalError(
                f"n_blocks must be an odd whole number of at least 3 (the record starts and ends "
                f"with training blocks, so record-only terms interpolate), got {n_blocks!r}"
            )
        if dataset.time_s is None:
            position = np.arange(n) / n
        block = np.minimum((position * n_blocks).astype(int), n_blocks - 1)  # 0-based: 0, 2, 4... train
        train = block % 2 == 0
    else:
        if not 0.0 < float(test_fraction) < 1.0:
            raise MagcalError(f"test_fraction must lie between 0 and 1, got {test_fraction!r}")
        train = position < 1.0 - float(test_fraction)
    test = ~train
    if not train.any() or not test.any():
        raise MagcalError(
            f"the {scheme!r} split leaves no {'training' if not train.any() else 'held-out'} "
            f"samples in this record of {n}; give a longer record"
        )
    return train, test


def held_out_blocks(dataset, n_blocks: int | None = None) -> tuple[np.ndarray, np.ndarray, int]:
    """``(train, test, n_blocks)``: the ``blocks`` split of :func:`holdout_masks` for a fit's held-out check (the vector and the
    gravity fits' as the total-field fit's): blocks of equal duration in time order, the first and the last
    training, each at least :data:`MIN_BLOCK_S` long by default.

    Raises
    ------
    CalibrationError
        A record too short to split (:func:`split_problem`), the message naming it and why.
    MagcalError
        An even or too small ``n_blocks`` (:func:`holdout_masks`).
    """
    problem = split_problem(dataset)
    if problem is not None:
        raise CalibrationError(f"{dataset.source or 'data'}: {problem}")
    n_blocks = default_n_blocks(dataset) if n_blocks is None else n_blocks
    train, test = holdout_masks(dataset, "blocks", n_blocks)
    return train, test, n_blocks


@dataclass
class BlockValidation:
    """Held-out figures of a mode's fits on :func:`held_out_blocks` (the vector and the gravity fits' checks).

    Attributes
    ----------
    n_blocks : int
        Blocks in time: the fits use the odd-numbered ones (the first and the last among them), the figures
        ``held_*`` come from the others.
    rows : list of dict
        Per fit, its figures on the fitted blocks (``in_*``) and on the others (``held_*``).
    train : numpy.ndarray of bool, shape (N,), or None
        The samples of the fitted blocks.
    """

    n_blocks: int
    rows: list
    train: np.ndarray | None = field(default=None, repr=False, kw_only=True)

    def to_dict(self) -> dict:
        return {"n_blocks": self.n_blocks, "rows": [dict(r) for r in self.rows]}


@dataclass
class ValidationResult:
    """A model fitted on training samples and scored on held-out samples.

    Attributes
    ----------
    scheme : str
        ``blocks`` or ``later`` (:func:`holdout_masks`).
    effects : list of str
        The effect terms of the model fitted (labels).
    n_train, n_test : int
        Training and held-out samples.
    in_sample_rms_per_sensor_nT, held_out_rms_per_sensor_nT : numpy.ndarray, shape (n_sensors,)
        Total-field residual RMS per sensor on the training and on the held-out samples, nT.
    in_sample_rms_nT, held_out_rms_nT : float
        The same over all sensors, nT.
    dropped : list of str
        Record-only terms left out of the held-out score (``later`` scheme: they cannot be extrapolated).
    notes : list of str
        What the reader needs to know about the score.
    calibration : Calibration
        The calibration fitted on the training samples.
    held_out_consistency_rms_nT : float or None
        Arrays: RMS per component of the corrected vectors' differences from their mean across the sensors,
        perpendicular to the field (the inter-sensor consistency), on the held-out samples, nT.
    relevelled_rms_nT, relevelled_consistency_rms_nT : float or None
        ``later`` scheme: the same after a vector offset and a field offset per sensor, each constant plus a
        linear trend, are fitted to the held-out residuals (:func:`relevel`): the record's level on the later
        stretch (where a drift or a step has taken it) taken out: for reading only; :func:`compare` judges the
        plain held-out RMS, as ``magcal apply`` leaves it.
    train, test : numpy.ndarray of bool
        The masks used.
    fit_notes : list of Note
        What the training fit said (:mod:`magcal.core.notes`: e.g. it did not converge), never raised here.
    """

    scheme: str
    effects: list
    n_train: int
    n_test: int
    in_sample_rms_per_sensor_nT: np.ndarray
    held_out_rms_per_sensor_nT: np.ndarray
    in_sample_rms_nT: float
    held_out_rms_nT: float
    dropped: list = field(default_factory=list)
    notes: list = field(default_factory=list)
    calibration: object = None
    train: np.ndarray | None = None
    test: np.ndarray | None = None
    held_out_residuals_nT: np.ndarray | None = field(default=None, repr=False)
    held_out_consistency_rms_nT: float | None = None
    relevelled_rms_nT: float | None = None
    relevelled_consistency_rms_nT: float | None = None
    fit_notes: list = field(default_factory=list, repr=False)

    @property
    def overfit_ratio(self) -> float:
        """Held-out RMS over in-sample RMS (about 1 for a model that carries; well above 1 when it over-fits)."""
        return self.held_out_rms_nT / self.in_sample_rms_nT if self.in_sample_rms_nT > 0 else float("inf")

    def text(self) -> str:
        """A short report."""
        model = ", ".join(self.effects) or "base terms only"
        lines = [
            f"held-out validation ({self.scheme}) of {model}: trained on {self.n_train} samples, "
            f"scored on {self.n_test}",
            f"  RMS in-sample {self.in_sample_rms_nT:.3f} nT, held-out {self.held_out_rms_nT:.3f} nT",
        ]
        for s, (a, b) in enumerate(zip(self.in_sample_rms_per_sensor_nT, self.held_out_rms_per_sensor_nT)):
            lines.append(f"  sensor {s + 1}: in-sample {a:.3f} nT, held-out {b:.3f} nT")
        lines += [f"  note: {n}" for n in self.notes]
        return "\n".join(lines) + "\n"


def _rms(residuals) -> tuple[np.ndarray, float]:
    r = np.asarray(residuals, dtype=float)
    return np.sqrt(np.mean(r**2, axis=1)), float(np.sqrt(np.mean(r**2)))


def _effects_of(model, effects):
    """(effect specs, base terms) from a Model and/or a list of names / Effect objects."""
    specs, base = list(effects or ()), None
    if model is not None:
        specs = list(model.effects) + specs
        base = tuple(model.base)
    return specs, base


def relevel(residuals_nT, vectors_nT):
    """Residuals and vectors with the record's level taken out: per sensor, the least-squares vector offset
    ``d(tau) = d0 + d1 tau`` (nT, 3 each) and field offset ``f0 + f1 tau`` (nT) for ``r + u . d - f`` (``u`` the
    unit field direction, ``tau`` the sample's place in the stretch, -1 to 1), so a record-level bias or field
    that has moved on, or goes on drifting, is not counted against either model (8 parameters per sensor, the
    same for both models compared).

    Returns
    -------
    residuals_nT : numpy.ndarray, shape (n_sensors, N)
    vectors_nT : numpy.ndarray, shape (n_sensors, N, 3)
    """
    r = np.asarray(residuals_nT, float).copy()
    v = np.asarray(vectors_nT, float).copy()
    n = r.shape[1]
    tau = np.linspace(-1.0, 1.0, n)[:, None] if n > 1 else np.zeros((n, 1))
    for s in range(r.shape[0]):
        u = unit_rows(v[s])
        design = np.column_stack([u, u * tau, -np.ones(n), -tau[:, 0]])
        coef, *_ = np.linalg.lstsq(design, -r[s], rcond=None)
        r[s] += design @ coef
        v[s] += coef[:3] + tau * coef[3:6]
    return r, v


def consistency_rms_nT(vectors) -> float | None:
    """RMS per component (nT) of corrected array vectors' differences from their mean across the sensors,
    perpendicular to the field (two components per sensor; ``n_sensors / (n_sensors - 1)`` corrects for the
    mean); None for one sensor."""
    v = np.asarray(vectors, float)
    ns = v.shape[0]
    if ns < 2:
        return None
    mean = v.mean(axis=0)
    u = unit_rows(mean)
    diff = v - mean
    perp = diff - np.einsum("sni,ni->sn", diff, u)[..., None] * u
    return float(np.sqrt(np.sum(perp**2) * ns / (ns - 1) / (2 * ns * v.shape[1])))


def validate(
    dataset,
    model=None,
    effects=(),
    scheme: str = "blocks",
    n_blocks: int | None = None,
    test_fraction: float = 0.25,
    robust: bool = False,
    reference_total_nT=None,
    masks=None,
    init=None,
) -> ValidationResult:
    """Fit on the training samples of a record and score the total-field residuals on the held-out ones.

    Parameters
    ----------
    dataset : Dataset
        The record.
    model : Model, optional
        Base terms and effects to fit (copied; never changed).
    effects : sequence of str or Effect
        Effects to fit (added to ``model``'s), as :func:`magcal.fitting.pipeline.calibrate` takes them.
    scheme, n_blocks, test_fraction
        The split (:func:`holdout_masks`).
    robust : bool
        Robust loss in the fit (:func:`magcal.fitting.pipeline.calibrate`); the scores still use every sample.
    reference_total_nT : float, optional
        Known total field, nT (as in :func:`magcal.fitting.pipeline.calibrate`).
    masks : tuple of numpy.ndarray, optional
        ``(train, test)`` to use instead of computing them (so that two models are scored on the same split).
    init : Calibration, optional
        A calibration of the same model next to its whole-record minimum (fitted on the whole record, or a
        candidate's predicted start in the diagnosis) to start the maximum-likelihood fit of the training samples
        from, instead of the ellipsoid and Procrustes steps. The training fit is then the one-step estimator
        (:func:`magcal.fitting.fitter.fit` with ``max_steps=1``): such a start lies within a few standard errors
        of the training samples' minimum, and one Gauss-Newton step from there reaches it to first order (its
        remaining error is second order in that distance, far below the held-out RMS's own spread), for one pass
        over the training samples. The effects' data-derived constants (a step time, a reference time) are still
        found from the training samples alone.

    Returns
    -------
    ValidationResult
    """
    if scheme not in SCHEMES:
        raise MagcalError(f"unknown validation scheme {scheme!r}; use one of {', '.join(SCHEMES)}")
    train, test = holdout_masks(dataset, scheme, n_blocks, test_fraction) if masks is None else masks
    train, test = np.asarray(train, bool), np.asarray(test, bool)
    specs, base = _effects_of(model, effects)
    if init is not None:
        built = _build_model(dataset, specs)
        full = Model(built.n_sensors, base=tuple(base) if base is not None else built.base, effects=built.effects)
        fitted = fit(
            dataset,
            full,
            init=init,
            loss="soft_l1" if robust else "linear",
            mask=train,
            reference_total_nT=reference_total_nT,
            cost_tolerance=COMPARISON_COST_TOLERANCE,
            max_steps=1,
            warn=False,
        )
    else:
        result = calibrate(
            dataset, effects=specs, robust=robust, reference_total_nT=reference_total_nT, mask=train, base_terms=base
        )
        assert result.fit is not None  # the maximum-likelihood step always runs here
        fitted = result.fit
    fit_notes = list(result.notes) if init is None else list(fitted.notes)
    cal, labels = fitted.calibration, fitted.model.effect_labels
    test_ds = dataset.masked(test)
    notes, dropped = [], []
    record_only = [e.label for e in (cal.model.effects if cal.model is not None else []) if not is_transferable(e)]
    if scheme == "later" and record_only:
        dropped = record_only
        notes.append(
            f"{', '.join(record_only)} describe(s) the fitted record only: fitted with the base terms (so they "
            "are not biased) and dropped on the later samples, as magcal apply drops them on another record"
        )
        vectors = cal.correct(test_ds, record_terms="drop")
        out_res = cal.total_field_residuals(test_ds, vectors, record_terms="drop")
    else:
        if record_only:
            notes.append(
                f"{', '.join(record_only)} describe(s) the record: evaluated at held-out times between "
                "training blocks (interpolation in time)"
            )
        vectors = cal.correct(test_ds, record_terms="apply")
        out_res = cal.total_field_residuals(test_ds, vectors, record_terms="apply")
    # in-sample: the fit's own residuals on the training samples (record-only terms applied, as fitted)
    in_per, in_all = np.asarray(fitted.rms_per_sensor_nT, float), float(fitted.rms_nT)
    out_per, out_all = _rms(out_res)
    relevelled = relevelled_consistency = None
    if scheme == "later":
        level_res, level_vec = relevel(out_res, vectors)
        relevelled = _rms(level_res)[1]
        relevelled_consistency = consistency_rms_nT(level_vec)
    return ValidationResult(
        scheme=scheme,
        effects=list(labels),
        n_train=int(train.sum()),
        n_test=int(test.sum()),
        in_sample_rms_per_sensor_nT=in_per,
        held_out_rms_per_sensor_nT=out_per,
        in_sample_rms_nT=in_all,
        held_out_rms_nT=out_all,
        dropped=dropped,
        notes=notes,
        calibration=cal,
        train=train,
        test=test,
        held_out_residuals_nT=out_res,
        held_out_consistency_rms_nT=consistency_rms_nT(vectors),
        relevelled_rms_nT=relevelled,
        relevelled_consistency_rms_nT=relevelled_consistency,
        fit_notes=fit_notes,
    )


@dataclass
class Comparison:
    """Whether an added effect's in-sample gain holds on held-out samples (:func:`compare`).

    Attributes
    ----------
    effect : str
        Label of the added effect.
    base, with_effect : ValidationResult
        The model without and with it, fitted and scored on the same split.
    in_sample_ratio, held_out_ratio : float
        RMS with the effect over RMS without, in-sample (total field) and held-out (below 1: the effect lowers
        the error). For arrays the held-out total-field RMS and inter-sensor consistency RMS are compared apart
        and the smaller ratio is kept (a sensor timing skew changes only the consistency).
    retained : float
        Share of the in-sample fall of the RMS that the held-out RMS keeps (1: all of it; 0 or less: none).
    holds : bool
        True when the held-out RMS falls by at least ``min_relative_gain`` (default 1 %); for arrays, one of the
        two held-out figures falls so and the other does not rise.
    does_not_rise : bool
        True when no held-out RMS rises by more than :data:`LATER_TOLERANCE_SE` standard errors of it.
    improves : bool
        True when the held-out RMS falls by more than :data:`LATER_TOLERANCE_SE` standard errors and none rises
        (the rule of the ``later`` scheme in :func:`judge`: the calibration improves for new data).
    """

    effect: str
    base: ValidationResult
    with_effect: ValidationResult
    in_sample_ratio: float
    held_out_ratio: float
    retained: float
    holds: bool
    min_relative_gain: float = MIN_RELATIVE_GAIN
    does_not_rise: bool = True
    improves: bool = False

    @property
    def rise_tolerance_nT(self) -> float:
        """The rise of the held-out RMS (nT) still counted as none: :data:`LATER_TOLERANCE_SE` standard errors."""
        return rise_tolerance_nT(self.base.held_out_rms_nT, self.base.n_test)

    def text(self) -> str:
        verdict = "holds" if self.holds else "does not hold"
        return (
            f"{self.effect}: in-sample RMS x{self.in_sample_ratio:.3f}, held-out RMS x{self.held_out_ratio:.3f} "
            f"({self.with_effect.scheme} scheme; {self.with_effect.n_test} held-out samples): the gain "
            f"{verdict} on held-out data\n"
        )


def rise_tolerance_nT(rms_nT, n_test) -> float:
    """:data:`LATER_TOLERANCE_SE` standard errors of a held-out RMS of ``n_test`` samples per sensor, nT
    (``rms / sqrt(2 n)``, the standard error of the RMS of Gaussian residuals)."""
    return float(LATER_TOLERANCE_SE * rms_nT / np.sqrt(2.0 * max(int(n_test), 1)))


def compare(
    dataset,
    base_effects=(),
    added_effect=None,
    scheme: str = "blocks",
    n_blocks: int | None = None,
    test_fraction: float = 0.25,
    min_relative_gain: float = MIN_RELATIVE_GAIN,
    robust: bool = False,
    reference_total_nT=None,
    base=None,
    base_model=None,
    base_init=None,
    with_model=None,
    with_init=None,
    with_effect=None,
) -> Comparison:
    """Does adding ``added_effect`` to ``base_effects`` lower the error on held-out samples?

    Both models are fitted on the same training samples and scored on the same held-out ones.

    Parameters
    ----------
    dataset : Dataset
    base_effects : sequence of str or Effect
        Effects already in the model (names as ``"temperature_bias"``, ``"bias_drift:2"``, or objects).
    added_effect : str or Effect
        The effect tried.
    scheme, n_blocks, test_fraction
        As in :func:`holdout_masks`.
    min_relative_gain : float
        Least relative fall of the held-out RMS for :attr:`Comparison.holds`.
    robust, reference_total_nT
        As in :func:`validate`.
    base : ValidationResult, optional
        The base model already validated on this split (reused: several candidates are compared with one base).
    base_model, with_model : Model, optional
        The models without and with the effect, instead of ``base_effects`` and ``added_effect`` (which then
        only names the effect).
    base_init, with_init : Calibration, optional
        Warm starts of the two fits (:func:`validate`'s ``init``).
    with_effect : ValidationResult, optional
        The model with the effect already validated on the same split as ``base`` (so that the fits of several
        candidates and schemes can run side by side before they are compared).

    Returns
    -------
    Comparison
    """
    if added_effect is None:
        raise MagcalError("compare needs the effect to add (a name such as 'temperature_bias' or an Effect)")
    masks = (base.train, base.test) if base is not None else holdout_masks(dataset, scheme, n_blocks, test_fraction)
    kwargs = dict(scheme=scheme, robust=robust, reference_total_nT=reference_total_nT, masks=masks)
    if base is None:
        base = (
            validate(dataset, model=base_model, init=base_init, **kwargs)
            if base_model is not None
            else validate(dataset, effects=list(base_effects), init=base_init, **kwargs)
        )
    if with_effect is not None:
        pass
    elif with_model is not None:
        with_effect = validate(dataset, model=with_model, init=with_init, **kwargs)
    else:
        with_effect = validate(dataset, effects=list(base_effects) + [added_effect], init=with_init, **kwargs)
    label = added_effect if isinstance(added_effect, str) else added_effect.label
    in_ratio = with_effect.in_sample_rms_nT / base.in_sample_rms_nT
    parts = [(base.held_out_rms_nT, with_effect.held_out_rms_nT)]
    if base.held_out_consistency_rms_nT is not None and with_effect.held_out_consistency_rms_nT is not None:
        parts.append((base.held_out_consistency_rms_nT, with_effect.held_out_consistency_rms_nT))
    if with_effect.dropped:
        # a record-only term on later data, dropped as apply drops it: the total field judges the calibration kept
        # for new data; an array's consistency residual is left out, since the record-only terms that act on it
        # (a site gradient, following the attitude in the site's field) describe the site, not the instrument
        parts = parts[:1]
    # arrays: the total field and the inter-sensor consistency are judged apart (a sensor timing skew changes only
    # the second): the better ratio counts, and neither may rise
    out_ratio = min(after / before for before, after in parts)
    no_rise = all(after <= before + rise_tolerance_nT(before, base.n_test) for before, after in parts)
    improves = no_rise and any(after < before - rise_tolerance_nT(before, base.n_test) for before, after in parts)
    in_gain = base.in_sample_rms_nT - with_effect.in_sample_rms_nT
    out_gain = base.held_out_rms_nT - with_effect.held_out_rms_nT
    retained = out_gain / in_gain if in_gain > 0 else 0.0
    return Comparison(
        effect=label,
        base=base,
        with_effect=with_effect,
        in_sample_ratio=in_ratio,
        held_out_ratio=out_ratio,
        retained=float(retained),
        holds=bool(out_ratio <= 1.0 - min_relative_gain and (len(parts) == 1 or no_rise)),
        min_relative_gain=min_relative_gain,
        does_not_rise=bool(no_rise),
        improves=bool(improves),
    )


def judge(blocks: Comparison, later: Comparison | None = None) -> bool:
    """Whether an added effect *describes the record*: its ``blocks`` held-out RMS falls by at least
    :data:`MIN_RELATIVE_GAIN` (interpolation, every term). ``later`` is accepted for the callers of the earlier
    rule and no longer consulted: whether the effect *improves the calibration for new data* is :func:`transfers`."""
    return bool(blocks.holds)


def transfers(later: Comparison, record_only: bool = False) -> bool:
    """Whether an added effect improves the calibration for new data: fitted on the earlier part and applied to
    the later stretch as ``magcal apply`` does (record-only terms dropped, nothing re-levelled).

    An instrument term stays in the calibration and acts on the later stretch as it did on the record: it
    transfers when the later RMS does not rise beyond :data:`LATER_TOLERANCE_SE` standard errors
    (:attr:`Comparison.does_not_rise`). A record-only term is dropped there, so what it described is gone: it
    transfers only when the calibration it leaves is measurably better, a fall by :data:`MIN_RELATIVE_GAIN` and
    beyond :data:`LATER_TOLERANCE_SE` standard errors (:attr:`Comparison.holds` and :attr:`Comparison.improves`;
    on real recordings a fall of 0.7 % on the later stretch became a rise of 2 % on new data)."""
    return bool(later.holds and later.improves) if record_only else bool(later.does_not_rise)


@dataclass
class EffectsValidation:
    """Held-out RMS of a calibration's base model and of the model with its effects (:func:`validate_effects`).

    Attributes
    ----------
    effects : list of str
        Labels of the effects in the calibrated model.
    base, with_effects : ValidationResult or None
        The base model and the model with the effects, fitted on the same training blocks and scored on the same
        held-out ones (``blocks`` scheme); None when the record is too short to split.
    in_sample_base_nT, in_sample_with_effects_nT : float
        Total-field RMS of the two models fitted on the whole record, nT.
    skipped : str or None
        Why there is no held-out score.
    notes : list of Note
        What its fits said (:mod:`magcal.core.notes`), never raised here (:func:`magcal.calibrate` raises them).
    holds : bool or None
        Whether the effects lower the held-out RMS by at least :data:`MIN_RELATIVE_GAIN`.
    """

    effects: list
    base: ValidationResult | None
    with_effects: ValidationResult | None
    in_sample_base_nT: float | None
    in_sample_with_effects_nT: float
    skipped: str | None = None
    notes: list = field(default_factory=list, repr=False)

    @property
    def holds(self) -> bool | None:
        if self.base is None or self.with_effects is None:
            return None
        return bool(self.with_effects.held_out_rms_nT <= (1.0 - MIN_RELATIVE_GAIN) * self.base.held_out_rms_nT)

    @property
    def notes_for_user(self) -> list:
        """Warnings for the command line: a skipped validation, or effects whose gain does not hold."""
        if self.skipped:
            return [f"held-out validation not done: {self.skipped}"]
        if self.holds is False:
            assert self.base is not None and self.with_effects is not None  # set whenever not skipped
            return [
                f"the effects {', '.join(self.effects)} do not lower the held-out RMS (blocks) by "
                f"{MIN_RELATIVE_GAIN:.0%}: {self.base.held_out_rms_nT:.4g} -> "
                f"{self.with_effects.held_out_rms_nT:.4g} nT; their in-sample gain fits this record only"
            ]
        return []

    def to_dict(self) -> dict:
        """The ``validation`` object of ``magcal calibrate --json`` (RMS in nT)."""

        def scores(v):
            if v is None:
                return None
            return {
                "effects": list(v.effects),
                "n_train": v.n_train,
                "n_test": v.n_test,
                "in_sample_rms_nT": float(v.in_sample_rms_nT),
                "held_out_rms_nT": float(v.held_out_rms_nT),
                "held_out_rms_per_sensor_nT": [float(x) for x in v.held_out_rms_per_sensor_nT],
                "notes": list(v.notes),
            }

        return {
            "scheme": "blocks",
            "effects": list(self.effects),
            "skipped": self.skipped,
            "in_sample_rms_base_nT": self.in_sample_base_nT,
            "in_sample_rms_with_effects_nT": self.in_sample_with_effects_nT,
            "base": scores(self.base),
            "with_effects": scores(self.with_effects),
            "holds": self.holds,
            "min_relative_gain": MIN_RELATIVE_GAIN,
        }

    def text(self) -> str:
        """Lines for the calibration report."""
        if self.skipped:
            return f"Held-out validation: not done ({self.skipped})\n"
        b, w = self.base, self.with_effects
        assert b is not None and w is not None  # set whenever not skipped
        base_in = "-" if self.in_sample_base_nT is None else f"{self.in_sample_base_nT:.4g}"
        lines = [
            f"Held-out validation (blocks: fitted on {w.n_train} samples in alternating blocks of time, scored "
            f"on the {w.n_test} between), total-field RMS, nT",
            f"  {'model':<36}{'in-sample':>12}{'held-out':>12}",
            f"  {'base terms':<36}{base_in:>12}{b.held_out_rms_nT:>12.4g}",
            f"  {'+ ' + ', '.join(self.effects):<36}{self.in_sample_with_effects_nT:>12.4g}{w.held_out_rms_nT:>12.4g}",
            "  the effects' gain "
            + (
                "holds on held-out data"
                if self.holds
                else f"does NOT hold on held-out data (less than {MIN_RELATIVE_GAIN:.0%})"
            ),
        ]
        lines += [f"  note: {n}" for n in w.notes]
        return "\n".join(lines) + "\n"


def validate_effects(dataset, result) -> EffectsValidation:
    """Held-out RMS (``blocks`` scheme) of a calibration's base model and of its model with effects.

    Parameters
    ----------
    dataset : Dataset
        The record the calibration was fitted on.
    result : CalibrationResult
        A maximum-likelihood calibration (:func:`magcal.fitting.pipeline.calibrate` with ``effects=``).

    Returns
    -------
    EffectsValidation
        Also set as ``result.validation`` by :func:`magcal.calibrate` with ``validate=True``.
    """

    fit = getattr(result, "fit", None)
    if fit is None:
        raise MagcalError("held-out validation needs a maximum-likelihood calibration (method 'ml')")
    kept = dataset.masked(fit.mask)
    reference = fit.calibration.reference_total_nT if fit.reference_kind == "given" else None
    effects = list(fit.model.effect_labels)
    base_in, notes = None, []
    if effects:
        base_fit = calibrate(kept, reference_total_nT=reference, base_terms=fit.model.base)
        base_in = float(base_fit.rms_nT)
        notes += base_fit.notes
    else:
        base_in = float(fit.rms_nT)
    problem = split_problem(kept)
    if problem:
        return EffectsValidation(effects, None, None, base_in, float(fit.rms_nT), skipped=problem, notes=notes)
    masks = holdout_masks(kept, "blocks")
    base = validate(
        kept,
        model=type(fit.model)(fit.model.n_sensors, fit.model.base, []),
        masks=masks,
        reference_total_nT=reference,
        init=base_fit.calibration if effects else fit.calibration,
    )
    with_effects = (
        validate(kept, model=fit.model, masks=masks, reference_total_nT=reference, init=fit.calibration)
        if effects
        else base
    )
    notes += base.fit_notes + (with_effects.fit_notes if effects else [])
    return EffectsValidation(effects, base, with_effects, base_in, float(fit.rms_nT), notes=_notes.unique(notes))
