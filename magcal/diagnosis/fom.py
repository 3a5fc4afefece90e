"""The figure of merit of a compensation: the maneuvers of a compensation box found in the record, and the
12 peak-to-peak values of the band-passed signal in them (SEG's FOM), before and after, with the improvement ratio.

Figure of merit
    The box flies four headings, and on each rolls, pitches and yaws (12 maneuvers). Band-pass the compensated
    scalar (0.1-0.9 Hz, as the fit: the geology and drift below, the noise above) and take the peak-to-peak value
    in each maneuver; the FOM is their sum (nT). The same on the uncompensated scalar is the FOM before.
Improvement ratio
    The standard deviation of the band-passed uncompensated scalar over that of the band-passed compensated one,
    over the maneuvers' samples.

The maneuvers (:func:`find_maneuvers`) come from the attitude (roll, pitch, yaw in deg) when the record has it:
stretches where one angle oscillates about its running mean by more than ``min_amplitude_deg``, named by the angle
that moves most for its nominal amplitude (roll 10, pitch 5, yaw 5 deg), outside the turns between the legs
(heading changing by more than 15 deg within 10 s). Without attitude, from the fluxgate's direction: the heading
is ``atan2(-u_y, u_x)`` (magnetic, level flight), a maneuver moves the direction by more than
``min_amplitude_deg``, and the stretches of a leg are named in the order a box flies them (roll, pitch, yaw): the
direction alone cannot tell a roll from a yaw at some headings (both turn the field about the same body axis).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
from scipy.ndimage import maximum_filter1d

from magcal.core.errors import MagcalError
from magcal.core.stats import moving_mean
from magcal.model.tolles_lawson import DEFAULT_PASSBAND_HZ, bandpass

#: Maneuver kinds in the order a box flies them, and their nominal amplitudes (deg).
KINDS = ("roll", "pitch", "yaw")
NOMINAL_AMPLITUDE_DEG = (10.0, 5.0, 5.0)

__all__ = ["FOMReport", "FOMTable", "Maneuver", "figure_of_merit", "find_maneuvers", "fom_report", "improvement_ratio"]


@dataclass(frozen=True)
class Maneuver:
    """One maneuver found in a record: the leg's heading (deg, measured), kind, samples ``[start, stop)``."""

    heading_deg: float
    kind: str
    start: int
    stop: int


@dataclass
class FOMTable:
    """Peak-to-peak values (nT) of a band-passed signal per maneuver, and their sum (the FOM).

    The unit-neutral accessors of :class:`magcal.diagnosis.fom_protocol.FOMFigures`: :attr:`fom` is
    :attr:`fom_nT`, :attr:`per_maneuver` is :attr:`peak_to_peak_nT`, :attr:`unit` ``"nT"``.
    """

    maneuvers: list[Maneuver]
    peak_to_peak_nT: np.ndarray

    unit: ClassVar[str] = "nT"

    @property
    def fom_nT(self) -> float:
        return float(np.sum(self.peak_to_peak_nT))

    @property
    def fom(self) -> float:
        """:attr:`fom_nT` (nT)."""
        return self.fom_nT

    @property
    def per_maneuver(self) -> np.ndarray:
        """:attr:`peak_to_peak_nT` (nT per maneuver)."""
        return np.asarray(self.peak_to_peak_nT, dtype=float)

    def to_dict(self) -> dict:
        return {
            "fom_nT": self.fom_nT,
            "rows": [
                {
                    "heading_deg": round(m.heading_deg, 1),
                    "kind": m.kind,
                    "start": m.start,
                    "stop": m.stop,
                    "p2p_nT": float(v),
                }
                for m, v in zip(self.maneuvers, self.peak_to_peak_nT)
            ],
        }


@dataclass
class FOMReport:
    """The FOM before and after a compensation, and the improvement ratio (nT:
    :class:`magcal.diagnosis.fom_protocol.FOMComparison`)."""

    before: FOMTable
    after: FOMTable
    improvement_ratio: float
    notes: list[str] = field(default_factory=list)

    unit: ClassVar[str] = "nT"

    def to_dict(self) -> dict:
        return {
            "fom_before_nT": self.before.fom_nT,
            "fom_after_nT": self.after.fom_nT,
            "improvement_ratio": float(self.improvement_ratio),
            "before": self.before.to_dict(),
            "after": self.after.to_dict(),
            "notes": list(self.notes),
        }

    def text(self) -> str:
        """The table: one line per maneuver, peak-to-peak before and after (nT), then the sums and the ratio."""
        lines = [f"{'heading':>8} {'maneuver':>8} {'before nT':>10} {'after nT':>9}"]
        for m, b, a in zip(self.after.maneuvers, self.before.peak_to_peak_nT, self.after.peak_to_peak_nT):
            lines.append(f"{m.heading_deg:8.0f} {m.kind:>8} {b:10.3f} {a:9.3f}")
        lines.append(f"{'FOM':>17} {self.before.fom_nT:10.3f} {self.after.fom_nT:9.3f}")
        lines.append(f"improvement ratio {self.improvement_ratio:.1f}")
        return "\n".join(lines + self.notes)


