"""The maximum-likelihood fitter for any model, one sensor or four together.

:class:`Problem` turns a dataset, a :class:`~magcal.model.terms.Model` and a starting calibration into a residual
vector and its Jacobian; :func:`fit` minimises it by Levenberg-Marquardt on the normal equations
(:meth:`Problem.normal_equations` never forms the tall consistency rows of an array, which keeps a warm
four-sensor refit interactive) and returns a :class:`FitResult`. Robust losses (scipy's ``soft_l1``, ``huber``,
``cauchy``) enter as iteratively reweighted least squares.

Residuals (nT)
    * total field, per sensor and sample: ``|B_s| - F_s(t)``;
    * for arrays whose model has ``misalignment``: inter-sensor consistency, the part of ``B_s - mean_s B_s``
      perpendicular to the field, scaled by ``sqrt(n/(n-1))`` so that its noise matches one axis's.

Parameters per sensor: the 6 entries of the upper-triangular ``C^-1`` (``scale`` frees the diagonal,
``non_orthogonality`` the off-diagonal), the bias (3, ``bias``) and, for sensors 2-4, a rotation vector (3,
``misalignment``, sensor 1 defines the array frame). An unknown reference adds ``F0``; then the overall scale is
fixed by ``det C^-1 = 1`` for sensor 1 (the product of its scale factors is 1), since total-field data cannot tell
a larger field from larger gains. Candidate effects add their own parameters (see :mod:`magcal.model.terms`).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from magcal.calibration.calibration import Calibration, SensorCalibration, corrected_fields, expected_total_field
from magcal.calibration.uncertainty import base_covariance
from magcal.checks.reference import resolve_reference
from magcal.core import conventions
from magcal.core import notes as _notes
from magcal.core.blas import one_blas_thread
from magcal.core.errors import CalibrationError, ConvergenceWarning, DataWarning
from magcal.core.notes import Note, row_runs
from magcal.core.rows import basis_times, cross_rows, row_norm, unit_rows
from magcal.core.stats import robust_sigma
from magcal.fitting.solver import ROBUST_SCALE, NoiseGroup, beyond, normal_covariance, reweighted_fit
from magcal.model.terms import (
    Model,
    attitude_effects,
    block_label,
    bound_pulls,
    contexts,
    fitted_outside_domain,
    held_note_text,
    rows_without_attitude,
    without_attitude_note,
)

#: Samples per block when a model of base terms only is evaluated block by block (:meth:`Problem.normal_equations`).
BLOCK_ROWS = 1 << 16

#: ``cost_tolerance`` (noise variances) of the fits that are only compared, by an information criterion or a held-out
#: RMS (the diagnosis's confirming refits, the held-out fits): parameters within ~0.14 standard errors of the minimum.
COMPARISON_COST_TOLERANCE = 0.01

#: Readings (samples times sensors) of the even subsample a base model is first converged on when the record has
#: more than twice as many (:func:`fit`): the fit of every sample then starts within a few of its standard errors
#: of the minimum, and takes two passes over the record instead of three or four.
WARMUP_SAMPLES = 100_000

#: After the warm-up, finish with one Gauss-Newton step over every sample when it lowers the cost as predicted
#: (:func:`_fit_once`; False: iterate until the next step's predicted gain is below the tolerance, one more pass).
ONE_STEP_AFTER_WARMUP = True

#: Readings (kept samples times sensors) from which :func:`fit` runs BLAS on one thread
#: (:func:`magcal.core.blas.one_blas_thread`): its normal equations are ``(k, m) @ (m, k)`` products of a few dozen
#: columns, which OpenBLAS splits over the cores, and its threads spin while one waits for a core that anything
#: else keeps busy (the workbench's browser drawing beside a refit). 2-core machine, load 5-8, 4 x 1e5 samples: a
#: refit with one effect 8.9 s on the default two threads, 0.32 s on one; the base calibration 1.93 against 0.53 s
#: (``benchmarks/refit_latency.py``). Below this the products are too small for OpenBLAS to split.
ONE_BLAS_THREAD_READINGS = 20_000

#: Typical change of each base parameter that moves the readings by about 1 nT in a 50 uT field.
_CINV_SCALE = 2e-5
_ROT_SCALE = 2e-5


def fit_reference(dataset, reference_total_nT=None):
    """``(value or None, kind)`` of the reference a fit uses (:meth:`magcal.checks.reference.Reference.for_fit` of
    :func:`magcal.checks.reference.resolve_reference`, without its user-facing checks)."""
    return resolve_reference(dataset, reference_total_nT, check=False).for_fit()


def crude_initial_calibration(dataset, reference_total_nT=None) -> Calibration:
    """A rough start when none is given: a linear sphere fit per sensor and vector alignment of the sensors.

    Good enough for Levenberg-Marquardt from typical fluxgate errors (a few percent); the two-step
    ellipsoid + Procrustes start of :func:`magcal.fitting.pipeline.calibrate` is better and should normally be used.
    """
    ref, kind = fit_reference(dataset, reference_total_nT)
    sensors, centred = [], []
    for y in dataset.readings_nT:
        design = np.column_stack([2 * y, np.ones(len(y))])
        sol, *_ = np.linalg.lstsq(design, np.sum(y**2, axis=1), rcond=None)
        centre = sol[:3]
        radius = np.sqrt(max(sol[3] + centre @ centre, 1e-12))
        target = ref if ref is not None else (np.median(dataset.ref_total_nT) if kind == "column" else radius)
        sensors.append(SensorCalibration(np.eye(3) * target / radius, centre))
        centred.append((y - centre) * target / radius)
    for s in range(1, len(sensors)):
        rot, _ = Rotation.align_vectors(centred[0], centred[s])
        sensors[s].R = rot.as_matrix()
    return Calibration(
        sensors,
        reference_total_nT=ref
        if ref is not None
        else (None if kind == "column" else float(np.mean([row_norm(c).mean() for c in centred]))),
        reference_fitted=kind == "fitted",
        baseline_m=dataset.baseline_m,
    )


class Problem:
    """Residuals and Jacobian of a model on a dataset, around a starting calibration.

    Parameters
    ----------
    dataset : Dataset
        The samples to fit (already restricted to the kept ones).
    model : Model
    init : Calibration
        Starting point; candidate effects missing from ``init.effect_values`` start at zero.
    reference_total_nT : float, optional
        Overrides the dataset's reference.

    Attributes
    ----------
    x0 : numpy.ndarray
        Starting parameter vector (physical units).
    param_names : list of str
    blocks : dict of str to slice
        Columns of each parameter block: ``sensorS/base``, ``F0``, and one per effect instance
        (:func:`magcal.calibration.calibration.block_label`).
    total_field_rows : slice
        Rows of the total-field residuals (sensor-major: sensor ``s`` sample ``i`` is row ``s*N + i``).
    """

    def __init__(self, dataset, model: Model, init: Calibration, reference_total_nT=None):
        self.dataset = dataset
        self.model = model
        self.n_sensors = ns = dataset.n_sensors
        self.n_samples = n = dataset.n_samples
        self.ctxs = contexts(dataset, init.baseline_m if init.baseline_m is not None else dataset.baseline_m)
        ref, self.reference_kind = fit_reference(dataset, reference_total_nT)
        if self.reference_kind == "fitted" and init.reference_total_nT:
            ref = float(init.reference_total_nT)
        self.coupled = ns > 1 and "misalignment" in model.base
        #: The analytic Jacobian is exact (no effect whose basis depends on the readings: that dependence is left
        #: out of :meth:`field_derivatives`; :attr:`magcal.model.terms.Effect.basis_uses_readings`).
        self.exact_jacobian = not any(e.basis_uses_readings for e, _ in model.instances())
        self.baseline_m = init.baseline_m if init.baseline_m is not None else dataset.baseline_m

        names: list = []
        values: list = []
        scales: list = []
        self.blocks = {}
        self._base_free = []
        free_c = [
            k
            for k, (i, j) in enumerate(conventions.UPPER_TRIANGLE)
            if ("scale" in model.base if i == j else "non_orthogonality" in model.base)
        ]
        init_sensors = [SensorCalibration(c.cinv.copy(), c.bias_nT.copy(), c.R.copy()) for c in init.sensors]
        if self.reference_kind == "fitted":
            # gauge: det(C^-1) = 1 for sensor 1; rescale the whole start and the field together.
            lam = np.linalg.det(init_sensors[0].cinv) ** (-1.0 / 3.0)
            for c in init_sensors:
                c.cinv = c.cinv * lam
            ref = (ref if ref else np.mean(row_norm(corrected_fields(dataset, init.sensors)))) * lam
        self.init_sensors = init_sensors
        for s, cal in enumerate(init_sensors):
            start = len(names)
            cpar = conventions.cinv_to_params(cal.cinv)
            free = []
            for k in free_c:
                if self.reference_kind == "fitted" and s == 0 and k == 5:
                    continue  # c22 of sensor 1 follows from det = 1
                names.append(f"s{s + 1}_Cinv{conventions.UPPER_TRIANGLE[k][0]}{conventions.UPPER_TRIANGLE[k][1]}")
                values.append(cpar[k])
                scales.append(_CINV_SCALE)
                free.append(("c", k))
            if "bias" in model.base:
                for a, axis in enumerate("xyz"):
                    names.append(f"s{s + 1}_bias_{axis}_nT")
                    values.append(cal.bias_nT[a])
                    scales.append(1.0)
                    free.append(("b", a))
            if "misalignment" in model.base and s > 0:
                # small rotation about the array axes applied on top of the starting R: R = exp([w]x) R_start
                for a, axis in enumerate("xyz"):
                    names.append(f"s{s + 1}_rotation_{axis}_rad")
                    values.append(0.0)
                    scales.append(_ROT_SCALE)
                    free.append(("r", a))
            self._base_free.append(free)
            self.blocks[f"sensor{s + 1}/base"] = slice(start, len(names))
        if self.reference_kind == "fitted":
            self.blocks["F0"] = slice(len(names), len(names) + 1)
            names.append("F0_nT")
            values.append(ref)
            scales.append(1.0)
        self.reference_value = ref
        for e, s in model.instances():
            label = block_label(e, s)
            start = len(names)
            pn = e.param_names()
            prefix = "" if s is None else f"s{s + 1}_"
            names += [f"{prefix}{e.name}.{p}" for p in pn]
            v = init.effect_values.get(label)
            values += list(np.zeros(len(pn)) if v is None else e.check_params(v, f"the starting calibration ({label})"))
            scales += list(np.asarray(e.param_scale(), dtype=float))
            self.blocks[label] = slice(start, len(names))
        self.param_names = names
        self.x0 = np.asarray(values, dtype=float)
        self.x_scale = np.asarray(scales, dtype=float)
        #: Bounds the fit keeps each parameter in (:meth:`magcal.model.terms.Effect.param_bounds`; base terms free).
        self.lower = np.full(len(names), -np.inf)
        self.upper = np.full(len(names), np.inf)
        for e, s in model.instances():
            sl = self.blocks[block_label(e, s)]
            lo, hi = e.param_bounds()
            self.lower[sl], self.upper[sl] = lo, hi
        self.x0 = np.clip(self.x0, self.lower, self.upper)
        self.total_field_rows = slice(0, ns * n)
        self.n_residuals = ns * n * (3 if self.coupled else 1)
        if len(names) >= ns * n:
            raise CalibrationError(
                f"{len(names)} parameters but only {ns * n} total-field values; record more samples "
                "or use fewer effects"
            )

    # --- unpacking ------------------------------------------------------------------------------------------
    def sensors(self, x) -> list:
        """Each sensor's :class:`~magcal.calibration.calibration.SensorCalibration` at ``x``."""
        return [self.sensor(x, s) for s in range(self.n_sensors)]

    def sensor(self, x, s) -> SensorCalibration:
        """Sensor ``s``'s calibration at ``x``: it depends only on the columns ``blocks[f"sensor{s + 1}/base"]``."""
        block = x[self.blocks[f"sensor{s + 1}/base"]]
        init = self.init_sensors[s]
        cpar = conventions.cinv_to_params(init.cinv)
        bias, rotvec = init.bias_nT.copy(), None
        for (kind, k), value in zip(self._base_free[s], block):
            if kind == "c":
                cpar[k] = value
            elif kind == "b":
                bias[k] = value
            else:
                rotvec = np.zeros(3) if rotvec is None else rotvec
                rotvec[k] = value
        if self.reference_kind == "fitted" and s == 0:
            cpar[5] = 1.0 / (cpar[0] * cpar[3])
        rot = init.R if rotvec is None else Rotation.from_rotvec(rotvec).as_matrix() @ init.R
        return SensorCalibration(conventions.params_to_cinv(cpar), bias, rot)

    def effect_values(self, x) -> dict:
        return {label: x[sl].copy() for label, sl in self.blocks.items() if "/" not in label and label != "F0"}

    def reference(self, x):
        return float(x[self.blocks["F0"]][0]) if "F0" in self.blocks else self.reference_value

    def calibration(self, x) -> Calibration:
        return Calibration(
            sensors=self.sensors(x),
            reference_total_nT=self.reference(x),
            reference_fitted=self.reference_kind == "fitted",
            baseline_m=self.baseline_m,
            model=self.model,
            effect_values=self.effect_values(x),
        )

    # --- residuals ------------------------------------------------------------------------------------------
    def fields(self, x):
        return corrected_fields(self.dataset, self.sensors(x), self.model, self.effect_values(x), self.ctxs)

    def residuals(self, x) -> np.ndarray:
        """Residual vector (nT): total field (n_sensors*N), then consistency (n_sensors*N*2) when coupled."""
        blocks = self._sample_blocks()
        if blocks is None:
            return self._residuals_from_fields(self.fields(x), x)
        r = np.empty(self.n_residuals)
        for a, b, part in blocks:
            r[self._rows_of_samples(a, b)] = part._residuals_from_fields(part.fields(x), x)
        return r

    def _residuals_from_fields(self, b, x, basis=None, mean=None) -> np.ndarray:
        """Residuals (as :meth:`residuals`) of the corrected fields ``b``; ``mean`` is ``b.mean(axis=0)`` and
        ``basis`` ``_perpendicular_basis(mean)`` when the caller has them."""
        expected = expected_total_field(self.dataset, self.reference(x), self.model, self.effect_values(x), self.ctxs)
        total = (row_norm(b) - expected).ravel()
        if not self.coupled:
            return total
        mean = b.mean(axis=0) if mean is None else mean
        e1, e2 = _perpendicular_basis(mean) if basis is None else basis
        diff = b - mean
        perp = np.empty(diff.shape[:2] + (2,))
        for k, e in enumerate((e1, e2)):
            np.multiply(diff[..., 0], e[:, 0], out=perp[..., k])
            perp[..., k] += diff[..., 1] * e[:, 1]
            perp[..., k] += diff[..., 2] * e[:, 2]
        return np.concatenate([total, self._consistency_factor * perp.ravel()])

    @property
    def _consistency_factor(self) -> float:
        """Scale of the consistency rows, ``sqrt(n/(n-1))``: the noise of one axis's deviation from the mean."""
        return float(np.sqrt(self.n_sensors / (self.n_sensors - 1.0)))

    def field_derivatives(self, x):
        """Corrected fields (n_sensors, N, 3) and, per sensor, its derivatives dB_s/dx as a :class:`_Derivative`.

        The chain rule through each term's basis: entries of C^-1 act through ``R e_i z_j``, the bias through
        ``-R C^-1``, the rotation through ``[e_a]x B``, raw-stage effects through ``-R C^-1 basis`` and
        array-stage effects through their basis. The bases' own dependence on ``z0`` and ``B`` is second order
        and left out. The derivatives are kept as these factors: the residuals need only their projections on
        a direction per sample (:meth:`_Derivative.project`), an (N, k) matrix, never the (N, 3, k) array.
        """
        sensors = self.sensors(x)
        values = self.effect_values(x)
        instances = list(self.model.instances())
        n = self.n_samples
        fields = np.empty((self.n_sensors, n, 3))
        derivs = []
        for s, cal in enumerate(sensors):
            ctx = self.ctxs[s]
            z0 = self.dataset.readings_nT[s] - cal.bias_nT
            z = z0
            raw = []
            for e, es in instances:
                if e.stage == "raw" and (es == s or (es is None and e.applies_to(s))):
                    basis = e.raw_basis(z0, ctx)
                    theta = values[block_label(e, es)]
                    if np.any(theta):  # a candidate at zero (the score tests' Gram matrix) moves nothing
                        z = z - basis_times(basis, theta)
                    raw.append((self.blocks[block_label(e, es)], basis))
            rc = cal.R @ cal.cinv
            b_rot = z @ rc.T
            start = self.blocks[f"sensor{s + 1}/base"].start
            c = conventions.cinv_to_params(cal.cinv)
            base = []
            for kind, k in self._base_free[s]:
                if kind == "c":
                    i, j = conventions.UPPER_TRIANGLE[k]
                    tied = (c[5] / c[k]) if (self.reference_kind == "fitted" and s == 0 and k in (0, 3)) else None
                    base.append(("c", i, j, tied))  # through c22 = 1/(c00 c11) when tied
                else:
                    base.append((kind, k, None, None))
            b = b_rot  # the terms below make new arrays: b_rot itself is kept for the derivatives
            array = []
            for e, es in instances:
                if e.stage == "array" and (es == s or (es is None and e.applies_to(s))):
                    basis = e.array_basis(b_rot, ctx)
                    theta = values[block_label(e, es)]
                    if np.any(theta):
                        b = b + basis_times(basis, theta)
                    array.append((self.blocks[block_label(e, es)], basis))
            fields[s] = b
            derivs.append(_Derivative(start, base, z, cal.R, rc, b_rot, raw, array))
        return fields, derivs

    def _total_field_jacobian(self, x, fields, derivs) -> np.ndarray:
        """Rows of the Jacobian (n_sensors*N, p) for the total-field residuals."""
        ns, n = self.n_sensors, self.n_samples
        jac = np.zeros((ns * n, x.size))
        units = unit_rows(fields)
        for s, d in enumerate(derivs):
            jac[s * n : (s + 1) * n, d.cols] += d.project(units[s])
        if "F0" in self.blocks:
            jac[:, self.blocks["F0"].start] = -1.0
        for e, es in self.model.instances():
            if e.stage != "reference":
                continue
            sl = self.blocks[block_label(e, es)]
            for s in range(ns):
                if es is None or es == s:
                    jac[s * n : (s + 1) * n, sl] -= e.reference_basis(self.ctxs[s])
        return jac

    def _total_field_normal(self, x, fields, derivs, r_tf, w_tf=None):
        """``J^T W J`` and ``J^T W r`` of the total-field rows, sensor by sensor: each sensor's rows touch only its
        own columns (and the shared reference terms), so its block is accumulated from an (N, k) matrix instead of
        the (n_sensors N, p) Jacobian of :meth:`_total_field_jacobian` (mostly zeros for an array); and that
        matrix is built and multiplied :func:`_row_blocks` rows at a time, so that it stays in cache."""
        n = self.n_samples
        p = x.size
        jtj, jtr = np.zeros((p, p)), np.zeros(p)
        ref_instances = [(e, es) for e, es in self.model.instances() if e.stage == "reference"]
        has_f0 = "F0" in self.blocks
        for s, d in enumerate(derivs):
            extra = [
                np.asarray(e.reference_basis(self.ctxs[s]), float).reshape(n, -1)
                for e, es in ref_instances
                if es is None or es == s
            ]
            extra_idx = [
                np.arange(self.blocks[block_label(e, es)].start, self.blocks[block_label(e, es)].stop)
                for e, es in ref_instances
                if es is None or es == s
            ]
            at = np.concatenate([d.cols] + ([np.array([self.blocks["F0"].start])] if has_f0 else []) + extra_idx)
            k = at.size
            norms = row_norm(fields[s])
            gram, rhs = np.zeros((k, k)), np.zeros(k)
            for rows in _row_blocks(n, k):
                m = rows.stop - rows.start
                j = np.empty((k, m)).T  # column-major: each column written contiguously
                d.project(fields[s, rows] / norms[rows, None], out=j[:, : len(d.cols)], rows=rows)
                at_col = len(d.cols)
                if has_f0:
                    j[:, at_col] = -1.0
                    at_col += 1
                for e in extra:
                    np.negative(e[rows], out=j[:, at_col : at_col + e.shape[1]])
                    at_col += e.shape[1]
                rs = r_tf[s * n + rows.start : s * n + rows.stop]
                wj = j if w_tf is None else j * w_tf[s * n + rows.start : s * n + rows.stop, None]
                gram += wj.T @ j
                rhs += wj.T @ rs
            jtj[np.ix_(at, at)] += gram
            jtr[at] += rhs
        return jtj, jtr

    def _consistency_derivatives(self, fields, derivs, basis=None):
        """Per sensor, dP_s/dx (N, 2, k) of the two perpendicular components of ``B_s`` (scaled like the rows).

        The consistency rows of sensor ``k`` are ``sum_s (delta_ks - 1/n) dP_s/dx``; the derivative of the
        perpendicular basis itself multiplies ``B_s - mean B`` (a few nT) and is left out.
        """
        e1, e2 = _perpendicular_basis(fields.mean(axis=0)) if basis is None else basis
        factor = self._consistency_factor
        return [factor * np.stack([d.project(e1), d.project(e2)], axis=1) for d in derivs]

    def jacobian(self, x) -> np.ndarray:
        """Analytic Jacobian (m, p) of :meth:`residuals` (see :meth:`field_derivatives`)."""
        fields, derivs = self.field_derivatives(x)
        ns, n = self.n_sensors, self.n_samples
        tf = self._total_field_jacobian(x, fields, derivs)
        if not self.coupled:
            return tf
        jac = np.zeros((self.n_residuals, x.size))
        jac[: ns * n] = tf
        for s, (d, p) in enumerate(zip(derivs, self._consistency_derivatives(fields, derivs))):
            cols, p = d.cols, p.reshape(2 * n, -1)
            for k in range(ns):
                w = (1.0 if k == s else 0.0) - 1.0 / ns
                jac[ns * n + k * 2 * n : ns * n + (k + 1) * 2 * n, cols] += w * p
        return jac

    def normal_equations(self, x, weights=None, with_total_field=False):
        """Residuals ``r``, ``J^T W J`` and ``J^T W r`` at ``x`` (see :meth:`_normal_equations_whole`).

        A model of base terms only (no effect, whose bases may depend on the whole record) is evaluated in
        blocks of :data:`BLOCK_ROWS` samples and the blocks' sums added: the same equations, but each block's
        temporaries stay in cache instead of a dozen (N, k) arrays going through memory.
        """
        blocks = self._sample_blocks()
        if blocks is None:
            return self._normal_equations_whole(x, weights, with_total_field)
        r = np.empty(self.n_residuals)
        sums = None
        for a, b, part in blocks:
            rows = self._rows_of_samples(a, b)
            out = part._normal_equations_whole(x, None if weights is None else weights[rows], with_total_field)
            r[rows] = out[0]
            flat = [out[1], out[2]] + ([out[3][0], out[3][1]] if with_total_field else [])
            sums = flat if sums is None else [s + f for s, f in zip(sums, flat)]
        return (r, sums[0], sums[1]) + (((sums[2], sums[3]),) if with_total_field else ())

    def _rows_of_samples(self, a, b) -> np.ndarray:
        """Indices of the residual rows of samples ``a:b`` (:meth:`residuals`' order), in the order a problem of
        those samples alone lists them: total field sensor by sensor, then the consistency rows."""
        ns, n = self.n_sensors, self.n_samples
        total = (np.arange(ns)[:, None] * n + np.arange(a, b)[None, :]).ravel()
        if not self.coupled:
            return total
        cons = (
            ns * n
            + (
                (np.arange(ns)[:, None, None] * n + np.arange(a, b)[None, :, None]) * 2 + np.arange(2)[None, None, :]
            ).ravel()
        )
        return np.concatenate([total, cons])

    def _sample_blocks(self):
        """``(start, stop, problem of those rows)`` per block, or None when the model has effects or the data
        fit in one block."""
        if self.n_samples <= BLOCK_ROWS or any(True for _ in self.model.instances()):
            return None
        out = []
        for a in range(0, self.n_samples, BLOCK_ROWS):
            b = min(a + BLOCK_ROWS, self.n_samples)
            part = copy.copy(self)
            part.dataset, part.n_samples = _Rows(self.dataset, a, b), b - a
            part.n_residuals = self.n_sensors * (b - a) * (3 if self.coupled else 1)
            part.total_field_rows = slice(0, self.n_sensors * (b - a))
            out.append((a, b, part))
        return out

    def _normal_equations_whole(self, x, weights=None, with_total_field=False):
        """Residuals ``r``, ``J^T W J`` and ``J^T W r`` at ``x``, without forming the consistency rows of ``J``.

        The consistency rows of sensor ``k`` are the centred per-sensor derivatives ``sum_s c_ks P_s`` with
        ``c = I - 1/n``. Unweighted, since the centring matrix is idempotent, their contribution is
        ``sum_s P_s^T P_s - (1/n) Q^T Q`` with ``Q = sum_s P_s``, and ``J^T r`` is ``sum_s P_s^T r_s`` (the
        consistency residuals sum to zero over the sensors). With row weights ``W_k`` the pair ``(s, s')``
        contributes ``P_s^T (sum_k c_ks c_ks' W_k) P_s'``. For four sensors this is a third of the rows and no
        dense tall matrix.

        Parameters
        ----------
        x : numpy.ndarray
        weights : numpy.ndarray, shape (m,), optional
            A weight per residual (as :meth:`residuals` orders them); default 1.
        with_total_field : bool
            Also return the total-field rows' own ``(J^T W J, J^T W r)`` as a fourth item.

        Returns
        -------
        r : numpy.ndarray, shape (m,)
            As :meth:`residuals` (nT).
        jtj : numpy.ndarray, shape (p, p)
        jtr : numpy.ndarray, shape (p,)
        """
        fields, derivs = self.field_derivatives(x)
        mean = fields.mean(axis=0) if self.coupled else None
        basis = _perpendicular_basis(mean) if self.coupled else None
        r = self._residuals_from_fields(fields, x, basis, mean)
        ns, n = self.n_sensors, self.n_samples
        w_tf = None if weights is None else weights[: ns * n]
        jtj, jtr = self._total_field_normal(x, fields, derivs, r[: ns * n], w_tf)
        extra = ((jtj.copy(), jtr.copy()),) if with_total_field else ()
        if not self.coupled:
            return (r, jtj, jtr) + extra
        rc = r[ns * n :].reshape(ns, 2 * n)
        cols = [d.cols for d in derivs]
        if weights is None:
            # every sensor's P_s side by side in one (2N, K) matrix: one product gives all the pairs P_s^T P_s'
            edges = np.cumsum([0] + [len(c) for c in cols])
            gram = np.zeros((edges[-1], edges[-1]))
            rhs = [np.zeros(len(c)) for c in cols]
            factor = self._consistency_factor
            rows_of = rc.reshape(ns, n, 2)
            for rows in _row_blocks(n, 2 * edges[-1]):
                m = rows.stop - rows.start
                both = np.empty((edges[-1], 2, m))  # column-major (2m, K): each column written contiguously
                for s, d in enumerate(derivs):
                    for k, e in enumerate(basis):
                        d.project(e[rows], out=both[edges[s] : edges[s + 1], k].T, rows=rows)
                both *= factor
                both = both.reshape(edges[-1], 2 * m)
                gram += both @ both.T
                block_r = rows_of[:, rows].transpose(0, 2, 1).reshape(ns, 2 * m)  # the rows' order in ``both``
                for s in range(ns):
                    rhs[s] += both[edges[s] : edges[s + 1]] @ block_r[s]
            for s in range(ns):
                own = slice(edges[s], edges[s + 1])
                jtr[cols[s]] += rhs[s]
                for s2 in range(ns):
                    pair = gram[own, edges[s2] : edges[s2 + 1]]
                    jtj[np.ix_(cols[s], cols[s2])] += pair * ((1.0 if s == s2 else 0.0) - 1.0 / ns)
            return (r, jtj, jtr) + extra
        ps = [p.reshape(2 * n, -1) for p in self._consistency_derivatives(fields, derivs, basis)]
        wc = weights[ns * n :].reshape(ns, 2 * n)
        centring = np.eye(ns) - 1.0 / ns
        weighted_r = centring.T @ (wc * rc)  # sum_k c_ks W_k r_k, per s
        for s in range(ns):
            jtr[cols[s]] += ps[s].T @ weighted_r[s]
            for s2 in range(ns):
                pair = (centring[:, s] * centring[:, s2]) @ wc
                jtj[np.ix_(cols[s], cols[s2])] += ps[s].T @ (pair[:, None] * ps[s2])
        return (r, jtj, jtr) + extra


