"""How long a new mesh's sparse view model takes to build (`build_view_model`, 2562 views), variants side by side.

    python experiments/view_model_build.py --meshes box,teapot,dragon --variant "before=/tmp/before" --variant "now="
    python experiments/view_model_build.py --meshes box --rounds 1 --out /tmp/v.md   # one variant, as installed

Each build runs in a fresh process with no compile cache (what a new mesh costs on a new machine: the build's
compile included), the variants in turn within each round so that the machine's drift falls on all of them alike.
A variant is `LABEL=PYTHONPATH` as in `warm_start_ab.py` (an empty path: the environment as installed). Meshes:
`box` (the demo's 100x60x40 mm box, 12 faces) or a name from `MESHES` or a mesh file path. With two or more variants
the models of the last round are compared array by array (`identical` in the table: every field equal).
"""

from __future__ import annotations

import argparse
import os
import pathlib
import statistics
import subprocess
import sys
import tempfile

from warm_start_ab import parse_variant, variant_env

from jaxtrack.bench import command_line, report_header, save_text, start_experiment

RESULTS = pathlib.Path(__file__).resolve().parent / "results"
DATA = pathlib.Path(os.environ.get("JAXTRACK_SHARED", pathlib.Path(__file__).resolve().parents[2] / "shared")) / "data"
MESHES = {
    "cube": DATA / "sequences/visp_rbt/models/obj_000001.ply",
    "dragon": DATA / "sequences/visp_rbt/models/obj_000002.ply",
    "teabox": DATA / "sequences/visp_teabox/models/obj_000001.ply",
    "teapot": DATA / "meshes/utah_teapot_solid.stl",
    "cracker_box": DATA / "meshes/ycb_003_cracker_box/cracker_box.obj",
    "milk_truck": DATA / "meshes/CesiumMilkTruck.glb",
}

WORKER = """
import sys, time
import numpy as np
from jaxtrack.cues.lines import build_view_model
from jaxtrack.io import load_mesh
from jaxtrack.render import box_mesh
mesh = box_mesh((100.0, 60.0, 40.0)) if sys.argv[1] == "box" else load_mesh(sys.argv[1])
start = time.perf_counter()
model = build_view_model(mesh)
print("seconds", time.perf_counter() - start, int(mesh.faces.shape[0]))
np.savez(sys.argv[2], **{k: np.asarray(v) for k, v in vars(model).items()})
"""


def mesh_path(name: str) -> str:
    if name == "box":
        return "box"
    path = MESHES.get(name, pathlib.Path(name))
    if not pathlib.Path(path).is_file():
        raise SystemExit(f"view_model_build: --meshes: {name!r} is neither box, one of {sorted(MESHES)} nor a file")
    return str(path)


def build_once(path: str, variant_path: str, out: pathlib.Path) -> tuple[float, int]:
    env = dict(os.environ, **variant_env(variant_path))
    env.pop("JAX_COMPILATION_CACHE_DIR", None)  # build_view_model compiles with plain jax.jit: no cache unless set
    done = subprocess.run([sys.executable, "-c", WORKER, path, str(out)], env=env, capture_output=True, text=True,
                          check=False)
    if done.returncode != 0:
        raise SystemExit(f"view_model_build: the build of {path} failed:\n{done.stderr[-2000:]}")
    line = [w for w in done.stdout.splitlines() if w.startswith("seconds ")][-1].split()
    return float(line[1]), int(line[2])


def identical(a: pathlib.Path, b: pathlib.Path) -> bool:
    import numpy as np

    with np.load(a) as x, np.load(b) as y:
        return set(x) == set(y) and all(np.array_equal(x[k], y[k]) for k in x)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--meshes", default="box,teapot,dragon", help="comma-separated: box, a name of MESHES, or a path")
    ap.add_argument("--variant", action="append", default=None, help="LABEL=PYTHONPATH (repeat; default: as installed)")
    ap.add_argument("--rounds", type=int, default=1, help="builds per variant and mesh")
    ap.add_argument("--out", default=str(RESULTS / "view_model_build.md"))
    args = ap.parse_args(argv)
    if args.rounds < 1:
        raise SystemExit("view_model_build: --rounds must be at least 1")
    variants = [parse_variant(v) for v in args.variant] if args.variant else [("as installed", "")]
    meshes = [(name, mesh_path(name)) for name in args.meshes.split(",") if name]
    command = command_line(__file__, argv)
    clock = start_experiment(cache=False, compile_tiers=True)
    seconds = {}
    faces, same = {}, {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, path in meshes:
            for r in range(args.rounds):
                for i, (label, vpath) in enumerate(variants):
                    s, faces[name] = build_once(path, vpath, pathlib.Path(tmp) / f"{name}_{i}.npz")
                    seconds.setdefault((name, label), []).append(s)
                    print(f"{name}, {label}, round {r + 1}: {s:.2f} s", flush=True)
            if len(variants) > 1:
                same[name] = all(identical(pathlib.Path(tmp) / f"{name}_0.npz", pathlib.Path(tmp) / f"{name}_{i}.npz")
                                 for i in range(1, len(variants)))
    lines = ["# A new mesh's view model: build time (2562 views, 200 points, 256 px)", "",
             *report_header(command, clock.load_start, os.getloadavg(), clock.elapsed_s()), "",
             "Each build in a fresh process without a compile cache (its compile included); rounds alternate the variants.",
             "", "| mesh | faces | " + " | ".join(f"{label} (s), median [rounds]" for label, _ in variants)
             + (" | identical models |" if len(variants) > 1 else " |"),
             "|---|---:|" + "---:|" * len(variants) + ("---|" if len(variants) > 1 else "")]
    for name, _ in meshes:
        cells = [f"{statistics.median(seconds[name, label]):.2f} [{', '.join(f'{x:.1f}' for x in seconds[name, label])}]"
                 for label, _ in variants]
        lines.append(f"| {name} | {faces[name]} | " + " | ".join(cells)
                     + (f" | {'yes' if same[name] else 'no'} |" if len(variants) > 1 else " |"))
    text = "\n".join(lines) + "\n"
    print(text)
    save_text(args.out, text)


if __name__ == "__main__":
    main()
