"""Synthetic articulated sequences with exact joint ground truth (a URDF robot, or a human driven by mocap).

The images come from the independent ray caster (`RayCaster`, embree through trimesh), never from the
tracker's rasteriser: each frame the model's parts are posed by forward kinematics (eq. 2) and the posed
surface is ray cast from every camera. Written in the BOP layout extended for articulated objects:
`models/obj_000001.urdf` (written by `jaxtrack.io.write_urdf`, so the tracker reads the same file) and
scene_gt.json entries with the root link's pose and `"joints"` (URDF units: radians, metres).

World frame: y up (the mocap convention); a URDF robot, z up in its own frame, stands on the x-z plane.
Static cameras on a ring around the motion's centre look at it from slightly above.
"""

from __future__ import annotations

import dataclasses
import json
import os
import pathlib

import numpy as np
import trimesh

from ..io import prepare_output_folder, write_camera_view, write_image
from ._pose_scenes import look_at
from ._raycast import RayCaster, _sample, background_plane
from ._sequences import PHOTOS, Progress, photo

APPEARANCES = ("parts", "photo", "suit")
# A distinct colour per part (cycled): the tracker's region cue then sees limb boundaries too.
PART_COLOURS = np.array([
    [200, 60, 40], [60, 140, 200], [230, 190, 60], [80, 170, 90], [170, 90, 180], [230, 130, 60],
    [90, 200, 200], [200, 200, 200], [140, 100, 60], [120, 120, 230],
], np.float32)
SUIT_COLOUR = (45.0, 45.0, 55.0)  # the paper's subjects wore a plain dark suit


