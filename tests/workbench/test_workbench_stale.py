"""Opening other data leaves nothing of the old data's views: the time window and the vehicle view start anew.

Each kind of data the workbench opens (the four-sensor demo, a vehicle record with attitude, a compass beside an
accelerometer, a compensation flight, a lesson) is opened after each other kind, with the old one's vehicle view shown and its time window
moved; the new data's page must then show every sample, no vehicle, and describe the new record, not the old.
"""

import itertools

import pytest

from magcal_workbench.dataio import load_dataset
from magcal_workbench.lessons import get_lesson

#: The kinds of data, by a lesson that holds one (None: the workbench's own demo, the four-sensor cross).
KINDS = {
    "four-sensor demo": None,
    "vehicle with attitude": "drone-current",
    "compass beside an accelerometer": "tilted-compass",
    "vehicle that cannot tumble": "cannot-tumble",
    "scalar beside a fluxgate": "survey-drone-current",
}


def _open(slug):
    if slug is None:
        return None, None
    path = get_lesson(slug).data_path
    ds, _ = load_dataset(path)
    return ds, path.read_bytes()


@pytest.mark.parametrize(("first", "second"), list(itertools.permutations(KINDS, 2)))
def test_other_data_open_with_no_view_state_of_the_old(bench, first, second):
    ds, _ = _open(KINDS[first])
    wb = bench(ds=ds)
    has_attitude = wb.ctrl.vector.attitude_kind() is not None
    vehicle_on = wb.panels.vector_panel.vehicle_on
    if has_attitude:
        vehicle_on.value = True  # turns the time window on too
        assert wb.vehicle.enabled and wb.vehicle.nodes
    wb.panels.window_on.value = True
    wb.panels.window_start.value = 60.0
    assert wb.window.enabled and wb.window.start_pct == pytest.approx(60.0)
    old_text = wb.panels.window_info.content

    new, content = _open(KINDS[second])
    if new is None:
        new, content = _open("warm-sensor")  # a four-sensor record like the demo
    wb.load(new, content, "next.csv", resume=False)

    assert not wb.window.enabled and wb.window.start_pct == 0.0
    assert not wb.panels.window_on.value and wb.panels.window_start.value == 0.0
    assert not wb.vehicle.enabled and not vehicle_on.value and wb.vehicle.nodes == {}
    text = wb.panels.window_info.content
    assert f"every sample shown ({new.n_samples})" in text and text != old_text
    assert "Sample" not in wb.panels.vector_panel.vehicle_info.content  # no sample of the old record named
    vp = wb.panels.vector_panel  # the location inputs: the new record's site (its file's `# site:` line), or none
    place = (53.0, 4.5, 1500.0, "2024-06-01") if second == "vehicle that cannot tumble" else (0.0, 0.0, 0.0)
    assert (vp.lat.value, vp.lon.value, vp.alt.value, vp.date.value)[: len(place)] == place
