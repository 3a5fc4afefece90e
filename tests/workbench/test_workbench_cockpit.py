"""The cockpit: the compact table, |B| against time with its region editor, the error histogram, the
tilt ring and the motion marks, the layout (no cross for one sensor, the camera framing the canvas left of the
panel), and a live session's tabs.

The plot-data functions are tested headless against known truth: a sensor simulated here with a known soft iron,
hard iron and noise, whose true correction is applied independently of magcal. The browser tests (marked ``e2e``)
start the workbench on 127.0.0.1 themselves and drive the page in headless Chromium (see tests/workbench/test_workbench_e2e.py).
"""

from __future__ import annotations

import re

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import magcal
from magcal.data.attitude import attitude_quaternions, turn_rate_dps
from magcal.data.dataset import Dataset
from magcal_workbench import motion, plots, viser_adapter
from magcal_workbench.cockpit import controller_record, range_bounds_s, samples_in_range
from magcal_workbench.panels import summary_markdown
from tests.workbench.test_workbench_live import _wait

F_nT = 50_000.0
NOISE_nT = 3.0
C_TRUE = np.array([[1.03, 0.02, -0.01], [0.0, 0.97, 0.015], [0.0, 0.0, 1.01]])
B_TRUE = np.array([400.0, -250.0, 120.0])


def _sensor(n=3000, seed=1):
    """One sensor's raw readings ``C F u + b + noise`` over random directions, and their true correction
    ``C^-1 (y - b)`` (nT)."""
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    raw = (F_nT * u) @ C_TRUE.T + B_TRUE + rng.normal(scale=NOISE_nT, size=(n, 3))
    corrected = (raw - B_TRUE) @ np.linalg.inv(C_TRUE).T
    return raw, corrected


def _record(n=3000, kept=None):
    raw, corrected = _sensor(n)
    return plots.FieldRecord(
        time_s=np.arange(n) * 0.1,
        raw_nT=raw[None],
        corrected_nT=corrected[None],
        reference_nT=np.full(n, F_nT),
        kept=np.ones(n, bool) if kept is None else kept,
    )


# --- the plot data, against known truth --------------------------------------------------------------------
def test_within_fractions_equal_an_independent_count():
    raw, corrected = _sensor()
    for pct in (1.0, 2.0, 5.0):
        count = sum(1 for y in raw if abs(np.sqrt(y @ y) - F_nT) <= pct / 100.0 * F_nT)
        got = plots.within_fractions(np.linalg.norm(raw, axis=1), F_nT, (pct,))[pct]
        assert got == pytest.approx(count / len(raw), abs=1e-12)
    # the soft iron of +-3 % puts some raw samples beyond 1 % and 2 %, none beyond 5 %
    w = plots.within_fractions(np.linalg.norm(raw, axis=1), F_nT)
    assert 0.1 < w[1.0] < 0.9 and w[1.0] < w[2.0] < w[5.0] == 1.0
    # the true correction brings every sample within 1 % (3 nT of noise is 0.006 %)
    assert plots.within_fractions(np.linalg.norm(corrected, axis=1), F_nT)[1.0] == 1.0
    assert np.isnan(plots.within_fractions([np.nan], F_nT)[1.0])


def test_the_table_figures_of_a_known_calibration():
    rec = _record()
    fig = plots.table_figures(rec)
    raw_err = np.linalg.norm(rec.raw_nT[0], axis=1) - F_nT
    assert fig["rms_raw_nT"] == pytest.approx(np.sqrt(np.mean(raw_err**2)))
    assert fig["within_corrected"][1.0] == 1.0 and fig["n_kept"] == fig["n_samples"] == 3000
    assert fig["coverage"][0] > 0.95  # random directions cover the sphere
    # the compact table shows them, with the matrix and bias given
    text = summary_markdown(fig, 3.02, 3.0, [(np.linalg.inv(C_TRUE), B_TRUE)])
    assert "1.01× floor" in text and "| x | 0.97087" in text and "400.0 |" in text and "Coverage" in text


def test_the_coverage_of_a_large_record_is_read_at_a_stride():
    """A path's neighbouring samples are far closer than the 30 deg cap: a stride reads the same coverage."""
    t = np.linspace(0, 1, 20_000)
    u = np.column_stack([np.cos(40 * t) * np.sin(1.2 * t), np.sin(40 * t) * np.sin(1.2 * t), np.cos(1.2 * t)])
    rec = plots.FieldRecord(t, F_nT * u[None], F_nT * u[None], np.full(t.size, F_nT), np.ones(t.size, bool))
    full = plots.coverage_fraction(rec, max_samples=t.size)[0]
    assert 0.3 < full < 0.95  # a part of the sphere, so that a wrong stride would show
    assert plots.coverage_fraction(rec, max_samples=2000)[0] == pytest.approx(full, abs=0.01)


