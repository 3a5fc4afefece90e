"""The CLI on bad files: non-zero exit, one clear message, never a traceback; and align/apply end to end."""

import dataclasses
import json
import subprocess
import sys

import numpy as np
import pytest

from magcal.calibration.calibration import Calibration, SensorCalibration
from magcal.cli import main
from magcal.data import io
from magcal.data import simulation as sim
from magcal.fitting import platform as pf
from tests.data.test_io import BAD_FILES


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("clifiles")
    truth = pf.platform_truth()
    io.write_csv(d / "free.csv", sim.simulate(truth, n_samples=200, noise_nT=3.0, seed=5))
    io.write_csv(d / "table.csv", pf.simulate_level_table(truth, n_per_group=80, noise_nT=3.0, seed=1))
    io.write_csv(d / "survey.csv", sim.simulate_timeseries(truth, n_samples=400, noise_nT=3.0, seed=3))
    Calibration(
        [SensorCalibration(s.Cinv, s.bias_nT) for s in truth.sensors], reference_total_nT=50_000.0, baseline_m=0.5
    ).save(d / "intrinsic.json")
    Calibration([SensorCalibration(np.eye(3), np.zeros(3))]).save(d / "one.json")
    return d


def run(argv, capsys):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def assert_clean_failure(code, err, *needles):
    assert code == 2, err
    assert "Traceback" not in err
    assert "error:" in err
    for needle in needles:
        assert needle.lower() in err.lower(), (needle, err)


COMMANDS = {
    "calibrate": lambda f, d: ["calibrate", f],
    "align": lambda f, d: ["align", f, "--cal", d / "intrinsic.json"],
    "apply": lambda f, d: ["apply", d / "one.json", f, "-o", d / "out_bad.csv"],
}


@pytest.mark.parametrize("command", list(COMMANDS))
@pytest.mark.parametrize("name,content,needles", BAD_FILES, ids=[b[0] for b in BAD_FILES])
def test_bad_data_files_fail_cleanly(tmp_path, files, capsys, command, name, content, needles):
    path = tmp_path / "bad.csv"
    path.write_bytes(content)
    code, out, err = run(COMMANDS[command](path, files), capsys)
    assert_clean_failure(code, err, str(path), *needles[:1])
    assert not (files / "out_bad.csv").exists()


@pytest.mark.parametrize(
    "args,needles",
    [
        (["apply", "{d}/absent.json", "{d}/survey.csv", "-o", "{t}/o.csv"], ["no such calibration"]),
        (["apply", "{d}/survey.csv", "{d}/survey.csv", "-o", "{t}/o.csv"], ["not a JSON"]),
        (["apply", "{d}/intrinsic.json", "{d}/survey.csv", "-o", "{d}/survey.csv"], ["overwrite"]),
        (["apply", "{d}/intrinsic.json", "{d}/survey.csv", "-o", "{t}/o.csv", "--units", "furlong"], ["unknown unit"]),
        (["apply", "{d}/intrinsic.json", "{d}/survey.csv", "-o", "{t}/o.csv", "--columns", "w=foo"], ["not a magcal"]),
        (["apply", "{d}/intrinsic.json", "{d}/survey.csv", "-o", "{t}/o.csv", "--chunk-rows", "0"], ["chunk-rows"]),
        (["apply", "{d}/intrinsic.json", "{d}/survey.csv", "-o", "{t}/nodir/o.csv"], ["cannot write"]),
        (["align", "{d}/survey.csv", "--cal", "{d}/intrinsic.json"], ["group column"]),
        (["align", "{d}/table.csv", "--cal", "{d}/absent.json"], ["no such calibration"]),
        (["align", "{d}/table.csv", "--noise", "-1"], ["--noise"]),
        (["align", "{d}/table.csv", "--reference", "igrf"], ["--lat"]),
        (["align", "{d}/table.csv", "--reference", "52.1"], ["looks like uT"]),
        (["calibrate", "{d}/survey.csv", "--columns", "x=nothing"], ["nothing"]),
    ],
)
def test_bad_options_fail_cleanly(tmp_path, files, capsys, args, needles):
    argv = [a.format(d=files, t=tmp_path) for a in args]
    code, out, err = run(argv, capsys)
    assert_clean_failure(code, err, *needles)


def test_calibration_for_another_instrument(tmp_path, files, capsys):
    one = sim.chi2017_truth(1)
    io.write_csv(tmp_path / "one.csv", sim.simulate(one, n_samples=20, seed=1))
    code, _, err = run(["apply", files / "intrinsic.json", tmp_path / "one.csv", "-o", tmp_path / "o.csv"], capsys)
    assert_clean_failure(code, err, "4 sensor", "1 sensor")
    code, _, err = run(["align", files / "table.csv", "--cal", tmp_path / "nope.json"], capsys)
    assert_clean_failure(code, err, "no such")


def test_unknown_calibration_version(tmp_path, files, capsys):
    doc = json.loads((files / "intrinsic.json").read_text())
    doc["version"] = 99
    (tmp_path / "v99.json").write_text(json.dumps(doc))
    code, _, err = run(["apply", tmp_path / "v99.json", files / "survey.csv", "-o", tmp_path / "o.csv"], capsys)
    assert_clean_failure(code, err, "version 99")


