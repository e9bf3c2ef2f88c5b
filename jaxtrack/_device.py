"""Host values onto the device without compiling anything."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def to_device(x, dtype=None) -> jax.Array:
    """`x` (numpy array, Python scalar or nested sequence) as a device array of `dtype`, cast on the host.

    `jax.device_put` compiles nothing, where `jnp.asarray` / `jnp.array` of a host value compile a small copy
    program ("stage", and a cast when the dtype changes) for each new shape and dtype in every fresh process:
    10-30 ms each on a 2-core CPU, about 70 of them in a tracker's first frame before this helper. A Python
    scalar without `dtype` keeps JAX's weak type, as `jnp.asarray` gives it; a JAX array (or a tracer) without
    `dtype` is returned as it is; with `dtype` the result is strongly typed, as `jnp.asarray(x, dtype)` gives it
    (weakly typed arguments send `persistent_jit` to the plain path: no kept program).
    """
    if isinstance(x, jax.core.Tracer):
        return x if dtype is None else x.astype(dtype)
    if isinstance(x, jax.Array):
        if dtype is None or (x.dtype == np.dtype(dtype) and not x.weak_type):
            return x
        return jax.device_put(np.asarray(x, dtype))  # a dtype asked for: strongly typed, as jnp.asarray(x, dtype)
    if dtype is None and isinstance(x, (bool, int, float, complex)):
        return jax.device_put(x)
    if isinstance(x, (list, tuple)) and any(isinstance(v, jax.Array) for v in jax.tree.leaves(x)):
        return jnp.asarray(x, dtype)  # a sequence of device arrays or tracers: stacked by JAX
    return jax.device_put(np.asarray(x, dtype))
