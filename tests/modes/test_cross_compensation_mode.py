"""The cross compensation fit mode: ``auto`` takes it for a four-sensor compensation flight, never for a cross
turned for its calibration; its fit, validation and diagnosis through the mode object."""

from __future__ import annotations

import numpy as np
import pytest

import magcal
from magcal.data.cross_flight import simulate_cross_flight
from magcal.modes import CROSS_COMPENSATION, TOTAL_FIELD, VECTOR, choose_mode, mode_choice


@pytest.fixture(scope="module")
def flight():
    return simulate_cross_flight(3, platform="drone_current")


def _flat(ds):
    """The record with its attitude held level and heading north: no maneuvers."""
    return ds.replace(attitude_wxyz=np.tile([1.0, 0.0, 0.0, 0.0], (ds.n_samples, 1)))


@pytest.mark.parametrize(
    ("record", "expected"),
    [
        (lambda f: f.dataset(), CROSS_COMPENSATION),  # a box's maneuvers in the attitude
        (lambda f: _flat(f.dataset()), TOTAL_FIELD),  # four sensors, times and a baseline, but no maneuvers
        (lambda f: f.dataset().replace(attitude_wxyz=None), TOTAL_FIELD),  # no attitude
        (lambda f: f.dataset().replace(baseline_m=None), TOTAL_FIELD),  # no baseline: no tensor
        (lambda f: magcal.simulate("chi2017", seed=1), TOTAL_FIELD),  # the seed's cross turned in a uniform field
        (lambda f: _timed(magcal.simulate("chi2017", seed=1)), TOTAL_FIELD),  # ... even with times
    ],
)
def test_auto_takes_it_only_for_a_compensation_flight(flight, record, expected):
    assert choose_mode(record(flight)) is expected


def _timed(ds):
    return ds.replace(time_s=np.arange(ds.n_samples) / 10.0)


def test_auto_takes_it_over_the_vector_fit(flight):
    """A box with the field vector could have the vector fit; its maneuvers make it a compensation flight."""
    ds = flight.dataset()
    reference = np.tile(flight.truth.field_ned_nT, (ds.n_samples, 1))
    assert VECTOR.applicable(ds, reference=_Reference(reference)) is None
    chosen, _ = mode_choice(ds, reference=_Reference(reference))
    assert chosen is CROSS_COMPENSATION


class _Reference:
    """A field vector per sample as the vector fit takes it."""

    def __init__(self, ned):
        self.ned_nT, self.text, self.kind = ned, "given", "given"


@pytest.mark.parametrize("sensors", [1, 2])
def test_named_on_a_record_it_cannot_fit_says_what_it_needs(sensors):
    ds = magcal.simulate("chi2017", seed=1)
    with pytest.raises(magcal.MagcalError, match="needs four sensors"):
        choose_mode(ds.replace(readings_nT=ds.readings_nT[:sensors]), "cross_compensation")


@pytest.mark.parametrize("effects", [(), ("current",)])
def test_fit_validate_and_diagnose_through_the_mode(flight, effects):
    ds = flight.dataset()
    ds.extra["current_A"] = flight.current_A
    result = CROSS_COMPENSATION.fit(ds, reference=flight.truth.field_ned_nT, effects=effects)
    assert result.mode == "cross_compensation" and result.fom is not None
    assert result.calibration.current == bool(effects)
    validation = CROSS_COMPENSATION.validate(ds, result, reference=flight.truth.field_ned_nT, effects=effects)
    if effects:
        assert validation.fom_effects < validation.fom_tl / 5
    else:
        assert validation is None
    diagnosis = CROSS_COMPENSATION.diagnose(ds, result, reference=flight.truth.field_ned_nT)
    assert diagnosis.explained_by == ([] if effects else ["current"])
    assert diagnosis.verdict == ("adequate" if effects else "missing_effect")


def test_the_fit_takes_only_the_samples_the_mask_keeps(flight):
    """A mask leaving the first heading out of the fit changes the fit, not the maneuvers judged; a mask of another
    length is refused in one line."""
    ds = flight.dataset()
    whole = CROSS_COMPENSATION.fit(ds)
    kept = np.ones(ds.n_samples, bool)
    kept[: ds.n_samples // 4] = False
    part = CROSS_COMPENSATION.fit(ds, mask=kept)
    assert len(part.fom.after.maneuvers) == len(whole.fom.after.maneuvers) == 12
    assert part.fom.after.fom_nT_per_m != pytest.approx(whole.fom.after.fom_nT_per_m, rel=1e-6)
    with pytest.raises(magcal.MagcalError, match="the mask has shape"):
        CROSS_COMPENSATION.fit(ds, mask=kept[:-1])
