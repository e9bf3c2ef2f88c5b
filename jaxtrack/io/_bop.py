"""BOP scene layout: read and write sequences (one folder per camera) and the BOP results CSV.

    SEQ/models/obj_000001.ply           mesh in mm (.ply/.obj/.stl/.glb through trimesh)
    SEQ/000000/rgb/000000.png ...       camera 0 frames (gray/ also accepted); 000001/ for camera 1
    SEQ/000000/scene_camera.json        {"0": {"cam_K": [9], "cam_R_w2c": [9], "cam_t_w2c": [3]}, ...}
    SEQ/000000/scene_gt.json            {"0": [{"obj_id": 1, "cam_R_m2c": [9], "cam_t_m2c": [3]}], ...}

Frame 0 of scene_gt.json is the initial pose; later frames, when present, are ground truth.
"""

from __future__ import annotations

import dataclasses
import json
import pathlib

import cv2
import numpy as np

MODEL_SUFFIXES = (".ply", ".obj", ".stl", ".glb", ".gltf", ".off")


class SequenceError(ValueError):
    """A sequence on disk is missing a file or has a malformed field (the message names which)."""


@dataclasses.dataclass
class CameraView:
    """One camera of a sequence: its frames and per-frame calibration / ground truth.

    Attributes:
        folder: the camera folder (SEQ/000000).
        frame_paths: image file of every frame, in frame order.
        K: (3, 3) intrinsics (of frame 0; BOP stores them per frame, checked constant).
        T_cam_world: (4, 4) extrinsics (identity when absent).
        T_cam_obj: dict obj_id -> (num_frames, 4, 4) ground-truth poses, NaN where unknown.
        width, height: image size.
    """

    folder: pathlib.Path
    frame_paths: list
    K: np.ndarray
    T_cam_world: np.ndarray
    T_cam_obj: dict
    width: int
    height: int

    def read_frame(self, index: int, gray: bool = False) -> np.ndarray:
        """Frame `index` as float32 H×W×3 RGB (or H×W gray) in [0, 255]."""
        path = self.frame_paths[index]
        img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE if gray else cv2.IMREAD_COLOR)
        if img is None:
            raise SequenceError(f"{path}: cannot read image")
        if not gray:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
        return img.astype(np.float32)


@dataclasses.dataclass
class Sequence:
    """A BOP-layout sequence: meshes and one `CameraView` per camera."""

    root: pathlib.Path
    model_paths: dict
    views: list

    @property
    def num_frames(self) -> int:
        return len(self.views[0].frame_paths)


def _load_json(path: pathlib.Path):
    if not path.is_file():
        raise SequenceError(f"{path}: missing")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise SequenceError(f"{path}: malformed JSON ({e.msg} at line {e.lineno})") from e


def _matrix(entry, key, shape, path, frame):
    if key not in entry:
        raise SequenceError(f"{path}: frame {frame} has no field '{key}'")
    arr = np.asarray(entry[key], np.float64)
    if arr.size != int(np.prod(shape)) or not np.all(np.isfinite(arr)):
        raise SequenceError(f"{path}: frame {frame} field '{key}' must hold {int(np.prod(shape))} finite numbers, got {arr.size}")
    return arr.reshape(shape)


