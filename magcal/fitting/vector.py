"""Vector calibration with attitude: platforms that turn in yaw but cannot tumble.

A vehicle, an aircraft or a ship sees the Earth's field over a cone of directions, not a sphere: a total-field fit
is not determined there. With the body's attitude ``q`` (body -> north-east-down, :mod:`magcal.data.attitude`)
and the Earth's field vector ``B_ned`` (:func:`magcal.checks.reference.resolve_vector_reference`), every sample
gives three equations per sensor::

    y = C R^T B_body + b + sum_k basis_k theta_k + n,      B_body = R(q)^T B_ned

with ``b`` the bias (hard iron), ``C`` the sensor's scale, non-orthogonality and the platform's soft iron, ``R``
the sensor's mounting (its corrected axes -> the body frame; no longer a gauge), and the platform terms of
:mod:`magcal.model.platform_terms` (eddy currents, a field per ampere or per unit of throttle). The fit finds
``W = R C^-1`` (nine numbers), ``b`` and ``theta``; ``W = R C^-1`` is split by a QR decomposition into the
mounting ``R`` and an upper-triangular ``C^-1`` (the seed's gauge; the split is a convention, ``W`` is what the
data fix).

The likelihood. The corrected field ``B = W (y - b - ...)`` differs from ``R(q)^T B_ned`` by the attitude error,
the field model's error and the sensor noise. An attitude error ``dtheta`` (rad) turns the field: it moves it by
``dtheta x B``, perpendicular to the field, ``sigma_att |B|`` per perpendicular component (0.1 deg on 50 uT is
87 nT). Along the field it moves nothing: there the residual is the total-field residual ``|B| - F``, with the
sensor's own noise. So each sample's residual is split into the total-field residual (weight ``1/sigma_F``) and
the two components perpendicular to the reference field (weight ``1/sigma_perp``, ``sigma_perp^2 =
(sigma_att |B|)^2 + sigma_n^2``): the full likelihood, without counting the along-field part twice. The noises
are given (``attitude_noise_deg``, ``noise_nT``) or estimated from the residuals (a first fit, then a refit with
the estimated weights). :func:`scipy.optimize.least_squares` minimises the weighted sum from the linear
least-squares start.

Standard deviations. The covariance ``(J^T J)^-1`` of the weighted fit counts every sample as independent. An
attitude error that wanders (an AHRS's or an INS's heading drifts over tens of seconds) makes the residuals of
neighbouring samples alike, and the record then holds far fewer independent samples: the standard deviations are
widened by ``sqrt((1 + r) / (1 - r))``, ``r`` the lag-1 correlation of the residuals in record order (the variance of
the mean of a first-order autoregressive sequence). A bias or mounting whose (widened) standard deviation is
more than :data:`UNDETERMINED_BIAS_FRACTION` of the field or :data:`UNDETERMINED_MOUNTING_DEG` is reported as not
determined by the record (a note): found on real flight logs (benchmarks/real/vector_logs.py), where a model
aircraft carried level with a 3-5 deg attitude error gave biases of 100-170 uT with standard deviations of
7-27 uT computed for white errors.

Samples without attitude or reference. A live recording's samples before its first attitude message, a gap in a
log, the samples before the GPS's fix (no position for IGRF along the track) hold NaN: the fit uses the other
samples, exactly as a fit on the clean samples would (:class:`SampleGaps` counts those left out, a note names their
rows), and refuses only when fewer than its minimum are left.

Mounting. The 24 right-angle orientations are tried first, as ArduPilot's orientation detection does (a gain and
an offset fitted for each; the best is the one the field vectors agree with), and the fit then refines the
mounting continuously; the result says which right angle it was and how far off it the sensor sits.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from magcal.calibration.calibration import Calibration, SensorCalibration
from magcal.checks.reference import PLAUSIBLE_TOTAL_nT, VectorReference, resolve_vector_reference
from magcal.core import notes as _notes
from magcal.core.errors import CalibrationError, DataWarning, MagcalError
from magcal.core.notes import Note, row_runs
from magcal.core.stats import explained_share, lag1_correlation, robust_sigma, smooth_in_time
from magcal.data.attitude import attitude_rows
from magcal.data.dataset import Dataset
from magcal.fitting import labfield
from magcal.fitting.result import SampleFitResult
from magcal.fitting.solver import (
    OUTLIER_SIGMAS,
    NoiseGroup,
    SensorMounting,
    beyond,
    correlated_covariance,
    mounting_fields,
    reweighted_fit,
    weighted_least_squares,
)
from magcal.fitting.truth import true_calibration as true_calibration
from magcal.fitting.validation import BlockValidation, held_out_blocks
from magcal.geometry.orientations import (
    RIGHT_ANGLES,
    describe_right_angle,
    mounting_sd_deg,
    nearest_right_angle,
)
from magcal.geometry.shape import field_magnitude_nT
from magcal.model.operators import GRADIENT_BASIS
from magcal.model.platform_terms import available_terms
from magcal.model.terms import (
    Effect,
    Model,
    block_label,
    bound_pulls,
    contexts,
    fitted_outside_domain,
    held_note_text,
)

#: Most evaluations of one least-squares solve: a well-posed vector fit converges in a handful; one whose effects
#: are nearly degenerate wanders along the degenerate direction instead (its covariance then says so).
MAX_NFEV = 300

#: A residual "follows" time or position when a smooth function of it explains at least this share of its variance
#: (:func:`undetermined_cause`).
FOLLOWS_SHARE = 0.5

#: ... and, for the total-field residual, when its RMS is at least this many times its white noise (the noise of its
#: differences in time): a misfit, not the sensor's noise.
FOLLOWS_EXCESS = 3.0

#: Below this spread (deg) of the field's direction in the body frame about its least-covered axis
#: (:func:`direction_spread_deg`) the attitudes span too few directions to fix the calibration (the geometry): a level
#: vehicle turning in yaw with +-20 deg of tilt gives about 6 deg, a tumbled record about 35, a translation without
#: rotation under 1.
LOW_SPREAD_DEG = 10.0

#: Most rounds in which the effects may move their data-derived constants after a fit (a time offset's shift).
MAX_REFINEMENTS = 3

#: Fewest samples per sensor for a vector fit (12 base parameters plus platform terms, three equations each).
MIN_SAMPLES = 20

#: A bias whose standard deviation exceeds this fraction of the field is not determined by the record (the
#: total-field fit's limit on the ellipsoid's misfit is the same 5 %).
UNDETERMINED_BIAS_FRACTION = 0.05

#: A mounting whose standard deviation about a body axis exceeds this many degrees is not determined.
UNDETERMINED_MOUNTING_DEG = 2.0

#: A vehicle whose logged declination (``metadata['log_declination_deg']``, ArduPilot's ``COMPASS_DEC``) differs
#: from the reference field's by more than this (deg) logged a yaw that far off true north: a note says so.
DECLINATION_TOLERANCE_DEG = 1.0


@dataclass
class SensorVectorFit(SensorMounting):
    """One sensor's vector fit.

    Attributes
    ----------
    W, bias_nT, mounting, cinv, right_angle, right_angle_text, angle_off_deg, orientation_margin
        As :class:`magcal.fitting.solver.SensorMounting`: ``W = R C^-1`` maps the raw reading minus bias and
        platform terms into the body frame; ``angle_off_deg`` is the angle from the right angle nearest the fitted
        mounting, ``orientation_margin`` the RMS of the second-best right angle over the best one's.
    bias_sd_nT : numpy.ndarray, shape (3,)
        The bias's standard deviation from the fit's covariance, nT.
    terms : dict
        Fitted effects acting on this sensor, by catalogue name: their parameters (e.g. ``current_field``: the
        field per unit of current in nT, ``eddy_currents``: ``E`` row by row in ms).
    rms_vector_nT : float
        RMS of the vector residual ``B - R(q)^T B_ned`` per component, nT.
    rms_perpendicular_nT : float
        RMS of its components perpendicular to the field (the attitude error's share), nT.
    rms_total_field_nT : float
        RMS of the total-field residual ``|B| - F``, nT.
    sigma_perpendicular_nT, sigma_total_field_nT : float
        The noises weighting the two residuals (given or estimated), nT.
    attitude_noise_deg : float
        The attitude error those imply: ``sigma_perp / |B|`` (deg), or the one given.
    attitude_noise_source : str
        ``given`` or ``estimated``.
    mounting_sd_deg : numpy.ndarray, shape (3,)
        Standard deviation (deg) of the mounting's small rotations about the body's x, y, z axes, from the
        covariance ``(J^T J)^-1`` of the weighted fit (the Cramer-Rao bound when the noises are right).
    n_outliers : int
        Samples whose residual exceeds 5 of its standard deviations (left out of the start; with ``robust``
        the soft-L1 loss keeps them from pulling the fit).
    residual_lag1_correlation : float
        Lag-1 correlation of the weighted residuals in record order (0 for white errors).
    sd_widening : float
        Factor the standard deviations were widened by for that correlation (>= 1; see the module docstring).
    determined : bool
        False when the bias's or the mounting's standard deviation is beyond :data:`UNDETERMINED_BIAS_FRACTION` of
        the field or :data:`UNDETERMINED_MOUNTING_DEG`: the record does not fix the calibration (a note says so).
    bound_pull_z : dict
        Per effect block (label) of this sensor, how far the data pull each parameter past its nearer bound, in its
        (widened) standard deviations (:func:`magcal.model.terms.bound_pulls`); empty when none sits on a bound.
    undetermined_cause : UndeterminedCause or None
        Why not (:func:`undetermined_cause`: the geometry or a misfit); None when determined.
    total_residual_nT : numpy.ndarray, shape (n_fitted,)
        The total-field residual ``|B| - F`` of every fitted sample (:attr:`VectorFitResult.fitted`), nT.
    vector_residual_nT : numpy.ndarray, shape (n_fitted, 3)
        The body-frame vector residual ``B - R(q)^T B_ned`` of every fitted sample, nT.
    """

    terms: dict
    rms_vector_nT: float
    rms_perpendicular_nT: float
    rms_total_field_nT: float
    sigma_perpendicular_nT: float
    sigma_total_field_nT: float
    attitude_noise_deg: float
    attitude_noise_source: str
    nfev: int = 0
    bias_sd_nT: np.ndarray | None = None
    mounting_sd_deg: np.ndarray | None = None
    n_outliers: int = 0
    residual_lag1_correlation: float = 0.0
    sd_widening: float = 1.0
    determined: bool = True
    bound_pull_z: dict = field(default_factory=dict, repr=False)
    undetermined_cause: UndeterminedCause | None = None
    total_residual_nT: np.ndarray | None = field(default=None, repr=False)
    vector_residual_nT: np.ndarray | None = field(default=None, repr=False)

    SUMMARY_FIELDS = (
        "rms_vector_nT",
        "rms_perpendicular_nT",
        "rms_total_field_nT",
        "sigma_perpendicular_nT",
        "sigma_total_field_nT",
        "attitude_noise_deg",
        "attitude_noise_source",
        "bias_sd_nT",
        "mounting_sd_deg",
        "n_outliers",
        "residual_lag1_correlation",
        "sd_widening",
        "determined",
        "undetermined_cause",
    )


@dataclass
class SampleGaps:
    """The samples a vector fit leaves out because they lack an attitude or a reference field vector.

    A live recording's samples before its first ``ATTITUDE`` message, a gap in a log, the samples before the GPS's
    fix (no position for IGRF along the track): each is a sample without the body's attitude or without the field
    vector, and the fit uses the others (:func:`fit_vector`).

    Attributes
    ----------
    n_samples : int
        Samples in the dataset.
    n_chosen : int
        Samples the fit was asked to use (its mask; all without one).
    without_attitude, without_reference : numpy.ndarray of bool, shape (N,)
        Chosen samples without an attitude; chosen samples without a finite reference vector (or reference total
        field).
    """

    n_samples: int
    n_chosen: int
    without_attitude: np.ndarray
    without_reference: np.ndarray

    @classmethod
    def count(cls, chosen, have_attitude, have_reference) -> SampleGaps:
        """From the mask of chosen samples and the per-sample flags (all bool, shape (N,))."""
        chosen = np.asarray(chosen, dtype=bool)
        return cls(
            int(chosen.size), int(chosen.sum()), chosen & ~have_attitude, chosen & ~np.asarray(have_reference, bool)
        )

    @property
    def n_without_attitude(self) -> int:
        return int(np.count_nonzero(self.without_attitude))

    @property
    def n_without_reference(self) -> int:
        return int(np.count_nonzero(self.without_reference))

    @property
    def left_out(self) -> np.ndarray:
        """Chosen samples left out of the fit (no attitude or no reference), bool (N,)."""
        return self.without_attitude | self.without_reference

    @property
    def n_left_out(self) -> int:
        return int(np.count_nonzero(self.left_out))

    def where(self) -> str:
        """Which rows lack what (data rows counted from 1)."""
        parts = []
        if self.n_without_attitude:
            parts.append(f"no attitude in {row_runs(self.without_attitude)}")
        if self.n_without_reference:
            parts.append(f"no reference field vector in {row_runs(self.without_reference)}")
        return "; ".join(parts)

    def text(self) -> str:
        """The note: how many samples were left out and why, naming the first rows."""
        of = f"{self.n_chosen}" if self.n_chosen == self.n_samples else f"the {self.n_chosen} selected"
        parts = []
        if self.n_without_attitude:
            parts.append(
                f"{self.n_without_attitude} of {of} samples have no attitude ({row_runs(self.without_attitude)})"
            )
        if self.n_without_reference:
            parts.append(
                f"{self.n_without_reference}{'' if parts else f' of {of} samples'} have no reference field vector "
                f"({row_runs(self.without_reference)}: no position for IGRF, e.g. before the GPS's fix, or empty "
                "ref_n, ref_e, ref_d)"
            )
        fitted = self.n_chosen - self.n_left_out
        if len(parts) == 1:
            return f"{parts[0]} and were left out of the vector fit ({fitted} samples fitted)"
        return f"{' and '.join(parts)}: those {self.n_left_out} were left out of the vector fit ({fitted} fitted)"

    def to_dict(self) -> dict:
        return {
            "n_chosen": self.n_chosen,
            "n_without_attitude": self.n_without_attitude,
            "n_without_reference": self.n_without_reference,
            "n_left_out": self.n_left_out,
        }


@dataclass
class VectorFitResult(SampleFitResult):
    """Outcome of :func:`fit_vector`.

    Attributes
    ----------
    calibration : Calibration
        ``mode = "vector"``, ``frame = "body"``: corrected vectors are body-frame components; with attitude,
        :meth:`Calibration.world` turns them into north-east-down.
    sensors : list of SensorVectorFit
    reference : VectorReference
    terms : list of str
        Labels of the catalogue effects fitted beside the base terms (``calibration.model``).
    warnings : list of str
        The fit's notes (:attr:`notes` gives them as :class:`~magcal.core.notes.Note` values).
    n_samples : int
        Samples fitted.
    wall_s : float
    fitted : numpy.ndarray of bool, shape (N,), or None
        One entry per sample of the dataset: True where the sample was fitted (chosen by the mask, with an attitude
        and a reference field vector).
    gaps : SampleGaps or None
        The chosen samples left out for lack of an attitude or a reference (their count is also a note).
    field : LabField or None
        The field fitted with the calibration (``reference="fitted"``) or its gradient along the path
        (``field_gradient``): :class:`magcal.fitting.labfield.LabField`.
    """

    mode = "vector"  # the fit mode (magcal.modes) that makes it

    calibration: Calibration
    sensors: list
    reference: VectorReference
    terms: list
    gaps: SampleGaps | None = None
    field: labfield.LabField | None = None

    @property
    def bound_pull_z(self) -> dict:
        """Every sensor's :attr:`SensorVectorFit.bound_pull_z`, by effect block label."""
        return {label: z for s in self.sensors for label, z in s.bound_pull_z.items()}

    @property
    def notes(self) -> list[Note]:
        """The fit's notes as values (:class:`~magcal.core.notes.Note`, :class:`DataWarning`)."""
        return [Note(w, DataWarning, "vector fit") for w in self.warnings]

    @property
    def rms_vector_nT(self) -> float:
        return float(np.sqrt(np.mean([s.rms_vector_nT**2 for s in self.sensors])))

    @property
    def rms_total_field_nT(self) -> float:
        return float(np.sqrt(np.mean([s.rms_total_field_nT**2 for s in self.sensors])))

    def text(self) -> str:
        """A readable report."""
        lines = [
            f"Vector calibration (attitude and the field vector): {len(self.sensors)} sensor(s), "
            f"{self.n_samples} samples, {self.wall_s:.2f} s",
            f"  reference: {self.reference.text}",
            f"  effects: {', '.join(self.terms) or 'none (the base model: bias, C^-1, mounting)'}",
        ]
        if self.field is not None:
            lines += [f"  what the record cannot separate: {g}" for g in self.field.gauges]
        for i, s in enumerate(self.sensors):
            lines += [
                f"  sensor {i + 1}:",
                f"    mounting: {s.right_angle_text}, {s.angle_off_deg:.3f} deg off it "
                f"(next right angle {s.orientation_margin:.1f}x worse)",
                f"    bias (nT): {np.array2string(s.bias_nT, precision=1)}"
                + ("" if s.bias_sd_nT is None else f" +- {np.array2string(s.bias_sd_nT, precision=2)}"),
                "    mounting sd about body x, y, z (deg): "
                + ("n/a" if s.mounting_sd_deg is None else np.array2string(s.mounting_sd_deg, precision=5)),
                f"    vector residual RMS {s.rms_vector_nT:.2f} nT per component (perpendicular to the field "
                f"{s.rms_perpendicular_nT:.2f} nT: attitude error {s.attitude_noise_deg:.4f} deg, "
                f"{s.attitude_noise_source}); total-field residual RMS {s.rms_total_field_nT:.2f} nT",
            ]
            if s.sd_widening > 1.05:
                lines.append(
                    f"    standard deviations widened {s.sd_widening:.1f}x: residuals correlated in time (lag-1 r = "
                    f"{s.residual_lag1_correlation:.3f})"
                )
            if not s.determined:
                lines.append("    NOT DETERMINED by this record (see the warning): do not apply this calibration")
            lines += [f"    {line}" for line in _effect_lines(self.calibration, i)]
        lines += [f"  warning: {w}" for w in self.warnings]
        return "\n".join(lines) + "\n"

    def to_dict(self) -> dict:
        return {
            "mode": "vector",
            "reference": {"text": self.reference.text, "kind": self.reference.kind},
            "terms": list(self.terms),
            "effects": list(self.terms),
            "n_samples": self.n_samples,
            "samples_left_out": None if self.gaps is None else self.gaps.to_dict(),
            "rms_vector_nT": self.rms_vector_nT,
            "rms_total_field_nT": self.rms_total_field_nT,
            "sensors": [s.summary() for s in self.sensors],
            "warnings": list(self.warnings),
            "field": None if self.field is None else self.field.to_dict(),
        }


def _effect_lines(calibration, sensor) -> list[str]:
    """One line per effect acting on ``sensor`` (0-based): its parameters with their names and units, and what
    they do in words where the effect says (:meth:`magcal.model.terms.Effect.quote`)."""
    model = calibration.model
    if model is None:
        return []
    lines = []
    for e, es in model.instances():
        if not (es == sensor or (es is None and e.applies_to(sensor))):
            continue
        values = np.asarray(calibration.effect_values.get(block_label(e, es), []), dtype=float)
        text = ", ".join(f"{n} {v:.4g}" for n, v in zip(e.param_names(), values))
        column = getattr(e, "column", None)
        quote = e.quote(values, calibration.reference_total_nT, sensor)
        lines.append(
            f"{e.name}{f' (per unit of {column})' if column else ''}: {text}" + (f" ({quote})" if quote else "")
        )
    return lines


def body_reference_nT(rotation: Rotation, reference_ned_nT) -> np.ndarray:
    """``R(q)^T B_ned`` (N, 3): the reference field in the body frame, nT."""
    return rotation.inv().apply(np.array(reference_ned_nT, dtype=float))  # a copy: scipy refuses read-only input


def _perpendicular_basis(u):
    """Two unit vectors (N, 3) each, perpendicular to the unit rows ``u`` and to each other."""
    helper = np.zeros_like(u)
    helper[np.arange(len(u)), np.argmin(np.abs(u), axis=1)] = 1.0
    p1 = np.cross(u, helper)
    p1 /= np.linalg.norm(p1, axis=1)[:, None]
    return p1, np.cross(u, p1)


def _orientation_search(y, b_body):
    """Each of the 24 right angles ``A``: least squares of ``y = g A^T B_body + c`` (gain ``g``, offset ``c``).

    Returns the best right angle, the RMS of every one (24,), and the margin (second-best RMS / best)."""
    rms = np.empty(len(RIGHT_ANGLES))
    yc = y - y.mean(axis=0)
    for k, a in enumerate(RIGHT_ANGLES):
        pred = b_body @ a  # rows: (A^T B)^T = B^T A
        pc = pred - pred.mean(axis=0)
        g = float(np.sum(pc * yc) / max(np.sum(pc * pc), 1e-30))
        rms[k] = np.sqrt(np.mean((yc - g * pc) ** 2)) if g > 0 else np.inf
    order = np.argsort(rms)
    margin = float(rms[order[1]] / max(rms[order[0]], 1e-12))
    return RIGHT_ANGLES[order[0]], rms, margin


def _linear_start(y, b_body, bases, robust=False):
    """Least squares of ``y = A B_body + b + basis @ theta``: returns ``W = A^-1``, ``b``, ``theta``; with
    ``robust``, once more without the samples beyond 5 robust standard deviations."""
    W, b, theta, resid = _linear_lstsq(y, b_body, bases, np.ones(len(y), bool))
    if robust:
        size = np.linalg.norm(resid, axis=1)
        keep = size <= np.median(size) + OUTLIER_SIGMAS * robust_sigma(size)
        if keep.sum() >= len(y) // 2:
            W, b, theta, _ = _linear_lstsq(y, b_body, bases, keep)
    return W, b, theta


def _linear_lstsq(y, b_body, bases, keep):
    """One least-squares solve of the linear start on the kept samples; also the residuals (N, 3) of all."""
    n = len(y)
    q = bases.shape[2] if bases is not None else 0
    design = np.zeros((n, 3, 12 + q))
    for j in range(3):
        design[:, j, 3 * j : 3 * j + 3] = b_body
        design[:, j, 9 + j] = 1.0
    if q:
        design[:, :, 12:] = bases
    coef, *_ = np.linalg.lstsq(design[keep].reshape(-1, 12 + q), y[keep].reshape(-1), rcond=None)
    a = coef[:9].reshape(3, 3)
    resid = y - np.einsum("njk,k->nj", design, coef)
    return np.linalg.inv(a), coef[9:12], coef[12:], resid


class _SensorProblem:
    """Residuals of one sensor's vector fit, weighted by their noises."""

    def __init__(self, y, b_body, f_ref, bases):
        self.y, self.b_body, self.f_ref, self.bases = y, b_body, f_ref, bases
        self.u = b_body / np.linalg.norm(b_body, axis=1)[:, None]
        self.p1, self.p2 = _perpendicular_basis(self.u)
        self.q = 0 if bases is None else bases.shape[2]

    def unpack(self, x):
        return x[:9].reshape(3, 3), x[9:12], x[12:]

    def corrected(self, x):
        W, b, theta = self.unpack(x)
        z = self.y - b
        if self.q:
            z = z - np.einsum("njk,k->nj", self.bases, theta)
        return z @ W.T

    def parts(self, x):
        """Total-field residual (N,), the two perpendicular components (N, 2), the vector residual (N, 3)."""
        B = self.corrected(x)
        e = B - self.b_body
        total = np.linalg.norm(B, axis=1) - self.f_ref
        perp = np.column_stack([np.sum(e * self.p1, axis=1), np.sum(e * self.p2, axis=1)])
        return total, perp, e

    def residuals(self, x, sigma_f, sigma_p):
        total, perp, _ = self.parts(x)
        return np.concatenate([total / sigma_f, perp.ravel() / sigma_p])

    def jacobian(self, x, sigma_f, sigma_p):
        """The Jacobian of :meth:`residuals` (rows as they are: the total-field residuals, then the two
        perpendicular components of each sample in turn; columns ``W`` row by row, ``b``, ``theta``)."""
        W, b, theta = self.unpack(x)
        z = self.y - b
        if self.q:
            z = z - np.einsum("njk,k->nj", self.bases, theta)
        B = z @ W.T
        n = len(z)
        dB = np.zeros((n, 3, 12 + self.q))  # dB_i / dx
        for i in range(3):
            dB[:, i, 3 * i : 3 * i + 3] = z
        dB[:, :, 9:12] = -W[None]
        if self.q:
            dB[:, :, 12:] = -np.einsum("ij,njk->nik", W, self.bases)
        u = B / np.linalg.norm(B, axis=1)[:, None]
        j_total = np.einsum("ni,nik->nk", u, dB) / sigma_f
        j_perp = np.stack([np.einsum("ni,nik->nk", self.p1, dB), np.einsum("ni,nik->nk", self.p2, dB)], axis=1)
        return np.concatenate([j_total, j_perp.reshape(2 * n, -1) / sigma_p])


#: The platform terms of earlier versions (``--platform-terms``, ``terms=``) and the catalogue effects they now are.
PLATFORM_EFFECTS = {"eddy": "eddy_currents", "current": "current_field"}


def vector_model(dataset, effects=(), terms=None) -> Model:
    """The model of a vector fit: the base terms and the catalogue ``effects`` (names ``NAME`` or ``NAME:SENSOR``,
    :class:`~magcal.model.terms.Effect` objects, or a :class:`~magcal.model.terms.Model`), plus the platform
    ``terms`` of earlier versions (``eddy``, ``current``: :data:`PLATFORM_EFFECTS`).

    Raises
    ------
    CalibrationError
        An effect the vector fit cannot take (a stage other than ``raw``: it acts on the array frame or the
        reference total field), one shared by the sensors of an array, or one whose channels the data lack.
    """
    if isinstance(effects, Model):
        model = effects.copy()
    else:
        items = list(effects or ())
        for t in list(terms or ()):
            if t not in PLATFORM_EFFECTS:
                raise CalibrationError(f"unknown platform term {t!r}; use {', '.join(PLATFORM_EFFECTS)}")
            items.append(PLATFORM_EFFECTS[t])
        names = [e for e in items if isinstance(e, str)]
        try:
            model = Model.from_names(names, dataset.n_sensors)
        except MagcalError as exc:
            raise CalibrationError(str(exc)) from None
        for e in items:
            if isinstance(e, Effect):
                model = model.with_effect(e)
            elif not isinstance(e, str):
                raise CalibrationError(f"effects must be names (e.g. 'current_field') or Effect objects, got {e!r}")
    seen = set()
    for e in model.effects:
        if e.label in seen:
            raise CalibrationError(f"effect {e.label} is named twice")
        seen.add(e.label)
        if e.stage != "raw":
            raise CalibrationError(
                f"{e.label}: a vector fit takes effects that act on a sensor's raw reading; this one acts on the "
                f"{'array frame' if e.stage == 'array' else 'reference total field'}: fit it in scalar mode"
            )
        if not e.per_sensor and dataset.n_sensors > 1:
            raise CalibrationError(f"{e.label}: shared by the sensors of an array; a vector fit fits each sensor alone")
        missing = e.missing_channels(dataset)
        if missing:
            raise CalibrationError(f"{e.label} needs {', '.join(missing)}; the data lack it")
    for e in model.effects:
        for x in model.effects:
            if x.name in getattr(e, "nested_in", ()) and (e.sensor is None or x.sensor is None or e.sensor == x.sensor):
                raise CalibrationError(
                    f"{e.label} is a special case of {x.label} (it holds it): together they leave a direction the "
                    "data cannot fix; fit one of them"
                )
    return model


def _instances_of(model, sensor) -> list:
    """``(effect, block label)`` of the model's instances acting on ``sensor``, in the model's order."""
    return [
        (e, block_label(e, es)) for e, es in model.instances() if es == sensor or (es is None and e.applies_to(sensor))
    ]


def _raw_bases(instances, dataset, ctx, bias_nT, rows) -> np.ndarray | None:
    """The raw-stage bases (n_rows, 3, q) of one sensor's effect instances, computed on the whole record (a rate in
    time stays exact under a mask of blocks) at ``z0 = y - bias`` and cut to ``rows``."""
    if not instances:
        return None
    z0 = dataset.readings_nT[ctx.sensor] - bias_nT
    return np.concatenate([np.asarray(e.raw_basis(z0, ctx), dtype=float)[rows] for e, _ in instances], axis=2)


def fit_vector(
    dataset: Dataset,
    reference: VectorReference | str,
    effects=None,
    terms=None,
    attitude_noise_deg: float | None = None,
    noise_nT: float | None = None,
    reference_total_nT=None,
    robust: bool = False,
    mask=None,
    warn: bool = True,
    field_gradient: bool = False,
) -> VectorFitResult:
    """Vector calibration of every sensor into the body frame from attitude and the field vector.

    Parameters
    ----------
    dataset : Dataset
        Readings (nT) and attitude (quaternions or ``roll_deg, pitch_deg, yaw_deg``, body -> NED).
    reference : VectorReference or str
        The Earth's field vector per sample (nT, NED); or ``"fitted"`` (a reference of kind ``fitted``, from
        :func:`magcal.checks.reference.resolve_vector_reference`): the field is a constant of unknown vector, fitted
        with the calibration (:mod:`magcal.fitting.labfield`: its uncertainty and the gauges the record leaves in
        :attr:`VectorFitResult.field`; a given vector in such a reference is the start and its declination the one
        kept when the attitudes cannot tell the declination from the mounting's yaw).
    effects : sequence of str or Effect, or Model, optional
        Catalogue effects fitted beside the base terms (``current_field``, ``eddy_currents``,
        ``attitude_time_offset``, ``temperature_bias:2``, ...; :func:`vector_model`). Default: none, the base
        model (bias, ``C^-1``, mounting); :func:`magcal.diagnosis.vector.diagnose_vector` says which to add.
    terms : sequence of str, optional
        The platform terms of earlier versions, ``eddy`` and ``current``: the same as the effects
        ``eddy_currents`` and ``current_field``.
    attitude_noise_deg : float, optional
        Attitude error per axis (deg, 1 sigma); estimated from the residuals when None.
    noise_nT : float, optional
        Sensor noise per axis (nT); estimated from the total-field residuals when None.
    reference_total_nT : numpy.ndarray or float, optional
        The total field for the total-field residual (e.g. a scalar magnetometer's ``ref_total``); default
        ``|B_ned|``.
    robust : bool
        Soft-L1 loss (residuals beyond about 3 standard deviations count less), and a start without the samples
        beyond 5: for records with spikes or drop-outs.
    mask : numpy.ndarray of bool, shape (N,), optional
        The samples fitted (default all). The effects' bases (a rate in time) are computed on the whole record, so
        a mask of blocks in time leaves them exact; their data-derived constants (a reference temperature, a step
        time) come from the fitted samples. Samples without an attitude (NaN angles or quaternion:
        :func:`magcal.data.attitude.attitude_rows`) or without a finite reference vector (no position for IGRF)
        are left out as well, and a note counts them and names their rows (:attr:`VectorFitResult.gaps`,
        :attr:`VectorFitResult.fitted`).
    warn : bool
        Raise the fit's notes (:attr:`VectorFitResult.warnings`: weak tilt, samples set aside...) as
        :class:`~magcal.core.errors.DataWarning` (the default, for a user's call); False leaves them in the result
        only, for the engine's own steps and the command line, which pass notes back as values.
    field_gradient : bool
        Also fit a gradient of the field along the path, ``B(p) = B0 + G (p - p0)`` (5 parameters, nT/m), from the
        positions (``pos_n_m, pos_e_m, pos_d_m`` or ``lat, lon, alt_m``): a magnet or steel near the path. It is the
        record's (:attr:`VectorFitResult.field`), never carried by apply.

    Raises
    ------
    CalibrationError
        No attitude, a mirrored axis, too few samples: fewer than :data:`MIN_SAMPLES` (or the parameters per sensor)
        left with an attitude and a reference (the message says how many had each); an effect the vector fit
        cannot take (:func:`vector_model`).
    """
    start = time.perf_counter()
    if isinstance(reference, str):
        reference = _named_reference(dataset, reference)
    if reference.kind == "fitted" or field_gradient:
        options = {
            "effects": effects,
            "terms": terms,
            "attitude_noise_deg": attitude_noise_deg,
            "noise_nT": noise_nT,
            "reference_total_nT": reference_total_nT,
            "robust": robust,
        }
        result = _fit_with_field(dataset, reference, field_gradient, mask, options)
        result.wall_s = time.perf_counter() - start
        if warn:
            _notes.warn(result.notes)
        return result
    rotation, have_attitude = _attitude_of(dataset)
    ned = np.asarray(reference.ned_nT, dtype=float)
    if ned.shape != (dataset.n_samples, 3):
        raise CalibrationError(f"the reference vector has shape {ned.shape}, expected ({dataset.n_samples}, 3)")
    model = vector_model(dataset, effects if effects is not None else (), terms)
    n_par = 12 + max(sum(len(e.param_names()) for e, _ in _instances_of(model, s)) for s in range(dataset.n_sensors))
    chosen = np.ones(dataset.n_samples, bool) if mask is None else np.asarray(mask, dtype=bool)
    if chosen.shape != (dataset.n_samples,):
        raise CalibrationError(f"mask has shape {chosen.shape}, expected ({dataset.n_samples},)")
    f_all = (
        np.linalg.norm(ned, axis=1)
        if reference_total_nT is None
        else np.broadcast_to(np.asarray(reference_total_nT, dtype=float), (dataset.n_samples,))
    )
    have_reference = np.all(np.isfinite(ned), axis=1) & np.isfinite(f_all)
    keep = chosen & have_attitude & have_reference
    gaps = SampleGaps.count(chosen, have_attitude, have_reference)
    fewest = max(MIN_SAMPLES, n_par)
    if keep.sum() < fewest:
        if gaps.n_left_out:
            raise CalibrationError(
                f"{dataset.source or 'data'}: only {int(keep.sum())} of {gaps.n_chosen} samples have both an "
                f"attitude and a reference field vector ({gaps.n_chosen - gaps.n_without_attitude} have an attitude, "
                f"{gaps.n_chosen - gaps.n_without_reference} a reference): a vector fit of {n_par} parameters per "
                f"sensor needs at least {fewest}. "
                + gaps.where()
                + "; record longer after the attitude (and the GPS's fix) starts"
            )
        raise CalibrationError(
            f"{dataset.source or 'data'}: {int(keep.sum())} samples are too few for a vector fit of {n_par} "
            "parameters per sensor; record more"
        )
    rows = np.flatnonzero(keep)
    b_body = body_reference_nT(rotation[rows], ned[keep])
    f_ref = f_all[keep]
    notes = _declination_notes(dataset, ned[keep])
    if gaps.n_left_out:
        notes.append(gaps.text())
    ctxs = contexts(dataset)
    starts = [_base_start(dataset.readings_nT[s][keep], b_body) for s in range(dataset.n_sensors)]
    if model.effects:  # data-derived constants from the fitted samples and the base start's total-field residuals
        kept = dataset.masked(keep)
        residuals = np.array(
            [
                np.linalg.norm((dataset.readings_nT[s][keep] - b0) @ W0.T, axis=1) - f_ref
                for s, (W0, b0, _) in enumerate(starts)
            ]
        )
        for e in model.effects:
            e.configure(kept, residuals)
    fits, effect_values, blocks = [], {}, []
    for s in range(dataset.n_sensors):
        fit, values, cov = _fit_sensor(
            s, dataset, model, ctxs[s], rows, b_body, f_ref, starts[s], noise_nT, attitude_noise_deg, robust, notes
        )
        fits.append(fit)
        effect_values.update(values)
        blocks.append(cov)
    pulls = {label: z for f in fits for label, z in f.bound_pull_z.items()}
    held = fitted_outside_domain(model, effect_values, pulls=pulls) if model.effects else ""
    if held:
        notes.append(held_note_text(held))
    tilt = _tilt_range_deg(rotation[rows])
    for s, fit in enumerate(fits):
        if not fit.determined:
            notes.append(_undetermined_note(s, fit, dataset, rows, b_body, tilt))
    sensors = [SensorCalibration(f.cinv, f.bias_nT, f.mounting, summary=f.summary()) for f in fits]
    if tilt < 5:
        notes.append(
            f"the body tilted at most {tilt:.1f} deg: the vertical axis's scale and the bias along it rest on few "
            "directions; fly some banked turns or pitch changes"
        )
    cal = Calibration(
        sensors=sensors,
        reference_total_nT=float(np.median(f_ref)),
        baseline_m=dataset.baseline_m,
        frame="body",
        mode="vector",
        model=model if model.effects else None,
        effect_values=effect_values,
        base_covariance=_joint_covariance(model, blocks),
    )
    result = VectorFitResult(
        calibration=cal,
        sensors=fits,
        reference=reference,
        terms=model.effect_labels,
        warnings=notes,
        n_samples=int(keep.sum()),
        wall_s=time.perf_counter() - start,
        fitted=keep,
        gaps=gaps,
    )
    cal.summary = {"vector_fit": result.to_dict()}
    if warn:
        _notes.warn(result.notes)
    return result


def _attitude_of(dataset):
    """``(rotation, have_attitude)`` of a dataset (:func:`magcal.data.attitude.attitude_rows`), refused without."""
    found = attitude_rows(dataset)
    if found is None:
        raise CalibrationError(
            f"{dataset.source or 'data'}: a vector calibration needs the attitude: qw, qx, qy, qz or roll_deg, "
            "pitch_deg, yaw_deg columns (or a flight log with ATT / vehicle_attitude)"
        )
    return found


def _named_reference(dataset, name) -> VectorReference:
    """A reference named by text (``"fitted"``, ``"igrf"``) for the dataset, refused when it gives none."""
    found = resolve_vector_reference(dataset, reference=name)
    if found is None:
        raise CalibrationError(
            f"reference {name!r}: no field vector; use 'fitted', 'igrf' or the ref_n, ref_e, ref_d columns"
        )
    return found


def _base_start(y, b_body):
    """``(W, b, right angle)``: the linear start of the base model (no effects) and the right angle the field
    vectors choose."""
    right, _, margin = _orientation_search(y, b_body)
    W0, b0, _ = _linear_start(y, b_body, None)
    return W0, b0, (right, margin)


def _joint_covariance(model, blocks) -> np.ndarray | None:
    """The calibration's ``base_covariance`` from each sensor's covariance of ``(W, b, theta)``: every sensor's
    ``W`` and bias first, then the effects' parameters in the model's order
    (:func:`magcal.calibration.uncertainty.effect_layout`); the sensors' fits are independent."""
    if any(c is None for c in blocks):
        return None
    n_s = len(blocks)
    layout = [(block_label(e, es), es) for e, es in model.instances()]
    sizes = {block_label(e, es): len(e.param_names()) for e, es in model.instances()}
    offsets, k = {}, 12 * n_s
    for label, _ in layout:
        offsets[label] = k
        k += sizes[label]
    cov = np.zeros((k, k))
    for s, (c, labels) in enumerate(blocks):
        index = list(range(12 * s, 12 * s + 12))
        for label in labels:
            index += list(range(offsets[label], offsets[label] + sizes[label]))
        cov[np.ix_(index, index)] = c
    return cov


def _fit_sensor(s, dataset, model, ctx, rows, b_body, f_ref, start, noise_nT, attitude_noise_deg, robust, notes):
    """One sensor's maximum-likelihood vector fit: ``(SensorVectorFit, effect values, (covariance, labels))``."""
    y = dataset.readings_nT[s][rows]
    W_start, b_start, (right, margin) = start
    instances = _instances_of(model, s)
    labels = [label for _, label in instances]
    sizes = [len(e.param_names()) for e, _ in instances]
    basis = _raw_bases(instances, dataset, ctx, b_start, rows)
    W0, b0, theta0 = _linear_start(y, b_body, basis, robust) if basis is not None else (W_start, b_start, np.zeros(0))
    prob = _SensorProblem(y, b_body, f_ref, basis)
    x = np.concatenate([W0.ravel(), b0, theta0])
    field_nT = float(np.median(f_ref))
    total_group = NoiseGroup(1e-3, noise_nT)
    sigma_f = total_group.sigma(prob.parts(x)[0])
    given_p = (
        None if attitude_noise_deg is None else float(np.hypot(np.radians(attitude_noise_deg) * field_nT, sigma_f))
    )
    groups = [total_group, NoiseGroup(1e-3, given_p)]  # the total field; each component across the field
    scale = np.concatenate(
        [np.full(9, 1e-3), np.full(3, 10.0)] + [np.asarray(e.param_scale(), dtype=float) for e, _ in instances]
    )
    rebased = not any(e.basis_uses_readings for e, _ in instances)

    def parts(xv):
        total, perp, _ = prob.parts(xv)
        return [total, perp.ravel()]

    def solve(xv, sigmas):
        # within the effects' domains (a loop width >= 0...), taken after a refinement moved their constants
        return _solve_within(prob, xv, tuple(sigmas), _bounds(instances), scale, robust)

    def again(rnd, xv):
        # a basis of the readings minus the bias, or constants the fit moved: once more
        nonlocal prob, rebased
        refined = _refine(instances, sizes, xv[12:]) if rnd < MAX_REFINEMENTS else False
        if not (refined or not rebased):
            return False
        prob = _SensorProblem(y, b_body, f_ref, _raw_bases(instances, dataset, ctx, xv[9:12], rows))
        rebased = True
        return True

    start_sigmas = [sigma_f, groups[1].sigma(parts(x)[1])]
    fit = reweighted_fit(solve, parts, groups, x, start_sigmas, rounds=2, most_rounds=MAX_REFINEMENTS + 2, again=again)
    x, sol, (sigma_f, sigma_p) = fit.x, fit.solution, fit.sigmas
    total, perp, e = prob.parts(x)
    W, b, theta = prob.unpack(x)
    mounted = mounting_fields(W, b, right, margin, s)
    cov = correlated_covariance(sol.jac, prob.residuals(x, sigma_f, sigma_p), len(x), (total, e), len(total))
    n_out = int(np.count_nonzero(beyond(total, sigma_f) | beyond(perp, sigma_p)))
    bias_sd = mount_sd = cov_block = None
    pulls: dict = {}
    if cov.matrix is not None:
        bias_sd = np.sqrt(np.clip(np.diag(cov.matrix)[9:12], 0.0, None))
        mount_sd = mounting_sd_deg(W, cov.matrix[:9, :9])
        cov_block = (cov.matrix, labels)
        pulls = _pulls(prob, x, (sigma_f, sigma_p), _bounds(instances), cov.jtj_inv, cov.matrix, labels, sizes)
    determined = not (
        (bias_sd is not None and float(np.max(bias_sd)) > UNDETERMINED_BIAS_FRACTION * field_nT)
        or (mount_sd is not None and float(np.max(mount_sd)) > UNDETERMINED_MOUNTING_DEG)
    )
    notes.extend(_sensor_notes(s, n_out, robust, mounted["mounting"], right))
    values, k = {}, 0
    for label, q in zip(labels, sizes):
        values[label] = theta[k : k + q].copy()
        k += q
    att_noise = (
        float(attitude_noise_deg) if attitude_noise_deg is not None else attitude_error_deg(sigma_p, sigma_f, field_nT)
    )
    fit = SensorVectorFit(
        **mounted,
        terms=_terms_of(values),
        rms_vector_nT=float(np.sqrt(np.mean(e**2))),
        rms_perpendicular_nT=float(np.sqrt(np.mean(perp**2))),
        rms_total_field_nT=float(np.sqrt(np.mean(total**2))),
        sigma_perpendicular_nT=float(sigma_p),
        sigma_total_field_nT=float(sigma_f),
        attitude_noise_deg=att_noise,
        attitude_noise_source="given" if attitude_noise_deg is not None else "estimated",
        nfev=int(sol.nfev),
        bias_sd_nT=bias_sd,
        mounting_sd_deg=mount_sd,
        n_outliers=n_out,
        residual_lag1_correlation=float(cov.lag1),
        sd_widening=float(cov.widening),
        determined=determined,
        bound_pull_z=pulls,
        total_residual_nT=total,
        vector_residual_nT=e,
    )
    return fit, values, cov_block


def _solve_within(prob, x, sigmas, bounds, scale, robust):
    """``(x, solution)``: the weighted least squares of one sensor with every parameter within ``bounds``.

    An active set around :func:`scipy.optimize.least_squares` (Levenberg-Marquardt, or the trust region of a robust
    loss): the unbounded minimum first; a parameter that it leaves outside its domain is held at the bound it
    crossed and the others refitted, until none is outside. The solution's ``jac`` is the whole Jacobian at ``x``
    (the held parameters' columns too, for the covariance). A bounded trust-region fit would do the same at 50-100x
    the cost on a record of 2000 samples.
    """
    lower, upper = bounds
    x = np.clip(np.asarray(x, dtype=float), lower, upper)
    held = np.zeros(x.size, bool)
    sol = None
    for _ in range(x.size + 1):
        free = ~held

        def full(v, free=free, start=x):
            out = start.copy()
            out[free] = v
            return out

        sol = weighted_least_squares(
            lambda v, free=free: prob.residuals(full(v, free), *sigmas),
            x[free],
            scale[free],
            robust,
            jac=lambda v, free=free: prob.jacobian(full(v, free), *sigmas)[:, free],
            max_nfev=MAX_NFEV,
        )
        x = full(sol.x)
        out = free & ((x < lower) | (x > upper))
        if not out.any():
            break
        held |= out
        x = np.clip(x, lower, upper)
    assert sol is not None
    if held.any():
        sol.x, sol.jac = x, prob.jacobian(x, *sigmas)
    return x, sol


def _pulls(prob, x, sigmas, bounds, jtj_inv, cov, labels, sizes) -> dict:
    """Per effect block, how far the data pull each parameter past its nearer bound (standard deviations,
    :func:`magcal.model.terms.bound_pulls`); empty when no parameter sits on a bound."""
    lower, upper = bounds
    if not np.any((x <= lower) | (x >= upper)):
        return {}
    gradient = prob.jacobian(x, *sigmas).T @ prob.residuals(x, *sigmas)
    z = bound_pulls(x, lower, upper, gradient, jtj_inv, np.sqrt(np.clip(np.diag(cov), 0.0, None)))
    out, k = {}, 12
    for label, q in zip(labels, sizes):
        out[label] = z[k : k + q]
        k += q
    return out


def _bounds(instances) -> tuple[np.ndarray, np.ndarray]:
    """Bounds of one sensor's parameters ``(W, b, theta)``: the base terms free, each effect within its physical
    domain (:meth:`magcal.model.terms.Effect.domain`)."""
    lower, upper = [np.full(12, -np.inf)], [np.full(12, np.inf)]
    for e, _ in instances:
        lo, hi = e.param_bounds()
        q = len(e.param_names())
        lower.append(np.broadcast_to(np.asarray(lo, dtype=float), (q,)))
        upper.append(np.broadcast_to(np.asarray(hi, dtype=float), (q,)))
    return np.concatenate(lower), np.concatenate(upper)


def _refine(instances, sizes, theta) -> bool:
    """Let each effect move its data-derived constants to the fitted values (:meth:`~magcal.model.terms.Effect.refine`:
    a time offset's shift, a hysteresis loop's width); True when one did (the fit is then repeated)."""
    changed, k = False, 0
    for (e, label), q in zip(instances, sizes):
        try:
            changed |= bool(e.refine({label: theta[k : k + q]}, None))
        except (TypeError, AttributeError):  # an effect whose refinement needs the scalar fitter's context
            pass
        k += q
    return changed


def _terms_of(values) -> dict:
    """A sensor's fitted effects by catalogue name, and the platform's under the names of earlier versions
    (``eddy_ms`` (3, 3), ``current_nT_per_unit`` (3,))."""
    terms = {label.split(":")[0]: np.asarray(v, dtype=float) for label, v in values.items()}
    if "eddy_currents" in terms:
        terms["eddy_ms"] = terms["eddy_currents"].reshape(3, 3)
    if "current_field" in terms:
        terms["current_nT_per_unit"] = terms["current_field"]
    return terms


def _sensor_notes(s, n_out, robust, R, right) -> list:
    """What one sensor's fit has to say: samples far out, a mounting off the right angles (not determined:
    :func:`_undetermined_note`)."""
    notes = []
    if n_out:
        notes.append(
            f"sensor {s + 1}: {n_out} sample(s) lie beyond 5 standard deviations of the residuals"
            + ("" if robust else "; --robust keeps them from pulling the fit")
        )
    nearest, off = nearest_right_angle(R)
    if not np.allclose(nearest, right):
        notes.append(
            f"sensor {s + 1}: the right angle the field vectors chose first ({describe_right_angle(right)}) is not "
            f"the one nearest the fitted mounting ({describe_right_angle(nearest)}); the mounting is far from "
            "any right angle or the attitude and reference disagree"
        )
    if off > 20:
        notes.append(
            f"sensor {s + 1}: the mounting is {off:.1f} deg off the nearest right angle: check the attitude's frame "
            "(body x forward, y right, z down; world north-east-down) and the reference"
        )
    return notes


def attitude_error_deg(sigma_perpendicular_nT, sigma_total_nT, field_nT) -> float:
    """The attitude error (deg, 1 sigma per axis) that a residual across the field implies beside the sensor's own
    noise: ``sqrt(sigma_perp^2 - sigma_F^2) / |B|`` (0 when the residual across the field is no larger than the
    sensor's). The one estimate of ``magcal calibrate`` (:attr:`SensorVectorFit.attitude_noise_deg`) and of
    ``magcal diagnose``.

    Parameters
    ----------
    sigma_perpendicular_nT : float
        Noise of each component of the residual perpendicular to the field, nT.
    sigma_total_nT : float
        Noise of the total-field residual (the sensor's own), nT.
    field_nT : float
        The field's magnitude, nT.

    Examples
    --------
    >>> round(attitude_error_deg(np.hypot(np.radians(0.1) * 50_000.0, 3.0), 3.0, 50_000.0), 4)
    0.1
    """
    excess = max(float(sigma_perpendicular_nT) ** 2 - float(sigma_total_nT) ** 2, 0.0)
    return float(np.degrees(np.sqrt(excess) / float(field_nT)))


def positions_m(dataset) -> np.ndarray | None:
    """The record's positions (N, 3), m, north-east-down (:func:`magcal.fitting.labfield.positions_ned_m`: the
    ``pos_n_m..`` columns, else latitude, longitude and height), or None without them."""
    return labfield.positions_ned_m(dataset)


def position_basis(p) -> np.ndarray:
    """A smooth function of a position (N, 3): the polynomials of its components up to degree 3 (19 columns; a
    magnet's field, falling as the cube of the distance, needs the third)."""
    p = (p - p.mean(axis=0)) / np.maximum(p.std(axis=0), 1e-9)
    cols = [p[:, i] for i in range(3)]
    cols += [p[:, i] * p[:, j] for i in range(3) for j in range(i, 3)]
    cols += [p[:, i] * p[:, j] * p[:, k] for i in range(3) for j in range(i, 3) for k in range(j, 3)]
    return np.column_stack(cols)


@dataclass
class UndeterminedCause:
    """Why a record does not determine a vector fit: the geometry, or a misfit (:func:`undetermined_cause`).

    Attributes
    ----------
    kind : str
        ``geometry`` (the attitudes span too few directions: a spread below :data:`LOW_SPREAD_DEG`), ``misfit`` (the
        attitudes span enough and the total-field residual follows time or position: the field itself changes; no
        attitude error moves ``|B|``), ``attitude`` (only the components across the field follow time: a wandering
        attitude error) or ``noise`` (none of these).
    follows : str
        ``time``, ``position`` or ``""``.
    share : float
        The share of the residual's variance the smooth function of ``follows`` explains.
    lag1 : float
        Lag-1 correlation of the total-field residual in record order.
    total_rms_nT, total_white_nT : float
        RMS of the total-field residual, and its white noise (from its differences), nT.
    spread_deg : float
        The spread of the field's direction in the body frame about its least-covered axis, deg
        (:func:`direction_spread_deg`).
    text : str
        The reason and what to do, in words.
    """

    kind: str
    follows: str
    share: float
    lag1: float
    total_rms_nT: float
    total_white_nT: float
    spread_deg: float
    text: str

    def to_dict(self) -> dict:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


def direction_spread_deg(field_body_nT) -> float:
    """How widely a record turned the field in the body frame: the RMS angle (deg) of its direction about the
    least-covered axis, ``asin(sqrt(lambda_min))`` of the covariance of the unit directions.

    Examples
    --------
    >>> u = Rotation.random(2000, random_state=0).apply([0.0, 0.0, 1.0])  # tumbled: every direction
    >>> 30 < direction_spread_deg(u) < 40
    True
    >>> round(direction_spread_deg(np.tile([0.4, 0.0, 0.9], (50, 1))), 3)  # never turned
    0.0
    """
    u = np.asarray(field_body_nT, dtype=float)
    u = u / np.linalg.norm(u, axis=1, keepdims=True)
    lam = float(np.clip(np.linalg.eigvalsh(np.cov(u.T))[0], 0.0, 1.0))
    return float(np.degrees(np.arcsin(np.sqrt(lam))))


def undetermined_cause(
    total_nT, perpendicular_nT, time_s=None, position_m=None, spread_deg=35.0, tilt_deg=None
) -> UndeterminedCause:
    """Tell the geometry from a misfit when a record does not determine a vector fit.

    An attitude error turns the field and leaves ``|B|`` alone; a magnet or steel near the path, a field that
    changes or a hard iron that moves change ``|B|`` itself. So when the attitudes span enough directions (tilt
    :data:`LOW_SPREAD_DEG` or more of spread), a total-field residual that follows time or position (a smooth function of it
    explains :data:`FOLLOWS_SHARE` of its variance, and it is :data:`FOLLOWS_EXCESS` times its white noise) is a
    misfit; residuals across the field that follow time with ``|B|`` at its noise are a wandering attitude error.
    With little tilt the fit bends an attitude error into ``|B|`` as well (the vertical scale and the bias trade),
    and the geometry comes first.

    Parameters
    ----------
    total_nT : array_like, shape (N,)
        The total-field residual, nT, in record order.
    perpendicular_nT : array_like, shape (N, k)
        The residual's components across the field, nT.
    time_s : array_like, shape (N,), optional
        Sample times (s); the sample index without them.
    position_m : array_like, shape (N, 3), optional
        Positions (m).
    spread_deg : float
        The spread of the field's direction in the body frame (deg, :func:`direction_spread_deg`).
    tilt_deg : float, optional
        Largest tilt of the record (deg), named in the advice when under 60 deg (a vehicle that stays near level).
    """
    total = np.asarray(total_nT, dtype=float)
    n = len(total)
    t = np.arange(n, dtype=float) if time_s is None else np.asarray(time_s, dtype=float)
    basis = smooth_in_time(t)
    white = float(robust_sigma(np.diff(total)) / np.sqrt(2.0)) if n > 3 else float(np.std(total))
    rms = float(np.sqrt(np.mean(total**2)))
    shares = {"time": explained_share(total, basis)}
    if position_m is not None and np.all(np.isfinite(position_m)) and np.ptp(position_m, axis=0).max() > 0:
        shares["position"] = explained_share(total, position_basis(np.asarray(position_m, dtype=float)))
    follows = max(shares, key=lambda k: shares[k])
    lag1 = lag1_correlation(total)
    perp_share = explained_share(perpendicular_nT, basis)
    field_follows = shares[follows] >= FOLLOWS_SHARE and rms >= FOLLOWS_EXCESS * max(white, 1e-9)
    geometry = (
        f"the attitudes span few directions (the field turned {spread_deg:.1f} deg about its least-covered axis in "
        "the body"
        + (f", tilt at most {tilt_deg:.0f} deg" if tilt_deg is not None and tilt_deg < 60.0 else "")
        + "): the scale and the bias along it trade against each other; turn the sensor about more axes (a vehicle: "
        "banked turns and pitch changes of +-20 deg or more over several minutes)"
    )
    share = shares[follows]
    if spread_deg < LOW_SPREAD_DEG:  # the fit bends an attitude error into |B| too: the two cannot be told apart
        kind = "geometry"
        text = geometry
        if field_follows or perp_share >= FOLLOWS_SHARE:
            text += (
                f"; the residual follows the {follows if field_follows else 'time'}: a wandering attitude error (then "
                "a better attitude, an INS) or a field that changes, which this geometry cannot tell apart"
            )
        follows = follows if field_follows else ""
    elif field_follows:
        kind = "misfit"
        text = (
            f"the total-field residual follows the {follows} ({100 * share:.0f} % of its variance, lag-1 r = "
            f"{lag1:.2f}; {rms:.3g} nT RMS against {white:.3g} nT of noise): a misfit, not the attitudes (they turned "
            f"the field {spread_deg:.0f} deg about its least-covered axis, and no attitude error changes |B|): "
            + (
                "a magnet or steel near the path (the field differs from place to place)"
                if follows == "position"
                else "a magnet or steel near the path, a field that changes in time, or a hard iron that moves"
            )
            + "; record away from it, with the sensor's own magnets fixed"
        )
    elif perp_share >= FOLLOWS_SHARE:
        kind, follows, share = "attitude", "time", perp_share
        text = (
            f"the residual across the field follows time ({100 * perp_share:.0f} % of its variance) while |B| stays "
            f"near its noise ({rms:.3g} nT RMS): a wandering attitude error that does not average out; record longer, "
            "with a better attitude (an INS)"
        )
    else:
        kind, follows = "noise", ""
        perp_rms = float(np.sqrt(np.mean(np.sum(np.square(perpendicular_nT), axis=1) / 2.0)))
        text = (
            f"the residuals (across the field {perp_rms:.3g} nT RMS, |B| {rms:.3g} nT) follow neither time nor "
            "position: spikes or a noisy attitude (try --robust), or the attitude's frame or the field vector are not "
            "the ones the record holds"
        )
    return UndeterminedCause(kind, follows, float(share), float(lag1), rms, white, float(spread_deg), text)


def _undetermined_note(s, fit, dataset, rows, b_body, tilt_deg) -> str:
    """The note of a sensor the record does not determine: its standard deviations and why
    (:func:`undetermined_cause`, also kept as :attr:`SensorVectorFit.undetermined_cause`)."""
    u = b_body / np.linalg.norm(b_body, axis=1, keepdims=True)
    e = np.asarray(fit.vector_residual_nT, dtype=float)
    perp = e - np.sum(e * u, axis=1)[:, None] * u
    time_s = None if dataset.time_s is None else np.asarray(dataset.time_s, dtype=float)[rows]
    pos = positions_m(dataset)
    cause = undetermined_cause(
        fit.total_residual_nT,
        perp,
        time_s,
        None if pos is None else pos[rows],
        spread_deg=direction_spread_deg(b_body),
        tilt_deg=tilt_deg,
    )
    fit.undetermined_cause = cause
    field_nT = float(np.median(np.linalg.norm(b_body, axis=1)))
    bias_sd, mount_sd = float(np.max(fit.bias_sd_nT)), float(np.max(fit.mounting_sd_deg))
    return (
        f"sensor {s + 1}: this record does not determine the calibration: the bias's standard deviation is up "
        f"to {bias_sd:.0f} nT ({100 * bias_sd / field_nT:.1f} % of the field) and the mounting's {mount_sd:.2f} deg"
        + (
            f" (widened {fit.sd_widening:.1f}x: the residuals are correlated in time, r = "
            f"{fit.residual_lag1_correlation:.2f})"
            if fit.sd_widening > 1.05
            else ""
        )
        + f"; {cause.text}. Do not apply it"
    )


def _declination_notes(dataset, ned) -> list:
    """A note when the declination the vehicle used for its heading (``metadata['log_declination_deg']``) is not the
    reference field's: the logged yaw is then off true north by the difference, and no calibration removes that."""
    given = (dataset.metadata or {}).get("log_declination_deg")
    try:
        setting = float(given) if given is not None else None
    except (TypeError, ValueError):
        return []
    if setting is None:
        return []
    if not np.isfinite(setting):
        return []
    field_dec = float(np.degrees(np.arctan2(np.median(ned[:, 1]), np.median(ned[:, 0]))))
    diff = (setting - field_dec + 180.0) % 360.0 - 180.0
    if abs(diff) <= DECLINATION_TOLERANCE_DEG:
        return []
    return [
        f"the vehicle turned its magnetic heading into a true heading with a declination of {setting:.2f} deg (the "
        f"log's COMPASS_DEC), but the reference field's declination is {field_dec:.2f} deg: its logged yaw is about "
        f"{diff:+.1f} deg off true north, which turns the world components by as much and which no calibration of "
        "the sensor removes; set COMPASS_DEC right (or COMPASS_AUTODEC 1) and record again"
    ]


def _tilt_range_deg(rotation: Rotation) -> float:
    """Largest angle (deg) between the body's z axis and the vertical over the record."""
    z = rotation.apply(np.array([0.0, 0.0, 1.0]))
    return float(np.degrees(np.max(np.arccos(np.clip(z[:, 2], -1.0, 1.0)))))


@dataclass
class VectorValidation(BlockValidation):
    """Held-out figures of vector fits with and without effects (:func:`validate_vector`).

    Attributes
    ----------
    rows : list of dict
        Per model (``terms``: the effects fitted): ``in_vector_nT`` / ``held_vector_nT`` (world
        components against the reference, RMS per component) and ``in_total_nT`` / ``held_total_nT`` (|B| against
        the reference total field), all sensors together.
    n_blocks, train
        As :class:`magcal.fitting.validation.BlockValidation`.
    """

    def text(self) -> str:
        lines = [
            f"  held-out check (fitted on the 1st, 3rd, ... of {self.n_blocks} blocks in time, scored on the others; "
            "world components and |B| against the reference, RMS in nT):"
        ]
        for r in self.rows:
            name = ", ".join(r["terms"]) or "base model"
            lines.append(
                f"    {name:28s} vector {r['in_vector_nT']:.2f} in / {r['held_vector_nT']:.2f} held out; "
                f"|B| {r['in_total_nT']:.2f} in / {r['held_total_nT']:.2f} held out"
            )
        return "\n".join(lines) + "\n"


def validate_vector(dataset, reference, terms=None, n_blocks=None, effects=None, **options) -> VectorValidation:
    """Fit on alternate blocks in time and score on the blocks between: the base vector model and the model with
    the platform terms (each term alone too when there are several), so that a term that only fits this record
    shows (its held-out figures do not fall).

    Parameters
    ----------
    dataset, reference
        As for :func:`fit_vector` (the dataset needs its attitude).
    terms : sequence of str, optional
        The platform terms of earlier versions (``eddy``, ``current``), as effects (:data:`PLATFORM_EFFECTS`).
    effects : sequence of str, optional
        Effect labels (``current_field``, ``eddy_currents:2``...). With neither: every platform effect the data
        support.
    n_blocks : int, optional
        Blocks in time, odd, at least 3 (:func:`magcal.fitting.validation.held_out_blocks`: by default blocks of at
        least :data:`magcal.fitting.validation.MIN_BLOCK_S`).
    **options
        Passed to :func:`fit_vector` (``attitude_noise_deg``, ``noise_nT``, ``reference_total_nT``, ``robust``).

    Raises
    ------
    CalibrationError
        A record too short to split (:func:`magcal.fitting.validation.split_problem`).
    """
    n = dataset.n_samples
    train, test, n_blocks = held_out_blocks(dataset, n_blocks)
    if effects is None and terms is None:
        terms = available_terms(dataset)
    terms = list(effects or ()) + [PLATFORM_EFFECTS.get(t, t) for t in terms or ()]
    models = [[]] + ([[t] for t in terms] if len(terms) > 1 else []) + ([terms] if terms else [])
    found = attitude_rows(dataset)
    if found is None:
        raise MagcalError(f"{dataset.source or 'dataset'}: the held-out check of a vector calibration needs attitude")
    rotation, have = found
    ned = np.asarray(reference.ned_nT, dtype=float)
    f_ref = options.get("reference_total_nT")
    f_ref = np.linalg.norm(ned, axis=1) if f_ref is None else np.broadcast_to(np.asarray(f_ref, float), (n,))
    scored = have & np.all(np.isfinite(ned), axis=1) & np.isfinite(f_ref)  # what the fits could use
    rows = []
    # one fit per model on the training blocks (their notes are not the held-out check's: left in each result)
    for model in models:
        cal = fit_vector(dataset, reference, effects=model, mask=train, warn=False, **options).calibration
        world = np.stack([rotation.apply(b) for b in cal.correct(dataset, warn=False, force=True)])
        err = world - ned[None]
        total = np.linalg.norm(world, axis=2) - f_ref[None]

        def rms(values, part):
            return float(np.sqrt(np.mean(values[:, part & scored] ** 2)))

        rows.append(
            {
                "terms": list(model),
                "in_vector_nT": rms(err, train),
                "held_vector_nT": rms(err, test),
                "in_total_nT": rms(total, train),
                "held_total_nT": rms(total, test),
            }
        )
    return VectorValidation(n_blocks, rows, train=train)


# ----------------------------------------------------------------------------------------------------------------
# the field fitted with the calibration (magcal.fitting.labfield)
# ----------------------------------------------------------------------------------------------------------------

#: Directions tried for the start of a fitted field (a Fibonacci sphere) and the samples they are tried on.
FIELD_START_DIRECTIONS = 400
FIELD_START_SAMPLES = 600


def _fit_with_field(dataset, reference, gradient, mask, options) -> VectorFitResult:
    """:func:`fit_vector` with the field fitted (a reference of kind ``fitted``) or with a gradient of it along the
    path: rounds of a vector fit at the field so far and a joint solve of every sensor's parameters with the field's
    (:func:`magcal.fitting.labfield.solve`), then the vector fit at the field found."""
    rotation, have_attitude = _attitude_of(dataset)
    fitted = reference.kind == "fitted"
    given = np.asarray(reference.ned_nT, dtype=float)
    usable = (np.ones(dataset.n_samples, bool) if mask is None else np.asarray(mask, bool)) & have_attitude
    offsets = origin = None
    positions = labfield.positions_ned_m(dataset) if gradient else None
    if gradient:
        if positions is None:
            raise CalibrationError(
                f"{dataset.source or 'data'}: a gradient of the field along the path needs the positions: pos_n_m, "
                "pos_e_m, pos_d_m columns (m, north-east-down) or lat, lon, alt_m"
            )
        usable &= np.all(np.isfinite(positions), axis=1)
    if not fitted:
        usable &= np.all(np.isfinite(given), axis=1)
    rows = np.flatnonzero(usable)
    if len(rows) < MIN_SAMPLES:
        raise CalibrationError(
            f"{dataset.source or 'data'}: {len(rows)} samples have an attitude"
            + (" and a position" if gradient else "")
            + f"; a vector fit with the field needs at least {MIN_SAMPLES}"
        )
    if positions is not None:
        origin = np.mean(positions[rows], axis=0)
        offsets = positions[rows] - origin
    total, total_given = _field_total(dataset, options.get("reference_total_nT"), rows)
    turned, _ = labfield.turn_span_deg(rotation[rows])
    if fitted and turned < labfield.YAW_ONLY_TILT_DEG:
        raise CalibrationError(
            f"{dataset.source or 'data'}: the record barely turned (its attitudes lie within {turned:.1f} deg of "
            "their mean): neither the calibration nor the field can be fitted from it; turn the sensor through many "
            "directions (a record that only moves the sensor can be judged against a field fitted on another "
            "record of the lab: --reference-vector CAL.json)"
        )
    if fitted:
        start = given[rows[0]] if np.all(np.isfinite(given[rows[0]])) else None
        start = _field_start(dataset.readings_nT[0][rows], rotation[rows]) if start is None else start
        total = total if total_given else field_magnitude_nT(dataset.readings_nT[0][rows])
        dec, inc = labfield.angles_deg(start)
        setup = labfield.FieldSetup(total, dec, inc, np.eye(2), offsets_m=offsets)
    else:
        setup = labfield.FieldSetup(total, 0.0, 0.0, np.zeros((2, 0)), base_ned_nT=given[rows], offsets_m=offsets)
    state = _FieldState(setup, total_given, given_start=fitted and np.all(np.isfinite(given[rows[0]])))
    for rnd in range(labfield.MAX_ROUNDS):
        result = fit_vector(dataset, _field_reference(dataset, state.setup, rows), mask=usable, warn=False, **options)
        problems, xs, sigmas = _problems_of(result, dataset, rows, state.setup)
        if rnd == 0 and fitted:
            state.gauge(problems, xs, sigmas, rotation[rows])
        moved = state.solve(problems, xs, sigmas, rotation[rows], options.get("robust", False))
        if moved < 0.01:
            break
    result = fit_vector(dataset, _field_reference(dataset, state.setup, rows), mask=usable, warn=False, **options)
    lab = state.lab_field(origin)
    lab.determined = _field_determined(result, lab, state)
    result.field = lab
    result.reference = VectorReference(
        _field_reference(dataset, state.setup, rows).ned_nT, lab.text(), "lab" if fitted else reference.kind
    )
    result.warnings = list(dict.fromkeys(state.notes + result.warnings))
    result.calibration.summary = {"vector_fit": result.to_dict(), "lab_field": lab.to_dict()}
    return result


def _field_determined(result, lab, state) -> bool:
    """Whether the record determines the field: every sensor's fit determined, the direction's standard deviations
    within :data:`labfield.UNDETERMINED_DIRECTION_DEG`, ``|B|`` within the Earth's range; a note otherwise."""
    lo, hi = PLAUSIBLE_TOTAL_nT
    why = []
    if not all(s.determined for s in result.sensors):
        why.append("the calibration itself is not determined (see its note)")
    worst = max(lab.declination_sd_deg, lab.inclination_sd_deg)
    if worst > labfield.UNDETERMINED_DIRECTION_DEG:
        why.append(f"the field's direction has a standard deviation of {worst:.1f} deg")
    if state.setup.base_ned_nT is None and not lo <= lab.total_nT <= hi:
        why.append(f"|B| came out {lab.total_nT:.0f} nT, outside the Earth's {lo:.0f}-{hi:.0f} nT")
    if why:
        state.notes.append(
            "this record does not determine the lab's field: " + "; ".join(why) + ". Do not take it as the lab's "
            "reference: turn the sensor through every direction (+-90 deg about two axes and full turns) in one place"
        )
    return not why


def _field_total(dataset, reference_total_nT, rows) -> tuple[float, bool]:
    """``(|B_w|, given)``: the total field given (the argument, the ``ref_total`` column's median, the file's
    ``reference_total_nT``), else ``(nan, False)``."""
    for value in (reference_total_nT, dataset.ref_total_nT, dataset.reference_total_nT):
        if value is not None:
            v = np.atleast_1d(np.asarray(value, dtype=float))
            v = v[rows] if v.size == dataset.n_samples else v
            if np.all(np.isfinite(v)):
                return float(np.median(v)), True
    return float("nan"), False


def _field_start(y, rotation) -> np.ndarray:
    """A start for the field's direction: of :data:`FIELD_START_DIRECTIONS` directions, the one whose linear fit
    ``y = A Q^T d + b`` (a proper ``A``: no mirrored axis) leaves the least residual on up to
    :data:`FIELD_START_SAMPLES` samples."""
    pick = np.unique(np.linspace(0, len(y) - 1, min(len(y), FIELD_START_SAMPLES)).astype(int))
    y, rotation = y[pick], rotation[pick]
    k = np.arange(FIELD_START_DIRECTIONS) + 0.5
    z = 1.0 - 2.0 * k / FIELD_START_DIRECTIONS
    phi = np.pi * (1.0 + 5**0.5) * k
    dirs = np.column_stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z])
    inv = rotation.inv()
    best, best_rms = dirs[0], np.inf
    for d in dirs:
        design = np.column_stack([inv.apply(np.tile(d, (len(y), 1))), np.ones(len(y))])
        coef, *_ = np.linalg.lstsq(design, y, rcond=None)  # y_j = a_j . B_body + b_j, every axis j at once
        rms = float(np.sqrt(np.mean((y - design @ coef) ** 2)))
        if np.linalg.det(coef[:3].T) > 0 and rms < best_rms:
            best, best_rms = d, rms
    return best


