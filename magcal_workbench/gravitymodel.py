"""The gravity model of the opened data: the engine's gravity fit beside the separate calibrations, and
what the page shows of them (no physics here: every heading, dip and tilt comes from the engine's calibration).

:class:`GravityModel` runs :func:`magcal.fitting.gravity.fit_gravity` on the kept samples (and
:func:`magcal.fitting.gravity.separate_calibration`: the total-field fit with the accelerometer's own, what a user
has without the dip), keeps both calibrations' headings, dips and tilts per sample
(:meth:`magcal.calibration.calibration.Calibration.heading`), and gives the page its table, the dip over time and
against the tilt, the compass rose of the heading error the total-field fit leaves, and the accelerometer's cloud.
The functions that build these are pure and tested without a browser.
"""

from __future__ import annotations

import time

import numpy as np

from magcal.core.errors import CalibrationError, MagcalError
from magcal.data.accelerometer import accelerometer, has_accelerometer
from magcal.fitting.gravity import HEADING_MAX_PITCH_DEG, fit_gravity, separate_calibration

from .events import Change
from .markup import safe_text

#: Sectors of the compass rose (deg each).
ROSE_SECTOR_DEG = 30.0


class GravityModel:
    """The gravity fit of one controller's data.

    Attributes
    ----------
    result : magcal.fitting.gravity.GravityFitResult or None
    separate : magcal.calibration.calibration.Calibration or None
        The total-field fit beside the accelerometer's own (None when the record has no ellipsoid).
    heading, heading_separate : dict or None
        :meth:`Calibration.heading` of each on every sample.
    """

    def __init__(self, ctrl):
        self.ctrl = ctrl
        self.result = None
        self.separate = None
        self.heading: dict | None = None
        self.heading_separate: dict | None = None
        self.still: np.ndarray | None = None
        self.accel_m_s2: np.ndarray | None = None

    @property
    def dataset(self):
        return self.ctrl.dataset

    @property
    def available(self) -> bool:
        """Whether the data have accelerometer columns (``ax, ay, az``)."""
        return has_accelerometer(self.dataset)

    def fit(self, kept=None):
        """The gravity fit on the kept samples (the session's robust loss), the separate calibrations beside it,
        and a message with the figures.

        Raises
        ------
        MagcalError
            No accelerometer columns, too few still samples (the engine's message).
        """
        if not self.available:
            raise MagcalError("the gravity fit needs the accelerometer beside the magnetometer: ax, ay, az columns")
        ctrl, ds = self.ctrl, self.dataset
        kept = np.asarray(ctrl.kept if kept is None else kept, dtype=bool)
        t0 = time.perf_counter()
        ctrl._report_progress("gravity fit (beside the accelerometer)", None)
        try:
            result = fit_gravity(ds, mask=kept, robust=bool(ctrl.state.robust))
            try:
                sep = separate_calibration(ds, right_angle=result.sensors[0].right_angle, mask=kept)
            except (CalibrationError, MagcalError):
                sep = None
            heading = result.calibration.heading(ds, force=True)
            heading_sep = sep.heading(ds, force=True) if sep is not None else None
        finally:
            ctrl.progress = None
            ctrl._emit(Change.PROGRESS)
        with ctrl.state.lock:
            self.result, self.separate = result, sep
            self.heading, self.heading_separate = heading, heading_sep
            self.still = result.still.mask & kept
            self.accel_m_s2 = result.calibration.accelerometer.correct(accelerometer(ds).m_s2)
        ctrl._emit(Change.GRAVITY)
        s = result.sensors[0]
        text = (
            f"**gravity fit (beside the accelerometer)** ({time.perf_counter() - t0:.2f} s): mounting "
            f"{safe_text(s.right_angle_text.split(':')[0], 200)}, {s.angle_off_deg:.3f} deg off it; dip spread "
            f"{s.dip_sd_deg:.3f} deg; inclination {result.inclination_deg:.2f} deg"
        )
        text += "".join(f"  \n- {safe_text(w, 600)}" for w in result.warnings)
        ctrl.say(text)
        return result

    def forget(self) -> None:
        self.result = self.separate = self.heading = self.heading_separate = None
        self.still = self.accel_m_s2 = None

    def lesson_findings(self) -> dict | None:
        """Per sensor, the right angle the gravity fit found and the angle off it (deg); None before a fit (what
        :meth:`magcal_workbench.lessons.Lesson.check` compares)."""
        if self.result is None:
            return None
        return {
            "mounting": [s.right_angle_text.split(" ")[0] for s in self.result.sensors],
            "angle_off_deg": [float(s.angle_off_deg) for s in self.result.sensors],
        }

    def level(self) -> np.ndarray:
        """Still samples whose x axis is within :data:`HEADING_MAX_PITCH_DEG` of the horizontal (where a heading
        means something), bool (N,)."""
        f, still = self.accel_m_s2, self.still
        if f is None or still is None:
            return np.zeros(self.dataset.n_samples, bool)
        with np.errstate(invalid="ignore"):
            flat = np.abs(f[:, 0] / np.linalg.norm(f, axis=1)) <= np.sin(np.radians(HEADING_MAX_PITCH_DEG))
        return still & flat


def _rms(values) -> float:
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    return float(np.sqrt(np.mean(v**2))) if v.size else float("nan")


