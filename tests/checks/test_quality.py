"""magcal.checks.quality: data quality read before fitting, checked on simulated data whose defects we set."""

import json

import numpy as np
import pytest

from magcal.checks import quality
from magcal.data.simulation import simulate, simulate_timeseries


def timeseries(n=1500, noise_nT=3.0, seed=2, **kw):
    return simulate_timeseries("chi2017", n_samples=n, noise_nT=noise_nT, noise_kind="gaussian", seed=seed, **kw)


def only(report, kind, sensor=None):
    found = report.find(kind, sensor)
    assert len(found) == 1, [f.to_dict() for f in report.findings]
    return found[0]


# -- clean data ----------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "make",
    [
        lambda: simulate("chi2017", seed=1),
        lambda: simulate("chi2017", n_samples=1000, noise_nT=0.0, seed=4),
        lambda: timeseries(seed=2),
        lambda: timeseries(n=600, noise_nT=30.0, seed=7),
    ],
    ids=["random", "random-noiseless", "timeseries", "timeseries-noisy"],
)
def test_clean_data_gives_no_warnings(make):
    ds = make()
    report = quality.assess(ds)
    assert report.warnings == []
    for s in range(1, ds.n_sensors + 1):
        assert only(report, "stale", s).values["fraction"] == 0.0
        assert only(report, "quantization", s).values["step_nT"] == [None, None, None]
        assert only(report, "clipping", s).values["clipped"] == []
        assert only(report, "static", s).values["count"] == 0
    json.dumps(report.to_dict())  # JSON-able as it is
    assert report.section().startswith("Data quality\n")


# -- quantization --------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "q_nT,n,offset_nT",
    [
        (q, n, off)
        for q in (0.1, 15.0, 150.0, 300.0)
        for n, off in ((200, 0.0), (2000, 0.0), (2000, 7.3))
        if not (q < 1 and n < 1000)  # 200 samples over a million 0.1 nT levels: too sparse to see (and harmless)
    ],
)
def test_quantization_step_is_found(q_nT, n, offset_nT):
    ds = simulate("chi2017", n_samples=n, noise_nT=3.0, seed=5)
    y = q_nT * np.round(ds.readings_nT / q_nT) + offset_nT
    report = quality.assess(ds.replace(readings_nT=y, noise_nT=None))
    for s in range(1, 5):
        f = only(report, "quantization", s)
        assert f.values["step_nT"] == pytest.approx([q_nT] * 3, rel=1e-6)
        assert f.values["noise_floor_nT"] == pytest.approx([q_nT / np.sqrt(12)] * 3, rel=1e-6)


def test_quantization_step_survives_a_unit_conversion():
    """Counts of 0.15 uT read as uT and multiplied by 1000: float noise must not hide the 150 nT step."""
    counts = np.round(np.random.default_rng(3).normal(0, 300, size=800))
    assert quality.quantization_step(counts * 0.15 * 1e3) == pytest.approx(150.0, rel=1e-9)
    assert quality.quantization_step(counts * 1e3 * 0.15) == pytest.approx(150.0, rel=1e-9)


@pytest.mark.parametrize(
    "values",
    [
        np.random.default_rng(0).normal(0, 3e4, 500),  # continuous
        np.arange(8) * 15.0,  # too few levels to tell
        np.full(100, 42.0),  # constant
    ],
)
def test_no_step_claimed_without_evidence(values):
    assert quality.quantization_step(values) is None


@pytest.mark.parametrize(
    "q_nT,noise_nT,severity",
    [
        (150.0, 3.0, "warning"),  # floor 43 nT, far above the noise
        (15.0, None, "warning"),  # floor 4.3 nT, noise unknown
        (1.0, 3.0, "info"),  # floor 0.29 nT: under 1 nT
        (15.0, 100.0, "info"),  # floor 4.3 nT, well below 100 nT of noise
    ],
)
def test_quantization_severity_follows_its_floor_and_the_noise(q_nT, noise_nT, severity):
    ds = simulate("chi2017", n_samples=500, noise_nT=noise_nT or 3.0, seed=8)
    y = q_nT * np.round(ds.readings_nT / q_nT)
    f = only(quality.assess(ds.replace(readings_nT=y, noise_nT=noise_nT)), "quantization", 1)
    assert f.severity == severity
    assert ("q/sqrt(12)" in f.summary) and f.effect


