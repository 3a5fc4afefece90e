"""The cockpit: the compact table the panel opens with, |B| against time with its region editor, and the error
histogram, for the open data or, while one runs, the live session.

The figures are :mod:`magcal_workbench.plots`' (pure functions of a :class:`~magcal_workbench.plots.FieldRecord`);
this module builds the record, places the figures, and runs the region editor's actions. Excluding or including a
time range goes through the controller's selection (:meth:`magcal_workbench.controller.Controller.select`), so undo,
redo and the saved session keep it, and the refit runs in the worker like any rejection's
(:meth:`magcal_workbench.steps.Steps.maybe_refit`). viser's plotly element sends no selection events back, so the
range is chosen with two sliders (percent of the record's duration) and shaded on the plot.

Updates come from the page's thread (:mod:`magcal_workbench.uiqueue`): the controller's changes, and the live view's
refresh after new samples, throttled to one redraw per :data:`LIVE_INTERVAL_S` (plotly figures are heavy to send).
"""

from __future__ import annotations

import time

import numpy as np

from magcal.core.errors import MagcalError

from . import motion
from .actions import action
from .compensationpanel import header_markdown as compensation_header
from .floors import mode_floor
from .panels import summary_markdown
from .parts import PagePart
from .plots import FieldRecord, histogram_figure, magnitude_figure, raw_reference_nT, record_key, table_figures
from .timewindow import sample_times

#: Shortest time between two redraws of the table and plots while samples stream in, s.
LIVE_INTERVAL_S = 1.0


def range_bounds_s(times, from_pct: float, to_pct: float) -> tuple[float, float]:
    """``(t0, t1)`` (s) of the range ``from_pct ... to_pct`` percent of the record's duration (either order)."""
    t = np.asarray(times, float)
    lo, hi = float(np.nanmin(t)), float(np.nanmax(t))
    a, b = sorted((float(from_pct), float(to_pct)))
    return lo + (hi - lo) * a / 100.0, lo + (hi - lo) * b / 100.0


def samples_in_range(times, from_pct: float, to_pct: float) -> np.ndarray:
    """Indices of the samples whose time lies in the range (see :func:`range_bounds_s`)."""
    t = np.asarray(times, float)
    t0, t1 = range_bounds_s(t, from_pct, to_pct)
    return np.flatnonzero((t >= t0) & (t <= t1))


def controller_record(ctrl) -> FieldRecord:
    """The open data's :class:`FieldRecord`: raw and corrected readings, the reference per sample (the file's
    ``ref_total`` column, else the field the fit uses, :attr:`Controller.field_nT`), the kept mask (the state's:
    what the page shows), and the samples taken while turning fast."""
    ds = ctrl.dataset
    ref = ds.ref_total_nT if ds.ref_total_nT is not None and not ctrl.state.fit_reference else None
    reference = np.asarray(ref, float) if ref is not None else np.full(ds.n_samples, float(ctrl.field_nT))
    return FieldRecord(
        time_s=sample_times(ds),
        raw_nT=ds.readings_nT,
        corrected_nT=ctrl.corrected_nT,
        reference_nT=reference,
        kept=ctrl.state.kept,
        fast=motion.fast_turning(ds),
        raw_reference_nT=raw_reference_nT(ds, ctrl.state.reference_nT),
    )


def live_record(live) -> FieldRecord | None:
    """A live session's :class:`FieldRecord` (every sample kept; corrected by the latest live fit, whose
    reference it uses, else the median |raw|), or None before the first sample."""
    ds = live.dataset()
    if ds is None:
        return None
    fit = live.fit
    corrected = None
    F = float(np.median(np.linalg.norm(ds.readings_nT, axis=2)))
    if fit is not None:
        corrected = fit.calibration.correct(ds, record_terms="apply", force=True)
        if fit.calibration.reference_total_nT:
            F = float(fit.calibration.reference_total_nT)
    return FieldRecord(
        time_s=sample_times(ds),
        raw_nT=ds.readings_nT,
        corrected_nT=corrected,
        reference_nT=np.full(ds.n_samples, F),
        kept=np.ones(ds.n_samples, bool),
        fast=motion.fast_turning(ds),
    )


