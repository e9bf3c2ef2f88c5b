"""The variational optical-flow energy of Brox et al. 2004 restricted to the object region (eq. 6).

    E(u, v) = ∫_Ω1 r(x) Ψ(Σ_c |I2_c(x + w) − I1_c(x)|² + γ |∇I2_c(x + w) − ∇I1_c(x)|²) dx
              + α ∫_Ω1 Ψ2(|∇u|² + |∇v|²) dx,            Ψ(s²) = sqrt(s² + ε²)

with r(x) ∈ [0, 1] the occlusion weight (0 = occluded), Ω1 the object region, Ψ2 = Ψ (robust, α = 50,
articulated) or Ψ2(s²) = s² (quadratic, α = 800, rigid). Colour channels are summed inside Ψ.
I2 and ∇I2 are warped bilinearly; pixels whose warped position leaves the image carry no data term.
Image gradients use the 5-point stencil (`jaxtrack.image.image_gradients`), flow gradients forward
differences; a smoothness term counts only where both of its pixels lie in Ω1.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

from ..._device import to_device
from ...image import as_channels as _channels
from ...image import image_gradients, warp_bilinear
from ._quarters import ip, kp


class FlowEnergyParams(eqx.Module):
    """Parameters of eq. 6 (arrays, so sweeping or differentiating them does not recompile).

    Attributes:
        alpha: smoothness weight α.
        gamma: gradient-constancy weight γ.
        epsilon: ε of Ψ(s²) = sqrt(s² + ε²).
        robust_smoothness: Ψ2 = Ψ if True, quadratic otherwise (static: it changes the function).
        separate_penalties: False (the paper's eq. 6): one Ψ over grey + γ·gradient terms;
            True: Ψ(grey) + γ Ψ(gradient), robustified separately (Bruhn and Weickert, ICCV 2005),
            so an outlier in one constancy assumption does not switch off the other (static).
    """

    alpha: jax.Array
    gamma: jax.Array
    epsilon: jax.Array
    robust_smoothness: bool = eqx.field(static=True, default=True)
    separate_penalties: bool = eqx.field(static=True, default=False)


def articulated_params() -> FlowEnergyParams:
    """The paper's articulated setting: robust smoothness, α = 50, γ = 5, ε = 0.001."""
    return FlowEnergyParams(to_device(50.0), to_device(5.0), to_device(1e-3), True)


def rigid_params() -> FlowEnergyParams:
    """The paper's rigid setting: quadratic smoothness, α = 800, γ = 5, ε = 0.001."""
    return FlowEnergyParams(to_device(800.0), to_device(5.0), to_device(1e-3), False)


def middlebury_params() -> FlowEnergyParams:
    """Plain Brox flow tuned once on the Middlebury training pairs (robust smoothness).

    Used by `jaxtrack flow` and `experiments/bench_flow.py`; the tracker uses the paper's values.
    """
    return FlowEnergyParams(to_device(MIDDLEBURY_ALPHA), to_device(MIDDLEBURY_GAMMA), to_device(1e-3), True)


MIDDLEBURY_ALPHA = 4.0
MIDDLEBURY_GAMMA = 5.0


def smoothness_s2(
    U: jax.Array, V: jax.Array, in_x: jax.Array, in_y: jax.Array, right: Callable = kp, down: Callable = ip
) -> jax.Array:
    """|∇w|² per pixel: forward differences on the edges (p, p+x) and (p, p+y) that lie inside Ω1.

    `in_x`/`in_y` mark those edges; `right`/`down` give the neighbour values (full layout by default,
    the solver passes its parity-layout shifts). Shared by the energy and the solver so both use one
    discretisation.
    """
    dux, dvx = right(U) - U, right(V) - V
    duy, dvy = down(U) - U, down(V) - V
    return jnp.where(in_x, dux * dux + dvx * dvx, 0.0) + jnp.where(in_y, duy * duy + dvy * dvy, 0.0)


def local_flow_energy(
    flow: jax.Array,
    img1: ArrayLike,
    img2: ArrayLike,
    params: FlowEnergyParams,
    data_weight: ArrayLike | None = None,
    region: ArrayLike | None = None,
) -> jax.Array:
    """Per-pixel energy density e(x) (H, W) of eq. 6 (data + α · smoothness); its sum is E.

    Args:
        flow: (H, W, 2) flow w = (u, v) from img1 to img2, pixels.
        img1, img2: (H, W) or (H, W, C) images on the 0-255 scale.
        params: α, γ, ε and the smoothness type.
        data_weight: (H, W) r(x) ∈ [0, 1] (default 1).
        region: (H, W) bool Ω1 (default: the whole image, plain Brox flow).
    """
    img1, img2 = _channels(img1).astype(flow.dtype), _channels(img2).astype(flow.dtype)
    h, w = img1.shape[:2]
    r = jnp.ones((h, w), flow.dtype) if data_weight is None else data_weight.astype(flow.dtype)
    in_region = jnp.ones((h, w), bool) if region is None else jnp.asarray(region, bool)
    eps2 = params.epsilon**2
    g1x, g1y = image_gradients(img1)
    g2x, g2y = image_gradients(img2)
    warped, inside = warp_bilinear(jnp.concatenate([img2, g2x, g2y], -1), flow)
    c = img1.shape[-1]
    i2w, g2xw, g2yw = warped[..., :c], warped[..., c : 2 * c], warped[..., 2 * c :]
    grey2 = jnp.sum((i2w - img1) ** 2, -1)
    grad2 = jnp.sum((g2xw - g1x) ** 2 + (g2yw - g1y) ** 2, -1)
    if params.separate_penalties:
        psi_data = jnp.sqrt(grey2 + eps2) + params.gamma * jnp.sqrt(grad2 + eps2)
    else:
        psi_data = jnp.sqrt(grey2 + params.gamma * grad2 + eps2)
    data = jnp.where(in_region & inside, r * psi_data, 0.0)
    in_x, in_y = in_region & kp(in_region), in_region & ip(in_region)
    grad_sq = smoothness_s2(flow[..., 0], flow[..., 1], in_x, in_y)
    smooth = jnp.sqrt(grad_sq + eps2) if params.robust_smoothness else grad_sq
    smooth = jnp.where(in_region, smooth, 0.0)
    return data + params.alpha * smooth


def flow_energy(
    flow: jax.Array,
    img1: ArrayLike,
    img2: ArrayLike,
    params: FlowEnergyParams,
    data_weight: ArrayLike | None = None,
    region: ArrayLike | None = None,
) -> jax.Array:
    """E(u, v) of eq. 6 (scalar): the sum of `local_flow_energy`."""
    return jnp.sum(local_flow_energy(flow, img1, img2, params, data_weight, region))


def flow_confidence(local_energy: jax.Array, beta: ArrayLike) -> jax.Array:
    """Confidence c(x) = β / (1 + e(x)) of eq. 8 (β = 12 quadratic, 3 robust)."""
    return beta / (1.0 + local_energy)
