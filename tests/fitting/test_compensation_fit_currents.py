"""The compensation's current term with several current columns (a platform's wires, each with its own field per
ampere at the sensor), on a simulated flight whose two hidden currents point in different directions and whose other
recorded currents carry no field: the record's columns, the fit per column, the document, a line that lacks one."""

from __future__ import annotations

import numpy as np
import pytest

from magcal.core.errors import MagcalError
from magcal.data.compensation_flight import CompensationPlatform, simulate_compensation_flight
from magcal.data.dataset import Dataset
from magcal.fitting.compensation import Compensation, compensation_record, fit_compensation

#: The strobe lights' and the radio's wires near the sensor (nT per A, body frame, of different directions); the
#: heater's, the flaps' and the tank pump's far from it (recorded, no field).
STROBE, RADIO = np.array([1.5, -1.0, 0.8]), np.array([-0.6, 1.2, 1.0])
TWO_CURRENTS = CompensationPlatform(
    currents_nT_per_A={
        "cur_strb": STROBE,
        "cur_com_1": RADIO,
        "cur_heat": np.zeros(3),
        "cur_flap": np.zeros(3),
        "cur_tank": np.zeros(3),
    }
)


def currents_dataset(flight, source="box.csv", drop=()) -> Dataset:
    """A flight with MagNav.jl's current columns (``cur_*``), the scalar and the attitude."""
    extra = {"scalar_nT": flight.scalar_nT} | {k: v for k, v in flight.currents_A.items() if k not in drop}
    extra |= dict(zip(("roll_deg", "pitch_deg", "yaw_deg"), flight.attitude_deg.T))
    return Dataset(flight.flux_nT[None], time_s=flight.time_s, extra=extra, source=source)


@pytest.fixture(scope="module")
def flight():
    return simulate_compensation_flight(1, platform=TWO_CURRENTS)


def test_the_record_takes_the_first_current_and_keeps_the_others_for_the_diagnosis(flight):
    record = compensation_record(currents_dataset(flight))
    assert record.current_column == "cur_strb"  # MagNav.jl's order: the strobe before the radio
    assert list(record.term_currents) == ["cur_strb"]
    assert set(record.other_currents) == {"cur_com_1", "cur_heat", "cur_flap", "cur_tank"}
    named = compensation_record(currents_dataset(flight), current="cur_com_1, cur_strb")
    assert list(named.term_currents) == ["cur_com_1", "cur_strb"] and not named.other_currents
    with pytest.raises(MagcalError, match="no column 'cur_fan'.*--current"):
        compensation_record(currents_dataset(flight), current=["cur_strb", "cur_fan"])


def test_each_current_column_gets_its_own_field_per_ampere(flight, tmp_path):
    record = compensation_record(currents_dataset(flight), current="cur_strb,cur_com_1")
    comp = fit_compensation(record, ("current",))
    values = dict(zip(comp.extra_labels, comp.extra_coefficients))
    np.testing.assert_allclose([values[f"current_cur_strb_{a}"] for a in "xyz"], STROBE, atol=0.05)
    np.testing.assert_allclose([values[f"current_cur_com_1_{a}"] for a in "xyz"], RADIO, atol=0.05)
    assert comp.current_columns == ("cur_strb", "cur_com_1")
    path = tmp_path / "comp.json"
    comp.save(path)
    back = Compensation.load(path)
    assert back.current_columns == ("cur_strb", "cur_com_1")
    line = simulate_compensation_flight(2, platform=TWO_CURRENTS)
    line_record = compensation_record(currents_dataset(line, "line.csv"), current=list(back.current_columns))
    np.testing.assert_allclose(back.compensate(line_record), comp.compensate(line_record))
    without = compensation_record(currents_dataset(line, "line.csv", drop=("cur_com_1",)), current="cur_strb")
    with pytest.raises(MagcalError, match="line.csv: .*needs its cur_com_1 column"):
        back.compensate(without)


def test_one_current_column_keeps_the_labels_of_earlier_documents(flight):
    comp = fit_compensation(compensation_record(currents_dataset(flight)), ("current",))
    assert comp.extra_labels == ["current_x", "current_y", "current_z"] and comp.current_columns == ("cur_strb",)
    doc = comp.to_dict()
    del doc["current_columns"]  # a document of an earlier version: its one current_column
    assert Compensation.from_dict(doc).current_columns == ("cur_strb",)
