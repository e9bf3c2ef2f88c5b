"""URDF models (robots, and human bodies built from mocap skeletons) as jaxtrack kinematic trees.

    read_urdf(path)  ->  ArticulatedModel(mesh, model, joint_names, lower, upper, ...)    (mm, radians)
    write_urdf(model or RobotDescription, path)  ->  path.urdf + one STL per link beside it

The XML is parsed by `yourdfpy` (a maintained, dependency-light URDF parser whose dataclasses keep every
element: origins, mesh scale, limits, mimic). Its scene graph is not used here: jaxtrack builds its own
tree so that it can check the file (one parent per link, no cycle, known joint types, non-zero axes)
with errors naming the file and element, and merge fixed links. The writer is our own because yourdfpy
drops `<mimic>` when writing.

Conventions. URDF lengths are metres, jaxtrack's are millimetres: every origin, mesh vertex and
prismatic value is multiplied by 1000 on reading (and divided on writing). Links joined by `fixed`
joints merge into one part; every revolute/continuous/prismatic joint starts a new part, so part p > 0
hangs from joint p − 1 (the order of `chain_model`, parents first, depth first in document order).
Multi-DoF joints are chains of revolute joints through massless links (parts without vertices).
The model frame is the root link's frame at the zero configuration; a link's pose at χ = (ξ, Θ) is

    T_world_link = part_transforms(model, T_world_root, Θ)[link_part[link]] · T_root_link0[link]   (eq. 2)

with `T_root_link0` the link's pose in the root frame at Θ = 0.
"""

from __future__ import annotations

import dataclasses
import os
import pathlib
import re
from collections.abc import Iterable, Mapping, Sequence
from typing import Literal
from xml.etree import ElementTree

import numpy as np
import numpy.typing as npt

from ..geometry import KinematicModel, chain_model
from ..render import Mesh, make_mesh

MOVABLE_TYPES = ("revolute", "continuous", "prismatic")
JOINT_TYPES = (*MOVABLE_TYPES, "fixed")
MM_PER_M = 1000.0
_part_transforms_jit = None


@dataclasses.dataclass(frozen=True, eq=False)
class RobotLink:
    """A link with its surface in its own frame.

    Attributes:
        name: the URDF link name.
        vertices: (V, 3) mm, link frame (visual origins and mesh scales applied); V may be 0.
        faces: (F, 3) int vertex indices (F = 0 for a massless or invisible link).
    """

    name: str
    vertices: np.ndarray
    faces: np.ndarray


@dataclasses.dataclass(frozen=True, eq=False)
class RobotJoint:
    """A URDF joint in jaxtrack units.

    Attributes:
        name, type, parent, child: as in the URDF (type one of `JOINT_TYPES`).
        T_parent_joint: (4, 4) the joint `<origin>` (child frame at zero in the parent frame), mm.
        axis: (3,) unit axis in the joint (= child) frame.
        lower, upper: limits in model units (radians, mm for prismatic); ±inf when absent or continuous.
        mimic: (source joint name, multiplier, offset in URDF units) or None.
    """

    name: str
    type: str
    parent: str
    child: str
    T_parent_joint: np.ndarray
    axis: np.ndarray
    lower: float = -np.inf
    upper: float = np.inf
    mimic: tuple[str, float, float] | None = None


@dataclasses.dataclass(frozen=True, eq=False)
class RobotDescription:
    """A kinematic tree of links and joints, lengths in mm (what a URDF file says, read or to write)."""

    name: str
    links: tuple[RobotLink, ...]
    joints: tuple[RobotJoint, ...]


