"""Running bench jobs: in this process one after another, or on Ray (a local instance started here, or a cluster
joined by address), with a progress bar over the sequences that moves every second.

On Ray, each worker is an actor with one CPU: one process that keeps its traced and compiled programs for its next
sequences (a new object's mesh costs a process a trace of the tracker's step, seconds; `JobQueue` hands a worker
the objects it has seen) and uses one XLA thread (`worker_env`), so the processes share the cores instead of
fighting over them. Every worker reads
and writes the same on-disk compilation cache ($JAXTRACK_CACHE_DIR or ~/.cache/jaxtrack/xla).
"""

from __future__ import annotations

import os
import time
import warnings
from collections.abc import Callable

from ._jobs import BenchJob, BenchSettings, run_job

# One XLA CPU thread per worker process (JAX issue #743's recipe): the bench's parallelism is its processes.
SINGLE_THREAD_XLA = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"


def worker_env(single_thread: bool = True) -> dict:
    """Environment of the Ray workers: this process's JAXTRACK_* and XLA settings, plus (`single_thread`) one XLA
    thread each."""
    env = {k: v for k, v in os.environ.items() if k.startswith("JAXTRACK_")}
    flags = os.environ.get("XLA_FLAGS", "")
    if single_thread and "intra_op_parallelism_threads" not in flags:
        flags = f"{flags} {SINGLE_THREAD_XLA}".strip()
        env["OMP_NUM_THREADS"] = "1"
    if flags:
        env["XLA_FLAGS"] = flags
    return env


def run_sequential(jobs: list[BenchJob], settings: BenchSettings, out, on_result: Callable[[dict], None],
                   use_cache: bool = True) -> None:
    """Every job in this process, in order."""
    for job in jobs:
        on_result(run_job(job, settings, out, use_cache))


def _ray():
    try:
        import ray
    except ImportError as e:
        raise ValueError("--workers: running on Ray needs the ray package: pip install 'jaxtrack[bench]' (or --workers 0 "
                         "to run the sequences one after another in this process)") from e
    return ray


class JobQueue:
    """Which job a free worker takes next: one of an object it has tracked before (a new object costs its process a
    trace of the tracker's step, seconds), else the first job of the object with the most jobs nobody has started,
    else one of the object with the most jobs left (so no worker idles while work remains)."""

    def __init__(self, jobs: list[BenchJob]):
        self.left: dict[str, list[BenchJob]] = {}
        for job in jobs:
            self.left.setdefault(job.item.group, []).append(job)
        self.started: set[str] = set()
        self.seen: dict[int, list[str]] = {}

    def __len__(self) -> int:
        return sum(len(v) for v in self.left.values())

    def take(self, worker: int) -> BenchJob | None:
        seen = self.seen.setdefault(worker, [])
        for group in seen:
            if self.left.get(group):
                return self.left[group].pop(0)
        fresh = [g for g, v in self.left.items() if v and g not in self.started]
        busy = [g for g, v in self.left.items() if v]
        if not busy:
            return None
        group = max(fresh or busy, key=lambda g: len(self.left[g]))
        self.started.add(group)
        seen.append(group)
        return self.left[group].pop(0)


def _failure(job: BenchJob, error: BaseException) -> dict:
    return {"key": job.key, "name": job.item.name, "group": job.item.group, "variant": job.item.variant,
            "step": job.step, "reset": job.reset, "error": f"{type(error).__name__}: {error}".splitlines()[0],
            "wall_s": float("nan")}


class BenchWorker:
    """A Ray actor's body: one process that runs jobs one at a time and keeps its traced programs between them."""

    def run(self, job: BenchJob, settings: BenchSettings, out: str, use_cache: bool) -> dict:
        return run_job(job, settings, out, use_cache)


