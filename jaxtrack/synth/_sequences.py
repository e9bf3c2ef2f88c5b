"""Synthetic tracking sequences with exact ground truth, written in the BOP scene layout.

Deterministic given the seed. Objects: the meshes in ../shared/data/meshes (teapot, textured cracker
box, milk truck) or built-in primitives (box); textured, photo-projected or homogeneous. Backgrounds:
photographs that ship with scikit-image, or a flat colour. Motions: turntable, smooth random 6-DoF
with a set inter-frame displacement, a moving camera, or poses read from a file. Degradations:
Gaussian noise, salt (uniform random pixels), moving occluders (with per-frame ground-truth masks),
frame-rate subsampling. 1-4 cameras on a ring.
"""

from __future__ import annotations

import dataclasses
import json
import os
import pathlib
import shutil
from typing import Protocol

import cv2
import numpy as np
import trimesh

from ..geometry import checked_array, checked_rotation
from ..io import load_trimesh, prepare_output_folder, write_camera_view, write_image
from ._pose_scenes import look_at
from ._raycast import RayCaster, background_plane, mesh_appearance

SHARED_MESHES = pathlib.Path(os.environ.get("JAXTRACK_SHARED", pathlib.Path(__file__).resolve().parents[3] / "shared")) / "data" / "meshes"
NAMED_OBJECTS = {
    "teapot": SHARED_MESHES / "utah_teapot_solid.stl",
    "cracker_box": SHARED_MESHES / "ycb_003_cracker_box" / "cracker_box.obj",
    "milk_truck": SHARED_MESHES / "CesiumMilkTruck.glb",
}
PHOTOS = ("coffee", "astronaut", "rocket", "chelsea", "brick", "gravel", "camera", "grass")


class Progress(Protocol):
    """Anything with tqdm's `update(n)` (told once per rendered frame and camera)."""

    def update(self, n: int = 1) -> object: ...


@dataclasses.dataclass
class SynthConfig:
    """Everything that defines a synthetic sequence (all lengths in mm, angles in degrees)."""

    object: str = "box"  # box | teapot | cracker_box | milk_truck | path to a mesh
    size_mm: float = 160.0  # longest side after scaling
    appearance: str = "photo"  # texture | photo | flat
    texture_photo: str = "astronaut"
    colour: tuple = (200.0, 60.0, 40.0)
    background: str = "coffee"  # a scikit-image photo name or 'flat'
    background_colour: tuple = (70.0, 70.0, 70.0)
    motion: str = "random"  # turntable | random | camera | file
    pose_file: str | None = None
    frames: int = 30
    step_px: float = 15.0  # random motion: image displacement per frame
    step_deg: float = 5.0  # random / turntable rotation per frame
    noise_sigma: float = 0.0
    salt_fraction: float = 0.0
    occluders: int = 0
    cameras: int = 1
    subsample: int = 1
    width: int = 640
    height: int = 480
    focal: float = 700.0
    distance: float = 600.0
    seed: int = 0

    def __post_init__(self):
        """Refuse values that would render something else than asked (or fail deep in numpy)."""
        _check_choice("object", self.object, None)
        _check_choice("appearance", self.appearance, APPEARANCES)
        _check_choice("texture_photo", self.texture_photo, PHOTOS)
        _check_choice("background", self.background, (*PHOTOS, "flat"))
        _check_choice("motion", self.motion, MOTIONS)
        if self.object not in (*NAMED_OBJECTS, "box") and not pathlib.Path(self.object).is_file():
            raise ValueError(f"SynthConfig.object must be box, {', '.join(NAMED_OBJECTS)} or a mesh file; "
                             f"{self.object}: mesh file not found")
        if self.motion == "file" and not self.pose_file:
            raise ValueError("SynthConfig.pose_file: motion 'file' needs a .npy of (N, 4, 4) object poses in mm")
        if self.pose_file is not None and not pathlib.Path(self.pose_file).is_file():
            raise ValueError(f"SynthConfig.pose_file: {self.pose_file}: pose file not found")
        for name in ("colour", "background_colour"):
            c = np.asarray(getattr(self, name), dtype=object)
            if c.shape != (3,) or not all(_is_number(v) and 0 <= v <= 255 for v in c):
                raise ValueError(f"SynthConfig.{name} must be 3 numbers in [0, 255], got {getattr(self, name)!r}")
        for name, low, high in (("frames", 1, None), ("occluders", 0, None), ("cameras", 1, 4), ("subsample", 1, None),
                                ("width", 8, None), ("height", 8, None), ("seed", 0, None)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | np.integer) or v < low or (high is not None and v > high):
                bound = f"in [{low}, {high}]" if high is not None else f"≥ {low}"
                raise ValueError(f"SynthConfig.{name} must be an integer {bound}, got {v!r}")
        for name, positive in (("size_mm", True), ("focal", True), ("distance", True), ("step_px", False),
                               ("step_deg", False), ("noise_sigma", False), ("salt_fraction", False)):
            v = getattr(self, name)
            if not _is_number(v) or not (v > 0 if positive else v >= 0):
                raise ValueError(f"SynthConfig.{name} must be a finite number {'> 0' if positive else '≥ 0'}, got {v!r}")
        if self.salt_fraction > 1:
            raise ValueError(f"SynthConfig.salt_fraction must lie in [0, 1], got {self.salt_fraction!r}")


