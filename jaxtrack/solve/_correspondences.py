"""Padded sets of 2D-3D correspondences: what every cue hands to the pose solver.

Each row ties an observed pixel of camera c (as the Plücker line of its viewing ray, world frame,
eq. 3) to a model point X on part p (model frame, zero configuration) with a weight w ≥ 0. Sets have
a fixed capacity; unused rows carry w = 0, so any number of matches up to the capacity shares one
compiled solver (DESIGN.md, static shapes).

Edge rows. A contour match (eq. 14) says where the silhouette edge lies across the edge, not where
along it the model point goes: its displacement is along the contour normal by construction. A point
row (the paper's |X × n − m|², eq. 4) nevertheless pins the point along the edge too, which holds
back every motion with a component along the contour (ICP's point-to-point slowness: measured, the
pose moved less than half the way per refinement round and the residual to the targets did not
drop). An edge row carries the unit normal of the plane through the viewing ray and the image edge
(world frame): its residual across the edge has weight 1 and the one along the edge `tangent_weight`
(0: point-to-plane; 1: exactly the point row).
"""

from __future__ import annotations

import enum

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..geometry import Camera, pixel_rays_world, plucker_from_ray, select_camera, undistort_points


class Cue(enum.IntEnum):
    """Which cue produced a correspondence row (recorded per row; the solver never looks at it)."""

    UNKNOWN = 0  # given by the user (e.g. `make_correspondences`)
    REGION = 1  # contour matches of the level-set segmentation (eq. 14-15)
    FLOW = 2  # optical flow (eq. 6-8)
    SIFT = 3  # SIFT keypoint matches
    LINES = 4  # correspondence lines across the model contour (the sparse region modality)


class Correspondences(eqx.Module):
    """N (= capacity) correspondences, padded rows with zero weight.

    Attributes:
        n: (N, 3) unit direction of the viewing ray, world frame (Plücker n, eq. 3).
        m: (N, 3) moment of the viewing ray, world frame (Plücker m = origin × n).
        p_model: (N, 3) model point on its part, model frame at Θ = 0 (mm).
        part: (N,) int32 part index of the model point.
        camera: (N,) int32 camera that observed the pixel.
        pixel: (N, 2) the ideal (undistorted) pixel, kept for drawing and reprojection errors.
        weight: (N,) ≥ 0, zero for padding.
        cue: (N,) int32 `Cue` that produced the row (for counts, plots and per-cue weights only).
        normal: (N, 3) world-frame unit normal of the plane through the viewing ray and the observed
            image edge (⊥ n) for an edge row; zero for a point row.
        tangent_weight: (N,) factor on the squared residual along the edge (1 for point rows).

    `normal` and `tangent_weight` default to point rows (zeros and ones).
    """

    n: jax.Array
    m: jax.Array
    p_model: jax.Array
    part: jax.Array
    camera: jax.Array
    pixel: jax.Array
    weight: jax.Array
    cue: jax.Array
    normal: jax.Array | None = None
    tangent_weight: jax.Array | None = None

    def __post_init__(self):
        # Point rows unless told otherwise: sets built by hand need not know about edge rows.
        if self.normal is None:
            self.normal = jnp.zeros(jnp.shape(self.n), jnp.result_type(self.n))
        if self.tangent_weight is None:
            self.tangent_weight = jnp.ones(jnp.shape(self.weight), jnp.result_type(self.n))

    @property
    def capacity(self) -> int:
        return self.weight.shape[-1]

    def num_effective(self):
        """Number of rows with positive weight (traced scalar)."""
        return jnp.sum(self.weight > 0, axis=-1)

    def count_by_cue(self, cue) -> jax.Array:
        """Number of rows with positive weight produced by `cue` (traced scalar)."""
        return jnp.sum((self.weight > 0) & (self.cue == cue), axis=-1)

    def with_weight(self, weight) -> Correspondences:
        """The same set with new weights (e.g. a cue-weight sweep under vmap)."""
        return eqx.tree_at(lambda c: c.weight, self, jnp.asarray(weight, self.weight.dtype))


