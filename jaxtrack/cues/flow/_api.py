"""Host-side entry points built on the jitted flow solver: bidirectional flow and the ROI mode."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike, DTypeLike

from ..._status import Status, first_failure
from ._consistency import forward_backward_consistency
from ._energy import FlowEnergyParams
from ._solver import (
    FlowConfig,
    FlowResult,
    check_flow_inputs,
    check_flow_params,
    checked_result,
    default_beta,
    flow_core,
    weight_and_region,
)

# Side lengths of the static crop classes of the ROI mode (≈ √2 apart, multiples of 16).
ROI_SIZES = (32, 48, 64, 96, 128, 176, 256, 352, 512, 704, 1024, 1408, 2048)


class BidirectionalFlow(eqx.Module):
    """Forward and backward flow with their forward-backward consistency masks.

    Attributes:
        forward: `FlowResult` frame 1 → frame 2.
        backward: `FlowResult` frame 2 → frame 1.
        consistent_forward: (H, W) bool, forward flow passes the round-trip test.
        consistent_backward: (H, W) bool, the same for the backward flow.
        status: int32 `jaxtrack.Status`, the first failure of the two directions (the masks are
            all False when it is not OK).
    """

    forward: FlowResult
    backward: FlowResult
    consistent_forward: jax.Array
    consistent_backward: jax.Array
    status: jax.Array


@eqx.debug.assert_max_traces(max_traces=None)  # counts traces (`eqx.debug.get_num_traces`), never fails
def _bidirectional_body(img1, img2, params, config, r1, r2, om1, om2, beta, dtype, a1, a2):
    # Both directions in one vmapped solve: the same compiled program, twice the batch.
    imgs_a = jnp.stack([img1, img2])
    imgs_b = jnp.stack([img2, img1])
    res = jax.vmap(lambda a, b, r, om: flow_core(a, b, params, config, r, om, None, beta, dtype))(
        imgs_a, imgs_b, jnp.stack([r1, r2]), jnp.stack([om1, om2])
    )
    fw = jax.tree.map(lambda x: x[0], res)
    bw = jax.tree.map(lambda x: x[1], res)
    status = first_failure(fw.status, bw.status)
    ok = status == Status.OK  # zero flows would pass the round-trip test: a failure is never consistent
    return BidirectionalFlow(
        fw,
        bw,
        ok & forward_backward_consistency(fw.flow, bw.flow, a1, a2),
        ok & forward_backward_consistency(bw.flow, fw.flow, a1, a2),
        status,
    )


_bidirectional_jit = eqx.filter_jit(_bidirectional_body)


def compute_flow_bidirectional(
    img1: ArrayLike,
    img2: ArrayLike,
    params: FlowEnergyParams,
    config: FlowConfig | None = None,
    data_weight: ArrayLike | None = None,
    region: ArrayLike | None = None,
    region2: ArrayLike | None = None,
    beta: ArrayLike | None = None,
    a1: ArrayLike = 0.01,
    a2: ArrayLike = 0.5,
    dtype: DTypeLike = jnp.float32,
    throw: bool = True,
) -> BidirectionalFlow:
    """Flow 1 → 2 and 2 → 1 plus the forward-backward consistency masks (Sundaram et al. 2010).

    Args:
        img1, img2: (H, W) or (H, W, C) frames, 0-255 scale.
        config: the minimiser's static settings (default `FlowConfig()`).
        data_weight: optional (H, W) r(x) of frame 1 (the backward flow uses r = 1).
        region, region2: optional (H, W) bool Ω1 in frame 1 and in frame 2 (default: whole image).
        a1, a2: consistency tolerances (≥ 0; arrays inside the program, so new values do not recompile).
        throw: raise `StatusError` when either direction failed (else the status comes back).

    Raises:
        ValueError: as `compute_flow`, and for negative tolerances.
    """
    config = FlowConfig() if config is None else config
    check_flow_inputs(img1, img2, data_weight, region, where="compute_flow_bidirectional")
    check_flow_inputs(img1, img2, None, region2, where="compute_flow_bidirectional")
    check_flow_params(params, where="compute_flow_bidirectional")
    for name, tol in (("a1", a1), ("a2", a2)):
        if not isinstance(tol, jax.core.Tracer) and not np.all(np.asarray(tol, np.float64) >= 0):
            raise ValueError(f"compute_flow_bidirectional: {name} must be ≥ 0, got {tol}")
    r1, om1 = weight_and_region(jnp.shape(img1)[:2], data_weight, region, dtype)
    ones, om2 = weight_and_region(jnp.shape(img1)[:2], None, region2, dtype)
    beta = default_beta(params) if beta is None else beta
    out = _bidirectional_jit(
        jnp.asarray(img1), jnp.asarray(img2), params, config, r1, ones, om1, om2, jnp.asarray(beta, dtype), dtype,
        jnp.asarray(a1, dtype), jnp.asarray(a2, dtype),
    )
    return checked_result(out, throw, "compute_flow_bidirectional")


def roi_crop(region: ArrayLike, margin: int, sizes: tuple[int, ...] = ROI_SIZES) -> tuple[int, int, int, int]:
    """Crop (y0, x0, height, width) of a static size class around the region's bounding box.

    The box is grown by `margin` pixels on every side and each side is rounded up to the next class
    in `sizes` (capped at the image side), so that a moving object changes the crop's size, and
    with it the compiled program, only when it crosses a class boundary.

    Raises:
        ValueError: when the region is empty.
    """
    reg = np.asarray(region, bool)
    if reg.ndim != 2:
        raise ValueError(f"roi_crop: region must be (H, W), got shape {reg.shape}")
    rows, cols = np.flatnonzero(reg.any(1)), np.flatnonzero(reg.any(0))
    if rows.size == 0:
        raise ValueError("roi_crop: the region is empty; there is nothing to compute flow for")
    H, W = reg.shape

    def side(lo, hi, n):
        need = hi - lo + 1 + 2 * margin
        size = next((s for s in sizes if s >= need), need)
        size = min(size, n)
        start = int(np.clip((lo + hi + 1) // 2 - size // 2, 0, n - size))
        return start, size

    y0, ch = side(rows[0], rows[-1], H)
    x0, cw = side(cols[0], cols[-1], W)
    return y0, x0, ch, cw


@eqx.debug.assert_max_traces(max_traces=None)  # counts traces (`eqx.debug.get_num_traces`), never fails
def _roi_body(img1, img2, params, config, r, om, init, offset, beta, dtype, crop_shape):
    ch, cw = crop_shape
    y0, x0 = offset[0], offset[1]

    def crop(a):
        zero = jnp.zeros((), y0.dtype)
        return jax.lax.dynamic_slice(a, (y0, x0) + (zero,) * (a.ndim - 2), (ch, cw) + a.shape[2:])

    res = flow_core(crop(img1), crop(img2), params, config, crop(r), crop(om), None if init is None else crop(init), beta, dtype)

    def paste(full_like, part):
        zero = jnp.zeros((), y0.dtype)
        return jax.lax.dynamic_update_slice(full_like, part, (y0, x0) + (zero,) * (part.ndim - 2))

    h, w = img1.shape[:2]
    return FlowResult(
        paste(jnp.zeros((h, w, 2), res.flow.dtype), res.flow),
        paste(jnp.zeros((h, w), res.local_energy.dtype), res.local_energy),
        paste(jnp.zeros((h, w), res.confidence.dtype), res.confidence),
        paste(jnp.zeros((h, w), bool), res.region),
        res.status,
    )


_roi_jit = eqx.filter_jit(_roi_body)


def compute_flow_roi(
    img1: ArrayLike,
    img2: ArrayLike,
    params: FlowEnergyParams,
    region: ArrayLike,
    config: FlowConfig | None = None,
    data_weight: ArrayLike | None = None,
    init_flow: ArrayLike | None = None,
    margin: int = 16,
    beta: ArrayLike | None = None,
    dtype: DTypeLike = jnp.float32,
    throw: bool = True,
) -> tuple[FlowResult, tuple[int, int, int, int]]:
    """Flow inside Ω1 computed on a padded crop around it (the tracker's mode).

    Only the crop is solved; it has one of a few static sizes (`ROI_SIZES`), so a tracked object
    compiles once per size class, not once per frame. Results are pasted into full-frame arrays
    (zero outside the crop and outside Ω1).

    Args:
        region: (H, W) bool Ω1 (required, non-empty).
        config: the minimiser's static settings (default `FlowConfig()`).
        margin: pixels of context around the region's bounding box.
        throw: raise `StatusError` when `FlowResult.status` is a failure (else return it with zeros).

    Returns:
        (`FlowResult` of full-frame arrays, crop (y0, x0, height, width)).

    Raises:
        ValueError: as `compute_flow`, and for an empty region.
    """
    config = FlowConfig() if config is None else config
    check_flow_inputs(img1, img2, data_weight, region, init_flow, where="compute_flow_roi")
    check_flow_params(params, where="compute_flow_roi")
    box = roi_crop(region, margin)
    r, _ = weight_and_region(jnp.shape(img1)[:2], data_weight, None, dtype)
    beta = default_beta(params) if beta is None else beta
    offset = jnp.asarray(box[:2], jnp.int32)
    res = _roi_jit(
        jnp.asarray(img1), jnp.asarray(img2), params, config, r, jnp.asarray(region, bool),
        None if init_flow is None else jnp.asarray(init_flow, dtype), offset, jnp.asarray(beta, dtype), dtype, box[2:],
    )
    return checked_result(res, throw, "compute_flow_roi"), box
