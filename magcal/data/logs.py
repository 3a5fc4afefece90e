"""Flight-controller logs in: ArduPilot DataFlash ``.bin`` and PX4 ``.ulg`` as a :class:`~magcal.data.dataset.Dataset`.

ArduPilot (read with pymavlink's ``DFReader``)
    ``MAG`` messages (one per compass: the instance field ``I``, or the older names ``MAG2``, ``MAG3``) hold the
    field in milligauss in the body frame *after* the compass calibration of the time
    (``AP_Compass_Backend::correct_field``: ``M (SCALE (raw + OFS)) + motor``), with the offsets (``OfsX..``) and
    the motor offsets (``MOX..``) logged beside it. To calibrate, magcal needs the raw field: by default it undoes
    that correction with the logged offsets and the ``COMPASS_DIA*``, ``COMPASS_ODI*``, ``COMPASS_SCALE*``
    parameters (``PARM`` messages) in force at each sample (``undo_calibration=False`` keeps the logged field).
    Each compass's parameters are those of its device: ArduPilot logs the compasses in their priority order and
    ``COMPASS_PRIOn_ID`` (4.1 and later) names the ``COMPASS_DEV_ID*`` whose parameters apply. The logged field
    itself is kept beside the raw one as the channels ``s1x_logged, s1y_logged, s1z_logged`` (nT, body frame; ``s2..``
    for the second compass, :func:`logged_field_columns`): what the flight controller's own consistency check and
    heading saw. Temperature: the ``IMU`` message's ``T`` (degC, first IMU), interpolated to the compass times.
    Motor current: ``BAT`` ``Curr`` (A), or in older logs ``CURR`` ``Curr`` (cA), as ``current_A``; throttle:
    ``CTUN`` ``ThO`` (0-1; ``ThrOut`` / 1000 before Copter 3.3)
    as ``throttle`` when it moves (the channels of the vector fit's field-per-unit term). Attitude:
    ``ATT`` roll, pitch, yaw (deg), as the quaternion channel (body to north-east-down) and as extra columns
    ``att_roll_deg``, ``att_pitch_deg``, ``att_yaw_deg``. Position: the first ``GPS`` receiver's samples with a 3D
    fix (``Status`` >= 3) as the columns ``lat``, ``lon`` (deg) and ``alt_m`` (m above mean sea level, which IGRF
    takes for height above the ellipsoid: tens of metres, far below a nT), timed by the board's clock (``TimeUS``;
    in logs before 2015 ``T``, the board's ms: their ``TimeMS`` is the GPS time of week, not the board's); the
    date of the first fix (``GWk``/``GMS`` or ``Week``/``TimeMS``) as ``metadata['date']``, which the IGRF
    reference uses when no ``--date`` is given. ``COMPASS_DEC`` (the declination the vehicle added to its magnetic
    heading: ``ATT`` yaw is true heading only if it is right) as ``metadata['log_declination_deg']``.
PX4 (read with pyulog)
    ``sensor_mag`` (one instance per magnetometer) holds the raw field in gauss in the sensor's frame before the
    ``CAL_MAGn_*`` calibration, with its ``temperature`` (degC; NaN when the part has none). The field PX4 computed
    from it with the log's ``CAL_MAGn_*`` parameters (its device's, by ``CAL_MAGn_ID``) is kept as the channels
    ``s1x_logged..`` (body frame), as for ArduPilot. Attitude: the
    ``vehicle_attitude`` quaternion ``q`` (body FRD to NED), interpolated to the magnetometer times (both readers:
    NaN for a sample far from any attitude message, :data:`LOG_ATTITUDE_MAX_GAP_S`). Position:
    ``vehicle_gps_position`` or ``sensor_gps`` with a 3D fix (``fix_type`` >= 3) as ``lat``, ``lon``, ``alt_m``,
    and the date of ``time_utc_usec`` as ``metadata['date']``.

Several magnetometers become magcal sensors 1, 2, 3 in instance order; their samples are paired by time (the
nearest sample within half the first one's sample interval; unpaired samples are dropped with a warning). Note that
the attitude is the vehicle's: a magnetometer mounted rotated (``COMPASS_ORIENT``, ``CAL_MAGn_ROT``) reads in its
own frame (PX4) or is already rotated to the body frame (ArduPilot).
"""

from __future__ import annotations

import contextlib
import itertools
import mmap
import os
import re
import struct
import time
import warnings

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from magcal.core import notes as _notes
from magcal.core.errors import DataWarning, exception_text
from magcal.core.files import check_regular_file
from magcal.core.memory import available_bytes
from magcal.core.notes import Note, row_runs
from magcal.data import dataflash_scan
from magcal.data.dataset import BAD_VALUE_TEXT, Dataset, DatasetError, bad_values
from magcal.geometry.orientations import FIRMWARE_ROTATIONS, euler_matrix

#: File name endings read as flight-controller logs, and the reader of each.
LOG_EXTENSIONS = (".bin", ".ulg")

NT_PER_MILLIGAUSS = 100.0
NT_PER_GAUSS = 1.0e5

#: ArduPilot applies COMPASS_SCALE only inside these bounds (``Compass::have_scale_factor``).
ARDUPILOT_SCALE_RANGE = (1.0 / 1.5, 1.5)

MAX_SENSORS = 4


def logged_field_columns(sensor) -> tuple:
    """Names of the channels holding magnetometer ``sensor``'s (0-based) field as the flight controller computed
    it with its calibration of the time (nT, body frame): ``s1x_logged, s1y_logged, s1z_logged`` for the first.
    The readers keep them beside the raw readings, so that a calibration can be compared with the firmware's."""
    return tuple(f"s{sensor + 1}{a}_logged" for a in "xyz")


#: Time allowed to read a log: this many seconds per MB of file, and at least :data:`MIN_DEADLINE_S` (pymavlink
#: reads about 1 MB/s of DataFlash; a log that takes far longer is damaged in a way that loops).
DEADLINE_S_PER_MB = 10.0
MIN_DEADLINE_S = 60.0


def is_log(path) -> bool:
    """True if ``path`` names a flight-controller log magcal reads (by its ending, case-insensitive)."""
    return isinstance(path, (str, os.PathLike)) and os.fspath(path).lower().endswith(LOG_EXTENSIONS)


def read_log(path, sensors=None, name=None, undo_calibration=True, min_samples=1, timeout_s=None, warn=True) -> Dataset:
    """Read an ArduPilot ``.bin`` or PX4 ``.ulg`` log into a :class:`Dataset` (readings in nT).

    Parameters
    ----------
    path : str or os.PathLike
    sensors : sequence of int, optional
        Which magnetometers (0-based instance numbers, in the order of the log) to read; default all (at most 4).
    name : str, optional
        What messages call the file.
    undo_calibration : bool
        ArduPilot only: undo the logged calibration to recover the raw field (default), or keep the logged one.
    min_samples : int
        Fewest samples accepted.
    timeout_s : float, optional
        Give up (with a :class:`DatasetError`) after this many seconds; default :data:`DEADLINE_S_PER_MB` per MB
        of file, at least :data:`MIN_DEADLINE_S`. DataFlash: every format field the reader steps by is checked
        first (a format shorter than its header, or not the size of its fields, is refused) and every message must
        move it forward, so a damaged log ends with a message, never a hang. ULog: the formats are checked first
        (:func:`check_ulog_definitions`: nesting, fields), and pyulog's reader is stopped from inside at the
        deadline or when its subscriptions' fields pass :data:`ULOG_MAX_SUBSCRIBED_FIELDS`.
    warn : bool
        Raise the reader's notes (magnetometers left out, samples dropped...) as :class:`DataWarning` warnings, the
        default; False leaves them in the dataset's ``notes`` only (what the command line, the workbench and the
        engine's own reads do).

    Returns
    -------
    Dataset
        Its ``notes``: what the reader had to say (:class:`~magcal.core.notes.Note`).

    Values that are NaN, infinite or beyond :data:`magcal.data.dataset.MAX_ABS_VALUE` (the rule of every magcal
    reader) are dropped, each kind counted in one :class:`DataWarning`.

    Raises
    ------
    DatasetError
        Missing file, a log the reader cannot parse, no magnetometer messages, too few samples, too slow.
    """
    source = str(name or os.fspath(path))
    path = os.fspath(path)
    if os.path.isdir(path):
        raise DatasetError(f"{source}: is a directory, not a log file")
    check_regular_file(path, "file", DatasetError, source)  # a FIFO would block, a device never end
    if timeout_s is None:
        timeout_s = max(MIN_DEADLINE_S, DEADLINE_S_PER_MB * os.path.getsize(path) / 1e6)
    if path.lower().endswith(".ulg"):
        ds = read_ulog(path, sensors=sensors, name=source, timeout_s=timeout_s)
    elif path.lower().endswith(".bin"):
        ds = read_dataflash(path, sensors=sensors, name=source, undo_calibration=undo_calibration, timeout_s=timeout_s)
    else:
        raise DatasetError(f"{source}: not a flight-controller log (expected {', '.join(LOG_EXTENSIONS)})")
    if ds.n_samples < int(min_samples):
        raise DatasetError(
            f"{source}: {ds.n_samples} magnetometer sample(s), fewer than the {int(min_samples)} "
            "needed; record more attitudes"
        )
    if warn:
        _notes.warn(ds.notes)
    return ds


def _note(text) -> Note:
    """A reader's note (a :class:`DataWarning` at the boundary), said by the step ``read``."""
    return Note(text, DataWarning, "read")


# -- pairing several magnetometers and interpolating channels ------------------------------------------------------
def _strictly_increasing(t, values, source, what, notes):
    """Sort by time and drop repeated time stamps (with a warning): the dataset's times must increase strictly."""
    if t.size == 0:
        return t, values
    order = np.argsort(t, kind="stable")
    t = t[order]
    values = values[order]
    keep = np.concatenate([[True], np.diff(t) > 0])
    if not keep.all():
        notes.append(_note(f"{source}: {what}: {int((~keep).sum())} sample(s) repeat a time stamp and are dropped"))
    return t[keep], values[keep]


