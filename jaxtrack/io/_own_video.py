"""Your own footage as a sequence: a video file or a folder of images, an OpenCV calibration file, a mesh.

`own_sequence` wraps them as a `Sequence` (one camera, no ground truth) that `track_sequence` and
`jaxtrack track` read like a BOP folder. Frames are undistorted where they are read (`cv2.remap` with
maps computed once, keeping K), so the tracker sees a pinhole camera: the cues need no distortion model,
and a pose found on the undistorted frame is the pose in the camera.

Calibration files: what `cv2.FileStorage` writes (YAML or XML) with `camera_matrix`,
`distortion_coefficients`, `image_width`, `image_height` (OpenCV's calibration sample), or a JSON object
with `K` (3x3, or fx fy cx cy) and optional `dist` (4, 5, 8, 12 or 14 OpenCV coefficients), `width`,
`height` (the FileStorage names are accepted in JSON too).
"""

from __future__ import annotations

import dataclasses
import json
import os
import pathlib

import numpy as np

from ._bop import MODEL_SUFFIXES, CameraView, Sequence, SequenceError

VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".ppm", ".pgm")
MESH_UNITS = {"mm": 1.0, "cm": 10.0, "m": 1000.0}


@dataclasses.dataclass(frozen=True)
class CameraCalibration:
    """A pinhole camera with OpenCV's lens distortion.

    Attributes:
        K: (3, 3) intrinsics (pixels). dist: (D,) OpenCV distortion coefficients (k1 k2 p1 p2 [k3 ...]), D ≥ 4.
        width, height: the image size the calibration is for (None when the file does not say).
        source: the file it was read from (for messages).
    """

    K: np.ndarray
    dist: np.ndarray
    width: int | None
    height: int | None
    source: str = ""

    @property
    def distorted(self) -> bool:
        return bool(np.any(self.dist != 0))


def _as_matrix(value, name: str, source) -> np.ndarray:
    try:
        a = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{source}: field '{name}' must be numbers, got {value!r}") from None
    if a.size == 4 and name in ("K", "camera_matrix"):  # fx fy cx cy
        fx, fy, cx, cy = a.reshape(-1)
        a = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    if a.size != 9:
        raise ValueError(f"{source}: field '{name}' must be a 3x3 matrix (or fx fy cx cy), got {a.size} number(s)")
    a = a.reshape(3, 3)
    if not np.all(np.isfinite(a)) or a[0, 0] <= 0 or a[1, 1] <= 0 or not np.allclose(a[2], [0, 0, 1]) or a[1, 0] != 0:
        raise ValueError(f"{source}: field '{name}' is not a camera matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with "
                         f"fx, fy > 0: {a.tolist()}")
    return a


