"""Which cue loses a sequence: every cue subset, with the flow's structure factor on and off, without resets.

Each synthetic preset named is rendered (or read from `--seq-dir`) and tracked from its first true pose with each cue
subset, once with the tracker's defaults (the flow confidence of eq. 8 times the structure factor,
`TrackerParams.flow_structure` = `FLOW_STRUCTURE`) and once with the factor off (eq. 8 alone, the paper's). Per
run: the mean rotation error, the frames within 5 cm / 5°, and the rotation errors of the first frames (the final
pose and the motion prediction), so that a cue pinning the pose shows as an error growing by the motion per frame.

    python experiments/cue_subsets.py      # turntable-teapot → experiments/results/cue_subsets.md
    python experiments/cue_subsets.py --presets turntable-teapot,occluded-box --cues lines,lines+flow --out /tmp/c.md
"""

from __future__ import annotations

import argparse
import os
import pathlib
import shutil
import tempfile

import numpy as np
import track_presets as tp

from jaxtrack.bench import command_line, start_experiment

RESULTS = pathlib.Path(__file__).resolve().parent / "results"


def track(seq, cues: tuple[str, ...], structure: bool) -> dict:
    """Track camera 0 of `seq` with `cues` (no resets); the flow's structure factor on (the default) or off."""
    import equinox as eqx
    import jax.numpy as jnp

    from jaxtrack.geometry import make_camera, rotation_error_deg, stack_cameras
    from jaxtrack.io import load_mesh
    from jaxtrack.track import Tracker, TrackerConfig, success_mask

    view = seq.views[0]
    rig = stack_cameras([make_camera(view.K, view.width, view.height, view.T_cam_world[:3, :3], view.T_cam_world[:3, 3])])
    oid = min(seq.model_paths)
    T_world = np.einsum("ij,fjk->fik", np.linalg.inv(np.asarray(view.T_cam_world, np.float64)), view.T_cam_obj[oid])
    tracker = Tracker(load_mesh(seq.model_paths[oid]), rig, config=TrackerConfig(cues=cues))
    state = tracker.start(view.read_frame(0)[None], T_world[0])
    params = tracker.params_for(tracker.crop_shape)
    if not structure:
        params = eqx.tree_at(lambda p: p.flow_structure, params, -jnp.ones_like(params.flow_structure))
    rot, pred, ok = [], [], []
    for k in range(1, seq.num_frames):
        state, r, _ = tracker.step(state, view.read_frame(k)[None], params=params)
        T, Tp = np.asarray(r.T_world_root, np.float64), np.asarray(r.T_pred, np.float64)
        rot.append(float(rotation_error_deg(T[:3, :3], T_world[k][:3, :3])))
        pred.append(float(rotation_error_deg(Tp[:3, :3], T_world[k][:3, :3])))
        ok.append(bool(success_mask(rot[-1], float(np.linalg.norm(T[:3, 3] - T_world[k][:3, 3])), 5.0, 50.0)))
    return {"rot": rot, "pred": pred, "success": 100.0 * float(np.mean(ok))}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--presets", default="turntable-teapot", help="comma-separated synthetic presets")
    ap.add_argument("--cues", default="lines,lines+flow,lines+sift,lines+flow+sift", help="cue subsets joined with '+'")
    ap.add_argument("--scale", type=float, default=0.5, help="image scale (1 = 640x480)")
    ap.add_argument("--frames", type=int, default=None, help="frames per preset (default: the preset's own)")
    ap.add_argument("--seq-dir", default=None, help="keep the rendered sequences here (and reuse them)")
    ap.add_argument("--out", default=str(RESULTS / "cue_subsets.md"))
    args = ap.parse_args(argv)
    command = command_line(__file__, argv)

    from jaxtrack.io import read_sequence
    from jaxtrack.track._tracker import FLOW_STRUCTURE

    clock = start_experiment(cache=False)
    seq_dir = pathlib.Path(args.seq_dir) if args.seq_dir else pathlib.Path(tempfile.mkdtemp(prefix="cues_"))
    lines = ["# Which cue loses a sequence (no resets)", "", f"`{command}`", "",
             (f"Camera 0, the tracker's defaults but for the cues; the flow's structure factor k = {FLOW_STRUCTURE:g} "
             "(on) or off (eq. 8 alone). Errors: rotation error (°) of the final pose / of the motion prediction, "
             "frames 1-12."), "",
             "| preset | cues | flow structure | within 5 cm / 5° | mean rot ° | rotation error, frames 1-12 | prediction, frames 1-12 |",
             "|---|---|---|---:|---:|---|---|"]
    try:
        for preset in args.presets.split(","):
            cfg = tp.preset_config(preset, args.scale, args.frames)
            seq = read_sequence(tp.write_preset(preset, cfg, seq_dir))
            for cues in args.cues.split(","):
                for structure in ((True, False) if "flow" in cues else (True,)):
                    r = track(seq, tuple(cues.split("+")), structure)
                    row = (f"| {preset} | {cues} | {('on' if structure else 'off') if 'flow' in cues else '-'} | "
                           f"{r['success']:.0f} % | {np.mean(r['rot']):.1f} | {' '.join(f'{e:.0f}' for e in r['rot'][:12])} | "
                           f"{' '.join(f'{e:.0f}' for e in r['pred'][:12])} |")
                    lines.append(row)
                    print(row, flush=True)
    finally:
        if not args.seq_dir:
            shutil.rmtree(seq_dir, ignore_errors=True)
    lines += ["", (f"Run took {clock.minutes():.1f} min; load average {clock.load_start[0]:.2f} → {os.getloadavg()[0]:.2f} "
              "(2 cores).")]
    text = "\n".join(lines) + "\n"
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    return text


if __name__ == "__main__":
    main()
