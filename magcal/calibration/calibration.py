"""The calibration: apply a fitted model to new data, and save or load it as JSON.

:func:`corrected_fields` and :func:`expected_total_field` are *the* correction model (see :mod:`magcal.model.terms`);
the fitter evaluates the same two functions, so what is fitted is exactly what is applied.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field, replace

import numpy as np

from magcal.calibration.accelerometer import AccelerometerCalibration
from magcal.calibration.uncertainty import covariance_size, field_uncertainty
from magcal.checks.reference import USABLE_TOTAL_nT
from magcal.core import conventions
from magcal.core import notes as _notes
from magcal.core.errors import DataWarning, MagcalError, RecordTermWarning, exception_text
from magcal.core.files import not_regular_reason
from magcal.core.jsonable import jsonable
from magcal.core.notes import Note, row_runs
from magcal.core.rows import basis_times, row_norm
from magcal.data.accelerometer import accelerometer
from magcal.data.attitude import attitude_rows
from magcal.data.dataset import MAX_ABS_VALUE
from magcal.data.inputs import as_dataset
from magcal.data.io import atomic_write
from magcal.geometry.heading import dip_deg, tilt_deg, tilt_heading_deg
from magcal.model.effects import CURRENT_COLUMNS
from magcal.model.platform_terms import PlatformTerms
from magcal.model.terms import (
    BASE_TERMS,
    CORRECTION_STAGES,
    EFFECTS,
    Model,
    attitude_effects,
    block_label,
    contexts,
    parse_effect,
    rows_without_attitude,
    unknown_effect_message,
)

FORMAT = "magcal-calibration"
VERSION = 1

#: The calibration modes (``mode`` in the file) and those whose sensors' ``R`` is a mounting into a physical frame
#: (the vehicle's body, or the board's accelerometer) rather than a gauge.
MODES = ("scalar", "vector", "gravity")
MOUNTED_MODES = ("vector", "gravity")
#: Largest magnitude of any parameter a calibration file may hold (the bias, ``C^-1``, an effect's parameters and
#: constants, a platform term; the baseline from its inverse up to it): the bound of every read value
#: (:data:`magcal.data.dataset.MAX_ABS_VALUE`). Applied to readings within that bound, such parameters give finite
#: results; beyond it a calibration (``C^-1 = 1e308 I``) made infinite corrected values and firmware parameters.
MAX_PARAMETER = MAX_ABS_VALUE
#: Largest magnitude of a covariance entry (a parameter's variance: :data:`MAX_PARAMETER` squared).
MAX_COVARIANCE = MAX_PARAMETER**2
#: Largest calibration file read (bytes): a calibration of four sensors with effects and its covariance is tens of
#: kB; a file far larger is not one (and is refused before it is parsed).
MAX_CALIBRATION_BYTES = 64 << 20

#: Effects that describe one recording, used only for an effect class that does not say
#: (:attr:`magcal.model.terms.Effect.transferable` is the authority).
RECORD_ONLY_FALLBACK = frozenset({"bias_drift", "bias_step", "reference_drift", "site_gradient"})

#: The ``where`` of :meth:`Calibration.correction_notes`'s note on samples an effect cannot correct for want of
#: an attitude (``magcal apply`` counts those rows over the whole survey instead, :class:`magcal.output.apply.AttitudeGaps`).
ATTITUDE_GAP_NOTE = "correct: no attitude"

#: The ``where`` of :meth:`Calibration.refusal_note`: sensors whose calibration is not determined, refused or forced.
UNDETERMINED_NOTE = "apply: not determined"

#: Choices of ``record_terms`` (:meth:`Calibration.correct`): ``None`` decides from the record fingerprint.
RECORD_TERM_CHOICES = ("apply", "drop")


#: Resolution (nT, s) at which readings and times enter the record fingerprint: far below any sensor's noise,
#: far above the rounding of a number written to a CSV file and read back.
_FINGERPRINT_RESOLUTION = 1e-6


def is_transferable(effect) -> bool:
    """True if the effect term describes the instrument and carries to new data; False for a term that describes
    one recording (:attr:`magcal.model.terms.Effect.transferable`; a class that does not say falls back on
    :data:`RECORD_ONLY_FALLBACK`)."""
    flag = getattr(effect, "transferable", None)
    if isinstance(flag, bool):
        return flag
    return getattr(effect, "name", "") not in RECORD_ONLY_FALLBACK


class RecordHasher:
    """Fingerprint of a record built sample by sample, so a streamed file gives the same result as the whole
    dataset: :func:`record_fingerprint` of a dataset equals feeding its chunks in order to :meth:`update`.

    The hash covers the readings (nT) and the times (s), rounded to 1e-6, sample after sample.
    """

    def __init__(self):
        self._hash = hashlib.sha256()
        self.n_samples = 0
        self.time_start_s = None
        self.time_end_s = None

    def update(self, dataset) -> None:
        """Add the samples of one dataset (a chunk of the record, in time order)."""
        readings = np.ascontiguousarray(np.transpose(dataset.readings_nT, (1, 0, 2)))  # sample-major
        rows = np.round(readings.reshape(readings.shape[0], -1) / _FINGERPRINT_RESOLUTION)
        if dataset.time_s is not None:
            t = np.asarray(dataset.time_s, dtype=float)
            rows = np.column_stack([np.round(t / _FINGERPRINT_RESOLUTION), rows])
            if t.size:
                self.time_start_s = float(t[0]) if self.time_start_s is None else self.time_start_s
                self.time_end_s = float(t[-1])
        self._hash.update(np.ascontiguousarray(rows, dtype="<f8"))  # the buffer itself: no copy of its bytes
        self.n_samples += int(dataset.n_samples)

    def fingerprint(self) -> dict:
        """``n_samples``, ``time_start_s``, ``time_end_s`` (None without a time column) and ``readings_sha256``."""
        return {
            "n_samples": self.n_samples,
            "time_start_s": self.time_start_s,
            "time_end_s": self.time_end_s,
            "readings_sha256": self._hash.hexdigest(),
        }


def record_fingerprint(dataset) -> dict:
    """The fingerprint of the record a calibration is fitted on (see :class:`RecordHasher`).

    Stored as ``Calibration.record`` (the JSON key ``record``), it tells :meth:`Calibration.correct` whether new
    data are that record, where the record-only terms (bias drift, bias step, reference drift, site gradient)
    hold, or another one, where they do not.
    """
    hasher = RecordHasher()
    hasher.update(dataset)
    return hasher.fingerprint()


def same_record(fingerprint, other) -> bool:
    """True when two fingerprints (:func:`record_fingerprint`) describe the same samples."""
    keys = ("n_samples", "readings_sha256")
    return (
        isinstance(fingerprint, dict)
        and isinstance(other, dict)
        and all(fingerprint.get(k) is not None and fingerprint.get(k) == other.get(k) for k in keys)
    )


@dataclass
class SensorCalibration:
    """Calibration of one triaxial sensor.

    Attributes
    ----------
    cinv : numpy.ndarray, shape (3, 3)
        Correction matrix ``C^-1`` (dimensionless), upper triangular in the seed's gauge.
    bias_nT : numpy.ndarray, shape (3,)
        Bias in nT (in a platform-interference model it holds ``C B_hard + b``).
    R : numpy.ndarray, shape (3, 3)
        Rotation taking this sensor's corrected vector into the array frame (identity for the reference sensor).
    summary : dict
        Figures from the fit (e.g. ``rms_before_nT``, ``rms_nT``), written to JSON as they are.
    """

    cinv: np.ndarray
    bias_nT: np.ndarray
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    summary: dict = field(default_factory=dict)

    def __post_init__(self):
        self.cinv = np.asarray(self.cinv, dtype=float).reshape(3, 3)
        self.bias_nT = np.asarray(self.bias_nT, dtype=float).reshape(3)
        self.R = np.asarray(self.R, dtype=float).reshape(3, 3)

    @property
    def determined(self) -> bool:
        """False when the fit marked this sensor's calibration not determined by its record (``summary["determined"]``
        of a vector or gravity fit: the bias's, the mounting's or the heading's standard deviation beyond its limit);
        True otherwise (a total-field fit refuses what it cannot determine instead)."""
        return not (isinstance(self.summary, dict) and self.summary.get("determined") is False)

    def undetermined_why(self) -> str:
        """Why the record did not determine this sensor's calibration, from the standard deviations its fit saved
        (``""`` when :attr:`determined`)."""
        if self.determined:
            return ""
        figures = []
        bias_sd = self.summary.get("bias_sd_nT")
        if bias_sd:
            figures.append(f"the bias's standard deviation is up to {float(np.max(bias_sd)):.0f} nT")
        mount_sd = self.summary.get("mounting_sd_deg")
        if mount_sd:
            figures.append(f"the mounting's {float(np.max(mount_sd)):.2f} deg")
        heading_sd = self.summary.get("heading_sd_deg")
        if heading_sd is not None:
            figures.append(f"the heading's {float(heading_sd):.2f} deg")
        return "the record it was fitted on does not determine it" + (f" ({', '.join(figures)})" if figures else "")


def corrected_fields(dataset, sensors, model=None, effect_values=None, ctxs=None):
    """Corrected field vectors in the array frame, nT, shape (n_sensors, N, 3).

    Parameters
    ----------
    dataset : Dataset
    sensors : list of SensorCalibration
    model : Model, optional
        Candidate effects to undo (base terms are in ``sensors``).
    effect_values : dict of str to numpy.ndarray, optional
        Parameters of each effect instance by :func:`block_label`.
    ctxs : list of Context, optional
        Precomputed :func:`contexts` (the fitter passes them to save work).
    """
    if len(sensors) != dataset.n_sensors:
        raise MagcalError(
            f"the calibration is for {len(sensors)} sensor(s) but the data {dataset.source or ''} have "
            f"{dataset.n_sensors}; use a calibration made for this instrument"
        )
    ctxs = ctxs or contexts(dataset)
    effect_values = effect_values or {}
    instances = list(model.instances()) if model is not None else []
    out = np.empty_like(dataset.readings_nT)
    for s, cal in enumerate(sensors):
        z0 = dataset.readings_nT[s] - cal.bias_nT
        z = z0
        for e, es in instances:
            if e.stage == "raw" and (es == s or (es is None and e.applies_to(s))):
                z = z - basis_times(e.raw_basis(z0, ctxs[s]), effect_values[block_label(e, es)])
        out[s] = z @ (cal.R @ cal.cinv).T
    for s in range(len(sensors)):
        b = out[s].copy()
        for e, es in instances:
            if e.stage == "array" and (es == s or (es is None and e.applies_to(s))):
                out[s] = out[s] + basis_times(e.array_basis(b, ctxs[s]), effect_values[block_label(e, es)])
    return out


def expected_total_field(dataset, reference_total_nT, model=None, effect_values=None, ctxs=None):
    """Expected total field (n_sensors, N) in nT: the reference plus reference-stage effects.

    ``reference_total_nT`` is a number, or ``None`` to use the dataset's per-sample ``ref_total_nT`` column.
    """
    n = dataset.n_samples
    if reference_total_nT is None:
        if dataset.ref_total_nT is None:
            raise MagcalError("no reference field: give one, add a ref_total column, or let it be fitted")
        base = dataset.ref_total_nT
    else:
        base = np.full(n, float(reference_total_nT))
    total = np.tile(base, (dataset.n_sensors, 1))
    if model is not None:
        ctxs = ctxs or contexts(dataset)
        effect_values = effect_values or {}
        for e, es in model.instances():
            if e.stage != "reference":
                continue
            for s in range(dataset.n_sensors):
                if es is None or es == s:
                    total[s] = total[s] + e.reference_basis(ctxs[s]) @ effect_values[block_label(e, es)]
    return total


@dataclass
class Calibration:
    """A fitted calibration of one to four sensors, ready to apply to new data.

    Attributes
    ----------
    sensors : list of SensorCalibration
    reference_total_nT : float or None
        The total field used (given or fitted) in nT; ``None`` when a per-sample reference column was used.
    reference_fitted : bool
        True if the field magnitude was fitted because no reference was given.
    baseline_m : float or None
        Array baseline in m (for the tensor).
    model : Model or None
        The candidate effects included (their data-derived constants travel with them).
    effect_values : dict of str to numpy.ndarray
        Fitted parameters of each effect instance, keyed by :func:`block_label`.
    frame : str
        The array frame: ``"sensor1"`` (the seed's) or ``"platform"`` (after a level-table alignment).
    base_covariance : numpy.ndarray or None
        Covariance of every sensor's ``M = R C^-1`` (row by row) and bias (nT), followed by the effects'
        parameters (in the model's order; 12 n_sensors square for the base model) from the fit
        (:func:`magcal.calibration.uncertainty.base_covariance`), saved with the file; :meth:`uncertainty` carries it to the
        corrected field and the tensor. None without a maximum-likelihood fit.
    mode : str
        ``"scalar"`` (a total-field fit: the corrected vectors are in the array frame, turned by a gauge) or
        ``"vector"`` (a fit with attitude and the field vector, :mod:`magcal.fitting.vector`: each sensor's ``R``
        is its mounting into the vehicle's body frame, and :meth:`world` gives north-east-down components) or
        ``"gravity"`` (a fit beside an accelerometer, :mod:`magcal.fitting.gravity`: each sensor's ``R`` is its
        mounting into the accelerometer's frame, :attr:`accelerometer` the accelerometer's own calibration, and
        :meth:`heading` gives the tilt-compensated heading).
    platform : PlatformTerms or None
        The platform's fields a vector fit found (eddy currents, a field per ampere or per unit of throttle),
        subtracted from the raw readings before the correction.
    accelerometer : AccelerometerCalibration or None
        A gravity calibration's accelerometer correction (``mode == "gravity"``).
    summary : dict
        Figures from the fit (``n_samples``, ``rms_nT``, ``tensor_rms_nT_per_m``, ...), saved with the file.
        Its ``record`` entry (also :attr:`record`) is the fingerprint of the record fitted
        (:func:`record_fingerprint`): record-only terms (:func:`is_transferable` False) act on that record only.
    """

    sensors: list
    reference_total_nT: float | None = None
    reference_fitted: bool = False
    baseline_m: float | None = None
    model: Model | None = None
    effect_values: dict = field(default_factory=dict)
    frame: str = "sensor1"
    summary: dict = field(default_factory=dict)
    base_covariance: np.ndarray | None = None
    mode: str = "scalar"
    platform: PlatformTerms | None = None
    accelerometer: AccelerometerCalibration | None = None

    @property
    def n_sensors(self) -> int:
        return len(self.sensors)

    def check(self, dataset) -> None:
        """Raise a clear error if this calibration cannot be applied to the dataset."""
        where = f" ({dataset.source})" if dataset.source else ""
        if dataset.n_sensors != self.n_sensors:
            raise MagcalError(
                f"the calibration is for {self.n_sensors} sensor(s) but the data{where} have {dataset.n_sensors}; "
                "use a calibration made for this instrument"
            )
        if self.model is not None:
            missing = {c for e in self.model.effects for c in e.missing_channels(dataset)}
            if missing:
                raise MagcalError(
                    f"the calibration includes {', '.join(self.model.effect_labels)}, which need "
                    f"{', '.join(sorted(missing))}; the data{where} lack them"
                )
        if self.platform is not None and self.platform.missing(dataset):
            raise MagcalError(
                f"the calibration holds the platform term(s) {', '.join(self.platform.names)}, which need "
                f"{', '.join(self.platform.missing(dataset))}; the data{where} lack them"
            )

    # --- the record it was fitted on ------------------------------------------------------------------------
    @property
    def record(self) -> dict | None:
        """Fingerprint of the record this calibration was fitted on (:func:`record_fingerprint`), saved in the JSON
        as ``record``; ``{}`` for a file that does not say (made before magcal saved it); ``None`` when never set."""
        return self.summary.get("record") if isinstance(self.summary, dict) else None

    @record.setter
    def record(self, fingerprint) -> None:
        self.summary = dict(self.summary or {})
        self.summary["record"] = None if fingerprint is None else dict(fingerprint)

    def fitted_on(self, dataset) -> Calibration:
        """Record ``dataset`` (the whole record given to the fit, mask or not) as the one fitted; returns self."""
        self.record = record_fingerprint(dataset)
        return self

    def record_terms(self, stages=None) -> list[str]:
        """Labels of the record-only terms (:func:`is_transferable` False) held, optionally of some stages only."""
        if self.model is None:
            return []
        return [e.label for e in self.model.effects if not is_transferable(e) and (stages is None or e.stage in stages)]

    def record_decision(self, dataset=None, record_terms=None, stages=None, fingerprint=None):
        """Whether this calibration's record-only terms act on ``dataset``, and why.

        Parameters
        ----------
        dataset : Dataset, optional
            The data to correct (its fingerprint is computed unless ``fingerprint`` is given).
        record_terms : {None, 'apply', 'drop'}
            ``None`` (default): apply them on the fitted record itself, drop them on any other data (with a
            reason), apply them with a caution when the calibration does not say which record it was fitted on.
            ``'apply'``: the user asserts these data are the fitted record (or has an external reference).
            ``'drop'``: never apply them.
        stages : sequence of str, optional
            Consider only terms of these stages (``CORRECTION_STAGES`` for corrected vectors).
        fingerprint : dict, optional
            The data's fingerprint, when the caller streamed it (:class:`RecordHasher`).

        Returns
        -------
        dropped : list of str
            Labels of the record-only terms to leave out.
        note : str or None
            A message for a :class:`~magcal.core.errors.RecordTermWarning`, or None when nothing needs saying.
        """
        if record_terms is not None and record_terms not in RECORD_TERM_CHOICES:
            raise MagcalError(
                f"record_terms must be 'apply' or 'drop' (or None to decide from the record), got {record_terms!r}"
            )
        labels = self.record_terms(stages)
        if not labels or record_terms == "apply":
            return [], None
        if record_terms == "drop":
            return labels, None
        names = ", ".join(labels)
        record = self.record
        if record is None:  # built in memory and never told its record: the caller holds the fit
            return [], None
        if not record:
            return [], (
                f"the calibration holds the record-only term(s) {names}, which describe the recording they "
                "were fitted on, and it does not say which record that was (it was made before magcal "
                "saved a record fingerprint); they are applied as fitted. If these data are another "
                "record, drop them (record_terms='drop', --record-terms drop) or recalibrate"
            )
        if fingerprint is None:
            fingerprint = record_fingerprint(dataset)
        if same_record(record, fingerprint):
            return [], None
        return labels, (
            f"dropped the record-only term(s) {names}: they describe the recording the calibration was "
            f"fitted on ({_record_text(record)}), not the instrument, and these data are another record "
            f"({_record_text(fingerprint)}): applied, they would put that recording's drift, step or "
            "interference into these data. If they are the same record, or you have a reference for "
            "this one, apply them with "
            "record_terms='apply' (--record-terms apply)"
        )

    def _model_for(self, dataset, record_terms, stages, warn=True):
        """The model (and effect values) to evaluate on ``dataset`` after the record-term decision; its note
        raised as a :class:`~magcal.core.errors.RecordTermWarning` with ``warn`` (the public methods)."""
        model, _, notes = self._acting(dataset, record_terms, stages)
        if warn:
            _notes.warn(notes, stacklevel=3)
        return model

    def _acting(self, dataset, record_terms, stages):
        """``(model, sensors, notes)`` to evaluate on ``dataset`` after the record-term decision: the dropped terms
        left out of the model, the level each keeps for new data folded into the sensors' biases
        (:meth:`sensors_for_new_data`), and the decision's note (:class:`~magcal.core.notes.Note`,
        RecordTermWarning) in a list."""
        dropped, note = self.record_decision(dataset, record_terms, stages)
        notes = [Note(note, RecordTermWarning, "correct")] if note else []
        if not dropped:
            return self.model, self.sensors, notes
        model = self.model
        for label in dropped:
            model = model.without(label)
        return model, self.sensors_for_new_data(dropped), notes

    def sensors_for_new_data(self, dropped=None) -> list:
        """The sensors' base calibrations as kept for new data: each dropped record-only raw-stage term's kept level
        (:meth:`magcal.model.terms.Effect.kept_raw_level`, e.g. the bias after a bias step) folded into the bias.

        Parameters
        ----------
        dropped : sequence of str, optional
            Labels of the terms dropped (default: every record-only term).
        """
        dropped = set(self.record_terms() if dropped is None else dropped)
        if self.model is None or not dropped:
            return self.sensors
        sensors = [replace(c, bias_nT=c.bias_nT.copy()) for c in self.sensors]
        for e, es in self.model.instances():
            if e.label not in dropped or e.stage != "raw":
                continue
            for s, cal in enumerate(sensors):
                if es == s or (es is None and e.applies_to(s)):
                    level = e.kept_raw_level((self.effect_values or {}).get(block_label(e, es)))
                    if level is not None:
                        cal.bias_nT = cal.bias_nT + level
        return sensors

    # --- applying it --------------------------------------------------------------------------------------
    def undetermined(self) -> dict[int, str]:
        """The sensors (0-based) whose calibration the fit marked not determined by its record, and why
        (:meth:`SensorCalibration.undetermined_why`): :meth:`correct` and ``magcal apply`` refuse them unless
        forced."""
        return {s: c.undetermined_why() for s, c in enumerate(self.sensors) if not c.determined}

    def refusal_note(self, force=False) -> Note | None:
        """What applying this calibration does with its undetermined sensors (:meth:`undetermined`), or None when
        every sensor is determined: refused (their corrected values are left out) or, with ``force``, applied
        anyway. A :class:`~magcal.core.errors.DataWarning` note, ``where`` :data:`UNDETERMINED_NOTE`."""
        refused = self.undetermined()
        if not refused:
            return None
        said = "; ".join(f"sensor {s + 1}: {why}" for s, why in refused.items())
        if force:
            text = f"applied although not determined (forced): {said}; do not trust its corrected values"
        else:
            text = (
                f"not applied: {said}. Its corrected values are left out; recalibrate it on a record that determines "
                "it (docs/vector.md), or force it (--force, force=True) knowing they may be far off"
            )
        return Note(text, DataWarning, UNDETERMINED_NOTE)

    @staticmethod
    def _as_dataset(data, t=None, temp=None):
        """``data`` as a :class:`~magcal.data.dataset.Dataset` (what :func:`magcal.calibrate` takes), and whether
        it was one sensor's ``(N, 3)`` array (whose results then drop the sensor axis)."""
        one = isinstance(data, np.ndarray | list | tuple) and np.ndim(data) == 2
        return as_dataset(data, t=t, temp=temp), one

    def correct(self, data, record_terms=None, *, t=None, temp=None, warn=True, force=False) -> np.ndarray:
        """Corrected field vectors (n_sensors, N, 3) in nT, in the array frame.

        Parameters
        ----------
        data : Dataset, array_like or pandas.DataFrame
            What :func:`magcal.calibrate` takes: a dataset, raw readings in nT of shape ``(N, 3)`` (one sensor; the
            result is then ``(N, 3)``) or ``(n_sensors, N, 3)``, or a DataFrame with the data CSV's columns.
        record_terms : {None, 'apply', 'drop'}
            What to do with record-only terms (bias drift, bias step...) on these data; see
            :meth:`record_decision`. By default they act on the fitted record and are dropped, with a
            :class:`~magcal.core.errors.RecordTermWarning` naming them, on any other.
        t : array_like, shape (N,), optional
            Sample times in s, for array input (time-dependent effects need them).
        temp : array_like, shape (N,) or float, optional
            Temperature in degC, for array input (temperature effects need it).
        warn : bool
            Raise what the correction has to say (:meth:`correction_notes`: record-only terms dropped, samples an
            effect cannot correct, sensors refused) as Python warnings, the default (``Calibration`` is a public
            name); the engine's steps pass False and ask :meth:`correction_notes` when they hand the notes on.
        force : bool
            Correct a sensor whose calibration the fit marked not determined by its record (:meth:`undetermined`)
            too. By default such a sensor is refused: its corrected vectors are NaN, and the note
            (:meth:`refusal_note`) names it and says why. The engine's own steps that judge a fit on its record
            pass True.

        Examples
        --------
        >>> import magcal
        >>> ds = magcal.simulate("chi2017", seed=2)
        >>> cal = magcal.calibrate(ds.readings_nT[0], reference_total_nT=50_000).calibration
        >>> cal.correct(ds.readings_nT[0]).shape        # one sensor's (N, 3) readings in, (N, 3) out
        (200, 3)
        """
        dataset, one = self._as_dataset(data, t, temp)
        self.check(dataset)
        model, sensors, notes = self._acting(dataset, record_terms, CORRECTION_STAGES)
        refusal = self.refusal_note(force)
        if warn:
            _notes.warn(notes + self._gap_notes(model, dataset) + ([refusal] if refusal else []))
        dataset = self._without_platform(dataset)
        vectors = corrected_fields(dataset, sensors, model, self.effect_values, contexts(dataset, self.baseline_m))
        if not force:
            for s in self.undetermined():
                vectors[s] = np.nan
        return vectors[0] if one else vectors

    def correction_notes(self, dataset, record_terms=None, force=False) -> list:
        """What :meth:`correct` has to say of ``dataset`` (:class:`~magcal.core.notes.Note` list, never raised): the
        record-only terms dropped or applied unproven (RecordTermWarning), and the samples an effect that needs
        each sample's attitude cannot correct (DataWarning, ``where`` :data:`ATTITUDE_GAP_NOTE`), the sensors refused
        or forced (:meth:`refusal_note`)."""
        model, _, notes = self._acting(dataset, record_terms, CORRECTION_STAGES)
        refusal = self.refusal_note(force)
        return notes + self._gap_notes(model, dataset) + ([refusal] if refusal else [])

    @staticmethod
    def _gap_notes(model, dataset) -> list:
        """The note on the samples of ``dataset`` that ``model``'s effects needing an attitude cannot correct."""
        missing = None if model is None else rows_without_attitude(model, dataset)
        if missing is not None and missing.any():  # the term has no value there: NaN, said once
            labels = ", ".join(attitude_effects(model))
            return [
                Note(
                    f"{int(missing.sum())} of {missing.size} samples have no attitude ({row_runs(missing)}): {labels} "
                    "cannot be applied to them and their corrected vectors are NaN; drop the term "
                    "(record_terms='drop', --record-terms drop) to correct every sample with the base terms",
                    DataWarning,
                    ATTITUDE_GAP_NOTE,
                )
            ]
        return []

    def attitude_terms(self, record_terms=None, dataset=None) -> list[str]:
        """Labels of the effects acting under ``record_terms`` (:meth:`record_decision` on ``dataset``) that need
        each sample's attitude (``site_gradient``): a sample without one gets NaN corrected vectors."""
        if self.model is None:
            return []
        dropped, _ = self.record_decision(dataset, record_terms, CORRECTION_STAGES)
        return [label for label in attitude_effects(self.model) if label not in set(dropped)]

    def _without_platform(self, dataset):
        """The dataset with the platform terms' field taken out of the readings (unchanged without any)."""
        if self.platform is None or not self.platform.names:
            return dataset
        return dataset.replace(readings_nT=dataset.readings_nT - self.platform.offsets_nT(dataset))

    def world(self, data, corrected=None, record_terms=None, *, t=None, temp=None, force=False) -> np.ndarray:
        """Corrected field vectors in the world (north-east-down) frame, (n_sensors, N, 3) in nT.

        Needs a vector calibration (``mode == "vector"``: body-frame vectors) and the data's attitude
        (quaternions or ``roll_deg, pitch_deg, yaw_deg``, body -> NED): ``B_ned = R(q) B_body`` (``data``,
        ``record_terms``, ``t``, ``temp``, ``force`` as in :meth:`correct`). A sample without attitude (NaN angles:
        :func:`magcal.data.attitude.attitude_rows`) gets NaN world components; its body-frame vector
        (:meth:`correct`) is still known.
        """
        dataset, _ = self._as_dataset(data, t, temp)
        if self.mode != "vector":
            raise MagcalError(
                "world components need a vector calibration (magcal calibrate --mode vector, with attitude and a "
                "reference field vector): a total-field calibration leaves the sensor's rotation unknown"
            )
        found = attitude_rows(dataset)
        if found is None:
            raise MagcalError(
                f"the data {dataset.source or ''} have no attitude (qw, qx, qy, qz or roll_deg, pitch_deg, yaw_deg): "
                "world components need it"
            )
        rotation, have = found
        body = self.correct(dataset, record_terms, force=force) if corrected is None else corrected
        world = np.stack([rotation.apply(b) for b in body])
        world[:, ~have] = np.nan
        return world

    def total_field(self, data, record_terms=None, *, t=None, temp=None) -> np.ndarray:
        """Corrected total field (n_sensors, N) in nT, or (N,) for one sensor's ``(N, 3)`` array (``data``,
        ``record_terms``, ``t``, ``temp`` as in :meth:`correct`)."""
        return row_norm(self.correct(data, record_terms, t=t, temp=temp))

    def expected_total_field(self, data, record_terms=None, *, t=None, temp=None) -> np.ndarray:
        """The total field (n_sensors, N) in nT this calibration expects on ``data``: its reference (the
        dataset's ``ref_total`` column when it has none) plus its reference-stage effects (``record_terms`` as in
        :meth:`correct`: a reference drift of the fitted record is dropped on another)."""
        dataset, _ = self._as_dataset(data, t, temp)
        model = self._model_for(dataset, record_terms, ("reference",))
        return expected_total_field(
            dataset, self.reference_total_nT, model, self.effect_values, contexts(dataset, self.baseline_m)
        )

    def total_field_residuals(self, data, corrected=None, record_terms=None, *, t=None, temp=None) -> np.ndarray:
        """Total-field residuals ``|B| - F`` (n_sensors, N) in nT; ``corrected`` reuses :meth:`correct`'s output
        (``data``, ``record_terms``, ``t``, ``temp`` as in :meth:`correct`; one warning names every term dropped)."""
        dataset, _ = self._as_dataset(data, t, temp)
        if corrected is not None and np.ndim(corrected) == 2:
            corrected = np.asarray(corrected)[None]
        model, sensors, notes = self._acting(dataset, record_terms, None)
        _notes.warn(notes, stacklevel=2)
        ctxs = contexts(dataset, self.baseline_m)
        if corrected is None:
            self.check(dataset)
            corrected = corrected_fields(self._without_platform(dataset), sensors, model, self.effect_values, ctxs)
        expected = expected_total_field(dataset, self.reference_total_nT, model, self.effect_values, ctxs)
        return row_norm(corrected) - expected

    def uncertainty(self, data, corrected=None, record_terms=None, *, t=None, temp=None) -> dict | None:
        """The calibration's standard deviations carried to each sample's corrected field and tensor
        (:func:`magcal.calibration.uncertainty.field_uncertainty`; ``data``, ``record_terms``, ``t``, ``temp`` as in
        :meth:`correct`), or None without a :attr:`base_covariance`."""
        dataset, _ = self._as_dataset(data, t, temp)
        return field_uncertainty(self, dataset, corrected, record_terms)

    def tensor_frame(self) -> np.ndarray:
        """Rotation (3, 3) from the cross's own frame (the frame of eq. 1, in which sensor 1 sits at +x, 2 at +y, 3 at
        -x, 4 at -y) into this calibration's frame: the identity for a total-field calibration (its frame is
        sensor 1's), sensor 1's mounting ``R`` for a vector calibration (its frame is the vehicle's body; the cross
        is taken to lie along sensor 1's axes, as in the seed's convention)."""
        return self.sensors[0].R if self.mode in MOUNTED_MODES else np.eye(3)

    def tensor(self, data, corrected=None, record_terms=None, *, t=None, temp=None) -> dict:
        """Gradient tensor components (eq. 1) in nT/m from corrected vectors, in the cross's own frame
        (:meth:`tensor_frame`); needs four sensors and a baseline (``data``, ``record_terms``, ``t``, ``temp`` as in
        :meth:`correct`)."""
        if self.n_sensors != 4 or not self.baseline_m:
            raise MagcalError("the gradient tensor needs four sensors and a baseline (baseline_m)")
        vectors = self.correct(data, record_terms, t=t, temp=temp) if corrected is None else corrected
        if self.mode in MOUNTED_MODES:
            vectors = np.asarray(vectors) @ self.tensor_frame()  # body -> the cross's frame: v_cross = A^T v
        return conventions.tensor_components(vectors, self.baseline_m)

    def world_tensor(self, dataset, corrected=None, record_terms=None) -> np.ndarray:
        """The gradient tensor in the world (north-east-down) frame, (N, 3, 3) nT/m: ``G_world = R A G A^T R^T`` with
        ``G`` the cross-frame tensor (:meth:`tensor`), ``A`` the cross's frame in the body (:meth:`tensor_frame`)
        and ``R`` the attitude (four sensors, a vector calibration and attitude); NaN for a sample without
        attitude."""
        found = attitude_rows(dataset)
        if found is None or self.mode != "vector":
            raise MagcalError("the tensor in world coordinates needs a vector calibration and the data's attitude")
        rotation, have = found
        g = conventions.tensor_matrix(self.tensor(dataset, corrected, record_terms))
        r = rotation.as_matrix() @ self.tensor_frame()
        world = np.einsum("nij,njk,nlk->nil", r, g, r)
        world[~have] = np.nan
        return world

    def heading(self, dataset, corrected=None, record_terms=None, accel_units=None, force=False) -> dict:
        """The tilt-compensated compass of a gravity calibration: per sample, from the corrected field (in the
        accelerometer's frame) and the corrected accelerometer (:mod:`magcal.geometry.heading`).

        Parameters
        ----------
        dataset : Dataset
            With accelerometer columns (:mod:`magcal.data.accelerometer`).
        corrected : numpy.ndarray, shape (n_sensors, N, 3), optional
            :meth:`correct`'s vectors, when already computed.
        record_terms, accel_units, force
            As in :meth:`correct`; the unit of unmarked ``ax, ay, az`` columns; as in :meth:`correct`.

        Returns
        -------
        dict
            ``heading_deg`` (n_sensors, N): the magnetic heading of the board's x axis, [0, 360); ``dip_deg``
            (n_sensors, N): the field's angle below the horizontal; ``tilt_deg`` (N,): the board's tilt. NaN on a
            row without an accelerometer sample.
        """
        if self.mode != "gravity" or self.accelerometer is None:
            raise MagcalError(
                "a heading needs a gravity calibration (magcal calibrate --mode gravity, with accelerometer columns): "
                "it holds the magnetometer's rotation into the accelerometer's frame"
            )
        accel = accelerometer(dataset, units=accel_units)
        if accel is None:
            raise MagcalError(
                f"the data {dataset.source or ''} have no accelerometer columns (ax, ay, az): a heading needs them"
            )
        vectors = self.correct(dataset, record_terms, warn=False, force=force) if corrected is None else corrected
        f = self.accelerometer.correct(accel.m_s2)
        return {
            "heading_deg": np.stack([tilt_heading_deg(f, v) for v in vectors]),
            "dip_deg": np.stack([dip_deg(f, v) for v in vectors]),
            "tilt_deg": tilt_deg(f),
        }

    # --- JSON -----------------------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        """The versioned JSON document (``format``, ``version``, per-sensor ``Cinv``, ``bias_nT``, ``R``...)."""
        sensors = []
        for i, cal in enumerate(self.sensors):
            scale, angles = conventions.gauge_free(cal.cinv)
            entry = {
                "id": i + 1,
                "Cinv": cal.cinv.tolist(),
                "bias_nT": cal.bias_nT.tolist(),
                "R": cal.R.tolist(),
                "scale": scale.tolist(),
                "axis_angles_deg": angles.tolist(),
            }
            entry.update(jsonable(cal.summary))
            sensors.append(entry)
        effects = []
        if self.model is not None:
            for e, s in self.model.instances():
                label = block_label(e, s)
                values = np.asarray(self.effect_values.get(label, np.zeros(len(e.param_names()))), dtype=float)
                effects.append(
                    {
                        "effect": e.name,
                        "sensor": None if s is None else s + 1,
                        "term": e.label,
                        "params": dict(zip(e.param_names(), values.tolist())),
                        "state": jsonable(e.state()),
                        "transferable": is_transferable(e),  # False: record-only, applied only to the fitted record
                    }
                )
                if not is_transferable(e) and getattr(e, "kept_for_new_data", None):
                    effects[-1]["kept_for_new_data"] = e.kept_for_new_data  # what apply keeps when it drops it
        doc = {
            "format": FORMAT,
            "version": VERSION,
            "reference_total_nT": self.reference_total_nT,
            "reference_fitted": self.reference_fitted,
            "baseline_m": self.baseline_m,
            "frame": self.frame,
            "base_terms": list(self.model.base) if self.model is not None else None,
            "effects": self.model.effect_labels if self.model is not None else [],
            "effect_params": effects,
            "sensors": sensors,
        }
        if self.mode != "scalar":
            doc["mode"] = self.mode
        if self.platform is not None and self.platform.names:
            doc["platform_terms"] = self.platform.to_dict()
        if self.accelerometer is not None:
            doc["accelerometer"] = self.accelerometer.to_dict()
        if self.base_covariance is not None:
            doc["base_covariance"] = {
                "order": "per sensor: M = R Cinv row by row (9), then bias_nT (3); then each effect's parameters, "
                "in the order of 'effects'",
                "matrix": np.asarray(self.base_covariance, float).tolist(),
            }
        doc.update(jsonable(self.summary))
        doc["record"] = jsonable(self.record)  # null: never told which record it was fitted on
        return doc

    @classmethod
    def from_dict(cls, doc: dict, source: str = "calibration", n_sensors=None) -> Calibration:
        """Rebuild a calibration from :meth:`to_dict` output, refusing anything else with one clear message.

        Parameters
        ----------
        doc : dict
            The JSON document.
        source : str
            Where it came from (a file name), for the messages.
        n_sensors : int, optional
            Refuse a calibration made for a different number of sensors.

        Raises
        ------
        MagcalError
            Wrong format or version, wrong sensor count, a damaged sensor entry (shapes, finite values, a singular
            ``Cinv``, an ``R`` that is not a proper rotation), a damaged effect entry or a bad baseline.
        """
        if not isinstance(doc, dict) or doc.get("format") != FORMAT:
            raise MagcalError(f'{source}: not a magcal calibration file (expected "format": "{FORMAT}")')
        if doc.get("version") != VERSION:
            raise MagcalError(
                f"{source}: calibration file version {doc.get('version')!r} is not supported by this magcal "
                f"(it reads version {VERSION}); upgrade magcal or recalibrate"
            )
        entries = doc.get("sensors")
        if not isinstance(entries, list) or not 1 <= len(entries) <= 4:
            raise MagcalError(f"{source}: 'sensors' must list 1 to 4 sensors; the file is damaged, recalibrate")
        if n_sensors is not None and len(entries) != int(n_sensors):
            raise MagcalError(
                f"{source}: this calibration is for {len(entries)} sensor(s) but the data have {n_sensors}; use the "
                "calibration made for this instrument"
            )
        _check_parameter_bounds(doc, source)  # first: a huge value overflows the entries' own checks
        for i, entry in enumerate(entries):
            _check_sensor_entry(source, i, entry)
        _check_document_types(doc, source)
        baseline = doc.get("baseline_m")
        if baseline is not None:
            try:
                within = 1.0 / MAX_PARAMETER <= float(baseline) <= MAX_PARAMETER
            except (TypeError, ValueError, OverflowError):
                within = False
            if not within:
                raise MagcalError(
                    f"{source}: baseline_m {str(baseline)[:40]!r} must be a positive number of metres, from "
                    f"{1.0 / MAX_PARAMETER:g} to {MAX_PARAMETER:g}; the file is damaged, recalibrate"
                )
        derived = {"id", "Cinv", "bias_nT", "R", "scale", "axis_angles_deg"}  # recomputed by to_dict
        sensors = [
            SensorCalibration(
                np.array(s["Cinv"], float),
                np.array(s["bias_nT"], float),
                np.array(s.get("R", np.eye(3)), float),
                summary={k: v for k, v in s.items() if k not in derived},
            )
            for s in entries
        ]
        try:
            model, values = _effects_from_dict(doc, len(sensors), source)
        except MagcalError:
            raise
        except Exception as exc:  # a damaged effect entry: any failure of the rebuild is the file's fault
            raise MagcalError(f"{source}: damaged effect entry ({exception_text(exc)}); recalibrate") from None
        known = {
            "format",
            "version",
            "reference_total_nT",
            "reference_fitted",
            "baseline_m",
            "frame",
            "base_terms",
            "effects",
            "effect_params",
            "sensors",
            "base_covariance",
            "mode",
            "platform_terms",
            "accelerometer",
        }
        mode = doc.get("mode", "scalar")
        if mode not in MODES:
            raise MagcalError(f"{source}: 'mode' must be one of {', '.join(MODES)}, got {mode!r}; the file is damaged")
        accel = None
        if doc.get("accelerometer") is not None:
            accel = AccelerometerCalibration.from_dict(doc["accelerometer"], source)
        if mode == "gravity" and accel is None:
            raise MagcalError(f"{source}: a gravity calibration needs its 'accelerometer' entry; recalibrate")
        platform = None
        if doc.get("platform_terms") is not None:
            platform = PlatformTerms.from_dict(doc["platform_terms"], len(sensors), source)
        cov = None
        if doc.get("base_covariance") is not None:
            size = 12 * len(sensors)
            joint = covariance_size(len(sensors), model)  # with the effects' parameters (files made since)
            try:
                cov = np.array(doc["base_covariance"]["matrix"], float)
                ok = (
                    cov.ndim == 2
                    and cov.shape[0] == cov.shape[1]
                    and cov.shape[0] in (size, joint)
                    and np.all(np.isfinite(cov))
                )
            except (TypeError, ValueError, KeyError):
                ok = False
            if not ok:
                shapes = f"{size} x {size}" + (f" or {joint} x {joint}" if joint != size else "")
                raise MagcalError(
                    f"{source}: 'base_covariance' must hold a {shapes} matrix of numbers; the "
                    "file is damaged, recalibrate"
                )
        summary = {k: v for k, v in doc.items() if k not in known}
        record = summary.get("record")
        if record is not None and not (isinstance(record, dict) and _fingerprint_ok(record)):
            raise MagcalError(
                f"{source}: 'record' must be the fingerprint of the fitted record (n_samples, "
                "time_start_s, time_end_s, readings_sha256); the file is damaged, recalibrate"
            )
        if "record" not in doc and model is not None and any(not is_transferable(e) for e in model.effects):
            summary["record"] = {}  # made before magcal saved the record: which one it was is unknown
        return cls(
            sensors=sensors,
            reference_total_nT=doc.get("reference_total_nT"),
            reference_fitted=bool(doc.get("reference_fitted", False)),
            baseline_m=baseline,
            model=model,
            effect_values=values,
            frame=doc.get("frame", "sensor1"),
            summary=summary,
            base_covariance=cov,
            mode=mode,
            platform=platform,
            accelerometer=accel,
        )

    def save(self, path) -> None:
        """Write the JSON file atomically (a temporary file renamed over the target)."""
        write_json_atomic(path, self.to_dict())

    @classmethod
    def load(cls, path, n_sensors=None) -> Calibration:
        """Read a calibration file written by :meth:`save`, with one clear :class:`MagcalError` for any problem.

        Parameters
        ----------
        path : str or os.PathLike
        n_sensors : int, optional
            Refuse a calibration made for a different number of sensors.
        """
        path = os.fspath(path)
        reason = not_regular_reason(path)
        if reason is not None and reason != "no such file" and not reason.startswith("cannot"):
            raise MagcalError(f"{path}: is {reason}; give the calibration file (JSON) itself")
        try:
            with open(path, "rb") as fh:
                raw = fh.read(MAX_CALIBRATION_BYTES + 1)
        except FileNotFoundError:
            raise MagcalError(f"{path}: no such calibration file; check the path") from None
        except IsADirectoryError:
            raise MagcalError(f"{path}: is a directory, not a calibration file") from None
        except OSError as exc:
            raise MagcalError(f"{path}: cannot read the calibration file ({exc.strerror or exc})") from None
        if len(raw) > MAX_CALIBRATION_BYTES:
            raise MagcalError(
                f"{path}: more than {MAX_CALIBRATION_BYTES >> 20} MB, far larger than any calibration file; give "
                "the file written by magcal calibrate or magcal align"
            )
        try:
            doc = json.loads(raw.decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
            raise MagcalError(
                f"{path}: not a JSON calibration file ({exception_text(exc)}); give the file "
                "written by magcal calibrate or magcal align"
            ) from None
        return cls.from_dict(doc, source=path, n_sensors=n_sensors)


def _record_text(fingerprint) -> str:
    """``1200 samples, t = 0-119.9 s`` for a fingerprint."""
    n = fingerprint.get("n_samples")
    t0, t1 = fingerprint.get("time_start_s"), fingerprint.get("time_end_s")
    span = f", t = {t0:g}-{t1:g} s" if isinstance(t0, (int, float)) and isinstance(t1, (int, float)) else ""
    return f"{n} samples{span}"


#: The keys of a calibration document whose type is checked, and what each must be (None is allowed for all).
_DOCUMENT_TYPES = {
    "effects": "a list of effect names",
    "effect_params": "a list of objects (one per effect block)",
    "base_terms": "a list of term names",
    "reference_total_nT": f"a number of nT from {USABLE_TOTAL_nT[0]:g} to {USABLE_TOTAL_nT[1]:g}",
    "reference_fitted": "true or false",
    "frame": "a text",
}


def _check_document_types(doc, source) -> None:
    """Refuse a document whose keys have the wrong type (``effect_params`` a number...), naming the key."""

    def ok(key, value):
        if value is None:
            return True
        if key in ("effects", "base_terms"):
            return isinstance(value, list) and all(isinstance(v, str) for v in value)
        if key == "effect_params":
            return isinstance(value, list) and all(
                isinstance(e, dict)
                and isinstance(e.get("effect", e.get("term")), str)
                and isinstance(e.get("term", ""), str)
                and isinstance(e.get("params"), dict)
                and isinstance(e.get("state") or {}, dict)
                and (e.get("sensor") is None or (isinstance(e["sensor"], int) and not isinstance(e["sensor"], bool)))
                for e in value
            )
        if key == "reference_total_nT":
            return (  # NaN and infinities fail the range; an integer beyond any float compares too
                isinstance(value, (int, float))
                and not isinstance(value, bool)
                and USABLE_TOTAL_nT[0] <= value <= USABLE_TOTAL_nT[1]
            )
        if key == "reference_fitted":
            return isinstance(value, bool)
        if key == "frame":
            return isinstance(value, str)
        return True

    for key, want in _DOCUMENT_TYPES.items():
        value = doc.get(key)
        if not ok(key, value):
            raise MagcalError(
                f"{source}: {key!r} must be {want}, not {str(value)[:40]!r}; the file is damaged, recalibrate"
            )


def _numbers(value, path=()):
    """Every number in a JSON value (nested lists and objects), with its key path: ``(path, number)``."""
    if isinstance(value, bool):
        return
    if isinstance(value, (int, float)):
        yield path, value
    elif isinstance(value, dict):
        for k, v in value.items():
            yield from _numbers(v, (*path, str(k)))
    elif isinstance(value, list):
        for k, v in enumerate(value):
            yield from _numbers(v, (*path, k))


def _number_text(number) -> str:
    """A number of a document as a message shows it: ``1e+308``; an integer beyond any float by its digits."""
    try:
        return f"{float(number):.6g}"
    except OverflowError:
        return f"an integer of {len(str(abs(number))):,} digits"


def _path_text(path) -> str:
    """``sensors[0].Cinv[1][1]`` for a key path: the document's own keys and (0-based) list positions."""
    out = ""
    for k in path:
        if not isinstance(k, int) and not (k.isprintable() and len(k) <= 40):
            k = repr(k[:40])  # a key of a damaged file: quoted, line ends escaped
        out += f"[{k}]" if isinstance(k, int) else (f".{k}" if out else k)
    return out[:120]


def _check_parameter_bounds(doc, source, then="the file is damaged or was edited; recalibrate") -> None:
    """Refuse a document holding a parameter beyond :data:`MAX_PARAMETER` (a covariance entry beyond
    :data:`MAX_COVARIANCE`): every number that correcting, the uncertainty or an export computes with. Finite but
    huge values (``C^-1 = 1e308 I``) overflow to infinities there, written out with exit status 0. (NaN and
    infinities are refused by each part's own check, naming them.)"""
    sensors = doc.get("sensors") if isinstance(doc.get("sensors"), list) else []
    parts: list[tuple[tuple, object]] = [
        (("sensors", i, key), e.get(key))
        for i, e in enumerate(sensors)
        if isinstance(e, dict)
        for key in ("Cinv", "bias_nT", "R")
    ]
    effects = doc.get("effect_params") if isinstance(doc.get("effect_params"), list) else []
    for k, entry in enumerate(effects):
        if isinstance(entry, dict):  # another type: the document's type check names it
            parts += [(("effect_params", k, key), entry.get(key)) for key in ("params", "state")]
    if isinstance(doc.get("platform_terms"), dict):
        parts += [
            (("platform_terms", key), doc["platform_terms"].get(key)) for key in ("eddy_ms", "current_nT_per_unit")
        ]
    covariance = doc.get("base_covariance")
    limits = [(parts, MAX_PARAMETER)]
    if isinstance(covariance, dict):
        limits.append(([(("base_covariance", "matrix"), covariance.get("matrix"))], MAX_COVARIANCE))
    for found, limit in limits:
        for head, value in found:
            for path, number in _numbers(value, head):
                try:  # NaN and infinities are left to the checks of each part, which name them
                    beyond = bool(np.isfinite(float(number))) and abs(float(number)) > limit
                except OverflowError:  # an integer too large for a float
                    beyond = True
                if beyond:
                    raise MagcalError(
                        f"{source}: {_path_text(path)} = {_number_text(number)} is beyond +-{limit:g}, no "
                        "calibration's "
                        f"value (it would correct readings to infinities): {then}"
                    )


def _check_sensor_entry(source, i, s) -> None:
    """Refuse a damaged sensor entry of a calibration document, naming the sensor and the key."""
    where = f"{source}: sensor {i + 1}"
    if not isinstance(s, dict):
        raise MagcalError(f"{where}: entry is not an object; the file is damaged, recalibrate")
    for key, shape in (("Cinv", (3, 3)), ("bias_nT", (3,)), ("R", (3, 3))):
        if key not in s:
            if key == "R":
                continue
            raise MagcalError(f"{where}: missing {key}; the file is damaged, recalibrate")
        try:
            a = np.array(s[key], dtype=float)
        except (TypeError, ValueError, OverflowError):  # OverflowError: an integer beyond any float
            raise MagcalError(f"{where}: {key} is not numeric; the file is damaged, recalibrate") from None
        if a.shape != shape or not np.all(np.isfinite(a)):
            raise MagcalError(f"{where}: {key} must be {shape} finite numbers; the file is damaged, recalibrate")
        if key == "Cinv" and abs(np.linalg.det(a)) < 1e-9:
            raise MagcalError(f"{where}: Cinv is singular; the file is damaged, recalibrate")
        if key == "R" and (not np.allclose(a @ a.T, np.eye(3), atol=1e-6) or np.linalg.det(a) < 0):
            raise MagcalError(f"{where}: R is not a proper rotation; the file is damaged, recalibrate")


def _fingerprint_ok(record) -> bool:
    """True for ``{}`` (record unknown) or a fingerprint with a sample count and a hash."""
    if not record:
        return True
    n = record.get("n_samples")
    return isinstance(n, int) and not isinstance(n, bool) and n >= 0 and isinstance(record.get("readings_sha256"), str)


def _effects_from_dict(doc, n_sensors, source="calibration"):
    """The model and effect values saved in a calibration document (None, {} when it has none).

    An effect name that is not in the catalogue is refused with :func:`magcal.model.terms.unknown_effect_message`
    (it may be a user's effect whose file was not loaded).
    """
    model, values = None, {}
    if doc.get("effect_params") or doc.get("base_terms"):
        model = Model(n_sensors, base=tuple(doc.get("base_terms") or BASE_TERMS))
        seen = {}
        for entry in doc.get("effect_params", []):
            term = entry.get("term", entry["effect"])
            name = str(term).partition(":")[0].strip()
            if name not in EFFECTS and name not in BASE_TERMS:
                raise MagcalError(unknown_effect_message(name, where=source))
            if term not in seen:
                effect = parse_effect(term, n_sensors)
                effect.set_state(entry.get("state") or {})
                seen[term] = effect
                model.effects.append(effect)
            effect = seen[term]
            sensor = entry.get("sensor")
            if effect.per_sensor and sensor is not None and not 1 <= sensor <= n_sensors:
                raise MagcalError(
                    f"{source}: effect {term}: sensor {sensor}, but the calibration has {n_sensors} sensor(s); the "
                    "file is damaged, recalibrate"
                )
            label = block_label(effect, None if sensor is None or not effect.per_sensor else sensor - 1)
            # a non-physical value (a negative hysteresis width...) is refused with the file and parameter named
            values[label] = effect.check_params(_saved_params(effect, entry["params"], source, term), source)
        missing = [block_label(e, s) for e, s in model.instances() if block_label(e, s) not in values]
        if missing:  # every block the model applies needs its parameters (a KeyError when correcting, otherwise)
            raise MagcalError(
                f"{source}: no parameters for the effect block(s) {', '.join(missing)}; the file is damaged, recalibrate"
            )
    return model, values


def _saved_params(effect, params: dict, source, term) -> list:
    """An effect's saved parameters in :meth:`~magcal.model.terms.Effect.param_names` order; a file saved under
    the effect's former names (``former_param_names``, e.g. ``k_x_nT_per_unit`` of a current in amperes) is read
    too."""
    former: list = getattr(effect, "former_param_names", lambda: [])()
    for names in (effect.param_names(), former):
        if names and all(n in params for n in names):
            return [params[n] for n in names]
    raise MagcalError(
        f"{source}: effect {term}: its parameters should be named {', '.join(effect.param_names())}, the file has "
        f"{', '.join(map(str, params)) or 'none'}; the file is damaged, recalibrate"
    )


def document_text(document, what="calibration") -> str:
    """A calibration's ``document`` (:meth:`Calibration.to_dict`) as indented JSON text (with a final line end),
    refusing what magcal would not read back: a parameter beyond :data:`MAX_PARAMETER`, or a value that is not a
    finite number (JSON has none: Python would write ``NaN`` or ``Infinity``, which no JSON reader takes).

    Raises
    ------
    MagcalError
    """
    if isinstance(document.get("sensors"), list):
        _check_parameter_bounds(document, f"the {what}", "it is not written; recalibrate")
    try:
        return json.dumps(document, indent=2, allow_nan=False) + "\n"
    except ValueError:
        where = next((_path_text(p) for p, v in _numbers(document) if not np.isfinite(v)), "a value")
        raise MagcalError(
            f"the {what} holds {where} that is not a finite number; it is not written (recalibrate)"
        ) from None


def write_json_atomic(path, document) -> None:
    """Write ``document`` as indented JSON to ``path`` atomically (:func:`magcal.data.io.atomic_write`); a value
    that is not a finite number is refused before anything is written (:func:`document_text`)."""
    text = document_text(document)
    with atomic_write(path, "w", newline=None) as fh:
        fh.write(text)


def current_term(calibration):
    """The field per unit of current (or throttle) a calibration holds, wherever it holds it.

    Parameters
    ----------
    calibration : Calibration
        Its ``platform.current_nT_per_unit`` (a vector fit's platform terms) and/or the catalogue effect
        ``current_field`` in its model (values ``effect_values["current_field:S"]``, column the effect's
        ``column``).

    Returns
    -------
    k : numpy.ndarray, shape (n_sensors, 3), or None
        ``k`` per sensor and axis, nT per unit of the column, in the sensor's own axes (``y += k u``); zero rows
        for sensors without the term. None when no sensor has one.
    columns : list of str or None
        Per sensor the column the term follows (``current_A`` or ``throttle``), None where there is none.

    Raises
    ------
    MagcalError
        A term whose column is not recorded or not a known one, values that are not 3 finite numbers, or one sensor
        holding two terms that follow different columns.
    """
    n = calibration.n_sensors
    k = np.zeros((n, 3))
    columns: list[str | None] = [None] * n

    def add(sensor, values, column, where):
        if column not in CURRENT_COLUMNS:
            raise MagcalError(
                f"{where}: the column of sensor {sensor + 1}'s current term is {column!r}, not one of "
                f"{', '.join(CURRENT_COLUMNS)}; the calibration is damaged: recalibrate"
            )
        try:
            v = np.asarray(values, dtype=float).reshape(3)
        except (TypeError, ValueError):
            v = np.full(3, np.nan)
        if not np.all(np.isfinite(v)):
            raise MagcalError(f"{where}: sensor {sensor + 1}'s current term is not 3 finite numbers: recalibrate")
        if columns[sensor] not in (None, column):
            raise MagcalError(
                f"sensor {sensor + 1} holds a field per unit of {columns[sensor]} and another per unit of {column}; "
                "no firmware holds two: recalibrate with one of them"
            )
        k[sensor] += v
        columns[sensor] = column

    platform = getattr(calibration, "platform", None)
    values = getattr(platform, "current_nT_per_unit", None)
    if values is not None:
        rows = np.asarray(values, dtype=float)
        if rows.shape != (n, 3):
            raise MagcalError(f"platform_terms.current_nT_per_unit must be ({n}, 3); the calibration is damaged")
        for s in range(n):
            add(s, rows[s], platform.current_column, "platform_terms")
    model = getattr(calibration, "model", None)
    if model is not None:
        for effect, s in model.instances():
            if effect.name != "current_field":
                continue
            label = block_label(effect, s)
            theta = (calibration.effect_values or {}).get(label)
            if theta is None:
                raise MagcalError(f"{label}: the calibration holds the effect but not its values: recalibrate")
            for sensor in range(n) if s is None else (s,):
                add(sensor, theta, getattr(effect, "column", None), label)
    return (k if any(c is not None for c in columns) else None), columns
