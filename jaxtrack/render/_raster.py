"""A jittable triangle rasteriser with static shapes: depth, face id, surface points, visibility.

Each triangle is tested over a fixed square pixel patch anchored at its (image-clipped) bounding box.
Triangles are sorted into a few patch-size classes (4, 6, 8, ..., 724 px); each class has a fixed
capacity chosen on the host (`plan_raster`); a class with more triangles than slots spills them into
spare slots of larger classes (`_spill_slots`). A triangle larger than the plan's largest class (one
close to the camera) goes to the tile pool instead: the image is cut into square tiles of
`RasterPlan.tile_size` px, and each such triangle gets one pool slot per tile it overlaps (an exact
triangle-rectangle test), from a pool of `tile_capacity` slots shared by up to `tile_faces` such
triangles, so no on-screen triangle is too big to draw. Depth is written with a scatter-min over all candidate (triangle, pixel) pairs, then
the winning face id with a scatter-max among the pixels whose depth equals the minimum. A class or
the tile pool overflowing its capacity is reported (`RenderOutput.overflow`, status
RENDER_OVERFLOW), never silently cropped; `Renderer` re-plans on the host when that happens. A mesh
of few faces large on screen (a box, the view model's close-ups) is drawn densely instead: every face
tested at every pixel, the depth and face by a min over the faces, no scatter (`dense_is_cheaper`).

Pixel centres are at integer coordinates (OpenCV). Depth is interpolated perspective-correctly
(1/z is affine in screen space). Triangles with a vertex in front of the near plane are dropped
(`RenderOutput.near_clipped` counts them): the tracker never looks at an object that close.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from .._exported import persistent_jit
from .._status import Status, StatusError, first_failure, status_where
from ..geometry import (
    Camera,
    KinematicModel,
    part_point_columns,
    part_transforms,
    pixels_to_normalized,
    rigid_model,
    se3_inverse,
    transform_point_columns,
)
from ._mesh import Mesh

# Steps of √2: a face's square patch is then at most 2x the area of its bounding square.
PATCH_SIZES = (4, 6, 8, 11, 16, 23, 32, 45, 64, 91, 128, 181, 256, 362, 512, 724)


# Side of the image tiles that cover triangles beyond the largest patch class (128² candidates each;
# small tiles follow a big triangle's edges closely, and the triangle-tile tests stay few: one per
# tile of the image and oversized face).
TILE_SIZE = 128


class RasterPlan(eqx.Module):
    """Static capacities per patch-size class (host-chosen; changing them recompiles).

    Attributes:
        patch_sizes: increasing square patch sides of the classes in use.
        capacities: triangles per class.
        near: near-plane depth; triangles with a vertex in front of it are dropped.
        cull_backfaces: skip back faces (closed meshes only).
        tile_size: side of the image tiles covering triangles larger than the largest class.
        tile_faces: how many such triangles the pool takes (0: none expected; any is an overflow).
        tile_capacity: (triangle, tile) slots in the pool.
        dense: draw every face at every pixel instead of the patches (True), never (False), or where that
            is cheaper (None: `dense_is_cheaper`).
    """

    patch_sizes: tuple = eqx.field(static=True)
    capacities: tuple = eqx.field(static=True)
    near: float = eqx.field(static=True, default=1.0)
    cull_backfaces: bool = eqx.field(static=True, default=False)
    tile_size: int = eqx.field(static=True, default=TILE_SIZE)
    tile_faces: int = eqx.field(static=True, default=0)
    tile_capacity: int = eqx.field(static=True, default=0)
    dense: bool | None = eqx.field(static=True, default=None)


class RenderOutput(eqx.Module):
    """Per-pixel buffers (H, W) of one camera.

    Attributes:
        depth: (H, W) camera-frame z of the visible surface, +inf on background.
        face_id: (H, W) int32 visible face, −1 on background (silhouette = face_id ≥ 0).
        p_model: (H, W, 3) model-frame (zero-configuration) surface point behind each pixel.
        part_id: (H, W) int32 part of the visible face, −1 on background.
        vertex_visible: (V,) bool vertex in the image and not occluded.
        overflow: bool, a patch-size class or the tile pool exceeded its capacity (some triangles
            were not drawn).
        near_clipped: int32 triangles dropped for crossing the near plane.
        status: int32 `jaxtrack.Status`: INVALID_INPUT for a non-finite pose or joint angle,
            RENDER_OVERFLOW (usable, incomplete) on overflow, else OK.
    """

    depth: jax.Array
    face_id: jax.Array
    p_model: jax.Array
    part_id: jax.Array
    vertex_visible: jax.Array
    overflow: jax.Array
    near_clipped: jax.Array
    status: jax.Array

    @property
    def silhouette(self) -> jax.Array:
        return self.face_id >= 0


def _project_vertices(mesh: Mesh, camera: Camera, model: KinematicModel, T_world_root, theta):
    """Camera-frame vertices (V, 3), ideal pixels (V, 2) (distortion is not rendered) and the
    part poses T_cam_part (P, 4, 4)."""
    T_cam_parts = camera.T_cam_world @ part_transforms(model, T_world_root, theta)
    v = mesh.vertices
    if model.num_parts == 1:
        p_cam = jnp.stack(transform_point_columns(T_cam_parts[0], v[:, 0], v[:, 1], v[:, 2]), -1)
    else:
        p_cam = jnp.stack(part_point_columns(T_cam_parts, mesh.vertex_part, v[:, 0], v[:, 1], v[:, 2]), -1)
    z = p_cam[:, 2]
    safe_z = jnp.where(jnp.abs(z) > 1e-6, z, 1e-6)
    K = camera.K
    x, y = p_cam[:, 0] / safe_z, p_cam[:, 1] / safe_z
    px = jnp.stack([K[0, 0] * x + K[0, 1] * y + K[0, 2], K[1, 1] * y + K[1, 2]], -1)
    return p_cam, px, T_cam_parts


def _face_boxes(px_f, valid, width, height):
    """Integer pixel boxes [x0, x1] x [y0, y1] of pixel centres inside each face's bbox, clipped.

    Returns the lower corner (F, 2) int32, the box sides (F, 2) in pixels and the on-screen mask.
    """
    lo = jnp.ceil(jnp.min(px_f, axis=1))
    hi = jnp.floor(jnp.max(px_f, axis=1))
    lo = jnp.maximum(lo, 0)
    hi = jnp.minimum(hi, jnp.array([width - 1, height - 1], px_f.dtype))
    sides = hi - lo + 1
    on_screen = valid & jnp.all(hi >= lo, axis=1)
    return lo.astype(jnp.int32), sides, on_screen


def _edge(ax, ay, bx, by, px, py):
    return (bx - ax) * (py - ay) - (by - ay) * (px - ax)


def _triangle_depths(tri, inv_z_tri, pxf, pyf, mask):
    """Perspective-correct depth (C, P) of triangles `tri` (C, 3, 2) px with vertex 1/z `inv_z_tri` (C, 3) at the
    pixel centres (pxf, pyf) (broadcast with (C, 1) to (C, P)); +inf outside its triangle, for a degenerate
    triangle, behind the camera and where `mask` (broadcast to (C, P)) is False. 1/z is affine in screen space."""
    ax, ay = tri[:, 0, 0:1], tri[:, 0, 1:2]
    bx, by = tri[:, 1, 0:1], tri[:, 1, 1:2]
    cx, cy = tri[:, 2, 0:1], tri[:, 2, 1:2]
    area = _edge(ax, ay, bx, by, cx, cy)
    safe_area = jnp.where(jnp.abs(area) > 1e-12, area, 1.0)
    l0 = _edge(bx, by, cx, cy, pxf, pyf) / safe_area
    l1 = _edge(cx, cy, ax, ay, pxf, pyf) / safe_area
    l2 = 1.0 - l0 - l1
    inside = (l0 >= 0) & (l1 >= 0) & (l2 >= 0) & (jnp.abs(area) > 1e-12) & mask
    inv_z = l0 * inv_z_tri[:, 0:1] + l1 * inv_z_tri[:, 1:2] + l2 * inv_z_tri[:, 2:3]
    return jnp.where(inside & (inv_z > 0), 1.0 / jnp.where(inv_z > 0, inv_z, 1.0), jnp.inf)


def _rasterize_class(px_f, inv_z_f, faces_idx, corner, size: int, width: int, height: int):
    """Candidates of one patch class: flat pixel index, depth and face (masked by coverage).

    `faces_idx` (C,) gives the face of each slot (−1: empty), `corner` (C, 2) the integer pixel of
    its patch's top-left corner.
    """
    num = faces_idx.shape[0]
    face_ok = faces_idx >= 0
    f = jnp.where(face_ok, faces_idx, 0)
    tri = px_f[f]  # (C, 3, 2)
    iz = inv_z_f[f]  # (C, 3)
    offs = jnp.arange(size, dtype=jnp.int32)
    gx = corner[:, 0][:, None, None] + offs[None, None, :]
    gy = corner[:, 1][:, None, None] + offs[None, :, None]
    gx = jnp.broadcast_to(gx, (num, size, size)).reshape(num, -1)
    gy = jnp.broadcast_to(gy, (num, size, size)).reshape(num, -1)
    pxf, pyf = gx.astype(px_f.dtype), gy.astype(px_f.dtype)
    depth = _triangle_depths(tri, iz, pxf, pyf, face_ok[:, None] & (gx < width) & (gy < height))
    inside = jnp.isfinite(depth)
    flat = jnp.where(inside, gy * width + gx, 0)
    return flat.reshape(-1), depth.reshape(-1), jnp.broadcast_to(f[:, None], flat.shape).reshape(-1)


# The dense path (`_rasterize_dense`) tests every face at every pixel: no scatter, which on the CPU costs about ten
# times a pixel test (measured: a 12-face box at 256x256, 32 views batched, 14 ms a view planned and 1.5 ms dense, the
# same depth and face at every pixel). `render` takes it when its F x H x W pixel tests are at most this many times
# the plan's candidate pixels (few large faces: boxes, the view model's close-up renders, small crops).
DENSE_RATIO = 2.0


def planned_candidates(plan: RasterPlan) -> int:
    """Candidate (face, pixel) pairs a plan's patches and tile pool test per render (static)."""
    return sum(s * s * c for s, c in zip(plan.patch_sizes, plan.capacities)) + plan.tile_capacity * plan.tile_size**2


