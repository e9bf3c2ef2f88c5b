"""Tracker speed (issue 11): milliseconds per frame, first-frame time with a cold and a warm compile
cache, and a per-stage breakdown, for region only and for all cues, on 1, 2 and 4 cameras; DLR M3T's
ms per frame on the same 1-camera frames, from the same run.

Setting: a synthetic textured box (`jaxtrack.synth`, photo texture, random 6-DoF motion of ~10 px
and 3° per frame) seen by up to 4 cameras on a ring, 640x480, the box about 200 px across (measured
and printed), float32, the tracker's default configuration and parameters.

Each configuration (cue subset x number of cameras) runs in fresh subprocesses, so nothing compiled
in memory carries over:
- cold: an empty on-disk compilation cache (a new temporary folder, set up like `jaxtrack track`
  does); first frame ready = imports + reading + `Tracker.start` + the first `Tracker.step`
  (which compiles), counted from the moment the subprocess was launched;
- warm: a second subprocess with the cache the cold one filled;
- ms per frame: the median host time of `Tracker.step` (crop, SIFT on the host, the jitted step)
  over the frames after the first, in the cold subprocess; frames that traced the step again (a new
  crop size class or raster plan) are left out and counted.
The per-stage split cannot be read from inside one jitted step: each stage is jitted on its own and
timed on the inputs of the last tracked frame (medians of repeats), then multiplied by its calls per
frame (rounds of the refinement loop as run on that frame). The sum is shown beside the whole step.

    python experiments/bench_track.py                 # writes experiments/results/bench_track.md
    python experiments/bench_track.py --quick --out /tmp/bench_track.md   # smoke run (occluded-box at 96x72, region only)
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import pathlib
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np

from jaxtrack.bench import command_line, output_path, report_header, save_text, start_experiment

RESULTS = pathlib.Path(__file__).resolve().parent / "results"
SHARED = pathlib.Path(os.environ.get("JAXTRACK_SHARED", pathlib.Path(__file__).resolve().parents[2] / "shared"))
M3T_RUN = SHARED / "baselines" / "m3t" / "run.sh"
M3T_BIN = pathlib.Path(os.environ.get("M3T_BASELINE_ROOT", pathlib.Path.home() / ".cache" / "m3t-baseline")) / "build" / "m3t_run_bop"
ALL_CUES = ("region", "flow", "sift")
STAGES_FIXED = ("frame context (crops, render at t)", "render", "host inputs (SIFT detect + match)", "prediction solve",
                "refinement solve", "occlusion")
# Issue 23's goals (640x480, this 2-core CPU, after the first frame): ms per frame by (cues, cameras), and the
# first frame from a fresh process with an empty / a warm compilation cache.
GOALS = {("all", 1): 50.0, ("region", 1): 10.0, ("all", 4): 150.0, "cold_s": 20.0, "warm_s": 3.0}


def m3t_available() -> bool:
    """The M3T baseline runner and its binary are built on this machine."""
    return M3T_RUN.is_file() and M3T_BIN.is_file()


def parse_configs(text: str) -> list[tuple[str, int]]:
    """'region:1,all:2' → [('region', 1), ('all', 2)]; errors name the bad entry."""
    out = []
    for item in text.split(","):
        cues, _, cams = item.strip().partition(":")
        if cues not in ("region", "all") or cams not in ("1", "2", "3", "4"):
            raise SystemExit(f"bench_track: --configs entry {item!r} must be region:N or all:N with N in 1..4")
        out.append((cues, int(cams)))
    return out


# --- the subprocess: one configuration, one cache state --------------------------------------------
def _median_ms(fn, repeats: int) -> float:
    import jax

    jax.block_until_ready(fn())  # compile (or cache hit) + one run
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t)
    return 1000.0 * float(np.median(times))


def stage_breakdown(tracker, state, frames_np, repeats: int, host_cache: dict | None = None) -> dict:
    """ms per call and calls per frame of each stage of `track_step`, each jitted alone on the inputs
    of one frame (state at t, frames t+1), through the modality protocol itself (no copy of the loop):
    the frame context (crops, render at χ_t), each modality's `start`, `rows` (one refinement round),
    `update`, the prediction and refinement solves on `fuse_rows`, and the occlusion update. The whole
    frame (`Tracker.step`) is timed on the same inputs. `host_cache`: the tracker's host state before the step from
    `state` (SIFT: frame t's keypoints, detected by the step before as its frame t+1); the host inputs are timed
    from it, as the tracker makes them (one detection a frame), and without it (two)."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    from jaxtrack.cues.levelset import projected_boxes
    from jaxtrack.cues.occlusion import detect_occlusion, observe_texels, update_appearance
    from jaxtrack.modality import Pose, fuse_rows, render_crops
    from jaxtrack.solve import JointPrior, PosePrior, SolverConfig, solve_pose
    from jaxtrack.track._step import _robust_prediction, frame_context, modality_context

    config, model, dtype = tracker.config, tracker.model, tracker.dtype
    frames = tracker.check_frames(frames_np)
    boxes = projected_boxes(tracker.mesh, tracker.cameras, state.T_world_root, state.theta, model)
    offsets_np, crop_shape, scales_np = tracker.windows(state.T_world_root, state.theta, boxes)
    params = tracker.params_for(crop_shape)
    offsets = jnp.asarray(offsets_np)
    scales = None if scales_np is None else jnp.asarray(scales_np)
    frames_j = jnp.asarray(frames, dtype)
    setup = tracker.setup()
    config = setup.config  # "auto" resolved by the tracker
    modalities = config.modalities()
    out = {"crop": list(crop_shape), "ms": {}, "calls": {}}

    # The whole frame as the tracker runs it (host crop + host inputs + the compiled step), same inputs.
    box_motion = tracker.last_box_motion

    # The host state before that step (`host_cache`: frame t's keypoints), a copy per call made before the timing.
    caches = [copy.deepcopy(host_cache) for _ in range(repeats + 2)] if host_cache is not None else None

    def whole():
        # keep the windows (and so the compiled program) fixed, and the host state the step started from
        tracker.last_box_motion = box_motion
        if caches:
            tracker.host_cache = caches.pop()
        return tracker.step(state, frames)[1].T_world_root

    out["whole_ms"] = _median_ms(whole, repeats)
    tracker.last_box_motion = box_motion
    if caches:
        tracker.host_cache = caches.pop()
    _, result, _ = tracker.step(state, frames)
    rounds = int(result.iterations)
    out["rounds"] = rounds
    final = Pose(result.T_world_root, result.theta)
    refined = any(not m.motion for m in modalities)

    ctx_fn = eqx.filter_jit(lambda st, fr, off: frame_context(setup, st, fr, off, crop_shape, scales))
    def context_leaves():
        ctx = ctx_fn(state, frames_j, offsets)
        return jax.tree.leaves((ctx.crops, ctx.render_t))

    out["ms"]["frame context (crops, render at t)"] = _median_ms(context_leaves, repeats)
    out["calls"]["frame context (crops, render at t)"] = 1
    ctx = ctx_fn(state, frames_j, offsets)
    rend = eqx.filter_jit(lambda c, p: render_crops(c, p).depth)
    out["ms"]["render"] = _median_ms(lambda: rend(ctx, final), repeats)
    final_render = config.runs_occlusion() or any(m.motion or (m.contour and m.needs_render) for m in modalities)
    out["calls"]["render"] = int(final_render) + (rounds if refined and any(m.needs_render for m in modalities) else 0)

    def host_ms(cache):
        times = []
        for _ in range(repeats):
            tracker.host_cache = copy.deepcopy(cache) if cache is not None else {}
            t = time.perf_counter()
            host = tracker.host_inputs(state, frames)
            times.append(time.perf_counter() - t)
        return 1000.0 * float(np.median(times)), host

    kept_cache = tracker.host_cache
    ms_fresh, host = host_ms(None)
    if any(h is not None for h in host):
        out["ms"]["host inputs (SIFT detect + match)"] = ms_fresh if host_cache is None else host_ms(host_cache)[0]
        out["calls"]["host inputs (SIFT detect + match)"] = 1
        out["host_fresh_ms"] = ms_fresh  # frame t's keypoints detected again (no state from the frame before)
    tracker.host_cache = kept_cache

    contexts = [modality_context(ctx, setup, i) for i in range(len(modalities))]
    data = []
    for m, mc, s, h in zip(modalities, contexts, state.modalities, host):
        fn = eqx.filter_jit(lambda c, s, h, p, m=m: m.start(c, s, h, p))
        ms = _median_ms(lambda fn=fn, mc=mc, s=s, h=h: jax.tree.leaves(fn(mc, s, h, params)), repeats) if jax.tree.leaves(
            jax.eval_shape(lambda mc=mc, s=s, h=h, m=m: m.start(mc, s, h, params))) else 0.0
        out["ms"][f"{m.name}: start"] = ms
        out["calls"][f"{m.name}: start"] = 1
        data.append(fn(mc, s, h, params))
    pred_pose = Pose(state.T_world_root, state.theta)
    data = [m.check_prediction(mc, s, d, pred_pose, params) for m, mc, s, d in zip(modalities, contexts, state.modalities, data)]
    motion = [i for i, m in enumerate(modalities) if m.motion]
    T_t, theta_t = state.T_world_root, state.theta
    if motion:
        pred = eqx.filter_jit(lambda d: _robust_prediction(  # the step's prediction: with its Cauchy-weighted second pass
            ctx, model, fuse_rows([modalities[i] for i in motion], d, params, prediction=True), T_t, theta_t, params,
            ctx.cameras.center_world if config.depth_invariance is not False else None,  # as the step
            config.prediction_steps).T_world_root)
        out["ms"]["prediction solve"] = _median_ms(lambda: pred([data[i] for i in motion]), repeats)
        out["calls"]["prediction solve"] = 1
    if refined:
        ren = render_crops(ctx, final)
        carries = [m.round_start(mc, s, d, params) for m, mc, s, d in zip(modalities, contexts, state.modalities, data)]
        sets = []
        for m, mc, s, d, c in zip(modalities, contexts, state.modalities, data, carries):
            fn = eqx.filter_jit(lambda s, d, c, r, m=m, mc=mc: m.rows(mc, s, d, c, final, r, jnp.ones((), jnp.int32), params))
            out["ms"][f"{m.name}: rows"] = 0.0 if m.motion else _median_ms(lambda fn=fn, s=s, d=d, c=c: fn(s, d, c, ren)[0].weight, repeats)
            out["calls"][f"{m.name}: rows"] = rounds
            sets.append(fn(s, d, c, ren)[0])
        solve = eqx.filter_jit(lambda sets: solve_pose(
            model, fuse_rows(modalities, sets, params), final.T_world_root, final.theta, SolverConfig(max_steps=config.region.solver_steps),
            prior=JointPrior(final.theta, params.region.joint_prior),
            pose_prior=PosePrior(final.T_world_root, params.pose_prior_rotation, params.pose_prior_translation),
            ray_origins=ctx.cameras.center_world if config.depth_invariance is not False else None,  # as the step
            depth_invariance=params.depth_invariant).T_world_root)
        out["ms"]["refinement solve"] = _median_ms(lambda: solve(sets), repeats)
        out["calls"]["refinement solve"] = rounds
        for m, mc, s, d, c in zip(modalities, contexts, state.modalities, data, carries):
            fn = eqx.filter_jit(lambda s, d, c, m=m, mc=mc: m.update(mc, s, d, c, final, params))
            leaves = jax.tree.leaves(jax.eval_shape(lambda s=s, d=d, c=c, m=m, mc=mc: m.update(mc, s, d, c, final, params)))
            if leaves:
                out["ms"][f"{m.name}: update"] = _median_ms(lambda fn=fn, s=s, d=d, c=c: jax.tree.leaves(fn(s, d, c)), repeats)
                out["calls"][f"{m.name}: update"] = 1

    if config.runs_occlusion():
        def occlusion(c, T, th):
            ren = render_crops(c, Pose(T, th))
            obs = observe_texels(tracker.atlas, c.crops, ren.depth, c.crop_cameras, T, params.occlusion, th, model,
                                 config.occlusion_config)
            occ = detect_occlusion(tracker.atlas, state.appearance, obs, ren, params.occlusion, config.occlusion_config)
            return update_appearance(state.appearance, obs, occ.occluded, params.occlusion, hold_new=occ.near_occlusion)

        occ_fn = eqx.filter_jit(occlusion)
        ms = _median_ms(lambda: jax.tree.leaves(occ_fn(ctx, final.T_world_root, final.theta))[0], repeats)
        out["ms"]["occlusion"] = max(ms - out["ms"]["render"], 0.0)  # its render at χ_{t+1} is counted under render
        out["calls"]["occlusion"] = 1
    return out


def worker(spec: dict) -> dict:
    """One configuration in this (fresh) process: first frame, then timed frames, then the breakdown."""
    start_experiment(cache=spec["cache_dir"] or False, compile_tiers=True)  # OpenCV on one thread; this configuration's cache folder
    import equinox as eqx
    import ml_dtypes  # loaded by jax already: named here for the versions the result reports

    import jaxtrack
    from jaxtrack import _tiered
    from jaxtrack.geometry import make_camera, rotation_error_deg, stack_cameras
    from jaxtrack.io import load_mesh, read_sequence
    from jaxtrack.track import Tracker, TrackerConfig, track_step

    imported_s = time.time() - spec["launched"]
    seq = read_sequence(spec["sequence"])
    views = list(range(spec["cameras"]))
    rig = stack_cameras([make_camera(seq.views[c].K, seq.views[c].width, seq.views[c].height, seq.views[c].T_cam_world[:3, :3],
                                     seq.views[c].T_cam_world[:3, 3]) for c in views])
    view0 = seq.views[0]
    gt = view0.T_cam_obj[1]
    T_cam0_world = np.asarray(view0.T_cam_world, np.float64)
    T_world_gt = np.einsum("ij,fjk->fik", np.linalg.inv(T_cam0_world), gt)
    cues = ALL_CUES if spec["cues"] == "all" else ("region",)
    region = spec.get("region")
    extra = {} if region is None else {"region_modality": region}
    if spec.get("working_shape"):
        extra["working_shape"] = tuple(spec["working_shape"])
    config = TrackerConfig(cues=cues, **extra)
    tracker = Tracker(load_mesh(seq.model_paths[1]), rig, config=config)

    def frames(k):
        return np.stack([seq.views[c].read_frame(k, dtype=None) for c in views])  # 8-bit, as track_sequence reads them

    def traces():
        try:
            return eqx.debug.get_num_traces(track_step)
        except ValueError:  # the step is no longer wrapped in assert_max_traces: count nothing
            return 0

    t = time.perf_counter()
    state = tracker.start(frames(0), T_world_gt[0])
    start_s = time.perf_counter() - t
    t = time.perf_counter()
    state, result, info = tracker.step(state, frames(1))
    first_step_s = time.perf_counter() - t
    out = {"imported_s": imported_s, "start_s": start_s, "first_step_s": first_step_s, "ready_s": time.time() - spec["launched"],
           "crop": list(info["crop_shape"] or ()), "jaxtrack_from": str(pathlib.Path(jaxtrack.__file__).parent),
           "ml_dtypes": ml_dtypes.__version__, "trimesh_imported": "trimesh" in sys.modules}
    if spec["mode"] == "warm":
        return out
    # The step compiled quickly for the first frame: the frames after it run that build while a background process
    # compiles the optimised one (`jaxtrack._tiered`); timed here, then the frames again from frame 1 on the swapped build.
    if _tiered.optimise_counts()[0]:
        kept = (state, result, tracker.last_box_motion, copy.deepcopy(tracker.host_cache))
        t_ready, quick = time.perf_counter(), []
        for k in range(2, seq.num_frames):
            state, _, info = tracker.step(state, frames(k))
            quick.append(info["timings"]["total_s"])
        out["swapped"] = _tiered.wait_for_optimised_programs(timeout=900)
        out["optimised_after_s"] = time.perf_counter() - t_ready
        out["quick_frame_ms"] = 1000.0 * float(np.median(quick)) if quick else float("nan")
        out["optimise_failures"] = _tiered.optimise_failures()
        state, result, tracker.last_box_motion, tracker.host_cache = kept
    rot = [float(rotation_error_deg(np.asarray(result.T_world_root)[:3, :3], T_world_gt[1][:3, :3]))]
    trans = [float(np.linalg.norm(np.asarray(result.T_world_root)[:3, 3] - T_world_gt[1][:3, 3]))]
    total, step, sift, rounds, retraced, crops = [], [], [], [], 0, set()
    prev = prev_motion = prev_cache = None
    for k in range(2, seq.num_frames):
        images = frames(k)
        before = traces()
        prev, prev_motion, prev_cache = state, tracker.last_box_motion, copy.deepcopy(tracker.host_cache)
        state, result, info = tracker.step(state, images)
        T = np.asarray(result.T_world_root)
        rot.append(float(rotation_error_deg(T[:3, :3], T_world_gt[k][:3, :3])))
        trans.append(float(np.linalg.norm(T[:3, 3] - T_world_gt[k][:3, 3])))
        if traces() != before:
            retraced += 1
            continue
        tm = info["timings"]
        total.append(tm["total_s"])
        step.append(tm.get("step_s", np.nan))
        sift.append(tm.get("detect_s", 0.0) + tm.get("match_s", 0.0))
        rounds.append(int(result.iterations))
        crops.add(tuple(info["crop_shape"] or ()))
    out.update({
        "frame_ms": 1000.0 * float(np.median(total)) if total else float("nan"),
        "step_ms": 1000.0 * float(np.median(step)) if step else float("nan"),
        "sift_ms": 1000.0 * float(np.median(sift)) if sift else float("nan"),
        "rounds": float(np.median(rounds)) if rounds else float("nan"),
        "timed": len(total), "retraced": retraced, "crops": sorted(crops),
        "rot_deg": float(np.mean(rot)), "trans_mm": float(np.mean(trans)), "max_rot_deg": float(np.max(rot)),
    })
    if spec["breakdown"] and prev is not None:
        tracker.last_box_motion = prev_motion  # that frame's windows: the same crop class and program
        out["stages"] = stage_breakdown(tracker, prev, frames(seq.num_frames - 1), spec["repeats"], prev_cache)
    return out


def run_worker(spec: dict, timeout_s: float, env: dict | None = None) -> dict:
    """Launch `worker(spec)` in a fresh Python process and read back its JSON result. `env`: variables set
    for that process on top of this one's (e.g. a PYTHONPATH that puts another tree or package first)."""
    spec = dict(spec, launched=time.time())
    proc = subprocess.run([sys.executable, __file__, "--worker", json.dumps(spec)], check=False, capture_output=True, text=True,
                          timeout=timeout_s, env=dict(os.environ, PYTHONUNBUFFERED="1", **(env or {})))
    for line in proc.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[len("RESULT "):])
    raise RuntimeError(f"bench_track worker {spec['cues']}:{spec['cameras']} ({spec['mode']}) failed with code "
                       f"{proc.returncode}:\n{proc.stderr[-4000:]}")


