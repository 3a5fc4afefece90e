"""The noise floor honest, record-only terms never carried silently, and the diagnose-add-refit
loop judged on held-out data (simulated truth throughout)."""

import json

import numpy as np
import pytest

import magcal
from magcal.calibration.report import text_report
from magcal.checks.noise import estimate_noise
from magcal.cli import main
from magcal.core.errors import CoverageWarning
from magcal.data import io
from magcal.data.simulation import chi2017_truth, simulate_timeseries
from magcal.diagnosis import diagnose
from magcal.fitting import validation as val
from magcal.fitting.pipeline import calibrate
from magcal.model import perturbations
from magcal.model.terms import EFFECTS

SIGMA = 3.0
N = 1500


#: The catalogue's series with knots every few seconds, judged in-sample only: in-sample they follow any slow
#: change of a record, an effect outside the catalogue included.
SERIES = tuple(n for n, cls in EFFECTS.items() if not getattr(cls, "held_out_blocks", True))


def _record(hidden=None, n=N, seed=5, n_sensors=1, perturbations=()):
    perts = list(perturbations)
    if hidden:
        perts.append(EFFECTS[hidden]().perturbation(EFFECTS[hidden].default_magnitude))
    return simulate_timeseries(chi2017_truth(n_sensors), n_samples=n, noise_nT=SIGMA, seed=seed, perturbations=perts)


# --- item 3: noise -----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("step_nT, stale_share", [(6.0, 0.0), (0.0, 0.25), (6.0, 0.25)])
def test_noise_estimate_survives_quantization_and_stale_repeats(step_nT, stale_share):
    """Readings on a grid of ``step_nT`` and a share of exact repeats of the previous sample (a host polling faster
    than the part converts): the estimate stays within 10 % of sqrt(sigma^2 + q^2/12)."""
    ds = _record(n=4000, seed=8).replace(noise_nT=None)
    y = ds.readings_nT.copy()
    if step_nT:
        y = step_nT * np.round(y / step_nT)
    if stale_share:
        rng = np.random.default_rng(1)
        repeat = np.flatnonzero(rng.random(y.shape[1]) < stale_share)
        repeat = repeat[repeat > 0]
        for i in repeat:  # in order, so runs of repeats hold one reading
            y[:, i] = y[:, i - 1]
    ds = ds.replace(readings_nT=y)
    fit = calibrate(ds).fit
    noise = estimate_noise(ds, fit.residuals_nT, fit.n_params)
    truth = np.sqrt(SIGMA**2 + step_nT**2 / 12.0)
    assert noise.source == "differences"
    assert noise.sigma_nT == pytest.approx(truth, rel=0.10)
    if step_nT:
        assert noise.quantization_floor_nT[0] == pytest.approx(step_nT / np.sqrt(12.0), rel=0.01)


def test_noise_never_goes_below_the_quantization_floor():
    ds = _record(n=2000, seed=9).replace(noise_nT=None)
    y = 60.0 * np.round(ds.readings_nT / 60.0)  # q/sqrt(12) = 17 nT, far above the 3 nT noise
    ds = ds.replace(readings_nT=y)
    noise = estimate_noise(ds, np.random.default_rng(0).normal(0.0, 1.0, (1, ds.n_samples)))
    assert noise.source == "quantization"
    assert noise.sigma_nT == pytest.approx(60.0 / np.sqrt(12.0), rel=0.01)


def test_still_stretches_measure_the_noise_and_are_reported():
    """A record that starts with a still stretch: the noise comes from it (free of the model's misfit)."""
    ds = _record(n=3000, seed=10).replace(noise_nT=None)
    y = ds.readings_nT.copy()
    rng = np.random.default_rng(2)
    y[:, :600] = y[:, :1] + rng.normal(0.0, SIGMA, (1, 600, 3))  # 60 s still at the start
    ds = ds.replace(readings_nT=y)
    misfit = 40.0 * np.sin(ds.time_s / 7.0)[None]  # a misfit that leaks into the residuals' differences
    noise = estimate_noise(ds, misfit + rng.normal(0.0, SIGMA, (1, ds.n_samples)))
    assert noise.source == "static"
    assert noise.sigma_nT == pytest.approx(SIGMA, rel=0.1)
    assert noise.static_scatter_nT[0] == pytest.approx(SIGMA, rel=0.15)
    assert "still stretches" in noise.text()