def dense_is_cheaper(plan: RasterPlan, num_faces: int, width: int, height: int) -> bool:
    """Whether `render` tests every face at every pixel instead of the plan's patches (static: shapes and plan):
    `RasterPlan.dense` when set, else whether F · H · W is within `DENSE_RATIO` times the plan's candidates."""
    if plan.dense is not None:
        return bool(plan.dense)
    return num_faces * width * height <= DENSE_RATIO * planned_candidates(plan)


def _rasterize_dense(px_f, inv_z_f, valid, width: int, height: int):
    """Depth (H·W,) and face id (H·W,) with every face tested at every pixel centre (F x H·W pixel tests).

    The same barycentric tests and perspective-correct depth as `_rasterize_class`, and the same tie rule (the
    largest face id among the faces at the nearest depth), so the buffers equal the planned path's wherever that
    path does not overflow; it never overflows.
    """
    gy, gx = jnp.meshgrid(jnp.arange(height, dtype=px_f.dtype), jnp.arange(width, dtype=px_f.dtype), indexing="ij")
    depth_f = _triangle_depths(px_f, inv_z_f, gx.reshape(1, -1), gy.reshape(1, -1), valid[:, None])  # (F, H·W)
    depth = jnp.min(depth_f, axis=0)
    faces = jnp.arange(px_f.shape[0], dtype=jnp.int32)[:, None]
    face_id = jnp.max(jnp.where(jnp.isfinite(depth_f) & (depth_f <= depth[None]), faces, -1), axis=0)
    return depth, face_id


