"""Vector calibration with attitude: frames, the reference vector, the fit against a simulated vehicle's
truth, the calibration file, apply's world components and the firmware export."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from magcal.calibration.calibration import Calibration
from magcal.checks.coverage import calibration_input_checks
from magcal.checks.reference import (
    igrf_ned_nT,
    igrf_total_nT,
    parse_reference_vector,
    resolve_vector_reference,
)
from magcal.cli import main
from magcal.core.errors import MagcalError
from magcal.data.attitude import attitude, euler_to_wxyz, wxyz_rotation
from magcal.data.dataset import Dataset, dataset_columns, dataset_metadata
from magcal.data.io import write_csv
from magcal.data.vehicle import simulate_vehicle, vehicle_truth
from magcal.fitting.pipeline import calibrate
from magcal.fitting.vector import fit_vector, true_calibration
from magcal.geometry.orientations import (
    FIRMWARE_ROTATIONS,
    RIGHT_ANGLES,
    euler_matrix,
    firmware_rotation,
    nearest_right_angle,
)
from magcal.output.export import apply_ardupilot, apply_px4, export_calibration

ROLL_180_YAW_90 = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
ROLL_90_YAW_90 = euler_matrix(90, 0, 90)
PITCH_270 = euler_matrix(0, 270, 0)


def _world_rms(calibration, ds):
    """RMS per component of the world (NED) field against the reference, and of |B| against |B_ref| (nT)."""
    world = calibration.world(ds)[0]
    ref = resolve_vector_reference(ds).ned_nT
    total = np.linalg.norm(world, axis=1) - np.linalg.norm(ref, axis=1)
    return float(np.sqrt(np.mean((world - ref) ** 2))), float(np.sqrt(np.mean(total**2)))


# -- frames --------------------------------------------------------------------------------------------------------
def test_the_24_right_angles_all_have_a_firmware_number():
    assert RIGHT_ANGLES.shape == (24, 3, 3)
    assert len({tuple(m.ravel()) for m in RIGHT_ANGLES}) == 24
    assert all(np.isclose(np.linalg.det(m), 1.0) for m in RIGHT_ANGLES)
    numbers = {firmware_rotation(m) for m in RIGHT_ANGLES}
    assert None not in numbers and len(numbers) == 24
    # ArduPilot's rotate(): ROTATION_ROLL_180_YAW_90 makes (x, y, z) -> (y, x, -z); YAW_90 (x, y) -> (-y, x)
    assert firmware_rotation(ROLL_180_YAW_90) == 10
    assert np.allclose(euler_matrix(*FIRMWARE_ROTATIONS[2]) @ [1.0, 2.0, 3.0], [-2.0, 1.0, 3.0])


@pytest.mark.parametrize("k", [0, 5, 17, 23])
def test_nearest_right_angle_and_the_angle_off_it(k):
    off = Rotation.from_rotvec(np.radians(3.0) * np.array([0.6, -0.8, 0.0])).as_matrix()
    found, angle = nearest_right_angle(RIGHT_ANGLES[k] @ off)
    assert np.allclose(found, RIGHT_ANGLES[k]) and angle == pytest.approx(3.0, abs=1e-9)


def test_euler_columns_are_aerospace_zyx_body_to_ned():
    q = euler_to_wxyz([0.0, 0.0, 30.0], [0.0, 10.0, 0.0], [90.0, 0.0, 0.0])
    r = wxyz_rotation(q)
    nose = r.apply(np.array([1.0, 0.0, 0.0]))
    assert np.allclose(nose[0], [0.0, 1.0, 0.0], atol=1e-12)  # yaw 90: the nose points east
    assert nose[1][2] < 0 and np.degrees(np.arcsin(-nose[1][2])) == pytest.approx(10.0)  # pitch up: nose above
    right_wing = r.apply(np.array([0.0, 1.0, 0.0]))[2]
    assert right_wing[2] == pytest.approx(np.sin(np.radians(30.0)))  # roll right: the right wing goes down
    ds = Dataset(
        np.zeros((1, 3, 3)),
        extra={
            "roll_deg": np.array([0.0, 0.0, 30.0]),
            "pitch_deg": np.array([0.0, 10.0, 0.0]),
            "yaw_deg": np.array([90.0, 0.0, 0.0]),
        },
    )
    assert np.allclose(attitude(ds).as_matrix(), r.as_matrix())
    with pytest.raises(MagcalError, match="roll_deg, pitch_deg, yaw_deg"):
        attitude(Dataset(np.zeros((1, 3, 3)), extra={"roll_deg": np.zeros(3)}))


# -- the reference vector -----------------------------------------------------------------------------------------
def test_vector_reference_from_columns_vector_and_igrf():
    n = 5
    ds = Dataset(np.zeros((1, n, 3)), extra={"ref_n": np.full(n, 2e4), "ref_e": np.zeros(n), "ref_d": np.full(n, 4e4)})
    ref = resolve_vector_reference(ds)
    assert ref.kind == "column" and np.allclose(ref.ned_nT, [2e4, 0.0, 4e4])
    given = resolve_vector_reference(ds, vector="19000, 500, 45000")
    assert given.kind == "vector" and np.allclose(given.ned_nT[3], [19000, 500, 45000])
    place = resolve_vector_reference(ds, reference="igrf", lat=45.0, lon=7.0, alt_km=0.5, date="2020-06-01")
    total, comps = igrf_total_nT(45.0, 7.0, 0.5, "2020-06-01")
    assert place.kind == "igrf" and np.allclose(
        place.ned_nT[0], [comps["north_nT"], comps["east_nT"], comps["down_nT"]]
    )
    assert np.linalg.norm(place.ned_nT[0]) == pytest.approx(total)
    assert resolve_vector_reference(Dataset(np.zeros((1, n, 3)))) is None
    with pytest.raises(MagcalError, match="ref_n, ref_e, ref_d"):
        resolve_vector_reference(Dataset(np.zeros((1, n, 3)), extra={"ref_n": np.zeros(n)}))
    with pytest.raises(MagcalError, match="three numbers"):
        parse_reference_vector("1,2")
    with pytest.raises(MagcalError, match="uT"):
        parse_reference_vector("20,1,44")  # uT given as nT


def test_igrf_along_a_long_track_is_interpolated_within_a_nanotesla():
    n = 6000  # more than the nodes: evaluated at 2000 samples and interpolated
    lat = np.linspace(44.0, 45.0, n) + 0.01 * np.sin(np.linspace(0, 20, n))
    lon = np.linspace(7.0, 8.5, n)
    alt_m = 1000.0 + 200.0 * np.sin(np.linspace(0, 3, n))
    ds = Dataset(np.zeros((1, n, 3)), extra={"lat": lat, "lon": lon, "alt_m": alt_m})
    ref = resolve_vector_reference(ds, reference="igrf", date="2020-06-01")
    assert ref.kind == "igrf-track" and ref.ned_nT.shape == (n, 3)
    check = np.arange(1, n, 397)
    exact = igrf_ned_nT(lat[check], lon[check], alt_m[check] / 1000.0, "2020-06-01")
    assert np.max(np.abs(ref.ned_nT[check] - exact)) < 1.0
    assert np.ptp(ref.ned_nT[:, 0]) > 50  # the field changes along the track and the reference follows it


# -- the fit against the truth ------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "mounting, seed",
    [(ROLL_180_YAW_90, 1), (ROLL_90_YAW_90, 2), (PITCH_270, 3), (np.eye(3), 4)],
    ids=["roll180yaw90", "roll90yaw90", "pitch270", "none"],
)
def test_vehicle_calibrated_on_one_flight_gives_world_components_on_another(mounting, seed):
    truth = vehicle_truth(seed=seed, mounting=mounting, off_deg=2.0)
    cal_flight, tr = simulate_vehicle(truth, seed=seed, n=4000, noise_nT=3.0, attitude_noise_deg=0.02)
    test_flight, _ = simulate_vehicle(truth, seed=seed + 100, n=4000, noise_nT=3.0, attitude_noise_deg=0.02)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # nothing to warn about on a good record
        result = fit_vector(cal_flight, resolve_vector_reference(cal_flight), terms=[])
    fit = result.sensors[0]
    ours, ours_total = _world_rms(result.calibration, test_flight)
    best, best_total = _world_rms(true_calibration(tr), test_flight)
    assert ours <= 1.15 * best, (ours, best)
    assert ours_total <= 1.15 * best_total, (ours_total, best_total)
    # the mounting: the right angle, and how far off it (2 deg) the sensor sits
    assert np.allclose(fit.right_angle, mounting)
    true_r = true_calibration(tr).sensors[0].R
    assert np.degrees(Rotation.from_matrix(fit.mounting.T @ true_r).magnitude()) < 0.02
    assert fit.angle_off_deg == pytest.approx(2.0, abs=0.02)
    assert fit.orientation_margin > 3
    # the vector residual sits at the attitude error times the field, the total-field residual at the noise
    field = np.linalg.norm(tr.field_ned_nT)
    assert fit.rms_perpendicular_nT == pytest.approx(np.hypot(np.radians(0.02) * field, 3.0), rel=0.1)
    assert fit.rms_total_field_nT == pytest.approx(3.0, rel=0.1)
    assert fit.attitude_noise_deg == pytest.approx(0.02, rel=0.15)
    # the total-field fit of the same record is told that it is not determined
    scalar_data = cal_flight.replace(reference_total_nT=float(field))
    assert any("coverage" in w for w in calibration_input_checks(scalar_data))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        scalar = calibrate(scalar_data)
    assert any("weak coverage" in w for w in scalar.warnings)


def test_platform_terms_are_recovered_and_matter():
    truth = vehicle_truth(seed=7, eddy=True, current=True)
    flight, tr = simulate_vehicle(truth, seed=7, n=6000)
    other, _ = simulate_vehicle(truth, seed=8, n=6000)
    ref = resolve_vector_reference(flight)
    assert fit_vector(flight, ref, warn=False).terms == []  # nothing beyond the base model unless asked
    result = fit_vector(flight, ref, effects=["eddy_currents", "current_field"])
    assert result.terms == ["eddy_currents", "current_field"]
    assert fit_vector(flight, ref, terms=["eddy", "current"], warn=False).terms == result.terms  # the old names
    s, t = result.sensors[0], tr.sensors[0]
    assert np.max(np.abs(s.terms["current_nT_per_unit"] - t.current_nT_per_unit)) < 0.5  # nT/A of ~25
    assert np.max(np.abs(s.terms["eddy_ms"] - t.eddy_ms)) < 1.5  # ms of ~10
    with_terms, _ = _world_rms(result.calibration, other)
    best, _ = _world_rms(true_calibration(tr), other)
    assert with_terms <= 1.15 * best
    without, _ = _world_rms(fit_vector(flight, ref, terms=[]).calibration, other)
    assert without > 1.5 * with_terms  # the current's field is hundreds of nT: leaving it out shows


def test_given_noises_weight_the_fit_and_are_reported():
    truth = vehicle_truth(seed=3)
    flight, _ = simulate_vehicle(truth, seed=3, n=2000, attitude_noise_deg=0.1)
    res = fit_vector(flight, resolve_vector_reference(flight), terms=[], attitude_noise_deg=0.1, noise_nT=3.0)
    s = res.sensors[0]
    assert s.attitude_noise_source == "given" and s.attitude_noise_deg == 0.1
    assert s.sigma_perpendicular_nT == pytest.approx(np.hypot(np.radians(0.1) * 48_769.0, 3.0), rel=1e-3)
    assert s.rms_perpendicular_nT == pytest.approx(np.radians(0.1) * 48_769.0, rel=0.1)  # 85 nT
    assert "total-field residual RMS" in res.text() and "perpendicular" in res.text()


def test_vector_fit_refuses_data_without_attitude():
    ds = Dataset(np.ones((1, 50, 3)))
    ref = resolve_vector_reference(ds, vector="20000,0,44000")
    with pytest.raises(MagcalError, match="attitude"):
        fit_vector(ds, ref)


# -- the calibration file, apply, export -------------------------------------------------------------------------
def test_vector_calibration_json_round_trip_and_old_files_load_as_scalar(tmp_path):
    truth = vehicle_truth(seed=5, eddy=True, current=True)
    flight, _ = simulate_vehicle(truth, seed=5, n=1500)
    cal = fit_vector(flight, resolve_vector_reference(flight), effects=["eddy_currents", "current_field"]).calibration
    cal.save(tmp_path / "cal.json")
    back = Calibration.load(tmp_path / "cal.json")
    assert back.mode == "vector" and back.frame == "body" and back.platform is None
    assert back.model.effect_labels == ["eddy_currents", "current_field"]
    assert np.allclose(back.world(flight), cal.world(flight))
    doc = json.loads((tmp_path / "cal.json").read_text())
    assert doc["sensors"][0]["mounting_rotation_number"] == 10
    # a file of an earlier version held the same terms as platform_terms: it loads and corrects the same
    values = cal.effect_values
    old_doc = {k: v for k, v in doc.items() if k not in ("effects", "effect_params", "base_terms", "base_covariance")}
    old_doc["platform_terms"] = {
        "eddy_ms": [np.reshape(values["eddy_currents:1"], (3, 3)).tolist()],
        "current_nT_per_unit": [np.asarray(values["current_field:1"]).tolist()],
        "current_column": "current_A",
    }
    earlier = Calibration.from_dict(old_doc)
    assert earlier.platform.names == ["eddy", "current"] and earlier.model is None
    assert np.max(np.abs(earlier.world(flight) - cal.world(flight))) < 1e-6
    for key in ("mode", "vector_fit"):
        old_doc.pop(key)
    old_doc.pop("platform_terms")
    old = Calibration.from_dict(old_doc)
    assert old.mode == "scalar" and old.platform is None
    with pytest.raises(MagcalError, match="world components need a vector calibration"):
        old.world(flight)
    old_doc["platform_terms"] = {"eddy_ms": [[1, 2]]}
    with pytest.raises(MagcalError, match="platform_terms.eddy_ms"):
        Calibration.from_dict(old_doc)


def test_world_tensor_of_the_cross_recovers_a_world_gradient():
    """Four sensors on the vehicle, calibrated in a uniform field, then flown through a field with a gradient G
    (nT/m, NED): the tensor in world coordinates is G. The cross lies along sensor 1's axes (mounted
    ROLL_180_YAW_90): without turning the body-frame vectors into the cross's frame, eq. 1 would mix the axes."""
    grad = np.array([[20.0, 5.0, -3.0], [5.0, -8.0, 4.0], [-3.0, 4.0, -12.0]])
    truth = vehicle_truth(seed=23, n_sensors=4)
    one, _ = simulate_vehicle(truth, seed=23, n=4000, baseline_m=0.5)
    two, tr = simulate_vehicle(truth, seed=24, n=4000, baseline_m=0.5, gradient_ned_nT_per_m=grad)
    cal = fit_vector(one, resolve_vector_reference(one), terms=[]).calibration
    g_world = cal.world_tensor(two)
    assert np.max(np.abs(g_world.mean(axis=0) - grad)) < 0.6  # noise of the mean ~0.2 nT/m
    truth_cal = true_calibration(tr)
    truth_cal.baseline_m = 0.5
    assert np.max(np.abs(truth_cal.world_tensor(two).mean(axis=0) - grad)) < 0.6
    # in the cross's frame the same tensor, turned by the attitude and sensor 1's mounting
    from magcal.core import conventions

    g_cross = conventions.tensor_matrix(cal.tensor(two))
    r = attitude(two).as_matrix() @ cal.tensor_frame()
    assert np.allclose(g_world[7], r[7] @ g_cross[7] @ r[7].T)


