"""The text-line formats sensor sketches print, for the live sources' :class:`magcal.data.live.LineParser`.

Three ways to read a line, besides plain separated numbers (``1.5,20.1,-3.2,41.0``):

a template (``template=...``)
    The line written out with the fields in braces: ``x={x} y={y} z={z}``, ``Magnetometer reading: [{x}, {y},
    {z}]``, ``{t_ms}: mag {mx} {my} {mz} att {roll} {pitch} {yaw}``. Every other character is literal; whitespace
    is optional around every literal word or punctuation mark (``x = 1`` matches ``x={x}``); ``{_}`` skips a
    field (any text); ``{{`` and ``}}`` are literal braces. Numbers are read in any float syntax (``-12``,
    ``1.5e3``, ``.5``, ``+2.``, ``nan``, ``inf``). The template describes the whole line (after a ``prefix``).
a frame
    A leading ``|`` or ``$`` and a trailing ``*`` (or ``|``) are stripped; a trailing NMEA-like checksum ``*hh``
    (two hex digits: the XOR of the characters between the start mark and ``*``) is checked, and a line whose
    checksum differs is refused (``checksum=off`` strips it without checking). So
    ``|1234,0.01,0.02,1.0,0.1,0.2,0.3,21.5,-3.2,40.1,1.5,-0.5,87.0*`` reads with
    ``columns=t_ms,ax,ay,az,gx,gy,gz,mx,my,mz,roll,pitch,yaw``.
bracketed lists
    A line holding a list in brackets, ``[x, y, z]`` or ``(x, y, z)`` anywhere in it (``Magnetometer reading: [21.5,
    -3.2, 40.1] uT``), is read from the one list with as many numbers as there are columns; a line with several
    such lists is refused (give a template to say which).

Field and column names (:func:`column_role`): ``x, y, z`` or ``mx, my, mz`` (sensor 1), ``s1x .. s4z``; ``t`` (s),
``t_ms`` (ms), ``t_us`` (us); ``temp`` (degC); the channels of :data:`CHANNEL_ALIASES`: ``roll, pitch, yaw`` (deg,
aerospace ZYX, body -> north-east-down, as :mod:`magcal.data.attitude` reads them), ``gx, gy, gz`` (gyro, deg/s),
``ax, ay, az`` (accelerometer, in the sketch's own unit), ``lat, lon`` (deg) and ``alt`` (m above the
ellipsoid); ``_`` skips one.

Nothing here raises a magcal error: a bad template or column name is a :class:`ValueError` that
:class:`~magcal.data.live.LineParser` turns into a :class:`~magcal.data.live.LiveError`, and a line that does not
fit is a :class:`ValueError` whose text starts with the reason (``template: ...``, ``checksum: ...``,
``brackets: ...``), which the live source counts.
"""

from __future__ import annotations

import functools
import re
import string

#: A number in any float syntax Python reads (sign, decimals, exponent, ``nan``, ``inf``, ``infinity``), not
#: starting inside another number and not followed by more of one.
NUMBER = (
    r"(?<![\d.])(?<![\d.][eE])(?<![\d.][eE][-+])[-+]?(?:(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?|(?i:nan|inf(?:inity)?))"
    r"(?![\d.]|[eE][-+]?\d)"
)
#: What ``{_}`` matches: any text (the least that lets the rest of the line match).
SKIP = r".*?"

