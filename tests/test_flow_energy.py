"""The flow energy of eq. 6: minimum at the true motion, gradients, region and occlusion weights."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtrack.cues.flow import (
    FlowEnergyParams,
    articulated_params,
    flow_confidence,
    flow_energy,
    local_flow_energy,
    rigid_params,
)
from jaxtrack.image import warp_bilinear


def _textured(h=40, w=48, seed=0):
    """A smooth random texture (sum of sinusoids) and the function that samples it anywhere."""
    rng = np.random.default_rng(seed)
    freqs = rng.uniform(0.05, 0.35, size=(6, 2))
    phases = rng.uniform(0, 2 * np.pi, size=6)

    def sample(x, y):
        return 128 + sum(20 * np.sin(fx * x + fy * y + p) for (fx, fy), p in zip(freqs, phases))

    y, x = np.mgrid[0:h, 0:w].astype(float)
    return sample, x, y


def test_warp_is_exact_for_bilinear_content_and_flags_the_border():
    img = jnp.asarray(np.add.outer(np.arange(10.0), 2 * np.arange(12.0))[..., None])  # affine: bilinear is exact
    flow = jnp.full((10, 12, 2), 0.25).at[..., 1].set(-0.5)
    warped, inside = warp_bilinear(img, flow)
    expected = np.add.outer(np.arange(10.0) - 0.5, 2 * (np.arange(12.0) + 0.25))
    ok = np.asarray(inside)
    np.testing.assert_allclose(np.asarray(warped)[..., 0][ok], expected[ok], atol=1e-12)
    assert not ok[0].any() and ok[1:, :-1].all()


@pytest.mark.parametrize("params", [articulated_params(), rigid_params()], ids=["robust", "quadratic"])
def test_true_translation_has_lowest_energy(params):
    sample, x, y = _textured()
    shift = np.array([0.6, -0.35])
    img1 = jnp.asarray(sample(x, y))
    img2 = jnp.asarray(sample(x - shift[0], y - shift[1]))  # img2(x + w) = img1(x)
    true = jnp.broadcast_to(jnp.asarray(shift), img1.shape + (2,))
    e_true = float(flow_energy(true, img1, img2, params))
    for delta in ([0.2, 0.0], [0.0, 0.2], [-0.3, 0.1]):
        assert e_true < float(flow_energy(true + jnp.asarray(delta), img1, img2, params))
    assert e_true < float(flow_energy(jnp.zeros_like(true), img1, img2, params))


@pytest.mark.parametrize("separate", [False, True], ids=["joint-penalty", "separate-penalties"])
def test_gradient_matches_finite_differences(separate):
    sample, x, y = _textured(12, 14)
    img1, img2 = jnp.asarray(sample(x, y)), jnp.asarray(sample(x - 0.4, y + 0.2))
    flow = jnp.asarray(np.random.default_rng(1).normal(scale=0.3, size=(12, 14, 2)))
    a = articulated_params()
    params = FlowEnergyParams(a.alpha, a.gamma, a.epsilon, True, separate)
    g = jax.grad(flow_energy)(flow, img1, img2, params)
    eps = 1e-6
    for idx in [(3, 4, 0), (7, 9, 1), (0, 0, 0), (11, 13, 1)]:
        fd = (flow_energy(flow.at[idx].add(eps), img1, img2, params) - flow_energy(flow.at[idx].add(-eps), img1, img2, params)) / (2 * eps)
        np.testing.assert_allclose(g[idx], fd, rtol=1e-5, atol=1e-5)


def test_region_and_occlusion_weights():
    sample, x, y = _textured()
    img1, img2 = jnp.asarray(sample(x, y)), jnp.asarray(sample(x - 1.0, y))
    params = rigid_params()
    region = jnp.zeros(img1.shape, bool).at[10:30, 12:36].set(True)
    flow = jnp.asarray(np.random.default_rng(2).normal(size=img1.shape + (2,)))
    e = local_flow_energy(flow, img1, img2, params, region=region)
    assert float(jnp.abs(e[~region]).max()) == 0.0
    # Changing the flow outside Ω1 does not change E.
    outside = flow.at[0:5].set(99.0)
    assert float(flow_energy(outside, img1, img2, params, region=region)) == pytest.approx(float(jnp.sum(e)))
    # r = 0 removes the data term: only smoothness is left.
    r0 = local_flow_energy(flow, img1, img2, params, data_weight=jnp.zeros(img1.shape))
    smooth_only = local_flow_energy(flow, img1, img1 * 0, params, data_weight=jnp.zeros(img1.shape))
    np.testing.assert_allclose(r0, smooth_only)
    # Colour: three equal channels give the data residual √3 times one channel's.
    grey = local_flow_energy(jnp.zeros_like(flow), img1, img2, params.__class__(params.alpha * 0, params.gamma, params.epsilon, False))
    rgb = local_flow_energy(jnp.zeros_like(flow), jnp.stack([img1] * 3, -1), jnp.stack([img2] * 3, -1), params.__class__(params.alpha * 0, params.gamma, params.epsilon, False))
    np.testing.assert_allclose(rgb, np.sqrt(3) * grey, rtol=1e-6, atol=1e-3)


def test_confidence_and_vmap_over_alpha():
    sample, x, y = _textured(16, 16)
    img1, img2 = jnp.asarray(sample(x, y)), jnp.asarray(sample(x - 0.5, y))
    flow = jnp.full((16, 16, 2), 0.5).at[..., 1].set(0.0)
    e = local_flow_energy(flow, img1, img2, rigid_params())
    c = flow_confidence(e, 12.0)
    assert float(c.max()) <= 12.0 and float(c.min()) > 0
    params = rigid_params()
    alphas = jnp.linspace(10.0, 800.0, 5)
    batched = jax.vmap(lambda a: flow_energy(flow, img1, img2, params.__class__(a, params.gamma, params.epsilon, False)))(alphas)
    single = [flow_energy(flow, img1, img2, params.__class__(a, params.gamma, params.epsilon, False)) for a in alphas]
    np.testing.assert_allclose(batched, single, rtol=1e-12)