def _drop_bad(source, what, t, *arrays, keep=(), notes):
    """Rows of ``t`` and ``arrays`` (same length) whose values all pass the one rule of read values
    (:func:`magcal.data.dataset.bad_values`); the others dropped with one :class:`DataWarning` counting them.
    The arrays of ``keep`` are not checked, only cut to the same rows (returned after the others)."""
    bad = bad_values(t)
    for a in arrays:
        a = np.asarray(a, dtype=float)
        bad |= bad_values(a, axis=tuple(range(1, a.ndim))) if a.ndim > 1 else bad_values(a)
    if bad.any():
        notes.append(
            _note(
                f"{source}: {what}: {int(bad.sum())} of {bad.size} sample(s) hold values {BAD_VALUE_TEXT} "
                "(a damaged log); they are dropped"
            )
        )
    good = ~bad
    return (np.asarray(t)[good], *(np.asarray(a)[good] for a in arrays + tuple(keep)))


def _pair_by_time(series, source, notes):
    """Pair the samples of several magnetometers by time.

    Parameters
    ----------
    series : list of (time_s, values)
        Per magnetometer: times (N_k,) in s (strictly increasing) and values (N_k, ...).
    source : str
        For the warning.

    Returns
    -------
    time_s : numpy.ndarray, shape (N,)
        The first magnetometer's times that every other one has a sample near (within half its median interval).
    values : list of numpy.ndarray
        Each magnetometer's values at those times.
    """
    t0, v0 = series[0]
    if len(series) == 1:
        return t0, [v0]
    step = float(np.median(np.diff(t0))) if t0.size > 1 else np.inf
    keep = np.ones(t0.size, dtype=bool)
    picks = []
    for t, _ in series[1:]:
        if t.size == 0:
            keep[:] = False
            picks.append(np.zeros(t0.size, dtype=int))
            continue
        j = np.clip(np.searchsorted(t, t0), 1, max(t.size - 1, 1))
        j0 = np.clip(j - 1, 0, t.size - 1)
        j1 = np.clip(j, 0, t.size - 1)
        nearest = np.where(np.abs(t[j0] - t0) <= np.abs(t[j1] - t0), j0, j1)
        keep &= np.abs(t[nearest] - t0) <= 0.5 * step
        picks.append(nearest)
    if not keep.all():
        notes.append(
            _note(
                f"{source}: {int((~keep).sum())} of {t0.size} samples of the first magnetometer have no sample "
                "of every other one within half a sample interval; they are dropped"
            )
        )
    values = [v0[keep]] + [v[p[keep]] for (_, v), p in zip(series[1:], picks)]
    return t0[keep], values


def _interp(t, t_src, v_src):
    """Linear interpolation of a channel onto times ``t`` (held constant beyond its ends)."""
    return np.interp(t, t_src, v_src)


#: Longest span (s) between two attitude messages that a magnetometer sample's attitude is interpolated across, and
#: how far (s) from its nearest message a sample outside such a span may be and still take that message's attitude:
#: a sample in a longer gap, or before the first message or after the last by more than the latter, has no attitude
#: (NaN): the vehicle may have turned meanwhile. Logs write the attitude at 10-50 Hz; the live MAVLink source takes
#: the nearest ``ATTITUDE`` within 0.2 s the same way.
LOG_ATTITUDE_MAX_GAP_S = 1.0
LOG_ATTITUDE_HOLD_S = 0.2


def _interp_attitude(t, t_src, rotations, source="log", *, notes):
    """Attitude quaternions (N, 4) ``w, x, y, z`` at times ``t`` by spherical interpolation between the messages
    around each sample; NaN for a sample farther than :data:`LOG_ATTITUDE_HOLD_S` from every message unless the two
    around it are at most :data:`LOG_ATTITUDE_MAX_GAP_S` apart (a note counts them)."""
    t = np.asarray(t, float)
    t_src = np.asarray(t_src, float)
    if t_src.size == 1:
        q = np.repeat(rotations.as_quat()[:1], t.size, axis=0)
    else:
        q = Slerp(t_src, rotations)(np.clip(t, t_src[0], t_src[-1])).as_quat()
    q = np.column_stack([q[:, 3], q[:, :3]])
    k = np.clip(np.searchsorted(t_src, t), 1, max(t_src.size - 1, 1))  # the messages around each sample
    before, after = t_src[np.minimum(k - 1, t_src.size - 1)], t_src[np.minimum(k, t_src.size - 1)]
    nearest = np.minimum(np.abs(t - before), np.abs(after - t))
    spanned = (t >= t_src[0]) & (t <= t_src[-1]) & (after - before <= LOG_ATTITUDE_MAX_GAP_S)
    missing = ~spanned & (nearest > LOG_ATTITUDE_HOLD_S + 1e-6)  # 1 us: the logs' resolution
    if missing.any():
        q[missing] = np.nan
        notes.append(
            _note(
                f"{source}: {int(missing.sum())} of {t.size} magnetometer samples ({row_runs(missing)}) lie more than "
                f"{LOG_ATTITUDE_HOLD_S:g} s from any attitude message, before the first, after the last or in a gap of "
                f"more than {LOG_ATTITUDE_MAX_GAP_S:g} s: they have no attitude (NaN; the vector fit leaves them out)"
            )
        )
    return q


def _build(source, series, temperature=None, attitude=None, extra=None, metadata=None, *, notes):
    """The dataset from per-magnetometer (t, nT) series and optional (t, values) channels.

    A series whose values have six columns holds the raw field (the readings) and then the field the flight
    controller computed with its calibration of the time, kept as the channels ``s{k}x_logged, s{k}y_logged,
    s{k}z_logged`` (:func:`logged_field_columns`)."""
    t, values = _pair_by_time(series, source, notes)
    if t.size == 0:
        raise DatasetError(f"{source}: no magnetometer samples left after pairing the magnetometers by time")
    logged = {}
    if all(v.ndim == 2 and v.shape[1] == 6 for v in values):
        for k, v in enumerate(values):
            logged.update({name: v[:, 3 + a] for a, name in enumerate(logged_field_columns(k))})
        values = [v[:, :3] for v in values]
    kwargs = {}
    if temperature is not None:
        kwargs["temperature_C"] = _interp(t, *temperature)
    extras = {k: _interp(t, ts, v) for k, (ts, v) in (extra or {}).items()}
    extras.update(logged)
    if attitude is not None:
        q = _interp_attitude(t, *attitude, source=source, notes=notes)
        kwargs["attitude_wxyz"] = q
        gap = np.isnan(q).any(axis=1)
        for k in ("att_roll_deg", "att_pitch_deg", "att_yaw_deg"):  # the angles the quaternion was made from
            if k in extras and gap.any():
                extras[k] = np.where(gap, np.nan, extras[k])
    return Dataset(
        readings_nT=np.stack(values), time_s=t, extra=extras, metadata=dict(metadata or {}), source=source, **kwargs
    )


def _alive(series, labels, source, notes):
    """Indices of the magnetometers to keep: those whose samples are not all one vector (zero: no compass fitted,
    or it failed), the others left out with a warning."""
    alive = []
    for k, ((_, v), label) in enumerate(zip(series, labels)):
        v = v[:, :3]  # the readings (a log's series may hold the logged field beside them)
        if v.shape[0] > 1 and np.all(v == v[0]):
            notes.append(
                _note(
                    f"{source}: {label} reads the same vector ({', '.join(f'{x:g}' for x in v[0])}) nT on all "
                    f"{v.shape[0]} samples (zero: no compass fitted, or it failed); it is left out"
                )
            )
            continue
        alive.append(k)
    if not alive:
        raise DatasetError(
            f"{source}: every magnetometer in the log reads one constant vector ({', '.join(labels)}); "
            "there is nothing to calibrate: check that the compass was detected and enabled"
        )
    return alive


def _select(instances, sensors, source, what, notes):
    """The instances chosen by ``sensors`` (0-based positions), at most :data:`MAX_SENSORS`."""
    if sensors is None:
        if len(instances) > MAX_SENSORS:
            notes.append(
                _note(
                    f"{source}: {len(instances)} magnetometers; the first {MAX_SENSORS} are read (choose with sensors=)"
                )
            )
        return instances[:MAX_SENSORS]
    chosen = []
    for k in sensors:
        if not 0 <= int(k) < len(instances):
            raise DatasetError(
                f"{source}: magnetometer {k} asked for, but the log has {len(instances)} "
                f"({', '.join(map(str, instances))}) in its {what}"
            )
        chosen.append(instances[int(k)])
    return chosen


# -- ArduPilot DataFlash ---------------------------------------------------------------------------------------------
def _compass_tag(index) -> str:
    """Parameter infix of ArduPilot compass ``index`` (0-based): '', '2', '3'."""
    return "" if index == 0 else str(index + 1)


def _ardupilot_state_tag(params, instance) -> str:
    """Parameter infix of the compass a ``MAG`` message's instance ``I`` names.

    ArduPilot logs its compasses in the order of their priority (``Compass::Write_Compass_instance`` takes the
    priority index), while ``COMPASS_OFS2_*``, ``COMPASS_DIA2_*``... belong to the second *detected* compass (its
    ``COMPASS_DEV_ID2``). Since 4.1 ``COMPASS_PRIOn_ID`` says which device has priority n: the parameters are those
    whose ``COMPASS_DEV_ID*`` is that device. Without those parameters (older logs) the two orders are one."""
    wanted = params.get(f"COMPASS_PRIO{instance + 1}_ID")
    if wanted:
        for state in range(MAX_SENSORS):
            if params.get(f"COMPASS_DEV_ID{_compass_tag(state)}") == wanted:
                return _compass_tag(state)
    return _compass_tag(instance)