def _rasterize_planned(px_f, inv_z_f, valid, plan: RasterPlan, num_faces: int, width: int, height: int):
    """Depth (H·W,), face id (H·W,) and overflow from the plan's patch classes and tile pool (scatter-min, then the
    winning face by scatter-max among the candidates at the minimum)."""
    lo, sides, on_screen = _face_boxes(px_f, valid, width, height)
    extent = jnp.max(sides, axis=1)
    sizes = jnp.asarray(plan.patch_sizes)
    cls = jnp.searchsorted(sizes, extent.astype(sizes.dtype), side="left")  # smallest size ≥ extent
    cls = jnp.where(on_screen, cls, len(plan.patch_sizes))  # off-screen faces: no class
    flats, depths, fids = [], [], []
    assigned, slot, overflow = _spill_slots(cls, plan.capacities)
    for k, (size, cap) in enumerate(zip(plan.patch_sizes, plan.capacities)):
        if cap == 0:  # a class without slots (its faces spill upwards)
            continue
        idx = jnp.full((cap,), -1, jnp.int32).at[jnp.where(assigned == k, slot, cap)].set(
            jnp.arange(num_faces, dtype=jnp.int32), mode="drop"
        )
        f, d, i = _rasterize_class(px_f, inv_z_f, idx, lo[jnp.maximum(idx, 0)], size, width, height)
        flats.append(f)
        depths.append(d)
        fids.append(i)
    # Faces beyond the largest class: the image tiles they overlap (none planned: an overflow).
    oversized = on_screen & (cls >= len(plan.patch_sizes))
    if plan.tile_capacity > 0 and plan.tile_faces > 0:
        idx, corner, tile_overflow = _tile_slots(
            oversized, px_f, plan.tile_faces, plan.tile_size, plan.tile_capacity, width, height
        )
        overflow = overflow | tile_overflow
        f, d, i = _rasterize_class(px_f, inv_z_f, idx, corner, plan.tile_size, width, height)
        flats.append(f)
        depths.append(d)
        fids.append(i)
    else:
        overflow = overflow | jnp.any(oversized)
    flat = jnp.concatenate(flats)
    depth_c = jnp.concatenate(depths)
    fid_c = jnp.concatenate(fids)
    depth = jnp.full((height * width,), jnp.inf, depth_c.dtype).at[flat].min(depth_c)
    winner = jnp.where(jnp.isfinite(depth_c) & (depth_c <= depth[flat]), fid_c, -1)
    face_id = jnp.full((height * width,), -1, jnp.int32).at[flat].max(winner)
    return depth, face_id, overflow