@pytest.mark.parametrize("unit", ["nT", "%"])
def test_the_error_histogram_before_and_after(unit):
    kept = np.ones(3000, bool)
    kept[100:400] = False
    rec = _record(kept=kept)
    h = plots.error_histogram(rec, unit)
    m_raw = np.linalg.norm(rec.raw_nT[0][kept], axis=1)
    m_cor = np.linalg.norm(rec.corrected_nT[0][kept], axis=1)
    scale = (lambda e: 100.0 * e / F_nT) if unit == "%" else (lambda e: e)
    for key, m in (("before", m_raw), ("after", m_cor)):
        part = h[key]
        assert part["counts"].sum() == part["n"] == kept.sum()  # every kept sample counted, the tails piled in
        assert part["rms"] == pytest.approx(np.sqrt(np.mean(scale(m - F_nT) ** 2)))
        assert part["edges"][0] <= 0.0 <= part["edges"][-1]
    # the truth: after the true correction the total-field error is the noise (sigma per axis -> ~sigma on |B|)
    after_nT = h["after"]["rms"] * (F_nT / 100.0 if unit == "%" else 1.0)
    assert 0.85 * NOISE_nT < after_nT < 1.15 * NOISE_nT
    assert h["before"]["rms"] > 50 * h["after"]["rms"]
    # before a fit there is no "after"
    rec.corrected_nT = None
    assert plots.error_histogram(rec, unit)["after"] is None


def test_excluded_bands_are_the_runs_of_excluded_samples():
    t = np.arange(100.0)
    kept = np.ones(100, bool)
    kept[10:20] = False  # a stretch
    kept[50] = False  # a single sample: no band
    kept[90:] = False  # to the end
    assert plots.excluded_bands(t, kept) == [(10.0, 19.0), (90.0, 99.0)]
    assert plots.excluded_bands(t[::-1], kept[::-1]) == [(10.0, 19.0), (90.0, 99.0)]  # in time order
    assert plots.excluded_bands(t, kept, max_bands=1) == [(10.0, 19.0)]


def test_the_field_series_is_decimated_and_keeps_the_flags():
    kept = np.ones(3000, bool)
    kept[1000:1200] = False
    rec = _record(kept=kept)
    d = plots.magnitude_series(rec, max_points=500)
    assert len(d["t"]) <= 500 and d["index"][0] == 0 and d["index"][-1] == 2999
    assert np.array_equal(d["kept"], kept[d["index"]])
    assert np.allclose(d["raw"][0], np.linalg.norm(rec.raw_nT[0][d["index"]], axis=1))
    assert d["bands"] == [(100.0, pytest.approx(119.9))]
    fig = plots.magnitude_figure(rec, pending_s=(10.0, 20.0), max_points=500)
    shapes = [(s.x0, s.x1, s.fillcolor) for s in fig.layout.shapes]
    assert (100.0, pytest.approx(119.9), plots.EXCLUDED_BAND_COLOUR) in shapes
    assert (10.0, 20.0, plots.RANGE_COLOUR) in shapes


def test_a_time_range_in_percent():
    t = np.linspace(10.0, 110.0, 1001)
    assert range_bounds_s(t, 50, 20) == pytest.approx((30.0, 60.0))
    idx = samples_in_range(t, 20, 50)
    assert idx[0] == 200 and idx[-1] == 500


# --- motion: the tilt ring and fast turning ---------------------------------------------------------------
def _field_world(incl_deg=60.0, decl_deg=10.0):
    i, d = np.radians(incl_deg), np.radians(decl_deg)
    return F_nT * np.array([np.cos(i) * np.cos(d), np.cos(i) * np.sin(d), np.sin(i)])


