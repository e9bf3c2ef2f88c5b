"""The tracker's host edge: validation, crops, raster plans, SIFT on the host, the jitted step.

`Tracker` holds what a sequence fixes (mesh, model, cameras, configuration, parameters) and turns a
stream of frames into poses:

    tracker = jt.Tracker(mesh, cameras)                      # rigid; pass model= for a chain
    state = tracker.start(frames0, T_world_root0)            # appearance model from the known pose
    for frames in stream:
        state, result, info = tracker.step(state, frames)    # result.status, result.confidence

Between frames, on the host: the crop around the object (one static size class for all cameras, or the fixed
working resolution, holding the projected model at t and where the last step's motion carries it, with a margin
that grows with that motion), SIFT detection
and matching (OpenCV, one thread per camera and core), and a re-plan of the rasteriser when a render overflowed
(the frame is then redone). Everything else is `track_step`, one compiled program per configuration,
crop size class and raster plan; with a modality that reads host inputs (SIFT) its first part, `start_frame`
(crops, render at χ_t, flow), is a program of its own, dispatched before the host detects and matches so
that the device computes the flow meanwhile (`Tracker.overlap_host`). After a LOST frame (rigid object, line
modality; on by default) the keyframes' PnP and the hypothesis search (`jaxtrack.track._recovery.recover_pose`,
compiled in the background at the first frame reported UNCERTAIN or LOST; lost frames wait for that compile at
most `RECOVERY_COMPILE_WAIT_S` in all, and one lost while it still compiles stays LOST) look for the pose, and the normal step is run again from what it found
(status RECOVERED when that step is OK).
"""

from __future__ import annotations

import atexit
import copy
import os
import threading
import time
import weakref

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._device import to_device
from .._exported import _settings as jax_settings  # the trace settings a kept program is keyed by
from .._exported import persistent_jit
from .._status import Status
from ..cues.flow import articulated_params, rigid_params
from ..cues.levelset import projected_boxes, region_crop, region_params
from ..cues.lines import SparseViewModel, line_params
from ..cues.occlusion import (
    OcclusionParams,
    init_appearance,
    make_texture_atlas,
    observe_texels,
    occlusion_params,
    update_appearance,
)
from ..cues.sift import SiftConfig, sift_params
from ..geometry import Camera, KinematicModel, crop_camera, rigid_model, stack_cameras
from ..geometry._validate import checked_rotation
from ..modality import Pose, StartContext
from ..render import Mesh, RasterPlan, hides_its_back_faces, render, replan
from ..solve import CueWeights
from ._keyframes import KeyframeModel, _rotation_deg
from ._recovery import recover_pose
from ._step import (
    LOSS_EVIDENCE,
    LOSS_EVIDENCE_DECAY,
    LOSS_FRAME_EVIDENCE,
    LOSS_WEIGHTS,
    FrameResult,
    TrackerConfig,
    TrackerParams,
    TrackerSetup,
    TrackerState,
    crop_frames,
    reads_host,
    start_frame,
    track_step,
)

# The step's two programs compile in two tiers by default (`jaxtrack._tiered`): quickly for the first frame, then XLA's
# optimised build from a background process.
_track_step_jit = persistent_jit(track_step, tiered=True)
_start_frame_jit = persistent_jit(start_frame, tiered=True)
_recover_pose_jit = persistent_jit(recover_pose)

# The trackers' background compiles still running. A process that exits while XLA compiles in a daemon thread aborts
# ("terminate called after throwing an instance of ..."): a run stopped by an exception from a callback, or a script
# whose last frame started the recovery's compile, waits for them at exit instead.
_BACKGROUND_COMPILES: weakref.WeakSet = weakref.WeakSet()


def _background_thread(target, name: str) -> threading.Thread:
    """A started daemon thread running `target`, joined at the interpreter's exit if still alive."""
    thread = threading.Thread(target=target, daemon=True, name=name)
    _BACKGROUND_COMPILES.add(thread)
    thread.start()
    return thread


@atexit.register
def _join_background_compiles() -> None:
    for thread in list(_BACKGROUND_COMPILES):
        thread.join()


# $JAXTRACK_RECOVERY_WARMUP → `Tracker.warm_up_recovery` (anything else: "doubt").
_WARMUP_ENV = {"0": "off", "false": "off", "off": "off", "1": "first frame", "true": "first frame",
               "first frame": "first frame"}
_WARMUP_MODES = ("doubt", "first frame", "off")

# Longest time a tracker's lost frames wait, all of them together, for the recovery program's background compile
# (`Tracker._search`): enough for a trace and a cache hit (0.3-0.4 s measured), not for a compile (6.9 s).
RECOVERY_COMPILE_WAIT_S = 1.0

# The flow's structure factor counts no structure near the limbs of the render (`TrackerParams.flow_limb_slope`,
# `jaxtrack.cues.flow.limb_pixels`): a one-pixel depth step above tan 80°. Rigid objects only (chains: not measured,
# off). Measured off → 5.67 (README, "Flow rows at the limbs"): turntable teapot / truck / noisy teapot 3.28 / 10.04 /
# 3.09° → 2.45 / 7.09 / 2.28°, large motion with the flow alone 6/8 → 7/8; worse: the real dragon 47 → 44 %. tan 70°
# (2.75) gave the teapot 1.99° but the dragon 37 % and the occluded frame-rate sequence at S = 3, 4: 36 / 25 → 18 / 12 %.
FLOW_LIMB_SLOPE = 5.67
# Factor on the Section V flow weights in the tracker's defaults (see `default_params`).
TRACKER_FLOW_FACTOR = 0.1
# k of the flow's structure factor on eq. 8's confidence (`TrackerParams.flow_structure`, negative: off; see
# `jaxtrack.cues.flow.structure_confidence`). Measured off → 4 (README, "Flow where the image does not pin it"): the loss
# experiment's sequences without resets 37.7 → 50.1 % within 5 cm / 5° (noisy S = 3: 9 → 91 %, occluded box
# 10 → 49 %); frame rate with resets, noisy 97/94/91/50 → 100/94/91/88 %, occluded 51/18/9/12 → 60/24/18/25 %;
# teabox-large-motion 64 → 91 %, turntable-teapot 55 → 73 %; tea box 0.62° → 0.45°. Worse: the real dragon
# 49 → 40 % (k = 1: 45 %), the occluded-box preset 73 → 64 % (one frame of 11), the real cube 1.90° → 1.97°.
FLOW_STRUCTURE = 4.0
# The flow, SIFT and level-set rows' weights per px² as the lines' (`TrackerParams.rows_per_px`; 0: per mm²).
ROWS_PER_PX = 1.0
# The prediction's and the refinement's residuals × Z₀ / Z (`TrackerParams.depth_invariant`; 0: eq. 4 as it is): rows
# that disagree were fitted by sliding the object toward the camera (README "Residuals that shrink toward the camera, ...").
# Rigid objects only: on chains it measured mixed (Table II all cues: run 120 fps 4.07 → 5.66°, run 24 fps and the walk
# better) and the two-camera mocap walk of tests/test_articulated.py drifted 25.7 mm in 3 frames; chains keep eq. 4.
DEPTH_INVARIANT = 1.0
# Scale (px of the crops) of the Cauchy loss on the motion rows, in the prediction's second pass and in every refinement
# round (`TrackerParams.motion_robust_px`; ≤ 0: off): rows the pose does not explain, an occluder's flow, lose their pull
# (README "Motion rows the pose does not explain"). 1, 1.5 and 2 measured on every experiment: 1 and 1.5 did more for the
# synthetic occlusions and the teapot but cost the real dragon 10 and 6 points (47 % within 5 cm / 5° before) and, at 1,
# the truck 1.0°; 2 costs the dragon 2 points. Rigid objects only: on the human (12 frames, 120 fps) knees + elbows
# 1.35 / 1.36° → 1.26 / 1.28°, but the run's right foot failed at frame 3; chains keep eq. 5 as it is.
MOTION_ROBUST_PX = 2.0
# The refinement rounds whose fused solve holds the flow and SIFT rows (`TrackerParams.motion_rounds`; ∞: every round,
# eq. 5) and the factor on them after (`motion_late_factor`); $JAXTRACK_MOTION_ROUNDS / $JAXTRACK_MOTION_LATE_FACTOR set
# other defaults (opt-in, README "Motion rows in the last rounds"). 3 and 0.3 (M3T's split: the motion predicts, the
# contour refines) measured on every experiment: the tea box 0.81 → 0.48°, the presets without resets all at 95-100 %,
# the turntable teapot 1.50 → 0.50°, the occlusion experiment 3.25 → 1.97°; but the real dragon 46 → 21 %, the truck
# 6.75 → 10.47°, Table I's all cues fail at frame 77 at σ = 60 (the paper: 85) and the occluded frame-rate sequences
# without resets 24 / 18 → 0 / 0 %: where the contour misleads, the motion rows in the last rounds hold the pose.
# Rigid objects only (chains: not measured, ∞). Only $JAXTRACK_MOTION_ROUNDS set: the factor is 0 (dropped after K).


def _env_number(name: str, default: str, low: float, high: float) -> float:
    """A number from the environment in [low, high] (inf allowed where high is), or a ValueError naming the variable."""
    text = os.environ.get(name, default)
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"${name} must be a number in [{low}, {high}], got {text!r}") from None
    if not low <= value <= high:  # NaN fails too
        raise ValueError(f"${name} must be a number in [{low}, {high}], got {text!r}")
    return value


MOTION_ROUNDS = _env_number("JAXTRACK_MOTION_ROUNDS", "inf", 0.0, float("inf"))
MOTION_LATE_FACTOR = _env_number("JAXTRACK_MOTION_LATE_FACTOR", "0", 0.0, 1.0)
# The confidence of the frame before that the two above need (`TrackerParams.motion_late_above`; 0: every frame);
# $JAXTRACK_MOTION_LATE_ABOVE sets another default. With 3, 0.3 and 0.9 (README "The late rounds only after a confident
# frame"): the real dragon kept at 45 % and Table I at σ = 60 / 80 fails at 172 / 157 (default 129 / 126), the presets
# without resets 92 → 100 % on the large motion; but the real cube 1.83 → 2.30° and the recovery experiment 77.5 →
# 70.7 %: opt-in.
MOTION_LATE_ABOVE = _env_number("JAXTRACK_MOTION_LATE_ABOVE", "0", 0.0, 1.0)


