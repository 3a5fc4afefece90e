"""magcal.diagnosis.statistics: the spectrum on irregular stamps and the direction analysis on partial coverage."""

import numpy as np
import pytest
from scipy.signal import lombscargle, periodogram
from scipy.spatial.transform import Rotation

from magcal.diagnosis import statistics as st
from magcal.diagnosis.evidence import _effect_extra
from magcal.diagnosis.scores import Candidate


def _batched_times(n, mean_interval_s, rng):
    """Host arrival times: bursts of 2-6 samples 2 ms apart, then a wait (mean interval as given)."""
    t, now = [], 0.0
    while len(t) < n:
        size = int(rng.integers(2, 7))
        now += size * mean_interval_s * rng.uniform(0.5, 1.5)
        t.extend(now + 0.002 * np.arange(size))
    return np.array(t[:n])


@pytest.mark.parametrize("stamps", ["batched", "poisson"])
@pytest.mark.parametrize("freq_hz", [0.095, 1.3])
def test_spectrum_on_irregular_stamps_finds_the_frequency(stamps, freq_hz):
    """sf_fullsphere: the study found 0.095 Hz by Lomb-Scargle where magcal said 0.334 Hz."""
    rng = np.random.default_rng(int(freq_hz * 1000))
    n = 6000
    if stamps == "batched":
        t = _batched_times(n, 1 / 77.0, rng)
    else:
        t = np.cumsum(rng.exponential(1 / 50.0, n))
    r = 60.0 * np.sin(2 * np.pi * freq_hz * t + 0.3) + rng.normal(0, 100.0, n)
    spec = st.spectrum(r, t)
    bin_hz = 1.0 / (t[-1] - t[0])
    assert spec["method"] == "lomb-scargle"
    assert abs(spec["peak_hz"] - freq_hz) <= bin_hz
    assert spec["p"] < 1e-6 and spec["amplitude_nT"] == pytest.approx(60.0, rel=0.3)
    # the uniform periodogram at the median interval (what the spectrum did) puts the peak elsewhere
    fs = 1.0 / np.median(np.diff(t))
    f, p = periodogram(r - r.mean(), fs=fs, detrend=False)
    assert abs(f[1:][np.argmax(p[1:])] - freq_hz) > 3 * bin_hz


def test_regular_stamps_keep_the_fft_periodogram():
    t = np.arange(4000) / 50.0
    r = 10.0 * np.sin(2 * np.pi * 2.5 * t) + np.random.default_rng(1).normal(0, 5.0, t.size)
    spec = st.spectrum(r, t)
    assert spec["method"] == "periodogram" and spec["peak_hz"] == pytest.approx(2.5, abs=1 / 80)
    assert not st.irregular_stamps(t) and st.irregular_stamps(np.r_[t[:2000], t[2000:] + 3.0])


def test_lomb_scargle_grid_is_scipys_periodogram():
    rng = np.random.default_rng(2)
    t = np.sort(rng.uniform(0, 40, 700))
    r = np.sin(2 * np.pi * 0.8 * t) + rng.normal(0, 1, t.size)
    r -= r.mean()
    freq = np.arange(1, 351) / 40.0
    np.testing.assert_allclose(
        st.lomb_scargle_grid(t, r, freq[0], freq.size), lombscargle(t, r, 2 * np.pi * freq), rtol=1e-9, atol=1e-9
    )


def _three_great_circles(n_per):
    """Directions on three great circles (a drone rolled, pitched and yawed: mxl_test1)."""
    a = np.linspace(0, 2 * np.pi, n_per, endpoint=False)
    c, s, z = np.cos(a), np.sin(a), np.zeros_like(a)
    return np.vstack([np.column_stack([c, s, z]), np.column_stack([c, z, s]), np.column_stack([z, c, s])])


def _degree4(u):
    """A degree-4 pattern: RMS over the sphere 40 nT."""
    y = st.real_sph_harm(u, 4)[:, 16 + 4]  # (l=4, m=0)
    return 40.0 * np.sqrt(4 * np.pi) * y


def test_ring_coverage_withholds_the_degrees_it_cannot_resolve():
    """mxl_test1: SH RMS per degree of 1.5-5.5 uT for a 300 nT residual on three great circles."""
    rng = np.random.default_rng(3)
    u = _three_great_circles(1500)
    u = Rotation.from_rotvec([0.1, -0.2, 0.05]).apply(u)
    r = rng.normal(0, 300.0, len(u))
    sh = st.sh_analysis(u, r)
    assert list(sh["resolved"]) == [True, True, True, False, False, False, False]
    assert sh["max_resolved_degree"] == 2
    assert np.all(np.isnan(sh["rms_nT"][3:]))  # withheld: they were 1.5-5.5 uT for 300 nT of residual
    assert np.all(np.isfinite(sh["p"]))  # the F-tests stay (valid, with less power)
    assert np.all(sh["rms_nT"][:3] < 50.0)  # the resolved degrees of pure noise stay small
    assert sh["high_rms_in_sample_nT"] < 0.3 * 300.0  # noise: degrees 3+ explain little where the samples are
    np.testing.assert_allclose(sh["map"]["value_nT"], 0.0)  # no map of what the coverage does not resolve


