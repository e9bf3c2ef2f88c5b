"""BOP scene layout: read and write sequences (one folder per camera) and the BOP results CSV.

    SEQ/models/obj_000001.ply           mesh in mm (.ply/.obj/.stl/.glb through trimesh)
    SEQ/000000/rgb/000000.png ...       camera 0 frames (gray/ also accepted); 000001/ for camera 1
    SEQ/000000/scene_camera.json        {"0": {"cam_K": [9], "cam_R_w2c": [9], "cam_t_w2c": [3]}, ...}
    SEQ/000000/scene_gt.json            {"0": [{"obj_id": 1, "cam_R_m2c": [9], "cam_t_m2c": [3]}], ...}

Articulated objects: `models/obj_000001.urdf` (URDF, metres; read by `jaxtrack.io.read_urdf`), and each
scene_gt.json entry of it gives the root link's pose plus `"joints": {"<joint name>": value, ...}` for
its movable joints (radians; metres for prismatic joints, as URDF).

Frames are named by BOP image id and paired with the JSON entries by id, never by position: ids may
have gaps, an entry whose image is missing is an error naming the file, an image without ground truth
has unknown (NaN) poses. The first image's scene_gt.json entry is the initial pose; later entries, when
present, are ground truth. scene_camera.json holds one entry per image (or only the first); cam_K must
not change over a camera's frames, and all its frames must have one size.
"""

from __future__ import annotations

import dataclasses
import json
import os
import pathlib
from collections.abc import Iterable

import numpy as np
import numpy.typing as npt

from ..geometry import checked_array, checked_intrinsics, checked_rotation
from ._images import image_size, prepare_output_file, prepare_output_folder, read_image, write_image

MODEL_SUFFIXES = (".ply", ".obj", ".stl", ".glb", ".gltf", ".off", ".urdf")
FRAME_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif")
# Two cam_K of one camera are "the same" within this relative difference (JSON round trips of float32).
K_RTOL = 1e-6


class SequenceError(ValueError):
    """A sequence on disk is missing a file or has a malformed field (the message names which)."""


@dataclasses.dataclass
class CameraView:
    """One camera of a sequence: its frames and per-frame calibration / ground truth.

    BOP names frames by image id (000000.png, 000001.png, ...); ids may have gaps. Frame index i of
    every array here is the i-th image in id order, and `frame_ids[i]` is its id in the JSON files.

    Attributes:
        folder: the camera folder (SEQ/000000).
        frame_paths: image file of every frame, in id order.
        frame_ids: (num_frames,) BOP image id of every frame.
        K: (3, 3) intrinsics (BOP stores them per frame; checked equal over the sequence).
        T_cam_world: (4, 4) extrinsics of the first frame (identity when absent).
        T_cam_obj: dict obj_id -> (num_frames, 4, 4) ground-truth poses, NaN where unknown (the root
            link's pose for an articulated object).
        width, height: image size (checked equal for every frame).
        joints: dict obj_id -> {joint name: (num_frames,) values in URDF units, NaN where unknown}, for
            the objects whose scene_gt.json entries carry "joints".
    """

    folder: pathlib.Path
    frame_paths: list
    K: np.ndarray
    T_cam_world: np.ndarray
    T_cam_obj: dict
    width: int
    height: int
    frame_ids: list = dataclasses.field(default_factory=list)
    joints: dict = dataclasses.field(default_factory=dict)

    def read_frame(self, index: int, gray: bool = False, dtype=np.float32) -> np.ndarray:
        """Frame `index` (position, not id) as H×W×3 RGB (or H×W gray) in [0, 255], float32 by default
        (`dtype`; None keeps the file's, e.g. uint8, which the tracker moves and stores at a quarter of the bytes).

        Raises:
            SequenceError: naming the image file when it cannot be read or its size is not the view's.
        """
        if not -len(self.frame_paths) <= int(index) < len(self.frame_paths):
            raise IndexError(f"{self.folder}: frame index {index} out of range [0, {len(self.frame_paths)})")
        path = self.frame_paths[index]
        try:
            img = read_image(path, "grey" if gray else "rgb", dtype)
        except (FileNotFoundError, ValueError) as e:
            raise SequenceError(str(e)) from e
        if img.shape[:2] != (self.height, self.width):
            raise SequenceError(f"{path}: {img.shape[1]}x{img.shape[0]} pixels, the camera's frames are {self.width}x{self.height}")
        return img


