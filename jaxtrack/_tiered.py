"""Two tiers of the tracker's large programs: a quick compile now, the optimised program from a background process.

XLA:CPU compiles the tracker's step programs (`track_step`, `start_frame`) with its MLIR fusion emitters in about 1.5
times the time of its older elemental emitters, and the programs it makes run 15-30 % faster (README "Fast compile,
slower frames"). With an empty compile cache a `persistent_jit(..., tiered=True)` program (`$JAXTRACK_FUSION_EMITTERS`
unset or `auto`, on the CPU, with the on-disk caches on) is compiled with the quick options first, so the first frame
waits for the shorter compile; once it has run, a child process (`python -m jaxtrack._tiered_child`, at a lower priority)
compiles the exported program with XLA's defaults into the shared on-disk compile cache and marks it done
(`<program>.jaxexport.optimised`); this process then loads it from that cache in a background thread and the calls
after that run the optimised program (the same program, compiled otherwise: poses agree to float rounding, not bit for
bit). A later process that finds the mark loads the optimised program at once.

The child outlives this process (a short run leaves the compile to finish for the next one); one child at a time
compiles a given program (a lock file beside it, holding the child's pid: a lock whose process is gone, or older than
`LOCK_STALE_S`, is taken over). The child marks a program only once a second compile found it in the cache (a cache
write that failed, a full disk, leaves no mark). `wait_for_optimised_programs` waits for the swap (benchmarks time the
steady state after it).
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
from collections.abc import Callable

import jax

MARK_SUFFIX = ".optimised"
LOCK_SUFFIX = ".optimising"
# Requests arriving within this time of the first share one child (a step's two programs run milliseconds apart).
BATCH_WAIT_S = 0.5
# A lock file this old belongs to a child that died without removing it (a compile takes 10-30 s).
LOCK_STALE_S = 600.0
# How often a process whose program another process's child compiles looks for the mark.
POLL_S = 0.5


def mark_path(program: pathlib.Path) -> pathlib.Path:
    return program.with_name(program.name + MARK_SUFFIX)


def lock_path(program: pathlib.Path) -> pathlib.Path:
    return program.with_name(program.name + LOCK_SUFFIX)


def mark_content() -> str:
    """What decides whether the compile cache holds a program's optimised executable besides the program itself: the
    cache folder (where it lives) and $XLA_FLAGS (part of XLA's cache key)."""
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
    make_entry: Callable
    swap: Callable
    structs: tuple


class _Optimiser:
    """The background thread that runs children and swaps their programs in, one batch at a time."""

    def __init__(self):
        self._cond = threading.Condition()
        self._pending: list[Request] = []
        self._busy = False  # a batch is in flight
        self._loading = False  # this process is loading an optimised executable (XLA; not to be left at exit)
        self._closing = False  # the interpreter is exiting: no new load starts
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
        """A load in flight is joined (XLA aborts a process that exits while it compiles in a thread) and no new one
        starts (other exit handlers may still wait a while); a child is left to finish (its compile serves the next
        process)."""
        with self._cond:
            self._closing = True
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
        waiting = [r for r in batch if not is_marked(r.program)]
        for _ in range(2):  # a program whose lock holder gave up unmarked is tried once more by this process
            own = [r for r in waiting if _take_lock(r.program)]
            if own:
                _run_child(own, self.failures)
            for request in waiting:  # another process's child compiles these: wait for its lock to go
                while _lock_held(request.program):
                    time.sleep(POLL_S)
            waiting = [r for r in waiting if r not in own and not is_marked(r.program)]
            if not waiting:
                break
        for request in batch:
            if not is_marked(request.program):
                continue
            entry = request.make_entry()
            with self._cond:
                if self._closing:
                    return
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


def _holder(lock: pathlib.Path) -> int | None:
    try:
        return int(lock.read_text().strip())
    except (OSError, ValueError):
        return None


def _alive(pid: int | None) -> bool:
    if pid is None:
        return True  # not written yet: count it as held until it is stale
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # another user's process
        return True
    return True


def _lock_held(program: pathlib.Path) -> bool:
    """Whether a live process holds `program`'s lock (one whose holder is gone, or older than `LOCK_STALE_S`, is not)."""
    lock = lock_path(program)
    return lock.exists() and time.time() - _mtime(lock) < LOCK_STALE_S and _alive(_holder(lock))


def _write_holder(lock: pathlib.Path, pid: int) -> None:
    with contextlib.suppress(OSError):
        lock.write_text(str(pid))


def _release(program: pathlib.Path, pid: int) -> None:
    """Remove `program`'s lock if `pid` still holds it (not one another process took over)."""
    lock = lock_path(program)
    if _holder(lock) == pid:
        with contextlib.suppress(OSError):
            lock.unlink()


def _take_lock(program: pathlib.Path) -> bool:
    lock = lock_path(program)
    for _ in range(2):
        try:
            handle = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        except FileExistsError:
            if _lock_held(program):
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


def _child_environment() -> dict:
    """This environment with the folder that holds this `jaxtrack` first on the child's path, on the CPU."""
    root = str(pathlib.Path(__file__).resolve().parent.parent)
    path = os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH", "")) if p)
    return dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=path)


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
    # Its messages go to a file, not a pipe: a child whose parent has exited would write into a closed pipe.
    with tempfile.TemporaryFile() as log:
        try:
            # A session of its own: the child finishes its compile after this process exits (or is interrupted).
            proc = subprocess.Popen([sys.executable, "-m", "jaxtrack._tiered_child", spec_path], env=_child_environment(),
                                    stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=log, start_new_session=True)
        except OSError as error:
            for r in requests:
                _release(r.program, os.getpid())
            with contextlib.suppress(OSError):
                os.unlink(spec_path)
            failures.append(f"the optimising process did not start: {error}")
            return
        for r in requests:  # the child holds them now (it may outlive this process)
            _write_holder(lock_path(r.program), proc.pid)
        proc.wait()
        for r in requests:  # a child that died before it released them
            _release(r.program, proc.pid)
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