def render(
    mesh: Mesh,
    camera: Camera,
    T_world_root: ArrayLike,
    theta: ArrayLike | None = None,
    model: KinematicModel | None = None,
    plan: RasterPlan | None = None,
    vertex_depth_tolerance: float = 1e-3,
) -> RenderOutput:
    """Rasterise `mesh` at pose (T_world_root, Θ) in one camera. Jittable, vmappable, differentiable.

    Inside a trace (jit, vmap, grad) it traces inline. Called eagerly it runs as one compiled
    program per (mesh size, camera size, plan), the one `Renderer` uses, instead of op by op (which
    dispatches some hundred small programs per call).

    The faces are drawn through the plan's patch classes and tile pool, or, where testing every face
    at every pixel is cheaper (`dense_is_cheaper`: few large faces, F · H · W within `DENSE_RATIO`
    times the plan's candidates), densely with no scatter; both give the same buffers, and the dense
    path never overflows.

    Args:
        mesh: triangle mesh (V vertices, F faces) with per-vertex parts.
        camera: a single camera (its width/height set the buffers).
        T_world_root: (4, 4) root pose (model → world); theta: (J,) joint angles.
        model: the kinematic tree (rigid if None).
        plan: class capacities (`plan_raster`); `Renderer` makes and updates one for you.
        vertex_depth_tolerance: relative depth slack of the vertex visibility test.
    """
    if plan is None:
        # Without a plan every face would need a full-image patch: F x H x W candidates.
        raise ValueError("render needs a RasterPlan: plan_raster(face_extents(...)) or use Renderer")
    if not _is_traced(mesh, camera, T_world_root, theta, model):
        return _render_compiled(mesh, camera, T_world_root, theta, model, plan, vertex_depth_tolerance)
    return _render_traced(mesh, camera, T_world_root, theta, model, plan, vertex_depth_tolerance)


def _is_traced(*trees) -> bool:
    """Whether any array leaf of `trees` is a tracer (we are inside jit, vmap or a derivative)."""
    return any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves(trees))


def _render_traced(mesh, camera, T_world_root, theta, model, plan, vertex_depth_tolerance):
    """`render`'s body, traced inline (see `render`)."""
    model = rigid_model(mesh.vertices.dtype) if model is None else model
    theta = jnp.zeros((model.num_joints,), mesh.vertices.dtype) if theta is None else theta
    width, height = camera.width, camera.height
    p_cam, px, T_cam_parts = _project_vertices(mesh, camera, model, T_world_root, theta)
    px_f = px[mesh.faces]  # (F, 3, 2)
    z_f = p_cam[mesh.faces, 2]  # (F, 3)
    in_front = jnp.all(z_f > plan.near, axis=1)
    near_clipped = jnp.sum(~in_front & jnp.any(z_f > 0, axis=1))
    valid = in_front
    if plan.cull_backfaces:  # only for closed meshes: a back face is then always hidden
        valid = valid & _front_facing(px_f)
    inv_z_f = 1.0 / jnp.where(in_front[:, None], z_f, 1.0)
    if dense_is_cheaper(plan, mesh.num_faces, width, height):
        depth, face_id = _rasterize_dense(px_f, inv_z_f, valid, width, height)
        overflow = jnp.asarray(False)
    else:
        depth, face_id, overflow = _rasterize_planned(px_f, inv_z_f, valid, plan, mesh.num_faces, width, height)
    depth = depth.reshape(height, width)
    face_id = face_id.reshape(height, width)

    # Surface point behind each pixel: back-project the depth through the pixel (exact for planar
    # faces) and carry it into the model frame of the pixel's part. This replaces per-pixel gathers
    # of the face's vertices, which cost ~4x the rasterisation itself on the CPU.
    covered = face_id >= 0
    part_id = jnp.where(covered, mesh.face_part[jnp.where(covered, face_id, 0)], -1)
    gy, gx = jnp.meshgrid(jnp.arange(height, dtype=px.dtype), jnp.arange(width, dtype=px.dtype), indexing="ij")
    xy = pixels_to_normalized(camera, jnp.stack([gx, gy], -1))
    z = jnp.where(covered, depth, 0.0)
    pix_cam = jnp.stack([xy[..., 0] * z, xy[..., 1] * z, z], -1)
    T_part_cam = se3_inverse(T_cam_parts)  # (P, 4, 4)
    p_model = jnp.zeros_like(pix_cam)
    for p in range(model.num_parts):  # few parts: a select per part beats a per-pixel 4x4 gather
        q = jnp.stack(transform_point_columns(T_part_cam[p], pix_cam[..., 0], pix_cam[..., 1], pix_cam[..., 2]), -1)
        p_model = jnp.where((part_id == p)[..., None], q, p_model)

    # Vertex visibility: in the image and not behind the depth buffer at its pixel.
    u = jnp.round(px[:, 0]).astype(jnp.int32)
    v = jnp.round(px[:, 1]).astype(jnp.int32)
    in_img = (u >= 0) & (u < width) & (v >= 0) & (v < height) & (p_cam[:, 2] > plan.near)
    d_at = depth[jnp.clip(v, 0, height - 1), jnp.clip(u, 0, width - 1)]
    vertex_visible = in_img & (p_cam[:, 2] <= d_at * (1 + vertex_depth_tolerance) + 1e-3)
    pose_ok = jnp.all(jnp.isfinite(T_world_root)) & jnp.all(jnp.isfinite(theta))
    status = first_failure(
        status_where(pose_ok, Status.OK, Status.INVALID_INPUT),
        status_where(overflow, Status.RENDER_OVERFLOW, Status.OK),
    )
    return RenderOutput(
        depth, face_id, p_model, part_id, vertex_visible, overflow, near_clipped.astype(jnp.int32), status
    )


