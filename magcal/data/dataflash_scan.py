"""An ArduPilot DataFlash log's messages found and decoded with NumPy, column by column, without a Python object
per message.

A DataFlash log is a stream of messages ``A3 95 TYPE payload``, each type's length, field types and column names
given by an FMT message (type 128). pymavlink's ``DFReader`` walks it message by message, making a Python object of
each (233 s for a log of 1.2 million MAG messages on the 2-core development machine,
``benchmarks/dataflash_read.py``). Here the walk is pymavlink's own,
done on arrays: every place the two sync bytes and a known type meet is a candidate; from the file's first
candidate, each message is followed by the first candidate at or after its end (pymavlink skips bytes one by one
until it finds one, so a damaged stretch is passed over the same way), and the walk ends at a message cut by the
file's end. Each type's messages are then decoded as a NumPy structured array, their values as pymavlink gives
them (its multipliers applied by the same division, text cut at its first NUL).

:func:`scan` gives up (returns None) wherever it could differ from pymavlink, which then reads the log: a type
defined twice with different formats, an FMT message found outside the walk, a field type it does not decode
(``a``, arrays of int16). The reader (:func:`magcal.data.logs.read_dataflash`) uses it for the messages it keeps.
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass

import numpy as np

#: The two bytes every message starts with.
SYNC = b"\xa3\x95"
FMT_TYPE = 0x80
FMT_LENGTH = 89
_FMT_RE = re.compile(rb"\xa3\x95\x80")

#: Field types as NumPy types (little-endian), with pymavlink's multiplier (None: none) and whether the value is
#: text (pymavlink's ``FORMAT_TO_STRUCT``). ``a`` (an array of 32 int16) is not decoded here.
FIELD_TYPES = {
    "b": ("i1", None),
    "B": ("u1", None),
    "h": ("<i2", None),
    "H": ("<u2", None),
    "i": ("<i4", None),
    "I": ("<u4", None),
    "q": ("<i8", None),
    "Q": ("<u8", None),
    "f": ("<f4", None),
    "d": ("<f8", None),
    "g": ("<f2", None),
    "M": ("i1", None),
    "c": ("<i2", 0.01),
    "C": ("<u2", 0.01),
    "e": ("<i4", 0.01),
    "E": ("<u4", 0.01),
    "L": ("<i4", 1e-7),
    "n": ("S4", None),
    "N": ("S16", None),
    "Z": ("S64", None),
}
#: Rows gathered at a time while decoding (the gather's index takes 8 bytes a payload byte).
BLOCK_ROWS = 65_536


@dataclass(frozen=True)
class Format:
    """One message type's format (an FMT message)."""

    type: int
    name: str
    length: int
    fields: str
    columns: tuple


@dataclass
class Scan:
    """The messages of a log along pymavlink's walk.

    Attributes
    ----------
    data : numpy.ndarray of uint8
        The file's bytes.
    formats : dict
        Type number -> :class:`Format`.
    starts : numpy.ndarray of int64
        Each message's first byte (its sync bytes), in the file's order.
    types : numpy.ndarray of uint8
        Each message's type.
    """

    data: np.ndarray
    formats: dict
    starts: np.ndarray
    types: np.ndarray

    def of(self, name: str) -> np.ndarray:
        """Indices (into :attr:`starts`) of the messages named ``name``."""
        numbers = [t for t, f in self.formats.items() if f.name == name]
        return np.flatnonzero(np.isin(self.types, numbers)) if numbers else np.array([], dtype=np.int64)

    def columns(self, name: str, rows: np.ndarray) -> dict | None:
        """The messages ``rows`` (all of type ``name``) as ``{column: values}``, values as pymavlink gives them:
        numbers as float64 or int64 (multiplied), text as Python ``str``; None where a field is not decoded here."""
        named = [f for f in self.formats.values() if f.name == name]
        dtype = _dtype(named[0]) if len(named) == 1 else None
        if dtype is None:
            return None
        (fmt,) = named
        size = fmt.length - 3
        out = np.empty(len(rows), dtype=dtype)
        offsets = self.starts[rows] + 3
        for lo in range(0, len(rows), BLOCK_ROWS):
            block = offsets[lo : lo + BLOCK_ROWS]
            raw = self.data[block[:, None] + np.arange(size)]
            out[lo : lo + len(block)] = np.ascontiguousarray(raw).view(dtype).reshape(len(block))
        return {col: _values(out[col], code) for col, code in zip(fmt.columns, fmt.fields)}


def _dtype(fmt: Format):
    if any(c not in FIELD_TYPES for c in fmt.fields) or len(set(fmt.columns)) != len(fmt.columns):
        return None
    if not all(fmt.columns):
        return None  # a column without a name (a damaged FMT): NumPy would name it f0
    if len(fmt.columns) != len(fmt.fields):
        return None
    dtype = np.dtype([(col, FIELD_TYPES[c][0]) for col, c in zip(fmt.columns, fmt.fields)])
    return dtype if dtype.itemsize == fmt.length - 3 else None


