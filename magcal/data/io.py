"""Reading and writing magcal's CSV format (documented in ``docs/formats.md``).

The format: UTF-8 text, comma separated, one header row. Lines before the header that start with ``#`` carry
metadata as ``# key: value`` (``baseline_m``, ``reference_total_nT``, ``units``, ``lsb_nT``, ``noise_nT``; any other
key is kept as text in :attr:`Dataset.metadata`). Readings in raw sensor counts (``units: counts``) need the LSB in
nT per count (``lsb_nT``, or ``--lsb``). Columns ``s1x,s1y,s1z ... s4x,s4y,s4z`` (one to four sensors; bare
``x,y,z`` means one sensor), optional ``t`` (s), ``temp`` (degC), ``ref_total`` (nT), ``qw,qx,qy,qz`` (attitude,
array frame to world frame; all four empty or ``nan``: a sample without attitude), ``group`` (text). Any other column is kept in :attr:`Dataset.extra`.

The reader tells the truth about the file: every problem is a :class:`~magcal.data.dataset.DatasetError` naming the
file, the 1-based line number of the file and the column, and saying what to do; problems it can work around
(dropped rows, suspicious units) are :class:`~magcal.core.errors.DataWarning` notes in the dataset's ``notes``,
raised as warnings by :func:`read_csv` (the public reader) unless ``warn=False``. It never lets another exception
through for bad input.

Records are one line each: quoted fields (``"a,b"``) are understood, quoted line breaks are not. Lines end in LF
or CRLF (CRs piled before the LF, or ending the file, are part of the line end); a carriage return inside a line
(:func:`stray_cr`) and old Mac line ends (CR only) are refused, by every reader alike.
"""

from __future__ import annotations

import collections
import concurrent.futures
import contextlib
import csv
import itertools
import os
import re
import secrets
import stat
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from magcal.core import notes as _notes
from magcal.core.errors import DataWarning, MagcalError, exception_text
from magcal.core.files import check_regular_file, not_regular_reason
from magcal.core.memory import available_bytes
from magcal.core.notes import Note
from magcal.data.accelerometer import MAPPABLE_ACCEL_COLUMNS
from magcal.data.dataset import (
    BAD_VALUE_TEXT,
    MAX_ABS_VALUE,
    QUATERNION_COLUMNS,
    SENSOR_AXES,
    Dataset,
    DatasetError,
    bad_values,
    dataset_columns,
    dataset_metadata,
)
from magcal.data.logs import is_log, read_log
from magcal.data.site import SITE_EXAMPLE, SITE_FORM, SITE_KEYS, names_a_place, parse_site, site_metadata
from magcal.geometry.shape import field_magnitude_nT

#: Factor that turns a reading in each unit into nT (keys are lower case; ``u`` and ``µ`` both mean micro).
UNIT_FACTORS_nT = {
    "nt": 1.0,
    "ut": 1.0e3,
    "µt": 1.0e3,
    "μt": 1.0e3,
    "mt": 1.0e6,
    "t": 1.0e9,
    "g": 1.0e5,
    "mg": 1.0e2,
    "gauss": 1.0e5,
    "mgauss": 1.0e2,
    "gamma": 1.0,
}

#: The unit names shown to users, with their factor to nT.
UNIT_NAMES = {"nT": 1.0, "uT": 1.0e3, "G": 1.0e5, "mG": 1.0e2}

#: Unit names (lower case) meaning raw integer counts of the sensor; their factor is the LSB in nT per count.
COUNT_UNITS = ("counts", "count")

#: Range of the Earth's field at the surface, nT (used by the unit sanity check).
EARTH_FIELD_RANGE_nT = (20_000.0, 70_000.0)

#: Optional single columns: canonical name -> Dataset attribute.
CHANNEL_COLUMNS = {"t": "time_s", "temp": "temperature_C", "ref_total": "ref_total_nT"}
MAX_SENSORS = 4

#: Metadata keys the reader turns into numbers: key -> (Dataset attribute, must be > 0).
NUMERIC_METADATA = {
    "baseline_m": ("baseline_m", True),
    "reference_total_nT": ("reference_total_nT", True),
    "noise_nT": ("noise_nT", False),
}

_SENSOR_RE = re.compile(r"^s([1-9])([xyz])$")
_MAX_SHOWN = 5  # problems named in one message
#: The first bytes of a CSV every reader checks before reading it (:func:`check_csv_head`).
HEAD_PROBE_BYTES = 8192

#: Longest line of a CSV file (bytes, line end included): far beyond any row of readings and channels, and small
#: enough that a file of one endless line is refused before it fills the memory.
MAX_LINE_BYTES = 1 << 20
#: Most columns a CSV header (or a Parquet schema) may name: a million would make every block of rows huge.
MAX_COLUMNS = 1000
#: The first bytes (UTF-8) of every character ``str.isspace`` calls whitespace (tests check it against every code
#: point): a line beginning with none of them holds more than whitespace, so the CSV reader reads it as a row.
SPACE_LEAD_BYTES = b"\t\n\x0b\x0c\r\x1c\x1d\x1e\x1f \xc2\xe1\xe2\xe3"
_SPACE_LEAD = np.zeros(256, dtype=bool)
_SPACE_LEAD[list(SPACE_LEAD_BYTES)] = True
#: A line end followed by a line that may hold only whitespace (it begins with one of :data:`SPACE_LEAD_BYTES`).
_MAYBE_BLANK = re.compile(b"\n[" + re.escape(SPACE_LEAD_BYTES) + b"]")
#: Bytes read at a time when counting a CSV's rows (:meth:`CsvSource.count_rows`).
COUNT_BLOCK_BYTES = 1 << 24


#: Most characters of a value from a file that a message quotes (a cell, a column name, a metadata value), and most
#: column names it lists: a message stays one readable line whatever the file holds (five 5000-character cells
#: made one line of 25 000).
MAX_QUOTED_CHARS = 40
MAX_LISTED_NAMES = 12


def shown(value, limit=MAX_QUOTED_CHARS) -> str:
    """A value from a file as a message quotes it: ``repr`` of a text (of anything else), cut to ``limit``
    characters with its length said (``'99999...' (5,000 characters)``)."""
    text = value if isinstance(value, str) else repr(value)
    if len(text) <= limit:
        return repr(text) if isinstance(value, str) else text
    return f"{text[:limit]!r}... ({len(text):,} characters)"


def names_shown(names, limit=MAX_LISTED_NAMES) -> str:
    """Column names as a message lists them: the first ``limit``, each cut (:func:`shown`'s length), and how many
    more there are."""
    names = list(names)
    listed = ", ".join(n if len(n) <= MAX_QUOTED_CHARS else n[:MAX_QUOTED_CHARS] + "..." for n in names[:limit])
    return listed + (f" ... ({len(names):,} columns)" if len(names) > limit else "")


def canonical_columns(n_sensors=MAX_SENSORS):
    """All canonical column names for up to ``n_sensors`` sensors."""
    names = [f"s{i}{a}" for i in range(1, n_sensors + 1) for a in SENSOR_AXES]
    return names + list(CHANNEL_COLUMNS) + list(QUATERNION_COLUMNS) + ["group"]


def is_counts(units) -> bool:
    """True if ``units`` names raw sensor counts (``counts``)."""
    return units is not None and str(units).strip().lower() in COUNT_UNITS


#: The LSBs (nT per count) magcal reads raw counts with: from a femtotesla per count to a tesla per count, six
#: and four orders beyond any magnetometer's (a 24-bit fluxgate 0.01 nT, a MEMS part 100-1000 nT). An LSB outside
#: (1e308, 1e-300) made the readings infinite or zero and the fit fail with a library's error.
LSB_RANGE_nT = (1e-6, 1e9)


def parse_lsb(value, where="--lsb"):
    """The LSB of raw counts in nT per count, from a number or its text.

    Raises
    ------
    DatasetError
        Unless it is a finite number within :data:`LSB_RANGE_nT`.
    """
    number = value if isinstance(value, (int, float)) and not isinstance(value, bool) else _strict_float(str(value))
    lo, hi = LSB_RANGE_nT
    if number is None or not lo <= number <= hi:  # NaN compares False: refused too
        raise DatasetError(
            f"{where}: {shown(value)} must be a positive number of nT per count, from {lo:g} to {hi:g} (e.g. 150 "
            "for 0.15 uT/LSB, or 91.74 for a part giving 1090 LSB/G)"
        )
    return float(number)


def parse_units(units, where="--units", lsb_nT=None):
    """Factor (nT per unit) for a unit name such as ``nT``, ``uT``, ``G``, ``mG``, or ``counts`` with an LSB.

    Parameters
    ----------
    units : str
        The unit name (case-insensitive).
    where : str
        Where the name came from, for messages.
    lsb_nT : float, optional
        nT per count; needed for ``counts`` (raw sensor counts), whose factor it is.

    Raises
    ------
    DatasetError
        For an unknown unit, or ``counts`` without an LSB.
    """
    key = str(units).strip()
    if is_counts(key):
        if lsb_nT is None:
            raise DatasetError(
                f"{where}: readings in raw counts need the LSB in nT per count: pass --lsb NT_PER_COUNT or add a "
                "'# lsb_nT: ...' line to the file (e.g. 150 for 0.15 uT/LSB; see the sensor's data sheet)"
            )
        return parse_lsb(lsb_nT, where="lsb_nT")
    factor = UNIT_FACTORS_nT.get(key.lower())
    if factor is None:
        raise DatasetError(
            f"{where}: unknown unit {shown(units)}; use one of {', '.join(UNIT_NAMES)} (nT is the default), or counts "
            "with --lsb for raw sensor counts"
        )
    return factor


def _note(text) -> Note:
    """A reader's note (a :class:`DataWarning` at the boundary), said by the step ``read``."""
    return Note(text, DataWarning, "read")


def parse_column_mapping(text):
    """Parse a CLI column mapping ``"x=magX,y=magY,z=magZ,t=time"`` into ``{"s1x": "magX", ...}``.

    Parameters
    ----------
    text : str
        Comma-separated ``canonical=file_column`` pairs. Bare ``x,y,z`` mean sensor 1.

    Raises
    ------
    DatasetError
        If a pair is malformed or names an unknown canonical column.
    """
    mapping = {}
    if text is None or not str(text).strip():
        return mapping
    for part in str(text).split(","):
        part = part.strip()
        if not part:
            continue
        if "=" not in part:
            raise DatasetError(
                f"--columns: {part!r} is not of the form name=file_column (e.g. x=magX,y=magY,z=magZ,t=time)"
            )
        key, value = (s.strip() for s in part.split("=", 1))
        if not key or not value:
            raise DatasetError(f"--columns: {part!r} has an empty name; write name=file_column")
        mapping[key] = value
    return _normalise_mapping(mapping, "--columns")


def _normalise_mapping(columns, where):
    allowed = set(canonical_columns()) | set(MAPPABLE_ACCEL_COLUMNS)
    out = {}
    for key, value in dict(columns).items():
        k = str(key).strip()
        if k in SENSOR_AXES:
            k = f"s1{k}"
        if k not in allowed:
            raise DatasetError(
                f"{where}: {key!r} is not a magcal column; map onto one of "
                f"s1x..s4z (or x,y,z), {', '.join(CHANNEL_COLUMNS)}, {', '.join(QUATERNION_COLUMNS)}, group, "
                f"{', '.join(MAPPABLE_ACCEL_COLUMNS)} (the accelerometer)"
            )
        if k in out:
            raise DatasetError(f"{where}: column {k} is mapped twice")
        out[k] = str(value).strip()
    if len(set(out.values())) != len(out):
        dup = sorted({v for v in out.values() if list(out.values()).count(v) > 1})
        raise DatasetError(f"{where}: file column(s) {', '.join(dup)} mapped to more than one magcal column")
    return out


@dataclass
class Layout:
    """Where each magcal quantity sits in a file's columns (0-based indices into the header)."""

    header: list
    sensors: list  # per sensor: (ix, iy, iz)
    channels: dict = field(default_factory=dict)  # canonical name -> index (t, temp, ref_total)
    quaternion: tuple | None = None
    group: int | None = None
    extra: dict = field(default_factory=dict)  # file column name -> index

    @property
    def n_sensors(self):
        return len(self.sensors)

    @property
    def numeric(self):
        """(index, canonical name) of every column that must hold finite numbers."""
        cols = []
        for i, idx in enumerate(self.sensors):
            cols += [(j, f"s{i + 1}{a}") for j, a in zip(idx, SENSOR_AXES)]
        cols += [(j, name) for name, j in self.channels.items()]
        if self.quaternion:
            cols += [(j, name) for j, name in zip(self.quaternion, QUATERNION_COLUMNS)]
        return cols

    @property
    def quaternion_positions(self) -> list:
        """Positions of ``qw, qx, qy, qz`` in :attr:`numeric` (empty without attitude columns): the only numeric
        cells that may be empty or NaN, all four together (a sample without attitude)."""
        if not self.quaternion:
            return []
        pos = {name: m for m, (_, name) in enumerate(self.numeric)}
        return [pos[name] for name in QUATERNION_COLUMNS]


