"""The sparse region modality (jaxtrack.cues.lines): correspondence lines, histograms, view model.

Small images (≤ 160x120), few views and points; float32 except the derivative check.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.ndimage as ndi

import jaxtrack as jt
import jaxtrack.cues.lines as L
from jaxtrack.cues.lines import _viewmodel
from jaxtrack.geometry import make_camera, rotation_error_deg, so3_exp
from jaxtrack.render import Renderer, box_mesh, make_mesh, torus_mesh

F32 = jnp.float32
FG, BG = np.array([200.0, 70.0, 60.0]), np.array([50.0, 90.0, 190.0])


def _camera(f=125.0, dtype=F32):
    return make_camera([[f, 0, 79.5], [0, f, 59.5], [0, 0, 1]], 160, 120, dtype=dtype)


def _pose(rotvec, t):
    T = np.eye(4)
    T[:3, :3] = np.asarray(so3_exp(jnp.asarray(rotvec, jnp.float64)))
    T[:3, 3] = t
    return T


def _errors(T, T_ref):
    T, T_ref = np.asarray(T, np.float64), np.asarray(T_ref, np.float64)
    rot = float(rotation_error_deg(jnp.asarray(T[:3, :3]), jnp.asarray(T_ref[:3, :3])))
    return float(np.linalg.norm(T[:3, 3] - T_ref[:3, 3])), rot


def _raycast_silhouette(mesh, camera, T_cam_model):
    """(H, W) bool silhouette by embree ray casting through the pixel centres (independent of the JAX
    rasteriser the view model is built with)."""
    import trimesh
    from trimesh.ray.ray_pyembree import RayMeshIntersector

    tm = trimesh.Trimesh(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces), process=False)
    K, T = np.asarray(camera.K, np.float64), np.asarray(T_cam_model, np.float64)
    R, t = T[:3, :3], T[:3, 3]
    uu, vv = np.meshgrid(np.arange(camera.width), np.arange(camera.height))
    d_cam = np.stack([(uu - K[0, 2]) / K[0, 0], (vv - K[1, 2]) / K[1, 1], np.ones(uu.shape)], -1).reshape(-1, 3)
    directions = d_cam @ R  # Rᵀ d per row: model frame
    origins = np.broadcast_to(-R.T @ t, directions.shape)
    return RayMeshIntersector(tm).intersects_any(origins, directions).reshape(uu.shape)


def _sdf(silhouette):
    """Signed distance, positive inside, zero half-way between inside and outside pixel centres."""
    return np.where(silhouette, ndi.distance_transform_edt(silhouette) - 0.5,
                    -(ndi.distance_transform_edt(~silhouette) - 0.5))


def _at(image, p):
    """Bilinear lookup of an (H, W) image at (N, 2) (x, y)."""
    return ndi.map_coordinates(image, [p[:, 1], p[:, 0]], order=1, mode="nearest")


def _project(camera, T, p, n=None):
    """numpy pinhole: pixels (N, 2) of model points at pose T, and the unit image direction of n."""
    K, T = np.asarray(camera.K, np.float64), np.asarray(T, np.float64)
    q = p @ T[:3, :3].T + T[:3, 3]
    px = np.stack([K[0, 0] * q[:, 0] / q[:, 2] + K[0, 2], K[1, 1] * q[:, 1] / q[:, 2] + K[1, 2]], -1)
    if n is None:
        return px
    d = _project(camera, T, p + 1e-3 * n) - px
    return px, d / np.linalg.norm(d, axis=-1, keepdims=True)


def _perturb(T, rotvec, dt):
    """Rotate about the object's own origin and shift it (not a left increment about the camera)."""
    out = np.array(T, np.float64)
    out[:3, :3] = np.asarray(so3_exp(jnp.asarray(rotvec, jnp.float64))) @ out[:3, :3]
    out[:3, 3] += dt
    return out


# ------------------------------------------------------------------------------- lines, numpy reference