class _Derivative:
    """dB/dx of one sensor's corrected field, kept as its factors (see :meth:`Problem.field_derivatives`).

    ``cols`` are the parameter indices the sensor's field depends on; :meth:`project` gives ``w_n . dB_n/dx``
    for a direction per sample (N, k) and :meth:`dense` the whole (N, 3, k) array (tests, small problems).
    """

    def __init__(self, start, base, z, rot, rc, b_rot, raw, array):
        self._base, self._z, self._rot, self._rc, self._b_rot = base, z, rot, rc, b_rot
        self._raw, self._array = raw, array
        self._zt = self._bt = self._one_axis = None
        cols = [start + i for i in range(len(base))]
        for sl, _ in raw + array:
            cols.extend(range(sl.start, sl.stop))
        self.cols = np.asarray(cols, dtype=int)

    @staticmethod
    def _single_axis(basis):
        """``(axes, axis_values)`` of a :class:`~magcal.model.terms.SingleAxisBasis` (each parameter moves one axis:
        its projections are q products instead of a contraction over the whole array, 8x), else None."""
        axes = getattr(basis, "axes", None)
        return None if axes is None else (axes, basis.axis_values)

    def project(self, w, out=None, rows=None):
        """``sum_i w[n, i] dB[n, i]/dx_k`` (N, k) for directions ``w`` (N, 3); with ``rows`` (a slice), for those
        samples only (``w`` then has their directions)."""
        n = len(w)
        out = np.empty((len(self.cols), n)).T if out is None else out
        if self._zt is None:  # components as contiguous rows, once for all the directions projected on
            self._zt, self._bt = np.ascontiguousarray(self._z.T), np.ascontiguousarray(self._b_rot.T)
            self._one_axis = (
                [self._single_axis(b) for _, b in self._raw],
                [self._single_axis(b) for _, b in self._array],
            )
        rows = slice(None) if rows is None else rows
        zt, bt = self._zt[:, rows], self._bt[:, rows]
        wt = w.T
        wr = self._rot.T @ wt  # (R^T w)_i: an entry (i, j) of C^-1 moves B by R e_i z_j
        wrc = None
        for col, (kind, a, bcol, tied) in enumerate(self._base):
            if kind == "c":
                np.multiply(wr[a], zt[bcol], out=out[:, col])
                if tied is not None:
                    out[:, col] -= tied * wr[2] * zt[2]
            elif kind == "b":
                wrc = self._rc.T @ wt if wrc is None else wrc
                np.negative(wrc[a], out=out[:, col])
            else:  # w . (e_a x B) = (B x w)_a
                i, j = ((1, 2), (2, 0), (0, 1))[a]
                np.multiply(bt[i], wt[j], out=out[:, col])
                out[:, col] -= bt[j] * wt[i]
        col = len(self._base)
        raw_axes, array_axes = self._one_axis
        for (sl, basis), single in zip(self._raw, raw_axes):
            wrc = self._rc.T @ wt if wrc is None else wrc
            q = sl.stop - sl.start
            part = out[:, col : col + q]
            if single is None:
                np.negative(np.einsum("in,niq->nq", wrc, basis[rows]), out=part)
            else:
                np.multiply(-wrc[single[0]], single[1][:, rows], out=part.T)
            col += q
        for (sl, basis), single in zip(self._array, array_axes):
            q = sl.stop - sl.start
            part = out[:, col : col + q]
            if single is None:
                part[...] = np.einsum("ni,niq->nq", w, basis[rows])
            else:
                np.multiply(wt[single[0]], single[1][:, rows], out=part.T)
            col += q
        return out

    def dense(self):
        """The whole derivative (N, 3, k)."""
        n = len(self._z)
        return np.stack([self.project(np.broadcast_to(np.eye(3)[i], (n, 3))) for i in range(3)], axis=1)


