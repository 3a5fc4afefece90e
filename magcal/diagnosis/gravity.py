"""The dip's residual as evidence, and the effects that move it: a gravity calibration's diagnosis.

After a gravity fit (:mod:`magcal.fitting.gravity`) the dip ``asin(m . d / |m|)`` should be the inclination at every
still sample; what is left is the sensors' noise (and the hand's acceleration on samples that were not quite still),
or an effect the model lacks. Three move the dip in ways one can test for:

``temperature``
    a bias that follows the temperature moves the field by ``-W beta (T - T0)``, whose part across the field in the
    vertical plane is the dip's change: the residual follows ``(T - mean T)`` times the dip's gradient ``g = (d -
    (u . d) u) / (|m| cos dip)`` (three regressors, their coefficients the bias's change in nT per degC in the
    board's axes; needs the ``temperature_C`` channel);
``nonlinearity``
    a magnetometer (or accelerometer) whose response is not linear bends the directions by a pattern over the
    sphere: the residual follows the degree-2 and degree-3 harmonics of the field's direction;
``timing``
    the magnetometer's samples older (or younger) than the accelerometer's by ``tau`` while the board turns: the
    field moves between the two, ``dip(t) - I ~ -tau (d dip / dt)`` at constant gravity, seen on samples that turn
    while the accelerometer still reads ``|a|`` near ``g`` (needs times).

Each is a least-squares regression of the residual on its regressors against a constant, with an F-test, the
fraction of the residual's variance it explains and its coefficient. A residual correlated in time (a slow drift)
makes the p-values optimistic: read them with the explained fraction. :func:`dip_evidence` gives them ranked, as a
diagnosis (:class:`magcal.diagnosis.base.DiagnosisBase`) whose verdict is ``not_judged``: no candidate is judged on
held-out data, so none is advised; the verdict of a scalar or vector calibration is :mod:`magcal.diagnosis.verdict`'s,
this module stands beside it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np
from scipy import stats

from magcal.data.accelerometer import STANDARD_GRAVITY_M_S2, accelerometer, find_still
from magcal.data.dataset import Dataset
from magcal.diagnosis.base import DiagnosisBase
from magcal.geometry.heading import dip_deg

#: Candidates, in the order they are tried.
CANDIDATES = ("temperature", "nonlinearity", "timing")

#: A candidate is reported as supported when its p-value is below this and it explains at least
#: :data:`MIN_EXPLAINED` of the dip residual's variance.
P_SUPPORTED = 1e-3
MIN_EXPLAINED = 0.02

#: The samples the timing candidate uses: turning at least this fast (deg/s) with ``|a|`` within this fraction of g.
TIMING_MIN_TURN_DPS = 10.0
TIMING_NEAR_G = 0.03


@dataclass
class DipCandidate:
    """One effect tested against the dip's residual.

    Attributes
    ----------
    name : str
    n : int
        Samples the regression used.
    f_statistic, p_value : float
    explained : float
        Fraction of the residual's variance the regressors explain.
    estimate : float or None
        The coefficient, when the candidate has one (temperature: deg of dip per degC; timing: the delay in s).
    unit : str
    supported : bool
    """

    name: str
    n: int
    f_statistic: float
    p_value: float
    explained: float
    estimate: float | None = None
    unit: str = ""
    supported: bool = False

    def text(self) -> str:
        est = "" if self.estimate is None else f"; estimate {self.estimate:+.4g} {self.unit}"
        mark = "supported" if self.supported else "not supported"
        return (
            f"{self.name}: explains {100 * self.explained:.1f} % of the dip's variance over {self.n} samples "
            f"(F = {self.f_statistic:.3g}, p = {self.p_value:.2g}){est}: {mark}"
        )

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class DipEvidence(DiagnosisBase):
    """The dip's residual after a gravity calibration and the candidates that move it: a diagnosis
    (:class:`magcal.diagnosis.base.DiagnosisBase`) that judges nothing held out, so its verdict is ``not_judged``
    and it advises nothing (``explained_by`` empty); the supported candidates are named in the summary.

    Attributes
    ----------
    residual_deg : numpy.ndarray
        Dip minus the inclination (deg) at the still samples (``rows``), sensor ``sensor``.
    rows : numpy.ndarray of int
    sd_deg : float
    candidates : list of DipCandidate
        Ranked: supported first, then by p-value.
    skipped : list of str
        Candidates the data cannot test, with why.
    sensor : int
        Which magnetometer (0-based).
    """

    residual_deg: np.ndarray
    rows: np.ndarray
    sd_deg: float
    candidates: list
    skipped: list = field(default_factory=list)
    sensor: int = 0

    #: No held-out judgement, no noise figure, no structure test and no fits of its own.
    verdict = "not_judged"
    explained_by: list = field(default_factory=list, init=False, repr=False)
    remaining: list = field(default_factory=list, init=False, repr=False)
    notes: list = field(default_factory=list, init=False, repr=False)
    noise = None
    elapsed_s = 0.0

    @property
    def supported(self) -> list:
        return [c for c in self.candidates if c.supported]

    @property
    def summary(self) -> str:  # type: ignore[override]
        """The dip's residual and the candidates supported in-sample (not advised: none is judged held out)."""
        named = ", ".join(c.name for c in self.supported)
        found = (
            f"supported in-sample, not advised until judged held out: {named}"
            if named
            else "no candidate explains a significant part of it"
        )
        return (
            f"dip residual {self.sd_deg:.3f} deg RMS over {self.rows.size} still samples; {found} (the dip's candidates "
            "are tested in-sample only)"
        )

    @property
    def warnings(self) -> list:  # type: ignore[override]
        """The candidates the data cannot test, with why."""
        return list(self.skipped)

    @property
    def evidence(self) -> dict:  # type: ignore[override]
        """Plot data: the dip's residual (deg) at the still samples' rows."""
        return {"rows": self.rows, "residual_deg": self.residual_deg}

    def text(self, limit: int = 12) -> str:
        lines = [
            f"dip residual (sensor {self.sensor + 1}): {self.sd_deg:.3f} deg RMS over {self.rows.size} still samples"
        ]
        lines += [f"  {c.text()}" for c in self.candidates[:limit]]
        lines += [f"  {s}" for s in self.skipped]
        return "\n".join(lines) + "\n"

    def _own_dict(self) -> dict:
        return {
            "sensor": self.sensor + 1,
            "sd_deg": self.sd_deg,
            "n": int(self.rows.size),
            "skipped": list(self.skipped),
        }


