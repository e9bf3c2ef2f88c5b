"""The modality protocol: what a cue provides to the tracker's one refinement loop.

In the manner of M3T's Modality → Optimizer → Tracker split, a *modality* turns images and its own
state into padded 2D-3D correspondence rows for the current pose; the tracker (`jaxtrack.track`)
owns the loop that calls every configured modality, fuses their rows with each one's weight rule
(Section V of the paper) and solves once per round:

    frame  = m.start(ctx, state, host)                        # per frame: flow, keypoints, crops of densities
    pred   = solve(fuse(m.rows(...) for motion modalities, prediction=True))
    frame  = m.check_prediction(ctx, state, frame, pred)   # e.g. SIFT's back-projection check
    carry  = m.round_start(ctx, state, frame)
    repeat: rows = m.rows(ctx, state, frame, carry, pose, render, r)  → pose = solve(fuse(rows), priors)
    state  = m.update(ctx, state, frame, carry, pose)      # densities, histograms
    m.evidence(ctx, state, frame, carry, pose, render)     # what it says about the frame's confidence

Every method is jittable and pure; a modality is an `eqx.Module` whose fields are static settings
(or arrays of its own parameters); the shared numeric parameters arrive as `params` (the tracker's
`TrackerParams`, so sweeping them with vmap costs no recompilation). A new modality is one module
plus `register_modality` (see `_registry.py`); the fusion, the counts in `frames.jsonl`, the CLI's
`--cues` choices and the benchmarks iterate the registry.
"""

from __future__ import annotations

from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp

from ..geometry import Camera, KinematicModel
from ..image import full_to_window, window_to_full
from ..render import Mesh, RasterPlan, RenderOutput
from ..solve import Correspondences


class Pose(eqx.Module):
    """χ = (ξ, Θ): T_world_root (4, 4) model → world and theta (J,) joint angles."""

    T_world_root: jax.Array
    theta: jax.Array


class FrameContext(eqx.Module):
    """What every modality sees of one step t → t+1 (C cameras; crops of one static size class).

    Attributes:
        mesh, model, plan: the object and the rasteriser's plan.
        cameras: the full-frame rig (C stacked); crop_cameras: the same cameras seeing only their crop
            (principal point shifted by `offsets`, `crop_camera`).
        offsets: (C, 2) (y0, x0) of each crop in its full frame.
        frames: (C, H, W, 3) frames t+1 (0-255) as given (uint8 from 8-bit video, else float; cast what you
            read); crops: (C, h, w, 3) their crops (float).
        scales: (C,) full-frame pixels per crop pixel (the fixed working resolution,
            `TrackerConfig.working_shape`), or None: 1 (crops cut at the native resolution). Window pixel
            (x, y) is full-frame pixel offset + s·(x + ½) − ½ (`jaxtrack.image.window_to_full`).
        previous: (C, H, W, 3) frames t (as given); previous_crops: (C, h, w, 3) (float).
        data_weight: (C, h, w) r(x) of frame t on the crop (0 = occluded; the flow cue's data weight).
        render_t: `RenderOutput` with a leading C axis: the model at χ_t in the crops (shared by the
            motion modalities).
        pose_t: the pose at t.
        prepared: what this modality's `prepare` made once per tracker (e.g. a sparse viewpoint model);
            the tracker hands each modality its own.
        occluder_depth: (C, H, W) full-frame depth (mm) of the other objects of a joint run (`JointTracker`)
            at their latest poses, min-filtered over a few pixels, inf where none; None when tracking one object.
    """

    mesh: Mesh
    model: KinematicModel
    cameras: Camera
    crop_cameras: Camera
    offsets: jax.Array
    frames: jax.Array
    crops: jax.Array
    previous: jax.Array
    previous_crops: jax.Array
    data_weight: jax.Array
    render_t: RenderOutput
    pose_t: Pose
    plan: RasterPlan = eqx.field(static=True)
    prepared: Any = None
    scales: jax.Array | None = None
    occluder_depth: jax.Array | None = None

    @property
    def num_cameras(self) -> int:
        return self.offsets.shape[0]

    def to_crop(self, points_full):
        """(C, ..., 2) full-frame pixels (x, y) of each camera → its crop's pixels."""
        return _to_crop(points_full, self.offsets, self.scales)

    def to_full(self, points_crop):
        """(C, ..., 2) crop pixels (x, y) of each camera → full-frame pixels."""
        return _to_full(points_crop, self.offsets, self.scales)

    @property
    def crop_shape(self) -> tuple[int, int]:
        return tuple(self.crops.shape[1:3])


class StartContext(eqx.Module):
    """What a modality sees at the first frame, whose pose is known (`Modality.init_state`).

    Attributes: as `FrameContext` (frames and crops of the first frame, render at the known pose,
    this modality's prepared data, the other objects' depth of a joint run).
    """

    mesh: Mesh
    model: KinematicModel
    cameras: Camera
    crop_cameras: Camera
    offsets: jax.Array
    frames: jax.Array
    crops: jax.Array
    render: RenderOutput
    pose: Pose
    plan: RasterPlan = eqx.field(static=True)
    prepared: Any = None
    scales: jax.Array | None = None
    occluder_depth: jax.Array | None = None


def _per_camera(points, offsets, scales):
    """(C, 1.., 2) offsets and (C, 1..) scales (ones for None) broadcast against (C, ..., 2) points."""
    C, mid = offsets.shape[0], (1,) * (points.ndim - 2)
    s = jnp.ones((C,), points.dtype) if scales is None else jnp.asarray(scales, points.dtype)
    return offsets.astype(points.dtype).reshape((C,) + mid + (2,)), s.reshape((C,) + mid)


