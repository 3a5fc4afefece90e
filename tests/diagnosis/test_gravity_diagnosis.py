"""The dip's residual as evidence after a gravity calibration: the candidates that move it are found when
the simulated board hides them, and none is claimed when it hides nothing."""

from __future__ import annotations

import pytest

from magcal.data.board import simulate_board
from magcal.diagnosis.gravity import dip_evidence
from magcal.fitting.gravity import fit_gravity


def _evidence(**options):
    ds, _, _ = simulate_board(seed=3, **options)
    return dip_evidence(ds, fit_gravity(ds))


@pytest.mark.parametrize("seed", [3, 8])
def test_nothing_hidden_nothing_claimed(seed):
    ds, _, _ = simulate_board(seed=seed)
    ev = dip_evidence(ds, fit_gravity(ds))
    assert ev.supported == []
    assert any(s.startswith("temperature: not tested") for s in ev.skipped)


def test_temperature_moves_the_dip():
    ev = _evidence(temperature_C=(15.0, 45.0))
    top = ev.candidates[0]
    assert top.name == "temperature" and top.supported and top.explained > 0.5
    assert 40.0 < top.estimate < 100.0  # the bias moves 40 nT/degC per axis (69 nT/degC long), seen across the field


@pytest.mark.parametrize("delay_s", [0.03, -0.03])
def test_a_timing_offset_between_the_sensors_moves_the_dip_while_turning(delay_s):
    ev = _evidence(mag_delay_s=delay_s)
    timing = next(c for c in ev.candidates if c.name == "timing")
    assert timing.supported
    assert timing.estimate == pytest.approx(delay_s, abs=0.5 * abs(delay_s))


def test_without_times_the_timing_is_not_tested():
    ds, _, _ = simulate_board(seed=3, n_poses=15)
    ds = ds.replace(time_s=None)
    ev = dip_evidence(ds, fit_gravity(ds))
    assert "timing: not tested (no sample times)" in ev.skipped
    assert "dip residual (sensor 1)" in ev.text()


def test_magcal_diagnose_gives_the_dip_evidence_of_a_board_with_an_accelerometer(tmp_path, capsys):
    """A record with accelerometer columns and no attitude: the total-field diagnosis and, beside it, the dip's
    residual of the gravity fit with the candidates that move it."""
    import json

    from magcal.cli import main
    from magcal.data.board import simulate_board
    from magcal.data.dataset import dataset_columns, dataset_metadata
    from magcal.data.io import write_csv

    ds, _, _ = simulate_board(seed=3)
    write_csv(tmp_path / "board.csv", dataset_columns(ds), dataset_metadata(ds))
    assert main(["diagnose", str(tmp_path / "board.csv")]) == 0
    assert "dip residual (sensor 1)" in capsys.readouterr().out
    assert main(["diagnose", str(tmp_path / "board.csv"), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["dip_evidence"] and "verdict" in doc
