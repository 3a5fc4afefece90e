"""The attitude-aided vector calibration on records whose attitude (or reference) has gaps: a live recording's
samples before the first ATTITUDE message, a gap in a log, the samples before the GPS's fix.

The fit leaves those samples out (a note counts them and names their rows) and its parameters are those of a fit on
the clean samples; ``magcal apply`` writes the body-frame columns on every row and NaN world columns where a row has
no attitude (one note); the workbench's vector model runs on such a record. Known truth: simulated vehicles whose
mounting, biases and soft iron are set by :func:`magcal.data.vehicle.vehicle_truth`.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magcal.calibration.calibration import Calibration
from magcal.checks.reference import resolve_vector_reference
from magcal.cli import main
from magcal.core.errors import DataWarning, MagcalError
from magcal.core.notes import Note, row_runs, runs
from magcal.data.attitude import EULER_COLUMNS, attitude, attitude_present, attitude_rows, wxyz_rotation
from magcal.data.dataset import DatasetError, dataset_columns, dataset_metadata
from magcal.data.io import write_csv
from magcal.data.vehicle import simulate_vehicle, vehicle_truth
from magcal.fitting.vector import MIN_SAMPLES, fit_vector, validate_vector

N = 3000


def _gap(n=N, runs_=((0, 300), (1200, 1212))) -> np.ndarray:
    """True on the samples without attitude: rows 1-300 and 1201-1212 by default (0-based half-open runs)."""
    gap = np.zeros(n, bool)
    for a, b in runs_:
        gap[a:b] = True
    return gap


def _euler(ds):
    """The dataset with its attitude as roll_deg, pitch_deg, yaw_deg columns (the live recording's form)."""
    ypr = wxyz_rotation(ds.attitude_wxyz).as_euler("ZYX", degrees=True)
    extra = dict(ds.extra)
    extra.update(roll_deg=ypr[:, 2], pitch_deg=ypr[:, 1], yaw_deg=ypr[:, 0])
    return ds.replace(attitude_wxyz=None, extra=extra)


def _without_attitude(ds, gap, form):
    """``ds`` with no attitude on the ``gap`` samples: NaN quaternions, or NaN Euler angles."""
    if form == "quaternion":
        q = np.array(ds.attitude_wxyz, dtype=float)
        q[gap] = np.nan
        return ds.replace(attitude_wxyz=q)
    ds = _euler(ds)
    extra = dict(ds.extra)
    for c in EULER_COLUMNS:
        extra[c] = np.where(gap, np.nan, extra[c])
    return ds.replace(extra=extra)


def _same_fit(a, b, rtol=1e-9):
    """Two vector fits give the same calibration (W = R C^-1, bias, platform terms) to ``rtol``."""
    for sa, sb in zip(a.sensors, b.sensors):
        assert np.allclose(sa.W, sb.W, rtol=rtol, atol=rtol * np.abs(sb.W).max())
        assert np.allclose(sa.bias_nT, sb.bias_nT, rtol=rtol, atol=1e-6)
        for k in sb.terms:
            assert np.allclose(sa.terms[k], sb.terms[k], rtol=rtol, atol=1e-6)
        assert sa.rms_vector_nT == pytest.approx(sb.rms_vector_nT, rel=1e-9)


# --- the engine ----------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("form", ["quaternion", "euler"])
def test_samples_without_attitude_are_left_out_with_a_note_and_the_fit_is_the_clean_one(form):
    truth = vehicle_truth(seed=3, current=True)
    flight, _ = simulate_vehicle(truth, seed=3, n=N, attitude_noise_deg=0.02)
    gap = _gap()
    gappy = _without_attitude(flight, gap, form)
    with pytest.raises(DatasetError, match="data row 1"):  # the strict form still names the first row without one
        attitude(gappy)
    got = fit_vector(gappy, resolve_vector_reference(gappy), terms=["current"], warn=False)
    clean = _without_attitude(flight, np.zeros(N, bool), form).subset(~gap)  # the same attitude, its clean rows
    ref = fit_vector(clean, resolve_vector_reference(clean), terms=["current"], warn=False)
    _same_fit(got, ref)
    # the truth: mounting to the attitude error's share, bias to a few nT, the current's field
    s, t = got.sensors[0], truth.sensors[0]
    assert np.degrees(np.arccos(np.clip((np.trace(s.mounting @ t.mounting.T) - 1) / 2, -1, 1))) < 0.01
    assert np.max(np.abs(s.bias_nT - t.bias_nT)) < 15.0
    assert np.allclose(s.terms["current_nT_per_unit"], t.current_nT_per_unit, atol=1.0)
    # one entry per sample of the dataset
    assert got.fitted.shape == (N,) and np.array_equal(got.fitted, ~gap)
    assert got.n_samples == N - 312
    assert got.gaps.n_without_attitude == 312 and got.gaps.n_without_reference == 0
    note = [w for w in got.warnings if "no attitude" in w]
    assert note == [
        "312 of 3000 samples have no attitude (rows 1-300, 1201-1212) and were left out of the vector fit (2688 "
        "samples fitted)"
    ]
    assert Note(note[0], DataWarning, "vector fit") in got.notes
    assert got.to_dict()["samples_left_out"]["n_without_attitude"] == 312
    # a user's call raises it as a warning; the clean record has no such note
    with pytest.warns(DataWarning, match="312 of 3000 samples have no attitude"):
        fit_vector(gappy, resolve_vector_reference(gappy), terms=[])
    assert ref.gaps.n_left_out == 0 and not any("no attitude" in w for w in ref.warnings)


def test_a_mask_and_the_gaps_together_fit_what_both_keep():
    truth = vehicle_truth(seed=5)
    flight, _ = simulate_vehicle(truth, seed=5, n=N)
    gap = _gap(runs_=((0, 150),))
    mask = np.ones(N, bool)
    mask[100:400] = False  # the user's rejection overlaps the gap: rows 101-150 are both
    gappy = _without_attitude(flight, gap, "euler")
    got = fit_vector(gappy, resolve_vector_reference(gappy), terms=["eddy"], mask=mask, warn=False)
    assert np.array_equal(got.fitted, mask & ~gap) and got.n_samples == N - 400
    # the eddy term's rate is taken on the whole record, so the reference is the full record's fit under one mask
    full = _euler(flight)
    ref = fit_vector(full, resolve_vector_reference(full), terms=["eddy"], mask=mask & ~gap, warn=False)
    _same_fit(got, ref)
    assert (
        "100 of the 2700 selected samples have no attitude (rows 1-100) and were left out of the vector fit (2600 "
        "samples fitted)" in got.warnings
    )


def test_samples_without_a_reference_vector_are_left_out_too():
    truth = vehicle_truth(seed=6)
    flight, _ = simulate_vehicle(truth, seed=6, n=N)
    no_att, no_ref = _gap(runs_=((0, 50),)), _gap(runs_=((0, 200), (2999, 3000)))  # the GPS fixes later
    extra = dict(flight.extra)
    for c in ("ref_n", "ref_e", "ref_d"):
        extra[c] = np.where(no_ref, np.nan, extra[c])
    gappy = _without_attitude(flight.replace(extra=extra), no_att, "quaternion")
    ref = resolve_vector_reference(gappy)
    assert ref.kind == "column" and "201 samples without one" in ref.text
    assert np.array_equal(np.isnan(ref.ned_nT).any(axis=1), no_ref)
    got = fit_vector(gappy, ref, terms=[], warn=False)
    keep = ~(no_att | no_ref)
    clean = flight.subset(keep)
    _same_fit(got, fit_vector(clean, resolve_vector_reference(clean), terms=[], warn=False))
    text = next(w for w in got.warnings if "left out" in w)
    assert text.startswith(
        "50 of 3000 samples have no attitude (rows 1-50) and 201 have no reference field vector (rows 1-200, 3000"
    )
    assert text.endswith("those 201 were left out of the vector fit (2799 fitted)")
    # the total field given per sample (a scalar magnetometer) counts too
    total = ref.total_nT  # NaN where the vector is
    total[2500] = np.nan
    got = fit_vector(gappy, ref, terms=[], reference_total_nT=total, warn=False)
    assert got.gaps.n_without_reference == 202 and not got.fitted[2500]


def test_igrf_along_a_track_without_a_fix_has_no_reference_there():
    pytest.importorskip("ppigrf")
    from magcal.checks.reference import igrf_ned_nT

    n = 400
    lat, lon, alt = np.linspace(45.0, 45.2, n), np.linspace(7.0, 7.3, n), np.full(n, 500.0)
    nofix = np.zeros(n, bool)
    nofix[:40] = True
    truth = vehicle_truth(seed=2)
    flight, _ = simulate_vehicle(truth, seed=2, n=n)
    extra = {
        "lat": np.where(nofix, np.nan, lat),
        "lon": np.where(nofix, np.nan, lon),
        "alt_m": np.where(nofix, np.nan, alt),
    }
    ds = flight.replace(extra=extra)
    ref = resolve_vector_reference(ds, "igrf", date="2024-06-01")
    assert ref.kind == "igrf-track" and "40 samples without a position have none" in ref.text
    assert np.isnan(ref.ned_nT[nofix]).all()
    direct = igrf_ned_nT(lat[~nofix], lon[~nofix], alt[~nofix] / 1000.0, "2024-06-01")
    assert np.allclose(ref.ned_nT[~nofix], direct, atol=1e-6)
    with pytest.raises(MagcalError, match="no sample has a position"):
        resolve_vector_reference(ds.replace(extra={k: np.full(n, np.nan) for k in extra}), "igrf")
    bad = dict(extra, lat=np.where(np.arange(n) == 100, 95.0, extra["lat"]))
    with pytest.raises(MagcalError, match="column lat, data row 101"):
        resolve_vector_reference(ds.replace(extra=bad), "igrf")


@pytest.mark.parametrize("n_with", [0, 5, MIN_SAMPLES - 1])
def test_too_few_samples_with_attitude_is_one_clear_error(n_with):
    truth = vehicle_truth(seed=8)
    flight, _ = simulate_vehicle(truth, seed=8, n=1000)
    gap = np.ones(1000, bool)
    gap[500 : 500 + n_with] = False
    gappy = _without_attitude(flight, gap, "euler")
    with pytest.raises(MagcalError) as err:
        fit_vector(gappy, resolve_vector_reference(gappy), terms=[], warn=False)
    text = str(err.value)
    assert f"only {n_with} of 1000 samples have both an attitude and a reference field vector" in text
    assert f"({n_with} have an attitude, 1000 a reference)" in text and f"needs at least {MIN_SAMPLES}" in text
    assert ("no attitude in rows 1-1000" if n_with == 0 else f"no attitude in rows 1-500, {501 + n_with}-1000") in text


def test_the_held_out_check_scores_only_samples_with_attitude():
    truth = vehicle_truth(seed=12, current=True)
    flight, _ = simulate_vehicle(truth, seed=12, n=N)
    gappy = _without_attitude(flight, _gap(), "quaternion")
    v = validate_vector(gappy, resolve_vector_reference(gappy), terms=["current"])
    clean = validate_vector(flight, resolve_vector_reference(flight), terms=["current"])
    for got, ref in zip(v.rows, clean.rows):
        for k in ("in_vector_nT", "held_vector_nT", "in_total_nT", "held_total_nT"):
            assert np.isfinite(got[k]) and got[k] == pytest.approx(ref[k], rel=0.1)


def test_world_components_are_nan_only_where_the_attitude_is_missing():
    truth = vehicle_truth(n_sensors=4, seed=23)
    flight, tr = simulate_vehicle(truth, seed=23, n=1500, baseline_m=0.5)
    cal = fit_vector(flight, resolve_vector_reference(flight), terms=[], warn=False).calibration
    gap = _gap(1500, ((0, 20), (700, 703)))
    gappy = _without_attitude(flight, gap, "euler")
    world = cal.world(gappy)
    assert np.isnan(world[:, gap]).all() and np.isfinite(world[:, ~gap]).all()
    assert np.allclose(world[:, ~gap], cal.world(flight)[:, ~gap], atol=1e-6)
    g = cal.world_tensor(gappy)
    assert np.isnan(g[gap]).all() and np.allclose(g[~gap], cal.world_tensor(flight)[~gap], atol=1e-9)
    # the body-frame vectors need no attitude
    assert np.allclose(cal.correct(gappy), cal.correct(flight))


@settings(max_examples=60, deadline=None)
@given(st.lists(st.booleans(), min_size=1, max_size=60), st.integers(1, 5000))
def test_row_runs_are_the_flagged_rows(flags, first):
    mask = np.array(flags, bool)
    found = runs(mask, first_row=first)
    back = np.zeros(mask.size, bool)
    for a, b in found:
        assert a <= b
        back[a - first : b - first + 1] = True
    assert np.array_equal(back, mask)
    assert all(b + 1 < a2 for (_, b), (a2, _) in zip(found, found[1:]))  # runs are separated
    text = row_runs(mask, first_row=first)
    assert text == "no rows" if not mask.any() else text.startswith("row")


# --- magcal apply ---------------------------------------------------------------------------------------------------
def _write_euler_csv(path, ds, gap):
    cols = dataset_columns(_without_attitude(ds, gap, "euler"))
    write_csv(path, cols, dataset_metadata(ds))


@pytest.mark.parametrize("chunk_rows", ["20000", "16"])
def test_cli_apply_writes_body_columns_everywhere_and_nan_world_columns_on_rows_without_attitude(
    tmp_path, capsys, chunk_rows
):
    import pandas as pd

    truth = vehicle_truth(seed=11)
    one, _ = simulate_vehicle(truth, seed=11, n=1500, attitude_noise_deg=0.02)
    two, tr = simulate_vehicle(truth, seed=12, n=400, attitude_noise_deg=0.02)
    _write_euler_csv(tmp_path / "one.csv", one, _gap(1500, ((0, 100),)))  # the calibration flight has a gap too
    gap = _gap(400, ((0, 30), (200, 205)))
    _write_euler_csv(tmp_path / "two.csv", two, gap)
    cal_path, out = tmp_path / "cal.json", tmp_path / "out.csv"
    assert main(["calibrate", str(tmp_path / "one.csv"), "-o", str(cal_path), "--platform-terms", "none"]) == 0
    said = capsys.readouterr()
    assert "100 of 1500 samples have no attitude (rows 1-100) and were left out of the vector fit" in said.out
    argv = ["apply", str(cal_path), str(tmp_path / "two.csv"), "-o", str(out), "--chunk-rows", chunk_rows]
    assert main(argv) == 0
    err = capsys.readouterr().err
    line = "35 of 400 rows have no attitude (rows 1-30, 201-205): their world components (s1n_cal, s1e_cal, s1d_cal)"
    assert err.count("no attitude") == 1 and line in err
    frame = pd.read_csv(out, comment="#")
    assert len(frame) == 400
    body = frame[["s1x_cal", "s1y_cal", "s1z_cal"]].to_numpy()
    world = frame[["s1n_cal", "s1e_cal", "s1d_cal"]].to_numpy()
    cal = Calibration.load(cal_path)
    assert np.isfinite(body).all() and np.allclose(body, cal.correct(two)[0], atol=1e-3)
    assert np.isnan(world[gap]).all() and np.isfinite(world[~gap]).all()
    # the world components where the attitude is known: the field, to the attitude error's share (0.02 deg: 14 nT)
    assert np.sqrt(np.mean((world[~gap] - tr.field_ned_nT) ** 2)) < 25.0
    # a survey with every attitude: no note
    _write_euler_csv(tmp_path / "full.csv", two, np.zeros(400, bool))
    assert main(["apply", str(cal_path), str(tmp_path / "full.csv"), "-o", str(tmp_path / "full_out.csv")]) == 0
    assert "no attitude" not in capsys.readouterr().err


def test_apply_of_a_parquet_survey_has_the_same_nan_world_rows(tmp_path):
    pytest.importorskip("pyarrow")
    import pandas as pd

    from magcal.data import io as mio
    from magcal.output.apply import apply_file

    truth = vehicle_truth(seed=14)
    one, _ = simulate_vehicle(truth, seed=14, n=1200)
    two, _ = simulate_vehicle(truth, seed=15, n=300)
    cal = fit_vector(one, resolve_vector_reference(one), terms=[], warn=False).calibration
    gap = _gap(300, ((10, 20), (63, 70)))  # the second run across the first blocks' edge (64 rows each)
    gappy = _without_attitude(
        two, gap, "euler"
    )  # angles are extras to the readers (tests/data/test_attitude_gaps.py: qw..qz)
    mio.write_parquet(tmp_path / "two.parquet", dataset_columns(gappy), dataset_metadata(gappy))
    summary = apply_file(cal, tmp_path / "two.parquet", tmp_path / "out.parquet", chunk_rows=64)
    said = [n.text for n in summary.notes if n.is_a(DataWarning) and "no attitude" in n.text]
    assert len(said) == 1 and "17 of 300 rows have no attitude (rows 11-20, 64-70)" in said[0]
    frame = pd.read_parquet(tmp_path / "out.parquet")
    world = frame[["s1n_cal", "s1e_cal", "s1d_cal"]].to_numpy()
    assert np.isnan(world[gap]).all() and np.allclose(world[~gap], cal.world(two)[0][~gap], atol=1e-6)
    assert np.allclose(frame[["s1x_cal", "s1y_cal", "s1z_cal"]].to_numpy(), cal.correct(two)[0], atol=1e-6)


def test_attitude_rows_flags_zero_and_nan_quaternions():
    truth = vehicle_truth(seed=1)
    ds, _ = simulate_vehicle(truth, seed=1, n=50)
    q = np.array(ds.attitude_wxyz)
    q[3] = 0.0
    q[7, 2] = np.nan
    rotation, have = attitude_rows(ds.replace(attitude_wxyz=q))
    assert list(np.flatnonzero(~have)) == [3, 7] and len(rotation) == 50
    assert np.array_equal(attitude_present(ds.replace(attitude_wxyz=q)), have)
    gappy = _without_attitude(ds, ~have, "euler")
    assert np.array_equal(attitude_present(gappy), have) and np.array_equal(attitude_rows(gappy)[1], have)
    assert attitude_present(ds.replace(attitude_wxyz=None)) is None
    assert np.allclose(rotation[3].as_matrix(), np.eye(3))
    text = ds.replace(extra={**ds.extra, "roll_deg": np.array(["a"] * 50), "pitch_deg": q[:, 0], "yaw_deg": q[:, 0]})
    with pytest.raises(DatasetError, match="roll_deg must hold angles"):
        attitude_rows(text.replace(attitude_wxyz=None))


# --- the workbench's vector model -----------------------------------------------------------------------------------
def test_the_workbench_vector_fit_runs_on_a_record_with_attitude_gaps_and_says_so():
    from magcal_workbench.controller import Controller
    from magcal_workbench.vectorpanel import comparison_markdown

    flight, truth = simulate_vehicle(n=1500, seed=4, attitude_noise_deg=0.05)
    gap = _gap(1500, ((0, 120), (800, 810)))
    gappy = _without_attitude(flight, gap, "euler")
    ctrl = Controller(gappy)
    assert ctrl.vector.available and ctrl.vector.attitude_kind() == "euler"
    ctrl.state.selection.reject(np.arange(1400, 1500))  # the user's own rejection beside the gaps
    ctrl.step_vector()
    res = ctrl.vector.result
    kept = np.ones(1500, bool)
    kept[1400:] = False
    full = _euler(flight)  # the eddy term's rate is taken on the whole record: the clean samples under one mask
    _same_fit(res, fit_vector(full, resolve_vector_reference(full), mask=kept & ~gap, warn=False))
    row = ctrl.vector.vector_row()
    assert row.samples == "1270 of 1400 kept samples (130 without attitude left out)"
    # the world residual: NaN on the samples without attitude, at the attitude error's floor elsewhere
    assert ctrl.vector.world_nT.shape == (1, 1500, 3)
    assert np.isnan(ctrl.vector.world_nT[0, gap]).all() and np.isfinite(ctrl.vector.world_nT[0, ~gap]).all()
    floor = np.sqrt(2.0 / 3.0) * np.radians(0.05) * np.linalg.norm(truth.field_ned_nT)
    assert 0.8 * floor < float(np.sqrt(np.mean(row.world_rms_nT**2))) < 1.2 * floor
    table = comparison_markdown(ctrl.vector)
    assert "| samples fitted | - | 1270 of 1400 kept samples (130 without attitude left out) |" in table
    assert "130 of the 1400 selected samples have no attitude (rows 1-120, 801-810)" in table
    # the vehicle view at a sample without attitude draws nothing there, and says why
    assert ctrl.vector.current_vectors(5)["attitude_wxyz"] is None
    here = ctrl.vector.current_vectors(500)
    assert here["attitude_wxyz"] is not None and np.isfinite(here["measured_ned_nT"]).all()


def test_each_partition_of_a_parallel_apply_counts_its_rows_without_attitude(tmp_path):
    """``magcal apply --workers``: each task (:func:`magcal.output.survey.correct_partition`, run here in this
    process) writes NaN world columns on its rows without attitude and returns how many; the summary warns once."""
    pytest.importorskip("pyarrow")
    import pandas as pd

    from magcal.data import io as mio
    from magcal.output import survey

    truth = vehicle_truth(seed=14)
    one, _ = simulate_vehicle(truth, seed=14, n=1200)
    two, _ = simulate_vehicle(truth, seed=15, n=300)
    cal = fit_vector(one, resolve_vector_reference(one), terms=[], warn=False).calibration
    gap = _gap(300, ((10, 20), (140, 160)))
    gappy = _without_attitude(two, gap, "euler")
    mio.write_parquet(tmp_path / "two.parquet", dataset_columns(gappy), dataset_metadata(gappy))
    parts = survey.partitions([tmp_path / "two.parquet"], partition_rows=150)
    assert len(parts) == 2
    done = [survey.correct_partition(cal.to_dict(), p, str(tmp_path), "parquet", "apply") for p in parts]
    assert [d[1:] for d in done] == [(150, 20, ()), (150, 10, ())]  # rows, rows without attitude, reader's notes
    world = np.concatenate([pd.read_parquet(d[0])[["s1n_cal", "s1e_cal", "s1d_cal"]].to_numpy() for d in done])
    assert np.isnan(world[gap]).all() and np.allclose(world[~gap], cal.world(two)[0][~gap], atol=1e-6)
    # the whole parallel apply on a local cluster: one warning for the survey
    summary = survey.apply_partitioned(cal, [tmp_path / "two.parquet"], tmp_path / "parts", workers=1, progress=False)
    said = [n.text for n in summary.notes if "no attitude" in n.text]
    assert summary.rows == 300 and len(said) == 1 and said[0].startswith("30 of 300 rows have no attitude")


@pytest.mark.parametrize("route", ["parquet_out", "workers"])
def test_an_euler_csv_survey_gets_its_world_columns_by_every_route(tmp_path, route):
    """A CSV survey whose attitude is in roll_deg, pitch_deg, yaw_deg (extra channels to the CSV reader): applied
    to Parquet, and in partitions on a local cluster, the world columns are written as ``magcal apply`` to CSV
    writes them (NaN on rows without attitude), and the angle columns are carried as numbers."""
    pytest.importorskip("pyarrow")
    import pandas as pd

    from magcal.output.apply import apply_file

    truth = vehicle_truth(seed=16)
    one, _ = simulate_vehicle(truth, seed=16, n=1200)
    two, _ = simulate_vehicle(truth, seed=17, n=300)
    cal = fit_vector(one, resolve_vector_reference(one), terms=[], warn=False).calibration
    gap = _gap(300, ((5, 9),))
    _write_euler_csv(tmp_path / "two.csv", two, gap)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if route == "parquet_out":
            apply_file(cal, tmp_path / "two.csv", tmp_path / "out.parquet")
            frame = pd.read_parquet(tmp_path / "out.parquet")
        else:
            from magcal.output.survey import apply_partitioned

            summary = apply_partitioned(
                cal, [tmp_path / "two.csv"], tmp_path / "parts", workers=1, partition_rows=100, progress=False
            )
            frame = pd.concat([pd.read_parquet(f) for f in summary.files], ignore_index=True)
    world = frame[["s1n_cal", "s1e_cal", "s1d_cal"]].to_numpy()
    assert len(frame) == 300
    assert np.isnan(world[gap]).all() and np.allclose(world[~gap], cal.world(two)[0][~gap], atol=1e-3)
    assert frame["roll_deg"].dtype.kind == "f"