def _as_array(scales):
    return None if scales is None else to_device(scales)


def _compile_step_programs(start_args: tuple, early_like, make_host) -> tuple:
    """Compile (or load from the on-disk cache) the step's kept programs without running them: `start_frame`'s on
    `start_args` in a thread while this one makes the host inputs (`make_host()`) and compiles `track_step`'s on
    them and `early_like` (zeros shaped as `start_frame`'s outputs; None: the one program that runs it inside). XLA
    releases the GIL: a warm cache's two loads, 0.58 + 0.54 s on this 2-core CPU, take about the time of one.

    Returns:
        (the host inputs, whether every compile succeeded: False where a program runs `eqx.filter_jit` or failed).
    """
    start_frame_compiled = [True]
    thread = None
    if early_like is not None:
        def compile_start_frame():
            start_frame_compiled[0] = _start_frame_jit.compile(*start_args)

        thread = threading.Thread(target=compile_start_frame, daemon=True, name="jaxtrack-start-frame-compile")
        thread.start()
    try:
        host = make_host()
        compiled = _track_step_jit.compile(*start_args[:3], host, *start_args[3:], early_like)
    finally:
        if thread is not None:
            thread.join()
    return host, compiled and start_frame_compiled[0]


def _initial_modality_states(setup: TrackerSetup, frames, offsets, T, theta, params: TrackerParams, crop_shape,
                             scales=None, occluder_depth=None):
    """Every configured modality's state at the first frame (known pose), one compiled program
    (`occluder_depth`: (C, H, W) mm of the other objects of a joint run, or None)."""
    cams = crop_camera(setup.cameras, offsets, crop_shape, scales)
    (crops,) = crop_frames((frames,), offsets, crop_shape, scales, T.dtype)
    ren = jax.vmap(lambda cam: render(setup.mesh, cam, T, theta, setup.model, setup.window_plan))(cams)
    ctx = StartContext(setup.mesh, setup.model, setup.cameras, cams, offsets, frames, crops, ren, Pose(T, theta),
                       setup.window_plan, scales=scales, occluder_depth=occluder_depth)
    return tuple(m.init_state(ctx if setup.prepared_for(i) is None else eqx.tree_at(
        lambda c: c.prepared, ctx, setup.prepared_for(i), is_leaf=lambda x: x is None), params)
        for i, m in enumerate(setup.config.modalities()))


def _initial_appearance_jit(setup: TrackerSetup, frames, T, theta, params: OcclusionParams, offsets=None, crop_shape=None,
                            scales=None):
    """Silhouettes (C, H, W) and the appearance model seen at the known first pose, one compiled program
    (run op by op, its renders alone took 13 s of the tea box's 18 s start with a warm cache).

    With `scales` (the fixed working resolution) the appearance is observed on the resampled crops at
    (`offsets`, `crop_shape`, `scales`), as every later step observes it: learnt on the frame's own pixels,
    its texels would not match the antialiased crops at texture edges: on the frame-rate experiment's
    regular and noisy sequences at S = 1 the detection (eq. 9) flagged 0.7 % of the tracked object's pixels as
    occluded, 0.1 % learnt on the crops (no occluder there; measured with the tracker's defaults)."""
    ren = jax.vmap(lambda cam: render(setup.mesh, cam, T, theta, setup.model, setup.plan))(setup.cameras)
    if scales is None:
        obs = observe_texels(setup.atlas, frames.astype(T.dtype), ren.depth, setup.cameras, T, params, theta, setup.model,
                             setup.config.occlusion_config)
        shape = ren.depth.shape
    else:
        cams = crop_camera(setup.cameras, offsets, crop_shape, scales)
        (crops,) = crop_frames((frames,), offsets, crop_shape, scales, T.dtype)
        crop_ren = jax.vmap(lambda cam: render(setup.mesh, cam, T, theta, setup.model, setup.window_plan))(cams)
        obs = observe_texels(setup.atlas, crops, crop_ren.depth, cams, T, params, theta, setup.model,
                             setup.config.occlusion_config)
        shape = crop_ren.depth.shape
    appearance = update_appearance(init_appearance(setup.atlas, T.dtype), obs, jnp.zeros(shape, bool), params)
    return ren.face_id >= 0, appearance


# Both run once per `start`: the quick build (`persistent_jit(quick=True)`; the first frame waits for their compile).
_initial_modality_states = persistent_jit(_initial_modality_states, quick=True)
_initial_appearance_jit = persistent_jit(_initial_appearance_jit, quick=True)


# Region settings for kinematic chains (measured on the mocap humans, experiments/human_table2.py; one refinement
# from the true pose on the static first frame, mean |Δθ| over 26 DoF, walk / run): edge rows with tangent
# weight 0.1 let thin limbs slide along their own contour (3.5° / 2.0°, the left foot 32° off); point rows
# 1.3° / 2.0°; plus the joint prior 0.03 0.5° / 0.5° (pelvis pitch against back and hips no longer drifts).
CHAIN_REGION = {"tangent_weight": 1.0, "joint_prior": 0.03}

# Relative stiffnesses (rotation, translation) of the refinement's pose prior (`jaxtrack.solve.PosePrior`).
DEFAULT_POSE_PRIOR = (0.0, 0.0, 0.0, 0.0, 0.0)
# A refinement round reuses the last render when the model moved less than this (px) since it was made.
RENDER_REUSE_PX = 0.0


def checked_late_rounds(late_rounds) -> tuple[float, float, float]:
    """(K, f, τ) from `late_rounds` = (K, f[, τ]) (τ 0 when not given), or a ValueError that names what is wrong:
    K ≥ 0 refinement rounds (inf: every round), the factor f and the confidence τ in [0, 1]."""
    try:
        late = tuple(float(v) for v in late_rounds)
    except (TypeError, ValueError):
        late = ()
    late = late + ((0.0,) if len(late) == 2 else ())
    if len(late) != 3 or np.isnan(late[0]) or late[0] < 0 or not all(np.isfinite(v) and 0 <= v <= 1 for v in late[1:]):
        raise ValueError(f"late_rounds must be (K, f[, τ]): K ≥ 0 rounds (inf: every round), the factor f and the "
                         f"confidence τ in [0, 1], got {late_rounds!r}")
    return late


def default_params(
    model: KinematicModel, crop_shape: tuple[int, int] = (256, 256), dtype=jnp.float32, weights: CueWeights | None = None,
    occlusion: OcclusionParams | None = None, joint_limits: tuple | None = None, pose_prior: tuple | None = None,
    late_rounds: tuple | None = None,
) -> TrackerParams:
    """The method's parameters: quadratic flow smoothness α = 800 for a rigid object, robust α = 50 for
    a chain (β = 12 / 3), region λ = 0.05, ν = 0.001 |Ω|^0.7 (Ω the crop), ρ = 12, occlusion 1/4 and 1/8.

    One departure, measured: the flow factor on the Section V weights is 0.1 (`TRACKER_FLOW_FACTOR`).
    With the paper's rule the flow rows weigh mean(c)·n_C, and the confidences c = β/(1 + e) average
    about 2.5 (tea box), so flow outweighed the contour 2.5 : 1. Flow is a relative cue: its rows pin
    the model points of frame t, so they carry frame t's pose error forward and the contour could not
    pull it back. Mean rotation error with all cues at factor 1 / 0.3 / 0.1 (10 refinement rounds):
    tea box 1.43° / 0.96° / 0.61°; synthetic demo scene 2.04° / 1.55° / 1.60°; occluded box (lost
    either way) 10.7° / 8.8° / 8.5°. Where the region cue is poor (a 50 px textured box on a similar
    background, tests/test_tracker.py) less flow weight is worse: 2.7° → 5.0° after one frame.

    `pose_prior` = (rotation, translation[, rotation_abs, translation_abs, follows_round]): relative (and
    absolute) stiffnesses of the refinement's Tikhonov prior (`jaxtrack.solve.PosePrior`), toward the
    prediction, or toward each round's start when follows_round = 1 (M3T); `DEFAULT_POSE_PRIOR` by default.

    `joint_limits` = (lower, upper), (J,) each in model units (radians, mm), e.g. a URDF's
    (`ArticulatedModel.lower/upper`); by default none (±inf), as the method uses no priors.

    SIFT rows come from every keypoint on the object (`SiftParams.boundary_px` = 0): 2 px inside their part
    measured mixed on the mocap human (README "Table II at the paper's length, and what turns the walk's right foot").

    `late_rounds` = (K, f[, τ]): the flow and SIFT rows count fully in the refinement's first K rounds and × f after,
    on frames after one of confidence ≥ τ (0 if not given) (`TrackerParams.motion_rounds`, `motion_late_factor`,
    `motion_late_above`); by default `MOTION_ROUNDS` / `MOTION_LATE_FACTOR` / `MOTION_LATE_ABOVE` for rigid objects
    (∞: every round, the method) and ∞ for chains. (3, 0.3, 0.9) is the opt-in measured in the README ("The late
    rounds only after a confident frame"), for footage whose contour one trusts.
    """
    if weights is None:
        weights = CueWeights(flow=TRACKER_FLOW_FACTOR)
    prior = DEFAULT_POSE_PRIOR if pose_prior is None else tuple(float(v) for v in pose_prior)
    if len(prior) == 2:
        prior = prior + (0.0, 0.0, 0.0)
    if len(prior) != 5 or not all(np.isfinite(v) and v >= 0 for v in prior):
        raise ValueError(f"pose_prior must be (rotation, translation[, rotation_abs, translation_abs, follows_round]), "
                         f"finite numbers ≥ 0, got {pose_prior}")
    J = model.num_joints
    late = (MOTION_ROUNDS if J == 0 else np.inf, MOTION_LATE_FACTOR, MOTION_LATE_ABOVE)
    if late_rounds is not None:
        late = checked_late_rounds(late_rounds)
    flow = rigid_params() if model.num_joints == 0 else articulated_params()
    def device(a):
        return to_device(a, dtype)

    flow = jax.tree.map(device, flow)
    beta = 3.0 if flow.robust_smoothness else 12.0
    lower, upper = device(np.full((J,), -np.inf)), device(np.full((J,), np.inf))
    if joint_limits is not None:
        lo, hi = (np.asarray(a, np.float64) for a in joint_limits)
        if lo.shape != (J,) or hi.shape != (J,) or np.any(np.isnan(lo)) or np.any(np.isnan(hi)) or np.any(lo > hi):
            raise ValueError(f"joint_limits must be (lower, upper) of shape ({J},) with lower ≤ upper, got shapes "
                             f"{lo.shape}, {hi.shape}")
        lower, upper = device(lo), device(hi)
    return TrackerParams(
        weights=jax.tree.map(device, weights),
        flow=flow,
        flow_beta=device(beta),
        region=region_params(crop_shape, dtype, **(CHAIN_REGION if J else {})),
        sift=sift_params(dtype=dtype),
        occlusion=occlusion_params(dtype=dtype) if occlusion is None else occlusion,
        lost_iou=device(0.5),
        uncertain_iou=device(0.8),
        inlier_px=device(3.0),
        theta_lower=lower,
        theta_upper=upper,
        pose_prior_rotation=device(prior[0]),
        pose_prior_translation=device(prior[1]),
        render_reuse_px=device(RENDER_REUSE_PX),
        pose_prior_rotation_abs=device(prior[2]),
        pose_prior_translation_abs=device(prior[3]),
        prior_follows_round=device(prior[4]),
        lines=line_params(dtype),
        line_learning_rate=device(0.2),
        loss_weights=device(LOSS_WEIGHTS),
        loss_evidence_decay=device(LOSS_EVIDENCE_DECAY),
        uncertain_confidence=device(0.5),
        lost_confidence=device(0.25),
        flow_structure=device(FLOW_STRUCTURE),
        flow_limb_slope=device(FLOW_LIMB_SLOPE if J == 0 else -1.0),
        rows_per_px=device(ROWS_PER_PX),
        depth_invariant=device(DEPTH_INVARIANT if J == 0 else 0.0),
        motion_robust_px=device(MOTION_ROBUST_PX if J == 0 else -1.0),
        motion_rounds=device(late[0]),
        motion_late_factor=device(late[1]),
        motion_late_above=device(late[2]),
    )


