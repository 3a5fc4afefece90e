"""The live sources by URL scheme: one :class:`SourceKind` per source, registered in :data:`LIVE_SOURCES`, and
:func:`open_source`, which reads a URL and hands it to the source of its scheme.

A source says what it is -- its name, its URL schemes, a description, the URL forms and an example, the URL options
it reads -- and opens a URL (:attr:`SourceKind.opener`, given the URL split as a :class:`SourceURL`). The built-in
sources (:mod:`~magcal.data.live.serialport`, :mod:`~magcal.data.live.network`,
:mod:`~magcal.data.live.simulated`) register themselves when :mod:`magcal.data.live` is imported. An installed
package adds its own in the entry-point group ``magcal.live_sources`` (``[project.entry-points."magcal.live_sources"]
toy = "my_pkg.live:TOY"``, a :class:`SourceKind` or a module registering some): :func:`load_entry_points` loads
them, once; ``magcal record`` calls it. CONTRIBUTING.md has the recipe.
"""

from __future__ import annotations

import re
import urllib.parse
from collections.abc import Callable
from dataclasses import dataclass

from magcal.core.errors import MagcalError
from magcal.core.registry import Loaded, Registry
from magcal.data.live.parser import LineParser
from magcal.data.live.source import LiveError, LiveSource

#: The entry-point group installed packages declare their live sources in.
ENTRY_POINT_GROUP = "magcal.live_sources"

#: What a URL scheme may look like (RFC 3986, lower case).
SCHEME_PATTERN = re.compile(r"^[a-z][a-z0-9+.-]{0,31}$")

#: The options of a text-line source (:meth:`SourceURL.line_parser`).
LINE_OPTIONS = ("columns", "template", "sep", "units", "lsb", "prefix", "checksum")


@dataclass(frozen=True, eq=False)
class SourceKind:
    """One live source.

    Attributes
    ----------
    name : str
        Its name (lower-case letters, digits, ``_`` or ``-``).
    schemes : tuple of str
        The URL schemes it opens (``serial``; ``udp`` and ``tcp``); no other source may take one.
    description : str
        What it reads, one sentence.
    forms : tuple of str
        Its URL forms, as a message lists them (``serial://DEVICE``).
    example : str
        A URL that opens it (``sim://chi2017?rate=50``).
    options : tuple of str
        The URL options it reads (``baud``, ``rate`` ...); ``open_source`` refuses an option no source reads.
    opener : callable
        ``opener(url: SourceURL) -> LiveSource``; raises :class:`~magcal.data.live.source.LiveError` naming the URL
        and what to change.
    """

    name: str
    schemes: tuple
    description: str
    forms: tuple
    example: str
    options: tuple
    opener: Callable

    def open(self, url: SourceURL) -> LiveSource:
        """The source ``url`` names (see :attr:`opener`)."""
        source = self.opener(url)
        if not isinstance(source, LiveSource):
            raise LiveError(f"{url.url}: the {self.name} source gave {type(source).__name__}, not a LiveSource")
        return source


def _check(kind: SourceKind, registry) -> None:
    """Its schemes are URL schemes no other source takes; its texts and options are given; it has an opener."""
    if not kind.schemes or not all(isinstance(s, str) and SCHEME_PATTERN.match(s) for s in kind.schemes):
        raise MagcalError(f"live source {kind.name!r}: give its URL schemes (lower case, e.g. ('toy',))")
    for other in registry.values():
        taken = set(other.schemes) & set(kind.schemes)
        if other.name != kind.name and taken:
            raise MagcalError(f"live source {kind.name!r}: scheme {sorted(taken)[0]!r} is {other.name!r}'s")
    if not all(isinstance(t, str) and t.strip() for t in (kind.description, kind.example, *kind.forms)):
        raise MagcalError(f"live source {kind.name!r}: give its description, forms and example (texts)")
    if not all(isinstance(o, str) and o for o in kind.options) or not callable(kind.opener):
        raise MagcalError(f"live source {kind.name!r}: give its options (names) and its opener (a function)")


#: Every live source by name, in the order they were registered (the built-ins first).
LIVE_SOURCES: Registry[SourceKind] = Registry("live source", ENTRY_POINT_GROUP, SourceKind, _check)


def register_source(kind: SourceKind, replace: bool = False) -> SourceKind:
    """Add a live source to :data:`LIVE_SOURCES` (returns it)."""
    return LIVE_SOURCES.register(kind, replace=replace, depth=2)


def load_entry_points(force: bool = False) -> Loaded:
    """Add the sources installed packages declare in ``magcal.live_sources`` (once): see
    :meth:`magcal.core.registry.Registry.load_entry_points` (the names added, and the skipped ones' ``notes``)."""
    return LIVE_SOURCES.load_entry_points(force=force)


def schemes() -> tuple[str, ...]:
    """Every registered URL scheme, in registration order."""
    return tuple(s for kind in LIVE_SOURCES.values() for s in kind.schemes)


def source_for(scheme: str) -> SourceKind | None:
    """The source that opens URLs of ``scheme``, or None."""
    return next((k for k in LIVE_SOURCES.values() if scheme in k.schemes), None)


