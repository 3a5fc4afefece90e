"""The Files tab's Export section (magcal_workbench.exporting): every download is byte for byte what the command
line writes from the downloaded calibration.json (``magcal export``, ``magcal apply``), in a real headless Chromium
(the download captured from the page's link); refusals become lines of the zip's README; *Send to vehicle* shows
only for a MAVLink source, reads old -> new first, writes on Confirm, and every value read back equals what
``magcal export`` writes (a fake autopilot on loopback, tests/helpers/fake_autopilot.py). Every wait is bounded."""

from __future__ import annotations

import io
import zipfile
from pathlib import Path

import numpy as np
import pytest

import magcal
from magcal.cli import main
from magcal.data import io as mio
from magcal.output.export import parse_parameter_file
from tests.workbench.test_workbench_live import _wait

ARTIFACTS = Path(__file__).resolve().parents[2] / "test-artifacts"
#: Files of the single-sensor export and the button that downloads each.
BUTTONS = {
    "calibration.json": "calibration.json",
    "compass.parm": "ArduPilot .parm",
    "mag.params": "PX4 .params",
    "magcal_calibration.h": "C header (.h)",
    "corrected.csv": "Corrected CSV (magcal apply)",
    "corrected.parquet": "Corrected Parquet",
    "raw_mask.csv": "Raw data + fit mask (CSV)",
    "magcal_export.zip": "Export all (.zip)",
}
#: Gross outliers put into the recording (the page's "Reject beyond k sigma" finds them).
OUTLIERS = (17, 90, 151, 233)
WAIT_MS = 120_000


def one_sensor_with_outliers():
    ds = magcal.simulate("ding2024", seed=3)
    readings = ds.readings_nT.copy()
    readings[0, list(OUTLIERS)] += 3000.0
    return ds.replace(readings_nT=readings)


def command_line(tmp_path, monkeypatch, data_path, mask_file=None):
    """What the command line writes from ``tmp_path/cli/calibration.json`` (the page's download), run there so the
    files name the calibration as the page does."""
    cli = tmp_path / "cli"
    monkeypatch.chdir(cli)
    out = {}
    for fmt, name in (("ardupilot", "compass.parm"), ("px4", "mag.params"), ("c", "magcal_calibration.h")):
        assert main(["export", "calibration.json", "--format", fmt, "-o", f"out-{name}"]) == 0
        out[name] = (cli / f"out-{name}").read_bytes()
    for name in ("corrected.csv", "corrected.parquet"):
        assert main(["apply", "calibration.json", str(data_path), "-o", f"out-{name}", "--no-progress"]) == 0
        out[name] = (cli / f"out-{name}").read_bytes()
    mask = ["--mask", str(mask_file)] if mask_file else []
    assert main(["export", "calibration.json", "--format", "mask", "--data", str(data_path), "-o", "m.csv"] + mask) == 0
    out["raw_mask.csv"] = (cli / "m.csv").read_bytes()
    assert main(["export", "calibration.json", "--format", "all", "--data", str(data_path), "-o", "a.zip"] + mask) == 0
    out["magcal_export.zip"] = (cli / "a.zip").read_bytes()
    # the calibration file itself: what magcal writes when it saves the calibration it reads
    magcal.Calibration.load(cli / "calibration.json").save(cli / "resaved.json")
    out["calibration.json"] = (cli / "resaved.json").read_bytes()
    return out


def unzip(content):
    with zipfile.ZipFile(io.BytesIO(content)) as zf:
        return {n: zf.read(n) for n in zf.namelist()}