@pytest.mark.parametrize("roll, pitch", [(0.0, 0.0), (20.0, -35.0), (-60.0, 15.0)])
def test_the_tilt_ring_is_what_a_yaw_sweep_sees(roll, pitch):
    """Every yaw at this roll and pitch sees a field direction on the ring, and the ring holds nothing else."""
    f = _field_world()
    incl = np.radians(60.0)
    att = Rotation.from_euler("ZYX", [37.0, pitch, roll], degrees=True)
    ring = motion.tilt_ring(att.as_quat()[[3, 0, 1, 2]], incl, n_points=720)
    assert np.allclose(np.linalg.norm(ring, axis=1), 1.0)
    yaws = np.linspace(0, 360, 90, endpoint=False)
    seen = np.array([Rotation.from_euler("ZYX", [y, pitch, roll], degrees=True).inv().apply(f) for y in yaws])
    seen /= np.linalg.norm(seen, axis=1, keepdims=True)
    gap = np.degrees(np.arccos(np.clip(seen @ ring.T, -1, 1))).min(axis=1)
    assert gap.max() < 0.3  # each direction a yaw sweep sees lies on the ring (720 points: 0.25 deg apart)
    back = np.degrees(np.arccos(np.clip(ring @ seen.T, -1, 1))).min(axis=1)
    assert back.max() < 2.5  # and the ring is nothing but those (90 yaws: 4 deg apart)


def test_the_inclination_comes_from_the_data():
    f = _field_world(incl_deg=67.0)
    att = Rotation.random(500, random_state=3)
    b = att.inv().apply(f) + np.random.default_rng(0).normal(scale=3.0, size=(500, 3))
    incl = motion.inclination_from_data(b, att.as_quat()[:, [3, 0, 1, 2]])
    assert np.degrees(incl) == pytest.approx(67.0, abs=0.05)


def test_without_attitude_the_ring_is_the_circle_a_yaw_sweep_drew():
    f = _field_world()
    yaws = np.linspace(0, 120, 200)  # a third of a turn at a fixed tilt
    seen = np.array([Rotation.from_euler("ZYX", [y, 10, -25], degrees=True).inv().apply(f) for y in yaws])
    seen += np.random.default_rng(1).normal(scale=30.0, size=seen.shape)  # 30 nT of noise
    ring = motion.ring_from_directions(seen)
    truth = motion.tilt_ring(
        Rotation.from_euler("ZYX", [0, 10, -25], degrees=True).as_quat()[[3, 0, 1, 2]], np.radians(60.0), 720
    )
    dist = np.degrees(np.arccos(np.clip(ring @ truth.T, -1, 1))).min(axis=1)
    assert dist.max() < 0.5
    # tumbling (random directions) draws no circle; nor does a short arc
    assert motion.ring_from_directions(np.random.default_rng(2).normal(size=(200, 3))) is None
    assert motion.ring_from_directions(seen[:20]) is None


def test_the_turn_rate_from_attitude_and_from_gyro_columns():
    t = np.arange(200) * 0.02
    rate = np.where(t < 2.0, 30.0, 90.0)  # deg/s about a tilted axis
    angle = np.concatenate([[0.0], np.cumsum(rate[1:] * np.diff(t))])
    axis = np.array([0.3, -0.2, 0.93]) / np.linalg.norm([0.3, -0.2, 0.93])
    q = Rotation.from_rotvec(np.radians(angle)[:, None] * axis).as_quat()[:, [3, 0, 1, 2]]
    ds = Dataset(readings_nT=np.ones((200, 3)), time_s=t, attitude_wxyz=q)
    got = turn_rate_dps(ds)
    assert np.allclose(got[1:], rate[1:], rtol=1e-6)
    fast = motion.fast_turning(ds)
    assert not fast[:100].any() and fast[101:].all()
    gyro = {"gx": np.radians(rate) * axis[0], "gy": np.radians(rate) * axis[1], "gz": np.radians(rate) * axis[2]}
    in_rad = Dataset(readings_nT=np.ones((200, 3)), extra=gyro, metadata={"gyro_units": "rad/s"})
    assert np.allclose(turn_rate_dps(in_rad), rate)
    assert turn_rate_dps(Dataset(readings_nT=np.ones((200, 3)))) is None