@dataclasses.dataclass(frozen=True, eq=False)
class ArticulatedModel:
    """A URDF model ready for rendering and tracking (host-side container; its `mesh` and `model` are
    the device pytrees).

    Attributes:
        name: the robot name.
        mesh: surface of all links at the zero configuration in the root frame (mm), `vertex_part` set.
        model: the kinematic tree (J movable joints, P = J + 1 parts), mm.
        joint_names: (J,) movable joints in the model's joint order.
        joint_types: (J,) "revolute", "continuous" or "prismatic".
        lower, upper: (J,) limits in model units (radians, mm); ±inf where the URDF sets none.
        joint_scale: (J,) model units per URDF unit (1 for angles, 1000 for prismatic metres).
        mimic: (J,) None or (source joint index, multiplier, offset in URDF units).
        part_names: (P,) the first link of each part (the root link, then each joint's child link).
        link_part: link name -> part index (merged fixed links share their parent's part).
        T_root_link0: link name -> (4, 4) the link's pose in the root frame at Θ = 0 (mm).
        description: the links and joints as read (for `write_urdf`).
    """

    name: str
    mesh: Mesh
    model: KinematicModel
    joint_names: tuple[str, ...]
    joint_types: tuple[str, ...]
    lower: np.ndarray
    upper: np.ndarray
    joint_scale: np.ndarray
    mimic: tuple[tuple[int, float, float] | None, ...]
    part_names: tuple[str, ...]
    link_part: Mapping[str, int]
    T_root_link0: Mapping[str, np.ndarray]
    description: RobotDescription

    @property
    def root_link(self) -> str:
        return self.part_names[0]

    @property
    def num_joints(self) -> int:
        return len(self.joint_names)

    def joint_vector(self, values: Mapping[str, float] | None = None, units: Literal["urdf", "model"] = "urdf"):
        """(J,) Θ in model units from `{joint name: value}`.

        Joints not named are 0, except mimic joints, which follow their source joint
        (θ = multiplier · θ_source + offset, in URDF units) unless named themselves.

        Args:
            values: joint values, radians and metres (`units="urdf"`) or radians and mm (`"model"`).

        Raises:
            ValueError: naming a joint the model lacks, or a non-finite value.
        """
        values = {} if values is None else dict(values)
        unknown = sorted(set(values) - set(self.joint_names))
        if unknown:
            raise ValueError(f"joint(s) {unknown} not in model {self.name!r} (its joints: {list(self.joint_names)})")
        scale = self.joint_scale if units == "model" else np.ones(self.num_joints)
        if units not in ("urdf", "model"):
            raise ValueError(f"units must be 'urdf' or 'model', got {units!r}")
        urdf = np.zeros(self.num_joints)
        for j, name in enumerate(self.joint_names):
            if name in values:
                value = float(values[name])
                if not np.isfinite(value):
                    raise ValueError(f"joint {name!r}: value must be finite, got {value}")
                urdf[j] = value / scale[j]
        for j, mimic in enumerate(self.mimic):
            if mimic is not None and self.joint_names[j] not in values:
                source, multiplier, offset = mimic
                urdf[j] = multiplier * urdf[source] + offset
        return urdf * self.joint_scale

    def joint_values(self, theta: npt.ArrayLike, units: Literal["urdf", "model"] = "urdf") -> dict[str, float]:
        """`{joint name: value}` of a (J,) Θ in model units (the inverse of `joint_vector`)."""
        theta = np.asarray(theta, np.float64)
        if theta.shape != (self.num_joints,):
            raise ValueError(f"theta must have shape ({self.num_joints},), got {theta.shape}")
        if units not in ("urdf", "model"):
            raise ValueError(f"units must be 'urdf' or 'model', got {units!r}")
        values = theta / self.joint_scale if units == "urdf" else theta
        return {name: float(v) for name, v in zip(self.joint_names, values)}

    def link_poses(self, theta: npt.ArrayLike, T_world_root: npt.ArrayLike | None = None) -> dict[str, np.ndarray]:
        """Host-side forward kinematics: `{link: (4, 4) T_world_link}` (mm) at Θ (model units), eq. (2)."""
        import jax
        import jax.numpy as jnp

        from ..geometry import part_transforms

        global _part_transforms_jit
        if _part_transforms_jit is None:  # one compilation per model shape instead of op-by-op dispatch
            _part_transforms_jit = jax.jit(part_transforms)
        T_world_root = np.eye(4) if T_world_root is None else np.asarray(T_world_root, np.float64)
        theta = np.asarray(theta, np.float64)
        if theta.shape != (self.num_joints,):
            raise ValueError(f"theta must have shape ({self.num_joints},), got {theta.shape}")
        dtype = self.model.joint_twists.dtype
        parts = np.asarray(
            _part_transforms_jit(self.model, jnp.asarray(T_world_root, dtype), jnp.asarray(theta, dtype))
        )
        return {link: parts[p] @ self.T_root_link0[link] for link, p in self.link_part.items()}


