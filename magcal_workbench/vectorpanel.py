"""The vector model's widgets (issue 29, issue 32 item 3): the reference from a location (Calibrate tab), the
vector fit beside the total-field fit with their comparison table (Calibrate tab), and the vehicle view's toggle
(View tab).

:class:`VectorPanel` is made by :class:`~magcal_workbench.panels.Panels` and builds into its tabs where the panels
call it; like the panels it is given what it needs (the panels' widget maker, callback runner and actions), never
the app. The text is built by pure functions (``*_markdown``) the tests call directly.
"""

from __future__ import annotations

import datetime as _dt

import numpy as np

from .markup import safe_text
from .sessionfile import ALT_RANGE_M, DATE_CHARS, LAT_RANGE_DEG, LON_RANGE_DEG
from .vectormodel import NED


def _nT(v) -> str:
    return "-" if v is None or not np.isfinite(v) else f"{v:.4g} nT"


def comparison_markdown(vm) -> str:
    """The two fits side by side (:class:`~magcal_workbench.vectormodel.VectorModel`): total-field RMS, world RMS per
    N/E/D, the mounting, the attitude noise, and the total-field fit's undetermined warning where it applies."""
    if vm.attitude_kind() is None:
        return ""
    scalar, vector = vm.scalar_row(), vm.vector_row()
    fitted = vm.result is not None
    sc_total = _nT(scalar.total_field_rms_nT) if scalar.total_field_rms_nT is not None else "not fitted yet"
    rows = [
        "| on the kept samples | total-field fit | vector fit (attitude-aided) |",
        "|---|---|---|",
        f"| total-field RMS | {sc_total} | {_nT(vector.total_field_rms_nT) if fitted else 'not run yet'} |",
    ]
    if fitted:
        rows.append(f"| samples fitted | - | {safe_text(vector.samples, 200)} |")
    for k, c in enumerate(NED):
        world = _nT(vector.world_rms_nT[k]) if vector.world_rms_nT is not None else "-"
        rows.append(f"| world {c} RMS | n/a: its rotation is unknown | {world} |")
    mounting = safe_text("; ".join(vector.mounting), 400) if vector.mounting else "-"
    rows.append(f"| mounting found | not determined (a gauge) | {mounting} |")
    noise = safe_text("; ".join(vector.attitude_noise), 300) if vector.attitude_noise else "-"
    rows.append(f"| attitude noise | - | {noise} |")
    text = "\n".join(rows)
    if scalar.undetermined:
        text += "\n\n⚠ **The total-field fit is undetermined here**: " + safe_text(scalar.undetermined[0], 600)
    for w in vector.warnings:
        text += f"\n- vector fit: {safe_text(w, 600)}"
    return text


def availability_markdown(vm) -> str:
    """What the data offer the vector fit: the attitude and where the reference vector comes from, or what is
    missing."""
    kind = vm.attitude_kind()
    if kind is None:
        return (
            "_**Vector model**: these data have no attitude (`qw, qx, qy, qz` or `roll_deg, pitch_deg, yaw_deg`), "
            "so only the total-field fit applies._"
        )
    att = "quaternions `qw..qz`" if kind == "quaternion" else "`roll_deg, pitch_deg, yaw_deg`"
    missing = vm.missing()
    if missing:
        return f"**Vector model**: attitude from {att}; the fit also needs {safe_text(' and '.join(missing), 400)}"
    try:
        ref = vm.reference()
        where = "?" if ref is None else safe_text(ref.text, 400)
    except Exception as exc:  # an IGRF failure is said, not raised, in a status line
        where = f"not available ({safe_text(str(exc), 300)})"
    return f"**Vector model**: attitude from {att}; reference vector: {where}"


def location_markdown(vm) -> str:
    """The location in use (or none), and why a saved one could not be used."""
    loc = vm.location
    text = (
        f"_Location in use:_ {safe_text(loc.text(), 400)}"
        if loc is not None
        else "_No location typed: the file's reference is used (or the field magnitude is fitted)._"
    )
    if vm.location_note:
        text += f"  \n{vm.location_note}"
    return text


