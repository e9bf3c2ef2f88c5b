"""A human body model from a mocap skeleton, written as a URDF so that it is read like any other model.

    skeleton = read_asf("07-walk.asf"); motion = read_amc("07_05-walk.amc", skeleton)
    write_urdf(human_description(skeleton), "human.urdf")           # 26 DoF, like the paper's model
    body = read_urdf("human.urdf")
    T_world_root, theta = human_joint_values(skeleton, motion, body.joint_names)

Surface: one tapered capsule per bone segment (radii from a table for the CMU bone names, else from the
bone's length), in the bone's link frame. Joints: the DoF kept by `dofs` (default `PAPER_DOFS`: hips and
shoulders 3 each, knees, elbows, ankles, spine and neck 1 each; with the root's 6, 26 DoF) become
revolute joints named `<bone>_<dof>`; a bone with several kept DoF is a chain of revolute joints
through massless links `<bone>_<dof>_link`, in the skeleton's rotation order, so that

    R_{C·e_a1}(θ_a1) · R_{C·e_a2}(θ_a2) · ... = C · M · C⁻¹       (the ASF bone rotation, `_mocap`)

with the axes C·e_a expressed in the link frames, which are parallel to the world axes at the zero
pose. DoF not kept are locked at 0 (a bone without kept DoF hangs from a `fixed` joint `<bone>_fixed`
and merges into its parent's part). The root's 6 DoF are the model's root pose T_world_root.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import numpy.typing as npt

from ._mocap import Motion, Skeleton, bone_transforms
from ._urdf import RobotDescription, RobotJoint, RobotLink

# The reduced joint set of the paper's 26-DoF body (root 6 + 20), in CMU ASF bone names: hips and
# shoulders 3 DoF, knees and elbows 1 (flexion, rx), ankles 1 (rx; the ASF foot also has rz), spine and
# neck 1 each (forward bending, rx). Clavicles, wrists, hands, fingers, toes, upper spine and head: locked.
PAPER_DOFS: Mapping[str, tuple[str, ...]] = {
    "lfemur": ("rx", "ry", "rz"),
    "rfemur": ("rx", "ry", "rz"),
    "ltibia": ("rx",),
    "rtibia": ("rx",),
    "lfoot": ("rx",),
    "rfoot": ("rx",),
    "lhumerus": ("rx", "ry", "rz"),
    "rhumerus": ("rx", "ry", "rz"),
    "lradius": ("rx",),
    "rradius": ("rx",),
    "lowerback": ("rx",),
    "lowerneck": ("rx",),
}

# Capsule radii (mm) at a bone's joint and at its far end, by CMU bone name without its l/r prefix:
# roughly an adult's limb and trunk widths (the rendered silhouette only needs to be plausible).
CMU_RADII: Mapping[str, tuple[float, float]] = {
    "hipjoint": (70.0, 65.0),
    "femur": (75.0, 50.0),
    "tibia": (50.0, 38.0),
    "foot": (38.0, 30.0),
    "toes": (28.0, 20.0),
    "lowerback": (115.0, 120.0),
    "upperback": (120.0, 125.0),
    "thorax": (125.0, 90.0),
    "lowerneck": (50.0, 45.0),
    "upperneck": (45.0, 50.0),
    "head": (85.0, 85.0),
    "clavicle": (50.0, 45.0),
    "humerus": (45.0, 38.0),
    "radius": (38.0, 30.0),
    "wrist": (28.0, 28.0),
    "hand": (30.0, 25.0),
    "fingers": (18.0, 12.0),
    "thumb": (15.0, 12.0),
}
_MIN_SEGMENT_MM = 1.0


def bone_radii(name: str, length_mm: float) -> tuple[float, float]:
    """Capsule radii (mm) at the joint and the far end of a bone segment: `CMU_RADII` by name (with or
    without its l/r prefix), else 12% and 9% of the length plus 8 mm."""
    for key in (name, name[1:] if name[:1] in ("l", "r") else name):
        if key in CMU_RADII:
            return CMU_RADII[key]
    return 0.12 * length_mm + 8.0, 0.09 * length_mm + 8.0


def tapered_capsule(
    start: npt.ArrayLike, end: npt.ArrayLike, radius_start: float, radius_end: float, segments: int = 16
) -> tuple[np.ndarray, np.ndarray]:
    """A closed surface around the segment start → end: hemispheres of the two radii joined by a cone.

    Returns:
        vertices (V, 3) and faces (F, 3), counter-clockwise seen from outside; V = segments · (2·rings) + 2.
    """
    start, end = np.asarray(start, np.float64), np.asarray(end, np.float64)
    axis = end - start
    length = np.linalg.norm(axis)
    if length <= 0 or radius_start <= 0 or radius_end <= 0 or segments < 3:
        raise ValueError("tapered_capsule needs start != end, radii > 0 and segments >= 3")
    z = axis / length
    x = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    rings = max(2, segments // 4)
    # Profile (radius, height) from the bottom pole to the top pole, poles excluded.
    phi = np.linspace(-np.pi / 2, 0.0, rings + 1)[1:]
    bottom = np.stack([radius_start * np.cos(phi), radius_start * np.sin(phi)], -1)
    phi = np.linspace(0.0, np.pi / 2, rings + 1)[:-1]
    top = np.stack([radius_end * np.cos(phi), length + radius_end * np.sin(phi)], -1)
    profile = np.concatenate([bottom, top])
    angle = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    ring_xy = np.stack([np.cos(angle), np.sin(angle)], -1)
    rings_xyz = np.concatenate(
        [
            profile[:, None, 0, None] * ring_xy[None],
            np.broadcast_to(profile[:, None, 1, None], (len(profile), segments, 1)),
        ],
        -1,
    ).reshape(-1, 3)
    local = np.concatenate([[[0.0, 0.0, -radius_start]], rings_xyz, [[0.0, 0.0, length + radius_end]]])
    vertices = start + local @ np.stack([x, y, z])
    num_rings = len(profile)
    top_pole = 1 + num_rings * segments
    faces = []
    for s in range(segments):
        t = (s + 1) % segments
        faces.append((0, 1 + t, 1 + s))
        for r in range(num_rings - 1):
            a, b = 1 + r * segments + s, 1 + r * segments + t
            c, d = a + segments, b + segments
            faces += [(a, b, d), (a, d, c)]
        last = 1 + (num_rings - 1) * segments
        faces.append((last + s, last + t, top_pole))
    return vertices, np.asarray(faces, np.int64)


def _bone_surface(skeleton: Skeleton, b: int, segments: int) -> tuple[np.ndarray, np.ndarray]:
    """Capsules from bone b's joint to its tip and to each child's joint (duplicates and stubs dropped)."""
    targets = [skeleton.tips[b]] + [skeleton.offsets[c] for c in skeleton.children(b)]
    kept: list[np.ndarray] = []
    for target in targets:
        if np.linalg.norm(target) >= _MIN_SEGMENT_MM and all(np.linalg.norm(target - k) > 1e-6 for k in kept):
            kept.append(np.asarray(target, np.float64))
    vertices, faces, count = [], [], 0
    for target in kept:
        r0, r1 = bone_radii(skeleton.names[b], float(np.linalg.norm(target)))
        v, f = tapered_capsule(np.zeros(3), target, r0, r1, segments)
        vertices.append(v)
        faces.append(f + count)
        count += len(v)
    if not vertices:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    return np.concatenate(vertices), np.concatenate(faces)


def human_description(
    skeleton: Skeleton,
    dofs: Mapping[str, Sequence[str]] | str = PAPER_DOFS,
    name: str = "human",
    segments: int = 16,
) -> RobotDescription:
    """The body model of a skeleton as links and joints (write it with `write_urdf`).

    Args:
        skeleton: from `read_asf` or `read_bvh` (non-root bones may only have rotation DoF).
        dofs: `{bone: ("rx", ...)}` the rotation DoF to keep, or "all" for every rotation DoF of every
            non-root bone. The root is always free (its pose is the model's root pose).
        name: the robot name.
        segments: vertices around each capsule.

    Raises:
        ValueError: naming a bone the skeleton lacks or a DoF the bone does not have.
    """
    if isinstance(dofs, str):
        if dofs != "all":
            raise ValueError(f"dofs must be a mapping or 'all', got {dofs!r}")
        dofs = {bone: skeleton.dofs[b] for b, bone in enumerate(skeleton.names) if b > 0}
    for bone, kept in dofs.items():
        b = skeleton.index(bone)
        if b == 0:
            raise ValueError(f"dofs: the root {bone!r} is always free (its pose is the root pose); leave it out")
        for dof in kept:
            if dof not in skeleton.dofs[b] or dof not in ("rx", "ry", "rz"):
                raise ValueError(f"dofs: bone {bone!r} has no rotation DoF {dof!r} (its DoF: {list(skeleton.dofs[b])})")
    for b in range(1, skeleton.num_bones):
        if any(d.startswith("t") for d in skeleton.dofs[b]):
            raise ValueError(
                f"bone {skeleton.names[b]!r} has a translation DoF; the body model rotates non-root bones only"
            )
    limits = dict(zip(skeleton.dof_names, skeleton.limits))
    links = [RobotLink(skeleton.names[0], *_bone_surface(skeleton, 0, segments))]
    joints = []
    for b in range(1, skeleton.num_bones):
        bone, parent = skeleton.names[b], skeleton.names[skeleton.parents[b]]
        kept = set(dofs.get(bone, ()))
        chain = [a for a in skeleton.rotation_orders[b] if f"r{a}" in kept]  # product order
        origin = np.eye(4)
        origin[:3, 3] = skeleton.offsets[b]
        if not chain:
            joints.append(RobotJoint(f"{bone}_fixed", "fixed", parent, bone, origin, np.array([1.0, 0.0, 0.0])))
        for k, a in enumerate(chain):
            child = bone if k == len(chain) - 1 else f"{bone}_r{a}_link"
            if child != bone:
                links.append(RobotLink(child, np.zeros((0, 3)), np.zeros((0, 3), np.int64)))
            lower, upper = limits[f"{bone}_r{a}"]
            joints.append(
                RobotJoint(
                    name=f"{bone}_r{a}",
                    type="revolute",
                    parent=parent,
                    child=child,
                    T_parent_joint=origin if k == 0 else np.eye(4),
                    axis=skeleton.axes[b][:, "xyz".index(a)].copy(),
                    lower=float(lower),
                    upper=float(upper),
                )
            )
            parent = child
        links.append(RobotLink(bone, *_bone_surface(skeleton, b, segments)))
    return RobotDescription(name=name, links=tuple(links), joints=tuple(joints))


def human_joint_values(skeleton: Skeleton, motion: Motion, joint_names: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    """Root poses and joint angles of a body model (from `human_description`) for a mocap motion.

    Forward kinematics of the model at these values puts each bone's joint where
    `joint_positions(skeleton, locked_motion(skeleton, motion, joint_names).values)` puts it.

    Args:
        skeleton: the skeleton the model was built from.
        motion: its motion (F frames).
        joint_names: (J,) the model's joints, `<bone>_<dof>` (e.g. `ArticulatedModel.joint_names`).

    Returns:
        T_world_root (F, 4, 4) in mm (rotation and position of the root in the mocap world frame) and
        theta (F, J) radians.

    Raises:
        ValueError: naming a joint that is not a rotation DoF of the motion.
    """
    if tuple(motion.names) != skeleton.dof_names:
        raise ValueError("motion.names must equal skeleton.dof_names (the motion of this skeleton)")
    columns = []
    for joint in joint_names:
        if joint not in motion.names or joint.rsplit("_", 1)[-1] not in ("rx", "ry", "rz"):
            raise ValueError(f"joint {joint!r} is not a rotation DoF <bone>_<dof> of the motion")
        if motion.names.index(joint) < len(skeleton.dofs[0]):
            raise ValueError(f"joint {joint!r}: the root's DoF are the root pose, not joints")
        columns.append(motion.names.index(joint))
    root_dofs = len(skeleton.dofs[0])
    T_world_root = bone_transforms(_root_only(skeleton), motion.values[:, :root_dofs])[:, 0]
    return T_world_root, motion.values[:, columns].copy()


def _root_only(skeleton: Skeleton) -> Skeleton:
    """The skeleton cut down to its root (the root pose needs no other bone)."""
    return Skeleton(
        names=skeleton.names[:1],
        parents=skeleton.parents[:1],
        offsets=skeleton.offsets[:1],
        tips=skeleton.tips[:1],
        axes=skeleton.axes[:1],
        dofs=skeleton.dofs[:1],
        rotation_orders=skeleton.rotation_orders[:1],
        limits=skeleton.limits[: len(skeleton.dofs[0])],
        length_unit_mm=skeleton.length_unit_mm,
    )


def locked_motion(skeleton: Skeleton, motion: Motion, joint_names: Sequence[str]) -> Motion:
    """The motion with every DoF that is neither the root's nor in `joint_names` set to 0: what a body
    model with those joints follows exactly."""
    if tuple(motion.names) != skeleton.dof_names:
        raise ValueError("motion.names must equal skeleton.dof_names (the motion of this skeleton)")
    root_dofs = len(skeleton.dofs[0])
    keep = np.array([i < root_dofs or n in set(joint_names) for i, n in enumerate(motion.names)])
    return Motion(motion.names, np.where(keep, motion.values, 0.0), motion.frame_rate)
