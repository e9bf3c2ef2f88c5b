"""Kinematic chains, cameras (against OpenCV) and Plücker lines."""

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtrack.geometry import (
    backproject_pixels,
    chain_model,
    make_camera,
    part_points_world,
    part_transforms,
    pixel_rays_world,
    plucker_from_ray,
    point_line_distance,
    point_line_residual,
    project_ideal,
    project_points,
    rigid_model,
    se3_exp,
    select_camera,
    stack_cameras,
    undistort_points,
)
from jaxtrack.synth import demo_chain, look_at

K = np.array([[810.0, 0.0, 322.5], [0.0, 790.0, 241.0], [0.0, 0.0, 1.0]])
# Tolerances scale with the working precision (tests run in float64, see conftest.py).
EPS = float(jnp.finfo(jnp.float64).eps)
DIST = np.array([-0.21, 0.08, 0.0012, -0.0007, -0.01])


def _rodrigues_joint(axis, point, angle):
    """Rotation by `angle` about the line through `point` with direction `axis`, as a 4x4 matrix."""
    R, _ = cv2.Rodrigues(np.asarray(axis, float) / np.linalg.norm(axis) * angle)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = point - R @ point
    return T


def test_forward_kinematics_matches_explicit_composition():
    # Tree: 0 root; 1 on 0; 2 on 1; 3 on 0 (second branch).
    axes = [(0, 0, 1), (0, 1, 0), (1, 0, 0)]
    points = [(100.0, 0, 0), (200.0, 0, 0), (-100.0, 0, 0)]
    model = chain_model([-1, 0, 1, 0], axes, points, dtype=jnp.float64)
    theta = np.array([0.3, -0.7, 1.1])
    T_root = np.asarray(se3_exp(jnp.array([10.0, -5, 900, 0.1, 0.2, -0.3])))
    got = np.asarray(part_transforms(model, jnp.asarray(T_root), jnp.asarray(theta)))
    E = [_rodrigues_joint(a, np.array(q), t) for a, q, t in zip(axes, points, theta)]
    expected = [T_root, T_root @ E[0], T_root @ E[0] @ E[1], T_root @ E[2]]
    np.testing.assert_allclose(got, np.stack(expected), atol=1e6 * EPS)
    # A rigid model is one part at the root pose.
    np.testing.assert_allclose(part_transforms(rigid_model(jnp.float64), jnp.asarray(T_root), jnp.zeros(0))[0], T_root)


def test_part_point_columns_are_the_points_moved_by_their_own_parts_transform():
    from jaxtrack.geometry import part_point_columns, transform_point_columns

    axes = [(0, 0, 1), (0, 1, 0), (1, 0, 0)]
    points = [(100.0, 0, 0), (200.0, 0, 0), (-100.0, 0, 0)]
    model = chain_model([-1, 0, 1, 0], axes, points)
    T_parts = part_transforms(model, se3_exp(jnp.array([10.0, -5, 900, 0.1, 0.2, -0.3])), jnp.array([0.3, -0.7, 1.1]))
    rng = np.random.default_rng(1)
    p = jnp.asarray(rng.normal(size=(500, 3)) * 100, jnp.float32)
    part = jnp.asarray(rng.integers(0, 4, 500), jnp.int32)
    got = jax.jit(part_point_columns)(T_parts, part, p[:, 0], p[:, 1], p[:, 2])
    want = transform_point_columns(T_parts[part], p[:, 0], p[:, 1], p[:, 2])  # every point's whole 4x4, gathered
    for g, w in zip(got, want):
        np.testing.assert_allclose(np.asarray(g), np.asarray(w), rtol=1e-6, atol=1e-3)
    moved = np.stack([np.asarray(g) for g in got], -1)
    for k in (0, 1, 2, 3):  # each part's points moved by that part's transform, not another's
        T = np.asarray(T_parts[k], np.float64)
        sel = np.asarray(part) == k
        np.testing.assert_allclose(moved[sel], np.asarray(p, np.float64)[sel] @ T[:3, :3].T + T[:3, 3], atol=1e-2)
    # one part: no gather, the points moved by it
    one = part_point_columns(T_parts[:1], jnp.zeros(500, jnp.int32), p[:, 0], p[:, 1], p[:, 2])
    np.testing.assert_allclose(np.stack(one, -1), np.asarray(p) @ np.asarray(T_parts[0, :3, :3]).T + np.asarray(T_parts[0, :3, 3]),
                               atol=1e-2)


