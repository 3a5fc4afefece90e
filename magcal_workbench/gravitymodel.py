"""The gravity model of the opened data: the engine's gravity fit beside the separate calibrations, and
what the page shows of them (no physics here: every heading, dip and tilt comes from the engine's calibration).

:class:`GravitySession` runs the engine's gravity fit mode (:data:`magcal.modes.GRAVITY`, the fit of
``magcal.calibrate(ds, mode="gravity")``) on the kept samples, and the mode's separate calibrations beside it
(:meth:`magcal.modes.gravity.GravityMode.separate_calibration`: the total-field fit with the accelerometer's own, what
a user has without the dip); it keeps both calibrations' headings, dips and tilts per sample
(:meth:`magcal.calibration.calibration.Calibration.heading`), and gives the page its table, the dip over time and
against the tilt, the compass rose of the heading error the total-field fit leaves, and the accelerometer's cloud.
The functions that build these are pure and tested without a browser.
"""

from __future__ import annotations

import time

import numpy as np

from magcal.core.errors import CalibrationError, MagcalError
from magcal.data.accelerometer import accelerometer, has_accelerometer
from magcal.fitting.gravity import HEADING_MAX_PITCH_DEG
from magcal.modes import GRAVITY

from .events import Change
from .markup import safe_text
from .modelsession import ModelSession, register_session
from .state import JobInputs, pack_mask, unpack_mask

#: Sectors of the compass rose (deg each).
ROSE_SECTOR_DEG = 30.0

#: Largest record (samples x sensors) whose saved gravity fit is run again when its session opens (about a second
#: on a shared two-core machine, as the vector fit's :data:`magcal_workbench.vectormodel.RESTORE_MAX_SAMPLES`); a
#: larger one keeps its settings and the page says to press the button.
RESTORE_MAX_SAMPLES = 30_000


def model_of(ctrl) -> GravitySession | None:
    """The gravity session of ``ctrl``'s data (the controller's ``gravity``), None for a controller without one."""
    return getattr(ctrl, "gravity", None)


