"""Gravity calibration: a magnetometer beside an accelerometer, calibrated together and judged by heading.

Most magnetometers sit on a board beside an accelerometer, and their users want one figure: the tilt-compensated
heading (:mod:`magcal.geometry.heading`). It needs more than the magnetometer's ellipsoid: the magnetometer's axes
must agree with the accelerometer's, or the tilt compensation turns the vertical field into the horizontal one (a
tilt error ``e`` becomes ``e tan(I)`` of heading). A total-field fit cannot see that rotation (it is invisible in
``|B|``) and a vector fit needs a yaw the board does not have. What sees it is the **dip**: the angle between the
field and gravity is the inclination ``I`` in every attitude. So, per magnetometer ``s`` and still sample ``i``::

    m_i = W_s (y_i - b_s)                 the field in the accelerometer's frame (W = R C^-1: mounting and matrix)
    f_i = K^-1 (a_i - b_a)                the specific force (up), the accelerometer's own correction
    |m_i| - F                             total-field residual, every sample, weight 1 / sigma_F
    |f_i| - g                             the accelerometer's magnitude residual, still samples, weight 1 / sigma_a
    asin(m_i . d_i / |m_i|) - I,  d_i = -f_i / |f_i|     the dip residual, still samples, weight 1 / sigma_D

and :func:`scipy.optimize.least_squares` finds ``W_s``, ``b_s`` (twelve numbers per magnetometer: no gauge is
left, the mounting is fixed by the dip), ``K^-1`` (upper triangular: the accelerometer's own axes are the board's)
and ``b_a`` (the six-position or tumbled accelerometer fit, inside the joint one) and, unless it is given (a number,
or IGRF at a location), the inclination ``I``. Each residual is weighted by its own noise (given, or estimated from
the residuals: a first fit, then a refit with the estimates): the magnetometer's noise along the field, the
accelerometer's along gravity, and across them the dip's (both sensors' noise across, and the hand's acceleration
on samples that were not quite still). ``F`` is the reference total field, or the magnitude the ellipsoid implies
(``det C^-1 = 1``): it only scales ``W``. A rotation about gravity is the one thing left unseen (a heading offset:
the declination, or a board mounted turned in its vehicle); it is the world's, not the board's.

Start: each sensor's ellipsoid (:func:`magcal.geometry.ellipsoid.fit_ellipsoid`), the accelerometer's on the still
samples; the 24 right angles between the two sensors' axes tried by the spread of the dip they give (boards often
carry parts whose axes differ), the best refined as a small rotation by linear least squares, then the joint
maximum likelihood.

The figure of merit is the heading. :func:`validate_gravity` fits on alternate blocks in time and scores the others:
the dip's spread, ``|B|`` and, beside it, the **separate** calibrations a user gets without the dip (the
magnetometer's total-field fit and the accelerometer's own fit, the right angle between them taken as known): the
heading difference between the two is the heading error the separate fit leaves. :func:`heading_budget` says what a
heading of 0.5 deg needs: the sensors' noise per sample, the calibration's own error (its covariance carried to the
heading), and how many still samples and which tilts would bring it there.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.linalg
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from magcal.calibration.accelerometer import AccelerometerCalibration
from magcal.calibration.calibration import Calibration, SensorCalibration
from magcal.core.errors import CalibrationError, DataWarning, MagcalError
from magcal.core.notes import Note
from magcal.data.accelerometer import (
    MIN_STILL,
    STANDARD_GRAVITY_M_S2,
    Accelerometer,
    StillSamples,
    accelerometer,
    direction_spread,
    find_still,
)
from magcal.data.dataset import Dataset
from magcal.fitting.pipeline import calibrate
from magcal.fitting.result import SampleFitResult
from magcal.fitting.solver import (
    Covariance,
    NoiseGroup,
    Reweighted,
    SensorMounting,
    correlated_covariance,
    estimate_sigmas,
    mounting_fields,
    reweighted_fit,
    weighted_least_squares,
)
from magcal.fitting.truth import true_calibration as true_calibration
from magcal.fitting.validation import BlockValidation, held_out_blocks
from magcal.geometry.ellipsoid import WEAK_DIRECTION_SPREAD, fit_ellipsoid
from magcal.geometry.heading import (
    angle_difference_deg,
    heading_noise_deg,
    tilt_deg,
    tilt_heading_deg,
)
from magcal.geometry.orientations import RIGHT_ANGLES, mounting_sd_deg
from magcal.geometry.sphere import sphere_centre

#: The heading a cave-survey instrument reaches (deg): what the report says is needed for.
HEADING_GOAL_DEG = 0.5

#: Headings are scored where the board's x axis is within this many degrees of the horizontal (at 90 deg the
#: heading of the x axis is not defined).
HEADING_MAX_PITCH_DEG = 60.0

#: The accelerometer is fitted (``accel_fit="auto"``) when its still samples' directions spread this much: the
#: smallest eigenvalue of their mean outer product (1/3 for directions over the whole sphere, 0 in a plane or at
#: one attitude).
ACCEL_SPREAD_MIN = 0.12

#: A mounting whose standard deviation exceeds this (deg), or a heading whose calibration error does (deg), is not
#: determined by the record.
UNDETERMINED_MOUNTING_DEG = 1.0
UNDETERMINED_HEADING_DEG = 2.0

#: Samples the heading's standard deviation is carried to (a sample of the still ones).
HEADING_SD_SAMPLES = 300

_UPPER = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _upper(values) -> np.ndarray:
    m = np.zeros((3, 3))
    for (i, j), v in zip(_UPPER, values):
        m[i, j] = v
    return m


# --- the accelerometer alone (the six-position or tumbled fit) --------------------------------------------------
@dataclass
class AccelFit:
    """The accelerometer's correction ``f = K^-1 (a - b_a)`` and how well ``|f| = g`` holds.

    Attributes
    ----------
    kinv : numpy.ndarray, shape (3, 3)
        Upper triangular.
    bias_m_s2 : numpy.ndarray, shape (3,)
    rms_m_s2 : float
        RMS of ``|f| - g`` over the still samples.
    sigma_m_s2 : float
        The noise weighting that residual (given or estimated).
    fitted : bool
        False when the still samples' directions do not determine it (then ``K^-1 = I``, ``b_a = 0``).
    spread : float
        :func:`direction_spread` of the still samples.
    bias_sd_m_s2 : numpy.ndarray or None
    """

    kinv: np.ndarray
    bias_m_s2: np.ndarray
    rms_m_s2: float
    sigma_m_s2: float
    fitted: bool
    spread: float
    bias_sd_m_s2: np.ndarray | None = None

    def correct(self, a) -> np.ndarray:
        return (np.asarray(a, float) - self.bias_m_s2) @ self.kinv.T

    def calibration(self) -> AccelerometerCalibration:
        summary = {
            "rms_m_s2": self.rms_m_s2,
            "sigma_m_s2": self.sigma_m_s2,
            "direction_spread": self.spread,
            "bias_sd_m_s2": None if self.bias_sd_m_s2 is None else np.asarray(self.bias_sd_m_s2).tolist(),
        }
        return AccelerometerCalibration(self.kinv, self.bias_m_s2, STANDARD_GRAVITY_M_S2, self.fitted, summary)


def fit_accelerometer(accel_m_s2, gravity_m_s2=STANDARD_GRAVITY_M_S2, fit="auto", noise_m_s2=None) -> AccelFit:
    """The accelerometer's own calibration from still samples: ``|K^-1 (a - b_a)| = g`` by maximum likelihood,
    started from the ellipsoid (the six-position or tumbled accelerometer fit).

    Parameters
    ----------
    accel_m_s2 : array_like, shape (N, 3)
        Still samples (m/s^2).
    gravity_m_s2 : float
    fit : {"auto", "full", "none"}
        ``auto``: fit when the directions spread (:data:`ACCEL_SPREAD_MIN`), else take the readings as they are;
        ``none``: take them as they are (a firmware's calibration).
    noise_m_s2 : float, optional
        The noise per axis; default estimated from the residuals.
    """
    a = np.asarray(accel_m_s2, dtype=float)
    spread = direction_spread(a)
    if fit == "none" or (fit == "auto" and spread < ACCEL_SPREAD_MIN) or len(a) < 12:
        left = np.linalg.norm(a, axis=1) - gravity_m_s2
        sigma = NoiseGroup(1e-5, noise_m_s2).sigma(left)
        return AccelFit(np.eye(3), np.zeros(3), float(np.sqrt(np.mean(left**2))), float(sigma), False, spread)
    try:
        start = fit_ellipsoid(a, reference_total_nT=gravity_m_s2, strict=False, label="accelerometer")
        k0, b0 = start.cinv, start.bias_nT
    except CalibrationError:
        k0, b0 = np.eye(3), np.zeros(3)
    x0 = np.concatenate([[k0[i, j] for i, j in _UPPER], b0])

    def resid(x):
        return np.linalg.norm((a - x[6:]) @ _upper(x[:6]).T, axis=1) - gravity_m_s2

    sol = least_squares(resid, x0, method="lm", x_scale=np.r_[np.full(6, 1e-3), np.full(3, 1e-2)])
    r = resid(sol.x)
    sigma = NoiseGroup(1e-5, noise_m_s2).sigma(r)
    cov = correlated_covariance(sol.jac, r, 9, (), len(r)).matrix  # white residuals: no stream widens it
    bias_sd = None if cov is None else np.sqrt(np.clip(np.diag(cov)[6:], 0.0, None))
    return AccelFit(
        _upper(sol.x[:6]), sol.x[6:].copy(), float(np.sqrt(np.mean(r**2))), float(sigma), True, spread, bias_sd
    )


# --- the dip's start: the right angle between the sensors, then a small rotation ------------------------------
def dip_start(m_dirs, down, inclination_rad=None):
    """The rotation ``R`` that makes the dip constant, from the magnetometer's field directions (its own frame) and
    the accelerometer's down at still samples.

    The 24 right angles are tried first (the one whose dip ``asin(d . A m)`` spreads least), then refined by a small
    rotation ``R = exp(w) A`` from the linear equations ``d . (u + w x u) = sin I`` (``u = A m``; ``sin I`` fitted
    unless given).

    Returns
    -------
    right_angle, rotation : numpy.ndarray, shape (3, 3)
    inclination_rad : float
    margin : float
        The second-best right angle's spread over the best one's.
    """
    spreads = np.array([np.std(np.sum(down * (m_dirs @ a.T), axis=1)) for a in RIGHT_ANGLES])
    order = np.argsort(spreads)
    best = RIGHT_ANGLES[order[0]]
    margin = float(spreads[order[1]] / max(spreads[order[0]], 1e-12))
    rot = best.copy()
    s = np.sin(inclination_rad) if inclination_rad is not None else float(np.mean(np.sum(down * (m_dirs @ rot.T), 1)))
    for _ in range(6):
        u = m_dirs @ rot.T
        lhs = np.cross(u, down)
        rhs = -np.sum(down * u, axis=1)
        if inclination_rad is None:
            sol = np.linalg.lstsq(np.column_stack([lhs, -np.ones(len(u))]), rhs, rcond=None)[0]
            w, s = sol[:3], float(sol[3])
        else:
            w = np.linalg.lstsq(lhs, rhs + s, rcond=None)[0]
        rot = Rotation.from_rotvec(w).as_matrix() @ rot
        if np.linalg.norm(w) < 1e-10:
            break
    return best, rot, float(np.arcsin(np.clip(s, -1.0, 1.0))), margin


# --- the joint fit ----------------------------------------------------------------------------------------------
class _Problem:
    """The weighted residuals of the joint fit (see the module docstring).

    Per magnetometer either the full model (``W`` and ``b``: twelve parameters) or, where the readings do not
    determine an ellipsoid (``fixed[s] = (W0, b0)``), its rotation only: ``W = exp([w]) W0`` (three parameters).
    """

    def __init__(self, ys, a_still, still_rows, fields, gravity, fit_accel, accel_fixed, inclination_rad, fixed):
        self.ys, self.a, self.rows = ys, a_still, still_rows
        self.fields, self.g = fields, gravity
        self.fit_accel, self.accel_fixed = fit_accel, accel_fixed
        self.inc_fixed = inclination_rad
        self.fixed = list(fixed)
        self.na = 9 if fit_accel else 0
        self.ns = len(ys)
        self.widths = [12 if f is None else 3 for f in self.fixed]
        self.offsets = list(self.na + np.concatenate([[0], np.cumsum(self.widths)[:-1]]).astype(int))

    def pack(self, kinv, ba, ws, bs, inc) -> np.ndarray:
        parts = [np.r_[[kinv[i, j] for i, j in _UPPER], ba]] if self.fit_accel else []
        for w, b, f in zip(ws, bs, self.fixed):
            parts.append(
                np.r_[w.ravel(), b] if f is None else Rotation.from_matrix(w @ np.linalg.inv(f[0])).as_rotvec()
            )
        if self.inc_fixed is None:
            parts.append([inc])
        return np.concatenate(parts)

    def unpack(self, x):
        if self.fit_accel:
            kinv, ba = _upper(x[:6]), x[6:9]
        else:
            kinv, ba = self.accel_fixed
        ws, bs = [], []
        for k, f in zip(self.offsets, self.fixed):
            if f is None:
                ws.append(x[k : k + 9].reshape(3, 3))
                bs.append(x[k + 9 : k + 12])
            else:
                ws.append(Rotation.from_rotvec(x[k : k + 3]).as_matrix() @ f[0])
                bs.append(f[1])
        inc = x[-1] if self.inc_fixed is None else self.inc_fixed
        return kinv, ba, ws, bs, inc

    def parts(self, x):
        """Unweighted residuals: accelerometer (m/s^2, still samples; None when not fitted), per sensor the total
        field (nT, every sample) and the dip (rad, still samples)."""
        kinv, ba, ws, bs, inc = self.unpack(x)
        f = (self.a - ba) @ kinv.T
        fn = np.linalg.norm(f, axis=1)
        down = -f / fn[:, None]
        r_a = fn - self.g if self.fit_accel else None
        r_f, r_d = [], []
        for y, w, b, field_nT in zip(self.ys, ws, bs, self.fields):
            m = (y - b) @ w.T
            mn = np.linalg.norm(m, axis=1)
            r_f.append(mn - field_nT)
            ms = m[self.rows] / mn[self.rows, None]
            r_d.append(np.arcsin(np.clip(np.sum(ms * down, axis=1), -1.0, 1.0)) - inc)
        return r_a, r_f, r_d

    def residuals(self, x, sigma_a, sigma_f, sigma_d):
        r_a, r_f, r_d = self.parts(x)
        out = [] if r_a is None else [r_a / sigma_a]
        for rf, rd, sf, sd, f in zip(r_f, r_d, sigma_f, sigma_d, self.fixed):
            out += [rd / sd] if f is not None else [rf / sf, rd / sd]
        return np.concatenate(out)

    def scale(self) -> np.ndarray:
        parts = [np.r_[np.full(6, 1e-3), np.full(3, 1e-2)]] if self.fit_accel else []
        parts += [np.r_[np.full(9, 1e-3), np.full(3, 10.0)] if f is None else np.full(3, 1e-3) for f in self.fixed]
        if self.inc_fixed is None:
            parts.append([1e-3])
        return np.concatenate(parts)

    def sensor_covariance(self, cov, s, x) -> np.ndarray:
        """The covariance (12 x 12) of sensor ``s``'s ``W`` (row by row) and bias from the parameters' ``cov``."""
        k = self.offsets[s]
        if self.fixed[s] is None:
            return cov[k : k + 12, k : k + 12]
        w = self.unpack(x)[2][s]
        jac = np.column_stack([(_skew(e) @ w).ravel() for e in np.eye(3)])  # d vec(exp([w]) W0) / dw at w
        out = np.zeros((12, 12))
        out[:9, :9] = jac @ cov[k : k + 3, k : k + 3] @ jac.T
        return out


def _skew(v) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


@dataclass
class SensorGravityFit(SensorMounting):
    """One magnetometer's part of the joint fit.

    Attributes
    ----------
    W, bias_nT, mounting, cinv, right_angle, right_angle_text, angle_off_deg, orientation_margin
        As :class:`magcal.fitting.solver.SensorMounting`: ``W = R C^-1`` maps the raw reading minus bias into the
        accelerometer's frame; the right angle is the one the dip chose first, ``angle_off_deg`` the mounting's
        angle off it, ``orientation_margin`` the second-best right angle's dip spread over the best's.
    field_nT : float
        The total field ``F`` the fit maps to (the reference, or the ellipsoid's magnitude).
    rms_total_field_nT, sigma_total_field_nT : float
        RMS of ``|m| - F`` and the noise weighting it.
    dip_sd_deg, sigma_dip_deg : float
        Spread of the dip residual over the still samples (deg) and the noise weighting it.
    mounting_sd_deg : numpy.ndarray, shape (3,), or None
        Standard deviations of the mounting about the board's x, y, z (deg), from the fit's covariance.
    bias_sd_nT : numpy.ndarray, shape (3,), or None
    heading_sd_deg : float or None
        The calibration's own heading error: its covariance carried to the heading of the still samples (RMS, deg).
    sd_widening : float
        The standard deviations were widened by this for residuals correlated in time.
    determined : bool
        False when the mounting's or the heading's standard deviation is beyond :data:`UNDETERMINED_MOUNTING_DEG`,
        :data:`UNDETERMINED_HEADING_DEG`, or when the accelerometer was neither fitted nor said calibrated
        (``accel_fit="none"``): its bias is then in the mounting, unseen by the covariance.
    """

    field_nT: float
    rms_total_field_nT: float
    sigma_total_field_nT: float
    dip_sd_deg: float
    sigma_dip_deg: float
    mounting_sd_deg: np.ndarray | None = None
    bias_sd_nT: np.ndarray | None = None
    heading_sd_deg: float | None = None
    sd_widening: float = 1.0
    determined: bool = True

    SUMMARY_FIELDS = (
        "rms_total_field_nT",
        "sigma_total_field_nT",
        "dip_sd_deg",
        "sigma_dip_deg",
        "mounting_sd_deg",
        "bias_sd_nT",
        "heading_sd_deg",
        "sd_widening",
        "determined",
    )


@dataclass
class GravityFitResult(SampleFitResult):
    """Outcome of :func:`fit_gravity`.

    Attributes
    ----------
    calibration : Calibration
        ``mode = "gravity"``, ``frame = "accelerometer"``: corrected vectors in the accelerometer's axes; its
        ``accelerometer`` holds the accelerometer's correction; :meth:`Calibration.heading` the compass.
    sensors : list of SensorGravityFit
    accel : AccelFit
    inclination_deg : float
        Fitted, or given (``inclination_source``); ``inclination_sd_deg`` its standard deviation when fitted.
    still : StillSamples
    tilt_range_deg : (float, float)
        The still samples' smallest and largest tilt (deg).
    budget : dict
        :func:`heading_budget`'s figures.
    warnings : list of str
    fitted : numpy.ndarray of bool, shape (N,)
        The samples in the total-field residual (the still ones are ``still.mask``).
    """

    mode = "gravity"  # the fit mode (magcal.modes) that makes it

    calibration: Calibration
    sensors: list
    accel: AccelFit
    inclination_deg: float
    inclination_source: str
    inclination_sd_deg: float | None
    still: StillSamples
    tilt_range_deg: tuple
    budget: dict
    accel_unit: str = "m/s^2"

    @property
    def notes(self) -> list[Note]:
        return [Note(w, DataWarning, "gravity fit") for w in self.warnings]

    def to_dict(self) -> dict:
        return {
            "mode": "gravity",
            "n_samples": self.n_samples,
            "n_still": self.still.n,
            "still_kind": self.still.kind,
            "inclination_deg": self.inclination_deg,
            "inclination_source": self.inclination_source,
            "inclination_sd_deg": self.inclination_sd_deg,
            "tilt_range_deg": list(self.tilt_range_deg),
            "accelerometer": {
                "fitted": self.accel.fitted,
                "rms_m_s2": self.accel.rms_m_s2,
                "sigma_m_s2": self.accel.sigma_m_s2,
                "direction_spread": self.accel.spread,
                "unit": self.accel_unit,
            },
            "sensors": [s.summary() for s in self.sensors],
            "heading_budget": dict(self.budget),
            "wall_s": self.wall_s,
        }

    def text(self) -> str:
        """The readable report."""
        lines = [
            "Gravity calibration (magnetometer beside an accelerometer, judged by the tilt-compensated heading)",
            f"  samples: {self.n_samples} in the total-field residual; {self.still.text()}",
            f"  tilt of the still samples: {self.tilt_range_deg[0]:.0f} to {self.tilt_range_deg[1]:.0f} deg",
            "  inclination: "
            + (
                f"{self.inclination_deg:.3f} +- {self.inclination_sd_deg:.3f} deg (fitted from the dip)"
                if self.inclination_sd_deg is not None
                else f"{self.inclination_deg:.3f} deg ({self.inclination_source})"
            ),
            "  accelerometer: "
            + (
                f"fitted (six-position/tumbled), |a| - g RMS {self.accel.rms_m_s2:.4f} m/s^2, bias "
                + ", ".join(f"{v:+.4f}" for v in self.accel.bias_m_s2)
                + " m/s^2, scale "
                + ", ".join(f"{v:.4f}" for v in np.diag(self.accel.kinv))
                if self.accel.fitted
                else f"taken as it reads (its still samples do not spread: {self.accel.spread:.3f}); |a| - g RMS "
                f"{self.accel.rms_m_s2:.4f} m/s^2"
            ),
        ]
        for k, s in enumerate(self.sensors):
            sd = "" if s.mounting_sd_deg is None else " +- " + "/".join(f"{v:.3f}" for v in s.mounting_sd_deg)
            lines += [
                f"  sensor {k + 1}: mounting {s.right_angle_text}, {s.angle_off_deg:.3f} deg off it (sd about x/y/z"
                f"{sd} deg)",
                f"    bias {', '.join(f'{v:.1f}' for v in s.bias_nT)} nT; |B| RMS {s.rms_total_field_nT:.2f} nT "
                f"(noise {s.sigma_total_field_nT:.2f}) on F = {s.field_nT:.1f} nT; dip spread {s.dip_sd_deg:.3f} deg",
                "    heading error the calibration leaves (its covariance): "
                + ("n/a" if s.heading_sd_deg is None else f"{s.heading_sd_deg:.3f} deg RMS"),
            ]
        lines.append("  what a heading of 0.5 deg needs:")
        lines += [f"    {line}" for line in self.budget.get("lines", [])]
        if self.warnings:
            lines.append("  warnings:")
            lines += [f"    - {w}" for w in self.warnings]
        return "\n".join(lines) + "\n"


def fit_gravity(
    dataset: Dataset,
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
    """The joint maximum-likelihood fit of the magnetometers and the accelerometer (see the module docstring).

    Parameters
    ----------
    dataset : Dataset
        Readings with accelerometer columns (:mod:`magcal.data.accelerometer`).
    inclination_deg : float, optional
        The field's inclination (deg, positive down), e.g. IGRF at the place; default fitted from the dip.
    inclination_source : str
        Where a given inclination came from (for the report).
    reference_total_nT : float, optional
        The total field; default the ellipsoid's magnitude (``det C^-1 = 1``), which only scales the result.
    noise_nT : float, optional
        The magnetometer's noise per axis; default estimated.
    accel_noise_m_s2 : float, optional
        The accelerometer's noise per axis; default estimated.
    accel_fit : {"auto", "full", "none"}
        Whether to fit the accelerometer's bias and scale (:func:`fit_accelerometer`).
    accel_units : str, optional
        The unit of unmarked ``ax, ay, az`` columns.
    mask : array_like of bool, shape (N,), optional
        Samples to use.
    still : StillSamples, optional
        The still samples (default :func:`magcal.data.accelerometer.find_still`).
    robust : bool
        Soft-L1 loss: samples the hand knocked do not pull the fit.
    mag_model : {"auto", "full", "rotation"}
        ``full``: each magnetometer's matrix, bias and rotation; ``rotation``: its rotation into the accelerometer's
        frame only, the matrix and bias taken from its ellipsoid (or, when the readings determine none, a sphere
        through them: a flight log's band of attitudes); ``auto``: ``full`` where the ellipsoid is determined.

    Returns
    -------
    GravityFitResult
        Its ``warnings`` (the texts, saved with the fit) and ``notes`` (the same as :class:`DataWarning` notes)
        say what the user must hear; never raised here: the command line and the workbench print them.

    Raises
    ------
    MagcalError
        No accelerometer columns, too few still samples, a magnetometer without an ellipsoid.
    """
    start = time.perf_counter()
    rec = _still_record(dataset, mask, still, accel_units, accel_fit, accel_noise_m_s2)
    notes = rec.notes
    inc_given = None if inclination_deg is None else float(np.radians(inclination_deg))
    prob, x, starts, start_notes = _joint_start(dataset, rec, reference_total_nT, mag_model, inc_given)
    notes += start_notes
    fit = _joint_solve(prob, x, rec.af, noise_nT, accel_noise_m_s2, robust)
    x, (sigma_a, sigma_f, sigma_d) = fit.x, _sigma_blocks(fit.sigmas, dataset.n_sensors)
    r_a, r_f, r_d = prob.parts(x)
    kinv, ba, _, _, inc = prob.unpack(x)
    af = rec.af
    if af.fitted:
        af = AccelFit(
            kinv, np.asarray(ba, float).copy(), float(np.sqrt(np.mean(r_a**2))), float(sigma_a), True, af.spread
        )
    z = prob.residuals(x, sigma_a, sigma_f, sigma_d)
    cov = correlated_covariance(fit.solution.jac, z, len(x), r_d, len(z))
    if cov.matrix is None:
        notes.append("the fit's covariance is singular: the record does not determine every parameter")
    inc_sd = None
    if cov.matrix is not None and inc_given is None:
        inc_sd = float(np.degrees(np.sqrt(max(cov.matrix[-1, -1], 0.0))))
        if af.fitted:
            af.bias_sd_m_s2 = np.sqrt(np.clip(np.diag(cov.matrix)[6:9], 0.0, None))
    residuals = (r_f, r_d, sigma_f, sigma_d)
    fits, blocks, sensor_notes = _sensor_fits(prob, x, cov, rec, af, starts, residuals, accel_fit)
    notes += sensor_notes
    inc_deg = float(np.degrees(inc))
    if inclination_deg is not None:
        notes.extend(_dip_note(r_d, inc, inclination_source))
    tilts = tilt_deg(rec.af.correct(rec.a_still))  # by the accelerometer's own fit, before the joint one
    tilt_range = (float(np.min(tilts)), float(np.max(tilts)))
    if tilt_range[1] < 60.0:
        notes.append(
            f"the board tilted at most {tilt_range[1]:.0f} deg while still: the mounting about its vertical axis and "
            "the magnetometer's vertical scale rest on few attitudes; turn it onto its sides and upside down"
        )
    budget = heading_budget(fits, af, inc_deg, rec.still.n, tilt_range, sigma_d)
    cal = Calibration(
        sensors=[SensorCalibration(f.cinv, f.bias_nT, f.mounting, summary=f.summary()) for f in fits],
        reference_total_nT=float(np.median(prob.fields)),
        reference_fitted=reference_total_nT is None,
        baseline_m=dataset.baseline_m,
        frame="accelerometer",
        mode="gravity",
        base_covariance=(scipy.linalg.block_diag(*blocks) if all(b is not None for b in blocks) else None),
        accelerometer=af.calibration(),
    )
    result = GravityFitResult(
        calibration=cal,
        sensors=fits,
        accel=af,
        inclination_deg=inc_deg,
        inclination_source="fitted" if inclination_deg is None else inclination_source,
        inclination_sd_deg=inc_sd,
        still=rec.still,
        tilt_range_deg=tilt_range,
        budget=budget,
        warnings=list(dict.fromkeys(notes)),
        n_samples=int(rec.keep.sum()),
        wall_s=time.perf_counter() - start,
        fitted=rec.keep,
        accel_unit=rec.accel.unit,
    )
    cal.summary = {"gravity_fit": result.to_dict()}
    return result


@dataclass
class _StillRecord:
    """The samples of a gravity fit: those kept (``keep``, bool N), the still ones among them (``still_rows``: their
    positions among the kept), their specific force (``a_still``, m/s^2) and the accelerometer's own fit."""

    accel: Accelerometer
    keep: np.ndarray
    still: StillSamples
    still_rows: np.ndarray
    a_still: np.ndarray
    af: AccelFit
    notes: list


def _still_record(dataset, mask, still, accel_units, accel_fit, accel_noise_m_s2) -> _StillRecord:
    """The accelerometer, the kept and the still samples, and the accelerometer's own fit (:func:`fit_gravity`'s
    first step); refused without accelerometer columns or with too few still samples."""
    notes: list[str] = []
    accel = accelerometer(dataset, units=accel_units)
    where = dataset.source or "data"
    if accel is None:
        raise MagcalError(
            f"{where}: no accelerometer columns (ax, ay, az; docs/gravity.md): a gravity calibration needs the "
            "accelerometer beside the magnetometer"
        )
    notes += list(accel.notes)
    keep = np.ones(dataset.n_samples, bool) if mask is None else np.asarray(mask, bool).copy()
    keep &= np.all(np.isfinite(dataset.readings_nT), axis=(0, 2))
    if still is None:
        still = find_still(dataset, accel, mask=keep)
    notes += list(still.notes)
    still_mask = still.mask & keep & accel.present
    if still_mask.sum() < MIN_STILL:
        raise MagcalError(
            f"{where}: only {int(still_mask.sum())} samples measure gravity (the accelerometer near g and steady); a "
            f"gravity calibration needs at least {MIN_STILL}, at many attitudes: hold the board still for a second "
            "or two at each"
        )
    still_rows = np.flatnonzero(still_mask[np.flatnonzero(keep)])  # positions of the still samples among the kept
    a_still = accel.m_s2[still_mask]
    af = fit_accelerometer(a_still, fit=accel_fit, noise_m_s2=accel_noise_m_s2)
    if not af.fitted:
        notes.append(
            (
                f"the accelerometer's still samples point over too few directions (spread {af.spread:.3f}, "
                f"{ACCEL_SPREAD_MIN} needed) to fit its bias and scale: its readings are used as they are"
                if accel_fit != "none"
                else "the accelerometer is taken as it reads (--accel-fit none)"
            )
            + ". Its own bias (20-60 mg for an uncalibrated MEMS part: 1-3 deg of tilt) then goes into the mounting "
            "and the heading, and the figures below do not include it. Turn the board onto each of its six faces "
            "(or through every attitude) to calibrate it too, or give a calibrated accelerometer"
        )
    return _StillRecord(accel, keep, still, still_rows, a_still, af, notes)


def _joint_start(dataset, rec: _StillRecord, reference_total_nT, mag_model, inc_given):
    """``(problem, x, starts, notes)``: each magnetometer's ellipsoid and the right angle the dip chooses
    (:func:`dip_start`), the joint problem and its start; ``starts[s] = (right angle, margin)``; the notes of a
    magnetometer whose rotation only is fitted."""
    notes = []
    down = -_unit(rec.af.correct(rec.a_still))
    ys, fields, ws, bs, incs, starts, fixed = [], [], [], [], [], [], []
    for s in range(dataset.n_sensors):
        y = dataset.readings_nT[s][rec.keep]
        cinv, bias, field_nT, why = _magnetometer_start(y, reference_total_nT, mag_model, s)
        if why:
            notes.append(why)
        m_dirs = _unit((y[rec.still_rows] - bias) @ cinv.T)
        right, rot, inc0, margin = dip_start(m_dirs, down, inc_given)
        ys.append(y)
        fields.append(field_nT)
        ws.append(rot @ cinv)
        bs.append(bias)
        incs.append(inc0)
        starts.append((right, margin))
        fixed.append(None if not why else (rot @ cinv, bias))
    af = rec.af
    prob = _Problem(
        ys,
        rec.a_still,
        rec.still_rows,
        fields,
        STANDARD_GRAVITY_M_S2,
        af.fitted,
        (af.kinv, af.bias_m_s2),
        inc_given,
        fixed,
    )
    return prob, prob.pack(af.kinv, af.bias_m_s2, ws, bs, float(np.mean(incs))), starts, notes


#: Re-weighting rounds of the joint fit (:func:`magcal.fitting.solver.reweighted_fit`).
REWEIGHT_ROUNDS = 3


def _joint_solve(prob: _Problem, x, af: AccelFit, noise_nT, accel_noise_m_s2, robust) -> Reweighted:
    """The joint maximum likelihood, its noises re-estimated between rounds: the accelerometer's magnitude, then per
    magnetometer its total field and its dip (:class:`magcal.fitting.solver.NoiseGroup`)."""
    ns = prob.ns
    groups = [NoiseGroup(1e-5, accel_noise_m_s2)] + [NoiseGroup(1e-3, noise_nT)] * ns + [NoiseGroup(1e-6)] * ns

    def parts(xv):
        r_a, r_f, r_d = prob.parts(xv)
        return [r_a, *r_f, *r_d]

    def solve(xv, sigmas):
        sol = weighted_least_squares(prob.residuals, xv, prob.scale(), robust, args=tuple(_sigma_blocks(sigmas, ns)))
        return sol.x, sol

    first = estimate_sigmas(groups, parts(x))
    first[0] = accel_noise_m_s2 if accel_noise_m_s2 is not None else af.sigma_m_s2
    return reweighted_fit(solve, parts, groups, x, first, rounds=REWEIGHT_ROUNDS)


def _sigma_blocks(sigmas, ns):
    """``(sigma_a, sigma_f, sigma_d)`` of the flat list of :func:`_joint_solve`'s noises."""
    return sigmas[0], list(sigmas[1 : 1 + ns]), list(sigmas[1 + ns :])


def _sensor_fits(prob: _Problem, x, cov: Covariance, rec: _StillRecord, af: AccelFit, starts, residuals, accel_fit):
    """``(fits, covariance blocks, notes)``: each magnetometer's :class:`SensorGravityFit` and its 12 x 12
    covariance of ``W`` and bias (None without a covariance); notes of a mounting not determined or a right angle
    not clear."""
    notes = []
    r_f, r_d, sigma_f, sigma_d = residuals
    _, _, ws, bs, _ = prob.unpack(x)
    pitch_ok = np.abs(_unit(af.correct(rec.a_still))[:, 0]) <= np.sin(np.radians(HEADING_MAX_PITCH_DEG))
    fits, blocks = [], []
    for s, (right, margin) in enumerate(starts):
        w = ws[s]
        block = None if cov.matrix is None else prob.sensor_covariance(cov.matrix, s, x)
        blocks.append(block)
        mount_sd = None if block is None else mounting_sd_deg(w, block[:9, :9])
        head_sd = None
        if cov.matrix is not None and pitch_ok.any():
            head_sd = _heading_sd_deg(prob, x, cov.matrix, s, rec.still_rows, pitch_ok)
        spread_out = (mount_sd is not None and float(np.max(mount_sd)) > UNDETERMINED_MOUNTING_DEG) or (
            head_sd is not None and head_sd > UNDETERMINED_HEADING_DEG
        )
        if spread_out:
            notes.append(
                f"sensor {s + 1}: this record does not determine the mounting: its standard deviation is up to "
                f"{float(np.max(mount_sd)) if mount_sd is not None else float('nan'):.2f} deg and the heading error "
                f"the calibration leaves {head_sd if head_sd is not None else float('nan'):.2f} deg. Turn the board "
                "through more attitudes (on its sides and upside down) and hold it still at each"
            )
        if margin < 1.5:
            notes.append(
                f"sensor {s + 1}: the right angle between the magnetometer's axes and the accelerometer's is not clear "
                f"(the second best spreads the dip only {margin:.2f}x as much): check that both sensors are on one "
                "board and that the still samples span many attitudes"
            )
        fits.append(
            SensorGravityFit(
                **mounting_fields(w, np.asarray(bs[s], float).copy(), right, margin, s, "board", off_nearest=False),
                field_nT=prob.fields[s],
                rms_total_field_nT=float(np.sqrt(np.mean(r_f[s] ** 2))),
                sigma_total_field_nT=float(sigma_f[s]),
                dip_sd_deg=float(np.degrees(np.std(r_d[s]))),
                sigma_dip_deg=float(np.degrees(sigma_d[s])),
                mounting_sd_deg=mount_sd,
                bias_sd_nT=None if block is None else np.sqrt(np.clip(np.diag(block)[9:], 0.0, None)),
                heading_sd_deg=head_sd,
                sd_widening=cov.widening,
                # an accelerometer neither fitted nor said to be calibrated (--accel-fit none): its bias is in the
                # mounting
                determined=not spread_out and (af.fitted or accel_fit == "none"),
            )
        )
    return fits, blocks, notes


def _dip_note(r_d, inc, inclination_source) -> list:
    """A note when the dip the data measure is more than 3 deg off the inclination given (its sign reversed: the
    accelerometer reads gravity; else a local anomaly or the wrong place)."""
    inc_deg = float(np.degrees(inc))
    measured = float(np.median(np.concatenate([np.degrees(r + inc) for r in r_d])))
    if abs(measured - inc_deg) <= 3.0:
        return []
    return [
        f"the dip the data measure ({measured:.1f} deg) is {measured - inc_deg:+.1f} deg off the inclination "
        f"given ({inc_deg:.1f} deg, {inclination_source})"
        + (
            ": its sign is reversed: does the accelerometer read gravity (down) instead of the specific force "
            "(up when still)? Negate its columns"
            if measured * inc_deg < 0
            else ": a local anomaly (steel, a building) or the wrong place; leave the inclination to the fit"
        )
    ]


def _magnetometer_start(y, reference_total_nT, mag_model, s):
    """``(C^-1, b, F, why)``: a magnetometer's start from its ellipsoid; ``why`` says, when not empty, that only its
    rotation will be fitted (``mag_model="rotation"``, or an ellipsoid the readings do not determine: then the
    sphere through them, :func:`magcal.geometry.sphere.sphere_centre`)."""
    try:
        ell = fit_ellipsoid(y, reference_total_nT=reference_total_nT, label=f"sensor {s + 1}")
        cinv, bias, field_nT, problem = ell.cinv, ell.bias_nT, float(ell.field_nT), ""
        if ell.coverage.thinnest_spread < WEAK_DIRECTION_SPREAD:  # an ellipsoid extrapolated from a band
            problem = (
                f"sensor {s + 1}: the readings' directions spread too little (thinnest spread "
                f"{ell.coverage.thinnest_spread:.3f}, full sphere 0.33) to determine an ellipsoid"
            )
    except CalibrationError as exc:
        bias = sphere_centre(y)
        radius = float(np.median(np.linalg.norm(y - bias, axis=1)))
        field_nT = float(reference_total_nT) if reference_total_nT else radius
        cinv, problem = np.eye(3) * field_nT / max(radius, 1e-9), str(exc)
    if mag_model == "full" and problem:
        raise CalibrationError(problem)
    if mag_model == "rotation":
        return (
            cinv,
            bias,
            field_nT,
            (
                f"sensor {s + 1}: only its rotation into the accelerometer's frame is fitted (the matrix and bias of its "
                "ellipsoid are kept)"
            ),
        )
    if problem:
        return (
            cinv,
            bias,
            field_nT,
            (
                f"sensor {s + 1}: its readings do not determine an ellipsoid ({problem.split(' (')[0].split(': ', 1)[-1]}: "
                "a band of attitudes, as in a flight log): only its rotation into the accelerometer's frame is fitted, "
                "with the bias of the sphere through the readings and no matrix; calibrate the magnetometer on a record "
                "turned through every direction first"
            ),
        )
    return cinv, bias, field_nT, ""


def _heading_sd_deg(prob: _Problem, x, cov, sensor, still_rows, pitch_ok) -> float:
    """RMS over (a sample of) the still samples of the heading's standard deviation that the parameters' covariance
    implies: the heading's derivatives by central differences, ``sd_i^2 = J_i cov J_i^T``."""
    pick = np.flatnonzero(pitch_ok)
    if pick.size > HEADING_SD_SAMPLES:
        pick = pick[np.linspace(0, pick.size - 1, HEADING_SD_SAMPLES).astype(int)]
    y = prob.ys[sensor][still_rows[pick]]
    a = prob.a[pick]

    def heading(xv):
        kinv, ba, ws, bs, _ = prob.unpack(xv)
        return tilt_heading_deg((a - ba) @ kinv.T, (y - bs[sensor]) @ ws[sensor].T)

    step = 1e-6 * np.maximum(np.abs(x), prob.scale())
    jac = np.empty((pick.size, x.size))
    for k in range(x.size):
        dx = np.zeros_like(x)
        dx[k] = step[k]
        jac[:, k] = angle_difference_deg(heading(x + dx), heading(x - dx)) / (2 * step[k])
    var = np.einsum("ij,jk,ik->i", jac, cov, jac)
    return float(np.sqrt(np.mean(np.clip(var, 0.0, None))))


def heading_budget(fits, accel: AccelFit, inclination_deg, n_still, tilt_range, sigma_dip_rad) -> dict:
    """What a heading of :data:`HEADING_GOAL_DEG` needs, from the fit's figures.

    The heading error of one sample is the sensors' noise (the tilt error across gravity times ``tan I``, the
    magnetometer's east noise over the horizontal field) and the calibration's own error (:attr:`SensorGravityFit.heading_sd_deg`), which falls as ``1 / sqrt(still samples)``. Returns the figures and the lines the report prints.
    """
    s = fits[0]
    field_nT = max(s.field_nT, 1e-9)
    mag_frac = s.sigma_total_field_nT / field_nT
    tilt_noise = float(np.sqrt(max(float(sigma_dip_rad[0]) ** 2 - mag_frac**2, 0.0)))
    per_sample = heading_noise_deg(tilt_noise, mag_frac, inclination_deg)
    cal = s.heading_sd_deg
    goal = HEADING_GOAL_DEG
    lines = [
        f"sensors' noise: {per_sample:.2f} deg per sample at {inclination_deg:.0f} deg of inclination "
        f"(tilt noise {np.degrees(tilt_noise):.3f} deg x tan I; magnetometer {s.sigma_total_field_nT:.0f} nT over the "
        f"horizontal field)",
    ]
    average = int(np.ceil((per_sample / (0.9 * goal)) ** 2)) if per_sample > 0.9 * goal else 1
    lines.append(
        "one sample reaches it"
        if average == 1
        else f"average {average} still samples per reading (or a quieter part) to bring the noise under {0.9 * goal:.2f} deg"
    )
    need_still = None
    if cal is not None:
        if cal <= 0.4 * goal:
            lines.append(f"the calibration's own error, {cal:.3f} deg, is within it ({n_still} still samples)")
        else:
            need_still = int(np.ceil(n_still * (cal / (0.4 * goal)) ** 2))
            lines.append(
                f"the calibration's own error, {cal:.3f} deg, needs about {need_still} still samples at as many "
                f"attitudes (now {n_still}) to fall under {0.4 * goal:.2f} deg"
            )
    if tilt_range[1] < 90.0:
        lines.append(
            f"tilts up to {tilt_range[1]:.0f} deg only: turn the board onto its sides and upside down so that the dip "
            "sees every axis"
        )
    return {
        "goal_deg": goal,
        "noise_per_sample_deg": per_sample,
        "tilt_noise_deg": float(np.degrees(tilt_noise)),
        "calibration_heading_sd_deg": cal,
        "samples_to_average": average,
        "still_samples_needed": need_still,
        "lines": lines,
    }


# --- the separate calibrations, the true one, and the held-out check ---------------------------------------------
def separate_calibration(
    dataset, right_angle=None, mask=None, still=None, accel_fit="auto", reference_total_nT=None, accel_units=None
) -> Calibration:
    """What a user gets without the dip: the magnetometer's total-field fit (:func:`magcal.fitting.pipeline.calibrate`,
    its upper-triangular frame) turned by the right angle between the two parts (taken as known, e.g.
    from the data sheets), beside the accelerometer's own fit. Its heading error is the misalignment the total
    field cannot see.

    Parameters
    ----------
    dataset : Dataset
    right_angle : array_like, shape (3, 3), optional
        Magnetometer axes -> accelerometer axes; default the identity.
    mask, still, accel_fit, reference_total_nT, accel_units
        As for :func:`fit_gravity`.
    """
    n = dataset.n_samples
    keep = np.ones(n, bool) if mask is None else np.asarray(mask, bool)
    accel = accelerometer(dataset, units=accel_units)
    if accel is None:
        raise MagcalError(f"{dataset.source or 'data'}: no accelerometer columns")
    if still is None:
        still = find_still(dataset, accel, mask=keep)
    af = fit_accelerometer(accel.m_s2[still.mask & keep & accel.present], fit=accel_fit)
    result = calibrate(dataset, mask=keep, reference_total_nT=reference_total_nT)
    a = np.eye(3) if right_angle is None else np.asarray(right_angle, float)
    sensors = [SensorCalibration(c.cinv, c.bias_nT, a @ c.R) for c in result.calibration.sensors]
    return Calibration(
        sensors=sensors,
        reference_total_nT=result.calibration.reference_total_nT,
        frame="accelerometer",
        mode="gravity",
        accelerometer=af.calibration(),
    )


def heading_rows(calibration, dataset, rows, accel_units=None) -> np.ndarray:
    """The rows (bool, N) among ``rows`` whose board x axis is within :data:`HEADING_MAX_PITCH_DEG` of the
    horizontal by ``calibration``'s accelerometer (where a heading of the x axis means something)."""
    accel = accelerometer(dataset, units=accel_units)
    if accel is None:
        raise MagcalError(f"{dataset.source or 'data'}: no accelerometer columns (ax, ay, az): a heading needs them")
    f = calibration.accelerometer.correct(accel.m_s2)
    with np.errstate(invalid="ignore"):
        level = np.abs(f[:, 0] / np.linalg.norm(f, axis=1)) <= np.sin(np.radians(HEADING_MAX_PITCH_DEG))
    return np.asarray(rows, bool) & level


def heading_figures(calibration, dataset, rows, true_heading_deg=None, other=None, accel_units=None) -> dict:
    """Per sensor, on the samples ``rows`` (bool, N; those whose x axis is steep are left out of the headings):
    the dip's mean and spread (deg), the RMS heading error against ``true_heading_deg`` (deg, when known) and the
    RMS heading difference from another calibration ``other`` (deg)."""
    h = calibration.heading(dataset, accel_units=accel_units, force=True)
    rows = np.asarray(rows, bool)
    level = heading_rows(calibration, dataset, rows, accel_units)

    def rms(v):
        return float(np.sqrt(np.mean(v**2))) if v.size else float("nan")

    out: dict = {"dip_mean_deg": [], "dip_sd_deg": [], "n": int(np.count_nonzero(rows)), "n_heading": int(level.sum())}
    if true_heading_deg is not None:
        out["heading_rms_deg"] = [
            rms(angle_difference_deg(hd[level], np.asarray(true_heading_deg)[level])) for hd in h["heading_deg"]
        ]
    if other is not None:
        h2 = other.heading(dataset, accel_units=accel_units, force=True)
        out["heading_difference_rms_deg"] = [
            rms(angle_difference_deg(a[level], b[level])) for a, b in zip(h["heading_deg"], h2["heading_deg"])
        ]
    for d in h["dip_deg"]:
        out["dip_mean_deg"].append(float(np.mean(d[rows])) if rows.any() else float("nan"))
        out["dip_sd_deg"].append(float(np.std(d[rows])) if rows.any() else float("nan"))
    return out


@dataclass
class GravityValidation(BlockValidation):
    """Held-out figures of the gravity fit beside the separate calibrations (:func:`validate_gravity`).

    Attributes
    ----------
    n_blocks, train
        As :class:`magcal.fitting.validation.BlockValidation`.
    rows : list of dict
        Per calibration (``name``: ``gravity`` or ``separate``): on the still samples of the fitted blocks (``in_``)
        and of the others (``held_``), sensor 1: the dip's spread (deg), ``|B|`` RMS against the fit's ``F`` (nT).
    heading_difference_deg : float
        RMS over the held-out still samples of the heading difference between the two (deg): the heading error
        the separate calibrations leave, if the gravity fit is right (NaN when the record has no total-field fit).
    """

    heading_difference_deg: float

    def text(self) -> str:
        lines = [
            f"  held-out check (fitted on the 1st, 3rd, ... of {self.n_blocks} blocks in time, scored on the still "
            "samples of the others; sensor 1):"
        ]
        for r in self.rows:
            lines.append(
                f"    {r['name']:9s} dip spread {r['in_dip_sd_deg']:.3f} in / {r['held_dip_sd_deg']:.3f} deg held out; "
                f"|B| {r['in_total_nT']:.1f} in / {r['held_total_nT']:.1f} nT held out"
            )
        if np.isfinite(self.heading_difference_deg):
            lines.append(
                f"    heading difference, separate calibrations - gravity fit: {self.heading_difference_deg:.2f} deg "
                "RMS (held out)"
            )
        else:
            lines.append("    (no total-field fit of this record to set beside it: its ellipsoid is not determined)")
        return "\n".join(lines) + "\n"

    def to_dict(self) -> dict:
        return {**super().to_dict(), "heading_difference_deg": self.heading_difference_deg}


def validate_gravity(dataset, n_blocks=None, **options) -> GravityValidation:
    """Fit on alternate blocks in time and score on the blocks between: the gravity fit and, beside it, the separate
    calibrations (:func:`separate_calibration`, with the right angle the gravity fit found).

    Parameters
    ----------
    dataset : Dataset
    n_blocks : int, optional
        Blocks in time, odd, at least 3 (:func:`magcal.fitting.validation.held_out_blocks`: by default blocks of at
        least :data:`magcal.fitting.validation.MIN_BLOCK_S`).
    **options
        Passed to :func:`fit_gravity` (``inclination_deg``, ``noise_nT``, ``accel_fit``, ``accel_units``,
        ``reference_total_nT``, ``robust``).

    Raises
    ------
    CalibrationError
        A record too short to split (:func:`magcal.fitting.validation.split_problem`).
    """
    train, test, n_blocks = held_out_blocks(dataset, n_blocks)
    accel = accelerometer(dataset, units=options.get("accel_units"))
    if accel is None:
        raise MagcalError(f"{dataset.source or 'data'}: no accelerometer columns")
    still = find_still(dataset, accel)
    fit = fit_gravity(dataset, mask=train, **options)
    try:
        sep = separate_calibration(
            dataset,
            right_angle=fit.sensors[0].right_angle,
            mask=train,
            accel_fit=options.get("accel_fit", "auto"),
            reference_total_nT=options.get("reference_total_nT"),
            accel_units=options.get("accel_units"),
        )
    except CalibrationError:  # no total-field fit on this record (a band of attitudes): nothing to set beside
        sep = None
    rows = []
    units = options.get("accel_units")
    for name, cal in (("gravity", fit.calibration), ("separate", sep)):
        if cal is None:
            continue
        total = cal.total_field(dataset)
        total = total if total.ndim == 2 else total[None]
        f_in = heading_figures(cal, dataset, still.mask & train, accel_units=units)
        f_out = heading_figures(cal, dataset, still.mask & test, accel_units=units)
        field_nT = float(cal.reference_total_nT or np.median(total[0]))
        rows.append(
            {
                "name": name,
                "in_dip_sd_deg": f_in["dip_sd_deg"][0],
                "held_dip_sd_deg": f_out["dip_sd_deg"][0],
                "in_total_nT": float(np.sqrt(np.mean((total[0][train] - field_nT) ** 2))),
                "held_total_nT": float(np.sqrt(np.mean((total[0][test] - field_nT) ** 2))),
            }
        )
    if sep is None:
        return GravityValidation(n_blocks, rows, float("nan"), train=train)
    diff = heading_figures(fit.calibration, dataset, still.mask & test, other=sep, accel_units=units)
    return GravityValidation(n_blocks, rows, diff["heading_difference_rms_deg"][0], train=train)
