"""A field that changes within seconds, an offset that wanders, sampling jitter between sensors, and a part of the
record in another field: each hidden in a small simulated record, named (and told from the others) by the
diagnosis, or flagged before the fit and left out in one step."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from magcal.checks.quality import assess, other_field_finding, without_other_field_parts
from magcal.cli import main
from magcal.data import io
from magcal.data.dataset import Dataset
from magcal.data.simulation import chi2017_truth, simulate_timeseries
from magcal.diagnosis import diagnose
from magcal.diagnosis.jitter import jitter_estimates
from magcal.fitting.pipeline import calibrate
from magcal.model.effects import hat_columns, wander_knots
from magcal.model.terms import EFFECTS

SIGMA = 3.0
#: A hand-held tumble (about 90 deg/s): many directions within one knot interval, which is what tells an offset
#: that wanders (a pattern over the direction) from a field that changes (the same for every direction).
TUMBLE = 5.0
#: What the revisits say of each form (:class:`magcal.diagnosis.statistics.RevisitForms`).
REVISIT_WORDS = {
    "field_change": "the change is the same in every direction: a field that changes",
    "offset_wander": "the change follows the direction: an offset that wanders",
}
DRIFTS = {"bias_drift", "bias_step", "reference_drift", "field_change", "offset_wander", "periodic_interference"}


def _hidden(name, n_sensors, magnitude, n=1500, seed=3, sensor=None):
    effect = EFFECTS[name]()
    return simulate_timeseries(
        chi2017_truth(n_sensors),
        n_samples=n,
        noise_nT=SIGMA,
        seed=seed,
        perturbations=[effect.perturbation(magnitude, sensor)],
        turn_rate=TUMBLE,
    )


def _named(diagnosis) -> set:
    """The effect names the diagnosis holds responsible (advice and what the record holds)."""
    labels = diagnosis.explained_by + diagnosis.partially_explained_by + diagnosis.record_holds
    return {label.partition(":")[0] for label in labels}


@pytest.mark.parametrize(
    ("hidden", "n_sensors", "magnitude", "other"),
    [
        ("field_change", 1, 20.0, "offset_wander"),
        ("field_change", 2, 20.0, "offset_wander"),
        ("offset_wander", 1, 30.0, "field_change"),
        ("offset_wander", 2, 30.0, "field_change"),
    ],
)
def test_a_changing_field_and_a_wandering_offset_are_named_and_told_apart(hidden, n_sensors, magnitude, other):
    ds = _hidden(hidden, n_sensors, magnitude)
    d = diagnose(ds, workers=1)
    assert d.candidates[0].effect == hidden
    assert hidden in _named(d) and other not in _named(d)
    best = {c.effect: c for c in d.candidates if c.refitted and c.sensor is None}
    assert best[hidden].delta_bic < best[other].delta_bic - 100 if other in best else True
    assert d.rms_final_nT < 1.1 * SIGMA < d.rms_nT
    assert hidden in d.summary
    # the same-direction revisits, in the evidence of both series, tell the one hidden
    lines = [c.evidence for c in d.candidates if c.effect in ("field_change", "offset_wander")]
    assert lines and all(REVISIT_WORDS[hidden] in line for line in lines), lines
    assert all(REVISIT_WORDS[other] not in line for line in lines)
    wander = [c.evidence for c in d.candidates if c.effect == "offset_wander"]
    assert all("its fitted size is not determined" in line for line in wander)


@pytest.mark.parametrize("tau_ms", [1.0, 3.0])
def test_sampling_jitter_between_sensors_is_estimated_in_ms(tau_ms):
    ds = _hidden("sensor_jitter", 2, tau_ms, n=800, seed=2, sensor=1)
    d = diagnose(ds, workers=1, max_effects=1)
    (est,) = d.variance_terms
    assert est["label"] == "sensor_jitter:2" and est["significant"]
    assert est["jitter_rms_ms"] == pytest.approx(tau_ms, rel=0.15)
    assert est["rms_by_rate_quartile_nT"][3] > 1.5 * est["rms_by_rate_quartile_nT"][0]
    assert "sensor_jitter:2" in d.summary
    assert not {"field_change", "offset_wander"} & _named(d)
    assert json.loads(json.dumps(d.to_dict()))["variance_terms"][0]["sensor"] == 2


@pytest.mark.parametrize("hidden", [None, "field_change", "offset_wander"])
def test_no_jitter_is_named_without_one(hidden):
    ds = simulate_timeseries(
        chi2017_truth(2),
        n_samples=800,
        noise_nT=SIGMA,
        seed=4,
        perturbations=[EFFECTS[hidden]().perturbation(20.0)] if hidden else [],
        turn_rate=TUMBLE,
    )
    fit = calibrate(ds, effects=[hidden] if hidden else []).fit
    (est,) = jitter_estimates(ds.masked(fit.mask), fit)
    assert not est["significant"] and est["jitter_rms_ms"] < 0.3


def test_the_series_terms_carry_their_knots_through_a_saved_calibration(tmp_path):
    ds = _hidden("offset_wander", 1, 30.0, n=600)
    result = calibrate(ds, effects=["offset_wander", "field_change"])
    path = tmp_path / "cal.json"
    result.calibration.save(path)
    loaded = type(result.calibration).load(path)
    before = result.calibration.correct(ds)
    after = loaded.correct(ds)
    np.testing.assert_allclose(after, before, atol=1e-6)
    wander = next(e for e in loaded.model.effects if e.name == "offset_wander")
    assert len(wander.param_names()) == 3 * (len(wander.knots_s) - 1)


def test_hat_columns_sum_to_one_and_interpolate_linearly():
    t = np.linspace(0.0, 20.0, 201)
    knots = wander_knots(t, spacing_s=3.0, max_knots=60)
    assert knots[0] == 0.0 and knots[-1] == pytest.approx(20.0) and np.all(np.diff(knots) <= 3.0 + 1e-9)
    h = hat_columns(t, knots)
    np.testing.assert_allclose(h.sum(axis=1), 1.0)
    values = np.sin(knots)
    np.testing.assert_allclose(h @ values, np.interp(t, knots, values), atol=1e-12)


# -- a part of the record in another field -------------------------------------------------------------------------


def _join(parts) -> Dataset:
    """One record of consecutive simulated pieces (readings, time and temperature)."""
    readings = np.concatenate([p.readings_nT for p in parts], axis=1)
    n = readings.shape[1]
    return Dataset(readings, time_s=np.arange(n) / 10.0, source="joined record")


def _with_part(kind):
    truth = chi2017_truth(1)
    main_run = simulate_timeseries(truth, n_samples=1200, noise_nT=SIGMA, seed=4, with_reference=False)
    if kind == "another_run_first":  # 24 rows of another run, in a field 2.2 uT stronger
        other = dataclasses.replace(truth, total_nT=truth.total_nT + 2200.0)
        first = simulate_timeseries(other, n_samples=24, noise_nT=SIGMA, seed=9, with_reference=False)
        return _join([first, main_run]), (0, 24)
    # the last 20 s still, in a field 5 uT weaker
    other = dataclasses.replace(truth, total_nT=truth.total_nT - 5000.0)
    still = simulate_timeseries(other, n_samples=200, noise_nT=SIGMA, seed=5, with_reference=False)
    rng = np.random.default_rng(1)
    held = still.readings_nT[:, :1] + rng.normal(0.0, SIGMA, size=(1, 200, 3))
    return _join([main_run, Dataset(held, time_s=np.arange(200) / 10.0)]), (1200, 1400)


@pytest.mark.parametrize("kind", ["another_run_first", "still_at_the_end"])
def test_a_part_in_another_field_is_flagged_left_out_in_one_step_and_no_drift_is_found_after(kind):
    ds, (start, stop) = _with_part(kind)
    finding = other_field_finding(ds)
    assert finding is not None and finding.severity == "warning"
    (part,) = finding.values["parts"]
    assert abs(part["start"] - start) <= 2 and abs(part["stop"] - stop) <= 2
    assert f"rows {part['start'] + 1}-{part['stop']}" in finding.summary
    assert assess(ds).find("other_field")
    clean, _ = without_other_field_parts(ds, finding)
    assert clean.n_samples == ds.n_samples - (part["stop"] - part["start"])
    assert other_field_finding(clean) is None
    d = diagnose(clean, workers=1)
    assert not DRIFTS & _named(d)


def test_a_record_in_one_field_has_no_part_flagged():
    ds = simulate_timeseries(chi2017_truth(2), n_samples=1200, noise_nT=SIGMA, seed=6)
    assert other_field_finding(ds) is None


def test_exclude_part_on_the_command_line(tmp_path, capsys):
    ds, (start, stop) = _with_part("still_at_the_end")
    path = tmp_path / "record.csv"
    io.write_csv(path, ds)
    assert main(["calibrate", str(path), "--json"]) == 0
    with_part = json.loads(capsys.readouterr().out)
    assert main(["calibrate", str(path), "--json", "--exclude-part"]) == 0
    without = json.loads(capsys.readouterr().out)
    assert any("another field" in w for w in json.dumps(with_part["warnings"]).split("\\n"))
    assert any("--exclude-part: left out rows" in w for w in without["warnings"])
    assert without["rms_nT"] < 0.2 * with_part["rms_nT"]
