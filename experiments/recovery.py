"""Recovery after a lost frame (issue 24): the tracker resetting itself against an oracle that resets it.

The evaluation sequences of `loss_detection.py` (the frame-rate experiment's regular / noisy / occluded
sequences at S = 2..4, the occluded-box preset, the teapot turntable; none of them seen by the loss
calibration) are tracked three ways from the first true pose, camera 0, the tracker's defaults otherwise:

- `no recovery`: `TrackerConfig(recovery=None)`; a lost frame is reported and tracking goes on from its pose;
- `recovery`: the defaults (`TrackerConfig.recovery` = `RecoveryConfig()`): after a LOST frame the keyframes' PnP,
  then the pose hypotheses (`--keyframes-only`: the PnP alone), then the normal step again (RECOVERED when that step
  is OK); the search compiles in the background from the first frame reported UNCERTAIN or LOST
  (`$JAXTRACK_RECOVERY_WARMUP=1`: from the first frame);
- `RBOT resets`: no recovery; a frame beyond 5 cm / 5° is counted failed and the tracker restarts from the
  truth (the oracle of the RBOT protocol).

The table gives the success rate (frames within 5 cm / 5°), the failure runs (frames until the pose is back
within the bound), the status's precision / recall for "frame beyond the bound" in the recovery run, the
frames RECOVERED (and how many of them were right) and the time of the frames that searched.

    python experiments/recovery.py            # experiments/results/recovery.md / .json
    python experiments/recovery.py --quick --out /tmp/r.md   # smoke run (one short sequence)
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import shutil
import sys
import tempfile

import loss_detection as ld
import numpy as np
import track_presets as tp

from jaxtrack.bench import command_line, start_experiment

RESULTS = pathlib.Path(__file__).resolve().parent / "results"
MODES = ("no recovery", "recovery", "RBOT resets")


def track(seq, mode: str, hypotheses: bool = True) -> list[dict]:
    """Track camera 0 of `seq` in one of `MODES`; one row per frame 1.. (errors against the truth, status, timings)."""
    from jaxtrack import Status
    from jaxtrack.geometry import make_camera, rotation_error_deg, stack_cameras
    from jaxtrack.io import load_mesh
    from jaxtrack.track import RecoveryConfig, Tracker, TrackerConfig, success_mask

    view = seq.views[0]
    rig = stack_cameras([make_camera(view.K, view.width, view.height, view.T_cam_world[:3, :3], view.T_cam_world[:3, 3])])
    oid = min(seq.model_paths)
    T_world = np.einsum("ij,fjk->fik", np.linalg.inv(np.asarray(view.T_cam_world, np.float64)), view.T_cam_obj[oid])
    config = TrackerConfig(recovery=RecoveryConfig(hypotheses=hypotheses) if mode == "recovery" else None)
    tracker = Tracker(load_mesh(seq.model_paths[oid]), rig, config=config)
    state = tracker.start(view.read_frame(0)[None], T_world[0])
    rows = []
    for k in range(1, seq.num_frames):
        image = view.read_frame(k)[None]
        state, r, info = tracker.step(state, image)
        T = np.asarray(r.T_world_root, np.float64)
        rot = float(rotation_error_deg(T[:3, :3], T_world[k][:3, :3]))
        trans = float(np.linalg.norm(T[:3, 3] - T_world[k][:3, 3]))
        failed = not bool(success_mask(rot, trans, ld.MAX_DEG, ld.MAX_MM))
        rec = info.get("recovery")
        rows.append({"frame": k, "rot_deg": rot, "trans_mm": trans, "failed": failed, "status": Status(int(r.status)).name,
                     "confidence": float(r.confidence), "total_s": info["timings"]["total_s"],
                     "recovery_s": info["timings"].get("recovery_s"), "searched": rec is not None,
                     "source": None if rec is None else rec["source"], "recovered": bool(rec and rec["recovered"]),
                     "pnp_inliers": None if rec is None else rec.get("pnp_inliers"),
                     "hypothesis": None if rec is None else rec.get("hypothesis"),
                     "skipped": None if rec is None else rec.get("skipped"),
                     "turned_deg": None if rec is None else rec.get("turned_deg"),
                     "score": None if rec is None else rec.get("score"), "own_score": None if rec is None else rec.get("own_score"),
                     "found_rot_deg": None if rec is None or "T_found" not in rec else
                     float(rotation_error_deg(rec["T_found"][:3, :3], T_world[k][:3, :3])),
                     "found_trans_mm": None if rec is None or "T_found" not in rec else
                     float(np.linalg.norm(rec["T_found"][:3, 3] - T_world[k][:3, 3]))})
        if mode == "RBOT resets" and failed:
            state = tracker.start(image, T_world[k])
    # The recovery's background compile may outlast a short sequence: waited for here, so that it does not run on
    # into the next sequence's tracker (whose own warm-up would then wait for it, and its first lost frames skip the
    # search: each sequence as in a process of its own with the program compiled).
    tracker.join_background()
    return rows


def _rate(rows) -> float:
    return 100.0 * float(np.mean([not r["failed"] for r in rows])) if rows else float("nan")


def report(command: str, elapsed_s: float, load, runs: dict, hypotheses: bool = True) -> str:
    from jaxtrack.track import failure_episodes, precision_recall

    names = list(runs)
    lines = ["# Recovery after a lost frame (issue 24)", "",
             (f"`{command}`: {elapsed_s / 60:.1f} min, load average {load[0][0]:.2f} → {load[1][0]:.2f} (2 cores); camera 0, "
             "the tracker's defaults (lines, flow, SIFT, occlusion detection, 96x128 working resolution); the recovery "
             + ("searches the keyframes' PnP, then the pose hypotheses." if hypotheses else "searches the keyframes' PnP alone "
                "(`--keyframes-only`).")
             + " Compiled programs are kept on disk, as `jaxtrack track` keeps them (not with --quick): the search compiles "
             "in the background at a tracker's first doubt, and a frame lost before it is ready (6.9 s for a compile, "
             "under 1 s for a load from the cache of an earlier run) is not searched (\"lost while the search's program "
             "still compiled\" below)."), "",
             ("Success: frames within 5 cm / 5° (frames 1..). Failure runs: consecutive frames beyond the bound, "
             "as (frames until back within it; `end` when the sequence ended first)."), "",
             "| sequence | frames | no recovery | recovery | RBOT resets | recovery − resets | failure runs: no recovery | recovery |",
             "|---|---:|---:|---:|---:|---:|---|---|"]
    totals = {m: [] for m in MODES}
    for name in names:
        rates = {m: _rate(runs[name][m]) for m in MODES}
        for m in MODES:
            totals[m] += runs[name][m]

        def episodes(m, name=name):
            ep = failure_episodes([r["failed"] for r in runs[name][m]])
            return " ".join(f"{n}" if back else f"{n}(end)" for n, back in ep) or "none"

        lines.append(f"| {name} | {len(runs[name]['recovery'])} | {rates['no recovery']:.0f} % | {rates['recovery']:.0f} % | "
                     f"{rates['RBOT resets']:.0f} % | {rates['recovery'] - rates['RBOT resets']:+.0f} | {episodes('no recovery')} | "
                     f"{episodes('recovery')} |")
    mean = {m: float(np.mean([_rate(runs[n][m]) for n in names])) for m in MODES}
    lines.append(f"| **mean over sequences** | | **{mean['no recovery']:.1f} %** | **{mean['recovery']:.1f} %** | "
                 f"**{mean['RBOT resets']:.1f} %** | **{mean['recovery'] - mean['RBOT resets']:+.1f}** | | |")
    rec = totals["recovery"]
    flagged = np.array([r["status"] in ("LOST", "UNCERTAIN") for r in rec])
    failed = np.array([r["failed"] for r in rec])
    p, rcl = precision_recall(flagged, failed)
    searched = [r for r in rec if r["searched"]]
    compiling = [r for r in searched if r.get("skipped") == "compiling"]  # lost while the search still compiled
    backoff = [r for r in searched if r.get("skipped") == "backoff"]  # a persistently lost object, due no search
    searched = [r for r in searched if not r.get("skipped")]
    recovered = [r for r in rec if r["status"] == "RECOVERED"]
    times = np.array([r["recovery_s"] for r in searched], float) * 1000.0
    normal = np.array([r["total_s"] for r in rec if not r["searched"]], float) * 1000.0
    lines += ["", "## The recovery run", "",
              (f"- Status LOST / UNCERTAIN against frames beyond 5 cm / 5° (all sequences): precision {p:.2f}, recall {rcl:.2f} "
              f"({int(flagged.sum())} flagged, {int(failed.sum())} beyond, {len(rec)} frames)."),
              (f"- Frames that searched (LOST after the step): {len(searched)} (not searched: {len(backoff)} LOST frames of the "
              f"backoff, {len(compiling)} lost while the search's program still compiled); RECOVERED: {len(recovered)}, of which within "
              f"the bound: {sum(not r['failed'] for r in recovered)}; found by the keyframes' PnP: "
              f"{sum(r['source'] == 'keyframes' and r['recovered'] for r in searched)}, by the region search: "
              f"{sum(r['source'] == 'region' and r['recovered'] for r in searched)}."),
              (f"- Time of the search and the step after it (median / max): {np.median(times):.0f} / {np.max(times):.0f} ms; "
               f"a frame that did not search: median {np.median(normal):.0f} ms." if len(times) else "- No frame searched."),
              ]
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scale", type=float, default=0.5, help="image scale (1 = 640x480)")
    ap.add_argument("--frames", type=int, default=36, help="frames of the frame-rate sequences at S = 1")
    ap.add_argument("--quick", action="store_true", help="smoke run: one short sequence")
    ap.add_argument("--keyframes-only", dest="hypotheses", action="store_false",
                    help="the recovery searches the keyframes' PnP alone, not the pose hypotheses (RecoveryConfig(hypotheses=False))")
    ap.add_argument("--only", default=None, help="comma-separated substrings: track only the sequences they name")
    ap.add_argument("--seq-dir", default=None, help="keep the rendered sequences here (and reuse them)")
    ap.add_argument("--out", default=str(RESULTS / "recovery.md"))
    args = ap.parse_args(argv)
    if args.quick:
        args.frames = 8
    command = command_line(__file__, argv)

    from jaxtrack.io import read_sequence

    clock = start_experiment(cache=not args.quick)  # as `jaxtrack track`: a rerun loads the search from disk
    seq_dir = pathlib.Path(args.seq_dir) if args.seq_dir else pathlib.Path(tempfile.mkdtemp(prefix="recovery_"))
    runs: dict = {}
    try:
        for i, (name, cfg) in enumerate(ld.evaluation_configs(args.scale, args.frames, args.quick)):
            if args.only and not any(s in name for s in args.only.split(",")):
                continue
            seq = read_sequence(tp.write_preset(f"eval{i}", cfg, seq_dir))
            runs[name] = {m: track(seq, m, args.hypotheses) for m in MODES}
            print(f"[recovery] {name}: " + ", ".join(f"{m} {_rate(runs[name][m]):.0f} %" for m in MODES)
                  + f" ({clock.minutes():.1f} min)", file=sys.stderr, flush=True)
    finally:
        if not args.seq_dir:
            shutil.rmtree(seq_dir, ignore_errors=True)
    text = report(command, clock.elapsed_s(), (clock.load_start, os.getloadavg()), runs, args.hypotheses)
    print(text)
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    out.with_suffix(".json").write_text(json.dumps(runs))
    return runs


if __name__ == "__main__":
    main()
