"""The `jaxtrack` command line."""

from __future__ import annotations

import argparse
import sys

import numpy as np


def _cmd_demo(args) -> int:
    """Track a built-in synthetic articulated scene frame to frame with the pose solver."""
    import jax
    import jax.numpy as jnp
    from tqdm import tqdm

    import jaxtrack as jt
    from jaxtrack.geometry import rotation_error_deg, se3_exp
    from jaxtrack.synth import demo_chain, random_pose_scene

    model = demo_chain(args.joints, branches=args.branches, dtype=jnp.float32) if args.joints else jt.rigid_model()
    solve = jax.jit(lambda c, T, th: jt.solve_pose(model, c, T, th))
    # A smooth trajectory: every frame the root turns by ~3 deg and moves ~5 mm, the joints bend.
    base = random_pose_scene(args.seed, num_points=args.points, num_cameras=args.cameras, model=model, dtype=np.float32)
    T_prev, theta_prev = jnp.asarray(base.T_world_root, jnp.float32), jnp.asarray(base.theta, jnp.float32)
    step = np.array([4.0, -3.0, 2.0, 0.05, 0.03, -0.04], np.float32)
    rows = []
    for frame in tqdm(range(args.frames), desc="frames", disable=args.quiet):
        T_true = np.asarray(se3_exp(jnp.asarray(step * (frame + 1))), np.float64) @ base.T_world_root
        theta_true = base.theta + 0.3 * np.sin(0.2 * (frame + 1) + np.arange(model.num_joints))
        scene = jt.synth.project_model_points(base, T_true, theta_true, noise_px=args.noise, seed=args.seed + frame)
        corr = jt.make_correspondences(
            scene.cameras, scene.pixel, scene.p_model, camera_index=scene.camera_index, part=scene.part, capacity=args.points
        )
        sol = solve(corr, T_prev, theta_prev)
        R_est = np.asarray(sol.T_world_root[:3, :3], np.float64)
        rows.append(
            (
                float(rotation_error_deg(R_est, T_true[:3, :3])),
                float(np.linalg.norm(np.asarray(sol.T_world_root[:3, 3], np.float64) - T_true[:3, 3])),
                np.degrees(np.abs(np.asarray(sol.theta) - theta_true)).max(initial=0.0),
                jt.PoseStatus(int(sol.status)).name,
            )
        )
        T_prev, theta_prev = sol.T_world_root, sol.theta
    rot = np.array([r[0] for r in rows])
    trans = np.array([r[1] for r in rows])
    joint = np.array([r[2] for r in rows])
    ok = sum(r[3] == "OK" for r in rows)
    print(
        f"jaxtrack demo: {model.num_parts} part(s), {model.num_joints} joint(s), {args.cameras} camera(s), "
        f"{args.points} correspondences/frame, {args.noise} px noise, {args.frames} frames"
    )
    print("| error | mean | max |\n|---|---:|---:|")
    print(f"| root rotation (deg) | {rot.mean():.4f} | {rot.max():.4f} |")
    print(f"| root translation (mm) | {trans.mean():.3f} | {trans.max():.3f} |")
    if model.num_joints:
        print(f"| joint angle (deg) | {joint.mean():.4f} | {joint.max():.4f} |")
    print(f"solver status OK on {ok}/{len(rows)} frames")
    return 0 if ok == len(rows) else 1


def _cmd_synth(args) -> int:
    """Write a synthetic BOP-layout sequence with exact ground truth."""
    import dataclasses

    from tqdm import tqdm

    from jaxtrack.io import prepare_output_folder
    from jaxtrack.synth import PRESETS, SynthConfig, write_sequence

    if args.list:
        for name, cfg in PRESETS.items():
            print(f"{name:22s} {cfg.object}, {cfg.appearance}, {cfg.motion} motion, {cfg.frames} frames, "
                  f"{cfg.cameras} camera(s), noise σ={cfg.noise_sigma}, occluders={cfg.occluders}")
        return 0
    if args.out is None:
        raise ValueError("an output folder is required (or --list)")
    if args.preset and args.preset not in PRESETS:
        raise ValueError(f"unknown preset {args.preset!r}; `jaxtrack synth --list` shows them")
    cfg = PRESETS[args.preset] if args.preset else SynthConfig()
    overrides = {k: getattr(args, k) for k in ("object", "appearance", "background", "motion", "pose_file", "frames",
                                               "noise_sigma", "salt_fraction", "occluders", "cameras", "subsample", "seed")
                 if getattr(args, k) is not None}
    cfg = dataclasses.replace(cfg, **overrides)  # SynthConfig validates every field
    prepare_output_folder(args.out, "output folder")  # before rendering: a file in the way fails now
    with tqdm(total=cfg.frames * cfg.cameras, desc="rendering", disable=args.quiet) as bar:
        root = write_sequence(cfg, args.out, progress=bar)
    print(f"wrote {cfg.frames} frames x {cfg.cameras} camera(s) to {root}")
    return 0


