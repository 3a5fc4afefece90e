"""The calibration model: a list of named effect terms.

A model always holds the *base* terms (``bias``, ``scale``, ``non_orthogonality`` and, for arrays,
``misalignment``) unless the user removes them, plus any number of *candidate* effects from the catalogue
(:data:`EFFECTS`, filled by :mod:`magcal.model.effects`).

How a term acts is fixed by its ``stage`` (see ``docs/architecture.md``). For sensor ``s`` with raw reading ``y``::

    z0  = y - b                                    base: bias
    z   = z0 - sum raw_basis(z0, ctx) @ theta      stage "raw"        (sensor frame, nT)
    B   = R C^-1 z                                 base: scale, non_orthogonality, misalignment
    B  += sum array_basis(B, ctx) @ theta          stage "array"      (array frame, nT)
    F   = F0 + sum reference_basis(ctx) @ theta    stage "reference"  (nT)

Every candidate term is linear in its parameters; the basis it returns is its Jacobian with respect to them
(the fitter treats the basis's own dependence on ``z0``/``B`` as second order). Parameters are expressed in units
chosen so that a parameter of size ``param_scale`` changes the readings by about 1 nT, which keeps the fit
well conditioned.
"""

from __future__ import annotations

import copy
import dataclasses
import inspect
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from scipy.spatial.transform import Rotation

from magcal.core import conventions
from magcal.core.errors import MagcalError
from magcal.core.notes import row_runs
from magcal.data.attitude import filled_wxyz

#: Names of the base terms, in order.
BASE_TERMS = ("bias", "scale", "non_orthogonality", "misalignment")

#: The catalogue of candidate effects by name. :mod:`magcal.model.effects` registers the built-in terms when
#: ``magcal`` is imported; :func:`register` adds more (a user's own effect).
EFFECTS: dict[str, type[Effect]] = {}


class EffectTexts(Mapping):
    """A read-only view of one text every registered effect says of itself (:data:`EFFECTS`), by name: what the
    diagnosis's tables read (``EffectTexts("signature")``), kept on the effect so that a new effect is one class.
    Effects that leave the text empty are not in it."""

    def __init__(self, attribute: str):
        self.attribute = attribute

    def _texts(self) -> dict:
        return {name: text for name, cls in EFFECTS.items() if (text := getattr(cls, self.attribute, ""))}

    def __getitem__(self, name):
        return self._texts()[name]

    def __iter__(self):
        return iter(self._texts())

    def __len__(self):
        return len(self._texts())


def register(cls=None, *, replace: bool = False):
    """Class decorator: add an :class:`Effect` subclass to :data:`EFFECTS` under ``cls.name``.

    Used as ``@register`` or ``@register(replace=True)``. A name already in the catalogue is refused unless
    ``replace`` is true: a built-in effect, or another module's, is never replaced by accident. Registering the
    same class again changes nothing. Every effect, built-in or a user's, is held to the same checks by
    :func:`magcal.model.plugins.validate_effect` (files and entry points when they load; the catalogue in the
    test suite).

    Parameters
    ----------
    cls : type
        An :class:`Effect` subclass with a ``name``.
    replace : bool
        Replace an effect already registered under that name.

    Raises
    ------
    MagcalError
        For a class that is not an Effect subclass, has no name, or whose name is taken (without ``replace``).
    """
    if cls is None:
        return lambda c: register(c, replace=replace)
    if not (isinstance(cls, type) and issubclass(cls, Effect)) or cls is Effect:
        raise MagcalError(f"register: {cls!r} is not a subclass of magcal.model.Effect; derive your effect from it")
    name = getattr(cls, "name", None)
    if not isinstance(name, str) or not name:
        raise MagcalError(f'register: effect class {cls.__name__} has no name; set name = "my_effect"')
    current = EFFECTS.get(name)
    if current is not None and current is not cls and not replace:
        raise MagcalError(
            f"register: effect name {name!r} is {_owner(current)}; give {cls.__name__} another name "
            f'(e.g. "my_{name}"), or register it with replace=True to replace the registered one'
        )
    EFFECTS[name] = cls
    return cls


def _owner(cls) -> str:
    """Who holds a registered effect class, for messages: a built-in, a file, or a module."""
    module = getattr(cls, "__module__", "") or ""
    if module == "magcal" or module.startswith("magcal."):
        return f"already a built-in effect ({module}.{cls.__qualname__})"
    try:
        path = inspect.getsourcefile(cls)
    except TypeError:
        path = None
    if path and module.startswith("_magcal_user_effects_"):  # loaded from a file by magcal.model.plugins
        return f"already taken by the effect from file {path}"
    return f"already taken by {module}.{cls.__qualname__}"


