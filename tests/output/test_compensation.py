"""The platform's current field and a mounting off the right angles, exported as the firmwares hold them
(magcal.output.compensation, docs/export.md), proved like the offsets: each firmware's own correction, written out
here from its source and applied to simulated raw readings, gives magcal's corrected body-frame field.

ArduPilot, ``AP_Compass_Backend::rotate_field`` then ``correct_field``: the raw reading (mG) is turned by
``COMPASS_ORIENT`` (101/102: ``Matrix3::from_euler(CUST_ROTn_ROLL, _PITCH, _YAW)``), then ``mag += OFS``,
``mag *= SCALE``, ``mag = M mag``, and last ``mag += MOT * u`` with ``u`` the battery current in A
(``COMPASS_MOTCT`` 2) or the throttle 0-1 (``COMPASS_MOTCT`` 1).

PX4, ``calibration::Magnetometer::Correct``: ``rot * (S * ((raw + power * COMP) - OFF))`` in gauss, ``power`` the
battery current in kA (``VehicleMagnetometer``: ``current_a * 0.001f``, ``CAL_MAG_COMP_TYP`` 2) or the throttle 0-1
(``CAL_MAG_COMP_TYP`` 1), ``rot`` from ``CAL_MAGn_ROT``.

None of magcal's own firmware helpers is used here.
"""

from __future__ import annotations

import copy
import math
import shutil
import subprocess
import zipfile
from io import BytesIO

import numpy as np
import pytest

from magcal.calibration.calibration import Calibration, SensorCalibration
from magcal.checks.reference import resolve_vector_reference
from magcal.cli import main
from magcal.core.errors import MagcalError
from magcal.data.vehicle import simulate_vehicle, vehicle_truth
from magcal.fitting.vector import fit_vector
from magcal.model.effects import CurrentField, TemperatureBias
from magcal.model.platform_terms import PlatformTerms
from magcal.model.terms import Model
from magcal.output.bundle import export_all, parameter_bytes
from magcal.output.compensation import current_compensation
from magcal.output.export import export_calibration, parse_parameter_file
from magcal.output.vehicle_params import values_to_send

#: The throttle column of the simulated flights: the motor current over this many amperes (0 to about 0.85).
FULL_THROTTLE_A = 30.0


# -- the firmwares' formulas, from their source -------------------------------------------------------------------


def from_euler(roll_deg, pitch_deg, yaw_deg):
    """ArduPilot's ``Matrix3<T>::from_euler(roll, pitch, yaw)`` (rows a, b, c), radians from degrees."""
    r, p, y = (math.radians(v) for v in (roll_deg, pitch_deg, yaw_deg))
    cp, sp, sr, cr, sy, cy = math.cos(p), math.sin(p), math.sin(r), math.cos(r), math.sin(y), math.cos(y)
    return np.array(
        [
            [cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy],
            [cp * sy, sr * sp * sy + cr * cy, cr * sp * sy - sr * cy],
            [-sp, sr * cp, cr * cp],
        ]
    )


def rotate_roll_180_yaw_90(v):
    """ArduPilot's ``Vector3::rotate(ROTATION_ROLL_180_YAW_90)``: ``tmp = x; x = y; y = tmp; z = -z``."""
    return np.array([v[1], v[0], -v[2]])


def ardupilot_field(params, raw_mG, compass, motor):
    """``rotate_field`` then ``correct_field`` for compass 1, 2 or 3, sample by sample (mG)."""
    tag = "" if compass == 1 else str(compass)
    ofs = np.array([params[f"COMPASS_OFS{tag}_{a}"] for a in "XYZ"])
    d = [params[f"COMPASS_DIA{tag}_{a}"] for a in "XYZ"]
    o = [params[f"COMPASS_ODI{tag}_{a}"] for a in "XYZ"]
    m = np.array([[d[0], o[0], o[1]], [o[0], d[1], o[2]], [o[1], o[2], d[2]]])
    mot = np.array([params.get(f"COMPASS_MOT{tag}_{a}", 0.0) for a in "XYZ"])
    motct = params.get("COMPASS_MOTCT", 0)
    orient = int(params.get(f"COMPASS_ORIENT{tag}", 0))
    out = []
    for v, u in zip(raw_mG, motor):
        if orient in (101, 102):
            n = orient - 100
            v = from_euler(params[f"CUST_ROT{n}_ROLL"], params[f"CUST_ROT{n}_PITCH"], params[f"CUST_ROT{n}_YAW"]) @ v
        elif orient == 10:
            v = rotate_roll_180_yaw_90(v)
        else:
            assert orient == 0, orient
        v = v + ofs
        v = v * params[f"COMPASS_SCALE{tag}"]
        v = m @ v
        if motct in (1, 2):  # throttle (0-1) or current (A): the compensation comes after the matrix
            v = v + mot * u
        out.append(v)
    return np.array(out)


