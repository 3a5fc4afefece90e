"""Send to vehicle (magcal.output.vehicle_params, magcal send) against a fake autopilot on loopback
(tests/helpers/fake_autopilot.py): every value read back equals what ``magcal export`` writes; a vehicle that drops or
alters a value is reported as failed; the old values are backed up before anything is written."""

from __future__ import annotations

import time

import numpy as np
import pytest

import magcal
from magcal.cli import main
from magcal.core.errors import MagcalError
from magcal.data.simulation import ArrayTruth, SensorErrors
from magcal.output.export import parse_parameter_file
from magcal.output.vehicle_params import mavlink_device, send_parameters, values_to_send

pytest.importorskip("pymavlink")

from tests.helpers.fake_autopilot import FakeAutopilot, free_udp_port

#: Bound on one send (the fake answers within milliseconds; a failure retries with these short waits).
SEND_BOUND_S = 30.0


@pytest.fixture(scope="module")
def cal_path(tmp_path_factory):
    errors = SensorErrors(
        matrix=np.array([[1.03, 0.02, -0.01], [0.0, 0.98, 0.02], [0.0, 0.0, 1.01]]),
        bias_nT=np.array([1200.0, -700.0, 2100.0]),
    )
    truth = ArrayTruth(sensors=[errors], total_nT=50_000.0, declination_deg=0.0, inclination_deg=60.0)
    ds = magcal.simulate(truth, n_samples=300, noise_nT=2.0, seed=4)
    path = tmp_path_factory.mktemp("send") / "calibration.json"
    magcal.calibrate(ds, reference_total_nT=50_000.0).calibration.save(path)
    return path


def exported(cal_path, fmt, tmp_path):
    out = tmp_path / f"params.{fmt}"
    assert main(["export", str(cal_path), "--format", fmt, "-o", str(out)]) == 0
    return parse_parameter_file(out.read_text())


def vehicle_table(names, extra=()):
    """The vehicle's table before: every parameter at a value other than the one to write."""
    table = {n: -7.5 for n in names}
    table.update({n: 0.0 for n in extra})
    return table


@pytest.mark.parametrize("fmt", ["ardupilot", "px4"])
def test_every_value_read_back_equals_magcal_export(cal_path, fmt, tmp_path, capsys):
    params = exported(cal_path, fmt, tmp_path)
    port = free_udp_port()
    backup = tmp_path / "backup.parm"
    t0 = time.monotonic()
    with FakeAutopilot(vehicle_table(params, ["COMPASS_USE", "CAL_MAG1_XOFF"]), port, bytewise=fmt == "px4") as fake:
        rc = main(
            [
                "send",
                str(cal_path),
                "--format",
                fmt,
                "--url",
                f"udp://127.0.0.1:{port}?mavlink",
                "--yes",
                "--backup",
                str(backup),
                "--timeout",
                "0.5",
            ]
        )
        vehicle = dict(fake.params)
    assert time.monotonic() - t0 < SEND_BOUND_S
    assert rc == 0
    # the vehicle holds, as float32, exactly what the exported file says; nothing else was touched
    for name, value in params.items():
        assert np.float32(vehicle[name]) == np.float32(value), name
    assert vehicle.get("COMPASS_USE", 0.0) == 0.0 and vehicle.get("CAL_MAG1_XOFF", 0.0) == 0.0
    # the old values were saved first, in a file magcal send restores from
    old = parse_parameter_file(backup.read_text())
    assert old == {n: -7.5 for n in params}
    out = capsys.readouterr().out
    assert f"{len(params)} of {len(params)} parameter(s) written and read back equal" in out


@pytest.mark.parametrize("fault", ["drop", "alter"])
def test_a_value_the_vehicle_drops_or_alters_is_reported_failed(cal_path, fault, tmp_path):
    params = values_to_send(_export_text(cal_path, tmp_path), "ardupilot")  # what magcal export writes
    bad = "COMPASS_DIA_Y"
    port = free_udp_port()
    t0 = time.monotonic()
    with FakeAutopilot(vehicle_table(params), port, **{fault: [bad]}) as fake:
        report = send_parameters(
            f"udp://127.0.0.1:{port}?mavlink",
            params,
            "ardupilot",
            backup_path=tmp_path / "b.parm",
            answer_timeout_s=0.3,
        )
        tried = [n for n, _ in fake.sets if n == bad]
    assert time.monotonic() - t0 < SEND_BOUND_S
    assert not report.ok
    assert [r.name for r in report.failed] == [bad]
    failed = report.failed[0]
    assert failed.old == pytest.approx(-7.5)
    expect = -7.5 if fault == "drop" else params[bad] * 1.01
    assert failed.read_back == pytest.approx(expect, rel=1e-6)
    assert len(tried) == 3  # retried a bounded number of times
    assert "FAILED: COMPASS_DIA_Y" in report.text()
    others = [r for r in report.results if r.name != bad]
    assert all(r.ok and np.float32(r.read_back) == np.float32(r.new) for r in others)


