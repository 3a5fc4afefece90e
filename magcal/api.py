"""The one-call API: read, calibrate and diagnose whatever the user holds.

``magcal.calibrate`` and ``magcal.diagnose`` take a :class:`~magcal.data.dataset.Dataset`, a plain array of raw readings
in nT (``(N, 3)`` for one sensor, ``(n_sensors, N, 3)`` for an array) or a pandas DataFrame with the columns of
the data CSV, turn it into a dataset with :func:`magcal.data.inputs.as_dataset`, choose the fit mode as ``magcal
calibrate`` does (:func:`magcal.modes.base.choose_mode`: the vector fit for a record with the attitude and the field
vector, the gravity fit beside an accelerometer, else the total-field fit) and call that mode's
:meth:`~magcal.modes.base.FitMode.fit` or :meth:`~magcal.modes.base.FitMode.diagnose`, which keep taking datasets only.
"""

from __future__ import annotations

from magcal.core import notes as _notes
from magcal.core.errors import MagcalError
from magcal.data.inputs import as_dataset
from magcal.data.io import read_csv
from magcal.fitting.pipeline import CalibrationResult
from magcal.fitting.result import ModeResult
from magcal.modes import FitMode, fit_mode, mode_choice

__all__ = ["read_csv", "calibrate", "diagnose", "as_dataset"]


