"""Image files and output paths: the one reader/writer every command and loader goes through.

OpenCV reads and writes; its failures (None from imread, False or cv2.error from imwrite) become
errors that name the file. Writers share one output-path rule: missing parent folders are created,
a path that is a folder, or below a file, is refused with a message naming it.
"""

from __future__ import annotations

import os
import pathlib

import numpy as np
import numpy.typing as npt

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".ppm", ".pgm")
_MODES = ("rgb", "grey", "native")


def read_image(path: str | os.PathLike, mode: str = "rgb", dtype: npt.DTypeLike | None = None) -> np.ndarray:
    """An image file as an array.

    Args:
        path: the file (any format OpenCV reads).
        mode: "rgb" → (H, W, 3) RGB; "grey" → (H, W); "native" → (H, W) for single-channel files and
            (H, W, 3) RGB otherwise (alpha dropped), keeping the file's channel count.
        dtype: convert to this dtype (values are not rescaled); None keeps the file's (uint8/uint16).

    Raises:
        FileNotFoundError: the file does not exist (named).
        ValueError: the file exists but is not a readable image, or `mode` is unknown (named).
    """
    import cv2

    if mode not in _MODES:
        raise ValueError(f"read_image: mode must be one of {', '.join(_MODES)}, got {mode!r}")
    path = pathlib.Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: image file not found" + (" (it is a folder)" if path.is_dir() else ""))
    flag = {"rgb": cv2.IMREAD_COLOR, "grey": cv2.IMREAD_GRAYSCALE, "native": cv2.IMREAD_UNCHANGED}[mode]
    img = cv2.imread(str(path), flag)
    if img is None:
        raise ValueError(f"{path}: cannot read image (unknown format or corrupt file)")
    if img.ndim == 3:
        img = np.ascontiguousarray(img[..., :3][..., ::-1])  # BGR(A) → RGB
    return img if dtype is None else img.astype(dtype)


def image_size(path: str | os.PathLike) -> tuple[int, int]:
    """(width, height) of an image file from its header (no full decode where the format allows).

    Raises:
        FileNotFoundError / ValueError: as `read_image`.
    """
    path = pathlib.Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: image file not found")
    try:
        from PIL import Image  # a dependency of scikit-image; reads only the header

        with Image.open(path) as im:
            return int(im.size[0]), int(im.size[1])
    except (ImportError, OSError, ValueError):  # no Pillow, or a format it does not know: decode with OpenCV
        img = read_image(path, "native")
        return img.shape[1], img.shape[0]


def prepare_output_file(path: str | os.PathLike, what: str = "output file", suffixes: tuple | None = None) -> pathlib.Path:
    """Check an output file path before any work is done, creating missing parent folders.

    Args:
        path: the file to be written.
        what: how error messages name it (e.g. "--viz").
        suffixes: allowed extensions (lower case, with dot); None allows any.

    Raises:
        ValueError: the path is an existing folder, lies below an existing file, has a suffix not in
            `suffixes`, or its parent folder cannot be created.
    """
    path = pathlib.Path(path)
    if str(path) in ("", "."):
        raise ValueError(f"{what}: empty path")
    if path.is_dir():
        raise ValueError(f"{what}: {path} is a folder, expected a file name")
    if suffixes is not None and path.suffix.lower() not in suffixes:
        raise ValueError(f"{what}: {path} must end in one of {', '.join(suffixes)}")
    _make_folder(path.parent, what)
    _probe_write(path, what)
    return path


def _probe_write(path: pathlib.Path, what: str) -> None:
    """Open `path` for appending (creating it) and close it, removing it again when it did not exist: a read-only
    or virtual file system is found before the work, not after it (permission bits alone do not tell)."""
    existed = path.exists()
    try:
        with open(path, "ab"):
            pass
    except OSError as e:
        raise ValueError(f"{what}: cannot write {path} ({e.strerror or e})") from e
    if not existed:
        try:
            path.unlink()
        except OSError:
            pass


def prepare_output_folder(path: str | os.PathLike, what: str = "output folder") -> pathlib.Path:
    """Create an output folder (and its parents); refuse a path that is an existing file."""
    path = pathlib.Path(path)
    if path.exists() and not path.is_dir():
        raise ValueError(f"{what}: {path} exists and is not a folder")
    _make_folder(path, what)
    _probe_write(path / f".jaxtrack-write-test-{os.getpid()}", what)
    return path


def prepare_image_output(path: str | os.PathLike, what: str = "image") -> pathlib.Path:
    """`prepare_output_file` for an image: also refuses an extension OpenCV has no writer for.

    Call it before expensive work whose result goes to `write_image`.
    """
    import cv2

    path = pathlib.Path(path)
    if not cv2.haveImageWriter(str(path)):
        raise ValueError(f"{what}: {path}: no image writer for extension {path.suffix!r} (use .png, .jpg, ...)")
    return prepare_output_file(path, what)


def _make_folder(folder: pathlib.Path, what: str) -> None:
    for p in (folder, *folder.parents):
        if p.exists() and not p.is_dir():
            raise ValueError(f"{what}: cannot create folder {folder}: {p} is a file")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ValueError(f"{what}: cannot create folder {folder} ({e.strerror})") from e


def write_image(path: str | os.PathLike, image: npt.ArrayLike, what: str = "image") -> pathlib.Path:
    """Write an (H, W) grey or (H, W, 3) RGB uint8/uint16 image; the format follows the extension.

    Missing parent folders are created (see `prepare_output_file`).

    Raises:
        ValueError: naming the path (no writer for its extension, a folder, write failure) or the
            image's shape/dtype.
    """
    import cv2

    image = np.asarray(image)
    if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] != 3) or image.size == 0:
        raise ValueError(f"{what}: image must be (H, W) or (H, W, 3), got shape {image.shape}")
    if image.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"{what}: image must be uint8 or uint16, got {image.dtype}")
    path = prepare_image_output(path, what)
    if image.ndim == 3:
        image = np.ascontiguousarray(image[..., ::-1])  # RGB → BGR
    try:
        ok = cv2.imwrite(str(path), image)
    except cv2.error as e:
        raise ValueError(f"{what}: {path}: cannot write image ({e})") from e
    if not ok:
        raise ValueError(f"{what}: {path}: cannot write image")
    return path
