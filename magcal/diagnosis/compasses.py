"""Several compasses on one vehicle: how far apart their corrected fields are, against what the flight
controllers' "inconsistent compasses" checks tolerate, and what makes them differ.

A vehicle with two or three compasses (ArduPilot ``MAG``/``MAG2``/``MAG3``, PX4 ``sensor_mag`` instances; read as
sensors 1, 2, 3 of one :class:`~magcal.data.dataset.Dataset`) has each compass calibrated into the body frame
(:func:`magcal.fitting.vector.fit_vector`). Their fields should then agree; the flight controllers refuse to arm
when they do not:

ArduPilot, ``Compass::consistent()`` (``libraries/AP_Compass/AP_Compass.cpp``, limits in ``AP_Compass.h``)
    Compares every compass used for yaw with the primary one, each as ``get_field()`` gives it: body frame, after
    the compass's offsets, matrix, scale and motor compensation, in milligauss. It fails when the 3-D angle
    between the two fields exceeds ``AP_COMPASS_MAX_XYZ_ANG_DIFF`` = 90 deg, the angle between their body-frame
    x-y projections exceeds ``AP_COMPASS_MAX_XY_ANG_DIFF`` = 60 deg, or the length of the difference of those
    projections exceeds ``AP_COMPASS_MAX_XY_LENGTH_DIFF`` = 200 mGauss (20 000 nT). ``AP_Arming`` reports
    "Compasses inconsistent" before arming. Older releases used 50 deg, 30 deg and 100 mGauss.
PX4, ``VehicleMagnetometer::calcMagInconsistency()`` (``src/modules/sensors/vehicle_magnetometer/``)
    Takes the 3-D angle between each calibrated magnetometer (``CAL_MAGn_*`` applied and rotated into the body
    frame) and the selected one, low-pass filters it (``0.95 a + 0.05 angle`` per update of about 50 ms: about
    1 s) while disarmed, and ``MagnetometerChecks::consistencyCheck()``
    (``src/modules/commander/HealthAndArmingChecks/checks/magnetometerCheck.cpp``) fails arming when it exceeds
    ``COM_ARM_MAG_ANG`` (deg; default 60 in ``commander_params.c``, 45 in older releases; -1 disables it).

:func:`compass_consistency` gives, for every pair of compasses, those figures (median, 95th percentile and maximum
of the 3-D angle, the body-frame x-y angle, the x-y length difference and the difference of ``|B|``, and how
they move over the record) for the fields *before* (the flight controller's logged calibration when the log kept
it, :func:`magcal.data.logs.logged_field_columns`, else the raw readings in the right-angle orientation the fit
found) and *after* the given calibration, and names the cause of a difference where it is one of the model's
effects. The difference ``d = B_j - B_i`` of compass ``j`` from compass ``i`` is regressed on

* a constant, and a linear function of the field ``B_i`` (a relative mounting rotation, a scale or soft-iron
  difference, an offset: separable only when the field's directions spread, else reported as one constant part),
* the current (``current_A``, else ``throttle``): a field one compass sees and the other does not, in nT per
  ampere, with the angle and ``|B|`` difference it makes per ampere,
* the temperature (when it moves by more than 2 degC), and
* the field's rate ``dB_i/dt`` (a sampling delay between the two, in ms);

each term's share of the mean-square difference and its significance (its estimate over its standard error,
widened for residuals correlated in time) decide whether it is named. With the attitude and the reference field,
each compass's own residual against the reference field is regressed on the current too: the pair difference
cannot tell which of two compasses sees the current, the reference can. The fitted mountings of a vector
calibration say how far each compass sits off the right angle its firmware orientation parameter can hold.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np
import scipy.signal
from scipy.spatial.transform import Rotation

from magcal.calibration.calibration import Calibration, current_term
from magcal.core.errors import MagcalError
from magcal.core.jsonable import jsonable
from magcal.data.attitude import attitude_rows
from magcal.data.dataset import Dataset
from magcal.data.logs import logged_field_columns
from magcal.geometry.orientations import describe_right_angle, nearest_right_angle
from magcal.model.effects import CURRENT_COLUMNS, current_column, time_derivative

#: ArduPilot's limits (``libraries/AP_Compass/AP_Compass.h``): the 3-D angle and the body x-y angle (deg) between a
#: compass's field and the primary's, and the length of the difference of their x-y projections (200 mGauss, nT).
ARDUPILOT_MAX_XYZ_ANGLE_DEG = 90.0
ARDUPILOT_MAX_XY_ANGLE_DEG = 60.0
ARDUPILOT_MAX_XY_LENGTH_nT = 20_000.0

#: PX4's ``COM_ARM_MAG_ANG`` default (deg) and the time constant (s) of its filter of the angle (``0.95``/``0.05``
#: per update of about 50 ms).
PX4_MAX_ANGLE_DEG = 60.0
PX4_FILTER_TIME_S = 0.05 / -np.log(0.95)

#: A cause is named when it accounts for at least this fraction of the pair's mean-square difference ...
MIN_SHARE = 0.1
#: ... and its estimate is at least this many (widened) standard errors from zero.
MIN_SIGNIFICANCE = 5.0
#: The relative rotation and scale of a pair are separated from a constant offset only when the fit determines
#: them to better than these (the field's directions spread enough): deg and fraction.
MAX_ROTATION_SD_DEG = 0.25
MAX_STRETCH_SD = 0.005
#: A temperature channel takes part when it moves by more than this (degC) over the samples compared.
MIN_TEMPERATURE_RANGE_C = 2.0
#: Blocks in time of the figures "over time".
N_BLOCKS = 10
#: Fewest samples compared.
MIN_SAMPLES = 20
#: The regressions that name the causes take at most this many samples, evenly spread over the record (the
#: figures the firmwares check use every sample).
MAX_REGRESSION_SAMPLES = 20_000


def angle_deg(a, b) -> np.ndarray:
    """Angle (deg) between the rows of ``a`` and ``b`` (N, k); NaN where either is zero."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        c = np.sum(a * b, axis=-1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


@dataclass
class Spread:
    """Median, 95th percentile and maximum of a quantity over the samples (its unit)."""

    median: float
    p95: float
    max: float

    @classmethod
    def of(cls, values, signed=False) -> Spread:
        """Of ``values`` (their absolute values for the percentile and maximum when ``signed``: the median keeps
        the sign, e.g. which compass reads the larger ``|B|``)."""
        v = np.asarray(values, dtype=float)
        v = v[np.isfinite(v)]
        if v.size == 0:
            return cls(np.nan, np.nan, np.nan)
        size = np.abs(v) if signed else v
        return cls(float(np.median(v)), float(np.percentile(size, 95)), float(np.max(size)))

    def text(self, digits=2) -> str:
        return f"{self.median:.{digits}f} / {self.p95:.{digits}f} / {self.max:.{digits}f}"

    def to_dict(self) -> dict:
        return {"median": self.median, "p95": self.p95, "max": self.max}


