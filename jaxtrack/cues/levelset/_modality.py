"""The dense level-set region modality (the paper's configuration, Section IV) and region-only refinement.

`LevelSetRegion` implements the modality protocol (`jaxtrack.modality`): per round, Φ0 is the signed
distance of the shared render at the current pose, the level set (eq. 11-13) evolves from Φ0 (or from
the previous round's Φ, `RegionConfig.warm_start`) with the local densities carried from the previous
frame, the contour of Φ is matched to the model's (eq. 14-15) and the matches become `Cue.REGION`
rows (edge rows with carried densities). Its rows are the n_C of Section V. At the end of the frame
the segmentation and densities are pasted into the full-frame `RegionState`.

`refine_pose_region` is region-only refinement on the tracker's own loop (`refine_rounds`) with this one
modality; `RegionRefiner` (`_host.py`) is its host edge.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ...geometry import Camera, KinematicModel, crop_camera
from ...image import crop_window, sample_window
from ...modality import (
    FrameContext,
    FusionCounts,
    Modality,
    Pose,
    RefineSettings,
    StartContext,
    refine_rounds,
    register_modality,
)
from ...render import Mesh, RasterPlan, render
from ...solve import Correspondences, Cue, CueWeights, correspondences_from_pixels, weights_per_pixel
from ._densities import LocalDensities, check_grid, data_term
from ._energy import RegionParams, evolve
from ._features import feature_channels, smoothed_features
from ._redistance import band_sdf
from ._refine import RegionConfig, RegionState, _densities, _paste_state, contour_matches, initial_state


class LevelSetFrame(eqx.Module):
    """Per-frame data of the level-set modality (crop coordinates, C cameras).

    Attributes:
        features: (C, h, w, K) feature channels of the crops of frame t+1.
        carried: `LocalDensities` (C, 2, h/f, w/f, K) from the previous frame, cropped.
        has_densities: (C,) bool, densities were carried (else each round estimates them from Φ0).
    """

    features: jax.Array
    carried: LocalDensities
    has_densities: jax.Array


class LevelSetCarry(eqx.Module):
    """The rounds' carry: the last segmentation and densities.

    Attributes:
        phi: (C, h, w) the last round's Φ; phi0: (C, h, w) its shape prior Φ0.
        densities: the densities the next round uses.
        has_densities: (C,) densities exist for the next round.
        num_matches: int32 contour matches with weight in the last round.
    """

    phi: jax.Array
    phi0: jax.Array
    densities: LocalDensities
    has_densities: jax.Array
    num_matches: jax.Array


def _crop_densities(dens: LocalDensities, offsets, coarse_shape, scales=None) -> LocalDensities:
    """(C, 2, Hc, Wc, K) full-frame coarse fields → the crops' (C, 2, hc, wc, K) (`offsets` on the coarse
    grid; `scales`: resampled crops, else None)."""
    if scales is None:
        f = jax.vmap(lambda m, off: jnp.moveaxis(crop_window(jnp.moveaxis(m, 0, 2), off, coarse_shape), 2, 0))
        return LocalDensities(f(dens.mean, offsets), f(dens.var, offsets))
    g = jax.vmap(lambda m, off, sc: jnp.moveaxis(sample_window(jnp.moveaxis(m, 0, 2), off, sc, coarse_shape, antialias=False,
                                                               dtype=m.dtype), 2, 0))
    return LocalDensities(g(dens.mean, offsets, scales), g(dens.var, offsets, scales))


@register_modality
class LevelSetRegion(Modality):
    """The paper's region cue as a modality: dense level set with local densities and shape matching.

    Attributes:
        config: `RegionConfig` (level-set iterations, contour capacity per camera, matching, ...).
    """

    name = "levelset"
    cue = int(Cue.REGION)
    contour = True
    needs_render = True
    uses_occlusion = True  # the per-part support reads the occlusion mask (as the paper's tracker always ran it)
    config: RegionConfig = eqx.field(static=True, default_factory=RegionConfig)

    @classmethod
    def from_config(cls, config) -> LevelSetRegion:
        return cls(config.region)

    def loop_preferences(self) -> tuple[int, int, int]:
        return self.config.outer_iterations, self.config.solver_steps, 0

    def init_state(self, ctx: StartContext, params, base: RegionState | None = None) -> RegionState:
        """Densities learnt from the model silhouette at the known first pose (Section IV: the next frame's
        first iterations use densities of the right regions), pasted into `base` (default: an empty state
        with as many feature channels as the crops give)."""
        f = self.config.density_factor
        check_grid(ctx.crops.shape[1:3], f)
        dtype = ctx.pose.T_world_root.dtype
        C, H, W = ctx.offsets.shape[0], ctx.cameras.height, ctx.cameras.width
        channels = jax.eval_shape(lambda im: feature_channels(im, self.config.texture), ctx.crops[0]).shape[-1]
        empty = initial_state(C, H, W, channels, f, dtype) if base is None else base
        rp = params.region

        def per_camera(image, face_id):
            phi0 = band_sdf(face_id >= 0).astype(dtype)
            features = smoothed_features(image, self.config.texture, rp.feature_sigma).astype(dtype)
            return phi0, _densities(features, phi0, rp.density_band, rp, f)

        phi0, dens = jax.vmap(per_camera)(ctx.crops, ctx.render.face_id)
        return _paste_state(empty, phi0, dens, ctx.offsets, f, ctx.scales)

    def start(self, ctx: FrameContext, state: RegionState, host, params) -> LevelSetFrame:
        f = self.config.density_factor
        check_grid(ctx.crop_shape, f)
        dtype = ctx.pose_t.T_world_root.dtype
        sigma = params.region.feature_sigma
        features = jax.vmap(lambda im: smoothed_features(im, self.config.texture, sigma))(ctx.crops).astype(dtype)
        coarse = (ctx.crop_shape[0] // f, ctx.crop_shape[1] // f)
        coarse_offsets = ctx.offsets // f if ctx.scales is None else ctx.offsets / f
        carried = _crop_densities(state.densities, coarse_offsets, coarse, ctx.scales)
        return LevelSetFrame(features, jax.tree.map(lambda a: a.astype(dtype), carried), state.has_densities)

    def round_start(self, ctx: FrameContext, state, frame: LevelSetFrame, params) -> LevelSetCarry:
        zero = jnp.zeros(frame.features.shape[:3], frame.features.dtype)
        return LevelSetCarry(zero, zero, frame.carried, frame.has_densities, jnp.zeros((), jnp.int32))

    def rows(self, ctx: FrameContext, state, frame: LevelSetFrame, carry: LevelSetCarry, pose: Pose, render, round_index,
             params) -> tuple[Correspondences, LevelSetCarry]:
        """Segment each crop at the round's render, match the contours, one `Cue.REGION` row per match.

        Density estimates are paid only where used: densities from Φ0 only while a camera has none
        (`lax.cond` over all cameras: under the camera vmap a per-camera branch would compute both), the
        re-estimate from Φ only when the next round needs it (no densities carried in, or
        `RegionConfig.fixed_densities` off); the densities carried to the next frame are estimated once,
        in `update`.
        """
        config, rp, f = self.config, params.region, self.config.density_factor
        dtype = frame.features.dtype
        first = round_index == 0
        sil = render.face_id >= 0
        phi0 = jax.vmap(lambda s: band_sdf(s).astype(dtype))(sil)

        def from_phi(phi):
            return jax.vmap(lambda feats, p: _densities(feats, p, rp.density_band, rp, f))(frame.features, phi)

        def per_camera_where(mask, a_tree, b_tree):
            return jax.tree.map(lambda a, b: jnp.where(mask.reshape((-1,) + (1,) * (a.ndim - 1)), a, b), a_tree, b_tree)

        has = carry.has_densities
        dens = jax.lax.cond(jnp.all(has), lambda: carry.densities,
                            lambda: per_camera_where(has, carry.densities, from_phi(phi0)))
        carried_in = frame.has_densities
        # Warm start and fixed densities only with densities from the previous frame: without them the
        # first round's densities come from Φ0 at the unrefined pose, and keeping them (or a segmentation
        # made with them) holds the pose where it started (a 2-joint chain stayed 0.06 rad off).
        if config.warm_start:
            start = jnp.where((~first & carried_in).reshape(-1, 1, 1), carry.phi, phi0)
        else:
            start = phi0
        phi = jax.vmap(lambda feats, p0, p_init, d: evolve(p_init, p0, data_term(feats, d, f), rp, config.levelset_iterations,
                                                           config.redistance_every))(frame.features, phi0, start, dens)
        if config.fixed_densities:
            dens_next = jax.lax.cond(jnp.all(carried_in), lambda: dens, lambda: per_camera_where(carried_in, dens, from_phi(phi)))
        else:
            dens_next = from_phi(phi)
        _, target, p_model, part, weight, edge_normal = jax.vmap(
            lambda p0, p, s, pm, pid: contour_matches(p0, p, s, pm, pid, rp, config.capacity, config.matching)
        )(phi0, phi, sil, render.p_model, render.part_id)
        num_cams = ctx.offsets.shape[0]
        target = ctx.to_full(target)  # crop → full-frame pixels
        cam_index = jnp.broadcast_to(jnp.arange(num_cams, dtype=jnp.int32)[:, None], weight.shape)
        corr = correspondences_from_pixels(
            ctx.cameras, target.reshape(-1, 2), cam_index.reshape(-1), p_model.reshape(-1, 3), part.reshape(-1),
            weight.reshape(-1), undistort=False, cue=Cue.REGION,
            edge_normal=edge_normal.reshape(-1, 2) if config.edge_rows else None,
            # Point rows (tangent weight 1) for a camera without carried densities: its segmentation is
            # made with densities from an unrefined Φ0, and the along-contour pull steadies the pose
            # (the cracker box at its true pose, no densities: 9.1 mm with edge rows, 4.1 with point rows).
            tangent_weight=jnp.broadcast_to(
                jnp.where(carried_in, rp.tangent_weight, 1.0)[:, None].astype(dtype), weight.shape).reshape(-1),
        )
        corr = weights_per_pixel(corr, ctx.cameras, ctx.model, pose.T_world_root, pose.theta, params.rows_per_px)
        new = LevelSetCarry(phi, phi0, dens_next, jnp.ones_like(carry.has_densities), jnp.sum(weight > 0).astype(jnp.int32))
        return corr, new

    def update(self, ctx: FrameContext, state: RegionState, frame: LevelSetFrame, carry: LevelSetCarry, pose, params) -> RegionState:
        """The last segmentation and the densities estimated from it, in full-frame coordinates."""
        rp, f = params.region, self.config.density_factor
        dens = jax.vmap(lambda feats, p: _densities(feats, p, rp.density_band, rp, f))(frame.features, carry.phi)
        return _paste_state(state, carry.phi, dens, ctx.offsets, f, ctx.scales)

    def evidence(self, ctx, state, frame, carry: LevelSetCarry, pose, render, params) -> dict:
        return {"segmentation": carry.phi}

    def weight_scale(self, counts: FusionCounts, params, prediction: bool):
        return params.weights.region  # contour rows: w_C = 1 × the user factor


# --- region-only refinement on the same loop ---------------------------------------------------------


class RegionProblem(eqx.Module):
    """The static side of a refinement: model, mesh, cameras, raster plan and settings."""

    mesh: Mesh
    model: KinematicModel
    cameras: Camera  # stacked (C on the leading axis)
    plan: RasterPlan = eqx.field(static=True)
    config: RegionConfig = eqx.field(static=True)


class RegionResult(eqx.Module):
    """Outcome of `refine_pose_region`.

    Attributes:
        T_world_root: (4, 4) refined root pose; theta: (J,) refined joint angles.
        status: int32 `Status` (OK, MAX_STEPS if it did not settle, RENDER_OVERFLOW, OUT_OF_VIEW, ...).
        iterations: int32 outer rounds run.
        num_matches: int32 contour correspondences with weight in the last round.
        correspondences: the last round's `Cue.REGION` set (capacity C x `RegionConfig.capacity`).
        state: the updated `RegionState`.
        phi0: (C, h, w) the model's signed distance at the last round's render (crop).
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