def test_given_noise_beats_the_file_and_any_estimate():
    ds = _record(seed=11)  # the simulator declares noise_nT = 3 nT
    fit = calibrate(ds).fit
    assert estimate_noise(ds, fit.residuals_nT).source == "given"
    assert estimate_noise(ds, fit.residuals_nT).sigma_nT == SIGMA
    given = estimate_noise(ds, fit.residuals_nT, noise_nT=7.0)
    assert (given.source, given.sigma_nT, given.note) == ("given", 7.0, "given by the user")
    with pytest.raises(magcal.MagcalError, match="positive"):
        estimate_noise(ds, fit.residuals_nT, noise_nT=-1.0)


def test_floors_use_the_given_noise():
    ds = _record(seed=12).replace(noise_nT=None)
    estimated = calibrate(ds)
    given = calibrate(ds, noise_nT=10.0)
    assert estimated.noise_source == "differences" and estimated.noise_nT == pytest.approx(SIGMA, rel=0.1)
    assert given.noise_source == "given" and given.noise_nT == 10.0
    assert given.total_field_floor_nT == pytest.approx(10.0 * estimated.total_field_floor_nT / estimated.noise_nT)
    assert "(given)" in text_report(given)
    d = diagnose(ds, given, noise_nT=10.0)
    assert d.noise.source == "given" and d.noise_nT == 10.0
    assert any("differs from the noise seen" in w for w in d.warnings)  # 10 nT is not what the data show


@pytest.fixture
def noisy_file(tmp_path):
    path = tmp_path / "rec.csv"
    io.write_csv(path, _record(seed=13).replace(noise_nT=None))
    return path