def _wrap_deg(angle):
    return (np.asarray(angle) + 180.0) % 360.0 - 180.0


def _smoothed_heading(heading_deg, window: int) -> np.ndarray:
    rad = np.radians(heading_deg)
    return np.degrees(np.arctan2(moving_mean(np.sin(rad), window), moving_mean(np.cos(rad), window)))


def _turning(heading_s, half: int) -> np.ndarray:
    """Samples where the smoothed heading changes by more than 15 deg between ``half`` samples before and after."""
    n = heading_s.size
    idx = np.arange(n)
    change = _wrap_deg(heading_s[np.minimum(idx + half, n - 1)] - heading_s[np.maximum(idx - half, 0)])
    return np.abs(change) > 15.0


def _runs(flags) -> list[tuple[int, int]]:
    edges = np.flatnonzero(np.diff(np.concatenate([[0], np.asarray(flags).astype(int), [0]])))
    return list(zip(edges[::2].tolist(), edges[1::2].tolist()))


def _channels(flux_nT, attitude_deg):
    """(heading deg, channels (3, N) in deg, whether they are roll, pitch, yaw)."""
    if attitude_deg is not None:
        att = np.asarray(attitude_deg, dtype=float)
        if att.ndim != 2 or att.shape[1] != 3 or not np.isfinite(att).all():
            raise MagcalError("the attitude must be an (N, 3) array of finite roll, pitch, yaw in degrees")
        unwrapped = np.degrees(np.unwrap(np.radians(att[:, 2])))
        return att[:, 2], np.vstack([att[:, 0], att[:, 1], unwrapped]), True
    if flux_nT is None:
        raise MagcalError("give the attitude (roll, pitch, yaw) or the fluxgate's vector to find the maneuvers")
    flux = np.asarray(flux_nT, dtype=float)
    if flux.ndim != 2 or flux.shape[1] != 3 or not np.isfinite(flux).all():
        raise MagcalError("the fluxgate's vector must be an (N, 3) array of finite nT to find the maneuvers")
    u = flux / np.linalg.norm(flux, axis=1, keepdims=True)
    return np.degrees(np.arctan2(-u[:, 1], u[:, 0])), np.degrees(u.T), False


def find_maneuvers(
    sample_rate_hz: float,
    *,
    attitude_deg=None,
    flux_nT=None,
    min_amplitude_deg: float = 1.0,
    min_duration_s: float = 6.0,
    window_s: float = 8.0,
) -> list[Maneuver]:
    """The maneuvers of a compensation box, found in the attitude (preferred) or the fluxgate's direction.

    The legs are the stretches between turns (the heading, smoothed over ``window_s``, changing by more than
    15 deg within 10 s); in a leg, a maneuver is a stretch where the attitude (or the field's direction) swings
    about the leg's level by more than ``min_amplitude_deg`` and crosses it at least three times.

    Parameters
    ----------
    sample_rate_hz : float
    attitude_deg : array_like, shape (N, 3), optional
        Roll, pitch, yaw (deg).
    flux_nT : array_like, shape (N, 3), optional
        The fluxgate's vector (nT), used without attitude.
    min_amplitude_deg : float
        A maneuver's smallest amplitude (deg of attitude, or of the field's direction).
    min_duration_s : float
        A maneuver's shortest duration (s).
    window_s : float
        The heading's smoothing window (s): a maneuver's period or more.

    Returns
    -------
    list of Maneuver
        In time order; at most one of each kind per leg (the longest).
    """
    heading, channels, named = _channels(flux_nT, attitude_deg)
    rate = float(sample_rate_hz)
    heading_s = _smoothed_heading(heading, max(3, int(round(window_s * rate))))
    turning = _turning(heading_s, int(round(5.0 * rate)))
    found = []
    for start, stop in _runs(~turning):
        if stop - start >= 2 * min_duration_s * rate:
            leg = _leg_maneuvers(channels[:, start:stop], named, rate, min_amplitude_deg, min_duration_s)
            rad = np.radians(heading_s[start:stop])
            h = float(np.degrees(np.arctan2(np.sin(rad).mean(), np.cos(rad).mean())) % 360.0)
            found += [Maneuver(h, KINDS[k], int(start + a), int(start + b)) for a, b, k in leg]
    return found