class VectorPanel:
    """The vector model's widgets, built into the panels' tabs.

    Parameters
    ----------
    panels : magcal_workbench.panels.Panels
        Gives ``w`` (the checked widget maker), ``_button``, ``handle``, ``on`` (the actions: ``do_use_location``,
        ``do_forget_location``, ``do_vector_fit``, ``do_vehicle_view``, ``do_vehicle_options``, ``vehicle_text``)
        and ``ctrl``.
    """

    def __init__(self, panels):
        self.p = panels

    # --- construction --------------------------------------------------------------------------------------
    def build_location(self, gui) -> None:
        """Calibrate tab, under the reference: a place and date -> IGRF (the scalar and the vector reference)."""
        p = self.p
        with gui.add_folder("Reference from a location (IGRF)", expand_by_default=False):
            self.lat = p.w.number(
                "Latitude deg", 0.0, min=LAT_RANGE_DEG[0], max=LAT_RANGE_DEG[1], step=0.0001, hint="north positive"
            )
            self.lon = p.w.number(
                "Longitude deg", 0.0, min=LON_RANGE_DEG[0], max=LON_RANGE_DEG[1], step=0.0001, hint="east positive"
            )
            self.alt = p.w.number(
                "Altitude m",
                0.0,
                min=ALT_RANGE_M[0],
                max=ALT_RANGE_M[1],
                step=1.0,
                hint="height above the WGS84 ellipsoid, m",
            )
            self.date = p.w.text(
                "Date",
                _dt.date.today().isoformat(),
                max_chars=DATE_CHARS,
                hint="YYYY-MM-DD or a decimal year (2024.5), within the IGRF model's years",
            )
            self.btn_location = p._button(gui, "Use this location (IGRF)", p.on.do_use_location, engine=False)
            self.btn_forget = p._button(gui, "Forget the location", p.on.do_forget_location, engine=False)
            self.location_info = gui.add_markdown("")

    def build_calibrate(self, gui) -> None:
        """Calibrate tab, after the total-field steps: the vector fit and the two fits side by side."""
        p = self.p
        with gui.add_folder("Vector model (attitude-aided)", expand_by_default=True):
            self.info = gui.add_markdown("")
            self.btn_vector = p._button(
                gui,
                "Run the vector fit (attitude-aided)",
                p.on.do_vector_fit,
                color="teal",
                hint="magcal's fit_vector: bias, matrix and the sensor's mounting into the body frame, from the "
                "attitude and the field vector; shown beside the total-field fit",
            )
            self.table = gui.add_markdown("")

    def build_view(self, gui) -> None:
        """View tab: the vehicle view's toggle and its residual exaggeration."""
        p = self.p
        with gui.add_folder("Vehicle view", expand_by_default=True):
            self.vehicle_on = gui.add_checkbox(
                "Show the vehicle view",
                False,
                hint="The body turned by its attitude, the model and the measured field in world axes N, E, D, and "
                "their difference; the time window's Play flies it through the record",
            )
            self.vehicle_gain = p.w.number(
                "Residual arrows x",
                0.0,
                min=0.0,
                max=1e7,
                step=1.0,
                hint="exaggeration of the red arrow; 0 = automatic",
            )
            self.vehicle_info = gui.add_markdown("")
        self.vehicle_on.on_update(lambda e: p.handle(p.on.do_vehicle_view, e))
        self.vehicle_gain.on_update(lambda e: p.handle(p.on.do_vehicle_options, e))

    # --- refresh -------------------------------------------------------------------------------------------
    def refresh(self, kinds) -> None:
        """Write what changed into the widgets (``kinds`` as :meth:`Panels.refresh` takes them)."""
        kinds = set(kinds)
        everything = "all" in kinds
        vm = self.p.ctrl().vector
        has_attitude = vm.attitude_kind() is not None
        if "vector" in kinds:  # a location sets the Reference field box: show it
            self.p.show_state()
        if everything or kinds & {"data", "vector", "settings"}:
            self.info.content = availability_markdown(vm)
            self.location_info.content = location_markdown(vm)
            self.btn_vector.visible = has_attitude
        if everything or kinds & {"data", "vector", "result", "selection", "settings"}:
            self.table.content = comparison_markdown(vm)
            self.table.visible = vm.available or vm.result is not None
        if everything or "data" in kinds:
            loc = vm.location
            if loc is not None:  # show the session's place (the widgets' callbacks do nothing)
                self.lat.value, self.lon.value, self.alt.value, self.date.value = (
                    loc.lat_deg,
                    loc.lon_deg,
                    loc.alt_m,
                    loc.date,
                )
            self.refresh_vehicle()

    def refresh_vehicle(self) -> None:
        self.vehicle_info.content = self.p.on.vehicle_text()
