"""Rasteriser: exactness against an independent ray caster (embree via trimesh), plans, jit."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxtrack as jt
from jaxtrack.render import box_mesh, face_extents, make_mesh, plan_raster, render, torus_mesh
from jaxtrack.synth import look_at

K = np.array([[600.0, 0, 319.5], [0, 600.0, 239.5], [0, 0, 1]])


def _camera(eye):
    R, t = look_at(eye)
    return jt.make_camera(K, 640, 480, R, t), R, t


def ray_cast(mesh, R, t, width=640, height=480, K=K):
    """Reference: embree ray casting through every pixel centre. Returns face id and depth (H, W)."""
    trimesh = pytest.importorskip("trimesh")
    from trimesh.ray.ray_pyembree import RayMeshIntersector

    tm = trimesh.Trimesh(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces), process=False)
    v, u = np.mgrid[0:height, 0:width]
    d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones(u.shape)], -1).reshape(-1, 3)
    d_world = d_cam @ R
    d_world /= np.linalg.norm(d_world, axis=1, keepdims=True)
    origin = -R.T @ t
    loc, ray_idx, tri_idx = RayMeshIntersector(tm).intersects_location(
        np.repeat(origin[None], len(d_world), 0), d_world, multiple_hits=False
    )
    face = np.full(height * width, -1)
    face[ray_idx] = tri_idx
    depth = np.full(height * width, np.inf)
    depth[ray_idx] = (loc @ R.T + t)[:, 2]
    return face.reshape(height, width), depth.reshape(height, width)


def _mixed_mesh():
    """A huge ground quad plus a cloud of tiny triangles above it."""
    rng = np.random.default_rng(0)
    verts = [[-400, -400, 60], [400, -400, 60], [400, 400, 60], [-400, 400, 60]]
    faces = [[0, 2, 1], [0, 3, 2]]
    for k in range(300):
        c = rng.uniform(-120, 120, 3) * [1, 1, 0.3]
        tri = c + rng.normal(scale=2.5, size=(3, 3))
        verts += tri.tolist()
        faces.append([4 + 3 * k, 5 + 3 * k, 6 + 3 * k])
    return make_mesh(np.array(verts), np.array(faces))


@pytest.mark.parametrize(
    "name, mesh_fn, eye, cull, dense",
    [
        ("torus", torus_mesh, [0, -250, -350], False, None),
        ("torus-culled", torus_mesh, [0, -250, -350], True, None),
        ("box-culled", lambda: box_mesh((160, 70, 80)), [120, -160, -300], True, False),
        ("box-culled-dense", lambda: box_mesh((160, 70, 80)), [120, -160, -300], True, True),
        ("mixed", _mixed_mesh, [30, -20, -420], False, None),
    ],
)
def test_matches_ray_caster(name, mesh_fn, eye, cull, dense):
    """Through the plan's patches (the torus and the mixed mesh: `render`'s own choice) and every face at every pixel
    (`RasterPlan.dense`) for the box."""
    mesh = mesh_fn()
    cam, R, t = _camera(eye)
    T = jnp.eye(4)
    plan = plan_raster(face_extents(mesh, cam, T, cull_backfaces=cull), cull_backfaces=cull)
    if dense is None:
        assert not jt.render.dense_is_cheaper(plan, mesh.num_faces, 640, 480)
    plan = dataclasses.replace(plan, dense=dense)
    out = jax.jit(lambda T: render(mesh, cam, T, plan=plan))(T)
    assert not bool(out.overflow) and int(out.status) == jt.Status.OK
    _assert_matches_ray_caster(out, mesh, R, t)


def _assert_matches_ray_caster(out, mesh, R, t, width=640, height=480, K=K):
    face_ref, depth_ref = ray_cast(mesh, R, t, width, height, K)
    sil, sil_ref = np.asarray(out.silhouette), face_ref >= 0
    iou = (sil & sil_ref).sum() / (sil | sil_ref).sum()
    both = sil & sil_ref
    agree = (np.asarray(out.face_id)[both] == face_ref[both]).mean()
    depth_err = np.abs(np.asarray(out.depth)[both] - depth_ref[both])
    same_face = np.asarray(out.face_id)[both] == face_ref[both]
    assert iou >= 0.999, iou
    assert agree >= 0.99, agree
    # Depth < 0.01 mm wherever both pick the same face; on a shared edge the other face's depth
    # differs only by the slope across a fraction of a pixel.
    assert depth_err[same_face].max() < 0.01, depth_err[same_face].max()
    assert depth_err.max() < 0.05, depth_err.max()
    # Surface points lie on the ray of their pixel at the rendered depth.
    p_cam = np.asarray(out.p_model)[both] @ R.T + t
    np.testing.assert_allclose(p_cam[:, 2], np.asarray(out.depth)[both], atol=0.02)


def test_visibility_and_parts_of_an_articulated_mesh():
    # Two boxes side by side on a joint at the origin; the second part bends behind the first.
    a = box_mesh((100, 40, 40))
    verts = np.concatenate([np.asarray(a.vertices) - [50, 0, 0], np.asarray(a.vertices) + [50, 0, 0]])
    faces = np.concatenate([np.asarray(a.faces), np.asarray(a.faces) + 8])
    mesh = make_mesh(verts, faces, vertex_part=np.r_[np.zeros(8), np.ones(8)])
    model = jt.chain_model([-1, 0], [(0, 1, 0)], [(0, 0, 0)])
    cam, _, _ = _camera([0, 0, -400])
    out = jt.render.Renderer(mesh, cam, model)(jnp.eye(4), jnp.array([0.0]))
    assert set(np.unique(np.asarray(out.part_id))) == {-1, 0, 1}
    # Front-face vertices (z = −20) are visible, back-face vertices (z = +20) are hidden.
    vis = np.asarray(out.vertex_visible)
    front = verts[:, 2] < 0
    assert vis[front].all() and not vis[~front].any()


def test_renders_compile_once_over_a_sequence():
    mesh = torus_mesh()
    cam, _, _ = _camera([0, -250, -350])
    plan = plan_raster(face_extents(mesh, cam, jnp.eye(4)))

    @jax.jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def draw(T):
        return render(mesh, cam, T, plan=plan).silhouette.sum()

    for k in range(5):
        draw(jt.se3_exp(jnp.array([k * 2.0, 0, 0, 0, 0.02 * k, 0])))


def test_faces_spill_into_larger_classes():
    """A plan made for big faces still draws the same object far away (its faces now of smaller classes than
    planned): they take the spare slots of the larger classes, the image is the same as with a plan made for
    that pose (which `test_matches_ray_caster` checks against embree), and only more faces of a class and above
    than those classes hold is an overflow."""
    mesh = torus_mesh()
    near_cam, _, _ = _camera([0, -125, -175])
    far_cam, _, _ = _camera([0, -250, -350])
    near_plan = plan_raster(face_extents(mesh, near_cam, jnp.eye(4)))  # margin 1.3
    far_plan = plan_raster(face_extents(mesh, far_cam, jnp.eye(4)), margin=1.0, minimum=1)
    assert min(near_plan.patch_sizes) > min(far_plan.patch_sizes)  # the far faces have classes the near plan lacks
    far_ext = face_extents(mesh, far_cam, jnp.eye(4))
    assert sum(near_plan.capacities) >= int((far_ext > 0).sum())  # the near plan holds that many faces in all
    spilled = render(mesh, far_cam, jnp.eye(4), plan=near_plan)
    exact = render(mesh, far_cam, jnp.eye(4), plan=far_plan)
    assert not bool(spilled.overflow) and int(spilled.status) == jt.Status.OK
    np.testing.assert_array_equal(np.asarray(spilled.face_id), np.asarray(exact.face_id))
    np.testing.assert_array_equal(np.asarray(spilled.depth), np.asarray(exact.depth))
    assert int(spilled.silhouette.sum()) > 1000  # the torus is on screen
    # Too few slots in the largest class for its own faces: reported, never silently dropped.
    short = jt.render.RasterPlan(near_plan.patch_sizes, near_plan.capacities[:-1] + (0,))
    near_ext = face_extents(mesh, near_cam, jnp.eye(4))
    assert (near_ext > near_plan.patch_sizes[-2]).any()
    assert bool(render(mesh, near_cam, jnp.eye(4), plan=short).overflow)


def test_overflow_is_reported_and_renderer_replans():
    mesh = torus_mesh()
    cam, _, _ = _camera([0, -250, -350])
    tiny = jt.render.RasterPlan(patch_sizes=(8,), capacities=(16,))
    out = render(mesh, cam, jnp.eye(4), plan=tiny)
    assert bool(out.overflow) and int(out.status) == jt.Status.RENDER_OVERFLOW
    with pytest.raises(ValueError, match="RasterPlan"):
        render(mesh, cam, jnp.eye(4))
    # Moving the torus 3x closer makes every face bigger: the renderer re-plans once and stays exact.
    renderer = jt.render.Renderer(mesh, cam)
    far = renderer(jnp.eye(4))
    near = renderer(jt.se3_exp(jnp.array([0.0, -125.0, -175.0, 0, 0, 0])))  # half-way to the camera
    assert not bool(far.overflow) and not bool(near.overflow)
    assert renderer.compilations == 2
    assert int(near.silhouette.sum()) > 2 * int(far.silhouette.sum())
    with pytest.raises(ValueError, match="T_world_root"):
        renderer(jnp.full((4, 4), jnp.nan))
    with pytest.raises(ValueError, match="theta"):
        renderer(jnp.eye(4), jnp.zeros(2))
    # A non-finite pose is a status of the compiled program, not an exception.
    nan_pose = jnp.full((4, 4), jnp.nan, jnp.float32)
    bad = render(mesh, cam, nan_pose, plan=renderer.plan)
    assert int(bad.status) == jt.Status.INVALID_INPUT


# 1280x720 with a wide lens: an object 250 mm away fills most of the frame and its faces span
# far more than the largest patch class (724 px).
K_HD = np.array([[700.0, 0, 639.5], [0, 700.0, 359.5], [0, 0, 1]])


def test_faces_larger_than_every_patch_class_are_tiled():
    mesh = box_mesh((400, 300, 200))
    R, t = look_at([60, -40, -350])
    cam = jt.make_camera(K_HD, 1280, 720, R, t)
    assert face_extents(mesh, cam, jnp.eye(4), cull_backfaces=True).max() > jt.render.PATCH_SIZES[-1]
    faces, tiles = jt.render.tile_demand(mesh, cam, jnp.eye(4), cull_backfaces=True)
    # Only the tiles a triangle overlaps: fewer than its bounding box's (a triangle is half its box).
    assert 0 < tiles < faces * (1280 // 128) * (720 // 128 + 1)
    renderer = jt.render.Renderer(mesh, cam, cull_backfaces=True)
    renderer(jnp.eye(4))
    assert renderer.plan.tile_faces >= faces and renderer.plan.tile_capacity >= tiles
    plan = dataclasses.replace(renderer.plan, dense=False)  # the tiles, not the dense path this box would take
    out = render(mesh, cam, jnp.eye(4), plan=plan)
    assert not bool(out.overflow) and int(out.status) == jt.Status.OK
    assert np.asarray(out.silhouette).mean() > 0.6
    _assert_matches_ray_caster(out, mesh, R, t, 1280, 720, K_HD)
    # A plan without enough tiles reports the overflow instead of dropping faces silently.
    short = jt.render.RasterPlan(
        plan.patch_sizes, plan.capacities, cull_backfaces=True, tile_faces=plan.tile_faces, tile_capacity=tiles - 1,
        dense=False,
    )
    out_short = jax.jit(lambda T: render(mesh, cam, T, plan=short))(jnp.eye(4))
    assert bool(out_short.overflow) and int(out_short.status) == jt.Status.RENDER_OVERFLOW


def test_renderers_of_one_mesh_share_a_compilation():
    from jaxtrack.render import _raster

    mesh = box_mesh((90, 50, 30))
    cam, _, _ = _camera([40, -120, -380])
    before = eqx.debug.get_num_traces(_raster._render_body)
    first = jt.render.Renderer(mesh, cam, cull_backfaces=True)
    second = jt.render.Renderer(mesh, cam, cull_backfaces=True)
    a = first(jnp.eye(4))
    b = second(jt.se3_exp(jnp.array([2.0, 0, 0, 0, 0.01, 0])))  # same plan, another pose
    assert first.plan == second.plan
    assert eqx.debug.get_num_traces(_raster._render_body) == before + 1
    assert int(a.silhouette.sum()) > 0 and not np.array_equal(np.asarray(a.depth), np.asarray(b.depth))


def test_eager_render_is_the_renderers_compiled_program():
    """Called outside a trace, `render` runs the one compiled program per plan that `Renderer` runs (not op by
    op), with the same output as inside `jax.jit`; another pose or an explicit zero Θ traces nothing new."""
    from jaxtrack.render import _raster

    mesh = box_mesh((90, 50, 30))
    cam, _, _ = _camera([40, -120, -380])
    renderer = jt.render.Renderer(mesh, cam, cull_backfaces=True)
    first = renderer(jnp.eye(4))
    before = eqx.debug.get_num_traces(_raster._render_body)
    T = jt.se3_exp(jnp.array([2.0, 0, 0, 0, 0.01, 0]))
    eager = render(mesh, cam, T, plan=renderer.plan)
    again = render(mesh, cam, np.eye(4), jnp.zeros((0,)), plan=renderer.plan)  # numpy pose, explicit empty Θ
    assert eqx.debug.get_num_traces(_raster._render_body) == before
    inline = jax.jit(lambda T: render(mesh, cam, T, plan=renderer.plan))(T)
    np.testing.assert_array_equal(np.asarray(eager.face_id), np.asarray(inline.face_id))
    np.testing.assert_allclose(np.asarray(eager.depth), np.asarray(inline.depth), rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(again.depth), np.asarray(first.depth))


def test_dense_path_draws_what_the_planned_path_draws():
    """`RasterPlan.dense` (every face at every pixel, no scatter) against the plan's patches and tiles, on a box (whole,
    culled, partly off-screen, a face crossing the near plane), a two-part chain with its joint turned and the torus:
    the same face at every pixel, the same depth to rounding, the same surface points, parts and visible vertices."""
    small_K = np.array([[150.0, 0, 79.5], [0, 150.0, 59.5], [0, 0, 1]])
    a = box_mesh((100, 40, 40))
    chain = make_mesh(np.concatenate([np.asarray(a.vertices) - [50, 0, 0], np.asarray(a.vertices) + [50, 0, 0]]),
                      np.concatenate([np.asarray(a.faces), np.asarray(a.faces) + 8]), vertex_part=np.r_[np.zeros(8), np.ones(8)])
    cases = [  # (mesh, model, theta, eye, pose shift, cull)
        (box_mesh((90, 50, 30)), None, None, [40, -120, -380], [0, 0, 0], False),
        (box_mesh((90, 50, 30)), None, None, [40, -120, -380], [0, 0, 0], True),
        (box_mesh((90, 50, 30)), None, None, [40, -120, -380], [200, 0, 0], True),  # partly off-screen
        (box_mesh((90, 50, 30)), None, None, [0, 0, -10], [0, 0, 0], False),  # the camera inside the box: faces cross its near plane
        (chain, jt.chain_model([-1, 0], [(0, 1, 0)], [(0, 0, 0)]), jnp.array([0.7]), [0, -90, -400], [0, 0, 0], False),
        (torus_mesh(), None, None, [0, -250, -350], [0, 0, 0], False),
    ]
    clipped = []
    for mesh, model, theta, eye, shift, cull in cases:
        R, t = look_at(eye)
        cam = jt.make_camera(small_K, 160, 120, R, t)
        T = jt.se3_exp(jnp.array([*shift, 0.0, 0.0, 0.0]))
        base = plan_raster(face_extents(mesh, cam, T, theta, model, cull_backfaces=cull), cull_backfaces=cull)
        planned = render(mesh, cam, T, theta, model, dataclasses.replace(base, dense=False))
        dense = render(mesh, cam, T, theta, model, dataclasses.replace(base, dense=True))
        assert not bool(planned.overflow) and not bool(dense.overflow)
        np.testing.assert_array_equal(np.asarray(dense.face_id), np.asarray(planned.face_id))
        np.testing.assert_allclose(np.asarray(dense.depth), np.asarray(planned.depth), rtol=1e-6)
        np.testing.assert_allclose(np.asarray(dense.p_model), np.asarray(planned.p_model), atol=1e-3)
        np.testing.assert_array_equal(np.asarray(dense.part_id), np.asarray(planned.part_id))
        np.testing.assert_array_equal(np.asarray(dense.vertex_visible), np.asarray(planned.vertex_visible))
        assert int(dense.near_clipped) == int(planned.near_clipped)
        assert 0 < int(planned.silhouette.sum()) <= 160 * 120, (eye, shift)
        clipped.append(int(planned.near_clipped))
    assert clipped[3] > 0 and clipped[0] == 0  # the close-up case does drop faces at the near plane


def test_make_mesh_errors():
    with pytest.raises(ValueError, match="faces"):
        make_mesh(np.zeros((3, 3)), np.zeros((0, 3), int))
    with pytest.raises(ValueError, match="indices"):
        make_mesh(np.zeros((3, 3)), np.array([[0, 1, 5]]))
    with pytest.raises(ValueError, match="vertices"):
        make_mesh(np.zeros((3, 2)), np.array([[0, 1, 2]]))


def test_silhouette_sdf_matches_exact_distance_transform():
    import cv2

    from jaxtrack.render import silhouette_sdf

    mesh = torus_mesh()
    cam, _, _ = _camera([0, -250, -350])
    sil = np.asarray(jt.render.Renderer(mesh, cam)(jnp.eye(4)).silhouette)
    phi = np.asarray(jax.jit(silhouette_sdf)(jnp.asarray(sil)))
    d_in = cv2.distanceTransform(sil.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    d_out = cv2.distanceTransform((~sil).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    exact = np.where(sil, d_in - 0.5, -(d_out - 0.5))
    assert ((phi > 0) == sil).all()
    err = np.abs(phi - exact)
    assert err.max() < 1.0 and err.mean() < 0.01, (err.max(), err.mean())


def test_tile_overlap_never_misses_a_covered_pixel():
    from jaxtrack.render._raster import _tile_corners, _tile_overlap

    rng = np.random.default_rng(3)
    tile, width, height = 16, 96, 64
    tri = rng.uniform([-20, -20], [width + 20, height + 20], size=(200, 3, 2))
    tri[:50] = tri[:50, :1] + rng.normal(scale=6.0, size=(50, 3, 2))  # small ones too
    corners = _tile_corners(width, height, tile)
    hit = np.asarray(_tile_overlap(jnp.asarray(tri), jnp.asarray(corners), tile))
    # Brute force: a tile is needed iff one of its pixel centres lies inside the triangle.
    y, x = np.mgrid[0:height, 0:width]
    a, b, c = tri[:, 0, None, None], tri[:, 1, None, None], tri[:, 2, None, None]

    def edge(p, q):
        return (q[..., 0] - p[..., 0]) * (y - p[..., 1]) - (q[..., 1] - p[..., 1]) * (x - p[..., 0])

    e0, e1, e2 = edge(b, c), edge(c, a), edge(a, b)
    inside = ((e0 >= 0) & (e1 >= 0) & (e2 >= 0)) | ((e0 <= 0) & (e1 <= 0) & (e2 <= 0))
    needed = np.stack([inside[:, y0 : y0 + tile, x0 : x0 + tile].any((1, 2)) for x0, y0 in corners], 1)
    assert not (needed & ~hit).any()  # no covered tile is skipped
    assert hit.sum() < 1.1 * needed.sum() and hit.sum() < 0.5 * hit.size  # and few are tested in vain


def test_connected_pieces_are_scipys_connected_components():
    """The union-find behind `hides_its_back_faces` labels the pieces as scipy.sparse.csgraph does, each by its smallest
    node (random graphs, a shuffled path: the longest chain of hooks, no edges)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from jaxtrack.render._mesh import _connected_labels

    rng = np.random.default_rng(0)
    order = rng.permutation(3000)
    graphs = [(n, rng.integers(0, n, m), rng.integers(0, n, m)) for n, m in ((10, 4), (500, 400), (4000, 6000))]
    graphs += [(3000, order[:-1], order[1:]), (7, np.zeros(0, int), np.zeros(0, int))]
    for n, a, b in graphs:
        ours = _connected_labels(n, a, b)
        count, theirs = connected_components(coo_matrix((np.ones(len(a)), (a, b)), shape=(n, n)), directed=False)
        assert len(np.unique(ours)) == count
        first = {}
        for node in range(n):  # the smallest node of each of scipy's pieces is the label of the whole piece
            first.setdefault(theirs[node], node)
        np.testing.assert_array_equal(ours, [first[t] for t in theirs])


