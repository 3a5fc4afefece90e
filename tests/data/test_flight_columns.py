"""A compensation flight in MagNav.jl's column names (``tt``, ``mag_1_uc``, ``flux_a_x`` ... ``flux_d_z``,
``ins_roll``, ``cur_outpwr`` ...) or other common ones calibrates and applies without ``--columns``: the fluxgate,
the time, the attitude and a current found by name, the fluxgate chosen with ``--fluxgate``."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from magcal.cli import main
from magcal.core.errors import MagcalError
from magcal.data import io
from magcal.data.compensation_flight import CompensationPlatform, simulate_compensation_flight
from magcal.data.flight_columns import find_fluxgates, flight_mapping, header_names
from magcal.fitting.compensation import compensation_record

CURRENT = CompensationPlatform(current_nT_per_A=np.array([1.5, -1.0, 0.8]))
#: A second fluxgate turned 90 deg about z against the first (its x along the first's y).
TURNED = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


def _magnav_frame(flight, prefixes=("flux_a", "flux_b"), suffix=""):
    """The flight as MagNav.jl names its fields: fluxgate A the simulated one, B turned (so a wrong choice shows),
    the INS attitude, two current sensors (the platform's current on cur_outpwr, a strobe's blinking on cur_strb)."""
    n = flight.time_s.size
    frame = {"line": np.full(n, 1002.01), "tt": 50_000.0 + flight.time_s, "mag_1_uc": flight.scalar_nT}
    frame["mag_2_uc"] = flight.scalar_nT + 40.0 * np.sin(flight.time_s / 9.0)
    for prefix, turn in zip(prefixes, (np.eye(3), TURNED)):
        flux = flight.flux_nT @ turn.T
        frame |= {f"{prefix}_{a}{suffix}": flux[:, k] for k, a in enumerate("xyz")}
        frame[f"{prefix}_t"] = np.linalg.norm(flux, axis=1)
    frame |= {"ins_roll": flight.attitude_deg[:, 0], "ins_pitch": flight.attitude_deg[:, 1]}
    frame |= {"ins_yaw": flight.attitude_deg[:, 2], "cur_outpwr": flight.current_A}
    frame["cur_strb"] = 0.5 * (np.sin(2 * np.pi * flight.time_s) > 0.9)
    return pd.DataFrame(frame)


@pytest.fixture(scope="module")
def magnav(tmp_path_factory):
    folder = tmp_path_factory.mktemp("magnav")
    first, second = simulate_compensation_flight(1, platform=CURRENT), simulate_compensation_flight(2, platform=CURRENT)
    _magnav_frame(first).to_csv(folder / "Flt1002.csv", index=False)
    _magnav_frame(second).to_parquet(folder / "Flt1003.parquet")
    return folder, first, second


@pytest.mark.parametrize(
    ("names", "fluxgate", "expected"),
    [
        (["flux_a_x", "flux_a_y", "flux_a_z", "flux_a_t", "flux_b_x", "flux_b_y", "flux_b_z"], None, "flux_a"),
        (["flux_a_x", "flux_a_y", "flux_a_z", "flux_b_x", "flux_b_y", "flux_b_z"], "flux_b", "flux_b"),
        (["fluxgate_x_nT", "fluxgate_y_nT", "fluxgate_z_nT", "scalar_nT"], None, "fluxgate"),
        (["t", "flux_x", "flux_y", "flux_z"], None, "flux"),
        (["FG1_X", "FG1_Y", "FG1_Z"], None, "fg1"),
    ],
)
def test_fluxgates_found_by_name(names, fluxgate, expected):
    found = find_fluxgates(names)
    mapping = flight_mapping(names, fluxgate=fluxgate)
    assert [mapping[k] for k in ("s1x", "s1y", "s1z")] == list(found[expected])
    assert all(name.lower().startswith(expected) for name in found[expected])


@pytest.mark.parametrize(
    ("names", "columns", "expected"),
    [
        (["t", "x", "y", "z", "flux_a_x", "flux_a_y", "flux_a_z"], None, {}),  # magcal's own names win
        (["tt", "flux_a_x", "flux_a_y", "flux_a_z"], {"s1x": "flux_a_y"}, {"s1x": "flux_a_y", "t": "tt"}),
        (["flux_a_x", "flux_a_y"], None, {}),  # no whole fluxgate: the reader says what is missing
    ],
)
def test_a_file_in_magcal_names_or_a_given_mapping_is_left_as_it_is(names, columns, expected):
    assert flight_mapping(names, columns) == expected


def test_an_unknown_fluxgate_is_named_with_those_the_file_has():
    with pytest.raises(MagcalError, match=r"flux_e.*flux_a \(flux_a_x"):
        flight_mapping(["flux_a_x", "flux_a_y", "flux_a_z"], fluxgate="flux_e")


def test_the_record_takes_magnav_attitude_and_current(magnav):
    folder, first, _ = magnav
    path = folder / "Flt1002.csv"
    ds = io.read_csv(path, columns=flight_mapping(header_names(path)), warn=False)
    record = compensation_record(ds)
    assert record.scalar_column == "mag_1_uc" and record.current_column == "cur_outpwr"
    np.testing.assert_allclose(record.flux_nT, first.flux_nT)
    np.testing.assert_allclose(record.attitude_deg, first.attitude_deg)
    assert record.sample_rate_hz == pytest.approx(10.0)
    assert compensation_record(ds, current="cur_strb").current_column == "cur_strb"
    with pytest.raises(MagcalError, match="cur_none.*cur_outpwr"):
        compensation_record(ds, current="cur_none")


@pytest.mark.parametrize(("fluxgate", "columns"), [(None, "flux_a"), ("flux_b", "flux_b")])
def test_magnav_flight_calibrates_and_applies_without_a_mapping(magnav, tmp_path, capsys, fluxgate, columns):
    folder, first, second = magnav
    comp = tmp_path / "comp.json"
    extra = ["--fluxgate", fluxgate] if fluxgate else []
    args = ["calibrate", str(folder / "Flt1002.csv"), "--effects", "current", "--no-validate", "--json"]
    assert main([*args, *extra, "-o", str(comp)]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["mode"] == "compensation" and doc["calibration"]["scalar_column"] == "mag_1_uc"
    assert doc["calibration"]["fluxgate_columns"] == [f"{columns}_{a}" for a in "xyz"]
    assert doc["calibration"]["current_column"] == "cur_outpwr"
    assert [row["kind"] for row in doc["fom"]["after"]["rows"]] == ["roll", "pitch", "yaw"] * 4  # from ins_*
    assert doc["fom_nT"] < 1.0  # the current's field compensated through cur_outpwr
    out = tmp_path / "Flt1003_comp.parquet"
    assert main(["apply", str(comp), str(folder / "Flt1003.parquet"), "-o", str(out)]) == 0
    compensated = pd.read_parquet(out)["mag_1_uc_comp"].to_numpy()
    residual = compensated - second.truth.compensated_nT(second.scalar_nT)
    assert np.std(residual - np.mean(residual)) < 0.2  # the same fluxgate read on the line as on the flight


def test_an_unknown_fluxgate_on_the_command_line(magnav, capsys):
    folder, *_ = magnav
    assert main(["calibrate", str(folder / "Flt1002.csv"), "--fluxgate", "flux_e"]) == 2
    err = capsys.readouterr().err
    assert "flux_e" in err and "flux_a" in err and "Traceback" not in err
