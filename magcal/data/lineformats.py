"""The text-line formats sensor sketches print, for the live sources' :class:`magcal.data.live.LineParser`.

Three ways to read a line, besides plain separated numbers (``1.5,20.1,-3.2,41.0``):

a template (``template=...``)
    The line written out with the fields in braces: ``x={x} y={y} z={z}``, ``Magnetometer reading: [{x}, {y},
    {z}]``, ``{t_ms}: mag {mx} {my} {mz} att {roll} {pitch} {yaw}``. Every other character is literal; whitespace
    is optional around every literal word or punctuation mark (``x = 1`` matches ``x={x}``); ``{_}`` skips a
    field (any text); ``{{`` and ``}}`` are literal braces. Numbers are read in any float syntax (``-12``,
    ``1.5e3``, ``.5``, ``+2.``, ``nan``, ``inf``), each as far as it goes. The template describes the whole line
    (after a ``prefix``). A line is matched in time linear in its length whatever it holds (no backtracking:
    :class:`LineTemplate`); a template holds at most :data:`MAX_TEMPLATE_CHARS` characters.
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

import re
import string

#: A number in any float syntax Python reads (sign, decimals, exponent, ``nan``, ``inf``, ``infinity``), not
#: starting inside another number and not followed by more of one. Atomic, with possessive digits: the number at a
#: place is read once, as far as it goes, and never tried again shorter (a shorter one would be followed by more of
#: a number), so a line of 4000 digits costs about 4000 steps, not 4000^2.
NUMBER = (
    r"(?<![\d.])(?<![\d.][eE])(?<![\d.][eE][-+])"
    r"(?>[-+]?+(?:(?:\d++\.?+\d*+|\.\d++)(?:[eE][-+]?+\d++)?+|(?i:nan|infinity|inf))(?![\d.]|[eE][-+]?\d))"
)
#: Longest template (characters). With the longest line a live source takes (``magcal.data.live.MAX_LINE_BYTES``)
#: it bounds what one line may cost: the match is linear in the line's length times the template's tokens.
MAX_TEMPLATE_CHARS = 1000

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
#: Whitespace between two tokens of a template: optional, possessive (a token never starts with whitespace).
_GAP = r"\s*+"


class _Segment:
    """The tokens of a template between two skips (``{_}``), matched without backtracking.

    Each token (a literal word, a number) matches at a given place in one way or not at all, and the whitespace
    between them is possessive, so the segment's match from a given start is decided in one pass over what it
    covers. ``anchored``: the segment starts the line (no skip before it), else it may start anywhere after the
    text already matched; ``last``: it ends the line (no skip after it).
    """

    def __init__(self, tokens, anchored: bool, last: bool):
        self.tokens = tokens  # (kind "lit" or "num", regex, description)
        self.anchored = anchored
        self.last = last
        self._regex: dict[tuple[int, bool], re.Pattern] = {}

    def _pattern(self, k: int, held: bool) -> re.Pattern:
        """The first ``k`` tokens, held to the line's end or not."""
        if (k, held) not in self._regex:
            body = _GAP.join(t[1] for t in self.tokens[:k])
            self._regex[(k, held)] = re.compile((_GAP if self.anchored else "") + body + (_GAP + r"\Z" if held else ""))
        return self._regex[(k, held)]

    def find(self, line: str, pos: int, k: int | None = None) -> re.Match | None:
        """The match of the segment (held to the line's end if it is the last), or of its first ``k`` tokens (never
        held), at or after ``pos`` that ends first, or None.

        Anchored: only at ``pos``. Held to the line's end: the leftmost start (all end there). Otherwise the
        earliest end, so that the rest of the template (which starts with a skip) has the most room; each start
        is tried once, so the cost stays linear in the text scanned.
        """
        held = k is None and self.last
        regex = self._pattern(len(self.tokens) if k is None else k, held)
        if self.anchored:
            return regex.match(line, pos)
        best = regex.search(line, pos)
        if best is None or held:
            return best
        m: re.Match | None = best
        while m is not None and m.start() + 1 < best.end():  # a later start could still end earlier
            m = regex.search(line, m.start() + 1)
            if m is not None and m.end() < best.end():
                best = m
        return best