#: PX4's ``get_rot_matrix(ROTATION_ROLL_180_YAW_90)``: ``Dcmf(Eulerf(pi, 0, pi/2))`` = Rz(90) Rx(180).
PX4_ROLL_180_YAW_90 = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


def px4_field(params, raw_G, n, power):
    """``Magnetometer::Correct`` for ``CAL_MAG{n}``, sample by sample (G)."""
    off = np.array([params[f"CAL_MAG{n}_{a}OFF"] for a in "XYZ"])
    d = [params[f"CAL_MAG{n}_{a}SCALE"] for a in "XYZ"]
    o = [params[f"CAL_MAG{n}_{a}ODIAG"] for a in "XYZ"]
    s = np.array([[d[0], o[0], o[1]], [o[0], d[1], o[2]], [o[1], o[2], d[2]]])
    comp = np.array([params.get(f"CAL_MAG{n}_{a}COMP", 0.0) for a in "XYZ"])
    rot = {0: np.eye(3), 10: PX4_ROLL_180_YAW_90}[int(params.get(f"CAL_MAG{n}_ROT", 0))]
    if params.get("CAL_MAG_COMP_TYP", 0) == 0:
        power = np.zeros(len(raw_G))
    return np.array([rot @ (s @ ((v + p * comp) - off)) for v, p in zip(raw_G, power)])


# -- simulated flights ---------------------------------------------------------------------------------------------


def as_throttle(ds, full_scale=1.0):
    """The flight with its motor current replaced by a throttle column (current / 30 A, times ``full_scale``)."""
    extra = {k: v for k, v in ds.extra.items() if k != "current_A"}
    extra["throttle"] = full_scale * np.asarray(ds.extra["current_A"]) / FULL_THROTTLE_A
    return ds.replace(extra=extra)


@pytest.fixture(scope="module")
def flights():
    """Two flights of a two-compass vehicle whose compasses see ~25 nT per ampere, each mounted ~2 deg off
    ROLL_180_YAW_90; the first fitted by the vector calibration with its current term."""
    truth = vehicle_truth(n_sensors=2, seed=11, current=True)
    one, _ = simulate_vehicle(truth, seed=11, n=2000)
    two, _ = simulate_vehicle(truth, seed=12, n=600)
    cal = fit_vector(one, resolve_vector_reference(one), terms=["current"], warn=False).calibration
    thr_one = as_throttle(one)
    cal_thr = fit_vector(thr_one, resolve_vector_reference(thr_one), terms=["current"], warn=False).calibration
    return {"current_A": (cal, two), "throttle": (cal_thr, as_throttle(two))}


def motor_input(ds, column):
    return np.asarray(ds.extra[column], dtype=float)


# -- ArduPilot -----------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("column", ["current_A", "throttle"])
def test_ardupilot_motor_compensation_and_custom_rotation_give_the_body_field(flights, column, tmp_path):
    cal, two = flights[column]
    assert current_compensation(cal)[1] == [column, column]
    path = tmp_path / "cal.json"
    cal.save(path)
    out = tmp_path / "compass.parm"
    assert main(["export", str(path), "--format", "ardupilot", "-o", str(out)]) == 0  # nothing refused
    params = parse_parameter_file(out.read_text())
    assert params["COMPASS_MOTCT"] == {"current_A": 2, "throttle": 1}[column]
    assert params["CUST_ROT_ENABLE"] == 1 and params["COMPASS_ORIENT"] == 101 and params["COMPASS_ORIENT2"] == 102
    body = cal.correct(two)  # magcal's corrected body-frame field, nT
    u = motor_input(two, column)
    for compass in (1, 2):
        firmware = ardupilot_field(params, two.readings_nT[compass - 1] / 100.0, compass, u) * 100.0
        assert np.max(np.abs(firmware - body[compass - 1])) < 1.0
        # the motor compensation is doing real work: without it the compass is tens of nT off
        off = dict(params, COMPASS_MOTCT=0)
        worst = np.max(np.linalg.norm(ardupilot_field(off, two.readings_nT[compass - 1] / 100, compass, u) * 100
                                      - body[compass - 1], axis=1))  # fmt: skip
        assert worst > 100.0