# --------------------------------------------------------------------------------------------- reading


def read_urdf(
    path: str | os.PathLike,
    package_dirs: Iterable[str | os.PathLike] = (),
    geometry: Literal["visual", "collision"] = "visual",
    dtype: npt.DTypeLike = np.float32,
) -> ArticulatedModel:
    """Read a URDF file into an `ArticulatedModel` (mm, radians).

    Args:
        path: the .urdf file.
        package_dirs: folders holding ROS packages: `package://PKG/REST` is looked up as `DIR/PKG/REST`
            in these, then in every ancestor folder of the URDF (and as `ANCESTOR/REST` where the
            ancestor is named PKG). Relative mesh paths are relative to the URDF's folder.
        geometry: the surface to use, the links' `<visual>` or `<collision>` elements (meshes, boxes,
            cylinders, spheres).
        dtype: float dtype of the mesh and model arrays.

    Raises:
        ValueError: naming the file and the element: unreadable XML, a missing or unreadable mesh, a
            cycle, a link with two parents, several roots, an unknown joint type, a zero axis,
            lower > upper, a mimic of an unknown joint.
    """
    description = read_robot_description(path, package_dirs, geometry)
    return articulated_model(description, dtype=dtype, source=str(path))


def read_robot_description(
    path: str | os.PathLike,
    package_dirs: Iterable[str | os.PathLike] = (),
    geometry: Literal["visual", "collision"] = "visual",
) -> RobotDescription:
    """The links (with their surfaces loaded, mm) and joints of a URDF file; see `read_urdf`."""
    import yourdfpy

    path = pathlib.Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: URDF file not found")
    if geometry not in ("visual", "collision"):
        raise ValueError(f"geometry must be 'visual' or 'collision', got {geometry!r}")
    try:
        ElementTree.parse(path)  # yourdfpy silently "recovers" broken XML; refuse it instead
        robot = yourdfpy.URDF.load(
            str(path), build_scene_graph=False, build_collision_scene_graph=False, load_meshes=False
        ).robot
    except Exception as e:  # lxml / ElementTree / yourdfpy raise many kinds
        raise ValueError(f"{path}: cannot parse URDF ({type(e).__name__}: {e})") from e
    search = [pathlib.Path(d) for d in package_dirs]
    links = tuple(RobotLink(link.name, *_link_surface(link, geometry, path, search)) for link in robot.links)
    joints = tuple(_joint_from_urdf(joint, path) for joint in robot.joints)
    return RobotDescription(name=str(robot.name), links=links, joints=joints)


def _joint_from_urdf(joint, path: pathlib.Path) -> RobotJoint:
    where = f"{path}: joint {joint.name!r}"
    if joint.type not in JOINT_TYPES:
        kind = "unsupported" if joint.type in ("floating", "planar") else "unknown"
        raise ValueError(f"{where} has {kind} type {joint.type!r} (jaxtrack reads {', '.join(JOINT_TYPES)})")
    origin = np.eye(4) if joint.origin is None else np.array(joint.origin, np.float64)
    origin[:3, 3] *= MM_PER_M
    axis = np.array([1.0, 0.0, 0.0] if joint.axis is None else joint.axis, np.float64)
    norm = np.linalg.norm(axis)
    if joint.type != "fixed" and (axis.shape != (3,) or not np.isfinite(norm) or norm < 1e-9):
        raise ValueError(f"{where} has a zero or malformed <axis xyz> {axis.tolist()}")
    axis = axis / norm if norm > 0 else axis
    lower, upper = -np.inf, np.inf
    if joint.type in ("revolute", "prismatic") and joint.limit is not None:
        scale = MM_PER_M if joint.type == "prismatic" else 1.0
        lower = -np.inf if joint.limit.lower is None else float(joint.limit.lower) * scale
        upper = np.inf if joint.limit.upper is None else float(joint.limit.upper) * scale
        if lower > upper:
            raise ValueError(f"{where}: <limit> lower {joint.limit.lower} > upper {joint.limit.upper}")
    mimic = None
    if joint.mimic is not None and joint.type != "fixed":
        multiplier = 1.0 if joint.mimic.multiplier is None else float(joint.mimic.multiplier)
        offset = 0.0 if joint.mimic.offset is None else float(joint.mimic.offset)
        mimic = (str(joint.mimic.joint), multiplier, offset)
    return RobotJoint(
        name=str(joint.name),
        type=str(joint.type),
        parent=str(joint.parent),
        child=str(joint.child),
        T_parent_joint=origin,
        axis=axis,
        lower=lower,
        upper=upper,
        mimic=mimic,
    )


