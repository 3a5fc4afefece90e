"""A user's own effect, written outside magcal: the field of a pump running at a known frequency.

The situation: the magnetometer is calibrated on a platform that also carries a circulation pump. Its motor runs
at a fixed, known speed (here 1.3 Hz, from the pump's data sheet or a tachometer) and its magnet and currents make
a small alternating field at that frequency and at twice it. The field is fixed to the platform, so in each
sensor's own axes it is a sinusoid per axis at ``f0`` and ``2 f0`` with an amplitude and phase per axis:

    y_j(t) += sum_k  a_jk sin(2 pi k f0 (t - t0)) + b_jk cos(2 pi k f0 (t - t0)),   k = 1, 2

The term is linear in ``a`` and ``b`` (nT), so its basis -- the Jacobian of the correction -- is the sines and
cosines themselves: 12 columns per sensor (3 axes x 2 harmonics x sin, cos). It is *record-only*: the phase
belongs to this recording (the pump's phase on another day is unknown), so it is fitted, but it does not carry
to new data.

Load it with ``magcal calibrate data.csv --effects-file user_effects_example.py --effects pump_interference``
(see ``docs/user-effects.md``). The tests in ``tests/model/test_plugins.py`` use this file.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from magcal.model import Context, Effect, register

HARMONIC_RATIO = 0.4  # simulator: amplitude of the second harmonic relative to the fundamental


@register
@dataclass
class PumpInterference(Effect):
    """Field of a pump at a known frequency ``f0`` and its harmonics, fixed in the sensor's axes:
    ``y_j += sum_k a_jk sin(2 pi k f0 (t - t0)) + b_jk cos(2 pi k f0 (t - t0))``, ``a``, ``b`` in nT.

    ``t0`` (s) is the first sample time of the fitted record (data-derived, saved with the calibration). To use
    another pump, subclass with another ``name`` and ``frequency_hz``.
    """

    name: ClassVar[str] = "pump_interference"
    stage: ClassVar[str] = "raw"  # acts on the raw reading, in the sensor's own axes
    channels: ClassVar[tuple] = ("time",)
    per_sensor: ClassVar[bool] = True
    description: ClassVar[str] = (
        "pump field at f0 = 1.3 Hz and 2 f0, a sinusoid per axis fixed in the sensor "
        "[nT, sin and cos per axis and harmonic]"
    )
    #: Instrument terms carry to new data; this one describes one recording (its phase).
    transferable: ClassVar[bool] = False

    #: The pump's frequency (Hz) and the number of harmonics (1: f0 only; 2: f0 and 2 f0).
    frequency_hz: ClassVar[float] = 1.3
    harmonics: ClassVar[int] = 2

    #: Data-derived: the time origin of the phases (s), set by configure.
    reference_time_s: float | None = None

    def param_names(self):
        return [
            f"{kind}{k}_{axis}_nT" for k in range(1, self.harmonics + 1) for kind in ("sin", "cos") for axis in "xyz"
        ]

    def param_scale(self):
        # an amplitude of 1 nT moves the readings by about 1 nT
        return np.ones(6 * self.harmonics)

    def configure(self, dataset, residuals_nT=None):
        self.reference_time_s = float(dataset.time_s[0])

    def state(self):
        return {"reference_time_s": self.reference_time_s}

    def set_state(self, state):
        self.reference_time_s = state.get("reference_time_s")

    def raw_basis(self, z0, ctx: Context):
        """(N, 3, 12): column ``(kind, k, axis)`` is the sine or cosine on that axis only."""
        t = ctx.time_s
        t0 = t[0] if self.reference_time_s is None else self.reference_time_s
        basis = np.zeros((len(t), 3, 6 * self.harmonics))
        col = 0
        for k in range(1, self.harmonics + 1):
            phase = 2 * np.pi * k * self.frequency_hz * (t - t0)
            for wave in (np.sin(phase), np.cos(phase)):
                for axis in range(3):
                    basis[:, axis, col] = wave
                    col += 1
        return basis

    def perturbation(self, magnitude=None, sensor=None):
        """A callable for :func:`magcal.data.simulation.simulate_timeseries` that adds the pump's field.

        Parameters
        ----------
        magnitude : float, optional
            Peak amplitude of the fundamental (nT) along a fixed direction of the sensor's axes (default 4 nT);
            the second harmonic is 0.4 of it along another direction, with other phases.
        sensor : int, optional
            0-based sensor (default every sensor, each with its own directions).
        """
        amplitude = 4.0 if magnitude is None else float(np.ravel(magnitude)[0])
        f0 = self.frequency_hz

        def perturb(readings, context, rng):
            readings = np.array(readings, dtype=float)
            t = context["time_s"]
            sensors = range(readings.shape[0]) if sensor is None else [sensor]
            for s in sensors:
                d1 = np.roll([0.8, -0.5, 0.33], s)
                d2 = np.roll([-0.2, 0.6, 0.77], s)
                wave1 = np.sin(2 * np.pi * f0 * t + 0.7 + s)
                wave2 = np.sin(2 * np.pi * 2 * f0 * t + 2.1 - s)
                readings[s] += amplitude * (
                    wave1[:, None] * d1 / np.linalg.norm(d1) + HARMONIC_RATIO * wave2[:, None] * d2 / np.linalg.norm(d2)
                )
            return readings

        where = "all sensors" if sensor is None else f"sensor {sensor + 1}"
        perturb.description = f"{self.name} {amplitude} nT at {f0} Hz ({where})"
        perturb.effect = self.name
        perturb.sensor = sensor
        perturb.magnitude = amplitude
        return perturb
