"""The columns of a compensation flight found by name: the fluxgate, the time, the attitude, a current and the
temperature, in MagNav.jl's names and other common ones, so that such a file reads without ``--columns``.

MagNav.jl's flight files (its HDF5 fields, and the CSVs its users export from them; the SGL 2020/2021 data
dictionary, ``readmes/sgl_2020_fields_readme.txt`` in MagNav.jl) name

=================================  ==========================================================================
``tt``                             time, s (fiducial seconds past midnight UTC)
``mag_1_uc`` ... ``mag_6_uc``      the scalar magnetometers, uncompensated, nT
``flux_a_x``, ``_y``, ``_z``       fluxgate A's axes, nT (``flux_b_*``, ``flux_c_*``, ``flux_d_*`` the others;
                                   ``flux_a_t`` its total)
``ins_roll``, ``ins_pitch``,       the INS attitude, deg (yaw clockwise from north, then pitch up, then roll to
``ins_yaw``                        starboard: aerospace ZYX, as magcal's ``roll_deg, pitch_deg, yaw_deg``);
                                   ``roll, pitch, yaw`` the same in their CSV exports
``cur_outpwr``, ``cur_strb`` ...   current sensors, A (system output power, strobe lights, radio, fan ...)
=================================  ==========================================================================

:func:`find_fluxgates` finds every fluxgate's x, y, z columns by name (:data:`FLUXGATE_NAME`: ``flux_a_x``,
``flux_x``, ``fluxgate_x``, ``fluxgate1_x``, ``fg_x``, with or without an ``_nT`` suffix); :func:`flight_mapping`
maps the chosen one (the first in the file by default) onto sensor 1 and ``tt`` onto the time ``t`` when the file
does not name them as magcal does, and leaves a mapping the user gave as it is. The attitude, current and
temperature columns (:data:`ATTITUDE_COLUMNS`, :data:`CURRENT_COLUMNS`, :data:`TEMPERATURE_COLUMNS`) are read from
a dataset's other columns by :mod:`magcal.fitting.compensation`.
"""

from __future__ import annotations

import csv
import os
import re

from magcal.core.errors import MagcalError
from magcal.data.io import is_parquet

#: A fluxgate axis's column: a prefix naming the fluxgate (``flux_a``, ``flux``, ``fluxgate``, ``fluxgate2``,
#: ``fg``), the axis, and an optional unit suffix; case is ignored.
FLUXGATE_NAME = re.compile(
    r"^(?P<prefix>(?:flux|fluxgate|fg)(?:_?[a-z0-9]{1,2})?)_?(?P<axis>[xyz])(?:_nt)?$", re.IGNORECASE
)

#: Time columns (s) taken as ``t`` when the file has none: MagNav.jl's ``tt``.
TIME_COLUMNS = ("tt",)

#: Attitude columns (roll, pitch, yaw in deg, aerospace ZYX), first complete triple wins: magcal's, MagNav.jl's INS
#: attitude, the plain names of its CSV exports.
ATTITUDE_COLUMNS = (
    ("roll_deg", "pitch_deg", "yaw_deg"),
    ("ins_roll", "ins_pitch", "ins_yaw"),
    ("roll", "pitch", "yaw"),
)

#: Current columns (A, or a throttle), first present wins unless one is named: magcal's, then MagNav.jl's current
#: sensors in the order its own models use them (system output power, strobe lights, radio 1, the fan), then its
#: others.
CURRENT_COLUMNS = (
    "current_A",
    "throttle",
    "cur_outpwr",
    "cur_strb",
    "cur_com_1",
    "cur_ac_lo",
    "cur_ac_hi",
    "cur_acpwr",
    "cur_bat_1",
    "cur_bat_2",
    "cur_tank",
    "cur_flap",
    "cur_heat",
    "cur_srvo_o",
    "cur_srvo_m",
    "cur_srvo_i",
    "current",
)

#: Temperature columns (degC) read when the file has no ``temp``.
TEMPERATURE_COLUMNS = ("temperature_C", "temperature", "temp_C", "temp_c")