@dataclasses.dataclass
class Sequence:
    """A BOP-layout sequence: meshes and one `CameraView` per camera.

    `model_scales`: obj_id → factor from the mesh file's unit to millimetres (1 when absent: BOP meshes are in
    mm; `jaxtrack.io.own_sequence` sets it from --mesh-unit)."""

    root: pathlib.Path
    model_paths: dict
    views: list
    model_scales: dict = dataclasses.field(default_factory=dict)

    def model_scale(self, obj_id: int) -> float:
        return float(self.model_scales.get(obj_id, 1.0))

    @property
    def num_frames(self) -> int:
        return len(self.views[0].frame_paths)


def _load_json(path: pathlib.Path):
    if not path.is_file():
        raise SequenceError(f"{path}: missing")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise SequenceError(f"{path}: malformed JSON ({e.msg} at line {e.lineno})") from e
    if not isinstance(data, dict):
        raise SequenceError(f"{path}: expected a JSON object keyed by frame id, got {type(data).__name__}")
    out = {}
    for key, value in data.items():
        if not key.isdigit():
            raise SequenceError(f"{path}: key {key!r} is not a frame id (a non-negative integer)")
        out[int(key)] = value
    return dict(sorted(out.items()))


def _field(entry, key, path, frame, size, what=""):
    """Field `key` of a JSON entry as `size` finite numbers; errors name file, frame and field."""
    name = f"{path}: frame {frame}{what} field '{key}'"
    if not isinstance(entry, dict) or key not in entry:
        raise SequenceError(f"{path}: frame {frame}{what} has no field '{key}'")
    try:
        return checked_array(entry[key], name, size=size)
    except ValueError as e:
        raise SequenceError(str(e)) from e


def _rotation(entry, key, path, frame, what=""):
    R = _field(entry, key, path, frame, 9, what)
    try:
        return checked_rotation(R, f"{path}: frame {frame}{what} field '{key}'")
    except ValueError as e:
        raise SequenceError(str(e)) from e


def _transform(R, t):
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = np.asarray(R).reshape(3, 3), t
    return T


def _frame_images(image_dir: pathlib.Path) -> dict:
    """Image id -> file, from BOP frame names (000000.png, ...), in id order."""
    images: dict = {}
    for p in sorted(image_dir.iterdir()):
        if p.suffix.lower() not in FRAME_SUFFIXES:
            continue
        if not p.stem.isdigit():
            raise SequenceError(f"{p}: frame images must be named by image id (000000{p.suffix}, 000001{p.suffix}, ...)")
        if int(p.stem) in images:
            raise SequenceError(f"{image_dir}: two images for frame {int(p.stem)}: {images[int(p.stem)].name} and {p.name}")
        images[int(p.stem)] = p
    if not images:
        raise SequenceError(f"{image_dir}: no images ({', '.join(FRAME_SUFFIXES)})")
    return dict(sorted(images.items()))


def _missing_images(json_path, ids, images: dict, image_dir: pathlib.Path, count_msg: str) -> None:
    """Error naming the image files of frames that `json_path` describes but that do not exist."""
    missing = [i for i in ids if i not in images]
    if missing:
        first = next(iter(images.values()))
        names = ", ".join(f"{i:0{len(first.stem)}d}{first.suffix}" for i in missing[:5]) + (", ..." if len(missing) > 5 else "")
        raise SequenceError(f"{json_path}: {count_msg}; no image for frame(s) {', '.join(map(str, missing[:5]))} "
                            f"in {image_dir} (missing {names})")


