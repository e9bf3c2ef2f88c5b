"""Motion capture: ASF/AMC (Acclaim, as in the CMU database) and BVH skeletons and motions, numpy FK.

    skeleton = read_asf("07-walk.asf"); motion = read_amc("07_05-walk.amc", skeleton)
    skeleton, motion = read_bvh("walk.bvh", length_unit_mm=10.0)        # a BVH in centimetres
    joint_positions(skeleton, motion.values[0])   -> (B, 3) mm, each bone's joint (where it rotates)

One skeleton form for both formats. Bone b hangs from bone parents[b]; at the zero pose its joint sits at
`offsets[b]` from its parent's joint (world axes, mm) and the bone reaches `tips[b]` further. Its local
frame has orientation C_b (ASF `axis`, identity for BVH) and its degrees of freedom rotate about that
frame's axes:

    M_b = Π_{a in rotation_orders[b]} R_a(θ_{b,a})        (product left to right)
    L_b = L_parent · C_b · M_b · C_b⁻¹                      (ASF: M = Cinv·R·C in the row-vector notation)
    x_b = x_parent + L_parent · (offsets[b] + t_b)          (t_b: translation DoF, the root's only)

with L_root's parent term the identity. The files say the order differently: an ASF `dof rx ry rz`
line (and `axis ... XYZ`) lists the rotations in the order they act on a vector, so the product is
Rz·Ry·Rx (`rotation_orders = "zyx"`), as in the CMU reference player; a BVH `CHANNELS ... Zrotation
Xrotation Yrotation` line lists them in product order, Rz·Rx·Ry (`"zxy"`). An ASF bone's own rotation
turns its own segment (its `direction × length` becomes the `tips` of the bone and the `offsets` of its
children); a BVH joint's rotation turns its children's offsets; both are the formula above.

Units: angles in radians, lengths in mm. ASF lengths are in units of `25.4 / length` mm where `length`
is the `:units length` value (CMU: length 0.45, so 1 unit = 56.44 mm); AMC root translations use the
same unit. BVH files carry no unit: `read_bvh(length_unit_mm=...)` says it.
"""

from __future__ import annotations

import dataclasses
import os
import pathlib
import re
from collections.abc import Iterable, Sequence

import numpy as np
import numpy.typing as npt

_AXES = "xyz"
_TRANSLATIONS = ("tx", "ty", "tz")
_ROTATIONS = ("rx", "ry", "rz")
_BVH_CHANNELS = {
    "xposition": "tx",
    "yposition": "ty",
    "zposition": "tz",
    "xrotation": "rx",
    "yrotation": "ry",
    "zrotation": "rz",
}


@dataclasses.dataclass(frozen=True, eq=False)
class Skeleton:
    """A tree of bones (bone 0 is the root; parents come before children).

    Attributes:
        names: (B,) bone names.
        parents: (B,) int parent bone, -1 for the root.
        offsets: (B, 3) mm, the bone's joint relative to its parent's joint at the zero pose (world axes).
        tips: (B, 3) mm, the bone's far end relative to its joint at the zero pose (ASF direction × length;
            BVH: the End Site, or the only child's offset; zero where undefined).
        axes: (B, 3, 3) C_b, the orientation of the bone's local frame (ASF `axis`), identity for BVH.
        dofs: (B,) per bone its DoF as listed in the file ("tx", "ty", "tz", "rx", "ry", "rz").
        rotation_orders: (B,) the bone's rotation axes in matrix-product order, e.g. "zyx" = Rz·Ry·Rx.
        limits: (D, 2) lower/upper limit of each DoF (radians, mm), ±inf where the file gives none.
        length_unit_mm: mm per length unit of the file (for information; everything here is in mm).
    """

    names: tuple[str, ...]
    parents: np.ndarray
    offsets: np.ndarray
    tips: np.ndarray
    axes: np.ndarray
    dofs: tuple[tuple[str, ...], ...]
    rotation_orders: tuple[str, ...]
    limits: np.ndarray
    length_unit_mm: float = 1.0

    @property
    def num_bones(self) -> int:
        return len(self.names)

    @property
    def dof_names(self) -> tuple[str, ...]:
        """(D,) `<bone>_<dof>`, bones in order, each bone's DoF in file order (the `Motion` columns)."""
        return tuple(f"{bone}_{dof}" for bone, dofs in zip(self.names, self.dofs) for dof in dofs)

    def index(self, bone: str) -> int:
        """Index of a bone by name; ValueError naming it when absent."""
        try:
            return self.names.index(bone)
        except ValueError:
            raise ValueError(f"skeleton has no bone {bone!r}") from None

    def children(self, bone: int) -> list[int]:
        return [int(c) for c in np.flatnonzero(self.parents == bone)]