def calibrate(
    data,
    method: str = "ml",
    effects=(),
    robust: bool = False,
    reference_total_nT=None,
    *,
    mode: str = "auto",
    t=None,
    temp=None,
    noise_nT=None,
    validate: bool = False,
    warn: bool = True,
    **options,
) -> ModeResult:
    """Calibrate one to four sensors from what the record holds: readings turned in a uniform field, and the
    attitude with the field vector or an accelerometer beside them when it has them.

    Parameters
    ----------
    data : Dataset, array_like or pandas.DataFrame
        Raw readings in nT: a :class:`~magcal.data.dataset.Dataset`, an array of shape ``(N, 3)`` (one sensor) or
        ``(n_sensors, N, 3)``, or a DataFrame with the data CSV's columns (see :func:`magcal.data.inputs.as_dataset`).
    method : {"ml", "ellipsoid", "pso", "ipso", "de"}
        The total-field fit's method: ``ml`` (default): ellipsoid -> Procrustes -> maximum likelihood; ``ellipsoid``:
        the seed's two steps only.
    effects : sequence of str or Effect
        Effects to add to the base model, by name (``"temperature_bias"``, ``"bias_drift:2"``, sensors 1-based),
        e.g. those a :func:`diagnose` names in ``explained_by``.
    robust : bool
        Soft-L1 loss; gross outliers do not pull the fit (reported in the total-field fit's ``outliers``).
    reference_total_nT : float, optional
        Known total field in nT; otherwise the data's ``ref_total`` column or metadata, else fitted.
    mode : str
        The fit mode (:mod:`magcal.modes`, ``magcal calibrate --mode``): ``"auto"`` (default) chooses as the command
        line does (:func:`magcal.modes.base.choose_mode`: ``"vector"`` when some rows have an attitude and the field
        vector is known, ``"gravity"`` beside an accelerometer without attitude, else ``"total_field"``); or a
        registered mode's name (``"scalar"`` is ``"total_field"``). A mode the record cannot have is refused with
        what it needs.
    t : array_like, shape (N,), optional
        Sample times in s, for array input (time-dependent effects need them).
    temp : array_like, shape (N,) or float, optional
        Temperature in degC, for array input (temperature effects need it).
    noise_nT : float, optional
        Noise per axis in nT, if known: used for the floors instead of the data's ``noise_nT`` or any estimate
        (the total-field fit's ``noise_source`` then reads ``given``).
    validate : bool
        Also judge the fit on held-out samples (:meth:`magcal.modes.base.FitMode.validate`; for the total-field fit the
        base model and the model with ``effects`` fitted on alternating blocks in time and scored on the blocks
        between, :func:`magcal.fitting.validation.validate_effects`, method ``ml`` only): ``result.validation``.
    warn : bool
        Raise the result's ``notes`` (weak coverage, a fit that did not converge) and what the choice of the mode
        said as Python warnings (:class:`~magcal.core.errors.CoverageWarning`,
        :class:`~magcal.core.errors.ConvergenceWarning`...), the default; False leaves them in ``result.notes`` only
        (for a program that shows them itself, or calls this from threads: :mod:`warnings` filters are
        process-wide).
    **options
        Passed on to the mode's fit. Total-field (:func:`magcal.fitting.pipeline.calibrate`): ``seed``,
        ``progress``, ``mask``, ``ellipsoid_method``, ``base_terms``. Vector (:func:`magcal.fitting.vector.fit_vector`):
        ``reference`` (the field vector: ``[N, E, D]`` nT, a VectorReference, ``"igrf"`` along the ``lat, lon,
        alt_m`` columns, or ``"fitted"``: a lab's constant field; default the ``ref_n, ref_e, ref_d`` columns),
        ``attitude_noise_deg``, ``field_gradient``, ``mask``. Gravity (:func:`magcal.fitting.gravity.fit_gravity`):
        ``inclination_deg``, ``accel_fit``, ``accel_units``, ``mask``. An option the mode does not take is refused,
        naming those it takes.

    Returns
    -------
    ModeResult
        The mode's result (:class:`~magcal.fitting.result.ModeResult`: ``.mode``, ``.calibration``, ``.notes``,
        ``.text()``, ``.to_dict()``): a :class:`~magcal.fitting.pipeline.CalibrationResult` for the total-field fit
        (``.rms_after_per_sensor_nT``: the total-field RMS per sensor in nT), a
        :class:`~magcal.fitting.vector.VectorFitResult` or a :class:`~magcal.fitting.gravity.GravityFitResult`.
        ``.calibration`` applies to new data (``.correct(new)``, ``.save(path)``). Without ``mask=`` the calibration
        knows the record it was fitted on, so its record-only terms (bias drift, step...) act on that record only:
        on other data ``.correct`` drops them with a warning.

    Raises
    ------
    DatasetError
        (a ``ValueError``) for input of the wrong shape or with NaN values.
    CalibrationError
        Too few samples, degenerate coverage, unknown method or effect.
    MagcalError
        An unknown mode (naming the known ones), a mode the record cannot have (saying what it needs), an option
        the mode does not take.

    Examples
    --------
    >>> import numpy as np, magcal
    >>> readings = magcal.simulate("chi2017", seed=1).readings_nT[0]     # (200, 3) nT, one sensor
    >>> result = magcal.calibrate(readings, reference_total_nT=50000)
    >>> result.mode, result.calibration.n_sensors, bool(result.rms_after_per_sensor_nT[0] < 4.0)   # noise 3 nT
    ('total_field', 1, True)
    """

    dataset = as_dataset(data, reference_total_nT=reference_total_nT, t=t, temp=temp)
    given = {
        "method": (method, "ml"),
        "effects": (effects, ()),
        "robust": (robust, False),
        "reference_total_nT": (reference_total_nT, None),
        "noise_nT": (noise_nT, None),
    }
    chosen, said = mode_choice(dataset, mode, **options)
    fit_options = _mode_options(chosen, given, options)
    result = chosen.fit(dataset, **fit_options)
    if validate:
        result.validation = chosen.validate(dataset, result, **fit_options)
        if isinstance(result, CalibrationResult) and result.validation is not None:
            result.notes = _notes.unique(result.notes + result.validation.notes)
    if warn:
        _notes.warn(said + list(result.notes))
    return result


