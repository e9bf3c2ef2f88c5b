"""The per-frame step of the tracker (Section V, Fig. 2): one jittable function of arrays.

The tracker owns one loop over modalities (`jaxtrack.modality`; region, flow, SIFT and any registered
one). For frames t → t+1 of C cameras sharing one state χ = (ξ, Θ):

1. render the model at χ_t into each camera's crop (principal point shifted, static crop size); every
   modality starts its frame (`Modality.start`: the flow of the crop with r(x) of frame t as data
   weight (eq. 6-8), the SIFT rows from the host's matches, the carried densities cropped). The part that
   needs nothing from the host is also a function of its own, `start_frame`: the tracker runs it while the
   host detects SIFT keypoints and hands its output to `track_step(early=)`;
2. prediction: one Gauss-Newton solve on the motion modalities' rows with the prediction weights of
   Section V (n_C → n_OF), and with `TrackerParams.motion_robust_px` > 0 a second pass from it with the rows
   weighed by a Cauchy loss of their reprojection error (`_robust_prediction`); the modalities check their rows
   against it (SIFT back-projection);
3. refinement (`refine_rounds`): rounds of {one render per camera at the current pose, the rows of every
   modality (the motion rows Cauchy-weighted at the round's pose), one fused solve with the joint and pose
   priors} until the pose settles;
4. update: every modality's state (densities), the occlusion map of frame t+1 at the final pose (the
   next step's r(x) and the SIFT mask) and the appearance model where not occluded (eq. 10).

Failures are values: the frame's `Status` and a confidence from evidence the tracker has (contour and
silhouette agreement, agreement of the motion cues with the final pose, the appearance model against the
image, how far the refinement moved from the prediction; for the lines with the occlusion detection combined
by weights calibrated on synthetic sequences, `LOSS_WEIGHTS`), never from ground truth. Every parameter is an array (`TrackerParams`), so weights and thresholds can be swept
with vmap or differentiated without recompiling; what shapes the program (`TrackerConfig`, the raster
plan, the crop size class) is static.
"""

from __future__ import annotations

import dataclasses
import functools
import os

import equinox as eqx
import jax
import jax.numpy as jnp

from .._status import Status, first_failure, is_usable, status_where
from ..cues.flow import FlowConfig, FlowEnergyParams
from ..cues.levelset import RegionConfig, RegionParams
from ..cues.lines import LineParams, line_params
from ..cues.occlusion import (
    AppearanceModel,
    OcclusionConfig,
    OcclusionParams,
    TextureAtlas,
    detect_occlusion,
    observe_texels,
    update_appearance,
)
from ..cues.sift import SiftParams, reprojection_errors
from ..geometry import Camera, KinematicModel, crop_camera, rotation_error_deg
from ..image import crop_window, paste_window, paste_window_scaled, sample_window
from ..modality import (
    FrameContext,
    Modality,
    Pose,
    RefineSettings,
    cauchy_weights,
    fuse_rows,
    modality_class,
    modality_names,
    refine_rounds,
    render_crops,
    reprojection_px,
)
from ..render import Mesh, RasterPlan
from ..solve import Correspondences, CueWeights, SolverConfig, concatenate_correspondences, solve_pose
from . import _builtin_modalities  # noqa: F401  (registers region/levelset, flow, sift)
from ._recovery import RecoveryConfig

CUES = ("region", "flow", "sift")
# The crops' working resolution for rigid objects (TrackerConfig.working_shape "auto"), measured in the README's
# working-resolution table against native crops (experiments/results/working_resolution.md).
RIGID_WORKING_SHAPE = (96, 128)
REGION_MODALITIES = ("levelset", "lines")
# The evidence of a lost frame (`FrameResult.loss_evidence`, in this order) and the logistic models that turn it
# into p(frame beyond 5 cm / 5°), fitted by experiments/loss_detection.py on its calibration sequences (other seeds,
# objects and motions than the sequences it is evaluated on). The frame's own evidence comes first, then its running
# average over the frames up to this one (`TrackerState.loss_evidence_average`: a · average + (1 − a) · frame, a =
# LOSS_EVIDENCE_DECAY, zero at `Tracker.start`): a pose that drifts off slowly shows weak evidence on many frames in a
# row (issue 24's "against its running statistics").
LOSS_FRAME_EVIDENCE = ("contour", "motion", "occluded", "appearance", "jump_pred")
LOSS_EVIDENCE = LOSS_FRAME_EVIDENCE + tuple(f"{name}_avg" for name in LOSS_FRAME_EVIDENCE)
LOSS_EVIDENCE_DECAY = 0.5
# One row per model, [intercept, one weight per LOSS_EVIDENCE]; the confidence is the least of the models' p(frame
# right). Row 0 reads the frame alone (the weights of 20cb01f, fitted when the Cauchy loss on the motion rows came: a
# loss that starts in this frame); row 1 also the running averages (fitted at 2026-11-29 on the calibration sequences:
# a loss that has lasted). Alone, row 1 left the first lost frame of a sequence less often LOST (README, "Knowing when
# it is lost").
LOSS_WEIGHTS = ((-3.432, 20.073, 1.809, 12.357, -5.943, 0.294, 0.0, 0.0, 0.0, 0.0, 0.0),
                (-3.506, 1.805, -0.737, 8.361, -7.675, 0.073, 23.472, 5.522, 1.293, 2.751, 0.059))

# The flow pyramid's coarsest level at the working resolution (px, short side). With the default 16 a 96 px crop
# had 3 levels, one fewer than the native crops it replaced, and the prediction did not reach a 20 px / 12° frame
# step (frame_rate S = 4: 38 % success, 100 % with 8; tests/test_tracker.py shows the cut-off reach).
# With 8 px (4 levels) a 24 px shift of a 96x128 crop came out as about zero: the large-motion experiment's 30 px /
# 10° step (24 crop px) left the flow + SIFT prediction worse than none (all cues 3/8 tracked); with 4 px, 8/8
# (experiments/large_motion.py; README "Residuals that shrink toward the camera, and a flow that missed a large motion").
WORKING_FLOW_MIN_SIZE = 4


@functools.lru_cache(maxsize=64)
def _configured_modalities(config: TrackerConfig, view_subdivisions_env: str | None) -> tuple[Modality, ...]:
    del view_subdivisions_env  # part of the cache key only
    region = "lines" if config.region_modality == "auto" else config.region_modality
    return tuple(c if isinstance(c, Modality) else modality_class(region if c == "region" else c).from_config(config)
                 for c in config.cues)


