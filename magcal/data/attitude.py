"""The vehicle's attitude (body frame -> north-east-down world frame) from a dataset's columns.

Two forms are read, the first present wins:

* the quaternion channel ``qw, qx, qy, qz`` (:attr:`magcal.data.dataset.Dataset.attitude_wxyz`, scalar first),
  rotating body-frame vectors into the world frame; the flight-log readers (:mod:`magcal.data.logs`) fill it from
  ArduPilot ``ATT`` and PX4 ``vehicle_attitude`` (body front-right-down -> NED);
* Euler angles ``roll_deg, pitch_deg, yaw_deg`` (degrees), in the aerospace convention: the body frame is
  x forward, y right, z down; the world frame is north-east-down; the rotation body -> world is
  ``R = Rz(yaw) Ry(pitch) Rx(roll)`` (yaw about down, then pitch, then roll; ZYX intrinsic), so a vector ``v`` in
  the body frame is ``R v`` in NED and the field the body sees is ``B_body = R^T B_ned``.

For a vector calibration the world frame must be NED (the reference field :mod:`magcal.checks.reference` gives is
north, east, down).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from magcal.data.dataset import Dataset, DatasetError

#: The Euler-angle columns (degrees, aerospace ZYX, body -> NED).
EULER_COLUMNS = ("roll_deg", "pitch_deg", "yaw_deg")


def euler_to_wxyz(roll_deg, pitch_deg, yaw_deg) -> np.ndarray:
    """Quaternions ``(N, 4)`` ``w, x, y, z`` (body -> NED) from aerospace roll, pitch, yaw in degrees."""
    angles = np.column_stack([np.ravel(yaw_deg), np.ravel(pitch_deg), np.ravel(roll_deg)])
    q = Rotation.from_euler("ZYX", angles, degrees=True).as_quat()  # x, y, z, w
    return np.column_stack([q[:, 3], q[:, :3]])


def wxyz_rotation(q_wxyz) -> Rotation:
    """A :class:`~scipy.spatial.transform.Rotation` from ``(N, 4)`` quaternions ``w, x, y, z``."""
    q = np.asarray(q_wxyz, dtype=float)
    return Rotation.from_quat(np.column_stack([q[:, 1:], q[:, :1]]))


def attitude_source(dataset: Dataset) -> str | None:
    """``"quaternion"``, ``"euler"`` or None: which attitude the dataset holds."""
    if dataset.attitude_wxyz is not None:
        return "quaternion"
    if all(c in dataset.extra for c in EULER_COLUMNS):
        return "euler"
    return None


def attitude(dataset: Dataset) -> Rotation | None:
    """The body -> NED attitude of every sample, or None when the dataset has none.

    The strict form: every sample must have one. :func:`attitude_rows` takes a record whose first samples (or a
    gap) have none.

    Raises
    ------
    DatasetError
        Euler columns that are not numbers or not finite, quaternions that are not finite or zero, or only some
        of the Euler columns present.
    """
    found = attitude_rows(dataset)
    if found is None:
        return None
    rotation, have = found
    if not have.all():
        where = dataset.source or "data"
        bad = int(np.argmin(have))
        if attitude_source(dataset) == "euler":
            c = next(c for c in EULER_COLUMNS if not np.isfinite(float(dataset.extra[c][bad])))
            raise DatasetError(
                f"{where}: column {c} must hold finite angles in degrees (data row {bad + 1} has none; "
                f"{int(np.count_nonzero(~have))} rows lack an attitude)"
            )
        raise DatasetError(
            f"{where}: the quaternion qw, qx, qy, qz of data row {bad + 1} is not a finite, non-zero quaternion "
            f"({int(np.count_nonzero(~have))} rows lack an attitude)"
        )
    return rotation


def attitude_rows(dataset: Dataset) -> tuple[Rotation, np.ndarray] | None:
    """The body -> NED attitude of every sample and which samples have one, or None when the dataset has none.

    A sample has no attitude when its Euler angles are not all finite (a live recording's samples before its
    first ``ATTITUDE`` message, a gap in a log: NaN) or its quaternion is not finite or is zero.

    Returns
    -------
    rotation : scipy.spatial.transform.Rotation
        One per sample (N); the identity where a sample has none (so that arrays stay one row per sample).
    have : numpy.ndarray of bool, shape (N,)
        True where the sample has an attitude.

    Raises
    ------
    DatasetError
        Euler columns that are not numbers, or only some of them present.
    """
    kind = attitude_source(dataset)
    where = dataset.source or "data"
    if kind == "quaternion":
        q = np.array(dataset.attitude_wxyz, dtype=float)
    elif kind == "euler":
        values = []
        for c in EULER_COLUMNS:
            v = np.asarray(dataset.extra[c])
            if v.dtype.kind not in "fiu":
                raise DatasetError(f"{where}: column {c} must hold angles in degrees (numbers; empty or nan: none)")
            values.append(v.astype(float))
        have = np.isfinite(values[0]) & np.isfinite(values[1]) & np.isfinite(values[2])
        q = np.full((len(have), 4), np.nan)
        if have.any():
            q[have] = euler_to_wxyz(*(v[have] for v in values))
    else:
        present = [c for c in EULER_COLUMNS if c in dataset.extra]
        if present:
            raise DatasetError(
                f"{where}: attitude needs all three columns {', '.join(EULER_COLUMNS)} (degrees); found only "
                f"{', '.join(present)}"
            )
        return None
    q, have = filled_wxyz(q)
    return wxyz_rotation(q), have


def attitude_present(dataset: Dataset) -> np.ndarray | None:
    """Which samples have an attitude (bool, shape (N,)), as :func:`attitude_rows` says, without turning the
    angles into rotations; None when the dataset has no attitude."""
    kind = attitude_source(dataset)
    if kind == "quaternion":
        return filled_wxyz(dataset.attitude_wxyz)[1]
    if kind == "euler":
        try:
            values = [np.asarray(dataset.extra[c], dtype=float) for c in EULER_COLUMNS]
        except (TypeError, ValueError):
            found = attitude_rows(dataset)  # raises the message naming the column
            return None if found is None else found[1]
        return np.isfinite(values[0]) & np.isfinite(values[1]) & np.isfinite(values[2])
    return None


def filled_wxyz(q_wxyz) -> tuple[np.ndarray, np.ndarray]:
    """``(q, have)``: the quaternions ``(N, 4)`` ``w, x, y, z`` (a copy) with the identity where a row is not a
    finite, non-zero quaternion (a sample without attitude), and ``have`` (N,) bool, True where the row is one."""
    q = np.array(q_wxyz, dtype=float).reshape(-1, 4)
    have = np.all(np.isfinite(q), axis=1)
    have[have] = np.sum(q[have] ** 2, axis=1) > 0
    q[~have] = (1.0, 0.0, 0.0, 0.0)
    return q, have


def with_attitude(dataset: Dataset) -> Dataset:
    """The dataset with its Euler columns (if any) turned into the quaternion channel (unchanged otherwise)."""
    if attitude_source(dataset) != "euler":
        return dataset
    found = attitude_rows(dataset)
    assert found is not None  # Euler columns give one
    rotation, have = found
    q = rotation.as_quat()
    q[~have] = np.nan  # a sample without attitude keeps none
    return dataset.replace(attitude_wxyz=np.column_stack([q[:, 3], q[:, :3]]))


#: Gyro columns read for the turn rate, with the unit each implies (None: :func:`gyro_units`). The first are what
#: :mod:`magcal.data.live` gives a stream's gyro (:mod:`magcal.data.lineformats`).
GYRO_COLUMNS = (
    (("gyro_x_dps", "gyro_y_dps", "gyro_z_dps"), "deg/s"),
    (("gx_dps", "gy_dps", "gz_dps"), "deg/s"),
    (("gx_rad_s", "gy_rad_s", "gz_rad_s"), "rad/s"),
    (("gx", "gy", "gz"), None),
    (("gyro_x", "gyro_y", "gyro_z"), None),
    (("wx", "wy", "wz"), None),
)


def attitude_quaternions(dataset: Dataset) -> np.ndarray | None:
    """The attitude as ``(N, 4)`` quaternions ``w, x, y, z`` (body -> NED), or None, where some samples may lack
    one: the quaternion channel, else the Euler columns (:data:`EULER_COLUMNS`), a row of NaN for a sample whose
    angles are not finite (a stream's samples before its first attitude message). :func:`attitude` is the strict
    form a calibration needs; this one is for looking at the motion."""
    if dataset.attitude_wxyz is not None:
        return np.asarray(dataset.attitude_wxyz, float)
    if not all(c in dataset.extra for c in EULER_COLUMNS):
        return None
    try:
        roll, pitch, yaw = (np.asarray(dataset.extra[c], float) for c in EULER_COLUMNS)
    except (TypeError, ValueError):  # text in an angle column: attitude() names it when a fit needs it
        return None
    out = np.full((len(roll), 4), np.nan)
    ok = np.isfinite(roll) & np.isfinite(pitch) & np.isfinite(yaw)
    if ok.any():
        out[ok] = euler_to_wxyz(roll[ok], pitch[ok], yaw[ok])
    return out


def gyro_units(dataset: Dataset) -> str:
    """The unit of the dataset's unmarked gyro columns: the file's ``# gyro_units:`` line (``deg/s`` or
    ``rad/s``), else ``deg/s`` (what most sensor sketches print)."""
    text = str(dataset.metadata.get("gyro_units", "")).strip().lower().replace(" ", "")
    return "rad/s" if text in ("rad/s", "rads", "rad/sec", "radps") else "deg/s"


def turn_rate_dps(dataset: Dataset) -> np.ndarray | None:
    """The instrument's turn rate per sample (deg/s), or None when the data cannot tell.

    From gyro columns (:data:`GYRO_COLUMNS`; unmarked ones in :func:`gyro_units`), else from the attitude
    (:func:`attitude_quaternions`) and the sample times: the angle between consecutive attitudes over their time
    step, given to the later sample; a sample without attitude gets 0."""
    for names, unit in GYRO_COLUMNS:
        if all(n in dataset.extra for n in names):
            w = np.column_stack([np.asarray(dataset.extra[n], float) for n in names])
            rate = np.linalg.norm(w, axis=1)
            return np.degrees(rate) if (unit or gyro_units(dataset)) == "rad/s" else rate
    q, t = attitude_quaternions(dataset), dataset.time_s
    if q is None or t is None:
        return None
    have = np.flatnonzero(np.all(np.isfinite(q), axis=1))  # samples with an attitude
    if have.size < 2:
        return None
    r = Rotation.from_quat(q[have][:, [1, 2, 3, 0]])
    step = (r[:-1].inv() * r[1:]).magnitude()
    dt = np.diff(np.asarray(t, float)[have])
    rate = np.degrees(step / np.where(dt > 0, dt, np.inf))
    out = np.zeros(len(q))
    out[have] = np.concatenate([[rate[0]], rate])
    return out