APPEARANCES = ("texture", "photo", "flat")
MOTIONS = ("turntable", "random", "camera", "file")


def _is_number(v) -> bool:
    return isinstance(v, int | float | np.integer | np.floating) and not isinstance(v, bool) and bool(np.isfinite(v))


def _check_choice(name: str, value, choices) -> None:
    if not isinstance(value, str) or not value:
        raise ValueError(f"SynthConfig.{name} must be a non-empty string, got {value!r}")
    if choices is not None and value not in choices:
        raise ValueError(f"SynthConfig.{name} must be one of {', '.join(choices)}, got {value!r}")


PRESETS = {
    "teabox-large-motion": SynthConfig(object="box", appearance="photo", texture_photo="chelsea", size_mm=165, motion="random", step_px=30, step_deg=10, frames=40, background="coffee"),
    "noisy-moving-camera": SynthConfig(object="cracker_box", appearance="texture", motion="camera", step_px=12, step_deg=3, noise_sigma=40, frames=40, background="brick"),
    "turntable-teapot": SynthConfig(object="teapot", appearance="flat", colour=(210, 180, 60), motion="turntable", step_deg=6, frames=60, background="gravel", size_mm=220),
    "turntable-truck": SynthConfig(object="milk_truck", appearance="texture", motion="turntable", step_deg=6, frames=60, background="grass", size_mm=240),
    "occluded-box": SynthConfig(object="cracker_box", appearance="texture", motion="random", step_px=8, step_deg=3, occluders=2, frames=40, background="rocket"),
    "stereo-noise": SynthConfig(object="box", appearance="photo", texture_photo="astronaut", motion="random", step_px=10, step_deg=4, cameras=2, noise_sigma=60, salt_fraction=0.1, frames=30, background="coffee"),
}


def photo(name: str) -> np.ndarray:
    """A photograph shipped with scikit-image as float32 RGB in [0, 255]."""
    import skimage.data  # heavy: only when a photo is used

    if name not in PHOTOS:
        raise ValueError(f"unknown photo {name!r}; choose from {', '.join(PHOTOS)}")
    img = getattr(skimage.data, name)()
    if img.ndim == 2:
        img = np.stack([img] * 3, -1)
    return img[..., :3].astype(np.float32)


def load_object(cfg: SynthConfig) -> trimesh.Trimesh:
    """The object mesh centred at its bounding-box centre, scaled so its longest side is cfg.size_mm."""
    if cfg.object == "box":
        tm = trimesh.creation.box(extents=(1.0, 0.41, 0.48))
    elif cfg.object in NAMED_OBJECTS:
        tm = load_trimesh(NAMED_OBJECTS[cfg.object])
    else:
        tm = load_trimesh(cfg.object)
    tm = tm.copy()
    tm.apply_translation(-tm.bounding_box.centroid)
    tm.apply_scale(cfg.size_mm / tm.extents.max())
    return tm


def _rotation(axis, angle_rad):
    R, _ = cv2.Rodrigues(np.asarray(axis, float) / np.linalg.norm(axis) * angle_rad)
    return R


