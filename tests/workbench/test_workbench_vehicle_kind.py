"""The vehicle view draws the record's vehicle: a quadcopter as four rotors on an X, an aircraft with wings, a
plain block when the record names none; the body's axes share no colour with the fields."""

import numpy as np
import pytest

from magcal_workbench import vehicleview as vv
from magcal_workbench.dataio import load_dataset
from magcal_workbench.lessons import get_lesson


class _Record:
    def __init__(self, **metadata):
        self.metadata = metadata


@pytest.mark.parametrize(
    ("metadata", "kind"),
    [
        ({"vehicle": "quadcopter"}, "multirotor"),
        ({"vehicle": "Hexacopter"}, "multirotor"),
        ({"log_firmware": "ArduCopter V4.5"}, "multirotor"),
        ({"vehicle": "aeroplane"}, "aeroplane"),
        ({"vehicle": "rover"}, "ground"),
        ({}, "body"),
    ],
)
def test_the_vehicle_kind_is_read_from_the_record(metadata, kind):
    assert vv.vehicle_kind(_Record(**metadata)) == kind


@pytest.mark.parametrize(("slug", "kind"), [("drone-current", "multirotor"), ("cannot-tumble", "aeroplane")])
def test_the_lessons_name_their_vehicle(slug, kind):
    ds, _ = load_dataset(get_lesson(slug).data_path)
    assert vv.vehicle_kind(ds) == kind


def test_a_quadcopter_is_four_rotors_on_an_x_and_no_wings():
    (hull, _), (nose, _) = vv.vehicle_mesh(kind="multirotor")
    (plane, _), _ = vv.vehicle_mesh(kind="aeroplane")
    # the rotors sit at the four diagonals, as far forward as aft and as far left as right
    for sx in (1, -1):
        for sy in (1, -1):
            quadrant = hull[(np.sign(hull[:, 0]) == sx) & (np.sign(hull[:, 1]) == sy)]
            assert np.hypot(quadrant[:, 0], quadrant[:, 1]).max() > 0.7
    assert np.ptp(hull[:, 0]) == pytest.approx(np.ptp(hull[:, 1]), rel=0.05)  # square: no wing span
    assert np.ptp(plane[:, 1]) > np.ptp(plane[:, 0])  # the aircraft: its wings span more than its length
    assert nose[:, 0].mean() > 0.0  # the nose marks the front (+x)


def test_no_field_colour_is_a_body_axis_colour():
    fields = {vv.MODEL_RGB, vv.MEASURED_RGB, vv.RESIDUAL_RGB}
    assert vv.BODY_AXIS_RGB not in fields and len(fields) == 3
    grey = np.ptp(vv.BODY_AXIS_RGB) < 30  # a grey: none of the red, green, blue of the fields
    assert grey