# --- the sequence and M3T ---------------------------------------------------------------------------
def write_bench_sequence(root: pathlib.Path, cameras: int, frames: int, scale: float, preset: str | None = None):
    """The textured box sequence (or a `PRESETS` entry), scaled; and the object's width in pixels in
    frame 0 of camera 0."""
    import dataclasses

    import cv2

    from jaxtrack.synth import PRESETS, SynthConfig, write_sequence

    if preset is None:
        cfg = SynthConfig(object="box", appearance="photo", texture_photo="chelsea", size_mm=170, background="coffee",
                          motion="random", step_px=10, step_deg=3, seed=3)
    else:
        cfg = PRESETS[preset]
    # Scaling the image scales the focal length and the motion in pixels with it (same scene, same motion).
    cfg = dataclasses.replace(cfg, frames=frames, cameras=cameras, width=round(640 * scale), height=round(480 * scale),
                              focal=cfg.focal * scale, step_px=cfg.step_px * scale)
    write_sequence(cfg, root)
    mask = cv2.imread(str(root / "000000" / "object_mask" / "000000.png"), cv2.IMREAD_GRAYSCALE) > 0
    xs = np.nonzero(mask.any(axis=0))[0]
    return root, int(xs.max() - xs.min() + 1) if len(xs) else 0