def _values(values: np.ndarray, code: str) -> np.ndarray:
    """A field's values as pymavlink gives them: its multiplier applied as pymavlink does (dividing by its inverse,
    the more accurate for 0.01 and 1e-7), floats widened, text decoded and cut at its first NUL."""
    kind, mult = FIELD_TYPES[code]
    if kind.startswith("S"):
        return np.array([_text(v) for v in values.tolist()], dtype=object)
    if mult is not None:
        return values.astype(np.float64) / (1 / mult)
    if values.dtype.kind == "f":
        return values.astype(np.float64)
    return values.astype(np.int64) if values.dtype != np.uint64 else values


def _text(raw: bytes) -> str:
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        text = raw.decode("ISO-8859-1")
    return text.split("\0", 1)[0]


def _c_string(raw: bytes) -> str | None:
    text = raw.split(b"\0", 1)[0]
    if not all(32 <= b < 127 for b in text):
        return None
    return text.decode("ascii")


def formats(data) -> dict | None:
    """The formats of every FMT message in ``data`` (the sync bytes, type 128, a printable name, format and
    columns): type -> :class:`Format`; None where a type is defined twice differently."""
    found: dict = {}
    for match in _FMT_RE.finditer(data):
        body = bytes(data[match.start() + 3 : match.start() + FMT_LENGTH])
        if len(body) < FMT_LENGTH - 3:
            break
        ftype, length, name, fields, columns = struct.unpack("<BB4s16s64s", body)
        name, fields, columns = _c_string(name), _c_string(fields), _c_string(columns)
        if not name or fields is None or columns is None:
            continue
        fmt = Format(ftype, name, length, fields, tuple(columns.split(",")) if columns else ())
        if found.setdefault(ftype, fmt) != fmt:
            return None
    return found


def _walk(nxt: np.ndarray) -> np.ndarray:
    """The candidates visited from the first: each followed by ``nxt`` of it, until past the last. Runs of
    candidates each followed by the next are taken whole; only the jumps (past a candidate inside a message, or a
    damaged stretch) are followed one by one."""
    n = len(nxt)
    jumps = np.flatnonzero(nxt != np.arange(1, n + 1))
    follow = nxt.tolist()
    runs = []
    i = 0
    while i < n:
        at = int(np.searchsorted(jumps, i))
        last = int(jumps[at]) if at < len(jumps) else n - 1  # the run from i ends at its first jump
        runs.append(np.arange(i, last + 1))
        i = follow[last]
    return np.concatenate(runs) if runs else np.zeros(0, dtype=np.int64)


def scan(path_or_bytes) -> Scan | None:
    """The log's messages along pymavlink's walk (module docstring), or None where the walk could differ from
    pymavlink's: no format, a type defined twice differently, a type's FMT message not on the walk, a length below
    the header."""
    if isinstance(path_or_bytes, (bytes, bytearray, memoryview)):
        data = np.frombuffer(path_or_bytes, dtype=np.uint8)
    else:
        data = np.fromfile(path_or_bytes, dtype=np.uint8)
    found = formats(data.data)
    if not found or FMT_TYPE not in found or any(_payload_bytes(f) != f.length - 3 for f in found.values()):
        return None  # pymavlink reads a message whose fields do not fill its length otherwise (from inside it)
    lengths = np.zeros(256, dtype=np.int64)
    for f in found.values():
        lengths[f.type] = f.length
    sync = np.flatnonzero((data[:-2] == 0xA3) & (data[1:-1] == 0x95))
    types = data[sync + 2]
    known = lengths[types] > 0
    starts, types = sync[known], types[known]
    ends = starts + lengths[types]
    visited = _walk(np.searchsorted(starts, ends))
    starts, types, ends = starts[visited], types[visited], ends[visited]
    cut = np.flatnonzero(ends > len(data))  # a message cut by the file's end ends the reading
    if cut.size:
        starts, types = starts[: cut[0]], types[: cut[0]]
    out = Scan(data, found, starts, types)
    # every format in force was read on the walk (pymavlink learns them there)
    fmt = out.columns("FMT", np.flatnonzero(types == FMT_TYPE))
    if fmt is None or "Type" not in fmt:
        return None  # a damaged FMT that names other columns: its types cannot be learned here
    return out if {int(t) for t in fmt["Type"]} == set(found) else None


def _payload_bytes(fmt: Format) -> int:
    """The bytes a format's fields take (pymavlink's struct; ``a``: 64), -1 for a field type no reader knows."""
    sizes = {c: np.dtype(kind).itemsize for c, (kind, _) in FIELD_TYPES.items()} | {"a": 64}
    return sum(sizes[c] for c in fmt.fields) if all(c in sizes for c in fmt.fields) else -1