def test_cli_noise_option_and_file_line(tmp_path, noisy_file, capsys):
    assert main(["calibrate", str(noisy_file), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["noise_source"] == "differences" and doc["noise"]["source"] == "differences"
    assert main(["calibrate", str(noisy_file), "--json", "--noise", "8"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert (doc["noise_source"], doc["noise_nT"]) == ("given", 8.0)
    declared = tmp_path / "declared.csv"
    declared.write_text("# noise_nT: 4.5\n" + noisy_file.read_text())
    assert main(["calibrate", str(declared), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["noise_nT"] == 4.5
    assert main(["diagnose", str(declared), "--json", "--noise", "6"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert (doc["noise_source"], doc["noise_nT"]) == ("given", 6.0)
    assert main(["calibrate", str(declared)]) == 0
    assert "4.5 nT per axis (given)" in capsys.readouterr().out
    assert main(["calibrate", str(noisy_file), "--noise", "-3"]) != 0
    assert "--noise must be a positive" in capsys.readouterr().err


# --- item 5: held-out judgement in diagnose ------------------------------------------------------------------------
def test_an_in_sample_gain_that_does_not_hold_is_not_recommended():
    """A slow interference (15 nT at 0.02 Hz) that a temperature bias fits in-sample but not on held-out blocks."""
    ds = _record(seed=4, perturbations=[perturbations.periodic_interference(15.0, 0.02)])
    # the interference is outside the catalogue; so are the series with knots every few seconds (field_change,
    # offset_wander), which follow any slow change of the record in-sample
    outside = [n for n in EFFECTS if n not in ("periodic_interference", *SERIES)]
    unjudged = diagnose(ds, validate=False, candidates=outside)
    assert "temperature_bias" in unjudged.explained_by + unjudged.partially_explained_by  # the old advice
    d = diagnose(ds, candidates=outside)
    assert "temperature_bias" not in d.explained_by + d.partially_explained_by
    assert d.verdict != "missing_effect"
    c = next(c for c in d.candidates if c.effect == "temperature_bias")
    assert c.refitted and c.delta_bic < -10 and c.rms_after_nT < d.rms_nT  # in-sample it looks good
    assert c.holds is False and c.held_out_after_nT > c.held_out_before_nT
    assert "does not hold on held-out data" in c.evidence
    assert any(w.startswith("temperature_bias: in-sample") and "does not hold" in w for w in d.warnings)
    assert d.candidates.index(c) > max((d.candidates.index(o) for o in d.candidates if o.holds), default=-1)


@pytest.mark.parametrize(
    "hidden", ["temperature_bias", "nonlinearity_quadratic", "bias_drift", "bias_step", "reference_drift"]
)
def test_a_hidden_effect_is_found_with_a_held_out_gain(hidden):
    """Instrument terms are advised (explained_by) when they improve the later stretch, scored as magcal apply
    scores it; record-only terms (interpolated in blocks) are named as what the record holds (record_holds) and
    advised only if, fitted with the base terms, they improve the calibration kept for new data."""
    d = diagnose(_record(hidden, seed=6))
    c = d.candidates[0]
    assert d.verdict == "missing_effect" and c.effect == hidden and c.holds is True, d.summary
    assert c.held_out_after_nT <= (1 - val.MIN_RELATIVE_GAIN) * c.held_out_before_nT
    tolerance = val.rise_tolerance_nT(c.later_before_nT, 375)
    if c.record_only:  # dropped on later data: it must leave a measurably better calibration
        falls = c.later_after_nT < c.later_before_nT - tolerance
        assert c.transfers is (falls and c.later_after_nT <= (1 - val.MIN_RELATIVE_GAIN) * c.later_before_nT)
    else:  # kept: it must not make later data worse
        assert c.transfers is (c.later_after_nT <= c.later_before_nT + tolerance)
    if EFFECTS[hidden].transferable:
        assert c.transfers and d.explained_by == [hidden] and d.record_holds == [], d.summary
    else:
        assert c.record_only and d.record_holds == [hidden], d.summary
        assert d.explained_by == ([hidden] if c.transfers else [])
        assert f"this record holds {hidden}" in d.summary and "When recording:" in d.summary
        detail = d.to_dict()["record_details"][0]
        assert detail["label"] == hidden and detail["record_only"] and detail["when_recording"]
        assert detail["kept_for_new_data"] == EFFECTS[hidden].kept_for_new_data
    assert d.validation["validated"] and d.validation["held_out_rms_after_nT"] == c.held_out_after_nT
    assert "held-out samples" in d.summary
    doc = d.to_dict()
    assert doc["candidates"][0]["holds"] is True and doc["validation"]["validated"] is True
    assert doc["candidates"][0]["transfers"] is c.transfers
    assert {"held_out_rms_before_nT", "held_out_rms_after_nT", "later_rms_before_nT", "later_rms_after_nT"} <= set(
        doc["candidates"][0]
    )
    assert "held-out" in d.text() and "later" in d.text()


def test_record_only_terms_are_dropped_on_later_data_as_apply_drops_them():
    """The later score of a real bias drift is what magcal apply leaves: the drift dropped, nothing re-levelled."""
    ds = _record("bias_drift", seed=7)
    cmp = val.compare(ds, added_effect="bias_drift", scheme="later")
    assert cmp.with_effect.dropped == ["bias_drift"]
    assert cmp.does_not_rise
    assert "as magcal apply drops them" in cmp.with_effect.notes[0]


def test_a_bias_step_keeps_the_bias_after_the_step_for_new_data():
    """A calibration fitted with a bias step, applied to new data (the step dropped), keeps the bias after it."""
    ds = _record("bias_step", seed=7)
    result = calibrate(ds, effects=["bias_step"])
    cal = result.calibration
    (label,) = [k for k in cal.effect_values if k.startswith("bias_step")]
    step = cal.effect_values[label]
    kept = cal.sensors_for_new_data()[0].bias_nT
    assert np.allclose(kept, cal.sensors[0].bias_nT + step)
    later = ds.subset(ds.time_s > cal.model.effects[0].step_time_s[0])
    applied = cal.correct(later, record_terms="drop")
    assert np.allclose(applied, cal.correct(later, record_terms="apply"), atol=1e-6)  # after the step: unchanged
    doc = cal.to_dict()
    entry = next(e for e in doc["effect_params"] if e["effect"] == "bias_step")
    assert entry["kept_for_new_data"].startswith("the bias after the step")


def test_a_record_too_short_to_split_is_judged_in_sample_with_a_note():
    ds = _record("temperature_bias", n=120, seed=3)
    assert val.split_problem(ds) is not None
    d = diagnose(ds)
    assert not d.validation["validated"] and d.validation["skipped"]
    assert any("held-out validation skipped" in w for w in d.warnings)
    assert all(c.holds is None for c in d.candidates)


@pytest.mark.parametrize("hidden", [None, "bias_drift"])
def test_nothing_is_recommended_when_the_base_calibration_is_not_determined(hidden):
    """A record that turns the sensor through a cap of directions only (the field within ~35 deg of the sensor's x
    axis) and gives no reference field: the fit extrapolates and its field magnitude trades off with the gains,
    so a candidate's gain says nothing about the instrument. The diagnosis recommends nothing and says why."""
    truth = chi2017_truth(1)
    ds = simulate_timeseries(
        truth,
        n_samples=12_000,
        noise_nT=SIGMA,
        seed=4,
        perturbations=[EFFECTS[hidden]().perturbation(EFFECTS[hidden].default_magnitude)] if hidden else [],
    )
    y = ds.readings_nT[0] - truth.sensors[0].bias_nT
    cap = (y / np.linalg.norm(y, axis=1, keepdims=True))[:, 0] > 0.82
    ds = ds.subset(cap).replace(reference_total_nT=None)
    assert 300 < ds.n_samples < 6000
    with pytest.warns(CoverageWarning, match="weak coverage"):  # said at the fit too: a note magcal.diagnose raises
        d = magcal.diagnose(ds)
    assert any(n.is_a(CoverageWarning) and "weak coverage" in n.text for n in d.notes)
    assert d.explained_by == [] and d.verdict != "missing_effect"
    assert any("not determined by these data" in w and "weak coverage" in w for w in d.warnings)


def test_no_validate(tmp_path, capsys):
    path = tmp_path / "hidden.csv"
    io.write_csv(path, _record("temperature_bias", seed=6))
    assert main(["diagnose", str(path), "--json", "--no-validate"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["validation"]["validated"] is False and doc["candidates"][0]["holds"] is None
    assert main(["diagnose", str(path)]) == 0
    out = capsys.readouterr().out
    assert "held-out validation: blocks" in out and " yes " in out


# --- items 2 and 4: calibrate --effects, transferable terms -------------------------------------------------------
def test_calibrate_reports_held_out_rms_and_the_scope_of_each_effect(tmp_path, capsys):
    path = tmp_path / "drift.csv"
    io.write_csv(path, _record("bias_drift", seed=6))
    assert main(["calibrate", str(path), "--effects", "bias_drift,temperature_bias", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    v = doc["validation"]
    assert v["scheme"] == "blocks" and v["holds"] is True
    assert v["with_effects"]["held_out_rms_nT"] < v["base"]["held_out_rms_nT"]
    assert v["in_sample_rms_with_effects_nT"] < v["in_sample_rms_base_nT"]
    scope = {e["effect"]: e["transferable"] for e in doc["effect_params"]}
    assert scope == {"bias_drift": False, "temperature_bias": True}
    assert main(["calibrate", str(path), "--effects", "bias_drift,temperature_bias"]) == 0
    out = capsys.readouterr().out
    assert "Held-out validation" in out and "record-only term" in out and "instrument term" in out
    result = magcal.calibrate(_record("bias_drift", seed=6), effects=["bias_drift"], validate=True)
    assert result.validation.holds is True


def test_a_calibration_saved_by_the_cli_never_carries_a_record_only_term_silently(tmp_path, capsys):
    """Before: ``calibrate -o`` saved ``"record": null`` and ``apply`` put the drift into another record."""
    first, other = tmp_path / "first.csv", tmp_path / "other.csv"
    io.write_csv(first, _record("bias_drift", seed=1))
    io.write_csv(other, _record("bias_drift", seed=2))
    cal = tmp_path / "cal.json"
    assert main(["calibrate", str(first), "--effects", "bias_drift", "-o", str(cal)]) == 0
    assert json.loads(cal.read_text())["record"] is not None
    capsys.readouterr()
    assert main(["apply", str(cal), str(other), "-o", str(tmp_path / "out.csv")]) == 0
    assert "dropped the record-only term(s) bias_drift" in capsys.readouterr().err
    assert main(["apply", str(cal), str(first), "-o", str(tmp_path / "same.csv")]) == 0
    assert "record-only" not in capsys.readouterr().err  # its own record: applied silently


# --- messages that match the data -------------------------------------------------------------------------
def test_a_field_outside_the_earths_range_with_good_coverage_is_a_units_question():
    """Readings scaled by 2 (a logger's LSB off by two): the fitted field is twice the Earth's; the directions cover
    the sphere, so the diagnosis asks about the units and still finds the hidden temperature bias."""
    ds = _record("temperature_bias", seed=6)
    ds = ds.replace(readings_nT=2.0 * ds.readings_nT, reference_total_nT=None, noise_nT=None)
    d = diagnose(ds)
    field = d.result.calibration.reference_total_nT
    assert field > 70_000
    note = next(w for w in d.warnings if "units or the LSB" in w)
    assert f"x0.5 gives {0.5 * field / 1000:.3g} uT" in note and "--units or --lsb" in note
    assert "not determined" not in d.summary and "x0.5 gives" in d.summary
    assert d.explained_by == ["temperature_bias"] and d.verdict == "missing_effect"


def test_a_diverged_refit_reads_did_not_converge(monkeypatch):
    """A candidate refit that stopped far from its minimum (here: its residuals blown up by 1e7, as a refit on
    directions that fill a cone can) is shown as "did not converge", not with an RMS of 1e8 nT, and not advised."""
    import dataclasses

    import magcal.diagnosis.scores as scores

    real_refit = scores._refit

    def diverging(dataset, fit, candidate, pool=None):
        f1 = real_refit(dataset, fit, candidate, pool)
        if candidate.effect != "temperature_bias":
            return f1
        return dataclasses.replace(f1, residuals_nT=f1.residuals_nT * 1e7, rms_nT=f1.rms_nT * 1e7, rss=f1.rss * 1e14)

    monkeypatch.setattr(scores, "_refit", diverging)
    d = diagnose(_record("temperature_bias", seed=6), validate=False)
    c = next(c for c in d.candidates if c.effect == "temperature_bias")
    assert c.refitted and not c.converged and not c.recommendable
    assert "temperature_bias" not in d.explained_by + d.partially_explained_by
    row = next(line for line in d.text().splitlines() if "temperature_bias" in line and "did not converge" in line)
    assert "e+" not in row.split("did not converge")[0]
    assert d.to_dict()["candidates"][d.candidates.index(c)]["converged"] is False


@pytest.mark.parametrize("cycles, trend", [(1.0, True), (1.8, True), (12.0, False)])
def test_two_cycles_per_record_or_fewer_is_a_trend_not_a_period(cycles, trend):
    """A sinusoidal change of the field of one or two cycles over the record is called a trend; twelve cycles are
    a period."""
    change = perturbations.catalogue_perturbation(EFFECTS["reference_drift"](), 20.0, period_fraction=1.0 / cycles)
    ds = _record(seed=3, perturbations=[change])
    d = diagnose(ds, candidates=["nonlinearity_cubic"], validate=False)
    texts = [s.text for s in d.structure]
    assert any(s.kind == "periodic" for s in d.structure) is not trend, texts
    assert any("slow trend over the record" in t for t in texts) is trend, texts


def test_a_bias_step_is_found_where_the_readings_jump_not_inside_a_still_head():
    """A record whose first 30 s are still, with a bias step (80 nT, across the field) at the moment the turning
    starts: the total field cannot place the step inside the still head, and the readings do not jump there; the
    step is placed where they do (a placement inside the ramp was 11.9 s, 18 s early)."""
    truth = chi2017_truth(1)
    ds = simulate_timeseries(truth, n_samples=1500, noise_nT=SIGMA, seed=4)
    y = ds.readings_nT.copy()
    head = 300
    y[0, :head] = y[0, head] + np.random.default_rng(0).normal(scale=SIGMA, size=(head, 3))
    u = y[0, head] - truth.sensors[0].bias_nT
    step = np.cross(u / np.linalg.norm(u), [0.0, 0.0, 1.0])
    y[0, head:] += 80.0 * step / np.linalg.norm(step)
    ds = ds.replace(readings_nT=y)
    fitted = calibrate(ds, effects=["bias_step"]).calibration.model.effects[0].step_time_s[0]
    assert abs(fitted - 0.5 * (ds.time_s[head - 1] + ds.time_s[head])) < 0.25


def test_hysteresis_reversals_come_from_the_fitted_field_not_the_noise():
    """A 4 nT loop at 3 nT noise sampled at 100 Hz: the noise no longer turns the play operator back and forth, so
    the term brings the residuals to the floor and is advised (without it: 1.04x the floor, unexplained)."""
    ds = simulate_timeseries(
        chi2017_truth(1),
        n_samples=10_000,
        rate_hz=100.0,
        noise_nT=SIGMA,
        seed=1,
        perturbations=[EFFECTS["hysteresis"]().perturbation(4.0)],
    )
    d = diagnose(ds)
    assert d.verdict == "missing_effect" and d.explained_by == ["hysteresis"], d.summary
    assert d.fits["hysteresis"].rms_nT <= 1.01 * d.floor_nT


def test_smoothed_readings_have_no_floor_to_compare_with():
    """Low-pass filtered readings (a 4th-order Butterworth at a tenth of the Nyquist frequency, run both ways): the
    differences say 0.01 nT, which is not the sensor's noise; the estimate says the floor is unknown and no
    structure is called an excess over a floor. White noise is recognised as white."""
    from scipy.signal import butter, filtfilt

    from magcal.checks.noise import smoothing_ratio

    ds = _record(seed=1, n=3000)
    assert abs(smoothing_ratio(calibrate(ds).fit.residuals_nT[0]) - 1.0) < 0.1
    b, a = butter(4, 0.1)
    smooth = ds.replace(readings_nT=filtfilt(b, a, ds.readings_nT, axis=1), noise_nT=None)
    d = diagnose(smooth, validate=False)
    assert d.noise.source == "residuals" and "smoothed or filtered" in d.noise.note
    assert d.noise.sigma_nT > 0.5 * d.rms_nT  # the residual RMS stands in, not the 0.01 nT of the differences
    assert any("smoothed or filtered" in w for w in d.warnings)
    assert not any(s.kind == "excess" for s in d.structure)


def test_an_unexplained_direction_pattern_says_what_it_means():
    """A degree-4 direction pattern (a cubic nonlinearity) with the nonlinearity terms left out of the candidates:
    unexplained, and the summary names the likely causes and the recording that separates them."""
    ds = _record("nonlinearity_cubic", seed=2)
    others = [n for n in EFFECTS if not n.startswith("nonlinearity") and n not in SERIES]  # nothing to stand in
    d = diagnose(ds, candidates=others, validate=False)
    assert d.verdict == "unexplained", d.summary
    assert "direction" in {s.kind for s in d.structure}
    assert "non-uniform field" in d.summary and "turn it in place" in d.summary
    clean = diagnose(_record("bias_drift", seed=2), candidates=["nonlinearity_cubic"], validate=False)
    assert "non-uniform field" not in clean.summary  # a drift is structure in time, not a direction pattern
