"""The SIFT cue: detection and matching on synthetic pairs with exact poses, the outlier filters,
both vertex assignments, several cameras, homogeneous objects, validation and trace counts."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxtrack as jt
from jaxtrack.cues.sift import (
    SiftConfig,
    SiftMatches,
    backprojection_filter,
    detect_sift,
    match_descriptors,
    remove_gross_and_static,
    reprojection_errors,
    sift_correspondences,
    sift_matches,
    sift_params,
)
from jaxtrack.cues.sift._assign import _correspondences_body
from jaxtrack.cues.sift._filters import _filter_body
from jaxtrack.geometry import rigid_model, rotation_error_deg, stack_cameras
from jaxtrack.render import Renderer, RenderOutput, make_mesh
from jaxtrack.solve import Cue, solve_pose
from jaxtrack.synth import PRESETS, SynthConfig, render_sequence

F64 = jnp.float64


def _stack(rendered):
    return jax.tree.map(lambda x: x[None], rendered)


@pytest.fixture(scope="module")
def textured(shared_data):
    """The photo-textured tea box with large motion (30 px, 10° per frame), full 640x480."""
    cfg = dataclasses.replace(PRESETS["teabox-large-motion"], frames=3)
    seq = render_sequence(cfg)
    mesh = make_mesh(seq["mesh"].vertices, seq["mesh"].faces, dtype=F64)
    camera = jt.make_camera(seq["K"], cfg.width, cfg.height, dtype=F64)
    return seq, mesh, camera, Renderer(mesh, camera)


def _pair_correspondences(seq, renderer, camera, k, params):
    matches = sift_matches(seq["images"][0][k][None], seq["images"][0][k + 1][None], seq["object_mask"][0][k][None], dtype=F64)
    filtered = remove_gross_and_static(matches, params)
    rendered = _stack(renderer(jnp.asarray(seq["T_cam_obj"][0][k])))
    return matches, filtered, sift_correspondences(filtered, rendered, stack_cameras([camera]), params)


def test_textured_pair_correspondences_and_pose(textured):
    seq, _, camera, renderer = textured
    params, model, cams = sift_params(dtype=F64), rigid_model(F64), stack_cameras([camera])
    T0, T1 = seq["T_cam_obj"][0][0], seq["T_cam_obj"][0][1]
    _, _, corr = _pair_correspondences(seq, renderer, camera, 0, params)
    assert int(corr.count_by_cue(Cue.SIFT)) == int(corr.num_effective()) >= 30
    # Preliminary pose from the matches alone, then the back-projection check and the final pose.
    first = solve_pose(model, corr, jnp.asarray(T0))
    kept = backprojection_filter(corr, cams, model, first.T_world_root, first.theta, params)
    final = solve_pose(model, kept, first.T_world_root)
    live = np.asarray(kept.weight) > 0
    err = np.asarray(reprojection_errors(kept, cams, model, jnp.asarray(T1)))[live]
    assert live.sum() >= 30 and np.mean(err <= 2.0) >= 0.95, np.sort(err)[-5:]
    assert int(final.status) == 0
    assert float(rotation_error_deg(final.T_world_root[:3, :3], jnp.asarray(T1[:3, :3]))) <= 1.0
    assert abs(float(final.T_world_root[2, 3]) - T1[2, 3]) <= 0.02 * T1[2, 3]


def test_compiles_once_over_a_sequence(textured):
    seq, _, camera, renderer = textured
    params = sift_params(dtype=F64)
    counts = []
    for k in range(2):
        _pair_correspondences(seq, renderer, camera, k, params)
        counts.append((eqx.debug.get_num_traces(_filter_body), eqx.debug.get_num_traces(_correspondences_body)))
    assert counts[1] == counts[0]  # the second pair reused the compiled programs


def test_roi_and_full_frame_detection_agree(textured):
    seq = textured[0]
    mask = seq["object_mask"][0][0]
    # Every keypoint (`max_keypoints=0`): a bound would apply to the crop in one case, the whole frame in the other.
    roi, _ = detect_sift(seq["images"][0][0], mask, SiftConfig(roi=True, max_side=0, max_keypoints=0))
    full, _ = detect_sift(seq["images"][0][0], mask, SiftConfig(roi=False, max_side=0, max_keypoints=0))
    assert len(roi) > 30 and abs(len(roi) - len(full)) <= 0.2 * len(full)
    # Keypoints lie in the mask (up to OpenCV's sub-pixel refinement at its border).
    ys, xs = np.nonzero(mask)
    inside = mask[np.round(roi[:, 1]).astype(int).clip(0, 479), np.round(roi[:, 0]).astype(int).clip(0, 639)]
    assert inside.mean() >= 0.95
    assert roi[:, 0].min() >= xs.min() - 1 and roi[:, 0].max() <= xs.max() + 1
    assert roi[:, 1].min() >= ys.min() - 1 and roi[:, 1].max() <= ys.max() + 1


def test_shrunk_detection_maps_keypoints_back_to_the_frame(textured):
    """`max_side` shrinks the detection crop: fewer keypoints, in full-frame pixels, most of them at a native
    keypoint (within 1.5 px), all inside the mask; the crop's longer side here is > 192 px."""
    seq = textured[0]
    image, mask = seq["images"][0][0], seq["object_mask"][0][0]
    native, _ = detect_sift(image, mask, SiftConfig(max_side=0))
    small, desc = detect_sift(image, mask, SiftConfig(max_side=96))
    assert 10 <= len(small) < len(native) and desc.shape == (len(small), 128)
    ys, xs = np.nonzero(mask)
    assert xs.max() - xs.min() > 96 or ys.max() - ys.min() > 96  # the crop was shrunk
    inside = mask[np.round(small[:, 1]).astype(int).clip(0, 479), np.round(small[:, 0]).astype(int).clip(0, 639)]
    assert inside.mean() >= 0.9
    nearest = np.min(np.linalg.norm(small[:, None, :] - native[None, :, :], axis=-1), axis=1)
    assert np.median(nearest) <= 1.5, np.median(nearest)
    with pytest.raises(ValueError, match="max_side"):
        SiftConfig(max_side=8)


