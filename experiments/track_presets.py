"""Tracking success on the synthetic presets (issue 11, "Accuracy goals"): the 5 cm / 5° success rate
and the mean rotation / translation errors per cue subset, with DLR M3T (region, region + ORB
texture) on the same frames from the same run.

Presets (`jaxtrack.synth.PRESETS`): teabox-large-motion (30 px, 10° per frame), noisy-moving-camera
(σ = 40 noise, moving camera), occluded-box (two moving occluders), stereo-noise (two cameras, σ = 60
noise and 10 % salt) and turntable-teapot (homogeneous, 6° per frame). Each is written once per run
in the BOP layout (`write_sequence`, embree ray caster) to a temporary folder, optionally scaled
(`--scale`: image size, focal length and motion in pixels scale together; the scene is unchanged).

Protocol (RBOT): every frame is compared with the ground truth; beyond 5 cm or 5° it counts as a
failure and tracking restarts from the true pose of that frame (`track_sequence(reset_on_failure=True)`,
M3T's `--reset-on-failure`). Success rate = frames within 5 cm / 5° among the tracked frames (frame 0
initialises and is not counted); errors are means over the tracked frames (a failed frame counts with
its failed estimate). Without resets, a run is the same computation as with resets up to its first
failure, so the first failure frame without resets is read from the run with resets (`--without-reset`
also runs without resets and reports that run's own success rate and first failure). Poses and
ground truth of camera 0 are compared (stereo-noise: jaxtrack uses both cameras, M3T camera 0 alone).

    python experiments/track_presets.py                       # writes experiments/results/track_presets.md
    python experiments/track_presets.py --cues region,region+flow+sift --frames 15 --scale 0.5
    python experiments/track_presets.py --quick --out /tmp/p.md   # smoke run (occluded-box at 96x72, region)
"""

from __future__ import annotations

import argparse
import dataclasses
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
PRESET_NAMES = ("teabox-large-motion", "noisy-moving-camera", "occluded-box", "stereo-noise", "turntable-teapot")
SUBSETS = ("region", "flow", "sift", "region+flow", "region+sift", "flow+sift", "region+flow+sift")
M3T_CONFIGS = ("region", "regtex")


def m3t_available() -> bool:
    """The M3T baseline runner and its binary are built on this machine."""
    return M3T_RUN.is_file() and M3T_BIN.is_file()


def parse_subsets(text: str) -> tuple[str, ...]:
    """'region,flow+sift' → ('region', 'flow+sift'), each in the registry's order (region first); any
    registered modality (`jaxtrack.cli.cue_choices`) may be named."""
    from jaxtrack.cli import cue_choices

    choices = cue_choices()
    out = []
    for item in text.split(","):
        cues = [c.strip() for c in item.split("+") if c.strip()]
        if not cues or any(c not in choices for c in cues) or len(set(cues)) != len(cues):
            raise SystemExit(f"track_presets: --cues entry {item!r} must join modalities from {', '.join(choices)} with '+'")
        out.append("+".join(c for c in choices if c in cues))
    return tuple(out)


def preset_config(name: str, scale: float, frames: int | None):
    """The preset at `scale` (image, focal length and motion in pixels scaled together), `frames` frames."""
    from jaxtrack.synth import PRESETS

    if name not in PRESETS:
        raise SystemExit(f"track_presets: unknown preset {name!r} (have {', '.join(PRESETS)})")
    base = PRESETS[name]
    width, height = round(base.width * scale), round(base.height * scale)
    if width % 4 or height % 4:
        raise SystemExit(f"track_presets: --scale {scale} gives {width}x{height}; the tracker needs multiples of 4")
    return dataclasses.replace(base, width=width, height=height, focal=base.focal * scale, step_px=base.step_px * scale,
                               frames=base.frames if frames is None else min(frames, base.frames))


def write_preset(name: str, cfg, folder: pathlib.Path) -> pathlib.Path:
    """The preset's sequence under `folder` (reused when it was written with the same config)."""
    from jaxtrack.synth import write_sequence

    root = folder / f"{name}_{cfg.width}x{cfg.height}_{cfg.frames}"
    stamp = root / "synth_config.json"
    if stamp.is_file() and json.loads(stamp.read_text()) == json.loads(json.dumps(dataclasses.asdict(cfg))):
        return root
    if root.exists():
        shutil.rmtree(root)
    return write_sequence(cfg, root)


