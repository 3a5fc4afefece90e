"""The vector diagnosis advises only what it judged held out, and its words follow its numbers: a record too short
or too slow is "not judged" (and says what would let it judge), an advice may not raise one world component of the
held-out part beyond its noise, "not determined" tells a misfit from the attitudes, another flight is weighed at
its own noise, and diagnose and calibrate report one attitude error."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magcal.checks.reference import resolve_vector_reference
from magcal.cli import main
from magcal.data.dataset import dataset_columns, dataset_metadata
from magcal.data.io import write_csv
from magcal.data.vehicle import simulate_vehicle, vehicle_truth
from magcal.diagnosis.vector import (
    MAX_COMPONENT_RISE,
    MIN_JUDGED_SAMPLES,
    Flight,
    _part_verdict,
    _scores,
    diagnose_vector,
    raised_components,
)
from magcal.fitting.labfield import POSITION_NED_COLUMNS
from magcal.fitting.vector import fit_vector
from magcal.model.perturbations import parse_hidden

FIELD_NED = np.array([21_000.0, 1_200.0, 44_000.0])


def _diagnose(ds, **options):
    return diagnose_vector(ds, resolve_vector_reference(ds), **options)


# ---- judged, or no advice ------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "n, rate_hz, validate, px4, needs",
    [
        (70, 1.0, True, True, ["SDLOG_PROFILE", "1 Hz", "more"]),  # a PX4 compass logged at 1 Hz in a 70-s flight
        (70, 1.0, True, False, ["log the compass at 10 Hz", "minutes more"]),
        (150, 10.0, True, False, [f"needs {MIN_JUDGED_SAMPLES}", "minutes more at this record's 10 Hz"]),  # short
        (3000, 10.0, False, False, ["drop --no-validate"]),  # the judgement turned off
    ],
    ids=["px4-1Hz", "1Hz", "short", "no-validate"],
)
def test_a_record_that_cannot_be_judged_gets_no_advice_and_says_what_would_judge_it(n, rate_hz, validate, px4, needs):
    """A current field hidden in the record (25 nT/A): supported in-sample, but with no held-out part nothing is
    advised, the verdict is "not judged" and its text says what is needed; the same vehicle's long record at 10 Hz
    is judged and advised (the test can fail)."""
    truth = vehicle_truth(seed=3)
    hidden = [parse_hidden("current_field=25", 1)]
    ds, _ = simulate_vehicle(truth, seed=1, n=n, rate_hz=rate_hz, perturbations=hidden, log_current=True)
    if px4:
        ds = ds.replace(metadata={"log_format": "PX4 ULog", "log_magnetometers": "sensor_mag 0"})
    d = _diagnose(ds, validate=validate, max_effects=1)
    assert d.verdict == "not_judged" and d.explained_by == [] and d.final is None
    assert not [c for c in d.candidates if c.recommended]
    assert all("not judged" in c.why for c in d.candidates if c.supported)
    for words in needs:
        assert words in d.summary, (words, d.summary)
    assert "not judged" in d.text()
    if n == 150:  # the same vehicle, long enough: judged and advised
        long_ds, _ = simulate_vehicle(truth, seed=1, n=1500, perturbations=hidden, log_current=True)
        judged = _diagnose(long_ds, max_effects=1)
        assert judged.verdict == "missing_effect" and judged.explained_by == ["current_field"]


# ---- no component raised beyond its noise ----------------------------------------------------------------------


def _scored(residual_ned, total, sigma_f=3.0, sigma_p=30.0):
    """Scores of given residuals (one sensor; north, east, down and |B|, nT) on a record whose field points down (a
    high latitude's: north and east are across it)."""
    n = len(total)
    record = SimpleNamespace(
        reference=SimpleNamespace(ned_nT=np.tile([0, 0, 50_000.0], (n, 1))), usable=np.ones(n, bool)
    )
    return _scores(record, residual_ned[None], total[None], np.ones(n, bool), np.array([sigma_f]), np.array([sigma_p]))


@pytest.mark.parametrize(
    "down_after, fresh_noise, raised_down",
    [
        (1.0, True, False),  # the same level, another draw of the noise: a rise by chance is no rise
        (1.01, False, False),  # 1 %: under the least rise counted (MIN_COMPONENT_RISE)
        (1.06, False, True),  # 6 % on every stretch: beyond its noise
        (1.25, True, True),  # beyond MAX_COMPONENT_RISE, whatever the noise
        (1.4, False, True),
        (2.0, True, True),
    ],
)
def test_a_candidate_that_lowers_the_total_but_raises_one_component_is_not_advised(
    down_after, fresh_noise, raised_down
):
    """North and east fall from 100 to 20 nT, the total and the weighed residual with them; the down component is
    scaled by ``down_after`` (with a fresh draw of its noise or the same): a rise beyond its noise is refused, by
    name, a rise within it is not."""
    rng = np.random.default_rng(0)
    n = 900
    white = rng.normal(0.0, 1.0, (n, 3))
    before = _scored(100.0 * white, rng.normal(0.0, 3.0, n))
    down = rng.normal(0.0, 1.0, n) if fresh_noise else white[:, 2]
    after_res = np.column_stack([20.0 * white[:, 0], 20.0 * white[:, 1], 100.0 * down_after * down])
    after = _scored(after_res, before.per_component[:, 3] ** 0.5)
    assert after.weighted < 0.9 * before.weighted  # the weighed residual falls
    raised = raised_components(before, after)
    verdict = _part_verdict("the later part", before, after)
    if raised_down:
        assert [label for label, _, _ in raised] == ["down"]
        assert verdict.startswith("raises on the later part the down residual")
    else:
        assert raised == [] and verdict == ""
    if down_after - 1.0 > MAX_COMPONENT_RISE:
        assert raised_down


@settings(max_examples=40, deadline=None)
@given(
    scales=st.lists(st.floats(0.05, 3.0), min_size=4, max_size=4),
    sigma=st.floats(1.0, 300.0),
    seed=st.integers(0, 2**16),
)
def test_no_component_rises_past_the_bound_unnoticed(scales, sigma, seed):
    """Whatever the noise: a component whose RMS rises by more than MAX_COMPONENT_RISE is always named."""
    rng = np.random.default_rng(seed)
    n = 200
    white = rng.normal(0.0, 1.0, (n, 4))
    before = _scored(100.0 * white[:, :3], 3.0 * white[:, 3], sigma_f=sigma, sigma_p=sigma)
    after = _scored(100.0 * white[:, :3] * scales[:3], 3.0 * white[:, 3] * scales[3], sigma_f=sigma, sigma_p=sigma)
    named = {label for label, _, _ in raised_components(before, after)}
    for label, b, a in zip(before.component_labels(), before.components_nT.ravel(), after.components_nT.ravel()):
        if a > (1.0 + MAX_COMPONENT_RISE) * b:
            assert label in named


@pytest.mark.parametrize("world_after", [129.0, 140.0])
def test_the_words_follow_the_numbers(world_after):
    """A candidate that lowers a flight's world RMS a little (130 -> 129 nT, |B| unchanged: under the 1 % of the
    weighed residual) is refused in words that say it lowers the world components; one that raises them is said
    to raise them, never 'does not improve' where it does."""
    rng = np.random.default_rng(1)
    n = 900
    white = rng.normal(0.0, 1.0, (n, 3))
    noise_f = rng.normal(0.0, 3.0, n)
    before = _scored(130.0 * white, noise_f, sigma_p=130.0)
    after = _scored(world_after * white, noise_f, sigma_p=130.0)
    verdict = _part_verdict("line 20", before, after)
    if world_after < 130.0:
        assert verdict.startswith("lowers line 20's world components but not its residual weighed at its noise")
        assert f"world {before.world_nT:.4g} -> {after.world_nT:.4g} nT" in verdict
    else:
        assert verdict.startswith("raises on line 20 the north residual")


# ---- not determined: the misfit, not the attitudes -------------------------------------------------------------


def _path(t):
    w = 2 * np.pi * t / 50.0
    return np.column_stack([0.8 * np.cos(w), 0.8 * np.sin(w), 0.1 * np.sin(3 * w)])


def _magnet_near_the_path(readings, context, rng):
    """A magnet (12 A m^2, vertical) standing 0.3 m from the closest point of the carried sensor's loop."""
    r = _path(context["time_s"]) - np.array([1.1, 0.0, 0.0])
    d = np.linalg.norm(r, axis=1, keepdims=True)
    u = r / d
    m = np.array([0.0, 0.0, 12.0])
    b_ned = 100.0 * (3.0 * (u @ m)[:, None] * u - m) / d**3  # mu0 / 4 pi = 100 nT m^3 / (A m^2)
    return readings + context["attitudes"].inv().apply(b_ned)[None]


@pytest.mark.parametrize("positions", [True, False])
def test_a_tumbled_record_past_a_magnet_is_not_determined_for_the_misfit_not_the_attitudes(positions):
    truth = vehicle_truth(seed=4, mounting=np.eye(3))
    ds, _ = simulate_vehicle(
        truth, seed=4, n=1500, turns=6, roll_max_deg=170, pitch_max_deg=80, perturbations=[_magnet_near_the_path]
    )
    if positions:
        p = _path(ds.time_s)
        ds = ds.replace(extra={**ds.extra, **dict(zip(POSITION_NED_COLUMNS, p.T))})
    fit = fit_vector(ds, resolve_vector_reference(ds), warn=False)
    cause = fit.sensors[0].undetermined_cause
    assert not fit.sensors[0].determined and cause is not None
    assert cause.kind == "misfit" and cause.follows == ("position" if positions else "time")
    assert cause.share > 0.5 and cause.lag1 > 0.9 and cause.spread_deg > 20  # tumbled: not the geometry
    note = next(w for w in fit.warnings if "does not determine" in w)
    assert "misfit, not the attitudes" in note and "magnet or steel near the path" in note
    assert "better attitude" not in note and "banked turns" not in note
    d = _diagnose(ds)
    assert d.verdict == "unexplained" and "misfit" in d.summary and "better attitude" not in d.summary


@pytest.mark.parametrize("seed", [0, 1])
def test_a_level_record_with_a_wandering_attitude_blames_the_geometry_and_the_attitude(seed):
    """Little tilt and a wandering attitude error: the fit bends the error into |B| too, so the geometry is named
    first, and the attitude beside a field that changes (which this record cannot tell apart)."""
    truth = vehicle_truth(seed=seed, mounting=np.eye(3))
    for s in truth.sensors:
        s.bias_nT = np.array([47_900.0, -35_600.0, -39_400.0])
    ds, _ = simulate_vehicle(
        truth,
        seed=seed,
        n=500,
        turns=1.0,
        roll_max_deg=8.0,
        pitch_max_deg=6.0,
        attitude_noise_deg=4.0,
        attitude_tau_s=20.0,
    )
    fit = fit_vector(ds, resolve_vector_reference(ds), warn=False)
    cause = fit.sensors[0].undetermined_cause
    assert cause is not None and cause.kind == "geometry" and "banked turns" in cause.text
    assert "better attitude" in cause.text and "cannot tell apart" in cause.text


# ---- other flights at their own noise ---------------------------------------------------------------------------


@pytest.mark.parametrize("moved_nT", [0.0, 400.0])
def test_another_flight_with_a_different_calibration_error_is_not_adequate(moved_nT):
    """Flight two of the same vehicle, its hard iron moved by ``moved_nT`` along x: the base calibration of flight one
    leaves that on flight two, far above flight two's noise: not "adequate", and the summary names the flight."""
    truth = vehicle_truth(seed=3)
    one, _ = simulate_vehicle(truth, seed=1, n=1500)
    two, _ = simulate_vehicle(truth, seed=2, n=1500)
    two = two.replace(readings_nT=two.readings_nT + np.array([moved_nT, 0.0, 0.0]))
    d = _diagnose(one, also=[Flight(two, resolve_vector_reference(two), "two")], max_effects=1)
    base_two = d.validation["flights_base"]["two"]
    if moved_nT:
        assert base_two["world_rms_nT"] > 3 * d.base.world_nT
        assert d.verdict != "adequate" and "does not carry to two" in d.summary
    else:
        assert d.verdict == "adequate" and base_two["weighted_rms"] < 1.25
    assert "on two: world components" in d.text()


# ---- one attitude error -----------------------------------------------------------------------------------------


def test_diagnose_and_calibrate_report_the_same_attitude_error(tmp_path, capsys):
    """A wandering attitude error (0.3 deg, 10 s): its white part is small, the fit's estimate is not; both commands
    report the fit's."""
    ds, _ = simulate_vehicle(vehicle_truth(seed=3), seed=1, n=1200, attitude_noise_deg=0.3, attitude_tau_s=10.0)
    path = tmp_path / "one.csv"
    write_csv(path, dataset_columns(ds), dataset_metadata(ds))
    assert main(["calibrate", str(path), "--json"]) == 0
    calibrated = json.loads(capsys.readouterr().out)
    (sensor,) = calibrated["vector_fit"]["sensors"] if "vector_fit" in calibrated else calibrated["sensors"]
    assert main(["diagnose", str(path), "--json"]) == 0
    diagnosed = json.loads(capsys.readouterr().out)
    assert diagnosed["noise"]["attitude_deg"] == pytest.approx(sensor["attitude_noise_deg"], rel=1e-9)
    assert 0.1 < sensor["attitude_noise_deg"] < 0.6
    assert diagnosed["noise"]["white_attitude_deg"] < 0.5 * sensor["attitude_noise_deg"]
