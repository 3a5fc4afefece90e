"""The record's site: where and when it was recorded, from a data file's ``# site:`` line.

A data CSV may say where and when it was recorded in one metadata line::

    # site: 53.0 N, 4.5 E, 1500 m, 2024-06-01

latitude (``N`` or ``S``, or a signed number), longitude (``E`` or ``W``, or a signed number, east positive),
height above the WGS84 ellipsoid (``m`` or ``km``) and the date (``YYYY-MM-DD`` or a decimal year such as
``2024.5``). The CSV reader (:mod:`magcal.data.io`) keeps the line as written in ``metadata["site"]`` and adds the
numbers it reads from it (:data:`SITE_KEYS`, text as every metadata value); :func:`record_site` gives them back
as a :class:`Site`. A site line that names a place in words (``# site: test range B``) is kept as text and read
as no place. The geomagnetic reference at the site is the checks' (:mod:`magcal.checks.reference`, IGRF).
"""

from __future__ import annotations

import datetime as _dt
import math
import re
from dataclasses import dataclass

#: How a site line is written, for messages.
SITE_FORM = "LAT N|S, LON E|W, ALT m, YYYY-MM-DD"
#: A site line as the lessons write it.
SITE_EXAMPLE = "53.0 N, 4.5 E, 1500 m, 2024-06-01"
#: The metadata keys the CSV reader adds from a site line (latitude and longitude in deg, north and east positive;
#: height above the ellipsoid in m; the date as written).
SITE_KEYS = ("site_lat_deg", "site_lon_deg", "site_alt_m", "site_date")
#: Latitude and longitude (deg) a site may have.
LAT_RANGE_DEG = (-90.0, 90.0)
LON_RANGE_DEG = (-180.0, 180.0)
#: Height above the ellipsoid (m) a site may have: the IGRF model's range, 10 km below to 2000 km above.
ALT_RANGE_M = (-10_000.0, 2_000_000.0)

_NUMBER = r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?"
_ANGLE = re.compile(rf"^({_NUMBER})\s*(?:°|deg)?\s*([A-Za-z]?)$")
_HEIGHT = re.compile(rf"^({_NUMBER})\s*(m|km)?$")


@dataclass(frozen=True)
class Site:
    """Where and when a record was made.

    Attributes
    ----------
    lat_deg, lon_deg : float
        Geodetic latitude and longitude (deg, north and east positive).
    alt_m : float
        Height above the WGS84 ellipsoid (m).
    date : str
        The date as the file writes it (``2024-06-01`` or a decimal year).
    """

    lat_deg: float
    lon_deg: float
    alt_m: float
    date: str

    def text(self) -> str:
        """``53 N, 4.5 E, 1500 m, 2024-06-01``: the site as a site line writes it."""
        lat = f"{abs(self.lat_deg):g} {'S' if self.lat_deg < 0 else 'N'}"
        lon = f"{abs(self.lon_deg):g} {'W' if self.lon_deg < 0 else 'E'}"
        return f"{lat}, {lon}, {self.alt_m:g} m, {self.date}"


def names_a_place(value: str) -> bool:
    """Whether a site line's value is meant as a place (it starts with a number), not a name in words."""
    return bool(re.match(r"\s*[+-]?\.?\d", str(value)))


def _angle(text: str, what: str, positive: str, negative: str, limit: tuple[float, float]) -> float:
    found = _ANGLE.match(text.strip())
    if not found:
        raise ValueError(f"the {what} {text.strip()!r} is not a number of degrees with {positive} or {negative}")
    value, side = float(found.group(1)), found.group(2).upper()
    if side not in ("", positive, negative):
        raise ValueError(f"the {what} {text.strip()!r} ends in {found.group(2)!r}, not {positive} or {negative}")
    if side and value < 0:
        raise ValueError(f"the {what} {text.strip()!r} has both a sign and {side}")
    value = -value if side == negative else value
    if not (math.isfinite(value) and limit[0] <= value <= limit[1]):
        raise ValueError(f"the {what} {text.strip()!r} is outside {limit[0]:g} ... {limit[1]:g} deg")
    return value


def _height(text: str) -> float:
    found = _HEIGHT.match(text.strip())
    if not found:
        raise ValueError(f"the altitude {text.strip()!r} is not a height in m (or km) above the ellipsoid")
    value = float(found.group(1)) * (1000.0 if found.group(2) == "km" else 1.0)
    if not (math.isfinite(value) and ALT_RANGE_M[0] <= value <= ALT_RANGE_M[1]):
        raise ValueError(f"the altitude {text.strip()!r} is outside {ALT_RANGE_M[0]:g} ... {ALT_RANGE_M[1]:g} m")
    return value


def _date(text: str) -> str:
    date = text.strip()
    try:
        _dt.date.fromisoformat(date)
        return date
    except ValueError:
        pass
    try:
        year = float(date)
    except ValueError:
        year = math.nan
    if not (math.isfinite(year) and 1 <= year < 10_000 and re.fullmatch(_NUMBER, date)):
        raise ValueError(f"the date {date!r} is not YYYY-MM-DD or a decimal year")
    return date


def parse_site(value: str) -> Site:
    """The :class:`Site` a site line's value writes (:data:`SITE_FORM`).

    Raises
    ------
    ValueError
        What is wrong with it, in words (the caller names the file and line).
    """
    parts = [p.strip() for p in str(value).split(",")]
    if len(parts) != 4:
        raise ValueError(f"has {len(parts)} comma-separated part(s), not 4 (latitude, longitude, altitude, date)")
    lat = _angle(parts[0], "latitude", "N", "S", LAT_RANGE_DEG)
    lon = _angle(parts[1], "longitude", "E", "W", LON_RANGE_DEG)
    return Site(lat, lon, _height(parts[2]), _date(parts[3]))


def site_metadata(site: Site) -> dict[str, str]:
    """The metadata entries (:data:`SITE_KEYS`, text) the CSV reader adds for ``site``."""
    return {
        "site_lat_deg": repr(site.lat_deg),
        "site_lon_deg": repr(site.lon_deg),
        "site_alt_m": repr(site.alt_m),
        "site_date": site.date,
    }


def record_site(metadata) -> Site | None:
    """The record's :class:`Site` from its metadata (a dataset's ``metadata``, or a dataset), or None when the
    file had no site line that names a place."""
    metadata = getattr(metadata, "metadata", metadata) or {}
    if not all(key in metadata for key in SITE_KEYS):
        return None
    try:
        lat, lon, alt = (float(metadata[key]) for key in SITE_KEYS[:3])
    except (TypeError, ValueError):
        return None
    if not all(math.isfinite(v) for v in (lat, lon, alt)):
        return None
    return Site(lat, lon, alt, str(metadata["site_date"]))