def scores(evaluation, reset_run: bool, step_s=None) -> dict:
    """Success rate, failures, first failure and mean errors over the tracked frames (frame 0 excluded)."""
    tracked = ~evaluation.initial & evaluation.has_gt
    ok = evaluation.success[tracked]
    failed = np.nonzero(~ok)[0]
    ids = evaluation.im_ids[tracked]
    return {
        "frames": int(tracked.sum()),
        "success": float(ok.mean()) if ok.size else float("nan"),
        "failures": int(failed.size),
        "first_failure": int(ids[failed[0]]) if failed.size else None,
        "rot_deg": float(np.mean(evaluation.rot_deg[tracked])),
        "trans_mm": float(np.mean(evaluation.trans_mm[tracked])),
        "ms": 1000.0 * float(np.median(step_s)) if step_s is not None and len(step_s) else float("nan"),
        "reset_run": reset_run,
    }


def _num_traces() -> int:
    """Traces of the tracker's step so far (0 when it is no longer wrapped in `assert_max_traces`)."""
    import equinox as eqx

    from jaxtrack.track import track_step

    try:
        return eqx.debug.get_num_traces(track_step)
    except ValueError:
        return 0


WORKING_SHAPE = "default"  # the tracker's crop working resolution (--working-shape; "default": TrackerConfig's)


def run_jaxtrack(seq, subset: str, reset: bool, out_dir: pathlib.Path) -> dict:
    """track_sequence with the cue subset (all cameras of the sequence), scored on camera 0; counts the
    frames whose step was traced (compiled) and leaves them out of the ms per frame."""
    from jaxtrack.track import evaluate_tracking, track_sequence, write_tracking_results

    traced, last = [], [_num_traces()]

    def on_frame(record):
        now = _num_traces()
        traced.append(now != last[0])
        last[0] = now

    run = track_sequence(seq, cues=tuple(subset.split("+")), reset_on_failure=reset, progress=False, on_frame=on_frame,
                         working_shape=WORKING_SHAPE)
    csv = out_dir / f"jaxtrack_{subset}_{'reset' if reset else 'noreset'}.csv"
    write_tracking_results(run, csv)
    step_s = [t["total_s"] for t, c in zip(run.timings[1:], traced[1:], strict=True) if not c]
    out = scores(evaluate_tracking(csv, seq, camera=0), reset, step_s)
    out["cameras"] = len(run.camera_ids)
    out["compiles"] = int(sum(traced))
    return out


def run_m3t(seq, config: str, reset: bool, out_dir: pathlib.Path) -> dict:
    """M3T on camera 0 (scene 000000), one thread, scored like jaxtrack; ms = median CSV `time`."""
    from jaxtrack.track import evaluate_tracking

    csv = out_dir / f"m3t_{config}_{'reset' if reset else 'noreset'}.csv"
    cmd = [str(M3T_RUN), str(seq.root), "-o", str(csv), "--config", config] + (["--reset-on-failure"] if reset else [])
    proc = subprocess.run(cmd, check=False, capture_output=True, text=True, timeout=1800)
    if proc.returncode != 0 or not csv.is_file():
        raise RuntimeError(f"M3T {config} on {seq.root} failed ({proc.returncode}): {proc.stderr[-2000:]}")
    times = [float(line.rsplit(",", 1)[1]) for line in csv.read_text().splitlines()[1:] if line.strip()]
    out = scores(evaluate_tracking(csv, seq, camera=0), reset, times[1:])
    out["cameras"], out["compiles"] = 1, None
    return out


def _pct(x) -> str:
    return "n/a" if x is None or not np.isfinite(x) else f"{100 * x:.0f} %"


def _num(x, digits=2) -> str:
    return "n/a" if x is None or not np.isfinite(x) else f"{x:.{digits}f}"


