"""Calibrated pinhole cameras with OpenCV's distortion model; several cameras batch on a leading axis.

Pixel centres sit at integer coordinates (OpenCV). `T_cam_world` maps world coordinates to camera
coordinates (BOP's cam_R_w2c, cam_t_w2c). Distortion coefficients follow OpenCV's order
(k1, k2, p1, p2, k3); zeros mean an ideal pinhole.
"""

from __future__ import annotations

from collections.abc import Iterable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import numpy.typing as npt
from jax.typing import ArrayLike, DTypeLike

from .._device import to_device
from ._lie import se3_inverse, transform_point_columns, transform_points
from ._validate import checked_array, checked_image_size, checked_intrinsics, checked_rotation


class Camera(eqx.Module):
    """One camera, or C cameras stacked on a leading axis (see `stack_cameras`).

    Attributes:
        K: (..., 3, 3) intrinsics [[fx, s, cx], [0, fy, cy], [0, 0, 1]].
        T_cam_world: (..., 4, 4) extrinsics, world → camera.
        dist: (..., 5) OpenCV distortion (k1, k2, p1, p2, k3).
        width, height: image size in pixels (static; shared by all cameras of a rig).
    """

    K: jax.Array
    T_cam_world: jax.Array
    dist: jax.Array
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)

    @property
    def center_world(self):
        """(..., 3) optical centre in world coordinates."""
        return se3_inverse(self.T_cam_world)[..., :3, 3]


def make_camera(
    K: npt.ArrayLike,
    width: int,
    height: int,
    R_cam_world: npt.ArrayLike | None = None,
    t_cam_world: npt.ArrayLike | None = None,
    dist: npt.ArrayLike | None = None,
    dtype: DTypeLike = jnp.float32,
) -> Camera:
    """Validated `Camera` from numpy-like inputs (world = camera when extrinsics are omitted).

    Args:
        K: (3, 3) or 9 intrinsics, fx, fy > 0, upper triangular, last row (0, 0, 1).
        width, height: image size in pixels (whole numbers > 0).
        R_cam_world: (3, 3) or 9 rotation world → camera (identity when None).
        t_cam_world: (3,) translation world → camera (zero when None).
        dist: up to 5 OpenCV coefficients (k1, k2, p1, p2, k3), zero-padded; None = ideal pinhole.
        dtype: a floating dtype for the arrays.

    Raises:
        ValueError: naming the argument whose shape or values are wrong.
    """
    if not jnp.issubdtype(dtype, jnp.floating):
        raise ValueError(f"make_camera: dtype must be a floating type, got {dtype!r}")
    K = checked_intrinsics(K, "camera K")
    width, height = checked_image_size(width, height, "camera image size")
    R = np.eye(3) if R_cam_world is None else checked_rotation(R_cam_world, "camera R_cam_world")
    t = np.zeros(3) if t_cam_world is None else checked_array(t_cam_world, "camera t_cam_world", size=3)
    d = np.zeros(5) if dist is None else checked_array(dist, "camera dist").reshape(-1)
    if d.size > 5:
        raise ValueError(f"camera dist must be at most 5 OpenCV coefficients (k1, k2, p1, p2, k3), got {d.size}")
    d = np.concatenate([d, np.zeros(5 - d.size)])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return Camera(
        K=to_device(K, dtype),
        T_cam_world=to_device(T, dtype),
        dist=to_device(d, dtype),
        width=width,
        height=height,
    )


def stack_cameras(cameras: Iterable[Camera]) -> Camera:
    """Stack cameras of one image size into a batched `Camera` with leading axis C."""
    cameras = list(cameras)
    if not cameras:
        raise ValueError("stack_cameras needs at least one camera")
    for i, c in enumerate(cameras):
        if not isinstance(c, Camera) or c.K.ndim != 2:
            raise ValueError(f"stack_cameras: cameras[{i}] must be a single Camera (from make_camera), got {type(c).__name__}")
    sizes = {(c.width, c.height) for c in cameras}
    if len(sizes) != 1:
        raise ValueError(f"cameras of a rig must share one image size, got {sorted(sizes)}")
    def stack(*xs):  # concrete arrays on the host (an eager jnp.stack compiles a program per field), tracers in jnp
        if any(isinstance(x, jax.core.Tracer) for x in xs):
            return jnp.stack(xs)
        return to_device(np.stack([np.asarray(x) for x in xs]))

    return jax.tree_util.tree_map(stack, *cameras)


def select_camera(cameras: Camera, index: ArrayLike) -> Camera:
    """Camera `index` of a stacked rig (works with a traced index)."""
    return jax.tree_util.tree_map(lambda x: x[index], cameras)


