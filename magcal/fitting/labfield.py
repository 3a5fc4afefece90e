"""The field of a lab, fitted with a vector calibration, and its gradient along the path.

A lab (motion capture, a turntable, a coil) has a constant field ``B_w`` whose vector nobody measured. With the
attitude ``Q_t`` (body -> north-east-down) it is fitted with the calibration (:func:`magcal.fitting.vector.fit_vector`
with ``reference="fitted"``)::

    y = C R^T Q_t^T B(p_t) + b + ...,       B(p) = B_w + G (p - p0)

Two things no record of a sensor alone fixes, each a *gauge* the fit has to set and the report names:

* ``|B_w|`` against the sensor's overall gain: ``(C^-1, B_w) -> (k C^-1, k B_w)`` fits the same readings. A total
  field given (a ``ref_total`` column, ``reference_total_nT``) fixes it; otherwise ``det C^-1 = 1`` for sensor 1,
  the fitters' gauge, and ``|B_w|`` is then as good as the sensor's nominal gain.
* a rotation of ``B_w`` about an axis every attitude of the record turned about is absorbed by the mounting ``R``:
  a record turned about the vertical only leaves the declination against the mounting's yaw. Found from the Fisher
  information of the field's direction with every calibration parameter profiled out (its Schur complement); a
  direction whose standard deviation exceeds :data:`UNDETERMINED_DIRECTION_DEG`, or the declination of a record
  whose turns moved the vertical by less than :data:`YAW_ONLY_TILT_DEG`, is fixed (the declination at the one given, else 0) and the
  report says so.

A field that is not uniform (a magnet, steel, a computer near the path). With positions (``pos_n_m, pos_e_m,
pos_d_m``, m, north-east-down, or ``lat, lon, alt_m``), ``G`` is a gradient tensor, symmetric and traceless in free
space (5 parameters, :data:`magcal.model.operators.GRADIENT_BASIS`, as the ``site_gradient`` effect), fitted with the
field: it belongs to the record and the place, never to the instrument, so the calibration's terms (the sensor's
bias, matrix and mounting) are what :func:`magcal.output.apply` carries; the gradient stays in the calibration file's
``lab_field`` as a record-only figure.

The joint solve takes the per-sensor problems of the vector fit (their residuals weighted by the total-field and
perpendicular noises, their Jacobians) and adds the field's columns: the sensors share one field.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from magcal.fitting.solver import correlated_covariance, weighted_least_squares
from magcal.model.operators import GRADIENT_BASIS

#: Position columns in the world frame: north, east, down (m) from any origin in the lab.
POSITION_NED_COLUMNS = ("pos_n_m", "pos_e_m", "pos_d_m")

#: A direction of the field whose standard deviation (deg, with the calibration profiled out) exceeds this is not
#: determined by the record's attitudes: it is fixed, and the report says so.
UNDETERMINED_DIRECTION_DEG = 2.0

#: A record whose turns move the vertical by less than this (deg) turned about the vertical only: the field's
#: declination is then a gauge (the mounting's yaw takes it), whatever the information says (with so little tilt
#: its standard deviation from the covariance is not to be trusted: the fit is far from linear along it). A record
#: whose attitudes all lie within this of their mean barely turned: nothing is fitted.
YAW_ONLY_TILT_DEG = 15.0

#: Mean Earth radius (m), for positions given as latitude and longitude (a flat patch about their mean).
EARTH_RADIUS_M = 6_371_000.0

#: Most rounds of the joint solve (each rebuilds the perpendicular directions and the noise weights).
MAX_ROUNDS = 3


def positions_ned_m(dataset) -> np.ndarray | None:
    """The samples' positions (N, 3) in m, north-east-down, or None when the data hold none.

    From ``pos_n_m, pos_e_m, pos_d_m`` (a motion-capture system's, in the lab's frame), else ``lat, lon`` (deg) and
    ``alt_m`` (m, optional) turned into metres on a flat patch about their mean. A row without a position is NaN.
    """
    extra = dataset.extra
    if all(c in extra for c in POSITION_NED_COLUMNS):
        cols = [np.asarray(extra[c]) for c in POSITION_NED_COLUMNS]
        if all(c.dtype.kind in "fiu" for c in cols):
            return np.column_stack(cols).astype(float)
    if "lat" in extra and "lon" in extra:
        lat, lon = (np.asarray(extra[c], dtype=float) for c in ("lat", "lon"))
        alt = np.asarray(extra.get("alt_m", np.zeros(len(lat))), dtype=float)
        ok = np.isfinite(lat) & np.isfinite(lon) & np.isfinite(alt)
        if not ok.any():
            return None
        lat0, lon0, alt0 = float(np.mean(lat[ok])), float(np.mean(lon[ok])), float(np.mean(alt[ok]))
        north = np.radians(lat - lat0) * EARTH_RADIUS_M
        east = np.radians(lon - lon0) * EARTH_RADIUS_M * np.cos(np.radians(lat0))
        return np.column_stack([north, east, -(alt - alt0)])
    return None


def turn_span_deg(rotation) -> tuple[float, float]:
    """How far a record's attitudes turned, and how far those turns moved the vertical (deg).

    Each attitude's turn from the mean attitude, ``T_t = Q_t Q_mean^T``, is a rotation in the world frame; a record
    turned about the vertical only (a turntable, a level hand) leaves the vertical where it is (``T_t e_down =
    e_down``), whatever the sensor's own tilt. Returns the largest turn and the largest angle between ``T_t e_down``
    and ``e_down``.
    """
    turns = rotation * rotation.mean().inv()
    down = turns.apply(np.array([0.0, 0.0, 1.0]))
    return float(np.degrees(np.max(turns.magnitude()))), float(
        np.degrees(np.max(np.arccos(np.clip(down[:, 2], -1.0, 1.0))))
    )


def direction(declination_deg, inclination_deg) -> np.ndarray:
    """Unit vector (north, east, down) of a field with this declination and inclination (deg)."""
    d, i = np.radians(declination_deg), np.radians(inclination_deg)
    return np.array([np.cos(i) * np.cos(d), np.cos(i) * np.sin(d), np.sin(i)])


def angles_deg(ned) -> tuple[float, float]:
    """Declination and inclination (deg) of a field vector (north, east, down)."""
    n, e, d = (float(v) for v in ned)
    return float(np.degrees(np.arctan2(e, n))), float(np.degrees(np.arctan2(d, np.hypot(n, e))))


def _direction_derivatives(declination_deg, inclination_deg) -> np.ndarray:
    """``d direction / d(declination, inclination)`` (3, 2), per radian."""
    d, i = np.radians(declination_deg), np.radians(inclination_deg)
    return np.array(
        [
            [-np.cos(i) * np.sin(d), -np.sin(i) * np.cos(d)],
            [np.cos(i) * np.cos(d), -np.sin(i) * np.sin(d)],
            [0.0, np.cos(i)],
        ]
    )


@dataclass
class FieldSetup:
    """What the joint solve fits of the field, and about which point.

    Attributes
    ----------
    total_nT : float
        ``|B_w|`` held during the solve (the given total field, or a provisional one rescaled afterwards).
    declination_deg, inclination_deg : float
        The field's direction the solve starts from (and keeps along the directions it does not fit).
    free : numpy.ndarray, shape (2, k)
        The directions in (declination, inclination) the solve moves, in radians per unit parameter (k = 2: both;
        1: the one the attitudes determine; 0: none).
    base_ned_nT : numpy.ndarray, shape (N, 3), or None
        A given field per sample (a vector reference): then the direction is not fitted, only the gradient.
    offsets_m : numpy.ndarray, shape (N, 3), or None
        ``p - p0`` (m, north-east-down) of the fitted samples, when the gradient is fitted.
    gradient0 : numpy.ndarray, shape (5,)
        The gradient's parameters (nT/m) the solve starts from; its own are added to them.
    """

    total_nT: float
    declination_deg: float
    inclination_deg: float
    free: np.ndarray
    base_ned_nT: np.ndarray | None = None
    offsets_m: np.ndarray | None = None
    gradient0: np.ndarray = field(default_factory=lambda: np.zeros(5))

    @property
    def n_direction(self) -> int:
        return int(self.free.shape[1]) if self.base_ned_nT is None else 0

    @property
    def n_params(self) -> int:
        return self.n_direction + (5 if self.offsets_m is not None else 0)

    def field_at(self, params) -> np.ndarray:
        """The field (N, 3) or (3,) (north-east-down, nT) at the fitted samples for the field's parameters."""
        params = np.asarray(params, dtype=float)
        k = self.n_direction
        if self.base_ned_nT is not None:
            base = self.base_ned_nT
        else:
            dec, inc = np.array([self.declination_deg, self.inclination_deg]) + np.degrees(self.free @ params[:k])
            base = self.total_nT * direction(dec, inc)
        if self.offsets_m is None:
            return base
        return base + self.offsets_m @ np.tensordot(self.gradient0 + params[k:], GRADIENT_BASIS, axes=1).T

    def field_derivatives(self, params) -> np.ndarray:
        """``dB / dparams`` (N, 3, n_params) at the fitted samples (N = 1 without a gradient)."""
        params = np.asarray(params, dtype=float)
        k = self.n_direction
        cols = []
        if k:
            dec, inc = np.array([self.declination_deg, self.inclination_deg]) + np.degrees(self.free @ params[:k])
            cols.append((self.total_nT * _direction_derivatives(dec, inc) @ self.free)[None])
        if self.offsets_m is not None:
            cols.append(np.stack([self.offsets_m @ g.T for g in GRADIENT_BASIS], axis=-1))
        if not cols:
            return np.zeros((1, 3, 0))
        n = max(c.shape[0] for c in cols)
        return np.concatenate([np.broadcast_to(c, (n, 3, c.shape[2])) for c in cols], axis=2)


