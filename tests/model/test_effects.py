"""The effect catalogue: bases, perturbations, data-derived state, parameter recovery."""

import json

import numpy as np
import pytest

import magcal.model.effects as fx
from magcal.calibration.calibration import Calibration
from magcal.core import conventions
from magcal.core.errors import MagcalError
from magcal.data.simulation import chi2017_truth, simulate_timeseries
from magcal.fitting.fitter import fit
from magcal.model import perturbations
from magcal.model.terms import EFFECTS, Model, contexts, parse_effect

ISSUE_EFFECTS = (
    "temperature_bias",
    "temperature_scale",
    "bias_drift",
    "bias_step",
    "nonlinearity_quadratic",
    "nonlinearity_cubic",
    "axis_timing_skew",
    "sensor_timing_skew",
    "reference_drift",
    "site_gradient",
)
UNITS = ("_nT", "_ms", "_ms2", "_ppm_per_K", "_nT_per_K", "_nT_per_h", "_nT_per_m", "_nT_per_unit", "_nT_per_A")


def _pair(name, magnitude=None, n_sensors=1, seed=4, n=600, sensor=None):
    """Noise-free data with and without the effect (same trajectory and temperature)."""
    effect = EFFECTS[name]()
    truth = chi2017_truth(n_sensors)
    clean = simulate_timeseries(truth, n_samples=n, noise_nT=0.0, seed=seed)
    pert = simulate_timeseries(
        truth, n_samples=n, noise_nT=0.0, seed=seed, perturbations=[effect.perturbation(magnitude, sensor)]
    )
    return truth, clean, pert, effect


def _true_residuals(truth, ds):
    """Total-field residuals of the true base calibration (what a base fit leaves, before refinement)."""
    out = []
    for s, y in zip(truth.sensors, ds.readings_nT):
        b = (y - s.total_offset_nT) @ np.linalg.inv(s.total_matrix).T
        out.append(np.linalg.norm(b, axis=1) - truth.total_nT)
    return np.array(out)


def _rms_error(error, reference):
    """RMS of ``error`` (N, 3) after removing what the base terms absorb (an affine function of the reading:
    bias, scale, non-orthogonality), leaving out the worst 2 % of samples: the simulator's trajectory has a kink
    where its pitch turns at +-90 deg, where time derivatives (timing skews) and reversals (hysteresis) are
    ill-defined."""
    design = np.column_stack([np.ones(len(reference)), reference])
    coef, *_ = np.linalg.lstsq(design, error, rcond=None)
    e = np.linalg.norm(error - design @ coef, axis=1)
    e = np.sort(e)[: int(0.98 * len(e))]
    return float(np.sqrt(np.mean(e**2)))


def test_catalogue_has_every_effect_of_the_issue():
    assert set(ISSUE_EFFECTS) <= set(EFFECTS)
    assert "hysteresis" in EFFECTS


@pytest.mark.parametrize("name", sorted(EFFECTS))
def test_declarations_are_consistent(name):
    cls = EFFECTS[name]
    n_sensors = max(cls.min_sensors, 1) if cls.min_sensors > 1 else 1
    truth, clean, pert, effect = _pair(name, n_sensors=max(n_sensors, 2 if cls.min_sensors > 1 else 1), n=200)
    effect.configure(pert, _true_residuals(truth, pert))
    q = len(effect.param_names())
    assert len(effect.param_scale()) == q and np.all(effect.param_scale() > 0)
    assert all(any(p.endswith(u) for u in UNITS) for p in effect.param_names()), effect.param_names()
    assert effect.default_magnitude > 0 and effect.magnitude_unit and effect.description
    ctx = contexts(pert, pert.baseline_m)[-1]
    if cls.stage == "raw":
        basis = effect.raw_basis(pert.readings_nT[-1], ctx)
        assert basis.shape == (pert.n_samples, 3, q)
    elif cls.stage == "array":
        basis = effect.array_basis(pert.readings_nT[-1], ctx)
        assert basis.shape == (pert.n_samples, 3, q)
    else:
        basis = effect.reference_basis(ctx)
        assert basis.shape == (pert.n_samples, q)
        assert np.allclose(basis.mean(axis=0), 0.0, atol=1e-9)  # zero mean: F0 keeps its meaning
    assert np.all(np.isfinite(basis))


