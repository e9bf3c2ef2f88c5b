"""A lean damped Gauss-Newton on a manifold, for few unknowns (6 + J) and many residuals.

The normal equations H δ = −g with H = JᵀWJ of size (6+J)² are the cheap route for the pose
problem (eq. 5); Marquardt damping H + λ diag(H) handles rank deficiency (an unobserved joint, few
points). Optimistix's LevenbergMarquardt solves the same problem through QR on the full Jacobian,
which under vmap on a CPU is many times slower; it stays available as
`SolverConfig(backend="optimistix")` and the tests check both agree.

Derivatives of the solution come from the implicit function theorem on the optimality condition
∇_y ½|f(y, args)|² = 0 (`jax.lax.custom_root`), not from unrolling the iterations.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp


def damped_gauss_newton(
    normal_equations: Callable,
    retract: Callable,
    magnitude: Callable,
    x0,
    max_steps: int,
    rtol: float,
    atol: float,
):
    """Minimise a least-squares cost over a state x (any pytree) moved by `retract(x, δ)`.

    Args:
        normal_equations: x ↦ (H (D, D), g (D,), cost) linearised at x.
        retract: (x, δ) ↦ x ⊕ δ, e.g. a left SE(3) increment; δ = 0 must give x.
        magnitude: x ↦ scalar scale of x for the relative step test.

    A step solves (H + λ (diag H + ε)) δ = −g; it is accepted when the cost does not increase
    (λ ×0.3), else rejected (λ ×10). Converged when a step has |δ|_∞ < atol + rtol·|x|, or when
    even huge damping cannot lower the cost (machine precision). One `lax.while_loop`: no unrolling, vmappable, no recompilation.

    Returns:
        (x, converged, num_steps, nonfinite)
    """
    system0 = normal_equations(x0)
    dtype = system0[2].dtype
    eye = jnp.eye(system0[1].shape[0], dtype=dtype)
    select = lambda c, new, old: jax.tree_util.tree_map(lambda u, v: jnp.where(c, u, v), new, old)  # noqa: E731

    def body(state):
        x, (H, g, c), lam, step, _ = state
        diag = jnp.diagonal(H)
        # The floor on the diagonal keeps an unobserved joint (zero column) damped, not singular.
        damp = lam * (diag + 1e-9 * (jnp.max(diag) + 1.0))
        delta = jnp.linalg.solve(H + damp * eye, -g)
        x_new = retract(x, delta)
        system_new = normal_equations(x_new)
        c_new = system_new[2]
        # Accept within rounding of the cost: at the optimum the cost is flat to ~√eps in y, so a
        # strict decrease test would reject the last, accurate Gauss-Newton steps.
        accept = jnp.isfinite(c_new) & (c_new <= c * (1 + 16 * jnp.finfo(dtype).eps))
        # A step below tolerance ends the loop whether or not it lowered the cost: a rejected tiny
        # step means the cost sits at its rounding floor, and cost-change tests are unreliable there
        # (near a minimum the cost is flat to ~√eps in x).
        small_step = jnp.max(jnp.abs(delta)) < atol + rtol * magnitude(x)
        done = small_step | (lam > 1e10)
        lam = jnp.clip(jnp.where(accept, lam * 0.3, lam * 10.0), 1e-12, 1e16)
        return select(accept, x_new, x), select(accept, system_new, (H, g, c)), lam, step + 1, done

    def cond(state):
        return (state[3] < max_steps) & ~state[4]

    # A non-finite start ends the loop at once; the caller reports it as NONFINITE.
    init = (x0, system0, jnp.asarray(1e-3, dtype), jnp.asarray(0, jnp.int32), ~jnp.isfinite(system0[2]))
    x, (_, _, c), _, steps, done = jax.lax.while_loop(cond, body, init)
    finite = jnp.isfinite(c) & jnp.all(jnp.stack([jnp.all(jnp.isfinite(v)) for v in jax.tree_util.tree_leaves(x)]))
    return x, done & finite, steps, ~finite


def solve_implicit(residual_fn: Callable, iterate: Callable, y0, args):
    """Run `iterate(y0) -> (y*, aux)` and differentiate y* implicitly w.r.t. `args` (not y0).

    Args:
        residual_fn: (y, args) -> residual array f whose |f|² `iterate` minimises in the chart y.
        iterate: the solver; its own iterations are never differentiated.

    Returns:
        (y*, aux) with aux's leaves as floats of y's dtype; only y* carries derivatives (through
        ∇_y ½|f|² = 0).
    """

    def optimality(y):
        return jax.grad(lambda yy: 0.5 * jnp.sum(residual_fn(yy, args) ** 2))(y)

    def tangent_solve(linear_fn, rhs):
        A = jax.jacfwd(linear_fn)(rhs)
        # Jacobi scaling first (translations in mm and rotations in rad differ by ~1e6 in H), then a
        # tiny Tikhonov term so a rank-deficient optimum (unobserved joint) gets a finite derivative.
        diag = jnp.abs(jnp.diagonal(A))
        scale = jnp.sqrt(jnp.where(diag > 0, diag, 1.0))
        A_scaled = A / (scale[:, None] * scale[None, :])
        eye = jnp.eye(A.shape[0], dtype=A.dtype)
        return jnp.linalg.solve(A_scaled + 1e-12 * eye, rhs / scale) / scale

    def solve(_, guess):
        y, aux = iterate(guess)
        # custom_root differentiates its aux outputs too; integer/bool leaves travel as floats.
        return y, jax.tree_util.tree_map(lambda a: jnp.asarray(a, y.dtype), aux)

    y, aux_float = jax.lax.custom_root(optimality, jax.lax.stop_gradient(y0), solve, tangent_solve, has_aux=True)
    aux_float = jax.lax.stop_gradient(aux_float)
    return y, aux_float