def term_label(name: str, sensor: int | None) -> str:
    """The label of an effect term: ``name`` for every sensor (or a shared term), ``name:S`` for one sensor.

    ``sensor`` counts from 0, as everywhere in the Python API (:attr:`Effect.sensor`,
    :attr:`magcal.diagnosis.Candidate.sensor`); the label shows it from 1, as the command line, the JSON and the
    workbench do.
    """
    return name if sensor is None else f"{name}:{sensor + 1}"


@dataclass
class Context:
    """What an effect's basis may look at for one sensor.

    Attributes
    ----------
    dataset : Dataset
        The (kept-samples) dataset being fitted or corrected.
    sensor : int
        0-based sensor index.
    position_m : numpy.ndarray, shape (3,)
        The sensor's position in the array frame (m), from :func:`magcal.core.conventions.sensor_positions`.
    attitude : scipy.spatial.transform.Rotation or None
        Array-to-world attitudes, when the dataset has them; the identity on a sample without one (see
        ``attitude_present``).
    attitude_present : numpy.ndarray of bool, shape (N,), or None
        True where the sample has an attitude (None when ``attitude`` is None). A basis that needs the attitude
        has no value where it is False: it returns NaN there (:class:`magcal.model.effects.SiteGradient`), and the
        fitter leaves such samples out (:func:`rows_without_attitude`).
    """

    dataset: Any  # the Dataset (magcal.data.dataset)
    sensor: int
    position_m: np.ndarray
    attitude: Rotation | None = None
    attitude_present: np.ndarray | None = None

    @property
    def time_s(self):
        return self.dataset.time_s

    @property
    def temperature_C(self):
        return self.dataset.temperature_C

    @property
    def reading_nT(self):
        return self.dataset.readings_nT[self.sensor]


class SingleAxisBasis(np.ndarray):
    """An effect's basis (N, 3, q) in which parameter ``k`` moves axis ``axes[k]`` only, as most raw-stage terms
    have (a temperature bias, a drift, a step, a nonlinearity: one parameter per axis).

    It is the dense array, usable as any basis, that also keeps its non-zero entries: ``axes`` (q,) and
    ``axis_values`` (q, N), parameter ``k`` moving axis ``axes[k]`` by ``axis_values[k]`` per unit. The fitter
    projects such a basis on a direction per sample with q products instead of a contraction over the whole
    array (8x). Views and results of arithmetic are plain bases (``axes`` None).

    Parameters
    ----------
    columns : numpy.ndarray, shape (N, q)
        ``axis_values`` transposed: column ``k`` is parameter ``k``'s effect on its axis.
    axes : sequence of int, shape (q,)
        The axis (0, 1, 2) each parameter moves.

    Examples
    --------
    >>> b = SingleAxisBasis(np.array([[1.0, 2.0, 3.0]]), [0, 1, 2])
    >>> b[0]
    SingleAxisBasis([[1., 0., 0.],
                     [0., 2., 0.],
                     [0., 0., 3.]])
    >>> b.axes.tolist(), b.axis_values.ravel().tolist()
    ([0, 1, 2], [1.0, 2.0, 3.0])
    """

    def __new__(cls, columns, axes):
        columns = np.asarray(columns, dtype=float)
        axes = np.asarray(axes, dtype=int)
        n, q = columns.shape
        dense = np.zeros((n, 3, q))
        dense[:, axes, np.arange(q)] = columns
        out = dense.view(cls)
        out.axes, out.axis_values = axes, np.ascontiguousarray(columns.T)
        return out

    def __array_finalize__(self, obj):
        self.axes = self.axis_values = None

    def __deepcopy__(self, memo):
        """A copy that keeps ``axes`` and ``axis_values`` (numpy's own copy would drop them)."""
        if self.axes is None:
            return np.array(self)
        return SingleAxisBasis(self.axis_values.T, self.axes)


def span_text(lower: float, upper: float) -> str:
    """``">= 0"``, ``"<= 5"``, ``"in [-250, 250]"`` or ``"any number"``: one parameter's bounds in words."""
    if np.isinf(lower) and np.isinf(upper):
        return "any number"
    if np.isinf(upper):
        return f">= {lower:g}"
    if np.isinf(lower):
        return f"<= {upper:g}"
    return f"in [{lower:g}, {upper:g}]"


#: A fitted parameter within this fraction of its :meth:`Effect.param_scale` (the size that moves the readings by
#: about 1 nT) of a bound sits on it (:func:`outside_domain`): the fit was held there.
ON_BOUND_FRACTION = 1e-3

