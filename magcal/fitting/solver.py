"""The solver core the fits share: residual groups weighted by their noises, the re-weighting rounds, the covariance
widened for residuals correlated in time, and the outliers.

A fit of several kinds of residual (the total field in nT, a vector's components across the field in nT, a dip in
rad, an accelerometer's magnitude in m/s^2) weighs each kind by its own noise: a :class:`NoiseGroup` is one kind,
its noise given or estimated from the residuals (a normal-consistent median absolute deviation, at least the group's
floor). :func:`reweighted_fit` solves with the noises so far, re-estimates them from the residuals of the solution
and solves again until they settle (each within :data:`SETTLED` of the last) or the rounds run out: the maximum
likelihood of the noises and the parameters together, one block at a time.

:func:`correlated_covariance` is ``s^2 (J^T J)^-1`` of the weighted residuals, ``s^2`` their variance per degree of
freedom, widened by ``sqrt((1 + r) / (1 - r))`` for the lag-1 correlation ``r`` of the residuals in record order
(the variance of the mean of a first-order autoregressive sequence: an attitude or a hand that wanders makes
neighbouring samples alike, and the record then holds fewer independent samples). :func:`beyond` marks the samples
whose residual lies beyond :data:`OUTLIER_SIGMAS` standard deviations.

:func:`weighted_least_squares` is the one call of :func:`scipy.optimize.least_squares` with the options these fits
share: Levenberg-Marquardt, or with ``robust`` the soft-L1 loss (residuals beyond :data:`ROBUST_SCALE` standard
deviations count less) in a trust region. :class:`SensorMounting` is the part of a sensor's result that says how
it is mounted (its matrix ``W = R C^-1`` split, the right angle chosen first), shared by the vector and the gravity
fit.

Used by :mod:`magcal.fitting.fitter` (its robust scale and outliers, its covariance), :mod:`magcal.fitting.vector`,
:mod:`magcal.fitting.gravity` and :mod:`magcal.fitting.labfield`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from magcal.core.errors import CalibrationError
from magcal.core.stats import lag1_correlation, robust_sigma
from magcal.geometry.orientations import describe_right_angle, firmware_rotation, nearest_right_angle, split_mounting

#: A residual beyond this many of its standard deviations is an outlier.
OUTLIER_SIGMAS = 5.0

#: The noises have settled when each moved by less than this fraction of itself in a round.
SETTLED = 0.05

#: Where the robust (soft-L1) loss starts to count a weighted residual less: this many standard deviations.
ROBUST_SCALE = 3.0


@dataclass(frozen=True)
class NoiseGroup:
    """One kind of residual and its noise (1 sigma, in the residual's unit).

    Attributes
    ----------
    floor : float
        Smallest estimate (a record of identical samples has a median absolute deviation of zero).
    given : float or None
        The noise given; None: estimated from the residuals.
    """

    floor: float
    given: float | None = None

    def sigma(self, residuals, current=None):
        """The given noise, else the robust sigma of ``residuals`` (at least :attr:`floor`); ``current`` when the
        residuals are None (a part not fitted this time)."""
        if self.given is not None:
            return self.given
        if residuals is None:
            return current
        return max(robust_sigma(residuals), self.floor)


def estimate_sigmas(groups: Sequence[NoiseGroup], parts, current=None) -> list:
    """Each group's noise from its residuals ``parts`` (one array, or None, per group)."""
    current = [None] * len(groups) if current is None else current
    return [g.sigma(r, c) for g, r, c in zip(groups, parts, current)]


@dataclass
class Reweighted:
    """Outcome of :func:`reweighted_fit`: the parameters, the last solver's solution, the noises, the rounds run."""

    x: np.ndarray
    solution: Any
    sigmas: list
    rounds: int


def reweighted_fit(
    solve: Callable,
    parts: Callable,
    groups: Sequence[NoiseGroup],
    x,
    sigmas=None,
    rounds: int = 3,
    most_rounds: int | None = None,
    again: Callable | None = None,
    tolerance: float = SETTLED,
) -> Reweighted:
    """Solve, re-estimate the noises from the residuals, and solve again until they settle.

    Parameters
    ----------
    solve : callable
        ``solve(x, sigmas) -> (x, solution)``: the weighted fit from ``x`` with the noises ``sigmas``.
    parts : callable
        ``parts(x) -> sequence``: each group's unweighted residuals at ``x`` (None keeps that group's noise).
    groups : sequence of NoiseGroup
    x : numpy.ndarray
        The start.
    sigmas : sequence of float, optional
        The noises of the first solve; default estimated from the residuals at ``x``.
    rounds : int
        Solves in all after which the loop stops once ``again`` no longer asks for another (noises settled within
        ``tolerance`` stop it sooner).
    most_rounds : int, optional
        Most solves in all, ``again`` included; default ``rounds``.
    again : callable, optional
        ``again(round, x) -> bool``, after each solve and the noises' update: True asks for one more solve whatever
        the noises did (a model whose data-derived constants moved).
    tolerance : float
        The noises have settled when each moved by less than this fraction (0: every round is run).
    """
    sigmas = estimate_sigmas(groups, parts(x)) if sigmas is None else list(sigmas)
    most = rounds if most_rounds is None else most_rounds
    solution, done = None, 0
    for done in range(1, most + 1):
        x, solution = solve(x, sigmas)
        new = estimate_sigmas(groups, parts(x), sigmas)
        settled = all(abs(a / b - 1.0) < tolerance for a, b in zip(new, sigmas))
        sigmas = new
        if again is not None and again(done - 1, x):
            continue
        if settled or done >= rounds:
            break
    return Reweighted(x, solution, sigmas, done)


def weighted_least_squares(fun, x0, x_scale, robust=False, jac="2-point", max_nfev=None, args=()):
    """:func:`scipy.optimize.least_squares` of weighted residuals ``fun(x, *args)`` with the options the fits share:
    LM, or with ``robust`` the soft-L1 loss at :data:`ROBUST_SCALE` in a trust region; tolerances 1e-12."""
    return least_squares(
        fun,
        x0,
        jac=jac,
        args=args,
        method="trf" if robust else "lm",
        loss="soft_l1" if robust else "linear",
        f_scale=ROBUST_SCALE,
        x_scale=x_scale,
        xtol=1e-12,
        ftol=1e-12,
        max_nfev=max_nfev,
    )


@dataclass
class Covariance:
    """The parameters' covariance of a weighted fit (:func:`correlated_covariance`).

    Attributes
    ----------
    matrix : numpy.ndarray or None
        ``s^2 (J^T J)^-1 w^2`` in the parameters' units; None when ``J^T J`` is singular.
    jtj_inv : numpy.ndarray or None
        ``(J^T J)^-1`` of the weighted residuals.
    s2 : float
        Variance per weighted residual (sum of squares over the degrees of freedom).
    lag1 : float
        Lag-1 correlation of the residuals in record order (:func:`magcal.core.stats.lag1_correlation`).
    widening : float
        ``w = sqrt((1 + lag1) / (1 - lag1))``, at most ``sqrt(most)``: the standard deviations' factor.
    """

    matrix: np.ndarray | None
    jtj_inv: np.ndarray | None
    s2: float
    lag1: float
    widening: float


def correlated_covariance(jac, z, n_params: int, streams, most: int) -> Covariance:
    """The covariance of a weighted least-squares fit, widened for residuals correlated in time.

    Parameters
    ----------
    jac : numpy.ndarray, shape (m, n_params)
        The Jacobian of the weighted residuals at the solution.
    z : numpy.ndarray, shape (m,)
        The weighted residuals at the solution.
    n_params : int
    streams : sequence of array_like
        Residual sequences in record order whose largest lag-1 correlation widens the covariance.
    most : int
        The widening's square is at most this (the samples: a record holds at least one independent sample).
    """
    lag1 = lag1_correlation(*streams)
    widening = float(np.sqrt(min((1.0 + lag1) / (1.0 - lag1), most)))
    s2 = float(z @ z) / max(len(z) - n_params, 1)
    try:
        jtj_inv = np.linalg.inv(jac.T @ jac)
    except np.linalg.LinAlgError:
        return Covariance(None, None, s2, lag1, widening)
    return Covariance(s2 * jtj_inv * widening**2, jtj_inv, s2, lag1, widening)


def normal_covariance(jtj, s2: float) -> np.ndarray | None:
    """``s^2 (J^T J)^+`` from the normal equations (a pseudo-inverse: a direction the data do not fix gets no
    variance instead of an overflow); None when it cannot be computed."""
    try:
        return s2 * np.linalg.pinv(jtj)
    except np.linalg.LinAlgError:
        return None


def beyond(residuals, sigma, axis: int | None = 1) -> np.ndarray:
    """Samples whose residual (any component along ``axis``; None: one value per sample) lies beyond
    :data:`OUTLIER_SIGMAS` standard deviations ``sigma`` (the residual's unit)."""
    far = np.abs(np.asarray(residuals, dtype=float)) > OUTLIER_SIGMAS * sigma
    return far if axis is None or far.ndim == 1 else np.any(far, axis=axis)


def split_fitted(W, sensor: int):
    """``(R, C^-1)``: a fitted ``W = R C^-1`` split (:func:`magcal.geometry.orientations.split_mounting`).

    Raises
    ------
    CalibrationError
        A matrix that mirrors an axis (negative determinant): one axis's sign is reversed against the others.
    """
    try:
        return split_mounting(W)
    except ValueError:
        raise CalibrationError(
            f"sensor {sensor + 1}: the fitted matrix mirrors an axis (its determinant is negative): one of the "
            "sensor's axes has the opposite sign to the others (a left-handed sensor); negate that column (e.g. "
            "with --columns) and calibrate again"
        ) from None


@dataclass
class SensorMounting:
    """How a sensor is mounted, as a fit found it: the part the vector and the gravity fit share.

    Attributes
    ----------
    W : numpy.ndarray, shape (3, 3)
        ``R C^-1``: raw reading minus bias (and platform terms) -> the fit's frame (the body, the accelerometer).
    bias_nT : numpy.ndarray, shape (3,)
        Bias (hard iron), nT.
    mounting : numpy.ndarray, shape (3, 3)
        ``R``, the rotation of the sensor's corrected axes into the fit's frame.
    cinv : numpy.ndarray, shape (3, 3)
        Upper-triangular ``C^-1``.
    right_angle : numpy.ndarray, shape (3, 3)
        The best of the 24 right-angle orientations (tried first).
    right_angle_text : str
        Its firmware name and axis mapping.
    angle_off_deg : float
        Angle between the fitted mounting and a right angle, deg.
    orientation_margin : float
        The second-best right angle's misfit over the best one's (large: the choice was clear).
    """

    W: np.ndarray
    bias_nT: np.ndarray
    mounting: np.ndarray
    cinv: np.ndarray
    right_angle: np.ndarray
    right_angle_text: str
    angle_off_deg: float
    orientation_margin: float

    #: The attributes a sensor's :meth:`summary` holds after the mounting's figures, in order.
    SUMMARY_FIELDS: ClassVar[tuple[str, ...]] = ()

    def summary(self) -> dict:
        """JSON-ready figures for the calibration file's sensor entry: the mounting's, then :attr:`SUMMARY_FIELDS`
        (arrays as lists, a cause as its dictionary)."""
        out = {
            "mounting_right_angle": self.right_angle_text,
            "mounting_rotation_number": firmware_rotation(self.right_angle),
            "mounting_angle_off_deg": self.angle_off_deg,
            "mounting_rotvec_deg": np.degrees(Rotation.from_matrix(self.mounting).as_rotvec()).tolist(),
            "orientation_margin": self.orientation_margin,
        }
        for name in self.SUMMARY_FIELDS:
            value = getattr(self, name)
            if isinstance(value, np.ndarray):
                value = value.tolist()
            elif hasattr(value, "to_dict"):
                value = value.to_dict()
            out[name] = value
        return out


def mounting_fields(W, bias_nT, right_angle, margin: float, sensor: int, frame="body", off_nearest=True) -> dict:
    """The :class:`SensorMounting` fields of a fitted ``W`` and bias (keywords for a sensor's result).

    Parameters
    ----------
    W : numpy.ndarray, shape (3, 3)
    bias_nT : numpy.ndarray, shape (3,)
    right_angle : numpy.ndarray, shape (3, 3)
        The right angle chosen first; ``margin`` its margin.
    sensor : int
        0-based, for the message of a mirrored matrix (:func:`split_fitted`).
    frame : str
        The name of the fit's frame in the right angle's text (``body``, ``board``).
    off_nearest : bool
        ``angle_off_deg`` from the right angle nearest the fitted mounting (True) or from ``right_angle``.
    """
    R, cinv = split_fitted(W, sensor)
    if off_nearest:
        _, off = nearest_right_angle(R)
    else:
        off = float(np.degrees(Rotation.from_matrix(np.asarray(right_angle).T @ R).magnitude()))
    return {
        "W": W,
        "bias_nT": bias_nT,
        "mounting": R,
        "cinv": cinv,
        "right_angle": right_angle,
        "right_angle_text": describe_right_angle(right_angle).replace("-> body", f"-> {frame}"),
        "angle_off_deg": off,
        "orientation_margin": margin,
    }