def report(args, command, presets, subsets, rows, sizes, load_start, load_end, elapsed_s, m3t_note, skipped, failed) -> str:
    methods = [("jaxtrack", s) for s in subsets] + [("M3T", c) for c in M3T_CONFIGS if any(r[0] == "M3T" and r[1] == c for r in rows)]
    lines = [
        "# Tracking success on the synthetic presets",
        "",
        *report_header(command, load_start, load_end, elapsed_s, setup="float32; OpenCV single-threaded; M3T one thread",
                       note=("ms / frame are host times on a shared machine when the load is above the core count; they "
                             "include nothing of compilation only when the median frame did not compile")),
        "",
        "Sequences: " + "; ".join(f"{p} {w}x{h}, {n} frames, {c} camera(s)" for p, (w, h, n, c) in sizes.items()) + ".",
        "",
        "## 5 cm / 5° success rate with resets (RBOT protocol), camera 0",
        "",
        "| method | cues | " + " | ".join(presets) + " |",
        "|---|---|" + "---:|" * len(presets),
    ]
    by_key = {(r[0], r[1], r[2], r[3]["reset_run"]): r[3] for r in rows}
    for method, cues in methods:
        cells = [_pct(by_key[(method, cues, p, True)]["success"]) if (method, cues, p, True) in by_key
                 else ("not run (time)" if (cues, p) in skipped and method == "jaxtrack" else "-") for p in presets]
        lines.append(f"| {method} | {cues} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "## Per preset and method",
        "",
        ("success / failures / mean errors: run with resets; first failure without resets: "
         + ("from the run without resets (`--without-reset`)" if args.without_reset else
            "the first reset frame of the run with resets (the same computation up to there)")
         + "; 'none' = no failure. ms / frame: median host time per frame (jaxtrack: `Tracker.step` incl. SIFT on the "
         "host, frames that compiled the step left out; M3T: its CSV `time`). compiles: frames whose step was traced "
         "and compiled (first frame, new crop size classes, raster re-plans)."),
        "",
        "| preset | method | cues | cameras | frames | success (resets) | failures | first failure (no reset) "
        + ("| success without resets " if args.without_reset else "")
        + "| mean rot ° | mean trans mm | ms / frame | compiles |",
        "|---|---|---|---:|---:|---:|---:|---:|" + ("---:|" if args.without_reset else "") + "---:|---:|---:|---:|",
    ]
    for p in presets:
        for method, cues in methods:
            r = by_key.get((method, cues, p, True))
            if r is None:
                continue
            nr = by_key.get((method, cues, p, False))
            first = nr["first_failure"] if nr is not None else r["first_failure"]
            extra = f"| {_pct(nr['success']) if nr else 'n/a'} " if args.without_reset else ""
            lines.append(
                f"| {p} | {method} | {cues} | {r['cameras']} | {r['frames']} | {_pct(r['success'])} | {r['failures']} | "
                f"{'none' if first is None else first} {extra}| {_num(r['rot_deg'])} | {_num(r['trans_mm'], 1)} | "
                f"{_num(r['ms'], 1)} | {'-' if r['compiles'] is None else r['compiles']} |"
            )
    notes = [
        "",
        "Notes:",
        (f"- Scale {args.scale}: images {args.scale:g} x 640x480 with the focal length and the per-frame motion in pixels "
         "scaled alike (the same scene and object motion as the preset)."
         + ("" if args.scale == 1 and args.frames is None else " Cut from the presets' full size / length to keep the run "
            "within ~25 minutes on the 2-core machine (every cue subset and preset is a separate compilation).")),
        "- M3T is monocular: on stereo-noise it tracks camera 0 alone while jaxtrack uses both cameras." if "stereo-noise" in presets else "",
        m3t_note,
        (f"- Not run, the time budget (--budget-min {args.budget_min:g}) was spent: "
         + ", ".join(f"{c} on {p}" for c, p in skipped) + ".") if skipped else "",
        ("- Failed: " + "; ".join(failed)) if failed else "",
    ]
    lines += ["", *[n for n in notes if n]]
    return "\n".join(lines) + "\n"


