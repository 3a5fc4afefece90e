"""The fit-mode seam (:mod:`magcal.modes`): one choice of the fit for the command line and the API.

A simulated vehicle's flight (attitude and the field vector) and a simulated hand-tumbled board (an accelerometer
beside the magnetometer) are each calibrated by ``magcal.calibrate(ds)`` and by ``magcal calibrate FILE -o
cal.json``: the same mode, the same calibration, and ``magcal apply`` of either calibration writes the same world
components (the vehicle) or heading (the board), which match the simulation's truth.
"""

from __future__ import annotations

import csv
import dataclasses
import json

import numpy as np
import pytest

import magcal
from magcal.calibration.calibration import Calibration
from magcal.cli import main
from magcal.core.errors import MagcalError
from magcal.data.board import SWAPPED_MOUNTING, simulate_board
from magcal.data.dataset import dataset_columns, dataset_metadata
from magcal.data.io import write_csv
from magcal.data.vehicle import simulate_vehicle, vehicle_truth
from magcal.fitting.gravity import GravityFitResult
from magcal.fitting.pipeline import CalibrationResult
from magcal.fitting.result import ModeResult
from magcal.fitting.vector import VectorFitResult
from magcal.geometry.heading import angle_difference_deg
from magcal.modes import FIT_MODES, FitMode, choose_mode, mode_names

#: The columns ``magcal apply`` writes that each record is judged on.
APPLIED = {"vector": ["s1n_cal", "s1e_cal", "s1d_cal"], "gravity": ["s1_heading_deg", "s1_dip_deg", "tilt_deg"]}


def _vehicle(folder):
    truth = vehicle_truth(seed=3)
    ds, tr = simulate_vehicle(truth, seed=3, n=1500)
    later, tr_later = simulate_vehicle(truth, seed=4, n=800)
    for name, d in (("record.csv", ds), ("later.csv", later)):
        write_csv(folder / name, dataset_columns(d), dataset_metadata(d))
    return tr_later


def _board(folder):
    ds, truth, _ = simulate_board(seed=11, n_poses=24, mounting=SWAPPED_MOUNTING)
    later, _, rec = simulate_board(truth=truth, seed=12, n_poses=12)
    write_csv(folder / "record.csv", ds)
    write_csv(folder / "later.csv", later)
    return rec


@pytest.fixture(scope="module", params=["vector", "gravity"])
def record(request, tmp_path_factory):
    """``(mode, folder, truth of the later record)``: a record of that mode and a later one, as CSV files."""
    folder = tmp_path_factory.mktemp(request.param)
    truth = _vehicle(folder) if request.param == "vector" else _board(folder)
    return request.param, folder, truth


def _applied(folder, cal, name):
    out = folder / f"{name}.csv"
    assert main(["apply", str(cal), str(folder / "later.csv"), "-o", str(out)]) == 0
    with open(out, encoding="utf-8") as fh:
        return list(csv.DictReader(line for line in fh if not line.startswith("#")))