class LineTemplate:
    """A line template such as ``x={x} y={y} z={z}`` (see the module docstring).

    A line is matched in time linear in its length (times the template's tokens), whatever it holds: the numbers
    are read possessively (:data:`NUMBER`), and a skip never backtracks into the text before it: the tokens
    between two skips (a segment) are placed where they end first after the previous segment, which leaves the
    rest of the template the most room, so a line matches exactly when it can (adjacent skips are one).

    Parameters
    ----------
    text : str
        The template; fields in braces (``{x}``), ``{_}`` to skip, ``{{``/``}}`` for literal braces; at most
        :data:`MAX_TEMPLATE_CHARS` characters.

    Attributes
    ----------
    fields : list of str
        The named fields in order (``_`` left out).

    Raises
    ------
    ValueError
        A malformed template (an unclosed brace, a format spec), an unknown or repeated field, none at all, or a
        template over :data:`MAX_TEMPLATE_CHARS` characters.
    """

    def __init__(self, text: str):
        self.text = str(text)
        if len(self.text) > MAX_TEMPLATE_CHARS:
            raise ValueError(
                f"template {self.text[:40]!r}...: {len(self.text)} characters, at most {MAX_TEMPLATE_CHARS}; write "
                "the line's start and end and {_} for the rest"
            )
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
                self._tokens.append(("skip", "", "{_}"))
                continue
            if name in self.fields:
                raise ValueError(f"template {self.text!r}: field {{{name}}} appears twice")
            self.fields.append(name)
            self._tokens.append(("num", f"({NUMBER})", f"a number for {{{name}}}"))
        if not self.fields:
            raise ValueError(f"template {self.text!r}: no field; write the readings as {{x}}, {{y}}, {{z}}")
        runs: list[list] = [[]]
        for token in self._tokens:
            if token[0] == "skip":
                runs.append([])
            else:
                runs[-1].append(token)
        #: the runs of tokens between skips; an empty one between two skips is nothing
        self._segments = [
            _Segment(run, anchored=(i == 0), last=(i == len(runs) - 1))
            for i, run in enumerate(runs)
            if run or i in (0, len(runs) - 1)
        ]

    def match(self, line: str) -> list[str]:
        """The text of each named field (in :attr:`fields` order).

        Raises
        ------
        ValueError
            ``template: ...`` saying where the line departs from the template.
        """
        found: list[str] = []
        pos = 0
        for seg in self._segments:
            m = seg.find(line, pos)
            if m is None:
                raise ValueError(self._departure(line, seg, pos))
            found += m.groups()
            pos = m.end()
        return found

    def _departure(self, line, seg, pos):
        """``template: ...``: where ``line`` departs from segment ``seg`` (which does not match from ``pos``)."""
        n = len(seg.tokens)
        if seg.last and n:  # the last segment may be there, with text after it
            m = seg.find(line, pos, n)
            if m is not None:
                return f"template: text after the template's end: {line[m.end() :].strip()[:30]!r}"
        lo, hi = 0, n - 1  # the longest start of the segment found in the line (bisection: a start of one is one)
        while lo < hi:
            k = (lo + hi + 1) // 2
            if seg.find(line, pos, k) is not None:
                lo = k
            else:
                hi = k - 1
        m = seg.find(line, pos, lo) if lo else None
        end = m.end() if m is not None else pos + len(line[pos:]) - len(line[pos:].lstrip())
        rest = line[end:].lstrip()[:20]
        shown = repr(rest) if rest else "the line's end"
        return f"template: expected {seg.tokens[lo][2]} at character {end + 1}, found {shown}"


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