def _as_distortion(value, name: str, source) -> np.ndarray:
    try:
        d = np.asarray(value, np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise ValueError(f"{source}: field '{name}' must be numbers, got {value!r}") from None
    if d.size not in (0, 4, 5, 8, 12, 14) or not np.all(np.isfinite(d)):
        raise ValueError(f"{source}: field '{name}' must hold 4, 5, 8, 12 or 14 finite OpenCV coefficients, got {d.size}")
    return np.zeros(5) if d.size == 0 else d


def _as_size(value, name: str, source) -> int | None:
    if value is None:
        return None
    try:
        v = float(np.asarray(value, np.float64).reshape(-1)[0])
    except (TypeError, ValueError, IndexError):
        raise ValueError(f"{source}: field '{name}' must be a positive integer, got {value!r}") from None
    if not (np.isfinite(v) and v >= 1 and v == int(v)):
        raise ValueError(f"{source}: field '{name}' must be a positive integer, got {value!r}")
    return int(v)


def read_calibration(path: str | os.PathLike) -> CameraCalibration:
    """A `CameraCalibration` from an OpenCV FileStorage file (.yaml, .yml, .xml) or a JSON file.

    Raises:
        FileNotFoundError: naming the file. ValueError: naming the file and the missing or malformed field.
    """
    path = pathlib.Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: calibration file not found" + (" (it is a folder)" if path.is_dir() else ""))
    suffix = path.suffix.lower()
    if suffix == ".json":
        try:
            data = json.loads(path.read_text(encoding="utf-8-sig"))
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise ValueError(f"{path}: not readable as JSON ({e})") from None
        if not isinstance(data, dict):
            raise ValueError(f"{path}: expected a JSON object with 'K' (or 'camera_matrix'), got {type(data).__name__}")
        k_name = "K" if "K" in data else "camera_matrix"
        if k_name not in data:
            raise ValueError(f"{path}: no field 'K' (or 'camera_matrix'): the 3x3 intrinsics")
        d_name = next((n for n in ("dist", "distortion_coefficients", "D") if n in data), None)
        w_name = "width" if "width" in data else "image_width"
        h_name = "height" if "height" in data else "image_height"
        return CameraCalibration(_as_matrix(data[k_name], k_name, path),
                                 _as_distortion(data[d_name] if d_name else [], d_name or "dist", path),
                                 _as_size(data.get(w_name), w_name, path), _as_size(data.get(h_name), h_name, path), str(path))
    if suffix not in (".yaml", ".yml", ".xml"):
        raise ValueError(f"{path}: a calibration file is .yaml/.yml/.xml (cv2.FileStorage) or .json, got '{suffix}'")
    import cv2  # lazily: `import jaxtrack` must not load OpenCV

    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except cv2.error as e:
        raise ValueError(f"{path}: not readable by cv2.FileStorage ({str(e).strip().splitlines()[-1]})") from None
    try:
        if not fs.isOpened():
            raise ValueError(f"{path}: not readable by cv2.FileStorage")

        def node(name):
            n = fs.getNode(name)
            return None if n.empty() else n

        k = node("camera_matrix") or node("K")
        if k is None or k.mat() is None:
            raise ValueError(f"{path}: no field 'camera_matrix' (a 3x3 !!opencv-matrix)")
        d = node("distortion_coefficients") or node("dist_coeffs") or node("D")
        dist = _as_distortion(d.mat() if d is not None and d.mat() is not None else [], "distortion_coefficients", path)
        sizes = []
        for name in ("image_width", "image_height"):
            n = node(name)
            sizes.append(None if n is None else _as_size(n.real(), name, path))
        return CameraCalibration(_as_matrix(k.mat(), "camera_matrix", path), dist, sizes[0], sizes[1], str(path))
    finally:
        fs.release()


def write_calibration(path: str | os.PathLike, K, dist, width: int, height: int) -> pathlib.Path:
    """Write an OpenCV FileStorage calibration file (.yaml/.yml/.xml), as OpenCV's calibration sample does."""
    import cv2  # lazily: `import jaxtrack` must not load OpenCV

    path = pathlib.Path(path)
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", int(width))
    fs.write("image_height", int(height))
    fs.write("camera_matrix", np.asarray(K, np.float64))
    fs.write("distortion_coefficients", np.asarray(dist, np.float64).reshape(-1, 1))
    fs.release()
    return path


class _Undistorter:
    """Remaps frames of one size to the pinhole camera with the same K (maps made once)."""

    def __init__(self, calib: CameraCalibration, width: int, height: int):
        import cv2  # lazily: `import jaxtrack` must not load OpenCV

        self.maps = None
        if calib.distorted:
            self.maps = cv2.initUndistortRectifyMap(calib.K, calib.dist, None, calib.K, (width, height), cv2.CV_32FC1)

    def __call__(self, img: np.ndarray) -> np.ndarray:
        if self.maps is None:
            return img
        import cv2  # lazily: `import jaxtrack` must not load OpenCV

        return cv2.remap(img, self.maps[0], self.maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def _convert(img: np.ndarray, gray: bool, dtype) -> np.ndarray:
    import cv2  # lazily: `import jaxtrack` must not load OpenCV

    if img.ndim == 2:
        img = img if gray else cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
    elif img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY if gray else cv2.COLOR_BGRA2RGB)
    else:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY if gray else cv2.COLOR_BGR2RGB)
    if img.dtype == np.uint16:
        img = (img / 257.0).round().astype(np.uint8)
    return img if dtype is None else img.astype(dtype)


