"""Outlier removal of SIFT matches (Section III-D), jittable on padded `SiftMatches`.

Three filters, each a pure function of padded arrays, per camera (the motion of one camera's image
says nothing about another's):
- gross mismatches: a displacement far longer than the mean displacement is dropped
  (|d_i| > factor · mean |d| + slack, repeated so that the outliers' own share of the mean goes);
- static background: when the mean displacement is large, matches that stay in place belong to the
  background seen through or beside the object and are dropped;
- back-projection (in `_assign.py`): after a preliminary pose, matches whose model point projects far
  from the matched pixel are dropped.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ..._device import to_device
from ._detect import SiftMatches


class SiftParams(eqx.Module):
    """Filter thresholds as arrays (sweepable under vmap, no recompilation).

    Attributes:
        gross_factor: a displacement longer than gross_factor · mean + gross_slack_px is a mismatch.
        gross_slack_px: slack (pixels) so that a near-still object keeps its sub-pixel matches.
        large_motion_px: mean displacement above which still matches are background.
        static_px: a match moving less than this is still.
        backprojection_px: largest distance between the projected model point (preliminary pose)
            and the matched pixel.
        max_vertex_px: vertex assignment only: largest distance of the keypoint to its vertex.
        boundary_px: surface assignment only: a keypoint makes a row only where the render at χ_t shows its part at
            every pixel within this distance (Chebyshev, pixels of the render, at most `BOUNDARY_MAX_PX`): no other
            part and no background. A keypoint that close to a part's outline belongs to it only if the pose at t is
            right to about that distance, and its descriptor spans both sides. 0 = every keypoint on the object.
    """

    gross_factor: jax.Array
    gross_slack_px: jax.Array
    large_motion_px: jax.Array
    static_px: jax.Array
    backprojection_px: jax.Array
    max_vertex_px: jax.Array
    boundary_px: jax.Array


BOUNDARY_MAX_PX = 4  # the largest `SiftParams.boundary_px` (the window the assignment reads is static)


def sift_params(
    gross_factor=3.0,
    gross_slack_px=2.0,
    large_motion_px=3.0,
    static_px=1.0,
    backprojection_px=2.0,
    max_vertex_px=15.0,
    boundary_px=0.0,
    dtype=jnp.float32,
) -> SiftParams:
    """`SiftParams` with defaults; raises ValueError naming a non-positive parameter (`boundary_px`: outside
    [0, `BOUNDARY_MAX_PX`])."""
    values = {
        "gross_factor": gross_factor,
        "gross_slack_px": gross_slack_px,
        "large_motion_px": large_motion_px,
        "static_px": static_px,
        "backprojection_px": backprojection_px,
        "max_vertex_px": max_vertex_px,
    }
    for name, value in values.items():
        if not float(value) > 0:
            raise ValueError(f"sift_params: {name} must be > 0, got {value}")
    if not 0.0 <= float(boundary_px) <= BOUNDARY_MAX_PX:
        raise ValueError(f"sift_params: boundary_px must be in [0, {BOUNDARY_MAX_PX}], got {boundary_px}")
    values["boundary_px"] = boundary_px
    return SiftParams(**{k: to_device(v, dtype) for k, v in values.items()})


def _mean_length(length, valid):
    return jnp.sum(jnp.where(valid, length, 0.0), -1) / jnp.maximum(jnp.sum(valid, -1), 1)


def _filter_one(p_t, p_t1, valid, params, rounds: int):
    length = jnp.linalg.norm(p_t1 - p_t, axis=-1)

    def gross_round(_, keep):
        bound = params.gross_factor * _mean_length(length, keep) + params.gross_slack_px
        return keep & (length <= bound)

    keep = jax.lax.fori_loop(0, rounds, gross_round, valid)
    moving = _mean_length(length, keep) > params.large_motion_px
    return keep & ~(moving & (length < params.static_px))


@eqx.debug.assert_max_traces(max_traces=None)  # counts traces (eqx.debug.get_num_traces); never fails
def _filter_body(matches: SiftMatches, params: SiftParams, rounds: int = 2) -> SiftMatches:
    """Drop gross mismatches (`rounds` passes, static) and, when the mean motion is large, still
    matches; per camera. Jittable."""
    keep = jax.vmap(lambda a, b, v: _filter_one(a, b, v, params, rounds))(matches.p_t, matches.p_t1, matches.valid)
    return eqx.tree_at(lambda m: m.valid, matches, keep)


remove_gross_and_static = eqx.filter_jit(_filter_body)