def test_full_coverage_resolves_and_measures_every_degree():
    rng = np.random.default_rng(4)
    u = Rotation.random(4000, random_state=rng).apply([0.0, 0.0, 1.0])
    r = _degree4(u) + rng.normal(0, 30.0, len(u))
    sh = st.sh_analysis(u, r)
    assert sh["resolved"].all() and sh["max_resolved_degree"] == st.SH_DEGREE
    assert sh["rms_nT"][4] == pytest.approx(40.0, rel=0.1) and sh["p"][4] < 1e-20
    assert np.all(sh["rms_nT"][[1, 2, 3, 5, 6]] < 5.0)
    assert sh["high_rms_in_sample_nT"] == pytest.approx(40.0, rel=0.1)


def test_a_ring_pattern_is_found_without_a_made_up_size():
    """A real degree-4 pattern seen on three great circles: the F-test finds it, its size over the sphere is
    withheld, and what it explains at the visited directions is about its true RMS there."""
    rng = np.random.default_rng(7)
    u = Rotation.from_rotvec([0.1, -0.2, 0.05]).apply(_three_great_circles(1500))
    truth = _degree4(u)
    sh = st.sh_analysis(u, truth + rng.normal(0, 30.0, len(u)))
    assert sh["p"][4] < 1e-10 and np.isnan(sh["rms_nT"][4])
    assert sh["high_rms_in_sample_nT"] == pytest.approx(np.sqrt(np.mean(truth**2)), rel=0.25)


def test_evidence_says_a_withheld_degree_is_not_measured():
    u = Rotation.from_rotvec([0.1, -0.2, 0.05]).apply(_three_great_circles(500))
    sh = st.sh_analysis(u, np.random.default_rng(5).normal(0, 300.0, len(u)))
    c = Candidate(
        effect="nonlinearity_cubic",
        sensor=None,
        label="nonlinearity_cubic",
        n_params=3,
        lm=10.0,
        p_value=1e-3,
        predicted_delta_bic=-5.0,
        delta_bic=-5.0,
        rms_after_nT=290.0,
    )
    text = _effect_extra(c, None, None, None, [sh])
    assert "not resolved by the coverage" in text and "up to 2" in text and "nan" not in text
    full = st.sh_analysis(
        Rotation.random(2000, random_state=6).apply([0, 0, 1.0]), np.random.default_rng(6).normal(0, 30.0, 2000)
    )
    assert _effect_extra(c, None, None, None, [full]).startswith("direction degree 4: ")


def _tumbled_directions(n, rate_hz, turn_dps, seed):
    """Field directions (N, 3) of a sensor turned at ``turn_dps`` about an axis that itself wanders."""
    rng = np.random.default_rng(seed)
    dt = 1.0 / rate_hz
    axis = rng.normal(size=3)
    rot = Rotation.identity()
    out = np.empty((n, 3))
    for i in range(n):
        axis = axis / np.linalg.norm(axis) + 0.05 * rng.normal(size=3)
        rot = Rotation.from_rotvec(np.radians(turn_dps) * dt * axis / np.linalg.norm(axis)) * rot
        out[i] = rot.apply([0.0, 0.0, 1.0])
    return out


@pytest.mark.parametrize("truth", ["none", "field", "offset", "static_pattern"])
def test_revisits_tell_a_changing_field_from_a_wandering_offset(truth):
    """Same-direction revisits: a field change (the same in every direction) reads ``field``, an offset wander
    (``u . b(t)``) reads ``offset``, noise alone and a static direction pattern (a misfit, a nonlinearity: the same at
    every visit, however large) read ``none``."""
    n, rate = 3000, 10.0
    t = np.arange(n) / rate
    u = _tumbled_directions(n, rate, 60.0, seed=1)
    rng = np.random.default_rng(2)
    sigma = 3.0
    r = sigma * rng.normal(size=n)
    if truth == "field":
        r += 20.0 * np.sin(2 * np.pi * t / 90.0) + 10.0 * np.sin(2 * np.pi * t / 40.0)
    elif truth == "offset":
        b = 30.0 * np.column_stack([np.sin(2 * np.pi * t / 37.0), np.cos(2 * np.pi * t / 23.0), np.sin(t / 9.0)])
        r += np.sum(u * b, axis=1)
    elif truth == "static_pattern":
        r += 200.0 * (u[:, 0] ** 4 + u[:, 1] ** 4 + u[:, 2] ** 4 - 0.6)
    knots = np.linspace(t[0], t[-1], 61)
    hats = np.clip(1.0 - np.abs(t[:, None] - knots[None, :]) / (knots[1] - knots[0]), 0.0, None)[:, 1:]
    found = st.revisit_forms(u, r, t, hats)
    assert found is not None
    assert found.form == {"static_pattern": "none"}.get(truth, truth), found.text()
    if truth == "none":  # white noise: the visits differ by sqrt(2) sigma at any time apart
        assert np.allclose(found.gap_rms_nT, np.sqrt(2) * sigma, rtol=0.15)
    assert "same-direction revisits" in found.text()


