"""A texture atlas over a triangle mesh: the support of the appearance model f(X) (Section III-C).

Every face carries the cells (i, j) of an R_f × R_f grid over its barycentric coordinates (l1, l2) that
touch the triangle (i + j ≤ R_f), stored row after row: R_f (R_f + 3) / 2 − 1 texels instead of R_f² (the
cells beyond the triangle were stored too until 2026-11-27: 38 % of the mocap human's 266 000, read in every
camera at every frame). R_f follows the face's longest
edge and a texel size in mm, so big faces (the 12 triangles of a box) and small ones (a teapot's
9438) both get texels of about one pixel. The atlas is built once on the host; inside jit it is a
constant pytree of arrays.
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
        face_res: (F,) int32 grid resolution R_f (cells along each barycentric axis; row i holds the cells
            j ≤ min(R_f − 1, R_f − i), see `_row_start`).
        face_map: (F, 2, 4) affine map from a model-frame point on face f to its (l1, l2).
        texel_p_model: (T, 3) texel centre, model frame at the zero configuration (mm), clamped
            into its triangle.
        texel_part: (T,) int32 part of the texel's face.
        texel_live: (T,) bool texel of a non-degenerate face (every stored cell touches its triangle).
        texel_normal: (T, 3) unit normal of the texel's face (model frame).
    """

    face_offset: jax.Array
    face_res: jax.Array
    face_map: jax.Array
    texel_p_model: jax.Array
    texel_part: jax.Array
    texel_live: jax.Array
    texel_normal: jax.Array

    @property
    def num_texels(self) -> int:
        return self.texel_live.shape[0]


def _face_resolutions(edge_max, texel_mm, max_res):
    return np.clip(np.ceil(edge_max / texel_mm), 1, max_res).astype(np.int64)


def make_texture_atlas(mesh: Mesh, texel_mm: float = 1.0, max_texels: int = 400_000, max_res: int = 512) -> TextureAtlas:
    """Build the atlas of `mesh` (host side).

    Args:
        mesh: the tracked mesh (model frame, mm).
        texel_mm: texel edge length; about the pixel footprint of the surface at the working distance
            (e.g. 1 mm for a 16 cm object seen at 60 cm with f = 700 px).
        max_texels: capacity bound; the texel size grows until Σ R_f² (the full grids) fits, so the atlas, which
            stores R_f (R_f + 3) / 2 − 1 cells per face, holds fewer texels (the resolutions as before the
            compact layout).
        max_res: largest R_f.

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
    e1, e2 = b - a, c - a
    edge_max = np.max(np.stack([np.linalg.norm(e1, axis=1), np.linalg.norm(e2, axis=1), np.linalg.norm(c - b, axis=1)]), 0)
    res = _face_resolutions(edge_max, texel_mm, max_res)
    while np.sum(res**2) > max_texels:
        texel_mm *= 1.1 * np.sqrt(np.sum(res**2) / max_texels)
        res = _face_resolutions(edge_max, texel_mm, max_res)
    # (l1, l2) = G⁻¹ [e1·(p − a), e2·(p − a)]: least squares on the face plane.
    G = np.stack([np.stack([np.sum(e1 * e1, 1), np.sum(e1 * e2, 1)], -1), np.stack([np.sum(e1 * e2, 1), np.sum(e2 * e2, 1)], -1)], 1)
    det = G[:, 0, 0] * G[:, 1, 1] - G[:, 0, 1] ** 2
    ok = det > 1e-12 * np.maximum(G[:, 0, 0] * G[:, 1, 1], 1e-30)
    Ginv = np.zeros_like(G)
    Ginv[ok] = np.linalg.inv(G[ok])
    lin = np.einsum("fij,fjk->fik", Ginv, np.stack([e1, e2], 1))  # (F, 2, 3)
    off = -np.einsum("fik,fk->fi", lin, a)
    face_map = np.concatenate([lin, off[..., None]], -1)
    normal = np.cross(e1, e2)
    normal = normal / np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-30)
    square = np.concatenate([[0], np.cumsum(res**2)[:-1]])
    face_of = np.repeat(np.arange(len(f)), res**2)
    local = np.arange(int(np.sum(res**2))) - square[face_of]
    r = res[face_of]
    i, j = local // r, local % r
    touches = i + j <= r  # the cell [i, i+1] x [j, j+1] / R touches the triangle l1 + l2 ≤ 1: the only ones kept
    face_of, r, i, j = face_of[touches], r[touches], i[touches], j[touches]
    offset = np.concatenate([[0], np.cumsum(res * (res + 3) // 2 - 1)[:-1]])
    assert np.array_equal(offset[face_of] + _row_start(i, r) + j, np.arange(len(face_of)))  # the layout texel_index reads
    l1, l2 = (i + 0.5) / r, (j + 0.5) / r
    s = np.maximum(l1 + l2, 1.0)  # clamp centres into the triangle
    l1, l2 = l1 / s, l2 / s
    p = a[face_of] + l1[:, None] * e1[face_of] + l2[:, None] * e2[face_of]
    dtype = mesh.vertices.dtype

    return TextureAtlas(
        face_offset=to_device(offset, np.int32),
        face_res=to_device(res, np.int32),
        face_map=to_device(face_map, dtype),
        texel_p_model=to_device(p, dtype),
        texel_part=to_device(np.asarray(mesh.face_part)[face_of], np.int32),
        texel_live=to_device(ok[face_of]),
        texel_normal=to_device(normal[face_of], dtype),
    )


def texel_index(atlas: TextureAtlas, face_id, p_model):
    """Texel under surface points: face ids (...,) (−1 = none) and model points (..., 3) → (...,) int32
    texel index (0 where face_id < 0; mask with face_id ≥ 0). Jittable. A point on its triangle falls in a stored
    cell (i + j ≤ R); one at least a cell beyond the hypotenuse gets its row's last stored cell (with the full grid
    it fell on a never-observed cell, "unknown")."""
    covered = face_id >= 0
    face = jnp.where(covered, face_id, 0)
    M = atlas.face_map[face]  # (..., 2, 4)
    l = M[..., :3] @ p_model[..., None]
    l = l[..., 0] + M[..., 3]
    res = atlas.face_res[face]
    ij = jnp.clip(jnp.floor(l * res[..., None].astype(l.dtype)).astype(jnp.int32), 0, res[..., None] - 1)
    i = ij[..., 0]
    j = jnp.minimum(ij[..., 1], res - i)  # a point on the triangle has i + j ≤ R (a cell beyond it: its row's last)
    return jnp.where(covered, atlas.face_offset[face] + _row_start(i, res) + j, 0)


def _row_start(i, r):
    """Index of cell (i, 0) among a face's stored cells: row 0 holds R cells, row i ≥ 1 holds R − i + 1
    (j ≤ R − i). Works on numpy and jax integer arrays."""
    return i * r - (i > 0) * ((i - 1) * i // 2 - (i - 1))