def _test(name, residual, regressors, estimate_index=None, unit="") -> DipCandidate:
    """F-test of ``residual ~ 1 + regressors`` against ``residual ~ 1``."""
    r = np.asarray(residual, float)
    x = np.column_stack([np.ones(r.size), np.asarray(regressors, float).reshape(r.size, -1)])
    q = x.shape[1] - 1
    coef, *_ = np.linalg.lstsq(x, r, rcond=None)
    rss1 = float(np.sum((r - x @ coef) ** 2))
    rss0 = float(np.sum((r - r.mean()) ** 2))
    dof = r.size - q - 1
    if dof <= 0 or rss0 <= 0:
        return DipCandidate(name, int(r.size), 0.0, 1.0, 0.0)
    f_stat = ((rss0 - rss1) / q) / max(rss1 / dof, 1e-300)
    p = float(stats.f.sf(f_stat, q, dof))
    explained = max(0.0, 1.0 - rss1 / rss0)
    est = None if estimate_index is None else float(coef[1 + estimate_index])
    return DipCandidate(
        name, int(r.size), float(f_stat), p, explained, est, unit, p < P_SUPPORTED and explained >= MIN_EXPLAINED
    )


def _harmonics(u) -> np.ndarray:
    """Degree-2 and degree-3 real harmonics (unnormalised, 5 + 7) of unit vectors (N, 3)."""
    x, y, z = u[:, 0], u[:, 1], u[:, 2]
    deg2 = [x * y, x * z, y * z, x * x - y * y, 3 * z * z - 1]
    deg3 = [
        x * (x * x - 3 * y * y),
        y * (3 * x * x - y * y),
        z * (x * x - y * y),
        x * y * z,
        x * (5 * z * z - 1),
        y * (5 * z * z - 1),
        z * (5 * z * z - 3),
    ]
    return np.column_stack(deg2 + deg3)


