"""The user's own effects: load :class:`~magcal.model.terms.Effect` terms from a Python file or from installed packages.

When the catalogue (:mod:`magcal.model.effects`) lacks a term, a user writes it as an :class:`~magcal.model.terms.Effect`
subclass and makes it known to magcal in one of two ways (walk-through: ``docs/user-effects.md``):

* **A file** -- ``magcal calibrate data.csv --effects-file my_effects.py`` or, from Python,
  :func:`load_effects_file`. *The file is Python code that runs with the user's rights*: only a file the user
  chose and trusts. The rule: *every class the file decorates with* ``@register``
  (:func:`magcal.model.terms.register`) *joins the catalogue*; nothing else does (helper base classes, imports of other
  effects). A file that registers nothing is refused, naming the undecorated Effect subclasses it found.
* **A package** that declares entry points in the group ``magcal.effects`` (pyproject:
  ``[project.entry-points."magcal.effects"] pump = "my_pkg.effects:PumpInterference"``). An entry point names an
  Effect subclass (registered here) or a module (imported; its ``@register`` classes join, as for a file).
  :func:`load_entry_points` loads them once; the command line calls it at start, the workbench calls the same
  function. They are *not* loaded at ``import magcal`` (the import stays light and never runs a third party's
  code unasked). A failing entry point is reported as a warning and skipped.

Either way the effect is then a catalogue term like a built-in one: ``calibrate --effects NAME``, a candidate
of ``diagnose``, saved in and restored from the calibration JSON (the JSON names the effect; loading it needs
the effect loaded again), ``apply``, ``simulate --hidden NAME`` when it has a perturbation, and the workbench.

Every effect class is checked before it joins (:func:`validate_effect`): a name that is new (a built-in, a base
term or another source's effect of that name is refused) and usable on the command line, a stage of ``raw``,
``array`` or ``reference`` with that stage's basis implemented, known channels, parameter names, scales of the
same length, a state that survives JSON, and a dry run of ``configure`` and the basis on a small synthetic
four-sensor record (its shapes and finiteness). Errors in the user's file -- a syntax error, a failed import, an
exception while it runs, a class that fails the checks -- become one :class:`UserEffectError` naming the file,
the line and what to do, never a traceback; on any error the catalogue is left as it was.
"""

from __future__ import annotations

import errno
import hashlib
import importlib
import importlib.abc
import importlib.metadata
import importlib.util
import inspect
import json
import linecache
import os
import re
import stat
import sys
import threading
import traceback
from dataclasses import dataclass

import numpy as np

from magcal.core import notes as _notes
from magcal.core.errors import MagcalError
from magcal.core.files import not_regular_reason
from magcal.core.jsonable import jsonable
from magcal.core.notes import Note
from magcal.core.registry import Loaded
from magcal.data.dataset import CHANNELS, Dataset
from magcal.model import perturbations
from magcal.model.terms import BASE_TERMS, EFFECTS, Effect, contexts

#: The entry-point group a package declares its effects in.
ENTRY_POINT_GROUP = "magcal.effects"

#: The stages an effect may act in, and the basis method each one needs (see :mod:`magcal.model.terms`).
STAGE_METHODS = {"raw": "raw_basis", "array": "array_basis", "reference": "reference_basis"}

#: What an effect name may look like: it is typed on the command line as ``NAME`` or ``NAME:S``.
NAME_PATTERN = re.compile(r"^[a-z][a-z0-9_]{0,63}$")

#: The documentation page of user effects, quoted in messages.
DOC = "docs/user-effects.md"

_LOCK = threading.RLock()
#: name -> (kind, where): kind "file" or "entry point"; where the absolute path or "NAME = VALUE (dist)".
_ORIGINS: dict[str, tuple[str, str]] = {}
#: name -> source key (the absolute path of a file, or "entry point NAME"), so that reloading a file is allowed.
_SOURCES: dict[str, str] = {}
#: Absolute paths of the files the user's effects live in (for errors raised later from their code).
_USER_FILES: set[str] = set()
_ENTRY_POINTS_LOADED = False


class UserEffectError(MagcalError):
    """A user's effect file or class cannot be loaded; the message names the file, the line and what to do."""


# ----------------------------------------------------------------------------------------------------------------
# where an effect came from
# ----------------------------------------------------------------------------------------------------------------


def _is_magcal_module(module: str) -> bool:
    return module == "magcal" or module.startswith("magcal.")


def origin(name: str) -> tuple[str, str]:
    """Where the effect ``name`` came from: ``(kind, where)``.

    Returns
    -------
    tuple of str
        ``("built-in", "magcal.model.effects")``, ``("file", "/abs/path.py")``,
        ``("entry point", "NAME = VALUE (distribution)")`` or ``("python", "module")`` for a class registered
        by Python code with :func:`magcal.model.terms.register` directly.
    """
    if name in _ORIGINS:
        return _ORIGINS[name]
    cls = EFFECTS.get(name)
    module = getattr(cls, "__module__", "") or ""
    if _is_magcal_module(module):
        return "built-in", module
    return "python", module


def is_builtin(name: str) -> bool:
    """True for an effect of magcal's own catalogue."""
    return name in EFFECTS and origin(name)[0] == "built-in"