RAW = [
    "temperature_bias",
    "temperature_scale",
    "bias_drift",
    "bias_step",
    "nonlinearity_quadratic",
    "nonlinearity_cubic",
    "axis_timing_skew",
    "hysteresis",
    "current_field",
]


@pytest.mark.parametrize("name", RAW)
@pytest.mark.parametrize("sensor", [0, 2])
def test_raw_basis_undoes_the_physical_perturbation(name, sensor):
    """z0 - basis(z0) @ theta_true equals the unperturbed reading to first order in the effect."""
    truth, clean, pert, effect = _pair(name, n_sensors=4, sensor=sensor)
    effect.configure(pert, _true_residuals(truth, pert))
    theta = effect.true_params(None, sensor)
    s = truth.sensors[sensor]
    z0_clean = clean.readings_nT[sensor] - s.total_offset_nT
    z0 = pert.readings_nT[sensor] - s.total_offset_nT
    ctx = contexts(pert, pert.baseline_m)[sensor]
    corrected = z0 - effect.raw_basis(z0, ctx) @ theta
    size = np.sqrt(np.mean((z0 - z0_clean) ** 2))
    error = _rms_error(corrected - z0_clean, z0_clean)
    assert size > 0.5  # the perturbation is there (nT)
    # hysteresis: the samples in the play operator's dead zone after each reversal are approximate
    assert error < (0.1 if name == "hysteresis" else 0.02) * size, (size, error)
    other = (sensor + 1) % 4
    assert np.allclose(pert.readings_nT[other], clean.readings_nT[other])  # only the named sensor


@pytest.mark.parametrize("name", ["sensor_timing_skew", "site_gradient"])
def test_array_basis_undoes_the_physical_perturbation(name):
    truth, clean, pert, effect = _pair(name, n_sensors=4, magnitude=None)
    effect.configure(pert, None)
    ctxs = contexts(pert, pert.baseline_m)
    for s, sensor in enumerate(truth.sensors):
        rc = sensor.R @ np.linalg.inv(sensor.total_matrix)
        b_clean = (clean.readings_nT[s] - sensor.total_offset_nT) @ rc.T
        b = (pert.readings_nT[s] - sensor.total_offset_nT) @ rc.T
        if not effect.applies_to(s):
            assert np.allclose(b, b_clean)
            continue
        theta = effect.true_params(None, s)
        corrected = b + effect.array_basis(b, ctxs[s]) @ theta
        size = np.sqrt(np.mean((b - b_clean) ** 2))
        error = _rms_error(corrected - b_clean, b_clean)
        assert size > 0.5 and error < 0.02 * size, (s, size, error)


def test_reference_drift_basis_spans_a_slow_field_variation():
    truth, clean, pert, effect = _pair("reference_drift", n_sensors=1, magnitude=8.0)
    effect.configure(pert, None)
    s = truth.sensors[0]
    inv = np.linalg.inv(s.total_matrix)
    d_total = np.linalg.norm((pert.readings_nT[0] - s.total_offset_nT) @ inv.T, axis=1) - np.linalg.norm(
        (clean.readings_nT[0] - s.total_offset_nT) @ inv.T, axis=1
    )
    basis = np.column_stack([np.ones(pert.n_samples), effect.reference_basis(contexts(pert)[0])])
    coef, *_ = np.linalg.lstsq(basis, d_total, rcond=None)
    assert np.sqrt(np.mean(d_total**2)) > 3.0
    assert np.sqrt(np.mean((d_total - basis @ coef) ** 2)) < 0.05 * np.std(d_total)