@dataclass
class PairFigures:
    """One pair of compasses in one state (``before`` or ``after``), the figures the firmware checks compare.

    Attributes
    ----------
    angle_deg, xy_angle_deg : Spread
        3-D angle and body x-y angle between the two fields (deg).
    xy_length_nT : Spread
        Length of the difference of their body x-y projections (nT).
    total_diff_nT : Spread
        ``|B_j| - |B_i|`` (nT; median signed).
    fail_fraction : dict
        Fraction of the samples the checks would refuse: ``ardupilot`` (any of its three limits), ``px4`` (the
        filtered angle beyond ``COM_ARM_MAG_ANG``'s default).
    px4_filtered_max_deg : float
        Largest value of the angle filtered as PX4 filters it (deg).
    blocks : dict
        Over time, :data:`N_BLOCKS` blocks: ``t_mid_s`` (or sample index), the median ``angle_deg`` and
        ``total_diff_nT`` of each.
    """

    angle_deg: Spread
    xy_angle_deg: Spread
    xy_length_nT: Spread
    total_diff_nT: Spread
    fail_fraction: dict
    px4_filtered_max_deg: float
    blocks: dict

    def to_dict(self) -> dict:
        return {
            "angle_deg": self.angle_deg.to_dict(),
            "xy_angle_deg": self.xy_angle_deg.to_dict(),
            "xy_length_nT": self.xy_length_nT.to_dict(),
            "total_diff_nT": self.total_diff_nT.to_dict(),
            "fail_fraction": dict(self.fail_fraction),
            "px4_filtered_max_deg": self.px4_filtered_max_deg,
            "over_time": {k: list(v) for k, v in self.blocks.items()},
        }


@dataclass
class Cause:
    """One term of a pair's difference.

    Attributes
    ----------
    kind : str
        ``current`` (or ``throttle``), ``temperature``, ``timing``, ``mounting`` (a relative rotation), ``scale``,
        ``offset``, ``constant`` (offset and rotation not separable), ``direction`` (a part that changes with the
        field's direction, not separable), ``mounting_fit`` (the calibration's fitted mountings).
    share : float
        Fraction of the pair's mean-square difference the term accounts for (0-1, not additive: terms overlap).
    rms_nT : float
        RMS of the term's vector over the samples (nT).
    significance : float
        Its estimate over its standard error (inf for the calibration's own figures).
    named : bool
        Whether it is named as a cause (:data:`MIN_SHARE`, :data:`MIN_SIGNIFICANCE`).
    values : dict
        Its numbers (per unit of a channel in nT and deg, a rotation in deg, a delay in ms...).
    text : str
    """

    kind: str
    share: float
    rms_nT: float
    significance: float
    named: bool
    values: dict
    text: str

    def to_dict(self) -> dict:
        return {**asdict(self), "values": jsonable(self.values)}


@dataclass
class PairConsistency:
    """Compass ``j`` against compass ``i`` (0-based; ``i`` the primary when it is 0).

    Attributes
    ----------
    i, j : int
    before, after : PairFigures or None
    causes_before, causes_after : list of Cause
        Every term examined, largest share first (``named`` says which are named).
    rms_before_nT, rms_after_nT : float
        RMS of the difference vector (nT).
    residual_before_nT, residual_after_nT : float
        RMS of what no term explains (nT).
    """

    i: int
    j: int
    before: PairFigures | None
    after: PairFigures
    causes_before: list = field(default_factory=list)
    causes_after: list = field(default_factory=list)
    rms_before_nT: float = float("nan")
    rms_after_nT: float = float("nan")
    residual_before_nT: float = float("nan")
    residual_after_nT: float = float("nan")

    @property
    def label(self) -> str:
        return f"{self.i + 1}-{self.j + 1}"

    def named(self, state="before") -> list:
        """The named causes of one state."""
        return [c for c in (self.causes_before if state == "before" else self.causes_after) if c.named]

    def to_dict(self) -> dict:
        return {
            "pair": [self.i + 1, self.j + 1],
            "before": None if self.before is None else self.before.to_dict(),
            "after": self.after.to_dict(),
            "rms_before_nT": self.rms_before_nT,
            "rms_after_nT": self.rms_after_nT,
            "residual_before_nT": self.residual_before_nT,
            "residual_after_nT": self.residual_after_nT,
            "causes_before": [c.to_dict() for c in self.causes_before],
            "causes_after": [c.to_dict() for c in self.causes_after],
        }


@dataclass
class Sensitivity:
    """How much of a channel one compass sees, from its own residual against the reference field.

    Attributes
    ----------
    sensor : int
        0-based.
    state : str
        ``before`` or ``after``.
    per_unit_nT : numpy.ndarray, shape (3,)
        Body-frame field per unit of the channel in that state's field (nT per A, or per unit of throttle),
        with its standard errors ``sd_nT`` (widened for correlated residuals).
    compensated_nT : numpy.ndarray, shape (3,), or None
        After: what the calibration's own current term removes per unit (body frame, nT).
    sees : bool
        Named as a compass that sees the channel (beyond :data:`MIN_SIGNIFICANCE` standard errors and at least
        30 % of the largest).
    """

    sensor: int
    state: str
    per_unit_nT: np.ndarray
    sd_nT: np.ndarray
    compensated_nT: np.ndarray | None = None
    sees: bool = False

    @property
    def total_nT(self) -> np.ndarray:
        """What the compass sees per unit in all: what is left plus what the calibration removes."""
        return self.per_unit_nT + (0.0 if self.compensated_nT is None else self.compensated_nT)

    def to_dict(self) -> dict:
        return {
            "sensor": self.sensor + 1,
            "state": self.state,
            "per_unit_nT": self.per_unit_nT.tolist(),
            "sd_nT": self.sd_nT.tolist(),
            "compensated_nT": None if self.compensated_nT is None else self.compensated_nT.tolist(),
            "total_per_unit_nT": float(np.linalg.norm(self.total_nT)),
            "sees": self.sees,
        }


