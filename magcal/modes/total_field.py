"""The total-field fit mode: every record's (``magcal calibrate --mode total_field``, alias ``scalar``).

Readings turned in a uniform field are fitted so that their magnitude is the field's
(:func:`magcal.fitting.pipeline.calibrate`: ellipsoid, Procrustes between sensors, maximum likelihood); held out
with :func:`magcal.fitting.validation.validate_effects`, diagnosed with :func:`magcal.diagnosis.diagnose`. The
maximum likelihood alone, started from a calibration one already has, is :meth:`TotalFieldMode.refine` (the
workbench's step 3 and its loop's Add and Remove).
"""

from __future__ import annotations

from magcal.diagnosis import diagnose
from magcal.fitting import fitter, pipeline
from magcal.fitting.validation import validate_effects
from magcal.model.terms import Model
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

    def refine(self, dataset, init, effects=(), robust=False, mask=None, reference_total_nT=None) -> fitter.FitResult:
        """The maximum likelihood of the base model and ``effects`` alone (:func:`magcal.fitting.fitter.fit`, never
        warns: the notes are the result's), started from the calibration ``init`` rather than from the ellipsoid
        and Procrustes steps of :meth:`fit`: a calibration refined step by step, an effect added or taken out of it.

        Parameters
        ----------
        dataset : Dataset
        init : Calibration
            The start (a fit of the same record, e.g. without the effect just added).
        effects : sequence of str
            Effect labels beside the base terms (``"temperature_bias"``, ``"bias_drift:2"``).
        robust : bool
            scipy's soft-L1 loss instead of least squares.
        mask : numpy.ndarray of bool, shape (N,), optional
            The samples fitted (default all).
        reference_total_nT : float or numpy.ndarray, optional
            The field's magnitude (nT); default the record's reference (its ``ref_total`` column), else fitted.
        """
        return fitter.fit(
            dataset,
            Model.from_names(list(effects), dataset.n_sensors),
            init=init,
            loss="soft_l1" if robust else "linear",
            mask=mask,
            reference_total_nT=reference_total_nT,
            warn=False,
        )

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
