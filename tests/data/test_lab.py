"""The simulated lab record (:func:`magcal.data.lab.simulate_lab`): a magnet carried with the sensor is an offset in
the sensor's axes that changes as it is moved; a faster hand turns the sensor faster."""

from __future__ import annotations

import numpy as np

from magcal.data.lab import dipole_field_nT, lab_truth, simulate_lab
from magcal.model.effects import median_turn_rate_dps


def test_a_carried_magnet_is_an_offset_in_the_sensor_axes_that_moves_with_the_magnet():
    truth = lab_truth(seed=3)
    start, end, moment = (0.10, 0.0, 0.0), (0.15, 0.02, 0.0), (0.01, 0.0, 0.005)
    plain, _ = simulate_lab(truth, n=400, seed=3)
    carried, _ = simulate_lab(truth, n=400, seed=3, carried_dipole=(start, end, moment))
    extra = carried.readings_nT[0] - plain.readings_nT[0]  # the same noise: the magnet's part alone
    matrix = truth.sensors[0].matrix @ truth.sensors[0].mounting.T
    for i, where in ((0, start), (-1, end)):
        field = dipole_field_nT(np.zeros((1, 3)), where, moment)[0]  # at the sensor, in its axes
        assert np.allclose(extra[i], matrix @ field, rtol=1e-9)
    # at the start the magnet is 0.1 m away on x, along its moment: 2 m / d^3 = 2000 nT on x before the sensor's gains
    assert np.linalg.norm(matrix @ dipole_field_nT(np.zeros((1, 3)), start, moment)[0]) > 1500.0
    # the offset does not follow the attitude: it changes only as the magnet moves (smoothly, toward or away)
    assert np.all(np.abs(np.diff(extra, axis=0)) < 10.0)


def test_turns_make_the_hand_faster():
    truth = lab_truth(seed=4)
    slow, _ = simulate_lab(truth, n=3000, seed=4, noise_nT=0.0)
    fast, _ = simulate_lab(truth, n=3000, seed=4, noise_nT=0.0, turns=4.0)
    ratio = median_turn_rate_dps(fast.readings_nT[0], fast.time_s) / median_turn_rate_dps(
        slow.readings_nT[0], slow.time_s
    )
    assert 3.0 < ratio < 5.0
