"""The plumbing the benchmark scripts in experiments/ share: the setup of a run (OpenCV on one thread, the on-disk
compilation cache, the start time and load average), the command and header lines their markdown reports begin
with, the commit measured, and where a report is written.

    clock = start_experiment(cache=not args.quick)
    ...
    if clock.over(args.budget_min): ...                       # start no new run
    text = "\\n".join(["# Title", "", *report_header(command_line(__file__, argv), clock.load_start, os.getloadavg(),
                                                     clock.elapsed_s()), ...])
    save_text(output_path(args.out, RESULTS / "name.md", args.quick), text)
"""

from __future__ import annotations

import dataclasses
import os
import pathlib
import platform
import subprocess
import sys
import time

_CHECKOUT = pathlib.Path(__file__).resolve().parents[2]  # jaxtrack/bench/_harness.py → the repository root


def source_state() -> str:
    """The commit measured, and whether the library had uncommitted changes (work in progress).

    Returns:
        "commit abc1234", "commit abc1234 with uncommitted changes in jaxtrack/x.py, jaxtrack/y.py", or
        "unknown (not a git checkout)".
    """
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=_CHECKOUT, capture_output=True, text=True,
                              check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "jaxtrack"], cwd=_CHECKOUT, capture_output=True,
                               text=True, check=True).stdout.split("\n")
    except (OSError, subprocess.CalledProcessError):
        return "unknown (not a git checkout)"
    changed = sorted(line[3:] for line in dirty if line.strip())
    return f"commit {head}" + (f" with uncommitted changes in {', '.join(changed)}" if changed else "")


def command_line(script: str | os.PathLike, argv: list[str] | None) -> str:
    """The command a report quotes: "python experiments/NAME.py ARG ..." for the script file `script` (its
    `__file__`) and the arguments `argv` given to its `main` (None: this process's, sys.argv[1:])."""
    return " ".join([f"python experiments/{pathlib.Path(script).name}", *(sys.argv[1:] if argv is None else argv)])


@dataclasses.dataclass(frozen=True)
class ExperimentClock:
    """When an experiment started and the load average then (`start_experiment` makes one).

    Attributes:
        started: `time.perf_counter()` at the start.
        load_start: `os.getloadavg()` at the start: the load average over 1, 5 and 15 minutes.
    """

    started: float
    load_start: tuple[float, float, float]

    def elapsed_s(self) -> float:
        """Seconds since the start."""
        return time.perf_counter() - self.started

    def minutes(self) -> float:
        """Minutes since the start."""
        return self.elapsed_s() / 60

    def over(self, budget_min: float | None) -> bool:
        """Whether more than `budget_min` minutes have passed (never for None): a script starts no new run then."""
        return budget_min is not None and self.elapsed_s() > 60 * budget_min


def start_experiment(*, cache: bool | str | os.PathLike = True, compile_tiers: bool = False) -> ExperimentClock:
    """Set up this process for a benchmark run and start its clock.

    OpenCV runs on one thread (its idle workers compete with XLA on a 2-core machine). With `cache` (a full run, not
    a --quick smoke run) JAX keeps compiled programs in the on-disk compilation cache
    (`jaxtrack.enable_compilation_cache`, as `jaxtrack track` does), so a rerun, or the next script, loads them
    instead of compiling again: True, its default folder; a path, that folder; False (or ""), no cache.
    `compile_tiers` False (the accuracy experiments): unless $JAXTRACK_FUSION_EMITTERS is set, it is set to 1 here (this
    process and its children): the tracker's step in one build, XLA's optimised one, so that no pose depends on when a
    background compile finished (`jaxtrack._tiered`; the quick build of an empty cache rounds otherwise); True (the
    speed benchmarks): the product's default, two tiers.

    Returns:
        The `ExperimentClock` started now, with the load average now.
    """
    import cv2

    cv2.setNumThreads(1)
    if not compile_tiers:
        os.environ.setdefault("JAXTRACK_FUSION_EMITTERS", "1")
    if cache:
        from .._cache import enable_compilation_cache

        enable_compilation_cache(None if cache is True else os.fspath(cache))
    return ExperimentClock(time.perf_counter(), tuple(os.getloadavg()))


def report_header(command: str, load_start, load_end, elapsed_s: float, *,
                  setup: str = "float32; OpenCV single-threaded", note: str = "") -> list[str]:
    """The lines under a report's title: the command, the machine, the source measured, the load and the run time.

    Args:
        command: the command line (`command_line`); load_start, load_end: `os.getloadavg()` at the start and the
            end; elapsed_s: the run's seconds.
        setup: what the machine line says after the JAX version (precision, threads).
        note: a remark in parentheses after the run time ("" for none).

    Returns:
        Four markdown lines, "Command: `...`", "Machine: CPU, N cores, platform, JAX x.y, {setup}.", "Source: ..."
        (`source_state`), "Load average (1, 5, 15 min) at the start (...), at the end (...); run took M min[ (note)]."
        The first three end in two spaces (a markdown line break).
    """
    import jax

    def rounded(load):
        return tuple(round(x, 2) for x in load)

    return [
        f"Command: `{command}`  ",
        (f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, {jax.devices()[0].platform}, "
         f"JAX {jax.__version__}, {setup}.  "),
        f"Source: {source_state()}  ",
        (f"Load average (1, 5, 15 min) at the start {rounded(load_start)}, at the end {rounded(load_end)}; run took "
         f"{elapsed_s / 60:.1f} min" + (f" ({note})" if note else "") + "."),
    ]


def output_path(option: str | None, default: str | os.PathLike, quick: bool = False) -> str | None:
    """Where a script writes an output: `option` (its --out / --plot / --json value) when given, else nothing for a
    --quick smoke run (`quick`), else `default` (under experiments/results/). Returns the path as a string, or None."""
    if option is not None:
        return option
    return None if quick else str(default)


def save_text(path: str | os.PathLike | None, text: str) -> None:
    """Write `text` to `path`, making its folder; nothing when `path` is None."""
    if path is None:
        return
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