def _as_rig(cameras: Camera) -> Camera:
    if not isinstance(cameras, Camera):
        raise TypeError(f"cameras must be a jaxtrack Camera (or a stacked rig), got {type(cameras).__name__}")
    return cameras if cameras.K.ndim == 3 else stack_cameras([cameras])


class Tracker:
    """Tracks one object (rigid, or parts on a kinematic chain) seen by 1-4 calibrated cameras.

    Args:
        mesh: the model (mm; part per vertex for a chain).
        cameras: one `Camera` or a stacked rig sharing one image size.
        model: kinematic tree (`rigid_model()` if None).
        config: static settings (`TrackerConfig`: cue subset, iterations, capacities).
        params: numeric parameters (`default_params` if None; ν follows the crop area unless given).
        sift: host SIFT settings.
        margin: pixels of context around the projected model in each crop.
        texel_mm: appearance-model texel size (default: about one pixel at the first pose).
        joint_limits: (lower, upper) (J,) joint limits in model units for the default parameters (none by
            default: the method uses no priors).
        pose_prior: (rotation, translation) relative stiffnesses of the pose prior for the default parameters.
        late_rounds: (K, f[, τ]) of the default parameters: the motion rows × f after K refinement rounds, on frames
            after a confident one (`default_params`; default: the method, every round).

    Attributes (settable):
        overlap_host: dispatch `start_frame` (crops, render at χ_t, the flow) before the host makes its inputs (SIFT),
            so the device computes while the host detects: None (default) where the rig has fewer cameras than the
            machine has cores (the host detects one camera per core), True for any rig, False never
            ($JAXTRACK_OVERLAP_HOST=0). Only where that program dispatches asynchronously (a kept program,
            `jaxtrack.enable_compilation_cache`). The poses are the same either way.
        warm_up_recovery: when to compile the recovery search (`TrackerConfig.recovery`) in a background thread:
            "doubt" (the default) at the first frame reported UNCERTAIN or LOST, so that a run that never doubts pays
            no compile (the keyframes for the PnP are still taken: a SIFT pass at `start` and per new view), or after
            the first frame where an earlier process kept the program on disk (then it is a load, 0.3-0.5 s in the
            background, and no first search waits for it); "first frame" (or True) after the first frame ($JAXTRACK_RECOVERY_WARMUP=1); "off" (or False;
            $JAXTRACK_RECOVERY_WARMUP=0) never: the first lost frame compiles it in the tracking thread.
        rectangular_texels: build the appearance model's atlas with rectangular grids on elongated faces
            (`make_texture_atlas(rectangular=True)`: texels about `texel_mm` along and across a sliver, 3x fewer on the
            mocap human, 4-camera steps ~7 % faster); False (default; $JAXTRACK_RECTANGULAR_TEXELS=1 sets it True):
            the square grids, whose finer texels across slivers tracked the occluded and noisy sequences better
            (README, "Texels along elongated faces"). Read at the first `start`.
        cull_backfaces: the rasteriser skips back faces (`RasterPlan.cull_backfaces`: half the candidate pixels,
            the same renders) where the mesh hides them (`jaxtrack.render.hides_its_back_faces`: closed, consistently
            oriented, every piece outward; $JAXTRACK_CULL_BACKFACES=0, read here, turns it off). Read when the first
            raster plan is made; set True by hand for a mesh that fails the check, renders may miss faces.
        precompile_first_step: compile the first step's programs in a background thread from `start` on, beside the
            start's own (True; $JAXTRACK_PRECOMPILE=0 sets it False); only with the on-disk program cache (kept programs).
        crop_follows_motion: the next step's windows hold the box at t and the box moved on by the last step's motion
            (plus the margin and half that motion) instead of the box at t plus 1.5x the motion on every side
            (`_crop_boxes`); True by default, $JAXTRACK_CROP_FOLLOWS_MOTION=0 sets it False.
    """

    def __init__(self, mesh: Mesh, cameras: Camera, model: KinematicModel | None = None, config: TrackerConfig | None = None,
                 params: TrackerParams | None = None, sift: SiftConfig | None = None, margin: int = 24,
                 texel_mm: float | None = None, joint_limits: tuple | None = None, pose_prior: tuple | None = None,
                 late_rounds: tuple | None = None):
        if not isinstance(mesh, Mesh):
            raise TypeError(f"mesh must be a jaxtrack.render.Mesh (see make_mesh / io.load_mesh), got {type(mesh).__name__}")
        self.mesh = mesh
        self.cameras = _as_rig(cameras)
        self.dtype = self.cameras.K.dtype
        self.model = rigid_model(self.dtype) if model is None else model
        if int(np.max(np.asarray(mesh.vertex_part))) >= self.model.num_parts:
            raise ValueError(f"mesh has parts up to {int(np.max(np.asarray(mesh.vertex_part)))} but the model has "
                             f"{self.model.num_parts} part(s)")
        # "auto" region modality: the correspondence lines (rigid objects and chains); working resolution for rigid ones.
        self.config = (TrackerConfig() if config is None else config).resolved(self.model.num_joints > 0)
        self._checked_params: tuple = ()
        self.user_params = self._checked(params)
        self.sift = SiftConfig() if sift is None else sift
        self.margin = int(margin)
        self.texel_mm = texel_mm
        self.plan: RasterPlan | None = None
        self.crop_plan: RasterPlan | None = None  # renders in the crops at the fixed working resolution
        self.atlas = None
        self.replans = 0
        self._default_params: dict = {}
        self.last_box_motion: np.ndarray | None = None  # (C, 4) the last step's motion of each box side (x0, y0, x1, y1; px)
        self.crop_shape: tuple[int, int] | None = None  # kept while the object fits (one compile per class)
        self.frame_dtype = np.dtype(self.dtype)  # the state's image dtype: uint8 after `start` on 8-bit frames
        self.host_cache: dict = {}  # per-modality host state between frames (SIFT: the keypoints of frame t)
        self.joint_limits = joint_limits
        self.prepared: tuple | None = None
        self.pose_prior = pose_prior
        self.late_rounds = late_rounds
        self.last_good_pose = None  # (4, 4) the last pose reported OK (or RECOVERED): a recovery's second reference
        self._boxes_memo = None  # (pose bytes, (C, 4) boxes) of the last projected pose (`_boxes_at`)
        self._step_config_memo = None  # (config, the same without recovery) (`_step_config`)
        self.recoveries = 0  # frames RECOVERED since `start`
        self._recovery_warmup: threading.Thread | None = None
        self._recovery_warmup_error: BaseException | None = None  # what the background compile raised, if it did
        self._recovery_kept_asked = False  # whether the search's program was looked for on disk (`_recovery_kept`)
        self._recovery_wait_left = RECOVERY_COMPILE_WAIT_S  # what lost frames may still wait for that compile
        self._failed_searches = 0  # searches in a row that recovered nothing (`RecoveryConfig.max_skip`)
        self._searches_to_skip = 0  # lost frames still to pass without a search
        # (crop shape, fixed resolution, plan) whose step programs are compiled (`_compile_both`, `_start_precompile`)
        self._compiled: set = set()
        # The first step's programs compile in a background thread from `start` on (`_start_precompile`), beside the
        # start's own small programs; $JAXTRACK_PRECOMPILE=0: when the first step needs them.
        self.precompile_first_step = os.environ.get("JAXTRACK_PRECOMPILE", "1") != "0"
        self._precompile: threading.Thread | None = None
        # Compile the recovery program in the background at the first doubt (`_warm_up_recovery`); "1": after the
        # first frame; "0" compiles it when first needed instead.
        self.warm_up_recovery = _WARMUP_ENV.get(os.environ.get("JAXTRACK_RECOVERY_WARMUP", "").strip().lower(), "doubt")
        # Windows around where the last step's motion carries the object (`_crop_boxes`);
        # $JAXTRACK_CROP_FOLLOWS_MOTION=0: around the box at t with 1.5x the motion on every side (the old rule).
        self.crop_follows_motion = os.environ.get("JAXTRACK_CROP_FOLLOWS_MOTION", "1") != "0"
        # With a modality that reads host inputs (SIFT), dispatch `start_frame` (crops, render, flow) before making
        # them, so the device works while the host detects ($JAXTRACK_OVERLAP_HOST=0: one program, host first).
        self.overlap_host: bool | None = False if os.environ.get("JAXTRACK_OVERLAP_HOST", "1") == "0" else None
        self.rectangular_texels = os.environ.get("JAXTRACK_RECTANGULAR_TEXELS", "0") == "1"
        self.cull_backfaces = os.environ.get("JAXTRACK_CULL_BACKFACES", "1") != "0" and hides_its_back_faces(self.mesh)
        self.keyframes: KeyframeModel | None = None  # SIFT keyframes for the re-detection (`RecoveryConfig.keyframes`)
        if joint_limits is not None or pose_prior is not None or late_rounds is not None:  # checked now, not at frame 1
            default_params(self.model, (64, 64), self.dtype, joint_limits=joint_limits, pose_prior=pose_prior,
                           late_rounds=late_rounds)

    @property
    def num_cameras(self) -> int:
        return self.cameras.K.shape[0]

    def setup(self) -> TrackerSetup:
        """What the compiled step takes as fixed: mesh, model, cameras, atlas, plan, config, prepared data. The config
        without `recovery` (the host's search after a LOST frame, not read by the step): one step program, and one
        on-disk entry, with and without it."""
        return TrackerSetup(self.mesh, self.model, self.cameras, self.atlas, self.plan, self._step_config(), self.prepared,
                            crop_plan=self.crop_plan)

    def _step_config(self) -> TrackerConfig:
        """`config` with `recovery` None, made once per config object."""
        memo = self._step_config_memo
        if memo is None or memo[0] is not self.config:
            step_config = self.config.without_recovery()
            memo = self._step_config_memo = (self.config, step_config)
        return memo[1]

    def prepare(self) -> tuple:
        """Every modality's one-off host set-up (`Modality.prepare`, e.g. a sparse viewpoint model), made once."""
        if self.prepared is None:
            self.prepared = tuple(m.prepare(self.mesh, self.model, self.cameras) for m in self.config.modalities())
        return self.prepared

    # --- host helpers -----------------------------------------------------------------------------
    def check_frames(self, frames, name: str = "frames") -> np.ndarray:
        """(C, H, W, 3) frames from (C, H, W[, 3]) or, for one camera, (H, W[, 3]): uint8 stays uint8, anything
        else becomes float32 (checked finite); errors name the problem."""
        frames = np.asarray(frames)
        H, W, C = self.cameras.height, self.cameras.width, self.num_cameras
        if C == 1 and frames.ndim in (2, 3) and frames.shape[:2] == (H, W):
            frames = frames[None]
        if frames.ndim == 3 and frames.shape[0] == C:
            frames = frames[..., None]
        if frames.ndim != 4 or frames.shape[:3] != (C, H, W) or frames.shape[-1] not in (1, 3):
            raise ValueError(f"{name} must have shape ({C}, {H}, {W}[, 3]) for this rig of {C} camera(s) of "
                             f"{W}x{H}, got {frames.shape}")
        if frames.shape[-1] == 1:
            frames = np.repeat(frames, 3, axis=-1)
        if frames.dtype == np.uint8:  # 8-bit frames go to the step as they are (a quarter of the bytes)
            return frames
        frames = frames.astype(np.float32, copy=False)
        if not np.all(np.isfinite(frames)):
            raise ValueError(f"{name} contain non-finite pixel values")
        return frames

    def _check_pose(self, T, theta):
        T = np.asarray(T, np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError(f"T_world_root must be a finite (4, 4) pose, got shape {T.shape}")
        checked_rotation(T[:3, :3], "T_world_root's rotation block (a rigid transform is needed)")
        if not np.allclose(T[3], [0, 0, 0, 1]):
            raise ValueError(f"T_world_root is not a rigid transform: last row {T[3].tolist()}, need [0, 0, 0, 1]")
        J = self.model.num_joints
        theta = np.zeros(J) if theta is None else np.asarray(theta, np.float64)
        if theta.shape != (J,) or not np.all(np.isfinite(theta)):
            raise ValueError(f"theta must be ({J},) finite joint angles, got shape {theta.shape}")
        return to_device(T, self.dtype), to_device(theta, self.dtype)

    def _host_cameras(self) -> Camera:
        """The rig as numpy arrays, for host-side planning (slicing or cropping device arrays op by op compiles
        a small program per operation in a fresh process)."""
        return jax.tree.map(np.asarray, self.cameras)

    def _replan(self, T, theta, windows=None, poses=()):
        """Raster plans for the pose (T, Θ), merged with the old ones: the full frame's and, at the fixed working
        resolution, the crops' (face extents in working pixels: a 218 px box's faces fit 45-91 px patches in a
        96x128 crop instead of 128-256 px ones, 10.8 → 3 ms per render).

        The crops' plan is made in `windows` ((offsets, shape, scales) of the step that overflowed; default:
        the windows at (T, Θ)) at (T, Θ) and at each of `poses` ((T, Θ) pairs: the step's other renders),
        and merged with the plan of those extents grown by √2 (one patch class of headroom for faces that
        turn toward the camera) times `_window_growth` (the object growing inside the window); faces that
        shrink spill into the larger classes, so one plan serves every distance and the step compiles once.
        """
        cull = self.plan.cull_backfaces if self.plan is not None else self.cull_backfaces
        self.plan = replan(self.plan, self.mesh, self._host_cameras(), T, theta, self.model, self.replans, cull)
        if self.config.working_shape is not None and self.config.uses_crop():
            offsets, shape, scales = self.windows(T, theta) if windows is None else windows
            if offsets is not None:
                cams = crop_camera(self._host_cameras(), np.asarray(offsets), shape, np.asarray(scales))
                plan = self.crop_plan
                for T_k, theta_k in ((T, theta),) + tuple(poses):
                    plan = replan(plan, self.mesh, cams, T_k, theta_k, self.model, self.replans, cull)
                    plan = replan(plan, self.mesh, cams, T_k, theta_k, self.model, 0, cull,
                                  extent_scale=np.sqrt(2.0) * self._window_growth(T_k, theta_k), base_margin=1.0)
                self.crop_plan = plan
        self.replans += 1

    @property
    def last_motion_px(self) -> float:
        """Largest image motion (px) of a side of the object's box in the last step (0 without one)."""
        return 0.0 if self.last_box_motion is None else float(np.max(np.abs(self.last_box_motion)))

    def _crop_margin(self) -> int:
        """Pixels of context around the object's box: the fixed margin plus 1.5x the last frame's motion (the window
        centred on the box at t; `_crop_boxes` centres it on the motion instead and needs less)."""
        return self.margin + int(np.ceil(1.5 * self.last_motion_px))

    def _crop_boxes(self, boxes: np.ndarray, follow_motion: bool = True) -> tuple[np.ndarray, int]:
        """(C, 4) boxes the windows of the next step must hold and the margin around them.

        With `crop_follows_motion` (and a last motion): the union of the box at t and the box moved on by the last
        step's motion of each side (constant velocity: where the object will be at t+1), plus the fixed margin and
        half the largest motion of any side in any camera, for a change of speed. Else the box at t plus
        `_crop_margin` (1.5x the motion on every side). After a 54 px step the window holds the object with 54 + 2 x 51 px along the motion and 2 x 51 px
        across it instead of 2 x 105 px both ways, so the fixed working resolution keeps more of the object's pixels
        (the noisy moving camera at 640x480: issue 25). `follow_motion=False` (a step between a frame and itself): the
        box at t and the fixed margin, whatever the last motion."""
        if not follow_motion:  # a step without motion: the box and the fixed margin
            return boxes, self.margin
        motion = self.last_box_motion
        if not self.crop_follows_motion or motion is None or motion.shape != boxes.shape or not np.all(np.isfinite(motion)):
            return boxes, self._crop_margin()
        moved = boxes + motion
        union = np.concatenate([np.minimum(boxes[:, :2], moved[:, :2]), np.maximum(boxes[:, 2:], moved[:, 2:])], axis=1)
        return union, self.margin + int(np.ceil(0.5 * float(np.max(np.abs(motion)))))

    def record_motion(self, boxes_before, boxes_after) -> None:
        """Remember one step's image motion from the object's (C, 4) projected boxes before and after it (px; None:
        no motion, as after `start`): the next step's windows follow it (`_crop_boxes`). Where a box is not finite
        (the object behind a camera) the previous motion is kept. Every step records its motion, a LOST frame's
        too (recording only OK and UNCERTAIN frames was measured and not kept: README, "The crop windows follow the
        motion")."""
        if boxes_before is None or boxes_after is None:
            self.last_box_motion = None
            return
        before, after = np.asarray(boxes_before, np.float64), np.asarray(boxes_after, np.float64)
        if np.all(np.isfinite(before)) and np.all(np.isfinite(after)):
            self.last_box_motion = after - before

    def _needed_scales(self, boxes: np.ndarray, margin: int) -> np.ndarray:
        """(C,) full-frame pixels per working pixel that fit each box plus `margin` in the working shape (unclamped)."""
        h, w = self.config.working_shape
        need_w = boxes[:, 2] - boxes[:, 0] + 1 + 2 * margin
        need_h = boxes[:, 3] - boxes[:, 1] + 1 + 2 * margin
        return np.maximum(need_h / h, need_w / w)

    def _window_growth(self, T, theta) -> float:
        """How much larger the object may get in working pixels before the crops' plan is made again: while it
        is smaller than the working window (scale clamped at 1) it grows at the window's own scale until it
        fills it; and once the window would need more than the frame (scale clamped at the largest that fits)
        it grows in the window again: within 2x of that clamp, plan for 2x."""
        boxes = projected_boxes(self.mesh, self.cameras, T, theta, self.model)
        if not np.all(np.isfinite(boxes)):
            return 1.0
        H, W = self.cameras.height, self.cameras.width
        h, w = self.config.working_shape
        need = self._needed_scales(*self._crop_boxes(boxes))
        fit = min(H / h, W / w)
        below = np.maximum(1.0 / need, 1.0)  # scale 1: room left in the window
        above = np.where(2.0 * np.maximum(need, 1.0) > fit, 2.0, 1.0)  # near the largest scale
        return float(np.max(below * above))

    def crop(self, T, theta, boxes: np.ndarray | None = None) -> tuple[np.ndarray, tuple[int, int]]:
        """Crop offsets (C, 2) and the shared static crop size around the object at (T, Θ)
        (`boxes`: its projected boxes when already computed). With a working resolution the windows also
        have a scale: use `windows`."""
        offsets, shape, _ = self.windows(T, theta, boxes)
        return offsets, shape

    def windows(self, T, theta, boxes: np.ndarray | None = None, follow_motion: bool = True):
        """(offsets (C, 2), crop shape (h, w), scales (C,) or None) of the crops around the object at (T, Θ).

        Native resolution (`TrackerConfig.working_shape` None): integer offsets, a size class, scales None.
        Working resolution: each camera's window covers the boxes of `_crop_boxes` (the box at t and where the
        last step's motion carries it; `follow_motion=False`: the box alone, for a step without motion) plus the
        margin at the fixed shape, scale s = full-frame pixels per crop pixel (at least 1 while the window fits in
        the frame), centred on those boxes and kept inside the frame.
        Native crops hold the same boxes and margin. (None, None, None) when the object is behind a camera.
        """
        boxes = projected_boxes(self.mesh, self.cameras, T, theta, self.model) if boxes is None else boxes.copy()
        if not np.all(np.isfinite(boxes)):
            return None, None, None
        H, W = self.cameras.height, self.cameras.width
        if not self.config.uses_crop():  # no modality reads crops: whole frames, one program for every size
            self.crop_shape = (H, W)
            return np.zeros((self.num_cameras, 2), np.int32), (H, W), None
        # Keep what is on screen; a box entirely off screen still gets a crop at the border.
        boxes[:, [0, 2]] = np.clip(boxes[:, [0, 2]], 0, W - 1)
        boxes[:, [1, 3]] = np.clip(boxes[:, [1, 3]], 0, H - 1)
        boxes, margin = self._crop_boxes(boxes, follow_motion)  # the carried box may leave the frame: clip again
        boxes[:, [0, 2]] = np.clip(boxes[:, [0, 2]], 0, W - 1)
        boxes[:, [1, 3]] = np.clip(boxes[:, [1, 3]], 0, H - 1)
        if self.config.working_shape is not None:
            return self._scaled_windows(boxes, margin)
        # A new size class has 25% headroom and is kept while the object fits: each class is one
        # compilation of the step (measured 40 s idle, 110-150 s under load, against 1-5 s per frame).
        offsets, shape = region_crop(boxes, (H, W), margin, self.config.region.density_factor, keep=self.crop_shape,
                                     grow=1.25)
        self.crop_shape = shape
        return offsets, shape, None

    def _scaled_windows(self, boxes: np.ndarray, margin: float):
        """Windows of the fixed working shape: one scale per camera (see `windows`)."""
        H, W = self.cameras.height, self.cameras.width
        h, w = self.config.working_shape
        fit = min(H / h, W / w)  # the largest scale whose window lies inside the frame
        scales = np.minimum(np.maximum(self._needed_scales(boxes, margin), 1.0), fit)
        cy, cx = (boxes[:, 1] + boxes[:, 3]) / 2, (boxes[:, 0] + boxes[:, 2]) / 2
        y0 = np.clip(cy + 0.5 - scales * h / 2, 0.0, np.maximum(H - scales * h, 0.0))
        x0 = np.clip(cx + 0.5 - scales * w / 2, 0.0, np.maximum(W - scales * w, 0.0))
        # At scale 1 a whole-pixel offset reads the frame's own pixels (no bilinear blur between two).
        native = scales <= 1.0
        y0, x0 = np.where(native, np.floor(y0 + 0.5), y0), np.where(native, np.floor(x0 + 0.5), x0)
        self.crop_shape = (h, w)
        return (np.stack([y0, x0], -1).astype(np.float32), (h, w), scales.astype(np.float32))

    def _checked(self, params: TrackerParams | None) -> TrackerParams | None:
        """`params` (None passes), refused where they ask for a depth scaling the solves would not apply
        (`TrackerConfig.depth_invariance` False; p is clipped to [0, 1], non-finite as 0, as `solve_pose` reads it).
        Checked once per object (the last few kept by identity)."""
        if (params is None or self.config.depth_invariance is not False or any(params is p for p in self._checked_params)
                or isinstance(params.depth_invariant, jax.core.Tracer)):  # traced (a caller's jit / vmap): not readable
            return params
        p = np.asarray(jax.device_get(params.depth_invariant), np.float64)
        if np.any(np.clip(np.nan_to_num(p, nan=0.0, posinf=0.0, neginf=0.0), 0.0, 1.0) > 0):
            raise ValueError("params.depth_invariant must be 0 when the solves are eq. 4 as it is "
                             "(TrackerConfig.depth_invariance False, the default for a chain); got "
                             f"{p.tolist()}: pass TrackerConfig(depth_invariance=True) to scale the residuals by depth")
        self._checked_params = (params,) + self._checked_params[:3]
        return params

    def params_for(self, crop_shape) -> TrackerParams:
        """The parameters used for a crop size: the user's, or the defaults with ν = 0.001 |Ω|^0.7."""
        if self.user_params is not None:
            return self.user_params
        if crop_shape not in self._default_params:  # built once per crop size, not per frame
            params = default_params(self.model, crop_shape, self.dtype, joint_limits=self.joint_limits,
                                    pose_prior=self.pose_prior, late_rounds=self.late_rounds)
            if self.config.depth_invariance is False:  # the solves take no depth scaling: the defaults say so
                params = eqx.tree_at(lambda p: p.depth_invariant, params, jnp.zeros_like(params.depth_invariant))
            self._default_params[crop_shape] = params
        return self._default_params[crop_shape]

    # --- tracking ---------------------------------------------------------------------------------
    def start(self, frames, T_world_root, theta=None, occluder_depth=None) -> TrackerState:
        """The state at the first frame, whose pose is known: the appearance model sees it unoccluded.

        `occluder_depth`: (C, H, W) depth (mm, inf: none) of the other objects of a joint run (`JointTracker`),
        kept in the state (`TrackerState.occluder_depth`); None for one object.

        With the on-disk program cache, the first step's programs start compiling in a background thread here
        (`precompile_first_step`); `step` waits for them, and `join_background` where no step follows.

        Raises:
            ValueError: malformed frames or pose, or an object behind a camera / outside every image.
        """
        frames = self.check_frames(frames, "frames")
        T, theta = self._check_pose(T_world_root, theta)
        self._warm_up_mode()  # a misspelt setting is refused before the first frame, not in the middle of a run
        boxes = projected_boxes(self.mesh, self.cameras, T, theta, self.model)
        if not np.all(np.isfinite(boxes)):
            raise ValueError("the initial pose puts the object behind a camera (T_world_root)")
        H, W = self.cameras.height, self.cameras.width
        on_screen = (boxes[:, 2] >= 0) & (boxes[:, 0] < W) & (boxes[:, 3] >= 0) & (boxes[:, 1] < H)
        if not np.any(on_screen):
            raise ValueError("the initial pose puts the object outside every camera's image (T_world_root)")
        self.record_motion(None, None)
        self.last_good_pose, self.recoveries = T, 0
        self._failed_searches = self._searches_to_skip = 0
        if self.plan is None:
            self._replan(T, theta)
        self.prepare()
        offsets, crop_shape, scales = self.windows(T, theta, boxes)
        if self.atlas is None:
            texel = self.texel_mm
            if texel is None:  # about one crop pixel at the first pose (a working-resolution pixel when resampled)
                rig = self._host_cameras()
                depth = float((np.asarray(rig.T_cam_world[0], np.float64) @ np.asarray(T, np.float64))[2, 3])
                scale = 1.0 if scales is None else float(np.max(scales))
                texel = max(0.25, scale * depth / float(rig.K[0, 0, 0]))
            self.atlas = make_texture_atlas(self.mesh, texel_mm=texel, rectangular=self.rectangular_texels)
        # Frames t live in the state as they came: 8-bit frames stay uint8 (a quarter of the bytes to copy and
        # move), others in the tracker's dtype. Later frames are cast to the same dtype: one program.
        self.frame_dtype = np.uint8 if frames.dtype == np.uint8 else np.dtype(self.dtype)
        occluder_depth = None if occluder_depth is None else to_device(occluder_depth, self.dtype)
        setup = self.setup()
        appearance_args = self._initial_appearance_args(to_device(frames), T, theta, offsets, crop_shape, scales)
        # The first frame's pose is known: every modality learns its state there (the level set's local
        # densities, so the next frame's first iterations use densities of the right regions, Section IV).
        states_args = (setup, to_device(frames, self.dtype), to_device(offsets), T, theta, self.params_for(crop_shape),
                       crop_shape, _as_array(scales), occluder_depth)
        self._start_precompile(frames, appearance_args, states_args)
        sil, appearance = _initial_appearance_jit(*appearance_args)
        states = _initial_modality_states(*states_args)
        self.keyframes = None
        if self.recovery_modality() is not None and self.config.recovery.keyframes is not None:
            self.keyframes = KeyframeModel(np.asarray(self.mesh.vertices), np.asarray(self.mesh.faces),
                                           self.config.recovery.keyframes, self.sift)
            self._add_keyframe(frames, np.asarray(sil), T)
        return TrackerState(
            T_world_root=T, theta=theta, images=to_device(self._frames_as_state(frames)),
            data_weight=to_device(np.ones((self.num_cameras, H, W), self.dtype)), visible=sil, appearance=appearance,
            modalities=states, occluder_depth=occluder_depth, loss_evidence_average=self._no_loss_evidence(),
            last_confidence=self._no_confidence(),
        )

    def _no_confidence(self) -> jax.Array:
        """() zero: `TrackerState.last_confidence` of a start (no frame measured yet)."""
        return to_device(np.zeros((), self.dtype))

    def _no_loss_evidence(self) -> jax.Array:
        """(len(LOSS_FRAME_EVIDENCE),) zeros: `TrackerState.loss_evidence_average` of a start (the pose is known)."""
        return to_device(np.zeros((len(LOSS_FRAME_EVIDENCE),), self.dtype))

    def _initial_appearance_args(self, frames, T, theta, offsets=None, crop_shape=None, scales=None) -> tuple:
        """The arguments of `_initial_appearance_jit`: silhouettes and appearance at the first pose, observed on the
        working-resolution crops when `scales` is given (native crops: on the frames, whose pixels the crops are)."""
        setup = self.setup()
        params = self.params_for((self.cameras.height, self.cameras.width)).occlusion
        if scales is None:
            return setup, frames, T, theta, params
        return setup, frames, T, theta, params, to_device(offsets), tuple(crop_shape), to_device(scales)

    def _start_precompile(self, frames, appearance_args: tuple, states_args: tuple) -> None:
        """Compile the first step's programs in a background thread while `start` runs its own (`precompile_first_step`).

        The first `step` from this pose takes the windows `start` takes (the same boxes, no motion yet), so its
        signature is known here; the state's shapes come from the start programs' entries (`outputs_like`: traced
        and exported, or loaded, not run), the host inputs' from the host modalities run on an empty region (a
        scratch cache: nothing carries over). Only for kept programs (`persistent_jit` with the on-disk cache). The
        thread compiles only under this thread's jax settings (jax's context managers are thread-local: a
        `default_matmul_precision` or `default_device` block would make it compile another program) and marks the
        signature compiled only when every compile succeeded; otherwise the step compiles as it did before."""
        self._join_precompile()  # a restart's (`start` again) compile after the last one's, not beside it
        setup, _, offsets_j, T, theta, params, crop_shape, scales_j, occluder_depth = states_args
        signature = (crop_shape, scales_j is None, id(setup.window_plan))
        if not self.precompile_first_step or signature in self._compiled:
            return
        sil_like = _initial_appearance_jit.outputs_like(*appearance_args)
        states_like = _initial_modality_states.outputs_like(*states_args)
        if sil_like is None or states_like is None:  # the plain path: each program compiles at its first call
            return
        H, W = self.cameras.height, self.cameras.width
        state_like = TrackerState(
            T_world_root=T, theta=theta, images=self._frames_as_state(frames),
            data_weight=np.ones((self.num_cameras, H, W), self.dtype), visible=sil_like[0], appearance=sil_like[1],
            modalities=states_like, occluder_depth=occluder_depth, loss_evidence_average=self._no_loss_evidence(),
            last_confidence=self._no_confidence())
        saved, self.host_cache = self.host_cache, {}
        try:
            host_like = self.host_inputs(state_like, frames)  # frame t+1's shape: the first frame's
        except Exception:  # noqa: BLE001  (a host modality that fails here fails in the step, which reports it)
            return
        finally:
            self.host_cache = saved
        start_args = (setup, state_like, to_device(self._frames_as_state(frames)), offsets_j, params, crop_shape, scales_j)
        overlaps = self._overlaps_host()
        settings = (jax_settings(), jax.config.jax_default_device)

        def compile_first_step():
            if (jax_settings(), jax.config.jax_default_device) != settings:
                return
            try:
                early_like = _start_frame_jit.outputs_like(*start_args) if overlaps else None
                _, compiled = _compile_step_programs(start_args, early_like, lambda: host_like)
            except Exception:  # noqa: BLE001  (the step's own call compiles, and reports what fails)
                compiled = False
            if compiled:
                self._compiled.add(signature)  # read by the step only after it joined this thread

        self._precompile = _background_thread(compile_first_step, "jaxtrack-first-step-compile")

    def _join_precompile(self) -> None:
        if self._precompile is not None:
            self._precompile.join()
            self._precompile = None

    def _frames_as_state(self, frames: np.ndarray) -> np.ndarray:
        """Checked frames in the state's image dtype (`frame_dtype`, fixed by `start`)."""
        dtype = self.frame_dtype
        if frames.dtype == dtype:
            return frames
        if dtype == np.uint8:
            return np.clip(np.rint(frames), 0, 255).astype(np.uint8)
        return frames.astype(dtype)

    def previous_images(self, state: TrackerState) -> np.ndarray:
        """(C, H, W, 3) frames t on the host (for host-side modalities such as SIFT detection)."""
        return np.asarray(state.images)

    def visible_mask(self, state: TrackerState) -> np.ndarray:
        """(C, H, W) bool unoccluded object pixels of frame t on the host (the SIFT detection mask)."""
        return np.asarray(state.visible)

    def host_inputs(self, state: TrackerState, frames: np.ndarray, timings: dict | None = None) -> tuple:
        """Every configured modality's host-side input for frames t+1 (`Modality.host_inputs`): SIFT matches
        t → t+1 inside the visible object region of frame t; None for the others."""
        return tuple(m.host_inputs(self, state, frames, timings) for m in self.config.modalities())

    matches = host_inputs  # the old name (the only host input used to be the SIFT matches)

    def step(self, state: TrackerState, frames, params: TrackerParams | None = None,
             recover: bool = True) -> tuple[TrackerState, FrameResult, dict]:
        """Track frames t+1 from `state` at t. Never raises for tracking failures (see `FrameResult.status`).

        A frame the step reports LOST starts the hypothesis search where the configuration recovers
        (`TrackerConfig.recovers`; `recover=False`: not this frame), see `_recover`.

        Returns:
            (state at t+1, `FrameResult`, info: host timings in seconds, the crop, and "recovery": None, or what the
            search after a LOST frame found ("source", "pnp_inliers", "score", "own_score", "hypothesis", "recovered";
            "skipped": "compiling" when the hypotheses' program was still compiling in the background, "compile
            failed: ..." when that compile raised, "backoff" when a persistently lost object was due no search;
            "turned_deg": the found pose's rotation from the lost one)).

        Raises:
            ValueError: malformed frames, or `params` asking for a depth scaling the solves do not apply.
        """
        params = self._checked(params)
        frames = self.check_frames(frames, "frames")
        timings: dict = {}
        start = time.perf_counter()
        before = self._boxes_at(state.T_world_root, state.theta)
        H, W = self.cameras.height, self.cameras.width
        on_screen = np.isfinite(before).all(1) & (before[:, 2] >= 0) & (before[:, 0] < W) & (before[:, 3] >= 0) & (before[:, 1] < H)
        offsets, crop_shape, scales = (self.windows(state.T_world_root, state.theta, before) if on_screen.any()
                                       else (None, None, None))
        if offsets is None:  # behind a camera or outside every image: keep the pose, report it out of view
            self._failed_searches = self._searches_to_skip = 0  # not LOST: the search's backoff starts over
            lost = eqx.tree_at(lambda s: s.images, state, to_device(self._frames_as_state(frames)))
            timings["total_s"] = time.perf_counter() - start
            return lost, self._out_of_view(state), {"timings": timings, "offsets": None, "crop_shape": None, "scales": None,
                                                    "recovery": None}
        params = self.params_for(crop_shape) if params is None else params
        frames_j = to_device(self._frames_as_state(frames))
        step_start = time.perf_counter()
        new_state, result, host_s = self._run_step(state, frames, frames_j, offsets, params, crop_shape, scales, timings=timings)
        timings["step_s"] = time.perf_counter() - step_start - host_s
        if recover and self._wants_recovery_warmup(result, new_state, frames_j, params):  # before this frame's search
            self._warm_up_recovery(new_state, frames_j, params)
        recovery = None
        if int(result.status) != Status.LOST:  # the object is back (or never lost): the search's backoff starts over
            self._failed_searches = self._searches_to_skip = 0
        if recover and int(result.status) == Status.LOST and self.recovery_modality() is not None:
            rec_start = time.perf_counter()
            new_state, result, recovery = self._recover(state, new_state, result, frames, frames_j, params)
            offsets, crop_shape, scales = recovery.pop("windows")
            timings["recovery_s"] = time.perf_counter() - rec_start
        elif int(result.status) == Status.OK:
            self.last_good_pose = result.T_world_root
            if self.keyframes is not None and self.keyframes.wants(result.T_world_root):
                key_start = time.perf_counter()
                self._add_keyframe(frames, np.asarray(new_state.visible), result.T_world_root)
                timings["keyframe_s"] = time.perf_counter() - key_start
        timings["total_s"] = time.perf_counter() - start
        self.record_motion(before, self._boxes_at(result.T_world_root, result.theta))
        return new_state, result, {"timings": timings, "offsets": offsets, "crop_shape": crop_shape, "scales": scales,
                                   "recovery": recovery}

    def _boxes_at(self, T, theta) -> np.ndarray:
        """`projected_boxes` at (T, Θ), remembered for one pose: a step's final pose is the next step's start, so each
        frame projects the mesh once (a compiled call and a device round trip)."""
        key = np.asarray(T).tobytes() + np.asarray(theta).tobytes()
        if self._boxes_memo is not None and self._boxes_memo[0] == key:
            return self._boxes_memo[1].copy()
        boxes = projected_boxes(self.mesh, self.cameras, T, theta, self.model)
        self._boxes_memo = (key, boxes)
        return boxes.copy()

    def _overlaps_host(self) -> bool:
        """Whether to dispatch `start_frame` before the host inputs: asked for, some modality reads host inputs, and
        the host's threads (one per camera, up to the cores: `sift_matches`) leave a core for the device. `_run_step`
        then dispatches it only where the call returns at once (a kept program, `persistent_jit.call_async`;
        `eqx.filter_jit` waits for the result, and two programs run one after the other cost more than one). Measured
        on 2 cores, frames alternating in one process (experiments/bench_overlap.py): 1 camera 44.9 → 40.7 ms per
        frame; 4 cameras 188.9 → 201.9 ms (the host already used both cores)."""
        wanted = self.num_cameras < (os.cpu_count() or 1) if self.overlap_host is None else self.overlap_host
        return wanted and any(reads_host(m) for m in self.config.modalities())

    def _run_step(self, state, frames, frames_j, offsets, params, crop_shape, scales, host=None, timings=None):
        """The compiled step; after a render overflow the plans are made again and the frame is redone.

        The host inputs (`host_inputs`, unless given) are made after `start_frame` is dispatched where the host's
        work can overlap the device's (`overlap_host`). Returns (state, result, seconds spent making host inputs)."""
        offsets_j, scales_j = to_device(offsets), _as_array(scales)
        self._join_precompile()  # the first step's programs, compiled from `start` on
        host_s = 0.0
        for _ in range(3):
            setup = self.setup()
            early = None
            if self._overlaps_host():  # dispatched, not waited for: the device works while the host detects
                signature = (crop_shape, scales is None, id(setup.window_plan))
                if host is None and signature not in self._compiled:
                    self._compiled.add(signature)
                    host, host_s = self._compile_both(setup, state, frames, frames_j, offsets_j, params, crop_shape,
                                                      scales_j, timings)
                early = _start_frame_jit.call_async(setup, state, frames_j, offsets_j, params, crop_shape, scales_j)
            if host is None:
                host, host_s = self._timed_host_inputs(state, frames, timings)
            new_state, result = _track_step_jit(setup, state, frames_j, host, offsets_j, params, crop_shape, scales_j,
                                                early)
            if int(result.status) != Status.RENDER_OVERFLOW:
                break
            # The crops' plan in this step's own windows, at the poses it rendered (χ_t and the result).
            self._replan(result.T_world_root, result.theta, (offsets, crop_shape, scales),
                         poses=((state.T_world_root, state.theta),))
        jax.block_until_ready(result)
        return new_state, result, host_s

    def _compile_both(self, setup, state, frames, frames_j, offsets_j, params, crop_shape, scales_j, timings):
        """The first frame of a signature with the host overlapped: the two programs compile while the host inputs are
        made (`_compile_step_programs`). Only for kept programs (`persistent_jit`; the plain path compiles each at its
        first call). Returns (host inputs, their seconds)."""
        start_args = (setup, state, frames_j, offsets_j, params, crop_shape, scales_j)
        early_like = _start_frame_jit.outputs_like(*start_args)  # its entry: traced and exported, or loaded
        if early_like is None:
            return self._timed_host_inputs(state, frames, timings)
        seconds = []

        def make_host():
            host, host_s = self._timed_host_inputs(state, frames, timings)
            seconds.append(host_s)
            return host

        host, _ = _compile_step_programs(start_args, early_like, make_host)
        return host, seconds[0]

    def _timed_host_inputs(self, state, frames, timings):
        """(`host_inputs`, the seconds they took)."""
        start = time.perf_counter()
        host = self.host_inputs(state, frames, timings)
        return host, time.perf_counter() - start

    # --- recovery (issue 24) ------------------------------------------------------------------------
    def recovery_modality(self) -> int | None:
        """Index of the line modality whose sparse viewpoint model and histograms the recovery uses; None when the
        configuration does not recover (`TrackerConfig.recovers`) or the object has no view model (a chain)."""
        if not self.config.recovers():
            return None
        prepared = self.prepare()
        for i, m in enumerate(self.config.modalities()):
            if m.name == "lines" and isinstance(prepared[i], SparseViewModel):
                return i
        return None

    def _camera_arrays(self):
        return (np.asarray(self.cameras.K, np.float64), np.asarray(self.cameras.dist, np.float64),
                np.asarray(self.cameras.T_cam_world, np.float64))

    def _add_keyframe(self, frames: np.ndarray, visible: np.ndarray, T) -> int:
        K, dist, T_cam_world = self._camera_arrays()
        return self.keyframes.add(frames, visible, K, dist, T_cam_world, np.asarray(T, np.float64))

    def _search_regions(self, poses) -> np.ndarray:
        """(C, H, W) bool: the union of the object's boxes at `poses` ((T, Θ) pairs), grown by
        `KeyframeConfig.region_growth` times its size on each side (where the re-detection looks)."""
        H, W = self.cameras.height, self.cameras.width
        boxes = np.stack([projected_boxes(self.mesh, self.cameras, T, th, self.model) for T, th in poses])  # (P, C, 4)
        regions = np.zeros((self.num_cameras, H, W), bool)
        grow = self.config.recovery.keyframes.region_growth
        for c in range(self.num_cameras):
            b = boxes[:, c][np.isfinite(boxes[:, c]).all(1)]
            if not len(b):
                continue
            x0, y0, x1, y1 = b[:, 0].min(), b[:, 1].min(), b[:, 2].max(), b[:, 3].max()
            gx, gy = grow * (x1 - x0 + 1), grow * (y1 - y0 + 1)
            x0, x1 = int(np.clip(x0 - gx, 0, W - 1)), int(np.clip(x1 + gx, 0, W - 1))
            y0, y1 = int(np.clip(y0 - gy, 0, H - 1)), int(np.clip(y1 + gy, 0, H - 1))
            regions[c, y0:y1 + 1, x0:x1 + 1] = True
        return regions

    def _recovery_args(self, state: TrackerState, frames_j, references, params: TrackerParams) -> tuple:
        i = self.recovery_modality()
        lines = self.config.modalities()[i]
        return (self.cameras, frames_j, self.prepared[i], state.modalities[i].histograms, params.lines, references,
                tuple(lines.scales), tuple(lines.standard_deviations), lines.rounds, self.config.recovery)

    def _warm_up_mode(self) -> str:
        """`warm_up_recovery` as one of "doubt", "first frame", "off" (True / False: the latter two).

        Raises:
            ValueError: any other value (checked by `start`, before a frame is tracked)."""
        value = self.warm_up_recovery
        when = ("first frame" if value else "off") if isinstance(value, bool) else value
        if when not in _WARMUP_MODES:
            raise ValueError(f'Tracker.warm_up_recovery must be "doubt", "first frame" or "off" (or True / False), got {value!r}')
        return when

    def _wants_recovery_warmup(self, result: FrameResult, state: TrackerState | None = None, frames_j=None,
                               params: TrackerParams | None = None) -> bool:
        """Whether to start the search's background compile after this frame (`warm_up_recovery`; with the frame's
        `state`, frames and params, "doubt" also asks whether the program is on disk: `_recovery_kept`)."""
        when = self._warm_up_mode()
        if (when == "off" or self._recovery_warmup is not None or self.recovery_modality() is None
                or not self.config.recovery.hypotheses):
            return False
        if when == "first frame" or int(result.status) in (Status.UNCERTAIN, Status.LOST):
            return True
        return state is not None and self._recovery_kept(state, frames_j, params)

    def _recovery_kept(self, state: TrackerState, frames_j, params: TrackerParams) -> bool:
        """Whether an earlier process kept the search's program on disk (`persistent_jit.is_kept`: exported; its
        executable is then normally in the compile cache too): the "doubt" warm-up then starts after the first frame,
        a load, so that the first lost frame finds it ready (a search waited up to 0.55 s for the load at the first
        doubt). Where the compile cache does not hold it (cleared, other compile options or $XLA_FLAGS) that warm-up
        is a compile in the background after the first frame, as with "first frame". Asked once per tracker (the
        signature is pickled and hashed: about a millisecond)."""
        if self._recovery_kept_asked:
            return False
        self._recovery_kept_asked = True
        return _recover_pose_jit.is_kept(*self._recovery_args(state, frames_j, jnp.stack([state.T_world_root] * 2), params))

    def _warm_up_recovery(self, state: TrackerState, frames_j, params: TrackerParams) -> None:
        """Compile the recovery program in a background thread (after a step: that step's compile comes first), so
        that no lost frame waits for it (`_search`). What the compile raises is kept
        (`_recovery_warmup_error`): the search is then skipped, not compiled again in the tracking thread."""
        args = self._recovery_args(state, frames_j, jnp.stack([state.T_world_root] * 2), params)

        def compile_search():
            try:
                jax.block_until_ready(_recover_pose_jit(*args))
            except Exception as error:  # noqa: BLE001  (reported through the frames' recovery info)
                self._recovery_warmup_error = error

        self._recovery_wait_left = RECOVERY_COMPILE_WAIT_S
        self._recovery_warmup = _background_thread(compile_search, "jaxtrack-recovery-compile")

    def recover(self, state: TrackerState, frames, reference=None, params: TrackerParams | None = None):
        """The hypothesis search alone (`recover_pose`) on frames (C, H, W[, 3]) with the line histograms of `state`,
        around `reference` (4, 4) (default: the state's pose) and the last pose reported OK. Returns a
        `RecoveryResult` (its `T_world_root` is the best refined pose). Called directly, it waits for the background
        compile however long it takes (the tracking loop's lost frames do not: `_search`)."""
        if self.recovery_modality() is None:
            raise ValueError("recover: this tracker has no recovery (needs TrackerConfig.recovers() and a rigid object)")
        if self._recovery_warmup is not None:  # its compile, not a second one
            self._recovery_warmup.join()
        frames_j = to_device(self._frames_as_state(self.check_frames(frames, "frames")))
        params = self.params_for(self.crop_shape) if params is None else self._checked(params)
        reference = state.T_world_root if reference is None else jnp.asarray(reference, self.dtype)
        good = state.T_world_root if self.last_good_pose is None else self.last_good_pose
        return _recover_pose_jit(*self._recovery_args(state, frames_j, jnp.stack([reference, good]), params))

    def join_background(self) -> None:
        """Wait for the background compiles (the first step's, the recovery program's; call before the process exits)."""
        self._join_precompile()
        if self._recovery_warmup is not None:
            self._recovery_warmup.join()

    def _recover(self, state: TrackerState, lost_state: TrackerState, lost: FrameResult, frames, frames_j, params):
        """`_search` with failures as values: an exception in the search (OpenCV, a compile) leaves the frame LOST.
        With the backoff of a persistently lost object (`RecoveryConfig.max_skip`), a frame due no search stays LOST
        as one whose search found nothing ("skipped": "backoff")."""
        if self._searches_to_skip > 0:
            self._searches_to_skip -= 1
            return self._still_lost(lost_state, lost, {"recovered": False, "source": None, "skipped": "backoff"})
        try:
            out = self._search(state, lost_state, lost, frames, frames_j, params)
        except Exception as error:  # noqa: BLE001  (inside the tracking loop a failure is a status, never a raise)
            out = self._still_lost(lost_state, lost, {"recovered": False, "source": None, "error": repr(error)})
        info = out[2]
        if info["recovered"]:
            self._failed_searches = 0
        elif info.get("skipped") is None:  # searched and found nothing: the next search waits longer
            self._failed_searches += 1
            self._searches_to_skip = min(2 ** (self._failed_searches - 1) - 1, self.config.recovery.max_skip)
        return out

    def _still_lost(self, lost_state: TrackerState, lost: FrameResult, info: dict) -> tuple:
        """(`lost_state`, `lost`, `info` with the windows at the lost pose): a frame that stays LOST after (or without)
        a search goes on with the same state as without recovery (its colour histograms and appearance model learnt from it as
        from any frame: kept as they were instead, the noisy moving camera lost 20 → 4 % of its frames and the noise
        table failed up to 14 frames earlier, though the truck on the turntable held better, 5.39° → 3.48°;
        README, "Finding it again")."""
        info["windows"] = self.windows(lost.T_world_root, lost.theta)
        return lost_state, lost, info

    def _search(self, state: TrackerState, lost_state: TrackerState, lost: FrameResult, frames, frames_j, params):
        """After a LOST frame: search for the pose (`recover`), then the normal step again on frames t+1 → t+1 from
        what it found (no motion: the prediction is the found pose). Its status OK makes the frame RECOVERED and
        its state the next one; otherwise the frame stays LOST with the lost step's state (`_still_lost`)."""
        theta = lost.theta
        info = {"recovered": False, "source": None}
        if self.keyframes is not None:  # re-detection: keyframe descriptors → PnP + RANSAC
            good = state.T_world_root if self.last_good_pose is None else self.last_good_pose
            regions = self._search_regions(((lost.T_world_root, theta), (good, theta)))
            K, dist, T_cam_world = self._camera_arrays()
            pnp = self.keyframes.locate(frames, regions, K, dist, T_cam_world)
            info["pnp_inliers"] = 0 if pnp is None else pnp.inliers
            if pnp is not None:
                info["source"], info["T_found"] = "keyframes", pnp.T_world_root
                out = self._restart(state, lost_state, lost, frames, frames_j, params, jnp.asarray(pnp.T_world_root, self.dtype), info)
                if info["recovered"]:
                    return out
        if not self.config.recovery.hypotheses:
            return self._still_lost(lost_state, lost, info)
        warmup = self._recovery_warmup
        if warmup is not None and warmup.is_alive() and self._recovery_wait_left > 0:
            # No frame waits for a compile: a frame lost while the hypotheses' program still compiles in the background
            # (6.9 s in a fresh process on the loss experiment's sequences) stays LOST, and the search runs from the
            # next lost frame on. A short wait is taken, once per tracker (`RECOVERY_COMPILE_WAIT_S` for all its lost
            # frames together): a second tracker of the same configuration in a process only traces the program and
            # finds it compiled (0.3-0.4 s measured), and the first lost frame, often the one nearest the right pose,
            # is where the search is most likely to find it.
            wait_start = time.perf_counter()
            warmup.join(timeout=self._recovery_wait_left)
            self._recovery_wait_left -= time.perf_counter() - wait_start
        if warmup is not None and (warmup.is_alive() or self._recovery_warmup_error is not None):
            info["skipped"] = "compiling" if warmup.is_alive() else f"compile failed: {self._recovery_warmup_error!r}"
            return self._still_lost(lost_state, lost, info)
        found = self.recover(state, frames, lost.T_world_root, params)
        info.update({"score": float(found.score), "own_score": float(found.own_score), "hypothesis": int(found.index),
                     "T_found": np.asarray(found.T_world_root), "source": "region"})
        turned = _rotation_deg(np.asarray(found.T_world_root, np.float64)[:3, :3],
                               np.asarray(lost.T_world_root, np.float64)[:3, :3])
        # Flips must beat the lost pose's refinement clearly; a near pose must only not be worse. The lost pose's own
        # refinement by the lines (hypothesis 0, at its own score) is then tried whenever it is the best: every
        # search that finds nothing better is followed by the normal step from that refinement (`_restart` decides).
        margin = 0.0 if turned <= self.config.recovery.near_deg else self.config.recovery.margin
        info["turned_deg"] = turned
        if not float(found.score) >= float(found.own_score) + margin:  # nothing better
            return self._still_lost(lost_state, lost, info)
        return self._restart(state, lost_state, lost, frames, frames_j, params, found.T_world_root, info)

    def _restart(self, state, lost_state, lost, frames, frames_j, params, T_found, info):
        """The normal step on frames t+1 → t+1 from a found pose: (state, result) RECOVERED when it is OK and explains
        the frame better than the lost pose did, else (`lost_state`, `lost`); `info` gets "windows", "confidence",
        "recovered". Between a frame and itself the motion cues see no motion, so the restart's motion evidence and
        jump are empty (they read as agreement): the found pose must also beat the lost one on the evidence that
        does not depend on motion, the contour, the occluded fraction and the appearance distance."""
        theta = lost.theta
        boxes = projected_boxes(self.mesh, self.cameras, T_found, theta, self.model)
        H, W = self.cameras.height, self.cameras.width
        on_screen = np.isfinite(boxes).all(1) & (boxes[:, 2] >= 0) & (boxes[:, 0] < W) & (boxes[:, 3] >= 0) & (boxes[:, 1] < H)
        # frames t+1 → t+1: no motion between them, so the windows hold the found box without the last step's motion
        offsets, crop_shape, scales = (self.windows(T_found, theta, boxes, follow_motion=False) if on_screen.any()
                                       else (None, None, None))
        if offsets is None:
            return self._still_lost(lost_state, lost, info)
        visible = np.zeros((self.num_cameras, H, W), bool)  # the SIFT mask of "frame t" (= t+1): the found box
        for c, (x0, y0, x1, y1) in enumerate(np.clip(np.nan_to_num(boxes), 0, [W - 1, H - 1, W - 1, H - 1]).astype(int)):
            visible[c, y0:y1 + 1, x0:x1 + 1] = on_screen[c]
        # a new start from the found pose: the running loss evidence starts over, as at `start`
        restart = eqx.tree_at(lambda s: (s.T_world_root, s.images, s.data_weight, s.visible, s.loss_evidence_average,
                                         s.last_confidence),
                              state, (T_found, frames_j, jnp.ones_like(state.data_weight), jnp.asarray(visible),
                                      self._no_loss_evidence(), self._no_confidence()), is_leaf=lambda x: x is None)
        host_cache = copy.deepcopy(self.host_cache)  # what the step from the found pose detects is kept only if taken
        new_state, result, _ = self._run_step(restart, frames, frames_j, offsets, params, crop_shape, scales)
        info["windows"] = (offsets, crop_shape, scales)
        info["confidence"] = float(result.confidence)
        found_ev, lost_ev = np.asarray(result.loss_evidence), np.asarray(lost.loss_evidence)
        static = [LOSS_EVIDENCE.index(n) for n in ("contour", "occluded", "appearance")]
        if int(result.status) != Status.OK or np.any(found_ev[static] > lost_ev[static]):
            self.host_cache = host_cache  # refused: the lost step's host state (SIFT: frame t+1's keypoints) as it was
            return lost_state, lost, info
        info["recovered"] = True
        self.recoveries += 1
        self.last_good_pose = result.T_world_root
        return new_state, eqx.tree_at(lambda r: r.status, result, jnp.asarray(Status.RECOVERED, jnp.int32)), info

    def _out_of_view(self, state: TrackerState) -> FrameResult:
        C, dt = self.num_cameras, self.dtype
        return FrameResult(
            T_world_root=state.T_world_root, theta=state.theta, T_pred=state.T_world_root, theta_pred=state.theta,
            status=jnp.asarray(Status.OUT_OF_VIEW, jnp.int32), confidence=jnp.zeros((), dt), iou=jnp.zeros((C,), dt),
            counts=jnp.zeros((C, len(self.config.cues)), jnp.int32), motion_inliers=jnp.zeros((), dt), occluded_fraction=jnp.zeros((C,), dt),
            iterations=jnp.zeros((), jnp.int32), region_phi=-jnp.ones((C, 1, 1), dt),
            part_support=-jnp.ones((self.model.num_parts,), dt), appearance_distance=-jnp.ones((C,), dt),
            loss_evidence=jnp.zeros((len(LOSS_EVIDENCE),), dt),
        )
