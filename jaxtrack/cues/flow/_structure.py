"""How much of the flow the image determines: the structure tensor's smaller eigenvalue against the image noise.

Eq. 8's confidence c = β / (1 + e) is high wherever the flow energy is low; on a surface without texture every
flow fits the data, the smoothness term fills in the flow from the borders (zero on a flat object turning in
place), and e is low there too: the flow rows then pin the surface where it was and outweigh the contour (the
flat teapot on the turntable: 0.9° mean error with the lines alone, 98° with the lines and flow; measured in
experiments/results/cue_subsets.md). Lucas-Kanade's aperture measure says how far the image pins the flow at a
pixel: the smaller eigenvalue λ_min of the structure tensor J_ρ = G_ρ ∗ (∇I ∇Iᵀ). The tracker multiplies eq. 8's
confidence by

    g(x) = λ_min(x) / (λ_min(x) + κ),   κ = k · σ_n² + 1,

near 1 on strong texture and corners, 0 on homogeneous regions and along straight edges (the aperture problem), with σ_n the
image noise (Immerkær's estimate, from the Laplacian difference of the crop) so that noise alone does not count
as texture: a pure noise image has λ_min ≈ 0.65 σ_n² (the 5-point derivative stencil), g ≈ 0.65 / (0.65 + k).

Near a limb (where a smooth surface turns away from the camera: its occluding contour, also where a part of the object
occludes another) the image's structure does not belong to a point of the surface: the contour is where the view grazes
the surface, and it slides over the surface whenever the object turns relative to the camera (a body of revolution
turning about its axis keeps its outline while its surface moves). The edge against what lies behind is strong
structure there, so g was high on flow rows that pinned the object where it was: the flat teapot on the turntable
drifted about 0.4° a frame with the lines and flow, not with the lines alone. `limb_pixels` finds those pixels in the render
at χ_t (the surface's slope from the depth map), and `structure_confidence(..., limbs=)` counts no gradient within two
pixels of them (the derivative stencil's reach).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ...image import gaussian_blur, image_gradients

_LAPLACE_DIFFERENCE = np.array([[1.0, -2.0, 1.0], [-2.0, 4.0, -2.0], [1.0, -2.0, 1.0]])


def noise_sigma(grey) -> jax.Array:
    """Immerkær's estimate of the noise standard deviation of an (H, W) image: √(π/2) / (6 (W−2)(H−2)) Σ |I ∗ N|
    (N the difference of two Laplacians, which cancels image structure up to second order)."""
    grey = jnp.asarray(grey)
    h, w = grey.shape
    acc = jnp.zeros((h - 2, w - 2), grey.dtype)
    for dy in range(3):
        for dx in range(3):
            acc = acc + _LAPLACE_DIFFERENCE[dy, dx] * grey[dy:dy + h - 2, dx:dx + w - 2]
    return jnp.sqrt(jnp.pi / 2.0) * jnp.sum(jnp.abs(acc)) / (6.0 * (w - 2) * (h - 2))


def limb_pixels(depth, silhouette, focal, max_slope) -> jax.Array:
    """(H, W) bool: silhouette pixels where the surface turns away from the camera (a limb), from the rendered depth.

    The slope |ΔZ| · f / Z of a one-pixel step (the depth change over the pixel's lateral size Z / f: the tangent of
    the angle between the surface and the image plane, 0 facing the camera) along either image axis, the larger of
    the two one-sided differences whose neighbour is on the silhouette; a limb where it exceeds `max_slope`. Read
    from the pixel grid, the step underestimates the slope at a smooth outline: with tan 80° = 5.67 (the tracker's)
    a sphere 60 px across has limbs on some of its outermost pixels, with tan 70° on all of them. A depth jump inside
    the silhouette (one part in front of another) is a limb on both sides at any threshold that its size exceeds.

    Args:
        depth: (H, W) rendered camera-frame depth (any value off the silhouette); silhouette: (H, W) bool;
        focal: the camera's focal length in pixels; max_slope: scalar (an array: sweeping it does not recompile;
            ≤ 0 marks every pixel with a neighbour at another depth).
    """
    silhouette = jnp.asarray(silhouette, bool)
    z = jnp.where(silhouette, jnp.asarray(depth), 0.0)
    h, w = z.shape
    slopes = []
    for axis, n in ((0, h), (1, w)):
        index = jnp.arange(n)[:, None] if axis == 0 else jnp.arange(n)[None, :]
        step = jnp.zeros_like(z)
        for shift, keep in ((-1, index < n - 1), (1, index > 0)):  # the next and the previous pixel along the axis
            on = jnp.roll(silhouette, shift, axis) & keep
            step = jnp.maximum(step, jnp.where(on, jnp.abs(jnp.roll(z, shift, axis) - z), 0.0))
        slopes.append(step)
    slope = jnp.maximum(*slopes) * focal / jnp.maximum(z, 1e-6)
    return silhouette & (slope > max_slope)


def _within(mask, reach: int) -> jax.Array:
    """(H, W) bool: pixels within `reach` px (Chebyshev) of a pixel of `mask` (dilation; a row then a column window:
    0.04 ms at 96x128 on this CPU, against 0.5 ms for one square window of int32)."""
    side = 2 * reach + 1
    grown = jnp.asarray(mask, jnp.float32)
    for window in ((side, 1), (1, side)):
        grown = jax.lax.reduce_window(grown, -jnp.inf, jax.lax.max, window, (1, 1), "SAME")
    return grown > 0


def structure_confidence(image, noise_factor, rho: float = 1.5, limbs=None) -> jax.Array:
    """(H, W) g(x) ∈ [0, 1) of an (H, W) or (H, W, C) image (0-255): λ_min / (λ_min + k σ_n² + 1) of the structure
    tensor smoothed at `rho` px (grey: the channels' mean), k = `noise_factor` (an array: 0 keeps only the +1).

    limbs: (H, W) bool or None: `limb_pixels` of the image; gradients within 2 px of one (the 5-point stencil's
    reach) count as no structure."""
    image = jnp.asarray(image)
    grey = image if image.ndim == 2 else jnp.mean(image, axis=-1)
    gx, gy = image_gradients(grey[..., None])
    gx, gy = gx[..., 0], gy[..., 0]
    if limbs is not None:
        near = _within(limbs, 2)
        gx, gy = jnp.where(near, 0.0, gx), jnp.where(near, 0.0, gy)
    jxx, jxy, jyy = (gaussian_blur(a, rho) for a in (gx * gx, gx * gy, gy * gy))
    half_trace = 0.5 * (jxx + jyy)
    lam_min = jnp.maximum(half_trace - jnp.sqrt(jnp.maximum((0.5 * (jxx - jyy)) ** 2 + jxy**2, 0.0)), 0.0)
    kappa = jnp.asarray(noise_factor, grey.dtype) * noise_sigma(grey) ** 2 + 1.0
    return lam_min / (lam_min + kappa)