class FieldProblem:
    """The sensors' weighted residuals with one shared field: parameters ``[x_1, .., x_S, field]``.

    Each sensor's problem (:class:`magcal.fitting.vector._SensorProblem`) holds its body-frame field ``b_body``, its
    expected total field ``f_ref`` and its perpendicular directions ``p1, p2``; this one sets the first two from the
    field's parameters before every evaluation and adds the field's columns to the Jacobian.
    """

    def __init__(self, problems, sizes, sigmas, rotation, setup: FieldSetup):
        self.problems, self.sizes, self.sigmas = problems, list(sizes), list(sigmas)
        self.rotation, self.setup = rotation, setup
        self.offsets = np.concatenate([[0], np.cumsum(self.sizes)]).astype(int)

    def _split(self, x):
        return [x[a:b] for a, b in zip(self.offsets[:-1], self.offsets[1:])], x[self.offsets[-1] :]

    def _set_field(self, params):
        world = np.broadcast_to(self.setup.field_at(params), (len(self.rotation), 3))
        body = self.rotation.inv().apply(np.array(world))
        total = np.linalg.norm(world, axis=1)
        for prob in self.problems:
            prob.b_body, prob.f_ref = body, total
        return world

    def residuals(self, x):
        xs, params = self._split(x)
        self._set_field(params)
        return np.concatenate([p.residuals(xi, sf, sp) for p, xi, (sf, sp) in zip(self.problems, xs, self.sigmas)])

    def jacobian(self, x):
        xs, params = self._split(x)
        world = self._set_field(params)
        unit = world / np.linalg.norm(world, axis=1)[:, None]
        d_world = self.setup.field_derivatives(params)  # (N or 1, 3, k)
        n, k = len(self.rotation), self.setup.n_params
        d_world = np.broadcast_to(d_world, (n, 3, k))
        inv = self.rotation.inv()
        d_body = np.stack([inv.apply(np.array(d_world[:, :, j])) for j in range(k)], axis=-1) if k else None
        blocks = []
        for s, (prob, xi, (sf, sp)) in enumerate(zip(self.problems, xs, self.sigmas)):
            own = prob.jacobian(xi, sf, sp)
            full = np.zeros((own.shape[0], self.offsets[-1] + k))
            full[:, self.offsets[s] : self.offsets[s + 1]] = own
            if k:
                assert d_body is not None
                j_total = -np.einsum("ni,nik->nk", unit, d_world) / sf
                j_perp = -np.stack(
                    [np.einsum("ni,nik->nk", prob.p1, d_body), np.einsum("ni,nik->nk", prob.p2, d_body)], axis=1
                )
                full[:, self.offsets[-1] :] = np.concatenate([j_total, j_perp.reshape(2 * n, k) / sp])
            blocks.append(full)
        return np.concatenate(blocks)


