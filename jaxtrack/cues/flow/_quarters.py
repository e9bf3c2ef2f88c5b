"""The red-black (parity) layout used by the SOR solver.

A per-pixel field of shape (H, W, ...) with H, W even is stored as (4, H/2, W/2, ...): the four parity
sub-grids A = (even row, even column), B = (even, odd), C = (odd, even), D = (odd, odd). Red = A ∪ D,
black = B ∪ C, so all four neighbours of a red pixel are black and vice versa, and a red-black
half-sweep touches only the pixels it updates (no masked selects, half the arithmetic).

The `q_*` shifts give, at every pixel, the value of its right/left/lower/upper neighbour in the same
layout, with zero beyond the border.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def to_quarters(a: jax.Array) -> jax.Array:
    """(H, W, ...) with H, W even → (4, H/2, W/2, ...) in the order A, B, C, D."""
    h, w = a.shape[:2]
    rest = a.shape[2:]
    q = a.reshape(h // 2, 2, w // 2, 2, *rest)
    q = jnp.moveaxis(q, (1, 3), (0, 1))
    return q.reshape(4, h // 2, w // 2, *rest)


def from_quarters(q: jax.Array) -> jax.Array:
    """Inverse of `to_quarters`: (4, h, w, ...) → (2h, 2w, ...)."""
    h2, w2 = q.shape[1:3]
    rest = q.shape[3:]
    a = q.reshape(2, 2, h2, w2, *rest)
    a = jnp.moveaxis(a, (0, 1), (1, 3))
    return a.reshape(2 * h2, 2 * w2, *rest)


# Shifts within one (h, w) sub-grid, zero fill: the next/previous column (k) or row (i).
def kp(a: jax.Array) -> jax.Array:
    return jnp.pad(a[:, 1:], ((0, 0), (0, 1)))


def km(a: jax.Array) -> jax.Array:
    return jnp.pad(a[:, :-1], ((0, 0), (1, 0)))


def ip(a: jax.Array) -> jax.Array:
    return jnp.pad(a[1:], ((0, 1), (0, 0)))


def im(a: jax.Array) -> jax.Array:
    return jnp.pad(a[:-1], ((1, 0), (0, 0)))


def q_right(x: jax.Array) -> jax.Array:
    """Value at p + (0, 1) for every p, on (4, h, w) fields."""
    return jnp.stack([x[1], kp(x[0]), x[3], kp(x[2])])


def q_left(x: jax.Array) -> jax.Array:
    """Value at p − (0, 1)."""
    return jnp.stack([km(x[1]), x[0], km(x[3]), x[2]])


def q_down(x: jax.Array) -> jax.Array:
    """Value at p + (1, 0)."""
    return jnp.stack([x[2], x[3], ip(x[0]), ip(x[1])])


def q_up(x: jax.Array) -> jax.Array:
    """Value at p − (1, 0)."""
    return jnp.stack([im(x[2]), im(x[3]), x[0], x[1]])
