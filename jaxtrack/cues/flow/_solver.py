"""Minimiser of the flow energy of eq. 6: coarse-to-fine warping with two nested fixed points.

Following Brox, Bruhn, Papenberg and Weickert (ECCV 2004), Section 3:

* outer fixed point (warping): at each pyramid level the flow w is held fixed, I2 and ∇I2 are warped
  by w and the data term is linearised in the increment dw (the motion tensor J, a 3x3 quadratic form
  s²(dw) = [dw, 1]ᵀ J [dw, 1] per pixel, summed over channels);
* inner fixed point (lagged nonlinearity): the robust weights Ψ'(s²) and Ψ2'(|∇(w + dw)|²) are frozen,
  which leaves a sparse linear system in dw (eq. 7 of the tracking paper's Euler-Lagrange equations);
* linear solver: coupled point SOR in red-black order. Each pixel solves its own 2x2 block for
  (du, dv) from its four neighbours; all pixels of one colour update at once, which is the form that
  vectorises on XLA:CPU.

Pyramid levels are unrolled in Python (their shapes differ), each its own copy of the solver in the
compiled program (about 2.5 s of XLA:CPU compile per level); every loop inside a level is a
`lax.fori_loop` with a static trip count, so one image size compiles once. With
`FlowConfig.shared_levels_from` = k the levels from k on (the coarse ones) are instead one compiled level
in a `lax.fori_loop` over the levels, each padded to level k's shape with its true size as data
(edge-replicated images, sampling clamped to the true size): the same flow to rounding, fewer compiled
levels, at the price of solving the coarse levels on the larger padded grid.

The smoothness discretisation is exactly the one of `local_flow_energy` (forward differences, a
Ψ2' per pixel shared by its right and lower edges, edges only between two pixels of Ω1), so the
lagged-diffusivity iteration is a fixed point of that discrete energy, and `linearised_flow_energy`
gives the energy the solver actually decreases at the finest level.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike, DTypeLike

from ..._status import Status, check_status, first_failure, is_usable, status_where
from ...image import (
    downsample,
    gaussian_blur,
    image_gradients,
    median_filter,
    pyramid_shapes,
    sample_bilinear,
    upsample_flow,
    warp_bilinear,
)
from ._energy import FlowEnergyParams, flow_energy, local_flow_energy, smoothness_s2
from ._quarters import from_quarters, im, ip, km, kp, q_down, q_left, q_right, q_up, to_quarters


class FlowConfig(eqx.Module):
    """Settings of the minimiser; all static (they fix shapes and loop counts).

    Defaults: a factor-2 pyramid with 8 warps per level. Brox et al. use η = 0.95 with one warp per
    level; on Middlebury, η = 0.5 x 8 warps measured the same accuracy as η = 0.75 x 3 and η = 0.9 x 1
    (within 0.01 px EPE) at equal run time, and each level is a separately compiled program, so
    fewer levels compile much faster (about 20 s vs 40-120 s for a 640x480 frame on 2 cores).

    Attributes:
        eta: pyramid downsampling factor η per level (Brox et al. 2004: 0.95).
        min_size: the coarsest level's short side in pixels.
        max_levels: cap on the number of pyramid levels.
        presmooth_sigma: Gaussian σ (pixels) applied to both images before everything else; the
            energy is that of the smoothed images.
        warps: outer fixed-point iterations (warps) per level.
        lagged: inner fixed-point iterations (robust weights frozen) per warp.
        sor_iters: red-black SOR sweeps per inner iteration.
        sor_relaxation: SOR over-relaxation factor ω_SOR, 0 < ω_SOR < 2 (not Ω1, the region, nor Φ).
        finest_warps: extra warps at the finest level (0: the same as every level).
        median: side of a median filter applied to the flow (0 = off, 3 or 5). A heuristic
            from Sun, Roth and Black (CVPR 2010) that removes outliers of the linearised solution;
            it is not part of eq. 6, so the result is no longer an exact fixed point of the energy.
            Inside Ω1 only: neighbours outside Ω1 count as the centre pixel's own value.
        median_every_warp: filter after every warp (Sun et al.) or only after each level's last warp.
        shared_levels_from: 0: every pyramid level is its own compiled copy of the solver. k ≥ 1: the
            levels k, k+1, ... (coarser) share one compiled level, run in a loop on level k's shape (see
            the module docstring). The flow is the same to rounding; compile time drops by about the
            shared levels' share, run time grows by the padding (k = 2 at η = ½: the coarse levels cost
            4 x 1/16 of the finest level instead of 1/16 + 1/64 + ...).
    """

    eta: float = eqx.field(static=True, default=0.5)
    min_size: int = eqx.field(static=True, default=16)
    max_levels: int = eqx.field(static=True, default=100)
    presmooth_sigma: float = eqx.field(static=True, default=0.8)
    warps: int = eqx.field(static=True, default=8)
    lagged: int = eqx.field(static=True, default=2)
    sor_iters: int = eqx.field(static=True, default=20)
    sor_relaxation: float = eqx.field(static=True, default=1.8)
    finest_warps: int = eqx.field(static=True, default=0)
    median: int = eqx.field(static=True, default=0)
    median_every_warp: bool = eqx.field(static=True, default=True)
    shared_levels_from: int = eqx.field(static=True, default=0)

    def __check_init__(self):
        if not 0.0 < self.eta < 1.0:
            raise ValueError(f"FlowConfig.eta must lie in (0, 1), got {self.eta}")
        if not 0.0 < self.sor_relaxation < 2.0:
            raise ValueError(f"FlowConfig.sor_relaxation must lie in (0, 2), got {self.sor_relaxation}")
        if self.median not in (0, 3, 5):
            raise ValueError(f"FlowConfig.median must be 0 (off), 3 or 5 (window side), got {self.median}")
        for name in ("min_size", "max_levels", "warps", "lagged", "sor_iters"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"FlowConfig.{name} must be ≥ 1, got {getattr(self, name)}")
        if int(self.shared_levels_from) < 0:
            raise ValueError(f"FlowConfig.shared_levels_from must be ≥ 0 (0 = off), got {self.shared_levels_from}")


def middlebury_config() -> FlowConfig:
    """The minimiser settings of `jaxtrack flow` and the benchmark: the defaults plus a 3x3 median
    filter of the flow after every warp.

    Measured on Middlebury (α = 4, γ = 5, `experiments/bench_flow.py`): mean EPE 0.303 at about 1.0 s per
    640x480 pair; a 5x5 median after every level gives 0.296 at about 1.4 s, and 5x5 after every warp
    0.293 at several seconds.
    """
    return FlowConfig(median=3)


class FlowResult(eqx.Module):
    """Output of `compute_flow`.

    Attributes:
        flow: (H, W, 2) flow (u, v) in pixels from frame 1 to frame 2; zero outside the region Ω1.
        local_energy: (H, W) energy density e(x) of eq. 6 at the solution (0 outside Ω1).
        confidence: (H, W) c(x) = β / (1 + e(x)) of eq. 8 inside Ω1, 0 outside.
        region: (H, W) bool Ω1 as used.
        status: int32 `jaxtrack.Status`: OK; INVALID_INPUT when an input was non-finite or a parameter
            lay outside its domain (α ≥ 0, γ ≥ 0, ε > 0); NONFINITE when the solution was not finite.
            When not OK, flow, local_energy and confidence are zeros (never NaN).
    """

    flow: jax.Array
    local_energy: jax.Array
    confidence: jax.Array
    region: jax.Array
    status: jax.Array


class MotionTensor(NamedTuple):
    """Linearised data term at a fixed flow, as two 3x3 quadratic forms per pixel.

    Grey value constancy: s_g²(du, dv) = [du dv 1] J [du dv 1]ᵀ (fields j..), gradient constancy:
    s_d²(du, dv) = [du dv 1] K [du dv 1]ᵀ (fields k..), each summed over channels. Eq. 6 penalises
    Ψ(s_g² + γ s_d²); with separate penalties, Ψ(s_g²) + γ Ψ(s_d²). Also carries the data weight
    ρ = r · Ω1 · [warped position inside the image]. Fields have the layout of the pixels they were
    computed for ((H, W), or (4, H/2, W/2) in the solver).
    """

    j11: jax.Array
    j12: jax.Array
    j22: jax.Array
    j13: jax.Array
    j23: jax.Array
    j33: jax.Array
    k11: jax.Array
    k12: jax.Array
    k22: jax.Array
    k13: jax.Array
    k23: jax.Array
    k33: jax.Array
    rho: jax.Array


def default_beta(params: FlowEnergyParams) -> float:
    """β of eq. 8: 3 for robust smoothness, 12 for quadratic."""
    return 3.0 if params.robust_smoothness else 12.0


def prepare_image(img: ArrayLike, sigma: float, dtype: DTypeLike = jnp.float32) -> jax.Array:
    """(H, W) or (H, W, C) image → float (H, W, C), pre-smoothed with Gaussian σ (static)."""
    img = jnp.asarray(img)
    img = img[..., None] if img.ndim == 2 else img
    return gaussian_blur(img.astype(dtype), sigma)


def _replicate_beyond(a: jax.Array, size) -> jax.Array:
    """(H, W, ...) a with the rows ≥ h and columns ≥ w replaced by copies of row h − 1 and column w − 1:
    the top-left (h, w) part edge-replicated over the rest (`size` = (h, w), may be traced)."""
    rows = jnp.minimum(jnp.arange(a.shape[0]), size[0] - 1)
    cols = jnp.minimum(jnp.arange(a.shape[1]), size[1] - 1)
    return jnp.take(jnp.take(a, rows, axis=0), cols, axis=1)


def derivative_stack(img2: jax.Array, size=None) -> jax.Array:
    """[I2, ∂x I2, ∂y I2, ∂xx I2, ∂xy I2, ∂yy I2] on I2's grid (5-point stencil), (H, W, 6C).

    With `size` = (h, w) only the top-left h x w part is the image and the rest edge-replicates it (a
    padded pyramid level): the first derivatives are replicated the same way before the second, so the
    stack on the image part equals that of the unpadded image."""
    g2x, g2y = image_gradients(img2)
    if size is not None:
        g2x, g2y = _replicate_beyond(g2x, size), _replicate_beyond(g2y, size)
    g2xx, g2xy = image_gradients(g2x)
    g2yx, g2yy = image_gradients(g2y)
    return jnp.concatenate([img2, g2x, g2y, g2xx, 0.5 * (g2xy + g2yx), g2yy], -1)


def _tensor(warped, inside, i1_stack, data_weight, region) -> MotionTensor:
    """Motion tensors from the warped derivative stack (..., 6C) and [I1, ∂x I1, ∂y I1] (..., 3C).

    The sums over colour channels are written out channel by channel: XLA:CPU turns a reduction over a
    minor axis of 3 into a slow strided loop (measured 2x slower for the whole tensor at 96x128x3).
    """
    c = i1_stack.shape[-1] // 3
    grey, grad = [0.0] * 6, [0.0] * 6
    for j in range(c):
        i2, ix, iy, ixx, ixy, iyy = (warped[..., k * c + j] for k in range(6))
        i1, g1x, g1y = (i1_stack[..., k * c + j] for k in range(3))
        iz, ixz, iyz = i2 - i1, ix - g1x, iy - g1y
        terms_grey = (ix * ix, ix * iy, iy * iy, ix * iz, iy * iz, iz * iz)
        terms_grad = (
            ixx * ixx + ixy * ixy,
            ixx * ixy + ixy * iyy,
            ixy * ixy + iyy * iyy,
            ixx * ixz + ixy * iyz,
            ixy * ixz + iyy * iyz,
            ixz * ixz + iyz * iyz,
        )
        grey = [a + t for a, t in zip(grey, terms_grey)]
        grad = [a + t for a, t in zip(grad, terms_grad)]
    rho = jnp.where(region & inside, data_weight, 0.0).astype(i1_stack.dtype)
    return MotionTensor(*grey, *grad, rho)


def motion_tensor(
    flow: jax.Array, img1: jax.Array, img2: jax.Array, data_weight: jax.Array, region: jax.Array
) -> MotionTensor:
    """Linearise the data term of eq. 6 around `flow` (the outer fixed point's linearisation).

    I2, ∂xI2, ∂yI2 and the second derivatives are taken on I2's grid (5-point stencil) and then
    warped bilinearly by `flow`; the increment's coefficients are the warped first derivatives (grey
    value constancy) and the warped Hessian (gradient constancy).

    Args:
        flow: (H, W, 2) current flow.
        img1, img2: (H, W, C) float images.
        data_weight: (H, W) r(x); region: (H, W) bool Ω1.

    Returns:
        `MotionTensor` with (H, W) fields.
    """
    g1x, g1y = image_gradients(img1)
    warped, inside = warp_bilinear(derivative_stack(img2), flow)
    return _tensor(warped, inside, jnp.concatenate([img1, g1x, g1y], -1), data_weight, region)


def _quadratic(J: MotionTensor, du, dv, grey: bool):
    """s_g² (grey=True) or s_d² of the linearised data term at the increment (du, dv)."""
    a11, a12, a22, a13, a23, a33 = J[:6] if grey else J[6:12]
    return a11 * du * du + 2 * a12 * du * dv + a22 * dv * dv + 2 * a13 * du + 2 * a23 * dv + a33


def _data_weights(J: MotionTensor, du, dv, params: FlowEnergyParams):
    """(Ψ-weight of the grey tensor, Ψ-weight of the gradient tensor) at (du, dv), ρ included.

    The data term's gradient in (du, dv) is 2 (w_g J + w_d K)[du dv 1]ᵀ: the lagged-nonlinearity
    weights. Ψ'(s²) = 1 / (2 sqrt(s² + ε²)).
    """
    eps2 = params.epsilon**2
    sg = jnp.maximum(_quadratic(J, du, dv, True), 0.0)
    sd = jnp.maximum(_quadratic(J, du, dv, False), 0.0)
    if params.separate_penalties:
        wg = J.rho * 0.5 / jnp.sqrt(sg + eps2)
        wd = params.gamma * J.rho * 0.5 / jnp.sqrt(sd + eps2)
    else:
        wg = J.rho * 0.5 / jnp.sqrt(sg + params.gamma * sd + eps2)
        wd = params.gamma * wg
    return wg, wd


def _data_energy(J: MotionTensor, du, dv, params: FlowEnergyParams):
    """ρ Ψ(...) of the linearised data term per pixel."""
    eps2 = params.epsilon**2
    sg = jnp.maximum(_quadratic(J, du, dv, True), 0.0)
    sd = jnp.maximum(_quadratic(J, du, dv, False), 0.0)
    if params.separate_penalties:
        return J.rho * (jnp.sqrt(sg + eps2) + params.gamma * jnp.sqrt(sd + eps2))
    return J.rho * jnp.sqrt(sg + params.gamma * sd + eps2)


def linearised_flow_energy(
    dflow: jax.Array,
    flow: jax.Array,
    img1: jax.Array,
    img2: jax.Array,
    params: FlowEnergyParams,
    data_weight: ArrayLike | None = None,
    region: ArrayLike | None = None,
) -> jax.Array:
    """Eq. 6 with the data term linearised around `flow` (what one warp of the solver minimises).

    E_lin(dw) = Σ ρ Ψ(s_g² + γ s_d²) + α Σ Ψ2(|∇(w + dw)|²) (or the separate-penalty form), the s² from
    `motion_tensor`. At dw = 0 it equals
    `flow_energy(flow, ...)`.

    Args:
        dflow, flow: (H, W, 2) increment and the linearisation point.
        img1, img2: (H, W) or (H, W, C) float images (already pre-smoothed, if the solver smooths).
    """
    img1 = img1[..., None] if img1.ndim == 2 else img1
    img2 = img2[..., None] if img2.ndim == 2 else img2
    r, in_region = weight_and_region(img1.shape[:2], data_weight, region, flow.dtype)
    J = motion_tensor(flow, img1.astype(flow.dtype), img2.astype(flow.dtype), r, in_region)
    eps2 = params.epsilon**2
    data = _data_energy(J, dflow[..., 0], dflow[..., 1], params)
    in_x, in_y = in_region & kp(in_region), in_region & ip(in_region)
    W = flow + dflow
    g = smoothness_s2(W[..., 0], W[..., 1], in_x, in_y)
    smooth = jnp.sqrt(g + eps2) if params.robust_smoothness else g
    return jnp.sum(data) + params.alpha * jnp.sum(jnp.where(in_region, smooth, 0.0))


def _solve_increment(J: MotionTensor, u, v, region, params: FlowEnergyParams, config: FlowConfig):
    """Minimise the linearised energy over (du, dv): lagged nonlinearity + red-black coupled SOR.

    All fields are in the parity layout (4, H/2, W/2) of `_quarters`, so a half-sweep updates the
    red (A, D) or black (B, C) sub-grids only, with no masked select.

    Returns:
        (du, dv), each (4, H/2, W/2).
    """
    dtype = u.dtype
    eps2 = params.epsilon**2
    alpha = params.alpha
    in_x, in_y = region & q_right(region), region & q_down(region)
    relax = jnp.asarray(config.sor_relaxation, dtype)

    def inner(_, carry):
        du, dv = carry
        # Frozen robust weights (the lagged nonlinearity).
        wg, wd = _data_weights(J, du, dv, params)
        if params.robust_smoothness:
            psi = 0.5 / jnp.sqrt(smoothness_s2(u + du, v + dv, in_x, in_y, q_right, q_down) + eps2)
        else:
            psi = jnp.ones_like(u)
        a_e = jnp.where(in_x, alpha * psi, 0.0)  # weight of edge (p, p+x)
        a_s = jnp.where(in_y, alpha * psi, 0.0)  # weight of edge (p, p+y)
        a_w, a_n = q_left(a_e), q_up(a_s)
        a_sum = a_e + a_w + a_s + a_n
        a11 = wg * J.j11 + wd * J.k11 + a_sum
        a12 = wg * J.j12 + wd * J.k12
        a22 = wg * J.j22 + wd * J.k22 + a_sum
        det = a11 * a22 - a12 * a12
        # Pixels without any term (outside Ω1) get a zero block inverse and keep du = 0.
        ok = det > 1e-9 * (a11 * a22 + 1e-30)
        inv_det = jnp.where(ok, 1.0 / jnp.where(ok, det, 1.0), 0.0)
        # The 2x2 block inverse per pixel, and the constant part of the right-hand side:
        # −ρΨ' J_{·3} + α div(ψ ∇w) at the base flow.
        m11, m12, m22 = a22 * inv_det, -a12 * inv_det, a11 * inv_det
        nb = lambda a: a_e * q_right(a) + a_w * q_left(a) + a_s * q_down(a) + a_n * q_up(a)
        cu = -(wg * J.j13 + wd * J.k13) + nb(u) - a_sum * u
        cv = -(wg * J.j23 + wd * J.k23) + nb(v) - a_sum * v
        coef = [tuple(x[q] for x in (m11, m12, m22, cu, cv, a_e, a_w, a_s, a_n)) for q in range(4)]

        def update(x_u, x_v, c, nbr_u, nbr_v):
            m11, m12, m22, cu, cv, we, ww, ws, wn = c
            bu = cu + we * nbr_u[0] + ww * nbr_u[1] + ws * nbr_u[2] + wn * nbr_u[3]
            bv = cv + we * nbr_v[0] + ww * nbr_v[1] + ws * nbr_v[2] + wn * nbr_v[3]
            return x_u + relax * (m11 * bu + m12 * bv - x_u), x_v + relax * (m12 * bu + m22 * bv - x_v)

        # Neighbours (right, left, down, up) of each sub-grid in terms of the other colour's sub-grids.
        def nbr_a(b, c):
            return (b, km(b), c, im(c))

        def nbr_d(b, c):
            return (kp(c), c, ip(b), b)

        def nbr_b(a, d):
            return (kp(a), a, d, im(d))

        def nbr_c(a, d):
            return (d, km(d), ip(a), a)

        def sweep(_, s):
            (au, bu, cu_, du_), (av, bv, cv_, dv_) = s
            au, av = update(au, av, coef[0], nbr_a(bu, cu_), nbr_a(bv, cv_))
            du_, dv_ = update(du_, dv_, coef[3], nbr_d(bu, cu_), nbr_d(bv, cv_))
            bu, bv = update(bu, bv, coef[1], nbr_b(au, du_), nbr_b(av, dv_))
            cu_, cv_ = update(cu_, cv_, coef[2], nbr_c(au, du_), nbr_c(av, dv_))
            return (au, bu, cu_, du_), (av, bv, cv_, dv_)

        qu, qv = jax.lax.fori_loop(0, config.sor_iters, sweep, (tuple(du), tuple(dv)))
        return jnp.stack(qu), jnp.stack(qv)

    zero = jnp.zeros_like(u)
    return jax.lax.fori_loop(0, config.lagged, inner, (zero, zero))


def median_filter_flow(flow: jax.Array, region: jax.Array, size: int = 3) -> jax.Array:
    """Median of each flow component over a size x size window (size 3 or 5), inside Ω1, (H, W, 2).

    Window pixels outside Ω1 (or beyond the border) take the centre pixel's value, so the filter
    neither pulls the flow towards the zeros outside the region nor across its boundary; see
    `jaxtrack.image.median_filter`.
    """
    return median_filter(flow, size, region)


def _level(flow, img1, img2, r, region, params, config: FlowConfig, warps: int, size=None):
    """`warps` outer fixed-point iterations at one pyramid level (H, W even); returns (H, W, 2) flow.

    Per-pixel fields live in the parity layout for the whole level; warping samples the full-layout
    derivative stack of I2 directly at the parity-ordered positions, so no per-warp relayout is needed.
    With `size` = (h, w) (traced) the level is the top-left h x w of padded arrays: images edge-
    replicated beyond it, r = 0 and Ω1 false there; warping samples within it.
    """
    h, w = img1.shape[:2]
    dtype = img1.dtype
    stack2 = derivative_stack(img2, size)
    g1x, g1y = image_gradients(img1)
    i1q = to_quarters(jnp.concatenate([img1, g1x, g1y], -1))
    rq, regq = to_quarters(r), to_quarters(region)
    gy, gx = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    xq, yq = to_quarters(jnp.asarray(gx, dtype)), to_quarters(jnp.asarray(gy, dtype))

    def outer(_, fq):
        warped, inside = sample_bilinear(stack2, xq + fq[..., 0], yq + fq[..., 1], size)
        J = _tensor(warped, inside, i1q, rq, regq)
        du, dv = _solve_increment(J, fq[..., 0], fq[..., 1], regq, params, config)
        fq = fq + jnp.stack([du, dv], -1)
        if config.median and config.median_every_warp:
            fq = to_quarters(median_filter_flow(from_quarters(fq), region, config.median))
        return fq

    flow = from_quarters(jax.lax.fori_loop(0, warps, outer, to_quarters(flow)))
    if config.median and not config.median_every_warp:
        flow = median_filter_flow(flow, region, config.median)
    return flow


def _pad_to(a: jax.Array, shape: tuple[int, int], fill) -> jax.Array:
    """Pad (h, w, ...) at the bottom/right to `shape`: edge-replicated (fill None) or with `fill`."""
    pad = [(0, shape[0] - a.shape[0]), (0, shape[1] - a.shape[1])] + [(0, 0)] * (a.ndim - 2)
    return jnp.pad(a, pad, mode="edge") if fill is None else jnp.pad(a, pad, constant_values=fill)


def _resize_flow_within(flow: jax.Array, src, dst) -> jax.Array:
    """`upsample_flow` between sizes given as data: the top-left `src` = (h, w) part of an (H, W, 2) flow
    resampled (bilinear, pixel centres aligned, border clamped: `resize_bilinear`'s rule) onto the top-left
    `dst` part and rescaled to its pixel units. Pixels beyond `dst` get clamped copies (they are padding)."""
    dtype = flow.dtype

    def taps(n_grid, n_in, n_out):
        i = jnp.arange(n_grid, dtype=dtype)
        pos = jnp.clip((i + 0.5) * (n_in.astype(dtype) / n_out.astype(dtype)) - 0.5, 0.0, (n_in - 1).astype(dtype))
        i0 = jnp.minimum(jnp.floor(pos).astype(jnp.int32), jnp.maximum(n_in - 2, 0))
        return i0, jnp.minimum(i0 + 1, n_in - 1), pos - i0.astype(dtype)

    r0, r1, fr = taps(flow.shape[0], src[0], dst[0])
    c0, c1, fc = taps(flow.shape[1], src[1], dst[1])
    rows = jnp.take(flow, r0, axis=0) * (1 - fr)[:, None, None] + jnp.take(flow, r1, axis=0) * fr[:, None, None]
    out = jnp.take(rows, c0, axis=1) * (1 - fc)[None, :, None] + jnp.take(rows, c1, axis=1) * fc[None, :, None]
    scale = jnp.stack([dst[1].astype(dtype) / src[1].astype(dtype), dst[0].astype(dtype) / src[0].astype(dtype)])
    return out * scale


def _shared_levels(flow, shapes, i1s, i2s, rs, oms, params, config: FlowConfig):
    """Pyramid levels shapes[0] (the finest of them) ... shapes[-1] (the coarsest), coarse to fine, as one
    compiled level in a `lax.fori_loop`: each level padded to shapes[0] (frames edge-replicated, r = 0 and
    Ω1 false beyond it) with its true size as data (`_level(size=)`).

    Args:
        flow: (shapes[-1] + (2,)) the start flow at the coarsest of these levels.
        i1s, i2s, rs, oms: per level (finest first) the frames (h, w, C), r (h, w, 1) and Ω1's fraction (h, w, 1).

    Returns:
        (shapes[0] + (2,)) the flow at the finest of these levels.
    """
    grid = shapes[0]
    order = range(len(shapes) - 1, -1, -1)  # coarse to fine
    img1 = jnp.stack([_pad_to(i1s[k], grid, None) for k in order])
    img2 = jnp.stack([_pad_to(i2s[k], grid, None) for k in order])
    r = jnp.stack([_pad_to(rs[k][..., 0], grid, 0.0) for k in order])
    region = jnp.stack([_pad_to(oms[k][..., 0] > 0.5, grid, False) for k in order])
    sizes = jnp.asarray([shapes[k] for k in order], jnp.int32)  # (L, 2)

    def level(j, flow):
        size = sizes[j]
        flow = _resize_flow_within(flow, sizes[jnp.maximum(j - 1, 0)], size)  # the identity at j = 0
        return _level(flow, img1[j], img2[j], r[j], region[j], params, config, config.warps, (size[0], size[1]))

    return jax.lax.fori_loop(0, len(shapes), level, _pad_to(flow, grid, 0.0))


def _compute_flow(inputs: FlowInputs, config: FlowConfig, record: bool = False):
    """Coarse-to-fine loop over the pyramid; `inputs` padded to even sides (`FlowInputs.padded_even`).

    Returns the (H, W, 2) flow (zero outside Ω1); with `record`, also the energies per level (L, 2) (every
    level unrolled then, whatever `config.shared_levels_from`).
    """
    img1, img2, params, region = inputs.img1, inputs.img2, inputs.params, inputs.region
    h, w = img1.shape[:2]
    dtype = img1.dtype
    shapes = pyramid_shapes(h, w, config.eta, min(config.min_size, h, w), config.max_levels)
    # The four pyramids (I1, I2, r, Ω1's fraction) as the channels of one array: one blur and resample per level
    # (the blur is per channel), a quarter of the compiled pyramid code.
    c = img1.shape[-1]
    levels = [jnp.concatenate([img1, img2, inputs.data_weight[..., None], region[..., None].astype(dtype)], -1)]
    for shape in shapes[1:]:
        levels.append(downsample(levels[-1], shape, config.eta))
    i1s = [img1] + [a[..., :c] for a in levels[1:]]
    i2s = [img2] + [a[..., c:2 * c] for a in levels[1:]]
    rs = [a[..., 2 * c:2 * c + 1] for a in levels]
    oms = [a[..., 2 * c + 1:] for a in levels]
    ch, cw = shapes[-1]
    init_flow = inputs.init_flow
    flow = jnp.zeros((ch, cw, 2), dtype) if init_flow is None else upsample_flow(init_flow, (ch, cw))
    energies = []
    finest_unrolled = len(shapes) - 1
    shared = config.shared_levels_from
    if not record and 1 <= shared < len(shapes) - 1:  # two or more coarse levels share one compiled level
        flow = _shared_levels(flow, shapes[shared:], i1s[shared:], i2s[shared:], rs[shared:], oms[shared:], params, config)
        finest_unrolled = shared - 1
    for k in range(finest_unrolled, -1, -1):
        if flow.shape[:2] != shapes[k]:
            flow = upsample_flow(flow, shapes[k])
        # Level 0 uses Ω1 exactly; coarser levels keep pixels that are mostly inside.
        om = region if k == 0 else oms[k][..., 0] > 0.5
        warps = config.warps + (config.finest_warps if k == 0 else 0)
        flow_in = flow
        flow = _level(flow, i1s[k], i2s[k], rs[k][..., 0], om, params, config, warps)
        if record:
            e = [flow_energy(f, i1s[k], i2s[k], params, rs[k][..., 0], om) for f in (flow_in, flow)]
            energies.append(jnp.stack(e))
    flow = jnp.where(region[..., None], flow, 0.0)
    if record:
        return flow, jnp.stack(energies[::-1])
    return flow


def _first_nonfinite(a) -> tuple[int, tuple[int, ...]]:
    """Host: number of non-finite entries of `a` and the (row, column) of the first one."""
    bad = ~np.isfinite(np.asarray(a))
    if bad.ndim > 2:  # channels / flow components: a pixel is bad if any of its values is
        bad = bad.reshape(bad.shape[:2] + (-1,)).any(-1)
    count = int(bad.sum())
    return count, (tuple(int(i) for i in np.argwhere(bad)[0]) if count else ())


def _is_concrete(a) -> bool:
    return a is not None and not isinstance(a, jax.core.Tracer)


def check_flow_inputs(
    img1: ArrayLike,
    img2: ArrayLike,
    data_weight: ArrayLike | None = None,
    region: ArrayLike | None = None,
    init_flow: ArrayLike | None = None,
    where: str = "compute_flow",
) -> None:
    """The API edge: raise ValueError naming the argument for wrong shapes or non-finite values.

    Shapes are always checked; values only when concrete (not under an outer `jit`, where the same
    problems come back as `FlowResult.status` = INVALID_INPUT instead).
    """
    img1, img2 = jnp.asarray(img1), jnp.asarray(img2)
    if img1.ndim not in (2, 3) or img1.shape != img2.shape:
        raise ValueError(
            f"{where}: frames must be (H, W) or (H, W, C) of the same shape, got {img1.shape} and {img2.shape}"
        )
    if min(img1.shape[:2]) < 4:
        raise ValueError(f"{where}: frames must be at least 4x4 pixels, got {img1.shape[:2]}")
    hw = img1.shape[:2]
    for name, a, extra in (("data_weight", data_weight, ()), ("region", region, ()), ("init_flow", init_flow, (2,))):
        if a is not None and tuple(jnp.shape(a)) != hw + extra:
            raise ValueError(f"{where}: {name} must have shape {hw + extra}, got {tuple(jnp.shape(a))}")
    for name, a in (("img1", img1), ("img2", img2), ("data_weight", data_weight), ("init_flow", init_flow)):
        if _is_concrete(a):
            count, first = _first_nonfinite(a)
            if count:
                what = "pixel(s)" if name.startswith("img") else "value(s)"
                raise ValueError(f"{where}: {name} has {count} non-finite {what}, first at (y, x) = {first}")


def check_flow_params(params: FlowEnergyParams, where: str = "compute_flow") -> None:
    """The API edge: raise ValueError unless α ≥ 0, γ ≥ 0 and ε > 0 (all finite), when concrete."""
    domains = (("alpha", params.alpha, False), ("gamma", params.gamma, False), ("epsilon", params.epsilon, True))
    for name, value, strict in domains:
        if not _is_concrete(value):
            continue
        v = np.asarray(value, np.float64)
        ok = np.isfinite(v) & ((v > 0) if strict else (v >= 0))
        if not np.all(ok):
            bound = "> 0" if strict else "≥ 0"
            raise ValueError(f"{where}: params.{name} must be finite and {bound}, got {v[~ok].reshape(-1)[0]:g}")


def weight_and_region(
    shape: tuple[int, int], data_weight: ArrayLike | None, region: ArrayLike | None, dtype: DTypeLike
) -> tuple[jax.Array, jax.Array]:
    """r(x) (default 1) and Ω1 (default: the whole image) as (H, W) arrays of `dtype` and bool."""
    r = jnp.ones(shape, dtype) if data_weight is None else jnp.asarray(data_weight, dtype)
    om = jnp.ones(shape, bool) if region is None else jnp.asarray(region, bool)
    return r, om


def _pad_even(a, fill):
    """Pad rows/columns at the bottom/right so both sides are even (edge-replicated or `fill`)."""
    if a is None:
        return None
    h, w = a.shape[:2]
    return _pad_to(a, (h + h % 2, w + w % 2), fill)


class FlowInputs(eqx.Module):
    """The minimiser's inputs after `prepare_inputs`: validated values, named fields.

    Non-finite input values and out-of-domain parameters are replaced by safe ones (0 for pixels,
    weights and start flows; α = γ = 0, ε = 0.001) so that nothing NaN enters the solver, and
    flagged in `status`; the caller then returns zeros with that status.

    Attributes:
        img1, img2: (H, W, C) pre-smoothed float frames.
        data_weight: (H, W) r(x) clipped to [0, 1].
        region: (H, W) bool Ω1.
        init_flow: (H, W, 2) flow to start from, or None (start from zero).
        params: the parameters of eq. 6 as used.
        status: int32 `Status.INVALID_INPUT` if anything was replaced, else OK.
    """

    img1: jax.Array
    img2: jax.Array
    data_weight: jax.Array
    region: jax.Array
    init_flow: jax.Array | None
    params: FlowEnergyParams
    status: jax.Array

    def padded_even(self) -> FlowInputs:
        """The same inputs padded at the bottom/right to even sides (the parity layout needs them):
        frames and start flow edge-replicated, the padding outside Ω1 and with r = 0."""
        return FlowInputs(
            _pad_even(self.img1, None),
            _pad_even(self.img2, None),
            _pad_even(self.data_weight, 0.0),
            _pad_even(self.region, False),
            _pad_even(self.init_flow, None),
            self.params,
            self.status,
        )


def _finite_or_zero(a):
    ok = jnp.isfinite(a)
    return jnp.where(ok, a, jnp.zeros((), a.dtype)), jnp.all(ok)


def _safe_params(params: FlowEnergyParams):
    """Parameters with out-of-domain values replaced (α, γ → 0, ε → 0.001) and whether all were valid."""
    alpha, gamma, eps = (jnp.asarray(v) for v in (params.alpha, params.gamma, params.epsilon))
    ok_a = jnp.isfinite(alpha) & (alpha >= 0)
    ok_g = jnp.isfinite(gamma) & (gamma >= 0)
    ok_e = jnp.isfinite(eps) & (eps > 0)
    safe = FlowEnergyParams(
        jnp.where(ok_a, alpha, 0.0),
        jnp.where(ok_g, gamma, 0.0),
        jnp.where(ok_e, eps, 1e-3),
        params.robust_smoothness,
        params.separate_penalties,
    )
    return safe, ok_a & ok_g & ok_e


def prepare_inputs(
    img1: ArrayLike,
    img2: ArrayLike,
    params: FlowEnergyParams,
    config: FlowConfig,
    data_weight: ArrayLike,
    region: ArrayLike,
    init_flow: ArrayLike | None,
    dtype: DTypeLike,
) -> FlowInputs:
    """Validate and prepare the solver's inputs (traceable): float frames pre-smoothed with
    `config.presmooth_sigma`, r clipped to [0, 1], Ω1 as bool; non-finite values and out-of-domain
    parameters replaced and flagged (`FlowInputs.status` = INVALID_INPUT)."""
    frames = []
    ok = jnp.asarray(True)
    for img in (img1, img2):
        img = jnp.asarray(img)
        img = (img[..., None] if img.ndim == 2 else img).astype(dtype)
        img, finite = _finite_or_zero(img)  # before the blur, which would spread a NaN
        ok = ok & finite
        frames.append(gaussian_blur(img, config.presmooth_sigma))
    r, finite = _finite_or_zero(jnp.asarray(data_weight, dtype))
    ok = ok & finite
    init = None
    if init_flow is not None:
        init, finite = _finite_or_zero(jnp.asarray(init_flow, dtype))
        ok = ok & finite
    safe, params_ok = _safe_params(params)
    status = status_where(ok & params_ok, Status.OK, Status.INVALID_INPUT)
    return FlowInputs(frames[0], frames[1], jnp.clip(r, 0.0, 1.0), jnp.asarray(region, bool), init, safe, status)


def _nonfinite_status(*arrays):
    finite = jnp.asarray(True)
    for a in arrays:
        finite = finite & jnp.all(jnp.isfinite(a))
    return status_where(finite, Status.OK, Status.NONFINITE)


def flow_core(
    img1: ArrayLike,
    img2: ArrayLike,
    params: FlowEnergyParams,
    config: FlowConfig,
    data_weight: ArrayLike,
    region: ArrayLike,
    init_flow: ArrayLike | None,
    beta: ArrayLike,
    dtype: DTypeLike,
) -> FlowResult:
    """The traceable body of `compute_flow` (no host checks; all optional inputs given as arrays).

    Args:
        img1, img2: (H, W) or (H, W, C) frames; data_weight (H, W) float; region (H, W) bool;
        init_flow (H, W, 2) or None; beta scalar.

    Returns:
        `FlowResult`; on a failure (status INVALID_INPUT or NONFINITE) flow, energy and confidence are
        zeros.
    """
    inputs = prepare_inputs(img1, img2, params, config, data_weight, region, init_flow, dtype)
    h, w = inputs.img1.shape[:2]
    flow = _compute_flow(inputs.padded_even(), config)[:h, :w]
    om = inputs.region
    e = jnp.where(om, local_flow_energy(flow, inputs.img1, inputs.img2, inputs.params, inputs.data_weight, om), 0.0)
    conf = jnp.where(om, beta / (1.0 + e), 0.0)
    # The cause before its consequence: invalid input usually also makes the solution non-finite.
    status = first_failure(inputs.status, _nonfinite_status(flow, e, conf))
    ok = status == Status.OK
    zero = lambda a: jnp.where(ok, a, jnp.zeros((), a.dtype))
    return FlowResult(zero(flow), zero(e), zero(conf), om, status)


def checked_result(result: eqx.Module, throw: bool, context: str):
    """Pass `result.status` through `check_status` (raises for a failure when `throw`)."""
    return eqx.tree_at(lambda r: r.status, result, check_status(result.status, throw, context))


@eqx.debug.assert_max_traces(max_traces=None)  # counts traces (`eqx.debug.get_num_traces`), never fails
def _compute_flow_body(img1, img2, params, config, data_weight, region, init_flow, beta, dtype):
    r, om = weight_and_region(img1.shape[:2], data_weight, region, dtype)
    return flow_core(img1, img2, params, config, r, om, init_flow, beta, dtype)


_compute_flow_jit = eqx.filter_jit(_compute_flow_body)


@eqx.filter_jit
def _level_energies_jit(img1, img2, params, config, data_weight, region, dtype):
    inputs = prepare_inputs(img1, img2, params, config, data_weight, region, None, dtype)
    return _compute_flow(inputs.padded_even(), config, record=True)[1]


@eqx.filter_jit
def _refine_jit(flow, img1, img2, params, config, data_weight, region, dtype):
    inputs = prepare_inputs(img1, img2, params, config, data_weight, region, flow, dtype)
    even = inputs.padded_even()
    h, w = inputs.img1.shape[:2]
    out = _level(even.init_flow, even.img1, even.img2, even.data_weight, even.region, even.params, config, config.warps)
    out = jnp.where(inputs.region[..., None], out[:h, :w], inputs.init_flow)
    status = first_failure(inputs.status, _nonfinite_status(out))
    return jnp.where(status == Status.OK, out, jnp.zeros((), out.dtype)), status


def refine_flow(
    flow: ArrayLike,
    img1: ArrayLike,
    img2: ArrayLike,
    params: FlowEnergyParams,
    config: FlowConfig | None = None,
    data_weight: ArrayLike | None = None,
    region: ArrayLike | None = None,
    dtype: DTypeLike = jnp.float32,
    throw: bool = True,
) -> jax.Array:
    """`config.warps` warps at full resolution only, starting from `flow` (no pyramid), (H, W, 2).

    For a flow that is already close (a prediction from the previous pose, or a coarse solution).
    With warps = 1 it returns w + dw, dw the minimiser of `linearised_flow_energy(·, w, ...)`
    found by the lagged-nonlinearity / SOR iterations.

    Raises:
        ValueError: wrong shapes, non-finite values in `flow`, the frames or `data_weight`, or
            parameters outside their domain (α ≥ 0, γ ≥ 0, ε > 0).
        StatusError: with `throw`, when the result is not finite (else the flow comes back as zeros).
    """
    config = FlowConfig() if config is None else config
    check_flow_inputs(img1, img2, data_weight, region, flow, where="refine_flow")
    check_flow_params(params, where="refine_flow")
    r, om = weight_and_region(jnp.shape(img1)[:2], data_weight, region, dtype)
    out, status = _refine_jit(
        jnp.asarray(flow, dtype), jnp.asarray(img1), jnp.asarray(img2), params, config, r, om, dtype
    )
    if throw and isinstance(status, jax.core.Tracer):  # under an outer jit: a runtime error of the program
        return eqx.error_if(out, ~is_usable(status), "refine_flow: unusable status (see jaxtrack.Status)")
    check_status(status, throw, "refine_flow")
    return out


def flow_level_energies(
    img1: ArrayLike,
    img2: ArrayLike,
    params: FlowEnergyParams,
    config: FlowConfig | None = None,
    data_weight: ArrayLike | None = None,
    region: ArrayLike | None = None,
    dtype: DTypeLike = jnp.float32,
) -> jax.Array:
    """Diagnostic: eq. 6 per pyramid level before and after that level's warps, (L, 2), finest first.

    Row k holds E_k(flow entering level k) and E_k(flow leaving it), each evaluated on level k's
    images, r and Ω1 (so rows are comparable only within themselves).
    """
    config = FlowConfig() if config is None else config
    check_flow_inputs(img1, img2, data_weight, region, where="flow_level_energies")
    check_flow_params(params, where="flow_level_energies")
    r, om = weight_and_region(jnp.shape(img1)[:2], data_weight, region, dtype)
    return _level_energies_jit(jnp.asarray(img1), jnp.asarray(img2), params, config, r, om, dtype)


def compute_flow(
    img1: ArrayLike,
    img2: ArrayLike,
    params: FlowEnergyParams,
    config: FlowConfig | None = None,
    data_weight: ArrayLike | None = None,
    region: ArrayLike | None = None,
    init_flow: ArrayLike | None = None,
    beta: ArrayLike | None = None,
    dtype: DTypeLike = jnp.float32,
    throw: bool = True,
) -> FlowResult:
    """Dense flow from img1 to img2 minimising eq. 6 inside Ω1 (Brox et al. 2004 numerics).

    Jit-compiled; frames of the same shape (and the same config and optional arguments present)
    compile once. The parameters of eq. 6 are arrays, so sweeping α or γ does not recompile.

    Args:
        img1, img2: (H, W) or (H, W, C) frames on the 0-255 scale (any real or integer dtype).
        params: α, γ, ε and the smoothness type (`articulated_params()`, `rigid_params()`).
        config: the minimiser's static settings (default `FlowConfig()`).
        data_weight: optional (H, W) r(x) ∈ [0, 1]; 0 switches the data term off (occluded pixels),
            whose flow is then filled in by the smoothness term.
        region: optional (H, W) bool Ω1; the energy is integrated inside it only (default: the whole
            image, which is plain Brox et al. 2004 flow).
        init_flow: optional (H, W, 2) flow to start from (e.g. predicted by the previous pose).
        beta: β of eq. 8 (default 3 robust / 12 quadratic).
        dtype: float type of the computation.
        throw: raise `StatusError` when `FlowResult.status` is a failure (else return it with zeros).

    Returns:
        `FlowResult` with the flow, the local energy, the confidence of eq. 8 and a status.

    Raises:
        ValueError: naming the argument: wrong shapes, non-finite pixels/weights/start flow, or
            parameters outside their domain (α ≥ 0, γ ≥ 0, ε > 0), checked when concrete.
    """
    config = FlowConfig() if config is None else config
    check_flow_inputs(img1, img2, data_weight, region, init_flow, where="compute_flow")
    check_flow_params(params, where="compute_flow")
    beta = default_beta(params) if beta is None else beta
    # Defaults materialised and frames cast here, at the edge: calls with and without r(x), Ω1 or a start
    # flow, and frames of any input dtype, then share one compiled program per frame shape (a zero start
    # flow is the solver's own start). The test suite compiled this solver once per combination.
    shape = tuple(jnp.shape(img1)[:2])
    r, om = weight_and_region(shape, data_weight, region, dtype)
    init = jnp.zeros(shape + (2,), dtype) if init_flow is None else jnp.asarray(init_flow, dtype)
    res = _compute_flow_jit(jnp.asarray(img1, dtype), jnp.asarray(img2, dtype), params, config, r, om, init,
                            jnp.asarray(beta, dtype), dtype)
    return checked_result(res, throw, "compute_flow")