@pytest.mark.parametrize(
    "name, n_sensors, mult",
    [
        ("temperature_bias", 1, 1),
        ("temperature_scale", 1, 2),
        ("bias_drift", 1, 1),
        ("bias_step", 1, 1),
        ("nonlinearity_quadratic", 1, 1),
        ("nonlinearity_cubic", 1, 2),
        ("axis_timing_skew", 1, 3),
        ("hysteresis", 1, 1),
        ("sensor_timing_skew", 4, 2),
        ("site_gradient", 4, 1),
    ],
)
def test_fit_recovers_the_hidden_parameters(name, n_sensors, mult):
    """Units and signs: the fitted parameters equal the simulator's within their standard deviations."""
    effect = EFFECTS[name]()
    magnitude = mult * effect.default_magnitude
    ds = simulate_timeseries(
        chi2017_truth(n_sensors), n_samples=1200, noise_nT=2.0, seed=7, perturbations=[effect.perturbation(magnitude)]
    )
    result = fit(ds, Model.from_names([name], n_sensors))
    for entry in result.effect_params:
        s = 0 if entry["sensor"] is None else entry["sensor"] - 1
        truth = effect.true_params(magnitude, s)
        got = np.array(list(entry["params"].values()))
        std = np.array(list(entry["std"].values()))
        assert np.all(np.abs(got - truth) < 5 * std + 0.03 * np.abs(truth) + 1e-9), (entry, truth)
    floor = conventions.total_field_floor_nT(2.0, 1200, result.n_params / n_sensors)
    assert result.rms_nT < 1.05 * floor


@pytest.mark.parametrize("name", ["temperature_bias", "bias_drift", "bias_step", "reference_drift", "hysteresis"])
def test_state_survives_json(name):
    truth, clean, pert, effect = _pair(name, n_sensors=1, n=300)
    effect.configure(pert, _true_residuals(truth, pert))
    state = json.loads(json.dumps(effect.state()))
    other = EFFECTS[name]()
    other.set_state(state)
    ctx = contexts(pert)[0]
    if effect.stage == "raw":
        z0 = pert.readings_nT[0] - truth.sensors[0].total_offset_nT
        assert np.allclose(effect.raw_basis(z0, ctx), other.raw_basis(z0, ctx))
    else:
        assert np.allclose(effect.reference_basis(ctx), other.reference_basis(ctx))


def test_calibration_with_effects_round_trips_through_json(tmp_path):
    truth = chi2017_truth(2)
    ds = simulate_timeseries(
        truth,
        n_samples=800,
        noise_nT=2.0,
        seed=3,
        perturbations=[perturbations.parse_hidden("bias_step:2=12", 2), perturbations.parse_hidden("hysteresis", 2)],
    )
    result = fit(ds, Model.from_names(["bias_step:2", "hysteresis", "temperature_bias", "reference_drift"], 2))
    path = tmp_path / "cal.json"
    result.calibration.save(path)
    loaded = Calibration.load(path)
    assert np.allclose(loaded.correct(ds), result.calibration.correct(ds), atol=1e-6)
    doc = json.loads(path.read_text())
    terms = {e["term"] for e in doc["effect_params"]}
    assert {"bias_step:2", "hysteresis", "temperature_bias", "reference_drift"} <= terms


def test_bias_step_time_is_found_by_the_scan():
    truth = chi2017_truth(1)
    ds = simulate_timeseries(
        truth, n_samples=1000, noise_nT=3.0, seed=2, perturbations=[perturbations.parse_hidden("bias_step=15", 1)]
    )
    effect = EFFECTS["bias_step"]()
    effect.configure(ds, _true_residuals(truth, ds))
    te = effect.step_time_s[0]
    t = ds.time_s
    expected = t[0] + 0.6 * (t[-1] - t[0])
    assert abs(te - expected) < 3 * np.median(np.diff(t))


