"""Where the first frame's time goes with an empty compile cache (issue 23): `Tracker.start` and the first
`Tracker.step` in a fresh process, and XLA's compile time per program from JAX's compile log.

Each configuration runs in its own subprocess with a new, empty on-disk cache folder (`jaxtrack track`'s
settings), on the first frames of the occluded-box preset at 320x240, camera 0; `--repeats` alternates the runs.
Compare two versions of jaxtrack by running this script from each (e.g. a git worktree through `PYTHONPATH`).

    python experiments/first_frame_compile.py                       # experiments/results/first_frame_compile.md
    python experiments/first_frame_compile.py --configs lines,all --repeats 2 --out /tmp/f.md
    python experiments/first_frame_compile.py --quick               # smoke run: lines only, once, no file
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import re
import subprocess
import sys
import tempfile
import time

import track_presets as tp

from jaxtrack.bench import command_line, output_path, report_header, save_text, start_experiment

RESULTS = pathlib.Path(__file__).resolve().parent / "results"
CONFIGS = {  # name: (cues, occlusion detection)
    "lines": ("region",),
    "lines+sift": ("region", "sift"),
    "all": ("region", "flow", "sift"),
}


def worker(seq_dir: str, cues: tuple[str, ...], cache: str) -> dict:
    """In this (fresh) process: Tracker.start + one step with an empty cache; the compile log's times."""
    import io
    import logging

    import jax

    jax.config.update("jax_log_compiles", True)
    log = io.StringIO()
    handler = logging.StreamHandler(log)
    logging.getLogger("jax").addHandler(handler)
    logging.getLogger("jax").setLevel(logging.WARNING)
    import numpy as np

    from jaxtrack import enable_compilation_cache
    from jaxtrack.geometry import make_camera, stack_cameras
    from jaxtrack.io import load_mesh, read_sequence
    from jaxtrack.track import Tracker, TrackerConfig

    enable_compilation_cache(cache)
    seq = read_sequence(pathlib.Path(seq_dir))
    view = seq.views[0]
    rig = stack_cameras([make_camera(view.K, view.width, view.height, view.T_cam_world[:3, :3], view.T_cam_world[:3, 3])])
    oid = min(seq.model_paths)
    T0 = np.linalg.inv(np.asarray(view.T_cam_world, np.float64)) @ np.asarray(view.T_cam_obj[oid][0], np.float64)
    t = time.perf_counter()
    tracker = Tracker(load_mesh(seq.model_paths[oid]), rig, config=TrackerConfig(cues=cues))
    state = tracker.start(view.read_frame(0)[None], T0)
    start_s = time.perf_counter() - t
    state, _, _ = tracker.step(state, view.read_frame(1)[None])
    total_s = time.perf_counter() - t
    text = log.getvalue()
    xla = [float(s) for s in re.findall(r"Finished XLA compilation of .* in ([0-9.]+) sec", text)]
    tracing = [float(s) for s in re.findall(r"Finished tracing .* in ([0-9.]+) sec", text)]
    lowering = [float(s) for s in re.findall(r"Finished jaxpr to MLIR module conversion .* in ([0-9.]+) sec", text)]
    from jaxtrack import wait_for_optimised_programs

    wait_for_optimised_programs(timeout=600)  # after the timing: no background compile beside the next run's
    return {"start_s": start_s, "first_frame_s": total_s, "xla_s": sum(xla), "tracing_s": sum(tracing),
            "lowering_s": sum(lowering), "largest_xla_s": sorted(xla, reverse=True)[:4]}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--configs", default="lines,all", help=f"comma-separated, from {', '.join(CONFIGS)}")
    ap.add_argument("--repeats", type=int, default=2, help="runs per configuration (alternated)")
    ap.add_argument("--quick", action="store_true", help="smoke run: lines only, once, no file")
    ap.add_argument("--out", default=None, help="markdown output (default experiments/results/first_frame_compile.md)")
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        spec = json.loads(args.worker)
        print(json.dumps(worker(spec["seq"], tuple(spec["cues"]), spec["cache"])))
        return None
    if args.quick:
        args.configs, args.repeats = "lines", 1
    names = [c.strip() for c in args.configs.split(",") if c.strip()]
    bad = [c for c in names if c not in CONFIGS]
    if bad or args.repeats < 1:
        raise SystemExit(f"first_frame_compile: --configs from {', '.join(CONFIGS)} (got {bad}); --repeats ≥ 1")
    command = command_line(__file__, argv)
    clock = start_experiment(cache=False, compile_tiers=True)
    runs = {c: [] for c in names}
    with tempfile.TemporaryDirectory(prefix="first_frame_") as tmp:
        cfg = tp.preset_config("occluded-box", 0.5, 3)
        seq = tp.write_preset("occluded-box", cfg, pathlib.Path(tmp))
        for r in range(args.repeats):
            for c in names:
                spec = {"seq": str(seq), "cues": CONFIGS[c], "cache": str(pathlib.Path(tmp) / f"cache_{c}_{r}")}
                out = subprocess.run([sys.executable, __file__, "--worker", json.dumps(spec)], capture_output=True,
                                     check=False, text=True, cwd=pathlib.Path(__file__).resolve().parent, timeout=1200)
                if out.returncode != 0:
                    raise SystemExit(f"first_frame_compile: the {c} run failed:\n{out.stderr[-2000:]}")
                runs[c].append(json.loads(out.stdout.strip().splitlines()[-1]))
                row = runs[c][-1]
                print(f"[first_frame_compile] {c}: first frame {row['first_frame_s']:.1f} s, XLA {row['xla_s']:.1f} s "
                      f"({clock.minutes():.1f} min)", file=sys.stderr, flush=True)
    lines = ["# The first frame with an empty compile cache", ""]
    lines += report_header(command, clock.load_start, os.getloadavg(), clock.elapsed_s())
    legend = ("Fresh process per run, empty cache folder; occluded-box preset at 320x240, camera 0, the tracker's "
              "defaults with the cues named. Times from `Tracker(...)` to the end of the first step (the imports "
              "before it are not counted); XLA, tracing and lowering summed over every program of JAX's compile log.")
    header = ("| cues | run | first frame (s) | of which start (s) | XLA compile (s) | tracing (s) | lowering (s) | "
              "largest programs' XLA compile (s) |")
    lines += ["", legend, "", header, "|---|---:|---:|---:|---:|---:|---:|---|"]
    for c in names:
        for i, row in enumerate(runs[c]):
            largest = ", ".join(f"{x:.1f}" for x in row["largest_xla_s"])
            lines.append(f"| {'+'.join(CONFIGS[c])} | {i + 1} | {row['first_frame_s']:.1f} | {row['start_s']:.1f} | "
                         f"{row['xla_s']:.1f} | {row['tracing_s']:.1f} | {row['lowering_s']:.1f} | {largest} |")
    text = "\n".join(lines) + "\n"
    print(text)
    save_text(output_path(args.out, RESULTS / "first_frame_compile.md", args.quick), text)
    return runs


if __name__ == "__main__":
    main()
