"""Feature channels of the region cue (Section IV): colour (or grey) plus a texture channel.

The channels are modelled as independent, p_i(x) = Π_j p_ij(I_j(x)) (eq. 12), so each channel only
needs to carry information the others do not. The texture channel is the square root of the
smoothed trace of the linear structure tensor, sqrt(K_σ * |∇I|²), on the grey image: a local
"edge energy" that separates textured from flat regions of similar colour. (The paper uses the
nonlinear structure tensor or the local scale of Brox and Weickert; this linear variant is cheaper.)

Measured (flat-coloured teapot, 320x240, a 3-px shift, ten one-round refinements): with the texture
channel the depth drifted to 13.5 mm, without it to 4.0 mm — the linear tensor's edge energy is high
on both sides of the object's boundary, so rim pixels look like textured background. It is therefore
off by default (`RegionConfig.texture`); an edge-preserving (nonlinear) texture feature is left to do.
"""

from __future__ import annotations

import jax.numpy as jnp

from ...image import as_channels, gaussian_blur, gaussian_blur_traced, image_gradients


def texture_channel(grey, sigma: float = 1.5):
    """(H, W) texture magnitude sqrt(K_σ * (I_x² + I_y²)) of an (H, W) grey image (0-255 scale)."""
    gx, gy = image_gradients(grey[..., None])
    energy = gaussian_blur(gx**2 + gy**2, sigma)[..., 0]
    return jnp.sqrt(energy + 1e-6)


def feature_channels(image, texture: bool = True, texture_sigma: float = 1.5):
    """(H, W, K) feature image: the colour channels (or grey) and, if `texture`, the texture channel.

    Args:
        image: (H, W) grey or (H, W, 3) colour frame on the 0-255 scale (any real or integer dtype).
        texture: append `texture_channel` of the grey image (static).
        texture_sigma: σ (px) of the structure-tensor smoothing (static).

    Returns:
        (H, W, K) with K = 1 or 3 (+1 with texture), in the image's float dtype (float32 for ints).
    """
    img = as_channels(jnp.asarray(image))
    if not jnp.issubdtype(img.dtype, jnp.floating):
        img = img.astype(jnp.float32)
    if not texture:
        return img
    grey = jnp.mean(img, axis=-1)
    return jnp.concatenate([img, texture_channel(grey, texture_sigma)[..., None]], axis=-1)


def smoothed_features(image, texture: bool, sigma):
    """`feature_channels` of an (H, W[, 3]) crop, then Gaussian-smoothed with the traced σ
    (`RegionParams.feature_sigma`; 0 = the channels as they are). (H, W, K)."""
    return gaussian_blur_traced(feature_channels(image, texture), sigma)
