"""The View tab, a panel of the panel recipe (:mod:`magcal_workbench.panelkit`): the sensor shown, the scene's gains
and clouds, the sphere surface, the time window and the vehicle view's widgets.

:class:`ViewTab` is built at its place by :class:`~magcal_workbench.panels.Panels` (``build(panels, gui)``) and
refreshed with the other tabs: other data give the sensor choice its options, a fit or other data set the gains to
suit them (:func:`~magcal_workbench.panels.view_gains`, unless the user moved them). Its widgets call the scene
control's handlers (:class:`~magcal_workbench.view.SceneControl`: ``set_sensor``, ``view_changed``,
``surface_changed``, ``window_changed``, ``do_play``, ``do_pause_play``, ``do_show_all``), which redraw the scene,
the surfaces and the time window they share with the clicks and the box selection in the scene.
"""

from __future__ import annotations

from .events import Change
from .maps import SURFACE_CHOICES
from .panels import ALL_SENSORS, view_gains


def sensor_options(n_sensors: int) -> tuple:
    """The Sensor choices for ``n_sensors`` sensors: ``all sensors`` then each one, or ``sensor 1`` alone."""
    return tuple([ALL_SENSORS] + [f"sensor {i + 1}" for i in range(n_sensors)]) if n_sensors > 1 else ("sensor 1",)


class ViewTab:
    """The View tab's widgets, the scene's settings they hold, and their refresh.

    Parameters
    ----------
    ctrl : callable
        ``ctrl()``: the open data's :class:`~magcal_workbench.controller.Controller`.
    """

    #: The tab it fills.
    tab = "View"

    def __init__(self, *, ctrl):
        self._ctrl = ctrl
        self.on = None

    def attach(self, panels) -> None:
        """Follow the open data (built already at its place, else into its tab now)."""
        if self.on is None:
            with panels.tab(self.tab):
                self.build(panels, panels.gui)
            self.refresh(("all",))

    def build(self, panels, gui) -> None:
        """Make the widgets (in the tab being built)."""
        self.on = on = panels.on
        w, handle = panels.w, panels.handle
        options = sensor_options(self._ctrl().dataset.n_sensors)
        self.sensor_choice = panels.bind(
            w.dropdown(
                "Sensor",
                options,
                allowed=lambda: sensor_options(self._ctrl().dataset.n_sensors),
                initial_value=options[0],
            ),
            self.sensor_shown,
            on.set_sensor,
        )
        self.distortion_gain = w.slider("Raw distortion x", min=0.1, max=50.0, step=0.1, initial_value=10.0)
        self.residual_gain = w.slider(
            "Residual x (radius 1 + x r/F)", min=0.0, max=5000.0, step=1.0, initial_value=1000.0
        )
        self.axes_gain = w.slider("Misalignment x (cross axes)", min=1.0, max=100.0, step=1.0, initial_value=20.0)
        self.show_raw = gui.add_checkbox("Raw cloud", True)
        self.show_ellipsoid = gui.add_checkbox("Fitted ellipsoid", True)
        self.show_corrected = gui.add_checkbox("Corrected cloud", True)
        #: The gains last set to suit the data (:func:`~magcal_workbench.panels.view_gains`); a gain the user
        #: moved is left alone.
        self._auto_gains = {id(self.distortion_gain): 10.0, id(self.residual_gain): 1000.0}
        for h in (
            self.distortion_gain,
            self.residual_gain,
            self.axes_gain,
            self.show_raw,
            self.show_ellipsoid,
            self.show_corrected,
        ):
            h.on_update(lambda e: handle(on.view_changed, e))
        self.surface_choice = w.dropdown(
            "Sphere surface",
            SURFACE_CHOICES,
            initial_value=SURFACE_CHOICES[0],
            hint="A smooth surface inside each corrected cloud, coloured by a direction pattern (nT): the residual's, "
            "the chosen candidate's (what adding it would explain), or what the last fit took away",
        )
        self.surface_choice.on_update(lambda e: handle(on.surface_changed, e))
        self.maps_info = gui.add_markdown("")
        with gui.add_folder("Time window", expand_by_default=True):
            self._build_time(panels, gui)
        panels.vector_panel.build_view(gui)
        panels.tab_panels.append(self)

    def _build_time(self, panels, gui) -> None:
        """The time scrubber (:mod:`magcal_workbench.timewindow`): a window of the recording on the sphere,
        replayed."""
        w, on = panels.w, panels.on
        self.window_on = gui.add_checkbox(
            "Show a time window", False, hint="Draw only the samples in the window; the evidence plots shade it"
        )
        self.window_start = w.slider("Window start %", min=0.0, max=100.0, step=0.1, initial_value=0.0)
        self.window_width = w.slider("Window width %", min=0.5, max=100.0, step=0.5, initial_value=10.0)
        self.play_speed = w.slider(
            "Play speed x", min=1.0, max=100.0, step=1.0, initial_value=10.0, hint="Multiple of real time"
        )
        self.btn_play = panels.button("Play", on.do_play)
        self.btn_pause = panels.button("Pause", on.do_pause_play)
        self.btn_show_all = panels.button("Show all", on.do_show_all)
        self.window_info = gui.add_markdown("")
        for h in (self.window_on, self.window_start, self.window_width, self.play_speed):
            h.on_update(lambda e: panels.handle(on.window_changed, e))

    # --- what the scene reads ------------------------------------------------------------------------------
    def sensor_shown(self) -> str:
        """The sensor choice the state holds, as the dropdown shows it."""
        ctrl = self._ctrl()
        s = ctrl.state.sensor
        return sensor_options(ctrl.dataset.n_sensors)[0] if s is None else f"sensor {s + 1}"

    def view_options(self) -> dict:
        """The tab's settings, as :class:`~magcal_workbench.scene.SceneModel` fields."""
        return {
            "distortion_gain": float(self.distortion_gain.value),
            "residual_gain": float(self.residual_gain.value),
            "axes_gain": float(self.axes_gain.value),
            "show_raw": bool(self.show_raw.value),
            "show_corrected": bool(self.show_corrected.value),
            "show_ellipsoid": bool(self.show_ellipsoid.value),
        }

    def fit_view_to_data(self) -> None:
        """Set the gains to suit the data and fit (:func:`~magcal_workbench.panels.view_gains`), unless the user
        moved them."""
        distortion, residual = view_gains(self._ctrl(), self.on.drawn_residual_rms())
        for handle, value in ((self.distortion_gain, distortion), (self.residual_gain, residual)):
            if handle.value == self._auto_gains.get(id(handle)) and handle.value != value:
                self._auto_gains[id(handle)] = value
                handle.value = value  # its callback redraws the scene

    # --- following the data --------------------------------------------------------------------------------
    def refresh(self, kinds) -> None:
        """A fit or other data: the gains (the scene is drawn at them); other data: the sensor choices."""
        if self.on is None:
            return
        every = "all" in kinds
        if every or Change.RESULT in kinds or Change.DATA in kinds:
            self.fit_view_to_data()
        if every or Change.DATA in kinds:
            # the state's choice first: new options then never fall back to a stale one (which would apply it)
            self.sensor_choice.value = self.sensor_shown()
            self.sensor_choice.options = sensor_options(self._ctrl().dataset.n_sensors)