def test_step_scan_finds_a_moved_ellipsoid_centre_without_a_calibration():
    rng = np.random.default_rng(0)
    u = rng.normal(size=(600, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    y = 50_000 * u * [1.02, 0.99, 1.01] + [120.0, -80.0, 40.0] + rng.normal(0, 2.0, (600, 3))
    y[321:] += [6.0, -4.0, 3.0]
    k, improvement = fx.step_scan(y)
    assert abs(k - 321) <= 3
    assert improvement[k] > 25 * 4.0  # far above the noise (sigma^2 = 4 nT^2 per sample)
    k0, none = fx.step_scan(y[:321])  # no step: no comparable improvement anywhere
    assert none.max() < 0.2 * improvement[k]


def test_time_derivative_of_a_sine():
    t = np.arange(0, 20, 0.1)
    x = np.column_stack([np.sin(0.7 * t), 3 * np.cos(0.3 * t)])
    d = fx.time_derivative(x, t)
    truth = np.column_stack([0.7 * np.cos(0.7 * t), -0.9 * np.sin(0.3 * t)])
    assert np.abs(d - truth).max() < 1e-3
    irregular = np.sort(np.random.default_rng(1).uniform(0, 20, 400))
    d2 = fx.time_derivative(np.sin(irregular), irregular)
    assert np.abs(d2 - np.cos(irregular))[5:-5].max() < 0.02


def test_play_operator_lags_by_its_half_width():
    x = np.concatenate([np.linspace(0, 100, 101), np.linspace(99, 0, 100)])
    out = fx.play_operator(x, 5.0)
    assert np.all(np.abs(out - x) <= 5.0 + 1e-12)
    assert np.allclose(out[10:101], x[10:101] - 5.0)  # rising: lags by h
    assert np.allclose(out[115:], x[115:] + 5.0)  # falling after the dead zone of 2h
    assert np.all(out[101:110] == out[100])  # dead zone after the reversal


@pytest.mark.parametrize(
    "spec, effect, sensor, magnitude",
    [
        ("temperature_bias:2=3", "temperature_bias", 1, 3.0),
        ("bias_drift", "bias_drift", None, 300.0),
        ("site_gradient=1,2,3,4,5", "site_gradient", None, [1.0, 2.0, 3.0, 4.0, 5.0]),
        ("periodic_interference:4=2", "periodic_interference", 3, 2.0),
    ],
)
def test_parse_hidden(spec, effect, sensor, magnitude):
    p = perturbations.parse_hidden(spec, 4)
    assert p.effect == effect and p.sensor == sensor and p.magnitude == magnitude and p.description


@pytest.mark.parametrize(
    "spec, n_sensors, message",
    [
        ("no_such=1", 4, "unknown effect"),
        ("temperature_bias:5", 4, "does not exist"),
        ("temperature_bias=abc", 4, "must be a number"),
        ("sensor_timing_skew:1", 4, "time reference"),
        ("site_gradient", 1, "at least 2 sensors"),
        ("reference_drift:2", 4, "shared by the whole array"),
    ],
)
def test_parse_hidden_refuses_clearly(spec, n_sensors, message):
    with pytest.raises(MagcalError, match=message):
        perturbations.parse_hidden(spec, n_sensors)


def test_sensor_timing_skew_has_no_parameters_for_the_reference_sensor():
    model = Model.from_names(["sensor_timing_skew"], 4)
    assert [s for _, s in model.instances()] == [1, 2, 3]
    with pytest.raises(MagcalError, match="time reference"):
        parse_effect("sensor_timing_skew:1", 4)


def test_periodic_interference_hides_a_sinusoid_of_the_given_peak():
    """Its perturbation (the catalogue effect since it learnt the term; tests/model/test_effects_interference.py fits it)."""
    assert "periodic_interference" in EFFECTS and not EFFECTS["periodic_interference"].transferable
    truth = chi2017_truth(1)
    clean = simulate_timeseries(truth, n_samples=300, noise_nT=0.0, seed=1)
    pert = simulate_timeseries(
        truth, n_samples=300, noise_nT=0.0, seed=1, perturbations=[perturbations.periodic_interference(4.0, 0.5)]
    )
    d = pert.readings_nT[0] - clean.readings_nT[0]
    assert np.allclose(np.linalg.norm(d, axis=1).max(), 4.0, rtol=0.01)


# ----------------------------------------------------------------------------------------------------------------
# no non-physical parameter: a hysteresis loop width is not negative
# ----------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", range(1, 9))
@pytest.mark.parametrize("widths_nT", [(6.0, 0.0, 0.0), (0.0, 0.0, 4.0)])
def test_fit_never_returns_a_negative_hysteresis_width(widths_nT, seed):
    """Axes without hysteresis sit at the bound 0 (an unbounded fit puts about half of them below it), and the
    axis with it is still recovered."""
    ds = simulate_timeseries(
        chi2017_truth(1),
        n_samples=800,
        noise_nT=3.0,
        seed=seed,
        perturbations=[EFFECTS["hysteresis"]().perturbation(list(widths_nT))],
    )
    result = fit(ds, Model.from_names(["hysteresis"], 1))
    fitted = np.array(list(result.effect_params[0]["params"].values()))
    assert np.all(fitted >= 0.0), fitted
    hidden = int(np.argmax(widths_nT))
    assert abs(fitted[hidden] - widths_nT[hidden]) < 0.25 * widths_nT[hidden], fitted


def test_a_negative_hysteresis_width_is_refused_clearly():
    effect = EFFECTS["hysteresis"]()
    assert np.allclose(effect.check_params([2.0, 0.0, 1.5]), [2.0, 0.0, 1.5])
    with pytest.raises(MagcalError, match=r"hysteresis: h_y_nT = -1 is not physical; it must be >= 0 \(.*lags"):
        effect.check_params([2.0, -1.0, 0.0])
    with pytest.raises(MagcalError, match="shape_half_width_nT of sensor 2 .* numbers >= 0"):
        EFFECTS["hysteresis"](shape_half_width_nT=[[1.0, 1.0, 1.0], [1.0, -3.0, 0.0]])
    with pytest.raises(MagcalError, match="shape_half_width_nT of sensor 1"):
        EFFECTS["hysteresis"]().set_state({"shape_half_width_nT": [[-1.0, 0.0, 0.0]]})
    with pytest.raises(MagcalError, match="half-width must be >= 0"):
        simulate_timeseries(
            chi2017_truth(1), n_samples=100, perturbations=[perturbations.parse_hidden("hysteresis=-5,0,0", 1)]
        )


def test_a_starting_calibration_with_a_negative_hysteresis_width_is_refused():
    """A Calibration built by the user (effect_values) and given as the start of a fit."""
    ds = simulate_timeseries(chi2017_truth(1), n_samples=400, noise_nT=3.0, seed=1)
    model = Model.from_names(["hysteresis"], 1)
    start = fit(ds).calibration
    start = Calibration(
        start.sensors, start.reference_total_nT, model=model, effect_values={"hysteresis:1": np.array([0.0, -2.0, 0.0])}
    )
    with pytest.raises(MagcalError, match=r"starting calibration \(hysteresis:1\): hysteresis: h_y_nT = -2"):
        fit(ds, model, init=start)


def test_a_calibration_file_with_a_negative_hysteresis_width_is_refused(tmp_path):
    ds = simulate_timeseries(
        chi2017_truth(1),
        n_samples=600,
        noise_nT=3.0,
        seed=2,
        perturbations=[perturbations.parse_hidden("hysteresis", 1)],
    )
    path = tmp_path / "cal.json"
    fit(ds, Model.from_names(["hysteresis"], 1)).calibration.save(path)
    doc = json.loads(path.read_text())
    doc["effect_params"][0]["params"]["h_x_nT"] = -4.0
    path.write_text(json.dumps(doc))
    with pytest.raises(MagcalError, match=rf"{path.name}.*h_x_nT = -4 is not physical"):
        Calibration.load(path)


# ----------------------------------------------------------------------------------------------------------------
# every parameter quoted at the data's own field magnitude
# ----------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name, magnitude", [("nonlinearity_quadratic", 20.0), ("nonlinearity_cubic", 30.0)])
@pytest.mark.parametrize("with_reference", [True, False])
def test_nonlinearity_is_quoted_at_the_field_of_the_data(name, magnitude, with_reference):
    """In a 10 uT field the coefficient is the deviation at 10 uT (not at 50 uT, which would be 25x / 125x
    larger), known from the reference or, when the field is fitted, from the readings."""
    truth = chi2017_truth(1)
    truth.total_nT = 10_000.0
    hidden = EFFECTS[name]().perturbation(magnitude)
    ds = simulate_timeseries(
        truth, n_samples=1200, noise_nT=1.0, seed=7, perturbations=[hidden], with_reference=with_reference
    )
    assert hidden.description == f"{name} {magnitude} nT at 10 uT (all sensors)"
    result = fit(ds, Model.from_names([name], 1))
    effect = result.calibration.model.effects[0]
    assert effect.field_magnitude_nT == pytest.approx(10_000.0, rel=1e-9 if with_reference else 0.03)
    assert effect.quote_unit() == ("nT at 10 uT" if with_reference else effect.quote_unit(effect.field_magnitude_nT))
    got = np.array(list(result.effect_params[0]["params"].values()))
    std = np.array(list(result.effect_params[0]["std"].values()))
    truth_params = EFFECTS[name]().true_params(magnitude, 0)
    tolerance = 5 * std + (0.03 if with_reference else 0.12) * np.abs(truth_params)
    assert np.all(np.abs(got - truth_params) < tolerance), (got, truth_params)


def test_nonlinearity_without_a_known_field_is_quoted_at_50_uT():
    """An effect never configured, or restored from a calibration saved before the field was recorded."""
    effect = EFFECTS["nonlinearity_quadratic"]()
    effect.set_state({})
    assert effect.quote_unit() == "nT at 50 uT" and effect.quoted_at_nT == fx.NONLINEARITY_REFERENCE_NT
    with pytest.raises(MagcalError, match="field_magnitude_nT must be a positive number"):
        effect.set_state({"field_magnitude_nT": -3.0})


@pytest.mark.parametrize(
    "name, state, message",
    [
        ("bias_drift", {"reference_time_s": 5.0, "duration_s": -10.0}, "duration_s must be a positive number"),
        ("bias_drift", {"reference_time_s": "soon", "duration_s": 10.0}, "reference_time_s must be a finite number"),
        (
            "temperature_bias",
            {"reference_temperature_C": -300.0},
            r"reference_temperature_C must be a finite number >= "
            r"-273.15",
        ),
        ("bias_step", {"step_time_s": [float("nan")]}, "step_time_s must be a finite number"),
        ("bias_step", {"step_time_s": 4.0}, "step_time_s must be a list"),
        ("reference_drift", {"time_span_s": [10.0, 2.0], "offsets": None}, "the last after the first"),
        ("reference_drift", {"time_span_s": [0.0, 2.0], "offsets": [0.0, 1.0]}, "offsets must be 4 numbers"),
        ("periodic_interference", {"frequency_hz": [0.0]}, "positive number of Hz"),
        ("nonlinearity_cubic", {"field_magnitude_nT": 0.0}, "field_magnitude_nT must be a positive number"),
    ],
)
def test_data_derived_constants_that_are_not_physical_are_refused(name, state, message):
    with pytest.raises(MagcalError, match=message):
        EFFECTS[name]().set_state(state)


def test_a_calibration_file_with_a_negative_record_length_is_refused(tmp_path):
    ds = simulate_timeseries(chi2017_truth(1), n_samples=400, noise_nT=3.0, seed=2)
    path = tmp_path / "cal.json"
    fit(ds, Model.from_names(["bias_drift"], 1)).calibration.save(path)
    doc = json.loads(path.read_text())
    doc["effect_params"][0]["state"]["duration_s"] = -40.0
    path.write_text(json.dumps(doc))
    with pytest.raises(MagcalError, match="bias_drift: duration_s must be a positive number"):
        Calibration.load(path)


@pytest.mark.parametrize("name", ["nonlinearity_quadratic", "nonlinearity_cubic"])
def test_the_report_quotes_a_nonlinearity_at_the_data_field_not_at_50_uT(name):
    """The cubic term was quoted "at 50 uT" for a field of 8.9 uT."""
    from magcal import calibrate
    from magcal.calibration.report import text_report

    truth = chi2017_truth(1)
    truth.total_nT = 8_900.0
    ds = simulate_timeseries(
        truth, n_samples=1200, noise_nT=0.5, seed=7, perturbations=[EFFECTS[name]().perturbation(20.0)]
    )
    result = calibrate(ds, effects=[name])
    lines = text_report(result).splitlines()
    i = next(k for k, line in enumerate(lines) if line.strip().startswith(f"{name} (sensor 1)"))
    quote = lines[i + 1]
    assert "an axis reading the whole field of the data, 8.9 uT, is off by" in quote, quote
    assert "50 uT" not in "\n".join(lines[i : i + 3])


@pytest.mark.parametrize(
    "name, values, field_nT, expected",
    [
        (
            "temperature_scale",
            [100.0, -50.0, 0.0],
            35_700.0,
            "at the data's field 35.7 uT: an axis reading the whole field changes by (3.57, -1.78, 0) nT/K",
        ),
        ("hysteresis", [3.57, 0.0, 35.7], 35_700.0, "loop half-widths (100, 0, 1000) ppm of the data's field 35.7 uT"),
        ("temperature_bias", [1.0, 2.0, 3.0], 35_700.0, ""),
    ],
)
def test_field_relative_parameters_are_quoted_at_the_given_field(name, values, field_nT, expected):
    assert EFFECTS[name]().quote(values, field_nT) == expected