def _field_reference(dataset, setup, rows) -> VectorReference:
    """The field so far at every sample (NaN where it is not fitted) as a given reference."""
    ned = np.full((dataset.n_samples, 3), np.nan)
    params = np.zeros(setup.n_params)
    ned[rows] = np.broadcast_to(setup.field_at(params), (len(rows), 3))
    if setup.offsets_m is None and setup.base_ned_nT is None:
        ned[:] = setup.field_at(params)  # a uniform field: every sample's
    return VectorReference(ned, "the field fitted so far", "lab")


def _problems_of(result, dataset, rows, setup):
    """Every sensor's weighted problem at the vector fit ``result`` (its parameters ``x`` and noises)."""
    rotation, _ = _attitude_of(dataset)
    world = np.broadcast_to(setup.field_at(np.zeros(setup.n_params)), (len(rows), 3))
    b_body = body_reference_nT(rotation[rows], world)
    f_ref = np.linalg.norm(world, axis=1)
    model = result.calibration.model
    ctxs = contexts(dataset)
    problems, xs, sigmas = [], [], []
    for s, fit in enumerate(result.sensors):
        instances = _instances_of(model, s) if model is not None else []
        basis = _raw_bases(instances, dataset, ctxs[s], fit.bias_nT, rows)
        problems.append(_SensorProblem(dataset.readings_nT[s][rows], b_body, f_ref, basis))
        theta = [np.asarray(result.calibration.effect_values[label], dtype=float) for _, label in instances]
        xs.append(np.concatenate([fit.W.ravel(), fit.bias_nT] + theta))
        sigmas.append((fit.sigma_total_field_nT, fit.sigma_perpendicular_nT))
    return problems, xs, sigmas


