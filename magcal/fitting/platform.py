"""Level-table platform alignment: every sensor's rotation into the carrier platform's frame (patent S5-S8).

The procedure (Ocean University of China patent, 2019, steps S7-S8): after each sensor's intrinsic calibration
(bias, scale, non-orthogonality from a scalar calibration, S3-S4), the array is put on a level table three times,
with the platform's x axis vertical, then its y axis, then its z axis, and turned freely about the vertical each
time. A ``group`` column labels the samples ``x_up``, ``y_up``, ``z_up`` (``x_down`` ... for an axis pointing down;
other labels are ignored here).

Physics. Let ``R_i`` take sensor ``i``'s corrected vector ``v = C^-1 (y - b)`` into the platform frame, so the
platform-frame field is ``B_p = R_i v``. In group ``g`` the platform axis ``a_g`` points up and the array turns
about it, so the vertical component of the field in the platform frame, ``a_g . B_p = U_g``, is the same for every
sample of the group while the horizontal part (magnitude ``H = F cos I``) turns. In the sensor frame the samples
therefore lie on a circle in the plane ``r_g . v = U_g`` with ``r_g = R_i^T a_g``: the plane's normal *is* the
platform axis seen by the sensor. Each group pins two of the three rotation angles (the tilts of ``a_g``); the
rotation about ``a_g`` itself is left free by that group and pinned by the others, so two groups determine ``R_i``
and three over-determine it (the angles between the three estimated axes then check the procedure: 90 deg).

Estimator. A start from the plane normals (total least squares per group, a sign fixed by a prior rotation),
joined by a Kabsch rotation, then maximum likelihood: least squares of ``a_g^T R_i v_k - U_g`` over ``R_i``
(3 angles) and one ``U_g`` per group (nuisance; the table may be moved between groups). The horizontal
components carry no information on ``R_i`` (the heading is unknown per sample), so this is the full likelihood
for isotropic Gaussian noise. The covariance ``s^2 (J^T J)^-1`` is the Cramer-Rao bound; its size is about
``sigma / (H sqrt(N_g))`` rad per angle: for the seed's sigma = 3 nT, F = 50 000 nT, I = 55 deg (H = 28 700 nT)
and 100 samples per group, about 1e-5 rad (0.0006 deg).

What it assumes. The platform's axis is perpendicular to the table's top and the array turns about the table's
normal; the table itself need not be level (a constant tilt only changes ``U_g``). A platform seated at an angle
``delta`` to the table's normal tilts the estimated axis by ``delta``: the procedure is only as good as the seat.
The intrinsic calibration's own errors (sd of the C^-1 gauge angles ~ (sigma/F) sqrt(15/N_cal)) enter the
alignment one to one: :func:`align` propagates them when given their covariance.

The patent's claim. "Parameter estimation error at the 1/1000 level" in simulation. At the seed's noise
(3 nT) the Cramer-Rao bound of the misalignment angles is 1.05e-5 rad with 100 samples per group, and this
estimator reaches it (Monte Carlo RMS / bound 0.96). Read as 1/1000 of the angles themselves (0.012-0.038 rad in
the test truth, i.e. 12-38 urad), the claim holds - but at the physical floor for the smallest angles, and only
with about 100 samples per group or more (25 per group give a 22 urad floor). Read as an absolute 1e-3 rad
(0.06 deg), the claim is ~100 times weaker than what the data support. ``benchmarks/platform_alignment.py`` prints
the figures (recorded in ``benchmarks/README.md``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from magcal.calibration.calibration import Calibration, corrected_fields
from magcal.core import conventions
from magcal.core.errors import DataWarning, MagcalError
from magcal.core.notes import Note
from magcal.data import simulation as sim
from magcal.data.dataset import Dataset, DatasetError
from magcal.data.simulation import chi2017_truth
from magcal.fitting.pipeline import calibrate
from magcal.model.terms import Model, contexts

#: Group labels and the platform axis (unit vector, platform frame) that points up in each.
GROUP_AXES = {
    "x_up": np.array([1.0, 0.0, 0.0]),
    "y_up": np.array([0.0, 1.0, 0.0]),
    "z_up": np.array([0.0, 0.0, 1.0]),
    "x_down": np.array([-1.0, 0.0, 0.0]),
    "y_down": np.array([0.0, -1.0, 0.0]),
    "z_down": np.array([0.0, 0.0, -1.0]),
}

#: Fewest samples per group.
MIN_GROUP_SAMPLES = 5

#: A group whose in-plane spread (second over first singular value of the centred vectors) is below this was
#: hardly turned: its plane, hence its axis, is not determined.
MIN_TURN_RATIO = 0.1

#: The seed's "parameter estimation error at the 1/1000 level" (patent 2019, simulation), relative.
PATENT_CLAIM_RELATIVE = 1e-3


# -- simulation ---------------------------------------------------------------------------------------------------
def platform_truth():
    """Chi et al. (2017) Table 1 sensors, with sensor 1 also misaligned to the carrier platform.

    Sensors 2-4 keep Table 1's angles relative to the platform; sensor 1 gets (alpha, beta, gamma) =
    (0.012, -0.017, 0.021) rad, so no sensor's frame is the platform's.
    """

    truth = chi2017_truth()
    s1 = truth.sensors[0]
    truth.sensors[0] = dataclasses.replace(s1, alpha=0.012, beta=-0.017, gamma=0.021)
    return truth


def _up_rotation(axis_up):
    """Rotation (platform -> world NED) taking the platform vector ``axis_up`` onto world up (0, 0, -1)."""
    up = np.array([0.0, 0.0, -1.0])
    a = np.asarray(axis_up, dtype=float)
    if np.allclose(a, -up):
        return Rotation.from_rotvec([np.pi, 0.0, 0.0])
    rot, _ = Rotation.align_vectors(up[None], a[None])
    return rot


def simulate_level_table(
    truth=None,
    n_per_group=100,
    noise_nT=3.0,
    seed=0,
    groups=("x_up", "y_up", "z_up"),
    n_free=0,
    heading_range_deg=360.0,
    seat_error_deg=0.0,
    rate_hz=None,
) -> Dataset:
    """Simulated level-table records: the array turned about the vertical with each platform axis up in turn.

    Parameters
    ----------
    truth : ArrayTruth, optional
        Sensors' errors; their misalignment angles are relative to the *platform* frame. Default
        :func:`platform_truth`.
    n_per_group : int
        Samples per group.
    noise_nT : float
        Gaussian noise sigma per axis, nT.
    seed : int
    groups : sequence of str
        Labels from :data:`GROUP_AXES`.
    n_free : int
        Extra samples at random attitudes, labelled ``free`` (for a scalar calibration from the same file).
    heading_range_deg : float
        Headings are drawn uniformly in ``[0, heading_range_deg)``.
    seat_error_deg : float
        The platform sits tilted by this angle (random direction, one per group) from the table's normal.
    rate_hz : float, optional
        Adds a time column at this rate.

    Returns
    -------
    Dataset
        With ``group`` labels, attitudes (platform -> world) and ``reference_total_nT``.
    """

    truth = platform_truth() if truth is None else truth
    rng = np.random.default_rng(seed)
    atts, labels = [], []
    for g in groups:
        if g not in GROUP_AXES:
            raise ValueError(f"unknown group {g!r}; use {', '.join(GROUP_AXES)}")
        base = _up_rotation(GROUP_AXES[g])
        if seat_error_deg:
            tilt_axis = np.cross(GROUP_AXES[g], rng.normal(size=3))
            tilt_axis /= np.linalg.norm(tilt_axis)
            base = base * Rotation.from_rotvec(np.radians(seat_error_deg) * tilt_axis)
        heading = rng.uniform(0.0, np.radians(heading_range_deg), n_per_group)
        atts.append(Rotation.from_euler("z", heading[:, None]) * base)
        labels += [g] * n_per_group
    if n_free:
        atts.append(Rotation.random(n_free, random_state=rng))
        labels += ["free"] * n_free
    att = Rotation.concatenate(atts)
    fields = sim.true_fields(truth, att)
    clean = np.stack([s.measure(f) for s, f in zip(truth.sensors, fields)])
    readings = clean + rng.normal(0.0, noise_nT, clean.shape) if noise_nT > 0 else clean
    xyzw = att.as_quat()
    n = readings.shape[1]
    return Dataset(
        readings_nT=readings,
        attitude_wxyz=np.column_stack([xyzw[:, 3], xyzw[:, :3]]),
        group=np.array(labels),
        time_s=None if rate_hz is None else np.arange(n) / float(rate_hz),
        reference_total_nT=truth.total_nT,
        baseline_m=truth.baseline_m if truth.n_sensors > 1 else None,
        noise_nT=float(noise_nT),
        metadata={"simulated": "true", "procedure": "level table (patent S7)"},
    )


# -- estimation ---------------------------------------------------------------------------------------------------
@dataclass
class PlatformAlignment:
    """Result of :func:`estimate_alignment`.

    Attributes
    ----------
    R : numpy.ndarray, shape (n_sensors, 3, 3)
        Rotation taking each sensor's corrected vector into the platform frame (the ``R`` of a calibration whose
        ``frame`` is ``"platform"``).
    angles_rad : numpy.ndarray, shape (n_sensors, 3)
        The seed's misalignment angles (alpha, beta, gamma) of ``M = R^T`` (eq. 3), rad.
    angles_std_rad : numpy.ndarray, shape (n_sensors, 3)
        Their standard deviations (Cramer-Rao level, from the fit), rad.
    rotation_cov_rad2 : numpy.ndarray, shape (n_sensors, 3, 3)
        Covariance of the small rotation about the platform's x, y, z axes, rad^2.
    vertical_nT : numpy.ndarray, shape (n_sensors, n_groups)
        Vertical field component ``U_g`` in each group, nT.
    residual_rms_nT : numpy.ndarray, shape (n_sensors, n_groups)
        RMS of ``a_g^T R v - U_g`` per group (should be the noise), nT.
    axis_angles_deg : numpy.ndarray, shape (n_sensors, 3)
        Angles between the per-group axis estimates (x-y, x-z, y-z; NaN if a group is missing), deg: 90 for a
        consistent procedure.
    groups : list of str
    counts : list of int
    noise_nT : float
        The per-axis noise used for the covariance (the residual estimate unless given).
    intrinsic_included : bool
        True if the intrinsic calibration's uncertainty is propagated into the covariances.
    remarks : list of str
        What the report says besides its figures (samples not used, the intrinsic calibration's origin, a vertical
        component that changes sign); saved as ``notes`` in the calibration file.
    notes : list of Note
        What the user must hear (:mod:`magcal.core.notes`): group labels that look wrong and, from :func:`align`,
        the notes of the scalar calibration it fitted first. Never raised here: ``magcal align`` prints them.
    """

    R: np.ndarray
    angles_rad: np.ndarray
    angles_std_rad: np.ndarray
    rotation_cov_rad2: np.ndarray
    vertical_nT: np.ndarray
    residual_rms_nT: np.ndarray
    axis_angles_deg: np.ndarray
    groups: list
    counts: list
    noise_nT: float
    intrinsic_included: bool = False
    remarks: list = field(default_factory=list)
    notes: list = field(default_factory=list)

    @property
    def rotation_std_rad(self) -> np.ndarray:
        """Standard deviation of the small rotation about the platform's x, y, z axes (n_sensors, 3), rad."""
        return np.sqrt(np.clip(np.diagonal(self.rotation_cov_rad2, axis1=1, axis2=2), 0, None))

    def to_dict(self) -> dict:
        """JSON-ready figures (stored as ``platform_alignment`` in the calibration file)."""
        return {
            "method": "level table (patent S5-S8): plane of each group, maximum likelihood",
            "groups": dict(zip(self.groups, self.counts)),
            "noise_nT": self.noise_nT,
            "intrinsic_uncertainty_included": self.intrinsic_included,
            "sensors": [
                {
                    "id": i + 1,
                    "angles_rad": self.angles_rad[i].tolist(),
                    "angles_std_rad": self.angles_std_rad[i].tolist(),
                    "rotation_std_rad": self.rotation_std_rad[i].tolist(),
                    "vertical_nT": dict(zip(self.groups, self.vertical_nT[i].tolist())),
                    "residual_rms_nT": dict(zip(self.groups, self.residual_rms_nT[i].tolist())),
                    "axis_angles_deg": [None if not np.isfinite(a) else float(a) for a in self.axis_angles_deg[i]],
                }
                for i in range(self.R.shape[0])
            ],
            "notes": list(self.remarks),
        }

    def text(self) -> str:
        """Readable report."""
        lines = [
            "platform alignment (level table, patent S5-S8): "
            + ", ".join(f"{g} {n} samples" for g, n in zip(self.groups, self.counts)),
            f"noise used for the uncertainties: {self.noise_nT:.3g} nT per axis"
            + (" (intrinsic calibration's uncertainty included)" if self.intrinsic_included else ""),
            "sensor  alpha (mrad)        beta (mrad)         gamma (mrad)        residual RMS (nT)   axes (deg)",
        ]
        for i in range(self.R.shape[0]):
            ang = "  ".join(
                f"{1e3 * a:+8.4f} +- {1e3 * s:.4f}" for a, s in zip(self.angles_rad[i], self.angles_std_rad[i])
            )
            res = "/".join(f"{r:.2f}" for r in self.residual_rms_nT[i])
            axes = "/".join("-" if not np.isfinite(a) else f"{a:.3f}" for a in self.axis_angles_deg[i])
            lines.append(f"  {i + 1}     {ang}   {res:18s}  {axes}")
        for remark in self.remarks:
            lines.append(f"note: {remark}")
        return "\n".join(lines)


