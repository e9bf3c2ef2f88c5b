"""jaxtrack.image: the shared windows at traced offsets and the general median filter."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtrack.image import crop_window, median_filter, paste_window


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