def user_files() -> list[str]:
    """Absolute paths of the effect files loaded so far (and of the modules entry points loaded)."""
    return sorted(_USER_FILES)


# ----------------------------------------------------------------------------------------------------------------
# validation
# ----------------------------------------------------------------------------------------------------------------


def _class_line(cls) -> int | None:
    try:
        return inspect.getsourcelines(cls)[1]
    except (OSError, TypeError):
        return None


def _where_class(cls, path=None) -> str:
    """``file.py, line 12: effect class Foo`` for messages."""
    if path is None:
        try:
            path = inspect.getsourcefile(cls)
        except TypeError:
            path = None
    line = _class_line(cls)
    head = path or cls.__module__
    if line:
        head += f", line {line}"
    return f"{head}: effect class {cls.__name__}"


def reserved_names() -> set:
    """Names the simulator already gives to perturbations outside the catalogue (``simulate --hidden NAME``)."""
    return set(perturbations.EXTRA_PERTURBATIONS)


def _check_name(cls, source_key, where) -> str:
    name = getattr(cls, "name", None)
    if not isinstance(name, str) or not name:
        raise UserEffectError(
            f'{where}: has no name; set the class attribute name = "my_effect" (lower case, '
            f"letters, digits and _), the name used by --effects and the JSON ({DOC})"
        )
    if not NAME_PATTERN.match(name):
        raise UserEffectError(
            f"{where}: name {name!r} cannot be typed as --effects NAME[:S]; use lower-case "
            'letters, digits and _ only, starting with a letter (e.g. "pump_interference")'
        )
    if name in BASE_TERMS:
        raise UserEffectError(f"{where}: name {name!r} is a base term of every model; choose another name")
    current = EFFECTS.get(name)
    if current is not None and current is not cls:
        kind, place = origin(name)
        if kind == "built-in":
            raise UserEffectError(
                f"{where}: name {name!r} is already a built-in effect of magcal; a user's effect "
                f'cannot replace it: give yours another name (e.g. "my_{name}")'
            )
        if _SOURCES.get(name) != source_key:
            raise UserEffectError(
                f"{where}: name {name!r} is already taken by the effect from {kind} {place}; "
                "give one of them another name, or load only one of the two"
            )
    if name in reserved_names():
        raise UserEffectError(
            f"{where}: name {name!r} is taken by the simulator (magcal simulate --hidden {name}); choose another name"
        )
    return name


def validate_effect(cls, source_key=None, path=None) -> str:
    """Check that ``cls`` can join the catalogue; returns its name.

    Parameters
    ----------
    cls : type
        The candidate class.
    source_key : str, optional
        The file (absolute path) or entry point it comes from: an effect of the same name from the same source
        may replace the old one (a file loaded again), from another source it may not.
    path : str, optional
        The file, for messages (default: where the class is defined).

    Raises
    ------
    UserEffectError
        Naming the file, the line of the class and what to do: not an Effect subclass; a missing, malformed or
        taken name; an unknown stage, or the stage's basis method not implemented; unknown channels; missing or
        malformed ``param_names``; ``param_scale`` of another length or not positive; a state that is not JSON;
        a basis of the wrong shape or not finite, or an exception, in a dry run on a synthetic record.
    """
    if not (inspect.isclass(cls) and issubclass(cls, Effect)) or cls is Effect:
        raise UserEffectError(
            f"{path or getattr(cls, '__module__', '?')}: {cls!r} is not a subclass of "
            "magcal.model.terms.Effect; derive your effect class from it"
        )
    where = _where_class(cls, path)
    name = _check_name(cls, source_key, where)
    stage = getattr(cls, "stage", None)
    if stage not in STAGE_METHODS:
        raise UserEffectError(
            f"{where}: stage {stage!r} is not one of raw, array, reference; set stage to where "
            f"the term acts (docs/architecture.md, {DOC})"
        )
    method = STAGE_METHODS[stage]
    if getattr(cls, method) is getattr(Effect, method):
        raise UserEffectError(
            f"{where}: stage is {stage!r} but the class does not define {method}(); define it "
            "(it returns the Jacobian of the correction, one column per parameter)"
        )
    if cls.param_names is Effect.param_names:
        raise UserEffectError(
            f"{where}: no param_names(); define it to return the parameter names with their "
            'units, e.g. ["a_x_nT", "a_y_nT", "a_z_nT"]'
        )

    channels = getattr(cls, "channels", ())
    if isinstance(channels, str) or not all(isinstance(c, str) for c in channels):
        raise UserEffectError(f'{where}: channels must be a tuple of channel names, e.g. ("time",), got {channels!r}')
    unknown = [c for c in channels if c not in CHANNELS]
    if unknown:
        raise UserEffectError(
            f"{where}: unknown channel(s) {', '.join(map(repr, unknown))}; an effect may use "
            f"only the dataset's channels: {', '.join(CHANNELS)}"
        )
    if not isinstance(getattr(cls, "per_sensor", True), bool):
        raise UserEffectError(f"{where}: per_sensor must be True or False")
    min_sensors = getattr(cls, "min_sensors", 1)
    if not isinstance(min_sensors, int) or not 1 <= min_sensors <= 4:
        raise UserEffectError(f"{where}: min_sensors must be a whole number 1..4, got {min_sensors!r}")
    transferable = getattr(cls, "transferable", None)
    if transferable is not None and not isinstance(transferable, bool):
        raise UserEffectError(
            f"{where}: transferable must be True (the term describes the instrument and carries "
            "to new data) or False (it describes one recording)"
        )
    if not isinstance(getattr(cls, "description", ""), str):
        raise UserEffectError(f"{where}: description must be one line of text")
    with _user_code(where):
        instance = cls()
        names = instance.param_names()
    if not isinstance(names, (list, tuple)) or not names or not all(isinstance(n, str) and n for n in names):
        raise UserEffectError(
            f'{where}: param_names() must return a non-empty list of names (with units, e.g. "a_x_nT"), got {names!r}'
        )
    if len(set(names)) != len(names):
        raise UserEffectError(f"{where}: param_names() repeats a name: {names}; every parameter needs its own")
    with _user_code(where):
        scale = np.asarray(instance.param_scale(), dtype=float)
    if scale.shape != (len(names),) or not np.all(np.isfinite(scale)) or not np.all(scale > 0):
        raise UserEffectError(
            f"{where}: param_scale() must return {len(names)} positive numbers (the size of each "
            f"parameter that changes the readings by about 1 nT), got {scale.tolist()}"
        )
    _dry_run(cls, where, len(names))
    return name


