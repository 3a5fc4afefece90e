"""The first picture of a file (start fast): its preview's raw clouds, drawn while the engine is
imported and the whole file read.

:func:`magcal.data.io.read_csv_preview` reads a few thousand lines spread through the file; they are drawn as the
raw clouds the workbench will draw (the same :class:`~magcal_workbench.scene.SceneView`, which the
:class:`~magcal_workbench.app.Workbench` takes over and redraws in place), and the camera of a page that opens
meanwhile frames them.
"""

from __future__ import annotations

import numpy as np

from magcal.data import io as mio

from . import scene as scn

#: Most lines a preview reads: a record of up to this many samples is previewed whole (and its raw clouds are
#: then not sent again); a larger one is drawn from this many lines spread through it until the whole is read.
PREVIEW_ROWS = 10_000


def preview_model(dataset) -> scn.SceneModel:
    """The scene of ``dataset`` before any fit: its raw clouds scaled by the record's field (what the workbench's
    scene shows before a fit), every sample kept, no corrected cloud, and nothing beside the clouds (the labels and
    the cross follow with the workbench: the page paints bare clouds sooner)."""
    field_nT = scn.record_field_nT(dataset)
    views = [
        scn.SensorView(sensor=s, raw_nT=dataset.readings_nT[s], corrected_nT=None, residual_nT=None)
        for s in range(dataset.n_sensors)
    ]
    return scn.SceneModel(
        sensors=views,
        n_sensors=dataset.n_sensors,
        field_nT=field_nT,
        kept=np.ones(dataset.n_samples, bool),
        baseline_m=dataset.baseline_m,
        show_corrected=False,
        # the gain the workbench will choose: a preview of the whole record is then its scene, sent once
        distortion_gain=scn.distortion_gain(dataset.readings_nT, field_nT),
        decorations=False,
    )


def draw_preview(server, path, max_points: int = scn.MAX_POINTS):
    """Draw the preview of the CSV ``path`` on ``server``'s scene.

    Parameters
    ----------
    server : viser.ViserServer
    path : str
        The data file. Every CSV is previewed, a small one too: the preview needs only the reader and the scene,
        so its picture comes before the engine's other parts are imported (about a second); a file of at most
        :data:`PREVIEW_ROWS` (and ``max_points``) lines is previewed whole, and the workbench then sends none of its points again.
    max_points : int
        The workbench's ``--max-points``: at most this many (and :data:`PREVIEW_ROWS`) samples previewed.

    Returns
    -------
    tuple of (magcal_workbench.scene.SceneView, int) or None
        The scene drawn and the number of samples in it; None when no preview was taken.
    """
    # any size (see ``path`` above), at most PREVIEW_ROWS lines: the browser paints fewer points sooner
    ds = mio.read_csv_preview(path, max_rows=min(max_points, PREVIEW_ROWS), min_bytes=0)
    if ds is None:
        return None
    view = scn.SceneView(server, max_points=max_points)
    view.update(preview_model(ds))
    n_groups = ds.n_sensors
    position, look_at = scn.camera_pose(n_groups, cross=n_groups > 1)
    server.initial_camera.position = tuple(float(v) for v in position)
    server.initial_camera.look_at = tuple(float(v) for v in look_at)
    server.initial_camera.up = (0.0, 0.0, 1.0)
    return view, ds.n_samples
