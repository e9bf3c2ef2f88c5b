"""Region-cue speed: ms per level-set iteration, per density update, per refinement round (with a
breakdown) and per full region-only refinement of one frame, plus the compile time.

Setting: one camera, 640x480, the flat-coloured synthetic teapot about 200 px wide on the coffee
photo (`jaxtrack.synth`), float32, the default `RegionConfig` (10 level-set iterations per round,
re-distancing every 5, densities on a factor-4 grid, up to 30 rounds, 5 Gauss-Newton steps per
round), started from the true pose perturbed by θ = 10 of the Fig. 6 twist. Times are medians of
5 calls after a warm-up call (compile excluded); the compile time is the first call minus a later one.

    python experiments/bench_region.py
"""

from __future__ import annotations

import pathlib
import platform
import time

import cv2
import jax
import jax.numpy as jnp
import numpy as np

from jaxtrack.cues.levelset import (
    RegionConfig,
    RegionRefiner,
    band_sdf,
    data_term,
    evolve,
    feature_channels,
    local_densities,
    region_membership,
    region_params,
)
from jaxtrack.geometry import crop_camera, make_camera, rigid_model, se3_exp
from jaxtrack.render import make_mesh, render
from jaxtrack.solve import Cue, SolverConfig, correspondences_from_pixels, solve_pose
from jaxtrack.synth import SynthConfig, render_sequence

RESULTS = pathlib.Path(__file__).resolve().parent / "results"


def timed(fn, repeats=5):
    jax.block_until_ready(fn())
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        ts.append(time.perf_counter() - t)
    return 1000 * float(np.median(ts))