#: A parameter held on a bound is not physical here when the data pull it past the bound by more than this many of
#: its standard deviations (:func:`bound_pulls`); an effect absent on one axis sits on a bound too, pulled past it by
#: noise alone (within about 1 standard deviation, on half the records).
BOUND_PULL_Z = 3.0


@dataclass(frozen=True)
class Domain:
    """The physical domain of an effect's parameters: a lower and an upper bound per parameter (in the
    parameters' units; ``-inf``/``inf`` where physics sets none) and why, in words.

    Attributes
    ----------
    lower, upper : numpy.ndarray, shape (q,)
        Bounds of each parameter, in :meth:`Effect.param_names` order and units.
    why : str
        The physics that sets them, for messages and ``docs/effects.md`` ("a loop half-width: the output lags the
        field, it cannot lead it"); empty for an unbounded domain.
    """

    lower: np.ndarray
    upper: np.ndarray
    why: str = ""

    def __post_init__(self):
        lower = np.asarray(self.lower, dtype=float).reshape(-1)
        upper = np.broadcast_to(np.asarray(self.upper, dtype=float), lower.shape).copy()
        if np.any(lower > upper):
            raise MagcalError(f"a domain's lower bounds {lower.tolist()} exceed its upper bounds {upper.tolist()}")
        object.__setattr__(self, "lower", lower)
        object.__setattr__(self, "upper", upper)

    @classmethod
    def free(cls, q: int) -> Domain:
        """``q`` unbounded parameters."""
        return cls(np.full(q, -np.inf), np.full(q, np.inf))

    @classmethod
    def symmetric(cls, q: int, limit: float, why: str) -> Domain:
        """``q`` parameters each within ``[-limit, limit]``."""
        return cls(np.full(q, -float(limit)), np.full(q, float(limit)), why)

    @property
    def bounded(self) -> bool:
        """True when some parameter has a finite bound."""
        return bool(np.any(np.isfinite(self.lower)) or np.any(np.isfinite(self.upper)))

    def text(self, names) -> str:
        """The domain in words, one ``name span`` per parameter, equal spans gathered: ``"h_x_nT, h_y_nT, h_z_nT
        >= 0"``."""
        groups: dict = {}
        for name, lo, hi in zip(names, self.lower, self.upper):
            groups.setdefault(span_text(lo, hi), []).append(name)
        return "; ".join(f"{', '.join(n)} {span}" for span, n in groups.items())


def outside_domain(effect: Effect, values, label: str | None = None, pull_z=None) -> str:
    """Why one instance's fitted ``values`` are not physical here, or ``""``: the parameters that sit on (or
    past) a bound of the effect's :meth:`~Effect.domain` (within :data:`ON_BOUND_FRACTION` of their
    :meth:`~Effect.param_scale`) because the data pull them out of the domain (by more than :data:`BOUND_PULL_Z`
    standard deviations, when ``pull_z`` says). A candidate effect so fitted describes something else the record
    holds (the diagnoses never recommend it).

    Parameters
    ----------
    effect : Effect
        The effect (its data-derived constants set: the domain may depend on them).
    values : array_like, shape (q,)
        Its fitted parameters, in :meth:`~Effect.param_names` order.
    label : str, optional
        The block's label (``name:S``) the text names; default the effect's.
    pull_z : array_like, shape (q,), optional
        How far the data pull each parameter past the bound it sits on, in its standard deviations (:func:`bound_pulls`;
        NaN where unknown). Without it every parameter on a bound counts.
    """
    v = np.asarray(values, dtype=float).reshape(-1)
    pulls = np.full(v.shape, np.nan) if pull_z is None else np.broadcast_to(np.asarray(pull_z, dtype=float), v.shape)
    names = effect.param_names()
    lower, upper = (np.broadcast_to(np.asarray(b, dtype=float), v.shape) for b in effect.param_bounds())
    if not (np.any(np.isfinite(lower)) or np.any(np.isfinite(upper))) or v.size != len(names):
        return ""
    tol = ON_BOUND_FRACTION * np.abs(np.broadcast_to(np.asarray(effect.param_scale(), dtype=float), v.shape))
    held: dict = {}  # (where, span) -> [(name, pull)] held there
    for name, value, lo, hi, t, z in zip(names, v, lower, upper, tol, pulls):
        if not np.isfinite(value):
            held.setdefault(("is not a finite number", ""), []).append((name, np.nan))
        elif (value <= lo + t or value >= hi - t) and not z < BOUND_PULL_Z:
            bound = lo if value <= lo + t else hi
            held.setdefault((f"held at the bound {bound:g}", span_text(lo, hi)), []).append((name, z))
    if not held:
        return ""
    parts = []
    for (where, span), found in held.items():
        z = [p for _, p in found if np.isfinite(p)]
        said = [f"pulled {', '.join(f'{p:.0f}' for p in z)} standard deviations past it"] if z else []
        said += [f"the domain is {span}"] if span else []
        parts.append(f"{', '.join(n for n, _ in found)} {where}" + (f" ({'; '.join(said)})" if said else ""))
    why = effect.domain().why
    return f"{label or effect.label}: " + "; ".join(parts) + (f": {why}" if why else "")