def _ardupilot_matrix(params, index):
    """``SCALE * M`` of the ArduPilot compass logged as instance ``index`` from the parameter values (DIA zero means
    identity; :func:`_ardupilot_state_tag` finds its parameters)."""
    tag = _ardupilot_state_tag(params, index)
    dia = np.array([params.get(f"COMPASS_DIA{tag}_{a}", 1.0) for a in "XYZ"], dtype=float)
    odi = np.array([params.get(f"COMPASS_ODI{tag}_{a}", 0.0) for a in "XYZ"], dtype=float)
    if not np.any(dia):
        dia = np.ones(3)
    m = np.array([[dia[0], odi[0], odi[1]], [odi[0], dia[1], odi[2]], [odi[1], odi[2], dia[2]]])
    scale = float(params.get(f"COMPASS_SCALE{tag}", 0.0))
    if ARDUPILOT_SCALE_RANGE[0] <= scale <= ARDUPILOT_SCALE_RANGE[1]:
        m = m * scale
    if not np.isfinite(m).all() or np.linalg.cond(m) > _ARDUPILOT_MAX_CONDITION:
        raise _DamagedParameters(
            f"the logged calibration of compass {index} (COMPASS_DIA{tag}_*, COMPASS_ODI{tag}_*) is a singular "
            "matrix: the log's parameters are damaged and its raw field cannot be recovered; take the logged field "
            "as it is (read_log(..., undo_calibration=False))"
        )
    return m


#: The largest condition number of a logged compass matrix that is undone: ArduPilot keeps DIA in 0.8-1.2 and ODI
#: within +-0.2 (condition < 4); far beyond, the parameters were damaged.
_ARDUPILOT_MAX_CONDITION = 1e6


class _DamagedParameters(Exception):
    """A log whose compass parameters cannot be undone (said with the file's name by the reader)."""


#: The FMT message (type 128): header, Type B, Length B, Name 4s, Format 16s, Columns 64s.
_DF_FMT_TYPE = 0x80
_DF_FMT_LENGTH = 89
_DF_FMT_RE = re.compile(rb"\xa3\x95\x80")  # the sync bytes, then the type of FMT
#: The message types magcal reads: a damaged format of one of them is refused, not skipped.
_DF_READ_TYPES = ("FMT", "PARM", "MAG", "MAG2", "MAG3", "IMU", "ATT", "GPS", "CTUN", "BAT", "CURR")
#: The message types the reader takes into its tables.
_DF_KEPT_TYPES = ("PARM", "MAG", "MAG2", "MAG3", "IMU", "ATT", "BAT", "CURR", "GPS", "CTUN")


def _c_string(raw: bytes) -> str | None:
    """The NUL-terminated ASCII text of a fixed-size field, or None if it holds other bytes."""
    text = raw.split(b"\0", 1)[0]
    if not all(32 <= b < 127 for b in text):
        return None
    return text.decode("ascii")


def check_dataflash_formats(path, source=None) -> int:
    """Check every FMT message of a DataFlash log before pymavlink reads it; returns how many there are.

    pymavlink steps through the file by the lengths the FMT messages declare: a length below the 3-byte header
    (0 makes it loop forever) or a format whose fields do not fill its length leaves it looping, or silently
    reading the wrong bytes. Each FMT message found (the sync bytes and type 128, then a printable name, format
    and column list: another message's bytes cannot pass for one) is checked. (A format of length 0 made of
    damaged bytes that pass for none is caught while reading: :func:`read_dataflash`'s reader refuses a message
    that does not move it forward; pymavlink's slower Python indexer, used without its compiled one, loops on
    those too, so then every candidate's length is checked.)

    Raises
    ------
    DatasetError
        Not a DataFlash log (no FMT message, which every DataFlash log begins with), or a format that would make
        the reader loop or misread (named, with its byte offset).
    """
    from pymavlink import dfindexer
    from pymavlink.DFReader import FORMAT_TO_STRUCT

    source = str(source or path)
    legacy_indexer = not dfindexer.available or os.environ.get("PYMAVLINK_FAST_INDEX", "1") != "1"
    with open(path, "rb") as fh:
        size = os.fstat(fh.fileno()).st_size
        if size < _DF_FMT_LENGTH:
            raise DatasetError(
                f"{source}: not an ArduPilot DataFlash log ({size} bytes, less than one format message); check the file"
            )
        data = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ)
    try:
        count = 0
        for match in _DF_FMT_RE.finditer(data):
            ofs = match.start()
            body = data[ofs + 3 : ofs + _DF_FMT_LENGTH]
            if len(body) < _DF_FMT_LENGTH - 3:
                break  # a log cut in the middle of its last message
            ftype, length, name, fmt, columns = struct.unpack("<BB4s16s64s", body)
            name, fmt, columns = _c_string(name), _c_string(fmt), _c_string(columns)
            if length < 3 and legacy_indexer:  # pymavlink's Python indexer loops on any of these, named or not
                raise DatasetError(
                    f"{source}: byte {ofs}: a format message declares a length of {length} byte(s), less than the "
                    "3-byte message header: the log is damaged (a reader would loop on it); record it again"
                )
            if not name or fmt is None or columns is None:
                continue  # not a FMT message: these bytes belong to another one
            count += 1
            where = f"{source}: byte {ofs}: the format of message {name} (type {ftype})"
            unknown = sorted(set(fmt) - set(FORMAT_TO_STRUCT))
            if unknown:
                if name in _DF_READ_TYPES:
                    raise DatasetError(
                        f"{where} has field type(s) {''.join(unknown)!r} no DataFlash reader knows; the log is damaged"
                    )
                continue
            need = 3 + struct.calcsize("<" + "".join(FORMAT_TO_STRUCT[c][0] for c in fmt))
            if length < 3:
                raise DatasetError(
                    f"{where} declares a length of {length} byte(s), less than the 3-byte message header: the "
                    "log is damaged (a reader would loop on it); record or download it again"
                )
            if (ftype == _DF_FMT_TYPE or name in _DF_READ_TYPES) and length != need:
                raise DatasetError(
                    f"{where} declares {length} bytes but its fields ({fmt}) take {need}: the log is damaged; "
                    "record or download it again"
                )
        if count == 0:
            raise DatasetError(
                f"{source}: not an ArduPilot DataFlash log: it holds no FMT message, which every DataFlash log "
                "begins with (is it another kind of file, or a text log? magcal reads the binary .bin)"
            )
        return count
    finally:
        data.close()


class _Stuck(Exception):
    """Raised inside pymavlink's reader: ``("slow",)`` past the deadline, ``("loop", offset)`` a message that did
    not move the reader forward."""


def _looping(source, offset):
    return DatasetError(
        f"{source}: byte {offset}: a message does not move the reader forward (its format declares a length below "
        "the 3-byte header): the log is damaged; record or download it again"
    )


_GUARDED: dict = {}


def _guarded_reader(DFReader):
    """pymavlink's ``DFReader_binary`` with two guards on every message it parses (its indexer, its clock set-up,
    every ``recv_match``): the deadline, and progress -- a message that leaves the reader where it was (a format
    of length 0 registered from damaged bytes) stops it instead of looping forever."""
    if "class" not in _GUARDED:

        class GuardedReader(DFReader.DFReader_binary):
            def __init__(self, *args, deadline=None, **kwargs):
                self._deadline = deadline
                super().__init__(*args, **kwargs)

            def _parse_next(self):
                if self._deadline is not None and time.monotonic() > self._deadline:
                    raise _Stuck("slow")
                before = self.offset
                message = super()._parse_next()
                if message is not None and self.offset <= before:
                    raise _Stuck("loop", before)
                return message

        _GUARDED["class"] = GuardedReader
    return _GUARDED["class"]


def read_dataflash(path, sensors=None, name=None, undo_calibration=True, timeout_s=None) -> Dataset:
    """Read an ArduPilot DataFlash ``.bin`` log (see the module docstring). Readings in nT, body frame.

    Its format messages are checked first (:func:`check_dataflash_formats`); reading stops with a
    :class:`DatasetError` after ``timeout_s`` seconds (default: no limit). Values NaN, infinite or beyond
    :data:`magcal.data.dataset.MAX_ABS_VALUE` are dropped with a count. What the reader has to say is the dataset's
    ``notes`` (never raised here: :func:`read_log` raises them).
    """
    source = str(name or path)
    try:
        from pymavlink import DFReader  # noqa: F401  (both readers need it: its checks, its fallback)
    except ImportError:
        raise DatasetError(
            f'{source}: reading ArduPilot logs needs pymavlink: pip install "magcal[instruments]"'
        ) from None
    check_regular_file(path, "file", DatasetError, source)  # a FIFO would block the checks below
    check_dataflash_formats(path, source)
    started = time.monotonic()
    try:
        gathered = _gather_fast(path, source, undo_calibration)  # NumPy, where it gives what pymavlink would
    except _DamagedParameters as exc:
        raise DatasetError(f"{source}: {exc}") from None
    if gathered is not None and timeout_s is not None and time.monotonic() - started > float(timeout_s):
        raise _too_slow(source, timeout_s)
    if gathered is None:
        gathered = _gather_pymavlink(path, source, undo_calibration, timeout_s)
    notes: list[Note] = []
    ds = _dataflash_dataset(source, gathered, sensors, undo_calibration, notes)
    ds.notes = tuple(notes)
    return ds


def _new_gathered() -> dict:
    """The lists a DataFlash reader fills (:func:`_dataflash_message`)."""
    return {
        "params": {},
        "bad_params": [],
        "mags": {},  # instance -> list of rows (t, x, y, z) nT
        "imu": [],  # (t, temperature degC) of the first IMU
        "att": [],  # (t, roll, pitch, yaw) deg
        "bat": [],  # (t, current A) of the first battery
        "curr": [],  # (t, current A) of CURR, the battery message of logs before 2016 (read when there is no BAT)
        "gps": [],  # (t, lat deg, lon deg, alt m, GPS week, GPS ms of week) of the first receiver's 3D fixes
        "thr": [],  # (t, throttle 0-1) of CTUN
        "seen": set(),
        "unhealthy": {},  # compass -> samples the firmware marked unhealthy (left out)
    }


def _too_slow(source, timeout_s) -> DatasetError:
    """The message of a DataFlash read past its deadline."""
    return DatasetError(
        f"{source}: reading stopped after {float(timeout_s):g} s, far longer than a log of this size takes: "
        "the log is damaged; record or download it again"
    )


