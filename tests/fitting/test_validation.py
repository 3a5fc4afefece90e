"""magcal.fitting.validation: time splits, held-out scores, and whether an effect's gain is real (simulated truth)."""

import numpy as np
import pytest

from magcal.core.errors import MagcalError
from magcal.data.simulation import chi2017_truth, simulate_timeseries
from magcal.fitting import validation as val
from magcal.model.terms import EFFECTS, Model

NOISE_NT = 2.0


def _record(hidden=None, n_sensors=1, sensor=None, n=1200, seed=5, magnitude=None):
    """A 120 s record (10 Hz) with, optionally, one hidden effect at its default magnitude."""
    perturbations = []
    if hidden:
        effect = EFFECTS[hidden]()
        perturbations = [effect.perturbation(magnitude or effect.default_magnitude, sensor)]
    return simulate_timeseries(
        chi2017_truth(n_sensors), n_samples=n, noise_nT=NOISE_NT, seed=seed, perturbations=perturbations
    )


@pytest.fixture(scope="module")
def clean():
    return _record()


@pytest.fixture(scope="module")
def hidden_temperature():
    return _record("temperature_bias")


def _runs(mask):
    """Number of contiguous runs of True."""
    m = np.asarray(mask, int)
    return int(m[0]) + int(np.sum(np.diff(m) == 1))


# --- splits ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "scheme, kwargs",
    [
        ("blocks", {}),
        ("blocks", {"n_blocks": 5}),
        ("blocks", {"n_blocks": 3}),
        ("later", {}),
        ("later", {"test_fraction": 0.4}),
    ],
)
@pytest.mark.parametrize("with_time", [True, False])
def test_masks_are_disjoint_and_cover_the_record(clean, scheme, kwargs, with_time):
    ds = clean if with_time else clean.replace(time_s=None)
    train, test = val.holdout_masks(ds, scheme, **kwargs)
    assert train.shape == test.shape == (ds.n_samples,)
    assert not np.any(train & test) and np.all(train | test)
    assert train[0]  # the fit always sees the start of the record
    if scheme == "blocks":
        n_blocks = kwargs.get("n_blocks", val.default_n_blocks(ds))
        assert _runs(train) == (n_blocks + 1) // 2 and _runs(test) == (n_blocks - 1) // 2
        assert train[-1]  # ... and its end: record-only terms are interpolated, never extrapolated
    else:
        fraction = kwargs.get("test_fraction", 0.25)
        assert _runs(train) == _runs(test) == 1 and np.flatnonzero(test)[0] > np.flatnonzero(train)[-1]
        assert test.mean() == pytest.approx(fraction, abs=0.01)


def test_default_blocks_are_long_enough_not_to_leak(clean):
    """Blocks of at least MIN_BLOCK_S: neighbouring samples' correlation stays within a block."""
    train, test = val.holdout_masks(clean, "blocks")
    t = clean.time_s
    edges = np.flatnonzero(np.diff(train.astype(int))) + 1
    lengths = np.diff(t[np.concatenate([[0], edges, [t.size - 1]])])
    assert len(lengths) == val.default_n_blocks(clean) == 11
    assert np.all(lengths >= val.MIN_BLOCK_S - 0.2)


@pytest.mark.parametrize("duration_s, blocks", [(25, 3), (59.9, 5), (90, 9), (119.9, 11), (1000, 11)])
def test_default_block_count_follows_the_duration(duration_s, blocks):
    ds = _record(n=int(duration_s * 10) + 1)
    assert val.default_n_blocks(ds) == blocks


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"scheme": "random"}, "unknown validation scheme 'random'"),
        ({"n_blocks": 4}, "odd"),
        ({"n_blocks": 1}, "at least 3"),
        ({"n_blocks": 2.5}, "odd"),
        ({"scheme": "later", "test_fraction": 1.0}, "between 0 and 1"),
        ({"scheme": "later", "test_fraction": 0}, "between 0 and 1"),
    ],
)
def test_bad_splits_are_refused_clearly(clean, kwargs, message):
    with pytest.raises(MagcalError, match=message):
        val.holdout_masks(clean, **kwargs)


def test_a_record_too_short_for_the_split_is_refused(clean):
    with pytest.raises(MagcalError, match="no held-out samples"):
        val.holdout_masks(clean.subset(np.arange(2)), "blocks", n_blocks=11)  # both samples in end blocks


# --- scores ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("scheme", ["blocks", "later"])
def test_the_right_model_scores_the_noise_in_and_out_of_sample(hidden_temperature, scheme):
    result = val.validate(hidden_temperature, effects=["temperature_bias"], scheme=scheme)
    assert result.n_train + result.n_test == hidden_temperature.n_samples and result.scheme == scheme
    assert result.in_sample_rms_per_sensor_nT.shape == result.held_out_rms_per_sensor_nT.shape == (1,)
    assert result.in_sample_rms_nT == pytest.approx(NOISE_NT, rel=0.1)
    assert result.held_out_rms_nT == pytest.approx(NOISE_NT, rel=0.15)
    assert result.effects == ["temperature_bias"] and result.dropped == []


