"""The gravity model in the page: a compass beside an accelerometer, calibrated against gravity and
judged by heading.

Calibrate tab, section *Gravity model (beside an accelerometer)*: **Run the gravity fit**, the table of the gravity
fit beside the total-field fit (:func:`magcal_workbench.gravitymodel.table_markdown`), the dip over time and against
the tilt, and the compass rose of the heading error the total-field fit leaves. View tab, section *Accelerometer*:
**Show the accelerometer's cloud and sphere** draws its corrected directions on a unit sphere below the magnetometer's
clouds (still samples coloured, the others grey). :class:`GravityPage` is made by the app, builds its sections with
:meth:`Panels.section`, and follows the controller's events (:meth:`changed`); its ``do_*`` actions are found by the
app like every part's. The figures are built by pure functions the tests call.
"""

from __future__ import annotations

import numpy as np

from magcal.core.errors import MagcalError

from .actions import action
from .events import Change
from .gravitymodel import GravitySession, accel_cloud, dip_series, rose, table_markdown
from .plots import add_figure
from .scene import GROUP_DZ, sphere_mesh

#: Colours of the page's gravity figures.
OURS_COLOUR = "#1f77b4"
SEPARATE_COLOUR = "#ff7f0e"
STILL_RGB = (31, 119, 180)
MOVING_RGB = (190, 190, 190)
#: Where the accelerometer's sphere sits in the scene and its radius (scene units: the magnetometer's spheres have
#: radius 1 and sit at x = -+1.5): between and below them, inside the camera's frame.
ACCEL_CENTRE = (0.0, 0.0, -0.72 * GROUP_DZ)
ACCEL_RADIUS = 0.8


def dip_figure(series):
    """The dip against time (left) and against the tilt (right) of both fits, with the inclination (plotly)."""
    import plotly.graph_objects as go
    from plotly.subplots import make_subplots

    fig = make_subplots(rows=1, cols=2, subplot_titles=("dip over time", "dip against tilt"))
    if series is not None:
        for key, colour, name in (
            ("dip_separate_deg", SEPARATE_COLOUR, "total-field fit"),
            ("dip_deg", OURS_COLOUR, "gravity fit"),
        ):
            if key not in series:
                continue
            for col, x in ((1, series["x"]), (2, series["tilt_deg"])):
                fig.add_trace(
                    go.Scattergl(
                        x=x,
                        y=series[key],
                        mode="markers",
                        marker={"size": 3, "color": colour, "opacity": 0.6},
                        name=name,
                        legendgroup=name,
                        showlegend=col == 1,
                    ),
                    row=1,
                    col=col,
                )
        for col in (1, 2):
            fig.add_hline(y=series["inclination_deg"], line={"color": "black", "width": 1}, row=1, col=col)
        fig.update_xaxes(title_text=series["x_label"], row=1, col=1)
        fig.update_xaxes(title_text="tilt (deg)", row=1, col=2)
    fig.update_yaxes(title_text="dip (deg)", row=1, col=1)
    fig.update_layout(
        height=280,
        margin={"l": 55, "r": 10, "t": 30, "b": 40},
        legend={"orientation": "h", "y": -0.3, "font": {"size": 10}},
        template="plotly_white",
    )
    return fig


def rose_figure(data):
    """The compass rose: per heading sector, the RMS heading error the total-field fit leaves (plotly, polar)."""
    import plotly.graph_objects as go

    fig = go.Figure()
    if data is not None:
        fig.add_trace(
            go.Barpolar(
                theta=data["centre_deg"],
                r=data["rms_deg"],
                width=np.full(len(data["centre_deg"]), 360.0 / len(data["centre_deg"])),
                marker_color=SEPARATE_COLOUR,
                opacity=0.8,
                name="heading error of the total-field fit (deg RMS)",
            )
        )
    fig.update_layout(
        height=300,
        margin={"l": 30, "r": 30, "t": 40, "b": 20},
        title={"text": "heading error the total-field fit leaves, by heading (deg RMS)", "font": {"size": 12}},
        polar={"angularaxis": {"direction": "clockwise", "rotation": 90}},
        showlegend=False,
        template="plotly_white",
    )
    return fig