def _link_surface(link, geometry: str, urdf_path: pathlib.Path, search: Sequence[pathlib.Path]):
    """(V, 3) mm vertices and (F, 3) faces of a link's visual or collision elements, in the link frame."""
    import trimesh

    from ._meshes import load_trimesh

    pieces = []
    for k, element in enumerate(link.visuals if geometry == "visual" else link.collisions):
        where = f"{urdf_path}: link {link.name!r}, {geometry} {k}"
        shape = element.geometry
        if shape is None:
            continue
        if shape.mesh is not None:
            filename = _resolve_filename(shape.mesh.filename, urdf_path, search, where)
            try:
                tm = load_trimesh(filename)
            except (OSError, ValueError) as e:
                raise ValueError(f"{where}: {e}") from e
            scale = np.broadcast_to(np.asarray(1.0 if shape.mesh.scale is None else shape.mesh.scale, float), (3,))
            vertices, faces = np.asarray(tm.vertices) * scale, np.asarray(tm.faces)
            if np.prod(scale) < 0:  # a mirroring scale turns the triangles inside out
                faces = faces[:, ::-1]
        elif shape.box is not None:
            tm = trimesh.creation.box(extents=np.asarray(shape.box.size, float))
            vertices, faces = np.asarray(tm.vertices), np.asarray(tm.faces)
        elif shape.cylinder is not None:  # URDF cylinders lie along z, centred on the origin, like trimesh's
            tm = trimesh.creation.cylinder(radius=shape.cylinder.radius, height=shape.cylinder.length, sections=32)
            vertices, faces = np.asarray(tm.vertices), np.asarray(tm.faces)
        elif shape.sphere is not None:
            tm = trimesh.creation.icosphere(subdivisions=2, radius=shape.sphere.radius)
            vertices, faces = np.asarray(tm.vertices), np.asarray(tm.faces)
        else:
            continue
        origin = np.eye(4) if element.origin is None else np.asarray(element.origin, np.float64)
        vertices = (vertices @ origin[:3, :3].T + origin[:3, 3]) * MM_PER_M
        pieces.append(_merged(vertices, faces))
    if not pieces:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    offsets = np.cumsum([0] + [len(v) for v, _ in pieces[:-1]])
    return (
        np.concatenate([v for v, _ in pieces]),
        np.concatenate([f + o for (_, f), o in zip(pieces, offsets)]),
    )