@dataclass
class CompassConsistency:
    """Outcome of :func:`compass_consistency`.

    Attributes
    ----------
    n_sensors, n_samples : int
        Compasses, and samples compared (where every field is finite and the mask keeps them).
    before_source, after_source : str
        What the two states' fields are.
    channel : str or None
        The current channel (``current_A`` or ``throttle``) examined, if any.
    pairs : list of PairConsistency
        Every pair ``(i, j)``, ``i < j``: those with compass 1 are what the firmwares check.
    sensitivities : list of Sensitivity
        Per compass and state, with the attitude and the reference field (empty without).
    mountings : list of dict
        Per compass, from a vector calibration: the right angle nearest its fitted mounting, the angle off it (deg),
        that rotation (``off_rotvec_body_deg``), the mounting's standard deviation (deg, the norm over the body axes)
        and whether the fit determined it. A relative mounting is named as a cause only when both are determined
        and it is :data:`MIN_SIGNIFICANCE` standard deviations from zero.
    notes : list of str
    """

    n_sensors: int
    n_samples: int
    before_source: str
    after_source: str
    channel: str | None
    pairs: list
    sensitivities: list = field(default_factory=list)
    mountings: list = field(default_factory=list)
    notes: list = field(default_factory=list)

    def pair(self, i, j) -> PairConsistency:
        """The pair of compasses ``i`` and ``j`` (0-based, either order)."""
        i, j = min(i, j), max(i, j)
        for p in self.pairs:
            if (p.i, p.j) == (i, j):
                return p
        raise KeyError(f"no pair {i + 1}-{j + 1}")

    def seeing(self, state="before") -> list:
        """0-based compasses named as seeing the current channel in ``state`` (by the reference field)."""
        return [s.sensor for s in self.sensitivities if s.state == state and s.sees]

    def text(self) -> str:
        """The consistency table, the causes and the firmware limits."""
        lines = [
            f"Compass consistency ({self.n_sensors} compasses, {self.n_samples} samples; pair i-j: compass j "
            "against compass i; compass 1 is the primary the firmwares compare with):",
            f"  before: {self.before_source}",
            f"  after:  {self.after_source}",
            "  limits: ArduPilot Compass::consistent() (AP_Compass.cpp): 3-D angle <= "
            f"{ARDUPILOT_MAX_XYZ_ANGLE_DEG:g} deg, body x-y angle <= {ARDUPILOT_MAX_XY_ANGLE_DEG:g} deg, x-y length "
            f"difference <= {ARDUPILOT_MAX_XY_LENGTH_nT:.0f} nT (200 mGauss); PX4 (VehicleMagnetometer.cpp, "
            f"magnetometerCheck.cpp): 3-D angle filtered over ~1 s <= COM_ARM_MAG_ANG ({PX4_MAX_ANGLE_DEG:g} deg "
            "by default)",
            f"  {'pair':5s} {'state':7s} {'angle deg':>21s} {'x-y angle deg':>21s} {'x-y length nT':>27s} "
            f"{'|B| diff nT':>24s} {'refused AP / PX4':>17s}",
            f"  {'':5s} {'':7s} {'(median / p95 / max)':>21s}",
        ]
        for p in self.pairs:
            for state, fig in (("before", p.before), ("after", p.after)):
                if fig is None:
                    continue
                lines.append(
                    f"  {p.label:5s} {state:7s} {fig.angle_deg.text():>21s} {fig.xy_angle_deg.text():>21s} "
                    f"{fig.xy_length_nT.text(0):>27s} {fig.total_diff_nT.text(0):>24s} "
                    f"{100 * fig.fail_fraction['ardupilot']:7.1f} % / {100 * fig.fail_fraction['px4']:.1f} %"
                )
        for p in self.pairs:
            lines.append(f"  compasses {p.label}:")
            for state, fig in (("before", p.before), ("after", p.after)):
                if fig is None:
                    continue
                med = fig.blocks["angle_deg"]
                dbs = fig.blocks["total_diff_nT"]
                lines.append(
                    f"    {state}: over time ({len(med)} blocks) the angle's median runs "
                    f"{np.nanmin(med):.2f}-{np.nanmax(med):.2f} deg and |B| diff's {np.nanmin(dbs):.0f} to "
                    f"{np.nanmax(dbs):.0f} nT; difference RMS "
                    f"{(p.rms_before_nT if state == 'before' else p.rms_after_nT):.1f} nT, "
                    f"{(p.residual_before_nT if state == 'before' else p.residual_after_nT):.1f} nT of it explained "
                    "by none of the terms"
                )
                named = p.named(state)
                if named:
                    lines += [f"      cause: {c.text}" for c in named]
                else:
                    lines.append("      no cause stands out (no term accounts for 10 % of the difference)")
        if self.mountings:
            text = "; ".join(
                f"compass {m['sensor']} {m['angle_off_deg']:.2f} deg off {m['right_angle']}"
                + ("" if m["determined"] else " (not determined by this record)")
                for m in self.mountings
            )
            lines.append(f"  mountings the calibration found (what an orientation parameter cannot hold): {text}")
        for state in ("before", "after"):
            rows = [s for s in self.sensitivities if s.state == state]
            if not rows:
                continue
            unit = CURRENT_COLUMNS.get(self.channel or "", "unit")
            parts = []
            for s in rows:
                part = f"compass {s.sensor + 1} {np.linalg.norm(s.per_unit_nT):.1f} +- {np.linalg.norm(s.sd_nT):.1f}"
                if s.compensated_nT is not None and np.linalg.norm(s.compensated_nT) > 0:
                    part += f" (+ {np.linalg.norm(s.compensated_nT):.1f} the calibration's current term removes)"
                parts.append(part)
            seen = [s.sensor + 1 for s in rows if s.sees]
            lines.append(
                f"  {state}, each compass against the reference field: nT per {unit}"
                + ("" if self.channel == "throttle" else f" of {self.channel}")
                + ": "
                + "; ".join(parts)
                + (
                    f" -> seen by compass{'' if len(seen) == 1 else 'es'} {', '.join(map(str, seen))}"
                    if seen
                    else " -> no compass stands out"
                )
            )
        lines += [f"  note: {n}" for n in self.notes]
        return "\n".join(lines) + "\n"

    def to_dict(self) -> dict:
        return {
            "n_sensors": self.n_sensors,
            "n_samples": self.n_samples,
            "before_source": self.before_source,
            "after_source": self.after_source,
            "channel": self.channel,
            "limits": {
                "ardupilot_max_xyz_angle_deg": ARDUPILOT_MAX_XYZ_ANGLE_DEG,
                "ardupilot_max_xy_angle_deg": ARDUPILOT_MAX_XY_ANGLE_DEG,
                "ardupilot_max_xy_length_nT": ARDUPILOT_MAX_XY_LENGTH_nT,
                "px4_com_arm_mag_ang_deg": PX4_MAX_ANGLE_DEG,
                "px4_filter_time_s": PX4_FILTER_TIME_S,
            },
            "pairs": [p.to_dict() for p in self.pairs],
            "sensitivities": [s.to_dict() for s in self.sensitivities],
            "mountings": jsonable(self.mountings),
            "notes": list(self.notes),
        }


# -- the firmware's figures --------------------------------------------------------------------------------------
def _px4_filtered(angle, time_s) -> np.ndarray:
    """The angle low-pass filtered as PX4 filters it (a first-order filter of :data:`PX4_FILTER_TIME_S`, started
    at the first angle)."""
    step = float(np.median(np.diff(time_s))) if time_s is not None and len(time_s) > 1 else 0.1
    a = float(np.exp(-max(step, 1e-6) / PX4_FILTER_TIME_S))
    return scipy.signal.lfilter([1.0 - a], [1.0, -a], angle, zi=[a * angle[0]])[0]


