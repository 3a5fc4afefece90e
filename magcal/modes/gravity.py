"""The gravity fit mode: a magnetometer beside an accelerometer, without attitude (``--mode gravity``,
docs/gravity.md).

The magnetometers and the accelerometer are fitted together so that the field's dip against gravity is the same at
every still sample (:func:`magcal.fitting.gravity.fit_gravity`), which the tilt-compensated heading needs. Held out
with :func:`magcal.fitting.gravity.validate_gravity`; diagnosed as the total-field fit is
(:func:`magcal.diagnosis.diagnose`), with the dip's residual as evidence beside it
(:func:`magcal.diagnosis.gravity.dip_evidence`): a :class:`GravityDiagnosis`. What a user has without the dip, the
total-field fit beside the accelerometer's own, is :meth:`GravityMode.separate_calibration`
(:func:`magcal.fitting.gravity.separate_calibration`), the workbench's baseline beside the gravity fit.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

from magcal.core.errors import CalibrationError, MagcalError
from magcal.core.notes import Note
from magcal.data.accelerometer import has_accelerometer
from magcal.data.attitude import attitude_source
from magcal.diagnosis import Diagnosis
from magcal.diagnosis.gravity import DipEvidence, dip_evidence
from magcal.fitting.gravity import GravityFitResult, fit_gravity, separate_calibration, validate_gravity
from magcal.modes.base import FIT_MODES, FitMode
from magcal.modes.total_field import TOTAL_FIELD

#: What the gravity fit needs beside the readings, as the messages say it.
NEEDS_ACCELEROMETER = (
    "needs the accelerometer beside the magnetometer: ax, ay, az columns (g, mg or m/s^2; docs/gravity.md)"
)


@dataclass
class GravityDiagnosis(Diagnosis):
    """The total-field diagnosis of a record with an accelerometer (:class:`magcal.diagnosis.Diagnosis`), with the
    gravity fit's dip residual as evidence beside it.

    Attributes
    ----------
    dip_evidence : DipEvidence or None
        The dip's residual and the effects that move it (:func:`magcal.diagnosis.gravity.dip_evidence`); None when
        the gravity fit could not be made (a note says why).
    """

    dip_evidence: DipEvidence | None = None

    def to_dict(self) -> dict:
        doc = super().to_dict()
        if self.dip_evidence is not None:
            doc["dip_evidence"] = self.dip_evidence.to_dict()
        return doc


class GravityMode(FitMode):
    """The gravity fit: the magnetometers and the accelerometer together, judged by the tilt-compensated heading."""

    name = "gravity"
    title = "gravity fit (an accelerometer beside the magnetometer)"
    priority = 20

    def needs(self) -> str:
        return "needs the accelerometer beside the magnetometer (ax, ay, az) and no attitude"

    def applicable(self, dataset, **options):
        return None if has_accelerometer(dataset) else NEEDS_ACCELEROMETER

    def chosen_by_auto(self, dataset, **options) -> bool:
        return has_accelerometer(dataset) and attitude_source(dataset) is None

    def fit(
        self,
        dataset,
        inclination_deg=None,
        inclination_source="given",
        reference_total_nT=None,
        noise_nT=None,
        accel_noise_m_s2=None,
        accel_fit="auto",
        accel_units=None,
        mask=None,
        still=None,
        robust=False,
        mag_model="auto",
    ) -> GravityFitResult:
        """:func:`magcal.fitting.gravity.fit_gravity` (its arguments); without ``mask`` the calibration knows the
        record it was fitted on."""
        result = fit_gravity(
            dataset,
            inclination_deg=inclination_deg,
            inclination_source=inclination_source,
            reference_total_nT=reference_total_nT,
            noise_nT=noise_nT,
            accel_noise_m_s2=accel_noise_m_s2,
            accel_fit=accel_fit,
            accel_units=accel_units,
            mask=mask,
            still=still,
            robust=robust,
            mag_model=mag_model,
        )
        if mask is None:
            result.calibration.fitted_on(dataset)
        return result

    def validate(
        self,
        dataset,
        result,
        inclination_deg=None,
        reference_total_nT=None,
        noise_nT=None,
        accel_fit="auto",
        accel_units=None,
        robust=False,
        **options,
    ):
        """The gravity fit on alternating blocks in time, judged on the blocks between against separate
        calibrations (:func:`magcal.fitting.gravity.validate_gravity`)."""
        return validate_gravity(
            dataset,
            inclination_deg=inclination_deg,
            reference_total_nT=reference_total_nT,
            noise_nT=noise_nT,
            accel_fit=accel_fit,
            accel_units=accel_units,
            robust=robust,
        )

    def separate_calibration(
        self, dataset, result=None, mask=None, still=None, accel_fit="auto", reference_total_nT=None, accel_units=None
    ):
        """What a user gets without the dip (:func:`magcal.fitting.gravity.separate_calibration`, a
        :class:`~magcal.calibration.calibration.Calibration`): the magnetometer's total-field fit turned by the right
        angle the gravity fit ``result`` found for the first sensor (the identity without one), beside the
        accelerometer's own fit; ``mask`` and the other options as for :meth:`fit`.

        Raises
        ------
        CalibrationError, MagcalError
            The total-field fit cannot be made on the samples (no ellipsoid), or no accelerometer columns.
        """
        right_angle = None if result is None else result.sensors[0].right_angle
        return separate_calibration(
            dataset,
            right_angle=right_angle,
            mask=mask,
            still=still,
            accel_fit=accel_fit,
            reference_total_nT=reference_total_nT,
            accel_units=accel_units,
        )

    def diagnose(self, dataset, result=None, robust=False, accel_units=None, **options) -> GravityDiagnosis:
        """The total-field diagnosis (:meth:`magcal.modes.total_field.TotalFieldMode.diagnose` with ``options``, of
        ``result`` when it is a total-field fit's), and the dip's evidence of the gravity fit (``result`` when it is
        one, else fitted here with ``robust``)."""
        scalar = None if isinstance(result, GravityFitResult) else result
        diagnosis = TOTAL_FIELD.diagnose(dataset, scalar, **TOTAL_FIELD.taken(options, "diagnose"))
        found = GravityDiagnosis(**{f.name: getattr(diagnosis, f.name) for f in fields(diagnosis)})
        try:
            fit = result if isinstance(result, GravityFitResult) else fit_gravity(dataset, robust=robust)
            found.dip_evidence = dip_evidence(dataset, fit, accel_units=accel_units)
        except (CalibrationError, MagcalError, ValueError) as exc:
            text = f"the dip's evidence (the gravity fit) not given: {exc}"
            found.notes = [*found.notes, Note(text, UserWarning, "gravity diagnosis")]
        return found


#: The gravity fit mode.
GRAVITY = GravityMode()
FIT_MODES.register(GRAVITY)
