"""Residual maps on the sphere: a smooth surface per sensor, coloured by a direction pattern in nT.

Beside (inside) each corrected cloud the View tab's *Sphere surface* draws one of

* ``residual pattern``: where on the direction sphere the current model fails
  (:func:`magcal.diagnosis.residual_patterns`);
* ``candidate's pattern``: what the candidate chosen in the Model tab would explain if added
  (:func:`magcal.diagnosis.candidate_patterns`): the shape of what is missing, before adding it;
* ``change at the last step``: the residual before the last fit minus the residual now, on the same samples:
  what the last Add-and-refit (or any refit) took away (model against model).

Directions the samples never visited are grey: an expansion there is an extrapolation. The surfaces share one colour
scale (the largest pattern), so the sensor that fails stands out; the legend prints it. The patterns are the
engine's; this module draws them.
"""

from __future__ import annotations

import numpy as np

from magcal.diagnosis import candidate_patterns, residual_patterns

from . import scene as scn
from .controller import candidate_label

SURFACE_CHOICES = ("none", "residual pattern", "candidate's pattern", "change at the last step")
#: Radius of a surface (the corrected cloud lies at radius 1 +- the residual exaggeration), scene units.
SURFACE_RADIUS = 0.9
UNSUPPORTED_RGB = (205, 205, 205)
#: Icosphere subdivisions of a surface (642 vertices at 3).
SUBDIVISIONS = 3


def sphere_vertices_faces(subdivisions: int = SUBDIVISIONS):
    """Unit icosphere (trimesh): vertices (V, 3) and faces (F, 3)."""
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=subdivisions)
    return np.asarray(mesh.vertices, float), np.asarray(mesh.faces, np.int64)


def pattern_colours(pattern, limit_nT: float | None = None) -> np.ndarray:
    """Vertex colours (V, 3) uint8 of a :class:`magcal.diagnosis.DirectionPattern`: the residual colour map
    scaled to ``limit_nT`` (default the pattern's own largest supported value), grey where unsupported."""
    limit = limit_nT if limit_nT else max(pattern.amplitude_nT, 1e-9)
    colours = np.asarray(scn.residual_colors(pattern.value_nT, limit), np.uint8).copy()
    colours[~pattern.supported] = UNSUPPORTED_RGB
    return colours


def surface_visuals(rgba):
    """The look of a surface (trimesh visuals, for ``mesh.visual``): its vertex colours ``rgba`` (V, 4) uint8 on a
    matte, non-metallic material. A mesh with vertex colours alone reaches the page with glTF's default material, which is fully
    metallic: with no environment map (:func:`magcal_workbench.scene.light_for_data`) it would be drawn black."""
    import trimesh

    material = trimesh.visual.material.PBRMaterial(metallicFactor=0.0, roughnessFactor=1.0)
    visuals = trimesh.visual.TextureVisuals(material=material)
    visuals.vertex_attributes["color"] = np.asarray(rgba, np.uint8)
    return visuals