def _merged(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Identical vertices merged (STL and COLLADA repeat them per face or per normal); face order kept."""
    unique, inverse = np.unique(vertices, axis=0, return_inverse=True)
    return unique, inverse.reshape(-1)[faces]


def _resolve_filename(filename: str, urdf_path: pathlib.Path, search: Sequence[pathlib.Path], where: str):
    urdf_dir = urdf_path.resolve().parent
    if filename.startswith("package://"):
        package, _, rest = filename[len("package://") :].partition("/")
        candidates = [d / package / rest for d in search]
        for ancestor in [urdf_dir, *urdf_dir.parents]:
            candidates.append(ancestor / package / rest)
            if ancestor.name == package:
                candidates.append(ancestor / rest)
    elif filename.startswith("file://"):
        candidates = [pathlib.Path(filename[len("file://") :])]
    else:
        candidates = [urdf_dir / filename]
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    tried = ", ".join(str(c) for c in candidates[:4]) + (", ..." if len(candidates) > 4 else "")
    raise ValueError(f"{where}: mesh file {filename!r} not found (looked for {tried})")


# --------------------------------------------------------------------------------------------- building


def articulated_model(
    description: RobotDescription, dtype: npt.DTypeLike = np.float32, source: str | None = None
) -> ArticulatedModel:
    """Check a `RobotDescription` and build its mesh and kinematic tree (fixed links merged).

    Raises:
        ValueError: naming `source` (the file) and the element: duplicate names, a joint naming a
            missing link, a link with two parents, a cycle, several roots, a mimic of an unknown or
            fixed joint.
    """
    where = source or description.name
    links = {link.name: link for link in description.links}
    if len(links) != len(description.links):
        raise ValueError(f"{where}: duplicate link names")
    if len({j.name for j in description.joints}) != len(description.joints):
        raise ValueError(f"{where}: duplicate joint names")
    parent_joint: dict[str, RobotJoint] = {}
    children: dict[str, list[RobotJoint]] = {name: [] for name in links}
    for joint in description.joints:
        for role, link in (("parent", joint.parent), ("child", joint.child)):
            if link not in links:
                raise ValueError(f"{where}: joint {joint.name!r} names {role} link {link!r}, which is not defined")
        if joint.type not in JOINT_TYPES:
            raise ValueError(f"{where}: joint {joint.name!r} has unknown type {joint.type!r}")
        if joint.child in parent_joint:
            raise ValueError(
                f"{where}: link {joint.child!r} has two parents (joints {parent_joint[joint.child].name!r} and "
                f"{joint.name!r}); a URDF must be a tree"
            )
        parent_joint[joint.child] = joint
        children[joint.parent].append(joint)
    roots = [name for name in links if name not in parent_joint]
    if not roots:
        raise ValueError(f"{where}: no root link (every link has a parent): the joints form a cycle")
    if len(roots) > 1:
        raise ValueError(f"{where}: several root links {roots}: the links must form one tree")

    # Depth first from the root, children in document order (preorder); a movable joint starts a new
    # part, numbered when visited, so every part's parent part has a smaller index (chain_model's order).
    part_parents, part_names, movable = [-1], [roots[0]], []
    link_part, T_root_link0 = {roots[0]: 0}, {roots[0]: np.eye(4)}
    stack = list(reversed(children[roots[0]]))
    while stack:
        joint = stack.pop()
        T_root_link0[joint.child] = T_root_link0[joint.parent] @ joint.T_parent_joint
        if joint.type == "fixed":
            link_part[joint.child] = link_part[joint.parent]
        else:
            link_part[joint.child] = len(part_names)
            part_parents.append(link_part[joint.parent])
            part_names.append(joint.child)
            movable.append(joint)
        stack.extend(reversed(children[joint.child]))  # reversed: popped in document order
    unreached = [name for name in links if name not in link_part]
    if unreached:
        raise ValueError(
            f"{where}: links {unreached} are not reachable from root {roots[0]!r}: the joints form a cycle"
        )

    joint_names = tuple(j.name for j in movable)
    mimic = []
    for joint in movable:
        if joint.mimic is None:
            mimic.append(None)
            continue
        source_name, multiplier, offset = joint.mimic
        if source_name not in joint_names:
            raise ValueError(f"{where}: joint {joint.name!r} mimics {source_name!r}, which is not a movable joint")
        mimic.append((joint_names.index(source_name), multiplier, offset))

    axes, points = [], []
    for joint in movable:
        T_root_child = T_root_link0[joint.child]
        axes.append(T_root_child[:3, :3] @ joint.axis)
        points.append(T_root_child[:3, 3])
    model = chain_model(
        part_parents,
        axes,
        points,
        dtype=dtype,
        joint_types=["prismatic" if j.type == "prismatic" else "revolute" for j in movable],
    )

    vertices, faces, vertex_part = [], [], []
    count = 0
    for name, link in links.items():
        if len(link.faces) == 0:
            continue
        T = T_root_link0[name]
        vertices.append(link.vertices @ T[:3, :3].T + T[:3, 3])
        faces.append(np.asarray(link.faces) + count)
        vertex_part.append(np.full(len(link.vertices), link_part[name]))
        count += len(link.vertices)
    if not vertices:
        raise ValueError(f"{where}: no link has a surface (no visual or collision geometry)")
    mesh = make_mesh(
        np.concatenate(vertices), np.concatenate(faces), np.concatenate(vertex_part), dtype=dtype, name=where
    )
    return ArticulatedModel(
        name=description.name,
        mesh=mesh,
        model=model,
        joint_names=joint_names,
        joint_types=tuple(j.type for j in movable),
        lower=np.array([j.lower for j in movable], np.float64),
        upper=np.array([j.upper for j in movable], np.float64),
        joint_scale=np.array([MM_PER_M if j.type == "prismatic" else 1.0 for j in movable]),
        mimic=tuple(mimic),
        part_names=tuple(part_names),
        link_part=link_part,
        T_root_link0=T_root_link0,
        description=description,
    )


# --------------------------------------------------------------------------------------------- writing


def write_urdf(model_description: ArticulatedModel | RobotDescription, path: str | os.PathLike) -> pathlib.Path:
    """Write a URDF (metres) and one binary STL per link with a surface (mm, `scale="0.001 ..."`) in a
    folder `<stem>_meshes/` beside it, referenced relative to the URDF.

    Returns:
        The URDF path.
    """
    import trimesh

    description = (
        model_description.description if isinstance(model_description, ArticulatedModel) else model_description
    )
    if not isinstance(description, RobotDescription):
        raise TypeError(f"model_description must be an ArticulatedModel or RobotDescription, got {type(description)}")
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    mesh_dir = path.parent / f"{path.stem}_meshes"
    robot = ElementTree.Element("robot", name=description.name)
    used: set[str] = set()
    for link in description.links:
        element = ElementTree.SubElement(robot, "link", name=link.name)
        if len(link.faces) == 0:
            continue
        stem = re.sub(r"[^A-Za-z0-9_.-]", "_", link.name)
        while stem in used:
            stem += "_"
        used.add(stem)
        mesh_dir.mkdir(exist_ok=True)
        trimesh.Trimesh(link.vertices, link.faces, process=False).export(mesh_dir / f"{stem}.stl")
        visual = ElementTree.SubElement(element, "visual")
        shape = ElementTree.SubElement(visual, "geometry")
        ElementTree.SubElement(shape, "mesh", filename=f"{mesh_dir.name}/{stem}.stl", scale="0.001 0.001 0.001")
    for joint in description.joints:
        element = ElementTree.SubElement(robot, "joint", name=joint.name, type=joint.type)
        ElementTree.SubElement(element, "parent", link=joint.parent)
        ElementTree.SubElement(element, "child", link=joint.child)
        xyz = np.asarray(joint.T_parent_joint[:3, 3]) / MM_PER_M
        ElementTree.SubElement(
            element, "origin", xyz=_floats(xyz), rpy=_floats(rpy_from_rotation(joint.T_parent_joint[:3, :3]))
        )
        if joint.type != "fixed":
            ElementTree.SubElement(element, "axis", xyz=_floats(joint.axis))
        if joint.type in ("revolute", "prismatic"):
            scale = MM_PER_M if joint.type == "prismatic" else 1.0
            limit = {"effort": "0", "velocity": "0"}  # required attributes; jaxtrack has no dynamics
            if np.isfinite(joint.lower):
                limit["lower"] = _floats([joint.lower / scale])
            if np.isfinite(joint.upper):
                limit["upper"] = _floats([joint.upper / scale])
            ElementTree.SubElement(element, "limit", **limit)
        if joint.mimic is not None:
            source, multiplier, offset = joint.mimic
            ElementTree.SubElement(
                element, "mimic", joint=source, multiplier=_floats([multiplier]), offset=_floats([offset])
            )
    ElementTree.indent(robot)
    ElementTree.ElementTree(robot).write(path, encoding="utf-8", xml_declaration=True)
    return path


def _floats(values: Iterable[float]) -> str:
    return " ".join(f"{float(v):.17g}" for v in values)


def rpy_from_rotation(rotation: npt.ArrayLike) -> np.ndarray:
    """URDF roll, pitch, yaw of a rotation R = Rz(yaw) · Ry(pitch) · Rx(roll) (fixed axes x, y, z)."""
    r = np.asarray(rotation, np.float64)
    pitch = np.arcsin(np.clip(-r[2, 0], -1.0, 1.0))
    if np.hypot(r[0, 0], r[1, 0]) > 1e-9:
        roll = np.arctan2(r[2, 1], r[2, 2])
        yaw = np.arctan2(r[1, 0], r[0, 0])
    else:  # gimbal lock (pitch = ±90°): only roll ∓ yaw is defined; put it all in yaw
        roll = 0.0
        yaw = np.arctan2(-r[0, 1], r[1, 1])
    return np.array([roll, pitch, yaw])
