"""``magcal simulate`` and ``magcal calibrate`` end to end, in-process and as a real process."""

import json
import subprocess
import sys

import numpy as np
import pytest

from magcal.calibration.calibration import Calibration
from magcal.cli import main
from magcal.data import io
from magcal.data.simulation import chi2017_truth

ITEM9_TOP = {
    "format",
    "version",
    "reference_total_nT",
    "baseline_m",
    "n_samples",
    "effects",
    "rms_nT",
    "tensor_rms_nT_per_m",
    "sensors",
}
ITEM9_SENSOR = {"id", "Cinv", "bias_nT", "R", "scale", "axis_angles_deg", "rms_before_nT", "rms_nT"}


@pytest.fixture(scope="module")
def chi_csv(tmp_path_factory):
    path = tmp_path_factory.mktemp("cli") / "chi.csv"
    assert main(["simulate", "--preset", "chi2017", "--seed", "21", "-o", str(path)]) == 0
    return path


def test_simulate_writes_a_readable_file(chi_csv):
    ds = io.read_csv(chi_csv)
    assert ds.n_sensors == 4 and ds.n_samples == 200
    assert ds.baseline_m == 0.5 and ds.reference_total_nT == 50_000.0 and ds.noise_nT == 3.0
    assert ds.metadata["preset"] == "chi2017" and ds.metadata["seed"] == "21"


@pytest.mark.parametrize(
    "extra,check",
    [
        (["--n", "60", "--noise", "0"], lambda ds: ds.n_samples == 60 and ds.noise_nT == 0.0),
        (["--timeseries", "--n", "120"], lambda ds: ds.n_samples == 120 and ds.has("time") and ds.has("temperature")),
        (["--no-reference", "--n", "30"], lambda ds: ds.reference_total_nT is None),
    ],
)
def test_simulate_options(tmp_path, extra, check):
    path = tmp_path / "s.csv"
    assert main(["simulate", "--preset", "chi2017", "-o", str(path)] + extra) == 0
    assert check(io.read_csv(path))


def test_simulate_is_reproducible(tmp_path):
    a, b = tmp_path / "a.csv", tmp_path / "b.csv"
    for p in (a, b):
        main(["simulate", "--seed", "5", "--n", "40", "-o", str(p)])
    assert a.read_text() == b.read_text()


def test_calibrate_report(chi_csv, capsys):
    assert main(["calibrate", str(chi_csv)]) == 0
    out = capsys.readouterr().out
    for text in (
        "Sensor 1: total-field RMS",
        "Sensor 4",
        "C^-1 =",
        "b = [",
        "R =",
        "scale (gauge-free)",
        "axis angles",
        "Tensor RMS",
        "Gzz",
        "floor",
        "procrustes",
        "ml",
    ):
        assert text in out, text


def test_calibrate_json_and_saved_file_agree(chi_csv, tmp_path, capsys):
    cal_path = tmp_path / "cal.json"
    assert main(["calibrate", str(chi_csv), "--json", "-o", str(cal_path)]) == 0
    printed = json.loads(capsys.readouterr().out)
    saved = json.loads(cal_path.read_text())
    assert ITEM9_TOP <= set(printed) and ITEM9_TOP <= set(saved)
    assert printed["format"] == "magcal-calibration" and printed["version"] == 1
    assert printed["n_samples"] == 200 and printed["effects"] == [] and printed["baseline_m"] == 0.5
    assert set(printed["tensor_rms_nT_per_m"]) == {"Gxx", "Gxy", "Gxz", "Gyx", "Gyy", "Gyz", "Gzz"}
    for p, s in zip(printed["sensors"], saved["sensors"]):
        assert ITEM9_SENSOR <= set(p)
        assert p["Cinv"] == s["Cinv"] and p["R"] == s["R"] and p["rms_nT"] == s["rms_nT"]
    assert printed["sensors"][0]["R"] == np.eye(3).tolist()
    truth = chi2017_truth()
    for p, t in zip(printed["sensors"], truth.sensors):
        assert np.max(np.abs(np.array(p["Cinv"]) - t.Cinv)) < 2e-4
        assert np.max(np.abs(np.array(p["bias_nT"]) - t.bias_nT)) < 2.0
        assert np.max(np.abs(np.array(p["R"]) - t.R)) < 1.5e-3
        assert p["rms_before_nT"] > 100 and p["rms_nT"] < 3.6
    # the saved file applies to the data exactly as the fitted calibration did
    ds = io.read_csv(chi_csv)
    total = Calibration.load(cal_path).total_field(ds)
    assert np.sqrt(np.mean((total - 50_000.0) ** 2)) == pytest.approx(printed["rms_nT"], rel=1e-9)


