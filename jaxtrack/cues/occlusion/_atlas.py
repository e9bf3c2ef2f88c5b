"""A texture atlas over a triangle mesh: the support of the appearance model f(X) (Section III-C).

Every face carries the cells (i, j) of an R_f × R_f grid over its barycentric coordinates (l1, l2) that
touch the triangle (i + j ≤ R_f), stored row after row: R_f (R_f + 3) / 2 − 1 texels instead of R_f² (the
cells beyond the triangle were stored too until 2026-11-27: 38 % of the mocap human's 266 000, read in every
camera at every frame). R_f follows the face's longest edge and a texel size in mm, so big faces (the 12
triangles of a box) and small ones (a teapot's 9438) both get texels of about one pixel. An elongated face
(a capsule's slivers, 400 x 20 mm) gets texels 20 times finer across than along it. With `rectangular=True`
(opt-in since 2026-11-28) a face carries a rectangular R1 × R2 grid along its two edges from one vertex
instead (R = ⌈edge / texel⌉ each) wherever that stores at most half the cells (mostly elongated faces; at a
few cells a face also rounds into it; its texels stay at most texel_mm a side): the mocap human's atlas in the
tracker 170 384 → 55 344 texels, but the occluded and noisy sequences tracked worse with the coarser texels
(README, "Texels along elongated faces"). The atlas is built once on the host; inside jit it is a constant
pytree of arrays.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..._device import to_device
from ...render import Mesh


class TextureAtlas(eqx.Module):
    """Texel layout of a mesh (T texels in all, F faces).

    Attributes:
        face_offset: (F,) int32 index of face f's first texel.
        face_res: (F, 2) int32 cells along the two barycentric axes: (R_f, R_f) of a square grid (row i holds the
            cells j ≤ min(R_f − 1, R_f − i), see `_row_start`) or (R1, R2) of a rectangular one (R2 cells a row).
        face_rect: (F,) bool the face has a rectangular grid (`rectangular=True` and it stores at most half the cells).
        any_rect: static: some face has one (without, `texel_index` reads the square layout alone: the default's
            per-pixel lookup and program as before the rectangular grids).
        face_map: (F, 2, 4) affine map from a model-frame point on face f to its (l1, l2).
        texel_p_model: (T, 3) texel centre, model frame at the zero configuration (mm), clamped
            into its triangle (a rectangular grid's cells beyond the hypotenuse, not live: their lower corner).
        texel_part: (T,) int32 part of the texel's face.
        texel_live: (T,) bool texel of a non-degenerate face whose cell touches the triangle (every cell of a square
            grid; a rectangular grid's cell with its lower corner on the triangle).
        texel_normal: (T, 3) unit normal of the texel's face (model frame).
    """

    face_offset: jax.Array
    face_res: jax.Array
    face_rect: jax.Array
    face_map: jax.Array
    texel_p_model: jax.Array
    texel_part: jax.Array
    texel_live: jax.Array
    texel_normal: jax.Array
    any_rect: bool = eqx.field(static=True, default=False)

    @property
    def num_texels(self) -> int:
        return self.texel_live.shape[0]


def _face_resolutions(edge_max, texel_mm, max_res):
    return np.clip(np.ceil(edge_max / texel_mm), 1, max_res).astype(np.int64)


def make_texture_atlas(mesh: Mesh, texel_mm: float = 1.0, max_texels: int = 400_000, max_res: int = 512,
                       rectangular: bool = False) -> TextureAtlas:
    """Build the atlas of `mesh` (host side).

    Args:
        mesh: the tracked mesh (model frame, mm).
        texel_mm: texel edge length; about the pixel footprint of the surface at the working distance
            (e.g. 1 mm for a 16 cm object seen at 60 cm with f = 700 px).
        max_texels: capacity bound; the texel size grows until Σ R_f² (the square grids of the longest edges) fits,
            so the atlas, which stores fewer cells per face, holds fewer texels (the resolutions as before the
            compact layouts).
        max_res: largest R_f (and R1, R2 of a rectangular grid).
        rectangular: rectangular grids where they store at most half the cells (elongated faces; module
            docstring); False: every face the square grid (the default: measured to track the occluded and noisy
            sequences better, README).

    Raises:
        ValueError: for a non-positive `texel_mm` or `max_texels` smaller than the face count.
    """
    if not texel_mm > 0:
        raise ValueError(f"texel_mm must be > 0, got {texel_mm}")
    v = np.asarray(mesh.vertices, np.float64)
    f = np.asarray(mesh.faces, np.int64)
    if max_texels < len(f):
        raise ValueError(f"max_texels ({max_texels}) must be at least the number of faces ({len(f)})")
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    edge_max = np.max(np.stack([np.linalg.norm(b - a, axis=1), np.linalg.norm(c - a, axis=1), np.linalg.norm(c - b, axis=1)]), 0)
    res = _face_resolutions(edge_max, texel_mm, max_res)
    while np.sum(res**2) > max_texels:
        texel_mm *= 1.1 * np.sqrt(np.sum(res**2) / max_texels)
        res = _face_resolutions(edge_max, texel_mm, max_res)
    # With `rectangular`, a face gets a rectangular grid R1 × R2 along the two edges from the vertex (of the three
    # cyclic orders, which keep the normal) that stores the fewest cells, where that is at most half the square grid's
    # cells (slivers: texels about texel_mm along both edges instead of texel_mm / aspect across; a few faces of a
    # few cells round into it too).
    square_cells = res * (res + 3) // 2 - 1
    if rectangular:
        rect_res, rotation = _rectangular_resolutions(v, f, texel_mm, max_res)
        rect = 2 * rect_res[:, 0] * rect_res[:, 1] <= square_cells
    else:
        rect_res, rotation, rect = np.ones((len(f), 2), np.int64), np.zeros(len(f), np.int64), np.zeros(len(f), bool)
    k = np.where(rect, rotation, 0)
    rows = np.arange(len(f))
    a, b, c = v[f[rows, k]], v[f[rows, (k + 1) % 3]], v[f[rows, (k + 2) % 3]]
    e1, e2 = b - a, c - a
    grid = np.where(rect[:, None], rect_res, res[:, None])  # (F, 2) cells along e1 and e2
    # (l1, l2) = G⁻¹ [e1·(p − a), e2·(p − a)]: least squares on the face plane.
    G = np.stack([np.stack([np.sum(e1 * e1, 1), np.sum(e1 * e2, 1)], -1), np.stack([np.sum(e1 * e2, 1), np.sum(e2 * e2, 1)], -1)], 1)
    det = G[:, 0, 0] * G[:, 1, 1] - G[:, 0, 1] ** 2
    ok = det > 1e-12 * np.maximum(G[:, 0, 0] * G[:, 1, 1], 1e-30)
    Ginv = np.zeros_like(G)
    Ginv[ok] = np.linalg.inv(G[ok])
    lin = np.einsum("fij,fjk->fik", Ginv, np.stack([e1, e2], 1))  # (F, 2, 3)
    off = -np.einsum("fik,fk->fi", lin, a)
    face_map = np.concatenate([lin, off[..., None]], -1)
    normal = np.cross(e1, e2)  # a cyclic order: the face's own normal
    normal = normal / np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-30)
    cells = np.where(rect, grid[:, 0] * grid[:, 1], square_cells)
    offset = np.concatenate([[0], np.cumsum(cells)[:-1]])
    full = grid[:, 0] * grid[:, 1]  # every face's whole grid, row after row; square faces keep i + j ≤ R of it
    face_of = np.repeat(np.arange(len(f)), full)
    local = np.arange(int(np.sum(full))) - np.concatenate([[0], np.cumsum(full)[:-1]])[face_of]
    r1, r2 = grid[face_of, 0], grid[face_of, 1]
    i, j = local // r2, local % r2
    kept = rect[face_of] | (i + j <= r1)  # a square grid's cell [i, i+1] x [j, j+1] / R touching the triangle
    face_of, r1, r2, i, j = face_of[kept], r1[kept], r2[kept], i[kept], j[kept]
    is_rect = rect[face_of]
    # the layout texel_index reads: square faces row i at `_row_start(i, R)`, rectangular ones R2 cells per row
    assert np.array_equal(offset[face_of] + np.where(is_rect, i * r2, _row_start(i, r1)) + j, np.arange(len(face_of)))
    # A rectangular grid's cells beyond the hypotenuse (lower corner i/R1 + j/R2 > 1) are never read: not live.
    touches = ~is_rect | (j * r1 <= r2 * (r1 - i))
    l1, l2 = (i + 0.5) / r1, (j + 0.5) / r2
    s = np.maximum(l1 + l2, 1.0)  # clamp centres into the triangle (square grids: toward the face's first vertex)
    l1, l2 = np.where(is_rect, l1, l1 / s), np.where(is_rect, l2, l2 / s)
    # Rectangular grids: a cell cut by the hypotenuse keeps its centre in the cell, halfway from its lower corner to
    # the hypotenuse along its diagonal (scaling toward the vertex would move it many cells along the long edge).
    room = np.maximum(1.0 - i / r1 - j / r2, 0.0) / (1.0 / r1 + 1.0 / r2)  # diagonal steps to the hypotenuse
    t = np.minimum(0.5, 0.5 * room)
    l1, l2 = np.where(is_rect, (i + t) / r1, l1), np.where(is_rect, (j + t) / r2, l2)
    p = a[face_of] + l1[:, None] * e1[face_of] + l2[:, None] * e2[face_of]
    dtype = mesh.vertices.dtype

    return TextureAtlas(
        face_offset=to_device(offset, np.int32),
        face_res=to_device(grid, np.int32),
        face_rect=to_device(rect),
        face_map=to_device(face_map, dtype),
        texel_p_model=to_device(p, dtype),
        texel_part=to_device(np.asarray(mesh.face_part)[face_of], np.int32),
        texel_live=to_device(ok[face_of] & touches),
        texel_normal=to_device(normal[face_of], dtype),
        any_rect=bool(np.any(rect)),
    )


def _rectangular_resolutions(v, f, texel_mm, max_res):
    """(F, 2) int R1, R2 = ⌈|e1| / texel⌉, ⌈|e2| / texel⌉ of the cyclic vertex order (F,) in {0, 1, 2} (the first vertex)
    whose rectangular grid R1 · R2 is smallest."""
    best_res, best_k = None, None
    for k in range(3):
        a, b, c = v[f[:, k]], v[f[:, (k + 1) % 3]], v[f[:, (k + 2) % 3]]
        r = np.stack([_face_resolutions(np.linalg.norm(b - a, axis=1), texel_mm, max_res),
                      _face_resolutions(np.linalg.norm(c - a, axis=1), texel_mm, max_res)], -1)
        if best_res is None:
            best_res, best_k = r, np.zeros(len(f), np.int64)
            continue
        better = r[:, 0] * r[:, 1] < best_res[:, 0] * best_res[:, 1]
        best_res, best_k = np.where(better[:, None], r, best_res), np.where(better, k, best_k)
    return best_res, best_k


def texel_index(atlas: TextureAtlas, face_id, p_model):
    """Texel under surface points: face ids (...,) (−1 = none) and model points (..., 3) → (...,) int32
    texel index (0 where face_id < 0; mask with face_id ≥ 0). Jittable. A point on its triangle falls in a stored
    cell (i/R1 + j/R2 ≤ 1); one at least a cell beyond the hypotenuse gets its row's last cell on the triangle (with
    the full square grid it fell on a never-observed cell, "unknown")."""
    covered = face_id >= 0
    face = jnp.where(covered, face_id, 0)
    M = atlas.face_map[face]  # (..., 2, 4)
    l = M[..., :3] @ p_model[..., None]
    l = l[..., 0] + M[..., 3]
    res = atlas.face_res[face]  # (..., 2)
    ij = jnp.clip(jnp.floor(l * res.astype(l.dtype)).astype(jnp.int32), 0, res - 1)
    i, j = ij[..., 0], ij[..., 1]
    r1, r2 = res[..., 0], res[..., 1]
    local = _row_start(i, r1) + jnp.minimum(j, r1 - i)  # a point on the triangle has i + j ≤ R
    if atlas.any_rect:  # ... on a rectangular grid j ≤ R2 (R1 − i) / R1
        local = jnp.where(atlas.face_rect[face], i * r2 + jnp.minimum(j, (r2 * (r1 - i)) // r1), local)
    return jnp.where(covered, atlas.face_offset[face] + local, 0)


def _row_start(i, r):
    """Index of cell (i, 0) among a face's stored cells: row 0 holds R cells, row i ≥ 1 holds R − i + 1
    (j ≤ R − i). Works on numpy and jax integer arrays."""
    return i * r - (i > 0) * ((i - 1) * i // 2 - (i - 1))
