"""A synthetic scene of two objects that cross in front of each other, in the BOP layout (two obj_ids).

Both are boxes with different photo textures; object 1 passes in front of object 2 half-way through, so
each hides part of the other's contour (object 2 for several frames). Ground truth is exact: poses per
frame for both objects and each object's visible mask (`visible_mask/<obj_id>/NNNNNN.png`).
"""

from __future__ import annotations

import dataclasses
import json
import os
import pathlib

import numpy as np

from ..io import prepare_output_folder, write_camera_view, write_image
from ._pose_scenes import look_at
from ._raycast import RayCaster, background_plane, mesh_appearance
from ._sequences import PHOTOS, SynthConfig, _check_choice, _rotation, load_object, photo


@dataclasses.dataclass
class CrossingConfig:
    """Two boxes crossing (lengths in mm, angles in degrees).

    Attributes:
        frames: number of frames; width, height, focal: the pinhole camera.
        size_mm: longest side of each box; distances: (front, back) depths of the two paths.
        travel_mm: horizontal distance each object covers (in opposite directions; they meet mid-way).
        step_deg: rotation per frame of each object about its own axis.
        textures: the two boxes' photos; background: a photo or "flat".
        noise_sigma: Gaussian pixel noise; seed: of the start rotations and axes.
    """

    frames: int = 24
    width: int = 320
    height: int = 240
    focal: float = 350.0
    size_mm: float = 140.0
    distances: tuple = (520.0, 700.0)
    travel_mm: float = 260.0
    step_deg: float = 1.5
    textures: tuple = ("astronaut", "chelsea")
    background: str = "coffee"
    noise_sigma: float = 0.0
    seed: int = 0

    def __post_init__(self):
        for name in ("frames", "width", "height"):
            v = getattr(self, name)
            if not isinstance(v, (int, np.integer)) or v < (2 if name == "frames" else 16):
                raise ValueError(f"CrossingConfig.{name} must be an integer ≥ {2 if name == 'frames' else 16}, got {v!r}")
        for name in ("focal", "size_mm", "travel_mm"):
            if not np.isfinite(getattr(self, name)) or getattr(self, name) <= 0:
                raise ValueError(f"CrossingConfig.{name} must be a positive number, got {getattr(self, name)!r}")
        if len(self.distances) != 2 or not all(np.isfinite(d) and d > self.size_mm for d in self.distances):
            raise ValueError(f"CrossingConfig.distances must be two depths beyond size_mm ({self.size_mm} mm), got {self.distances}")
        if len(self.textures) != 2:
            raise ValueError(f"CrossingConfig.textures must name two photos, got {self.textures}")
        for t in self.textures:
            _check_choice("textures", t, PHOTOS)
        _check_choice("background", self.background, (*PHOTOS, "flat"))
        if not np.isfinite(self.noise_sigma) or self.noise_sigma < 0:
            raise ValueError(f"CrossingConfig.noise_sigma must be ≥ 0, got {self.noise_sigma!r}")


def crossing_trajectories(cfg: CrossingConfig) -> np.ndarray:
    """(2, N, 4, 4) model → camera poses: object 1 left → right in front, object 2 right → left behind."""
    rng = np.random.default_rng(cfg.seed)
    n = cfg.frames
    s = np.linspace(-0.5, 0.5, n)
    out = np.repeat(np.eye(4)[None, None], 2, 0).repeat(n, 1)
    for o, (sign, z) in enumerate(((1.0, cfg.distances[0]), (-1.0, cfg.distances[1]))):
        R0 = _rotation(rng.normal(size=3), rng.uniform(0.4, 1.0))
        axis = np.array([0.2, 1.0, 0.1]) + 0.3 * rng.normal(size=3)
        for k in range(n):
            out[o, k, :3, :3] = _rotation(axis, np.radians(cfg.step_deg * k)) @ R0
            out[o, k, :3, 3] = [sign * s[k] * cfg.travel_mm, 0.02 * z * (1 if o else -1), z]
    return out