def _synthetic_record(n=240):
    """A small four-sensor record with every channel: 10 Hz, smooth rotation in a 50 uT field, 15-25 degC, a motor
    current (``current_A``) and a throttle column."""
    from scipy.spatial.transform import Rotation

    t = np.arange(n) / 10.0
    att = Rotation.from_rotvec(np.column_stack([0.31 * t, 0.17 * t + 0.4, 0.05 * t * np.sin(0.2 * t)]))
    field = np.array([20_000.0, 5_000.0, -45_552.0])
    field *= 50_000.0 / np.linalg.norm(field)
    body = att.inv().apply(field)
    readings = np.stack([body + 30.0 * k for k in range(4)])
    q = att.as_quat()
    return Dataset(
        readings,
        time_s=t,
        temperature_C=20.0 + 5.0 * np.sin(0.05 * t),
        ref_total_nT=np.full(n, 50_000.0),
        attitude_wxyz=np.column_stack([q[:, 3], q[:, :3]]),
        group=np.array(["x_up", "y_up", "z_up"] * (n // 3) + ["x_up"] * (n % 3)),
        reference_total_nT=50_000.0,
        baseline_m=0.5,
        extra={"current_A": 5.0 + 2.0 * np.sin(0.3 * t), "throttle": 0.5 + 0.2 * np.sin(0.3 * t)},
        source="synthetic test record",
    )


def _dry_run(cls, where, q):
    """configure, state/set_state and the basis on :func:`_synthetic_record`: shapes and finite values."""

    ds = _synthetic_record()
    n = ds.n_samples
    with _user_code(where, "in a dry run on a synthetic 240-sample record"):
        effect = cls()
        if cls.per_sensor:
            cls(sensor=max(0, getattr(cls, "min_sensors", 1) - 1))  # e.g. sensor 1 may be a time reference
        effect.configure(ds, np.zeros((ds.n_sensors, n)))
        state = effect.state()
        q = len(effect.param_names())  # a count that follows the record (knots every few seconds) is set by configure
    try:
        text = json.dumps(jsonable(state if state is not None else {}), allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise UserEffectError(
            f"{where}: state() must return JSON-ready values (numbers, text, lists, dicts) to be "
            f"saved with a calibration; {type(exc).__name__}: {exc}"
        ) from None
    with _user_code(where, "restoring its state()"):
        cls().set_state(json.loads(text))
    stage = cls.stage
    for ctx in contexts(ds):
        with _user_code(where, f"in a dry run of {STAGE_METHODS[stage]} on a synthetic 240-sample record"):
            if stage == "raw":
                basis = effect.raw_basis(ds.readings_nT[ctx.sensor] - 0.0, ctx)
            elif stage == "array":
                basis = effect.array_basis(ds.readings_nT[ctx.sensor], ctx)
            else:
                basis = effect.reference_basis(ctx)
        expected = (n, q) if stage == "reference" else (n, 3, q)
        shape = np.shape(basis)
        if shape != expected:
            what = "(N, q)" if stage == "reference" else "(N, 3, q)"
            raise UserEffectError(
                f"{where}: {STAGE_METHODS[stage]} returned shape {shape} on a {n}-sample record; "
                f"it must be {what} = {expected}: one row per sample"
                f"{'' if stage == 'reference' else ' and axis'}, one column per parameter "
                f"({q} in param_names())"
            )
        if not np.all(np.isfinite(np.asarray(basis, dtype=float))):
            raise UserEffectError(
                f"{where}: {STAGE_METHODS[stage]} returned NaN or infinite values on a synthetic "
                "record; guard divisions and empty channels"
            )


class _user_code:
    """Context manager: an exception raised by the user's code becomes a :class:`UserEffectError`."""

    def __init__(self, where, doing=""):
        self.where, self.doing = where, doing

    def __enter__(self):
        return self

    def __exit__(self, kind, exc, tb):
        if exc is None or isinstance(exc, MagcalError) or not isinstance(exc, Exception):
            return False
        frame = _last_user_frame(exc)
        at = f" (at {frame.filename}, line {frame.lineno}: {(frame.line or '').strip()})" if frame else ""
        doing = f" {self.doing}" if self.doing else ""
        raise UserEffectError(
            f"{self.where}: raised {type(exc).__name__}: {exc}{doing}{at}; correct the effect ({DOC})"
        ) from None


def _last_user_frame(exc, files=None):
    """The innermost traceback frame in one of the user's files (or outside magcal and the standard library)."""
    frames = traceback.extract_tb(exc.__traceback__)
    files = _USER_FILES if files is None else files
    for frame in reversed(frames):
        if os.path.abspath(frame.filename) in files:
            return frame
    magcal_dir = os.path.dirname(os.path.abspath(__file__))
    stdlib = os.path.dirname(os.__file__)
    for frame in reversed(frames):
        path = os.path.abspath(frame.filename)
        if not path.startswith(magcal_dir) and not path.startswith(stdlib) and "site-packages" not in path:
            return frame
    return None


# ----------------------------------------------------------------------------------------------------------------
# loading
# ----------------------------------------------------------------------------------------------------------------


def _module_name(path: str) -> str:
    stem = re.sub(r"\W", "_", os.path.splitext(os.path.basename(path))[0]) or "effects"
    digest = hashlib.sha1(path.encode("utf-8")).hexdigest()[:10]
    return f"_magcal_user_effects_{stem}_{digest}"


def _file_error(path, exc) -> UserEffectError:
    """One clear message for an exception raised while a user's file runs."""
    if isinstance(exc, SyntaxError):
        line = exc.lineno or "?"
        text = (exc.text or linecache.getline(path, exc.lineno or 0) or "").rstrip()
        code = f"\n    {text.strip()}" if text.strip() else ""
        kind = "indentation error" if isinstance(exc, IndentationError) else "syntax error"
        return UserEffectError(
            f"{path}, line {line}: {kind}: {exc.msg}{code}\n  correct this line of your effects "
            f"file and run again ({DOC})"
        )
    if isinstance(exc, SystemExit):
        return UserEffectError(
            f"{path}: the file exits when imported (sys.exit({exc.code!r})); put script code under "
            'if __name__ == "__main__": so that importing it only defines the effects'
        )
    frame = _last_user_frame(exc, {path})
    line = frame.lineno if frame else "?"
    code = f"\n    {frame.line.strip()}" if frame and frame.line else ""
    if isinstance(exc, ImportError):
        missing = getattr(exc, "name", None)
        hint = (
            f"install {missing!r} (pip install ...) or remove the import"
            if isinstance(exc, ModuleNotFoundError) and missing
            else "check the name imported (an Effect and register come from magcal.model.terms)"
        )
        return UserEffectError(f"{path}, line {line}: cannot import: {exc}{code}\n  {hint}")
    return UserEffectError(
        f"{path}, line {line}: {type(exc).__name__}: {exc}{code}\n  the file raised this while it "
        f"was loaded; correct it and run again ({DOC})"
    )


def _registered_since(before: dict) -> tuple[list, list]:
    """Names added to :data:`EFFECTS` since ``before`` was copied, and names whose class was replaced."""
    added = [n for n in EFFECTS if n not in before]
    replaced = [n for n in EFFECTS if n in before and EFFECTS[n] is not before[n]]
    return added, replaced


def _restore(before: dict) -> None:
    EFFECTS.clear()
    EFFECTS.update(before)


def _admit(classes, before, source_key, kind, where, path=None) -> list[str]:
    """Validate the classes registered from one source against the catalogue as it was before the source ran
    (``before``), add them and record their origin; on any error the catalogue is restored to ``before``."""
    _restore(before)
    names = []
    try:
        seen: dict = {}
        for cls in classes:
            name = getattr(cls, "name", None)
            if isinstance(name, str) and name in seen and seen[name] is not cls:
                raise UserEffectError(
                    f"{where}: two effect classes are named {name!r} ({seen[name].__name__} and "
                    f"{cls.__name__}); give each its own name"
                )
            name = validate_effect(cls, source_key, path)
            seen[name] = cls
            EFFECTS[name] = cls
            names.append(name)
    except BaseException:
        _restore(before)
        raise
    for stale in [n for n, src in _SOURCES.items() if src == source_key and n not in names]:
        EFFECTS.pop(stale, None)  # the source was loaded again and no longer defines it (renamed, removed)
        _ORIGINS.pop(stale, None)
        _SOURCES.pop(stale, None)
    for name in names:
        _ORIGINS[name] = (kind, where)
        _SOURCES[name] = source_key
    return names


#: Largest effects file read, bytes: a Python file that defines a few effects is a few kilobytes.
MAX_EFFECTS_FILE_BYTES = 16 * 1024 * 1024


@dataclass(frozen=True)
class EffectsSource:
    """An effects file as read once: the code :func:`load_effects_file` runs is exactly ``code``, whatever the path
    names afterwards (an edit, a symbolic link moved).

    Attributes
    ----------
    path : str
        The absolute path given (``~`` not expanded), the name the file's effects and messages carry.
    real : str
        The file that was read: ``path`` with its symbolic links resolved once, then opened without following any
        link (:func:`read_effects_file`).
    code : bytes
        The file's content as read.
    sha256 : str
        The SHA-256 digest of ``code`` (hexadecimal): what a consent given to this file is bound to.
    """

    path: str
    real: str
    code: bytes
    sha256: str


def _open_without_links(real: str) -> int:
    """A descriptor of the file at ``real`` (an absolute path without symbolic links), opened one component at a
    time from ``/`` with ``O_NOFOLLOW``: a component that became a symbolic link since ``real`` was resolved is
    an :class:`OSError` (``ELOOP`` or ``ENOTDIR``), never followed. The last component is opened non-blocking (a
    FIFO put there does not block). Where the system lacks ``openat`` (Windows), the path is opened as it is."""
    nofollow = getattr(os, "O_NOFOLLOW", 0)
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0) | nofollow
    if not nofollow or os.open not in os.supports_dir_fd:
        return os.open(real, flags | getattr(os, "O_BINARY", 0))
    walk = getattr(os, "O_PATH", os.O_RDONLY) | os.O_DIRECTORY | nofollow | getattr(os, "O_CLOEXEC", 0)
    *folders, name = real.split(os.sep)[1:]
    at = os.open(os.sep, walk)
    try:
        for folder in folders:
            inner = os.open(folder, walk, dir_fd=at)
            os.close(at)
            at = inner
        return os.open(name, flags, dir_fd=at)
    finally:
        os.close(at)


def read_effects_file(path) -> EffectsSource:
    """Read an effects file once: its content, where it was read, and the content's digest.

    The path's symbolic links are resolved once (:func:`os.path.realpath`) and that file is opened without
    following any further link; whether it is a regular file and how large is checked on the descriptor opened,
    and the bytes read there are what :func:`load_effects_file` runs. A link moved between two reads therefore
    never puts another file's code in place of the one checked.

    Parameters
    ----------
    path : str or os.PathLike
        A Python file (``.py``).

    Raises
    ------
    UserEffectError
        Missing, no regular file (a folder, a FIFO, a device), not ``.py``, larger than
        :data:`MAX_EFFECTS_FILE_BYTES`, unreadable, or a path whose links changed while it was opened.
    """
    path = os.path.abspath(os.fspath(path))
    reason = not_regular_reason(path)
    if reason == "no such file":
        raise UserEffectError(f"{path}: no such effects file; check the path given to --effects-file")
    if reason is not None:  # a directory; a FIFO or a device would block or never end the import
        raise UserEffectError(
            f"{path}: is {reason}; give the Python file that defines your effect"
            if not reason.startswith("cannot")
            else f"{path}: the effects file {reason}; check the path and its permissions"
        )
    if not path.endswith(".py"):
        raise UserEffectError(f"{path}: an effects file must be a Python file ending in .py ({DOC})")
    real = os.path.realpath(path)
    try:
        fd = _open_without_links(real)
    except OSError as exc:
        if exc.errno in (errno.ELOOP, errno.ENOTDIR, errno.ENOENT):
            raise UserEffectError(
                f"{path}: the file or a folder on its path was replaced while it was opened (a symbolic link "
                "moved); nothing was run. Load it again once the file stays in place"
            ) from None
        raise UserEffectError(f"{path}: the effects file cannot be read ({exc.strerror or exc})") from None
    with os.fdopen(fd, "rb") as fh:
        mode = os.fstat(fh.fileno())
        if not stat.S_ISREG(mode.st_mode):
            raise UserEffectError(f"{path}: is not a regular file any more; give the Python file of your effect")
        if mode.st_size > MAX_EFFECTS_FILE_BYTES:
            raise UserEffectError(
                f"{path}: {mode.st_size / 1e6:.1f} MB is no effects file (at most "
                f"{MAX_EFFECTS_FILE_BYTES / 1e6:.0f} MB); give the Python file that defines your effect"
            )
        code = fh.read(MAX_EFFECTS_FILE_BYTES + 1)
    if len(code) > MAX_EFFECTS_FILE_BYTES:
        raise UserEffectError(f"{path}: grew past {MAX_EFFECTS_FILE_BYTES / 1e6:.0f} MB while it was read")
    return EffectsSource(path, real, code, hashlib.sha256(code).hexdigest())


class _SourceLoader(importlib.abc.Loader):
    """Runs an :class:`EffectsSource`'s bytes as a module (never the path again), and gives tracebacks and
    :mod:`inspect` those bytes' lines."""

    def __init__(self, source: EffectsSource):
        self.source = source

    def create_module(self, spec):
        return None  # the default module

    def exec_module(self, module) -> None:
        code = compile(self.source.code, self.source.path, "exec", dont_inherit=True)
        text = importlib.util.decode_source(self.source.code)
        lines = text.splitlines(keepends=True)
        # the lines that run, under the file's name (no modification time: linecache never reads the disk again)
        linecache.cache[self.source.path] = (len(text), None, lines, self.source.path)
        exec(code, module.__dict__)

    def get_source(self, fullname) -> str:
        return importlib.util.decode_source(self.source.code)


def load_effects_file(path) -> list[str]:
    """Load a user's effect file: the Effect classes it decorates with ``@register`` join the catalogue.

    **The file is Python code and runs with the rights of the process** (it runs as ``python FILE.py`` would):
    load only a file the user chose and trusts, never one named by a data file, a calibration or a session
    document.

    The file is read once (:func:`read_effects_file`) and exactly the bytes read run, as a module of its own (a
    unique name derived from its path, so two files may share a stem); loading the same file again replaces its
    effects (after an edit).

    Parameters
    ----------
    path : str, os.PathLike or EffectsSource
        A Python file, or one read already (:func:`read_effects_file`: what a consent was given to).

    Returns
    -------
    list of str
        The names of the effects it registered, in the file's order.

    Raises
    ------
    UserEffectError
        The file is missing or not Python; it has a syntax error, fails to import something or raises while it
        runs (the line and what to do); it registers no effect; an effect fails :func:`validate_effect` (a name
        clash with a built-in or another source, a missing ``param_names``...). The catalogue is then unchanged.
    """
    source = path if isinstance(path, EffectsSource) else read_effects_file(path)
    path = source.path
    module_name = _module_name(path)
    with _LOCK:
        before = dict(EFFECTS)
        for name in [n for n, src in _SOURCES.items() if src == path]:
            EFFECTS.pop(name, None)  # loaded again: the file registers its effects anew (put back on any error)
        spec = importlib.util.spec_from_loader(module_name, _SourceLoader(source), origin=path)
        assert spec is not None
        spec.has_location = True  # the module's __file__ is the path (inspect finds its classes' lines)
        module = importlib.util.module_from_spec(spec)
        old_module = sys.modules.get(module_name)
        sys.modules[module_name] = module  # dataclasses and pickling look the module up by name
        try:
            spec.loader.exec_module(module)  # type: ignore[union-attr]
        except (Exception, SystemExit) as exc:  # SystemExit: a script's sys.exit() or argparse run on import
            _restore(before)
            _put_back(module_name, old_module)
            raise _file_error(path, exc) from None
        added, replaced = _registered_since(before)
        classes = sorted((EFFECTS[n] for n in added + replaced), key=lambda c: _class_line(c) or 0)  # file order
        if not classes:
            _restore(before)
            _put_back(module_name, old_module)
            local = [
                c.__name__
                for c in vars(module).values()
                if inspect.isclass(c) and issubclass(c, Effect) and c.__module__ == module_name
            ]
            found = (
                (
                    f" It defines {', '.join(local)} without it: put @register (from magcal.model import register) "
                    "above each class that is an effect."
                )
                if local
                else " Define a subclass of magcal.model.Effect and decorate it with @register."
            )
            raise UserEffectError(f"{path}: registers no effect.{found} ({DOC})")
        _USER_FILES.add(path)
        try:
            return _admit(classes, before, path, "file", path, path)
        except BaseException:
            _put_back(module_name, old_module)
            raise


def _put_back(module_name, old_module):
    if old_module is None:
        sys.modules.pop(module_name, None)
    else:
        sys.modules[module_name] = old_module


def load_effects_files(paths) -> list[str]:
    """:func:`load_effects_file` for each path (``None`` or empty: nothing); returns every name registered."""
    names = []
    for p in paths or ():
        names += load_effects_file(p)
    return names


#: Effect files this process has loaded for a worker's task (:func:`load_for_worker`): path -> (mtime, size).
_WORKER_FILES: dict = {}


def load_for_worker(names, files=()) -> None:
    """Make the effects ``names`` (a calibration's) known in this worker process: the user's ``files`` loaded (each
    once per process, again only when it changed), then the installed packages' entry points if a name is still
    unknown.

    A process of a local cluster or of a cluster elsewhere does not share the catalogue of the process that loaded
    the user's file (``--effects-file``): the task is given the file's path and loads it here, as the caller did.

    Raises
    ------
    UserEffectError
        A file that is not on this machine's file system (a cluster's workers must see it, as they see the
        surveys), or that fails to load (:func:`load_effects_file`); an effect still unknown after an installed
        package's entry point was skipped (the message says why it was).
    """
    import socket

    for path in files or ():
        try:
            st = os.stat(path)
        except OSError:
            raise UserEffectError(
                f"{path}: the effects file is not on the file system of the worker on {socket.gethostname()}; "
                "on a cluster put it where every worker sees it, as the surveys and the output folder"
            ) from None
        key = (st.st_mtime_ns, st.st_size)
        if _WORKER_FILES.get(path) != key:
            load_effects_file(path)
            _WORKER_FILES[path] = key
    if any(name not in EFFECTS for name in names or ()):
        loaded = load_entry_points(warn=False)
        missing = [name for name in names or () if name not in EFFECTS]
        if missing and loaded.notes:  # a worker's warnings go nowhere the user looks: say why in the error
            raise UserEffectError(
                f"effect(s) {', '.join(missing)} unknown on the worker on {socket.gethostname()}: "
                + "; ".join(note.text for note in loaded.notes)
            )


def _entry_point_text(ep) -> str:
    dist = getattr(ep, "dist", None)
    metadata = getattr(dist, "metadata", None)
    dist_name = getattr(dist, "name", None) or (metadata["Name"] if metadata else None)
    return f"{ep.name} = {ep.value}" + (f" ({dist_name})" if dist_name else "")


def load_entry_points(group: str = ENTRY_POINT_GROUP, force: bool = False, warn: bool = True) -> Loaded:
    """Load the effects that installed packages declare in the entry-point group ``magcal.effects``.

    Each entry point names an Effect subclass or a module whose ``@register`` classes join the catalogue.
    Called once (later calls return ``[]`` unless ``force``): by the command line at start and by the workbench.

    Parameters
    ----------
    group : str
        The entry-point group.
    force : bool
        Load again even if already loaded.
    warn : bool
        Raise the notes of the entry points skipped as ``UserWarning`` warnings, the default; False leaves them in
        the result's ``notes`` (what the command line, the workbench and a worker do).

    Returns
    -------
    magcal.core.registry.Loaded
        Names of the effects added (a list of str), and in its ``notes`` a ``UserWarning`` note for each entry
        point skipped.

    Warns
    -----
    UserWarning
        For each entry point that fails to import or whose effect fails :func:`validate_effect`: it is skipped
        with a message naming it and its package; the others load.
    """
    loaded = _load_entry_points(group, force)
    if warn:
        _notes.warn(loaded.notes)
    return loaded


def _load_entry_points(group: str, force: bool) -> Loaded:
    """:func:`load_entry_points` but the warnings."""
    global _ENTRY_POINTS_LOADED
    with _LOCK:
        if _ENTRY_POINTS_LOADED and not force:
            return Loaded()
        _ENTRY_POINTS_LOADED = True
        try:
            found = importlib.metadata.entry_points(group=group)
        except Exception as exc:  # a broken installation must not stop magcal
            text = (
                f"could not list the {group!r} entry points ({type(exc).__name__}: {exc}); "
                "installed effect packages are not loaded"
            )
            return Loaded((), [Note(text, UserWarning, "plugins")])
        names = Loaded()
        for ep in found:
            text = _entry_point_text(ep)
            before = dict(EFFECTS)
            try:
                try:
                    obj = ep.load()
                except Exception as exc:
                    frame = _last_user_frame(exc, set())
                    at = f" at {frame.filename}, line {frame.lineno}" if frame else ""
                    raise UserEffectError(f"cannot import it: {type(exc).__name__}: {exc}{at}") from None
                added, replaced = _registered_since(before)
                if inspect.isclass(obj):
                    classes = [EFFECTS[n] for n in added + replaced if EFFECTS[n] is not obj] + [obj]
                    module_file = inspect.getsourcefile(obj) if obj.__module__ in sys.modules else None
                elif inspect.ismodule(obj):
                    classes = [EFFECTS[n] for n in added + replaced]
                    classes += [
                        c
                        for c in EFFECTS.values()
                        if c.__module__ == obj.__name__ and c not in classes and not _is_magcal_module(c.__module__)
                    ]
                    module_file = getattr(obj, "__file__", None)
                    if not classes:
                        raise UserEffectError(
                            "the module registers no effect (decorate its Effect classes with @register)"
                        )
                else:
                    raise UserEffectError(f"it names {obj!r}, which is neither an Effect subclass nor a module")
                if module_file:
                    _USER_FILES.add(os.path.abspath(module_file))
                names += _admit(classes, before, f"entry point {text}", "entry point", text)
            except Exception as exc:
                _restore(before)
                names.notes.append(Note(f"skipped the effect entry point {text}: {exc}", UserWarning, "plugins"))
        return names


def unregister(name: str) -> None:
    """Remove a user's effect from the catalogue (a built-in cannot be removed).

    Raises
    ------
    MagcalError
        For a built-in or an unknown name.
    """
    with _LOCK:
        if name not in EFFECTS:
            raise MagcalError(f"no effect {name!r} in the catalogue")
        if is_builtin(name):
            raise MagcalError(f"{name!r} is a built-in effect; only a user's effect can be removed")
        EFFECTS.pop(name)
        _ORIGINS.pop(name, None)
        _SOURCES.pop(name, None)


# ----------------------------------------------------------------------------------------------------------------
# helping the user when an effect is not loaded, or when their code fails later
# ----------------------------------------------------------------------------------------------------------------


def calibration_effect_names(path) -> list[str]:
    """The effect names a calibration JSON file uses (``[]`` if it cannot be read: its loader then says why)."""
    if not_regular_reason(path) is not None:
        return []  # a FIFO would block here: the loader refuses it with its message
    try:
        with open(os.fspath(path), "rb") as fh:
            doc = json.loads(fh.read().decode("utf-8"))
    except (OSError, ValueError, RecursionError):
        return []
    if not isinstance(doc, dict):
        return []
    names = []
    entries, terms = doc.get("effect_params"), doc.get("effects")
    for entry in entries if isinstance(entries, list) else []:  # another type: the loader says what is wrong
        if isinstance(entry, dict) and isinstance(entry.get("effect"), str):
            names.append(entry["effect"])
    for term in terms if isinstance(terms, list) else []:
        if isinstance(term, str):
            names.append(term.partition(":")[0])
    return list(dict.fromkeys(names))


def check_calibration_effects(path, option: str = "--effects-file FILE.py") -> None:
    """Refuse a calibration file that names an effect not in the catalogue, saying which and how to load it.

    Raises
    ------
    MagcalError
        ``CAL.json uses the effect 'pump_interference', which is not loaded ...``.
    """
    missing = [n for n in calibration_effect_names(path) if n not in EFFECTS and n not in BASE_TERMS]
    if missing:
        which = ", ".join(repr(n) for n in missing)
        plural = "s" if len(missing) > 1 else ""
        raise MagcalError(
            f"{os.fspath(path)}: the calibration uses the effect{plural} {which}, not built into magcal "
            f"and not loaded: it is a user's own effect; give the file that defines it with {option} "
            "(the same file used to calibrate), or install the package that provides it"
        )


def user_code_error(exc: BaseException) -> str | None:
    """A one-paragraph message if ``exc`` was raised inside a user's effect file, else ``None``.

    Used by the command line so that a bug in a user's effect during a fit is reported as the file, the line and
    the error, without a traceback.
    """
    if not isinstance(exc, Exception) or not _USER_FILES:
        return None
    frames = traceback.extract_tb(exc.__traceback__)
    for frame in reversed(frames):
        if os.path.abspath(frame.filename) in _USER_FILES:
            code = f"\n    {frame.line.strip()}" if frame.line else ""
            return (
                f"{frame.filename}, line {frame.lineno}, in {frame.name}: {type(exc).__name__}: {exc}{code}\n"
                f"  the error is in your effect's code, not in magcal; correct it and run again ({DOC})"
            )
    return None


# ----------------------------------------------------------------------------------------------------------------
# describing the catalogue
# ----------------------------------------------------------------------------------------------------------------

_UNIT_START = {
    "nT",
    "uT",
    "pT",
    "mT",
    "G",
    "mG",
    "ppm",
    "ppb",
    "percent",
    "ms",
    "us",
    "s",
    "h",
    "deg",
    "rad",
    "mrad",
    "urad",
    "Hz",
    "m",
    "K",
    "degC",
    "LSB",
}


def split_param_name(name: str) -> tuple[str, str]:
    """``("beta_x", "nT/K")`` from ``"beta_x_nT_per_K"``: the unit is the tail of the name from its first unit
    word (``_per_`` read as ``/``); ``(name, "")`` when the name carries no unit."""
    parts = name.split("_")
    for i in range(1, len(parts)):
        if parts[i] in _UNIT_START:
            return "_".join(parts[:i]), "_".join(parts[i:]).replace("_per_", "/").replace("_", " ")
    return name, ""


def describe_effect(name: str) -> dict:
    """A JSON-ready description of one catalogue effect (the ``magcal effects`` listing and the workbench).

    Returns
    -------
    dict
        ``name``, ``stage``, ``channels``, ``per_sensor``, ``min_sensors``, ``description``, ``doc`` (the class
        docstring), ``params`` (list of ``{"name", "symbol", "unit", "scale"}``; ``scale`` the size that moves
        the readings by about 1 nT), ``transferable`` (:attr:`magcal.model.terms.Effect.transferable`: True for an
        instrument term that carries to new data, False for a record-only term; None only for a class that
        overrides it with something else),
        ``simulator`` (whether it can be hidden in simulated data), ``origin`` (``built-in``, ``file``,
        ``entry point``, ``python``) and ``source``.
    """
    cls = EFFECTS[name]
    kind, where = origin(name)
    params, error = [], None
    try:
        inst = cls()
        names = list(inst.param_names())
        scales = np.asarray(inst.param_scale(), dtype=float).tolist()
        for p, sc in zip(names, scales):
            symbol, unit = split_param_name(p)
            params.append({"name": p, "symbol": symbol, "unit": unit, "scale": sc})
    except Exception as exc:  # shown, not raised: the listing must always work
        error = f"{type(exc).__name__}: {exc}"
    transferable = getattr(cls, "transferable", None)
    simulator = getattr(cls, "perturbation", None) is not Effect.perturbation
    if not simulator:  # the base method may delegate to the simulator's own table of perturbations
        try:
            simulator = callable(cls().perturbation(None))
        except Exception:
            simulator = False
    doc = inspect.getdoc(cls) or ""
    if doc == inspect.getdoc(Effect):
        doc = ""
    out = {
        "name": name,
        "stage": cls.stage,
        "channels": list(cls.channels),
        "per_sensor": bool(cls.per_sensor),
        "min_sensors": int(cls.min_sensors),
        "description": cls.description or (doc.splitlines()[0] if doc else ""),
        "doc": doc,
        "params": params,
        "transferable": transferable if isinstance(transferable, bool) else None,
        "simulator": bool(simulator),
        "origin": kind,
        "source": where,
    }
    if error:
        out["error"] = error
    return out


def catalogue() -> list[dict]:
    """:func:`describe_effect` of every effect in the catalogue: built-ins first (in registration order), then
    the user's."""
    names = list(EFFECTS)
    names.sort(key=lambda n: 0 if is_builtin(n) else 1)
    return [describe_effect(n) for n in names]