def test_revisits_need_enough_revisited_samples():
    """Too few samples for the series: no verdict rather than one fitted to noise."""
    t = np.arange(40) / 10.0
    u = _tumbled_directions(40, 10.0, 60.0, seed=3)
    hats = np.column_stack([np.sin(t * k) for k in range(1, 9)])
    assert st.revisit_forms(u, np.zeros(40), t, hats) is None


@pytest.mark.parametrize(("spread_deg", "resolved"), [(90.0, True), (8.0, False)])
def test_the_calibration_shape_is_judged_only_where_the_directions_fix_it(spread_deg, resolved):
    """Degree 2 (the ellipsoid's shape) to :data:`SHAPE_JUDGED_MIN_EIGEN`: a full sphere fixes it, a band of
    directions within a few degrees of one great circle does not."""
    rng = np.random.default_rng(4)
    lon = rng.uniform(-np.pi, np.pi, 4000)
    lat = np.arcsin(np.sin(np.radians(spread_deg)) * rng.uniform(-1.0, 1.0, 4000))
    u = np.column_stack([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)])
    assert st.resolves_degree(u, 2, st.SHAPE_JUDGED_MIN_EIGEN) is resolved


def _hats(t, n_knots):
    knots = np.linspace(t[0], t[-1], n_knots)
    return np.clip(1.0 - np.abs(t[:, None] - knots[None, :]) / (knots[1] - knots[0]), 0.0, None)[:, 1:]


@pytest.mark.parametrize("truth", ["fast_field", "offset"])
def test_a_field_faster_than_the_knots_is_not_read_as_an_offset(truth):
    """A field that changes faster than the series' knots (the place changing as the sensor is carried past a magnet
    fixed in the room) reads ``offset`` on the series' knots alone, for the offset form's three times the columns;
    the pace test on knots three times closer finds it faster and reads ``field``. A slow offset stays ``offset``."""
    n, rate = 3000, 10.0
    t = np.arange(n) / rate
    u = _tumbled_directions(n, rate, 60.0, seed=1)
    r = 3.0 * np.random.default_rng(4).normal(size=n)
    if truth == "fast_field":  # a bump of about 4 s as the sensor passes the magnet, every 11 s (knots 5 s apart)
        r += 150.0 * np.exp(-0.5 * ((t % 11.0 - 5.5) / 1.2) ** 2)
    else:
        r += np.sum(u * 30.0 * np.column_stack([np.sin(t / 37.0), np.cos(t / 23.0), np.sin(t / 19.0)]), axis=1)
    coarse, closer = _hats(t, 61), _hats(t, 3 * 60 + 1)
    alone = st.revisit_forms(u, r, t, coarse)
    paced = st.revisit_forms(u, r, t, coarse, fine_columns=closer)
    if truth == "fast_field":
        assert alone.form in ("offset", "both"), alone.text()
        assert paced.form == "field" and paced.faster_than_knots, paced.text()
        assert "faster than the series' knots" in paced.text() and "fixed in the room" in paced.text()
    else:
        assert alone.form == paced.form == "offset" and not paced.faster_than_knots, paced.text()
        assert "carried with the sensor" in paced.text()


@pytest.mark.parametrize("seed", [1, 2])
def test_a_magnet_fixed_in_the_room_reads_field_and_one_carried_with_the_sensor_reads_offset(seed):
    """A hand-held tumble (about 100 deg/s) under motion capture, calibrated by the total field: a magnet fixed 0.35
    m from the path is a field that changes with the place (passed at a walking pace, faster than the series' knots);
    a magnet carried with the sensor and moved from 10 to 15 cm over the record is an offset that changes in the
    sensor's axes. The revisits' words say which."""
    from magcal.api import calibrate
    from magcal.data.lab import lab_truth, simulate_lab
    from magcal.diagnosis._fitted import _kept, _sensor_directions
    from magcal.diagnosis.evidence import revisit_words

    truth = lab_truth(seed=seed)
    options = {"n": 3000, "seed": seed, "noise_nT": 20.0, "turns": 4.0}
    fixed, _ = simulate_lab(truth, dipole=((0.0, 0.35, 0.0), (0.0, 0.0, 0.5)), **options)
    carried, _ = simulate_lab(truth, carried_dipole=((0.10, 0, 0), (0.15, 0, 0), (0.01, 0, 0)), **options)
    clean, _ = simulate_lab(truth, **options)
    words = {}
    for name, ds in (("fixed", fixed), ("carried", carried), ("clean", clean)):
        fit = calibrate(ds, mode="total_field", warn=False).fit
        kept = _kept(ds, fit)
        words[name] = revisit_words(kept, fit, _sensor_directions(kept, fit)[0])
    assert "a field that changes (in time, or with the place" in words["fixed"], words["fixed"]
    assert "an offset that wanders (the sensor's own, or a magnet" in words["carried"], words["carried"]
    assert "faster than the series' knots" not in words["carried"]
    assert "no change in time between the visits" in words["clean"], words["clean"]