@eqx.filter_jit
def correspondences_from_pixels(
    cameras: Camera, pixel, camera_index, p_model, part, weight, undistort: bool = True, cue=Cue.UNKNOWN,
    edge_normal=None, tangent_weight=None,
):
    """Jittable builder: pixels (+ camera per row) and model points to a correspondence set.

    No checks (use `make_correspondences` at the API edge). Shapes are kept: pad first.

    Args:
        cameras: stacked rig (C cameras on a leading axis) or a single camera.
        pixel: (N, 2) observed pixels (distorted if the camera has distortion and `undistort`).
        camera_index: (N,) int camera of each pixel (ignored for a single camera).
        p_model: (N, 3) model-frame points; part: (N,) int; weight: (N,).
        cue: `Cue` of every row (scalar) or (N,) per row.
        edge_normal: optional (N, 2) image direction across the edge each pixel lies on (any length;
            zero rows stay point rows): the rows become edge rows (see the module docstring).
        tangent_weight: optional scalar or (N,) weight of the residual along the edge (default 1).
    """
    cam_rows = select_camera(cameras, camera_index) if cameras.K.ndim == 3 else cameras
    pixel = jnp.asarray(pixel)
    ideal = undistort_points(cam_rows, pixel) if undistort else pixel
    origin, direction = pixel_rays_world(cam_rows, ideal)
    n, m = plucker_from_ray(origin, direction)
    if edge_normal is None:
        normal = jnp.zeros_like(n)
    else:
        # The plane through the camera centre, the ray of the pixel and the ray of a point one pixel
        # along the edge (the edge is perpendicular to edge_normal).
        e = jnp.asarray(edge_normal, pixel.dtype)
        length = jnp.linalg.norm(e, axis=-1, keepdims=True)
        along = jnp.stack([-e[..., 1], e[..., 0]], -1) / jnp.where(length > 0, length, 1.0)
        other = undistort_points(cam_rows, pixel + along) if undistort else pixel + along
        _, direction2 = pixel_rays_world(cam_rows, other)
        t = jnp.cross(direction, direction2)
        t_norm = jnp.linalg.norm(t, axis=-1, keepdims=True)
        normal = jnp.where((length > 0) & (t_norm > 0), t / jnp.where(t_norm > 0, t_norm, 1.0), 0.0)
    tw = jnp.ones(jnp.shape(weight), n.dtype) if tangent_weight is None else jnp.broadcast_to(
        jnp.asarray(tangent_weight, n.dtype), jnp.shape(weight))
    return Correspondences(
        n=n,
        m=m,
        p_model=jnp.asarray(p_model, n.dtype),
        part=jnp.asarray(part, jnp.int32),
        camera=jnp.asarray(camera_index, jnp.int32),
        pixel=ideal,
        weight=jnp.asarray(weight, n.dtype),
        cue=jnp.broadcast_to(jnp.asarray(cue, jnp.int32), jnp.shape(weight)),
        normal=normal.astype(n.dtype),
        tangent_weight=tw,
    )


def pad_rows(array, capacity: int, fill=0):
    """Pad a host array along axis 0 to `capacity` rows with `fill`."""
    array = np.asarray(array)
    pad = [(0, capacity - array.shape[0])] + [(0, 0)] * (array.ndim - 1)
    return np.pad(array, pad, constant_values=fill)


def make_correspondences(
    cameras: Camera,
    pixel,
    p_model,
    *,
    camera_index=None,
    part=None,
    weight=None,
    capacity: int | None = None,
    num_parts: int | None = None,
    undistort: bool = True,
) -> Correspondences:
    """Validated, padded correspondence set from variable-length host arrays (API edge).

    Args:
        cameras: one camera or a stacked rig of C cameras.
        pixel: (n, 2) observed pixels.
        p_model: (n, 3) model points (mm, model frame at the zero configuration).
        camera_index: (n,) camera per row (default 0).
        part: (n,) part per row (default 0).
        weight: (n,) non-negative weights (default 1).
        capacity: padded size N ≥ n (default n); keep it fixed to avoid recompiling.
        num_parts: if given, part indices are checked against it.

    Raises:
        ValueError: naming the argument with a wrong shape, a non-finite value, a negative weight,
            an index out of range, or more rows than the capacity.
    """
    pixel = np.asarray(pixel, np.float64)
    p_model = np.asarray(p_model, np.float64)
    if pixel.ndim != 2 or pixel.shape[1] != 2:
        raise ValueError(f"pixel must have shape (n, 2), got {pixel.shape}")
    count = pixel.shape[0]
    if p_model.shape != (count, 3):
        raise ValueError(f"p_model must have shape ({count}, 3) to match pixel, got {p_model.shape}")
    num_cameras = cameras.K.shape[0] if cameras.K.ndim == 3 else 1
    camera_index = np.zeros(count, np.int64) if camera_index is None else np.asarray(camera_index)
    part = np.zeros(count, np.int64) if part is None else np.asarray(part)
    weight = np.ones(count) if weight is None else np.asarray(weight, np.float64)
    for name, arr in (("camera_index", camera_index), ("part", part), ("weight", weight)):
        if arr.shape != (count,):
            raise ValueError(f"{name} must have shape ({count},) to match pixel, got {arr.shape}")
    for name, arr in (("pixel", pixel), ("p_model", p_model), ("weight", weight)):
        if not np.all(np.isfinite(arr)):
            bad = np.argwhere(~np.isfinite(arr.reshape(count, -1)).all(axis=1)).ravel()
            raise ValueError(f"{name} has non-finite values in rows {bad[:10].tolist()}")
    if np.any(weight < 0):
        raise ValueError(f"weight must be ≥ 0; rows {np.flatnonzero(weight < 0)[:10].tolist()} are negative")
    if np.any((camera_index < 0) | (camera_index >= num_cameras)):
        raise ValueError(f"camera_index must lie in [0, {num_cameras}) for a rig of {num_cameras} camera(s)")
    if np.any(part < 0) or (num_parts is not None and np.any(part >= num_parts)):
        raise ValueError(f"part must lie in [0, {num_parts}) ")
    capacity = count if capacity is None else int(capacity)
    if count > capacity:
        raise ValueError(f"{count} correspondences exceed the capacity {capacity}; raise the capacity")
    dtype = cameras.K.dtype
    return correspondences_from_pixels(
        cameras,
        jnp.asarray(pad_rows(pixel, capacity), dtype),
        jnp.asarray(pad_rows(camera_index, capacity), jnp.int32),
        jnp.asarray(pad_rows(p_model, capacity), dtype),
        jnp.asarray(pad_rows(part, capacity), jnp.int32),
        jnp.asarray(pad_rows(weight, capacity), dtype),
        undistort=undistort,
    )


def concatenate_correspondences(*sets: Correspondences) -> Correspondences:
    """Stack several sets (e.g. contour, flow and SIFT cues) into one of summed capacity."""
    return jax.tree_util.tree_map(lambda *xs: jnp.concatenate(xs, axis=0), *sets)
