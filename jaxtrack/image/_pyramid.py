"""Image pyramids for coarse-to-fine schemes: level shapes, anti-aliased downsampling, resampling.

Everything here works on (H, W, C) arrays with shapes known at trace time; the level shapes are
computed on the host (`pyramid_shapes`) so that each level is a static-shape computation.
Resampling is written as gathers along one axis at a time (cheap on XLA:CPU), not as the dense
interpolation matrices of `jax.image.resize`, which cost a matrix product per level.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from ._filters import gaussian_blur


def pyramid_shapes(height: int, width: int, eta: float, min_size: int, max_levels: int) -> list[tuple[int, int]]:
    """Level shapes, finest first: (H η^k, W η^k) rounded to even, while the short side is ≥ min_size.

    Even sides let the SOR solver split every level into its four parity sub-grids; H and W
    themselves must be even.

    Args:
        height, width: the finest level's shape.
        eta: downsampling factor per level, 0 < η < 1 (Brox et al. use 0.9-0.95).
        min_size: the coarsest level's short side is at least this (or the image's, if smaller).
        max_levels: cap on the number of levels.
    """
    if not 0.0 < eta < 1.0:
        raise ValueError(f"pyramid factor eta must lie in (0, 1), got {eta}")
    if height % 2 or width % 2:
        raise ValueError(f"pyramid_shapes needs even sides, got {height}x{width}")
    shapes = [(int(height), int(width))]
    k = 1
    while len(shapes) < max_levels:
        h, w = 2 * round(height * eta**k / 2), 2 * round(width * eta**k / 2)
        if min(h, w) < min_size:
            break
        if (h, w) != shapes[-1]:
            shapes.append((h, w))
        k += 1
    return shapes


def _resample_axis(img, n_out: int, axis: int):
    """Linear resampling along `axis` to n_out samples, pixel centres aligned, border clamped."""
    n_in = img.shape[axis]
    if n_in == n_out:
        return img
    if n_in == 2 * n_out:  # exactly halved: the taps are the pairs (2i, 2i+1) at ½ each (slices, no gather)
        pairs = img.reshape(img.shape[:axis] + (n_out, 2) + img.shape[axis + 1:])
        return jnp.mean(pairs, axis=axis + 1)
    if n_out == 2 * n_in and n_in > 1:  # exactly doubled: ¼ / ¾ of the neighbours, the border clamped
        first = jax.lax.slice_in_dim(img, 0, 1, axis=axis)
        last = jax.lax.slice_in_dim(img, n_in - 1, n_in, axis=axis)
        lo = jax.lax.slice_in_dim(img, 0, n_in - 1, axis=axis)
        hi = jax.lax.slice_in_dim(img, 1, n_in, axis=axis)
        prev = jnp.concatenate([first, lo], axis=axis)
        nxt = jnp.concatenate([hi, last], axis=axis)
        even, odd = 0.25 * prev + 0.75 * img, 0.75 * img + 0.25 * nxt
        both = jnp.stack([even, odd], axis=axis + 1)
        return both.reshape(img.shape[:axis] + (n_out,) + img.shape[axis + 1:])
    src = (np.arange(n_out, dtype=np.float64) + 0.5) * (n_in / n_out) - 0.5
    src = np.clip(src, 0.0, n_in - 1)
    i0 = np.minimum(np.floor(src).astype(np.int32), max(n_in - 2, 0))
    i1 = np.minimum(i0 + 1, n_in - 1)
    f = (src - i0).astype(np.float32)
    shape = [1] * img.ndim
    shape[axis] = n_out
    f = jnp.asarray(f, img.dtype).reshape(shape)
    return jnp.take(img, jnp.asarray(i0), axis=axis) * (1 - f) + jnp.take(img, jnp.asarray(i1), axis=axis) * f


def resize_bilinear(img, shape: tuple[int, int]):
    """Bilinear resampling of an (H, W, ...) array to `shape` = (H', W') (static), centres aligned."""
    return _resample_axis(_resample_axis(img, int(shape[0]), 0), int(shape[1]), 1)


def downsample(img, shape: tuple[int, int], eta: float, sigma0: float = 0.6):
    """One pyramid step: blur with σ = σ0 sqrt(η⁻² − 1) (anti-aliasing), then resample to `shape`."""
    sigma = sigma0 * math.sqrt(max(1.0 / eta**2 - 1.0, 0.0))
    return resize_bilinear(gaussian_blur(img, sigma), shape)


def upsample_flow(flow, shape: tuple[int, int]):
    """Resample an (h, w, 2) flow to `shape` and rescale its components to the finer pixel units."""
    h, w = flow.shape[:2]
    out = resize_bilinear(flow, shape)
    scale = jnp.asarray([shape[1] / w, shape[0] / h], flow.dtype)
    return out * scale