def bad_numeric_cells(values, quaternion_positions=()):
    """Where the numeric cells of a block (N, k) break the rule for read values (:func:`bad_values`), a sample
    without attitude excepted: its four quaternion cells NaN together (the file's empty or ``nan`` cells). One,
    two or three of them NaN stay bad, as does an infinite or huge value anywhere.

    Returns
    -------
    numpy.ndarray of bool, shape (N, k)
    """
    bad = bad_values(values)
    if len(quaternion_positions):
        q = np.asarray(values, dtype=float)[:, list(quaternion_positions)]
        without = np.all(np.isnan(q), axis=1)  # no attitude for this sample
        if without.any():
            bad[np.ix_(without, list(quaternion_positions))] = False
    return bad


def _find_layout(header, columns, source, header_line=1) -> tuple[Layout, list[Note]]:
    """Build the :class:`Layout` from the header names and the optional mapping canonical -> file name; returned
    with the notes it has (a bare ``x`` column kept as unused)."""
    names = list(header)
    index = _header_index(names, source, header_line)
    canonical, mapped_files = _mapped_columns(columns, index, names, source)
    notes = _named_columns(names, canonical, mapped_files, source)
    sensors = _sensor_columns(names, canonical, source)
    channels = {name: canonical[name] for name in CHANNEL_COLUMNS if name in canonical}
    q = [name for name in QUATERNION_COLUMNS if name in canonical]
    if q and len(q) != 4:
        raise DatasetError(f"{source}: attitude needs all four columns qw,qx,qy,qz; found only {', '.join(q)}")
    quaternion = tuple(canonical[n] for n in QUATERNION_COLUMNS) if q else None
    used = set(canonical.values())
    extra = {names[j] or f"column_{j + 1}": j for j in range(len(names)) if j not in used}
    for name in MAPPABLE_ACCEL_COLUMNS:  # a file's accelerometer column mapped onto ax, ay, az: kept under that name
        if name in canonical:
            extra.pop(name, None)  # the file's own column of that name gives way to the mapped one
            extra[name] = canonical[name]
    return Layout(names, sensors, channels, quaternion, canonical.get("group"), extra), notes


def _header_index(names, source, header_line) -> dict[str, int]:
    """(Part of :func:`_find_layout`.) Each named column's index (0-based); a name that appears twice is an error."""
    index: dict[str, int] = {}
    for j, name in enumerate(names):
        if not name:
            continue
        if name in index:
            raise DatasetError(
                f"{source}: line {header_line} (the header): column {shown(name)} appears twice (columns {index[name] + 1} "
                f"and {j + 1}); rename one of them"
            )
        index[name] = j
    return index


def _mapped_columns(columns, index, names, source) -> tuple[dict[str, int], set]:
    """(Part of :func:`_find_layout`.) The mapping ``columns`` (canonical -> file name) as canonical name -> file
    index, and the file names it maps; a file name the header lacks is an error."""
    canonical: dict[str, int] = {}
    mapped_files: set = set()
    if not columns:
        return canonical, mapped_files
    for canon, file_name in _normalise_mapping(columns, "column mapping").items():
        if file_name not in index:
            raise DatasetError(
                f"{source}: the column mapping names {shown(file_name)} (for {canon}) but the file has no such "
                f"column; its columns are: {names_shown(names)}"
            )
        canonical[canon] = index[file_name]
        mapped_files.add(file_name)
    return canonical, mapped_files


def _named_columns(names, canonical, mapped_files, source) -> list[Note]:
    """(Part of :func:`_find_layout`.) Add to ``canonical`` the file's columns named as magcal names them (a bare
    ``x, y, z`` as sensor 1's, unless the file has ``s1x``-style columns too: then it is kept unused, with a note,
    returned); a sensor number beyond :data:`MAX_SENSORS` is an error."""
    notes: list[Note] = []
    known = set(canonical_columns())
    for j, name in enumerate(names):
        if name in mapped_files:
            continue
        key = name
        if key in SENSOR_AXES:
            key = f"s1{key}"
            if any(_SENSOR_RE.match(n) for n in names):  # s1x... and bare x: keep x as an extra column
                notes.append(
                    _note(
                        f"{source}: the file has both s1x-style columns and a bare {name!r} column; {name!r} is "
                        "kept as an unused column"
                    )
                )
                continue
        if key in canonical:
            continue  # a mapped column took this role; the file's own column is kept as an extra
        if key in known:
            canonical[key] = j
    for name in names:
        m = re.match(r"^s(\d+)[xyz]$", name)
        if m and not 1 <= int(m.group(1)) <= MAX_SENSORS and name not in mapped_files:
            raise DatasetError(
                f"{source}: column {shown(name)} names sensor {int(m.group(1))}; magcal handles sensors 1 to "
                f"{MAX_SENSORS} (s1x .. s{MAX_SENSORS}z). Rename or remove it"
            )
    return notes


def _sensor_columns(names, canonical, source) -> list[tuple]:
    """(Part of :func:`_find_layout`.) Per sensor the indices of its x, y, z columns; sensors numbered 1, 2, ...
    without a gap, each with all three axes (else an error that says which)."""
    present = sorted({int(m.group(1)) for m in map(_SENSOR_RE.match, canonical) if m})
    if not present:
        raise DatasetError(
            f"{source}: no magnetometer columns; the header is {names_shown(names) or '(empty)'}. Name the columns "
            "s1x,s1y,s1z (... s4x,s4y,s4z) or x,y,z, or map yours with --columns x=magX,y=magY,z=magZ"
        )
    if present[-1] > MAX_SENSORS:
        raise DatasetError(f"{source}: sensor {present[-1]} found; magcal handles one to four sensors (s1..s4)")
    if present != list(range(1, len(present) + 1)):
        missing = sorted(set(range(1, present[-1] + 1)) - set(present))
        raise DatasetError(
            f"{source}: sensor columns for sensor(s) {', '.join(map(str, present))} but not for "
            f"{', '.join(map(str, missing))}; sensors are numbered by position (1 +x, 2 +y, 3 -x, 4 -y), so add the "
            "missing sensor's columns or map yours onto s1.. with --columns"
        )
    sensors = []
    for i in present:
        need = [f"s{i}{a}" for a in SENSOR_AXES]
        lacking = [n for n in need if n not in canonical]
        if lacking:
            raise DatasetError(
                f"{source}: sensor {i} lacks column(s) {', '.join(lacking)}; every sensor needs x, y and z "
                f"(header: {names_shown(names)})"
            )
        sensors.append(tuple(canonical[n] for n in need))
    return sensors


def _partial_quaternion(q):
    """The message for a row whose quaternion cells ``q`` (qw, qx, qy, qz) are some but not all missing (empty or
    nan), else None."""
    missing = np.isnan(q)
    if not missing.any() or missing.all():
        return None
    lacking = [n for n, m in zip(QUATERNION_COLUMNS, missing) if m]
    given = [n for n, m in zip(QUATERNION_COLUMNS, missing) if not m]
    return (
        f"column {lacking[0]}: empty or nan while {', '.join(given)} {'holds' if len(given) == 1 else 'hold'} "
        f"a number; give all four of qw,qx,qy,qz, or leave all four empty for a sample without attitude"
    )


def _strict_float(text):
    """``float(text)`` for plain ASCII decimal numbers; ``None`` for anything else."""
    s = text.strip()
    if not s or "_" in s or not s.isascii():
        return None
    try:
        return float(s)
    except ValueError:
        return None


@dataclass
class Chunk:
    """One block of rows of a file: the dataset, the raw lines and their 1-based line numbers."""

    dataset: Dataset
    lines: list
    line_numbers: np.ndarray


def _blank(raw) -> bool:
    """Whether a line (bytes) is one the CSV reader skips: nothing but whitespace (``str.strip`` of the text
    empty). Bytes that are not UTF-8 make it a line it refuses, not a blank one."""
    return not raw.decode("utf-8", "replace").strip()


def _blank_lines(data, end) -> int:
    """The blank lines (:func:`_blank`) among the whole lines of ``data[:end]`` (``end`` just after a line end).

    Only the lines that begin with one of :data:`SPACE_LEAD_BYTES` can be blank; a block without any (one regular
    expression search, as fast as counting the line ends) has none."""
    if not _SPACE_LEAD[data[0]] and _MAYBE_BLANK.search(data, 0, end) is None:
        return 0
    codes = np.frombuffer(data, dtype=np.uint8, count=end)
    ends = np.flatnonzero(codes == 10)
    starts = np.empty_like(ends)
    starts[0] = 0
    starts[1:] = ends[:-1] + 1
    maybe = _SPACE_LEAD[codes[starts]]  # an empty line begins with its own line end
    return sum(_blank(data[a:b]) for a, b in zip(starts[maybe].tolist(), ends[maybe].tolist()))


def check_csv_head(head, source):
    """Refuse a CSV from its first bytes ``head`` (:data:`HEAD_PROBE_BYTES` of them): empty, binary (NUL bytes), or
    with old Mac line ends (lines ending in a lone carriage return: CRs and no LF). Every reader of a CSV (the
    whole-file and line-by-line readers, the survey's partitions) checks the same bytes, with the same message.

    Raises
    ------
    DatasetError
    """
    if not head.strip():
        raise DatasetError(f"{source}: the file is empty; it needs a header row (e.g. s1x,s1y,s1z) and data rows")
    if b"\x00" in head:
        raise DatasetError(
            f"{source}: this looks like a binary file (it contains NUL bytes), not CSV text; export the "
            "data as UTF-8 CSV (docs/formats.md)"
        )
    if b"\r" in head and b"\n" not in head and len(head.strip().splitlines()) > 1:
        raise DatasetError(
            f"{source}: the lines end with a lone carriage return (old Mac style), which magcal does not read as a "
            "line end; convert the file to Unix (LF) or Windows (CRLF) line endings (e.g. mac2unix FILE)"
        )


def stray_cr_message(source, line_no) -> str:
    """The message refusing line ``line_no`` of ``source`` for a carriage return inside it (:func:`stray_cr`)."""
    return (
        f"{source}: line {line_no} holds a carriage return (CR, \\r) inside the line; magcal's line ends are LF or "
        "CRLF, and a lone CR (an old Mac line end, or a stray byte) would split or hide a row: convert the file's "
        "line endings to LF or CRLF (e.g. mac2unix FILE), or remove the stray CR from that line"
    )


#: Bytes looked at a time by :func:`stray_cr`.
_CR_BLOCK = 1 << 20


def stray_cr(data, start=0) -> int:
    """Where the first carriage return inside a line of ``data[start:]`` is, or -1: a CR followed by a byte other
    than CR or LF. CRs that end a line (before its LF: CRLF, CRCRLF; or at the end of ``data``) are line ends.

    The rule of every CSV reader of magcal: the line-by-line reader refuses such a line, and the whole-file reader
    (pyarrow, which would take the CR for a line end) gives the file to it. ``data`` is any bytes-like object (a
    memory-mapped file); it is looked at :data:`_CR_BLOCK` bytes at a time, with NumPy.
    """
    view = np.frombuffer(data, dtype=np.uint8)
    for s in range(int(start), view.size, _CR_BLOCK):
        block = view[s : s + _CR_BLOCK + 1]  # one byte more: the byte after a CR that ends the block
        after = np.flatnonzero(block[:_CR_BLOCK] == 13) + 1
        if not after.size:
            continue
        after = after[after < block.size]
        follow = block[after]
        inside = np.flatnonzero((follow != 10) & (follow != 13))
        if inside.size:
            return s + int(after[inside[0]]) - 1
    return -1