def run_m3t(sequence: pathlib.Path, config: str, out_dir: pathlib.Path) -> dict:
    """M3T (`region` or `regtex`) on camera 0, one thread: median ms per frame of its CSV `time`
    column (the tracking cycle, image decoding excluded), frames after the first."""
    csv = out_dir / f"m3t_{config}.csv"
    proc = subprocess.run([str(M3T_RUN), str(sequence), "-o", str(csv), "--config", config], check=False, capture_output=True, text=True,
                          timeout=900)
    if proc.returncode != 0 or not csv.is_file():
        raise RuntimeError(f"M3T {config} failed ({proc.returncode}): {proc.stderr[-2000:]}")
    times = [float(line.rsplit(",", 1)[1]) for line in csv.read_text().splitlines()[1:] if line.strip()]
    return {"ms": 1000.0 * float(np.median(times[1:])), "frames": len(times) - 1}


# --- the report ----------------------------------------------------------------------------------------
def _warm(warm) -> str:
    if warm is None:
        return "not measured (--quick)"
    return f"{warm['ready_s']:.1f} ({warm['start_s']:.1f} / {warm['first_step_s']:.1f})"


def _fmt(x, digits=1):
    return "n/a" if x is None or not np.isfinite(x) else f"{x:.{digits}f}"