@pytest.mark.e2e
@pytest.mark.slow
def test_each_export_downloads_equal_to_the_command_line(browser, bench, tmp_path, monkeypatch):
    wb = bench(one_sensor_with_outliers(), name="one.csv")  # written to tmp_path/one.csv and opened from it
    path = tmp_path / "one.csv"
    context = browser.new_context(accept_downloads=True, viewport={"width": 1400, "height": 1000})
    try:
        page = context.new_page()
        page.goto(wb.url, wait_until="domcontentloaded")
        page.wait_for_function(
            "() => document.body && document.body.innerText.includes('Total-field RMS')", timeout=WAIT_MS
        )
        page.get_by_role("button", name="Run the chosen method").click(timeout=WAIT_MS)
        page.wait_for_function("() => /Total-field RMS: [0-9.]+ nT/.test(document.body.innerText)", timeout=WAIT_MS)
        assert wb.worker.wait(120)
        page.get_by_role("tab", name="Outliers").click(timeout=WAIT_MS)
        page.get_by_role("button", name="Reject beyond k sigma").click(timeout=WAIT_MS)
        page.wait_for_function("() => /Rejected: [1-9]\\d* of 300/.test(document.body.innerText)", timeout=WAIT_MS)
        assert wb.worker.wait(120)
        rejected = np.flatnonzero(~wb.ctrl.state.kept)
        assert set(OUTLIERS) <= set(rejected.tolist())

        page.get_by_role("tab", name="Files").click(timeout=WAIT_MS)
        got = {}
        for name, label in BUTTONS.items():
            page.get_by_role("button", name=label, exact=True).click(timeout=WAIT_MS)
            link = page.locator(f'a[download="{name}"]').last
            link.wait_for(timeout=WAIT_MS)
            with page.expect_download(timeout=WAIT_MS) as info:
                link.click(timeout=WAIT_MS)
            got[name] = open(info.value.path(), "rb").read()
            for close in page.locator(".mantine-Notification-closeButton").all():
                try:
                    close.click(timeout=2000)
                except Exception:  # already gone
                    pass
        ARTIFACTS.mkdir(exist_ok=True)
        page.screenshot(path=str(ARTIFACTS / "workbench_export.png"))
    finally:
        context.close()

    (tmp_path / "cli").mkdir()
    (tmp_path / "cli" / "calibration.json").write_bytes(got["calibration.json"])
    (tmp_path / "cli" / "raw_mask.csv").write_bytes(got["raw_mask.csv"])
    want = command_line(tmp_path, monkeypatch, path, mask_file=tmp_path / "cli" / "raw_mask.csv")
    for name in BUTTONS:
        if name == "magcal_export.zip":
            continue
        assert got[name] == want[name], name

    # the mask is the page's: the outliers rejected there are 0 in the file, the residuals are the fit's
    mask = mio.read_csv(tmp_path / "cli" / "raw_mask.csv")
    kept = np.asarray(mask.extra["kept"], dtype=int)
    assert np.flatnonzero(kept == 0).tolist() == rejected.tolist()
    assert np.all(
        np.abs(np.asarray(mask.extra["s1_residual_nT"])[list(OUTLIERS)]) > 200.0
    )  # |B| moved by the 3000 nT push
    assert np.sqrt(np.mean(np.asarray(mask.extra["s1_residual_nT"])[kept == 1] ** 2)) < 3.0

    # the zip holds every file the command line's zip holds, the same bytes, plus the session
    page_zip, cli_zip = unzip(got["magcal_export.zip"]), unzip(want["magcal_export.zip"])
    assert set(page_zip) == set(cli_zip) | {"session.json"}
    for name in set(cli_zip) - {"README.txt"}:
        assert page_zip[name] == cli_zip[name] == got.get(name, page_zip[name]), name
    assert b"Not written" not in page_zip["README.txt"]
    assert parse_parameter_file(page_zip["compass.parm"].decode())["COMPASS_SCALE"] == 1.0


def _as_browser(handle, value):
    """What a browser's update does: the value is set (viser checks nothing), then the widget's callbacks run."""
    from viser import GuiEvent

    handle._impl.value = value
    for cb in list(handle._impl.update_cb):
        cb(GuiEvent(None, None, handle))


def test_refusals_are_readme_lines_and_messages_not_crashes(bench):
    wb = bench()  # the four-sensor cross: no single-compass firmware file holds it
    wb.actions.do_calibrate(None)
    assert wb.worker.wait(120) and wb.ctrl.calibration is not None
    wb.handle(wb.exporting.do_export_format, None, "ardupilot")
    assert "sensor 4 would go to slot 4" in wb.ctrl.message
    wb.handle(wb.exporting.do_export_all, None)
    name, content = wb.downloads.last
    assert name == "magcal_export.zip"
    files = unzip(content)
    readme = files["README.txt"].decode()
    assert "compass.parm: not written: sensor 4 would go to slot 4" in readme
    assert "mag.params: not written" in readme and "rotation R" in readme
    assert {"calibration.json", "corrected.csv", "raw_mask.csv", "session.json"} <= set(files)
    assert "compass.parm" not in files


def test_send_to_vehicle_shows_for_mavlink_previews_then_writes(bench, tmp_path):
    pytest.importorskip("pymavlink")
    from tests.helpers.fake_autopilot import FakeAutopilot, free_udp_port

    ds = magcal.simulate("ding2024", seed=3)
    wb = bench(ds=ds, name="one.csv")
    wb.actions.do_calibrate(None)
    assert wb.worker.wait(120)
    section, panels = wb.panels.export, wb.panels
    assert not section.btn_send.visible  # the default source is simulated
    mav = next(label for label in panels.live_source.options if label.startswith("UDP MAVLink"))
    _as_browser(panels.live_source, mav)
    assert section.btn_send.visible and not section.btn_confirm.visible
    port = free_udp_port()
    _as_browser(panels.live_port, port)

    (tmp_path / "cli").mkdir()
    wb.handle(wb.exporting.do_export_format, None, "ardupilot")
    params = parse_parameter_file(wb.downloads.last[1].decode())
    with FakeAutopilot({n: -7.5 for n in params}, port) as fake:
        wb.handle(wb.exporting.do_send_preview, None)
        assert wb.worker.wait(60)
        wb.ui.wait(10)
        assert fake.sets == []  # the first click writes nothing
        assert "| -7.5 |" in section.send_info.content and section.btn_confirm.visible
        wb.handle(wb.exporting.do_send_confirm, None)
        assert wb.worker.wait(60)
        wb.ui.wait(10)
        vehicle = dict(fake.params)
    assert "every value read back equal" in wb.ctrl.message
    assert f"all {len(params)} parameter(s) equal" in section.send_info.content
    for name, value in params.items():
        assert np.float32(vehicle[name]) == np.float32(value), name
    backups = list((wb.store.folder(wb.ctrl.session_id)).glob("vehicle-backup-*.parm"))
    assert len(backups) == 1 and parse_parameter_file(backups[0].read_text()) == {n: -7.5 for n in params}
    # a Confirm without a fresh preview writes nothing
    wb.handle(wb.exporting.do_send_confirm, None)
    assert "press Send to vehicle again" in wb.ctrl.message
    # a firmware the page did not offer is refused before anything is read
    _as_browser(section.firmware, "px4; rm -rf /")
    wb.handle(wb.exporting.do_send_preview, None)
    assert "not one of the choices offered" in wb.ctrl.message and section.firmware.value == "ardupilot"