@dataclasses.dataclass(frozen=True, eq=False)
class Motion:
    """A DoF trajectory.

    Attributes:
        names: (D,) DoF names `<bone>_<dof>` (e.g. `ltibia_rx`, the left knee).
        values: (F, D) per frame: radians for rotations, mm for translations.
        frame_rate: frames per second (CMU AMC: 120).
    """

    names: tuple[str, ...]
    values: np.ndarray
    frame_rate: float

    @property
    def num_frames(self) -> int:
        return self.values.shape[0]

    def column(self, name: str) -> np.ndarray:
        """(F,) values of one DoF; ValueError naming it when absent."""
        if name not in self.names:
            raise ValueError(f"motion has no DoF {name!r}")
        return self.values[:, self.names.index(name)]

    def subsample(self, step: int, start: int = 0) -> Motion:
        """Every `step`-th frame from `start` (120 fps with step 3, 4, 5: 40, 30, 24 fps)."""
        if int(step) != step or step < 1 or int(start) != start or start < 0:
            raise ValueError(f"step must be an integer >= 1 and start >= 0, got step={step}, start={start}")
        return Motion(self.names, self.values[start :: int(step)].copy(), self.frame_rate / step)


# ------------------------------------------------------------------------------------------ rotations


def axis_rotation(axis: str, angle: npt.ArrayLike) -> np.ndarray:
    """(..., 3, 3) rotation by `angle` (radians) about the x, y or z axis (right-handed)."""
    angle = np.asarray(angle, np.float64)
    c, s = np.cos(angle), np.sin(angle)
    i = _AXES.index(axis)
    j, k = (i + 1) % 3, (i + 2) % 3
    rot = np.zeros((*angle.shape, 3, 3))
    rot[..., i, i] = 1.0
    rot[..., j, j], rot[..., j, k] = c, -s
    rot[..., k, j], rot[..., k, k] = s, c
    return rot


def euler_rotation(order: str, angles: npt.ArrayLike) -> np.ndarray:
    """(..., 3, 3) Π_i R_{order[i]}(angles[..., i]), the product left to right (`order` like "zyx")."""
    angles = np.asarray(angles, np.float64)
    rot = np.broadcast_to(np.eye(3), (*angles.shape[:-1], 3, 3))
    for i, axis in enumerate(order):
        rot = rot @ axis_rotation(axis, angles[..., i])
    return rot


def euler_angles(order: str, rotation: npt.ArrayLike) -> np.ndarray:
    """(..., 3) angles a with `euler_rotation(order, a) = rotation` for three distinct axes; the middle
    angle lies in [−π/2, π/2] (at ±π/2 the first angle takes the whole remaining rotation)."""
    if sorted(order) != list(_AXES):
        raise ValueError(f"order must be a permutation of 'xyz', got {order!r}")
    r = np.asarray(rotation, np.float64)
    i, j, k = (_AXES.index(a) for a in order)
    # R = R_i(a) R_j(b) R_k(c): R[i, k] = s·sin b with s = +1 for cyclic (even) orders, −1 otherwise.
    sign = 1.0 if (j - i) % 3 == 1 else -1.0
    b = np.arcsin(np.clip(sign * r[..., i, k], -1.0, 1.0))
    a = np.arctan2(-sign * r[..., j, k], r[..., k, k])
    c = np.arctan2(-sign * r[..., i, j], r[..., i, i])
    locked = np.hypot(r[..., k, k], r[..., j, k]) < 1e-9
    if np.any(locked):  # gimbal lock: c = 0, a from the rows not involving c
        a = np.where(locked, np.arctan2(sign * r[..., k, j], r[..., j, j]), a)
        c = np.where(locked, 0.0, c)
    return np.stack([a, b, c], -1)


