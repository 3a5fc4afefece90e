"""Every exported file as bytes (magcal.output.bundle): the same bytes as the command line, the raw + mask file's
residuals against the simulated truth, the zip's README of refusals, and clear messages for bad input."""

from __future__ import annotations

import io
import zipfile

import numpy as np
import pytest

import magcal
from magcal.cli import main
from magcal.core.errors import MagcalError
from magcal.data import io as mio
from magcal.output import bundle

NOISE_nT = 2.0


@pytest.fixture(scope="module")
def one(tmp_path_factory):
    """A single sensor with known errors and noise, its file and its calibration (saved as calibration.json)."""
    folder = tmp_path_factory.mktemp("bundle")
    ds = magcal.simulate("ding2024-fluxgate", seed=11, noise_nT=NOISE_nT)
    mio.write_csv(folder / "data.csv", ds)
    data = mio.read_csv(folder / "data.csv")
    cal = magcal.calibrate(data).calibration
    cal.save(folder / "calibration.json")
    return folder, data, magcal.Calibration.load(folder / "calibration.json")


def test_parameter_files_are_the_command_line_s_bytes_and_hold_no_clock(one, monkeypatch):
    folder, _, cal = one
    monkeypatch.chdir(folder)
    for fmt, name in bundle.PARAMETER_FILES.items():
        assert main(["export", "calibration.json", "--format", fmt, "-o", f"cli-{name}"]) == 0
        content, _ = bundle.parameter_bytes(cal, fmt)
        assert content == (folder / f"cli-{name}").read_bytes()
        assert content == bundle.parameter_bytes(bundle.calibration_from_bytes(bundle.calibration_bytes(cal)), fmt)[0]
        assert b"UTC" not in content


@pytest.mark.parametrize("kind", ["csv", "parquet"])
def test_corrected_bytes_are_magcal_apply_s(one, monkeypatch, kind):
    folder, _, cal = one
    monkeypatch.chdir(folder)
    out = f"cli-corrected.{kind}"
    assert main(["apply", "calibration.json", "data.csv", "-o", out, "--no-progress"]) == 0
    content, notes = bundle.corrected_bytes(cal, folder / "data.csv", kind)
    assert content == (folder / out).read_bytes() and notes == []


def test_raw_mask_holds_the_raw_data_the_mask_and_residuals_at_the_noise(one):
    folder, data, cal = one
    kept = np.ones(data.n_samples, dtype=bool)
    kept[[3, 50, 77]] = False
    content, _ = bundle.raw_mask_bytes(cal, data, kept)
    (folder / "m.csv").write_bytes(content)
    back = mio.read_csv(folder / "m.csv")
    np.testing.assert_array_equal(back.readings_nT, data.readings_nT)  # the raw readings, exactly
    assert np.flatnonzero(np.asarray(back.extra["kept"]) == 0).tolist() == [3, 50, 77]
    res = np.asarray(back.extra["s1_residual_nT"], dtype=float)
    # uniform noise of full width 2 nT per axis: about 0.58 nT rms on |B|; the fit leaves that, not more
    assert np.sqrt(np.mean(res**2)) < NOISE_nT
    np.testing.assert_allclose(res, cal.total_field_residuals(data, record_terms="apply")[0])
    assert bundle.mask_from_file(folder / "m.csv", data.n_samples).tolist() == kept.tolist()
    # a mask file read back and written again gives the same file (its old kept and residuals replaced)
    again, _ = bundle.raw_mask_bytes(cal, back, bundle.mask_from_file(folder / "m.csv", data.n_samples))
    assert again.splitlines()[-5:] == content.splitlines()[-5:]


def test_bad_masks_are_one_clear_message(one, tmp_path):
    _, data, cal = one
    with pytest.raises(MagcalError, match="3 values for 300 samples"):
        bundle.raw_mask_bytes(cal, data, [True, False, True])
    bad = tmp_path / "bad.csv"
    bad.write_text("kept\n1\n2\n")
    with pytest.raises(MagcalError, match=r"bad.csv: data row 2: kept is '2'"):
        bundle.mask_from_file(bad, 2)
    bad.write_text("x\n1\n")
    with pytest.raises(MagcalError, match="no 'kept' column"):
        bundle.mask_from_file(bad, 1)
    bad.write_text("kept\n1\n")
    with pytest.raises(MagcalError, match="1 kept values for 300 samples"):
        bundle.mask_from_file(bad, 300)


def test_export_all_is_deterministic_and_lists_refusals(tmp_path):
    ds = magcal.simulate("chi2017", seed=2)
    mio.write_csv(tmp_path / "four.csv", ds)
    data = mio.read_csv(tmp_path / "four.csv")
    cal = magcal.calibrate(data).calibration
    first, readme = bundle.export_all(cal, dataset=data, data_path=tmp_path / "four.csv")
    second, _ = bundle.export_all(cal, dataset=data, data_path=tmp_path / "four.csv")
    assert first == second
    with zipfile.ZipFile(io.BytesIO(first)) as zf:
        names = set(zf.namelist())
        text = zf.read("README.txt").decode()
    assert names == {"calibration.json", "corrected.csv", "corrected.parquet", "raw_mask.csv", "README.txt"}
    assert "compass.parm: not written: sensor 4 would go to slot 4" in text
    assert "mag.params: not written" in text and "magcal_calibration.h: not written" in text
    assert text.splitlines() == readme
    # without data: the calibration's files only, the rest named
    only, readme = bundle.export_all(cal)
    assert any("raw_mask.csv: not written: no data given" in line for line in readme)


def test_cli_data_formats_need_data_and_an_output(one, monkeypatch, capsys):
    folder, _, _ = one
    monkeypatch.chdir(folder)
    assert main(["export", "calibration.json", "--format", "mask", "-o", "x.csv"]) == 2
    assert "needs the data: --data" in capsys.readouterr().err
    assert main(["export", "calibration.json", "--format", "all", "--data", "data.csv"]) == 2
    assert "give -o FILE" in capsys.readouterr().err
    assert main(["export", "calibration.json", "--format", "px4", "--data", "data.csv"]) == 2
    assert "--data and --mask are for --format" in capsys.readouterr().err
