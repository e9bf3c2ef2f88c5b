"""Pose error metrics shared by the CLI, benchmarks, experiments and tests."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike


def _array_module(*arrays):
    """numpy for host values (no eager XLA program per operation; in the inputs' own precision, float64 for Python
    floats and float64 arrays where JAX without x64 measured in float32), jax.numpy when any is a JAX array."""
    return jnp if any(isinstance(a, jax.Array) for a in arrays) else np


def rotation_error_deg(R_a: ArrayLike, R_b: ArrayLike):
    """Angle (degrees) of the relative rotation R_a R_bᵀ, for (..., 3, 3) rotations (broadcast).

    θ = atan2(|vee(R − Rᵀ)| / 2, (tr R − 1) / 2) with R = R_a R_bᵀ: unlike arccos of the trace alone it
    keeps full precision near 0° (arccos loses √eps there, ~0.02° in float32) and never gives NaN. Host inputs
    (numpy, lists) are measured in numpy; JAX arrays and tracers in jax.numpy (jittable).
    """
    xp = _array_module(R_a, R_b)
    R = xp.einsum("...ij,...kj->...ik", xp.asarray(R_a), xp.asarray(R_b))
    cos = (xp.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    skew = xp.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    sin = xp.linalg.norm(skew, axis=-1) / 2.0
    return xp.degrees(xp.arctan2(sin, cos))


def translation_error(t_a: ArrayLike, t_b: ArrayLike):
    """Euclidean distance |t_a − t_b| over the last axis (same units as the inputs, mm here)."""
    xp = _array_module(t_a, t_b)
    return xp.linalg.norm(xp.asarray(t_a) - xp.asarray(t_b), axis=-1)
