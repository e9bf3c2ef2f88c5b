"""Mesh loading through trimesh (PLY, OBJ, STL, GLB, ...), with clear errors."""

from __future__ import annotations

import os
import pathlib

import numpy as np
import numpy.typing as npt
import trimesh

from ..render import Mesh, make_mesh


def load_trimesh(path: str | os.PathLike, scale: float = 1.0) -> trimesh.Trimesh:
    """A single `trimesh.Trimesh` from a file (scenes are flattened), vertices scaled by `scale`.

    Raises:
        FileNotFoundError: naming the missing file.
        ValueError: naming the file that is empty, unreadable, has no faces or non-finite vertices,
            or a bad `scale`.
    """
    path = pathlib.Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: mesh file not found" + (" (it is a folder)" if path.is_dir() else ""))
    if not (isinstance(scale, int | float | np.number) and np.isfinite(scale) and scale > 0):
        raise ValueError(f"{path}: scale must be a finite number > 0, got {scale!r}")
    if path.stat().st_size == 0:
        raise ValueError(f"{path}: mesh file is empty")
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


def load_mesh(path: str | os.PathLike, scale: float = 1.0, dtype: npt.DTypeLike = np.float32) -> Mesh:
    """A rigid `Mesh` (mm) from a file; `scale` converts its units to mm (e.g. 1000 for metres)."""
    tm = load_trimesh(path, scale)
    return make_mesh(np.asarray(tm.vertices), np.asarray(tm.faces), dtype=dtype, name=str(path))
