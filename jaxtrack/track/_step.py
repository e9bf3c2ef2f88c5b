"""The per-frame step of the tracker (Section V, Fig. 2): one jittable function of arrays.

For frames t → t+1 of C cameras sharing one state χ = (ξ, Θ):

1. render the model at χ_t into each camera's crop (principal point shifted, static crop size);
2. prediction: optical flow t → t+1 inside the object region with the occlusion map r(x) of frame t
   as data weight (eq. 6-8), its correspondences, and the SIFT matches (filtered, moved to surface
   points); a Gauss-Newton solve with the prediction weights of Section V (n_C → n_OF);
3. refinement: level-set segmentation of frame t+1 with the shape prior Φ0(χ), shape matching, and
   Gauss-Newton on contour + flow + SIFT correspondences with the adaptive weights, repeated until the
   pose settles (`refine_pose_region` with the motion correspondences as extra rows);
4. update: the occlusion map of frame t+1 at the final pose (the next step's r(x) and the SIFT mask),
   the appearance model where not occluded (eq. 10), the local densities (carried in the region state).

Failures are values: the frame's `Status` and a confidence from evidence the tracker has (silhouette
agreement of segmentation and model, agreement of the motion cues with the final pose), never from
ground truth. Every parameter is an array (`TrackerParams`), so weights and thresholds can be swept
with vmap or differentiated without recompiling; what shapes the program (`TrackerConfig`, the raster
plan, the crop size class) is static.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from .._status import Status, first_failure, is_usable, status_where
from ..cues.flow import FlowConfig, FlowEnergyParams
from ..cues.flow._correspondences import flow_correspondences
from ..cues.flow._solver import flow_core
from ..cues.levelset import RegionConfig, RegionParams, RegionProblem, RegionState, crop_camera, refine_pose_region
from ..cues.occlusion import (
    AppearanceModel,
    OcclusionConfig,
    OcclusionParams,
    TextureAtlas,
    detect_occlusion,
    observe_texels,
    update_appearance,
)
from ..cues.sift import (
    SiftMatches,
    SiftParams,
    backprojection_filter,
    remove_gross_and_static,
    reprojection_errors,
    sift_correspondences,
)
from ..geometry import Camera, KinematicModel
from ..image import crop_window, paste_window
from ..render import Mesh, RasterPlan, render
from ..solve import (
    Correspondences,
    Cue,
    CueWeights,
    SolverConfig,
    concatenate_correspondences,
    fuse_cue_weights,
    solve_pose,
)

CUES = ("region", "flow", "sift")


class TrackerConfig(eqx.Module):
    """Static settings of the tracker (they shape the compiled step).

    Attributes:
        cues: the cues used, a subset of ("region", "flow", "sift").
        occlusion: run the model-based occlusion detection (r(x) for flow, the SIFT mask).
        region: the region cue's settings (level-set iterations, rounds (10 here), contour capacity, ...).
        flow: the flow minimiser's settings (a fast coarse-to-fine schedule on the crop).
        flow_stride: grid step of the flow correspondences (capacity (h/s)·(w/s) per camera).
        prediction_steps: Gauss-Newton steps of the prediction solve.
        occlusion_config: histogram bins and window of the occlusion test.
        sift_mode: "surface" (rendered surface point under the keypoint) or "vertex" (the paper's
            closest projected visible vertex).
    """

    cues: tuple = eqx.field(static=True, default=CUES)
    occlusion: bool = eqx.field(static=True, default=True)
    # The prediction starts the refinement near the answer: 10 rounds gave the tea box the same errors as
    # 30 (1.43° / 2.54 mm both, measured) and bound the frame's worst-case time.
    region: RegionConfig = eqx.field(static=True, default_factory=lambda: RegionConfig(outer_iterations=10))
    flow: FlowConfig = eqx.field(static=True, default_factory=lambda: FlowConfig(eta=0.5, min_size=16, warps=4, lagged=1, sor_iters=10))
    flow_stride: int = eqx.field(static=True, default=4)
    prediction_steps: int = eqx.field(static=True, default=10)
    occlusion_config: OcclusionConfig = eqx.field(static=True, default_factory=OcclusionConfig)
    sift_mode: str = eqx.field(static=True, default="surface")

    def __check_init__(self):
        cues = tuple(self.cues)
        if not cues or any(c not in CUES for c in cues) or len(set(cues)) != len(cues):
            raise ValueError(f"TrackerConfig.cues must be a non-empty subset of {CUES} without repeats, got {self.cues}")
        if self.flow_stride < 1 or self.prediction_steps < 1:
            raise ValueError("TrackerConfig: flow_stride and prediction_steps must be ≥ 1")
        if self.sift_mode not in ("surface", "vertex"):
            raise ValueError(f"TrackerConfig.sift_mode must be 'surface' or 'vertex', got {self.sift_mode!r}")


class TrackerParams(eqx.Module):
    """Every numeric parameter of the tracker, as arrays (vmap, grad, no recompilation).

    Attributes:
        weights: user factors on the Section V cue weights.
        flow: α, γ, ε and the smoothness type of eq. 6 (rigid: quadratic α = 800; chains: robust α = 50).
        flow_beta: β of the confidence (eq. 8).
        region: λ, ν, ρ, ... of the region cue (eq. 11-15).
        sift: the SIFT outlier-filter thresholds.
        occlusion: the occlusion threshold 1/4 and update rate 1/8 (eq. 9-10).
        lost_iou, uncertain_iou: silhouette agreement below which a frame is lost / uncertain.
        inlier_px: a motion correspondence agrees with the final pose within this many pixels.
        theta_lower, theta_upper: (J,) joint limits (model units); ±inf (the default: the method uses no
            priors) leaves Θ free. The prediction and the refined Θ are projected onto them.
    """

    weights: CueWeights
    flow: FlowEnergyParams
    flow_beta: jax.Array
    region: RegionParams
    sift: SiftParams
    occlusion: OcclusionParams
    lost_iou: jax.Array
    uncertain_iou: jax.Array
    inlier_px: jax.Array
    theta_lower: jax.Array
    theta_upper: jax.Array


class TrackerSetup(eqx.Module):
    """What a sequence fixes: mesh, kinematic model, cameras (C stacked), appearance atlas, raster plan.

    The plan and the config are static (a re-plan after a render overflow is one recompilation,
    decided on the host between frames).
    """

    mesh: Mesh
    model: KinematicModel
    cameras: Camera
    atlas: TextureAtlas
    plan: RasterPlan = eqx.field(static=True)
    config: TrackerConfig = eqx.field(static=True)


class TrackerState(eqx.Module):
    """What the tracker carries from frame t to t+1 (full-frame arrays, C cameras).

    Attributes:
        T_world_root: (4, 4) root pose at t (model → world); theta: (J,) joint angles at t.
        images: (C, H, W, 3) frames t (0-255).
        data_weight: (C, H, W) r(x) of frame t (0 = occluded), the flow cue's data weight.
        visible: (C, H, W) bool non-occluded object pixels of frame t (the SIFT detection mask).
        region: the region cue's state (last segmentation and local densities).
        appearance: the appearance model f of the occlusion detection.
    """

    T_world_root: jax.Array
    theta: jax.Array
    images: jax.Array
    data_weight: jax.Array
    visible: jax.Array
    region: RegionState
    appearance: AppearanceModel


class FrameResult(eqx.Module):
    """What one step reports about frame t+1.

    Attributes:
        T_world_root, theta: the final pose; T_pred, theta_pred: the prediction from the motion cues.
        status: int32 `Status`: OK, UNCERTAIN, LOST, OUT_OF_VIEW, RENDER_OVERFLOW (re-plan and redo), ...
        confidence: [0, 1] evidence that the pose is right (silhouette agreement, else motion inliers).
        iou: (C,) agreement of the segmentation with the model silhouette at the final pose per camera.
        counts: (C, 3) correspondences with weight per camera and cue (region, flow, sift).
        motion_inliers: fraction of weighted motion correspondences within `inlier_px` at the final pose.
        occluded_fraction: (C,) fraction of object pixels of frame t+1 detected as occluded.
        iterations: refinement rounds run.
        region_phi: (C, h, w) the segmentation Φ of frame t+1 on the crop (for overlays).
        part_support: (P,) per part, the fraction of its unoccluded model silhouette (all cameras) that the
            segmentation covers; −1 where the part is not seen or the region cue is off. A limb whose
            support falls below `lost_iou` has lost its silhouette.
    """

    T_world_root: jax.Array
    theta: jax.Array
    T_pred: jax.Array
    theta_pred: jax.Array
    status: jax.Array
    confidence: jax.Array
    iou: jax.Array
    counts: jax.Array
    motion_inliers: jax.Array
    occluded_fraction: jax.Array
    iterations: jax.Array
    region_phi: jax.Array
    part_support: jax.Array


def _flatten_cameras(corr: Correspondences) -> Correspondences:
    """A (C, N) stack of per-camera sets → one set of C·N rows."""
    return jax.tree.map(lambda a: a.reshape((-1,) + a.shape[2:]), corr)


def _counts(corr: Correspondences, num_cameras: int, cue) -> jax.Array:
    live = (corr.weight > 0) & (corr.cue == cue)
    return jnp.sum(live[None, :] & (corr.camera[None, :] == jnp.arange(num_cameras)[:, None]), axis=1)


def _motion_inliers(corr: Correspondences, cameras: Camera, model: KinematicModel, T, theta, inlier_px):
    """Fraction of weighted rows whose model point projects within `inlier_px` of its pixel at (T, Θ)."""
    err = reprojection_errors(corr, cameras, model, T, theta)
    live = corr.weight > 0
    return jnp.sum(live & (err <= inlier_px)) / jnp.maximum(jnp.sum(live), 1)


def motion_correspondences(setup: TrackerSetup, state: TrackerState, frames, matches: SiftMatches, offsets, params: TrackerParams, crop_shape):
    """Step 2a: flow and SIFT correspondences at t+1 from frames t, t+1 and the render at χ_t.

    Returns:
        (Correspondences with FLOW and SIFT rows (raw weights: c_i and 1), the crop render at χ_t).
    """
    config, dtype = setup.config, state.T_world_root.dtype
    cams = crop_camera(setup.cameras, offsets, crop_shape)
    num_cams = offsets.shape[0]
    ren_t = jax.vmap(lambda cam: render(setup.mesh, cam, state.T_world_root, state.theta, setup.model, setup.plan))(cams)
    sil_t = ren_t.face_id >= 0
    parts = []
    if "flow" in config.cues:
        img_t = jax.vmap(crop_window, in_axes=(0, 0, None))(state.images, offsets, crop_shape)
        img_t1 = jax.vmap(crop_window, in_axes=(0, 0, None))(frames, offsets, crop_shape)
        r_t = jax.vmap(crop_window, in_axes=(0, 0, None))(state.data_weight, offsets, crop_shape)
        flow = jax.vmap(lambda a, b, r, om: flow_core(a, b, params.flow, config.flow, r, om, None, params.flow_beta, dtype))(
            img_t, img_t1, r_t, sil_t
        )
        usable = sil_t & (r_t > 0.5) & (flow.status == Status.OK)[:, None, None]
        fc = jax.vmap(
            lambda cam, fl, conf, ok, pm, part, c: flow_correspondences(cam, fl, conf, ok, pm, part, None, config.flow_stride, c)
        )(cams, flow.flow, flow.confidence, usable, ren_t.p_model, ren_t.part_id, jnp.arange(num_cams, dtype=jnp.int32))
        parts.append(_flatten_cameras(fc))
    if "sift" in config.cues:
        shift = offsets[:, None, ::-1].astype(matches.p_t.dtype)  # (y0, x0) → (x0, y0) per camera
        local = SiftMatches(matches.p_t - shift, matches.p_t1 - shift, matches.valid)
        local = remove_gross_and_static(local, params.sift)
        parts.append(
            sift_correspondences(local, ren_t, cams, params.sift, 1.0, config.sift_mode, setup.mesh, setup.model,
                                 state.T_world_root, state.theta)
        )
    corr = concatenate_correspondences(*parts) if parts else None
    return corr, ren_t, cams


@eqx.debug.assert_max_traces(max_traces=None)  # counts traces (`eqx.debug.get_num_traces`), never fails
def track_step(
    setup: TrackerSetup,
    state: TrackerState,
    frames: jax.Array,
    matches: SiftMatches,
    offsets: jax.Array,
    params: TrackerParams,
    crop_shape: tuple[int, int],
) -> tuple[TrackerState, FrameResult]:
    """One frame t → t+1 (Section V). Jittable and pure; vmap over `params` sweeps cue weights.

    Args:
        setup: mesh, model, stacked cameras (C), atlas, raster plan and config.
        state: the tracker state at t.
        frames: (C, H, W, 3) frames t+1 (0-255).
        matches: `SiftMatches` t → t+1 in full-frame pixels (C, N); ignored without the SIFT cue.
        offsets: (C, 2) int32 (y0, x0) of each camera's crop, chosen on the host around the object at t.
        params: `TrackerParams`.
        crop_shape: (h, w) the static crop size class (shared by the cameras).

    Returns:
        (new `TrackerState` at t+1, `FrameResult`).
    """
    config, model = setup.config, setup.model
    dtype = state.T_world_root.dtype
    num_cams = offsets.shape[0]
    frames = frames.astype(dtype)
    T_t, theta_t = state.T_world_root, state.theta

    # 2. Prediction from the motion cues (n_C → n_OF in the weights).
    motion, ren_t, cams = motion_correspondences(setup, state, frames, matches, offsets, params, crop_shape)
    if motion is not None:
        pred = solve_pose(model, fuse_cue_weights(motion, params.weights, prediction=True), T_t, theta_t,
                          SolverConfig(max_steps=config.prediction_steps))
        use = is_usable(pred.status)
        T_pred = jnp.where(use, pred.T_world_root, T_t)
        theta_pred = jnp.clip(jnp.where(use, pred.theta, theta_t), params.theta_lower, params.theta_upper)
        if "sift" in config.cues:  # the back-projection check against the preliminary pose
            is_sift = motion.cue == Cue.SIFT
            checked = backprojection_filter(motion, cams, model, T_pred, theta_pred, params.sift)
            motion = motion.with_weight(jnp.where(is_sift, checked.weight, motion.weight))
    else:
        T_pred, theta_pred = T_t, theta_t

    # 3. Refinement: region correspondences + the motion rows, adaptive weights, until settled.
    crops_t1 = jax.vmap(crop_window, in_axes=(0, 0, None))(frames, offsets, crop_shape)
    if "region" in config.cues:
        problem = RegionProblem(setup.mesh, model, setup.cameras, setup.plan, config.region)
        res = refine_pose_region(problem, crops_t1, offsets, state.region, params.region, T_pred, theta_pred,
                                 extra=motion, weights=params.weights)
        T_new, theta_new, region_state = res.T_world_root, jnp.clip(res.theta, params.theta_lower, params.theta_upper), res.state
        solve_status, iterations, phi = res.status, res.iterations, res.phi
        fused = res.correspondences
    else:
        T_new, theta_new, region_state = T_pred, theta_pred, state.region
        solve_status = Status.OK if motion is None else first_failure(pred.status)
        solve_status = jnp.where(solve_status == Status.MAX_STEPS, Status.OK, solve_status)
        iterations = jnp.zeros((), jnp.int32)
        phi = -jnp.ones((num_cams,) + tuple(crop_shape), dtype)
        fused = motion

    # 4. Occlusion map of frame t+1 at the final pose; appearance update where not occluded.
    ren_t1 = jax.vmap(lambda cam: render(setup.mesh, cam, T_new, theta_new, model, setup.plan))(cams)
    sil_t1 = ren_t1.face_id >= 0
    if config.occlusion:
        obs = observe_texels(setup.atlas, crops_t1, ren_t1.depth, cams, T_new, params.occlusion, theta_new, model,
                             config.occlusion_config)
        occ = detect_occlusion(setup.atlas, state.appearance, obs, ren_t1, params.occlusion, config.occlusion_config)
        appearance = update_appearance(state.appearance, obs, occ.occluded, params.occlusion, hold_new=occ.near_occlusion)
        occluded = occ.occluded
    else:
        appearance = state.appearance
        occluded = jnp.zeros_like(sil_t1)
    full = state.data_weight.shape[1:]
    data_weight = jax.vmap(lambda o, off: paste_window(jnp.ones(full, dtype), jnp.where(o, 0.0, 1.0).astype(dtype), off))(occluded, offsets)
    visible = jax.vmap(lambda v, off: paste_window(jnp.zeros(full, bool), v, off))(sil_t1 & ~occluded, offsets)

    # Evidence: silhouette agreement, motion-cue agreement, visibility.
    seg = phi > 0
    inter = jnp.sum(seg & sil_t1, axis=(1, 2))
    union = jnp.sum(seg | sil_t1, axis=(1, 2))
    iou = jnp.where(union > 0, inter / jnp.maximum(union, 1), 0.0).astype(dtype)
    seen = jnp.sum(sil_t1, axis=(1, 2)) > 0
    # Per part (limb): how much of its unoccluded silhouette the segmentation supports.
    own = sil_t1 & ~occluded
    part_ids = jnp.where(own, ren_t1.part_id, model.num_parts)  # a spill bin for background pixels
    part_pixels = jnp.zeros(model.num_parts + 1, dtype).at[part_ids.ravel()].add(1.0)[:-1]
    part_inside = jnp.zeros(model.num_parts + 1, dtype).at[jnp.where(seg, part_ids, model.num_parts).ravel()].add(1.0)[:-1]
    part_support = jnp.where(part_pixels > 0, part_inside / jnp.maximum(part_pixels, 1.0), -1.0)
    if "region" not in config.cues:
        part_support = -jnp.ones_like(part_support)
    if motion is not None:
        inliers = _motion_inliers(motion, cams, model, T_new, theta_new, params.inlier_px).astype(dtype)
    else:
        inliers = jnp.ones((), dtype)
    if "region" in config.cues:
        confidence = jnp.sum(jnp.where(seen, iou, 0.0)) / jnp.maximum(jnp.sum(seen), 1)
    else:
        confidence = inliers
    confidence = jnp.clip(confidence, 0.0, 1.0)
    quality = jnp.where(confidence < params.lost_iou, Status.LOST,
                        jnp.where(confidence < params.uncertain_iou, Status.UNCERTAIN, Status.OK))
    solve_ok = is_usable(solve_status)
    status = first_failure(
        status_where(~jnp.any(seen), Status.OUT_OF_VIEW, Status.OK),
        status_where(jnp.any(ren_t.status == Status.RENDER_OVERFLOW) | jnp.any(ren_t1.status == Status.RENDER_OVERFLOW),
                     Status.RENDER_OVERFLOW, Status.OK),
        status_where(solve_ok, Status.OK, Status.LOST),
        quality,
    )
    # A pose is never NaN: a failed step keeps the previous pose.
    finite = jnp.all(jnp.isfinite(T_new)) & jnp.all(jnp.isfinite(theta_new))
    T_new = jnp.where(finite, T_new, T_t)
    theta_new = jnp.where(finite, theta_new, theta_t)
    status = first_failure(status_where(finite, Status.OK, Status.NONFINITE), status)

    counts = jnp.zeros((num_cams, 3), jnp.int32)
    if fused is not None:
        counts = jnp.stack([_counts(fused, num_cams, cue) for cue in (Cue.REGION, Cue.FLOW, Cue.SIFT)], -1).astype(jnp.int32)
    n_obj = jnp.maximum(jnp.sum(sil_t1, axis=(1, 2)), 1)
    new_state = TrackerState(T_new, theta_new, frames, data_weight, visible, region_state, appearance)
    result = FrameResult(
        T_world_root=T_new, theta=theta_new, T_pred=T_pred, theta_pred=theta_pred, status=status.astype(jnp.int32),
        confidence=confidence, iou=iou, counts=counts, motion_inliers=inliers,
        occluded_fraction=(jnp.sum(occluded, axis=(1, 2)) / n_obj).astype(dtype),
        iterations=jnp.asarray(iterations, jnp.int32), region_phi=phi, part_support=part_support.astype(dtype),
    )
    return new_state, result