# ------------------------------------------------------------------------------------------ kinematics


def bone_transforms(skeleton: Skeleton, values: npt.ArrayLike) -> np.ndarray:
    """(..., B, 4, 4) world transform of each bone's frame: rotation L_b, translation its joint x_b (mm).

    Args:
        skeleton: the skeleton.
        values: (..., D) DoF values in `skeleton.dof_names` order (radians, mm).
    """
    values = np.asarray(values, np.float64)
    num_dofs = len(skeleton.dof_names)
    if values.shape[-1:] != (num_dofs,):
        raise ValueError(f"values must have shape (..., {num_dofs}) (the skeleton's DoF), got {values.shape}")
    batch = values.shape[:-1]
    out = np.zeros((*batch, skeleton.num_bones, 4, 4))
    out[..., 3, 3] = 1.0
    column = 0
    for b in range(skeleton.num_bones):
        named = dict(zip(skeleton.dofs[b], np.moveaxis(values[..., column : column + len(skeleton.dofs[b])], -1, 0)))
        column += len(skeleton.dofs[b])
        zero = np.zeros(batch)
        motion = (
            euler_rotation(
                skeleton.rotation_orders[b],
                np.stack([named.get(f"r{a}", zero) for a in skeleton.rotation_orders[b]], -1),
            )
            if skeleton.rotation_orders[b]
            else np.broadcast_to(np.eye(3), (*batch, 3, 3))
        )
        local = skeleton.axes[b] @ motion @ skeleton.axes[b].T
        shift = skeleton.offsets[b] + np.stack([named.get(t, zero) for t in _TRANSLATIONS], -1)
        p = skeleton.parents[b]
        if p < 0:
            out[..., b, :3, :3] = local
            out[..., b, :3, 3] = shift
        else:
            parent_rot = out[..., p, :3, :3]
            out[..., b, :3, :3] = parent_rot @ local
            out[..., b, :3, 3] = out[..., p, :3, 3] + (parent_rot @ shift[..., None])[..., 0]
    return out


def joint_positions(skeleton: Skeleton, motion_frame: npt.ArrayLike, ends: bool = False) -> np.ndarray:
    """(..., B, 3) mm: each bone's joint (`ends=False`), or its far end x_b + L_b · tips[b] (`ends=True`,
    the ASF bone "coordinate"), for DoF values (..., D) in `skeleton.dof_names` order."""
    transforms = bone_transforms(skeleton, motion_frame)
    if not ends:
        return transforms[..., :3, 3]
    return transforms[..., :3, 3] + (transforms[..., :3, :3] @ skeleton.tips[:, :, None])[..., 0]


# ------------------------------------------------------------------------------------------ ASF / AMC