def test_max_keypoints_keeps_the_strongest_of_a_detection(textured):
    """`max_keypoints` bounds a detection to the keypoints of the strongest DoG response (OpenCV's `nfeatures`):
    at most that many, each one of the unbounded detection's keypoints with its descriptor; 0 keeps all."""
    seq = textured[0]
    image, mask = seq["images"][0][0], seq["object_mask"][0][0]
    every, desc_every = detect_sift(image, mask, SiftConfig(max_side=0, max_keypoints=0))
    assert len(every) > 40
    bound = len(every) // 3
    few, desc_few = detect_sift(image, mask, SiftConfig(max_side=0, max_keypoints=bound))
    assert 0 < len(few) <= bound and desc_few.shape == (len(few), 128)
    # Each kept keypoint is one of the unbounded detection's, with its descriptor (a location can carry several
    # orientations: the same place and the same descriptor).
    same_place = np.linalg.norm(few[:, None, :] - every[None, :, :], axis=-1) < 1e-3
    same_descriptor = np.abs(desc_few[:, None, :] - desc_every[None, :, :]).max(-1) < 1e-3
    assert np.all((same_place & same_descriptor).any(1))
    # A larger bound keeps a superset (the order is by response); the default is a bound too.
    more, _ = detect_sift(image, mask, SiftConfig(max_side=0, max_keypoints=2 * bound))
    assert len(few) <= len(more) and np.all(np.min(np.linalg.norm(few[:, None] - more[None], axis=-1), axis=1) < 1e-3)
    assert len(detect_sift(image, mask, SiftConfig(max_side=0))[0]) <= SiftConfig().max_keypoints  # the default bounds
    with pytest.raises(ValueError, match="max_keypoints"):
        SiftConfig(max_keypoints=-1)


def test_cached_keypoints_of_t_plus_1_serve_the_next_pair(textured):
    """With a cache, frame t+1's keypoints are kept and the next call reuses them for its frame t (one detection
    per frame): the matches of the second pair are close to those detected afresh, and a different frame t is
    detected (the cache holds another image)."""
    seq = textured[0]
    imgs, masks = seq["images"][0], seq["object_mask"][0]
    cache, timings = {}, {}
    sift_matches(imgs[0][None], imgs[1][None], masks[0][None], cache=cache)
    assert np.array_equal(cache[0][0], imgs[1])
    reused = sift_matches(imgs[1][None], imgs[2][None], masks[1][None], cache=cache, timings=timings)
    fresh = sift_matches(imgs[1][None], imgs[2][None], masks[1][None])
    n_reused, n_fresh = int(reused.count()[0]), int(fresh.count()[0])
    assert n_reused >= 0.8 * n_fresh and n_fresh >= 30, (n_reused, n_fresh)
    motion = np.asarray(reused.p_t1 - reused.p_t)[0][np.asarray(reused.valid[0])]
    motion_fresh = np.asarray(fresh.p_t1 - fresh.p_t)[0][np.asarray(fresh.valid[0])]
    np.testing.assert_allclose(np.median(motion, 0), np.median(motion_fresh, 0), atol=1.0)
    # Another frame t than the cached t+1: no reuse (the keypoints of frame 0 are detected again).
    again = sift_matches(imgs[0][None], imgs[1][None], masks[0][None], cache=cache)
    first = sift_matches(imgs[0][None], imgs[1][None], masks[0][None])
    np.testing.assert_array_equal(again.p_t, first.p_t)


