"""Jump flooding with nearest-seed coordinates, and re-distancing of a level-set function.

`nearest_seed_points` is the coordinate-returning twin of `jaxtrack.image.nearest_seed_distance`
(JFA+1, Rong & Tan 2006): shape matching needs the nearest contour point itself, not only its
distance. A candidate for `jaxtrack.image` once the region cue settles.
"""

from __future__ import annotations

import jax.numpy as jnp

_FAR = 1e9


def _shift(a, dy: int, dx: int, fill):
    """b[y, x] = a[y + dy, x + dx] (fill outside)."""
    h, w = a.shape[:2]
    pad = [(abs(dy), abs(dy)), (abs(dx), abs(dx))] + [(0, 0)] * (a.ndim - 2)
    p = jnp.pad(a, pad, constant_values=fill)
    return p[abs(dy) + dy : abs(dy) + dy + h, abs(dx) + dx : abs(dx) + dx + w]


def nearest_seed_points(seeds, max_distance: int | None = None):
    """(H, W, 2) (y, x) of the nearest True pixel of `seeds` for every pixel (1e9 where none).

    Args:
        seeds: (H, W) bool.
        max_distance: if given (static), the flooding starts with the largest power-of-two step
            below it: exact within about that distance of a seed, fewer rounds (the level set only
            needs a band). Pixels farther away may get a farther seed or none (1e9).
    """
    h, w = seeds.shape
    gy, gx = jnp.meshgrid(jnp.arange(h, dtype=jnp.float32), jnp.arange(w, dtype=jnp.float32), indexing="ij")
    grid = jnp.stack([gy, gx], -1)
    nearest = jnp.where(seeds[..., None], grid, _FAR)
    steps, k = [], 1
    limit = max(h, w) if max_distance is None else min(max(h, w), int(max_distance))
    while k < limit:
        steps.append(k)
        k *= 2
    for step in steps[::-1] + [1]:
        best = nearest
        best_d = jnp.sum((best - grid) ** 2, -1)
        for dy in (-step, 0, step):
            for dx in (-step, 0, step):
                if dy == 0 and dx == 0:
                    continue
                cand = _shift(nearest, dy, dx, _FAR)
                d = jnp.sum((cand - grid) ** 2, -1)
                better = d < best_d
                best = jnp.where(better[..., None], cand, best)
                best_d = jnp.where(better, d, best_d)
        nearest = best
    return nearest


def contour_pixels(phi):
    """(H, W) bool pixels next to the zero level: a 4-neighbour has the other sign of Φ > 0."""
    inside = phi > 0
    pad = jnp.pad(inside, 1, mode="edge")
    h, w = inside.shape
    differs = jnp.zeros_like(inside)
    for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        differs = differs | (pad[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w] != inside)
    return differs


BAND = 16  # px: level-set functions are signed distances out to here and clipped beyond


def band_sdf(inside, band: int = BAND):
    """Signed distance (H, W) of a boolean region, positive inside, clipped to ±band.

    One jump flooding from the pixels on either side of the boundary, limited to the band: the
    nearest boundary pixel sits ~½ px from the zero level, so |Φ| = distance + ½ (the convention of
    `jaxtrack.image.silhouette_sdf`, which floods twice over the whole image).
    """
    phi = jnp.where(inside, 1.0, -1.0)
    seeds = contour_pixels(phi)
    h, w = inside.shape
    gy, gx = jnp.meshgrid(jnp.arange(h, dtype=jnp.float32), jnp.arange(w, dtype=jnp.float32), indexing="ij")
    near = nearest_seed_points(seeds, band)
    dist = jnp.sqrt((near[..., 0] - gy) ** 2 + (near[..., 1] - gx) ** 2)
    return jnp.where(inside, 1.0, -1.0) * jnp.minimum(dist + 0.5, float(band))


def redistance(phi, band: int = BAND):
    """Signed distance with the zero level of Φ (clipped to ±band), keeping Φ's own values in |Φ| < 1.

    Keeping the band |Φ| < 1 keeps the sub-pixel position of the zero level.
    """
    sdf = band_sdf(phi > 0, band).astype(phi.dtype)
    return jnp.where(jnp.abs(phi) < 1.0, phi, jnp.where(jnp.abs(sdf) < 1.0, jnp.sign(sdf) * 1.0, sdf))
