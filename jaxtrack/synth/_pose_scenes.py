"""Random 2D-3D scenes with exact ground truth for the pose solver (demo, tests, benchmarks).

Host-side numpy with an explicit seed: the same seed gives the same scene.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import numpy.typing as npt

from ..geometry import (
    Camera,
    KinematicModel,
    chain_model,
    checked_array,
    checked_rotation,
    make_camera,
    part_transforms,
    project_points,
    rigid_model,
    select_camera,
    stack_cameras,
    transform_points,
)


@dataclasses.dataclass(frozen=True)
class PoseScene:
    """A solved-for-truth scene: observed pixels of model points under a known pose.

    Attributes:
        cameras: stacked rig (C on the leading axis).
        model: the kinematic tree.
        pixel: (n, 2) observed pixels (with noise, distortion applied if the camera has any).
        p_model: (n, 3) model points (mm), part: (n,), camera_index: (n,).
        T_world_root: (4, 4) true root pose; theta: (J,) true joint angles.
    """

    cameras: Camera
    model: KinematicModel
    pixel: np.ndarray
    p_model: np.ndarray
    part: np.ndarray
    camera_index: np.ndarray
    T_world_root: np.ndarray
    theta: np.ndarray


def random_rotation(rng: np.random.Generator, max_angle: float | None = None) -> np.ndarray:
    """Uniform random rotation, or one of angle ≤ max_angle (rad) about a uniform axis."""
    if max_angle is not None:
        _check_number("random_rotation: max_angle", max_angle, low=0.0)
    if max_angle is None:
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        w, x, y, z = q
        return np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
            ]
        )
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = rng.uniform(0, max_angle)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def look_at(
    eye: npt.ArrayLike,
    target: npt.ArrayLike = (0.0, 0.0, 0.0),
    up: npt.ArrayLike = (0.0, -1.0, 0.0),
) -> tuple[np.ndarray, np.ndarray]:
    """R_cam_world, t_cam_world of a camera at `eye` looking at `target` (OpenCV axes: z forward, y down)."""
    eye, target, up = (checked_array(a, f"look_at: {n}", size=3) for a, n in ((eye, "eye"), (target, "target"), (up, "up")))
    z = target - eye
    if np.linalg.norm(z) == 0 or np.linalg.norm(up) == 0:
        raise ValueError(f"look_at: eye {eye.tolist()} must differ from target and up must be non-zero")
    z /= np.linalg.norm(z)
    x = np.cross(up, z)
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(np.array([1.0, 0.0, 0.0]), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ eye


def camera_ring(
    num_cameras: int,
    distance: float = 1000.0,
    width: int = 640,
    height: int = 480,
    focal: float = 800.0,
    dtype: npt.DTypeLike = np.float32,
) -> Camera:
    """C cameras on a horizontal circle around the origin, all looking at it (world frame = first camera's view axis)."""
    _check_count("camera_ring: num_cameras", num_cameras, 1)
    _check_number("camera_ring: distance", distance, low=0.0, strict=True)
    K = np.array([[focal, 0, (width - 1) / 2], [0, focal, (height - 1) / 2], [0, 0, 1]])  # make_camera checks it
    cams = []
    for c in range(num_cameras):
        angle = 2 * np.pi * c / max(num_cameras, 1)
        eye = distance * np.array([np.sin(angle), 0.0, -np.cos(angle)])
        R, t = look_at(eye)
        cams.append(make_camera(K, width, height, R, t, dtype=dtype))
    return stack_cameras(cams)


def demo_chain(
    num_joints: int = 3,
    branches: int = 1,
    link_length: float = 120.0,
    dtype: npt.DTypeLike = np.float32,
) -> KinematicModel:
    """An arm of `num_joints` links along +x (branches=1) or a torso with two arms of num_joints/2 links
    each (branches=2, num_joints even)."""
    _check_count("demo_chain: num_joints", num_joints, 0)
    _check_number("demo_chain: link_length", link_length, low=0.0, strict=True)
    if branches == 2 and (num_joints < 2 or num_joints % 2):
        raise ValueError(f"demo_chain: two branches need an even num_joints ≥ 2 (half per arm), got {num_joints}")
    if branches == 1:
        parents = [-1] + list(range(num_joints))
        axes = [(0.0, 0.0, 1.0) if j % 2 == 0 else (0.0, 1.0, 0.0) for j in range(num_joints)]
        points = [(link_length * (j + 0.5), 0.0, 0.0) for j in range(num_joints)]
        return chain_model(parents, axes, points, dtype=dtype)
    if branches != 2:
        raise ValueError(f"demo_chain: branches must be 1 or 2, got {branches!r}")
    per_arm = max(num_joints // 2, 1)
    parents, axes, points = [-1], [], []
    for side in (1.0, -1.0):
        prev = 0
        for j in range(per_arm):
            parents.append(prev)
            prev = len(parents) - 1
            axes.append((0.0, 0.0, 1.0) if j % 2 == 0 else (0.0, 1.0, 0.0))
            points.append((side * link_length * (j + 0.5), 0.0, 0.0))
    return chain_model(parents, axes, points, dtype=dtype)


def _part_points(rng, model: KinematicModel, num_points: int, extent: float, link_length: float):
    """Points spread over the parts: the root fills a box, link p is a bar along its joint's x."""
    num_parts = model.num_parts
    part = rng.integers(0, num_parts, size=num_points) if num_parts > 1 else np.zeros(num_points, int)
    part[:num_parts] = np.arange(num_parts)[: min(num_parts, num_points)]
    pts = rng.uniform(-extent, extent, size=(num_points, 3))
    if num_parts > 1:
        twists = np.asarray(model.joint_twists, np.float64)
        for p in range(1, num_parts):
            sel = part == p
            omega, v = twists[p - 1, 3:], twists[p - 1, :3]
            q = np.cross(omega, v)  # the point of the axis closest to the origin
            direction = np.sign(q[0]) if abs(q[0]) > 0 else 1.0
            offs = rng.uniform(0, link_length, size=sel.sum())
            pts[sel] = q + np.stack([direction * offs, rng.uniform(-20, 20, sel.sum()), rng.uniform(-20, 20, sel.sum())], axis=1)
    return pts, part


def random_pose_scene(
    seed: int,
    num_points: int = 200,
    noise_px: float = 0.0,
    num_cameras: int = 1,
    model: KinematicModel | None = None,
    extent: float = 100.0,
    max_joint_angle: float = 0.6,
    dtype: npt.DTypeLike = np.float64,
) -> PoseScene:
    """A random pose of `model` (rigid by default) seen by a ring of cameras, with pixel noise.

    Points that project outside the image or behind a camera are still kept (they constrain the
    pose as lines do); each point is observed by one camera, chosen at random.
    """
    _check_count("random_pose_scene: seed", seed, 0)
    _check_count("random_pose_scene: num_points", num_points, 1)
    _check_number("random_pose_scene: noise_px", noise_px, low=0.0)
    _check_number("random_pose_scene: extent", extent, low=0.0, strict=True)
    _check_number("random_pose_scene: max_joint_angle", max_joint_angle, low=0.0)
    rng = np.random.default_rng(seed)
    model = rigid_model(dtype) if model is None else model
    if num_points < model.num_parts:
        raise ValueError(f"random_pose_scene: num_points must be ≥ the model's {model.num_parts} parts (one point each), got {num_points}")
    cameras = camera_ring(num_cameras, dtype=dtype)
    R = random_rotation(rng)
    t = rng.uniform([-50, -50, -50], [50, 50, 50])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    theta = rng.uniform(-max_joint_angle, max_joint_angle, size=model.num_joints)
    p_model, part = _part_points(rng, model, num_points, extent, link_length=120.0)
    cam_idx = rng.integers(0, num_cameras, size=num_points)
    pixel = _observe(cameras, model, T, theta, p_model, part, cam_idx, noise_px, rng)
    return PoseScene(cameras, model, pixel, p_model, part, cam_idx, T, theta)


@eqx.filter_jit
def _project_model(cameras, model, T, theta, p_model, part, cam_idx):
    T_parts = part_transforms(model, T, theta)
    p_world = transform_points(T_parts[part], p_model)
    pixel, _ = project_points(select_camera(cameras, cam_idx), p_world)
    return pixel


def _observe(cameras, model, T, theta, p_model, part, cam_idx, noise_px, rng):
    """Pixels of model points at pose (T, Θ) in their cameras, plus Gaussian noise."""
    dtype = cameras.K.dtype
    pixel = _project_model(
        cameras,
        model,
        jnp.asarray(T, dtype),
        jnp.asarray(theta, dtype),
        jnp.asarray(p_model, dtype),
        jnp.asarray(part, jnp.int32),
        jnp.asarray(cam_idx, jnp.int32),
    )
    return np.asarray(pixel, np.float64) + rng.normal(scale=noise_px, size=(len(p_model), 2))


def project_model_points(
    scene: PoseScene,
    T_world_root: npt.ArrayLike,
    theta: npt.ArrayLike,
    noise_px: float = 0.0,
    seed: int = 0,
) -> PoseScene:
    """The same model points and cameras as `scene`, observed at a new pose (T_world_root, Θ)."""
    _check_count("project_model_points: seed", seed, 0)
    _check_number("project_model_points: noise_px", noise_px, low=0.0)
    rng = np.random.default_rng(seed)
    T = _checked_pose(T_world_root, "project_model_points: T_world_root")
    theta = checked_array(theta, "project_model_points: theta", size=scene.model.num_joints)
    pixel = _observe(scene.cameras, scene.model, T, theta, scene.p_model, scene.part, scene.camera_index, noise_px, rng)
    return dataclasses.replace(scene, pixel=pixel, T_world_root=T, theta=theta)


def perturb_pose(rng: np.random.Generator, T: np.ndarray, max_angle: float, max_translation: float) -> np.ndarray:
    """T with a random rotation of ≤ max_angle (rad) and translation of ≤ max_translation (mm) applied."""
    T = _checked_pose(T, "perturb_pose: T")
    _check_number("perturb_pose: max_translation", max_translation, low=0.0)
    R = random_rotation(rng, max_angle)
    direction = rng.normal(size=3)
    out = np.array(T, np.float64)
    out[:3, :3] = R @ out[:3, :3]  # rotate about the object's own position, then shift it
    out[:3, 3] += direction / np.linalg.norm(direction) * rng.uniform(0, max_translation)
    return out


def _check_number(name: str, value, low: float, strict: bool = False) -> None:
    ok = isinstance(value, int | float | np.integer | np.floating) and not isinstance(value, bool)
    if not ok or not np.isfinite(value) or (value <= low if strict else value < low):
        raise ValueError(f"{name} must be a finite number {'>' if strict else '≥'} {low:g}, got {value!r}")


def _check_count(name: str, value, low: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < low:
        raise ValueError(f"{name} must be an integer ≥ {low}, got {value!r}")


def _checked_pose(T, name: str) -> np.ndarray:
    """A (4, 4) rigid transform: finite, rotation block in SO(3), last row (0, 0, 0, 1)."""
    T = checked_array(T, name)
    if T.shape != (4, 4):
        raise ValueError(f"{name} must be a (4, 4) matrix, got shape {T.shape}")
    checked_rotation(T[:3, :3], f"{name}[:3, :3]")
    if not np.allclose(T[3], [0, 0, 0, 1]):
        raise ValueError(f"{name} must have last row (0, 0, 0, 1), got {T[3].tolist()}")
    return T