def read_camera_view(folder: str | os.PathLike) -> CameraView:
    """One camera folder of a BOP sequence (see the module docstring for the layout).

    Ground truth and calibration are paired with images by image id; a JSON entry whose image is
    missing, a frame of another size, a cam_K that changes between frames, a zero/singular K or a
    cam_R_* that is not a rotation is an error naming the file, frame and field.

    Raises:
        SequenceError: as above.
    """
    folder = pathlib.Path(folder)
    image_dir = next((folder / d for d in ("rgb", "gray") if (folder / d).is_dir()), None)
    if image_dir is None:
        raise SequenceError(f"{folder}: no rgb/ or gray/ image folder")
    images = _frame_images(image_dir)
    ids = list(images)
    first = ids[0]

    cam_path = folder / "scene_camera.json"
    cams = _load_json(cam_path)
    if first not in cams:
        raise SequenceError(f"{cam_path}: no entry for frame {first} (the first image, {images[first].name})")
    _missing_images(cam_path, cams, images, image_dir, f"{len(cams)} entries for {len(images)} images")
    if len(cams) > 1:  # per-frame calibration (BOP): every image needs its entry
        lacking = [i for i in ids if i not in cams]
        if lacking:
            raise SequenceError(f"{cam_path}: no entry for frame {lacking[0]} ({images[lacking[0]].name}); "
                                f"give one entry per image or only the first")
    K = None
    for frame, entry in cams.items():
        K_frame = _field(entry, "cam_K", cam_path, frame, 9)
        try:
            K_frame = checked_intrinsics(K_frame, f"{cam_path}: frame {frame} field 'cam_K'")
        except ValueError as e:
            raise SequenceError(str(e)) from e
        if K is None:
            K = K_frame
        elif not np.allclose(K_frame, K, rtol=K_RTOL, atol=0):
            raise SequenceError(f"{cam_path}: frame {frame} field 'cam_K' {K_frame.ravel().tolist()} differs from frame "
                                f"{first}'s {K.ravel().tolist()}; a camera must keep one K over the sequence")
        if "cam_R_w2c" in entry:
            _rotation(entry, "cam_R_w2c", cam_path, frame)
        if "cam_t_w2c" in entry:
            _field(entry, "cam_t_w2c", cam_path, frame, 3)
    entry0 = cams[first]
    R = _rotation(entry0, "cam_R_w2c", cam_path, first) if "cam_R_w2c" in entry0 else np.eye(3)
    t = _field(entry0, "cam_t_w2c", cam_path, first, 3) if "cam_t_w2c" in entry0 else np.zeros(3)

    gt_path = folder / "scene_gt.json"
    gt = _load_json(gt_path)
    if first not in gt:
        raise SequenceError(f"{gt_path}: no entry for frame {first} (the initial pose; first image {images[first].name})")
    _missing_images(gt_path, gt, images, image_dir, f"{len(gt)} frames of ground truth for {len(images)} images")
    index = {frame: i for i, frame in enumerate(ids)}
    poses: dict = {}
    joints: dict = {}
    for frame, objects in gt.items():
        if not isinstance(objects, list):
            raise SequenceError(f"{gt_path}: frame {frame} must hold a list of objects, got {type(objects).__name__}")
        for n, obj in enumerate(objects):
            if not isinstance(obj, dict) or "obj_id" not in obj:
                raise SequenceError(f"{gt_path}: frame {frame} object #{n} has no 'obj_id'")
            try:
                obj_id = int(obj["obj_id"])
            except (TypeError, ValueError):
                raise SequenceError(f"{gt_path}: frame {frame} object #{n} field 'obj_id' must be an integer, got {obj['obj_id']!r}") from None
            what = f" object {obj_id}"
            R_m2c = _rotation(obj, "cam_R_m2c", gt_path, frame, what)
            t_m2c = _field(obj, "cam_t_m2c", gt_path, frame, 3, what)
            arr = poses.setdefault(obj_id, np.full((len(ids), 4, 4), np.nan))
            if np.isfinite(arr[index[frame]]).all():
                raise SequenceError(f"{gt_path}: frame {frame} has two instances of obj_id {obj_id}; "
                                    f"jaxtrack tracks one instance per object")
            arr[index[frame]] = _transform(R_m2c, t_m2c)
            if "joints" in obj:
                _read_joints(obj["joints"], joints.setdefault(obj_id, {}), index[frame], len(ids), gt_path, frame, what)

    # Every frame must have the first frame's size: a stray frame would break the renderer's static
    # shapes (or, resized, every pose). Only headers are read.
    try:
        width, height = image_size(images[first])
        for frame in ids[1:]:
            size = image_size(images[frame])
            if size != (width, height):
                raise SequenceError(f"{images[frame]}: {size[0]}x{size[1]} pixels, but frame {first} "
                                    f"({images[first].name}) is {width}x{height}; all frames of a camera must have one size")
    except (FileNotFoundError, ValueError) as e:
        raise SequenceError(str(e)) from e
    cx, cy = float(K[0, 2]), float(K[1, 2])
    if not (-0.5 <= cx <= width - 0.5 and -0.5 <= cy <= height - 0.5):
        raise SequenceError(f"{cam_path}: frame {first} field 'cam_K' puts the principal point at ({cx:g}, {cy:g}), outside the "
                            f"{width}x{height} images: a calibration for another resolution, or cam_K not row-major "
                            "[fx, 0, cx, 0, fy, cy, 0, 0, 1]?")
    return CameraView(folder, list(images.values()), K, _transform(R, t), poses, width, height, ids, joints)