def _quick(cold) -> str:
    if "optimised_after_s" not in cold:
        return "- (one build)"
    failed = " (optimising failed)" if cold.get("optimise_failures") else "" if cold.get("swapped", True) else " (not swapped)"
    return f"{_fmt(cold['quick_frame_ms'])} ms, {_fmt(cold['optimised_after_s'])} s{failed}"


def report(args, command, width_px, size, rows, m3t, load_start, load_end, elapsed_s) -> str:
    header = report_header(command, load_start, load_end, elapsed_s)
    if max(load_start[0], load_end[0], load_start[1]) > 1.5:
        header[-1] += " Other jobs shared the machine during this run: times are upper bounds (they vary ~2x between runs)."
    lines = [
        "# Tracker speed",
        "",
        *header,
        "",
        (f"Sequence: synthetic textured box, {size[0]}x{size[1]}, box {width_px} px wide in frame 0 of camera 0, "
         f"random 6-DoF motion (~{10 * args.scale:.0f} px, 3° per frame), {args.frames} frames; cameras on a ring, "
         "the tracker's default configuration and parameters." if args.preset is None else
         f"Sequence: the `{args.preset}` preset scaled to {size[0]}x{size[1]} (object {width_px} px wide in frame 0), "
         f"{args.frames} frames, the tracker's default configuration and parameters."),
        *(["", ("--quick: one configuration run in this process (cold = whatever this process had compiled before; "
                "no warm-cache run); a smoke test of the script, not a measurement.")] if args.quick else []),
        "",
        ("| cues | cameras | crop | ms / frame | frames / s | jitted step ms | SIFT host ms | rounds | timed frames (retraced) "
         "| first frame, cold cache (s) | of which start / first step | after it, cold: ms / frame until the optimised "
         "build, which came (s) | first frame, warm cache (s) (start / first step) | mean rot ° / trans mm |"),
        "|---|---:|---|---:|---:|---:|---:|---:|---|---:|---|---|---:|---|",
    ]
    for (cues, cams), (cold, warm) in rows.items():
        crop = ", ".join(f"{c[0]}x{c[1]}" for c in cold.get("crops", [])) or "x".join(map(str, cold["crop"]))
        fps = 1000.0 / cold["frame_ms"] if np.isfinite(cold["frame_ms"]) else float("nan")
        lines.append(
            f"| {'region' if cues == 'region' else 'region+flow+sift'} | {cams} | {crop} | {_fmt(cold['frame_ms'])} | "
            f"{_fmt(fps, 2)} | {_fmt(cold['step_ms'])} | {_fmt(cold['sift_ms']) if cues == 'all' else '-'} | "
            f"{_fmt(cold['rounds'], 0)} | {cold['timed']} ({cold['retraced']}) | {_fmt(cold['ready_s'])} | "
            f"{_fmt(cold['start_s'])} / {_fmt(cold['first_step_s'])} | {_quick(cold)} | {_warm(warm)} | "
            f"{_fmt(cold['rot_deg'], 2)} / {_fmt(cold['trans_mm'], 1)} |"
        )
    lines += [
        "",
        ("ms / frame: median host time of `Tracker.step` (crop, SIFT detection and matching on the host, the jitted "
         "step, waiting for its result) over the frames after the first; frames that traced the step again (new crop "
         "class or raster plan) are left out and counted in brackets. First frame: from launching a fresh Python process "
         "(imports included, ~"
         f"{_fmt(np.median([r[0]['imported_s'] for r in rows.values()]))} s) to the first tracked frame; cold = empty "
         "on-disk compilation cache, warm = the cache the cold process filled (`jaxtrack track`'s settings). "
         "start = `Tracker.start` (texture atlas, first render, appearance model: op-by-op dispatch), first step = "
         "`Tracker.step` on frame 1 (compiles the step; with an empty cache its quick build, `jaxtrack._tiered`). With an "
         "empty cache the frames after the first run the quick build while a background process compiles the optimised "
         "one (their median ms, and the seconds from the first frame until the swap); ms / frame and the breakdown are "
         "timed after the swap, from frame 1 again. Errors: mean over the tracked frames, against the ground truth."),
    ]
    for (cues, cams), (cold, _) in rows.items():
        for failure in cold.get("optimise_failures") or []:
            lines += ["", f"Optimising {cues}:{cams} failed: {failure.strip()}"]
    with_stages = [(k, v[0]["stages"]) for k, v in rows.items() if "stages" in v[0]]
    if with_stages:
        header = " | ".join(f"{'region' if c == 'region' else 'all'}, {n} cam ({s['rounds']} rounds, crop {s['crop'][0]}x{s['crop'][1]})"
                            for (c, n), s in with_stages)
        lines += [
            "",
            "## Per-stage breakdown (ms per frame = ms per call x calls per frame)",
            "",
            ("Each stage jitted on its own and timed on the inputs of the last tracked frame (state at t, frames t+1; "
             f"medians of {args.repeats}); calls per frame from the rounds the refinement ran on that frame, through the "
             "modality protocol (no copy of the loop). Frame context: the crops and, when a motion modality reads it, the "
             "render at χ_t. Render: the model in every crop, once per refinement round for modalities that render, and "
             "at χ_{t+1} when the occlusion map or a segmentation needs it. 'M: start / rows / update': that modality's "
             "per-frame work, one round's rows (the level set: Φ0, segmentation and shape matching; lines: nearest view, "
             "lines, distributions) and its end-of-frame update. Solves: `solve_pose` on the fused rows. Occlusion: "
             "texel observation, detection (eq. 9) and appearance update (eq. 10), its render excluded. Host inputs: "
             "made alone (the device idle), with frame t's keypoints kept from the frame before as the tracker keeps "
             "them (one detection a frame); 'detected again' below: without them (two). "
             "'whole step' is `Tracker.step` on the same inputs; separately jitted stages lose XLA's fusion across "
             "stages, so the sum and the whole differ."),
            "",
            f"| stage | {header} |",
            "|---|" + "---:|" * len(with_stages),
        ]
        named = sorted({k for _, s in with_stages for k in s["ms"] if k not in STAGES_FIXED})
        for stage in STAGES_FIXED[:4] + tuple(named) + STAGES_FIXED[4:]:
            cells = []
            for _, s in with_stages:
                if stage in s["ms"]:
                    cells.append(f"{s['ms'][stage] * s['calls'][stage]:.1f} ({s['calls'][stage]} x {s['ms'][stage]:.2f})")
                else:
                    cells.append("-")
            lines.append(f"| {stage} | {' | '.join(cells)} |")
            if stage == "host inputs (SIFT detect + match)":
                fresh = [f"{s['host_fresh_ms']:.1f}" if "host_fresh_ms" in s else "-" for _, s in with_stages]
                lines.append(f"| host inputs, frame t's keypoints detected again | {' | '.join(fresh)} |")
        sums = [sum(s["ms"][k] * s["calls"][k] for k in s["ms"]) for _, s in with_stages]
        lines.append(f"| sum of the stages | {' | '.join(f'{x:.1f}' for x in sums)} |")
        wholes = " | ".join(f"{s['whole_ms']:.1f}" for _, s in with_stages)
        lines.append(f"| whole step (`Tracker.step`, same inputs) | {wholes} |")
    lines += ["", "## DLR M3T on the same frames (camera 0)", ""]
    if m3t is None:
        lines.append("Skipped (--no-m3t)." if args.no_m3t else
                     f"Skipped: the M3T baseline is not built on this machine ({M3T_BIN} missing; see {M3T_RUN.parent}/README.md).")
    else:
        lines += [
            "| M3T config | ms / frame | frames / s | frames |",
            "|---|---:|---:|---:|",
        ] + [f"| {name} | {r['ms']:.2f} | {1000.0 / r['ms']:.0f} | {r['frames']} |" for name, r in m3t.items()]
        lines += ["", ("M3T: monocular, one thread, its RBOT parameters (`../shared/baselines/m3t/run.sh`); ms = median of "
                       "its CSV `time` column (the tracking cycle, image decoding excluded) over the frames after the first.")]
    lines += ["", "## Where we stand against the goals (issue 23)", ""] + goals(rows, m3t)
    return "\n".join(lines) + "\n"