def pair_figures(bi, bj, time_s=None, n_blocks=N_BLOCKS) -> PairFigures:
    """The firmware checks' figures of compass ``j``'s field ``bj`` against compass ``i``'s ``bi`` (N, 3) nT, body
    frame; ``time_s`` (N,) for PX4's filter and the blocks in time."""
    ang = angle_deg(bi, bj)
    xy_ang = angle_deg(bi[:, :2], bj[:, :2])
    xy_len = np.linalg.norm(bi[:, :2] - bj[:, :2], axis=1)
    dtot = np.linalg.norm(bj, axis=1) - np.linalg.norm(bi, axis=1)
    refused_ap = (ang > ARDUPILOT_MAX_XYZ_ANGLE_DEG) | (xy_ang > ARDUPILOT_MAX_XY_ANGLE_DEG)
    refused_ap |= xy_len > ARDUPILOT_MAX_XY_LENGTH_nT
    filtered = _px4_filtered(np.nan_to_num(ang), time_s)
    n = len(ang)
    k = max(1, min(n_blocks, n // 5))
    edges = np.linspace(0, n, k + 1).astype(int)
    where = np.arange(n, dtype=float) if time_s is None else np.asarray(time_s, dtype=float)
    blocks = {
        "t_mid_s" if time_s is not None else "sample_mid": [
            float(np.mean(where[a:b])) for a, b in zip(edges, edges[1:])
        ],
        "angle_deg": [float(np.nanmedian(ang[a:b])) for a, b in zip(edges, edges[1:])],
        "total_diff_nT": [float(np.nanmedian(dtot[a:b])) for a, b in zip(edges, edges[1:])],
    }
    return PairFigures(
        Spread.of(ang),
        Spread.of(xy_ang),
        Spread.of(xy_len),
        Spread.of(dtot, signed=True),
        {"ardupilot": float(np.mean(refused_ap)), "px4": float(np.mean(filtered > PX4_MAX_ANGLE_DEG))},
        float(np.max(filtered)),
        blocks,
    )


# -- the causes ----------------------------------------------------------------------------------------------------
def _widening(resid) -> float:
    """``sqrt((1 + r) / (1 - r))`` for the largest lag-1 correlation ``r`` of the residual components (>= 1)."""
    a = resid - resid.mean(axis=0)
    den = np.sum(a * a, axis=0)
    ok = den > 0
    if a.shape[0] < 3 or not ok.any():
        return 1.0
    r = float(np.clip(np.max(np.sum(a[1:] * a[:-1], axis=0)[ok] / den[ok]), 0.0, 0.9999))
    return float(np.sqrt(min((1.0 + r) / (1.0 - r), len(a))))


def _significance(theta, cov) -> float:
    """``sqrt(theta^T cov^-1 theta / q)``: how many standard errors a q-vector is from zero."""
    try:
        return float(np.sqrt(max(theta @ np.linalg.solve(cov, theta), 0.0) / len(theta)))
    except np.linalg.LinAlgError:
        return 0.0


def _rotation_text(rotvec_deg) -> str:
    angle = float(np.linalg.norm(rotvec_deg))
    axis = rotvec_deg / angle if angle > 0 else np.zeros(3)
    return f"{angle:.2f} deg about body ({axis[0]:+.2f}, {axis[1]:+.2f}, {axis[2]:+.2f})"


def _cross_columns(b) -> np.ndarray:
    """(N, 3, 3): the columns of ``omega -> omega x b`` for each row of ``b`` (a small rotation's Jacobian)."""
    out = np.zeros((len(b), 3, 3))
    out[:, 0, 1], out[:, 0, 2] = b[:, 2], -b[:, 1]
    out[:, 1, 0], out[:, 1, 2] = -b[:, 2], b[:, 0]
    out[:, 2, 0], out[:, 2, 1] = b[:, 1], -b[:, 0]
    return out


def _symmetric_columns(b) -> np.ndarray:
    """(N, 3, 6): the columns of ``S -> S b`` for a symmetric ``S`` (xx, yy, zz, xy, xz, yz)."""
    out = np.zeros((len(b), 3, 6))
    for k in range(3):
        out[:, k, k] = b[:, k]
    for k, (a, c) in enumerate(((0, 1), (0, 2), (1, 2))):
        out[:, a, 3 + k] = b[:, c]
        out[:, c, 3 + k] = b[:, a]
    return out


def _linear_fit(blocks, d):
    """Least squares of ``d`` (N, 3) on the named column blocks ``{name: (N, 3, q)}``: ``(theta by name, the
    fitted (N, 3), the residual sum of squares, the design (3N, p), the slices by name)``."""
    names = list(blocks)
    slices, k = {}, 0
    for name in names:
        q = blocks[name].shape[2]
        slices[name] = slice(k, k + q)
        k += q
    X = np.concatenate([blocks[name] for name in names], axis=2).reshape(3 * len(d), k)
    scale = np.linalg.norm(X, axis=0)
    scale[scale == 0] = 1.0
    xs = X / scale  # the normal equations of the equilibrated columns (a few columns, many rows: far faster than
    theta = np.linalg.lstsq(xs.T @ xs, xs.T @ d.reshape(-1), rcond=1e-13)[0] / scale  # an SVD of the tall matrix)
    fitted = (X @ theta).reshape(d.shape)
    return {n: theta[sl] for n, sl in slices.items()}, fitted, float(np.sum((d - fitted) ** 2)), X, slices


def _covariance(X, resid, rss, slices) -> dict:
    """Each term's covariance from a least-squares fit (design ``X``, residuals (N, 3)), widened for residuals
    correlated in time (:func:`_widening`)."""
    s2 = rss / max(X.shape[0] - X.shape[1], 1)
    cov = s2 * np.linalg.pinv(X.T @ X) * _widening(resid) ** 2
    return {name: cov[sl, sl] for name, sl in slices.items()}


def regress_terms(base, d, channels=None, rate=None):
    """Least squares of a difference ``d`` (N, 3) on a constant, a linear function of the field ``base`` (N, 3),
    the channels and the rate, with each term's share of ``sum |d|^2`` (:func:`_shapley_shares`).

    Returns a dict: ``theta`` (by term), ``fitted``, ``resid``, ``cov`` (by term, widened for correlated
    residuals), ``share`` (by term), ``separable`` (the rotation and the stretch of the linear part are determined
    to :data:`MAX_ROTATION_SD_DEG` and :data:`MAX_STRETCH_SD`, so that the constant is an offset; else the terms are
    ``constant`` and ``direction``, about the mean field), ``mean_base``."""
    n = len(d)
    mean_b = base.mean(axis=0)
    eye = np.broadcast_to(np.eye(3), (n, 3, 3))
    extra = {}
    for name, (u, _) in (channels or {}).items():
        uc = np.asarray(u, dtype=float) - float(np.mean(u))
        extra[name] = uc[:, None, None] * np.eye(3)[None]
    if rate is not None:
        extra["timing"] = (rate - rate.mean(axis=0))[:, :, None]
    # first about the mean field: a constant and the direction part, which are orthogonal to each other
    centred = {"constant": eye, "rotation": _cross_columns(base - mean_b), "stretch": _symmetric_columns(base - mean_b)}
    theta, fitted, rss, X, slices = _linear_fit({**centred, **extra}, d)
    cov = _covariance(X, d - fitted, rss, slices)
    rot_sd = np.degrees(np.sqrt(np.clip(np.diag(cov["rotation"]), 0.0, None)))
    str_sd = np.sqrt(np.clip(np.diag(cov["stretch"]), 0.0, None))
    separable = bool(np.max(rot_sd) < MAX_ROTATION_SD_DEG and np.max(str_sd) < MAX_STRETCH_SD)
    if separable:  # the same fit with the field uncentred: its constant is the offset at zero field
        blocks = {"offset": eye, "rotation": _cross_columns(base), "stretch": _symmetric_columns(base), **extra}
    else:
        blocks = {"constant": eye, "direction": np.concatenate([centred["rotation"], centred["stretch"]], axis=2)}
        blocks.update(extra)
    theta, fitted, rss, X, slices = _linear_fit(blocks, d)
    cov = _covariance(X, d - fitted, rss, slices)  # a term's marginal covariance does not depend on the centring
    return {
        "theta": theta,
        "fitted": fitted,
        "resid": d - fitted,
        "cov": cov,
        "share": _shapley_shares(X, d.reshape(-1), slices),
        "separable": separable,
        "mean_base": mean_b,
        "blocks": blocks,
    }


def _shapley_shares(X, y, slices) -> dict:
    """Each term's share of ``sum y^2`` that the fit explains, split among terms that overlap (a constant and a
    scale both move the mean field; a current that follows the attitude and a mounting) by their Shapley values:
    the explained sum of squares a term adds, averaged over the orders in which the terms could be added. The
    shares add up to the fit's R^2 (about ``sum y^2``). Every subset is solved from the one Gram matrix."""
    names = list(slices)
    m = len(names)
    gram, xty, tss = X.T @ X, X.T @ y, float(y @ y)
    if tss <= 0:
        return dict.fromkeys(names, 0.0)
    explained = {}
    for mask in range(1 << m):
        cols = np.array(
            [c for k, n in enumerate(names) if mask >> k & 1 for c in range(slices[n].start, slices[n].stop)], dtype=int
        )
        if cols.size == 0:
            explained[mask] = 0.0
            continue
        sub = np.sqrt(np.diag(gram)[cols])
        sub[sub == 0] = 1.0
        b = xty[cols] / sub
        explained[mask] = float(b @ np.linalg.lstsq(gram[np.ix_(cols, cols)] / np.outer(sub, sub), b, rcond=1e-13)[0])
    weight = [math.factorial(k) * math.factorial(m - k - 1) / math.factorial(m) for k in range(m)]
    share = {}
    for k, name in enumerate(names):
        total = 0.0
        for mask in range(1 << m):
            if mask >> k & 1:
                continue
            total += weight[bin(mask).count("1")] * (explained[mask | 1 << k] - explained[mask])
        share[name] = max(total, 0.0) / tss
    return share


def explain_difference(bi, bj, channels=None, rate=None, labels=("i", "j")) -> tuple[list, float]:
    """Name what the difference ``bj - bi`` (N, 3, nT) follows: :func:`regress_terms`, each term described.

    Parameters
    ----------
    bi, bj : numpy.ndarray, shape (N, 3)
        The two compasses' fields, nT.
    channels : dict of str to (numpy.ndarray, str), optional
        Per channel name (``current_A``, ``throttle``, ``temperature_C``): its values (N,) and unit.
    rate : numpy.ndarray, shape (N, 3), optional
        ``dB_i/dt`` (nT/s), for a delay between the two compasses.
    labels : tuple of str
        How the texts call compass i and compass j.

    Returns
    -------
    causes : list of Cause
        Every term, largest share first (``named``: a share of at least :data:`MIN_SHARE` and
        :data:`MIN_SIGNIFICANCE` standard errors).
    residual_rms_nT : float
        RMS of what the terms leave.
    """
    d = bj - bi
    fit = regress_terms(bi, d, channels, rate)
    causes = _separable_causes(fit, bi, labels) if fit["separable"] else _constant_causes(fit, channels)
    causes += _channel_causes(fit, bi, d, channels, labels)
    causes += _timing_causes(fit, labels)
    total = _rms(d)
    for c in causes:  # named when its share and its own size both count, and it is significant
        own = (c.rms_nT / total) ** 2 if total > 0 else 0.0
        c.named = min(c.share, own) >= MIN_SHARE and c.significance >= MIN_SIGNIFICANCE
    causes.sort(key=lambda c: -c.share)
    return causes, _rms(fit["resid"])


def _rms(vec) -> float:
    """RMS length of the rows of ``vec`` (N, 3), nT."""
    return float(np.sqrt(np.mean(np.sum(vec * vec, axis=1))))


def _part(fit, name) -> np.ndarray:
    """The part (N, 3, nT) of the difference that term ``name`` of :func:`regress_terms`' ``fit`` explains."""
    return np.einsum("njk,k->nj", fit["blocks"][name], fit["theta"][name])


def _separable_causes(fit, bi, labels) -> list:
    """(:func:`explain_difference`, where the directions flown separate them.) The mounting, scale and offset
    between compass i's fields ``bi`` (N, 3, nT) and compass j's."""
    theta = fit["theta"]
    li, lj = labels
    causes = []
    omega = theta["rotation"]
    rotvec = np.degrees(omega)
    stretch = np.array(
        [
            [theta["stretch"][0], theta["stretch"][3], theta["stretch"][4]],
            [theta["stretch"][3], theta["stretch"][1], theta["stretch"][5]],
            [theta["stretch"][4], theta["stretch"][5], theta["stretch"][2]],
        ]
    )
    eig = np.linalg.eigvalsh(stretch)
    med_angle = float(np.median(angle_deg(bi, Rotation.from_rotvec(omega).apply(bi))))
    causes.append(
        _block_cause(
            fit,
            "mounting",
            "rotation",
            {
                "mounting_rotvec_deg": -rotvec,
                "field_rotvec_deg": rotvec,
                "angle_deg": float(np.linalg.norm(rotvec)),
                "median_field_angle_deg": med_angle,
            },
            f"mounting: compass {lj} is turned {_rotation_text(-rotvec)} relative to compass {li} (its field, "
            f"read in the body frame, turned back as much: a constant {med_angle:.2f} deg between the fields for "
            "the directions flown)",
        )
    )
    causes.append(
        _block_cause(
            fit,
            "scale",
            "stretch",
            {"stretch_percent": (100 * eig).tolist()},
            f"scale: their scales differ by up to {100 * float(np.max(np.abs(eig))):.2f} % along some direction "
            "(soft iron near one, or a scale calibration)",
        )
    )
    offset = theta["offset"]
    causes.append(
        _block_cause(
            fit,
            "offset",
            "offset",
            {"offset_nT": offset},
            f"offset: a constant ({offset[0]:.0f}, {offset[1]:.0f}, {offset[2]:.0f}) nT "
            f"(|{np.linalg.norm(offset):.0f}| nT: hard iron near one compass, or offsets one calibration left)",
            size_nT=float(np.linalg.norm(offset)),
        )
    )
    return causes


def _block_cause(fit, kind, block, values, text, size_nT=None) -> Cause:
    """A cause of the kind ``kind`` from the term ``block`` of the difference's regression ``fit``: the share of
    the difference it accounts for, its size (``size_nT``, default the RMS of its part, nT), the significance of
    its estimate, its values and words; named or not by :func:`explain_difference`."""
    size = _rms(_part(fit, block)) if size_nT is None else size_nT
    return Cause(
        kind, fit["share"][block], size, _significance(fit["theta"][block], fit["cov"][block]), False, values, text
    )


def _constant_causes(fit, channels) -> list:
    """(:func:`explain_difference`, where the directions flown do not separate them.) The constant difference (its
    angle and |B|, at zero current too) and the part that changes with the field's direction."""
    theta = fit["theta"]
    causes = []
    d0 = theta["constant"]
    mean_b = fit["mean_base"]
    ang0 = float(angle_deg(mean_b[None], (mean_b + d0)[None])[0])
    dtot0 = float(np.linalg.norm(mean_b + d0) - np.linalg.norm(mean_b))
    values = {"offset_nT": d0, "angle_deg": ang0, "total_diff_nT": dtot0}
    text = (
        f"constant: ({d0[0]:.0f}, {d0[1]:.0f}, {d0[2]:.0f}) nT, {ang0:.2f} deg and {dtot0:+.0f} nT of |B| at the "
        "mean field"
    )
    zero = [name for name in channels or {} if name in CURRENT_COLUMNS]
    if zero:  # a current has a natural zero: the difference with the motors off
        name = zero[0]
        d_off = d0 - theta[name] * float(np.mean(channels[name][0]))
        ang_off = float(angle_deg(mean_b[None], (mean_b + d_off)[None])[0])
        values.update(zero_current_offset_nT=d_off, zero_current_angle_deg=ang_off)
        text += f" ({ang_off:.2f} deg at zero {name})"
    causes.append(
        _block_cause(
            fit,
            "constant",
            "constant",
            values,
            text + ": a mounting off by that angle, or an offset (hard iron); the directions flown cannot tell "
            "them apart",
            size_nT=float(np.linalg.norm(d0)),
        )
    )
    causes.append(
        _block_cause(
            fit,
            "direction",
            "direction",
            {},
            "direction: a part that changes with the field's direction (a scale, soft-iron or mounting difference "
            "the directions flown do not separate)",
        )
    )
    return causes


def _channel_causes(fit, bi, d, channels, labels) -> list:
    """(:func:`explain_difference`.) Per channel (current, throttle, temperature) the part of the difference ``d``
    (N, 3, nT) that follows it: per unit, as an angle and as |B|, over the record's range."""
    theta = fit["theta"]
    li, lj = labels
    causes = []
    bhat = bi / np.linalg.norm(bi, axis=1)[:, None]
    mean_field = float(np.mean(np.linalg.norm(bi, axis=1)))
    for name, (u, unit) in (channels or {}).items():
        kvec = theta[name]
        uc = np.asarray(u, dtype=float) - float(np.mean(u))
        deg_per = float(np.degrees(np.sqrt(np.mean(np.sum(np.cross(bhat, kvec) ** 2, axis=1))) / mean_field))
        db_per = float(np.mean(bhat @ kvec))
        along = d @ (kvec / max(float(np.linalg.norm(kvec)), 1e-12))
        r = float(np.corrcoef(along, uc)[0, 1]) if np.std(uc) > 0 and np.std(along) > 0 else 0.0
        span = float(np.ptp(u))
        kind = "temperature" if name == "temperature_C" else name
        what = {"current_A": "the current (current_A)", "throttle": "the throttle", "temperature_C": "the temperature"}
        causes.append(
            _block_cause(
                fit,
                kind,
                name,
                {
                    "column": name,
                    "per_unit_nT": kvec,
                    "per_unit_abs_nT": float(np.linalg.norm(kvec)),
                    "angle_deg_per_unit": deg_per,
                    "total_diff_nT_per_unit": db_per,
                    "correlation": r,
                    "range": [float(np.min(u)), float(np.max(u))],
                },
                f"{kind}: the difference follows {what.get(name, name)} (r = {r:.2f}): compass {lj}'s field differs "
                f"from compass {li}'s by ({kvec[0]:.1f}, {kvec[1]:.1f}, {kvec[2]:.1f}) nT per {unit} "
                f"(|{np.linalg.norm(kvec):.1f}| nT per {unit}): {deg_per:.3f} deg of angle and {db_per:+.1f} nT of "
                f"|B| per {unit}; over this record's {np.min(u):.3g}-{np.max(u):.3g} {unit} up to "
                f"{deg_per * span:.2f} deg",
            )
        )
    return causes


def _timing_causes(fit, labels) -> list:
    """(:func:`explain_difference`.) A delay between the two compasses: the part of the difference that follows the
    field's rate (when it was regressed)."""
    theta, cov, share = fit["theta"], fit["cov"], fit["share"]
    li, lj = labels
    causes = []
    if "timing" in fit["blocks"]:
        tau = float(theta["timing"][0])
        sd = float(np.sqrt(max(float(cov["timing"][0, 0]), 0.0)))
        causes.append(
            Cause(
                "timing",
                share["timing"],
                _rms(_part(fit, "timing")),
                abs(tau) / max(sd, 1e-12),
                False,
                {"delay_ms": 1e3 * tau, "sd_ms": 1e3 * sd},
                f"timing: the difference follows the field's rate (turns): compass {lj} reads the field of "
                f"{1e3 * tau:+.0f} ms later than compass {li} (a sampling delay between them, or eddy currents near "
                "one)",
            )
        )
    return causes


# -- per compass, against the reference field ----------------------------------------------------------------------
def _spread_evenly(n) -> np.ndarray:
    """Indices of at most :data:`MAX_REGRESSION_SAMPLES` of ``n`` samples, evenly spread."""
    if n <= MAX_REGRESSION_SAMPLES:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, MAX_REGRESSION_SAMPLES).astype(int))


