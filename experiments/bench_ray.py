"""`jaxtrack bench` on Ray against one process: the time of a whole bench, and whether the tables agree.

A synthetic RBOT-layout dataset (`jaxtrack synth --rbot`: 4 objects x 2 variants = 8 sequences, 320x240) is benched
with the same tracker settings by whole `jaxtrack bench` commands:

    sequential   --workers 0: one process tracks the sequences one after another
    ray N        --workers N: a local Ray instance with N worker processes, one XLA thread each
    cluster      --address: a 2-node Ray cluster on this machine (two `ray start` processes, 2 CPUs each)

Every command runs once to warm the on-disk compilation cache (compiled programs for one and for several XLA threads
are different entries), then `--repeats` times into fresh folders; the median is reported. The poses of every
sequence are compared with the sequential run's, bit for bit.

    python experiments/bench_ray.py                          # 8 sequences x 100 frames, all cues
    python experiments/bench_ray.py --frames 40 --cues region --repeats 1
"""

from __future__ import annotations

import argparse
import os
import pathlib
import re
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np

RESULTS = pathlib.Path(__file__).resolve().parent / "results"
JAXTRACK = [sys.executable, "-m", "jaxtrack.cli"]


def run(cmd: list[str], env: dict | None = None) -> float:
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, check=False, capture_output=True, text=True, env=env)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} exited {proc.returncode}:\n{proc.stderr[-2000:]}")
    return time.perf_counter() - t0


def poses(out: pathlib.Path) -> dict:
    """{csv relative path: the pose columns of its rows}."""
    return {str(p.relative_to(out)): [",".join(line.split(",")[:6]) for line in p.read_text().splitlines()]
            for p in sorted((out / "runs").rglob("*.csv"))}


def tables(out: pathlib.Path) -> str:
    return (out / "bench.md").read_text().split("## Success rate")[1].split("## Per sequence")[0]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--cues", default="region,flow,sift")
    ap.add_argument("--workers", default="2,4", help="comma-separated Ray worker counts")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--no-cluster", action="store_true", help="skip the 2-node cluster")
    ap.add_argument("--out", default=str(RESULTS / "bench_ray.md"))
    args = ap.parse_args()

    work = pathlib.Path(tempfile.mkdtemp(prefix="bench-ray-"))
    env = {**os.environ, "JAXTRACK_CACHE_DIR": str(work / "xla")}  # one cache, shared by every process here
    dataset = work / "RBOT"
    run([*JAXTRACK, "synth", str(dataset), "--rbot", "box,teapot,cracker_box,milk_truck", "--frames", str(args.frames)], env)
    common = ["--cues", args.cues, "--resets", "off", "--quiet"]
    modes = {"sequential (--workers 0)": ["--workers", "0"]}
    modes.update({f"ray, {w} workers": ["--workers", w] for w in args.workers.split(",")})
    times, reference, agree = {}, None, {}
    for name, flags in modes.items():
        run([*JAXTRACK, "bench", str(dataset), "-o", str(work / "warm"), *flags, *common], env)  # warm the cache
        shutil.rmtree(work / "warm")
        times[name] = []
        for r in range(args.repeats):
            out = work / f"{name.split()[0].strip(',')}-{flags[-1]}-{r}"
            times[name].append(run([*JAXTRACK, "bench", str(dataset), "-o", str(out), *flags, *common], env))
            if reference is None:
                reference = out
            agree[name] = (poses(out) == poses(reference), tables(out) == tables(reference))
        print(f"{name}: {', '.join(f'{t:.1f}' for t in times[name])} s", flush=True)
    cluster = None
    if not args.no_cluster:
        ray = shutil.which("ray", path=str(pathlib.Path(sys.executable).parent))
        port = "6391"
        # A cluster on loopback: Ray's token authentication off on every process of it (head, node, driver).
        env = {**env, "RAY_AUTH_MODE": "disabled"}
        try:
            run([ray, "start", "--head", "--num-cpus", "2", "--port", port, "--include-dashboard", "false"], env)
            run([ray, "start", "--address", f"127.0.0.1:{port}", "--num-cpus", "2"], env)
            flags = ["--address", f"127.0.0.1:{port}"]
            run([*JAXTRACK, "bench", str(dataset), "-o", str(work / "warm"), *flags, *common], env)
            shutil.rmtree(work / "warm")
            out = work / "cluster"
            t = run([*JAXTRACK, "bench", str(dataset), "-o", str(out), *flags, *common], env)
            md = (out / "bench.md").read_text()
            found = re.search(r" on ray \((.*?)\);", md)
            nodes = found.group(1) if found else "?"
            cluster = (t, nodes, poses(out) == poses(reference), tables(out) == tables(reference))
            print(f"cluster ({nodes}): {t:.1f} s", flush=True)
        finally:
            subprocess.run([ray, "stop", "--force"], check=False, capture_output=True)
    base = float(np.median(times["sequential (--workers 0)"]))
    lines = ["# jaxtrack bench: Ray workers against one process", "",
             (f"Command: `python experiments/bench_ray.py --frames {args.frames} --cues {args.cues} --workers {args.workers} "
             f"--repeats {args.repeats}`"), "",
             (f"Dataset: `jaxtrack synth --rbot box,teapot,cracker_box,milk_truck --frames {args.frames}` (8 sequences: 4 "
             f"objects x a_regular, c_noisy; 320x240). Bench: `jaxtrack bench DATASET --cues {args.cues} --resets off`; "
             f"whole commands (Python start, Ray start, every sequence, the tables), after one warm-up run of each mode "
             f"(compilation cache warm); machine: {os.cpu_count()} cores."), "",
             "| mode | wall s (each run) | median | ratio to sequential | poses equal to sequential | tables equal |",
             "|---|---|---:|---:|---|---|"]
    for name, ts in times.items():
        med = float(np.median(ts))
        same_poses, same_tables = agree[name]
        lines.append(f"| {name} | {', '.join(f'{t:.1f}' for t in ts)} | {med:.1f} | {med / base:.2f} | "
                     f"{'yes (bit for bit)' if same_poses else 'NO'} | {'yes' if same_tables else 'NO'} |")
    if cluster is not None:
        t, nodes, same_poses, same_tables = cluster
        lines.append(f"| 2-node cluster ({nodes}), --address | {t:.1f} | {t:.1f} | {t / base:.2f} | "
                     f"{'yes (bit for bit)' if same_poses else 'NO'} | {'yes' if same_tables else 'NO'} |")
    else:
        lines.append("| 2-node cluster | not run (--no-cluster) | | | | |")
    text = "\n".join(lines) + "\n"
    pathlib.Path(args.out).write_text(text)
    print(text)
    shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
