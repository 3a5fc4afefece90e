"""Records whose attitude has gaps (a live recording's samples before its first ATTITUDE message, a gap in a log)
read, written and fitted as what they are: a sample whose four quaternion cells ``qw, qx, qy, qz`` are all empty
or ``nan`` has no attitude (as a row of NaN Euler angles has none); one with some but not all four, or a zero
quaternion, is refused naming the file, the line (or row) and the column.

Known truth: simulated vehicles (:func:`magcal.data.vehicle.simulate_vehicle`) and a four-sensor array in a site
gradient (:func:`magcal.data.simulation.simulate_timeseries`) whose parameters the tests set.
"""

from __future__ import annotations

import io as _stdio
import os
import shutil
import tempfile
import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magcal.checks.reference import resolve_vector_reference
from magcal.core.errors import DataWarning
from magcal.data import io as mio
from magcal.data.attitude import attitude_present
from magcal.data.dataset import DatasetError
from magcal.data.vehicle import simulate_vehicle, vehicle_truth
from magcal.fitting.vector import fit_vector


def _gappy(n=200, seed=3, runs=((0, 20), (100, 103))):
    """A simulated flight whose attitude is NaN on ``runs`` (0-based half-open), and the gap mask."""
    flight, _ = simulate_vehicle(vehicle_truth(seed=seed), seed=seed, n=n)
    gap = np.zeros(n, bool)
    for a, b in runs:
        gap[a:b] = True
    q = np.array(flight.attitude_wxyz)
    q[gap] = np.nan
    return flight.replace(attitude_wxyz=q), gap


def _read(path, how):
    """The file read by one of the readers' routes: pyarrow's CSV reader (a clean path), the line-by-line reader
    (a file object), small blocks, the Parquet reader."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", DataWarning)  # a gap is no problem: nothing to say
        if how == "path":
            return mio.read_csv(path)
        if how == "file object":
            with open(path, "rb") as fh:
                return mio.read_csv(fh, name=str(path))
        if how == "blocks of 7":
            return mio.read_csv(path, chunk_rows=7, drop_bad=True)  # drop_bad: the line reader, nothing dropped
        return mio.read_parquet(path)


def _same(a, b):
    assert np.array_equal(a.attitude_wxyz, b.attitude_wxyz, equal_nan=True)
    assert np.array_equal(a.readings_nT, b.readings_nT) and np.array_equal(a.time_s, b.time_s)
    for k in b.extra:
        assert np.array_equal(a.extra[k], b.extra[k], equal_nan=True)


# --- reading and writing -------------------------------------------------------------------------------------------
@pytest.mark.parametrize("how", ["path", "file object", "blocks of 7", "parquet"])
def test_a_dataset_with_attitude_gaps_reads_back_equal_from_the_engines_writers(tmp_path, how):
    if how == "parquet":
        pytest.importorskip("pyarrow")
    ds, gap = _gappy()
    path = tmp_path / ("d.parquet" if how == "parquet" else "d.csv")
    (mio.write_parquet if how == "parquet" else mio.write_csv)(path, ds)
    back = _read(path, how)
    _same(back, ds)
    assert np.array_equal(attitude_present(back), ~gap)


@settings(max_examples=25, deadline=None)
@given(st.lists(st.booleans(), min_size=2, max_size=40), st.sampled_from(["csv", "parquet"]))
def test_any_pattern_of_gaps_round_trips(flags, fmt):
    if fmt == "parquet":
        pytest.importorskip("pyarrow")
    gap = np.array(flags, bool)
    flight, _ = simulate_vehicle(vehicle_truth(seed=1), seed=1, n=gap.size)
    q = np.array(flight.attitude_wxyz)
    q[gap] = np.nan
    ds = flight.replace(attitude_wxyz=q)
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, f"d.{fmt}")
        (mio.write_parquet if fmt == "parquet" else mio.write_csv)(path, ds)
        back = mio.read_parquet(path) if fmt == "parquet" else mio.read_csv(path)
    _same(back, ds)


@pytest.mark.parametrize("how", ["path", "file object", "blocks of 7"])
def test_empty_quaternion_cells_mean_no_attitude_as_nan_ones_do(tmp_path, how):
    ds, gap = _gappy(n=60, runs=((0, 5), (30, 33), (59, 60)))
    mio.write_csv(tmp_path / "nan.csv", ds)
    text = (tmp_path / "nan.csv").read_text()
    assert text.count(",nan,nan,nan,nan") == gap.sum()
    blank = text.replace(",nan,nan,nan,nan", ",,,,", 4).replace(",nan,nan,nan,nan", ",NaN, ,nan,", 1)
    (tmp_path / "blank.csv").write_text(blank)
    back = _read(tmp_path / "blank.csv", how)
    _same(back, ds)
    # a DataFrame with missing attitude takes the same reader
    pd = pytest.importorskip("pandas")
    from magcal.data.inputs import as_dataset

    frame = pd.read_csv(_stdio.StringIO(blank), comment="#")
    _same(as_dataset(frame), ds.replace(metadata={}))


def _row_line(path, row):
    """The file's 1-based line of 0-based data row ``row``."""
    lines = path.read_text().splitlines()
    header = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    return header + 2 + row


