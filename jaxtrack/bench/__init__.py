"""Evaluation at scale: `run_bench` tracks every sequence of a dataset (RBOT's, BCOT's or BOP layout) under a protocol,
on Ray workers or in this process, and writes per-sequence results and aggregated tables (`jaxtrack bench`).

    OUT/bench.json        what the bench was asked (dataset, layout, settings); a resumed bench must match it
    OUT/runs/...          per sequence: the BOP results CSV + frames.jsonl (written frame by frame) and its figures
    OUT/bench.md/.csv/.png  the tables and the plot (`jaxtrack.bench._report`)

Resumable: a job whose figures exist (and whose results are complete) is not run again, so an interrupted bench
continues where it stopped; a job that raised is reported with its error and the others finish.
"""

from __future__ import annotations

import dataclasses
import json
import os
import pathlib
import time

from ._datasets import LAYOUTS as LAYOUTS
from ._datasets import BenchItem as BenchItem
from ._datasets import detect_layout as detect_layout
from ._datasets import find_items as find_items
from ._harness import ExperimentClock as ExperimentClock
from ._harness import command_line as command_line
from ._harness import output_path as output_path
from ._harness import report_header as report_header
from ._harness import save_text as save_text
from ._harness import source_state as source_state
from ._harness import start_experiment as start_experiment
from ._jobs import PROTOCOLS as PROTOCOLS
from ._jobs import BenchJob as BenchJob
from ._jobs import BenchSettings as BenchSettings
from ._jobs import auc as auc
from ._jobs import jobs_for as jobs_for
from ._jobs import run_job as run_job
from ._profile import KernelProfile as KernelProfile
from ._profile import SourceFrame as SourceFrame
from ._profile import innermost_in as innermost_in
from ._profile import instruction_frames as instruction_frames
from ._profile import profile_kernels as profile_kernels


@dataclasses.dataclass
class BenchReport:
    """What `run_bench` did.

    Attributes:
        results: one dict per job (`jaxtrack.bench.run_job`'s figures, or its "error"), in job order.
        skipped: keys of the jobs found finished in OUT (resume); failed: keys of the jobs that raised.
        markdown, csv, plot: the written tables (plot None without matplotlib); wall_s: the bench's seconds.
        executor: "sequential" or "ray (N node(s), C CPUs)".
    """

    results: list
    skipped: list
    failed: list
    markdown: pathlib.Path
    csv: pathlib.Path
    plot: pathlib.Path | None
    wall_s: float
    executor: str


def _check_request(out: pathlib.Path, request: dict) -> None:
    """OUT/bench.json: written on the first run; a later run into the same folder must ask the same dataset/settings."""
    path = out / "bench.json"
    if path.is_file():
        try:
            before = json.loads(path.read_text())
        except json.JSONDecodeError as e:
            raise ValueError(f"{path}: not JSON ({e}); remove it or use another -o folder") from e
        if not isinstance(before, dict):
            raise ValueError(f"{path}: not a bench's description (a JSON object); remove it or use another -o folder")
        theirs = {"dataset": before.get("dataset"), "layout": before.get("layout"), **(before.get("tracker") or {})}
        ours = {"dataset": request["dataset"], "layout": request["layout"], **request["tracker"]}
        for key, value in ours.items():
            if theirs.get(key) != value:
                hint = (" (recovery: None = on without resets, the default from 2026-11-28; --recover / --no-recover "
                        "set it)") if key == "recovery" else ""
                raise ValueError(f"-o {out}: its bench.json has {key} = {theirs.get(key)!r}, this bench {value!r}{hint}; "
                                 "use another -o folder (or remove it) to bench something else")
    path.write_text(json.dumps(request, indent=1))