#: Channel names of the columns a line may hold besides the magnetometer, time and temperature: name in a line or
#: template -> the channel (the Dataset ``extra`` column it becomes).
CHANNEL_ALIASES = {
    "roll": "roll_deg",
    "pitch": "pitch_deg",
    "yaw": "yaw_deg",
    "gx": "gyro_x_dps",
    "gy": "gyro_y_dps",
    "gz": "gyro_z_dps",
    "gyro_x": "gyro_x_dps",
    "gyro_y": "gyro_y_dps",
    "gyro_z": "gyro_z_dps",
    "ax": "accel_x",
    "ay": "accel_y",
    "az": "accel_z",
    "lat": "lat",
    "lon": "lon",
    "alt": "alt_m",
}
#: The channels and their units.
CHANNEL_UNITS = {
    "roll_deg": "deg",
    "pitch_deg": "deg",
    "yaw_deg": "deg",
    "gyro_x_dps": "deg/s",
    "gyro_y_dps": "deg/s",
    "gyro_z_dps": "deg/s",
    "accel_x": "as sent",
    "accel_y": "as sent",
    "accel_z": "as sent",
    "lat": "deg",
    "lon": "deg",
    "alt_m": "m",
}
#: Time columns and their factor to s.
TIME_COLUMNS = {"t": 1.0, "t_s": 1.0, "t_ms": 1e-3, "t_us": 1e-6}
#: Names of a skipped field.
SKIP_NAMES = ("_", "-", "")

_SENSOR_RE = re.compile(r"^(?:s([1-4])|m)?([xyz])$")


def column_role(name: str):
    """What a column or template field named ``name`` holds.

    Returns
    -------
    tuple
        ``("sensor", s, axis)`` (sensor 1-4, axis ``x``/``y``/``z``), ``("time", factor_to_s)``, ``("temp",)``,
        ``("channel", channel_name)`` or ``("skip",)``.

    Raises
    ------
    ValueError
        An unknown name (the message lists the known ones).
    """
    name = name.strip()
    if name in SKIP_NAMES:
        return ("skip",)
    if name in TIME_COLUMNS:
        return ("time", TIME_COLUMNS[name])
    if name == "temp":
        return ("temp",)
    m = _SENSOR_RE.match(name)
    if m:
        return ("sensor", int(m.group(1) or 1), m.group(2))
    if name in CHANNEL_ALIASES:
        return ("channel", CHANNEL_ALIASES[name])
    if name in CHANNEL_UNITS:
        return ("channel", name)
    raise ValueError(
        f"{name!r} is not a known field: x, y, z (or mx, my, mz), s1x..s4z, t (s), t_ms, t_us, temp (degC), "
        "roll, pitch, yaw (deg), gx, gy, gz (deg/s), ax, ay, az, lat, lon, alt (m) or _ (skip)"
    )


# -- templates -------------------------------------------------------------------------------------------------------
_LITERAL_TOKEN = re.compile(r"\w+|\S")


class LineTemplate:
    """A line template such as ``x={x} y={y} z={z}`` (see the module docstring).

    Parameters
    ----------
    text : str
        The template; fields in braces (``{x}``), ``{_}`` to skip, ``{{``/``}}`` for literal braces.

    Attributes
    ----------
    fields : list of str
        The named fields in order (``_`` left out).

    Raises
    ------
    ValueError
        A malformed template (an unclosed brace, a format spec), an unknown or repeated field, or none at all.
    """

    def __init__(self, text: str):
        self.text = str(text)
        try:
            parts = list(string.Formatter().parse(self.text))
        except ValueError as exc:  # "Single '}' encountered", "expected '}' before end of string"
            raise ValueError(f"template {self.text!r}: {exc} (write {{{{ and }}}} for literal braces)") from None
        #: (kind, regex, description) per token: kind "lit", "num" or "skip"
        self._tokens: list[tuple[str, str, str]] = []
        self.fields: list[str] = []
        for literal, name, spec, conversion in parts:
            for word in _LITERAL_TOKEN.findall(literal):
                self._tokens.append(("lit", re.escape(word), repr(word)))
            if name is None:
                continue
            if spec or conversion:
                raise ValueError(f"template {self.text!r}: write fields as {{name}}, without ':' or '!' ({{{name}}})")
            role = column_role(name)  # raises for an unknown name
            if role[0] == "skip":
                self._tokens.append(("skip", SKIP, "{_}"))
                continue
            if name in self.fields:
                raise ValueError(f"template {self.text!r}: field {{{name}}} appears twice")
            self.fields.append(name)
            self._tokens.append(("num", f"({NUMBER})", f"a number for {{{name}}}"))
        if not self.fields:
            raise ValueError(f"template {self.text!r}: no field; write the readings as {{x}}, {{y}}, {{z}}")
        self._regex = re.compile(self._pattern(len(self._tokens)) + r"\s*")

    def _pattern(self, k):
        return r"\s*" + r"\s*".join(t[1] for t in self._tokens[:k])

    @functools.lru_cache(maxsize=64)  # noqa: B019 - a handful of templates live as long as their sources
    def _prefix(self, k):
        return re.compile(self._pattern(k))

    def match(self, line: str) -> list[str]:
        """The text of each named field (in :attr:`fields` order).

        Raises
        ------
        ValueError
            ``template: ...`` saying where the line departs from the template.
        """
        m = self._regex.fullmatch(line)
        if m is not None:
            return list(m.groups())
        k = 0  # the longest start of the template the line matches
        end = 0
        for j in range(1, len(self._tokens) + 1):
            p = self._prefix(j).match(line)
            if p is None:
                break
            k, end = j, p.end()
        if k == len(self._tokens):
            rest = line[end:].strip()
            raise ValueError(f"template: text after the template's end: {rest[:30]!r}")
        want = self._tokens[k][2]
        found = line[end:].lstrip()[:20]
        found = repr(found) if found else "the line's end"
        raise ValueError(f"template: expected {want} at character {end + 1}, found {found}")