def read_asf(path: str | os.PathLike, length_unit_mm: float | None = None) -> Skeleton:
    """Read an Acclaim skeleton (.asf).

    Args:
        path: the file.
        length_unit_mm: mm per ASF length unit; None: 25.4 / (`:units length`), the CMU convention
            (inches scaled by `length`; 56.44 mm for CMU's 0.45).

    Raises:
        ValueError: naming the file and the bone or section that is malformed.
    """
    path = pathlib.Path(path)
    sections = _asf_sections(path)
    units = dict(_key_values(sections.get("units", [])))
    if length_unit_mm is None:
        length = float(units.get("length", ["1.0"])[0])
        if not length > 0:
            raise ValueError(f"{path}: :units length must be > 0, got {length}")
        length_unit_mm = 25.4 / length
    if not (np.isfinite(length_unit_mm) and length_unit_mm > 0):
        raise ValueError(f"length_unit_mm must be a finite number > 0, got {length_unit_mm!r}")
    degrees = units.get("angle", ["deg"])[0].lower().startswith("deg")
    to_rad = np.pi / 180.0 if degrees else 1.0

    root = dict(_key_values(sections.get("root", [])))
    try:
        root_dofs = tuple(d.lower() for d in root.get("order", []))
        root_axis_order = root.get("axis", ["XYZ"])[0]
        position = np.array([float(v) for v in root.get("position", ["0", "0", "0"])]) * length_unit_mm
        orientation = np.array([float(v) for v in root.get("orientation", ["0", "0", "0"])]) * to_rad
    except ValueError as e:
        raise ValueError(f"{path}: malformed :root section ({e})") from e
    _check_dofs(root_dofs, path, "root", allow_translation=True)
    bones = {"root": _Bone("root", np.zeros(3), _axis_matrix(orientation, root_axis_order, path, "root"), root_dofs)}
    bones["root"].limits = [(-np.inf, np.inf)] * len(root_dofs)
    bones["root"].offset = position

    for block in _asf_bone_blocks(sections.get("bonedata", []), path):
        bone = _asf_bone(block, path, length_unit_mm, to_rad)
        if bone.name in bones:
            raise ValueError(f"{path}: bone {bone.name!r} is defined twice")
        bones[bone.name] = bone

    children: dict[str, list[str]] = {name: [] for name in bones}
    parent_of: dict[str, str] = {}
    for line in sections.get("hierarchy", []):
        words = line.split()
        if not words or words[0] in ("begin", "end"):
            continue
        for name in words:
            if name not in bones:
                raise ValueError(f"{path}: :hierarchy names bone {name!r}, which :bonedata does not define")
        for child in words[1:]:
            if child in parent_of:
                raise ValueError(f"{path}: bone {child!r} has two parents ({parent_of[child]!r}, {words[0]!r})")
            parent_of[child] = words[0]
            children[words[0]].append(child)
    order, stack = [], ["root"]
    while stack:  # depth first, children in file order
        name = stack.pop()
        order.append(name)
        stack.extend(reversed(children[name]))
    missing = [name for name in bones if name not in order]
    if missing:
        raise ValueError(f"{path}: bones {missing} are not connected to the root in :hierarchy (or form a cycle)")

    index = {name: i for i, name in enumerate(order)}
    parents = np.array([-1] + [index[parent_of[name]] for name in order[1:]], np.int64)
    tips = np.stack([bones[name].tip for name in order])
    # An ASF bone starts where its parent ends; the root's "offset" is its `position`.
    offsets = np.stack([bones["root"].offset] + [bones[parent_of[name]].tip for name in order[1:]])
    return Skeleton(
        names=tuple(order),
        parents=parents,
        offsets=offsets,
        tips=tips,
        axes=np.stack([bones[name].axis for name in order]),
        dofs=tuple(bones[name].dofs for name in order),
        rotation_orders=tuple("".join(d[1] for d in reversed(bones[name].dofs) if d in _ROTATIONS) for name in order),
        limits=np.array([lim for name in order for lim in bones[name].limits], np.float64).reshape(-1, 2),
        length_unit_mm=float(length_unit_mm),
    )


@dataclasses.dataclass
class _Bone:
    name: str
    tip: np.ndarray
    axis: np.ndarray
    dofs: tuple[str, ...]
    limits: list = dataclasses.field(default_factory=list)
    offset: np.ndarray | None = None


def _asf_sections(path: pathlib.Path) -> dict[str, list[str]]:
    if not path.is_file():
        raise ValueError(f"{path}: ASF file not found")
    sections: dict[str, list[str]] = {}
    current = None
    for raw in path.read_text(errors="replace").splitlines():
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        if line.startswith(":"):
            keyword, _, rest = line[1:].partition(" ")
            current = keyword.lower()
            sections[current] = [rest.strip()] if rest.strip() else []
        elif current is not None:
            sections[current].append(line)
    if "bonedata" not in sections or "hierarchy" not in sections:
        raise ValueError(f"{path}: not an ASF file (no :bonedata or :hierarchy section)")
    return sections