def test_ardupilot_units_and_signs_on_a_known_term():
    """Identity compass, no bias, 100 nT per A along x: ArduPilot adds -1 mG per A after its matrix; PX4 adds
    -1 G per kA (100 nT/A = 1e-3 G/A) to the raw reading."""
    platform = PlatformTerms(current_nT_per_unit=np.array([[100.0, 0.0, -50.0]]), current_column="current_A")
    cal = Calibration([SensorCalibration(np.diag([2.0, 1.0, 1.0]), np.zeros(3))], 50_000.0, frame="body",
                      mode="vector", platform=platform)  # fmt: skip
    ap = export_calibration(cal, "ardupilot").parameters
    assert [ap[f"COMPASS_MOT_{a}"] for a in "XYZ"] == pytest.approx([-2.0, 0.0, 0.5])  # M k / 100, M = diag(2,1,1)
    assert ap["COMPASS_MOTCT"] == 2 and ap["COMPASS_ORIENT"] == 0 and "CUST_ROT_ENABLE" not in ap
    px = export_calibration(cal, "px4").parameters
    assert [px[f"CAL_MAG0_{a}COMP"] for a in "XYZ"] == pytest.approx([-1.0, 0.0, 0.5])  # before the matrix
    assert px["CAL_MAG_COMP_TYP"] == 2


# -- PX4 -----------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("column", ["current_A", "throttle"])
def test_px4_power_compensation_gives_the_body_field_up_to_the_stated_rotation(flights, column, tmp_path):
    cal, two = flights[column]
    path = tmp_path / "cal.json"
    cal.save(path)
    # PX4 holds only listed rotations: the mounting's remainder is refused, never the current term
    with pytest.raises(MagcalError) as refused:
        export_calibration(cal, "px4")
    assert "cannot be stored" in str(refused.value) and "current" not in str(refused.value)
    out = tmp_path / "mag.params"
    assert main(["export", str(path), "--format", "px4", "--force", "-o", str(out)]) == 0
    text = out.read_text()
    params = parse_parameter_file(text)
    assert params["CAL_MAG_COMP_TYP"] == {"current_A": 2, "throttle": 1}[column]
    assert "\tCAL_MAG_COMP_TYP\t" in text and "\tCAL_MAG0_ROT\t10\t6" in text  # integers typed INT32 for QGC
    result = export_calibration(cal, "px4", force=True)
    body = cal.correct(two)
    u = motor_input(two, column)
    power = u * 1e-3 if column == "current_A" else u  # PX4's power: the current in kA, or the throttle
    for n in (0, 1):
        firmware = px4_field(params, two.readings_nT[n] / 1e5, n, power) * 1e5
        frame = result.sensors[n].frame_rotation  # the remainder of the mounting, listed as dropped
        assert np.max(np.abs(np.linalg.norm(firmware, axis=1) - np.linalg.norm(body[n], axis=1))) < 1.0
        assert np.max(np.abs(firmware @ frame.T - body[n])) < 1.0
        no_comp = px4_field(dict(params, CAL_MAG_COMP_TYP=0), two.readings_nT[n] / 1e5, n, power) * 1e5
        assert np.max(np.abs(no_comp @ frame.T - body[n])) > 100.0


# -- where the term lives: the catalogue effect, and the platform terms of files of earlier versions -------------


