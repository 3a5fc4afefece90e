"""The evidence plots: the Model tab's plotly figure, the full-size image over the canvas, and their downloads
(PNG, SVG). The figures are :mod:`magcal_workbench.plots`'; this module places them."""

from __future__ import annotations

import base64
import os

from magcal.core.errors import MagcalError

from .actions import action
from .parts import PagePart
from .plots import add_figure, evidence_figure, evidence_image
from .timewindow import sample_times

#: The Model tab's plotly figure's height over its width (four panels; more make it taller).
PANELS_ASPECT = 3.0


class Evidence(PagePart):
    """The evidence plots of the current fit.

    Handed what it uses.

    Parameters
    ----------
    ctrl, panels : callable
        Getters: the open data's :class:`~magcal_workbench.controller.Controller` and the
        :class:`~magcal_workbench.panels.Panels` (made after this part).
    window : magcal_workbench.timewindow.TimeWindow
        The time scrubber's window (its band is shaded on the plots).
    maps : magcal_workbench.maps.SphereMaps
        The RMS before the last fit.
    downloads : magcal_workbench.downloads.Downloads
        Sends the PNG and SVG.
    server : viser.ViserServer
        Where the plotly figure is added.
    """

    def __init__(self, *, ctrl, panels, window, maps, downloads, server):
        self._ctrl, self._panels = ctrl, panels
        self.window, self.maps, self.downloads, self.server = window, maps, downloads, server
        #: The Model tab's plotly handle (made at the first fit).
        self.plot = None

    def band(self):
        """The time window's bounds (s) shaded on the plots, or None when the window is off."""
        return self.window.bounds_s(sample_times(self.ctrl.dataset)) if self.window.enabled else None

    def title(self) -> str:
        ctrl = self.ctrl
        vector = ctrl.vector_loop()
        model = ", ".join(ctrl.vector.effects if vector else ctrl.state.effects) or "base terms only"
        which = "vector model" if vector else "model"
        return f"{ctrl.dataset.source and os.path.basename(str(ctrl.dataset.source))}: {which} {model}"

    def candidate(self) -> str | None:
        """The Candidate chosen in the Model tab (the vector model's plots put its channel on their axis)."""
        value = self.panels.candidate_choice.value
        return None if value == "-" else value

    @action(name="draw_evidence")
    def draw(self) -> None:
        fig = evidence_figure(
            self.ctrl,
            window_s=self.band(),
            before_rms_nT=self.maps.before_rms_nT(self.ctrl),
            candidate=self.candidate(),
        )
        if fig is None:
            if self.plot is not None:
                self.plot.visible = False
            return
        if self.panels.evidence_overlay.visible:
            self.show_full(True)
        # viser's client draws plotly at height = width * aspect (the docstring says width/height): a panel is as
        # tall as a quarter of 3 widths, however many there are (the vector model's five)
        rows = sum(1 for key in fig.layout.to_plotly_json() if key.startswith("yaxis"))
        aspect = max(PANELS_ASPECT, 0.75 * rows)
        if self.plot is None:
            with self.panels.evidence_holder:
                self.plot = add_figure(self.server.gui, fig, aspect=aspect)
        else:
            self.plot.figure = fig
            self.plot.aspect = aspect
            self.plot.visible = True

    def image(self, fmt: str) -> bytes:
        data = evidence_image(
            self.ctrl, fmt, self.band(), self.title(), self.maps.before_rms_nT(self.ctrl), self.candidate()
        )
        if data is None:
            raise MagcalError("fit first: the evidence plots show the residuals of a fit")
        return data

    def show_full(self, on: bool) -> None:
        """Show (or hide) the evidence plots over the canvas, left of the panel: a PNG drawn by the engine's
        numbers (:func:`magcal_workbench.plots.evidence_image`), the same data as the Model tab's plots."""
        panels = self.panels
        overlay = panels.evidence_overlay
        if not on:
            overlay.visible = False
            panels.btn_full_evidence.label = "Full-size evidence"
            return
        data = base64.b64encode(self.image("png")).decode("ascii")
        overlay.content = (
            '<div style="position:fixed;left:0;top:0;width:calc(100vw - 27em);height:100vh;'
            'background:white;z-index:50;overflow:auto;padding:0.5em;box-sizing:border-box">'
            f'<img alt="evidence plots" src="data:image/png;base64,{data}" '
            'style="display:block;margin:0 auto;max-width:100%;max-height:calc(100vh - 1em);width:auto;height:auto">'
            "</div>"
        )
        overlay.visible = True
        panels.btn_full_evidence.label = "Back to the scene"

    @action
    def do_full_evidence(self, event):
        self.show_full(not self.panels.evidence_overlay.visible)

    @action
    def do_download_evidence_png(self, event):
        self.downloads.send(event, "evidence.png", self.image("png"))

    @action
    def do_download_evidence_svg(self, event):
        self.downloads.send(event, "evidence.svg", self.image("svg"))