class _FileLines:
    """The lines (UTF-8 bytes, line ends kept) of a file object, binary or text, read block by block.

    ``head`` holds the first bytes for :meth:`CsvSource._check_head`; they are served again as lines. A line
    longer than :data:`MAX_LINE_BYTES` is refused (:class:`DatasetError`, naming it) as soon as that many bytes
    have come without a line end, so memory stays bounded whatever the file holds. Closing it leaves the file
    open unless ``owned``.
    """

    _BLOCK = 1 << 16

    def __init__(self, fh, source, owned=False):
        self._fh = fh
        self._owned = owned
        self._source = source
        self._lines = collections.deque()
        self._tail = b""
        self._n_read = 0  # bytes read from the file
        self._n_lines = 0  # lines split off so far (for the number of an over-long one)
        self.head = self._read(HEAD_PROBE_BYTES)
        self._take(self.head)

    def _read(self, n):
        try:
            data = self._fh.read(n)
        except UnicodeDecodeError as exc:  # a text file opened with another encoding than the file's
            raise DatasetError(
                f"{self._source}: the text cannot be decoded ({exc.reason}); save it as UTF-8 CSV or open it as binary"
            ) from None
        if isinstance(data, str):
            data = data.encode("utf-8", "surrogatepass")  # a lone surrogate then fails as "not UTF-8" by line
        data = bytes(data or b"")
        self._n_read += len(data)
        return data

    def _take(self, data):
        parts = (self._tail + data).split(b"\n")
        self._tail = parts.pop()  # an unfinished line waits for the next block
        longest = max(map(len, parts), default=0)
        if longest >= MAX_LINE_BYTES or len(self._tail) >= MAX_LINE_BYTES:
            k = next((i for i, part in enumerate(parts) if len(part) >= MAX_LINE_BYTES), len(parts))
            raise DatasetError(
                f"{self._source}: line {self._n_lines + k + 1} is longer than {MAX_LINE_BYTES:,} bytes; this is "
                "not a CSV of readings (a binary file, or the line ends are missing): check the file"
            )
        self._n_lines += len(parts)
        self._lines.extend(part + b"\n" for part in parts)

    def count_rest(self, block_bytes: int) -> int | None:
        """The lines not read yet that are not blank (:func:`_blank`), counted ``block_bytes`` at a time without
        splitting them (:meth:`CsvSource.count_rows`); None when one runs on for :data:`MAX_LINE_BYTES` without a
        line end. The file is then at its end."""
        n = sum(not _blank(raw) for raw in self._lines)  # the last block read, already split into lines
        self._lines.clear()
        carry, self._tail = self._tail, b""  # the start of a line whose end is not read yet
        while True:
            more = self._read(block_bytes)
            if not more:
                break
            data = carry + more if carry else more
            end = data.rfind(b"\n") + 1  # data[:end] is whole lines
            if end:
                n += data.count(b"\n") - _blank_lines(data, end)
            carry = data[end:]
            if len(carry) >= MAX_LINE_BYTES:
                return None
        return n + (1 if carry and not _blank(carry) else 0)

    def tell(self) -> int:
        """Bytes of the file consumed so far (read and served as lines)."""
        return self._n_read - len(self._tail) - sum(map(len, self._lines))

    def _fill(self):
        while not self._lines:
            more = self._read(self._BLOCK)
            if not more:
                if self._tail:
                    self._lines.append(self._tail)
                    self._tail = b""
                return
            self._take(more)

    def __iter__(self):
        return self

    def __next__(self):
        self._fill()
        if not self._lines:
            raise StopIteration
        return self._lines.popleft()

    def readline(self):
        return next(self, b"")

    def close(self):
        if self._owned and self._fh is not None:
            self._fh.close()
        self._fh = None