def test_the_api_and_the_command_line_choose_the_same_mode_and_calibration(record, capsys):
    mode, folder, truth = record
    ds = magcal.read_csv(folder / "record.csv")
    result = magcal.calibrate(ds, warn=False)
    assert isinstance(result, ModeResult) and result.mode == mode and result.calibration.mode == mode
    assert main(["calibrate", str(folder / "record.csv"), "-o", str(folder / "cli.json"), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["mode"] == mode == result.to_dict()["mode"]
    cli = Calibration.load(folder / "cli.json")
    for ours, theirs in zip(result.calibration.sensors, cli.sensors):
        np.testing.assert_allclose(ours.cinv, theirs.cinv, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(ours.bias_nT, theirs.bias_nT, rtol=1e-9, atol=1e-6)
        np.testing.assert_allclose(ours.R, theirs.R, rtol=1e-9, atol=1e-12)

    # magcal apply writes the same world components (heading) from either calibration, and they are the truth's
    result.calibration.save(folder / "api.json")
    api_rows, cli_rows = _applied(folder, folder / "api.json", "api"), _applied(folder, folder / "cli.json", "cli")
    for column in APPLIED[mode]:
        ours = np.array([float(r[column]) for r in api_rows])
        theirs = np.array([float(r[column]) for r in cli_rows])
        np.testing.assert_allclose(ours, theirs, rtol=1e-9, atol=1e-6)
    if mode == "vector":
        world = np.array([[float(r[c]) for c in APPLIED[mode]] for r in api_rows])
        assert np.sqrt(np.mean((world - truth.field_ned_nT) ** 2)) < 25  # attitude error 0.02 deg on 48.8 uT
    else:
        heading = np.array([float(r["s1_heading_deg"]) for r in api_rows])
        pitch = np.degrees(np.arcsin(np.abs(truth.attitude.apply([1.0, 0.0, 0.0])[:, 2])))
        ok = truth.still & (pitch < 60)
        err = angle_difference_deg(heading[ok], truth.heading_deg[ok])
        assert np.sqrt(np.mean(err**2)) < 1.0  # the sensors' noise: about 0.5 deg per sample


@pytest.mark.parametrize("name", ["vector", "gravity", "total_field", "scalar"])
def test_a_mode_named_is_the_mode_used(record, name):
    mode, folder, _ = record
    ds = magcal.read_csv(folder / "record.csv")
    expected = {"scalar": "total_field"}.get(name, name)
    if name in ("vector", "gravity") and name != mode:
        with pytest.raises(MagcalError, match=f"mode='{name}' needs the "):
            magcal.calibrate(ds, mode=name)
        return
    result = magcal.calibrate(ds, mode=name, warn=False)
    kind = {"vector": VectorFitResult, "gravity": GravityFitResult, "total_field": CalibrationResult}[expected]
    assert isinstance(result, kind) and result.mode == expected
    assert result.warnings == [note.text for note in result.notes]  # one meaning of warnings for every mode


def test_auto_takes_the_total_field_fit_for_readings_alone():
    ds = magcal.simulate("chi2017", seed=1)
    assert choose_mode(ds) is FIT_MODES["total_field"]
    assert magcal.calibrate(ds, warn=False).mode == "total_field"


@pytest.mark.parametrize("api", [True, False])
def test_an_unknown_mode_names_the_known_ones(api, tmp_path, capsys):
    ds = magcal.simulate("chi2017", seed=1)
    if api:
        with pytest.raises(MagcalError) as caught:
            magcal.calibrate(ds, mode="toy")
        said = str(caught.value)
    else:
        write_csv(tmp_path / "d.csv", ds)
        try:
            code = main(["calibrate", str(tmp_path / "d.csv"), "--mode", "toy"])
        except SystemExit as exc:  # argparse's refusal of a choice
            code = exc.code
        assert code == 2
        said = capsys.readouterr().err
    assert "'toy'" in said
    assert all(name in said for name in ("auto", "total_field", "vector", "gravity", "scalar")), said


@pytest.mark.parametrize(
    ("mode", "why"),
    [
        ("vector", "needs the attitude: qw, qx, qy, qz or roll_deg, pitch_deg, yaw_deg columns"),
        ("gravity", "needs the accelerometer beside the magnetometer: ax, ay, az columns"),
    ],
)
@pytest.mark.parametrize("api", [True, False])
def test_a_mode_the_record_cannot_have_says_why(mode, why, api, tmp_path, capsys):
    ds = magcal.simulate("chi2017", seed=1)
    if api:
        with pytest.raises(MagcalError, match=f"^mode='{mode}' {why}"):
            magcal.calibrate(ds, mode=mode)
        return
    write_csv(tmp_path / "d.csv", ds)
    assert main(["calibrate", str(tmp_path / "d.csv"), "--mode", mode]) == 2
    assert f"d.csv: --mode {mode} {why}" in capsys.readouterr().err


def test_the_vector_fit_needs_the_field_vector_and_takes_it_given(tmp_path):
    truth = vehicle_truth(seed=1)
    ds, tr = simulate_vehicle(truth, seed=1, n=600)
    bare = ds.replace(extra={})  # no ref_n, ref_e, ref_d
    assert choose_mode(bare) is FIT_MODES["total_field"]
    with pytest.raises(MagcalError, match="needs the Earth's field vector"):
        magcal.calibrate(bare, mode="vector")
    given = np.median(np.reshape(tr.field_ned_nT, (-1, 3)), axis=0)  # one vector for the record, nT
    assert choose_mode(bare, reference=given) is FIT_MODES["vector"]
    result = magcal.calibrate(bare, reference=given, warn=False)
    assert result.mode == "vector" and result.reference.kind != "fitted"


def test_an_option_the_mode_does_not_take_is_named(record):
    mode, folder, _ = record
    ds = magcal.read_csv(folder / "record.csv")
    with pytest.raises(MagcalError, match=r"takes no method=; it takes "):
        magcal.calibrate(ds, method="pso")


def test_auto_says_why_it_passed_over_the_vector_fit_when_no_row_has_an_attitude(tmp_path, capsys):
    truth = vehicle_truth(seed=1)
    ds, _ = simulate_vehicle(truth, seed=1, n=600)
    empty = ds.replace(attitude_wxyz=np.full_like(ds.attitude_wxyz, np.nan))
    with pytest.warns(UserWarning, match="the attitude columns are empty on every row .*: the total-field fit"):
        result = magcal.calibrate(empty)
    assert result.mode == "total_field"


def test_diagnose_follows_the_result_and_refuses_another_mode(record):
    mode, folder, _ = record
    ds = magcal.read_csv(folder / "record.csv")
    result = magcal.calibrate(ds, warn=False)
    other = "total_field" if mode != "total_field" else "vector"
    with pytest.raises(MagcalError, match=f"mode='{other}' with a "):
        magcal.diagnose(ds, result, mode=other)
    if mode == "gravity":  # the total-field diagnosis with the dip's evidence beside it
        diagnosis = magcal.diagnose(ds, result, warn=False, top=1, validate=False)
        assert isinstance(diagnosis, magcal.Diagnosis) and diagnosis.dip_evidence is not None
        assert diagnosis.to_dict()["dip_evidence"]["n"] == diagnosis.dip_evidence.rows.size > 0


def test_the_registry_refuses_a_mode_without_its_needs_or_with_a_reserved_name():
    @dataclasses.dataclass
    class Bare(FitMode):
        name: str = "bare"
        title: str = "a mode that says nothing"

    with pytest.raises(MagcalError, match="give its needs"):
        FIT_MODES.register(Bare())

    class Auto(FitMode):
        name = "auto"
        title = "not a mode"

        def needs(self):
            return "needs nothing"

    with pytest.raises(MagcalError, match="--mode's own"):
        FIT_MODES.register(Auto())
    assert "bare" not in FIT_MODES and mode_names()[0] == "auto" and mode_names()[-1] == "scalar"


def test_the_compensation_mode_takes_the_current_columns_by_name():
    """``current=`` names the current term's columns (one or several); a diagnosis of a fit with several keeps them
    and judges the record's other current columns."""
    from magcal.data.compensation_flight import simulate_compensation_flight
    from magcal.modes.compensation import COMPENSATION
    from tests.fitting.test_compensation_fit_currents import TWO_CURRENTS, currents_dataset

    ds = currents_dataset(simulate_compensation_flight(1, platform=TWO_CURRENTS))
    result = COMPENSATION.fit(ds, effects=("current",), current="cur_strb,cur_com_1")
    assert result.calibration.current_columns == ("cur_strb", "cur_com_1")
    found = COMPENSATION.diagnose(ds, result)
    assert found.effects == ["current"] and found.current_columns[:2] == ["cur_strb", "cur_com_1"]
    assert {c.columns[0] for c in found.candidates if c.name == "current"} == {"cur_heat", "cur_flap", "cur_tank"}