def _sensitivities(fields, keep, rotation, ned, u, state, compensated=None) -> list:
    """Each compass's residual ``B_s - R(q)^T B_ned`` regressed on a constant, a linear function of the reference
    field (what a calibration of the field ``fields`` still lacks) and the channel ``u``: the field per unit of
    ``u`` each compass sees (on at most :data:`MAX_REGRESSION_SAMPLES` of the ``keep`` samples)."""
    where = np.flatnonzero(keep)
    some = _spread_evenly(len(where))
    rotation, keep = rotation[some], np.zeros_like(keep)
    keep[where[some]] = True
    body_ref = rotation.inv().apply(ned[keep])
    channel = {"u": (u[keep], "unit")}
    out = []
    for s, f in enumerate(fields):
        fit = regress_terms(body_ref, f[keep] - body_ref, channel)
        k = fit["theta"]["u"]
        sd = np.sqrt(np.clip(np.diag(fit["cov"]["u"]), 0.0, None))
        out.append(Sensitivity(s, state, k, sd, None if compensated is None else compensated[s]))
    totals = [float(np.linalg.norm(x.total_nT)) for x in out]
    big = max(totals, default=0.0)
    for x, tot in zip(out, totals):
        x.sees = big > 0 and tot >= 0.3 * big and tot >= MIN_SIGNIFICANCE * float(np.linalg.norm(x.sd_nT))
    return out


