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

    Raises
    ------
    DatasetError
        Euler columns that are not numbers, or only some of them present.
    """
    kind = attitude_source(dataset)
    if kind == "quaternion":
        return wxyz_rotation(dataset.attitude_wxyz)
    present = [c for c in EULER_COLUMNS if c in dataset.extra]
    if kind is None:
        if present:
            raise DatasetError(
                f"{dataset.source or 'data'}: attitude needs all three columns {', '.join(EULER_COLUMNS)} "
                f"(degrees); found only {', '.join(present)}"
            )
        return None
    values = []
    for c in EULER_COLUMNS:
        v = dataset.extra[c]
        if v.dtype.kind not in "fiu" or not np.all(np.isfinite(v.astype(float))):
            raise DatasetError(f"{dataset.source or 'data'}: column {c} must hold finite angles in degrees")
        values.append(v.astype(float))
    return wxyz_rotation(euler_to_wxyz(*values))


def with_attitude(dataset: Dataset) -> Dataset:
    """The dataset with its Euler columns (if any) turned into the quaternion channel (unchanged otherwise)."""
    if attitude_source(dataset) != "euler":
        return dataset
    rotation = attitude(dataset)
    assert rotation is not None  # Euler columns give an attitude
    q = rotation.as_quat()
    return dataset.replace(attitude_wxyz=np.column_stack([q[:, 3], q[:, :3]]))
