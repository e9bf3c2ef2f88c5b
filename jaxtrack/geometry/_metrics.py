"""Pose error metrics shared by the CLI, benchmarks, experiments and tests."""

from __future__ import annotations

import jax.numpy as jnp
from jax.typing import ArrayLike


def rotation_error_deg(R_a: ArrayLike, R_b: ArrayLike):
    """Angle (degrees) of the relative rotation R_a R_bᵀ, for (..., 3, 3) rotations (broadcast).

    θ = atan2(|vee(R − Rᵀ)| / 2, (tr R − 1) / 2) with R = R_a R_bᵀ: unlike arccos of the trace alone it
    keeps full precision near 0° (arccos loses √eps there, ~0.02° in float32) and never gives NaN.
    """
    R = jnp.einsum("...ij,...kj->...ik", jnp.asarray(R_a), jnp.asarray(R_b))
    cos = (jnp.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    skew = jnp.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    sin = jnp.linalg.norm(skew, axis=-1) / 2.0
    return jnp.degrees(jnp.arctan2(sin, cos))


def translation_error(t_a: ArrayLike, t_b: ArrayLike):
    """Euclidean distance |t_a − t_b| over the last axis (same units as the inputs, mm here)."""
    return jnp.linalg.norm(jnp.asarray(t_a) - jnp.asarray(t_b), axis=-1)
