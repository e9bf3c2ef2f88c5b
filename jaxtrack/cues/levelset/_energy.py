"""The level-set energy of eq. 11 and its gradient descent (eq. 13).

    E(Φ) = −Σ_x [H(Φ) log p1 + (1 − H(Φ)) log p2] + ν Σ_x δ(Φ) |∇Φ| + λ Σ_x (Φ − Φ0(χ))²   (eq. 11)

with the regularised Heaviside H(s) = ½ + atan(s/ε)/π and δ = H'. The length term is written as
δ(Φ)|∇Φ| (= |∇H(Φ)| in the continuum), with forward differences and |v|_η = sqrt(|v|² + η²).
`levelset_update` is the paper's update

    ∂Φ/∂t = δ(Φ) (log p1/p2 + ν div(∇Φ/|∇Φ|)) + 2λ (Φ0 − Φ)                              (eq. 13)

in the discretisation that is exactly −∂E/∂Φ of this discrete energy (the curvature term as
div⁻(δ ∇⁺Φ/|∇⁺Φ|_η) − δ'|∇⁺Φ|_η, which is δ κ in the continuum), so the descent is provably a
descent; `tests/test_levelset.py` checks it against `jax.grad`.

Time step: the curvature term diffuses with coefficient ν δ/|∇Φ| ≤ ν/(π ε) for a signed distance
function, so dt = cfl / (4 ν/(π ε) + 2 λ) is the explicit stability limit. The data force can be
large where the densities are sharp (a σ of a few grey values), so each pixel's step is also
clipped to `max_step` pixels: sign-preserving, so the step stays a descent direction.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..._device import to_device
from ._redistance import redistance


class RegionParams(eqx.Module):
    """Parameters of the region cue (arrays: vmap over them, no recompilation).

    Attributes:
        lam: λ, weight of the shape prior (Φ − Φ0)² (paper: 0.05).
        nu: ν, weight of the length term (paper: 0.001 |Ω|^0.7, Ω the crop's area in pixels).
        epsilon: ε of the regularised Heaviside (pixels).
        eta: η of |∇Φ|_η in the length term (pixels⁻¹ scale of ∇Φ).
        cfl: fraction of the explicit stability limit used as time step.
        max_step: per-pixel clip of one update of Φ (pixels).
        rho: ρ, the window of the local densities (paper: 12 px).
        kappa: weight of the global moments in the local densities (see `local_densities`).
        sigma_min: floor on the density σ (feature units, 0-255 scale).
        density_band: pixels within this distance of the zero level count for neither region's
            densities (`region_memberships`), so that a pose error of a few pixels does not put the
            background strip it covers into the object's density. Default 0 (off): measured, 3 px
            makes a flat box refined from a 6 px shift converge (67 mm → 1.3 mm off) but drops
            thin side faces seen at grazing angles from the object's density (the shaded
            two-joint chain of tests/test_levelset.py then drifts 4.5 → 5.3 mm).
        min_match: contour matches shorter than this (px) get zero weight. Default 0: a zero-length
            match says "this contour point is where it should be" and anchors the pose; dropping
            them left Gauss-Newton with the few disagreeing rows (measured: 20 of 263 rows at the
            true pose of a flat box, one round jumped 19 mm in depth).
        max_match: matches longer than this (px) are treated as outliers: zero weight.
        alpha_match: α of the regularised shape matching (eq. 15; paper: 10).
        settle_motion: the pose has settled when a round moves the matched contour's model points
            less than this on average (mm). Points, not the twist: a rotation of 7e-4 rad about the
            camera's origin reads as 0.4 mm in the twist's translation yet moves the object's points
            0.03 mm, which is the round-to-round jitter at the true pose (sub-pixel matches).
        tangent_weight: weight of a contour match's residual along the contour, relative to the one across
            it, when `RegionConfig.edge_rows` is on (1 = the paper's point rows; small values keep a weak
            hold on motions the silhouette does not see, such as a symmetric body's spin).
        joint_prior: strength of the `JointPrior` that holds the joint angles near the refinement's start
            (the frame's prediction), relative to the mean joint curvature of the data; 0 = none (the
            method; rigid objects have no joints). See `jaxtrack.solve.JointPrior`.
        feature_sigma: σ (crop px, at most 2) of a Gaussian pre-smoothing of the feature channels before the
            densities and the data term; 0 (default) = none, the method. For heavy pixel noise: on the
            turntable teapot with 50 % of the pixels replaced by uniform noise the per-pixel data term is
            too weak against the length term, and the segmentation stays on the model's silhouette (it got
            27 of the 260 pixels the turn moved right, 199 on the clean frames); σ = 1 with ν at 0.3 of its
            default tracked it (see the README's level-set noise paragraph), at a cost in depth on clean frames.
    """

    lam: jax.Array
    nu: jax.Array
    epsilon: jax.Array
    eta: jax.Array
    cfl: jax.Array
    max_step: jax.Array
    rho: jax.Array
    kappa: jax.Array
    sigma_min: jax.Array
    density_band: jax.Array
    min_match: jax.Array
    max_match: jax.Array
    alpha_match: jax.Array
    settle_motion: jax.Array
    tangent_weight: jax.Array
    joint_prior: jax.Array
    feature_sigma: jax.Array


def region_params(crop_shape: tuple[int, int] = (256, 256), dtype=jnp.float32, **overrides) -> RegionParams:
    """The paper's settings (λ = 0.05, ν = 0.001 |Ω|^0.7 with |Ω| the crop's area, ρ = 12, α = 10).

    Keyword overrides replace any field (e.g. `lam=0.0`).

    Raises:
        ValueError: for an unknown field or a negative value.
    """
    area = float(crop_shape[0] * crop_shape[1])
    values = {
        "lam": 0.05,
        "nu": 0.001 * area**0.7,
        "epsilon": 1.0,
        "eta": 0.1,
        "cfl": 0.9,
        "max_step": 0.5,
        "rho": 12.0,
        "kappa": 0.05,
        "sigma_min": 5.0,
        "density_band": 0.0,
        "min_match": 0.0,
        "max_match": 15.0,
        "alpha_match": 10.0,
        "settle_motion": 0.05,
        "tangent_weight": 0.1,
        "joint_prior": 0.0,
        "feature_sigma": 0.0,
    }
    for name, value in overrides.items():
        if name not in values:
            raise ValueError(f"region_params: unknown parameter {name!r}; choose from {sorted(values)}")
        values[name] = value
    for name, value in values.items():
        if not np.all(np.asarray(value) >= 0):
            raise ValueError(f"region_params: {name} must be ≥ 0, got {value}")
    return RegionParams(**{k: to_device(v, dtype) for k, v in values.items()})


def heaviside(s, epsilon):
    """Regularised Heaviside H(s) = ½ + atan(s/ε)/π."""
    return 0.5 + jnp.arctan(s / epsilon) / jnp.pi


def region_membership(phi):
    """Object membership in [0, 1] for the density estimates: a one-pixel ramp across the zero level.

    Not H(Φ): the atan Heaviside's tails (≈ 1/(π|Φ|)) summed over a background many times larger
    than the object contaminate the object's moments (measured: object σ ≈ 50 grey values on a
    flat-coloured teapot instead of ≈ 15).
    """
    return jnp.clip(0.5 + phi, 0.0, 1.0)


def region_memberships(phi, band):
    """(object, background) memberships (H, W) each in [0, 1], both zero within `band` px of Φ's zero
    level (one-pixel ramps at |Φ| = band; band = 0 gives `region_membership` and its complement).

    Why a band: the densities are estimated from Φ0 (first round) or from the last segmentation,
    both wrong near the contour by the pose error. Measured on a flat box shifted 6 px: the strip of
    background inside Φ0 entered the object's local density, the segmentation never released it,
    and region-only refinement ran 70 mm off in depth; with the true mask's densities it converged.
    """
    return jnp.clip(0.5 + phi - band, 0.0, 1.0), jnp.clip(0.5 - phi - band, 0.0, 1.0)


def dirac(s, epsilon):
    """δ(s) = H'(s) = ε / (π (ε² + s²))."""
    return epsilon / (jnp.pi * (epsilon**2 + s**2))


