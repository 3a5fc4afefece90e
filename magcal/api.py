"""The one-call API: read, calibrate and diagnose whatever the user holds.

``magcal.calibrate`` and ``magcal.diagnose`` take a :class:`~magcal.data.dataset.Dataset`, a plain array of raw readings
in nT (``(N, 3)`` for one sensor, ``(n_sensors, N, 3)`` for an array) or a pandas DataFrame with the columns of
the data CSV, turn it into a dataset with :func:`magcal.data.inputs.as_dataset`, and call the engine's
:func:`magcal.fitting.pipeline.calibrate` and :func:`magcal.diagnosis.diagnose`, which keep taking datasets only.
"""

from __future__ import annotations

from magcal.checks.reference import resolve_vector_reference
from magcal.core import notes as _notes
from magcal.core.errors import MagcalError
from magcal.data.attitude import attitude_source
from magcal.data.inputs import as_dataset
from magcal.data.io import read_csv
from magcal.diagnosis import Diagnosis
from magcal.diagnosis import diagnose as _diagnose
from magcal.diagnosis.vector import Flight, VectorDiagnosis, diagnose_vector
from magcal.fitting import pipeline
from magcal.fitting.validation import validate_effects
from magcal.fitting.vector import VectorFitResult

__all__ = ["read_csv", "calibrate", "diagnose", "as_dataset"]


def calibrate(
    data,
    method: str = "ml",
    effects=(),
    robust: bool = False,
    reference_total_nT=None,
    *,
    t=None,
    temp=None,
    noise_nT=None,
    validate: bool = False,
    warn: bool = True,
    **options,
):
    """Calibrate one to four sensors from readings taken while turning them in a uniform field.

    Parameters
    ----------
    data : Dataset, array_like or pandas.DataFrame
        Raw readings in nT: a :class:`~magcal.data.dataset.Dataset`, an array of shape ``(N, 3)`` (one sensor) or
        ``(n_sensors, N, 3)``, or a DataFrame with the data CSV's columns (see :func:`magcal.data.inputs.as_dataset`).
    method : {"ml", "ellipsoid", "pso", "ipso", "de"}
        ``ml`` (default): ellipsoid -> Procrustes -> maximum likelihood; ``ellipsoid``: the seed's two steps only.
    effects : sequence of str or Effect
        Effects to add to the base model, by name (``"temperature_bias"``, ``"bias_drift:2"``, sensors 1-based),
        e.g. those a :func:`diagnose` names in ``explained_by``.
    robust : bool
        Soft-L1 loss in the maximum-likelihood step; gross outliers reported in ``outliers``.
    reference_total_nT : float, optional
        Known total field in nT; otherwise the data's ``ref_total`` column or metadata, else fitted.
    t : array_like, shape (N,), optional
        Sample times in s, for array input (time-dependent effects need them).
    temp : array_like, shape (N,) or float, optional
        Temperature in degC, for array input (temperature effects need it).
    noise_nT : float, optional
        Noise per axis in nT, if known: used for the floors instead of the data's ``noise_nT`` or any estimate
        (``result.noise_source`` then reads ``given``).
    validate : bool
        Also fit the base model and the model with ``effects`` on alternating blocks in time and score them on
        the blocks between (:func:`magcal.fitting.validation.validate_effects`): ``result.validation`` holds the
        held-out RMS beside the in-sample one (method ``ml`` only).
    warn : bool
        Raise the result's ``notes`` (weak coverage, a fit that did not converge) as Python warnings
        (:class:`~magcal.core.errors.CoverageWarning`, :class:`~magcal.core.errors.ConvergenceWarning`...), the
        default; False leaves them in ``result.notes`` only (for a program that shows them itself, or calls this
        from threads: :mod:`warnings` filters are process-wide).
    **options
        Passed on to :func:`magcal.fitting.pipeline.calibrate` (``seed``, ``progress``, ``mask``, ``ellipsoid_method``,
        ``base_terms``).

    Returns
    -------
    CalibrationResult
        ``.calibration`` applies to new data (``.correct(new)``, ``.save(path)``); ``.rms_after_per_sensor_nT``
        the total-field RMS per sensor in nT. Without ``mask=`` the calibration knows the record it was fitted on,
        so its record-only terms (bias drift, step...) act on that record only: on other data ``.correct``
        drops them with a warning.

    Raises
    ------
    DatasetError
        (a ``ValueError``) for input of the wrong shape or with NaN values.
    CalibrationError
        Too few samples, degenerate coverage, unknown method or effect.

    Examples
    --------
    >>> import numpy as np, magcal
    >>> readings = magcal.simulate("chi2017", seed=1).readings_nT[0]     # (200, 3) nT, one sensor
    >>> result = magcal.calibrate(readings, reference_total_nT=50000)
    >>> result.calibration.n_sensors, bool(result.rms_after_per_sensor_nT[0] < 4.0)   # noise sigma is 3 nT
    (1, True)
    """

    dataset = as_dataset(data, reference_total_nT=reference_total_nT, t=t, temp=temp)
    result = pipeline.calibrate(
        dataset,
        method=method,
        effects=effects,
        robust=robust,
        reference_total_nT=reference_total_nT,
        noise_nT=noise_nT,
        **options,
    )
    if validate:
        result.validation = validate_effects(dataset, result)
        result.notes = _notes.unique(result.notes + result.validation.notes)
    if options.get("mask") is None:
        result.calibration.fitted_on(dataset)  # record-only terms act on this record only
    if warn:
        _notes.warn(result.notes)
    return result