#: Elements of an (N, k) matrix built at once when its products are accumulated block by block (2 MB), and the
#: fewest rows of a block (:func:`_row_blocks`): a wide matrix (the diagnosis's ~170 candidate columns) still gets
#: 4 096 rows, so that the few dozen numpy calls per block, which hold the interpreter, stay few (at 1 024 rows
#: two threads accumulating side by side were 40 % slower).
ROW_BLOCK_ELEMENTS = 1 << 18
MIN_BLOCK_ROWS = 4096


def _row_blocks(n, width):
    """Slices of ``range(n)`` for accumulating products of an (N, ``width``) matrix block by block
    (:data:`ROW_BLOCK_ELEMENTS` per block, at least :data:`MIN_BLOCK_ROWS` rows)."""
    step = max(MIN_BLOCK_ROWS, ROW_BLOCK_ELEMENTS // max(int(width), 1))
    return [slice(a, min(a + step, n)) for a in range(0, n, step)]


class _Rows:
    """Rows ``start:stop`` of a dataset, as much of it as a model of base terms reads (views, no copy)."""

    def __init__(self, dataset, start, stop):
        self.readings_nT = dataset.readings_nT[:, start:stop]
        self.ref_total_nT = None if dataset.ref_total_nT is None else dataset.ref_total_nT[start:stop]
        self.n_sensors, self.n_samples = dataset.n_sensors, stop - start
        self.source = dataset.source


@dataclass
class _Solution:
    x: np.ndarray
    r: np.ndarray
    jtj: np.ndarray
    nfev: int
    message: str
    status: int = 0


#: scipy's robust losses: ``rho(z)`` and ``rho'(z)`` of ``z = (r / f)^2``; the cost is ``f^2/2 sum rho``.
LOSSES = {
    "linear": (lambda z: z, lambda z: np.ones_like(z)),
    "soft_l1": (lambda z: 2.0 * (np.sqrt(1.0 + z) - 1.0), lambda z: 1.0 / np.sqrt(1.0 + z)),
    "huber": (
        lambda z: np.where(z <= 1.0, z, 2.0 * np.sqrt(z) - 1.0),
        lambda z: np.where(z <= 1.0, 1.0, 1.0 / np.sqrt(np.maximum(z, 1.0))),
    ),
    "cauchy": (lambda z: np.log1p(z), lambda z: 1.0 / (1.0 + z)),
}


def _levenberg_marquardt(
    problem, x0, loss="linear", f_scale=1.0, max_nfev=200, ftol=1e-10, xtol=1e-10, max_steps=None, damping=1e-3
) -> _Solution:
    """Levenberg-Marquardt on the normal equations of :meth:`Problem.normal_equations`.

    Minimises ``f^2/2 sum rho((r/f)^2)`` (``||r||^2 / 2`` for the linear loss). A robust loss enters as
    iteratively reweighted least squares: each step solves the normal equations with the weights
    ``rho'((r/f)^2)`` of the current residuals, whose right-hand side is the exact gradient of the robust cost,
    and a step is kept only if it lowers that cost. The damping is ``lambda diag(D)`` with ``D`` the largest
    diagonal of ``J^T W J`` seen so far (MINPACK's scaling, so parameter units do not matter) and lambda follows
    Nielsen's gain-ratio update. The tall array Jacobian is never formed, so a warm refit of four sensors costs a
    few evaluations of ``p x p`` systems instead of a QR of a ``12 N x p`` matrix. ``J^T J`` squares the
    condition number; the scaled system here stays far from float64's limit (parameters move the readings by
    about 1 nT per unit of :attr:`Problem.x_scale`), and a factorisation failure raises the damping instead.

    Bounds of the problem (``problem.lower``, ``problem.upper`` from :meth:`magcal.model.terms.Effect.param_bounds`,
    e.g. a hysteresis width ``>= 0``) are kept by a projected step: a parameter at a bound that the gradient
    pushes out of is held for that step, and the step is clipped into the bounds.

    Stops when the relative cost reduction, both actual and predicted, is below ``ftol``, or the scaled step is
    below ``xtol`` relative to the scaled parameters, or, when the problem's Jacobian is exact
    (``problem.exact_jacobian``: base terms only), before taking it when the next, barely damped step would lower
    the cost by less than ``ftol`` relative: the minimum is then reached to well within the parameters' standard
    errors (``ftol`` of the cost is ``ftol m / 2`` noise variances). With an effect's approximate Jacobian the
    predicted reduction does not measure the distance to the minimum, so only the actual reduction stops. After an accepted step
    the trial point's normal equations are evaluated at once instead of its residuals alone, since they are the
    next iteration's when it is accepted: near the minimum one pass over the data per iteration. ``J^T W J`` is
    returned from the last iterate where it was evaluated, which differs from the returned ``x`` by at most that
    last, converged step.

    ``damping`` is the starting lambda: ``1e-3`` (Nielsen's) from afar; from a start already within a few
    standard errors of the minimum (converged on a subsample, or a warm start from a fit of more data) a
    negligible ``1e-9``, so that the first step is the Gauss-Newton step and lands at the minimum. ``max_steps``
    stops after that many accepted steps (status 4) when the last one lowered the cost by what the quadratic
    model predicted, to within the tolerance: with one step from such a start, the one-step estimator, equal to
    the minimum to first order, for one pass over the data and one evaluation of the residuals. When the cost
    did not fall as predicted (the start was far from the minimum along directions the data barely fix, where
    the model is not quadratic over the step), the iterations go on to the minimum.
    """
    from scipy.linalg import LinAlgError, cho_factor, cho_solve

    rho, drho = LOSSES[loss]
    f2 = float(f_scale) ** 2

    def cost_of(r):
        return 0.5 * f2 * float(np.sum(rho(r**2 / f2))) if np.all(np.isfinite(r)) else np.inf

    def equations(x):
        if loss == "linear":
            return problem.normal_equations(x)
        r = problem.residuals(x)
        return problem.normal_equations(x, weights=drho(r**2 / f2))

    # bounds (Effect.param_bounds, e.g. a hysteresis width >= 0): a parameter held at a bound that the descent
    # direction points out of is left out of the step, and every step is clipped into the bounds
    lower = getattr(problem, "lower", None)
    upper = getattr(problem, "upper", None)
    bounded = lower is not None and upper is not None and (np.any(np.isfinite(lower)) or np.any(np.isfinite(upper)))
    x = np.asarray(x0, dtype=float).copy()
    if bounded:
        x = np.clip(x, lower, upper)
    r, jtj, jtr = equations(x)
    if not np.all(np.isfinite(r)):
        raise CalibrationError("the starting calibration gives non-finite residuals; check the data for NaN")
    nfev, cost = 1, cost_of(r)
    diag = np.maximum(np.diag(jtj), 0.0)
    d = np.maximum(diag, 1e-12 * max(diag.max(), 1e-300))
    lam, nu = float(damping), 2.0
    steps = 0
    optimistic = max_steps is None or max_steps > 1  # the last allowed step needs its residuals only
    exact = bool(getattr(problem, "exact_jacobian", False))
    message, status = "maximum number of evaluations reached", 0
    while nfev < max_nfev:
        if not np.all(np.isfinite(jtj)) or not np.all(np.isfinite(jtr)):
            message, status = "non-finite Jacobian", -1
            break
        free = np.ones(x.size, bool)
        if bounded:
            free = ~(((x <= lower) & (jtr > 0)) | ((x >= upper) & (jtr < 0)))
        if np.max(np.abs(jtr[free]) / np.sqrt(d[free]), initial=0.0) <= 1e-14 * max(np.sqrt(2 * cost), 1e-300):
            message, status = "gradient is zero to machine precision", 1
            break
        try:
            if bounded:
                step = np.zeros_like(x)
                step[free] = cho_solve(cho_factor(jtj[np.ix_(free, free)] + lam * np.diag(d[free])), -jtr[free])
                step = np.clip(x + step, lower, upper) - x
            else:
                step = cho_solve(cho_factor(jtj + lam * np.diag(d)), -jtr)
        except LinAlgError:
            lam, nu = lam * nu, nu * 2
            if lam > 1e16:
                message, status = "the normal equations are singular", -1
                break
            continue
        predicted = -(step @ jtr + 0.5 * step @ jtj @ step)
        small_step = np.sqrt(step**2 @ d) <= xtol * (np.sqrt(x**2 @ d) + xtol)
        if exact and lam <= 1e-2 and (predicted <= ftol * cost or small_step):
            # the (nearly undamped) Gauss-Newton step from here lowers the cost by less than the tolerance
            message = "converged: the next step would lower the cost by less than the tolerance"
            status = 3 if small_step else 2
            break
        x_new = x + step
        # after an accepted step the trial point's normal equations are computed at once (they are the next
        # iteration's if it is accepted, as it nearly always is near the minimum); after a refusal, only its
        # residuals
        with np.errstate(over="ignore", invalid="ignore"):  # a wild trial step is refused below, not warned
            trial = equations(x_new) if optimistic else None
            r_new = trial[0] if trial is not None else problem.residuals(x_new)
        nfev += 1
        cost_new = cost_of(r_new)
        actual = cost - cost_new
        rho_gain = actual / predicted if predicted > 0 else -1.0
        if rho_gain > 0:
            x, r, cost = x_new, r_new, cost_new
            lam, nu = lam * max(1.0 / 3.0, 1.0 - (2.0 * rho_gain - 1.0) ** 3), 2.0
            if trial is not None:
                r, jtj, jtr = trial
            steps += 1
            if (abs(actual) <= ftol * cost and predicted <= ftol * cost) or small_step:
                message = "converged: the relative cost reduction or step is below tolerance"
                status = 3 if small_step else 2
                break
            if max_steps is not None and steps >= max_steps:
                if abs(actual - predicted) <= ftol * cost:
                    message = (
                        f"stopped after {steps} step(s) from the start, as asked: the cost fell as the "
                        "quadratic model predicted, to the tolerance (one-step estimate)"
                    )
                    status = 4
                    break
                max_steps = None  # the model does not hold over the step (far from a flat minimum): go on to it
            if trial is None:
                r, jtj, jtr = equations(x)
                nfev += 1
            d = np.maximum(d, np.diag(jtj))
            optimistic = max_steps is None or steps + 1 < max_steps
        else:
            if small_step:
                message, status = "converged: no smaller step reduces the cost", 3
                break
            lam, nu = lam * nu, nu * 2
            optimistic = False
    return _Solution(x=x, r=r, jtj=jtj, nfev=nfev, message=message, status=status)


def _perpendicular_basis(vectors):
    """Two unit vectors per row, perpendicular to each row of ``vectors`` (N, 3) and to each other."""
    u = unit_rows(vectors)
    helper = np.zeros_like(u)
    helper[np.arange(len(u)), np.argmin(np.abs(u), axis=1)] = 1.0
    e1 = cross_rows(u, helper)
    e1 /= row_norm(e1)[..., None]
    return e1, cross_rows(u, e1)


@dataclass
class FitResult:
    """Outcome of :func:`fit`.

    Attributes
    ----------
    calibration : Calibration
    model : Model
    param_names : list of str
    x : numpy.ndarray
        Fitted parameters (physical units).
    covariance : numpy.ndarray
        Parameter covariance ``s^2 (J^T J)^-1``.
    residuals_nT : numpy.ndarray, shape (n_sensors, N)
        Total-field residuals of every sample; NaN for samples left out of the fit.
    residuals_all_nT : numpy.ndarray, shape (n_sensors, N)
        Total-field residuals of every sample, rejected ones included (for display).
    consistency_residuals_nT : numpy.ndarray, shape (n_sensors, N, 2) or None
        Inter-sensor consistency residuals of the kept samples (arrays with misalignment): the two components
        of ``B_s - mean_s B_s`` perpendicular to the field, scaled to one axis's noise.
    rms_nT : float
        Total-field RMS over all sensors and kept samples.
    rms_per_sensor_nT : numpy.ndarray, shape (n_sensors,)
    noise_nT : float
        Noise estimate ``sqrt(RSS_total / (n - p))`` from the total-field residuals.
    rss : float
        Residual sum of squares of the whole residual vector (nT^2).
    n_residuals, n_params : int
        Independent residuals (total field, plus ``2 (n_sensors - 1)`` consistency values per sample for arrays
        with misalignment) and parameters.
    aic, bic : float
        ``m ln(RSS/m) + 2k`` and ``m ln(RSS/m) + k ln m``.
    outliers : numpy.ndarray of bool, shape (N,)
        Kept samples the fit distrusts (any sensor beyond 5 robust sigma).
    mask : numpy.ndarray of bool, shape (N,)
        Samples used.
    effect_params : list of dict
        ``{effect, sensor (1-based or None), term, params {name: value}, std {name: value}}``.
    reference_kind : str
        ``given``, ``column`` or ``fitted``.
    nfev : int
        Evaluations of the residuals.
    status : int
        As scipy.optimize.least_squares: ``0`` the evaluation limit was reached, ``-1`` the solver failed
        (non-finite or singular normal equations), ``1`` gradient zero, ``2`` cost reduction below tolerance,
        ``3`` step below tolerance; ``4`` (magcal's own) stopped after the ``max_steps`` steps :func:`fit` was
        asked for, the last having lowered the cost as the quadratic model predicted.
    message : str
        The solver's reason for stopping, in words.
    notes : list of Note
        What the fit says besides its figures (:mod:`magcal.core.notes`): a :class:`~magcal.core.errors.ConvergenceWarning`
        note when it did not converge, a :class:`~magcal.core.errors.DataWarning` one when an effect was held on a bound
        of its physical domain. :func:`fit` raises them as warnings unless ``warn=False``.
    bound_pull_z : dict
        Per effect block (label), how far the data pull each parameter past its nearer bound, in standard deviations
        (:func:`magcal.model.terms.bound_pulls`); empty when no parameter sits on a bound.
    """

    calibration: Calibration
    model: Model
    param_names: list
    x: np.ndarray
    covariance: np.ndarray
    residuals_nT: np.ndarray
    residuals_all_nT: np.ndarray
    consistency_residuals_nT: np.ndarray | None
    rms_nT: float
    rms_per_sensor_nT: np.ndarray
    noise_nT: float
    rss: float
    n_residuals: int
    n_params: int
    aic: float
    bic: float
    outliers: np.ndarray
    mask: np.ndarray
    effect_params: list
    reference_kind: str
    nfev: int = 0
    message: str = ""
    status: int = 1
    problem: Problem | None = field(default=None, repr=False)
    notes: list = field(default_factory=list)
    bound_pull_z: dict = field(default_factory=dict)

    @property
    def success(self) -> bool:
        """True when the solver converged (``status > 0``); a fit that stopped early is not a minimum."""
        return self.status > 0

    @property
    def std(self) -> np.ndarray:
        """Standard deviations of the parameters (physical units)."""
        return np.sqrt(np.clip(np.diag(self.covariance), 0, None))

    def summary(self) -> dict:
        """JSON-ready figures of the fit."""
        return {
            "effects": self.model.effect_labels,
            "rms_nT": self.rms_nT,
            "rms_per_sensor_nT": self.rms_per_sensor_nT.tolist(),
            "noise_nT": self.noise_nT,
            "n_params": self.n_params,
            "aic": self.aic,
            "bic": self.bic,
            "reference": self.reference_kind,
            "n_outliers": int(self.outliers.sum()),
            "success": self.success,
            "status": self.status,
            "message": self.message,
            "nfev": self.nfev,
        }


def fit(
    dataset,
    model: Model | None = None,
    init: Calibration | None = None,
    loss="linear",
    f_scale_nT=None,
    mask=None,
    reference_total_nT=None,
    max_nfev=200,
    cost_tolerance=None,
    max_steps=None,
    warn=True,
) -> FitResult:
    """Maximum-likelihood fit of a model, started from a calibration.

    Parameters
    ----------
    dataset : Dataset
    model : Model, optional
        Defaults to the base model (bias, scale, non-orthogonality, misalignment for arrays).
    init : Calibration, optional
        Warm start, normally the two-step ellipsoid + Procrustes result. Without it a rough sphere-fit start
        is used (:func:`crude_initial_calibration`).
    loss : {'linear', 'soft_l1', 'huber', 'cauchy'}
        scipy's loss; a robust one keeps the fit on the inliers when some samples are gross outliers.
    f_scale_nT : float, optional
        Residual size (nT) where a robust loss starts to down-weight; default 3x a robust noise estimate.
    mask : array_like of bool, shape (N,), optional
        Samples to use (True = kept); rejected samples are excluded from the fit. With an effect that needs each
        sample's attitude (``site_gradient``), samples without one are left out too (a world-fixed gradient has
        no prediction there), with a :class:`~magcal.core.errors.DataWarning` note counting them and naming their
        rows; :attr:`FitResult.mask` says which samples were fitted.
    reference_total_nT : float, optional
        Known total field; otherwise the dataset's reference, its ``ref_total`` column, or fitted.
    max_nfev : int
        Cap on evaluations of the residuals (each round of a robust fit has its own).
    cost_tolerance : float, optional
        Stop once a step lowers the cost ``||r||^2 / 2`` by less than this many noise variances (estimated as
        ``||r||^2 / (m - p)``): parameters then lie within about ``sqrt(2 cost_tolerance)`` standard errors of the
        minimum. Default: a relative reduction of 1e-10 (far tighter); the diagnosis judges its refits with 0.01,
        which is irrelevant to a change of the information criterion or of a held-out RMS.
    max_steps : int, optional
        Stop after this many accepted steps (status 4) if the last one lowered the cost by what the quadratic
        model predicted, to within the tolerance; else go on to the minimum. ``max_steps=1`` from a warm start
        that is already within a few standard errors of the minimum (``init`` fitted on a superset of the
        samples) gives the one-step estimator: one Gauss-Newton step, equal to the minimum to first order in the
        distance from the start (Le Cam), for one pass over the data; :func:`magcal.fitting.validation.validate` fits
        its training samples so. Where the data barely fix some directions the start can be far from the
        training samples' minimum along them; the cost then does not fall as predicted and the fit converges.
    warn : bool
        Raise the result's ``notes`` as Python warnings (the default: ``magcal.fit`` is a public name); the
        engine's steps pass False and hand the notes on in their own results (they may run on threads).

    Returns
    -------
    FitResult

    Warns
    -----
    ConvergenceWarning
        When the fit did not converge and ``warn`` (its ``notes`` hold the same).

    Notes
    -----
    Effects with constants estimated from the data (the hysteresis play width, the time of a bias step) refine
    them from the converged fit (:meth:`magcal.model.terms.Effect.refine` with a :class:`RefineContext`) and the
    model is fitted once more; the refined constants are kept only if that lowers the residual sum of squares.
    """
    # the caller's model (and its effect objects, whose data-derived constants a fit sets) stays untouched
    model = model.copy() if model is not None else Model.base_model(dataset.n_sensors)
    if model.n_sensors != dataset.n_sensors:
        raise CalibrationError(f"the model is for {model.n_sensors} sensor(s), the data have {dataset.n_sensors}")
    model.check(dataset)
    n_all = dataset.n_samples
    mask = np.ones(n_all, bool) if mask is None else np.asarray(mask, bool)
    if mask.shape != (n_all,):
        raise CalibrationError(f"mask has shape {mask.shape}, expected ({n_all},)")
    mask, gap_note = leave_out_rows_without_attitude(dataset, model, mask)
    options = _Options(loss, f_scale_nT, reference_total_nT, max_nfev, cost_tolerance, max_steps)
    # the normal equations' tall, thin products on one BLAS thread: see ONE_BLAS_THREAD_READINGS
    with one_blas_thread(int(mask.sum()) * dataset.n_sensors >= ONE_BLAS_THREAD_READINGS):
        result = _fit_once(dataset, model, init, mask, options)
        # effects whose basis has a data-derived shape (the hysteresis loop width) refine it from the fit, then one
        # more fit; the refined shape is kept only if it fits better
        saved = [e.state() for e in model.effects]
        context = RefineContext(result.problem, result.x)
        if any([e.refine(result.calibration.effect_values, context) for e in model.effects]):
            second = _fit_once(dataset, model, result.calibration, mask, options, configure=False)
            if second.rss < result.rss:
                second.nfev += result.nfev
                result = second
            else:
                for e, state in zip(model.effects, saved):
                    e.set_state(state)
    if gap_note is not None:
        result.notes.insert(0, gap_note)
    result = _note_if_not_converged(result)
    fitted = result.calibration.model
    held = (
        fitted_outside_domain(fitted, result.calibration.effect_values, pulls=result.bound_pull_z)
        if fitted is not None
        else ""
    )
    if held:
        result.notes.append(Note(held_note_text(held), DataWarning, "fit"))
    if warn:
        _notes.warn(result.notes)
    return result


def leave_out_rows_without_attitude(dataset, model, mask, what="the fit"):
    """``(mask, note)``: the chosen samples less those without attitude when an effect of ``model`` needs it
    (:func:`magcal.model.terms.rows_without_attitude`: ``site_gradient`` has no prediction there), and the
    :class:`~magcal.core.errors.DataWarning` note that counts them and names their rows (None when none was left
    out).

    Raises
    ------
    CalibrationError
        When no chosen sample has an attitude.
    """
    missing = rows_without_attitude(model, dataset)
    if missing is None or not (missing & mask).any():
        return mask, None
    labels = attitude_effects(model)
    keep = mask & ~missing
    if not keep.any():
        raise CalibrationError(
            f"{dataset.source or 'the data'}: none of the {int(mask.sum())} chosen samples has an attitude "
            f"({row_runs(missing & mask)} have none); {', '.join(labels)} needs each sample's attitude: fit without "
            "it, or give the attitude (qw, qx, qy, qz)"
        )
    return keep, Note(without_attitude_note(missing, mask, labels, what), DataWarning, "fit")


def _bound_pulls(problem, model, x, cov) -> dict:
    """Per effect block, how far the data pull each parameter past its nearer bound (standard deviations,
    :func:`magcal.model.terms.bound_pulls`); empty when no parameter sits on a bound (the usual case: no extra pass)."""
    lower, upper = problem.lower, problem.upper
    if not np.any((x <= lower) | (x >= upper)):
        return {}
    _, jtj, jtr = problem.normal_equations(x)
    z = bound_pulls(x, lower, upper, jtr, np.linalg.pinv(jtj), np.sqrt(np.clip(np.diag(cov), 0.0, None)))
    return {block_label(e, s): z[problem.blocks[block_label(e, s)]] for e, s in model.instances()}


def _note_if_not_converged(result: FitResult) -> FitResult:
    if not result.success:
        result.notes.append(
            Note(
                f"the fit did not converge ({result.message}, {result.nfev} evaluations): its parameters "
                "are not a minimum; raise max_nfev or check the data",
                ConvergenceWarning,
                "fit",
            )
        )
    return result


class RefineContext:
    """What an effect may use to refine its data-derived constants after a converged fit.

    Parameters
    ----------
    problem : Problem
        The fitted problem (its dataset is the kept samples).
    x : numpy.ndarray
        The fitted parameters.
    """

    def __init__(self, problem, x):
        self.problem = problem
        self.x = x
        self.dataset = problem.dataset
        self._fitted = None  # (fields, residuals, cost per sample, perpendicular basis), once asked for

    def cost_per_sample(self, effect, state) -> np.ndarray:
        """Squared residuals (nT^2) per sample, all sensors' total-field and consistency rows together, with the
        fitted parameters and ``effect``'s data-derived constants temporarily set to ``state``."""
        saved = effect.state()
        effect.set_state(state)
        try:
            return self.cost_of_fields(self.problem.fields(self.x))
        finally:
            effect.set_state(saved)

    def fields(self) -> np.ndarray:
        """The corrected fields (n_sensors, N, 3) of the fit, nT (for an effect that knows how a change of its
        constants moves them, so that each trial costs only :meth:`cost_of_fields`)."""
        return self.problem.fields(self.x)

    def sensors(self) -> list:
        """The fitted :class:`~magcal.calibration.calibration.SensorCalibration` of each sensor."""
        return self.problem.sensors(self.x)

    def values(self) -> dict:
        """The fitted parameters of each effect instance, by :func:`~magcal.calibration.calibration.block_label`."""
        return self.problem.effect_values(self.x)

    def cost_with_sensor_moved(self, sensor, delta_nT) -> np.ndarray:
        """:meth:`cost_of_fields` of the fitted fields with sensor ``sensor``'s moved by ``delta_nT`` (N, 3), nT,
        from that sensor's samples alone.

        The other sensors' total-field rows do not change; the consistency rows of all sensors do, through the
        mean: with ``d_k`` the deviations from the mean and ``P`` the projection perpendicular to it, moving
        sensor ``s`` by ``delta`` adds ``f^2 (2 P d_s . P delta) + |P delta|^2`` (``f^2 = n/(n-1)``, the rows'
        scale squared) to the sum of the squared consistency rows. The perpendicular basis is held at the fitted
        mean (the mean moves by ``delta / n``, a few nT of tens of thousands: the change is second order).
        """
        fields, r, base, basis = self._fitted_costs()
        problem = self.problem
        ns, n = problem.n_sensors, problem.n_samples
        delta = np.asarray(delta_nT, float)
        tf = r[sensor * n : (sensor + 1) * n]
        new_tf = row_norm(fields[sensor] + delta) - (row_norm(fields[sensor]) - tf)  # the expected field held
        cost = base + (new_tf - tf) * (new_tf + tf)
        if problem.coupled:
            f = problem._consistency_factor
            deviation = r[ns * n :].reshape(ns, n, 2)[sensor] / f  # P d_s: the fit's consistency rows, unscaled
            for k, e in enumerate(basis):
                pd = np.einsum("ni,ni->n", delta, e)
                cost += pd * (2.0 * f**2 * deviation[:, k] + pd)
        return cost

    def _fitted_costs(self):
        """``(fields, residuals, cost per sample, perpendicular basis or None)`` at the fit, computed once."""
        if self._fitted is None:
            fields = self.problem.fields(self.x)
            mean = fields.mean(axis=0) if self.problem.coupled else None
            basis = _perpendicular_basis(mean) if self.problem.coupled else None
            r = self.problem._residuals_from_fields(fields, self.x, basis, mean)
            self._fitted = (fields, r, self._cost_of_residuals(r), basis)
        return self._fitted

    def _cost_of_residuals(self, r):
        ns, n = self.problem.n_sensors, self.problem.n_samples
        cost = np.sum(r[: ns * n].reshape(ns, n) ** 2, axis=0)
        if self.problem.coupled:
            cost += np.sum(r[ns * n :].reshape(ns, n, 2) ** 2, axis=(0, 2))
        return cost

    def cost_of_fields(self, fields) -> np.ndarray:
        """:meth:`cost_per_sample` of given corrected fields (n_sensors, N, 3) with the fitted parameters (the
        expected total field, reference-stage effects included, as fitted)."""
        return self._cost_of_residuals(self.problem._residuals_from_fields(fields, self.x))


@dataclass(frozen=True)
class _Options:
    """The solver's options of one :func:`fit` (its arguments of the same names)."""

    loss: str
    f_scale_nT: float | None
    reference_total_nT: float | None
    max_nfev: int
    cost_tolerance: float | None
    max_steps: int | None


def _fit_once(dataset, model, init, mask, options: _Options, configure=True) -> FitResult:
    """One fit of :func:`fit` (arguments checked there); ``configure=False`` keeps the effects' data-derived
    constants as they are (the pass after :meth:`~magcal.model.terms.Effect.refine`)."""
    kept = dataset.masked(mask)  # the same samples, the same dataset: its readings' facts are computed once
    init = init or crude_initial_calibration(kept, options.reference_total_nT)
    if configure and model.effects:
        _configure_effects(kept, model, init, options.reference_total_nT)
    problem = Problem(kept, model, init, options.reference_total_nT)
    if options.loss not in LOSSES:
        raise CalibrationError(f"unknown loss {options.loss!r}; choose one of {', '.join(LOSSES)}")
    ftol = 1e-10
    if options.cost_tolerance is not None:  # in noise variances: relative to the cost, 2 tol / (m - p)
        ftol = max(ftol, 2.0 * float(options.cost_tolerance) / max(problem.n_residuals - problem.x0.size, 1))
    if options.loss == "linear":
        sol = _solve_linear(problem, kept, model, init, options, ftol)
    else:
        sol = _solve_robust(problem, options, ftol)
    return _fit_result(dataset, model, problem, mask, sol)


def _configure_effects(kept, model, init, reference_total_nT) -> None:
    """The effects' data-derived constants, from the total-field residuals of the start."""
    ref0, kind0 = fit_reference(kept, reference_total_nT)
    start_fields = corrected_fields(kept, init.sensors)
    if kind0 == "fitted":
        expected0 = init.reference_total_nT or float(np.mean(row_norm(start_fields)))
    else:
        expected0 = expected_total_field(kept, ref0)
    base_resid = row_norm(start_fields) - expected0
    for e in model.effects:
        e.configure(kept, base_resid)


def _solve_linear(problem, kept, model, init, options: _Options, ftol) -> _Solution:
    """The least squares of the plain loss: warmed up on an even subsample of a large record, then on every
    sample (one Gauss-Newton step when the warm-up lands next to the minimum)."""
    x0, nfev0 = problem.x0, 0
    readings = problem.n_samples * problem.n_sensors
    if not model.effects and readings > 2 * WARMUP_SAMPLES and options.max_steps is None:
        # converge on an even subsample first (same parametrisation: the same model and start), so that the
        # passes over every sample start next to their minimum
        every = int(np.ceil(readings / WARMUP_SAMPLES))
        warm = _levenberg_marquardt(
            Problem(kept.subset(np.arange(0, kept.n_samples, every)), model, init, options.reference_total_nT),
            problem.x0,
            max_nfev=options.max_nfev,
        )
        if warm.status > 0:
            x0, nfev0 = warm.x, warm.nfev
    # next to the minimum (warmed up, or one step asked for) the first step is the Gauss-Newton one
    near = nfev0 > 0 or options.max_steps is not None
    # warmed up (an exact Jacobian: base terms), the start lies within a few standard errors of the minimum
    # (sqrt(N / WARMUP_SAMPLES) of them at most), so one Gauss-Newton step lands on it to second order in
    # that distance: when the cost falls as the quadratic model predicts, the fit stops there, with the
    # residuals of that point and J^T J of the start (one pass over the record with derivatives, one
    # without, where a second pass with derivatives only confirmed that the next step is negligible)
    one_step = ONE_STEP_AFTER_WARMUP and nfev0 > 0 and options.max_steps is None and problem.exact_jacobian
    sol = _levenberg_marquardt(
        problem,
        x0,
        max_nfev=options.max_nfev,
        ftol=ftol,
        max_steps=1 if one_step else options.max_steps,
        damping=1e-9 if near else 1e-3,
    )
    if one_step and sol.status == 4:
        sol.status = 2
        sol.message = (
            "converged: from the minimum of an even subsample, one Gauss-Newton step lowered the cost as the "
            "quadratic model predicted, to the tolerance"
        )
    sol.nfev += nfev0
    return sol


#: Rounds of a robust fit whose scale follows the residuals (:func:`magcal.fitting.solver.reweighted_fit`).
ROBUST_ROUNDS = 4


def _solve_robust(problem, options: _Options, ftol) -> _Solution:
    """The least squares of a robust loss. Without a given scale, the scale follows the residuals as the fit
    converges (:data:`magcal.fitting.solver.ROBUST_SCALE` robust standard deviations of the total field, re-estimated
    each round), so that gross outliers stop pulling on it."""
    rows = problem.total_field_rows
    nfev = 0

    def solve(x, sigmas):
        nonlocal nfev
        scale = options.f_scale_nT if options.f_scale_nT is not None else ROBUST_SCALE * sigmas[0]
        sol = _levenberg_marquardt(
            problem,
            x,
            loss=options.loss,
            f_scale=scale,
            max_nfev=options.max_nfev,
            ftol=ftol,
            max_steps=options.max_steps,
        )
        nfev += sol.nfev
        return sol.x, sol

    rounds = 1 if options.f_scale_nT is not None else ROBUST_ROUNDS
    found = reweighted_fit(
        solve, lambda x: [problem.residuals(x)[rows]], [NoiseGroup(1e-9)], problem.x0, rounds=rounds, tolerance=0.0
    )
    sol = found.solution
    sol.r, sol.jtj, _ = problem.normal_equations(found.x)
    sol.nfev = nfev
    return sol


def _fit_result(dataset, model, problem, mask, sol: _Solution) -> FitResult:
    """The :class:`FitResult` of a solution: noise, covariance, outliers, AIC/BIC from the same residuals."""
    x, r, jtj = sol.x, sol.r, sol.jtj
    ns, n = problem.n_sensors, problem.n_samples
    tf = r[problem.total_field_rows].reshape(ns, n)
    p = x.size
    rss = float(r @ r)
    # independent residuals: the consistency rows of one sample sum to zero over the sensors
    m = ns * n + (2 * (ns - 1) * n if problem.coupled else 0)
    cov = normal_covariance(jtj, rss / max(m - p, 1))
    cov = np.full((p, p), np.nan) if cov is None else cov

    calibration = problem.calibration(x)
    if mask.all() and not model.effects:  # the fitted rows are every sample's residual already
        resid_all = tf.copy()
    else:
        resid_all = calibration.total_field_residuals(dataset)
    outliers = np.zeros(dataset.n_samples, bool)
    outliers[np.flatnonzero(mask)] = beyond(tf, robust_sigma(tf, floor=1e-9), axis=0)
    rms_per_sensor = np.sqrt(np.mean(tf**2, axis=1))
    calibration.summary = {"n_samples": int(mask.sum()), "rms_nT": float(np.sqrt(np.mean(tf**2)))}
    for s, cal in enumerate(calibration.sensors):
        cal.summary = {"rms_nT": float(rms_per_sensor[s])}
    result = FitResult(
        calibration=calibration,
        model=model,
        param_names=problem.param_names,
        x=x,
        covariance=cov,
        residuals_nT=np.where(mask[None, :], resid_all, np.nan),
        residuals_all_nT=resid_all,
        consistency_residuals_nT=r[ns * n :].reshape(ns, n, 2) if problem.coupled else None,
        rms_nT=float(np.sqrt(np.mean(tf**2))),
        rms_per_sensor_nT=rms_per_sensor,
        noise_nT=float(np.sqrt(float(np.sum(tf**2)) / max(ns * n - p, 1))),
        rss=rss,
        n_residuals=m,
        n_params=p,
        aic=m * np.log(rss / m) + 2 * p,
        bic=m * np.log(rss / m) + p * np.log(m),
        outliers=outliers,
        mask=mask,
        effect_params=_effect_params(problem, model, x, cov),
        reference_kind=problem.reference_kind,
        nfev=int(sol.nfev),
        message=sol.message,
        status=int(sol.status),
        problem=problem,
        bound_pull_z=_bound_pulls(problem, model, x, cov),
    )
    calibration.base_covariance = base_covariance(result)  # the error bars the calibration carries to apply
    return result


def _effect_params(problem, model, x, cov) -> list:
    """``{effect, sensor (1-based or None), term, params, std}`` of every effect instance."""
    std = np.sqrt(np.clip(np.diag(cov), 0, None))
    out = []
    for e, s in model.instances():
        sl = problem.blocks[block_label(e, s)]
        names = e.param_names()
        out.append(
            {
                "effect": e.name,
                "sensor": None if s is None else s + 1,
                "term": e.label,
                "params": dict(zip(names, x[sl].tolist())),
                "std": dict(zip(names, std[sl].tolist())),
            }
        )
    return out