def as_platform(cal):
    """The same calibration with its current term as the platform terms of calibration files of earlier versions."""
    other = copy.deepcopy(cal)
    (effect,) = cal.model.effects
    k = np.array([cal.effect_values[f"current_field:{s + 1}"] for s in range(cal.n_sensors)])
    other.model, other.effect_values = None, {}
    other.platform = PlatformTerms(current_nT_per_unit=k, current_column=effect.column)
    return other


@pytest.mark.parametrize("column", ["current_A", "throttle"])
def test_the_current_term_is_read_from_the_platform_terms_and_the_catalogue_alike(flights, column):
    cat, two = flights[column]
    cal = as_platform(cat)
    assert np.allclose(cat.correct(two), cal.correct(two), atol=1e-9)  # the same correction, held elsewhere
    k_platform, columns_platform = current_compensation(cal)
    k_catalogue, columns_catalogue = current_compensation(cat)
    assert np.allclose(k_platform, cal.platform.current_nT_per_unit) and np.allclose(k_catalogue, k_platform)
    assert columns_platform == columns_catalogue == [column, column]
    for fmt in ("ardupilot", "px4", "c"):
        a = export_calibration(cal, fmt, force=True)
        b = export_calibration(cat, fmt, force=True)
        assert a.parameters == b.parameters and a.dropped == b.dropped
    # and through the calibration file
    back = Calibration.from_dict(cat.to_dict())
    assert export_calibration(back, "ardupilot").parameters == export_calibration(cal, "ardupilot").parameters
    # no current term at all: nothing of the motor compensation is written
    bare = copy.deepcopy(cat)
    bare.model, bare.effect_values = None, {}
    assert current_compensation(bare) == (None, [None, None])
    assert not any("MOT" in n for n in export_calibration(bare, "ardupilot").parameters)


def test_other_catalogue_effects_of_a_vector_calibration_are_refused_not_lost(flights):
    """After the move into the catalogue a vector calibration may hold effects the firmware cannot: they are named,
    while its current_field is written."""
    cal, _ = flights["current_A"]
    cat = copy.deepcopy(cal)
    cat.model.effects.append(TemperatureBias(sensor=0))
    cat.effect_values["temperature_bias:1"] = np.array([2.0, -1.0, 0.5])
    with pytest.raises(MagcalError, match=r"effect temperature_bias:1: the firmware has no parameter"):
        export_calibration(cat, "ardupilot")
    forced = export_calibration(cat, "ardupilot", force=True)
    assert forced.dropped == [
        "effect temperature_bias:1: the firmware has no parameter for it (its correction is dropped)"
    ]
    assert forced.parameters["COMPASS_MOTCT"] == 2


def mixed(cal):
    """Sensor 1's field follows the current, sensor 2's the throttle (catalogue effects, one per sensor)."""
    k = np.asarray(current_compensation(cal)[0])
    other = copy.deepcopy(cal)
    other.model = Model(cal.n_sensors, effects=[CurrentField(sensor=0, column="current_A"),
                                                CurrentField(sensor=1, column="throttle")])  # fmt: skip
    other.effect_values = {"current_field:1": k[0].copy(), "current_field:2": FULL_THROTTLE_A * k[1]}
    return other


def test_one_compensation_type_per_firmware_refuses_mixed_columns_the_c_header_keeps_both(flights):
    cal, two = flights["current_A"]
    both = mixed(cal)
    data = two.replace(extra={**two.extra, "throttle": motor_input(two, "current_A") / FULL_THROTTLE_A})
    for fmt, name in (("ardupilot", "COMPASS_MOTCT"), ("px4", "CAL_MAG_COMP_TYP")):
        with pytest.raises(MagcalError, match=rf"sensor 2: its field follows throttle .*\({name}\)"):
            export_calibration(both, fmt)
        forced = export_calibration(both, fmt, force=True)
        assert forced.current_column == "current_A" and forced.parameters[name] == 2
        second = [v for n, v in forced.parameters.items() if n.startswith(("COMPASS_MOT2_", "CAL_MAG1_")) and
                  n.endswith(("_X", "_Y", "_Z", "XCOMP", "YCOMP", "ZCOMP"))]  # fmt: skip
        assert len(second) == 3 and not any(second)  # written as 0: an old value must not stay active
        assert any(line.startswith("sensor 2: its field follows throttle") for line in forced.dropped)
    header = export_calibration(both, "c")
    assert not header.dropped
    body = both.correct(data)
    for e, column in zip(header.sensors, ("current_A", "throttle")):
        assert e.current_column == column and f'#define MAGCAL_S{e.sensor}_CURRENT_COLUMN "{column}"' in header.text
        firmware = e.firmware_corrected_nT(data.readings_nT[e.sensor - 1], motor_input(data, column))
        assert np.max(np.abs(firmware - body[e.sensor - 1])) < 1e-6