@register_session
class GravitySession(ModelSession):
    """The gravity fit of one controller's data (the model session of the fit mode ``"gravity"``): what it fitted
    is kept in the session file (``gravity_fit``: the samples and the robust loss) and run again when the session
    reopens (:meth:`restore`).

    Attributes
    ----------
    result : magcal.fitting.gravity.GravityFitResult or None
    separate : magcal.calibration.calibration.Calibration or None
        The total-field fit beside the accelerometer's own (None when the record has no ellipsoid).
    heading, heading_separate : dict or None
        :meth:`Calibration.heading` of each on every sample.
    """

    mode = "gravity"
    title = "gravity model"

    def __init__(self, ctrl):
        super().__init__(ctrl)
        self.result = None
        self.separate = None
        self.heading: dict | None = None
        self.heading_separate: dict | None = None
        self.still: np.ndarray | None = None
        self.accel_m_s2: np.ndarray | None = None
        self._history: list[dict] = []

    def missing(self) -> list[str]:
        """The accelerometer's columns (``ax, ay, az``) when the data lack them."""
        return (
            [] if has_accelerometer(self.dataset) else ["the accelerometer beside the magnetometer: ax, ay, az columns"]
        )

    @property
    def calibration(self):
        """The gravity fit's calibration (magnetometer and accelerometer), or None."""
        return None if self.result is None else self.result.calibration

    def fit(self, kept=None, *, inputs: JobInputs | None = None, robust=None, again: bool = False):
        """The gravity fit on the kept samples (``kept``, else ``inputs``', else those of now; the session's robust
        loss unless ``robust`` is given), the separate calibrations beside it, and a message with the figures; the
        session file keeps what it fitted (``gravity_fit``). ``again``: the saved session's fit run again.

        Raises
        ------
        MagcalError
            No accelerometer columns, too few still samples (the engine's message).
        """
        if not self.available:
            raise MagcalError("the gravity fit needs the accelerometer beside the magnetometer: ax, ay, az columns")
        ctrl, ds = self.ctrl, self.dataset
        if kept is None and inputs is not None:
            kept = inputs.kept
        kept = np.asarray(ctrl.kept if kept is None else kept, dtype=bool)
        robust = bool(ctrl.state.robust if robust is None else robust)
        t0 = time.perf_counter()
        ctrl.report_progress("gravity fit (beside the accelerometer)", None)
        try:
            result = GRAVITY.fit(ds, mask=kept, robust=robust)
            try:
                sep = GRAVITY.separate_calibration(ds, result, mask=kept)
            except (CalibrationError, MagcalError):
                sep = None
            heading = result.calibration.heading(ds, force=True)
            heading_sep = sep.heading(ds, force=True) if sep is not None else None
        finally:
            ctrl.end_progress()
        elapsed = time.perf_counter() - t0
        s = result.sensors[0]
        with ctrl.state.lock:
            self.result, self.separate = result, sep
            self.heading, self.heading_separate = heading, heading_sep
            self.still = result.still.mask & kept
            accel_cal, accel = result.calibration.accelerometer, accelerometer(ds)
            assert accel_cal is not None and accel is not None  # a gravity fit is of the accelerometer's readings
            self.accel_m_s2 = accel_cal.correct(accel.m_s2)
            self.diagnosis = None
            ctrl.state.gravity_fit = {"kept": pack_mask(kept), "robust": robust}
            if not again:
                self._history.append(
                    {
                        "step": "gravity fit",
                        "dip_sd_deg": float(s.dip_sd_deg),
                        "angle_off_deg": float(s.angle_off_deg),
                        "n_fitted": int(kept.sum()),
                        "elapsed_s": elapsed,
                    }
                )
            ctrl.state.touch()
        ctrl.autosave()
        ctrl.emit(Change.GRAVITY)
        text = (
            ("the saved session's " if again else "")
            + f"**gravity fit (beside the accelerometer)** ({elapsed:.2f} s): mounting "
            f"{safe_text(s.right_angle_text.split(':')[0], 200)}, {s.angle_off_deg:.3f} deg off it; dip spread "
            f"{s.dip_sd_deg:.3f} deg; inclination {result.inclination_deg:.2f} deg"
        )
        text += "".join(f"  \n- {safe_text(w, 600)}" for w in result.warnings)
        ctrl.say(text)
        return result

    def forget(self) -> None:
        """Drop the gravity fit (the session forgets it too)."""
        super().forget()
        self.result = self.separate = self.heading = self.heading_separate = None
        self.still = self.accel_m_s2 = None
        self.ctrl.state.gravity_fit = None

    def history(self) -> list[dict]:
        """The gravity fits of this page (``step``, ``dip_sd_deg``, ``angle_off_deg``, ``n_fitted``,
        ``elapsed_s``), oldest first."""
        return list(self._history)

    def save(self) -> dict | None:
        """What the session file keeps of the last gravity fit (``gravity_fit``: ``kept``, a packed mask, and
        ``robust``), or None."""
        return self.ctrl.state.gravity_fit

    def restore(self) -> str:
        """Run the saved session's gravity fit again (its samples and robust loss); a note for the page when it
        could not (the session goes on without it)."""
        saved = self.ctrl.state.gravity_fit
        if not saved:
            return ""
        size = self.dataset.n_samples * self.dataset.n_sensors
        if size > RESTORE_MAX_SAMPLES:  # not on every opening: the settings stay, the button runs it
            return (
                f"the saved session ran the gravity fit; on {size:,} sensor samples it is not run again on opening "
                "(seconds): press Run the gravity fit (Calibrate tab) to see it"
            )
        try:
            self.fit(unpack_mask(saved["kept"], self.dataset.n_samples), robust=saved.get("robust", False), again=True)
        except (MagcalError, ValueError, KeyError, TypeError) as exc:
            with self.ctrl.state.lock:
                self.ctrl.state.gravity_fit = None
                self.ctrl.state.touch()
            return f"the saved gravity fit could not be run again ({safe_text(str(exc), 300)}); run it again"
        return ""

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


#: The gravity model's former name.
GravityModel = GravitySession


def table_markdown(gm: GravitySession) -> str:
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


def dip_series(gm: GravitySession) -> dict | None:
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


def rose(gm: GravitySession, sector_deg: float = ROSE_SECTOR_DEG) -> dict | None:
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


def accel_cloud(gm: GravitySession, max_points: int = 3000) -> dict | None:
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
