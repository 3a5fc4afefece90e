"""The vehicle view: the body and its attitude through the record, the measured and the model field in
world coordinates, and the residual vectors.

Drawn in a frame of its own (``/vehicle``), below the sphere views, in north-east-down coordinates: the frame's
rotation to the scene (z up) is 180 deg about north, so every child node is placed in NED and the world axes are
labelled N, E, D. The body (drawn by the record's vehicle kind, :func:`vehicle_kind`: a quadcopter, an aircraft, a
ground vehicle or a plain block; x forward, y right, z down) is turned by the sample's attitude
(body -> NED); the model field is the reference vector (IGRF or the file's ``ref_n, ref_e, ref_d``), the measured
field is the vector fit's corrected reading rotated to the world, ``R(q) B_body``; both are drawn at the same
scale (``|B|`` = :data:`ARROW_LENGTH` scene units), and their difference from the model's tip, exaggerated by a
stated factor. The sample shown is the time scrubber's current one (:meth:`magcal_workbench.timewindow.TimeWindow.
current`): *Play* in the Time window flies the body through the record.

The geometry is in pure functions (:func:`world_vectors`, :func:`field_arrows`, :func:`vehicle_mesh`) that the
tests check; :class:`VehicleView` only draws, and holds the page actions of the vector model (fit, location).
"""

from __future__ import annotations

import threading

import numpy as np

from magcal.core.errors import MagcalError
from magcal.data.attitude import wxyz_rotation

from .actions import action
from .events import Change
from .parts import PagePart
from .timewindow import sample_times

#: Rotation NED -> scene (z up): north -> +x, east -> -y, down -> -z (180 deg about north; a proper rotation).
NED_TO_SCENE = np.diag([1.0, -1.0, -1.0])
#: The same as a quaternion (w, x, y, z), the ``/vehicle`` frame's orientation in the scene.
NED_FRAME_WXYZ = (0.0, 1.0, 0.0, 0.0)
#: Where the vehicle view sits in the scene: below the sphere views, out of their camera's sight.
VEHICLE_ORIGIN = np.array([0.0, 0.0, -30.0])
#: Length (scene units) at which a field of the reference's magnitude is drawn.
ARROW_LENGTH = 2.5
#: Length of the world axes drawn (scene units).
AXIS_LENGTH = 3.0
#: The residual arrow's typical length the automatic exaggeration aims at, as a fraction of :data:`ARROW_LENGTH`.
RESIDUAL_DRAWN = 0.3
#: Most samples of the time window drawn in the residual trail.
TRAIL_POINTS = 400

MODEL_RGB = (20, 150, 60)
MEASURED_RGB = (30, 90, 230)
RESIDUAL_RGB = (220, 40, 40)
TRAIL_RGB = (240, 150, 150)
AXIS_RGB = (110, 110, 110)
BODY_RGB = (200, 200, 210)
NOSE_RGB = (230, 120, 20)
#: The body's own axes (x forward, y right, z down): dark grey, so that no field's colour (green, blue, red)
#: is also a body line.
BODY_AXIS_RGB = (60, 60, 70)
#: Length of the body's axes (scene units).
BODY_AXIS_LENGTH = 0.8


# --- geometry (pure) ------------------------------------------------------------------------------------------
def world_vectors(attitude_wxyz, body_nT) -> np.ndarray:
    """Body-frame vectors turned into the world (north-east-down) frame: ``R(q) v`` per row.

    Parameters
    ----------
    attitude_wxyz : array_like, shape (N, 4) or (4,)
        Attitude quaternions ``w, x, y, z`` (body -> NED).
    body_nT : array_like, shape (N, 3) or (3,)
        Vectors in the body frame (nT).

    Returns
    -------
    numpy.ndarray, shape (N, 3) or (3,)
        The same vectors in NED (nT).
    """
    q = np.atleast_2d(np.asarray(attitude_wxyz, dtype=float))
    v = np.atleast_2d(np.asarray(body_nT, dtype=float))
    out = wxyz_rotation(q).apply(v)
    return out[0] if np.ndim(body_nT) == 1 else out


