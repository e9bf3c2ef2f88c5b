"""Time `Tracker.start` on the tea box in fresh processes: empty on-disk compile cache, then warm.

    python experiments/time_tracker_start.py [--out experiments/results/time_tracker_start.md]

`Tracker.start` (texture atlas, first renders, appearance model, densities at the known pose) runs
before the first step; with the step itself it makes the "first frame ready" time of issue 11.
Each measurement is a new Python process, so nothing is cached in memory; the first uses an empty
temporary compile-cache folder and the second reuses it (as `jaxtrack track` does).
"""

from __future__ import annotations

import argparse
import os
import pathlib
import subprocess
import sys
import tempfile

ROOT = pathlib.Path(__file__).resolve().parents[1]
SEQ = ROOT.parent / "shared" / "data" / "sequences" / "visp_teabox"

WORKER = r"""
import sys, time
t0 = time.perf_counter()
import jax, numpy as np
from jaxtrack import enable_compilation_cache
from jaxtrack.geometry import make_camera, stack_cameras
from jaxtrack.io import load_mesh, read_sequence
from jaxtrack.track import Tracker
enable_compilation_cache(sys.argv[2])
seq = read_sequence(sys.argv[1]); v = seq.views[0]; obj = sorted(seq.model_paths)[0]
rig = stack_cameras([make_camera(v.K, v.width, v.height, v.T_cam_world[:3, :3], v.T_cam_world[:3, 3])])
tracker = Tracker(load_mesh(seq.model_paths[obj]), rig)
t1 = time.perf_counter()
jax.block_until_ready(tracker.start(v.read_frame(0)[None], np.linalg.inv(v.T_cam_world) @ v.T_cam_obj[obj][0]))
print(f"{t1 - t0:.2f} {time.perf_counter() - t1:.2f}")
"""


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(ROOT / "experiments" / "results" / "time_tracker_start.md"))
    ap.add_argument("--sequence", default=str(SEQ))
    args = ap.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as cache:
        for label in ("empty compile cache", "warm compile cache"):
            out = subprocess.run([sys.executable, "-c", WORKER, args.sequence, cache], capture_output=True, text=True,
                                 check=True, env=dict(os.environ, PYTHONWARNINGS="ignore"))
            setup_s, start_s = map(float, out.stdout.split()[-2:])
            rows.append((label, setup_s, start_s))
    load = os.getloadavg()
    lines = [
        "# Tracker.start on the tea box",
        "",
        f"Command: `python experiments/time_tracker_start.py`; 2-core CPU, load average {load[0]:.2f} at the end.",
        "",
        "| process | imports + sequence + Tracker (s) | Tracker.start (s) |",
        "|---|---:|---:|",
        *[f"| {label} | {a:.1f} | {b:.1f} |" for label, a, b in rows],
    ]
    text = "\n".join(lines) + "\n"
    print(text)
    pathlib.Path(args.out).write_text(text)
    return rows


if __name__ == "__main__":
    main()
