"""Tracking a BOP-layout sequence from its first ground-truth pose, and writing the results.

`track_sequence` reads the frames of one or more camera views, starts the `Tracker` at the first frame's
ground-truth pose (or a given one), tracks every later frame, and returns a `TrackingRun` with per-frame
poses, status, confidence, per-cue correspondence counts and host timings. With `reset_on_failure`
it runs the RBOT protocol: a frame beyond 5 cm / 5° of the ground truth counts as a failure and tracking
restarts from the true pose of that frame. `write_tracking_results` writes the BOP results CSV and the
per-frame JSON lines beside it.

An articulated object (`models/obj_XXXXXX.urdf`, read by `jaxtrack.io.read_urdf`) is tracked the same
way with its joint angles: the first frame's scene_gt.json "joints" give Θ0, the CSV holds the root
link's pose, and NAME.joints.csv beside it one row per frame with a column per movable joint (URDF
names and units: radians, metres).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import pathlib
import threading
import time
from collections.abc import Callable

import numpy as np

from .._status import Status
from ..geometry import make_camera, rotation_error_deg, stack_cameras
from ..solve import Cue
from ._recovery import RecoveryConfig
from ._results import TrackingResultsWriter, check_complete, joints_header, joints_row, write_run_frame
from ._step import TrackerConfig, TrackerParams
from ._tracker import Tracker

CUE_NAMES = {int(Cue.REGION): "region", int(Cue.FLOW): "flow", int(Cue.SIFT): "sift"}  # the built-in row tags

# The pose prior of a joint run (`track_objects`): M3T's Tikhonov stiffnesses (rotation 1000 / rad², translation
# 30000 / m², toward each round's start; see `default_params`). An object half hidden by another keeps too few lines
# to pin every direction, and without a prior it drifts along the free ones. Measured on five crossing scenes
# (experiments/results/two_objects.md; frames within 5 cm / 5°, object in front / behind): lines only, none → M3T's
# 96 / 48 → 100 / 95 % (each alone with M3T's: 100 / 29 %); with flow and SIFT 100 / 46 % either way (the flow
# loses the object behind: region+SIFT tracks seed 1's, region+flow does not). One object alone keeps
# `DEFAULT_POSE_PRIOR` (none).
JOINT_POSE_PRIOR = (0.0, 0.0, 1000.0, 0.03, 1.0)


@dataclasses.dataclass
class TrackingRun:
    """Per-frame output of `track_sequence` (F frames, C cameras).

    Attributes:
        frame_ids: (F,) BOP image ids.
        obj_id: the tracked object's id.
        T_world_root: (F, 4, 4) estimated root pose (model → world, mm); theta: (F, J) joint angles.
        T_cam_world: (C, 4, 4) extrinsics of the cameras used; camera_ids: their view indices.
        status: (F,) `Status` names; confidence: (F,) in [0, 1].
        counts: (F, C, M) correspondences with weight per camera and configured cue (`cue_names`).
        timings: per frame, host seconds per stage.
        reset: (F,) bool, tracking restarted from the ground truth at this frame (RBOT protocol).
        crops: per frame the (h, w) crop size class of the step (a new class is a new compilation),
            None for the first frame and out-of-view frames.
        joint_names: (J,) the URDF's movable joints in the order of theta's columns (empty when rigid);
            joint_scale: (J,) model units (radians, mm) per URDF unit (radians, metres).
        lost_joints: per frame, the joints whose moved part lost its silhouette (the segmentation covers
            less than `lost_iou` of the part's visible model silhouette); empty when rigid or region is off.
        cue_names: (M,) the configured cues, the last axis of `counts` (`TrackerConfig.cue_names`).
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
    crops: list | None = None
    joint_names: tuple = ()
    joint_scale: np.ndarray | None = None
    lost_joints: list | None = None
    cue_names: tuple = ("region", "flow", "sift")

    def joints_urdf(self) -> np.ndarray:
        """(F, J) joint values in URDF units (radians, metres)."""
        scale = np.ones(len(self.joint_names)) if self.joint_scale is None else np.asarray(self.joint_scale)
        return self.theta / scale

    def T_cam_obj(self, camera: int = 0) -> np.ndarray:
        """(F, 4, 4) estimated object pose in camera `camera` (position in `camera_ids`)."""
        return np.einsum("ij,fjk->fik", self.T_cam_world[camera], self.T_world_root)


@dataclasses.dataclass
class FrameRecord:
    """What `track_sequence` hands its `on_frame` callback after each frame (C cameras), e.g. for an overlay.

    Attributes:
        index: position of the frame in the sequence; im_id: its BOP image id.
        images: (C, H, W, 3) frames in [0, 255] (uint8 from 8-bit files, else float32).
        T_world_root: (4, 4) the reported pose (model → world, mm); T_cam_obj: (C, 4, 4) in each camera.
        status: `Status` name; confidence: in [0, 1].
        region_phi: (C, h, w) the segmentation Φ on the crops (> 0 inside), None for the first frame or
            when the object was out of view; offsets: (C, 2) (y0, x0) of the crops, or None; scales: (C,)
            full-frame pixels per crop pixel at the working resolution, or None (native crops).
        reset: tracking restarted from the ground truth after this frame (RBOT protocol).
        theta: (J,) the reported joint values (model units); empty for a rigid object.
    """

    index: int
    im_id: int
    images: np.ndarray
    T_world_root: np.ndarray
    T_cam_obj: np.ndarray
    status: str
    confidence: float
    region_phi: np.ndarray | None
    offsets: np.ndarray | None
    reset: bool
    theta: np.ndarray | None = None
    scales: np.ndarray | None = None


def _failed(T_est, T_gt, max_deg: float = 5.0, max_mm: float = 50.0) -> bool:
    if not np.all(np.isfinite(T_gt)):
        return False
    rot = float(rotation_error_deg(T_est[:3, :3], T_gt[:3, :3]))
    return rot > max_deg or np.linalg.norm(T_est[:3, 3] - T_gt[:3, 3]) > max_mm


def _views_and_rig(seq, cameras):
    """The view indices to track (default all, checked) and their stacked `Camera` rig."""
    views = list(range(len(seq.views))) if cameras is None else [int(c) for c in cameras]
    if not views or any(c < 0 or c >= len(seq.views) for c in views) or len(set(views)) != len(views):
        raise ValueError(f"cameras must be distinct view indices in [0, {len(seq.views)}), got {cameras}")
    rig = stack_cameras([
        make_camera(seq.views[c].K, seq.views[c].width, seq.views[c].height, seq.views[c].T_cam_world[:3, :3],
                    seq.views[c].T_cam_world[:3, 3])
        for c in views
    ])
    return views, rig


def _config_from(cues, region, working_shape, recovery: bool = True) -> TrackerConfig:
    """The `TrackerConfig` of a run's keyword arguments ("default" working shape: the config's own)."""
    extra = {} if region is None else {"region_modality": region}
    extra["recovery"] = RecoveryConfig() if recovery else None
    if not (isinstance(working_shape, str) and working_shape == "default"):
        extra["working_shape"] = None if working_shape is None else tuple(int(v) for v in working_shape)
    return TrackerConfig(cues=tuple(cues), **extra)


def _recovers(recovery: bool | None, reset_on_failure: bool) -> bool:
    """Whether a run searches after a LOST frame: as asked, else (None) unless the oracle resets it (RBOT protocol)."""
    return (not reset_on_failure) if recovery is None else bool(recovery)


def _frame_reader(seq, views):
    """k → (C, H, W, 3) frames k of the views (8-bit files stay uint8)."""
    return lambda k: np.stack([seq.views[c].read_frame(k, dtype=None) for c in views])


def _progress_bar(progress: bool, n: int, desc: str):
    if not progress:
        return None
    from tqdm import tqdm

    return tqdm(total=n, desc=desc, unit="frame")


class _BarHeartbeat:
    """Keeps a progress bar alive while one frame takes long (the set-up, a compile): from `busy(text)` on, a thread
    redraws the bar every `period` s once the frame has taken over a second, its clock running and `text (N s)` as
    its postfix (the view model's build, `view_model_build_progress`, puts its views there); `idle()` stops that
    before the frame's own update. With no bar it does nothing."""

    def __init__(self, bar, period: float = 0.5):
        self.bar, self.period = bar, period
        self._lock = threading.Lock()
        self._text, self._since, self._wrote = None, 0.0, False
        self._stop = threading.Event()
        self._thread = None
        if bar is not None:
            self._thread = threading.Thread(target=self._run, name="jaxtrack-progress", daemon=True)
            self._thread.start()

    def busy(self, text: str) -> None:
        with self._lock:
            self._text, self._since = text, time.perf_counter()

    def views(self, done: int, total: int) -> None:
        """A `view_model_build_progress` callback: the set-up's postfix names the views built."""
        with self._lock:
            if self._text is not None:
                self._text = f"set-up: view model {done}/{total} views"

    def idle(self) -> None:
        """The frame is done: no more redraws, and the postfix it wrote is cleared (the frame's own update follows)."""
        with self._lock:
            if self._wrote:
                self.bar.set_postfix_str("", refresh=False)
            self._text, self._wrote = None, False

    def close(self) -> None:
        self.idle()
        self._stop.set()
        if self._thread is not None:
            self._thread.join()

    def _run(self) -> None:
        while not self._stop.wait(self.period):
            with self._lock:
                waited = time.perf_counter() - self._since
                if self._text is not None and waited > 1.0:
                    self.bar.set_postfix_str(f"{self._text} ({waited:.0f} s)", refresh=False)
                    self.bar.refresh()
                    self._wrote = True


@contextlib.contextmanager
def _kept_alive(bar):
    """A `_BarHeartbeat` of `bar` for the block, hearing the view model's build (`view_model_build_progress`)."""
    from ..cues.lines import view_model_build_progress

    heartbeat = _BarHeartbeat(bar)
    try:
        with view_model_build_progress(heartbeat.views):
            yield heartbeat
    finally:
        heartbeat.close()


def track_sequence(
    sequence,
    *,
    cues: tuple[str, ...] = ("region", "flow", "sift"),
    cameras: list[int] | None = None,
    obj_id: int | None = None,
    config: TrackerConfig | None = None,
    params: TrackerParams | None = None,
    init_pose: np.ndarray | None = None,
    init_joints: dict | None = None,
    joint_limits: bool = False,
    pose_prior: tuple | None = None,
    late_rounds: tuple | None = None,
    region: str | None = None,
    working_shape: tuple[int, int] | None | str = "default",
    reset_on_failure: bool = False,
    recovery: bool | None = None,
    max_frames: int | None = None,
    progress: bool = True,
    on_frame: Callable[[FrameRecord], object] | None = None,
    results: str | os.PathLike | None = None,
) -> TrackingRun:
    """Track one rigid object through a BOP-layout sequence (`jaxtrack.io.read_sequence`).

    Args:
        sequence: a `jaxtrack.io.Sequence` (or a path to one).
        cues: the cue subset (ignored when `config` is given).
        cameras: view indices to use (default: all).
        obj_id: the object (default: the only, or the smallest, id with a mesh).
        init_pose: (4, 4) model → camera-0 pose of the first frame (default: its ground truth); the root
            link's pose for an articulated object.
        init_joints: articulated objects: {joint name: value} (URDF units) of the first frame (default: the
            first frame's scene_gt.json "joints"; joints not named are 0).
        joint_limits: articulated objects: keep Θ within the URDF's limits (off by default, as the method).
        region: the region modality "region" in `cues` stands for ("levelset", ...; default
            `TrackerConfig`'s); ignored when `config` is given.
        working_shape: (h, w) fixed working resolution of the crops, None for native-resolution crops in
            size classes, "default": `TrackerConfig`'s; ignored when `config` is given.
        pose_prior: (rotation, translation) relative stiffnesses of the pose prior (default
            `jaxtrack.track.DEFAULT_POSE_PRIOR`; ignored when `params` is given).
        late_rounds: (K, f[, τ]): the flow and SIFT rows × f after K refinement rounds on frames after one of
            confidence ≥ τ (`jaxtrack.track.default_params`; default: every round, the method; ignored when `params`
            is given).
        reset_on_failure: the RBOT protocol (needs ground truth for every frame).
        recovery: search after a LOST frame (True: `TrackerConfig.recovery` = `RecoveryConfig()`) or not (False);
            None (the default): on, except with `reset_on_failure` (the oracle's resets are measured without the
            tracker's own). With `config` given: its own `recovery`, left out with False, and with `reset_on_failure`
            unless True.
        max_frames: track only the first frames.
        progress: show a progress bar with the frame rate.
        on_frame: called with a `FrameRecord` after every frame (the first included), while tracking,
            so that per-frame output (an overlay video) needs no frame kept in memory.
        results: NAME.csv to write the results to frame by frame, as `write_tracking_results` writes them (a run
            that stops early leaves its frames and NAME.partial.json; see `jaxtrack.track.results_state`).

    Raises:
        ValueError: a camera index out of range, an unknown object, no initial pose, a joint named in
            scene_gt.json or `init_joints` that the URDF lacks, a rigid mesh whose unit does not fit the first
            pose (`jaxtrack.io.check_first_pose`: a dot-sized object, the camera inside the model).
    """
    from ..io import Sequence, check_first_pose, load_mesh, read_sequence

    seq = sequence if isinstance(sequence, Sequence) else read_sequence(sequence)
    views, rig = _views_and_rig(seq, cameras)
    ids = sorted(seq.model_paths)
    if obj_id is None:
        obj_id = ids[0] if ids else None
    if obj_id not in seq.model_paths:
        raise ValueError(f"obj_id {obj_id} has no mesh in {seq.root}/models (have {ids})")
    view0 = seq.views[views[0]]
    gt = view0.T_cam_obj.get(obj_id)
    T_cam0_world = np.asarray(view0.T_cam_world, np.float64)
    pose_source = "init_pose" if init_pose is not None else f"{view0.folder / 'scene_gt.json'}: frame 0, obj_id {obj_id}"
    if init_pose is None:
        if gt is None or not np.all(np.isfinite(gt[0])):
            raise ValueError(f"{view0.folder}/scene_gt.json has no pose of obj_id {obj_id} in the first frame; "
                             "pass init_pose")
        init_pose = gt[0]
    init_pose = np.asarray(init_pose, np.float64)
    if init_pose.shape != (4, 4):
        raise ValueError(f"init_pose must be (4, 4), got {init_pose.shape}")
    if max_frames is not None and int(max_frames) < 1:
        raise ValueError(f"max_frames must be ≥ 1, got {max_frames}")
    if reset_on_failure and gt is None:
        raise ValueError("reset_on_failure needs ground-truth poses in scene_gt.json")
    n = seq.num_frames if max_frames is None else min(seq.num_frames, int(max_frames))
    model_path = seq.model_paths[obj_id]
    articulated = None
    if model_path.suffix.lower() == ".urdf":
        articulated = _articulated(model_path, view0, obj_id, init_joints, n)
        mesh, model, theta0, theta_gt = articulated["mesh"], articulated["model"], articulated["theta0"], articulated["theta_gt"]
    else:
        if init_joints:
            raise ValueError(f"init_joints given, but obj_id {obj_id} is rigid ({model_path.name})")
        mesh, model, theta0, theta_gt = load_mesh(model_path, seq.model_scale(obj_id)), None, None, None
        # Before anything compiles: a mesh in the wrong unit (metres read as mm: a dot; mm read as metres: the
        # camera inside it) or a pose that does not show the object.
        check_first_pose(np.asarray(mesh.vertices, np.float64), view0.K, view0.width, view0.height, init_pose, pose_source,
                         diameter_mm=_info_diameter(seq, obj_id))
    if joint_limits and articulated is None:
        raise ValueError(f"joint_limits: obj_id {obj_id} is rigid ({model_path.name}); limits come from a URDF")
    if config is None:
        config = _config_from(cues, region, working_shape, _recovers(recovery, reset_on_failure))
    elif config.recovery is not None and (recovery is False or (reset_on_failure and recovery is not True)):
        config = config.without_recovery()  # asked not to, or the oracle resets instead of the search
    limits = (articulated["lower"], articulated["upper"]) if joint_limits else None
    tracker = Tracker(mesh, rig, model=model, config=config, params=params, joint_limits=limits,
                      **({} if pose_prior is None else {"pose_prior": pose_prior}),
                      **({} if late_rounds is None else {"late_rounds": late_rounds}))
    T_world_gt = None if gt is None else np.einsum("ij,fjk->fik", np.linalg.inv(T_cam0_world), gt)

    frames = _frame_reader(seq, views)
    bar = _progress_bar(progress, n, "tracking")
    T_cam_world = np.stack([np.asarray(seq.views[c].T_cam_world, np.float64) for c in views])

    def report(k, images, T, phi=None, offsets=None, scales=None):
        if on_frame is not None:
            on_frame(FrameRecord(
                index=k, im_id=int(view0.frame_ids[k]), images=images, T_world_root=T,
                T_cam_obj=np.einsum("cij,jk->cik", T_cam_world, T), status=status[-1], confidence=conf[-1],
                region_phi=None if phi is None else np.asarray(phi), offsets=None if offsets is None else np.asarray(offsets),
                reset=reset[-1], theta=thetas[-1], scales=None if scales is None else np.asarray(scales),
            ))

    writer = None if results is None else TrackingResultsWriter(
        results, camera_ids=views, T_cam_world=T_cam_world, cue_names=config.cue_names, frames_expected=n,
        joint_names=() if articulated is None else articulated["names"])

    def save(k):
        if writer is not None:
            writer.object_frame(obj_id=int(obj_id), im_id=int(view0.frame_ids[k]), T_world_root=poses[-1],
                                confidence=conf[-1], status=status[-1], counts=counts[-1], timings=timings[-1],
                                reset=reset[-1], crop=crops[-1], lost_joints=lost_joints[-1] if articulated else None,
                                joints_urdf=None if articulated is None else thetas[-1] / articulated["scale"])
            writer.end_frame()

    with (writer if writer is not None else contextlib.nullcontext(),  # rows on disk as they come; complete at the end
          _kept_alive(bar) as heartbeat):
        start = time.perf_counter()
        images = frames(0)
        heartbeat.busy("set-up")
        state = tracker.start(images, np.linalg.inv(T_cam0_world) @ init_pose, theta0)
        poses, thetas = [np.asarray(state.T_world_root, np.float64)], [np.asarray(state.theta, np.float64)]
        status, conf = [Status.OK.name], [1.0]
        counts = [np.zeros((len(views), len(config.cues)), np.int64)]
        timings = [{"total_s": time.perf_counter() - start}]
        reset = [False]
        crops = [None]
        lost_joints = [[]]
        lost_iou = None if articulated is None else float(tracker.params_for((64, 64)).lost_iou)
        save(0)
        report(0, images, poses[0])
        heartbeat.idle()
        if bar is not None:
            bar.update(1)
        for k in range(1, n):
            t0 = time.perf_counter()
            heartbeat.busy(f"frame {k}: compiling or loading a program" if k == 1 else f"frame {k}")
            images = frames(k)
            read_s = time.perf_counter() - t0
            state, result, info = tracker.step(state, images)
            T = np.asarray(result.T_world_root, np.float64)
            did_reset = False
            if reset_on_failure and T_world_gt is not None and _failed(T_cam0_world @ T, gt[k]):
                state = tracker.start(images, T_world_gt[k], None if theta_gt is None else theta_gt[k])
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
            crops.append(None if info.get("crop_shape") is None else tuple(int(v) for v in info["crop_shape"]))
            if articulated is not None:
                support = np.asarray(result.part_support)[articulated["child_part"]]
                lost_joints.append([name for name, s in zip(articulated["names"], support) if 0 <= s < lost_iou])
            else:
                lost_joints.append([])
            save(k)
            has_crop = info.get("offsets") is not None
            report(k, images, T, result.region_phi if has_crop else None, info["offsets"] if has_crop else None,
                   info.get("scales") if has_crop else None)
            heartbeat.idle()
            if bar is not None:
                bar.update(1)
                bar.set_postfix(status=status[-1], conf=f"{conf[-1]:.2f}")
        if bar is not None:
            bar.close()
    tracker.join_background()  # a background compile must not outlive the run (the process may exit next)
    return TrackingRun(
        frame_ids=list(view0.frame_ids[:n]), obj_id=int(obj_id), T_world_root=np.stack(poses), theta=np.stack(thetas),
        T_cam_world=T_cam_world, camera_ids=views,
        status=status, confidence=np.asarray(conf), counts=np.stack(counts), timings=timings, reset=np.asarray(reset),
        crops=crops, joint_names=() if articulated is None else articulated["names"],
        joint_scale=None if articulated is None else articulated["scale"], lost_joints=lost_joints,
        cue_names=config.cue_names,
    )


def track_objects(
    sequence,
    obj_ids: list[int] | None = None,
    *,
    cues: tuple[str, ...] = ("region", "flow", "sift"),
    cameras: list[int] | None = None,
    config: TrackerConfig | None = None,
    init_poses: dict | None = None,
    region: str | None = None,
    working_shape: tuple[int, int] | None | str = "default",
    pose_prior: tuple | None = JOINT_POSE_PRIOR,
    late_rounds: tuple | None = None,
    max_frames: int | None = None,
    progress: bool = True,
    on_frame: Callable[[list[FrameRecord]], object] | None = None,
    results: str | os.PathLike | None = None,
) -> list[TrackingRun]:
    """Track several rigid objects of one BOP-layout sequence jointly (`JointTracker`): each object's lines
    leave out what the others hide, its flow and SIFT the pixels they cover; each has its own status.

    Args:
        sequence: a `jaxtrack.io.Sequence` (or a path to one).
        obj_ids: the objects (default: every object with a mesh and a pose in the first frame's scene_gt.json).
        init_poses: {obj_id: (4, 4) model → camera-0 pose of the first frame} (default: the ground truth).
        on_frame: called after every frame with one `FrameRecord` per object (in `obj_ids` order).
        pose_prior: the refinement's pose prior (default `JOINT_POSE_PRIOR`, M3T's; None: the tracker's default, none).
        late_rounds: (K, f[, τ]) of every object's tracker, as `track_sequence`'s (default: every round).
        results: NAME.csv written frame by frame (every object's rows), as `track_sequence`'s.
        cues, cameras, config, region, working_shape, max_frames, progress: as `track_sequence`.

    Returns:
        one `TrackingRun` per object, in `obj_ids` order.

    Raises:
        ValueError: an unknown or repeated object, an articulated one (joint runs are rigid), no first pose,
            a mesh whose unit does not fit its first pose.
    """
    from ..io import Sequence, check_first_pose, load_mesh, read_sequence
    from ._joint import JointTracker

    seq = sequence if isinstance(sequence, Sequence) else read_sequence(sequence)
    views, rig = _views_and_rig(seq, cameras)
    view0 = seq.views[views[0]]
    init_poses = {} if init_poses is None else {int(k): v for k, v in init_poses.items()}
    if obj_ids is None:
        obj_ids = [o for o in sorted(seq.model_paths)
                   if o in init_poses or (o in view0.T_cam_obj and np.all(np.isfinite(view0.T_cam_obj[o][0])))]
    obj_ids = [int(o) for o in obj_ids]
    if not obj_ids or len(set(obj_ids)) != len(obj_ids):
        raise ValueError(f"obj_ids must name distinct objects of {seq.root}, got {obj_ids}")
    unknown = [o for o in obj_ids if o not in seq.model_paths]
    if unknown:
        raise ValueError(f"obj_id {unknown[0]} has no mesh in {seq.root}/models (have {sorted(seq.model_paths)})")
    if max_frames is not None and int(max_frames) < 1:
        raise ValueError(f"max_frames must be ≥ 1, got {max_frames}")
    n = seq.num_frames if max_frames is None else min(seq.num_frames, int(max_frames))
    T_cam0_world = np.asarray(view0.T_cam_world, np.float64)
    if config is None:
        # The search after a LOST frame does not see the other objects (their outlines hide lines): off here.
        config = _config_from(cues, region, working_shape, recovery=False)
    trackers, starts = [], []
    for o in obj_ids:
        path = seq.model_paths[o]
        if path.suffix.lower() == ".urdf":
            raise ValueError(f"obj_id {o}: {path.name} is articulated; several objects are tracked rigid (track it alone)")
        source = f"init_poses[{o}]" if o in init_poses else f"{view0.folder / 'scene_gt.json'}: frame 0, obj_id {o}"
        if o in init_poses:
            T0 = np.asarray(init_poses[o], np.float64)
            if T0.shape != (4, 4):
                raise ValueError(f"{source} must be (4, 4), got {T0.shape}")
        else:
            gt = view0.T_cam_obj.get(o)
            if gt is None or not np.all(np.isfinite(gt[0])):
                raise ValueError(f"{view0.folder}/scene_gt.json has no pose of obj_id {o} in the first frame; pass init_poses")
            T0 = gt[0]
        mesh = load_mesh(path, seq.model_scale(o))
        check_first_pose(np.asarray(mesh.vertices, np.float64), view0.K, view0.width, view0.height, T0, source,
                         diameter_mm=_info_diameter(seq, o))
        trackers.append(Tracker(mesh, rig, config=config, **({} if pose_prior is None else {"pose_prior": pose_prior}),
                                **({} if late_rounds is None else {"late_rounds": late_rounds})))
        starts.append(np.linalg.inv(T_cam0_world) @ T0)
    joint = JointTracker(trackers)
    T_cam_world = np.stack([np.asarray(seq.views[c].T_cam_world, np.float64) for c in views])

    frames = _frame_reader(seq, views)
    bar = _progress_bar(progress, n, f"tracking {len(obj_ids)} objects")
    N = len(obj_ids)
    poses = [[] for _ in range(N)]
    status = [[] for _ in range(N)]
    conf = [[] for _ in range(N)]
    counts = [[] for _ in range(N)]
    timings = [[] for _ in range(N)]
    crops = [[] for _ in range(N)]

    def report(k, images, step_results=None, infos=None):
        if on_frame is None:
            return
        records = []
        for i in range(N):
            T = poses[i][-1]
            has_crop = step_results is not None and infos[i].get("offsets") is not None
            records.append(FrameRecord(
                index=k, im_id=int(view0.frame_ids[k]), images=images, T_world_root=T,
                T_cam_obj=np.einsum("cij,jk->cik", T_cam_world, T), status=status[i][-1], confidence=conf[i][-1],
                region_phi=np.asarray(step_results[i].region_phi) if has_crop else None,
                offsets=np.asarray(infos[i]["offsets"]) if has_crop else None, reset=False, theta=np.zeros(0),
                scales=None if not has_crop or infos[i].get("scales") is None else np.asarray(infos[i]["scales"]),
            ))
        on_frame(records)

    writer = None if results is None else TrackingResultsWriter(
        results, camera_ids=views, T_cam_world=T_cam_world, cue_names=config.cue_names, frames_expected=n,
        several=N > 1)

    def save(k):
        if writer is not None:
            for i, o in enumerate(obj_ids):
                writer.object_frame(obj_id=o, im_id=int(view0.frame_ids[k]), T_world_root=poses[i][-1],
                                    confidence=conf[i][-1], status=status[i][-1], counts=counts[i][-1],
                                    timings=timings[i][-1], crop=crops[i][-1])
            writer.end_frame()

    with writer if writer is not None else contextlib.nullcontext(), _kept_alive(bar) as heartbeat:
        t0 = time.perf_counter()
        images = frames(0)
        heartbeat.busy("set-up")
        states = joint.start(images, starts)
        for i in range(N):
            poses[i].append(np.asarray(states[i].T_world_root, np.float64))
            status[i].append(Status.OK.name)
            conf[i].append(1.0)
            counts[i].append(np.zeros((len(views), len(config.cues)), np.int64))
            timings[i].append({"total_s": (time.perf_counter() - t0) / N})
            crops[i].append(None)
        save(0)
        report(0, images)
        heartbeat.idle()
        if bar is not None:
            bar.update(1)
        for k in range(1, n):
            t0 = time.perf_counter()
            heartbeat.busy(f"frame {k}: compiling or loading a program" if k == 1 else f"frame {k}")
            images = frames(k)
            read_s = time.perf_counter() - t0
            states, step_results, infos = joint.step(states, images)
            for i, (result, info) in enumerate(zip(step_results, infos)):
                poses[i].append(np.asarray(result.T_world_root, np.float64))
                status[i].append(Status(int(result.status)).name)
                conf[i].append(float(result.confidence))
                counts[i].append(np.asarray(result.counts))
                info["timings"]["read_s"] = read_s / N
                timings[i].append(info["timings"])
                crops[i].append(None if info.get("crop_shape") is None else tuple(int(v) for v in info["crop_shape"]))
            save(k)
            report(k, images, step_results, infos)
            heartbeat.idle()
            if bar is not None:
                bar.update(1)
                bar.set_postfix(status="/".join(s[-1] for s in status))
        if bar is not None:
            bar.close()
    joint.join_background()
    return [TrackingRun(
        frame_ids=list(view0.frame_ids[:n]), obj_id=o, T_world_root=np.stack(poses[i]), theta=np.zeros((n, 0)),
        T_cam_world=T_cam_world, camera_ids=views, status=status[i], confidence=np.asarray(conf[i]),
        counts=np.stack(counts[i]), timings=timings[i], reset=np.zeros(n, bool), crops=crops[i], lost_joints=[[]] * n,
        cue_names=config.cue_names,
    ) for i, o in enumerate(obj_ids)]


def _articulated(model_path: pathlib.Path, view0, obj_id: int, init_joints: dict | None, n: int) -> dict:
    """Read a URDF model and its first-frame joint values (URDF units) → model-unit Θ0 and ground truth."""
    from ..io import read_urdf

    art = read_urdf(model_path, package_dirs=[model_path.parent])
    gt_joints = view0.joints.get(obj_id, {})
    where = f"{view0.folder / 'scene_gt.json'}"
    unknown = sorted(set(gt_joints) - set(art.joint_names))
    if unknown:
        raise ValueError(f"{where}: joint(s) {unknown} of obj_id {obj_id} are not in {model_path.name} "
                         f"(its movable joints: {list(art.joint_names)})")
    if init_joints is None:
        init_joints = {name: float(v[0]) for name, v in gt_joints.items() if np.isfinite(v[0])}
    try:
        theta0 = art.joint_vector(init_joints)
    except ValueError as e:
        raise ValueError(f"init_joints: {e}") from None
    theta_gt = None
    if gt_joints and all(name in gt_joints for name in art.joint_names if art.mimic[art.joint_names.index(name)] is None):
        theta_gt = np.stack([art.joint_vector({name: float(v[k]) for name, v in gt_joints.items() if np.isfinite(v[k])})
                             for k in range(n)])
    return {"mesh": art.mesh, "model": art.model, "theta0": theta0, "theta_gt": theta_gt,
            "names": tuple(art.joint_names), "scale": np.asarray(art.joint_scale, np.float64),
            "lower": np.asarray(art.lower, np.float64), "upper": np.asarray(art.upper, np.float64),
            "child_part": np.asarray(art.model.joint_child_part)}


def write_tracking_results(run: TrackingRun | list[TrackingRun], path: str | os.PathLike) -> tuple[pathlib.Path, pathlib.Path]:
    """The BOP results CSV (one row per frame, camera view and object: scene_id = view index) and, beside it,
    NAME.frames.jsonl with the status, confidence, counts per cue and camera, timings, reset flag and the
    step's crop size class.

    `run` may be a list of runs of the same frames (`track_objects`): their rows share the CSV, and each
    record of NAME.frames.jsonl names its "obj_id".

    For an articulated run, NAME.joints.csv too: `scene_id,im_id,obj_id,<joint names>`, one row per
    frame, values in URDF units (radians, metres).

    Rows are written frame by frame (every object and camera of a frame together), as `track_sequence(...,
    results=)` writes them while tracking.

    Returns:
        (csv path, jsonl path).
    """
    path = pathlib.Path(path)
    if path.suffix.lower() != ".csv":
        raise ValueError(f"results path must end in .csv, got {path}")
    runs = list(run) if isinstance(run, list | tuple) else [run]
    if not runs:
        raise ValueError("write_tracking_results: no run to write")
    if len(runs) > 1 and any(r.joint_names for r in runs):
        raise ValueError("write_tracking_results: several runs are written together only when rigid")
    frames = len(runs[0].frame_ids)
    if any(len(r.frame_ids) != frames or list(r.camera_ids) != list(runs[0].camera_ids) for r in runs):
        raise ValueError("write_tracking_results: the runs must share their frames and cameras")
    with TrackingResultsWriter(path, camera_ids=runs[0].camera_ids, T_cam_world=runs[0].T_cam_world,
                               cue_names=runs[0].cue_names, frames_expected=frames, several=len(runs) > 1,
                               joint_names=runs[0].joint_names if len(runs) == 1 else ()) as writer:
        for k in range(frames):
            for r in runs:
                write_run_frame(writer, r, k)
            writer.end_frame()
    csv, jsonl = writer.path, writer.jsonl
    return csv, jsonl


def write_joint_results(path: str | os.PathLike, run: TrackingRun) -> pathlib.Path:
    """NAME.joints.csv: `scene_id,im_id,obj_id,<joint names>` with one row per frame (URDF units)."""
    from ..io import prepare_output_file

    path = prepare_output_file(path, "write_joint_results: path")
    values = run.joints_urdf()
    lines = [joints_header(run.joint_names)]
    lines += [joints_row(run.camera_ids[0], im_id, run.obj_id, values[k]) for k, im_id in enumerate(run.frame_ids)]
    path.write_text("\n".join(lines) + "\n")
    return path


def read_joint_results(path: str | os.PathLike) -> tuple[list, tuple, np.ndarray]:
    """Read NAME.joints.csv: (im_ids, joint names, (F, J) values in URDF units).

    Raises:
        ValueError: naming the file and line of a malformed row.
    """
    path = pathlib.Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: missing")
    lines = [ln for ln in path.read_text().splitlines() if ln.strip()]
    header = lines[0].split(",") if lines else []
    if header[:3] != ["scene_id", "im_id", "obj_id"]:
        raise ValueError(f"{path}: header must start with 'scene_id,im_id,obj_id', got {','.join(header[:3])!r}")
    names = tuple(header[3:])
    im_ids, values = [], []
    for n, line in enumerate(lines[1:], start=2):
        parts = line.split(",")
        if len(parts) != len(header):
            raise ValueError(f"{path}:{n}: expected {len(header)} fields, got {len(parts)}")
        try:
            im_ids.append(int(parts[1]))
            values.append([float(v) for v in parts[3:]])
        except ValueError as e:
            raise ValueError(f"{path}:{n}: malformed number ({e})") from None
    return im_ids, names, np.asarray(values, np.float64).reshape(len(im_ids), len(names))


@dataclasses.dataclass
class TrackingEvaluation:
    """Errors of one results CSV against a sequence's ground truth (F frames of one camera view).

    Attributes:
        im_ids: (F,) BOP image ids, in sequence order; camera: the view evaluated; obj_id: the object.
        rot_deg, trans_mm: (F,) rotation (deg) and translation (mm) errors, NaN without ground truth.
        add_mm, adds_mm: (F,) ADD and ADD-S over the mesh vertices (mm), NaN without ground truth.
        diameter_mm: the model's diameter (models_info.json when it has one, else from the mesh).
        has_gt: (F,) bool; initial: (F,) bool, the sequence's first frame (the given initial pose).
        success: (F,) within 5 cm / 5° (False without ground truth).
        score, time_s: (F,) the CSV's confidence and seconds per frame.
        status: (F,) status names from NAME.frames.jsonl, None when that file is absent.
        reset: (F,) bool reset flags from NAME.frames.jsonl, None when absent.
        points: how many mesh vertices ADD / ADD-S used.
    """

    im_ids: np.ndarray
    camera: int
    obj_id: int
    rot_deg: np.ndarray
    trans_mm: np.ndarray
    add_mm: np.ndarray
    adds_mm: np.ndarray
    diameter_mm: float
    has_gt: np.ndarray
    initial: np.ndarray
    success: np.ndarray
    score: np.ndarray
    time_s: np.ndarray
    status: list | None
    reset: np.ndarray | None
    points: int


MAX_EVAL_POINTS = 4000  # ADD-S is O(N²) per frame: larger meshes are subsampled (deterministically)


def _frames_jsonl(path: pathlib.Path, im_ids: list, obj_id: int | None = None) -> tuple[list | None, np.ndarray | None]:
    """Status and reset flag per image id from NAME.frames.jsonl (None, None when the file is absent); records
    that name another "obj_id" (a joint run's file) are skipped."""
    if not path.is_file():
        return None, None
    by_id = {}
    for n, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        try:
            rec = json.loads(line)
            if obj_id is not None and "obj_id" in rec and int(rec["obj_id"]) != obj_id:
                continue
            by_id[int(rec["im_id"])] = (str(rec["status"]), bool(rec.get("reset", False)))
        except (json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
            raise ValueError(f"{path}:{n}: malformed frame record ({e})") from e
        if rec["status"] not in Status.__members__:  # a typo would otherwise count as a flagged (lost) frame
            raise ValueError(f"{path}:{n}: field 'status' is {rec['status']!r}, not a status name "
                             f"({', '.join(Status.__members__)})")
        confidence = rec.get("confidence", 0.0)
        if isinstance(confidence, bool) or not isinstance(confidence, int | float) or not np.isfinite(confidence):
            raise ValueError(f"{path}:{n}: field 'confidence' is {confidence!r}, not a finite number")
    missing = [i for i in im_ids if i not in by_id]
    if missing:
        raise ValueError(f"{path}: no record for im_id {missing[0]} of the results CSV ({len(missing)} missing)")
    return [by_id[i][0] for i in im_ids], np.array([by_id[i][1] for i in im_ids], bool)


def _info_diameter(seq, obj_id: int) -> float | None:
    """The object's diameter (mm) from models/models_info.json, None when the file or the entry is missing."""
    info = seq.root / "models" / "models_info.json"
    if not info.is_file():
        return None
    try:
        d = float(json.loads(info.read_text())[str(obj_id)]["diameter"])
    except (json.JSONDecodeError, KeyError, TypeError, ValueError, OSError):
        return None
    return d if np.isfinite(d) and d > 0 else None


def _diameter(seq, obj_id: int, tm) -> float:
    """models_info.json's diameter when it has this object's, else measured on the mesh (its convex hull)."""
    d = _info_diameter(seq, obj_id)
    if d is not None:
        return d
    from ._evaluate import model_diameter

    return model_diameter(np.asarray(tm.convex_hull.vertices if len(tm.vertices) > 3 else tm.vertices))


def evaluate_tracking(results, sequence, *, obj_id: int | None = None, camera: int | None = None) -> TrackingEvaluation:
    """Compare a BOP results CSV (`write_tracking_results`) with the ground truth of a sequence.

    Reads NAME.frames.jsonl beside the CSV when present (statuses, resets). ADD / ADD-S use the mesh
    vertices (at most `MAX_EVAL_POINTS`, a fixed random subset beyond that).

    Args:
        results: the CSV path.
        sequence: a `jaxtrack.io.Sequence` or its folder.
        obj_id: the object (default: the only one in the CSV).
        camera: the view (scene_id) whose rows are evaluated (default: the smallest in the CSV).

    Raises:
        ValueError: naming the file and what does not match (partial results of a run that stopped, an im_id
            that is not a frame of the sequence, an object without a mesh, a repeated row, a view the sequence does not have).
    """
    from ..io import Sequence, load_trimesh, read_bop_results, read_sequence
    from ._evaluate import add_error, adds_error, pose_errors, success_mask

    path = pathlib.Path(results)
    check_complete(path)  # a run that stopped early: its last rows may be cut, and its frames are not the sequence
    seq = sequence if isinstance(sequence, Sequence) else read_sequence(sequence)
    rows = read_bop_results(path)
    if not rows:
        raise ValueError(f"{path}: no result rows")
    objs = sorted({r[2] for r in rows})
    if obj_id is None:
        if len(objs) > 1:
            raise ValueError(f"{path}: rows for several objects {objs}; choose one with obj_id")
        obj_id = objs[0]
    if obj_id not in objs:
        raise ValueError(f"{path}: no rows for obj_id {obj_id} (have {objs})")
    if obj_id not in seq.model_paths:
        raise ValueError(f"{path}: obj_id {obj_id} has no mesh in {seq.root}/models (have {sorted(seq.model_paths)})")
    rows = [r for r in rows if r[2] == obj_id]
    cams = sorted({r[0] for r in rows})
    camera = cams[0] if camera is None else int(camera)
    if camera not in cams:
        raise ValueError(f"{path}: no rows for view (scene_id) {camera} (have {cams})")
    if not 0 <= camera < len(seq.views):
        raise ValueError(f"{path}: scene_id {camera} is not a camera view of {seq.root} (it has {len(seq.views)})")
    view = seq.views[camera]
    position = {int(i): k for k, i in enumerate(view.frame_ids)}
    by_frame = {}
    for r in rows:
        if r[0] != camera:
            continue
        if r[1] not in position:
            raise ValueError(f"{path}: im_id {r[1]} is not a frame of {view.folder} (its ids run {view.frame_ids[0]}.."
                             f"{view.frame_ids[-1]}, {len(view.frame_ids)} frames): results of another sequence?")
        if r[1] in by_frame:
            raise ValueError(f"{path}: two rows for view {camera}, im_id {r[1]}, obj_id {obj_id}")
        by_frame[r[1]] = r
    im_ids = sorted(by_frame, key=position.get)
    k = np.array([position[i] for i in im_ids])
    T_est = np.stack([by_frame[i][4] for i in im_ids])
    gt_all = view.T_cam_obj.get(obj_id)
    T_gt = np.full_like(T_est, np.nan) if gt_all is None else np.asarray(gt_all, np.float64)[k]
    has_gt = np.all(np.isfinite(T_gt), axis=(1, 2))
    tm = load_trimesh(seq.model_paths[obj_id], seq.model_scale(obj_id))
    points = np.asarray(tm.vertices, np.float64)
    if len(points) > MAX_EVAL_POINTS:
        points = points[np.sort(np.random.default_rng(0).choice(len(points), MAX_EVAL_POINTS, replace=False))]
    nan = np.full(len(im_ids), np.nan)
    rot, trans, add, adds = nan.copy(), nan.copy(), nan.copy(), nan.copy()
    if has_gt.any():
        rot[has_gt], trans[has_gt] = pose_errors(T_est[has_gt], T_gt[has_gt])
        add[has_gt] = add_error(T_est[has_gt], T_gt[has_gt], points)
        adds[has_gt] = adds_error(T_est[has_gt], T_gt[has_gt], points)
    status, reset = _frames_jsonl(path.with_name(path.stem + ".frames.jsonl"), im_ids, int(obj_id))
    return TrackingEvaluation(
        im_ids=np.asarray(im_ids), camera=camera, obj_id=int(obj_id), rot_deg=rot, trans_mm=trans, add_mm=add, adds_mm=adds,
        diameter_mm=_diameter(seq, obj_id, tm), has_gt=has_gt, initial=k == 0,
        success=has_gt & success_mask(np.nan_to_num(rot, nan=np.inf), np.nan_to_num(trans, nan=np.inf)),
        score=np.array([by_frame[i][3] for i in im_ids]), time_s=np.array([by_frame[i][5] for i in im_ids]),
        status=status, reset=reset, points=len(points),
    )