def nice_gain(value: float) -> float:
    """``value`` rounded down to 1, 2 or 5 times a power of ten (at least 1): a factor a person reads."""
    if not np.isfinite(value) or value <= 1.0:
        return 1.0
    exp = np.floor(np.log10(value))
    for m in (5.0, 2.0, 1.0):
        if m * 10**exp <= value:
            return float(m * 10**exp)
    return float(10**exp)


def residual_gain(residual_rms_nT, field_nT, length=ARROW_LENGTH) -> float:
    """The residual arrows' exaggeration: a residual of the RMS size drawn :data:`RESIDUAL_DRAWN` of the field
    arrow's length (:func:`nice_gain`); 1 without a residual."""
    if residual_rms_nT is None or not np.isfinite(residual_rms_nT) or residual_rms_nT <= 0:
        return 1.0
    return nice_gain(RESIDUAL_DRAWN * float(field_nT) / float(residual_rms_nT))


def field_arrows(model_ned_nT, measured_ned_nT, field_nT, gain, length=ARROW_LENGTH) -> dict:
    """The arrows of one sample in NED scene units (|B| = ``length``), each ``(1, 2, 3)`` start and end.

    Returns
    -------
    dict
        ``model`` (origin -> the reference field), ``measured`` (origin -> the measured field in the world frame;
        absent without one) and ``residual`` (the model's tip -> plus ``gain`` times measured - model; absent
        without a measurement).
    """
    scale = length / float(field_nT)
    out = {}
    zero = np.zeros(3)
    model = None if model_ned_nT is None else np.asarray(model_ned_nT, float) * scale
    if model is not None:
        out["model"] = np.array([[zero, model]])
    if measured_ned_nT is not None:
        measured = np.asarray(measured_ned_nT, float) * scale
        out["measured"] = np.array([[zero, measured]])
        if model is not None:
            out["residual"] = np.array([[model, model + gain * (measured - model)]])
    return out


def arrow_mesh(start, end, radius=0.06, head_radius=0.13, head_length=0.3, sections=20):
    """A solid arrow from ``start`` to ``end`` (3,) as ``(vertices, faces)``: a cylinder and a cone (trimesh); used
    where an arrow must be translucent (viser's arrows are opaque)."""
    import trimesh

    start, end = np.asarray(start, float), np.asarray(end, float)
    d = end - start
    n = float(np.linalg.norm(d))
    head = min(head_length, 0.5 * n)
    shaft = trimesh.creation.cylinder(radius=radius, height=max(n - head, 1e-6), sections=sections)
    shaft.apply_translation((0.0, 0.0, 0.5 * max(n - head, 1e-6)))
    cone = trimesh.creation.cone(radius=head_radius, height=max(head, 1e-6), sections=sections)
    cone.apply_translation((0.0, 0.0, n - head))
    mesh = trimesh.util.concatenate([shaft, cone])
    if n > 0:
        mesh.apply_transform(trimesh.geometry.align_vectors([0.0, 0.0, 1.0], d / n))
    mesh.apply_translation(start)
    return np.asarray(mesh.vertices), np.asarray(mesh.faces)


def residual_trail(model_ned_nT, measured_ned_nT, field_nT, gain, length=ARROW_LENGTH) -> np.ndarray:
    """Points (M, 3), NED scene units: each sample's exaggerated residual from the model's tip (the samples of the
    time window: whether the residual follows the turns or only scatters)."""
    model = np.atleast_2d(np.asarray(model_ned_nT, float))
    measured = np.atleast_2d(np.asarray(measured_ned_nT, float))
    scale = length / float(field_nT)
    return (model + gain * (measured - model)) * scale


#: The vehicle kinds the view draws, and the words of a file's ``# vehicle:`` line (or a log's firmware) that name
#: each; a record that names none is drawn as a plain body with its nose (``body``).
VEHICLE_WORDS = {
    "multirotor": ("quad", "copter", "multirotor", "multicopter", "hexa", "octo", "drone", "rotor"),
    "aeroplane": ("plane", "aircraft", "wing", "glider", "airplane"),
    "ground": ("rover", "car", "boat", "ship", "ground", "vehicle on wheels", "truck"),
}