class SphereMaps:
    """The surfaces drawn for the current choice; :meth:`refresh` recomputes and redraws them.

    Parameters
    ----------
    server : viser.ViserServer
        Where the surfaces are drawn.
    ctrl : callable
        Returns the current :class:`~magcal_workbench.controller.Controller`.
    candidate : callable
        Returns the candidate chosen in the Model tab (its label, or ``-``).
    """

    def __init__(self, server, ctrl, candidate):
        self._server = server
        self._ctrl = ctrl
        self._candidate = candidate
        self.choice = SURFACE_CHOICES[0]
        self.patterns = []  # DirectionPattern per shown sensor (for tests and the legend)
        self.note = ""
        self._nodes = {}
        self._previous = None  # (calibration id, residual (n_sensors, N)) before the last fit
        self._current = None
        self._vf = None

    # --- what changed -----------------------------------------------------------------------------------------
    def fit_changed(self, ctrl) -> None:
        """Remember the residual before and after each new fit (for ``change at the last step``)."""
        if ctrl.residual_nT is None or ctrl.calibration is None:
            self._previous = self._current = None
            return
        key = id(ctrl.calibration)
        if self._current is not None and self._current[0] == key:
            return
        self._previous = self._current
        self._current = (key, np.array(ctrl.residual_nT, float))

    def before_rms_nT(self, ctrl):
        """Total-field RMS per sensor (kept samples) before the last fit of these data, or None."""
        if self._previous is None or ctrl.residual_nT is None or self._previous[1].shape != ctrl.residual_nT.shape:
            return None
        r = self._previous[1][:, ctrl.kept]
        return np.sqrt(np.nanmean(r * r, axis=1))

    # --- computing --------------------------------------------------------------------------------------------
    def compute(self, choice: str):
        """The patterns per sensor of the data for ``choice`` and a note (why there are none), engine calls."""

        ctrl = self._ctrl()
        if choice == "none":
            return [], ""
        if ctrl.calibration is None or ctrl.residual_nT is None:
            return [], "fit first: the surface shows a pattern of the residuals"
        if self._vf is None:
            self._vf = sphere_vertices_faces()
        verts = self._vf[0]
        ds = ctrl.dataset
        if choice == "residual pattern":
            return residual_patterns(ds, ctrl.calibration, ctrl.residual_nT, verts, kept=ctrl.kept), ""
        if choice == "change at the last step":
            if self._previous is None or self._previous[1].shape != ctrl.residual_nT.shape:
                return [], "no earlier fit of these data to compare with: refit or add an effect first"
            change = self._previous[1] - ctrl.residual_nT
            return residual_patterns(ds, ctrl.calibration, change, verts, kept=ctrl.kept), ""
        diagnosis = ctrl.diagnosis
        if diagnosis is None or not diagnosis.candidates:
            return [], "press Diagnose and choose a candidate"
        label = self._candidate()
        cand = next((c for c in diagnosis.candidates if candidate_label(c) == label), None)
        if cand is None:
            return [], "choose a candidate in the Model tab"
        if diagnosis.result is None or diagnosis.result.residuals_nT.shape[1] != ds.n_samples:
            return [], "diagnose again: the data changed since"
        return candidate_patterns(ds, diagnosis, cand, verts), f"what adding {label} would explain"

    def refresh(self, choice: str | None = None) -> None:
        """Recompute for ``choice`` (default: the current one) and redraw."""
        if choice is not None:
            self.choice = choice
        patterns, note = self.compute(self.choice)
        self.patterns, self.note = patterns, note
        self.draw()

    # --- drawing ----------------------------------------------------------------------------------------------
    def clear(self) -> None:
        for handle in self._nodes.values():
            handle.remove()
        self._nodes.clear()

    def draw(self) -> None:
        import trimesh

        self.clear()
        ctrl = self._ctrl()
        if not self.patterns:
            return
        shown = range(ctrl.dataset.n_sensors) if ctrl.state.sensor is None else [ctrl.state.sensor]
        shown = list(shown)
        verts, faces = self._vf
        scene = self._server.scene
        limit = self.limit_nT
        with self._server.atomic():
            for k, s in enumerate(shown):
                p = self.patterns[s]
                centre = scn.group_offset(k, len(shown)) + [scn.PAIR_OFFSET, 0, 0]
                mesh = trimesh.Trimesh(SURFACE_RADIUS * verts, faces, process=False)
                rgba = np.column_stack([pattern_colours(p, limit), np.full(len(verts), 255, np.uint8)])
                mesh.visual = surface_visuals(rgba)
                name = f"/maps/s{s + 1}/surface"
                self._nodes[name] = scene.add_mesh_trimesh(name, mesh, position=tuple(centre))

    @property
    def limit_nT(self) -> float:
        """The surfaces' common colour scale: the largest supported value of any pattern, nT."""
        return max([p.amplitude_nT for p in self.patterns] + [1e-9])

    def describe(self) -> str:
        """The View tab's line under the choice."""
        if self.choice == "none":
            return ""
        if not self.patterns:
            return self.note
        amps = ", ".join(f"S{i + 1} +-{scn.readable_nT(p.amplitude_nT)}" for i, p in enumerate(self.patterns))
        lead = f"{self.note}: " if self.note else ""
        return (
            f"{lead}colour scale per sensor (nT): {amps}; grey: directions never visited; degree up to "
            f"{max(p.max_degree for p in self.patterns)}"
        )