def goals(rows, m3t) -> list[str]:
    out = []
    for key in (("all", 1), ("region", 1), ("all", 4)):
        r = rows.get(key)
        if r is None:
            continue
        ms, goal = r[0]["frame_ms"], GOALS[key]
        name = f"{'all cues' if key[0] == 'all' else 'region only'}, {key[1]} camera{'s' if key[1] > 1 else ''}"
        out.append(f"- {name}: {ms:.1f} ms per frame (goal ≤ {goal:.0f}): "
                   f"{'met' if ms <= goal else f'{ms / goal:.1f}x too slow'}.")
    one = [r for (c, n), r in rows.items() if n == 1]
    if one and all(r[1] is not None for r in one):
        cold = max(r[0]["ready_s"] for r in one)
        warm = max(r[1]["ready_s"] for r in one)
        out.append(f"- first frame, empty compile cache: up to {cold:.0f} s (goal ≤ {GOALS['cold_s']:.0f}): "
                   f"{'met' if cold <= GOALS['cold_s'] else 'not met'}; warm cache: up to {warm:.1f} s "
                   f"(goal ≤ {GOALS['warm_s']:.0f}): {'met' if warm <= GOALS['warm_s'] else 'not met'}.")
    for (cues, cams), (cold, _) in rows.items():
        s = cold.get("stages")
        if s is None or cams != 1:
            continue
        per = {k: s["ms"][k] * s["calls"][k] for k in s["ms"]}
        top = sorted(per.items(), key=lambda kv: -kv[1])[:3]
        total = sum(per.values())
        out.append(f"- what dominates ({'all cues' if cues == 'all' else 'region only'}, 1 camera): "
                   + ", ".join(f"{k} {v:.0f} ms ({100 * v / total:.0f} %)" for k, v in top) + ".")
    if m3t:
        out.append("- M3T on the same frames: " + ", ".join(f"{k} {v['ms']:.1f} ms" for k, v in m3t.items()) + ".")
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true",
                    help="smoke run in this process: region, 1 camera, occluded-box at 96x72 (crop = whole frame), 4 frames")
    ap.add_argument("--configs", default="region:1,all:1,all:2,all:4", help="cue set (region|all) : cameras, comma-separated")
    ap.add_argument("--region", default=None,
                    help="the region modality of 'region' (levelset | lines; default: TrackerConfig's)")
    ap.add_argument("--working-shape", default=None,
                    help="HxW fixed working resolution of the crops (TrackerConfig.working_shape; default: the tracker's)")
    ap.add_argument("--frames", type=int, default=8, help="frames of the sequence (the first initialises, the second compiles)")
    ap.add_argument("--scale", type=float, default=1.0, help="image scale (1 = 640x480, f = 700)")
    ap.add_argument("--preset", default=None, help="a jaxtrack.synth preset instead of the textured box")
    ap.add_argument("--repeats", type=int, default=5, help="repeats per stage timing")
    ap.add_argument("--breakdown-cameras", default="1,2,3,4", help="camera counts that get the per-stage breakdown ('' = none)")
    ap.add_argument("--budget-min", type=float, default=None,
                    help="start no new configuration after this many minutes (the rest is reported as not run)")
    ap.add_argument("--no-m3t", action="store_true", help="skip the M3T baseline")
    ap.add_argument("--timeout", type=float, default=1200, help="seconds per subprocess")
    ap.add_argument("--out", default=None, help="markdown output (default experiments/results/bench_track.md; --quick: none)")
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker is not None:
        print("RESULT " + json.dumps(worker(json.loads(args.worker))), flush=True)
        return None
    if args.quick:  # the same sequence and configuration as track_presets.py --quick (one compiled program)
        args.configs, args.frames, args.scale, args.repeats, args.preset = "region:1", 4, 0.15, 1, "occluded-box"
    if args.frames < 3:
        raise SystemExit("bench_track: --frames must be ≥ 3 (initialise, compile, time)")
    configs = parse_configs(args.configs)
    working_shape = None
    if args.working_shape:
        try:
            working_shape = [int(v) for v in args.working_shape.lower().split("x")]
            assert len(working_shape) == 2
        except (ValueError, AssertionError):
            raise SystemExit(f"bench_track: --working-shape must be HxW, e.g. 96x128, got {args.working_shape!r}") from None
    command = command_line(__file__, argv)
    clock = start_experiment(cache=False, compile_tiers=True)  # each configuration's subprocess has its own cache
    work = pathlib.Path(tempfile.mkdtemp(prefix="bench_track_"))
    try:
        cameras = max(n for _, n in configs)
        seq, width_px = write_bench_sequence(work / "seq", cameras, args.frames, args.scale, args.preset)
        size = (round(640 * args.scale), round(480 * args.scale))
        rows, skipped, failed = {}, [], []
        for cues, cams in configs:
            if clock.over(args.budget_min):
                skipped.append(f"{cues}:{cams}")
                continue
            cache = work / f"xla_{cues}_{cams}"  # a fresh, empty on-disk cache per configuration
            spec = {"sequence": str(seq), "cues": cues, "cameras": cams, "cache_dir": str(cache), "repeats": args.repeats,
                    "breakdown": str(cams) in args.breakdown_cameras.split(","), "region": args.region,
                    "working_shape": working_shape}
            t = time.perf_counter()
            if args.quick:  # in this process: no fresh interpreter, no cache, no warm run
                cold, warm = worker(dict(spec, mode="cold", cache_dir=None, launched=time.time())), None
            else:
                try:
                    cold = run_worker(dict(spec, mode="cold"), args.timeout)
                    warm = run_worker(dict(spec, mode="warm"), args.timeout)
                except (RuntimeError, subprocess.TimeoutExpired) as e:  # report it and go on with the others
                    failed.append(f"{cues}:{cams} ({type(e).__name__}: {str(e).strip().splitlines()[-1][:300]})")
                    print(f"[bench_track] {failed[-1]}", file=sys.stderr, flush=True)
                    continue
            rows[(cues, cams)] = (cold, warm)
            print(f"[bench_track] {cues}:{cams} {cold['frame_ms']:.0f} ms/frame, first frame {cold['ready_s']:.0f} s cold, "
                  f"{_warm(warm)} warm ({time.perf_counter() - t:.0f} s)", file=sys.stderr, flush=True)
        m3t = None
        if not args.no_m3t and m3t_available():
            try:
                m3t = {name: run_m3t(seq, name, work) for name in ("region", "regtex")}
            except (RuntimeError, subprocess.TimeoutExpired) as e:
                failed.append(f"M3T ({type(e).__name__}: {str(e).strip().splitlines()[-1][:300]})")
        text = report(args, command, width_px, size, rows, m3t, clock.load_start, os.getloadavg(), clock.elapsed_s())
        if skipped:
            text += f"\nNot run, the time budget (--budget-min {args.budget_min:g}) was spent: {', '.join(skipped)}.\n"
        if failed:
            text += "\nFailed: " + "; ".join(failed) + "\n"
    finally:
        shutil.rmtree(work, ignore_errors=True)
    print(text)
    save_text(output_path(args.out, RESULTS / "bench_track.md", args.quick), text)
    return rows, m3t


if __name__ == "__main__":
    main()
