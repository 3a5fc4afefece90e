"""The workbench shows the data-quality findings, noise floors and structure the engine reads from real records,
driven through the page's handles on a real (browserless) viser server, on simulated data whose truth the tests set:

- the Quality tab lists :func:`magcal.checks.quality.assess` findings, warnings marked, each with what it does to the fit;
- the noise behind the floors says how it was found, and a noise the user gives sets the floor and is saved with
  the session;
- every maximum-likelihood step gets a held-out RMS (:func:`magcal.fitting.validation.validate`, blocks) beside its
  in-sample RMS, and a hidden effect's held-out figure falls once it is added;
- the Model tab marks each term instrument or record-only, and the corrected CSV names the record-only terms it
  applied;
- the Diagnose table shows each candidate's held-out figures and marks those whose gain does not hold.
"""

from __future__ import annotations

import io
import json
import time
from pathlib import Path

import numpy as np
import pytest

import magcal
from magcal.core import conventions
from magcal.data import io as mio
from magcal.model.terms import EFFECTS

SIGMA = 3.0  # the chi2017 preset's noise per axis, nT


def _click(wb, button):
    button.value = True  # what a click does: the callbacks run
    time.sleep(0.05)
    assert wb.worker.wait(180)


def _series(n=300, seed=5, rate_hz=2.0, perturbations=(), declared=False):
    """chi2017 (four sensors, 3 nT white noise per axis); the file declares its noise only if ``declared``."""
    ds = magcal.simulate_timeseries("chi2017", n_samples=n, seed=seed, rate_hz=rate_hz, perturbations=perturbations)
    return ds if declared else ds.replace(noise_nT=None)


# ---------------------------------------------------------------------------------------------------------------
# noise
# ---------------------------------------------------------------------------------------------------------------
def test_the_estimated_noise_says_its_method_and_finds_the_truth(bench):
    wb = bench(_series(), store=False)
    assert "not known yet" in wb.panels.noise_info.content
    _click(wb, wb.panels.btn_run)
    noise = wb.ctrl.noise
    assert noise.source in ("differences", "static") and noise.source != "given"
    assert abs(noise.sigma_nT - SIGMA) < 0.2 * SIGMA  # the true white noise, not the residual RMS
    assert "estimated from" in wb.panels.noise_info.content
    assert np.isclose(wb.ctrl.floor_nT(), conventions.total_field_floor_nT(noise.sigma_nT, 300, 9))


@pytest.mark.parametrize("how", ["typed in the Quality tab", "declared in the file"])
def test_a_given_noise_shows_as_given_and_sets_the_floor(bench, tmp_path, how):
    given = 7.5  # not the data's 3 nT: the floor must follow what is given
    if how == "declared in the file":
        wb = bench(_series().replace(noise_nT=given))
    else:
        wb = bench(_series())
        wb.panels.noise_input.value = given
        _click(wb, wb.panels.btn_noise)
        assert "given" in wb.panels.noise_info.content
    _click(wb, wb.panels.btn_run)
    ctrl = wb.ctrl
    assert ctrl.noise.source == "given" and ctrl.noise.sigma_nT == given
    floor = ctrl.floor_nT()
    assert given * 0.97 < floor < given  # sigma sqrt(1 - p/N)
    assert "(given)" in wb.panels.noise_info.content
    assert f"floor {floor:.3g} nT" in wb.panels.status.content
    assert np.allclose(wb.panels.rms_plot.data[2], floor)  # the history plot's floor line
    saved = json.loads((tmp_path / "sessions" / ctrl.session_id / "session.json").read_text())
    if how == "declared in the file":
        assert saved["noise_nT"] is None  # the file says it: nothing to save
        return
    assert saved["noise_nT"] == given
    wb.stop()
    again = bench(_series())  # the same data: the session reopens with the noise given
    assert again.ctrl.state.noise_nT == given and again.panels.noise_input.value == given
    assert again.ctrl.noise.source == "given" and np.isclose(again.ctrl.floor_nT(), floor)
    # 0 = estimate it again: the floor falls back to the data's own 3 nT
    again.panels.noise_input.value = 0.0
    _click(again, again.panels.btn_noise)
    assert again.ctrl.state.noise_nT is None and again.ctrl.noise.source != "given"
    assert abs(again.ctrl.noise.sigma_nT - SIGMA) < 0.2 * SIGMA