def test_a_streams_channels_give_the_turn_rate_and_the_tilt_ring():
    """What a live stream carries (magcal.data.live): roll/pitch/yaw in degrees, NaN before its first ATTITUDE
    message, and gyro_*_dps columns. Both give the turn rate; the Euler angles give the tilt ring."""
    from magcal_workbench.view import ring_directions

    t = np.arange(300) * 0.02
    yaw = np.where(t < 3.0, 20.0 * t, 60.0 + 90.0 * (t - 3.0))  # 20 deg/s, then 90 deg/s
    roll, pitch = np.full_like(t, 12.0), np.full_like(t, -5.0)
    att = Rotation.from_euler("ZYX", np.column_stack([yaw, pitch, roll]), degrees=True)
    f = _field_world(incl_deg=65.0)
    b = att.inv().apply(f)
    euler = {"roll_deg": roll.copy(), "pitch_deg": pitch.copy(), "yaw_deg": yaw.copy()}
    for v in euler.values():
        v[:10] = np.nan  # no attitude yet
    ds = Dataset(readings_nT=b, time_s=t, extra=euler)
    q = attitude_quaternions(ds)
    assert np.isnan(q[:10]).all() and np.allclose(np.abs(np.sum(q[10:] * att.as_quat()[10:, [3, 0, 1, 2]], 1)), 1)
    rate = turn_rate_dps(ds)
    assert np.allclose(rate[11:150], 20.0, rtol=1e-6) and np.allclose(rate[151:], 90.0, rtol=1e-6)
    assert not rate[:10].any()  # no attitude: not marked
    fast = motion.fast_turning(ds)
    assert not fast[:150].any() and fast[151:].all()
    true_rate = np.where(t < 3.0, 20.0, 90.0)
    gyro = {"gyro_x_dps": np.zeros_like(t), "gyro_y_dps": np.zeros_like(t), "gyro_z_dps": true_rate}
    assert np.allclose(turn_rate_dps(Dataset(readings_nT=b, time_s=t, extra=gyro)), true_rate)
    ring = ring_directions(ds, b, current=200)
    truth = motion.tilt_ring(q[200], np.radians(65.0), n_points=len(ring))
    gap = np.degrees(np.arccos(np.clip(ring @ truth.T, -1, 1))).min(axis=1)
    assert gap.max() < 5.0  # the ring at the sample's tilt, the inclination read from the data
    ring_directions(ds, b, current=5)  # before the stream's first attitude: the ring without attitude, no error


# --- the workbench, headless -------------------------------------------------------------------------------
def _single_sensor(n=300):
    ds = magcal.simulate_timeseries("chi2017", n_samples=n, seed=5, rate_hz=2.0)
    return ds.replace(readings_nT=ds.readings_nT[:1], baseline_m=None)


def test_a_single_sensor_recording_draws_no_cross(bench):
    wb = bench(ds=_single_sensor())
    wb.ctrl.step_calibrate("ml")
    wb.ui.wait()
    nodes = viser_adapter.scene_node_names(wb.server)
    assert any(n.startswith("/data/s1/") for n in nodes)
    assert not [n for n in nodes if n.startswith("/cross")], nodes
    four = bench(name="four.csv")
    assert [n for n in viser_adapter.scene_node_names(four.server) if n.startswith("/cross/s4")]


def test_the_table_and_plots_follow_the_fit_and_the_selection(bench):
    wb = bench()
    assert "raw" in wb.panels.summary.content and "corrected" not in wb.panels.summary.content
    wb.ctrl.step_calibrate("ml")
    wb.ui.wait()
    text = wb.panels.summary.content
    rms = re.search(r"\*\*corrected\*\* \| \*\*([0-9.]+)\*\*", text)
    assert rms and float(rms.group(1)) == pytest.approx(wb.ctrl.residual_rms_nT(), rel=1e-3)
    names = {tr.name for tr in wb.panels.field_plot.figure.data}
    assert {"reference", "raw (every sensor)", "corrected (every sensor)"} <= names
    hist = {tr.name.split(" (")[0] for tr in wb.panels.histogram_plot.figure.data}
    assert hist == {"raw", "corrected"}
    rec = controller_record(wb.ctrl)
    assert plots.table_figures(rec)["n_kept"] == 300


def _refit_done(wb):
    assert wb.worker.wait(120)
    wb.ui.wait()


