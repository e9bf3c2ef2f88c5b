"""Kinematic chains (eq. 2): a tree of rigid parts moved by a root twist and zero-pitch joint twists.

A point X on part p (given in the model frame at the zero configuration) moves to

    T(χ) X = exp(ξ̂) · Π_{j ∈ J(p)} exp(θ_j ξ̂_j) · X,                          (eq. 2)

with χ = (ξ, Θ) and J(p) the joints on the path from the root to part p, ordered root first. Joint j is
a revolute joint: unit axis ω_j through a point q_j, twist ξ_j = (−ω_j × q_j, ω_j) (zero pitch), θ_j in
radians; or a prismatic joint (URDF models): ξ_j = (v_j, 0) with v_j the unit sliding direction, θ_j in mm.
A rigid object is a chain with one part and no joints.

The tree is stored with static shapes as a mask `part_joints[p, j] = j ∈ J(p)`; joints are ordered so
that a joint's parent joints come first (topological order), which makes the product an ordered scan.
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import numpy.typing as npt
from jax.typing import DTypeLike

from .._device import to_device
from ._lie import se3_exp, transform_point_columns


class KinematicModel(eqx.Module):
    """Static description of a kinematic tree.

    Attributes:
        joint_twists: (J, 6) zero-pitch twists ξ_j = (−ω_j × q_j, ω_j) in the model frame at Θ = 0.
        part_joints: (P, J) bool, `part_joints[p, j]` iff joint j lies on the path root → part p.
        joint_parent_part: (J,) int, the part each joint hangs from (for information and drawing).
        joint_child_part: (J,) int, the part each joint moves.
    """

    joint_twists: jax.Array
    part_joints: jax.Array
    joint_parent_part: jax.Array
    joint_child_part: jax.Array

    @property
    def num_parts(self) -> int:
        return self.part_joints.shape[0]

    @property
    def num_joints(self) -> int:
        return self.part_joints.shape[1]

    @property
    def num_dof(self) -> int:
        """Degrees of freedom of χ: 6 for the root plus one per joint."""
        return 6 + self.num_joints


def rigid_model(dtype: DTypeLike = jnp.float32) -> KinematicModel:
    """A rigid object: one part, no joints."""
    return KinematicModel(
        joint_twists=to_device(np.zeros((0, 6), dtype)),  # host arrays: no eager XLA program per field
        part_joints=to_device(np.zeros((1, 0), bool)),
        joint_parent_part=to_device(np.zeros((0,), np.int32)),
        joint_child_part=to_device(np.zeros((0,), np.int32)),
    )


def revolute_twist(axis: npt.ArrayLike, point: npt.ArrayLike):
    """Zero-pitch twist ξ = (−ω × q, ω) of a revolute joint with axis ω (normalised) through q."""
    axis = np.asarray(axis, np.float64)
    norm = np.linalg.norm(axis)
    if not np.isfinite(norm) or norm < 1e-12:
        raise ValueError(f"revolute joint axis must be a finite non-zero 3-vector, got {axis!r}")
    omega = axis / norm
    q = np.asarray(point, np.float64)
    if q.shape != (3,) or not np.all(np.isfinite(q)):
        raise ValueError(f"revolute joint point must be a finite 3-vector, got {point!r}")
    return np.concatenate([-np.cross(omega, q), omega])


def prismatic_twist(axis: npt.ArrayLike):
    """Pure translation twist ξ = (v, 0) of a prismatic joint sliding along v (normalised)."""
    axis = np.asarray(axis, np.float64)
    norm = np.linalg.norm(axis)
    if axis.shape != (3,) or not np.isfinite(norm) or norm < 1e-12:
        raise ValueError(f"prismatic joint axis must be a finite non-zero 3-vector, got {axis!r}")
    return np.concatenate([axis / norm, np.zeros(3)])


def chain_model(
    parents: Sequence[int],
    axes: Sequence[Sequence[float]],
    points: Sequence[Sequence[float]],
    dtype: DTypeLike = jnp.float32,
    joint_types: Sequence[str] | None = None,
) -> KinematicModel:
    """Build a kinematic tree with one joint (revolute unless `joint_types` says otherwise) per non-root part.

    Args:
        parents: (P,) parent part of each part; `parents[0] = -1` is the root; every other part p is
            attached to `parents[p] < p` by joint p − 1 (so parts, and joints, are in topological order).
        axes: (P − 1, 3) joint axes ω_j (sliding directions for prismatic joints) in the model frame
            (normalised here).
        points: (P − 1, 3) a point q_j on each joint axis, model frame (unused by prismatic joints).
        joint_types: (P − 1,) "revolute" or "prismatic" per joint; None means all revolute.

    Returns:
        KinematicModel with J = P − 1 joints.
    """
    parents = [int(p) for p in parents]
    num_parts = len(parents)
    if num_parts == 0 or parents[0] != -1:
        raise ValueError("parents[0] must be -1 (part 0 is the root)")
    for p in range(1, num_parts):
        if not 0 <= parents[p] < p:
            raise ValueError(f"parents[{p}] = {parents[p]} must name an earlier part (0..{p - 1})")
    num_joints = num_parts - 1
    if len(axes) != num_joints or len(points) != num_joints:
        raise ValueError(
            f"a tree of {num_parts} parts has {num_joints} joints; got {len(axes)} axes and {len(points)} points"
        )
    joint_types = ["revolute"] * num_joints if joint_types is None else [str(t) for t in joint_types]
    if len(joint_types) != num_joints:
        raise ValueError(f"joint_types must have {num_joints} entries, got {len(joint_types)}")
    for j, kind in enumerate(joint_types):
        if kind not in ("revolute", "prismatic"):
            raise ValueError(f"joint_types[{j}] = {kind!r}: must be 'revolute' or 'prismatic'")
    twists = [
        prismatic_twist(a) if kind == "prismatic" else revolute_twist(a, q)
        for a, q, kind in zip(axes, points, joint_types)
    ]
    twists = np.stack(twists) if num_joints else np.zeros((0, 6))
    mask = np.zeros((num_parts, num_joints), bool)
    for p in range(1, num_parts):
        mask[p] = mask[parents[p]]
        mask[p, p - 1] = True
    return KinematicModel(
        joint_twists=to_device(twists, dtype),  # host arrays: no eager XLA program per field
        part_joints=to_device(mask),
        joint_parent_part=to_device(np.asarray(parents[1:]), np.int32),
        joint_child_part=to_device(np.arange(1, num_parts), np.int32),
    )


def part_transforms(model: KinematicModel, T_world_root: jax.Array, theta: jax.Array):
    """Forward kinematics of all parts at once (eq. 2).

    Args:
        model: the kinematic tree (P parts, J joints).
        T_world_root: (4, 4) the root pose exp(ξ̂) (maps model coordinates to world).
        theta: (J,) joint values Θ: radians (revolute), mm (prismatic).

    Returns:
        (P, 4, 4) T_world_part[p] = T_world_root · Π_{j ∈ J(p)} exp(θ_j ξ̂_j), to apply to model-frame
        points of part p at the zero configuration.
    """
    dtype = T_world_root.dtype
    num_parts = model.num_parts
    joint_exps = se3_exp(theta[:, None].astype(dtype) * model.joint_twists.astype(dtype))  # (J, 4, 4)
    eye = jnp.broadcast_to(jnp.eye(4, dtype=dtype), (num_parts, 4, 4))

    def multiply_joint(chain, joint):
        exp_j, on_path = joint  # (4, 4), (P,)
        # Parts whose path contains joint j pick up exp(θ_j ξ̂_j) on the right (root-first order).
        return jnp.where(on_path[:, None, None], chain @ exp_j, chain), None

    chain, _ = jax.lax.scan(multiply_joint, eye, (joint_exps, model.part_joints.T))
    return T_world_root @ chain


def part_points_world(model: KinematicModel, T_world_root: jax.Array, theta: jax.Array, p_model: jax.Array, part: jax.Array):
    """World coordinates (N, 3) of model points (N, 3) of parts (N,) int at the pose (T_world_root, θ) (eq. 2).
    Jittable."""
    T_parts = part_transforms(model, T_world_root, theta)
    return jnp.stack(part_point_columns(T_parts, part, p_model[:, 0], p_model[:, 1], p_model[:, 2]), -1)


def part_point_columns(T_parts: jax.Array, part: jax.Array, x: jax.Array, y: jax.Array, z: jax.Array):
    """Each point moved by its own part's transform, as coordinate columns: T_parts (P, 4, 4), part (N,) int and
    x, y, z (N,) → (x', y', z'), each (N,). The arithmetic of `transform_point_columns(T_parts[part], x, y, z)`
    (`part` has the points' shape).

    Each entry of T_parts[part] is gathered on its own from a (P,) column: XLA:CPU wrote the whole (N, 4, 4)
    gather out, in a transposed layout, before the arithmetic read it (the human's 170 000 texels on 4 cameras:
    44 MB a frame; README, "Per-part transforms gathered by entry"). One part (P = 1): its transform for every
    point, `part` is not read."""
    if T_parts.shape[0] == 1:
        return transform_point_columns(T_parts[0], x, y, z)

    def entry(i, j):
        return T_parts[:, i, j][part]

    return tuple(entry(i, 0) * x + entry(i, 1) * y + entry(i, 2) * z + entry(i, 3) for i in range(3))
