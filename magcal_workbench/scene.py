"""The 3-D scene: point clouds, the fitted ellipsoid, the corrected sphere and the cross.

Display conventions (no physics here: every number shown comes from the engine's calibration and fit):

* Data are shown *scaled*: vectors divided by the reference field ``F`` so the sphere has radius 1 and float
  precision never shows (the clouds are also sent as float32).
* Deviations from the unit sphere are tiny (a 2 % scale error, a 3 nT residual), so they are exaggerated
  radially by a gain the user sets: a point ``p`` is drawn at ``p/|p| (1 + g (|p| - 1))``. The raw cloud and
  the ellipsoid use the distortion gain; the corrected cloud is drawn at radius ``1 + g_r r/F`` where ``r`` is
  the sample's total-field residual (nT), so structure in the residual is visible as shape and colour.
* Layout: for each shown sensor the raw cloud (with its ellipsoid) on the left and the corrected cloud (on the
  reference sphere) on the right; "all sensors" stacks the four rows; with more than one sensor the cross sits
  to the right at its real proportions (baseline scaled to :data:`CROSS_SPAN` units) with each sensor's
  estimated sensing axes, whose deviation from ideal axes is exaggerated by a slider (a single sensor has no
  cross: none is drawn). The camera frames it all in the canvas left of the panel (:func:`camera_pose`).
* Motion (:mod:`magcal_workbench.motion`): samples taken while turning fast get a red dot just outside their point
  on every cloud; the
  tilt ring (the directions a yaw sweep at the current tilt would visit) is drawn on each corrected sphere.

The pure functions (projection, ray picking, colours, meshes) are tested without a browser.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import partial

import numpy as np
from viser.transforms import SO3

from magcal.core import conventions

from .defaults import MAX_POINTS

#: Horizontal distance between a raw cloud's centre and its corrected cloud's centre is twice this (scene units).
PAIR_OFFSET = 1.5
#: Spacing of the sensor groups in the all-sensors view (a 2 x 2 grid for three or four sensors).
GROUP_DX = 2 * PAIR_OFFSET + 2.9
GROUP_DZ = 2.9
#: Length of the cross's baseline in scene units (its proportions are real).
CROSS_SPAN = 2.0
#: Share of a decimated cloud given to the samples with the largest |residual| (outliers stay visible).
OUTLIER_SHARE = 0.1

#: Colours (RGB 0-255).
REJECTED_RGB = (230, 0, 230)
INSPECT_RGB = (255, 200, 0)
CURRENT_RGB = (20, 20, 20)
AXIS_RGB = ((220, 50, 50), (50, 170, 50), (60, 90, 230))
IDEAL_AXIS_RGB = (150, 150, 150)
ELLIPSOID_RGB = (90, 170, 255)
SPHERE_RGB = (180, 180, 180)
FAST_RGB = (214, 39, 40)
RING_RGB = (30, 30, 30)
#: Radius the tilt ring is drawn at (the corrected sphere's is 1): just outside, so the points do not hide it.
RING_RADIUS = 1.04
#: A fast-turning sample's mark sits this much farther from its cloud's centre than its point.
FAST_MARK_OUT = 1.06

# Diverging colour map (blue - light grey - red), stops at -1, -0.5, 0, 0.5, 1.
_CMAP_STOPS = np.array([-1.0, -0.5, 0.0, 0.5, 1.0])
_CMAP_RGB = np.array([[33, 102, 172], [103, 169, 207], [235, 235, 235], [239, 138, 98], [178, 24, 43]], float)


# --- colours ------------------------------------------------------------------------------------------------
def record_field_nT(dataset) -> float:
    """The field a record's scene is scaled by before any calibration or user's reference (nT): the file's
    reference total field, else the median of its reference channel, else the median |raw| of every sensor."""
    if dataset.reference_total_nT:
        return float(dataset.reference_total_nT)
    if dataset.ref_total_nT is not None:
        return float(np.median(dataset.ref_total_nT))
    return float(np.median(np.linalg.norm(dataset.readings_nT, axis=2)))


def residual_colors(residual_nT, limit_nT, kept=None) -> np.ndarray:
    """RGB uint8 (N, 3) for residuals on a diverging map clipped at +-``limit_nT``; rejected samples magenta.

    Samples with a NaN residual (not fitted yet) are grey.
    """
    r = np.asarray(residual_nT, dtype=float)
    x = np.clip(r / max(float(limit_nT), 1e-12), -1.0, 1.0)
    rgb = np.stack([np.interp(x, _CMAP_STOPS, _CMAP_RGB[:, k]) for k in range(3)], axis=-1)
    rgb[~np.isfinite(r)] = SPHERE_RGB
    if kept is not None:
        rgb[~np.asarray(kept, bool)] = REJECTED_RGB
    return rgb.astype(np.uint8)


def colour_limit_nT(residual_nT, floor_nT=None) -> float:
    """A symmetric colour limit: the 98th percentile of |residual|, at least 3x the floor (nT)."""
    r = np.abs(np.asarray(residual_nT, dtype=float))
    r = r[np.isfinite(r)]
    lim = float(np.percentile(r, 98)) if r.size else 1.0
    if floor_nT:
        lim = max(lim, 3.0 * float(floor_nT))
    return max(lim, 1e-6)


def readable_nT(value: float) -> str:
    """A number of nT as a person reads it on a scale: ``2,310`` not ``2.31e+03``, ``4.5``, ``0.012``; microtesla
    beyond 10^6 nT (``1.2e+03 uT`` would still be unreadable, so plain ``1,200 uT``)."""
    v = abs(float(value))
    if not np.isfinite(v):
        return "-"
    if v >= 1e6:
        return f"{v / 1e3:,.0f} uT"
    if v >= 100:
        return f"{v:,.0f}"
    if v >= 1:
        return f"{v:.3g}"
    return f"{v:.2g}"


def legend_html(limit_nT: float, title: str = "total-field residual", swatches: bool = True) -> str:
    """An HTML colour bar with ticks in nT, plus (``swatches``) the rejected and not-fitted colours."""
    stops = ", ".join(
        f"rgb({int(c[0])},{int(c[1])},{int(c[2])}) {int(100 * (s + 1) / 2)}%" for s, c in zip(_CMAP_STOPS, _CMAP_RGB)
    )
    rej = "rgb({},{},{})".format(*REJECTED_RGB)
    fmt = readable_nT
    return (
        f'<div style="font-size:0.8em;padding:2px 4px">{title} (nT)'
        f'<div style="height:12px;border-radius:3px;background:linear-gradient(to right, {stops})"></div>'
        f'<div style="display:flex;justify-content:space-between"><span>-{fmt(limit_nT)}</span><span>0</span>'
        f"<span>+{fmt(limit_nT)}</span></div>"
        + (
            f'<div><span style="display:inline-block;width:10px;height:10px;background:{rej}"></span> rejected '
            f'&nbsp;<span style="display:inline-block;width:10px;height:10px;background:rgb(180,180,180)"></span> '
            "not fitted</div>"
            if swatches
            else ""
        )
        + "</div>"
    )


# --- display transforms -------------------------------------------------------------------------------------
def exaggerate_radial(points, gain: float) -> np.ndarray:
    """Radial exaggeration about the unit sphere: ``p/|p| (1 + gain (|p| - 1))``."""
    p = np.asarray(points, dtype=float)
    r = np.linalg.norm(p, axis=-1, keepdims=True)
    r = np.where(r > 0, r, 1.0)
    return p / r * (1.0 + gain * (r - 1.0))


def residual_radius_points(corrected_scaled, residual_nT, field_nT, gain: float) -> np.ndarray:
    """Corrected directions drawn at radius ``1 + gain r/F`` (``r`` in nT; NaN residuals at radius 1). A sample
    with no corrected vector (NaN: an effect that needs the attitude, on a sample without one) is drawn at the
    sphere's centre, hidden inside it: a NaN position would spoil the whole cloud's bounds in the browser."""
    p = np.asarray(corrected_scaled, dtype=float)
    u = p / np.maximum(np.linalg.norm(p, axis=-1, keepdims=True), 1e-12)
    u = np.where(np.isfinite(u).all(axis=-1, keepdims=True), u, 0.0)
    r = np.nan_to_num(np.asarray(residual_nT, dtype=float), nan=0.0)
    return u * (1.0 + gain * r / float(field_nT))[:, None]


#: Largest default distortion gain of the View tab (that of data near a clean sensor in the Earth's field).
DISTORTION_GAIN_MAX = 10.0
#: Drawn radial departure the default distortion gain aims for: the raw cloud's typical one...
DRAWN_DISTORTION = 0.15
#: ...and its largest one (the 99th percentile), so that the cloud stays within its place in the scene.
DRAWN_DISTORTION_MAX = 0.3


def distortion_gain(readings_nT, field_nT: float) -> float:
    """The default distortion gain for raw clouds: their typical departure from the field's sphere drawn at about
    :data:`DRAWN_DISTORTION` of the radius (the largest at most :data:`DRAWN_DISTORTION_MAX`), not above
    :data:`DISTORTION_GAIN_MAX` for clean data.

    The View tab's default (:func:`magcal_workbench.panels.view_gains`, over the kept samples) and the launch's
    preview (:mod:`magcal_workbench.preview`) both draw with it, so a preview of the whole record is the scene the
    workbench then shows. A MEMS part with a hard-iron offset of the field's size would otherwise be drawn far
    outside the screen; below 1 the cloud is drawn closer to the sphere than it is.

    Parameters
    ----------
    readings_nT : array_like, shape (..., 3)
        Raw readings, nT.
    field_nT : float
        The field the clouds are scaled by, nT.

    Returns
    -------
    float
        The gain, rounded to 0.1 below 1 and to a whole number above; :data:`DISTORTION_GAIN_MAX` when there is no
        field to scale by (an all-zero file).
    """
    if not (np.isfinite(field_nT) and field_nT > 0):
        return DISTORTION_GAIN_MAX
    depart = np.abs(np.linalg.norm(np.asarray(readings_nT, dtype=float), axis=-1) / float(field_nT) - 1.0).ravel()
    depart = depart[np.isfinite(depart)]
    typical, largest = (float(np.median(depart)), float(np.percentile(depart, 99))) if depart.size else (0.0, 0.0)
    gain = (
        DISTORTION_GAIN_MAX
        if typical <= 0
        else float(np.clip(min(DRAWN_DISTORTION / typical, DRAWN_DISTORTION_MAX / largest), 0.1, DISTORTION_GAIN_MAX))
    )
    return float(round(gain, 1) if gain < 1 else round(gain))


def ellipsoid_mesh(cinv, bias_nT, field_nT, gain: float = 1.0, subdivisions: int = 3):
    """Vertices and faces of the fitted ellipsoid in scaled raw space: ``(b + C F u)/F`` over an icosphere.

    ``C = (C^-1)^-1`` maps the reference sphere back onto the raw readings; the result is exaggerated with
    :func:`exaggerate_radial` so it lies on the equally exaggerated raw cloud.
    """
    sphere = _icosphere(subdivisions)
    c = np.linalg.inv(np.asarray(cinv, dtype=float))
    v = (np.asarray(bias_nT, float) / field_nT)[None, :] + np.asarray(sphere.vertices) @ c.T
    return exaggerate_radial(v, gain), np.asarray(sphere.faces, dtype=np.int32)


def _icosphere(subdivisions: int):
    """The unit icosphere (trimesh's), imported when first drawn: the launch's preview draws no mesh and comes
    first (trimesh's import costs about 0.3 s)."""
    import trimesh

    return trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)


def sphere_mesh(subdivisions: int = 2):
    s = _icosphere(subdivisions)
    return np.asarray(s.vertices), np.asarray(s.faces, dtype=np.int32)


def sensor_axes(cinv, R, gain: float = 1.0) -> np.ndarray:
    """Unit sensing axes (rows) of one sensor in the array frame, their deviation from ideal axes exaggerated.

    The sensing axis ``j`` is row ``j`` of ``C = (C^-1)^-1`` in the sensor's ideal frame, taken into the array
    frame by ``R``; the drawn axis is ``normalize(e_j + gain (a_j - e_j))``.
    """
    c = np.linalg.inv(np.asarray(cinv, dtype=float))
    a = (np.asarray(R, float) @ c.T).T  # rows: R @ C[j]
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    e = np.eye(3)
    d = e + gain * (a - e)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def group_offset(k: int, n_groups: int) -> np.ndarray:
    """Centre of the k-th shown sensor group: one group at the origin, two stacked, three or four in a 2 x 2 grid
    (sensor 1 top left)."""
    if n_groups == 1:
        return np.zeros(3)
    if n_groups == 2:
        return np.array([0.0, 0.0, (0.5 - k) * GROUP_DZ])
    col, row = k % 2, k // 2
    return np.array([(col - 0.5) * GROUP_DX, 0.0, (0.5 - row) * GROUP_DZ])


def cross_centre(n_groups: int) -> np.ndarray:
    """Centre of the cross model (scene units): right of one or two groups of clouds, below a 2 x 2 grid of them
    (there the canvas left of the panel has room below, not beside)."""
    if n_groups > 2:
        return np.array([0.0, 0.0, -(0.5 * GROUP_DZ + 1.45 + 0.5 * CROSS_SPAN + 0.8)])
    right = PAIR_OFFSET + 1.4
    return np.array([right + 0.5 * CROSS_SPAN + 0.6, 0.0, 0.0])


def scene_bounds(n_groups: int, cross: bool = True):
    """(x_min, x_max, z_min, z_max) of what the scene shows, for placing the camera: the clouds' groups (radius
    about 1.3 with the default exaggeration, labels above), and the cross model (:func:`cross_centre`) when it is
    drawn (more than one sensor)."""
    half_x = (0.5 * GROUP_DX if n_groups > 2 else 0.0) + PAIR_OFFSET + 1.4
    half_z = (0.5 * GROUP_DZ if n_groups > 1 else 0.0) + 1.5
    x0, x1, z0, z1 = -half_x, half_x, -half_z, half_z
    if cross:
        c = cross_centre(n_groups)
        x1 = max(x1, c[0] + 0.5 * CROSS_SPAN + 0.3)
        z0 = min(z0, c[2] - 0.5 * CROSS_SPAN - 0.3)
    return x0, x1, z0, z1


#: Half the depth (scene y) of what is drawn: the clouds' radius with the default exaggeration, scene units.
SCENE_HALF_DEPTH = 1.5
#: Width of the control panel over the canvas, px: viser's "large" control width (24 em of 16 px) and its margin.
PANEL_PX = 24 * 16 + 32
#: Margin kept between what is drawn and the edges of the free canvas, share of its size.
FRAME_MARGIN = 0.02


def panel_fraction(image_width_px) -> float:
    """Share of the canvas's width the control panel covers (:data:`PANEL_PX` over the browser's canvas width),
    between 0.1 and 0.6; 0.25 when the width is not known."""
    try:
        w = float(image_width_px)
    except (TypeError, ValueError):
        return 0.25
    return float(np.clip(PANEL_PX / w, 0.1, 0.6)) if np.isfinite(w) and w > 0 else 0.25


def _framed_points(n_groups: int, cross: bool) -> np.ndarray:
    """Points on what the scene draws, for framing: each cloud as an ellipsoid of the half-extents
    :func:`scene_bounds` allows (1.4 across, :data:`SCENE_HALF_DEPTH` deep, 1.5 high with its label), and the
    cross's flat bounds."""
    k = np.arange(200) + 0.5
    polar, azim = np.arccos(1 - 2 * k / 200), np.pi * (1 + 5**0.5) * k
    u = np.column_stack([np.cos(azim) * np.sin(polar), np.sin(azim) * np.sin(polar), np.cos(polar)])
    blob = u * [1.4, SCENE_HALF_DEPTH, 1.5]
    centres = [group_offset(k, n_groups) + [dx, 0, 0] for k in range(n_groups) for dx in (-PAIR_OFFSET, PAIR_OFFSET)]
    pts = [c + blob for c in centres]
    if cross:
        c = cross_centre(n_groups)
        half = 0.5 * CROSS_SPAN + 0.3
        pts.append(np.array([c + [dx, 0, dz] for dx in (-half, half) for dz in (-half, half + 0.5)]))
    return np.concatenate(pts)


def camera_pose(
    n_groups: int, fov_rad: float = np.radians(75.0), aspect: float = 1.6, panel_fraction=0.25, cross: bool = True
):
    """Camera position and look-at point (looking along +y, z up) that frame the scene in the canvas left of the
    panel, as large as it fits.

    Every drawn object (:func:`_framed_points`, in perspective: a near cloud at the edge looks larger) must project
    inside the free part of the canvas (``1 - panel_fraction`` of its width, all its height) with a margin of
    :data:`FRAME_MARGIN`; the camera is moved as close as that allows (bisection on the distance; for each
    distance the horizontal offset that fits, if any, is an interval, whose middle is taken)."""
    pts = _framed_points(n_groups, cross)
    t = np.tan(0.5 * fov_rad)
    f = min(max(float(panel_fraction), 0.0), 0.6)
    m = FRAME_MARGIN
    x, y, z = pts[:, 0], pts[:, 1], pts[:, 2]
    cz = 0.5 * (z.min() + z.max())  # the camera's height: the middle of what is drawn
    z = z - cz

    def offset(dist):  # the camera x that fits at this distance, or None
        depth = y + dist
        if np.any(depth <= 1e-6) or np.any(np.abs(z) / (depth * t) > 1 - 2 * m):
            return None
        w = depth * t * aspect
        lo, hi = np.max(x - w * (1 - 2 * f - 2 * m)), np.min(x + w * (1 - 2 * m))
        return 0.5 * (lo + hi) if lo <= hi else None

    near, far = SCENE_HALF_DEPTH + 1e-3, 10.0
    while offset(far) is None:
        far *= 2.0
    for _ in range(40):
        mid = 0.5 * (near + far)
        near, far = (near, mid) if offset(mid) is not None else (mid, far)
    cx = offset(far)
    return np.array([cx, -far, cz]), np.array([cx, 0.0, cz])


#: How the cross is drawn: the array frame turned so that its x-y plane faces the camera (array x to the right,
#: array y up, array z toward the viewer).
ARRAY_TO_SCENE = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def cross_positions(n_sensors: int) -> np.ndarray:
    """Sensor positions of the cross (eq. 1, from :mod:`magcal.core.conventions`) scaled so the baseline is
    :data:`CROSS_SPAN` scene units (real proportions)."""
    return conventions.sensor_positions(1.0, n_sensors) * CROSS_SPAN


# --- picking ------------------------------------------------------------------------------------------------
def project_points(points_world, camera_wxyz, camera_position, fov_rad, aspect):
    """Screen coordinates (0..1, OpenCV: origin top-left, y down) and a visibility flag for world points.

    Parameters
    ----------
    camera_wxyz : array_like, shape (4,)
        Camera-to-world rotation (viser's ``client.camera.wxyz``; camera +z forward, +y down).
    camera_position : array_like, shape (3,)
    fov_rad : float
        Vertical field of view.
    aspect : float
        Image width / height.

    Returns
    -------
    uv : numpy.ndarray, shape (N, 2)
    in_front : numpy.ndarray of bool, shape (N,)
    """
    r = SO3(np.asarray(camera_wxyz, dtype=float)).normalize().as_matrix()
    pc = (np.asarray(points_world, float) - np.asarray(camera_position, float)) @ r  # R^T (p - t)
    z = pc[:, 2]
    in_front = z > 1e-9
    zs = np.where(in_front, z, 1.0)
    t = np.tan(0.5 * float(fov_rad))
    u = 0.5 + 0.5 * pc[:, 0] / zs / (t * float(aspect))
    v = 0.5 + 0.5 * pc[:, 1] / zs / t
    return np.column_stack([u, v]), in_front


def points_in_rect(points_world, camera_wxyz, camera_position, fov_rad, aspect, screen_min, screen_max):
    """Boolean mask of world points whose projection lies inside the screen rectangle (and in front)."""
    uv, front = project_points(points_world, camera_wxyz, camera_position, fov_rad, aspect)
    lo = np.minimum(screen_min, screen_max)
    hi = np.maximum(screen_min, screen_max)
    return front & np.all((uv >= lo) & (uv <= hi), axis=1)


def nearest_to_ray(points_world, origin, direction, max_distance=None):
    """Index of the point nearest to a ray (perpendicular distance, points behind the origin ignored).

    Returns ``(index, distance)``, or ``(None, inf)`` when no point is within ``max_distance``.
    """
    p = np.asarray(points_world, float) - np.asarray(origin, float)
    d = np.asarray(direction, float)
    d = d / np.linalg.norm(d)
    along = p @ d
    perp = np.linalg.norm(p - along[:, None] * d, axis=1)
    perp = np.where(along > 0, perp, np.inf)
    if perp.size == 0:
        return None, np.inf
    i = int(np.argmin(perp))
    if not np.isfinite(perp[i]) or (max_distance is not None and perp[i] > max_distance):
        return None, np.inf
    return i, float(perp[i])


# --- what the scene shows -----------------------------------------------------------------------------------
@dataclass
class SensorView:
    """Everything drawn for one sensor (engine results already evaluated, in nT)."""

    sensor: int
    raw_nT: np.ndarray  # (N, 3)
    corrected_nT: np.ndarray | None  # (N, 3) array frame, or None before any fit
    residual_nT: np.ndarray | None  # (N,) total-field residual incl. rejected samples
    cinv: np.ndarray | None = None
    bias_nT: np.ndarray | None = None
    R: np.ndarray | None = None


@dataclass
class SceneModel:
    """Input of :class:`SceneView.update`."""

    sensors: list  # list of SensorView, the ones to draw
    n_sensors: int  # in the data (for the cross)
    field_nT: float
    kept: np.ndarray  # (N,) bool
    floor_nT: float | None = None
    baseline_m: float | None = None
    all_calibrations: list = field(default_factory=list)  # (cinv, R) per sensor for the cross, or empty
    distortion_gain: float = 10.0
    residual_gain: float = 1000.0
    axes_gain: float = 20.0
    inspected: int | None = None
    show_raw: bool = True
    show_corrected: bool = True
    show_ellipsoid: bool = True
    window: np.ndarray | None = None  # (N,) bool: draw only these samples (the time scrubber), None for all
    current: int | None = None  # the window's last sample: each sensor's current direction, marked
    fast: np.ndarray | None = None  # (N,) bool: samples taken while turning fast (magcal_workbench.motion), marked
    ring: np.ndarray | None = None  # (M, 3) unit directions (array frame): the tilt ring, on each corrected sphere
    #: The labels, meshes and the cross beside the clouds. A launch's preview draws the clouds alone: each of these
    #: costs the page a shader or an HTML overlay before its first frame (0.6 s of a 1e6 first picture).
    decorations: bool = True
    #: Which fit corrected the right-hand clouds (``total-field``, ``vector`` or ``gravity``): their labels say it.
    corrected_by: str = "total-field"


@dataclass
class Displayed:
    """Points currently on screen, for picking: world positions and the sample index of each."""

    positions: np.ndarray
    samples: np.ndarray
    sensors: np.ndarray


def display_scale_nT(field_nT) -> float:
    """The field the clouds are divided by (nT): the reference, or 1 nT when there is none to speak of (a
    zero-filled file), so that nothing is drawn at NaN."""
    F = float(field_nT) if field_nT is not None else 0.0
    return F if np.isfinite(F) and F > 0 else 1.0


def level_of_detail(n_samples: int, max_points: int = MAX_POINTS, residual_nT=None) -> np.ndarray:
    """Sorted indices of the samples to draw: all of them up to ``max_points``, else an even stride through the
    recording plus the samples with the largest |residual| on any sensor (:data:`OUTLIER_SHARE` of the budget),
    so a million-sample file sends ~``max_points`` points per cloud and its outliers are still seen.

    Parameters
    ----------
    n_samples : int
    max_points : int
        Most indices returned.
    residual_nT : numpy.ndarray, shape (n_sensors, N) or (N,), optional
        Total-field residuals, nT (NaN where not fitted).
    """
    n, m = int(n_samples), max(int(max_points), 1)
    if n <= m:
        return np.arange(n)
    n_out = 0
    if residual_nT is not None:
        r = np.abs(np.nan_to_num(np.asarray(residual_nT, float), nan=0.0)).reshape(-1, n).max(axis=0)
        n_out = int(OUTLIER_SHARE * m) if np.any(r > 0) else 0
    stride = np.linspace(0, n - 1, m - n_out).round().astype(np.int64)
    if not n_out:
        return np.unique(stride)
    worst = np.argpartition(r, n - n_out)[n - n_out :]
    return np.union1d(stride, worst)


def decimated(model: SceneModel, idx: np.ndarray) -> SceneModel:
    """``model`` restricted to the samples ``idx`` (the same fields, every per-sample array indexed)."""
    from dataclasses import replace

    def cut(a):
        return None if a is None else np.asarray(a)[idx]

    sensors = [
        replace(sv, raw_nT=sv.raw_nT[idx], corrected_nT=cut(sv.corrected_nT), residual_nT=cut(sv.residual_nT))
        for sv in model.sensors
    ]
    return replace(model, sensors=sensors, kept=np.asarray(model.kept, bool)[idx], fast=cut(model.fast))


def iter_layout(model: SceneModel):
    """The drawn clouds one at a time: ``(name, sensor, kind, positions (N, 3))`` (see :func:`layout`)."""
    rows = len(model.sensors)
    F = display_scale_nT(model.field_nT)
    for k, sv in enumerate(model.sensors):
        centre = group_offset(k, rows)
        if model.show_raw:
            raw = exaggerate_radial(sv.raw_nT / F, model.distortion_gain)
            yield f"/data/s{sv.sensor + 1}/raw", sv.sensor, "raw", raw + centre - [PAIR_OFFSET, 0, 0]
        if model.show_corrected and sv.corrected_nT is not None:
            corr = residual_radius_points(
                sv.corrected_nT / F,
                sv.residual_nT if sv.residual_nT is not None else np.zeros(len(sv.corrected_nT)),
                F,
                model.residual_gain,
            )
            yield f"/data/s{sv.sensor + 1}/corrected", sv.sensor, "corrected", corr + centre + [PAIR_OFFSET, 0, 0]


def layout(model: SceneModel):
    """World positions of every drawn cloud: list of ``(name, sensor, kind, positions (N,3))``.

    ``kind`` is ``"raw"`` or ``"corrected"``.
    """
    return list(iter_layout(model))


#: The ambient light in place of the environment map (:func:`light_for_data`).
AMBIENT_INTENSITY = 2.0


def light_for_data(server) -> None:
    """Light ``server``'s scene as a plot, not a photograph: viser's default lights without shadows and no
    environment map. The clouds are flat-shaded and the meshes are translucent guides, so neither needs them.
    They cost a lot where the page renders WebGL in software: viser redraws the scene every second, and with
    them the page at rest after a session's clicks took 0.77 of a 2-core machine's cores, 0.42 without
    (``benchmarks/page_latency.py``, 4 x 1e4). That time was missing from every fit."""
    server.scene.configure_default_lights(True, cast_shadow=False)
    server.scene.configure_environment_map(hdri=None)
    # the environment map's light, evenly from everywhere: the meshes keep their colours
    server.scene.add_light_ambient("/light/ambient", intensity=AMBIENT_INTENSITY)


def _call_key(factory):
    """What a :func:`functools.partial` of a ``scene.add_*`` draws, comparable with ``==`` (arrays by dtype, shape
    and bytes); None for any other factory (a lambda: always drawn again)."""
    if not isinstance(factory, partial):
        return None

    def norm(v):
        if isinstance(v, np.ndarray):
            return ("array", v.dtype.str, v.shape, v.tobytes())
        if isinstance(v, (tuple, list)):
            return tuple(norm(x) for x in v)
        return v

    return (factory.func, norm(factory.args), tuple(sorted((k, norm(v)) for k, v in factory.keywords.items())))


class SceneView:
    """Owns the viser scene nodes and redraws them from a :class:`SceneModel`.

    Parameters
    ----------
    server : viser.ViserServer
        Scene nodes go to ``server.scene`` (shared by every connected browser).
    point_size : float
        Point size in scene units.
    max_points : int
        Most points drawn per cloud (:func:`level_of_detail`).

    Attributes
    ----------
    displayed : Displayed
        The drawn points (for clicks); :meth:`samples_in_rect` tests every sample, drawn or not.
    shown_samples : numpy.ndarray
        Indices of the samples drawn.
    """

    def __init__(self, server, point_size: float = 0.022, max_points: int = MAX_POINTS):
        self.server = server
        light_for_data(server)
        self.point_size = point_size
        self.max_points = int(max_points)
        self.shown_samples = np.zeros(0, int)
        self._full_model: SceneModel | None = None
        self.displayed = Displayed(np.zeros((0, 3)), np.zeros(0, int), np.zeros(0, int))
        self._clouds: dict = {}  # name -> handle
        self._static: dict = {}  # name -> handle (meshes, frames, labels)
        self._static_keys: dict = {}  # name -> the call that drew it (:func:`_call_key`), None if not comparable
        self._shape_key: tuple | None = None
        self.last_limit_nT = 1.0
        #: Point positions sent to the page so far (a cloud's unchanged positions are not sent again).
        self.n_points_sent = 0

    def update(self, model: SceneModel) -> None:
        """Redraw. Clouds whose point count is unchanged are updated in place (positions and colours)."""
        scene = self.server.scene
        kept = np.asarray(model.kept, bool)
        floor = model.floor_nT
        resid_all = [sv.residual_nT for sv in model.sensors if sv.residual_nT is not None]
        limit = colour_limit_nT(np.concatenate([r[kept] for r in resid_all]) if resid_all else [1.0], floor)
        self.last_limit_nT = limit
        self._full_model = model
        if model.window is not None:  # the time scrubber: only the window's samples, decimated within it
            base = np.flatnonzero(np.asarray(model.window, bool))
            sub = level_of_detail(base.size, self.max_points, np.array(resid_all)[:, base] if resid_all else None)
            idx = base[sub]
        else:
            idx = level_of_detail(len(kept), self.max_points, np.array(resid_all) if resid_all else None)
        self.shown_samples = idx
        if idx.size < len(kept):
            model = decimated(model, idx)
            kept = kept[idx]
        clouds = layout(model)
        key = (tuple(c[0] for c in clouds), len(model.sensors), model.n_sensors)
        positions, samples, sensors = [], [], []
        with self.server.atomic():
            if key != self._shape_key:
                for name in list(self._clouds) + list(self._static):
                    scene.remove_by_name(name)
                self._clouds.clear()
                self._static.clear()
                self._static_keys.clear()
                self._shape_key = key
            views = {sv.sensor: sv for sv in model.sensors}
            for name, s, _kind, pts in clouds:
                sv = views[s]
                resid = sv.residual_nT if sv.residual_nT is not None else np.full(len(pts), np.nan)
                colors = residual_colors(resid, limit, kept)
                handle = self._clouds.get(name)
                if handle is not None and len(handle.points) == len(pts):
                    # only what changed is sent: a refit leaves the raw clouds where they are
                    pts32 = pts.astype(np.float32)
                    if not np.array_equal(handle.points, pts32):
                        handle.points = pts32
                        self.n_points_sent += len(pts32)
                    if not np.array_equal(handle.colors, colors):
                        handle.colors = colors
                else:
                    self.n_points_sent += len(pts)
                    if handle is not None:
                        handle.remove()
                    self._clouds[name] = scene.add_point_cloud(
                        name,
                        pts.astype(np.float32),
                        colors,
                        point_size=self.point_size,
                        point_shape="circle",
                        precision="float32",
                        point_shading="flat",
                    )
                positions.append(pts)
                samples.append(idx[: len(pts)])
                sensors.append(np.full(len(pts), s))
            if model.decorations:
                self._draw_static(model)
            self._draw_motion(model, clouds)
            if positions:
                self.displayed = Displayed(np.concatenate(positions), np.concatenate(samples), np.concatenate(sensors))
            else:
                self.displayed = Displayed(np.zeros((0, 3)), np.zeros(0, int), np.zeros(0, int))
            self.mark_inspected(model.inspected)
            self.mark_current(model.current)

    def mark_current(self, sample: int | None) -> None:
        """Mark one sample on every shown cloud (the time window's current direction): a large point, and on the
        corrected side a line from the sphere's centre to it."""
        for name in ("/window/current", "/window/direction"):
            if name in self._static:
                self._static.pop(name).remove()
        if sample is None:
            return
        on = self.displayed.samples == int(sample)
        pts = self.displayed.positions[on]
        if len(pts) == 0:
            return
        self._put(
            "/window/current",
            lambda: self.server.scene.add_point_cloud(
                "/window/current",
                pts.astype(np.float32),
                CURRENT_RGB,
                point_size=self.point_size * 5,
                point_shape="circle",
                precision="float32",
                point_shading="flat",
            ),
        )
        model = self._full_model
        segs = []
        if model is not None and model.show_corrected:
            rows = len(model.sensors)
            for k, sv in enumerate(model.sensors):
                if sv.corrected_nT is None:
                    continue
                centre = group_offset(k, rows) + [PAIR_OFFSET, 0, 0]
                tips = self.displayed.positions[on & (self.displayed.sensors == sv.sensor)]
                if len(tips):  # the corrected point is the one nearer the corrected sphere's centre
                    segs.append([centre, tips[np.argmin(np.linalg.norm(tips - centre, axis=1))]])
        if segs:
            arr = np.array(segs, np.float32)
            self._put(
                "/window/direction",
                lambda: self.server.scene.add_line_segments(
                    "/window/direction", arr, colors=CURRENT_RGB, thickness=4.0, thickness_units="screen"
                ),
            )

    def clear(self) -> None:
        """Remove every node (before loading other data)."""
        with self.server.atomic():
            for name in list(self._clouds) + list(self._static):
                self.server.scene.remove_by_name(name)
        self._clouds.clear()
        self._static.clear()
        self._static_keys.clear()
        self._shape_key = None
        self._full_model = None
        self.shown_samples = np.zeros(0, int)
        self.displayed = Displayed(np.zeros((0, 3)), np.zeros(0, int), np.zeros(0, int))

    def samples_in_rect(self, camera_wxyz, camera_position, fov_rad, aspect, screen_min, screen_max) -> np.ndarray:
        """Indices of the samples (drawn or not: a decimated cloud stands for all of them) whose point in any
        shown cloud projects inside the screen box; sorted, unique."""
        model = self._full_model
        if model is None:
            return np.zeros(0, int)
        if self.shown_samples.size == len(model.kept):
            d = self.displayed
            inside = points_in_rect(d.positions, camera_wxyz, camera_position, fov_rad, aspect, screen_min, screen_max)
            return np.unique(d.samples[inside])
        hits = [
            np.flatnonzero(points_in_rect(pts, camera_wxyz, camera_position, fov_rad, aspect, screen_min, screen_max))
            for _, _, _, pts in iter_layout(model)
        ]
        hit = np.unique(np.concatenate(hits)) if hits else np.zeros(0, int)
        if model.window is not None:  # only what the time window shows
            hit = hit[np.asarray(model.window, bool)[hit]]
        return hit

    def mark_inspected(self, sample: int | None) -> None:
        """Put (or remove) the marker on every shown point of one sample."""
        name = "/inspect"
        if sample is None:
            if name in self._static:
                self._static.pop(name).remove()
            return
        pts = self.displayed.positions[self.displayed.samples == int(sample)]
        if len(pts) == 0:
            return
        self._put(
            name,
            lambda: self.server.scene.add_point_cloud(
                name,
                pts.astype(np.float32),
                INSPECT_RGB,
                point_size=self.point_size * 4,
                point_shape="diamond",
                precision="float32",
                point_shading="flat",
            ),
        )

    def recolor(self, model: SceneModel) -> None:
        """Only the colours (after a change of the kept mask): cheap."""
        kept = np.asarray(model.kept, bool)
        views = {sv.sensor: sv for sv in model.sensors}
        with self.server.atomic():
            for name, handle in self._clouds.items():
                s = int(name.split("/")[2][1:]) - 1
                sv = views.get(s)
                if sv is None:
                    continue
                resid = sv.residual_nT if sv.residual_nT is not None else np.full(len(kept), np.nan)
                idx = self.shown_samples if self.shown_samples.size < len(kept) else slice(None)
                handle.colors = residual_colors(np.asarray(resid)[idx], self.last_limit_nT, kept[idx])

    # --- helpers ----------------------------------------------------------------------------------------------
    def _put(self, name, factory):
        """Replace the static node ``name`` by ``factory()`` (a :func:`functools.partial` of a ``scene.add_*``:
        its arguments are bound when it is made, not when the loop has moved on). A node drawn by the same call
        with equal arguments stays: a refit does not make the page rebuild its labels and lines."""
        key = _call_key(factory)
        if key is not None and name in self._static and self._static_keys.get(name) == key:
            return
        old = self._static.pop(name, None)
        if old is not None:
            old.remove()
        self._static[name] = factory()
        self._static_keys[name] = key

    def _draw_static(self, model: SceneModel) -> None:
        scene = self.server.scene
        rows = len(model.sensors)
        F = display_scale_nT(model.field_nT)
        sv_faces = sphere_mesh(2)
        for k, sv in enumerate(model.sensors):
            centre = group_offset(k, rows)
            tag = f"s{sv.sensor + 1}"
            if model.show_raw:
                self._put(
                    f"/data/{tag}/raw_label",
                    partial(
                        scene.add_label,
                        f"/data/{tag}/raw_label",
                        f"S{sv.sensor + 1} raw",
                        position=centre + [-PAIR_OFFSET, 0, 1.2],
                        anchor="bottom-center",
                    ),
                )
                old = self._static.get(f"/data/{tag}/ellipsoid")
                if model.show_ellipsoid and sv.cinv is not None:
                    v, f = ellipsoid_mesh(sv.cinv, sv.bias_nT, F, model.distortion_gain)
                    if old is not None and len(old.vertices) == len(v):
                        # moved in place: a mesh removed and made again under its name at every live update was
                        # drawn at the origin by the page
                        old.vertices = v.astype(np.float32)
                        old.position = tuple(centre - [PAIR_OFFSET, 0, 0])
                        self._static_keys[f"/data/{tag}/ellipsoid"] = None  # no longer what its call drew
                    else:
                        self._put(
                            f"/data/{tag}/ellipsoid",
                            partial(
                                scene.add_mesh_simple,
                                f"/data/{tag}/ellipsoid",
                                v.astype(np.float32),
                                f,
                                color=ELLIPSOID_RGB,
                                opacity=0.25,
                                side="double",
                                position=centre - [PAIR_OFFSET, 0, 0],
                                cast_shadow=False,
                                receive_shadow=False,
                            ),
                        )
                elif f"/data/{tag}/ellipsoid" in self._static:
                    self._static.pop(f"/data/{tag}/ellipsoid").remove()
            if model.show_corrected and sv.corrected_nT is not None:
                if f"/data/{tag}/sphere" not in self._static:
                    self._put(
                        f"/data/{tag}/sphere",
                        partial(
                            scene.add_mesh_simple,
                            f"/data/{tag}/sphere",
                            sv_faces[0].astype(np.float32),
                            sv_faces[1],
                            color=SPHERE_RGB,
                            wireframe=True,
                            opacity=0.25,
                            position=centre + [PAIR_OFFSET, 0, 0],
                        ),
                    )
                self._put(
                    f"/data/{tag}/corr_label",
                    partial(
                        scene.add_label,
                        f"/data/{tag}/corr_label",
                        f"S{sv.sensor + 1} corrected"
                        + (f" ({model.corrected_by} fit)" if model.corrected_by != "total-field" else ""),
                        position=centre + [PAIR_OFFSET, 0, 1.2],
                        anchor="bottom-center",
                    ),
                )
        if model.n_sensors > 1:  # one sensor is no cross: nothing to draw
            self._draw_cross(model)

    def _draw_motion(self, model: SceneModel, clouds) -> None:
        """The samples taken while turning fast (a red ring round each of their points, every cloud) and the tilt
        ring (a dark circle on each corrected sphere); either removed when the model has none."""
        scene = self.server.scene
        fast = None if model.fast is None else np.asarray(model.fast, bool)
        parts: list = []
        if fast is not None and fast.any():
            rows = len(model.sensors)
            place = {sv.sensor: group_offset(k, rows) for k, sv in enumerate(model.sensors)}
            for _, s, kind, p in clouds:  # a red dot just outside each marked point (its colour stays seen)
                centre = place[s] + [-PAIR_OFFSET if kind == "raw" else PAIR_OFFSET, 0, 0]
                parts.append(centre + (p[fast[: len(p)]] - centre) * FAST_MARK_OUT)
        pts = np.concatenate(parts) if parts else np.zeros((0, 3))
        if len(pts):
            self._put(
                "/motion/fast",
                partial(
                    scene.add_point_cloud,
                    "/motion/fast",
                    pts.astype(np.float32),
                    FAST_RGB,
                    point_size=self.point_size * 0.8,
                    point_shape="circle",
                    precision="float32",
                    point_shading="flat",
                ),
            )
        elif "/motion/fast" in self._static:
            self._static.pop("/motion/fast").remove()
        segs = []
        if model.ring is not None and model.show_corrected:
            ring = np.asarray(model.ring, float) * RING_RADIUS
            loop = np.stack([ring, np.roll(ring, -1, axis=0)], axis=1)
            for k, sv in enumerate(model.sensors):
                if sv.corrected_nT is not None:
                    segs.append(loop + group_offset(k, len(model.sensors)) + [PAIR_OFFSET, 0, 0])
        if segs:
            arr = np.concatenate(segs).astype(np.float32)
            self._put(
                "/motion/ring",
                partial(
                    scene.add_line_segments,
                    "/motion/ring",
                    arr,
                    colors=RING_RGB,
                    thickness=3.0,
                    thickness_units="screen",
                ),
            )
        elif "/motion/ring" in self._static:
            self._static.pop("/motion/ring").remove()

    def _draw_cross(self, model: SceneModel) -> None:
        scene = self.server.scene
        n = model.n_sensors
        centre = cross_centre(len(model.sensors))
        positions = cross_positions(n) @ ARRAY_TO_SCENE.T + centre
        base = (
            f"baseline {model.baseline_m:g} m"
            if model.baseline_m
            else "single sensor"
            if n == 1
            else "baseline not given"
        )
        self._put(
            "/cross/label",
            partial(
                scene.add_label,
                "/cross/label",
                f"cross ({base}); array z toward you",
                position=tuple(centre + [0, 0, 0.5 * CROSS_SPAN + 0.45]),
                anchor="bottom-center",
            ),
        )
        if "/cross/arms" not in self._static:
            if n > 1:  # the cross's arms join opposite sensors (1-3, 2-4); two sensors: one baseline
                segs = (
                    np.array([[positions[0], positions[2]], [positions[1], positions[3 if n > 3 else 1]]])
                    if n > 2
                    else np.array([[positions[0], positions[1]]])
                )
                self._put(
                    "/cross/arms",
                    partial(
                        scene.add_line_segments,
                        "/cross/arms",
                        segs.astype(np.float32),
                        colors=(120, 120, 120),
                        thickness=3.0,
                        thickness_units="screen",
                    ),
                )
        for s in range(n):
            tag = f"/cross/s{s + 1}"
            if f"{tag}/label" not in self._static:
                self._put(
                    f"{tag}/label",
                    partial(
                        scene.add_label,
                        f"{tag}/label",
                        f"S{s + 1}",
                        position=positions[s] + [0.12, 0, 0.12],
                        anchor="bottom-left",
                    ),
                )
                ideal = np.concatenate([[positions[s], positions[s] + 0.4 * e] for e in ARRAY_TO_SCENE.T])
                self._put(
                    f"{tag}/ideal",
                    partial(
                        scene.add_line_segments,
                        f"{tag}/ideal",
                        ideal.reshape(3, 2, 3).astype(np.float32),
                        colors=IDEAL_AXIS_RGB,
                        thickness=1.0,
                        thickness_units="screen",
                    ),
                )
            cal = model.all_calibrations[s] if s < len(model.all_calibrations) else None
            if cal is None:
                continue
            axes = sensor_axes(cal[0], cal[1], model.axes_gain)
            segs = np.stack([np.stack([positions[s], positions[s] + 0.5 * a]) for a in axes @ ARRAY_TO_SCENE.T])
            cols = np.repeat(np.array(AXIS_RGB, np.uint8)[:, None, :], 2, axis=1)
            self._put(
                f"{tag}/axes",
                partial(
                    scene.add_line_segments,
                    f"{tag}/axes",
                    segs.astype(np.float32),
                    colors=cols,
                    thickness=3.0,
                    thickness_units="screen",
                ),
            )
