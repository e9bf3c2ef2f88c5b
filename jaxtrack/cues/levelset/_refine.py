"""Building blocks of the dense region cue (Section IV): its settings and carried state, one crop's
segmentation (eq. 11-13) and contour matching (eq. 14-15).

The per-round work of the dense level-set modality (`_modality.py`, `LevelSetRegion`) is made of
these: Φ0 from the round's render, the level set evolved with the carried local densities, the
densities re-estimated, the contour matches padded to a fixed capacity per camera.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ...image import paste_window, paste_window_scaled
from ._densities import LocalDensities, data_term, local_densities
from ._energy import RegionParams, evolve, region_memberships
from ._matching import closest_point_matches_at, regularised_matches
from ._redistance import contour_pixels


class RegionConfig(eqx.Module):
    """Static settings (they shape the compiled program).

    Attributes:
        levelset_iterations: steps of eq. 13 per outer iteration (a multiple of redistance_every).
        redistance_every: re-distance Φ after this many steps.
        density_factor: coarse-grid factor of the local densities (crops must be divisible by it).
        outer_iterations: cap on {segment, match, solve} rounds per refinement.
        solver_steps: Gauss-Newton steps per round.
        capacity: contour correspondences per camera.
        matching: "closest" (eq. 14) or "regularised" (eq. 15).
        texture: add the texture channel to the colour channels.
        warm_start: with densities carried from the previous frame, each round's level set starts from
            the previous round's Φ (the first round from Φ0) instead of from Φ0: the segmentation keeps
            evolving while the pose moves, as in the paper's alternation, and reaches the data's boundary
            instead of the first iterations' compromise. Without carried densities every round starts
            from Φ0 (a warm start on densities from an unrefined Φ0 held a 2-joint chain 0.06 rad off).
        fixed_densities: with densities carried from the previous frame, they serve every round; the last
            round's segmentation gives the densities carried to the next frame. Re-estimating them from
            each round's own segmentation lets an error feed itself. Without carried densities they are
            re-estimated every round (the first from Φ0).
        edge_rows: with densities carried from the previous frame, contour matches become edge rows of
            the solver (weight 1 across the contour, `RegionParams.tangent_weight` along it) instead of
            point rows (see `jaxtrack.solve`); without them, point rows.
    """

    levelset_iterations: int = eqx.field(static=True, default=10)
    redistance_every: int = eqx.field(static=True, default=5)
    density_factor: int = eqx.field(static=True, default=4)
    outer_iterations: int = eqx.field(static=True, default=30)
    solver_steps: int = eqx.field(static=True, default=5)
    capacity: int = eqx.field(static=True, default=512)
    matching: str = eqx.field(static=True, default="closest")
    texture: bool = eqx.field(static=True, default=False)
    warm_start: bool = eqx.field(static=True, default=True)
    fixed_densities: bool = eqx.field(static=True, default=True)
    edge_rows: bool = eqx.field(static=True, default=True)

    def __check_init__(self):
        if self.matching not in ("closest", "regularised"):
            raise ValueError(f"RegionConfig.matching must be 'closest' or 'regularised', got {self.matching!r}")
        if self.redistance_every < 1 or self.levelset_iterations < self.redistance_every:
            raise ValueError("RegionConfig: need levelset_iterations ≥ redistance_every ≥ 1")
        if self.outer_iterations < 1 or self.capacity < 1 or self.density_factor < 1:
            raise ValueError("RegionConfig: outer_iterations, capacity and density_factor must be ≥ 1")


class RegionState(eqx.Module):
    """What the region cue carries from frame to frame (full-frame coordinates, per camera).

    Attributes:
        phi: (C, H, W) the last segmentation Φ (inside its crop; −1 elsewhere).
        densities: `LocalDensities` with (C, 2, H/f, W/f, K) fields on the full frame's coarse grid.
        has_densities: (C,) bool, densities were estimated (else the first round estimates them from Φ0).
    """

    phi: jax.Array
    densities: LocalDensities
    has_densities: jax.Array


def initial_state(num_cameras: int, height: int, width: int, channels: int, factor: int = 4, dtype=jnp.float32) -> RegionState:
    """An empty `RegionState` (no densities yet).

    The coarse density grid covers the frame rounded up to whole cells (crops and their offsets are
    multiples of `factor`, so a frame of any size works; its last partial cell is never read).
    """
    if factor < 1:
        raise ValueError(f"density factor must be ≥ 1, got {factor}")
    shape = (num_cameras, 2, -(-height // factor), -(-width // factor), channels)
    return RegionState(
        phi=-jnp.ones((num_cameras, height, width), dtype),
        densities=LocalDensities(jnp.zeros(shape, dtype), jnp.ones(shape, dtype)),
        has_densities=jnp.zeros((num_cameras,), bool),
    )


def silhouette_contour(silhouette):
    """(H, W) bool inner contour of a silhouette, without the crop's border rows and columns
    (a silhouette cut by the crop has no contour there)."""
    contour = silhouette & contour_pixels(jnp.where(silhouette, 1.0, -1.0))
    h, w = silhouette.shape
    yy, xx = jnp.meshgrid(jnp.arange(h), jnp.arange(w), indexing="ij")
    return contour & (yy > 0) & (yy < h - 1) & (xx > 0) & (xx < w - 1)


def _select_slots(mask, capacity: int):
    """Flat indices (capacity,) of up to `capacity` True pixels spread evenly, −1 for empty slots."""
    flat = mask.reshape(-1)
    rank = jnp.cumsum(flat) - 1
    count = jnp.sum(flat)
    slot = (rank * capacity) // jnp.maximum(count, capacity)
    slot = jnp.where(flat, slot, capacity)
    return jnp.full((capacity,), -1, jnp.int32).at[slot].set(jnp.arange(flat.size, dtype=jnp.int32), mode="drop")


def contour_matches(phi0, phi, silhouette, p_model_img, part_img, params: RegionParams, capacity: int, matching: str = "closest"):
    """Matched contour points of one camera (crop coordinates), padded to `capacity`. Jittable.

    Args:
        phi0: (h, w) Φ0, the model's signed distance; phi: (h, w) the segmentation.
        silhouette: (h, w) bool model silhouette; p_model_img (h, w, 3), part_img (h, w): renderer buffers.
        params: min_match, max_match, alpha_match.

    Returns:
        (pixel (capacity, 2) x, y of the contour point where its model point projects, target
        (capacity, 2) the matched point on Φ's zero level, p_model (capacity, 3), part (capacity,),
        weight (capacity,): 1 for a usable match, 0 for padding, outliers and matches shorter than
        min_match (default 0: zero-length matches keep their weight and anchor the pose),
        normal (capacity, 2): the unit normal of the matched contour (the direction the match
        measures; the solver's edge rows use it)).
    """
    w = phi.shape[1]
    idx = _select_slots(silhouette_contour(silhouette), capacity)
    valid = idx >= 0
    safe = jnp.where(valid, idx, 0)
    pixel = jnp.stack([safe % w, safe // w], -1).astype(phi.dtype)
    if matching == "closest":
        dvec, found, normal = closest_point_matches_at(phi0, phi, pixel)
        valid = valid & found
    else:
        dvec = regularised_matches(phi0, phi, params.alpha_match).reshape(-1, 2)[safe]
        gx, gy = jnp.gradient(phi0)[::-1]
        g = jnp.stack([gx.reshape(-1)[safe], gy.reshape(-1)[safe]], -1)
        normal = g / jnp.maximum(jnp.linalg.norm(g, axis=-1, keepdims=True), 1e-6)
    length = jnp.sqrt(jnp.sum(dvec**2, -1))
    usable = valid & (length >= params.min_match) & (length <= params.max_match) & jnp.all(jnp.isfinite(dvec), -1)
    weight = usable.astype(phi.dtype)
    return pixel, pixel + dvec, p_model_img.reshape(-1, 3)[safe], part_img.reshape(-1)[safe], weight, normal


def _densities(features, phi, band, params: RegionParams, factor: int) -> LocalDensities:
    """Local densities of both regions of Φ without the band |Φ| < `band` (`region_memberships`).

    Used for Φ0 (first round) and for each round's segmentation (carried to the next round): the
    segmentation near a wrong Φ0 keeps part of the background strip, so densities from its plain
    membership re-learn the strip as object (measured: 67 mm off after 30 rounds from a 6 px shift).
    """
    w_obj, w_bg = region_memberships(phi, band)
    return local_densities(features, w_obj, params.rho, params.kappa, params.sigma_min, factor, weight_background=w_bg)


def segment(features, phi0, phi_init, densities: LocalDensities, params: RegionParams, config: RegionConfig | None = None):
    """Level-set segmentation of one crop (eq. 11-13) with the given densities; then new densities.

    Args:
        features: (h, w, K) feature crop; phi0: (h, w) shape prior; phi_init: (h, w) start.
        densities: `LocalDensities` (2, h/f, w/f, K) used for this round's data term.

    Returns:
        (Φ (h, w), `LocalDensities` re-estimated from H(Φ)).
    """
    config = RegionConfig() if config is None else config
    f = config.density_factor
    force = data_term(features, densities, f)
    phi = evolve(phi_init, phi0, force, params, config.levelset_iterations, config.redistance_every)
    new = _densities(features, phi, params.density_band, params, f)
    return phi, new


def _paste_state(state: RegionState, phi, dens: LocalDensities, offsets, f: int, scales=None) -> RegionState:
    """Crop-sized Φ and densities (C, ...) written into the full-frame `RegionState` (`scales`: (C,) full-frame
    pixels per crop pixel of resampled crops, else None; Φ keeps its crop-pixel units)."""
    dtype = phi.dtype

    def paste(full, part, offs):  # (C, H, W, ...) ← (C, h, w, ...)
        if scales is None:
            return jax.vmap(paste_window)(full, part, offs)
        return jax.vmap(paste_window_scaled)(full, part, offs, scales)

    def paste_field(full, part):  # (C, 2, Hc, Wc, K) ← (C, 2, hc, wc, K): the coarse grid's window is offset / f
        coarse = offsets // f if scales is None else offsets / f
        return jnp.moveaxis(paste(jnp.moveaxis(full, 1, 3), jnp.moveaxis(part, 1, 3), coarse), 3, 1)

    new_phi = paste(jnp.full_like(state.phi.astype(dtype), -1.0), phi, offsets)
    return RegionState(
        phi=new_phi,
        densities=LocalDensities(
            paste_field(state.densities.mean.astype(dtype), dens.mean), paste_field(state.densities.var.astype(dtype), dens.var)
        ),
        has_densities=jnp.ones_like(state.has_densities),
    )

