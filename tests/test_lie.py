"""SO(3)/SE(3): group axioms, exp against the matrix exponential, log∘exp = id, derivatives."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from jaxtrack.geometry import (
    se3_ad,
    se3_adjoint,
    se3_exp,
    se3_hat,
    se3_inverse,
    se3_left_jacobian_inverse,
    se3_log,
    se3_vee,
    so3_exp,
    so3_hat,
    so3_log,
    so3_vee,
    transform_points,
)

finite = st.floats(-1.0, 1.0, allow_nan=False, allow_subnormal=False)
# Tolerances scale with the working precision (tests run in float64, see conftest.py).
EPS = float(jnp.finfo(jnp.float64).eps)


@st.composite
def twists(draw, min_angle=0.0, max_angle=np.pi - 1e-3):
    """Twists with rotation angle in [min_angle, max_angle], including tiny and near-π angles."""
    regime = draw(st.sampled_from(["zero", "tiny", "small", "generic", "near_pi"]))
    axis = draw(arrays(np.float64, 3, elements=finite))
    axis = axis / np.linalg.norm(axis) if np.linalg.norm(axis) > 1e-3 else np.array([0.0, 0.0, 1.0])
    angle = {
        "zero": 0.0,
        "tiny": draw(st.floats(1e-9, 1e-4)),
        "small": draw(st.floats(1e-4, 0.2)),
        "generic": draw(st.floats(0.2, 3.0)),
        "near_pi": np.pi - draw(st.floats(1e-6, 1e-2)),
    }[regime]
    angle = float(np.clip(angle, min_angle, max_angle))
    v = draw(arrays(np.float64, 3, elements=st.floats(-500, 500)))
    return np.concatenate([v, axis * angle])


@settings(max_examples=60, deadline=None)
@given(twists())
def test_exp_matches_matrix_exponential(xi):
    np.testing.assert_allclose(se3_exp(jnp.asarray(xi)), scipy.linalg.expm(np.asarray(se3_hat(xi))), atol=1e7 * EPS, rtol=1e7 * EPS)


@settings(max_examples=60, deadline=None)
@given(twists())
def test_log_inverts_exp(xi):
    np.testing.assert_allclose(se3_log(se3_exp(jnp.asarray(xi))), xi, atol=1e-6 * (1 + np.abs(xi).max()))


@settings(max_examples=40, deadline=None)
@given(twists(), twists(), twists())
def test_group_axioms(a, b, c):
    A, B, C = (se3_exp(jnp.asarray(x)) for x in (a, b, c))
    eye = np.eye(4)
    np.testing.assert_allclose((A @ B) @ C, A @ (B @ C), atol=1e-8)
    np.testing.assert_allclose(A @ se3_inverse(A), eye, atol=1e7 * EPS)
    np.testing.assert_allclose(se3_inverse(A) @ A, eye, atol=1e7 * EPS)
    np.testing.assert_allclose(A @ jnp.eye(4), A)
    R = A[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e4 * EPS)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e4 * EPS)


@settings(max_examples=40, deadline=None)
@given(twists(), twists())
def test_adjoint(a, b):
    T = se3_exp(jnp.asarray(a))
    lhs = T @ se3_exp(jnp.asarray(b)) @ se3_inverse(T)
    np.testing.assert_allclose(lhs, se3_exp(se3_adjoint(T) @ b), atol=1e-7)


def _left_jacobian_series(xi):
    """J_l(ξ) = Σ ad_ξⁿ / (n + 1)! (an entire series: 40 terms reach float64 for θ ≤ π), in numpy."""
    ad = np.asarray(se3_ad(jnp.asarray(xi)))
    term, total = np.eye(6), np.eye(6)
    for n in range(1, 40):
        term = term @ ad / (n + 1)
        total = total + term
    return total


@jax.jit
def _left_jacobian_inverse_and_log_derivative(xi):
    """J_l⁻¹(ξ) and jax.jacfwd of ε ↦ log(exp(ε̂) exp(ξ̂)) at 0: one compiled program for every example (op by
    op, the 60 examples dispatched thousands of small programs)."""
    E = se3_exp(xi)
    return se3_left_jacobian_inverse(xi), jax.jacfwd(lambda e: se3_log(se3_exp(e) @ E))(jnp.zeros(6, xi.dtype))


@settings(max_examples=60, deadline=None)
@given(twists(max_angle=3.0))
def test_left_jacobian_inverse_inverts_the_series_and_differentiates_the_log(xi):
    """J_l⁻¹ in closed form (and its series below θ² = 0.25) against the inverse of the series J_l, and against
    jax.jacfwd of ε ↦ log(exp(ε̂) exp(ξ̂)) at 0, in float64."""
    got, ref = (np.asarray(a) for a in _left_jacobian_inverse_and_log_derivative(jnp.asarray(xi)))
    scale = 1.0 + np.abs(xi[:3]).max()  # the translation block grows with |v| (mm)
    np.testing.assert_allclose(got @ _left_jacobian_series(xi), np.eye(6), atol=1e-9 * scale)
    np.testing.assert_allclose(got, ref, atol=1e-8 * scale)


def test_left_jacobian_inverse_meets_itself_across_its_series_threshold():
    """At θ² = 0.25 the series (below) and the closed form (from there on) agree to the series' truncation
    (~2e-11 relative in the entries that |v| scales) in value, and the derivative along ω (which moves θ across the switch) matches central
    differences; at θ = 0 the derivative is finite."""
    threshold = 0.25
    v = np.array([30.0, -20.0, 10.0])
    axis = np.array([0.6, -0.8, 0.0])
    below, above = (np.concatenate([v, axis * np.sqrt(t)]) for t in (np.nextafter(threshold, 0.0), threshold))
    assert np.dot(below[3:], below[3:]) < threshold <= np.dot(above[3:], above[3:])
    np.testing.assert_allclose(np.asarray(se3_left_jacobian_inverse(jnp.asarray(below))),
                               np.asarray(se3_left_jacobian_inverse(jnp.asarray(above))), rtol=1e-10, atol=1e-10)
    f = lambda x: jnp.sum(se3_left_jacobian_inverse(x) * jnp.arange(36.0).reshape(6, 6))
    for xi in (jnp.asarray(above), jnp.asarray(np.concatenate([v, np.zeros(3)]))):
        d = jnp.asarray(np.concatenate([np.zeros(3), axis])) * 1e-5  # along ω: θ changes, across the switch at 0.5
        grad = np.asarray(jax.grad(f)(xi))
        assert np.all(np.isfinite(grad))
        fd = (f(xi + d) - f(xi - d)) / 2
        np.testing.assert_allclose(float(grad @ np.asarray(d)), float(fd), rtol=1e-6, atol=1e-12)


@settings(max_examples=30, deadline=None)
@given(arrays(np.float64, 6, elements=finite), arrays(np.float64, 3, elements=finite))
def test_hat_vee_and_action(xi, p):
    np.testing.assert_allclose(se3_vee(se3_hat(xi)), xi, atol=EPS)
    np.testing.assert_allclose(so3_vee(so3_hat(xi[3:])), xi[3:], atol=EPS)
    np.testing.assert_allclose(so3_hat(xi[3:]) @ p, np.cross(xi[3:], p), atol=8 * EPS)
    T = se3_exp(jnp.asarray(xi))
    np.testing.assert_allclose(transform_points(T, p), (T @ np.append(p, 1.0))[:3], atol=1e4 * EPS)


def test_batch_shapes():
    xi = jnp.asarray(np.random.default_rng(0).normal(size=(4, 5, 6)))
    T = se3_exp(xi)
    assert T.shape == (4, 5, 4, 4)
    assert se3_log(T).shape == (4, 5, 6)
    assert so3_exp(xi[..., 3:]).shape == (4, 5, 3, 3)
    np.testing.assert_allclose(T[2, 3], se3_exp(xi[2, 3]))


def test_log_at_exactly_pi_and_identity_is_finite():
    for axis in np.eye(3):
        R = so3_exp(jnp.asarray(axis * np.pi))
        w = so3_log(R)
        assert np.isfinite(w).all()
        assert np.linalg.norm(w) == pytest.approx(np.pi, abs=1e-6)
        np.testing.assert_allclose(so3_exp(w), R, atol=1e7 * EPS)
    assert np.all(se3_log(jnp.eye(4)) == 0)


def _central_difference(f, x, eps=1e-6):
    cols = []
    for i in range(x.size):
        dx = np.zeros_like(x)
        dx[i] = eps
        cols.append((np.asarray(f(x + dx)) - np.asarray(f(x - dx))) / (2 * eps))
    return np.stack(cols, axis=-1)


@functools.partial(jax.jit, static_argnums=0)
def _jacobians(f, x):
    """(jax.jacfwd(f)(x), jax.jacrev(f)(x)) as one compiled program per function and shape (op by op, each call
    dispatched hundreds of small programs)."""
    return jax.jacfwd(f)(x), jax.jacrev(f)(x)


def _log_of_exp(xi):
    return se3_log(se3_exp(xi))


@pytest.mark.parametrize("angle", [0.0, 1e-8, 1e-3, 0.7, np.pi - 1e-4, np.pi])
def test_exp_log_derivatives_agree(angle):
    rng = np.random.default_rng(1)
    axis = rng.normal(size=3)
    xi = np.concatenate([rng.normal(size=3) * 10, axis / np.linalg.norm(axis) * angle])
    for f, x in ((se3_exp, xi), (se3_log, np.asarray(se3_exp(xi)))):
        fwd, rev = _jacobians(f, jnp.asarray(x))
        assert np.isfinite(fwd).all() and np.isfinite(rev).all()
        np.testing.assert_allclose(fwd, rev, atol=1e7 * EPS)
        if f is se3_exp or angle < 3.0:  # log is not differentiable in all directions at π (matrix off SO(3))
            if f is se3_log:
                continue  # FD on raw 4x4 entries leaves SO(3); checked through exp below
            np.testing.assert_allclose(fwd, _central_difference(f, x), atol=1e-6)
    # log∘exp on the tangent space: d log(exp(ξ))/dξ = I away from π.
    if angle < 3.0:
        J = _jacobians(_log_of_exp, jnp.asarray(xi))[0]
        np.testing.assert_allclose(J, np.eye(6), atol=1e-7)


def _rotation_at_pi(axis):
    """R = exp(π â) built exactly as 2 â âᵀ − I (so3_exp rounds sin π to 1.2e-16, leaving q_w ≠ 0)."""
    a = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    return jnp.asarray(2 * np.outer(a, a) - np.eye(3))


@pytest.mark.parametrize("axis", [(0.0, 0.0, 1.0), (1.0, 0.0, 0.0), (1.0, -2.0, 0.5)])
def test_log_derivative_at_exactly_pi(axis):
    """At θ = π exactly (q_w = 0) the derivative of log is finite and correct.

    Correct means: exp∘log is the identity on SO(3), so the chain rule must map every tangent direction
    R b̂ to itself, and turning back from π (θ = π − ε, the side log's branch q_w ≥ 0 continues) must
    match a one-sided finite difference. Checked for so3_log and se3_log, forward and reverse mode.
    """
    R = _rotation_at_pi(axis)
    assert float(jnp.linalg.norm(so3_log(R))) == pytest.approx(np.pi, abs=8 * EPS)
    t = jnp.asarray([10.0, -20.0, 30.0])
    T = jnp.eye(4).at[:3, :3].set(R).at[:3, 3].set(t)
    for f, x in ((so3_log, R), (se3_log, T)):
        fwd, rev = _jacobians(f, x)
        assert np.isfinite(fwd).all() and np.isfinite(rev).all(), f.__name__
        np.testing.assert_allclose(fwd, rev, atol=1e4 * EPS)
    # The round trips' derivatives along every tangent direction: one compiled program per map, not op by op.
    so3_round = jax.jit(jax.vmap(lambda r, dr: jax.jvp(lambda m: so3_exp(so3_log(m)), (r,), (dr,))[1], in_axes=(None, 0)))
    se3_round = jax.jit(jax.vmap(lambda m, dm: jax.jvp(lambda x: se3_exp(se3_log(x)), (m,), (dm,))[1], in_axes=(None, 0)))
    tangents = jnp.stack([R @ so3_hat(jnp.asarray(b)) for b in np.eye(3)])
    np.testing.assert_allclose(so3_round(R, tangents), tangents, atol=1e4 * EPS)
    tangents = jnp.stack([T @ se3_hat(jnp.asarray(xi)) for xi in np.eye(6)])
    np.testing.assert_allclose(se3_round(T, tangents), tangents, atol=1e6 * EPS)
    # One-sided: rotating back about the log's own axis lowers θ to π − ε, so ω moves by −ε ω/π.
    w = so3_log(R)
    h = 1e-6
    step = jnp.asarray(scipy.linalg.expm(np.asarray(so3_hat(-h * w / np.pi))))
    one_sided = (so3_log(R @ step) - w) / h
    _, d = jax.jvp(so3_log, (R,), (R @ so3_hat(-w / np.pi),))
    np.testing.assert_allclose(d, -w / np.pi, atol=1e4 * EPS)
    np.testing.assert_allclose(d, one_sided, atol=1e-6)
    # float32 takes the same branches (its thresholds come from its own eps): finite and equal to float64.
    J32 = jax.jacrev(so3_log)(R.astype(jnp.float32))
    assert J32.dtype == jnp.float32 and np.isfinite(J32).all()
    np.testing.assert_allclose(J32, jax.jacrev(so3_log)(R), atol=1e3 * float(jnp.finfo(jnp.float32).eps))
