"""magcal.output.apply: streaming survey correction, tensor invariants, and calibration files that load or say why not."""

import json
import re
import tracemalloc
import warnings

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from magcal.calibration.calibration import Calibration, SensorCalibration
from magcal.cli import main
from magcal.core import conventions
from magcal.core.errors import DataWarning, MagcalError, RecordTermWarning
from magcal.data import io
from magcal.data import simulation as sim
from magcal.data.dataset import DatasetError
from magcal.fitting import platform as pf
from magcal.fitting.fitter import fit
from magcal.model.terms import EFFECTS, Model
from magcal.output import apply as ap
from tests.helpers import line_ends


def exact_calibration(truth, frame="platform"):
    """The true calibration: C^-1, b and R (sensor frame -> array/platform frame) of every sensor."""
    return Calibration(
        [SensorCalibration(s.Cinv, s.bias_nT, s.R) for s in truth.sensors],
        reference_total_nT=truth.total_nT,
        baseline_m=truth.baseline_m,
        frame=frame,
    )


@pytest.fixture(scope="module")
def truth():
    return pf.platform_truth()


@pytest.fixture(scope="module")
def survey(tmp_path_factory, truth):
    ds = sim.simulate_timeseries(truth, n_samples=300, noise_nT=0.0, seed=3)
    ds = ds.replace(extra={"line_id": np.repeat(["L1", "L2,b"], 150), "alt_m": np.linspace(10, 20, 300)})
    path = tmp_path_factory.mktemp("apply") / "survey.csv"
    io.write_csv(path, ds)
    return path, ds


def read_out(path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DataWarning)
        return io.read_csv(path)


def test_corrected_columns_are_the_platform_field(tmp_path, truth, survey):
    path, ds = survey
    out = tmp_path / "out.csv"
    summary = ap.apply_file(exact_calibration(truth), path, out)
    assert summary.rows == 300
    res = read_out(out)
    q = ds.attitude_wxyz
    b_platform = Rotation.from_quat(np.column_stack([q[:, 1:], q[:, :1]])).inv().apply(truth.field_world_nT)
    for s in range(4):
        got = np.column_stack([res.extra[f"s{s + 1}{a}_cal"] for a in "xyz"])
        np.testing.assert_allclose(got, b_platform, atol=6e-4)  # written to 1 pT
    # a uniform field has no gradient: the tensor is zero to the output rounding
    for c in ap.TENSOR_COLUMNS:
        assert np.max(np.abs(res.extra[c])) < 5e-3
    assert "# magcal_frame: platform" in out.read_text()


def test_every_input_line_is_copied_unchanged(tmp_path, truth, survey):
    path, _ = survey
    out = tmp_path / "out.csv"
    ap.apply_file(exact_calibration(truth), path, out)
    src = [line for line in path.read_text().splitlines() if not line.startswith("#")]
    dst = [line for line in out.read_text().splitlines() if not line.startswith("#")]
    assert len(src) == len(dst)
    n_new = len(ap.output_columns(4, True))
    for a, b in zip(src, dst):
        assert b.startswith(a + ",") and b.count(",") == a.count(",") + n_new
    meta_in = [line for line in path.read_text().splitlines() if line.startswith("#")]
    assert meta_in == [line for line in out.read_text().splitlines() if line.startswith("#")][: len(meta_in)]