def enable_compilation_cache(path: str | None = None) -> str:
    """Keep compiled XLA programs on disk so a second run with the same frame size skips compiling.

    The directory is `path`, else $JAXTRACK_CACHE_DIR, else ~/.cache/jaxtrack/xla.
    """
    import os

    import jax

    path = path or os.environ.get("JAXTRACK_CACHE_DIR") or os.path.join(os.path.expanduser("~"), ".cache", "jaxtrack", "xla")
    os.makedirs(path, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
    return path


def _cmd_flow(args) -> int:
    """Dense variational flow between two frames, written as Middlebury .flo (+ colour-wheel PNG).

    Everything the user gave is checked before the (long) solve: parameter ranges (argparse), output
    paths (parent folders created; a folder, or an extension with no writer, refused), inputs readable
    and of one size.
    """
    import time

    import jax.numpy as jnp

    from jaxtrack.cues.flow import FlowConfig, FlowEnergyParams, compute_flow
    from jaxtrack.io import (
        flow_errors,
        flow_to_colour,
        prepare_image_output,
        prepare_output_file,
        read_flo,
        read_image,
        write_flo,
        write_image,
    )

    params = FlowEnergyParams(
        jnp.asarray(args.alpha), jnp.asarray(args.gamma), jnp.asarray(args.epsilon), not args.quadratic
    )
    config = FlowConfig(
        eta=args.eta, warps=args.warps, lagged=args.lagged, sor_iters=args.sor, presmooth_sigma=args.sigma, median=args.median,
        median_every_warp=args.median_every_warp,
    )
    out = prepare_output_file(args.out, "-o/--out", suffixes=(".flo",))
    viz = prepare_image_output(args.viz, "--viz") if args.viz else None
    mode = "grey" if args.grey else "native"  # colour frames keep all channels: the data term sums over them
    img1, img2 = read_image(args.frame1, mode), read_image(args.frame2, mode)
    if img1.shape != img2.shape:
        raise ValueError(f"frames differ in size: {args.frame1} is {img1.shape}, {args.frame2} is {img2.shape}")
    region = None
    if args.region:
        mask = read_image(args.region, "grey")
        if mask.shape != img1.shape[:2]:
            raise ValueError(f"--region: {args.region} is {mask.shape[1]}x{mask.shape[0]}, the frames are {img1.shape[1]}x{img1.shape[0]}")
        region = mask > 0
        if not region.any():
            raise ValueError(f"--region: {args.region} has no non-zero pixel; there is nothing to compute flow for")
    gt = None
    if args.gt:
        gt = read_flo(args.gt)
        if gt.shape[:2] != img1.shape[:2]:
            raise ValueError(f"--gt: {args.gt} is {gt.shape[1]}x{gt.shape[0]}, the frames are {img1.shape[1]}x{img1.shape[0]}")
    if not args.no_cache:
        enable_compilation_cache()
    t0 = time.perf_counter()
    res = compute_flow(img1, img2, params, config, region=region)
    flow = np.asarray(res.flow)
    t1 = time.perf_counter()
    write_flo(out, flow)
    h, w = flow.shape[:2]
    print(f"flow {w}x{h}: {t1 - t0:.2f} s (including compilation on the first run of a frame size) -> {out}")
    if viz is not None:
        write_image(viz, flow_to_colour(flow), "--viz")
        print(f"colour-wheel visualisation -> {viz}")
    if gt is not None:
        err = flow_errors(flow, gt)
        print(f"against {args.gt}: EPE {err['epe']:.3f} px, AAE {err['aae']:.2f} deg over {err['pixels']} pixels")
    return 0


def _number(kind, low=None, high=None, low_open=False):
    """An argparse type: `kind` (int/float) in [low, high] (low excluded if low_open), finite."""

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {'an integer' if kind is int else 'a number'}, got {text!r}") from None
        if kind is float and not np.isfinite(value):
            raise argparse.ArgumentTypeError(f"must be finite, got {text}")
        if low is not None and (value <= low if low_open else value < low) or high is not None and value > high:
            lo = "" if low is None else f"{'>' if low_open else '≥'} {low:g}"
            hi = "" if high is None else f"≤ {high:g}"
            raise argparse.ArgumentTypeError(f"must be {' and '.join(x for x in (lo, hi) if x)}, got {text}")
        return value

    parse.__name__ = kind.__name__  # argparse names the type in its messages
    return parse


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="jaxtrack",
        description="Differentiable region- and motion-based 3D tracking of rigid and articulated objects (JAX).",
    )
    parser.add_argument("--version", action="version", version=f"jaxtrack {__import__('jaxtrack').__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    demo = sub.add_parser(
        "demo",
        help="track a built-in synthetic scene (no files needed) and print the pose errors",
        description="Track a built-in synthetic articulated object frame to frame: each frame, noisy 2D-3D "
        "correspondences are solved for the pose (6 DoF + joint angles) starting from the previous frame's "
        "pose, and the errors against the exact ground truth are printed.",
    )
    demo.add_argument("--frames", type=_number(int, 1), default=60, help="number of frames (default 60)")
    demo.add_argument("--joints", type=_number(int, 0), default=3, help="joints of the built-in chain; 0 = rigid (default 3)")
    demo.add_argument("--branches", type=int, default=1, choices=(1, 2), help="1 = an arm, 2 = a torso with two arms")
    demo.add_argument("--cameras", type=_number(int, 1), default=2, help="cameras around the object (default 2)")
    demo.add_argument("--points", type=_number(int, 1), default=200, help="correspondences per frame (default 200)")
    demo.add_argument("--noise", type=_number(float, 0), default=1.0, help="pixel noise σ in px (default 1.0)")
    demo.add_argument("--seed", type=_number(int, 0), default=0, help="random seed (default 0)")
    demo.add_argument("--quiet", action="store_true", help="no progress bar")
    demo.set_defaults(func=_cmd_demo)

    synth = sub.add_parser(
        "synth",
        help="write a synthetic sequence with exact ground truth (BOP layout)",
        description="Render a synthetic tracking sequence with an independent ray caster (embree) and write it "
        "in the BOP scene layout with exact ground-truth poses and occluder masks. Start from a preset "
        "(`--list` shows them) and override any field.",
    )
    synth.add_argument("out", nargs="?", type=str, help="output folder (created if missing)")
    synth.add_argument("--preset", help="a named scenario (see --list)")
    synth.add_argument("--list", action="store_true", help="list the presets and exit")
    synth.add_argument("--object", help="box | teapot | cracker_box | milk_truck | a mesh file")
    synth.add_argument("--appearance", choices=("texture", "photo", "flat"))
    synth.add_argument("--background", help="a scikit-image photo (coffee, astronaut, brick, ...) or flat")
    synth.add_argument("--motion", choices=("turntable", "random", "camera", "file"))
    synth.add_argument("--pose-file", dest="pose_file", help=".npy of (N, 4, 4) object poses for --motion file")
    synth.add_argument("--frames", type=_number(int, 1))
    synth.add_argument("--noise-sigma", dest="noise_sigma", type=_number(float, 0), help="Gaussian noise σ on 0-255")
    synth.add_argument("--salt-fraction", dest="salt_fraction", type=_number(float, 0, 1), help="fraction of uniform random pixels")
    synth.add_argument("--occluders", type=_number(int, 0), help="moving occluders crossing the object")
    synth.add_argument("--cameras", type=_number(int, 1, 4), help="cameras on a ring (1-4)")
    synth.add_argument("--subsample", type=_number(int, 1), help="keep every k-th frame of a k-times finer motion")
    synth.add_argument("--seed", type=_number(int, 0))
    synth.add_argument("--quiet", action="store_true", help="no progress bar")
    synth.set_defaults(func=_cmd_synth)

    from jaxtrack.cues.flow import middlebury_config, middlebury_params

    defaults, cfg = middlebury_params(), middlebury_config()
    flow = sub.add_parser(
        "flow",
        help="dense variational optical flow between two frames (Brox et al. 2004), .flo output",
        description="Compute the flow from FRAME1 to FRAME2 by minimising the energy of Brox et al. (2004): "
        "grey-value + gradient constancy with a robust penalty, robust (or quadratic) smoothness, coarse-to-fine "
        "warping. Writes Middlebury .flo; optionally a colour-wheel PNG and the error against a ground truth. "
        "Colour frames use all channels (or --grey). Compiled programs are cached on disk "
        "(~/.cache/jaxtrack/xla or $JAXTRACK_CACHE_DIR), so the first run of a frame size is the slow one.",
    )
    flow.add_argument("frame1", help="first frame (any format OpenCV reads)")
    flow.add_argument("frame2", help="second frame, same size")
    flow.add_argument("-o", "--out", required=True, help="output .flo file (missing folders are created)")
    flow.add_argument("--viz", help="write the colour-wheel visualisation to this image (.png, .jpg, ...)")
    flow.add_argument("--gt", help="ground-truth .flo: print EPE and AAE")
    flow.add_argument("--region", help="mask image: compute the flow inside its non-zero pixels only (Ω1)")
    flow.add_argument("--alpha", type=_number(float, 0), default=float(defaults.alpha), help=f"smoothness weight α (default {float(defaults.alpha):g})")
    flow.add_argument("--gamma", type=_number(float, 0), default=float(defaults.gamma), help=f"gradient-constancy weight γ (default {float(defaults.gamma):g})")
    flow.add_argument("--epsilon", type=_number(float, 0, low_open=True), default=1e-3, help="ε of the robust penalty (default 0.001)")
    flow.add_argument("--quadratic", action="store_true", help="quadratic smoothness (the paper's rigid setting uses α = 800)")
    flow.add_argument("--eta", type=_number(float, 0, 1, low_open=True), default=cfg.eta, help=f"pyramid factor η (default {cfg.eta})")
    flow.add_argument("--warps", type=_number(int, 1), default=cfg.warps, help=f"warps per level (default {cfg.warps})")
    flow.add_argument("--lagged", type=_number(int, 1), default=cfg.lagged, help=f"lagged-nonlinearity iterations per warp (default {cfg.lagged})")
    flow.add_argument("--sor", type=_number(int, 1), default=cfg.sor_iters, help=f"SOR sweeps per lagged iteration (default {cfg.sor_iters})")
    flow.add_argument("--median", type=int, default=cfg.median, choices=(0, 3, 5), help=f"median filter side, 0 = off (default {cfg.median})")
    flow.add_argument("--median-every-warp", dest="median_every_warp", action=argparse.BooleanOptionalAction,
                      default=cfg.median_every_warp, help="median after every warp instead of after every pyramid level")
    flow.add_argument("--sigma", type=_number(float, 0), default=cfg.presmooth_sigma, help=f"pre-smoothing σ in px (default {cfg.presmooth_sigma})")
    flow.add_argument("--grey", action="store_true", help="convert colour frames to grey first")
    flow.add_argument("--no-cache", action="store_true", help="do not use the on-disk compilation cache")
    flow.set_defaults(func=_cmd_flow)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the exit status (0 ok, 1 a solve that did not succeed, 2 a user error).

    A user mistake (a bad value, a missing or unreadable file, an output path that cannot be written)
    is printed as `jaxtrack COMMAND: error: MESSAGE` naming the argument or file, not as a traceback.
    """
    from jaxtrack._status import StatusError

    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return args.func(args)
    except (ValueError, OSError) as e:  # every input check in jaxtrack raises these, naming what is wrong
        print(f"jaxtrack {args.command}: error: {e}", file=sys.stderr)
        return 2
    except StatusError as e:  # the computation ran but reported a failure status
        print(f"jaxtrack {args.command}: {e}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
