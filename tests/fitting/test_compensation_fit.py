"""The compensation mode's library: the record read from a dataset, Tolles-Lawson with the terms beyond it fitted on
simulated compensation flights whose platform and fluxgate the test sets, the document and MagNav.jl's TL vector."""

from __future__ import annotations

import json

import numpy as np
import pytest

from magcal.core.errors import MagcalError
from magcal.data.compensation_flight import CompensationPlatform, simulate_compensation_flight
from magcal.data.dataset import Dataset
from magcal.diagnosis.compensation import compensation_result
from magcal.diagnosis.fom import figure_of_merit, find_maneuvers
from magcal.fitting.compensation import (
    Compensation,
    CompensationRecord,
    compensation_record,
    find_scalar_column,
    fit_compensation,
)
from magcal.output.magnav_tl import magnav_tl_document

RATE = 10.0
#: A fluxgate off by 5 % in scale, 1.7 deg of non-orthogonality and a bias of 1-2 uT.
MISCALIBRATED = {
    "fluxgate_matrix": np.array([[1.05, 0.0, 0.0], [0.03, 0.95, 0.0], [-0.03, 0.03, 1.025]]),
    "fluxgate_bias_nT": np.array([1000.0, -1500.0, 700.0]),
}
#: A permanent field that drifts by 0.3-0.5 nT per degC as the platform warms (12 degC through the flight).
WARMING = {"platform": CompensationPlatform(temperature_nT_per_C=np.array([-0.4, 0.3, -0.5]))}


def record_of(flight) -> CompensationRecord:
    return CompensationRecord(
        flight.scalar_nT,
        flight.flux_nT,
        flight.sample_rate_hz,
        attitude_deg=flight.attitude_deg,
        current=flight.current_A,
        current_column="current_A",
        temperature_C=flight.temperature_C,
    )


def second_flight_fom(comp: Compensation, flight) -> tuple[float, float]:
    """(our FOM, the true compensation's) on a flight, in the maneuvers found from its attitude."""
    found = find_maneuvers(RATE, attitude_deg=flight.attitude_deg)
    ours = figure_of_merit(comp.compensate(record_of(flight)), found, RATE).fom_nT
    true = figure_of_merit(flight.truth.compensated_nT(flight.scalar_nT), found, RATE).fom_nT
    return ours, true


def _dataset(flight, scalar="scalar_nT", euler=True):
    extra = {scalar: flight.scalar_nT, "current_A": flight.current_A}
    if euler:
        extra |= dict(zip(("roll_deg", "pitch_deg", "yaw_deg"), flight.attitude_deg.T))
    return Dataset(flight.flux_nT[None], time_s=flight.time_s, extra=extra, source="box.csv")


@pytest.mark.parametrize("scalar", ["scalar_nT", "mag_1_uc"])
def test_record_takes_the_scalar_by_name_and_the_rate_from_the_times(scalar):
    flight = simulate_compensation_flight(1)
    record = compensation_record(_dataset(flight, scalar))
    assert record.scalar_column == scalar
    assert record.sample_rate_hz == pytest.approx(RATE)
    np.testing.assert_allclose(record.attitude_deg[:, 0], flight.attitude_deg[:, 0])
    assert record.current_column == "current_A"


def test_record_without_a_scalar_says_how_to_name_it():
    flight = simulate_compensation_flight(1)
    ds = _dataset(flight, "tmi")
    assert find_scalar_column(ds) is None
    with pytest.raises(MagcalError, match="--scalar NAME"):
        compensation_record(ds)
    assert compensation_record(ds, "tmi").scalar_column == "tmi"
    with pytest.raises(MagcalError, match="no column 'mag'.*tmi"):
        compensation_record(ds, "mag")


def test_record_names_the_row_of_a_missing_scalar():
    flight = simulate_compensation_flight(1)
    scalar = flight.scalar_nT.copy()
    scalar[7] = np.nan
    ds = Dataset(flight.flux_nT[None], time_s=flight.time_s, extra={"scalar_nT": scalar}, source="box.csv")
    with pytest.raises(MagcalError, match="box.csv: column scalar_nT .* data row 8"):
        compensation_record(ds)


# (hidden term, the simulator's arguments, the effects that model it)
HIDDEN = [
    ("none", {}, ()),
    ("current", {"platform": CompensationPlatform(current_nT_per_A=np.array([1.5, -1.0, 0.8]))}, ("current",)),
    ("fluxgate 100 ms late", {"fluxgate_lag_s": 0.1}, ("time_offset",)),
    ("fluxgate miscalibrated", MISCALIBRATED, ("fluxgate_calibration",)),
    ("temperature", WARMING, ("temperature",)),
]


