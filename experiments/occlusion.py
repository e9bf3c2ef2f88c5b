"""Occlusion (paper Fig. 12, 13): tracking with and without the occlusion detection, and the detected
occlusion maps against the generator's occluder masks.

The `occluded-box` preset: the textured cracker box moving at random (8 px, 3° per frame) behind two
moving occluders (bars / discs of flat colour). It is tracked from its first ground-truth pose through
all frames without resets, twice with the same cues:

- with the occlusion detection (`TrackerConfig(occlusion=True)`, the default): the appearance-model test
  of eq. 9-10 marks occluded object pixels of each new frame at the final pose; they switch the flow
  data term off (r(x) = 0) and are left out of the next SIFT detection mask;
- without it (`TrackerConfig(occlusion=False)`, the tracker's own switch): r(x) = 1 everywhere, SIFT
  detects over the whole model silhouette, the appearance model is not updated.

Maps: after each step the tracker's state holds r(x) of the new frame (`TrackerState.data_weight`,
0 = occluded, full frame); the detected map is r(x) = 0. The truth is the generator's occluder mask on
the object (`000000/occluder_mask/`, occluder ∩ true object silhouette). Per frame: precision, recall
and IoU of the detected against the true occluded pixels (pooled over frames as well), as
`bench_sift_occlusion.py` scores them at the true poses; here at the tracked poses, so tracking errors
count against the maps. *Decidable* pixels are the true occluded ones whose surface texel the appearance model had
seen (`seen_surface`, at the true pose): the test of eq. 9 compares the image with what the model knows, so an
occluder over surface never seen unoccluded (a face turning into view behind it) is undecidable by design; the
report gives their share (the bound of the recall) and the recall on the decidable pixels.

    python experiments/occlusion.py                      # writes experiments/results/occlusion.md / .png
    python experiments/occlusion.py --frames 30 --cues region+flow+sift --budget-min 25
    python experiments/occlusion.py --quick --out /tmp/o.md   # smoke run (track_presets --quick's program)
"""

from __future__ import annotations

import argparse
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