def render_crossing(cfg: CrossingConfig) -> dict:
    """Render the scene: images (N, H, W, 3) uint8, K (3, 3), T_cam_obj {1: (N, 4, 4), 2: ...}, visible
    {obj_id: (N, H, W) bool} (each object's unoccluded pixels), meshes {obj_id: trimesh}."""
    if not isinstance(cfg, CrossingConfig):
        raise TypeError(f"render_crossing: cfg must be a CrossingConfig, got {type(cfg).__name__}")
    rng = np.random.default_rng(cfg.seed + 1)
    K = np.array([[cfg.focal, 0, (cfg.width - 1) / 2], [0, cfg.focal, (cfg.height - 1) / 2], [0, 0, 1]])
    meshes, casters = {}, {}
    for o, tex in enumerate(cfg.textures, 1):
        tm = load_object(SynthConfig(object="box", size_mm=cfg.size_mm))
        meshes[o] = tm
        casters[o] = RayCaster(tm, mesh_appearance(tm, "photo", photo(tex), (0, 0, 0)))
    poses = crossing_trajectories(cfg)
    bg = None if cfg.background == "flat" else photo(cfg.background)
    R_c, t_c = look_at([0.0, 0.0, -1.0])  # the background plane's camera: any fixed one
    T_bg = np.eye(4)
    T_bg[:3, :3], T_bg[:3, 3] = R_c, t_c
    images, visible = [], {1: [], 2: []}
    for k in range(cfg.frames):
        img = background_plane(bg, (70.0, 70.0, 70.0), K, T_bg, cfg.width, cfg.height)
        depth = np.full((cfg.height, cfg.width), np.inf)
        owner = np.zeros((cfg.height, cfg.width), np.int32)
        for o in (2, 1):
            face, d, pts = casters[o].cast(K, poses[o - 1, k], cfg.width, cfg.height)
            near = (face >= 0) & (d < depth)
            img[near] = casters[o].shade(face, pts, poses[o - 1, k])[near]
            depth = np.where(near, d, depth)
            owner[near] = o
        if cfg.noise_sigma > 0:
            img = img + rng.normal(scale=cfg.noise_sigma, size=img.shape)
        images.append(np.clip(np.round(img), 0, 255).astype(np.uint8))
        for o in (1, 2):
            visible[o].append(owner == o)
    return {"images": np.stack(images), "K": K, "T_cam_obj": {o: poses[o - 1] for o in (1, 2)},
            "visible": {o: np.stack(v) for o, v in visible.items()}, "meshes": meshes}


def write_crossing_sequence(cfg: CrossingConfig, root: str | os.PathLike) -> pathlib.Path:
    """Render `cfg` and write it in the BOP layout under `root`: models/obj_000001.ply and obj_000002.ply, one
    camera folder 000000/ with both objects' poses in scene_gt.json, their visible masks, and the config.

    Raises:
        ValueError: `root` is an existing file (checked before rendering), or a bad config value.
    """
    root = prepare_output_folder(root, "write_crossing_sequence: root")
    scene = render_crossing(cfg)
    (root / "models").mkdir(parents=True, exist_ok=True)
    for o, tm in scene["meshes"].items():
        tm.export(root / "models" / f"obj_{o:06d}.ply")
    folder = root / "000000"
    write_camera_view(folder, scene["images"], scene["K"], scene["T_cam_obj"])
    for o, masks in scene["visible"].items():
        (folder / "visible_mask" / f"{o:06d}").mkdir(parents=True, exist_ok=True)
        for k, m in enumerate(masks):
            write_image(folder / "visible_mask" / f"{o:06d}" / f"{k:06d}.png", m.astype(np.uint8) * 255,
                        "write_crossing_sequence: visible_mask")
    (root / "synth_config.json").write_text(json.dumps({"crossing": dataclasses.asdict(cfg)}, indent=1))
    return root