@pytest.mark.parametrize("background", ["flat", "coffee"])
def test_homogeneous_object_gives_few_or_none(background, shared_data):
    cfg = SynthConfig(object="box", appearance="flat", background=background, motion="random", step_px=10, step_deg=3, frames=2)
    seq = render_sequence(cfg)
    mesh = make_mesh(seq["mesh"].vertices, seq["mesh"].faces, dtype=F64)
    camera = jt.make_camera(seq["K"], cfg.width, cfg.height, dtype=F64)
    params = sift_params(dtype=F64)
    matches, _, corr = _pair_correspondences(seq, Renderer(mesh, camera), camera, 0, params)
    assert int(corr.num_effective()) <= 5, int(corr.num_effective())
    assert corr.weight.shape == (SiftConfig().capacity,)
    if background == "flat":  # the box's corners, shrunk to the detection size (`max_side`), may make a blob or two
        assert int(matches.count()[0]) <= 2


def test_empty_region_and_empty_descriptor_sets():
    img = np.random.default_rng(0).uniform(0, 255, (2, 64, 80)).astype(np.uint8)
    m = sift_matches(img[:1], img[1:], np.zeros((1, 64, 80), bool), SiftConfig(capacity=8))
    assert m.valid.shape == (1, 8) and not np.any(m.valid)
    ia, ib, r = match_descriptors(np.zeros((0, 128), np.float32), np.ones((3, 128), np.float32))
    assert ia.size == ib.size == r.size == 0
    ia, _, _ = match_descriptors(np.ones((3, 128), np.float32), np.ones((1, 128), np.float32))
    assert ia.size == 0  # one candidate: the ratio test cannot be applied


def test_conflicting_matches_are_deleted():
    rng = np.random.default_rng(1)
    b = rng.normal(size=(6, 128)).astype(np.float32)
    a = np.concatenate([b[:4] + 0.01 * rng.normal(size=(4, 128)), b[2:3] + 0.01 * rng.normal(size=(1, 128))]).astype(np.float32)
    ia, ib, _ = match_descriptors(a, b, 0.6)
    # a[2] and a[4] both pick b[2]: both go; the other three stay.
    assert sorted(zip(ia.tolist(), ib.tolist())) == [(0, 0), (1, 1), (3, 3)]


def _synthetic_matches(rng, motion, true=40, static=8, gross=6, capacity=64):
    p_t = rng.uniform(100, 300, (capacity, 2))
    d = np.zeros((capacity, 2))
    d[:true] = motion + rng.normal(scale=0.3 * np.linalg.norm(motion) / 4 + 0.05, size=(true, 2))
    d[true + static : true + static + gross] = rng.uniform(60, 150, (gross, 2)) * rng.choice([-1, 1], (gross, 2))
    valid = np.zeros(capacity, bool)
    valid[: true + static + gross] = True
    kind = np.array(["true"] * true + ["static"] * static + ["gross"] * gross + ["pad"] * (capacity - true - static - gross))
    return SiftMatches(jnp.asarray(p_t[None]), jnp.asarray((p_t + d)[None]), jnp.asarray(valid[None])), kind