def project_ideal(cameras: Camera, p_world: ArrayLike, camera_index: ArrayLike | None = None):
    """Ideal (undistorted) pinhole pixels and depth of world points, each point in its own camera. Jittable.

    The pixels of 2D-3D rows are stored undistorted (`Correspondences.pixel`), so their reprojection errors
    compare against this projection, not `project_points` (which distorts).

    Args:
        cameras: a stacked rig (C cameras; `camera_index` picks each point's) or one unbatched camera.
        p_world: (N, 3) world points.
        camera_index: (N,) int camera of each point, in [0, C) (rig only; an index beyond the rig is clamped by the
            gather and a negative one wraps: clip it first where it can be out of range; ignored with one camera).

    Returns:
        (px (N, 2) pixels, z (N,) camera-frame depth); points behind a camera get a finite, meaningless
        pixel (z clamped to 1e-6 in the division), mask them by z.
    """
    if cameras.K.ndim == 3 and camera_index is None:
        raise ValueError("project_ideal: a stacked rig needs camera_index (the camera of each point)")
    cam = select_camera(cameras, camera_index) if cameras.K.ndim == 3 else cameras
    p_world = jnp.asarray(p_world)
    x, y, z = transform_point_columns(cam.T_cam_world, p_world[:, 0], p_world[:, 1], p_world[:, 2])
    safe_z = jnp.where(z > 1e-6, z, 1e-6)
    xn, yn = x / safe_z, y / safe_z
    K = cam.K
    return jnp.stack([K[..., 0, 0] * xn + K[..., 0, 1] * yn + K[..., 0, 2], K[..., 1, 1] * yn + K[..., 1, 2]], -1), z


def _distortion_terms(xy, dist):
    """OpenCV's radial-tangential model at normalised coordinates xy (..., 2): the radial factor
    (..., 1) and the tangential shift (..., 2), so that distorted = xy · radial + shift.

    The one place the polynomial is written; `project_points` applies it and `undistort_points`
    inverts it by fixed-point iteration.
    """
    k1, k2, p1, p2, k3 = (dist[..., i : i + 1] for i in range(5))
    x, y = xy[..., 0:1], xy[..., 1:2]
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return radial, jnp.concatenate([dx, dy], axis=-1)


def _distort_normalized(xy, dist):
    """OpenCV's radial-tangential model on normalised coordinates (..., 2)."""
    radial, shift = _distortion_terms(xy, dist)
    return xy * radial + shift


def project_points(camera: Camera, p_world: ArrayLike):
    """Project world points of one camera to pixels, distortion applied (as cv2.projectPoints).

    Args:
        camera: a single (unbatched) camera.
        p_world: (..., 3) points in world coordinates.

    Returns:
        (px (..., 2), depth (...,)) pixel coordinates and camera-frame z.
    """
    p_cam = transform_points(camera.T_cam_world, p_world)
    z = p_cam[..., 2]
    # Points behind the camera keep a finite, meaningless projection; callers mask them by depth.
    safe_z = jnp.where(jnp.abs(z) > 1e-9, z, 1e-9)
    xy = _distort_normalized(p_cam[..., :2] / safe_z[..., None], camera.dist)
    return normalized_to_pixels(camera, xy), z


def normalized_to_pixels(camera: Camera, xy: jax.Array):
    """K on normalised image coordinates. (..., 2) -> (..., 2); camera dims broadcast with xy[..., 0]."""
    K = camera.K
    u = K[..., 0, 0] * xy[..., 0] + K[..., 0, 1] * xy[..., 1] + K[..., 0, 2]
    v = K[..., 1, 1] * xy[..., 1] + K[..., 1, 2]
    return jnp.stack([u, v], axis=-1)


def pixels_to_normalized(camera: Camera, px: jax.Array):
    """K⁻¹ on pixels without removing distortion. (..., 2) -> (..., 2)."""
    K = camera.K
    y = (px[..., 1] - K[..., 1, 2]) / K[..., 1, 1]
    x = (px[..., 0] - K[..., 0, 2] - K[..., 0, 1] * y) / K[..., 0, 0]
    return jnp.stack([x, y], axis=-1)


def undistort_points(camera: Camera, px: jax.Array, iterations: int = 20):
    """Remove lens distortion from observed pixels, returning ideal pinhole pixels.

    Fixed-point inversion of the distortion model as in cv2.undistortPoints (which also iterates);
    works on a single camera or on per-point cameras with matching leading axes.

    Args:
        camera: camera(s) whose leading dims broadcast against px[..., 0].
        px: (..., 2) distorted pixel coordinates.
        iterations: fixed number of fixed-point steps (static).
    """
    xy_d = pixels_to_normalized(camera, px)
    dist = camera.dist

    def step(_, xy):
        # Solve xy_d = xy · radial(xy) + shift(xy) for xy with the terms frozen at the last iterate.
        radial, shift = _distortion_terms(xy, dist)
        return (xy_d - shift) / radial

    # A camera without distortion runs one step instead of the loop (a lax.cond at run time; under vmap
    # with per-element cameras it becomes a select and both sides run). At zero distortion that step
    # gives the fixed point exactly and its first derivatives too (the terms' xy-derivatives vanish
    # there), so gradients with respect to the distortion stay those of the loop.
    xy = jax.lax.cond(jnp.any(dist != 0), lambda: jax.lax.fori_loop(0, iterations, step, xy_d), lambda: step(0, xy_d))
    return normalized_to_pixels(camera, xy)


