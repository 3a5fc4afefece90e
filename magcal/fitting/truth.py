"""The calibration a simulation's truth implies: what a fit is compared with in the tests and the benchmarks.

A simulated vehicle (:class:`magcal.data.vehicle.VehicleTruth`: each sensor's ``C``, bias and mounting, its eddy
currents and current field) gives a vector calibration into the body frame; a simulated board
(:class:`magcal.data.board.BoardTruth`: the magnetometer's ``C``, bias and mounting, the accelerometer's ``K`` and
bias) a gravity calibration into the accelerometer's frame. Each sensor's ``W = R_m C^-1`` is split as a fit's is
(:func:`magcal.geometry.orientations.split_mounting`).
"""

from __future__ import annotations

import numpy as np

from magcal.calibration.accelerometer import AccelerometerCalibration
from magcal.calibration.calibration import Calibration, SensorCalibration
from magcal.data.board import BoardTruth
from magcal.geometry.orientations import split_mounting
from magcal.model.terms import EFFECTS, Model, block_label


def true_calibration(truth) -> Calibration:
    """The calibration a simulated vehicle's or board's truth implies.

    Parameters
    ----------
    truth : VehicleTruth or BoardTruth
        A vehicle's: its eddy currents and current field are the effects ``eddy_currents`` and ``current_field``
        (on ``current_A``); effects hidden by perturbations are not in it (compare on the same flight simulated
        without them, whose noise is the same). A board's: the accelerometer's correction as well.

    Returns
    -------
    Calibration
        ``mode="vector"``, ``frame="body"`` for a vehicle; ``mode="gravity"``, ``frame="accelerometer"`` for a board.
    """
    field_nT = float(np.linalg.norm(truth.field_ned_nT))
    if isinstance(truth, BoardTruth):
        return Calibration(
            sensors=[_sensor(truth.mounting, truth.mag_matrix, truth.mag_bias_nT)],
            reference_total_nT=field_nT,
            frame="accelerometer",
            mode="gravity",
            accelerometer=AccelerometerCalibration(np.linalg.inv(truth.accel_matrix), truth.accel_bias_m_s2),
        )
    effects, values = _platform_effects(truth.sensors)
    return Calibration(
        sensors=[_sensor(s.mounting, s.matrix, s.bias_nT) for s in truth.sensors],
        reference_total_nT=field_nT,
        frame="body",
        mode="vector",
        model=Model(len(truth.sensors), effects=effects) if effects else None,
        effect_values=values,
    )


def _sensor(mounting, matrix, bias_nT) -> SensorCalibration:
    """A sensor's calibration from its true mounting ``R_m``, matrix ``C`` and bias (nT)."""
    R, cinv = split_mounting(mounting @ np.linalg.inv(matrix))
    return SensorCalibration(cinv, bias_nT, R)


def _platform_effects(sensors) -> tuple[list, dict]:
    """The vehicle's platform effects (``eddy_currents``, ``current_field`` on ``current_A``) and their values per
    sensor (zero where a sensor has none)."""
    effects, values = [], {}
    if any(s.eddy_ms is not None for s in sensors):
        effects.append(EFFECTS["eddy_currents"]())
        for k, s in enumerate(sensors):
            values[block_label(effects[-1], k)] = np.zeros(9) if s.eddy_ms is None else np.ravel(s.eddy_ms)
    if any(s.current_nT_per_unit is not None for s in sensors):
        current = EFFECTS["current_field"]()
        current.set_state({"column": "current_A"})
        effects.append(current)
        for k, s in enumerate(sensors):
            k_nT = s.current_nT_per_unit
            values[block_label(current, k)] = np.zeros(3) if k_nT is None else np.asarray(k_nT, dtype=float)
    return effects, values