def weak_directions(jacobian, columns, s2=1.0, widening=1.0):
    """The field direction's standard deviations with every other parameter profiled out.

    Parameters
    ----------
    jacobian : numpy.ndarray, shape (m, p)
        The joint Jacobian.
    columns : sequence of int
        Its columns of the field's direction (two angles on the sphere, rad).
    s2, widening : float
        The residual variance per weighted residual and the widening for correlated residuals.

    Returns
    -------
    sd_deg : numpy.ndarray, shape (k,)
        Standard deviation (deg) along each eigen-direction of the profiled information (its Schur complement),
        weakest first; inf for one the record does not see at all.
    vectors : numpy.ndarray, shape (k, k)
        Those directions in the angles' space, as columns.
    """
    columns = list(columns)
    others = [c for c in range(jacobian.shape[1]) if c not in columns]
    nuisance, fld = jacobian[:, others], jacobian[:, columns]
    coef, *_ = np.linalg.lstsq(nuisance, fld, rcond=None)
    left = fld - nuisance @ coef
    vals, vecs = np.linalg.eigh(left.T @ left)
    top = max(float(np.max(vals)), 1e-300)
    seen = vals > 1e-12 * top
    sd = np.full(len(vals), np.inf)
    sd[seen] = np.degrees(np.sqrt(s2 / vals[seen])) * widening
    return sd, vecs