def _leg_maneuvers(channels, named: bool, rate: float, min_amplitude_deg: float, min_duration_s: float):
    """(start, stop, kind index) of one leg's maneuvers, in time order, the longest of each kind."""
    deviation = channels - np.median(channels, axis=1, keepdims=True)
    envelope = maximum_filter1d(np.abs(deviation), max(3, int(round(4.0 * rate))), axis=1)
    if named:
        scored = envelope / np.asarray(NOMINAL_AMPLITUDE_DEG)[:, None]
        active = envelope.max(axis=0) > min_amplitude_deg
        dominant = np.argmax(scored, axis=0)
    else:
        active = np.linalg.norm(envelope, axis=0) > min_amplitude_deg
        dominant = np.zeros(active.size, dtype=int)
    stretches = []
    for start, stop in _runs(active):
        kind = int(np.bincount(dominant[start:stop], minlength=3).argmax())
        main = deviation[kind] if named else deviation[np.argmax(deviation[:, start:stop].var(axis=1))]
        swing = np.abs(main[start:stop])
        inside = np.flatnonzero(swing > 0.2 * swing.max())
        a, b = start + inside[0], start + inside[-1] + 1
        crossings = np.count_nonzero(np.diff(np.sign(main[a:b])) != 0)
        if b - a >= min_duration_s * rate and crossings >= 3:
            stretches.append((a, b, kind))
    if not named:
        longest = sorted(stretches, key=lambda s: s[0] - s[1])[:3]
        stretches = [(a, b, i) for i, (a, b, _) in enumerate(sorted(longest))]
    best: dict[int, tuple] = {}
    for s in stretches:
        if s[2] not in best or s[1] - s[0] > best[s[2]][1] - best[s[2]][0]:
            best[s[2]] = s
    return sorted(best.values())


def _bandpassed(signal_nT, sample_rate_hz, passband_hz) -> np.ndarray:
    y = np.asarray(signal_nT, dtype=float)
    if y.ndim != 1 or not np.isfinite(y).all():
        raise MagcalError("the signal must be a 1-D series of finite nT")
    return bandpass(y, sample_rate_hz, passband_hz)


def figure_of_merit(signal_nT, maneuvers, sample_rate_hz: float, passband_hz=DEFAULT_PASSBAND_HZ) -> FOMTable:
    """The peak-to-peak value (nT) of the band-passed ``signal_nT`` in each maneuver, and their sum (the FOM)."""
    if not maneuvers:
        raise MagcalError("no maneuvers: the record has no roll, pitch or yaw stretch to judge the compensation on")
    y = _bandpassed(signal_nT, sample_rate_hz, passband_hz)
    p2p = np.array([np.ptp(y[m.start : m.stop]) for m in maneuvers])
    return FOMTable(list(maneuvers), p2p)


def improvement_ratio(
    uncompensated_nT, compensated_nT, sample_rate_hz: float, maneuvers=None, passband_hz=DEFAULT_PASSBAND_HZ
) -> float:
    """Standard deviation of the band-passed uncompensated scalar over the band-passed compensated one, over the
    maneuvers' samples (all samples without maneuvers)."""
    before = _bandpassed(uncompensated_nT, sample_rate_hz, passband_hz)
    after = _bandpassed(compensated_nT, sample_rate_hz, passband_hz)
    keep = np.ones(before.size, dtype=bool)
    if maneuvers:
        keep[:] = False
        for m in maneuvers:
            keep[m.start : m.stop] = True
    return float(np.std(before[keep]) / np.std(after[keep]))


def fom_report(
    uncompensated_nT,
    compensated_nT,
    sample_rate_hz: float,
    *,
    maneuvers=None,
    attitude_deg=None,
    flux_nT=None,
    passband_hz=DEFAULT_PASSBAND_HZ,
) -> FOMReport:
    """The FOM before and after, and the improvement ratio; the maneuvers found when not given."""
    notes = []
    if maneuvers is None:
        maneuvers = find_maneuvers(sample_rate_hz, attitude_deg=attitude_deg, flux_nT=flux_nT)
        source = "the attitude" if attitude_deg is not None else "the fluxgate's direction (named in flying order)"
        notes.append(f"{len(maneuvers)} maneuvers found from {source}")
    if len(maneuvers) != 12:
        notes.append(f"{len(maneuvers)} maneuvers, not a box's 12: the FOM is not comparable with a standard one")
    before = figure_of_merit(uncompensated_nT, maneuvers, sample_rate_hz, passband_hz)
    after = figure_of_merit(compensated_nT, maneuvers, sample_rate_hz, passband_hz)
    ratio = improvement_ratio(uncompensated_nT, compensated_nT, sample_rate_hz, maneuvers, passband_hz)
    return FOMReport(before, after, ratio, notes)
