"""Overlay videos of a tracking run: the model's contour and the segmented contour over each frame.

Host code (numpy + OpenCV), called once per frame while tracking so no frame is kept in memory:

    with OverlayWriter("overlay.mp4", (H, C * W)) as video:      # or a folder of PNGs
        run = track_sequence(seq, on_frame=OverlayRecorder(video, vertices, faces, K))   # K: (C, 3, 3)

The model contour is the outline of the mesh's silhouette at the estimated pose: every triangle with all
three vertices in front of the camera is projected (OpenCV distortion included) and filled, and the
outline of the union is drawn. This is independent of the tracker's JAX renderer, so the overlay shows
the pose as reported, not a by-product of the step. The segmented contour is the zero level of the
region cue's Φ (> 0 inside, `FrameResult.region_phi`, on the crop), pasted at the crop offset.
"""

from __future__ import annotations

import os
import pathlib
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

if TYPE_CHECKING:
    from ._sequence import FrameRecord

VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".m4v")
MODEL_COLOUR = (60, 255, 60)  # RGB: green
SEGMENT_COLOUR = (255, 40, 220)  # RGB: magenta
_SUBPIXEL_BITS = 4  # OpenCV fixed-point drawing: 1/16 px


def _cv2():
    import cv2

    cv2.setNumThreads(1)  # OpenCV worker threads would compete with XLA's
    return cv2


def model_mask(p_cam: npt.ArrayLike, faces: npt.ArrayLike, K: npt.ArrayLike, shape: tuple[int, int],
               dist: npt.ArrayLike | None = None, near: float = 1e-3) -> np.ndarray:
    """The mesh's silhouette in one camera, (H, W) bool.

    Pixels whose centre lies in a projected triangle, give or take half a pixel (OpenCV's polygon fill
    includes the pixels its rounded edges touch).

    Args:
        p_cam: (V, 3) vertices in camera coordinates (mm).
        faces: (F, 3) vertex indices.
        K: (3, 3) intrinsics; dist: OpenCV (k1, k2, p1, p2, k3) or None.
        shape: (H, W) image size.
        near: triangles with a vertex closer than this (mm, in z) are skipped (they would not project).
    """
    cv2 = _cv2()
    p_cam = np.asarray(p_cam, np.float64)
    faces = np.asarray(faces, np.int64)
    H, W = shape
    mask = np.zeros((H, W), np.uint8)
    front = p_cam[:, 2] > near
    if not front.any():
        return mask.astype(bool)
    uv = np.full((len(p_cam), 2), np.nan)
    d = np.zeros(5) if dist is None else np.asarray(dist, np.float64)
    uv[front] = cv2.projectPoints(p_cam[front], np.zeros(3), np.zeros(3), np.asarray(K, np.float64), d)[0][:, 0]
    tri = uv[faces]  # (F, 3, 2)
    keep = np.all(front[faces], axis=1) & np.all(np.isfinite(tri), axis=(1, 2))
    # Triangles entirely beside the image add nothing; far-off coordinates would overflow the fixed point.
    lo, hi = tri.min(axis=1), tri.max(axis=1)
    keep &= (hi[:, 0] >= -1) & (lo[:, 0] <= W) & (hi[:, 1] >= -1) & (lo[:, 1] <= H)
    keep &= np.all(np.abs(tri) < 2**20, axis=(1, 2))
    # One call per triangle: cv2.fillPoly with many polygons fills by the even-odd rule, so overlapping
    # triangles would cancel; fillConvexPoly per triangle gives the union.
    pts = np.round(tri[keep] * (1 << _SUBPIXEL_BITS)).astype(np.int32)
    for p in pts:
        cv2.fillConvexPoly(mask, p, 1, lineType=cv2.LINE_8, shift=_SUBPIXEL_BITS)
    return mask.astype(bool)