# -- stale readings ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("fraction,run,severity", [(0.02, 2, "info"), (0.1, 3, "warning"), (0.3, 4, "warning")])
def test_stale_fraction_and_longest_run(fraction, run, severity):
    ds = timeseries(n=1200, seed=3)
    y = ds.readings_nT.copy()
    n = y.shape[1]
    n_repeats = int(round(fraction * n))
    per_run = run - 1  # a run of `run` identical samples holds run-1 repeats
    starts = np.linspace(10, n - 10, n_repeats // per_run).astype(int)
    starts = starts[np.diff(np.concatenate([[-10], starts])) > run + 1]
    for a in starts:
        y[1, a + 1 : a + run] = y[1, a]  # sensor 2 only
    repeats = len(starts) * per_run
    report = quality.assess(ds.replace(readings_nT=y))
    f = only(report, "stale", 2)
    assert f.values["count"] == repeats
    assert f.values["fraction"] == pytest.approx(repeats / n)
    assert f.values["longest_run"] == run
    assert f.severity == severity
    assert only(report, "stale", 1).values["count"] == 0
    assert any("sensor 2:" in w and "stale" in w for w in report.warnings) == (severity == "warning")


# -- timing --------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("jitter,severity", [(0.0, "info"), (0.03, "info"), (0.25, "warning")])
def test_sample_rate_and_jitter(jitter, severity):
    ds = timeseries(n=2000, seed=4)
    rng = np.random.default_rng(1)
    interval = 0.02
    dt = interval * (1 + jitter * rng.standard_normal(ds.n_samples - 1))
    t = np.concatenate([[0.0], np.cumsum(np.maximum(dt, 1e-4))])
    f = only(quality.assess(ds.replace(time_s=t)), "sample_rate")
    assert f.values["rate_Hz"] == pytest.approx(1 / interval, rel=0.01)
    assert f.values["jitter"] == pytest.approx(jitter, abs=0.01 + 0.1 * jitter)
    assert f.severity == severity


@pytest.mark.parametrize(
    "gaps_s,severity",
    [
        ((), None),
        ((0.5,), "info"),  # one short gap (5 intervals)
        ((0.45, 2.0, 0.35), "warning"),  # one of 20 intervals
        ((0.4,) * 12, "warning"),  # over 1 % of the intervals
    ],
)
def test_gaps_are_counted_with_the_longest(gaps_s, severity):
    ds = timeseries(n=1000, seed=5)
    t = ds.time_s.copy()  # 10 Hz
    for k, g in enumerate(gaps_s):
        t[(k + 1) * 70 :] += g - 0.1  # one interval of g s instead of 0.1 s
    f = only(quality.assess(ds.replace(time_s=t)), "gaps")
    assert f.values["count"] == len(gaps_s)
    assert f.values["longest_s"] == pytest.approx(max(gaps_s, default=0.0))
    if severity:
        assert f.severity == severity and f.notable


@pytest.mark.parametrize("n_repeated", [0, 1, 25])
def test_repeated_time_stamps(n_repeated):
    ds = timeseries(n=800, seed=6)
    t = ds.time_s.copy()
    for k in range(n_repeated):
        i = 20 + 30 * k
        t[i] = t[i - 1]
    found = quality.assess(ds.replace(time_s=t)).find("time_order")
    if n_repeated == 0:
        assert found == []
    else:
        assert found[0].values["repeated"] == n_repeated and found[0].severity == "warning"


# -- static stretches ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("sigma_nT", [1.0, 3.0, 30.0])
@pytest.mark.parametrize("known_noise", [True, False])
@pytest.mark.parametrize("length,severity", [(150, "info"), (450, "warning")])
def test_static_stretch_is_found_with_its_noise(sigma_nT, known_noise, length, severity):
    ds = timeseries(n=1500, noise_nT=sigma_nT, seed=7)
    y = ds.readings_nT.copy()
    rng = np.random.default_rng(2)
    a, b = 600, 600 + length
    y[:, a:b] = y[:, a : a + 1] + rng.normal(0.0, sigma_nT, size=(4, length, 3))  # the array held still
    report = quality.assess(ds.replace(readings_nT=y, noise_nT=sigma_nT if known_noise else None))
    for s in range(1, 5):
        f = only(report, "static", s)
        assert f.values["count"] == 1, f.summary
        start, stop = f.values["stretches"][0]
        window = f.values["window_samples"]
        assert abs(start - a) <= window and abs(stop - b) <= window
        assert f.values["longest_s"] == pytest.approx((length - 1) * 0.1, abs=window * 0.1)
        assert f.values["scatter_nT"] == pytest.approx([sigma_nT] * 3, rel=0.2)
        assert f.severity == severity and f.notable


# -- clipping ------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("axis,share", [(0, 0.05), (2, 0.02)])
def test_clipping_names_the_axis_and_value(axis, share):
    ds = timeseries(n=2000, seed=8)
    y = ds.readings_nT.copy()
    limit = np.quantile(y[0, :, axis], 1 - share)
    y[0, :, axis] = np.minimum(y[0, :, axis], limit)
    report = quality.assess(ds.replace(readings_nT=y))
    f = only(report, "clipping", 1)
    assert f.severity == "warning"
    (c,) = f.values["clipped"]
    assert c["axis"] == "xyz"[axis] and c["end"] == "max" and c["value_nT"] == pytest.approx(limit)
    assert c["count"] == pytest.approx(share * 2000, rel=0.05)
    assert only(report, "clipping", 2).values["clipped"] == []


# -- temperature ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "profile,severity,notable",
    [
        ("ramp", "warning", True),  # proportional to time: confounded with drift
        ("default", "info", False),  # the simulator's non-monotonic curve
        ("flat", "info", True),  # 0.2 K: too little to fit temperature terms
    ],
)
def test_temperature_range_and_correlation_with_time(profile, severity, notable):
    ds = timeseries(n=1000, seed=9)
    temp = {"ramp": 15.0 + 0.01 * ds.time_s, "default": ds.temperature_C, "flat": 20.0 + 0.1 * np.sin(ds.time_s)}[
        profile
    ]
    f = only(quality.assess(ds.replace(temperature_C=temp)), "temperature")
    assert f.values["min_C"] == pytest.approx(temp.min()) and f.values["max_C"] == pytest.approx(temp.max())
    assert f.severity == severity and f.notable == notable
    if profile == "ramp":
        assert f.values["corr_with_time"] == pytest.approx(1.0)
        assert "drift" in f.effect