def _export_text(cal_path, tmp_path):
    out = tmp_path / "c.parm"
    assert main(["export", str(cal_path), "--format", "ardupilot", "-o", str(out)]) == 0
    return out.read_text()


def test_cli_fails_with_status_3_when_a_value_is_not_read_back(cal_path, tmp_path):
    params = exported(cal_path, "ardupilot", tmp_path)
    port = free_udp_port()
    with FakeAutopilot(vehicle_table(params), port, alter=["COMPASS_OFS_Z"]):
        rc = main(
            ["send", str(cal_path), "--format", "ardupilot", "--url", f"udp://127.0.0.1:{port}", "--yes"]
            + ["--backup", str(tmp_path / "b.parm"), "--timeout", "0.3"]
        )
    assert rc == 3


def test_restore_sends_the_backup_back(cal_path, tmp_path):
    params = exported(cal_path, "ardupilot", tmp_path)
    port = free_udp_port()
    backup = tmp_path / "backup.parm"
    url = f"udp://127.0.0.1:{port}?mavlink"
    with FakeAutopilot(vehicle_table(params), port) as fake:
        report = send_parameters(url, params, backup_path=backup, answer_timeout_s=0.3)
        assert report.ok
        assert main(["send", str(backup), "--url", url, "--yes", "--backup", str(tmp_path / "b2.parm")]) == 0
        assert all(fake.params[n] == -7.5 for n in params)


def test_unknown_parameter_stops_before_anything_is_written(cal_path, tmp_path):
    params = exported(cal_path, "ardupilot", tmp_path)
    port = free_udp_port()
    table = vehicle_table(params)
    del table["COMPASS_ODI_Z"]  # a vehicle without it (another firmware, another compass)
    backup = tmp_path / "backup.parm"
    with FakeAutopilot(table, port) as fake:
        with pytest.raises(MagcalError, match="COMPASS_ODI_Z.*nothing was sent"):
            send_parameters(f"udp://127.0.0.1:{port}", params, backup_path=backup, retries=2, answer_timeout_s=0.2)
        assert fake.sets == []
    assert not backup.exists()


def test_declined_confirmation_writes_nothing(cal_path, tmp_path):
    params = exported(cal_path, "ardupilot", tmp_path)
    port = free_udp_port()
    shown = []
    with FakeAutopilot(vehicle_table(params), port) as fake:
        report = send_parameters(
            f"udp://127.0.0.1:{port}", params, confirm=lambda r: shown.append(r.rows()) or False, answer_timeout_s=0.3
        )
        assert fake.sets == []
    assert report.declined and not report.ok
    assert shown and [row[0] for row in shown[0]] == list(params)
    assert all(row[1] == "-7.5" for row in shown[0])


def test_no_vehicle_is_a_clear_error_within_the_bound(tmp_path):
    port = free_udp_port()
    t0 = time.monotonic()
    with pytest.raises(MagcalError, match="no vehicle heartbeat"):
        send_parameters(f"udp://127.0.0.1:{port}", {"COMPASS_OFS_X": 1.0}, heartbeat_timeout_s=0.5)
    assert time.monotonic() - t0 < 5.0


def test_refused_connections_and_values(tmp_path):
    exe = tmp_path / "prog"
    exe.write_text("#!/bin/sh\n")
    with pytest.raises(MagcalError, match="a file, not a serial port"):
        mavlink_device(str(exe))
    with pytest.raises(MagcalError, match="use udp"):
        mavlink_device("http://127.0.0.1:80")
    assert mavlink_device("udp://127.0.0.1:14550?mavlink") == ("udpin:127.0.0.1:14550", 115200)
    with pytest.raises(MagcalError, match=r"MAVLink over IPv6 \(::1\) is not supported"):
        mavlink_device("tcp://[::1]:5760")  # pymavlink would read "::1:5760" by its colons
    assert mavlink_device("serial:///dev/ttyACM0?baud=57600") == ("/dev/ttyACM0", 57600)
    with pytest.raises(MagcalError, match="not ardupilot compass parameters"):
        values_to_send("CAL_MAG0_XOFF,1\n", "ardupilot")
    with pytest.raises(MagcalError, match="no parameter"):
        values_to_send("# nothing\n", "px4")
