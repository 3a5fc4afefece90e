"""The loop on a vehicle: the vector diagnosis names the effect hidden in a simulated flight, and the
calibration with it carries to the vehicle's next flight as well as the true calibration does."""

from __future__ import annotations

import json

import numpy as np
import pytest

import magcal
from magcal.checks.reference import resolve_vector_reference
from magcal.cli import main
from magcal.core.errors import CalibrationError, MagcalError
from magcal.data.attitude import attitude
from magcal.data.dataset import dataset_columns, dataset_metadata
from magcal.data.io import write_csv
from magcal.data.vehicle import simulate_vehicle, vehicle_truth
from magcal.diagnosis.vector import Flight, diagnose_vector, vector_candidates
from magcal.fitting.vector import fit_vector, true_calibration
from magcal.model.perturbations import parse_hidden
from magcal.model.terms import EFFECTS, Model

N = 3000

#: (hidden effect spec, what the diagnosis must name, options of the next flight's perturbation)
CASES = [
    ("none", [], None),
    ("current_field=25", ["current_field"], None),
    ("temperature_bias=20", ["temperature_bias"], None),
    ("eddy_currents=12", ["eddy_currents"], None),
    ("attitude_time_offset=-80", ["attitude_time_offset"], None),  # the magnetometer sampled 80 ms after its attitude
    ("bias_step=60", ["bias_step"], {"at_fraction": 0.0}),  # the sensor stays permed: the next flight after the step
]


def _flight(truth, seed, spec, **options):
    hidden = [] if spec == "none" else [_perturbation(spec, options)]
    ds, _ = simulate_vehicle(truth, seed=seed, n=N, perturbations=hidden, log_current=True, temperature=True)
    return ds


def _perturbation(spec, options):
    if not options:
        return parse_hidden(spec, 1)
    name, _, magnitude = spec.partition("=")
    return EFFECTS[name]().perturbation(float(magnitude), None, **options)


def _world_rms(calibration, ds):
    world = calibration.world(ds, record_terms="drop")[0]
    return float(np.sqrt(np.mean((world - resolve_vector_reference(ds).ned_nT) ** 2)))


@pytest.fixture(scope="module")
def truth():
    return vehicle_truth(seed=3)


@pytest.mark.parametrize("spec, named, next_options", CASES, ids=[c[0].split("=")[0] for c in CASES])
def test_the_diagnosis_names_the_hidden_effect_and_its_calibration_carries_to_the_next_flight(
    truth, spec, named, next_options
):
    one = _flight(truth, 1, spec)
    two = _flight(truth, 2, spec, **(next_options or {}))
    d = diagnose_vector(one, resolve_vector_reference(one))
    assert d.explained_by == named
    assert d.verdict == ("missing_effect" if named else "adequate")
    if named:
        assert named[0] in d.summary and d.candidates[0].label == named[0] and d.candidates[0].recommended
        assert d.final.world_nT < 0.9 * d.base.world_nT
    # the advice, fitted on flight 1 and applied to flight 2 as magcal apply does, against the true calibration on
    # the same flight simulated without the hidden effect (the same noise: what a perfect correction leaves)
    ours = fit_vector(one, resolve_vector_reference(one), effects=d.explained_by, warn=False).calibration
    clean = _flight(truth, 2, "none")
    best = _world_rms(true_calibration(simulate_vehicle(truth, seed=2, n=N)[1]), clean)
    assert _world_rms(ours, two) <= 1.25 * best
    if named:  # the base model alone does not carry: the effect matters on the next flight
        base = fit_vector(one, resolve_vector_reference(one), warn=False).calibration
        assert _world_rms(base, two) > 1.25 * best


def test_other_flights_judge_the_candidates_and_the_advice_never_hurts_them(truth):
    """With the next flight given (``also``), a platform term must improve it too; a record-only term (the bias
    step) is judged on the record's later part, and the summary says what magcal apply keeps of it."""
    one, two = _flight(truth, 1, "current_field=25"), _flight(truth, 2, "current_field=25")
    d = diagnose_vector(one, resolve_vector_reference(one), also=[Flight(two, resolve_vector_reference(two), "two")])
    (best,) = [c for c in d.candidates if c.recommended]
    assert best.label == "current_field" and best.flights[0][0] == "two"
    name, before, after = best.flights[0]
    assert after.world_nT < 0.3 * before.world_nT and after.weighted < 1.25
    for c in d.candidates:
        for _, b, a in c.flights:
            assert not c.recommended or a.weighted <= b.weighted
    stepped = _flight(truth, 1, "bias_step=60")
    d = diagnose_vector(stepped, resolve_vector_reference(stepped))
    assert d.explained_by == ["bias_step"] and "the bias after the step" in d.summary
    assert "at t = 179.9" in d.summary  # the step's time: 60 % of the 300-s flight


