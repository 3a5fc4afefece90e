"""The vector fit mode: a record with the attitude and the Earth's field vector (``--mode vector``, docs/vector.md).

Each sensor's correction and mounting are fitted so that the corrected reading, turned by the attitude into
north-east-down, is the field vector (:func:`magcal.fitting.vector.fit_vector`): a platform that cannot tumble (a
vehicle, a drone) is calibrated from what it flies. Held out with :func:`magcal.fitting.vector.validate_vector`,
diagnosed on the world components with :func:`magcal.diagnosis.vector.diagnose_vector`; the plots' data of any vector
calibration of the record from :meth:`VectorMode.evidence` (:func:`magcal.diagnosis.vector.vector_evidence`). The
workbench's vector session calls these methods, so that the page and ``magcal.calibrate(ds, mode="vector")`` run one
code path.
"""

from __future__ import annotations

import dataclasses
import inspect

import numpy as np

from magcal.checks.reference import resolve_vector_reference
from magcal.core.errors import MagcalError
from magcal.data.attitude import attitude_present, attitude_source
from magcal.data.inputs import as_dataset
from magcal.diagnosis.vector import Flight, diagnose_vector, vector_evidence
from magcal.fitting.vector import VectorFitResult, fit_vector, validate_vector
from magcal.modes.base import FIT_MODES, FitMode

#: What the vector fit needs beside the readings, as the messages say it.
NEEDS_ATTITUDE = (
    "needs the attitude: qw, qx, qy, qz or roll_deg, pitch_deg, yaw_deg columns (body -> north-east-down; "
    "docs/formats.md)"
)
NEEDS_FIELD_VECTOR = (
    "needs the Earth's field vector: ref_n, ref_e, ref_d columns (nT), --reference-vector N,E,D "
    "(reference=[N, E, D]), or --reference igrf (reference='igrf') with --lat/--lon (or lat, lon, alt_m columns) "
    "and --date"
)


def field_vector(dataset, reference=None):
    """The field vector a vector fit of ``dataset`` is made against (a
    :class:`~magcal.checks.reference.VectorReference`), or None when neither ``reference`` nor the record gives one.

    ``reference``: a VectorReference (taken as it is), ``[N, E, D]`` nT (one vector for the record), ``"igrf"``
    (along the ``lat, lon, alt_m`` columns), ``"fitted"`` (a lab's constant field, fitted with the calibration), or
    None: the ``ref_n, ref_e, ref_d`` columns (:func:`magcal.checks.reference.resolve_vector_reference`).
    """
    if reference is None or isinstance(reference, str):
        return resolve_vector_reference(dataset, reference=reference)
    if hasattr(reference, "ned_nT"):
        return reference
    return resolve_vector_reference(dataset, vector=reference)


def flight(item, number: int) -> Flight:
    """An ``also=`` entry as a :class:`~magcal.diagnosis.vector.Flight`: a Flight, a ``(data, reference)`` pair, or
    data whose ``ref_n, ref_e, ref_d`` columns give its field vector (``number``: its place in ``also``, from 1)."""
    if isinstance(item, Flight):
        return item
    data, reference = item if isinstance(item, tuple) else (item, None)
    ds = as_dataset(data)
    ref = field_vector(ds, reference)
    if ref is None:
        raise MagcalError(f"also[{number - 1}]: no field vector (ref_n, ref_e, ref_d columns); give (data, reference)")
    return Flight(ds, ref, ds.source or f"flight {number + 1}")


#: The keyword arguments of :func:`magcal.diagnosis.vector.diagnose_vector` a vector diagnosis passes on.
_DIAGNOSE_OPTIONS = tuple(inspect.signature(diagnose_vector).parameters)[3:]