class _FieldState:
    """The field between the rounds of :func:`_fit_with_field`: its setup, covariance and gauge notes."""

    def __init__(self, setup, total_given, given_start):
        self.setup, self.total_given, self.given_start = setup, total_given, given_start
        self.cov_field = np.zeros((setup.n_params, setup.n_params))
        self.var_log_gain = 0.0
        self.notes: list[str] = []
        self.gauges: list[str] = []
        self.declination_fixed = False
        if not total_given:
            self.gauges.append(
                "|B| cannot be told from the sensor's overall gain by attitudes alone: it rests on det C^-1 = 1 for "
                "sensor 1 (the sensor's nominal gain, as a total-field fit without a reference), so a gain error of "
                "1 % moves it by 1 %; a total field given (a ref_total column, the file's reference_total_nT) fixes it"
            )

    def gauge(self, problems, xs, sigmas, rotation):
        """Which directions of the field the attitudes determine: a record whose turns moved the vertical by less
        than :data:`labfield.YAW_ONLY_TILT_DEG` turned about the vertical only (its declination is the
        mounting's yaw; :func:`labfield.turn_span_deg`); otherwise the Fisher information's weak directions with the calibration profiled out. A weak one is fixed
        and named."""
        _, tilt = labfield.turn_span_deg(rotation)
        if tilt < labfield.YAW_ONLY_TILT_DEG:
            self._fix_declination(tilt)
            return
        setup = self.setup
        inc = np.radians(setup.inclination_deg)
        probe = labfield.FieldSetup(
            setup.total_nT,
            setup.declination_deg,
            setup.inclination_deg,
            np.diag([1.0 / max(np.cos(inc), 1e-6), 1.0]),
            offsets_m=setup.offsets_m,
        )
        prob = labfield.FieldProblem(problems, [len(x) for x in xs], sigmas, rotation, probe)
        jac = prob.jacobian(np.concatenate(list(xs) + [np.zeros(probe.n_params)]))
        first = sum(len(x) for x in xs)
        sd, vecs = labfield.weak_directions(jac, [first, first + 1])
        weak = sd > labfield.UNDETERMINED_DIRECTION_DEG
        if not weak.any():
            return
        if weak.all():
            setup.free = np.zeros((2, 0))
            self._note(
                f"the record's attitudes do not determine the field's direction (standard deviations "
                f"{sd[0]:.1f} and {sd[1]:.1f} deg): it is kept at the "
                + ("vector given" if self.given_start else "start found from the readings")
                + "; turn the sensor about several axes"
            )
            return
        if abs(vecs[0, int(np.argmax(sd))]) > 0.9:  # the weak direction is a rotation about the vertical
            self._fix_declination(tilt)
            return
        setup.free = probe.free @ vecs[:, int(np.argmin(sd))][:, None]
        self._note(
            "the record turned about one axis only: its attitudes cannot tell the field's rotation about that axis "
            f"from the mounting (standard deviation {float(np.max(sd)):.1f} deg); that part of the field's direction "
            "is kept at its start and the mounting takes the rest; turn the sensor about several axes"
        )

    def _fix_declination(self, tilt):
        """The declination as a gauge: kept at the one given, else 0, and said."""
        setup = self.setup
        self.declination_fixed = True
        dec = setup.declination_deg if self.given_start else 0.0
        setup.declination_deg, setup.free = dec, np.array([[0.0], [1.0]])
        self._note(
            f"the record turned about the vertical only (its turns moved the vertical by {tilt:.1f} deg at most): its "
            "attitudes cannot tell "
            "the field's declination from the mounting's yaw (a rotation of the one is absorbed by the other); "
            f"the declination is fixed at {dec:.2f} deg "
            + ("(the one given)" if self.given_start else "(world north is then the field's horizontal direction)")
            + " and the mounting's yaw takes the rest; with so little tilt the inclination and |B| also rest on the "
            "vertical axis's scale and bias, which the record barely separates: tilt the sensor (+-30 deg about two "
            "axes) to fit them"
        )

    def _note(self, text):
        self.gauges.append(text)
        self.notes.append(text)

    def solve(self, problems, xs, sigmas, rotation, robust) -> float:
        """One joint solve; moves the setup to the field found and returns how far its direction moved (deg)."""
        setup = self.setup
        x, cov, _, _, _ = labfield.solve(problems, xs, sigmas, rotation, setup, robust=robust)
        k = setup.n_direction
        params = x[-setup.n_params :] if setup.n_params else np.zeros(0)
        before = setup.field_at(np.zeros(setup.n_params))
        step = np.degrees(setup.free @ params[:k]) if k else np.zeros(2)
        setup.declination_deg += float(step[0])
        setup.inclination_deg += float(step[1])
        if setup.offsets_m is not None:
            setup.gradient0 = setup.gradient0 + params[k:]
        if cov is not None:
            self.cov_field = cov[-setup.n_params :, -setup.n_params :] if setup.n_params else self.cov_field
            if not self.total_given and setup.base_ned_nT is None:
                g = np.linalg.inv(x[:9].reshape(3, 3)).T.ravel()  # d ln det W / dW
                self.var_log_gain = float(g @ cov[:9, :9] @ g) / 9.0
        if not self.total_given and setup.base_ned_nT is None:
            gain = float(np.linalg.det(x[:9].reshape(3, 3))) ** (-1.0 / 3.0)  # det C^-1 = 1 for sensor 1
            setup.total_nT *= gain
            setup.gradient0 = setup.gradient0 * gain
        after = setup.field_at(np.zeros(setup.n_params))
        a, b = np.atleast_2d(before)[0], np.atleast_2d(after)[0]
        return float(np.degrees(np.arccos(np.clip(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)), -1.0, 1.0))))

    def lab_field(self, origin) -> labfield.LabField:
        """The field found, with its standard deviations and gauges."""
        setup = self.setup
        k = setup.n_direction
        ned = np.atleast_2d(setup.field_at(np.zeros(setup.n_params)))
        ned = (
            ned.mean(axis=0)
            if setup.offsets_m is None
            else ned.mean(axis=0)
            - setup.offsets_m.mean(axis=0) @ (np.tensordot(setup.gradient0, GRADIENT_BASIS, axes=1).T)
        )
        total = float(np.linalg.norm(ned))
        unit = ned / total
        cov_dir = setup.free @ self.cov_field[:k, :k] @ setup.free.T if k else np.zeros((2, 2))
        jac = total * labfield._direction_derivatives(setup.declination_deg, setup.inclination_deg)
        total_sd = total * np.sqrt(self.var_log_gain) if not self.total_given else 0.0
        cov_ned = jac @ cov_dir @ jac.T + np.outer(unit, unit) * total_sd**2
        dec, inc = labfield.angles_deg(ned)
        grad = grad_sd = None
        if setup.offsets_m is not None:
            grad = np.tensordot(setup.gradient0, GRADIENT_BASIS, axes=1)
            grad_sd = np.sqrt(np.clip(np.diag(self.cov_field)[k:], 0.0, None))
        return labfield.LabField(
            ned_nT=ned,
            sd_nT=np.sqrt(np.clip(np.diag(cov_ned), 0.0, None)),
            declination_deg=dec,
            inclination_deg=inc,
            declination_sd_deg=0.0 if self.declination_fixed else float(np.degrees(np.sqrt(max(cov_dir[0, 0], 0)))),
            inclination_sd_deg=float(np.degrees(np.sqrt(max(cov_dir[1, 1], 0.0)))),
            total_nT=total,
            total_sd_nT=float(total_sd),
            total_source="given" if self.total_given else "gain",
            gauges=list(self.gauges),
            declination_fixed=self.declination_fixed,
            gradient_nT_per_m=grad,
            gradient_sd_nT_per_m=grad_sd,
            origin_m=origin,
        )
