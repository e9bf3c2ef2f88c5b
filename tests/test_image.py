"""jaxtrack.image: the shared windows at traced offsets and the general median filter."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtrack.image import (
    crop_window,
    full_to_window,
    gaussian_blur_traced,
    median_filter,
    paste_window,
    paste_window_scaled,
    sample_window,
    window_to_full,
)


def test_windows_at_traced_offsets_compile_once():
    img = jnp.arange(12 * 16 * 3, dtype=jnp.float32).reshape(12, 16, 3)

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def roundtrip(offset):
        part = crop_window(img, offset, (4, 6))
        return part, paste_window(jnp.zeros_like(img), part, offset)

    for y0, x0 in [(0, 0), (3, 5), (8, 10)]:
        part, pasted = roundtrip(jnp.array([y0, x0]))
        np.testing.assert_array_equal(part, img[y0 : y0 + 4, x0 : x0 + 6])
        expected = np.zeros(img.shape, np.float32)
        expected[y0 : y0 + 4, x0 : x0 + 6] = img[y0 : y0 + 4, x0 : x0 + 6]
        np.testing.assert_array_equal(pasted, expected)
    # Past the border the window is shifted back inside (dynamic_slice semantics).
    part, _ = roundtrip(jnp.array([11, 15]))
    np.testing.assert_array_equal(part, img[8:12, 10:16])


def test_scaled_windows_one_program_exact_at_scale_one_and_box_at_scale_two():
    rng = np.random.default_rng(1)
    img = jnp.asarray(rng.uniform(0, 255, (24, 32, 3)), jnp.float32)

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def window(offset, scale):
        return sample_window(img, offset, scale, (6, 8))

    # Scale 1 at an integer offset: the plain crop, exactly.
    np.testing.assert_array_equal(window(jnp.array([3.0, 5.0]), jnp.float32(1.0)), img[3:9, 5:13])
    # Scale 2: each window pixel is the mean of its 2x2 block of frame pixels (antialiased).
    box = np.asarray(img[2:14, 4:20]).reshape(6, 2, 8, 2, 3).mean(axis=(1, 3))
    np.testing.assert_allclose(window(jnp.array([2.0, 4.0]), jnp.float32(2.0)), box, rtol=1e-5)
    # Same program for another offset and scale (assert_max_traces above).
    window(jnp.array([1.5, 0.25]), jnp.float32(1.7))
    # Coordinates: window_to_full and full_to_window are inverses and put window pixel (0, 0) at the
    # centre of the block it covers.
    pts = jnp.asarray(rng.uniform(-2, 30, (5, 2)), jnp.float32)
    off, sc = jnp.array([2.0, 4.0]), jnp.float32(2.0)
    np.testing.assert_allclose(full_to_window(window_to_full(pts, off, sc), off, sc), pts, rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(window_to_full(jnp.zeros((1, 2)), off, sc), [[4.5, 2.5]])


def test_scaled_paste_is_the_nearest_window_pixel_inside_the_window_only():
    part = jnp.arange(2 * 3, dtype=jnp.float32).reshape(2, 3) + 1
    full = paste_window_scaled(jnp.zeros((8, 10)), part, jnp.array([1.0, 2.0]), jnp.float32(2.0))
    expected = np.zeros((8, 10))
    expected[1:5, 2:8] = np.kron(np.asarray(part), np.ones((2, 2)))
    np.testing.assert_array_equal(full, expected)
    # Scale 1 at an integer offset: `paste_window`.
    img = jnp.zeros((6, 7))
    np.testing.assert_array_equal(paste_window_scaled(img, part, jnp.array([2.0, 3.0]), jnp.float32(1.0)),
                                  paste_window(img, part, jnp.array([2, 3])))


def test_median_filter_matches_scipy_and_respects_the_region():
    scipy_ndimage = pytest.importorskip("scipy.ndimage")
    rng = np.random.default_rng(0)
    img = rng.normal(size=(9, 11, 2))
    for size in (3, 5):
        ours = np.asarray(jax.jit(lambda a, s=size: median_filter(a, s))(jnp.asarray(img)))
        ref = np.stack([scipy_ndimage.median_filter(img[..., c], size=size, mode="nearest") for c in range(2)], -1)
        r = size // 2
        np.testing.assert_allclose(ours[r:-r, r:-r], ref[r:-r, r:-r])
    valid = np.zeros((9, 11), bool)
    valid[2:7, 3:9] = True
    out = np.asarray(median_filter(jnp.asarray(img), 3, jnp.asarray(valid)))
    np.testing.assert_array_equal(out[~valid], img[~valid])
    with pytest.raises(ValueError, match="3x3 and 5x5"):
        median_filter(jnp.asarray(img), 7)


def _blur_reference(img, sigma, radius):
    """numpy separable Gaussian (taps over ±radius, normalised), border pixels replicated."""
    x = np.arange(-radius, radius + 1)
    k = np.exp(-0.5 * (x / sigma) ** 2)
    k /= k.sum()
    out = np.asarray(img, np.float64)
    for axis in (0, 1):
        pad = [(0, 0)] * out.ndim
        pad[axis] = (radius, radius)
        padded = np.pad(out, pad, mode="edge")
        n = out.shape[axis]
        out = sum(k[i] * np.take(padded, np.arange(i, i + n), axis=axis) for i in range(len(k)))
    return out


def test_traced_gaussian_blur_matches_a_reference_is_the_identity_at_zero_and_differentiates_in_sigma():
    img = jnp.asarray(np.random.default_rng(0).uniform(0, 255, (9, 11, 3)))
    np.testing.assert_array_equal(gaussian_blur_traced(img, 0.0), img)  # exactly the input: the method's default
    for sigma in (0.6, 1.0, 1.7):  # radius = ceil(3 · max_sigma) = 6
        np.testing.assert_allclose(gaussian_blur_traced(img, sigma), _blur_reference(img, sigma, 6), rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(gaussian_blur_traced(img, 5.0), gaussian_blur_traced(img, 2.0))  # σ clipped to max_sigma
    # One program for every σ; vmap over σ gives the per-σ results.
    sigmas = jnp.array([0.0, 0.8, 1.5])
    batched = jax.vmap(lambda s: gaussian_blur_traced(img, s))(sigmas)
    for b, s in zip(batched, sigmas, strict=True):
        np.testing.assert_allclose(b, gaussian_blur_traced(img, s), rtol=1e-12, atol=1e-9)
    # d/dσ of a scalar readout against central differences (float64).
    def readout(s):
        return jnp.sum(gaussian_blur_traced(img, s) * jnp.linspace(-1.0, 1.0, img.size).reshape(img.shape))

    h = 1e-5
    fd = (readout(1.2 + h) - readout(1.2 - h)) / (2 * h)
    np.testing.assert_allclose(jax.grad(readout)(1.2), fd, rtol=1e-6)


def test_flat_bilinear_reads_exactly_what_sample_bilinear_reads():
    from jaxtrack.image import sample_bilinear, sample_bilinear_flat

    rng = np.random.default_rng(3)
    img = jnp.asarray(rng.uniform(0, 255, (17, 23)), jnp.float32)
    x = jnp.asarray(rng.uniform(-3, 26, (50, 40)), jnp.float32)  # some beyond the border: clamped, masked
    y = jnp.asarray(rng.uniform(-3, 20, (50, 40)), jnp.float32)
    want, want_inside = sample_bilinear(img[..., None], x, y)
    got, inside = jax.jit(sample_bilinear_flat)(img, x, y)
    assert np.array_equal(np.asarray(got), np.asarray(want[..., 0]))
    assert np.array_equal(np.asarray(inside), np.asarray(want_inside))
    assert 0 < np.mean(np.asarray(inside)) < 1