def _dirac_prime(s, epsilon):
    return -2.0 * epsilon * s / (jnp.pi * (epsilon**2 + s**2) ** 2)


def _forward_differences(phi):
    """∇⁺Φ with zero difference across the last row/column (replicated border)."""
    dx = jnp.concatenate([phi[:, 1:] - phi[:, :-1], jnp.zeros_like(phi[:, :1])], axis=1)
    dy = jnp.concatenate([phi[1:] - phi[:-1], jnp.zeros_like(phi[:1])], axis=0)
    return dx, dy


def _backward_divergence(vx, vy):
    """div⁻ v = v_x(x) − v_x(x − e_x) + v_y(y) − v_y(y − e_y), v(−1) = 0: the adjoint of −∇⁺."""
    dx = jnp.concatenate([vx[:, :1], vx[:, 1:] - vx[:, :-1]], axis=1)
    dy = jnp.concatenate([vy[:1], vy[1:] - vy[:-1]], axis=0)
    return dx + dy


def levelset_energy(phi, phi0, log_p, params: RegionParams):
    """Discrete energy of eq. 11 (scalar).

    Args:
        phi: (H, W) level-set function Φ (> 0 on the object).
        phi0: (H, W) the model's signed distance Φ0(χ) (shape prior).
        log_p: (2, H, W) log p1 (object) and log p2 (background) per pixel (`log_likelihoods`).
        params: λ, ν, ε, η.
    """
    h = heaviside(phi, params.epsilon)
    region = -jnp.sum(h * log_p[0] + (1.0 - h) * log_p[1])
    dx, dy = _forward_differences(phi)
    length = params.nu * jnp.sum(dirac(phi, params.epsilon) * jnp.sqrt(dx**2 + dy**2 + params.eta**2))
    shape = params.lam * jnp.sum((phi - phi0) ** 2)
    return region + length + shape


