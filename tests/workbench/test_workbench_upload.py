"""Opening files in the page: column mapping, units and LSB for the upload, flight-controller logs.

A file with the user's own column names is refused with the columns it holds and what to set; after setting
Columns (and Units) and re-reading the same upload -- no new upload -- it opens and fits to the simulated floor.
ArduPilot ``.bin`` and PX4 ``.ulg`` logs written by the tests open by upload.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

import magcal
from magcal.data import io as mio
from tests.data.test_logs import ardupilot_case, px4_case, write_dataflash, write_ulog
from tests.workbench.test_workbench_e2e import _open, _upload_in_page

TRUTH_NOISE_nT = 3.0


def _foreign_csv(ds, unit_factor=1.0) -> bytes:
    """One sensor's readings under the user's own names (magX...), divided by ``unit_factor``, and a time column."""
    r = ds.readings_nT[0] / unit_factor
    lines = ["time,magX,magY,magZ"] + [f"{t:.3f},{x:.17g},{y:.17g},{z:.17g}" for t, (x, y, z) in zip(ds.time_s, r)]
    return ("\n".join(lines) + "\n").encode()


def _wait_idle(wb, timeout_s=120):
    assert wb.worker.wait(timeout_s)
    time.sleep(0.05)


@pytest.mark.parametrize("units, factor", [("nT", 1.0), ("uT", 1e3), ("G", 1e5)])
def test_foreign_columns_are_named_then_mapped_and_reread(bench, units, factor):
    ds = magcal.simulate_timeseries("chi2017", n_samples=600, seed=4, rate_hz=5.0)
    wb = bench()
    content = _foreign_csv(ds, factor)
    wb.uploads.last = ("board.csv", content)
    wb.uploads.do_reread(None)
    _wait_idle(wb)
    msg = wb.ctrl.message
    assert "board.csv" in msg and "magX" in msg and "Columns box" in msg and "--columns" not in msg
    assert "time,magX,magY,magZ" in wb.panels.upload_info.content
    before = wb.ctrl.dataset.n_samples
    assert before == 300  # the bench's own data are still open: nothing was replaced by the refused file
    wb.panels.upload_columns.value = "x=magX,y=magY,z=magZ,t=time"
    wb.panels.upload_units.value = units
    wb.uploads.do_reread(None)
    _wait_idle(wb)
    got = wb.ctrl.dataset
    assert got.n_sensors == 1 and got.n_samples == 600
    np.testing.assert_allclose(got.readings_nT[0], ds.readings_nT[0], rtol=1e-6, atol=1e-3)
    wb.ctrl.step_calibrate("ml")
    assert wb.ctrl.residual_rms_nT() < 1.1 * TRUTH_NOISE_nT  # at the simulated noise floor


def test_reading_options_are_checked_on_the_server(bench):
    wb = bench()
    wb.panels.upload_units.value = "parsecs"  # a value the page never offered
    with pytest.raises(magcal.MagcalError, match="not one of the choices"):
        wb.uploads.read_options()
    assert wb.panels.upload_units.value == "from the file"
    with pytest.raises(magcal.MagcalError, match="upload a file first"):
        wb.uploads.do_reread(None)


def test_counts_need_and_use_the_lsb(bench):
    ds = magcal.simulate_timeseries("chi2017", n_samples=400, seed=6, rate_hz=5.0)
    wb = bench()
    wb.uploads.last = ("counts.csv", _foreign_csv(ds, 13.333))
    wb.panels.upload_columns.value = "x=magX,y=magY,z=magZ,t=time"
    wb.panels.upload_units.value = "counts"
    wb.uploads.do_reread(None)
    _wait_idle(wb)
    assert "LSB box" in wb.ctrl.message and wb.ctrl.dataset.n_samples == 300
    wb.panels.upload_lsb.value = 13.333
    wb.uploads.do_reread(None)
    _wait_idle(wb)
    np.testing.assert_allclose(wb.ctrl.dataset.readings_nT[0], ds.readings_nT[0], rtol=1e-6, atol=2e-3)


def test_a_mapped_upload_reopens_from_its_session_without_the_mapping(bench):
    ds = magcal.simulate_timeseries("chi2017", n_samples=300, seed=8, rate_hz=5.0)
    wb = bench()
    wb.uploads.last = ("mine.csv", _foreign_csv(ds))
    wb.panels.upload_columns.value = "x=magX,y=magY,z=magZ,t=time"
    wb.uploads.do_reread(None)
    _wait_idle(wb)
    sid = wb.ctrl.session_id
    kept = mio.read_csv(wb.store.data_path(sid))  # the session keeps magcal's own CSV: reads with no options
    np.testing.assert_allclose(kept.readings_nT, wb.ctrl.dataset.readings_nT, rtol=1e-9)


@pytest.mark.parametrize("kind", ["bin", "ulg"])
def test_flight_controller_logs_open_by_upload(bench, tmp_path, kind):
    if kind == "bin":
        pytest.importorskip("pymavlink")
        messages, truth, _, _ = ardupilot_case(n=300, compasses=2)
        path = tmp_path / "flight.bin"
        write_dataflash(path, messages)
        n_sensors, raw = 2, truth[0]
    else:
        pytest.importorskip("pyulog")
        topics, raw, _, _, _ = px4_case(n=250)
        path = tmp_path / "flight.ulg"
        write_ulog(path, topics)
        n_sensors = 1
    wb = bench()
    wb.panels.upload_units.value = "uT"  # does not apply to a log: said, and ignored
    wb.uploads.last = (path.name, path.read_bytes())
    wb.uploads.do_reread(None)
    _wait_idle(wb)
    got = wb.ctrl.dataset
    assert got.n_sensors == n_sensors and got.n_samples == len(raw), wb.ctrl.message
    assert np.median(np.abs(got.readings_nT[0] - raw)) < 60.0  # the firmware's correction undone, nT
    assert "ignored" in wb.ctrl.message


@pytest.mark.e2e
@pytest.mark.slow
def test_foreign_columns_fixed_in_the_page(browser, bench):
    """Through the real page: upload, read the refusal, type the mapping, choose uT, re-read, fit."""
    ds = magcal.simulate_timeseries("chi2017", n_samples=400, seed=9, rate_hz=5.0)
    wb = bench()
    page = _open(browser, wb)
    _upload_in_page(page, "board.csv", _foreign_csv(ds, 1e3))
    page.wait_for_function("() => document.body.innerText.includes('no magnetometer columns')", timeout=60_000)
    box = page.locator("label:text-is('Columns')").locator("xpath=ancestor::div[.//input][1]//input")
    box.fill("x=magX,y=magY,z=magZ,t=time")
    box.press("Enter")
    end = time.monotonic() + 20
    while wb.panels.upload_columns.value != "x=magX,y=magY,z=magZ,t=time" and time.monotonic() < end:
        time.sleep(0.1)
    wb.panels.upload_units.value = "uT"  # a dropdown: set as the page would (its value is checked the same way)
    page.get_by_role("button", name="Re-read the last upload with these").click()
    page.wait_for_function("() => document.body.innerText.includes('opened')", timeout=60_000)
    _wait_idle(wb)
    assert wb.ctrl.dataset.n_samples == 400
    np.testing.assert_allclose(wb.ctrl.dataset.readings_nT[0], ds.readings_nT[0], rtol=1e-6, atol=1e-3)