@pytest.mark.parametrize(
    "missing, named, given_",
    [(["qx"], "qx", "qw, qy, qz hold"), (["qw", "qz"], "qw", "qx, qy hold"), (["qx", "qy", "qz"], "qx", "qw holds")],
)
def test_some_but_not_all_quaternion_cells_missing_is_refused_naming_line_and_column(tmp_path, missing, named, given_):
    ds, gap = _gappy(n=50, runs=((0, 3),))
    cols = mio.dataset_columns(ds)
    cols = {k: np.array(v, dtype=float if k != "group" else None) for k, v in cols.items()}
    for c in missing:
        cols[c][17] = np.nan
    path = tmp_path / "partial.csv"
    mio.write_csv(path, cols, mio.dataset_metadata(ds))
    line = _row_line(path, 17)
    for how in ("path", "file object"):
        with pytest.raises(DatasetError) as err:
            _read(path, how)
        text = str(err.value)
        assert text.startswith(f"{path}: 1 row(s) with bad values: line {line}, column {named}: empty or nan while")
        assert f"{given_} a number; give all four of qw,qx,qy,qz, or leave all four empty" in text
    # --drop-bad drops that row alone, saying so; the rows without attitude stay
    kept = mio.read_csv(path, drop_bad=True, warn=False)
    notes = kept.notes
    assert kept.n_samples == 49 and np.array_equal(attitude_present(kept), ~np.delete(gap, 17))
    assert any(f"dropped 1 row(s) with bad values: line {line}, column {named}" in n.text for n in notes)
    # Parquet: the row (1-based) and the column
    pytest.importorskip("pyarrow")
    mio.write_parquet(tmp_path / "partial.parquet", cols, mio.dataset_metadata(ds))
    with pytest.raises(DatasetError, match=rf"partial\.parquet: row 18, column {named}: empty or nan while"):
        mio.read_parquet(tmp_path / "partial.parquet")


def test_a_zero_or_infinite_quaternion_is_still_refused_and_a_long_one_normalised(tmp_path):
    ds, _ = _gappy(n=30, runs=((0, 2),))
    cols = {k: np.array(v, dtype=float) for k, v in mio.dataset_columns(ds).items()}
    for c in ("qw", "qx", "qy", "qz"):
        cols[c][9] = 0.0
    mio.write_csv(tmp_path / "zero.csv", cols)
    with pytest.raises(DatasetError, match=rf"zero\.csv: line {_row_line(tmp_path / 'zero.csv', 9)}: .* is zero"):
        mio.read_csv(tmp_path / "zero.csv")
    cols["qw"][9], cols["qx"][9] = np.inf, 0.5
    mio.write_csv(tmp_path / "inf.csv", cols)
    with pytest.raises(DatasetError, match=r"column qw: 'inf' is not a finite number"):
        mio.read_csv(tmp_path / "inf.csv")
    cols["qw"][9], cols["qx"][9], cols["qy"][9], cols["qz"][9] = 2.0, 0.0, 0.0, 0.0
    mio.write_csv(tmp_path / "long.csv", cols)
    with pytest.warns(DataWarning, match=r"not unit length \(line \d+: \|q\| = 2\); they are normalised"):
        back = mio.read_csv(tmp_path / "long.csv")
    assert np.allclose(back.attitude_wxyz[9], [1, 0, 0, 0]) and np.isnan(back.attitude_wxyz[:2]).all()