def object_trajectory(cfg: SynthConfig, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(T_world_obj (N, 4, 4), T_cam0_world (N, 4, 4)) before subsampling; world = first camera's target."""
    n = cfg.frames * cfg.subsample
    T_obj = np.repeat(np.eye(4)[None], n, 0)
    T_obj[0, :3, :3] = _rotation(rng.normal(size=3), rng.uniform(0.3, 1.0))
    R_cam, t_cam = look_at([0.0, -0.35 * cfg.distance, -cfg.distance])
    T_cam = np.repeat(np.eye(4)[None], n, 0)
    T_cam[:, :3, :3], T_cam[:, :3, 3] = R_cam, t_cam
    step_deg = cfg.step_deg / cfg.subsample
    step_mm = cfg.step_px / cfg.subsample * cfg.distance / cfg.focal
    if cfg.motion == "file":
        return _read_pose_file(cfg.pose_file, n), T_cam
    axis = np.array([0.0, 1.0, 0.0]) + 0.3 * rng.normal(size=3)
    direction = rng.normal(size=3) * [1, 1, 0.3]
    # The object (or the camera's aim point) wanders within this radius of the view centre.
    radius = 0.3 * min(cfg.width, cfg.height) * cfg.distance / cfg.focal
    aim = np.zeros(3)
    azimuth, elevation = 0.0, np.arctan2(0.35, 1.0)
    for k in range(1, n):
        T = T_obj[k - 1].copy()
        axis = axis + 0.2 * rng.normal(size=3)
        R_step = _rotation(axis, np.radians(step_deg))
        # A smooth random walk of the direction, steered back towards the centre as it nears the edge.
        here = T[:3, 3] if cfg.motion == "random" else aim
        direction = direction / np.linalg.norm(direction) + 0.3 * rng.normal(size=3) * [1, 1, 0.3]
        direction = direction - 2.0 * (np.linalg.norm(here) / radius) ** 2 * here / max(np.linalg.norm(here), 1e-9)
        vel = direction / np.linalg.norm(direction) * step_mm
        if cfg.motion == "turntable":
            T[:3, :3] = _rotation([0.0, 1.0, 0.0], np.radians(step_deg)) @ T[:3, :3]
        elif cfg.motion == "random":
            T[:3, :3] = R_step @ T[:3, :3]
            T[:3, 3] = T[:3, 3] + vel
        elif cfg.motion == "camera":
            # The camera orbits the static object by step_deg and re-aims at a wandering point,
            # so the background sweeps by and the object moves by ~step_px in the image.
            azimuth += np.radians(step_deg)
            elevation = np.clip(elevation + 0.3 * np.radians(step_deg) * rng.normal(), 0.1, 0.9)
            aim = aim + vel
            eye = cfg.distance * np.array([np.sin(azimuth) * np.cos(elevation), -np.sin(elevation), -np.cos(azimuth) * np.cos(elevation)])
            R_c, t_c = look_at(eye, target=aim)
            T_cam[k, :3, :3], T_cam[k, :3, 3] = R_c, t_c
        else:
            raise ValueError(f"unknown motion {cfg.motion!r} (turntable, random, camera, file)")
        T_obj[k] = T
    return T_obj, T_cam


def _read_pose_file(path, n: int) -> np.ndarray:
    """(n, 4, 4) object poses from a .npy file; errors name the file and the first bad pose."""
    path = pathlib.Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: pose file not found")
    try:
        poses = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise ValueError(f"{path}: not a .npy array file ({e})") from e
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) < n:
        raise ValueError(f"{path}: need ({n}, 4, 4) poses (frames x subsample), got {poses.shape}")
    poses = poses[:n].astype(float)
    for k, T in enumerate(poses):
        checked_array(T, f"{path}: pose {k}")
        checked_rotation(T[:3, :3], f"{path}: pose {k} rotation")
        if not np.allclose(T[3], [0, 0, 0, 1]):
            raise ValueError(f"{path}: pose {k} must have last row (0, 0, 0, 1), got {T[3].tolist()}")
    return poses


def _occluder_masks(cfg, rng, n):
    """Moving bars/discs that cross the image: masks (num_occluders, N, H, W) bool and RGB colours."""
    masks = np.zeros((cfg.occluders, n, cfg.height, cfg.width), bool)
    colours = rng.uniform(20, 235, size=(cfg.occluders, 3))
    yy, xx = np.mgrid[0 : cfg.height, 0 : cfg.width]
    for o in range(cfg.occluders):
        start = rng.uniform([0, 0], [cfg.width, cfg.height])
        end = np.array([cfg.width, cfg.height]) - start
        radius = rng.uniform(0.06, 0.12) * cfg.width
        disc = rng.random() < 0.5
        for k in range(n):
            c = start + (end - start) * k / max(n - 1, 1)
            if disc:
                masks[o, k] = (xx - c[0]) ** 2 + (yy - c[1]) ** 2 < radius**2
            else:
                masks[o, k] = (np.abs(xx - c[0]) < radius * 0.4) & (np.abs(yy - c[1]) < radius * 2.0)
    return masks, colours