def vehicle_kind(dataset) -> str:
    """The record's vehicle kind for the drawing: ``multirotor``, ``aeroplane``, ``ground`` or ``body`` (not
    named), from the file's ``# vehicle:`` line, else the firmware a log names (ArduCopter, ArduPlane, Rover)."""
    meta = getattr(dataset, "metadata", None) or {}
    words = " ".join(str(meta.get(k, "")) for k in ("vehicle", "log_vehicle", "log_firmware")).lower()
    for kind, names in VEHICLE_WORDS.items():
        if any(n in words for n in names):
            return kind
    return "body"


def vehicle_mesh(length=1.3, kind="aeroplane"):
    """The vehicle in the body frame (x forward, y right, z down): ``(hull, nose)``, each ``(vertices, faces)``;
    the nose marks the front. ``kind`` (:func:`vehicle_kind`): ``aeroplane`` (fuselage, wings, tail),
    ``multirotor`` (a centre plate, two arms in an X and a rotor disc at each end), ``ground`` (a low hull and four
    wheels) or ``body`` (a plain block). Made with trimesh."""
    import trimesh

    def box(extents, centre):
        m = trimesh.creation.box(extents=extents)
        m.apply_translation(centre)
        return m

    def disc(radius, height, centre, axis=(0.0, 0.0, 1.0)):
        m = trimesh.creation.cylinder(radius=radius, height=height, sections=24)
        if axis != (0.0, 0.0, 1.0):  # a wheel: its axis along y
            m.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1.0, 0.0, 0.0]))
        m.apply_translation(centre)
        return m

    s = length
    if kind == "multirotor":
        arm = 0.5 * s  # centre to rotor
        parts = [box((0.36 * s, 0.26 * s, 0.1 * s), (0.0, 0.0, 0.0))]
        for angle in (45.0, 135.0):  # the two arms of the X (front-right/back-left, front-left/back-right)
            a = trimesh.creation.box(extents=(2.0 * arm, 0.05 * s, 0.04 * s))
            a.apply_transform(trimesh.transformations.rotation_matrix(np.radians(angle), [0.0, 0.0, 1.0]))
            parts.append(a)
        for angle in (45.0, 135.0, 225.0, 315.0):  # a rotor disc above each arm's end (up is -z)
            c = (arm * np.cos(np.radians(angle)), arm * np.sin(np.radians(angle)), -0.06 * s)
            parts.append(disc(0.2 * s, 0.012 * s, c))
        nose = box((0.14 * s, 0.12 * s, 0.1 * s), (0.25 * s, 0.0, 0.0))
    elif kind == "ground":
        parts = [box((s, 0.5 * s, 0.18 * s), (0.0, 0.0, 0.0))]
        for x in (0.32 * s, -0.32 * s):
            for y in (0.28 * s, -0.28 * s):
                parts.append(disc(0.12 * s, 0.06 * s, (x, y, 0.1 * s), axis=(0.0, 1.0, 0.0)))
        nose = box((0.12 * s, 0.3 * s, 0.12 * s), (0.55 * s, 0.0, -0.02 * s))
    elif kind == "aeroplane":
        parts = [
            box((s, 0.16 * s, 0.14 * s), (0.0, 0.0, 0.0)),  # fuselage
            box((0.28 * s, 1.1 * s, 0.025 * s), (0.05 * s, 0.0, 0.0)),  # wings
            box((0.14 * s, 0.45 * s, 0.02 * s), (-0.42 * s, 0.0, 0.0)),  # tailplane
            box((0.16 * s, 0.02 * s, 0.22 * s), (-0.42 * s, 0.0, -0.16 * s)),  # fin, up (-z)
        ]
        nose = box((0.18 * s, 0.17 * s, 0.15 * s), (0.55 * s, 0.0, 0.0))
    else:
        parts = [box((0.8 * s, 0.45 * s, 0.12 * s), (0.0, 0.0, 0.0))]
        nose = box((0.16 * s, 0.2 * s, 0.13 * s), (0.46 * s, 0.0, 0.0))
    hull = trimesh.util.concatenate(parts)
    return (np.asarray(hull.vertices), np.asarray(hull.faces)), (np.asarray(nose.vertices), np.asarray(nose.faces))