def test_filters_remove_what_they_should():
    rng = np.random.default_rng(2)
    params = sift_params(dtype=F64)
    # Large motion: static background matches and gross mismatches go, true matches stay.
    matches, kind = _synthetic_matches(rng, np.array([12.0, -7.0]))
    kept = np.asarray(remove_gross_and_static(matches, params).valid[0])
    assert kept[kind == "true"].all() and not kept[kind == "static"].any() and not kept[kind == "gross"].any()
    assert not kept[kind == "pad"].any()
    # A still object: nothing is "static background", gross mismatches still go.
    matches, kind = _synthetic_matches(rng, np.array([0.3, 0.2]))
    kept = np.asarray(remove_gross_and_static(matches, params).valid[0])
    assert kept[kind == "true"].all() and kept[kind == "static"].all() and not kept[kind == "gross"].any()
    # The filters are per camera: a second camera with other motion is judged on its own.
    other, kind2 = _synthetic_matches(rng, np.array([-20.0, 3.0]))
    both = jax.tree.map(lambda a, b: jnp.concatenate([a, b]), matches, other)
    kept2 = np.asarray(remove_gross_and_static(both, params).valid)
    np.testing.assert_array_equal(kept2[0], kept)
    assert kept2[1][kind2 == "true"].all() and not kept2[1][kind2 == "static"].any()


def _plane_scene(num_cameras=1):
    """A dense fronto-parallel grid (100 mm, 5 mm spacing) moved sideways: every point of it shifts
    by the same pixels, so moving the nearest vertex by a match's displacement is exact."""
    g = np.linspace(-50, 50, 21)
    xx, yy = np.meshgrid(g, g)
    verts = np.stack([xx.ravel(), yy.ravel(), np.zeros(xx.size)], -1)
    idx = np.arange(441).reshape(21, 21)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    faces = np.concatenate([np.stack([a, b, c], -1), np.stack([a, c, d], -1)])
    mesh = make_mesh(verts, faces, dtype=F64)
    cams = [jt.make_camera(np.array([[500.0, 0, 159.5], [0, 500.0, 119.5], [0, 0, 1]]), 320, 240, t_cam_world=[-30.0 * c, 0, 0], dtype=F64) for c in range(num_cameras)]
    T0 = np.eye(4)
    T0[:3, 3] = [3.0, -2.0, 500.0]
    T1 = T0.copy()
    T1[:3, 3] += [8.0, 5.0, 0.0]
    return mesh, cams, T0, T1


def _true_matches(rng, cams, T0, T1, capacity=32, count=24):
    pts = np.concatenate([rng.uniform(-45, 45, (count, 2)), np.zeros((count, 1))], 1)
    p_t, p_t1 = [], []
    for cam in cams:
        for T, out in ((T0, p_t), (T1, p_t1)):
            px, _ = jt.geometry.project_points(cam, jnp.asarray(pts @ T[:3, :3].T + T[:3, 3]))
            out.append(np.pad(np.asarray(px), ((0, capacity - count), (0, 0))))
    valid = np.zeros((len(cams), capacity), bool)
    valid[:, :count] = True
    return SiftMatches(jnp.asarray(np.stack(p_t)), jnp.asarray(np.stack(p_t1)), jnp.asarray(valid))


@pytest.mark.parametrize("mode", ["surface", "vertex"])
def test_assignment_exact_for_a_uniform_shift_two_cameras(mode):
    rng = np.random.default_rng(3)
    mesh, cams, T0, T1 = _plane_scene(num_cameras=2)
    rig = stack_cameras(cams)
    rendered = jax.tree.map(lambda *x: jnp.stack(x), *[Renderer(mesh, c)(jnp.asarray(T0)) for c in cams])
    matches = _true_matches(rng, cams, T0, T1)
    params, model = sift_params(dtype=F64), rigid_model(F64)
    corr = sift_correspondences(matches, rendered, rig, params, mode=mode, mesh=mesh, T_world_root=jnp.asarray(T0))
    live = np.asarray(corr.weight) > 0
    assert live.sum() == 48 and set(np.asarray(corr.camera)[live].tolist()) == {0, 1}
    err = np.asarray(reprojection_errors(corr, rig, model, jnp.asarray(T1)))[live]
    np.testing.assert_array_less(err, 1e-6)
    sol = solve_pose(model, corr, jnp.asarray(T0))
    np.testing.assert_allclose(sol.T_world_root, T1, atol=1e-5)
    if mode == "vertex":  # keypoints more than max_vertex_px from every vertex are dropped
        tight = sift_correspondences(matches, rendered, rig, sift_params(max_vertex_px=1.0, dtype=F64), mode=mode, mesh=mesh, T_world_root=jnp.asarray(T0))
        assert 0 < int(tight.num_effective()) < 48


