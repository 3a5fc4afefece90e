"""What the 3-D scene shows and how the page moves it: the scene model of the open data (or of a live session),
the legend, the cameras, pointer events (click to inspect, shift-drag to reject), the View tab's sensor choice,
gains and sphere surfaces, and the time scrubber. The drawing itself is :mod:`magcal_workbench.scene`."""

from __future__ import annotations

import dataclasses
import threading
import time
from typing import Any

import numpy as np

from magcal.core.errors import MagcalError
from magcal.data.attitude import attitude_quaternions

from . import motion
from . import scene as scn
from .actions import action
from .compensationmodel import band_passed_traces
from .compensationpanel import legend_title as compensation_legend_title
from .gravitymodel import model_of
from .guide import compensation_mode, gravity_mode
from .markup import clean_text, safe_text
from .panels import ALL_SENSORS
from .parts import PagePart
from .timewindow import sample_times

#: Without attitude, the tilt ring is sought in the directions of the latest samples: at most this many ...
RING_RECENT_SAMPLES = 400
#: ... taken in at most this many seconds before the current sample.
RING_RECENT_S = 20.0
#: Most samples the field's inclination is estimated from (an even stride through the record).
INCLINATION_SAMPLES = 5000


def ring_directions(dataset, corrected_nT, current: int | None):
    """The tilt ring at sample ``current`` (unit directions, array frame, :mod:`magcal_workbench.motion`), or
    None: with attitude, the ring of a yaw sweep at that sample's roll and pitch and the inclination the data show;
    without, the circle the latest corrected directions lie on, if they lie on one. Nothing before a fit
    (``corrected_nT`` None) without attitude: raw directions, off-centre by the hard iron, lie on no circle of the
    sphere drawn."""
    if dataset is None or current is None or not 0 <= int(current) < dataset.n_samples:
        return None
    current = int(current)
    q = attitude_quaternions(dataset)
    n = dataset.n_samples if corrected_nT is None else min(dataset.n_samples, len(corrected_nT))
    if current >= n:
        return None
    if q is not None and np.all(np.isfinite(q[current])):
        vectors = corrected_nT if corrected_nT is not None else dataset.readings_nT[0]
        idx = np.unique(np.linspace(0, n - 1, INCLINATION_SAMPLES).astype(int))
        idx = idx[np.all(np.isfinite(q[idx]), axis=1)]  # a stream's samples before its first attitude have none
        incl = motion.inclination_from_data(np.asarray(vectors)[idx], np.asarray(q)[idx])
        return motion.tilt_ring(np.asarray(q)[current], incl)
    if corrected_nT is None:
        return None
    t = sample_times(dataset)
    lo = max(0, current + 1 - RING_RECENT_SAMPLES)
    recent = np.arange(lo, current + 1)
    recent = recent[t[recent] >= t[current] - RING_RECENT_S]
    return motion.ring_from_directions(np.asarray(corrected_nT)[recent])


@dataclasses.dataclass(frozen=True)
class FitDrawn:
    """What the scene draws of a fit: its calibration (the ellipsoid), the corrected readings (n_sensors, N, 3,
    nT) and their |B| residual (n_sensors, N, nT), the field the clouds are scaled by and the floor the colours
    are judged against (nT), and which fit (``total-field`` or ``vector``); arrays None before a fit."""

    calibration: Any  # magcal.calibration.calibration.Calibration or None
    corrected_nT: np.ndarray | None
    residual_nT: np.ndarray | None
    field_nT: float
    floor_nT: float | None
    by: str