def diagnose(data, result=None, *, reference_total_nT=None, t=None, temp=None, warn: bool = True, **options):
    """Where the calibration model fails on the data, and which physical effect is missing.

    Parameters
    ----------
    data : Dataset, array_like or pandas.DataFrame
        Raw readings as for :func:`calibrate` (the same record the ``result`` was fitted on).
    result : CalibrationResult, FitResult or VectorFitResult, optional
        The fitted model to diagnose; without it the base model (plus ``effects=``) is fitted first. A vector fit's
        result (:func:`magcal.fitting.vector.fit_vector`) is diagnosed in vector mode.
    reference_total_nT : float, optional
        Known total field in nT (when ``result`` is not given).
    t : array_like, shape (N,), optional
        Sample times in s, for array input; the tests against time need them.
    temp : array_like, shape (N,) or float, optional
        Temperature in degC, for array input; the tests against temperature need it.
    warn : bool
        Raise the diagnosis's ``notes`` (what its own fits said: weak coverage of the fit made when ``result``
        is not given, a refit that did not converge) as Python warnings, the default; False leaves them in
        ``.notes`` only.
    **options
        Passed on to :func:`magcal.diagnosis.diagnose` (``effects``, ``model``, ``top``, ``candidates``,
        ``max_effects``, ``progress``, ``validate``: judge the candidates on held-out samples, default True;
        ``noise_nT``: the noise per axis in nT, if known, used instead of any estimate; ``workers``: cores for the
        independent fits, default every one; ``scheduler``: a Dask scheduler's address or client to run them on).
        Vector mode (a record with the attitude and the field vector, :func:`magcal.diagnosis.vector.diagnose_vector`):
        ``mode`` (``"auto"``: vector when the record has both and no total-field result is given; ``"scalar"``;
        ``"vector"``), ``reference`` (the field vector: ``[N, E, D]`` nT, a VectorReference, ``"igrf"`` along
        the ``lat, lon, alt_m`` columns, or ``"fitted"``: a lab's constant field fitted with the calibration,
        :mod:`magcal.fitting.labfield`; default the ``ref_n, ref_e, ref_d`` columns), ``also`` (other flights of
        the same vehicle: datasets with those columns, ``(data, reference)`` pairs or Flights), ``attitude_noise_deg``.

    Returns
    -------
    Diagnosis
        ``.verdict`` (``adequate``, ``missing_effect`` or ``unexplained``; in vector mode also ``not_judged``: no
        held-out judgement could be made, nothing advised), ``.summary``, ``.candidates`` best
        first (each with its held-out RMS and ``holds``), ``.explained_by`` (effect labels to pass to
        :func:`calibrate` as ``effects=``: only effects whose gain holds on held-out data).

    Examples
    --------
    >>> import magcal
    >>> ds = magcal.simulate("chi2017", seed=1)          # the base model is all there is to find
    >>> magcal.diagnose(ds, magcal.calibrate(ds)).verdict
    'adequate'
    """

    dataset = as_dataset(data, reference_total_nT=reference_total_nT, t=t, temp=temp)
    mode = options.pop("mode", "auto")
    reference = options.pop("reference", None)
    also = options.pop("also", ())
    vector = _vector_mode(dataset, result, mode, reference)
    diagnosis: Diagnosis | VectorDiagnosis
    if vector is not None:
        flights = [_flight(f, i) for i, f in enumerate(also or (), 1)]
        vector_options = {k: v for k, v in options.items() if k in _VECTOR_OPTIONS}
        diagnosis = diagnose_vector(dataset, vector, result=result, also=flights, **vector_options)
    else:
        if also:
            raise MagcalError(
                "also=: other flights judge a vector calibration; these data are diagnosed in scalar mode"
            )
        diagnosis = _diagnose(dataset, result, **options)
    if warn:
        _notes.warn(diagnosis.notes)
    return diagnosis


