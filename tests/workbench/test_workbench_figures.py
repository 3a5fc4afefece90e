"""One figure per quantity: one record's noise floor reads the same in the header, the compact table, the Quality
tab, the Model tab's verdict and the history plot, through the loop; the raw row of the table is the raw data's
figure before and after a fit; the reference text says what the fit uses."""

import re
import time

import numpy as np
import pytest

from magcal.diagnosis.vector import VectorNoise
from magcal_workbench.dataio import load_dataset
from magcal_workbench.floors import lowest, mode_floor
from magcal_workbench.guide import next_step
from magcal_workbench.lessons import get_lesson


def _lesson(slug):
    ds, _ = load_dataset(get_lesson(slug).data_path)
    return ds


def _press(wb):
    """The guide's button, as a click does."""
    wb.panels.btn_next.value = True
    time.sleep(0.05)
    assert wb.worker.wait(300)
    wb.ui.wait()


def _floors_shown(wb) -> dict:
    """Each place's floor figure, as the page's text reads (nT)."""
    p = wb.panels
    found = {}
    for name, widget, pattern in (
        ("header", p.status, r"\(floor ([\d.]+) nT\)"),
        ("table", p.summary, r"noise floor \(world components\) ([\d.]+) nT"),
        ("quality", p.noise_info, r"Noise floor \(world components\): ([\d.]+) nT"),
        ("diagnose", p.candidates, r"noise floor ([\d.]+) nT"),
    ):
        m = re.search(pattern, widget.content)
        found[name] = float(m.group(1)) if m else None
    plot = p.vector_panel.rms_plot.data if hasattr(p.vector_panel, "rms_plot") else None
    if plot is not None and len(plot[-1]) and np.isfinite(plot[-1][-1]):
        found["history plot"] = float(f"{plot[-1][-1]:.4g}")
    return found


@pytest.mark.slow
def test_one_records_noise_floor_reads_the_same_in_every_tab_through_the_loop(bench):
    """The drone lesson (attitude, a field vector and a hidden current): after each diagnosis, whatever the model
    holds, the header, the table, the Quality tab, the verdict and the history plot show one world floor, with its
    source; it does not rise when the model changes."""
    wb = bench(ds=_lesson("drone-current"), store=False)
    seen = []
    for _ in range(5):
        step = next_step(wb.ctrl)
        if step.key == "none":
            break
        _press(wb)
        if wb.ctrl.vector.diagnosis is None:
            continue
        figures = _floors_shown(wb)
        assert None not in figures.values() and len(set(figures.values())) == 1, figures
        seen.append(figures["header"])
        assert "Source:" in wb.panels.noise_info.content and "differences in time" in wb.panels.noise_info.content
    assert len(seen) >= 2 and seen == sorted(seen, reverse=True)
    assert mode_floor(wb.ctrl).value_nT == pytest.approx(seen[-1], rel=1e-3)


def _noise(world_floor_nT, total_nT):
    """A vector diagnosis's noise as the engine gives it (one sensor)."""
    return VectorNoise([total_nT], [total_nT], 0.0, world_floor_nT)


def test_the_held_floor_is_the_lowest_estimate_and_counts_the_diagnoses():
    first = lowest(None, _noise(15.0, 7.0))
    second = lowest(first, _noise(12.0, 3.0))
    third = lowest(second, _noise(13.0, 4.0))
    assert (first.world_floor_nT, second.world_floor_nT, third.world_floor_nT) == (15.0, 12.0, 12.0)
    assert third.total_noise_nT == 3.0 and (third.diagnosis, third.of) == (2, 3)
    assert "diagnosis 2 of 3" in third.source() and "the vector diagnosis" in first.source()
    given = lowest(third, _noise(20.0, 9.0), given_nT=9.0)  # a noise given: as it is
    assert given.world_floor_nT == 20.0 and "the noise given, 9 nT per axis" in given.source()
    again = lowest(given, _noise(14.0, 3.5))  # taken back: estimated anew
    assert (again.world_floor_nT, again.given_nT, again.of) == (14.0, None, 1)


@pytest.mark.parametrize("given", [True, False])
def test_the_raw_row_is_the_raw_datas_figure_before_and_after_a_fit(bench, given):
    """The table's raw row and the history's first step agree, and neither moves when a fit finds the field (a
    record with its field given, and one whose field the fit finds)."""
    ds = _lesson("warm-sensor")
    wb = bench(ds=ds if given else ds.replace(reference_total_nT=None), store=False)

    def raw_row():
        wb.ui.wait()
        return re.search(r"\| raw \| ([\d.]+) \|", wb.panels.summary.content).group(1)

    before = raw_row()
    assert float(before) == pytest.approx(wb.ctrl.state.history[0].rms_nT, rel=1e-3)
    _press(wb)
    assert wb.ctrl.calibration is not None and raw_row() == before


