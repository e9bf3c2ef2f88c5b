"""Tracking a BOP-layout sequence from its first ground-truth pose, and writing the results.

`track_sequence` reads the frames of one or more camera views, starts the `Tracker` at the first frame's
ground-truth pose (or a given one), tracks every later frame, and returns a `TrackingRun` with per-frame
poses, status, confidence, per-cue correspondence counts and host timings. With `reset_on_failure`
it runs the RBOT protocol: a frame beyond 5 cm / 5° of the ground truth counts as a failure and tracking
restarts from the true pose of that frame. `write_tracking_results` writes the BOP results CSV and the
per-frame JSON lines beside it.
"""

from __future__ import annotations

import dataclasses
import json
import os
import pathlib
import time

import numpy as np

from .._status import Status
from ..geometry import make_camera, rotation_error_deg, stack_cameras
from ..solve import Cue
from ._step import TrackerConfig, TrackerParams
from ._tracker import Tracker

CUE_NAMES = {int(Cue.REGION): "region", int(Cue.FLOW): "flow", int(Cue.SIFT): "sift"}


@dataclasses.dataclass
class TrackingRun:
    """Per-frame output of `track_sequence` (F frames, C cameras).

    Attributes:
        frame_ids: (F,) BOP image ids.
        obj_id: the tracked object's id.
        T_world_root: (F, 4, 4) estimated root pose (model → world, mm); theta: (F, J) joint angles.
        T_cam_world: (C, 4, 4) extrinsics of the cameras used; camera_ids: their view indices.
        status: (F,) `Status` names; confidence: (F,) in [0, 1].
        counts: (F, C, 3) correspondences with weight per camera and cue (region, flow, sift).
        timings: per frame, host seconds per stage.
        reset: (F,) bool, tracking restarted from the ground truth at this frame (RBOT protocol).
    """

    frame_ids: list
    obj_id: int
    T_world_root: np.ndarray
    theta: np.ndarray
    T_cam_world: np.ndarray
    camera_ids: list
    status: list
    confidence: np.ndarray
    counts: np.ndarray
    timings: list
    reset: np.ndarray

    def T_cam_obj(self, camera: int = 0) -> np.ndarray:
        """(F, 4, 4) estimated object pose in camera `camera` (position in `camera_ids`)."""
        return np.einsum("ij,fjk->fik", self.T_cam_world[camera], self.T_world_root)


def _failed(T_est, T_gt, max_deg: float = 5.0, max_mm: float = 50.0) -> bool:
    if not np.all(np.isfinite(T_gt)):
        return False
    rot = float(rotation_error_deg(T_est[:3, :3], T_gt[:3, :3]))
    return rot > max_deg or np.linalg.norm(T_est[:3, 3] - T_gt[:3, 3]) > max_mm


