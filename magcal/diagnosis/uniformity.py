"""Whether the field was uniform where a vector record was taken: a residual that follows position.

A magnet, steel or a computer near the path makes the field depend on where the sensor is. That is the place's,
not the instrument's: no calibration term carries it to another record, and a calibration fitted through it is
bent by it. The vector fit's residuals show it:

* with positions (``pos_n_m, pos_e_m, pos_d_m`` or ``lat, lon, alt_m``,
  :func:`magcal.fitting.labfield.positions_ned_m`), the total-field residual (and the world components) follow the
  position: a quadratic function of the position explains much of them, and more than a smooth function of time
  with as many terms does (a drift follows time; an anomaly comes back when the path does);
* without positions, the total-field residual changes over seconds, as the field does at a walking pace past a
  magnet, far beyond its white noise; a hint, since a misfit that follows the turning can do the same.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magcal.fitting.labfield import positions_ned_m

#: Share of the total-field residual's variance a quadratic function of the position must explain to name a field
#: that is not uniform, and by how much more than a smooth function of time with as many terms.
POSITION_R2 = 0.2
POSITION_OVER_TIME = 0.1

#: Without positions: the residual's RMS at periods of about 1 to 20 s must exceed this many times what white noise
#: leaves there, and :data:`WALKING_MIN_NT`.
WALKING_FACTOR = 3.0
WALKING_MIN_NT = 10.0


@dataclass
class Uniformity:
    """What the residuals say about the field's uniformity.

    Attributes
    ----------
    uniform : bool
        False when the residual follows the position (or, without positions, time at a walking pace).
    basis : str
        ``position`` or ``time``: what the test used.
    r2_position, r2_time : float
        Share of the total-field residual's variance a quadratic in position and a degree-9 polynomial in time
        explain (NaN without positions).
    anomaly_rms_nT, anomaly_max_nT : float
        RMS and largest size of the part that follows position (or of the residual at 1-20 s), nT.
    where_m : numpy.ndarray, shape (3,), or None
        Where the largest part lies (north, east, down, m).
    text : str
        The finding in words ("" when uniform).
    """

    uniform: bool
    basis: str
    r2_position: float
    r2_time: float
    anomaly_rms_nT: float
    anomaly_max_nT: float
    where_m: np.ndarray | None
    text: str

    def to_dict(self) -> dict:
        return {
            "uniform": self.uniform,
            "basis": self.basis,
            "r2_position": self.r2_position,
            "r2_time": self.r2_time,
            "anomaly_rms_nT": self.anomaly_rms_nT,
            "anomaly_max_nT": self.anomaly_max_nT,
            "where_m": None if self.where_m is None else self.where_m.tolist(),
            "text": self.text,
        }


def _r2(design, values) -> tuple[float, np.ndarray]:
    """Share of the variance of ``values`` (N, k) the least squares on ``design`` explains, and its prediction."""
    coef, *_ = np.linalg.lstsq(design, values, rcond=None)
    pred = design @ coef
    centred = values - values.mean(axis=0)
    den = float(np.sum(centred**2))
    return (float(np.sum((pred - values.mean(axis=0)) ** 2)) / den if den > 0 else 0.0), pred


def _quadratic(p) -> np.ndarray:
    """1, the three coordinates, their squares and products (N, 10)."""
    n, e, d = p.T
    return np.column_stack([np.ones(len(p)), n, e, d, n * n, e * e, d * d, n * e, n * d, e * d])


def _smooth_in_time(t) -> np.ndarray:
    """Legendre polynomials of degree 0-9 over the record's time (N, 10)."""
    span = float(np.ptp(t)) or 1.0
    x = 2.0 * (t - t.min()) / span - 1.0
    return np.polynomial.legendre.legvander(x, 9)


UNIFORM_TEXT = ""


