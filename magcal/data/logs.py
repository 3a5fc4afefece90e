"""Flight-controller logs in: ArduPilot DataFlash ``.bin`` and PX4 ``.ulg`` as a :class:`~magcal.data.dataset.Dataset`.

ArduPilot (read with pymavlink's ``DFReader``)
    ``MAG`` messages (one per compass: the instance field ``I``, or the older names ``MAG2``, ``MAG3``) hold the
    field in milligauss in the body frame *after* the compass calibration of the time
    (``AP_Compass_Backend::correct_field``: ``M (SCALE (raw + OFS)) + motor``), with the offsets (``OfsX..``) and
    the motor offsets (``MOX..``) logged beside it. To calibrate, magcal needs the raw field: by default it undoes
    that correction with the logged offsets and the ``COMPASS_DIA*``, ``COMPASS_ODI*``, ``COMPASS_SCALE*``
    parameters (``PARM`` messages) in force at each sample (``undo_calibration=False`` keeps the logged field).
    Temperature: the ``IMU`` message's ``T`` (degC, first IMU), interpolated to the compass times. Attitude:
    ``ATT`` roll, pitch, yaw (deg), as the quaternion channel (body to north-east-down) and as extra columns
    ``att_roll_deg``, ``att_pitch_deg``, ``att_yaw_deg``. Current: the first battery's ``BAT`` ``Curr`` (A) as the
    extra column ``current_A`` (a vector calibration fits the field per ampere, ``COMPASS_MOT``'s quantity).
PX4 (read with pyulog)
    ``sensor_mag`` (one instance per magnetometer) holds the raw field in gauss in the sensor's frame before the
    ``CAL_MAGn_*`` calibration, with its ``temperature`` (degC; NaN when the part has none). Attitude: the
    ``vehicle_attitude`` quaternion ``q`` (body FRD to NED), interpolated to the magnetometer times. Current: the
    first ``battery_status``'s ``current_a`` (A) as ``current_A``.

Several magnetometers become magcal sensors 1, 2, 3 in instance order; their samples are paired by time (the
nearest sample within half the first one's sample interval; unpaired samples are dropped with a warning). Note that
the attitude is the vehicle's: a magnetometer mounted rotated (``COMPASS_ORIENT``, ``CAL_MAGn_ROT``) reads in its
own frame (PX4) or is already rotated to the body frame (ArduPilot).
"""

from __future__ import annotations

import os
import warnings

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from magcal.core.errors import DataWarning
from magcal.core.notes import say
from magcal.data.dataset import Dataset, DatasetError

#: File name endings read as flight-controller logs, and the reader of each.
LOG_EXTENSIONS = (".bin", ".ulg")

NT_PER_MILLIGAUSS = 100.0
NT_PER_GAUSS = 1.0e5

#: ArduPilot applies COMPASS_SCALE only inside these bounds (``Compass::have_scale_factor``).
ARDUPILOT_SCALE_RANGE = (1.0 / 1.5, 1.5)

MAX_SENSORS = 4


def is_log(path) -> bool:
    """True if ``path`` names a flight-controller log magcal reads (by its ending, case-insensitive)."""
    return isinstance(path, (str, os.PathLike)) and os.fspath(path).lower().endswith(LOG_EXTENSIONS)