# -- the throttle's scale ------------------------------------------------------------------------------------------


def test_a_throttle_column_in_percent_is_scaled_to_full_throttle(flights, tmp_path, capsys):
    cal, two = flights["throttle"]
    percent = copy.deepcopy(cal)
    percent.effect_values = {k: np.asarray(v) / 100.0 for k, v in cal.effect_values.items()}  # per percent
    unit = export_calibration(cal, "ardupilot")
    assert any("--throttle-full-scale 100" in n for n in unit.notes)  # 0-1 assumed, and said
    scaled = export_calibration(percent, "ardupilot", throttle_full_scale=100)
    for a in "XYZ":
        for tag in ("", "2"):
            assert scaled.parameters[f"COMPASS_MOT{tag}_{a}"] == pytest.approx(unit.parameters[f"COMPASS_MOT{tag}_{a}"])
    with pytest.raises(MagcalError, match="positive number"):
        export_calibration(percent, "px4", force=True, throttle_full_scale=0)
    current, _ = flights["current_A"]
    path = tmp_path / "cal.json"
    current.save(path)
    assert main(["export", str(path), "--format", "px4", "--force", "--throttle-full-scale", "100"]) == 2
    err = capsys.readouterr().err
    assert "no field per unit of a throttle column (theirs follows current_A)" in err and "Traceback" not in err


# -- ArduPilot's custom rotation: which compasses, and the right angle without it -----------------------------------


def test_custom_rotations_go_to_compasses_1_and_2_only():
    truth = vehicle_truth(n_sensors=3, seed=4, current=True)
    ds, _ = simulate_vehicle(truth, seed=4, n=1500)
    cal = fit_vector(ds, resolve_vector_reference(ds), terms=["current"], warn=False).calibration
    with pytest.raises(MagcalError, match=r"sensor 3: its mounting is the right angle ROLL_180_YAW_90"):
        export_calibration(cal, "ardupilot")
    forced = export_calibration(cal, "ardupilot", force=True)
    p = forced.parameters
    assert (p["COMPASS_ORIENT"], p["COMPASS_ORIENT2"], p["COMPASS_ORIENT3"]) == (101, 102, 10)
    assert any(n.startswith("compass 3: ArduPilot's two custom rotations are kept for compasses 1 and 2")
               for n in forced.notes)  # fmt: skip
    # sensor 3 exported alone to compass 1 takes custom rotation 1, and is held whole
    alone = export_calibration(cal, "ardupilot", sensors=[3], slots=[1])
    assert not alone.dropped and alone.parameters["COMPASS_ORIENT"] == 101
    body = cal.correct(ds)[2]
    u = motor_input(ds, "current_A")
    assert np.max(np.abs(ardupilot_field(alone.parameters, ds.readings_nT[2] / 100, 1, u) * 100 - body)) < 1.0
    # the right angle, as before, when asked: the remainder is refused (the firmware's vector is turned by it)
    with pytest.raises(MagcalError, match="cannot be stored"):
        export_calibration(cal, "ardupilot", sensors=[1], custom_rotation=False)
    right = export_calibration(cal, "ardupilot", sensors=[1], custom_rotation=False, force=True)
    assert right.parameters["COMPASS_ORIENT"] == 10 and "CUST_ROT_ENABLE" not in right.parameters
    firmware = ardupilot_field(right.parameters, ds.readings_nT[0] / 100, 1, u) * 100
    assert np.max(np.abs(firmware @ right.sensors[0].frame_rotation.T - cal.correct(ds)[0])) < 1.0


# -- the bundle, the page and the vehicle take the same parameters --------------------------------------------------