def _group_axes(group, source):
    if group is None:
        raise DatasetError(
            f"{source}: the level-table alignment needs a group column labelling the samples x_up, y_up, z_up "
            "(the platform axis that was vertical while the array was turned)"
        )
    labels = np.char.lower(np.char.strip(np.asarray(group).astype(str)))
    present = [g for g in GROUP_AXES if np.any(labels == g)]
    if not present:
        found = ", ".join(sorted(set(labels.tolist()))[:8])
        raise DatasetError(
            f"{source}: no level-table groups; the group column holds {found or 'nothing'}, expected x_up, y_up, z_up "
            "(or x_down, y_down, z_down)"
        )
    axes = {tuple(np.abs(GROUP_AXES[g])) for g in present}
    if len(axes) < 2:
        raise DatasetError(
            f"{source}: only the group(s) {', '.join(present)}: one vertical axis leaves the rotation about it "
            "undetermined; record at least two of x_up, y_up, z_up (all three check each other)"
        )
    for g in present:
        n = int(np.sum(labels == g))
        if n < MIN_GROUP_SAMPLES:
            raise DatasetError(
                f"{source}: group {g} has {n} sample(s); record at least {MIN_GROUP_SAMPLES} (some tens) while turning "
                "the array about the vertical"
            )
    return labels, present


