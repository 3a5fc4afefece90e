"""Held-out validation: does an effect term lower the error on samples the fit did not see?

A term added to the model always lowers the in-sample RMS a little (it has more parameters to fit the noise
with), so "watch the error fall" means something only on *held-out* samples. This module splits a record in time,
fits on one part (:func:`magcal.pipeline.calibrate` with ``mask=``) and scores the total-field residuals on the
other:

``scheme="blocks"``
    The record is cut into an odd number of contiguous blocks in time; the fit uses the odd-numbered ones
    (1, 3, 5, ... -- the first and the last), the score the even-numbered ones. Blocks last at least
    :data:`MIN_BLOCK_S` (10 s), so the residuals of neighbouring samples, which are correlated through the
    slow attitude and temperature, do not leak from training into testing. Every held-out time lies between
    training times, so the record-only terms (bias drift, bias step, reference drift, site gradient:
    :attr:`magcal.model.Effect.transferable` False) are *interpolated* there, which is honest.
``scheme="later"``
    The fit uses the first part of the record, the score its last stretch (``test_fraction``): what a
    calibration does for later data. Record-only terms cannot be extrapolated past the fitted record, so they
    are left out of the score (the fit keeps them, so that they do not bias the instrument terms) and the
    result says so.

:func:`validate` scores one model; :func:`compare` tells whether an added effect's in-sample gain holds on
held-out data.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .calibration import is_transferable
from .errors import MagcalError

SCHEMES = ("blocks", "later")

#: Shortest block (s) of the ``blocks`` scheme by default: longer than the correlation of the residuals of a
#: slowly turned instrument (its attitude and temperature change over seconds).
MIN_BLOCK_S = 10.0

#: Most blocks used by default (the first and last train, so the count is odd).
MAX_BLOCKS = 11

#: Relative fall of the held-out RMS an added effect must bring for :attr:`Comparison.holds` (1 %).
MIN_RELATIVE_GAIN = 0.01


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
        if isinstance(n_blocks, bool) or not isinstance(n_blocks, (int, np.integer)) or n_blocks < 3 \
                or n_blocks % 2 == 0:
            raise MagcalError(f"n_blocks must be an odd whole number of at least 3 (the record starts and ends "
                              f"with training blocks, so record-only terms interpolate), got {n_blocks!r}")
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
        raise MagcalError(f"the {scheme!r} split leaves no {'training' if not train.any() else 'held-out'} "
                          f"samples in this record of {n}; give a longer record")
    return train, test


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
    train, test : numpy.ndarray of bool
        The masks used.
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

    @property
    def overfit_ratio(self) -> float:
        """Held-out RMS over in-sample RMS (about 1 for a model that carries; well above 1 when it over-fits)."""
        return self.held_out_rms_nT / self.in_sample_rms_nT if self.in_sample_rms_nT > 0 else float("inf")

    def text(self) -> str:
        """A short report."""
        model = ", ".join(self.effects) or "base terms only"
        lines = [f"held-out validation ({self.scheme}) of {model}: trained on {self.n_train} samples, "
                 f"scored on {self.n_test}",
                 f"  RMS in-sample {self.in_sample_rms_nT:.3f} nT, held-out {self.held_out_rms_nT:.3f} nT"]
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


def validate(dataset, model=None, effects=(), scheme: str = "blocks", n_blocks: int | None = None,
             test_fraction: float = 0.25, robust: bool = False, reference_total_nT=None, masks=None,
             ) -> ValidationResult:
    """Fit on the training samples of a record and score the total-field residuals on the held-out ones.

    Parameters
    ----------
    dataset : Dataset
        The record.
    model : Model, optional
        Base terms and effects to fit (copied; never changed).
    effects : sequence of str or Effect
        Effects to fit (added to ``model``'s), as :func:`magcal.pipeline.calibrate` takes them.
    scheme, n_blocks, test_fraction
        The split (:func:`holdout_masks`).
    robust : bool
        Robust loss in the fit (:func:`magcal.pipeline.calibrate`); the scores still use every sample.
    reference_total_nT : float, optional
        Known total field, nT (as in :func:`magcal.pipeline.calibrate`).
    masks : tuple of numpy.ndarray, optional
        ``(train, test)`` to use instead of computing them (so that two models are scored on the same split).

    Returns
    -------
    ValidationResult
    """
    from .pipeline import calibrate

    train, test = holdout_masks(dataset, scheme, n_blocks, test_fraction) if masks is None else masks
    train, test = np.asarray(train, bool), np.asarray(test, bool)
    if scheme not in SCHEMES:
        raise MagcalError(f"unknown validation scheme {scheme!r}; use one of {', '.join(SCHEMES)}")
    specs, base = _effects_of(model, effects)
    result = calibrate(dataset, effects=specs, robust=robust, reference_total_nT=reference_total_nT, mask=train,
                       base_terms=base)
    cal = result.calibration
    train_ds, test_ds = dataset.subset(train), dataset.subset(test)
    in_res = cal.total_field_residuals(train_ds, record_terms="apply")
    notes, dropped = [], []
    record_only = [e.label for e in (cal.model.effects if cal.model is not None else []) if not is_transferable(e)]
    if scheme == "later" and record_only:
        dropped = record_only
        notes.append(f"{', '.join(record_only)} describe(s) the fitted record only and cannot be extrapolated to "
                     "later samples: fitted (so the instrument terms are not biased) but left out of the held-out "
                     "score")
        out_res = cal.total_field_residuals(test_ds, record_terms="drop")
    else:
        if record_only:
            notes.append(f"{', '.join(record_only)} describe(s) the record: evaluated at held-out times between "
                         "training blocks (interpolation in time)")
        out_res = cal.total_field_residuals(test_ds, record_terms="apply")
    in_per, in_all = _rms(in_res)
    out_per, out_all = _rms(out_res)
    return ValidationResult(
        scheme=scheme, effects=list(result.effects), n_train=int(train.sum()), n_test=int(test.sum()),
        in_sample_rms_per_sensor_nT=in_per, held_out_rms_per_sensor_nT=out_per, in_sample_rms_nT=in_all,
        held_out_rms_nT=out_all, dropped=dropped, notes=notes, calibration=cal, train=train, test=test,
        held_out_residuals_nT=out_res,
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
        RMS with the effect over RMS without, in-sample and held-out (below 1: the effect lowers the error).
    retained : float
        Share of the in-sample fall of the RMS that the held-out RMS keeps (1: all of it; 0 or less: none).
    holds : bool
        True when the held-out RMS falls by at least ``min_relative_gain`` (default 1 %).
    """

    effect: str
    base: ValidationResult
    with_effect: ValidationResult
    in_sample_ratio: float
    held_out_ratio: float
    retained: float
    holds: bool
    min_relative_gain: float = MIN_RELATIVE_GAIN

    def text(self) -> str:
        verdict = "holds" if self.holds else "does not hold"
        return (f"{self.effect}: in-sample RMS x{self.in_sample_ratio:.3f}, held-out RMS x{self.held_out_ratio:.3f} "
                f"({self.with_effect.scheme} scheme; {self.with_effect.n_test} held-out samples): the gain "
                f"{verdict} on held-out data\n")


def compare(dataset, base_effects=(), added_effect=None, scheme: str = "blocks", n_blocks: int | None = None,
            test_fraction: float = 0.25, min_relative_gain: float = MIN_RELATIVE_GAIN, robust: bool = False,
            reference_total_nT=None) -> Comparison:
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

    Returns
    -------
    Comparison
    """
    if added_effect is None:
        raise MagcalError("compare needs the effect to add (a name such as 'temperature_bias' or an Effect)")
    masks = holdout_masks(dataset, scheme, n_blocks, test_fraction)
    kwargs = dict(scheme=scheme, robust=robust, reference_total_nT=reference_total_nT, masks=masks)
    base = validate(dataset, effects=list(base_effects), **kwargs)
    with_effect = validate(dataset, effects=list(base_effects) + [added_effect], **kwargs)
    label = added_effect if isinstance(added_effect, str) else added_effect.label
    in_ratio = with_effect.in_sample_rms_nT / base.in_sample_rms_nT
    out_ratio = with_effect.held_out_rms_nT / base.held_out_rms_nT
    in_gain = base.in_sample_rms_nT - with_effect.in_sample_rms_nT
    out_gain = base.held_out_rms_nT - with_effect.held_out_rms_nT
    retained = out_gain / in_gain if in_gain > 0 else 0.0
    return Comparison(effect=label, base=base, with_effect=with_effect, in_sample_ratio=in_ratio,
                      held_out_ratio=out_ratio, retained=float(retained),
                      holds=bool(out_ratio <= 1.0 - min_relative_gain), min_relative_gain=min_relative_gain)
