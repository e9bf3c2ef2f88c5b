"""Large motion between two frames (paper Fig. 5): each single cue and the combination.

A textured box (the `teabox-large-motion` preset's photo-textured box on the coffee background) moves
by about 30 px in the image with a 10° rotation between frame 1 and frame 2. The tracker starts at the
true pose of frame 1 and makes one step per cue set (`Tracker.start` + `Tracker.step`, default
configuration and parameters). For each step the errors of

- the prediction, `FrameResult.T_pred`: the pose solved from the motion cues (flow, SIFT) before the
  refinement; with the region cue alone there is no motion cue, and the prediction is the frame-1 pose;
- the final pose, `FrameResult.T_world_root`, after the refinement (region + motion rows),

against the truth of frame 2. Several random trials of the same size (seeds: a new start pose, direction
of motion and rotation axis) give a success rate per cue set; success is the issue's tracking criterion
(rotation error ≤ 10° and translation error ≤ 10 % of the box diameter). One trial is drawn: the model
contour at the final pose (green) and at the prediction (yellow) over frame 2, one panel per cue set,
with the frame-1 pose (red) in the first panel.

    python experiments/large_motion.py                    # writes experiments/results/large_motion.md / .png
    python experiments/large_motion.py --trials 12 --step-px 40 --budget-min 20
    python experiments/large_motion.py --quick --out /tmp/l.md   # smoke run (track_presets --quick's program)
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import pathlib
import shutil
import sys
import tempfile
import time

import numpy as np
import track_presets as tp  # the presets' sequence writing, one definition

from jaxtrack.bench import command_line, output_path, report_header, save_text, start_experiment

RESULTS = pathlib.Path(__file__).resolve().parent / "results"
CUE_SETS = "region,flow,sift,region+flow+sift"
PRED_COLOUR, FINAL_COLOUR, START_COLOUR = (255, 220, 0), (60, 255, 60), (255, 60, 60)


def _projected_centre(K, T_cam_obj) -> np.ndarray:
    p = K @ T_cam_obj[:3, 3]
    return p[:2] / p[2]


def projection_error_px(K, vertices, T_cam_obj, T_true) -> float:
    """Mean image distance (px) of the model's vertices projected at `T_cam_obj` and at the truth (the 2D projection
    error): rotation and translation in one number, in the image the tracker sees."""
    def project(T):
        p = (vertices @ T[:3, :3].T + T[:3, 3]) @ K.T
        return p[:, :2] / p[:, 2:3]
    return float(np.mean(np.linalg.norm(project(T_cam_obj) - project(T_true), axis=1)))


class TwoFrameTrials:
    """One `Tracker` per cue set, reused over the trials (same mesh and camera: its raster plan, atlas and
    crop size class carry over, so a cue set compiles its step once unless a trial needs a larger crop)."""

    def __init__(self, seq, cues: tuple[str, ...], margin: int | None):
        from jaxtrack.geometry import make_camera, stack_cameras
        from jaxtrack.io import load_mesh
        from jaxtrack.track import Tracker, TrackerConfig

        view = seq.views[0]
        # Built as `track_sequence` builds them, so that the compiled step is the same program.
        rig = stack_cameras([make_camera(view.K, view.width, view.height, view.T_cam_world[:3, :3], view.T_cam_world[:3, 3])])
        kwargs = {} if margin is None else {"margin": margin}
        mesh = load_mesh(seq.model_paths[1])
        self.tracker = Tracker(mesh, rig, config=TrackerConfig(cues=cues), **kwargs)
        vertices = np.asarray(mesh.vertices, np.float64)
        self.vertices = vertices[np.unique(np.linspace(0, len(vertices) - 1, min(len(vertices), 2000)).astype(int))]

    def run(self, seq) -> dict:
        from jaxtrack.track import pose_errors

        view = seq.views[0]
        T_cam_world = np.asarray(view.T_cam_world, np.float64)
        gt = np.asarray(view.T_cam_obj[1], np.float64)
        frames = [view.read_frame(k)[None] for k in (0, 1)]
        traces = tp._num_traces()
        state = self.tracker.start(frames[0], np.linalg.inv(T_cam_world) @ gt[0])
        t = time.perf_counter()
        _, result, _ = self.tracker.step(state, frames[1])
        step_s = time.perf_counter() - t
        T_pred = T_cam_world @ np.asarray(result.T_pred, np.float64)
        T_final = T_cam_world @ np.asarray(result.T_world_root, np.float64)
        (rot_p, rot_f), (tr_p, tr_f) = pose_errors(np.stack([T_pred, T_final]), np.stack([gt[1], gt[1]]))
        K = np.asarray(view.K, np.float64)
        return {"pred_rot": float(rot_p), "pred_trans": float(tr_p), "final_rot": float(rot_f), "final_trans": float(tr_f),
                "pred_px": projection_error_px(K, self.vertices, T_pred, gt[1]),
                "none_px": projection_error_px(K, self.vertices, gt[0], gt[1]),
                "T_pred": T_pred, "T_final": T_final, "status": int(result.status), "step_s": step_s,
                "compiled": tp._num_traces() != traces}


def trial_sequences(args, seq_dir: pathlib.Path):
    """The trials' two-frame sequences and their measured motion (px of the projected centre, degrees)."""
    from jaxtrack.io import read_sequence
    from jaxtrack.track import pose_errors

    preset = "occluded-box" if args.quick else "teabox-large-motion"
    base = tp.preset_config(preset, args.scale, 2)
    out = []
    for s in range(args.trials):
        # step_px / step_deg are the motion in the tracked image (not scaled with --scale).
        cfg = dataclasses.replace(base, step_px=args.step_px, step_deg=args.step_deg, seed=s, frames=2, occluders=0)
        seq = read_sequence(tp.write_preset(f"{preset}-2f-{args.step_px:g}px-{args.step_deg:g}deg-seed{s}", cfg, seq_dir))
        view = seq.views[0]
        gt = np.asarray(view.T_cam_obj[1], np.float64)
        rot, _ = pose_errors(gt[1:], gt[:1])
        px = float(np.linalg.norm(_projected_centre(view.K, gt[1]) - _projected_centre(view.K, gt[0])))
        out.append((seq, px, float(rot[0])))
    return preset, base, out


