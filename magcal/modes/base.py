"""The fit modes: one :class:`FitMode` per way of calibrating a record, registered by name in :data:`FIT_MODES`.

A record says which fit it can have by what it holds: raw readings turned in a uniform field (the total-field fit),
the attitude and the Earth's field vector beside them (the vector fit), an accelerometer on the same board (the
gravity fit)... A mode is one object that says what a record needs for it (:meth:`FitMode.needs`,
:meth:`FitMode.applicable`), fits (:meth:`FitMode.fit`, a :class:`~magcal.fitting.result.ModeResult`), judges the
fit on held-out samples (:meth:`FitMode.validate`) and diagnoses it (:meth:`FitMode.diagnose`). ``magcal calibrate
--mode NAME``, ``magcal diagnose --mode NAME``, :func:`magcal.calibrate` and :func:`magcal.diagnose` take every
registered mode by name, and :func:`choose_mode` picks one for a record the same way for all of them: the applicable
mode of highest :attr:`FitMode.priority` (``mode="auto"``).

An installed package adds its own in the entry-point group ``magcal.fit_modes``
(``[project.entry-points."magcal.fit_modes"] toy = "my_pkg.modes:TOY"``, a :class:`FitMode` or a module registering
some with ``FIT_MODES.register``); :func:`choose_mode` loads them, once, on first use. CONTRIBUTING.md has the recipe.
"""

from __future__ import annotations

import inspect
from typing import TYPE_CHECKING, Any

from magcal.core.errors import MagcalError
from magcal.core.notes import Note
from magcal.core.registry import Loaded, Registry

if TYPE_CHECKING:
    from magcal.data.dataset import Dataset
    from magcal.fitting.result import ModeResult

#: The entry-point group installed packages declare their fit modes in.
ENTRY_POINT_GROUP = "magcal.fit_modes"

#: ``--mode`` values that are not modes of the registry: ``auto`` lets :func:`choose_mode` pick.
RESERVED_NAMES = ("auto",)

#: Other names of registered modes: ``scalar`` is the total-field fit's name on earlier command lines.
ALIASES = {"scalar": "total_field"}


class FitMode:
    """One way of fitting a calibration to a record (subclass it and register an instance in :data:`FIT_MODES`).

    Attributes
    ----------
    name : str
        ``--mode NAME`` and ``mode=NAME``: lower-case letters, digits, ``_`` or ``-``.
    title : str
        A few words: what the fit is and what it uses (``"vector fit (attitude and the field vector)"``); the words
        before `` (`` name it in messages (:attr:`label`).
    priority : int
        ``mode="auto"`` takes the applicable mode of highest priority (the total-field fit, 0, is always
        applicable).
    """

    name: str = ""
    title: str = ""
    priority: int = 0

    @property
    def label(self) -> str:
        """The title's words before its parenthesis: ``"vector fit"``."""
        return self.title.split(" (", 1)[0]

    def needs(self) -> str:
        """What a record must hold for this mode, one sentence (messages and ``--help``)."""
        raise NotImplementedError(f"fit mode {self.name!r} does not say what it needs")

    def applicable(self, dataset: Dataset, **options) -> str | None:
        """None when the record (with ``options``, e.g. the field vector given as ``reference=``) holds what this
        mode needs; else why not, a sentence naming what is missing and how to give it ("needs ...")."""
        return None

    def chosen_by_auto(self, dataset: Dataset, **options) -> bool:
        """Whether ``mode="auto"`` may take this mode for the record (default: when it is applicable)."""
        return self.applicable(dataset, **options) is None

    def passed_over(self, dataset: Dataset, **options) -> str | None:
        """What ``mode="auto"`` says when it takes a mode of lower priority than this one for a record that looks
        meant for this one (a sentence), or None to say nothing (the default)."""
        return None

    def fit(self, dataset: Dataset, *args: Any, **options: Any) -> ModeResult:
        """Fit the record; ``options`` are the mode's keyword arguments (``effects=``, ``robust=``, ``noise_nT=``,
        ``reference=``...). Raises :class:`~magcal.core.errors.CalibrationError` for a record it cannot fit."""
        raise NotImplementedError(f"fit mode {self.name!r} cannot fit")

    def validate(self, dataset: Dataset, result: ModeResult, **options):
        """The fit judged on samples it did not see (an object with ``text()`` and ``to_dict()``), or None when
        this mode has no such judgement (the default) or the fit has nothing to judge."""
        return None

    def diagnose(self, dataset: Dataset, result: ModeResult | None = None, **options):
        """Where the fit fails on the record and which effect is missing: a diagnosis with ``verdict``,
        ``candidates``, ``explained_by``, ``summary``, ``notes``, ``table()`` and ``to_dict()``
        (:class:`magcal.diagnosis.Diagnosis` or the vector one). Without ``result`` the mode fits first."""
        raise NotImplementedError(f"fit mode {self.name!r} has no diagnosis")

    def accepts(self, method: str = "fit") -> tuple[str, ...] | None:
        """The keyword arguments :meth:`fit` (or ``method``) takes, by name; None when it takes any."""
        params = list(inspect.signature(getattr(self, method)).parameters.values())
        if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params):
            return None
        records = 1 if method == "fit" else 2  # the dataset (and the result) before the options
        return tuple(p.name for p in params[records:] if p.kind is not inspect.Parameter.VAR_POSITIONAL)

    def taken(self, options: dict, method: str = "fit") -> dict:
        """``options`` checked against what :meth:`fit` (or ``method``) takes: a :class:`~magcal.core.errors.MagcalError` naming an
        option this mode does not take, and those it does."""
        known = self.accepts(method)
        if known is None:
            return dict(options)
        unknown = [k for k in options if k not in known]
        if unknown:
            raise MagcalError(
                f"the {self.label} (mode {self.name!r}) takes no {', '.join(f'{k}=' for k in unknown)}; it takes "
                + (", ".join(f"{k}=" for k in known) or "no options")
            )
        return dict(options)

    def __repr__(self) -> str:
        return f"<fit mode {self.name!r}: {self.title}>"


