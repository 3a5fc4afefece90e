"""Whether the field was uniform where a record was taken: a residual that follows position.

A magnet, steel or a computer near the path makes the field depend on where the sensor is. That is the place's,
not the instrument's: no calibration term carries it to another record, and a calibration fitted through it is
bent by it. The total-field residuals of a vector fit, and of a total-field fit of a record with positions, show
it:

* with positions (``pos_n_m, pos_e_m, pos_d_m`` or ``lat, lon, alt_m``,
  :func:`magcal.fitting.labfield.positions_ned_m`), the total-field residual follows the position: where the path
  comes back to a place on another pass, the residual comes back too (a drift follows time, a misfit the attitude,
  or for a total-field fit the field's direction in the sensor's axes; neither comes back with the place). A
  magnet carried with the sensor is an offset in its axes (a misfit or a wander that follows the direction and
  time), not a field of the place: it is not named;
* without positions (vector fits only), the total-field residual changes over seconds, as the field does at a
  walking pace past a magnet, far beyond its white noise; a hint, since a misfit that follows the turning can do
  the same.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from magcal.data.attitude import attitude_rows
from magcal.fitting.labfield import positions_ned_m

#: Share of the total-field residual's variance that the residual at the same place, on another pass, must explain
#: to name a field that is not uniform (and the part that follows the place must exceed the residual's noise).
POSITION_SHARE = 0.25

#: Samples within this distance (m) are at the same place; those closer in time than :data:`APART_S` (s) are the
#: same pass, not a revisit; the mean of up to :data:`NEIGHBOURS` revisits predicts a sample's residual, and at least
#: :data:`MIN_REVISITED` of the samples must have one.
RADIUS_M = 0.05
APART_S = 3.0
NEIGHBOURS = 10
MIN_REVISITED = 0.2

#: Samples within this angle (deg) of each other share an attitude; the residual of the same attitude at other
#: places (at least ``2 RADIUS_M`` away) predicts what a misfit of the calibration leaves, and the residual at the
#: same place must predict at least :data:`OVER_ATTITUDE` more of the variance than that.
ATTITUDE_DEG = 10.0
OVER_ATTITUDE = 0.15

#: A path shorter than this (m, the 5-95 % range along its longest axis) is a record turned in place: its places
#: are its attitudes (the hand moves the sensor as it turns it), and the test is not made.
MIN_PATH_M = 0.2

#: Without positions: the residual's RMS at periods of about 1 to 10 s (:data:`WALKING_PERIODS_S`: a walk past a
#: magnet) must exceed this many times what white noise leaves there, and :data:`WALKING_MIN_NT`.
WALKING_PERIODS_S = (1.0, 10.0)
WALKING_FACTOR = 3.0
WALKING_MIN_NT = 10.0

#: At most this many samples (evenly spaced) enter the test: a survey's positions would otherwise cost a neighbour
#: search per sample (0.3 s for 5000 on a busy 2-core machine, 6.7 s for 20 000).
MAX_SAMPLES = 5_000

#: The finding's text when the field looks uniform (nothing to say).
UNIFORM_TEXT = ""


@dataclass
class Uniformity:
    """What the residuals say about the field's uniformity.

    Attributes
    ----------
    uniform : bool
        False when the residual follows the position (or, without positions, time at a walking pace).
    basis : str
        ``position`` or ``time``: what the test used.
    share_position, share_attitude : float
        Share of the total-field residual's variance its value at the same place on other passes explains, and its
        value in the same attitude at other places (NaN without positions or revisits).
    anomaly_rms_nT, anomaly_max_nT : float
        RMS and largest size of the part that follows position (or of the residual at 1-10 s), nT.
    where_m : numpy.ndarray, shape (3,), or None
        Where the largest part lies (north, east, down, m).
    text : str
        The finding in words ("" when uniform).
    """

    uniform: bool
    basis: str
    share_position: float
    share_attitude: float
    anomaly_rms_nT: float
    anomaly_max_nT: float
    where_m: np.ndarray | None
    text: str

    def to_dict(self) -> dict:
        return {
            "uniform": self.uniform,
            "basis": self.basis,
            "share_position": self.share_position,
            "share_attitude": self.share_attitude,
            "anomaly_rms_nT": self.anomaly_rms_nT,
            "anomaly_max_nT": self.anomaly_max_nT,
            "where_m": None if self.where_m is None else self.where_m.tolist(),
            "text": self.text,
        }


def _revisits(points, t, values, radius, apart=None):
    """What the sample's neighbourhood predicts: the mean residual (N, k) of its :data:`NEIGHBOURS` nearest samples
    within ``radius`` of ``points`` (N, d) that are at least :data:`APART_S` away in time and, with ``apart`` =
    ``(other points (N, e), distance)``, at least that far in those (NaN where there are none)."""
    tree = cKDTree(points)
    k = min(len(points), 16 * NEIGHBOURS)
    dist, idx = tree.query(points, k=k, distance_upper_bound=radius)
    pred = np.full(values.shape, np.nan)
    for i in range(len(points)):
        j = idx[i][np.isfinite(dist[i])]
        j = j[np.abs(t[j] - t[i]) >= APART_S]
        if apart is not None:
            j = j[np.linalg.norm(apart[0][j] - apart[0][i], axis=1) >= apart[1]]
        j = j[:NEIGHBOURS]
        if len(j):
            pred[i] = values[j].mean(axis=0)
    return pred


def _attitude_points(rotation) -> np.ndarray:
    """Quaternions (N, 4) on one half of the sphere (``q`` and ``-q`` are one attitude): their chord distance is
    about half the angle between two attitudes (rad)."""
    q = rotation.as_quat()
    return q * np.where(q[:, 3:4] < 0, -1.0, 1.0)


def _share(pred, values) -> float:
    """Share of the variance of ``values`` (N, k) that ``pred`` explains (1 - residual over total, >= 0)."""
    centred = values - values.mean(axis=0)
    den = float(np.sum(centred**2))
    return max(0.0, 1.0 - float(np.sum((values - pred) ** 2)) / den) if den > 0 else 0.0


def field_uniformity(dataset, total_nT, fitted, sigma_total_nT, directions=None) -> Uniformity:
    """Test a fit's total-field residuals for a field that is not uniform.

    With positions: does the residual come back when the path does? Each sample's residual is predicted by the mean
    residual of its nearest samples in space (within :data:`RADIUS_M`) that are at least :data:`APART_S` away in
    time; a field that depends on the place is predicted, a drift in time or a misfit of the turning is not (the
    same place is revisited at other times, in other attitudes).

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
    directions : numpy.ndarray, shape (N, 3), optional
        For a total-field fit: the field's unit directions in sensor 1's axes. A total-field misfit follows them (not
        the attitude, which the record may lack), so the residual in the same direction at other places is what the
        residual at the same place must beat. Without positions nothing is said (a total-field misfit changes as
        fast as the turning, so a change at a walking pace is no hint; the same-direction revisits of the
        evidence, :func:`magcal.diagnosis.statistics.revisit_forms`, say whether the field changed).

    Returns
    -------
    Uniformity
    """
    n = dataset.n_samples
    t = np.asarray(dataset.time_s, dtype=float) if dataset.time_s is not None else np.arange(n, dtype=float)
    positions = positions_ned_m(dataset)
    use = np.asarray(fitted, bool) & np.all(np.isfinite(total_nT), axis=0)
    if directions is not None:  # a total-field fit: its misfit follows the field's direction in the sensor's axes
        points, radius, alike = np.asarray(directions, dtype=float), np.radians(ATTITUDE_DEG), "field direction"
        use &= np.all(np.isfinite(points), axis=1)
        if positions is None:
            return Uniformity(True, "none", float("nan"), float("nan"), 0.0, 0.0, None, UNIFORM_TEXT)
        use &= np.all(np.isfinite(positions), axis=1)
    else:
        found = attitude_rows(dataset)
        points = np.zeros((n, 4)) if found is None else _attitude_points(found[0])
        radius, alike = np.radians(ATTITUDE_DEG) / 2.0, "attitude"  # chords of quaternions: half the angle
        if positions is not None and found is not None:
            use &= np.all(np.isfinite(positions), axis=1) & found[1]
        elif positions is not None:
            positions = None  # no attitude: revisits cannot be told from a misfit of the turning
    if use.sum() > MAX_SAMPLES:  # evenly thinned: each sample's neighbours are searched one by one
        kept = np.flatnonzero(use)
        use = np.zeros(n, bool)
        use[kept[np.linspace(0, len(kept) - 1, MAX_SAMPLES).astype(int)]] = True
    if use.sum() < 30:
        return Uniformity(True, "none", float("nan"), float("nan"), 0.0, 0.0, None, UNIFORM_TEXT)
    values = np.asarray(total_nT, dtype=float)[:, use].T
    if positions is None:
        return _walking_pace(t[use], values, sigma_total_nT)
    spread = float(np.max(np.percentile(positions[use], 95, axis=0) - np.percentile(positions[use], 5, axis=0)))
    if spread < MIN_PATH_M:  # turned in place: the field was sampled at one place, and a place there is an attitude
        return Uniformity(True, "position", float("nan"), float("nan"), 0.0, 0.0, None, UNIFORM_TEXT)
    p, tt = positions[use], t[use]
    by_place = _revisits(p, tt, values, RADIUS_M)
    by_attitude = _revisits(points[use], tt, values, radius, apart=(p, 2 * RADIUS_M))
    seen = np.all(np.isfinite(by_place), axis=1)
    if seen.sum() < max(30, MIN_REVISITED * len(seen)):
        return Uniformity(True, "position", float("nan"), float("nan"), 0.0, 0.0, None, UNIFORM_TEXT)
    share = _share(by_place[seen], values[seen])
    known = seen & np.all(np.isfinite(by_attitude), axis=1)
    share_att = _share(by_attitude[known], values[known]) if known.sum() >= 30 else 0.0
    part = np.linalg.norm(by_place[seen] - values[seen].mean(axis=0), axis=1) / np.sqrt(values.shape[1])
    rms, peak = float(np.sqrt(np.mean(part**2))), float(np.max(part))
    where = p[seen][int(np.argmax(part))]
    uniform = not (share >= POSITION_SHARE and share >= share_att + OVER_ATTITUDE and rms > sigma_total_nT)
    text = UNIFORM_TEXT
    if not uniform:
        text = (
            f"the field is not uniform where you recorded: the total-field residual follows the position (where the "
            f"path comes back, at least {APART_S:g} s later, the residual there predicts {100 * share:.0f} % of its "
            f"variance, the same {alike} elsewhere {100 * share_att:.0f} %; {rms:.0f} nT RMS, {peak:.0f} nT at most, "
            f"near N {where[0]:.2f}, E {where[1]:.2f}, D {where[2]:.2f} m): a local anomaly of the place, not the instrument's; check for a magnet, steel or a "
            "computer near the path. Nothing of it is carried by magcal apply, but it bends a calibration fitted "
            + (
                "through it: record away from it, or fit its gradient with the calibration (--field-gradient: "
                "record-only)"
                if directions is None
                else "through it: record away from it, or turn the sensor in place about its own centre (a magnet "
                "fixed in the room is a field that changes with the place; one carried with the sensor would be an "
                "offset of the sensor instead)"
            )
        )
    return Uniformity(uniform, "position", share, share_att, rms, peak, where, text)


def _walking_pace(t, values, sigma_total_nT) -> Uniformity:
    """Without positions: the residual's part at periods of about 1 to 10 s against white noise's."""
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 1.0
    short = max(int(round(WALKING_PERIODS_S[0] / max(dt, 1e-9))), 1)
    long_ = max(int(round(WALKING_PERIODS_S[1] / max(dt, 1e-9))), 2)
    if len(t) < 2 * long_:
        return Uniformity(True, "time", float("nan"), float("nan"), 0.0, 0.0, None, UNIFORM_TEXT)
    band = _moving_mean(values, short) - _moving_mean(values, long_)
    rms = float(np.sqrt(np.mean(band**2)))
    white = sigma_total_nT * np.sqrt(1.0 / short + 1.0 / long_)
    uniform = not (rms > WALKING_FACTOR * white and rms > WALKING_MIN_NT)
    text = UNIFORM_TEXT
    if not uniform:
        text = (
            f"the total-field residual changes over seconds ({rms:.0f} nT RMS at periods of about 1 to 10 s, "
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
