"""Calibrated pinhole cameras with OpenCV's distortion model; several cameras batch on a leading axis.

Pixel centres sit at integer coordinates (OpenCV). `T_cam_world` maps world coordinates to camera
coordinates (BOP's cam_R_w2c, cam_t_w2c). Distortion coefficients follow OpenCV's order
(k1, k2, p1, p2, k3); zeros mean an ideal pinhole.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._lie import make_transform, se3_inverse, transform_points


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


def make_camera(K, width: int, height: int, R_cam_world=None, t_cam_world=None, dist=None, dtype=jnp.float32):
    """Validated `Camera` from numpy-like inputs (world = camera when extrinsics are omitted).

    Raises:
        ValueError: naming the field whose shape or values are wrong.
    """
    K = np.asarray(K, np.float64)
    if K.shape == (9,):
        K = K.reshape(3, 3)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise ValueError(f"camera K must be a finite 3x3 matrix (or 9 values), got shape {K.shape}")
    if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0, 0, 1]):
        raise ValueError(f"camera K must have fx, fy > 0 and last row (0, 0, 1), got {K.tolist()}")
    if int(width) <= 0 or int(height) <= 0:
        raise ValueError(f"camera image size must be positive, got {width}x{height}")
    R = np.eye(3) if R_cam_world is None else np.asarray(R_cam_world, np.float64).reshape(-1)
    if R.size != 9:
        raise ValueError(f"camera R_cam_world must have 9 values, got {R.size}")
    R = R.reshape(3, 3)
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0:
        raise ValueError("camera R_cam_world is not a rotation matrix (RᵀR ≠ I or det < 0)")
    t = np.zeros(3) if t_cam_world is None else np.asarray(t_cam_world, np.float64).reshape(-1)
    if t.shape != (3,) or not np.all(np.isfinite(t)):
        raise ValueError(f"camera t_cam_world must be 3 finite values, got shape {t.shape}")
    d = np.zeros(5) if dist is None else np.asarray(dist, np.float64).reshape(-1)
    if d.size > 5 or not np.all(np.isfinite(d)):
        raise ValueError(f"camera dist must be at most 5 finite OpenCV coefficients (k1,k2,p1,p2,k3), got {d.size}")
    d = np.concatenate([d, np.zeros(5 - d.size)])
    return Camera(
        K=jnp.asarray(K, dtype),
        T_cam_world=make_transform(jnp.asarray(R, dtype), jnp.asarray(t, dtype)),
        dist=jnp.asarray(d, dtype),
        width=int(width),
        height=int(height),
    )


def stack_cameras(cameras) -> Camera:
    """Stack cameras of one image size into a batched `Camera` with leading axis C."""
    cameras = list(cameras)
    if not cameras:
        raise ValueError("stack_cameras needs at least one camera")
    sizes = {(c.width, c.height) for c in cameras}
    if len(sizes) != 1:
        raise ValueError(f"cameras of a rig must share one image size, got {sorted(sizes)}")
    return jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *cameras)


def select_camera(cameras: Camera, index) -> Camera:
    """Camera `index` of a stacked rig (works with a traced index)."""
    return jax.tree_util.tree_map(lambda x: x[index], cameras)


def _distort_normalized(xy, dist):
    """OpenCV's radial-tangential model on normalised coordinates (..., 2)."""
    k1, k2, p1, p2, k3 = dist[..., 0:1], dist[..., 1:2], dist[..., 2:3], dist[..., 3:4], dist[..., 4:5]
    x, y = xy[..., 0:1], xy[..., 1:2]
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return jnp.concatenate([x * radial + dx, y * radial + dy], axis=-1)


def project_points(camera: Camera, p_world):
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


def normalized_to_pixels(camera: Camera, xy):
    """K on normalised image coordinates. (..., 2) -> (..., 2); camera dims broadcast with xy[..., 0]."""
    K = camera.K
    u = K[..., 0, 0] * xy[..., 0] + K[..., 0, 1] * xy[..., 1] + K[..., 0, 2]
    v = K[..., 1, 1] * xy[..., 1] + K[..., 1, 2]
    return jnp.stack([u, v], axis=-1)


def pixels_to_normalized(camera: Camera, px):
    """K⁻¹ on pixels without removing distortion. (..., 2) -> (..., 2)."""
    K = camera.K
    y = (px[..., 1] - K[..., 1, 2]) / K[..., 1, 1]
    x = (px[..., 0] - K[..., 0, 2] - K[..., 0, 1] * y) / K[..., 0, 0]
    return jnp.stack([x, y], axis=-1)


def undistort_points(camera: Camera, px, iterations: int = 20):
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
        k1, k2, p1, p2, k3 = (dist[..., i : i + 1] for i in range(5))
        x, y = xy[..., 0:1], xy[..., 1:2]
        r2 = x * x + y * y
        radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
        dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return jnp.concatenate([(xy_d[..., 0:1] - dx) / radial, (xy_d[..., 1:2] - dy) / radial], axis=-1)

    return normalized_to_pixels(camera, jax.lax.fori_loop(0, iterations, step, xy_d))


def backproject_pixels(camera: Camera, px, depth):
    """Ideal (undistorted) pixels with camera-frame depth z to world points. px (..., 2), depth (...)."""
    xy = pixels_to_normalized(camera, px)
    p_cam = jnp.concatenate([xy * depth[..., None], depth[..., None]], axis=-1)
    return transform_points(se3_inverse(camera.T_cam_world), p_cam)


def pixel_rays_world(camera: Camera, px):
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
