"""SIFT matches → 2D-3D correspondences at t+1 (Fig. 3 right), and the back-projection check.

A match x_t → x_{t+1} moves the surface point under x_t. Two assignments:
- "vertex" (the paper): the closest projected visible mesh vertex X_v (at pose χ_t) is moved by the
  match's displacement, giving (X_v, π_t(X_v) + x_{t+1} − x_t). Exact for translation in the image
  plane, and a good approximation when vertices are dense (a few pixels apart);
- "surface" (default): the rendered surface point under x_t (its pixel centre), from the renderer's
  `p_model` buffer. Exact up to half a pixel of transfer, and it works for coarse meshes too, where
  the nearest vertex can lie far from the keypoint (a box has 8).
Each correspondence keeps the part of its point, so articulated models work.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ...geometry import Camera, KinematicModel, part_points_world, project_ideal, rigid_model
from ...render import Mesh, RenderOutput
from ...solve import Correspondences, Cue, correspondences_from_pixels
from ._detect import SiftMatches
from ._filters import BOUNDARY_MAX_PX, SiftParams

_OFFSETS = np.stack(np.meshgrid(np.arange(-BOUNDARY_MAX_PX, BOUNDARY_MAX_PX + 1),
                                 np.arange(-BOUNDARY_MAX_PX, BOUNDARY_MAX_PX + 1), indexing="ij"), -1).reshape(-1, 2)
_CHEBYSHEV = np.abs(_OFFSETS).max(-1)  # (K,) each offset's distance from the keypoint's pixel


def _surface_rows(p_t, p_t1, valid, rendered: RenderOutput, boundary_px):
    """The rendered surface point under each keypoint (N,), where the render shows the keypoint's part at every
    pixel within `boundary_px` (`SiftParams.boundary_px`; the window clipped at the render's border)."""
    h, w = rendered.face_id.shape
    q = jnp.round(p_t)
    u = jnp.clip(q[:, 0].astype(jnp.int32), 0, w - 1)
    v = jnp.clip(q[:, 1].astype(jnp.int32), 0, h - 1)
    on_object = rendered.face_id[v, u] >= 0
    part = rendered.part_id[v, u]
    near = jnp.asarray(_CHEBYSHEV) <= boundary_px  # (K,)
    around = rendered.part_id[jnp.clip(v[:, None] + _OFFSETS[:, 0], 0, h - 1),
                              jnp.clip(u[:, None] + _OFFSETS[:, 1], 0, w - 1)]  # (N, K)
    inside = ~jnp.any(near & (around != part[:, None]), axis=1)
    pixel = jnp.stack([u, v], -1).astype(p_t.dtype) + (p_t1 - p_t)
    return pixel, rendered.p_model[v, u], jnp.maximum(part, 0), valid & on_object & inside


def _vertex_rows(p_t, p_t1, valid, rendered: RenderOutput, vertex_px, mesh: Mesh, max_px):
    d2 = jnp.sum((p_t[:, None, :] - vertex_px[None, :, :]) ** 2, -1)  # (N, V)
    d2 = jnp.where(rendered.vertex_visible[None, :], d2, jnp.inf)
    nearest = jnp.argmin(d2, axis=1)
    close = jnp.take_along_axis(d2, nearest[:, None], 1)[:, 0] <= max_px**2
    pixel = vertex_px[nearest] + (p_t1 - p_t)
    return pixel, mesh.vertices[nearest].astype(p_t.dtype), mesh.vertex_part[nearest], valid & close


@eqx.debug.assert_max_traces(max_traces=None)  # counts traces (eqx.debug.get_num_traces); never fails
def _correspondences_body(matches, rendered, cameras, params, weight, mesh, model, T_world_root, theta, mode):
    num_cameras, cap = matches.valid.shape
    cam_index = jnp.repeat(jnp.arange(num_cameras, dtype=jnp.int32), cap)
    if mode == "surface":
        pixel, p_model, part, ok = jax.vmap(lambda a, b, c, r: _surface_rows(a, b, c, r, params.boundary_px))(
            matches.p_t, matches.p_t1, matches.valid, rendered)
    else:
        model = rigid_model(mesh.vertices.dtype) if model is None else model
        v_world = part_points_world(model, T_world_root, theta, mesh.vertices, mesh.vertex_part)

        def vertex_pixels(cam):
            return project_ideal(cam, v_world)[0]

        cams = cameras if cameras.K.ndim == 3 else jax.tree.map(lambda x: x[None], cameras)
        vertex_px = jax.vmap(vertex_pixels)(cams).astype(matches.p_t.dtype)
        pixel, p_model, part, ok = jax.vmap(lambda a, b, v, r, vp: _vertex_rows(a, b, v, r, vp, mesh, params.max_vertex_px))(
            matches.p_t, matches.p_t1, matches.valid, rendered, vertex_px
        )
    dtype = cameras.K.dtype
    w = jnp.where(ok.reshape(-1), jnp.asarray(weight, dtype), 0.0)
    return correspondences_from_pixels(
        cameras if cameras.K.ndim == 3 else jax.tree.map(lambda x: x[None], cameras),
        pixel.reshape(-1, 2).astype(dtype),
        cam_index,
        p_model.reshape(-1, 3).astype(dtype),
        part.reshape(-1),
        w,
        undistort=False,
        cue=Cue.SIFT,
    )


_sift_correspondences = eqx.filter_jit(_correspondences_body)  # inlined inside a caller's jit


def sift_correspondences(
    matches: SiftMatches,
    rendered: RenderOutput,
    cameras: Camera,
    params: SiftParams,
    weight=1.0,
    mode: str = "surface",
    mesh: Mesh | None = None,
    model: KinematicModel | None = None,
    T_world_root=None,
    theta=None,
) -> Correspondences:
    """2D-3D correspondences at t+1 from (filtered) matches t → t+1 and the render at χ_t. Jittable.

    Args:
        matches: `SiftMatches` (C cameras, capacity N); invalid rows become zero-weight rows.
        rendered: the model rendered at χ_t in each camera, stacked on a leading C axis.
        cameras: stacked rig of C cameras.
        params: `max_vertex_px` bounds the keypoint-vertex distance in "vertex" mode; `boundary_px` keeps, in
            "surface" mode, only keypoints that far inside their part in `rendered`.
        weight: weight of every surviving row (array; the tracker's fusion rescales it).
        mode: "surface" (default) or "vertex" (the paper's closest projected visible vertex; needs
            `mesh`, `T_world_root` (and `theta`, `model` for an articulated model)).

    Returns:
        `Correspondences` of capacity C·N with `cue = Cue.SIFT`; pixels are ideal (undistorted):
        keypoints from distorted images should be undistorted before matching.
    """
    if mode not in ("surface", "vertex"):
        raise ValueError(f"sift_correspondences: mode must be 'surface' or 'vertex', got {mode!r}")
    if mode == "vertex" and (mesh is None or T_world_root is None):
        raise ValueError("sift_correspondences: mode 'vertex' needs mesh and T_world_root (the pose at t)")
    if mode == "vertex":
        dtype = mesh.vertices.dtype
        T_world_root = jnp.asarray(T_world_root, dtype)
        joints = 0 if model is None else model.num_joints
        theta = jnp.zeros((joints,), dtype) if theta is None else jnp.asarray(theta, dtype)
    return _sift_correspondences(matches, rendered, cameras, params, weight, mesh, model, T_world_root, theta, mode)


@eqx.debug.assert_max_traces(max_traces=None)
def _backprojection_body(
    corr: Correspondences, cameras: Camera, model: KinematicModel, T_world_root, theta, params: SiftParams
) -> Correspondences:
    """Zero the weight of rows whose model point, projected with a preliminary pose (T_world_root,
    theta), lands farther than `params.backprojection_px` from the row's pixel. Jittable.

    Args:
        corr: correspondences (ideal pixels in `corr.pixel`).
        cameras: stacked rig (or one camera).
        model: kinematic tree; T_world_root (4, 4), theta (J,): the preliminary pose at t+1.
    """
    dtype = corr.n.dtype
    T_world_root = jnp.asarray(T_world_root, dtype)
    theta = jnp.asarray(theta, dtype)
    p_world = part_points_world(model, T_world_root, theta, corr.p_model, corr.part)
    px, z = project_ideal(cameras, p_world, corr.camera)
    close = (jnp.linalg.norm(px - corr.pixel, axis=-1) <= params.backprojection_px) & (z > 0)
    return corr.with_weight(jnp.where(close, corr.weight, 0.0))


backprojection_filter = eqx.filter_jit(_backprojection_body)


@eqx.filter_jit
def reprojection_errors(corr: Correspondences, cameras: Camera, model: KinematicModel, T_world_root, theta=None):
    """(N,) pixel distance between each row's pixel and its model point projected at a pose (e.g. the
    ground truth at t+1, for evaluation). Jittable."""
    dtype = corr.n.dtype
    theta = jnp.zeros((model.num_joints,), dtype) if theta is None else jnp.asarray(theta, dtype)
    p_world = part_points_world(model, jnp.asarray(T_world_root, dtype), theta, corr.p_model, corr.part)
    px, _ = project_ideal(cameras, p_world, corr.camera)
    return jnp.linalg.norm(px - corr.pixel, axis=-1)
