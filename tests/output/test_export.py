"""Parameters out (magcal.output.export): each firmware's documented correction, applied to the exported parameters,
gives magcal's corrected field.

ArduPilot (AP_Compass_Backend::correct_field): corrected = M (SCALE (raw + OFS)), milligauss, M symmetric from
COMPASS_DIA*/COMPASS_ODI*. PX4 (calibration::Magnetometer::Correct): corrected = rot (S (raw - OFF)), gauss, S
symmetric from CAL_MAGn_*SCALE/*ODIAG. Both are reimplemented here from those formulas, independently of
magcal.output.export's helpers.
"""

from __future__ import annotations

import shutil
import subprocess

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import magcal
from magcal.cli import main
from magcal.core.errors import MagcalError
from magcal.data.simulation import ArrayTruth, SensorErrors
from magcal.output.export import export_calibration, parse_parameter_file, symmetric_factor

F_nT = 50_000.0


def one_sensor_truth():
    """A sensor with a full (not symmetric, not triangular) sensor matrix and a large bias."""
    c = np.array([[1.04, 0.03, -0.02], [-0.015, 0.97, 0.025], [0.01, -0.03, 1.02]])
    errors = SensorErrors(matrix=c, bias_nT=np.array([1500.0, -800.0, 2300.0]))
    return ArrayTruth(sensors=[errors], total_nT=F_nT, declination_deg=0.0, inclination_deg=60.0)


@pytest.fixture(scope="module")
def calibrated():
    truth = one_sensor_truth()
    ds = magcal.simulate(truth, n_samples=400, noise_nT=2.0, seed=3)
    result = magcal.calibrate(ds, reference_total_nT=F_nT)
    new = magcal.simulate(truth, n_samples=300, noise_nT=2.0, seed=9)  # other raw readings to correct
    return result.calibration, new


def ardupilot_correct(params, raw_mG, tag=""):
    ofs = np.array([params[f"COMPASS_OFS{tag}_{a}"] for a in "XYZ"])
    d = [params[f"COMPASS_DIA{tag}_{a}"] for a in "XYZ"]
    o = [params[f"COMPASS_ODI{tag}_{a}"] for a in "XYZ"]
    m = np.array([[d[0], o[0], o[1]], [o[0], d[1], o[2]], [o[1], o[2], d[2]]])
    out = []
    for v in raw_mG:  # exactly the firmware's order: add offsets, scale, then the matrix
        v = v + ofs
        v = v * params[f"COMPASS_SCALE{tag}"]
        out.append(m @ v)
    return np.array(out)


def px4_correct(params, raw_G, n=0):
    off = np.array([params[f"CAL_MAG{n}_{a}OFF"] for a in "XYZ"])
    d = [params[f"CAL_MAG{n}_{a}SCALE"] for a in "XYZ"]
    o = [params[f"CAL_MAG{n}_{a}ODIAG"] for a in "XYZ"]
    s = np.array([[d[0], o[0], o[1]], [o[0], d[1], o[2]], [o[1], o[2], d[2]]])
    return np.array([s @ (v - off) for v in raw_G])  # rot = identity (board rotation none)


@pytest.mark.parametrize("fmt", ["ardupilot", "px4"])
def test_firmware_formula_gives_magcal_field_within_1_nT(calibrated, fmt, tmp_path):
    cal, new = calibrated
    out = tmp_path / f"cal.{fmt}"
    path = tmp_path / "cal.json"
    cal.save(path)
    assert main(["export", str(path), "--format", fmt, "-o", str(out)]) == 0
    params = parse_parameter_file(out.read_text())
    raw = new.readings_nT[0]
    if fmt == "ardupilot":
        assert set(params) == {f"COMPASS_{k}_{a}" for k in ("OFS", "DIA", "ODI") for a in "XYZ"} | {"COMPASS_SCALE"}
        firmware_nT = ardupilot_correct(params, raw / 100.0) * 100.0
    else:
        assert len(params) == 9 and all(k.startswith("CAL_MAG0_") for k in params)
        firmware_nT = px4_correct(params, raw / 1e5) * 1e5
    magcal_nT = cal.correct(new)[0]
    # the magnitudes agree (the firmware's total field is magcal's)
    assert np.max(np.abs(np.linalg.norm(firmware_nT, axis=1) - np.linalg.norm(magcal_nT, axis=1))) < 1.0
    # and the vectors agree up to the stated frame rotation R Q
    frame = export_calibration(cal, fmt).sensors[0].frame_rotation
    assert np.max(np.abs(firmware_nT @ frame.T - magcal_nT)) < 1.0
    # that rotation is a real difference: without it the vectors differ by far more than 1 nT
    assert np.max(np.linalg.norm(firmware_nT - magcal_nT, axis=1)) > 10.0