@dataclasses.dataclass
class VideoView(CameraView):
    """A camera whose frames come from a video file (decoded in order; a jump back reopens the file) or from a
    folder of images, undistorted where they are read. `frame_paths` lists the image files, or for a video
    one entry per frame (the video's path), so `len(frame_paths)` is the frame count as everywhere."""

    calibration: CameraCalibration | None = None
    video: pathlib.Path | None = None
    _capture: object = dataclasses.field(default=None, repr=False)
    _next: int = 0
    _undistort: _Undistorter | None = dataclasses.field(default=None, repr=False)

    def _undistorter(self) -> _Undistorter:
        if self._undistort is None:
            self._undistort = _Undistorter(self.calibration, self.width, self.height)
        return self._undistort

    def _decode(self, index: int) -> np.ndarray:
        import cv2  # lazily: `import jaxtrack` must not load OpenCV

        if self._capture is None or index < self._next:
            if self._capture is not None:
                self._capture.release()
            self._capture, self._next = cv2.VideoCapture(str(self.video)), 0
        while self._next < index:  # skip forward without converting
            if not self._capture.grab():
                raise SequenceError(f"{self.video}: frame {self._next} cannot be decoded (the file ends early?)")
            self._next += 1
        ok, img = self._capture.read()
        if not ok or img is None:
            raise SequenceError(f"{self.video}: frame {index} cannot be decoded (the file ends early?)")
        self._next += 1
        return img

    def read_frame(self, index: int, gray: bool = False, dtype=np.float32) -> np.ndarray:
        """Frame `index` as in `CameraView.read_frame`, undistorted (the camera's K, no distortion)."""
        import cv2  # lazily: `import jaxtrack` must not load OpenCV

        n = len(self.frame_paths)
        if not -n <= int(index) < n:
            raise IndexError(f"{self.video or self.folder}: frame index {index} out of range [0, {n})")
        index = int(index) % n
        if self.video is not None:
            img = self._decode(index)
            where = f"{self.video}: frame {index}"
        else:
            path = self.frame_paths[index]
            img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if img is None:
                raise SequenceError(f"{path}: not readable as an image")
            where = str(path)
        if img.shape[:2] != (self.height, self.width):
            raise SequenceError(f"{where}: {img.shape[1]}x{img.shape[0]} pixels, the camera's frames are "
                                f"{self.width}x{self.height}")
        return _convert(self._undistorter()(img), gray, dtype)


def _count_frames(video: pathlib.Path) -> tuple[int, int, int]:
    """(frames, width, height) of a video, by decoding it once (container frame counts are estimates)."""
    import cv2  # lazily: `import jaxtrack` must not load OpenCV

    cap = cv2.VideoCapture(str(video))
    try:
        if not cap.isOpened():
            raise SequenceError(f"{video}: cannot be opened as a video by OpenCV (unknown container or codec?)")
        ok, first = cap.read()
        if not ok or first is None:
            raise SequenceError(f"{video}: no frame can be decoded")
        n = 1
        while cap.grab():
            n += 1
        return n, first.shape[1], first.shape[0]
    finally:
        cap.release()