def render_sequence(cfg: SynthConfig, progress: Progress | None = None):
    """Render all frames. Returns dict with images per camera (C, N, H, W, 3) uint8, T_cam_obj
    (C, N, 4, 4), T_cam_world (C, N, 4, 4), K, object masks (C, N, H, W) and occluder masks (C, N, H, W)."""
    if not isinstance(cfg, SynthConfig):
        raise TypeError(f"render_sequence: cfg must be a SynthConfig, got {type(cfg).__name__}")
    rng = np.random.default_rng(cfg.seed)
    tm = load_object(cfg)
    tex_photo = photo(cfg.texture_photo) if cfg.appearance == "photo" else None
    caster = RayCaster(tm, mesh_appearance(tm, cfg.appearance, tex_photo, cfg.colour))
    bg = None if cfg.background == "flat" else photo(cfg.background)
    T_obj, T_cam0 = object_trajectory(cfg, rng)
    n = len(T_obj)
    K = np.array([[cfg.focal, 0, (cfg.width - 1) / 2], [0, cfg.focal, (cfg.height - 1) / 2], [0, 0, 1]])
    # Extra cameras on a ring around the object's start, looking at the origin.
    rigs = [T_cam0]
    for c in range(1, cfg.cameras):
        a = 2 * np.pi * c / cfg.cameras
        R, t = look_at([cfg.distance * np.sin(a), -0.35 * cfg.distance, -cfg.distance * np.cos(a)])
        T = np.repeat(np.eye(4)[None], n, 0)
        T[:, :3, :3], T[:, :3, 3] = R, t
        rigs.append(T @ np.linalg.inv(T_cam0[0]) @ T_cam0 if cfg.motion == "camera" else T)
    keep = np.arange(0, n, cfg.subsample)
    for c, T_cam in enumerate(rigs):  # before anything is rendered: an object behind a camera cannot be drawn
        z = np.einsum("kij,kj->ki", T_cam[keep], T_obj[keep][:, :, 3])[:, 2]
        if np.any(z <= 0):
            k = int(keep[np.argmax(z <= 0)])
            where = f"{cfg.pose_file}: pose {k}" if cfg.motion == "file" else f"motion {cfg.motion!r}, frame {k}"
            raise ValueError(f"{where} puts the object behind camera {c} (depth {z[np.argmax(z <= 0)]:.1f} mm ≤ 0); poses are "
                             f"in mm in the world frame, whose origin the first camera sees at {cfg.distance:g} mm")
    occ, occ_colours = _occluder_masks(cfg, rng, n)
    out = {"K": K, "images": [], "T_cam_obj": [], "T_cam_world": [], "object_mask": [], "occluder_mask": []}
    for T_cam in rigs:
        imgs, poses, objm, occm = [], [], [], []
        for k in keep:
            T_co = T_cam[k] @ T_obj[k]
            face, _depth, pts = caster.cast(K, T_co, cfg.width, cfg.height)
            img = background_plane(bg, cfg.background_colour, K, T_cam[k], cfg.width, cfg.height)
            hit = face >= 0
            img[hit] = caster.shade(face, pts, T_co)[hit]
            for o in range(cfg.occluders):
                img[occ[o, k]] = occ_colours[o]
            if cfg.noise_sigma > 0:
                img = img + rng.normal(scale=cfg.noise_sigma, size=img.shape)
            if cfg.salt_fraction > 0:
                salt = rng.random(img.shape[:2]) < cfg.salt_fraction
                img[salt] = rng.uniform(0, 255, size=(salt.sum(), 3))
            imgs.append(np.clip(np.round(img), 0, 255).astype(np.uint8))
            poses.append(T_co)
            objm.append(hit)
            occm.append(occ[:, k].any(axis=0) & hit)
            if progress is not None:
                progress.update(1)
        out["images"].append(np.stack(imgs))
        out["T_cam_obj"].append(np.stack(poses))
        out["T_cam_world"].append(T_cam[keep])
        out["object_mask"].append(np.stack(objm))
        out["occluder_mask"].append(np.stack(occm))
    out["mesh"] = tm
    return out


def write_sequence(cfg: SynthConfig, root: str | os.PathLike, progress: Progress | None = None) -> pathlib.Path:
    """Render `cfg` and write it in the BOP layout under `root` (plus occluder masks and the config).

    Raises:
        ValueError: `root` is an existing file (checked before rendering), or a bad config value.
    """
    existed = pathlib.Path(root).exists()
    root = prepare_output_folder(root, "write_sequence: root")  # before rendering, not after
    try:
        seq = render_sequence(cfg, progress)
    except Exception:
        if not existed:  # no empty folder left behind by a config that cannot be rendered
            shutil.rmtree(root, ignore_errors=True)
        raise
    (root / "models").mkdir(parents=True, exist_ok=True)
    seq["mesh"].export(root / "models" / "obj_000001.ply")
    for c in range(len(seq["images"])):
        folder = root / f"{c:06d}"
        # GT per camera: the object pose in that camera; extrinsics of frame 0 place the rig.
        write_camera_view(folder, seq["images"][c], seq["K"], {1: seq["T_cam_obj"][c]}, seq["T_cam_world"][c][0])
        for name in ("object_mask", "occluder_mask"):
            (folder / name).mkdir(exist_ok=True)
            for k, m in enumerate(seq[name][c]):
                write_image(folder / name / f"{k:06d}.png", m.astype(np.uint8) * 255, f"write_sequence: {name}")
    cfg_dict = dataclasses.asdict(cfg)
    (root / "synth_config.json").write_text(json.dumps(cfg_dict, indent=1))
    return root
