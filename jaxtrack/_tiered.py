"""Two tiers of the tracker's large programs: a quick compile now, the optimised program from a background process.

XLA:CPU compiles the tracker's step programs (`track_step`, `start_frame`) with its MLIR fusion emitters in about 1.5
times the time of its older elemental emitters, and the programs it makes run 15-30 % faster (README "Fast compile,
slower frames"). With an empty compile cache a `persistent_jit(..., tiered=True)` program (`$JAXTRACK_FUSION_EMITTERS`
unset or `auto`, on the CPU, with the on-disk caches on) is compiled with the quick options first, so the first frame
waits for the shorter compile; once it has run, a child process (`python -m jaxtrack._tiered`, at a lower priority)
compiles the exported program with XLA's defaults into the shared on-disk compile cache and marks it done
(`<program>.jaxexport.optimised`); this process then loads it from that cache in a background thread and the calls
after that run the optimised program (the same program, compiled otherwise: poses agree to float rounding, not bit for
bit). A later process that finds the mark loads the optimised program at once.

The child outlives this process (a short run leaves the compile to finish for the next one); one child at a time
compiles a given program (a lock file beside it; a lock older than `LOCK_STALE_S` is taken over). `wait_for_optimised_programs`
waits for the swap (benchmarks time the steady state after it).
"""

from __future__ import annotations

import atexit
import contextlib
import dataclasses
import json
import os
import pathlib
import subprocess
import sys
import tempfile
import threading
import time
import warnings

import jax

MARK_SUFFIX = ".optimised"
LOCK_SUFFIX = ".optimising"
# Requests arriving within this time of the first share one child (a step's two programs run milliseconds apart).
BATCH_WAIT_S = 0.5
# A lock file this old belongs to a child that died without removing it (a compile takes 10-30 s).
LOCK_STALE_S = 600.0
# How often a process whose program another process's child compiles looks for the mark.
POLL_S = 0.5
# The child's niceness: the tracking process keeps its core while the child compiles.
CHILD_NICE = 10


def mark_path(program: pathlib.Path) -> pathlib.Path:
    return program.with_name(program.name + MARK_SUFFIX)


def lock_path(program: pathlib.Path) -> pathlib.Path:
    return program.with_name(program.name + LOCK_SUFFIX)


def mark_content() -> str:
    """What decides whether the compile cache holds a program's optimised executable besides the program itself: the
    cache folder and $XLA_FLAGS (both in XLA's cache key)."""
    return json.dumps({"cache_dir": str(jax.config.jax_compilation_cache_dir), "xla_flags": os.environ.get("XLA_FLAGS", "")},
                      sort_keys=True)


def is_marked(program: pathlib.Path) -> bool:
    """Whether a child compiled `program`'s optimised executable into this process's compile cache."""
    try:
        return mark_path(program).read_text() == mark_content()
    except OSError:
        return False


def available() -> bool:
    """Tiers need an on-disk compile cache for the child to fill (`enable_compilation_cache`)."""
    return bool(jax.config.jax_compilation_cache_dir) and bool(getattr(jax.config, "jax_enable_compilation_cache", True))


@dataclasses.dataclass(eq=False)
class Request:
    """One program to optimise. `swap(entry)` installs the optimised entry in its owner (`persistent_jit`);
    `make_entry()` builds it (not compiled); `structs` are the arguments' shapes for the compile."""

    program: pathlib.Path
    avals: tuple
    make_entry: object
    swap: object
    structs: tuple