# -- frames and checksums ----------------------------------------------------------------------------------------------
_CHECKSUM_RE = re.compile(r"\*([0-9A-Fa-f]{2})$")
#: Characters that open a framed line, and that close one.
FRAME_START = "|$"
FRAME_END = "*|"


def nmea_checksum(text: str) -> int:
    """XOR of the bytes of ``text`` (the NMEA 0183 checksum, computed between ``$`` and ``*``)."""
    value = 0
    for b in text.encode("utf-8", "replace"):
        value ^= b
    return value


def strip_frame(text: str, check: bool = True) -> str:
    """``text`` without a leading ``|`` or ``$``, a trailing ``*hh`` checksum (checked unless ``check`` is False), or
    a trailing ``*`` or ``|``.

    Raises
    ------
    ValueError
        ``checksum: ...`` when the checksum differs from the XOR of the characters between the start mark and ``*``.
    """
    text = text.strip()
    if text[:1] and text[0] in FRAME_START:
        text = text[1:]
    m = _CHECKSUM_RE.search(text)
    if m is not None:
        body = text[: m.start()]
        if check:
            sent = int(m.group(1), 16)
            computed = nmea_checksum(body)
            if sent != computed:
                raise ValueError(
                    f"checksum: the line says {sent:02X}, its text gives {computed:02X} (XOR of the characters "
                    "between the start mark and '*'); a damaged line, or give checksum=off"
                )
        text = body
    elif text[-1:] and text[-1] in FRAME_END:
        text = text[:-1]
    return text.strip()


# -- bracketed lists -----------------------------------------------------------------------------------------------
_BRACKETS_RE = re.compile(r"\[([^\[\]()]*)\]|\(([^\[\]()]*)\)")


def has_brackets(text: str) -> bool:
    """True when ``text`` holds a ``[...]`` or ``(...)`` list."""
    return _BRACKETS_RE.search(text) is not None


def bracketed_fields(text: str, n_fields: int, split) -> list[str]:
    """The fields of the one bracketed list of ``text`` with ``n_fields`` fields (``split`` splits a list's text).

    Raises
    ------
    ValueError
        ``brackets: ...`` when no list, or more than one, has ``n_fields`` fields.
    """
    lists = [split((m.group(1) if m.group(1) is not None else m.group(2)).strip()) for m in _BRACKETS_RE.finditer(text)]
    fitting = [f for f in lists if len(f) == n_fields]
    if len(fitting) == 1:
        return fitting[0]
    if not fitting:
        sizes = ", ".join(str(len(f)) for f in lists) or "none"
        raise ValueError(f"brackets: no bracketed list of {n_fields} fields (lists of {sizes})")
    raise ValueError(f"brackets: {len(fitting)} bracketed lists of {n_fields} fields; give a template to say which")
