"""The BCOT benchmark's layout (Li et al., "BCOT: A Markerless High-Precision 3D Object Tracking Benchmark",
CVPR 2022), read as a `Sequence` (no conversion, no copy):

    BCOT/models/<object>.obj            the objects' meshes (mm)
    BCOT/<scene>/K.txt                  the scene camera's intrinsics: nine numbers, row-major (the benchmark writes
                                        them as an OpenCV initialiser, `Matx33f K = Matx33f(fx, 0, cx, 0, fy, cy, 0, 0, 1);`)
    BCOT/<scene>/<object>/NNNN.png      the frames, numbered (any fixed width)
    BCOT/<scene>/<object>/pose.txt      per frame: r11 … r33 (row-major) tx ty tz (mm), model → camera

A sequence is a scene and an object; the object is obj_id 1.
"""

from __future__ import annotations

import os
import pathlib
import re

import numpy as np

from ._bop import CameraView, Sequence, SequenceError
from ._images import image_size
from ._rbot import numbered_frames, read_rbot_poses

MESH_SUFFIXES = (".obj", ".ply", ".stl", ".off")


def read_bcot_intrinsics(path: str | os.PathLike) -> np.ndarray:
    """(3, 3) K from a BCOT K.txt: the first nine numbers of the file, row-major (a `Matx33f(...)` line or plain
    numbers).

    Raises:
        SequenceError: the file is missing, holds fewer than nine numbers, or is not a pinhole matrix.
    """
    path = pathlib.Path(path)
    if not path.is_file():
        raise SequenceError(f"{path}: BCOT intrinsics file (K.txt) not found")
    text = path.read_text()
    inside = re.search(r"\(([^()]*)\)", text)  # Matx33f(...)
    numbers = re.findall(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?", inside.group(1) if inside else text)
    if len(numbers) < 9:
        raise SequenceError(f"{path}: {len(numbers)} numbers; K.txt holds the nine of K, row-major")
    K = np.asarray([float(v) for v in numbers[:9]]).reshape(3, 3)
    if not (np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0 and np.allclose(K[2], [0, 0, 1])
            and K[1, 0] == 0):
        raise SequenceError(f"{path}: not a pinhole camera matrix (fx, fy > 0, last row 0 0 1): {K.tolist()}")
    return K


def _mesh(root: pathlib.Path, obj: str) -> pathlib.Path:
    for suffix in MESH_SUFFIXES:
        candidate = root / "models" / f"{obj}{suffix}"
        if candidate.is_file():
            return candidate
    raise SequenceError(f"{root / 'models' / (obj + '.obj')}: the object's mesh is missing")


def bcot_sequences(dataset: str | os.PathLike) -> list[tuple[str, str]]:
    """(scene, object) of every BCOT sequence in `dataset`, sorted: a scene folder holds K.txt and object folders
    with pose.txt."""
    root = pathlib.Path(dataset)
    if not root.is_dir():
        raise SequenceError(f"{root}: no such BCOT folder")
    out = []
    for scene in sorted(p for p in root.iterdir() if p.is_dir() and (p / "K.txt").is_file()):
        out += [(scene.name, o.name) for o in sorted(scene.iterdir()) if (o / "pose.txt").is_file()]
    return out


def read_bcot_sequence(dataset: str | os.PathLike, scene: str, obj: str) -> Sequence:
    """One BCOT sequence (a scene and an object) as a `Sequence` for `track_sequence`.

    Raises:
        SequenceError: naming the missing file or folder, the malformed line or the missing frame.
    """
    root = pathlib.Path(dataset)
    folder = root / scene / obj
    if not folder.is_dir():
        have = [f"{s}/{o}" for s, o in bcot_sequences(root)] if root.is_dir() else []
        raise SequenceError(f"{folder}: no such BCOT sequence folder (sequences in {root}: {have[:8]}"
                            f"{' ...' if len(have) > 8 else ''})")
    frames = numbered_frames(folder)
    ids = [i for i, _ in frames]
    K = read_bcot_intrinsics(root / scene / "K.txt")
    poses = read_rbot_poses(folder / "pose.txt", len(ids))[: len(ids)]  # row k: the k-th frame
    try:
        width, height = image_size(frames[0][1])
    except (FileNotFoundError, ValueError) as e:
        raise SequenceError(str(e)) from e
    view = CameraView(folder, [p for _, p in frames], K, np.eye(4), {1: poses}, int(width), int(height), ids)
    return Sequence(root / scene / obj, {1: _mesh(root, obj)}, [view])