class TrackerConfig(eqx.Module):
    """Static settings of the tracker (they shape the compiled step).

    Attributes:
        cues: the modalities used, in order: registered names ("flow", "sift", "levelset", any name
            registered with `register_modality`), "region" for the configured region modality
            (`region_modality`), or `Modality` instances. Default ("region", "flow", "sift").
        region_modality: which modality "region" means: "levelset" (the paper's dense level set), "lines"
            (the region energy on correspondence lines, `jaxtrack.cues.lines.LineRegion`) or "auto" (the
            default): the lines, for rigid objects and chains (`resolved`; measured in
            experiments/results/real_sequences_*.md and track_presets_lines.md: on rigid objects the lines
            track the real video and the tea box better at a twentieth of the time; on chains, Table II's walk
            and run and the robot arm (human_table2_lines.md, robot_arm_lines.md): smaller knee and elbow errors
            at every frame rate in a third of the time). The level set's per-limb support
            (`FrameResult.part_support`, `TrackingRun.lost_joints`) needs its segmentation: -1 / none with the lines.
        occlusion: run the model-based occlusion detection (r(x) for flow, the SIFT mask).
        region: the level-set modality's settings (iterations, rounds (10 here), contour capacity, ...);
            its `outer_iterations` and `solver_steps` are the refinement's rounds and Gauss-Newton steps.
        flow: the flow minimiser's settings (a fast coarse-to-fine schedule on the crop).
        flow_stride: grid step of the flow correspondences (capacity (h/s)·(w/s) per camera).
        prediction_steps: Gauss-Newton steps of the prediction solve.
        occlusion_config: histogram bins and window of the occlusion test.
        sift_mode: "surface" (rendered surface point under the keypoint) or "vertex" (the paper's
            closest projected visible vertex).
        working_shape: (h, w) fixed working resolution of the crops, None, or "auto" (the default:
            `RIGID_WORKING_SHAPE` for a rigid object without the level set, else None, `resolved`). With a shape, the region
            around the object (box plus margin) is resampled to it with the scale as data
            (`jaxtrack.image.sample_window`, `crop_camera(..., scale)`): one compiled step whatever the
            object's size on screen, and the flow, occlusion and renders of the crops at that size. None:
            crops cut at the native resolution in size classes (one compilation per class); chains keep them
            (the working resolution is not measured on Table II).
        recovery: the search after a LOST frame (`RecoveryConfig`, `jaxtrack.track.Tracker.step`; where `recovers`
            holds: the lines and a rigid object), on by default; None: a lost frame is reported and tracking goes on
            from its pose. A frame the search does not recover goes on as without it. On the loss experiment's
            sequences, mean within 5 cm / 5°: 67.2 % without recovery, 77.7 % with it (the search loaded from the
            on-disk cache, or compiled from the first frame), 69.4 % with an empty cache (the search compiles at the
            first doubt), 81.3 % with RBOT resets (experiments/results/recovery.md, recovery_empty_cache.md,
            recovery_first_frame_warmup.md); the turntable truck 6.75° →
            5.39°; on the recorded video, the presets, the noise table and the moving camera it recovered no frame and
            changed no pose (README, "Finding it again"). It costs a search and a second step on a lost frame (154 ms
            median, 256 max; fewer and fewer on a persistently lost object, `RecoveryConfig.max_skip`) and a
            background compile of the search (6.9 s of the 2 cores in a fresh process; a load from the on-disk cache
            after that), started at the first frame reported UNCERTAIN or LOST (`Tracker.warm_up_recovery`). The
            compiled step does not depend on it (`Tracker.setup`: one step program with and without recovery).
        depth_invariance: whether the prediction's and the refinement's solves scale the residuals by depth
            (`TrackerParams.depth_invariant`, with the cameras' centres) or solve eq. 4 as it is, summing each solve's
            rows per part once where they are many (`SolverConfig.moments_from_rows`,
            `jaxtrack.solve._moments.plane_moments`: the same normal equations to rounding, at a cost per Gauss-Newton
            iterate independent of the rows). "auto" (the default, `resolved`): True for a rigid object
            (whose default p is 1), False for a chain (whose default p is 0: `DEPTH_INVARIANT` says why); with False
            the tracker refuses parameters with a non-zero `depth_invariant`.
    """

    cues: tuple = eqx.field(static=True, default=CUES)
    region_modality: str = eqx.field(static=True, default="auto")
    occlusion: bool = eqx.field(static=True, default=True)
    # The prediction starts the refinement near the answer: 10 rounds gave the tea box the same errors as
    # 30 (1.43° / 2.54 mm both, measured) and bound the frame's worst-case time.
    region: RegionConfig = eqx.field(static=True, default_factory=lambda: RegionConfig(outer_iterations=10))
    # Levels from 2 on share one compiled level (`FlowConfig.shared_levels_from`): the same flow to rounding, 4 s less
    # XLA compile at 96x128 and 240x320 for 0.3 ms or less per call; from 1 on compiled 2 s faster still but ran 3.4 ms
    # slower at 96x128 (experiments/results/flow_compile.md).
    flow: FlowConfig = eqx.field(static=True, default_factory=lambda: FlowConfig(eta=0.5, min_size=16, warps=4, lagged=1,
                                                                                 sor_iters=10, shared_levels_from=2))
    flow_stride: int = eqx.field(static=True, default=4)
    prediction_steps: int = eqx.field(static=True, default=10)
    occlusion_config: OcclusionConfig = eqx.field(static=True, default_factory=OcclusionConfig)
    sift_mode: str = eqx.field(static=True, default="surface")
    working_shape: tuple | str | None = eqx.field(static=True, default="auto")
    recovery: RecoveryConfig | None = eqx.field(static=True, default_factory=RecoveryConfig)
    depth_invariance: bool | str = eqx.field(static=True, default="auto")

    def __check_init__(self):
        cues = tuple(self.cues)
        names = [c if isinstance(c, str) else getattr(c, "name", None) for c in cues]
        choices = ("region",) + modality_names()
        bad = [c for c in cues if not (isinstance(c, Modality) or (isinstance(c, str) and c in choices))]
        if not cues or bad or len(set(names)) != len(names):
            raise ValueError(f"TrackerConfig.cues must be a non-empty list of distinct modalities from {choices} "
                             f"(or Modality instances), got {self.cues}")
        if self.region_modality != "auto" and (self.region_modality not in modality_names()
                                               or not modality_class(self.region_modality).contour):
            raise ValueError(f"TrackerConfig.region_modality must be a region modality {REGION_MODALITIES}, got "
                             f"{self.region_modality!r}")
        resolved = [(self.region_modality if self.region_modality != "auto" else "lines") if c == "region" else c for c in names]
        if len(set(resolved)) != len(resolved):
            raise ValueError(f"TrackerConfig.cues names one modality twice ('region' is {self.region_modality!r}): {self.cues}")
        if self.flow_stride < 1 or self.prediction_steps < 1:
            raise ValueError("TrackerConfig: flow_stride and prediction_steps must be ≥ 1")
        if self.working_shape is not None and not (isinstance(self.working_shape, str) and self.working_shape == "auto"):
            ws = tuple(self.working_shape) if not isinstance(self.working_shape, str) else ()
            f = self.region.density_factor
            if len(ws) != 2 or any(not isinstance(v, int) or v < 16 or v % f for v in ws):
                raise ValueError(f"TrackerConfig.working_shape must be (h, w): integers ≥ 16 divisible by the level "
                                 f"set's density factor {f}, got {self.working_shape}")
        if not (isinstance(self.depth_invariance, bool) or self.depth_invariance == "auto"):
            raise ValueError(f"TrackerConfig.depth_invariance must be True, False or 'auto', got {self.depth_invariance!r}")
        if self.sift_mode not in ("surface", "vertex"):
            raise ValueError(f"TrackerConfig.sift_mode must be 'surface' or 'vertex', got {self.sift_mode!r}")

    @property
    def cue_names(self) -> tuple[str, ...]:
        """The configured cues as named in `cues` ("region" stays "region"): the count columns' names."""
        return tuple(c if isinstance(c, str) else c.name for c in self.cues)

    def resolved(self, articulated: bool) -> TrackerConfig:
        """This configuration with "auto" resolved for a rigid object (lines; crops at `RIGID_WORKING_SHAPE` unless
        the level set is configured) or a chain (lines; native-resolution crops). With a working shape the
        flow pyramid runs down to `WORKING_FLOW_MIN_SIZE` (the crop is small: it needs its levels to reach the
        motion)."""
        out = self
        if self.region_modality == "auto":
            out = dataclasses.replace(out, region_modality="lines")
        if isinstance(self.working_shape, str):  # "auto": not with the level set (measured at native crops only)
            dense = any(m.name == "levelset" for m in out.modalities())
            out = dataclasses.replace(out, working_shape=None if articulated or dense else RIGID_WORKING_SHAPE)
        if isinstance(self.depth_invariance, str):  # "auto": scaled for rigid objects, eq. 4 (moments) for chains
            out = dataclasses.replace(out, depth_invariance=not articulated)
        if out.working_shape is not None and out.flow.min_size > WORKING_FLOW_MIN_SIZE:
            out = dataclasses.replace(out, flow=dataclasses.replace(out.flow, min_size=WORKING_FLOW_MIN_SIZE))
        return out

    def modalities(self) -> tuple[Modality, ...]:
        """The configured `Modality` instances, in the order of `cues` ("auto" counts as rigid: "lines").

        Built once per configuration (and `$JAXTRACK_VIEW_SUBDIVISIONS`, which `LineRegion.from_config` reads):
        the tracker asks several times per frame."""
        env = os.environ.get("JAXTRACK_VIEW_SUBDIVISIONS")
        try:
            return _configured_modalities(self, env)
        except TypeError:  # a user's Modality instance that cannot be hashed: built each time
            return _configured_modalities.__wrapped__(self, env)

    def loop_settings(self) -> tuple[int, int, int]:
        """(rounds, Gauss-Newton steps per round, minimum rounds) of the refinement: the largest of the
        modalities' preferences (`Modality.loop_preferences`), else the level set's `region` settings."""
        prefs = [m.loop_preferences() for m in self.modalities()]
        rounds = max([p[0] for p in prefs] + [0]) or self.region.outer_iterations
        steps = max([p[1] for p in prefs] + [0]) or self.region.solver_steps
        return rounds, steps, max([p[2] for p in prefs] + [0])

    def uses_crop(self) -> bool:
        """Whether any modality (or the occlusion detection) reads crops: else whole frames, one program."""
        return any(m.uses_crop for m in self.modalities()) or self.runs_occlusion()

    def runs_occlusion(self) -> bool:
        """The occlusion detection runs when asked for and some modality reads its r(x) or mask."""
        return self.occlusion and any(m.uses_occlusion for m in self.modalities())

    def calibrated_confidence(self) -> bool:
        """Whether the frame's confidence is the calibrated p(frame right) of `LOSS_EVIDENCE`: with a contour
        modality that reports its own agreement (the lines) and the occlusion detection (its appearance
        evidence), the configuration the weights were fitted on. Else the silhouette agreement (level set) or
        the modality's own confidence, as before."""
        if not self.runs_occlusion():
            return False
        contour = [m for m in self.modalities() if m.contour]
        return bool(contour) and not any(m.needs_render for m in contour)

    def without_recovery(self) -> TrackerConfig:
        """This configuration with no hypothesis search (`recovery` None); itself where it has none."""
        return self if self.recovery is None else dataclasses.replace(self, recovery=None)

    def recovers(self) -> bool:
        """Whether a LOST frame starts the hypothesis search (`recovery`): it needs the calibrated status (what
        says LOST) and the line modality (what scores and refines the hypotheses); a rigid object's sparse
        viewpoint model is checked by the tracker."""
        if self.recovery is None or not self.calibrated_confidence():
            return False
        return any(m.name == "lines" for m in self.modalities())

    def has(self, cue: str) -> bool:
        """Whether a cue is configured ("region" matches any contour modality)."""
        if cue == "region":
            return any(m.contour for m in self.modalities())
        return cue in self.cue_names or any(m.name == cue for m in self.modalities())


