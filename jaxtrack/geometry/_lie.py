"""SO(3) and SE(3) on plain arrays: hat/vee, exp, log, inverse, adjoint, action on points.

Conventions (DESIGN.md): a twist is ξ = (v, ω) ∈ R^6, translation part first, the paper's ξ = (m, ω)
(eq. 1). Rigid transforms are homogeneous 4x4 matrices; `T_b_a` maps coordinates in frame a to frame b.

Every function takes arbitrary leading batch dimensions (it is written for one element and lifted with
`jnp.vectorize`). `exp` and `log` are NaN-free in value and derivative at θ = 0 (Taylor branch behind a
double `where`, as in jaxlie) and `log` stays finite in value and derivative up to and at θ = π (it goes
through a unit quaternion, whose q_w is 0 there).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

# Below this θ² the closed forms lose digits to cancellation ((θ − sin θ)/θ³ in float32 keeps only
# ~4 digits at θ = 0.05), so a Taylor series to θ⁶ takes over; its truncation error at θ² = 1e-2 is
# below 1e-16, so one threshold serves float32 and float64.
_TAYLOR_THETA_SQ = 1e-2


def _vectorize(signature: str):
    """`jnp.vectorize` with `signature`, whose input's trailing shape is checked first: a (5,) twist or a
    (3, 4) matrix is a ValueError naming the function and the shape it needs, not a vectorize error."""
    core = tuple(int(d) for d in signature.split("->")[0].strip("()").split(","))

    def wrap(fn):
        vectorized = jnp.vectorize(fn, signature=signature)

        @functools.wraps(fn)
        def checked(x):
            shape = jnp.shape(x)
            if shape[len(shape) - len(core):] != core or len(shape) < len(core):
                need = ", ".join(map(str, core))
                raise ValueError(f"{fn.__name__}: the input must have shape (..., {need}), got {shape}")
            return vectorized(x)

        return checked

    return wrap


@_vectorize("(3)->(3,3)")
def so3_hat(omega: ArrayLike):
    """Skew matrix ω̂ with ω̂ x = ω × x. (..., 3) -> (..., 3, 3)."""
    wx, wy, wz = omega[0], omega[1], omega[2]
    z = jnp.zeros_like(wx)
    return jnp.stack(
        [jnp.stack([z, -wz, wy]), jnp.stack([wz, z, -wx]), jnp.stack([-wy, wx, z])]
    )


@_vectorize("(3,3)->(3)")
def so3_vee(omega_hat: ArrayLike):
    """Inverse of `so3_hat` (antisymmetric part). (..., 3, 3) -> (..., 3)."""
    return 0.5 * jnp.stack(
        [
            omega_hat[2, 1] - omega_hat[1, 2],
            omega_hat[0, 2] - omega_hat[2, 0],
            omega_hat[1, 0] - omega_hat[0, 1],
        ]
    )


@_vectorize("(6)->(4,4)")
def se3_hat(xi: ArrayLike):
    """4x4 twist matrix ξ̂ = [[ω̂, v], [0, 0]] of ξ = (v, ω) (eq. 1). (..., 6) -> (..., 4, 4)."""
    top = jnp.concatenate([so3_hat(xi[3:]), xi[:3, None]], axis=1)
    return jnp.concatenate([top, jnp.zeros((1, 4), xi.dtype)], axis=0)


@_vectorize("(4,4)->(6)")
def se3_vee(xi_hat: ArrayLike):
    """Inverse of `se3_hat`. (..., 4, 4) -> (..., 6)."""
    return jnp.concatenate([xi_hat[:3, 3], so3_vee(xi_hat[:3, :3])])


def _exp_coefficients(theta_sq):
    """A = sin θ/θ, B = (1 − cos θ)/θ², C = (θ − sin θ)/θ³ with a NaN-free Taylor branch."""
    use_taylor = theta_sq < _TAYLOR_THETA_SQ
    # Double where: the unused branch must not see θ = 0, or its derivative is NaN (jaxlie's trick).
    safe_sq = jnp.where(use_taylor, jnp.ones_like(theta_sq), theta_sq)
    theta = jnp.sqrt(safe_sq)
    s, c = jnp.sin(theta), jnp.cos(theta)
    t2, t4, t6 = theta_sq, theta_sq**2, theta_sq**3
    a = jnp.where(use_taylor, 1 - t2 / 6 + t4 / 120 - t6 / 5040, s / theta)
    b = jnp.where(use_taylor, 0.5 - t2 / 24 + t4 / 720 - t6 / 40320, (1 - c) / safe_sq)
    cc = jnp.where(
        use_taylor, 1 / 6 - t2 / 120 + t4 / 5040 - t6 / 362880, (theta - s) / (safe_sq * theta)
    )
    return a, b, cc


@_vectorize("(3)->(3,3)")
def so3_exp(omega: ArrayLike):
    """Rodrigues: exp(ω̂) = I + A ω̂ + B ω̂². (..., 3) -> (..., 3, 3)."""
    a, b, _ = _exp_coefficients(jnp.dot(omega, omega))
    w = so3_hat(omega)
    return jnp.eye(3, dtype=omega.dtype) + a * w + b * (w @ w)


@_vectorize("(6)->(4,4)")
def se3_exp(xi: ArrayLike):
    """exp(ξ̂) of a twist ξ = (v, ω) as a 4x4 matrix (eq. 1). (..., 6) -> (..., 4, 4).

    R = I + A ω̂ + B ω̂², t = (I + B ω̂ + C ω̂²) v.
    """
    v, omega = xi[:3], xi[3:]
    a, b, c = _exp_coefficients(jnp.dot(omega, omega))
    w = so3_hat(omega)
    w2 = w @ w
    eye = jnp.eye(3, dtype=xi.dtype)
    rot = eye + a * w + b * w2
    trans = (eye + b * w + c * w2) @ v
    return make_transform(rot, trans)


@_vectorize("(3,3)->(4)")
def rotation_to_quaternion(rot: ArrayLike):
    """Unit quaternion (w, x, y, z) with w ≥ 0 of a rotation matrix (Shepperd's four cases)."""
    m00, m11, m22 = rot[0, 0], rot[1, 1], rot[2, 2]
    trace = m00 + m11 + m22
    # Each candidate divides by the largest of 4|w|, 4|x|, 4|y|, 4|z|; all are computed on a
    # clamped argument so the branches not chosen stay finite for the derivative.
    cands = jnp.stack(
        [
            jnp.stack([1 + trace, rot[2, 1] - rot[1, 2], rot[0, 2] - rot[2, 0], rot[1, 0] - rot[0, 1]]),
            jnp.stack([rot[2, 1] - rot[1, 2], 1 + m00 - m11 - m22, rot[0, 1] + rot[1, 0], rot[0, 2] + rot[2, 0]]),
            jnp.stack([rot[0, 2] - rot[2, 0], rot[0, 1] + rot[1, 0], 1 - m00 + m11 - m22, rot[1, 2] + rot[2, 1]]),
            jnp.stack([rot[1, 0] - rot[0, 1], rot[0, 2] + rot[2, 0], rot[1, 2] + rot[2, 1], 1 - m00 - m11 + m22]),
        ]
    )
    diag = jnp.stack([1 + trace, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22])
    k = jnp.argmax(diag)
    # diag sums to 4 on SO(3), so its maximum is ≥ 1; the floor only keeps non-rotations finite.
    q = cands[k] / (2 * jnp.sqrt(jnp.maximum(diag[k], jnp.finfo(rot.dtype).eps)))
    q = q / jnp.linalg.norm(q)
    return jnp.where(q[0] < 0, -q, q)


@_vectorize("(3,3)->(3)")
def so3_log(rot: ArrayLike):
    """Rotation vector ω (|ω| = θ ∈ [0, π]) with exp(ω̂) = R. (..., 3, 3) -> (..., 3).

    Through the unit quaternion: θ = 2 atan2(|q_v|, q_w), finite at θ = 0 and at θ = π.
    """
    q = rotation_to_quaternion(rot)
    qw, qv = q[0], q[1:]
    n_sq = jnp.dot(qv, qv)
    # Below √eps the series' first dropped term (|q_v|⁴/5) is under eps, and the closed form's
    # derivative would lose digits to cancellation; the series is exact to working precision there.
    small = n_sq < jnp.sqrt(jnp.finfo(q.dtype).eps)
    # Double where (jaxlie): each branch only ever sees arguments where it is finite, so the branch
    # not taken cannot put NaN into the derivative: √ at |q_v| = 0 (θ = 0) and 1/q_w at q_w = 0 (θ = π).
    safe_n = jnp.sqrt(jnp.where(small, jnp.ones_like(n_sq), n_sq))
    safe_qw = jnp.where(small, qw, jnp.ones_like(qw))
    # θ/|q_v| = 2 atan2(|q_v|, q_w)/|q_v|; small |q_v| means q_w ≈ 1: 2/q_w (1 − |q_v|²/(3 q_w²)).
    scale = jnp.where(
        small, 2.0 / safe_qw * (1 - n_sq / (3 * safe_qw**2)), 2.0 * jnp.arctan2(safe_n, qw) / safe_n
    )
    return scale * qv


@_vectorize("(4,4)->(6)")
def se3_log(transform: ArrayLike):
    """Twist ξ = (v, ω) with exp(ξ̂) = T, θ ∈ [0, π]. (..., 4, 4) -> (..., 6).

    v = V⁻¹ t with V⁻¹ = I − ½ ω̂ + (1 − A/(2B))/θ² ω̂².
    """
    rot, trans = transform[:3, :3], transform[:3, 3]
    omega = so3_log(rot)
    theta_sq = jnp.dot(omega, omega)
    use_taylor = theta_sq < _TAYLOR_THETA_SQ
    safe_sq = jnp.where(use_taylor, jnp.ones_like(theta_sq), theta_sq)
    theta = jnp.sqrt(safe_sq)
    # (1 − A/(2B))/θ² = (1 − θ sin θ / (2 (1 − cos θ)))/θ²; Taylor 1/12 + θ²/720 + θ⁴/30240.
    d = jnp.where(
        use_taylor,
        1 / 12 + theta_sq / 720 + theta_sq**2 / 30240,
        (1 - theta * jnp.sin(theta) / (2 * (1 - jnp.cos(theta)))) / safe_sq,
    )
    w = so3_hat(omega)
    v_inv = jnp.eye(3, dtype=transform.dtype) - 0.5 * w + d * (w @ w)
    return jnp.concatenate([v_inv @ trans, omega])


def make_transform(rot: ArrayLike, trans: ArrayLike):
    """Homogeneous matrix from R (..., 3, 3) and t (..., 3) -> (..., 4, 4)."""
    rot = jnp.asarray(rot)
    trans = jnp.asarray(trans)
    batch = jnp.broadcast_shapes(rot.shape[:-2], trans.shape[:-1])
    rot = jnp.broadcast_to(rot, batch + (3, 3))
    trans = jnp.broadcast_to(trans, batch + (3,))
    top = jnp.concatenate([rot, trans[..., None]], axis=-1)
    bottom = jnp.broadcast_to(jnp.array([0, 0, 0, 1], rot.dtype), batch + (1, 4))
    return jnp.concatenate([top, bottom], axis=-2)


def se3_inverse(transform: jax.Array):
    """T⁻¹ = [[Rᵀ, −Rᵀ t], [0, 1]] without a general matrix inverse. (..., 4, 4)."""
    rot_t = jnp.swapaxes(transform[..., :3, :3], -1, -2)
    trans = transform[..., :3, 3]
    return make_transform(rot_t, -jnp.einsum("...ij,...j->...i", rot_t, trans))


def se3_compose(T_c_b: jax.Array, T_b_a: jax.Array):
    """T_c_a = T_c_b · T_b_a. (..., 4, 4)."""
    return T_c_b @ T_b_a


@_vectorize("(4,4)->(6,6)")
def se3_adjoint(transform: ArrayLike):
    """Adjoint Ad_T acting on twists (v, ω): T exp(ξ̂) T⁻¹ = exp((Ad_T ξ)^). (..., 4, 4) -> (..., 6, 6)."""
    rot, trans = transform[:3, :3], transform[:3, 3]
    top = jnp.concatenate([rot, so3_hat(trans) @ rot], axis=1)
    bottom = jnp.concatenate([jnp.zeros_like(rot), rot], axis=1)
    return jnp.concatenate([top, bottom], axis=0)


@_vectorize("(6)->(6,6)")
def se3_ad(xi: ArrayLike):
    """The Lie algebra's adjoint ad_ξ (the "small adjoint", not the group's `se3_adjoint`) of a twist ξ = (v, ω):
    ad_ξ η = [ξ̂, η̂]ˇ, [[ω̂, v̂], [0, ω̂]].
    (..., 6) -> (..., 6, 6)."""
    v_hat, w_hat = so3_hat(xi[:3]), so3_hat(xi[3:])
    top = jnp.concatenate([w_hat, v_hat], axis=1)
    bottom = jnp.concatenate([jnp.zeros_like(w_hat), w_hat], axis=1)
    return jnp.concatenate([top, bottom], axis=0)


# Below this θ² the inverse left Jacobian's closed-form coefficients lose digits to cancellation (their
# numerators are O(θ⁴)); the series to θ⁸ takes over (terms fall by ~θ²/4π² each: relative error ~1e-12 at the
# threshold (2e-12 measured), far below float32's eps; in float64 the closed form is exact to ~1e-15 from there on).
_JACOBIAN_TAYLOR_THETA_SQ = 0.25


@_vectorize("(6)->(6,6)")
def se3_left_jacobian_inverse(xi: ArrayLike):
    """J_l(ξ)⁻¹ of SE(3) for ξ = (v, ω), θ = |ω| < 2π; for θ < π (the logarithm's principal branch) it is
    d log(exp(ε̂) exp(ξ̂)) / dε at ε = 0. (..., 6) -> (..., 6, 6).

    J_l⁻¹ = Σ Bₙ/n! ad_ξⁿ (Bernoulli numbers) = f(ad_ξ) with f(x) = x / (eˣ − 1). ad_ξ has the eigenvalues 0
    (semisimple) and ±iθ (double) and satisfies ad (ad² + θ²)² = 0, so f(ad) is the polynomial that matches f at
    0 and f with its derivative at ±iθ: f(x) + x/2 is even, = G(x²), and J_l⁻¹ = I − ½ ad + c₁ ad² + c₂ ad⁴ with
    1 + c₁ y + c₂ y² the Hermite interpolant of G at y = −θ², where G(−θ²) = F(θ) = (θ/2) cot(θ/2):
    c₂ = (θ F′(θ)/2 − F + 1) / θ⁴ and c₁ = −F′(θ)/(2θ) + 2 c₂ θ², F′ = ½ cot(θ/2) − (θ/4) / sin²(θ/2).
    Near θ = 0 (θ² < 0.25) the series c₁ = 1/12 − θ⁴/30240 − θ⁶/604800 − θ⁸/15966720, c₂ = −1/720 − θ²/15120
    − θ⁴/403200 − θ⁶/11975040 − 691 θ⁸/261534873600 (from B₂..B₁₂) replaces the closed form, with the double
    `where` that keeps derivatives finite.
    """
    omega = xi[3:]
    theta_sq = jnp.dot(omega, omega)
    use_taylor = theta_sq < _JACOBIAN_TAYLOR_THETA_SQ
    safe_sq = jnp.where(use_taylor, jnp.ones_like(theta_sq), theta_sq)
    theta = jnp.sqrt(safe_sq)
    half = 0.5 * theta
    cot = jnp.cos(half) / jnp.sin(half)
    F = half * cot
    dF = 0.5 * cot - 0.25 * theta / jnp.sin(half) ** 2
    c2_closed = (0.5 * theta * dF - F + 1.0) / safe_sq**2
    c1_closed = -dF / (2.0 * theta) + 2.0 * c2_closed * safe_sq
    t2, t4, t6, t8 = theta_sq, theta_sq**2, theta_sq**3, theta_sq**4
    c1 = jnp.where(use_taylor, 1 / 12 - t4 / 30240 - t6 / 604800 - t8 / 15966720, c1_closed)
    c2 = jnp.where(use_taylor, -1 / 720 - t2 / 15120 - t4 / 403200 - t6 / 11975040 - t8 * (691 / 261534873600), c2_closed)
    ad = se3_ad(xi)
    ad2 = ad @ ad
    return jnp.eye(6, dtype=ad.dtype) - 0.5 * ad + c1 * ad2 + c2 * (ad2 @ ad2)


def transform_points(transform: jax.Array, points: jax.Array):
    """Apply T (..., 4, 4) to points (..., N, 3) or (..., 3); batch dims broadcast."""
    rot, trans = transform[..., :3, :3], transform[..., :3, 3]
    if points.ndim == transform.ndim - 1:  # one point per transform
        return jnp.einsum("...ij,...j->...i", rot, points) + trans
    return jnp.einsum("...ij,...nj->...ni", rot, points) + trans[..., None, :]


def transform_point_columns(transform: jax.Array, x: ArrayLike, y: ArrayLike, z: ArrayLike):
    """T applied to points given as three coordinate arrays: returns (x', y', z').

    `transform` is (4, 4) or (..., 4, 4) broadcasting against x, y, z. Keeping coordinates as separate
    columns avoids small batched matrix products, which are slow on XLA:CPU (the solver's normal
    equations and the rasteriser use this form).
    """
    T = transform
    return tuple(T[..., i, 0] * x + T[..., i, 1] * y + T[..., i, 2] * z + T[..., i, 3] for i in range(3))
