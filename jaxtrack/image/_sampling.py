"""Bilinear sampling and warping of (H, W, C) images at real positions (pixel centres at integers)."""

from __future__ import annotations

import jax.numpy as jnp


def sample_bilinear(img, x, y, size=None):
    """img at real positions (x, y): (H, W, C) img, x and y of any shape S → (S + (C,), S mask).

    Positions are clamped to the image (border replication); the mask says which lay inside.
    With `size` = (h, w) (integer scalars, may be traced) only the top-left h x w part of img is the
    image: positions are clamped to it and the mask says which lay inside it (the rest is padding).
    """
    h, w = img.shape[:2] if size is None else size
    inside = (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
    x = jnp.clip(x, 0, w - 1)
    y = jnp.clip(y, 0, h - 1)
    x0 = jnp.clip(jnp.floor(x), 0, w - 2).astype(jnp.int32)
    y0 = jnp.clip(jnp.floor(y), 0, h - 2).astype(jnp.int32)
    fx = (x - x0)[..., None]
    fy = (y - y0)[..., None]
    top = img[y0, x0] * (1 - fx) + img[y0, x0 + 1] * fx
    bottom = img[y0 + 1, x0] * (1 - fx) + img[y0 + 1, x0 + 1] * fx
    return top * (1 - fy) + bottom * fy, inside


def sample_bilinear_flat(img, x, y):
    """`sample_bilinear` of a one-channel (H, W) image at real positions x, y of any shape S: (S values, S mask),
    the same values, read through flat indices (four 1-D takes of the raveled image).

    XLA:CPU runs a gather with two computed indices per point several times slower than a 1-D take of the same
    points (measured on the appearance model's texels, `jaxtrack.cues.occlusion.observe_texels`)."""
    h, w = img.shape
    inside = (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
    x = jnp.clip(x, 0, w - 1)
    y = jnp.clip(y, 0, h - 1)
    x0 = jnp.clip(jnp.floor(x), 0, w - 2).astype(jnp.int32)
    y0 = jnp.clip(jnp.floor(y), 0, h - 2).astype(jnp.int32)
    fx = x - x0
    fy = y - y0
    flat = img.reshape(-1)
    k = y0 * w + x0
    top = jnp.take(flat, k, mode="clip") * (1 - fx) + jnp.take(flat, k + 1, mode="clip") * fx
    bottom = jnp.take(flat, k + w, mode="clip") * (1 - fx) + jnp.take(flat, k + w + 1, mode="clip") * fx
    return top * (1 - fy) + bottom * fy, inside


def warp_bilinear(img, flow):
    """img(x + w) for (H, W, C) img and (H, W, 2) flow, coordinates clamped; also the in-image mask."""
    h, w = img.shape[:2]
    gy, gx = jnp.meshgrid(jnp.arange(h, dtype=flow.dtype), jnp.arange(w, dtype=flow.dtype), indexing="ij")
    return sample_bilinear(img, gx + flow[..., 0], gy + flow[..., 1])