def read_log(path, sensors=None, name=None, undo_calibration=True, min_samples=1, notes=None) -> Dataset:
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
    notes : list, optional
        Where the reader's notes go (:class:`~magcal.core.notes.Note`: magnetometers left out, samples dropped...):
        given, they are appended to it; None (default), each is raised as a :class:`DataWarning`.

    Raises
    ------
    DatasetError
        Missing file, a log the reader cannot parse, no magnetometer messages, too few samples.
    """
    source = str(name or os.fspath(path))
    path = os.fspath(path)
    if os.path.isdir(path):
        raise DatasetError(f"{source}: is a directory, not a log file")
    if not os.path.exists(path):
        raise DatasetError(f"{source}: no such file; check the path")
    if path.lower().endswith(".ulg"):
        ds = read_ulog(path, sensors=sensors, name=source, notes=notes)
    elif path.lower().endswith(".bin"):
        ds = read_dataflash(path, sensors=sensors, name=source, undo_calibration=undo_calibration, notes=notes)
    else:
        raise DatasetError(f"{source}: not a flight-controller log (expected {', '.join(LOG_EXTENSIONS)})")
    if ds.n_samples < int(min_samples):
        raise DatasetError(
            f"{source}: {ds.n_samples} magnetometer sample(s), fewer than the {int(min_samples)} "
            "needed; record more attitudes"
        )
    return ds


# -- pairing several magnetometers and interpolating channels ------------------------------------------------------
def _strictly_increasing(t, values, source, what, notes=None):
    """Sort by time and drop repeated time stamps (with a warning): the dataset's times must increase strictly."""
    order = np.argsort(t, kind="stable")
    t = t[order]
    values = values[order]
    keep = np.concatenate([[True], np.diff(t) > 0])
    if not keep.all():
        say(
            notes,
            f"{source}: {what}: {int((~keep).sum())} sample(s) repeat a time stamp and are dropped",
            DataWarning,
            "read",
            stacklevel=4,
        )
    return t[keep], values[keep]


def pair_by_time(series, source, notes=None):
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
        say(
            notes,
            f"{source}: {int((~keep).sum())} of {t0.size} samples of the first magnetometer have no sample "
            "of every other one within half a sample interval; they are dropped",
            DataWarning,
            "read",
            stacklevel=4,
        )
    values = [v0[keep]] + [v[p[keep]] for (_, v), p in zip(series[1:], picks)]
    return t0[keep], values


def _interp(t, t_src, v_src):
    """Linear interpolation of a channel onto times ``t`` (held constant beyond its ends)."""
    return np.interp(t, t_src, v_src)


def _interp_attitude(t, t_src, rotations):
    """Attitude quaternions (N, 4) ``w, x, y, z`` at times ``t`` by spherical interpolation (held at the ends)."""
    if t_src.size == 1:
        q = np.repeat(rotations.as_quat()[:1], t.size, axis=0)
    else:
        q = Slerp(t_src, rotations)(np.clip(t, t_src[0], t_src[-1])).as_quat()
    return np.column_stack([q[:, 3], q[:, :3]])


def _build(source, series, temperature=None, attitude=None, extra=None, metadata=None, notes=None):
    """The dataset from per-magnetometer (t, nT) series and optional (t, values) channels."""
    t, values = pair_by_time(series, source, notes)
    if t.size == 0:
        raise DatasetError(f"{source}: no magnetometer samples left after pairing the magnetometers by time")
    kwargs = {}
    if temperature is not None:
        kwargs["temperature_C"] = _interp(t, *temperature)
    if attitude is not None:
        kwargs["attitude_wxyz"] = _interp_attitude(t, *attitude)
    extras = {k: _interp(t, ts, v) for k, (ts, v) in (extra or {}).items()}
    return Dataset(
        readings_nT=np.stack(values), time_s=t, extra=extras, metadata=dict(metadata or {}), source=source, **kwargs
    )


def _alive(series, labels, source, notes=None):
    """Indices of the magnetometers to keep: those whose samples are not all one vector (zero: no compass fitted,
    or it failed), the others left out with a warning."""
    alive = []
    for k, ((_, v), label) in enumerate(zip(series, labels)):
        if v.shape[0] > 1 and np.all(v == v[0]):
            say(
                notes,
                f"{source}: {label} reads the same vector ({', '.join(f'{x:g}' for x in v[0])}) nT on all "
                f"{v.shape[0]} samples (zero: no compass fitted, or it failed); it is left out",
                DataWarning,
                "read",
                stacklevel=4,
            )
            continue
        alive.append(k)
    if not alive:
        raise DatasetError(
            f"{source}: every magnetometer in the log reads one constant vector ({', '.join(labels)}); "
            "there is nothing to calibrate: check that the compass was detected and enabled"
        )
    return alive