# -- the whole ----------------------------------------------------------------------------------------------------
def before_fields(dataset: Dataset, calibration: Calibration | None = None) -> tuple[np.ndarray | None, str]:
    """The compasses' fields before a calibration (n_sensors, N, 3), nT, and what they are.

    The flight controller's own calibration of the time when the log kept it (the channels of
    :func:`magcal.data.logs.logged_field_columns`); otherwise, for a vector calibration, each raw reading turned by
    the right angle nearest its fitted mounting (what a firmware with only its orientation parameter set would
    compare); otherwise the raw readings."""
    names = [logged_field_columns(s) for s in range(dataset.n_sensors)]
    if all(all(c in dataset.extra for c in cols) for cols in names):
        fields = np.stack([np.column_stack([dataset.extra[c] for c in cols]) for cols in names]).astype(float)
        return fields, "the flight controller's calibration of the time (the logged field, s1x_logged..)"
    if calibration is not None and calibration.mode == "vector":
        turned = [dataset.readings_nT[s] @ nearest_right_angle(cal.R)[0].T for s, cal in enumerate(calibration.sensors)]
        return (
            np.stack(turned),
            "raw readings in the right-angle orientation nearest each fitted mounting (no calibration)",
        )
    return np.array(dataset.readings_nT, dtype=float), "raw readings (no calibration)"