class _Optimiser:
    """The background thread that runs children and swaps their programs in, one batch at a time."""

    def __init__(self):
        self._cond = threading.Condition()
        self._pending: list[Request] = []
        self._busy = False  # a batch is in flight
        self._loading = False  # this process is loading an optimised executable (XLA; not to be left at exit)
        self._thread: threading.Thread | None = None
        self.failures: list[str] = []
        self.requested = 0
        self.swapped = 0

    def request(self, request: Request) -> None:
        with self._cond:
            self._pending.append(request)
            self.requested += 1
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, daemon=True, name="jaxtrack-optimise")
                self._thread.start()

    def wait(self, timeout: float | None = None) -> bool:
        """Block until every requested program is swapped in or given up; False on timeout."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            while self._pending or self._busy:
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    return False
                self._cond.wait(left)
        return True

    def at_exit(self) -> None:
        """A load in flight is joined (XLA aborts a process that exits while it compiles in a thread); a child is left
        to finish (its compile serves the next process)."""
        with self._cond:
            while self._loading:
                self._cond.wait()

    def _run(self) -> None:
        time.sleep(BATCH_WAIT_S)
        while True:
            with self._cond:
                batch, self._pending = self._pending, []
                if not batch:
                    self._thread = None
                    self._cond.notify_all()
                    return
                self._busy = True
            try:
                self._optimise(batch)
            except Exception as error:  # noqa: BLE001  (the quick programs keep running)
                self.failures.append(f"{type(error).__name__}: {error}")
            finally:
                with self._cond:
                    self._busy = False
                    self._cond.notify_all()

    def _optimise(self, batch: list[Request]) -> None:
        own, others = [], []
        for request in batch:
            if is_marked(request.program):
                continue
            (own if _take_lock(request.program) else others).append(request)
        if own:
            _run_child(own, self.failures)
        for request in others:  # another process's child compiles it: wait for its lock to go
            lock = lock_path(request.program)
            while lock.exists() and time.time() - _mtime(lock) < LOCK_STALE_S:
                time.sleep(POLL_S)
        for request in batch:
            if not is_marked(request.program):
                continue
            entry = request.make_entry()
            with self._cond:
                self._loading = True
            try:
                entry.compile(request.structs)  # a hit in the compile cache the child filled
            finally:
                with self._cond:
                    self._loading = False
                    self._cond.notify_all()
            request.swap(entry)
            self.swapped += 1


def _mtime(path: pathlib.Path) -> float:
    try:
        return path.stat().st_mtime
    except OSError:
        return 0.0


def _take_lock(program: pathlib.Path) -> bool:
    lock = lock_path(program)
    for _ in range(2):
        try:
            handle = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        except FileExistsError:
            if time.time() - _mtime(lock) < LOCK_STALE_S:
                return False
            with contextlib.suppress(OSError):
                lock.unlink()  # a dead child's: take it over
            continue
        except OSError:
            return False
        with os.fdopen(handle, "w") as file:
            file.write(str(os.getpid()))
        return True
    return False


def _run_child(requests: list[Request], failures: list[str]) -> None:
    spec = {
        "programs": [{"path": str(r.program), "avals": [[list(shape), dtype] for shape, dtype in r.avals]} for r in requests],
        "x64": bool(jax.config.jax_enable_x64),
        "cache_dir": str(jax.config.jax_compilation_cache_dir),
        "min_compile_s": float(jax.config.jax_persistent_cache_min_compile_time_secs),
        "mark": mark_content(),
    }
    handle, spec_path = tempfile.mkstemp(prefix="jaxtrack-optimise-", suffix=".json")
    with os.fdopen(handle, "w") as file:
        json.dump(spec, file)
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=os.pathsep.join(p for p in sys.path if p))
    # Its messages go to a file, not a pipe: a child whose parent has exited would write into a closed pipe.
    with tempfile.TemporaryFile() as log:
        try:
            # A session of its own: the child finishes its compile after this process exits (or is interrupted).
            proc = subprocess.Popen([sys.executable, "-m", "jaxtrack._tiered", spec_path], env=env, stdin=subprocess.DEVNULL,
                                    stdout=subprocess.DEVNULL, stderr=log, start_new_session=True)
        except OSError as error:
            for r in requests:
                with contextlib.suppress(OSError):
                    lock_path(r.program).unlink()
            failures.append(f"the optimising process did not start: {error}")
            return
        proc.wait()
        if proc.returncode != 0:
            log.seek(0)
            failures.append(f"the optimising process exited {proc.returncode}: {log.read().decode(errors='replace')[-800:]}")


_OPTIMISER = _Optimiser()
atexit.register(_OPTIMISER.at_exit)


def request(req: Request) -> None:
    """Optimise a program in the background (see the module's docstring)."""
    _OPTIMISER.request(req)


def wait_for_optimised_programs(timeout: float | None = None) -> bool:
    """Wait until the tracker's programs compiled quickly for the first frame are replaced by their optimised builds
    (or the attempt failed: `optimise_failures()` says why). Returns False if `timeout` (s) ran out first. A no-op where
    nothing was compiled in two tiers (a warm cache, `$JAXTRACK_FUSION_EMITTERS` = 0 or 1, no on-disk cache)."""
    return _OPTIMISER.wait(timeout)


def optimise_counts() -> tuple[int, int]:
    """(programs this process asked to optimise, programs it swapped in)."""
    return _OPTIMISER.requested, _OPTIMISER.swapped


def optimise_failures() -> list[str]:
    """Why background optimisations of this process failed (empty when none did)."""
    return list(_OPTIMISER.failures)


def _child_main(spec_path: str) -> int:
    """Compile each program of the spec with XLA's defaults into the compile cache, then mark it (the child)."""
    with contextlib.suppress(OSError, AttributeError):
        os.nice(CHILD_NICE)
    spec = json.loads(pathlib.Path(spec_path).read_text())
    with contextlib.suppress(OSError):
        os.unlink(spec_path)
    jax.config.update("jax_enable_x64", spec["x64"])
    jax.config.update("jax_compilation_cache_dir", spec["cache_dir"])
    jax.config.update("jax_persistent_cache_min_compile_time_secs", spec["min_compile_s"])
    from ._exported import _Entry, _loads

    device = jax.devices("cpu")[0]
    status = 0
    for program in spec["programs"]:
        path = pathlib.Path(program["path"])
        try:
            stored = _loads(path.read_bytes())
            entry = _Entry(jax.export.deserialize(stored["exported"]), *stored["out"], device, None)
            entry.compile([jax.ShapeDtypeStruct(tuple(shape), dtype) for shape, dtype in program["avals"]])
            handle, temporary = tempfile.mkstemp(prefix=f".{mark_path(path).name}.", dir=path.parent)
            with os.fdopen(handle, "w") as file:
                file.write(spec["mark"])
            os.replace(temporary, mark_path(path))
        except Exception as error:  # noqa: BLE001  (reported through the exit status; the parent keeps the quick build)
            print(f"{path.name}: {type(error).__name__}: {error}", file=sys.stderr)
            status = 1
        finally:
            with contextlib.suppress(OSError):
                lock_path(path).unlink()
    return status


if __name__ == "__main__":
    if len(sys.argv) != 2:
        raise SystemExit("usage: python -m jaxtrack._tiered SPEC.json (started by jaxtrack itself)")
    warnings.simplefilter("ignore")
    raise SystemExit(_child_main(sys.argv[1]))
