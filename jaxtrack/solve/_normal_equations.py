"""Analytic Jacobian and normal equations of the Plücker-line cost (eq. 4-5), in a plane basis.

The Plücker residual r = a × n − m of a world point a is orthogonal to n, so with an orthonormal
pair (b1, b2) ⊥ n its squared norm is the sum of two squared plane distances:

    |a × n − m|² = Σ_k (b_k · a − d_k)²,    d_k = b_k · p0,   p0 = n × m (closest line point to 0).

Same cost, same minimiser as eq. 4, but two rows per correspondence instead of three, and each
row's Jacobian has a closed form. Under a left increment (v, ω) of the root, δa = v + ω × a, so the
row is [b_k, a × b_k]; a joint j on the part's path moves a by ω'_j × a + v'_j with the joint twist
ξ'_j = Ad(T_world_parent(j)) ξ_j carried to the world, giving the entry ξ'_j · [b_k, a × b_k].

All D = 6 + J columns are stacked into one (N, 2, D) Jacobian built with array operations over the
joints, and H = Σ w JᵀJ is one contraction. The traced program therefore has the same size for any
joint count: XLA's compile time stays nearly flat in J (a body has 20-30 joints), where building H
from D(D+1)/2 separately traced column products grew with D² (measured in experiments/bench_pose.py).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ..geometry import KinematicModel, part_transforms, se3_adjoint, transform_point_columns


def line_planes(n: jax.Array, m: jax.Array):
    """Two orthonormal planes through each Plücker line (n unit, m moment).

    Args:
        n: (N, 3) unit directions; zero for padding rows.
        m: (N, 3) moments.

    Returns:
        normals (N, 2, 3) with b1, b2 ⊥ n, and offsets (N, 2) d_k = b_k · p0.
    """
    # The helper axis least aligned with n keeps the cross product well conditioned.
    helper = jnp.where(
        (jnp.abs(n[..., 0]) < 0.9)[..., None], jnp.array([1.0, 0.0, 0.0], n.dtype), jnp.array([0.0, 1.0, 0.0], n.dtype)
    )
    b1 = jnp.cross(n, helper)
    norm = jnp.linalg.norm(b1, axis=-1, keepdims=True)
    # Zeroed padding rows have n = 0; they get zero planes instead of 0/0.
    b1 = b1 / jnp.where(norm > 0, norm, 1.0)
    b2 = jnp.cross(n, b1)
    p0 = jnp.cross(n, m)
    normals = jnp.stack([b1, b2], axis=-2)
    return normals, jnp.sum(normals * p0[..., None, :], axis=-1)


def _world_points(model: KinematicModel, T_parts: jax.Array, p_model: jax.Array, part: jax.Array) -> jax.Array:
    """World coordinates T(χ) X (eq. 2) of model points on their parts, (N, 3)."""
    T = T_parts[0] if model.num_parts == 1 else T_parts[part]  # (4, 4) rigid: skip the gather; else (N, 4, 4)
    return jnp.stack(transform_point_columns(T, p_model[..., 0], p_model[..., 1], p_model[..., 2]), axis=-1)


def _plane_residuals(a: jax.Array, normals: jax.Array, offsets: jax.Array) -> jax.Array:
    """s_k = b_k · a − d_k, (N, 2), written elementwise (no small batched contractions on CPU)."""
    return jnp.sum(normals * a[..., None, :], axis=-1) - offsets


def plane_residuals(
    model: KinematicModel,
    T_world_root: jax.Array,
    theta: jax.Array,
    p_model: jax.Array,
    part: jax.Array,
    normals: jax.Array,
    offsets: jax.Array,
) -> jax.Array:
    """Plane residuals s (N, 2) of eq. 4 at (T_world_root, Θ): Σ_k s_k² = |T(χ)X × n − m|²."""
    a = _world_points(model, part_transforms(model, T_world_root, theta), p_model, part)
    return _plane_residuals(a, normals, offsets)


def plane_residuals_and_jacobian(
    model: KinematicModel,
    T_world_root: jax.Array,
    theta: jax.Array,
    p_model: jax.Array,
    part: jax.Array,
    normals: jax.Array,
    offsets: jax.Array,
):
    """Plane residuals s (N, 2) and their Jacobian (N, 2, D), D = 6 + J (eq. 5).

    Columns 0-5 are the root's left increment (v, ω): [b_k, a × b_k]. Column 6 + j is joint j's
    world twist ξ'_j (J, 6) applied to those six, times whether joint j lies on the point's path;
    one contraction over the six twist coordinates makes all J columns at once.
    """
    T_parts = part_transforms(model, T_world_root, theta)
    a = _world_points(model, T_parts, p_model, part)
    s = _plane_residuals(a, normals, offsets)
    root_columns = jnp.concatenate([normals, jnp.cross(a[..., None, :], normals)], axis=-1)  # (N, 2, 6)
    if not model.num_joints:
        return s, root_columns
    anchors = T_parts[model.joint_parent_part]  # (J, 4, 4)
    twists_world = jnp.einsum("jab,jb->ja", se3_adjoint(anchors), model.joint_twists.astype(s.dtype))  # (J, 6)
    on_path = model.part_joints[part].astype(s.dtype)  # (N, J)
    joint_columns = jnp.einsum("nkc,jc->nkj", root_columns, twists_world) * on_path[:, None, :]  # (N, 2, J)
    return s, jnp.concatenate([root_columns, joint_columns], axis=-1)


def plane_normal_equations(
    model: KinematicModel,
    T_world_root: jax.Array,
    theta: jax.Array,
    p_model: jax.Array,
    part: jax.Array,
    normals: jax.Array,
    offsets: jax.Array,
    weight: jax.Array,
):
    """Gauss-Newton normal equations of eq. 5 at (T_world_root, Θ).

    Returns:
        H = Σ w JᵀJ (D, D), g = Σ w Jᵀ s (D,), cost = Σ w |s|² (= Σ w |r|² of eq. 4), D = 6 + J.
    """
    s, jac = plane_residuals_and_jacobian(model, T_world_root, theta, p_model, part, normals, offsets)
    rows = jac.reshape(-1, jac.shape[-1])  # (2N, D): both planes of every correspondence
    w_rows = jnp.repeat(weight, 2)
    weighted = rows * w_rows[:, None]
    # HIGHEST: on accelerators the default may round the products to bf16/tf32, too coarse for H.
    H = jnp.einsum("rd,re->de", weighted, rows, precision=jax.lax.Precision.HIGHEST)
    s_rows = s.reshape(-1)
    g = jnp.einsum("rd,r->d", weighted, s_rows, precision=jax.lax.Precision.HIGHEST)
    return H, g, jnp.sum(w_rows * s_rows * s_rows)
