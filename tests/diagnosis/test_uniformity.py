"""A field that is not uniform where a record was taken: named by the diagnosis, fitted as a record-only
gradient, never carried by apply.

Simulated hand-held records under motion capture (:func:`magcal.data.lab.simulate_lab`) with a magnet (a point
dipole 0.3 m from the path, or one carried with the sensor) or a uniform gradient the test sets; the vector fit's
diagnosis and the total-field fit's.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from magcal.api import calibrate
from magcal.checks.reference import resolve_vector_reference
from magcal.cli import main
from magcal.data.io import write_csv
from magcal.data.lab import lab_truth, simulate_lab
from magcal.diagnosis import diagnose
from magcal.diagnosis.uniformity import field_uniformity
from magcal.diagnosis.vector import diagnose_vector
from magcal.fitting.labfield import positions_ned_m
from magcal.fitting.vector import fit_vector, true_calibration
from magcal.model.operators import GRADIENT_BASIS

N = 1500
#: A magnet of 0.5 A m^2 pointing down, 0.35 m east of the path along north (its nearest approach 0.3 m).
MAGNET = ((0.0, 0.35, 0.0), (0.0, 0.0, 0.5))
NAMED = "the field is not uniform where you recorded"


def _residual(calibration, dataset, total_nT):
    return np.linalg.norm(calibration.correct(dataset, warn=False), axis=2) - total_nT


@pytest.mark.parametrize("magnet", [False, True])
def test_the_diagnosis_names_a_magnet_near_the_path_as_a_local_anomaly(magnet):
    truth = lab_truth(seed=11)
    ds, _ = simulate_lab(truth, n=N, seed=11, dipole=MAGNET if magnet else None)
    d = diagnose_vector(ds, resolve_vector_reference(ds, "fitted"), max_effects=0, validate=False)
    named = [w for w in d.warnings if NAMED in w]
    assert bool(named) == magnet
    if magnet:
        assert "magnet, steel or a computer" in named[0] and "Nothing of it is carried by magcal apply" in named[0]


def test_a_misfit_that_follows_the_attitude_is_not_named():
    truth = lab_truth(seed=12)
    ds, _ = simulate_lab(truth, n=N, seed=12)
    wrong = true_calibration(truth)
    wrong.sensors[0].bias_nT = wrong.sensors[0].bias_nT + np.array([400.0, -300.0, 250.0])
    total = _residual(wrong, ds, float(np.linalg.norm(truth.field_ned_nT)))
    found = field_uniformity(ds, total, np.ones(ds.n_samples, bool), truth.noise_nT)
    assert found.uniform and found.share_attitude > found.share_position
    magnet, _ = simulate_lab(truth, n=N, seed=12, dipole=MAGNET)
    total = _residual(true_calibration(truth), magnet, float(np.linalg.norm(truth.field_ned_nT)))
    found = field_uniformity(magnet, total, np.ones(ds.n_samples, bool), truth.noise_nT)
    assert not found.uniform and found.share_position > 0.5 and found.basis == "position"
    assert abs(found.where_m[1]) < 0.1  # nearest the magnet: on the path beside it


def test_without_positions_a_field_that_changes_at_a_walking_pace_is_a_hint():
    truth = lab_truth(seed=13)
    magnet, _ = simulate_lab(truth, n=N, seed=13, dipole=MAGNET)
    clean, _ = simulate_lab(truth, n=N, seed=13)
    fitted = np.ones(N, bool)
    for ds, named in ((magnet, True), (clean, False)):
        blind = ds.replace(extra={})
        assert positions_ned_m(blind) is None
        total = _residual(true_calibration(truth), blind, float(np.linalg.norm(truth.field_ned_nT)))
        found = field_uniformity(blind, total, fitted, truth.noise_nT)
        assert found.basis == "time" and found.uniform != named
        if named:
            assert "walking pace" in found.text and "pos_n_m" in found.text


def test_a_gradient_fitted_with_the_field_is_recovered_and_stays_with_the_record(tmp_path):
    params = np.array([300.0, -150.0, 200.0, -100.0, 250.0])  # Gnn, Gne, Gnd, Gee, Ged (nT/m)
    gradient = np.tensordot(params, GRADIENT_BASIS, axes=1)
    truth = lab_truth(seed=14)
    ds, _ = simulate_lab(truth, n=2000, seed=14, gradient_ned_nT_per_m=gradient)
    result = fit_vector(ds, "fitted", field_gradient=True, warn=False)
    lab = result.field
    found = lab.gradient_nT_per_m[[0, 0, 0, 1, 1], [0, 1, 2, 1, 2]]
    assert np.all(np.abs(found - params) < 4 * lab.gradient_sd_nT_per_m)
    assert np.all(np.abs(lab.ned_nT - truth.field_ned_nT) < 4 * lab.sd_nT)
    cal = result.calibration
    assert cal.model is None  # nothing but the sensor's own terms: apply carries no gradient
    cal.save(tmp_path / "cal.json")
    doc = json.loads((tmp_path / "cal.json").read_text())
    assert doc["effects"] == [] and doc["lab_field"]["gradient_carried"] is False
    following, _ = simulate_lab(truth, n=N, seed=15)
    world = cal.world(following)[0]
    best = true_calibration(truth).world(following)[0]
    assert np.sqrt(np.mean((world - lab.ned_nT) ** 2)) < 1.1 * np.sqrt(np.mean((best - truth.field_ned_nT) ** 2))


def test_a_gradient_needs_positions():
    truth = lab_truth(seed=16)
    ds, _ = simulate_lab(truth, n=300, seed=16)
    with pytest.raises(Exception, match="needs the positions"):
        fit_vector(ds.replace(extra={}), "fitted", field_gradient=True, warn=False)


def test_positions_from_latitude_and_longitude():
    truth = lab_truth(seed=17)
    ds, _ = simulate_lab(truth, n=50, seed=17)
    lat0, lon0 = 48.0, 11.0
    north, east, down = (np.asarray(ds.extra[c]) for c in ("pos_n_m", "pos_e_m", "pos_d_m"))
    lat = lat0 + np.degrees(north / 6_371_000.0)
    lon = lon0 + np.degrees(east / (6_371_000.0 * np.cos(np.radians(lat0))))
    geo = ds.replace(extra={"lat": lat, "lon": lon, "alt_m": 500.0 - down})
    p = positions_ned_m(geo)
    assert np.allclose(
        p - p.mean(axis=0), np.column_stack([north, east, down]) - np.mean([north, east, down], axis=1), atol=2e-3
    )


def test_magcal_diagnose_with_the_field_fitted_names_the_magnet(tmp_path, capsys):
    truth = lab_truth(seed=18)
    ds, _ = simulate_lab(truth, n=N, seed=18, dipole=MAGNET)
    write_csv(tmp_path / "magnet.csv", ds)
    assert main(["diagnose", str(tmp_path / "magnet.csv"), "--reference", "fitted", "--no-validate"]) == 0
    captured = capsys.readouterr()
    assert NAMED in captured.out + captured.err
    assert "the lab's field fitted with the calibration" in captured.out


@pytest.mark.parametrize("magnet", ["none", "fixed", "carried"])
def test_the_total_field_diagnosis_names_a_magnet_fixed_in_the_room_not_one_carried(magnet):
    """A total-field fit of a record with positions: a magnet fixed beside the path makes the residual follow the
    place (named); a magnet carried with the sensor and moved is an offset of the sensor (a residual that follows
    the field's direction and time, not the place: not named), and neither is a clean record."""
    truth = lab_truth(seed=22)
    options = {
        "none": {},
        "fixed": {"dipole": MAGNET},
        "carried": {"carried_dipole": ((0.10, 0.0, 0.0), (0.15, 0.0, 0.0), (0.01, 0.0, 0.0))},
    }[magnet]
    ds, _ = simulate_lab(truth, n=N, seed=22, **options)
    result = calibrate(ds, mode="total_field", warn=False)
    d = diagnose(ds, result, max_effects=0, validate=False, workers=1)
    named = [w for w in d.warnings if NAMED in w]
    assert bool(named) == (magnet == "fixed"), d.warnings
    if named:
        assert "the same field direction elsewhere" in named[0] and "turn the sensor in place" in named[0]
        assert "--field-gradient" not in named[0]  # a vector fit's option


def test_a_total_field_record_without_positions_is_not_judged_by_its_pace():
    """Without positions a total-field misfit changes as fast as the turning: nothing is said."""
    truth = lab_truth(seed=22)
    ds, _ = simulate_lab(truth, n=N, seed=22, dipole=MAGNET)
    blind = ds.replace(extra={})
    u = np.tile([0.0, 0.0, 1.0], (N, 1))
    found = field_uniformity(blind, np.ones((1, N)) * 500.0, np.ones(N, bool), truth.noise_nT, directions=u)
    assert found.uniform and found.basis == "none" and found.text == ""
