"""The flow cue's room: optical flow t → t+1 turned into 2D-3D correspondences at t+1 (Section III-B).

A pixel x of the object region at frame t sees the model point X(x) of the pose at t (the renderer's
per-pixel surface point, with its part). The flow carries it to x + w(x) in frame t+1, so
(x + w(x), X(x)) is a 2D-3D correspondence of the pose at t+1, weighted by the flow confidence c(x) of
eq. 8. The set is sampled on a regular grid of the crop (stride s), which fixes its capacity at
⌈h/s⌉·⌈w/s⌉ rows: the same compiled solver serves every frame.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ...geometry import Camera
from ...solve import Correspondences, Cue, correspondences_from_pixels


def flow_correspondences(
    camera: Camera,
    flow: jax.Array,
    confidence: jax.Array,
    valid: jax.Array,
    p_model: jax.Array,
    part: jax.Array,
    offset: jax.Array | None = None,
    stride: int = 4,
    camera_index: jax.Array | int = 0,
) -> Correspondences:
    """Correspondences at t+1 from the flow of the object pixels at t. Jittable; vmap over cameras.

    Args:
        camera: the (single) camera of these pixels; image coordinates are distorted pixels, undistorted
            here before the viewing rays are formed.
        flow: (h, w, 2) flow t → t+1 in pixels over a crop (or the whole frame).
        confidence: (h, w) c(x) of eq. 8; it becomes the raw weight (fused later by Section V).
        valid: (h, w) bool: inside the object region at t, not occluded (r(x) = 1), flow usable.
        p_model: (h, w, 3) model-frame surface point at t (renderer), part: (h, w) int32 its part.
        offset: (2,) int (y0, x0) of the crop in the frame (zeros for a full frame); traced, so a moving
            crop of one size class never recompiles.
        stride: grid step in pixels (static); capacity = ceil(h/stride) * ceil(w/stride).
        camera_index: camera id recorded in every row.

    Returns:
        `Correspondences` with cue FLOW, weight c(x) on valid grid pixels and 0 elsewhere.
    """
    h, w = flow.shape[:2]
    offset = jnp.zeros((2,), jnp.int32) if offset is None else jnp.asarray(offset)
    ys = jnp.arange(0, h, stride)
    xs = jnp.arange(0, w, stride)
    gy, gx = jnp.meshgrid(ys, xs, indexing="ij")
    gy, gx = gy.reshape(-1), gx.reshape(-1)
    dtype = flow.dtype
    w_t1 = flow[gy, gx]
    pixel = jnp.stack([gx + offset[1], gy + offset[0]], -1).astype(dtype) + w_t1
    weight = jnp.where(valid[gy, gx], confidence[gy, gx], 0.0).astype(dtype)
    weight = jnp.where(jnp.all(jnp.isfinite(w_t1), -1), weight, 0.0)
    index = jnp.broadcast_to(jnp.asarray(camera_index, jnp.int32), weight.shape)
    corr = correspondences_from_pixels(
        camera, jnp.nan_to_num(pixel), index, p_model[gy, gx].astype(dtype), part[gy, gx], weight, cue=Cue.FLOW
    )
    return corr
