"""Every effect's parameters have a physical domain (:meth:`magcal.model.terms.Effect.domain`): the fits keep them in
it, the diagnoses never recommend a candidate held on one of its bounds, and whatever ``magcal calibrate`` writes,
``Calibration.load`` and ``magcal apply`` accept.

Found on real records of a hand-turned IMU with motion-capture attitude: the vector diagnosis recommended
``hysteresis`` with loop half-widths of -510, -327, -217 nT and a nonlinearity of 756 290 ppm; ``magcal calibrate``
wrote such a calibration and ``magcal apply`` then refused it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from magcal.calibration.calibration import Calibration
from magcal.checks.reference import resolve_vector_reference
from magcal.cli import main
from magcal.core.errors import MagcalError
from magcal.data.dataset import dataset_columns, dataset_metadata
from magcal.data.io import write_csv
from magcal.data.simulation import chi2017_truth, simulate_timeseries
from magcal.data.vehicle import simulate_vehicle, vehicle_truth
from magcal.diagnosis.vector import diagnose_vector
from magcal.fitting.fitter import fit
from magcal.fitting.vector import fit_vector
from magcal.model.effects import NONLINEARITY_LIMIT_PPM, smoothed_readings, time_derivative
from magcal.model.plugins import load_effects_file, unregister
from magcal.model.terms import BOUND_PULL_Z, EFFECTS, Domain, Model, fitted_outside_domain, outside_domain

USER_EFFECTS = Path(__file__).resolve().parents[1] / "helpers" / "user_effects_example.py"

#: Loop half-width (nT) of the hysteresis the tests hide with the wrong sign: the output leads the field.
LEADING_nT = 40.0


def _leading(ds, width_nT=LEADING_nT):
    """``ds`` whose every axis reads ``width_nT`` ahead of the field's direction of change: a hysteresis loop of
    negative half-width, which no magnetometer has (the fit's hysteresis would come out negative)."""
    y = np.array(ds.readings_nT, dtype=float)
    for s in range(ds.n_sensors):
        y[s] += width_nT * np.sign(time_derivative(smoothed_readings(y[s], ds.time_s), ds.time_s))
    return ds.replace(readings_nT=y)


def _nonlinear(ds, ppm=20 * NONLINEARITY_LIMIT_PPM):
    """``ds`` with a quadratic and a cubic nonlinearity of ``ppm`` of the field on every axis: far past any sensor's."""
    y = np.array(ds.readings_nT, dtype=float)
    for s in range(ds.n_sensors):
        f = float(np.median(np.linalg.norm(y[s], axis=1)))
        u = (y[s] - np.mean(y[s], axis=0)) / f
        y[s] += 1e-6 * ppm * f * (u**2 + u**3)
    return ds.replace(readings_nT=y)


def _hot_scale(ds, ppm_per_K=5e4):
    """``ds`` whose scale changes by ``ppm_per_K`` (5 %/K): past :data:`TEMPERATURE_SCALE_LIMIT_PPM_PER_K`."""
    y = np.array(ds.readings_nT, dtype=float)
    dT = np.asarray(ds.temperature_C, dtype=float) - float(np.mean(ds.temperature_C))
    centre = np.mean(y, axis=1, keepdims=True)
    return ds.replace(readings_nT=centre + (y - centre) * (1 + 1e-6 * ppm_per_K * dT)[None, :, None])


#: How each bounded effect is pushed past its domain in the simulated record.
PUSHES = {
    "hysteresis": _leading,
    "nonlinearity_quadratic": _nonlinear,
    "nonlinearity_cubic": _nonlinear,
    "temperature_scale": _hot_scale,
}


@pytest.fixture(scope="module")
def user_effect():
    """The user's own effect of tests/helpers/user_effects_example.py, registered for this module's tests."""
    names = load_effects_file(USER_EFFECTS)
    yield names[0]
    for name in names:  # no other module's tests see it (the diagnosis tries every registered effect)
        unregister(name)


def _vehicle(n=600, seed=1):
    ds, _ = simulate_vehicle(vehicle_truth(seed=3), seed=seed, n=n, log_current=True, temperature=True)
    return ds


def _write(path, ds):
    write_csv(path, dataset_columns(ds), dataset_metadata(ds))
    return str(path)


# ---------------------------------------------------------------------------------------------------------------
# the declaration
# ---------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(EFFECTS))
def test_every_effect_declares_a_domain_that_holds_zero_and_its_check_refuses_values_past_it(name):
    effect = EFFECTS[name]()
    domain = effect.domain()
    q = len(effect.param_names())
    assert isinstance(domain, Domain) and domain.lower.shape == domain.upper.shape == (q,)
    assert np.all(domain.lower <= 0) and np.all(domain.upper >= 0), "the model without the effect is in its domain"
    assert (domain.why != "") == domain.bounded, "a bound says why"
    effect.check_params(np.zeros(q))
    for k in range(q):
        for bound in (domain.lower[k], domain.upper[k]):
            if np.isfinite(bound):
                past = np.zeros(q)
                past[k] = bound + np.sign(bound or -1.0) * max(1.0, abs(bound))
                with pytest.raises(MagcalError, match="is not physical"):
                    effect.check_params(past)
                at = np.zeros(q)
                at[k] = bound
                assert effect.check_params(at)[k] == bound  # the bound itself is in the domain
                assert effect.param_names()[k] in outside_domain(effect, at)


def test_the_domains_are_the_physics_of_each_effect():
    assert EFFECTS["hysteresis"]().domain().lower.tolist() == [0.0, 0.0, 0.0]
    quadratic = EFFECTS["nonlinearity_quadratic"](field_magnitude_nT=20_000.0)
    assert quadratic.domain().upper == pytest.approx(np.full(3, 1e-6 * NONLINEARITY_LIMIT_PPM * 20_000.0))
    offset = EFFECTS["attitude_time_offset"]()
    assert not offset.domain().bounded  # before it has seen a record
    offset.configure(_vehicle(n=300))
    assert 0 < offset.max_delay_ms < np.inf and offset.domain().upper[0] == offset.max_delay_ms


# ---------------------------------------------------------------------------------------------------------------
# the fits keep the domain, the diagnoses never recommend a candidate held on a bound
# ---------------------------------------------------------------------------------------------------------------


def test_a_vector_fit_of_a_leading_field_holds_the_hysteresis_at_zero_and_the_diagnosis_refuses_it(monkeypatch):
    ds = _leading(_vehicle(n=1500))
    ref = resolve_vector_reference(ds)
    base = fit_vector(ds, ref, warn=False)
    with monkeypatch.context() as m:  # without its domain the fit finds the negative widths of the issue
        m.setattr(EFFECTS["hysteresis"], "domain", lambda self: Domain.free(3))
        free = fit_vector(ds, ref, effects=["hysteresis"], warn=False).calibration.effect_values["hysteresis:1"]
    assert np.all(free < -0.5 * LEADING_nT)
    fitted = fit_vector(ds, ref, effects=["hysteresis"], warn=False)
    widths = fitted.calibration.effect_values["hysteresis:1"]
    assert np.all(widths == 0.0)  # held on the bound: the model is the base model's
    assert fitted.sensors[0].rms_vector_nT == pytest.approx(base.sensors[0].rms_vector_nT, rel=0.01)
    d = diagnose_vector(ds, ref, candidates=["hysteresis"], validate=False)
    (c,) = [c for c in d.candidates if c.effect == "hysteresis"]
    assert "h_x_nT" in c.not_physical and "cannot lead" in c.not_physical
    assert not c.supported and not c.recommended and "not physical here" in c.why
    assert "hysteresis" not in d.explained_by and "hysteresis" not in d.summary.split("describes")[0]
    assert c.to_dict()["not_physical"] == c.not_physical and "not physical here" in d.text()


def test_a_total_field_fit_and_its_diagnosis_hold_the_hysteresis_of_a_leading_field_at_zero():
    from magcal.diagnosis.verdict import diagnose

    ds = _leading(simulate_timeseries("chi2017", n_samples=800, seed=4).subset(np.arange(800)), 15.0)
    f = fit(ds, Model.from_names(["hysteresis"], ds.n_sensors))
    values = {k: np.asarray(v) for k, v in f.calibration.effect_values.items()}
    assert all(np.all(v >= 0) for v in values.values())
    assert fitted_outside_domain(f.calibration.model, values)
    d = diagnose(ds, candidates=["hysteresis"])
    held = [c for c in d.candidates if c.effect == "hysteresis" and c.refitted]
    assert held and all(c.not_physical and not c.recommendable for c in held)
    assert not any(label.startswith("hysteresis") for label in d.explained_by)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_an_axis_without_hysteresis_sits_on_the_bound_by_noise_and_is_not_called_unphysical(seed):
    """A loop on x only: y and z sit at 0 (noise pulls them below on about half the records) and the effect is
    physical; only a pull of more than BOUND_PULL_Z standard deviations past the bound is not."""
    ds = simulate_timeseries(
        chi2017_truth(1),
        n_samples=800,
        noise_nT=3.0,
        seed=seed,
        perturbations=[EFFECTS["hysteresis"]().perturbation([6.0, 0.0, 0.0])],
    )
    f = fit(ds, Model.from_names(["hysteresis"], 1), warn=False)
    (label,) = f.calibration.effect_values
    values = f.calibration.effect_values[label]
    assert values[0] > 3.0 and np.all(values >= 0)
    pulls = f.bound_pull_z.get(label, np.zeros(3))
    assert np.all(pulls[values == 0.0] < BOUND_PULL_Z)
    assert not fitted_outside_domain(f.calibration.model, f.calibration.effect_values, pulls=f.bound_pull_z)
    assert not any("held it on the bound" in n.text for n in f.notes)
    leading = _leading(ds, 15.0)  # the same record leading by 15 nT: pulled far past the bound, and said
    g = fit(leading, Model.from_names(["hysteresis"], 1), warn=False)
    assert fitted_outside_domain(g.calibration.model, g.calibration.effect_values, pulls=g.bound_pull_z)
    assert any("held it on the bound" in n.text for n in g.notes)


# ---------------------------------------------------------------------------------------------------------------
# calibrate -> save -> load -> apply over the catalogue
# ---------------------------------------------------------------------------------------------------------------

VECTOR = sorted(n for n, cls in EFFECTS.items() if "vector" in cls.modes and cls.stage == "raw")
SCALAR_ONLY = sorted(n for n, cls in EFFECTS.items() if n not in VECTOR and "scalar" in cls.modes)


def _round_trip(tmp_path, csv, name, extra=(), fit_options=()):
    """``magcal calibrate`` with the effect, ``Calibration.load`` and ``magcal apply``: the parameters written, as
    read back. A sensor the fit marked not determined (a record pushed far past the domain may leave the base terms
    undetermined) is refused by apply for that reason alone, and applied with ``--force``."""
    cal = tmp_path / f"{name}.json"
    assert main(["calibrate", csv, "--effects", name, "-o", str(cal), *extra, *fit_options]) == 0
    loaded = Calibration.load(cal)
    out = tmp_path / f"{name}_cal.csv"
    apply = ["apply", str(cal), csv, "-o", str(out), "--no-progress", *extra]
    if loaded.undetermined():
        assert main(apply) != 0  # refused as not determined, not as not physical
        apply.append("--force")
    assert main(apply) == 0
    import pandas as pd

    frame = pd.read_csv(out, comment="#")
    assert np.all(np.isfinite(frame[[c for c in frame.columns if c.endswith("_cal")]].to_numpy()))
    assert loaded.model is not None
    return loaded


@pytest.mark.parametrize("name", VECTOR)
def test_vector_calibrate_save_load_apply_round_trip_with_every_effect_pushed_to_its_bound(tmp_path, name):
    ds = PUSHES.get(name, lambda d: d)(_vehicle())
    loaded = _round_trip(tmp_path, _write(tmp_path / "flight.csv", ds), name)
    if name in PUSHES:  # the data pull it out of its domain: the fit held it on the bound, and that was written
        assert fitted_outside_domain(loaded.model, loaded.effect_values, name)


@pytest.mark.parametrize("name", SCALAR_ONLY + ["hysteresis", "nonlinearity_cubic"])
def test_scalar_calibrate_save_load_apply_round_trip(tmp_path, name):
    ds = simulate_timeseries("chi2017", n_samples=600, seed=2)
    ds = PUSHES.get(name, lambda d: d)(ds)
    loaded = _round_trip(tmp_path, _write(tmp_path / "tumble.csv", ds), name, fit_options=["--mode", "scalar"])
    if name in PUSHES:
        assert fitted_outside_domain(loaded.model, loaded.effect_values, name)


def test_a_users_effect_round_trips_too(tmp_path, user_effect):
    csv = _write(tmp_path / "flight.csv", _vehicle())
    _round_trip(tmp_path, csv, user_effect, ["--effects-file", str(USER_EFFECTS)])
