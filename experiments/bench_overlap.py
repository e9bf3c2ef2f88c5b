"""Does running the host's SIFT while the device computes the frame's start pay? Frames alternating in one process.

`Tracker.step` can dispatch `start_frame` (crops, render at χ_t, the flow) as a program of its own before the host
detects and matches SIFT keypoints, then finish the frame with `track_step(early=)` (`Tracker.overlap_host`). Run
times on this shared 2-core machine drift by ±20 % between processes, so the modes are compared frame by frame in
one process: the same tracker tracks the bench's textured box forward and back, the mode alternating every frame
(the poses are the same in every mode; the compiled programs are loaded or made before the timed frames). Per rig:

- `one program`: `overlap_host = False` (host first, then the whole step);
- `overlapped`: `overlap_host = True` (forced, whatever the rig);
- the default (`overlap_host = None`) is `overlapped` where the rig has fewer cameras than the machine has cores.

    python experiments/bench_overlap.py            # experiments/results/bench_overlap.md
    python experiments/bench_overlap.py --quick    # smoke run: 1 camera, 6 frames, no file
"""

from __future__ import annotations

import argparse
import os
import pathlib
import tempfile

import numpy as np

from jaxtrack.bench import command_line, output_path, report_header, save_text, start_experiment

RESULTS = pathlib.Path(__file__).resolve().parent / "results"
MODES = {"one program": False, "overlapped": True}


def measure(seq_dir: pathlib.Path, passes: int) -> dict:
    """ms per frame of each mode (the host time of `Tracker.step`) over `passes` forward-and-back passes."""
    from jaxtrack.geometry import make_camera, rotation_error_deg, stack_cameras
    from jaxtrack.io import load_mesh, read_sequence
    from jaxtrack.track import Tracker, TrackerConfig

    seq = read_sequence(seq_dir)
    rig = stack_cameras([make_camera(w.K, w.width, w.height, w.T_cam_world[:3, :3], w.T_cam_world[:3, 3]) for w in seq.views])
    T_world = np.einsum("ij,fjk->fik", np.linalg.inv(np.asarray(seq.views[0].T_cam_world, np.float64)), seq.views[0].T_cam_obj[1])
    frames = [np.stack([w.read_frame(k, dtype=None) for w in seq.views]) for k in range(seq.num_frames)]
    tracker = Tracker(load_mesh(seq.model_paths[1]), rig, config=TrackerConfig(cues=("region", "flow", "sift")))
    state = tracker.start(frames[0], T_world[0])
    order = (list(range(1, seq.num_frames)) + list(range(seq.num_frames - 2, -1, -1))) * passes
    names = list(MODES)
    times = {name: [] for name in names}
    errors = []
    for i, k in enumerate(order):
        name = names[i % 2]
        tracker.overlap_host = MODES[name]
        state, result, info = tracker.step(state, frames[k])
        errors.append(float(rotation_error_deg(np.asarray(result.T_world_root)[:3, :3], T_world[k][:3, :3])))
        if i >= 2 * len(names):  # the first frames of each mode compile (or load) its programs
            times[name].append(1000.0 * info["timings"]["total_s"])
    return {"times": times, "frames": len(order), "rot_deg": float(np.mean(errors)), "cameras": len(seq.views)}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cameras", default="1,4", help="rigs to measure (comma-separated camera counts)")
    ap.add_argument("--frames", type=int, default=24, help="frames of the bench sequence")
    ap.add_argument("--passes", type=int, default=3, help="forward-and-back passes over the sequence")
    ap.add_argument("--quick", action="store_true", help="smoke run: 1 camera, 6 frames, one pass, no file")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    if args.quick:
        args.cameras, args.frames, args.passes = "1", 6, 1
    with tempfile.TemporaryDirectory(prefix="bench_overlap_") as tmp:
        clock = start_experiment(cache=pathlib.Path(tmp) / "cache")  # kept programs: the overlap needs them (async dispatch)
        import bench_track as bt

        rows = []
        for cams in [int(c) for c in args.cameras.split(",")]:
            seq_dir, _ = bt.write_bench_sequence(pathlib.Path(tmp) / f"seq{cams}", cams, args.frames, 1.0)
            rows.append(measure(seq_dir, args.passes))
            r = rows[-1]
            print(f"{cams} camera(s): " + ", ".join(f"{n} {np.median(t):.1f} ms" for n, t in r["times"].items()), flush=True)
    lines = ["# Host SIFT overlapped with the device's frame start, or one program after the host", ""]
    lines += report_header(command_line(__file__, argv), clock.load_start, os.getloadavg(), clock.elapsed_s())
    lines += ["", (f"Sequence: the bench's textured box (`bench_track.py`), 640x480, {args.frames} frames, tracked forward and back "
                   f"{args.passes} times by one tracker (lines + flow + SIFT, 96x128 working resolution), the mode alternating every "
                   "frame; ms per frame = `Tracker.step`'s host time, median (mean) over the frames after each mode's first two. "
                   f"This machine has {os.cpu_count()} cores; the host detects one camera per core."), "",
              "| cameras | frames | one program ms | overlapped ms | overlapped / one | default (`overlap_host=None`) | mean rot ° |",
              "|---:|---:|---:|---:|---:|---|---:|"]
    for r in rows:
        one, over = (np.asarray(r["times"][n]) for n in MODES)
        default = "overlapped" if r["cameras"] < (os.cpu_count() or 1) else "one program"
        lines.append(f"| {r['cameras']} | {r['frames']} | {np.median(one):.1f} ({one.mean():.1f}) | {np.median(over):.1f} "
                     f"({over.mean():.1f}) | {np.median(over) / np.median(one):.2f} | {default} | {r['rot_deg']:.2f} |")
    text = "\n".join(lines) + "\n"
    print(text)
    save_text(output_path(args.out, RESULTS / "bench_overlap.md", args.quick), text)


if __name__ == "__main__":
    main()