#: The options of :func:`magcal.diagnosis.vector.diagnose_vector` that :func:`diagnose` passes on in vector mode.
_VECTOR_OPTIONS = (
    "effects",
    "candidates",
    "max_effects",
    "attitude_noise_deg",
    "noise_nT",
    "reference_total_nT",
    "robust",
    "validate",
    "top",
    "progress",
)


def _vector_mode(dataset, result, mode, reference):
    """The field vector to diagnose a vector calibration against, or None for the scalar diagnosis: a vector fit's
    result, ``mode="vector"``, or (``"auto"``, no result given) a record with the attitude and a field vector."""
    if mode not in ("auto", "scalar", "vector"):
        raise MagcalError(f"mode must be 'auto', 'scalar' or 'vector', got {mode!r}")
    if isinstance(result, VectorFitResult):
        if mode == "scalar":
            raise MagcalError("mode='scalar' with a vector fit's result: give a total-field calibration's result")
        return result.reference
    if mode == "scalar" or result is not None:
        if mode == "vector":
            raise MagcalError("mode='vector' takes a vector fit's result (magcal.fitting.vector.fit_vector) or none")
        return None
    if attitude_source(dataset) is None:
        if mode == "vector":
            raise MagcalError("mode='vector' needs the attitude: qw..qz or roll_deg, pitch_deg, yaw_deg")
        return None
    if reference is None or isinstance(reference, str):
        found = resolve_vector_reference(dataset, reference=reference)
    elif hasattr(reference, "ned_nT"):
        found = reference
    else:
        found = resolve_vector_reference(dataset, vector=reference)
    if found is None and mode == "vector":
        raise MagcalError(
            "mode='vector' needs the field vector: ref_n, ref_e, ref_d columns, reference=[N, E, D] (nT) or "
            "reference='igrf' with lat, lon, alt_m columns"
        )
    return found


def _flight(item, number):
    """An ``also=`` entry as a :class:`~magcal.diagnosis.vector.Flight`: a Flight, a ``(data, reference)`` pair, or
    data whose ``ref_n, ref_e, ref_d`` columns give its field vector."""
    if isinstance(item, Flight):
        return item
    data, reference = item if isinstance(item, tuple) else (item, None)
    ds = as_dataset(data)
    ref = reference if reference is not None else resolve_vector_reference(ds)
    if ref is None:
        raise MagcalError(f"also[{number - 1}]: no field vector (ref_n, ref_e, ref_d columns); give (data, reference)")
    return Flight(ds, ref, ds.source or f"flight {number + 1}")
