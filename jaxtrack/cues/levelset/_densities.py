"""Local Gaussian densities of the two regions (eq. 12), by normalised convolution on a coarse grid.

For region i ∈ {object, background} with soft membership w_i (H(Φ) and 1 − H(Φ)) and feature
channel j, the local density at x is a Gaussian with

    μ_ij(x)  = (G_ρ * w_i I_j)(x)  / (G_ρ * w_i)(x),
    σ²_ij(x) = (G_ρ * w_i I_j²)(x) / (G_ρ * w_i)(x) − μ_ij(x)²,                         (eq. 12)

restricted to the region by the normalised convolution. Where a region is (almost) absent in the
window the estimate blends into the region's global moments with weight κ (otherwise the ratio is
0/0), and σ has a floor σ_min (a flat-colour region would otherwise have σ → 0).

Speed (XLA:CPU): the ρ = 12 window is 73 taps wide. The moments are smooth, so they are computed
on a grid `factor` times coarser (box-averaged), where the Gaussian is a dense matrix product on
each axis (σ = ρ / factor ≈ 3 coarse cells, exact, no truncation, built from the array ρ so
sweeping it does not recompile), and μ, σ² are brought back by bilinear interpolation. `factor=1`
is the exact normalised convolution over the whole crop (tested against a direct sum).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


class LocalDensities(eqx.Module):
    """Gaussian densities per region and channel on the coarse grid.

    Attributes:
        mean: (2, Hc, Wc, K) μ of region 0 (object, Φ > 0) and region 1 (background).
        var: (2, Hc, Wc, K) σ² (floored), same layout.
    """

    mean: jax.Array
    var: jax.Array


def _gauss_matrix(n: int, factor: int, rho, dtype):
    """(n, n) Gaussian weights between coarse cells (spacing `factor` px), normalised to unit mass."""
    c = jnp.arange(n, dtype=dtype) * factor
    d = c[:, None] - c[None, :]
    return jnp.exp(-0.5 * (d / rho) ** 2) * (factor / (math.sqrt(2.0 * math.pi) * rho))


def _upsample_matrix(n_fine: int, factor: int) -> np.ndarray:
    """(n_fine, n_fine // factor) bilinear interpolation from coarse cell centres (host constant)."""
    n = n_fine // factor
    m = np.zeros((n_fine, n))
    t = np.clip((np.arange(n_fine) - (factor - 1) / 2.0) / factor, 0, n - 1)
    i0 = np.floor(t).astype(int)
    i1 = np.minimum(i0 + 1, n - 1)
    f = t - i0
    m[np.arange(n_fine), i0] += 1 - f
    m[np.arange(n_fine), i1] += f
    return m


def _coarse(x, factor: int):
    """Box average over factor x factor blocks: (H, W, ...) → (H/f, W/f, ...)."""
    if factor == 1:
        return x
    h, w = x.shape[:2]
    return x.reshape((h // factor, factor, w // factor, factor) + x.shape[2:]).mean(axis=(1, 3))


def upsample(coarse, shape: tuple[int, int], factor: int):
    """Bilinear upsampling of a (Hc, Wc, ...) field to (H, W, ...) = shape (factor static)."""
    if factor == 1:
        return coarse
    uy = jnp.asarray(_upsample_matrix(shape[0], factor), coarse.dtype)
    ux = jnp.asarray(_upsample_matrix(shape[1], factor), coarse.dtype)
    return jnp.einsum("bj,aj...->ab...", ux, jnp.einsum("ai,ij...->aj...", uy, coarse))


def check_grid(shape, factor: int):
    if shape[0] % factor or shape[1] % factor:
        raise ValueError(f"region crop {shape[0]}x{shape[1]} must be divisible by the density grid factor {factor}")


def local_densities(features, weight_object, rho, kappa, sigma_min, factor: int = 4, weight_background=None) -> LocalDensities:
    """Local Gaussian densities of object and background (eq. 12) on the coarse grid. Jittable.

    Args:
        features: (H, W, K) feature image (H, W divisible by `factor`).
        weight_object: (H, W) membership of the object region in [0, 1] (H(Φ)); the background
            gets 1 − weight_object.
        rho: window σ in pixels (array; the paper's ρ = 12).
        kappa: weight of the global moments blended in where a region is locally absent.
        sigma_min: floor on σ (feature units).
        factor: coarse-grid factor (static; 1 = exact).
        weight_background: (H, W) membership of the background (default 1 − weight_object).

    Returns:
        `LocalDensities` with (2, H/factor, W/factor, K) fields.
    """
    h, w, k = features.shape
    check_grid((h, w), factor)
    dtype = features.dtype
    weight_background = 1.0 - weight_object if weight_background is None else weight_background
    weights = jnp.stack([weight_object, weight_background], -1).astype(dtype)  # (H, W, 2)
    stack = jnp.concatenate(
        [weights[..., None], weights[..., None] * features[:, :, None, :], weights[..., None] * features[:, :, None, :] ** 2],
        axis=-1,
    )  # (H, W, 2, 1 + 2K)
    total = jnp.sum(stack, axis=(0, 1))  # (2, 1 + 2K) global moments of each region
    coarse = _coarse(stack, factor)
    gy = _gauss_matrix(h // factor, factor, rho, dtype)
    gx = _gauss_matrix(w // factor, factor, rho, dtype)
    smooth = jnp.einsum("bj,ajrm->abrm", gx, jnp.einsum("ai,ijrm->ajrm", gy, coarse))
    area = total[:, :1]
    global_mean = total[:, 1 : 1 + k] / jnp.maximum(area, 1e-12)
    global_sq = total[:, 1 + k :] / jnp.maximum(area, 1e-12)
    denom = smooth[..., :1] + kappa
    mean = (smooth[..., 1 : 1 + k] + kappa * global_mean) / denom
    second = (smooth[..., 1 + k :] + kappa * global_sq) / denom
    var = jnp.maximum(second - mean**2, sigma_min**2)
    return LocalDensities(jnp.moveaxis(mean, 2, 0), jnp.moveaxis(var, 2, 0))


def log_likelihoods(features, densities: LocalDensities, factor: int = 4):
    """(2, H, W) log p_i(x) = Σ_j log N(I_j(x); μ_ij(x), σ²_ij(x)) of both regions (eq. 11-12)."""
    shape = features.shape[:2]
    mean = upsample(jnp.moveaxis(densities.mean, 0, 2), shape, factor)  # (H, W, 2, K)
    var = upsample(jnp.moveaxis(densities.var, 0, 2), shape, factor)
    ll = -0.5 * jnp.log(2.0 * jnp.pi * var) - 0.5 * (features[:, :, None, :] - mean) ** 2 / var
    return jnp.moveaxis(jnp.sum(ll, axis=-1), 2, 0)


def data_term(features, densities: LocalDensities, factor: int = 4):
    """(H, W) log p1 − log p2: the region competition force of eq. 13 (object minus background)."""
    ll = log_likelihoods(features, densities, factor)
    return ll[0] - ll[1]