def test_chain_model_rejects_bad_trees():
    with pytest.raises(ValueError, match="parents\\[0\\]"):
        chain_model([0, 0], [(0, 0, 1)], [(0, 0, 0)])
    with pytest.raises(ValueError, match="earlier part"):
        chain_model([-1, 2, 0], [(0, 0, 1)] * 2, [(0, 0, 0)] * 2)
    with pytest.raises(ValueError, match="axis"):
        chain_model([-1, 0], [(0, 0, 0)], [(0, 0, 0)])


def test_forward_kinematics_derivatives_agree_with_finite_differences():
    model = demo_chain(4, branches=2, dtype=jnp.float64)
    theta0 = jnp.array([0.2, -0.4, 0.9, 0.1])
    T_root = se3_exp(jnp.array([1.0, 2.0, 800.0, 0.3, -0.2, 0.1]))
    f = jax.jit(lambda th: part_transforms(model, T_root, th))  # jitted: one program each, not one per operation
    fwd, rev = jax.jit(jax.jacfwd(f))(theta0), jax.jit(jax.jacrev(f))(theta0)
    eps = 1e-6
    fd = np.stack([(f(theta0.at[j].add(eps)) - f(theta0.at[j].add(-eps))) / (2 * eps) for j in range(4)], -1)
    np.testing.assert_allclose(fwd, rev, atol=1e4 * EPS)
    np.testing.assert_allclose(fwd, fd, atol=1e-6)


def _camera(dist=DIST):
    R, t = look_at([300.0, -200.0, -900.0])
    return make_camera(K, 640, 480, R, t, dist=dist, dtype=jnp.float64), R, t


def test_projection_and_undistortion_match_opencv():
    cam, R, t = _camera()
    rng = np.random.default_rng(0)
    p_world = rng.uniform(-150, 150, size=(200, 3))
    px, depth = project_points(cam, jnp.asarray(p_world))
    rvec, _ = cv2.Rodrigues(R)
    px_cv, _ = cv2.projectPoints(p_world, rvec, t, K, DIST)
    np.testing.assert_allclose(px, px_cv[:, 0], atol=1e-6)
    np.testing.assert_allclose(depth, (p_world @ R.T + t)[:, 2], atol=1e7 * EPS)
    ideal = undistort_points(cam, px)
    ideal_cv = cv2.undistortPoints(
        px_cv, K, DIST, None, None, K, (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
    )[:, 0]
    np.testing.assert_allclose(ideal, ideal_cv, atol=1e-3)
    # The undistorted pixels are the pinhole projections of the same points.
    pinhole, _ = project_points(make_camera(K, 640, 480, R, t, dtype=jnp.float64), jnp.asarray(p_world))
    np.testing.assert_allclose(ideal, pinhole, atol=1e-3)


def test_backprojection_rays_and_plucker_lines():
    cam, _, _ = _camera(dist=None)
    rng = np.random.default_rng(1)
    p_world = jnp.asarray(rng.uniform(-150, 150, size=(50, 3)))
    px, depth = project_points(cam, p_world)
    np.testing.assert_allclose(backproject_pixels(cam, px, depth), p_world, atol=1e7 * EPS)
    origin, direction = pixel_rays_world(cam, px)
    n, m = plucker_from_ray(origin, direction)
    np.testing.assert_allclose(point_line_distance(p_world, n, m), 0.0, atol=1e7 * EPS)
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0)
    # A point moved by d perpendicular to the ray lies at distance d, and r ⊥ n.
    perp = np.cross(np.asarray(n), np.array([0.0, 0.0, 1.0]))
    perp /= np.linalg.norm(perp, axis=-1, keepdims=True)
    moved = p_world + 7.5 * perp
    np.testing.assert_allclose(point_line_distance(moved, n, m), 7.5, atol=1e7 * EPS)
    np.testing.assert_allclose(np.sum(point_line_residual(moved, n, m) * n, -1), 0.0, atol=1e7 * EPS)