def _mountings(calibration) -> list:
    """(:func:`compass_consistency`.) Per compass of a vector calibration its mounting: the nearest right angle, the
    angle off it (deg) and that turn (rotation vector, body frame, deg), its standard deviation (deg), whether the
    record determines it."""
    mountings = []
    for s, cal in enumerate(calibration.sensors):
        right, off = nearest_right_angle(cal.R)
        turn = Rotation.from_matrix(cal.R @ right.T).as_rotvec()
        sd = (cal.summary or {}).get("mounting_sd_deg")
        mountings.append(
            {
                "sensor": s + 1,
                "right_angle": describe_right_angle(right).split(":")[0],
                "angle_off_deg": float(off),
                "off_rotvec_body_deg": np.degrees(turn),
                "mounting_sd_deg": float(np.linalg.norm(sd)) if sd is not None else 0.0,
                "determined": bool((cal.summary or {}).get("determined", True)),
            }
        )
    return mountings


def _add_mounting_causes(pairs, mountings, before, idx) -> None:
    """(:func:`compass_consistency`.) To each pair's causes before, the relative mounting of its compasses off the
    right angles (``mountings``: :func:`_mountings`; ``before``: the fields before, nT; ``idx``: the samples
    compared), re-ranked."""
    for p in pairs:  # the relative mounting off the right angles: what a firmware's orientation cannot hold
        di = Rotation.from_rotvec(np.radians(mountings[p.i]["off_rotvec_body_deg"]))
        dj = Rotation.from_rotvec(np.radians(mountings[p.j]["off_rotvec_body_deg"]))
        mount = np.degrees((dj * di.inv()).as_rotvec())  # compass j's mounting relative to compass i's, body
        turn = dj.inv() * di  # what that does to compass j's field against compass i's
        bi = before[p.i][idx]
        vec = turn.apply(bi) - bi
        size = float(np.sqrt(np.mean(np.sum(vec * vec, axis=1))))
        share = (size / p.rms_before_nT) ** 2 if p.rms_before_nT > 0 else 0.0
        med = float(np.median(angle_deg(bi, turn.apply(bi))))
        sd = float(np.hypot(mountings[p.i]["mounting_sd_deg"], mountings[p.j]["mounting_sd_deg"]))
        significance = float(np.linalg.norm(mount) / sd) if sd > 0 else float("inf")
        determined = mountings[p.i]["determined"] and mountings[p.j]["determined"]
        p.causes_before.append(
            Cause(
                "mounting_fit",
                share,
                size,
                significance if determined else 0.0,
                bool(determined and share >= MIN_SHARE and significance >= MIN_SIGNIFICANCE),
                {
                    "mounting_rotvec_deg": mount,
                    "angle_deg": float(np.linalg.norm(mount)),
                    "median_field_angle_deg": med,
                },
                f"mounting (the calibration's): compass {p.j + 1} sits {mountings[p.j]['angle_off_deg']:.2f} deg "
                f"off its right angle and compass {p.i + 1} {mountings[p.i]['angle_off_deg']:.2f} deg; compass "
                f"{p.j + 1} is turned {_rotation_text(mount)} relative to compass {p.i + 1}, which no right-angle "
                f"orientation holds ({med:.2f} deg between the fields for the directions flown); the calibration's "
                "mounting turns it out",
            )
        )
        p.causes_before.sort(key=lambda c: -c.share)