def segmentation_mask(region_phi: npt.ArrayLike, offset: npt.ArrayLike, shape: tuple[int, int], scale=None) -> np.ndarray:
    """Φ > 0 of one camera's crop pasted at its offset into an (H, W) bool mask (clipped at the borders).

    Args:
        region_phi: (h, w) the segmentation on the crop (> 0 inside).
        offset: (y0, x0) of the crop in the frame.
        shape: (H, W) frame size.
        scale: full-frame pixels per crop pixel of a resampled crop (the working resolution), or None (1):
            each frame pixel takes its nearest crop pixel.
    """
    phi = np.asarray(region_phi)
    H, W = shape
    h, w = phi.shape
    if scale is not None and float(scale) != 1.0:
        s = float(scale)
        oy, ox = (float(v) for v in np.asarray(offset))
        i = np.floor((np.arange(H) + 0.5 - oy) / s).astype(int)
        j = np.floor((np.arange(W) + 0.5 - ox) / s).astype(int)
        inside = ((i >= 0) & (i < h))[:, None] & ((j >= 0) & (j < w))[None, :]
        return inside & (phi[np.clip(i, 0, h - 1)][:, np.clip(j, 0, w - 1)] > 0)
    y0, x0 = (round(float(v)) for v in np.asarray(offset))
    out = np.zeros((H, W), bool)
    ys, xs = slice(max(y0, 0), min(y0 + h, H)), slice(max(x0, 0), min(x0 + w, W))
    if ys.start < ys.stop and xs.start < xs.stop:
        out[ys, xs] = phi[ys.start - y0 : ys.stop - y0, xs.start - x0 : xs.stop - x0] > 0
    return out