class CsvSource:
    """An open magcal CSV file: metadata and header are read at once, the rows in chunks.

    Parameters
    ----------
    path : str, os.PathLike or file object
        A path, or an open file (binary, or text) with ``read``: an upload's ``io.BytesIO``, an ``io.StringIO``,
        ``open(path, "rb")``. A file object is read from where it stands and left open.
    columns : dict, optional
        Mapping canonical name -> file column name (``{"s1x": "magX"}``; ``x`` means ``s1x``).
    units : str, optional
        Unit of the readings (nT, uT, G, mG, or counts); overrides the file's ``# units:`` line.
    name : str, optional
        What messages and :attr:`Dataset.source` call the file (e.g. an upload's file name); default the path, or
        the file object's ``name``.
    lsb_nT : float or str, optional
        nT per count for readings in raw counts; overrides the file's ``# lsb_nT:`` line. Refused unless the
        readings are in counts. The LSB used is kept as the metadata ``lsb_nT`` of the datasets.

    Notes
    -----
    Use as a context manager, or call :meth:`close`. What it has to say (a metadata line given twice, units given
    over the file's, rows dropped, quaternions normalised) is in :attr:`notes` as it reads.
    """

    #: What the numbers given to :meth:`_dataset` count in its messages: the file's lines (a Parquet file: rows).
    _row_word = "line"
    #: How a message names row number ``n`` (1-based) when not ``"{_row_word} {n}"``: a DataFrame's index label.
    _row_label: Callable[[int], str] | None = None
    #: What a message tells the user to sort (a DataFrame's rows rather than the file).
    _sort_what = "file"

    #: Where a metadata line is, in messages, when not ``line N`` (a Parquet file's schema holds no lines).
    _metadata_in: str | None = None

    def _metadata_at(self) -> str:
        """``line 3`` (the CSV's metadata line being read), or :attr:`_metadata_in`."""
        return self._metadata_in or f"line {self._lineno}"

    def _where(self, number, word=None) -> str:
        """The message's name of the row numbered ``number``: ``line 12`` (CSV), ``row 12`` (Parquet), or the
        label :attr:`_row_label` gives (a DataFrame's index)."""
        if self._row_label is not None:
            return self._row_label(int(number))
        return f"{word or self._row_word} {number}"

    def __init__(self, path, columns=None, units=None, name=None, lsb_nT=None):
        #: What the reader has said so far (:class:`~magcal.core.notes.Note`, :class:`DataWarning`), in order.
        self.notes: list[Note] = []
        self.metadata = {}
        self.metadata_lines = []
        self._file = None
        self._lineno = 0
        if hasattr(path, "read"):
            self.path = None
            self.source = str(name or getattr(path, "name", None) or "<file object>")
            self._file = _FileLines(path, self.source)
            head = self._file.head
        else:
            self.path = os.fspath(path)
            self.source = str(name or self.path)
            head = self._probe_path()
        try:
            self._check_head(head)
            if self._file is None:
                try:
                    fh = open(self.path, "rb")
                except OSError as exc:
                    raise DatasetError(
                        f"{self.source}: cannot open the file ({exc.strerror or exc}); check the path"
                    ) from None
                self._file = _FileLines(fh, self.source, owned=True)
            self._read_head()
            self.layout, said = _find_layout(self.header, columns, self.source, self.header_line)
            self.notes += said
            self._resolve_units(units, lsb_nT)
        except BaseException:
            self.close()
            raise
        self._last_time = None
        self._last_time_line = None

    # -- file head ----------------------------------------------------------------------------------------------
    def _probe_path(self):
        """The first bytes of the file at :attr:`path` (a clear error for a folder or a missing file)."""
        try:
            if os.path.isdir(self.path):
                raise DatasetError(f"{self.source}: is a directory, not a CSV file")
            reason = not_regular_reason(self.path)
            if reason is not None and reason != "no such file" and not reason.startswith("cannot"):
                raise DatasetError(f"{self.source}: is {reason}; give the path of a regular CSV file")
            with open(self.path, "rb") as fh:
                return fh.read(HEAD_PROBE_BYTES)
        except FileNotFoundError:
            raise DatasetError(f"{self.source}: no such file; check the path") from None
        except OSError as exc:
            raise DatasetError(f"{self.source}: cannot read the file ({exc.strerror or exc})") from None

    def _check_head(self, head):
        check_csv_head(head, self.source)

    def _decode(self, raw, line_no):
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise DatasetError(
                f"{self.source}: line {line_no} is not UTF-8 text ({exc.reason} at byte {exc.start} of the line); "
                "this looks like a binary file or another encoding: save it as UTF-8 CSV"
            ) from None
        if line_no == 1 and text.startswith("\ufeff"):
            text = text[1:]
        text = text.rstrip("\n").rstrip("\r")
        if "\r" in text:
            raise DatasetError(stray_cr_message(self.source, line_no))
        return text

    def _readline(self):
        raw = self._file.readline()
        if not raw:
            return None
        self._lineno += 1
        return self._decode(raw, self._lineno)

    def _read_head(self):
        while True:
            text = self._readline()
            if text is None:
                raise DatasetError(
                    f"{self.source}: no header row found (only blank or # lines); add a header such as s1x,s1y,s1z"
                )
            if not text.strip():
                continue
            if text.lstrip().startswith("#"):
                self.metadata_lines.append(text)
                body = text.lstrip()[1:]
                if ":" in body:
                    key, value = body.split(":", 1)
                    key, value = key.strip(), value.strip()
                    if key:
                        if key in self.metadata and self.metadata[key] != value:
                            self.notes.append(
                                _note(
                                    f"{self.source}: {self._metadata_at()}: metadata {shown(key)} given twice; the "
                                    f"last value {shown(value)} is used"
                                )
                            )
                        self.metadata[key] = value
                        self._check_metadata(key, value)
                continue
            break
        self.header_line = self._lineno
        if "\x00" in text:
            raise DatasetError(f"{self.source}: line {self._lineno} contains NUL bytes; this is not a CSV text file")
        try:
            header = next(csv.reader([text]))
        except csv.Error as exc:
            raise DatasetError(
                f"{self.source}: line {self._lineno}: the header cannot be read as CSV ({exc})"
            ) from None
        if len(header) > MAX_COLUMNS:
            raise DatasetError(
                f"{self.source}: line {self._lineno}: the header names {len(header):,} columns, more than the "
                f"{MAX_COLUMNS:,} magcal reads; keep the columns you need (readings, t, temp...) and save again"
            )
        self.header = [h.strip() for h in header]
        if all(_strict_float(h) is not None for h in self.header):
            raise DatasetError(
                f"{self.source}: line {self._lineno} is the first non-comment line but holds only numbers; the file "
                "needs a header row naming the columns (e.g. s1x,s1y,s1z,t)"
            )

    def _check_metadata(self, key, value):
        if key in NUMERIC_METADATA:
            number = _strict_float(value)
            positive = NUMERIC_METADATA[key][1]
            if number is None or bad_values(number) or number < 0 or (positive and number == 0):
                need = "a positive number" if positive else "a number >= 0"
                raise DatasetError(
                    f"{self.source}: {self._metadata_at()}: metadata {key}: {shown(value)} must be {need}"
                    + (" in nT" if key.endswith("_nT") else " in m" if key.endswith("_m") else "")
                )
        elif key == "units":
            if not is_counts(value):
                parse_units(value, where=f"{self.source}: {self._metadata_at()}: metadata units")
            self._units_line = self._lineno
        elif key == "lsb_nT":
            parse_lsb(value, where=f"{self.source}: {self._metadata_at()}: metadata lsb_nT")
        elif key == "site":
            self._read_site(value)

    def _read_site(self, value):
        """A ``# site:`` line that names a place: its numbers join the metadata (:mod:`magcal.data.site`); a
        malformed one is said in one note naming the file and line, and the file is read without it."""
        for name in SITE_KEYS:
            self.metadata.pop(name, None)
        if not names_a_place(value):
            return  # a name in words: kept as text
        try:
            self.metadata.update(site_metadata(parse_site(value)))
        except ValueError as exc:
            self.notes.append(
                _note(
                    f"{self.source}: {self._metadata_at()}: metadata site: {shown(value)} {exc}; write it as "
                    f"'{SITE_FORM}' (e.g. {SITE_EXAMPLE}); the file is read without the site"
                )
            )

    def _resolve_units(self, units, lsb_nT=None):
        """Set :attr:`units`, :attr:`unit_factor` (nT per unit) and :attr:`lsb_nT` (None unless counts)."""
        file_units = self.metadata.get("units")
        file_lsb = self.metadata.get("lsb_nT")
        given = units is not None and bool(str(units).strip())
        self.units = str(units).strip() if given else file_units if file_units is not None else "nT"
        counts = is_counts(self.units)
        lsb = None
        if lsb_nT is not None and str(lsb_nT).strip():
            lsb = parse_lsb(lsb_nT, where=f"{self.source}: --lsb")
            if not counts:
                origin = "--units" if given else "the file's units line" if file_units is not None else "the default"
                raise DatasetError(
                    f"{self.source}: --lsb {lsb_nT} applies to readings in raw counts, but they are in {self.units} "
                    f"({origin}); add --units counts if the readings are counts, or leave out --lsb"
                )
            if file_lsb is not None and parse_lsb(file_lsb) != lsb:
                self.notes.append(_note(f"{self.source}: --lsb {lsb_nT} overrides the file's 'lsb_nT: {file_lsb}'"))
        elif counts and file_lsb is not None:
            lsb = parse_lsb(file_lsb)
        if given:
            where = f"{self.source}: --units {self.units}"
        elif file_units is not None:
            where = f"{self.source}: line {self._units_line}: metadata units"
        else:
            where = f"{self.source}: units"
        self.unit_factor = parse_units(self.units, where=where, lsb_nT=lsb)
        if given and file_units is not None:
            same = is_counts(file_units) == counts and (counts or parse_units(file_units) == self.unit_factor)
            if not same:
                self.notes.append(
                    _note(f"{self.source}: --units {self.units} overrides the file's 'units: {file_units}'")
                )
        self.lsb_nT = lsb if counts else None
        if self.lsb_nT is not None:
            self.metadata["lsb_nT"] = repr(self.lsb_nT) if lsb_nT is not None else file_lsb

    # -- rows --------------------------------------------------------------------------------------------------
    def number_lines_from(self, line_no):
        """Number the lines still to read from ``line_no`` (1-based) on: for a file object holding a file's head
        and then a range of its lines (a survey's partition), whose messages then name the file's own lines."""
        self._lineno = int(line_no) - 1

    def _read_lines(self, n):
        """The non-blank lines (text without line ends) among the next ``n`` lines, and their 1-based line numbers;
        past ``n`` lines that are all blank, to the next non-blank one: none only at the end of the file."""
        while True:
            lines, numbers = self._next_lines(n)
            if lines or not numbers.size:
                return lines, numbers

    def _next_lines(self, n):
        """The non-blank lines among the next ``n`` lines of the file and their line numbers: at the end of the
        file no numbers; when the ``n`` lines are all blank no lines, and the numbers of those read."""
        raws = list(itertools.islice(self._file, int(n)))
        if not raws:
            return [], np.zeros(0, dtype=np.int64)
        first = self._lineno + 1
        self._lineno += len(raws)
        try:
            text = b"".join(raws).decode("utf-8")
        except UnicodeDecodeError:
            for k, raw in enumerate(raws):
                self._decode(raw, first + k)  # raises with the exact line number
            raise
        lines = text.split("\n")
        if text.endswith("\n"):
            lines.pop()
        if "\r" in text:  # CRs before a line's end end it; one inside a line is refused
            lines = [line.rstrip("\r") for line in lines]
            stray = next((k for k, line in enumerate(lines) if "\r" in line), None)
            if stray is not None:
                raise DatasetError(stray_cr_message(self.source, first + stray))
        numbers = np.arange(first, first + len(lines), dtype=np.int64)
        keep = [bool(line.strip()) for line in lines]
        if not any(keep):
            return [], numbers
        if not all(keep):
            lines = [line for line, k in zip(lines, keep) if k]
            numbers = numbers[np.asarray(keep, dtype=bool)]
        return lines, numbers

    def count_rows(self, block_bytes=COUNT_BLOCK_BYTES) -> int | None:
        """The rows left to read, counted from the file's bytes without parsing one (the source is then at its end).

        The rows are the lines that :meth:`chunks` reads as rows: every line after the header but the blank ones,
        which it skips (``str.strip`` of the line empty: an empty line, ``\\r\\n``, spaces, tabs, a no-break
        space...), a last line without a line end included; a ``#`` line after the header is a row (a bad one).
        Whenever :meth:`chunks` reads the rest of the file without an error, it yields exactly this many samples
        with ``drop_bad=False``, and at most this many with ``drop_bad=True`` (which only removes rows). For a file
        it refuses (a bad row, a line that is not UTF-8, a carriage return inside a line: :func:`stray_cr`) the
        count means nothing: read it for the message.

        The line ends are counted ``block_bytes`` at a time (:meth:`bytes.count`); only a line that begins with a
        byte a whitespace character can begin with (:data:`SPACE_LEAD_BYTES`; rare in a data file) is decoded and
        looked at: about 1 GB/s, 27x faster than parsing the rows (``benchmarks/csv_count.py``, 2e6 rows, 264 MB).

        Returns
        -------
        int or None
            The rows; None when a line runs on for :data:`MAX_LINE_BYTES` without a line end (the reader refuses
            the file: read it for its message).
        """
        return self._file.count_rest(int(block_bytes))

    def chunks(self, chunk_rows=200_000, drop_bad=False, text_columns=True):
        """Yield :class:`Chunk` objects of up to ``chunk_rows`` rows.

        Parameters
        ----------
        chunk_rows : int
            Rows per chunk.
        drop_bad : bool
            Drop rows with NaN, inf, empty cells or text in numeric columns (with a :class:`DataWarning`) instead
            of refusing the file.
        text_columns : bool
            Also read the ``group`` and unused columns (``Dataset.group``, ``Dataset.extra``).
        """
        while True:
            lines, numbers = self._read_lines(int(chunk_rows))
            if not lines:
                return
            yield self._parse(lines, numbers, drop_bad, text_columns)

    def _parse(self, lines, numbers, drop_bad, text_columns):
        layout = self.layout
        ncol = len(layout.header)
        num = layout.numeric
        values = None
        fast = not any('"' in line for line in lines)
        if fast:
            commas = np.fromiter((line.count(",") for line in lines), dtype=np.int64, count=len(lines))
            fast = bool(np.all(commas == ncol - 1))
        if fast:
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    values = np.loadtxt(
                        lines,
                        delimiter=",",
                        usecols=[j for j, _ in num],
                        dtype=float,
                        comments=None,
                        ndmin=2,
                        quotechar='"',
                    )
            except (ValueError, TypeError, IndexError):
                values = None
            if values is not None and values.shape != (len(lines), len(num)):
                values = None
            if values is not None and bad_numeric_cells(values, layout.quaternion_positions).any():
                values = None
        rows = None
        if values is None:
            rows, values, keep = self._parse_carefully(lines, numbers, drop_bad)
            lines = [line for line, k in zip(lines, keep) if k]
            numbers = numbers[keep]
            rows = [r for r, k in zip(rows, keep) if k]
        text = {}
        if text_columns and (layout.group is not None or layout.extra):
            want = ([layout.group] if layout.group is not None else []) + list(layout.extra.values())
            if rows is None:
                rows = self._split(lines, numbers)
            for j in want:
                text[j] = text_cells(
                    [r[j].strip() for r in rows], self.source, layout.header[j], lambda k: f"line {numbers[k]}"
                )
        ds = self._dataset(values, text, numbers)
        return Chunk(ds, lines, numbers)

    def _split(self, lines, numbers):
        rows = []
        reader = csv.reader(lines)
        for line_no in numbers:  # the line a row comes from names it in the message
            try:
                row = next(reader)
            except StopIteration:
                break
            except csv.Error as exc:
                raise DatasetError(f"{self.source}: line {line_no}: cannot be read as CSV ({exc})") from None
            rows.append(row)
        return rows

    def _parse_carefully(self, lines, numbers, drop_bad):
        layout = self.layout
        ncol = len(layout.header)
        num = layout.numeric
        quaternion = layout.quaternion_positions
        rows = []
        problems = []  # (line, message)
        values = np.empty((len(lines), len(num)))
        keep = np.ones(len(lines), dtype=bool)
        reader = csv.reader(lines)
        for k, line_no in enumerate(numbers):
            try:
                row = next(reader)
            except csv.Error as exc:
                raise DatasetError(f"{self.source}: line {line_no}: cannot be read as CSV ({exc})") from None
            if reader.line_num != k + 1:  # a quoted field went on over the line end: one row per line here
                raise DatasetError(
                    f"{self.source}: line {line_no}: a quoted field is not closed on its line (a '\"' without its "
                    "pair); every row must be on one line: close or remove the quote"
                )
            rows.append(row)
            if len(row) != ncol:
                raise DatasetError(
                    f"{self.source}: line {line_no} has {len(row)} field(s) but the header (line {self.header_line}) "
                    f"has {ncol}; every row needs one value per column (check for a missing or extra comma)"
                )
            bad = None
            for m, (j, name) in enumerate(num):
                number = _strict_float(row[j])
                if m in quaternion and (
                    number is None and not row[j].strip() or number is not None and np.isnan(number)
                ):
                    values[k, m] = np.nan  # empty or nan: no attitude, if the other three say so too (below)
                    continue
                if number is None:
                    cell = row[j].strip()
                    bad = f"column {name}: " + (f"{shown(cell)} is not a number" if cell else "empty cell")
                    break
                if not np.isfinite(number):
                    bad = f"column {name}: {shown(row[j].strip())} is not a finite number"
                    break
                if abs(number) > MAX_ABS_VALUE:
                    bad = (
                        f"column {name}: {shown(row[j].strip())} is beyond +-{MAX_ABS_VALUE:g}, no instrument's "
                        "reading in any unit (a corrupted value)"
                    )
                    break
                values[k, m] = number
            if bad is None and quaternion:
                bad = _partial_quaternion(values[k, quaternion])
            if bad is not None:
                keep[k] = False
                problems.append((int(line_no), bad))
        if problems:
            listed = "; ".join(f"line {ln}, {msg}" for ln, msg in problems[:_MAX_SHOWN])
            more = f" (and {len(problems) - _MAX_SHOWN} more)" if len(problems) > _MAX_SHOWN else ""
            if not drop_bad:
                raise DatasetError(
                    f"{self.source}: {len(problems)} row(s) with bad values: {listed}{more}. Fix or delete these rows, "
                    "or drop them with --drop-bad (drop_bad=True)"
                )
            self.notes.append(_note(f"{self.source}: dropped {len(problems)} row(s) with bad values: {listed}{more}"))
        return rows, values[keep], keep

    def _dataset(self, values, text, numbers):
        layout = self.layout
        n = values.shape[0]
        pos = {name: m for m, (_, name) in enumerate(layout.numeric)}
        readings = (
            np.stack([values[:, [pos[f"s{i + 1}{a}"] for a in SENSOR_AXES]] for i in range(layout.n_sensors)]).reshape(
                layout.n_sensors, n, 3
            )
            * self.unit_factor
        )
        kwargs = {attr: values[:, pos[name]] for name, attr in CHANNEL_COLUMNS.items() if name in layout.channels}
        if layout.quaternion is not None:
            q = values[:, [pos[name] for name in QUATERNION_COLUMNS]]
            norm = np.linalg.norm(q, axis=1)  # NaN on a sample without attitude (all four cells empty or nan)
            partial = np.isnan(q).any(axis=1) & ~np.isnan(q).all(axis=1)  # the readers refuse these; data in code
            if partial.any():
                k = int(np.argmax(partial))
                raise DatasetError(f"{self.source}: {self._where(numbers[k])}, {_partial_quaternion(q[k])}")
            zero = norm < 1e-12
            if zero.any():
                raise DatasetError(
                    f"{self.source}: {self._where(numbers[np.argmax(zero)])}: the attitude quaternion qw,qx,qy,qz "
                    "is zero; give a unit quaternion (array frame to world frame), or leave all four cells empty "
                    "for a sample without attitude"
                )
            error = np.abs(norm - 1.0)
            if np.any(error > 1e-3):
                worst = int(np.nanargmax(error))
                self.notes.append(
                    _note(
                        f"{self.source}: attitude quaternions are not unit length ({self._where(numbers[worst])}: "
                        f"|q| = {norm[worst]:.4g}); they are normalised"
                    )
                )
            off = error > 1e-9  # False where NaN: a sample without attitude stays NaN
            if off.any():
                q = q.copy()
                q[off] /= norm[off, None]
            kwargs["attitude_wxyz"] = q
        if "t" in layout.channels:
            self._check_time(kwargs["time_s"], numbers)
        if layout.group is not None and layout.group in text:
            kwargs["group"] = text[layout.group]
        extra = {}
        for name, j in layout.extra.items():
            if j in text:
                extra[name] = _maybe_numeric(text[j])
        meta_numbers = {}
        for key, (attr, _) in NUMERIC_METADATA.items():
            if key in self.metadata:
                meta_numbers[attr] = float(self.metadata[key])
        return Dataset(
            readings_nT=readings,
            metadata=dict(self.metadata),
            extra=extra,
            source=self.source,
            **kwargs,
            **meta_numbers,
        )

    def _check_time(self, t, numbers):
        if t.size == 0:
            return
        prev = np.concatenate([[self._last_time], t[:-1]]) if self._last_time is not None else None
        if prev is None:
            steps = np.diff(t)
            bad = np.flatnonzero(steps <= 0) + 1
            prev_lines = numbers[:-1]
            prev_t = t[:-1]
            offset = 1
        else:
            steps = t - prev
            bad = np.flatnonzero(steps <= 0)
            prev_lines = np.concatenate([[self._last_time_line], numbers[:-1]])
            prev_t = prev
            offset = 0
        if bad.size:
            k = int(bad[0])
            p = k - offset
            kind = "repeats" if t[k] == prev_t[p] else "goes back from"
            raise DatasetError(
                f"{self.source}: {self._where(numbers[k], 'line')}, column t: time {t[k]:.9g} s {kind} "
                f"{prev_t[p]:.9g} s on {self._where(prev_lines[p], 'line')}; time stamps must increase strictly "
                f"({bad.size} such row(s) in this block). Sort the {self._sort_what} by time, remove duplicated rows, "
                "or rename the t column if it is not a time stamp"
            )
        self._last_time = float(t[-1])
        self._last_time_line = int(numbers[-1])

    def close(self):
        if self._file is not None:
            self._file.close()
            self._file = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


#: A text column (``group``, a column magcal does not use) is held as fixed-width text: every cell as wide as
#: the longest. A file is refused when that would take more than :data:`TEXT_PADDING_FACTOR` times the text's own
#: size and more than :data:`TEXT_FLOOR_BYTES`: one very long cell among short ones (a 2000-character cell above
#: 100 000 one-character cells took 0.8 GB from a 1.2 MB CSV; a 1 MB cell above 200 000 would have taken 800 GB).
TEXT_PADDING_FACTOR = 8
TEXT_FLOOR_BYTES = 64 << 20