class _RegionOnlyParams(eqx.Module):
    """The parameters the level-set modality reads, for region-only refinement."""

    region: RegionParams
    weights: CueWeights
    rows_per_px: jax.Array = eqx.field(default_factory=lambda: jnp.zeros(()))  # alone, the rows' unit changes nothing


def _region_context(problem: RegionProblem, images, offsets, T, theta) -> FrameContext:
    crop_shape = images.shape[1:3]
    cams = crop_camera(problem.cameras, offsets, crop_shape)
    ren = jax.vmap(lambda cam: render(problem.mesh, cam, T, theta, problem.model, problem.plan))(cams)
    return FrameContext(
        mesh=problem.mesh, model=problem.model, cameras=problem.cameras, crop_cameras=cams, offsets=offsets,
        frames=None, crops=images, previous=None, previous_crops=None, data_weight=None, render_t=ren,
        pose_t=Pose(T, theta), plan=problem.plan,
    )


@eqx.debug.assert_max_traces(max_traces=None)  # counts traces (`eqx.debug.get_num_traces`), never fails
def refine_pose_region(problem: RegionProblem, images, offsets, state: RegionState, params: RegionParams, T_init, theta_init):
    """Region-only refinement of χ = (ξ, Θ) on one frame of C cameras (the tracker's loop, one modality).

    Args:
        problem: mesh, kinematic model, stacked cameras (C), raster plan and `RegionConfig`.
        images: (C, h, w, 3) or (C, h, w) crops of the frames (0-255) at `offsets`.
        offsets: (C, 2) int32 (y0, x0) of each crop in its full frame (multiples of density_factor).
        state: `RegionState` carried from the previous frame.
        params: `RegionParams`.
        T_init: (4, 4) initial root pose (model → world); theta_init: (J,) initial joint angles.

    Returns:
        `RegionResult`.
    """
    dtype = T_init.dtype
    theta_init = jnp.asarray(theta_init, dtype)
    if images.ndim == 3:
        images = images[..., None]
    modality = LevelSetRegion(problem.config)
    ctx = _region_context(problem, images, offsets, T_init, theta_init)
    p = _RegionOnlyParams(params, CueWeights())
    frame = modality.start(ctx, state, None, p)
    zero = jnp.zeros((), dtype)
    settings = RefineSettings(params.settle_motion, params.joint_prior, zero, zero, depth_scaled=False)
    res = refine_rounds((modality,), ctx, (state,), (frame,), Pose(T_init, theta_init), p, settings,
                        problem.config.outer_iterations, problem.config.solver_steps)
    carry = res.carries[0]
    new_state = modality.update(ctx, state, frame, carry, res.pose, p)
    return RegionResult(res.pose.T_world_root, res.pose.theta, res.status, res.rounds, carry.num_matches, res.rows,
                        new_state, carry.phi0, carry.phi)


def densities_at_pose(problem: RegionProblem, images, offsets, state: RegionState, params: RegionParams, T_world_root, theta):
    """The region state of a frame whose pose is known (the tracker's first frame). Jittable.

    Args:
        problem, images (C, h, w, 3) crops at offsets (C, 2), state: as for `refine_pose_region`.

    Returns:
        `RegionState` with Φ = Φ0(χ) and the densities of frame t in full-frame coordinates.
    """
    T_world_root = jnp.asarray(T_world_root)
    ctx = _region_context(problem, images, offsets, T_world_root, jnp.asarray(theta, T_world_root.dtype))
    start = StartContext(problem.mesh, problem.model, problem.cameras, ctx.crop_cameras, offsets, None, images,
                         ctx.render_t, ctx.pose_t, problem.plan)
    base = jax.tree.map(lambda a: a.astype(T_world_root.dtype) if jnp.issubdtype(a.dtype, jnp.floating) else a, state)
    return LevelSetRegion(problem.config).init_state(start, _RegionOnlyParams(params, CueWeights()), base)


_refine_jit = eqx.filter_jit(refine_pose_region)