__all__ = [
    "ATTITUDE_COLUMNS",
    "CURRENT_COLUMNS",
    "FLUXGATE_NAME",
    "TEMPERATURE_COLUMNS",
    "TIME_COLUMNS",
    "find_fluxgates",
    "flight_mapping",
    "header_names",
]


def header_names(path) -> list[str]:
    """The column names of a CSV (its first line that is neither blank nor ``#``) or Parquet file; [] when it
    cannot be read (the reader says why later)."""
    path = os.fspath(path)
    try:
        if is_parquet(path):
            import pyarrow.parquet as pq

            return list(pq.read_schema(path).names)
        with open(path, encoding="utf-8-sig", newline="") as fh:
            for _, line in zip(range(10_000), fh):
                text = line.strip()
                if text and not text.startswith("#"):
                    return [name.strip() for name in next(csv.reader([text]))]
    except (OSError, UnicodeDecodeError, ValueError, ImportError, StopIteration, csv.Error):
        return []
    except Exception:  # pyarrow's own errors: a damaged or non-Parquet file
        return []
    return []


def find_fluxgates(names) -> dict[str, tuple[str, str, str]]:
    """Every fluxgate in ``names`` whose x, y and z columns are all there: prefix -> (x, y, z column), in the order
    their x columns appear (:data:`FLUXGATE_NAME`)."""
    found: dict[str, dict[str, str]] = {}
    for name in names:
        m = FLUXGATE_NAME.match(str(name))
        if m:
            found.setdefault(m.group("prefix").lower(), {}).setdefault(m.group("axis").lower(), name)
    return {prefix: (axes["x"], axes["y"], axes["z"]) for prefix, axes in found.items() if len(axes) == 3}


def _has_sensor_one(names, mapping) -> bool:
    keys = {str(k).strip() for k in mapping}
    return bool({"x", "s1x"} & (set(names) | keys))


def flight_mapping(names, columns=None, fluxgate: str | None = None, preferred=None) -> dict[str, str]:
    """The column mapping (magcal name -> file column) that reads a compensation flight with these ``names``.

    Parameters
    ----------
    names : sequence of str
        The file's columns (:func:`header_names`).
    columns : dict, optional
        The user's mapping (``--columns``, already parsed): kept as it is, and whatever it maps is not guessed.
    fluxgate : str, optional
        The fluxgate to take, by its prefix (``flux_b``; ``--fluxgate``): mapped onto sensor 1 even when the file
        has x, y, z columns.
    preferred : sequence of 3 str, optional
        The fluxgate columns a compensation was fitted on (its document's ``fluxgate_columns``): taken when the
        file has them and no fluxgate is named.

    Returns
    -------
    dict
        ``columns`` plus ``s1x, s1y, s1z`` (the fluxgate) when the file does not name sensor 1 as magcal does (or
        ``fluxgate`` is given), and ``t`` from :data:`TIME_COLUMNS` when it has no ``t``.

    Raises
    ------
    MagcalError
        ``fluxgate`` names no fluxgate of the file (the message lists those it has).
    """
    names = [str(n) for n in names]
    mapping = dict(columns or {})
    found = find_fluxgates(names)
    chosen = None
    if fluxgate is not None:
        key = str(fluxgate).strip().lower().rstrip("_")
        if key not in found:
            have = ", ".join(f"{p} ({', '.join(c)})" for p, c in found.items()) or "none"
            raise MagcalError(f"--fluxgate {fluxgate}: the file has no such fluxgate; its fluxgates: {have}")
        chosen = found[key]
    elif not _has_sensor_one(names, mapping):
        if preferred is not None and all(c in names for c in preferred):
            chosen = tuple(preferred)
        elif found:
            chosen = next(iter(found.values()))
    if chosen is not None:
        for key in ("x", "y", "z"):
            mapping.pop(key, None)
        mapping |= dict(zip(("s1x", "s1y", "s1z"), chosen))
    if "t" not in names and "t" not in mapping:
        time_name = next((n for n in TIME_COLUMNS if n in names), None)
        if time_name is not None:
            mapping["t"] = time_name
    return mapping
