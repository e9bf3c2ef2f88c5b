"""Separable Gaussian filtering of (H, W, C) arrays (σ static: it sets the number of taps)."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np


def gaussian_kernel(sigma: float) -> np.ndarray:
    """Normalised 1-D Gaussian taps, radius ceil(3σ) (a host constant; σ is static)."""
    radius = max(1, math.ceil(3.0 * sigma))
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    k = np.exp(-0.5 * (x / sigma) ** 2)
    return k / k.sum()


def _convolve_axis(img, taps: np.ndarray, axis: int):
    """Correlate `img` with symmetric `taps` along `axis`, replicating the border pixels."""
    r = len(taps) // 2
    pad = [(0, 0)] * img.ndim
    pad[axis] = (r, r)
    padded = jnp.pad(img, pad, mode="edge")
    n = img.shape[axis]
    out = 0.0
    for i, t in enumerate(taps):
        out = out + float(t) * jax.lax.slice_in_dim(padded, i, i + n, axis=axis)  # a slice, not a gather
    return out


def gaussian_blur(img, sigma: float):
    """Separable Gaussian blur of an (H, W, C) image (σ in pixels, static); σ ≤ 0 returns `img`."""
    if sigma <= 0:
        return img
    taps = gaussian_kernel(float(sigma))
    return _convolve_axis(_convolve_axis(img, taps, 0), taps, 1)