def _transform(R, t):
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def read_camera_view(folder: pathlib.Path) -> CameraView:
    folder = pathlib.Path(folder)
    image_dir = next((folder / d for d in ("rgb", "gray") if (folder / d).is_dir()), None)
    if image_dir is None:
        raise SequenceError(f"{folder}: no rgb/ or gray/ image folder")
    frames = sorted(p for p in image_dir.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg", ".tif"))
    if not frames:
        raise SequenceError(f"{image_dir}: no images")
    cam_path = folder / "scene_camera.json"
    cams = _load_json(cam_path)
    if str(0) not in cams:
        raise SequenceError(f"{cam_path}: no entry for frame 0")
    K = _matrix(cams["0"], "cam_K", (3, 3), cam_path, 0)
    R = _matrix(cams["0"], "cam_R_w2c", (3, 3), cam_path, 0) if "cam_R_w2c" in cams["0"] else np.eye(3)
    t = _matrix(cams["0"], "cam_t_w2c", (3,), cam_path, 0) if "cam_t_w2c" in cams["0"] else np.zeros(3)
    if len(cams) not in (1, len(frames)):
        raise SequenceError(f"{cam_path}: {len(cams)} entries for {len(frames)} frames in {image_dir}")
    gt_path = folder / "scene_gt.json"
    gt = _load_json(gt_path)
    if "0" not in gt:
        raise SequenceError(f"{gt_path}: no entry for frame 0 (the initial pose)")
    if len(gt) > len(frames):
        raise SequenceError(f"{gt_path}: {len(gt)} frames of ground truth for {len(frames)} images in {image_dir}")
    poses: dict = {}
    for key, objects in gt.items():
        frame = int(key)
        if not 0 <= frame < len(frames):
            raise SequenceError(f"{gt_path}: frame {frame} out of range [0, {len(frames)})")
        for obj in objects:
            if "obj_id" not in obj:
                raise SequenceError(f"{gt_path}: frame {frame} has an object without 'obj_id'")
            R_m2c = _matrix(obj, "cam_R_m2c", (3, 3), gt_path, frame)
            t_m2c = _matrix(obj, "cam_t_m2c", (3,), gt_path, frame)
            arr = poses.setdefault(int(obj["obj_id"]), np.full((len(frames), 4, 4), np.nan))
            arr[frame] = _transform(R_m2c, t_m2c)
    first = cv2.imread(str(frames[0]), cv2.IMREAD_UNCHANGED)
    if first is None:
        raise SequenceError(f"{frames[0]}: cannot read image")
    return CameraView(folder, frames, K, _transform(R, t), poses, first.shape[1], first.shape[0])


def read_sequence(root) -> Sequence:
    """Read a BOP-layout sequence folder (meshes are located, not loaded: see `load_mesh`).

    Raises:
        SequenceError: naming the missing file, the malformed JSON or field, or mismatched counts.
    """
    root = pathlib.Path(root)
    if not root.is_dir():
        raise SequenceError(f"{root}: not a directory")
    models_dir = root / "models"
    if not models_dir.is_dir():
        raise SequenceError(f"{models_dir}: missing (the object meshes)")
    model_paths = {}
    for p in sorted(models_dir.iterdir()):
        if p.suffix.lower() in MODEL_SUFFIXES and p.stem.startswith("obj_"):
            model_paths[int(p.stem[4:])] = p
    if not model_paths:
        raise SequenceError(f"{models_dir}: no obj_XXXXXX mesh ({', '.join(MODEL_SUFFIXES)})")
    cam_dirs = sorted(p for p in root.iterdir() if p.is_dir() and p.name.isdigit())
    if not cam_dirs:
        raise SequenceError(f"{root}: no camera folder (000000/)")
    views = [read_camera_view(d) for d in cam_dirs]
    counts = {len(v.frame_paths) for v in views}
    if len(counts) != 1:
        raise SequenceError(f"{root}: cameras have different frame counts {sorted(counts)}")
    return Sequence(root, model_paths, views)


def write_camera_view(folder, images, K, T_cam_obj: dict, T_cam_world=None, gray=False):
    """Write one camera of a sequence: images (N, H, W[, 3]) in [0, 255] RGB, K (3, 3), poses per object."""
    folder = pathlib.Path(folder)
    image_dir = folder / ("gray" if gray else "rgb")
    image_dir.mkdir(parents=True, exist_ok=True)
    T_cam_world = np.eye(4) if T_cam_world is None else np.asarray(T_cam_world)
    cams, gts = {}, {}
    for i, img in enumerate(images):
        img = np.clip(np.asarray(img), 0, 255).astype(np.uint8)
        if img.ndim == 3:
            img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
        cv2.imwrite(str(image_dir / f"{i:06d}.png"), img)
        cams[str(i)] = {
            "cam_K": np.asarray(K, float).ravel().tolist(),
            "cam_R_w2c": T_cam_world[:3, :3].ravel().tolist(),
            "cam_t_w2c": T_cam_world[:3, 3].tolist(),
            "depth_scale": 1.0,
        }
        objs = []
        for obj_id, poses in T_cam_obj.items():
            T = np.asarray(poses[i])
            if np.all(np.isfinite(T)):
                objs.append({"obj_id": int(obj_id), "cam_R_m2c": T[:3, :3].ravel().tolist(), "cam_t_m2c": T[:3, 3].tolist()})
        gts[str(i)] = objs
    (folder / "scene_camera.json").write_text(json.dumps(cams, indent=1))
    (folder / "scene_gt.json").write_text(json.dumps(gts, indent=1))


RESULT_HEADER = "scene_id,im_id,obj_id,score,R,t,time"


def write_bop_results(path, rows):
    """Write the BOP results CSV. rows: iterable of (scene_id, im_id, obj_id, score, T (4, 4) mm, time s)."""
    lines = [RESULT_HEADER]
    for scene_id, im_id, obj_id, score, T, seconds in rows:
        T = np.asarray(T, np.float64)
        R = " ".join(f"{v:.8f}" for v in T[:3, :3].ravel())
        t = " ".join(f"{v:.6f}" for v in T[:3, 3])
        lines.append(f"{int(scene_id)},{int(im_id)},{int(obj_id)},{float(score):.6f},{R},{t},{float(seconds):.6f}")
    pathlib.Path(path).write_text("\n".join(lines) + "\n")


def read_bop_results(path):
    """Read a BOP results CSV into a list of (scene_id, im_id, obj_id, score, T (4, 4), time)."""
    path = pathlib.Path(path)
    if not path.is_file():
        raise SequenceError(f"{path}: missing")
    lines = path.read_text().strip().splitlines()
    if not lines or lines[0].strip() != RESULT_HEADER:
        raise SequenceError(f"{path}: header must be '{RESULT_HEADER}'")
    rows = []
    for n, line in enumerate(lines[1:], start=2):
        parts = line.split(",")
        if len(parts) != 7:
            raise SequenceError(f"{path}:{n}: expected 7 comma-separated fields, got {len(parts)}")
        R = np.array(parts[4].split(), float)
        t = np.array(parts[5].split(), float)
        if R.size != 9 or t.size != 3:
            raise SequenceError(f"{path}:{n}: R needs 9 values and t 3, got {R.size} and {t.size}")
        rows.append((int(parts[0]), int(parts[1]), int(parts[2]), float(parts[3]), _transform(R.reshape(3, 3), t), float(parts[6])))
    return rows
