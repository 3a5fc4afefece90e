"""``magcal calibrate --mode gravity``, ``magcal apply`` writing the heading, ``magcal export`` writing the mounting as
the firmware's custom rotation and the C header with both calibrations, on the simulated board."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from magcal.calibration.calibration import Calibration
from magcal.cli import main
from magcal.data.accelerometer import accelerometer
from magcal.data.board import SWAPPED_MOUNTING, simulate_board
from magcal.data.io import write_csv
from magcal.fitting.gravity import fit_gravity
from magcal.geometry.heading import angle_difference_deg
from magcal.output.export import NT_PER_MILLIGAUSS, apply_ardupilot, export_calibration


@pytest.fixture(scope="module")
def board(tmp_path_factory):
    """A calibration record, a held-out record of the same board, and the truth."""
    folder = tmp_path_factory.mktemp("board")
    ds, truth, _ = simulate_board(seed=11, n_poses=30, mounting=SWAPPED_MOUNTING)
    ds2, _, rec2 = simulate_board(truth=truth, seed=12, n_poses=15)
    write_csv(folder / "board.csv", ds)
    write_csv(folder / "later.csv", ds2)
    return folder, truth, rec2


def test_auto_mode_takes_the_gravity_fit_for_accelerometer_columns(board, capsys):
    folder, truth, _ = board
    assert main(["calibrate", str(folder / "board.csv"), "-o", str(folder / "cal.json"), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["mode"] == "gravity"
    cal = Calibration.load(folder / "cal.json")
    assert cal.mode == "gravity" and cal.accelerometer.fitted
    assert doc["inclination_deg"] == pytest.approx(truth.inclination_deg, abs=0.1)
    assert doc["sensors"][0]["mounting_right_angle"].startswith("ROLL_180_YAW_90 (rotation 10)")
    assert doc["validation"]["rows"][0]["name"] == "gravity"


def test_scalar_mode_still_ignores_the_accelerometer(board, capsys):
    folder, _, _ = board
    assert main(["calibrate", str(folder / "board.csv"), "--mode", "scalar", "--json", "--no-validate"]) == 0
    assert json.loads(capsys.readouterr().out).get("mode", "scalar") != "gravity"


def test_gravity_mode_refuses_a_file_without_accelerometer(tmp_path, capsys):
    ds, _, _ = simulate_board(seed=1, n_poses=6)
    write_csv(tmp_path / "bare.csv", ds.replace(extra={}))
    assert main(["calibrate", str(tmp_path / "bare.csv"), "--mode", "gravity"]) == 2
    assert "needs the accelerometer beside the magnetometer" in capsys.readouterr().err


@pytest.mark.parametrize("option", [["--inclination", "95"], ["--accel-units", "furlongs"]])
def test_bad_gravity_options_are_one_message(board, capsys, option):
    folder, _, _ = board
    assert main(["calibrate", str(folder / "board.csv"), "--mode", "gravity", *option]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and ("--inclination" in err or "--accel-units" in err)


def test_given_inclination_is_used(board, capsys):
    folder, truth, _ = board
    args = ["calibrate", str(folder / "board.csv"), "--inclination", f"{truth.inclination_deg:.4f}", "--json"]
    assert main([*args, "--no-validate"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["inclination_source"] == "given" and doc["inclination_sd_deg"] is None


def test_apply_writes_the_heading(board, capsys):
    folder, truth, rec2 = board
    main(["calibrate", str(folder / "board.csv"), "-o", str(folder / "cal2.json"), "--no-validate"])
    capsys.readouterr()
    out = folder / "later_out.csv"
    assert main(["apply", str(folder / "cal2.json"), str(folder / "later.csv"), "-o", str(out)]) == 0
    with open(out, encoding="utf-8") as fh:
        rows = list(csv.DictReader(line for line in fh if not line.startswith("#")))
    heading = np.array([float(r["s1_heading_deg"]) for r in rows])
    dip = np.array([float(r["s1_dip_deg"]) for r in rows])
    tilt = np.array([float(r["tilt_deg"]) for r in rows])
    assert len(heading) == len(rec2.heading_deg)
    still = rec2.still
    pitch = np.degrees(np.arcsin(np.abs(rec2.attitude.apply([1.0, 0.0, 0.0])[:, 2])))
    ok = still & (pitch < 60)
    err = angle_difference_deg(heading[ok], rec2.heading_deg[ok])
    assert np.sqrt(np.mean(err**2)) < 1.0  # the sensors' noise: ~0.5 deg per sample
    assert np.mean(dip[still]) == pytest.approx(truth.inclination_deg, abs=0.1)
    true_tilt = np.degrees(np.arccos(np.clip(rec2.attitude.apply([0.0, 0.0, 1.0])[:, 2], -1, 1)))
    assert np.sqrt(np.mean((tilt[still] - true_tilt[still]) ** 2)) < 0.5


def test_export_writes_the_rotation_as_the_firmware_custom_rotation():
    """ArduPilot holds the whole rotation into the accelerometer's frame as its custom rotation (COMPASS_ORIENT 101,
    CUST_ROT1_*); PX4 holds only the right angles: the remainder is refused unless forced."""
    ds, _, _ = simulate_board(seed=11, n_poses=30, mounting=SWAPPED_MOUNTING)
    cal = fit_gravity(ds).calibration
    result = export_calibration(cal, "ardupilot")
    assert result.dropped == []  # nothing the firmware cannot hold
    p = result.parameters
    raw = ds.readings_nT[0][:200]
    ours = cal.correct(raw)
    assert p["COMPASS_ORIENT"] == 101 and p["CUST_ROT_ENABLE"] == 1
    firmware = apply_ardupilot(p, raw / NT_PER_MILLIGAUSS) * NT_PER_MILLIGAUSS
    # the firmware's own correction, written out in export.apply_*, gives the calibrated field in the board's axes
    assert np.max(np.abs(firmware - ours)) < 0.05
    with pytest.raises(Exception, match="cannot be stored"):
        export_calibration(cal, "px4")
    forced = export_calibration(cal, "px4", force=True)
    assert forced.parameters["CAL_MAG0_ROT"] == 10 and forced.dropped  # ROLL_180_YAW_90, the rest listed


def test_export_without_custom_rotation_refuses_the_remainder():
    ds, _, _ = simulate_board(seed=11, n_poses=30, mounting=SWAPPED_MOUNTING)
    cal = fit_gravity(ds).calibration
    with pytest.raises(Exception, match="cannot be stored"):
        export_calibration(cal, "ardupilot", custom_rotation=False)
    forced = export_calibration(cal, "ardupilot", custom_rotation=False, force=True)
    assert forced.parameters["COMPASS_ORIENT"] == 10  # ROLL_180_YAW_90, the right angle


def test_c_header_holds_both_calibrations(board, tmp_path, capsys):
    folder, _, _ = board
    main(["calibrate", str(folder / "board.csv"), "-o", str(tmp_path / "c.json"), "--no-validate"])
    capsys.readouterr()
    assert main(["export", str(tmp_path / "c.json"), "--format", "c"]) == 0
    text = capsys.readouterr().out
    cal = Calibration.load(tmp_path / "c.json")
    assert "MAGCAL_ACCEL_MATRIX" in text and "heading = atan2(east.x, north.x)" in text
    assert " 1f" not in text and "{1f" not in text  # valid C float literals
    # the header's numbers reproduce the calibration: the magnetometer's W (y - b) and the accelerometer's K^-1 (a - b)
    result = export_calibration(cal, "c")
    p = result.parameters
    w = np.array([[p[f"MAGCAL_S1_MATRIX_{i}{j}"] for j in range(3)] for i in range(3)])
    b = np.array([p[f"MAGCAL_S1_BIAS_NT_{a}"] for a in "xyz"])
    k = np.array([[p[f"MAGCAL_ACCEL_MATRIX_{i}{j}"] for j in range(3)] for i in range(3)])
    ba = np.array([p[f"MAGCAL_ACCEL_BIAS_M_S2_{a}"] for a in "xyz"])
    ds, _, _ = simulate_board(seed=11, n_poses=30, mounting=SWAPPED_MOUNTING)
    y = ds.readings_nT[0][:100]
    assert np.allclose((y - b) @ w.T, cal.correct(y), atol=1e-6)
    a = accelerometer(ds).m_s2[:100]
    assert np.allclose((a - ba) @ k.T, cal.accelerometer.correct(a), atol=1e-9)