def read_mask(path: pathlib.Path) -> np.ndarray:
    """A written mask PNG as (H, W) bool; ValueError naming the file when it cannot be read."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise ValueError(f"{path}: mask image missing or unreadable")
    return img > 127


def map_scores(detected: np.ndarray, truth: np.ndarray, seen: np.ndarray | None = None) -> dict:
    """Pixel counts and precision / recall / IoU of a detected occlusion map against the truth (NaN when
    undefined: no detection for precision, no true occlusion for recall, neither for IoU). With `seen` (the object
    pixels whose surface the appearance model has seen, `seen_surface`): the true occluded pixels there
    ("decidable") and the recall on them."""
    tp_, fp, fn = int(np.sum(detected & truth)), int(np.sum(detected & ~truth)), int(np.sum(~detected & truth))
    out = {"tp": tp_, "fp": fp, "fn": fn,
           "precision": tp_ / (tp_ + fp) if tp_ + fp else float("nan"),
           "recall": tp_ / (tp_ + fn) if tp_ + fn else float("nan"),
           "iou": tp_ / (tp_ + fp + fn) if tp_ + fp + fn else float("nan")}
    if seen is not None:
        decidable = truth & seen
        found = int(np.sum(detected & decidable))
        out.update(decidable=int(decidable.sum()), tp_decidable=found,
                   recall_decidable=found / int(decidable.sum()) if decidable.any() else float("nan"))
    return out


def track_with_maps(seq, cues: tuple[str, ...], occlusion: bool, frames: int) -> dict:
    """Track camera 0 from the first true pose (no resets); per frame the pose errors and, with the
    detection on, the detected map scored against the occluder mask."""
    from jaxtrack.geometry import make_camera, stack_cameras
    from jaxtrack.io import load_mesh
    from jaxtrack.track import Tracker, TrackerConfig, pose_errors

    view = seq.views[0]
    # Built as `track_sequence` builds them, so that the compiled step is the same program.
    rig = stack_cameras([make_camera(view.K, view.width, view.height, view.T_cam_world[:3, :3], view.T_cam_world[:3, 3])])
    tracker = Tracker(load_mesh(seq.model_paths[1]), rig, config=TrackerConfig(cues=cues, occlusion=occlusion))
    T_cam_world = np.asarray(view.T_cam_world, np.float64)
    gt = np.asarray(view.T_cam_obj[1], np.float64)[:frames]
    state = tracker.start(view.read_frame(0)[None], np.linalg.inv(T_cam_world) @ gt[0])
    # The detection runs only when a configured modality reads its maps (flow, SIFT); the lines alone skip it.
    detecting = occlusion and tracker.setup().config.runs_occlusion()
    seen_at = seen_surface(tracker) if detecting else None
    poses, maps, scores, step_s, compiled = [gt[0]], [None], [None], [], []
    for k in range(1, frames):
        # What the model f_{t-1} the detection reads has seen of the surface, at the true pose of frame k.
        seen = np.asarray(seen_at(state.appearance, np.linalg.inv(T_cam_world) @ gt[k])) if detecting else None
        traces = tp._num_traces()
        t = time.perf_counter()
        state, result, _ = tracker.step(state, view.read_frame(k)[None])
        step_s.append(time.perf_counter() - t)
        compiled.append(tp._num_traces() != traces)
        poses.append(T_cam_world @ np.asarray(result.T_world_root, np.float64))
        detected = np.asarray(state.data_weight[0]) < 0.5
        maps.append(detected)
        truth = read_mask(view.folder / "occluder_mask" / f"{int(view.frame_ids[k]):06d}.png")
        scores.append(map_scores(detected, truth, seen) if occlusion else None)
    rot, trans = pose_errors(np.stack(poses), gt)
    return {"rot": rot, "trans": trans, "maps": maps if occlusion else None, "scores": scores, "step_s": step_s,
            "compiled": compiled, "poses": np.stack(poses)}


def seen_surface(tracker):
    """A jitted `(appearance, T_world_root) -> (H, W) bool` of camera 0's full frame: the object's pixels at that pose whose
    surface texel the appearance model has seen (`model_image`'s `known`). Only there can the histogram test of eq. 9
    tell an occluder from the surface; a texel never seen unoccluded (a face that turned into view behind an occluder)
    is unknown, and the detection leaves its pixels undecided by design."""
    import jax
    import jax.numpy as jnp

    from jaxtrack.cues.occlusion import model_image
    from jaxtrack.render import render

    setup = tracker.setup()
    camera = jax.tree.map(lambda x: x[0], setup.cameras)

    @jax.jit
    def seen(appearance, T_world_root):
        T = jnp.asarray(T_world_root, setup.mesh.vertices.dtype)
        rendered = render(setup.mesh, camera, T, jnp.zeros((0,), T.dtype), setup.model, setup.plan)
        return model_image(setup.atlas, appearance, rendered)[1]

    return seen


def _mean(x) -> float:
    x = np.asarray(x, float)
    return float(np.nanmean(x)) if np.any(np.isfinite(x)) else float("nan")


def _num(x, digits=2) -> str:
    return "n/a" if x is None or not np.isfinite(x) else f"{x:.{digits}f}"


def report(command, args, size, diameter, runs, skipped, failed, load_start, load_end, elapsed_s, truth_px) -> str:
    w, h, n = size
    lines = [
        "# Occlusion: tracking with and without the occlusion detection (paper Fig. 12, 13)",
        "",
        *report_header(command, load_start, load_end, elapsed_s),
        "",
        (f"Sequence: occluded-box {w}x{h}, {n} frames ({n - 1} tracked, no resets), two moving occluders; box diameter "
         f"{diameter:.0f} mm; {sum(p > 0 for p in truth_px[1:])} of the tracked frames have occluded object pixels "
         f"({int(np.sum(truth_px[1:]))} in all). Failure: rotation error > 10° or translation error > 10 % of the diameter."),
        "",
        "## Pose errors",
        "",
        "| cues | occlusion detection | mean rot ° | max rot ° | mean trans mm | max trans mm | first failure | ms / frame | compiles |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for (cues, occ), r in runs.items():
        rot, trans = r["rot"][1:], r["trans"][1:]
        bad = np.nonzero((rot > 10) | (trans > 0.1 * diameter))[0]
        steps = [s for s, c in zip(r["step_s"], r["compiled"], strict=True) if not c]
        lines.append(
            f"| {cues} | {'on' if occ else 'off'} | {rot.mean():.2f} | {rot.max():.2f} | {trans.mean():.1f} | {trans.max():.1f} | "
            f"{'none' if not bad.size else int(bad[0]) + 1} | {_num(1000 * np.median(steps), 0) if steps else 'n/a'} | "
            f"{sum(r['compiled'])} |"
        )
    for cues, occ in skipped:
        lines.append(f"| {cues} | {'on' if occ else 'off'} | not run (time) | | | | | | |")
    for (cues, occ), r in runs.items():
        if not occ:
            continue
        sc = r["scores"][1:]
        tp_, fp, fn = (sum(s[k] for s in sc) for k in ("tp", "fp", "fn"))
        measured = bool(sc) and all("decidable" in s for s in sc)
        decidable = sum(s["decidable"] for s in sc) if measured else 0
        found = sum(s["tp_decidable"] for s in sc) if measured else 0
        lines += [
            "",
            f"## Detected occlusion maps against the occluder masks ({cues}, detection on)",
            "",
            (f"Pooled over the tracked frames: precision {_num(tp_ / max(tp_ + fp, 1))}, recall {_num(tp_ / max(tp_ + fn, 1))}, "
             f"IoU {_num(tp_ / max(tp_ + fp + fn, 1))} ({tp_} true positive, {fp} false positive, {fn} missed pixels). "
             f"Means over frames (where defined): precision {_num(_mean([s['precision'] for s in sc]))}, recall "
             f"{_num(_mean([s['recall'] for s in sc]))}, IoU {_num(_mean([s['iou'] for s in sc]))}."),
            "",
            ((f"Decidable: {decidable} of the {tp_ + fn} true occluded pixels ({_num(decidable / max(tp_ + fn, 1))}) lie on "
              "surface the appearance model had seen (at the true pose, in the model f_(t-1) the frame's test reads); the "
              "others are on texels never seen unoccluded, which eq. 9 leaves undecided, so at the true poses its recall could "
              f"not exceed {_num(decidable / max(tp_ + fn, 1))} (at the tracked poses the model is read elsewhere). Recall on the decidable pixels: {_num(found / max(decidable, 1))} "
              f"({found} found).") if measured else
             "Decidable pixels: not measured (the detection did not run: no configured modality reads its maps)."),
            "",
            "| frame | true occluded px | decidable px | detected px | precision | recall | recall, decidable | IoU | rot err ° |",
            "|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for k, s in enumerate(r["scores"]):
            if s is None:
                continue
            lines.append(f"| {k} | {s['tp'] + s['fn']} | {s.get('decidable', 'n/a')} | {s['tp'] + s['fp']} | {_num(s['precision'])} | "
                         f"{_num(s['recall'])} | {_num(s.get('recall_decidable'))} | {_num(s['iou'])} | {r['rot'][k]:.2f} |")
    notes = [
        "",
        "Notes:",
        ("- Persistent XLA compile cache on (~/.cache/jaxtrack/xla, as `jaxtrack track` uses it): compiles counts the "
         "steps that traced a new program; a cache hit loads it instead of compiling." if not args.quick else ""),
        (f"- Scale {args.scale:g} of the preset's 640x480 (focal length and motion in pixels scaled alike)"
         + ("" if args.frames is None else f", the first {n} of its frames") + ", to fit the shared 2-core machine."),
        ("- Detected map: r(x) = 0 of the tracker state after the step, i.e. object pixels of the model silhouette at the "
         "estimated pose (inside the crop) that the appearance test marked occluded; truth: occluder ∩ true object silhouette. "
         "Precision n/a: nothing detected; recall n/a: no true occlusion in that frame."),
        ("- Decidable: true occluded pixels whose surface texel the appearance model f_(t-1) had seen, at the true pose "
         "of the frame on the full frame (`seen_surface`); the test of eq. 9 cannot flag the rest (unknown texels are "
         "neither occluded nor visible to it), so at the true poses the recall against the masks is bounded by the decidable fraction."),
        ("- Without detection the tracker's own switch `TrackerConfig(occlusion=False)` is used (a separately compiled step); "
         "it has no maps." + (" Not run in --quick (it would compile a second program)." if args.quick else "")),
        f"- Picture: {args.plot or 'experiments/results/occlusion.png'} (errors over frames, map scores, and the frame with the most true "
        "occluded pixels: detected map next to the truth)." if not args.quick else "",
        (f"- Not run, the time budget (--budget-min {args.budget_min:g}) was spent: "
         + ", ".join(f"{c} with detection {'on' if o else 'off'}" for c, o in skipped) + ".") if skipped else "",
        ("- Failed: " + "; ".join(failed)) if failed else "",
    ]
    lines += ["", *[n for n in notes if n]]
    return "\n".join(lines) + "\n"


def plot(path, seq, runs, truth_px) -> None:
    """Errors over frames (on / off), map scores over frames, and one detected map next to the truth."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from jaxtrack.io import load_trimesh
    from jaxtrack.track._overlay import draw_contour, model_mask

    view = seq.views[0]
    fig, axes = plt.subplots(2, 3, figsize=(13, 7))
    for (cues, occ), r in runs.items():
        k = np.arange(len(r["rot"]))
        style = "-" if occ else "--"
        axes[0, 0].plot(k, r["rot"], style, label=f"{cues}, detection {'on' if occ else 'off'}")
        axes[0, 1].plot(k, r["trans"], style, label=f"{cues}, detection {'on' if occ else 'off'}")
    axes[0, 0].set(xlabel="frame", ylabel="rotation error (°)")
    axes[0, 1].set(xlabel="frame", ylabel="translation error (mm)")
    axes[0, 0].legend(fontsize=7)
    on = next(((c, o) for c, o in runs if o), None)
    for ax in axes[1]:
        ax.axis("off")
    if on is not None:
        r = runs[on]
        k = np.arange(1, len(r["scores"]))
        for name in ("precision", "recall", "iou", "recall_decidable"):
            if all(name in r["scores"][i] for i in k):
                axes[0, 2].plot(k, [r["scores"][i][name] for i in k], ".-", label=name.replace("_", ", "))
        axes[0, 2].set(xlabel="frame", ylabel="detected vs true occluded pixels", ylim=(-0.02, 1.02))
        axes[0, 2].legend(fontsize=7)
        best = int(np.argmax(truth_px[1:]) + 1)
        frame = np.clip(view.read_frame(best), 0, 255).astype(np.uint8)
        tm = load_trimesh(seq.model_paths[1])
        T = r["poses"][best]
        sil = model_mask(np.asarray(tm.vertices) @ T[:3, :3].T + T[:3, 3], np.asarray(tm.faces), view.K, frame.shape[:2])
        truth = read_mask(view.folder / "occluder_mask" / f"{int(view.frame_ids[best]):06d}.png")
        obj = read_mask(view.folder / "object_mask" / f"{int(view.frame_ids[best]):06d}.png")

        def coloured(base, mask):
            img = np.full(frame.shape, 40, np.uint8)
            img[base] = (150, 150, 150)
            img[mask] = (255, 60, 60)
            return img

        s = r["scores"][best]
        axes[1, 0].imshow(draw_contour(frame.copy(), sil, (60, 255, 60), 1))
        axes[1, 0].set_title(f"frame {best}, tracked pose (green)", fontsize=8)
        axes[1, 1].imshow(coloured(sil, r["maps"][best]))
        axes[1, 1].set_title(f"detected occlusion (red) on the model silhouette\nprecision {_num(s['precision'])}, "
                             f"recall {_num(s['recall'])}, IoU {_num(s['iou'])}", fontsize=8)
        axes[1, 2].imshow(coloured(obj, truth))
        axes[1, 2].set_title("true occluder pixels (red) on the object", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="smoke run: occluded-box at 96x72, region, 4 frames, detection on")
    ap.add_argument("--cues", default="region+flow+sift", help="cue sets joined with '+', comma-separated")
    ap.add_argument("--frames", type=int, default=None, help="frames (default: the preset's 40)")
    ap.add_argument("--scale", type=float, default=0.5, help="image scale (1 = 640x480)")
    ap.add_argument("--budget-min", type=float, default=None, help="start no new run after this many minutes")
    ap.add_argument("--seq-dir", default=None, help="folder for the rendered sequence (default: a temporary one)")
    ap.add_argument("--out", default=None, help="markdown output (default experiments/results/occlusion.md; --quick: none)")
    ap.add_argument("--plot", default=None, help="figure (default experiments/results/occlusion.png; --quick: none)")
    args = ap.parse_args(argv)
    if args.quick:  # track_presets --quick's sequence and configuration: its compiled step is reused
        args.cues, args.frames, args.scale = "region", 4, 0.15
    if args.frames is not None and args.frames < 2:
        raise SystemExit("occlusion: --frames must be ≥ 2")
    cue_sets = tp.parse_subsets(args.cues)
    switches = (True,) if args.quick else (True, False)
    command = command_line(__file__, argv)

    import jax

    from jaxtrack.io import load_trimesh, read_sequence
    from jaxtrack.track import model_diameter

    clock = start_experiment(cache=not args.quick)
    seq_dir = pathlib.Path(args.seq_dir) if args.seq_dir else pathlib.Path(tempfile.mkdtemp(prefix="occlusion_"))
    runs, skipped, failed = {}, [], []
    try:
        cfg = tp.preset_config("occluded-box", args.scale, args.frames)
        seq = read_sequence(tp.write_preset("occluded-box", cfg, seq_dir))
        view = seq.views[0]
        truth_px = [int(read_mask(view.folder / "occluder_mask" / f"{int(i):06d}.png").sum()) for i in view.frame_ids[: cfg.frames]]
        diameter = float(model_diameter(np.asarray(load_trimesh(seq.model_paths[1]).convex_hull.vertices)))
        for cues in cue_sets:
            for occ in switches:
                if clock.over(args.budget_min):
                    skipped.append((cues, occ))
                    continue
                t = time.perf_counter()
                try:
                    r = track_with_maps(seq, tuple(cues.split("+")), occ, cfg.frames)
                except Exception as e:  # noqa: BLE001 - one crashed run is reported, the others go on
                    failed.append(f"{cues} detection {'on' if occ else 'off'} ({type(e).__name__}: {str(e).strip()[:300]})")
                    print(f"[occlusion] failed: {failed[-1]}", file=sys.stderr, flush=True)
                    continue
                runs[(cues, occ)] = r
                print(f"[occlusion] {cues} detection {'on' if occ else 'off'}: mean rot {r['rot'][1:].mean():.2f}°, "
                      f"{sum(r['compiled'])} compiles ({time.perf_counter() - t:.0f} s, {clock.minutes():.1f} min)",
                      file=sys.stderr, flush=True)
                if not args.quick:
                    jax.clear_caches()  # the other switch is another program
        text = report(command, args, (cfg.width, cfg.height, cfg.frames), diameter, runs, skipped, failed,
                      clock.load_start, os.getloadavg(), clock.elapsed_s(), truth_px)
        figure = output_path(args.plot, RESULTS / "occlusion.png", args.quick)
        if figure is not None and runs:
            plot(figure, seq, runs, truth_px)
    finally:
        if not args.seq_dir:
            shutil.rmtree(seq_dir, ignore_errors=True)
    print(text)
    save_text(output_path(args.out, RESULTS / "occlusion.md", args.quick), text)
    return runs


if __name__ == "__main__":
    main()
