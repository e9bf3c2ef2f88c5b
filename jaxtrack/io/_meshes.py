"""Mesh loading through trimesh (PLY, OBJ, STL, GLB, ...), with clear errors."""

from __future__ import annotations

import pathlib

import numpy as np
import trimesh

from ..render import Mesh, make_mesh


def load_trimesh(path, scale: float = 1.0) -> trimesh.Trimesh:
    """A single `trimesh.Trimesh` from a file (scenes are flattened), vertices scaled by `scale`."""
    path = pathlib.Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: mesh file not found")
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
    if scale != 1.0:
        loaded = loaded.copy()
        loaded.apply_scale(scale)
    return loaded


def load_mesh(path, scale: float = 1.0, dtype=np.float32) -> Mesh:
    """A rigid `Mesh` (mm) from a file; `scale` converts its units to mm (e.g. 1000 for metres)."""
    tm = load_trimesh(path, scale)
    return make_mesh(np.asarray(tm.vertices), np.asarray(tm.faces), dtype=dtype, name=str(path))