def test_a_candidate_that_fits_this_record_only_is_not_advised():
    """The current swings with the flight's own rhythm in flight 1 only: a field that follows it in flight 1 (a
    periodic interference of that record) must not be advised for the next flight, where it would add error."""
    truth = vehicle_truth(seed=5)
    one, _ = simulate_vehicle(truth, seed=5, n=N, log_current=True)
    t = one.time_s
    one = one.replace(readings_nT=one.readings_nT + 40.0 * np.sin(2 * np.pi * t / 37.0)[None, :, None])
    two, _ = simulate_vehicle(truth, seed=6, n=N, log_current=True)
    d = diagnose_vector(one, resolve_vector_reference(one), also=[Flight(two, resolve_vector_reference(two), "two")])
    assert not [c for c in d.candidates if c.recommended and not c.record_only]
    for c in d.candidates:
        if c.recommended:
            assert c.record_only  # periodic interference describes this record: magcal apply drops it


def test_structure_outside_the_catalogue_is_named_by_what_it_follows(truth):
    """A field that follows the vehicle's heading (no catalogue term has that form): unexplained, named 'heading'."""
    one = _flight(truth, 1, "none")
    yaw = attitude(one).as_euler("ZYX")[:, 0]
    extra = np.zeros_like(one.readings_nT)
    extra[0, :, 0] = 150.0 * np.cos(yaw)
    odd = one.replace(readings_nT=one.readings_nT + extra)
    d = diagnose_vector(odd, resolve_vector_reference(odd), max_effects=1)
    assert d.verdict == "unexplained"
    assert any(s.follows == "heading" for s in d.remaining)
    assert "heading" in d.summary


def test_vector_only_effects_are_refused_in_scalar_mode_and_never_proposed_there():
    for name in ("eddy_currents", "attitude_time_offset"):
        assert EFFECTS[name].modes == ("vector",)
    ds = magcal.simulate_timeseries("chi2017", seed=1)
    with pytest.raises(CalibrationError, match="vector mode"):
        magcal.calibrate(ds, effects=["eddy_currents"], warn=False)
    d = magcal.diagnose(ds, magcal.calibrate(ds, warn=False), warn=False, validate=False)
    assert not {c.effect for c in d.candidates} & {"eddy_currents", "attitude_time_offset"}


def test_vector_candidates_are_the_raw_effects_whose_channels_exist(truth):
    one = _flight(truth, 1, "none")
    names = {e.name for e in vector_candidates(one, Model(1))}
    assert {"current_field", "temperature_bias", "eddy_currents", "attitude_time_offset", "bias_step"} <= names
    assert not names & {"sensor_timing_skew", "reference_drift", "site_gradient"}  # not the raw stage
    bare = one.replace(temperature_C=None, extra={k: v for k, v in one.extra.items() if k != "current_A"})
    names = {e.name for e in vector_candidates(bare, Model(1))}
    assert "current_field" not in names and "temperature_bias" not in names
    two = simulate_vehicle(vehicle_truth(seed=1, n_sensors=2), seed=1, n=300)[0]
    labels = {e.label for e in vector_candidates(two, Model(2)) if e.name == "eddy_currents"}
    assert labels == {"eddy_currents:1", "eddy_currents:2"}


@pytest.mark.parametrize("delay_ms", [-80.0, 40.0])
def test_the_time_offset_and_eddy_matrix_are_recovered(truth, delay_ms):
    ds, _ = simulate_vehicle(truth, seed=4, n=N, perturbations=[parse_hidden(f"attitude_time_offset={delay_ms}", 1)])
    fit = fit_vector(ds, resolve_vector_reference(ds), effects=["attitude_time_offset"], warn=False)
    assert fit.calibration.effect_values["attitude_time_offset:1"][0] == pytest.approx(delay_ms, abs=2.0)
    lead_or_lag = "lags" if delay_ms > 0 else "leads"
    assert f"the magnetometer {lead_or_lag} its attitude" in fit.text()
    eddy = EFFECTS["eddy_currents"]()
    E = eddy.true_params(12.0)
    ds, _ = simulate_vehicle(truth, seed=4, n=N, perturbations=[eddy.perturbation(E)])
    fit = fit_vector(ds, resolve_vector_reference(ds), effects=["eddy_currents"], warn=False)
    assert np.max(np.abs(fit.calibration.effect_values["eddy_currents:1"] - E)) < 1.5  # ms, of 12