def test_symmetric_factor_is_the_polar_decomposition():
    rng = np.random.default_rng(1)
    cinv = np.triu(np.eye(3) + rng.normal(0, 0.05, (3, 3)))
    q, s = symmetric_factor(cinv)
    assert np.allclose(q @ s, cinv) and np.allclose(s, s.T)
    assert np.all(np.linalg.eigvalsh(s) > 0) and np.isclose(np.linalg.det(q), 1.0)
    assert np.allclose(s @ s, cinv.T @ cinv)  # the same quadric, so the same corrected magnitudes
    with pytest.raises(MagcalError, match="mirrored axis"):
        symmetric_factor(np.diag([1.0, 1.0, -1.0]))


def test_offsets_units_and_signs(calibrated):
    cal, _ = calibrated
    ap = export_calibration(cal, "ardupilot").parameters
    px = export_calibration(cal, "px4").parameters
    b = cal.sensors[0].bias_nT
    assert np.allclose([ap[f"COMPASS_OFS_{a}"] for a in "XYZ"], -b / 100.0)  # added, in milligauss
    assert np.allclose([px[f"CAL_MAG0_{a}OFF"] for a in "XYZ"], b / 1e5)  # subtracted, in gauss
    # the truth's bias is about (1500, -800, 2300) nT, so the ArduPilot offsets are about (-15, 8, -23) mG
    assert np.allclose([ap[f"COMPASS_OFS_{a}"] for a in "XYZ"], [-15, 8, -23], atol=1.0)


def array_calibration():
    ds = magcal.simulate("chi2017", seed=2)
    return magcal.calibrate(ds, reference_total_nT=50_000).calibration


def test_misaligned_sensors_refused_unless_forced():
    cal = array_calibration()
    with pytest.raises(MagcalError, match=r"sensor 2: its rotation R into the sensor1 frame .* --force"):
        export_calibration(cal, "px4")
    # sensor 1 defines the array frame: it exports alone without loss
    alone = export_calibration(cal, "px4", sensors=[1])
    assert not alone.dropped
    forced = export_calibration(cal, "px4", force=True)
    assert len(forced.dropped) == 3 and all("cannot be stored" in d for d in forced.dropped)
    assert "DROPPED: sensor 2" in forced.text
    assert {k[:8] for k in forced.parameters} == {"CAL_MAG0", "CAL_MAG1", "CAL_MAG2", "CAL_MAG3"}
    # ArduPilot calibrates three compasses: the fourth sensor has no slot unless moved
    with pytest.raises(MagcalError, match="ArduPilot calibrates compasses 1 to 3"):
        export_calibration(cal, "ardupilot", force=True)
    moved = export_calibration(cal, "ardupilot", sensors=[4], slots=[2], force=True)
    assert set(moved.parameters) >= {"COMPASS_OFS2_X", "COMPASS_DIA2_Z", "COMPASS_ODI2_Y", "COMPASS_SCALE2"}


def test_effects_are_refused_unless_forced(tmp_path):
    ds = magcal.simulate_timeseries("chi2017", n_samples=600, seed=5)
    cal = magcal.calibrate(ds.sensors([0]), effects=["temperature_bias"]).calibration
    with pytest.raises(MagcalError, match="effect temperature_bias"):
        export_calibration(cal, "ardupilot")
    forced = export_calibration(cal, "ardupilot", force=True)
    assert any("temperature_bias" in d for d in forced.dropped)
    path = tmp_path / "cal.json"
    cal.save(path)
    assert main(["export", str(path), "--format", "ardupilot"]) == 2  # refused on the command line too


@pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler")
def test_c_header_compiles_and_corrects(calibrated, tmp_path):
    cal, new = calibrated
    header = tmp_path / "magcal_cal.h"
    path = tmp_path / "cal.json"
    cal.save(path)
    assert main(["export", str(path), "--format", "c", "-o", str(header)]) == 0
    raw = new.readings_nT[0][:5]
    program = tmp_path / "main.c"
    rows = ",".join("{" + ",".join(repr(float(x)) for x in v) + "}" for v in raw)
    program.write_text(f"""#include <stdio.h>
#include "magcal_cal.h"
int main(void) {{
    const double raw[5][3] = {{{rows}}};
    for (int n = 0; n < 5; n++) {{
        double d[3], b[3];
        for (int i = 0; i < 3; i++) d[i] = raw[n][i] - MAGCAL_S1_BIAS_NT[i];
        for (int i = 0; i < 3; i++) b[i] = MAGCAL_S1_MATRIX[i][0]*d[0] + MAGCAL_S1_MATRIX[i][1]*d[1]
                                          + MAGCAL_S1_MATRIX[i][2]*d[2];
        printf("%.6f %.6f %.6f\\n", b[0], b[1], b[2]);
    }}
    return 0;
}}
""")
    exe = tmp_path / "main"
    subprocess.run(["cc", "-std=c99", "-Wall", "-Werror", "-o", str(exe), str(program)], check=True, timeout=60)
    out = np.loadtxt(
        subprocess.run([str(exe)], capture_output=True, text=True, check=True, timeout=30).stdout.splitlines()
    )
    magcal_nT = cal.correct(new.subset(np.arange(5)))[0]
    assert np.max(np.abs(np.linalg.norm(out, axis=1) - np.linalg.norm(magcal_nT, axis=1))) < 1.0  # float32 params


def test_export_cli_errors_are_one_line(tmp_path, capsys):
    assert main(["export", str(tmp_path / "missing.json"), "--format", "px4"]) == 2
    assert "no such calibration file" in capsys.readouterr().err
    cal = array_calibration()
    path = tmp_path / "a.json"
    cal.save(path)
    assert main(["export", str(path), "--format", "px4", "--sensor", "5"]) == 2
    assert "the calibration has sensor(s) 1 to 4" in capsys.readouterr().err
    assert main(["export", str(path), "--format", "ardupilot", "--sensor", "1"]) == 0
    text = capsys.readouterr().out
    assert "COMPASS_OFS_X," in text and "COMPASS_OFS2_X" not in text


def test_rotation_error_figure_matches_the_vector_difference(calibrated):
    cal, new = calibrated
    e = export_calibration(cal, "px4").sensors[0]
    angle = Rotation.from_matrix(e.frame_rotation).magnitude()
    assert np.isclose(e.vector_error_nT, 2 * F_nT * np.sin(angle / 2))
    firmware = e.firmware_corrected_nT(new.readings_nT[0])
    worst = np.max(np.linalg.norm(firmware - cal.correct(new)[0], axis=1))
    assert worst <= e.vector_error_nT * 1.01 + 1.0


def test_long_offsets_get_an_ardupilot_note():
    from magcal.calibration.calibration import Calibration, SensorCalibration

    cal = Calibration(sensors=[SensorCalibration(np.eye(3), [150_000.0, 0.0, 0.0])], reference_total_nT=F_nT)
    ap = export_calibration(cal, "ardupilot")
    assert ap.parameters["COMPASS_OFS_X"] == -1500.0
    assert any("COMPASS_OFFS_MAX" in n for n in ap.notes)
    assert not any("COMPASS_OFFS_MAX" in n for n in export_calibration(cal, "px4").notes)
    assert not ap.dropped and not any("gauge" in n for n in ap.notes)  # identity: nothing turned, nothing lost