@dataclass
class LabField:
    """The field a record gave itself (:func:`magcal.fitting.vector.fit_vector` with ``reference="fitted"``).

    Attributes
    ----------
    ned_nT : numpy.ndarray, shape (3,)
        The field ``B_w`` (north, east, down, nT) at ``origin_m`` (the path's mean position) or everywhere when
        uniform.
    sd_nT : numpy.ndarray, shape (3,)
        Its standard deviations (nT) from the joint covariance (widened for residuals correlated in time); a
        component along a gauge has only the statistical part of the others.
    declination_deg, inclination_deg : float
        Its direction (deg); ``declination_sd_deg``, ``inclination_sd_deg`` their standard deviations (0 for one
        fixed by the gauge).
    total_nT, total_sd_nT : float
        ``|B_w|`` and its standard deviation (0 when given).
    total_source : str
        ``given`` (a total field given) or ``gain`` (``det C^-1 = 1`` for sensor 1: the sensor's nominal gain).
    gauges : list of str
        What the record cannot separate and how it was fixed, in words.
    declination_fixed : bool
        True when the declination is a gauge (the attitudes turned about the vertical only).
    gradient_nT_per_m : numpy.ndarray, shape (3, 3), or None
        ``G`` (north-east-down, nT/m) when fitted; ``gradient_sd_nT_per_m`` (5,) the standard deviations of its five
        parameters (Gnn, Gne, Gnd, Gee, Ged).
    origin_m : numpy.ndarray, shape (3,), or None
        ``p0``: where ``ned_nT`` holds when the gradient is fitted.
    determined : bool
        False when the record does not determine the field (a sensor's fit not determined, a direction's standard
        deviation beyond :data:`UNDETERMINED_DIRECTION_DEG`, ``|B|`` outside the Earth's range): a note says so.
    """

    ned_nT: np.ndarray
    sd_nT: np.ndarray
    declination_deg: float
    inclination_deg: float
    declination_sd_deg: float
    inclination_sd_deg: float
    total_nT: float
    total_sd_nT: float
    total_source: str
    gauges: list = field(default_factory=list)
    declination_fixed: bool = False
    gradient_nT_per_m: np.ndarray | None = None
    gradient_sd_nT_per_m: np.ndarray | None = None
    origin_m: np.ndarray | None = None
    determined: bool = True

    def text(self) -> str:
        """One line: the field, its uncertainty and its gauges."""
        n, e, d = self.ned_nT
        sn, se, sd = self.sd_nT
        line = (
            f"the lab's field fitted with the calibration: N {n:.1f} +- {sn:.1f}, E {e:.1f} +- {se:.1f}, D {d:.1f} +- "
            f"{sd:.1f} nT (|B| {self.total_nT:.1f}"
            + (f" +- {self.total_sd_nT:.1f}" if self.total_sd_nT > 0 else "")
            + f" nT, declination {self.declination_deg:.2f}"
            + ("" if self.declination_fixed else f" +- {self.declination_sd_deg:.2f}")
            + f" deg, inclination {self.inclination_deg:.2f} +- {self.inclination_sd_deg:.2f} deg)"
        )
        if not self.determined:
            line += " NOT DETERMINED by this record (see the note)"
        if self.gradient_nT_per_m is not None:
            g = self.gradient_nT_per_m
            line += (
                f"; a gradient along the path (record-only, not carried by apply): Gnn {g[0, 0]:.0f}, Gne "
                f"{g[0, 1]:.0f}, Gnd {g[0, 2]:.0f}, Gee {g[1, 1]:.0f}, Ged {g[1, 2]:.0f} nT/m"
            )
        return line

    def to_dict(self) -> dict:
        doc = {
            "ned_nT": self.ned_nT.tolist(),
            "sd_nT": self.sd_nT.tolist(),
            "total_nT": self.total_nT,
            "total_sd_nT": self.total_sd_nT,
            "total_source": self.total_source,
            "declination_deg": self.declination_deg,
            "declination_sd_deg": self.declination_sd_deg,
            "declination_fixed": self.declination_fixed,
            "inclination_deg": self.inclination_deg,
            "inclination_sd_deg": self.inclination_sd_deg,
            "gauges": list(self.gauges),
            "determined": self.determined,
        }
        if self.gradient_nT_per_m is not None:
            doc["gradient_nT_per_m"] = self.gradient_nT_per_m.tolist()
            doc["gradient_sd_nT_per_m"] = (
                None if self.gradient_sd_nT_per_m is None else (self.gradient_sd_nT_per_m.tolist())
            )
            doc["origin_m"] = None if self.origin_m is None else self.origin_m.tolist()
            doc["gradient_carried"] = False  # the record's, not the instrument's: apply never uses it
        return doc


