"""Warm (or cold) first frame, alternatives side by side: `bench_track`'s worker in fresh processes, variants alternated.

    python experiments/warm_start_ab.py --variant "ml_dtypes 0.7.0=/tmp/mld070" --variant "as installed=" \\
        --cameras 1,4 --rounds 4 --out experiments/results/warm_start_ml_dtypes.md
    python experiments/warm_start_ab.py --cold --variant "before=/tmp/before" --variant "after=" --cameras 1 --rounds 3

A variant is `LABEL=PYTHONPATH`: its processes run with that PYTHONPATH put first (another checkout of the
repository, e.g. a `git worktree` of an older commit, or a folder a package was installed into with
`pip install --target DIR --no-deps PKG==VER`); an empty path runs the environment as installed. Each variant and
camera count gets its own on-disk compile cache, filled by one cold process first (the step compiled, the view
models and the mesh cache written); then each round runs one warm process per variant and camera count, the
variants in turn, so that the machine's drift over the run falls on all of them alike. With `--cold` every round's
process starts from empty caches instead (compile cache, exported programs, view models, mesh cache: what a new
machine has), and no fill runs first.

Measured per process, from its launch (bench_track's 'first frame, warm cache'): imports (until the worker's
imports are done), `Tracker.start`, the first `Tracker.step` and the first frame ready (all of it). Setting:
bench_track's textured box, 640x480, all cues, `--frames` frames. The table also names what each variant
actually imported (jaxtrack's folder, ml_dtypes' version, whether trimesh was loaded), so that a PYTHONPATH
that did not take is seen.
"""

from __future__ import annotations

import argparse
import os
import pathlib
import shutil
import sys
import tempfile

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from bench_track import run_worker, write_bench_sequence

from jaxtrack.bench import command_line, report_header, save_text, start_experiment

RESULTS = pathlib.Path(__file__).resolve().parent / "results"


def parse_variant(text: str) -> tuple[str, str]:
    """'LABEL=PYTHONPATH' → (label, path); the path may be empty, the label may not; errors name the argument."""
    label, sep, path = text.partition("=")
    if not sep or not label.strip():
        raise SystemExit(f"warm_start_ab: --variant {text!r} must be LABEL=PYTHONPATH (the path may be empty)")
    if path and not all(pathlib.Path(p).exists() for p in path.split(os.pathsep)):
        raise SystemExit(f"warm_start_ab: --variant {text!r}: a folder of its PYTHONPATH does not exist")
    return label.strip(), path


