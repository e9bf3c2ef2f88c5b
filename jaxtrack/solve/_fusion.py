"""Adaptive cue weights of the method's Section V, applied to one fused correspondence set.

Every cue hands over rows with a raw per-row weight: 1 for contour (region) and SIFT rows, the flow
confidence c_i of eq. 8 for flow rows. With n_C contour rows and n_OF flow rows in the set,

    contour  w = 1,    SIFT  w = 0.002 · n_C,    flow  w_i = c_i · n_C / n_OF,

so the flow and SIFT cues weigh in proportion to the contour evidence whatever their own counts. In
the prediction step there is no contour yet and n_C is replaced by n_OF (flow w_i = c_i, SIFT
w = 0.002 · n_OF). Every weight is further multiplied by a user factor (an array, default 1): sweeping
or differentiating the factors costs no recompilation.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from .._device import to_device
from ._correspondences import Correspondences, Cue


class CueWeights(eqx.Module):
    """User factors on the Section V weights, one per cue (arrays: vmap and grad work over them).

    Attributes:
        region: factor on contour correspondences (w_C = 1 · region).
        flow: factor on flow correspondences.
        sift: factor on SIFT correspondences.
        sift_ratio: the method's 0.002 (SIFT weight per contour correspondence).
    """

    region: jax.Array = eqx.field(default_factory=lambda: to_device(1.0), converter=to_device)
    flow: jax.Array = eqx.field(default_factory=lambda: to_device(1.0), converter=to_device)
    sift: jax.Array = eqx.field(default_factory=lambda: to_device(1.0), converter=to_device)
    sift_ratio: jax.Array = eqx.field(default_factory=lambda: to_device(0.002), converter=to_device)


def fuse_cue_weights(corr: Correspondences, factors: CueWeights, prediction: bool = False) -> Correspondences:
    """Scale the raw per-row weights of a fused set by the Section V rule (jittable, differentiable).

    Args:
        corr: concatenated correspondences of all cues; `corr.cue` says which cue produced each row and
            `corr.weight` holds the raw weight (1 for REGION and SIFT rows, c_i for FLOW rows, 0 padding).
            Rows of other cues (UNKNOWN) keep their weight times 1.
        factors: user factors per cue.
        prediction: True in the prediction step (no contour yet: n_C is replaced by n_OF). Static.

    Returns:
        The same set with fused weights. With no flow rows the flow term is empty; with no contour
        (and not in prediction) SIFT and flow rows get weight 0, as the rule says.
    """
    dtype = corr.weight.dtype
    live = corr.weight > 0
    n_contour = jnp.sum(live & (corr.cue == Cue.REGION)).astype(dtype)
    n_flow = jnp.sum(live & (corr.cue == Cue.FLOW)).astype(dtype)
    n_ref = n_flow if prediction else n_contour
    flow_scale = jnp.where(n_flow > 0, n_ref / jnp.maximum(n_flow, 1.0), 0.0)
    scale = jnp.select(
        [corr.cue == Cue.REGION, corr.cue == Cue.FLOW, corr.cue == Cue.SIFT],
        [factors.region.astype(dtype), factors.flow.astype(dtype) * flow_scale,
         factors.sift.astype(dtype) * factors.sift_ratio.astype(dtype) * n_ref],
        jnp.ones((), dtype),
    )
    return corr.with_weight(corr.weight * scale)