def _check(mode: FitMode, registry) -> None:
    """A mode's name is free and not an alias, and its title and needs are given."""
    if mode.name in RESERVED_NAMES or mode.name in ALIASES:
        raise MagcalError(
            f"fit mode {mode.name!r}: the name is --mode's own ({', '.join(RESERVED_NAMES + tuple(ALIASES))})"
        )
    if not isinstance(mode.title, str) or not mode.title.strip():
        raise MagcalError(f"fit mode {mode.name!r}: give its title (a non-empty text)")
    try:
        needs = mode.needs()
    except NotImplementedError:
        needs = None
    if not isinstance(needs, str) or not needs.strip():
        raise MagcalError(f"fit mode {mode.name!r}: give its needs() (what a record must hold, one sentence)")
    if not isinstance(mode.priority, int):
        raise MagcalError(f"fit mode {mode.name!r}: its priority must be an integer, got {mode.priority!r}")


#: Every fit mode by name, in the order they were registered (the built-ins first).
FIT_MODES: Registry[FitMode] = Registry("fit mode", ENTRY_POINT_GROUP, FitMode, _check)


def load_entry_points(force: bool = False) -> Loaded:
    """Add the fit modes installed packages declare in ``magcal.fit_modes`` (once): see
    :meth:`magcal.core.registry.Registry.load_entry_points` (the names added, and the skipped ones' ``notes``)."""
    return FIT_MODES.load_entry_points(force=force)


def mode_names() -> tuple[str, ...]:
    """What ``--mode`` takes: ``auto``, every registered mode's name (in the order ``auto`` prefers them: highest
    :attr:`FitMode.priority` first), and the aliases."""
    return (*RESERVED_NAMES, *_ranked(), *ALIASES)


def _ranked() -> list:
    """The registered modes' names, highest priority first (registration order among equals)."""
    return [m.name for m in sorted(FIT_MODES.values(), key=lambda m: -m.priority)]


def fit_mode(name: str, option: str = "mode") -> FitMode:
    """The mode called ``name`` (or an alias of it), or a :class:`~magcal.core.errors.MagcalError` naming those there are (``option``:
    how the user gave the name, ``mode`` or ``--mode``)."""
    found = FIT_MODES.get(ALIASES.get(name, name)) if isinstance(name, str) else None
    if found is None:
        given = f"{option} {name!r}" if option.startswith("-") else f"{option}={name!r}"
        raise MagcalError(f"{given}: use one of {', '.join(mode_names())}")
    return found


def _named(mode: FitMode, option: str) -> str:
    return f"{option} {mode.name}" if option.startswith("-") else f"{option}={mode.name!r}"


def mode_choice(dataset: Dataset, mode: str = "auto", *, option: str = "mode", **options) -> tuple[FitMode, list]:
    """:func:`choose_mode`, with what the choice has to say: ``(mode, notes)``.

    The notes (:class:`~magcal.core.notes.Note`, ``UserWarning``) say why ``auto`` passed over a mode the record
    looks meant for (:meth:`FitMode.passed_over`: attitude columns empty on every row...), and which installed
    fit modes could not be loaded.
    """
    notes = list(load_entry_points().notes)
    if mode != "auto":
        named = fit_mode(mode, option)
        reason = named.applicable(dataset, **options)
        if reason is not None:
            raise MagcalError(f"{_named(named, option)} {reason}")
        return named, notes
    ranked = [FIT_MODES[name] for name in _ranked()]
    chosen = next((m for m in ranked if m.chosen_by_auto(dataset, **options)), None)
    if chosen is None:
        raise MagcalError("no fit mode takes this record: " + "; ".join(f"the {m.label} {m.needs()}" for m in ranked))
    for m in ranked:
        if m.priority <= chosen.priority:
            break
        said = m.passed_over(dataset, **options)
        if said:
            notes.append(Note(f"{said}: the {chosen.label}", UserWarning, "fit mode"))
    return chosen, notes


def choose_mode(dataset: Dataset, mode: str = "auto", *, option: str = "mode", **options) -> FitMode:
    """The fit mode for ``dataset``: the one named (``"vector"``; ``"scalar"`` is ``"total_field"``), refused with
    why when the record lacks what it needs, or with ``"auto"`` the applicable mode of highest priority (vector when
    some rows have an attitude and the field vector is known, gravity beside an accelerometer without attitude,
    else the total-field fit).

    Parameters
    ----------
    dataset : Dataset
        The record.
    mode : str
        A registered mode's name, an alias, or ``"auto"``.
    option : str
        How the user named the mode, for messages (``"mode"`` or ``"--mode"``).
    **options
        What the modes need beside the record (the vector fit's ``reference=``).

    Raises
    ------
    MagcalError
        An unknown name (naming the known ones), or a mode the record cannot have (saying what it needs).
    """
    return mode_choice(dataset, mode, option=option, **options)[0]