def test_no_temperature_channel_no_temperature_finding():
    assert quality.assess(simulate("chi2017", seed=1)).find("temperature") == []


# -- after the fit -------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "field_nT,kind,warned",
    [
        (50_000.0, "fitted", False),
        (20_500.0, "fitted", False),
        (5_000.0, "fitted", True),
        (5.0e6, "fitted", True),
        (5_000.0, "given", False),
        (None, "fitted", False),
    ],
)
def test_field_magnitude_outside_the_earths_range(field_nT, kind, warned):
    f = quality.field_magnitude_finding(field_nT, kind)
    assert (f is not None) == warned
    if warned:
        assert f.severity == "warning" and "--lsb" in f.effect and "shielded" in f.effect


def test_report_text_shows_notable_findings_and_effects():
    ds = timeseries(n=1000, seed=10)
    y = 150.0 * np.round(ds.readings_nT / 150.0)
    report = quality.assess(ds.replace(readings_nT=y, noise_nT=None))
    text = report.section()
    assert "sample rate 10 Hz" in text and "quantization step (x, y, z) 150, 150, 150 nT" in text
    assert "WARNING sensor 1:" in text and "-> the total-field RMS cannot go below" in text
    assert "no clipping" not in text  # clean findings are left to --json
    doc = report.to_dict()
    assert {f["kind"] for f in doc["findings"]} >= {
        "sample_rate",
        "gaps",
        "stale",
        "quantization",
        "clipping",
        "static",
        "temperature",
    }
    json.dumps(doc)  # plain Python types only (no numpy bools or floats)
    assert len(report.warnings) == 4 and all(w.startswith(f"sensor {s}:") for s, w in zip(range(1, 5), report.warnings))