class GravityPage:
    """The gravity model's sections, actions and drawing.

    Parameters
    ----------
    ctrl, steps : callable
        Getters: the open data's :class:`~magcal_workbench.controller.Controller` and the
        :class:`~magcal_workbench.steps.Steps` (their check of the readings), handed instead of the workbench
       .
    server : viser.ViserServer
        The scene the accelerometer's cloud is drawn in.
    """

    def __init__(self, *, ctrl, steps, server):
        self._ctrl, self._steps, self.server = ctrl, steps, server
        self.cloud_on = False
        self.nodes: dict = {}

    @property
    def model(self) -> GravitySession:
        """The gravity model of the opened data (the controller's :attr:`~magcal_workbench.controller.Controller.
        gravity` session: saved and restored with the session)."""
        return self._ctrl().gravity

    # --- construction --------------------------------------------------------------------------------------
    def attach(self, panels) -> None:
        """Build the sections into the panels' tabs."""
        import plotly.graph_objects as go

        gui = panels.gui
        self.folder = panels.section("Calibrate", "Gravity model (beside an accelerometer)", expand=True)
        with self.folder:
            self.info = gui.add_markdown("")
            self.btn_fit = panels.button(
                "Run the gravity fit (beside the accelerometer)",
                panels.on.do_gravity_fit,
                engine=True,
                color="teal",
                hint="magcal's fit_gravity: the magnetometer's matrix, bias and rotation into the accelerometer's "
                "frame with the accelerometer's bias and scale, so that the dip (the angle between the field and "
                "gravity) is the same at every attitude; judged by the tilt-compensated heading",
            )
            self.table = gui.add_markdown("")
            self.dip_plot = add_figure(gui, go.Figure(), aspect=2.2)
            self.rose_plot = add_figure(gui, go.Figure(), aspect=1.0)
        with panels.section("View", "Accelerometer"):
            self.cloud_box = gui.add_checkbox(
                "Show the accelerometer's cloud and sphere",
                False,
                hint="its corrected directions on a unit sphere below the magnetometer's clouds: blue the still "
                "samples (they measure gravity), grey the others",
            )
            self.cloud_info = gui.add_markdown("")
        self.cloud_box.on_update(lambda e: panels.handle(panels.on.do_accel_cloud, e))
        self.refresh()

    # --- page actions --------------------------------------------------------------------------------------
    @action
    def do_gravity_fit(self, event):
        """Calibrate tab: the gravity fit beside the total-field fit, in the worker."""
        self._steps().check_readings()
        gm = self.model
        if not gm.available:
            raise MagcalError("the gravity fit needs the accelerometer beside the magnetometer: ax, ay, az columns")
        self._ctrl().run_step("gravity fit", lambda inputs: gm.fit(inputs=inputs))

    @action
    def do_accel_cloud(self, event):
        """View tab: show or hide the accelerometer's cloud and sphere."""
        self.cloud_on = bool(self.cloud_box.value)
        self.draw_cloud()

    # --- following the data --------------------------------------------------------------------------------
    def changed(self, kind: Change) -> None:
        """The controller's event (on the page's thread): a new record (its own gravity model) or a fit redraws."""
        if kind in (Change.DATA, Change.GRAVITY, Change.SELECTION):
            self.refresh()
            self.draw_cloud()

    def refresh(self) -> None:
        if not hasattr(self, "table"):
            return
        gm = self.model
        self.folder.visible = not self._ctrl().compensation_loop()  # a compensation flight: not this fit
        self.btn_fit.visible = gm.available
        self.info.content = "" if gm.available else table_markdown(gm)
        self.table.content = table_markdown(gm) if gm.available else ""
        fitted = gm.result is not None
        self.dip_plot.visible = self.rose_plot.visible = fitted
        if fitted:
            self.dip_plot.figure = dip_figure(dip_series(gm))
            self.rose_plot.figure = rose_figure(rose(gm))
        self.cloud_box.visible = gm.available

    def draw_cloud(self) -> None:
        """Draw (or remove) the accelerometer's cloud and sphere."""
        if not hasattr(self, "cloud_info"):
            return
        scene = self.server.scene
        data = accel_cloud(self.model) if self.cloud_on else None
        if data is None:
            for handle in self.nodes.values():
                handle.remove()
            self.nodes = {}
            self.cloud_info.content = "_Run the gravity fit first._" if self.cloud_on else ""
            return
        centre = np.asarray(ACCEL_CENTRE)
        vertices, faces = sphere_mesh()
        self.nodes["/gravity/accel_sphere"] = scene.add_mesh_simple(
            "/gravity/accel_sphere",
            vertices=(ACCEL_RADIUS * np.asarray(vertices) + centre).astype(np.float32),
            faces=faces,
            color=(200, 200, 200),
            opacity=0.25,
            wireframe=True,
        )
        still = data["still"]
        for name, rows, rgb, size in (
            ("/gravity/accel_moving", ~still, MOVING_RGB, 0.018),
            ("/gravity/accel_still", still, STILL_RGB, 0.04),
        ):
            points = ACCEL_RADIUS * data["directions"][rows] + centre
            self.nodes[name] = scene.add_point_cloud(
                name,
                points=points.astype(np.float32),
                colors=np.tile(np.asarray(rgb, np.uint8), (len(points), 1)),
                point_size=size,
                precision="float32",
            )
        n_still = int(np.count_nonzero(data["still"]))
        self.cloud_info.content = (
            f"{len(data['directions'])} accelerometer directions drawn between and below the magnetometer's clouds, "
            f"{n_still} of them still (blue): the sphere the accelerometer's own fit maps them onto"
        )
