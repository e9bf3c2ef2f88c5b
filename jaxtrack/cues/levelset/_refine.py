"""Region-only pose refinement: {level-set iterations, shape matching, Gauss-Newton} until the pose
settles (Section IV), for one or several cameras sharing one state χ = (ξ, Θ).

Everything between the images and the pose is one jittable function, `refine_pose_region`, of
arrays and `eqx.Module`s: the renderer draws the model straight into each camera's region of
interest (a crop of a static size class, by shifting the principal point), Φ0 is its signed
distance, the level set evolves from Φ0 with the carried local densities, the densities are
re-estimated from the result, the contour matches become `Cue.REGION` correspondences (fixed
capacity per camera, each with its model point and part from the renderer), and `solve_pose` takes a
few Gauss-Newton steps. Cameras are a vmapped leading axis. Nothing assumes a single rigid part.

`RegionRefiner` is the host edge: it validates inputs, picks the crop (`region_crop`) and raster
plan, keeps one compiled program per crop size class and plan, and carries `RegionState`.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ..._status import Status, first_failure, status_where
from ...geometry import Camera, KinematicModel, part_transforms
from ...image import crop_window, paste_window
from ...render import Mesh, RasterPlan, render
from ...solve import (
    Correspondences,
    Cue,
    CueWeights,
    JointPrior,
    SolverConfig,
    concatenate_correspondences,
    correspondences_from_pixels,
    fuse_cue_weights,
    solve_pose,
)
from ._densities import LocalDensities, check_grid, data_term, local_densities
from ._energy import RegionParams, evolve, region_memberships
from ._features import feature_channels
from ._matching import closest_point_matches_at, regularised_matches
from ._redistance import band_sdf, contour_pixels


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


class RegionResult(eqx.Module):
    """Outcome of `refine_pose_region`.

    Attributes:
        T_world_root: (4, 4) refined root pose; theta: (J,) refined joint angles.
        status: int32 `Status` (OK, MAX_STEPS if it did not settle, RENDER_OVERFLOW, OUT_OF_VIEW, ...).
        iterations: int32 outer rounds run.
        num_matches: int32 contour correspondences with weight in the last round.
        correspondences: the last round's `Cue.REGION` set (capacity C x `RegionConfig.capacity`).
        state: the updated `RegionState`.
        phi0: (C, h, w) the model's signed distance at the final pose's last render (crop).
        phi: (C, h, w) the last segmentation (crop).
    """

    T_world_root: jax.Array
    theta: jax.Array
    status: jax.Array
    iterations: jax.Array
    num_matches: jax.Array
    correspondences: Correspondences
    state: RegionState
    phi0: jax.Array
    phi: jax.Array


def crop_camera(camera: Camera, offset, crop_shape: tuple[int, int]) -> Camera:
    """The camera seeing only the crop at `offset` = (y0, x0): principal point shifted (jittable)."""
    K = camera.K.at[..., 0, 2].add(-offset[..., 1].astype(camera.K.dtype))
    K = K.at[..., 1, 2].add(-offset[..., 0].astype(camera.K.dtype))
    return Camera(K, camera.T_cam_world, camera.dist, width=crop_shape[1], height=crop_shape[0])


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


def _mean_motion(model: KinematicModel, corr: Correspondences, T_old, theta_old, T_new, theta_new):
    """Mean distance (mm) the weighted rows' model points move from χ_old to χ_new (∞ without rows)."""
    def world(T, theta):
        A = part_transforms(model, T, theta)[corr.part]
        return jnp.einsum("nij,nj->ni", A[:, :3, :3], corr.p_model) + A[:, :3, 3]

    live = corr.weight > 0
    d = jnp.linalg.norm(world(T_new, theta_new) - world(T_old, theta_old), axis=-1)
    n = jnp.sum(live)
    return jnp.where(n > 0, jnp.sum(jnp.where(live, d, 0.0)) / jnp.maximum(n, 1), jnp.inf)


class RegionProblem(eqx.Module):
    """The static side of a refinement: model, mesh, cameras, raster plan and settings."""

    mesh: Mesh
    model: KinematicModel
    cameras: Camera  # stacked (C on the leading axis)
    plan: RasterPlan = eqx.field(static=True)
    config: RegionConfig = eqx.field(static=True)