def _to_crop(points, offsets, scales):
    return full_to_window(points, *_per_camera(points, offsets, scales))


def _to_full(points, offsets, scales):
    return window_to_full(points, *_per_camera(points, offsets, scales))


class FusionCounts(eqx.Module):
    """Row counts the Section V weight rules read.

    Attributes:
        reference: n_C (live rows of the contour modalities) in the refinement, n_OF (live rows of the
            modalities that are the prediction's reference, flow) in the prediction.
        own: live rows of the modality whose weights are being set.
    """

    reference: jax.Array
    own: jax.Array


class Modality(eqx.Module):
    """Interface of a cue in the tracker's refinement loop (override what applies; defaults do nothing).

    Class attributes (set by each modality class):
        name: registry key and `--cues` choice ("region", "flow", "sift", ...).
        cue: int tag written into every row's `Correspondences.cue` (`jaxtrack.solve.Cue` for the
            built-ins; `register_modality` hands out new tags).
        contour: its live rows are the n_C of Section V (the region modalities).
        motion: its rows are fixed for the frame (made in `start`) and enter the prediction solve.
        prediction_reference: its live rows are n_OF, the prediction's reference count (flow).
        needs_render: `rows` wants the model rendered at the current pose in every crop (one render per
            camera per round, shared by all modalities that ask).
        needs_render_t: `start` reads `FrameContext.render_t` (the model at χ_t in the crops).
        uses_crop: the modality reads the crops; when none does, the step works on whole frames and
            one program serves every object size (no crop size classes).
        uses_occlusion: the modality reads r(x) or the visible mask of the occlusion detection; without
            one, the detection is skipped.
    """

    name: ClassVar[str] = ""
    cue: ClassVar[int] = 0
    contour: ClassVar[bool] = False
    motion: ClassVar[bool] = False
    prediction_reference: ClassVar[bool] = False
    needs_render: ClassVar[bool] = False
    needs_render_t: ClassVar[bool] = False
    uses_crop: ClassVar[bool] = True
    uses_occlusion: ClassVar[bool] = False

    # --- per tracker ----------------------------------------------------------------------------
    def prepare(self, mesh, model, cameras) -> Any:
        """Host-side set-up once per tracker (e.g. a sparse viewpoint model, cached on disk): a pytree of
        arrays handed back as `ctx.prepared`, an input of the compiled step (never copied per frame)."""
        return None

    def loop_preferences(self) -> tuple[int, int, int]:
        """(rounds, Gauss-Newton steps per round, minimum rounds before the pose may settle) this modality
        wants from the refinement loop; 0 = no preference. The loop takes the largest of each."""
        return 0, 0, 0

    # --- per sequence -------------------------------------------------------------------------
    def init_state(self, ctx: StartContext, params) -> Any:
        """The modality's state at the first frame (known pose): e.g. densities, histograms. Jittable."""
        return None

    # --- per frame ------------------------------------------------------------------------------
    def host_inputs(self, tracker, state, frames, timings: dict | None = None) -> Any:
        """Host-side per-frame input (numpy and OpenCV allowed; e.g. SIFT matches), handed to `start`.

        Runs between frames, outside the compiled step. Must return a pytree of arrays of a static
        shape (padded), or None. Default None. A modality that overrides it starts its frame after the host
        inputs exist; the others' `start` may run on the device meanwhile (`jaxtrack.track.start_frame`).
        """
        return None

    def start(self, ctx: FrameContext, state, host, params) -> Any:
        """Per-frame work before the prediction (flow, keypoint rows, densities cropped). Jittable.

        `host` is what `host_inputs` returned for this frame.
        """
        return None

    def check_prediction(self, ctx: FrameContext, state, frame, pose: Pose, params) -> Any:
        """Update the frame data once the prediction `pose` is known (default: unchanged); called for every
        modality (the prediction is χ_t without motion modalities)."""
        return frame

    def round_start(self, ctx: FrameContext, state, frame, params) -> Any:
        """The carry of the refinement rounds (e.g. the last segmentation; default None)."""
        return None

    def rows(self, ctx: FrameContext, state, frame, carry, pose: Pose, render: RenderOutput | None, round_index,
             params) -> tuple[Correspondences, Any]:
        """Padded rows (raw weights, `cue` tag set) at `pose`, and the new carry. Jittable.

        `render` is the model at `pose` in the crops (C leading) when any configured modality
        `needs_render`, else None. Motion modalities return their fixed rows (from `start`).
        """
        raise NotImplementedError(f"modality {self.name!r} defines no rows")

    def update(self, ctx: FrameContext, state, frame, carry, pose: Pose, params) -> Any:
        """The state carried to the next frame, at the final pose (default: unchanged)."""
        return state

    def evidence(self, ctx: FrameContext, state, frame, carry, pose: Pose, render: RenderOutput, params) -> dict:
        """Named arrays about the frame at the final pose (`render` is the model there, C leading).

        Keys the tracker reads where present: "silhouette_iou" (C,) agreement of the modality's own
        segmentation with the model silhouette, "segmentation" (C, h, w) signed (> 0 object),
        "part_support" (P,); any other key is reported as is.
        """
        return {}

    def weight_scale(self, counts: FusionCounts, params, prediction: bool) -> jax.Array:
        """Factor on this modality's raw row weights (Section V rule × user factor; default 1)."""
        return jnp.ones((), counts.own.dtype)
