"""Mesh loading through trimesh (PLY, OBJ, STL, GLB, ...), with clear errors, and a geometry cache on disk.

`import trimesh` takes about a second (it loads scipy.spatial and networkx), as much as a warm tracker's whole
start. `load_mesh_arrays` (and `load_mesh`) keep what a file's geometry came to (vertices, faces) in
`mesh_cache_dir()`, keyed by a sha256 of the file's bytes (and of the OBJ's material libraries), the scale and
trimesh's version; a process that finds the entry reads it (milliseconds) and never imports trimesh. Formats whose
geometry may sit in other files (glTF's external buffers, COLLADA, ...) are always read through trimesh.
"""

from __future__ import annotations

import hashlib
import os
import pathlib
import re
import tempfile
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from ..render import Mesh, make_mesh

if TYPE_CHECKING:
    import trimesh

# Formats whose geometry is all in the file (an OBJ's material libraries are hashed with it: trimesh groups
# faces by material); the cache is used for these only.
CACHED_SUFFIXES = (".ply", ".stl", ".off", ".glb", ".obj")
_CACHE_FORMAT = 1  # bump when what an entry holds, or how the geometry is read, changes


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


def mesh_cache_dir() -> pathlib.Path:
    """$JAXTRACK_CACHE/meshes if $JAXTRACK_CACHE is set, else ~/.cache/jaxtrack/meshes."""
    env = os.environ.get("JAXTRACK_CACHE")
    return (pathlib.Path(env) if env else pathlib.Path.home() / ".cache" / "jaxtrack") / "meshes"


def _cache_key(path: pathlib.Path, scale: float) -> str | None:
    """The entry's name for this file and scale; None where the format is not cached."""
    if path.suffix.lower() not in CACHED_SUFFIXES or os.environ.get("JAXTRACK_MESH_CACHE", "1") == "0":
        return None
    from importlib.metadata import PackageNotFoundError, version

    try:
        trimesh_version = version("trimesh")
    except PackageNotFoundError:
        return None
    data = path.read_bytes()
    h = hashlib.sha256(data)
    if path.suffix.lower() == ".obj":  # its material libraries decide how trimesh groups the faces
        for name in re.findall(rb"^[ \t]*mtllib[ \t]+(.+?)[ \t]*$", data, flags=re.MULTILINE):
            library = path.parent / name.decode("utf-8", "replace")
            h.update(name + b"\0" + (library.read_bytes() if library.is_file() else b"<missing>"))
    h.update(f"|{path.suffix.lower()}|{float(scale)!r}|{trimesh_version}|{_CACHE_FORMAT}".encode())
    return h.hexdigest()[:40]


def load_mesh_arrays(path: str | os.PathLike, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """(V, 3) float64 vertices (scaled by `scale`) and (F, 3) int64 faces of a mesh file, as `load_trimesh` reads
    them, kept in `mesh_cache_dir()` ($JAXTRACK_MESH_CACHE=0: not kept) so that a later process skips trimesh.

    Raises:
        FileNotFoundError, ValueError: as `load_trimesh` (the same checks, the same messages).
    """
    path = _checked_path(path, scale)
    key = _cache_key(path, scale)
    entry = None if key is None else mesh_cache_dir() / f"mesh-{key}.npz"
    if entry is not None and entry.is_file():
        try:
            with np.load(entry) as data:
                return np.asarray(data["vertices"], np.float64), np.asarray(data["faces"], np.int64)
        except (OSError, ValueError, KeyError):
            pass  # unreadable: read the file again and write a new entry
    tm = load_trimesh(path, scale)
    vertices, faces = np.asarray(tm.vertices, np.float64), np.asarray(tm.faces, np.int64)
    if entry is not None:
        try:
            entry.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(dir=entry.parent, suffix=".npz.tmp")
            try:
                with os.fdopen(fd, "wb") as f:
                    np.savez(f, vertices=vertices, faces=faces)
                os.replace(tmp, entry)  # atomic: a reader sees the old entry, none, or the whole new one
            finally:
                if os.path.exists(tmp):
                    os.remove(tmp)
        except OSError:
            pass  # a cache that cannot be written only costs the next process the read
    return vertices, faces


def load_mesh(path: str | os.PathLike, scale: float = 1.0, dtype: npt.DTypeLike = np.float32) -> Mesh:
    """A rigid `Mesh` (mm) from a file; `scale` converts its units to mm (e.g. 1000 for metres). Read through
    `load_mesh_arrays` (its geometry cache)."""
    vertices, faces = load_mesh_arrays(path, scale)
    return make_mesh(vertices, faces, dtype=dtype, name=str(path))