def field_uniformity(dataset, total_nT, fitted, sigma_total_nT) -> Uniformity:
    """Test the vector fit's total-field residuals for a field that is not uniform.

    Parameters
    ----------
    dataset : Dataset
        The record (its positions and time).
    total_nT : numpy.ndarray, shape (n_sensors, N)
        Total-field residuals ``|B| - F`` of the fit, nT.
    fitted : numpy.ndarray of bool, shape (N,)
        The samples the fit used.
    sigma_total_nT : float
        The total-field residual's white noise (nT).

    Returns
    -------
    Uniformity
    """
    n = dataset.n_samples
    t = dataset.time_s if dataset.time_s is not None else np.arange(n, dtype=float)
    positions = positions_ned_m(dataset)
    use = np.asarray(fitted, bool) & np.all(np.isfinite(total_nT), axis=0)
    if positions is not None:
        use &= np.all(np.isfinite(positions), axis=1)
    if use.sum() < 30:
        return Uniformity(True, "none", float("nan"), float("nan"), 0.0, 0.0, None, UNIFORM_TEXT)
    values = np.asarray(total_nT, dtype=float)[:, use].T
    if positions is None:
        return _walking_pace(t[use], values, sigma_total_nT)
    p = positions[use] - positions[use].mean(axis=0)
    r2_pos, pred = _r2(_quadratic(p), values)
    r2_time, _ = _r2(_smooth_in_time(t[use]), values)
    part = np.linalg.norm(pred - pred.mean(axis=0), axis=1) / np.sqrt(values.shape[1])
    rms, peak = float(np.sqrt(np.mean(part**2))), float(np.max(part))
    where = positions[use][int(np.argmax(part))]
    uniform = not (r2_pos >= POSITION_R2 and r2_pos >= r2_time + POSITION_OVER_TIME and rms > 2 * sigma_total_nT)
    text = UNIFORM_TEXT
    if not uniform:
        text = (
            f"the field is not uniform where you recorded: the total-field residual follows the position (a quadratic "
            f"in it explains {100 * r2_pos:.0f} % of its variance, a smooth function of time {100 * r2_time:.0f} %; "
            f"{rms:.0f} nT RMS, {peak:.0f} nT at most, near N {where[0]:.2f}, E {where[1]:.2f}, D {where[2]:.2f} m): "
            "a local anomaly of the place, not the instrument's; check for a magnet, steel or a computer near the "
            "path. Nothing of it is carried by magcal apply, but it bends a calibration fitted through it: record "
            "away from it, or fit its gradient with the calibration (--field-gradient: record-only)"
        )
    return Uniformity(uniform, "position", r2_pos, r2_time, rms, peak, where, text)


def _walking_pace(t, values, sigma_total_nT) -> Uniformity:
    """Without positions: the residual's part at periods of about 1 to 20 s against white noise's."""
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 1.0
    short, long_ = max(int(round(1.0 / max(dt, 1e-9))), 1), max(int(round(20.0 / max(dt, 1e-9))), 2)
    if len(t) < 2 * long_:
        return Uniformity(True, "time", float("nan"), float("nan"), 0.0, 0.0, None, UNIFORM_TEXT)
    band = _moving_mean(values, short) - _moving_mean(values, long_)
    rms = float(np.sqrt(np.mean(band**2)))
    white = sigma_total_nT * np.sqrt(1.0 / short + 1.0 / long_)
    uniform = not (rms > WALKING_FACTOR * white and rms > WALKING_MIN_NT)
    text = UNIFORM_TEXT
    if not uniform:
        text = (
            f"the total-field residual changes over seconds ({rms:.0f} nT RMS at periods of about 1 to 20 s, "
            f"{rms / max(white, 1e-9):.0f} times what its noise leaves there), as the field does at a walking pace "
            "past a magnet, steel or a computer near the path: the field may not be uniform where you recorded (a "
            "misfit that follows the turning can do the same). Record positions (pos_n_m, pos_e_m, pos_d_m) to tell"
        )
    return Uniformity(uniform, "time", float("nan"), float("nan"), rms, float(np.max(np.abs(band))), None, text)


def _moving_mean(values, width) -> np.ndarray:
    """Centred moving mean (N, k) over ``width`` samples (edges: the mean of what there is)."""
    kernel = np.ones(width)
    out = np.empty_like(values)
    norm = np.convolve(np.ones(len(values)), kernel, mode="same")
    for j in range(values.shape[1]):
        out[:, j] = np.convolve(values[:, j], kernel, mode="same") / norm
    return out