def variant_env(path: str) -> dict:
    """The environment additions of a variant's processes: its PYTHONPATH first, then this process's."""
    if not path:
        return {}
    return {"PYTHONPATH": os.pathsep.join(p for p in (path, os.environ.get("PYTHONPATH", "")) if p)}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--variant", action="append", required=True, help="LABEL=PYTHONPATH (repeat; an empty path: as installed)")
    ap.add_argument("--cameras", default="1,4", help="camera counts, comma-separated (1..4)")
    ap.add_argument("--cues", default="all", choices=("all", "region"))
    ap.add_argument("--rounds", type=int, default=4, help="warm processes per variant and camera count")
    ap.add_argument("--cold", action="store_true", help="every round from empty caches (no fill first)")
    ap.add_argument("--frames", type=int, default=3, help="frames of the sequence (the warm process tracks one)")
    ap.add_argument("--timeout", type=float, default=1200, help="seconds per process")
    ap.add_argument("--title", default=None, help="the report's title (default: Warm or Cold first frame: ...)")
    ap.add_argument("--out", default=str(RESULTS / "warm_start_ab.md"), help="markdown output")
    args = ap.parse_args(argv)
    variants = [parse_variant(v) for v in args.variant]
    if len({label for label, _ in variants}) != len(variants):
        raise SystemExit("warm_start_ab: --variant labels must differ")
    try:
        cameras = [int(c) for c in args.cameras.split(",")]
        assert cameras and all(1 <= c <= 4 for c in cameras)
    except (ValueError, AssertionError):
        raise SystemExit(f"warm_start_ab: --cameras must be counts in 1..4, comma-separated, got {args.cameras!r}") from None
    if args.rounds < 1 or args.frames < 3:
        raise SystemExit("warm_start_ab: --rounds must be ≥ 1 and --frames ≥ 3")
    command = command_line(__file__, argv)
    clock = start_experiment(cache=False, compile_tiers=True)
    work = pathlib.Path(tempfile.mkdtemp(prefix="warm_start_ab_"))
    try:
        seq, _ = write_bench_sequence(work / "seq", max(cameras), args.frames, 1.0)
        base = {"sequence": str(seq), "cues": args.cues, "repeats": 1, "breakdown": False, "region": None, "working_shape": None}

        def run(i, label, path, cams, mode):
            # Each variant's own view-model and mesh caches as well as its compile cache: nothing filled by another.
            cache = work / f"cache_{i}_{cams}"
            if args.cold:  # what a new machine has: nothing
                shutil.rmtree(cache, ignore_errors=True)
            env = dict(variant_env(path), JAXTRACK_CACHE=str(cache / "views"), JAXTRACK_MESH_CACHE=str(cache / "meshes"))
            out = run_worker(dict(base, cameras=cams, cache_dir=str(cache / "xla"), mode=mode), args.timeout, env)
            print(f"[warm_start_ab] {label} {cams} cam {mode}: first frame {out['ready_s']:.2f} s "
                  f"(imports {out['imported_s']:.2f}, start {out['start_s']:.2f}, step {out['first_step_s']:.2f})",
                  file=sys.stderr, flush=True)
            return out

        keys = [(label, c) for c in cameras for label, _ in variants]
        cold = {} if args.cold else {(label, c): run(i, label, path, c, "cold") for c in cameras
                                     for i, (label, path) in enumerate(variants)}
        warm = {key: [] for key in keys}  # the rounds (cold ones with --cold)
        for _ in range(args.rounds):
            for c in cameras:
                for i, (label, path) in enumerate(variants):
                    warm[(label, c)].append(run(i, label, path, c, "cold" if args.cold else "warm"))
    finally:
        shutil.rmtree(work, ignore_errors=True)
    text = report(args, command, variants, cameras, cold, warm, clock)
    print(text)
    save_text(args.out, text)
    return cold, warm


def report(args, command, variants, cameras, cold, warm, clock) -> str:
    med = lambda runs, key: float(np.median([r[key] for r in runs]))
    title = args.title or f"{'Cold' if args.cold else 'Warm'} first frame: alternatives alternated"
    lines = [f"# {title}", "", *report_header(command, clock.load_start, os.getloadavg(), clock.elapsed_s()), "",
             (f"bench_track's textured box, 640x480, cues {args.cues}; each process fresh, launched by this script; each variant "
              + ("with empty compile, exported-program, view-model and mesh caches in every round (`--cold`)"
                 if args.cold else "with its own compile, view-model and mesh caches filled by its cold process")
              + "; rounds alternate the variants."),
             "", (f"| variant | cameras | first frame, {'cold' if args.cold else 'warm'} (s), rounds | median | imports (s), median | start (s), median | "
             "first step (s), median | ml_dtypes | trimesh imported | jaxtrack from |"),
             "|---|---:|---|---:|---:|---:|---:|---|---|---|"]
    for c in cameras:
        for label, _ in variants:
            runs = warm[(label, c)]
            rounds = ", ".join(f"{r['ready_s']:.2f}" for r in runs)
            lines.append(f"| {label} | {c} | {rounds} | {med(runs, 'ready_s'):.2f} | "
                         f"{med(runs, 'imported_s'):.2f} | {med(runs, 'start_s'):.2f} | {med(runs, 'first_step_s'):.2f} | "
                         f"{runs[0].get('ml_dtypes', '?')} | {runs[0].get('trimesh_imported', '?')} | `{runs[0].get('jaxtrack_from', '?')}` |")
    if len(variants) > 1:
        ref = variants[0][0]
        lines += ["", f"Paired ratios of the first frame against `{ref}`, per round:"]
        for c in cameras:
            for label, _ in variants[1:]:
                ratios = [round(b["ready_s"] / a["ready_s"], 2) for a, b in zip(warm[(ref, c)], warm[(label, c)])]
                lines.append(f"- {label}, {c} camera{'s' if c > 1 else ''}: {ratios}")
    if cold:
        lines += ["", "Cold fills (s; first frame / imports / start / first step): " + "; ".join(
            f"{label} {c} cam {r['ready_s']:.1f} / {r['imported_s']:.2f} / {r['start_s']:.2f} / {r['first_step_s']:.2f}"
            for (label, c), r in cold.items()) + "."]
    lines.append("")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