@pytest.mark.parametrize(("name", "kwargs", "effects"), HIDDEN, ids=[h[0] for h in HIDDEN])
def test_the_term_that_models_a_hidden_effect_compensates_a_second_flight(name, kwargs, effects):
    first, second = simulate_compensation_flight(1, **kwargs), simulate_compensation_flight(2, **kwargs)
    ours, true = second_flight_fom(fit_compensation(record_of(first), effects), second)
    assert ours < 1.2 * true
    if effects:  # TL alone does worse: the term is what TL lacks
        tl, _ = second_flight_fom(fit_compensation(record_of(first)), second)
        assert tl > 1.15 * ours


def test_fitted_terms_are_the_platforms():
    kwargs = {"platform": CompensationPlatform(current_nT_per_A=np.array([1.5, -1.0, 0.8])), "fluxgate_lag_s": 0.1}
    comp = fit_compensation(record_of(simulate_compensation_flight(1, **kwargs)), ("current", "time_offset"))
    np.testing.assert_allclose(comp.extra_coefficients, [1.5, -1.0, 0.8], atol=0.03)
    assert comp.time_offset_s == pytest.approx(0.1, abs=0.005)


def test_joint_fluxgate_calibration_finds_the_bias():
    comp = fit_compensation(record_of(simulate_compensation_flight(1, **MISCALIBRATED)), ("fluxgate_calibration",))
    np.testing.assert_allclose(comp.fluxgate_bias_nT, MISCALIBRATED["fluxgate_bias_nT"], atol=5.0)
    # M W is a rotation times a scale (the band cannot see the overall scale, set from the scalar's median to the
    # platform field's share, < 1 %): the corrected fluxgate's magnitude is the same at every attitude
    product = comp.fluxgate_matrix @ MISCALIBRATED["fluxgate_matrix"]
    gram = product.T @ product
    np.testing.assert_allclose(gram / np.mean(np.diag(gram)), np.eye(3), atol=2e-4)
    assert abs(np.mean(np.diag(gram)) - 1) < 0.01


def test_document_round_trip_and_magnav_vector(tmp_path):
    flight = simulate_compensation_flight(1, platform=CompensationPlatform(current_nT_per_A=np.array([1.0, 0, 0])))
    record = record_of(flight)
    comp = fit_compensation(record, ("current",))
    path = tmp_path / "comp.json"
    comp.save(path)
    back = Compensation.load(path)
    np.testing.assert_allclose(back.compensate(record), comp.compensate(record))
    doc = json.loads(path.read_text())
    assert doc["kind"] == "compensation" and doc["tl18_order"][0] == "permanent_x" and len(doc["tl18"]) == 18
    with pytest.raises(MagcalError, match="cannot hold the term current"):
        magnav_tl_document(back)
    forced = magnav_tl_document(back, force=True)
    np.testing.assert_allclose(forced["TL_coef"], comp.tl18())
    assert forced["dropped"]


def test_a_damaged_document_is_named(tmp_path):
    comp = fit_compensation(record_of(simulate_compensation_flight(1)))
    doc = comp.to_dict()
    doc["extra_labels"] = ["current_x"]
    with pytest.raises(MagcalError, match="comp.json: a damaged compensation document"):
        Compensation.from_dict(doc, "comp.json")


def test_result_reports_the_fom_table():
    result = compensation_result(record_of(simulate_compensation_flight(1)), source="box.csv")
    doc = result.to_dict()
    assert doc["mode"] == "compensation" and len(doc["fom"]["after"]["rows"]) == 12
    assert doc["fom_nT"] < 0.05 * doc["fom_before_nT"]
    assert doc["improvement_ratio"] > 100
    text = result.text()
    assert "condition number" in text and "improvement ratio" in text and "eddy_zz" in text


def test_record_takes_a_throttle_and_the_temperature():
    flight = simulate_compensation_flight(1)
    ds = Dataset(
        flight.flux_nT[None],
        time_s=flight.time_s,
        temperature_C=20 + 0.01 * flight.time_s,
        extra={"scalar_nT": flight.scalar_nT, "throttle": np.linspace(0.2, 0.8, flight.time_s.size)},
        source="box.csv",
    )
    record = compensation_record(ds)
    assert record.current_column == "throttle" and record.temperature_C[-1] > record.temperature_C[0]
    assert record.attitude_deg is None  # the maneuvers are then found from the fluxgate