def plot(path, presets, rows) -> None:
    """Grouped bars: success rate with resets per preset, one bar per method (jaxtrack cue subsets, M3T)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    methods = sorted(dict.fromkeys((m, c) for m, c, _, r in rows if r["reset_run"]), key=lambda mc: mc[0] == "M3T")
    width = 0.8 / max(len(methods), 1)
    fig, ax = plt.subplots(figsize=(max(6.0, 1.6 * len(presets)), 3.6))
    for i, (method, cues) in enumerate(methods):
        by_preset = {p: r["success"] for m, c, p, r in rows if (m, c) == (method, cues) and r["reset_run"]}
        xs = [k + (i - (len(methods) - 1) / 2) * width for k, p in enumerate(presets) if p in by_preset]
        ax.bar(xs, [100 * by_preset[p] for p in presets if p in by_preset], width, label=f"{method} {cues}",
               hatch="//" if method == "M3T" else None)
    ax.set_xticks(range(len(presets)), presets, rotation=15, fontsize=8)
    ax.set_ylabel("5 cm / 5° success with resets (%)")
    ax.set_ylim(0, 105)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="smoke run: occluded-box, region, 96x72, 4 frames")
    ap.add_argument("--presets", default=",".join(PRESET_NAMES))
    ap.add_argument("--cues", default=",".join(SUBSETS), help="cue subsets joined with '+', comma-separated")
    ap.add_argument("--frames", type=int, default=None, help="frames per preset (default: the preset's own)")
    ap.add_argument("--working-shape", default=None, help="HxW crop working resolution, or native (default: the tracker's)")
    ap.add_argument("--scale", type=float, default=1.0, help="image scale (1 = 640x480)")
    ap.add_argument("--without-reset", action="store_true", help="also run every configuration without resets")
    ap.add_argument("--no-m3t", action="store_true", help="skip the M3T baseline")
    ap.add_argument("--budget-min", type=float, default=None,
                    help="start no new jaxtrack run after this many minutes (the rest is reported as not run)")
    ap.add_argument("--seq-dir", default=None, help="folder for the rendered sequences (default: a temporary one)")
    ap.add_argument("--out", default=None, help="markdown output (default experiments/results/track_presets.md; --quick: none)")
    ap.add_argument("--plot", default=None, help="bar chart (default experiments/results/track_presets.png; --quick: none)")
    args = ap.parse_args(argv)
    if args.working_shape:
        global WORKING_SHAPE
        from jaxtrack.cli import _working_shape

        WORKING_SHAPE = _working_shape(args.working_shape)
    if args.quick:  # the same sequence and configuration as bench_track.py --quick (one compiled program)
        args.presets, args.cues, args.frames, args.scale = "occluded-box", "region", 4, 0.15
    if args.frames is not None and args.frames < 2:
        raise SystemExit("track_presets: --frames must be ≥ 2")
    presets = tuple(p.strip() for p in args.presets.split(",") if p.strip())
    subsets = parse_subsets(args.cues)
    command = command_line(__file__, argv)

    import jax

    from jaxtrack.io import read_sequence

    clock = start_experiment(cache=False)
    use_m3t = not args.no_m3t and m3t_available()
    m3t_note = "" if use_m3t else (
        "- M3T skipped: " + ("--no-m3t." if args.no_m3t else f"the baseline is not built on this machine ({M3T_BIN} missing)."))
    seq_dir = pathlib.Path(args.seq_dir) if args.seq_dir else pathlib.Path(tempfile.mkdtemp(prefix="track_presets_"))
    work = pathlib.Path(tempfile.mkdtemp(prefix="track_presets_out_"))
    rows, sizes, seqs, skipped, failed = [], {}, {}, [], []
    resets = (True, False) if args.without_reset else (True,)
    try:
        for p in presets:  # every sequence, and M3T on each (seconds), before the long jaxtrack runs
            cfg = preset_config(p, args.scale, args.frames)
            seqs[p] = read_sequence(write_preset(p, cfg, seq_dir))
            sizes[p] = (cfg.width, cfg.height, cfg.frames, cfg.cameras)
            for config in M3T_CONFIGS if use_m3t else ():
                for reset in resets:
                    try:
                        rows.append(("M3T", config, p, run_m3t(seqs[p], config, reset, work)))
                    except (RuntimeError, subprocess.TimeoutExpired) as e:
                        failed.append(f"M3T {config} on {p} ({type(e).__name__}: {str(e).strip()[-300:]})")
        # Subset by subset, so that a spent time budget drops whole subsets rather than presets.
        for subset in subsets:
            for p in presets:
                if clock.over(args.budget_min):
                    skipped.append((subset, p))
                    continue
                for reset in resets:
                    t = time.perf_counter()
                    try:
                        r = run_jaxtrack(seqs[p], subset, reset, work)
                    except Exception as e:  # noqa: BLE001 - a crash of one run is reported, the others go on
                        failed.append(f"{subset} on {p} ({type(e).__name__}: {str(e).strip()[:300]})")
                        print(f"[track_presets] failed: {failed[-1]}", file=sys.stderr, flush=True)
                        continue
                    rows.append(("jaxtrack", subset, p, r))
                    print(f"[track_presets] {p} {subset} reset={reset}: {_pct(r['success'])}, first failure {r['first_failure']}, "
                          f"{r['compiles']} compiles ({time.perf_counter() - t:.0f} s, {clock.minutes():.1f} min)",
                          file=sys.stderr, flush=True)
                if len(presets) > 1:
                    jax.clear_caches()  # programs of this preset and subset (mesh, raster plan, crops) are not used again
        text = report(args, command, presets, subsets, rows, sizes, clock.load_start, os.getloadavg(), clock.elapsed_s(),
                      m3t_note, skipped, failed)
    finally:
        shutil.rmtree(work, ignore_errors=True)
        if not args.seq_dir:
            shutil.rmtree(seq_dir, ignore_errors=True)
    print(text)
    save_text(output_path(args.out, RESULTS / "track_presets.md", args.quick), text)
    figure = output_path(args.plot, RESULTS / "track_presets.png", args.quick)
    if figure is not None and rows:
        plot(figure, presets, rows)
    return rows


if __name__ == "__main__":
    main()