def run_on_ray(jobs: list[BenchJob], settings: BenchSettings, out, on_result: Callable[[dict], None], *,
               workers: int | None = None, address: str | None = None, use_cache: bool = True,
               single_thread: bool = True, timeout_s: float | None = None,
               tick: Callable[[], None] | None = None) -> dict:
    """Every job on a pool of Ray actors (one CPU and one process each; `JobQueue` picks their jobs); `on_result` is
    called as each job finishes, `tick` every second.

    Args:
        workers: worker processes (default: one per CPU of the local instance started here, or of the cluster);
            a local instance is started with this many CPUs.
        address: an existing cluster ("auto", or host:port of `ray start --head`); its nodes must see the dataset
            and the output folder at the same paths.
        single_thread: one XLA thread per worker (False: XLA's default, as in this process; see `run_bench`).
        timeout_s: after this many seconds the runs not finished are reported as failed ("timed out") and the
            workers are stopped.

    Returns:
        {"nodes": how many alive nodes ran the bench, "cpus": their CPUs, "workers": the actors}.
    """
    ray = _ray()
    started = False
    if not ray.is_initialized():
        kwargs = {"runtime_env": {"env_vars": worker_env(single_thread)}, "log_to_driver": False, "include_dashboard": False}
        with warnings.catch_warnings():
            # Ray starts its processes with fork + exec, which JAX's at-fork warning cannot tell from a bare fork.
            warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called", category=RuntimeWarning)
            if address:
                ray.init(address=address, **kwargs)
            else:
                ray.init(num_cpus=int(workers or os.cpu_count() or 1), **kwargs)
        started = True
    try:
        nodes = [n for n in ray.nodes() if n.get("Alive")]
        cpus = int(sum(n.get("Resources", {}).get("CPU", 0) for n in nodes))
        free = int(ray.available_resources().get("CPU", 0))
        if free < 1:
            raise ValueError(f"--address {address}: the Ray cluster has no free CPU for a bench worker" if address
                             else "Ray has no free CPU for a bench worker")
        # An actor holds its CPU for its whole life: more actors than free CPUs would wait for ever.
        n_actors = max(1, min(len(jobs), int(workers) if workers else free, free))
        actor_class = ray.remote(num_cpus=1, max_restarts=0)(BenchWorker)
        actors = {i: actor_class.remote() for i in range(n_actors)}
        queue = JobQueue(jobs)
        pending = {}

        def feed(i: int) -> None:
            job = queue.take(i)
            if job is not None:
                pending[actors[i].run.remote(job, settings, str(out), use_cache)] = (i, job)

        for i in list(actors):
            feed(i)
        deadline = None if timeout_s is None else time.monotonic() + float(timeout_s)
        while pending:
            if deadline is not None and time.monotonic() > deadline:
                late = [job for _, job in pending.values()]
                while (job := queue.take(-1)) is not None:
                    late.append(job)
                for job in late:
                    on_result(_failure(job, TimeoutError(f"timed out: the bench's {timeout_s:g} s were over")))
                for actor in actors.values():
                    ray.kill(actor)
                pending.clear()
                break
            done, _ = ray.wait(list(pending), num_returns=1, timeout=1.0)
            for ref in done:
                i, job = pending.pop(ref)
                try:
                    result = ray.get(ref)
                except Exception as e:  # noqa: BLE001 - a worker that died: the job is reported, the others go on
                    on_result(_failure(job, e))
                    actors.pop(i, None)  # its process is gone (max_restarts=0)
                    if not actors:  # nobody left to run the rest: each is reported
                        for _, other in list(pending.values()):
                            on_result(_failure(other, RuntimeError("every Ray worker died")))
                        pending.clear()
                        while (other := queue.take(-1)) is not None:
                            on_result(_failure(other, RuntimeError("every Ray worker died")))
                    continue
                on_result(result)
                feed(i)
            if tick is not None:
                tick()
        return {"nodes": len(nodes), "cpus": cpus, "workers": n_actors}
    finally:
        if started:
            ray.shutdown()