def known_options() -> set[str]:
    """The URL options some registered source reads."""
    return {o for kind in LIVE_SOURCES.values() for o in kind.options}


class SourceURL:
    """A source URL split: its scheme, its place (host and port, or a device or preset), and its options (the
    URL's query with the caller's options over it).

    Parameters
    ----------
    url : str
        The URL as given (every message names it).
    parsed : urllib.parse.SplitResult
    params : dict of str to str
        The options, each its last value in the query.
    """

    def __init__(self, url: str, parsed, params: dict):
        self.url = url
        self.parsed = parsed
        self.scheme = parsed.scheme.lower()
        self.params = params

    def __str__(self) -> str:
        return self.url

    @property
    def target(self) -> str:
        """What the URL names after ``SCHEME://``, unquoted: a device path, a preset or a file."""
        parsed = self.parsed
        return urllib.parse.unquote((parsed.netloc + parsed.path) if parsed.netloc else parsed.path)

    def flag(self, name: str) -> bool:
        """Whether option ``name`` is given as a flag (``?mavlink``, ``loop=1``, ``yes``, ``true``, ``on``)."""
        return name in self.params and self.params[name] in ("", "1", "true", "yes", "on")

    @property
    def mavlink(self) -> bool:
        """Whether the URL asks for MAVLink (``?mavlink`` or ``format=mavlink``)."""
        return self.flag("mavlink") or self.params.get("format", "").lower() == "mavlink"

    def number(self, name: str, default, kind=float, bounds=None):
        """Option ``name`` as a number of ``kind`` (``default`` when not given), within ``bounds`` (inclusive)."""
        params = self.params
        try:
            value = kind(params[name]) if name in params else default
        except (ValueError, OverflowError):
            what = "a whole number" if kind is int else "a number"  # 14551.5 is refused, never truncated
            raise LiveError(f"{self.url}: {name}={params[name][:40]!r} is not {what}") from None
        if bounds is not None and value is not None and not bounds[0] <= value <= bounds[1]:
            raise LiveError(f"{self.url}: {name}={params[name][:40]!r}: give {bounds[0]:g} to {bounds[1]:g}")
        return value

    def host_port(self) -> tuple[str, int]:
        """``(host, port)`` of a ``SCHEME://HOST:PORT`` URL."""
        scheme = self.scheme
        try:
            host, port = self.parsed.hostname, self.parsed.port
        except ValueError as exc:  # a port that is not a number, or beyond 65535
            raise LiveError(
                f"{self.url}: {exc}; give the address as {scheme}://HOST:PORT with a port of 1 to 65535"
            ) from None
        if not host or not port:
            raise LiveError(f"{self.url}: give the address as {scheme}://HOST:PORT (e.g. {scheme}://127.0.0.1:14550)")
        return host, port

    def line_parser(self) -> LineParser:
        """The text-line parser the options describe (:data:`LINE_OPTIONS`)."""
        params = self.params
        check = params.get("checksum", "on").lower()
        if check not in ("on", "off", "1", "0", "true", "false", "yes", "no", ""):
            raise LiveError(f"{self.url}: checksum={params['checksum'][:20]!r}: give checksum=on or checksum=off")
        try:
            return LineParser(
                params.get("columns") or None,
                params.get("sep") or None,
                params.get("units", "nT"),
                params.get("lsb"),
                params.get("prefix"),
                template=params.get("template") or None,
                checksum=check not in ("off", "0", "false", "no"),
            )
        except MagcalError as exc:
            raise LiveError(f"{self.url}: {exc}") from None


def open_source(url: str, **options) -> LiveSource:
    """Open a live source from its URL (:mod:`magcal.data.live` lists the built-in forms); ``options`` override
    URL parameters. The source of the URL's scheme (:data:`LIVE_SOURCES`) opens it.

    Raises
    ------
    LiveError
        A malformed URL, an unknown scheme or option, or a port that cannot be opened.
    """
    try:
        parsed = urllib.parse.urlsplit(str(url))
    except ValueError as exc:  # e.g. tcp://[::1 (an unclosed IPv6 bracket)
        raise LiveError(f"{url}: not a valid source URL ({exc})") from None
    kind = source_for(parsed.scheme.lower())
    if kind is None:
        kinds = list(LIVE_SOURCES.values())
        forms = [f for k in kinds for f in k.forms]
        listed = ", ".join(forms[:-1]) + " or " + forms[-1] if len(forms) > 1 else "".join(forms)
        example = f" (e.g. {kinds[-1].example})" if kinds else ""
        raise LiveError(f"{url}: unknown source; use {listed}{example}")
    params = {k: v[-1] for k, v in urllib.parse.parse_qs(parsed.query, keep_blank_values=True).items()}
    if options.get("template") is not None:  # a template given as an option replaces the URL's columns
        params.pop("columns", None)
    if options.get("columns") is not None:  # and the reverse
        params.pop("template", None)
    params.update({k: str(v) for k, v in options.items() if v is not None})
    known = known_options()
    unknown = sorted(set(params) - known)
    if unknown:
        raise LiveError(f"{url}: unknown option(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}")
    return kind.open(SourceURL(str(url), parsed, params))
