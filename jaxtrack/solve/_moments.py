"""The normal equations of eq. 5 from per-part moments of the rows: one pass over the rows per solve.

`plane_normal_equations` builds H, g and the cost from every row at every Gauss-Newton iterate: the 4-camera human's
solves multiply a 27 x 38 016 matrix by its transpose about 50 times a frame (README, "Where the whole step spends its
time"), though the rows and their weights do not change within a solve. Their residuals and Jacobian columns are
linear in a few numbers per row, so the sums can be taken once and the iterates only combine them.

A plane row (unit normal b, world offset d, weight w) of a model point p on part k, whose part transform at the
iterate is A_k = [R_k | t_k] (3 x 4, model → world), has the world point a = A_k v, v = (p, 1), the residual
s = b · a − d and the root columns u = (b, a × b) (`_normal_equations`). Both are linear in z = b ⊗ v (12 numbers):
b_c = z_{c,3}, (a × b)_x = Σ_m A_{y,m} z_{z,m} − A_{z,m} z_{y,m} (and cyclic), and, measured from the solve's start
A⁰_k where the residual is s⁰ = b · A⁰_k v − d, s = s⁰ + Σ_{c,m} (A_k − A⁰_k)_{c,m} z_{c,m}. So with
ẑ = (z, s⁰) (13) and the 7 x 13 matrix M_k of the iterate, (u, s) = M_k ẑ and

    Σ_{rows of part k} w (u, s)(u, s)ᵀ = M_k Q_k M_kᵀ,    Q_k = Σ_{rows of part k} w ẑ ẑᵀ   (13 x 13).

A joint's Jacobian column is its world twist applied to u (on the row's path), so H = Σ_k P_k G_k P_kᵀ with
P_k = [I₆; on_path_k ⊙ twists] (D x 6) and G_k the 6 x 6 block of M_k Q_k M_kᵀ; g and the cost come from its last
column. The residual is kept relative to the start (s⁰, not d): in float32 the world offsets d (metres, in mm) would
cancel against b · a to a residual of a millimetre and lose three digits of g and six of the cost.

The two planes of a correspondence share v, so Σ_planes w b⊗v (b⊗v)ᵀ = (Σ_planes w b bᵀ) ⊗ v vᵀ: 6 x 10 products
of a correspondence, 12 for its s⁰ b ⊗ v and 1 for s⁰², summed per part in one product with the parts' one-hot
columns. Not for the depth-invariant residuals (`depth_invariant`: their scale depends on the iterate's depth).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..geometry import KinematicModel, part_transforms, se3_adjoint
from ._normal_equations import _plane_residuals, _world_point_columns

# Unique pairs (i ≤ j) of a symmetric 3 x 3 and 4 x 4 matrix.
_PAIRS3 = tuple((i, j) for i in range(3) for j in range(i, 3))
_PAIRS4 = tuple((i, j) for i in range(4) for j in range(i, 4))


class PlaneMoments(eqx.Module):
    """The rows of one solve summed per part (`plane_moments`).

    Attributes:
        Q: (P, 13, 13) Σ w ẑ ẑᵀ over each part's plane rows, ẑ = (b ⊗ (p, 1), s⁰) (index 4c + m for b_c v_m, 12 for s⁰).
        A0: (P, 3, 4) the part transforms [R | t] at the solve's start (where s⁰ was taken).
    """

    Q: jax.Array
    A0: jax.Array


def plane_moments(
    model: KinematicModel,
    T_world_root: jax.Array,
    theta: jax.Array,
    p_model: jax.Array,
    part: jax.Array,
    normals: jax.Array,
    offsets: jax.Array,
    weight: jax.Array,
) -> PlaneMoments:
    """Per-part moments of the plane rows at the start (T_world_root, Θ) of a solve.

    Args: as `plane_normal_equations` (p_model (N, 3), part (N,), normals (N, 2, 3), offsets (N, 2), weight (N,) or
    (N, 2)).
    """
    dtype = normals.dtype
    T_parts = part_transforms(model, T_world_root, theta)
    s0 = _plane_residuals(_world_point_columns(model, T_parts, p_model, part), normals, offsets)  # (N, 2)
    w = jnp.broadcast_to(weight[:, None] if weight.ndim == 1 else weight, s0.shape).astype(dtype)
    b = [normals[..., c] for c in range(3)]  # 3 x (N, 2)
    v = [p_model[:, 0], p_model[:, 1], p_model[:, 2], jnp.ones_like(p_model[:, 0])]
    # Σ_planes w b_c b_c', Σ_planes w s⁰ b_c, Σ_planes w s⁰²: per correspondence.
    bb = [jnp.sum(w * b[i] * b[j], axis=-1) for i, j in _PAIRS3]
    sb = [jnp.sum(w * s0 * b[c], axis=-1) for c in range(3)]
    ss = jnp.sum(w * s0 * s0, axis=-1)
    columns = [x * v[m] * v[n] for x in bb for m, n in _PAIRS4]  # 60
    columns += [x * v[m] for x in sb for m in range(4)]  # 12
    columns.append(ss)
    F = jnp.stack(columns, axis=-1)  # (N, 73)
    if model.num_parts == 1:
        sums = jnp.sum(F, axis=0)[None]
    else:
        onehot = (part[:, None] == jnp.arange(model.num_parts, dtype=part.dtype)[None, :]).astype(dtype)
        sums = jnp.einsum("np,nf->pf", onehot, F, precision=jax.lax.Precision.HIGHEST)  # (P, 73)
    return PlaneMoments(_unpack(sums), T_parts[:, :3, :])


def _unpack_index() -> np.ndarray:
    """(13, 13) the index into the 73 unique sums of each entry of Q."""
    index = np.full((13, 13), -1, np.int32)
    f = 0
    for ci, cj in _PAIRS3:
        for mi, mj in _PAIRS4:
            for c1, m1, c2, m2 in ((ci, mi, cj, mj), (ci, mj, cj, mi), (cj, mi, ci, mj), (cj, mj, ci, mi)):
                index[4 * c1 + m1, 4 * c2 + m2] = f
            f += 1
    for c in range(3):
        for m in range(4):
            index[4 * c + m, 12] = index[12, 4 * c + m] = f
            f += 1
    index[12, 12] = f
    assert f == 72 and np.all(index >= 0)
    return index


_UNPACK = _unpack_index()


def _unpack(sums: jax.Array) -> jax.Array:
    """(P, 73) unique sums → (P, 13, 13) Q (one gather with a constant index)."""
    return sums[:, _UNPACK]


def _row_map(A: jax.Array, A0: jax.Array) -> jax.Array:
    """M (P, 7, 13): (u, s) = M ẑ for the part transforms A (P, 3, 4) of the iterate and A0 of the start."""
    P, dtype = A.shape[0], A.dtype
    zero = jnp.zeros((P, 4), dtype)
    e3 = jnp.broadcast_to(jnp.eye(4, dtype=dtype)[3], (P, 4))

    def block(c0, c1, c2):  # a row over z's 12 entries as 3 blocks of 4 (b_x v, b_y v, b_z v)
        return jnp.concatenate([c0, c1, c2, jnp.zeros((P, 1), dtype)], axis=-1)

    rows = [block(e3, zero, zero), block(zero, e3, zero), block(zero, zero, e3)]
    # (a × b)_x = a_y b_z − a_z b_y with a_c = Σ_m A_{c,m} v_m: the coefficient of z_{z,m} is A_{y,m}, of z_{y,m} −A_{z,m}.
    rows.append(block(zero, -A[:, 2], A[:, 1]))
    rows.append(block(A[:, 2], zero, -A[:, 0]))
    rows.append(block(-A[:, 1], A[:, 0], zero))
    dA = (A - A0).reshape(P, 12)
    rows.append(jnp.concatenate([dA, jnp.ones((P, 1), dtype)], axis=-1))
    return jnp.stack(rows, axis=1)


def moment_normal_equations(model: KinematicModel, T_world_root: jax.Array, theta: jax.Array, moments: PlaneMoments):
    """H (D, D), g (D,) and the cost of eq. 5 at (T_world_root, Θ) from the solve's `plane_moments`: the values of
    `plane_normal_equations` on the same rows (up to rounding), at a cost independent of the number of rows."""
    T_parts = part_transforms(model, T_world_root, theta)
    M = _row_map(T_parts[:, :3, :], moments.A0.astype(T_parts.dtype))
    G = jnp.einsum("pab,pbc,pdc->pad", M, moments.Q.astype(M.dtype), M, precision=jax.lax.Precision.HIGHEST)  # (P, 7, 7)
    if not model.num_joints:
        G = G[0]
        return G[:6, :6], G[:6, 6], G[6, 6]
    anchors = T_parts[model.joint_parent_part]  # (J, 4, 4)
    twists_world = jnp.einsum("jab,jb->ja", se3_adjoint(anchors), model.joint_twists.astype(M.dtype))  # (J, 6)
    on_path = model.part_joints.astype(M.dtype)  # (P, J)
    eye = jnp.broadcast_to(jnp.eye(6, dtype=M.dtype), (model.num_parts, 6, 6))
    Pk = jnp.concatenate([eye, on_path[:, :, None] * twists_world[None]], axis=1)  # (P, D, 6)
    H = jnp.einsum("pda,pab,peb->de", Pk, G[:, :6, :6], Pk, precision=jax.lax.Precision.HIGHEST)
    g = jnp.einsum("pda,pa->d", Pk, G[:, :6, 6], precision=jax.lax.Precision.HIGHEST)
    return H, g, jnp.sum(G[:, 6, 6])