def _read_joints(values, into: dict, i: int, n: int, gt_path, frame, what) -> None:
    """One scene_gt.json "joints" object into `into` ({name: (n,) NaN-filled}) at frame position i."""
    if not isinstance(values, dict):
        raise SequenceError(f"{gt_path}: frame {frame}{what} field 'joints' must be an object "
                            f"{{joint name: value}}, got {type(values).__name__}")
    for name, value in values.items():
        if isinstance(value, bool) or not isinstance(value, int | float) or not np.isfinite(value):
            raise SequenceError(f"{gt_path}: frame {frame}{what} joint {name!r} must be a finite number, got {value!r}")
        into.setdefault(name, np.full(n, np.nan))[i] = float(value)


def _model_paths(models_dir: pathlib.Path) -> dict:
    """obj_id → the obj_XXXXXX mesh file in `models_dir`."""
    if not models_dir.is_dir():
        raise SequenceError(f"{models_dir}: missing (the object meshes)")
    model_paths = {}
    for p in sorted(models_dir.iterdir()):
        if p.suffix.lower() in MODEL_SUFFIXES and p.stem.startswith("obj_") and p.stem[4:].isdigit():
            if int(p.stem[4:]) in model_paths:
                raise SequenceError(f"{models_dir}: two meshes for object {int(p.stem[4:])}: {model_paths[int(p.stem[4:])].name} and {p.name}")
            model_paths[int(p.stem[4:])] = p
    if not model_paths:
        raise SequenceError(f"{models_dir}: no obj_XXXXXX mesh ({', '.join(MODEL_SUFFIXES)})")
    return model_paths


def bop_scenes(dataset: str | os.PathLike) -> list[tuple[str, str]]:
    """(split, scene) of every scene of a BOP dataset as the BOP toolkit lays it out: DATASET/models/obj_XXXXXX.ply
    and DATASET/<split>/<scene>/ with rgb/ (or gray/), scene_camera.json and scene_gt.json (test, val, test_primesense,
    ...), sorted."""
    root = pathlib.Path(dataset)
    if not (root / "models").is_dir():
        return []
    out = []
    for split in sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith("models")):
        out += [(split.name, scene.name) for scene in sorted(split.iterdir())
                if scene.is_dir() and scene.name.isdigit() and (scene / "scene_gt.json").is_file()]
    return out


