"""The simulated source: a preset (:func:`magcal.data.simulation.simulate_timeseries`) or a magcal CSV file played
in real time (``sim://chi2017?rate=50``, ``sim://path/to/file.csv``), for tests, teaching and demonstrations
without hardware. Registered as the live source ``sim``."""

from __future__ import annotations

import os
import time

import numpy as np

from magcal.data import lineformats
from magcal.data.io import read_csv
from magcal.data.live.registry import SourceKind, SourceURL, register_source
from magcal.data.live.source import LiveError, LiveSource
from magcal.data.simulation import PRESETS, simulate_timeseries

#: Bounds of a simulated source's options (``sim://PRESET?n=..&rate=..&speed=..``): samples of a preset, samples
#: per second, and how much faster than real time it plays. The workbench offers these and nothing beyond.
SIM_MAX_SAMPLES = 100_000  # about 1.5 s to simulate; ``loop`` plays a preset for as long as wanted
SIM_RATE_RANGE_HZ = (0.1, 10_000.0)
SIM_SPEED_RANGE = (0.01, 100.0)
#: Most samples per second a simulated source sends (``rate`` times ``speed``): a recording grows at most
#: about 1 MB/s.
SIM_MAX_SAMPLES_PER_S = 20_000.0
#: Largest seed of a simulated source (numpy's seeds are unsigned 32-bit here).
SIM_MAX_SEED = 2**32 - 1


class SimSource(LiveSource):
    """A preset or a magcal CSV file played in real time.

    Sample ``k`` is always the same (deterministic): time ``t_k`` (``k / rate`` for a preset, the file's own times
    for a file unless ``rate`` is given) and the ``k``-th reading (modulo the length when looping).

    Parameters
    ----------
    url : str
    name : str
        A preset of :data:`magcal.data.simulation.PRESETS` or a path to a magcal CSV file.
    rate_hz : float, optional
        Samples per second (default 50 for a preset; the file's own times, or 10 Hz, for a file).
    n_samples : int
        Samples simulated for a preset.
    seed : int
        Seed of the preset's noise.
    loop : bool
        Start again at the end (times go on increasing); otherwise the source ends.
    speed : float
        Play faster (> 1) or slower than real time.
    """

    def __init__(self, url, name, rate_hz=None, n_samples=3000, seed=0, loop=False, speed=1.0):
        super().__init__(url)

        lo, hi = SIM_RATE_RANGE_HZ
        if rate_hz is not None and not lo <= float(rate_hz) <= hi:
            raise LiveError(f"{url}: rate={rate_hz!r}: give {lo:g} to {hi:g} samples per second")
        lo, hi = SIM_SPEED_RANGE
        if not lo <= float(speed) <= hi:
            raise LiveError(f"{url}: speed={speed!r}: give {lo:g} to {hi:g} (times real time)")
        pace = (50.0 if rate_hz is None else float(rate_hz)) * float(speed)
        if name in PRESETS and pace > SIM_MAX_SAMPLES_PER_S:
            raise LiveError(
                f"{url}: rate x speed = {pace:g} samples per second; at most {SIM_MAX_SAMPLES_PER_S:g} (lower rate or "
                "speed)"
            )
        if not 1 <= int(n_samples) <= SIM_MAX_SAMPLES:
            raise LiveError(f"{url}: n={n_samples!r}: give 1 to {SIM_MAX_SAMPLES:,} samples")
        if not 0 <= int(seed) <= SIM_MAX_SEED:
            raise LiveError(f"{url}: seed={seed!r}: give 0 to {SIM_MAX_SEED}")
        if name in PRESETS:
            rate = 50.0 if rate_hz is None else float(rate_hz)
            ds = simulate_timeseries(name, n_samples=int(n_samples), seed=int(seed), rate_hz=rate)
            times = np.arange(ds.n_samples) / rate
        else:
            if not os.path.exists(name):
                raise LiveError(f"{url}: {name!r} is neither a preset ({', '.join(PRESETS)}) nor a file")
            ds = read_csv(name)
            if rate_hz is not None:
                times = np.arange(ds.n_samples) / float(rate_hz)
            elif ds.time_s is not None:
                times = ds.time_s - ds.time_s[0]
            else:
                times = np.arange(ds.n_samples) / 10.0
        self.dataset = ds
        self._times = times
        self._period = float(times[-1] + (np.median(np.diff(times)) if times.size > 1 else 0.1))
        self.loop = bool(loop)
        self.speed = float(speed)
        self.n_sensors = ds.n_sensors
        self.has_temperature = ds.temperature_C is not None
        #: a recording's channels (attitude, gyro, position: :data:`magcal.data.lineformats.CHANNEL_UNITS`), played too
        self._channels = {
            k: np.asarray(ds.extra[k], dtype=float)
            for k in lineformats.CHANNEL_UNITS
            if k in ds.extra and np.asarray(ds.extra[k]).dtype.kind in "fiu"
        }
        self.channel_names = tuple(self._channels)
        self._k = 0
        self._start = None

    def sample(self, k):
        """Sample ``k`` as the source sends it: ``(t_s, readings (n_sensors, 3) nT, temperature or None)``."""
        n = self._times.size
        i = k % n
        t = float(self._times[i] + (k // n) * self._period)
        temp = None if self.dataset.temperature_C is None else float(self.dataset.temperature_C[i])
        return t, self.dataset.readings_nT[:, i], temp

    def _poll(self, deadline, max_samples):
        now = time.monotonic()
        if self._start is None:
            self._start = now
        n = self._times.size
        samples = []
        while len(samples) < max_samples:
            if not self.loop and self._k >= n:
                self.ended = True
                break
            t, r, temp = self.sample(self._k)
            i = self._k % n
            due = self._start + t / self.speed
            now = time.monotonic()
            if due > now:
                if samples or due > deadline:
                    if not samples:
                        time.sleep(max(0.0, deadline - now))
                    break
                time.sleep(due - now)
            samples.append((t, r, temp, {k: float(v[i]) for k, v in self._channels.items()}))
            self._k += 1
        return samples


def open_simulated(url: SourceURL):
    """A ``sim://PRESET`` or ``sim://path/to/file.csv`` URL's source (:class:`SimSource`)."""
    return SimSource(
        url.url,
        url.target,
        rate_hz=url.number("rate", None),
        n_samples=url.number("n", 3000, int),
        seed=url.number("seed", 0, int),
        loop=url.flag("loop"),
        speed=url.number("speed", 1.0),
    )


SIMULATED = register_source(
    SourceKind(
        name="sim",
        schemes=("sim",),
        description="a preset of a paper (simulated, deterministic for a seed) or a magcal CSV file played in real "
        "time",
        forms=("sim://PRESET",),
        example="sim://chi2017?rate=50",
        options=("rate", "seed", "n", "loop", "speed"),
        opener=open_simulated,
    )
)
