"""Static-size windows at traced offsets: a crop class compiles once, wherever the object moves."""

from __future__ import annotations

import jax
import jax.numpy as jnp


def crop_window(image: jax.Array, offset: jax.Array, shape: tuple[int, int]) -> jax.Array:
    """image[y0 : y0 + h, x0 : x0 + w] for (H, W, ...) `image`, traced `offset` = (y0, x0), static `shape`.

    Like `lax.dynamic_slice`, a window reaching past the border is shifted back inside the image.
    """
    zero = jnp.zeros((), jnp.int32)
    start = (jnp.asarray(offset[0], jnp.int32), jnp.asarray(offset[1], jnp.int32)) + (zero,) * (image.ndim - 2)
    return jax.lax.dynamic_slice(image, start, tuple(shape) + image.shape[2:])


def paste_window(full: jax.Array, part: jax.Array, offset: jax.Array) -> jax.Array:
    """`full` with `part` written at traced `offset` = (y0, x0) (the inverse of `crop_window`)."""
    zero = jnp.zeros((), jnp.int32)
    start = (jnp.asarray(offset[0], jnp.int32), jnp.asarray(offset[1], jnp.int32)) + (zero,) * (part.ndim - 2)
    return jax.lax.dynamic_update_slice(full, part.astype(full.dtype), start)
