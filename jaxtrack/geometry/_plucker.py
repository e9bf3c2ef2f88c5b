"""Plücker lines (eq. 3) and the point-line residual of the pose solver (eq. 4).

A line through point p with unit direction n is L = (n, m), m = p × n. For any point X,
X × n − m is a vector orthogonal to n whose norm is the distance of X from L (eq. 4).
"""

from __future__ import annotations

import jax.numpy as jnp
from jax.typing import ArrayLike


def plucker_from_ray(origin: ArrayLike, direction: ArrayLike):
    """(n, m) of rays. origin, direction (..., 3); direction is normalised here."""
    n = direction / jnp.linalg.norm(direction, axis=-1, keepdims=True)
    return n, jnp.cross(origin, n)


def point_line_residual(points: ArrayLike, n: ArrayLike, m: ArrayLike):
    """r = X × n − m (eq. 4), (..., 3); |r| is the point-line distance."""
    return jnp.cross(points, n) - m


def point_line_distance(points: ArrayLike, n: ArrayLike, m: ArrayLike):
    """Euclidean distance of points (..., 3) from lines (n, m)."""
    return jnp.linalg.norm(point_line_residual(points, n, m), axis=-1)