class SceneControl(PagePart):
    """The scene, the camera, pointer events and the View tab's actions.

    Handed what it uses, no more: the parts made before it as they are, those made after it or
    replaced when other data open as getters (called when used).

    Parameters
    ----------
    ctrl, panels, scene_view, live, steps, vehicle : callable
        Getters: the open data's :class:`~magcal_workbench.controller.Controller`, the
        :class:`~magcal_workbench.panels.Panels`, the :class:`~magcal_workbench.scene.SceneView`, the live view
        (:class:`~magcal_workbench.live.LiveView` or None), the :class:`~magcal_workbench.steps.Steps` (the refit
        after a box rejection) and the :class:`~magcal_workbench.vehicleview.VehicleView`.
    maps : magcal_workbench.maps.SphereMaps
        The sphere surfaces.
    window : magcal_workbench.timewindow.TimeWindow
        The time scrubber's window.
    values : magcal_workbench.checks.PageValues
        What each input widget may send (checked before it is read).
    ui : magcal_workbench.uiqueue.UiQueue
        The page's thread (playback hands its moves to it).
    server : viser.ViserServer
        Its connected clients' cameras.
    evidence : magcal_workbench.evidence.Evidence
        The evidence plots (their band follows the scrubber).
    """

    def __init__(self, *, ctrl, panels, scene_view, live, steps, vehicle, maps, window, values, ui, server, evidence):
        self._ctrl, self._panels, self._scene_view = ctrl, panels, scene_view
        self._live_view, self._steps, self._vehicle = live, steps, vehicle
        self.maps, self.window, self.values, self.ui, self.server = maps, window, values, ui, server
        self.evidence = evidence
        self._lock = threading.RLock()
        #: The vector fit's corrected readings and |B| residuals, made once per fit (:meth:`fit_drawn`).
        self._vector_drawn: tuple = (None, None)
        self._last_evidence_t = 0.0

    @property
    def scene_view(self):
        return self._scene_view()

    @property
    def steps(self):
        return self._steps()

    @property
    def vehicle(self):
        return self._vehicle()

    def _live(self):
        live = self._live_view()
        return live if live is not None and live.active else None

    # --- the scene ----------------------------------------------------------------------------------------
    def scene_model(self) -> scn.SceneModel:
        live = self._live()
        if live is not None:  # a live session owns the scene until it stops
            model = live.scene_model(self.panels.view_options())
            if model is not None:
                ds = live.dataset()  # it may have grown since the model was made: take the model's samples
                n = len(model.kept)
                corrected = model.sensors[0].corrected_nT if model.sensors else None
                fast = motion.fast_turning(ds)
                return dataclasses.replace(
                    model, fast=None if fast is None else fast[:n], ring=ring_directions(ds, corrected, n - 1)
                )
        ctrl = self.ctrl
        ds = ctrl.dataset
        shown = range(ds.n_sensors) if ctrl.state.sensor is None else [ctrl.state.sensor]
        drawn = self.fit_drawn()
        cal, corrected, residual = drawn.calibration, drawn.corrected_nT, drawn.residual_nT
        views = [
            scn.SensorView(
                sensor=s,
                raw_nT=ds.readings_nT[s],
                corrected_nT=None if corrected is None else corrected[s],
                residual_nT=(ctrl.raw_residual_nT()[s] if residual is None else residual[s]),
                cinv=None if cal is None else cal.sensors[s].cinv,
                bias_nT=None if cal is None else cal.sensors[s].bias_nT,
                R=None if cal is None else cal.sensors[s].R,
            )
            for s in shown
        ]
        times = sample_times(ds)
        current = self.window.current(times)
        return scn.SceneModel(
            sensors=views,
            n_sensors=ds.n_sensors,
            field_nT=drawn.field_nT,
            kept=ctrl.state.kept,  # live, even in a job
            floor_nT=drawn.floor_nT,
            corrected_by=drawn.by,
            baseline_m=ds.baseline_m,
            all_calibrations=[] if cal is None else [(c.cinv, c.R) for c in cal.sensors],
            inspected=ctrl.inspected,
            window=self.window.mask(times),
            current=current,
            fast=motion.fast_turning(ds),
            ring=None if current is None else ring_directions(ds, views[0].corrected_nT if views else None, current),
            **self.panels.view_options(),
        )

    def fit_drawn(self) -> FitDrawn:
        """The fit the scene draws: where the loop works on the vector fit and it has run, the vector fit's
        correction (its readings corrected in the body frame, |B| residual against the field vector); else the
        total-field fit's (none before a fit)."""
        ctrl = self.ctrl
        vm = ctrl.vector
        result, world, ned = vm.result, vm.world_nT, vm.reference_ned_nT
        gm = model_of(ctrl)
        if gravity_mode(ctrl) and gm is not None and gm.result is not None:
            return self._gravity_drawn(gm.result)
        if compensation_mode(ctrl) and ctrl.compensation.result is not None:
            return self._compensation_drawn(ctrl.compensation)
        if not ctrl.vector_loop() or result is None or world is None or ned is None:
            return FitDrawn(
                ctrl.calibration, ctrl.corrected_nT, ctrl.residual_nT, ctrl.field_nT, ctrl.floor_nT(), "total-field"
            )
        key, drawn = self._vector_drawn
        if key is not result:
            cal = result.calibration
            corrected = np.asarray(cal.correct(ctrl.dataset, record_terms="apply", warn=False, force=True), float)
            ref_total = np.linalg.norm(ned, axis=1)
            residual = np.linalg.norm(world, axis=2) - ref_total[None]
            drawn = FitDrawn(cal, corrected, residual, float(np.median(ref_total)), None, "vector")
            self._vector_drawn = (result, drawn)
        return dataclasses.replace(drawn, floor_nT=vm.floor_nT)

    @action
    def drawn_residual_rms(self) -> float:
        """RMS (nT) of the kept samples' |B| residual of the fit the scene draws (NaN before a fit): the View tab's
        residual gain is set from it (:func:`magcal_workbench.panels.view_gains`)."""
        residual = self.fit_drawn().residual_nT
        if residual is None:
            return float("nan")
        kept = np.asarray(self.ctrl.kept, bool)
        values = np.asarray(residual, float)[:, kept]
        values = values[np.isfinite(values)]
        return float(np.sqrt(np.mean(values**2))) if values.size else float("nan")

    def _compensation_drawn(self, session) -> FitDrawn:
        """The compensation's drawing: the fluxgate as the compensation reads it (its own calibration and time
        offset applied when the model holds them), coloured by the band-passed compensated scalar (nT: what the
        FOM measures), made once per fit."""
        key, drawn = self._vector_drawn
        result = session.result
        if key is not result:
            flux = np.asarray(self.ctrl.dataset.readings_nT[0], float)
            corrected = result.calibration.corrected_flux_nT(flux)[None]
            traces = band_passed_traces(session)
            if traces is None:  # no fit to draw (the key above says there is one)
                raise MagcalError("the compensation has no fit to draw yet")
            residual = np.asarray(traces["after_nT"], dtype=float)[None]
            field = float(np.median(np.linalg.norm(corrected[0], axis=1)))
            drawn = FitDrawn(None, corrected, residual, field, None, "compensation")
            self._vector_drawn = (result, drawn)
        return drawn

    def _gravity_drawn(self, result) -> FitDrawn:
        """The gravity fit's correction: the magnetometer corrected into the accelerometer's frame, its |B|
        residual against the field the fit found (made once per fit)."""
        key, drawn = self._vector_drawn
        if key is not result:
            cal = result.calibration
            corrected = np.asarray(cal.correct(self.ctrl.dataset, record_terms="apply", warn=False, force=True), float)
            field = float(cal.reference_total_nT or np.median(np.linalg.norm(corrected, axis=2)))
            residual = np.linalg.norm(corrected, axis=2) - field
            drawn = FitDrawn(cal, corrected, residual, field, self.ctrl.floor_nT(), "gravity")
            self._vector_drawn = (result, drawn)
        return drawn

    def update_scene(self) -> None:
        with self._lock:
            self.scene_view.update(self.scene_model())

    def recolor(self) -> None:
        """The selection changed: recolour the points (and keep the inspected sample marked)."""
        self.scene_view.recolor(self.scene_model())
        if self.ctrl.inspected is not None:
            self.scene_view.mark_inspected(self.ctrl.inspected)

    @action
    def legend_html(self) -> str:
        live = self._live()
        fitted = (live.fit is not None) if live is not None else self.ctrl.calibration is not None
        by = self.fit_drawn().by if live is None else "total-field"
        fitted = fitted or by != "total-field"
        title = (
            "band-passed compensated scalar (compensation)"
            if by == "compensation"
            else f"|B| residual of the {by} fit"
            if by != "total-field"
            else "total-field residual"
            if fitted
            else "raw |y| - F"
        )
        if live is None and compensation_mode(self.ctrl):
            title = compensation_legend_title(self.ctrl, by)
        html = scn.legend_html(self.scene_view.last_limit_nT, title)
        if self.maps.patterns and live is None:
            html += scn.legend_html(
                self.maps.limit_nT, f"sphere surface: {self.maps.choice}; grey: not visited", swatches=False
            )
        return html

    # --- cameras ------------------------------------------------------------------------------------------
    def reset_cameras(self) -> None:
        for client in self.server.get_clients().values():
            self.place_camera(client)

    def place_camera(self, client) -> None:
        if self.vehicle.enabled:  # the vehicle view is shown: its camera (a browser that joins sees it too)
            self.vehicle.place_camera(client)
            return
        ctrl = self.ctrl
        live = self._live()
        ds = live.dataset() if live is not None and live.dataset() is not None else ctrl.dataset
        n_sensors = ds.n_sensors if live is not None else ctrl.dataset.n_sensors
        n_groups = 1 if ctrl.state.sensor is not None and live is None else n_sensors
        try:
            fov, aspect = float(client.camera.fov), float(client.camera.aspect)
            fraction = scn.panel_fraction(client.camera.image_width)
        except (AssertionError, ZeroDivisionError):  # the browser has not reported its camera yet
            fov, aspect, fraction = np.radians(75.0), 1.6, 0.25
        position, look_at = scn.camera_pose(n_groups, fov, aspect, fraction, cross=n_sensors > 1)
        with client.atomic():
            client.camera.up_direction = (0.0, 0.0, 1.0)
            client.camera.position = tuple(position)
            client.camera.look_at = tuple(look_at)

    # --- pointer events -----------------------------------------------------------------------------------
    def on_click(self, event) -> None:
        if self._live() is not None:
            return  # the points of a stream are not the opened data's samples
        sv = self.scene_view
        d = sv.displayed
        if d.positions.shape[0] == 0:
            return
        i, _ = scn.nearest_to_ray(d.positions, event.ray_origin, event.ray_direction, max_distance=4 * sv.point_size)
        self.ctrl.inspect(None if i is None else int(d.samples[i]))

    def on_rect_select(self, event) -> None:
        cam = event.client.camera
        self.select_in_rect(cam.wxyz, cam.position, cam.fov, cam.aspect, event.screen_min, event.screen_max)

    def select_in_rect(self, wxyz, position, fov, aspect, screen_min, screen_max) -> int:
        """Reject (or restore, by the panel's mode) the samples whose shown points fall in a screen box."""
        if self._live() is not None:
            raise MagcalError("stop the live session first: rejecting works on the recording once it is opened")
        samples = self.scene_view.samples_in_rect(wxyz, position, fov, aspect, screen_min, screen_max)
        if samples.size == 0:
            self.ctrl.say("the box holds no point")
            return 0
        with self.steps.changing_selection():
            n = self.ctrl.select(samples, self.values.check(self.panels.box_mode))
        return n

    # --- the View tab -------------------------------------------------------------------------------------
    @action
    def set_sensor(self, choice: str) -> None:
        """Show one sensor (``"sensor 2"``) or all of them (the panels' sensor choice)."""
        if choice not in self.values.allowed(self.panels.sensor_choice):
            raise MagcalError(f"no sensor choice {clean_text(repr(choice), 40)}; refused")
        self.ctrl.configure(sensor=None if choice == ALL_SENSORS else int(choice.split()[-1]) - 1)
        self.update_scene()
        self.maps.draw()
        self.reset_cameras()

    @action
    def view_changed(self, event):
        self.update_scene()
        self.panels.legend.content = self.legend_html()

    @action
    def refresh_maps(self) -> None:
        """Recompute and redraw the sphere surfaces for the current choice; an engine refusal becomes the note."""
        try:
            self.maps.refresh()
        except MagcalError as exc:
            self.maps.patterns, self.maps.note = [], str(exc)
            self.maps.clear()
        self.panels.maps_info.content = safe_text(self.maps.describe(), 600)
        self.panels.legend.content = self.legend_html()

    @action
    def surface_changed(self, event):
        self.maps.choice = self.values.check(self.panels.surface_choice)
        self.refresh_maps()

    # --- the time scrubber --------------------------------------------------------------------------------
    @action
    def window_changed(self, event):
        """A Time window widget moved: take its values (checked) into the window, which redraws."""
        p, check = self.panels, self.values.check
        self.window.set(
            enabled=bool(check(p.window_on)),
            start_pct=float(check(p.window_start)),
            width_pct=float(check(p.window_width)),
            speed=float(check(p.play_speed)),
        )

    def window_moved(self) -> None:
        self.update_scene()
        self.vehicle.redraw()  # the vehicle view follows the scrubber's current sample
        times = sample_times(self.ctrl.dataset)
        self.panels.window_info.content = safe_text(self.window.describe(times))
        now = time.monotonic()
        if not self.window.playing or now - self._last_evidence_t > 1.0:  # the plots' band: at most once a second
            self._last_evidence_t = now
            self.evidence.draw()

    @action
    def do_play(self, event):
        """Replay the recording: the window's start advances at the Play speed until the end or Pause."""
        times = sample_times(self.ctrl.dataset)
        if not self.panels.window_on.value:
            self.panels.window_on.value = True  # its callback turns the window on
        slider = self.panels.window_start

        def advance(pct):  # the playback's thread hands the move to the page's thread (and waits for it)
            self.ui.run(lambda: setattr(slider, "value", round(pct, 1)))

        self.window.play(float(np.nanmax(times) - np.nanmin(times)), advance=advance)
        self.panels.window_info.content = safe_text(self.window.describe(times))

    @action
    def do_pause_play(self, event):
        self.window.pause()
        self.window_moved()

    @action
    def do_show_all(self, event):
        self.window.pause()
        self.panels.window_on.value = False  # its callback shows every sample