def backproject_pixels(camera: Camera, px: jax.Array, depth: jax.Array):
    """Ideal (undistorted) pixels with camera-frame depth z to world points. px (..., 2), depth (...)."""
    xy = pixels_to_normalized(camera, px)
    p_cam = jnp.concatenate([xy * depth[..., None], depth[..., None]], axis=-1)
    return transform_points(se3_inverse(camera.T_cam_world), p_cam)


def pixel_rays_world(camera: Camera, px: jax.Array):
    """Rays through ideal pixels: origin (..., 3) = optical centre and unit direction (..., 3), world frame.

    `camera` may be one camera or per-ray cameras whose leading dims match px[..., 0].
    """
    xy = pixels_to_normalized(camera, px)
    d_cam = jnp.concatenate([xy, jnp.ones_like(xy[..., :1])], axis=-1)
    R_world_cam = jnp.swapaxes(camera.T_cam_world[..., :3, :3], -1, -2)
    d_world = jnp.einsum("...ij,...j->...i", R_world_cam, d_cam)
    d_world = d_world / jnp.linalg.norm(d_world, axis=-1, keepdims=True)
    origin = jnp.broadcast_to(camera.center_world, d_world.shape)
    return origin, d_world


def _crop_camera_host(camera: Camera, offset: np.ndarray, crop_shape: tuple[int, int], scale=None) -> Camera:
    """`crop_camera` in numpy, the same arithmetic in the same dtype."""
    dt = camera.K.dtype
    oy, ox = offset[..., 0].astype(dt), offset[..., 1].astype(dt)
    K = np.array(camera.K, copy=True)
    if scale is None:
        K[..., 0, 2] -= ox
        K[..., 1, 2] -= oy
    else:
        s = np.asarray(scale, dt)
        K[..., 0, 2] = (camera.K[..., 0, 2] - ox + dt.type(0.5)) / s - dt.type(0.5)
        K[..., 1, 2] = (camera.K[..., 1, 2] - oy + dt.type(0.5)) / s - dt.type(0.5)
        K[..., :2, :2] = camera.K[..., :2, :2] / s[..., None, None]
    return Camera(K, camera.T_cam_world, camera.dist, width=crop_shape[1], height=crop_shape[0])


def crop_camera(camera: Camera, offset, crop_shape: tuple[int, int], scale=None) -> Camera:
    """The camera seeing only the window at `offset` = (..., 2) (y0, x0) with `scale` s (..., full-frame
    pixels per window pixel; None: 1) of static size `crop_shape` (jittable).

    The crop geometry of the tracker in one place: every modality and the renderer see the window through
    this camera. Window pixel (x, y) is full-frame pixel (x0 + s·(x + ½) − ½, y0 + s·(y + ½) − ½)
    (`jaxtrack.image.window_to_full`); with s = 1, pixels of the crop plus (x0, y0). Distortion is applied
    before K, so it is unchanged. With numpy arrays (camera, offset, scale) it runs on the host and returns
    a numpy `Camera` (host planning: no eager XLA programs).
    """
    if isinstance(camera.K, np.ndarray) and isinstance(offset, np.ndarray):
        return _crop_camera_host(camera, offset, crop_shape, scale)
    dt = camera.K.dtype
    oy, ox = offset[..., 0].astype(dt), offset[..., 1].astype(dt)
    if scale is None:
        K = camera.K.at[..., 0, 2].add(-ox)
        K = K.at[..., 1, 2].add(-oy)
        return Camera(K, camera.T_cam_world, camera.dist, width=crop_shape[1], height=crop_shape[0])
    s = jnp.asarray(scale, dt)
    K = camera.K.at[..., 0, 2].set((camera.K[..., 0, 2] - ox + 0.5) / s - 0.5)
    K = K.at[..., 1, 2].set((camera.K[..., 1, 2] - oy + 0.5) / s - 0.5)
    K = K.at[..., :2, :2].set(camera.K[..., :2, :2] / s[..., None, None])
    return Camera(K, camera.T_cam_world, camera.dist, width=crop_shape[1], height=crop_shape[0])
