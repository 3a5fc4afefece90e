"""The one reader of ``session.json``: every field checked for type and range before a session is reopened.

A file is read in bounded memory: at most :data:`MAX_BYTES`, and at most :data:`MAX_VALUES` JSON values counted
before it is decoded (:func:`json_values`); the rows over a history's bound are dropped unread, with a note.

A session file is written by the workbench, but it sits on disk where a crash, a full disk, a hand edit or a
copied folder can damage it, and its text reaches the page. :func:`read_session_document` turns a decoded JSON
document into a :class:`~magcal_workbench.state.SessionState` or raises :class:`SessionFileError` -- one line naming the
file, the field and what is wrong -- and nothing else: no ``KeyError``, ``TypeError`` or ``binascii.Error`` from
a damaged file escapes. :func:`read_session_bytes` does the same from the file's bytes (not JSON, not UTF-8, too
large). The caller (:class:`~magcal_workbench.session.SessionStore`, the workbench at start) then moves the folder aside
and starts afresh.

The fields (all written by :meth:`SessionState.to_dict`):

==================  =========================================================================================
``format``          ``"magcal-workbench-session"``
``version``         1
``n_samples``       whole number 1 ... 10^8; ``n_sensors`` whole number 1 ... 4
``data_path``       text or null; ``lesson`` a lesson's slug or null
``selection``       ``{"n_samples": N, "kept": packed mask of N bits, "undo"/"redo": [[mask, text], ...]}`` (the
                    most recent undo and redo masks within ``MAX_MASK_SAMPLES`` read, the older dropped with a
                    note)
``effects``         list of effect labels ``NAME`` or ``NAME:S`` (S = 1 ... n_sensors), no repeats
``effects_files``   list of absolute paths of ``.py`` files (the user's effects; never run on opening, offered)
``method``          one of :data:`~magcal_workbench.state.METHODS`
``reference_nT``    number 1 ... 10^7 nT, or null
``fit_reference``, ``robust``, ``answer_revealed``: true or false
``noise_nT``        the noise per axis the user gave, number 1e-6 ... 10^6 nT, or null (estimated)
``sensor``          whole number 0 ... n_sensors - 1, or null
``history``         list of steps ``{"step", "rms_nT", "floor_nT", "effects", "n_kept", "changes", "elapsed_s",
                    "fit", "held_out_rms_nT"}`` (numbers finite, ``n_kept`` 0 ... N; ``held_out_rms_nT`` null
                    when the step ran no held-out validation); the last ``MAX_HISTORY_ROWS`` (1000) are read,
                    the older dropped with a note (``SessionState.notes``)
``location``        the place typed for IGRF ``{"lat_deg": -90 ... 90, "lon_deg": -180 ... 180, "alt_m": -10^4 ...
                    2 10^6, "date": text of at most 32 characters}``, or null
``vector_fit``      the last vector fit's settings ``{"kept": packed mask of N bits, "robust": true or false,
                    "noise_nT": number 1e-6 ... 10^6 or null, "effects": list of effect labels}`` (run again when
                    the session reopens), or null
``vector_history``  list of the vector model's fits ``{"step", "world_rms_nT": [N, E, D], "total_rms_nT",
                    "effects", "n_fitted", "changes", "elapsed_s"}`` (numbers finite or null, ``n_fitted`` 0 ... N;
                    the last 1000 read, as ``history``)
``gravity_fit``     the last gravity fit's settings ``{"kept": packed mask of N bits, "robust": true or false}`` (run
                    again when the session reopens), or null; absent in a session saved before the gravity fit was
                    kept (read as null)
``calibration``     an object (checked by :meth:`magcal.calibration.calibration.Calibration.from_dict` when restored) or null
==================  =========================================================================================

and ``compensation_fit``: the last compensation ``{"kept": packed mask of N bits, "effects": terms beyond
Tolles-Lawson, "history": [{"step", "effects", "fom_before_nT", "fom_nT", "improvement_ratio", "n_fitted",
"elapsed_s"}]}`` (run again when the session reopens), or null; absent in a session saved before it was kept (read
as null).
"""

from __future__ import annotations

import base64
import binascii
import json
import math
import re

import numpy as np

from magcal.core.errors import MagcalError
from magcal.fitting.compensation import COMPENSATION_EFFECTS

from .markup import clean_text
from .state import (
    MAX_HISTORY_ROWS,
    METHODS,
    Selection,
    SessionState,
    StepRecord,
    VectorStep,
    saved_masks,
    trimmed,
)