@dataclasses.dataclass
class ArticulatedSynthConfig:
    """How an articulated sequence is rendered (the model and its motion are given separately).

    Attributes:
        cameras: 1-8 static cameras on a ring around the motion's centre, `height_ratio`·distance above it.
        distance: camera distance (mm) from the centre of the motion.
        appearance: 'parts' (a flat colour per part), 'photo' (a photograph glued to the surface at the
            zero configuration, so it moves with every part) or 'suit' (one dark colour, the paper's setup).
        subsample: keep every n-th frame of the motion (120 fps mocap → 40, 30, 24 fps with 3, 4, 5).
    """

    cameras: int = 1
    width: int = 640
    height: int = 480
    focal: float = 700.0
    distance: float = 2000.0
    height_ratio: float = 0.3
    appearance: str = "parts"
    texture_photo: str = "astronaut"
    background: str = "coffee"
    background_colour: tuple = (70.0, 70.0, 70.0)
    noise_sigma: float = 0.0
    subsample: int = 1
    seed: int = 0

    def __post_init__(self):
        for name, low in (("cameras", 1), ("width", 8), ("height", 8), ("subsample", 1), ("seed", 0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | np.integer) or v < low:
                raise ValueError(f"ArticulatedSynthConfig.{name} must be an integer ≥ {low}, got {v!r}")
        if self.cameras > 8:
            raise ValueError(f"ArticulatedSynthConfig.cameras must be at most 8, got {self.cameras}")
        for name in ("focal", "distance"):
            v = getattr(self, name)
            if not isinstance(v, int | float) or not np.isfinite(v) or v <= 0:
                raise ValueError(f"ArticulatedSynthConfig.{name} must be a positive number, got {v!r}")
        if not isinstance(self.noise_sigma, int | float) or not np.isfinite(self.noise_sigma) or self.noise_sigma < 0:
            raise ValueError(f"ArticulatedSynthConfig.noise_sigma must be ≥ 0, got {self.noise_sigma!r}")
        if self.appearance not in APPEARANCES:
            raise ValueError(f"ArticulatedSynthConfig.appearance must be one of {', '.join(APPEARANCES)}, got {self.appearance!r}")
        if self.texture_photo not in PHOTOS:
            raise ValueError(f"ArticulatedSynthConfig.texture_photo must be one of {', '.join(PHOTOS)}, got {self.texture_photo!r}")
        if self.background != "flat" and self.background not in PHOTOS:
            raise ValueError(f"ArticulatedSynthConfig.background must be 'flat' or one of {', '.join(PHOTOS)}, "
                             f"got {self.background!r}")


def upright_urdf_pose(position_mm=(0.0, 0.0, 0.0), yaw_rad: float = 0.0) -> np.ndarray:
    """(4, 4) T_world_root placing a z-up URDF robot upright in the y-up world, turned by `yaw_rad`."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    R_yaw = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    R_up = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # robot z → world y, robot y → world −z
    T = np.eye(4)
    T[:3, :3] = R_yaw @ R_up
    T[:3, 3] = position_mm
    return T


def random_joint_trajectory(
    model, frames: int, step_deg: float = 3.0, seed: int = 0, joints=None, margin: float = 0.15
) -> np.ndarray:
    """(frames, J) smooth random joint values (model units) within the limits.

    Each moving joint passes through random waypoints in the inner (1 − 2·margin) of its range (±π for
    joints without limits) and eases between them (smoothstep), so the largest change per frame is
    about `step_deg`. Joints not in `joints` (default: every revolute / continuous joint; prismatic
    joints such as grippers stay at the middle of their range) are held.

    Args:
        model: an `ArticulatedModel` (`jaxtrack.io.read_urdf`).
    """
    if frames < 1:
        raise ValueError(f"frames must be ≥ 1, got {frames}")
    if not np.isfinite(step_deg) or step_deg <= 0:
        raise ValueError(f"step_deg must be positive, got {step_deg}")
    rng = np.random.default_rng(seed)
    lower = np.where(np.isfinite(model.lower), model.lower, -np.pi)
    upper = np.where(np.isfinite(model.upper), model.upper, np.pi)
    mid, half = (lower + upper) / 2, (upper - lower) / 2 * (1 - 2 * margin)
    names = list(model.joint_names)
    moving = ([j for j, t in enumerate(model.joint_types) if t in ("revolute", "continuous")] if joints is None
              else [names.index(n) if n in names else _unknown_joint(n, names) for n in joints])
    theta = np.repeat(mid[None], frames, 0)
    step = np.radians(step_deg)
    for j in moving:
        if model.mimic[j] is not None:
            continue
        # Legs between random waypoints, each eased by smoothstep (peak speed 1.5x the mean), so a leg of
        # length L takes ⌈1.5·L / step⌉ frames and no frame moves more than `step`.
        values, current = [], mid[j] + half[j] * rng.uniform(-1, 1)
        while len(values) < frames:
            target = mid[j] + half[j] * rng.uniform(-1, 1)
            legs = max(4, int(np.ceil(1.5 * abs(target - current) / step)))
            f = np.arange(legs) / legs
            values.extend(current + (target - current) * f * f * (3 - 2 * f))
            current = target
        theta[:, j] = values[:frames]
    for j, mimic in enumerate(model.mimic):  # followers track their source (URDF units)
        if mimic is not None:
            source, multiplier, offset = mimic
            scale = model.joint_scale
            theta[:, j] = (multiplier * theta[:, source] / scale[source] + offset) * scale[j]
    return theta


def _unknown_joint(name, names):
    raise ValueError(f"joints: {name!r} is not a movable joint of the model (have {names})")


def _ring_cameras(cfg: ArticulatedSynthConfig, centre: np.ndarray) -> list:
    """(4, 4) T_cam_world of each camera on the ring around `centre` (world y up)."""
    rigs = []
    for c in range(cfg.cameras):
        a = 2 * np.pi * c / cfg.cameras
        eye = centre + np.array([cfg.distance * np.sin(a), cfg.height_ratio * cfg.distance, -cfg.distance * np.cos(a)])
        R, t = look_at(eye, target=centre, up=(0.0, -1.0, 0.0))
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, t
        rigs.append(T)
    return rigs


def _posed_vertices(model, T_world_root: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """(V, 3) world positions of the model's vertices at (T_world_root, Θ), by its own forward kinematics."""
    T_parts = _part_poses(model, T_world_root, theta)
    v = np.asarray(model.mesh.vertices, np.float64)
    part = np.asarray(model.mesh.vertex_part)
    return np.einsum("vij,vj->vi", T_parts[part, :3, :3], v) + T_parts[part, :3, 3]


_fk_jit = None


def _part_poses(model, T_world_root, theta) -> np.ndarray:
    import jax
    import jax.numpy as jnp

    from ..geometry import part_transforms

    global _fk_jit
    if _fk_jit is None:
        _fk_jit = jax.jit(part_transforms)
    dtype = jnp.float64 if jax.config.jax_enable_x64 else jnp.float32
    return np.asarray(_fk_jit(jax.tree.map(lambda a: jnp.asarray(a, dtype) if jnp.issubdtype(a.dtype, jnp.floating) else a,
                                           model.model), jnp.asarray(T_world_root, dtype), jnp.asarray(theta, dtype)),
                      np.float64)


def _shade(cfg, tm_posed, rest_vertices, faces, face_part, face, points, tex, lo, span, T_cam_world):
    """Colour (H, W, 3) of the hit pixels: a part colour, a photo glued at the zero configuration, or the suit."""
    hit = face >= 0
    f = face[hit]
    if cfg.appearance == "photo":
        bary = trimesh.triangles.points_to_barycentric(tm_posed.triangles[f], points[hit])
        rest = np.einsum("nk,nkj->nj", bary, rest_vertices[faces[f]])
        rel = (rest - lo) / span
        # Each part reads its own patch (shifted by part index) so that limbs do not repeat one pattern.
        col = _sample(tex, (rel[:, 0] + 0.37 * face_part[f]) % 1.0, (rel[:, 1] + 0.21 * face_part[f]) % 1.0)
    elif cfg.appearance == "suit":
        col = np.broadcast_to(np.asarray(SUIT_COLOUR, np.float32), (len(f), 3))
    else:
        col = PART_COLOURS[face_part[f] % len(PART_COLOURS)]
    n_cam = tm_posed.face_normals[f] @ T_cam_world[:3, :3].T
    light = np.array([-0.3, 0.5, 1.0]) / np.linalg.norm([0.3, 0.5, 1.0])
    lambert = np.abs(n_cam @ light)
    out = np.zeros(face.shape + (3,), np.float32)
    out[hit] = col * (0.45 + 0.55 * lambert)[:, None]
    return out


def render_articulated_sequence(
    model, T_world_root: np.ndarray, theta: np.ndarray, cfg: ArticulatedSynthConfig, progress: Progress | None = None
) -> dict:
    """Render an articulated motion from every camera.

    Args:
        model: an `ArticulatedModel` (`jaxtrack.io.read_urdf`).
        T_world_root: (F, 4, 4) root poses (mm); theta: (F, J) joint values (model units).

    Returns:
        dict with images (C, N, H, W, 3) uint8, T_cam_obj (C, N, 4, 4) root pose in each camera,
        T_cam_world (C, 4, 4), K, theta (N, J) model units, object_mask (C, N, H, W), part_id
        (C, N, H, W) int (−1 = background); N = ⌈F / subsample⌉.
    """
    if not isinstance(cfg, ArticulatedSynthConfig):
        raise TypeError(f"cfg must be an ArticulatedSynthConfig, got {type(cfg).__name__}")
    T_world_root = np.asarray(T_world_root, np.float64)
    theta = np.asarray(theta, np.float64)
    if T_world_root.ndim != 3 or T_world_root.shape[1:] != (4, 4) or not np.all(np.isfinite(T_world_root)):
        raise ValueError(f"T_world_root must be finite (F, 4, 4), got shape {T_world_root.shape}")
    if theta.shape != (len(T_world_root), model.num_joints) or not np.all(np.isfinite(theta)):
        raise ValueError(f"theta must be finite ({len(T_world_root)}, {model.num_joints}), got shape {theta.shape}")
    rng = np.random.default_rng(cfg.seed)
    keep = np.arange(0, len(T_world_root), cfg.subsample)
    faces = np.asarray(model.mesh.faces)
    rest = np.asarray(model.mesh.vertices, np.float64)
    face_part = np.asarray(model.mesh.vertex_part)[faces[:, 0]]
    lo, span = rest.min(0), np.maximum(np.ptp(rest, 0), 1e-9)
    tex = photo(cfg.texture_photo) if cfg.appearance == "photo" else None
    bg = None if cfg.background == "flat" else photo(cfg.background)
    posed = [_posed_vertices(model, T_world_root[k], theta[k]) for k in keep]
    centre = np.mean([p.mean(0) for p in posed], axis=0)
    rigs = _ring_cameras(cfg, centre)
    K = np.array([[cfg.focal, 0, (cfg.width - 1) / 2], [0, cfg.focal, (cfg.height - 1) / 2], [0, 0, 1]])
    out = {"K": K, "images": [], "T_cam_obj": [], "T_cam_world": np.stack(rigs), "theta": theta[keep],
           "object_mask": [], "part_id": []}
    for ci, T_cw in enumerate(rigs):
        imgs, poses, masks, parts = [], [], [], []
        # A backdrop 1.5 m behind the centre, facing this camera (each camera sees its own patch of the photo).
        T_bg = np.eye(4)
        T_bg[:3, 3] = (0.0, 0.0, 0.0) if ci == 0 else (700.0 * ci, 300.0 * ci, 0.0)
        backdrop = background_plane(bg, cfg.background_colour, K, T_bg, cfg.width, cfg.height, depth_world=cfg.distance + 1500.0)
        for n, k in enumerate(keep):
            tm = trimesh.Trimesh(posed[n], faces, process=False)
            caster = RayCaster(tm, None)
            face, _depth, pts = caster.cast(K, T_cw, cfg.width, cfg.height)
            img = backdrop.copy()
            hit = face >= 0
            img[hit] = _shade(cfg, tm, rest, faces, face_part, face, pts, tex, lo, span, T_cw)[hit]
            if cfg.noise_sigma > 0:
                img = img + rng.normal(scale=cfg.noise_sigma, size=img.shape)
            imgs.append(np.clip(np.round(img), 0, 255).astype(np.uint8))
            poses.append(T_cw @ T_world_root[k])
            masks.append(hit)
            parts.append(np.where(hit, face_part[np.maximum(face, 0)], -1))
            if progress is not None:
                progress.update(1)
        out["images"].append(np.stack(imgs))
        out["T_cam_obj"].append(np.stack(poses))
        out["object_mask"].append(np.stack(masks))
        out["part_id"].append(np.stack(parts))
    return out


def write_articulated_sequence(
    model,
    T_world_root: np.ndarray,
    theta: np.ndarray,
    cfg: ArticulatedSynthConfig,
    root: str | os.PathLike,
    progress: Progress | None = None,
    info: dict | None = None,
) -> pathlib.Path:
    """Render and write an articulated sequence in the BOP layout (see the module docstring).

    The model is written with `write_urdf` as models/obj_000001.urdf (meshes beside it), object masks per
    camera go to object_mask/, and the config (plus `info`, e.g. the motion's source) to synth_config.json.

    Raises:
        ValueError: `root` is an existing file (checked before rendering), or a bad argument.
    """
    from ..io import write_urdf

    root = prepare_output_folder(root, "write_articulated_sequence: root")
    seq = render_articulated_sequence(model, T_world_root, theta, cfg, progress)
    (root / "models").mkdir(parents=True, exist_ok=True)
    write_urdf(model, root / "models" / "obj_000001.urdf")
    joints = {1: {name: seq["theta"][:, j] / model.joint_scale[j] for j, name in enumerate(model.joint_names)}}
    for c in range(len(seq["images"])):
        folder = root / f"{c:06d}"
        write_camera_view(folder, seq["images"][c], seq["K"], {1: seq["T_cam_obj"][c]}, seq["T_cam_world"][c], joints=joints)
        (folder / "object_mask").mkdir(exist_ok=True)
        for k, m in enumerate(seq["object_mask"][c]):
            write_image(folder / "object_mask" / f"{k:06d}.png", m.astype(np.uint8) * 255, "write_articulated_sequence: mask")
    (root / "synth_config.json").write_text(json.dumps({**dataclasses.asdict(cfg), **(info or {})}, indent=1))
    return root


def mocap_motion(asf: str | os.PathLike, amc: str | os.PathLike, frames: int | None = None, start: int = 0):
    """The paper's 26-DoF body model of a CMU subject and its motion: (ArticulatedModel, T_world_root
    (F, 4, 4) mm, Θ (F, J) radians), the model read back from its URDF so the tracker sees the same file.

    Args:
        asf, amc: the CMU skeleton and motion (120 frames/s).
        frames, start: the frames of the motion to keep (all from `start` by default).
    """
    import tempfile

    from ..io import human_description, human_joint_values, read_amc, read_asf, read_urdf, write_urdf

    skeleton = read_asf(asf)
    motion = read_amc(amc, skeleton)
    n = motion.values.shape[0]
    if not 0 <= start < n:
        raise ValueError(f"start must be in [0, {n}) for {amc}, got {start}")
    stop = n if frames is None else min(n, start + int(frames))
    with tempfile.TemporaryDirectory() as tmp:
        path = write_urdf(human_description(skeleton), pathlib.Path(tmp) / "human.urdf")
        model = read_urdf(path)
    T_world_root, theta = human_joint_values(skeleton, motion, model.joint_names)
    return model, T_world_root[start:stop], theta[start:stop]