def _key_values(lines: Iterable[str]) -> list[tuple[str, list[str]]]:
    out = []
    for line in lines:
        words = line.split()
        if words:
            out.append((words[0].lower(), words[1:]))
    return out


def _asf_bone_blocks(lines: Sequence[str], path: pathlib.Path) -> list[list[str]]:
    blocks, current = [], None
    for line in lines:
        word = line.split()[0].lower()
        if word == "begin":
            current = []
        elif word == "end":
            if current is None:
                raise ValueError(f"{path}: :bonedata has 'end' without 'begin'")
            blocks.append(current)
            current = None
        elif current is not None:
            current.append(line)
    if current is not None:
        raise ValueError(f"{path}: :bonedata block without 'end'")
    return blocks


def _asf_bone(block: list[str], path: pathlib.Path, length_unit_mm: float, to_rad: float) -> _Bone:
    fields: dict[str, list[str]] = {}
    limit_words: list[str] = []
    in_limits = False
    for line in block:
        words = line.split()
        if words[0].startswith("("):
            if not in_limits:
                raise ValueError(f"{path}: limits line {line!r} outside a 'limits' field")
            limit_words += words
            continue
        in_limits = words[0].lower() == "limits"
        if in_limits:
            limit_words += words[1:]
        else:
            fields[words[0].lower()] = words[1:]
    name = (fields.get("name") or ["?"])[0]
    where = f"{path}: bone {name!r}"
    try:
        direction = np.array([float(v) for v in fields["direction"]])
        length = float(fields["length"][0])
        axis_words = fields["axis"]
        axis_angles = np.array([float(v) for v in axis_words[:3]]) * to_rad
    except (KeyError, IndexError, ValueError) as e:
        raise ValueError(f"{where}: missing or malformed direction/length/axis ({e})") from e
    if direction.shape != (3,) or not np.all(np.isfinite(direction)) or not np.isfinite(length):
        raise ValueError(f"{where}: direction must be 3 finite numbers and length finite")
    norm = np.linalg.norm(direction)
    tip = direction / norm * length * length_unit_mm if norm > 0 else np.zeros(3)
    dofs = tuple(d.lower() for d in fields.get("dof", []))
    _check_dofs(dofs, path, name, allow_translation=False)
    numbers = [float(w) for w in " ".join(limit_words).replace("(", " ").replace(")", " ").split()]
    if limit_words and len(numbers) != 2 * len(dofs):
        raise ValueError(f"{where}: {len(numbers) // 2} limits for {len(dofs)} DoF")
    limits = [(numbers[2 * i] * to_rad, numbers[2 * i + 1] * to_rad) for i in range(len(numbers) // 2)]
    limits = limits or [(-np.inf, np.inf)] * len(dofs)
    axis = _axis_matrix(axis_angles, axis_words[3] if len(axis_words) > 3 else "XYZ", path, name)
    return _Bone(name=name, tip=tip, axis=axis, dofs=dofs, limits=limits)


def _axis_matrix(angles: np.ndarray, order: str, path: pathlib.Path, bone: str) -> np.ndarray:
    order = order.lower()
    if sorted(order) != list(_AXES) or angles.shape != (3,):
        raise ValueError(f"{path}: bone {bone!r}: axis must be 3 angles and an order like XYZ, got {order!r}")
    # "XYZ" lists the rotations in the order they act: C = Rz(az) · Ry(ay) · Rx(ax).
    return euler_rotation(order[::-1], angles[[_AXES.index(a) for a in order[::-1]]])


def _check_dofs(dofs: Sequence[str], path: pathlib.Path, bone: str, allow_translation: bool) -> None:
    allowed = (_TRANSLATIONS if allow_translation else ()) + _ROTATIONS
    for dof in dofs:
        if dof not in allowed:
            raise ValueError(f"{path}: bone {bone!r}: DoF {dof!r} is not supported (allowed: {', '.join(allowed)})")
    if len(set(dofs)) != len(dofs):
        raise ValueError(f"{path}: bone {bone!r}: repeated DoF in {list(dofs)}")


def read_amc(path: str | os.PathLike, skeleton: Skeleton, frame_rate: float = 120.0) -> Motion:
    """Read an Acclaim motion (.amc) for `skeleton`: (F, D) values in `skeleton.dof_names` order.

    Angles are read as degrees unless the file says `:RADIANS`; the root translation is converted with
    `skeleton.length_unit_mm`. A bone missing from a frame keeps 0 for its DoF.

    Raises:
        ValueError: naming the file and line of an unknown bone, a wrong number of values, or a
            non-number.
    """
    path = pathlib.Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: AMC file not found")
    columns, start = {}, 0
    for bone, dofs in zip(skeleton.names, skeleton.dofs):
        columns[bone] = (start, dofs)
        start += len(dofs)
    to_rad = np.pi / 180.0
    frames: list[np.ndarray] = []
    current = None
    for number, raw in enumerate(path.read_text(errors="replace").splitlines(), 1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        if line.startswith(":"):
            if line.upper().startswith(":RADIANS"):
                to_rad = 1.0
            continue
        words = line.split()
        if len(words) == 1 and re.fullmatch(r"\d+", words[0]):
            current = np.zeros(start)
            frames.append(current)
            continue
        where = f"{path}:{number}"
        if current is None:
            raise ValueError(f"{where}: bone values before the first frame number")
        bone = words[0]
        if bone not in columns:
            raise ValueError(f"{where}: bone {bone!r} is not in the skeleton")
        first, dofs = columns[bone]
        if len(words) - 1 != len(dofs):
            raise ValueError(f"{where}: bone {bone!r} has {len(words) - 1} values, its DoF are {list(dofs)}")
        try:
            values = np.array([float(w) for w in words[1:]])
        except ValueError as e:
            raise ValueError(f"{where}: {e}") from e
        scale = np.array([skeleton.length_unit_mm if d in _TRANSLATIONS else to_rad for d in dofs])
        current[first : first + len(dofs)] = values * scale
    if not frames:
        raise ValueError(f"{path}: no frames")
    return Motion(skeleton.dof_names, np.stack(frames), float(frame_rate))


# ------------------------------------------------------------------------------------------ BVH


def read_bvh(path: str | os.PathLike, length_unit_mm: float = 1.0) -> tuple[Skeleton, Motion]:
    """Read a Biovision hierarchy (.bvh): its skeleton and motion (angles to radians, lengths × unit).

    Raises:
        ValueError: naming the file and what is malformed (unbalanced braces, unknown channel, a frame
            with the wrong number of values).
    """
    path = pathlib.Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: BVH file not found")
    if not (np.isfinite(length_unit_mm) and length_unit_mm > 0):
        raise ValueError(f"length_unit_mm must be a finite number > 0, got {length_unit_mm!r}")
    text = path.read_text(errors="replace")
    head, sep, motion_text = text.partition("MOTION")
    if not sep or "HIERARCHY" not in head:
        raise ValueError(f"{path}: not a BVH file (no HIERARCHY or MOTION section)")
    tokens = head.split("HIERARCHY", 1)[1].split()
    names, parents, offsets, tips, dofs, orders = [], [], [], [], [], []
    stack: list[int] = []  # open joints; -2 marks an End Site
    pos = 0

    def take(count: int) -> list[str]:
        nonlocal pos
        if pos + count > len(tokens):
            raise ValueError(f"{path}: hierarchy ends early")
        pos += count
        return tokens[pos - count : pos]

    try:
        while pos < len(tokens):
            word = take(1)[0]
            if word in ("ROOT", "JOINT"):
                if (word == "ROOT") != (not stack) or (stack and stack[-1] == -2):
                    raise ValueError(f"{path}: {word} {tokens[pos]!r} in the wrong place")
                names.append(take(1)[0])
                parents.append(stack[-1] if stack else -1)
                offsets.append(np.zeros(3))
                tips.append(None)
                dofs.append(())
                orders.append("")
                if take(1) != ["{"]:
                    raise ValueError(f"{path}: '{{' expected after {word} {names[-1]!r}")
                stack.append(len(names) - 1)
            elif word == "End":
                take(1)  # "Site"
                if take(1) != ["{"] or not stack:
                    raise ValueError(f"{path}: malformed End Site")
                stack.append(-2)
            elif word == "OFFSET":
                offset = np.array([float(v) for v in take(3)]) * length_unit_mm
                if not stack:
                    raise ValueError(f"{path}: OFFSET outside a joint")
                if stack[-1] == -2:
                    tips[stack[-2]] = offset
                else:
                    offsets[stack[-1]] = offset
            elif word == "CHANNELS":
                count = int(take(1)[0])
                channels = [c.lower() for c in take(count)]
                unknown = [c for c in channels if c not in _BVH_CHANNELS]
                if unknown or not stack or stack[-1] < 0:
                    raise ValueError(f"{path}: joint {names[-1]!r}: unknown channel(s) {unknown} or CHANNELS misplaced")
                dofs[stack[-1]] = tuple(_BVH_CHANNELS[c] for c in channels)
                orders[stack[-1]] = "".join(c[0] for c in channels if c.endswith("rotation"))
            elif word == "}":
                if not stack:
                    raise ValueError(f"{path}: unbalanced '}}'")
                stack.pop()
            else:
                raise ValueError(f"{path}: unexpected token {word!r} in HIERARCHY")
    except (IndexError, ValueError) as e:
        if str(e).startswith(str(path)):
            raise
        raise ValueError(f"{path}: malformed HIERARCHY ({e})") from e
    if stack or not names:
        raise ValueError(f"{path}: unbalanced braces or no ROOT in HIERARCHY")
    for b, dof_list in enumerate(dofs):
        _check_dofs(dof_list, path, names[b], allow_translation=True)
        if len(orders[b]) not in (0, 3) and len(set(orders[b])) != len(orders[b]):
            raise ValueError(f"{path}: joint {names[b]!r}: repeated rotation channel")
    parents_arr = np.array(parents, np.int64)
    for b in range(len(names)):  # a bone without an End Site reaches its only child, if it has one
        if tips[b] is None:
            kids = np.flatnonzero(parents_arr == b)
            tips[b] = offsets[kids[0]] if len(kids) == 1 else np.zeros(3)
    skeleton = Skeleton(
        names=tuple(names),
        parents=parents_arr,
        offsets=np.stack(offsets),
        tips=np.stack(tips),
        axes=np.broadcast_to(np.eye(3), (len(names), 3, 3)).copy(),
        dofs=tuple(dofs),
        rotation_orders=tuple(orders),
        limits=np.tile([-np.inf, np.inf], (sum(len(d) for d in dofs), 1)),
        length_unit_mm=float(length_unit_mm),
    )

    lines = [line.strip() for line in motion_text.splitlines() if line.strip()]
    num_dofs = len(skeleton.dof_names)
    try:
        num_frames = int(lines[0].split(":")[1])
        frame_time = float(lines[1].split(":")[1])
        rows = [[float(v) for v in line.split()] for line in lines[2 : 2 + num_frames]]
    except (IndexError, ValueError) as e:
        raise ValueError(f"{path}: malformed MOTION header or frame ({e})") from e
    if len(rows) != num_frames:
        raise ValueError(f"{path}: MOTION says {num_frames} frames but has {len(rows)}")
    for f, row in enumerate(rows):
        if len(row) != num_dofs:
            raise ValueError(f"{path}: MOTION frame {f} has {len(row)} values, the hierarchy has {num_dofs} channels")
    values = np.array(rows, np.float64).reshape(num_frames, num_dofs)
    if not frame_time > 0:
        raise ValueError(f"{path}: Frame Time must be > 0, got {frame_time}")
    scale = np.array([length_unit_mm if d in _TRANSLATIONS else np.pi / 180.0 for bone in dofs for d in bone])
    return skeleton, Motion(skeleton.dof_names, values * scale, 1.0 / frame_time)


def write_bvh(
    path: str | os.PathLike,
    skeleton: Skeleton,
    motion: Motion,
    rotation_order: str = "zxy",
    length_unit_mm: float = 1.0,
) -> pathlib.Path:
    """Write a skeleton and motion as BVH (any skeleton: ASF bone frames C_b are folded into the angles).

    Every bone becomes a joint with three rotation channels in `rotation_order` (product order), the root
    also with three position channels; a bone's channels are the Euler angles of its local rotation
    C_b·M_b·C_b⁻¹, so FK of the file read back equals `joint_positions(skeleton, motion)`. Leaves get an
    End Site at their tip. Translation DoF are only written for the root.

    Raises:
        ValueError: a motion whose names differ from `skeleton.dof_names`, or a non-root translation DoF.
    """
    path = pathlib.Path(path)
    if tuple(motion.names) != skeleton.dof_names:
        raise ValueError("motion.names must equal skeleton.dof_names (the motion of this skeleton)")
    if sorted(rotation_order) != list(_AXES):
        raise ValueError(f"rotation_order must be a permutation of 'xyz', got {rotation_order!r}")
    for b in range(1, skeleton.num_bones):
        if any(d in _TRANSLATIONS for d in skeleton.dofs[b]):
            raise ValueError(f"bone {skeleton.names[b]!r} has a translation DoF; BVH is written for the root only")
    transforms = bone_transforms(skeleton, motion.values)  # (F, B, 4, 4)
    rot = transforms[..., :3, :3]
    local = rot.copy()
    has_parent = skeleton.parents >= 0
    local[:, has_parent] = np.swapaxes(rot[:, skeleton.parents[has_parent]], -1, -2) @ rot[:, has_parent]
    angles = np.degrees(euler_angles(rotation_order, local))  # (F, B, 3)
    root_shift = (transforms[:, 0, :3, 3] - skeleton.offsets[0]) / length_unit_mm
    channel_names = " ".join(f"{a.upper()}rotation" for a in rotation_order)

    def fmt(values: Iterable[float]) -> str:
        return " ".join(f"{float(v):.9g}" for v in values)

    out = ["HIERARCHY"]

    def emit(b: int, depth: int) -> None:
        pad = "  " * depth
        out.append(f"{pad}{'ROOT' if depth == 0 else 'JOINT'} {skeleton.names[b]}")
        out.append(f"{pad}{{")
        out.append(f"{pad}  OFFSET {fmt(skeleton.offsets[b] / length_unit_mm)}")
        if depth == 0:
            out.append(f"{pad}  CHANNELS 6 Xposition Yposition Zposition {channel_names}")
        else:
            out.append(f"{pad}  CHANNELS 3 {channel_names}")
        kids = skeleton.children(b)
        for c in kids:
            emit(c, depth + 1)
        if not kids:
            out.append(f"{pad}  End Site")
            out.append(f"{pad}  {{")
            out.append(f"{pad}    OFFSET {fmt(skeleton.tips[b] / length_unit_mm)}")
            out.append(f"{pad}  }}")
        out.append(f"{pad}}}")

    emit(0, 0)
    order = []

    def collect(b: int) -> None:
        order.append(b)
        for c in skeleton.children(b):
            collect(c)

    collect(0)
    out += ["MOTION", f"Frames: {motion.num_frames}", f"Frame Time: {1.0 / motion.frame_rate:.9g}"]
    for f in range(motion.num_frames):
        out.append(fmt(np.concatenate([root_shift[f], *(angles[f, b] for b in order)])))
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(out) + "\n")
    return path
