"""An independent simulator for held-out diagnosis tests (written separately from :mod:`magcal.data.simulation` and
:mod:`magcal.model.effects`): its own rotation path (integrated random angular velocity, sampled by slerp at any time,
so that delays are exact), its own sensor errors (general sensor matrices), its own forward model of each effect,
and its own CSV writer following ``docs/formats.md``.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

FIELD_NT = 48_500.0
INCLINATION_DEG = 63.0
DECLINATION_DEG = 4.0
BASELINE_M = 0.4
RATE_HZ = 8.0
NOISE_NT = 2.5


def _earth():
    i, d = np.radians(INCLINATION_DEG), np.radians(DECLINATION_DEG)
    return FIELD_NT * np.array([np.cos(i) * np.cos(d), np.cos(i) * np.sin(d), np.sin(i)])


class Path:
    """Array attitude (array -> world) from an integrated, smoothly varying angular velocity."""

    def __init__(self, duration_s, rng, substeps=5):
        dt = 1.0 / (RATE_HZ * substeps)
        self.t = np.arange(0.0, duration_s + 1.0, dt)
        freqs = rng.uniform(0.005, 0.04, (3, 3))
        phases = rng.uniform(0, 2 * np.pi, (3, 3))
        amps = rng.uniform(0.25, 0.45, (3, 3))
        w = np.stack(
            [
                np.sum(amps[a, :, None] * np.sin(2 * np.pi * freqs[a, :, None] * self.t + phases[a, :, None]), axis=0)
                for a in range(3)
            ],
            axis=1,
        ) + rng.uniform(-0.1, 0.1, 3)
        rots = [Rotation.from_euler("xyz", rng.uniform(-np.pi, np.pi, 3))]
        steps = Rotation.from_rotvec(w[:-1] * dt)
        current = rots[0]
        quats = [current.as_quat()]
        for k in range(len(steps)):
            current = current * steps[k]  # body-frame angular velocity
            quats.append(current.as_quat())
        self.rotations = Rotation.from_quat(np.array(quats))
        self._slerp = Slerp(self.t, self.rotations)

    def at(self, times):
        return self._slerp(np.clip(times, self.t[0], self.t[-1]))


def _general_matrix(rng, first):
    k = rng.uniform(0.975, 1.025, 3)
    upper = np.eye(3) + np.triu(rng.normal(0, 0.012, (3, 3)), 1)
    c = np.diag(k) @ upper
    if not first:  # mounting rotation of the other sensors
        c = c @ Rotation.from_rotvec(rng.normal(0, 0.02, 3)).as_matrix()
    return c


def play(x, h):
    """Backlash operator (this simulator's own loop)."""
    out = np.empty_like(x)
    state = x[0]
    for i in range(len(x)):
        if x[i] > state + h:
            state = x[i] - h
        elif x[i] < state - h:
            state = x[i] + h
        out[i] = state
    return out


def dipole_field(offsets_m, moment_Am2):
    """Field (nT) of a point dipole at the origin at the given offsets (N, 3) m."""
    r = np.linalg.norm(offsets_m, axis=1, keepdims=True)
    rhat = offsets_m / r
    m = np.asarray(moment_Am2, dtype=float)
    return 1e-7 * 1e9 * (3 * (rhat @ m)[:, None] * rhat - m) / r**3


def simulate(effect, n_sensors=4, sensor=None, magnitude=1.0, n=1600, seed=0):
    """Readings and channels with one effect hidden (``effect`` None: clean).

    ``sensor`` (0-based) restricts per-sensor effects; ``magnitude`` scales the effect's built-in size.
    Returns a dict of columns and metadata for :func:`write_csv`.
    """
    rng = np.random.default_rng(1000 + seed)
    duration = (n - 1) / RATE_HZ
    t = np.arange(n) / RATE_HZ
    path = Path(duration, rng)
    temp = 18.0 + 5.0 * np.sin(2 * np.pi * 1.1 * t / duration + 0.5) + 1.5 * np.sin(2 * np.pi * 2.7 * t / duration)
    positions = np.array([[1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0]], float)[:n_sensors] * BASELINE_M / 2
    if n_sensors == 1:
        positions = np.zeros((1, 3))
    mats = [_general_matrix(rng, s == 0) for s in range(n_sensors)]
    biases = [rng.uniform(-120, 120, 3) for _ in range(n_sensors)]
    earth = _earth()
    which = range(n_sensors) if sensor is None else [sensor]
    pattern = np.array([1.0, -0.6, 0.45])
    m = magnitude

    dip_pos = np.array([2.5, -1.8, 1.2])
    dip_moment = np.array([6.0, -3.75, 4.5]) * m  # A m^2
    reference = FIELD_NT
    if effect == "site_gradient":
        reference = float(np.linalg.norm(earth + dipole_field(-dip_pos[None], dip_moment)[0]))

    def world_field(times, offsets_array):
        att = path.at(times)
        scale = 1.0
        if effect == "reference_drift":
            d = duration
            scale = 1.0 + (4.0 * m * np.tanh((times - 0.55 * d) / (0.18 * d)) + 1.5 * m * (times / d)) / FIELD_NT
        b = np.tile(earth, (len(times), 1)) * np.atleast_1d(scale)[:, None]
        if effect == "site_gradient":
            b = b + dipole_field(att.apply(offsets_array) - dip_pos, dip_moment)
        return att.inv().apply(b)  # array frame

    readings, att_now = [], path.at(t)
    for s in range(n_sensors):
        delays = np.zeros(3)
        if effect == "axis_timing_skew" and s in which:
            delays = np.array([0.5, -0.3, 0.0]) * m * 1e-3
        if effect == "sensor_timing_skew" and s in which and s > 0:
            delays = np.full(3, [0.0, 0.4, -0.3, 0.25][s] * m * 1e-3)
        lin = np.empty((n, 3))
        for j in range(3):
            b = world_field(t - delays[j], positions[s])
            lin[:, j] = (b @ mats[s].T)[:, j]
        y = lin + biases[s]
        if s in which:
            if effect == "temperature_bias":
                y = y + np.outer(temp - 21.0, 1.6 * m * np.roll(pattern, s))
            elif effect == "temperature_scale":
                y = y + 1e-6 * np.outer(temp - 21.0, 35.0 * m * np.roll(pattern, s)) * lin
            elif effect == "bias_drift":
                y = y + np.outer(t / 3600.0, 180.0 * m * np.roll(pattern, s))
            elif effect == "bias_step":
                y = y + np.outer(t >= 0.42 * duration, 7.0 * m * np.roll(pattern, s))
            elif effect == "nonlinearity_quadratic":
                y = y + 12.0 * m * np.roll(pattern, s) * (lin / 50_000.0) ** 2
            elif effect == "nonlinearity_cubic":
                y = y + 22.0 * m * np.roll(pattern, s) * (lin / 50_000.0) ** 3
            elif effect == "hysteresis":
                h = 3.5 * m * np.abs(np.roll(pattern, s))
                y = y + np.column_stack([play(lin[:, j], h[j]) - lin[:, j] for j in range(3)])
            elif effect == "periodic_interference":
                y = y + np.outer(5.0 * m * np.sin(2 * np.pi * 0.9 * t + 1.0), [0.5, 0.7, -0.5])
        readings.append(y + rng.normal(0, NOISE_NT, (n, 3)))
    q = att_now.as_quat()  # x, y, z, w
    return {
        "t": t,
        "readings": np.array(readings),
        "temp": temp,
        "quat_wxyz": np.column_stack([q[:, 3], q[:, :3]]),
        "reference_total_nT": reference,
        "baseline_m": BASELINE_M if n_sensors > 1 else None,
        "noise_nT": NOISE_NT,
    }


def write_csv(path, sim, attitude=True):
    """The documented CSV: ``# key: value`` lines, a header, one row per sample."""
    ns = sim["readings"].shape[0]
    lines = []
    if sim["baseline_m"]:
        lines.append(f"# baseline_m: {sim['baseline_m']}")
    lines.append(f"# reference_total_nT: {sim['reference_total_nT']:.3f}")
    lines.append("# units: nT")
    lines.append(f"# noise_nT: {sim['noise_nT']}")
    lines.append("# site: held-out simulator of tests/helpers/heldout_sim.py")
    header = ["t"] + [f"s{s + 1}{a}" for s in range(ns) for a in "xyz"] + ["temp"]
    if attitude:
        header += ["qw", "qx", "qy", "qz"]
    lines.append(",".join(header))
    cols = [sim["t"]] + [sim["readings"][s][:, a] for s in range(ns) for a in range(3)] + [sim["temp"]]
    if attitude:
        cols += [sim["quat_wxyz"][:, k] for k in range(4)]
    table = np.column_stack(cols)
    lines += [",".join(f"{v:.6f}" for v in row) for row in table]
    with open(path, "w", encoding="utf-8") as fh:
        fh.write("\n".join(lines) + "\n")
