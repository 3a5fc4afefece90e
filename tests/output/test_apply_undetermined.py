"""A calibration the fit marked not determined by its record is refused where it would be applied, naming the sensor
and why, unless forced; the determined sensors of the same calibration are applied.

Found on a real PX4 log: compass 1 was reported "NOT DETERMINED ... do not apply", and ``magcal apply`` wrote it
without a word (5 866 nT world RMS on the next flight).
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from magcal.calibration.calibration import Calibration
from magcal.checks.reference import resolve_vector_reference
from magcal.cli import main
from magcal.core.errors import DataWarning, MagcalError
from magcal.data.dataset import dataset_columns, dataset_metadata
from magcal.data.io import write_csv
from magcal.data.vehicle import simulate_vehicle, vehicle_truth
from magcal.fitting.vector import fit_vector
from magcal.output.apply import apply_file
from magcal.output.export import export_calibration

pd = pytest.importorskip("pandas")

#: What the fit saved of the sensor it could not determine (a level flight's: benchmarks/real/vector_logs.py).
UNDETERMINED = {"determined": False, "bias_sd_nT": [5866.0, 4100.0, 2900.0], "mounting_sd_deg": [3.1, 2.2, 7.5]}


@pytest.fixture(scope="module")
def flights(tmp_path_factory):
    """Two flights of a two-compass vehicle and the vector calibration of the first, whose compass 2 the fit
    marked not determined (saved as ``cal.json``); ``one.csv``, ``two.csv``."""
    folder = tmp_path_factory.mktemp("undetermined")
    truth = vehicle_truth(n_sensors=2, seed=4)
    paths = {}
    for name, seed in (("one", 1), ("two", 2)):
        ds, _ = simulate_vehicle(truth, seed=seed, n=600)
        write_csv(folder / f"{name}.csv", dataset_columns(ds), dataset_metadata(ds))
        paths[name] = ds
    fit = fit_vector(paths["one"], resolve_vector_reference(paths["one"]), warn=False)
    assert all(s.determined for s in fit.sensors)  # both are; the second is marked as the real log's compass 1
    cal = fit.calibration
    cal.sensors[1].summary.update(UNDETERMINED)
    cal.save(folder / "cal.json")
    return folder, paths


def _frame(path):
    return pd.read_csv(path, comment="#")


def _header(path):
    with open(path, encoding="utf-8") as fh:
        return "".join(line for line in fh if line.startswith("#"))


def test_the_calibration_file_keeps_which_sensor_is_not_determined_and_why(flights):
    folder, _ = flights
    cal = Calibration.load(folder / "cal.json")
    assert list(cal.undetermined()) == [1]
    why = cal.undetermined()[1]
    assert "does not determine it" in why and "5866 nT" in why and "7.50 deg" in why


def test_apply_refuses_the_undetermined_sensor_and_corrects_the_other(flights, tmp_path, capsys):
    folder, ds = flights
    out = tmp_path / "out.csv"
    assert main(["apply", str(folder / "cal.json"), str(folder / "two.csv"), "-o", str(out), "--no-progress"]) == 0
    err = capsys.readouterr().err
    assert "not applied: sensor 2" in err and "5866 nT" in err and "--force" in err
    frame = _frame(out)
    assert {"s1x_cal", "s1n_cal"} <= set(frame.columns)
    assert not any(c.startswith("s2") and c.endswith("_cal") for c in frame.columns)
    cal = Calibration.load(folder / "cal.json")
    truth = cal.correct(ds["two"], force=True, warn=False)[0]
    assert np.allclose(frame[["s1x_cal", "s1y_cal", "s1z_cal"]].to_numpy(), truth, atol=1e-3)
    assert "magcal_refused" in _header(out) and "sensor 2" in _header(out)


def test_force_applies_it_and_the_output_header_says_so(flights, tmp_path, capsys):
    folder, _ = flights
    out = tmp_path / "forced.csv"
    args = ["apply", str(folder / "cal.json"), str(folder / "two.csv"), "-o", str(out), "--no-progress", "--force"]
    assert main(args) == 0
    assert "applied although not determined (forced): sensor 2" in capsys.readouterr().err
    frame = _frame(out)
    assert {"s1x_cal", "s2x_cal", "s2n_cal"} <= set(frame.columns)
    header = _header(out)
    assert "magcal_forced" in header and "sensor 2" in header and "magcal_refused" not in header


def test_parquet_output_refuses_it_too(flights, tmp_path):
    pytest.importorskip("pyarrow")
    import pyarrow.parquet as pq

    folder, _ = flights
    out = tmp_path / "out.parquet"
    summary = apply_file(folder / "cal.json", folder / "two.csv", out, progress=False)
    assert any("not applied: sensor 2" in n.text for n in summary.notes)
    table = pq.read_table(out)
    assert "s1x_cal" in table.column_names and "s2x_cal" not in table.column_names
    import json

    meta = json.loads(table.schema.metadata[b"magcal"])
    assert "sensor 2" in meta["magcal_refused"]


def test_the_parallel_apply_refuses_it_in_every_partition(flights, tmp_path):
    pytest.importorskip("distributed")
    from magcal.output.survey import apply_partitioned

    folder, _ = flights
    out = tmp_path / "parts"
    summary = apply_partitioned(folder / "cal.json", [folder / "two.csv"], out, fmt="csv", workers=1, progress=False)
    assert any("not applied: sensor 2" in n.text for n in summary.notes)
    parts = sorted(out.glob("part-*.csv"))
    assert parts
    for part in parts:
        columns = set(_frame(part).columns)
        assert "s1x_cal" in columns and "s2x_cal" not in columns
        assert "magcal_refused" in _header(part)


def test_the_library_gives_nan_for_it_with_a_warning_unless_forced(flights):
    folder, ds = flights
    cal = Calibration.load(folder / "cal.json")
    with pytest.warns(DataWarning, match="not applied: sensor 2"):
        vectors = cal.correct(ds["two"])
    assert np.all(np.isfinite(vectors[0])) and np.all(np.isnan(vectors[1]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DataWarning)  # the forced note
        forced = cal.correct(ds["two"], force=True)
    assert np.all(np.isfinite(forced)) and np.allclose(forced[0], vectors[0])


def test_a_calibration_with_no_determined_sensor_is_refused_whole(flights, tmp_path, capsys):
    folder, _ = flights
    cal = Calibration.load(folder / "cal.json")
    cal.sensors[0].summary.update(UNDETERMINED)
    cal.save(tmp_path / "none.json")
    out = tmp_path / "out.csv"
    assert main(["apply", str(tmp_path / "none.json"), str(folder / "two.csv"), "-o", str(out)]) != 0
    err = capsys.readouterr().err
    assert "sensor 1" in err and "sensor 2" in err and "--force" in err and not out.exists()
    assert main(["apply", str(tmp_path / "none.json"), str(folder / "two.csv"), "-o", str(out), "--force"]) == 0


def test_export_leaves_it_out_refuses_it_named_and_writes_it_forced(flights):
    folder, _ = flights
    cal = Calibration.load(folder / "cal.json")
    result = export_calibration(cal, "ardupilot", force=False)
    assert "COMPASS_OFS_X" in result.parameters and "COMPASS_OFS2_X" not in result.parameters
    assert result.notes[0].startswith("not exported: sensor 2")
    with pytest.raises(MagcalError, match="not exported: sensor 2"):
        export_calibration(cal, "ardupilot", sensors=[2])
    forced = export_calibration(cal, "ardupilot", force=True)
    assert "COMPASS_OFS2_X" in forced.parameters and "forced" in forced.notes[0]


def test_the_workbench_export_refuses_it_and_names_it(bench, flights):
    folder, ds = flights
    wb = bench(ds=ds["two"], name="two.csv")
    wb.ctrl.calibration = Calibration.load(folder / "cal.json")
    wb.handle(wb.exporting.do_export_csv, None)
    name, content = wb.downloads.last
    header = content.decode()
    assert name == "corrected.csv" and "s1x_cal" in header and "s2x_cal" not in header
    assert "not applied: sensor 2" in wb.ctrl.message
    wb.handle(wb.exporting.do_export_format, None, "ardupilot")
    name, content = wb.downloads.last
    assert name == "compass.parm" and b"COMPASS_OFS2_X" not in content and b"COMPASS_OFS_X" in content
    assert "not exported: sensor 2" in wb.ctrl.message
    wb.panels.export.force.value = True
    wb.handle(wb.exporting.do_export_csv, None)
    assert "s2x_cal" in wb.downloads.last[1].decode() and "magcal_forced" in wb.downloads.last[1].decode()
