"""The child process of `jaxtrack._tiered`: compiles programs with XLA's defaults into the on-disk compile cache.

    python -m jaxtrack._tiered_child SPEC.json      (started by jaxtrack itself)

For each program of the spec (an exported program kept by `jaxtrack._exported`, its arguments' shapes): compile it as
`jaxtrack._exported._Entry` compiles it in the tracking process (the same jit, so the same cache key), compile it again in a
fresh jit and mark it done (`<program>.jaxexport.optimised`) only if that second compile was a hit in the cache (a
failed cache write leaves no mark). Releases each program's lock (`<program>.jaxexport.optimising`) if it still holds
it. Exit status 1 if any program failed (the messages on stderr).
"""

from __future__ import annotations

import contextlib
import json
import os
import pathlib
import sys
import tempfile

CHILD_NICE = 10  # the tracking process keeps its core while the child compiles


def _compile_and_check(spec: dict, program: dict, device) -> None:
    import jax
    import jax.monitoring

    from ._exported import _Entry, _loads
    from ._tiered import mark_path

    path = pathlib.Path(program["path"])
    stored = _loads(path.read_bytes())
    exported = jax.export.deserialize(stored["exported"])
    structs = [jax.ShapeDtypeStruct(tuple(shape), dtype) for shape, dtype in program["avals"]]
    _Entry(exported, *stored["out"], device, None).compile(structs)
    events: list[str] = []
    jax.monitoring.register_event_listener(lambda name, **_: events.append(name) if "compilation_cache" in name else None)
    _Entry(exported, *stored["out"], device, None).compile(structs)  # a fresh jit: from the cache, or compiled again
    if not any(name.endswith("cache_hits") for name in events):
        raise RuntimeError(f"the compile cache in {spec['cache_dir']} did not keep the program (events: {events})")
    handle, temporary = tempfile.mkstemp(prefix=f".{mark_path(path).name}.", dir=path.parent)
    with os.fdopen(handle, "w") as file:
        file.write(spec["mark"])
    os.replace(temporary, mark_path(path))


def main(spec_path: str) -> int:
    with contextlib.suppress(OSError, AttributeError):
        os.nice(CHILD_NICE)
    spec = json.loads(pathlib.Path(spec_path).read_text())
    with contextlib.suppress(OSError):
        os.unlink(spec_path)
    import jax

    jax.config.update("jax_enable_x64", spec["x64"])
    jax.config.update("jax_compilation_cache_dir", spec["cache_dir"])
    jax.config.update("jax_persistent_cache_min_compile_time_secs", spec["min_compile_s"])
    from ._tiered import _release

    device = jax.devices("cpu")[0]
    status = 0
    for program in spec["programs"]:
        path = pathlib.Path(program["path"])
        try:
            _compile_and_check(spec, program, device)
        except Exception as error:  # noqa: BLE001  (reported through the exit status; the parent keeps the quick build)
            print(f"{path.name}: {type(error).__name__}: {error}", file=sys.stderr)
            status = 1
        finally:
            _release(path, os.getpid())
    return status


if __name__ == "__main__":
    if len(sys.argv) != 2:
        raise SystemExit("usage: python -m jaxtrack._tiered_child SPEC.json (started by jaxtrack itself)")
    raise SystemExit(main(sys.argv[1]))