def test_the_vector_fit_of_a_file_with_attitude_gaps_is_the_fit_of_its_samples_with_attitude(tmp_path):
    ds, gap = _gappy(n=1500, seed=9, runs=((0, 150), (700, 720)))
    mio.write_csv(tmp_path / "flight.csv", ds)
    back = mio.read_csv(tmp_path / "flight.csv")
    got = fit_vector(back, resolve_vector_reference(back), terms=[], warn=False)
    clean = ds.subset(~gap)
    ref = fit_vector(clean, resolve_vector_reference(clean), terms=[], warn=False)
    assert np.array_equal(got.fitted, ~gap) and got.gaps.n_without_attitude == 170
    for a, b in zip(got.sensors, ref.sensors):
        assert np.allclose(a.W, b.W, rtol=1e-9) and np.allclose(a.bias_nT, b.bias_nT, atol=1e-6)


# --- site_gradient on samples without attitude ---------------------------------------------------------------------
SITE_G = 20.0  # nT/m; the truth is SITE_G * SiteGradient.pattern


@pytest.fixture(scope="module")
def site():
    """A four-sensor cross in a site gradient (known G), and the same record with attitude gaps."""
    from magcal.data.simulation import chi2017_truth, simulate_timeseries
    from magcal.model.terms import EFFECTS

    effect = EFFECTS["site_gradient"]()
    ds = simulate_timeseries(
        chi2017_truth(4), n_samples=1200, noise_nT=2.0, seed=7, perturbations=[effect.perturbation(SITE_G)]
    )
    gap = np.zeros(ds.n_samples, bool)
    gap[:100] = True
    gap[500:520] = True
    gap[::9] = True  # scattered dropouts too
    q = np.array(ds.attitude_wxyz)
    q[gap] = np.nan
    return ds, ds.replace(attitude_wxyz=q), gap, effect.true_params(SITE_G)


def _gradient(result):
    entry = next(e for e in result.effect_params if e["effect"] == "site_gradient")
    return np.array(list(entry["params"].values())), np.array(list(entry["std"].values()))


