"""The optical-flow modality (eq. 6-8): flow t → t+1 inside the object region, one row per grid pixel.

A motion modality: its rows are made once per frame in `start` (the flow of the crop of frames t and
t+1, restricted to the model silhouette at χ_t, with r(x) of frame t as the data weight) and enter both
the prediction and every refinement round. Their confidence is eq. 8's times the structure factor of frame t's
crop (`structure_confidence`, `TrackerParams.flow_structure`) where that is on, with no structure counted near the
limbs of the render at χ_t (`limb_pixels`, `TrackerParams.flow_limb_slope`). Weight rule of Section V: w_i = c_i · n_ref / n_OF, where
n_ref is n_C in the refinement and n_OF in the prediction, per px² of the image like the lines' rows
(`TrackerParams.rows_per_px`, `jaxtrack.solve.weights_per_pixel`).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ..._status import Status
from ...modality import FrameContext, FusionCounts, Modality, register_modality
from ...solve import Correspondences, Cue, weights_per_pixel
from ._api import FlowConfig
from ._correspondences import flow_correspondences
from ._solver import flow_core
from ._structure import limb_pixels, structure_confidence


def _flatten_cameras(corr: Correspondences) -> Correspondences:
    """A (C, N) stack of per-camera sets → one set of C·N rows."""
    return jax.tree.map(lambda a: a.reshape((-1,) + a.shape[2:]), corr)


@register_modality
class OpticalFlow(Modality):
    """Flow correspondences from frames t → t+1 (the paper's motion cue).

    Attributes:
        config: the flow minimiser's settings; stride: grid step of the rows (capacity (h/s)·(w/s) per camera).
    """

    name = "flow"
    cue = int(Cue.FLOW)
    motion = True
    prediction_reference = True
    needs_render_t = True
    uses_occlusion = True
    config: FlowConfig = eqx.field(static=True, default_factory=FlowConfig)
    stride: int = eqx.field(static=True, default=4)

    @classmethod
    def from_config(cls, config) -> OpticalFlow:
        return cls(config.flow, config.flow_stride)

    def start(self, ctx: FrameContext, state, host, params) -> Correspondences:
        """Flow of each crop (C vmapped) inside the silhouette at χ_t; rows in the crop cameras' pixels."""
        dtype = ctx.pose_t.T_world_root.dtype
        ren = ctx.render_t
        sil = ren.face_id >= 0
        flow = jax.vmap(lambda a, b, r, om: flow_core(a, b, params.flow, self.config, r, om, None, params.flow_beta, dtype))(
            ctx.previous_crops, ctx.crops, ctx.data_weight, sil)
        usable = sil & (ctx.data_weight > 0.5) & (flow.status == Status.OK)[:, None, None]
        k = jnp.asarray(params.flow_structure, dtype)
        max_slope = jnp.asarray(params.flow_limb_slope, dtype)
        # Limbs at χ_t (the render the rows sample), none where the parameter is off (not positive).
        limbs = jax.vmap(lambda d, m, cam: limb_pixels(d, m, cam.K[0, 0], max_slope) & (max_slope > 0))(
            ren.depth, sil, ctx.crop_cameras)
        pinned = jax.vmap(lambda im, lb: structure_confidence(im.astype(dtype), jnp.maximum(k, 0.0), limbs=lb))(
            ctx.previous_crops, limbs)
        confidence = flow.confidence * jnp.where(k < 0, 1.0, pinned)

        rows = jax.vmap(
            lambda cam, fl, conf, ok, pm, part, c: flow_correspondences(cam, fl, conf, ok, pm, part, None, self.stride, c)
        )(ctx.crop_cameras, flow.flow, confidence, usable, ren.p_model, ren.part_id,
          jnp.arange(ctx.num_cameras, dtype=jnp.int32))
        return weights_per_pixel(_flatten_cameras(rows), ctx.cameras, ctx.model, ctx.pose_t.T_world_root,
                                 ctx.pose_t.theta, params.rows_per_px)

    def rows(self, ctx, state, frame: Correspondences, carry, pose, render, round_index, params):
        return frame, carry

    def weight_scale(self, counts: FusionCounts, params, prediction: bool):
        own = counts.own
        return params.weights.flow * jnp.where(own > 0, counts.reference / jnp.maximum(own, 1.0), 0.0)