@pytest.mark.parametrize("value", [-1.0, float("nan"), 1e9])
def test_a_noise_the_page_could_not_offer_is_refused(bench, value):
    from magcal.core.errors import MagcalError

    wb = bench(_series(), store=False)
    wb.panels.noise_input._impl.value = value  # a browser may send any value
    wb.panels.btn_noise.value = True
    assert wb.ctrl.state.noise_nT is None and "refused" in wb.ctrl.message
    with pytest.raises(MagcalError, match="noise"):
        wb.ctrl.set_noise(value)


# ---------------------------------------------------------------------------------------------------------------
# held-out RMS in the history, and in the Diagnose panel
# ---------------------------------------------------------------------------------------------------------------
HIDDEN = "temperature_bias"


@pytest.fixture(scope="module")
def warm_data():
    """chi2017, 600 samples at 10 Hz, hiding a 60 nT temperature bias in sensor 1 (an instrument term)."""
    return _series(n=600, seed=3, rate_hz=10.0, perturbations=[EFFECTS[HIDDEN]().perturbation(60.0, 0)])


def test_a_hidden_effect_held_out_figure_falls_after_add(bench, warm_data):
    wb = bench(warm_data, store=False)
    _click(wb, wb.panels.btn_run)
    base = wb.ctrl.state.history[-1]
    assert base.held_out_rms_nT is not None and base.held_out_rms_nT > 5 * SIGMA  # the effect is missing
    _click(wb, wb.panels.btn_diagnose)
    top = wb.ctrl.diagnosis.candidates[0]
    assert top.label == f"{HIDDEN}:1" and top.holds is True
    shown = wb.panels.candidates.content
    assert f"`{HIDDEN}:1`" in shown and f"{base.held_out_rms_nT:.4g}→{top.held_out_after_nT:.4g}" in shown
    for c in wb.ctrl.diagnosis.candidates[:8]:  # each candidate's row says whether its gain holds
        row = next(line for line in shown.splitlines() if f"`{c.label}`" in line)
        assert ("does not hold" in row) == (c.holds is False) and ("| holds |" in row) == (c.holds is True)
    _click(wb, wb.panels.btn_add)
    after = wb.ctrl.state.history[-1]
    assert after.step == f"add {HIDDEN}:1"
    assert after.held_out_rms_nT < 1.15 * SIGMA < base.held_out_rms_nT / 5  # down to the noise on unseen samples
    assert after.rms_nT <= after.held_out_rms_nT  # in-sample below held-out, as it must be
    table = wb.panels.history.content
    assert "| held-out nT |" in table and f"| {after.held_out_rms_nT:.4g} |" in table
    x, y, floor, held = wb.panels.rms_plot.data
    assert held[0] == y[0]  # raw readings: nothing fitted, held-out is in-sample
    assert np.allclose(held[-2:], [base.held_out_rms_nT, after.held_out_rms_nT])
    assert "held-out RMS" in wb.ctrl.message


