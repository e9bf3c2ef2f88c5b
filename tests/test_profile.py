"""Kernel times of a compiled program attributed to the Python lines that made them (`jaxtrack.bench._profile`)."""

import inspect

import jax
import jax.numpy as jnp

from jaxtrack.bench import innermost_in, instruction_frames, profile_kernels


def _heavy(x):
    return jax.lax.fori_loop(0, 60, lambda i, y: jnp.sin(y) * 1.0001 + jnp.cos(y), x)


def _light(x):
    return x + 1.0


def _both(x):
    return _light(_heavy(x))


HEAVY_LINE = inspect.getsourcelines(_heavy)[1] + 1
LIGHT_LINE = inspect.getsourcelines(_light)[1] + 1


def test_kernel_time_goes_to_the_line_that_made_the_kernel():
    x = jnp.linspace(0.0, 1.0, 256 * 128).reshape(256, 128)
    f = jax.jit(_both)
    text = f.lower(x).compile().as_text()
    here = innermost_in("test_profile.py", exclude=())
    lines = {here(stack).line for stack in instruction_frames(text).values() if here(stack) is not None}
    assert HEAVY_LINE in lines  # the optimised program names the lines that made its instructions
    jax.block_until_ready(f(x))
    profile = profile_kernels(lambda: [jax.block_until_ready(f(x)) for _ in range(4)], texts=[text])
    assert sum(profile.count.values()) >= 4 and len(profile.programs()) >= 1
    by_line = profile.by_line(here)
    top, top_ns = by_line.most_common(1)[0]
    assert top.endswith(f":{HEAVY_LINE}") and top_ns > 0.5 * sum(by_line.values())
    by_function = profile.by_line(here, line=False)
    assert max(by_function, key=by_function.get).endswith(":_heavy.<locals>.<lambda>")  # the loop's body, not `_light`
    assert not any(k.endswith(f":{LIGHT_LINE}") and v > top_ns for k, v in by_line.items())
