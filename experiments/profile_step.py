"""Where the tracker's step spends its time, by line of Python: the JAX profiler on the whole compiled step.

`bench_track.py --breakdown-cameras` jits each stage alone, which loses XLA's fusion across stages and its scheduling
on the two cores; this script profiles the step as the tracker runs it (`jaxtrack.bench.profile_kernels`): the
sequence is tracked once (compiling), then again under `jax.profiler.trace`, and every kernel of the programs is
attributed to the Python lines that made it (the optimised HLO's stack frames). Kernel time is summed over XLA's
threads (loops' and calls' own events left out: their bodies count), so it can exceed the wall time where kernels
run side by side on the two cores.

    python experiments/profile_step.py                        # the 4-camera human (walk, 120 fps): experiments/results/profile_step_human.md
    python experiments/profile_step.py --target box --cameras 1   # the bench_track box, 640x480
"""

from __future__ import annotations

import argparse
import os
import pathlib
import sys
import tempfile
import time

import numpy as np

from jaxtrack.bench import command_line, innermost_in, profile_kernels, report_header, save_text, start_experiment

RESULTS = pathlib.Path(__file__).resolve().parent / "results"


def sequence_for(args, folder: pathlib.Path) -> pathlib.Path:
    """The sequence to profile: the human walk at 120 fps (4 cameras, 320x240) or bench_track's textured box."""
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
    if args.target == "human":
        import human_table2

        return human_table2.write_motion_sequences("walk", args.frames + 1, [120], 0.5, folder, "photo")[120]
    import bench_track

    return bench_track.write_bench_sequence(folder / "box", args.cameras, args.frames, 1.0)[0]


def table(counter, frames: int, top: int, total_ns: float) -> list[str]:
    rows = ["| ms / frame | share | where (file:function[:line]) |", "|---:|---:|---|"]
    for name, ns in counter.most_common(top):
        rows.append(f"| {ns / frames / 1e6:.2f} | {100 * ns / total_ns:.1f} % | `{name}` |")
    return rows


def kernel_table(profile, frames: int, top: int, total_ns: float) -> list[str]:
    choose = innermost_in()
    rows = ["| ms / frame | share | launches / frame | µs / launch | kernel (program) | line |", "|---:|---:|---:|---:|---|---|"]
    for key, ns in profile.ns.most_common(top):
        frame = choose(profile.frames.get(key, ()))
        where = frame.short() if frame is not None else "unattributed"
        n = profile.count[key]
        rows.append(f"| {ns / frames / 1e6:.2f} | {100 * ns / total_ns:.1f} % | {n / frames:.1f} | {ns / n / 1e3:.0f} | "
                    f"`{key[1]}` ({key[0]}) | `{where}` |")
    return rows


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--target", choices=("human", "box"), default="human")
    parser.add_argument("--cameras", type=int, default=1, help="cameras of the box (the human has 4)")
    parser.add_argument("--frames", type=int, default=12, help="frames tracked (the first initialises)")
    parser.add_argument("--cues", default="region+flow+sift")
    parser.add_argument("--top", type=int, default=25, help="rows per table")
    parser.add_argument("--seq-dir", default=None, help="keep the rendered sequence here")
    parser.add_argument("--out", default=None, help="markdown (default: experiments/results/profile_step_<target>.md)")
    args = parser.parse_args(argv)
    if args.frames < 3:
        parser.error(f"--frames must be ≥ 3 (the first initialises, the second compiles), got {args.frames}")
    clock = start_experiment(compile_tiers=False)

    from jaxtrack.io import read_sequence
    from jaxtrack.track import track_sequence

    with tempfile.TemporaryDirectory() as scratch:
        folder = pathlib.Path(args.seq_dir or scratch)
        seq = read_sequence(sequence_for(args, folder))
        cues = tuple(args.cues.split("+"))
        track = lambda: track_sequence(seq, cues=cues, progress=False, max_frames=args.frames)
        track()  # compiles every program; the profiled run below loads nothing and compiles nothing
        runs, wall = [], []

        def timed_track():
            t0 = time.perf_counter()
            runs.append(track())
            wall.append(time.perf_counter() - t0)

        profile = profile_kernels(timed_track)
        wall_s = wall[0]
    steps = args.frames - 1
    step_wall = [t["total_s"] for t in runs[0].timings[1:]]
    programs = profile.programs()
    total = sum(programs.values())
    lines = [f"# Where the step spends its time ({args.target}, {args.cues})", ""]
    lines += report_header(command_line(__file__, argv), clock.load_start, os.getloadavg(), time.perf_counter() - clock.started)
    what = ("the CMU walk at 120 fps, 4 cameras at 320x240, the 26-DoF body (`human_table2.py`'s sequence)"
            if args.target == "human" else f"bench_track's textured box, 640x480, {args.cameras} camera(s)")
    lines += ["", (f"Sequence: {what}; {args.frames} frames tracked twice with `track_sequence` (the first run compiles), "
              f"the second under `jax.profiler.trace`: {steps} steps in {wall_s:.1f} s, median host time of a step "
              f"{1000 * float(np.median(step_wall)):.0f} ms (profiler on). Kernel times are summed over XLA's threads "
              "(loops' own events left out), per tracked frame (`ms / frame`: the profiled run's kernels, the first "
              "frame's small programs included, over its frames after the first); `unattributed`: kernels whose instruction names no line of jaxtrack "
              "(copies and layout changes XLA adds, jax's own code)."), "",
              "Kernel time by program (ms per frame; the step's programs are the largest):", ""]
    lines += ["| program id | ms / frame | share |", "|---|---:|---:|"]
    lines += [f"| {p} | {ns / steps / 1e6:.1f} | {100 * ns / total:.1f} % |" for p, ns in programs.most_common(6)]
    lines += ["", "By the innermost line of jaxtrack (what computes):", ""]
    lines += table(profile.by_line(innermost_in()), steps, args.top, total)
    lines += ["", "By the function of that line:", ""]
    lines += table(profile.by_line(innermost_in(), line=False), steps, args.top, total)
    lines += ["", "By the step's own line that led to it (`jaxtrack/track/_step.py`, `jaxtrack/modality/_loop.py`: the stage):",
              ""]
    lines += table(profile.by_line(innermost_in(("jaxtrack/track/_step.py", "jaxtrack/modality/_loop.py"))), steps,
                   args.top, total)
    lines += ["", "The largest kernels (launches per frame, mean µs per launch, the line that made them):", ""]
    lines += kernel_table(profile, steps, args.top, total)
    out = args.out or RESULTS / f"profile_step_{args.target}.md"
    save_text(out, "\n".join(lines) + "\n")
    print("\n".join(lines))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
