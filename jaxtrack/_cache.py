"""The on-disk XLA compilation cache that `jaxtrack track`, `jaxtrack bench` and the experiments share, and the atomic
.npz write of the caches kept as arrays (the sparse view models, the meshes' geometry)."""

from __future__ import annotations


def enable_compilation_cache(path: str | None = None) -> str:
    """Keep compiled XLA programs on disk so a second run with the same frame size skips compiling, and the tracker's
    traced programs (`jaxtrack._exported`, in `<path>/exported`) so that it also skips tracing them.

    The directory is `path`, else $JAXTRACK_CACHE_DIR, else ~/.cache/jaxtrack/xla.
    """
    import os

    import jax

    path = path or os.environ.get("JAXTRACK_CACHE_DIR") or os.path.join(os.path.expanduser("~"), ".cache", "jaxtrack", "xla")
    os.makedirs(path, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", path)
    # Every program, the small ones too: a fresh process otherwise compiles again the ~50 small programs of
    # `Tracker.start` and its host helpers (1.4 s of a 4 s warm start).
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    from ._exported import enable_exported_cache

    enable_exported_cache(os.path.join(path, "exported"))
    return path


def write_npz_atomically(path, arrays: dict) -> None:
    """Write `arrays` (name -> array) as the .npz `path`: to a temporary file in its folder, flushed to disk, made 0644
    (mkstemp's 0600 would hide it from the folder's other users) and renamed into place, so that a reader sees the old
    file, none, or the whole new one. Makes the folder. Raises OSError when it cannot be written."""
    import os
    import pathlib
    import tempfile

    import numpy as np

    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".npz.tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(f, **arrays)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