def _mode_options(mode: FitMode, given: dict, options: dict, method: str = "fit") -> dict:
    """The keyword arguments for ``mode``'s ``method``: ``options``, and each of ``given`` (``name -> (value,
    default)``) that the mode takes or that was given other than its default (which :meth:`~magcal.modes.base.FitMode.taken` then
    refuses, naming what the mode takes)."""
    known = mode.accepts(method)
    passed = dict(options)
    for name, (value, default) in given.items():
        if known is None or name in known or not _unset(value, default):
            passed[name] = value
    return mode.taken(passed, method)


def _unset(value, default) -> bool:
    """Whether an argument of :func:`calibrate` was left at its default (``()``: any empty sequence or None)."""
    if default is None:
        return value is None
    if default == ():
        return value is None or (hasattr(value, "__len__") and len(value) == 0)
    return isinstance(value, type(default)) and value == default


def diagnose(
    data,
    result=None,
    *,
    mode: str = "auto",
    reference_total_nT=None,
    t=None,
    temp=None,
    warn: bool = True,
    **options,
):
    """Where the calibration model fails on the data, and which physical effect is missing.

    Parameters
    ----------
    data : Dataset, array_like or pandas.DataFrame
        Raw readings as for :func:`calibrate` (the same record the ``result`` was fitted on).
    result : ModeResult or FitResult, optional
        The fitted model to diagnose (:func:`calibrate`'s result); it is diagnosed in its own mode (a vector fit's
        on the world components). Without it the mode is chosen as :func:`calibrate` chooses it and the base model
        (plus ``effects=``) is fitted first.
    mode : str
        ``"auto"`` (default), or a registered mode's name (``"scalar"`` is ``"total_field"``), as for
        :func:`calibrate`; with a ``result`` of another mode it is refused.
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
        Passed on to the mode's diagnosis (:meth:`magcal.modes.base.FitMode.diagnose`). Total-field and gravity
        (:func:`magcal.diagnosis.diagnose`): ``effects``, ``model``, ``top``, ``candidates``, ``max_effects``,
        ``progress``, ``validate`` (judge the candidates on held-out samples, default True), ``noise_nT`` (the noise
        per axis in nT, if known, used instead of any estimate), ``workers`` (cores for the independent fits,
        default every one), ``scheduler`` (a Dask scheduler's address or client to run them on); the gravity
        diagnosis adds the dip's evidence (``dip_evidence``). Vector
        (:func:`magcal.diagnosis.vector.diagnose_vector`): ``reference`` (the field vector, as for
        :func:`calibrate`), ``also`` (other flights of the same vehicle: datasets with ``ref_n, ref_e, ref_d``
        columns, ``(data, reference)`` pairs or Flights), ``effects``, ``candidates``, ``max_effects``,
        ``attitude_noise_deg``, ``noise_nT``, ``robust``, ``validate``, ``top``, ``progress``.

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
    if result is None:
        chosen, said = mode_choice(dataset, mode, **options)
    else:
        chosen, said = _result_mode(result, mode), []
    known = chosen.accepts("diagnose")
    if known is not None and "reference" not in known:
        options.pop("reference", None)  # the field vector: only a vector diagnosis uses it
    diagnosis = chosen.diagnose(dataset, result, **chosen.taken(options, "diagnose"))
    if warn:
        _notes.warn(said + list(diagnosis.notes))
    return diagnosis


def _result_mode(result, mode: str) -> FitMode:
    """The mode a fit's ``result`` is diagnosed in: its own (a result that is not a :class:`~magcal.fitting.result.ModeResult`, such as
    :func:`magcal.fit`'s, is a total-field fit's); ``mode`` other than ``"auto"`` must name it."""
    own = fit_mode(getattr(result, "mode", "") if isinstance(result, ModeResult) else "total_field")
    if mode != "auto" and fit_mode(mode) is not own:
        raise MagcalError(
            f"mode={mode!r} with a {own.label}'s result (mode {own.name!r}): give a result of mode "
            f"{fit_mode(mode).name!r}, or no result"
        )
    return own
