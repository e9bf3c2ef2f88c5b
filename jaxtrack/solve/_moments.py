"""The normal equations of eq. 5 from per-part moments of the rows: one pass over the rows per solve.

`plane_normal_equations` builds H, g and the cost from every row at every Gauss-Newton iterate: the 4-camera human's
solves multiplied a 27 x 38 016 matrix (both planes of 19 008 rows) by its transpose about 50 times a frame (README,
"Where the whole step spends its time"), though the rows and their weights do not change within a solve. Their
residuals and Jacobian columns are linear in a few numbers per row, so the sums can be taken once and the iterates
only combine them.

A plane row (unit normal b, world offset d, weight w) of a model point p on part k has, at an iterate whose part
transform is (R_k, t_k) (model → world), the world point a = R_k p + t_k, the residual s = b · a − d and the root
columns u = (b, a × b) (`_normal_equations`). Centred on the part's rows, q = p − p̄_k and c_k = R_k p̄_k + t_k (the
centroid's world position at the iterate), a = c_k + R_k q and

    u = L(c_k) u_c,   u_c = (b, (R_k q) × b),   L(c) = [[I, 0], [ĉ, I]]   (a × b = (R q) × b + c × b),
    s = s⁰ + b · ((R_k − R⁰_k) q + (c_k − c⁰_k)),

with s⁰ the residual at the solve's start (R⁰_k, c⁰_k). Both u_c and s are linear in ẑ = (b ⊗ (q, 1), s⁰) (13
numbers), (u_c, s) = M_k ẑ with M_k (7 x 13) built from R_k, R_k − R⁰_k and c_k − c⁰_k, so

    Σ_{rows of part k} w (u_c, s)(u_c, s)ᵀ = M_k Q_k M_kᵀ,    Q_k = Σ_{rows of part k} w ẑ ẑᵀ   (13 x 13).

A joint's Jacobian column is its world twist applied to u (on the row's path), so H = Σ_k P̃_k G_k P̃_kᵀ with
P̃_k = [I₆; on_path_k ⊙ twists] L(c_k) (D x 6) and G_k the 6 x 6 block of M_k Q_k M_kᵀ; g and the cost come from
its last column. The centring is for float32: uncentred, a twist's column ξ' · u cancels (|a| / |a − q_joint|)² in
H's joint entries (a metre from the origin against a limb's length), and the cost's (s⁰ + (A − A⁰) v)² carries the
translation column's change under a rotation about the model origin (ω × t, a hundred mm for a small step); centred,
H and g are as precise as the rows' (tests/test_normal_equations.py). The residual is kept relative to the start (s⁰,
not d) for the same reason: the world offsets d (metres, in mm) would cancel against b · a to a residual of a
millimetre. What remains is the cost's (s⁰ + δ)², which loses digits where the start's residuals are much larger
than the iterate's; near the optimum that can decide a step's acceptance by rounding. On few rows the per-part
products cost more than they save (`SolverConfig.moments_from_rows`: the solver takes them from 1024 rows on).

The two planes of a correspondence share q, so Σ_planes w b⊗v (b⊗v)ᵀ = (Σ_planes w b bᵀ) ⊗ v vᵀ, v = (q, 1): 6 x 10
products of a correspondence, 12 for its s⁰ b ⊗ v and 1 for s⁰², summed per part in one product with the parts'
one-hot columns (a second, of 4 columns, finds the centroids first). Not for the depth-invariant residuals
(`depth_invariant`: their scale depends on the iterate's depth).
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
        Q: (P, 13, 13) Σ w ẑ ẑᵀ over each part's plane rows, ẑ = (b ⊗ (q, 1), s⁰), q = p − p̄ (index 4c + m for
            b_c v_m, 12 for s⁰).
        centroid: (P, 3) p̄, the weighted mean of each part's model points (model frame; 0 for a part without rows).
        R0: (P, 3, 3) the part rotations at the solve's start (where s⁰ was taken).
        c0: (P, 3) the centroids' world positions there.
    """

    Q: jax.Array
    centroid: jax.Array
    R0: jax.Array
    c0: jax.Array


def _part_sums(model: KinematicModel, part: jax.Array, F: jax.Array) -> jax.Array:
    """(N, F) per-row columns summed per part, (P, F): one product with the parts' one-hot columns."""
    if model.num_parts == 1:
        return jnp.sum(F, axis=0)[None]
    onehot = (part[:, None] == jnp.arange(model.num_parts, dtype=part.dtype)[None, :]).astype(F.dtype)
    return jnp.einsum("np,nf->pf", onehot, F, precision=jax.lax.Precision.HIGHEST)


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
    w_row = jnp.sum(w, axis=-1)
    first = _part_sums(model, part, jnp.concatenate([w_row[:, None] * p_model, w_row[:, None]], axis=-1))  # (P, 4)
    centroid = first[:, :3] / jnp.where(first[:, 3:] > 0, first[:, 3:], 1.0)
    q = p_model - (centroid[0] if model.num_parts == 1 else centroid[part])
    b = [normals[..., c] for c in range(3)]  # 3 x (N, 2)
    v = [q[:, 0], q[:, 1], q[:, 2], jnp.ones_like(q[:, 0])]
    # Σ_planes w b_c b_c', Σ_planes w s⁰ b_c, Σ_planes w s⁰²: per correspondence.
    bb = [jnp.sum(w * b[i] * b[j], axis=-1) for i, j in _PAIRS3]
    sb = [jnp.sum(w * s0 * b[c], axis=-1) for c in range(3)]
    ss = jnp.sum(w * s0 * s0, axis=-1)
    columns = [x * v[m] * v[n] for x in bb for m, n in _PAIRS4]  # 60
    columns += [x * v[m] for x in sb for m in range(4)]  # 12
    columns.append(ss)
    sums = _part_sums(model, part, jnp.stack(columns, axis=-1))  # (P, 73)
    R0 = T_parts[:, :3, :3]
    c0 = jnp.einsum("pab,pb->pa", R0, centroid) + T_parts[:, :3, 3]
    return PlaneMoments(_unpack(sums), centroid, R0, c0)


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