def main():
    cv2.setNumThreads(1)
    cfg = SynthConfig(object="teapot", appearance="flat", colour=(210, 180, 60), background="coffee", frames=1,
                      size_mm=170, focal=700, motion="turntable")
    seq = render_sequence(cfg)
    mesh = make_mesh(seq["mesh"].vertices, seq["mesh"].faces)
    cam = make_camera(seq["K"], cfg.width, cfg.height)
    T_true = seq["T_cam_obj"][0][0]
    img = seq["images"][0][0].astype(np.float32)
    width_px = np.ptp(np.nonzero(seq["object_mask"][0][0])[1]) + 1
    T0 = T_true @ np.asarray(se3_exp(jnp.asarray(0.1 * np.array([10, 10, 10, 0.5, 0.5, 0.5]))))
    config = RegionConfig()
    refiner = RegionRefiner(mesh, cam, config=config)

    t = time.perf_counter()
    res, (offsets, crop) = refiner(img, T0)
    jax.block_until_ready(res.T_world_root)
    first = time.perf_counter() - t
    refiner.reset()
    full = timed(lambda: refiner(img, T0)[0].T_world_root)
    rounds = int(res.iterations)
    compile_s = first - full / 1000

    # Components on the same crop, each jitted on its own.
    (y0, x0), (h, w) = offsets[0], crop
    params = region_params(crop, jnp.float32)
    feats = feature_channels(jnp.asarray(img[y0 : y0 + h, x0 : x0 + w]), texture=config.texture)
    ccam = crop_camera(cam, jnp.asarray(offsets[0]), crop)
    plan = refiner.plan
    T0j = jnp.asarray(T0, jnp.float32)
    theta = jnp.zeros((0,), jnp.float32)
    model = rigid_model()
    f = config.density_factor
    rend = jax.jit(lambda T: render(mesh, ccam, T, theta, model, plan))
    out = rend(T0j)
    sil = out.face_id >= 0
    sdf = jax.jit(lambda s: band_sdf(s))
    phi0 = sdf(sil).astype(jnp.float32)
    dens_fn = jax.jit(lambda p: local_densities(feats, region_membership(p), params.rho, params.kappa, params.sigma_min, f))
    dens = dens_fn(phi0)
    force_fn = jax.jit(lambda d: data_term(feats, d, f))
    force = force_fn(dens)
    ls_fn = jax.jit(lambda p: evolve(p, phi0, force, params, config.levelset_iterations, config.redistance_every))
    step_only = jax.jit(lambda p: evolve(p, phi0, force, params, config.levelset_iterations, config.levelset_iterations))
    phi = ls_fn(phi0)
    from jaxtrack.cues.levelset._refine import contour_matches

    cm = jax.jit(lambda p: contour_matches(phi0, p, sil, out.p_model, out.part_id, params, config.capacity))
    _, target, pm, part, wgt, edge_normal = cm(phi)
    corr = correspondences_from_pixels(cam, target + jnp.asarray([x0, y0], jnp.float32), jnp.zeros_like(part), pm, part, wgt,
                                       undistort=False, cue=Cue.REGION, edge_normal=edge_normal if config.edge_rows else None,
                                       tangent_weight=params.tangent_weight)
    solve = jax.jit(lambda c: solve_pose(model, c, T0j, None, SolverConfig(max_steps=config.solver_steps)))
    # One whole round as the tracker's loop runs it: the modality's `rows` on the round's render.
    from jaxtrack.cues.levelset import LevelSetRegion, initial_state
    from jaxtrack.cues.levelset._modality import _region_context, _RegionOnlyParams
    from jaxtrack.solve import CueWeights

    modality = LevelSetRegion(config)
    from jaxtrack.cues.levelset import RegionProblem

    problem = RegionProblem(mesh, model, jax.tree.map(lambda a: a[None], cam) if cam.K.ndim == 2 else cam, plan, config)
    crops = jnp.asarray(img[None, y0 : y0 + h, x0 : x0 + w])
    offs = jnp.asarray(offsets)
    ctx = _region_context(problem, crops, offs, T0j, theta)
    p_only = _RegionOnlyParams(params, CueWeights())
    state0 = initial_state(1, cfg.height, cfg.width, 3 + int(config.texture), f)
    frame = modality.start(ctx, state0, None, p_only)
    carry = modality.round_start(ctx, state0, frame, p_only)
    from jaxtrack.modality import Pose

    round_fn = jax.jit(lambda c: modality.rows(ctx, state0, frame, c, Pose(T0j, theta), ctx.render_t, jnp.zeros((), jnp.int32),
                                               p_only)[0].weight)
    rows = [
        ("one round through the protocol: `LevelSetRegion.rows` (render excluded)", timed(lambda: round_fn(carry))),
        ("render into the crop", timed(lambda: rend(T0j).depth)),
        ("Φ0 = band_sdf (one band-limited jump flooding)", timed(lambda: sdf(sil))),
        ("density update (eq. 12, factor-4 grid) + data term", timed(lambda: force_fn(dens_fn(phi)))),
        (f"{config.levelset_iterations} level-set iterations incl. re-distancing", timed(lambda: ls_fn(phi0))),
        (f"{config.levelset_iterations} level-set iterations without re-distancing", timed(lambda: step_only(phi0))),
        ("contour correspondences (contour selection + sparse closest-point matching)", timed(lambda: cm(phi)[4])),
        (f"Gauss-Newton ({config.solver_steps} steps, {config.capacity} rows)", timed(lambda: solve(corr).T_world_root)),
    ]
    per_iter = timed(lambda: ls_fn(phi0)) / config.levelset_iterations
    per_density = timed(lambda: force_fn(dens_fn(phi)))
    lines = [
        "# Region-cue speed",
        "",
        "Command: `python experiments/bench_region.py`  ",
        (
            f"Machine: {platform.machine()}, {jax.devices()[0].platform}, JAX {jax.__version__}, float32, one camera, "
            f"{cfg.width}x{cfg.height} frame, teapot {width_px} px wide, crop {h}x{w}, start θ = 10 (Fig. 6 twist)."
        ),
        "",
        "| quantity | value |",
        "|---|---:|",
        f"| full region-only refinement of one frame (ms) | {full:.1f} |",
        f"| rounds run (cap {config.outer_iterations}) | {rounds} |",
        f"| ms per round (full / rounds) | {full / max(rounds, 1):.1f} |",
        f"| ms per level-set iteration (incl. re-distancing every {config.redistance_every}) | {per_iter:.2f} |",
        f"| ms per density update (+ data term) | {per_density:.2f} |",
        f"| compile time of the refinement (s) | {compile_s:.1f} |",
        "",
        "Breakdown of one round (each part jitted alone on the same crop; medians of 5):",
        "",
        "| part | ms |",
        "|---|---:|",
    ] + [f"| {name} | {ms:.2f} |" for name, ms in rows]
    text = "\n".join(lines) + "\n"
    print(text)
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "bench_region.md").write_text(text)


if __name__ == "__main__":
    main()
