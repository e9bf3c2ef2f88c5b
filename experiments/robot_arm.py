"""Robot-arm tracking (issue 13, experiment 2): joint-angle and root errors per cue subset, 1 and 2 cameras,
with and without the URDF's joint limits, and seconds per frame.

The Franka Panda of ../shared/data/articulated (its collision meshes: 2.4k faces; the visual meshes have
135k) moves along smooth random joint trajectories within its limits (`random_joint_trajectory`, the 7
arm joints; the gripper is held), rendered by the independent ray caster with a colour per link over a
photo (`jaxtrack synth --urdf`). `track_sequence` tracks it from the first frame's true pose and
joints. Errors are over the tracked frames: |estimated − true| of the 7 arm joints (degrees; mean and
max) and the root link's pose (camera 0).

    python experiments/robot_arm.py                 # writes experiments/results/robot_arm.md and .png
    python experiments/robot_arm.py --cues region+flow --cameras 1 --frames 20
    python experiments/robot_arm.py --region lines   # the correspondence lines instead of the level set
"""

from __future__ import annotations

import argparse
import os
import pathlib
import platform
import tempfile
import time

import numpy as np

from jaxtrack.bench import command_line, save_text, source_state, start_experiment

RESULTS = pathlib.Path(__file__).resolve().parent / "results"
SHARED = pathlib.Path(os.environ.get("JAXTRACK_SHARED", pathlib.Path(__file__).resolve().parents[2] / "shared"))
ROBOTS = SHARED / "data" / "articulated"
PANDA = ROBOTS / "example-robot-data" / "robots" / "panda_description" / "urdf" / "panda.urdf"
ARM_JOINTS = tuple(f"panda_joint{k}" for k in range(1, 8))
STAGES = ("read_s", "detect_s", "match_s", "step_s", "total_s")


def write_arm_sequence(folder: pathlib.Path, cameras: int, frames: int, scale: float, step_deg: float, seed: int):
    from jaxtrack.io import read_urdf
    from jaxtrack.synth import (
        ArticulatedSynthConfig,
        random_joint_trajectory,
        upright_urdf_pose,
        write_articulated_sequence,
    )

    root = folder / f"panda_{cameras}cam_{frames}_{scale}_{step_deg}_{seed}"
    if (root / "synth_config.json").is_file():
        return root
    arm = read_urdf(PANDA, package_dirs=[ROBOTS], geometry="collision")
    theta = random_joint_trajectory(arm, frames, step_deg=step_deg, seed=seed)
    T = np.repeat(upright_urdf_pose((0.0, -400.0, 0.0))[None], frames, 0)
    w, h = round(640 * scale) // 4 * 4, round(480 * scale) // 4 * 4
    cfg = ArticulatedSynthConfig(cameras=cameras, width=w, height=h, focal=700.0 * scale, distance=1800.0, seed=seed)
    return write_articulated_sequence(arm, T, theta, cfg, root, info={"urdf": str(PANDA), "step_deg": step_deg})


def run_one(seq_path, cues: str, limits: bool, region: str = "auto") -> dict:
    from jaxtrack.io import read_sequence
    from jaxtrack.track import pose_errors, track_sequence

    seq = read_sequence(seq_path)
    t0 = time.perf_counter()
    run = track_sequence(seq, cues=tuple(cues.split("+")), joint_limits=limits, progress=False,
                         region=None if region == "auto" else region)
    wall = time.perf_counter() - t0
    gt = np.stack([seq.views[0].joints[1][n] for n in run.joint_names], 1)
    idx = [run.joint_names.index(n) for n in ARM_JOINTS]
    err = np.degrees(np.abs(run.joints_urdf()[:, idx] - gt[:, idx]))[1:]
    rot, trans = pose_errors(run.T_cam_obj(0), seq.views[0].T_cam_obj[1])
    seen, steady = set(), []
    for k in range(1, len(run.timings)):  # steps that compiled a new crop size class are left out
        if run.crops[k] is not None and run.crops[k] not in seen:
            seen.add(run.crops[k])
            continue
        steady.append(k)
    stages = {name: float(np.median([run.timings[k].get(name, 0.0) for k in steady])) if steady else float("nan")
              for name in STAGES}
    return {"stages": stages,"joint_mean": float(err.mean()), "joint_max": float(err.max()), "per_joint": err.mean(0),
            "rot": float(rot[1:].mean()), "trans": float(trans[1:].mean()), "frames": len(err),
            "s_per_frame": stages["total_s"], "wall_s": wall,
            "first_s": float(run.timings[0]["total_s"] + run.timings[1]["total_s"]),
            "status": {s: run.status.count(s) for s in set(run.status)},
            "curve": (np.degrees(gt[:, idx]), np.degrees(run.joints_urdf()[:, idx]))}


