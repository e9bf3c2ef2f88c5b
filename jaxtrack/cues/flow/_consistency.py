"""Forward-backward consistency of a flow pair (occlusion / mismatch check).

Following Sundaram, Brox and Keutzer (ECCV 2010): a pixel is consistent when the backward flow at its
forward target undoes the forward flow, |w_f + w_b(x + w_f)|² < a1 (|w_f|² + |w_b(x + w_f)|²) + a2.
Pixels that become occluded in frame 2 fail the test, which makes it a check of the occlusion
weights r(x) of eq. 6.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

from ...image import warp_bilinear


def forward_backward_consistency(
    flow_fw: jax.Array, flow_bw: jax.Array, a1: ArrayLike = 0.01, a2: ArrayLike = 0.5
) -> jax.Array:
    """Consistency mask (H, W) bool of a forward flow (H, W, 2) against the backward flow (H, W, 2).

    Args:
        flow_fw: flow from frame 1 to frame 2.
        flow_bw: flow from frame 2 to frame 1.
        a1, a2: relative and absolute tolerance (Sundaram et al.: 0.01 and 0.5 px²).

    Returns:
        True where the round trip closes within tolerance and x + w_f lies inside frame 2.
    """
    bw_at_target, inside = warp_bilinear(flow_bw, flow_fw)
    loop = flow_fw + bw_at_target
    lhs = jnp.sum(loop * loop, -1)
    rhs = a1 * (jnp.sum(flow_fw * flow_fw, -1) + jnp.sum(bw_at_target * bw_at_target, -1)) + a2
    return (lhs < rhs) & inside
