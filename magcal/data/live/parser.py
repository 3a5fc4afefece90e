"""Text lines made samples: :class:`LineParser` (separated numbers, framed lines, bracketed lists or a template,
with units, column names and channels; :mod:`magcal.data.lineformats` reads the line formats)."""

from __future__ import annotations

import re

import numpy as np

from magcal.data import lineformats
from magcal.data.dataset import SENSOR_AXES
from magcal.data.io import is_counts, parse_units
from magcal.data.live.source import LiveError

_SPLIT_DEFAULT = re.compile(r"[,;\t ]+")


class LineParser:
    """Turns one text line into a sample: separated numbers, a framed line, a bracketed list or a template
    (:mod:`magcal.data.lineformats` has the formats).

    Parameters
    ----------
    columns : str or sequence of str, optional
        Names of the fields in order (default ``x,y,z``): ``x,y,z`` or ``mx,my,mz`` (sensor 1), ``s1x..s4z``,
        ``t`` (s; ``t_ms``, ``t_us``), ``temp`` (degC), the channels ``roll, pitch, yaw`` (deg), ``gx, gy, gz``
        (deg/s), ``ax, ay, az``, ``lat, lon`` (deg), ``alt`` (m), ``_`` (skipped).
    sep : str, optional
        Field separator; default any run of commas, semicolons, tabs or spaces.
    units : str
        Unit of the readings (``nT``, ``uT``, ``G``, ``mG``, or ``counts`` with ``lsb_nT``).
    lsb_nT : float, optional
        nT per count for ``counts``.
    prefix : str, optional
        Only lines starting with it are data (it is removed); other lines are skipped, not counted as bad.
    template : str, optional
        The line written out with its fields in braces, e.g. ``x={x} y={y} z={z}`` (instead of ``columns``).
    checksum : bool
        Check a trailing ``*hh`` checksum of a framed line (it is stripped either way).

    Attributes
    ----------
    n_sensors : int
    channel_names : tuple of str
        The channels each sample carries (:attr:`LiveChunk.channels`).
    last_skip : str or None
        Why the last line :meth:`parse` returned None for was not data.
    """

    def __init__(self, columns=None, sep=None, units="nT", lsb_nT=None, prefix=None, template=None, checksum=True):
        if template is not None and columns is not None:
            raise LiveError("give columns or a template, not both (a template names its own fields)")
        if template is not None:
            try:
                self.template = lineformats.LineTemplate(template)
            except ValueError as exc:
                raise LiveError(str(exc)) from None
            names = list(self.template.fields)
        else:
            self.template = None
            columns = "x,y,z" if columns is None else columns
            names = [c.strip() for c in (columns.split(",") if isinstance(columns, str) else columns)]
        self.columns = names
        self.sep = sep
        self.prefix = prefix or None
        self.checksum = bool(checksum)
        self.last_skip = None
        self.factor = parse_units(units, where="live source units", lsb_nT=lsb_nT if is_counts(units) else None)
        self.index_t = self.index_temp = None
        self.time_factor = 1.0
        axes, channels, seen, used = {}, {}, {}, []
        for j, name in enumerate(names):
            try:
                role = lineformats.column_role(name)
            except ValueError as exc:
                raise LiveError(f"columns: {exc}") from None
            kind = role[0]
            if kind == "skip":
                continue
            key = role if kind != "time" else ("time",)
            if key in seen:
                raise LiveError(
                    f"columns: {name!r} and {seen[key]!r} name the same field"
                    if seen[key] != name
                    else f"columns: {name!r} appears twice"
                )
            seen[key] = name
            used.append(j)
            if kind == "time":
                self.index_t, self.time_factor = j, role[1]
            elif kind == "temp":
                self.index_temp = j
            elif kind == "channel":
                channels[role[1]] = j
            else:
                axes[(role[1], role[2])] = j
        sensors = sorted({s for s, _ in axes})
        if not sensors or sensors != list(range(1, len(sensors) + 1)):
            raise LiveError(f"columns {','.join(names)}: name sensors 1.. without gaps (x,y,z or s1x,s1y,s1z,...)")
        for s in sensors:
            if any((s, a) not in axes for a in SENSOR_AXES):
                raise LiveError(f"columns {','.join(names)}: sensor {s} needs x, y and z")
        self.index_xyz = np.array([[axes[(s, a)] for a in SENSOR_AXES] for s in sensors])
        self.n_sensors = len(sensors)
        self.channel_names = tuple(channels)
        self._index_channels = np.array(list(channels.values()), dtype=int)
        self._used = used

    def _split(self, text):
        return text.split(self.sep) if self.sep else _SPLIT_DEFAULT.split(text)

    def _skip(self, reason):
        self.last_skip = reason
        return None

    def parse(self, text):
        """``(t or None, readings (n_sensors, 3) nT, temperature or None)``, or ``None`` for a line that is not data
        (:attr:`last_skip` says why).

        Raises
        ------
        ValueError
            With the reason, for a line that should be data but is not.
        """
        sample = self.parse_sample(text)
        return None if sample is None else sample[:3]

    def parse_sample(self, text):
        """:meth:`parse` with the channels: ``(t, readings, temperature, {channel: value})`` or None."""
        self.last_skip = None
        text = text.strip()
        if not text:
            return self._skip("empty line")
        if text.startswith("#"):
            return self._skip("comment")
        if self.prefix is not None:
            if not text.startswith(self.prefix):
                return self._skip(f"no prefix: the line does not start with {self.prefix!r}")
            text = text[len(self.prefix) :].strip()
        if self.template is not None:
            fields = self.template.match(text)  # raises "template: ..."
        else:
            text = lineformats.strip_frame(text, self.checksum)  # raises "checksum: ..."
            if lineformats.has_brackets(text):
                fields = lineformats.bracketed_fields(text, len(self.columns), self._split)
            else:
                fields = self._split(text)
            if len(fields) != len(self.columns):
                raise ValueError(
                    f"field count: {len(fields)} field(s), expected {len(self.columns)} ({','.join(self.columns)})"
                )
        values = np.full(len(fields), np.nan)
        for j in self._used:  # a skipped field may hold anything
            f = fields[j]
            try:
                values[j] = float(f) if f.strip() else np.nan
            except ValueError:
                raise ValueError(f"not a number: {f[:30]!r}") from None
        readings = values[self.index_xyz] * self.factor
        t = None if self.index_t is None else float(values[self.index_t]) * self.time_factor
        temp = None if self.index_temp is None else float(values[self.index_temp])
        channels = dict(zip(self.channel_names, values[self._index_channels].tolist()))
        return t, readings, temp, channels