def report(args, command, rows, elapsed, load) -> str:
    lines = [
        "# Robot arm (Franka Panda from URDF): joint and root errors per cue subset", "",
        f"Command: `{command}`  ",
        (f"Measured: {source_state()}; {platform.machine()}, {os.cpu_count()} cores, load {load[0]:.1f} → {load[1]:.1f}; "
         f"{elapsed / 60:.1f} min.  "),
        (f"Sequence: {args.frames} frames at {round(640 * args.scale) // 4 * 4}x{round(480 * args.scale) // 4 * 4}, the 7 arm "
         f"joints on smooth random trajectories (≤ {args.step_deg}° per frame), a colour per link over a photo, cameras "
         "1.8 m away on a ring; errors over the tracked frames (frame 0 is the given start). Region cue: "
         f"{'the tracker default for a chain' if args.region == 'auto' else args.region}."), "",
        "| cues | cameras | joint limits | joint error mean / max (°) | root (° / mm) | s / frame | first frame (s) | statuses |",
        "|---|---:|---|---:|---:|---:|---:|---|",
    ]
    for (cues, cams, limits), r in rows.items():
        if r is None:
            lines.append(f"| {cues} | {cams} | {'on' if limits else 'off'} | not run (time) | | | | |")
            continue
        st = ", ".join(f"{k} {v}" for k, v in sorted(r["status"].items()))
        lines.append(f"| {cues} | {cams} | {'on' if limits else 'off'} | {r['joint_mean']:.2f} / {r['joint_max']:.2f} | "
                     f"{r['rot']:.2f} / {r['trans']:.2f} | {r['s_per_frame']:.2f} | {r['first_s']:.0f} | {st} |")
    done = [(k, r) for k, r in rows.items() if r is not None]
    if done:
        lines += ["", "Mean error per joint (°), " + ", ".join(ARM_JOINTS) + ":", ""]
        for (cues, cams, limits), r in done:
            lines.append(f"- {cues}, {cams} camera(s), limits {'on' if limits else 'off'}: "
                         + " / ".join(f"{v:.2f}" for v in r["per_joint"]))
        lines += ["", ("Speed per stage (host seconds per frame, median over the steps that compiled nothing; the jitted "
                       "step holds flow, prediction, level sets, Gauss-Newton and the occlusion map):"), "",
                  "| cues | cameras | joint limits | read | SIFT detect | SIFT match | jitted step | total |",
                  "|---|---:|---|---:|---:|---:|---:|---:|"]
        for (cues, cams, limits), r in done:
            st = r["stages"]
            lines.append(f"| {cues} | {cams} | {'on' if limits else 'off'} | {st['read_s']:.2f} | {st['detect_s']:.2f} | "
                         f"{st['match_s']:.2f} | {st['step_s']:.2f} | {st['total_s']:.2f} |")
    lines += ["", ("s / frame: median over the steps that compiled nothing; first frame: Tracker.start plus the first "
              "step (its compilation).")]
    return "\n".join(lines) + "\n"


def plot(path, rows) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    done = [(k, r) for k, r in rows.items() if r is not None]
    if not done:
        return
    (cues, cams, limits), r = max(done, key=lambda kr: (kr[0][1], kr[0][0].count("+"), not kr[0][2]))
    gt, est = r["curve"]
    fig, axes = plt.subplots(1, 7, figsize=(17, 2.6), sharex=True)
    for j, ax in enumerate(axes):
        ax.plot(gt[:, j], "k-", label="truth")
        ax.plot(est[:, j], "r--", label="jaxtrack")
        ax.set_title(ARM_JOINTS[j], fontsize=8)
    axes[0].set_ylabel("angle (°)")
    axes[0].legend(fontsize=7)
    fig.suptitle(f"Panda, {cues}, {cams} camera(s), limits {'on' if limits else 'off'}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cues", default="region,region+flow,region+flow+sift", help="comma-separated cue subsets")
    ap.add_argument("--cameras", default="1,2", help="comma-separated camera counts")
    ap.add_argument("--limits", default="off,on", help="joint limits: off, on or both (off,on); 'on' runs only for "
                    "the last cue subset")
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--scale", type=float, default=0.5)
    ap.add_argument("--step-deg", type=float, default=2.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--budget-min", type=float, default=40.0, help="start no new run after this many minutes")
    ap.add_argument("--seq-dir", default=None)
    ap.add_argument("--region", default="auto", choices=("auto", "levelset", "lines"),
                    help="the region modality \"region\" stands for (default: the tracker's for a chain)")
    ap.add_argument("--out", default=str(RESULTS / "robot_arm.md"))
    ap.add_argument("--plot", default=str(RESULTS / "robot_arm.png"))
    args = ap.parse_args(argv)
    subsets = [c.strip() for c in args.cues.split(",") if c.strip()]
    cams = [int(c) for c in args.cameras.split(",")]
    limits = [v.strip() == "on" for v in args.limits.split(",")]
    command = command_line(__file__, argv)
    clock = start_experiment(cache=False)
    folder = pathlib.Path(args.seq_dir) if args.seq_dir else pathlib.Path(tempfile.mkdtemp(prefix="robot_arm_"))
    rows = {}
    for c in cams:
        seq = write_arm_sequence(folder, c, args.frames, args.scale, args.step_deg, args.seed)
        for cues in subsets:
            for lim in limits:
                if lim and cues != subsets[-1]:
                    continue
                key = (cues, c, lim)
                if clock.over(args.budget_min):
                    rows[key] = None
                    continue
                rows[key] = r = run_one(seq, cues, lim, args.region)
                print(f"{cues:17s} {c} cam limits {'on ' if lim else 'off'}: joints {r['joint_mean']:.2f} / "
                      f"{r['joint_max']:.2f}°, root {r['rot']:.2f}° {r['trans']:.2f} mm, {r['s_per_frame']:.2f} s/frame",
                      flush=True)
    text = report(args, command, rows, clock.elapsed_s(), (clock.load_start[0], os.getloadavg()[0]))
    print(text)
    if args.out:
        save_text(args.out, text)
    if args.plot:
        plot(pathlib.Path(args.plot), rows)
    return rows


if __name__ == "__main__":
    main()
