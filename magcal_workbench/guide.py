"""The first screen's guide: what the data are, which fits they allow, and the next step of the loop as one button.

The loop is the same for every record: fit the model, diagnose where it fails, add what the diagnosis advises,
until the residuals reach the noise floor. :func:`next_step` reads where the open session stands (a fit or not, a
diagnosis or not, its advice) and names the step that comes next; the page shows it as a button under the status
line (:class:`magcal_workbench.panels.Panels`), whose click runs the same handler as the step's own button in its
tab. On a record with attitude and a field vector the loop is the vector fit's, as Diagnose and Add are; on a board
with an accelerometer (and no field vector) the first step is the gravity fit, the total-field loop one choice
away.
Only reading: the steps, the verdicts and the advice are the engine's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magcal.checks.reference import VECTOR_COLUMNS
from magcal.data.accelerometer import has_accelerometer

from .gravitymodel import model_of
from .lessons import get_lesson
from .markup import hide_paths, safe_code


@dataclass(frozen=True)
class NextStep:
    """The loop's next step.

    Attributes
    ----------
    key : str
        ``run`` (the total-field fit), ``vector`` (the vector fit), ``gravity`` (the gravity fit, beside an
        accelerometer), ``compensation`` (Tolles-Lawson, a scalar beside a fluxgate), ``diagnose``, ``add`` (the advice), or ``none`` (nothing to press: at the floor, or nothing
        that holds to add).
    label : str
        The button's text (empty for ``none``).
    why : str
        One line saying why this step comes next (markdown).
    effects : tuple of str
        For ``add``: the effects the advice names (all are added, with one refit).
    """

    key: str
    label: str
    why: str
    effects: tuple = ()


def data_markdown(ctrl) -> str:
    """What the open data are and which fits they allow (one or two lines of markdown)."""
    ds = ctrl.dataset
    t = ds.time_s
    span = f" over {float(np.nanmax(t) - np.nanmin(t)):.0f} s" if t is not None and ds.n_samples > 1 else ""
    sensors = "1 sensor" if ds.n_sensors == 1 else f"{ds.n_sensors} sensors"
    vm = ctrl.vector
    channels = []
    kind = vm.attitude_kind()
    if kind is not None:
        channels.append(f"attitude ({kind})")
    if has_accelerometer(ds):
        channels.append("an accelerometer")
    if ds.temperature_C is not None:
        channels.append("temperature")
    if compensation_mode(ctrl) and ctrl.model_session is ctrl.compensation:
        channels.append(f"a scalar magnetometer ({safe_code(ctrl.compensation.record().scalar_column)})")
    held = f", with {', '.join(channels)}" if channels else ""
    fits = ["the total-field fit"]
    if compensation_mode(ctrl):  # its tabs show the compensation only: the other fits are not offered
        fom = "the FOM" if ctrl.model_session is ctrl.compensation else "the tensor FOM"
        fits = [f"the {ctrl.model_session.words} (Tolles-Lawson and beyond, judged by {fom} in the maneuvers)"]
    elif ctrl.vector_loop():
        fits.insert(0, "the vector fit (attitude and the field vector: world components, the mounting)")
    elif kind is not None:
        fits.append("the vector fit once a field vector is given (Calibrate tab: a location, or ref_n/e/d columns)")
    if gravity_mode(ctrl):  # the first step: first in the list
        fits.insert(0, "the gravity fit (the mounting against the accelerometer, the heading)")
    elif has_accelerometer(ds):
        fits.append("the gravity fit (heading; Calibrate tab)")
    return (
        f"**Data:** {_source(ctrl)}: {sensors}, {ds.n_samples} samples{span}{held}.  \n"
        f"**Fits it allows:** {'; '.join(fits)}."
    )


def _source(ctrl) -> str:
    """Where the data came from, as the page may show it (no folder of the server)."""
    if ctrl.state.lesson:
        return f"lesson {safe_code(ctrl.state.lesson)}"
    if ctrl.dataset.source:
        return safe_code(hide_paths(str(ctrl.dataset.source)), 80)
    return "simulated data"


def compensation_mode(ctrl) -> bool:
    """Whether the record is a compensation flight, the engine's choice of fit mode: a scalar magnetometer's column
    beside the fluxgate, or a four-sensor cross flown through a compensation box; its compensation comes first."""
    loop = getattr(ctrl, "compensation_loop", None)
    return bool(loop is not None and loop())


def gravity_mode(ctrl) -> bool:
    """Whether the record's first fit is the gravity fit: a magnetometer beside an accelerometer, and no attitude
    with a field vector (whose vector fit comes first)."""
    return not ctrl.vector_loop() and not compensation_mode(ctrl) and has_accelerometer(ctrl.dataset)


def _gravity_step(ctrl) -> NextStep | None:
    """On a board with an accelerometer: the gravity fit first, then nothing to press until the total-field fit
    runs (its loop one choice away); None elsewhere, or once the total-field fit has run."""
    if not gravity_mode(ctrl):
        return None
    gm = model_of(ctrl)
    if gm is None or gm.result is None:
        return NextStep(
            "gravity",
            "Step 1: fit with the accelerometer (the gravity fit)",
            "The board carries an accelerometer: fit the compass against gravity (its mounting, the dip, the "
            "tilt-compensated heading). The total-field fit stays one choice away (Calibrate tab).",
        )
    if np.isfinite(ctrl.residual_rms_nT()):
        return None
    lesson = " Then the Lessons tab: Check my model." if getattr(ctrl.state, "lesson", None) else ""
    return NextStep(
        "none",
        "",
        "The gravity fit ran: its table, the dip and the compass rose are in the Calibrate tab (Gravity "
        f"model).{lesson} The total-field loop (fit, diagnose, add) stays one choice away: Calibrate tab, "
        "Run the chosen method.",
    )


def next_step(ctrl) -> NextStep:
    """The loop's next step for the open session (see the module's docstring)."""
    gravity = _gravity_step(ctrl)
    if gravity is not None:
        return gravity
    if compensation_mode(ctrl):
        session = ctrl.model_session
        if session.result is None:
            return NextStep("compensation", "Step 1: fit Tolles-Lawson (the compensation)", session.step_text)
    elif ctrl.vector_loop():
        vm = ctrl.vector
        if vm.result is None:
            return NextStep(
                "vector",
                "Step 1: fit with the attitude and the field vector",
                "The record has attitude and a field vector: fit them together.",
            )
    elif not np.isfinite(ctrl.residual_rms_nT()):
        return NextStep("run", "Step 1: fit the model", "Fit the base model: bias, scale, non-orthogonality.")
    diagnosis = ctrl.loop_diagnosis()
    if diagnosis is None:
        return NextStep(
            "diagnose",
            "Step 2: find where the model fails",
            "Compare the model with the measurements: which physical effect is missing, judged on held-out data.",
        )
    advised, verdict = ctrl.advice(), str(getattr(diagnosis, "verdict", ""))
    if advised:
        names = ", ".join(advised)
        return NextStep(
            "add",
            f"Step 3: add the advice ({names}) and refit",
            f"The diagnosis advises {', '.join(safe_code(a) for a in advised)}: "
            f"{'it holds' if len(advised) == 1 else 'they hold'} on data the fit did not see.",
            tuple(advised),
        )
    if verdict == "adequate":
        why = "The residuals are at the noise floor: the model is adequate. Export it (Files tab)."
    elif verdict == "not_judged":
        why = (
            "Verdict `not_judged`: the record cannot hold samples out to judge a candidate on, so nothing is advised. "
            "The Model tab says what would let it judge (a longer record, a faster log, another flight)."
        )
    else:
        why = (
            f"Verdict {safe_code(verdict or 'none')}: nothing advised holds on held-out data. The Model tab's "
            "evidence shows what is left."
        )
    vector = getattr(ctrl, "vector", None)
    if not ctrl.vector_loop() and vector is not None and vector.attitude_kind() is not None:
        why += (
            " The record has attitude: type where and when it was recorded (Calibrate tab, the vector model's "
            "location and date) and the vector fit comes first, with the world components and the mounting."
        )
    return NextStep("none", "", why)


def gravity_status_markdown(ctrl) -> str:
    """The gravity fit's line for the status, where it is the record's first fit and has run (markdown; engine
    words): the mounting it found and the dip's spread; empty otherwise."""
    gm = model_of(ctrl)
    if not gravity_mode(ctrl) or gm is None or gm.result is None:
        return ""
    s = gm.result.sensors[0]
    mounting = safe_code(s.right_angle_text.split(":")[0], 80)
    return (
        f"**Gravity fit: dip spread {s.dip_sd_deg:.3g} deg**, mounting {mounting} {s.angle_off_deg:.2f} deg off it, "
        f"inclination {gm.result.inclination_deg:.2f} deg"
    )