def _spill_slots(cls, capacities: tuple):
    """Slots of the patch classes for faces of class `cls` (F,) (len(capacities): none), spilling upwards.

    The faces, ordered by class from the largest down (by index within a class), fill the classes'
    slots from the largest class down: a class with more faces than its capacity hands the rest to
    spare slots of larger classes (a bigger patch draws the same pixels). So a plan made for bigger
    faces still holds the same faces when they shrink (an object moving away, or smaller in the fixed
    working resolution), and only the counts above each class matter: overflow iff, for some class
    k, more faces are of class ≥ k than the classes ≥ k hold.

    Returns:
        (class each face is drawn in (F,) int32, len(capacities) for none; its slot (F,); overflow).
    """
    num = len(capacities)
    caps = jnp.asarray(capacities, jnp.int32)
    one_hot = (cls[:, None] == jnp.arange(num)[None, :]).astype(jnp.int32)  # (F, K)
    counts = jnp.sum(one_hot, axis=0)
    above = jnp.cumsum(counts[::-1])[::-1] - counts  # faces of a larger class than k
    within = jnp.take_along_axis(jnp.cumsum(one_hot, axis=0), jnp.minimum(cls, num - 1)[:, None], axis=1)[:, 0] - 1
    drawn = cls < num
    rank = jnp.where(drawn, above[jnp.minimum(cls, num - 1)] + within, 0)  # place in largest-first order
    start = jnp.cumsum(caps[::-1])[::-1] - caps  # first rank each class takes (largest class: 0)
    target = num - jnp.sum(rank[:, None] >= start[None, :], axis=1)  # the class whose slots hold that rank
    target = jnp.clip(target, 0, num - 1)
    fits = drawn & (rank < jnp.sum(caps)) & (target >= cls)
    overflow = jnp.any(drawn & ~fits)
    return jnp.where(fits, target, num).astype(jnp.int32), (rank - start[target]).astype(jnp.int32), overflow


def _tile_corners(width: int, height: int, tile: int) -> np.ndarray:
    """Top-left pixels (G, 2) of the square tiles of side `tile` that cut the image (static)."""
    gx, gy = np.meshgrid(np.arange(0, width, tile), np.arange(0, height, tile))
    return np.stack([gx.reshape(-1), gy.reshape(-1)], -1).astype(np.int32)


def _tile_overlap(tri, corners, tile: int):
    """(N, G) bool: triangle n (screen vertices (N, 3, 2)) may cover a pixel centre of tile g.

    Exact separating-axis test of the triangle against the rectangle of the tile's pixel centres
    grown by half a pixel (so rounding never drops a centre the rasteriser would draw): the
    rectangle's two axes, then the triangle's three edge normals. Degenerate triangles count as
    overlapping (the rasteriser's own test drops them).
    """
    x0 = corners[:, 0].astype(tri.dtype) - 0.5
    y0 = corners[:, 1].astype(tri.dtype) - 0.5
    x1, y1 = x0 + tile, y0 + tile
    tmin, tmax = jnp.min(tri, axis=1), jnp.max(tri, axis=1)
    hit = (tmin[:, 0:1] <= x1) & (tmax[:, 0:1] >= x0) & (tmin[:, 1:2] <= y1) & (tmax[:, 1:2] >= y0)
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    orient = jnp.sign(_edge(a[:, 0], a[:, 1], b[:, 0], b[:, 1], c[:, 0], c[:, 1]))[:, None, None]
    xs = jnp.stack([x0, x1, x0, x1], -1)[None]  # (1, G, 4) rectangle corners
    ys = jnp.stack([y0, y0, y1, y1], -1)[None]
    for p, q in ((a, b), (b, c), (c, a)):
        e = _edge(p[:, 0, None, None], p[:, 1, None, None], q[:, 0, None, None], q[:, 1, None, None], xs, ys)
        hit = hit & ~jnp.all(orient * e < 0, axis=-1)  # all four corners outside this edge: separated
    return hit