def run_bench(dataset: str | os.PathLike, out: str | os.PathLike, settings: BenchSettings | None = None, *,
              layout: str = "auto", objects: list[str] | None = None, variants: list[str] | None = None,
              workers: int | None = None, address: str | None = None, use_cache: bool = True,
              single_thread: bool = True, timeout_s: float | None = None, progress: bool = True) -> BenchReport:
    """Track and evaluate every sequence of `dataset` under `settings`; write OUT's results and tables.

    Args:
        dataset: the dataset folder; layout: rbot | bcot | bop | auto (from its files).
        out: the output folder (created); a folder of an earlier run of the same bench is resumed.
        settings: protocol and tracker settings (default `BenchSettings()`: RBOT protocol, S = 1, with and without
            resets, all cues). Its x64 field is taken from this process's JAX config.
        objects, variants: only these objects / variants (RBOT variants, BCOT scenes, BOP sequences).
        workers: 0 runs the jobs here one after another; N ≥ 1 runs N Ray worker processes, on a local instance
            started with N CPUs or on the cluster at `address` (default: one per CPU of either).
        address: join a running Ray cluster (host:port of `ray start --head`, or "auto") instead of starting one.
        use_cache: the workers use the on-disk compilation cache.
        single_thread: each Ray worker uses one XLA thread (the processes share the cores). At XLA's default
            optimisation level its poses are bit-identical to a multi-threaded run's; at level 0 (the test suite's)
            they differ in the last bits, so False keeps this process's threading for an exact comparison there.
        timeout_s: on Ray, runs not finished after this many seconds are reported as failed and the workers stopped
            (a resumed bench runs them again).
        progress: a progress bar over the sequences with the ETA.

    Raises:
        ValueError: a dataset or option that does not fit (naming it), or an OUT made by another bench.
    """
    import jax

    from ..io import prepare_output_folder
    from ._executor import run_on_ray, run_sequential
    from ._jobs import finished_result
    from ._report import markdown, plot, write_csv

    settings = BenchSettings() if settings is None else settings
    settings = dataclasses.replace(settings, x64=bool(jax.config.jax_enable_x64))
    if workers is not None and int(workers) < 0:
        raise ValueError(f"--workers must be ≥ 0, got {workers}")
    sequential = workers is not None and int(workers) == 0
    if sequential and address:
        raise ValueError("--workers 0 runs the sequences in this process, --address on a Ray cluster: give one of them")
    if sequential and timeout_s is not None:
        raise ValueError("--timeout-min bounds a run on Ray; with --workers 0 stop it with Ctrl-C (the same command "
                         "resumes it)")
    items = find_items(dataset, layout, objects=objects, variants=variants)
    out = prepare_output_folder(out, "-o/--out").resolve()  # the workers do not share this process's folder
    request = {"dataset": str(pathlib.Path(dataset).resolve()), "layout": items[0].layout,
               "tracker": settings.tracker_dict(), "protocol": settings.protocol,
               "frame_steps": list(settings.frame_steps), "resets": list(settings.resets)}
    _check_request(out, request)
    jobs = jobs_for(items, settings)
    results, skipped, todo = {}, [], []
    for job in jobs:
        done = finished_result(job, settings, out)
        if done is not None:
            results[job.key] = done
            skipped.append(job.key)
        else:
            todo.append(job)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(jobs), initial=len(skipped), desc="bench", unit="seq")

    def on_result(result: dict) -> None:
        results[result["key"]] = result
        if bar is not None:
            if result.get("error"):
                bar.write(f"{result['key']}: FAILED: {result['error']}")
            bar.update(1)
            bar.set_postfix_str(result["key"][-40:])

    start = time.perf_counter()
    try:
        if not todo:
            executor = "nothing to run (every job finished before)"
        elif sequential:
            run_sequential(todo, settings, out, on_result, use_cache)
            executor = "sequential (this process)"
        else:
            info = run_on_ray(todo, settings, out, on_result, workers=workers, address=address, use_cache=use_cache,
                              single_thread=single_thread, timeout_s=timeout_s,
                              tick=None if bar is None else bar.refresh)
            executor = f"ray ({info['nodes']} node(s), {info['cpus']} CPUs, {info['workers']} worker(s))"
    finally:
        if bar is not None:
            bar.close()
    wall = time.perf_counter() - start
    ordered = [results[j.key] for j in jobs if j.key in results]
    failed = [r["key"] for r in ordered if r.get("error")]
    header = [f"Dataset: `{request['dataset']}` ({request['layout']} layout, {len(items)} sequences); protocol "
              f"{settings.protocol}; cues {'+'.join(settings.cues)}"
              + (f", region {settings.region}" if settings.region else "")
              + (f", pose prior {list(settings.pose_prior)}" if settings.pose_prior else "")
              + (f", late rounds (K, f, τ) {list(settings.late_rounds)}" if settings.late_rounds else "")
              + ("; the runs without resets search after a LOST frame (with the lines)" if settings.recovery is not False else "") + ".",
              f"Ran {len(todo)} job(s) in {wall:.1f} s on {executor}; {len(skipped)} found finished; {len(failed)} failed.",
              ("Success: frames after the first within 5 cm / 5° of the truth. AUC: ADD / ADD-S accuracy over thresholds "
              "0-10 cm. ms/frame: median of the steps after the second frame (the workers ran side by side).")]
    md = out / "bench.md"
    md.write_text(markdown(ordered, "jaxtrack bench", header))
    csv = write_csv(ordered, out / "bench.csv")
    png = plot(ordered, out / "bench.png")
    return BenchReport(results=ordered, skipped=skipped, failed=failed, markdown=md, csv=csv, plot=png, wall_s=wall,
                       executor=executor)