def test_the_wrong_model_looks_better_in_sample_than_held_out(hidden_temperature):
    result = val.validate(hidden_temperature)  # base terms only: the temperature bias is left in the residuals
    assert result.held_out_rms_nT > 1.5 * NOISE_NT
    assert result.overfit_ratio > 1.1


@pytest.mark.parametrize("scheme", ["blocks", "later"])
def test_a_real_hidden_temperature_bias_holds_on_held_out_data(hidden_temperature, scheme):
    c = val.compare(hidden_temperature, [], "temperature_bias", scheme=scheme)
    assert c.held_out_ratio < 0.7 and c.in_sample_ratio < 0.7
    assert c.holds and c.retained > 0.5
    assert c.with_effect.held_out_rms_nT < c.base.held_out_rms_nT
    assert "holds on held-out" in c.text()


@pytest.mark.parametrize("scheme", ["blocks", "later"])
@pytest.mark.parametrize("added", ["bias_drift", "temperature_bias"])
def test_an_effect_that_is_not_there_gains_nothing_held_out(clean, scheme, added):
    c = val.compare(clean, [], added, scheme=scheme)
    assert c.in_sample_ratio <= 1.0  # more parameters always fit the noise a little
    assert c.held_out_ratio == pytest.approx(1.0, abs=0.01) or c.held_out_ratio > 1.0
    assert not c.holds and "does not hold" in c.text()


def test_the_gain_shows_on_the_sensor_that_has_the_effect():
    magnitude = 2 * EFFECTS["temperature_bias"]().default_magnitude
    ds = _record("temperature_bias", n_sensors=2, sensor=1, magnitude=magnitude)
    c = val.compare(ds, [], "temperature_bias:2")
    base, added = c.base.held_out_rms_per_sensor_nT, c.with_effect.held_out_rms_per_sensor_nT
    assert added[1] < 0.3 * base[1]  # the sensor with the temperature bias: from ~5 sigma to the noise
    assert added[1] / base[1] < 0.5 * added[0] / base[0]  # sensor 1 gains only what the joint fit shared
    assert np.all(added < 1.2 * NOISE_NT) and c.holds


def test_record_only_terms_interpolate_in_blocks_but_are_dropped_later():
    """A hidden bias drift: inside the record (blocks) the drift term is real; on later data it is dropped, as
    magcal apply drops it on another record, and nothing is re-levelled: its own gain does not carry (the drift goes
    on for both models), and the instrument terms fitted with it do not get worse."""
    ds = _record("bias_drift")
    blocks = val.compare(ds, [], "bias_drift", scheme="blocks")
    later = val.compare(ds, [], "bias_drift", scheme="later")
    assert blocks.holds and blocks.held_out_ratio < 0.8 and blocks.with_effect.dropped == []
    assert later.with_effect.dropped == ["bias_drift"]
    assert any("dropped on the later samples" in n for n in later.with_effect.notes)
    assert 0.95 < later.held_out_ratio < 1.01 and later.does_not_rise and not later.improves
    # the score is the calibration's own residuals on the later samples with the drift dropped
    cal, test = later.with_effect.calibration, ds.subset(later.with_effect.test)
    expected = cal.total_field_residuals(test, cal.correct(test, "drop"), "drop")
    assert np.allclose(later.with_effect.held_out_residuals_nT, expected)
    # the drift carries the level on for both: without re-levelling the later RMS is well above the noise
    assert later.base.held_out_rms_nT > 1.5 * later.base.relevelled_rms_nT


def test_validate_takes_a_model_and_leaves_it_unchanged(hidden_temperature):
    model = Model.from_names(["temperature_bias"], 1)
    before = [e.state() for e in model.effects]
    result = val.validate(hidden_temperature, model=model)
    assert result.effects == ["temperature_bias"]
    assert [e.state() for e in model.effects] == before
    assert result.held_out_rms_nT == pytest.approx(NOISE_NT, rel=0.15)


def test_validate_accepts_its_own_masks(clean):
    train = np.zeros(clean.n_samples, bool)
    train[::2] = True
    result = val.validate(clean, masks=(train, ~train))
    assert result.n_train == result.n_test == clean.n_samples // 2
    assert result.held_out_rms_nT == pytest.approx(NOISE_NT, rel=0.15)


def test_compare_needs_an_effect(clean):
    with pytest.raises(MagcalError, match="effect to add"):
        val.compare(clean, [])
