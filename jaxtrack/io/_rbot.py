"""The RBOT dataset's own layout (Tjaden et al., "A Region-based Gauss-Newton Approach to Real-Time Monocular
Multiple Object Tracking", TPAMI 2019), read as a `Sequence` (no conversion, no copy):

    RBOT/poses_first.txt            a header line, then per frame: r11 … r33 (row-major) tx ty tz (mm), tab-separated
    RBOT/poses_second.txt           the same for the occluding object of the d_occlusion variant
    RBOT/camera_calibration.txt     a header line, then fx fy cx cy [k1 k2 p1 p2] (one camera, every object)
    RBOT/squirrel_small.obj         the occluding object's mesh (mm)
    RBOT/<object>/<object>.obj      the object's mesh (mm)
    RBOT/<object>/frames/<variant>NNNN.png    a_regular0000.png, b_dynamiclight…, c_noisy…, d_occlusion…

Frame k's poses are the k-th pose rows (model → camera; the camera is the world). The tracked object is obj_id 1;
in the d_occlusion variant the occluding object is obj_id 2 (`jaxtrack.track.track_objects` tracks both).
"""

from __future__ import annotations

import itertools
import os
import pathlib
import re

import numpy as np

from ._bop import CameraView, Sequence, SequenceError
from ._images import image_size

RBOT_VARIANTS = ("a_regular", "b_dynamiclight", "c_noisy", "d_occlusion")
RBOT_OCCLUDER = "squirrel_small"


def _numbers(line: str) -> list[float] | None:
    try:
        return [float(v) for v in line.replace(",", " ").split()]
    except ValueError:
        return None


def numbered_frames(folder: pathlib.Path, prefix: str = "") -> list[tuple[int, pathlib.Path]]:
    """(number, path) of the frames `<prefix>NNNN.png` in `folder`, in order (RBOT's and BCOT's naming).

    Raises:
        SequenceError: none is there, or one is missing between the first and the last (naming it).
    """
    pattern = re.compile(re.escape(prefix) + r"(\d+)\.png")
    frames = sorted(((int(m.group(1)), p) for p in folder.iterdir() if (m := pattern.fullmatch(p.name))),
                    key=lambda t: t[0])
    if not frames:
        raise SequenceError(f"{folder}: no {prefix}NNNN.png frame")
    ids = [i for i, _ in frames]
    if ids != list(range(ids[0], ids[0] + len(ids))):
        gap = next(a + 1 for a, b in itertools.pairwise(ids) if b != a + 1)
        width = len(frames[0][1].name) - len(prefix) - len(".png")
        raise SequenceError(f"{folder}: {prefix}{gap:0{width}d}.png is missing (the frames must be consecutive)")
    return frames


def read_rbot_poses(path: str | os.PathLike, n: int | None = None) -> np.ndarray:
    """(F, 4, 4) model → camera poses (mm) from an RBOT poses file (a header line, then 12 numbers per line; BCOT's
    pose.txt is the same without the header).

    Raises:
        SequenceError: the file is missing, a line does not hold 12 numbers, a rotation is not one, or fewer than
            `n` poses are given (the file and the line named).
    """
    from ..geometry import checked_rotation

    path = pathlib.Path(path)
    if not path.is_file():
        raise SequenceError(f"{path}: poses file not found")
    poses = []
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        values = _numbers(line)
        if values is None:
            if number == 1:  # the header
                continue
            raise SequenceError(f"{path}:{number}: not 12 numbers (r11 … r33 tx ty tz)")
        if len(values) != 12 or not np.all(np.isfinite(values)):
            raise SequenceError(f"{path}:{number}: {len(values)} values; a pose is 12 finite numbers (r11 … r33 tx ty tz)")
        T = np.eye(4)
        T[:3, :3] = np.reshape(values[:9], (3, 3))
        T[:3, 3] = values[9:]
        try:
            checked_rotation(T[:3, :3], f"{path}:{number}: the rotation")
        except ValueError as e:
            raise SequenceError(str(e)) from e
        poses.append(T)
    if not poses or (n is not None and len(poses) < n):
        raise SequenceError(f"{path}: {len(poses)} poses for {n} frames")
    return np.stack(poses)


