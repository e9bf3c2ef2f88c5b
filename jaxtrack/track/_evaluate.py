"""Tracking accuracy against ground truth: pose errors, ADD / ADD-S, success rates, status quality.

Host-side numpy (evaluation runs after tracking, on a few hundred poses). Poses are (F, 4, 4)
model → camera transforms in millimetres.
"""

from __future__ import annotations

import numpy as np

from ..geometry import rotation_error_deg


def _check_poses(name: str, T) -> np.ndarray:
    T = np.asarray(T, np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise ValueError(f"{name} must have shape (F, 4, 4), got {T.shape}")
    return T


def pose_errors(T_est, T_gt) -> tuple[np.ndarray, np.ndarray]:
    """Rotation error (deg) and translation error (mm) per frame, (F,) each."""
    T_est, T_gt = _check_poses("T_est", T_est), _check_poses("T_gt", T_gt)
    if T_est.shape != T_gt.shape:
        raise ValueError(f"T_est {T_est.shape} and T_gt {T_gt.shape} must have the same number of frames")
    rot = np.asarray(rotation_error_deg(T_est[:, :3, :3], T_gt[:, :3, :3]), np.float64)
    trans = np.linalg.norm(T_est[:, :3, 3] - T_gt[:, :3, 3], axis=-1)
    return rot, trans


def _transform(T, points):
    return points @ T[:3, :3].T + T[:3, 3]


def add_error(T_est, T_gt, points) -> np.ndarray:
    """ADD (Hinterstoisser et al. 2012): mean distance of model points under both poses, (F,) mm."""
    T_est, T_gt = _check_poses("T_est", T_est), _check_poses("T_gt", T_gt)
    points = np.asarray(points, np.float64)
    return np.array([np.linalg.norm(_transform(a, points) - _transform(b, points), axis=-1).mean()
                     for a, b in zip(T_est, T_gt, strict=True)])


def adds_error(T_est, T_gt, points, chunk: int = 1024) -> np.ndarray:
    """ADD-S: mean distance from each ground-truth point to the closest estimated point, (F,) mm.

    The symmetric-object variant of ADD; brute force in chunks (exact, O(N²) per frame).
    """
    T_est, T_gt = _check_poses("T_est", T_est), _check_poses("T_gt", T_gt)
    points = np.asarray(points, np.float64)
    out = []
    for a, b in zip(T_est, T_gt, strict=True):
        est, gt = _transform(a, points), _transform(b, points)
        est_sq = np.sum(est * est, -1)
        best = np.empty(len(gt))
        for s in range(0, len(gt), chunk):
            g = gt[s : s + chunk]
            d2 = np.sum(g * g, -1)[:, None] + est_sq[None, :] - 2.0 * g @ est.T
            best[s : s + chunk] = np.sqrt(np.maximum(d2.min(axis=1), 0.0))
        out.append(best.mean())
    return np.array(out)


def model_diameter(points) -> float:
    """Largest distance between two model points (mm), exact by brute force in chunks."""
    points = np.asarray(points, np.float64)
    best = 0.0
    for s in range(0, len(points), 1024):
        d = np.linalg.norm(points[s : s + 1024, None, :] - points[None, :, :], axis=-1)
        best = max(best, float(d.max()))
    return best


def success_mask(rot_err_deg, trans_err_mm, max_deg: float = 5.0, max_mm: float = 50.0) -> np.ndarray:
    """The RBOT criterion: a frame succeeds when within `max_deg` and `max_mm` (5° / 5 cm)."""
    return (np.asarray(rot_err_deg) <= max_deg) & (np.asarray(trans_err_mm) <= max_mm)


def precision_recall(predicted, actual) -> tuple[float, float]:
    """Precision and recall of a boolean prediction (e.g. status lost/uncertain) of `actual` failures.

    NaN where undefined (nothing predicted, or nothing to find).
    """
    predicted, actual = np.asarray(predicted, bool), np.asarray(actual, bool)
    tp = np.sum(predicted & actual)
    precision = tp / predicted.sum() if predicted.any() else float("nan")
    recall = tp / actual.sum() if actual.any() else float("nan")
    return float(precision), float(recall)


def failure_episodes(failed) -> list[tuple[int, bool]]:
    """Runs of consecutive failed frames: (length = frames until the tracker is back within the bound, whether it
    came back before the sequence ended), in order; `failed` (F,) bool per frame."""
    out, run = [], 0
    for f in np.asarray(failed, bool):
        if f:
            run += 1
        elif run:
            out.append((run, True))
            run = 0
    if run:
        out.append((run, False))
    return out
