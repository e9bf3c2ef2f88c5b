"""Dense patch histograms and their L1 distance d = ½ Σ_b |p_a,b − p_b,b| (eq. 9), by box sums."""

from __future__ import annotations

import jax
import jax.numpy as jnp


def to_gray(image):
    """(H, W) unchanged; (H, W, 3) RGB → (H, W) luma (ITU-R 601 weights), 0-255 scale."""
    image = jnp.asarray(image)
    if image.ndim == 2:
        return image
    if image.ndim == 3 and image.shape[-1] == 1:
        return image[..., 0]
    return 0.299 * image[..., 0] + 0.587 * image[..., 1] + 0.114 * image[..., 2]


def soft_bins(gray, bins: int):
    """(H, W) grey values in [0, 255] → (H, W, bins) triangular (linear-interpolation) bin weights.

    Each value splits between its two nearest bin centres, so a small grey change moves a histogram
    by a small amount (hard bins would flip whole pixels at bin edges). Weights sum to 1.
    """
    s = jnp.clip(gray * (bins / 256.0) - 0.5, 0.0, bins - 1.0)
    centres = jnp.arange(bins, dtype=s.dtype)
    return jnp.maximum(0.0, 1.0 - jnp.abs(s[..., None] - centres))


def _box_sum_axis(x, radius: int, axis: int):
    """Σ_{k=i−r}^{i+r} x[k] along `axis` (zeros outside), by doubling: sums over 1, 2, 4, ... samples
    combined along the binary digits of 2r + 1, O(log r) adds of static slices. (A cumulative sum
    measured 2.5-5x slower on XLA:CPU, 2r + 1 shifted adds 2.5x slower at r = 15.)"""
    n = x.shape[axis]
    length = 2 * radius + 1
    pad = [(0, 0)] * x.ndim
    pad[axis] = (radius, radius)
    block = jnp.pad(x, pad)  # block[i] = sum of `size` padded samples from i
    size, offset, out = 1, 0, None
    while True:
        if length & size:
            term = jax.lax.slice_in_dim(block, offset, offset + n, axis=axis)
            out = term if out is None else out + term
            offset += size
        if 2 * size > length:
            return out
        m = block.shape[axis]
        block = jax.lax.slice_in_dim(block, 0, m - size, axis=axis) + jax.lax.slice_in_dim(block, size, m, axis=axis)
        size *= 2


def box_sum(x, radius: int):
    """Window sums over (2r+1)² neighbourhoods of the first two axes of x (H, W, ...)."""
    return _box_sum_axis(_box_sum_axis(x, radius, 0), radius, 1)


def patch_histogram_distance(gray_a, gray_b, valid, bins: int, window: int):
    """Per-pixel distance of the grey histograms of two images over a window (eq. 9).

    Both histograms of pixel x are taken over the same pixels: those of the (window × window)
    neighbourhood of x where `valid` holds.

    Args:
        gray_a, gray_b: (H, W) grey images (0-255).
        valid: (H, W) bool pixels that enter the histograms.
        bins, window: static histogram size and odd window side.

    Returns:
        (d (H, W) in [0, 1] (0 where no pixel is valid), count (H, W) valid pixels per window).
    """
    w = valid.astype(gray_a.dtype)[..., None]
    diff = (soft_bins(gray_a, bins) - soft_bins(gray_b, bins)) * w
    r = window // 2
    # Σ_y w(y) (h_a(y) − h_b(y)) per bin: one box sum of the difference instead of two.
    hist_diff = box_sum(diff, r)
    count = box_sum(w, r)[..., 0]
    d = 0.5 * jnp.sum(jnp.abs(hist_diff), -1) / jnp.maximum(count, 1.0)
    return jnp.where(count > 0, d, 0.0), count


def local_gain(model, image, valid, window: int, max_gain, groups=None, num_groups: int = 1):
    """Brightness gain g(x) = Σ I / Σ M over the valid pixels of a window, clipped to
    [1/max_gain, max_gain] (1 where the window holds no valid pixel): M·g matches I's local shading.

    With `groups` ((H, W) int in [0, num_groups), e.g. a quantised surface normal), the sums only run
    over the window's pixels of x's own group: Lambertian shading changes by normal, so two faces
    meeting inside one window get their own gains.
    """
    dtype = model.dtype
    if groups is None:
        groups, num_groups = jnp.zeros(model.shape, jnp.int32), 1
    member = (groups[..., None] == jnp.arange(num_groups)) & valid[..., None]  # (H, W, G)
    w = member.astype(dtype)
    sums = box_sum(jnp.concatenate([model[..., None] * w, image[..., None] * w], -1), window // 2)
    own = jax.nn.one_hot(groups, num_groups, dtype=dtype)
    den = jnp.sum(sums[..., :num_groups] * own, -1)
    num = jnp.sum(sums[..., num_groups:] * own, -1)
    ratio = jnp.where(den > 1e-6, num / jnp.where(den > 1e-6, den, 1.0), 1.0)
    return jnp.clip(ratio, 1.0 / max_gain, max_gain)