def _text_padding_refused(source, where, column, width, rows, padded_bytes) -> DatasetError:
    return DatasetError(
        f"{source}: {where}, column {shown(column)}: a text cell of {width:,} characters among {rows:,} rows of "
        f"mostly shorter ones would take {padded_bytes / 1e6:,.0f} MB as magcal holds text (every cell as wide as "
        "the longest); shorten that cell, or leave the column out of the file"
    )


#: The longest text cell a reader takes, characters: a CSV's line is at most :data:`MAX_LINE_BYTES`, and a cell
#: of another table (a Parquet dictionary holds one value, of any length, for any number of rows) is held to the
#: same.
MAX_TEXT_CELL_CHARS = MAX_LINE_BYTES
#: The text a reader may hold where the free memory cannot be read (not Linux), bytes.
TEXT_BUDGET_BYTES = 4 << 30


class TextBudget:
    """The bytes of text cells a reader may still make, as numpy holds them (4 bytes a character, every cell of a
    block as wide as its longest): half the memory free when it is made (:func:`magcal.core.memory.available_bytes`;
    :data:`TEXT_BUDGET_BYTES` where that cannot be read), or ``nbytes``. A whole-file reader spends one budget on
    all its blocks; a streaming reader's blocks each get one of their own."""

    def __init__(self, nbytes=None):
        if nbytes is None:
            free = available_bytes()
            nbytes = TEXT_BUDGET_BYTES if free is None else free // 2
        #: Bytes left.
        self.left = int(nbytes)

    def take(self, nbytes, source, column, rows) -> None:
        """Spend ``nbytes`` on ``rows`` cells of ``column``, or refuse them (before they are made).

        Raises
        ------
        DatasetError
            Naming the file, the column and the room left.
        """
        if nbytes > self.left:
            raise DatasetError(
                f"{source}: column {shown(column)}: its text ({rows:,} cells) would take {nbytes / 1e6:,.0f} MB as "
                f"magcal holds text (4 bytes a character, every cell as wide as the longest), more than the "
                f"{max(self.left, 0) / 1e6:,.0f} MB left for text (half the memory free); leave the column out of "
                "the file, or shorten its cells"
            )
        self.left -= int(nbytes)


def _check_text(lengths, source, column, row_name, budget) -> int:
    """The width of text cells of ``lengths`` characters, refused before they are made when a cell is longer than
    :data:`MAX_TEXT_CELL_CHARS`, when their padding is a bomb (:data:`TEXT_PADDING_FACTOR`) or when they do not
    fit ``budget`` (:class:`TextBudget`)."""
    n = len(lengths)
    longest = int(lengths.argmax())
    width = int(lengths[longest])
    if width > MAX_TEXT_CELL_CHARS:
        raise DatasetError(
            f"{source}: {row_name(longest)}, column {shown(column)}: a text cell of {width:,} characters, more than "
            f"the {MAX_TEXT_CELL_CHARS:,} magcal reads in one cell; shorten it, or leave the column out of the file"
        )
    padded = 4 * n * width  # numpy's str holds 4 bytes per character
    if padded > TEXT_FLOOR_BYTES and padded > TEXT_PADDING_FACTOR * 4 * int(lengths.sum()):
        raise _text_padding_refused(source, row_name(longest), column, width, n, padded)
    (budget if budget is not None else TextBudget()).take(padded, source, column, n)
    return width


def text_cells(cells, source, column, row_name, lengths=None, budget=None) -> np.ndarray:
    """A column's text cells as a fixed-width ``str`` array, refusing before it is made one with a cell longer
    than :data:`MAX_TEXT_CELL_CHARS`, one whose padding would be a bomb (:data:`TEXT_PADDING_FACTOR`,
    :data:`TEXT_FLOOR_BYTES`) and one over ``budget``.

    Parameters
    ----------
    cells : list of str or numpy.ndarray
        The cells (an object array from pyarrow: None is written ``'None'``, as ``astype(str)`` does; a numeric
        array is converted as it is).
    source, column : str
        The file and the column's name, for the message.
    row_name : callable
        The message's name of cell ``k`` (0-based): ``lambda k: f"line {numbers[k]}"``.
    lengths : array_like of int, optional
        The cells' lengths in characters, when the caller has them (pyarrow's ``utf8_length``).
    budget : TextBudget, optional
        What the reader may still spend on text (default: half the memory free now).
    """
    if isinstance(cells, np.ndarray) and cells.dtype.kind not in "OUS":
        return cells.astype(str)  # numbers: a few dozen characters each
    n = len(cells)
    if n == 0:
        return np.array([], dtype=str)
    if lengths is None:
        lengths = np.fromiter((len(c) if isinstance(c, str) else len(str(c)) for c in cells), np.int64, count=n)
    width = _check_text(np.asarray(lengths, dtype=np.int64), source, column, row_name, budget)
    if isinstance(cells, np.ndarray):
        return cells.astype(str)
    return np.array(cells, dtype=f"<U{max(width, 1)}")


def _maybe_numeric(strings):
    """A float array if every entry is a plain number, else the strings."""
    if strings.size == 0:
        return strings
    values = [_strict_float(s) for s in strings]
    if any(v is None for v in values):
        return strings
    return np.asarray(values, dtype=float)