@dataclass
class Effect:
    """A named candidate term of the model.

    Subclasses set the class attributes and implement the basis of their stage, :meth:`param_names`, and
    :meth:`perturbation` (how the simulator hides this effect in data). ``sensor`` restricts a per-sensor term
    to one sensor (0-based); ``None`` applies it to every sensor, each with its own parameters.

    Attributes
    ----------
    name : str
        Catalogue name, used identically by the API, the CLI, JSON and the workbench.
    stage : {'raw', 'array', 'reference'}
        Where the term acts (see the module docstring).
    channels : tuple of str
        Dataset channels required (keys of :data:`magcal.data.dataset.CHANNELS`).
    per_sensor : bool
        True if each sensor has its own parameters; False for one set shared by the array.
    min_sensors : int
        Fewest sensors the term makes sense for (2 for inter-sensor effects).
    description : str
        One line for tables and the workbench.
    transferable : bool
        True (the default) when the term describes the *instrument* and carries to new data: a temperature
        coefficient, a nonlinearity, a timing skew, hysteresis are properties of the sensor, and a calibration
        that includes them corrects later recordings too. False when the term describes *one recording*: a bias
        drift since power-on, a bias step at one moment, the reference field's drift during the record, the
        gradient of the calibration site. Such a term is fitted so that it does not bias the instrument terms,
        but cannot be carried to another record without an external reference (a new step time, the field's
        variation during that record...).
    """

    name: ClassVar[str] = ""
    stage: ClassVar[str] = "raw"
    channels: ClassVar[tuple] = ()
    per_sensor: ClassVar[bool] = True
    min_sensors: ClassVar[int] = 1
    description: ClassVar[str] = ""
    transferable: ClassVar[bool] = True
    #: A record-only term: what the calibration keeps for new data when the term, fitted with the base terms, is
    #: dropped (the level its parametrisation refers the base terms to), in words; saved with a calibration.
    kept_for_new_data: ClassVar[str | None] = None
    #: The basis depends on the readings or the field (``z0``, ``B``), not only on channels such as time and
    #: temperature. The fitter leaves that dependence out of its Jacobian, so only a model whose effects all
    #: declare False has an exact one (:attr:`magcal.fitting.fitter.Problem.exact_jacobian`). Plug-ins keep the safe True.
    basis_uses_readings: ClassVar[bool] = True
    #: The fits that can judge the term: ``"scalar"`` (the total-field fit of a turned instrument) and
    #: ``"vector"`` (the fit with attitude and the field vector, :mod:`magcal.fitting.vector`). A term the total
    #: field cannot see (a delay common to a sensor's three axes, a full eddy-current matrix) declares
    #: ``("vector",)``: the scalar diagnosis never proposes it and the scalar fit refuses it.
    modes: ClassVar[tuple] = ("scalar", "vector")
    #: Effects that hold this one as a special case (a delay common to the axes is an eddy-current matrix ``d I``):
    #: with one of them in the model on the same sensor this one adds nothing, and the diagnosis does not propose it.
    nested_in: ClassVar[tuple] = ()
    #: How the term shows in the total-field residual, one line (the scalar diagnosis's evidence column).
    signature: ClassVar[str] = ""
    #: How it shows in a vector calibration's world residuals (:mod:`magcal.diagnosis.vector`).
    vector_signature: ClassVar[str] = ""
    #: What a record-only term (``transferable`` False) asks of the next recording, in words.
    when_recording: ClassVar[str] = ""
    #: The channel a vector calibration's residuals are plotted against when judging the term: ``current`` (the
    #: current or throttle column), ``temperature_C``, ``turn_rate_dps`` or ``time_s``.
    evidence_channel: ClassVar[str] = "time_s"
    #: A variance term: what it does shows in the residuals' variance rather than their mean (a random sampling
    #: jitter), so the score tests do not propose it; the diagnosis estimates it from the variance instead.
    variance_term: ClassVar[bool] = False
    #: The term can predict a block of 10 s or more held out of its fit (False for a series with knots every few
    #: seconds, which has no samples there): the diagnosis judges it on held-out blocks only then, else in-sample.
    held_out_blocks: ClassVar[bool] = True

    sensor: int | None = None

    def __init_subclass__(cls, **kwargs):
        """Read an effect class written with the array stage's former names: ``stage = "vector"`` is stage
        ``"array"`` and a ``vector_basis`` method is its :meth:`array_basis` (``docs/user-effects.md``)."""
        super().__init_subclass__(**kwargs)
        if cls.__dict__.get("stage") == "vector":
            cls.stage = "array"
        if "vector_basis" in cls.__dict__ and "array_basis" not in cls.__dict__:
            cls.array_basis = cls.__dict__["vector_basis"]

    # --- declared by subclasses -------------------------------------------------------------------------------
    def param_names(self) -> list[str]:
        """Names of the parameters of one instance (one sensor, or the array), with units in the name."""
        raise NotImplementedError

    def param_scale(self) -> np.ndarray:
        """Typical magnitude of each parameter that changes the readings by ~1 nT (for conditioning)."""
        return np.ones(len(self.param_names()))

    def domain(self) -> Domain:
        """The physical domain of one instance's parameters: their bounds and why (:class:`Domain`).

        The one declaration of what the parameters may be: the fitters keep every parameter within it
        (:func:`magcal.fitting.fitter.fit`, :func:`magcal.fitting.vector.fit_vector`), :meth:`check_params` refuses a
        value outside it (a calibration file), and the diagnoses mark a candidate whose fitted value sits on one of
        its bounds as not physical here (:func:`outside_domain`). It may depend on the data-derived constants
        (:meth:`configure`, saved by :meth:`state`), so that a calibration read back has the domain it was fitted in.
        The default is unbounded.
        """
        return Domain.free(len(self.param_names()))

    def param_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper bounds of each parameter: :meth:`domain`'s (an effect written before domains may
        override this instead; :meth:`domain` is then unbounded and every consumer reads the bounds here)."""
        d = self.domain()
        return d.lower, d.upper

    def check_params(self, values, where: str = "") -> np.ndarray:
        """``values`` (one instance's parameters) as floats, or a clear :class:`MagcalError` if a value is not a
        finite number or lies outside :meth:`domain` (its bounds, :meth:`param_bounds`).

        Parameters
        ----------
        values : array_like, shape (q,)
            Parameters of one instance, in :meth:`param_names` order.
        where : str, optional
            Where the values came from (a file, ``init``...), put in front of the message.
        """
        head = f"{where}: " if where else ""
        names = self.param_names()
        try:
            v = np.asarray(values, dtype=float).reshape(-1)
        except (TypeError, ValueError):
            raise MagcalError(
                f"{head}{self.label}: the parameters must be {len(names)} numbers ({', '.join(names)})"
            ) from None
        if v.size != len(names):
            raise MagcalError(
                f"{head}{self.label}: {v.size} parameter values for {len(names)} parameters ({', '.join(names)})"
            )
        lower, upper = (np.broadcast_to(np.asarray(b, dtype=float), v.shape) for b in self.param_bounds())
        why = self.domain().why
        for name, value, lo, hi in zip(names, v, lower, upper):
            if not np.isfinite(value):
                raise MagcalError(f"{head}{self.label}: {name} = {value} is not a finite number")
            if value < lo or value > hi:
                raise MagcalError(
                    f"{head}{self.label}: {name} = {value:g} is not physical; it must be {span_text(lo, hi)}"
                    + (f" ({why})" if why else "")
                )
        return v

    def quote(self, values, field_nT=None, sensor=None) -> str:
        """What one instance's fitted ``values`` do to the readings at the data's own field magnitude, in words
        (``""`` when the parameters' units say it already).

        Parameters quoted relative to a field (a nonlinearity, a scale change with temperature, a hysteresis
        width) read differently in a 9 uT and a 50 uT field; the report prints this line beside them.

        Parameters
        ----------
        values : array_like, shape (q,)
            The instance's parameters, in :meth:`param_names` order.
        field_nT : float, optional
            The field magnitude of the data (nT): the fitted or the reference total field.
        sensor : int, optional
            The instance's sensor (0-based), for constants kept per sensor.
        """
        return ""

    def configure(self, dataset, residuals_nT=None) -> None:
        """Set data-derived constants (reference temperature, reference time, knots, step time...).

        Called once before a fit with the kept-samples dataset and, when available, the base model's
        total-field residuals (n_sensors, N).
        """

    def raw_basis(self, z0, ctx: Context) -> np.ndarray:
        """Stage 'raw': basis (N, 3, q); the corrected raw vector is ``z0 - basis @ theta``. A basis whose
        parameters each move one axis may be returned as a :class:`SingleAxisBasis` (the fitter is faster on it)."""
        raise NotImplementedError

    def array_basis(self, field_nT, ctx: Context) -> np.ndarray:
        """Stage 'array': basis (N, 3, q); the array-frame field becomes ``B + basis @ theta``."""
        raise NotImplementedError

    def reference_basis(self, ctx: Context) -> np.ndarray:
        """Stage 'reference': basis (N, q); the expected total field becomes ``F0 + basis @ theta``."""
        raise NotImplementedError

    def perturbation(self, magnitude, sensor=None):
        """A callable for :func:`magcal.data.simulation.simulate_timeseries` that hides this effect in data."""
        raise NotImplementedError

    # --- shared ----------------------------------------------------------------------------------------------
    def applies_to(self, sensor: int) -> bool:
        """True if this instance has parameters for (or acts on) the given sensor."""
        return self.sensor is None or self.sensor == sensor

    def missing_channels(self, dataset) -> list[str]:
        """The required channels the dataset lacks (empty when the term can be fitted)."""
        missing = [c for c in self.channels if not dataset.has(c)]
        if dataset.n_sensors < self.min_sensors:
            missing.append(f"at least {self.min_sensors} sensors")
        return missing

    def state(self) -> dict:
        """Data-derived constants set by :meth:`configure`, as JSON-ready values (saved with a calibration)."""
        return {}

    def set_state(self, state: dict) -> None:
        """Restore what :meth:`state` returned."""

    def kept_raw_level(self, values) -> np.ndarray | None:
        """The raw-stage offset (nT per axis, sensor frame) that this record-only term leaves in a sensor's bias
        when it is dropped on new data (:meth:`magcal.calibration.calibration.Calibration.correct` with
        ``record_terms="drop"``), given the term's fitted ``values`` for that sensor; None (default): the term's
        zero is the level kept (a drift referred to the record's mean time, a zero-mean interference)."""
        return None

    def refine(self, effect_values: dict, context=None) -> bool:
        """Update data-derived constants from a converged fit.

        Parameters
        ----------
        effect_values : dict
            Fitted parameters, ``{block label: values}``.
        context : magcal.fitting.fitter.RefineContext, optional
            The fitted samples, and the residual cost per sample with this effect's constants changed.

        Returns
        -------
        bool
            True if the constants changed enough to warrant one more fit (:func:`magcal.fitting.fitter.fit` then refits
            without calling :meth:`configure`). Most effects have nothing to refine.
        """
        return False

    @property
    def label(self) -> str:
        """``name`` or ``name:S`` (1-based sensor) as used on the command line."""
        return term_label(self.name, self.sensor)


def parse_effect(spec: str, n_sensors: int) -> Effect:
    """Build an effect from ``NAME`` or ``NAME:SENSOR`` (SENSOR 1-based), as the CLI and JSON write it.

    Raises
    ------
    MagcalError
        For an unknown name or a sensor number outside 1..n_sensors.
    """
    name, _, sensor_text = spec.strip().partition(":")
    name = name.strip()
    if name in BASE_TERMS:
        raise MagcalError(f"{name!r} is a base term: it is always in the model unless removed")
    if name not in EFFECTS:
        raise MagcalError(unknown_effect_message(name))
    sensor = None
    if sensor_text:
        sensor = parse_sensor_number(spec, sensor_text, n_sensors)
        if not EFFECTS[name].per_sensor:
            raise MagcalError(f"effect {name!r} is shared by the whole array; it takes no sensor number")
    return EFFECTS[name](sensor=sensor)


def parse_sensor_number(spec: str, text: str, n_sensors: int) -> int:
    """The 0-based sensor of the 1-based number ``text`` after ``NAME:`` in ``spec``; a clear error otherwise."""
    try:
        sensor = int(text) - 1
    except ValueError:
        raise MagcalError(f"effect {spec!r}: the sensor after ':' must be a number 1..{n_sensors}") from None
    if not 0 <= sensor < n_sensors:
        raise MagcalError(f"effect {spec!r}: sensor {sensor + 1} does not exist (the data have {n_sensors})")
    return sensor


@dataclass
class Model:
    """The base terms in use and the candidate effects added to them.

    Parameters
    ----------
    n_sensors : int
        1 to 4.
    base : tuple of str
        Base terms kept (subset of :data:`BASE_TERMS`). ``misalignment`` is dropped for one sensor.
    effects : list of Effect
        Candidate terms added.
    """

    n_sensors: int
    base: tuple = BASE_TERMS
    effects: list = dataclasses.field(default_factory=list)

    def __post_init__(self):
        self.base = tuple(t for t in BASE_TERMS if t in self.base and not (t == "misalignment" and self.n_sensors < 2))
        unknown = [e for e in self.effects if not isinstance(e, Effect)]
        if unknown:
            raise MagcalError(f"not effect terms: {unknown}")

    @classmethod
    def base_model(cls, n_sensors: int) -> Model:
        """Bias, scale, non-orthogonality (and misalignment for arrays)."""
        return cls(n_sensors)

    @classmethod
    def from_names(cls, names, n_sensors: int, base=BASE_TERMS) -> Model:
        """A base model plus the effects named as ``NAME`` or ``NAME:SENSOR`` (1-based)."""
        effects = [parse_effect(n, n_sensors) for n in names if n.strip()]
        return cls(n_sensors, base=tuple(base), effects=effects)

    @property
    def effect_labels(self) -> list[str]:
        return [e.label for e in self.effects]

    def copy(self) -> Model:
        """A deep copy: the effect objects (and their data-derived constants) are new, so fitting the copy never
        changes this model."""
        return copy.deepcopy(self)

    def with_effect(self, effect: Effect) -> Model:
        """A new model with one more effect (every effect is copied, so neither this model nor ``effect`` changes)."""
        return Model(self.n_sensors, self.base, [copy.deepcopy(e) for e in self.effects + [effect]])

    def without(self, label: str) -> Model:
        """A new model without the effect (or base term) of that label (the remaining effects are copied)."""
        if label in BASE_TERMS:
            return Model(self.n_sensors, tuple(t for t in self.base if t != label), copy.deepcopy(self.effects))
        return Model(self.n_sensors, self.base, [copy.deepcopy(e) for e in self.effects if e.label != label])

    def check(self, dataset) -> None:
        """Raise :class:`MagcalError` naming any effect whose channels the dataset lacks."""
        problems = [
            f"{e.label} needs {', '.join(e.missing_channels(dataset))}"
            for e in self.effects
            if e.missing_channels(dataset)
        ]
        if problems:
            raise MagcalError("the data cannot support: " + "; ".join(problems))

    def instances(self):
        """Yield ``(effect, sensor_or_None)`` for every parameter block: per-sensor terms once per sensor."""
        for e in self.effects:
            if e.per_sensor:
                for s in range(self.n_sensors):
                    if e.applies_to(s):
                        yield e, s
            else:
                yield e, None


def unknown_effect_message(name: str, where: str = "", option: str = "--effects-file FILE.py") -> str:
    """The message for an effect name that is not in the catalogue: it may be a user's effect not loaded."""
    head = f"{where}: " if where else ""
    known = ", ".join(sorted(EFFECTS))
    return (
        f"{head}unknown effect {name!r}: it is not built in, so it is either misspelt or a user's own effect "
        f"that is not loaded; give the file that defines it with {option} (or install the package that provides "
        f"it). Known effects: {known}"
    )


def check_effect_names(specs, where: str = "", option: str = "--effects-file FILE.py") -> None:
    """Refuse any ``NAME`` / ``NAME:S`` in ``specs`` whose name is not in the catalogue (base terms are left to
    :func:`magcal.model.terms.parse_effect`), with :func:`unknown_effect_message`."""
    for spec in specs or ():
        name = str(spec).partition(":")[0].strip()
        if name and name not in BASE_TERMS and name not in EFFECTS:
            raise MagcalError(unknown_effect_message(name, where, option))


#: Stages whose terms change the corrected vectors (``reference`` terms change only the expected total field).
CORRECTION_STAGES = ("raw", "array")


def block_label(effect, sensor) -> str:
    """Key of one effect instance's parameters: ``name`` (shared) or ``name:S`` (S 1-based)."""
    return term_label(effect.name, sensor)


def fitted_outside_domain(model, effect_values, name: str | None = None, pulls=None) -> str:
    """Why a fit's effects are not physical here, or ``""``: :func:`outside_domain` of every block of ``model``
    in ``effect_values`` (``{block label: values}``, a calibration's), or only of the effect ``name``'s;
    ``pulls``: the fit's ``{block label: pull_z}`` (:func:`bound_pulls`)."""
    reasons = []
    for e, s in model.instances():
        label = block_label(e, s)
        values = effect_values.get(label)
        if values is not None and (name is None or e.name == name):
            reasons.append(outside_domain(e, values, label, (pulls or {}).get(label)))
    return "; ".join(r for r in reasons if r)


def bound_pulls(x, lower, upper, gradient, jtj_inv, sd) -> np.ndarray:
    """How far the data pull each parameter past its nearer bound, in its standard deviations: the unbounded
    Gauss-Newton step from the fitted ``x``, ``-(J^T J)^-1 J^T r``, in the outward direction of that bound, over the
    parameter's standard deviation; NaN for a parameter without a finite bound or standard deviation
    (:func:`outside_domain` reads it for the parameters that sit on a bound).

    Parameters
    ----------
    x, lower, upper : numpy.ndarray, shape (p,)
        The fitted parameters and their bounds.
    gradient : numpy.ndarray, shape (p,)
        ``J^T r`` at ``x`` (the residuals in the units ``jtj_inv`` was made with).
    jtj_inv : numpy.ndarray, shape (p, p)
        ``(J^T J)^-1`` (a pseudo-inverse where singular).
    sd : numpy.ndarray, shape (p,)
        The parameters' standard deviations (widened as the fit widens them).
    """
    x, lower, upper = (np.asarray(v, dtype=float) for v in (x, lower, upper))
    step = -(np.asarray(jtj_inv, dtype=float) @ np.asarray(gradient, dtype=float))
    outward = np.where(np.abs(x - lower) <= np.abs(upper - x), -step, step)
    with np.errstate(invalid="ignore", divide="ignore"):
        z = outward / np.asarray(sd, dtype=float)
    z[~(np.isfinite(lower) | np.isfinite(upper)) | ~np.isfinite(z)] = np.nan
    return z


def held_note_text(held: str) -> str:
    """The fit's note on effects held on a bound of their domain (``held``: :func:`fitted_outside_domain`)."""
    return (
        f"{held}. The fit held it on the bound of its physical domain: this record does not show the effect as the "
        "model has it (something else pulls the parameter out of its domain); the calibration is the one without it "
        "along that parameter: leave it out of the effects"
    )


def contexts(dataset, baseline_m=None):
    """One :class:`~magcal.model.terms.Context` per sensor of the dataset."""
    baseline = baseline_m if baseline_m is not None else (dataset.baseline_m or 0.0)
    positions = conventions.sensor_positions(baseline, dataset.n_sensors)
    attitude, present = None, None
    if dataset.attitude_wxyz is not None:
        q, present = filled_wxyz(dataset.attitude_wxyz)  # a sample without attitude (NaN): the identity, flagged
        attitude = Rotation.from_quat(np.column_stack([q[:, 1:], q[:, :1]]))
    return [Context(dataset, s, positions[s], attitude, present) for s in range(dataset.n_sensors)]


def attitude_effects(model) -> list[str]:
    """Labels of the model's effects whose basis needs each sample's attitude (``"attitude"`` in their
    ``channels``)."""
    return [e.label for e in model.effects if "attitude" in getattr(e, "channels", ())]


def rows_without_attitude(model, dataset) -> np.ndarray | None:
    """The samples the model cannot predict for want of an attitude: bool (N,), True where a sample has no
    attitude (a quaternion row of NaN: a live recording's samples before its first attitude message, a gap in a
    log) and an effect of the model needs it (:func:`attitude_effects`, e.g. ``site_gradient``: a world-fixed
    gradient seen through an unknown rotation has no predicted value); None when no effect needs the attitude or
    the dataset has none (:meth:`Model.check` refuses the latter)."""
    if not attitude_effects(model) or dataset.attitude_wxyz is None:
        return None
    return ~filled_wxyz(dataset.attitude_wxyz)[1]


def without_attitude_note(missing, mask, labels, what="the fit") -> str:
    """The note for samples left out of ``what`` because ``labels`` (effect labels) need their attitude:
    ``"312 of 3000 samples have no attitude (rows 1-300, 1201-1212) and were left out of the fit: site_gradient
    needs each sample's attitude (2688 samples fitted)"``; rows counted from 1 over the whole dataset."""
    missing = np.asarray(missing, bool)
    mask = np.asarray(mask, bool)
    chosen = int(mask.sum())
    left = missing & mask
    of = f"{chosen}" if chosen == mask.size else f"the {chosen} selected"
    needs = f"{', '.join(labels)} {'needs' if len(labels) == 1 else 'need'}"
    return (
        f"{int(left.sum())} of {of} samples have no attitude ({row_runs(left)}) and were left out of {what}: "
        f"{needs} each sample's attitude ({chosen - int(left.sum())} samples fitted)"
    )