def test_excluding_a_time_range_refits_and_including_it_restores(bench):
    wb = bench()
    wb.ctrl.step_calibrate("ml")
    cal0 = wb.ctrl.calibration.to_dict()
    kept0 = int(wb.ctrl.fit_result.mask.sum())
    wb.panels.range_from.value, wb.panels.range_to.value = 20.0, 45.0
    wb.cockpit.do_exclude_range(None)
    _refit_done(wb)
    idx = samples_in_range(wb.ctrl.dataset.time_s, 20.0, 45.0)
    assert wb.ctrl.state.selection.n_rejected == idx.size > 50
    assert int(wb.ctrl.fit_result.mask.sum()) == kept0 - idx.size
    assert not np.allclose(wb.ctrl.calibration.sensors[0].bias_nT, cal0["sensors"][0]["bias_nT"], atol=1e-6)
    assert any(s.fillcolor == plots.EXCLUDED_BAND_COLOUR for s in wb.panels.field_plot.figure.layout.shapes)
    wb.cockpit.do_include_range(None)
    _refit_done(wb)
    assert wb.ctrl.state.selection.n_rejected == 0 and int(wb.ctrl.fit_result.mask.sum()) == kept0
    assert np.allclose(wb.ctrl.calibration.sensors[0].bias_nT, cal0["sensors"][0]["bias_nT"], atol=1e-3)
    # one undo step each, so undo gives the exclusion back
    wb.actions.do_undo(None)
    _refit_done(wb)
    assert wb.ctrl.state.selection.n_rejected == idx.size


def test_a_live_sessions_tabs_describe_the_stream_then_the_recording(bench):
    wb = bench()
    assert "data.csv" in wb.panels.data_info.content
    live = wb.livectl.start("sim://chi2017?rate=50&n=400&speed=4")
    assert _wait(lambda: live.fit is not None and wb.cockpit.n_plotted >= 60, 60)
    wb.ui.wait()
    for text in (wb.panels.data_info.content, wb.panels.sensors_table.content):
        assert "data.csv" not in text
    assert "live from `sim://chi2017" in wb.panels.data_info.content
    assert "Live fit on" in wb.panels.sensors_table.content
    assert "Live session" in wb.panels.history.content and "Live session" in wb.panels.quality.content
    assert _wait(lambda: not live.session.running, 60)
    wb.livectl.do_live_stop(None)
    assert wb.worker.wait(60)
    wb.ui.wait()
    assert live.path.name in wb.panels.data_info.content and "live from" not in wb.panels.data_info.content
    assert "Live session" not in wb.panels.history.content


# --- in the browser ----------------------------------------------------------------------------------------
def _click(page, name):
    """Click the button ``name``; a panel that reflows (plots redrawn) may keep it "unstable" for a while, so a
    click that waited long enough is forced."""
    button = page.get_by_role("button", name=name)
    button.scroll_into_view_if_needed(timeout=30_000)
    try:
        button.click(timeout=20_000)
    except Exception:  # playwright's TimeoutError: still moving
        button.click(force=True)


def _plot_data(page, title):
    """``(points, largest x, sum of y)`` of the plotly figure whose title starts with ``title``, as the page holds it
    (every trace), or ``(-1, nan, nan)`` when the page has no such figure."""
    got = page.evaluate(
        """(title) => {
        for (const el of document.querySelectorAll('.js-plotly-plot')) {
            const t = el.layout && el.layout.title && el.layout.title.text;
            if (!t || !t.startsWith(title)) continue;
            let n = 0, top = -Infinity, total = 0;
            const plain = (a) => a && a._inputArray !== undefined ? a._inputArray : a;  // plotly's typed arrays
            for (const tr of el.data) {
                const x = plain(tr.x), y = plain(tr.y);
                if (x) {
                    n += x.length;
                    for (const v of x) if (typeof v === 'number' && v > top) top = v;
                }
                if (y) for (const v of y) if (typeof v === 'number') total += v;
            }
            return [n, top, total];
        }
        return [-1, null, null];
    }""",
        title,
    )
    return got[0], (float("nan") if got[1] is None else float(got[1])), (float("nan") if got[2] is None else got[2])


@pytest.mark.e2e
@pytest.mark.slow
def test_in_the_page_excluding_a_time_range_changes_the_fit_and_including_restores(browser, bench):
    from tests.workbench.test_workbench_e2e import _open

    wb = bench()
    page = _open(browser, wb)
    page.get_by_role("button", name="Run the chosen method").click()
    page.wait_for_function("() => /Total-field RMS: [0-9.]+ nT/.test(document.body.innerText)", timeout=120_000)
    assert wb.worker.wait(60)
    bias0 = np.array(wb.ctrl.calibration.sensors[1].bias_nT)
    wb.panels.range_from.value, wb.panels.range_to.value = 10.0, 40.0  # as the page's sliders would send
    _click(page, "Exclude range")
    page.wait_for_function("() => /Rejected: [1-9]\\d* of 300/.test(document.body.innerText)", timeout=60_000)
    assert _wait(lambda: wb.ctrl.fit_result is not None and int(wb.ctrl.fit_result.mask.sum()) < 300, 60)
    assert wb.worker.wait(60)
    n = wb.ctrl.state.selection.n_rejected
    assert n == samples_in_range(wb.ctrl.dataset.time_s, 10, 40).size
    page.wait_for_function(f"() => document.body.innerText.includes('{300 - n} of 300 samples kept')", timeout=60_000)
    assert np.abs(np.array(wb.ctrl.calibration.sensors[1].bias_nT) - bias0).max() > 1e-3
    _click(page, "Include range")
    page.wait_for_function("() => document.body.innerText.includes('Rejected: 0 of 300')", timeout=60_000)
    assert _wait(lambda: int(wb.ctrl.fit_result.mask.sum()) == 300, 60)
    assert wb.worker.wait(60)
    assert np.allclose(wb.ctrl.calibration.sensors[1].bias_nT, bias0, atol=1e-3)
    page.close()


