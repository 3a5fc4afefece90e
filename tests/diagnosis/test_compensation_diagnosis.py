"""The compensation's diagnosis on simulated compensation flights with one hidden term each: it names the term the
platform has (nothing for a clean flight, whose temperature changes as every flight's does), judged on held-out
maneuvers or on a second flight, and the advice compensates a second flight to within 1.2x of the true
compensation."""

from __future__ import annotations

import numpy as np
import pytest

from magcal.data.compensation_flight import CompensationPlatform, simulate_compensation_flight
from magcal.diagnosis.compensation import FOLDS, diagnose_compensation
from magcal.fitting.compensation import fit_compensation
from tests.fitting.test_compensation_fit import MISCALIBRATED, WARMING, record_of, second_flight_fom

HIDDEN = [
    ("none", {}, []),
    ("current", {"platform": CompensationPlatform(current_nT_per_A=np.array([1.5, -1.0, 0.8]))}, ["current"]),
    ("fluxgate 100 ms late", {"fluxgate_lag_s": 0.1}, ["time_offset"]),
    ("fluxgate miscalibrated", MISCALIBRATED, ["fluxgate_calibration"]),
    ("temperature", WARMING, ["temperature"]),
]


@pytest.mark.parametrize(("name", "kwargs", "expected"), HIDDEN, ids=[h[0] for h in HIDDEN])
def test_diagnosis_names_the_hidden_term_on_held_out_maneuvers(name, kwargs, expected):
    first, second = simulate_compensation_flight(1, **kwargs), simulate_compensation_flight(2, **kwargs)
    found = diagnose_compensation(record_of(first))
    assert found.explained_by == expected
    assert found.verdict == ("missing_effect" if expected else "adequate")
    assert found.validation["scheme"] == "maneuvers" and found.validation["n_maneuvers"] == 12
    recommended = [c.name for c in found.candidates if c.recommended]
    assert recommended == expected
    if expected:  # the evidence and the advice say what to add
        assert "--effects " + ",".join(expected) in found.summary
        assert found.fom_final_nT < 0.8 * found.fom_held_out_nT
    ours, true = second_flight_fom(fit_compensation(record_of(first), found.explained_by), second)
    assert ours < 1.2 * true
    doc = found.to_dict()
    assert doc["mode"] == "compensation" and doc["explained_by"] == expected


def test_a_second_flight_judges_the_candidates():
    kwargs = {"platform": CompensationPlatform(current_nT_per_A=np.array([1.5, -1.0, 0.8]))}
    first, second = simulate_compensation_flight(1, **kwargs), simulate_compensation_flight(2, **kwargs)
    found = diagnose_compensation(record_of(first), also=record_of(second), candidates=["current", "heading"])
    assert found.validation["scheme"] == "flight"
    assert found.explained_by == ["current"]
    assert "per A" in next(c.evidence for c in found.candidates if c.name == "current")


def test_without_a_current_column_the_current_is_not_judged():
    flight = simulate_compensation_flight(1)
    record = record_of(flight)
    record.current, record.current_column, record.temperature_C = None, None, None
    found = diagnose_compensation(record, candidates=["current", "temperature"])
    assert {c.name: c.judged for c in found.candidates} == {"current": False, "temperature": False}
    assert "no current_A or throttle" in found.text()


def test_a_record_of_one_heading_is_not_judged():
    flight = simulate_compensation_flight(1, headings_deg=(0.0,))
    found = diagnose_compensation(record_of(flight))
    assert len(found.candidates) and not any(c.judged for c in found.candidates)
    assert found.verdict == "not_judged" and found.explained_by == []
    assert "--also" in found.summary
    assert found.validation["n_maneuvers"] < FOLDS


def test_a_temperature_the_platform_does_not_follow_is_judged_and_not_recommended():
    flight = simulate_compensation_flight(1)
    record = record_of(flight)
    record.temperature_C = 20.0 + 5.0 * np.sin(2 * np.pi * flight.time_s / 300.0)
    found = diagnose_compensation(record, candidates=["temperature"])
    (candidate,) = found.candidates
    assert candidate.judged and not candidate.recommended and "per degC" in candidate.evidence
    assert found.verdict == "adequate"


def test_the_current_term_takes_the_columns_whose_field_shows_on_held_out_maneuvers():
    from magcal.diagnosis.fom import figure_of_merit, find_maneuvers
    from magcal.fitting.compensation import compensation_record
    from tests.fitting.test_compensation_fit_currents import TWO_CURRENTS, currents_dataset

    first = simulate_compensation_flight(1, platform=TWO_CURRENTS)
    second = simulate_compensation_flight(2, platform=TWO_CURRENTS)
    record = compensation_record(currents_dataset(first))  # five current columns, two carry a field
    found = diagnose_compensation(record, candidates=["current", "heading"])
    assert found.explained_by == ["current"] and found.verdict == "missing_effect"
    assert sorted(found.current_columns) == ["cur_com_1", "cur_strb"]
    assert "--effects current --current " + ",".join(found.current_columns) in found.summary
    judged = {c.columns[0] for c in found.candidates if c.name == "current" and c.judged}
    assert judged == {"cur_strb", "cur_com_1", "cur_heat", "cur_flap", "cur_tank"}  # each column judged
    assert found.to_dict()["current_columns"] == found.current_columns
    comp = fit_compensation(record.taking_currents(found.current_columns), found.explained_by)
    line = compensation_record(currents_dataset(second, "line.csv"), current=found.current_columns)
    maneuvers = find_maneuvers(second.sample_rate_hz, attitude_deg=second.attitude_deg)
    ours = figure_of_merit(comp.compensate(line), maneuvers, second.sample_rate_hz).fom_nT
    true = figure_of_merit(second.truth.compensated_nT(second.scalar_nT), maneuvers, second.sample_rate_hz).fom_nT
    assert ours < 1.2 * true
    one = fit_compensation(record, ["current"])  # the first column alone (the old default) leaves the radio's field
    assert figure_of_merit(one.compensate(line), maneuvers, second.sample_rate_hz).fom_nT > 3 * true