def test_a_closed_outward_mesh_hides_its_back_faces_and_culling_them_renders_the_same():
    from jaxtrack.render import hides_its_back_faces

    box = box_mesh((160, 70, 80))
    v, f = np.asarray(box.vertices), np.asarray(box.faces)
    assert hides_its_back_faces(box) and hides_its_back_faces(torus_mesh())
    assert not hides_its_back_faces(make_mesh(v, f[:, ::-1]))  # closed but wound inward: culling would drop the front
    assert not hides_its_back_faces(make_mesh(v, f[:-1]))  # a face missing: the inside shows through the hole
    assert not hides_its_back_faces(_mixed_mesh())
    small = np.asarray(box_mesh((20, 20, 20)).vertices) + [300.0, 0.0, 0.0]
    pieces = lambda f_small: make_mesh(np.concatenate([v, small]), np.concatenate([f, f_small + len(v)]))
    assert hides_its_back_faces(pieces(f))  # two closed pieces, both outward (a body's capsules)
    assert not hides_its_back_faces(pieces(f[:, ::-1]))  # the small piece inward: the total volume is still > 0
    # One scene for every view: the torus (self-occluding) and the box (faces too large for a patch class: the tile
    # pool) as two closed pieces; one plan per culling setting over all views, one class, so two programs compile.
    tor = torus_mesh()
    scene = make_mesh(np.concatenate([np.asarray(tor.vertices), v + [0.0, 0.0, 120.0]]),
                      np.concatenate([np.asarray(tor.faces), f + len(tor.vertices)]))
    assert hides_its_back_faces(scene)
    cams = [_camera(eye)[0] for eye in ([0, -250, -350], [120, -160, -300], [-40, 200, -260])]
    T = jnp.eye(4)
    plans = {cull: plan_raster(np.stack([np.asarray(face_extents(scene, cam, T, cull_backfaces=cull)) for cam in cams]),
                               patch_sizes=(32,), cull_backfaces=cull) for cull in (False, True)}
    assert all(p.tile_faces > 0 for p in plans.values())  # the box's faces take the tile pool
    assert plans[True].capacities[0] < plans[False].capacities[0]  # culling drops the back faces before placing
    for cam in cams:
        plain, culled = (render(scene, cam, T, plan=plans[cull]) for cull in (False, True))
        assert np.array_equal(np.asarray(plain.face_id), np.asarray(culled.face_id))
        assert np.array_equal(np.asarray(plain.depth), np.asarray(culled.depth))
        assert int(np.sum(np.asarray(plain.face_id) >= len(tor.faces))) > 1000  # the box shows
        assert int(np.sum((np.asarray(plain.face_id) >= 0) & (np.asarray(plain.face_id) < len(tor.faces)))) > 1000