def read_bop_scene(dataset: str | os.PathLike, split: str, scene: str) -> Sequence:
    """One scene of a BOP dataset in the BOP toolkit's layout (`bop_scenes`) as a one-camera `Sequence`: its meshes
    from DATASET/models, its frames, calibration and ground truth from DATASET/<split>/<scene> (which is laid out as
    this project's camera folder). Every object of the scene can be tracked (one instance per object and frame).

    Raises:
        SequenceError: naming the missing folder or file, or the malformed field.
    """
    root = pathlib.Path(dataset)
    folder = root / split / scene
    if not folder.is_dir():
        raise SequenceError(f"{folder}: no such BOP scene folder (scenes in {root}: {bop_scenes(root)[:6]})")
    model_paths = _model_paths(root / "models")
    view = read_camera_view(folder)
    for obj_id in view.T_cam_obj:
        if obj_id not in model_paths:
            raise SequenceError(f"{folder / 'scene_gt.json'}: obj_id {obj_id} has no mesh {root}/models/obj_{obj_id:06d}.*")
    return Sequence(folder, model_paths, [view])


def read_sequence(root: str | os.PathLike) -> Sequence:
    """Read a BOP-layout sequence folder (meshes are located, not loaded: see `load_mesh`).

    Raises:
        SequenceError: naming the missing file, the malformed JSON or field, or mismatched frames.
    """
    root = pathlib.Path(root)
    if not root.is_dir():
        raise SequenceError(f"{root}: not a directory")
    model_paths = _model_paths(root / "models")
    cam_dirs = sorted(p for p in root.iterdir() if p.is_dir() and p.name.isdigit())
    if not cam_dirs:
        raise SequenceError(f"{root}: no camera folder (000000/)")
    views = [read_camera_view(d) for d in cam_dirs]
    counts = {len(v.frame_paths) for v in views}
    if len(counts) != 1:
        raise SequenceError(f"{root}: cameras have different frame counts {sorted(counts)}")
    for v in views[1:]:
        if v.frame_ids != views[0].frame_ids:
            frame = next(a for a, b in zip(v.frame_ids, views[0].frame_ids) if a != b)
            raise SequenceError(f"{v.folder}: frame ids differ from {views[0].folder.name}'s (first difference at id {frame})")
    for v in views:
        for obj_id in v.T_cam_obj:
            if obj_id not in model_paths:
                raise SequenceError(f"{v.folder / 'scene_gt.json'}: obj_id {obj_id} has no mesh models/obj_{obj_id:06d}.*")
    return Sequence(root, model_paths, views)