def track_sequence(
    sequence,
    *,
    cues: tuple[str, ...] = ("region", "flow", "sift"),
    cameras: list[int] | None = None,
    obj_id: int | None = None,
    config: TrackerConfig | None = None,
    params: TrackerParams | None = None,
    init_pose: np.ndarray | None = None,
    reset_on_failure: bool = False,
    max_frames: int | None = None,
    progress: bool = True,
) -> TrackingRun:
    """Track one rigid object through a BOP-layout sequence (`jaxtrack.io.read_sequence`).

    Args:
        sequence: a `jaxtrack.io.Sequence` (or a path to one).
        cues: the cue subset (ignored when `config` is given).
        cameras: view indices to use (default: all).
        obj_id: the object (default: the only, or the smallest, id with a mesh).
        init_pose: (4, 4) model → camera-0 pose of the first frame (default: its ground truth).
        reset_on_failure: the RBOT protocol (needs ground truth for every frame).
        max_frames: track only the first frames.
        progress: show a progress bar with the frame rate.

    Raises:
        ValueError: a camera index out of range, an unknown object, no initial pose.
    """
    from ..io import Sequence, load_mesh, read_sequence

    seq = sequence if isinstance(sequence, Sequence) else read_sequence(sequence)
    views = list(range(len(seq.views))) if cameras is None else [int(c) for c in cameras]
    if not views or any(c < 0 or c >= len(seq.views) for c in views) or len(set(views)) != len(views):
        raise ValueError(f"cameras must be distinct view indices in [0, {len(seq.views)}), got {cameras}")
    ids = sorted(seq.model_paths)
    if obj_id is None:
        obj_id = ids[0] if ids else None
    if obj_id not in seq.model_paths:
        raise ValueError(f"obj_id {obj_id} has no mesh in {seq.root}/models (have {ids})")
    view0 = seq.views[views[0]]
    rig = stack_cameras([
        make_camera(seq.views[c].K, seq.views[c].width, seq.views[c].height, seq.views[c].T_cam_world[:3, :3],
                    seq.views[c].T_cam_world[:3, 3])
        for c in views
    ])
    gt = view0.T_cam_obj.get(obj_id)
    T_cam0_world = np.asarray(view0.T_cam_world, np.float64)
    if init_pose is None:
        if gt is None or not np.all(np.isfinite(gt[0])):
            raise ValueError(f"{view0.folder}/scene_gt.json has no pose of obj_id {obj_id} in the first frame; "
                             "pass init_pose")
        init_pose = gt[0]
    init_pose = np.asarray(init_pose, np.float64)
    if init_pose.shape != (4, 4):
        raise ValueError(f"init_pose must be (4, 4), got {init_pose.shape}")
    if reset_on_failure and gt is None:
        raise ValueError("reset_on_failure needs ground-truth poses in scene_gt.json")
    mesh = load_mesh(seq.model_paths[obj_id])
    config = TrackerConfig(cues=tuple(cues)) if config is None else config
    tracker = Tracker(mesh, rig, config=config, params=params)
    n = seq.num_frames if max_frames is None else min(seq.num_frames, int(max_frames))
    T_world_gt = None if gt is None else np.einsum("ij,fjk->fik", np.linalg.inv(T_cam0_world), gt)

    def frames(k):
        return np.stack([seq.views[c].read_frame(k) for c in views])

    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=n, desc="tracking", unit="frame")
    start = time.perf_counter()
    state = tracker.start(frames(0), np.linalg.inv(T_cam0_world) @ init_pose)
    poses, thetas = [np.asarray(state.T_world_root, np.float64)], [np.asarray(state.theta, np.float64)]
    status, conf = [Status.OK.name], [1.0]
    counts = [np.zeros((len(views), 3), np.int64)]
    timings = [{"total_s": time.perf_counter() - start}]
    reset = [False]
    if bar is not None:
        bar.update(1)
    for k in range(1, n):
        t0 = time.perf_counter()
        images = frames(k)
        read_s = time.perf_counter() - t0
        state, result, info = tracker.step(state, images)
        T = np.asarray(result.T_world_root, np.float64)
        did_reset = False
        if reset_on_failure and T_world_gt is not None and _failed(T_cam0_world @ T, gt[k]):
            state = tracker.start(images, T_world_gt[k])
            did_reset = True
        poses.append(T)
        thetas.append(np.asarray(result.theta, np.float64))
        status.append(Status(int(result.status)).name)
        conf.append(float(result.confidence))
        counts.append(np.asarray(result.counts))
        info["timings"]["read_s"] = read_s
        info["timings"]["total_s"] = time.perf_counter() - t0
        timings.append(info["timings"])
        reset.append(did_reset)
        if bar is not None:
            bar.update(1)
            bar.set_postfix(status=status[-1], conf=f"{conf[-1]:.2f}")
    if bar is not None:
        bar.close()
    return TrackingRun(
        frame_ids=list(view0.frame_ids[:n]), obj_id=int(obj_id), T_world_root=np.stack(poses), theta=np.stack(thetas),
        T_cam_world=np.stack([np.asarray(seq.views[c].T_cam_world, np.float64) for c in views]), camera_ids=views,
        status=status, confidence=np.asarray(conf), counts=np.stack(counts), timings=timings, reset=np.asarray(reset),
    )


def write_tracking_results(run: TrackingRun, path: str | os.PathLike) -> tuple[pathlib.Path, pathlib.Path]:
    """The BOP results CSV (one row per frame and camera view: scene_id = view index) and, beside it,
    NAME.frames.jsonl with the status, confidence, counts per cue and camera, timings and reset flag.

    Returns:
        (csv path, jsonl path).
    """
    from ..io import write_bop_results

    path = pathlib.Path(path)
    if path.suffix.lower() != ".csv":
        raise ValueError(f"results path must end in .csv, got {path}")
    rows = []
    for ci, c in enumerate(run.camera_ids):
        T_co = run.T_cam_obj(ci)
        for k, im_id in enumerate(run.frame_ids):
            rows.append((c, im_id, run.obj_id, run.confidence[k], T_co[k], run.timings[k].get("total_s", 0.0)))
    csv = write_bop_results(path, rows)
    jsonl = path.with_name(path.stem + ".frames.jsonl")
    with jsonl.open("w") as f:
        for k, im_id in enumerate(run.frame_ids):
            counts = {
                str(c): {CUE_NAMES[cue]: int(run.counts[k, ci, j]) for j, cue in enumerate(sorted(CUE_NAMES))}
                for ci, c in enumerate(run.camera_ids)
            }
            f.write(json.dumps({
                "im_id": int(im_id), "status": run.status[k], "confidence": float(run.confidence[k]), "counts": counts,
                "timings": {key: round(float(v), 6) for key, v in run.timings[k].items()}, "reset": bool(run.reset[k]),
            }) + "\n")
    return csv, jsonl