def vector_reference_markdown(ctrl) -> str:
    """What the vector fit uses as the field, where it comes from (markdown); empty when the record has no vector
    loop. The total-field fit's reference (a magnitude) is said after it, by the Calibrate tab."""
    if not ctrl.vector_loop():
        return ""
    vm, ds = ctrl.vector, ctrl.dataset
    if vm.location is not None:
        where = (
            "IGRF at the file's `# site:` line (the location below)"
            if vm.from_site()
            else ("IGRF at the location typed below")
        )
    elif any(c in ds.extra for c in VECTOR_COLUMNS):
        where = "the file's `ref_n, ref_e, ref_d` columns, per sample"
    else:
        where = "IGRF along the file's `lat, lon, alt_m` columns"
    ref = vm.reference()
    size = ""
    if ref is not None:
        size = f" (|B| median {float(np.median(np.linalg.norm(np.asarray(ref.ned_nT, float), axis=1))):.6g} nT)"
    return f"_Reference used by the vector fit:_ the field vector from {where}{size}"


def lesson_markdown(ctrl) -> str:
    """An open lesson's title and text, on the first screen under the guide's button (the Lessons tab holds them
    too, with its checks); empty without a lesson."""
    slug = getattr(ctrl.state, "lesson", None)
    if not slug:
        return ""
    try:
        lesson = get_lesson(slug)
    except KeyError:
        return ""
    return f"### Lesson: {lesson.title}\n\n{lesson.guide().strip()}"


def guide_markdown(ctrl) -> str:
    """The guide's text: the data, the fits they allow, and the next step's reason."""
    step = next_step(ctrl)
    return f"{data_markdown(ctrl)}  \n**Next:** {step.why}"
