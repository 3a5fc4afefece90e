"""The fit modes' options and methods the workbench's sessions call (so that the page and ``magcal.calibrate(ds,
mode=...)`` run one code path): the vector diagnosis of a mask of samples, the vector fit's plot data, the record's
total field as the vector diagnosis's default, the gravity mode's separate calibrations, the total-field mode's
maximum likelihood started from a calibration."""

from __future__ import annotations

import numpy as np
import pytest

import magcal
from magcal.core.errors import MagcalError
from magcal.data.board import SWAPPED_MOUNTING, simulate_board
from magcal.data.vehicle import simulate_vehicle, vehicle_truth
from magcal.model.perturbations import parse_hidden
from magcal.modes import GRAVITY, TOTAL_FIELD, VECTOR
from magcal.modes.vector import field_vector


@pytest.fixture(scope="module")
def vehicle():
    ds, _ = simulate_vehicle(vehicle_truth(seed=3), seed=3, n=900, attitude_noise_deg=0.05)
    return ds


def test_the_vector_diagnosis_of_a_mask_is_the_diagnosis_of_those_samples(vehicle):
    kept = np.ones(vehicle.n_samples, bool)
    kept[200:320] = False
    masked = VECTOR.diagnose(vehicle, mask=kept, max_effects=1)
    alone = VECTOR.diagnose(vehicle.subset(kept), max_effects=1)
    assert masked.result.n_samples == alone.result.n_samples == int(kept.sum())
    assert [(c.label, c.delta_bic) for c in masked.candidates] == [(c.label, c.delta_bic) for c in alone.candidates]
    with pytest.raises(MagcalError, match="give effects=, no result"):
        VECTOR.diagnose(vehicle, VECTOR.fit(vehicle), mask=kept)


def test_the_vector_evidence_is_the_world_residual_of_every_sample(vehicle):
    kept = np.arange(vehicle.n_samples) < 600  # fitted on the first samples, drawn on all of them
    result = VECTOR.fit(vehicle, mask=kept)
    ev = VECTOR.evidence(vehicle, result)
    ned = field_vector(vehicle).ned_nT
    world = result.calibration.world(vehicle, record_terms="apply", force=True)
    np.testing.assert_allclose(ev["world_residual_nT"], world - ned[None], atol=1e-9)
    assert ev["world_residual_nT"].shape == (1, vehicle.n_samples, 3)
    # about the attitude error's floor on the samples the fit did not see too: sqrt(2/3) sigma_att |B| per component
    floor = np.sqrt(2.0 / 3.0) * np.radians(0.05) * float(np.mean(np.linalg.norm(ned, axis=1)))
    assert np.sqrt(np.mean(ev["world_residual_nT"][0, ~kept] ** 2)) < 1.5 * floor


def test_the_vector_diagnosis_takes_the_records_total_field_as_the_fit_does(vehicle):
    """A scalar magnetometer's ``ref_total`` column, 200 nT above |B_ned|: the diagnosis's base fit is the mode's fit,
    both against that column (the command line passes it too), unless another total field is given."""
    ned = field_vector(vehicle).ned_nT
    scalar = vehicle.replace(ref_total_nT=np.linalg.norm(ned, axis=1) + 200.0)
    fitted = VECTOR.fit(scalar).calibration.sensors[0]
    diagnosed = VECTOR.diagnose(scalar, max_effects=0, validate=False).result.calibration.sensors[0]
    np.testing.assert_allclose(diagnosed.cinv, fitted.cinv, rtol=1e-9)
    np.testing.assert_allclose(diagnosed.bias_nT, fitted.bias_nT, rtol=1e-9)
    own = VECTOR.diagnose(scalar, max_effects=0, validate=False, reference_total_nT=np.linalg.norm(ned, axis=1))
    assert not np.allclose(own.result.calibration.sensors[0].cinv, fitted.cinv, rtol=1e-6)


def test_the_gravity_modes_separate_calibration_is_the_total_field_fit_turned_by_the_right_angle():
    ds, truth, _ = simulate_board(seed=21, n_poses=20, mounting=SWAPPED_MOUNTING, rate_hz=25.0)
    result = GRAVITY.fit(ds)
    right = result.sensors[0].right_angle
    turned = GRAVITY.separate_calibration(ds, result)
    plain = GRAVITY.separate_calibration(ds)
    assert turned.frame == "accelerometer" and turned.accelerometer is not None
    np.testing.assert_allclose(turned.sensors[0].R, right @ plain.sensors[0].R, atol=1e-12)
    np.testing.assert_allclose(turned.sensors[0].cinv, plain.sensors[0].cinv, atol=1e-12)
    # the right angle is the truth's, which the gravity fit finds 2 deg off
    assert result.sensors[0].right_angle_text.startswith("ROLL_180_YAW_90")


def test_the_total_field_refine_starts_from_a_calibration_and_reaches_the_fits_minimum():
    """A temperature-driven bias hidden in the record: refined from the base model's calibration with the effect,
    the maximum likelihood lands where the whole fit with the effect does, and finds the hidden 30 nT/degC."""
    ds = magcal.simulate_timeseries(
        "chi2017", n_samples=1500, seed=7, rate_hz=5.0, perturbations=[parse_hidden("temperature_bias=30", 1)]
    )
    base = TOTAL_FIELD.fit(ds)
    refined = TOTAL_FIELD.refine(ds, base.calibration, effects=["temperature_bias"])
    whole = TOTAL_FIELD.fit(ds, effects=["temperature_bias"])
    assert refined.success and refined.rms_nT < 0.5 * base.fit.rms_nT
    assert refined.rms_nT == pytest.approx(whole.fit.rms_nT, rel=1e-6)
    found = refined.calibration.effect_values["temperature_bias:1"]
    np.testing.assert_allclose(found, whole.calibration.effect_values["temperature_bias:1"], rtol=1e-4, atol=1e-3)