FORMAT = "magcal-workbench-session"
VERSION = 1
#: Largest session file read, bytes (a session of 10^8 samples with its undo masks is far smaller).
MAX_BYTES = 256 * 1024 * 1024
MAX_SAMPLES = 10**8
MAX_SENSORS = 4
#: Longest text field kept (a step's description, a path), characters.
MAX_TEXT = 10_000
MAX_HISTORY = 100_000
MAX_UNDO = 200
#: Most JSON values (numbers, texts, lists, objects) a session file may hold, counted before it is decoded: each
#: is a Python object once decoded (about 60 bytes), so that a file within :data:`MAX_BYTES` stays within about
#: 100 MB read. A session within its bounds (:data:`~magcal_workbench.state.MAX_HISTORY_ROWS` steps of each history,
#: some twenty values each; masks are one text each) holds some tens of thousands.
MAX_VALUES = 1_000_000
#: Reference field range accepted, nT (well beyond any geomagnetic or laboratory field).
REFERENCE_RANGE_nT = (1.0, 1e7)
#: Range of a noise level the user gives (``noise_nT``: per-axis standard deviation), nT.
NOISE_RANGE_nT = (1e-6, 1e6)
#: What the page's location inputs (the IGRF reference) may hold: latitude and longitude (deg), altitude above the
#: WGS84 ellipsoid (m; IGRF is defined from 10 km below it to 2000 km above), the date's length (characters).
LAT_RANGE_DEG = (-90.0, 90.0)
LON_RANGE_DEG = (-180.0, 180.0)
ALT_RANGE_M = (-10_000.0, 2_000_000.0)
DATE_CHARS = 32

#: The numbers of a compensation history's row (``CompensationSession.history``), each finite and at least 0, or
#: null.
COMPENSATION_STEP_NUMBERS = ("fom_before_nT", "fom_nT", "improvement_ratio", "n_fitted", "elapsed_s")

LABEL = re.compile(r"^[a-z][a-z0-9_]{0,63}(?::([0-9]{1,2}))?$")
SLUG = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")


class SessionError(MagcalError):
    """A session cannot be opened: a name outside the session folder, or a damaged file."""


class SessionFileError(SessionError):
    """``session.json`` is damaged: the message names the file and the field, on one line.

    Attributes
    ----------
    where : str
        The file (or a description of the document).
    field : str
        The field, as a path: ``selection.kept``, ``history[3].rms_nT``.
    problem : str
        What is wrong with it.
    """

    def __init__(self, where: str, field: str, problem: str):
        self.where, self.field, self.problem = where, field, problem
        super().__init__(clean_text(f"{where}: field {field!r}: {problem}", 400))


def _show(value) -> str:
    """A short picture of a bad value for the message."""
    if isinstance(value, (dict, list)):
        return f"{type(value).__name__} of {len(value)}"
    return clean_text(repr(value), 40)


def _kind(value) -> str:
    return {
        bool: "true/false",
        int: "a whole number",
        float: "a number",
        str: "text",
        list: "a list",
        dict: "an object",
        type(None): "null",
    }.get(type(value), type(value).__name__)


