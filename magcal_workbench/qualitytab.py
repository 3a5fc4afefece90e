"""The Quality tab, a panel of the panel recipe (:mod:`magcal_workbench.panelkit`): the data's quality read before
fitting (:func:`magcal.checks.quality.assess`, with what the fit adds) and the noise behind the floors, given or
estimated, with the handler of its widget beside it.

:class:`QualityTab` is built at its place by :class:`~magcal_workbench.panels.Panels` (``build(panels, gui)``; into
its tab when attached otherwise), is refreshed with the other tabs
(:meth:`Panels.refresh <magcal_workbench.panels.Panels.refresh>`), and offers ``do_apply_noise`` to the page's
widgets like every part's :func:`~magcal_workbench.actions.action`. Its texts are pure functions the tests call.
"""

from __future__ import annotations

from .actions import action
from .events import Change
from .figures import fmt
from .floors import floor_markdown
from .markup import safe_text
from .sessionfile import NOISE_RANGE_nT


def quality_markdown(report) -> str:
    """The data-quality findings (:func:`magcal.checks.quality.assess`), warnings first and marked, each with what it does
    to the fit; the findings with nothing to say are listed in one line at the end."""
    if report is None:
        return "_No quality report._"
    findings = list(report.findings)
    shown = [f for f in findings if f.severity == "warning" or f.notable or f.kind == "sample_rate"]
    shown.sort(key=lambda f: f.severity != "warning")
    lines = []
    for f in shown:
        where = f"sensor {f.sensor}: " if f.sensor is not None else ""
        head = f"{where}{f.summary}"
        if f.severity == "warning":
            lines.append(f"- ⚠ **Warning: {safe_text(head, 600)}**  \n  → {safe_text(f.effect, 600)}")
        else:
            lines.append(f"- {safe_text(head, 600)}  \n  → _{safe_text(f.effect, 600)}_")
    quiet = [f for f in findings if f not in shown]
    if quiet:
        seen = sorted({f.kind.replace("_", " ") for f in quiet})
        lines.append(f"\nChecked, nothing to say: {safe_text(', '.join(seen), 300)}.")
    n_warn = sum(f.severity == "warning" for f in findings)
    head = f"**Data quality**: {n_warn} warning(s)" if n_warn else "**Data quality**: no warning"
    return head + "\n\n" + "\n".join(lines)


def noise_markdown(ctrl) -> str:
    """The noise behind the floors, the method that gave it, and the floor it sets; where the loop works on the
    vector fit, its floor (:func:`magcal_workbench.floors.floor_markdown`), the one every place shows."""
    if ctrl.vector_loop():
        return floor_markdown(ctrl)
    floor = ctrl.floor_nT()
    text = (
        f"**Noise:** {safe_text(ctrl.noise_text(), 800)}  \nTotal-field floor of the current fit: {fmt(floor, 'nT', 3)}"
    )
    noise = ctrl.noise
    if noise is not None and noise.note:
        text += f"  \n_{safe_text(noise.note, 600)}_"
    return text


class QualityTab:
    """The Quality tab's widgets, their handler and their refresh.

    Parameters
    ----------
    ctrl : callable
        ``ctrl()``: the open data's :class:`~magcal_workbench.controller.Controller`.
    """

    #: The tab it fills.
    tab = "Quality"

    def __init__(self, *, ctrl):
        self._ctrl = ctrl
        self.values = None

    def attach(self, panels) -> None:
        """Follow the open data (built already at its place, else into its tab now)."""
        if self.values is None:
            with panels.tab(self.tab):
                self.build(panels, panels.gui)
        self.refresh(("all",))

    def build(self, panels, gui) -> None:
        """Make the widgets (in the tab being built)."""
        self.values = panels.values
        self.noise_info = gui.add_markdown("")
        self.noise_input = panels.w.number(
            "Noise nT per axis",
            0.0,
            min=0.0,
            max=NOISE_RANGE_nT[1],
            step=0.1,
            hint="The sensor's noise per axis (standard deviation, nT) if you know it; 0 = estimate it from the "
            "data (differences in time, still stretches, never below the quantization floor)",
        )
        self.btn_noise = panels.button("Use this noise for the floors", panels.on.do_apply_noise)
        self.quality = gui.add_markdown("")
        panels.tab_panels.append(self)

    @action
    def do_apply_noise(self, event) -> None:
        """Give the noise typed (0: estimate it again); the floors follow."""
        value = float(self.values.check(self.noise_input))
        self._ctrl().set_noise(value if value > 0 else None)

    def refresh(self, kinds) -> None:
        """Follow the fit, the selection and the model (the texts) and other data (the noise typed)."""
        if self.values is None:
            return
        ctrl = self._ctrl()
        everything = "all" in kinds
        # the vector model's diagnosis and fit too: where the loop works on it, its floor is the one shown
        if everything or any(
            k in kinds for k in (Change.RESULT, Change.SELECTION, Change.MODEL, Change.VECTOR, Change.DIAGNOSIS)
        ):
            self.noise_info.content = noise_markdown(ctrl)
            self.quality.content = quality_markdown(ctrl.quality_with_fit())
        if everything or Change.DATA in kinds:
            self.noise_input.value = float(ctrl.state.noise_nT or 0.0)
