"""Memory over a long sequence (issue 23): peak resident memory of the tracking process after frame 100
and after frame N (default 1000), all cues, one camera, the default configuration.

The sequence is `bench_track`'s textured box (640x480, ~10 px and 3° per frame), rendered once for
`--clip` frames and played forwards and backwards (a ping-pong of its frames: the object keeps moving,
no frame jumps), so a 1000-frame run needs no 1000 rendered frames. Peak RSS is the kernel's high-water
mark of this process (`resource.getrusage`, ru_maxrss), read after frames 1, 100 and N; the current RSS
(/proc/self/statm) beside it. Memory that grows with the frame count (a list of results, compiled
programs per frame, host caches) shows as a gap between frames 100 and N.

    python experiments/memory_flat.py                      # writes experiments/results/memory_flat.md
    python experiments/memory_flat.py --frames 120 --out /tmp/m.md   # smoke run
"""

from __future__ import annotations

import argparse
import os
import pathlib
import platform
import resource
import subprocess
import sys
import tempfile

import numpy as np

from jaxtrack.bench import command_line, start_experiment

RESULTS = pathlib.Path(__file__).resolve().parent / "results"


def _rss_mib() -> tuple[float, float]:
    """(peak, current) resident memory of this process in MiB."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # KiB on Linux
    with open("/proc/self/statm") as f:
        current = int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    return peak, current


def ping_pong(n_clip: int, n: int) -> list[int]:
    """Frame indices 0, 1, ..., n_clip−1, n_clip−2, ..., 1, 0, 1, ... (n of them)."""
    period = list(range(n_clip)) + list(range(n_clip - 2, 0, -1))
    return [period[k % len(period)] for k in range(n)]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=1000, help="frames to track (≥ 101)")
    ap.add_argument("--clip", type=int, default=24, help="rendered frames played back and forth")
    ap.add_argument("--out", default=None, help="markdown output (default experiments/results/memory_flat.md)")
    args = ap.parse_args(argv)
    if args.frames < 101 or args.clip < 3:
        raise SystemExit("memory_flat: --frames must be ≥ 101 and --clip ≥ 3")
    from bench_track import ALL_CUES, write_bench_sequence  # experiments/ is on sys.path: this script's folder

    from jaxtrack.geometry import make_camera, rotation_error_deg, stack_cameras
    from jaxtrack.io import load_mesh, read_sequence
    from jaxtrack.track import Tracker, TrackerConfig

    clock = start_experiment(cache=False)
    work = pathlib.Path(tempfile.mkdtemp(prefix="memory_flat_"))
    write_bench_sequence(work / "seq", 1, args.clip, 1.0)
    seq = read_sequence(work / "seq")
    view = seq.views[0]
    rig = stack_cameras([make_camera(view.K, view.width, view.height, view.T_cam_world[:3, :3], view.T_cam_world[:3, 3])])
    T_world = np.einsum("ij,fjk->fik", np.linalg.inv(np.asarray(view.T_cam_world, np.float64)), view.T_cam_obj[1])
    frames = [view.read_frame(k, dtype=None) for k in range(args.clip)]
    order = ping_pong(args.clip, args.frames + 1)
    tracker = Tracker(load_mesh(seq.model_paths[1]), rig, config=TrackerConfig(cues=ALL_CUES))
    state = tracker.start(frames[order[0]], T_world[order[0]])
    marks, rot, ms = {}, [], []
    for k in range(1, args.frames + 1):
        state, result, info = tracker.step(state, frames[order[k]])
        T = np.asarray(result.T_world_root)
        rot.append(float(rotation_error_deg(T[:3, :3], T_world[order[k]][:3, :3])))
        ms.append(1000.0 * info["timings"]["total_s"])
        if k in (1, 100, args.frames):
            marks[k] = _rss_mib()
        if k % 100 == 0:
            print(f"[memory_flat] frame {k}: peak {marks.get(k, _rss_mib())[0]:.0f} MiB, rot {rot[-1]:.2f}°", file=sys.stderr,
                  flush=True)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], check=False, capture_output=True, text=True,
                            cwd=pathlib.Path(__file__).resolve().parent).stdout.strip() or "unknown"
    growth = marks[args.frames][0] - marks[100][0]
    lines = [
        "# Memory over a long sequence",
        "",
        f"Command: `{command_line(__file__, argv)}`  ",
        (f"Machine: {platform.machine()}, {os.cpu_count()} cores; source: {commit}; load average at the start "
         f"{tuple(round(x, 2) for x in clock.load_start)}; run took {clock.minutes():.1f} min."),
        "",
        (f"Sequence: bench_track's textured box (640x480), {args.clip} rendered frames played back and forth for "
         f"{args.frames} tracked frames; all cues, one camera, the default configuration (96x128 working resolution)."),
        "",
        "| after frame | peak RSS MiB | current RSS MiB |",
        "|---:|---:|---:|",
        *(f"| {k} | {marks[k][0]:.0f} | {marks[k][1]:.0f} |" for k in sorted(marks)),
        "",
        (f"Peak RSS growth from frame 100 to frame {args.frames}: {growth:+.0f} MiB "
         f"({100 * growth / marks[100][0]:+.1f} %). Median {np.median(ms):.0f} ms per frame; rotation error mean "
         f"{np.mean(rot):.2f}°, max {np.max(rot):.2f}° (the box's known poses)."),
    ]
    text = "\n".join(lines) + "\n"
    print(text)
    out = pathlib.Path(args.out) if args.out else RESULTS / "memory_flat.md"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)


if __name__ == "__main__":
    main()
