"""The reference total field a scalar calibration fits to, and where it came from.

Four sources, in the order :func:`resolve_reference` prefers them:

1. a number given by the user (``--reference 52193``), in nT;
2. the IGRF main field at a place and date (``--reference igrf --lat .. --lon .. --alt-km .. --date ..``,
   computed with ``ppigrf``); it omits crustal anomalies and the daily variation (typically tens to hundreds
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
import warnings
from dataclasses import dataclass

import numpy as np

from magcal.core.errors import DataWarning, MagcalError
from magcal.data.dataset import Dataset
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
    """

    value_nT: float | np.ndarray | None
    text: str
    kind: str

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


def _check_plausible(value, what):
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
        warnings.warn(
            f"{what}: {bad:g} nT is outside the Earth's field range {lo:g}-{hi:g} nT; fine for a coil system, "
            "otherwise check the value",
            DataWarning,
            stacklevel=4,
        )


def resolve_reference(dataset=None, reference=None, lat=None, lon=None, alt_km=0.0, date=None, check=True):
    """The reference total field and a sentence saying where it came from: the one place that decides it.

    Parameters
    ----------
    dataset : Dataset, optional
        Supplies the ``ref_total`` column (``ref_total_nT``) or the ``reference_total_nT`` metadata.
    reference : float, str or None
        A number in nT, ``"igrf"`` (needs ``lat``, ``lon``; ``alt_km``, ``date`` optional), ``"column"`` (use the
        ``ref_total`` column), ``"fit"`` / ``"none"`` (fit the magnitude), or ``None`` (the dataset's column, else its
        metadata, else fitted).
    lat, lon, alt_km, date
        Place (deg, deg, km above the ellipsoid) and date for IGRF.
    check : bool
        Check plausibility (refuse a value in the wrong unit, warn when far from the data). The fitters pass
        False: the user-facing checks ran once when the command or the workbench resolved the reference.

    Returns
    -------
    Reference
        ``value_nT`` (float, (N,) array or None), ``text``, ``kind``; unpacks as ``value, text``.

    Raises
    ------
    MagcalError
        Bad numbers, a missing column, an implausible field, IGRF without a place.
    """
    column = None if dataset is None else dataset.ref_total_nT
    meta = None if dataset is None else dataset.reference_total_nT
    where = (dataset.source if dataset is not None and dataset.source else None) or "data"
    choice = None if reference is None else str(reference).strip()
    if choice is not None and choice.lower() == "igrf":
        if lat is None or lon is None:
            raise MagcalError(
                "--reference igrf needs the place: --lat DEG --lon DEG (and --alt-km KM, --date YYYY-MM-DD)"
            )
        total, comps = igrf_total_nT(lat, lon, alt_km, date)
        when = parse_date(date if date is not None else _dt.date.today()).date()
        text = (
            f"IGRF main field ({comps['model']}) at {float(lat):.4f} N, {float(lon):.4f} E, {float(alt_km):g} km, "
            f"{when}: {total:.1f} nT (inclination {comps['inclination_deg']:.2f} deg); crustal anomalies and the "
            "daily variation (tens to hundreds of nT) are not in it"
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
            _check_plausible(value, "--reference")
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
            _check_plausible(meta, f"{where}: metadata reference_total_nT")
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
        _compare_with_data(dataset, ref)
    return ref


def _column_reference(column, where, check=True):
    col = np.asarray(column, dtype=float)
    if check:
        _check_plausible(col, f"{where}: column ref_total")
    else:
        _check_usable(col, f"{where}: column ref_total")
    spread = float(np.ptp(col)) if col.size else 0.0
    text = f"per-sample ref_total column: mean {np.mean(col):.1f} nT, spread {spread:.1f} nT over {col.size} samples"
    return Reference(col, text, "column")


def _compare_with_data(dataset, ref):
    """Warn when the field the readings imply is far from the reference (wrong units or wrong reference).

    The readings' magnitude is the fitted one (:func:`magcal.checks.coverage.field_magnitude_nT`: about the fitted
    centre, through the fitted shape), so neither a hard-iron offset nor unequal axis gains are mistaken for a
    wrong reference.
    """

    if dataset.readings_nT.size == 0:
        return
    median = float(np.median([field_magnitude_nT(y) for y in dataset.readings_nT]))
    value = float(np.median(np.atleast_1d(ref.value_nT)))
    if not 0.8 <= median / value <= 1.25:
        warnings.warn(
            f"{dataset.source or 'dataset'}: the field the readings imply (fitted: hard iron removed, axis gains "
            f"averaged) {median:.0f} nT differs from the reference "
            f"{value:.0f} nT by {100 * (median / value - 1):+.0f}%; check the units and the reference",
            DataWarning,
            stacklevel=3,
        )


def add_reference_arguments(parser) -> None:
    """The ``--reference``, ``--lat``, ``--lon``, ``--alt-km``, ``--date`` options of the CLI subcommands."""
    parser.add_argument(
        "--reference",
        default=None,
        metavar="NT|igrf|column|fit",
        help="reference total field: a number in nT, 'igrf' (with --lat, --lon, --alt-km, --date), "
        "'column' (the file's ref_total) or 'fit'; default: the file's ref_total column or "
        "reference_total_nT line, else fitted",
    )
    parser.add_argument("--lat", type=float, default=None, help="geodetic latitude in degrees (for --reference igrf)")
    parser.add_argument("--lon", type=float, default=None, help="longitude in degrees east (for --reference igrf)")
    parser.add_argument("--alt-km", type=float, default=0.0, help="height above the WGS84 ellipsoid in km (igrf)")
    parser.add_argument("--date", default=None, help="date YYYY-MM-DD or decimal year (igrf; default today)")


def reference_from_args(args, dataset=None) -> Reference:
    """:func:`resolve_reference` from the options of :func:`add_reference_arguments`."""
    return resolve_reference(
        dataset, reference=args.reference, lat=args.lat, lon=args.lon, alt_km=args.alt_km, date=args.date
    )
