"""The total-field fit mode: every record's (``magcal calibrate --mode total_field``, alias ``scalar``).

Readings turned in a uniform field are fitted so that their magnitude is the field's
(:func:`magcal.fitting.pipeline.calibrate`: ellipsoid, Procrustes between sensors, maximum likelihood); held out
with :func:`magcal.fitting.validation.validate_effects`, diagnosed with :func:`magcal.diagnosis.diagnose`.
"""

from __future__ import annotations

from magcal.diagnosis import diagnose
from magcal.fitting import pipeline
from magcal.fitting.validation import validate_effects
from magcal.modes.base import FIT_MODES, FitMode


class TotalFieldMode(FitMode):
    """The total-field fit: ``|B|`` of the corrected readings against the field's magnitude."""

    name = "total_field"
    title = "total-field fit (|B| against the field's magnitude)"
    priority = 0

    def needs(self) -> str:
        return (
            "needs the raw readings (x, y, z per sensor) taken while the sensors turn through many directions in a "
            "uniform field"
        )

    def fit(
        self,
        dataset,
        method="ml",
        effects=(),
        robust=False,
        reference_total_nT=None,
        noise_nT=None,
        seed=None,
        progress=None,
        mask=None,
        ellipsoid_method="algebraic",
        base_terms=None,
    ) -> pipeline.CalibrationResult:
        """:func:`magcal.fitting.pipeline.calibrate` (its arguments); without ``mask`` the calibration knows the
        record it was fitted on, so that its record-only terms act on that record only."""
        result = pipeline.calibrate(
            dataset,
            method=method,
            effects=effects,
            robust=robust,
            reference_total_nT=reference_total_nT,
            noise_nT=noise_nT,
            seed=seed,
            progress=progress,
            mask=mask,
            ellipsoid_method=ellipsoid_method,
            base_terms=base_terms,
        )
        if mask is None:
            result.calibration.fitted_on(dataset)
        return result

    def validate(self, dataset, result, **options):
        """The held-out RMS of the base model and of the model with the effects
        (:func:`magcal.fitting.validation.validate_effects`); None for a fit not made by maximum likelihood."""
        if getattr(result, "method", "ml") != "ml":
            return None
        return validate_effects(dataset, result)

    def diagnose(
        self,
        dataset,
        result=None,
        model=None,
        top=3,
        effects=None,
        candidates=None,
        max_effects=2,
        progress=None,
        validate=True,
        noise_nT=None,
        scheduler=None,
        workers=None,
    ):
        """:func:`magcal.diagnosis.diagnose` (its arguments)."""
        return diagnose(
            dataset,
            result,
            model=model,
            top=top,
            effects=effects,
            candidates=candidates,
            max_effects=max_effects,
            progress=progress,
            validate=validate,
            noise_nT=noise_nT,
            scheduler=scheduler,
            workers=workers,
        )


#: The total-field fit mode.
TOTAL_FIELD = TotalFieldMode()
FIT_MODES.register(TOTAL_FIELD)
