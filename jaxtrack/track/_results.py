"""Tracking results written as the frames go: the BOP results CSV, NAME.frames.jsonl and (articulated)
NAME.joints.csv, one frame at a time, flushed after each, so that a run killed at frame 70 of 100 leaves frames
0-69 on disk.

While a run writes, NAME.partial.json lies beside the CSV ({"frames_expected": F}, written once); it is removed
when the last frame is written (`TrackingResultsWriter.finish`, or leaving its `with` block without an error). Files with that marker are partial:
`results_state` says so, `jaxtrack eval` refuses them (naming how far the run got) and `jaxtrack bench` tracks such
a sequence again from its first frame instead of trusting it.
"""

from __future__ import annotations

import dataclasses
import json
import os
import pathlib

import numpy as np


def joints_header(joint_names) -> str:
    """NAME.joints.csv's header: scene_id,im_id,obj_id,<joint names>."""
    return ",".join(("scene_id", "im_id", "obj_id", *joint_names))


def joints_row(scene_id, im_id, obj_id, values) -> str:
    """One NAME.joints.csv row (no newline): the joint values in URDF units."""
    return ",".join((str(int(scene_id)), str(int(im_id)), str(int(obj_id)), *(f"{v:.8f}" for v in np.asarray(values))))


def partial_marker(csv: str | os.PathLike) -> pathlib.Path:
    """NAME.partial.json beside NAME.csv."""
    csv = pathlib.Path(csv)
    return csv.with_name(csv.stem + ".partial.json")


@dataclasses.dataclass(frozen=True)
class ResultsState:
    """What is on disk at a results CSV path: "missing", "partial" (a run that stopped; `frames_written` of
    `frames_expected`) or "complete"."""

    state: str
    frames_written: int = 0
    frames_expected: int | None = None


def results_state(csv: str | os.PathLike) -> ResultsState:
    """Whether the results at `csv` are missing, partial (the marker is there) or complete."""
    csv = pathlib.Path(csv)
    marker = partial_marker(csv)
    if marker.is_file():
        try:
            expected = json.loads(marker.read_text()).get("frames_expected")
        except (json.JSONDecodeError, OSError, TypeError, ValueError, AttributeError):
            expected = None
        return ResultsState("partial", _frames_on_disk(csv), expected)
    return ResultsState("complete") if csv.is_file() else ResultsState("missing")


def _frames_on_disk(csv: pathlib.Path) -> int:
    """How many frames NAME.frames.jsonl holds whole (distinct im_ids of its complete lines)."""
    jsonl = csv.with_name(csv.stem + ".frames.jsonl")
    ids = set()
    try:
        lines = jsonl.read_text().splitlines()
    except OSError:
        return 0
    for line in lines:
        try:
            ids.add(int(json.loads(line)["im_id"]))
        except (json.JSONDecodeError, KeyError, TypeError, ValueError):
            continue  # the line a killed run cut
    return len(ids)


def check_complete(csv: str | os.PathLike) -> None:
    """Raise ValueError naming the marker when the results at `csv` are partial."""
    state = results_state(csv)
    if state.state == "partial":
        expected = "" if state.frames_expected is None else f" of {state.frames_expected}"
        raise ValueError(f"{csv}: partial results: the run stopped after {state.frames_written}{expected} frame(s) "
                         f"({partial_marker(csv).name} is beside it); run the tracking again to finish it")