def test_bundle_and_send_carry_the_motor_compensation(flights):
    cal, two = flights["current_A"]
    content, readme = export_all(cal)
    with zipfile.ZipFile(BytesIO(content)) as zf:
        parm = zf.read("compass.parm").decode()
        names = set(zf.namelist())
    assert parm.encode() == parameter_bytes(cal, "ardupilot")[0]
    assert "COMPASS_MOTCT,2" in parm and "COMPASS_MOT2_Z," in parm and "CUST_ROT1_YAW," in parm
    assert "mag.params" not in names  # PX4 cannot hold the mounting's remainder: a README line, not the current
    line = next(x for x in readme if x.strip().startswith("mag.params: not written"))
    assert "cannot be stored" in line and "current" not in line
    sent = values_to_send(parm, "ardupilot")  # magcal send takes the custom rotation's parameters too
    assert {"CUST_ROT_ENABLE", "CUST_ROT1_ROLL", "COMPASS_MOTCT", "COMPASS_MOT_X"} <= set(sent)


def test_the_page_exports_what_the_command_line_writes(flights, bench, tmp_path, monkeypatch):
    cal, two = flights["current_A"]
    wb = bench(ds=two, name="flight.csv")
    wb.ctrl.calibration = cal  # a vector calibration with its current term
    wb.handle(wb.exporting.do_export_format, None, "ardupilot")
    name, content = wb.downloads.last
    assert name == "compass.parm" and b"COMPASS_MOTCT,2" in content
    (tmp_path / "cli").mkdir()
    monkeypatch.chdir(tmp_path / "cli")
    cal_file = tmp_path / "cli" / "calibration.json"
    cal_file.write_bytes(wb.exporting._calibration()[1])
    assert main(["export", "calibration.json", "--format", "ardupilot", "-o", "compass.parm"]) == 0
    assert (tmp_path / "cli" / "compass.parm").read_bytes() == content


@pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler")
def test_c_header_with_the_current_compiles_and_corrects(flights, tmp_path):
    cal, two = flights["current_A"]
    header = tmp_path / "magcal_cal.h"
    header.write_text(export_calibration(cal, "c").text)
    n = 5
    raw = two.readings_nT[0][:n]
    u = motor_input(two, "current_A")[:n]
    rows = ",".join("{" + ",".join(repr(float(x)) for x in v) + "}" for v in raw)
    amps = ",".join(repr(float(x)) for x in u)
    program = tmp_path / "main.c"
    program.write_text(f"""#include <stdio.h>
#include "magcal_cal.h"
int main(void) {{
    const double raw[{n}][3] = {{{rows}}};
    const double amps[{n}] = {{{amps}}};
    for (int k = 0; k < {n}; k++) {{
        double d[3], b[3];
        for (int i = 0; i < 3; i++) d[i] = raw[k][i] - MAGCAL_S1_BIAS_NT[i] - MAGCAL_S1_CURRENT_NT_PER_UNIT[i] * amps[k];
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
        subprocess.run([str(exe)], capture_output=True, text=True, check=True, timeout=30).stdout.split("\n")[:n]
    )
    assert np.max(np.abs(out - cal.correct(two)[0][:n])) < 1.0  # float32 parameters


@pytest.mark.parametrize(("column", "unit"), [("current_A", "A"), ("throttle", "unit")])
def test_the_current_terms_parameters_are_named_in_the_columns_unit_and_old_names_still_read(flights, column, unit):
    """A current in amperes gives ``k_x_nT_per_A``; a file saved with the former ``k_x_nT_per_unit`` names reads
    back to the same correction."""
    cal, two = flights[column]
    doc = cal.to_dict()
    entries = [e for e in doc["effect_params"] if e["effect"] == "current_field"]
    assert len(entries) == 2
    names = {n for e in entries for n in e["params"]}
    assert names == {f"k_{a}_nT_per_{unit}" for a in "xyz"}
    for e in entries:  # as a calibration of an earlier version saved them
        e["params"] = {n.replace("_per_A", "_per_unit"): v for n, v in e["params"].items()}
    old = Calibration.from_dict(doc)
    assert np.allclose(old.correct(two), cal.correct(two), atol=1e-9)