class TrackerParams(eqx.Module):
    """Every numeric parameter of the tracker, as arrays (vmap, grad, no recompilation).

    Attributes:
        weights: user factors on the Section V cue weights.
        flow: α, γ, ε and the smoothness type of eq. 6 (rigid: quadratic α = 800; chains: robust α = 50).
        flow_beta: β of the confidence (eq. 8).
        region: λ, ν, ρ, ... of the region cue (eq. 11-15); its `settle_motion` ends the refinement rounds and
            its `joint_prior` is the refinement's joint prior.
        sift: the SIFT outlier-filter thresholds.
        occlusion: the occlusion threshold 1/4 and update rate 1/8 (eq. 9-10).
        lost_iou, uncertain_iou: silhouette agreement below which a frame is lost / uncertain.
        inlier_px: a motion correspondence agrees with the final pose within this many pixels.
        theta_lower, theta_upper: (J,) joint limits (model units); ±inf (the default: the method uses no
            priors) leaves Θ free. The prediction and the refined Θ are projected onto them.
        pose_prior_rotation, pose_prior_translation: relative stiffnesses of the Tikhonov prior of the
            refinement toward the prediction (`jaxtrack.solve.PosePrior`; 0: none, the method's choice).
        render_reuse_px: a refinement round reuses the previous round's render when the model moved less than
            this many pixels since (0: a render every round).
        pose_prior_rotation_abs, pose_prior_translation_abs: absolute stiffnesses of the pose prior (per rad²,
            per mm² of the weighted residual; M3T's 1000 / 30000 for rows weighted as the line modality's).
        prior_follows_round: 1: the pose prior pulls toward each round's starting pose (M3T's damping); 0:
            toward the prediction for the whole frame.
        lines: the correspondence-line modality's parameters (`jaxtrack.cues.lines.LineParams`, M3T's defaults).
        line_learning_rate: rate of its colour-histogram update per frame (M3T: 0.2).
        loss_weights: (K, 1 + len(LOSS_EVIDENCE)) K logistic models of the calibrated confidence (`LOSS_WEIGHTS`;
            one row (1 + len(LOSS_EVIDENCE),) is one model): confidence = min_k 1 − σ(w_k0 + w_k · evidence) where
            it applies (`TrackerConfig.calibrated_confidence`).
        loss_evidence_decay: a of the running average of the frames' loss evidence (`TrackerState
            .loss_evidence_average`, the second half of `FrameResult.loss_evidence`; `LOSS_EVIDENCE_DECAY`).
        uncertain_confidence, lost_confidence: a calibrated confidence below these is UNCERTAIN / LOST (0.5: one of
            the models finds the frame more likely beyond 5 cm / 5° than not).
        flow_structure: k of the flow's structure factor g = λ_min / (λ_min + k σ_n² + 1) on eq. 8's confidence
            (`jaxtrack.cues.flow.structure_confidence`: the image must pin the flow); negative: off (the paper's c).
        flow_limb_slope: where the structure factor is on, no structure counts within 2 px of the limbs of the render
            at χ_t: pixels whose surface slope |ΔZ|·f/Z exceeds this (`jaxtrack.cues.flow.limb_pixels`; tan 80° = 5.67,
            the tracker's default for rigid objects); ≤ 0: off (chains' default).
        rows_per_px: 1: the flow, SIFT and level-set rows' weights count per px² of the full-frame image, as the
            line modality's (`jaxtrack.solve.weights_per_pixel`: × (f / Z)²), so that the cues' balance does not
            depend on the object's distance or the image resolution; 0: per mm² of the Plücker residual (eq. 4).
        depth_invariant: p in [0, 1] of the prediction's and the refinement's solves (`jaxtrack.solve.solve_pose`'s
            `depth_invariance`, with the cameras' centres): each row's residual × (Z₀ / Z)^p, so that rows that
            disagree are not fitted by sliding the object toward the camera; 0: eq. 4 as it is (the tracker's
            default for chains; 1 for rigid objects). Read where `TrackerConfig.depth_invariance` holds (rigid
            objects by default); a chain's tracker refuses a non-zero value unless that is set.
        motion_robust_px: scale (px of the crops) of the Cauchy loss on the flow and SIFT rows: the prediction's
            second pass (`_robust_prediction`) and every refinement round (`jaxtrack.modality.RefineSettings
            .motion_robust_px`); ≤ 0: off (eq. 5 as it is; the default for chains, 2 for rigid objects).
        motion_rounds, motion_late_factor: the flow and SIFT rows count fully in the refinement's rounds 0 ..
            motion_rounds − 1 and × motion_late_factor after (`jaxtrack.modality.RefineSettings.motion_rounds`);
            ∞: every round (the method; the field's default, and `default_params`' for chains; rigid objects take
            `jaxtrack.track._tracker.MOTION_ROUNDS` / `MOTION_LATE_FACTOR`, ∞ / 0 unless the environment says).
        motion_late_above: motion_rounds and motion_late_factor apply to a frame only when the confidence of the frame
            before (`TrackerState.last_confidence`) is at least this: the contour finishes the refinement alone where the
            tracker was sure of the last frame, and the motion rows hold every round where it was not, or where no frame
            has been measured yet (the first frame after `start` or a recovery, 0); 0: always (the field's default;
            rigid objects take `jaxtrack.track._tracker.MOTION_LATE_ABOVE`). `motion_rounds_for` applies it.
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
    pose_prior_rotation: jax.Array = eqx.field(default_factory=lambda: jnp.zeros(()))
    pose_prior_translation: jax.Array = eqx.field(default_factory=lambda: jnp.zeros(()))
    render_reuse_px: jax.Array = eqx.field(default_factory=lambda: jnp.zeros(()))
    pose_prior_rotation_abs: jax.Array = eqx.field(default_factory=lambda: jnp.zeros(()))
    pose_prior_translation_abs: jax.Array = eqx.field(default_factory=lambda: jnp.zeros(()))
    prior_follows_round: jax.Array = eqx.field(default_factory=lambda: jnp.zeros(()))
    lines: LineParams = eqx.field(default_factory=line_params)
    line_learning_rate: jax.Array = eqx.field(default_factory=lambda: jnp.asarray(0.2))
    loss_weights: jax.Array = eqx.field(default_factory=lambda: jnp.asarray(LOSS_WEIGHTS))
    loss_evidence_decay: jax.Array = eqx.field(default_factory=lambda: jnp.asarray(LOSS_EVIDENCE_DECAY))
    flow_structure: jax.Array = eqx.field(default_factory=lambda: jnp.asarray(-1.0))
    flow_limb_slope: jax.Array = eqx.field(default_factory=lambda: jnp.asarray(-1.0))
    rows_per_px: jax.Array = eqx.field(default_factory=lambda: jnp.asarray(0.0))
    depth_invariant: jax.Array = eqx.field(default_factory=lambda: jnp.asarray(0.0))
    uncertain_confidence: jax.Array = eqx.field(default_factory=lambda: jnp.asarray(0.5))
    lost_confidence: jax.Array = eqx.field(default_factory=lambda: jnp.asarray(0.25))
    motion_robust_px: jax.Array = eqx.field(default_factory=lambda: jnp.asarray(-1.0))
    motion_rounds: jax.Array = eqx.field(default_factory=lambda: jnp.asarray(jnp.inf))
    motion_late_factor: jax.Array = eqx.field(default_factory=lambda: jnp.zeros(()))
    motion_late_above: jax.Array = eqx.field(default_factory=lambda: jnp.zeros(()))


def motion_rounds_for(last_confidence, params: TrackerParams) -> jax.Array:
    """The refinement's `motion_rounds` for a frame after one of confidence `last_confidence` (() array, or None: no
    frame measured yet, read as 0): `params.motion_rounds` where that is at least `params.motion_late_above`, else ∞
    (the motion rows count in every round). Jittable."""
    previous = jnp.zeros(()) if last_confidence is None else jnp.asarray(last_confidence)
    rounds = jnp.asarray(params.motion_rounds)
    return jnp.where(previous >= params.motion_late_above, rounds, jnp.full_like(rounds, jnp.inf))


class TrackerSetup(eqx.Module):
    """What a sequence fixes: mesh, kinematic model, cameras (C stacked), appearance atlas, raster plans (the
    full frame's and, at the fixed working resolution, the crops'), and each modality's prepared data
    (`Modality.prepare`).

    The plan and the config are static (a re-plan after a render overflow is one recompilation,
    decided on the host between frames).
    """

    mesh: Mesh
    model: KinematicModel
    cameras: Camera
    atlas: TextureAtlas
    plan: RasterPlan = eqx.field(static=True)
    config: TrackerConfig = eqx.field(static=True)
    prepared: tuple | None = None  # one entry per modality: what its `prepare` made (e.g. a view model)
    crop_plan: RasterPlan | None = eqx.field(static=True, default=None)

    @property
    def window_plan(self) -> RasterPlan:
        """The plan of renders in the crops: `crop_plan` at the fixed working resolution (face extents in
        working pixels, a fraction of the full frame's), else `plan` (crops at the frame's own pixels)."""
        return self.plan if self.crop_plan is None else self.crop_plan

    def prepared_for(self, index: int):
        return None if self.prepared is None else self.prepared[index]


class TrackerState(eqx.Module):
    """What the tracker carries from frame t to t+1 (full-frame arrays, C cameras).

    Attributes:
        T_world_root: (4, 4) root pose at t (model → world); theta: (J,) joint angles at t.
        images: (C, H, W, 3) frames t (0-255): uint8 when the tracker started on 8-bit frames, else floats.
        data_weight: (C, H, W) r(x) of frame t (0 = occluded), the flow cue's data weight.
        visible: (C, H, W) bool non-occluded object pixels of frame t (the SIFT detection mask).
        appearance: the appearance model f of the occlusion detection.
        modalities: one state per configured modality (`TrackerConfig.modalities()` order), e.g. the
            level set's `RegionState` (last segmentation and local densities).
        occluder_depth: (C, H, W) depth (mm) of the other objects of a joint run at their latest poses
            (`JointTracker` sets it before each step; inf where none), None when one object is tracked; the
            line modality leaves out the lines it hides (`FrameContext.occluder_depth`).
        loss_evidence_average: (len(LOSS_FRAME_EVIDENCE),) the running average of the frames' loss evidence up to t
            (`LOSS_EVIDENCE_DECAY`; zeros at `Tracker.start` and after a recovery, a new start); None reads as zeros.
        last_confidence: () `FrameResult.confidence` of frame t, the gate of `TrackerParams.motion_late_above`; 0 at
            `Tracker.start` and after a recovery (no frame measured yet); None reads as 0.
    """

    T_world_root: jax.Array
    theta: jax.Array
    images: jax.Array
    data_weight: jax.Array
    visible: jax.Array
    appearance: AppearanceModel
    modalities: tuple
    occluder_depth: jax.Array | None = None
    loss_evidence_average: jax.Array | None = None
    last_confidence: jax.Array | None = None


class FrameResult(eqx.Module):
    """What one step reports about frame t+1.

    Attributes:
        T_world_root, theta: the final pose; T_pred, theta_pred: the prediction from the motion cues.
        status: int32 `Status`: OK, UNCERTAIN, LOST (from the confidence), OUT_OF_VIEW, RENDER_OVERFLOW (re-plan and
            redo), ...
        confidence: [0, 1] evidence that the pose is right: with `TrackerConfig.calibrated_confidence` the
            lowest of the calibrated models' p(frame within 5 cm / 5°) of `loss_evidence` (`TrackerParams
            .loss_weights`; conservative: either model's doubt counts); else the silhouette agreement of
            segmentation and model (level set), the contour modality's own agreement, or the motion inliers.
        iou: (C,) agreement of the segmentation with the model silhouette at the final pose per camera.
        counts: (C, M) correspondences with weight per camera and configured cue (`TrackerConfig.cue_names`) in the
            refinement's last round (with `TrackerParams.motion_late_factor` 0 the motion cues read 0 there).
        motion_inliers: fraction of weighted motion correspondences within `inlier_px` at the final pose.
        occluded_fraction: (C,) fraction of object pixels of frame t+1 detected as occluded.
        iterations: refinement rounds run.
        region_phi: (C, h, w) the segmentation Φ of frame t+1 on the crop (for overlays).
        part_support: (P,) per part, the fraction of its unoccluded model silhouette (all cameras) that the
            segmentation covers; −1 where the part is not seen or no modality segments. A limb whose
            support falls below `lost_iou` has lost its silhouette.
        appearance_distance: (C,) mean histogram distance d (eq. 9) between the appearance model and the image
            over the object pixels whose texel is known, at the final pose (0: the surface looks as learnt; a
            wrong pose reads the wrong texture); −1 where the occlusion detection did not run or nothing is known.
        loss_evidence: (len(LOSS_EVIDENCE),) what the calibrated confidence reads: 1 − the contour modality's
            agreement, 1 − motion_inliers (0 without motion rows), the largest occluded fraction and appearance
            distance over the cameras (0 when not measured), and the rotation (°/10) from the motion prediction
            to the final pose (0 without a prediction): the refinement had to overrule the motion cues
            (`LOSS_FRAME_EVIDENCE`); then the running average of these over the frames up to t+1
            (`TrackerState.loss_evidence_average` after this frame).
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
    appearance_distance: jax.Array
    loss_evidence: jax.Array


def _counts(corr: Correspondences, num_cameras: int, cue) -> jax.Array:
    live = (corr.weight > 0) & (corr.cue == cue)
    return jnp.sum(live[None, :] & (corr.camera[None, :] == jnp.arange(num_cameras)[:, None]), axis=1)


class _PredictionPass(eqx.Module):
    """The carry of the prediction's IRLS passes: the latest solution and the passes run."""

    T_world_root: jax.Array
    theta: jax.Array
    status: jax.Array
    passes: jax.Array


def _robust_prediction(ctx, model, fused: Correspondences, T_t, theta_t, params, ray_origins, steps: int):
    """The prediction solve (eq. 5 on the motion rows from the pose at t); with `params.motion_robust_px` > 0 a second
    pass from its result with the rows weighed by the Cauchy loss of their reprojection error there (IRLS), so that
    rows of an occluder that moved another way do not bias it. One traced solve (a `while_loop` over passes; under
    vmap over parameters every member runs the passes of the largest).

    Args:
        ctx: the step's context (its crop cameras and model; `fused` pixels are crop pixels); fused: (N rows) the
        motion rows with the prediction weights; T_t (4, 4), theta_t (J,): the pose at t; steps: Gauss-Newton steps
        per pass (static).

    Returns:
        `_PredictionPass`: the pose and status of the last usable pass (a second pass that fails keeps the first's;
        after an unusable first pass, whose pose is the pose at t, the second still runs from there and is kept when
        usable), and the passes run."""

    def solve(T, theta, corr):
        return solve_pose(model, corr, T, theta, SolverConfig(max_steps=steps), ray_origins=ray_origins,
                          depth_invariance=params.depth_invariant)

    def body(carry: _PredictionPass) -> _PredictionPass:
        first = carry.passes == 0
        scale = jnp.where(first, -1.0, params.motion_robust_px)
        err = reprojection_px(ctx, fused, Pose(carry.T_world_root, carry.theta))
        sol = solve(carry.T_world_root, carry.theta, fused.with_weight(fused.weight * cauchy_weights(err, scale)))
        keep = first | is_usable(sol.status)
        dtype = carry.T_world_root.dtype  # the carry keeps its dtype whatever the rows' (a while_loop requires it)
        return _PredictionPass(jnp.where(keep, sol.T_world_root, carry.T_world_root).astype(dtype),
                               jnp.where(keep, sol.theta, carry.theta).astype(dtype),
                               jnp.where(keep, sol.status, carry.status).astype(jnp.int32), carry.passes + 1)

    passes = jnp.where(params.motion_robust_px > 0, 2, 1)
    start = _PredictionPass(T_t, theta_t.astype(T_t.dtype), jnp.asarray(Status.OK, jnp.int32), jnp.zeros((), jnp.int32))
    return jax.lax.while_loop(lambda c: c.passes < passes, body, start)


def _motion_inliers(corr: Correspondences, cameras: Camera, model: KinematicModel, T, theta, inlier_px):
    """Fraction of weighted rows whose model point projects within `inlier_px` of its pixel at (T, Θ)."""
    err = reprojection_errors(corr, cameras, model, T, theta)
    live = corr.weight > 0
    return jnp.sum(live & (err <= inlier_px)) / jnp.maximum(jnp.sum(live), 1)


def crop_frames(arrays, offsets, crop_shape, scales=None, dtype=jnp.float32):
    """(C, H, W, ...) full-frame arrays → their (C, h, w, ...) windows: cut at `offsets` (scales None) or
    resampled at `offsets` / `scales` (`jaxtrack.image.sample_window`, the fixed working resolution)."""
    if scales is None:
        crop = jax.vmap(crop_window, in_axes=(0, 0, None))
        return tuple(crop(a, offsets, crop_shape).astype(dtype) for a in arrays)
    sample = jax.vmap(lambda a, o, s: sample_window(a, o, s, crop_shape, dtype=dtype))
    return tuple(sample(a, offsets, scales) for a in arrays)


def paste_frames(full, part, offsets, scales=None):
    """(C, h, w, ...) windows written back into (C, H, W, ...) full-frame arrays (the inverse of `crop_frames`)."""
    if scales is None:
        return jax.vmap(paste_window)(full, part, offsets)
    return jax.vmap(paste_window_scaled)(full, part, offsets, scales)


def frame_context(setup: TrackerSetup, state: TrackerState, frames, offsets, crop_shape, scales=None,
                  early: FrameStart | None = None) -> FrameContext:
    """The step's `FrameContext`: crops of frames t and t+1, r(x) of t on the crop, the render at χ_t
    (`scales`: (C,) full-frame pixels per crop pixel at the fixed working resolution, or None). With `early`
    (`start_frame`'s output for the same inputs) the crops and the render are taken from it, not made again."""
    dtype = state.T_world_root.dtype
    previous = state.images
    if early is not None:
        cams, crops, previous_crops, data_weight_crops = early.crop_cameras, early.crops, early.previous_crops, early.data_weight
    else:
        cams = crop_camera(setup.cameras, offsets, crop_shape, scales)
        if setup.config.uses_crop():  # cut (or resampled) from the frames as they are, then cast
            crops, previous_crops, data_weight_crops = crop_frames((frames, previous, state.data_weight), offsets,
                                                                   crop_shape, scales, dtype)
        else:  # whole frames (offsets 0, crop_shape = the frame): no copies
            crops, previous_crops, data_weight_crops = (a.astype(dtype) for a in (frames, previous, state.data_weight))
    ctx = FrameContext(
        mesh=setup.mesh, model=setup.model, cameras=setup.cameras, crop_cameras=cams, offsets=offsets,
        frames=frames, crops=crops, previous=previous, previous_crops=previous_crops,
        data_weight=data_weight_crops, render_t=None, pose_t=Pose(state.T_world_root, state.theta), plan=setup.window_plan,
        scales=scales, occluder_depth=state.occluder_depth,
    )
    if not any(m.needs_render_t for m in setup.config.modalities()):
        return ctx
    render_t = early.render_t if early is not None else render_crops(ctx, ctx.pose_t)
    return eqx.tree_at(lambda c: c.render_t, ctx, render_t, is_leaf=lambda x: x is None)


def modality_context(ctx, setup: TrackerSetup, index: int):
    """The context as modality `index` sees it: with its own prepared data."""
    prepared = setup.prepared_for(index)
    return ctx if prepared is None else eqx.tree_at(lambda c: c.prepared, ctx, prepared, is_leaf=lambda x: x is None)


def reads_host(modality: Modality) -> bool:
    """Whether a modality's `start` reads host inputs: its class overrides `Modality.host_inputs` (SIFT's matches).
    The others can start their frame on the device while the host makes those inputs (`start_frame`)."""
    return type(modality).host_inputs is not Modality.host_inputs


class FrameStart(eqx.Module):
    """What `start_frame` makes before the host inputs exist (the first part of step 1), for `track_step(early=)`.

    Attributes:
        crop_cameras: the C crop cameras; crops, previous_crops: (C, h, w, 3) frames t+1 and t in the crops;
        data_weight: (C, h, w) r(x) of frame t in the crops; render_t: the model at χ_t in the crops (None when no
        modality reads it); data: per configured modality its `start` output, None for those that read host inputs.
    """

    crop_cameras: Camera
    crops: jax.Array
    previous_crops: jax.Array
    data_weight: jax.Array
    render_t: object
    data: tuple


@eqx.debug.assert_max_traces(max_traces=None)  # counts traces (`eqx.debug.get_num_traces`), never fails
def start_frame(setup: TrackerSetup, state: TrackerState, frames, offsets, params: TrackerParams, crop_shape,
                scales=None) -> FrameStart:
    """Step 1 without the host: the crops, the render at χ_t and the `start` of every modality that reads no host
    inputs (the flow). Jittable. `Tracker.step` dispatches it before the host detects and matches SIFT keypoints,
    so the device computes the flow while the host detects; `track_step(..., early=)` then finishes the frame.
    Arguments as `track_step`'s."""
    ctx = frame_context(setup, state, frames, offsets, crop_shape, scales)
    data = tuple(None if reads_host(m) else m.start(modality_context(ctx, setup, i), s, None, params)
                 for i, (m, s) in enumerate(zip(setup.config.modalities(), state.modalities)))
    return FrameStart(ctx.crop_cameras, ctx.crops, ctx.previous_crops, ctx.data_weight, ctx.render_t, data)


def start_modalities(setup: TrackerSetup, state: TrackerState, frames, host, offsets, params: TrackerParams, crop_shape,
                     scales=None, early: FrameStart | None = None):
    """Step 1: the `FrameContext` and every modality's per-frame data: `start_frame` (unless `early` is its output,
    made in a program of its own), then the modalities that read host inputs. Returns (modalities, ctx, frame data)."""
    modalities = setup.config.modalities()
    early = start_frame(setup, state, frames, offsets, params, crop_shape, scales) if early is None else early
    ctx = frame_context(setup, state, frames, offsets, crop_shape, scales, early)
    data = tuple(m.start(modality_context(ctx, setup, i), s, h, params) if reads_host(m) else early.data[i]
                 for i, (m, s, h) in enumerate(zip(modalities, state.modalities, host)))
    return modalities, ctx, data


def motion_correspondences(setup: TrackerSetup, state: TrackerState, frames, host, offsets, params: TrackerParams, crop_shape,
                           scales=None):
    """The motion modalities' rows at t+1 (raw weights) from frames t, t+1 and the render at χ_t.

    Returns:
        (Correspondences of every motion modality (None without one), the crop render at χ_t, the crop cameras).
    """
    modalities, ctx, data = start_modalities(setup, state, frames.astype(state.T_world_root.dtype), host, offsets,
                                             params, crop_shape, scales)
    sets = [d for m, d in zip(modalities, data) if m.motion]
    corr = concatenate_correspondences(*sets) if sets else None
    return corr, ctx.render_t, ctx.crop_cameras


@eqx.debug.assert_max_traces(max_traces=None)  # counts traces (`eqx.debug.get_num_traces`), never fails
def track_step(
    setup: TrackerSetup,
    state: TrackerState,
    frames: jax.Array,
    host: tuple,
    offsets: jax.Array,
    params: TrackerParams,
    crop_shape: tuple[int, int],
    scales: jax.Array | None = None,
    early: FrameStart | None = None,
) -> tuple[TrackerState, FrameResult]:
    """One frame t → t+1 (Section V). Jittable and pure; vmap over `params` sweeps cue weights.

    Args:
        setup: mesh, model, stacked cameras (C), atlas, raster plan and config.
        state: the tracker state at t.
        frames: (C, H, W, 3) frames t+1 (0-255).
        host: one entry per configured modality: what its `host_inputs` made on the host (the SIFT
            matches t → t+1 in full-frame pixels), None for most (`Tracker.host_inputs`).
        offsets: (C, 2) (y0, x0) of each camera's crop, chosen on the host around the object at t.
        params: `TrackerParams`.
        crop_shape: (h, w) the static crop size (a size class, or the fixed working resolution; shared by the cameras).
        scales: (C,) full-frame pixels per crop pixel when the crops are resampled to the working
            resolution (`TrackerConfig.working_shape`); None: crops cut at the native resolution.
        early: `start_frame` of the same inputs (computed in its own program while the host made `host`), or None:
            the whole step here. The result is the same either way.

    Returns:
        (new `TrackerState` at t+1, `FrameResult`).
    """
    config, model = setup.config, setup.model
    dtype = state.T_world_root.dtype
    num_cams = offsets.shape[0]
    frames_in = frames  # kept in the state in their own dtype (uint8 from 8-bit video); modalities cast what they read
    T_t, theta_t = state.T_world_root, state.theta

    # 1. Every modality starts its frame.
    modalities, ctx, data = start_modalities(setup, state, frames, host, offsets, params, crop_shape, scales, early)
    contexts = tuple(modality_context(ctx, setup, i) for i in range(len(modalities)))
    motion_idx = [i for i, m in enumerate(modalities) if m.motion]

    # 2. Prediction from the motion modalities (n_C → n_OF in the weights); every modality sees it.
    if motion_idx:
        motion = [modalities[i] for i in motion_idx]
        fused = fuse_rows(motion, [data[i] for i in motion_idx], params, prediction=True)
        pred = _robust_prediction(ctx, model, fused, T_t, theta_t, params,
                                  setup.cameras.center_world if config.depth_invariance is not False else None,
                                  config.prediction_steps)
        use = is_usable(pred.status)
        predicted = use
        T_pred = jnp.where(use, pred.T_world_root, T_t)
        theta_pred = jnp.clip(jnp.where(use, pred.theta, theta_t), params.theta_lower, params.theta_upper)
    else:
        T_pred, theta_pred, predicted = T_t, theta_t, jnp.zeros((), bool)
    data = tuple(m.check_prediction(c, s, d, Pose(T_pred, theta_pred), params)
                 for m, c, s, d in zip(modalities, contexts, state.modalities, data))

    # 3. Refinement: rounds of {rows of every modality at the current pose → one fused solve}.
    refined = any(not m.motion for m in modalities)
    if refined:
        rounds, steps, min_rounds = config.loop_settings()
        settings = RefineSettings(params.region.settle_motion, params.region.joint_prior,
                                  params.pose_prior_rotation, params.pose_prior_translation, params.render_reuse_px,
                                  params.pose_prior_rotation_abs, params.pose_prior_translation_abs,
                                  params.prior_follows_round, params.depth_invariant, params.motion_robust_px,
                                  motion_rounds_for(state.last_confidence, params), params.motion_late_factor,
                                  depth_scaled=config.depth_invariance is not False)
        res = refine_rounds(modalities, ctx, state.modalities, data, Pose(T_pred, theta_pred.astype(dtype)), params, settings,
                            rounds, steps, min_rounds=min_rounds, contexts=contexts)
        T_new, theta_new = res.pose.T_world_root, jnp.clip(res.pose.theta, params.theta_lower, params.theta_upper)
        solve_status, iterations, fused, carries = res.status, res.rounds, res.rows, res.carries
    else:
        T_new, theta_new = T_pred, theta_pred
        solve_status = Status.OK if not motion_idx else first_failure(pred.status)
        solve_status = jnp.where(solve_status == Status.MAX_STEPS, Status.OK, solve_status)
        iterations = jnp.zeros((), jnp.int32)
        carries = tuple(None for _ in modalities)
        fused = fuse_rows(modalities, list(data), params, prediction=True) if motion_idx else None
    # A pose is never NaN: a failed step keeps the previous pose (and the modalities learn nothing from it).
    finite = jnp.all(jnp.isfinite(T_new)) & jnp.all(jnp.isfinite(theta_new))
    T_new = jnp.where(finite, T_new, T_t)
    theta_new = jnp.where(finite, theta_new, theta_t)
    final = Pose(T_new, theta_new)
    updated = tuple(m.update(c, s, d, r, final, params)
                    for m, c, s, d, r in zip(modalities, contexts, state.modalities, data, carries))
    modality_states = jax.tree.map(lambda new, old: jnp.where(finite, new, old), updated, tuple(state.modalities))

    # 4. Occlusion map of frame t+1 at the final pose; appearance update where not occluded (when some
    #    modality reads r(x) or the visible mask; the final render only when something reads it).
    cams = ctx.crop_cameras
    crops_t1 = ctx.crops
    occlusion = config.runs_occlusion()
    segmenting = any(m.contour and m.needs_render for m in modalities)
    ren_t1 = render_crops(ctx, final) if (occlusion or segmenting or motion_idx) else None
    # Evidence: each modality's, silhouette agreement, motion-cue agreement, visibility.
    evidence = {}
    for m, c, s, d, r in zip(modalities, contexts, state.modalities, data, carries):  # states of t: nothing learnt yet
        if refined or m.motion:
            evidence.update(m.evidence(c, s, d, r, final, ren_t1, params))
    has_segmentation = "segmentation" in evidence
    full = state.data_weight.shape[1:]
    if ren_t1 is None and not has_segmentation:
        # Nothing rendered or segmented (e.g. the line modality alone): no per-pixel maps to compute or carry.
        appearance, data_weight, visible = state.appearance, state.data_weight, state.visible
        phi = -jnp.ones((num_cams, 1, 1), dtype)
        iou = jnp.zeros((num_cams,), dtype)
        seen = evidence.get("seen", jnp.ones((num_cams,), bool))
        part_support = -jnp.ones((model.num_parts,), dtype)
        occluded_fraction = jnp.zeros((num_cams,), dtype)
        appearance_distance = -jnp.ones((num_cams,), dtype)
    else:
        sil_t1 = ren_t1.face_id >= 0 if ren_t1 is not None else jnp.zeros((num_cams,) + tuple(crop_shape), bool)
        if occlusion:
            obs = observe_texels(setup.atlas, crops_t1, ren_t1.depth, cams, T_new, params.occlusion, theta_new, model,
                                 config.occlusion_config)
            occ = detect_occlusion(setup.atlas, state.appearance, obs, ren_t1, params.occlusion, config.occlusion_config)
            appearance = update_appearance(state.appearance, obs, occ.occluded, params.occlusion, hold_new=occ.near_occlusion)
            occluded = occ.occluded
            known = occ.known
            n_known = jnp.sum(known, axis=(1, 2))
            appearance_distance = jnp.where(n_known > 0, jnp.sum(jnp.where(known, occ.distance, 0.0), axis=(1, 2))
                                            / jnp.maximum(n_known, 1), -1.0).astype(dtype)
        else:
            appearance = state.appearance
            occluded = jnp.zeros_like(sil_t1)
            appearance_distance = -jnp.ones((num_cams,), dtype)
        if occlusion or motion_idx:
            data_weight = paste_frames(jnp.ones((num_cams,) + full, dtype), jnp.where(occluded, 0.0, 1.0).astype(dtype),
                                       offsets, scales)
            visible = paste_frames(jnp.zeros((num_cams,) + full, bool), sil_t1 & ~occluded, offsets, scales)
        else:  # nothing reads them: carried unchanged (no full-frame writes)
            data_weight, visible = state.data_weight, state.visible
        phi = evidence["segmentation"] if has_segmentation else -jnp.ones((num_cams,) + tuple(crop_shape), dtype)
        seg = phi > 0
        inter = jnp.sum(seg & sil_t1, axis=(1, 2))
        union = jnp.sum(seg | sil_t1, axis=(1, 2))
        iou = jnp.where(union > 0, inter / jnp.maximum(union, 1), 0.0).astype(dtype)
        if ren_t1 is not None:
            seen = jnp.sum(sil_t1, axis=(1, 2)) > 0
        else:
            seen = evidence.get("seen", jnp.ones((num_cams,), bool))
        # Per part (limb): how much of its unoccluded silhouette the segmentation supports.
        own = sil_t1 & ~occluded
        part_ids = jnp.where(own, ren_t1.part_id, model.num_parts) if ren_t1 is not None else jnp.full(own.shape, model.num_parts)
        part_pixels = jnp.zeros(model.num_parts + 1, dtype).at[part_ids.ravel()].add(1.0)[:-1]
        part_inside = jnp.zeros(model.num_parts + 1, dtype).at[jnp.where(seg, part_ids, model.num_parts).ravel()].add(1.0)[:-1]
        part_support = jnp.where(part_pixels > 0, part_inside / jnp.maximum(part_pixels, 1.0), -1.0)
        if not has_segmentation:
            part_support = -jnp.ones_like(part_support)
        n_obj = jnp.maximum(jnp.sum(sil_t1, axis=(1, 2)), 1)
        occluded_fraction = (jnp.sum(occluded, axis=(1, 2)) / n_obj).astype(dtype)
    motion_rows = [data[i] for i in motion_idx]
    if motion_rows:
        motion = concatenate_correspondences(*motion_rows) if len(motion_rows) > 1 else motion_rows[0]
        inliers = _motion_inliers(motion, cams, model, T_new, theta_new, params.inlier_px).astype(dtype)
        motion_disagreement = jnp.where(jnp.any(motion.weight > 0), 1.0 - inliers, 0.0)  # no rows: no evidence
    else:
        inliers = jnp.ones((), dtype)
        motion_disagreement = jnp.zeros((), dtype)
    if has_segmentation:
        agreement = jnp.sum(jnp.where(seen, iou, 0.0)) / jnp.maximum(jnp.sum(seen), 1)
    elif "confidence" in evidence:
        agreement = jnp.asarray(evidence["confidence"], dtype)
    else:
        agreement = inliers
    agreement = jnp.clip(agreement, 0.0, 1.0)
    jump = jnp.where(predicted, rotation_error_deg(T_new[:3, :3], T_pred[:3, :3]) / 10.0, 0.0)  # no prediction: none
    frame_evidence = jnp.stack([
        1.0 - agreement, motion_disagreement, jnp.max(occluded_fraction), jnp.maximum(jnp.max(appearance_distance), 0.0),
        jump,
    ]).astype(dtype)
    previous = (jnp.zeros_like(frame_evidence) if state.loss_evidence_average is None
                else state.loss_evidence_average.astype(dtype))
    decay = params.loss_evidence_decay.astype(dtype)
    evidence_average = decay * previous + (1.0 - decay) * frame_evidence
    loss_evidence = jnp.concatenate([frame_evidence, evidence_average])
    if config.calibrated_confidence():
        w = jnp.atleast_2d(params.loss_weights.astype(dtype))  # (models, 1 + len(LOSS_EVIDENCE))
        if w.ndim != 2 or w.shape[1] != 1 + loss_evidence.shape[0]:
            raise ValueError(f"TrackerParams.loss_weights must be (K, {1 + loss_evidence.shape[0]}) or "
                             f"({1 + loss_evidence.shape[0]},): [intercept, one per LOSS_EVIDENCE] per model, got {w.shape}")
        # the least of the models' 1 − p(frame beyond 5 cm / 5°)
        confidence = jnp.min(jax.nn.sigmoid(-(w[:, 0] + w[:, 1:] @ loss_evidence)))
        quality = jnp.where(confidence < params.lost_confidence, Status.LOST,
                            jnp.where(confidence < params.uncertain_confidence, Status.UNCERTAIN, Status.OK))
    else:
        confidence = agreement
        quality = jnp.where(confidence < params.lost_iou, Status.LOST,
                            jnp.where(confidence < params.uncertain_iou, Status.UNCERTAIN, Status.OK))
    solve_ok = is_usable(solve_status)
    overflow = jnp.zeros((), bool)
    for r in (ctx.render_t, ren_t1):
        if r is not None:
            overflow = overflow | jnp.any(r.status == Status.RENDER_OVERFLOW)
    status = first_failure(
        status_where(~jnp.any(seen), Status.OUT_OF_VIEW, Status.OK),
        status_where(overflow, Status.RENDER_OVERFLOW, Status.OK),
        status_where(solve_ok, Status.OK, Status.LOST),
        quality,
    )
    status = first_failure(status_where(finite, Status.OK, Status.NONFINITE), status)

    counts = jnp.zeros((num_cams, len(modalities)), jnp.int32)
    if fused is not None:
        counts = jnp.stack([_counts(fused, num_cams, m.cue) for m in modalities], -1).astype(jnp.int32)
    new_state = TrackerState(T_new, theta_new, frames_in.astype(state.images.dtype), data_weight, visible, appearance,
                             modality_states, occluder_depth=state.occluder_depth,
                             loss_evidence_average=evidence_average, last_confidence=jnp.asarray(confidence, dtype))
    result = FrameResult(
        T_world_root=T_new, theta=theta_new, T_pred=T_pred, theta_pred=theta_pred, status=status.astype(jnp.int32),
        confidence=confidence, iou=iou, counts=counts, motion_inliers=inliers,
        occluded_fraction=occluded_fraction,
        iterations=jnp.asarray(iterations, jnp.int32), region_phi=phi, part_support=part_support.astype(dtype),
        appearance_distance=appearance_distance, loss_evidence=loss_evidence,
    )
    return new_state, result
