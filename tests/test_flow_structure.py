"""The flow's structure factor (jaxtrack.cues.flow.structure_confidence): where the image pins the flow."""

import jax.numpy as jnp
import numpy as np

from jaxtrack.cues.flow import noise_sigma, structure_confidence


def _texture(rng, shape=(64, 80)):
    """Band-limited random texture, 0-255 (Gaussian-blurred noise by a separable 5-tap kernel)."""
    x = rng.normal(size=(shape[0] + 4, shape[1] + 4))
    taps = np.array([1.0, 4.0, 6.0, 4.0, 1.0]) / 16.0
    x = sum(t * x[i:i + shape[0], :] for i, t in enumerate(taps))
    x = sum(t * x[:, i:i + shape[1]] for i, t in enumerate(taps))
    return np.clip(128.0 + 120.0 * x / x.std(), 0.0, 255.0)


def test_noise_estimate_recovers_gaussian_noise():
    rng = np.random.default_rng(0)
    for sigma in (5.0, 20.0, 40.0):
        image = 120.0 + rng.normal(0.0, sigma, (96, 128))
        assert abs(float(noise_sigma(jnp.asarray(image))) - sigma) < 0.05 * sigma


def test_texture_pins_the_flow_and_flat_regions_edges_and_noise_do_not():
    """g high on texture; 0 on a flat image; ≈ 0 along a straight edge (the aperture problem: one direction only);
    on noise alone ≈ 0.65 / (0.65 + k) (λ_min ≈ 0.65 σ² against k σ² + 1); and it falls as k grows."""
    rng = np.random.default_rng(1)
    texture = _texture(rng)
    g_texture = np.asarray(structure_confidence(jnp.asarray(texture), 4.0))
    assert np.median(g_texture[4:-4, 4:-4]) > 0.6  # 0.76: the texture's finest detail reads partly as noise (σ_n)
    assert np.all(np.asarray(structure_confidence(jnp.full((64, 80), 90.0), 4.0)) == 0.0)
    edge = np.where(np.arange(80)[None, :] < 40, 60.0, 200.0) * np.ones((64, 1))
    g_edge = np.asarray(structure_confidence(jnp.asarray(edge), 0.0))
    assert g_edge[8:-8].max() < 0.05  # strong gradient, one direction
    k = 4.0
    noise = 120.0 + rng.normal(0.0, 30.0, (96, 128))
    g_noise = float(np.median(np.asarray(structure_confidence(jnp.asarray(noise), k))))
    assert 0.5 * 0.65 / (0.65 + k) < g_noise < 2.0 * 0.65 / (0.65 + k), g_noise
    g = [float(np.mean(np.asarray(structure_confidence(jnp.asarray(texture + rng.normal(0, 10, texture.shape)), kk))))
         for kk in (0.0, 1.0, 4.0, 16.0)]
    assert np.all(np.diff(g) < 0), g