def read_rbot_calibration(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """(K (3, 3), dist (5,)) from RBOT's camera_calibration.txt: the first line of numbers gives fx fy cx cy and
    optionally k1 k2 p1 p2 (or they follow on the next line of numbers)."""
    path = pathlib.Path(path)
    if not path.is_file():
        raise SequenceError(f"{path}: RBOT camera calibration not found")
    rows = [v for v in (_numbers(line) for line in path.read_text().splitlines() if line.strip()) if v]
    if not rows or len(rows[0]) < 4:
        raise SequenceError(f"{path}: no line of at least four numbers fx fy cx cy")
    values = rows[0] + (rows[1] if len(rows[0]) == 4 and len(rows) > 1 else [])
    fx, fy, cx, cy = values[:4]
    if not (np.isfinite([fx, fy, cx, cy]).all() and fx > 0 and fy > 0):
        raise SequenceError(f"{path}: fx fy cx cy must be finite with fx, fy > 0, got {values[:4]}")
    dist = np.zeros(5)
    extra = values[4:8]
    dist[: len(extra)] = extra
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]), dist


def read_rbot_sequence(dataset: str | os.PathLike, obj: str, variant: str = "a_regular") -> Sequence:
    """One RBOT sequence (an object and a variant) as a `Sequence` for `track_sequence` / `track_objects`.

    Args:
        dataset: the RBOT folder (with poses_first.txt); obj: an object folder in it ("ape", "soda", ...);
        variant: a_regular, b_dynamiclight, c_noisy or d_occlusion (which adds the occluding squirrel as obj_id 2).

    Raises:
        SequenceError / ValueError: naming the missing file or folder, or the malformed line.
    """
    root = pathlib.Path(dataset)
    if variant not in RBOT_VARIANTS:
        raise ValueError(f"RBOT variant must be one of {', '.join(RBOT_VARIANTS)}, got {variant!r}")
    folder = root / obj / "frames"
    if not folder.is_dir():
        raise SequenceError(f"{folder}: no such RBOT frames folder (objects in {root}: "
                            f"{sorted(p.name for p in root.iterdir() if (p / 'frames').is_dir()) if root.is_dir() else []})")
    frames = numbered_frames(folder, variant)
    ids = [i for i, _ in frames]
    n = ids[-1] + 1
    mesh = root / obj / f"{obj}.obj"
    if not mesh.is_file():
        raise SequenceError(f"{mesh}: the object's mesh is missing")
    K, dist = read_rbot_calibration(root / "camera_calibration.txt")
    if np.any(dist != 0):
        raise SequenceError(f"{root / 'camera_calibration.txt'}: distortion {dist[:4].tolist()} given; RBOT's frames are "
                            "rendered without distortion and jaxtrack reads them as they are")
    poses = {1: read_rbot_poses(root / "poses_first.txt", n)[ids]}
    models = {1: mesh}
    if variant == "d_occlusion":
        occluder = root / f"{RBOT_OCCLUDER}.obj"
        if not occluder.is_file():
            raise SequenceError(f"{occluder}: the occluding object's mesh is missing (d_occlusion)")
        poses[2] = read_rbot_poses(root / "poses_second.txt", n)[ids]
        models[2] = occluder
    try:
        width, height = image_size(frames[0][1])
    except (FileNotFoundError, ValueError) as e:
        raise SequenceError(str(e)) from e
    view = CameraView(folder, [p for _, p in frames], K, np.eye(4), poses, int(width), int(height), ids)
    return Sequence(root / obj, models, [view])


def rbot_sequences(dataset: str | os.PathLike) -> list[tuple[str, str]]:
    """(object, variant) of every RBOT sequence in `dataset`, sorted: an object folder with its mesh and at least one
    frame of the variant in frames/ (the layout's 18 objects × 4 variants when complete)."""
    root = pathlib.Path(dataset)
    if not root.is_dir():
        raise SequenceError(f"{root}: no such RBOT folder")
    out = []
    for folder in sorted(p for p in root.iterdir() if (p / "frames").is_dir() and (p / f"{p.name}.obj").is_file()):
        names = {p.name for p in (folder / "frames").iterdir()}
        out += [(folder.name, v) for v in RBOT_VARIANTS
                if any(n.startswith(v) and n.endswith(".png") for n in names)]
    return out