def _batched_stamps(n, rate_Hz, batch, host_period_s, rng):
    """Host arrival times of a sensor sampled at ``rate_Hz`` and read ``batch`` samples at a time: each batch
    arrives ~2 ms apart inside, then the host waits (sf_fullsphere: 77 Hz mean, median interval 3.3 ms)."""
    t, now, k = [], 0.0, 0
    while k < n:
        size = min(batch + int(rng.integers(-1, 2)), n - k)
        now += max(host_period_s * size / batch * (1 + 0.3 * rng.standard_normal()), 0.0)
        t.extend(now + 0.002 * np.arange(size) + 0.0003 * rng.random(size))
        k += size
    t = np.sort(np.array(t))
    return t - t[0]


def test_batched_stamps_are_named_with_the_mean_rate():
    """sf_fullsphere: 'sample rate 304 Hz, jitter 57 %, 2744 gaps' for 77 Hz arriving in batches."""
    ds = timeseries(n=3000, seed=8)
    rng = np.random.default_rng(8)
    t = _batched_stamps(ds.n_samples, 77.0, 4, 4 / 77.0, rng)
    report = quality.assess(ds.replace(time_s=t))
    f = only(report, "sample_rate")
    mean_rate = (t.size - 1) / (t[-1] - t[0])
    assert f.values["batched"] and f.severity == "warning"
    assert f.values["rate_Hz"] == pytest.approx(mean_rate) and mean_rate == pytest.approx(77.0, rel=0.05)
    assert f.values["median_interval_s"] < 0.004
    assert "arrive in batches" in f.summary and f"{mean_rate:.4g} Hz on average" in f.summary
    assert "arrival times" in f.effect
    gaps = only(report, "gaps")
    assert gaps.values["count"] < 0.01 * t.size  # the batch-to-batch intervals are not gaps


def test_regular_stamps_with_a_few_gaps_are_not_batches():
    ds = timeseries(n=1000, seed=9)
    t = ds.time_s.copy()
    t[500:] += 300.0  # one long gap carries most of the duration
    report = quality.assess(ds.replace(time_s=t))
    f = only(report, "sample_rate")
    assert not f.values["batched"] and f.values["rate_Hz"] == pytest.approx(10.0)
    assert "mean rate" in f.summary  # mean and median differ: both are said
    assert only(report, "gaps").values["count"] == 1


@pytest.mark.parametrize("coarse, shift_every, forward", [(5, 8, True), (5, 40, True), (5, 8, False), (4, 15, False)])
def test_quantization_step_on_a_grid_that_shifts(coarse, shift_every, forward):
    """QMC5883L z: integer counts on a 5-count grid that jumps by 2-3 counts every ~8 levels
    (mean spacing 5.3 counts). The common step is 1 count, but the readings carry a 5-count quantization.
    ``forward``: the jumps add to the spacing (5 -> 7, 8, as in the QMC); else the grid's origin moves with
    the value, which also puts levels 2-3 counts apart."""
    lsb = 33.3333
    rng = np.random.default_rng(coarse * 100 + shift_every)
    if forward:
        raw = np.round(rng.uniform(-600, 600, 20_000))  # the part's internal integer
        counts = coarse * raw + np.floor(2.5 * np.floor(raw / shift_every))  # jumps of 2, 3, 2, 3 ... counts
    else:
        true = rng.uniform(-3000, 3000, 20_000)
        origin = np.floor(true / (coarse * shift_every)) * 3
        counts = coarse * np.round((true - origin) / coarse) + origin
    x = counts * lsb
    grid = quality.quantization_grid(x)
    assert quality.quantization_step(x) == pytest.approx(coarse * lsb, rel=1e-6)
    # a rare shift (every 40 levels) is tolerated by the common step itself; frequent ones make it 1 count
    assert grid["common_step_nT"] * grid["spacing_multiple"] == pytest.approx(coarse * lsb, rel=1e-6)
    assert grid["shift_share"] > 0.01
    finding = quality.quantization_finding(np.column_stack([x, x, x]), lsb_nT=lsb)
    assert f"{coarse:g}, {coarse:g}, {coarse:g} LSB" in finding.summary and "grid shifts" in finding.summary