def _gather_pymavlink(path, source, undo_calibration, timeout_s) -> dict:
    """The messages magcal keeps, read one by one by pymavlink's ``DFReader`` (:func:`read_dataflash`)."""
    from pymavlink import DFReader

    deadline = None if timeout_s is None else time.monotonic() + float(timeout_s)

    def too_slow():
        return _too_slow(source, timeout_s)

    def progress(_percent):
        if deadline is not None and time.monotonic() > deadline:
            raise _Stuck("slow")

    try:
        with warnings.catch_warnings(), open(os.devnull, "w") as devnull:
            warnings.simplefilter("ignore")
            # pymavlink prints a line per damaged byte (thousands for a damaged log) to stdout and stderr
            with contextlib.redirect_stdout(devnull), contextlib.redirect_stderr(devnull):
                log = _guarded_reader(DFReader)(
                    path, zero_time_base=True, progress_callback=progress, deadline=deadline
                )
    except _Stuck as exc:
        raise too_slow() if exc.args[0] == "slow" else _looping(source, exc.args[1]) from None
    except Exception as exc:  # a damaged or foreign file: any failure of the parser is the file's fault
        raise DatasetError(f"{source}: not a readable ArduPilot DataFlash log ({exception_text(exc)})") from None
    try:
        _check_dataflash_counts(log, source)
    except BaseException:
        with contextlib.suppress(Exception):
            log.close()
        raise
    gathered = _new_gathered()
    try:
        with open(os.devnull, "w") as devnull, contextlib.redirect_stdout(devnull), contextlib.redirect_stderr(devnull):
            while True:
                if deadline is not None and time.monotonic() > deadline:
                    raise too_slow()
                m = log.recv_match(type=list(_DF_KEPT_TYPES))
                if m is None:
                    break
                _dataflash_message(m, gathered, undo_calibration)
    except DatasetError:
        raise
    except _DamagedParameters as exc:
        raise DatasetError(f"{source}: {exc}") from None
    except _Stuck as exc:
        raise too_slow() if exc.args[0] == "slow" else _looping(source, exc.args[1]) from None
    except Exception as exc:
        raise DatasetError(f"{source}: the DataFlash log is damaged ({exception_text(exc)})") from None
    finally:
        with contextlib.suppress(Exception):
            log.close()
    return gathered


#: Bytes each message magcal keeps from a DataFlash log takes while it is read (a row of Python floats in a
#: list, then its NumPy row): about 250, for messages of 30-90 bytes in the file.
DATAFLASH_BYTES_PER_MESSAGE = 250


def _check_dataflash_counts(log, source) -> int:
    """The messages of the kinds magcal keeps (pymavlink's index counts them before any is read), refused when
    they would not fit in the free memory (:func:`magcal.core.memory.available_bytes`)."""
    ids = getattr(log, "name_to_id", {}) or {}
    counts = getattr(log, "counts", None) or {}
    try:
        kept = sum(int(counts[ids[name]]) for name in _DF_KEPT_TYPES if name in ids)
    except (TypeError, KeyError, IndexError):
        return 0  # a reader without counts (the legacy indexer's dictionary): nothing to say before reading
    return _check_kept_messages(kept, source)


def _check_kept_messages(kept, source) -> int:
    """Refuse ``kept`` messages of the kinds magcal keeps when they would not fit in the free memory."""
    need = kept * DATAFLASH_BYTES_PER_MESSAGE
    free = available_bytes()
    if free is not None and need > free:
        raise DatasetError(
            f"{source}: {kept:,} messages of the kinds magcal reads (MAG, IMU, ATT, GPS...) would take about "
            f"{need / 1e9:.3g} GB, more than the {free / 1e9:.3g} GB of memory free: cut the log to the stretch you "
            "need (e.g. with MAVExplorer or mavlogdump.py), or use a machine with more memory"
        )
    return kept


class _Message:
    """One decoded DataFlash message as :func:`_dataflash_message` reads it (pymavlink's ``DFMessage``'s
    attributes and ``get_type``)."""

    def __init__(self, kind, fields):
        self._kind, self._fields = kind, fields

    def get_type(self):
        return self._kind

    def __getattr__(self, name):
        try:
            return self.__dict__["_fields"][name]
        except KeyError:
            raise AttributeError(name) from None


def _gather_fast(path, source, undo_calibration) -> dict | None:
    """What :func:`_gather_pymavlink` gathers, read with NumPy (:mod:`magcal.data.dataflash_scan`): the compass,
    attitude and IMU messages as columns, the few others one by one through :func:`_dataflash_message`; None where
    the scan could differ from pymavlink (it then reads the log). On a synthetic log of 1.2 million MAG messages
    (47 MB): 3.4-6.1 s against 233 s on the loaded 2-core machine (``benchmarks/dataflash_read.py``)."""
    found = dataflash_scan.scan(path)
    if found is None:
        return None
    rows = {name: found.of(name) for name in _DF_KEPT_TYPES}
    _check_kept_messages(sum(len(r) for r in rows.values()), source)
    decoded = {name: found.columns(name, r) for name, r in rows.items() if len(r)}
    cols: dict[str, dict] = {name: c for name, c in decoded.items() if c is not None}
    if len(cols) < len(decoded) or ("ATT" in cols and not {"Roll", "Pitch", "Yaw"} <= set(cols["ATT"])):
        return None  # a field not decoded here, an ATT without its angles (pymavlink's reader says so)
    if any(name in cols and not {"MagX", "MagY", "MagZ"} <= set(cols[name]) for name in ("MAG", "MAG2", "MAG3")):
        return None  # a compass message without its field (a damaged FMT: pymavlink's reader says so)
    gathered = _new_gathered()
    gathered["seen"] = set(cols)
    mags = [(name, rows[name]) for name in ("MAG", "MAG2", "MAG3") if name in cols]
    if len(mags) > 1 and "MAG" in cols and np.any(cols["MAG"].get("I", np.zeros(1)) != 0):
        return None  # compasses 2 and 3 in both MAG and MAGn messages: their rows would interleave
    epochs = {n: np.searchsorted(rows["PARM"], r) for n, r in mags}  # the parameters read before each message
    wanted = set(np.unique(np.concatenate([e for e in epochs.values()] or [np.zeros(0, int)])).tolist())
    params_at: dict[int, dict] = {0: {}} if 0 in wanted else {}
    for name in ("PARM", "GPS", "BAT", "CURR", "CTUN"):
        if name in cols:
            names = list(cols[name])
            for k, values in enumerate(zip(*(cols[name][c].tolist() for c in names))):
                _dataflash_message(_Message(name, dict(zip(names, values))), gathered, undo_calibration)
                if name == "PARM" and k + 1 in wanted:
                    params_at[k + 1] = dict(gathered["params"])
    for name, _ in mags:
        _fast_mag(name, cols[name], epochs[name], params_at, gathered, undo_calibration)
    if cols.get("ATT"):
        att = cols["ATT"]
        gathered["att"] = np.column_stack([_seconds(att), att["Roll"], att["Pitch"], att["Yaw"]])
    if cols.get("IMU"):  # an IMU format of no fields holds nothing to take
        _fast_imu(cols["IMU"], gathered)
    return gathered


def _seconds(cols) -> np.ndarray:
    """Each message's board time, s, as :func:`_dataflash_message` takes it (``TimeUS``, else ``TimeMS``)."""
    n = len(next(iter(cols.values())))
    if "TimeUS" in cols:
        return cols["TimeUS"].astype(float) * 1e-6
    t_ms = cols["TimeMS"] if "TimeMS" in cols else np.zeros(n)
    return (t_ms * 1000.0).astype(float) * 1e-6


def _fast_mag(name, cols, epochs, params_at, gathered, undo_calibration) -> None:
    """A compass message type's columns into ``gathered`` as :func:`_dataflash_message` takes each message: the
    logged calibration undone with the parameters read before it (one solve per message, as there)."""
    n = len(epochs)
    t = _seconds(cols)
    zeros = np.zeros(n)
    instance = (cols["I"] if "I" in cols else zeros).astype(int) if name == "MAG" else np.full(n, int(name[3:]) - 1)
    healthy = (cols["Health"] != 0) if "Health" in cols else np.ones(n, bool)
    logged = np.column_stack([cols[f"Mag{a}"].astype(float) for a in "XYZ"])
    ofs = np.column_stack([cols.get(f"Ofs{a}", zeros).astype(float) for a in "XYZ"])
    mot = np.column_stack([cols.get(f"MO{a}", cols.get(f"MOfs{a}", zeros)).astype(float) for a in "XYZ"])
    for k in np.unique(instance).tolist():
        mine = instance == k
        bad = int(np.count_nonzero(mine & ~healthy))
        if bad:
            gathered["unhealthy"][k] = gathered["unhealthy"].get(k, 0) + bad
        parts = []
        for e in np.unique(epochs[mine & healthy]).tolist():
            sel = mine & healthy & (epochs == e)
            if undo_calibration:
                matrix = _ardupilot_matrix(params_at[e], k)
                raw_mG = np.linalg.solve(matrix[None], (logged[sel] - mot[sel])[..., None])[..., 0] - ofs[sel]
                parts.append(np.column_stack([t[sel], raw_mG * NT_PER_MILLIGAUSS, logged[sel] * NT_PER_MILLIGAUSS]))
            else:
                parts.append(np.column_stack([t[sel], logged[sel] * NT_PER_MILLIGAUSS]))
        if parts:
            before = gathered["mags"].get(k)
            gathered["mags"][k] = np.concatenate(([np.asarray(before)] if before is not None else []) + parts)


def _fast_imu(cols, gathered) -> None:
    """The first IMU's temperature and accelerometer and gyro as :func:`_dataflash_message` takes them."""
    t = _seconds(cols)
    first = (cols["I"].astype(int) == 0) if "I" in cols else np.ones(len(t), bool)
    if "T" in cols:
        gathered["imu"] = np.column_stack([t[first], cols["T"][first].astype(float)])
    if "AccX" in cols:
        nan = np.full(len(t), np.nan)
        acc = [cols.get(k, nan).astype(float)[first] for k in _DATAFLASH_IMU]
        gathered["acc"] = np.column_stack([t[first], *acc])