@pytest.mark.e2e
@pytest.mark.slow
def test_in_the_page_a_single_sensor_recording_has_no_cross(browser, bench):
    from tests.workbench.test_workbench_e2e import _open

    wb = bench(ds=_single_sensor())
    page = _open(browser, wb)  # the scene's labels are drawn in WebGL: the nodes the server sends are the test
    assert len(wb.server.get_clients()) == 1
    page.get_by_role("button", name="Run the chosen method").click()
    page.wait_for_function("() => /Total-field RMS: [0-9.]+ nT/.test(document.body.innerText)", timeout=120_000)
    assert wb.worker.wait(60)
    wb.ui.wait()
    nodes = viser_adapter.scene_node_names(wb.server)
    assert {"/data/s1/raw", "/data/s1/corrected", "/data/s1/ellipsoid"} <= set(nodes)
    assert not [n for n in nodes if n.startswith("/cross")], nodes
    # the page's C^-1 table names the one sensor, not "sensor 1 of 4"
    page.wait_for_function("() => document.body.innerText.includes('(the sensor)')", timeout=30_000)
    page.close()


@pytest.mark.e2e
@pytest.mark.slow
def test_a_live_session_fills_the_tabs_and_the_plots_follow_the_stream(browser, bench):
    from tests.workbench.test_workbench_e2e import _open

    wb = bench()
    page = _open(browser, wb)
    assert "data.csv" in wb.panels.data_info.content
    page.get_by_text("Data", exact=True).click()  # unfold the Calibrate tab's Data section
    page.get_by_role("tab", name="Files").click(timeout=30_000)
    wb.panels.live_source.value = "simulated chi2017"
    wb.panels.live_rate.value, wb.panels.live_samples.value, wb.panels.live_speed.value = 50.0, 20_000, 2.0
    page.get_by_role("button", name="Start live").click()
    page.wait_for_function("() => /\\d+ samples received/.test(document.body.innerText)", timeout=30_000)
    page.get_by_role("tab", name="Calibrate").click(force=True)  # the panel reflows as the figures change
    # the Calibrate tab's data are the stream's, not the file open before
    page.wait_for_function("() => document.body.innerText.includes('live from sim://chi2017')", timeout=30_000)
    assert "data.csv" not in wb.panels.data_info.content
    # the plots appear and grow with the stream
    # the page may still hold the file's plot (its time ends at the file's last sample): wait for the stream's
    file_end_s = float(wb.ctrl.dataset.time_s[-1])
    assert _wait(lambda: 0 < _plot_data(page, "|B| against time")[1] < file_end_s - 1.0, 60)
    _, first_t, _ = _plot_data(page, "|B| against time")
    assert _wait(lambda: _plot_data(page, "|B| against time")[1] > first_t + 1.0, 30)  # later samples drawn
    assert _wait(lambda: wb.live.fit is not None, 60)
    # the corrected histogram's axis title carries its RMS
    page.wait_for_function("() => /corrected, nT \\(RMS/.test(document.body.innerText)", timeout=30_000)
    counted = _plot_data(page, "error |B|")[2]  # samples in the histograms: every sensor's, raw and corrected
    assert _wait(lambda: _plot_data(page, "error |B|")[2] > counted, 90)  # software WebGL: the page lags
    grown = wb.cockpit.n_plotted
    assert _wait(lambda: wb.cockpit.n_plotted > grown, 30)
    page.wait_for_function("() => /Now: \\d+ of \\d+ samples kept/.test(document.body.innerText)", timeout=30_000)
    wb.live.stop()
    page.close()
