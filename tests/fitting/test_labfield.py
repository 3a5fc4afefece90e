"""The field a record gives itself: a vector calibration with the lab's field fitted (``reference="fitted"``).

Simulated hand-held records under motion capture (:func:`magcal.data.lab.simulate_lab`) in a field the test sets:
the fitted field lies within its stated standard deviations, the next record's world error is the true
calibration's, a record turned about the vertical only has its declination named as inseparable from the mounting's
yaw, and the saved calibration carries the field to the next record of the same lab.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from magcal.checks.reference import parse_reference_vector, resolve_vector_reference
from magcal.cli import main
from magcal.core.errors import CalibrationError, MagcalError
from magcal.data.attitude import attitude_rows
from magcal.data.io import write_csv
from magcal.data.lab import lab_truth, simulate_lab
from magcal.fitting.labfield import angles_deg, turn_span_deg
from magcal.fitting.vector import fit_vector, true_calibration

N = 1500


def _world_rms(calibration, dataset, field_ned_nT) -> float:
    world = calibration.world(dataset)[0]
    return float(np.sqrt(np.mean((world - field_ned_nT) ** 2)))


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_fitted_field_within_its_uncertainty_and_next_record_as_truth(seed):
    truth = lab_truth(seed=seed)
    ds, _ = simulate_lab(truth, n=N, seed=seed)
    result = fit_vector(ds, "fitted", warn=False)
    lab = result.field
    assert lab is not None and lab.total_source == "gain"  # no total field given: det C^-1 = 1 for sensor 1
    z = (lab.ned_nT - truth.field_ned_nT) / lab.sd_nT
    assert np.all(np.abs(z) < 3.5), z
    assert not lab.declination_fixed
    dec, inc = angles_deg(truth.field_ned_nT)
    assert abs(lab.declination_deg - dec) < 4 * lab.declination_sd_deg
    assert abs(lab.inclination_deg - inc) < 4 * lab.inclination_sd_deg
    following, _ = simulate_lab(truth, n=N, seed=seed + 100)
    ours = _world_rms(result.calibration, following, lab.ned_nT)
    best = _world_rms(true_calibration(truth), following, truth.field_ned_nT)
    assert ours < 1.1 * best


def test_the_gain_gauge_is_named_and_a_given_total_field_fixes_it():
    truth = lab_truth(seed=4)
    ds, _ = simulate_lab(truth, n=N, seed=4)
    free = fit_vector(ds, "fitted", warn=False).field
    assert any("overall gain" in g for g in free.gauges)
    total = float(np.linalg.norm(truth.field_ned_nT)) * 1.01  # the sensor reads 1 % low against it
    given = fit_vector(ds, "fitted", reference_total_nT=total, warn=False).field
    assert given.total_source == "given" and given.total_sd_nT == 0.0
    assert given.total_nT == pytest.approx(total, rel=1e-6)
    assert not any("overall gain" in g for g in given.gauges)


@pytest.mark.parametrize("given", [None, (19_000.0, 3_000.0, 45_000.0)])
def test_a_record_turned_about_the_vertical_names_declination_against_the_mounting_yaw(given):
    truth = lab_truth(seed=5)
    ds, _ = simulate_lab(truth, n=N, seed=5, motion="yaw")
    found = attitude_rows(ds)
    assert found is not None and turn_span_deg(found[0])[1] < 15.0
    reference = resolve_vector_reference(ds, "fitted", vector=given)
    result = fit_vector(ds, reference, warn=False)
    lab = result.field
    assert lab.declination_fixed and lab.declination_sd_deg == 0.0
    expected = 0.0 if given is None else angles_deg(given)[0]
    assert lab.declination_deg == pytest.approx(expected, abs=1e-6)
    named = [g for g in lab.gauges if "declination from the mounting's yaw" in g]
    assert named and "vertical only" in named[0]
    assert any("declination from the mounting's yaw" in w for w in result.warnings)
    assert "what the record cannot separate" in result.text()


def test_a_record_that_barely_turns_is_refused():
    truth = lab_truth(seed=6)
    ds, _ = simulate_lab(truth, n=600, seed=6, motion="yaw", tilt_deg=0.0)
    still = ds.replace(attitude_wxyz=np.tile(ds.attitude_wxyz[:1], (ds.n_samples, 1)))
    with pytest.raises(CalibrationError, match="barely turned"):
        fit_vector(still, "fitted", warn=False)


def test_the_saved_calibration_holds_the_field_for_the_next_record(tmp_path, capsys):
    truth = lab_truth(seed=7)
    first, _ = simulate_lab(truth, n=N, seed=7)
    second, _ = simulate_lab(truth, n=N, seed=8)
    write_csv(tmp_path / "first.csv", first)
    write_csv(tmp_path / "second.csv", second)
    cal = tmp_path / "cal.json"
    assert main(["calibrate", str(tmp_path / "first.csv"), "--reference", "fitted", "-o", str(cal)]) == 0
    out = capsys.readouterr().out
    assert "the lab's field fitted with the calibration" in out
    doc = json.loads(cal.read_text())
    lab = doc["lab_field"]
    assert np.all(np.abs(np.array(lab["ned_nT"]) - truth.field_ned_nT) < 4 * np.array(lab["sd_nT"]))
    assert np.array_equal(parse_reference_vector(str(cal)), np.array(lab["ned_nT"]))
    assert main(["apply", str(cal), str(tmp_path / "second.csv"), "-o", str(tmp_path / "out.csv")]) == 0
    assert "the lab's field fitted with this calibration" in capsys.readouterr().out
    ref = resolve_vector_reference(second, vector=str(cal))
    assert ref is not None and np.allclose(ref.ned_nT, lab["ned_nT"])


def test_a_calibration_without_a_lab_field_is_refused_as_a_reference(tmp_path):
    path = tmp_path / "plain.json"
    path.write_text(json.dumps({"format": "magcal-calibration"}))
    with pytest.raises(MagcalError, match="holds no lab field"):
        parse_reference_vector(str(path))