def _select(instances, sensors, source, what, notes=None):
    """The instances chosen by ``sensors`` (0-based positions), at most :data:`MAX_SENSORS`."""
    if sensors is None:
        if len(instances) > MAX_SENSORS:
            say(
                notes,
                f"{source}: {len(instances)} magnetometers; the first {MAX_SENSORS} are read (choose with sensors=)",
                DataWarning,
                "read",
                stacklevel=4,
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


def _ardupilot_matrix(params, index):
    """``SCALE * M`` of ArduPilot compass ``index`` from the parameter values (DIA zero means identity)."""
    tag = _compass_tag(index)
    dia = np.array([params.get(f"COMPASS_DIA{tag}_{a}", 1.0) for a in "XYZ"], dtype=float)
    odi = np.array([params.get(f"COMPASS_ODI{tag}_{a}", 0.0) for a in "XYZ"], dtype=float)
    if not np.any(dia):
        dia = np.ones(3)
    m = np.array([[dia[0], odi[0], odi[1]], [odi[0], dia[1], odi[2]], [odi[1], odi[2], dia[2]]])
    scale = float(params.get(f"COMPASS_SCALE{tag}", 0.0))
    if ARDUPILOT_SCALE_RANGE[0] <= scale <= ARDUPILOT_SCALE_RANGE[1]:
        m = m * scale
    return m


def read_dataflash(path, sensors=None, name=None, undo_calibration=True, notes=None) -> Dataset:
    """Read an ArduPilot DataFlash ``.bin`` log (see the module docstring). Readings in nT, body frame."""
    source = str(name or path)
    try:
        from pymavlink import DFReader
    except ImportError:
        raise DatasetError(
            f'{source}: reading ArduPilot logs needs pymavlink: pip install "magcal-workbench[instruments]"'
        ) from None
    try:
        with warnings.catch_warnings(), open(os.devnull, "w") as devnull:
            warnings.simplefilter("ignore")
            import contextlib

            with contextlib.redirect_stdout(devnull):  # pymavlink prints notes about the indexer
                log = DFReader.DFReader_binary(path, zero_time_base=True)
    except Exception as exc:  # a damaged or foreign file: any failure of the parser is the file's fault
        raise DatasetError(f"{source}: not a readable ArduPilot DataFlash log ({type(exc).__name__}: {exc})") from None
    params = {}
    mags: dict = {}  # (name, instance) -> list of rows (t, x, y, z) nT
    imu_t, imu_temp = [], []
    att_t, att = [], []
    bat_t, bat = [], []
    seen_types = set()
    unhealthy: dict = {}  # compass -> samples the firmware marked unhealthy (left out)
    try:
        while True:
            m = log.recv_match(type=["PARM", "MAG", "MAG2", "MAG3", "IMU", "ATT", "BAT"])
            if m is None:
                break
            kind = m.get_type()
            seen_types.add(kind)
            if kind == "PARM":
                params[str(m.Name)] = float(m.Value)
                continue
            t_us = getattr(m, "TimeUS", None)
            if t_us is None:
                t_us = getattr(m, "TimeMS", 0) * 1000.0
            t = float(t_us) * 1e-6
            if kind.startswith("MAG"):
                instance = int(getattr(m, "I", 0) or 0) if kind == "MAG" else int(kind[3:]) - 1
                if getattr(m, "Health", 1) == 0:
                    unhealthy[instance] = unhealthy.get(instance, 0) + 1
                    continue
                field_mG = np.array([m.MagX, m.MagY, m.MagZ], dtype=float)
                if undo_calibration:
                    ofs = np.array([getattr(m, f"Ofs{a}", 0.0) for a in "XYZ"], dtype=float)
                    mot = np.array([getattr(m, f"MO{a}", 0.0) for a in "XYZ"], dtype=float)
                    field_mG = np.linalg.solve(_ardupilot_matrix(params, instance), field_mG - mot) - ofs
                mags.setdefault(instance, []).append((t, *(field_mG * NT_PER_MILLIGAUSS)))
            elif kind == "IMU":
                if int(getattr(m, "I", 0) or 0) == 0 and hasattr(m, "T"):
                    imu_t.append(t)
                    imu_temp.append(float(m.T))
            elif kind == "ATT":
                att_t.append(t)
                att.append((float(m.Roll), float(m.Pitch), float(m.Yaw)))
            elif kind == "BAT":
                if int(getattr(m, "Inst", getattr(m, "Instance", 0)) or 0) == 0 and hasattr(m, "Curr"):
                    bat_t.append(t)
                    bat.append(float(m.Curr))
    except Exception as exc:
        raise DatasetError(f"{source}: the DataFlash log is damaged ({type(exc).__name__}: {exc})") from None
    for k, count in sorted(unhealthy.items()):
        say(
            notes,
            f"{source}: compass {k + 1}: {count} sample(s) the firmware marked unhealthy (Health 0) are left out",
            DataWarning,
            "read",
            stacklevel=3,
        )
    if not mags:
        raise DatasetError(
            f"{source}: no MAG messages (compass data); the log holds "
            f"{', '.join(sorted(seen_types)) or 'none of MAG, IMU, ATT, PARM'}. Enable compass logging "
            "(LOG_BITMASK) and record again"
        )
    instances = _select(sorted(mags), sensors, source, "MAG messages", notes)
    series = []
    for k in instances:
        rows = np.array(mags[k], dtype=np.float64)
        series.append(_strictly_increasing(rows[:, 0], rows[:, 1:], source, f"compass {k + 1}", notes))
    labels = [f"compass {k + 1}" for k in instances]
    keep = _alive(series, labels, source, notes)
    series, labels = [series[i] for i in keep], [labels[i] for i in keep]
    temperature = attitude = None
    extra = {}
    if imu_t:
        temperature = _strictly_increasing(np.asarray(imu_t), np.asarray(imu_temp), source, "IMU temperature", notes)
    if att_t:
        ta, angles = _strictly_increasing(np.asarray(att_t), np.asarray(att), source, "ATT", notes)
        attitude = (ta, Rotation.from_euler("ZYX", angles[:, ::-1], degrees=True))
        yaw = np.degrees(np.unwrap(np.radians(angles[:, 2])))
        extra = {"att_roll_deg": (ta, angles[:, 0]), "att_pitch_deg": (ta, angles[:, 1]), "att_yaw_deg": (ta, yaw)}
    if bat_t:
        extra["current_A"] = _strictly_increasing(np.asarray(bat_t), np.asarray(bat), source, "BAT")
    metadata = {
        "log_format": "ArduPilot DataFlash",
        "log_magnetometers": ", ".join(labels),
        "log_field": "raw (logged calibration undone)" if undo_calibration else "as logged (calibrated)",
    }
    ds = _build(source, series, temperature, attitude, extra, metadata, notes)
    if "att_yaw_deg" in ds.extra:
        ds.extra["att_yaw_deg"] = (ds.extra["att_yaw_deg"] + 180.0) % 360.0 - 180.0
    return ds


# -- PX4 ULog --------------------------------------------------------------------------------------------------------
def read_ulog(path, sensors=None, name=None, notes=None) -> Dataset:
    """Read a PX4 ``.ulg`` log (see the module docstring). Readings in nT, each magnetometer's own frame."""
    source = str(name or path)
    try:
        from pyulog import ULog
    except ImportError:
        raise DatasetError(
            f'{source}: reading PX4 logs needs pyulog: pip install "magcal-workbench[instruments]"'
        ) from None
    try:
        ulog = ULog(
            path, ["sensor_mag", "vehicle_attitude", "vehicle_magnetometer", "sensor_combined", "battery_status"]
        )
    except Exception as exc:  # a damaged or foreign file
        raise DatasetError(f"{source}: not a readable PX4 ULog file ({type(exc).__name__}: {exc})") from None
    mags = sorted((d for d in ulog.data_list if d.name == "sensor_mag"), key=lambda d: d.multi_id)
    if not mags:
        return _ulog_calibrated_field(ulog, source, notes)
    chosen = _select(mags, sensors, source, "sensor_mag instances", notes)
    series = []
    temps = []
    for d in chosen:
        data = d.data
        t_key = "timestamp_sample" if "timestamp_sample" in data else "timestamp"
        t = np.asarray(data[t_key], dtype=float) * 1e-6
        xyz = np.column_stack([data[a] for a in "xyz"]).astype(float) * NT_PER_GAUSS
        temp = np.asarray(data.get("temperature", np.full(t.size, np.nan)), dtype=float)
        t, both = _strictly_increasing(t, np.column_stack([xyz, temp]), source, f"sensor_mag {d.multi_id}", notes)
        good = np.isfinite(both[:, :3]).all(axis=1)
        if not good.all():
            say(
                notes,
                f"{source}: sensor_mag {d.multi_id}: {int((~good).sum())} non-finite sample(s) dropped",
                DataWarning,
                "read",
                stacklevel=3,
            )
        series.append((t[good], both[good, :3]))
        temps.append((t[good], both[good, 3]))
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
    return _build(source, series, temperature, attitude, _ulog_current(ulog, source), metadata, notes)


def _ulog_current(ulog, source):
    """``{"current_A": (t, A)}`` from the first ``battery_status`` (``current_a``), or None."""
    bats = sorted((d for d in ulog.data_list if d.name == "battery_status"), key=lambda d: d.multi_id)
    if not bats or "current_a" not in bats[0].data:
        return None
    data = bats[0].data
    t = np.asarray(data["timestamp"], dtype=float) * 1e-6
    amps = np.asarray(data["current_a"], dtype=float)
    good = np.isfinite(amps) & (amps >= 0)  # PX4 writes -1 when the current is not measured
    if good.sum() < 2:
        return None
    return {"current_A": _strictly_increasing(t[good], amps[good], source, "battery_status")}


def _ulog_attitude(ulog, source, notes=None):
    """``(t, Rotation)`` of the ``vehicle_attitude`` quaternions (body FRD to NED), or None."""
    att = [d for d in ulog.data_list if d.name == "vehicle_attitude"]
    if not att:
        return None
    data = att[0].data
    ta = np.asarray(data["timestamp"], dtype=float) * 1e-6
    q = np.column_stack([data[f"q[{k}]"] for k in range(4)]).astype(float)
    ta, q = _strictly_increasing(ta, q, source, "vehicle_attitude", notes)
    ok = np.isfinite(q).all(axis=1) & (np.linalg.norm(q, axis=1) > 0.5)
    if not ok.any():
        return None
    return ta[ok], Rotation.from_quat(np.column_stack([q[ok, 1:], q[ok, :1]]))


#: ``sensor_combined``'s relative time stamp meaning "no sample" (PX4's RELATIVE_TIMESTAMP_INVALID).
_RELATIVE_TIMESTAMP_INVALID = 2_147_483_647


def _ulog_calibrated_field(ulog, source, notes=None):
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
    t = np.asarray(data["timestamp"], dtype=np.int64)
    if "magnetometer_timestamp_relative" in data:
        rel = np.asarray(data["magnetometer_timestamp_relative"], dtype=np.int64)
        ok = rel != _RELATIVE_TIMESTAMP_INVALID
        t = np.where(ok, t + rel, t)
    else:
        ok = np.ones(t.size, dtype=bool)
    xyz = np.column_stack([data[f"magnetometer_ga[{k}]"] for k in range(3)]).astype(float) * NT_PER_GAUSS
    ok &= np.isfinite(xyz).all(axis=1)
    t, xyz = t[ok], xyz[ok]
    first = np.unique(t, return_index=True)[1]  # sensor_combined repeats a magnetometer sample at each IMU update
    t_s, xyz = _strictly_increasing(t[first] * 1e-6, xyz[first], source, topic, notes)
    changed = np.concatenate([[True], np.any(np.diff(xyz, axis=0) != 0, axis=1)])
    t_s, xyz = t_s[changed], xyz[changed]  # sensor_combined repeats the last magnetometer sample between updates
    say(
        notes,
        f"{source}: no raw sensor_mag in this log; read the field the vehicle had already calibrated with "
        f"its CAL_MAG parameters ({topic}). A calibration of it corrects what those parameters left, and "
        "its parameters do not replace them",
        DataWarning,
        "read",
        stacklevel=3,
    )
    metadata = {
        "log_format": "PX4 ULog",
        "log_magnetometers": topic,
        "log_field": f"calibrated by the vehicle ({topic}, body frame)",
    }
    return _build(source, [(t_s, xyz)], None, _ulog_attitude(ulog, source, notes), None, metadata, notes)
