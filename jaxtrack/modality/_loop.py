"""The tracker's one refinement loop over modalities: rows of every modality → one fused solve, repeated.

`fuse_rows` applies each modality's Section V weight rule to its raw rows (n_C from the contour
modalities, n_OF from the prediction's reference modality) and concatenates them; `refine_rounds`
runs rounds of {one render per camera at the current pose (when a modality asks), rows of every
modality, one Gauss-Newton solve with the joint and pose priors} until the pose settles, as a
`lax.while_loop` with a named state (`RoundState`). Both are jittable and vmappable over parameters.
With `RefineSettings.motion_robust_px` > 0 each round weighs the motion modalities' rows by a Cauchy loss of
their reprojection error at the round's pose (`cauchy_weights`, `reprojection_px`; IRLS from the raw rows, so the
weights do not compound over rounds).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._status import Status, first_failure, status_where
from ..geometry import part_points_world, part_transforms, project_ideal, project_points
from ..render import RenderOutput, render
from ..solve import Correspondences, JointPrior, PosePrior, SolverConfig, concatenate_correspondences, solve_pose
from ._protocol import FrameContext, FusionCounts, Modality, Pose


def live_count(corr: Correspondences) -> jax.Array:
    """Rows with positive weight (a float of the set's dtype)."""
    return jnp.sum(corr.weight > 0).astype(corr.weight.dtype)


def fuse_rows(modalities: Sequence[Modality], row_sets: Sequence[Correspondences], params, prediction: bool = False) -> Correspondences:
    """Section V fusion over modalities: each set scaled by its modality's `weight_scale`, then concatenated.

    Args:
        modalities: the configured modalities (static); row_sets: their raw rows, one set each.
        params: the tracker's parameters (user factors live there).
        prediction: True in the prediction step (the reference count is n_OF instead of n_C). Static.

    A configuration without the reference modality counts the next one instead (static): the refinement without a
    contour modality counts n_OF, and without the flow the motion modalities' rows are the reference (SIFT alone
    counts its own). A zero reference used to zero every motion weight: SIFT alone and region + SIFT made no
    prediction (`experiments/large_motion.py`: SIFT's "prediction" was the frame-t pose in every trial).

    Returns:
        One `Correspondences` (capacity = sum of the sets' capacities).
    """
    counts = [live_count(c) for c in row_sets]
    dtype = row_sets[0].weight.dtype
    flags = ((lambda m: m.prediction_reference) if prediction else (lambda m: m.contour),
             lambda m: m.prediction_reference, lambda m: m.motion)
    flag = next((f for f in flags if any(f(m) for m in modalities)), flags[0])
    reference = sum((n for m, n in zip(modalities, counts) if flag(m)), jnp.zeros((), dtype))
    scaled = [
        c.with_weight(c.weight * m.weight_scale(FusionCounts(reference, n), params, prediction).astype(dtype))
        for m, c, n in zip(modalities, row_sets, counts)
    ]
    return concatenate_correspondences(*scaled) if len(scaled) > 1 else scaled[0]


def render_crops(ctx: FrameContext, pose: Pose) -> RenderOutput:
    """The model at `pose` in every crop (C leading): one render per camera."""
    return jax.vmap(lambda cam: render(ctx.mesh, cam, pose.T_world_root, pose.theta, ctx.model, ctx.plan))(ctx.crop_cameras)


PROBE_VERTICES = 64


def max_pixel_motion(ctx: FrameContext, before: Pose, after: Pose) -> jax.Array:
    """Largest image motion (px, over the cameras) of up to `PROBE_VERTICES` mesh vertices from `before` to
    `after`: whether a render made at `before` still stands for `after`."""
    mesh, model = ctx.mesh, ctx.model
    idx = np.unique(np.linspace(0, mesh.num_vertices - 1, min(PROBE_VERTICES, mesh.num_vertices)).astype(np.int32))
    verts, part = mesh.vertices[idx], mesh.vertex_part[idx]

    def world(p: Pose):
        A = part_transforms(model, p.T_world_root, p.theta)[part]
        return jnp.einsum("nij,nj->ni", A[:, :3, :3], verts.astype(A.dtype)) + A[:, :3, 3]

    a, b = world(before), world(after)
    px_a = jax.vmap(lambda cam: project_points(cam, a)[0])(ctx.crop_cameras)
    px_b = jax.vmap(lambda cam: project_points(cam, b)[0])(ctx.crop_cameras)
    return jnp.max(jnp.linalg.norm(px_a - px_b, axis=-1))


def reprojection_px(ctx: FrameContext, corr: Correspondences, pose: Pose) -> jax.Array:
    """(N,) distance (px of the crops) between each row's pixel and its model point projected at `pose` into the
    row's crop camera (ideal pinhole, as the rows' pixels are stored; `jaxtrack.geometry.project_ideal`)."""
    p_world = part_points_world(ctx.model, pose.T_world_root, pose.theta, corr.p_model, corr.part)
    index = jnp.clip(corr.camera, 0, ctx.crop_cameras.K.shape[0] - 1)
    px, _ = project_ideal(ctx.crop_cameras, p_world, index)
    return jnp.linalg.norm(px - corr.pixel, axis=-1)


def cauchy_weights(error, scale) -> jax.Array:
    """IRLS weights of the Cauchy loss, 1 / (1 + (e / s)²); all ones where `scale` ≤ 0 (off)."""
    s = jnp.where(scale > 0, scale, 1.0)
    return jnp.where(scale > 0, 1.0 / (1.0 + (error / s) ** 2), 1.0).astype(error.dtype)


def mean_motion(model, corr: Correspondences, before: Pose, after: Pose) -> jax.Array:
    """Mean distance (mm) the weighted rows' model points move from `before` to `after` (∞ without rows)."""
    def world(p: Pose):
        A = part_transforms(model, p.T_world_root, p.theta)[corr.part]
        return jnp.einsum("nij,nj->ni", A[:, :3, :3], corr.p_model) + A[:, :3, 3]

    live = corr.weight > 0
    d = jnp.linalg.norm(world(after) - world(before), axis=-1)
    n = jnp.sum(live)
    return jnp.where(n > 0, jnp.sum(jnp.where(live, d, 0.0)) / jnp.maximum(n, 1), jnp.inf)


class RefineSettings(eqx.Module):
    """Numeric settings of the loop (arrays: vmap/grad over them costs no recompilation).

    Attributes:
        settle_motion: the pose has settled when the rows' model points move less than this (mm) in a round.
        joint_prior: relative stiffness of the `JointPrior` (anchored at the refinement's start).
        pose_prior_rotation, pose_prior_translation: relative stiffnesses of the `PosePrior` (anchored
            where the rounds start, or at `refine_rounds`' `anchor`).
        render_reuse_px: a round reuses the last round's render when no probe vertex moved more than this
            many pixels since it was made (0: render every round).
        pose_prior_rotation_abs, pose_prior_translation_abs: absolute stiffnesses of the `PosePrior`.
        prior_follows_round: 1: the pose prior pulls toward each round's starting pose (M3T's damping per
            iteration); 0: toward the anchor (the prediction) for the whole frame.
        depth_invariance: p of each round's solve (`solve_pose(ray_origins=ctx.cameras' centres)`): residuals
            × (Z₀ / Z)^p; 0: eq. 4 as it is. Read only where `depth_scaled`.
        depth_scaled: (static) whether the solves take the cameras' centres and `depth_invariance` (True, the
            default); False: eq. 4 as it is whatever `depth_invariance` holds, which lets each solve sum its rows per
            part once instead of at every Gauss-Newton iterate where they are many (`SolverConfig.moments_from_rows`,
            `jaxtrack.solve._moments.plane_moments`; chains' default).
        motion_robust_px: scale s (px of the crops) of a Cauchy loss on the motion modalities' rows: each round
            weighs a row by 1 / (1 + (e / s)²), e its reprojection error at the round's pose (IRLS), so that rows
            the pose does not explain (an occluder's flow) lose their pull; ≤ 0: off (eq. 5 as it is).
        motion_rounds, motion_late_factor: the motion modalities' rows count fully in rounds 0 .. motion_rounds − 1
            and × motion_late_factor in the later ones (0: those fit the contour modalities alone, from where the
            motion brought the pose; M3T's split); motion_rounds ∞: every round (eq. 5, the default). With K finite
            and f ≠ 1 the loop does not stop as settled before round K + 1 (the rounds after K run).
    """

    settle_motion: jax.Array
    joint_prior: jax.Array
    pose_prior_rotation: jax.Array
    pose_prior_translation: jax.Array
    render_reuse_px: jax.Array = eqx.field(default_factory=lambda: jnp.zeros(()))
    pose_prior_rotation_abs: jax.Array = eqx.field(default_factory=lambda: jnp.zeros(()))
    pose_prior_translation_abs: jax.Array = eqx.field(default_factory=lambda: jnp.zeros(()))
    prior_follows_round: jax.Array = eqx.field(default_factory=lambda: jnp.zeros(()))
    depth_invariance: jax.Array = eqx.field(default_factory=lambda: jnp.zeros(()))
    motion_robust_px: jax.Array = eqx.field(default_factory=lambda: -jnp.ones(()))
    motion_rounds: jax.Array = eqx.field(default_factory=lambda: jnp.full((), jnp.inf))
    motion_late_factor: jax.Array = eqx.field(default_factory=lambda: jnp.zeros(()))
    depth_scaled: bool = eqx.field(static=True, default=True)


class RoundState(eqx.Module):
    """The carry of `refine_rounds` (named, never positional).

    Attributes:
        pose: the current pose; carries: one per modality (its `round_start` / `rows` carry).
        round_index: rounds run; settled: the last round moved the rows' points less than the settle bound
            (or no row was usable: the contours agree); status: the rounds' combined `Status`.
        rows: the last round's fused set.
        render, render_pose: the last render in the crops (None when no modality renders) and the pose it shows.
        renders: renders made so far.
    """

    pose: Pose
    carries: tuple
    round_index: jax.Array
    settled: jax.Array
    status: jax.Array
    rows: Correspondences
    render: RenderOutput | None
    render_pose: Pose
    renders: jax.Array


class RefineResult(eqx.Module):
    """Outcome of `refine_rounds`: pose, carries, status (OK, MAX_STEPS if unsettled, ...), rounds, rows, renders."""

    pose: Pose
    carries: tuple
    status: jax.Array
    rounds: jax.Array
    rows: Correspondences
    renders: jax.Array


def _round(modalities, ctx, contexts, states, frames, params, settings: RefineSettings, anchor: Pose, solver: SolverConfig,
           state: RoundState) -> RoundState:
    pose = state.pose
    ren, renders = None, state.renders
    if any(m.needs_render for m in modalities):
        fresh = (state.round_index == 0) | (max_pixel_motion(ctx, state.render_pose, pose) > settings.render_reuse_px)
        ren = jax.lax.cond(fresh, lambda: render_crops(ctx, pose), lambda: state.render)
        renders = renders + fresh.astype(jnp.int32)
    sets, carries = [], []
    for m, mctx, s, f, c in zip(modalities, contexts, states, frames, state.carries):
        rows, c = m.rows(mctx, s, f, c, pose, ren, state.round_index, params)
        if m.motion:
            live = jnp.where(state.round_index < settings.motion_rounds, 1.0, settings.motion_late_factor).astype(rows.weight.dtype)
            rows = rows.with_weight(rows.weight * live
                                    * cauchy_weights(reprojection_px(ctx, rows, pose), settings.motion_robust_px))
        sets.append(rows)
        carries.append(c)
    fused = fuse_rows(modalities, sets, params)
    sol = solve_pose(
        ctx.model, fused, pose.T_world_root, pose.theta, solver,
        prior=JointPrior(anchor.theta, settings.joint_prior),
        pose_prior=PosePrior(jnp.where(settings.prior_follows_round > 0.5, pose.T_world_root, anchor.T_world_root),
                             settings.pose_prior_rotation, settings.pose_prior_translation,
                             settings.pose_prior_rotation_abs, settings.pose_prior_translation_abs),
        ray_origins=ctx.cameras.center_world if settings.depth_scaled else None, depth_invariance=settings.depth_invariance,
    )
    new = Pose(sol.T_world_root, sol.theta)
    settled = mean_motion(ctx.model, fused, pose, new) < settings.settle_motion
    no_rows = sol.status == Status.TOO_FEW  # no usable row at all: the contours agree, settled
    solve_status = jnp.where(no_rows | (sol.status == Status.MAX_STEPS), Status.OK, sol.status)
    parts = [solve_status]
    if ren is not None:
        parts = [status_where(~jnp.any(ren.face_id >= 0), Status.OUT_OF_VIEW, Status.OK), solve_status,
                 status_where(jnp.any(ren.overflow), Status.RENDER_OVERFLOW, Status.OK)]
    render_pose = pose if ren is None else jax.tree.map(lambda a, b: jnp.where(fresh, a, b), pose, state.render_pose)
    return RoundState(new, tuple(carries), state.round_index + 1, settled | no_rows,
                      first_failure(*parts).astype(jnp.int32), fused, ren, render_pose, renders)


def refine_rounds(
    modalities: Sequence[Modality],
    ctx: FrameContext,
    states: Sequence[Any],
    frames: Sequence[Any],
    start: Pose,
    params,
    settings: RefineSettings,
    rounds: int,
    solver_steps: int,
    anchor: Pose | None = None,
    min_rounds: int = 0,
    contexts: Sequence[FrameContext] | None = None,
) -> RefineResult:
    """Rounds of {rows of every modality at the current pose → one fused solve} until settled. Jittable.

    Args:
        modalities: the configured modalities (static); states, frames: their states and per-frame data.
        ctx: the step's `FrameContext`; start: the pose the rounds start from (the prediction).
        params: the tracker's parameters (weight rules read their factors there).
        settings: settle bound and prior strengths (`RefineSettings`).
        rounds: cap on rounds (static); solver_steps: Gauss-Newton steps per round (static).
        anchor: where the joint and pose priors pull (default `start`).
        min_rounds: rounds run before the pose may count as settled (static; e.g. a coarse-to-fine schedule).
        contexts: one context per modality (with its prepared data); default `ctx` for all.

    Returns:
        `RefineResult`; its status is OK, MAX_STEPS (did not settle within `rounds`), OUT_OF_VIEW,
        RENDER_OVERFLOW (the host re-plans and redoes the frame) or the solver's failure.
    """
    anchor = start if anchor is None else anchor
    contexts = tuple(ctx for _ in modalities) if contexts is None else tuple(contexts)
    solver = SolverConfig(max_steps=solver_steps)
    carries0 = tuple(m.round_start(c, s, f, params) for m, c, s, f in zip(modalities, contexts, states, frames))

    def body(state: RoundState) -> RoundState:
        return _round(modalities, ctx, contexts, states, frames, params, settings, anchor, solver, state)

    # With the motion rows weighed down after round K, rounds 0 .. K may not end the loop as settled: the rounds after
    # K are the ones the setting is for (traced; K = ∞ or a factor of 1 leaves `min_rounds` as it is).
    late = jnp.isfinite(settings.motion_rounds) & (settings.motion_late_factor != 1)
    settle_from = jnp.maximum(min_rounds, jnp.where(late, settings.motion_rounds + 1, 0))

    def cond(state: RoundState):
        running = (state.status == Status.OK) | (state.status == Status.RENDER_OVERFLOW)
        return (state.round_index < rounds) & ~(state.settled & (state.round_index >= settle_from)) & running

    zero_i, ok = jnp.zeros((), jnp.int32), jnp.asarray(Status.OK, jnp.int32)
    renders_ = any(m.needs_render for m in modalities)

    def probe():  # one round's render and fused rows, without its solve (tracing a solve costs seconds)
        ren = render_crops(ctx, start) if renders_ else None
        sets = [m.rows(mc, s, f, c, start, ren, zero_i, params)[0]
                for m, mc, s, f, c in zip(modalities, contexts, states, frames, carries0)]
        return fuse_rows(modalities, sets, params), ren

    # The carry's rows and render have the structure of one round's: zeros of that shape (traced, not run).
    shapes = jax.eval_shape(probe)
    zeros = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)
    first = RoundState(start, carries0, zero_i, jnp.zeros((), bool), ok, zeros[0], zeros[1], start, zero_i)
    out = jax.lax.while_loop(cond, body, first)
    status = first_failure(out.status, status_where(out.settled, Status.OK, Status.MAX_STEPS))
    return RefineResult(out.pose, out.carries, status.astype(jnp.int32), out.round_index, out.rows, out.renders)