class TrackingResultsWriter:
    """Append one frame's results at a time (every object and camera of it), flushed after each frame.

    Args:
        path: NAME.csv; NAME.frames.jsonl (and NAME.joints.csv for `joint_names`) go beside it.
        camera_ids: (C,) the view indices (the CSV's scene_id); T_cam_world: (C, 4, 4) their extrinsics (mm).
        cue_names: (M,) the counts' cues; frames_expected: F, for the partial marker.
        several: records of NAME.frames.jsonl name their "obj_id" (a joint run).
        joint_names: an articulated run's movable joints (NAME.joints.csv columns, URDF units).
    """

    def __init__(self, path, *, camera_ids, T_cam_world, cue_names, frames_expected: int, several: bool = False,
                 joint_names: tuple = ()):
        from ..io import prepare_output_file
        from ..io._bop import RESULT_HEADER

        self.path = prepare_output_file(path, "results path", suffixes=(".csv",))
        self.jsonl = self.path.with_name(self.path.stem + ".frames.jsonl")
        self.camera_ids = [int(c) for c in camera_ids]
        self.T_cam_world = np.asarray(T_cam_world, np.float64)
        self.cue_names = tuple(cue_names)
        self.frames_expected = int(frames_expected)
        self.several = bool(several)
        self.joint_names = tuple(joint_names)
        partial_marker(self.path).write_text(json.dumps({"frames_expected": self.frames_expected}))
        self._csv = self.path.open("w")
        self._csv.write(RESULT_HEADER + "\n")
        self._records = self.jsonl.open("w")
        self._joints = None
        if self.joint_names:
            self._joints = self.path.with_name(self.path.stem + ".joints.csv").open("w")
            self._joints.write(joints_header(self.joint_names) + "\n")

    def object_frame(self, *, obj_id: int, im_id: int, T_world_root, confidence: float, status: str, counts,
                     timings: dict, reset: bool = False, crop=None, lost_joints=None, joints_urdf=None) -> None:
        """One object's frame: a CSV row per camera and a frames.jsonl record (flushed by `end_frame`).

        T_world_root: (4, 4) model → world (mm); counts: (C, M); joints_urdf: (J,) URDF units when articulated."""
        from ..io._bop import bop_result_line

        T = np.asarray(T_world_root, np.float64)
        if not np.all(np.isfinite(T)):  # a row no BOP reader accepts: refused here, naming the frame
            raise ValueError(f"{self.path}: the pose of obj_id {obj_id} at im_id {im_id} is not finite")
        for ci, c in enumerate(self.camera_ids):
            self._csv.write(bop_result_line(c, im_id, obj_id, confidence, self.T_cam_world[ci] @ T,
                                            timings.get("total_s", 0.0)) + "\n")
        counts = np.asarray(counts)
        record = {
            "im_id": int(im_id), **({"obj_id": int(obj_id)} if self.several else {}),
            "status": status, "confidence": float(confidence),
            "counts": {str(c): {name: int(counts[ci, j]) for j, name in enumerate(self.cue_names)}
                       for ci, c in enumerate(self.camera_ids)},
            "timings": {key: round(float(v), 6) for key, v in timings.items()}, "reset": bool(reset),
            "crop": None if crop is None else [int(v) for v in crop],
            **({"lost_joints": list(lost_joints)} if self.joint_names and lost_joints is not None else {}),
        }
        self._records.write(json.dumps(record) + "\n")
        if self._joints is not None and joints_urdf is not None:
            self._joints.write(joints_row(self.camera_ids[0], im_id, obj_id, joints_urdf) + "\n")

    def end_frame(self) -> None:
        """Flush the frame's rows to disk."""
        for f in (self._csv, self._records, self._joints):
            if f is not None:
                f.flush()

    def finish(self) -> tuple[pathlib.Path, pathlib.Path]:
        """Close the files and remove the partial marker: the results are complete. Returns (csv, jsonl)."""
        self.close()
        partial_marker(self.path).unlink(missing_ok=True)
        return self.path, self.jsonl

    def close(self) -> None:
        """Close the files; the marker stays unless `finish` removed it (the run stopped early)."""
        for f in (self._csv, self._records, self._joints):
            if f is not None and not f.closed:
                f.close()

    def __enter__(self) -> TrackingResultsWriter:  # noqa: PYI034 - typing.Self needs Python 3.11; we support 3.10
        return self

    def __exit__(self, kind, error, trace) -> None:
        """Complete (`finish`) when the block ran to its end, else only closed: the marker says partial."""
        if kind is None:
            self.finish()
        else:
            self.close()


def write_run_frame(writer: TrackingResultsWriter, run, k: int) -> None:
    """Frame k of a `TrackingRun` (all its cameras) into `writer`, without `end_frame`."""
    writer.object_frame(
        obj_id=run.obj_id, im_id=run.frame_ids[k], T_world_root=run.T_world_root[k], confidence=run.confidence[k],
        status=run.status[k], counts=run.counts[k], timings=run.timings[k], reset=bool(run.reset[k]),
        crop=None if run.crops is None else run.crops[k],
        lost_joints=run.lost_joints[k] if run.joint_names and run.lost_joints else None,
        joints_urdf=run.joints_urdf()[k] if run.joint_names else None)