def test_values_match_the_calibration_object_and_tensor(tmp_path, truth, survey):
    path, ds = survey
    rng = np.random.default_rng(0)
    noisy = ds.replace(readings_nT=ds.readings_nT + rng.normal(0, 3, ds.readings_nT.shape))
    io.write_csv(tmp_path / "noisy.csv", noisy)
    cal = exact_calibration(truth)
    ap.apply_file(cal, tmp_path / "noisy.csv", tmp_path / "out.csv")
    res = read_out(tmp_path / "out.csv")
    vec = cal.correct(noisy)
    for s in range(4):
        for k, a in enumerate("xyz"):
            np.testing.assert_allclose(res.extra[f"s{s + 1}{a}_cal"], vec[s, :, k], atol=6e-4)
    comps = conventions.tensor_components(vec, 0.5)
    for c in ap.TENSOR_COLUMNS:
        np.testing.assert_allclose(res.extra[c], comps[c], atol=6e-4)
    # noise-only tensor: RMS at the floor sqrt(2) sigma / d (Gzz 2 sigma / d)
    floor = conventions.tensor_floor_nT_per_m(3.0, 0.5)
    for c in ("Gxx", "Gyy", "Gzz"):
        assert np.sqrt(np.mean(res.extra[c] ** 2)) == pytest.approx(floor[c], rel=0.2)
    i0, i1, i2 = ap.tensor_invariants(conventions.tensor_matrix(comps))
    np.testing.assert_allclose(res.extra["I0"], 0.0, atol=1e-9)  # eq. (1)'s Gzz makes the trace vanish
    np.testing.assert_allclose(res.extra["I1"], i1, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(res.extra["I2"], i2, rtol=1e-6, atol=1e-6)


def test_invariants_are_invariant_and_match_eigenvalues():
    rng = np.random.default_rng(1)
    a = rng.normal(0, 50, (20, 3, 3))
    g = a + np.swapaxes(a, 1, 2)
    g -= np.trace(g, axis1=1, axis2=2)[:, None, None] * np.eye(3) / 3
    i0, i1, i2 = ap.tensor_invariants(g)
    lam = np.linalg.eigvalsh(g)
    np.testing.assert_allclose(i0, 0, atol=1e-9)
    np.testing.assert_allclose(i1, lam[:, 0] * lam[:, 1] + lam[:, 1] * lam[:, 2] + lam[:, 0] * lam[:, 2], rtol=1e-9)
    np.testing.assert_allclose(i2, lam.prod(axis=1), rtol=1e-9)
    q = Rotation.random(20, random_state=rng).as_matrix()
    rotated = q @ g @ np.swapaxes(q, 1, 2)
    for x, y in zip(ap.tensor_invariants(rotated), (i0, i1, i2)):
        np.testing.assert_allclose(x, y, rtol=1e-9, atol=1e-6)


@pytest.mark.parametrize("chunk_rows", [3, 7, 100_000])
def test_output_does_not_depend_on_the_chunk_size(tmp_path, truth, survey, chunk_rows):
    path, _ = survey
    ap.apply_file(exact_calibration(truth), path, tmp_path / "a.csv", chunk_rows=100_000)
    ap.apply_file(exact_calibration(truth), path, tmp_path / "b.csv", chunk_rows=chunk_rows)
    a, b = (tmp_path / "a.csv").read_text().splitlines(), (tmp_path / "b.csv").read_text().splitlines()
    assert len(a) == len(b)
    for la, lb in zip(a, b):  # identical text except the last digits of rounding-level invariants (~1e-21)
        ca, cb = la.split(","), lb.split(",")
        assert ca[:-2] == cb[:-2]
        if not la.startswith("#") and ca[-1] != "I2":
            np.testing.assert_allclose(np.array(ca[-2:], float), np.array(cb[-2:], float), atol=1e-12)


def test_single_sensor_gets_only_its_columns(tmp_path):
    truth = sim.chi2017_truth()
    one = sim.ArrayTruth(truth.sensors[:1])
    ds = sim.simulate(one, n_samples=50, seed=2)
    io.write_csv(tmp_path / "one.csv", ds)
    cal = Calibration([SensorCalibration(one.sensors[0].Cinv, one.sensors[0].bias_nT)], reference_total_nT=50_000.0)
    summary = ap.apply_file(cal, tmp_path / "one.csv", tmp_path / "out.csv")
    assert summary.columns_added == ["s1x_cal", "s1y_cal", "s1z_cal"]
    res = read_out(tmp_path / "out.csv")
    total = np.linalg.norm(np.column_stack([res.extra[f"s1{a}_cal"] for a in "xyz"]), axis=1)
    assert np.sqrt(np.mean((total - 50_000) ** 2)) < 5.0  # the noise, 3 nT


def test_column_mapping_and_units_in_apply(tmp_path):
    truth = sim.chi2017_truth()
    one = sim.ArrayTruth(truth.sensors[:1])
    ds = sim.simulate(one, n_samples=20, seed=2, noise_nT=0.0)
    cols = {
        "Bx": ds.readings_nT[0, :, 0] / 1e3,
        "By": ds.readings_nT[0, :, 1] / 1e3,
        "Bz": ds.readings_nT[0, :, 2] / 1e3,
    }
    io.write_csv(tmp_path / "uT.csv", cols)
    cal = Calibration([SensorCalibration(one.sensors[0].Cinv, one.sensors[0].bias_nT)])
    ap.apply_file(cal, tmp_path / "uT.csv", tmp_path / "out.csv", columns="x=Bx,y=By,z=Bz", units="uT")
    res = io.read_csv(tmp_path / "out.csv", columns="x=Bx,y=By,z=Bz", units="uT")
    total = np.linalg.norm(np.column_stack([res.extra[f"s1{a}_cal"] for a in "xyz"]), axis=1)
    np.testing.assert_allclose(total, 50_000.0, atol=1e-2)


def test_bad_rows_refuse_and_leave_no_output_or_drop(tmp_path, truth, survey, corrupt_csv):
    path, _ = survey
    k = len(path.read_text().splitlines()) - 5
    bad = corrupt_csv(path, k, 3, "NaN")
    out = tmp_path / "out.csv"
    out.write_text("old\n")
    with pytest.raises(DatasetError, match=f"line {k + 1}"):
        ap.apply_file(exact_calibration(truth), bad, out, chunk_rows=50)
    assert out.read_text() == "old\n"  # atomic: the old file is untouched
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # said in the summary, never raised by the engine
        summary = ap.apply_file(exact_calibration(truth), bad, out, drop_bad=True, chunk_rows=50)
    assert any(n.is_a(DataWarning) and re.search(f"dropped 1 row.*line {k + 1}", n.text) for n in summary.notes)
    assert summary.rows == 299


def test_refusals(tmp_path, truth, survey):
    path, ds = survey
    cal2 = Calibration(exact_calibration(truth).sensors[:2], baseline_m=0.5)
    with pytest.raises(MagcalError, match="4 sensor.*for 2"):
        ap.apply_file(cal2, path, tmp_path / "o.csv")
    with pytest.raises(MagcalError, match="overwrite"):
        ap.apply_file(exact_calibration(truth), path, path)
    ap.apply_file(exact_calibration(truth), path, tmp_path / "o.csv")
    with pytest.raises(MagcalError, match="already has column"):
        ap.apply_file(exact_calibration(truth), tmp_path / "o.csv", tmp_path / "o2.csv")


def test_memory_stays_flat(tmp_path, truth):
    """Peak memory does not grow with the file: 4x the rows, about the same peak."""
    peaks = []
    for n in (2_000, 8_000):
        ds = sim.simulate(truth, n_samples=n, seed=1)
        io.write_csv(tmp_path / f"m{n}.csv", ds, float_format="%.3f")
        tracemalloc.start()
        ap.apply_file(
            exact_calibration(truth), tmp_path / f"m{n}.csv", tmp_path / "o.csv", chunk_rows=500, progress=False
        )
        peaks.append(tracemalloc.get_traced_memory()[1])
        tracemalloc.stop()
    assert peaks[1] < 1.5 * peaks[0], peaks


# -- calibration files --------------------------------------------------------------------------------------------
def test_calibration_round_trip(tmp_path, truth):
    cal = exact_calibration(truth)
    cal.summary["rms_nT"] = 2.9
    cal.save(tmp_path / "c.json")
    back = ap.load_calibration(tmp_path / "c.json", n_sensors=4)
    assert back.frame == "platform" and back.baseline_m == 0.5 and back.reference_total_nT == truth.total_nT
    for a, b in zip(cal.sensors, back.sensors):
        np.testing.assert_array_equal(a.cinv, b.cinv)
        np.testing.assert_array_equal(a.bias_nT, b.bias_nT)
        np.testing.assert_array_equal(a.R, b.R)
    assert back.summary["rms_nT"] == 2.9
    survey = sim.simulate(truth, n_samples=10, seed=1)
    np.testing.assert_array_equal(back.correct(survey), cal.correct(survey))


def _doc(truth):
    return exact_calibration(truth).to_dict()


@pytest.mark.parametrize(
    "edit,match",
    [
        (lambda d: d.update(version=2), "version 2 is not supported"),
        (lambda d: d.update(version=None), "version None"),
        (lambda d: d.update(format="other"), "not a magcal calibration"),
        (lambda d: d.update(sensors=[]), "1 to 4"),
        (lambda d: d.update(sensors="abc"), "1 to 4"),
        (lambda d: d["sensors"][1].update(Cinv=[[1, 0], [0, 1]]), "sensor 2: Cinv"),
        (lambda d: d["sensors"][0].update(Cinv=[[1, 0, 0], [0, float("nan"), 0], [0, 0, 1]]), "finite"),
        (lambda d: d["sensors"][0].update(Cinv=[[1, 0, 0], [0, 0, 0], [0, 0, 1]]), "singular"),
        (
            lambda d: d["sensors"][2].update(R=[[1, 0, 0], [0, 1, 0], [0, 0, -1]]),
            "sensor 3: R is not a proper rotation",
        ),
        (lambda d: d["sensors"][3].pop("bias_nT"), "sensor 4: missing bias_nT"),
        (lambda d: d["sensors"][3].update(bias_nT="x"), "not numeric"),
        (lambda d: d.update(effect_params=[{"nonsense": 1}]), "damaged"),
        (lambda d: d.update(baseline_m=-1), "baseline_m"),
    ],
)
def test_damaged_or_foreign_files_are_refused(tmp_path, truth, edit, match):
    doc = _doc(truth)
    edit(doc)
    path = tmp_path / "c.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(MagcalError, match=match):
        ap.load_calibration(path)


def test_wrong_sensor_count_and_non_json(tmp_path, truth):
    exact_calibration(truth).save(tmp_path / "c.json")
    with pytest.raises(MagcalError, match="for 4 sensor.*data have 1"):
        ap.load_calibration(tmp_path / "c.json", n_sensors=1)
    (tmp_path / "bin.json").write_bytes(bytes(range(256)))
    with pytest.raises(MagcalError, match="not a JSON"):
        ap.load_calibration(tmp_path / "bin.json")
    with pytest.raises(MagcalError, match="no such"):
        ap.load_calibration(tmp_path / "absent.json")
    with pytest.raises(MagcalError, match="directory"):
        ap.load_calibration(tmp_path)


# -- record-only terms: a bias drift of the calibration record is not carried to another file ------------------------
@pytest.fixture(scope="module")
def drift_files(tmp_path_factory):
    """The calibration record (hidden bias drift) and a later record of the same sensor, as CSV files, and a
    calibration with a bias drift and a temperature bias fitted on the first, told its record (as read back)."""
    folder = tmp_path_factory.mktemp("record")
    truth = sim.chi2017_truth(1)
    drift = EFFECTS["bias_drift"]()
    paths = {}
    for name, seed in (("record", 3), ("later", 4)):
        ds = sim.simulate_timeseries(
            truth,
            n_samples=600,
            noise_nT=2.0,
            seed=seed,
            perturbations=[drift.perturbation(2 * drift.default_magnitude)],
        )
        paths[name] = folder / f"{name}.csv"
        io.write_csv(paths[name], ds)
    record = read_out(paths["record"])
    cal = fit(record, Model.from_names(["bias_drift", "temperature_bias"], 1)).calibration.fitted_on(record)
    cal_path = folder / "cal.json"
    cal.save(cal_path)
    return cal, cal_path, paths


def _corrected(path):
    res = read_out(path)
    return np.column_stack([res.extra[f"s1{a}_cal"] for a in "xyz"])


@pytest.mark.parametrize("chunk_rows", [7, 100_000])
def test_record_terms_apply_silently_to_the_fitted_record_file(tmp_path, drift_files, chunk_rows):
    cal, cal_path, paths = drift_files
    summary = ap.apply_file(cal_path, paths["record"], tmp_path / "out.csv", chunk_rows=chunk_rows)
    assert not [n for n in summary.notes if n.is_a(RecordTermWarning)]
    expected = cal.correct(read_out(paths["record"]), record_terms="apply")[0]
    np.testing.assert_allclose(_corrected(tmp_path / "out.csv"), expected, atol=6e-4)


@pytest.mark.parametrize("chunk_rows", [7, 100_000])
def test_record_terms_are_dropped_on_another_file_with_one_warning(tmp_path, drift_files, chunk_rows):
    cal, cal_path, paths = drift_files
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # said in the summary, never raised by the engine
        summary = ap.apply_file(cal_path, paths["later"], tmp_path / "out.csv", chunk_rows=chunk_rows)
    notes = [n for n in summary.notes if n.is_a(RecordTermWarning)]
    text = notes[0].text
    assert len(notes) == 1 and "bias_drift" in text and "temperature_bias" not in text
    later = read_out(paths["later"])
    got = _corrected(tmp_path / "out.csv")
    np.testing.assert_allclose(got, cal.correct(later, record_terms="drop")[0], atol=6e-4)
    assert np.max(np.abs(got - cal.correct(later, record_terms="apply")[0])) > 1.0  # the drift was really left out


def test_record_terms_apply_forces_them(tmp_path, drift_files):
    cal, cal_path, paths = drift_files
    summary = ap.apply_file(cal_path, paths["later"], tmp_path / "out.csv", record_terms="apply")
    assert not [n for n in summary.notes if n.is_a(RecordTermWarning)]
    np.testing.assert_allclose(
        _corrected(tmp_path / "out.csv"), cal.correct(read_out(paths["later"]), record_terms="apply")[0], atol=6e-4
    )


@pytest.mark.parametrize(
    "args, warned", [([], True), (["--record-terms", "drop"], False), (["--record-terms", "apply"], False)]
)
def test_cli_record_terms(tmp_path, drift_files, capsys, args, warned):
    cal, cal_path, paths = drift_files
    out = tmp_path / "out.csv"
    code = main(
        ["apply", str(cal_path), str(paths["later"]), "-o", str(out), "--no-progress", "--chunk-rows", "50"] + args
    )
    err = capsys.readouterr().err
    assert code == 0 and "Traceback" not in err
    assert err.count("record-only term") == (1 if warned else 0), err  # printed once, not once per block
    choice = "apply" if "apply" in args else "drop"
    np.testing.assert_allclose(
        _corrected(out), cal.correct(read_out(paths["later"]), record_terms=choice)[0], atol=6e-4
    )


def test_cli_refuses_a_bad_record_terms_choice(tmp_path, drift_files, capsys):
    cal, cal_path, paths = drift_files
    with pytest.raises(SystemExit):
        main(["apply", str(cal_path), str(paths["later"]), "-o", str(tmp_path / "o.csv"), "--record-terms", "keep"])
    assert "invalid choice: 'keep'" in capsys.readouterr().err


def test_an_old_calibration_file_applies_its_record_terms_with_a_caution(tmp_path, drift_files, capsys):
    cal, cal_path, paths = drift_files
    doc = json.loads(cal_path.read_text())
    del doc["record"]
    old = tmp_path / "old.json"
    old.write_text(json.dumps(doc))
    out = tmp_path / "out.csv"
    assert main(["apply", str(old), str(paths["later"]), "-o", str(out), "--no-progress"]) == 0
    err = capsys.readouterr().err
    assert err.count("does not say which record") == 1
    np.testing.assert_allclose(
        _corrected(out), cal.correct(read_out(paths["later"]), record_terms="apply")[0], atol=6e-4
    )


@pytest.mark.parametrize("rows, same", [(600, True), (600, False), (900, False), (450, False)])
def test_a_parquet_survey_of_another_length_is_another_record_without_a_read(
    tmp_path, drift_files, monkeypatch, rows, same
):
    """A Parquet survey whose footer gives another row count than the fitted record's samples is another record:
    its record-only terms are dropped with the note, and no row is read for the fingerprint (the survey is read
    once, for the correction). One of the same length is fingerprinted: the record itself keeps its drift."""
    cal, cal_path, paths = drift_files
    record = read_out(paths["record"])
    if same:
        ds = record
    else:
        later = sim.simulate_timeseries(sim.chi2017_truth(1), n_samples=rows, noise_nT=2.0, seed=11)
        ds = later
    survey = tmp_path / "survey.parquet"
    io.write_parquet(survey, ds)
    hashed = []
    real_update = ap.RecordHasher.update
    monkeypatch.setattr(ap.RecordHasher, "update", lambda self, d: hashed.append(d.n_samples) or real_update(self, d))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        choice, note = ap.record_choice(cal, survey)
    assert not [w for w in caught if issubclass(w.category, RecordTermWarning)]  # a value, said by the caller
    if same:
        assert (choice, note) == ("apply", None) and sum(hashed) == rows
        return
    assert choice == "drop" and "bias_drift" in note
    if rows == record.n_samples:
        assert sum(hashed) == rows  # the same length: only the readings tell
    else:
        assert hashed == [] and f"({rows} samples)" in note


def csv_variant(text, variant):
    """The same CSV (written by magcal) as another program may write it: the reader yields the same samples."""
    if variant == "crlf":
        return text.replace("\n", "\r\n")
    if variant == "comments":  # comment and blank lines before the metadata and the header
        return "# written by another logger\n#\n\n   \n# operator: test\n" + text
    if variant == "blank":  # blank lines of whitespace between the rows and at the end
        lines = text.split("\n")
        blanks = ["", "  ", "\t\r", "\xa0", " \u3000"]
        out = [
            line + ("\n" + blanks[k % len(blanks)] if k > 12 and k % 37 == 0 else "") for k, line in enumerate(lines)
        ]
        return "\n".join(out) + "\n\n  \r\n\t"
    if variant == "no_end":  # no line end after the last row
        return text.rstrip("\n")
    if variant == "bom":
        return "\ufeff" + text.replace("\n", "\r\n")
    return text


CSV_VARIANTS = ["lf", "crlf", "comments", "blank", "no_end", "bom"]


@pytest.mark.parametrize("variant", CSV_VARIANTS)
@pytest.mark.parametrize("rows, same", [(600, True), (600, False), (900, False), (450, False)])
def test_a_csv_survey_of_another_length_is_another_record_without_a_parse(
    tmp_path, drift_files, monkeypatch, variant, rows, same
):
    """A CSV survey whose data rows (counted from its line ends, blank lines skipped as the reader skips them)
    are another number than the fitted record's samples is another record: dropped with the note, and not a row
    parsed or hashed before the correction. One of the same length is hashed: the record itself, whatever its line
    ends, comments and blank lines, keeps its drift. The decision is the one of hashing the whole file."""
    cal, cal_path, paths = drift_files
    if rows == 600:
        text = paths["record" if same else "later"].read_text()
    else:
        other = tmp_path / "other.csv"
        io.write_csv(other, sim.simulate_timeseries(sim.chi2017_truth(1), n_samples=rows, noise_nT=2.0, seed=11))
        text = other.read_text()
    survey = tmp_path / "survey.csv"
    survey.write_bytes(csv_variant(text, variant).encode("utf-8"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DataWarning)
        whole = ap.file_fingerprint(survey)  # every row read and hashed: what decides
    assert whole["n_samples"] == rows
    hashed, parsed = [], []
    real_update, real_parse = ap.RecordHasher.update, io.CsvSource._parse
    monkeypatch.setattr(ap.RecordHasher, "update", lambda self, d: hashed.append(d.n_samples) or real_update(self, d))
    monkeypatch.setattr(
        io.CsvSource, "_parse", lambda self, lines, *a: parsed.append(len(lines)) or real_parse(self, lines, *a)
    )
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        choice, note = ap.record_choice(cal, survey)  # magcal apply's decision, every path
    assert not caught  # a value, said by the caller; the reader's notes are the correcting pass's
    dropped, _ = cal.record_decision(None, None, ap.CORRECTION_STAGES, fingerprint=whole)
    assert choice == ("drop" if dropped else "apply")  # the decision of the whole file's hash
    if same:
        assert (choice, note) == ("apply", None) and sum(hashed) == rows
        return
    assert choice == "drop" and "bias_drift" in note
    if rows == 600:
        assert sum(hashed) == rows  # the same length: only the readings tell
    else:
        assert hashed == [] and parsed == [] and f"({rows} samples)" in note


@pytest.mark.parametrize("rows", [600, 450, 900])
def test_with_drop_bad_a_csv_survey_is_hashed_as_read(tmp_path, drift_files, monkeypatch, rows):
    """With drop_bad the reader may drop rows, so the line count cannot decide: the survey is hashed as read, up
    to the block past the record's samples. A bad row dropped from the record makes it another record."""
    cal, cal_path, paths = drift_files
    record = lines = paths["record"].read_text().split("\n")
    head = next(k for k, line in enumerate(lines) if line and not line.startswith("#")) + 1
    if rows == 450:
        lines = lines[: head + 450]
    elif rows == 900:
        other = tmp_path / "other.csv"
        io.write_csv(other, sim.simulate_timeseries(sim.chi2017_truth(1), n_samples=rows, noise_nT=2.0, seed=11))
        lines = other.read_text().split("\n")
    survey = tmp_path / "survey.csv"
    survey.write_text("\n".join(lines))
    hashed = []
    real_update = ap.RecordHasher.update
    monkeypatch.setattr(ap.RecordHasher, "update", lambda self, d: hashed.append(d.n_samples) or real_update(self, d))
    choice, note = ap.record_choice(cal, survey, drop_bad=True, chunk_rows=100)
    assert choice == ("apply" if rows == 600 else "drop")
    assert sum(hashed) == min(rows, 700)  # stopped once past the record's 600 samples
    bad = record[:]
    bad[head + 10] = "nan," + bad[head + 10].split(",", 1)[1]
    survey.write_text("\n".join(bad))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DataWarning)
        assert ap.record_choice(cal, survey, drop_bad=True)[0] == "drop"


@pytest.mark.parametrize("out_name", ["out.csv", "out.parquet"])
def test_the_record_with_other_line_ends_keeps_its_terms_through_apply(tmp_path, drift_files, out_name):
    """End to end: the fitted record saved with CRLF, comments and blank lines is still that record (its drift
    applied, no warning); another file is corrected without it."""
    pytest.importorskip("pyarrow")
    cal, cal_path, paths = drift_files
    for name, choice in (("record", "apply"), ("later", "drop")):
        survey = tmp_path / f"{name}.csv"
        survey.write_bytes(csv_variant(csv_variant(paths[name].read_text(), "blank"), "crlf").encode("utf-8"))
        out = tmp_path / f"{name}_{out_name}"
        said = [n for n in ap.apply_file(cal_path, survey, out, chunk_rows=128).notes if n.is_a(RecordTermWarning)]
        assert len(said) == (choice == "drop")
        np.testing.assert_allclose(
            _corrected(out), cal.correct(read_out(paths[name]), record_terms=choice)[0], atol=6e-4
        )


@pytest.mark.parametrize("variant", line_ends.VARIANTS)
def test_apply_reads_every_line_end_as_the_reader_or_refuses_alike(tmp_path, truth, survey, capsys, variant):
    """``magcal apply`` (blocks of rows, ``--drop-bad`` too, CSV and Parquet out): LF, CRLF, CRs before the LF
    give the LF file's output; CR-only line ends and a CR inside a line are refused with ``read_csv``'s message
    naming the file and line, and nothing is written."""
    path, _ = survey
    cal = exact_calibration(truth)
    want = {ext: tmp_path / f"want{ext}" for ext in (".csv", ".parquet")}
    for target in want.values():
        ap.apply_file(cal, path, target, chunk_rows=70)
    data, refusal = line_ends.line_end_variant(path.read_text(), variant)
    src = tmp_path / "survey.csv"
    src.write_bytes(data)
    for k, (out, drop_bad) in enumerate([("o.csv", False), ("o.csv", True), ("o.parquet", False)]):
        out = tmp_path / f"{k}-{out}"
        if refusal is None:
            ap.apply_file(cal, src, out, chunk_rows=70, drop_bad=drop_bad)
            got, ref = read_out(out), read_out(want[out.suffix])
            np.testing.assert_array_equal(got.readings_nT, ref.readings_nT)
            for name in [f"s{i}{a}_cal" for i in range(1, 5) for a in "xyz"] + ["Gxx", "I0"]:
                np.testing.assert_array_equal(np.asarray(got.extra[name], float), np.asarray(ref.extra[name], float))
            continue
        with pytest.raises(DatasetError) as info:
            ap.apply_file(cal, src, out, chunk_rows=70, drop_bad=drop_bad)
        with pytest.raises(DatasetError) as whole:
            read_out(src)
        assert str(info.value) == str(whole.value) and re.search(refusal, str(info.value)), str(info.value)
        assert not out.exists()
    if refusal is not None:  # the command line says it, without a traceback
        cal.save(tmp_path / "cal.json")
        out = tmp_path / "cli.csv"
        assert main(["apply", str(tmp_path / "cal.json"), str(src), "-o", str(out), "--no-progress"]) == 2
        err = capsys.readouterr().err
        assert re.search(refusal, err) and "Traceback" not in err and not out.exists()
