"""The compensation's figure: the traces before and after on their own scales with the maneuvers named, and the
FOM table (per heading and maneuver, before / after, the sums and the FOM) as the report gives it."""

from __future__ import annotations

import numpy as np
import pytest

from magcal.core.errors import MagcalError
from magcal.data.compensation_flight import CompensationPlatform, simulate_compensation_flight
from magcal.diagnosis.compensation import compensation_result
from magcal.fitting.compensation import CompensationRecord
from magcal.output.compensation_figure import _table_rows, write_compensation_figure

CURRENT = CompensationPlatform(current_nT_per_A=np.array([1.5, -1.0, 0.8]))


@pytest.fixture(scope="module")
def flight():
    return simulate_compensation_flight(1, platform=CURRENT)


@pytest.mark.parametrize(("effects", "times"), [((), True), (("current",), False)])
def test_the_figure_and_its_table(flight, tmp_path, effects, times):
    record = CompensationRecord(
        flight.scalar_nT, flight.flux_nT, 10.0, time_s=flight.time_s if times else None,
        attitude_deg=flight.attitude_deg, current=flight.current_A, current_column="current_A",
    )  # fmt: skip
    result = compensation_result(record, effects)
    header, rows = _table_rows(result.fom)
    assert header == ["heading", "roll", "pitch", "yaw", "sum"]
    assert [r[0] for r in rows] == ["0 deg", "90 deg", "180 deg", "270 deg", "all"]
    before, after = (float(v) for v in rows[-1][-1].split(" / "))
    assert before == pytest.approx(result.fom.before.fom_nT, abs=0.01)
    assert after == pytest.approx(result.fom.after.fom_nT, abs=0.001)
    per_heading = sum(float(r[-1].split(" / ")[1]) for r in rows[:-1])
    assert per_heading == pytest.approx(result.fom.after.fom_nT, abs=0.005)
    path = write_compensation_figure(result, tmp_path / "fom.png")
    assert open(path, "rb").read(4) == b"\x89PNG"


def test_no_maneuvers_no_figure(flight, tmp_path):
    result = compensation_result(CompensationRecord(flight.scalar_nT, flight.flux_nT, 10.0))
    result.fom = None
    with pytest.raises(MagcalError, match="no FOM table"):
        write_compensation_figure(result, tmp_path / "fom.png")
