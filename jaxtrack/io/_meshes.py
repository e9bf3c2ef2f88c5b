"""Mesh loading through trimesh (PLY, OBJ, STL, GLB, ...), with clear errors, and a geometry cache on disk.

`import trimesh` takes about a second (it loads scipy.spatial and networkx), as much as a warm tracker's whole
start. `load_mesh_arrays` (and `load_mesh`) keep what a file's geometry came to (vertices, faces) in
`mesh_cache_dir()`, keyed by a sha256 of the file's bytes, the scale and trimesh's version; a process that finds the
entry reads it (milliseconds) and never imports trimesh. Formats whose geometry may sit in other files (glTF's external
buffers, COLLADA, ...) are always read through trimesh; so is any file the cache cannot key or keep (unreadable, no
cache folder), and an entry that cannot be read or does not hold a valid mesh is removed and made again.
"""

from __future__ import annotations

import hashlib
import os
import pathlib
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from .._cache import write_npz_atomically
from ..render import Mesh, make_mesh

if TYPE_CHECKING:
    import trimesh

# Formats whose geometry is all in the file; the cache is used for these only. (An OBJ's material library does not
# change the vertices and faces trimesh reads: checked with the library present, missing and edited, trimesh 5.2.)
CACHED_SUFFIXES = (".ply", ".stl", ".off", ".glb", ".obj")
_CACHE_FORMAT = 2  # bump when what an entry holds, or how the geometry is read, changes


def load_trimesh(path: str | os.PathLike, scale: float = 1.0) -> trimesh.Trimesh:
    """A single `trimesh.Trimesh` from a file (scenes are flattened), vertices scaled by `scale`.

    Raises:
        FileNotFoundError: naming the missing file.
        ValueError: naming the file that is empty, unreadable, has no faces or non-finite vertices,
            or a bad `scale`.
    """
    path = _checked_path(path, scale)
    import trimesh  # lazily: a second to import, and a cached mesh does not need it

    try:
        loaded = trimesh.load(str(path), process=False)
    except Exception as e:  # trimesh raises many kinds for bad files
        raise ValueError(f"{path}: cannot read mesh ({e})") from e
    if isinstance(loaded, trimesh.Scene):
        geoms = [g for g in loaded.dump() if isinstance(g, trimesh.Trimesh)] if hasattr(loaded, "dump") else []
        if not geoms:
            raise ValueError(f"{path}: the scene holds no triangle mesh")
        loaded = trimesh.util.concatenate(geoms) if len(geoms) > 1 else geoms[0]
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise ValueError(f"{path}: mesh has no faces")
    if not np.all(np.isfinite(loaded.vertices)):
        raise ValueError(f"{path}: mesh has non-finite vertex coordinates")
    if scale != 1.0:
        loaded = loaded.copy()
        loaded.apply_scale(scale)
    return loaded


def _checked_path(path, scale) -> pathlib.Path:
    path = pathlib.Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: mesh file not found" + (" (it is a folder)" if path.is_dir() else ""))
    if not (isinstance(scale, int | float | np.number) and np.isfinite(scale) and scale > 0):
        raise ValueError(f"{path}: scale must be a finite number > 0, got {scale!r}")
    if path.stat().st_size == 0:
        raise ValueError(f"{path}: mesh file is empty")
    return path


def mesh_cache_dir() -> pathlib.Path | None:
    """Where `load_mesh_arrays` keeps geometry: $JAXTRACK_MESH_CACHE if it names a folder, else ~/.cache/jaxtrack/meshes;
    None when $JAXTRACK_MESH_CACHE is 0 or there is no home folder to put it in."""
    env = os.environ.get("JAXTRACK_MESH_CACHE", "")
    if env == "0":
        return None
    if env:
        return pathlib.Path(env)
    try:
        return pathlib.Path.home() / ".cache" / "jaxtrack" / "meshes"
    except RuntimeError:  # no $HOME and no passwd entry (some containers)
        return None


def _cache_key(path: pathlib.Path, scale: float) -> str | None:
    """The entry's name for this file and scale; None where the format is not cached or the file cannot be read
    (then `load_trimesh` reads it, and names the file in its error)."""
    if path.suffix.lower() not in CACHED_SUFFIXES:
        return None
    from importlib.metadata import PackageNotFoundError, version

    try:
        trimesh_version = version("trimesh")
        h = hashlib.sha256(path.read_bytes())
    except (PackageNotFoundError, OSError):
        return None
    h.update(f"|{path.suffix.lower()}|{float(scale)!r}|{trimesh_version}|{_CACHE_FORMAT}".encode())
    return h.hexdigest()[:40]


def _read_entry(entry: pathlib.Path) -> tuple[np.ndarray, np.ndarray] | None:
    """An entry's (vertices, faces) when it holds a valid mesh; None (and the entry removed) when it does not."""
    try:
        with np.load(entry) as data:
            vertices, faces = np.asarray(data["vertices"], np.float64), np.asarray(data["faces"], np.int64)
    except Exception:  # noqa: BLE001  (a damaged .npz raises EOFError, BadZipFile, ValueError, ...)
        vertices = faces = np.zeros((0, 3))
    if (vertices.ndim == 2 and vertices.shape[1] == 3 and len(vertices) and faces.ndim == 2 and faces.shape[1] == 3
            and len(faces) and np.all(np.isfinite(vertices)) and faces.min() >= 0 and faces.max() < len(vertices)):
        return vertices, faces
    try:
        entry.unlink()
    except OSError:
        pass
    return None


def load_mesh_arrays(path: str | os.PathLike, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """(V, 3) float64 vertices (scaled by `scale`) and (F, 3) int64 faces of a mesh file, as `load_trimesh` reads
    them, kept in `mesh_cache_dir()` so that a later process skips trimesh.

    Raises:
        FileNotFoundError, ValueError: as `load_trimesh` (the same checks, the same messages).
    """
    path = _checked_path(path, scale)
    folder = mesh_cache_dir()
    key = None if folder is None else _cache_key(path, scale)
    entry = None if key is None else folder / f"mesh-{key}.npz"
    if entry is not None and entry.is_file():
        cached = _read_entry(entry)
        if cached is not None:
            return cached
    tm = load_trimesh(path, scale)
    vertices, faces = np.asarray(tm.vertices, np.float64), np.asarray(tm.faces, np.int64)
    if entry is not None:
        try:
            write_npz_atomically(entry, {"vertices": vertices, "faces": faces})
        except OSError:
            pass  # a cache that cannot be written only costs the next process the read
    return vertices, faces


def load_mesh(path: str | os.PathLike, scale: float = 1.0, dtype: npt.DTypeLike = np.float32) -> Mesh:
    """A rigid `Mesh` (mm) from a file; `scale` converts its units to mm (e.g. 1000 for metres). Read through
    `load_mesh_arrays` (its geometry cache)."""
    vertices, faces = load_mesh_arrays(path, scale)
    return make_mesh(vertices, faces, dtype=dtype, name=str(path))