def write_camera_view(
    folder: str | os.PathLike,
    images: npt.ArrayLike,
    K: npt.ArrayLike,
    T_cam_obj: dict,
    T_cam_world: npt.ArrayLike | None = None,
    gray: bool = False,
    joints: dict | None = None,
) -> pathlib.Path:
    """Write one camera of a sequence in the BOP layout (frames 000000.png, ... and the two JSON files).

    Args:
        folder: the camera folder (created with its parents).
        images: (N, H, W) or (N, H, W, 3) RGB in [0, 255] (clipped, rounded down to uint8).
        K: (3, 3) or 9 intrinsics.
        T_cam_obj: obj_id -> (N, 4, 4) poses in mm; frames with non-finite poses get no ground truth.
        T_cam_world: (4, 4) extrinsics (identity when None).
        gray: write to gray/ instead of rgb/.
        joints: obj_id -> {joint name: (N,) values in URDF units (radians, metres)} for articulated
            objects, written as each frame's "joints" object.

    Raises:
        ValueError: naming the argument or path that is wrong.
    """
    images = np.asarray(images)
    if images.ndim not in (3, 4) or (images.ndim == 4 and images.shape[3] != 3) or len(images) == 0:
        raise ValueError(f"write_camera_view: images must be (N, H, W) or (N, H, W, 3) with N ≥ 1, got shape {images.shape}")
    if not np.issubdtype(images.dtype, np.number):
        raise ValueError(f"write_camera_view: images must be numeric, got dtype {images.dtype}")
    K = checked_intrinsics(K, "write_camera_view: K")
    n = len(images)
    for obj_id, poses in T_cam_obj.items():
        if np.shape(poses) != (n, 4, 4):
            raise ValueError(f"write_camera_view: T_cam_obj[{obj_id!r}] must be ({n}, 4, 4) for {n} images, got {np.shape(poses)}")
    joints = {} if joints is None else joints
    for obj_id, values in joints.items():
        if obj_id not in T_cam_obj:
            raise ValueError(f"write_camera_view: joints[{obj_id!r}] names an object without poses in T_cam_obj")
        for name, v in values.items():
            if np.shape(v) != (n,) or not np.all(np.isfinite(np.asarray(v, float))):
                raise ValueError(f"write_camera_view: joints[{obj_id!r}][{name!r}] must be {n} finite values, got shape {np.shape(v)}")
    T_cam_world = np.eye(4) if T_cam_world is None else checked_array(T_cam_world, "write_camera_view: T_cam_world")
    if T_cam_world.shape != (4, 4):
        raise ValueError(f"write_camera_view: T_cam_world must be (4, 4), got {T_cam_world.shape}")
    checked_rotation(T_cam_world[:3, :3], "write_camera_view: T_cam_world[:3, :3]")
    folder = prepare_output_folder(folder, "write_camera_view: folder")
    image_dir = prepare_output_folder(folder / ("gray" if gray else "rgb"), "write_camera_view: image folder")
    cams, gts = {}, {}
    for i, img in enumerate(images):
        write_image(image_dir / f"{i:06d}.png", np.clip(img, 0, 255).astype(np.uint8), "write_camera_view")
        cams[str(i)] = {
            "cam_K": K.ravel().tolist(),
            "cam_R_w2c": T_cam_world[:3, :3].ravel().tolist(),
            "cam_t_w2c": T_cam_world[:3, 3].tolist(),
            "depth_scale": 1.0,
        }
        objs = []
        for obj_id, poses in T_cam_obj.items():
            T = np.asarray(poses[i], np.float64)
            if np.all(np.isfinite(T)):
                objs.append({"obj_id": int(obj_id), "cam_R_m2c": T[:3, :3].ravel().tolist(), "cam_t_m2c": T[:3, 3].tolist()})
                if obj_id in joints:
                    objs[-1]["joints"] = {name: float(v[i]) for name, v in joints[obj_id].items()}
        gts[str(i)] = objs
    (folder / "scene_camera.json").write_text(json.dumps(cams, indent=1))
    (folder / "scene_gt.json").write_text(json.dumps(gts, indent=1))
    return folder


RESULT_HEADER = "scene_id,im_id,obj_id,score,R,t,time"


def write_bop_results(path: str | os.PathLike, rows: Iterable[tuple]) -> pathlib.Path:
    """Write the BOP results CSV (parent folders created).

    Args:
        path: the .csv file.
        rows: iterable of (scene_id, im_id, obj_id, score, T (4, 4) mm, time s).

    Raises:
        ValueError: naming the path, or the row and field that is malformed.
    """
    path = prepare_output_file(path, "write_bop_results: path")
    lines = [RESULT_HEADER]
    for n, row in enumerate(rows):
        if len(row) != 6:
            raise ValueError(f"write_bop_results: row {n} must be (scene_id, im_id, obj_id, score, T, time), got {len(row)} values")
        scene_id, im_id, obj_id, score, T, seconds = row
        T = checked_array(T, f"write_bop_results: row {n} T")
        if T.shape != (4, 4):
            raise ValueError(f"write_bop_results: row {n} T must be (4, 4), got {T.shape}")
        lines.append(bop_result_line(scene_id, im_id, obj_id, score, T, seconds))
    path.write_text("\n".join(lines) + "\n")
    return path