@pytest.mark.parametrize(
    "args",
    [
        ["--method", "ellipsoid"],
        ["--robust"],
        ["--reference", "50000"],
        ["--ellipsoid", "li-griffiths", "--method", "ellipsoid"],
    ],
)
def test_calibrate_options(chi_csv, capsys, args):
    assert main(["calibrate", str(chi_csv), "--json"] + args) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["rms_nT"] < 3.6 and max(doc["tensor_rms_nT_per_m"].values()) < 15


def test_calibrate_without_reference_says_it_is_fitted(tmp_path, capsys):
    path = tmp_path / "noref.csv"
    main(["simulate", "--no-reference", "--seed", "2", "-o", str(path)])
    capsys.readouterr()
    assert main(["calibrate", str(path)]) == 0
    assert "unknown, fitted" in capsys.readouterr().out


@pytest.mark.parametrize(
    "setup,args,message",
    [
        (None, ["calibrate", "no/such/file.csv"], "no/such/file.csv"),
        ("chi", ["calibrate", "{chi}", "--reference", "-5"], "--reference"),
        (None, ["simulate", "--preset", "nope", "-o", "x.csv"], "unknown preset"),
        ("few", ["calibrate", "{few}"], "too few samples"),
    ],
)
def test_user_errors_exit_2_without_traceback(tmp_path, chi_csv, capsys, setup, args, message):
    few = tmp_path / "few.csv"
    if setup == "few":
        main(["simulate", "--n", "6", "-o", str(few)])
        capsys.readouterr()
    args = [a.format(chi=chi_csv, few=few) for a in args]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


def test_real_process(tmp_path):
    """The command as a user runs it: exit codes and no traceback on a user error."""
    cmd = [sys.executable, "-c", "import sys; from magcal.cli import main; sys.exit(main())"]
    path = tmp_path / "d.csv"
    ok = subprocess.run(cmd + ["simulate", "--n", "80", "-o", str(path)], capture_output=True, text=True)
    assert ok.returncode == 0 and path.exists()
    ok = subprocess.run(cmd + ["calibrate", str(path), "--method", "ellipsoid"], capture_output=True, text=True)
    assert ok.returncode == 0 and "Sensor 4" in ok.stdout
    bad = subprocess.run(cmd + ["calibrate", str(tmp_path / "missing.csv")], capture_output=True, text=True)
    assert bad.returncode == 2 and "Traceback" not in bad.stderr and "missing.csv" in bad.stderr


@pytest.mark.parametrize("command", ["calibrate", "diagnose"])
def test_a_fit_the_data_cannot_support_names_the_file(tmp_path, capsys, command):
    path = tmp_path / "few.csv"
    assert main(["simulate", "--n", "8", "-o", str(path)]) == 0
    capsys.readouterr()
    assert main([command, str(path)]) == 2
    err = capsys.readouterr().err
    assert f"error: {path}: sensor 1: too few samples (8)" in err and "Traceback" not in err


@pytest.mark.parametrize("method", ["ml", "de"])
def test_a_coverage_warning_is_shown_once(tmp_path, capsys, method):
    from magcal.data.simulation import simulate

    ds = simulate("chi2017", n_samples=400, seed=3)
    y = ds.readings_nT[0]
    cap = ds.subset(y[:, 2] > 0.2 * np.linalg.norm(y, axis=1))  # only the upper part of the sky
    path = tmp_path / "cap.csv"
    io.write_csv(path, cap, metadata={"reference_total_nT": 50_000.0})
    assert main(["calibrate", str(path), "--method", method, "--seed", "1"]) == 0
    out = capsys.readouterr()
    assert (out.out + out.err).count("poor direction coverage") == 1


@pytest.mark.parametrize("command", ["calibrate", "diagnose"])
def test_json_carries_every_warning_of_the_run(tmp_path, capsys, command):
    """The coverage warning (raised before the fit) is in --json, not only on stderr."""
    from magcal.data.simulation import simulate

    ds = simulate("chi2017", n_samples=400, seed=3)
    y = ds.readings_nT[0]
    cap = ds.subset(y[:, 2] > 0.2 * np.linalg.norm(y, axis=1))
    path = tmp_path / "cap.csv"
    io.write_csv(path, cap, metadata={"reference_total_nT": 50_000.0})
    extra = ["--top", "1"] if command == "diagnose" else []
    assert main([command, str(path), "--json"] + extra) == 0
    doc = json.loads(capsys.readouterr().out)
    for text in ["poor direction coverage"]:
        assert any(text in w for w in doc["warnings"]), doc["warnings"]
    assert len(doc["warnings"]) == len(set(doc["warnings"]))


