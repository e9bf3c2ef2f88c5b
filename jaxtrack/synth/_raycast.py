"""An independent image renderer for synthetic sequences: embree ray casting (through trimesh) and a
small shader. It shares no code with the tracker's JAX rasteriser, so the tracker is never only
tested on its own renderer's pixels.

Surface colour comes from the mesh's UV texture, a photograph projected along the model z axis, or
one flat colour; Lambert shading with an ambient term. The background is a textured plane in the
world (a photograph or a flat colour), so camera motion moves it with the correct parallax.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import numpy.typing as npt
import trimesh
from trimesh.ray.ray_pyembree import RayMeshIntersector


@dataclasses.dataclass
class Appearance:
    """How the object surface is coloured: kind is 'texture', 'photo' or 'flat'."""

    kind: str
    image: np.ndarray | None = None  # (h, w, 3) float32 0-255 for texture / photo
    colour: tuple = (200.0, 60.0, 40.0)


def mesh_appearance(
    tm: trimesh.Trimesh,
    kind: str,
    photo: np.ndarray | None = None,
    colour: npt.ArrayLike = (200.0, 60.0, 40.0),
) -> Appearance:
    """An `Appearance` for a mesh; 'texture' needs UVs and an image on the mesh."""
    if kind == "texture":
        uv = getattr(tm.visual, "uv", None)
        mat = getattr(tm.visual, "material", None)
        img = getattr(mat, "image", None) or getattr(mat, "baseColorTexture", None)
        if uv is None or img is None:
            raise ValueError("appearance 'texture' needs a mesh with UV coordinates and a texture image")
        return Appearance("texture", np.asarray(img.convert("RGB"), np.float32))
    if kind == "photo":
        if photo is None:
            raise ValueError("appearance 'photo' needs a photograph")
        return Appearance("photo", np.asarray(photo, np.float32))
    if kind == "flat":
        return Appearance("flat", colour=tuple(float(c) for c in colour))
    raise ValueError(f"unknown appearance {kind!r} (texture, photo, flat)")


def _sample(image, u, v):
    """Bilinear lookup of image (h, w, 3) at normalised u, v ∈ [0, 1] (v = 0 at the bottom, as UVs)."""
    h, w = image.shape[:2]
    x = np.clip(u, 0, 1) * (w - 1)
    y = (1 - np.clip(v, 0, 1)) * (h - 1)
    n = len(x)
    cols = 1024  # cv2.remap wants maps under 32767 columns: fold the point list into rows
    pad = (-n) % cols
    mx = np.pad(x.astype(np.float32), (0, pad)).reshape(-1, cols)
    my = np.pad(y.astype(np.float32), (0, pad)).reshape(-1, cols)
    out = cv2.remap(np.ascontiguousarray(image), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    return out.reshape(-1, image.shape[2])[:n]


class RayCaster:
    """Ray casts one mesh (model frame, mm) placed at T_cam_obj in a pinhole camera."""

    def __init__(self, tm: trimesh.Trimesh, appearance: Appearance):
        self.tm = tm
        self.appearance = appearance
        self.intersector = RayMeshIntersector(tm)
        lo, hi = tm.bounds
        self._lo, self._span = lo, np.maximum(hi - lo, 1e-9)

    def cast(self, K: np.ndarray, T_cam_obj: np.ndarray, width: int, height: int):
        """Face id (H, W) (−1 = miss), depth (H, W) (inf = miss) and model-frame hit points."""
        v, u = np.mgrid[0:height, 0:width]
        d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones(u.shape)], -1).reshape(-1, 3)
        R, t = T_cam_obj[:3, :3], T_cam_obj[:3, 3]
        d_obj = d_cam @ R  # Rᵀ d
        d_obj /= np.linalg.norm(d_obj, axis=1, keepdims=True)
        origin = -R.T @ t
        loc, ray, tri = self.intersector.intersects_location(np.repeat(origin[None], len(d_obj), 0), d_obj, multiple_hits=False)
        face = np.full(height * width, -1)
        face[ray] = tri
        depth = np.full(height * width, np.inf)
        depth[ray] = (loc @ R.T + t)[:, 2]
        points = np.zeros((height * width, 3))
        points[ray] = loc
        return face.reshape(height, width), depth.reshape(height, width), points.reshape(height, width, 3)

    def shade(
        self,
        face: np.ndarray,
        points: np.ndarray,
        T_cam_obj: npt.ArrayLike,
        light_cam: npt.ArrayLike = (0.3, -0.5, -1.0),
        ambient: float = 0.45,
    ):
        """Colour (H, W, 3) of hit pixels (zeros elsewhere)."""
        hit = face >= 0
        f = face[hit]
        p = points[hit]
        app = self.appearance
        if app.kind == "texture":
            tri = self.tm.triangles[f]
            bary = trimesh.triangles.points_to_barycentric(tri, p)
            uv = np.einsum("nk,nkj->nj", bary, self.tm.visual.uv[self.tm.faces[f]])
            col = _sample(app.image, uv[:, 0], uv[:, 1])
        elif app.kind == "photo":
            rel = (p - self._lo) / self._span
            col = _sample(app.image, rel[:, 0], rel[:, 1])
        else:
            col = np.broadcast_to(np.asarray(app.colour, np.float32), (len(f), 3))
        n_cam = self.tm.face_normals[f] @ T_cam_obj[:3, :3].T
        light = -np.asarray(light_cam, float) / np.linalg.norm(light_cam)
        lambert = np.abs(n_cam @ light)  # two-sided: open meshes show their inside too
        out = np.zeros(face.shape + (3,), np.float32)
        out[hit] = col * (ambient + (1 - ambient) * lambert)[:, None]
        return out


def background_plane(
    image: np.ndarray | None,
    colour: npt.ArrayLike,
    K: npt.ArrayLike,
    T_cam_world: npt.ArrayLike,
    width: int,
    height: int,
    depth_world: float = 2500.0,
    size: float = 4000.0,
):
    """A textured plane z_world = depth_world (size x size mm) seen by the camera, (H, W, 3)."""
    if image is None:
        return np.broadcast_to(np.asarray(colour, np.float32), (height, width, 3)).copy()
    v, u = np.mgrid[0:height, 0:width]
    d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones(u.shape)], -1).reshape(-1, 3)
    R, t = T_cam_world[:3, :3], T_cam_world[:3, 3]
    d_w = d_cam @ R
    o = -R.T @ t
    s = (depth_world - o[2]) / np.where(np.abs(d_w[:, 2]) > 1e-9, d_w[:, 2], 1e-9)
    hit = o + s[:, None] * d_w
    uu = (hit[:, 0] / size + 0.5) % 1.0
    vv = 1.0 - ((hit[:, 1] / size + 0.5) % 1.0)
    return _sample(np.asarray(image, np.float32), uu, vv).reshape(height, width, 3)