def draw_contour(image: np.ndarray, mask: np.ndarray, colour: tuple[int, int, int], thickness: int = 1) -> np.ndarray:
    """Draw the outline of `mask` (H, W bool) on `image` (H, W, 3 uint8, modified in place and returned)."""
    cv2 = _cv2()
    contours, _ = cv2.findContours(np.asarray(mask, np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    if contours:
        cv2.drawContours(image, contours, -1, tuple(int(c) for c in colour), thickness, lineType=cv2.LINE_8)
    return image


def draw_text(image: np.ndarray, text: str) -> np.ndarray:
    """A line of white text on a dark band at the top left (in place; returned)."""
    cv2 = _cv2()
    scale = max(0.35, min(0.6, image.shape[0] / 600))
    (tw, th), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    cv2.rectangle(image, (0, 0), (min(tw + 6, image.shape[1] - 1), th + base + 4), (0, 0, 0), -1)
    cv2.putText(image, text, (3, th + 3), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1, cv2.LINE_AA)
    return image


def overlay_frame(
    images: npt.ArrayLike,
    p_cam: list,
    faces: npt.ArrayLike,
    K: npt.ArrayLike,
    dist: npt.ArrayLike | None = None,
    region_phi: npt.ArrayLike | None = None,
    offsets: npt.ArrayLike | None = None,
    text: str | None = None,
    thickness: int = 1,
    scales: npt.ArrayLike | None = None,
) -> np.ndarray:
    """One overlay frame: per camera the model contour (green) and the segmented contour (magenta),
    the views tiled side by side, a text line on top. Nothing else in the frames changes.

    Args:
        images: (C, H, W, 3) RGB frames in [0, 255] (or (C, H, W) grey).
        p_cam: C arrays (V, 3), the mesh vertices in each camera's coordinates at the estimated pose.
        faces: (F, 3) vertex indices.
        K: (C, 3, 3) intrinsics; dist: (C, 5) distortion or None.
        region_phi: (C, h, w) the segmentation Φ on the crops, or None (no segmented contour).
        offsets: (C, 2) (y0, x0) of the crops (needed with `region_phi`).
        text: drawn at the top left of the tiled image.
        thickness: line width in pixels.
        scales: (C,) full-frame pixels per crop pixel of resampled crops (the working resolution), or None.

    Returns:
        (H, C·W, 3) uint8 RGB.
    """
    images = np.asarray(images)
    if images.ndim == 3:
        images = np.repeat(images[..., None], 3, axis=-1)
    if images.ndim != 4 or images.shape[-1] != 3:
        raise ValueError(f"overlay_frame: images must be (C, H, W, 3) or (C, H, W), got {images.shape}")
    C, H, W = images.shape[:3]
    if len(p_cam) != C:
        raise ValueError(f"overlay_frame: p_cam has {len(p_cam)} vertex arrays for {C} camera(s)")
    K = np.broadcast_to(np.asarray(K, np.float64), (C, 3, 3))
    dist = None if dist is None else np.broadcast_to(np.asarray(dist, np.float64), (C, 5))
    if region_phi is not None and offsets is None:
        raise ValueError("overlay_frame: region_phi needs the crop offsets")
    tiles = []
    for c in range(C):
        tile = np.ascontiguousarray(np.clip(images[c], 0, 255).astype(np.uint8))
        sil = model_mask(p_cam[c], faces, K[c], (H, W), None if dist is None else dist[c])
        seg = None if region_phi is None else segmentation_mask(np.asarray(region_phi)[c], np.asarray(offsets)[c], (H, W),
                                                                None if scales is None else np.asarray(scales)[c])
        # Where the two contours coincide (good tracking) one would hide the other: with thick lines the
        # segmentation goes on top, a pixel thinner, so both stay visible; 1-px lines show the model's.
        if thickness >= 2:
            draw_contour(tile, sil, MODEL_COLOUR, thickness)
            if seg is not None:
                draw_contour(tile, seg, SEGMENT_COLOUR, thickness - 1)
        else:
            if seg is not None:
                draw_contour(tile, seg, SEGMENT_COLOUR, thickness)
            draw_contour(tile, sil, MODEL_COLOUR, thickness)
        tiles.append(tile)
    out = np.concatenate(tiles, axis=1)
    if text:
        draw_text(out, text)
    return out


class OverlayWriter:
    """Writes overlay frames as they come: an MP4 (cv2.VideoWriter, 'mp4v') or a folder of PNGs.

    The path decides: a video suffix (.mp4, .avi, .mov, .mkv, .m4v) makes a video, anything else a folder
    (000000.png, ...). The writer is opened at construction, so an unwritable path fails before any
    tracking work.

    Args:
        path: the video file or the folder.
        frame_shape: (H, W) of every frame to be written (the tiled size).
        fps: frames per second of the video.
        what: how error messages name the path (e.g. "--video").

    Raises:
        ValueError: naming the path when it cannot be written.
    """

    def __init__(self, path: str | os.PathLike, frame_shape: tuple[int, int], fps: float = 10.0, what: str = "video"):
        from ..io import prepare_output_file, prepare_output_folder

        cv2 = _cv2()
        self.path = pathlib.Path(path)
        self.shape = (int(frame_shape[0]), int(frame_shape[1]))
        self.count = 0
        self.video = None
        self.is_video = self.path.suffix.lower() in VIDEO_SUFFIXES
        if self.is_video:
            prepare_output_file(self.path, what)
            self.video = cv2.VideoWriter(str(self.path), cv2.VideoWriter_fourcc(*"mp4v"), float(fps),
                                         (self.shape[1], self.shape[0]))
            if not self.video.isOpened():
                raise ValueError(f"{what}: {self.path}: OpenCV cannot open a video writer (codec mp4v) for this file")
        else:
            prepare_output_folder(self.path, what)
            if not os.access(self.path, os.W_OK):
                raise ValueError(f"{what}: {self.path}: folder is not writable")
        self.what = what

    def write(self, frame: npt.ArrayLike) -> None:
        """Append one (H, W, 3) uint8 RGB frame."""
        frame = np.asarray(frame)
        if frame.shape != (*self.shape, 3) or frame.dtype != np.uint8:
            raise ValueError(f"{self.what}: frames must be {self.shape + (3,)} uint8, got {frame.shape} {frame.dtype}")
        bgr = np.ascontiguousarray(frame[..., ::-1])
        if self.is_video:
            if self.video is None:
                raise ValueError(f"{self.what}: {self.path} is closed")
            self.video.write(bgr)
        else:
            cv2 = _cv2()
            name = self.path / f"{self.count:06d}.png"
            if not cv2.imwrite(str(name), bgr):
                raise ValueError(f"{self.what}: cannot write {name}")
        self.count += 1

    def close(self) -> None:
        if self.video is not None:
            self.video.release()
            self.video = None

    def __enter__(self):
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class OverlayRecorder:
    """A `track_sequence(on_frame=...)` callback that draws each `FrameRecord` and hands it to a writer.

    Args:
        writer: an `OverlayWriter` (or anything with `write(frame)`).
        vertices: (V, 3) mesh vertices in model coordinates (mm); faces: (F, 3).
        K: (C, 3, 3) intrinsics of the tracked cameras; dist: (C, 5) or None.
        thickness: line width in pixels; None: 2 for a video (its codec's halved chroma resolution washes
            1-px colour lines out) and for frames from 400 px wide, else 1.
        pose_vertices: articulated models: Θ (J,) → (V, 3) the vertices posed by the joints in the root
            frame (e.g. forward kinematics of `ArticulatedModel`); None for a rigid mesh.
    """

    def __init__(self, writer: OverlayWriter, vertices: npt.ArrayLike, faces: npt.ArrayLike, K: npt.ArrayLike,
                 dist: npt.ArrayLike | None = None, thickness: int | None = None, pose_vertices=None):
        self.writer = writer
        self.thickness = thickness
        self.vertices = np.asarray(vertices, np.float64)
        self.faces = np.asarray(faces, np.int64)
        self.K = np.asarray(K, np.float64)
        self.dist = None if dist is None else np.asarray(dist, np.float64)
        self.pose_vertices = pose_vertices

    def __call__(self, record: FrameRecord) -> None:
        thickness = self.thickness
        if thickness is None:
            thickness = 2 if getattr(self.writer, "is_video", False) or record.images.shape[2] >= 400 else 1
        vertices = self.vertices
        if self.pose_vertices is not None and record.theta is not None:
            vertices = np.asarray(self.pose_vertices(record.theta), np.float64)
        p_cam = [vertices @ T[:3, :3].T + T[:3, 3] for T in np.asarray(record.T_cam_obj, np.float64)]
        text = f"frame {record.im_id}  {record.status}  conf {record.confidence:.2f}" + ("  RESET" if record.reset else "")
        self.writer.write(overlay_frame(record.images, p_cam, self.faces, self.K, self.dist, record.region_phi,
                                        record.offsets, text, thickness, record.scales))


# Per-object contour colours of a joint run (RGB): green first (the single-object colour), then cyan, yellow, ...
# (an orange second outline was hard to see on warm backgrounds).
OBJECT_COLOURS = (MODEL_COLOUR, (0, 220, 255), (255, 255, 0), (255, 0, 255), (255, 160, 0), (160, 80, 255))


class JointOverlayRecorder:
    """A `track_objects(on_frame=...)` callback: every object's model contour in its own colour
    (`OBJECT_COLOURS`, in the order of the objects), their statuses on top.

    Args:
        writer: an `OverlayWriter` (or anything with `write(frame)`).
        objects: per object (vertices (V, 3) model mm, faces (F, 3)).
        K: (C, 3, 3) intrinsics of the tracked cameras; dist: (C, 5) or None.
        names: per object the label of the status line (default "obj 1", "obj 2", ...).
        thickness: line width; None: 2 for a video or frames from 400 px wide, else 1.
    """

    def __init__(self, writer: OverlayWriter, objects: list, K: npt.ArrayLike, dist: npt.ArrayLike | None = None,
                 names: list[str] | None = None, thickness: int | None = None):
        self.writer = writer
        self.objects = [(np.asarray(v, np.float64), np.asarray(f, np.int64)) for v, f in objects]
        self.K = np.asarray(K, np.float64)
        self.dist = None if dist is None else np.asarray(dist, np.float64)
        self.names = [f"obj {i + 1}" for i in range(len(self.objects))] if names is None else list(names)
        self.thickness = thickness

    def __call__(self, records: list[FrameRecord]) -> None:
        if len(records) != len(self.objects):
            raise ValueError(f"JointOverlayRecorder: {len(records)} record(s) for {len(self.objects)} object(s)")
        images = np.asarray(records[0].images)
        if images.ndim == 3:
            images = np.repeat(images[..., None], 3, axis=-1)
        C, H, W = images.shape[:3]
        thickness = self.thickness
        if thickness is None:
            thickness = 2 if getattr(self.writer, "is_video", False) or W >= 400 else 1
        K = np.broadcast_to(self.K, (C, 3, 3))
        tiles = []
        for c in range(C):
            tile = np.ascontiguousarray(np.clip(images[c], 0, 255).astype(np.uint8))
            for i, ((vertices, faces), rec) in enumerate(zip(self.objects, records)):
                T = np.asarray(rec.T_cam_obj, np.float64)[c]
                mask = model_mask(vertices @ T[:3, :3].T + T[:3, 3], faces, K[c], (H, W),
                                  None if self.dist is None else self.dist[c])
                draw_contour(tile, mask, OBJECT_COLOURS[i % len(OBJECT_COLOURS)], thickness)
            tiles.append(tile)
        out = np.concatenate(tiles, axis=1)
        text = f"frame {records[0].im_id}  " + "  ".join(f"{n} {r.status} {r.confidence:.2f}"
                                                          for n, r in zip(self.names, records))
        draw_text(out, text)
        self.writer.write(out)