def test_site_gradient_fits_the_samples_with_attitude_and_finds_the_truth(site):
    from magcal.core.errors import MagcalError
    from magcal.fitting.fitter import fit
    from magcal.model.terms import Model

    clean, gappy, gap, truth = site
    model = Model.from_names(["site_gradient"], 4)
    with pytest.warns(DataWarning, match=r"samples have no attitude \(rows 1-100, 109, 118 and \d+ more runs\)"):
        got = fit(gappy, model)
    g, sd = _gradient(got)
    assert np.all(np.abs(g - truth) < 4.0 * sd), (g, sd, truth)  # the truth, within the standard errors
    # exactly the fit of the samples with attitude, and the fit says which samples those were
    ref = fit(clean, model, mask=~gap)
    assert np.array_equal(got.mask, ~gap)
    assert np.allclose(got.x, ref.x, rtol=1e-9, atol=1e-9) and got.rss == pytest.approx(ref.rss, rel=1e-12)
    note = next(n for n in fit(gappy, model, warn=False).notes if n.is_a(DataWarning))
    n_gap = int(gap.sum())
    assert note.text.startswith(f"{n_gap} of 1200 samples have no attitude (rows 1-100, 109, 118")
    assert note.text.endswith(
        f"left out of the fit: site_gradient needs each sample's attitude ({1200 - n_gap} samples fitted)"
    )
    # the user's own mask counts "of the selected"
    mask = np.ones(1200, bool)
    mask[:50] = False
    sel = next(n for n in fit(gappy, model, mask=mask, warn=False).notes if n.is_a(DataWarning)).text
    assert sel.startswith(f"{int((gap & mask).sum())} of the 1150 selected samples have no attitude (rows 51-100, 109")
    # the old behaviour (the identity for a missing attitude) was tens of standard errors off: the test can fail
    from magcal.data.attitude import filled_wxyz

    wrong = fit(gappy.replace(attitude_wxyz=filled_wxyz(gappy.attitude_wxyz)[0]), model)
    assert np.max(np.abs(_gradient(wrong)[0] - truth) / sd) > 10.0
    # no sample with attitude: one clear error
    with pytest.raises(MagcalError, match="none of the 100 chosen samples has an attitude"):
        fit(gappy, model, mask=gap & (np.arange(1200) < 100))
    # the base model needs no attitude: every sample is fitted, nothing said
    with warnings.catch_warnings():
        warnings.simplefilter("error", DataWarning)
        assert fit(gappy, Model.base_model(4)).mask.all()


def test_without_attitude_the_site_gradient_predicts_nothing_rather_than_a_wrong_field(site):
    from magcal.model.terms import EFFECTS, contexts

    clean, gappy, gap, truth = site
    effect = EFFECTS["site_gradient"]()
    for ctx_clean, ctx in zip(contexts(clean, clean.baseline_m), contexts(gappy, gappy.baseline_m)):
        basis = effect.array_basis(None, ctx)
        assert np.isnan(basis[gap]).all()
        assert np.array_equal(basis[~gap], effect.array_basis(None, ctx_clean)[~gap])
        assert np.array_equal(ctx.attitude_present, ~gap)


def test_calibrate_correct_and_apply_leave_rows_without_attitude_out_and_say_it_once(site, tmp_path, capsys):
    from magcal.cli import main
    from magcal.fitting.pipeline import calibrate

    clean, gappy, gap, truth = site
    res = calibrate(gappy, effects=["site_gradient"])
    n_gap = int(gap.sum())
    said = [w for w in res.remarks if "no attitude" in w]
    assert len(said) == 1 and said[0].startswith(f"{n_gap} of 1200 samples have no attitude (rows 1-100, 109")
    assert "left out of the calibration: site_gradient needs each sample's attitude" in said[0]
    assert np.array_equal(res.fit.mask, ~gap)
    g, sd = _gradient(res.fit)
    assert np.all(np.abs(g - truth) < 4.0 * sd)
    # correcting the record: NaN where the term cannot act, with a note; dropping the term corrects every row
    cal = res.calibration
    with pytest.warns(
        DataWarning, match=f"{n_gap} of 1200 samples have no attitude .*: site_gradient cannot be applied"
    ):
        v = cal.correct(gappy, record_terms="apply")
    assert np.isnan(v[:, gap]).all() and np.isfinite(v[:, ~gap]).all()
    assert np.allclose(v[:, ~gap], cal.correct(clean, record_terms="apply")[:, ~gap])
    assert np.isfinite(cal.correct(gappy, record_terms="drop")).all()
    # magcal apply on the fitted record, in blocks: one note over the whole file, rows counted in the file
    mio.write_csv(tmp_path / "rec.csv", gappy)
    cal.save(tmp_path / "cal.json")
    out = tmp_path / "out.csv"
    argv = ["apply", str(tmp_path / "cal.json"), str(tmp_path / "rec.csv"), "-o", str(out), "--chunk-rows", "300"]
    assert main(argv) == 0
    err = capsys.readouterr().err
    texts = [line for line in err.splitlines() if "no attitude" in line]
    assert len(texts) == 1 and f"{n_gap} of 1200 rows have no attitude (rows 1-100, 109, 118" in texts[0]
    assert "site_gradient cannot be applied to them, so their corrected columns (s1x_cal" in texts[0]
    frame = pytest.importorskip("pandas").read_csv(out, comment="#")
    body = frame[[f"s{s}{a}_cal" for s in range(1, 5) for a in "xyz"]].to_numpy()
    assert np.isnan(body[gap]).all() and np.isfinite(body[~gap]).all()