def _check_joined_text(parts, source, column) -> None:
    """Refuse joining text blocks whose joined array (as wide as the widest block) would be a padding bomb: more
    than :data:`TEXT_PADDING_FACTOR` times the blocks and more than :data:`TEXT_FLOOR_BYTES` (a block of long
    cells joined to many blocks of short ones)."""
    rows = sum(len(p) for p in parts)
    width = max(p.dtype.itemsize // 4 for p in parts)
    padded = 4 * rows * width
    if padded > TEXT_FLOOR_BYTES and padded > TEXT_PADDING_FACTOR * sum(p.nbytes for p in parts):
        raise _text_padding_refused(source or "data", "the file", column, width, rows, padded)


def concatenate(datasets):
    """Join datasets with the same layout along the sample axis (metadata of the first)."""
    first = datasets[0]
    if len(datasets) == 1:
        return first

    def cat(attr):
        arrays = [getattr(d, attr) for d in datasets]
        if arrays[0] is not None and attr == "group":
            _check_joined_text(arrays, first.source, "group")
        return None if arrays[0] is None else np.concatenate(arrays)

    extra = {}
    for name in first.extra:
        parts = [d.extra[name] for d in datasets]
        if any(p.dtype.kind in "US" for p in parts):
            parts = [p.astype(str) for p in parts]
            _check_joined_text(parts, first.source, name)
        extra[name] = np.concatenate(parts)
    return first.replace(
        readings_nT=np.concatenate([d.readings_nT for d in datasets], axis=1),
        time_s=cat("time_s"),
        temperature_C=cat("temperature_C"),
        ref_total_nT=cat("ref_total_nT"),
        attitude_wxyz=cat("attitude_wxyz"),
        group=cat("group"),
        extra=extra,
    )


def check_units(dataset, units="nT", source=None, lsb_nT=None) -> str | None:
    """What to tell the user when the readings' magnitudes look like another unit (or another LSB), or None.

    The Earth's field is 20-70 uT; a median field magnitude far outside that range (after conversion to nT)
    usually means a wrong ``units`` line, or for raw counts a wrong LSB. The magnitude is taken about the readings'
    fitted centre (:func:`magcal.geometry.shape.field_magnitude_nT`), so a hard-iron offset does not masquerade as a unit
    error. ``lsb_nT`` (nT per count) defaults to the dataset's metadata ``lsb_nT`` for ``units="counts"``.
    Returns the text (the readers put it in their dataset's ``notes`` as a :class:`DataWarning` note), or ``None``.
    """

    r = dataset.readings_nT
    if r.size == 0:
        return None
    median = float(np.median([field_magnitude_nT(y) for y in r]))  # about the fitted centre: hard iron removed
    lo, hi = EARTH_FIELD_RANGE_nT
    if 0.5 * lo <= median <= 1.5 * hi:
        return None
    if is_counts(units):
        lsb = lsb_nT if lsb_nT is not None else dataset.metadata.get("lsb_nT")
        factor = parse_units(units, where=f"{source or dataset.source or 'dataset'}: units", lsb_nT=lsb)
        raw = median / factor
        hint = (
            f"check the LSB: {factor:.4g} nT per count is given, and about {50_000.0 / raw:.3g} nT per count "
            "would put the field at 50 uT (or the sensor is not in the Earth's field)"
        )
    else:
        factor = parse_units(units)
        raw = median / factor
        guesses = [name for name, f in UNIT_NAMES.items() if lo <= raw * f <= hi and f != factor]
        hint = (
            f"they look like {' or '.join(guesses)}: pass --units {guesses[0]} (or a '# units: {guesses[0]}' line)"
            if guesses
            else "check the units (nT, uT, G, mG, or counts with --lsb) and that the sensor is in the Earth's field"
        )
    value = f"{median:.4g} nT" if factor == 1.0 else f"{raw:.4g} {units} = {median:.4g} nT"
    msg = (
        f"{source or dataset.source or 'dataset'}: the field the readings imply (median magnitude about their "
        f"centre) is {value}, outside the Earth's field range of 20-70 uT; {hint}"
    )
    return msg


def _with_notes(ds, notes, units, source, lsb_nT):
    """``ds`` with its reader's ``notes`` (and :func:`check_units`' note, if any) as its :attr:`Dataset.notes`."""
    unit_text = check_units(ds, units, source, lsb_nT=lsb_nT)
    ds.notes = tuple(notes) + ((_note(unit_text),) if unit_text else ())
    return ds


def require_samples(dataset, n_params, what="this model"):
    """Raise :class:`DatasetError` unless every sensor has more samples than ``n_params``.

    Parameters
    ----------
    dataset : Dataset
    n_params : int
        Number of parameters fitted per sensor (9 for bias, scale and non-orthogonality).
    what : str
        The model's name, for the message.
    """
    need = int(n_params) + 1
    if dataset.n_samples < need:
        raise DatasetError(
            f"{dataset.source or 'dataset'}: {dataset.n_samples} sample(s) is too few for {what} "
            f"({n_params} parameters per sensor need at least {need}, and a good fit several times that); "
            "record more attitudes"
        )


def read_csv(
    path,
    columns=None,
    units=None,
    drop_bad=False,
    min_samples=1,
    chunk_rows=200_000,
    name=None,
    lsb_nT=None,
    max_rows=None,
    warn=True,
):
    """Read a magcal CSV file into a :class:`~magcal.data.dataset.Dataset` (readings in nT).

    Parameters
    ----------
    path : str, os.PathLike or file object
        The file, or an open binary or text file object (``io.BytesIO(uploaded_bytes)``, ``io.StringIO(text)``).
        A path ending in ``.bin`` (ArduPilot DataFlash) or ``.ulg`` (PX4 ULog) is read by
        :func:`magcal.data.logs.read_log` (the options below but ``name`` and ``min_samples`` do not apply); one ending
        in ``.parquet`` by :func:`read_parquet` (the CSV's columns and metadata, in Parquet).
    columns : dict or str, optional
        Column mapping canonical -> file name, e.g. ``{"s1x": "magX", "t": "time"}`` or the CLI form
        ``"x=magX,y=magY,z=magZ,t=time"``.
    units : str, optional
        Unit of the readings: ``nT`` (default), ``uT``, ``G``, ``mG``, or ``counts`` (raw sensor counts, with an
        LSB); overrides the file's ``# units:`` line.
    drop_bad : bool
        Drop rows whose numeric columns hold NaN, inf, empty cells or text, with a :class:`DataWarning`;
        otherwise such rows make the whole file refused.
    min_samples : int
        Fewest samples accepted (after dropping rows).
    name : str, optional
        What messages and ``Dataset.source`` call the file; default the path (or the file object's ``name``).
    lsb_nT : float or str, optional
        nT per count for ``counts``; overrides the file's ``# lsb_nT:`` line (kept as metadata ``lsb_nT``). An error
        unless the readings are in counts.
    max_rows : int, optional
        Refuse a file of more data rows than this (0: no limit): a Parquet file's rows are counted from its footer
        before any is read, and by default limited to :data:`MAX_READ_ROWS` (its size does not bound them); a
        CSV's are counted as they are read, and not limited unless ``max_rows`` is given (its bytes bound them).
        Either is refused when it would not fit in the free memory (:func:`check_read_rows`).
    warn : bool
        Raise the reader's notes (dropped rows, units that look wrong...) as :class:`DataWarning` warnings, the
        default; False leaves them in the dataset's ``notes`` only (what the command line, the workbench and the
        engine's own reads do).

    Returns
    -------
    Dataset
        ``source`` is the path (or ``name``), ``metadata`` holds every ``# key: value`` line as text, ``notes``
        what the reader had to say (:class:`~magcal.core.notes.Note`).

    Raises
    ------
    DatasetError
        For any problem with the file, naming the file, line (1-based) and column, and what to do.
    """

    ds = _read_any(path, columns, units, drop_bad, min_samples, chunk_rows, name, lsb_nT, max_rows)
    if warn:
        _notes.warn(ds.notes)
    return ds


def _read_any(path, columns, units, drop_bad, min_samples, chunk_rows, name, lsb_nT, max_rows):
    """:func:`read_csv` but the warnings: the dataset with its reader's notes."""
    if is_log(path):  # a flight-controller log (.bin, .ulg): magcal.data.logs reads it, in nT
        return read_log(path, name=name, min_samples=min_samples, warn=False)
    if isinstance(columns, str):
        columns = parse_column_mapping(columns)
    if is_parquet(path):  # the same columns and metadata, in Parquet (pyarrow)
        return read_parquet(path, name=name, max_rows=max_rows, columns=columns)
    if not hasattr(path, "read") and not drop_bad:
        ds = _read_csv_arrow(path, columns, units, name, lsb_nT)  # None: take the line-by-line reader
        if ds is not None:
            if max_rows:
                check_read_rows(ds.source, ds.n_samples, 0, max_rows)
            if ds.n_samples >= int(min_samples):
                return ds
    with CsvSource(path, columns=columns, units=units, name=name, lsb_nT=lsb_nT) as src:
        parts, rows = [], 0
        for chunk in src.chunks(chunk_rows, drop_bad=drop_bad):
            rows += chunk.dataset.n_samples
            if max_rows and rows > int(max_rows):
                check_read_rows(f"{src.source} (at line {int(chunk.line_numbers[-1]):,})", rows, 0, max_rows)
            parts.append(chunk.dataset)
        if not parts:
            raise DatasetError(
                f"{src.source}: no data rows after the header (line {src.header_line}); the file has no samples"
            )
        ds = concatenate(parts)
        if ds.n_samples < int(min_samples):
            dropped = " after dropping bad rows" if drop_bad else ""
            raise DatasetError(
                f"{src.source}: {ds.n_samples} sample(s){dropped}, fewer than the {int(min_samples)} needed; "
                "record more attitudes"
            )
        return _with_notes(ds, src.notes, src.units, src.source, src.lsb_nT)


#: Smallest CSV (bytes) worth a preview (:func:`read_csv_preview`): a smaller file is read whole about as fast.
PREVIEW_MIN_BYTES = 8_000_000
#: Bytes read at each offset of a preview (a longer line is read on).
PREVIEW_BLOCK_BYTES = 2048
#: Data up to this size (bytes) are previewed from all their lines (read at once: a few milliseconds), every
#: ``n / max_rows``-th line, so that a record of at most ``max_rows`` lines is previewed whole; a larger file by
#: seeking to evenly spaced offsets, whose lines (of unequal lengths) are spread about as evenly.
PREVIEW_WHOLE_BYTES = 16_000_000


def read_csv_preview(path, max_rows=20_000, columns=None, units=None, name=None, lsb_nT=None, min_bytes=None):
    """A quick look at a large CSV: at most ``max_rows`` data lines spread evenly through the file, read without
    reading the rest (an interactive program draws them while :func:`read_csv` reads the whole file).

    The head (metadata, header) is the file's own. Data of at most :data:`PREVIEW_WHOLE_BYTES` are read at once
    and every ``n / max_rows``-th of their ``n`` lines is taken (all of them when ``n <= max_rows``); in a larger
    file the lines are found by seeking to evenly spaced byte offsets and taking the first whole line after each.
    Either way the preview spans the whole recording in order. It is a picture, not data to fit: anything that :func:`read_csv` would warn about
    or refuse makes it None (the whole read then says so, naming the line).

    Parameters
    ----------
    path : str or os.PathLike
        A CSV file (a flight-controller log, a Parquet file or a file object gives None).
    max_rows : int
        Most data lines read.
    columns, units, name, lsb_nT
        As in :func:`read_csv`.
    min_bytes : int, optional
        Smaller files give None: reading them whole costs about as much (default :data:`PREVIEW_MIN_BYTES`).

    Returns
    -------
    Dataset or None
        Readings in nT of the sampled lines (``source`` names the file), or None when no preview is taken.
    """
    import io as _io

    if hasattr(path, "read") or is_log(path) or is_parquet(path) or int(max_rows) < 1:
        return None
    try:
        size = os.path.getsize(path)
        if size < int(PREVIEW_MIN_BYTES if min_bytes is None else min_bytes):
            return None
        with CsvSource(path, columns=columns, units=units, name=name, lsb_nT=lsb_nT) as src:
            header_line = src.header_line
            head_notes = list(src.notes)
        with open(os.fspath(path), "rb") as fh:
            head = b"".join(fh.readline() for _ in range(header_line))
            start = len(head)
            if size - start <= PREVIEW_WHOLE_BYTES:
                lines = _every_kth_line(fh.read(), int(max_rows))
            else:
                lines = _lines_at_offsets(fh, start, size, int(max_rows))
        if not lines:
            return None
        ds = read_csv(
            _io.BytesIO(head + b"".join(lines[: int(max_rows)])),
            columns=columns,
            units=units,
            name=name if name is not None else os.fspath(path),
            lsb_nT=lsb_nT,
            warn=False,
        )
    except (OSError, MagcalError):
        return None
    return None if head_notes or ds.notes else ds


def _every_kth_line(data: bytes, max_rows: int) -> list:
    """The non-blank lines of ``data``, at most ``max_rows`` of them evenly spaced by index (first and last kept),
    each ending in a newline."""
    lines = [line.rstrip(b"\r") + b"\n" for line in data.split(b"\n") if line.strip()]
    if len(lines) <= max_rows:
        return lines
    return [lines[i] for i in np.linspace(0, len(lines) - 1, max_rows).round().astype(int)]


def _lines_at_offsets(fh, start: int, size: int, max_rows: int) -> list | None:
    """About ``max_rows`` lines of the open file ``fh`` (``size`` bytes, data from byte ``start``): the first
    whole line after each of evenly spaced offsets, each ending in a newline; None where a line is longer than
    :data:`MAX_LINE_BYTES` (the whole read names it)."""
    step = max((size - start) // max_rows, 1)
    lines, last_end = [], start
    for pos in range(start, size, step):
        # the first line that starts at or after pos: from the byte before it, past its newline
        fh.seek(pos - 1)
        block = fh.read(PREVIEW_BLOCK_BYTES)
        cut = block.find(b"\n")
        if cut < 0:
            return None  # a line longer than the block: the whole read names it
        line_start = pos + cut
        if line_start < last_end or line_start >= size:
            continue  # the line taken last (a line longer than the step), or the end of the file
        block = block[cut + 1 :]
        end = block.find(b"\n")
        if end < 0 and line_start + len(block) < size:  # the line goes on past the block
            fh.seek(line_start)
            block = fh.read(MAX_LINE_BYTES)
            end = block.find(b"\n")
            if end < 0 and line_start + len(block) < size:
                return None
        if end < 0:
            end = len(block)  # the file's last line, without a newline
        line = block[:end].rstrip(b"\r")
        if line.strip():
            lines.append(line + b"\n")
        last_end = line_start + end + 1
    return lines


def _arrow_table(pa, pacsv, data, header, layout, numeric):
    """The data lines ``data`` (a pyarrow buffer) read by pyarrow's CSV reader: the ``numeric`` columns as float64,
    the group and unused columns as text."""
    return pacsv.read_csv(
        pa.BufferReader(data),
        read_options=pacsv.ReadOptions(column_names=header, use_threads=True),
        parse_options=pacsv.ParseOptions(delimiter=",", quote_char=False, newlines_in_values=False),
        convert_options=pacsv.ConvertOptions(
            column_types={h: pa.float64() for h in numeric},
            include_columns=numeric
            + [header[j] for j in ([layout.group] if layout.group is not None else []) + list(layout.extra.values())],
            strings_can_be_null=False,
            quoted_strings_can_be_null=False,
        ),
    )


def _arrow_lengths(array):
    """The characters of each cell of a pyarrow array as :func:`text_cells` writes it (a null: ``'None'``, 4), or
    None where pyarrow cannot measure them (not text)."""
    import pyarrow as pa
    import pyarrow.compute as pc

    if pa.types.is_string(array.type) or pa.types.is_large_string(array.type):
        return pc.fill_null(pc.utf8_length(array), 4).to_numpy(zero_copy_only=False)
    return None


def _arrow_text(column, source, name, row_name, budget=None):
    """A pyarrow column (array or chunked array) as :func:`text_cells` makes text: the lengths of a string column
    measured by pyarrow, a null cell written ``'None'``; a dictionary column (:class:`ParquetSource` reads text so)
    measured and checked from its dictionary before a cell is made (:func:`_dictionary_text`)."""
    import pyarrow as pa

    if pa.types.is_dictionary(column.type):
        chunks = column.chunks if isinstance(column, pa.ChunkedArray) else [column]
        parts, offset = [], 0
        for chunk in chunks:
            parts.append(_dictionary_text(chunk, source, name, lambda k, o=offset: row_name(o + k), budget))
            offset += len(chunk)
        return parts[0] if len(parts) == 1 else np.concatenate(parts) if parts else np.array([], dtype=str)
    cells = np.asarray(column.to_numpy(zero_copy_only=False))
    return text_cells(cells, source, name, row_name, _arrow_lengths(column), budget)


def _dictionary_text(array, source, name, row_name, budget=None) -> np.ndarray:
    """A pyarrow ``DictionaryArray``'s cells as :func:`text_cells` makes them from the same cells decoded, without
    decoding them: each cell's length is its dictionary entry's, so a dictionary of one long value repeated over
    many rows (a Parquet bomb: 30 rows of one 100 MB value in 5.6 kB) is refused before any cell is made; the
    entries the cells use are made text once, then indexed."""
    import pyarrow as pa
    import pyarrow.compute as pc

    n = len(array)
    if n == 0:
        return np.array([], dtype=str)
    index = pc.fill_null(array.indices, -1).to_numpy(zero_copy_only=False).astype(np.int64)
    used, where = np.unique(index, return_inverse=True)
    real = used[used >= 0]
    entries = array.dictionary.take(pa.array(real, type=pa.int64()))
    lengths = _arrow_lengths(entries)  # measured in pyarrow: no cell made yet
    cells = None
    if lengths is None:  # not text (bytes, numbers): measured as written
        cells = np.asarray(entries.to_numpy(zero_copy_only=False), dtype=object)
        lengths = np.fromiter((len(str(c)) for c in cells), np.int64, count=len(cells))
    lengths = np.asarray(lengths, dtype=np.int64)
    if len(real) < len(used):  # a null cell: 'None', as astype(str) writes it
        lengths = np.concatenate([[4], lengths])
    width = _check_text(lengths[where], source, name, row_name, budget)
    measured = cells is None
    made = np.asarray(entries.to_numpy(zero_copy_only=False), dtype=object) if cells is None else cells
    if len(real) < len(used):
        made = np.concatenate([np.array([None], dtype=object), made])
    # text as wide as its longest cell; other values as numpy writes them (bytes decoded: narrower than measured)
    return (made.astype(f"<U{max(width, 1)}") if measured else made.astype(str))[where]


def _read_csv_arrow(path, columns, units, name, lsb_nT):
    """The whole file read by pyarrow's CSV reader when it is clean, else None (the caller then reads it line by
    line, which finds and names every problem).

    The head (metadata, header, layout, units) is read by :class:`CsvSource` itself, so its checks and messages
    are the same; the data lines go to pyarrow with the numeric columns typed float64, and the values to the same
    dataset builder as a CSV block. Anything unusual -- pyarrow missing, a field it cannot convert, a quoted or
    short line, a non-finite value, a problem the builder would report (it names lines, which blank lines would
    shift here) -- returns None. The dataset's ``notes`` as in :func:`read_csv`.
    """
    try:
        import pyarrow as pa
        import pyarrow.csv as pacsv
    except ImportError:
        return None
    with CsvSource(path, columns=columns, units=units, name=name, lsb_nT=lsb_nT) as src:
        header_line = src.header_line
        layout, header = src.layout, list(src.header)
        head_notes = src.notes  # any sends the file to the line-by-line reader, which says them
    if head_notes or len(set(header)) != len(header) or any(not h for h in header):
        return None
    try:
        offset = 0
        with open(os.fspath(path), "rb") as fh:  # the head's lines are shorter than MAX_LINE_BYTES (checked)
            for _ in range(header_line):
                offset += len(fh.readline())
        # memory-mapped, not read into memory: a line longer than pyarrow's block fails at once (then the line
        # reader names it), and a large file costs no copy
        raw = pa.memory_map(os.fspath(path), "r").read_buffer()
        numeric = [header[j] for j, _ in layout.numeric]
        with concurrent.futures.ThreadPoolExecutor(1) as pool:
            # a CR inside a line, which pyarrow would take for a line end: looked for beside pyarrow's parsing
            stray = pool.submit(stray_cr, raw, offset)
            table = _arrow_table(pa, pacsv, raw.slice(offset), header, layout, numeric)
            if stray.result() >= 0:
                return None  # the line reader refuses the line, naming it
    except (ValueError, OSError, pa.ArrowException):
        return None
    n = table.num_rows
    if n == 0:
        return None
    values = np.empty((n, len(numeric)))
    quaternion = layout.quaternion_positions
    for m, h in enumerate(numeric):
        col = table.column(h)
        if col.null_count and m not in quaternion:  # an empty or nan cell: the line reader names it
            return None
        values[:, m] = col.to_numpy(zero_copy_only=False)  # a null quaternion cell (empty, nan): NaN
    if bad_numeric_cells(values, quaternion).any():
        return None
    extra_names = [
        header[j] for j in ([layout.group] if layout.group is not None else []) + list(layout.extra.values())
    ]
    if any(pa.types.is_null(table.column(h).type) for h in extra_names):
        return None  # a column of nothing but nan (a live recording's channel never sent): the line reader reads it
    text = {}
    for j in ([layout.group] if layout.group is not None else []) + list(layout.extra.values()):
        try:
            text[j] = _arrow_text(table.column(header[j]), "whole file", header[j], lambda k: f"line {k}")
        except DatasetError:
            return None  # the line reader names the line
    with CsvSource(path, columns=columns, units=units, name=name, lsb_nT=lsb_nT) as src:
        try:
            ds = src._dataset(values, text, np.arange(header_line + 1, header_line + 1 + n))
        except DatasetError:
            return None
        units_used, lsb_used, source, build_notes = src.units, src.lsb_nT, src.source, src.notes
    if build_notes:
        return None  # e.g. quaternions normalised: the line-by-line reader says it with the right line numbers
    return _with_notes(ds, (), units_used, source, lsb_used)


# -- writing --------------------------------------------------------------------------------------------------------
def check_output_path(path, option="-o", directory=False) -> str:
    """Refuse, before any work is done, an output that could not be written at the end.

    Parameters
    ----------
    path : str or os.PathLike
    option : str
        How the command line names it, for the message.
    directory : bool
        The output is a new folder of partitions (it must not exist, or be an empty folder); otherwise a file
        (it must not be a folder).

    Returns
    -------
    str
        The path.

    Raises
    ------
    MagcalError
        Its folder is missing or not writable; a file output names a folder; a folder output names a file or a
        folder that holds files.
    """
    path = os.fspath(path)
    parent = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(parent):
        raise MagcalError(
            f"{option} {path}: cannot write there: the folder {parent} does not exist; create it or choose another path"
        )
    if not os.access(parent, os.W_OK | os.X_OK):
        raise MagcalError(f"{option} {path}: cannot write in the folder {parent} (permission denied)")
    if directory:
        if os.path.exists(path) and (not os.path.isdir(path) or os.listdir(path)):
            raise MagcalError(
                f"{option} {path}: exists and is not an empty directory; choose a new one (partitions are never "
                "mixed with other files)"
            )
    elif os.path.isdir(path):
        raise MagcalError(f"{option} {path}: is a directory; name a file in it (e.g. {os.path.join(path, 'out.csv')})")
    return path


def current_umask() -> int:
    """The process's umask, read without changing it where the system tells it (Linux ``/proc``); elsewhere set
    and restored at once."""
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _create_beside(path):
    """A new file beside ``path`` named ``.NAME.XXXXXXXX.tmp``, opened for writing: ``(fd, name)``.

    Created with mode 0666 less the umask, as any program's output is (``tempfile.mkstemp`` would make it 0600
    whatever the umask); when ``path`` exists, it takes that file's permissions instead.
    """
    directory = os.path.dirname(os.path.abspath(path))
    base = os.path.basename(path)
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0) | getattr(os, "O_NOFOLLOW", 0)
    for _ in range(100):
        tmp = os.path.join(directory, f".{base}.{secrets.token_hex(4)}.tmp")
        try:
            fd = os.open(tmp, flags, 0o666)
        except FileExistsError:
            continue
        try:
            if os.path.isfile(path):
                os.chmod(tmp, stat.S_IMODE(os.stat(path).st_mode))
        except OSError:
            pass
        return fd, tmp
    raise FileExistsError(f"no free temporary name beside {path}")


@contextlib.contextmanager
def atomic_write(path, mode="w", encoding="utf-8", newline=""):
    """Open a temporary file beside ``path``; on success it is flushed to disk (``fsync``) and replaces ``path``
    (``os.replace``), else it is removed, so ``path`` holds either its old content or the whole new one.

    The one atomic writer of magcal: CSV and Parquet outputs, calibration files and workbench sessions use it.
    The file gets the permissions of the file it replaces, or 0666 less the umask for a new one.

    Yields the open file object.
    """
    path = os.fspath(path)
    if os.path.isdir(path):
        raise MagcalError(f"{path}: is a directory; name a file in it (e.g. {os.path.join(path, 'out.csv')})")
    try:
        fd, tmp = _create_beside(path)
    except OSError as exc:
        raise MagcalError(f"{path}: cannot write here ({exc.strerror or exc}); check the directory") from None
    try:
        kwargs = {} if "b" in mode else {"encoding": encoding, "newline": newline}
        with os.fdopen(fd, mode, **kwargs) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def format_column(values, float_format=None):
    """Text of one column: floats in the shortest exact form (or ``float_format``), other values as text."""
    a = np.asarray(values)
    if a.dtype.kind in "fiub":
        a = a.astype(float)
        if float_format is None:
            return a.astype(str)
        return np.char.mod(float_format, a)
    return a.astype(str)


def metadata_text(metadata):
    """``# key: value`` lines (with newline) for a metadata dict; line breaks inside values become spaces."""
    out = []
    for key, value in metadata.items():
        key = " ".join(str(key).replace(":", " ").split())
        value = " ".join(str(value).splitlines())
        if key:
            out.append(f"# {key}: {value}\n")
    return "".join(out)


def write_rows(fh, columns, float_format=None):
    """Write the data rows (no header) of an ordered mapping name -> array to an open text file."""
    texts = [format_column(v, float_format) for v in columns.values()]
    if not texts:
        return
    writer = csv.writer(fh, lineterminator="\n")
    writer.writerows(zip(*texts))


def write_csv(path, data, metadata=None, float_format=None):
    """Write a dataset, or an ordered mapping of columns, as a magcal CSV file (atomically).

    Parameters
    ----------
    path : str or os.PathLike
    data : Dataset or dict of str to array_like
        A dataset is written in the documented layout with readings in nT; a mapping is written column by column
        in its order.
    metadata : dict, optional
        ``# key: value`` lines; for a dataset they are added to (and override) the dataset's own.
    float_format : str, optional
        printf-style format for numbers (e.g. ``"%.6f"``); the default writes the shortest text that reads back
        to the same float.
    """
    if isinstance(data, Dataset):
        columns = dataset_columns(data)
        meta = dataset_metadata(data)
        meta.update(metadata or {})
    else:
        columns = {str(k): np.asarray(v) for k, v in dict(data).items()}
        lengths = {len(v) for v in columns.values()}
        if len(lengths) > 1:
            raise DatasetError(f"{path}: columns of different lengths {sorted(lengths)} cannot be written as one table")
        meta = dict(metadata or {})
    with atomic_write(path) as fh:
        fh.write(metadata_text(meta))
        csv.writer(fh, lineterminator="\n").writerow(list(columns))
        write_rows(fh, columns, float_format)


# -- reading a whole file --------------------------------------------------------------------------------------------
#: Most rows a whole-file read of a Parquet file takes by default (``magcal calibrate``, ``diagnose``, ``align``,
#: ``export --data``; ``--max-rows`` changes it): a calibration record is minutes to hours of samples, far below
#: it (ten million is 28 hours at 100 Hz), and the row count of a Parquet file is not bounded by its size. A survey
#: of any length is corrected streaming (``magcal apply``), without this bound.
MAX_READ_ROWS = 10_000_000
#: Bytes per numeric value of a row while a file is read whole: the value block read, the dataset built from each
#: block and their concatenation, measured on the reader's peak (``benchmarks/bad_inputs.py`` measures it
#: beside the bombs it refuses).
READ_BYTES_PER_VALUE = 32


def check_read_rows(source, rows, columns, max_rows=None) -> None:
    """Refuse, before reading, a file of ``rows`` rows of ``columns`` numeric columns that a whole-file read cannot
    take: more than ``max_rows`` (None or 0: no limit of rows), or more than the free memory
    (:func:`magcal.core.memory.available_bytes`, at :data:`READ_BYTES_PER_VALUE` per value).

    Raises
    ------
    DatasetError
        Saying what the file holds, what the limit is and what to do.
    """
    rows = int(rows)
    if max_rows and rows > int(max_rows):
        raise DatasetError(
            f"{source}: {rows:,} rows, more than the {int(max_rows):,} read at once (--max-rows); a calibration "
            "needs minutes of samples, not this many: write the stretch you need to a file of its own, or pass "
            "--max-rows N to read more (magcal apply corrects a file of any length, streaming)"
        )
    need = rows * max(int(columns), 1) * READ_BYTES_PER_VALUE
    free = available_bytes()
    if free is not None and need > free:
        raise DatasetError(
            f"{source}: {rows:,} rows would take about {need / 1e9:.3g} GB to read, more than the "
            f"{free / 1e9:.3g} GB of memory free: read a part of them (write the stretch you need to a file of "
            "its own), or use a machine with more memory (magcal apply corrects a file of any length, streaming)"
        )


# -- Parquet ----------------------------------------------------------------------------------------------------------
#: File endings read and written as Parquet (case-insensitive).
PARQUET_EXTENSIONS = (".parquet", ".pq")
#: The key of the schema's key-value metadata that holds the data CSV's ``# key: value`` lines (a JSON object).
PARQUET_METADATA_KEY = b"magcal"


def is_parquet(path) -> bool:
    """True if ``path`` names a Parquet file (by its ending)."""
    return isinstance(path, (str, os.PathLike)) and os.fspath(path).lower().endswith(PARQUET_EXTENSIONS)


def _pyarrow(source):
    try:
        import pyarrow
        import pyarrow.parquet
    except ImportError:
        raise DatasetError(f'{source}: Parquet files need pyarrow: pip install "magcal-workbench[survey]"') from None
    return pyarrow


def parquet_metadata(schema, source="Parquet file") -> dict:
    """The ``# key: value`` metadata kept in a Parquet schema (empty when there is none).

    Raises
    ------
    DatasetError
        The ``magcal`` entry is not a JSON text (a damaged or foreign file).
    """
    import json

    raw = (schema.metadata or {}).get(PARQUET_METADATA_KEY)
    foreign = _foreign_site(schema)
    if not raw:
        return foreign
    try:
        doc = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise DatasetError(
            f"{source}: the magcal metadata in the Parquet schema is not JSON ({_one_line(exc)}); the file is "
            "damaged or was not written by magcal: write it again"
        ) from None
    found = {str(k): str(v) for k, v in doc.items()} if isinstance(doc, dict) else {}
    return {**foreign, **found}  # magcal's own entry wins


def _foreign_site(schema) -> dict:
    """``{"site": ...}`` from a schema key-value entry ``site`` another tool wrote beside (or instead of) magcal's
    own entry: read as a CSV's ``# site:`` line is (:mod:`magcal.data.site`); empty without one."""
    raw = (schema.metadata or {}).get(b"site")
    if not raw:
        return {}
    try:
        return {"site": raw.decode("utf-8").strip()}
    except UnicodeDecodeError:
        return {}


class _ParquetHead(CsvSource):
    """The CSV reader over a Parquet file's metadata and header: its messages name the schema, not a line."""

    _metadata_in = "Parquet schema"


def _one_line(exc) -> str:
    """``Type: message`` of an exception from a library, on one line and short."""
    return exception_text(exc)


#: The most bytes one text column of one row group of a Parquet file may take once its pages are decompressed
#: (the footer says it before a page is read): a text page or dictionary may hold one value, which the reader holds
#: whole, and a compressed page of one value repeated decompresses to any size. (A column of numbers is read page
#: by page, its rows bounded by the footer's count.)
MAX_PARQUET_CHUNK_BYTES = 1 << 30


def _is_text_type(kind) -> bool:
    import pyarrow as pa

    return any(
        test(kind)
        for test in (pa.types.is_string, pa.types.is_large_string, pa.types.is_binary, pa.types.is_large_binary)
    )


def _check_parquet_columns(source, schema, meta) -> None:
    """Refuse, from the footer and before any page is read, a Parquet file with a nested column (lists, structs,
    maps: magcal reads flat columns of numbers or text) or a text column chunk larger decompressed than
    :data:`MAX_PARQUET_CHUNK_BYTES` or half the memory free, naming the column, the row group and the limit."""
    import pyarrow as pa

    for f in schema:
        if pa.types.is_nested(f.type):
            raise DatasetError(
                f"{source}: column {shown(f.name)} holds {f.type} values; magcal reads flat columns of numbers or "
                "text: leave it out of the file"
            )
    free = available_bytes()
    limit = MAX_PARQUET_CHUNK_BYTES if free is None else min(MAX_PARQUET_CHUNK_BYTES, free // 2)
    text = [c for c, f in enumerate(schema) if _is_text_type(f.type)]
    for g in range(meta.num_row_groups if text else 0):
        group = meta.row_group(g)
        sizes = [group.column(c).total_uncompressed_size if c in text else 0 for c in range(group.num_columns)]
        if sizes and max(sizes) > limit:
            c = int(np.argmax(sizes))
            raise DatasetError(
                f"{source}: column {shown(group.column(c).path_in_schema)}, row group {g + 1}: "
                f"{sizes[c] / 1e6:,.0f} MB once decompressed, more than the {limit / 1e6:,.0f} MB magcal reads of "
                "a text column at a time (the smaller of 1 GiB and half the memory free); write the file with smaller "
                "row groups, or leave the column out"
            )


def _arrow_floats(column) -> np.ndarray:
    """A pyarrow column as floats, NaN for a null cell; a dictionary column (text read by :class:`ParquetSource`)
    converted entry by entry, its cells then indexed (never decoded cell by cell)."""
    import pyarrow as pa
    import pyarrow.compute as pc

    if not pa.types.is_dictionary(column.type):
        return np.asarray(column.to_numpy(zero_copy_only=False), dtype=float)
    entries = np.append(np.asarray(column.dictionary.to_numpy(zero_copy_only=False), dtype=float), np.nan)
    index = pc.fill_null(column.indices, -1).to_numpy(zero_copy_only=False).astype(np.int64)
    return entries[index]


class ParquetSource:
    """A Parquet file read by record batches through the CSV reader's own layout, units and checks.

    The metadata and the column names are given to a :class:`CsvSource` as a CSV head with no rows (so the layout,
    the units, the metadata checks are the CSV's, and the same messages); each batch's numeric columns then go to
    the same dataset builder as a CSV block. A value that is not a finite number is refused naming the file, the
    row (1-based) and the column.
    """

    def __init__(self, path, name=None, text_budget=None, columns=None):
        self.source = str(name or os.fspath(path))
        _pyarrow(self.source)
        import pyarrow.parquet as pq

        check_regular_file(path, "Parquet file", DatasetError, self.source)  # a FIFO would block
        #: What the text cells read may take (:class:`TextBudget`): None, each block its own.
        self.text_budget = text_budget
        try:
            schema = pq.read_schema(os.fspath(path))
            # text columns are read as their dictionary and indices (:func:`_dictionary_text`): a cell is made
            # only once the lengths of all of them are known to fit
            text = [f.name for f in schema if _is_text_type(f.type)]
            # no pre-buffering and a bounded read buffer: memory stays flat (pre-buffered, a 3e6-row file took 3x)
            self.file = pq.ParquetFile(
                os.fspath(path), pre_buffer=False, buffer_size=1 << 20, read_dictionary=text or None
            )
            meta = self.file.metadata
            #: The rows its row groups declare (the footer; what the reader decodes), read before any row is.
            self.rows = sum(int(meta.row_group(k).num_rows) for k in range(meta.num_row_groups))
        except FileNotFoundError:
            raise DatasetError(f"{self.source}: no such file; check the path") from None
        except Exception as exc:  # pyarrow's own errors: a damaged or non-Parquet file
            raise DatasetError(f"{self.source}: not a readable Parquet file ({_one_line(exc)})") from None
        _check_parquet_columns(self.source, schema, meta)  # the file's own types (text, not dictionaries)
        self.metadata = parquet_metadata(self.file.schema_arrow, self.source)
        self.header = list(self.file.schema_arrow.names)
        head = metadata_text(self.metadata) + ",".join(self.header) + "\n"
        import io as _stdio

        self._csv = _ParquetHead(_stdio.StringIO(head), columns=columns, name=self.source)
        #: What the reader has said so far (:attr:`CsvSource.notes`).
        self.notes = self._csv.notes
        self._csv._row_word = "row"
        self.layout = self._csv.layout

    def _batches(self, chunk_rows, row_groups):
        """The file's record batches; a damaged page or footer is a :class:`DatasetError`, not pyarrow's own."""
        import pyarrow as pa

        try:
            batches = iter(self.file.iter_batches(batch_size=chunk_rows, row_groups=row_groups, use_threads=False))
            while True:
                try:
                    batch = next(batches)
                except StopIteration:
                    return
                yield batch
        except (pa.ArrowException, OSError, ValueError, TypeError, IndexError, KeyError, RuntimeError) as exc:
            raise DatasetError(f"{self.source}: the Parquet file is damaged ({_one_line(exc)})") from None

    def chunks(self, chunk_rows=200_000, row_groups=None, first_row=1):
        """Datasets of at most ``chunk_rows`` samples (readings in nT), of every row group or of ``row_groups``
        (whose first row is the file's row ``first_row``, 1-based, for messages)."""
        row = int(first_row) - 1
        for batch in self._batches(int(chunk_rows), row_groups):
            n = batch.num_rows

            def numeric(j, name, batch=batch):
                try:
                    # a null cell (a float column's missing value) reads as NaN
                    return _arrow_floats(batch.column(j))
                except (TypeError, ValueError):
                    raise DatasetError(
                        f"{self.source}: column {name}: not numbers ({batch.schema.field(j).type}); "
                        "readings, time and channels must be numeric"
                    ) from None

            def text(j, name, batch=batch, first=row):
                rows = lambda k: f"row {first + k + 1}"
                return _arrow_text(batch.column(j), self.source, name, rows, self.text_budget)

            numbers = np.arange(row + 1, row + n + 1)
            row += n
            yield columns_block(self._csv, numeric, text, numbers)


def columns_block(src: CsvSource, numeric, text, numbers, block=" in this block") -> Dataset:
    """A dataset from a table's columns, through the CSV reader's layout, checks and messages: a Parquet file's
    record batch (:class:`ParquetSource`) or a DataFrame (:func:`magcal.data.inputs.as_dataset`).

    Parameters
    ----------
    src : CsvSource
        The reader of the table's head (its metadata and column names as a CSV head with no rows): its layout,
        units and metadata.
    numeric : callable
        ``numeric(j, name)``: the ``j``-th column (named ``name``) as floats, NaN for a missing cell; raises the
        table's own message for a column that is not numbers.
    text : callable
        ``text(j, name)``: the ``j``-th column as text (:func:`text_cells`).
    numbers : numpy.ndarray of int
        The rows' numbers (1-based) for messages (:meth:`CsvSource._where` names them).
    block : str
        How the message counts the bad rows' scope (``" in this block"``; ``""`` for a whole table).
    """
    layout = src.layout
    quaternion = layout.quaternion_positions
    values = np.empty((len(numbers), len(layout.numeric)))
    for m, (j, name) in enumerate(layout.numeric):
        values[:, m] = numeric(j, name)
    bad = bad_numeric_cells(values, quaternion)  # NaN in all four quaternion cells: no attitude, kept
    if bad.any():
        k, m = (int(i) for i in np.argwhere(bad)[0])
        partial = _partial_quaternion(values[k, quaternion]) if m in quaternion else None
        if partial is not None and np.isnan(values[k, m]):
            what = partial
        else:
            what = f"column {layout.numeric[m][1]}: {float(values[k, m])!r} is {BAD_VALUE_TEXT}"
        raise DatasetError(
            f"{src.source}: {src._where(numbers[k], 'row')}, {what} ({int(bad[:, m].sum())} such row(s){block}); "
            "fix or delete these rows"
        )
    cells = {}
    for j in ([layout.group] if layout.group is not None else []) + list(layout.extra.values()):
        cells[j] = text(j, src.header[j])
    return src._dataset(values, cells, numbers)


def read_parquet(path, name=None, chunk_rows=200_000, max_rows=None, columns=None) -> Dataset:
    """Read a Parquet file with the data CSV's columns (docs/formats.md) into a :class:`Dataset`.

    The columns are those of the CSV (``s1x`` ..., ``t``, ``temp``, ``ref_total``, ``qw..qz``, ``group``, others
    kept as extra channels); the CSV's ``# key: value`` lines are the JSON object under the schema's key-value
    metadata key ``magcal`` (units, baseline, noise...). Every check of the CSV reader applies
    (:class:`ParquetSource`), and messages name the file, the row (1-based) and the column. The dataset's ``notes``
    as in :func:`read_csv` (never raised here: :func:`read_csv` raises them).

    The rows are known from the file's footer before any is read, and refused beyond ``max_rows`` (None:
    :data:`MAX_READ_ROWS`; 0: no limit) or beyond what the free memory holds (:func:`check_read_rows`): a small
    file may hold any number of rows (1.3 MB held 1e8 constant rows, which took 9.6 GB). A file holding more rows
    than its footer says is refused as damaged when the reader finds them. ``columns``: a mapping (magcal name ->
    the file's column) as :func:`read_csv`'s, for a file whose columns are not named as magcal names them.
    """
    src = ParquetSource(path, name, text_budget=TextBudget(), columns=columns)  # one text budget for the file
    check_read_rows(src.source, src.rows, len(src.header), MAX_READ_ROWS if max_rows is None else max_rows)
    parts, rows = [], 0
    for part in src.chunks(chunk_rows):
        rows += part.n_samples
        if rows > src.rows:
            raise DatasetError(
                f"{src.source}: the file holds more rows than its footer declares ({src.rows:,}); it is damaged: "
                "write it again"
            )
        parts.append(part)
    if not parts:
        raise DatasetError(f"{src.source}: no rows; the file has no samples")
    ds = concatenate(parts)
    return _with_notes(ds, src.notes, src._csv.units, src.source, src._csv.lsb_nT)


def parquet_table(columns, metadata=None):
    """A pyarrow Table of ``columns`` (name -> NumPy or Arrow array) carrying ``metadata`` under the ``magcal``
    key."""
    import json

    pa = _pyarrow("parquet")
    table = pa.table({str(k): v if isinstance(v, pa.Array) else np.asarray(v) for k, v in columns.items()})
    meta = {PARQUET_METADATA_KEY: json.dumps({str(k): str(v) for k, v in (metadata or {}).items()}).encode()}
    return table.replace_schema_metadata({**(table.schema.metadata or {}), **meta})


#: Codecs of Parquet's float columns magcal writes (``compression`` of :func:`parquet_write_options`).
PARQUET_CODECS = ("none", "snappy", "zstd", "lz4", "gzip", "brotli")

#: The float columns' codec by default: snappy, Parquet's usual one. Readings and corrected vectors are float64
#: with noise in their last digits, so it shrinks a corrected survey by only about 11 %; ``"none"`` writes faster
#: (benchmarks/notes/apply_throughput.md), ``"zstd"`` smaller. The other columns (text, integers) are always
#: snappy-compressed.
PARQUET_FLOAT_CODEC = "snappy"


def parquet_write_options(table, compression=None) -> dict:
    """Keyword arguments of pyarrow's Parquet writers for a table of magcal columns.

    Dictionary encoding only for the non-float columns (a float channel has nearly as many values as rows, so a
    dictionary costs two thirds of the writing time and makes the file larger); the float columns compressed with
    ``compression`` (one of :data:`PARQUET_CODECS`; default :data:`PARQUET_FLOAT_CODEC`), the others with snappy.
    """
    pa = _pyarrow("parquet")
    codec = check_parquet_codec(compression)
    floats = {f.name for f in table.schema if pa.types.is_floating(f.type)}
    return {
        "use_dictionary": [f.name for f in table.schema if f.name not in floats],
        "compression": {f.name: (codec if f.name in floats else "snappy") for f in table.schema},
    }


def check_parquet_codec(compression) -> str:
    """``compression`` (None: :data:`PARQUET_FLOAT_CODEC`) checked against :data:`PARQUET_CODECS`, lower case."""
    codec = PARQUET_FLOAT_CODEC if compression is None else str(compression).lower()
    if codec not in PARQUET_CODECS:
        raise MagcalError(f"Parquet compression {compression!r}: use one of {', '.join(PARQUET_CODECS)}")
    return codec


def write_parquet(path, data, metadata=None) -> None:
    """Write a dataset (or an ordered mapping of columns) as Parquet, atomically (a temporary file, then
    ``os.replace``): the CSV's columns, readings in nT, and the metadata in the schema (``magcal`` key)."""
    if isinstance(data, Dataset):
        columns = dataset_columns(data)
        meta = dataset_metadata(data)
        meta.update(metadata or {})
    else:
        columns, meta = dict(data), dict(metadata or {})
    table = parquet_table(columns, meta)
    import pyarrow.parquet as pq

    path = os.fspath(path)
    if os.path.isdir(path):
        raise MagcalError(f"{path}: is a directory; name a file in it (e.g. {os.path.join(path, 'out.parquet')})")
    tmp = f"{path}.tmp-{os.getpid()}"
    try:
        pq.write_table(table, tmp, **parquet_write_options(table))
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