@eqx.debug.assert_max_traces(max_traces=None)  # counts traces (`eqx.debug.get_num_traces`), never fails
def refine_pose_region(
    problem: RegionProblem,
    images,
    offsets,
    state: RegionState,
    params: RegionParams,
    T_init,
    theta_init,
    extra: Correspondences | None = None,
    weights: CueWeights | None = None,
):
    """Region-only refinement of χ = (ξ, Θ) on one frame of C cameras. Jittable, pure.

    Args:
        problem: mesh, kinematic model, stacked cameras (C), raster plan and `RegionConfig`.
        images: (C, h, w, 3) or (C, h, w) crops of the frames (0-255) at `offsets`.
        offsets: (C, 2) int32 (y0, x0) of each crop in its full frame (multiples of density_factor).
        state: `RegionState` carried from the previous frame.
        params: `RegionParams`.
        T_init: (4, 4) initial root pose (model → world); theta_init: (J,) initial joint angles.
        extra: correspondences of other cues (the tracker's flow and SIFT rows, raw weights) solved
            together with the contour rows in every round; their weights follow Section V
            (`fuse_cue_weights`), so they scale with the number of contour matches.
        weights: user factors of that fusion (default 1).

    Returns:
        `RegionResult`; its `correspondences` are the last round's fused set (contour rows first).
    """
    config, model, mesh = problem.config, problem.model, problem.mesh
    f = config.density_factor
    crop_shape = images.shape[1:3]
    check_grid(crop_shape, f)
    dtype = T_init.dtype
    features = jax.vmap(lambda im: feature_channels(im, config.texture))(images).astype(dtype)
    cams = crop_camera(problem.cameras, offsets, crop_shape)
    coarse_shape = (crop_shape[0] // f, crop_shape[1] // f)
    # (2, Hc, Wc, K) per camera → crop on the coarse grid → back to (2, hc, wc, K).
    dens0 = jax.vmap(lambda m, off: jnp.moveaxis(crop_window(jnp.moveaxis(m, 0, 2), off // f, coarse_shape), 2, 0))
    carried = LocalDensities(dens0(state.densities.mean, offsets), dens0(state.densities.var, offsets))
    solver = SolverConfig(max_steps=config.solver_steps)
    num_cams = offsets.shape[0]
    theta_anchor = jnp.asarray(theta_init, dtype)  # the joint prior holds Θ near the refinement's start

    def per_camera(cam, feats, phi_prev, dens, has_dens, carried_in, first, T, theta):
        out = render(mesh, cam, T, theta, model, problem.plan)
        sil = out.face_id >= 0
        phi0 = band_sdf(sil).astype(dtype)
        own = _densities(feats, phi0, params.density_band, params, f)
        dens = jax.tree.map(lambda a, b: jnp.where(has_dens, a, b), dens, own)
        # Warm start and fixed densities only with densities from the previous frame: without them the
        # first round's densities come from Φ0 at the unrefined pose, and keeping them (or a segmentation
        # made with them) holds the pose where it started (a 2-joint chain stayed 0.06 rad off).
        start = jnp.where(first | ~carried_in, phi0, phi_prev) if config.warm_start else phi0
        phi, new_dens = segment(feats, phi0, start, dens, params, config)
        matches = contour_matches(phi0, phi, sil, out.p_model, out.part_id, params, config.capacity, config.matching)
        dens_next = jax.tree.map(lambda a, b: jnp.where(carried_in, a, b), dens, new_dens) if config.fixed_densities else new_dens
        return phi0, phi, (dens_next, new_dens), matches, out.overflow, jnp.any(sil)

    def round_(carry):
        T, theta, phi, dens, has_dens, it = carry[:6]
        phi0, phi, (dens_next, dens_out), (_, _target, p_model, part, weight, edge_normal), overflow, visible = jax.vmap(
            per_camera, in_axes=(0, 0, 0, 0, 0, 0, None, None, None)
        )(cams, features, phi, dens, has_dens, state.has_densities, it == 0, T, theta)
        target = _target + offsets[:, None, ::-1].astype(dtype)
        cam_index = jnp.broadcast_to(jnp.arange(num_cams, dtype=jnp.int32)[:, None], weight.shape)
        corr = correspondences_from_pixels(
            problem.cameras, target.reshape(-1, 2), cam_index.reshape(-1), p_model.reshape(-1, 3), part.reshape(-1),
            weight.reshape(-1), undistort=False, cue=Cue.REGION,
            edge_normal=edge_normal.reshape(-1, 2) if config.edge_rows else None,
            # Point rows (tangent weight 1) for a camera without carried densities: its segmentation is
            # made with densities from an unrefined Φ0, and the along-contour pull steadies the pose
            # (the cracker box at its true pose, no densities: 9.1 mm with edge rows, 4.1 with point rows).
            tangent_weight=jnp.broadcast_to(
                jnp.where(state.has_densities, params.tangent_weight, 1.0)[:, None].astype(dtype), weight.shape).reshape(-1),
        )
        if extra is not None:
            corr = fuse_cue_weights(concatenate_correspondences(corr, extra), CueWeights() if weights is None else weights)
        sol = solve_pose(model, corr, T, theta, solver, prior=JointPrior(theta_anchor, params.joint_prior))
        settled = _mean_motion(model, corr, T, theta, sol.T_world_root, sol.theta) < params.settle_motion
        # No usable match at all means the contours agree: the pose has settled, not failed.
        no_matches = sol.status == Status.TOO_FEW
        solve_status = jnp.where(no_matches | (sol.status == Status.MAX_STEPS), Status.OK, sol.status)
        frame_status = first_failure(
            status_where(~jnp.any(visible), Status.OUT_OF_VIEW, Status.OK),
            solve_status,
            status_where(jnp.any(overflow), Status.RENDER_OVERFLOW, Status.OK),
        )
        return (sol.T_world_root, sol.theta, phi, dens_next, jnp.ones_like(has_dens), it + 1, settled | no_matches, frame_status, corr, phi0,
                jnp.sum(weight > 0).astype(jnp.int32), dens_out)

    def cond(carry):
        it, settled, status = carry[5], carry[6], carry[7]
        return (it < config.outer_iterations) & ~settled & ((status == Status.OK) | (status == Status.RENDER_OVERFLOW))

    rows = num_cams * config.capacity
    empty = Correspondences(
        n=jnp.zeros((rows, 3), dtype), m=jnp.zeros((rows, 3), dtype), p_model=jnp.zeros((rows, 3), dtype),
        part=jnp.zeros((rows,), jnp.int32), camera=jnp.zeros((rows,), jnp.int32), pixel=jnp.zeros((rows, 2), dtype),
        weight=jnp.zeros((rows,), dtype), cue=jnp.full((rows,), int(Cue.REGION), jnp.int32),
        normal=jnp.zeros((rows, 3), dtype), tangent_weight=jnp.ones((rows,), dtype),
    )
    if extra is not None:
        empty = concatenate_correspondences(empty, extra.with_weight(jnp.zeros_like(extra.weight)))
    phi_start = jnp.zeros((num_cams,) + tuple(crop_shape), dtype)
    carried = jax.tree.map(lambda a: a.astype(dtype), carried)
    init = (
        T_init, theta_init.astype(dtype), phi_start, carried, state.has_densities, jnp.zeros((), jnp.int32),
        jnp.zeros((), bool), jnp.asarray(Status.OK, jnp.int32), empty, phi_start, jnp.zeros((), jnp.int32), carried,
    )
    T, theta, phi, _, _, it, settled, status, corr, phi0, num_matches, dens = jax.lax.while_loop(cond, round_, init)
    status = first_failure(status, status_where(settled, Status.OK, Status.MAX_STEPS))

    # Carry the segmentation and densities in full-frame coordinates.
    new_state = _paste_state(state, phi, dens, offsets, f)
    return RegionResult(T, theta, status.astype(jnp.int32), it, num_matches.astype(jnp.int32), corr, new_state, phi0, phi)


def densities_at_pose(problem: RegionProblem, images, offsets, state: RegionState, params: RegionParams, T_world_root, theta):
    """The region state of a frame whose pose is known (the tracker's first frame). Jittable.

    The local densities are learnt from the model silhouette at (T, Θ), so the next frame's first
    level-set iterations use densities of the right regions ("the first iterations of a new frame use
    the previous frame's densities", Section IV) instead of ones learnt from a predicted pose.

    Args:
        problem, images (C, h, w, 3) crops at offsets (C, 2), state: as for `refine_pose_region`.

    Returns:
        `RegionState` with Φ = Φ0(χ) and the densities of frame t in full-frame coordinates.
    """
    config, f = problem.config, problem.config.density_factor
    crop_shape = images.shape[1:3]
    check_grid(crop_shape, f)
    dtype = T_world_root.dtype
    cams = crop_camera(problem.cameras, offsets, crop_shape)

    def per_camera(cam, image):
        out = render(problem.mesh, cam, T_world_root, theta, problem.model, problem.plan)
        phi0 = band_sdf(out.face_id >= 0).astype(dtype)
        return phi0, _densities(feature_channels(image, config.texture).astype(dtype), phi0, params.density_band, params, f)

    phi0, dens = jax.vmap(per_camera)(cams, images)
    return _paste_state(state, phi0, dens, offsets, f)


def _paste_state(state: RegionState, phi, dens: LocalDensities, offsets, f: int) -> RegionState:
    """Crop-sized Φ and densities (C, ...) written into the full-frame `RegionState`."""
    dtype = phi.dtype
    new_phi = jax.vmap(lambda full, part, off: paste_window(jnp.full_like(full, -1.0), part, off))(state.phi.astype(dtype), phi, offsets)
    paste_dens = jax.vmap(lambda full, part, off: jnp.moveaxis(paste_window(jnp.moveaxis(full, 0, 2), jnp.moveaxis(part, 0, 2), off // f), 2, 0))
    return RegionState(
        phi=new_phi,
        densities=LocalDensities(
            paste_dens(state.densities.mean.astype(dtype), dens.mean, offsets), paste_dens(state.densities.var.astype(dtype), dens.var, offsets)
        ),
        has_densities=jnp.ones_like(state.has_densities),
    )


_refine_jit = eqx.filter_jit(refine_pose_region)