def test_report_says_whether_the_fit_converged(chi_csv, capsys):
    assert main(["calibrate", str(chi_csv)]) == 0
    out = capsys.readouterr().out
    assert "converged (" in out and "DID NOT CONVERGE" not in out


def test_every_subcommand_takes_effects_files():
    from magcal.cli import SUBCOMMANDS, build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    assert set(SUBCOMMANDS) <= set(sub.choices)
    for name, p in sub.choices.items():
        assert any(a.dest == "effects_file" and "--effects-file" in a.option_strings for a in p._actions), name


def test_the_command_line_imports_only_the_command_that_runs():
    """``magcal --help`` lists every subcommand from its table without importing one; ``magcal COMMAND`` imports
    that command's module (the command line starts in about the time of ``import magcal``)."""
    import subprocess
    import sys

    code = (
        "import sys; from magcal.cli import main\n"
        "try:\n    main(sys.argv[1:])\nexcept SystemExit:\n    pass\n"
        "print(sorted(m for m in sys.modules if m.startswith('magcal.cli.') or m == 'magcal.fitting.pipeline'))"
    )
    out = subprocess.run([sys.executable, "-c", code, "--help"], capture_output=True, text=True, timeout=120).stdout
    assert "calibrate" in out and "record" in out
    assert out.strip().splitlines()[-1] == "['magcal.cli.commands']"
    out = subprocess.run([sys.executable, "-c", code, "effects"], capture_output=True, text=True, timeout=120).stdout
    loaded = out.strip().splitlines()[-1]
    assert "magcal.cli.effects" in loaded and "magcal.cli.calibrate" not in loaded


def test_effects_lists_the_built_in_catalogue(capsys):
    from magcal.model.terms import EFFECTS

    assert main(["effects"]) == 0
    out = capsys.readouterr().out
    for name in EFFECTS:
        assert f"\n{name}  (" in out, name
    assert "beta_x, beta_y, beta_z [nT/K]" in out and "Gxx, Gxy, Gxz, Gyy, Gyz [nT/m]" in out
    assert main(["effects", "bias_step", "--json"]) == 0
    entry = json.loads(capsys.readouterr().out)["effects"][0]
    assert entry["name"] == "bias_step" and entry["origin"] == "built-in" and entry["channels"] == ["time"]
    assert [p["unit"] for p in entry["params"]] == ["nT"] * 3


# -- data quality and raw counts --------------------------------------------------------------------------
def _write_counts(path, lsb_nT, seed=3, n=300):
    """Integer counts of ``lsb_nT`` for the chi2017 array, no units line; returns the dataset in nT."""
    from magcal.data.simulation import simulate

    ds = simulate("chi2017", n_samples=n, seed=seed)
    counts = np.round(ds.readings_nT / lsb_nT).astype(int)
    cols = {f"s{i + 1}{a}": counts[i, :, k] for i in range(4) for k, a in enumerate("xyz")}
    io.write_csv(path, cols, metadata={"baseline_m": 0.5, "reference_total_nT": 50_000.0})
    return ds


