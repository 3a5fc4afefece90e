"""The cross's compensation with several current columns: a platform whose two wires (of four recorded currents)
carry a field at the cross; the diagnosis names each carrying column as its own candidate, and the model it advises,
fitted on one flight, compensates a second flight's tensor within 1.2x of the true compensation; a line's currents
are looked up by name; ``--current a,b`` names them on the command line."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from magcal.core.errors import MagcalError
from magcal.data.cross_flight import CROSS_PLATFORMS, simulate_cross_flight
from magcal.diagnosis.cross_compensation import (
    cross_compensation_result,
    cross_record,
    diagnose_cross_compensation,
)
from magcal.diagnosis.cross_fom import tensor_fom
from magcal.fitting.cross_compensation import CrossCompensation

#: Two wires that carry a field at the cross, two recorded currents that carry none there.
HIDDEN = {"cur_strb": np.array([0.003, 0.001, -0.002]), "cur_com_1": np.array([-0.001, 0.0025, 0.002])}
PLATFORM = replace(
    CROSS_PLATFORMS["drone"],
    currents_Am2_per_A={"cur_outpwr": np.zeros(3), **HIDDEN, "cur_ac_lo": np.zeros(3)},
)


@pytest.fixture(scope="module")
def flights():
    return simulate_cross_flight(31, platform=PLATFORM), simulate_cross_flight(32, platform=PLATFORM)


def test_the_simulated_currents_are_recorded_and_the_hidden_ones_carry_a_field(flights):
    first, _ = flights
    record = cross_record(first.dataset())
    assert set(record.all_currents) == set(PLATFORM.currents_Am2_per_A)
    assert record.current_column == "cur_outpwr"  # the first found by name; the others the diagnosis's
    k = first.truth.currents_nT_per_A
    assert np.linalg.norm(k["cur_outpwr"]) == 0 and min(np.linalg.norm(k[c]) for c in HIDDEN) > 0.1


def test_both_hidden_currents_are_named_and_the_second_flight_reaches_the_truth(flights):
    first, second = flights
    ned = first.truth.field_ned_nT
    record = cross_record(first.dataset())
    diagnosis = diagnose_cross_compensation(record, field_ned_nT=ned)
    assert diagnosis.verdict == "missing_effect" and diagnosis.explained_by == ["current"]
    assert set(diagnosis.current_columns) == set(HIDDEN)
    labels = {c.label for c in diagnosis.candidates if c.judged}
    assert {f"current ({c})" for c in PLATFORM.currents_Am2_per_A} <= labels  # each column its own candidate
    assert f"--current {','.join(diagnosis.current_columns)}" in diagnosis.summary
    assert diagnosis.to_dict()["current_columns"] == diagnosis.current_columns
    # the advised model, fitted on the first flight with those columns, compensates the second as the truth does
    taken = cross_record(first.dataset(), ",".join(diagnosis.current_columns))
    fit = cross_compensation_result(taken, ["current"], field_ned_nT=ned).calibration
    assert fit.current_columns == tuple(diagnosis.current_columns)
    again = CrossCompensation.from_json(fit.to_json())
    ours = again.compensate(second.readings_nT, sample_rate_hz=10.0, current_A=second.currents_A)
    maneuvers, baseline = second.truth.maneuvers, second.baseline_m
    truth = tensor_fom(second.truth.compensated_nT(second.readings_nT), baseline, maneuvers, 10.0).fom_nT_per_m
    assert tensor_fom(ours, baseline, maneuvers, 10.0).fom_nT_per_m <= 1.2 * truth
    # one current alone leaves the other's field: the tensor FOM well above the truth's
    one = cross_compensation_result(cross_record(first.dataset(), "cur_strb"), ["current"], field_ned_nT=ned)
    alone = one.calibration.compensate(second.readings_nT, sample_rate_hz=10.0, current_A=second.currents_A)
    assert tensor_fom(alone, baseline, maneuvers, 10.0).fom_nT_per_m > 1.5 * truth


def test_a_line_without_one_of_the_currents_is_refused_by_name(flights):
    first, _ = flights
    record = cross_record(first.dataset(), "cur_strb,cur_com_1")
    fit = cross_compensation_result(record, ["current"], field_ned_nT=first.truth.field_ned_nT).calibration
    with pytest.raises(MagcalError, match="cur_com_1"):
        fit.compensate(first.readings_nT, sample_rate_hz=10.0, current_A={"cur_strb": first.currents_A["cur_strb"]})
