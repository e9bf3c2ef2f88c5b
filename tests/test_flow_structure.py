"""The flow's structure factor (jaxtrack.cues.flow.structure_confidence): where the image pins the flow."""

import jax.numpy as jnp
import numpy as np

from jaxtrack.cues.flow import limb_pixels, noise_sigma, structure_confidence


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


def _sphere_depth(radius_px=30.0, z_centre=500.0, focal=500.0, size=80):
    """The rendered depth of a sphere facing the camera (orthographic approximation of its visible cap)."""
    y, x = np.mgrid[:size, :size] - size / 2.0
    r2 = x * x + y * y
    silhouette = r2 < radius_px**2
    radius_mm = radius_px * z_centre / focal
    depth = np.where(silhouette, z_centre - np.sqrt(np.maximum(radius_mm**2 - r2 * (z_centre / focal) ** 2, 0.0)), np.inf)
    return depth, silhouette, np.sqrt(r2)


def test_limbs_are_where_the_surface_grazes_the_view():
    """A sphere's limbs lie on the outermost pixels of its outline (the one-pixel depth steps there, read from the
    render, reach tan 70° all round and tan 80° in places), none inside; a plane at 60° to the image plane has none,
    one at 85° is limb everywhere; a depth jump inside the silhouette (one part in front of another) is a limb on
    both sides."""
    focal = 500.0
    depth, silhouette, r = _sphere_depth(focal=focal)
    for max_slope in (2.75, 5.67):
        limbs = np.asarray(limb_pixels(jnp.asarray(depth), jnp.asarray(silhouette), focal, max_slope))
        assert limbs.any() and not limbs[r < 27.5].any(), max_slope
    limbs_70 = np.asarray(limb_pixels(jnp.asarray(depth), jnp.asarray(silhouette), focal, 2.75))
    assert limbs_70[silhouette & (r > 29.0)].all()
    assert np.asarray(limb_pixels(jnp.asarray(depth), jnp.asarray(silhouette), focal, 5.67)).sum() < limbs_70.sum()
    cols = np.arange(64)[None, :] * np.ones((48, 1))
    inside = np.ones((48, 64), bool)
    for angle, expected in ((60.0, False), (85.0, True)):
        z = 400.0 * (1.0 + np.tan(np.radians(angle)) / focal) ** cols  # each step: ΔZ · f / Z = tan(angle)
        got = np.asarray(limb_pixels(jnp.asarray(z), jnp.asarray(inside), focal, 5.67))
        assert got[:, 1:-1].all() if expected else not got.any(), angle
    z = np.where(cols < 32, 400.0, 450.0)
    got = np.asarray(limb_pixels(jnp.asarray(z), jnp.asarray(inside), focal, 5.67))
    assert got[:, 31:33].all() and got.sum() == 2 * 48
    assert not np.asarray(limb_pixels(jnp.asarray(depth), jnp.asarray(silhouette), focal, 5.67))[~silhouette].any()


def test_no_structure_counts_near_limbs():
    """Gradients within 2 px of a limb pixel count as no structure: g falls there (the tensor's smoothing, ρ = 1.5 px,
    still reaches the texture beside the band); farther away g is what it was."""
    rng = np.random.default_rng(2)
    texture = jnp.asarray(_texture(rng))
    limbs = np.zeros((64, 80), bool)
    limbs[30, 10:70] = True
    plain = np.asarray(structure_confidence(texture, 4.0))
    masked = np.asarray(structure_confidence(texture, 4.0, limbs=jnp.asarray(limbs)))
    assert np.mean(masked[30, 12:68]) < 0.4 * np.mean(plain[30, 12:68])
    assert np.all(masked[28:33, 12:68] < plain[28:33, 12:68])
    np.testing.assert_allclose(masked[:20], plain[:20], atol=1e-6)
    np.testing.assert_allclose(masked[42:], plain[42:], atol=1e-6)