def test_backprojection_filter_drops_the_disagreeing():
    rng = np.random.default_rng(4)
    mesh, cams, T0, T1 = _plane_scene()
    rig = stack_cameras(cams)
    matches = _true_matches(rng, cams, T0, T1)
    bad = np.zeros(matches.valid.shape, bool)
    bad[0, [1, 5, 9]] = True
    matches = eqx.tree_at(lambda m: m.p_t1, matches, matches.p_t1 + jnp.asarray(bad[..., None] * np.array([6.0, -4.0])))
    params, model = sift_params(dtype=F64), rigid_model(F64)
    corr = sift_correspondences(matches, _stack(Renderer(mesh, cams[0])(jnp.asarray(T0))), rig, params)
    kept = backprojection_filter(corr, rig, model, jnp.asarray(T1), jnp.zeros(0), params)
    np.testing.assert_array_equal(np.asarray(kept.weight) > 0, np.asarray(matches.valid[0]) & ~bad[0])


def test_validation_errors():
    with pytest.raises(ValueError, match="ratio"):
        SiftConfig(ratio=1.5)
    with pytest.raises(ValueError, match="gross_factor"):
        sift_params(gross_factor=0.0)
    for bad in (5.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="boundary_px"):
            sift_params(boundary_px=bad)
    img = np.zeros((1, 32, 32), np.uint8)
    with pytest.raises(ValueError, match="region_t"):
        sift_matches(img, img, np.zeros((1, 16, 16), bool))
    with pytest.raises(ValueError, match="images_t"):
        sift_matches(img, np.zeros((1, 32, 33), np.uint8), np.zeros((1, 32, 32), bool))
    with pytest.raises(ValueError, match="mask"):
        detect_sift(img[0], np.zeros((4, 4), bool))
    _, cams, _, _ = _plane_scene()
    empty = SiftMatches(jnp.zeros((1, 4, 2)), jnp.zeros((1, 4, 2)), jnp.zeros((1, 4), bool))
    with pytest.raises(ValueError, match="mode"):
        sift_correspondences(empty, None, stack_cameras(cams), sift_params(), mode="nearest")
    with pytest.raises(ValueError, match="vertex"):
        sift_correspondences(empty, None, stack_cameras(cams), sift_params(), mode="vertex")


@pytest.mark.parametrize("boundary_px", [0.0, 1.0, 2.0])
def test_a_keypoint_near_another_part_or_the_background_makes_no_row(boundary_px):
    """`SiftParams.boundary_px`: a keypoint makes a row only where the render shows its own part at every pixel
    within that distance (Chebyshev: a pixel diagonally next to it is 1 away): two parts side by side (columns 10-19
    and 20-29 of rows 10-29) with a one-pixel hole at (15, 15), background around them; through
    `sift_correspondences`, as the tracker calls it."""
    part = np.full((40, 40), -1, np.int32)
    part[10:30, 10:20], part[10:30, 20:30] = 0, 1
    part[15, 15] = -1
    on = jnp.asarray(part) >= 0
    rendered = _stack(RenderOutput(depth=jnp.where(on, 500.0, jnp.inf), face_id=jnp.where(on, 7, -1),
                                   p_model=jnp.zeros((40, 40, 3)), part_id=jnp.asarray(part),
                                   vertex_visible=jnp.zeros((1,), bool), overflow=jnp.zeros((), bool),
                                   near_clipped=jnp.zeros((), jnp.int32), status=jnp.zeros((), jnp.int32)))
    # (column, row) of keypoints and their Chebyshev distance to the nearest pixel of another part or background
    points = np.array([[16.0, 16.0], [18.0, 20.0], [17.0, 20.0], [21.0, 20.0], [25.0, 11.0], [25.0, 12.0],
                       [25.0, 28.0], [12.0, 24.0], [19.0, 20.0], [5.0, 5.0]])
    distance = np.array([1, 2, 3, 2, 2, 3, 2, 3, 1, 0])
    _, cams, _, _ = _plane_scene()
    matches = SiftMatches(jnp.asarray(points[None]), jnp.asarray(points[None] + 1.5), jnp.ones((1, len(points)), bool))
    corr = sift_correspondences(matches, rendered, stack_cameras(cams[:1]), sift_params(boundary_px=boundary_px, dtype=F64))
    np.testing.assert_array_equal(np.asarray(corr.weight) > 0, (distance > boundary_px) & (distance > 0))
    kept = np.asarray(corr.weight) > 0
    np.testing.assert_array_equal(np.asarray(corr.part)[kept], part[points[kept, 1].astype(int), points[kept, 0].astype(int)])