def test_candidates_that_do_not_hold_are_marked_and_may_still_be_added(bench, warm_data):
    """Rendering of the engine's held-out figures: a candidate whose gain does not hold is marked, with its
    figures, and Add stays enabled for it (the user may try it)."""
    from magcal_workbench.panels import candidate_evidence_markdown, candidates_markdown

    doc = {
        "verdict": "unexplained",
        "rms_nT": 10.0,
        "noise_nT": 3.0,
        "floor_nT": 2.9,
        "candidates": [
            {
                "label": "bias_drift",
                "delta_bic": -40.0,
                "rms_after_nT": 9.0,
                "refitted": True,
                "held_out_rms_before_nT": 11.0,
                "held_out_rms_after_nT": 12.5,
                "holds": False,
            },
            {
                "label": "<img src=x onerror=alert(1)>",
                "delta_bic": -20.0,
                "rms_after_nT": 9.5,
                "refitted": True,
                "held_out_rms_before_nT": 11.0,
                "held_out_rms_after_nT": 10.0,
                "holds": True,
            },
            {
                "label": "bias_step",
                "delta_bic": -15.0,
                "rms_after_nT": 9.6,
                "refitted": True,
                "held_out_rms_before_nT": 11.0,
                "held_out_rms_after_nT": 10.5,
                "later_rms_before_nT": 20.0,
                "later_rms_after_nT": 25.0,
                "holds": False,
            },
        ],
    }
    text = candidates_markdown(doc)
    drift = next(line for line in text.splitlines() if "`bias_drift`" in line)
    assert "11→12.5" in drift and "does not hold" in drift and "later" not in drift
    step = next(line for line in text.splitlines() if "`bias_step`" in line)
    assert "does not hold**: later 20→25" in step  # the blocks fall, the later stretch rises
    assert "<img" not in text.replace("`<img src=x onerror=alert(1)>`", "")  # escaped as a code span

    class Cand:
        label, refitted, evidence, holds = "bias_drift", True, "in-sample 10 -> 9 nT", False

    class Diag:
        candidates = [Cand()]

    assert "does not hold on held-out data" in candidate_evidence_markdown(Diag(), "bias_drift")
    wb = bench(warm_data, store=False)
    _click(wb, wb.panels.btn_diagnose)
    assert not wb.panels.btn_add.disabled


# ---------------------------------------------------------------------------------------------------------------
# instrument or record-only
# ---------------------------------------------------------------------------------------------------------------
def test_a_record_only_term_is_marked_and_named_in_the_download(bench):
    drift = EFFECTS["bias_drift"]().perturbation(40.0, None)
    wb = bench(_series(n=400, seed=7, rate_hz=2.0, perturbations=[drift]), store=False)
    assert "record-only" in wb.panels.effect_boxes["bias_drift"].hint.lower()
    assert "instrument term" in wb.panels.effect_boxes["temperature_bias"].hint.lower()
    wb.panels.effect_boxes["bias_drift"].value = True
    wb.panels.effect_boxes["temperature_bias"].value = True
    terms = wb.panels.model_terms.content
    assert "`bias_drift` **record-only**" in terms and "`temperature_bias` **instrument**" in terms
    _click(wb, wb.panels.btn_refine)
    assert wb.ctrl.residual_rms_nT() < 1.1 * SIGMA  # the drift is fitted on this record
    assert "`bias_drift`" in wb.panels.download_info.content and "record-only" in wb.panels.download_info.content
    wb.panels.btn_dl_csv.value = True
    name, content = wb.downloads.last
    text = content.decode()
    assert "# record_only_terms_applied: bias_drift\n" in text
    # the download really holds the record-only correction: its residual is the fit's, at the noise
    corrected = mio.read_csv(io.BytesIO(content), name="corrected.csv")
    residual = corrected.extra["s1_residual_nT"]
    assert np.sqrt(np.mean(residual**2)) < 1.1 * SIGMA
    # only instrument terms: the download says so
    wb.panels.effect_boxes["bias_drift"].value = False
    _click(wb, wb.panels.btn_refine)
    assert "instrument terms only" in wb.panels.download_info.content
    wb.panels.btn_dl_csv.value = True
    assert "# record_only_terms_applied: none\n" in wb.downloads.last[1].decode()


