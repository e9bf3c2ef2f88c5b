"""Weighted Gauss-Newton / Levenberg-Marquardt on Plücker-line residuals (eq. 3-5).

Minimises Σ_i w_i |T(χ) X_i × n_i − m_i|² over χ = (ξ, Θ) (eq. 4). The root pose is parametrised
as a left increment δ on the initial pose, T_world_root = exp(δ̂) T_init, which is the paper's
linearisation point (eq. 5) and keeps the unknowns near zero; joint angles are solved directly.
A damped Gauss-Newton on the (6+J)² normal equations runs the iterations (optimistix's
Levenberg-Marquardt is the reference backend); failures come back as a `Status`, never as an
exception, and implicit differentiation gives derivatives of the solution with respect to weights,
points and lines.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._status import Status, check_status, first_failure, is_usable, status_where
from ..geometry import (
    Camera,
    KinematicModel,
    part_transforms,
    point_line_residual,
    se3_adjoint,
    se3_exp,
    se3_inverse,
    se3_left_jacobian_inverse,
    se3_log,
    transform_points,
)
from ._correspondences import Correspondences
from ._gauss_newton import damped_gauss_newton, solve_implicit
from ._moments import PlaneMoments, moment_normal_equations, plane_moments
from ._normal_equations import RayDepths, line_planes, plane_normal_equations, plane_residuals

# The solver reports the library-wide status codes; `PoseStatus` is kept as its old name.
PoseStatus = Status


class SolverConfig(eqx.Module):
    """Iteration settings (static: they shape the compiled loop, not the data).

    Attributes:
        max_steps: iteration budget.
        rtol, atol: stop when the step or the relative cost decrease is this small.
        backend: "gauss-newton" (default): Marquardt-damped Gauss-Newton on the (6+J)² normal
            equations (eq. 5), implicit derivatives through a `jax.custom_jvp` (`solve_implicit`); "optimistix":
            `optimistix.LevenbergMarquardt` (QR on the full Jacobian, optimistix's implicit adjoint),
            the reference implementation, ~30x slower under vmap on CPU.
        moments_from_rows: the Gauss-Newton backend on eq. 4 as it is (no depth scaling) sums the rows per part
            once per solve (`jaxtrack.solve._moments`) when they number at least this (capacity N), else at every
            iterate. Measured (experiments/results/bench_pose.md, vmapped solves of 200 rows: rows at every iterate
            1.8x (rigid) to 4x (24 joints) the solves per second of the moments, whose small per-part products and
            float32 cost (3.9 against 3.7 steps) cost more than they save there; 1000 rows rigid: moments 1.1x;
            the 4-camera human's 19 008 rows: the refinement's solves 95-104 → 29 ms a frame).
    """

    max_steps: int = eqx.field(static=True, default=50)
    rtol: float = eqx.field(static=True, default=1e-6)
    atol: float = eqx.field(static=True, default=1e-6)
    backend: str = eqx.field(static=True, default="gauss-newton")
    moments_from_rows: int = eqx.field(static=True, default=1024)

    def __check_init__(self):
        if self.backend not in ("gauss-newton", "optimistix"):
            raise ValueError(f"SolverConfig.backend must be 'gauss-newton' or 'optimistix', got {self.backend!r}")
        if self.max_steps < 1:
            raise ValueError(f"SolverConfig.max_steps must be ≥ 1, got {self.max_steps}")


# The default settings as one module-level instance (a call in the signature would run at import anyway).
DEFAULT_CONFIG = SolverConfig()


class PoseSolution(eqx.Module):
    """Result of `solve_pose`.

    Attributes:
        T_world_root: (4, 4) solved root pose exp(ξ̂) (model → world).
        theta: (J,) solved joint angles (rad).
        status: int32 `PoseStatus`.
        num_steps: int32 iterations taken.
        cost: Σ w_i |r_i|² at the solution (mm²·weight).
        num_effective: int32 rows with positive weight.
    """

    T_world_root: jax.Array
    theta: jax.Array
    status: jax.Array
    num_steps: jax.Array
    cost: jax.Array
    num_effective: jax.Array

    @property
    def ok(self):
        """True where the pose can be used (converged, or budget ran out on a finite iterate)."""
        return is_usable(self.status)


def _safe_sqrt(x):
    # Padding rows have w = 0; a plain sqrt would give them an infinite derivative.
    positive = x > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, x, 1.0)), 0.0)


def rigidity_tolerance(dtype) -> float:
    """Tolerance of the rigid-transform test on T_init: eps^(1/3) of the solve dtype.

    ~6e-6 in float64 (rotations written to files with 6 decimals, as pose files often are, pass) and
    ~4.9e-3 in float32 (a float64 pose rounded to float32 passes); a zero, scaled (by 1 %), sheared or
    reflected block does not.
    """
    return float(np.finfo(dtype).eps ** (1.0 / 3.0))


def degeneracy_tolerance(dtype) -> float:
    """Smallest acceptable λ_min/λ_max of the Jacobi-scaled root block of H: eps^(3/4) of the dtype.

    ~1.8e-12 in float64, ~6.4e-6 in float32. Coincident or collinear model points give 0 (measured,
    both dtypes); random well-posed sets of 4 points seen by one camera gave ≥ 3.6e-3 over 40 draws
    (median 0.06, both dtypes), so the margin is wide in either direction.
    """
    return float(np.finfo(dtype).eps ** 0.75)


def root_conditioning(H: jax.Array) -> jax.Array:
    """λ_min / λ_max of the Jacobi-scaled 6x6 root block of H (eq. 5), in [0, 1]; jittable.

    Jacobi scaling removes the units (mm for translations, rad for rotations) so the ratio measures
    rank, not scale. Joint columns are left out: an unobserved joint is damped, not degenerate.
    """
    block = H[:6, :6]
    diag = jnp.diagonal(block)
    scale = jnp.sqrt(jnp.where(diag > 0, diag, 1.0))
    scaled = block / (scale[:, None] * scale[None, :])
    eig = jnp.linalg.eigvalsh(scaled)
    top = eig[-1]
    ratio = jnp.where(top > 0, eig[0] / jnp.where(top > 0, top, 1.0), 0.0)
    # A zero diagonal (a root direction no row constrains) is rank deficiency however the rest looks.
    return jnp.where(jnp.all(diag > 0) & jnp.isfinite(ratio), jnp.clip(ratio, 0.0, 1.0), 0.0)


def model_points_world(model: KinematicModel, T_world_root: jax.Array, theta: jax.Array, p_model: jax.Array, part: jax.Array):
    """World coordinates T(χ) X of model points on their parts (eq. 2). p_model (N, 3), part (N,)."""
    T_parts = part_transforms(model, T_world_root, theta)
    if model.num_parts == 1:  # rigid: skip the gather
        return transform_points(T_parts[0], p_model)
    return transform_points(T_parts[part], p_model)


def weights_per_pixel(corr: Correspondences, cameras: Camera, model: KinematicModel, T_world_root: jax.Array,
                      theta: jax.Array, on=True) -> Correspondences:
    """Rows weighted per px² of the image turned into weights per mm² of the Plücker residual: w · fx fy / Z².

    A point row's residual (eq. 4) is a distance in mm across the viewing ray; a pixel there spans Z / f mm
    (Z the point's depth in its camera at the given pose, f = √(fx fy) of that camera, `cameras` the full-frame
    rig, C stacked, or one camera). The line modality weighs its rows per px² (M3T); the flow and SIFT rows converted alike keep
    the balance of the cues independent of the object's distance and of the image resolution. (N,) rows of
    any camera; padding rows keep weight 0; Z is clamped at 1 mm. `on` (a bool or 0/1 array): False returns the
    rows as given."""
    p_world = model_points_world(model, T_world_root, theta, corr.p_model, corr.part)
    T_cw, K = cameras.T_cam_world, cameras.K
    if K.ndim == 3:  # a stacked rig: each row's own camera (a single camera serves every row)
        index = jnp.clip(corr.camera, 0, K.shape[0] - 1)
        T_cw, K = T_cw[index], K[index]
    z = jnp.einsum("...j,...j->...", T_cw[..., 2, :3], p_world) + T_cw[..., 2, 3]
    f2 = K[..., 0, 0] * K[..., 1, 1]
    scale = jnp.where(jnp.asarray(on) > 0, f2 / jnp.maximum(z, 1.0) ** 2, 1.0)
    return eqx.tree_at(lambda c: c.weight, corr, corr.weight * scale.astype(corr.weight.dtype))


def plucker_residuals(model: KinematicModel, T_world_root: jax.Array, theta: jax.Array, corr: Correspondences):
    """Unweighted residuals r_i = T(χ) X_i × n_i − m_i (eq. 4), (N, 3), world frame, mm."""
    p_world = model_points_world(model, T_world_root, theta, corr.p_model, corr.part)
    return point_line_residual(p_world, corr.n, corr.m)


class JointPrior(eqx.Module):
    """A quadratic pull of the joint angles towards an anchor: damping for weakly observed joints.

    Adds Σ_j k |θ_j − θ̄_j|² to eq. 4 with one stiffness k = `strength` · mean_j H_jj, the mean joint
    diagonal of the data's normal equations at the start of the solve: a joint (or a combination of
    joints, such as pelvis pitch against back and hips) whose data curvature is well below the mean
    stays near θ̄, while well observed joints barely feel it. Relative, so it does not depend on the
    number of rows, their weights or the units of the model. The method uses no priors; the tracker
    anchors at the frame's prediction (`RegionParams.joint_prior`; `jaxtrack.track` CHAIN_REGION says why).

    Attributes:
        theta: (J,) anchor angles (model units).
        strength: scalar ≥ 0 (0: no prior).
    """

    theta: jax.Array
    strength: jax.Array


def _prior_stiffness(H: jax.Array, strength: jax.Array) -> jax.Array:
    """k = strength · mean joint diagonal of H ((6+J)², data only); 0 for a rigid object."""
    joint_diag = jnp.diagonal(H)[6:]
    if joint_diag.shape[0] == 0:
        return jnp.zeros((), H.dtype)
    return jax.lax.stop_gradient(strength * jnp.mean(joint_diag))


class PosePrior(eqx.Module):
    """Tikhonov regularisation of the root pose toward an anchor (M3T's prior toward the previous pose).

    Adds k_t |v|² + k_r |ω|² to eq. 4, where (v, ω) = log(T_anchor⁻¹ T_world_root) is the root's motion
    from the anchor in the anchor's own (model) frame: a rotation about the model origin costs no
    translation. The stiffnesses are relative, as the `JointPrior`'s: k_t = `translation` · the mean
    translation diagonal and k_r = `rotation` · the mean rotation diagonal of the data's normal
    equations at the start of the solve (in that model frame), so a direction the data observe well
    barely feels the prior while a weakly observed one (the depth of a silhouette, the spin of a round
    object) stops random-walking. Unit-free: independent of the number of rows, their weights and mm.

    `rotation_abs` / `translation_abs` add absolute stiffnesses (per rad², per mm², in the units of the
    weighted residual): M3T's Tikhonov 1000 / 30000 (rad, m) on rows weighted in pixels are 1000 / 0.03
    here for rows weighted as `jaxtrack.cues.lines` weighs them (per px², converted to mm at the point).

    Attributes:
        T_anchor: (4, 4) the pose the root is pulled toward (model → world).
        rotation: scalar ≥ 0, relative rotation stiffness (0: none).
        translation: scalar ≥ 0, relative translation stiffness (0: none).
        rotation_abs, translation_abs: scalars ≥ 0, absolute stiffnesses (default 0).
    """

    T_anchor: jax.Array
    rotation: jax.Array
    translation: jax.Array
    rotation_abs: jax.Array = eqx.field(default_factory=lambda: jnp.zeros(()))
    translation_abs: jax.Array = eqx.field(default_factory=lambda: jnp.zeros(()))


def _root_prior_jacobian(error: jax.Array, T_anchor: jax.Array) -> jax.Array:
    """d log(T_anchor⁻¹ exp(δ̂) T_root) / dδ at δ = 0 (6, 6), exact, from `error` = log(T_anchor⁻¹ T_root): the
    Gauss-Newton steps then converge to the stationary point of the residual that implicit differentiation
    assumes. T_anchor⁻¹ exp(δ̂) = exp((Ad(T_anchor⁻¹) δ)^) T_anchor⁻¹, so it is J_l(error)⁻¹ Ad(T_anchor⁻¹)
    (≈ Ad(T_anchor⁻¹) near the anchor), in closed form: differentiating the logarithm with `jax.jacfwd`
    compiled ~100 kernels per copy for a term the tracker's default (zero stiffness) never runs."""
    return se3_left_jacobian_inverse(error) @ se3_adjoint(se3_inverse(T_anchor))


def _root_prior_error(T_root: jax.Array, T_anchor: jax.Array) -> jax.Array:
    """(6,) (v, ω) = log(T_anchor⁻¹ T_root), the root's motion from the anchor in the model frame."""
    return se3_log(se3_inverse(T_anchor) @ T_root)


def _root_prior_stiffness(H: jax.Array, T_root: jax.Array, prior: PosePrior) -> jax.Array:
    """(6,) k per body-frame root direction from the data's root block of H (left-increment chart)."""
    A = se3_adjoint(T_root)  # δ = Ad(T) δ_body
    Hb = A.T @ H[:6, :6] @ A
    d = jax.lax.stop_gradient(jnp.diagonal(Hb))  # the scale; the strengths keep their derivatives
    k_t = prior.translation * jnp.mean(d[:3]) + prior.translation_abs
    k_r = prior.rotation * jnp.mean(d[3:]) + prior.rotation_abs
    k = jnp.concatenate([jnp.broadcast_to(k_t, (3,)), jnp.broadcast_to(k_r, (3,))])
    return jnp.where(jnp.isfinite(k) & (k > 0), k, 0.0)


class PoseProblem(eqx.Module):
    """The data of one solve (the `args` of the residual and of the iterations).

    Attributes:
        model: kinematic tree.
        corr: correspondences with the geometry of zero-weight rows zeroed (`_sanitize`).
        T_init: (4, 4) the chart's origin: T_world_root = exp(δ̂) T_init.
        sqrt_weight: (N, 2) √w per plane (the row's weight times its plane weight), zero for padding.
        normals, offsets: (N, 2, 3), (N, 2) the two planes through each line (`line_planes`).
        prior_theta, prior_stiffness: (J,) anchor and scalar k of the `JointPrior` (k = 0: none).
        root_anchor, root_stiffness: (4, 4) anchor and (6,) k of the `PosePrior` (k = 0: none).
        depths: the rows' `RayDepths` when the residuals are depth-invariant (`solve_pose(ray_origins=)`), else None.
        moments: without `depths`, the rows summed per part at T_init (`jaxtrack.solve._moments.plane_moments`), from
            which every iterate's normal equations come; else None (the rows are summed at every iterate).
    """

    model: KinematicModel
    corr: Correspondences
    T_init: jax.Array
    sqrt_weight: jax.Array
    normals: jax.Array
    offsets: jax.Array
    prior_theta: jax.Array
    prior_stiffness: jax.Array
    root_anchor: jax.Array
    root_stiffness: jax.Array
    has_root_prior: bool = eqx.field(static=True, default=False)
    depths: RayDepths | None = None
    moments: PlaneMoments | None = None


def _weighted_residual(y: jax.Array, problem: PoseProblem) -> jax.Array:
    """Chart residual: y = (δ, Θ) with T_world_root = exp(δ̂) T_init; plane form of eq. 4 (2N,), then
    the joint prior's J rows √k (θ − θ̄) and the pose prior's 6 rows √k ⊙ log(T_anchor⁻¹ T_root)."""
    T_root = se3_exp(y[:6]) @ problem.T_init
    corr = problem.corr
    s = plane_residuals(problem.model, T_root, y[6:], corr.p_model, corr.part, problem.normals, problem.offsets,
                        problem.depths, corr.n)
    prior = _safe_sqrt(problem.prior_stiffness) * (y[6:] - problem.prior_theta)
    if not problem.has_root_prior:
        return jnp.concatenate([(s * problem.sqrt_weight).reshape(-1), prior])
    root = _safe_sqrt(problem.root_stiffness) * _root_prior_error(T_root, problem.root_anchor)
    return jnp.concatenate([(s * problem.sqrt_weight).reshape(-1), prior, root])


def _gauss_newton_iterate(y0: jax.Array, problem: PoseProblem, config: SolverConfig):
    """Damped Gauss-Newton on (T_world_root, Θ) with left increments (the paper's eq. 5 update).

    Returns:
        y (D,) in the chart of T_init, and aux (converged, num_steps, nonfinite, root conditioning).
    """
    corr, weight = problem.corr, problem.sqrt_weight**2

    J = problem.prior_theta.shape[0]
    k = problem.prior_stiffness

    def normal_equations(x):
        T_root, theta = x
        if problem.moments is not None:
            # eq. 4 as it is: the solve's rows summed per part once, each iterate combines the sums.
            H, g, cost = moment_normal_equations(problem.model, T_root, theta, problem.moments)
        else:
            # Looked up at trace time, so experiments/bench_pose.py can swap in the builder it compares.
            H, g, cost = plane_normal_equations(
                problem.model, T_root, theta, corr.p_model, corr.part, problem.normals, problem.offsets, weight,
                problem.depths, corr.n
            )
        if problem.has_root_prior:  # pose prior: residual √k ⊙ e, e = log(T_anchor⁻¹ T_root)
            kr = problem.root_stiffness

            def add_prior(H, g, cost):
                e = _root_prior_error(T_root, problem.root_anchor)
                B = _root_prior_jacobian(e, problem.root_anchor)
                return H.at[:6, :6].add(B.T @ (kr[:, None] * B)), g.at[:6].add(B.T @ (kr * e)), cost + jnp.sum(kr * e**2)

            # A zero stiffness (the tracker's default) skips the logarithm and its Jacobian at run time:
            # ~150 small kernels per step on a CPU. Under vmap the cond is a select and both sides run.
            H, g, cost = jax.lax.cond(jnp.any(kr > 0), add_prior, lambda H, g, cost: (H, g, cost), H, g, cost)
        if J == 0:
            return H, g, cost
        d = theta - problem.prior_theta
        H = H.at[6:, 6:].add(k * jnp.eye(J, dtype=H.dtype))
        return H, g.at[6:].add(k * d), cost + k * jnp.sum(d**2)

    def retract(x, delta):
        T_root, theta = x
        return se3_exp(delta[:6]) @ T_root, theta + delta[6:]

    def magnitude(x):
        T_root, _ = x
        return jnp.maximum(jnp.max(jnp.abs(T_root[:3, 3])), 1.0)

    x0 = (se3_exp(y0[:6]) @ problem.T_init, y0[6:])
    result = damped_gauss_newton(normal_equations, retract, magnitude, x0, config.max_steps, config.rtol, config.atol)
    T_root, theta = result.x
    # Back to the chart of T_init (exact while the rotation from T_init stays below π).
    y = jnp.concatenate([se3_log(T_root @ se3_inverse(problem.T_init)), theta])
    return y, (result.converged, result.num_steps, result.nonfinite, root_conditioning(result.hessian))


def _sanitize(corr: Correspondences) -> Correspondences:
    """Zero the geometry of rows that carry no weight so that padding can never poison the sums."""
    live = corr.weight > 0
    clean = lambda a: jnp.where(live[:, None], jnp.nan_to_num(a), 0.0)
    tw = jnp.where(live & jnp.isfinite(corr.tangent_weight), jnp.clip(corr.tangent_weight, 0.0, None), 0.0)
    return eqx.tree_at(lambda c: (c.n, c.m, c.p_model, c.normal, c.tangent_weight), corr,
                       (clean(corr.n), clean(corr.m), clean(corr.p_model), clean(corr.normal), tw))


def _rigid_transform_defect(T: jax.Array) -> jax.Array:
    """max(|RᵀR − I|, |last row − (0, 0, 0, 1)|), +inf where det R ≤ 0 (a reflection or a collapse)."""
    R = T[:3, :3]
    orth = jnp.max(jnp.abs(R.T @ R - jnp.eye(3, dtype=T.dtype)))
    row = jnp.max(jnp.abs(T[3] - jnp.array([0.0, 0.0, 0.0, 1.0], T.dtype)))
    return jnp.where(jnp.linalg.det(R) > 0, jnp.maximum(orth, row), jnp.inf)


def _ray_depths(model: KinematicModel, corr: Correspondences, T_world_root, theta, cameras: Camera) -> jax.Array:
    """Signed depth n · (a − o) of each model point a at the pose along its viewing ray from the centre o, (N,).

    The Plücker line (n, m) alone cannot tell where the ray starts (m fixes the line, not a point
    on it), so the camera centres come from the rig the correspondences were built with
    (`corr.camera` indexes it; a single camera serves every row).
    """
    centres = cameras.center_world  # (C, 3) or (3,)
    if centres.ndim == 2:
        centres = centres[jnp.clip(corr.camera, 0, centres.shape[0] - 1)]
    a = model_points_world(model, T_world_root, theta, corr.p_model, corr.part)
    return jnp.sum(corr.n * (a - centres.astype(a.dtype)), axis=-1)


def fraction_behind_cameras(
    model: KinematicModel, corr: Correspondences, T_world_root: jax.Array, theta: jax.Array, cameras: Camera
) -> jax.Array:
    """Weighted fraction of correspondences whose model point at (T_world_root, Θ) lies behind its camera.

    The Plücker residual (eq. 4) is blind to which side of the centre a point sits on, so a pose
    mirrored behind the cameras fits the lines as well as the true one; the solver cannot recover.
    """
    live_weight = jnp.where(corr.weight > 0, corr.weight, 0.0)
    behind = _ray_depths(model, corr, T_world_root, theta, cameras) <= 0
    total = jnp.sum(live_weight)
    return jnp.sum(jnp.where(behind, live_weight, 0.0)) / jnp.where(total > 0, total, 1.0)


def input_status(
    model: KinematicModel,
    corr: Correspondences,
    T_init: jax.Array,
    theta_init: jax.Array,
    cameras: Camera | None = None,
) -> jax.Array:
    """`Status.INVALID_INPUT` / `TOO_FEW` / `OK` for the inputs alone (jittable).

    INVALID_INPUT: a negative or non-finite weight, a weighted row with a non-finite line or point or
    an out-of-range part, a non-finite Θ_init, a T_init that is not a rigid transform (within
    `rigidity_tolerance`), or, when `cameras` are given, a camera index out of range or a T_init
    that puts more than half of the weight behind the cameras. TOO_FEW: 2·rows < 6 + J.
    """
    dtype = corr.n.dtype
    live = corr.weight > 0
    rows_finite = jnp.all(jnp.isfinite(corr.n) & jnp.isfinite(corr.m) & jnp.isfinite(corr.p_model), axis=-1)
    T_finite = jnp.all(jnp.isfinite(T_init))
    T_safe = jnp.where(T_finite, T_init, jnp.eye(4, dtype=T_init.dtype))
    theta_finite = jnp.all(jnp.isfinite(theta_init))
    invalid = (
        jnp.any(corr.weight < 0)
        | ~jnp.all(jnp.isfinite(corr.weight))
        | jnp.any(live & ~rows_finite)
        | jnp.any(live & ((corr.part < 0) | (corr.part >= model.num_parts)))
        | ~T_finite
        | ~theta_finite
        | ~(_rigid_transform_defect(T_safe) <= rigidity_tolerance(dtype))
    )
    if cameras is not None:
        num_cameras = cameras.K.shape[0] if cameras.K.ndim == 3 else 1
        bad_camera = jnp.any(live & ((corr.camera < 0) | (corr.camera >= num_cameras))) if num_cameras > 1 else False
        theta_safe = jnp.where(jnp.isfinite(theta_init), theta_init, 0.0)
        clean = _sanitize(corr)
        invalid = invalid | bad_camera | (fraction_behind_cameras(model, clean, T_safe, theta_safe, cameras) > 0.5)
    # An edge row with no weight along the edge constrains one direction, not two.
    planes = jnp.where(jnp.any(corr.normal != 0, axis=-1) & ~(corr.tangent_weight > 0), 1, 2)
    too_few = jnp.sum(jnp.where(live, planes, 0)) < model.num_dof
    return first_failure(status_where(invalid, Status.INVALID_INPUT, Status.OK), status_where(too_few, Status.TOO_FEW, Status.OK))


@eqx.filter_jit
def solve_pose(
    model: KinematicModel,
    corr: Correspondences,
    T_init: jax.Array,
    theta_init: jax.Array | None = None,
    config: SolverConfig = DEFAULT_CONFIG,
    cameras: Camera | None = None,
    prior: JointPrior | None = None,
    pose_prior: PosePrior | None = None,
    ray_origins: jax.Array | None = None,
    depth_invariance: jax.Array | float = 1.0,
) -> PoseSolution:
    """Solve χ = (ξ, Θ) minimising Σ w_i |T(χ) X_i × n_i − m_i|² (eq. 4-5). Jittable and vmappable.

    Compiled on first use for each input structure (an `eqx.filter_jit`; inside a caller's jit or
    vmap it is inlined). Never raises and never returns a NaN pose: on bad input, too few or
    degenerate constraints or a failed solve the initial pose comes back with the matching `Status`.
    Use `estimate_pose` at an API edge to get errors instead.

    Args:
        model: kinematic tree (P parts, J joints); `rigid_model()` for a rigid object.
        corr: padded correspondences (capacity N).
        T_init: (4, 4) initial root pose (model → world), a rigid transform.
        theta_init: (J,) initial joint angles (zeros if None).
        config: iteration settings.
        cameras: the rig `corr` was built with (optional). When given, a T_init that puts most of
            the weighted model points behind their cameras is INVALID_INPUT (the Plücker lines
            alone cannot tell in front from behind).
        prior: a `JointPrior` on Θ (default none, as the method).
        pose_prior: a `PosePrior` on the root pose (default none, as the method).
        ray_origins: (C, 3) or (3,) world centres of the cameras the rows' rays leave (`corr.camera` indexes
            them), or None (eq. 4 as it is). Given, each row's residual is scaled by (Z₀ / Z)^p, its depth along the
            ray at T_init over its depth at the iterate (p = `depth_invariance`, 0..1): eq. 4 at the start, but
            sliding the object toward the cameras no longer shrinks every residual, which is how rows that
            disagree were fitted (`jaxtrack.solve._normal_equations.depth_invariant`).

    Returns:
        PoseSolution. Statuses, first cause first: INVALID_INPUT, TOO_FEW (inputs), NONFINITE,
        SOLVER_FAILED, MAX_STEPS (iterations), DEGENERATE (the 6 root degrees of freedom are not
        determined: λ_min/λ_max of the Jacobi-scaled root block of H below `degeneracy_tolerance`).
    """
    dtype = corr.n.dtype
    T_init = jnp.asarray(T_init, dtype)
    theta_init = jnp.zeros((model.num_joints,), dtype) if theta_init is None else jnp.asarray(theta_init, dtype)
    pre_status = input_status(model, corr, T_init, theta_init, cameras)
    clean = _sanitize(corr)
    weight = jnp.where(jnp.isfinite(corr.weight) & (corr.weight > 0), corr.weight, 0.0)
    T_init_safe = jnp.where(jnp.isfinite(T_init), T_init, jnp.eye(4, dtype=dtype))
    theta_safe = jnp.where(jnp.isfinite(theta_init), theta_init, 0.0)
    y0 = jnp.concatenate([jnp.zeros((6,), dtype), theta_safe])
    normals, offsets, plane_weight = line_planes(clean.n, clean.m, clean.normal, clean.tangent_weight)
    weight = weight[:, None] * plane_weight
    depths = None
    if ray_origins is not None:
        origins = jnp.asarray(ray_origins, dtype)
        if origins.ndim == 2:
            origins = origins[jnp.clip(clean.camera, 0, origins.shape[0] - 1)]
        offset = jnp.sum(clean.n * origins, axis=-1)
        z0 = jnp.sum(clean.n * model_points_world(model, T_init_safe, theta_safe, clean.p_model, clean.part), -1) - offset
        power = jnp.clip(jnp.asarray(depth_invariance, dtype), 0.0, 1.0)
        depths = RayDepths(offset, jnp.where(z0 > 0, z0, 1.0), jnp.where(jnp.isfinite(power), power, 0.0))
    # eq. 4 as it is (no depth scaling) on many rows: the rows summed per part once, here, give the normal equations at
    # every iterate and at the start (the same H, g and cost to rounding; the depth-scaled residuals, and few rows,
    # are summed each time: `SolverConfig.moments_from_rows`).
    use_moments = depths is None and corr.weight.shape[0] >= config.moments_from_rows
    moments = None if not use_moments else plane_moments(model, T_init_safe, theta_safe, clean.p_model, clean.part,
                                                         normals, offsets, weight)

    J = model.num_joints
    H0 = None  # the data's H at the start, which both priors' stiffnesses read: built once, where a prior needs it
    if (prior is not None and J > 0) or pose_prior is not None:
        H0 = (moment_normal_equations(model, T_init_safe, theta_safe, moments)[0] if moments is not None else
              plane_normal_equations(model, T_init_safe, theta_safe, clean.p_model, clean.part, normals, offsets,
                                     weight, depths, clean.n)[0])
    if prior is None or J == 0:
        prior_theta, stiffness = jnp.zeros((J,), dtype), jnp.zeros((), dtype)
    else:
        prior_theta = jnp.broadcast_to(jnp.asarray(prior.theta, dtype), (J,))
        strength = jnp.asarray(prior.strength, dtype)
        stiffness = _prior_stiffness(H0, jnp.where(jnp.isfinite(strength) & (strength > 0), strength, 0.0))
        stiffness = jnp.where(jnp.isfinite(stiffness), stiffness, 0.0)
        prior_theta = jnp.where(jnp.isfinite(prior_theta), prior_theta, theta_safe)
    if pose_prior is None:
        root_anchor, root_stiffness = T_init_safe, jnp.zeros((6,), dtype)
    else:
        anchor = jnp.asarray(pose_prior.T_anchor, dtype)
        ok = jnp.all(jnp.isfinite(anchor))
        root_anchor = jnp.where(ok, anchor, T_init_safe)
        pos = lambda v: jnp.maximum(jnp.asarray(v, dtype), 0.0)
        root_stiffness = _root_prior_stiffness(H0, T_init_safe, PosePrior(
            root_anchor, pos(pose_prior.rotation), pos(pose_prior.translation), pos(pose_prior.rotation_abs),
            pos(pose_prior.translation_abs)))
    problem = PoseProblem(
        model=model, corr=clean, T_init=T_init_safe, sqrt_weight=_safe_sqrt(weight), normals=normals, offsets=offsets,
        prior_theta=prior_theta, prior_stiffness=stiffness, root_anchor=root_anchor, root_stiffness=root_stiffness,
        has_root_prior=pose_prior is not None, depths=depths, moments=moments,
    )
    if config.backend == "optimistix":
        # Imported here: the reference backend, not the default; loading optimistix and lineax costs every process that
        # imports jaxtrack 0.07-0.3 s otherwise (a fifth of `import jaxtrack` beyond jax and equinox).
        import lineax as lx
        import optimistix as optx

        sol = optx.least_squares(
            _weighted_residual,
            optx.LevenbergMarquardt(rtol=config.rtol, atol=config.atol, linear_solver=lx.QR()),
            y0,
            args=problem,
            max_steps=config.max_steps,
            throw=False,
        )
        y, num_steps = sol.value, sol.stats["num_steps"]
        out_of_steps = (sol.result == optx.RESULTS.max_steps_reached) | (
            sol.result == optx.RESULTS.nonlinear_max_steps_reached
        )
        solver_status = first_failure(
            status_where(out_of_steps, Status.MAX_STEPS, Status.OK),
            status_where(sol.result != optx.RESULTS.successful, Status.SOLVER_FAILED, Status.OK),
        )
        H, _, _ = plane_normal_equations(
            model, se3_exp(y[:6]) @ T_init_safe, y[6:], clean.p_model, clean.part, normals, offsets, weight, depths, clean.n
        )
        conditioning = root_conditioning(H)
        finite = jnp.all(jnp.isfinite(y))
    else:
        y, (converged, num_steps, nonfinite, conditioning) = solve_implicit(
            _weighted_residual, lambda guess, args: _gauss_newton_iterate(guess, args, config), y0, problem
        )
        finite = jnp.all(jnp.isfinite(y)) & ~(nonfinite > 0)
        solver_status = status_where(converged > 0, Status.OK, Status.MAX_STEPS)
    degenerate = ~(conditioning >= degeneracy_tolerance(dtype))
    # First cause first: bad input, then a NaN/inf (which also spoils H), then rank, then the solver.
    status = first_failure(
        pre_status,
        status_where(finite, Status.OK, Status.NONFINITE),
        status_where(degenerate, Status.DEGENERATE, Status.OK),
        solver_status,
    )
    y = jnp.where(is_usable(status) & finite, y, y0)
    T_root = se3_exp(y[:6]) @ T_init_safe
    residual = _weighted_residual(y, problem)
    return PoseSolution(
        T_world_root=T_root,
        theta=y[6:],
        status=status,
        num_steps=jnp.asarray(num_steps, jnp.int32),
        cost=jnp.sum(residual**2),
        num_effective=corr.num_effective().astype(jnp.int32),
    )


def _describe_invalid(model: KinematicModel, corr: Correspondences, T_init: np.ndarray, theta: np.ndarray, cameras) -> str:
    """Host-side reason for an INVALID_INPUT, naming the argument or field."""
    weight = np.asarray(corr.weight)
    live = weight > 0
    reasons = []
    if not np.all(np.isfinite(weight)) or np.any(weight < 0):
        reasons.append("correspondences.weight has negative or non-finite entries")
    for name in ("n", "m", "p_model"):
        bad = live & ~np.all(np.isfinite(np.asarray(getattr(corr, name))), axis=-1)
        if np.any(bad):
            reasons.append(f"correspondences.{name} is non-finite in weighted rows {np.flatnonzero(bad)[:10].tolist()}")
    part = np.asarray(corr.part)
    if np.any(live & ((part < 0) | (part >= model.num_parts))):
        reasons.append(f"correspondences.part is outside [0, {model.num_parts}) in a weighted row")
    if not np.all(np.isfinite(theta)):
        reasons.append("theta_init is not finite")
    if cameras is not None:
        num_cameras = cameras.K.shape[0] if cameras.K.ndim == 3 else 1
        camera = np.asarray(corr.camera)
        if num_cameras > 1 and np.any(live & ((camera < 0) | (camera >= num_cameras))):
            reasons.append(f"correspondences.camera is outside [0, {num_cameras}) in a weighted row")
    return "; ".join(reasons) or "invalid pose-solver input"


def _check_rigid(T_init: np.ndarray, dtype) -> None:
    """ValueError naming T_init unless it is a rigid transform within `rigidity_tolerance(dtype)`."""
    if not np.all(np.isfinite(T_init)):
        raise ValueError("T_init is not finite")
    tol = rigidity_tolerance(dtype)
    R = T_init[:3, :3].astype(np.float64)
    det = float(np.linalg.det(R))
    orth = float(np.max(np.abs(R.T @ R - np.eye(3))))
    row = float(np.max(np.abs(T_init[3] - np.array([0.0, 0.0, 0.0, 1.0]))))
    if det <= 0 or orth > tol:
        raise ValueError(
            f"T_init's rotation block is not a rotation: max|RᵀR − I| = {orth:.3g} (tolerance {tol:.2g} for "
            f"{np.dtype(dtype).name}), det R = {det:.6g} (must be +1)"
        )
    if row > tol:
        raise ValueError(f"T_init's last row must be [0, 0, 0, 1], got {T_init[3].tolist()}")


def estimate_pose(
    model: KinematicModel,
    corr: Correspondences,
    T_init: jax.Array | np.ndarray,
    theta_init: jax.Array | np.ndarray | None = None,
    config: SolverConfig = DEFAULT_CONFIG,
    cameras: Camera | None = None,
    throw: bool = True,
    prior: JointPrior | None = None,
    pose_prior: PosePrior | None = None,
) -> PoseSolution:
    """API-edge pose solve: validates the inputs, runs the jitted `solve_pose`, checks the status.

    Args:
        model, corr, T_init, theta_init, config, cameras, prior: as for `solve_pose`. Pass the rig `corr`
            was built with as `cameras` to have a T_init behind the cameras rejected.
        throw: raise `StatusError` for an unusable solver status (DEGENERATE, NONFINITE,
            SOLVER_FAILED); with False the solution comes back with its status.

    Raises:
        ValueError: malformed inputs (shape, NaN, negative weight, part or camera out of range),
            a T_init that is not a rigid transform or puts most points behind the cameras, or too
            few effective correspondences, with the argument or field named.
        StatusError: (a RuntimeError) the solve failed and `throw` is True.
    """
    num_rows = corr.weight.shape[0]
    for name in ("n", "m", "p_model"):
        shape = getattr(corr, name).shape
        if shape != (num_rows, 3):
            raise ValueError(f"correspondences.{name} must have shape ({num_rows}, 3), got {shape}")
    T_init = np.asarray(T_init)
    if T_init.shape != (4, 4):
        raise ValueError(f"T_init must have shape (4, 4), got {T_init.shape}")
    if theta_init is not None and np.shape(theta_init) != (model.num_joints,):
        raise ValueError(f"theta_init must have shape ({model.num_joints},), got {np.shape(theta_init)}")
    dtype = corr.n.dtype
    _check_rigid(T_init, dtype)
    theta = np.zeros(model.num_joints) if theta_init is None else np.asarray(theta_init)
    # The compiled solve checks its inputs first (never raising); its status is turned into an error here.
    if prior is not None and not (np.all(np.isfinite(np.asarray(prior.strength))) and np.all(np.asarray(prior.strength) >= 0)):
        raise ValueError(f"prior.strength must be finite and ≥ 0, got {np.asarray(prior.strength)}")
    sol = solve_pose(model, corr, T_init, theta_init, config, cameras, prior)
    status = Status(int(sol.status))
    if status == Status.INVALID_INPUT:
        reason = _describe_invalid(model, corr, T_init, theta, cameras)
        if reason == "invalid pose-solver input" and cameras is not None:
            clean = _sanitize(corr)
            behind = float(fraction_behind_cameras(model, clean, jnp.asarray(T_init, dtype), jnp.asarray(theta, dtype), cameras))
            reason = (
                f"T_init puts {100 * behind:.0f}% of the correspondence weight behind the cameras (the model "
                "points must lie in front of the camera along their viewing rays)"
            )
        raise ValueError(f"invalid pose-solver input: {reason}")
    if status == Status.TOO_FEW:
        raise ValueError(
            f"too few effective correspondences: {int(corr.num_effective())} with positive weight give "
            f"{2 * int(corr.num_effective())} constraints for {model.num_dof} degrees of freedom"
        )
    check_status(sol.status, throw=throw, context="estimate_pose")
    return sol
