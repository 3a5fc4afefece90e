"""``magcal calibrate|apply|diagnose`` on the four-sensor cross's compensation flight: the mode chosen by itself
from a box's maneuvers, the report and JSON with the tensor FOM, the compensated vectors and tensor of a second
flight against the simulation's truth, the current the per-sensor TL misses named."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from magcal.cli import main
from magcal.core import conventions
from magcal.data.cross_flight import simulate_cross_flight
from magcal.diagnosis.cross_compensation import LAG_FLAGS, LAG_NEEDS_FIELD
from magcal.diagnosis.cross_fom import tensor_fom
from magcal.output.apply import TENSOR_COLUMNS
from tests.helpers.cross_flights import write_cross_flight


@pytest.fixture(scope="module")
def flights(tmp_path_factory):
    """Two flights of the drone with its battery's current, and two of the drone without."""
    folder = tmp_path_factory.mktemp("cross")
    out = {}
    for platform in ("drone_current", "drone"):
        box, line = simulate_cross_flight(11, platform=platform), simulate_cross_flight(12, platform=platform)
        out[platform] = (
            box,
            line,
            write_cross_flight(box, folder / f"{platform}_box.csv"),
            write_cross_flight(line, folder / f"{platform}_line.csv"),
        )
    return out


@pytest.mark.parametrize(
    ("columns", "attitude", "mode", "given", "reference"),
    [
        (True, "euler", "auto", False, "attitude"),  # the field vector's columns ref_n, ref_e, ref_d
        (True, "quaternion", "cross_compensation", False, "attitude"),
        (False, "euler", "cross_compensation", True, "attitude"),  # --reference-vector N,E,D
        (False, "euler", "cross_compensation", False, "mean"),  # none: the four's mean field
    ],
)
def test_calibrate_reports_the_tensor_fom(flights, tmp_path, capsys, columns, attitude, mode, given, reference):
    box = flights["drone"][0]
    path = write_cross_flight(box, tmp_path / "box.csv", reference=columns, attitude=attitude)
    vector = ["--reference-vector", ",".join(f"{v:.3f}" for v in box.truth.field_ned_nT)] if given else []
    assert main(["calibrate", str(path), "--mode", mode, "--json", *vector]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["mode"] == "cross_compensation" and doc["calibration"]["kind"] == "cross_compensation"
    assert doc["calibration"]["reference"] == reference
    fom = doc["tensor_fom_nT_per_m"]
    assert len(fom["per_maneuver"]) == 12 and len(doc["fom_nT"]) == 4
    assert fom["after"] < fom["before"] / 50 and doc["improvement_ratio"] > 50
    # what the report says is what the true compensation leaves, within 1.2x (the fit saw these maneuvers)
    true = box.truth.compensated_nT(box.readings_nT)
    floor = tensor_fom(true, box.baseline_m, box.truth.maneuvers, box.sample_rate_hz).fom_nT_per_m
    assert fom["after"] <= 1.2 * floor
    for sensor in doc["fom_nT"]:
        assert sensor["after"] < sensor["before"] / 50


@pytest.mark.parametrize(("effects", "fmt"), [((), "csv"), (("current",), "csv"), (("current",), "parquet")])
def test_apply_writes_the_compensated_vectors_and_tensor(flights, tmp_path, capsys, effects, fmt):
    """The second flight compensated by the first's fit: its tensor's FOM within 1.2x of the true compensation's
    with the current, far above it without."""
    box, line, box_csv, line_csv = flights["drone_current"]
    comp = tmp_path / "cross.json"
    args = ["calibrate", str(box_csv), "--mode", "cross_compensation", "-o", str(comp)]
    assert main(args + (["--effects", ",".join(effects)] if effects else [])) == 0
    report = capsys.readouterr().out
    assert "tensor FOM" in report and "improvement ratio" in report
    assert ("Held-out tensor FOM" in report) == bool(effects)
    out = tmp_path / f"line_comp.{fmt}"
    assert main(["apply", str(comp), str(line_csv), "-o", str(out)]) == 0
    frame = pd.read_parquet(out) if fmt == "parquet" else pd.read_csv(out, comment="#")
    assert len(frame) == line.time_s.size
    vectors = np.stack([frame[[f"s{i}{a}_comp" for a in "xyz"]].to_numpy() for i in range(1, 5)])
    truth = line.truth.compensated_nT(line.readings_nT)
    components = conventions.tensor_components(vectors, line.baseline_m)
    for name in TENSOR_COLUMNS:
        assert np.allclose(frame[name], components[name], atol=2e-3)
    maneuvers = line.truth.maneuvers
    ours = tensor_fom(vectors, line.baseline_m, maneuvers, line.sample_rate_hz).fom_nT_per_m
    floor = tensor_fom(truth, line.baseline_m, maneuvers, line.sample_rate_hz).fom_nT_per_m
    if effects:
        assert ours <= 1.2 * floor
        # each sensor's compensated vector is the Earth field there, to the noise and a slow offset
        assert np.median(np.abs(np.diff(vectors - truth, axis=1))) < 0.3
    else:
        assert ours > 5 * floor


@pytest.mark.parametrize(("platform", "verdict", "explained", "also"), [
    ("drone_current", "missing_effect", ["current"], False),
    ("drone_current", "missing_effect", ["current"], True),
    ("drone", "adequate", [], False),
])  # fmt: skip
def test_diagnose_names_the_current(flights, capsys, platform, verdict, explained, also):
    _, _, box_csv, line_csv = flights[platform]
    args = ["diagnose", str(box_csv), "--json"] + (["--also", str(line_csv)] if also else [])
    assert main(args) == 0  # auto: the box's maneuvers choose the mode
    doc = json.loads(capsys.readouterr().out)
    assert doc["mode"] == "cross_compensation" and doc["verdict"] == verdict
    assert doc["explained_by"] == explained
    assert doc["validation"]["scheme"] == ("flight" if also else "maneuvers")
    if explained:
        assert doc["tensor_fom_final_nT_per_m"] <= 1.3 * doc["floor_tensor_fom_nT_per_m"]


def test_diagnose_adds_the_options_that_give_the_lag_its_field(flights, tmp_path, capsys):
    """Without a field vector the lag is not judged: the engine's reason names what the data lack, and the
    command line adds the options that give it."""
    path = write_cross_flight(flights["drone"][0], tmp_path / "bare.csv", reference=False)
    assert main(["diagnose", str(path), "--mode", "cross_compensation"]) == 0
    out = capsys.readouterr().out
    line = next(t for t in out.splitlines() if t.strip().startswith("time_offset"))
    assert LAG_NEEDS_FIELD in line and LAG_FLAGS in line and "--reference igrf" in line


@pytest.mark.parametrize(
    ("write", "argv", "message"),
    [
        (dict(baseline=False), ["calibrate", "{box}", "--mode", "cross_compensation"], "baseline_m"),
        ({}, ["calibrate", "{box}", "--mode", "cross_compensation", "--effects", "heading"], "no term 'heading'"),
        (dict(current=False), ["calibrate", "{box}", "--mode", "cross_compensation", "--effects", "current"],
         "current"),
        ({}, ["diagnose", "{box}", "--mode", "cross_compensation", "--also", "{box}", "--also", "{box}"], "one other"),
    ],
)  # fmt: skip
def test_bad_input_is_named(flights, tmp_path, capsys, write, argv, message):
    box = flights["drone"][0]
    path = write_cross_flight(box, tmp_path / "box.csv", **write)
    assert main([a.format(box=path) for a in argv]) != 0
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


def test_apply_refuses_a_line_without_the_current(flights, tmp_path, capsys):
    box, line, box_csv, _ = flights["drone_current"]
    comp = tmp_path / "cross.json"
    assert (
        main(["calibrate", str(box_csv), "--mode", "cross_compensation", "--effects", "current", "-o", str(comp)]) == 0
    )
    bare = write_cross_flight(line, tmp_path / "bare.csv", current=False)
    capsys.readouterr()
    assert main(["apply", str(comp), str(bare), "-o", str(tmp_path / "out.csv")]) != 0
    err = capsys.readouterr().err
    assert "current_A" in err and str(bare) in err


@pytest.mark.parametrize("command", ["calibrate", "diagnose"])
def test_auto_chooses_the_mode_before_it_checks_the_effects(flights, capsys, command):
    """``--mode auto --effects current`` on the cross's record: the box's maneuvers choose the cross compensation,
    whose terms hold the current (the catalogue's check would refuse it); an unknown name still fails."""
    _, _, box_csv, _ = flights["drone_current"]
    assert main([command, str(box_csv), "--mode", "auto", "--effects", "current", "--json", "--no-validate"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["mode"] == "cross_compensation" and doc["effects"] == ["current"]
    assert main([command, str(box_csv), "--effects", "current,bogus"]) == 2
    err = capsys.readouterr().err
    assert "bogus" in err and "Traceback" not in err


def test_several_current_columns_are_named_with_one_option(tmp_path, capsys):
    from tests.diagnosis.test_cross_compensation_currents import HIDDEN, PLATFORM

    def written(flight, name):
        path = write_cross_flight(flight, tmp_path / name, current=False)
        frame = pd.read_csv(path, comment="#")
        for column, values in flight.currents_A.items():
            frame[column] = values
        with open(path, "w", encoding="utf-8") as fh:
            fh.write(f"# baseline_m: {flight.baseline_m}\n")
            frame.to_csv(fh, index=False)
        return path

    box, line = simulate_cross_flight(34, platform=PLATFORM), simulate_cross_flight(35, platform=PLATFORM)
    path, line_path = written(box, "box.csv"), written(line, "line.csv")
    named = ",".join(HIDDEN)
    out = tmp_path / "cross.json"
    args = ["calibrate", str(path), "--mode", "cross_compensation", "--effects", "current", "--current", named]
    assert main([*args, "-o", str(out), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["calibration"]["current_columns"] == list(HIDDEN)
    assert np.shape(doc["calibration"]["sensors"][0]["current_nT_per_A"]) == (2, 3)
    true = box.truth.compensated_nT(box.readings_nT)
    floor = tensor_fom(true, box.baseline_m, box.truth.maneuvers, box.sample_rate_hz).fom_nT_per_m
    assert doc["tensor_fom_nT_per_m"]["after"] <= 1.2 * floor
    # a line is compensated with its own two currents, found by name
    assert main(["apply", str(out), str(line_path), "-o", str(tmp_path / "line_comp.csv")]) == 0
    comp = pd.read_csv(tmp_path / "line_comp.csv", comment="#")
    ours = np.stack([comp[[f"s{i}{a}_comp" for a in "xyz"]].to_numpy() for i in range(1, 5)])
    true_line = line.truth.compensated_nT(line.readings_nT)
    fom = [tensor_fom(v, line.baseline_m, line.truth.maneuvers, 10.0).fom_nT_per_m for v in (ours, true_line)]
    assert fom[0] <= 1.2 * fom[1]
    capsys.readouterr()
    # one of them alone leaves the other's field
    assert main(["calibrate", str(path), "--mode", "cross_compensation", "--effects", "current", "--current",
                 list(HIDDEN)[0], "--json"]) == 0  # fmt: skip
    assert json.loads(capsys.readouterr().out)["tensor_fom_nT_per_m"]["after"] > 1.5 * floor
    # a named column the file lacks: one line naming it
    assert main([*args[:-1], "cur_strb,cur_fan"]) != 0
    assert "cur_fan" in capsys.readouterr().err
