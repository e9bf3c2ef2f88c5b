"""Kernel times of a compiled program attributed to the Python lines that made them (`jaxtrack.bench._profile`)."""

import inspect

import jax
import jax.numpy as jnp

from jaxtrack.bench import innermost_in, instruction_frames, profile_kernels
from jaxtrack.bench._profile import control_flow_instructions


def _heavy(x):
    return jax.lax.fori_loop(0, 60, lambda i, y: jnp.sin(y) * 1.0001 + jnp.cos(y), x)


def _light(x):
    return x + 1.0


def _both(x):
    return _light(_heavy(x))


def _inner(x):
    return jnp.tanh(x) * 3.0


def _middle(x):
    return _inner(x) + 0.5


def _outer(x):
    return _middle(x) - 1.0


def _line(fn, offset=1):
    return inspect.getsourcelines(fn)[1] + offset


def test_the_whole_python_stack_of_an_instruction_is_read_innermost_first():
    text = jax.jit(_outer).lower(jnp.ones(8)).compile().as_text()
    stacks = [s for s in instruction_frames(text).values() if s and s[0].function == "_inner"]
    assert stacks
    here = [(f.function, f.line) for f in stacks[0] if f.file.endswith("test_profile.py")]
    assert here[:3] == [("_inner", _line(_inner)), ("_middle", _line(_middle)), ("_outer", _line(_outer))]


def test_kernel_time_goes_to_the_line_that_made_the_kernel_and_loops_count_once():
    x = jnp.linspace(0.0, 1.0, 256 * 128).reshape(256, 128)
    f = jax.jit(_both)
    text = f.lower(x).compile().as_text()
    loops = control_flow_instructions(text)
    assert loops and all(name.startswith("while") for name in loops)
    jax.block_until_ready(f(x))
    profile = profile_kernels(lambda: [jax.block_until_ready(f(x)) for _ in range(4)], texts=[text])
    assert sum(profile.count.values()) >= 4 and len(profile.programs()) >= 1
    assert not any(op in loops for _, op in profile.ns)  # the loop's own event left out: its body counts
    by_function = profile.by_line(innermost_in("test_profile.py", exclude=()), line=False)
    total = sum(by_function.values())
    body = by_function["test_profile.py:_heavy.<locals>.<lambda>"]
    assert body > 0.7 * total  # 60 sweeps of sin and cos against one addition
    assert by_function["test_profile.py:_light"] < 0.2 * total