# ---------------------------------------------------------------------------------------------------------------
# data quality
# ---------------------------------------------------------------------------------------------------------------
def test_quality_findings_appear_for_a_file_with_stale_repeats(bench):
    ds = _series(n=300)
    readings = ds.readings_nT.copy()
    readings[:, 1::4] = readings[:, 0:-1:4]  # every fourth sample repeats the one before: 25% stale
    wb = bench(ds.replace(readings_nT=readings), store=False)
    text = wb.panels.quality.content
    assert "**Data quality**: 4 warning(s)" in text  # one per sensor
    stale = [line for line in text.splitlines() if "stale" in line]
    assert len(stale) == 4 and all(line.startswith("- ⚠ **Warning: sensor") for line in stale)
    assert "25% of the readings repeat the previous vector" in text
    assert "counted twice" in text  # what it does to the fit
    clean = bench(_series(n=300), store=False)
    assert (
        "no warning" in clean.panels.quality.content
        and "stale" not in clean.panels.quality.content.split("Checked, nothing to say")[0]
    )


def test_a_fitted_field_outside_the_earths_range_joins_the_quality_list(bench):
    """Readings in the wrong unit (a fifth of nT: a 10 uT field) fit as well as right ones; the quality list says
    the fitted field is no geomagnetic field once the fit has found it."""
    ds = _series(n=300)
    wrong = ds.replace(readings_nT=ds.readings_nT / 5.0, reference_total_nT=None, ref_total_nT=None)
    wb = bench(wrong, store=False)
    assert "fitted field" not in wb.panels.quality.content  # nothing fitted yet
    _click(wb, wb.panels.btn_run)
    assert wb.ctrl.calibration.reference_fitted
    field_uT = wb.ctrl.calibration.reference_total_nT / 1000
    assert 8 < field_uT < 12
    lines = [line for line in wb.panels.quality.content.splitlines() if "fitted field" in line]
    assert len(lines) == 1 and lines[0].startswith("- ⚠ **Warning: the fitted field") and "below" in lines[0]
    right = bench(_series(n=300).replace(reference_total_nT=None, ref_total_nT=None), store=False)
    _click(right, right.panels.btn_run)
    assert "fitted field" not in right.panels.quality.content


# ---------------------------------------------------------------------------------------------------------------
# the user's own effect (a record-only one) in the Model tab and Diagnose
# ---------------------------------------------------------------------------------------------------------------
EXAMPLE = Path(__file__).resolve().parents[1] / "helpers" / "user_effects_example.py"
PUMP = "pump_interference"  # declared transferable = False in the example file


def test_a_user_effect_is_marked_by_its_own_transferable_flag(bench, clean_catalogue):
    from magcal.model import plugins

    plugins.load_effects_file(EXAMPLE)
    pump = EFFECTS[PUMP]().perturbation(4.0, 1)  # 4 nT at 1.3 Hz in sensor 2, as tests/model/test_plugins.py hides it
    data = magcal.simulate_timeseries("chi2017", n_samples=600, seed=3, perturbations=[pump])
    wb = bench(data, store=False)
    assert "record-only" in wb.panels.effect_boxes[PUMP].hint.lower()
    _click(wb, wb.panels.btn_run)
    _click(wb, wb.panels.btn_diagnose)
    top = wb.ctrl.diagnosis.candidates[0]
    assert top.label == f"{PUMP}:2" and top.holds is True  # the user's effect is validated like a built-in one
    assert f"`{PUMP}:2`" in wb.panels.candidates.content
    _click(wb, wb.panels.btn_add)
    assert f"`{PUMP}:2` **record-only**" in wb.panels.model_terms.content
    assert f"`{PUMP}:2`" in wb.panels.download_info.content
    history = wb.ctrl.state.history
    assert history[-1].held_out_rms_nT < history[-2].held_out_rms_nT


def test_a_failed_held_out_check_keeps_the_fit_and_says_why(bench, monkeypatch):
    from magcal.fitting import validation

    def broken(*args, **kwargs):
        raise RuntimeError("no split today")

    monkeypatch.setattr(validation, "validate", broken)
    wb = bench(_series(), store=False)
    _click(wb, wb.panels.btn_run)
    last = wb.ctrl.state.history[-1]
    assert last.step == "calibrate (ML)" and last.held_out_rms_nT is None and last.rms_nT < 1.1 * SIGMA
    assert "held-out validation failed: RuntimeError: no split today" in wb.ctrl.message
    assert wb.ctrl.calibration is not None