def test_align_then_apply_end_to_end(tmp_path, files, capsys):
    code, out, err = run(
        ["align", files / "table.csv", "--cal", files / "intrinsic.json", "-o", tmp_path / "p.json"], capsys
    )
    assert code == 0, err
    assert "platform alignment" in out and "saved" in out
    cal = Calibration.load(tmp_path / "p.json")
    truth = pf.platform_truth()
    assert cal.frame == "platform"
    assert np.all(
        pf.rotation_error_rad(np.array([c.R for c in cal.sensors]), np.array([s.R for s in truth.sensors])) < 1e-4
    )
    code, out, err = run(
        ["apply", tmp_path / "p.json", files / "survey.csv", "-o", tmp_path / "s.csv", "--no-progress"], capsys
    )
    assert code == 0, err
    assert "corrected 400 rows" in out
    header = next(line for line in (tmp_path / "s.csv").read_text().splitlines() if not line.startswith("#"))
    assert header.endswith("s4z_cal,Gxx,Gxy,Gxz,Gyy,Gyz,Gzz,Gyx,I0,I1,I2")
    code, out, err = run(["align", files / "table.csv", "--cal", files / "intrinsic.json", "--json"], capsys)
    assert code == 0 and json.loads(out)["groups"] == {"x_up": 80, "y_up": 80, "z_up": 80}


def test_warnings_are_printed_not_raised(tmp_path, files, capsys):
    text = (files / "survey.csv").read_text().replace("# units: nT", "# units: uT")
    (tmp_path / "uT.csv").write_text(text)
    code, out, err = run(["apply", files / "intrinsic.json", tmp_path / "uT.csv", "-o", tmp_path / "o.csv"], capsys)
    assert code == 0
    assert "warning:" in err and "Earth's field" in err and "Traceback" not in err


@pytest.mark.parametrize(
    "args",
    [
        ["apply", "{d}/intrinsic.json", "{t}/bin.csv", "-o", "{t}/o.csv"],
        ["align", "{t}/bin.csv"],
    ],
)
def test_real_process_exits_2_without_traceback(tmp_path, files, args):
    (tmp_path / "bin.csv").write_bytes(bytes(range(256)) * 8)
    argv = [a.format(d=files, t=tmp_path) for a in args]
    proc = subprocess.run(
        [sys.executable, "-c", "import sys; from magcal.cli import main; sys.exit(main())", *argv],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    assert "binary" in proc.stderr and "Traceback" not in proc.stderr


SITE_LINE = "53.0 N, 4.5 E, 1500 m, 2024-06-01"


@pytest.fixture(scope="module")
def sited(tmp_path_factory):
    """One record twice: with a ``# site:`` line and without; its field is IGRF's magnitude at the site."""
    from magcal.checks.reference import igrf_total_nT

    d = tmp_path_factory.mktemp("sited")
    total, _ = igrf_total_nT(53.0, 4.5, 1.5, "2024-06-01")
    truth = dataclasses.replace(sim.chi2017_truth(1), total_nT=total)
    data = sim.simulate(truth, n_samples=150, noise_nT=2.0, seed=11, with_reference=False)
    io.write_csv(d / "plain.csv", data)
    io.write_csv(d / "sited.csv", data, metadata={"site": SITE_LINE})
    return d


def calibrate_json(argv, capsys):
    code, out, err = run(["calibrate", *argv, "--json"], capsys)
    assert code == 0, err
    return json.loads(out), err


def test_igrf_at_the_site_line_is_the_igrf_at_the_typed_place(sited, capsys):
    """``--reference igrf`` without ``--lat/--lon`` takes the file's ``# site:`` line: the same calibration as
    the place and date typed, and the output says where the reference came from."""
    typed = ["--lat", "53", "--lon", "4.5", "--alt-km", "1.5", "--date", "2024-06-01"]
    by_site, err = calibrate_json([sited / "sited.csv", "--reference", "igrf"], capsys)
    by_hand, _ = calibrate_json([sited / "plain.csv", "--reference", "igrf", *typed], capsys)
    assert by_site["reference_total_nT"] == by_hand["reference_total_nT"]
    for a, b in zip(by_site["sensors"], by_hand["sensors"]):
        assert np.array_equal(a["Cinv"], b["Cinv"]) and np.array_equal(a["bias_nT"], b["bias_nT"])
    words = "IGRF at the file's # site: line (53 N, 4.5 E, 1500 m, 2024-06-01)"
    assert words in err and words in by_site["reference_source"]
    code, out, _ = run(["calibrate", sited / "sited.csv", "--reference", "igrf"], capsys)
    assert code == 0 and words in out


def test_typed_place_wins_over_the_site_line(sited, capsys):
    typed, err = calibrate_json([sited / "sited.csv", "--reference", "igrf", "--lat", "-30", "--lon", "20"], capsys)
    site, _ = calibrate_json([sited / "sited.csv", "--reference", "igrf"], capsys)
    assert abs(typed["reference_total_nT"] - site["reference_total_nT"]) > 1_000  # southern Africa, not the sea
    assert "-30.0000 N, 20.0000 E" in typed["reference_source"] and "is not used" in typed["reference_source"]


def test_igrf_without_a_site_or_a_place_is_refused_as_before(sited, capsys):
    code, _, err = run(["calibrate", sited / "plain.csv", "--reference", "igrf"], capsys)
    assert_clean_failure(code, err, "--reference igrf needs the place: --lat DEG --lon DEG")