def solve(problems, xs, sigmas, rotation, setup: FieldSetup, robust=False, max_nfev=200):
    """The joint least-squares solve of the sensors' parameters and the field's.

    Parameters
    ----------
    problems, xs, sigmas : list
        Per sensor: its weighted problem, its parameters ``(W, b, theta)`` at the start, its noises
        ``(sigma_total, sigma_perpendicular)`` in nT.
    rotation : scipy.spatial.transform.Rotation
        The fitted samples' attitudes (body -> NED).
    setup : FieldSetup
        What of the field is fitted, about which point.
    robust : bool
        Soft-L1 loss, as the vector fit's ``robust``.

    Returns
    -------
    x : numpy.ndarray
        ``[x_1, .., x_S, field]`` at the solution.
    covariance : numpy.ndarray or None
        ``s2 (J^T J)^-1`` widened for residuals correlated in time (None when singular).
    jacobian : numpy.ndarray
        The weighted Jacobian at the solution.
    s2, widening : float
        The residual variance per weighted residual and the widening for the lag-1 correlation of the residuals.
    """
    prob = FieldProblem(problems, [len(x) for x in xs], sigmas, rotation, setup)
    x0 = np.concatenate(list(xs) + [np.zeros(setup.n_params)])
    scale = np.concatenate(
        [np.concatenate([np.full(9, 1e-3), np.full(3, 10.0), np.ones(len(x) - 12)]) for x in xs]
        + [np.full(setup.n_direction, 1e-3), np.full(setup.n_params - setup.n_direction, 10.0)]
    )
    sol = weighted_least_squares(prob.residuals, x0, scale, robust, jac=prob.jacobian, max_nfev=max_nfev)
    jac = prob.jacobian(sol.x)
    z = prob.residuals(sol.x)
    n = len(rotation)
    total_parts = [z[s * 3 * n : s * 3 * n + n] for s in range(len(problems))]
    cov = correlated_covariance(jac, z, len(sol.x), total_parts, n)
    return sol.x, cov.matrix, jac, cov.s2, cov.widening
