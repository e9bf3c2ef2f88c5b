"""Host side of the SIFT cue (Section III-D): OpenCV keypoints in the object region, ratio matching.

Keypoints of frame t are detected inside the visible (non-occluded) object region, those of frame t+1
inside that region dilated by the largest expected motion; both only on a crop around the region
(the flow cue's `roi_crop`), not the whole frame. Matches pass Lowe's nearest-neighbour distance
ratio test (0.6 in the paper) and matches that share their frame-(t+1) keypoint are deleted. The result is
a fixed-capacity padded `SiftMatches` per camera (leading C axis), which the jittable filters and
the vertex assignment take from there.

OpenCV runs single-threaded here: its idle worker threads were measured to double XLA's run time on
a 2-core machine when both run side by side.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import dataclasses
import os
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..._device import to_device
from ..flow import roi_crop


@contextlib.contextmanager
def opencv_threads(count: int = 1):
    """Run OpenCV with `count` threads inside the block, restoring the previous setting after."""
    import cv2  # lazily: `import jaxtrack` must not load OpenCV

    previous = cv2.getNumThreads()
    cv2.setNumThreads(count)
    try:
        yield
    finally:
        cv2.setNumThreads(previous)


@dataclasses.dataclass(frozen=True)
class SiftConfig:
    """Host-side settings of detection and matching.

    Attributes:
        ratio: nearest / second-nearest descriptor distance bound (paper: 0.6).
        capacity: matches kept per camera (padded); the best ratios win when there are more.
        search_px: dilation of the frame-t region that bounds the frame-(t+1) detection (largest motion).
        margin: context in pixels around the region's bounding box of the detection crop.
        roi: detect on the crop around the region (True) or on the full frame with a mask (False).
        max_side: detect on the crop shrunk (area averaging) so its longer side is at most this many pixels
            (0: at the frame's own resolution); keypoints are mapped back to full-frame pixels. A large
            object then costs what a small one does (a 352 px crop: 18 ms at full size, 11 ms at 256, 5 ms at 192;
            192 lost 64 → 36 % on the teabox-large-motion preset, 256 none).
        max_keypoints: keep at most this many keypoints per detection, those of the strongest DoG response
            over the detection crop (OpenCV's `nfeatures`: chosen before the region mask is applied, so the
            region keeps at most this many; with `roi=False` over the whole frame); 0 keeps all. Descriptors
            cost about 22 µs a keypoint on this 2-core machine and matching grows with the product of the two
            frames' counts; the default, the match capacity, binds on richly textured crops (588 keypoints
            in a 256 px crop of a real textured scene: 24 ms to detect and match; 15 ms bounded at 300, 12 at
            200), not on the bench box or the recorded sequences' objects
            (experiments/results/sift_max_keypoints.md).
        contrast_threshold, edge_threshold, sigma, n_octave_layers: OpenCV SIFT settings.
    """

    ratio: float = 0.6
    capacity: int = 256
    search_px: int = 40
    margin: int = 16
    roi: bool = True
    max_side: int = 256
    max_keypoints: int = 256
    contrast_threshold: float = 0.04
    edge_threshold: float = 10.0
    sigma: float = 1.6
    n_octave_layers: int = 3

    def __post_init__(self):
        if not 0.0 < self.ratio <= 1.0:
            raise ValueError(f"SiftConfig.ratio must lie in (0, 1], got {self.ratio}")
        if self.capacity < 1:
            raise ValueError(f"SiftConfig.capacity must be ≥ 1, got {self.capacity}")
        if self.search_px < 0 or self.margin < 0:
            raise ValueError("SiftConfig.search_px and margin must be ≥ 0")
        if self.max_side < 0 or 0 < self.max_side < 16:
            raise ValueError(f"SiftConfig.max_side must be 0 (native) or ≥ 16 pixels, got {self.max_side}")
        if self.max_keypoints < 0:
            raise ValueError(f"SiftConfig.max_keypoints must be 0 (all) or ≥ 1, got {self.max_keypoints}")

    def detector(self):
        import cv2  # lazily: `import jaxtrack` must not load OpenCV

        return cv2.SIFT_create(
            nfeatures=self.max_keypoints,
            nOctaveLayers=self.n_octave_layers,
            contrastThreshold=self.contrast_threshold,
            edgeThreshold=self.edge_threshold,
            sigma=self.sigma,
        )


class SiftMatches(eqx.Module):
    """Padded keypoint matches t → t+1 of C cameras (N = capacity per camera).

    Attributes:
        p_t: (C, N, 2) keypoint in frame t (pixels).
        p_t1: (C, N, 2) matched keypoint in frame t+1.
        valid: (C, N) bool real match (False for padding and for matches a filter removed).
    """

    p_t: jax.Array
    p_t1: jax.Array
    valid: jax.Array

    @property
    def capacity(self) -> int:
        return self.valid.shape[-1]

    def count(self):
        """(C,) number of valid matches per camera."""
        return jnp.sum(self.valid, axis=-1)


def _gray_u8(image) -> np.ndarray:
    import cv2  # lazily: `import jaxtrack` must not load OpenCV

    img = np.asarray(image)
    if img.ndim == 3:
        if img.dtype != np.uint8:
            img = img.astype(np.float32)
        img = cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2GRAY)
    if img.ndim != 2:
        raise ValueError(f"images must be (H, W) grey or (H, W, 3) RGB per camera, got shape {np.shape(image)}")
    if img.dtype == np.uint8:
        return img
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def detect_sift(image, mask, config: SiftConfig = SiftConfig(), detector=None):
    """SIFT keypoints (n, 2) float32 (full-frame pixels) and descriptors (n, 128) float32 inside `mask` of one image.

    With `config.roi` only a crop around the mask (a `roi_crop` size class) is searched, shrunk to
    `config.max_side` when larger. An empty mask, or a region without texture, gives n = 0 (no error).
    """
    import cv2  # lazily: `import jaxtrack` must not load OpenCV

    image = np.asarray(image)
    mask = np.asarray(mask, bool)
    if image.ndim not in (2, 3):
        raise ValueError(f"images must be (H, W) grey or (H, W, 3) RGB per camera, got shape {image.shape}")
    if mask.shape != image.shape[:2]:
        raise ValueError(f"mask must have the image's shape {image.shape[:2]}, got {mask.shape}")
    empty = np.zeros((0, 2), np.float32), np.zeros((0, 128), np.float32)
    if not mask.any():
        return empty
    detector = config.detector() if detector is None else detector
    y0, x0, h, w = roi_crop(mask, config.margin) if config.roi else (0, 0) + mask.shape
    crop = _gray_u8(image[y0 : y0 + h, x0 : x0 + w])  # grey of the crop only, not of the frame
    crop_mask = mask[y0 : y0 + h, x0 : x0 + w].astype(np.uint8) * 255
    shrink = max(h, w) / config.max_side if config.max_side else 1.0
    with opencv_threads(1):
        if shrink > 1.0:
            size = (max(1, round(w / shrink)), max(1, round(h / shrink)))
            crop = cv2.resize(crop, size, interpolation=cv2.INTER_AREA)
            crop_mask = cv2.resize(crop_mask, size, interpolation=cv2.INTER_NEAREST)
        keypoints, descriptors = detector.detectAndCompute(crop, crop_mask)
    if descriptors is None or not keypoints:
        return empty
    xy = np.array([kp.pt for kp in keypoints], np.float32)
    if shrink > 1.0:  # pixel centres: full = (small + ½)·(crop side / small side) − ½
        sx, sy = w / crop.shape[1], h / crop.shape[0]
        xy = (xy + 0.5) * np.array([sx, sy], np.float32) - 0.5
    return xy + np.array([x0, y0], np.float32), descriptors.astype(np.float32)


def match_descriptors(desc_t, desc_t1, ratio: float = 0.6):
    """Ratio-test matches t → t+1 with conflicts (several t keypoints on one t+1 keypoint) deleted.

    Returns:
        (index_t (m,), index_t1 (m,), ratio (m,)) sorted by increasing ratio (best first).
    """
    import cv2  # lazily: `import jaxtrack` must not load OpenCV

    none = np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    if len(desc_t) == 0 or len(desc_t1) < 2:  # the ratio test needs a second neighbour
        return none
    with opencv_threads(1):
        knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(np.asarray(desc_t, np.float32), np.asarray(desc_t1, np.float32), k=2)
    pairs = [(m.queryIdx, m.trainIdx, m.distance / max(n.distance, 1e-12)) for m, n in (p for p in knn if len(p) == 2)]
    pairs = [p for p in pairs if p[2] < ratio]
    if not pairs:
        return none
    ia, ib, r = (np.array(x) for x in zip(*pairs))
    targets, counts = np.unique(ib, return_counts=True)
    keep = np.isin(ib, targets[counts == 1])
    order = np.argsort(r[keep], kind="stable")
    return ia[keep][order], ib[keep][order], r[keep][order]


def _dilate(mask, radius: int):
    """`mask` grown by `radius` pixels (Euclidean), computed on the box around the mask only (a distance
    transform there: 1 ms instead of the 13 ms of an 81 px elliptic dilation of a 640x480 frame)."""
    import cv2  # lazily: `import jaxtrack` must not load OpenCV

    mask = np.asarray(mask, bool)
    if radius <= 0 or not mask.any():
        return mask
    rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    H, W = mask.shape
    y0, y1 = max(rows[0] - radius, 0), min(rows[-1] + radius + 1, H)
    x0, x1 = max(cols[0] - radius, 0), min(cols[-1] + radius + 1, W)
    outside = (~mask[y0:y1, x0:x1]).astype(np.uint8)
    with opencv_threads(1):
        dist = cv2.distanceTransform(outside, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)  # to the nearest mask pixel
    out = np.zeros_like(mask)
    out[y0:y1, x0:x1] = dist <= radius
    return out


def _reuse_keypoints(cache: dict | None, c: int, image, region):
    """The keypoints of `image` detected by the previous call (as its frame t+1), kept where `region` is set;
    None when the cache holds another image."""
    entry = None if cache is None else cache.get(c)
    if entry is None or entry[0].shape != np.shape(image) or not np.array_equal(entry[0], image):
        return None
    xy, desc = entry[1], entry[2]
    if len(xy) == 0:
        return xy, desc
    h, w = region.shape
    xi = np.clip(np.floor(xy[:, 0] + 0.5).astype(int), 0, w - 1)
    yi = np.clip(np.floor(xy[:, 1] + 0.5).astype(int), 0, h - 1)
    keep = region[yi, xi]
    return xy[keep], desc[keep]


def sift_matches(images_t, images_t1, region_t, config: SiftConfig = SiftConfig(), region_t1=None, timings=None, dtype=jnp.float32,
                 cache: dict | None = None):
    """Detect and match SIFT keypoints of C cameras between frames t and t+1 (host side).

    Args:
        images_t, images_t1: (C, H, W) grey or (C, H, W, 3) RGB frames (0-255).
        region_t: (C, H, W) bool visible, non-occluded object pixels at t (the occlusion map's
            `visible`): where keypoints of frame t may lie.
        region_t1: (C, H, W) bool search region at t+1 (default: `region_t` dilated by `search_px`).
        timings: optional dict; "detect_s" and "match_s" are added to it (wall time; the cameras run in parallel
            threads, one per core, each OpenCV call single-threaded).
        cache: optional dict carried from call to call (a tracker's): frame t+1's keypoints are kept in it,
            and when the next call's frame t is that image, its keypoints are reused (those inside
            `region_t`) instead of detected again: one detection per frame instead of two.

    Returns:
        `SiftMatches` of capacity `config.capacity` per camera (best ratios first).
    """
    images_t, images_t1, region_t = np.asarray(images_t), np.asarray(images_t1), np.asarray(region_t, bool)
    if images_t.shape != images_t1.shape or images_t.ndim not in (3, 4):
        raise ValueError(f"images_t and images_t1 must both be (C, H, W[, 3]), got {images_t.shape} and {images_t1.shape}")
    if region_t.shape != images_t.shape[:3]:
        raise ValueError(f"region_t must have shape {images_t.shape[:3]}, got {region_t.shape}")
    if region_t1 is not None and np.shape(region_t1) != region_t.shape:
        raise ValueError(f"region_t1 must have shape {region_t.shape}, got {np.shape(region_t1)}")
    num_cameras, cap = images_t.shape[0], config.capacity
    p_t = np.zeros((num_cameras, cap, 2), np.float32)
    p_t1 = np.zeros((num_cameras, cap, 2), np.float32)
    valid = np.zeros((num_cameras, cap), bool)

    def one_camera(c):
        detector = config.detector()  # one per thread: OpenCV's detectors are not safe to share between threads
        search = _dilate(region_t[c], config.search_px) if region_t1 is None else np.asarray(region_t1[c], bool)
        start = time.perf_counter()
        reused = _reuse_keypoints(cache, c, images_t[c], region_t[c])
        xy_a, desc_a = reused if reused is not None else detect_sift(images_t[c], region_t[c], config, detector)
        xy_b, desc_b = detect_sift(images_t1[c], search, config, detector)
        mid = time.perf_counter()
        ia, ib, _ = match_descriptors(desc_a, desc_b, config.ratio)
        return xy_a, xy_b, desc_b, ia, ib, mid - start, time.perf_counter() - mid

    # Cameras in parallel threads (OpenCV releases the GIL; each runs single-threaded): the device is idle
    # while the host detects, so a rig of C cameras costs about C / cores detections instead of C.
    workers = min(num_cameras, os.cpu_count() or 1)
    wall_start = time.perf_counter()
    with opencv_threads(1):
        if workers > 1:
            with concurrent.futures.ThreadPoolExecutor(workers) as pool:
                per_camera = list(pool.map(one_camera, range(num_cameras)))
        else:
            per_camera = [one_camera(c) for c in range(num_cameras)]
    wall_s = time.perf_counter() - wall_start
    detect_s = match_s = 0.0
    for c, (xy_a, xy_b, desc_b, ia, ib, detect_c, match_c) in enumerate(per_camera):
        if cache is not None:
            cache[c] = (np.array(images_t1[c], copy=True), xy_b, desc_b)
        detect_s, match_s = detect_s + detect_c, match_s + match_c
        n = min(len(ia), cap)
        p_t[c, :n], p_t1[c, :n], valid[c, :n] = xy_a[ia[:n]], xy_b[ib[:n]], True
    if timings is not None:  # wall time, split between detection and matching as their summed times are
        busy = detect_s + match_s
        share = detect_s / busy if busy > 0 else 1.0
        timings["detect_s"] = timings.get("detect_s", 0.0) + wall_s * share
        timings["match_s"] = timings.get("match_s", 0.0) + wall_s * (1.0 - share)
    return SiftMatches(to_device(p_t, dtype), to_device(p_t1, dtype), to_device(valid))  # no copy programs
