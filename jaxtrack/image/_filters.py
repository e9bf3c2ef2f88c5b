"""Separable Gaussian filtering of (H, W, C) arrays: σ static (it sets the number of taps), or traced
with a static largest σ (`gaussian_blur_traced`)."""

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


def _convolve_axis(img, taps, axis: int):
    """Correlate `img` with symmetric `taps` along `axis`, replicating the border pixels. `taps`: host constants
    (numpy; taken as Python floats, so they do not promote the image's dtype) or a traced (K,) array."""
    r = len(taps) // 2
    pad = [(0, 0)] * img.ndim
    pad[axis] = (r, r)
    padded = jnp.pad(img, pad, mode="edge")
    n = img.shape[axis]
    host = isinstance(taps, np.ndarray)
    out = 0.0
    for i in range(len(taps)):
        out = out + (float(taps[i]) if host else taps[i]) * jax.lax.slice_in_dim(padded, i, i + n, axis=axis)  # a slice
    return out


def gaussian_blur(img, sigma: float):
    """Separable Gaussian blur of an (H, W, C) image (σ in pixels, static); σ ≤ 0 returns `img`."""
    if sigma <= 0:
        return img
    taps = gaussian_kernel(float(sigma))
    return _convolve_axis(_convolve_axis(img, taps, 0), taps, 1)


def gaussian_blur_traced(img, sigma, max_sigma: float = 2.0):
    """Separable Gaussian blur of an (H, W, C) image with σ a traced scalar (a parameter: vmap and grad over it).

    The taps span the static radius ceil(3 · max_sigma) and are computed from σ at run time; σ is clipped to
    [0, max_sigma]. σ ≤ 0 returns `img` itself (a `lax.cond`: nothing is computed; under `vmap` over σ both
    branches run and the unblurred branch is selected).
    """
    radius = max(1, math.ceil(3.0 * float(max_sigma)))
    sigma = jnp.clip(jnp.asarray(sigma, img.dtype), 0.0, max_sigma)

    def blur(image):
        x = jnp.arange(-radius, radius + 1, dtype=image.dtype)
        k = jnp.exp(-0.5 * (x / jnp.maximum(sigma, 1e-3)) ** 2)
        k = k / jnp.sum(k)
        return _convolve_axis(_convolve_axis(image, k, 0), k, 1)

    return jax.lax.cond(sigma > 0, blur, lambda image: image, img)