def _reference_line(c, n, scale, num_segments=19):
    """Brute force, float64: the pixels of one line as `sample_lines` defines them, and delta_r."""
    dom = 0 if abs(n[1]) < abs(n[0]) else 1
    nd, nm, cd, cm = n[dom], n[1 - dom], c[dom], c[1 - dom]
    sign = 1.0 if nd >= 0 else -1.0
    length = num_segments * scale
    u0 = np.floor(cd - sign * (length - 1) / 2 + 0.5)
    start = cd - sign * (length - 1) / 2 + 0.5
    pixels, ties = [], abs(start - np.round(start)) < 1e-3  # float32 may round the other way there
    for k in range(length):
        u = u0 + sign * k
        v_real = cm + (u - cd) / nd * nm + 0.5
        ties |= abs(v_real - np.round(v_real)) < 1e-3
        v = np.floor(v_real)
        pixels.append((u, v) if dom == 0 else (v, u))
    return np.array(pixels, np.int64), (u0 + sign * (length - 1) / 2 - cd) / nd, ties


def _reference_distribution(pf_pixels, scale, amplitude, slope, F=8, D=12):
    """M3T's loops, float64: segment products normalised, smoothed-step products, moments."""
    S = F + D - 1
    seg_f = np.ones(S)
    seg_b = np.ones(S)
    for k, p in enumerate(pf_pixels):
        seg_f[k // scale] *= p
        seg_b[k // scale] *= 1 - p
    total = seg_f + seg_b
    seg_f, seg_b = seg_f / total, seg_b / total
    x = np.arange(F) - (F - 1) / 2
    hf = 0.5 - amplitude * np.tanh(x / (2 * slope))
    dist = np.ones(D)
    for d in range(D):
        for j in range(F):
            dist[d] *= seg_f[d + j] * hf[j] + seg_b[d + j] * (1 - hf[j])
    dist /= dist.sum()
    mean = np.sum(np.arange(D) * dist)
    var = np.sum((np.arange(D) - mean) ** 2 * dist)
    min_var = max(1 / (2 * np.arctanh(2 * amplitude) ** 2), slope)
    return dist, mean - (D - 1) / 2, max(var, min_var)


def test_sample_lines_and_distribution_match_numpy_reference_on_a_disc():
    rng = np.random.default_rng(3)
    h, w, centre, radius = 120, 160, np.array([80.3, 60.7]), 30.0
    yy, xx = np.mgrid[0:h, 0:w]
    inside = (xx - centre[0]) ** 2 + (yy - centre[1]) ** 2 <= radius**2
    image = np.clip(np.where(inside[..., None], FG, BG) + rng.normal(0, 30, (h, w, 3)), 0, 255).astype(np.float32)
    pix = np.stack([xx.ravel(), yy.ravel()], -1).astype(np.float32)
    hist = L.learn_histograms(jnp.asarray(image), pix, inside.ravel(), pix, ~inside.ravel(), bins=32)
    params = L.line_params(F32)
    config = L.LineConfig(max_scale=3)
    angles = 2 * np.pi * np.arange(16) / 16 + 0.1
    normals = np.stack([np.cos(angles + 0.05), np.sin(angles + 0.05)], -1)
    centers = centre + (radius + rng.uniform(-3, 3, 16))[:, None] * np.stack([np.cos(angles), np.sin(angles)], -1)
    prior = float(params.posterior_prior)
    fg_hist, bg_hist = np.asarray(hist.fg, np.float64), np.asarray(hist.bg, np.float64)

    @jax.jit
    def lines(scale):
        smp = L.sample_lines(jnp.asarray(image), jnp.asarray(centers, F32), jnp.asarray(normals, F32), scale, config)
        log_odds = L.segment_log_odds(hist, smp, scale, config, params.posterior_prior)
        dist = L.contour_distribution(log_odds, params.function_amplitude, params.function_slope)
        min_var = L.min_expected_variance(params.function_amplitude, params.function_slope)
        return (smp, dist) + L.distribution_moments(dist, min_var)

    for scale in (1, 3):
        smp, dist, mean, var = lines(jnp.int32(scale))
        length = 19 * scale
        assert smp.pixel.shape == (16, 19 * 3, 2)
        assert np.all(np.asarray(smp.mask)[:, :length]) and not np.any(np.asarray(smp.mask)[:, length:])
        assert np.all(np.asarray(smp.inside))
        checked = 0
        for i in range(16):
            ref_pix, ref_dr, ties = _reference_line(centers[i], normals[i], scale)
            if ties:
                continue
            checked += 1
            np.testing.assert_array_equal(np.asarray(smp.pixel[i, :length]), ref_pix)
            np.testing.assert_allclose(float(smp.delta_r[i]), ref_dr, atol=1e-4)
            colours = image[ref_pix[:, 1], ref_pix[:, 0]]
            np.testing.assert_array_equal(np.asarray(smp.colour[i, :length]), colours)
            cells = np.asarray(L.colour_index(jnp.asarray(colours), 32))
            pf = (fg_hist[cells] + prior) / (fg_hist[cells] + bg_hist[cells] + 2 * prior)
            ref_dist, ref_mean, ref_var = _reference_distribution(pf, scale, 0.43, 0.5)
            np.testing.assert_allclose(np.asarray(dist[i]), ref_dist, atol=2e-5)
            np.testing.assert_allclose(float(mean[i]), ref_mean, atol=1e-4)
            np.testing.assert_allclose(float(var[i]), ref_var, rtol=1e-4)
            # the observed contour lies on the disc's rim (to the pixel grid's half pixel)
            observed = centers[i] + (float(smp.delta_r[i]) + float(mean[i]) * scale * float(smp.step[i])) * normals[i]
            assert abs(np.linalg.norm(observed - centre) - radius) < 0.6 * scale + 0.5
        assert checked >= 12
        # The recovery reads the same segments off the per-pixel log-odds image (one gather a pixel): the same sums.
        lo_img = L.log_odds_image(hist, jnp.asarray(image), params.posterior_prior)
        assert lo_img.shape == (h, w)
        on_lines = L.sample_lines(lo_img[..., None], jnp.asarray(centers, F32), jnp.asarray(normals, F32), scale, config)
        np.testing.assert_array_equal(np.asarray(on_lines.pixel), np.asarray(smp.pixel))
        per_pixel = np.where(np.asarray(on_lines.mask), np.asarray(on_lines.colour)[..., 0], 0.0)[:, :length]
        sums = per_pixel.reshape(16, 19, scale).sum(-1)
        lo = np.asarray(L.segment_log_odds(hist, smp, scale, config, params.posterior_prior))
        np.testing.assert_allclose(sums, lo, rtol=1e-5, atol=1e-4)
        assert np.abs(lo).max() > 1.0  # the disc's colours are told apart: not a comparison of zeros


def test_distribution_mean_finds_a_step_edge_within_a_tenth_of_a_pixel():
    h, w = 120, 160
    yy, xx = np.mgrid[0:h, 0:w]
    params = L.line_params(F32)
    config = L.LineConfig(max_scale=2)

    @jax.jit
    def observed_along(image, hist, centers, direction, scale):
        m = L.sample_lines(image, centers, jnp.broadcast_to(direction, centers.shape), scale, config)
        lo = L.segment_log_odds(hist, m, scale, config, params.posterior_prior)
        dist = L.contour_distribution(lo, params.function_amplitude, params.function_slope)
        mean, _ = L.distribution_moments(dist, 0.5)
        return m.delta_r + mean * scale * m.step

    for vertical in (True, False):
        fg = (xx <= 70) if vertical else (yy <= 55)  # edge at x = 70.5 / y = 55.5 (between pixel centres)
        image = jnp.asarray(np.where(fg[..., None], FG, BG), F32)
        hist = L.learn_histograms(image, jnp.array([[5.0, 5.0]]), jnp.ones(1), jnp.array([[150.0, 110.0]]), jnp.ones(1))
        edge = 70.5 if vertical else 55.5
        offsets = np.linspace(-4.0, 4.0, 17)
        for angle, scale in ((0.0, 1), (0.3, 2), (-0.6, 1), (-0.4, 2)):
            direction = np.array([np.cos(angle), np.sin(angle)]) if vertical else np.array([np.sin(angle), np.cos(angle)])
            base = np.array([edge, 60.2]) if vertical else np.array([80.2, edge])
            centers = base + offsets[:, None] * direction
            along = np.asarray(observed_along(image, hist, jnp.asarray(centers, F32), jnp.asarray(direction, F32),
                                              jnp.int32(scale)))
            observed = centers + along[:, None] * direction
            coordinate = observed[:, 0] if vertical else observed[:, 1]
            assert np.max(np.abs(coordinate - edge)) < 0.1, (vertical, angle, scale, coordinate - edge)


@pytest.mark.parametrize("bins", [8, 16, 30, 32, 64])
def test_colour_index_of_8_bit_colours_equals_the_float_bins(bins):
    """8-bit colours are binned in integer arithmetic (no cast): the same cell as floor(c · B / 256) in float, for
    every channel value, and the lines read the same log odds from a uint8 frame as from its float copy."""
    c = np.arange(256)
    colours = np.stack([c, c[::-1], (c * 7) % 256], -1)
    by_int = np.asarray(L.colour_index(jnp.asarray(colours, jnp.uint8), bins))
    b = np.floor(colours * bins / 256.0).astype(int)
    expected = (b[:, 0] * bins + b[:, 1]) * bins + b[:, 2]
    np.testing.assert_array_equal(by_int, expected)
    np.testing.assert_array_equal(by_int, np.asarray(L.colour_index(jnp.asarray(colours, F32), bins)))
    rng = np.random.default_rng(bins)
    image = rng.integers(0, 256, (120, 160, 3), dtype=np.uint8)
    table = L.LogOddsTable(jnp.asarray(rng.normal(size=bins**3), F32), jnp.asarray(1e-7, F32))
    centre = jnp.asarray(rng.uniform(40, 100, (16, 2)), F32)
    angle = rng.uniform(0, 2 * np.pi, 16)
    normal = jnp.asarray(np.stack([np.cos(angle), np.sin(angle)], -1), F32)
    odds = [np.asarray(L.segment_log_odds(table, L.sample_lines(jnp.asarray(im), centre, normal, 3), 3, L.LineConfig()))
            for im in (image, image.astype(np.float32))]
    np.testing.assert_array_equal(odds[0], odds[1])


def test_histograms_learn_update_and_posteriors():
    image = jnp.asarray(np.concatenate([np.broadcast_to(FG, (4, 8, 3)), np.broadcast_to(BG, (4, 8, 3))]), F32)
    fg_px = jnp.array([[1.0, 1.0], [2.0, 2.0], [3.0, 3.0]])
    bg_px = jnp.array([[1.0, 6.0], [5.0, 5.0], [9.0, 9.0]])
    hist = L.learn_histograms(image, fg_px, jnp.array([1, 1, 0]), bg_px, jnp.array([1, 1, 1]), bins=16)
    assert hist.fg.shape == (16**3,) and hist.bins == 16
    np.testing.assert_allclose([float(hist.fg.sum()), float(hist.bg.sum())], [1.0, 1.0], rtol=1e-6)
    assert float(hist.fg_count) == 2 and float(hist.bg_count) == 3  # the off-image pixel is clamped, not dropped
    p = L.pixel_posteriors(hist, jnp.asarray(np.stack([FG, BG, [128.0, 128.0, 128.0]]), F32))
    np.testing.assert_allclose(np.asarray(p), [1.0, 0.0, 0.5], atol=1e-4)
    empty = L.learn_histograms(image, fg_px, jnp.zeros(3), bg_px, jnp.zeros(3), bins=16)
    np.testing.assert_allclose(np.asarray(empty.fg), 1 / 16**3)  # empty: uniform
    assert jnp.array_equal(L.update_histograms(hist, empty, 0.2).fg, hist.fg)  # empty new: keeps the old one
    first = L.update_histograms(L.uniform_histograms(16), hist, 1.0)
    np.testing.assert_allclose(np.asarray(first.fg), np.asarray(hist.fg))
    blended = L.update_histograms(first, L.learn_histograms(image, bg_px, jnp.ones(3), fg_px, jnp.ones(3), bins=16), 0.2)
    cell = int(L.colour_index(jnp.asarray(FG, F32), 16))
    np.testing.assert_allclose(float(blended.fg[cell]), 0.8, rtol=1e-5)


# ------------------------------------------------------------------------------------------ view model


def _ellipsoid():
    v, f = L.icosphere(2)
    return make_mesh(v * np.array([50.0, 38.0, 28.0]), f, dtype=F32)


def _check_view_model_on_raycast_contour(mesh, vm):
    """Views 0, 7, 19, 33 (of 42): a camera 260 mm away looking along the view's direction; every valid
    contour point projects within 1 px of the ray-cast silhouette's contour, its normal points out."""
    camera = _camera(150.0)
    for view in (0, 7, 19, 33):
        direction = np.asarray(vm.directions[view], np.float64)
        T = np.eye(4)
        T[:3, :3] = _viewmodel.look_at_rotation(direction)  # looking along −direction, as the view did
        T[:3, 3] = -T[:3, :3] @ np.asarray(vm.center, np.float64) + np.array([2.0, -1.0, 260.0])
        assert int(L.nearest_view(vm, L.camera_direction(vm, camera, jnp.asarray(T, F32)))) == view
        sdf = _sdf(_raycast_silhouette(mesh, camera, T))
        valid = np.asarray(vm.valid[view])
        assert valid.all()
        px, n = _project(camera, T, np.asarray(vm.points[view], np.float64), np.asarray(vm.normals[view], np.float64))
        assert np.max(np.abs(_at(sdf, px))) < 1.0, np.max(np.abs(_at(sdf, px)))
        assert np.all(_at(sdf, px - 2.5 * n) > 0) and np.all(_at(sdf, px + 2.5 * n) < 0)


def _check_normals(vm):
    nrm = np.asarray(vm.normals)
    np.testing.assert_allclose(np.linalg.norm(nrm, axis=-1), 1.0, atol=1e-5)
    assert np.max(np.abs(np.einsum("vni,vi->vn", nrm, np.asarray(vm.directions)))) < 1e-5  # ⊥ the view


@pytest.mark.parametrize("name", ["torus", "ellipsoid"])
def test_view_model_points_lie_on_the_contour(name):
    mesh = torus_mesh(40, 15, 32, 12, F32) if name == "torus" else _ellipsoid()
    vm = L.build_view_model(mesh, num_points=40, subdivisions=1, image_size=128, batch_size=42)
    assert vm.points.shape == (42, 40, 3) and vm.directions.shape == (42, 3)
    _check_normals(vm)
    _check_view_model_on_raycast_contour(mesh, vm)


@pytest.mark.parametrize("capacity", [7, 40, 400])
def test_the_builds_host_selection_equals_the_jitted_one(capacity):
    """The view model's build selects contour pixels on the host (`contour_pixels_host`, `_contour_keys`,
    `select_along_contour_host`): the same indices, validity, count and overflow as the per-frame path's jitted
    `_select_along_contour`, for fewer and more contour pixels than slots, an empty silhouette and one whose
    contour overflows `max_contour`."""
    yy, xx = np.mgrid[:64, :80]
    silhouettes = np.stack([
        (yy - 30.3) ** 2 / 400 + (xx - 41.7) ** 2 / 900 < 1,  # an ellipse
        ((yy // 7 + xx // 5) % 2 == 0) & (yy > 2) & (yy < 60) & (xx > 3) & (xx < 70),  # a checker: long contour
        np.zeros((64, 80), bool),
        (np.abs(yy - 32) < 9) & (np.abs(xx - 40) < 9),  # a square: ties in angle about its centre
    ])
    max_contour = 300
    contour = np.asarray(jax.vmap(_viewmodel._inner_contour)(jnp.asarray(silhouettes)))
    assert contour[1].sum() > max_contour and 0 < contour[0].sum() < max_contour
    want = jax.jit(jax.vmap(lambda s: _viewmodel._select_along_contour(_viewmodel._inner_contour(s), s, capacity,
                                                                       max_contour)))(jnp.asarray(silhouettes))
    flat_all, total = _viewmodel.contour_pixels_host(contour, max_contour)
    centroid = jax.vmap(_viewmodel._silhouette_centroid)(jnp.asarray(silhouettes))
    keys = np.asarray(jax.vmap(lambda f, c, m: _viewmodel._contour_keys(f, c, m, 80))(
        flat_all, np.minimum(total, max_contour), centroid))
    for i in range(len(silhouettes)):
        got = _viewmodel.select_along_contour_host(flat_all[i], total[i], keys[i], capacity)
        for g, w in zip(got, want, strict=True):
            np.testing.assert_array_equal(np.asarray(g), np.asarray(w)[i])


def test_contour_points_from_render_of_a_chain():
    """The per-frame path: contour points of a two-part chain from one render, projected at the same pose."""
    a = box_mesh((60, 40, 40), F32)
    b = box_mesh((50, 30, 30), F32)
    verts = np.concatenate([np.asarray(a.vertices), np.asarray(b.vertices) + [55.0, 0, 0]])
    faces = np.concatenate([np.asarray(a.faces), np.asarray(b.faces) + 8])
    mesh = make_mesh(verts, faces, vertex_part=np.repeat([0, 1], 8), dtype=F32)
    model = jt.chain_model([-1, 0], [[0.0, 0.0, 1.0]], [[30.0, 0.0, 0.0]], dtype=F32)
    theta = jnp.array([0.5], F32)
    camera = _camera(150.0)
    T = jnp.asarray(_pose([0.4, -0.5, 0.2], [-15.0, 0.0, 320.0]), F32)
    out = Renderer(mesh, camera, model=model)(T, theta)

    @jax.jit
    def both(out, T, theta):
        T_parts = jt.geometry.part_transforms(model, T, theta)
        points, pixel, count = L.contour_points_from_render(out, camera, 80, T_parts)
        bare, _, _ = L.contour_points_from_render(out, camera, 80)  # no part poses: image normals only
        project = lambda p: L.project_contour(camera, T, p, model, theta)
        return points, pixel, count, project(points), bare, project(bare)

    points, pixel, count, proj, bare, bare_proj = both(out, T, theta)
    valid = np.asarray(points.valid)
    assert valid.all() and int(count) > 80
    assert set(np.asarray(points.part).tolist()) == {0, 1}
    sdf = _sdf(np.asarray(out.silhouette))
    assert np.max(np.abs(_at(sdf, np.asarray(proj.center)))) < 1.0
    np.testing.assert_allclose(np.asarray(proj.center), np.asarray(pixel), atol=0.75)
    assert np.min(np.sum(np.asarray(proj.normal) * np.asarray(points.normal_image), -1)) > 0.99
    assert not np.any(np.asarray(bare.normal))
    assert np.all(np.asarray(bare_proj.valid)) and np.max(np.abs(_at(sdf, np.asarray(bare_proj.center)))) < 1.0


def test_view_model_cache_round_trip(tmp_path, monkeypatch):
    mesh = box_mesh((50, 30, 20), F32)
    settings = {"num_points": 20, "subdivisions": 0, "image_size": 48}
    first = L.load_or_build_view_model(mesh, cache_dir=tmp_path, **settings)
    path = L.view_model_path(mesh, tmp_path, **settings)
    assert path.is_file() and len(list(tmp_path.iterdir())) == 1

    def no_build(*args, **kwargs):
        raise AssertionError("the cached model should have been loaded")

    monkeypatch.setattr(_viewmodel, "build_view_model", no_build)
    second = L.load_or_build_view_model(mesh, cache_dir=tmp_path, **settings)
    for a, b in zip(jax.tree_util.tree_leaves(first), jax.tree_util.tree_leaves(second)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        assert a.dtype == b.dtype
    other = L.view_model_path(box_mesh((50, 30, 21), F32), tmp_path, **settings)
    assert other != path and L.view_model_path(mesh, tmp_path, **dict(settings, num_points=21)) != path


# ------------------------------------------------------------------------------------------ tracking

@pytest.mark.parametrize("cull", [False, True])
def test_view_plan_extents_equal_a_per_view_reference(cull):
    """The build's face extents (a few views at a time, from the distinct vertex positions) equal the direct
    per-view computation on a mesh whose faces repeat their vertices, and the plan covers every view's classes."""
    torus = torus_mesh(40.0, 12.0, 12, 8, F32)
    v, f = np.asarray(torus.vertices, np.float64), np.asarray(torus.faces)
    vertices, faces = v[f].reshape(-1, 3), np.arange(3 * len(f)).reshape(-1, 3)  # no shared vertices
    directions, _ = _viewmodel.icosphere(1)
    K, T = _viewmodel._view_cameras(np.zeros(3), 52.0, directions, 64, 3.0)
    got = _viewmodel._face_extents_all(vertices, faces, K, T, 64, cull)
    assert got.shape == (len(T), len(faces)) and got.max() > 0
    for view in range(len(T)):
        p = vertices @ T[view, :3, :3].T + T[view, :3, 3]
        tri = np.stack([K[0, 0] * p[:, 0] / p[:, 2] + K[0, 2], K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2]], -1)[faces]
        lo, hi = np.maximum(np.ceil(tri.min(1)), 0), np.minimum(np.floor(tri.max(1)), 63)
        ok = np.all(hi >= lo, axis=-1)
        if cull:
            e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
            ok &= e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0] < 0
        np.testing.assert_array_equal(got[view], np.where(ok, (hi - lo + 1).max(-1), 0))
    plan = _viewmodel._tight_plan(got, cull)
    sizes = np.asarray(plan.patch_sizes)
    for view in range(len(T)):
        e = got[view][got[view] > 0]
        need = np.bincount(np.searchsorted(sizes, e), minlength=len(sizes))
        assert np.all(need[: len(sizes)] <= np.asarray(plan.capacities)) and need.max() > 0



@pytest.fixture(scope="module")
def box_scene():
    """A box rendered at a true pose (flat colours + noise), its view model and histograms at that pose."""
    mesh = box_mesh((90, 70, 60), F32)
    vm = L.build_view_model(mesh, num_points=200, subdivisions=1, image_size=256, batch_size=42)
    camera = _camera()
    T_true = _pose([2.2, 0.9, -0.4], [3.0, -2.0, 170.0])
    sil = _raycast_silhouette(mesh, camera, T_true)
    rng = np.random.default_rng(0)
    image = np.clip(np.where(sil[..., None], FG, BG) + rng.normal(0, 10, sil.shape + (3,)), 0, 255).astype(np.float32)
    params = L.line_params(F32)
    config = L.LineConfig(max_scale=2)
    learn = jax.jit(lambda T, image: L.learn_line_histograms(camera, T, vm, image, params, 32, config))
    hist = learn(jnp.asarray(T_true, F32), jnp.asarray(image))
    return {"mesh": mesh, "vm": vm, "camera": camera, "T_true": T_true, "image": jnp.asarray(image),
            "params": params, "config": config, "hist": hist}


def test_view_model_points_of_a_box_lie_on_the_contour(box_scene):
    vm = box_scene["vm"]
    assert vm.points.shape == (42, 200, 3)
    _check_normals(vm)
    _check_view_model_on_raycast_contour(box_scene["mesh"], vm)


SCALES, STDS = jnp.array([2, 1, 1, 1, 1, 1]), jnp.array([5.0, 3.0, 1.5])


def test_line_rows_and_solve_converge_on_a_box(box_scene):
    s = box_scene
    starts = [
        _perturb(s["T_true"], [0.03, -0.03, 0.02], [3.0, -3.0, 2.0]),  # 4.7 mm, 2.7°
        _perturb(s["T_true"], [-0.04, 0.0, 0.03], [-2.0, 4.0, -2.0]),  # 4.9 mm, 2.9°
    ]
    for T0 in starts:
        assert _errors(T0, s["T_true"])[0] > 4.5 and _errors(T0, s["T_true"])[1] > 2.5

    def refine(T0):
        return L.refine_pose_lines(s["camera"], T0, s["vm"], s["image"], s["hist"], s["params"], SCALES, STDS, 6,
                                   s["config"], jt.SolverConfig(max_steps=2))

    out = jax.jit(jax.vmap(refine))(jnp.asarray(np.stack(starts), F32))  # a batch of pose hypotheses
    for k in range(len(starts)):
        t_err, r_err = _errors(out.T_world_root[k], s["T_true"])
        assert t_err < 1.0 and r_err < 0.5, (k, t_err, r_err)
        assert jt.Status(int(out.status[k])).usable and int(out.num_lines[k]) > 120


def test_line_rows_compile_once_and_give_edge_rows(box_scene):
    s = box_scene
    rows = eqx.filter_jit(eqx.debug.assert_max_traces(L.line_rows, max_traces=1))
    args = (s["vm"], s["image"], s["hist"], s["params"])
    T1 = jnp.asarray(_perturb(s["T_true"], [0.01, 0.0, 0.0], [1.0, 0.0, 0.0]), F32)
    c1 = rows(s["camera"], T1, *args, jnp.int32(2), jnp.float32(5.0), s["config"])
    c2 = rows(s["camera"], jnp.asarray(s["T_true"], F32), s["vm"], s["image"] * 0.9, s["hist"], s["params"],
              jnp.int32(1), jnp.float32(1.5), s["config"])
    assert eqx.debug.get_num_traces(rows) == 1
    for c in (c1, c2):
        assert c.weight.dtype == F32 and c.capacity == 200
        live = np.asarray(c.weight) > 0
        assert live.sum() > 120
        assert np.all(np.asarray(c.tangent_weight) == 0)
        np.testing.assert_allclose(np.linalg.norm(np.asarray(c.normal)[live], axis=-1), 1.0, atol=1e-5)
        assert np.all(np.asarray(c.cue) == int(jt.Cue.REGION))
    # a sweep over parameters is one vmapped call: twice the weight, twice the rows' weights
    sweep = jax.tree_util.tree_map(lambda a: jnp.stack([a, a]), s["params"])
    sweep = eqx.tree_at(lambda p: p.weight, sweep, jnp.array([1.0, 2.0], F32))
    batch = jax.jit(jax.vmap(lambda p: L.line_rows(s["camera"], T1, s["vm"], s["image"], s["hist"], p, 2, 5.0,
                                                    s["config"])))(sweep)
    np.testing.assert_allclose(np.asarray(batch.weight[1]), 2 * np.asarray(batch.weight[0]), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(batch.weight[0]), np.asarray(c1.weight), rtol=1e-5)


def test_pose_after_rounds_differentiates_like_finite_differences(box_scene):
    s = box_scene
    f64 = jnp.float64
    to64 = lambda tree: jax.tree_util.tree_map(lambda a: a.astype(f64) if jnp.issubdtype(a.dtype, jnp.floating) else a, tree)
    camera = _camera(dtype=f64)
    vm, image, hist, params = to64(s["vm"]), s["image"].astype(f64), to64(s["hist"]), to64(s["params"])
    T0 = jnp.asarray(_perturb(s["T_true"], [0.01, -0.01, 0.01], [1.0, -1.0, 1.0]), f64)
    solver = jt.SolverConfig(max_steps=30, rtol=1e-13, atol=1e-13)
    uniform = jnp.full_like(hist.fg, 1.0 / hist.fg.shape[0])

    def final_pose(theta):
        amplitude, mix = theta
        p = eqx.tree_at(lambda q: q.function_amplitude, params, amplitude)
        h = eqx.tree_at(lambda q: q.fg, hist, (1 - mix) * hist.fg + mix * uniform)  # a histogram parameter
        out = L.refine_pose_lines(camera, T0, vm, image, h, p, jnp.array([1, 1]), jnp.array([1.5, 1.5]), 2,
                                  s["config"], solver)
        return jnp.concatenate([out.T_world_root[:3, 3], out.T_world_root[:3, :3].reshape(-1) * 100.0])

    theta = jnp.array([0.43, 0.3], f64)
    jvp = jax.jit(lambda x, v: jax.jvp(final_pose, (x,), (v,)))  # one program: primal and tangent
    jac = np.stack([np.asarray(jvp(theta, e)[1]) for e in jnp.eye(2, dtype=f64)], -1)
    eps = 1e-5
    fd = np.stack([(np.asarray(jvp(theta + eps * e, e)[0]) - np.asarray(jvp(theta - eps * e, e)[0])) / (2 * eps)
                   for e in jnp.eye(2, dtype=f64)], -1)
    assert np.max(np.abs(jac)) > 1e-2  # the parameters do move the pose
    np.testing.assert_allclose(jac, fd, rtol=1e-4, atol=1e-5 * np.max(np.abs(fd)))


def test_a_build_reports_its_views_to_the_progress_hook():
    """`view_model_build_progress`: within the block each batch of views is reported (done, total); outside, none."""
    mesh = box_mesh((50, 30, 20), F32)
    seen = []
    with L.view_model_build_progress(lambda done, total: seen.append((done, total))):
        L.build_view_model(mesh, num_points=8, subdivisions=0, image_size=32, batch_size=8)
    assert seen == [(8, 12), (12, 12)]
    L.build_view_model(mesh, num_points=8, subdivisions=0, image_size=32, batch_size=8)
    assert len(seen) == 2