def bop_result_line(scene_id, im_id, obj_id, score, T, seconds) -> str:
    """One row of the BOP results CSV (no newline): T (4, 4) a checked model → camera pose in mm."""
    R = " ".join(f"{v:.8f}" for v in T[:3, :3].ravel())
    t = " ".join(f"{v:.6f}" for v in T[:3, 3])
    return f"{int(scene_id)},{int(im_id)},{int(obj_id)},{float(score):.6f},{R},{t},{float(seconds):.6f}"


def read_bop_results(path: str | os.PathLike) -> list:
    """Read a BOP results CSV into a list of (scene_id, im_id, obj_id, score, T (4, 4), time).

    Raises:
        SequenceError: naming the file and line of a malformed row (field count, numbers, R not a rotation).
    """
    path = pathlib.Path(path)
    if path.is_dir():
        raise SequenceError(f"{path}: is a folder; expected the results CSV (jaxtrack track -o)")
    if not path.is_file():
        raise SequenceError(f"{path}: missing")
    lines = path.read_text(encoding="utf-8-sig").strip().splitlines()  # a BOM from a spreadsheet is not part of the header
    if not lines or lines[0].strip() != RESULT_HEADER:
        raise SequenceError(f"{path}: header must be '{RESULT_HEADER}'")
    rows = []
    for n, line in enumerate(lines[1:], start=2):
        parts = line.split(",")
        if len(parts) != 7:
            raise SequenceError(f"{path}:{n}: expected 7 comma-separated fields, got {len(parts)}")
        try:
            ids = [int(parts[0]), int(parts[1]), int(parts[2])]
            score, seconds = float(parts[3]), float(parts[6])
            R = np.array(parts[4].split(), float)
            t = np.array(parts[5].split(), float)
        except ValueError as e:
            raise SequenceError(f"{path}:{n}: malformed number ({e})") from e
        if R.size != 9 or t.size != 3:
            raise SequenceError(f"{path}:{n}: R needs 9 values and t 3, got {R.size} and {t.size}")
        try:
            R = checked_rotation(R, f"{path}:{n}: R")
            t = checked_array(t, f"{path}:{n}: t", size=3)
        except ValueError as e:
            raise SequenceError(str(e)) from e
        rows.append((*ids, score, _transform(R, t), seconds))
    return rows


def frame_step_sequence(seq: Sequence, step: int, start: int = 0) -> Sequence:
    """Every `step`-th frame of `seq` from `start` (the RBOT protocol's frame steps S: the same motion at 1/S the
    frame rate), as a new `Sequence` over the same files; image ids, poses and joints follow the frames kept.

    Raises:
        ValueError: `step` < 1, or `start` outside the sequence.
    """
    step, start = int(step), int(start)
    if step < 1:
        raise ValueError(f"frame step must be ≥ 1, got {step}")
    if not 0 <= start < seq.num_frames:
        raise ValueError(f"start frame {start} outside the {seq.num_frames} frames of {seq.root}")
    keep = np.arange(start, seq.num_frames, step)
    views = [dataclasses.replace(
        v, frame_paths=[v.frame_paths[k] for k in keep], frame_ids=[v.frame_ids[k] for k in keep],
        T_cam_obj={o: np.asarray(T)[keep] for o, T in v.T_cam_obj.items()},
        joints={o: {name: np.asarray(x)[keep] for name, x in js.items()} for o, js in v.joints.items()},
    ) for v in seq.views]
    return dataclasses.replace(seq, views=views)