def _wrap(d):
    return (np.asarray(d, float) + 180.0) % 360.0 - 180.0


def table_markdown(gm: GravityModel) -> str:
    """The gravity fit beside the total-field fit: mounting, dip spread, heading, what 0.5 deg needs."""
    if not gm.available:
        return (
            "_**Gravity model**: these data have no accelerometer columns (`ax, ay, az`), so the heading cannot be "
            "judged here._"
        )
    if gm.result is None:
        return "_**Gravity model**: the data have an accelerometer; run the gravity fit to judge the heading._"
    res, s = gm.result, gm.result.sensors[0]
    still, level = gm.still, gm.level()
    ours = gm.heading
    sep = gm.heading_separate
    assert still is not None and ours is not None  # set with the result
    dip_ours = float(np.std(ours["dip_deg"][0][still]))
    dip_sep = float(np.std(sep["dip_deg"][0][still])) if sep is not None else float("nan")
    diff = _rms(_wrap(sep["heading_deg"][0][level] - ours["heading_deg"][0][level])) if sep is not None else None
    sd = "-" if s.mounting_sd_deg is None else " / ".join(f"{v:.3f}" for v in s.mounting_sd_deg)
    rows = [
        "| on the kept samples | total-field fit (+ accelerometer's own) | gravity fit (the dip) |",
        "|---|---|---|",
        f"| mounting into the accelerometer's frame | the right angle, as given | "
        f"{safe_text(s.right_angle_text.split(':')[0], 200)} + {s.angle_off_deg:.3f} deg (sd {sd} deg) |",
        f"| dip spread, still samples | {dip_sep:.3f} deg | {dip_ours:.3f} deg |",
        f"| heading difference from the gravity fit (RMS) | {'-' if diff is None else f'{diff:.2f} deg'} | 0 |",
        f"| heading error of the calibration itself | - | "
        f"{'-' if s.heading_sd_deg is None else f'{s.heading_sd_deg:.3f} deg'} |",
        f"| inclination | - | {res.inclination_deg:.2f} deg ({safe_text(res.inclination_source, 100)}) |",
        f"| still samples, tilts | {res.still.n}, {res.tilt_range_deg[0]:.0f}-{res.tilt_range_deg[1]:.0f} deg | |",
    ]
    text = "\n".join(rows)
    text += "\n\n**What a heading of 0.5 deg needs:**" + "".join(
        f"\n- {safe_text(line, 400)}" for line in res.budget.get("lines", [])
    )
    if not s.determined:
        text += "\n\n⚠ **Not determined by this record**: see the warnings."
    for w in res.warnings:
        text += f"\n- gravity fit: {safe_text(w, 600)}"
    return text


def dip_series(gm: GravityModel) -> dict | None:
    """The dip (deg) of both fits on the still samples against time (or sample number) and against the tilt,
    with the inclination; None before a fit."""
    if gm.result is None or gm.still is None or gm.heading is None:
        return None
    rows = np.flatnonzero(gm.still)
    t = gm.dataset.time_s
    x = np.asarray(t, float)[rows] if t is not None else rows.astype(float)
    out = {
        "x": x,
        "x_label": "time (s)" if t is not None else "sample",
        "tilt_deg": gm.heading["tilt_deg"][rows],
        "dip_deg": gm.heading["dip_deg"][0][rows],
        "inclination_deg": gm.result.inclination_deg,
    }
    if gm.heading_separate is not None:
        out["dip_separate_deg"] = gm.heading_separate["dip_deg"][0][rows]
    return out


def rose(gm: GravityModel, sector_deg: float = ROSE_SECTOR_DEG) -> dict | None:
    """The compass rose: per sector of the gravity fit's heading, the RMS heading error the total-field fit leaves
    (its heading minus the gravity fit's, still samples with the x axis near horizontal); None without both."""
    if gm.result is None or gm.heading_separate is None or gm.heading is None:
        return None
    level = gm.level()
    h = gm.heading["heading_deg"][0][level]
    d = _wrap(gm.heading_separate["heading_deg"][0][level] - h)
    edges = np.arange(0.0, 360.0 + sector_deg / 2, sector_deg)
    centres, rms, counts = [], [], []
    for lo, hi in zip(edges[:-1], edges[1:]):
        inside = (h >= lo) & (h < hi)
        centres.append(0.5 * (lo + hi))
        rms.append(_rms(d[inside]) if inside.any() else 0.0)
        counts.append(int(inside.sum()))
    return {"centre_deg": np.array(centres), "rms_deg": np.array(rms), "n": np.array(counts)}


def accel_cloud(gm: GravityModel, max_points: int = 3000) -> dict | None:
    """The accelerometer's corrected directions (unit vectors, its own frame) and whether each is a still sample;
    None before a fit. Every ``k``-th sample when there are more than ``max_points``."""
    if gm.result is None or gm.accel_m_s2 is None or gm.still is None:
        return None
    f = gm.accel_m_s2
    ok = np.all(np.isfinite(f), axis=1)
    idx = np.flatnonzero(ok)
    if idx.size > max_points:
        idx = idx[:: int(np.ceil(idx.size / max_points))]
    u = f[idx] / np.linalg.norm(f[idx], axis=1, keepdims=True)
    return {"directions": u, "still": gm.still[idx], "rows": idx}
