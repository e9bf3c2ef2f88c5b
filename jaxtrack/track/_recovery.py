"""Recovery after a LOST frame (issue 24): a batch of pose hypotheses, scored by the region energy on the
correspondence lines in one vmapped call; the best few refined by the lines; the best refined pose back. (The
tracker tries the keyframes' PnP re-detection first, `_keyframes.py`, where `RecoveryConfig.keyframes` is set.)

Hypotheses (K = R · Q, static): the R reference poses (the lost frame's result, which usually keeps the
silhouette, and the last pose reported OK) each turned about the model's centre by Q rotations that
cover SO(3) around it: the identity, and `angles_deg` about each of the icosphere's axes
(`axis_subdivisions` 1: 42 axes, 21 of them for 180°; 6 angles: Q = 232).

Score of a pose (the region energy of eq. 11 in the limit of a hard shape prior, read on the lines): each
line of the sparse viewpoint model's nearest view is read at `score_scale` px per segment; the segments on
the model's inside should be foreground and those outside background, and a segment's posterior of its
side is σ(±Σ log h_f/h_b) (the lines' colour histograms). The score is the mean posterior over segments and
lines, an invalid line (off the image, too short) counting ½ (no evidence): 1 when every segment agrees, ½
for a pose the colours cannot tell from any other. The refined candidates are compared at the finest
scale of the lines' schedule (`final_scale`).

One compiled program per tracker (rig, mesh, view model and these static settings); `Tracker` compiles it in a
background thread at the first frame it reports UNCERTAIN or LOST (`Tracker.warm_up_recovery`; recovery is on by
default, `TrackerConfig.recovery`), so no frame waits for the compile: lost frames wait for it at most
`jaxtrack.track._tracker.RECOVERY_COMPILE_WAIT_S` (1 s, a trace and a cache hit) in all, and a frame lost while it
still compiles stays LOST without the search. With the warm-up off ($JAXTRACK_RECOVERY_WARMUP=0) the first lost
frame compiles it, and `Tracker.recover` called directly waits for it.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._status import Status, is_usable
from ..cues.lines import ColourHistograms, LineConfig, LineParams, SparseViewModel, line_rows
from ..cues.lines._histograms import LogOddsTable, log_odds_image, log_odds_table
from ..cues.lines._lines import DEFAULT_LINE_CONFIG, M3T_SOLVER, project_contour, sample_lines, schedule
from ..cues.lines._viewmodel import icosphere, points_for_pose
from ..geometry import Camera, rigid_model, so3_exp
from ..solve import solve_pose
from ._keyframes import KeyframeConfig


class RecoveryConfig(eqx.Module):
    """Static settings of the hypothesis search (they shape the compiled program).

    Attributes:
        axis_subdivisions: icosphere subdivisions of the rotation axes (0: 12 axes, 1: 42, 2: 162).
        angles_deg: rotation angles about each axis (the identity is always a hypothesis).
        refine: hypotheses refined by the lines (the best by score; the lost frame's own pose is always one).
        score_scale: px per segment of the hypotheses' score (coarse: the lines reach 19 · scale px).
        final_scale: px per segment of the refined candidates' score.
        max_skip: backoff of a persistently lost object: after k searches in a row that recovered nothing, the next
            min(2^(k−1) − 1, max_skip) lost frames are not searched (searched: lost frames 1, 2, 4, 8, 16, 25, 34,
            ... of a run; a frame not LOST (OUT_OF_VIEW too), or a RECOVERED one, starts over; 0: every lost frame).
            A skipped frame stays LOST exactly as one whose search found nothing (a refused step from a found pose
            leaves the host state, SIFT's cached keypoints, as it was); a search that raised counts as one that found
            nothing; a LOST frame stepped with `recover=False` neither uses a skip nor starts over. Measured: README,
            "Finding it again".
        keyframes: re-detection first (`jaxtrack.track._keyframes`: SIFT keyframes with model points, PnP + RANSAC),
            or None: the hypotheses alone.
        hypotheses: when the keyframes find nothing, search the pose hypotheses scored on the lines (on by default:
            on the loss experiment's sequences it RECOVERED 3 frames, all within 5 cm / 5°, which the keyframes
            never did: mean within 5 cm / 5° 66.7 % with the keyframes alone → 79.8 % with the hypotheses and the
            backoff (part of it chance, README), 81.3 % with RBOT resets; the 90-180° flips it found were
            refused by `margin` or by the step after it; experiments/results/recovery_opt_in.md against
            recovery_keyframes_only.md). Earlier every pose it found (17 in three runs) was 70-174° off: a search far
            from the truth can still take a wrong pose.
        margin: a found pose turned by more than `near_deg` from the lost pose is taken only when its score beats
            the lost frame's own refined pose by this much (the score cannot tell a symmetric object's turned poses
            apart: a 180° flip of a box scores within 0.01 of the right pose; measured in
            experiments/results/recovery_opt_in.md).
        near_deg: a found pose within this rotation of the lost pose needs only to score no worse than the lost
            pose's own refinement; the normal step from it then decides (`Tracker._restart`). So the lost pose's own
            refinement by the lines is tried whenever nothing scores better (a lost frame then costs a search and a
            second step; it RECOVERED one frame of the occluded S = 4 sequence at 1°). The margin is for the turned
            poses of a symmetric object, and a box's are 90° or more away: 45° is half of that (an object symmetric
            every 60°, or about an axis, is not covered; the translation is not compared). A correction that near
            scores like the lost pose (the occluded frame-rate sequences: found 1-5° off from lost poses 10-17° off,
            at the lost pose's score to 0.001). Read off the loss experiment's evaluation sequences. Like `margin`, a
            host-side rule that is part of the static configuration (changing it compiles the search again).
    """

    axis_subdivisions: int = eqx.field(static=True, default=1)
    angles_deg: tuple = eqx.field(static=True, default=(20.0, 40.0, 70.0, 100.0, 140.0, 180.0))
    refine: int = eqx.field(static=True, default=4)
    score_scale: int = eqx.field(static=True, default=5)
    final_scale: int = eqx.field(static=True, default=2)
    margin: float = eqx.field(static=True, default=0.02)
    near_deg: float = eqx.field(static=True, default=45.0)
    max_skip: int = eqx.field(static=True, default=8)
    keyframes: KeyframeConfig | None = eqx.field(static=True, default_factory=KeyframeConfig)
    hypotheses: bool = eqx.field(static=True, default=True)

    def __check_init__(self):
        if not 0 <= self.axis_subdivisions <= 3:
            raise ValueError(f"RecoveryConfig.axis_subdivisions must be 0..3, got {self.axis_subdivisions}")
        if self.refine < 1 or self.score_scale < 1 or self.final_scale < 1:
            raise ValueError("RecoveryConfig: refine, score_scale and final_scale must be ≥ 1")
        if self.max_skip < 0:
            raise ValueError(f"RecoveryConfig.max_skip must be ≥ 0, got {self.max_skip}")
        if not 0.0 <= self.near_deg <= 180.0:
            raise ValueError(f"RecoveryConfig.near_deg must be in [0, 180], got {self.near_deg}")
        if any(not 0 < a <= 180 for a in self.angles_deg):
            raise ValueError(f"RecoveryConfig.angles_deg must be in (0, 180], got {self.angles_deg}")

    def rotation_offsets(self) -> np.ndarray:
        """(Q, 3) rotation vectors (rad) of the hypotheses about a reference: 0, then every angle about every axis."""
        axes, _ = icosphere(self.axis_subdivisions)
        axes = axes / np.linalg.norm(axes, axis=1, keepdims=True)
        # 180° about a and about −a are one rotation: one hemisphere of axes for it (the icosphere's come in ± pairs)
        first = axes[np.arange(len(axes)), np.argmax(np.abs(axes) > 1e-9, axis=1)]
        half = axes[first > 0]
        turned = [(half if a >= 180.0 else axes) * np.radians(a) for a in self.angles_deg]
        return np.concatenate([np.zeros((1, 3))] + turned, axis=0)


class RecoveryResult(eqx.Module):
    """What `recover_pose` found.

    Attributes:
        T_world_root: (4, 4) the best refined pose.
        score: its score at `final_scale` (mean posterior of the lines' segments, ½ = no evidence).
        own_score: the same score of reference 0 refined (the lost frame's own pose: what recovery must beat).
        index: int32 hypothesis the best pose was refined from (0: reference 0 itself).
        scores: (K,) every hypothesis' score at `score_scale`.
        status: int32 `Status` of the best candidate's last solve.
    """

    T_world_root: jax.Array
    score: jax.Array
    own_score: jax.Array
    index: jax.Array
    scores: jax.Array
    status: jax.Array


def line_agreement(camera: Camera, T_world_root, view_model: SparseViewModel, log_odds, params: LineParams, scale: int,
                   config: LineConfig = DEFAULT_LINE_CONFIG):
    """(agreement, valid lines) of a pose in one camera: the mean over the view's N lines of the mean over their
    segments of the posterior of the side the pose puts them on (inside: foreground), invalid lines ½. Jittable.

    Args:
        camera: a single camera; T_world_root: (4, 4) the pose; view_model: the sparse viewpoint model.
        log_odds: (H, W) the image's per-pixel log(h_f / h_b) (`jaxtrack.cues.lines.log_odds_image` of the camera's
            colour histograms): a segment's log odds is the sum over its pixels, as `segment_log_odds` sums them,
            read here as one scalar gather per pixel (the colours' cells and logs computed once per frame, not once
            per hypothesis: 165 → 44 ms for the 464 hypotheses of a 320x240 frame).
        scale: px per segment, a static int (clamped to [1, config.max_scale]).
    """
    dtype = camera.K.dtype
    T = jnp.asarray(T_world_root, dtype)
    points = points_for_pose(view_model, camera, T)
    proj = project_contour(camera, T, points)
    s = min(max(int(scale), 1), config.max_scale)
    S = config.num_segments
    samples = sample_lines(log_odds[..., None], proj.center, proj.normal, s, config)  # "colour": the pixel's log odds
    per_pixel = jnp.where(samples.mask, samples.colour[..., 0], 0.0)[:, : S * s]
    seg_lo = per_pixel.reshape(per_pixel.shape[0], S, s).sum(-1)  # (N, S) inside → outside
    half = (S - 1) / 2  # the middle segment straddles the contour: left out
    index = jnp.arange(S)
    side = jnp.where(index < half, 1.0, jnp.where(index > half, -1.0, 0.0)).astype(dtype)
    agree = jax.nn.sigmoid(side[None, :] * seg_lo)
    line_score = jnp.sum(jnp.where(side[None, :] != 0, agree, 0.0), axis=1) / jnp.sum(side != 0)
    z = jnp.where(proj.valid, proj.depth, 1.0)
    seg_px = jnp.asarray(s, dtype) * samples.step
    continuous = jnp.minimum(points.foreground_distance, points.background_distance) * camera.K[0, 0] / (z * seg_px)
    valid = proj.valid & samples.inside & (continuous >= params.min_continuous_distance)
    n = jnp.maximum(jnp.sum(points.valid), 1)
    score = (jnp.sum(jnp.where(valid, line_score, 0.0)) + 0.5 * jnp.sum(points.valid & ~valid)) / n
    return score.astype(dtype), jnp.sum(valid).astype(jnp.int32)


def rig_log_odds(frames, histograms: ColourHistograms | LogOddsTable, params: LineParams):
    """(C, H, W) every camera's per-pixel log odds (`log_odds_image`) of frames (C, H, W, 3) with its histograms
    or their `LogOddsTable`s (leading C axis), in the histograms' dtype."""
    return jnp.stack([log_odds_image(jax.tree.map(lambda a, c=c: a[c], histograms), frames[c], params.posterior_prior)
                      for c in range(frames.shape[0])])


def rig_agreement(cameras: Camera, T_world_root, view_model, frames, histograms, params: LineParams, scale: int,
                  config: LineConfig = DEFAULT_LINE_CONFIG, log_odds=None):
    """`line_agreement` over a rig (C stacked cameras, frames (C, H, W, 3), histograms with a leading C axis): the
    cameras' agreements weighted by their valid lines (½ where no camera has one). Jittable, vmappable over poses
    (the per-pixel log odds do not depend on the pose: under `jax.vmap` over poses they are computed once; or pass
    them, `rig_log_odds`, as `log_odds` (C, H, W))."""
    C = cameras.K.shape[0]
    dtype = cameras.K.dtype
    log_odds = rig_log_odds(frames, histograms, params) if log_odds is None else log_odds
    total, count = jnp.zeros((), dtype), jnp.zeros((), jnp.int32)
    for c in range(C):
        cam = jax.tree.map(lambda a, c=c: a[c], cameras)
        s, n = line_agreement(cam, T_world_root, view_model, log_odds[c], params, scale, config)
        total, count = total + s * n, count + n
    return jnp.where(count > 0, total / jnp.maximum(count, 1), 0.5)


def hypothesis_poses(references, offsets, center):
    """(R · Q, 4, 4) poses: each reference (R, 4, 4) turned by each rotation vector of `offsets` (Q, 3) about the
    model point `center` (3,) (which stays where the reference puts it). Reference r's hypotheses are r·Q .. r·Q+Q−1,
    the first of each the reference itself when offsets[0] = 0."""
    dtype = references.dtype
    dR = jax.vmap(so3_exp)(jnp.asarray(offsets, dtype))  # (Q, 3, 3)
    c = jnp.asarray(center, dtype)
    local = jnp.zeros((dR.shape[0], 4, 4), dtype).at[:, :3, :3].set(dR).at[:, 3, 3].set(1.0)
    local = local.at[:, :3, 3].set(c - jnp.einsum("qij,j->qi", dR, c))  # x ↦ dR (x − c) + c
    return jnp.einsum("rij,qjk->rqik", references, local).reshape((-1, 4, 4))


def refine_on_lines(cameras: Camera, T_world_root, view_model, frames, histograms, params: LineParams, scales,
                    standard_deviations, num_rounds: int, config: LineConfig = DEFAULT_LINE_CONFIG):
    """`num_rounds` rounds of {every camera's line rows → one solve} from a pose (the lines' own schedule, M3T's
    two Gauss-Newton steps per round); `histograms`: the cameras' `ColourHistograms` or their `LogOddsTable`s (leading
    C axis). Returns (T (4, 4), status). Jittable, vmappable over poses."""
    kin = rigid_model(cameras.K.dtype)
    C = cameras.K.shape[0]

    def body(r, carry):
        T, _ = carry
        scale, std = schedule(scales, standard_deviations, r)
        sets = [line_rows(jax.tree.map(lambda a, c=c: a[c], cameras), T, view_model, frames[c],
                          jax.tree.map(lambda a, c=c: a[c], histograms), params, scale, std, config, camera_index=c)
                for c in range(C)]
        corr = jax.tree.map(lambda *a: jnp.concatenate(a), *sets)
        sol = solve_pose(kin, corr, T, None, M3T_SOLVER, cameras=cameras)
        return jnp.where(is_usable(sol.status), sol.T_world_root, T), sol.status

    T0 = jnp.asarray(T_world_root, cameras.K.dtype)
    return jax.lax.fori_loop(0, num_rounds, body, (T0, jnp.asarray(Status.OK, jnp.int32)))


@eqx.debug.assert_max_traces(max_traces=None)  # counts traces (`eqx.debug.get_num_traces`), never fails
def recover_pose(cameras: Camera, frames, view_model: SparseViewModel, histograms: ColourHistograms, params: LineParams,
                 references, scales, standard_deviations, num_rounds: int, config: RecoveryConfig | None = None,
                 line_config: LineConfig = DEFAULT_LINE_CONFIG) -> RecoveryResult:
    """Search for the pose of frames (C, H, W, 3) near `references` (R, 4, 4); reference 0 is the lost frame's pose.

    Every hypothesis (`hypothesis_poses`) is scored at `config.score_scale` in one vmapped call; reference 0 and the
    `config.refine − 1` best others are refined (`refine_on_lines`, vmapped; `scales`, `standard_deviations`,
    `num_rounds`: the line modality's schedule) and compared at `config.final_scale`. The colour histograms are
    turned into log odds once per call, per cell (`log_odds_table`, which the refinement reads) and per pixel of
    each frame (`rig_log_odds`, which every hypothesis' score reads). Jittable.
    """
    config = RecoveryConfig() if config is None else config
    dtype = cameras.K.dtype
    frames = jnp.asarray(frames)
    offsets = config.rotation_offsets()
    hyps = hypothesis_poses(jnp.asarray(references, dtype), offsets, view_model.center)
    # The colour model as log odds per cell, then per pixel, once per frame (every hypothesis and round reads them).
    tables = jax.vmap(lambda h: log_odds_table(h, params.posterior_prior))(histograms)
    log_odds = rig_log_odds(frames, tables, params)
    score = lambda T, s: rig_agreement(cameras, T, view_model, frames, histograms, params, s, line_config, log_odds)
    scores = jax.vmap(lambda T: score(T, config.score_scale))(hyps)
    ranked = jnp.nan_to_num(scores, nan=-jnp.inf).at[0].set(jnp.inf)  # the lost frame's own pose is always refined (recovery must beat it)
    _, top = jax.lax.top_k(ranked, min(config.refine, hyps.shape[0]))
    refined, status = jax.vmap(lambda T: refine_on_lines(cameras, T, view_model, frames, tables, params,
                                                         jnp.asarray(scales, jnp.int32),
                                                         jnp.asarray(standard_deviations, dtype), num_rounds,
                                                         line_config))(hyps[top])
    final = jnp.nan_to_num(jax.vmap(lambda T: score(T, config.final_scale))(refined), nan=-jnp.inf)
    best = jnp.argmax(final)
    return RecoveryResult(T_world_root=refined[best], score=final[best], own_score=final[0], index=top[best].astype(jnp.int32),
                          scores=scores, status=status[best].astype(jnp.int32))