def test_magcal_diagnose_in_vector_mode_with_another_flight(truth, tmp_path, capsys):
    for seed, name in ((1, "one.csv"), (2, "two.csv")):
        ds = _flight(truth, seed, "current_field=25")
        write_csv(tmp_path / name, dataset_columns(ds), dataset_metadata(ds))
    args = ["diagnose", str(tmp_path / "one.csv"), "--also", str(tmp_path / "two.csv")]
    assert main(args + ["--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["mode"] == "vector" and doc["verdict"] == "missing_effect" and doc["explained_by"] == ["current_field"]
    assert doc["validation"]["flights"] == ["two.csv"]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "mode: vector" in out and "RECOMMENDED" in out and "reference field vector" in out
    assert "unknown (fitted)" not in out  # the total field's 'not determined' does not speak for a vector fit
    # the advice, as the command line takes it
    assert main(["calibrate", str(tmp_path / "one.csv"), "--effects", "current_field", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["mode"] == "vector" and doc["effects"] == ["current_field"]
    # the scalar mode keeps the total-field diagnosis, and refuses another flight
    assert main(["diagnose", str(tmp_path / "one.csv"), "--mode", "scalar", "--also", str(tmp_path / "two.csv")]) == 2
    assert "--also" in capsys.readouterr().err
    assert main(["calibrate", str(tmp_path / "one.csv"), "--mode", "scalar", "--effects", "eddy_currents"]) == 2
    assert "vector mode" in capsys.readouterr().err


def test_magcal_diagnose_api_takes_a_vector_fit_and_other_flights(truth):
    one, two = _flight(truth, 1, "eddy_currents=12"), _flight(truth, 2, "eddy_currents=12")
    fit = fit_vector(one, resolve_vector_reference(one), warn=False)
    d = magcal.diagnose(one, fit, also=[two], warn=False)
    assert d.mode == "vector" and d.explained_by == ["eddy_currents"]
    assert magcal.diagnose(one, warn=False, max_effects=1).explained_by == ["eddy_currents"]  # auto: vector mode
    with pytest.raises(MagcalError, match="mode"):
        magcal.diagnose(one, fit, mode="scalar", warn=False)


def test_a_delay_is_named_alone_not_beside_the_eddy_matrix_that_holds_it():
    """A common delay is the eddy matrix ``d I``: fitted together they leave a direction no data fix (the fit once
    diverged to a mirrored matrix). The diagnosis tries the matrix in place of the delay, never beside it, and the
    fit refuses the pair with a message."""
    truth = vehicle_truth(seed=11)
    hidden = [parse_hidden("attitude_time_offset=-24", 1)]
    one, _ = simulate_vehicle(truth, seed=1, n=N, turns=20, attitude_noise_deg=0.1, perturbations=hidden)
    d = diagnose_vector(one, resolve_vector_reference(one))
    assert d.explained_by == ["attitude_time_offset"]
    later = [c for c in d.candidates if c.round == 2 and c.effect == "eddy_currents"]
    assert later and later[0].replaces == ["attitude_time_offset"] and not later[0].recommended
    with pytest.raises(CalibrationError, match="special case of eddy_currents"):
        fit_vector(one, resolve_vector_reference(one), effects=["attitude_time_offset", "eddy_currents"], warn=False)


def test_a_long_record_is_judged_on_a_subsample_and_the_advice_fitted_on_all(truth, monkeypatch):
    from magcal.diagnosis import vector as vector_diagnosis

    monkeypatch.setattr(vector_diagnosis, "MAX_SAMPLES", 1000)
    one = _flight(truth, 1, "current_field=25")
    d = diagnose_vector(one, resolve_vector_reference(one))
    assert d.validation["subsample"] == {"samples": 1000, "of": N}
    assert d.explained_by == ["current_field"] and "every k-th sample (1000 of 3000)" in d.text()
    final = d.fits["current_field"]
    assert final.n_samples == N  # the advice, fitted on every sample
    full = fit_vector(one, resolve_vector_reference(one), effects=["current_field"], warn=False)
    assert np.allclose(
        final.calibration.effect_values["current_field:1"], full.calibration.effect_values["current_field:1"]
    )


def test_a_sensor_the_record_does_not_determine_is_not_judged_and_a_gain_within_chance_is_not_advised():
    """Two compasses, the second's fit not determined (a field wandering by tens of uT, which no vector model fits):
    the first's current field is still named, nothing is proposed on the second, and a warning says so."""
    truth = vehicle_truth(seed=2, n_sensors=2)
    hidden = [parse_hidden("current_field:1=25", 2)]
    one, _ = simulate_vehicle(truth, seed=1, n=N, perturbations=hidden, log_current=True)
    rng = np.random.default_rng(0)
    garbled = one.readings_nT.copy()
    garbled[1] += np.cumsum(rng.normal(0.0, 600.0, garbled[1].shape), axis=0)
    one = one.replace(readings_nT=garbled)
    d = diagnose_vector(one, resolve_vector_reference(one), max_effects=1)
    assert d.explained_by == ["current_field:1"]
    assert not [c for c in d.candidates if c.sensor == 1]
    assert any("sensor(s) 2 is not determined" in w for w in d.warnings)
    # per-sample gains that are chance: one large but correlated stretch does not count as many samples
    from magcal.diagnosis.vector import Scores, significant_gain

    wander = np.repeat([1.5, -1.0, 1.2, -0.8, -1.3, 1.0], 100)  # six stretches of 100 correlated samples
    before = Scores(0, 0, 0, 600, np.full(600, 2.0))
    assert not significant_gain(before, Scores(0, 0, 0, 600, 2.0 - 0.1 - wander))  # lower on average, by chance
    smooth = 0.3 * (1.0 + 5.0 * np.exp(-np.arange(600) / 50.0))  # better everywhere, by much more at the start
    assert significant_gain(before, Scores(0, 0, 0, 600, 2.0 - smooth - 0.05 * rng.normal(size=600)))