def _row_map(R: jax.Array, dR: jax.Array, dc: jax.Array) -> jax.Array:
    """M (P, 7, 13): (u_c, s) = M ẑ for the iterate's part rotations R (P, 3, 3), their change from the start dR and
    the centroids' move dc (P, 3)."""
    P, dtype = R.shape[0], R.dtype
    zero = jnp.zeros((P, 4), dtype)
    e3 = jnp.broadcast_to(jnp.eye(4, dtype=dtype)[3], (P, 4))
    Rq = jnp.concatenate([R, jnp.zeros((P, 3, 1), dtype)], axis=-1)  # (R q)_c = Σ_m R_{c,m} v_m (v_3 = 1 not read)

    def block(c0, c1, c2):  # a row over z's 12 entries as 3 blocks of 4 (b_x v, b_y v, b_z v)
        return jnp.concatenate([c0, c1, c2, jnp.zeros((P, 1), dtype)], axis=-1)

    rows = [block(e3, zero, zero), block(zero, e3, zero), block(zero, zero, e3)]
    # ((R q) × b)_x = (Rq)_y b_z − (Rq)_z b_y: the coefficient of z_{z,m} is R_{y,m}, of z_{y,m} −R_{z,m}.
    rows.append(block(zero, -Rq[:, 2], Rq[:, 1]))
    rows.append(block(Rq[:, 2], zero, -Rq[:, 0]))
    rows.append(block(-Rq[:, 1], Rq[:, 0], zero))
    ds = jnp.concatenate([dR, dc[:, :, None]], axis=-1).reshape(P, 12)  # s − s⁰ = Σ_c b_c ((dR q)_c + dc_c)
    rows.append(jnp.concatenate([ds, jnp.ones((P, 1), dtype)], axis=-1))
    return jnp.stack(rows, axis=1)


def _hat(c: jax.Array) -> jax.Array:
    """(P, 3) → (P, 3, 3) ĉ with ĉ b = c × b."""
    zero = jnp.zeros_like(c[:, 0])
    return jnp.stack([jnp.stack([zero, -c[:, 2], c[:, 1]], -1), jnp.stack([c[:, 2], zero, -c[:, 0]], -1),
                      jnp.stack([-c[:, 1], c[:, 0], zero], -1)], axis=1)


def moment_normal_equations(model: KinematicModel, T_world_root: jax.Array, theta: jax.Array, moments: PlaneMoments):
    """H (D, D), g (D,) and the cost of eq. 5 at (T_world_root, Θ) from the solve's `plane_moments`: the values of
    `plane_normal_equations` on the same rows (up to rounding), at a cost independent of the number of rows."""
    T_parts = part_transforms(model, T_world_root, theta)
    dtype = T_parts.dtype
    R = T_parts[:, :3, :3]
    c = jnp.einsum("pab,pb->pa", R, moments.centroid.astype(dtype)) + T_parts[:, :3, 3]
    M = _row_map(R, R - moments.R0.astype(dtype), c - moments.c0.astype(dtype))
    G = jnp.einsum("pab,pbc,pdc->pad", M, moments.Q.astype(dtype), M, precision=jax.lax.Precision.HIGHEST)  # (P, 7, 7)
    P = model.num_parts
    eye3 = jnp.broadcast_to(jnp.eye(3, dtype=dtype), (P, 3, 3))
    zero3 = jnp.zeros((P, 3, 3), dtype)
    L = jnp.concatenate([jnp.concatenate([eye3, zero3], -1), jnp.concatenate([_hat(c), eye3], -1)], axis=1)  # (P, 6, 6)
    if model.num_joints:
        anchors = T_parts[model.joint_parent_part]  # (J, 4, 4)
        twists_world = jnp.einsum("jab,jb->ja", se3_adjoint(anchors), model.joint_twists.astype(dtype))  # (J, 6)
        on_path = model.part_joints.astype(dtype)  # (P, J)
        # A joint's row of P̃_k: ξ'ᵀ L(c_k) = (v' + ω' × c_k, ω'), the twist's velocity at the centroid.
        v_at = twists_world[None, :, :3] + jnp.cross(twists_world[None, :, 3:], c[:, None, :])  # (P, J, 3)
        joint_rows = on_path[:, :, None] * jnp.concatenate([v_at, jnp.broadcast_to(twists_world[None, :, 3:], v_at.shape)],
                                                           axis=-1)
        Pk = jnp.concatenate([L, joint_rows], axis=1)  # (P, D, 6)
    else:
        Pk = L
    H = jnp.einsum("pda,pab,peb->de", Pk, G[:, :6, :6], Pk, precision=jax.lax.Precision.HIGHEST)
    g = jnp.einsum("pda,pa->d", Pk, G[:, :6, 6], precision=jax.lax.Precision.HIGHEST)
    return H, g, jnp.sum(G[:, 6, 6])
