"""The time scrubber: show only the samples of a time window on the sphere, and replay the recording.

A window (start and width, in percent of the recording's duration, so the View tab's sliders need no new range
when other data open) selects the samples drawn; each sensor's current direction (the window's last sample) is
marked; the evidence plots shade the same window. *Play* advances the start at a chosen multiple of real time in a
thread of its own, so a bias step, a drift or a warm-up can be watched appearing on the sphere. Only indexing: the
residuals, directions and fits are the engine's, as elsewhere.
"""

from __future__ import annotations

import threading
import time

import numpy as np

#: Seconds between two steps of playback.
PLAY_STEP_S = 0.25


def sample_times(dataset) -> np.ndarray:
    """Times of the samples (s): the ``t`` channel, else the sample number (one per second)."""
    t = dataset.time_s
    return np.asarray(t, float) if t is not None else np.arange(dataset.n_samples, dtype=float)


class TimeWindow:
    """The window's state and its playback.

    Parameters
    ----------
    on_change : callable
        Called (without arguments) after the window moves; the workbench redraws.
    """

    def __init__(self, on_change):
        self.on_change = on_change
        self.enabled = False
        self.start_pct = 0.0
        self.width_pct = 10.0
        self.speed = 10.0
        self._stop = threading.Event()
        self._thread = None

    # --- the window ------------------------------------------------------------------------------------------
    def bounds_s(self, times) -> tuple[float, float]:
        """``(t0, t1)`` of the window, s."""
        times = np.asarray(times, float)
        lo, hi = float(np.nanmin(times)), float(np.nanmax(times))
        span = max(hi - lo, 0.0)
        t0 = lo + span * self.start_pct / 100.0
        return t0, t0 + span * self.width_pct / 100.0

    def mask(self, times) -> np.ndarray | None:
        """Samples in the window (bool, N), or None when the window is off (everything shown)."""
        if not self.enabled:
            return None
        times = np.asarray(times, float)
        t0, t1 = self.bounds_s(times)
        return (times >= t0) & (times <= t1)

    def current(self, times) -> int | None:
        """The window's last sample (the sensor's current direction), or None."""
        m = self.mask(times)
        if m is None or not m.any():
            return None
        return int(np.flatnonzero(m)[-1])

    def describe(self, times) -> str:
        """``window 40.0-55.0 s of 0-150 s: 151 samples`` (or that every sample is shown)."""
        times = np.asarray(times, float)
        if not self.enabled:
            return f"every sample shown ({times.size}); switch the time window on to replay the recording"
        t0, t1 = self.bounds_s(times)
        shown = self.mask(times)
        n = int(shown.sum()) if shown is not None else times.size
        state = "playing" if self.playing else "paused"
        return (
            f"window {t0:.1f}-{t1:.1f} s of {np.nanmin(times):.1f}-{np.nanmax(times):.1f} s: {n} samples "
            f"({state}, {self.speed:g}x real time)"
        )

    def set(self, enabled=None, start_pct=None, width_pct=None, speed=None) -> None:
        """Change the window (values in percent of the duration; clipped to 0-100)."""
        if enabled is not None:
            self.enabled = bool(enabled)
        if start_pct is not None:
            self.start_pct = float(np.clip(start_pct, 0.0, 100.0))
        if width_pct is not None:
            self.width_pct = float(np.clip(width_pct, 0.1, 100.0))
        if speed is not None:
            self.speed = float(max(speed, 0.0))
        self.on_change()

    # --- playback --------------------------------------------------------------------------------------------
    @property
    def playing(self) -> bool:
        return self._thread is not None and self._thread.is_alive() and not self._stop.is_set()

    def play(self, duration_s: float, advance=None) -> None:
        """Advance the start at :attr:`speed` times real time until the window reaches the end or :meth:`pause`.

        ``advance(new_start_pct)`` moves the window (the workbench sets its slider, whose callback redraws);
        default :meth:`set`."""
        self.pause()
        self.enabled = True
        if self.start_pct + self.width_pct >= 100.0:
            self.start_pct = 0.0  # at the end: play from the beginning
        self._stop = threading.Event()
        stop = self._stop
        advance = advance or (lambda pct: self.set(start_pct=pct))
        span = max(float(duration_s), 1e-9)

        def run():
            last = time.monotonic()
            pos = sent = self.start_pct  # kept here: a slider rounds what it is given
            while not stop.wait(PLAY_STEP_S):
                if abs(self.start_pct - sent) > 0.2:
                    pos = self.start_pct  # the user moved the slider meanwhile: go on from there
                now = time.monotonic()
                pos = min(pos + 100.0 * self.speed * (now - last) / span, 100.0 - self.width_pct)
                last = now
                advance(pos)
                sent = self.start_pct
                if pos >= 100.0 - self.width_pct:
                    break
            stop.set()

        self._thread = threading.Thread(target=run, name="workbench-play", daemon=True)
        self._thread.start()

    def pause(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(2.0)