def _plane_normal(v):
    centred = v - v.mean(axis=0)
    _, s, vt = np.linalg.svd(centred, full_matrices=False)
    return vt[2], s


def estimate_alignment(vectors_nT, group, noise_nT=None, prior_R=None, source="data", fixed_signs=None):
    """Each sensor's rotation into the platform frame from level-table groups; never warns (its ``remarks`` say
    what it found, its ``notes`` what a user must hear: group labels that look wrong).

    Parameters
    ----------
    vectors_nT : array_like, shape (n_sensors, N, 3)
        Intrinsically corrected vectors ``C^-1 (y - b)`` in each sensor's own frame, nT.
    group : array_like of str, shape (N,)
        Group labels (:data:`GROUP_AXES`; others are ignored).
    noise_nT : float, optional
        Per-axis noise sigma for the Cramer-Rao covariance; the residual estimate if omitted.
    prior_R : array_like, shape (n_sensors, 3, 3), optional
        A rough rotation of each sensor into the platform frame (default identity), used only to tell which side
        of each plane is "up".
    source : str
        Name for messages.

    Returns
    -------
    PlatformAlignment

    Raises
    ------
    DatasetError
        No or too few groups, a group not turned about the vertical.
    """
    v_all = np.asarray(vectors_nT, dtype=float)
    if v_all.ndim == 2:
        v_all = v_all[None]
    labels, present = _group_axes(group, source)
    n_sensors = v_all.shape[0]
    prior = np.broadcast_to(np.eye(3), (n_sensors, 3, 3)) if prior_R is None else np.asarray(prior_R, float)
    masks = [labels == g for g in present]
    counts = [int(m.sum()) for m in masks]
    axes_up = np.array([GROUP_AXES[g] for g in present])
    remarks, notes = [], []
    other, other_n = np.unique(labels[~np.isin(labels, present)], return_counts=True)
    if other.size:
        remarks.append(
            "samples not used by the alignment: "
            + ", ".join(f"{lab or '(empty)'} ({n})" for lab, n in zip(other[:8], other_n[:8]))
        )
    R_out, ang, ang_std, cov_out, vert, rms, axang = [], [], [], [], [], [], []
    sigma_used = []
    for s in range(n_sensors):
        normals = []
        for g, m in zip(present, masks):
            v = v_all[s][m]
            normal, sv = _plane_normal(v)
            if sv[1] < MIN_TURN_RATIO * sv[0] or sv[0] <= 0:
                raise DatasetError(
                    f"{source}: group {g}, sensor {s + 1}: the array was hardly turned about the vertical (the field "
                    "barely changed direction); turn it through at least 90 deg, ideally a full turn"
                )
            expected = prior[s].T @ GROUP_AXES[g]  # the up axis seen by the sensor
            if normal @ expected < 0:
                normal = -normal
            normals.append(normal)
        normals = np.array(normals)
        r0, _ = Rotation.align_vectors(axes_up, normals)  # r0 maps sensor-frame normals onto platform axes
        R0 = r0.as_matrix()
        W = [v_all[s][m] @ R0.T for m in masks]  # start-rotated vectors per group

        def residuals(p, W=W):
            rot = Rotation.from_rotvec(p[:3]).as_matrix()
            return np.concatenate([(w @ rot.T) @ a - u for w, a, u in zip(W, axes_up, p[3:])])

        def jacobian(p, W=W):
            rot = Rotation.from_rotvec(p[:3]).as_matrix()
            blocks = []
            for k, (w, a) in enumerate(zip(W, axes_up)):
                wr = w @ rot.T
                jb = np.zeros((len(w), 3 + len(W)))
                jb[:, :3] = np.cross(wr, a)
                jb[:, 3 + k] = -1.0
                blocks.append(jb)
            return np.vstack(blocks)

        p0 = np.concatenate([np.zeros(3), [float(np.mean(w @ a)) for w, a in zip(W, axes_up)]])
        sol = least_squares(residuals, p0, jac=jacobian, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
        R_s = Rotation.from_rotvec(sol.x[:3]).as_matrix() @ R0
        res = residuals(sol.x)
        dof = max(len(res) - len(sol.x), 1)
        s_hat = float(np.sqrt(res @ res / dof))
        sigma = float(noise_nT) if noise_nT is not None else s_hat
        sigma_used.append(sigma)
        J = jacobian(sol.x)
        try:
            cov_full = sigma**2 * np.linalg.inv(J.T @ J)
        except np.linalg.LinAlgError:
            cov_full = np.full((J.shape[1], J.shape[1]), np.inf)
        cov_rot = cov_full[:3, :3]
        angles = conventions.misalignment_angles(R_s.T)
        D = _angle_jacobian(R_s)
        ang_cov = D @ cov_rot @ D.T
        R_out.append(R_s)
        ang.append(angles)
        ang_std.append(np.sqrt(np.clip(np.diag(ang_cov), 0, None)))
        cov_out.append(cov_rot)
        vert.append(sol.x[3:].copy())
        splits = np.cumsum(counts)[:-1]
        rms.append([float(np.sqrt(np.mean(r**2))) for r in np.split(res, splits)])
        # per-group axis estimates (sensor frame), angles between them
        by_axis = {}
        for g, n in zip(present, normals):
            by_axis.setdefault(int(np.argmax(np.abs(GROUP_AXES[g]))), []).append(n * np.sign(GROUP_AXES[g].sum()))
        est = {k: np.mean(vs, axis=0) / np.linalg.norm(np.mean(vs, axis=0)) for k, vs in by_axis.items()}
        pair_angles = []
        for i, j in conventions.AXIS_PAIRS:
            if i in est and j in est:
                pair_angles.append(float(np.degrees(np.arccos(np.clip(est[i] @ est[j], -1, 1)))))
            else:
                pair_angles.append(float("nan"))
        axang.append(pair_angles)
        u = sol.x[3:]
        if len(u) > 1 and np.ptp(np.sign(u)) > 0 and np.min(np.abs(u)) > 10 * sigma / np.sqrt(min(counts)):
            remark = (
                f"sensor {s + 1}: the vertical field component changes sign between groups "
                f"({', '.join(f'{g} {x:+.0f} nT' for g, x in zip(present, u))}); check the group labels "
                "(an axis labelled _up that pointed down) before trusting the result"
            )
            remarks.append(remark)
            notes.append(Note(f"{source}: {remark}", DataWarning, "align"))
    result = PlatformAlignment(
        R=np.array(R_out),
        angles_rad=np.array(ang),
        angles_std_rad=np.array(ang_std),
        rotation_cov_rad2=np.array(cov_out),
        vertical_nT=np.array(vert),
        residual_rms_nT=np.array(rms),
        axis_angles_deg=np.array(axang),
        groups=list(present),
        counts=counts,
        noise_nT=float(np.mean(sigma_used)),
        remarks=remarks,
        notes=notes,
    )
    return result


def _angle_jacobian(R, h=1e-7):
    """d(alpha, beta, gamma of M = R^T) / d(small rotation about platform axes applied as exp(d) R)."""
    base = conventions.misalignment_angles(R.T)
    D = np.zeros((3, 3))
    for k in range(3):
        d = np.zeros(3)
        d[k] = h
        Rp = Rotation.from_rotvec(d).as_matrix() @ R
        D[:, k] = (conventions.misalignment_angles(Rp.T) - base) / h
    return D


def rotation_error_rad(R_est, R_true):
    """Angle (rad) of the rotation ``R_est R_true^T`` (0 for a perfect estimate), per sensor."""
    return np.linalg.norm(rotation_error_vector_rad(R_est, R_true), axis=1)


def rotation_error_vector_rad(R_est, R_true):
    """Small-rotation vector ``d`` (rad, about the platform axes) with ``R_est = exp(d) R_true``, per sensor."""
    R_est = np.asarray(R_est, float)
    R_true = np.asarray(R_true, float)
    if R_est.ndim == 2:
        R_est, R_true = R_est[None], R_true[None]
    return np.array([Rotation.from_matrix(a @ b.T).as_rotvec() for a, b in zip(R_est, R_true)])


# -- intrinsic calibration ------------------------------------------------------------------------------------------
def intrinsic_covariance(readings_nT, cinv, bias_nT, noise_nT, total_nT=None):
    """Cramer-Rao covariance (9 x 9) of one sensor's intrinsic parameters from a scalar calibration record.

    Parameters are the 6 upper-triangle entries of ``C^-1`` (:data:`magcal.core.conventions.UPPER_TRIANGLE` order)
    and the bias ``b`` (nT), for the total-field residual ``|C^-1 (y - b)| - F`` with a known ``F``.

    Parameters
    ----------
    readings_nT : array_like, shape (N, 3)
    cinv : array_like, shape (3, 3)
    bias_nT : array_like, shape (3,)
    noise_nT : float
        Per-axis noise sigma of the readings.
    """
    y = np.asarray(readings_nT, float)
    cinv = np.asarray(cinv, float)
    z = y - np.asarray(bias_nT, float)
    B = z @ cinv.T
    u = B / np.linalg.norm(B, axis=1)[:, None]
    cols = [u[:, i] * z[:, j] for i, j in conventions.UPPER_TRIANGLE]
    cols += list((-u @ cinv).T)
    J = np.column_stack(cols)
    # the residual's noise: u^T C^-1 n, variance sigma^2 |C^-T u|^2
    w = np.linalg.norm(u @ cinv, axis=1)
    Jw = J / w[:, None]
    return float(noise_nT) ** 2 * np.linalg.inv(Jw.T @ Jw)


def sensor_frame_vectors(calibration, dataset) -> np.ndarray:
    """Each sensor's intrinsically corrected vectors (n_sensors, N, 3) in its own frame (``R`` set to identity).

    Raw-stage effects of the calibration's model are applied; array-stage effects (which act in the array frame)
    are left out.
    """

    sensors = [dataclasses.replace(c, R=np.eye(3)) for c in calibration.sensors]
    model = calibration.model
    if model is not None:
        model = Model(model.n_sensors, base=model.base, effects=[e for e in model.effects if e.stage == "raw"])
    calibration.check(dataset)
    return corrected_fields(
        dataset, sensors, model, calibration.effect_values, contexts(dataset, calibration.baseline_m)
    )


def align(dataset, calibration=None, noise_nT=None, intrinsic_cov=None, reference_total_nT=None, source=None):
    """Level-table alignment of a dataset: a new calibration whose ``R`` take each sensor into the platform frame.

    Parameters
    ----------
    dataset : Dataset
        Level-table records with a ``group`` column (see the module docstring). Rows with other labels (e.g. a
        ``free`` rotation for the scalar calibration) are ignored by the alignment.
    calibration : Calibration, optional
        The intrinsic calibration (C^-1, b; the patent's S4). If omitted, a scalar calibration is fitted to the
        whole dataset first (:func:`magcal.fitting.pipeline.calibrate`), which needs attitudes covering the sphere well
        enough; a separate free-rotation record is better.
    noise_nT : float, optional
        Per-axis noise sigma for the uncertainties; else the dataset's ``noise_nT``, else the residual estimate.
    intrinsic_cov : array_like, shape (n_sensors, 9, 9), optional
        Covariance of each sensor's intrinsic parameters (:func:`intrinsic_covariance` order), propagated into the
        angle uncertainties to first order.
    reference_total_nT : float, optional
        Passed to the scalar calibration when ``calibration`` is omitted.

    Returns
    -------
    calibration : Calibration
        A copy with ``R`` replaced, ``frame = "platform"`` and ``platform_alignment`` figures in its summary.
    alignment : PlatformAlignment
        Its ``notes``: what the user must hear (:mod:`magcal.core.notes`: weak coverage of the scalar calibration
        fitted first, group labels that look wrong), never raised here.
    """

    source = source or dataset.source or "data"
    notes = []
    if calibration is None:
        result = calibrate(dataset, reference_total_nT=reference_total_nT)
        notes += result.notes
        calibration = result.calibration
        intrinsic_note = "intrinsic calibration fitted to the same file"
    else:
        intrinsic_note = "intrinsic calibration from the given calibration file"
        if calibration.n_sensors != dataset.n_sensors:
            raise MagcalError(
                f"the calibration is for {calibration.n_sensors} sensor(s) but {source} has {dataset.n_sensors}; use "
                "the calibration made for this instrument"
            )
    noise = noise_nT if noise_nT is not None else dataset.noise_nT
    vectors = sensor_frame_vectors(calibration, dataset)
    prior = None
    if calibration.frame == "platform":
        prior = np.array([c.R for c in calibration.sensors])
    result = estimate_alignment(vectors, dataset.group, noise_nT=noise, prior_R=prior, source=source)
    result.notes = notes + result.notes
    if intrinsic_cov is not None:
        _propagate_intrinsic(result, calibration, dataset, np.asarray(intrinsic_cov, float), noise, prior, source)
    result.remarks.append(intrinsic_note)
    sensors = []
    for c, R in zip(calibration.sensors, result.R):
        sensors.append(dataclasses.replace(c, R=R, summary=dict(c.summary)))
    summary = dict(calibration.summary)
    summary["platform_alignment"] = result.to_dict()
    new = Calibration(
        sensors=sensors,
        reference_total_nT=calibration.reference_total_nT,
        reference_fitted=calibration.reference_fitted,
        baseline_m=calibration.baseline_m or dataset.baseline_m,
        model=calibration.model,
        effect_values=dict(calibration.effect_values),
        frame="platform",
        summary=summary,
    )
    return new, result


def _propagate_intrinsic(result, calibration, dataset, intrinsic_cov, noise, prior, source, h=None):
    """Add the intrinsic parameters' covariance to the rotation covariance (first-order, finite differences)."""
    base_R = result.R
    n_sensors = calibration.n_sensors
    for s in range(n_sensors):
        c = calibration.sensors[s]
        params = np.concatenate([conventions.cinv_to_params(c.cinv), c.bias_nT])
        steps = np.concatenate([np.full(6, 1e-6), np.full(3, 0.1)])
        D = np.zeros((3, 9))
        for k in range(9):
            p = params.copy()
            p[k] += steps[k]
            sensors = list(calibration.sensors)
            sensors[s] = dataclasses.replace(c, cinv=conventions.params_to_cinv(p[:6]), bias_nT=p[6:])
            cal_k = dataclasses.replace(calibration, sensors=sensors)
            v = sensor_frame_vectors(cal_k, dataset)[s : s + 1]
            r = estimate_alignment(
                v, dataset.group, noise_nT=noise, prior_R=None if prior is None else prior[s : s + 1], source=source
            )
            D[:, k] = rotation_error_vector_rad(r.R[0], base_R[s])[0] / steps[k]
        extra = D @ intrinsic_cov[s] @ D.T
        result.rotation_cov_rad2[s] = result.rotation_cov_rad2[s] + extra
        J = _angle_jacobian(base_R[s])
        result.angles_std_rad[s] = np.sqrt(np.clip(np.diag(J @ result.rotation_cov_rad2[s] @ J.T), 0, None))
    result.intrinsic_included = True