def _dataflash_message(m, gathered, undo_calibration):
    """Take one PARM, MAG, IMU, ATT, BAT, CURR, CTUN or GPS message into ``gathered`` (the lists
    :func:`read_dataflash` fills)."""
    kind = m.get_type()
    gathered["seen"].add(kind)
    if kind == "GPS":
        _dataflash_gps(m, gathered["gps"])
        return
    if kind == "PARM":
        name, value = getattr(m, "Name", None), getattr(m, "Value", None)
        if name is None or value is None:  # a PARM whose format (FMT) lacks the fields: nothing to take
            return
        try:
            value = float(value)
        except (TypeError, ValueError):
            value = float("nan")
        if bad_values(value):
            gathered["bad_params"].append(str(name))
        else:
            gathered["params"][str(name)] = value
        return
    t_us = getattr(m, "TimeUS", None)
    if t_us is None:
        t_us = getattr(m, "TimeMS", 0) * 1000.0
    t = float(t_us) * 1e-6
    if kind.startswith("MAG"):
        instance = int(getattr(m, "I", 0) or 0) if kind == "MAG" else int(kind[3:]) - 1
        if getattr(m, "Health", 1) == 0:
            gathered["unhealthy"][instance] = gathered["unhealthy"].get(instance, 0) + 1
            return
        logged_mG = np.array([m.MagX, m.MagY, m.MagZ], dtype=float)
        if undo_calibration:  # the raw field, then the logged one (kept as channels: the firmware's calibration)
            ofs = np.array([getattr(m, f"Ofs{a}", 0.0) for a in "XYZ"], dtype=float)
            mot = np.array([getattr(m, f"MO{a}", getattr(m, f"MOfs{a}", 0.0)) for a in "XYZ"], dtype=float)
            raw_mG = np.linalg.solve(_ardupilot_matrix(gathered["params"], instance), logged_mG - mot) - ofs
            row = (t, *(raw_mG * NT_PER_MILLIGAUSS), *(logged_mG * NT_PER_MILLIGAUSS))
        else:
            row = (t, *(logged_mG * NT_PER_MILLIGAUSS))
        gathered["mags"].setdefault(instance, []).append(row)
    elif kind == "IMU":
        if int(getattr(m, "I", 0) or 0) == 0 and hasattr(m, "T"):
            gathered["imu"].append((t, float(m.T)))
        if int(getattr(m, "I", 0) or 0) == 0 and hasattr(m, "AccX"):
            gathered.setdefault("acc", []).append((t, *(float(getattr(m, k, np.nan)) for k in _DATAFLASH_IMU)))
    elif kind == "ATT":
        gathered["att"].append((t, float(m.Roll), float(m.Pitch), float(m.Yaw)))
    elif kind == "BAT":
        if int(getattr(m, "Inst", getattr(m, "Instance", 0)) or 0) == 0 and hasattr(m, "Curr"):
            gathered["bat"].append((t, float(m.Curr)))
    elif kind == "CURR":
        if hasattr(m, "Curr"):  # centiamperes: the firmware logged (int16_t)(battery.current_amps() * 100)
            gathered["curr"].append((t, float(m.Curr) / 100.0))
    elif kind == "CTUN":
        if hasattr(m, "ThO"):  # 0..1 (Copter 3.3 and later, Plane)
            gathered["thr"].append((t, float(m.ThO)))
        elif hasattr(m, "ThrOut"):  # 0..1000 (Copter before 3.3)
            gathered["thr"].append((t, float(m.ThrOut) / 1000.0))


#: The first IMU's fields read beside the compass: the accelerometer (m/s^2) and the gyro (rad/s), body frame.
_DATAFLASH_IMU = ("AccX", "AccY", "AccZ", "GyrX", "GyrY", "GyrZ")
#: The extra columns they become (:mod:`magcal.data.accelerometer`, :data:`magcal.data.attitude.GYRO_COLUMNS`).
IMU_COLUMNS = ("ax", "ay", "az", "gx_rad_s", "gy_rad_s", "gz_rad_s")


def _imu_channels(source, t, values, what, metadata, notes) -> dict:
    """The accelerometer and gyro as extra channels ``{name: (t, values)}`` (:data:`IMU_COLUMNS`), bad samples
    dropped with a count, ``metadata['accel_units']`` set; {} when there are none."""
    t, values = _drop_bad(source, what, np.asarray(t, float), np.asarray(values, float), notes=notes)
    if t.size < 2:
        return {}
    t, values = _strictly_increasing(t, values, source, what, notes)
    metadata["accel_units"] = "m/s^2"
    return {name: (t, values[:, k]) for k, name in enumerate(IMU_COLUMNS)}


#: GPS time starts at 1980-01-06 (leap seconds do not matter to a date for IGRF).
_GPS_EPOCH_DAY = np.datetime64("1980-01-06")


def _dataflash_gps(m, rows):
    """Append one DataFlash ``GPS`` message with a 3D fix of the first receiver to ``rows``.

    The board time is ``TimeUS`` (us), or in logs before 2015 ``T`` (ms): there ``TimeMS`` is the GPS time of week,
    which must not be taken for the board's clock (it is hundreds of thousands of seconds off)."""
    if int(getattr(m, "I", 0) or 0) != 0 or int(getattr(m, "Status", 0) or 0) < 3:
        return
    if getattr(m, "TimeUS", None) is not None:
        t = float(m.TimeUS) * 1e-6
    elif getattr(m, "T", None) is not None:
        t = float(m.T) * 1e-3
    else:
        return  # no board time: a GPS sample cannot be placed beside the compass's
    week = getattr(m, "GWk", getattr(m, "Week", None))
    ms = getattr(m, "GMS", getattr(m, "TimeMS", None) if hasattr(m, "Week") else None)
    lat, lon = float(getattr(m, "Lat", 0.0)), float(getattr(m, "Lng", 0.0))
    if lat == 0.0 and lon == 0.0:
        return
    rows.append((t, lat, lon, float(getattr(m, "Alt", 0.0)), float(week or 0), float(ms or 0)))


