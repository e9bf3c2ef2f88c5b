"""Static-size windows at traced offsets: a crop class compiles once, wherever the object moves."""

from __future__ import annotations

import jax
import jax.numpy as jnp


def crop_window(image: jax.Array, offset: jax.Array, shape: tuple[int, int]) -> jax.Array:
    """image[y0 : y0 + h, x0 : x0 + w] for (H, W, ...) `image`, traced `offset` = (y0, x0), static `shape`.

    Like `lax.dynamic_slice`, a window reaching past the border is shifted back inside the image.
    """
    zero = jnp.zeros((), jnp.int32)
    start = (jnp.asarray(offset[0], jnp.int32), jnp.asarray(offset[1], jnp.int32)) + (zero,) * (image.ndim - 2)
    return jax.lax.dynamic_slice(image, start, tuple(shape) + image.shape[2:])


def paste_window(full: jax.Array, part: jax.Array, offset: jax.Array) -> jax.Array:
    """`full` with `part` written at traced `offset` = (y0, x0) (the inverse of `crop_window`)."""
    zero = jnp.zeros((), jnp.int32)
    start = (jnp.asarray(offset[0], jnp.int32), jnp.asarray(offset[1], jnp.int32)) + (zero,) * (part.ndim - 2)
    return jax.lax.dynamic_update_slice(full, part.astype(full.dtype), start)


# --- scaled windows: a fixed working resolution whatever the object's size on screen ----------------
#
# Window pixel (i, j) of a window with top-left `offset` (y0, x0) and `scale` s (full-frame pixels per
# window pixel) sits at full-frame position (y0 + s·(i + ½) − ½, x0 + s·(j + ½) − ½): with s = 1 and an
# integer offset it is pixel (y0 + i, x0 + j) and the functions below reduce to `crop_window` /
# `paste_window` (exactly: bilinear weights 1 and 0).


def window_to_full(points, offset, scale):
    """(..., 2) (x, y) window pixels → full-frame pixels of the window (`offset` (y0, x0), `scale` s)."""
    shift = jnp.stack([offset[..., 1], offset[..., 0]], -1).astype(points.dtype)
    s = jnp.asarray(scale, points.dtype)[..., None]
    return shift + s * (points + 0.5) - 0.5


def full_to_window(points, offset, scale):
    """(..., 2) (x, y) full-frame pixels → window pixels (the inverse of `window_to_full`)."""
    shift = jnp.stack([offset[..., 1], offset[..., 0]], -1).astype(points.dtype)
    s = jnp.asarray(scale, points.dtype)[..., None]
    return (points + 0.5 - shift) / s - 0.5


def _axis_taps(start, scale, n: int, size: int, antialias: bool, dtype):
    """Source indices (n, k) and weights (n, k) along one axis for window pixels 0..n−1 (k = 2 bilinear taps, or
    4 with the antialiasing box: two bilinear taps at ±(s − 1)/2), clamped to [0, size − 1]."""
    s = jnp.asarray(scale, dtype)
    centre = jnp.asarray(start, dtype) + s * (jnp.arange(n, dtype=dtype) + 0.5) - 0.5
    d = jnp.maximum(s - 1.0, 0.0) / 2 if antialias else jnp.zeros((), dtype)
    positions = [centre - d, centre + d] if antialias else [centre]
    idx, wts = [], []
    for pos in positions:
        pos = jnp.clip(pos, 0.0, size - 1.0)
        lo = jnp.floor(pos)
        f = pos - lo
        lo = lo.astype(jnp.int32)
        idx += [lo, jnp.minimum(lo + 1, size - 1)]
        wts += [(1 - f) / len(positions), f / len(positions)]
    return jnp.stack(idx, -1), jnp.stack(wts, -1)


def sample_window(image, offset, scale, shape: tuple[int, int], antialias: bool = True, dtype=jnp.float32):
    """The (h, w, ...) window `shape` of an (H, W, ...) image at traced `offset` (y0, x0) and `scale` s. Jittable.

    Bilinear; with `antialias` the mean of four bilinear taps at ±(s − 1)/2 on both axes (for s = 2
    exactly the 2x2 box of full-frame pixels under the window pixel; for s ≤ 1 one tap). Separable: whole
    rows are gathered first (contiguous copies), then the columns of the h rows (a matrix product; about
    0.7 ms for a 96x128 window of a 640x480 RGB frame on 2 cores, against 10 ms per-element). Positions outside the
    image read the border. One compiled program serves every offset and scale; the image may be uint8
    (the samples are cast to `dtype`).
    """
    h, w = shape
    H, W = image.shape[:2]
    iy, wy = _axis_taps(offset[0], scale, h, H, antialias, dtype)  # (h, k)
    ix, wx = _axis_taps(offset[1], scale, w, W, antialias, dtype)  # (w, k)
    flat = image.reshape(H, W, -1)
    rows = flat[iy.reshape(-1)].astype(dtype).reshape(h, iy.shape[1], W, flat.shape[-1])  # whole rows: cheap copies
    rows = jnp.einsum("yk,ykXc->yXc", wy, rows)
    # Columns as a (w, W) interpolation matrix: a product, where a gather along the second axis is slow on the CPU.
    cols = jnp.zeros((w, W), dtype).at[jnp.arange(w)[:, None], ix].add(wx)
    return jnp.einsum("yXc,xX->yxc", rows, cols).reshape((h, w) + image.shape[2:])


def paste_window_scaled(full, part, offset, scale):
    """`full` (H, W, ...) with window `part` (h, w, ...) written back at traced `offset` / `scale`: each full-frame
    pixel inside the window takes its nearest window pixel, the others keep `full` (the inverse of
    `sample_window` up to resampling). Jittable."""
    H, W = full.shape[:2]
    h, w = part.shape[:2]
    s = jnp.asarray(scale, jnp.float32)
    i = (jnp.arange(H, dtype=jnp.float32) + 0.5 - jnp.asarray(offset[0], jnp.float32)) / s - 0.5
    j = (jnp.arange(W, dtype=jnp.float32) + 0.5 - jnp.asarray(offset[1], jnp.float32)) / s - 0.5
    ii, jj = jnp.floor(i + 0.5).astype(jnp.int32), jnp.floor(j + 0.5).astype(jnp.int32)
    in_y, in_x = (ii >= 0) & (ii < h), (jj >= 0) & (jj < w)
    picked = part[jnp.clip(ii, 0, h - 1)[:, None], jnp.clip(jj, 0, w - 1)[None, :]]
    inside = (in_y[:, None] & in_x[None, :]).reshape((H, W) + (1,) * (full.ndim - 2))
    return jnp.where(inside, picked.astype(full.dtype), full)