@pytest.mark.parametrize("sigma_counts", [0.8, 3.0, 30.0])
def test_a_fine_grid_sampled_sparsely_keeps_its_step(sigma_counts):
    """All multiples of the step occur, the smallest most often: the step is not mistaken for a coarser grid."""
    lsb = 13.3333
    x = lsb * np.round(np.random.default_rng(3).normal(0, 1500 * sigma_counts / 30, 800))
    assert quality.quantization_step(x) == pytest.approx(lsb, rel=1e-6)


def test_quantization_is_judged_against_the_motion_noise_without_a_still_stretch():
    """sf_fullsphere: 'WARNING quantization 26.5 nT ... with little noise to dither it' with 150 nT of noise."""
    ds = timeseries(n=2000, seed=12)
    rng = np.random.default_rng(12)
    y = 91.74 * np.round((ds.readings_nT + rng.normal(0, 150.0, ds.readings_nT.shape)) / 91.74)
    report = quality.assess(ds.replace(readings_nT=y, noise_nT=None))
    for f in report.find("quantization"):
        assert f.severity == "info" and "sample-to-sample scatter" in f.effect
        assert f"well below the {f.effect.split('well below the ')[1].split(' nT')[0]} nT" in f.effect
    # the scatter of the total field is the noise, whatever the motion (random attitudes here)
    rnd = simulate("chi2017", n_samples=800, noise_nT=150.0, seed=12)
    assert quality.total_field_scatter_nT(rnd.readings_nT[0]) == pytest.approx(150.0, rel=0.15)


def test_a_field_below_any_geomagnetic_one_says_to_check_the_lsb():
    """qmc_filtered read at 12000 LSB/G: a fitted field of 8.9 uT."""
    f = quality.field_magnitude_finding(8_900.0)
    text = f.message("qmc.csv")
    assert "fitted field 8.9 uT is below any geomagnetic field" in text and "check --units / --lsb" in text
    assert "above any geomagnetic field" in quality.field_magnitude_finding(250_000.0).summary


def test_every_finding_says_what_it_does_to_the_fit_and_survives_json():
    ds = timeseries(n=1200, seed=13)
    report = quality.assess(ds.replace(temperature_C=20.0 + 0.01 * ds.time_s, source="x.csv"))
    report.add(quality.field_magnitude_finding(9_000.0))
    for f in report.findings:
        assert f.effect and f.effect != "nothing" and not f.effect.endswith(".")
    doc = json.loads(json.dumps(report.to_dict()))
    back = quality.QualityReport.from_dict(doc)
    assert back.to_dict() == doc and back.warnings == report.warnings and back.section() == report.section()


@pytest.mark.parametrize("lag_nT_per_deg_s, severity", [(0.0, "info"), (2.0, "warning")])
def test_residual_growing_with_the_turn_rate(lag_nT_per_deg_s, severity):
    """qmc_filtered: residual RMS 881 -> 1110 nT from the slowest to the fastest turn-rate quartile."""
    rng = np.random.default_rng(14)
    n = 4000
    t = np.arange(n) / 50.0
    rate_deg_s = 200.0 * (1.0 + np.sin(2 * np.pi * t / 20.0)) + 5.0  # 5 to 405 deg/s, slowly varying
    angle = np.radians(np.cumsum(rate_deg_s) / 50.0)
    u = np.column_stack([np.cos(angle), np.sin(angle), 0.3 * np.sin(angle / 7)])
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    true_rate = np.degrees(np.r_[np.nan, np.arccos(np.clip(np.einsum("ij,ij->i", u[1:], u[:-1]), -1, 1))]) * 50.0
    r = rng.normal(0, 300.0, n) + lag_nT_per_deg_s * rng.choice([-1.0, 1.0], n) * np.nan_to_num(true_rate)
    f = quality.turn_rate_finding(u, r, t, sensor=1)
    assert f.kind == "turn_rate" and f.severity == severity and "deg/s" in f.summary
    rms = f.values["rms_nT"]
    if severity == "warning":
        assert rms[3] > 1.2 * rms[0] and f.values["spearman_rho"] > 0 and "timing" in f.effect
    else:
        assert max(rms) < 1.1 * min(rms)


