"""Where the energy of each cue set has its minimum: the tracker started at the true pose and stepped on the same frame.

A frame's pose energy is biased when its minimum lies away from the true pose: the refinement then walks away
from the truth even when it starts there, and tracking drifts by that much per frame (motion cues can only hold
it back). This measures the bias directly, on synthetic sequences with exact truth: for every `--stride`-th
frame k, `Tracker.start(frame k, true pose k)` learns the colour statistics and the appearance at the truth, then
`Tracker.step(frame k)` (no motion: frame t and t+1 are the same image) refines from the truth. The distance the
pose moves is the energy's bias at frame k (rotation, translation, and its depth component: the camera z, which
the silhouette's size pins).

With flow or SIFT in the cue set, frames t and t+1 are the same image, so their rows say "no motion" and hold the
pose where it started: the measure is then how far the region energy's bias gets against that, not the bias itself.

`--step 1` measures one frame of tracking from the truth instead: `Tracker.start(frame k, true pose k)`, then
`Tracker.step(frame k+1)`, and the error against the truth of frame k+1: what a single step of the sequence's
motion costs when it starts from nothing wrong (the bias plus how far the step's basin and prediction fall short),
so that a drift over the sequence can be told apart from the per-frame error it accumulates.

Defaults: the turntable sequences (teapot, truck, teapot with 50 % noise; `turntable.py`'s; `--presets` names other
`jaxtrack.synth` presets), the region alone as the sparse lines (M3T's global colour histograms, `lines`) and as
the dense level set (the paper's local Gaussian densities, `levelset`).

    python experiments/energy_bias.py                    # experiments/results/energy_bias.md / .json
    python experiments/energy_bias.py --cues lines,levelset,lines+flow+sift --stride 2 --seq-dir /tmp/tt
    python experiments/energy_bias.py --cues lines,lines+flow+sift --stride 1 --step 1 --presets turntable-truck
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import pathlib
import shutil
import sys
import tempfile

import numpy as np
import track_presets as tp
from turntable import RUNS

from jaxtrack.bench import command_line, output_path, report_header, save_text, start_experiment

RESULTS = pathlib.Path(__file__).resolve().parent / "results"


def bias_run(seq, cues: tuple[str, ...], frames: list[int], step: int = 0) -> list[dict]:
    """Per frame k of `frames`: start at the truth on frame k, step on frame k + `step` (0: the same frame); the error
    against the truth of frame k + `step` (rotation °, translation and its camera-z component in mm, the status).
    Frames k with k + `step` past the sequence's end are left out."""
    from jaxtrack import Status
    from jaxtrack.geometry import make_camera, rotation_error_deg, stack_cameras
    from jaxtrack.io import load_mesh
    from jaxtrack.track import Tracker, TrackerConfig

    view = seq.views[0]
    oid = min(seq.model_paths)
    rig = stack_cameras([make_camera(view.K, view.width, view.height, view.T_cam_world[:3, :3], view.T_cam_world[:3, 3])])
    T_cam_world = np.asarray(view.T_cam_world, np.float64)
    T_world = np.einsum("ij,fjk->fik", np.linalg.inv(T_cam_world), np.asarray(view.T_cam_obj[oid], np.float64))
    tracker = Tracker(load_mesh(seq.model_paths[oid], seq.model_scale(oid)), rig, config=TrackerConfig(cues=cues))
    rows = []
    for k in (k for k in frames if k + step < len(T_world)):
        image = view.read_frame(k, dtype=None)[None]
        state = tracker.start(image, T_world[k])
        _, result, _ = tracker.step(state, view.read_frame(k + step, dtype=None)[None] if step else image, recover=False)
        T, T_true = np.asarray(result.T_world_root, np.float64), T_world[k + step]
        d_cam = (T_cam_world @ T)[:3, 3] - (T_cam_world @ T_true)[:3, 3]
        rows.append({"frame": k, "rot_deg": float(rotation_error_deg(T[:3, :3], T_true[:3, :3])),
                     "trans_mm": float(np.linalg.norm(d_cam)), "depth_mm": float(d_cam[2]),
                     "status": Status(int(result.status)).name})
    return rows


def summary(rows: list[dict]) -> dict:
    rot = np.array([r["rot_deg"] for r in rows])
    trans = np.array([r["trans_mm"] for r in rows])
    depth = np.array([r["depth_mm"] for r in rows])
    return {"rot_mean": float(rot.mean()), "rot_max": float(rot.max()), "trans_mean": float(trans.mean()),
            "trans_max": float(trans.max()), "depth_mean": float(depth.mean()),
            "depth_abs_max": float(np.abs(depth).max()), "beyond": int(np.sum((rot > 5) | (trans > 50))), "n": len(rows)}


