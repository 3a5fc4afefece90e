"""The scalar's and the cross's FOM objects answer one protocol (:mod:`magcal.diagnosis.fom_protocol`): their
unit-neutral accessors are their unit-named fields, in their units (nT; the tensor's nT/m), on a simulated flight
of each with a hidden current (so that a candidate is judged and the advice has a final FOM)."""

from __future__ import annotations

import numpy as np
import pytest

from magcal.data.compensation_flight import CompensationPlatform, simulate_compensation_flight
from magcal.data.cross_flight import simulate_cross_flight
from magcal.diagnosis.compensation import compensation_result, diagnose_compensation
from magcal.diagnosis.cross_compensation import (
    cross_compensation_result,
    cross_record,
    diagnose_cross_compensation,
)
from magcal.diagnosis.fom_protocol import CandidateFOM, DiagnosisFOM, FOMComparison, FOMFigures
from tests.fitting.test_compensation_fit import record_of


def _scalar():
    flight = simulate_compensation_flight(3, platform=CompensationPlatform(current_nT_per_A=np.array([1.5, -1, 0.8])))
    record = record_of(flight)
    report, found = compensation_result(record).fom, diagnose_compensation(record)
    named = {
        "fom": "fom_nT",
        "per_maneuver": "peak_to_peak_nT",
        "fom_before": "fom_before_nT",
        "fom_after": "fom_after_nT",
        "fom_held_out": "fom_held_out_nT",
        "fom_final": "fom_final_nT",
        "floor_fom": "floor_fom_nT",
    }
    return report, found, "nT", named


def _cross():
    flight = simulate_cross_flight(21, platform="drone_current")
    ds = flight.dataset()
    ds.extra["current_A"] = flight.current_A
    record = cross_record(ds)
    ned = flight.truth.field_ned_nT
    report = cross_compensation_result(record, field_ned_nT=ned).fom
    found = diagnose_cross_compensation(record, field_ned_nT=ned)
    named = {
        "fom": "fom_nT_per_m",
        "per_maneuver": "maneuver_nT_per_m",
        "fom_before": "fom_before_nT_per_m",
        "fom_after": "fom_after_nT_per_m",
        "fom_held_out": "fom_held_out_nT_per_m",
        "fom_final": "fom_final_nT_per_m",
        "floor_fom": "floor_fom_nT_per_m",
    }
    return report, found, "nT/m", named


@pytest.fixture(scope="module", params=["scalar", "cross"])
def foms(request):
    return {"scalar": _scalar, "cross": _cross}[request.param]()


def test_the_reports_and_their_tables_answer_the_protocol(foms):
    report, _, unit, named = foms
    assert isinstance(report, FOMComparison) and report.unit == unit
    for table in (report.before, report.after):
        assert isinstance(table, FOMFigures) and table.unit == unit
        assert table.fom == getattr(table, named["fom"]) and np.isfinite(table.fom)
        np.testing.assert_array_equal(table.per_maneuver, getattr(table, named["per_maneuver"]))
        assert len(table.per_maneuver) == len(table.maneuvers) == 12
    assert report.after.fom < report.before.fom  # the compensation lowers it


def test_the_diagnosis_and_its_candidates_answer_the_protocol(foms):
    _, found, unit, named = foms
    assert isinstance(found, DiagnosisFOM) and found.unit == unit
    for accessor in ("fom_held_out", "fom_final", "floor_fom"):
        assert getattr(found, accessor) == getattr(found, named[accessor])
    assert found.fom_final is not None and found.fom_final < found.fom_held_out  # the hidden current named
    judged = [c for c in found.candidates if c.judged]
    assert judged and any(c.recommended for c in judged)
    for candidate in found.candidates:
        assert isinstance(candidate, CandidateFOM) and candidate.unit == unit and candidate.label
        for accessor in ("fom_before", "fom_after"):
            np.testing.assert_equal(getattr(candidate, accessor), getattr(candidate, named[accessor]))