def compass_consistency(
    dataset: Dataset,
    calibration: Calibration,
    before=None,
    before_source=None,
    reference=None,
    mask=None,
    after_source="this calibration",
) -> CompassConsistency:
    """The consistency of two to four compasses on one vehicle, before and after ``calibration``.

    Parameters
    ----------
    dataset : Dataset
        Two or more sensors (compasses), with their channels (``time_s``, ``current_A`` or ``throttle``,
        ``temperature_C``, the attitude).
    calibration : Calibration
        The calibration whose corrected fields are "after" (body frame for a vector calibration).
    before : numpy.ndarray, shape (n_sensors, N, 3), optional
        The fields "before" (nT, body frame); default :func:`before_fields`. ``before_source`` says what they are.
    reference : VectorReference or numpy.ndarray (N, 3), optional
        The Earth's field (nT, north-east-down): with the attitude, each compass's own sensitivity to the current.
    mask : numpy.ndarray of bool, shape (N,), optional
        The samples compared (e.g. the vector fit's ``fitted``); samples where a field is not finite are left out.
    after_source : str
        What the calibration is, for the report.

    Raises
    ------
    MagcalError
        Fewer than two sensors, or fewer than :data:`MIN_SAMPLES` samples to compare.
    """
    if dataset.n_sensors < 2:
        raise MagcalError(
            f"{dataset.source or 'data'}: the consistency of compasses needs two or more; the record has one"
        )
    after, before, before_source = _fields_compared(dataset, calibration, before, before_source)
    keep, column, temp = _samples_compared(dataset, after, before, mask)
    n = int(keep.sum())
    idx = np.flatnonzero(keep)
    time_s = None if dataset.time_s is None else np.asarray(dataset.time_s, dtype=float)[idx]
    channels, notes = _channels_compared(dataset, column, temp, idx, time_s)
    pairs = [
        _pair_consistency(i, j, before, after, idx, time_s, channels)
        for i in range(dataset.n_sensors)
        for j in range(i + 1, dataset.n_sensors)
    ]
    mountings = _mountings(calibration) if calibration.mode == "vector" else []
    if mountings:
        _add_mounting_causes(pairs, mountings, before, idx)
    sensitivities = []
    if column is not None and column in channels:
        sensitivities = _current_sensitivities(dataset, calibration, reference, column, keep, before, after)
    return CompassConsistency(
        dataset.n_sensors,
        n,
        before_source,
        after_source,
        column if column in channels else None,
        pairs,
        sensitivities,
        mountings,
        notes,
    )


def _fields_compared(dataset, calibration, before, before_source) -> tuple:
    """(Part of :func:`compass_consistency`.) The fields after ``calibration`` and before it (given, or
    :func:`before_fields`), (n_sensors, N, 3) nT each, and what the fields before are."""
    after = np.asarray(calibration.correct(dataset, warn=False, force=True), dtype=float)
    if before is None:
        before, what = before_fields(dataset, calibration)
        return after, before, before_source or what
    before = np.asarray(before, dtype=float)
    if before.shape != after.shape:
        raise MagcalError(f"the fields before have shape {before.shape}; the record's are {after.shape}")
    return after, before, before_source or "given"


def _samples_compared(dataset, after, before, mask) -> tuple:
    """(Part of :func:`compass_consistency`.) The samples compared (``mask``, where every field and the current
    are finite, and the temperature when it changes by more than :data:`MIN_TEMPERATURE_RANGE_C`), the current's
    column (or None) and the temperature (degC, None when it is not compared)."""
    keep = np.ones(dataset.n_samples, bool) if mask is None else np.asarray(mask, dtype=bool).copy()
    keep &= np.all(np.isfinite(after), axis=(0, 2)) & np.all(np.isfinite(before), axis=(0, 2))
    column = current_column(dataset)
    if column is not None:
        keep &= np.isfinite(np.asarray(dataset.extra[column], dtype=float))
    temp = None if dataset.temperature_C is None else np.asarray(dataset.temperature_C, dtype=float)
    if temp is not None:
        known = keep & np.isfinite(temp)
        if known.any() and np.ptp(temp[known]) > MIN_TEMPERATURE_RANGE_C:
            keep = known
        else:
            temp = None
    n = int(keep.sum())
    if n < MIN_SAMPLES:
        raise MagcalError(
            f"{dataset.source or 'data'}: only {n} samples have every compass's field (and the channels compared); "
            f"the consistency of compasses needs at least {MIN_SAMPLES}"
        )
    return keep, column, temp


def _channels_compared(dataset, column, temp, idx, time_s) -> tuple[dict, list]:
    """(Part of :func:`compass_consistency`.) The channels a difference is regressed on at the samples ``idx``
    (name -> (values, unit)): the current when it changes, the temperature; and the notes on what they cannot
    tell."""
    channels: dict = {}
    notes: list = []
    if column is not None:
        u = np.asarray(dataset.extra[column], dtype=float)[idx]
        if np.ptp(u) > 0:
            channels[column] = (u, CURRENT_COLUMNS[column])
        else:
            notes.append(f"{column} does not change over the samples compared: its field cannot be told from an offset")
    if temp is not None:
        channels["temperature_C"] = (temp[idx], "degC")
        if time_s is not None and np.std(time_s) > 0:
            r = float(np.corrcoef(temp[idx], time_s)[0, 1])
            if abs(r) > 0.9:
                notes.append(
                    f"the temperature follows time (r = {r:.2f}): a term following it could as well be a drift"
                )
    return channels, notes


def _pair_consistency(i, j, before, after, idx, time_s, channels) -> PairConsistency:
    """(Part of :func:`compass_consistency`.) Compasses ``i`` and ``j`` (0-based) compared at the samples ``idx``,
    before and after: their figures, the causes of their difference, its RMS (nT) and what the causes leave."""
    out = {}
    for state, fields in (("before", before), ("after", after)):
        bi, bj = fields[i][idx], fields[j][idx]
        rate = None
        if time_s is not None and len(time_s) >= 7 and np.all(np.diff(time_s) > 0):
            rate = time_derivative(bi, time_s)
        some = _spread_evenly(len(bi))
        causes, resid = explain_difference(
            bi[some],
            bj[some],
            {k: (v[some], unit) for k, (v, unit) in channels.items()},
            None if rate is None else rate[some],
            labels=(str(i + 1), str(j + 1)),
        )
        d = bj - bi
        out[state] = (pair_figures(bi, bj, time_s), causes, float(np.sqrt(np.mean(np.sum(d * d, axis=1)))), resid)
    (fig_b, causes_b, rms_b, resid_b), (fig_a, causes_a, rms_a, resid_a) = out["before"], out["after"]
    return PairConsistency(i, j, fig_b, fig_a, causes_b, causes_a, rms_b, rms_a, resid_b, resid_a)


def _current_sensitivities(dataset, calibration, reference, column, keep, before, after) -> list:
    """(Part of :func:`compass_consistency`.) Each compass's own sensitivity to the current before and after (the
    calibration's current term taken out), with the attitude and the Earth's field ``reference``; empty without
    them or with fewer than :data:`MIN_SAMPLES` samples that have both."""
    rows = attitude_rows(dataset)
    ned = getattr(reference, "ned_nT", reference)
    if rows is None or ned is None:
        return []
    rotation, have = rows
    ned = np.asarray(ned, dtype=float)
    use = keep & have & np.all(np.isfinite(ned), axis=1)
    if use.sum() < MIN_SAMPLES:
        return []
    rot_use = rotation[np.flatnonzero(use)]
    u_all = np.asarray(dataset.extra[column], dtype=float)
    out = _sensitivities(before, use, rot_use, ned, u_all, "before")
    comp = None
    k_all, columns = current_term(calibration)
    if k_all is not None and all(c in (None, column) for c in columns):
        comp = [(cal.R @ cal.cinv) @ np.asarray(k, dtype=float) for cal, k in zip(calibration.sensors, k_all)]
    return out + _sensitivities(after, use, rot_use, ned, u_all, "after", comp)
