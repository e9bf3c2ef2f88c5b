"""Running bench jobs: in this process one after another, or on Ray (a local instance started here, or a cluster
joined by address), with a progress bar over the sequences that moves every second.

Each Ray task takes one CPU; a worker process keeps its compiled programs for its next sequences and uses one XLA
thread (`worker_env`), so `workers` processes share the cores instead of fighting over them. Every worker reads
and writes the same on-disk compilation cache ($JAXTRACK_CACHE_DIR or ~/.cache/jaxtrack/xla).
"""

from __future__ import annotations

import os
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


def run_on_ray(jobs: list[BenchJob], settings: BenchSettings, out, on_result: Callable[[dict], None], *,
               workers: int | None = None, address: str | None = None, use_cache: bool = True,
               single_thread: bool = True, tick: Callable[[], None] | None = None) -> dict:
    """Every job as a Ray task (one CPU each); `on_result` is called as each finishes, `tick` every second.

    Args:
        workers: CPUs of the local Ray instance started here (default: this machine's); ignored with `address`.
        address: an existing cluster ("auto", or host:port of `ray start --head`); its nodes must see the dataset
            and the output folder at the same paths.
        single_thread: one XLA thread per worker (False: XLA's default, as in this process; see `run_bench`).

    Returns:
        {"nodes": how many alive nodes ran the bench, "cpus": their CPUs}.
    """
    ray = _ray()
    started = False
    if not ray.is_initialized():
        kwargs = {"runtime_env": {"env_vars": worker_env(single_thread)}, "log_to_driver": False, "include_dashboard": False}
        if address:
            ray.init(address=address, **kwargs)
        else:
            ray.init(num_cpus=int(workers or os.cpu_count() or 1), **kwargs)
        started = True
    try:
        nodes = [n for n in ray.nodes() if n.get("Alive")]
        cpus = int(sum(n.get("Resources", {}).get("CPU", 0) for n in nodes))
        task = ray.remote(num_cpus=1, max_retries=0)(run_job)
        pending = {task.remote(job, settings, str(out), use_cache): job for job in jobs}
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1, timeout=1.0)
            for ref in done:
                job = pending.pop(ref)
                try:
                    result = ray.get(ref)
                except Exception as e:  # noqa: BLE001 - a worker that died: the job is reported, the others go on
                    result = {"key": job.key, "name": job.item.name, "group": job.item.group,
                              "variant": job.item.variant, "step": job.step, "reset": job.reset,
                              "error": f"{type(e).__name__}: {e}".splitlines()[0], "wall_s": float("nan")}
                on_result(result)
            if tick is not None:
                tick()
        return {"nodes": len(nodes), "cpus": cpus}
    finally:
        if started:
            ray.shutdown()
