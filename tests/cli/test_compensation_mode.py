"""``magcal calibrate|diagnose|apply|export`` on a compensation flight: the mode chosen by itself from a scalar
column beside the fluxgate, the report and JSON with the FOM, the figure, the compensated line, MagNav.jl's vector."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from magcal.cli import main
from magcal.data.compensation_flight import CompensationPlatform, simulate_compensation_flight
from magcal.diagnosis.fom import figure_of_merit, find_maneuvers

CURRENT = CompensationPlatform(current_nT_per_A=np.array([1.5, -1.0, 0.8]))


def _write(flight, path, scalar="scalar_nT", fluxgate=("x", "y", "z")):
    frame = pd.DataFrame(
        {
            "t": flight.time_s,
            **dict(zip(fluxgate, flight.flux_nT.T)),
            scalar: flight.scalar_nT,
            "roll_deg": flight.attitude_deg[:, 0],
            "pitch_deg": flight.attitude_deg[:, 1],
            "yaw_deg": flight.attitude_deg[:, 2],
            "current_A": flight.current_A,
        }
    )
    if str(path).endswith(".parquet"):
        frame.to_parquet(path)
    else:
        frame.to_csv(path, index=False)
    return path


@pytest.fixture(scope="module")
def flights(tmp_path_factory):
    folder = tmp_path_factory.mktemp("comp")
    first, second = simulate_compensation_flight(1, platform=CURRENT), simulate_compensation_flight(2, platform=CURRENT)
    return folder, first, second, _write(first, folder / "box.csv"), _write(second, folder / "line.csv")


def test_calibrate_picks_the_compensation_and_reports_the_fom(flights, capsys):
    folder, *_, box, _ = flights
    assert main(["calibrate", str(box), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["mode"] == "compensation" and doc["calibration"]["kind"] == "compensation"
    assert len(doc["fom"]["after"]["rows"]) == 12 and doc["fom_nT"] > 5  # the current TL cannot follow
    assert doc["conditioning"]["condition_number"] > 1e3


def test_effects_figure_apply_and_export(flights, capsys, tmp_path):
    folder, first, second, box, line = flights
    comp, png = tmp_path / "comp.json", tmp_path / "fom.png"
    assert (
        main(
            [
                "calibrate",
                str(box),
                "--mode",
                "compensation",
                "--effects",
                "current",
                "-o",
                str(comp),
                "--figure",
                str(png),
            ]
        )
        == 0
    )
    report = capsys.readouterr().out
    assert "current_x" in report and "improvement ratio" in report and "Held-out FOM" in report
    assert png.read_bytes()[:4] == b"\x89PNG"
    for out in (tmp_path / "line_comp.csv", tmp_path / "line_comp.parquet"):
        assert main(["apply", str(comp), str(line), "-o", str(out)]) == 0
        frame = pd.read_parquet(out) if out.suffix == ".parquet" else pd.read_csv(out, comment="#")
        found = find_maneuvers(10.0, attitude_deg=second.attitude_deg)
        ours = figure_of_merit(frame["scalar_nT_comp"].to_numpy(), found, 10.0).fom_nT
        true = figure_of_merit(second.truth.compensated_nT(second.scalar_nT), found, 10.0).fom_nT
        assert ours < 1.2 * true
    capsys.readouterr()
    assert main(["export", str(comp), "--format", "magnav-tl"]) == 2  # a current term MagNav's TL-18 lacks
    assert "cannot hold the term current" in capsys.readouterr().err
    assert main(["export", str(comp), "--format", "magnav-tl", "--force", "-o", str(tmp_path / "tl.json")]) == 0
    tl = json.loads((tmp_path / "tl.json").read_text())
    assert len(tl["TL_coef"]) == 18 and tl["labels"][-1] == "eddy_zz"
    assert json.loads(comp.read_text())["tl18"] == pytest.approx(tl["TL_coef"])


def test_diagnose_names_the_current(flights, capsys):
    folder, *_, box, line = flights
    assert main(["diagnose", str(box), "--json", "--also", str(line)]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["mode"] == "compensation" and doc["explained_by"] == ["current"]
    assert doc["verdict"] == "missing_effect" and doc["validation"]["scheme"] == "flight"


def test_magnav_columns_with_a_mapping(tmp_path, capsys):
    flight = simulate_compensation_flight(3)
    path = _write(flight, tmp_path / "magnav.parquet", "mag_1_uc", ("flux_a_x", "flux_a_y", "flux_a_z"))
    assert main(["calibrate", str(path), "--json"]) == 0  # the fluxgate found by name (flux_a_x ...)
    assert json.loads(capsys.readouterr().out)["calibration"]["fluxgate_columns"] == [
        "flux_a_x",
        "flux_a_y",
        "flux_a_z",
    ]
    csv = _write(flight, tmp_path / "magnav.csv", "mag_1_uc", ("flux_a_x", "flux_a_y", "flux_a_z"))
    assert main(["calibrate", str(csv), "--columns", "x=flux_a_x,y=flux_a_y,z=flux_a_z", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["calibration"]["scalar_column"] == "mag_1_uc" and doc["fom_nT"] < 1.0


def test_a_compensation_term_needs_its_column(tmp_path, capsys):
    flight = simulate_compensation_flight(3)
    frame = pd.DataFrame(
        {
            "t": flight.time_s,
            "x": flight.flux_nT[:, 0],
            "y": flight.flux_nT[:, 1],
            "z": flight.flux_nT[:, 2],
            "scalar_nT": flight.scalar_nT,
        }
    )
    frame.to_csv(tmp_path / "box.csv", index=False)
    assert main(["calibrate", str(tmp_path / "box.csv"), "--effects", "current"]) == 2
    assert "current_A or throttle" in capsys.readouterr().err
    assert main(["calibrate", str(tmp_path / "box.csv"), "--effects", "bogus"]) == 2
    assert "not a compensation term" in capsys.readouterr().err


def test_the_api_takes_the_compensation_mode_as_the_command_line_does(flights):
    import magcal
    from magcal.data import io

    folder, first, *_ = flights
    ds = io.read_csv(folder / "box.csv", warn=False)
    result = magcal.calibrate(ds, effects=["current"], validate=True, warn=False)
    assert result.mode == "compensation" and result.calibration.effects == ("current",)
    assert result.fom_nT < 1.2 * result.fom.before.fom_nT / 100
    assert result.validation is not None and result.validation.fom_effects_nT < result.validation.fom_tl_nT
    found = magcal.diagnose(ds, result, warn=False)
    assert found.mode == "compensation" and found.effects == ["current"]
    assert "current" not in [c.name for c in found.candidates]


def test_several_lines_go_into_a_folder(flights, tmp_path, capsys):
    folder, first, second, box, line = flights
    comp = tmp_path / "comp.json"
    assert main(["calibrate", str(box), "-o", str(comp), "--effects", "current", "--no-validate"]) == 0
    out = tmp_path / "compensated"
    assert main(["apply", str(comp), str(box), str(line), "-o", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["box_comp.parquet", "line_comp.parquet"]
    assert pd.read_parquet(out / "line_comp.parquet")["scalar_nT_comp"].size == second.time_s.size
    capsys.readouterr()
    parts = tmp_path / "parts"
    assert main(["apply", str(comp), str(line), "-o", str(parts), "--workers", "2", "--no-progress"]) == 0
    assert sum(len(pd.read_parquet(p)) for p in parts.iterdir()) == second.time_s.size


def test_magnav_test_data_through_the_command_line(tmp_path, capsys):
    """MagNav.jl's own TL test data (fluxgate A, Mag 1) as a CSV with MagNav's names: the command line's
    compensation reproduces their compensated Mag 1 (their ridge) and is below it in the band (ridge 0)."""
    from magcal.model.tolles_lawson import bandpass
    from tests.fitting.test_tolles_lawson import _magnav_tl_data

    data = _magnav_tl_data(tmp_path)
    rate = float(data.fs)
    n = data.mag_1_uc.size
    frame = {"t": np.arange(n) / rate, "flux_a_x": data.flux_a_x, "flux_a_y": data.flux_a_y}
    frame |= {"flux_a_z": data.flux_a_z, "mag_1_uc": data.mag_1_uc}
    pd.DataFrame(frame).to_csv(tmp_path / "tl.csv", index=False)
    mapping = ["--columns", "x=flux_a_x,y=flux_a_y,z=flux_a_z"]
    for ridge in ("0", "0.001"):
        comp = tmp_path / f"comp{ridge}.json"
        assert main(["calibrate", str(tmp_path / "tl.csv"), *mapping, "--ridge", ridge, "-o", str(comp)]) == 0
        out = tmp_path / f"out{ridge}.csv"
        assert main(["apply", str(comp), str(tmp_path / "tl.csv"), *mapping, "-o", str(out)]) == 0
        ours = pd.read_csv(out, comment="#")["mag_1_uc_comp"].to_numpy()
        if ridge == "0":
            assert np.std(bandpass(ours, rate)[20:-20]) <= np.std(bandpass(data.mag_1_c, rate)[20:-20])
        else:
            assert np.std(ours - data.mag_1_c) < 0.1  # MagNav's own test of its compensation
    capsys.readouterr()


def test_several_current_columns_are_named_with_one_option(tmp_path, capsys):
    """``--current cur_strb,cur_com_1``: each column its own field per ampere, in the report and the document, and
    the line compensated with both to within 1.2x of the true compensation."""
    from tests.fitting.test_compensation_fit_currents import TWO_CURRENTS

    paths = []
    for seed in (1, 2):
        flight = simulate_compensation_flight(seed, platform=TWO_CURRENTS)
        frame = pd.read_csv(_write(flight, tmp_path / f"f{seed}.csv")).drop(columns="current_A")
        frame = frame.assign(**flight.currents_A)
        frame.to_csv(tmp_path / f"f{seed}.csv", index=False)
        paths.append(tmp_path / f"f{seed}.csv")
    comp, out = tmp_path / "comp.json", tmp_path / "line_comp.csv"
    args = ["calibrate", str(paths[0]), "--effects", "current", "--current", "cur_strb,cur_com_1", "-o", str(comp)]
    assert main(args + ["--no-validate"]) == 0
    captured = capsys.readouterr()
    assert "current_cur_strb_x" in captured.out and "current_cur_com_1_z" in captured.out
    assert "current 'cur_strb', 'cur_com_1'" in captured.err
    assert json.loads(comp.read_text())["current_columns"] == ["cur_strb", "cur_com_1"]
    assert main(["apply", str(comp), str(paths[1]), "-o", str(out)]) == 0
    line = simulate_compensation_flight(2, platform=TWO_CURRENTS)
    found = find_maneuvers(10.0, attitude_deg=line.attitude_deg)
    ours = figure_of_merit(pd.read_csv(out, comment="#")["scalar_nT_comp"].to_numpy(), found, 10.0).fom_nT
    assert ours < 1.2 * figure_of_merit(line.truth.compensated_nT(line.scalar_nT), found, 10.0).fom_nT