class VectorMode(FitMode):
    """The vector fit: the corrected readings, turned by the attitude, against the field vector."""

    name = "vector"
    title = "vector fit (attitude and the field vector)"
    priority = 30

    def needs(self) -> str:
        return (
            "needs the attitude (qw, qx, qy, qz or roll_deg, pitch_deg, yaw_deg) and the Earth's field vector "
            "(ref_n, ref_e, ref_d, a given vector or IGRF at the place)"
        )

    def applicable(self, dataset, reference=None, **options):
        if attitude_source(dataset) is None:
            return NEEDS_ATTITUDE
        if field_vector(dataset, reference) is None:
            return NEEDS_FIELD_VECTOR
        return None

    def chosen_by_auto(self, dataset, reference=None, **options) -> bool:
        present = attitude_present(dataset)
        if present is None or not present.any():
            return False
        return self.applicable(dataset, reference) is None

    def passed_over(self, dataset, **options):
        present = attitude_present(dataset)
        if present is not None and not present.any():  # e.g. a recording no ATTITUDE reached
            return "the attitude columns are empty on every row (no sample has an attitude)"
        return None

    def fit(
        self,
        dataset,
        reference=None,
        effects=None,
        terms=None,
        attitude_noise_deg=None,
        noise_nT=None,
        reference_total_nT=None,
        robust=False,
        mask=None,
        field_gradient=False,
    ) -> VectorFitResult:
        """:func:`magcal.fitting.vector.fit_vector` against :func:`field_vector` ``(dataset, reference)`` (its
        other arguments as there, ``reference_total_nT`` by default the record's ``ref_total`` column, as
        ``magcal calibrate`` passes it; never warns: the notes are the result's); without ``mask`` the calibration
        knows the record it was fitted on."""
        vref = field_vector(dataset, reference)
        if vref is None:
            raise MagcalError(f"the vector fit {NEEDS_FIELD_VECTOR}")
        result = fit_vector(
            dataset,
            vref,
            effects=effects,
            terms=terms,
            attitude_noise_deg=attitude_noise_deg,
            noise_nT=noise_nT,
            reference_total_nT=dataset.ref_total_nT if reference_total_nT is None else reference_total_nT,
            robust=robust,
            mask=mask,
            warn=False,
            field_gradient=field_gradient,
        )
        if mask is None:
            result.calibration.fitted_on(dataset)
        return result

    def validate(
        self, dataset, result, attitude_noise_deg=None, noise_nT=None, reference_total_nT=None, robust=False, **options
    ):
        """The held-out figures of the base model and of the model with the fit's effects
        (:func:`magcal.fitting.vector.validate_vector`, against the field the fit used); None for a fit of the base
        model alone."""
        if not result.terms:
            return None
        return validate_vector(
            dataset,
            result.reference,
            effects=result.terms,
            attitude_noise_deg=attitude_noise_deg,
            noise_nT=noise_nT,
            reference_total_nT=dataset.ref_total_nT if reference_total_nT is None else reference_total_nT,
            robust=robust,
        )

    def diagnose(self, dataset, result=None, reference=None, also=(), mask=None, reference_total_nT=None, **options):
        """:func:`magcal.diagnosis.vector.diagnose_vector` against the fit's field (else :func:`field_vector`);
        ``also``: other flights of the same vehicle (datasets with ``ref_n, ref_e, ref_d``, ``(data, reference)``
        pairs or Flights). ``mask`` (bool, shape (N,)): the samples diagnosed, the others left out of every refit
        (the base model plus ``effects=`` is fitted on them: give no ``result`` with it); ``reference_total_nT`` as
        for :meth:`fit` (default the record's ``ref_total`` column). Options
        :func:`~magcal.diagnosis.vector.diagnose_vector` does not take (``workers``, ``scheduler``) are not used.

        Raises
        ------
        MagcalError
            No field vector, or ``mask`` with a ``result`` (a fit of other samples than those diagnosed).
        """
        vref = result.reference if isinstance(result, VectorFitResult) else field_vector(dataset, reference)
        if vref is None:
            raise MagcalError(f"the vector diagnosis {NEEDS_FIELD_VECTOR}")
        total = dataset.ref_total_nT if reference_total_nT is None else reference_total_nT
        if mask is not None:
            if result is not None:
                raise MagcalError(
                    "the vector diagnosis of some samples (mask=) fits them itself: give effects=, no result"
                )
            keep = np.asarray(mask, dtype=bool)
            dataset, vref = dataset.subset(keep), dataclasses.replace(vref, ned_nT=np.asarray(vref.ned_nT)[keep])
            total = total[keep] if np.ndim(total) else total
        flights = [flight(f, i) for i, f in enumerate(also or (), 1)]
        passed = {k: v for k, v in options.items() if k in _DIAGNOSE_OPTIONS and k != "also"}
        return diagnose_vector(dataset, vref, result=result, also=flights, reference_total_nT=total, **passed)

    def evidence(self, dataset, result, reference=None, reference_total_nT=None) -> dict:
        """The plots' data of the vector fit ``result`` on every sample of ``dataset``
        (:func:`magcal.diagnosis.vector.vector_evidence`: the world and |B| residuals with the record-only terms
        applied, NaN where a sample has no attitude or reference, and the channels a candidate is plotted against),
        against ``reference`` (a field vector as for :func:`field_vector`; default the one the fit used) and
        ``reference_total_nT`` (as for :meth:`fit`)."""
        vref = result.reference if reference is None else field_vector(dataset, reference)
        total = dataset.ref_total_nT if reference_total_nT is None else reference_total_nT
        return vector_evidence(dataset, vref, result.calibration, reference_total_nT=total)


#: The vector fit mode.
VECTOR = VectorMode()
FIT_MODES.register(VECTOR)