def report(command, load, elapsed_s, runs: dict, sizes: dict, stride: int, step: int = 0) -> str:
    start = f"Every frame k = 0, {stride}, 2·{stride}, ... of each sequence: `Tracker.start` at the true pose of frame k, then "
    depth = "depth: the camera-z component (+: estimated farther)."
    if step:
        title = f"# One step from the true pose: frame k onto frame k+{step}"
        what = (f"{start}`Tracker.step` on frame k+{step}, against the truth of frame k+{step}: the error of one step of the "
                "sequence's motion started from nothing wrong (the energy's bias and what the step's prediction and "
                f"basin miss). {depth} beyond: errors over 5° or 50 mm.")
    else:
        title = "# Energy bias: the step from the true pose on the same frame"
        what = (f"{start}`Tracker.step` on frame k itself (no motion). How far the refined pose lies from the truth is the bias "
                f"of the energy's minimum at that frame (a perfect energy stays put). {depth} beyond: frames moved more than "
                "5° or 50 mm.")
    lines = [title, "", *report_header(command, load[0], load[1], elapsed_s), "", what, "",
             "Sequences: " + "; ".join(f"{label}: {p} {w}x{h}, {n} frames, {s:g} of the pixels uniform noise"
                                       for label, (p, w, h, n, s) in sizes.items()) + ".", "",
             "| sequence | cues | frames | mean rot ° | max rot ° | mean trans mm | max trans mm | mean depth mm | max abs depth mm | beyond |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for (label, cues), rows in runs.items():
        s = summary(rows)
        lines.append(f"| {label} | {cues} | {s['n']} | {s['rot_mean']:.2f} | {s['rot_max']:.2f} | {s['trans_mean']:.1f} | "
                     f"{s['trans_max']:.1f} | {s['depth_mean']:+.1f} | {s['depth_abs_max']:.1f} | {s['beyond']} |")
    lines += ["", "Per frame (rotation ° / depth mm):", ""]
    for (label, cues), rows in runs.items():
        lines.append(f"- {label}, {cues}: " + ", ".join(f"{r['frame']}: {r['rot_deg']:.1f} / {r['depth_mm']:+.0f}" for r in rows))
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cues", default="lines,levelset", help="cue sets joined with '+', comma-separated ('lines', 'levelset', ...)")
    ap.add_argument("--stride", type=int, default=4, help="every this many-th frame is measured")
    ap.add_argument("--step", type=int, default=0,
                    help="step onto frame k + STEP from the truth of frame k (0, the default: the same frame, the bias)")
    ap.add_argument("--presets", default=None,
                    help="comma-separated jaxtrack.synth presets instead of the turntable sequences (e.g. occluded-box)")
    ap.add_argument("--scale", type=float, default=0.5, help="image scale (1 = 640x480)")
    ap.add_argument("--quick", action="store_true", help="smoke run: the teapot, frames 0 and 1, the lines")
    ap.add_argument("--seq-dir", default=None, help="folder for the rendered sequences (and reuse them)")
    ap.add_argument("--out", default=None,
                    help="markdown output, JSON beside it (default experiments/results/energy_bias.md, with --presets "
                         "energy_bias_<presets>.md; --quick: none)")
    args = ap.parse_args(argv)
    if args.stride < 1:
        raise SystemExit("energy_bias: --stride must be ≥ 1")
    if args.step < 0:
        raise SystemExit("energy_bias: --step must be ≥ 0")
    command = command_line(__file__, argv)
    cue_sets = tp.parse_subsets("lines" if args.quick else args.cues)
    runs_def = RUNS[:1] if args.quick else RUNS
    if args.presets and not args.quick:
        runs_def = tuple((p, p, 0.0) for p in args.presets.split(","))
    clock = start_experiment(cache=not args.quick)
    seq_dir = pathlib.Path(args.seq_dir) if args.seq_dir else pathlib.Path(tempfile.mkdtemp(prefix="energy_bias_"))
    from jaxtrack.io import read_sequence

    runs, sizes = {}, {}
    try:
        seqs = {}
        for label, preset, salt in runs_def:
            cfg = dataclasses.replace(tp.preset_config(preset, args.scale, 2 if args.quick else None), salt_fraction=salt)
            seqs[label] = read_sequence(tp.write_preset(f"{preset}-salt{round(100 * salt)}", cfg, seq_dir))
            sizes[label] = (preset, cfg.width, cfg.height, cfg.frames, salt)
        for cues in cue_sets:
            for label, _, _ in runs_def:
                seq = seqs[label]
                frames = list(range(0, seq.num_frames, 1 if args.quick else args.stride))
                runs[(label, cues)] = bias_run(seq, tuple(cues.split("+")), frames, args.step)
                s = summary(runs[(label, cues)])
                print(f"[energy_bias] {label} {cues}: rot {s['rot_mean']:.2f}° (max {s['rot_max']:.2f}), depth "
                      f"{s['depth_mean']:+.1f} mm ({clock.minutes():.1f} min)", file=sys.stderr, flush=True)
    finally:
        if not args.seq_dir:
            shutil.rmtree(seq_dir, ignore_errors=True)
    text = report(command, (clock.load_start, os.getloadavg()), clock.elapsed_s(), runs, sizes, 1 if args.quick else args.stride,
                  args.step)
    print(text)
    # Other sequences than the turntable's go to their own file by default: energy_bias.md stays the turntable's.
    default = "energy_bias.md" if not args.presets else f"energy_bias_{args.presets.replace(',', '_').replace('-', '_')}.md"
    if args.step:
        default = default.replace("energy_bias", f"one_step_{args.step}", 1)
    out = output_path(args.out, RESULTS / default, args.quick)
    save_text(out, text)
    if out is not None:
        pathlib.Path(out).with_suffix(".json").write_text(json.dumps({f"{label} | {cues}": rows for (label, cues), rows in runs.items()}))
    return runs


if __name__ == "__main__":
    main()
