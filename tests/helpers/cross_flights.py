"""Simulated compensation flights of the four-sensor cross written as magcal records (CSV or Parquet)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from magcal.data.attitude import euler_to_wxyz


def write_cross_flight(flight, path, *, reference=True, current=True, attitude="euler", baseline=True):
    """Write ``flight`` (:class:`magcal.data.cross_flight.CrossFlight`) to ``path``: t, s1x .. s4z, the attitude
    (``"euler"``: roll_deg, pitch_deg, yaw_deg; ``"quaternion"``: qw .. qz; None: none), the Earth field vector
    ref_n, ref_e, ref_d when ``reference``, current_A when ``current``, and ``# baseline_m`` when ``baseline``."""
    cols = {"t": flight.time_s}
    for i in range(4):
        for k, a in enumerate("xyz"):
            cols[f"s{i + 1}{a}"] = flight.readings_nT[i][:, k]
    roll, pitch, yaw = flight.attitude_deg.T
    if attitude == "euler":
        cols.update(roll_deg=roll, pitch_deg=pitch, yaw_deg=yaw)
    elif attitude == "quaternion":
        cols.update(dict(zip(("qw", "qx", "qy", "qz"), np.asarray(euler_to_wxyz(roll, pitch, yaw)).T)))
    if reference:
        for k, a in enumerate("ned"):
            cols[f"ref_{a}"] = np.full(flight.time_s.size, flight.truth.field_ned_nT[k])
    if current:
        cols["current_A"] = flight.current_A
    frame = pd.DataFrame(cols)
    if str(path).endswith(".parquet"):
        frame.to_parquet(path)
        return path
    with open(path, "w", encoding="utf-8") as fh:
        if baseline:
            fh.write(f"# baseline_m: {flight.baseline_m}\n")
        frame.to_csv(fh, index=False)
    return path