def test_camera_rig_batches_and_rejects_bad_input():
    cams = stack_cameras([_camera(None)[0], make_camera(K, 640, 480, dtype=jnp.float64)])
    assert cams.K.shape == (2, 3, 3) and cams.T_cam_world.shape == (2, 4, 4)
    cam1 = select_camera(cams, 1)
    np.testing.assert_allclose(cam1.T_cam_world, np.eye(4))
    with pytest.raises(ValueError, match="K"):
        make_camera(np.eye(2), 640, 480)
    with pytest.raises(ValueError, match="rotation"):
        make_camera(K, 640, 480, R_cam_world=np.ones(9))
    with pytest.raises(ValueError, match="image size"):
        stack_cameras([make_camera(K, 640, 480), make_camera(K, 320, 240)])
    with pytest.raises(ValueError, match="cameras\\[1\\] must be a single Camera"):
        stack_cameras([make_camera(K, 640, 480), K])
    with pytest.raises(ValueError, match="cameras\\[0\\] must be a single Camera"):
        stack_cameras([cams])


def test_project_ideal_picks_each_points_camera_and_is_the_undistorted_projection():
    """Per-row camera selection equals projecting every point in every camera and picking (one camera with skew);
    with no distortion it is `project_points`; a point behind a camera keeps a finite pixel and its negative depth;
    a rig without camera indices is refused. `part_points_world` is eq. 2 applied per row."""
    rng = np.random.default_rng(0)
    R = cv2.Rodrigues(np.array([0.1, -0.2, 0.05]))[0]
    K_skew = K * np.array([[1.1], [0.9], [1.0]]) + np.array([[0.0, 3.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    cams = stack_cameras([make_camera(K, 640, 480, dtype=jnp.float64),
                          make_camera(K_skew, 640, 480, R, [30.0, -20.0, 50.0], dtype=jnp.float64)])
    p = jnp.asarray(rng.uniform([-100, -100, 600], [100, 100, 900], (40, 3)))
    index = jnp.asarray(rng.integers(0, 2, 40), jnp.int32)
    px, z = project_ideal(cams, p, index)
    for c in range(2):
        ref, zc = project_points(select_camera(cams, c), p)
        pick = np.asarray(index) == c
        np.testing.assert_allclose(np.asarray(px)[pick], np.asarray(ref)[pick], atol=1e-9)
        np.testing.assert_allclose(np.asarray(z)[pick], np.asarray(zc)[pick], atol=1e-9)
    one, _ = project_ideal(select_camera(cams, 1), p)
    np.testing.assert_allclose(np.asarray(one), np.asarray(project_points(select_camera(cams, 1), p)[0]), atol=1e-9)
    behind_px, behind_z = project_ideal(select_camera(cams, 0), jnp.asarray([[10.0, 5.0, -300.0]]))
    assert np.all(np.isfinite(np.asarray(behind_px))) and float(behind_z[0]) < 0
    with pytest.raises(ValueError, match="camera_index"):
        project_ideal(cams, p)
    model = chain_model([-1, 0], [(0, 0, 1)], [(50.0, 0, 0)], dtype=jnp.float64)
    T_root, theta = se3_exp(jnp.array([10.0, -5, 900, 0.1, 0.2, -0.3])), jnp.array([0.4])
    part = jnp.asarray(rng.integers(0, 2, 40), jnp.int32)
    T = np.asarray(part_transforms(model, T_root, theta))[np.asarray(part)]
    expected = np.einsum("nij,nj->ni", T[:, :3, :3], np.asarray(p)) + T[:, :3, 3]
    np.testing.assert_allclose(np.asarray(part_points_world(model, T_root, theta, p, part)), expected, atol=1e-9)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"K": np.zeros((3, 3))}, "camera K must have focal lengths"),
        ({"K": np.diag([800.0, 0.0, 1.0])}, "fy = K\\[1,1\\] > 0"),
        ({"K": K * 2}, "last row"),
        ({"K": K + np.array([[0, 0, 0], [5.0, 0, 0], [0, 0, 0]])}, "upper triangular"),
        ({"K": [[1, 2], [3, 4]]}, "camera K must be a 3x3"),
        ({"K": "fx"}, "camera K must be numeric"),
        ({"width": 0}, "width must be positive"),
        ({"height": -5}, "height must be positive"),
        ({"width": 640.5}, "width must be a whole number"),
        ({"height": float("nan")}, "height must be a whole number"),
        ({"width": True}, "width must be a whole number"),
        ({"R_cam_world": np.diag([1.0, 1.0, -1.0])}, "R_cam_world is not a rotation.*det R = -1"),
        ({"R_cam_world": np.eye(3) * 1.01}, "R_cam_world is not a rotation"),
        ({"R_cam_world": np.eye(2)}, "R_cam_world must hold 9 values"),
        ({"t_cam_world": [0.0, np.inf, 0.0]}, "t_cam_world must be finite"),
        ({"t_cam_world": [1.0, 2.0]}, "t_cam_world must hold 3 values"),
        ({"dist": np.zeros(8)}, "dist must be at most 5"),
        ({"dist": [np.nan]}, "dist must be finite"),
        ({"dtype": jnp.int32}, "dtype must be a floating"),
    ],
)
def test_make_camera_names_the_bad_argument(kwargs, message):
    args = {"K": K, "width": 640, "height": 480, **kwargs}
    with pytest.raises(ValueError, match=message):
        make_camera(**args)