def _tile_slots(oversized, px_f, face_capacity: int, tile: int, capacity: int, width: int, height: int):
    """Fill the tile pool: one slot per (oversized face, image tile it overlaps).

    The oversized faces are first gathered into `face_capacity` rows, then tested against every image
    tile; the (face, tile) pairs that overlap are packed into `capacity` slots by a running sum.

    Returns:
        face per slot (capacity,) int32 (−1: unused), the slot's tile corner (capacity, 2) int32, and
        whether the faces or their tiles exceeded the pool.
    """
    num_faces = oversized.shape[0]
    rank = jnp.cumsum(oversized) - 1
    faces = jnp.full((face_capacity,), -1, jnp.int32).at[jnp.where(oversized, rank, face_capacity)].set(
        jnp.arange(num_faces, dtype=jnp.int32), mode="drop"
    )
    corners = _tile_corners(width, height, tile)
    num_tiles = len(corners)
    hit = (faces >= 0)[:, None] & _tile_overlap(px_f[jnp.maximum(faces, 0)], jnp.asarray(corners), tile)
    hit = hit.reshape(-1)
    target = jnp.where(hit, jnp.cumsum(hit) - 1, capacity)
    slot_face = jnp.full((capacity,), -1, jnp.int32).at[target].set(jnp.repeat(faces, num_tiles), mode="drop")
    all_corners = jnp.asarray(np.tile(corners, (face_capacity, 1)))
    slot_corner = jnp.zeros((capacity, 2), jnp.int32).at[target].set(all_corners, mode="drop")
    overflow = (jnp.sum(oversized) > face_capacity) | (jnp.sum(hit) > capacity)
    return slot_face, slot_corner, overflow


def _front_facing(px_f):
    a, b, c = px_f[:, 0], px_f[:, 1], px_f[:, 2]
    # Image y points down: CCW-from-outside faces facing the camera have negative signed area.
    return _edge(a[:, 0], a[:, 1], b[:, 0], b[:, 1], c[:, 0], c[:, 1]) < 0


def _screen_faces(mesh, camera, T_world_root, theta, model, cull_backfaces):
    """Host planning: projected faces (F, 3, 2), clipped box sides (F, 2) and the on-screen mask."""
    dtype = mesh.vertices.dtype
    model = rigid_model(dtype) if model is None else model
    # Arguments cast on the host (an eager cast compiles a program in every fresh process).
    theta = np.zeros((model.num_joints,), dtype) if theta is None else np.asarray(theta, dtype)
    return _screen_faces_jit(mesh, camera, np.asarray(T_world_root, dtype), theta, model, bool(cull_backfaces))


def _screen_faces_body(mesh, camera, T_world_root, theta, model, cull_backfaces: bool):
    """`_screen_faces` as one compiled program (op by op it dispatched ~70 primitives, each compiled in every
    fresh process: 3 s of a tracker's start); kept on disk (`persistent_jit`: a warm process does not trace it)."""
    p_cam, px, _ = _project_vertices(mesh, camera, model, T_world_root, theta)
    valid = jnp.all(p_cam[mesh.faces, 2] > 0, axis=1)
    if cull_backfaces:
        valid = valid & _front_facing(px[mesh.faces])
    _, sides, on_screen = _face_boxes(px[mesh.faces], valid, camera.width, camera.height)
    return px[mesh.faces], jnp.where(on_screen[:, None], sides, 0), on_screen


_screen_faces_jit = persistent_jit(_screen_faces_body)


def face_extents(
    mesh: Mesh,
    camera: Camera,
    T_world_root: ArrayLike,
    theta: ArrayLike | None = None,
    model: KinematicModel | None = None,
    cull_backfaces: bool = False,
) -> np.ndarray:
    """Host helper: on-screen pixel extent of every face (0 if off-screen or culled), for planning.

    Returns (F,) the longer side of each face's image-clipped bounding box.
    """
    _, sides, _ = _screen_faces(mesh, camera, T_world_root, theta, model, cull_backfaces)
    return np.asarray(sides).max(axis=1)


def tile_demand(
    mesh: Mesh,
    camera: Camera,
    T_world_root: ArrayLike,
    theta: ArrayLike | None = None,
    model: KinematicModel | None = None,
    cull_backfaces: bool = False,
    threshold: int = PATCH_SIZES[-1],
    tile_size: int = TILE_SIZE,
) -> tuple[int, int]:
    """Host helper: (faces larger than `threshold` px, image tiles those faces overlap) at one pose.

    These are what `render` puts in its tile pool (`RasterPlan.tile_faces`, `tile_capacity`).
    """
    tri, sides, _ = _screen_faces(mesh, camera, T_world_root, theta, model, cull_backfaces)
    big = np.asarray(sides).max(axis=1) > threshold
    if not big.any():
        return 0, 0
    corners = _tile_corners(camera.width, camera.height, tile_size)
    hit = _tile_overlap(jnp.asarray(np.asarray(tri)[big]), jnp.asarray(corners), tile_size)
    return int(big.sum()), int(np.asarray(hit).sum())