def report(command, args, preset, base, motions, cue_sets, results, diameter, skipped, failed, load_start, load_end, elapsed_s) -> str:
    px = np.array([m[0] for m in motions])
    deg = np.array([m[1] for m in motions])
    lines = [
        "# Large motion between two frames (paper Fig. 5)",
        "",
        *report_header(command, load_start, load_end, elapsed_s),
        "",
        (f"Trials: {len(motions)} two-frame sequences of the {preset} preset's object at {base.width}x{base.height} (seeds "
         f"0-{len(motions) - 1}); measured motion of the projected object centre {px.mean():.1f} px (range {px.min():.1f}-"
         f"{px.max():.1f}), rotation {deg.mean():.1f}° (range {deg.min():.1f}-{deg.max():.1f}); box diameter "
         f"{diameter:.0f} mm. Success: final rotation error ≤ 10° and translation error ≤ 10 % of the diameter "
         f"({0.1 * diameter:.0f} mm)."),
        "",
        "| cues | trials | success | prediction rot ° (mean / median) | prediction trans mm (mean / median) | prediction px (mean / median) | prediction better than none | final rot ° (mean / median) | final trans mm (mean / median) | ms / step | compiles |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for cues in cue_sets:
        rs = results.get(cues, [])
        if not rs:
            lines.append(f"| {cues} | 0 | {'not run (time)' if cues in skipped else 'failed'} | | | | | | | | |")
            continue
        a = {k: np.array([r[k] for r in rs]) for k in ("pred_rot", "pred_trans", "final_rot", "final_trans", "pred_px", "none_px")}
        better = int(np.sum(a["pred_px"] < a["none_px"]))
        ok = (a["final_rot"] <= 10) & (a["final_trans"] <= 0.1 * diameter)
        steps = [r["step_s"] for r in rs if not r["compiled"]]
        pred_note = " (frame-1 pose)" if "flow" not in cues and "sift" not in cues else ""
        ms = f"{1000 * np.median(steps):.0f}" if steps else "n/a"
        lines.append(
            f"| {cues} | {len(rs)} | {100 * ok.mean():.0f} % ({ok.sum()}/{len(rs)}) | "
            f"{a['pred_rot'].mean():.2f} / {np.median(a['pred_rot']):.2f}{pred_note} | "
            f"{a['pred_trans'].mean():.1f} / {np.median(a['pred_trans']):.1f} | "
            f"{a['pred_px'].mean():.1f} / {np.median(a['pred_px']):.1f} | {'-' if pred_note else f'{better}/{len(rs)}'} | "
            f"{a['final_rot'].mean():.2f} / {np.median(a['final_rot']):.2f} | "
            f"{a['final_trans'].mean():.1f} / {np.median(a['final_trans']):.1f} | {ms} | {sum(r['compiled'] for r in rs)} |"
        )
    lines += [
        "",
        "## Per trial: final rotation error ° / translation error mm",
        "",
        "| trial | motion px | rotation ° | " + " | ".join(cue_sets) + " |",
        "|---:|---:|---:|" + "---:|" * len(cue_sets),
    ]
    for i, (p, d) in enumerate(motions):
        cells = []
        for cues in cue_sets:
            rs = {r["trial"]: r for r in results.get(cues, [])}
            cells.append(f"{rs[i]['final_rot']:.1f} / {rs[i]['final_trans']:.0f}" if i in rs else "-")
        lines.append(f"| {i} | {p:.1f} | {d:.1f} | " + " | ".join(cells) + " |")
    notes = [
        "",
        "Notes:",
        ("- Persistent XLA compile cache on (~/.cache/jaxtrack/xla, as `jaxtrack track` uses it): compiles counts the "
         "steps that traced a new program; a cache hit loads it instead of compiling." if not args.quick else ""),
        ("- Prediction: the pose solved from the flow and SIFT correspondences alone (`FrameResult.T_pred`); the "
         "region cue has no prediction, so its row shows the error of the frame-1 pose, i.e. the motion itself. "
         "prediction px: the mean image distance of the model's vertices projected at the prediction and at the truth "
         "(rotation and translation in one number); better than none: trials whose prediction is closer than the "
         "frame-1 pose by that measure."),
        (f"- Scale {args.scale:g} of 640x480 with the focal length scaled alike; the motion is set in the tracked image "
         f"(--step-px {args.step_px:g}, --step-deg {args.step_deg:g}; the generator's step also moves a little in depth, "
         "so the measured image motion is below the setting). The tracker's crop margin is "
         + (f"{args.margin} px (--margin)." if args.margin is not None else
            "its default (24 px plus 1.5x the last motion, which is 0 at the first step): part of a 30 px move can leave "
            "the crop taken around the frame-1 pose.")),
        f"- Picture: trial {args.picture_trial}, experiments/results/large_motion.png." if not args.quick else "",
        ("- Not run, the time budget (--budget-min " + f"{args.budget_min:g}) was spent: " + ", ".join(skipped) + ".") if skipped else "",
        ("- Failed: " + "; ".join(failed)) if failed else "",
    ]
    lines += ["", *[n for n in notes if n]]
    return "\n".join(lines) + "\n"


def picture(path, seq, cue_sets, results, trial: int) -> None:
    """Frame 2 of one trial with the model contour at the prediction and final pose, one panel per cue set."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from jaxtrack.io import load_trimesh
    from jaxtrack.track._overlay import draw_contour, model_mask

    view = seq.views[0]
    tm = load_trimesh(seq.model_paths[1])
    vertices, faces = np.asarray(tm.vertices, np.float64), np.asarray(tm.faces)
    gt = np.asarray(view.T_cam_obj[1], np.float64)
    frame2 = np.clip(view.read_frame(1), 0, 255).astype(np.uint8)
    shape = frame2.shape[:2]
    thick = max(1, round(frame2.shape[1] / 320))

    def mask(T):
        return model_mask(vertices @ T[:3, :3].T + T[:3, 3], faces, view.K, shape)

    panels = [("frame 2, frame-1 pose (red), truth (white)",
               draw_contour(draw_contour(frame2.copy(), mask(gt[0]), START_COLOUR, thick), mask(gt[1]), (255, 255, 255), thick))]
    for cues in cue_sets:
        r = {x["trial"]: x for x in results.get(cues, [])}.get(trial)
        if r is None:
            continue
        img = draw_contour(frame2.copy(), mask(r["T_pred"]), PRED_COLOUR, thick)
        img = draw_contour(img, mask(r["T_final"]), FINAL_COLOUR, thick)
        panels.append((f"{cues}: pred {r['pred_rot']:.1f}°/{r['pred_trans']:.0f} mm, final {r['final_rot']:.1f}°/{r['final_trans']:.0f} mm", img))
    fig, axes = plt.subplots(1, len(panels), figsize=(3.4 * len(panels), 3.0), squeeze=False)
    for ax, (title, img) in zip(axes[0], panels, strict=True):
        ax.imshow(img)
        ax.set_title(title, fontsize=7)
        ax.axis("off")
    fig.suptitle("prediction (yellow), final pose (green)", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="smoke run: occluded-box object at 96x72, region, 2 trials")
    ap.add_argument("--cues", default=CUE_SETS, help="cue sets joined with '+', comma-separated")
    ap.add_argument("--trials", type=int, default=8, help="random trials (seeds 0..N-1)")
    ap.add_argument("--step-px", type=float, default=35.0,
                    help="motion between the frames in the tracked image (px; 35 gives ~30 px measured, the rest is depth)")
    ap.add_argument("--step-deg", type=float, default=10.0, help="rotation between the frames (degrees)")
    ap.add_argument("--scale", type=float, default=0.5, help="image scale (1 = 640x480)")
    ap.add_argument("--margin", type=int, default=None, help="the tracker's crop margin in px (default: the Tracker's)")
    ap.add_argument("--picture-trial", type=int, default=0, help="the trial drawn in the picture")
    ap.add_argument("--budget-min", type=float, default=None, help="start no new cue set after this many minutes")
    ap.add_argument("--seq-dir", default=None, help="folder for the rendered sequences (default: a temporary one)")
    ap.add_argument("--out", default=None, help="markdown output (default experiments/results/large_motion.md; --quick: none)")
    ap.add_argument("--plot", default=None, help="picture (default experiments/results/large_motion.png; --quick: none)")
    args = ap.parse_args(argv)
    if args.quick:  # track_presets --quick's object, frame size and configuration: its compiled step is reused
        args.cues, args.trials, args.scale, args.step_px, args.step_deg = "region", 2, 0.15, 4.0, 10.0
    if args.trials < 1 or not 0 <= args.picture_trial < args.trials:
        raise SystemExit("large_motion: --trials must be ≥ 1 and --picture-trial one of them")
    if args.step_px < 0 or args.step_deg < 0:
        raise SystemExit("large_motion: --step-px and --step-deg must be ≥ 0")
    cue_sets = tp.parse_subsets(args.cues)
    command = command_line(__file__, argv)

    import jax

    from jaxtrack.io import load_trimesh
    from jaxtrack.track import model_diameter

    clock = start_experiment(cache=not args.quick)
    seq_dir = pathlib.Path(args.seq_dir) if args.seq_dir else pathlib.Path(tempfile.mkdtemp(prefix="large_motion_"))
    results, skipped, failed = {}, [], []
    try:
        preset, base, trials = trial_sequences(args, seq_dir)
        tm = load_trimesh(trials[0][0].model_paths[1])
        diameter = float(model_diameter(np.asarray(tm.convex_hull.vertices)))
        for cues in cue_sets:
            if clock.over(args.budget_min):
                skipped.append(cues)
                continue
            t = time.perf_counter()
            runner = TwoFrameTrials(trials[0][0], tuple(cues.split("+")), args.margin)
            results[cues] = []
            for i, (seq, _, _) in enumerate(trials):
                try:
                    r = runner.run(seq)
                except Exception as e:  # noqa: BLE001 - one crashed trial is reported, the others go on
                    failed.append(f"{cues} trial {i} ({type(e).__name__}: {str(e).strip()[:300]})")
                    print(f"[large_motion] failed: {failed[-1]}", file=sys.stderr, flush=True)
                    continue
                r["trial"] = i
                results[cues].append(r)
            rs = results[cues]
            print(f"[large_motion] {cues}: final rot {np.mean([r['final_rot'] for r in rs]):.2f}°, "
                  f"{sum(r['compiled'] for r in rs)} compiles ({time.perf_counter() - t:.0f} s, "
                  f"{clock.minutes():.1f} min)", file=sys.stderr, flush=True)
            if not args.quick:
                jax.clear_caches()  # this cue set's programs are not used again
        text = report(command, args, preset, base, [(px, deg) for _, px, deg in trials], cue_sets, results, diameter,
                      skipped, failed, clock.load_start, os.getloadavg(), clock.elapsed_s())
        figure = output_path(args.plot, RESULTS / "large_motion.png", args.quick)
        if figure is not None and any(results.values()):
            picture(figure, trials[args.picture_trial][0], cue_sets, results, args.picture_trial)
    finally:
        if not args.seq_dir:
            shutil.rmtree(seq_dir, ignore_errors=True)
    print(text)
    save_text(output_path(args.out, RESULTS / "large_motion.md", args.quick), text)
    return results


if __name__ == "__main__":
    main()