@pytest.mark.parametrize("lsb_nT", [15.0, 150.0])
def test_calibrate_reads_raw_counts_and_reports_their_quantization(tmp_path, capsys, lsb_nT):
    path = tmp_path / "counts.csv"
    _write_counts(path, lsb_nT)
    assert main(["calibrate", str(path), "--units", "counts", "--lsb", str(lsb_nT), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["rms_nT"] < 3.0 + lsb_nT / np.sqrt(12) * 1.3  # the quantization floor, not more
    quant = [f for f in doc["quality"]["findings"] if f["kind"] == "quantization"]
    assert [f["sensor"] for f in quant] == [1, 2, 3, 4]
    for f in quant:
        assert f["values"]["step_nT"] == pytest.approx([lsb_nT] * 3) and f["severity"] == "warning"
        assert f["values"]["step_counts"] == pytest.approx([1.0] * 3)
        assert any(w.endswith(f["effect"]) and f"sensor {f['sensor']}:" in w for w in doc["warnings"])


@pytest.mark.parametrize(
    "args,message",
    [
        (["--units", "counts"], "need the LSB in nT per count: pass --lsb"),
        (["--lsb", "150"], "add --units counts"),
        (["--units", "counts", "--lsb", "-1"], "positive number of nT per count"),
    ],
)
def test_counts_without_a_usable_lsb_exit_2_with_a_message(tmp_path, capsys, args, message):
    path = tmp_path / "counts.csv"
    _write_counts(path, 150.0, n=40)
    assert main(["calibrate", str(path)] + args) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err and str(path) in err


def test_text_report_has_a_data_quality_section(tmp_path, chi_csv, capsys):
    assert main(["calibrate", str(chi_csv)]) == 0
    out = capsys.readouterr()
    section = out.out.split("\nData quality\n------------\n")[1]
    assert section.strip() == "nothing notable" and "WARNING" not in out.out  # the clean simulation
    # stale readings in sensor 3: a warning in the section (with its effect), not repeated on stderr
    from magcal.data.simulation import simulate

    ds = simulate("chi2017", n_samples=300, seed=4)
    y = ds.readings_nT.copy()
    y[2, 1::4] = y[2, 0:-1:4]  # every 4th sample of sensor 3 repeats the one before
    path = tmp_path / "stale.csv"
    io.write_csv(path, ds.replace(readings_nT=y))
    assert main(["calibrate", str(path)]) == 0
    out = capsys.readouterr()
    section = out.out.split("\nData quality\n------------\n")[1]
    assert "WARNING sensor 3: 25% of the readings repeat the previous vector" in section
    assert "weights that direction twice" in section and "stale" not in out.err


@pytest.mark.parametrize("command", ["calibrate", "diagnose"])
def test_fitted_field_outside_the_earths_range_is_flagged(tmp_path, capsys, command):
    from magcal.data.simulation import simulate

    ds = simulate("chi2017", n_samples=200, seed=6, with_reference=False)
    path = tmp_path / "weak.csv"
    io.write_csv(path, ds.replace(readings_nT=0.3 * ds.readings_nT))  # 15 uT: a shielded room, or a wrong LSB
    extra = ["--top", "1"] if command == "diagnose" else []
    assert main([command, str(path), "--json"] + extra) == 0
    doc = json.loads(capsys.readouterr().out)
    field = [f for f in doc["quality"]["findings"] if f["kind"] == "field"]
    assert len(field) == 1 and field[0]["values"]["field_nT"] == pytest.approx(15_000, rel=0.01)
    assert sum("outside the Earth's field range of 20-70 uT" in w and "--lsb" in w for w in doc["warnings"]) == 1
    # inside the range: no such finding
    io.write_csv(path, ds)
    assert main([command, str(path), "--json"] + extra) == 0
    doc = json.loads(capsys.readouterr().out)
    assert not [f for f in doc["quality"]["findings"] if f["kind"] == "field"]


def test_diagnose_reports_data_quality(tmp_path, capsys):
    from magcal.data.simulation import simulate_timeseries

    ds = simulate_timeseries("chi2017", n_samples=600, seed=2)
    path = tmp_path / "ramp.csv"
    io.write_csv(path, ds.replace(temperature_C=20.0 + 0.05 * ds.time_s))  # temperature follows time
    assert main(["diagnose", str(path), "--top", "1"]) == 0
    out = capsys.readouterr()
    section = out.out.split("\nData quality\n------------\n")[1]
    assert "sample rate 10 Hz" in section and "WARNING temperature 20 to 23 degC" in section
    assert "indistinguishable" in section and "indistinguishable" not in out.err
    assert main(["diagnose", str(path), "--top", "1", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    kinds = {f["kind"] for f in doc["quality"]["findings"]}
    assert {"sample_rate", "gaps", "stale", "quantization", "clipping", "static", "temperature"} <= kinds
    assert any("indistinguishable" in w for w in doc["warnings"])


def test_diagnose_shows_the_reference_given_in_its_header(tmp_path, capsys):
    """`magcal diagnose FILE --reference 52000` says 52000 nT in its header, not "unknown (fitted)"."""
    from magcal.data.simulation import simulate_timeseries

    ds = simulate_timeseries("chi2017", n_samples=600, seed=2).replace(reference_total_nT=None)
    path = tmp_path / "unreferenced.csv"
    io.write_csv(path, ds)
    assert main(["diagnose", str(path), "--top", "1", "--no-validate"]) == 0
    assert "reference field unknown (fitted)" in capsys.readouterr().out
    assert main(["diagnose", str(path), "--top", "1", "--no-validate", "--reference", "52000"]) == 0
    header = capsys.readouterr().out.split("\n\n")[0]
    assert "reference field 52000.0 nT" in header and "unknown" not in header