def plan_raster(
    extents: ArrayLike,
    margin: float = 1.3,
    minimum: int = 8,
    patch_sizes: tuple = PATCH_SIZES,
    max_size: int | None = None,
    cull_backfaces: bool = False,
    tiles: ArrayLike | None = None,
    tile_size: int = TILE_SIZE,
) -> RasterPlan:
    """Capacities per class from observed face extents (one or more frames), with a margin.

    Capacities are rounded up to multiples of 8 (at least `minimum` for a class in use): a big-patch
    class costs size² candidates per slot, so slack there is expensive. Faces larger than the largest
    class go to the tile pool: room for that many faces (rounded up to 8) and for `tiles` (the tiles
    they overlap per frame, from `tile_demand`) times the margin, or, without `tiles`, the upper bound
    (ceil(extent / tile_size) + 1)² per face.

    Args:
        extents: (F,) or (N, F) face extents in pixels (`face_extents`), N frames.
        tiles: optional () or (N,) tiles the oversized faces overlap per frame (`tile_demand`).
    """
    extents = np.atleast_2d(np.asarray(extents))
    sizes = [s for s in patch_sizes if max_size is None or s < max_size] + ([max_size] if max_size else [])
    sizes = tuple(sorted(set(sizes)))
    caps = []
    for k, s in enumerate(sizes):
        lower = sizes[k - 1] if k else 0
        count = max(int(np.sum((extents > lower) & (extents <= s), axis=1).max()), 0)
        need = max(int(np.ceil(count * margin)), minimum if count else 0)
        caps.append(int(8 * np.ceil(need / 8)) if need else 0)
    kept = [(s, c) for s, c in zip(sizes, caps) if c > 0]
    if not kept:
        kept = [(sizes[0], minimum)]
    oversized = extents > sizes[-1]
    if tiles is None:  # a span of e pixels touches at most ceil(e / tile) + 1 tiles per axis
        tiles = np.sum(np.where(oversized, (np.ceil(extents / tile_size) + 1) ** 2, 0), axis=1)
    big_faces = int(np.ceil(oversized.sum(axis=1).max() * margin))
    return RasterPlan(
        patch_sizes=tuple(s for s, _ in kept),
        capacities=tuple(c for _, c in kept),
        cull_backfaces=cull_backfaces,
        tile_size=tile_size,
        tile_faces=int(8 * np.ceil(big_faces / 8)),
        tile_capacity=int(np.ceil(np.max(tiles) * margin)),  # tile_size² candidates each: no rounding up
    )


def merge_plans(old: RasterPlan, new: RasterPlan) -> RasterPlan:
    """The larger capacity of the two plans class by class (and for the tile pool); never shrinks."""
    if ((old.tile_size, old.near, old.cull_backfaces, old.dense)
            != (new.tile_size, new.near, new.cull_backfaces, new.dense)):
        raise ValueError("merge_plans: the plans differ in tile_size, near, cull_backfaces or dense")
    caps = dict(zip(old.patch_sizes, old.capacities))
    for size, cap in zip(new.patch_sizes, new.capacities):
        caps[size] = max(cap, caps.get(size, 0))
    sizes = tuple(sorted(caps))
    return RasterPlan(
        sizes,
        tuple(caps[s] for s in sizes),
        near=new.near,
        cull_backfaces=new.cull_backfaces,
        tile_size=new.tile_size,
        tile_faces=max(old.tile_faces, new.tile_faces),
        tile_capacity=max(old.tile_capacity, new.tile_capacity),
        dense=new.dense,
    )


@eqx.debug.assert_max_traces(max_traces=None)  # counts traces (`eqx.debug.get_num_traces`), never fails
def _render_body(mesh, camera, T_world_root, theta, model, plan, vertex_depth_tolerance):
    return _render_traced(mesh, camera, T_world_root, theta, model, plan, vertex_depth_tolerance)


# One jitted program for every Renderer: the plan (all static fields) is part of the cache key and
# the mesh and camera are arguments, so renderers of same-sized meshes with the same plan share a
# compilation instead of each closing over its own.
_render_jit = eqx.filter_jit(_render_body)


def _render_compiled(mesh, camera, T_world_root, theta, model, plan, vertex_depth_tolerance=1e-3) -> RenderOutput:
    """`render` through `_render_jit`, its arguments in one canonical form (one cache entry per plan).

    The pose and joint angles become arrays of the mesh's dtype (zeros (J,) when None) and the
    tolerance a float, so an eager `render` and a `Renderer` of the same mesh, camera and plan hit
    the same compiled program.
    """
    dtype = mesh.vertices.dtype
    num_joints = 0 if model is None else model.num_joints
    theta = jnp.zeros((num_joints,), dtype) if theta is None else jnp.asarray(theta, dtype)
    return _render_jit(mesh, camera, jnp.asarray(T_world_root, dtype), theta, model, plan,
                       float(vertex_depth_tolerance))