def test_make_camera_accepts_whole_float_sizes_and_short_distortion():
    cam = make_camera(K.ravel().tolist(), 640.0, np.int64(480), dist=[0.1, -0.01], dtype=jnp.float64)
    assert (cam.width, cam.height) == (640, 480) and isinstance(cam.width, int)
    np.testing.assert_array_equal(cam.dist, [0.1, -0.01, 0, 0, 0])
    np.testing.assert_array_equal(cam.K, K)


def test_crop_camera_with_a_scale_projects_into_window_pixels():
    """A point's pixel in the scaled crop camera is its full-frame pixel mapped by `full_to_window`."""
    from jaxtrack.geometry import crop_camera, make_camera, project_points
    from jaxtrack.image import full_to_window

    K = np.array([[500.0, 0.0, 320.0], [0.0, 480.0, 240.0], [0.0, 0.0, 1.0]])
    cam = make_camera(K, 640, 480, np.eye(3), np.zeros(3), dist=np.array([0.1, -0.05, 0.001, 0.002, 0.0]))
    pts = jnp.asarray(np.random.default_rng(2).uniform([-80, -60, 400], [80, 60, 700], (20, 3)))
    offset, scale = jnp.array([100.5, 150.25]), jnp.asarray(2.7)
    full, _ = project_points(cam, pts)
    win, _ = project_points(crop_camera(cam, offset, (96, 128), scale), pts)
    np.testing.assert_allclose(win, full_to_window(full, offset, scale), atol=1e-4)
    # Without a scale: the principal point shifted by the offset.
    win1, _ = project_points(crop_camera(cam, offset, (96, 128)), pts)
    np.testing.assert_allclose(win1, full - offset[::-1], atol=1e-4)
