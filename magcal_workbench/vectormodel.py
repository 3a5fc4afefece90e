"""The vector model in the workbench: the attitude-aided fit beside the total-field fit, and the
reference from a location typed in the page.

A record with attitude (``qw, qx, qy, qz`` or ``roll_deg, pitch_deg, yaw_deg``) and a field vector (``ref_n, ref_e,
ref_d`` columns, IGRF along ``lat, lon, alt_m`` columns, or IGRF at the place and date typed in the Calibrate tab)
can be calibrated by the engine's vector fit mode (:data:`magcal.modes.VECTOR`, the same fit, diagnosis and plots' data
as ``magcal.calibrate(ds, mode="vector")``): the mounting into the body frame is then determined, and so are the world
(north-east-down) components. :class:`VectorModel` belongs to one :class:`~magcal_workbench.controller.Controller`; it
chooses the reference, runs the mode's fit on the kept samples, and keeps what the page shows (the comparison table,
the vehicle view's vectors). The physics is the engine's: the fit, IGRF (:mod:`magcal.checks.reference`), the attitude (:mod:`magcal.data.attitude`), the coverage
check that says when a total-field fit is undetermined (:func:`magcal.checks.coverage.calibration_input_checks`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from magcal.checks.coverage import calibration_input_checks
from magcal.checks.reference import VECTOR_COLUMNS, igrf_ned_nT, igrf_place, parse_date, resolve_vector_reference
from magcal.core.errors import MagcalError
from magcal.data.attitude import attitude_rows, attitude_source
from magcal.data.site import record_site
from magcal.model.terms import EFFECTS
from magcal.modes import VECTOR

from .events import Change
from .floors import VectorNoise
from .floors import lowest as lowest_noise
from .markup import clean_text, hide_paths, safe_code, safe_text
from .modelsession import ModelSession, register_session
from .sessionfile import ALT_RANGE_M, DATE_CHARS, LAT_RANGE_DEG, LON_RANGE_DEG
from .state import JobInputs, VectorStep, effect_name, pack_mask, unpack_mask

#: The world components' names, in order.
NED = ("N", "E", "D")


def _rms(a, axis=None):
    a = np.asarray(a, dtype=float)
    return np.sqrt(np.nanmean(a**2, axis=axis))


@dataclass
class Location:
    """A place and date typed in the page: the reference through IGRF.

    Attributes
    ----------
    lat_deg, lon_deg : float
        Geodetic latitude and longitude (deg, north and east positive).
    alt_m : float
        Height above the WGS84 ellipsoid (m).
    date : str
        ISO date (``2024-06-01``) or decimal year.
    ned_nT : numpy.ndarray, shape (3,)
        The IGRF main field there (nT, north-east-down).
    """

    lat_deg: float
    lon_deg: float
    alt_m: float
    date: str
    ned_nT: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @property
    def total_nT(self) -> float:
        return float(np.linalg.norm(self.ned_nT))

    def to_dict(self) -> dict:
        """What the session file keeps (the field is computed again when the session reopens)."""
        return {"lat_deg": self.lat_deg, "lon_deg": self.lon_deg, "alt_m": self.alt_m, "date": self.date}

    def text(self) -> str:
        n, e, d = self.ned_nT
        return (
            f"IGRF at {self.lat_deg:.4f} N, {self.lon_deg:.4f} E, {self.alt_m:g} m, {self.date}: N {n:.1f}, "
            f"E {e:.1f}, D {d:.1f} nT (|B| {self.total_nT:.1f} nT)"
        )


def check_location(lat_deg, lon_deg, alt_m, date) -> Location:
    """A :class:`Location` with its IGRF field, or one clear :class:`MagcalError` naming the input that is wrong.

    The values come from a browser: each is checked for type and range before the engine sees it."""

    def number(name, value, lo, hi, unit):
        ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
        if not ok or not lo <= value <= hi:
            raise MagcalError(f"{name} {clean_text(repr(value), 40)}: give a number in {lo:g} ... {hi:g} {unit}")
        return float(value)

    lat = number("latitude", lat_deg, *LAT_RANGE_DEG, "deg")
    lon = number("longitude", lon_deg, *LON_RANGE_DEG, "deg")
    alt = number("altitude", alt_m, *ALT_RANGE_M, "m")
    if not isinstance(date, str) or not date.strip() or len(date) > DATE_CHARS:
        raise MagcalError("date: type it as YYYY-MM-DD (e.g. 2024-06-01) or a decimal year (2024.5)")
    text = date.strip()
    when = parse_date(text)  # a MagcalError naming the date when it is none
    ned = igrf_ned_nT(lat, lon, alt / 1000.0, when)[0]  # a MagcalError outside the model's years
    return Location(lat, lon, alt, text, np.asarray(ned, dtype=float))


def _changes(before, after) -> str:
    """One line: the world RMS per N/E/D and |B| before -> after a vector fit (:class:`FitRow` each)."""

    def world(row):
        return "/".join(f"{v:.4g}" for v in row.world_rms_nT)

    if after.world_rms_nT is None:
        return ""
    if before is None or before.world_rms_nT is None:
        return f"world RMS N/E/D {world(after)} nT, |B| {after.total_field_rms_nT:.4g} nT"
    return (
        f"world RMS N/E/D {world(before)} -> {world(after)} nT, |B| {before.total_field_rms_nT:.4g} -> "
        f"{after.total_field_rms_nT:.4g} nT"
    )


@dataclass
class FitRow:
    """One column of the comparison table: a fit's figures on the kept samples.

    Attributes
    ----------
    name : str
    total_field_rms_nT : float or None
        RMS of ``|B| - F`` (all sensors), nT.
    world_rms_nT : numpy.ndarray, shape (3,), or None
        RMS per world component N, E, D of ``B_world - B_ref`` (all sensors), nT; None when the fit cannot give
        world components (a total-field fit leaves the sensor's rotation a gauge).
    mounting : list of str
        Per sensor: the right angle found and the angle off it.
    attitude_noise : list of str
        Per sensor: the attitude error the vector residual implies (deg) and whether given or estimated.
    warnings : list of str
        The fit's notes.
    undetermined : list of str
        Why the fit is not determined by these data (a total-field fit on a cone of directions: the coverage
        check's notes); empty when it is.
    samples : str
        The samples fitted, in words: ``"4688 of 5000 kept samples (312 without attitude left out)"``.
    """

    name: str
    total_field_rms_nT: float | None = None
    world_rms_nT: np.ndarray | None = None
    mounting: list = field(default_factory=list)
    attitude_noise: list = field(default_factory=list)
    warnings: list = field(default_factory=list)
    undetermined: list = field(default_factory=list)
    samples: str = ""


#: Largest record (samples x sensors) whose saved vector fit is run again when its session opens, about 1 s (measured
#: on a shared two-core machine with the default eddy terms: 6000 samples of one sensor 0.2 s, 10^5 samples 4.5 s);
#: a larger one keeps its settings and the page says to press the button.
RESTORE_MAX_SAMPLES = 30_000


def _kept(ctrl, kept, inputs: JobInputs | None) -> np.ndarray:
    """The samples a step fits: ``kept`` when given, else those of ``inputs``, else the kept samples of now."""
    if kept is None and inputs is not None:
        kept = inputs.kept
    return np.asarray(ctrl.kept if kept is None else kept, dtype=bool)


def fitted_samples_text(result) -> str:
    """The samples a vector fit used, in words, naming those left out for lack of an attitude or a reference
    (:class:`magcal.fitting.vector.SampleGaps`)."""
    gaps = result.gaps
    if gaps is None or not gaps.n_left_out:
        return f"{result.n_samples} kept samples"
    why = []
    if gaps.n_without_attitude:
        why.append(f"{gaps.n_without_attitude} without attitude")
    if gaps.n_without_reference:
        why.append(f"{gaps.n_without_reference} without a reference vector")
    return f"{result.n_samples} of {gaps.n_chosen} kept samples ({' and '.join(why)} left out)"


@register_session
class VectorSession(ModelSession):
    """The vector model of one controller's data: reference, fit, and what the page shows of it (the model session
    of the fit mode ``"vector"``).

    Parameters
    ----------
    ctrl : magcal_workbench.controller.Controller
        Gives the dataset, the session state (kept mask, robust loss, noise, the location), the total-field
        calibration, and the page's message and change events.

    Attributes
    ----------
    result : magcal.fitting.vector.VectorFitResult or None
        The last vector fit.
    world_nT : numpy.ndarray, shape (n_sensors, N, 3), or None
        Its corrected readings rotated to the world frame (every sample).
    reference_ned_nT : numpy.ndarray, shape (N, 3), or None
        The reference field vector of the last fit (nT, north-east-down).
    effects : list of str
        The vector model's effects beyond the base terms (labels, in the order added): the loop's Add puts the
        diagnosis's candidates here (:meth:`add`); the total-field model's are the session's ``effects``.
    diagnosis : magcal.diagnosis.vector.VectorDiagnosis or None
        The last diagnosis of the vector fit (:meth:`diagnose`); None after a fit.
    evidence : dict or None
        The plot data of the last fit (:meth:`magcal.modes.vector.VectorMode.evidence`: world and |B| residuals,
        the channels), every sample.
    floor_nT : float or None
        The world components' noise floor (nT) the last diagnosis found (attitude error and sensor noise): a
        property of the record, kept across refits.
    """

    mode = "vector"
    title = "vector model"

    def __init__(self, ctrl):
        super().__init__(ctrl)
        self.result = None
        self.world_nT: np.ndarray | None = None
        self.reference_ned_nT: np.ndarray | None = None
        self.reference_text = ""
        saved_fit = getattr(ctrl.state, "vector_fit", None) or {}
        self.effects = list(saved_fit.get("effects", []))
        self.evidence: dict | None = None
        self.floor_nT: float | None = None
        #: The record's vector noise (:class:`magcal_workbench.floors.VectorNoise`): the lowest the diagnoses found.
        self.noise: VectorNoise | None = None
        self._fit_key: tuple | None = None  # what the last fit was asked: kept mask, effects, robust, noise
        self.location: Location | None = None
        self.location_note = ""
        self._coverage_key = None
        self._coverage_notes: list = []
        self._reference_cache: tuple = (None, None)
        saved = getattr(ctrl.state, "location", None)
        if saved:
            try:
                self.location = check_location(saved["lat_deg"], saved["lon_deg"], saved["alt_m"], saved["date"])
            except (MagcalError, KeyError, TypeError) as exc:  # IGRF not installed, or a hand-edited session
                self.location_note = f"the saved location could not be used ({safe_text(str(exc), 300)})"

    # --- what the data offer ----------------------------------------------------------------------------------
    @property
    def dataset(self):
        return self.ctrl.dataset

    def attitude_kind(self) -> str | None:
        """``"quaternion"``, ``"euler"`` or None (:func:`magcal.data.attitude.attitude_source`)."""
        return attitude_source(self.dataset)

    def reference(self):
        """The reference field vector (:class:`magcal.checks.reference.VectorReference`) or None: the location
        typed in the page first (the user asked for it), then the file's ``ref_n, ref_e, ref_d`` columns, then IGRF
        along its ``lat, lon, alt_m`` columns (at the typed date, else today)."""
        ds = self.dataset
        loc = self.location
        key = None if loc is None else tuple(loc.to_dict().values())
        if self._reference_cache[0] == key and self._reference_cache[1] is not None:
            return self._reference_cache[1]
        if loc is not None:
            ref = resolve_vector_reference(ds, "igrf", loc.lat_deg, loc.lon_deg, loc.alt_m / 1000.0, loc.date)
        elif any(c in ds.extra for c in VECTOR_COLUMNS):
            ref = resolve_vector_reference(ds)
        elif self._has_track():
            ref = resolve_vector_reference(ds, "igrf")
        else:
            ref = None
        self._reference_cache = (key, ref)
        return ref

    def missing(self) -> list[str]:
        """What the vector fit lacks (empty when it can run), in words for the page."""
        out = []
        if self.attitude_kind() is None:
            out.append("the attitude (qw, qx, qy, qz or roll_deg, pitch_deg, yaw_deg columns, body -> NED)")
        ds = self.dataset
        has_columns = any(c in ds.extra for c in VECTOR_COLUMNS) or ("lat" in ds.extra and "lon" in ds.extra)
        if self.location is None and not has_columns:
            out.append(
                "the field vector (ref_n, ref_e, ref_d or lat, lon, alt_m columns, or a location and date below)"
            )
        return out

    @property
    def available(self) -> bool:
        return not self.missing()

    # --- the location typed in the page, or the file's site ---------------------------------------------------
    def take_site(self) -> str:
        """A fresh session of a record whose file names its site (the engine's
        :func:`magcal.checks.reference.igrf_place`, from a ``# site:`` line, as ``--reference igrf``): IGRF there (the engine's, through
        :func:`check_location`) becomes the location, the vector reference and the scalar reference, as if typed;
        the page's location inputs show it, to change. Called by the controller before the first history row (its
        raw RMS then uses the same |B|). Returns the message for the page (markdown), empty without a site; a site
        IGRF cannot take (a date beyond the model's years) is said and the record opens without it."""
        place = igrf_place(self.dataset)  # the engine's: the place the command line's --reference igrf takes
        if place is None or place.site is None or self._has_track():
            return ""  # a track's lat, lon columns give IGRF where each sample was taken (reference())
        site = place.site
        try:
            loc = check_location(place.lat_deg, place.lon_deg, place.alt_m, place.date)
        except (MagcalError, ImportError) as exc:
            self.location_note = (
                f"the file's `# site:` line ({safe_text(site.text(), 120)}) could not be used "
                f"({safe_text(str(exc), 300)}); type the place and date"
            )
            return f"**Note:** {self.location_note}"
        state = self.ctrl.state
        with state.lock:
            self.location = loc
            self.location_note = ""
            state.location = loc.to_dict()
            state.reference_nT = round(loc.total_nT, 1)
            state.fit_reference = False
            state.touch()
        written = self.dataset.metadata.get("site") or site.text()
        return (
            f"**reference from the file's `# site:` line** ({safe_text(written, 120)}): "
            f"{safe_text(loc.text(), 400)}; the total-field fits use |B| = {loc.total_nT:.1f} nT, the vector fit the "
            "vector. To use another place or date, change it under *Reference from a location (IGRF)* (Calibrate "
            "tab)."
        )

    def _has_track(self) -> bool:
        """Whether the record carries its position per sample (``lat``, ``lon`` columns)."""
        return "lat" in self.dataset.extra and "lon" in self.dataset.extra

    def from_site(self) -> bool:
        """Whether the location in use is the one the file's ``# site:`` line gives."""
        site, loc = record_site(self.dataset), self.location
        if site is None or loc is None:
            return False
        return (loc.lat_deg, loc.lon_deg, loc.alt_m, loc.date) == (site.lat_deg, site.lon_deg, site.alt_m, site.date)

    def set_location(self, lat_deg, lon_deg, alt_m, date) -> Location:
        """Take the place and date typed in the page: IGRF there becomes the vector reference and its magnitude the
        scalar reference (the Reference field box); the session remembers the place. Raises a
        :class:`MagcalError` for a value out of range or a date IGRF does not cover."""
        loc = check_location(lat_deg, lon_deg, alt_m, date)
        ctrl = self.ctrl
        with ctrl.state.lock:
            self.forget_fit()  # it was made with the old reference
            self.location = loc
            self.location_note = ""
            ctrl.state.location = loc.to_dict()
            ctrl.state.touch()
        ctrl.configure(reference_nT=round(loc.total_nT, 1), fit_reference=False)  # autosaves, refreshes the page
        self._changed()
        ctrl.say(
            f"**reference from the location**: {safe_text(loc.text())}; the total-field fits use |B| = "
            f"{loc.total_nT:.1f} nT, the vector fit the vector. Run a fit to use it."
        )
        return loc

    def clear_location(self) -> None:
        """Forget the typed location (the file's reference, if any, is used again; the Reference field box too)."""
        ctrl = self.ctrl
        with ctrl.state.lock:
            self.forget_fit()
            self.location = None
            ctrl.state.location = None
            ctrl.state.touch()
        ctrl.configure(reference_nT=None)
        self._changed()
        ctrl.say("the location is forgotten: the file's reference is used again (or the field magnitude is fitted)")

    # --- the fit ---------------------------------------------------------------------------------------------
    def fit(
        self,
        kept=None,
        robust=None,
        noise_nT=None,
        again=False,
        effects=None,
        step="vector fit",
        *,
        inputs: JobInputs | None = None,
    ):
        """The vector fit of every sensor on the kept samples (:meth:`magcal.modes.vector.VectorMode.fit`, the
        vector fit mode's, with the vector model's effects, robust loss and noise as the session says), its world
        components on every sample, and a message with its figures. The session remembers its settings (:attr:`SessionState.vector_fit`), so
        that it runs again when the session reopens (:meth:`restore`), and the step joins the vector model's
        history (:attr:`SessionState.vector_history`: world RMS per N, E, D and |B|).

        Parameters
        ----------
        kept : numpy.ndarray of bool, optional
            The samples to fit (default: the kept samples); samples without attitude or reference among them are
            left out by the engine (a note says how many).
        robust : bool, optional
            The robust loss (default: the session's).
        noise_nT : float, optional
            The noise per axis (default: the session's, else estimated).
        again : bool
            The message says the fit was run again from the saved session (and the history, saved too, gains no
            step).
        effects : sequence of str, optional
            The vector model's effects (default: :attr:`effects`); they become :attr:`effects` when the fit succeeds.
        step : str
            The history's name of the step.
        inputs : JobInputs, optional
            The step's inputs: their kept mask is ``kept``.

        Returns
        -------
        magcal.fitting.vector.VectorFitResult

        Raises
        ------
        MagcalError
            No attitude, no reference, too few samples (the engine's message).
        """
        missing = self.missing()
        if missing:
            raise MagcalError("the vector fit needs " + " and ".join(missing))
        t0 = time.perf_counter()
        ctrl = self.ctrl
        ds = self.dataset
        kept = _kept(ctrl, kept, inputs)
        robust = bool(ctrl.state.robust if robust is None else robust)
        noise_nT = ctrl.state.noise_nT if noise_nT is None else float(noise_nT)
        effects = list(self.effects if effects is None else effects)
        before = self.vector_row(kept) if self.result is not None else None
        ctrl.report_progress("vector fit (attitude-aided)", None)
        try:
            ref = self.reference()
            if ref is None:  # missing() said there would be one
                raise MagcalError("no reference field vector")
            result = VECTOR.fit(ds, reference=ref, effects=effects, mask=kept, robust=robust, noise_nT=noise_nT)
            world = result.calibration.world(ds, record_terms="apply", force=True)
            evidence = VECTOR.evidence(ds, result, reference=ref)
        finally:
            ctrl.end_progress()
        with ctrl.state.lock:
            self.result = result
            self.world_nT = np.asarray(world, dtype=float)
            self.reference_ned_nT = np.asarray(ref.ned_nT, dtype=float)
            self.reference_text = ref.text
            self.effects = effects
            self.evidence = evidence
            self.diagnosis = None  # it diagnosed the fit before this one
            self._fit_key = self._key(kept, effects, robust, noise_nT)
            ctrl.state.vector_fit = {
                "kept": pack_mask(kept),
                "robust": robust,
                "noise_nT": noise_nT,
                "effects": list(effects),
            }
            row = self.vector_row(kept)
            assert row.world_rms_nT is not None  # a vector fit gives the world components
            elapsed = time.perf_counter() - t0
            if not again:
                ctrl.state.record_vector(
                    VectorStep(
                        step=step,
                        world_rms_nT=[float(v) for v in row.world_rms_nT],
                        total_rms_nT=row.total_field_rms_nT,
                        effects=list(effects),
                        n_fitted=int(result.n_samples),
                        changes=_changes(before, row),
                        elapsed_s=elapsed,
                    )
                )
            ctrl.state.touch()
        ctrl.autosave()
        self._changed()
        ctrl.emit(Change.DIAGNOSIS)  # the old diagnosis no longer applies
        mount = "; ".join(row.mounting)
        model = ", ".join(safe_code(e) for e in effects) or "base terms only"
        text = (
            ("the saved session's " if again else "")
            + f"**{safe_text(step)} (attitude-aided)** on {row.samples}, model {model} ({elapsed:.2f} s"
            + (", run again" if again else "")
            + "): "
            f"total-field RMS {row.total_field_rms_nT:.4g} nT, world RMS N/E/D "
            + " / ".join(f"{v:.4g}" for v in row.world_rms_nT)
            + f" nT; mounting {safe_text(mount, 600)}  \nreference: {safe_text(ref.text, 400)}"
        )
        text += "".join(f"  \n- {safe_text(w, 600)}" for w in result.warnings)
        ctrl.say(text)
        return result

    @staticmethod
    def _key(kept, effects, robust, noise_nT) -> tuple:
        return (pack_mask(kept), tuple(effects), bool(robust), noise_nT)

    def is_current(self, kept: np.ndarray | None = None) -> bool:
        """Whether the last fit is of the kept samples (``kept``, default: those of now), robust loss and noise the
        session asks for now."""
        ctrl = self.ctrl
        if self.result is None:
            return False
        kept = ctrl.kept if kept is None else kept
        return self._fit_key == self._key(kept, self.effects, ctrl.state.robust, ctrl.state.noise_nT)

    # --- the loop: diagnose, add ------------------------------------------------------------------------------
    def diagnose(self, kept: np.ndarray | None = None, *, inputs: JobInputs | None = None):
        """Diagnose the vector fit (the vector mode's diagnosis, :meth:`magcal.modes.vector.VectorMode.diagnose`): every catalogue effect the
        vector fit can take refitted with the vector model, judged on the world N/E/D residuals and |B| on the
        later part of the record, as ``magcal apply`` applies it. The fit runs first when there is none of the
        kept samples (``kept``, default: those of now) and settings of now. Rejected samples are left out of the
        diagnosis (it runs on the kept ones).

        Returns
        -------
        magcal.diagnosis.vector.VectorDiagnosis

        Raises
        ------
        MagcalError
            No attitude or reference, too few samples (the engine's message).
        """
        ctrl = self.ctrl
        kept = _kept(ctrl, kept, inputs)
        if not self.is_current(kept):
            self.fit(kept)
        ds, ref = self.dataset, self.reference()
        if ref is None:
            raise MagcalError("the vector diagnosis needs the field vector: " + " and ".join(self.missing()))
        options = {"robust": bool(ctrl.state.robust), "noise_nT": ctrl.state.noise_nT}
        ctrl.report_progress("diagnosing the vector fit", None)
        try:
            if kept.all():  # the fit on the page is the model diagnosed
                d = VECTOR.diagnose(ds, self.result, progress=ctrl.report_progress, **options)
            else:  # the rejected samples are left out of every refit too
                d = VECTOR.diagnose(
                    ds, reference=ref, mask=kept, effects=self.effects, progress=ctrl.report_progress, **options
                )
        finally:
            ctrl.end_progress()
        with ctrl.state.lock:
            self.diagnosis = d
            # one floor per record: it does not rise with the model (a noise given is taken as it is)
            self.noise = lowest_noise(self.noise, d.noise, options["noise_nT"] or None)
            self.floor_nT = None if self.noise is None else self.noise.world_floor_nT
        ctrl.emit(Change.DIAGNOSIS)
        ctrl.emit(Change.VECTOR)  # the history plot draws the floor found
        best = d.explained_by[0] if d.explained_by else None
        extra = f"; recommended {safe_code(best)}" if best else ""
        ctrl.say(
            f"**diagnose (vector fit)**: verdict {safe_code(d.verdict)}{extra} ({safe_text(d.where_text(), 120)})  \n"
            f"{safe_text(d.summary, 1000)}"
        )
        return d

    def candidate_labels(self) -> list[str]:
        """What Add may put into the vector model from the last diagnosis: the candidates for the model as it is
        (the first round's), the recommended one first, then by delta-BIC."""
        d = self.diagnosis
        if d is None:
            return []
        first = [c for c in d.candidates if c.round == 1]
        first.sort(key=lambda c: (not c.recommended, c.delta_bic))
        return list(dict.fromkeys(c.label for c in first))

    def add(
        self, label: str | None = None, kept: np.ndarray | None = None, *, inputs: JobInputs | None = None, note=""
    ):
        """Put a candidate (the recommended one by default, else the best) into the vector model and refit
        (:meth:`fit` with the effects, on ``kept``: default the kept samples of now).

        Raises
        ------
        MagcalError
            Nothing diagnosed yet, an effect the vector fit cannot take, one already in the model.
        """
        return super().add(label, inputs=self._inputs_of(kept, inputs), note=note)

    def _inputs_of(self, kept, inputs: JobInputs | None) -> JobInputs | None:
        return inputs if kept is None else JobInputs(np.asarray(kept, dtype=bool), tuple(self.effects))

    def add_all(self, labels, kept: np.ndarray | None = None, note: str = "", *, inputs: JobInputs | None = None):
        """Put ``labels`` into the vector model and refit once (:meth:`fit`); ``note`` is appended to the history's
        step (e.g. that the effect was not advised)."""
        kept = _kept(self.ctrl, kept, inputs)
        effects = list(self.effects)
        for label in labels:
            label = self.ctrl.check_label(label)
            cls = EFFECTS[effect_name(label)]
            if "vector" not in getattr(cls, "modes", ("scalar", "vector")) or cls.stage != "raw":
                raise MagcalError(
                    f"{label}: the vector fit cannot take this effect (it takes the raw-stage effects of the "
                    "catalogue); choose one of the diagnosis's candidates"
                )
            name = effect_name(label)
            if label in effects or name in effects:
                raise MagcalError(f"{label} is already in the vector model")
            effects = [e for e in effects if ":" in label or effect_name(e) != name] + [label]
        return self.fit(kept, effects=effects, step=f"vector: add {', '.join(labels)}{note}")

    def remove(self, label: str | None = None, kept: np.ndarray | None = None, *, inputs: JobInputs | None = None):
        """Take an effect (the last added by default) out of the vector model and refit (on ``kept``: default the
        kept samples of now)."""
        return super().remove(label, inputs=self._inputs_of(kept, inputs))

    def _refit_without(self, label: str, inputs: JobInputs | None):
        kept = None if inputs is None else inputs.kept
        return self.fit(kept, effects=[e for e in self.effects if e != label], step=f"vector: remove {label}")

    def history(self) -> list[VectorStep]:
        """The vector model's fits (the session file's ``vector_history``)."""
        return list(self.ctrl.state.vector_history)

    def save(self) -> dict | None:
        """The last vector fit's settings (the session file's ``vector_fit``: its samples, robust loss, noise and
        effects), or None."""
        return self.ctrl.state.vector_fit

    @property
    def calibration(self):
        """The last vector fit's calibration, or None."""
        return None if self.result is None else self.result.calibration

    def forget(self) -> None:
        """Drop the last vector fit (:meth:`forget_fit`)."""
        self.forget_fit()

    def plot_evidence(self) -> dict | None:
        """The evidence plots' data (every sample): the diagnosis's (:attr:`magcal.diagnosis.vector.VectorDiagnosis.
        evidence`, of the fit on the page) when it covers every sample, else the current fit's (:attr:`evidence`);
        None before a vector fit."""
        d = self.diagnosis
        if d is not None and np.shape(d.evidence.get("world_residual_nT"))[1:2] == (self.dataset.n_samples,):
            return d.evidence
        return self.evidence

    def gain_rms_nT(self) -> float | None:
        """The world residual RMS (nT) the vehicle view's automatic exaggeration is set by: the base model's (the
        last history step without effects: the loop's start), so that an added effect shows as a shorter arrow;
        the current fit's when there is none."""
        for rec in reversed(self.ctrl.state.vector_history):
            if not rec.effects and np.isfinite(rec.world_nT):
                return rec.world_nT
        row = self.vector_row() if self.result is not None else None
        if row is None or row.world_rms_nT is None:
            return None
        return float(np.sqrt(np.mean(np.square(row.world_rms_nT))))

    def forget_fit(self) -> None:
        """Drop the last vector fit (its reference changed); the session forgets it too (the model's effects
        stay)."""
        self.result = None
        self.world_nT = None
        self.reference_ned_nT = None
        self.reference_text = ""
        self.diagnosis = None
        self.evidence = None
        self.floor_nT = None
        self.noise = None
        self._fit_key = None
        self.ctrl.state.vector_fit = None

    def restore(self) -> str:
        """Run the saved session's vector fit again (:attr:`SessionState.vector_fit`: its samples, robust loss and
        noise; the reference is the session's as before). Returns a note for the page: empty when there was
        nothing to run or it ran (its own message says so), else why it could not run (the session goes on
        without it)."""
        saved = self.ctrl.state.vector_fit
        if not saved:
            return ""
        size = self.dataset.n_samples * self.dataset.n_sensors
        if size > RESTORE_MAX_SAMPLES:  # not on every opening: the settings stay, the button runs it
            return (
                f"the saved session ran the vector fit; on {size:,} sensor samples it is not run again on opening "
                "(seconds): press Run the vector fit (Calibrate tab) to see it"
            )
        try:
            kept = unpack_mask(saved["kept"], self.dataset.n_samples)
            effects = list(saved.get("effects", []))
            self.fit(kept, saved.get("robust", False), saved.get("noise_nT"), again=True, effects=effects)
        except (MagcalError, ValueError, KeyError, TypeError) as exc:
            with self.ctrl.state.lock:
                self.ctrl.state.vector_fit = None
                self.ctrl.state.touch()
            return f"the saved vector fit could not be run again ({safe_text(str(exc), 300)}); run it again"
        return ""

    def lesson_findings(self) -> dict | None:
        """What a lesson's check compares (:meth:`magcal_workbench.lessons.Lesson.check`): per sensor, the right
        angle the vector fit found (its firmware name) and the angle off it (deg), and the vector model's effects;
        None before a vector fit."""
        if self.result is None:
            return None
        return {
            "mounting": [s.right_angle_text.split(" ")[0] for s in self.result.sensors],
            "angle_off_deg": [float(s.angle_off_deg) for s in self.result.sensors],
            "effects": list(self.effects),
        }

    def _changed(self) -> None:
        self.ctrl.emit(Change.VECTOR)

    # --- what the page shows ---------------------------------------------------------------------------------
    def world_residual_nT(self) -> np.ndarray | None:
        """``B_world - B_ref`` (n_sensors, N, 3) of the last vector fit, nT (every sample), or None."""
        if self.world_nT is None or self.reference_ned_nT is None:
            return None
        return self.world_nT - self.reference_ned_nT[None]

    def vector_row(self, kept: np.ndarray | None = None) -> FitRow:
        """The vector fit's column of the comparison (kept samples: ``kept``, default those of now)."""
        row = FitRow("vector (attitude-aided)")
        res, resid = self.result, self.world_residual_nT()
        if res is None or resid is None or self.world_nT is None or self.reference_ned_nT is None:
            return row
        kept = self.ctrl.kept if kept is None else kept
        ref_total = np.linalg.norm(self.reference_ned_nT, axis=1)
        total = np.linalg.norm(self.world_nT, axis=2) - ref_total[None]
        row.total_field_rms_nT = float(_rms(total[:, kept]))
        row.world_rms_nT = _rms(resid[:, kept].reshape(-1, 3), axis=0)
        for i, s in enumerate(res.sensors):
            who = f"s{i + 1}: " if len(res.sensors) > 1 else ""
            row.mounting.append(f"{who}{s.right_angle_text.split(':')[0]}, {s.angle_off_deg:.2f} deg off it")
            row.attitude_noise.append(f"{who}{s.attitude_noise_deg:.3g} deg ({s.attitude_noise_source})")
        row.warnings = list(res.warnings)
        row.samples = fitted_samples_text(res)
        return row

    def coverage_notes(self) -> list[str]:
        """The coverage check of the kept samples (:func:`magcal.checks.coverage.calibration_input_checks`): the
        notes that make a total-field fit undetermined (computed once per kept mask)."""
        kept = self.ctrl.kept
        key = (self.ctrl.state.selection.n_rejected, hash(kept.tobytes()))
        if key != self._coverage_key:
            try:
                self._coverage_notes = calibration_input_checks(self.dataset.subset(kept))
            except MagcalError as exc:  # rotation about one axis: refused outright, which says the same
                self._coverage_notes = [str(exc)]
            self._coverage_key = key
        return list(self._coverage_notes)

    def scalar_row(self) -> FitRow:
        """The total-field fit's column (kept samples): its RMS, no world components (its rotation is a gauge), and
        the undetermined warning when the record's directions fill a cone rather than the sphere."""
        ctrl = self.ctrl
        row = FitRow("total-field")
        if ctrl.calibration is not None:
            rms = ctrl.residual_rms_nT()
            row.total_field_rms_nT = float(rms) if np.isfinite(rms) else None
        row.undetermined = [hide_paths(n) for n in self.coverage_notes()]
        return row

    def current_vectors(self, sample: int, sensor: int = 0) -> dict | None:
        """What the vehicle view draws at ``sample`` for ``sensor``: ``attitude_wxyz`` (4,), ``model_ned_nT`` (3,),
        ``measured_ned_nT`` (3,) or None before a vector fit, all world frame; None when the data have no attitude.

        A sample without attitude (NaN angles: before the first attitude message, a gap) gives ``attitude_wxyz``
        None and nothing else; a sample without a reference (no position yet) gives ``model_ned_nT`` None."""
        ds = self.dataset
        found = attitude_rows(ds)
        if found is None:
            return None
        rot, have = found
        i = int(np.clip(sample, 0, ds.n_samples - 1))
        if not have[i]:
            return {"sample": i, "attitude_wxyz": None, "model_ned_nT": None, "measured_ned_nT": None}
        q = rot[i].as_quat()
        out: dict = {"sample": i, "attitude_wxyz": np.array([q[3], q[0], q[1], q[2]]), "measured_ned_nT": None}
        model_ned = None
        if self.reference_ned_nT is not None:
            model_ned = self.reference_ned_nT[i]
        else:
            try:
                ref = self.reference()
            except MagcalError:
                ref = None
            model_ned = None if ref is None else ref.ned_nT[i]
        out["model_ned_nT"] = model_ned if model_ned is not None and np.all(np.isfinite(model_ned)) else None
        if self.world_nT is not None:
            measured = self.world_nT[min(sensor, self.world_nT.shape[0] - 1), i]
            out["measured_ned_nT"] = measured if np.all(np.isfinite(measured)) else None
        return out


#: The vector model's former name (tests and lessons call it so).
VectorModel = VectorSession