def gps_week_date(week, ms_of_week) -> str | None:
    """ISO date (``YYYY-MM-DD``) of a GPS week and millisecond of the week; None for week 0 (no time yet)."""
    if not week or week <= 0:
        return None
    day = _GPS_EPOCH_DAY + np.timedelta64(int(week) * 7 + int(ms_of_week // 86_400_000), "D")
    return str(day)


def _position(source, t, lat, lon, alt_m, what, notes):
    """``{"lat": (t, deg), "lon": ..., "alt_m": ...}`` of fixes, bad or impossible values dropped; {} if none."""
    t, lat, lon, alt_m = _drop_bad(source, what, np.asarray(t, float), lat, lon, alt_m, notes=notes)
    ok = (np.abs(lat) <= 90) & (np.abs(lon) <= 360) & (np.abs(alt_m) < 100_000)
    if not ok.any():
        return {}
    t, both = _strictly_increasing(t[ok], np.column_stack([lat[ok], lon[ok], alt_m[ok]]), source, what, notes)
    return {"lat": (t, both[:, 0]), "lon": (t, both[:, 1]), "alt_m": (t, both[:, 2])}


def _dataflash_dataset(source, gathered, sensors, undo_calibration, notes):
    """The dataset from the gathered messages (readings in nT), bad values dropped with a count."""
    mags = gathered["mags"]
    if gathered["bad_params"]:
        notes.append(
            _note(
                f"{source}: {len(gathered['bad_params'])} parameter value(s) {BAD_VALUE_TEXT} are ignored "
                f"({', '.join(dict.fromkeys(gathered['bad_params']))})"
            )
        )
    for k, count in sorted(gathered["unhealthy"].items()):
        notes.append(
            _note(f"{source}: compass {k + 1}: {count} sample(s) the firmware marked unhealthy (Health 0) are left out")
        )
    if not mags:
        raise DatasetError(
            f"{source}: no MAG messages (compass data); the log holds "
            f"{', '.join(sorted(gathered['seen'])) or 'none of MAG, IMU, ATT, PARM'}. Enable compass logging "
            "(LOG_BITMASK) and record again"
        )
    instances = _select(sorted(mags), sensors, source, "MAG messages", notes)
    series = []
    for k in instances:
        rows = np.asarray(mags[k], dtype=float)
        t, xyz = _drop_bad(source, f"compass {k + 1}", rows[:, 0], rows[:, 1:], notes=notes)
        series.append(_strictly_increasing(t, xyz, source, f"compass {k + 1}", notes))
    if not any(t.size for t, _ in series):
        raise DatasetError(f"{source}: no usable MAG samples: every one holds values {BAD_VALUE_TEXT}")
    labels = [f"compass {k + 1}" for k in instances]
    keep = _alive(series, labels, source, notes)
    series, labels = [series[i] for i in keep], [labels[i] for i in keep]
    temperature = attitude = None
    extra = {}
    imu = np.asarray(gathered["imu"], dtype=float).reshape(-1, 2)
    imu_t, imu_temp = _drop_bad(source, "IMU temperature", imu[:, 0], imu[:, 1], notes=notes)
    if imu_t.size:
        temperature = _strictly_increasing(imu_t, imu_temp, source, "IMU temperature", notes)
    att = np.asarray(gathered["att"], dtype=float).reshape(-1, 4)
    att_t, angles = _drop_bad(source, "ATT", att[:, 0], att[:, 1:], notes=notes)
    if att_t.size:
        ta, angles = _strictly_increasing(att_t, angles, source, "ATT", notes)
        attitude = (ta, Rotation.from_euler("ZYX", angles[:, ::-1], degrees=True))
        yaw = np.degrees(np.unwrap(np.radians(angles[:, 2])))
        extra = {"att_roll_deg": (ta, angles[:, 0]), "att_pitch_deg": (ta, angles[:, 1]), "att_yaw_deg": (ta, yaw)}
    acc = np.asarray(gathered.get("acc", []), dtype=float).reshape(-1, 7)
    imu_metadata: dict = {}
    extra.update(_imu_channels(source, acc[:, 0], acc[:, 1:], "IMU accelerometer", imu_metadata, notes))
    battery = "BAT" if gathered["bat"] else "CURR"
    bat = np.asarray(gathered["bat"] or gathered["curr"], dtype=float).reshape(-1, 2)
    bat_t, amps = _drop_bad(source, battery, bat[:, 0], bat[:, 1], notes=notes)
    if bat_t.size > 1 and np.ptp(amps) > 0:  # a current that never changes is no channel (no current sensor)
        extra["current_A"] = _strictly_increasing(bat_t, amps, source, battery, notes)
    thr = np.asarray(gathered["thr"], dtype=float).reshape(-1, 2)
    thr_t, throttle = _drop_bad(source, "CTUN throttle", thr[:, 0], thr[:, 1], notes=notes)
    if thr_t.size > 1 and np.ptp(throttle) > 0:  # a throttle that never moves is no channel (motors off)
        extra["throttle"] = _strictly_increasing(thr_t, throttle, source, "CTUN", notes)
    metadata = {
        "log_format": "ArduPilot DataFlash",
        "log_magnetometers": ", ".join(labels),
        "log_field": "raw (logged calibration undone)" if undo_calibration else "as logged (calibrated)",
    }
    if undo_calibration:
        metadata["log_logged_field"] = (
            "s{k}x_logged..: the field the flight controller computed (COMPASS_OFS*, DIA*, ODI*, SCALE*, MOT*)"
        )
    metadata.update(imu_metadata)
    if "COMPASS_DEC" in gathered["params"]:  # the declination (rad) the vehicle turned magnetic into true heading with
        metadata["log_declination_deg"] = f"{np.degrees(gathered['params']['COMPASS_DEC']):.4f}"
        if "COMPASS_AUTODEC" in gathered["params"]:
            metadata["log_autodec"] = f"{gathered['params']['COMPASS_AUTODEC']:g}"
    gps = np.asarray(gathered["gps"], dtype=float).reshape(-1, 6)
    if gps.size:
        extra.update(_position(source, gps[:, 0], gps[:, 1], gps[:, 2], gps[:, 3], "GPS", notes))
        dated = gps[gps[:, 4] > 0]
        date = gps_week_date(dated[0, 4], dated[0, 5]) if dated.size else None
        if date:
            metadata["date"] = date
        if "lat" in extra:
            metadata["position"] = "GPS 3D fixes (lat, lon deg; alt_m above mean sea level)"
    ds = _build(source, series, temperature, attitude, extra, metadata, notes=notes)
    if "att_yaw_deg" in ds.extra:
        ds.extra["att_yaw_deg"] = (ds.extra["att_yaw_deg"] + 180.0) % 360.0 - 180.0
    return ds


# -- PX4 ULog --------------------------------------------------------------------------------------------------------
def read_ulog(path, sensors=None, name=None, timeout_s=None) -> Dataset:
    """Read a PX4 ``.ulg`` log (see the module docstring). Readings in nT, each magnetometer's own frame.

    Its format definitions are checked first (:func:`check_ulog_definitions`); pyulog's reading stops with a
    :class:`DatasetError` after ``timeout_s`` seconds (default: no limit) or when the messages it subscribes to
    would flatten into more than :data:`ULOG_MAX_SUBSCRIBED_FIELDS` fields (:func:`_guarded_ulog`). What the reader
    has to say is the dataset's ``notes`` (never raised here: :func:`read_log` raises them)."""
    notes: list[Note] = []
    ds = _ulog_dataset(path, sensors, str(name or path), timeout_s, notes)
    ds.notes = tuple(notes)
    return ds


def _ulog_dataset(path, sensors, source, timeout_s, notes) -> Dataset:
    """:func:`read_ulog`'s dataset, its notes appended to ``notes`` (the read's own list)."""
    try:
        from pyulog import ULog
    except ImportError:
        raise DatasetError(f'{source}: reading PX4 logs needs pyulog: pip install "magcal[instruments]"') from None
    check_regular_file(path, "file", DatasetError, source)  # a FIFO would block the checks below
    deadline = None if timeout_s is None else time.monotonic() + float(timeout_s)
    check_ulog_definitions(path, source, deadline=deadline)
    try:
        with open(os.devnull, "w") as devnull, contextlib.redirect_stdout(devnull):  # pyulog prints its warnings
            ulog = _guarded_ulog(ULog)(path, _ULOG_TOPICS, deadline=deadline)
    except _Stuck as exc:
        if exc.args[0] == "slow":
            raise DatasetError(
                f"{source}: reading stopped after {float(timeout_s or 0):g} s, far longer than a log of this size "
                "takes: the log is damaged; record or download it again"
            ) from None
        raise DatasetError(f"{source}: {exc.args[1]}") from None
    except Exception as exc:  # a damaged or foreign file
        raise DatasetError(f"{source}: not a readable PX4 ULog file ({exception_text(exc)})") from None
    mags = sorted((d for d in ulog.data_list if d.name == "sensor_mag"), key=lambda d: d.multi_id)
    if not mags:
        return _ulog_calibrated_field(ulog, source, notes)
    chosen = _select(mags, sensors, source, "sensor_mag instances", notes)
    series = []
    temps = []
    for d in chosen:
        data = d.data
        what = f"sensor_mag {d.multi_id}"
        t_key = "timestamp_sample" if "timestamp_sample" in data else "timestamp"
        _require_fields(data, [t_key, "x", "y", "z"], source, what)
        t = np.asarray(data[t_key], dtype=float) * 1e-6
        xyz = np.column_stack([data[a] for a in "xyz"]).astype(float) * NT_PER_GAUSS
        temp = np.asarray(data.get("temperature", np.full(t.size, np.nan)), dtype=float)
        temp = np.where(bad_values(temp), np.nan, temp)  # a bad temperature is a missing one (NaN: none)
        t, xyz, temp = _drop_bad(source, what, t, xyz, keep=(temp,), notes=notes)
        t, both = _strictly_increasing(t, np.column_stack([xyz, temp]), source, what, notes)
        series.append((t, both[:, :3]))
        temps.append((t, both[:, 3]))
    if not any(t.size for t, _ in series):
        raise DatasetError(f"{source}: no usable sensor_mag samples: every one holds values {BAD_VALUE_TEXT}")
    keep = _alive(series, [f"sensor_mag {d.multi_id}" for d in chosen], source, notes)
    series, temps, chosen = [series[i] for i in keep], [temps[i] for i in keep], [chosen[i] for i in keep]
    temperature = None
    t_temp, v_temp = temps[0]
    finite = np.isfinite(v_temp)
    if finite.any() and np.any(v_temp[finite] != 0.0):  # all exactly 0: the driver has no temperature (SITL)
        temperature = (t_temp[finite], v_temp[finite])
    attitude = _ulog_attitude(ulog, source, notes)
    devices = [str(int(d.data["device_id"][0])) for d in chosen if "device_id" in d.data and len(d.data["device_id"])]
    metadata = {
        "log_format": "PX4 ULog",
        "log_magnetometers": ", ".join(f"sensor_mag {d.multi_id}" for d in chosen),
        "log_field": "raw (sensor_mag, before CAL_MAGn_*)",
    }
    if devices:
        metadata["log_device_ids"] = ", ".join(devices)
    current = _ulog_current(ulog, source, notes)
    extra = {**(current or {}), **_ulog_position(ulog, source, metadata, notes)}
    extra.update(_ulog_imu(ulog, source, metadata, notes))
    logged = _px4_logged_fields(ulog, chosen, series, current, source, notes)
    if logged is not None:
        series = [(t, np.column_stack([v, f])) for (t, v), f in zip(series, logged)]
        metadata["log_logged_field"] = (
            "s{k}x_logged..: the field PX4 computed with the log's CAL_MAGn_* (and board rotation) parameters"
        )
    return _build(source, series, temperature, attitude, extra, metadata, notes=notes)


#: PX4's (and MAVLink's) sensor rotations that are not right angles (number -> roll, pitch, yaw in deg), beside
#: :data:`magcal.geometry.orientations.FIRMWARE_ROTATIONS`; ``R = Rz(yaw) Ry(pitch) Rx(roll)`` as there.
PX4_ODD_ROTATIONS = {
    1: (0, 0, 45),
    3: (0, 0, 135),
    5: (0, 0, 225),
    7: (0, 0, 315),
    9: (180, 0, 45),
    11: (180, 0, 135),
    13: (180, 0, 225),
    15: (180, 0, 315),
    17: (90, 0, 45),
    19: (90, 0, 135),
    21: (270, 0, 45),
    23: (270, 0, 135),
    39: (0, 315, 0),
    40: (90, 315, 0),
}


def _px4_rotation(number):
    """The rotation matrix of a PX4 rotation number (``CAL_MAGn_ROT``, ``SENS_BOARD_ROT``), or None if unknown."""
    angles = FIRMWARE_ROTATIONS.get(int(number), PX4_ODD_ROTATIONS.get(int(number)))
    return None if angles is None else euler_matrix(*angles)


def _px4_logged_fields(ulog, chosen, series, current, source, notes):
    """The field PX4 computed from each ``sensor_mag`` (nT, body frame) with the log's calibration parameters,
    as ``calibration::Magnetometer::Correct`` does: ``R S (raw + power * COMP - OFF)`` with ``S`` the symmetric matrix
    of ``CAL_MAGn_[XYZ]SCALE`` and ``CAL_MAGn_[XYZ]ODIAG``, ``R`` the rotation ``CAL_MAGn_ROT`` of an external
    magnetometer or the board's ``SENS_BOARD_ROT`` of an internal one, turned by ``SENS_BOARD_[XYZ]_OFF``; the
    power is the battery current in kA with ``CAL_MAG_COMP_TYP`` 2 or 3. The parameters are the log's initial
    ones. None (the before/after comparison then uses the raw field) when a magnetometer has no ``CAL_MAGn_ID``
    of its device, the log is older than the raw ``sensor_mag`` (no ``is_external`` field), or a rotation or a
    throttle compensation cannot be reproduced (a note says which)."""
    params = ulog.initial_parameters

    def say_none(why):
        notes.append(_note(f"{source}: the field PX4 computed is not reconstructed: {why}"))

    if not any(k.startswith("CAL_MAG") for k in params):
        return None
    level = euler_matrix(*(float(params.get(f"SENS_BOARD_{a}_OFF", 0.0)) for a in "XYZ"))
    comp_type = int(params.get("CAL_MAG_COMP_TYP", 0))
    out = []
    for d, (t, raw) in zip(chosen, series):
        data = d.data
        if "device_id" not in data or "is_external" not in data or not len(data["device_id"]):
            return None
        device = int(data["device_id"][0])
        index = next((n for n in range(MAX_SENSORS) if int(params.get(f"CAL_MAG{n}_ID", -1)) == device), None)
        if index is None:
            say_none(f"sensor_mag {d.multi_id} (device {device}) has no CAL_MAGn_ID")
            return None
        external = bool(data["is_external"][0])
        number = params.get(f"CAL_MAG{index}_ROT", 0) if external else params.get("SENS_BOARD_ROT", 0)
        rot = _px4_rotation(number)
        if rot is None:
            say_none(f"rotation {int(number)} of sensor_mag {d.multi_id} is not one magcal knows")
            return None

        def vec(name, default, index=index):
            return np.array([float(params.get(f"CAL_MAG{index}_{a}{name}", default)) for a in "XYZ"])

        diag, odiag = vec("SCALE", 1.0), vec("ODIAG", 0.0)
        scale = np.array([[diag[0], odiag[0], odiag[1]], [odiag[0], diag[1], odiag[2]], [odiag[1], odiag[2], diag[2]]])
        offset_nT = vec("OFF", 0.0) * NT_PER_GAUSS
        comp_nT = vec("COMP", 0.0) * NT_PER_GAUSS
        power = np.zeros(len(t))
        if comp_type in (2, 3) and np.any(comp_nT) and current is not None:
            power = np.interp(t, *current["current_A"]) * 1e-3  # kA, as PX4's VehicleMagnetometer passes it
        elif np.any(comp_nT) and comp_type != 0:
            say_none(f"CAL_MAG_COMP_TYP {comp_type} compensates throttle, which magcal does not read from PX4 logs")
            return None
        out.append((raw + power[:, None] * comp_nT[None] - offset_nT) @ (level @ rot @ scale).T)
    return out


def _ulog_imu(ulog, source, metadata, notes) -> dict:
    """The accelerometer (m/s^2) and gyro (rad/s) of ``sensor_combined`` (body frame, the vehicle's calibration
    applied) as extra channels (:data:`IMU_COLUMNS`); {} when the log has none."""
    found = [d for d in ulog.data_list if d.name == "sensor_combined" and "accelerometer_m_s2[0]" in d.data]
    if not found:
        return {}
    data = found[0].data
    if "timestamp" not in data or "gyro_rad[0]" not in data:
        return {}
    t = np.asarray(data["timestamp"], dtype=np.int64)
    if "accelerometer_timestamp_relative" in data:
        rel = np.asarray(data["accelerometer_timestamp_relative"], dtype=np.int64)
        t = np.where(rel != _RELATIVE_TIMESTAMP_INVALID, t + rel, t)
    values = np.column_stack(
        [data[f"accelerometer_m_s2[{k}]"] for k in range(3)] + [data[f"gyro_rad[{k}]"] for k in range(3)]
    ).astype(float)
    return _imu_channels(source, t * 1e-6, values, "sensor_combined accelerometer", metadata, notes)


#: The ULog topics magcal reads (pyulog keeps the data of these only).
_ULOG_TOPICS = [
    "sensor_mag",
    "vehicle_attitude",
    "vehicle_magnetometer",
    "sensor_combined",
    "battery_status",
    "vehicle_gps_position",
    "sensor_gps",
]

#: A ULog format may nest other formats (``esc_status`` holds ``esc_report esc[8]``), which pyulog flattens into
#: one field per basic value, each with its own Python object and name: ``t0:t1[2] a;`` ... ``tN:...`` makes 2^N
#: fields from a few hundred bytes (554 bytes took 24 s and 3 GB). PX4's messages nest two levels deep and flatten
#: into a few hundred fields at most (``satellite_info``, ``ulog_stream``); these bounds are far beyond them.
ULOG_MAX_NESTING = 8
#: Most fields one message may flatten into (pyulog: about 3 us and 500 bytes each).
ULOG_MAX_FIELDS = 10_000
#: Most characters of one message's flattened field names (``esc[7].esc_rpm``...).
ULOG_MAX_NAME_CHARS = 1_000_000
#: Most fields all the subscriptions of a log (its ``A`` messages, each flattened anew) may flatten into; a
#: real log's hundred-odd topics flatten into some thousands.
ULOG_MAX_SUBSCRIBED_FIELDS = 500_000

_ULOG_MAGIC = b"ULog\x01\x12\x35"
_ULOG_DEFINITIONS_END = {ord("A"), ord("L"), ord("C")}  # the first of these begins the data section
_ULOG_DEFINITION_TYPES = {ord(c) for c in "FIMPQB"}  # the messages pyulog reads in the definitions section


def ulog_format_sizes(formats) -> dict:
    """What each ULog format flattens into, computed from the definitions alone (nothing is expanded).

    Parameters
    ----------
    formats : dict of str to list of (type, array_size, name)
        Each format's fields as pyulog parses them (``ULog.MessageFormat.fields``: ``array_size`` 0 for a
        single value).

    Returns
    -------
    dict of str to (int, int, int) or str
        Per format: ``(fields, name_chars, depth)`` -- the flattened fields, an upper bound of their names'
        characters, and the nesting depth (1: basic fields only); or the text of a problem: a format that nests
        itself (a cycle), or nesting deeper than :data:`ULOG_MAX_NESTING`. A field of a type that is neither basic
        nor defined counts for nothing (pyulog drops such a subscription as damaged).
    """
    from pyulog import ULog

    basic = ULog._UNPACK_TYPES
    sizes: dict = {}

    def size(name, chain):
        if name in sizes:
            return sizes[name]
        if name in chain:
            return f"format {name} nests itself ({' -> '.join(chain[chain.index(name) :] + (name,))})"
        if len(chain) >= ULOG_MAX_NESTING:
            return f"formats nest more than {ULOG_MAX_NESTING} levels deep ({' -> '.join(chain[:4])} ...)"
        fields = chars = 0
        depth = 1
        for type_name, array_size, field_name in formats[name]:
            count = max(int(array_size), 1)
            index_chars = len(str(count)) + 3 if array_size else 1  # "[12]." or "."
            if type_name in basic:
                fields += count
                chars += count * (len(field_name) + index_chars)
            elif type_name in formats:
                inner = size(type_name, (*chain, name))
                if isinstance(inner, str):
                    sizes[name] = inner
                    return inner
                inner_fields, inner_chars, inner_depth = inner
                fields += count * inner_fields
                chars += count * (inner_fields * (len(field_name) + index_chars) + inner_chars)
                depth = max(depth, inner_depth + 1)
        sizes[name] = (fields, chars, depth)
        return sizes[name]

    for name in formats:
        size(name, ())
    return sizes


def ulog_format_problem(name, found) -> str | None:
    """What is wrong with format ``name`` of sizes ``found`` (:func:`ulog_format_sizes`), or None."""
    if isinstance(found, str):
        return found
    fields, chars, _ = found
    if fields > ULOG_MAX_FIELDS:
        return f"format {name} flattens into {fields:,} fields, more than the {ULOG_MAX_FIELDS:,} magcal reads"
    if chars > ULOG_MAX_NAME_CHARS:
        return (
            f"format {name}'s flattened field names take {chars:,} characters, more than the "
            f"{ULOG_MAX_NAME_CHARS:,} magcal reads"
        )
    return None


def _damaged_formats(problem) -> str:
    return (
        f"{problem}: no PX4 message is like this, and reading it would take time and memory without bound; the log "
        "is damaged or was crafted"
    )


def check_ulog_definitions(path, source=None, deadline=None) -> int:
    """Check the format definitions of a ULog file before pyulog reads it; returns how many formats there are.

    The definitions section (after the 16-byte header, up to the first subscription or logged string) is walked
    message by message (a 3-byte header: size, type); each format message (``F``) is parsed with pyulog's own
    parser, and every format's flattened size is computed without expanding it (:func:`ulog_format_sizes`). A
    format that nests itself, nests deeper than :data:`ULOG_MAX_NESTING`, or flattens into more than
    :data:`ULOG_MAX_FIELDS` fields (or :data:`ULOG_MAX_NAME_CHARS` characters of names) is refused. A file that
    does not begin with the ULog header is left to pyulog (which says so); a damaged stretch ends the walk (pyulog
    skips it byte by byte; what it finds after it is bounded inside it: :func:`_guarded_ulog`).

    Raises
    ------
    DatasetError
        Naming the format and the byte offset of its definition.
    """
    from pyulog import ULog

    source = str(source or path)
    formats, offsets = {}, {}
    with open(path, "rb") as fh:
        if fh.read(16)[:7] != _ULOG_MAGIC:
            return 0
        offset = 16
        for count in itertools.count():
            if deadline is not None and count % 4096 == 0 and time.monotonic() > deadline:
                raise DatasetError(f"{source}: reading its definitions took too long: the log is damaged")
            head = fh.read(3)
            if len(head) < 3:
                break
            size, kind = struct.unpack("<HB", head)
            if kind in _ULOG_DEFINITIONS_END:
                break
            if kind not in _ULOG_DEFINITION_TYPES and (kind == 0 or size == 0 or size > 10_000):
                break  # damaged here (pyulog's own test): pyulog steps over it byte by byte
            body = fh.read(size)
            if len(body) < size:
                break
            if kind == ord("F"):
                try:  # pyulog decodes ignoring bad bytes (its disable_str_exceptions, on by default)
                    fmt = ULog.MessageFormat(body.decode("utf-8", "ignore").encode("utf-8"), None)
                except (IndexError, ValueError, KeyError, OverflowError, UnicodeDecodeError):
                    pass  # pyulog skips a format it cannot parse the same way
                else:
                    formats[fmt.name] = fmt.fields
                    offsets[fmt.name] = offset
            offset += 3 + size
    sizes = ulog_format_sizes(formats)
    for name in formats:
        problem = ulog_format_problem(name, sizes[name])
        if problem:
            raise DatasetError(f"{source}: byte {offsets[name]}: {_damaged_formats(problem)}")
    return len(formats)


_GUARDED_ULOG: dict = {}


def _guarded_ulog(ULog):
    """pyulog's ``ULog`` with guards inside its reading: every subscription (``A`` message, flattened anew each
    time) is sized from the formats first (:func:`ulog_format_sizes`) and refused beyond the per-message bounds
    or once all subscriptions together pass :data:`ULOG_MAX_SUBSCRIBED_FIELDS`; and the ``deadline`` (a
    ``time.monotonic`` value) is checked at data messages and at every damaged byte pyulog steps over. Either
    raises :class:`_Stuck` out of pyulog (whose own error handling catches only its parsing errors)."""
    if "class" in _GUARDED_ULOG:
        return _GUARDED_ULOG["class"]

    class GuardedULog(ULog):
        def __init__(self, *args, deadline=None, **kwargs):
            self._deadline = deadline
            self._ticks = 0
            self._fields_subscribed = 0
            self._sizes = None
            owner = self

            class AddLogged(ULog._MessageAddLogged):
                def __init__(self, data, header, message_formats):
                    owner._admit(data, message_formats)
                    super().__init__(data, header, message_formats)

            class MessageData(ULog._MessageData):
                def initialize(self, data, header, subscriptions, ulog_object):
                    owner._tick()
                    return super().initialize(data, header, subscriptions, ulog_object)

            self._MessageAddLogged = AddLogged  # pyulog makes these through self: the guarded ones are used
            self._MessageData = MessageData
            super().__init__(*args, **kwargs)

        def _tick(self):
            self._ticks += 1
            if self._deadline is not None and self._ticks % 1024 == 0 and time.monotonic() > self._deadline:
                raise _Stuck("slow")

        def _check_packet_corruption(self, header):
            self._tick()  # a damaged stretch is stepped over byte by byte, each step reading up to 64 kB
            return super()._check_packet_corruption(header)

        def _admit(self, data, message_formats):
            if self._sizes is None:
                self._sizes = ulog_format_sizes({k: f.fields for k, f in message_formats.items()})
            name = ULog.parse_string(data[3:])
            found = self._sizes.get(name)
            if found is None:
                return  # not a format: pyulog refuses the subscription itself (a KeyError it catches)
            problem = ulog_format_problem(name, found)
            if problem:
                raise _Stuck("bomb", _damaged_formats(problem))
            self._fields_subscribed += found[0]
            if self._fields_subscribed > ULOG_MAX_SUBSCRIBED_FIELDS:
                raise _Stuck(
                    "bomb",
                    _damaged_formats(
                        f"its subscriptions flatten into more than {ULOG_MAX_SUBSCRIBED_FIELDS:,} fields "
                        f"(the last one, {name!r}: {found[0]:,})"
                    ),
                )

    _GUARDED_ULOG["class"] = GuardedULog
    return GuardedULog


def _ulog_position(ulog, source, metadata, notes):
    """``lat, lon, alt_m`` channels from the first ``vehicle_gps_position`` / ``sensor_gps`` with a 3D fix (and the
    UTC date into ``metadata['date']``); {} when the log has none."""
    for topic in ("vehicle_gps_position", "sensor_gps"):
        found = sorted((d for d in ulog.data_list if d.name == topic), key=lambda d: d.multi_id)
        if found:
            break
    else:
        return {}
    data = found[0].data
    if "timestamp" not in data:
        return {}
    t = np.asarray(data["timestamp"], dtype=float) * 1e-6
    if "latitude_deg" in data:
        lat, lon = (np.asarray(data[k], dtype=float) for k in ("latitude_deg", "longitude_deg"))
        alt = np.asarray(data.get("altitude_msl_m", np.zeros(t.size)), dtype=float)
    elif "lat" in data and "lon" in data:
        lat, lon = (np.asarray(data[k], dtype=float) * 1e-7 for k in ("lat", "lon"))
        alt = np.asarray(data.get("alt", np.zeros(t.size)), dtype=float) * 1e-3
    else:
        return {}
    fix = np.asarray(data.get("fix_type", np.full(t.size, 3)), dtype=float) >= 3
    fix &= (lat != 0) | (lon != 0)
    if not fix.any():
        return {}
    utc = np.asarray(data.get("time_utc_usec", np.zeros(t.size)), dtype=float)[fix]
    if np.any(utc > 0):
        metadata["date"] = str(np.datetime64(int(utc[utc > 0][0]), "us").astype("datetime64[D]"))
    out = _position(source, t[fix], lat[fix], lon[fix], alt[fix], topic, notes)
    if out:
        metadata["position"] = f"{topic} 3D fixes (lat, lon deg; alt_m above mean sea level)"
    return out


def _ulog_current(ulog, source, notes):
    """``{"current_A": (t, A)}`` from the first ``battery_status`` (``current_a``), or None."""
    bats = sorted((d for d in ulog.data_list if d.name == "battery_status"), key=lambda d: d.multi_id)
    if not bats or "current_a" not in bats[0].data or "timestamp" not in bats[0].data:
        return None
    data = bats[0].data
    t = np.asarray(data["timestamp"], dtype=float) * 1e-6
    amps = np.asarray(data["current_a"], dtype=float)
    good = ~bad_values(amps) & ~bad_values(t) & (amps >= 0)  # PX4 writes -1 when the current is not measured
    if good.sum() < 2:
        return None
    return {"current_A": _strictly_increasing(t[good], amps[good], source, "battery_status", notes)}


def _require_fields(data, names, source, what):
    """Refuse a ULog topic that lacks one of the fields magcal reads (a KeyError otherwise)."""
    missing = [n for n in names if n not in data]
    if missing:
        raise DatasetError(
            f"{source}: {what} has no field {', '.join(missing)} (its fields: {', '.join(sorted(data)[:12])}); "
            "this is not the PX4 message magcal reads: the log is damaged or from an unknown firmware"
        )


def _ulog_attitude(ulog, source, notes):
    """``(t, Rotation)`` of the ``vehicle_attitude`` quaternions (body FRD to NED), or None."""
    att = [d for d in ulog.data_list if d.name == "vehicle_attitude"]
    if not att:
        return None
    data = att[0].data
    _require_fields(data, ["timestamp"] + [f"q[{k}]" for k in range(4)], source, "vehicle_attitude")
    ta = np.asarray(data["timestamp"], dtype=float) * 1e-6
    q = np.column_stack([data[f"q[{k}]"] for k in range(4)]).astype(float)
    ta, q = _drop_bad(source, "vehicle_attitude", ta, q, notes=notes)
    ta, q = _strictly_increasing(ta, q, source, "vehicle_attitude", notes)
    ok = np.linalg.norm(q, axis=1) > 0.5
    if not ok.any():
        return None
    return ta[ok], Rotation.from_quat(np.column_stack([q[ok, 1:], q[ok, :1]]))


#: ``sensor_combined``'s relative time stamp meaning "no sample" (PX4's RELATIVE_TIMESTAMP_INVALID).
_RELATIVE_TIMESTAMP_INVALID = 2_147_483_647


def _ulog_calibrated_field(ulog, source, notes):
    """A ULog without ``sensor_mag``: the field the vehicle computed with its calibration, from
    ``vehicle_magnetometer`` or (older PX4) ``sensor_combined.magnetometer_ga``, in gauss, body frame."""
    for topic in ("vehicle_magnetometer", "sensor_combined"):
        found = [d for d in ulog.data_list if d.name == topic and "magnetometer_ga[0]" in d.data]
        if found:
            break
    else:
        raise DatasetError(
            f"{source}: no sensor_mag messages (magnetometer data) in this ULog, nor "
            "vehicle_magnetometer or sensor_combined; set SDLOG_PROFILE to log sensor data and record "
            "again"
        )
    data = found[0].data
    _require_fields(data, ["timestamp"], source, topic)
    t = np.asarray(data["timestamp"], dtype=np.int64)
    if "magnetometer_timestamp_relative" in data:
        rel = np.asarray(data["magnetometer_timestamp_relative"], dtype=np.int64)
        ok = rel != _RELATIVE_TIMESTAMP_INVALID
        t = np.where(ok, t + rel, t)
    else:
        ok = np.ones(t.size, dtype=bool)
    xyz = np.column_stack([data[f"magnetometer_ga[{k}]"] for k in range(3)]).astype(float) * NT_PER_GAUSS
    t, xyz = t[ok], xyz[ok]
    t, xyz = _drop_bad(source, topic, t, xyz, notes=notes)
    t = t.astype(np.int64)
    first = np.unique(t, return_index=True)[1]  # sensor_combined repeats a magnetometer sample at each IMU update
    t_s, xyz = _strictly_increasing(t[first] * 1e-6, xyz[first], source, topic, notes)
    changed = np.concatenate([[True], np.any(np.diff(xyz, axis=0) != 0, axis=1)])
    t_s, xyz = t_s[changed], xyz[changed]  # sensor_combined repeats the last magnetometer sample between updates
    notes.append(
        _note(
            f"{source}: no raw sensor_mag in this log; read the field the vehicle had already calibrated with "
            f"its CAL_MAG parameters ({topic}). A calibration of it corrects what those parameters left, and "
            "its parameters do not replace them"
        )
    )
    metadata = {
        "log_format": "PX4 ULog",
        "log_magnetometers": topic,
        "log_field": f"calibrated by the vehicle ({topic}, body frame)",
    }
    position = _ulog_position(ulog, source, metadata, notes)
    position.update(_ulog_imu(ulog, source, metadata, notes))
    return _build(source, [(t_s, xyz)], None, _ulog_attitude(ulog, source, notes), position, metadata, notes=notes)