def test_the_reference_text_names_the_vector_the_vector_fit_uses(bench):
    wb = bench(ds=_lesson("drone-current"), store=False)
    text = wb.panels.reference_info.content
    ned = np.column_stack([wb.ctrl.dataset.extra[c] for c in ("ref_n", "ref_e", "ref_d")])
    median = float(np.median(np.linalg.norm(ned, axis=1)))
    assert text.startswith("_Reference used by the vector fit:_") and "ref_n, ref_e, ref_d" in text
    assert f"{median:.6g} nT" in text and "none given" not in text.split("\n")[0]


def test_the_scene_draws_what_the_vector_fit_corrected(bench):
    """On a record whose loop is the vector fit, the first step fits it and the scene's right-hand cloud is the
    vector fit's correction (on the unit sphere, labelled so), not an empty place beside 'S1 raw'."""
    wb = bench(ds=_lesson("drone-current"), store=False)
    assert next_step(wb.ctrl).key == "vector"
    _press(wb)
    assert wb.ctrl.calibration is None and wb.ctrl.vector.result is not None  # the total-field fit did not run
    model = wb.view.scene_model()
    (sv,) = model.sensors
    assert model.corrected_by == "vector" and sv.corrected_nT is not None
    radius = np.linalg.norm(sv.corrected_nT, axis=1) / model.field_nT
    assert np.median(np.abs(radius - 1.0)) < 0.01  # corrected: on the sphere (the raw cloud is not)
    assert np.median(np.abs(np.linalg.norm(sv.raw_nT, axis=1) / model.field_nT - 1.0)) > 0.01
    assert "/data/s1/corrected" in wb.scene_view._clouds
    assert "vector fit" in wb.view.legend_html()
    # the residual gain follows the drawn fit's residual: the cloud stays about its sphere, not across the canvas
    drawn = model.residual_gain * np.asarray(sv.residual_nT) / model.field_nT
    assert 0.02 < np.sqrt(np.mean(drawn**2)) < 0.3


def test_a_board_with_an_accelerometer_fits_gravity_first_and_the_scene_draws_it(bench):
    """The tilted compass: the first step is the gravity fit; after it the scene's corrected cloud is the gravity
    fit's (on the sphere), the guide names the total-field loop as one choice away, and nothing more to press."""
    wb = bench(ds=_lesson("tilted-compass"), store=False)
    assert next_step(wb.ctrl).key == "gravity"
    _press(wb)
    assert wb.gravity.model.result is not None and wb.ctrl.calibration is None
    step = next_step(wb.ctrl)
    assert step.key == "none" and "one choice away" in step.why and not wb.panels.btn_next.visible
    s = wb.gravity.model.result.sensors[0]
    assert wb.panels.status.content.startswith(f"**Gravity fit: dip spread {s.dip_sd_deg:.3g} deg**")
    model = wb.view.scene_model()
    (sv,) = model.sensors
    assert model.corrected_by == "gravity" and "/data/s1/corrected" in wb.scene_view._clouds
    radius = np.linalg.norm(sv.corrected_nT, axis=1) / model.field_nT
    assert np.median(np.abs(radius - 1.0)) < 0.01
    drawn = model.residual_gain * np.asarray(sv.residual_nT) / model.field_nT
    assert 0.02 < np.sqrt(np.mean(drawn**2)) < 0.3


def test_a_total_field_records_noise_floor_reads_the_same_in_every_tab(bench):
    """Real data whose noise the page estimates (no noise declared): after the fit and the diagnosis, the header,
    the table, the Quality tab and the verdict show one floor, and the Quality tab says where it comes from."""
    wb = bench(ds=_lesson("real-qmc5883l"), store=False)
    assert wb.ctrl.noise_given_nT is None
    _press(wb)  # the total-field fit
    _press(wb)  # the diagnosis
    p = wb.panels
    found = {}
    for name, widget, pattern in (
        ("header", p.status, r"\(floor ([\d.]+) nT\)"),
        ("table", p.summary, r"noise floor ([\d.]+) nT"),
        ("quality", p.noise_info, r"Total-field floor of the current fit: ([\d.]+) nT"),
        ("diagnose", p.candidates, r"floor ([\d.]+) nT\)"),
    ):
        m = re.search(pattern, widget.content)
        found[name] = float(m.group(1)) if m else None
    assert None not in found.values() and len(set(found.values())) == 1, found
    assert "estimated from" in p.noise_info.content
