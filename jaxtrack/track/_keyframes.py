"""Keyframes for re-detection after a loss (issue 24): SIFT descriptors with their 3D model points, and a pose from
a frame by matching them and PnP + RANSAC (host side, OpenCV and embree).

A keyframe is taken where the pose is known or trusted: the first frame, and later frames reported OK whose
rotation differs from every keyframe's by more than `min_angle_deg` (the object shows other faces), up to
`max_keyframes` (the oldest after the first is replaced). Its keypoints inside the visible object region are lifted
onto the mesh by casting their camera rays (embree, in the model frame: `MeshRays`): each keeps its descriptor and
its model point.

`locate` detects SIFT in a region of a new frame, matches it against every keyframe's descriptors (Lowe's ratio
test, conflicts dropped) and solves PnP with RANSAC (`cv2.solvePnPRansac`, EPnP, then Levenberg-Marquardt on the
inliers). Unlike the region energy on the contour, the keypoints tell a symmetric object's turned poses apart
where it is textured; an untextured object gives no pose (too few inliers).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..cues.sift import SiftConfig
from ..cues.sift._detect import detect_sift, match_descriptors, opencv_threads


@dataclasses.dataclass(frozen=True)
class KeyframeConfig:
    """Settings of the keyframe model and of the PnP re-detection.

    Attributes:
        max_keyframes: keyframes kept (the first frame's always).
        min_angle_deg: a frame reported OK becomes a keyframe when its rotation differs from every keyframe's by more.
        ratio: Lowe's ratio bound of the descriptor matches (0.8: his recognition setting).
        reprojection_px: RANSAC's inlier bound, px per 1000 px of image diagonal (4 px at 400 px, 8 at 800).
        min_inliers: fewest RANSAC inliers for a pose.
        iterations: RANSAC iterations.
        region_growth: the search region is the box of the reference poses grown by this times its size on each side.
    """

    max_keyframes: int = 8
    min_angle_deg: float = 30.0
    ratio: float = 0.8
    reprojection_px: float = 10.0
    min_inliers: int = 12
    iterations: int = 500
    region_growth: float = 1.0

    def __post_init__(self):
        if self.max_keyframes < 1 or self.min_inliers < 4 or self.iterations < 1:
            raise ValueError("KeyframeConfig: max_keyframes ≥ 1, min_inliers ≥ 4 and iterations ≥ 1 required")
        if not 0.0 < self.ratio <= 1.0 or self.reprojection_px <= 0 or self.min_angle_deg < 0 or self.region_growth < 0:
            raise ValueError("KeyframeConfig: ratio in (0, 1], reprojection_px > 0, min_angle_deg ≥ 0, region_growth ≥ 0")


# Rays whose direction's cosine with the hit triangle's normal is at most this are dropped (trimesh's `planes_lines`).
GRAZING_COSINE = 1e-5


class MeshRays:
    """First hits of rays on a triangle mesh, through embree (`embreex`, without trimesh: its import alone costs about
    a second of a warm tracker's start).

    As trimesh's embree intersector does: embree finds the hit triangle in float32 on the mesh moved to its bounding
    box's corner and scaled to a 100-unit diagonal (for precision); the hit point is then the ray's intersection with
    that triangle's plane in float64.

    Args:
        vertices: (V, 3) model frame; faces: (F, 3) vertex indices.
    """

    def __init__(self, vertices, faces):
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh

        vertices, faces = np.asarray(vertices, np.float64), np.asarray(faces, np.int64)
        self.origin = vertices.min(axis=0)
        diagonal = float(np.linalg.norm(vertices.max(axis=0) - self.origin))
        self.scale = 100.0 / diagonal if diagonal > 0 else 1.0
        self.scene = rtcore_scene.EmbreeScene()
        TriangleMesh(scene=self.scene, vertices=((vertices - self.origin) * self.scale).astype(np.float32),
                     indices=faces.astype(np.int32))
        corners = vertices[faces]  # (F, 3, 3)
        self.plane_points = corners[:, 0]
        normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        length = np.linalg.norm(normals, axis=1, keepdims=True)
        self.plane_normals = normals / np.where(length > 0, length, 1.0)

    def first_hits(self, origins, directions) -> tuple[np.ndarray, np.ndarray]:
        """(m, 3) float64 first hit points and (m,) int64 indices of the rays (n, 3) origins + (n, 3) directions that
        hit the mesh; rays that graze the hit triangle (|cos| ≤ `GRAZING_COSINE` with its normal) are dropped.

        Raises:
            ValueError: origins and directions not both (n, 3)."""
        origins, directions = np.asarray(origins, np.float64), np.asarray(directions, np.float64)
        if origins.shape != directions.shape or origins.ndim != 2 or origins.shape[1] != 3:
            raise ValueError(f"MeshRays.first_hits: origins and directions must both be (n, 3), got {origins.shape} and "
                             f"{directions.shape}")
        directions = directions / np.maximum(np.linalg.norm(directions, axis=1, keepdims=True), 1e-300)
        if len(origins) == 0:
            return np.zeros((0, 3)), np.zeros(0, np.int64)
        face = self.scene.run(((origins - self.origin) * self.scale).astype(np.float32), directions.astype(np.float32))
        ray = np.flatnonzero(face != -1)
        n = self.plane_normals[face[ray]]
        along = np.einsum("ij,ij->i", directions[ray], n)
        ok = np.abs(along) > GRAZING_COSINE  # trimesh's bound: a grazing ray's float32 hit is no point to trust
        ray, n, along = ray[ok], n[ok], along[ok]
        t = np.einsum("ij,ij->i", self.plane_points[face[ray]] - origins[ray], n) / along
        return origins[ray] + t[:, None] * directions[ray], ray.astype(np.int64)


@dataclasses.dataclass
class Keyframe:
    """One keyframe: descriptors (n, 128) float32, model points (n, 3) (mm), the pose's rotation (3, 3) model → world."""

    descriptors: np.ndarray
    points_model: np.ndarray
    R_world_root: np.ndarray


@dataclasses.dataclass
class PnPResult:
    """A pose from the keyframes: T_world_root (4, 4), inliers (RANSAC), matches tried, camera used."""

    T_world_root: np.ndarray
    inliers: int
    matches: int
    camera: int


def _rotation_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    c = (np.trace(Ra.T @ Rb) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


class KeyframeModel:
    """The keyframes of one rigid object seen by a rig (host side).

    Args:
        vertices, faces: the mesh (model frame, mm).
        config: `KeyframeConfig`; sift: detection settings (detected at the frames' own resolution, every keypoint
            kept: `max_side` and `max_keypoints` are per-frame budgets of the tracking cue, not of a keyframe).
    """

    def __init__(self, vertices, faces, config: KeyframeConfig | None = None, sift: SiftConfig | None = None):
        self.config = KeyframeConfig() if config is None else config
        self.sift = dataclasses.replace(SiftConfig() if sift is None else sift, max_side=0, max_keypoints=0)
        self.rays = MeshRays(vertices, faces)
        self.keyframes: list[Keyframe] = []
        self.tried: list[np.ndarray] = []  # rotations of every keyframe attempt (kept or not: no keypoints there)

    def __len__(self) -> int:
        return len(self.keyframes)

    def wants(self, T_world_root) -> bool:
        """Whether a frame at this pose (reported OK) would be a new keyframe: its rotation is new (also against
        attempts that found no keypoints), and there is room or a keyframe other than the first to replace."""
        if self.config.max_keyframes == 1 and self.keyframes:
            return False
        R = np.asarray(T_world_root, np.float64)[:3, :3]
        return all(_rotation_deg(R, Rk) > self.config.min_angle_deg for Rk in self.tried)

    def add(self, images, masks, K, dist, T_cam_world, T_world_root) -> int:
        """Take a keyframe from (C, H, W, 3) images at a trusted pose; `masks` (C, H, W) the visible object pixels,
        K (C, 3, 3), dist (C, 5), T_cam_world (C, 4, 4). Returns the keypoints kept (on the mesh)."""
        T = np.asarray(T_world_root, np.float64)
        self.tried.append(T[:3, :3].copy())
        desc, pts = [], []
        for c in range(len(images)):
            xy, d = detect_sift(images[c], masks[c], self.sift)
            if not len(xy):
                continue
            T_model_cam = np.linalg.inv(np.asarray(T_cam_world[c], np.float64) @ T)
            rays = _rays(xy, K[c], dist[c])  # camera frame
            origin = np.repeat(T_model_cam[:3, 3][None], len(rays), 0)
            loc, index = self.rays.first_hits(origin, rays @ T_model_cam[:3, :3].T)
            if len(index):
                desc.append(d[index])
                pts.append(loc)
        if not desc:
            return 0
        frame = Keyframe(np.concatenate(desc).astype(np.float32), np.concatenate(pts), T[:3, :3].copy())
        if len(self.keyframes) >= self.config.max_keyframes:
            self.keyframes.pop(1 if len(self.keyframes) > 1 else 0)
        self.keyframes.append(frame)
        return len(frame.descriptors)

    def locate(self, images, regions, K, dist, T_cam_world) -> PnPResult | None:
        """The pose of the object in (C, H, W, 3) images from the keyframes: SIFT in each camera's `regions` (C, H, W)
        bool, matched to every keyframe, PnP + RANSAC per camera; the camera with the most inliers wins. None when no
        camera has `min_inliers`."""
        import cv2

        if not self.keyframes:
            return None
        best = None
        for c in range(len(images)):
            xy, d = detect_sift(images[c], regions[c], self.sift)
            # Each keyframe matched on its own: keyframes share features, and one call over all of them would drop
            # every frame keypoint that two of them match (`match_descriptors` deletes conflicts).
            obj, img = [], []
            for k in self.keyframes:
                ia, ib, _ = match_descriptors(k.descriptors, d, self.config.ratio)
                obj.append(k.points_model[ia])
                img.append(xy[ib])
            obj, img = np.concatenate(obj).astype(np.float64), np.concatenate(img).astype(np.float64)
            if len(obj) < self.config.min_inliers:
                continue
            h, w = images[c].shape[:2]
            bound = self.config.reprojection_px * float(np.hypot(h, w)) / 1000.0
            Kc, dc = np.asarray(K[c], np.float64), np.asarray(dist[c], np.float64)
            with opencv_threads(1):
                ok, rvec, tvec, inl = cv2.solvePnPRansac(obj, img, Kc, dc, iterationsCount=self.config.iterations,
                                                         reprojectionError=bound, confidence=0.999, flags=cv2.SOLVEPNP_EPNP)
                if not ok or inl is None or len(inl) < self.config.min_inliers:
                    continue
                inl = inl[:, 0]
                ok, rvec, tvec = cv2.solvePnP(obj[inl], img[inl], Kc, dc, rvec, tvec, useExtrinsicGuess=True,
                                              flags=cv2.SOLVEPNP_ITERATIVE)
            if not ok or tvec[2, 0] <= 0:
                continue
            T_cam_model = np.eye(4)
            T_cam_model[:3, :3] = cv2.Rodrigues(rvec)[0]
            T_cam_model[:3, 3] = tvec[:, 0]
            found = PnPResult(np.linalg.inv(np.asarray(T_cam_world[c], np.float64)) @ T_cam_model, len(inl), len(obj), c)
            if best is None or found.inliers > best.inliers:
                best = found
        return best


def _rays(xy, K, dist) -> np.ndarray:
    """(n, 3) unit camera-frame ray directions of pixels (n, 2) (distorted, as in the image)."""
    import cv2

    pts = np.asarray(xy, np.float64).reshape(-1, 1, 2)
    with opencv_threads(1):
        norm = cv2.undistortPoints(pts, np.asarray(K, np.float64), np.asarray(dist, np.float64)).reshape(-1, 2)
    rays = np.concatenate([norm, np.ones((len(norm), 1))], axis=1)
    return rays / np.linalg.norm(rays, axis=1, keepdims=True)