def replan(
    old: RasterPlan | None,
    mesh: Mesh,
    cameras: Camera,
    T_world_root: ArrayLike,
    theta: ArrayLike | None = None,
    model: KinematicModel | None = None,
    attempt: int = 0,
    cull_backfaces: bool = False,
    base_margin: float = 2.0,
    extent_scale: float = 1.0,
) -> RasterPlan:
    """Host helper: the raster plan for a pose in every camera of a rig, merged with `old` (never shrinks).

    The one place every host class (`Renderer`, `RegionRefiner`, `Tracker`) plans the rasteriser: face
    extents and tile demand per camera, with a margin of `base_margin` · 1.5^attempt (each re-plan after
    an overflow widens it, so a drifting object settles after a few compilations instead of re-planning
    every few frames).

    Args:
        old: the plan in use (None at the start); cameras: one camera or a stacked rig.
        attempt: how many plans were made before (0 for the first).
        extent_scale: plan for faces this many times larger than they are at this pose (headroom).
    """
    rig = cameras if cameras.K.ndim == 3 else jax.tree.map(lambda a: a[None], cameras)
    extents, tiles = [], []
    for c in range(rig.K.shape[0]):
        cam = jax.tree.map(lambda a, c=c: a[c], rig)
        args = (mesh, cam, T_world_root, theta, model, cull_backfaces)
        grown = np.ceil(np.asarray(face_extents(*args)) * extent_scale)
        extents.append(np.minimum(grown, max(cam.width, cam.height)))  # a face's box never exceeds the image
        tiles.append(tile_demand(*args))
    new = plan_raster(np.stack(extents), margin=base_margin * 1.5**attempt, cull_backfaces=cull_backfaces,
                      tiles=np.asarray([t[1] for t in tiles]))
    return new if old is None else merge_plans(old, new)


class Renderer:
    """Host-side convenience: a jitted `render` of one mesh and camera that plans its own capacities.

    `cull_backfaces=True` is for closed (watertight) meshes: back faces are skipped, halving the work.
    The plan comes from the first pose; when a render reports overflow the plan is redone from the
    face extents of that pose (with margin, merged with the old plan) and the frame re-rendered.
    `compilations` counts the plans this renderer made; each is one compilation unless any renderer
    of a same-sized mesh and camera already compiled that plan (programs are shared, keyed by plan).
    """

    def __init__(self, mesh: Mesh, camera: Camera, model: KinematicModel | None = None, cull_backfaces: bool = False):
        self.mesh, self.camera, self.model = mesh, camera, model
        self.cull_backfaces = cull_backfaces
        self.plan: RasterPlan | None = None
        self.compilations = 0

    def _replan(self, T_world_root, theta):
        # Margins 1.3, 1.95, 2.9, ... (`replan`): a drifting object settles after a few compilations.
        self.plan = replan(self.plan, self.mesh, self.camera, T_world_root, theta, self.model, self.compilations,
                           self.cull_backfaces, base_margin=1.3)
        self.compilations += 1

    def __call__(self, T_world_root: ArrayLike, theta: ArrayLike | None = None, throw: bool = True) -> RenderOutput:
        """Render at root pose (4, 4) and joint angles (J,) (default zeros).

        Raises:
            ValueError: a pose or joint-angle array of the wrong shape or with non-finite values.
            StatusError: with `throw`, if the frame still overflows after re-planning (not expected:
                the new plan is made from this very pose); without, the output says RENDER_OVERFLOW.
        """
        num_joints = 0 if self.model is None else self.model.num_joints
        T_np = np.asarray(T_world_root)
        if T_np.shape != (4, 4) or not np.all(np.isfinite(T_np)):
            raise ValueError(f"Renderer: T_world_root must be a finite (4, 4) array, got shape {T_np.shape}")
        T_world_root = jnp.asarray(T_world_root, self.mesh.vertices.dtype)
        if theta is None:
            theta = jnp.zeros((num_joints,), T_world_root.dtype)
        th_np = np.asarray(theta)
        if th_np.shape != (num_joints,) or not np.all(np.isfinite(th_np)):
            raise ValueError(f"Renderer: theta must be a finite ({num_joints},) array, got shape {th_np.shape}")
        if self.plan is None:
            self._replan(T_world_root, theta)
        out = _render_compiled(self.mesh, self.camera, T_world_root, theta, self.model, self.plan)
        if bool(out.overflow):
            self._replan(T_world_root, theta)
            out = _render_compiled(self.mesh, self.camera, T_world_root, theta, self.model, self.plan)
        if throw and bool(out.overflow):
            raise StatusError(Status.RENDER_OVERFLOW, "Renderer: still overflowing after re-planning")
        return out
