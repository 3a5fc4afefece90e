"""The reference total field a scalar calibration fits to, and where it came from.

Four sources, in the order :func:`resolve_reference` prefers them:

1. a number given by the user (``--reference 52193``), in nT;
2. the IGRF main field at a place and date (``--reference igrf --lat .. --lon .. --alt-km .. --date ..``, else at
   the file's ``# site:`` line, :func:`igrf_place`; computed with ``ppigrf``); it omits crustal anomalies and the daily variation (typically tens to hundreds
   of nT), which the text says;
3. the per-sample ``ref_total`` column of the data (e.g. a proton magnetometer), nT;
4. the file's ``# reference_total_nT:`` metadata;

and otherwise none: the field magnitude is fitted as one more parameter, which fixes the calibration's scale
only up to that unknown (the text says so).
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import io as _io
import json
import warnings  # only to silence ppigrf's own noise
from dataclasses import dataclass, field

import numpy as np

from magcal.core.errors import DataWarning, MagcalError
from magcal.core.notes import Note
from magcal.data.dataset import Dataset
from magcal.data.site import Site, record_site
from magcal.geometry.shape import field_magnitude_nT

#: The Earth's field at the surface lies in this range (nT). A reference outside it is refused when another unit
#: would put it inside (e.g. 52.2 given in uT), and otherwise accepted with a warning (coil systems).
PLAUSIBLE_TOTAL_nT = (15_000.0, 80_000.0)

#: A reference outside this range (nT) is refused whatever the setting: no magnetometer magcal calibrates measures
#: it (1 nT is a fluxgate's noise; 10 mT saturates any fluxgate), and the fit's arithmetic fails far outside it
#: (1e308 overflows, 1e-308 leaves a singular problem).
USABLE_TOTAL_nT = (1.0, 1.0e7)


@dataclass
class Reference:
    """A reference total field.

    Attributes
    ----------
    value_nT : float, numpy.ndarray of shape (N,), or None
        The field magnitude in nT (one number, one per sample, or ``None`` when it is to be fitted).
    text : str
        Where it came from, for reports.
    kind : str
        ``number``, ``igrf``, ``column``, ``metadata`` or ``fitted``.
    notes : list of Note
        What the checks found (:mod:`magcal.core.notes`): a value outside the Earth's range, readings far from it.
        :func:`resolve_reference` leaves them here; the public functions and the command line say them.
    """

    value_nT: float | np.ndarray | None
    text: str
    kind: str
    notes: list = field(default_factory=list, compare=False)

    def __iter__(self):  # allows ``value, text = resolve_reference(...)``
        yield self.value_nT
        yield self.text

    @property
    def known(self) -> bool:
        return self.value_nT is not None

    def for_fit(self):
        """``(value or None, kind)`` as the fitters use it: ``kind`` is ``"given"`` (one number: given, IGRF or
        the file's metadata), ``"column"`` (the per-sample column; value None, read from the dataset) or
        ``"fitted"`` (unknown: the magnitude is fitted)."""
        if self.kind == "column":
            return None, "column"
        if self.value_nT is None:
            return None, "fitted"
        return float(self.value_nT), "given"

    def apply(self, dataset: Dataset) -> Dataset:
        """The dataset with this reference stored (scalar -> ``reference_total_nT``, array -> ``ref_total_nT``)."""
        if self.value_nT is None:
            return dataset.replace(reference_total_nT=None)
        if np.ndim(self.value_nT) == 0:
            return dataset.replace(reference_total_nT=float(self.value_nT))
        return dataset.replace(ref_total_nT=np.asarray(self.value_nT, dtype=float))


def parse_date(date):
    """A :class:`datetime.datetime` from a date, datetime, ISO text (``2024-06-01``) or decimal year (``2024.5``)."""
    if isinstance(date, _dt.datetime):
        return date
    if isinstance(date, _dt.date):
        return _dt.datetime(date.year, date.month, date.day)
    text = str(date).strip()
    try:
        return _dt.datetime.fromisoformat(text)
    except ValueError:
        pass
    try:
        year = float(text)
    except ValueError:
        raise MagcalError(
            f"--date: {date!r} is not a date; write it as YYYY-MM-DD (e.g. 2024-06-01) or 2024.5"
        ) from None
    if not np.isfinite(year) or not 1 <= year < 10_000:
        raise MagcalError(f"--date: {date!r} is not a year between 1 and 9999")
    start = _dt.datetime(int(year), 1, 1)
    length = (_dt.datetime(int(year) + 1, 1, 1) - start) if int(year) < 9999 else _dt.timedelta(days=365)
    return start + (year - int(year)) * length


def igrf_total_nT(lat, lon, alt_km=0.0, date=None):
    """IGRF main-field total intensity (nT) and its components at a place and date.

    Parameters
    ----------
    lat, lon : float
        Geodetic latitude and longitude in degrees (east positive).
    alt_km : float
        Height above the WGS84 ellipsoid in km.
    date : date, datetime, str or float
        The date (default: today).

    Returns
    -------
    total_nT : float
    components : dict
        ``north_nT``, ``east_nT``, ``down_nT``, ``inclination_deg``, ``declination_deg``, ``model``.

    Raises
    ------
    MagcalError
        For a place or date outside the model's range.
    """
    import ppigrf

    for name, value, lo, hi in (("--lat", lat, -90, 90), ("--lon", lon, -360, 360), ("--alt-km", alt_km, -10, 2000)):
        try:
            v = float(value)
        except (TypeError, ValueError):
            raise MagcalError(f"{name}: {value!r} is not a number") from None
        if not (np.isfinite(v) and lo <= v <= hi):
            raise MagcalError(f"{name}: {value!r} must lie between {lo} and {hi}")
    when = parse_date(date if date is not None else _dt.date.today())
    printed = _io.StringIO()
    with contextlib.redirect_stdout(printed), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        be, bn, bu = ppigrf.igrf(float(lon), float(lat), float(alt_km), when)
    if "not covered" in printed.getvalue() or not np.all(np.isfinite([be, bn, bu])):
        note = " ".join(printed.getvalue().split())
        raise MagcalError(
            f"--date: {when.date()} is outside the IGRF model's range ({note or 'no coefficients'}); give a date "
            "the model covers or a measured reference with --reference NT"
        )
    east, north, down = float(np.ravel(be)[0]), float(np.ravel(bn)[0]), -float(np.ravel(bu)[0])
    total = float(np.sqrt(east**2 + north**2 + down**2))
    comps = {
        "north_nT": north,
        "east_nT": east,
        "down_nT": down,
        "inclination_deg": float(np.degrees(np.arctan2(down, np.hypot(north, east)))),
        "declination_deg": float(np.degrees(np.arctan2(east, north))),
        "model": ppigrf.igrf.__defaults__[0].rsplit("/", 1)[-1].replace(".shc", "")
        if ppigrf.igrf.__defaults__
        else "IGRF",
    }
    return total, comps


def _check_usable(value, what):
    """Refuse a reference that is not a finite positive number of nT within :data:`USABLE_TOTAL_nT`."""
    try:
        v = np.atleast_1d(np.asarray(value, dtype=float))
    except (TypeError, ValueError):
        raise MagcalError(f"{what}: the reference field must be a number of nT, got {str(value)[:40]!r}") from None
    if not np.all(np.isfinite(v)):
        raise MagcalError(f"{what}: the reference field must be a finite number of nT")
    if np.any(v <= 0):
        raise MagcalError(f"{what}: the reference field must be positive (nT)")
    lo, hi = USABLE_TOTAL_nT
    if np.any((v < lo) | (v > hi)):
        bad = float(v[(v < lo) | (v > hi)][0])
        raise MagcalError(
            f"{what}: {bad:g} nT is outside what any magnetometer magcal calibrates measures (magcal accepts "
            f"{lo:g} to {hi:g} nT); give the reference in nT"
        )
    return v


def _check_plausible(value, what) -> list:
    """Refuse a reference that is no field in nT (:func:`_check_usable`, a unit hint first); a note (in a list) when
    it lies outside the Earth's range."""
    lo, hi = PLAUSIBLE_TOTAL_nT
    v = np.atleast_1d(np.asarray(value, dtype=float))
    if np.all(np.isfinite(v)) and np.all(v > 0) and np.any((v < lo) | (v > hi)):
        bad = float(v[(v < lo) | (v > hi)][0])
        for unit, f in (("uT", 1e3), ("G", 1e5), ("mG", 1e2)):
            if lo <= bad * f <= hi:  # a value in another unit: say which, before any other refusal
                raise MagcalError(
                    f"{what}: {bad:g} nT is outside the Earth's field range {lo:g}-{hi:g} nT ({bad:g} looks like "
                    f"{unit}: {bad * f:g} nT); give the reference in nT"
                )
    v = _check_usable(value, what)
    if np.any((v < lo) | (v > hi)):
        bad = float(v[(v < lo) | (v > hi)][0])
        hint = ""
        for unit, f in (("uT", 1e3), ("G", 1e5), ("mG", 1e2)):
            if lo <= bad * f <= hi:
                hint = f" ({bad:g} looks like {unit}: {bad * f:g} nT)"
                break
        if hint:
            raise MagcalError(
                f"{what}: {bad:g} nT is outside the Earth's field range {lo:g}-{hi:g} nT{hint}; give the reference in nT"
            )
        return [
            Note(
                f"{what}: {bad:g} nT is outside the Earth's field range {lo:g}-{hi:g} nT; fine for a coil system, "
                "otherwise check the value",
                DataWarning,
                "reference",
            )
        ]
    return []


@dataclass(frozen=True)
class IgrfPlace:
    """Where and when IGRF is evaluated, and who said so.

    Attributes
    ----------
    lat_deg, lon_deg : float
        Geodetic latitude and longitude (deg, north and east positive).
    alt_m, alt_km : float
        Height above the WGS84 ellipsoid, in m and in km (both kept, so that neither is a rounded copy of the
        other: the page holds metres, the command line kilometres).
    date : str or None
        The date (``YYYY-MM-DD`` or a decimal year); None: today.
    site : Site or None
        The file's ``# site:`` line when the place is its (:func:`magcal.data.site.record_site`); None when the
        user gave the place.
    """

    lat_deg: float
    lon_deg: float
    alt_m: float
    alt_km: float
    date: str | None
    site: Site | None = None

    @property
    def from_site(self) -> bool:
        return self.site is not None

    def words(self) -> str:
        """Where the place came from: ``IGRF at the file's # site: line (53 N, 4.5 E, 1500 m, 2024-06-01)``, or
        ``IGRF at the given place (53.0000 N, 4.5000 E, 1.5 km, 2024-06-01)``."""
        if self.site is not None:
            used = Site(self.lat_deg, self.lon_deg, self.alt_m, str(self.date))
            given = (self.alt_m, self.date) != (self.site.alt_m, self.site.date)
            return f"IGRF at the file's # site: line ({used.text()}{'; height or date given' if given else ''})"
        when = self.date if self.date is not None else f"{_dt.date.today()} (today)"
        return f"IGRF at the given place ({self.lat_deg:.4f} N, {self.lon_deg:.4f} E, {self.alt_km:g} km, {when})"


def igrf_place(dataset=None, lat=None, lon=None, alt_km=None, date=None) -> IgrfPlace | None:
    """The place and date IGRF is evaluated at: the one given (``--lat``, ``--lon``, ``--alt-km``, ``--date``),
    else the record's ``# site:`` line (:func:`magcal.data.site.record_site`), else None. The one function the
    command line (:func:`resolve_reference`, :func:`resolve_vector_reference`) and the workbench's location (its
    ``take_site``) take the site through.

    Parameters
    ----------
    dataset : Dataset or dict, optional
        The record (its ``metadata``): its site, and its own date (:func:`record_date`).
    lat, lon : float, optional
        Given latitude and longitude (deg); both win over the site. One without the other is refused.
    alt_km : float, optional
        Given height above the ellipsoid (km); wins over the site's; without a place, 0.
    date : str, optional
        Given date; wins over the site's and the record's own.

    Raises
    ------
    MagcalError
        One of ``lat``, ``lon`` given without the other.
    """
    if (lat is None) != (lon is None):
        said, missing = ("--lat", "--lon") if lon is None else ("--lon", "--lat")
        raise MagcalError(f"{said} is given without {missing}: IGRF needs both (deg)")
    km_given = _number("--alt-km", alt_km)
    if lat is not None:
        km = 0.0 if km_given is None else km_given
        lat_deg, lon_deg = _number("--lat", lat), _number("--lon", lon)
        assert lat_deg is not None and lon_deg is not None  # both given: checked above
        return IgrfPlace(lat_deg, lon_deg, km * 1000.0, km, record_date(dataset, date))
    site = record_site(getattr(dataset, "metadata", dataset))
    if site is None:
        return None
    alt_m, km = (site.alt_m, site.alt_m / 1000.0) if km_given is None else (km_given * 1000.0, km_given)
    return IgrfPlace(site.lat_deg, site.lon_deg, alt_m, km, site.date if date is None else date, site)


def _number(name, value) -> float | None:
    """``value`` as a float (None stays None), or a :class:`MagcalError` naming the option."""
    if value is None:
        return None
    try:
        return float(value)
    except (TypeError, ValueError):
        raise MagcalError(f"{name}: {value!r} is not a number") from None


def _unused_site(dataset) -> str:
    """`` (the file's # site: line ... is not used)`` when the user's place wins over a site the file names."""
    site = record_site(getattr(dataset, "metadata", None) or {}) if dataset is not None else None
    return "" if site is None else f" (the file's # site: line, {site.text()}, is not used)"


def resolve_reference(dataset=None, reference=None, lat=None, lon=None, alt_km=None, date=None, check=True):
    """The reference total field and a sentence saying where it came from: the one place that decides it. What the
    checks found is in its ``notes`` (:class:`~magcal.core.errors.DataWarning` notes), never raised here.

    Parameters
    ----------
    dataset : Dataset, optional
        Supplies the ``ref_total`` column (``ref_total_nT``) or the ``reference_total_nT`` metadata.
    reference : float, str or None
        A number in nT, ``"igrf"`` (at ``lat``, ``lon``, ``alt_km``, ``date`` when given, else at the file's
        ``# site:`` line: :func:`igrf_place`), ``"column"`` (use the
        ``ref_total`` column), ``"fit"`` / ``"none"`` (fit the magnitude), or ``None`` (the dataset's column, else its
        metadata, else fitted).
    lat, lon, alt_km, date
        Place (deg, deg, km above the ellipsoid; ``alt_km`` None: the site's, else 0) and date for IGRF; given, they
        win over the file's ``# site:`` line.
    check : bool
        Check plausibility (refuse a value in the wrong unit, warn when far from the data). The fitters pass
        False: the user-facing checks ran once when the command or the workbench resolved the reference.

    Returns
    -------
    Reference
        ``value_nT`` (float, (N,) array or None), ``text``, ``kind``, ``notes``; unpacks as ``value, text``.

    Raises
    ------
    MagcalError
        Bad numbers, a missing column, an implausible field, IGRF without a place.
    """
    column = None if dataset is None else dataset.ref_total_nT
    meta = None if dataset is None else dataset.reference_total_nT
    where = (dataset.source if dataset is not None and dataset.source else None) or "data"
    choice = None if reference is None else str(reference).strip()
    found = []  # the checks' notes
    if choice is not None and choice.lower() == "igrf":
        place = igrf_place(dataset, lat, lon, alt_km, date)
        if place is None:
            raise MagcalError(
                "--reference igrf needs the place: --lat DEG --lon DEG (and --alt-km KM, --date YYYY-MM-DD)"
            )
        total, comps = igrf_total_nT(place.lat_deg, place.lon_deg, place.alt_km, place.date)
        when = parse_date(place.date if place.date is not None else _dt.date.today()).date()
        if place.from_site:
            text = f"{place.words()}, {comps['model']} main field: {total:.1f} nT"
        else:
            text = (
                f"IGRF main field ({comps['model']}) at {place.lat_deg:.4f} N, {place.lon_deg:.4f} E, "
                f"{place.alt_km:g} km, {when}: {total:.1f} nT"
            )
        text += (
            f" (inclination {comps['inclination_deg']:.2f} deg); crustal anomalies and the daily variation (tens to "
            "hundreds of nT) are not in it" + ("" if place.from_site else _unused_site(dataset))
        )
        ref = Reference(total, text, "igrf")
    elif choice is not None and choice.lower() == "column":
        if column is None:
            raise MagcalError(f"{where}: --reference column, but the file has no ref_total column")
        ref = _column_reference(column, where, check)
    elif choice is not None and choice.lower() in ("fit", "fitted", "none", "unknown"):
        ref = Reference(
            None,
            "no reference: the field magnitude is fitted (the scale factors are then relative to "
            "the fitted magnitude, not absolute)",
            "fitted",
        )
    elif choice is not None and choice != "":
        try:
            value = float(choice)
        except ValueError:
            raise MagcalError(
                f"--reference: {reference!r} is neither a number of nT nor 'igrf', 'column' or 'fit'"
            ) from None
        if check:
            found += _check_plausible(value, "--reference")
        else:
            _check_usable(value, "--reference")
        text = f"given reference: {value:.1f} nT"
        if column is not None:
            text += " (the file's ref_total column is not used)"
        ref = Reference(value, text, "number")
    elif column is not None:
        ref = _column_reference(column, where, check)
    elif meta is not None:
        if check:
            found += _check_plausible(meta, f"{where}: metadata reference_total_nT")
        else:
            _check_usable(meta, f"{where}: metadata reference_total_nT")
        ref = Reference(float(meta), f"file metadata reference_total_nT: {float(meta):.1f} nT", "metadata")
    else:
        ref = Reference(
            None,
            "no reference given: the field magnitude is fitted (the scale factors are then relative "
            "to the fitted magnitude, not absolute)",
            "fitted",
        )
    if check and dataset is not None and ref.known:
        found += _compare_with_data(dataset, ref)
    ref.notes.extend(found)
    return ref


def _column_reference(column, where, check=True):
    col = np.asarray(column, dtype=float)
    found: list = []
    if check:
        found = _check_plausible(col, f"{where}: column ref_total")
    else:
        _check_usable(col, f"{where}: column ref_total")
    spread = float(np.ptp(col)) if col.size else 0.0
    text = f"per-sample ref_total column: mean {np.mean(col):.1f} nT, spread {spread:.1f} nT over {col.size} samples"
    return Reference(col, text, "column", found)


def _compare_with_data(dataset, ref) -> list:
    """A note (in a list) when the field the readings imply is far from the reference (wrong units or wrong reference).

    The readings' magnitude is the fitted one (:func:`magcal.geometry.shape.field_magnitude_nT`: about the fitted
    centre, through the fitted shape), so neither a hard-iron offset nor unequal axis gains are mistaken for a
    wrong reference.
    """

    if dataset.readings_nT.size == 0:
        return []
    median = float(np.median([field_magnitude_nT(y) for y in dataset.readings_nT]))
    value = float(np.median(np.atleast_1d(ref.value_nT)))
    if not 0.8 <= median / value <= 1.25:
        return [
            Note(
                f"{dataset.source or 'dataset'}: the field the readings imply (fitted: hard iron removed, axis "
                f"gains averaged) {median:.0f} nT differs from the reference "
                f"{value:.0f} nT by {100 * (median / value - 1):+.0f}%; check the units and the reference",
                DataWarning,
                "reference",
            )
        ]
    return []


def add_reference_arguments(parser) -> None:
    """The ``--reference``, ``--lat``, ``--lon``, ``--alt-km``, ``--date`` options of the CLI subcommands."""
    parser.add_argument(
        "--reference",
        default=None,
        metavar="NT|igrf|column|fit|fitted",
        help="reference total field: a number in nT, 'igrf' (at --lat, --lon, --alt-km, --date, else at the "
        "file's '# site:' line), "
        "'column' (the file's ref_total) or 'fit'; default: the file's ref_total column or "
        "reference_total_nT line, else fitted. With the attitude (vector mode), 'fitted' fits the lab's field "
        "vector with the calibration (a constant field nobody measured: motion capture, a turntable, a coil)",
    )
    parser.add_argument(
        "--lat", type=float, default=None, help="geodetic latitude in degrees (igrf; wins over the # site: line)"
    )
    parser.add_argument(
        "--lon", type=float, default=None, help="longitude in degrees east (igrf; wins over the # site: line)"
    )
    parser.add_argument(
        "--alt-km",
        type=float,
        default=None,
        help="height above the WGS84 ellipsoid in km (igrf; default: the # site: line's, else 0)",
    )
    parser.add_argument(
        "--date",
        default=None,
        help="date YYYY-MM-DD or decimal year (igrf; default: the record's own date - a flight log's GPS, a "
        "'# date:' header line - else today)",
    )


def reference_from_args(args, dataset=None) -> Reference:
    """:func:`resolve_reference` from the options of :func:`add_reference_arguments` (the command line
    prints its ``notes``)."""
    return resolve_reference(
        dataset, reference=args.reference, lat=args.lat, lon=args.lon, alt_km=args.alt_km, date=args.date
    )


# ----------------------------------------------------------------------------------------------------------------
# the reference field *vector* (north, east, down) for a vector calibration
# ----------------------------------------------------------------------------------------------------------------

#: Per-sample reference field components (nT, north-east-down).
VECTOR_COLUMNS = ("ref_n", "ref_e", "ref_d")

#: Per-sample position for IGRF along the track: geodetic latitude, longitude (deg) and height above the WGS84
#: ellipsoid (m).
POSITION_COLUMNS = ("lat", "lon", "alt_m")

#: Along a track longer than this, IGRF is evaluated at this many evenly spaced samples and interpolated between
#: them (the main field changes by a few nT per km; a survey's samples are metres apart).
IGRF_TRACK_NODES = 2000


@dataclass
class VectorReference:
    """The Earth's field vector at every sample, in the world (north-east-down) frame.

    Attributes
    ----------
    ned_nT : numpy.ndarray, shape (N, 3)
        North, east, down components in nT.
    text : str
        Where it came from, for reports.
    kind : str
        ``vector`` (one given vector), ``igrf`` (IGRF at one place), ``igrf-track`` (IGRF along the ``lat, lon,
        alt_m`` columns), ``column`` (the ``ref_n, ref_e, ref_d`` columns), ``fitted`` (to be fitted with the
        calibration; ``ned_nT`` its start or NaN) or ``lab`` (a field a vector fit found:
        :mod:`magcal.fitting.labfield`).
    """

    ned_nT: np.ndarray
    text: str
    kind: str

    @property
    def total_nT(self) -> np.ndarray:
        """``|B_ned|`` per sample (nT)."""
        return np.sqrt(np.sum(self.ned_nT**2, axis=1))


def igrf_ned_nT(lat, lon, alt_km, date=None) -> np.ndarray:
    """IGRF main field (N, 3) north, east, down in nT at arrays of places (deg, deg, km above the ellipsoid).

    Long tracks are evaluated at :data:`IGRF_TRACK_NODES` samples and linearly interpolated over the sample index.
    """
    import ppigrf

    lat, lon, alt_km = (np.atleast_1d(np.asarray(v, dtype=float)) for v in (lat, lon, alt_km))
    lat, lon, alt_km = np.broadcast_arrays(lat, lon, alt_km)
    n = lat.size
    for name, v, lo, hi in (("lat", lat, -90, 90), ("lon", lon, -360, 360), ("alt", alt_km, -10, 2000)):
        if not np.all(np.isfinite(v)) or np.any((v < lo) | (v > hi)):
            bad = int(np.argmax(~np.isfinite(v) | (v < lo) | (v > hi)))
            raise MagcalError(f"{name} of sample {bad + 1} ({v[bad]!r}) must be a number between {lo} and {hi}")
    nodes = np.arange(n) if n <= IGRF_TRACK_NODES else np.unique(np.linspace(0, n - 1, IGRF_TRACK_NODES).round())
    nodes = nodes.astype(int)
    when = parse_date(date if date is not None else _dt.date.today())
    printed = _io.StringIO()
    with contextlib.redirect_stdout(printed), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        be, bn, bu = ppigrf.igrf(lon[nodes], lat[nodes], alt_km[nodes], when)
    comps = np.column_stack([np.ravel(bn), np.ravel(be), -np.ravel(bu)])
    if "not covered" in printed.getvalue() or not np.all(np.isfinite(comps)):
        raise MagcalError(
            f"--date: {when.date()} is outside the IGRF model's range; give a date the model covers, or the "
            "field vector with --reference-vector N,E,D"
        )
    if nodes.size == n:
        return comps
    idx = np.arange(n)
    return np.column_stack([np.interp(idx, nodes, comps[:, k]) for k in range(3)])


def parse_reference_vector(text) -> np.ndarray:
    """``N,E,D`` (nT) from ``--reference-vector`` text or a sequence of three numbers; or the path of a saved
    calibration holding the lab's field fitted with it (``lab_field``: :mod:`magcal.fitting.labfield`), for the next
    record of the same lab."""
    if isinstance(text, str) and text.strip().lower().endswith(".json"):
        return lab_field_of(text.strip())
    try:
        parts = [float(v) for v in (str(text).replace(" ", "").split(",") if isinstance(text, str) else text)]
    except (TypeError, ValueError):
        parts = []
    v = np.asarray(parts, dtype=float)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise MagcalError(
            f"--reference-vector: {text!r} must be three numbers N,E,D in nT (e.g. 19500,200,44000: north, east, down)"
        )
    _check_plausible(float(np.linalg.norm(v)), "--reference-vector")
    return v


def lab_field_of(path) -> np.ndarray:
    """The lab's field (north, east, down, nT) a saved calibration holds (``lab_field.ned_nT``), refused with one
    message when the file has none."""
    try:
        with open(path, encoding="utf-8") as f:
            doc = json.load(f)
    except (OSError, ValueError) as exc:
        raise MagcalError(f"--reference-vector {path}: cannot read it as a calibration file ({exc})") from None
    found = doc.get("lab_field") if isinstance(doc, dict) else None
    ned = np.asarray(found.get("ned_nT", []) if isinstance(found, dict) else [], dtype=float)
    if ned.shape != (3,) or not np.all(np.isfinite(ned)):
        raise MagcalError(
            f"--reference-vector {path}: the calibration holds no lab field (it was not fitted with --reference "
            "fitted); give N,E,D in nT"
        )
    _check_plausible(float(np.linalg.norm(ned)), f"--reference-vector {path}")
    return ned


def record_date(dataset, date=None):
    """The date for IGRF: ``date`` when given, else the record's own (``metadata['date']``, which the flight-log
    readers take from the GPS, else the date of the file's ``# site:`` line, ``metadata['site_date']``), else None
    (today).

    A record years old evaluated at today's date is off by the secular variation, tens of nT a year in each
    component (a 2014 flight at 2026 is hundreds of nT off)."""
    if date is not None or dataset is None:
        return date
    metadata = getattr(dataset, "metadata", None) or {}
    found = str(metadata.get("date") or metadata.get("site_date") or "").strip()
    if not found:
        return None
    try:
        parse_date(found)
    except MagcalError:
        return None  # a free-text date in a file's header is not one IGRF can take: today, as before
    return found


def resolve_vector_reference(
    dataset, reference=None, lat=None, lon=None, alt_km=None, date=None, vector=None
) -> VectorReference | None:
    """The reference field vector (north-east-down, nT) for every sample, and where it came from; None when the
    data and the options give none.

    Parameters
    ----------
    dataset : Dataset
        Supplies ``ref_n, ref_e, ref_d`` (nT) or ``lat, lon, alt_m`` columns (in ``extra``).
    reference : str, optional
        ``"igrf"``: the IGRF main field, at ``lat, lon, alt_km`` when given, else along the dataset's ``lat, lon,
        alt_m`` columns (a track: the field where each sample was taken), else at the file's ``# site:`` line
        (:func:`igrf_place`, the place the workbench takes from it). ``"fitted"``: the field is a constant of unknown vector, fitted with the calibration (a
        reference of kind ``fitted``: its ``ned_nT`` is the vector given with ``vector``, else the ``ref_n, ref_e,
        ref_d`` columns' median, else NaN; :mod:`magcal.fitting.labfield`). Anything else (a number, ``column``,
        ``fit``) is a scalar reference and leaves the vector to the columns.
    lat, lon, alt_km, date
        Place (deg, deg, km above the ellipsoid) and date for IGRF; without ``date``, the record's
        ``metadata['date']`` (:func:`record_date`), else today.
    vector : str or sequence, optional
        ``N,E,D`` in nT (``--reference-vector``): one vector for the whole record; it wins over everything.

    Raises
    ------
    MagcalError
        Bad numbers, a missing column, IGRF without a place.
    """
    n = dataset.n_samples
    where = dataset.source or "data"
    extra = dataset.extra
    given_date = date
    date = record_date(dataset, date)
    if reference is not None and str(reference).strip().lower() == "fitted":
        return _fitted_vector_reference(dataset, vector)
    if vector is not None:
        v = parse_reference_vector(vector)
        return VectorReference(
            np.tile(v, (n, 1)),
            f"given field vector N {v[0]:.1f}, E {v[1]:.1f}, D {v[2]:.1f} nT (|B| {np.linalg.norm(v):.1f} nT)",
            "vector",
        )
    if reference is not None and str(reference).strip().lower() == "igrf":
        track = all(c in extra for c in POSITION_COLUMNS[:2])  # IGRF along it, per sample, beats one site
        place = igrf_place(dataset, lat, lon, alt_km, given_date) if lat is not None or not track else None
        if place is not None:  # given, else the file's # site: line (as the workbench's location)
            ned = igrf_ned_nT(place.lat_deg, place.lon_deg, place.alt_km, place.date)[0]
            _, comps = igrf_total_nT(place.lat_deg, place.lon_deg, place.alt_km, place.date)
            when = parse_date(place.date if place.date is not None else _dt.date.today()).date()
            where_text = (
                f"{place.words()}, {comps['model']} main field vector"
                if place.from_site
                else f"IGRF main field vector ({comps['model']}) at {place.lat_deg:.4f} N, {place.lon_deg:.4f} E, "
                f"{place.alt_km:g} km, {when}"
            )
            text = (
                f"{where_text}: N {ned[0]:.1f}, E {ned[1]:.1f}, D {ned[2]:.1f} nT; crustal anomalies and the daily "
                "variation (tens to hundreds of nT) are not in it" + ("" if place.from_site else _unused_site(dataset))
            )
            return VectorReference(np.tile(ned, (n, 1)), text, "igrf")
        if all(c in extra for c in POSITION_COLUMNS[:2]):
            cols = []
            for c in POSITION_COLUMNS:
                v = extra.get(c, np.zeros(n))
                if np.asarray(v).dtype.kind not in "fiu":
                    raise MagcalError(f"{where}: column {c} must hold numbers")
                cols.append(np.asarray(v, dtype=float))
            placed = np.isfinite(cols[0]) & np.isfinite(cols[1]) & np.isfinite(cols[2])  # NaN: no GPS fix yet
            if not placed.any():
                raise MagcalError(
                    f"{where}: no sample has a position (the lat, lon, alt_m columns are empty or NaN: no GPS fix); "
                    "give the place with --lat DEG --lon DEG, or the field vector with --reference-vector N,E,D"
                )
            for c, v, lo, hi in zip(POSITION_COLUMNS, cols, (-90, -360, -10_000), (90, 360, 2_000_000)):
                out = placed & ((v < lo) | (v > hi))
                if out.any():
                    k = int(np.argmax(out))
                    raise MagcalError(f"{where}: column {c}, data row {k + 1}: {v[k]:g} is not between {lo} and {hi}")
            ned = np.full((n, 3), np.nan)
            ned[placed] = igrf_ned_nT(cols[0][placed], cols[1][placed], cols[2][placed] / 1000.0, date)
            when = parse_date(date if date is not None else _dt.date.today()).date()
            total = np.linalg.norm(ned[placed], axis=1)
            unplaced = int(n - placed.sum())
            text = (
                f"IGRF main field vector along the track (lat, lon, alt_m columns; {n} samples, {when}): |B| "
                f"{total.min():.0f}-{total.max():.0f} nT; crustal anomalies and the daily variation are not in it"
                + (f"; {unplaced} samples without a position have none" if unplaced else "")
            )
            return VectorReference(ned, text, "igrf-track")
        raise MagcalError(
            "--reference igrf needs the place: --lat DEG --lon DEG (and --alt-km KM, --date YYYY-MM-DD), or "
            f"lat, lon (and alt_m) columns in {where}"
        )
    present = [c for c in VECTOR_COLUMNS if c in extra]
    if present:
        if len(present) < 3:
            raise MagcalError(
                f"{where}: the reference vector needs all three columns {', '.join(VECTOR_COLUMNS)} (nT); found only "
                f"{', '.join(present)}"
            )
        cols = [np.asarray(extra[c]) for c in VECTOR_COLUMNS]
        if any(c.dtype.kind not in "fiu" for c in cols):
            raise MagcalError(f"{where}: columns {', '.join(VECTOR_COLUMNS)} must hold numbers (nT)")
        ned = np.column_stack(cols).astype(float)
        given = np.all(np.isfinite(ned), axis=1)  # an empty (NaN) row: no reference for that sample
        if not given.any():
            raise MagcalError(f"{where}: columns {', '.join(VECTOR_COLUMNS)} hold no finite row (nT)")
        ned[~given] = np.nan
        total = np.linalg.norm(ned[given], axis=1)
        _check_plausible(total, f"{where}: columns ref_n, ref_e, ref_d")
        text = (
            f"per-sample field vector columns ref_n, ref_e, ref_d: |B| mean {total.mean():.1f} nT, spread "
            f"{np.ptp(total):.1f} nT" + (f"; {int(n - given.sum())} samples without one" if not given.all() else "")
        )
        return VectorReference(ned, text, "column")
    return None


def _fitted_vector_reference(dataset, vector=None) -> VectorReference:
    """The reference of kind ``fitted``: a constant field fitted with the calibration; a vector given (``vector``,
    else the median of the ``ref_n, ref_e, ref_d`` columns) is its start, and its declination the one kept when the
    record's attitudes cannot tell it from the mounting's yaw."""
    n = dataset.n_samples
    start = None
    if vector is not None:
        start = parse_reference_vector(vector)
    elif all(c in dataset.extra for c in VECTOR_COLUMNS):
        rows = np.column_stack([np.asarray(dataset.extra[c], dtype=float) for c in VECTOR_COLUMNS])
        rows = rows[np.all(np.isfinite(rows), axis=1)]
        start = np.median(rows, axis=0) if len(rows) else None
    text = "the field is fitted with the calibration (a constant field of unknown vector)"
    if start is None:
        return VectorReference(np.full((n, 3), np.nan), text, "fitted")
    return VectorReference(
        np.tile(start, (n, 1)),
        text + f", starting from N {start[0]:.1f}, E {start[1]:.1f}, D {start[2]:.1f} nT",
        "fitted",
    )


def add_vector_reference_arguments(parser) -> None:
    """``--reference-vector N,E,D`` (nT), beside :func:`add_reference_arguments`."""
    parser.add_argument(
        "--reference-vector",
        default=None,
        metavar="N,E,D|CAL.json",
        help="the Earth's field vector in nT (north, east, down) for a vector calibration, or a calibration file "
        "holding the lab's field fitted with it (--reference fitted); otherwise the file's ref_n, ref_e, ref_d "
        "columns, or IGRF with --reference igrf (at --lat/--lon or along lat, lon, alt_m columns)",
    )


def vector_reference_from_args(args, dataset) -> VectorReference | None:
    """:func:`resolve_vector_reference` from the options of :func:`add_reference_arguments` and
    :func:`add_vector_reference_arguments`."""
    return resolve_vector_reference(
        dataset,
        reference=getattr(args, "reference", None),
        lat=getattr(args, "lat", None),
        lon=getattr(args, "lon", None),
        alt_km=getattr(args, "alt_km", None),
        date=getattr(args, "date", None),
        vector=getattr(args, "reference_vector", None),
    )