class _Reader:
    """Checks one document; every check raises :class:`SessionFileError` naming the field."""

    def __init__(self, where: str):
        self.where = where
        #: What reading dropped (rows and masks over the bounds), to say once the session is open.
        self.notes: list[str] = []

    def rows(self, field, value, read_row):
        """The rows of a history list, read by ``read_row(field, row)``: the last
        :data:`~magcal_workbench.state.MAX_HISTORY_ROWS` (the older ones dropped, unread, with a note)."""
        rows = list(self.listing(field, value, MAX_HISTORY))
        first = len(rows) - MAX_HISTORY_ROWS
        self.notes += filter(None, [trimmed(rows, field.replace("_", " "))])
        return [read_row(f"{field}[{max(first, 0) + i}]", row) for i, row in enumerate(rows)]

    def fail(self, field: str, problem: str):
        raise SessionFileError(self.where, field, problem)

    def wrong(self, field: str, value, wanted: str):
        self.fail(field, f"must be {wanted}, got {_kind(value)} {_show(value)}")

    # --- scalar checks ----------------------------------------------------------------------------------------
    def integer(self, field, value, lo, hi):
        if type(value) is not int:
            self.wrong(field, value, f"a whole number {lo} ... {hi}")
        if not lo <= value <= hi:
            self.fail(field, f"{value} is outside {lo} ... {hi}")
        return value

    def number(self, field, value, lo=-math.inf, hi=math.inf, null=False):
        if value is None and null:
            return None
        if type(value) not in (int, float):
            self.wrong(field, value, "a number" + (" or null" if null else ""))
        v = float(value)
        if not math.isfinite(v):
            self.fail(field, f"must be a finite number, got {value!r}")
        if not lo <= v <= hi:
            self.fail(field, f"{v:g} is outside {lo:g} ... {hi:g}")
        return v

    def boolean(self, field, value):
        if type(value) is not bool:
            self.wrong(field, value, "true or false")
        return value

    def text(self, field, value, null=False, max_len=MAX_TEXT):
        if value is None and null:
            return None
        if type(value) is not str:
            self.wrong(field, value, "text" + (" or null" if null else ""))
        if len(value) > max_len:
            self.fail(field, f"is {len(value)} characters long; at most {max_len}")
        if "\x00" in value:
            self.fail(field, "holds a NUL character")
        return value

    def listing(self, field, value, max_len):
        if type(value) is not list:
            self.wrong(field, value, "a list")
        if len(value) > max_len:
            self.fail(field, f"holds {len(value)} entries; at most {max_len}")
        return value

    def obj(self, field, value):
        if type(value) is not dict:
            self.wrong(field, value, "an object")
        return value

    # --- composite checks -------------------------------------------------------------------------------------
    def mask(self, field, value, n):
        self.text(field, value, max_len=MAX_SAMPLES // 4)
        try:
            raw = base64.b64decode(value.encode("ascii"), validate=True)
        except (binascii.Error, ValueError, UnicodeEncodeError):
            self.fail(field, "is not a packed sample mask (base64 text)")
        if len(raw) != (n + 7) // 8:
            self.fail(field, f"holds {8 * len(raw)} bits, expected a mask of {n} samples")
        return np.unpackbits(np.frombuffer(raw, dtype=np.uint8))[:n].astype(bool)

    def labels(self, field, value, n_sensors):
        self.listing(field, value, 1000)
        out = []
        for i, label in enumerate(value):
            f = f"{field}[{i}]"
            self.text(f, label, max_len=80)
            m = LABEL.fullmatch(label)
            if not m:
                self.fail(f, f"{_show(label)} is not an effect label NAME or NAME:SENSOR (lower-case name)")
            if m.group(1) is not None and not 1 <= int(m.group(1)) <= n_sensors:
                self.fail(f, f"sensor {m.group(1)} is outside 1 ... {n_sensors}")
            out.append(label)
        return out

    def step(self, field, value, n_samples, n_sensors):
        doc = self.obj(field, value)
        if "step" not in doc or "rms_nT" not in doc:
            self.fail(field, "a step needs 'step' and 'rms_nT'")
        fit = doc.get("fit")
        if fit is not None:
            self.obj(f"{field}.fit", fit)
            fit = {}
            for key, check in (
                ("success", lambda f, v: self.boolean(f, v)),
                ("status", lambda f, v: self.integer(f, v, -1000, 1000)),
                ("message", lambda f, v: self.text(f, v, null=True)),
                ("nfev", lambda f, v: self.integer(f, v, 0, 10**12)),
            ):
                if key in doc["fit"]:
                    fit[key] = check(f"{field}.fit.{key}", doc["fit"][key])
        return StepRecord(
            step=self.text(f"{field}.step", doc["step"]),
            rms_nT=self.number(f"{field}.rms_nT", doc["rms_nT"], 0.0, null=True),
            floor_nT=self.number(f"{field}.floor_nT", doc.get("floor_nT"), 0.0, null=True),
            effects=self.labels(f"{field}.effects", doc.get("effects", []), n_sensors),
            n_kept=self.integer(f"{field}.n_kept", doc.get("n_kept", 0), 0, n_samples),
            changes=self.text(f"{field}.changes", doc.get("changes", "")),
            elapsed_s=self.number(f"{field}.elapsed_s", doc.get("elapsed_s", 0.0), 0.0),
            fit=fit,
            held_out_rms_nT=self.number(f"{field}.held_out_rms_nT", doc.get("held_out_rms_nT"), 0.0, null=True),
        )

    def location(self, field, value):
        """The place typed for IGRF, or None (the ranges of :mod:`magcal_workbench.vectormodel`)."""
        if value is None:
            return None
        doc = self.obj(field, value)
        unknown = set(doc) - {"lat_deg", "lon_deg", "alt_m", "date"}
        if unknown:
            self.fail(field, f"holds unknown key(s) {_show(sorted(unknown))}")
        for key in ("lat_deg", "lon_deg", "alt_m", "date"):
            if key not in doc:
                self.fail(f"{field}.{key}", "is missing")
        return {
            "lat_deg": self.number(f"{field}.lat_deg", doc["lat_deg"], *LAT_RANGE_DEG),
            "lon_deg": self.number(f"{field}.lon_deg", doc["lon_deg"], *LON_RANGE_DEG),
            "alt_m": self.number(f"{field}.alt_m", doc["alt_m"], *ALT_RANGE_M),
            "date": self.text(f"{field}.date", doc["date"], max_len=DATE_CHARS),
        }

    def vector_fit(self, field, value, n, n_sensors):
        """The last vector fit's settings, or None (:attr:`SessionState.vector_fit`)."""
        if value is None:
            return None
        doc = self.obj(field, value)
        unknown = set(doc) - {"kept", "robust", "noise_nT", "effects"}
        if unknown:
            self.fail(field, f"holds unknown key(s) {_show(sorted(unknown))}")
        if "kept" not in doc:
            self.fail(f"{field}.kept", "is missing")
        self.mask(f"{field}.kept", doc["kept"], n)  # checked here, unpacked when the fit runs again
        effects = self.labels(f"{field}.effects", doc.get("effects", []), n_sensors)
        if len(set(effects)) != len(effects):
            self.fail(f"{field}.effects", "names an effect twice")
        return {
            "kept": doc["kept"],
            "robust": self.boolean(f"{field}.robust", doc.get("robust", False)),
            "noise_nT": self.number(f"{field}.noise_nT", doc.get("noise_nT"), *NOISE_RANGE_nT, null=True),
            "effects": effects,
        }

    def gravity_fit(self, field, value, n):
        """The last gravity fit's settings, or None (:attr:`SessionState.gravity_fit`)."""
        if value is None:
            return None
        doc = self.obj(field, value)
        unknown = set(doc) - {"kept", "robust"}
        if unknown:
            self.fail(field, f"holds unknown key(s) {_show(sorted(unknown))}")
        if "kept" not in doc:
            self.fail(f"{field}.kept", "is missing")
        self.mask(f"{field}.kept", doc["kept"], n)  # checked here, unpacked when the fit runs again
        return {"kept": doc["kept"], "robust": self.boolean(f"{field}.robust", doc.get("robust", False))}

    def compensation_fit(self, field, value, n):
        """The last compensation's settings, or None (:attr:`SessionState.compensation_fit`): the samples, the terms
        beyond Tolles-Lawson (each a known one), the FOM history's rows (numbers or null)."""
        if value is None:
            return None
        doc = self.obj(field, value)
        unknown = set(doc) - {"kept", "effects", "current_columns", "history"}
        if unknown:
            self.fail(field, f"holds unknown key(s) {_show(sorted(unknown))}")
        if "kept" not in doc:
            self.fail(f"{field}.kept", "is missing")
        self.mask(f"{field}.kept", doc["kept"], n)
        effects = self.compensation_terms(f"{field}.effects", doc.get("effects", []))
        columns = self.current_columns(f"{field}.current_columns", doc.get("current_columns", []))
        history = self.rows(f"{field}.history", doc.get("history", []), self.compensation_step)
        return {"kept": doc["kept"], "effects": effects, "current_columns": columns, "history": history}

    def current_columns(self, field, value):
        """The current columns the compensation's current term takes (a session file of before names none: the
        engine's first column)."""
        columns = [self.text(f"{field}[{i}]", v, max_len=200) for i, v in enumerate(self.listing(field, value, 16))]
        if len(set(columns)) != len(columns):
            self.fail(field, "names a column twice")
        return columns

    def compensation_terms(self, field, value):
        """Terms beyond Tolles-Lawson, each one of :data:`magcal.fitting.compensation.COMPENSATION_EFFECTS`."""
        names = [self.text(f"{field}[{i}]", v, max_len=40) for i, v in enumerate(self.listing(field, value, 16))]
        for i, name in enumerate(names):
            if name not in COMPENSATION_EFFECTS:
                self.fail(f"{field}[{i}]", f"{_show(name)} is not one of {', '.join(COMPENSATION_EFFECTS)}")
        if len(set(names)) != len(names):
            self.fail(field, "names a term twice")
        return names

    def compensation_step(self, field, value):
        """One row of the compensation's history (its step, terms and FOM figures)."""
        doc = self.obj(field, value)
        unknown = set(doc) - set(COMPENSATION_STEP_NUMBERS) - {"step", "effects", "current_columns"}
        if unknown:
            self.fail(field, f"holds unknown key(s) {_show(sorted(unknown))}")
        row = {
            "step": self.text(f"{field}.step", doc.get("step", "")),
            "effects": self.compensation_terms(f"{field}.effects", doc.get("effects", [])),
            "current_columns": self.current_columns(f"{field}.current_columns", doc.get("current_columns", [])),
        }
        for key in COMPENSATION_STEP_NUMBERS:
            row[key] = self.number(f"{field}.{key}", doc.get(key), 0.0, math.inf, null=True)
        return row

    def vector_step(self, field, value, n_samples, n_sensors):
        """One fit of the vector model's history (:class:`~magcal_workbench.state.VectorStep`)."""
        doc = self.obj(field, value)
        for key in ("step", "world_rms_nT"):
            if key not in doc:
                self.fail(f"{field}.{key}", "is missing")
        world = self.listing(f"{field}.world_rms_nT", doc["world_rms_nT"], 3)
        if len(world) != 3:
            self.fail(f"{field}.world_rms_nT", f"holds {len(world)} numbers; three (north, east, down)")
        return VectorStep(
            step=self.text(f"{field}.step", doc["step"]),
            world_rms_nT=[self.number(f"{field}.world_rms_nT[{k}]", v, 0.0, null=True) for k, v in enumerate(world)],
            total_rms_nT=self.number(f"{field}.total_rms_nT", doc.get("total_rms_nT"), 0.0, null=True),
            effects=self.labels(f"{field}.effects", doc.get("effects", []), n_sensors),
            n_fitted=self.integer(f"{field}.n_fitted", doc.get("n_fitted", 0), 0, n_samples),
            changes=self.text(f"{field}.changes", doc.get("changes", "")),
            elapsed_s=self.number(f"{field}.elapsed_s", doc.get("elapsed_s", 0.0), 0.0),
        )

    def selection(self, field, value, n):
        doc = self.obj(field, value)
        if "kept" not in doc:
            self.fail(f"{field}.kept", "is missing")
        self.integer(f"{field}.n_samples", doc.get("n_samples"), n, n)
        sel = Selection(n, self.mask(f"{field}.kept", doc["kept"], n))
        for which in ("undo", "redo"):
            stack = []
            entries = self.listing(f"{field}.{which}", doc.get(which, []), MAX_UNDO)
            keep = saved_masks(n)
            if len(entries) > keep:  # the most recent within the masks' bound (MAX_MASK_SAMPLES)
                self.notes.append(
                    f"{which} keeps its last {keep} selection(s) of {n:,} samples: the oldest "
                    f"{len(entries) - keep} were dropped"
                )
            first = len(entries) - keep
            for i, entry in enumerate(entries):
                if i < first:
                    continue
                f = f"{field}.{which}[{i}]"
                if type(entry) is not list or len(entry) != 2:
                    self.wrong(f, entry, "a pair [mask, description]")
                stack.append((self.mask(f"{f}[0]", entry[0], n), self.text(f"{f}[1]", entry[1], max_len=500)))
            setattr(sel, f"_{which}", stack)
        return sel


def read_session_document(doc, where: str = "session.json"):
    """A :class:`~magcal_workbench.state.SessionState` from a decoded session document, every field checked.

    Parameters
    ----------
    doc : object
        What ``json.loads`` gave.
    where : str
        The file, for messages.

    Returns
    -------
    SessionState

    Raises
    ------
    SessionFileError
        On the first damaged field (its name, what is wrong): the only exception this function raises.
    """
    r = _Reader(where)
    if type(doc) is not dict:
        r.wrong("(document)", doc, "an object")
    if doc.get("format") != FORMAT:
        r.fail("format", f"must be {FORMAT!r}: this is not a workbench session file")
    r.integer("version", doc.get("version", VERSION), VERSION, VERSION)
    for key in ("n_samples", "n_sensors", "selection"):
        if key not in doc:
            r.fail(key, "is missing")
    n = r.integer("n_samples", doc["n_samples"], 1, MAX_SAMPLES)
    n_sensors = r.integer("n_sensors", doc["n_sensors"], 1, MAX_SENSORS)
    lesson = r.text("lesson", doc.get("lesson"), null=True, max_len=64)
    if lesson is not None and not SLUG.fullmatch(lesson):
        r.fail("lesson", f"{_show(lesson)} is not a lesson name")
    st = SessionState(n, n_sensors, r.text("data_path", doc.get("data_path"), null=True, max_len=4096), lesson)
    st.selection = r.selection("selection", doc["selection"], n)
    st.effects = r.labels("effects", doc.get("effects", []), n_sensors)
    if len(set(st.effects)) != len(st.effects):
        r.fail("effects", "names an effect twice")
    files = r.listing("effects_files", doc.get("effects_files", []), 100)
    for i, path in enumerate(files):
        r.text(f"effects_files[{i}]", path, max_len=4096)
        if not path.endswith(".py") or not (path.startswith("/") or re.match(r"^[A-Za-z]:[\\/]", path)):
            r.fail(f"effects_files[{i}]", f"{_show(path)} is not the absolute path of a .py file")
    st.effects_files = list(files)
    st.method = r.text("method", doc.get("method", "ml"), max_len=16)
    if st.method not in METHODS:
        r.fail("method", f"{_show(st.method)} is not one of {', '.join(METHODS)}")
    st.reference_nT = r.number("reference_nT", doc.get("reference_nT"), *REFERENCE_RANGE_nT, null=True)
    st.fit_reference = r.boolean("fit_reference", doc.get("fit_reference", False))
    st.robust = r.boolean("robust", doc.get("robust", False))
    st.answer_revealed = r.boolean("answer_revealed", doc.get("answer_revealed", False))
    st.noise_nT = r.number("noise_nT", doc.get("noise_nT"), *NOISE_RANGE_nT, null=True)
    sensor = doc.get("sensor")
    st.sensor = None if sensor is None else r.integer("sensor", sensor, 0, n_sensors - 1)
    st.history = r.rows("history", doc.get("history", []), lambda f, h: r.step(f, h, n, n_sensors))
    st.location = r.location("location", doc.get("location"))
    st.vector_fit = r.vector_fit("vector_fit", doc.get("vector_fit"), n, n_sensors)
    rows = r.rows("vector_history", doc.get("vector_history", []), lambda f, h: r.vector_step(f, h, n, n_sensors))
    st.vector_history = rows
    st.gravity_fit = r.gravity_fit("gravity_fit", doc.get("gravity_fit"), n)
    st.compensation_fit = r.compensation_fit("compensation_fit", doc.get("compensation_fit"), n)
    cal = doc.get("calibration")
    st.calibration = None if cal is None else r.obj("calibration", cal)
    st.notes = list(r.notes)
    saved_at = doc.get("saved_at")
    st.saved_at = clean_text(saved_at, 40) if isinstance(saved_at, str) else ""
    return st


def json_values(data: bytes) -> int:
    """At most how many JSON values ``data`` holds: its commas, brackets and braces (those inside texts too: the
    workbench's texts hold few), counted in C, in time linear in the bytes, before anything is decoded."""
    return data.count(b",") + data.count(b"[") + data.count(b"{")


def read_session_bytes(data: bytes, where: str = "session.json"):
    """:func:`read_session_document` of a file's bytes; undecodable bytes are a :class:`SessionFileError`."""
    if len(data) > MAX_BYTES:
        raise SessionFileError(where, "(file)", f"is {len(data)} bytes; at most {MAX_BYTES}")
    values = json_values(data)
    if values > MAX_VALUES:
        raise SessionFileError(
            where,
            "(file)",
            f"holds about {values:,} values, more than the {MAX_VALUES:,} a session is read with (it keeps the last "
            f"{MAX_HISTORY_ROWS:,} steps of each history)",
        )
    try:
        doc = json.loads(data.decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise SessionFileError(where, "(file)", f"is not UTF-8 text (byte {exc.start})") from None
    except json.JSONDecodeError as exc:
        raise SessionFileError(
            where, "(file)", f"is not JSON (line {exc.lineno}, column {exc.colno}: {exc.msg})"
        ) from None
    except (ValueError, RecursionError) as exc:
        raise SessionFileError(where, "(file)", f"is not JSON ({type(exc).__name__})") from None
    return read_session_document(doc, where)