def _image_files(folder: pathlib.Path) -> list[pathlib.Path]:
    import re

    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]
    key = lambda p: [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", p.name)]  # frame2 before frame10
    return sorted(files, key=key)


def is_bop_folder(path: str | os.PathLike) -> bool:
    """Whether `path` looks like a BOP sequence folder (a models/ folder beside it)."""
    path = pathlib.Path(path)
    return path.is_dir() and (path / "models").is_dir()


def own_sequence(source: str | os.PathLike, mesh: str | os.PathLike | list, calibration: str | os.PathLike | CameraCalibration,
                 mesh_unit: str = "mm") -> Sequence:
    """A one-camera `Sequence` (object id 1, or 1..N for N meshes; no ground truth) from a video file or a folder
    of images.

    Args:
        source: a video file OpenCV can decode, or a folder of images (sorted by name, numbers in order).
        mesh: any mesh file trimesh reads, or a list of them (objects 1, 2, ... in that order). mesh_unit: their
            length unit, "mm" (default), "cm" or "m" (the tracker works in millimetres; `Sequence.model_scales`
            carries the factor).
        calibration: a calibration file (`read_calibration`) or a `CameraCalibration`.

    Raises:
        FileNotFoundError / SequenceError / ValueError: naming the file and what is wrong with it.
    """
    source = pathlib.Path(source)
    meshes = [pathlib.Path(m) for m in (mesh if isinstance(mesh, list | tuple) else [mesh])]
    if mesh_unit not in MESH_UNITS:
        raise ValueError(f"--mesh-unit: one of {', '.join(MESH_UNITS)}, got {mesh_unit!r}")
    if not meshes:
        raise ValueError("own_sequence: mesh must name at least one mesh file")
    for path in meshes:
        if not path.is_file():
            raise FileNotFoundError(f"{path}: mesh file not found" + (" (it is a folder)" if path.is_dir() else ""))
        if path.suffix.lower() == ".urdf":
            raise ValueError(f"{path}: articulated models (URDF) are tracked from BOP folders (scene_gt.json gives the first "
                             "joint values); give a rigid mesh here")
        if path.suffix.lower() not in MODEL_SUFFIXES:
            raise ValueError(f"{path}: not a mesh file trimesh reads ({', '.join(MODEL_SUFFIXES[:-1])})")
    calib = calibration if isinstance(calibration, CameraCalibration) else read_calibration(calibration)
    if source.is_dir():
        files = _image_files(source)
        if not files:
            raise SequenceError(f"{source}: no image file ({', '.join(IMAGE_SUFFIXES)})")
        import cv2  # lazily: `import jaxtrack` must not load OpenCV

        first = cv2.imread(str(files[0]), cv2.IMREAD_UNCHANGED)
        if first is None:
            raise SequenceError(f"{files[0]}: not readable as an image")
        n, (height, width), frame_paths, video = len(files), first.shape[:2], files, None
    elif source.is_file():
        if source.suffix.lower() in IMAGE_SUFFIXES:
            raise SequenceError(f"{source}: a single image; give a folder of frames or a video file")
        n, width, height = _count_frames(source)
        frame_paths, video = [source] * n, source
    else:
        raise FileNotFoundError(f"{source}: no such video file or folder of images")
    cx, cy = calib.K[0, 2], calib.K[1, 2]
    if not (-0.5 <= cx <= width - 0.5 and -0.5 <= cy <= height - 0.5):
        raise ValueError(f"{calib.source}: the principal point ({cx:g}, {cy:g}) lies outside the {width}x{height} frames of "
                         f"{source}: a calibration for another resolution?")
    if (calib.width, calib.height) != (None, None) and (calib.width, calib.height) != (width, height):
        raise ValueError(f"{calib.source}: the calibration is for {calib.width}x{calib.height} images, {source} has "
                         f"{width}x{height} frames")
    view = VideoView(folder=source if source.is_dir() else source.parent, frame_paths=list(frame_paths), K=calib.K.copy(),
                     T_cam_world=np.eye(4), T_cam_obj={}, width=int(width), height=int(height), frame_ids=list(range(n)),
                     calibration=calib, video=video)
    return Sequence(source, {o: m for o, m in enumerate(meshes, 1)}, [view],
                    model_scales={o: MESH_UNITS[mesh_unit] for o in range(1, len(meshes) + 1)})


# ------------------------------------------------------------------------------------ the first pose
def read_init_points(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """(image_points (n, 2) pixels of the first frame, model_points (n, 3) in the mesh's units) from a JSON
    `{"image_points": [[u, v], ...], "model_points": [[x, y, z], ...]}` or a CSV of rows `u,v,x,y,z` (a header
    row is allowed).

    Raises:
        FileNotFoundError / ValueError: naming the file and the problem.
    """
    path = pathlib.Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: points file not found" + (" (it is a folder)" if path.is_dir() else ""))
    text = path.read_text(encoding="utf-8-sig")
    if path.suffix.lower() == ".json":
        try:
            data = json.loads(text)
        except json.JSONDecodeError as e:
            raise ValueError(f"{path}: not readable as JSON ({e})") from None
        if not isinstance(data, dict) or "image_points" not in data or "model_points" not in data:
            raise ValueError(f'{path}: expected {{"image_points": [[u, v], ...], "model_points": [[x, y, z], ...]}}')
        try:
            img, mdl = np.asarray(data["image_points"], np.float64), np.asarray(data["model_points"], np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"{path}: image_points and model_points must be lists of numbers") from None
        if img.ndim != 2 or img.shape[1] != 2:
            raise ValueError(f"{path}: field 'image_points' must be a list of [u, v] pairs, got shape {img.shape}")
        if mdl.ndim != 2 or mdl.shape[1] != 3:
            raise ValueError(f"{path}: field 'model_points' must be a list of [x, y, z] triples, got shape {mdl.shape}")
        if len(img) != len(mdl):
            raise ValueError(f"{path}: {len(img)} image_points but {len(mdl)} model_points")
    else:
        rows = []
        for k, line in enumerate(text.splitlines(), 1):
            cells = [c.strip() for c in line.replace(";", ",").split(",")] if "," in line or ";" in line else line.split()
            if not cells or cells == [""] or line.lstrip().startswith("#"):
                continue
            try:
                values = [float(c) for c in cells]
            except ValueError:
                if not rows and k == 1:
                    continue  # a header row
                raise ValueError(f"{path}: line {k} is not five numbers u,v,x,y,z: {line!r}") from None
            if len(values) != 5:
                raise ValueError(f"{path}: line {k} has {len(values)} value(s), expected five (u,v,x,y,z)")
            rows.append(values)
        a = np.asarray(rows, np.float64).reshape(-1, 5)
        img, mdl = a[:, :2], a[:, 2:]
    if not (np.all(np.isfinite(img)) and np.all(np.isfinite(mdl))):
        raise ValueError(f"{path}: the points must be finite numbers")
    if len(img) < 4:
        raise ValueError(f"{path}: {len(img)} point pair(s); the first pose needs at least 4")
    return img, mdl


@dataclasses.dataclass(frozen=True)
class PointsPose:
    """The first pose from clicked points: T_cam_obj (4, 4) (mm), the RMS and largest reprojection error (px)
    over the inliers, and which pairs were inliers (all of them without RANSAC)."""

    T_cam_obj: np.ndarray
    rms_px: float
    max_px: float
    inliers: np.ndarray


def pose_from_points(image_points, model_points, K, dist=None, scale: float = 1.0, ransac_px: float = 8.0,
                     max_rms_px: float = 4.0, what: str = "--init-points") -> PointsPose:
    """The model → camera pose from ≥ 4 image / model point pairs.

    With more than four pairs RANSAC over EPnP samples (`ransac_px`) gives the start and the inliers (SQPnP on all
    pairs when it fails); with four, SQPnP (globally optimal: on four points with 1 px noise EPnP was off by up to
    134°, SQPnP by 4.4° at most, experiments/init_points.py). jaxtrack's own Gauss-Newton on the Plücker lines of the inliers
    (`jaxtrack.solve.estimate_pose`, eq. 4-5) refines it.

    Args:
        image_points: (n, 2) pixels. model_points: (n, 3) in the mesh's units; `scale` converts them to mm.
        K: (3, 3) intrinsics; dist: optional OpenCV distortion of the image the points were clicked on.
        max_rms_px: refuse a pose whose RMS reprojection error over the inliers is larger.

    Raises:
        ValueError: naming `what`: too few pairs, degenerate points, no pose, a pose with points behind the
            camera, or a reprojection error above `max_rms_px` (the message gives the errors per point).
    """
    import cv2  # lazily: `import jaxtrack` must not load OpenCV

    img = np.asarray(image_points, np.float64).reshape(-1, 2)
    mdl = np.asarray(model_points, np.float64).reshape(-1, 3) * float(scale)
    K = np.asarray(K, np.float64)
    dist = np.zeros(5) if dist is None else np.asarray(dist, np.float64).reshape(-1)
    n = len(img)
    if n < 4 or len(mdl) != n:
        raise ValueError(f"{what}: at least 4 pairs of image and model points are needed, got {n}")
    if np.linalg.matrix_rank(mdl - mdl.mean(0), tol=1e-6 * max(np.abs(mdl).max(), 1.0)) < 2:
        raise ValueError(f"{what}: the model points are collinear (or the same point): they cannot fix a pose")
    ideal = cv2.undistortPoints(img.reshape(-1, 1, 2), K, dist, P=K).reshape(-1, 2) if np.any(dist != 0) else img
    inliers = np.ones(n, bool)
    if n > 4:
        ok, rvec, tvec, idx = cv2.solvePnPRansac(mdl, ideal, K, None, flags=cv2.SOLVEPNP_EPNP, reprojectionError=ransac_px,
                                                 iterationsCount=200, confidence=0.999)
        if ok and idx is not None and len(idx) >= 4:
            inliers = np.zeros(n, bool)
            inliers[idx.reshape(-1)] = True
        else:
            ok, rvec, tvec = cv2.solvePnP(mdl, ideal, K, None, flags=cv2.SOLVEPNP_SQPNP)
    else:
        ok, rvec, tvec = cv2.solvePnP(mdl, ideal, K, None, flags=cv2.SOLVEPNP_SQPNP)
    if not ok:
        raise ValueError(f"{what}: PnP found no pose for these {n} points")
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = cv2.Rodrigues(rvec)[0], np.asarray(tvec).reshape(3)
    T = _refine_on_lines(ideal[inliers], mdl[inliers], K, T)
    p_cam = mdl @ T[:3, :3].T + T[:3, 3]
    if np.any(p_cam[inliers, 2] <= 0):
        raise ValueError(f"{what}: the pose puts {int(np.sum(p_cam[inliers, 2] <= 0))} of the points behind the camera: "
                         "check that each image point matches its model point (same order)")
    proj = _pinhole(K, p_cam)
    err = np.linalg.norm(proj - ideal, axis=1)
    rms, worst = float(np.sqrt(np.mean(err[inliers] ** 2))), float(err[inliers].max())
    if rms > max_rms_px:
        listing = ", ".join(f"#{i}: {e:.1f}" for i, e in enumerate(err))
        raise ValueError(f"{what}: the best pose reprojects the points {rms:.1f} px RMS (more than {max_rms_px:g} px; per "
                         f"point {listing}): check the order of the pairs, the model unit (--mesh-unit) and the calibration")
    return PointsPose(T, rms, worst, inliers)


def _pinhole(K, p_cam) -> np.ndarray:
    """(n, 2) pixels of camera-frame points (n, 3) through K (skew included), host-side."""
    K = np.asarray(K, np.float64)
    h = p_cam / p_cam[:, 2:3]
    return h @ K[:2].T


def _refine_on_lines(pixels, model_mm, K, T_cam_obj) -> np.ndarray:
    """jaxtrack's Gauss-Newton on the pixels' viewing rays (Plücker lines, eq. 4-5) from `T_cam_obj`; the start
    when it does not improve it."""
    from ..geometry import make_camera, rigid_model
    from ..solve import SolverConfig, estimate_pose, make_correspondences

    cam = make_camera(K, max(int(2 * K[0, 2]) + 2, 2), max(int(2 * K[1, 2]) + 2, 2))  # the size is not used here
    corr = make_correspondences(cam, np.asarray(pixels, np.float32), np.asarray(model_mm, np.float32))
    try:
        sol = estimate_pose(rigid_model(), corr, np.asarray(T_cam_obj, np.float32), config=SolverConfig(max_steps=30),
                            cameras=cam)
    except (ValueError, RuntimeError):  # a degenerate set or a failed solve: keep PnP's pose
        return T_cam_obj
    T = np.asarray(sol.T_world_root, np.float64)
    return T if np.all(np.isfinite(T)) else T_cam_obj


def check_first_pose(vertices_mm, K, width: int, height: int, T_cam_obj, what: str, diameter_mm: float | None = None,
                     min_px: float = 8.0) -> None:
    """Refuse a first pose that cannot be tracked because of the mesh's unit: the object a few pixels wide (a mesh
    in metres read as millimetres), or the camera inside the model (a mesh 1000x too large), or entirely off the
    image. `diameter_mm`: the model's diameter from `models_info.json`, compared with the mesh's when given.

    Raises:
        ValueError: naming `what` and suggesting --mesh-unit where the unit is the likely cause.
    """
    v = np.asarray(vertices_mm, np.float64).reshape(-1, 3)
    T = np.asarray(T_cam_obj, np.float64)
    p = v @ T[:3, :3].T + T[:3, 3]
    lo, hi = v.min(0), v.max(0)
    size = float(np.linalg.norm(hi - lo))
    if diameter_mm is not None and np.isfinite(diameter_mm) and diameter_mm > 0:
        ratio = size / diameter_mm
        if ratio > 30 or ratio < 1 / 30:
            raise ValueError(f"{what}: the mesh spans {size:.4g} mm but models_info.json gives a diameter of {diameter_mm:.4g} mm: "
                             f"a mesh in other units? (--mesh-unit m|cm|mm)")
    centre_cam = T[:3, :3] @ ((lo + hi) / 2) + T[:3, 3]
    if centre_cam[2] <= 0 and np.linalg.norm(centre_cam) >= size / 2:
        raise ValueError(f"{what}: the pose puts the object behind the camera (its centre at depth {centre_cam[2]:.4g} mm; "
                         f"translation z = {T[2, 3]:.4g} mm must be positive)")
    if np.any(p[:, 2] <= 0) or np.linalg.norm(centre_cam) < size / 2:
        raise ValueError(f"{what}: the camera is inside the model or part of the model is behind it (the mesh spans "
                         f"{size:.4g} mm, its centre is {np.linalg.norm(centre_cam):.4g} mm from the camera): a mesh in "
                         f"millimetres read as metres? (--mesh-unit mm) or a wrong pose")
    uv = _pinhole(K, p)
    extent = float(np.max(uv.max(0) - uv.min(0)))
    if extent < min_px:
        raise ValueError(f"{what}: the model is {extent:.2g} px wide in the image at the first pose (the mesh spans "
                         f"{size:.4g} mm at {centre_cam[2]:.4g} mm): a mesh in metres read as millimetres? (--mesh-unit m)")
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < width) & (uv[:, 1] >= 0) & (uv[:, 1] < height)
    if not inside.any():
        raise ValueError(f"{what}: the model lies outside the {width}x{height} image at the first pose")