def _write_flight(path, ds, euler=False):
    cols = dataset_columns(ds)
    if euler:
        ypr = wxyz_rotation(ds.attitude_wxyz).as_euler("ZYX", degrees=True)
        for q in ("qw", "qx", "qy", "qz"):
            cols.pop(q)
        cols["roll_deg"], cols["pitch_deg"], cols["yaw_deg"] = ypr[:, 2], ypr[:, 1], ypr[:, 0]
    write_csv(path, cols, dataset_metadata(ds))


def test_cli_calibrate_apply_export_in_vector_mode(tmp_path, capsys):
    truth = vehicle_truth(seed=11, current=True)
    one, tr = simulate_vehicle(truth, seed=11, n=2000)
    two, _ = simulate_vehicle(truth, seed=12, n=2000)
    _write_flight(tmp_path / "one.csv", one)
    _write_flight(tmp_path / "two.csv", two, euler=True)  # the other attitude form
    args = ["calibrate", str(tmp_path / "one.csv"), "-o", str(tmp_path / "cal.json"), "--json"]
    assert main(args + ["--effects", "eddy_currents,current_field"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["mode"] == "vector" and doc["terms"] == ["eddy_currents", "current_field"]
    held = {tuple(r["terms"]): r["held_total_nT"] for r in doc["validation"]["rows"]}
    assert held[("eddy_currents", "current_field")] < 0.5 * held[()]  # the current's field carries to held-out data
    assert doc["sensors"][0]["mounting_right_angle"].startswith("ROLL_180_YAW_90")
    out = tmp_path / "out.csv"
    assert main(["apply", str(tmp_path / "cal.json"), str(tmp_path / "two.csv"), "-o", str(out)]) == 0
    import pandas as pd

    frame = pd.read_csv(out, comment="#")
    world = frame[["s1n_cal", "s1e_cal", "s1d_cal"]].to_numpy()
    assert np.sqrt(np.mean((world - tr.field_ned_nT) ** 2)) < 25  # attitude error 0.02 deg on 48.8 uT: 17 nT
    # scalar mode on the same file: the old fit, told it is undetermined
    assert main(["calibrate", str(tmp_path / "one.csv"), "--mode", "scalar", "--reference", "48769"]) == 0
    assert "undetermined" in capsys.readouterr().err
    # export: the right angle as the orientation parameter, the rest refused unless forced
    with pytest.raises(MagcalError):
        export_calibration(Calibration.load(tmp_path / "cal.json"), "px4")
    cal = Calibration.load(tmp_path / "cal.json")
    cal.model, cal.effect_values = None, {}  # what the firmware's correction leaves out: the effects
    px4 = export_calibration(cal, "px4", force=True)
    ardu = export_calibration(cal, "ardupilot", force=True, custom_rotation=False)  # custom: test_export_current
    assert px4.parameters["CAL_MAG0_ROT"] == 10 and ardu.parameters["COMPASS_ORIENT"] == 10
    raw = one.readings_nT[0][:200]
    body = cal.correct(
        one.replace(
            readings_nT=one.readings_nT[:, :200],
            time_s=one.time_s[:200],
            attitude_wxyz=one.attitude_wxyz[:200],
            extra={},
        )
    )[0]
    bound = px4.sensors[0].vector_error_nT
    fw_px4 = apply_px4(px4.parameters, raw / 1e5) * 1e5
    fw_ardu = apply_ardupilot(ardu.parameters, raw / 100.0) * 100.0
    assert np.allclose(np.linalg.norm(fw_px4, axis=1), np.linalg.norm(body, axis=1), rtol=1e-6)
    assert np.max(np.linalg.norm(fw_px4 - body, axis=1)) <= bound
    assert np.allclose(fw_ardu, fw_px4, atol=1e-3)
    header = export_calibration(cal, "c")  # the C header holds the whole R C^-1: nothing dropped
    assert not header.dropped and np.allclose(header.sensors[0].matrix, cal.sensors[0].R @ cal.sensors[0].cinv)


def test_cli_vector_mode_needs_attitude_and_a_field_vector(tmp_path, capsys):
    truth = vehicle_truth(seed=1)
    ds, _ = simulate_vehicle(truth, seed=1, n=300)
    bare = ds.replace(attitude_wxyz=None)
    _write_flight(tmp_path / "bare.csv", bare)
    assert main(["calibrate", str(tmp_path / "bare.csv"), "--mode", "vector"]) != 0
    assert "needs the attitude" in capsys.readouterr().err
    no_ref = ds.replace(extra={})
    _write_flight(tmp_path / "noref.csv", no_ref)
    assert main(["calibrate", str(tmp_path / "noref.csv"), "--mode", "vector"]) != 0
    assert "field vector" in capsys.readouterr().err
    assert (
        main(
            [
                "calibrate",
                str(tmp_path / "noref.csv"),
                "--mode",
                "vector",
                "--reference-vector",
                "21000,1200,44000",
                "--platform-terms",
                "none",
            ]
        )
        == 0
    )
    assert "ROLL_180_YAW_90" in capsys.readouterr().out


def test_magnav_reader_and_study_on_a_synthetic_file(tmp_path):
    """benchmarks/real/magnav_vector.py on a file with the MagNav HDF5 fields, written from the simulated vehicle
    flying where IGRF gives the simulated field: the reader's conventions (ins_* angles, utm_z, line numbers, the
    date from year/doy) must give back the truth."""
    h5py = pytest.importorskip("h5py")
    import importlib.util
    import pathlib

    script = pathlib.Path(__file__).resolve().parents[2] / "benchmarks" / "real" / "magnav_vector.py"
    spec = importlib.util.spec_from_file_location("magnav_vector", script)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    lat, lon, alt_m = 45.3, -75.7, 5182.0
    field = igrf_ned_nT(lat, lon, alt_m / 1000.0, "2020-07-06")[0]
    truth = vehicle_truth(seed=21, field_ned_nT=field)
    parts = [simulate_vehicle(truth, seed=21 + k, n=1500, attitude_noise_deg=0.05)[0] for k in range(2)]
    fields = {
        name: []
        for name in (
            "flux_d_x",
            "flux_d_y",
            "flux_d_z",
            "tt",
            "mag_1_c",
            "ins_roll",
            "ins_pitch",
            "ins_yaw",
            "lat",
            "lon",
            "utm_z",
            "line",
            "year",
            "doy",
        )
    }
    for k, ds in enumerate(parts):
        ypr = wxyz_rotation(ds.attitude_wxyz).as_euler("ZYX", degrees=True)
        n = ds.n_samples
        for a, axis in enumerate("xyz"):
            fields[f"flux_d_{axis}"].append(ds.readings_nT[0, :, a])
        fields["tt"].append(ds.time_s + 1000.0 * k)
        fields["mag_1_c"].append(np.full(n, np.linalg.norm(field)))
        fields["ins_yaw"].append(ypr[:, 0])
        fields["ins_pitch"].append(ypr[:, 1])
        fields["ins_roll"].append(ypr[:, 2])
        fields["lat"].append(np.full(n, lat))
        fields["lon"].append(np.full(n, lon))
        fields["utm_z"].append(np.full(n, alt_m))
        fields["line"].append(np.full(n, 1006.04 if k == 0 else 1006.06))
        fields["year"].append(np.full(n, 2020.0))
        fields["doy"].append(np.full(n, 188.0))
    path = tmp_path / "Flt1006_train.h5"
    with h5py.File(path, "w") as h5:
        for name, values in fields.items():
            h5[name] = np.concatenate(values)
    segments = mod.read_segments(path, ["1006.04", "1006.06"])
    assert segments["1006.04"].metadata["date"] == "2020-07-06"
    result = mod.study(segments, "1006.04", ["1006.06"], terms=[])
    test = result["tests"]["1006.06"]
    floor = np.hypot(np.sqrt(2 / 3) * np.radians(0.05) * np.linalg.norm(field), 3.0)
    assert test["world_rms_nT"] < 1.15 * floor
    assert test["F_vs_mag1c"]["vector"] < 4.0 and test["F_vs_igrf"]["vector"] < 4.0
    assert test["F_vs_mag1c"]["raw"] > 100 * test["F_vs_mag1c"]["vector"]
    assert result["calibration"]["vector"]["sensors"][0]["mounting_right_angle"].startswith("ROLL_180_YAW_90")


def test_reported_standard_deviations_match_the_spread_over_seeds():
    truth = vehicle_truth(seed=30)
    true_cal = None
    errors_b, errors_r, sd_b, sd_r = [], [], [], []
    probe, _ = simulate_vehicle(truth, seed=99, n=50, roll_max_deg=60, pitch_max_deg=40)  # directions off the cone
    fields, field_sd = [], []
    for seed in range(12):
        ds, tr = simulate_vehicle(truth, seed=100 + seed, n=1500, attitude_noise_deg=0.05)
        true_cal = true_cal or true_calibration(tr)
        result = fit_vector(ds, resolve_vector_reference(ds), terms=[])
        fit = result.sensors[0]
        fields.append(result.calibration.correct(probe)[0])
        field_sd.append(result.calibration.uncertainty(probe)["vector_sd_nT"][0])
        errors_b.append(fit.bias_nT - true_cal.sensors[0].bias_nT)
        errors_r.append(np.degrees(Rotation.from_matrix(fit.mounting @ true_cal.sensors[0].R.T).as_rotvec()))
        sd_b.append(fit.bias_sd_nT)
        sd_r.append(fit.mounting_sd_deg)
    for errors, sds in ((errors_b, sd_b), (errors_r, sd_r)):
        ratio = np.sqrt(np.mean(np.square(errors), axis=0)) / np.mean(sds, axis=0)
        assert np.all((ratio > 0.5) & (ratio < 2.0)), ratio
    # the calibration's error bars on the corrected field (magcal apply --uncertainty), against the spread
    spread = np.std(fields, axis=0, ddof=1)
    ratio = np.sqrt(np.mean(spread**2)) / np.sqrt(np.mean(np.mean(field_sd, axis=0) ** 2))
    assert 0.6 < ratio < 1.6, ratio


def test_robust_fit_ignores_spikes():
    truth = vehicle_truth(seed=9)
    ds, tr = simulate_vehicle(truth, seed=9, n=3000)
    other, _ = simulate_vehicle(truth, seed=10, n=3000)
    rng = np.random.default_rng(0)
    spikes = rng.choice(ds.n_samples, 30, replace=False)
    readings = ds.readings_nT.copy()
    readings[0, spikes, rng.integers(0, 3, 30)] += rng.choice([-1, 1], 30) * 5000.0
    spiky = ds.replace(readings_nT=readings)
    ref = resolve_vector_reference(spiky)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        plain = fit_vector(spiky, ref, terms=[])
    assert plain.sensors[0].n_outliers >= 30 and any("--robust" in str(w.message) for w in caught)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        robust = fit_vector(spiky, ref, terms=[], robust=True)
    best, _ = _world_rms(true_calibration(tr), other)
    ours, _ = _world_rms(robust.calibration, other)
    spoiled, _ = _world_rms(plain.calibration, other)
    assert ours <= 1.15 * best and spoiled > 1.3 * ours


def test_apply_to_parquet_writes_world_components_equal_to_the_csv_path(tmp_path):
    pytest.importorskip("pyarrow")
    import pandas as pd

    from magcal.data import io as mio

    truth = vehicle_truth(seed=14, eddy=True, current=True)
    one, _ = simulate_vehicle(truth, seed=14, n=1500)
    two, _ = simulate_vehicle(truth, seed=15, n=1500)
    cal = fit_vector(one, resolve_vector_reference(one), effects=["eddy_currents", "current_field"]).calibration
    cal.save(tmp_path / "cal.json")
    _write_flight(tmp_path / "two.csv", two, euler=True)
    mio.write_parquet(tmp_path / "two.parquet", dataset_columns(two), dataset_metadata(two))
    assert main(["apply", str(tmp_path / "cal.json"), str(tmp_path / "two.csv"), "-o", str(tmp_path / "a.csv")]) == 0
    args = ["apply", str(tmp_path / "cal.json"), str(tmp_path / "two.parquet"), "-o", str(tmp_path / "b.parquet")]
    assert main(args) == 0
    a = pd.read_csv(tmp_path / "a.csv", comment="#")
    b = pd.read_parquet(tmp_path / "b.parquet")
    cols = ["s1x_cal", "s1y_cal", "s1z_cal", "s1n_cal", "s1e_cal", "s1d_cal"]
    assert np.allclose(a[cols].to_numpy(), b[cols].to_numpy(), atol=0.01)  # CSV: 1 pT digits
    assert np.allclose(b[cols[3:]].to_numpy(), cal.world(two)[0], atol=1e-6)
    args = ["apply", str(tmp_path / "cal.json"), str(tmp_path / "two.csv"), "-o", str(tmp_path / "c.csv")]
    assert main(args + ["--uncertainty"]) == 0  # the vector fit's covariance of R C^-1 and b, in the file
    c = pd.read_csv(tmp_path / "c.csv", comment="#")
    assert np.all((c["s1_F_sd"] > 0) & (c["s1_F_sd"] < 5)) and np.allclose(c[cols].to_numpy(), a[cols].to_numpy())


def _test_logs_module():
    import importlib.util
    import pathlib

    path = pathlib.Path(__file__).resolve().parents[1] / "data" / "test_logs.py"
    spec = importlib.util.spec_from_file_location("magcal_test_logs", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_ardupilot_log_with_attitude_and_battery_current_calibrates_in_vector_mode(tmp_path, capsys):
    """A DataFlash log (ATT attitude, BAT current, MAG in whole milligauss): magcal calibrate finds the vector
    calibration, the mounting and the field per ampere (COMPASS_MOT's quantity) from the log alone."""
    pytest.importorskip("pymavlink")
    logs = _test_logs_module()
    logs._DF_FORMATS["BAT"] = (68, "QBff", "TimeUS,Inst,Volt,Curr")
    truth = vehicle_truth(seed=17, mounting=np.eye(3), current=True)
    ds, tr = simulate_vehicle(truth, seed=17, n=3000, attitude_noise_deg=0.02)
    att = wxyz_rotation(ds.attitude_wxyz)
    messages = []
    for i in range(ds.n_samples):
        t_us = int(1_000_000 + 100_000 * i)
        roll, pitch, yaw = att[i].as_euler("ZYX", degrees=True)[::-1]
        messages.append(("ATT", (t_us, 0.0, roll, 0.0, pitch, 0.0, yaw)))
        messages.append(("BAT", (t_us - 10, 0, 22.2, float(ds.extra["current_A"][i]))))
        mag_mG = np.round(ds.readings_nT[0, i] / 100.0).astype(int)
        messages.append(("MAG", (t_us + 50, 0, *mag_mG, 0, 0, 0, 0, 0, 0, 1, 0)))
    path = tmp_path / "flight.bin"
    logs.write_dataflash(path, messages)
    n, e, d = tr.field_ned_nT
    args = ["calibrate", str(path), "--reference-vector", f"{n},{e},{d}", "--platform-terms", "current", "--json"]
    assert main(args) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["mode"] == "vector" and doc["terms"] == ["current_field"]
    (entry,) = [e for e in doc["calibration"]["effect_params"] if e["term"] == "current_field"]
    per_amp = np.array(list(entry["params"].values()))
    assert np.max(np.abs(per_amp - tr.sensors[0].current_nT_per_unit)) < 1.0  # nT/A, of ~25
    assert doc["sensors"][0]["mounting_rotation_number"] == 0
    assert doc["sensors"][0]["mounting_angle_off_deg"] == pytest.approx(2.0, abs=0.1)


def test_px4_log_battery_current_and_vector_fit(tmp_path):
    """A ULog with sensor_mag (sensor frame, gauss), vehicle_attitude and battery_status: the current comes in as
    current_A (PX4's -1 'not measured' rows left out) and the vector fit finds the mounting and the nT/A."""
    pytest.importorskip("pyulog")
    from magcal.data.logs import read_log

    logs = _test_logs_module()
    truth = vehicle_truth(seed=19, current=True)
    ds, tr = simulate_vehicle(truth, seed=19, n=2000, noise_nT=3.0, attitude_noise_deg=0.02)
    t_us = (1_000_000 + 1e6 * ds.time_s).astype(np.uint64)
    q = ds.attitude_wxyz
    mag_rows = [(int(t), int(t), 1, *(ds.readings_nT[0, i] / 1e5), 30.0, 0, True) for i, t in enumerate(t_us)]
    att_rows = [(int(t) - 1000, *q[i]) for i, t in enumerate(t_us)]
    amps = ds.extra["current_A"].copy()
    bat_rows = [(int(t) - 2000, float(a)) for t, a in zip(t_us, amps)]
    bat_rows[5] = (bat_rows[5][0], -1.0)
    logs.write_ulog(
        tmp_path / "flight.ulg",
        [
            ("sensor_mag", 0, logs.MAG_FIELDS, mag_rows),
            ("vehicle_attitude", 0, logs.ATT_FIELDS, att_rows),
            ("battery_status", 0, [("uint64_t", "timestamp"), ("float", "current_a")], bat_rows),
        ],
    )
    log = read_log(tmp_path / "flight.ulg")
    assert "current_A" in log.extra and np.allclose(log.extra["current_A"][10:-10], amps[10:-10], atol=0.2)
    res = fit_vector(log, resolve_vector_reference(log, vector=tr.field_ned_nT.tolist()), terms=["current"])
    s = res.sensors[0]
    assert firmware_rotation(s.right_angle) == 10 and s.angle_off_deg == pytest.approx(2.0, abs=0.05)
    assert np.max(np.abs(s.terms["current_nT_per_unit"] - tr.sensors[0].current_nT_per_unit)) < 1.0


@pytest.mark.parametrize("with_terms", [True, False])
def test_held_out_check_judges_the_platform_terms(with_terms):
    from magcal.fitting.vector import validate_vector

    truth = vehicle_truth(seed=7, eddy=with_terms, current=with_terms)
    ds, _ = simulate_vehicle(truth, seed=7, n=4000)
    if not with_terms:  # the same channels, no platform field in the readings
        ds.extra["current_A"] = simulate_vehicle(vehicle_truth(seed=7, current=True), seed=7, n=4000)[0].extra[
            "current_A"
        ]
    v = validate_vector(ds, resolve_vector_reference(ds))
    rows = {tuple(r["terms"]): r for r in v.rows}
    both = ("eddy_currents", "current_field")
    assert set(rows) == {(), both[:1], both[1:], both}
    base, full = rows[()], rows[both]
    if with_terms:
        assert full["held_total_nT"] < 0.2 * base["held_total_nT"]
        assert full["held_vector_nT"] < 0.5 * base["held_vector_nT"]
        assert full["held_total_nT"] < 1.1 * 3.0  # at the sensor noise
    else:
        assert full["held_total_nT"] > 0.98 * base["held_total_nT"]  # nothing to gain on new data
    assert "held out" in v.text()


def test_simulated_attitude_error_has_its_size_and_correlation_time():
    truth = vehicle_truth(seed=4)
    ds, tr = simulate_vehicle(truth, seed=4, n=20000, rate_hz=10.0, attitude_noise_deg=0.1, attitude_tau_s=2.0)
    err = np.degrees((wxyz_rotation(tr.attitude_wxyz).inv() * wxyz_rotation(ds.attitude_wxyz)).as_rotvec())
    assert np.std(err, axis=0) == pytest.approx([0.1] * 3, rel=0.1)
    lag = 20  # 2 s = tau: correlation 1/e
    corr = [np.corrcoef(err[:-lag, k], err[lag:, k])[0, 1] for k in range(3)]
    assert np.allclose(corr, np.exp(-1.0), atol=0.08)


def test_the_diagnosis_proposes_the_current_field_and_the_fit_recovers_it():
    """The current's field is also a catalogue effect: a scalar record with a current_A column and a hidden
    current field is diagnosed with it, and calibrating with it recovers the nT/A; without the column it is not
    a candidate."""
    import magcal
    from magcal.data.simulation import chi2017_truth, simulate_timeseries
    from magcal.model.terms import EFFECTS

    effect = EFFECTS["current_field"]()
    ds = simulate_timeseries(
        chi2017_truth(1), n_samples=1500, noise_nT=3.0, seed=3, perturbations=[effect.perturbation(8.0)]
    )
    assert "current_A" in ds.extra
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        d = magcal.diagnose(ds)
    assert d.explained_by and d.explained_by[0].startswith("current_field"), d.explained_by
    res = magcal.calibrate(ds, effects=["current_field"])
    (k,) = [v for label, v in res.calibration.effect_values.items() if label.startswith("current_field")]
    assert np.allclose(k, effect.true_params(8.0, 0), atol=0.3)  # nT/A
    bare = ds.replace(extra={})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        names = {c.effect for c in magcal.diagnose(bare).candidates}
    assert "current_field" not in names


def test_apply_writes_the_tensor_in_world_coordinates_for_the_four_sensor_cross(tmp_path):
    import pandas as pd

    from magcal.core import conventions

    truth = vehicle_truth(seed=23, n_sensors=4)
    one, _ = simulate_vehicle(truth, seed=23, n=800)
    two, _ = simulate_vehicle(truth, seed=24, n=400)
    one, two = one.replace(baseline_m=0.5), two.replace(baseline_m=0.5)
    cal = fit_vector(one, resolve_vector_reference(one), terms=[]).calibration
    assert cal.baseline_m == 0.5
    cal.save(tmp_path / "cal.json")
    _write_flight(tmp_path / "two.csv", two)
    assert main(["apply", str(tmp_path / "cal.json"), str(tmp_path / "two.csv"), "-o", str(tmp_path / "o.csv")]) == 0
    out = pd.read_csv(tmp_path / "o.csv", comment="#")
    g_world = cal.world_tensor(two)
    for name, (i, j) in zip(
        ("Gnn", "Gne", "Gnd", "Gee", "Ged", "Gdd"), ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
    ):
        assert np.allclose(out[name], g_world[:, i, j], atol=2e-3), name
    g_body = conventions.tensor_matrix(cal.tensor(two))
    assert np.allclose(np.linalg.norm(g_world, axis=(1, 2)), np.linalg.norm(g_body, axis=(1, 2)))  # a rotation
    assert {"s4n_cal", "s4e_cal", "s4d_cal"} <= set(out.columns)
