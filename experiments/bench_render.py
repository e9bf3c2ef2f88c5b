"""Renderer benchmark: ms per render (depth + face id + surface points + visibility) at 640x480 for
meshes of ~1k / 5k / 20k faces, compile time, and compilations over a 200-frame sequence.

Meshes: icospheres subdivided to the face count (closed, like tracked objects) and the Utah teapot
from ../shared/data/meshes when present. The sequence turns the object 360° about a tilted axis while
it moves 60 mm; the raster plan is made from frame 0 and re-planned on the host only on overflow.
A last row renders a box filling most of a 1280x720 frame from 350 mm: its faces are larger than the
largest patch class (724 px) and go through the tile pool.

    python experiments/bench_render.py [--quick]
"""

from __future__ import annotations

import argparse
import pathlib
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np
import trimesh

import jaxtrack as jt
from jaxtrack.render import Renderer, make_mesh
from jaxtrack.synth import look_at

RESULTS = pathlib.Path(__file__).resolve().parent / "results"
TEAPOT = pathlib.Path(__file__).resolve().parents[1].parent / "shared" / "data" / "meshes" / "utah_teapot_solid.stl"


def meshes():
    out = []
    for subdiv, label in ((3, "icosphere 1.3k"), (4, "icosphere 5k"), (5, "icosphere 20k")):
        s = trimesh.creation.icosphere(subdivisions=subdiv, radius=80.0)
        out.append((label, make_mesh(s.vertices, s.faces)))
    if TEAPOT.is_file():
        tm = trimesh.load(str(TEAPOT))
        tm.apply_translation(-tm.bounding_box.centroid)
        tm.apply_scale(200.0 / tm.extents.max())
        out.append(("teapot 9.4k", make_mesh(tm.vertices, tm.faces)))
    return out


def _box(sx, sy, sz):
    s = trimesh.creation.box((sx, sy, sz))
    return s.vertices, s.faces


def trajectory(frames):
    axis = np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2])
    return [
        jt.se3_exp(jnp.asarray(np.concatenate([[60.0 * k / frames, 0, 0], axis * 2 * np.pi * k / frames]), jnp.float32))
        for k in range(frames)
    ]


def run(frames, repeats):
    R, t = look_at([0.0, -150.0, -450.0])
    cam = jt.make_camera([[600, 0, 319.5], [0, 600, 239.5], [0, 0, 1]], 640, 480, R, t)
    R_hd, t_hd = look_at([60.0, -40.0, -350.0])
    cam_hd = jt.make_camera([[700, 0, 639.5], [0, 700, 359.5], [0, 0, 1]], 1280, 720, R_hd, t_hd)
    cases = [(label, mesh, cam) for label, mesh in meshes()]
    cases.append(("box close-up, 1280x720", make_mesh(*_box(400.0, 300.0, 200.0)), cam_hd))
    rows = []
    for label, mesh, cam in cases:
        poses = trajectory(frames)
        renderer = Renderer(mesh, cam, cull_backfaces=True)  # all benchmark meshes are closed
        t0 = time.perf_counter()
        jax.block_until_ready(renderer(poses[0]).depth)
        compile_s = time.perf_counter() - t0
        times = []
        for T in poses:
            t0 = time.perf_counter()
            jax.block_until_ready(renderer(T).depth)
            times.append(time.perf_counter() - t0)
        # steady-state time at one pose
        T = poses[frames // 3]
        jax.block_until_ready(renderer(T).depth)
        t0 = time.perf_counter()
        for _ in range(repeats):
            out = renderer(T)
        jax.block_until_ready(out.depth)
        ms = 1e3 * (time.perf_counter() - t0) / repeats
        rows.append((label, mesh.num_faces, ms, 1e3 * float(np.median(times)), compile_s, renderer.compilations, renderer.plan))
    return rows


def to_markdown(rows, frames, command):
    lines = [
        "# Renderer benchmark",
        "",
        f"Command: `{command}`  ",
        (f"Machine: {platform.machine()}, JAX {jax.__version__} on {jax.devices()[0].platform}, 640x480 unless noted, float32, "
        "buffers: depth, face id, model points, part id, vertex visibility; back faces culled (closed meshes)."),
        "",
        f"| mesh | faces | ms / render (same pose) | ms / render (median over {frames} frames) | first call incl. compile (s) | compilations over {frames} frames | final plan (patch: capacity) |",
        "|---|---:|---:|---:|---:|---:|---|",
    ]
    for label, faces, ms, med, comp, ncomp, plan in rows:
        plan_s = ", ".join(f"{s}:{c}" for s, c in zip(plan.patch_sizes, plan.capacities))
        if plan.tile_capacity:
            plan_s += f", tiles of {plan.tile_size}: {plan.tile_capacity}"
        lines.append(f"| {label} | {faces} | {ms:.2f} | {med:.2f} | {comp:.2f} | {ncomp} | {plan_s} |")
    return "\n".join(lines) + "\n"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="20 frames; writes bench_render_quick.md")
    args = parser.parse_args(argv)
    frames = 20 if args.quick else 200
    rows = run(frames, repeats=5 if args.quick else 20)
    command = "python experiments/bench_render.py" + (" --quick" if args.quick else "")
    table = to_markdown(rows, frames, command)
    print(table)
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / ("bench_render_quick.md" if args.quick else "bench_render.md")).write_text(table)
    return rows


if __name__ == "__main__":
    main()