def dip_evidence(dataset: Dataset, fit, sensor=0, accel_units=None) -> DipEvidence:
    """The dip's residual of a gravity fit and the candidates that move it (see the module docstring).

    Parameters
    ----------
    dataset : Dataset
        The record fitted.
    fit : magcal.fitting.gravity.GravityFitResult
    sensor : int
        Which magnetometer (0-based).
    accel_units : str, optional
        The unit of unmarked ``ax, ay, az`` columns.
    """
    cal = fit.calibration
    accel = accelerometer(dataset, units=accel_units)
    if accel is None:
        raise ValueError("the dataset has no accelerometer columns")
    f = cal.accelerometer.correct(accel.m_s2)
    m = cal.correct(dataset, force=True)[sensor]
    dip = dip_deg(f, m)
    still = fit.still.mask & (fit.fitted if fit.fitted is not None else True) & np.isfinite(dip)
    rows = np.flatnonzero(still)
    residual = dip[rows] - fit.inclination_deg
    candidates, skipped = [], []
    if dataset.temperature_C is not None and np.ptp(dataset.temperature_C[rows]) > 0:
        t = dataset.temperature_C[rows]
        grad = _dip_gradient(f[rows], m[rows])
        cand = _test("temperature", residual, np.degrees(grad * (t - t.mean())[:, None]))
        coef = np.linalg.lstsq(
            np.column_stack([np.ones(t.size), np.degrees(grad * (t - t.mean())[:, None])]), residual, rcond=None
        )[0][1:]
        cand.estimate, cand.unit = float(np.linalg.norm(coef)), "nT per degC (the bias's change across the field)"
        candidates.append(cand)
    else:
        skipped.append("temperature: not tested (no temperature channel, or it does not change)")
    u = m[rows] / np.linalg.norm(m[rows], axis=1, keepdims=True)
    candidates.append(_test("nonlinearity", residual, _harmonics(u)))
    timing = _timing_candidate(dataset, f, m, fit.inclination_deg)
    if isinstance(timing, str):
        skipped.append(timing)
    else:
        candidates.append(timing)
    candidates.sort(key=lambda c: (not c.supported, c.p_value))
    sd = float(np.sqrt(np.mean(residual**2))) if residual.size else float("nan")
    return DipEvidence(residual, rows, sd, candidates, skipped, sensor)


def _dip_gradient(f, m) -> np.ndarray:
    """The dip's gradient (rad per nT, (N, 3)) with respect to the field ``m`` at gravity ``f`` held."""
    mn = np.linalg.norm(m, axis=1)
    u = m / mn[:, None]
    d = -f / np.linalg.norm(f, axis=1)[:, None]
    s = np.sum(u * d, axis=1)
    return (d - s[:, None] * u) / (mn * np.sqrt(np.clip(1.0 - s * s, 1e-12, None)))[:, None]


def _timing_candidate(dataset, f, m, inclination_deg):
    """The timing candidate on turning samples whose ``|a|`` is near ``g``, or why it cannot be tested."""
    t = dataset.time_s
    if t is None:
        return "timing: not tested (no sample times)"
    still = find_still(dataset)
    rate = still.turn_dps
    if rate is None:
        return "timing: not tested (no gyro or attitude to tell the turns)"
    fn = np.linalg.norm(f, axis=1)
    mn = np.linalg.norm(m, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        u = m / mn[:, None]
        d = -f / fn[:, None]
        du = np.gradient(u, t, axis=0)
        s = np.sum(u * d, axis=1)
        dip = np.arcsin(np.clip(s, -1, 1))
        # d dip / dt with gravity held: the field's own turn projected on the dip's gradient
        grad = (d - s[:, None] * u) / np.cos(dip)[:, None]
        rate_dip = np.sum(grad * du, axis=1)
    use = (
        (np.asarray(rate, float) > TIMING_MIN_TURN_DPS)
        & (np.abs(fn / STANDARD_GRAVITY_M_S2 - 1.0) < TIMING_NEAR_G)
        & np.isfinite(rate_dip)
        & np.isfinite(dip)
    )
    if use.sum() < 30:
        return f"timing: not tested ({int(use.sum())} turning samples with |a| near g; 30 needed)"
    residual = np.degrees(dip[use]) - inclination_deg
    cand = _test("timing", residual, -np.degrees(rate_dip[use]), 0, "s (magnetometer later than the accelerometer)")
    return cand