def euler_deg(attitude_wxyz) -> tuple[float, float, float]:
    """Roll, pitch, yaw (deg, aerospace ZYX) of one attitude quaternion (body -> NED)."""
    yaw, pitch, roll = wxyz_rotation(np.atleast_2d(attitude_wxyz)).as_euler("ZYX", degrees=True)[0]
    return float(roll), float(pitch), float(yaw % 360.0)


# --- drawing and actions --------------------------------------------------------------------------------------
class VehicleView(PagePart):
    """Draws the vehicle view and runs the vector model's page actions (the vector fit, the typed location).

    Handed what it uses.

    Parameters
    ----------
    ctrl, panels : callable
        Getters: the open data's :class:`~magcal_workbench.controller.Controller` (its
        :attr:`~magcal_workbench.controller.Controller.vector`) and the :class:`~magcal_workbench.panels.Panels`
        (made after this part).
    steps : magcal_workbench.steps.Steps
        Checks the readings before a fit.
    view : magcal_workbench.view.SceneControl
        Resets the cameras when the view is hidden.
    values : magcal_workbench.checks.PageValues
        What each input widget may send (checked before it is read).
    window : magcal_workbench.timewindow.TimeWindow
        The time scrubber's window: its current sample is drawn, its samples make the residual trail.
    server : viser.ViserServer
        Where the view is drawn (its scene) and whose clients' cameras are placed.

    Attributes
    ----------
    enabled : bool
        Whether the view is shown (View tab's *Show the vehicle view*).
    nodes : dict
        The scene nodes drawn, by name (``/vehicle/body``, ``/vehicle/model_field``...).
    gain : float
        The residual arrows' exaggeration in use.
    """

    def __init__(self, *, ctrl, panels, steps, view, values, window, server) -> None:
        self._ctrl, self._panels = ctrl, panels
        self.steps, self.view, self.values, self.window, self.server = steps, view, values, window, server
        self.enabled = False
        self.nodes: dict = {}
        self.gain = 1.0
        self.shown: dict | None = None  # what the last redraw drew: sample, vectors, arrows (for tests and text)
        self._lock = threading.RLock()
        self._static_drawn = False

    @property
    def _panel(self):
        return self.panels.vector_panel

    # --- page actions --------------------------------------------------------------------------------------
    @action
    def do_vector_fit(self, event):
        """Calibrate tab: the vector fit (attitude-aided) beside the total-field fit, in the worker."""
        self.steps.check_readings()
        ctrl = self.ctrl
        missing = ctrl.vector.missing()
        if missing:
            raise MagcalError("the vector fit needs " + " and ".join(missing))
        ctrl.run_step("vector fit", ctrl.step_vector)

    @action
    def do_remove_vector_effect(self, event):
        """Model tab: take the effect added last out of the vector model and refit, in the worker."""
        self.steps.check_readings()
        ctrl = self.ctrl
        ctrl.run_step("take out of the vector model", lambda inputs: ctrl.vector.remove(kept=inputs.kept))

    @action
    def do_use_location(self, event):
        """Calibrate tab: IGRF at the typed place and date becomes the reference (scalar and vector)."""
        p, check = self._panel, self.values.check
        self.ctrl.vector.set_location(check(p.lat), check(p.lon), check(p.alt), check(p.date))

    @action
    def do_forget_location(self, event):
        self.ctrl.vector.clear_location()

    @action
    def do_vehicle_view(self, event):
        """View tab: show or hide the vehicle view; showing it turns the time window on (the scrubber moves the
        body) and points the cameras at it."""
        on = bool(self._panel.vehicle_on.value)
        self.enabled = on
        if on:
            if not self.panels.window_on.value:
                self.panels.window_on.value = True  # its callback turns the window on and redraws (this too)
            self.redraw()
            self.place_cameras()
        else:
            self.clear()
            self.view.reset_cameras()
        self._panel.refresh_vehicle()

    @action
    def do_vehicle_options(self, event):
        """The residual exaggeration changed (0: automatic)."""
        self.values.check(self._panel.vehicle_gain)
        self.redraw()
        self._panel.refresh_vehicle()

    # --- cameras ----------------------------------------------------------------------------------------------
    @staticmethod
    def camera_pose() -> tuple[np.ndarray, np.ndarray]:
        """Camera position and look-at (scene frame) that show the vehicle view from the south-west, above, with
        the view left of the panel."""
        right = np.array([-1.0, -1.0, 0.0]) / np.sqrt(2.0)  # the screen's right, seen from the south-west
        look = VEHICLE_ORIGIN + 0.9 * right + np.array([0.0, 0.0, -0.8])  # the panel covers the screen's right
        return VEHICLE_ORIGIN + np.array([-3.6, 3.6, 1.6]), look

    def place_cameras(self) -> None:
        for client in self.server.get_clients().values():
            self.place_camera(client)

    def place_camera(self, client) -> None:
        position, look = self.camera_pose()
        with client.atomic():
            client.camera.up_direction = (0.0, 0.0, 1.0)
            client.camera.position = tuple(position)
            client.camera.look_at = tuple(look)

    # --- drawing ----------------------------------------------------------------------------------------------
    def changed(self, kind: Change) -> None:
        """The controller changed (``result``, ``data``, ``vector``, ``settings``...): redraw when shown."""
        if self.enabled and kind in (Change.RESULT, Change.DATA, Change.VECTOR, Change.SETTINGS):
            self.redraw()
            self._panel.refresh_vehicle()

    def current_sample(self) -> int:
        """The time scrubber's current sample (the window's last), else the first."""
        ds = self.ctrl.dataset
        current = self.window.current(sample_times(ds))
        return 0 if current is None else int(current)

    def _typed_gain(self) -> float:
        """The exaggeration typed in the View tab (0: automatic)."""
        return float(self._panel.vehicle_gain.value or 0.0)

    def chosen_gain(self, field_nT: float) -> float:
        """The exaggeration typed (View tab), else the automatic one from the vector model's world residual: the
        base model's (:meth:`VectorModel.gain_rms_nT`), so that the arrows shorten when an added effect explains
        part of it."""
        typed = self._typed_gain()
        if typed > 0:
            return typed
        return residual_gain(self.ctrl.vector.gain_rms_nT(), field_nT)

    def redraw(self) -> None:
        """Draw the body, the fields and the residual at the current sample (nothing when hidden or without
        attitude)."""
        if not self.enabled:
            return
        ctrl = self.ctrl
        sensor = ctrl.state.sensor or 0
        vectors = ctrl.vector.current_vectors(self.current_sample(), sensor)
        with self._lock:
            if vectors is None or vectors["attitude_wxyz"] is None:  # no attitude at all, or none at this sample
                self.clear()
                self.shown = vectors
                return
            model = vectors["model_ned_nT"]
            field_nT = float(np.linalg.norm(model)) if model is not None else float(ctrl.field_nT)
            self.gain = self.chosen_gain(field_nT)
            arrows = field_arrows(model, vectors["measured_ned_nT"], field_nT, self.gain)
            self.shown = {**vectors, "arrows": arrows, "field_nT": field_nT, "gain": self.gain, "sensor": sensor}
            scene = self.server.scene
            with self.server.atomic():
                self._draw_static(scene)
                body = self.nodes["/vehicle/body"]
                body.wxyz = tuple(np.asarray(vectors["attitude_wxyz"], float))
                self._remove("/vehicle/model_field")
                if "model" in arrows:  # translucent and wider: the measured arrow shows inside it
                    v, f = arrow_mesh(*arrows["model"][0])
                    self.nodes["/vehicle/model_field"] = scene.add_mesh_simple(
                        "/vehicle/model_field", v.astype(np.float32), f, color=MODEL_RGB, opacity=0.35
                    )
                for key, name, rgb, shaft, head in (
                    ("measured", "/vehicle/measured_field", MEASURED_RGB, 0.03, 0.08),
                    ("residual", "/vehicle/residual", RESIDUAL_RGB, 0.022, 0.06),
                ):
                    self._remove(name)
                    if key in arrows:
                        self.nodes[name] = scene.add_arrows(
                            name,
                            arrows[key].astype(np.float32),
                            rgb,
                            shaft_radius=shaft,
                            head_radius=head,
                            head_length=2.2 * head,
                        )
                self._draw_trail(scene, field_nT)
                self._labels(scene, vectors, arrows, field_nT)

    def _draw_trail(self, scene, field_nT) -> None:
        """The time window's residuals as red points around the model's tip (at most :data:`TRAIL_POINTS`)."""
        self._remove("/vehicle/residual_trail")
        ctrl = self.ctrl
        vm = ctrl.vector
        if vm.world_nT is None or vm.reference_ned_nT is None:
            return
        window = self.window.mask(sample_times(ctrl.dataset))
        idx = np.flatnonzero(window) if window is not None else np.arange(ctrl.dataset.n_samples)
        if idx.size == 0:
            return
        idx = idx[np.unique(np.linspace(0, idx.size - 1, min(idx.size, TRAIL_POINTS)).astype(int))]
        sensor = min(ctrl.state.sensor or 0, vm.world_nT.shape[0] - 1)
        pts = residual_trail(vm.reference_ned_nT[idx], vm.world_nT[sensor, idx], field_nT, self.gain)
        pts = pts[np.all(np.isfinite(pts), axis=1)]  # samples without attitude or reference: no point
        if pts.shape[0] == 0:
            return
        self.nodes["/vehicle/residual_trail"] = scene.add_point_cloud(
            "/vehicle/residual_trail",
            pts.astype(np.float32),
            TRAIL_RGB,
            point_size=0.022,
            point_shape="circle",
            precision="float32",
        )

    def _labels(self, scene, vectors, arrows, field_nT) -> None:
        ds = self.ctrl.dataset
        i = vectors["sample"]
        roll, pitch, yaw = euler_deg(vectors["attitude_wxyz"])
        t = sample_times(ds)[i]
        lines = [
            f"sample {i}, t = {t:.1f} s: roll {roll:+.1f}, pitch {pitch:+.1f}, yaw {yaw:.1f} deg",
            f"arrows: |B| = {field_nT:.0f} nT drawn {ARROW_LENGTH:g} units",
        ]
        if "measured" in arrows and "residual" not in arrows:
            lines.append("no reference field vector at this sample (no position yet): no residual")
        elif "measured" in arrows:
            d = vectors["measured_ned_nT"] - vectors["model_ned_nT"]
            lines.append(
                f"red: residual x{self.gain:g} (N {d[0]:+.1f}, E {d[1]:+.1f}, D {d[2]:+.1f} nT, "
                f"|r| {np.linalg.norm(d):.1f} nT)"
            )
        else:
            lines.append("run the vector fit (Calibrate tab) to draw the measured field")
        text = "\n".join(lines)
        placed = (
            ("/vehicle/label_info", text, (0.9 * AXIS_LENGTH, 0.9 * AXIS_LENGTH, -1.6)),
            (
                "/vehicle/label_model",
                "model field (reference)",
                arrows["model"][0, 1] * 1.08 if "model" in arrows else None,
            ),
            (
                "/vehicle/label_measured",
                "measured (corrected, world)",
                arrows["measured"][0, 1] * 0.55 if "measured" in arrows else None,
            ),
        )
        for name, words, where in placed:
            self._remove(name)
            if where is not None:
                self.nodes[name] = scene.add_label(name, words, position=tuple(np.asarray(where, float)))

    def _draw_static(self, scene) -> None:
        """The frame, the world axes and their labels, the ground grid and the body mesh (once)."""
        if self._static_drawn and "/vehicle" in self.nodes:
            return
        hull, nose = vehicle_mesh(kind=vehicle_kind(self.ctrl.dataset))
        self.nodes["/vehicle"] = scene.add_frame(
            "/vehicle", wxyz=NED_FRAME_WXYZ, position=tuple(VEHICLE_ORIGIN), show_axes=False
        )
        axes = np.array([[np.zeros(3), AXIS_LENGTH * e] for e in np.eye(3)], np.float32)
        self.nodes["/vehicle/world_axes"] = scene.add_arrows(
            "/vehicle/world_axes", axes, AXIS_RGB, shaft_radius=0.012, head_radius=0.05, head_length=0.12
        )
        for k, word in enumerate(("N (north)", "E (east)", "D (down)")):
            name = f"/vehicle/axis_{word[0]}"
            self.nodes[name] = scene.add_label(name, word, position=tuple(1.05 * AXIS_LENGTH * np.eye(3)[k]))
        self.nodes["/vehicle/grid"] = scene.add_grid(  # the horizontal plane (north-east) through the body
            "/vehicle/grid",
            width=1.6 * AXIS_LENGTH,
            height=1.6 * AXIS_LENGTH,
            plane="xy",
            cell_size=0.5,
            cell_color=(228, 228, 228),
            section_color=(190, 190, 190),
            shadow_opacity=0.0,
        )
        self.nodes["/vehicle/body"] = scene.add_frame("/vehicle/body", show_axes=False)
        body_axes = np.array([[np.zeros(3), BODY_AXIS_LENGTH * e] for e in np.eye(3)], np.float32)
        self.nodes["/vehicle/body/axes"] = scene.add_arrows(
            "/vehicle/body/axes", body_axes, BODY_AXIS_RGB, shaft_radius=0.01, head_radius=0.035, head_length=0.09
        )
        self.nodes["/vehicle/body/hull"] = scene.add_mesh_simple(
            "/vehicle/body/hull", hull[0].astype(np.float32), hull[1], color=BODY_RGB, flat_shading=True
        )
        self.nodes["/vehicle/body/nose"] = scene.add_mesh_simple(
            "/vehicle/body/nose", nose[0].astype(np.float32), nose[1], color=NOSE_RGB, flat_shading=True
        )
        self._static_drawn = True

    def _remove(self, name) -> None:
        handle = self.nodes.pop(name, None)
        if handle is not None:
            handle.remove()

    def clear(self) -> None:
        """Remove every node of the view (hidden, or other data opened)."""
        with self._lock:
            if "/vehicle" in self.nodes:
                self.server.scene.remove_by_name("/vehicle")  # the frame's children go with it
            self.nodes.clear()
            self._static_drawn = False

    @action(name="vehicle_text")
    def describe(self) -> str:
        """The View tab's line about the vehicle view (markdown, escaped)."""
        vm = self.ctrl.vector
        if vm.attitude_kind() is None:
            return "_The vehicle view needs the attitude (`qw..qz` or `roll_deg, pitch_deg, yaw_deg` columns)._"
        if not self.enabled:
            return "_Tick Show the vehicle view: the body, the field in world axes N, E, D, and the residuals._"
        s = self.shown
        if s is not None and s.get("attitude_wxyz") is None:
            return (
                f"_Sample {s['sample']} has no attitude (its angles are empty or NaN: before the first attitude "
                "message, or a gap): nothing to draw there; move the time window._"
            )
        if s is None:
            return "_No reference field vector: type a location (Calibrate tab) or add `ref_n, ref_e, ref_d`._"
        text = (
            f"Sample {s['sample']} (the time window's last; **Play** flies the record). Green: the model field; "
            f"blue: the measured field, corrected and rotated to the world; red: their difference x{s['gain']:g} "
            f"{'(typed)' if self._typed_gain() else '(automatic: Residual arrows x is 0)'} from the model's tip; "
            f"dark grey: the {vehicle_kind(self.ctrl.dataset)}'s axes (x forward, y right, z down). "
            f"|B| = {s['field_nT']:.0f} nT is drawn {ARROW_LENGTH:g} units."
        )
        if s["measured_ned_nT"] is None:
            text += " Run the vector fit (Calibrate tab) to draw the measured field."
        return text
