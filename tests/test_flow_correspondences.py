"""The flow cue's room: flow t → t+1 of the object pixels becomes 2D-3D correspondences at t+1."""

import jax.numpy as jnp
import numpy as np

import jaxtrack as jt
from jaxtrack.cues.flow import flow_correspondences
from jaxtrack.geometry import make_transform, rotation_error_deg, so3_exp
from jaxtrack.render import Renderer, box_mesh
from jaxtrack.solve import Cue

H, W = 96, 128


def _scene():
    cam = jt.make_camera(np.array([[150.0, 0, 63.5], [0, 150.0, 47.5], [0, 0, 1]]), W, H, dtype=jnp.float64)
    mesh = box_mesh((80.0, 60.0, 50.0), dtype=jnp.float64)
    T0 = make_transform(so3_exp(jnp.array([0.3, -0.4, 0.2])), jnp.array([5.0, -3.0, 400.0]))
    T1 = make_transform(so3_exp(jnp.array([0.33, -0.38, 0.25])), jnp.array([9.0, -1.0, 405.0]))
    out = Renderer(mesh, cam)(T0)
    # The exact flow of every object pixel: its surface point projected at T1 minus the pixel.
    p1 = np.asarray(out.p_model) @ np.asarray(T1)[:3, :3].T + np.asarray(T1)[:3, 3]
    K = np.asarray(cam.K)
    yy, xx = np.mgrid[0:H, 0:W]
    flow = np.stack([K[0, 0] * p1[..., 0] / p1[..., 2] + K[0, 2] - xx, K[1, 1] * p1[..., 1] / p1[..., 2] + K[1, 2] - yy], -1)
    sil = np.asarray(out.silhouette)
    return cam, out, np.where(sil[..., None], flow, 0.0), sil, T0, T1


def test_exact_flow_gives_the_next_pose():
    cam, out, flow, sil, T0, T1 = _scene()
    conf = jnp.ones((H, W))
    corr = flow_correspondences(cam, jnp.asarray(flow), conf, jnp.asarray(sil), out.p_model, out.part_id, stride=2)
    assert corr.capacity == (H // 2) * (W // 2)
    assert np.all(np.asarray(corr.cue) == Cue.FLOW)
    live = np.asarray(corr.weight) > 0
    assert 0 < live.sum() <= sil[::2, ::2].sum()
    sol = jt.solve_pose(jt.rigid_model(jnp.float64), corr, T0)
    assert int(sol.status) == jt.Status.OK
    T = np.asarray(sol.T_world_root)
    assert float(rotation_error_deg(T[:3, :3], np.asarray(T1)[:3, :3])) < 1e-4
    np.testing.assert_allclose(T[:3, 3], np.asarray(T1)[:3, 3], atol=1e-3)


def test_crop_offset_matches_full_frame_and_invalid_rows_carry_no_weight():
    cam, out, flow, sil, _, _ = _scene()
    conf = jnp.asarray(np.random.default_rng(0).uniform(0.5, 3.0, (H, W)))
    full = flow_correspondences(cam, jnp.asarray(flow), conf, jnp.asarray(sil), out.p_model, out.part_id, stride=1)
    y0, x0, h, w = 16, 32, 64, 64
    crop = lambda a: jnp.asarray(a)[y0 : y0 + h, x0 : x0 + w]
    part = flow_correspondences(cam, crop(flow), crop(conf), crop(sil), crop(out.p_model), crop(out.part_id),
                                offset=jnp.array([y0, x0]), stride=1)
    # Rows of the crop are the full-frame rows of the same pixels.
    rows = (np.arange(y0, y0 + h)[:, None] * W + np.arange(x0, x0 + w)[None, :]).reshape(-1)
    np.testing.assert_allclose(np.asarray(part.pixel), np.asarray(full.pixel)[rows], atol=1e-9)
    np.testing.assert_allclose(np.asarray(part.weight), np.asarray(full.weight)[rows])
    np.testing.assert_allclose(np.asarray(part.n), np.asarray(full.n)[rows], atol=1e-12)
    # Background and non-finite flow rows have zero weight.
    bad = flow.copy()
    bad[sil] = np.nan
    nan_rows = flow_correspondences(cam, jnp.asarray(bad), conf, jnp.asarray(sil), out.p_model, out.part_id, stride=1)
    assert float(jnp.sum(nan_rows.weight)) == 0.0
    assert np.all(np.isfinite(np.asarray(nan_rows.n))) and np.all(np.isfinite(np.asarray(nan_rows.pixel)))
    np.testing.assert_array_equal(np.asarray(full.weight)[~sil.reshape(-1)], 0.0)
