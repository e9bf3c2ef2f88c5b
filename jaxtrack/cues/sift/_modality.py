"""The SIFT keypoint modality (Section III-D): matches t → t+1 moved to surface points at t.

A motion modality. Detection and matching run on the host between frames (OpenCV, one thread,
inside the visible object region of frame t: `host_inputs`); in the step the matches are filtered
(gross outliers, static background), assigned to the surface points (or closest visible vertices)
rendered at χ_t, and after the prediction checked by back-projection. Weight rule of Section V:
w = 0.002 · n_ref (n_C in the refinement, n_OF in the prediction), per px² of the image like the lines' rows
(`TrackerParams.rows_per_px`).
"""

from __future__ import annotations

import equinox as eqx

from ...modality import FrameContext, FusionCounts, Modality, Pose, register_modality
from ...solve import Correspondences, Cue, weights_per_pixel
from ._assign import _backprojection_body, sift_correspondences
from ._detect import SiftMatches, sift_matches
from ._filters import remove_gross_and_static


@register_modality
class SiftKeypoints(Modality):
    """SIFT correspondences t → t+1.

    Attributes:
        mode: "surface" (rendered surface point under the keypoint) or "vertex" (the paper's closest
            projected visible vertex).
    """

    name = "sift"
    cue = int(Cue.SIFT)
    motion = True
    needs_render_t = True
    uses_occlusion = True
    mode: str = eqx.field(static=True, default="surface")

    @classmethod
    def from_config(cls, config) -> SiftKeypoints:
        return cls(config.sift_mode)

    def host_inputs(self, tracker, state, frames, timings=None) -> SiftMatches:
        """OpenCV SIFT matches t → t+1 in full-frame pixels (C, N) inside the visible region of frame t."""
        cache = tracker.host_cache.setdefault(self.name, {})  # frame t's keypoints: detected last frame as t+1
        return sift_matches(tracker.previous_images(state), frames, tracker.visible_mask(state), tracker.sift,
                            timings=timings, dtype=tracker.dtype, cache=cache)

    def start(self, ctx: FrameContext, state, host: SiftMatches, params) -> Correspondences:
        kept = remove_gross_and_static(host, params.sift)  # thresholds in full-frame pixels
        local = SiftMatches(ctx.to_crop(kept.p_t), ctx.to_crop(kept.p_t1), kept.valid)  # → crop pixels
        rows = sift_correspondences(local, ctx.render_t, ctx.crop_cameras, params.sift, 1.0, self.mode, ctx.mesh,
                                    ctx.model, ctx.pose_t.T_world_root, ctx.pose_t.theta)
        return weights_per_pixel(rows, ctx.cameras, ctx.model, ctx.pose_t.T_world_root, ctx.pose_t.theta,
                                 params.rows_per_px)

    def check_prediction(self, ctx: FrameContext, state, frame: Correspondences, pose: Pose, params) -> Correspondences:
        """The back-projection check against the preliminary pose: rows farther than the bound lose their weight."""
        return _backprojection_body(frame, ctx.crop_cameras, ctx.model, pose.T_world_root, pose.theta, params.sift)

    def rows(self, ctx, state, frame: Correspondences, carry, pose, render, round_index, params):
        return frame, carry

    def weight_scale(self, counts: FusionCounts, params, prediction: bool):
        return params.weights.sift * params.weights.sift_ratio * counts.reference
