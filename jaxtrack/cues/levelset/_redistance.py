"""Re-distancing of a level-set function: contour pixels and band-limited signed distances.

Built on `jaxtrack.image.nearest_seed_points` (jump flooding that returns the nearest seed's
coordinates, JFA+1, Rong & Tan 2006): shape matching needs the nearest contour point itself.
"""

from __future__ import annotations

import jax.numpy as jnp

from ...image import nearest_seed_points


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
