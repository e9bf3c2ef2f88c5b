"""A lean damped Gauss-Newton on a manifold, for few unknowns (6 + J) and many residuals.

The normal equations H δ = −g with H = JᵀWJ of size (6+J)² are the cheap route for the pose
problem (eq. 5); Marquardt damping H + λ diag(H) handles rank deficiency (an unobserved joint, few
points). Optimistix's LevenbergMarquardt solves the same problem through QR on the full Jacobian,
which under vmap on a CPU is many times slower; it stays available as
`SolverConfig(backend="optimistix")` and the tests check both agree.

Derivatives of the solution come from the implicit function theorem on the optimality condition
∇_y ½|f(y, args)|² = 0 (a `jax.custom_jvp`, `solve_implicit`), not from unrolling the iterations.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp


class GaussNewtonState(eqx.Module):
    """Loop state of `damped_gauss_newton` (named, in the manner of optimistix's `_GaussNewtonState`).

    Attributes:
        x: current iterate (any pytree), the last accepted one.
        hessian: (D, D) H = JᵀWJ linearised at x (eq. 5).
        gradient: (D,) g = JᵀW s at x.
        cost: Σ w |s|² at x.
        damping: Marquardt factor λ.
        num_steps: int32 steps taken (accepted or rejected).
        done: bool, a stopping test fired (or the start was non-finite).
        fresh: bool, x is the start and not yet linearised (the loop's first pass does it, taking no step).
    """

    x: Any
    hessian: jax.Array
    gradient: jax.Array
    cost: jax.Array
    damping: jax.Array
    num_steps: jax.Array
    done: jax.Array
    fresh: jax.Array


class GaussNewtonResult(eqx.Module):
    """Outcome of `damped_gauss_newton`.

    Attributes:
        x: the final iterate (the last accepted one).
        hessian: (D, D) H at x, for conditioning checks by the caller.
        converged: bool, a stopping test fired on a finite iterate.
        num_steps: int32 steps taken.
        nonfinite: bool, the cost or the iterate is not finite.
    """

    x: Any
    hessian: jax.Array
    converged: jax.Array
    num_steps: jax.Array
    nonfinite: jax.Array


def _select(pred, new, old):
    return jax.tree_util.tree_map(lambda u, v: jnp.where(pred, u, v), new, old)


def damped_gauss_newton(
    normal_equations: Callable,
    retract: Callable,
    magnitude: Callable,
    x0: Any,
    max_steps: int,
    rtol: float,
    atol: float,
) -> GaussNewtonResult:
    """Minimise a least-squares cost over a state x (any pytree) moved by `retract(x, δ)`.

    Args:
        normal_equations: x ↦ (H (D, D), g (D,), cost) linearised at x.
        retract: (x, δ) ↦ x ⊕ δ, e.g. a left SE(3) increment; δ = 0 must give x.
        magnitude: x ↦ scalar scale of x for the relative step test.
        x0: start.
        max_steps: iteration budget (static).
        rtol, atol: step tolerances (static).

    A step solves (H + λ max(diag H, ε_H)) δ = −g; it is accepted when the cost does not increase
    (λ ×0.3), else rejected (λ ×10). Converged when a step has |δ|_∞ < atol + rtol·|x|, or when
    even huge damping cannot lower the cost (machine precision). One `lax.while_loop`: no
    unrolling, vmappable, no recompilation. Its first pass linearises x0 and takes no step (not
    counted in `num_steps`), so `normal_equations` appears once in the program.

    Returns:
        GaussNewtonResult.
    """
    # The start is linearised by the loop's first pass (`fresh`), not by a call of its own here: `normal_equations`
    # then appears once in the compiled program, not twice (traced twice: here for its shapes only); the pose solve
    # was half of the tracker's step program.
    _, g0, cost0 = jax.eval_shape(normal_equations, x0)
    dtype = cost0.dtype
    eps = jnp.finfo(dtype).eps
    eye = jnp.eye(g0.shape[0], dtype=dtype)

    def body(state: GaussNewtonState) -> GaussNewtonState:
        diag = jnp.diagonal(state.hessian)
        # Marquardt's scale-invariant λ·diag(H), with a floor so that an unobserved joint (a zero
        # column) is damped, not singular. A floor *added* to every entry would mix units (rotation
        # entries are ~10⁶ x the translation ones at 1 m) and slow the translation steps; eps of the
        # largest entry only lifts entries that carry no information at the dtype's precision.
        damp = state.damping * jnp.maximum(diag, eps * (jnp.max(diag) + 1.0))
        delta = jnp.linalg.solve(state.hessian + damp * eye, -state.gradient)
        x_new = _select(state.fresh, state.x, retract(state.x, delta))  # the first pass: the start itself
        H_new, g_new, cost_new = normal_equations(x_new)
        # Accept within rounding of the cost: at the optimum the cost is flat to ~√eps in y, so a
        # strict decrease test would reject the last, accurate Gauss-Newton steps.
        accept = state.fresh | (jnp.isfinite(cost_new) & (cost_new <= state.cost * (1 + 16 * eps)))
        # A step below tolerance ends the loop whether or not it lowered the cost: a rejected tiny
        # step means the cost sits at its rounding floor, and cost-change tests are unreliable there
        # (near a minimum the cost is flat to ~√eps in x).
        small_step = jnp.max(jnp.abs(delta)) < atol + rtol * magnitude(state.x)
        damping = jnp.where(accept, state.damping * 0.3, state.damping * 10.0)
        # A non-finite start ends the loop at once; the caller reports it as NONFINITE.
        done = jnp.where(state.fresh, ~jnp.isfinite(cost_new), small_step | (state.damping > 1e10))
        return GaussNewtonState(
            x=_select(accept, x_new, state.x),
            hessian=jnp.where(accept, H_new, state.hessian),
            gradient=jnp.where(accept, g_new, state.gradient),
            cost=jnp.where(accept, cost_new, state.cost),
            damping=jnp.where(state.fresh, state.damping, jnp.clip(damping, 1e-12, 1e16)),
            num_steps=state.num_steps + jnp.where(state.fresh, 0, 1).astype(jnp.int32),
            done=done,
            fresh=jnp.zeros_like(state.fresh),
        )

    def cond(state: GaussNewtonState):
        return state.fresh | ((state.num_steps < max_steps) & ~state.done)

    init = GaussNewtonState(  # H = I and g = 0 until the first pass: its (unused) step stays finite
        x=x0,
        hessian=eye,
        gradient=jnp.zeros(g0.shape, dtype),
        cost=jnp.asarray(jnp.inf, dtype),
        damping=jnp.asarray(1e-3, dtype),
        num_steps=jnp.asarray(0, jnp.int32),
        done=jnp.asarray(False),
        fresh=jnp.asarray(True),
    )
    final = jax.lax.while_loop(cond, body, init)
    leaves_finite = [jnp.all(jnp.isfinite(v)) for v in jax.tree_util.tree_leaves(final.x)]
    finite = jnp.isfinite(final.cost) & jnp.all(jnp.stack(leaves_finite))
    return GaussNewtonResult(
        x=final.x, hessian=final.hessian, converged=final.done & finite, num_steps=final.num_steps, nonfinite=~finite
    )


def solve_implicit(residual_fn: Callable, iterate: Callable, y0: jax.Array, args: Any):
    """Run `iterate(y0, args) -> (y*, aux)` and differentiate y* implicitly w.r.t. `args` (not y0).

    A `jax.custom_jvp`: the tangent dy = −(∂g/∂y)⁻¹ (∂g/∂args)·dargs of the optimality condition
    g(y, args) = ∇_y ½|f(y, args)|² = 0 is traced only when a derivative is asked for (forward or reverse
    mode; `lax.custom_root` traced the Hessian of the residual with every solve, 3 s per solve in the
    tracker's step, whether differentiated or not).

    Args:
        residual_fn: (y, args) -> residual array f whose |f|² `iterate` minimises in the chart y.
        iterate: the solver, (guess, args) -> (y, aux); its own iterations are never differentiated.

    Returns:
        (y*, aux) with aux's leaves as floats of y's dtype; only y* carries derivatives.
    """

    def optimality(y, a):
        return jax.grad(lambda yy: 0.5 * jnp.sum(residual_fn(yy, a) ** 2))(y)

    def scaled_solve(A, rhs):
        # Jacobi scaling first (translations in mm and rotations in rad differ by ~1e6 in H), then a
        # tiny Tikhonov term so a rank-deficient optimum (unobserved joint) gets a finite derivative.
        diag = jnp.abs(jnp.diagonal(A))
        scale = jnp.sqrt(jnp.where(diag > 0, diag, 1.0))
        A_scaled = A / (scale[:, None] * scale[None, :])
        eye = jnp.eye(A.shape[0], dtype=A.dtype)
        # eps^(3/4): ~1e-12 in float64, ~7e-6 in float32 (a ridge below eps would not regularise).
        ridge = jnp.finfo(A.dtype).eps ** 0.75
        return jnp.linalg.solve(A_scaled + ridge * eye, rhs / scale) / scale

    @jax.custom_jvp
    def run(guess, a):
        y, aux = iterate(guess, a)
        # integer/bool aux leaves travel as floats (zero tangents)
        return y, jax.tree_util.tree_map(lambda v: jnp.asarray(v, y.dtype), aux)

    @run.defjvp
    def run_jvp(primals, tangents):
        guess, a = primals
        _, a_dot = tangents
        y, aux = run(guess, a)
        _, g_dot = jax.jvp(lambda aa: optimality(y, aa), (a,), (a_dot,))
        A = jax.jacfwd(lambda yy: optimality(yy, a))(y)
        y_dot = -scaled_solve(jax.lax.stop_gradient(A), g_dot)
        return (y, aux), (y_dot, jax.tree_util.tree_map(jnp.zeros_like, aux))

    y, aux_float = run(jax.lax.stop_gradient(y0), args)
    return y, jax.lax.stop_gradient(aux_float)
