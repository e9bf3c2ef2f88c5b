"""Analytic Jacobian and normal equations of the Plücker-line cost (eq. 4-5), in a plane basis.

The Plücker residual r = a × n − m of a world point a is orthogonal to n, so with an orthonormal
pair (b1, b2) ⊥ n its squared norm is the sum of two squared plane distances:

    |a × n − m|² = Σ_k (b_k · a − d_k)²,    d_k = b_k · p0,   p0 = n × m (closest line point to 0).

Same cost, same minimiser as eq. 4, but two rows per correspondence instead of three, and each
row's Jacobian has a closed form. Under a left increment (v, ω) of the root, δa = v + ω × a, so the
row is [b_k, a × b_k]; a joint j on the part's path moves a by ω'_j × a + v'_j with the joint twist
ξ'_j = Ad(T_world_parent(j)) ξ_j carried to the world, giving the entry ξ'_j · [b_k, a × b_k].

The J joint columns are built at once with array operations over the joints, stacked (J, N, 2), and
H, g and the cost come from one weighted product of the stacked columns and residuals. The traced
program therefore has the same size for any joint count: XLA's compile time stays nearly flat in J
(a body has 20-30 joints), where building H from D(D+1)/2 separately traced column products and a
Python loop over joints grew with D² (measured in experiments/bench_pose.py).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ..geometry import KinematicModel, part_point_columns, part_transforms, se3_adjoint, transform_point_columns


def line_planes(n: jax.Array, m: jax.Array, normal: jax.Array | None = None, tangent_weight: jax.Array | None = None):
    """Two orthonormal planes through each Plücker line (n unit, m moment), and their weights.

    Args:
        n: (N, 3) unit directions; zero for padding rows.
        m: (N, 3) moments.
        normal: optional (N, 3) unit normals ⊥ n of edge rows' planes (zero for point rows): an edge
            row's first plane is that plane, its second the plane along the edge.
        tangent_weight: optional (N,) weight of an edge row's second plane (ignored for point rows).

    Returns:
        normals (N, 2, 3) with b1, b2 ⊥ n, offsets (N, 2) d_k = b_k · p0, and plane weights (N, 2)
        (1, 1 for a point row: the sum is exactly |a × n − m|²; 1, tangent_weight for an edge row).
    """
    # The helper axis least aligned with n keeps the cross product well conditioned.
    helper = jnp.where(
        (jnp.abs(n[..., 0]) < 0.9)[..., None], jnp.array([1.0, 0.0, 0.0], n.dtype), jnp.array([0.0, 1.0, 0.0], n.dtype)
    )
    b1 = jnp.cross(n, helper)
    if normal is not None:
        edge = jnp.sum(normal * normal, axis=-1, keepdims=True) > 0
        b1 = jnp.where(edge, normal - jnp.sum(normal * n, -1, keepdims=True) * n, b1)
    norm = jnp.linalg.norm(b1, axis=-1, keepdims=True)
    # Zeroed padding rows have n = 0; they get zero planes instead of 0/0.
    b1 = b1 / jnp.where(norm > 0, norm, 1.0)
    b2 = jnp.cross(n, b1)
    p0 = jnp.cross(n, m)
    normals = jnp.stack([b1, b2], axis=-2)
    plane_weight = jnp.ones(n.shape[:-1] + (2,), n.dtype)
    if normal is not None:
        second = jnp.where(edge[..., 0], jnp.ones_like(n[..., 0]) if tangent_weight is None else tangent_weight, 1.0)
        plane_weight = plane_weight.at[..., 1].set(second)
    return normals, jnp.sum(normals * p0[..., None, :], axis=-1), plane_weight


def _world_point_columns(model: KinematicModel, T_parts: jax.Array, p_model: jax.Array, part: jax.Array):
    """World coordinates T(χ) X (eq. 2) of model points on their parts, as three (N,) arrays."""
    if model.num_parts == 1:  # rigid: skip the gather
        return transform_point_columns(T_parts[0], p_model[..., 0], p_model[..., 1], p_model[..., 2])
    return part_point_columns(T_parts, part, p_model[..., 0], p_model[..., 1], p_model[..., 2])


def _plane_residuals(a, normals: jax.Array, offsets: jax.Array) -> jax.Array:
    """s_k = b_k · a − d_k, (N, 2), per coordinate (no reductions over a minor axis of 3 on CPU)."""
    return sum(normals[..., c] * a[c][..., None] for c in range(3)) - offsets


class RayDepths(eqx.Module):
    """What makes the plane residuals invariant to the depth along the rays (`depth_invariant`).

    Attributes:
        origin_offset: (N,) n · o, the ray direction against the centre o of the camera the ray leaves: the depth
            of a point a along its ray is z = n · a − n · o.
        reference: (N,) > 0, the depth Z₀ at which a residual keeps its size (the rows' depths at the solve's
            initial pose: there the scaled residuals equal eq. 4's).
        power: scalar p in [0, 1]; the residual is s · (Z₀ / z)^p (0: eq. 4 as it is).
    """

    origin_offset: jax.Array
    reference: jax.Array
    power: jax.Array


def _with_depth_plane(n: jax.Array, normals: jax.Array, offsets: jax.Array, depths: RayDepths):
    """The planes (N, 2, 3) / (N, 2) with a third: the plane through o ⊥ n, whose residual is the depth z."""
    return (jnp.concatenate([normals, n[..., None, :]], axis=-2),
            jnp.concatenate([offsets, depths.origin_offset[..., None]], axis=-1))


def depth_invariant(s: jax.Array, columns: list, depths: RayDepths):
    """s (N, 3) and a list of columns (each (..., N, 3); empty for the residuals alone) with the depth z as their
    third plane → s · σ and the list of d(s · σ) for the two line planes, σ = (Z₀ / z)^p.

    eq. 4's residual is a distance in mm across the ray: moving every point toward the camera shrinks all of them,
    so rows that disagree (a flow that missed a large motion against SIFT matches that did not) are fitted best by
    sliding the object along the rays toward the centre (measured: 636 → 263 mm in 10 steps, experiments/large_motion.py).
    Scaled by Z₀ / z the residual is an angle across the ray times Z₀: a pixel at the reference depth, whatever
    the depth of the iterate. z is clamped at Z₀ / 10 (no derivative there).
    """
    z_raw = s[..., 2]
    floor = 0.1 * depths.reference
    z = jnp.maximum(z_raw, floor)
    p = jnp.asarray(depths.power, s.dtype)
    sigma = (depths.reference / z) ** p
    dz_factor = jnp.where((z_raw > floor)[..., None], p * s[..., :2] / z[..., None], 0.0)  # (N, 2)
    scaled = s[..., :2] * sigma[..., None]

    def column(c):
        return (c[..., :2] - dz_factor * c[..., 2:3]) * sigma[..., None]

    return scaled, [column(c) for c in columns]


def plane_residuals(
    model: KinematicModel,
    T_world_root: jax.Array,
    theta: jax.Array,
    p_model: jax.Array,
    part: jax.Array,
    normals: jax.Array,
    offsets: jax.Array,
    depths: RayDepths | None = None,
    n: jax.Array | None = None,
) -> jax.Array:
    """Plane residuals s (N, 2) of eq. 4 at (T_world_root, Θ): Σ_k s_k² = |T(χ)X × n − m|²; with `depths` (and
    the rows' ray directions `n`, (N, 3)) each scaled by (Z₀ / z)^p (`depth_invariant`)."""
    a = _world_point_columns(model, part_transforms(model, T_world_root, theta), p_model, part)
    if depths is None:
        return _plane_residuals(a, normals, offsets)
    s = _plane_residuals(a, *_with_depth_plane(n, normals, offsets, depths))
    return depth_invariant(s, [], depths)[0]


def _residuals_and_columns(
    model: KinematicModel,
    T_world_root: jax.Array,
    theta: jax.Array,
    p_model: jax.Array,
    part: jax.Array,
    normals: jax.Array,
    offsets: jax.Array,
):
    """s (N, 2), the six root columns as separate (N, 2) arrays, and the joint columns (J, N, 2) or None."""
    T_parts = part_transforms(model, T_world_root, theta)
    a = [c[..., None] for c in _world_point_columns(model, T_parts, p_model, part)]  # 3 x (N, 1)
    b = [normals[..., c] for c in range(3)]  # 3 x (N, 2)
    s = b[0] * a[0] + b[1] * a[1] + b[2] * a[2] - offsets
    cross = [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    root_columns = b + cross
    if not model.num_joints:
        return s, root_columns, None
    anchors = T_parts[model.joint_parent_part]  # (J, 4, 4)
    twists_world = jnp.einsum("jab,jb->ja", se3_adjoint(anchors), model.joint_twists.astype(s.dtype))  # (J, 6)
    on_path = model.part_joints[part].astype(s.dtype)  # (N, J)
    joint_columns = jnp.einsum("jc,cnk->jnk", twists_world, jnp.stack(root_columns)) * on_path.T[:, :, None]
    return s, root_columns, joint_columns


def plane_residuals_and_jacobian(
    model: KinematicModel,
    T_world_root: jax.Array,
    theta: jax.Array,
    p_model: jax.Array,
    part: jax.Array,
    normals: jax.Array,
    offsets: jax.Array,
):
    """Plane residuals s (N, 2) and their Jacobian, stored column-major as (D, N, 2), D = 6 + J (eq. 5).

    Columns 0-5 are the root's left increment (v, ω): [b_k, a × b_k], written per coordinate.
    Column 6 + j is joint j's world twist ξ'_j applied to those six, times whether joint j lies on
    the point's path; one contraction over the six twist coordinates makes all J columns at once.
    """
    s, root_columns, joint_columns = _residuals_and_columns(model, T_world_root, theta, p_model, part, normals, offsets)
    columns = jnp.stack(root_columns)
    return s, columns if joint_columns is None else jnp.concatenate([columns, joint_columns])


def plane_normal_equations(
    model: KinematicModel,
    T_world_root: jax.Array,
    theta: jax.Array,
    p_model: jax.Array,
    part: jax.Array,
    normals: jax.Array,
    offsets: jax.Array,
    weight: jax.Array,
    depths: RayDepths | None = None,
    n: jax.Array | None = None,
):
    """Gauss-Newton normal equations of eq. 5 at (T_world_root, Θ).

    The Jacobian's columns and the residuals are stacked as the rows of one (D + 1, 2N) array
    A = [J_root; J_joints; s] (both planes of every correspondence), and one weighted product
    M = (A·w) Aᵀ gives H = M[:D, :D], g = M[:D, D] and the cost M[D, D]. One dot instead of a
    reduction per entry of H: XLA:CPU runs each reduction as its own kernel, and the tracker's
    rounds were dominated by kernel launches (82 → 14 per call at N = 200: 0.16 → 0.03 ms; 2000 rows
    0.29 → 0.07 ms). Under vmap the product becomes a batch of tiny matrix products: about even at 64
    problems of 200 rows (0.49 → 0.56 ms), slower at 464 (2-3.6 → 4.4 ms; the tracker's vmapped
    uses are a handful of hypotheses or parameter sets).

    `solve_pose` calls it at every Gauss-Newton iterate for the depth-scaled residuals only; eq. 4 as it is takes the
    per-part moments of the rows once per solve (`jaxtrack.solve._moments`).

    `weight` is (N,) per correspondence or (N, 2) per plane (`line_planes`' plane weights times it). With `depths`
    (and the rays' directions `n`) the residuals and their columns are the depth-invariant ones (`depth_invariant`).

    Returns:
        H = Σ w JᵀJ (D, D), g = Σ w Jᵀ s (D,), cost = Σ w |s|² (= Σ w |r|² of eq. 4), D = 6 + J.
    """
    if depths is None:
        s, root_columns, joint_columns = _residuals_and_columns(model, T_world_root, theta, p_model, part, normals, offsets)
    else:
        s3, root3, joint3 = _residuals_and_columns(model, T_world_root, theta, p_model, part,
                                                   *_with_depth_plane(n, normals, offsets, depths))
        s, columns = depth_invariant(s3, list(root3) + ([] if joint3 is None else [joint3]), depths)
        root_columns, joint_columns = columns[:6], (None if joint3 is None else columns[6])
    w = jnp.broadcast_to(weight[:, None] if weight.ndim == 1 else weight, s.shape).reshape(-1)
    rows = [jnp.stack([c.reshape(-1) for c in root_columns])]
    if joint_columns is not None:
        rows.append(joint_columns.reshape(joint_columns.shape[0], -1))  # (J, 2N)
    A = jnp.concatenate(rows + [s.reshape(1, -1)])  # (D + 1, 2N)
    # HIGHEST: on accelerators the default may round the products to bf16/tf32, too coarse for H.
    M = jnp.einsum("ar,br->ab", A * w, A, precision=jax.lax.Precision.HIGHEST)
    D = A.shape[0] - 1
    return M[:D, :D], M[:D, D], M[D, D]