def levelset_update(phi, phi0, force, params: RegionParams):
    """∂Φ/∂t of eq. 13 (= −∂E/∂Φ of `levelset_energy`), (H, W).

    Args:
        force: (H, W) log p1 − log p2 (`data_term`).
    """
    eps = params.epsilon
    d = dirac(phi, eps)
    dx, dy = _forward_differences(phi)
    g = jnp.sqrt(dx**2 + dy**2 + params.eta**2)
    curvature = _backward_divergence(d * dx / g, d * dy / g) - _dirac_prime(phi, eps) * g
    return d * force + params.nu * curvature + 2.0 * params.lam * (phi0 - phi)


def time_step(params: RegionParams):
    """Explicit stability limit of eq. 13 scaled by cfl (see the module docstring)."""
    return params.cfl / (4.0 * params.nu / (jnp.pi * params.epsilon) + 2.0 * params.lam + 1e-12)


def evolve(phi, phi0, force, params: RegionParams, iterations: int, redistance_every: int = 5):
    """`iterations` clipped explicit steps of eq. 13, re-distancing Φ every `redistance_every`.

    Static loop counts (`lax.fori_loop`); iterations is rounded down to a multiple of
    redistance_every. Re-distancing keeps the sub-pixel values of the band |Φ| < 1 (so the zero
    level does not snap to the pixel grid) and replaces the rest by the jump-flooding distance.
    """
    dt = time_step(params)

    def step(_, p):
        return p + jnp.clip(dt * levelset_update(p, phi0, force, params), -params.max_step, params.max_step)

    def block(_, p):
        return redistance(jax.lax.fori_loop(0, redistance_every, step, p))

    return jax.lax.fori_loop(0, max(iterations // redistance_every, 0), block, phi)