def _common_step_one_by_one(values, min_levels=quality.MIN_LEVELS, max_divisor=50):
    """The common step found by trying each base's divisors in turn (the definition quality._common_step
    evaluates for all candidates at once)."""
    x = np.asarray(values, dtype=float)
    eps = 1e-9 * max(float(np.max(np.abs(x))), 1.0)
    u = np.unique(x)
    u = u[np.concatenate([[True], np.diff(u) > eps])]
    d = np.diff(u)
    if u.size < min_levels:
        return None
    sample = d if d.size <= 4000 else d[np.linspace(0, d.size - 1, 4000).astype(int)]
    best = None
    for base in np.unique(np.sort(d)[:5]):
        for k in range(1, max_divisor + 1):
            q = base / k
            if (best is not None and q <= best) or q <= 10 * eps:
                break
            if quality._multiple_share(sample, q) >= quality.MULTIPLE_SHARE:
                if sample is d or quality._multiple_share(d, q) >= quality.MULTIPLE_SHARE:
                    best = float(q)
                break
    return best


@pytest.mark.parametrize("kind", ["grid", "shifting", "continuous", "sparse", "two_grids"])
@pytest.mark.parametrize("seed", [0, 1])
def test_common_step_is_the_one_found_divisor_by_divisor(kind, seed):
    rng = np.random.default_rng(seed)
    n = 3000
    if kind == "grid":
        v = np.round(rng.normal(0, 2e4, n) / 0.15) * 0.15
    elif kind == "shifting":
        v = np.round(rng.normal(0, 3e3, n) / 5.0) * 5.0 + 2.0 * (rng.random(n) < 0.3)
    elif kind == "continuous":
        v = rng.normal(0, 2e4, n)
    elif kind == "sparse":
        v = np.round(rng.normal(0, 5e4, 200) / 0.1) * 0.1
    else:
        v = np.concatenate(
            [np.round(rng.normal(0, 1e3, n // 2) / 3.0) * 3.0, np.round(rng.normal(0, 1e3, n // 2) / 7.0) * 7.0]
        )
    found, _ = quality._common_step(v)
    expected = _common_step_one_by_one(v)
    assert (found is None) == (expected is None)
    if expected is not None:
        assert found == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize("kind", ["grid", "shifting", "continuous"])
def test_a_large_record_is_screened_on_a_subsample_with_the_same_step(monkeypatch, kind):
    """Above SCREEN_FROM_SAMPLES values the step is first looked for in an even subsample: continuous readings
    give None without sorting every value, and a grid gives the step of the whole computation."""
    rng = np.random.default_rng(3)
    n = quality.SCREEN_FROM_SAMPLES + 50_000
    if kind == "grid":
        v = np.round(rng.normal(0, 2e4, n) / 0.15) * 0.15
    elif kind == "shifting":
        v = np.round(rng.normal(0, 3e3, n) / 5.0) * 5.0 + 2.0 * (rng.random(n) < 0.3)
    else:
        v = rng.normal(0, 2e4, n)
    screened = quality.quantization_grid(v)
    monkeypatch.setattr(quality, "SCREEN_FROM_SAMPLES", 10**9)
    whole = quality.quantization_grid(v)
    assert (screened is None) == (whole is None) == (kind == "continuous")
    if whole is not None:
        assert screened == pytest.approx(whole, rel=1e-12)
