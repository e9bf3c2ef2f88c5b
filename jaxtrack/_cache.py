"""The on-disk XLA compilation cache that `jaxtrack track`, `jaxtrack bench` and the experiments share."""

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
