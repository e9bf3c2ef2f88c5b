"""Contour points of the model: the sparse viewpoint model (M3T's `RegionModel`) and, per frame, from a render.

Sparse viewpoint model. Cameras on a geodesic sphere around the object (an icosahedron subdivided
`subdivisions` times: 10 · 4^s + 2 views, 2562 for s = 4 as in M3T) each render the silhouette with
the project's rasteriser (`jaxtrack.render.render`, vmapped over a batch of views); the inner contour
pixels are ordered by their angle about the silhouette's centroid and `num_points` of them are taken
evenly spaced in that order. Each becomes a model point (the render's surface point, followed along
the surface onto the sub-pixel contour), a 3D normal (the 2D normal of the Gaussian-smoothed
silhouette, whose level lines near the contour are those of its smoothed signed distance, lifted into
the model frame perpendicular to the optical axis, pointing to the background) and the distances in
mm along the normal for which the line stays inside (foreground) and outside (background) the
silhouette before it meets another part of the contour (M3T drops lines shorter than a few segments).
The smoothed silhouette is evaluated in a window around each chosen pixel only, and its value there
gives the sub-pixel distance to the contour (v = Φ(d/σ) for a straight edge). At tracking
time the view whose direction is closest to the current direction from the object to the camera
(`nearest_view`) supplies the points: no render per frame for rigid objects.

Articulated objects (or anything the precomputed views cannot describe) take the same points from a
render at the current pose (`contour_points_from_render`), a jittable per-frame path.

Ordering by angle spaces the points evenly along a star-shaped contour and never aliases with the
raster (as every k-th pixel in raster order does on two parallel edges); where several contour
pieces share an angle (a torus' inner and outer rim) they share the points in proportion to their
pixel counts.
"""

from __future__ import annotations

import contextlib
import contextvars
import hashlib
import json
import os
import pathlib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..._cache import write_npz_atomically
from ..._device import to_device
from ...geometry import Camera, se3_inverse, transform_points
from ...render import PATCH_SIZES, Mesh, RasterPlan, RenderOutput, hides_its_back_faces, plan_raster, render

# Bump when the build changes what a cached file holds.
_FORMAT_VERSION = 1

# Steepest surface (depth change per lateral change, ≈ 83°) followed onto the contour.
_MAX_SURFACE_SLOPE = 8.0


class ContourPoints(eqx.Module):
    """N (padded) contour points of the model, ready to be projected at a pose.

    Attributes:
        p_model: (N, 3) points on the contour, model frame at the zero configuration (mm).
        normal: (N, 3) unit outward contour normal in the same frame (⊥ the viewing direction of the
            view it came from); zero where only `normal_image` is known.
        normal_image: (N, 2) unit outward normal in the image the points came from (used where
            `normal` is zero).
        part: (N,) int32 part of each point.
        valid: (N,) bool, False for padding.
        foreground_distance: (N,) mm along −normal the line stays on the object (inf: farther than
            was looked).
        background_distance: (N,) mm along +normal the line stays off the object (inf: never
            comes back).
    """

    p_model: jax.Array
    normal: jax.Array
    normal_image: jax.Array
    part: jax.Array
    valid: jax.Array
    foreground_distance: jax.Array
    background_distance: jax.Array


class SparseViewModel(eqx.Module):
    """Contour points of a rigid mesh seen from V directions (M3T's sparse viewpoint model).

    Attributes:
        directions: (V, 3) unit directions from `center` towards the camera of each view, model frame.
        points: (V, N, 3) contour points, model frame (mm).
        normals: (V, N, 3) unit outward contour normals, model frame, ⊥ directions[v].
        foreground_distance: (V, N) mm the line along −normal stays inside the silhouette (inf: beyond
            the render).
        background_distance: (V, N) mm the line along +normal stays outside (inf: never re-enters).
        valid: (V, N) bool, False where a view had fewer than N contour pixels.
        center: (3,) the bounding-box centre the views look at (model frame).
        contour_length: (V,) contour length of each view in mm (pixels × mm per pixel at the point).
    """

    directions: jax.Array
    points: jax.Array
    normals: jax.Array
    foreground_distance: jax.Array
    background_distance: jax.Array
    valid: jax.Array
    center: jax.Array
    contour_length: jax.Array

    @property
    def num_views(self) -> int:
        return self.directions.shape[-2]

    @property
    def num_points(self) -> int:
        return self.points.shape[-2]


# ----------------------------------------------------------------------------------------------- views


def icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit geodesic sphere: vertices (10 · 4^s + 2, 3) and faces (20 · 4^s, 3), counter-clockwise
    seen from outside (host numpy)."""
    t = (1.0 + 5.0**0.5) / 2.0
    verts = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t),
             (0, -1, -t), (0, 1, -t), (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]
    faces = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2),
             (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5),
             (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    v = [np.asarray(p, np.float64) / np.linalg.norm(p) for p in verts]
    for _ in range(int(subdivisions)):
        cache: dict[tuple[int, int], int] = {}

        def midpoint(a: int, b: int, cache: dict = cache) -> int:
            key = (min(a, b), max(a, b))
            if key not in cache:
                m = v[a] + v[b]
                v.append(m / np.linalg.norm(m))
                cache[key] = len(v) - 1
            return cache[key]

        new = []
        for a, b, c in faces:
            ab, bc, ca = midpoint(a, b), midpoint(b, c), midpoint(c, a)
            new += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = new
    vertices = np.stack(v)
    faces = np.asarray(faces, np.int64)
    tri = vertices[faces]
    outward = np.einsum("fi,fi->f", np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), tri.sum(1))
    faces = np.where((outward < 0)[:, None], faces[:, ::-1], faces)
    return vertices, faces


def look_at_rotation(direction: np.ndarray) -> np.ndarray:
    """R_cam_world (3, 3) of a camera on the ray `direction` (unit, from the target towards the camera)
    looking back at the target (host numpy; any roll)."""
    z = -np.asarray(direction, np.float64)
    up = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z])


# ------------------------------------------------------------------------------------ contour sampling


def _gaussian_window(sigma: float):
    """Static window offsets (M, 2) (dx, dy), normalised Gaussian weights (M,) and the weights of its
    gradient (M, 2) (d/dx, d/dy of the blurred image at the window's centre)."""
    r = max(1, int(np.ceil(3.0 * sigma)))
    d = np.arange(-r, r + 1, dtype=np.float64)
    dx, dy = np.meshgrid(d, d, indexing="xy")
    g = np.exp(-0.5 * (dx**2 + dy**2) / sigma**2)
    g /= g.sum()
    offsets = np.stack([dx.ravel(), dy.ravel()], -1).astype(np.int32)
    # blur(p) = Σ g(Δ) I(p + Δ): d blur / dp = Σ g'(Δ) I(p + Δ) with g'(Δ) = −∂g/∂Δ = g(Δ) Δ / σ²
    grad = np.stack([(g * dx).ravel(), (g * dy).ravel()], -1) / sigma**2
    return offsets, g.ravel(), grad


def _blurred_silhouette_at(silhouette, x, y, sigma: float):
    """Gaussian-blurred silhouette (value (N,), gradient (N, 2) in (x, y)) at integer pixels (N,),
    evaluated from a window around each pixel only (off-image pixels count as background)."""
    h, w = silhouette.shape
    offsets, g, grad = _gaussian_window(sigma)
    qx = x[:, None] + offsets[None, :, 0]
    qy = y[:, None] + offsets[None, :, 1]
    on = silhouette[jnp.clip(qy, 0, h - 1), jnp.clip(qx, 0, w - 1)] & (qx >= 0) & (qx < w) & (qy >= 0) & (qy < h)
    on = on.astype(jnp.float32)
    return on @ jnp.asarray(g, jnp.float32), on @ jnp.asarray(grad, jnp.float32)


def _inner_contour(silhouette):
    """(H, W) bool silhouette pixels with a 4-neighbour off it, minus the image's border pixels (a
    silhouette cut by the image border has no contour there)."""
    h, w = silhouette.shape
    p = jnp.pad(silhouette, 1, constant_values=False)
    interior = p[:-2, 1:-1] & p[2:, 1:-1] & p[1:-1, :-2] & p[1:-1, 2:]
    yy, xx = jnp.meshgrid(jnp.arange(h), jnp.arange(w), indexing="ij")
    return silhouette & ~interior & (yy > 0) & (yy < h - 1) & (xx > 0) & (xx < w - 1)


def _line_extents(silhouette, start, normal, march: int):
    """Pixels (capacity,) the line from `start` (capacity, 2) along ∓`normal` stays inside / outside.

    Samples at start ± (j − ½) n, j = 1..march (nearest pixel). Inside: up to the first sample off the
    silhouette or the image (inf if none). Outside: up to the first sample back on the silhouette
    after one that was off it (inf if the image ends first or none does).
    """
    h, w = silhouette.shape
    s = jnp.arange(1, march + 1, dtype=start.dtype) - 0.5

    def lookup(sign):
        q = start[:, None, :] + sign * s[None, :, None] * normal[:, None, :]
        x = jnp.floor(q[..., 0] + 0.5).astype(jnp.int32)
        y = jnp.floor(q[..., 1] + 0.5).astype(jnp.int32)
        inside_img = (x >= 0) & (x < w) & (y >= 0) & (y < h)
        on = silhouette[jnp.clip(y, 0, h - 1), jnp.clip(x, 0, w - 1)] & inside_img
        return inside_img, on

    big = march + 1
    idx = jnp.arange(1, march + 1)
    _, on_in = lookup(-1.0)
    first_off = jnp.min(jnp.where(~on_in, idx, big), axis=1)
    fg = jnp.where(first_off < big, first_off - 1.0, jnp.inf)
    img_out, on_out = lookup(1.0)
    off_seen = jnp.cumsum((img_out & ~on_out).astype(jnp.int32), axis=1)
    seen_before = jnp.concatenate([jnp.zeros_like(off_seen[:, :1]), off_seen[:, :-1]], axis=1) > 0
    back_on = jnp.min(jnp.where(on_out & seen_before, idx, big), axis=1)
    leaves = jnp.min(jnp.where(~img_out, idx, big), axis=1)
    bg = jnp.where((back_on < big) & (back_on < leaves), back_on - 1.0, jnp.inf)
    return fg.astype(start.dtype), bg.astype(start.dtype)


def _silhouette_centroid(silhouette):
    """(cy, cx) float32 mean pixel of an (H, W) silhouette ((0, 0) when empty)."""
    h, w = silhouette.shape
    yy, xx = jnp.meshgrid(jnp.arange(h, dtype=jnp.float32), jnp.arange(w, dtype=jnp.float32), indexing="ij")
    area = jnp.maximum(jnp.sum(silhouette), 1)
    return jnp.sum(jnp.where(silhouette, yy, 0.0)) / area, jnp.sum(jnp.where(silhouette, xx, 0.0)) / area


def _contour_keys(flat_all, count, centroid, width: int):
    """Sort keys (M,) of the first `count` of the contour pixels `flat_all` (M,) (flat indices, raster order): their
    angle about the silhouette's `centroid` (cy, cx); +inf on the padding."""
    cy, cx = centroid
    used = jnp.arange(flat_all.shape[0]) < count
    return jnp.where(used, jnp.arctan2((flat_all // width) - cy, (flat_all % width) - cx), jnp.inf)


def _spread_ranks(count, capacity: int, xp=jnp):
    """Ranks (capacity,) of the contour pixels taken (evenly spaced among `count` when there are more than
    `capacity`, else the first ones) and their validity."""
    i = xp.arange(capacity, dtype=xp.int32)
    spread = ((2 * i + 1) * count) // (2 * capacity)
    return xp.where(count >= capacity, spread, i), i < count


def _select_along_contour(contour, silhouette, capacity: int, max_contour: int):
    """Flat indices (capacity,) of contour pixels evenly spaced in angle order about the silhouette
    centroid, their validity (fewer contour pixels than `capacity` leave trailing slots empty), the
    number of contour pixels and whether it exceeded `max_contour` (then only the first `max_contour`
    in raster order were considered). `select_along_contour_host` is the same selection in numpy."""
    w = contour.shape[1]
    flat_all = jnp.nonzero(contour.reshape(-1), size=max_contour, fill_value=0)[0].astype(jnp.int32)
    total = jnp.sum(contour).astype(jnp.int32)
    count = jnp.minimum(total, max_contour)
    key = _contour_keys(flat_all, count, _silhouette_centroid(silhouette), w)
    order = jnp.argsort(key, stable=True)
    rank, valid = _spread_ranks(count, capacity)
    return flat_all[order[jnp.clip(rank, 0, max_contour - 1)]], valid, total, total > max_contour


def contour_pixels_host(contour: np.ndarray, max_contour: int) -> tuple[np.ndarray, np.ndarray]:
    """The nonzero of `_select_along_contour` on the host for a batch of contours (B, H, W): flat indices (B,
    `max_contour`) int32 in raster order, padded with 0, and the number of contour pixels (B,) int32."""
    flat_all = np.zeros((len(contour), max_contour), np.int32)
    total = np.zeros(len(contour), np.int32)
    for i, c in enumerate(contour):
        flat = np.flatnonzero(c.reshape(-1))
        total[i] = len(flat)
        flat_all[i, : min(len(flat), max_contour)] = flat[:max_contour]
    return flat_all, total


def select_along_contour_host(flat_all: np.ndarray, total: int, keys: np.ndarray, capacity: int):
    """The rest of `_select_along_contour` for one view on the host, from `contour_pixels_host` (flat_all (M,),
    total) and `_contour_keys` of them (M,): flat (capacity,) int32, valid (capacity,), total, overflow. The same
    indices (a stable sort of the same keys) at a tenth of the time of XLA's nonzero and sort of M keys on the CPU."""
    max_contour = len(flat_all)
    count = min(int(total), max_contour)
    # The padding's keys are +inf: a stable sort leaves it after the contour pixels, in its own order.
    order = np.concatenate([np.argsort(keys[:count], kind="stable"), np.arange(count, max_contour)])
    rank, valid = _spread_ranks(count, capacity, np)
    picked = flat_all[order[np.clip(rank, 0, max_contour - 1)]].astype(np.int32)
    return picked, valid, int(total), int(total) > max_contour


def _contour_samples_at(silhouette, depth, K, flat, valid, march: int, sigma: float):
    """Contour samples of one silhouette at its selected contour pixels `flat` (N,) (validity `valid`,
    `_select_along_contour`): pixel (N, 2), sub-pixel offset to the contour (≥ 0, along the normal), unit
    outward 2D normal, inside/outside extents in px, depth, flat index, validity.

    The normal is the negated gradient of the Gaussian-blurred silhouette (σ = `sigma` px), whose level
    lines near the contour are those of the smoothed signed distance; the offset to the contour is the
    distance d at which a straight edge gives the blurred value v = Φ(d/σ) (Φ the normal CDF).
    """
    w = silhouette.shape[1]
    dtype = K.dtype
    y, x = flat // w, flat % w
    value, grad = _blurred_silhouette_at(silhouette, x, y, sigma)
    value, grad = value.astype(dtype), grad.astype(dtype)
    norm = jnp.linalg.norm(grad, axis=-1)
    valid = valid & (norm > 1e-3)
    normal = -grad / jnp.where(norm > 1e-3, norm, 1.0)[:, None]
    v = jnp.clip(value, 0.02, 0.98)
    offset = jnp.clip(sigma * np.sqrt(2.0) * jax.scipy.special.erfinv(2.0 * v - 1.0), 0.0, 1.5)
    pixel = jnp.stack([x, y], -1).astype(dtype)
    fg, bg = _line_extents(silhouette, pixel + offset[:, None] * normal, normal, march)
    z = depth.reshape(-1)[flat].astype(dtype)
    valid = valid & jnp.isfinite(z) & (z > 0)
    return pixel, offset, normal, fg, bg, jnp.where(valid, z, 1.0), flat, valid


def _lift(K, normal_2d, offset, z):
    """Camera-frame 3D normal (N, 3) (unit, z = 0) and the shift (N, 3) of a point at depth z moving
    `offset` px along the 2D normal."""
    d = jnp.stack([normal_2d[:, 0] / K[0, 0], normal_2d[:, 1] / K[1, 1], jnp.zeros_like(z)], -1)
    n3 = d / jnp.linalg.norm(d, axis=-1, keepdims=True)
    return n3, (offset * z)[:, None] * d


def contour_points_from_render(
    render_output: RenderOutput,
    camera: Camera,
    capacity: int,
    T_world_parts: jax.Array | None = None,
    march: int = 64,
    sigma: float = 1.5,
    max_contour: int | None = None,
) -> tuple[ContourPoints, jax.Array, jax.Array]:
    """Up to `capacity` contour points evenly spread along the silhouette of one render. Jittable.

    The per-frame path (articulated objects, or any object without a view model): the inner contour
    pixels of `render_output.silhouette`, ordered by angle about the centroid and taken evenly spaced;
    each gets the render's model point and part, the unit outward normal of the Gaussian-smoothed
    (σ = `sigma` px) silhouette, and the inside/outside extents along it. The model point is moved
    onto the sub-pixel contour along the surface (extrapolated from the next pixel inward; where that
    pixel is on another part or the surface is steeper than 83°, sideways at constant depth when
    `T_world_parts` is given, else not at all).

    Args:
        render_output: one `RenderOutput` (H, W) of `camera` (its silhouette, depth, p_model, part_id).
        camera: the single camera it was rendered with (K sets px ↔ mm).
        capacity: N, number of slots (static).
        T_world_parts: optional (P, 4, 4) part poses of the render (`part_transforms`); when given the
            normals are lifted into the model frame (`ContourPoints.normal`, so they follow the pose
            in later rounds); without it only `normal_image` is set.
        march: how far (px, static) the inside/outside extents are searched (inf beyond).
        sigma: smoothing of the silhouette for the normals and the sub-pixel offsets (px, static).
        max_contour: contour pixels considered (static; default 4 (H + W)); beyond it only the first
            ones in raster order are (check `count` against it: the third value returned).

    Returns:
        (ContourPoints with N rows, pixel (N, 2): the (sub-pixel) contour position in the render,
        count: int32 number of contour pixels in the render).
    """
    sil = render_output.silhouette
    h, w = sil.shape
    max_contour = 4 * (h + w) if max_contour is None else int(max_contour)
    flat, valid, count, _ = _select_along_contour(_inner_contour(sil), sil, capacity, max_contour)
    points, pixel = _contour_points_at(render_output, camera, flat, valid, T_world_parts, march, sigma)
    return points, pixel, count


def _contour_points_at(render_output: RenderOutput, camera: Camera, flat, valid, T_world_parts, march: int,
                       sigma: float) -> tuple[ContourPoints, jax.Array]:
    """`contour_points_from_render` at selected contour pixels: flat (N,) int32 indices into the render, valid (N,).
    Returns (ContourPoints, the sub-pixel contour position (N, 2))."""
    sil = render_output.silhouette
    K = camera.K
    dtype = K.dtype
    h, w = sil.shape
    pixel, offset, n2, fg, bg, z, flat, valid = _contour_samples_at(sil, render_output.depth, K, flat, valid, march,
                                                                    sigma)
    p_img = render_output.p_model.reshape(-1, 3)
    p_model = p_img[flat].astype(dtype)
    part = jnp.maximum(render_output.part_id.reshape(-1)[flat], 0).astype(jnp.int32)
    mm_per_px = z / K[0, 0]
    # Onto the contour: follow the surface outward from the contour pixel's point by the sub-pixel
    # offset, extrapolating from the neighbour one pixel inward (exact on a planar face, whose edge
    # the contour is; a lateral shift at constant depth would miss it by offset · cot(slant)).
    q = jnp.floor(pixel - n2 + 0.5).astype(jnp.int32)
    q_in = (q[:, 0] >= 0) & (q[:, 0] < w) & (q[:, 1] >= 0) & (q[:, 1] < h)
    q_flat = jnp.clip(q[:, 1], 0, h - 1) * w + jnp.clip(q[:, 0], 0, w - 1)
    along = -jnp.sum((q.astype(dtype) - pixel) * n2, axis=-1)  # px inward, ~0.7..1
    dp = p_img[q_flat].astype(dtype) - p_model
    slope = jnp.linalg.norm(dp, axis=-1) / (jnp.maximum(along, 1e-3) * mm_per_px)
    follow = (q_in & (render_output.part_id.reshape(-1)[q_flat] == part) & (along > 0.5)
              & (slope < _MAX_SURFACE_SLOPE))
    surface_shift = -dp * (offset / jnp.maximum(along, 1e-3))[:, None]
    if T_world_parts is None:
        normal = jnp.zeros_like(p_model)
        shift = jnp.where(follow[:, None], surface_shift, 0.0)
    else:
        n3_cam, shift_cam = _lift(K, n2, offset, z)
        T_cam_part = camera.T_cam_world.astype(dtype) @ jnp.asarray(T_world_parts, dtype)  # (P, 4, 4)
        R_part_cam = jnp.swapaxes(T_cam_part[:, :3, :3], -1, -2)[part]  # (N, 3, 3)
        normal = jnp.einsum("nij,nj->ni", R_part_cam, n3_cam)
        shift = jnp.where(follow[:, None], surface_shift, jnp.einsum("nij,nj->ni", R_part_cam, shift_cam))
    points = ContourPoints(
        p_model=jnp.where(valid[:, None], p_model + shift, 0.0),
        normal=jnp.where(valid[:, None], normal, 0.0),
        normal_image=jnp.where(valid[:, None], n2, 0.0),
        part=jnp.where(valid, part, 0),
        valid=valid,
        foreground_distance=fg * mm_per_px,
        background_distance=bg * mm_per_px,
    )
    return points, pixel + offset[:, None] * n2


# ------------------------------------------------------------------------------------ the view model


def _view_cameras(center: np.ndarray, radius: float, directions: np.ndarray, image_size: int, distance_factor: float):
    """K (3, 3) and T_cam_world (V, 4, 4) of cameras at `distance_factor` · radius from the centre,
    with a focal length that puts the bounding sphere's outline at 90 % of the half image."""
    dist = distance_factor * radius
    f = 0.9 * (image_size / 2.0) * np.sqrt(dist**2 - radius**2) / radius
    c = (image_size - 1) / 2.0
    K = np.array([[f, 0.0, c], [0.0, f, c], [0.0, 0.0, 1.0]])
    T = np.zeros((len(directions), 4, 4))
    for i, d in enumerate(directions):
        R = look_at_rotation(d)
        eye = center + dist * d
        T[i, :3, :3] = R
        T[i, :3, 3] = -R @ eye
        T[i, 3, 3] = 1.0
    return K, T


def _face_extents_all(vertices: np.ndarray, faces: np.ndarray, K: np.ndarray, T: np.ndarray, size: int, cull: bool):
    """(V, F) int16 on-screen extents of every face in every view (host numpy, float64; as `face_extents`).

    Computed a few views at a time (temporaries of about 2^15 values) from the mesh's distinct vertex positions: the
    (V, F) float64 temporaries of all views at once (1.8 GB for a 15k-face mesh's 2562 views) took 81 s and 9 GB
    there, this 1.4 s, the same extents.
    """
    distinct, inverse = np.unique(vertices, axis=0, return_inverse=True)
    chunk = max(1, 2**15 // max(len(faces), len(distinct)))
    corners = inverse.reshape(-1)[faces]
    f0, f1, f2 = corners[:, 0], corners[:, 1], corners[:, 2]
    x, y, z = (distinct[None, :, i] for i in range(3))
    out = np.empty((len(T), len(faces)), np.int16)
    for start in range(0, len(T), chunk):
        R, t = T[start:start + chunk, :3, :3], T[start:start + chunk, :3, 3]

        def cam(i, R=R, t=t):  # camera-frame coordinate i of every distinct vertex, (chunk, N)
            return R[:, i, 0:1] * x + R[:, i, 1:2] * y + R[:, i, 2:3] * z + t[:, i:i + 1]

        depth = cam(2)
        u = K[0, 0] * cam(0) / depth + K[0, 2]
        v = K[1, 1] * cam(1) / depth + K[1, 2]
        u0, u1, u2, v0, v1, v2 = u[:, f0], u[:, f1], u[:, f2], v[:, f0], v[:, f1], v[:, f2]
        lo_u = np.maximum(np.ceil(np.minimum(np.minimum(u0, u1), u2)), 0)
        hi_u = np.minimum(np.floor(np.maximum(np.maximum(u0, u1), u2)), size - 1)
        lo_v = np.maximum(np.ceil(np.minimum(np.minimum(v0, v1), v2)), 0)
        hi_v = np.minimum(np.floor(np.maximum(np.maximum(v0, v1), v2)), size - 1)
        ok = (hi_u >= lo_u) & (hi_v >= lo_v)
        if cull:
            ok &= (u1 - u0) * (v2 - v0) - (v1 - v0) * (u2 - u0) < 0
        out[start:start + chunk] = np.where(ok, np.maximum(hi_u - lo_u, hi_v - lo_v) + 1, 0)
    return out


def _tight_plan(extents: np.ndarray, cull: bool, chunk: int = 64) -> RasterPlan:
    """Exact capacities per patch class for a known set of views (V, F): the most faces any view puts in
    each class (`plan_raster` rounds to multiples of 8, which for meshes of a few faces costs more
    than the faces themselves); `plan_raster` with its tile pool when a face is larger than the classes.
    Counted `chunk` views at a time (no (V, F) temporaries)."""
    sizes = np.asarray(PATCH_SIZES)
    if extents.max() > sizes[-1]:
        return plan_raster(extents, margin=1.0, cull_backfaces=cull)
    caps = np.zeros(len(sizes) + 1, np.int64)
    for start in range(0, len(extents), chunk):
        e = extents[start:start + chunk]
        cls = np.where(e > 0, np.searchsorted(sizes, e, side="left"), len(sizes))
        rows = np.arange(len(e))[:, None] * (len(sizes) + 1)
        counts = np.bincount((cls + rows).ravel(), minlength=len(e) * (len(sizes) + 1)).reshape(len(e), -1)
        caps = np.maximum(caps, counts.max(axis=0))
    kept = [(int(s), int(c)) for s, c in zip(sizes, caps[:-1]) if c > 0] or [(int(sizes[0]), 1)]
    return RasterPlan(patch_sizes=tuple(s for s, _ in kept), capacities=tuple(c for _, c in kept), cull_backfaces=cull)


# Who hears of a build's progress (`view_model_build_progress`): a callable (views done, views in all), or None.
_BUILD_PROGRESS: contextvars.ContextVar = contextvars.ContextVar("jaxtrack_view_model_build_progress", default=None)


@contextlib.contextmanager
def view_model_build_progress(callback):
    """Within the block, every `build_view_model` of this thread (a new mesh's model, built by `Tracker.start`) calls
    `callback(views_done, views_total)` after each batch of views: a progress bar's hook (`track_sequence` shows it)."""
    token = _BUILD_PROGRESS.set(callback)
    try:
        yield
    finally:
        _BUILD_PROGRESS.reset(token)


# Views per vmapped call of the build: 8 renders a box's 2562 views in 5.7 s against 8.5 s at 32 on a 2-core CPU; a
# mesh of many faces, which takes the planned raster path, built in the same time either way (the real dragon: 66 s,
# before its plan and the contour selection moved to the host: experiments/results/view_model_build.md).
# The model depends on it a little: pixels exactly on a face's edge fall either way in other batch shapes
# (experiments/results/*_view_batch_8.md).
BUILD_BATCH_SIZE = 8


def build_view_model(
    mesh: Mesh,
    num_points: int = 200,
    subdivisions: int = 4,
    image_size: int = 256,
    distance_factor: float = 10.0,
    batch_size: int = BUILD_BATCH_SIZE,
    cull_backfaces: bool | None = None,
    sigma: float = 1.5,
    progress: bool = False,
) -> SparseViewModel:
    """Render the mesh from 10 · 4^subdivisions + 2 directions and keep `num_points` contour points each.

    Host-side (numpy; per batch of views one jitted, vmapped render, the contour pixels selected on the host
    between it and the extraction of their points, `select_along_contour_host`).

    Args:
        mesh: a rigid triangle mesh (mm).
        num_points: N contour points per view (M3T: 200).
        subdivisions: of the icosahedron (M3T: 4 → 2562 views).
        image_size: side of the square renders in px; the object's bounding sphere fills 90 % of it.
        distance_factor: camera distance in bounding radii (far: nearly orthographic views).
        batch_size: views per vmapped call (memory ∝ batch_size · image_size²; default `BUILD_BATCH_SIZE`).
        cull_backfaces: skip back faces (exact for closed meshes, about twice as fast); None: when
            the mesh hides its back faces (`jaxtrack.render.hides_its_back_faces`).
        sigma: smoothing (px) of the silhouette for the normals.
        progress: print a line per batch (`view_model_build_progress` hands each batch to a callback).

    Returns:
        SparseViewModel in the mesh's dtype.

    Raises:
        ValueError: bad settings; RuntimeError: a render overflowed its plan (should not happen).
    """
    if num_points < 1 or subdivisions < 0 or image_size < 16 or distance_factor <= 1.0 or batch_size < 1:
        raise ValueError(
            "build_view_model: need num_points ≥ 1, subdivisions ≥ 0, image_size ≥ 16, distance_factor > 1, "
            f"batch_size ≥ 1; got {num_points}, {subdivisions}, {image_size}, {distance_factor}, {batch_size}"
        )
    dtype = mesh.vertices.dtype
    vertices = np.asarray(mesh.vertices, np.float64)
    faces = np.asarray(mesh.faces)
    center = 0.5 * (vertices.min(0) + vertices.max(0))
    radius = float(np.max(np.linalg.norm(vertices - center, axis=1)))
    if not radius > 0:
        raise ValueError("build_view_model: the mesh has no extent")
    if cull_backfaces is None:
        cull_backfaces = hides_its_back_faces(mesh)
    directions, _ = icosphere(subdivisions)
    K, T = _view_cameras(center, radius, directions, image_size, distance_factor)
    plan = _tight_plan(_face_extents_all(vertices, faces, K, T, image_size, cull_backfaces), cull_backfaces)
    identity = to_device(np.eye(4), dtype)
    Kj = to_device(K, dtype)
    max_contour = 16 * image_size

    def camera_at(T_cam_world):
        return Camera(Kj, T_cam_world, jnp.zeros((5,), dtype), width=image_size, height=image_size)

    def render_view(T_cam_world):  # the render, its contour pixels and the silhouette's centroid
        out = render(mesh, camera_at(T_cam_world), identity, plan=plan)
        return out, _inner_contour(out.silhouette), _silhouette_centroid(out.silhouette)

    def points_of_view(out, T_cam_world, flat, valid):
        return _contour_points_at(out, camera_at(T_cam_world), flat, valid, identity[None], image_size, sigma)[0]

    # The selection of `contour_points_from_render` split around the host: XLA's nonzero over the image and stable
    # sort of `max_contour` keys per view cost as much as the render on the CPU (a box: 8.8 of 18 ms per 8 views), and
    # the keys over the whole image another 4.7 ms; the keys of the contour pixels alone are their own program.
    render_batch = jax.jit(jax.vmap(render_view))
    keys_batch = jax.jit(jax.vmap(lambda flat_all, count, centroid: _contour_keys(flat_all, count, centroid, image_size)))
    points_batch = jax.jit(jax.vmap(points_of_view))
    num_views = len(directions)
    chunks = []
    for start in range(0, num_views, batch_size):
        stop = min(start + batch_size, num_views)
        Tb = T[start:stop]
        if stop - start < batch_size:  # pad the last batch: one compiled shape
            Tb = np.concatenate([Tb, np.repeat(Tb[-1:], batch_size - (stop - start), axis=0)])
        Tb = to_device(Tb, dtype)
        out, contour, centroid = render_batch(Tb)
        flat_all, total = contour_pixels_host(np.asarray(contour), max_contour)
        keys = np.asarray(keys_batch(flat_all, np.minimum(total, max_contour), centroid))
        flat, valid, count, too_long = (np.stack(a) for a in zip(*(
            select_along_contour_host(flat_all[i], total[i], keys[i], num_points) for i in range(batch_size))))
        if bool(np.any((np.asarray(out.overflow) | too_long)[: stop - start])):
            raise RuntimeError("build_view_model: a view overflowed the raster plan or had more than "
                               f"{max_contour} contour pixels")
        points = points_batch(out, Tb, flat, valid)
        chunks.append(jax.tree_util.tree_map(lambda a, n=stop - start: np.asarray(a)[:n], (points, count)))
        if progress:
            print(f"build_view_model: {stop}/{num_views} views", flush=True)
        if (report := _BUILD_PROGRESS.get()) is not None:
            report(stop, num_views)
    points = jax.tree_util.tree_map(lambda *a: np.concatenate(a), *[c[0] for c in chunks])
    count = np.concatenate([c[1] for c in chunks])
    mm_per_px = (distance_factor * radius) / K[0, 0]
    return SparseViewModel(
        directions=to_device(directions, dtype),
        points=to_device(points.p_model, dtype),
        normals=to_device(points.normal, dtype),
        foreground_distance=to_device(points.foreground_distance, dtype),
        background_distance=to_device(points.background_distance, dtype),
        valid=to_device(points.valid),
        center=to_device(center, dtype),
        contour_length=to_device(count * mm_per_px, dtype),
    )


def _cache_key(mesh: Mesh, settings: dict) -> str:
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(np.asarray(mesh.vertices, np.float64)).tobytes())
    h.update(np.ascontiguousarray(np.asarray(mesh.faces, np.int64)).tobytes())
    h.update(json.dumps({**settings, "format": _FORMAT_VERSION}, sort_keys=True).encode())
    return h.hexdigest()


def default_cache_dir() -> pathlib.Path:
    """$JAXTRACK_CACHE if set, else ~/.cache/jaxtrack/viewmodels."""
    env = os.environ.get("JAXTRACK_CACHE")
    return pathlib.Path(env) if env else pathlib.Path.home() / ".cache" / "jaxtrack" / "viewmodels"


def view_model_path(mesh: Mesh, cache_dir=None, **settings) -> pathlib.Path:
    """The .npz file `load_or_build_view_model` uses for this mesh and settings."""
    full = dict(_BUILD_DEFAULTS, **settings)
    folder = default_cache_dir() if cache_dir is None else pathlib.Path(cache_dir)
    return folder / f"viewmodel-{_cache_key(mesh, full)[:40]}.npz"


_BUILD_DEFAULTS = {"num_points": 200, "subdivisions": 4, "image_size": 256, "distance_factor": 10.0,
                   "cull_backfaces": None, "sigma": 1.5}
_FIELDS = ("directions", "points", "normals", "foreground_distance", "background_distance", "valid", "center",
           "contour_length")


def save_view_model(model: SparseViewModel, path) -> None:
    """Write a view model as .npz (atomically: a temporary file renamed into place)."""
    write_npz_atomically(path, {k: np.asarray(getattr(model, k)) for k in _FIELDS})


def load_view_model(path, dtype=jnp.float32) -> SparseViewModel:
    """Read a view model written by `save_view_model`."""
    with np.load(path) as data:
        arrays = {k: data[k] for k in _FIELDS}
    return SparseViewModel(**{k: to_device(v) if k == "valid" else to_device(v, dtype) for k, v in arrays.items()})


def load_or_build_view_model(mesh: Mesh, cache_dir=None, batch_size: int = BUILD_BATCH_SIZE, progress: bool = False,
                             **settings) -> SparseViewModel:
    """`build_view_model` cached on disk as .npz, keyed by a sha256 of the mesh's vertices and faces and
    the settings (`num_points`, `subdivisions`, `image_size`, `distance_factor`, `cull_backfaces`,
    `sigma`). cache_dir: default $JAXTRACK_CACHE or ~/.cache/jaxtrack/viewmodels."""
    unknown = set(settings) - set(_BUILD_DEFAULTS)
    if unknown:
        raise ValueError(f"load_or_build_view_model: unknown settings {sorted(unknown)}")
    path = view_model_path(mesh, cache_dir, **settings)
    dtype = mesh.vertices.dtype
    if path.is_file():
        try:
            return load_view_model(path, dtype)
        except (OSError, ValueError, KeyError):
            pass  # unreadable or stale: rebuild
    model = build_view_model(mesh, batch_size=batch_size, progress=progress, **dict(_BUILD_DEFAULTS, **settings))
    save_view_model(model, path)
    return model


# --------------------------------------------------------------------------------------- at run time


def camera_direction(view_model: SparseViewModel, camera: Camera, T_world_root) -> jax.Array:
    """(3,) unit direction from the model's centre towards the camera's centre, model frame. Jittable.

    Args:
        camera: a single camera; T_world_root: (4, 4) the object's pose (model → world).
    """
    c_model = transform_points(se3_inverse(jnp.asarray(T_world_root)), camera.center_world)
    d = c_model.astype(view_model.center.dtype) - view_model.center
    return d / jnp.maximum(jnp.linalg.norm(d), 1e-12)


def nearest_view(view_model: SparseViewModel, direction) -> jax.Array:
    """int32 index of the view whose direction is closest to `direction` (3,) (from the object towards
    the camera, model frame, any length): argmax of the dot products. Jittable."""
    return jnp.argmax(view_model.directions @ jnp.asarray(direction, view_model.directions.dtype)).astype(jnp.int32)


def view_points(view_model: SparseViewModel, index) -> ContourPoints:
    """The contour points of view `index` (a traced int is fine) as `ContourPoints` (part 0)."""
    p = view_model.points[index]
    n = p.shape[0]
    return ContourPoints(
        p_model=p,
        normal=view_model.normals[index],
        normal_image=jnp.zeros((n, 2), p.dtype),
        part=jnp.zeros((n,), jnp.int32),
        valid=view_model.valid[index],
        foreground_distance=view_model.foreground_distance[index],
        background_distance=view_model.background_distance[index],
    )


def points_for_pose(view_model: SparseViewModel, camera: Camera, T_world_root) -> ContourPoints:
    """The nearest view's contour points for an object at `T_world_root` seen by `camera`. Jittable."""
    return view_points(view_model, nearest_view(view_model, camera_direction(view_model, camera, T_world_root)))