class Cockpit(PagePart):
    """The compact table and the Calibrate tab's plots.

    Handed what it uses.

    Parameters
    ----------
    ctrl, panels, live, steps : callable
        Getters: the open data's :class:`~magcal_workbench.controller.Controller`, the
        :class:`~magcal_workbench.panels.Panels`, the live session (:class:`~magcal_workbench.live.LiveView` or
        None) and the :class:`~magcal_workbench.steps.Steps` (a selection's refit), made or replaced after this part.
    values : magcal_workbench.checks.PageValues
        What each input widget may send (checked before it is read).
    """

    def __init__(self, *, ctrl, panels, live, steps, values) -> None:
        self._ctrl, self._panels, self._live_view, self._steps = ctrl, panels, live, steps
        self.values = values
        self._last_live_draw = 0.0
        #: How many samples the plots show data of (the tests watch it grow with the stream).
        self.n_plotted = 0
        #: The key (:func:`magcal_workbench.plots.record_key`) each figure was last built from, by name: a figure
        #: whose data did not change is not rebuilt nor sent again.
        self._keys: dict[str, str] = {}
        self._table: dict = {}
        #: Figures built (the tests read it): the table's figures, |B| against time, the histogram.
        self.n_built = 0
        #: Redraws made (the tests and benchmarks read it).
        self.n_draws = 0

    def _live(self):
        live = self._live_view()
        return live if live is not None and live.active else None

    def record(self) -> FieldRecord | None:
        live = self._live()
        return live_record(live) if live is not None else controller_record(self.ctrl)

    def pending_s(self, record: FieldRecord):
        """The range the sliders choose, ``(t0, t1)`` s (shaded on the plot)."""
        p = self.panels
        return range_bounds_s(record.time_s, p.range_from.value, p.range_to.value)

    # --- drawing ----------------------------------------------------------------------------------------------
    @action(name="draw_cockpit")
    def draw(self, force: bool = False) -> None:
        """Redraw the table and the plots (on the page's thread); while a live session runs, at most once per
        :data:`LIVE_INTERVAL_S` unless ``force``."""
        live = self._live()
        now = time.monotonic()
        if live is not None and not force and now - self._last_live_draw < LIVE_INTERVAL_S:
            return
        record = self.record()
        if record is None or record.n_samples == 0:
            return
        self._last_live_draw = now
        p = self.panels
        key = record_key(record)
        if self._keys.get("table") != key:
            self._table = table_figures(record)
            self._keys["table"] = key
            self.n_built += 1
        figures = self._table
        if live is not None:
            fit = live.fit
            cal = None if fit is None else fit.calibration
            rms, floor = (None, None) if fit is None else (fit.rms_nT, fit.floor_nT)
            floor_what = ""
            sensor = 0
        else:
            ctrl = self.ctrl
            cal = ctrl.calibration
            rms = ctrl.residual_rms_nT() if cal is not None else None
            floor, floor_what = ctrl.floor_nT(), ""
            if ctrl.vector_loop():  # the record's one floor, as the header and the Model tab show it
                floor, floor_what = mode_floor(ctrl).value_nT, "world components"
            sensor = ctrl.state.sensor or 0
            for b in (p.btn_exclude_range, p.btn_include_range, p.btn_exclude_fast):
                b.disabled = False
        sensors = [] if cal is None else [(c.cinv, c.bias_nT) for c in cal.sensors]
        if live is None and self.ctrl.compensation_loop():  # judged by its FOM, not by |y| - F
            p.summary.content = compensation_header(self.ctrl, figures["n_kept"], figures["n_samples"])
        else:
            p.summary.content = summary_markdown(figures, rms, floor, sensors, sensor, floor_what)
        pending = self.pending_s(record) if live is None else None
        if self._keys.get("field") != (field_key := f"{key} {pending}"):
            p.field_plot.figure = magnitude_figure(record, pending)
            self._keys["field"] = field_key
            self.n_built += 1
        unit = p.histogram_unit.value if p.histogram_unit.value in ("nT", "%") else "nT"  # checked when it moves
        if self._keys.get("histogram") != (histogram_key := f"{key} {unit}"):
            p.histogram_plot.figure = histogram_figure(record, unit)
            self._keys["histogram"] = histogram_key
            self.n_built += 1
        fast = record.fast
        p.btn_exclude_fast.visible = live is None and fast is not None and bool(fast.any())
        if live is None:
            t0, t1 = self.pending_s(record)
            n_in = samples_in_range(record.time_s, p.range_from.value, p.range_to.value).size
            moving = (
                f"; {int(fast.sum())} taken while turning faster than {motion.FAST_TURN_DPS:g} deg/s (marked red)"
                if fast is not None and fast.any()
                else ""
            )
            p.range_info.content = (
                f"Range {t0:.4g} ... {t1:.4g} s: {n_in} samples (shaded blue); excluded stretches are shaded grey"
                f"{moving}."
            )
        self.n_plotted = record.n_samples
        self.n_draws += 1

    # --- the region editor ------------------------------------------------------------------------------------
    @action
    def range_changed(self, event) -> None:
        """A range slider or the histogram's unit moved: check the values, redraw."""
        p, check = self.panels, self.values.check
        check(p.range_from)
        check(p.range_to)
        check(p.histogram_unit)
        self.draw(force=True)

    def _select_range(self, mode: str) -> int:
        if self._live() is not None:
            raise MagcalError("stop the live session first: excluding works on the recording once it is opened")
        p, check = self.panels, self.values.check
        ctrl = self.ctrl
        times = sample_times(ctrl.dataset)
        idx = samples_in_range(times, check(p.range_from), check(p.range_to))
        if idx.size == 0:
            ctrl.say("the range holds no sample")
            return 0
        t0, t1 = range_bounds_s(times, p.range_from.value, p.range_to.value)
        what = f"time range {t0:.4g}-{t1:.4g} s"
        with self._steps().changing_selection():
            n = ctrl.select(idx, mode, what=f"{'exclude' if mode == 'reject' else 'include'} {what}")
        return n

    @action
    def do_exclude_range(self, event) -> None:
        self._select_range("reject")

    @action
    def do_include_range(self, event) -> None:
        self._select_range("restore")

    @action
    def do_exclude_fast(self, event) -> None:
        """Exclude the samples taken while turning fast (:func:`magcal_workbench.motion.fast_turning`)."""
        if self._live() is not None:
            raise MagcalError("stop the live session first: excluding works on the recording once it is opened")
        fast = motion.fast_turning(self.ctrl.dataset)
        if fast is None or not fast.any():
            raise MagcalError("no sample was taken while turning fast (or the data have no gyro or attitude)")
        with self._steps().changing_selection():
            self.ctrl.select(np.flatnonzero(fast), "reject", what=f"exclude {int(fast.sum())} fast-turning samples")