@pytest.mark.e2e
@pytest.mark.slow
def test_send_to_vehicle_in_the_page(browser, bench, tmp_path):
    """In Chromium: choose the UDP MAVLink source and its port, Send to vehicle (old -> new, nothing written),
    Confirm (written): the page's read-back table says every value equal, and the fake vehicle holds what
    ``magcal export`` writes."""
    pytest.importorskip("pymavlink")
    from tests.helpers.fake_autopilot import FakeAutopilot, free_udp_port

    wb = bench(magcal.simulate("ding2024", seed=3), name="one.csv")
    port = free_udp_port()
    page = browser.new_page(viewport={"width": 1400, "height": 1000})
    try:
        page.goto(wb.url, wait_until="domcontentloaded")
        page.wait_for_function(
            "() => document.body && document.body.innerText.includes('Total-field RMS')", timeout=WAIT_MS
        )
        page.get_by_role("button", name="Run the chosen method").click(timeout=WAIT_MS)
        page.wait_for_function("() => /Total-field RMS: [0-9.]+ nT/.test(document.body.innerText)", timeout=WAIT_MS)
        assert wb.worker.wait(120)
        (tmp_path / "cli").mkdir()
        wb.exporting.do_export_calibration(None)  # what the calibration.json button downloads
        (tmp_path / "cli" / "calibration.json").write_bytes(wb.downloads.last[1])
        cal, parm = str(tmp_path / "cli" / "calibration.json"), str(tmp_path / "cli" / "c.parm")
        assert main(["export", cal, "--format", "ardupilot", "-o", parm]) == 0
        params = parse_parameter_file((tmp_path / "cli" / "c.parm").read_text())

        page.get_by_role("tab", name="Files").click(timeout=WAIT_MS)
        assert not page.get_by_role("button", name="Send to vehicle").is_visible()
        fid = page.locator("label:text-is('Live source')").get_attribute("for")
        page.locator(f'[id="{fid}"]').click(timeout=WAIT_MS)
        page.get_by_role("option", name="UDP MAVLink on 127.0.0.1 (port below)").click(timeout=WAIT_MS)
        page.get_by_role("button", name="Send to vehicle").wait_for(timeout=WAIT_MS)
        box = page.get_by_label("Port (UDP/TCP)", exact=True)
        box.fill(str(port))
        box.press("Enter")
        assert _wait(lambda: wb.panels.live_port.value == port, 20)
        with FakeAutopilot({n: -7.5 for n in params}, port) as fake:
            page.get_by_role("button", name="Send to vehicle").click(timeout=WAIT_MS)
            page.wait_for_function("() => document.body.innerText.includes('Read from the vehicle')", timeout=WAIT_MS)
            assert fake.sets == []
            page.get_by_role("button", name="Confirm: write to the vehicle").click(timeout=WAIT_MS)
            page.wait_for_function(
                f"() => document.body.innerText.includes('Written and read back: all {len(params)} parameter(s) "
                "equal')",
                timeout=WAIT_MS,
            )
            vehicle = dict(fake.params)
        page.get_by_role("button", name="Confirm: write to the vehicle").wait_for(state="hidden", timeout=WAIT_MS)
        page.locator("text=Written and read back").scroll_into_view_if_needed()
        ARTIFACTS.mkdir(exist_ok=True)
        page.screenshot(path=str(ARTIFACTS / "workbench_send_to_vehicle.png"))
    finally:
        page.close()
    for name, value in params.items():
        assert np.float32(vehicle[name]) == np.float32(value), name


def test_send_shows_for_an_allowed_mavlink_url_only(bench):
    wb = bench(live_allow=("udp://0.0.0.0:14551?mavlink", "udp://0.0.0.0:14552?format=lines"))
    panels = wb.panels
    for label, shown in (
        ("allowed: udp://0.0.0.0:14551?mavlink", True),
        ("allowed: udp://0.0.0.0:14552?format=lines", False),
        ("UDP text lines on 127.0.0.1 (port below)", False),
        ("UDP MAVLink on 127.0.0.1 (port below)", True),
    ):
        _as_browser(panels.live_source, label)
        assert wb.exporting.mavlink_chosen() is shown, label
        assert panels.export.btn_send.visible is shown, label