def test_the_diagnosis_does_not_test_site_gradient_on_samples_without_attitude_and_says_why(site):
    from magcal.diagnosis import diagnose

    clean, gappy, gap, _ = site
    assert diagnose(clean).candidates[0].effect == "site_gradient"  # found where every sample has an attitude
    d = diagnose(gappy)
    assert "site_gradient" not in {c.effect for c in d.candidates}
    line = next(w for w in d.warnings if "no attitude" in w)
    assert line.startswith(f"{int(gap.sum())} of the 1200 samples fitted have no attitude (rows 1-100, 109")
    assert "site_gradient was not tested" in line and "exclude those samples to test it" in line
    # excluded, it is tested again, and found
    sub = gappy.subset(~gap)
    assert diagnose(sub).candidates[0].effect == "site_gradient"


def test_the_workbench_fits_site_gradient_on_a_record_with_gaps_and_draws_every_sample(site):
    from magcal_workbench import scene as scn
    from magcal_workbench.controller import Controller

    clean, gappy, gap, truth = site
    ctrl = Controller(gappy)
    ctrl.state.effects = ["site_gradient"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # what the steps say goes to the page, not to the server's stderr
        ctrl.step_calibrate()
        ctrl.step_refine()
    n_gap = int(gap.sum())
    assert f"{n_gap} of 1200 samples have no attitude (rows 1-100, 109" in ctrl.message
    assert np.array_equal(ctrl.fit_result.mask, ~gap)
    g, sd = _gradient(ctrl.fit_result)
    assert np.all(np.abs(g - truth) < 4.0 * sd)
    # the corrected vectors: NaN where the term cannot act; the figures over the others
    assert np.isnan(ctrl.corrected_nT[:, gap]).all() and np.isfinite(ctrl.corrected_nT[:, ~gap]).all()
    assert np.isfinite(ctrl.residual_rms_nT()) and ctrl.residual_rms_nT() < 2.2
    # the scene gets a finite position for every sample (a NaN one spoils the cloud's bounds in the browser)
    views = [
        scn.SensorView(
            sensor=s,
            raw_nT=gappy.readings_nT[s],
            corrected_nT=ctrl.corrected_nT[s],
            residual_nT=ctrl.residual_nT[s],
            cinv=ctrl.calibration.sensors[s].cinv,
            bias_nT=ctrl.calibration.sensors[s].bias_nT,
            R=ctrl.calibration.sensors[s].R,
        )
        for s in range(4)
    ]
    model = scn.SceneModel(sensors=views, n_sensors=4, field_nT=ctrl.field_nT, kept=ctrl.state.kept)
    for name, _, _kind, positions in scn.layout(model):
        assert positions.shape == (1200, 3) and np.isfinite(positions).all(), name


# --- a recording with attitude gaps, end to end ---------------------------------------------------------------------
def test_magcal_calibrate_and_apply_run_on_a_csv_whose_quaternions_have_gaps(tmp_path, capsys):
    """The file the engine's writers make of a recording with gaps (NaN quaternion rows) through the commands a
    user runs: the vector fit leaves those samples out and says which; apply writes NaN world columns there."""
    from magcal.calibration.calibration import Calibration
    from magcal.cli import main

    truth = vehicle_truth(seed=21)
    one, _ = simulate_vehicle(truth, seed=21, n=1500, attitude_noise_deg=0.02)
    two, tr = simulate_vehicle(truth, seed=22, n=400, attitude_noise_deg=0.02)
    gap_one, gap_two = np.zeros(1500, bool), np.zeros(400, bool)
    gap_one[:120], gap_two[:25], gap_two[300:304] = True, True, True
    for ds, gap, name in ((one, gap_one, "one.csv"), (two, gap_two, "two.csv")):
        q = np.array(ds.attitude_wxyz)
        q[gap] = np.nan
        mio.write_csv(tmp_path / name, ds.replace(attitude_wxyz=q))
    text = (tmp_path / "one.csv").read_text()
    (tmp_path / "one.csv").write_text(text.replace(",nan,nan,nan,nan,", ",,,,,"))  # empty cells read the same
    cal_path = tmp_path / "cal.json"
    argv = ["calibrate", str(tmp_path / "one.csv"), "--mode", "vector", "--platform-terms", "none", "-o", str(cal_path)]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "120 of 1500 samples have no attitude (rows 1-120) and were left out of the vector fit" in out
    cal = Calibration.load(cal_path)
    assert cal.mode == "vector"
    s, t = cal.sensors[0], truth.sensors[0]
    assert np.degrees(np.arccos(np.clip((np.trace(s.R @ t.mounting.T) - 1) / 2, -1, 1))) < 0.02
    assert main(["apply", str(cal_path), str(tmp_path / "two.csv"), "-o", str(tmp_path / "out.csv")]) == 0
    err = capsys.readouterr().err
    assert "29 of 400 rows have no attitude (rows 1-25, 301-304): their world components (s1n_cal" in err
    frame = pytest.importorskip("pandas").read_csv(tmp_path / "out.csv", comment="#")
    world = frame[["s1n_cal", "s1e_cal", "s1d_cal"]].to_numpy()
    assert np.isnan(world[gap_two]).all() and np.isfinite(world[~gap_two]).all()
    assert np.sqrt(np.mean((world[~gap_two] - tr.field_ned_nT) ** 2)) < 25.0  # 0.02 deg of 50 uT: 14 nT


def _gappy_vehicle(n=600):
    flight, truth = simulate_vehicle(n=n, seed=4, attitude_noise_deg=0.05)
    gap = np.zeros(n, bool)
    gap[:60] = True
    gap[400:410] = True
    q = np.array(flight.attitude_wxyz)
    q[gap] = np.nan
    return flight.replace(attitude_wxyz=q), gap


def test_the_workbench_opens_a_file_with_quaternion_gaps_and_runs_the_vector_fit(bench):
    ds, gap = _gappy_vehicle()
    wb = bench(ds=ds)  # written as CSV, opened as the page opens an upload
    assert np.array_equal(attitude_present(wb.ctrl.dataset), ~gap)
    p = wb.panels.vector_panel
    assert p.btn_vector.visible and "quaternions" in p.info.content
    wb.ctrl.step_vector()
    assert "530 of 600 kept samples (70 without attitude left out)" in p.table.content
    assert "70 of 600 samples have no attitude (rows 1-60, 401-410)" in p.table.content


@pytest.mark.e2e
@pytest.mark.slow
def test_the_vector_fit_button_on_a_recording_with_quaternion_gaps_in_the_page(browser, bench, tmp_path):
    """In Chromium: the vector fit button on a file whose quaternions have gaps gives the fit and says how many
    samples it left out."""
    from tests.workbench.test_workbench_e2e import _dismiss_toasts, _open

    ds, gap = _gappy_vehicle()
    wb = bench(ds=ds, max_points=300)
    page = _open(browser, wb)
    page.get_by_role("button", name="Run the vector fit (attitude-aided)").click()
    page.wait_for_function("() => document.body.innerText.includes('deg off it')", timeout=120_000)
    text = page.inner_text("body", timeout=120_000)
    assert "70 without attitude left out" in text and "world N RMS" in text
    _dismiss_toasts(page)
    shot = tmp_path / "vector_gaps.png"
    page.screenshot(path=str(shot), timeout=120_000)
    if os.environ.get("MAGCAL_KEEP_SHOT"):
        shutil.copy(shot, os.environ["MAGCAL_KEEP_SHOT"])
    assert shot.stat().st_size > 10_000
    page.close()


def test_the_tilt_ring_and_the_turn_rate_read_a_record_with_quaternion_gaps(tmp_path):
    from magcal.data.attitude import turn_rate_dps
    from magcal_workbench.view import ring_directions

    ds, gap = _gappy_vehicle()
    mio.write_csv(tmp_path / "d.csv", ds)
    back = mio.read_csv(tmp_path / "d.csv")
    rate = turn_rate_dps(back)
    assert np.isfinite(rate).all() and np.all(rate[gap] == 0.0) and rate[~gap].max() > 1.0
    corrected = back.readings_nT[0]  # directions enough for the ring's inclination
    ring = ring_directions(back, corrected, 200)  # a sample with attitude: the yaw sweep at its tilt
    assert ring is not None and np.isfinite(ring).all() and np.allclose(np.linalg.norm(ring, axis=1), 1.0)
    gap_ring = ring_directions(back, corrected, 405)  # without: the latest directions' circle, if any
    assert gap_ring is None or np.isfinite(gap_ring).all()


def test_a_recording_no_attitude_reached_gets_the_total_field_fit_unless_vector_is_asked(tmp_path, capsys):
    from magcal.cli import main
    from magcal.core.errors import MagcalError

    flight, _ = simulate_vehicle(vehicle_truth(seed=5), seed=5, n=400)
    mio.write_csv(tmp_path / "none.csv", flight.replace(attitude_wxyz=np.full((400, 4), np.nan)))
    assert main(["calibrate", str(tmp_path / "none.csv"), "-o", str(tmp_path / "cal.json")]) == 0
    assert "the attitude columns are empty on every row (no sample has an attitude): the total-field fit" in (
        capsys.readouterr().err
    )
    from magcal.calibration.calibration import Calibration

    assert Calibration.load(tmp_path / "cal.json").mode == "scalar"
    assert main(["calibrate", str(tmp_path / "none.csv"), "--mode", "vector", "-o", str(tmp_path / "v.json")]) == 2
    assert "only 0 of 400 samples have both an attitude and a reference field vector" in capsys.readouterr().err
    with pytest.raises(MagcalError, match="only 0 of 400"):
        back = mio.read_csv(tmp_path / "none.csv")
        fit_vector(back, resolve_vector_reference(back), terms=[], warn=False)


# --- flight logs: samples far from any attitude message -------------------------------------------------------------
@pytest.mark.parametrize("kind", ["dataflash", "ulog"])
def test_a_log_s_samples_far_from_any_attitude_message_have_none(tmp_path, kind):
    """Before the first attitude message, after the last and in a long gap the attitude was held or interpolated
    across whatever the vehicle did meanwhile; now those samples have none (NaN), a note says which, and short gaps
    are still interpolated. Known truth: the logs of tests/data/test_logs.py (one attitude per magnetometer sample)."""
    pytest.importorskip("pymavlink")
    pytest.importorskip("pyulog")
    from magcal.data.logs import LOG_ATTITUDE_HOLD_S, read_log
    from tests.data.test_logs import ardupilot_case, px4_case, write_dataflash, write_ulog

    # samples every 20 ms (DataFlash) or 10 ms... the attitude messages of samples `drop` are left out
    if kind == "dataflash":
        messages, _, att, _ = ardupilot_case(n=400, compasses=1)
        step = 0.02
        att_at = [i for i, m in enumerate(messages) if m[0] == "ATT"]
    else:
        topics, _, att, _, _ = px4_case(n=400)
        step = float(np.median(np.diff([r[0] for r in topics[0][3]]))) * 1e-6
    n = 400
    head = int(round(1.5 / step))  # no attitude for the first 1.5 s
    long_gap = np.arange(200, 200 + int(round(1.2 / step)))  # 1.2 s without: longer than the limit
    short_gap = np.arange(340, 340 + int(round(0.2 / step)))  # 0.2 s: interpolated across
    drop = set(range(head)) | set(long_gap.tolist()) | set(short_gap.tolist())
    if kind == "dataflash":
        messages = [m for i, m in enumerate(messages) if not (m[0] == "ATT" and att_at.index(i) in drop)]
        path = tmp_path / "gaps.bin"
        write_dataflash(path, messages)
    else:
        name, multi, fields, rows = topics[1]
        topics[1] = (name, multi, fields, [r for i, r in enumerate(rows) if i not in drop])
        path = tmp_path / "gaps.ulg"
        write_ulog(path, topics)
    ds = read_log(path, warn=False)
    notes = ds.notes
    assert ds.n_samples == n
    have = attitude_present(ds)
    t = ds.time_s
    t_att = t[np.setdiff1d(np.arange(n), sorted(drop))]  # (within 2 ms) the attitude messages' times
    t_att = t_att - (0.002 if kind == "ulog" else 0.0)
    nearest = np.min(np.abs(t[:, None] - t_att[None, :]), axis=1)
    expected = nearest <= LOG_ATTITUDE_HOLD_S + 1e-6
    expected[short_gap] = True  # spanned by messages 0.2 s apart: interpolated
    assert np.array_equal(have, expected), (np.flatnonzero(have != expected), step)
    assert have[short_gap].all() and not have[: head - int(round(0.25 / step))].any() and have[head - 3 : head].all()
    m = int(round(0.25 / step))
    assert not have[long_gap[m:-m]].any() and have[long_gap[:3]].all()
    said = [x.text for x in notes if "no attitude" in x.text]
    assert len(said) == 1 and said[0].startswith(
        f"{path}: {int((~expected).sum())} of {n} magnetometer samples (rows 1-"
    )
    assert (
        "lie more than 0.2 s from any attitude message, before the first, after the last or in a gap of more"
        in (said[0])
    )
    if kind == "dataflash":  # a sample with its own message has the logged attitude; the logged angles agree
        own = np.setdiff1d(np.arange(head, n), np.concatenate([long_gap, short_gap]))
        q = ds.attitude_wxyz[own]
        from scipy.spatial.transform import Rotation

        got = Rotation.from_quat(np.column_stack([q[:, 1:], q[:, :1]]))
        assert np.degrees(np.max((got * att[own].inv()).magnitude())) < 0.01
        assert np.isnan(ds.extra["att_roll_deg"][~expected]).all()
        assert np.isfinite(ds.extra["att_roll_deg"][expected]).all()
    # written and read back as CSV, the gaps stay gaps
    mio.write_csv(tmp_path / "log.csv", ds)
    _same(mio.read_csv(tmp_path / "log.csv"), ds)


def test_parquet_null_quaternion_cells_from_another_tool_mean_no_attitude(tmp_path):
    pa = pytest.importorskip("pyarrow")
    import pyarrow.parquet as pq

    ds, gap = _gappy(n=40, runs=((3, 6),))
    cols = mio.dataset_columns(ds)
    table = pa.table(
        {
            k: pa.array(np.asarray(v, float), from_pandas=True) if k in ("qw", "qx", "qy", "qz") else v
            for k, v in cols.items()
        }
    )
    assert table.column("qx").null_count == 3  # NaN written as null, as pandas and others do
    pq.write_table(table, tmp_path / "nulls.parquet")
    back = mio.read_parquet(tmp_path / "nulls.parquet")
    assert np.array_equal(attitude_present(back), ~gap)
    # a null in a reading is still refused, naming the row and the column
    table = table.set_column(table.schema.get_field_index("s1y"), "s1y", pa.array([None] + list(cols["s1y"][1:])))
    pq.write_table(table, tmp_path / "bad.parquet")
    with pytest.raises(DatasetError, match=r"bad\.parquet: row 1, column s1y: nan is NaN"):
        mio.read_parquet(tmp_path / "bad.parquet")
