"""Middlebury optical-flow files (.flo), the standard colour-wheel visualisation, and flow metrics.

.flo: float32 magic 202021.25, int32 width, int32 height, then width·height·(u, v) float32, row-major.
Unknown flow is marked by |u| or |v| > 1e9.
"""

from __future__ import annotations

import os
import pathlib

import numpy as np
import numpy.typing as npt

from ._images import prepare_output_file

FLO_MAGIC = 202021.25
UNKNOWN_FLOW = 1e9


def read_flo(path: str | os.PathLike) -> np.ndarray:
    """(H, W, 2) float32 flow (u, v) from a .flo file; unknown entries keep their huge values.

    Raises:
        FileNotFoundError: naming the missing file.
        ValueError: naming the file whose magic number or size (e.g. truncated) is wrong.
    """
    path = pathlib.Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: flow file not found")
    data = path.read_bytes()
    if len(data) < 12:
        raise ValueError(f"{path}: too short for a .flo header")
    magic = np.frombuffer(data[:4], "<f4")[0]
    if magic != np.float32(FLO_MAGIC):
        raise ValueError(f"{path}: not a .flo file (magic {magic}, expected {FLO_MAGIC})")
    width, height = (int(x) for x in np.frombuffer(data[4:12], "<i4"))
    expected = 12 + 8 * width * height
    if width <= 0 or height <= 0 or len(data) != expected:
        raise ValueError(f"{path}: header says {width}x{height} ({expected} bytes), file has {len(data)} bytes")
    return np.frombuffer(data[12:], "<f4").reshape(height, width, 2).copy()


def write_flo(path: str | os.PathLike, flow: npt.ArrayLike) -> pathlib.Path:
    """Write (H, W, 2) flow as a .flo file (missing parent folders are created).

    Raises:
        ValueError: naming the flow's bad shape or the unusable path.
    """
    flow = np.asarray(flow, np.float32)
    if flow.ndim != 3 or flow.shape[2] != 2 or flow.size == 0:
        raise ValueError(f"write_flo: flow must have shape (H, W, 2) with H, W ≥ 1, got {flow.shape}")
    path = prepare_output_file(path, "write_flo: path")
    h, w = flow.shape[:2]
    with open(path, "wb") as f:
        f.write(np.array([FLO_MAGIC], "<f4").tobytes())
        f.write(np.array([w, h], "<i4").tobytes())
        f.write(flow.astype("<f4").tobytes())
    return path


def known_flow_mask(flow: npt.ArrayLike) -> np.ndarray:
    """(H, W) True where the ground truth is known (|u|, |v| ≤ 1e9 and finite)."""
    flow = np.asarray(flow)
    return np.all(np.isfinite(flow) & (np.abs(flow) <= UNKNOWN_FLOW), axis=-1)


def flow_errors(flow: npt.ArrayLike, gt: npt.ArrayLike, mask: npt.ArrayLike | None = None) -> dict:
    """Mean endpoint error (px) and mean angular error (deg, Barron et al. with the third component 1)."""
    flow, gt = np.asarray(flow, np.float64), np.asarray(gt, np.float64)
    if gt.ndim != 3 or gt.shape[2] != 2:
        raise ValueError(f"flow_errors: gt must have shape (H, W, 2), got {gt.shape}")
    if flow.shape != gt.shape:
        raise ValueError(f"flow_errors: flow shape {flow.shape} does not match ground truth {gt.shape}")
    if mask is not None and np.shape(mask) != gt.shape[:2]:
        raise ValueError(f"flow_errors: mask must have shape {gt.shape[:2]}, got {np.shape(mask)}")
    valid = known_flow_mask(gt) if mask is None else (np.asarray(mask, bool) & known_flow_mask(gt))
    if not valid.any():
        raise ValueError("flow_errors: no pixel has known ground truth (inside the mask); the errors are undefined")
    f, g = flow[valid], gt[valid]
    epe = np.linalg.norm(f - g, axis=-1)
    cos = (1 + np.sum(f * g, -1)) / np.sqrt((1 + np.sum(f * f, -1)) * (1 + np.sum(g * g, -1)))
    aae = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return {"epe": float(epe.mean()), "aae": float(aae.mean()), "pixels": int(valid.sum())}


def _colour_wheel() -> np.ndarray:
    """The Middlebury colour wheel (Baker et al. 2011): 55 hues, RGB 0-255."""
    ry, yg, gc, cb, bm, mr = 15, 6, 4, 11, 13, 6
    cols = []
    cols += [[255, 255 * i / ry, 0] for i in range(ry)]
    cols += [[255 - 255 * i / yg, 255, 0] for i in range(yg)]
    cols += [[0, 255, 255 * i / gc] for i in range(gc)]
    cols += [[0, 255 - 255 * i / cb, 255] for i in range(cb)]
    cols += [[255 * i / bm, 0, 255] for i in range(bm)]
    cols += [[255, 0, 255 - 255 * i / mr] for i in range(mr)]
    return np.asarray(cols, np.float64)


def flow_to_colour(flow: npt.ArrayLike, max_flow: float | None = None) -> np.ndarray:
    """(H, W, 3) uint8 RGB colour-wheel image of a flow field (hue = direction, saturation = magnitude).

    Unknown flow is drawn black. `max_flow` sets the saturation scale (default: the largest magnitude).
    """
    flow = np.asarray(flow, np.float64)
    if flow.ndim != 3 or flow.shape[2] != 2:
        raise ValueError(f"flow_to_colour: flow must have shape (H, W, 2), got {flow.shape}")
    if max_flow is not None and not (np.isfinite(max_flow) and max_flow > 0):
        raise ValueError(f"flow_to_colour: max_flow must be a finite number > 0, got {max_flow!r}")
    known = known_flow_mask(flow)
    u = np.where(known, flow[..., 0], 0.0)
    v = np.where(known, flow[..., 1], 0.0)
    rad = np.hypot(u, v)
    scale = max_flow if max_flow is not None else max(rad.max(), 1e-9)
    u, v, rad = u / scale, v / scale, rad / scale
    wheel = _colour_wheel()
    n = len(wheel)
    angle = np.arctan2(-v, -u) / np.pi
    fk = (angle + 1) / 2 * (n - 1)
    k0 = np.floor(fk).astype(int)
    k1 = (k0 + 1) % n
    frac = (fk - k0)[..., None]
    col = ((1 - frac) * wheel[k0] + frac * wheel[k1]) / 255.0
    small = (rad <= 1)[..., None]
    col = np.where(small, 1 - rad[..., None] * (1 - col), col * 0.75)
    col = np.where(known[..., None], col, 0.0)
    return np.clip(np.round(255 * col), 0, 255).astype(np.uint8)
