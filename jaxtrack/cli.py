"""The `jaxtrack` command line."""

from __future__ import annotations

import argparse
import sys

import numpy as np

from jaxtrack._cache import enable_compilation_cache


def _cmd_demo_solver(args) -> int:
    """The pose-solver demo: a built-in synthetic articulated scene tracked frame to frame from noisy
    2D-3D correspondences (no images)."""
    import jax
    import jax.numpy as jnp
    from tqdm import tqdm

    import jaxtrack as jt
    from jaxtrack.geometry import rotation_error_deg, se3_exp
    from jaxtrack.synth import demo_chain, random_pose_scene

    model = demo_chain(args.joints, branches=args.branches, dtype=jnp.float32) if args.joints else jt.rigid_model()
    solve = jax.jit(lambda c, T, th: jt.solve_pose(model, c, T, th))
    # A smooth trajectory: every frame the root turns by ~3 deg and moves ~5 mm, the joints bend.
    seed = 0 if args.seed is None else args.seed
    base = random_pose_scene(seed, num_points=args.points, num_cameras=args.cameras, model=model, dtype=np.float32)
    T_prev, theta_prev = jnp.asarray(base.T_world_root, jnp.float32), jnp.asarray(base.theta, jnp.float32)
    step = np.array([4.0, -3.0, 2.0, 0.05, 0.03, -0.04], np.float32)
    rows = []
    frames = 60 if args.frames is None else args.frames
    for frame in tqdm(range(frames), desc="frames", disable=args.quiet):
        T_true = np.asarray(se3_exp(jnp.asarray(step * (frame + 1))), np.float64) @ base.T_world_root
        theta_true = base.theta + 0.3 * np.sin(0.2 * (frame + 1) + np.arange(model.num_joints))
        scene = jt.synth.project_model_points(base, T_true, theta_true, noise_px=args.noise, seed=seed + frame)
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
        f"{args.points} correspondences/frame, {args.noise} px noise, {frames} frames"
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
    import pathlib

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
    if args.rbot is not None and (args.urdf or args.mocap):
        raise ValueError("--rbot writes rigid objects in RBOT's layout; --urdf / --mocap write an articulated sequence")
    if args.variants is not None and args.rbot is None:
        raise ValueError("--variants chooses the RBOT variants of --rbot")
    if args.urdf or args.mocap:
        return _synth_articulated(args)
    if args.rbot is not None:
        return _synth_rbot(args)
    if args.step_deg is not None or args.fps is not None:
        raise ValueError("--step-deg and --fps apply to articulated sequences (--urdf or --mocap)")
    if args.preset and args.preset not in PRESETS:
        raise ValueError(f"unknown preset {args.preset!r}; `jaxtrack synth --list` shows them")
    cfg = PRESETS[args.preset] if args.preset else SynthConfig()
    overrides = {k: getattr(args, k) for k in ("object", "appearance", "background", "motion", "pose_file", "frames",
                                               "noise_sigma", "salt_fraction", "occluders", "cameras", "subsample", "seed")
                 if getattr(args, k) is not None}
    cfg = dataclasses.replace(cfg, **overrides)  # SynthConfig validates every field
    existed = pathlib.Path(args.out).exists()
    prepare_output_folder(args.out, "output folder")  # before rendering: a file in the way fails now
    if not existed:  # write_sequence removes the folder it made when the config cannot be rendered
        pathlib.Path(args.out).rmdir()
    with tqdm(total=cfg.frames * cfg.cameras, desc="rendering", disable=args.quiet) as bar:
        root = write_sequence(cfg, args.out, progress=bar)
    print(f"wrote {cfg.frames} frames x {cfg.cameras} camera(s) to {root}")
    return 0


def _synth_rbot(args) -> int:
    """A synthetic dataset in the RBOT dataset's layout (objects x variants on one trajectory), for jaxtrack bench."""
    from jaxtrack.synth import RbotSynthConfig, write_rbot_dataset

    ignored = [flag for flag, value in (("--preset", args.preset), ("--appearance", args.appearance),
                                        ("--motion", args.motion), ("--pose-file", args.pose_file),
                                        ("--salt-fraction", args.salt_fraction), ("--occluders", args.occluders),
                                        ("--cameras", args.cameras), ("--subsample", args.subsample),
                                        ("--object", args.object), ("--step-deg", args.step_deg),
                                        ("--fps", args.fps)) if value is not None]
    if ignored:
        raise ValueError(f"--rbot writes RBOT's layout (its objects are --rbot OBJECTS); {', '.join(ignored)} apply to one "
                         "BOP sequence")
    fields = {"objects": tuple(args.rbot), **({"variants": tuple(args.variants)} if args.variants else {}),
              **{k: getattr(args, k) for k in ("frames", "noise_sigma", "seed", "background") if getattr(args, k) is not None}}
    cfg = RbotSynthConfig(**fields)
    root = write_rbot_dataset(cfg, args.out)
    print(f"wrote an RBOT-layout dataset to {root}: {len(cfg.objects)} object(s) x {len(cfg.variants)} variant(s) "
          f"({', '.join(cfg.variants)}), {cfg.frames} frames each")
    return 0


def _synth_articulated(args) -> int:
    """`jaxtrack synth --urdf ROBOT.urdf` / `--mocap SUBJECT.asf MOTION.amc`: an articulated sequence."""
    import pathlib

    import numpy as np
    from tqdm import tqdm

    from jaxtrack.io import prepare_output_folder, read_urdf
    from jaxtrack.synth import (
        ArticulatedSynthConfig,
        mocap_motion,
        random_joint_trajectory,
        upright_urdf_pose,
        write_articulated_sequence,
    )

    if args.urdf and args.mocap:
        raise ValueError("give --urdf or --mocap, not both")
    rigid_only = [f"--{k.replace('_', '-')}" for k in ("preset", "object", "motion", "pose_file", "salt_fraction", "occluders")
                  if getattr(args, k) is not None]
    if rigid_only:
        raise ValueError(f"{', '.join(rigid_only)}: rigid-object options; not used with --urdf / --mocap")
    fps = 120 if args.fps is None else args.fps
    if args.mocap and 120 % fps:
        raise ValueError(f"argument --fps: {fps} does not divide the mocap's 120 frames/s (use 120, 60, 40, 30, 24, ...)")
    overrides = {k: getattr(args, k) for k in ("appearance", "background", "noise_sigma", "cameras", "seed")
                 if getattr(args, k) is not None}
    if args.mocap:
        for f in args.mocap:
            if not pathlib.Path(f).is_file():
                raise ValueError(f"argument --mocap: {f}: file not found")
        frames = 120 if args.frames is None else args.frames
        model, T_world_root, theta = mocap_motion(args.mocap[0], args.mocap[1], frames=frames)
        cfg = ArticulatedSynthConfig(**{"cameras": 4, "distance": 4500.0, "appearance": "photo", **overrides,
                                        "subsample": 120 // fps})
        info = {"mocap": [str(pathlib.Path(f).resolve()) for f in args.mocap], "fps": fps}
    else:
        if not pathlib.Path(args.urdf).is_file():
            raise ValueError(f"argument --urdf: {args.urdf}: file not found")
        model = read_urdf(args.urdf, package_dirs=args.package_dir or (), geometry=args.geometry)
        frames = 30 if args.frames is None else args.frames
        theta = random_joint_trajectory(model, frames, step_deg=3.0 if args.step_deg is None else args.step_deg,
                                        seed=0 if args.seed is None else args.seed)
        T_world_root = np.repeat(upright_urdf_pose((0.0, -400.0, 0.0))[None], frames, 0)
        cfg = ArticulatedSynthConfig(**{"distance": 1800.0, **overrides})
        info = {"urdf": str(pathlib.Path(args.urdf).resolve()), "step_deg": args.step_deg}
    prepare_output_folder(args.out, "output folder")
    n = len(range(0, len(theta), cfg.subsample))
    with tqdm(total=n * cfg.cameras, desc="rendering", disable=args.quiet) as bar:
        root = write_articulated_sequence(model, T_world_root, theta, cfg, args.out, progress=bar, info=info)
    print(f"wrote {n} frames x {cfg.cameras} camera(s) of {model.name} ({model.num_joints} joints) to {root}")
    return 0


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
    if img1.shape[:2] != img2.shape[:2]:
        raise ValueError(f"frames differ in size: {args.frame1} is {img1.shape[1]}x{img1.shape[0]}, {args.frame2} is "
                         f"{img2.shape[1]}x{img2.shape[0]}")
    if img1.ndim != img2.ndim:  # one grey file, one colour (or RGBA) file: compare them in grey
        print(f"note: {args.frame1 if img1.ndim == 2 else args.frame2} is grey, the other frame colour: both are read as grey")
        img1, img2 = read_image(args.frame1, "grey"), read_image(args.frame2, "grey")
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


CUE_CHOICES = ("region", "flow", "sift")  # the default: all of the paper's cues


def cue_choices() -> tuple[str, ...]:
    """Every name `--cues` accepts: "region" (the configured region modality) and each registered modality."""
    import jaxtrack.track  # noqa: F401  (registers the built-in modalities)
    from jaxtrack.modality import modality_names

    return ("region",) + tuple(n for n in modality_names() if n != "region")


def region_choices() -> tuple[str, ...]:
    """The registered region modalities (`--region`): those whose rows count as contour evidence."""
    import jaxtrack.track  # noqa: F401  (registers the built-in modalities)
    from jaxtrack.modality import modality_class, modality_names

    return ("auto",) + tuple(n for n in modality_names() if modality_class(n).contour)


def _cue_list(text: str) -> tuple[str, ...]:
    """An argparse type: comma-separated cue names, a non-empty subset of `cue_choices()`."""
    cues = tuple(c.strip().lower() for c in text.split(",") if c.strip())
    choices = cue_choices()
    bad = [c for c in cues if c not in choices]
    if bad or not cues:
        raise argparse.ArgumentTypeError(f"unknown cue {bad[0]!r} (choose from {', '.join(choices)})" if bad
                                         else f"expected cue names, got {text!r}")
    if len(set(cues)) != len(cues):
        raise argparse.ArgumentTypeError(f"a cue is named twice in {text!r}")
    return cues


def _prior_pair(text: str) -> tuple[float, ...]:
    """An argparse type: 'R,T[,RA,TA,F]', numbers ≥ 0 (one number sets R and T)."""
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected R,T[,RA,TA,F] (numbers ≥ 0), got {text!r}") from None
    if len(values) == 1:
        values = values * 2
    if len(values) not in (2, 5) or not all(np.isfinite(v) and v >= 0 for v in values):
        raise argparse.ArgumentTypeError(f"expected R,T or R,T,RA,TA,F (finite numbers ≥ 0), got {text!r}")
    return tuple(values)


def _late_rounds(text: str) -> tuple[float, ...]:
    """An argparse type: 'K,F[,T]': K ≥ 0 refinement rounds (inf: every one), the factor F and the confidence T in [0, 1]."""
    from jaxtrack.track._tracker import checked_late_rounds  # the rule `default_params` applies

    try:
        values = tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected K,F[,T] (numbers), got {text!r}") from None
    try:
        checked_late_rounds(values)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected K,F[,T]: K ≥ 0 (inf: every round), F and T in [0, 1], got {text!r}") from None
    return values


def _working_shape(text: str):
    """An argparse type: 'HxW' (integers ≥ 16, multiples of 4), 'native' (None) or 'default' (the tracker's)."""
    if text.strip().lower() == "native":
        return None
    if text.strip().lower() == "default":
        return "default"
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected HxW (e.g. 96x128) or 'native', got {text!r}") from None
    if h < 16 or w < 16 or h % 4 or w % 4:
        raise argparse.ArgumentTypeError(f"expected H and W ≥ 16 and multiples of 4, got {text!r}")
    return (h, w)


def _index_list(text: str) -> list[int]:
    """An argparse type: comma-separated distinct non-negative integers."""
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated view indices like 0,1, got {text!r}") from None
    if not values or any(v < 0 for v in values) or len(set(values)) != len(values):
        raise argparse.ArgumentTypeError(f"expected distinct view indices ≥ 0, got {text!r}")
    return values


def _object_ids(text: str):
    """An argparse type: one object id, comma-separated distinct ids, or 'all'."""
    if text.strip().lower() == "all":
        return "all"
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an object id, ids like 1,2 or 'all', got {text!r}") from None
    if not values or any(v < 0 for v in values) or len(set(values)) != len(values):
        raise argparse.ArgumentTypeError(f"expected distinct object ids ≥ 0, got {text!r}")
    return values


def _joint_ids(args, seq) -> list[int] | None:
    """The objects of a joint run (--obj-id with several ids or 'all'), None for one object."""
    ids = args.obj_id
    if ids == "all":
        bad = [c for c in (args.cameras or []) if c >= len(seq.views)]
        if bad:
            raise ValueError(f"--cameras: view {bad[0]} out of range: {seq.root} has {len(seq.views)} camera view(s) "
                             f"(0-{len(seq.views) - 1})")
        view0 = seq.views[(args.cameras or [0])[0]] if seq.views else None
        given = len(args.init_pose) if isinstance(args.init_pose, list) else 0
        ids = [o for o in sorted(seq.model_paths) if given or (
            view0 is not None and o in view0.T_cam_obj and np.all(np.isfinite(view0.T_cam_obj[o][0])))]
        if given and len(ids) != given:
            raise ValueError(f"--obj-id all: {seq.root} has {len(ids)} object(s) with a mesh, --init-pose was given {given} time(s)")
        if not ids:
            raise ValueError(f"--obj-id all: no object of {seq.root} has a mesh and a first pose in scene_gt.json")
    if ids is None or len(ids) == 1:
        args.obj_id = None if ids is None else ids[0]
        return None
    return list(ids)


def read_init_pose(text: str, what: str = "--init-pose") -> np.ndarray:
    """A (4, 4) model → camera pose (mm) from a file or from 12 / 16 numbers on the command line.

    Accepted: a .npy or .txt/.csv file holding 12 (3x4 [R|t]) or 16 (4x4) numbers, a .json file with such a
    list (flat or nested) or a BOP entry {"cam_R_m2c": [9], "cam_t_m2c": [3]}, or the numbers themselves,
    row-major, separated by commas or spaces.

    Raises:
        ValueError: naming `what` and the problem (unreadable file, wrong count, not a rigid transform).
    """
    import json
    import pathlib

    from jaxtrack.geometry import checked_rotation

    path = pathlib.Path(text)
    if path.is_file():
        try:
            if path.suffix.lower() == ".npy":
                values = np.load(path, allow_pickle=False)
            elif path.suffix.lower() == ".json":
                data = json.loads(path.read_text())
                if isinstance(data, dict):
                    if "cam_R_m2c" not in data or "cam_t_m2c" not in data:
                        raise ValueError("a JSON object needs the fields cam_R_m2c (9) and cam_t_m2c (3)")
                    data = np.concatenate([np.reshape(np.asarray(data["cam_R_m2c"], float), (3, 3)),
                                           np.reshape(np.asarray(data["cam_t_m2c"], float), (3, 1))], 1)
                values = np.asarray(data, float)
            else:
                values = np.loadtxt(path, delimiter=None if path.suffix.lower() != ".csv" else ",", ndmin=1)
        except (OSError, ValueError, TypeError) as e:
            raise ValueError(f"{what}: {path}: cannot read a pose ({e})") from e
        source = str(path)
    else:
        try:
            values = np.array([float(v) for v in text.replace(",", " ").split()])
        except ValueError:
            raise ValueError(f"{what}: {text!r} is neither a file nor 12 / 16 numbers") from None
        source = "the numbers given"
    values = np.asarray(values, np.float64).ravel()
    if values.size not in (12, 16):
        raise ValueError(f"{what}: {source} holds {values.size} numbers; need 12 (3x4 [R|t]) or 16 (4x4), row-major")
    if not np.all(np.isfinite(values)):
        raise ValueError(f"{what}: {source} holds non-finite numbers")
    T = np.eye(4)
    T[: values.size // 4] = values.reshape(-1, 4)
    if values.size == 16 and not np.allclose(T[3], [0, 0, 0, 1]):
        raise ValueError(f"{what}: the last row must be 0 0 0 1, got {T[3].tolist()}")
    checked_rotation(T[:3, :3], f"{what}: the rotation block")
    if T[2, 3] <= 0:
        raise ValueError(f"{what}: the translation puts the object behind the camera (z = {T[2, 3]:g} mm ≤ 0)")
    return T


def _check_writable(path, what: str) -> None:
    """A file that will be written after the (long) tracking: its folder and, if present, the file itself."""
    import os

    folder = path.parent if str(path.parent) else "."
    if not os.access(folder, os.W_OK | os.X_OK):
        raise ValueError(f"{what}: cannot write into {folder} (permission denied)")
    if path.exists() and not os.access(path, os.W_OK):
        raise ValueError(f"{what}: {path} exists and is not writable")


def _prepare_tracking(args, seq, out):
    """Everything checked before any compilation: views, object, first pose, outputs. Returns the kwargs of
    `track_sequence` and the overlay writer (or None)."""
    from jaxtrack.io import load_mesh_arrays, prepare_output_file
    from jaxtrack.track import OverlayRecorder, OverlayWriter

    n_views = len(seq.views)
    views = list(range(n_views)) if args.cameras is None else args.cameras
    bad = [c for c in views if c >= n_views]
    if bad:
        raise ValueError(f"--cameras: view {bad[0]} out of range: {seq.root} has {n_views} camera view(s) "
                         f"(0-{n_views - 1})")
    ids = sorted(seq.model_paths)
    obj_id = ids[0] if args.obj_id is None else args.obj_id
    if obj_id not in seq.model_paths:
        raise ValueError(f"--obj-id: object {obj_id} has no mesh models/obj_{obj_id:06d}.* in {seq.root} (have {ids})")
    view0 = seq.views[views[0]]
    gt = view0.T_cam_obj.get(obj_id)
    init_pose = None
    given = args.init_pose[0] if isinstance(args.init_pose, list) else args.init_pose
    if isinstance(args.init_pose, list) and len(args.init_pose) > 1:
        raise ValueError(f"--init-pose given {len(args.init_pose)} times for one object; several objects need "
                         "--obj-id with their ids (or --mesh once per object)")
    if isinstance(given, np.ndarray):  # found from --init-points
        init_pose = given
    elif given is not None:
        init_pose = read_init_pose(given)  # model → the first tracked view's camera
    elif gt is None or not np.all(np.isfinite(gt[0])):
        raise ValueError(f"{view0.folder / 'scene_gt.json'}: no pose of obj_id {obj_id} for the first frame; "
                         "give one with --init-pose")
    if args.reset_on_failure and (gt is None or not np.any(np.all(np.isfinite(gt[1:]), axis=(1, 2)))):
        raise ValueError(f"--reset-on-failure: {view0.folder / 'scene_gt.json'} has no ground truth after the first "
                         f"frame for obj_id {obj_id}")
    prepare_output_file(out, "-o/--out", suffixes=(".csv",))
    _check_writable(out, "-o/--out")
    _check_writable(out.with_name(out.stem + ".frames.jsonl"), "-o/--out")
    model_path = seq.model_paths[obj_id]
    pose_vertices = None
    if model_path.suffix.lower() == ".urdf":  # articulated: the URDF and its joints, checked now
        from jaxtrack.io import read_urdf

        art = read_urdf(model_path, package_dirs=[model_path.parent])
        unknown = sorted(set(view0.joints.get(obj_id, {})) - set(art.joint_names))
        if unknown:
            raise ValueError(f"{view0.folder / 'scene_gt.json'}: joint(s) {unknown} are not in {model_path.name} "
                             f"(its movable joints: {list(art.joint_names)})")
        _check_writable(out.with_name(out.stem + ".joints.csv"), "-o/--out")
        vertices, faces = np.asarray(art.mesh.vertices), np.asarray(art.mesh.faces)
        part = np.asarray(art.mesh.vertex_part)

        def pose_vertices(theta):
            T_parts = np.stack([art.link_poses(theta)[name] @ np.linalg.inv(art.T_root_link0[name])
                                for name in art.part_names])
            return np.einsum("vij,vj->vi", T_parts[part, :3, :3], vertices) + T_parts[part, :3, 3]
    else:
        if args.joint_limits:
            raise ValueError(f"--joint-limits: obj_id {obj_id} is rigid ({model_path.name}); limits come from a URDF")
        vertices, faces = load_mesh_arrays(model_path, seq.model_scale(obj_id))  # an unreadable or empty mesh fails here, named
    recorder = None
    if args.video is not None:
        H, W = view0.height, view0.width
        writer = OverlayWriter(args.video, (H, W * len(views)), fps=args.fps, what="--video")
        recorder = OverlayRecorder(writer, vertices, faces, np.stack([seq.views[c].K for c in views]),
                                   pose_vertices=pose_vertices)
    kwargs = {"cues": args.cues, "cameras": views, "obj_id": obj_id, "init_pose": init_pose,
              "reset_on_failure": args.reset_on_failure, "max_frames": args.max_frames, "progress": not args.quiet,
              "on_frame": recorder, **({"joint_limits": True} if args.joint_limits else {}),
              **({"pose_prior": args.pose_prior} if getattr(args, "pose_prior", None) is not None else {}),
              **({"late_rounds": args.late_rounds} if getattr(args, "late_rounds", None) is not None else {}),
              **({"region": args.region} if getattr(args, "region", None) is not None else {}),
              **({"working_shape": args.working_shape} if getattr(args, "working_shape", "default") != "default" else {}),
              **({"recovery": args.recover} if getattr(args, "recover", None) is not None else {})}
    return kwargs, recorder


def _prepare_joint_tracking(args, seq, out, obj_ids: list[int]):
    """As `_prepare_tracking` for several rigid objects tracked jointly (`track_objects`)."""
    from jaxtrack.io import load_mesh_arrays, prepare_output_file
    from jaxtrack.track import JointOverlayRecorder, OverlayWriter

    refused = [flag for flag, on in (("--reset-on-failure", args.reset_on_failure), ("--recover", getattr(args, "recover", None)),
                                     ("--joint-limits", args.joint_limits)) if on]
    if refused:
        raise ValueError(f"{', '.join(refused)}: not available when several objects are tracked together "
                         f"(--obj-id {','.join(map(str, obj_ids))}); track one object for it")
    n_views = len(seq.views)
    views = list(range(n_views)) if args.cameras is None else args.cameras
    bad = [c for c in views if c >= n_views]
    if bad:
        raise ValueError(f"--cameras: view {bad[0]} out of range: {seq.root} has {n_views} camera view(s) (0-{n_views - 1})")
    missing = [o for o in obj_ids if o not in seq.model_paths]
    if missing:
        raise ValueError(f"--obj-id: object {missing[0]} has no mesh in {seq.root} (have {sorted(seq.model_paths)})")
    view0 = seq.views[views[0]]
    poses = args.init_pose if isinstance(args.init_pose, list) else ([] if args.init_pose is None else [args.init_pose])
    if poses and len(poses) != len(obj_ids):
        raise ValueError(f"--init-pose given {len(poses)} time(s) for {len(obj_ids)} objects ({','.join(map(str, obj_ids))}): "
                         "one per object, in the same order")
    init_poses = {}
    for i, o in enumerate(obj_ids):
        if seq.model_paths[o].suffix.lower() == ".urdf":
            raise ValueError(f"--obj-id: object {o} is articulated ({seq.model_paths[o].name}); several objects are tracked "
                             "rigid: track it alone")
        if poses:
            init_poses[o] = poses[i] if isinstance(poses[i], np.ndarray) else read_init_pose(poses[i], f"--init-pose ({i + 1})")
        elif o not in view0.T_cam_obj or not np.all(np.isfinite(view0.T_cam_obj[o][0])):
            raise ValueError(f"{view0.folder / 'scene_gt.json'}: no pose of obj_id {o} for the first frame; give one "
                             "--init-pose per object")
    prepare_output_file(out, "-o/--out", suffixes=(".csv",))
    _check_writable(out, "-o/--out")
    _check_writable(out.with_name(out.stem + ".frames.jsonl"), "-o/--out")
    objects = []
    for o in obj_ids:
        objects.append(load_mesh_arrays(seq.model_paths[o], seq.model_scale(o)))  # an unreadable or empty mesh fails here, named
    recorder = None
    if args.video is not None:
        writer = OverlayWriter(args.video, (view0.height, view0.width * len(views)), fps=args.fps, what="--video")
        recorder = JointOverlayRecorder(writer, objects, np.stack([seq.views[c].K for c in views]),
                                        names=[f"obj {o}" for o in obj_ids])
    kwargs = {"cues": args.cues, "cameras": views, "init_poses": init_poses or None, "max_frames": args.max_frames,
              "progress": not args.quiet, "on_frame": recorder,
              **({"region": args.region} if getattr(args, "region", None) is not None else {}),
              **({"pose_prior": args.pose_prior} if getattr(args, "pose_prior", None) is not None else {}),
              **({"late_rounds": args.late_rounds} if getattr(args, "late_rounds", None) is not None else {}),
              **({"working_shape": args.working_shape} if getattr(args, "working_shape", "default") != "default" else {})}
    return kwargs, recorder


def _run_tracking(args, track, recorder):
    """`track()` with the on-disk compilation cache (unless --no-cache); the overlay is closed whatever happens."""
    if not args.no_cache:
        enable_compilation_cache()
    try:
        return track()
    finally:
        if recorder is not None:
            recorder.writer.close()


def _print_overlay(recorder, note: str = "") -> None:
    if recorder is not None:
        kind = "video" if recorder.writer.is_video else "PNG folder"
        print(f"overlay {kind} -> {recorder.writer.path} ({recorder.writer.count} frames{note})")


def _track_joint(args, seq, out, obj_ids: list[int]):
    """Track several objects of `seq` jointly, write one CSV (rows per object) and the overlay."""
    from jaxtrack.track import track_objects

    kwargs, recorder = _prepare_joint_tracking(args, seq, out, obj_ids)
    _note_partial(out)
    runs = _run_tracking(args, lambda: track_objects(seq, obj_ids, **kwargs, results=out), recorder)
    return runs, out, out.with_name(out.stem + ".frames.jsonl"), recorder


def _joint_summary(runs, seq, cues, csv, jsonl, recorder) -> None:
    from collections import Counter

    print(f"tracked {len(runs[0].frame_ids)} frame(s) of {seq.root}: {len(runs)} objects jointly "
          f"(view(s) {','.join(map(str, runs[0].camera_ids))}, cues {'+'.join(cues)})")
    steady = [sum(r.timings[k].get("total_s", 0.0) + r.timings[k].get("occluders_s", 0.0) for r in runs)
              for k in range(2, len(runs[0].frame_ids))]
    if steady:
        med = float(np.median(steady))
        print(f"time: first frame (set-up) {sum(r.timings[0]['total_s'] for r in runs):.1f} s; other frames {med:.2f} s "
              f"median for all objects ({1.0 / med:.1f} frames/s)")
    for r in runs:
        counts = Counter(r.status)
        print(f"obj {r.obj_id}: " + ", ".join(f"{k} {v}" for k, v in counts.most_common()))
    print(f"results -> {csv} (+ {jsonl.name}; one row per object and frame; jaxtrack eval --obj-id picks one)")
    _print_overlay(recorder, ", one colour per object")


def _track(args, seq, out):
    """Track `seq` as `args` say, write the results (and the overlay); returns the run and the paths."""
    from jaxtrack.track import track_sequence

    kwargs, recorder = _prepare_tracking(args, seq, out)
    _note_partial(out)
    run = _run_tracking(args, lambda: track_sequence(seq, **kwargs, results=out), recorder)
    return run, out, out.with_name(out.stem + ".frames.jsonl"), recorder


def _note_partial(out) -> None:
    """Say so when -o holds the partial results of a run that stopped: they are tracked again from the first frame
    (a restart from their last pose would not give the run's results)."""
    from jaxtrack.track import results_state

    state = results_state(out)
    if state.state == "partial":
        print(f"{out}: partial results of a run that stopped after {state.frames_written} frame(s); tracking the "
              "sequence again from its first frame", file=sys.stderr)


def _tracking_summary(run, seq, cues, csv, jsonl, recorder) -> None:
    """Frames, timings (set-up, steps that compiled a new crop size class, the rest), statuses, outputs."""
    from collections import Counter

    seconds = [t.get("total_s", 0.0) for t in run.timings]
    crops = run.crops or [None] * len(seconds)
    seen, compiled, steady = set(), [], []
    for k in range(1, len(seconds)):
        if crops[k] is not None and crops[k] not in seen:
            seen.add(crops[k])
            compiled.append(seconds[k])
        else:
            steady.append(seconds[k])
    print(f"tracked {len(seconds)} frame(s) of {seq.root} (view(s) {','.join(map(str, run.camera_ids))}, "
          f"cues {'+'.join(cues)})")
    line = f"time: first frame (set-up) {seconds[0]:.1f} s"
    if compiled:
        line += (f"; {len(compiled)} step(s) preparing a new crop size class (compile, or load from the cache) "
                 f"({', '.join('x'.join(map(str, c)) for c in sorted(seen))}): {', '.join(f'{t:.1f}' for t in compiled)} s")
    if steady:
        med = float(np.median(steady))
        line += f"; other frames {med:.2f} s median ({1.0 / med:.1f} frames/s)"
    print(line)
    counts = Counter(run.status)
    print("status: " + ", ".join(f"{k} {v}" for k, v in counts.most_common()) + f"; resets {int(np.sum(run.reset))}")
    print(f"results -> {csv} (+ {jsonl.name}" + (f", {csv.stem}.joints.csv" if run.joint_names else "") + ")")
    _print_overlay(recorder)


def _own_footage(args):
    """The `Sequence` of a video file or image folder (--mesh, --camera), and the first pose(s) from --init-points
    (printed with its reprojection error) unless --init-pose gives it; one --init-* per --mesh (objects 1, 2, ...).
    Everything checked before compiling."""
    from jaxtrack.io import own_sequence, pose_from_points, read_init_points

    missing = [flag for flag, value in (("--mesh", args.mesh), ("--camera", args.camera)) if not value]
    if missing:
        raise ValueError(f"{args.sequence}: not a BOP folder (no models/ in it), so it is read as your own footage, which "
                         f"needs {' and '.join(missing)} (see jaxtrack track --help)")
    if args.init_points is None and args.init_pose is None:
        raise ValueError(f"{args.sequence}: your own footage needs the first pose: --init-points POINTS (≥ 4 clicked image "
                         "points with their model points; `jaxtrack pick` writes the file) or --init-pose POSE")
    if args.init_points is not None and args.init_pose is not None:
        raise ValueError("--init-pose and --init-points: give one of them (one kind for every --mesh)")
    if args.reset_on_failure:
        raise ValueError("--reset-on-failure: your own footage has no ground truth to reset to")
    if args.obj_id is not None:
        raise ValueError("--obj-id: your own footage numbers its objects 1, 2, ... in the order of --mesh")
    meshes = list(args.mesh)
    firsts = args.init_points if args.init_points is not None else args.init_pose
    if len(firsts) != len(meshes):
        flag = "--init-points" if args.init_points is not None else "--init-pose"
        raise ValueError(f"--mesh given {len(meshes)} time(s), {flag} {len(firsts)} time(s): one first pose per mesh, "
                         "in the same order")
    seq = own_sequence(args.sequence, meshes if len(meshes) > 1 else meshes[0], args.camera, args.mesh_unit)
    if args.init_points is not None:
        view = seq.views[0]
        poses = []
        for o, points in enumerate(args.init_points, 1):
            image_points, model_points = read_init_points(points)
            found = pose_from_points(image_points, model_points, view.K, view.calibration.dist, seq.model_scale(o),
                                     what=f"--init-points {points}")
            used = int(found.inliers.sum())
            label = f" of object {o} ({meshes[o - 1]})" if len(meshes) > 1 else ""
            print(f"first pose{label} from {len(image_points)} points ({used} inliers): reprojection {found.rms_px:.2f} px "
                  f"RMS, {found.max_px:.2f} px at most")
            poses.append(found.T_cam_obj)
        args.init_pose = poses
    if len(meshes) > 1:
        args.obj_id = list(range(1, len(meshes) + 1))
    return seq


def _cmd_track(args) -> int:
    """Track a BOP-layout sequence, a video file or an image folder from its first pose; write the BOP CSV,
    frames.jsonl and an overlay."""
    import pathlib

    from jaxtrack.io import is_bop_folder, read_sequence

    own_flags = [flag for flag, value in (("--mesh", args.mesh), ("--camera", args.camera), ("--init-points", args.init_points))
                 if value]
    source = pathlib.Path(args.sequence)
    if not source.exists():
        raise FileNotFoundError(f"{source}: no such BOP sequence folder, video file or folder of images")
    # A BOP folder: models/ beside numbered camera folders (a broken one is read as BOP, so its message names the gap).
    bop_like = source.is_dir() and any(p.is_dir() and p.name.isdigit() for p in source.iterdir())
    if is_bop_folder(source) or (bop_like and not own_flags):
        if own_flags:
            raise ValueError(f"{args.sequence}: a BOP folder brings its own meshes, camera and first pose; "
                             f"{', '.join(own_flags)} are for a video file or an image folder")
        seq = read_sequence(args.sequence)
    else:
        seq = _own_footage(args)
    out = pathlib.Path(args.out) if args.out else pathlib.Path(f"{seq.root.resolve().stem}-results.csv")
    obj_ids = _joint_ids(args, seq)
    if obj_ids is not None:
        runs, csv, jsonl, recorder = _track_joint(args, seq, out, obj_ids)
        _joint_summary(runs, seq, args.cues, csv, jsonl, recorder)
        return 0
    run, csv, jsonl, recorder = _track(args, seq, out)
    _tracking_summary(run, seq, args.cues, csv, jsonl, recorder)
    return 0


def _name_list(text: str) -> list[str]:
    names = [t.strip() for t in text.split(",") if t.strip()]
    if not names:
        raise argparse.ArgumentTypeError(f"expected comma-separated names, got {text!r}")
    return names


def _step_list(text: str) -> list[int]:
    try:
        steps = [int(t) for t in text.split(",") if t.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers ≥ 1 (1,2,3,4), got {text!r}") from None
    if not steps or any(s < 1 for s in steps):
        raise argparse.ArgumentTypeError(f"expected comma-separated integers ≥ 1 (1,2,3,4), got {text!r}")
    return steps


def _cmd_bench(args) -> int:
    """Track every sequence of a dataset under a protocol (on Ray, or here with --workers 0); write the tables."""
    import pathlib

    from jaxtrack.bench import BenchSettings, run_bench

    resets = args.resets or ("both" if args.protocol == "rbot" else "off")
    if args.protocol == "bop" and resets != "off":
        raise ValueError("--resets: the bop protocol tracks without resets (use --protocol rbot for them)")
    settings = BenchSettings(
        protocol=args.protocol, frame_steps=tuple(args.frame_steps), resets={"both": (True, False), "on": (True,),
                                                                            "off": (False,)}[resets],
        cues=tuple(args.cues), region=args.region,
        working_shape=args.working_shape if args.working_shape in ("default", None) else tuple(args.working_shape),
        pose_prior=None if args.pose_prior is None else tuple(args.pose_prior),
        late_rounds=None if args.late_rounds is None else tuple(args.late_rounds), recovery=args.recover,
        max_frames=args.max_frames)
    workers = args.workers
    if workers is None and not args.address:
        try:
            import ray  # noqa: F401
        except ImportError:
            print("jaxtrack bench: ray is not installed (pip install 'jaxtrack[bench]'): running the sequences one after "
                  "another in this process", file=sys.stderr)
            workers = 0
    out = pathlib.Path(args.out) if args.out else pathlib.Path(f"bench-{pathlib.Path(args.dataset).resolve().name}")
    report = run_bench(args.dataset, out, settings, layout=args.layout, objects=args.objects, variants=args.variants,
                       workers=workers, address=args.address, use_cache=not args.no_cache,
                       timeout_s=None if args.timeout_min is None else 60.0 * args.timeout_min, progress=not args.quiet)
    ran = len(report.results) - len(report.skipped)
    print(f"benched {len(report.results)} run(s) of {args.dataset} ({ran} now, {len(report.skipped)} found finished in "
          f"{out}) in {report.wall_s:.1f} s on {report.executor}")
    modes = sorted({(r["step"], r["reset"]) for r in report.results if not r.get("error")}, key=lambda m: (m[0], not m[1]))
    for step, reset in modes:
        values = [r["success"] for r in report.results if not r.get("error") and (r["step"], r["reset"]) == (step, reset)]
        finite = [v for v in values if np.isfinite(v)]
        mean = f"{100.0 * float(np.mean(finite)):.1f} %" if finite else "n/a"
        print(f"  S = {step}, {'with' if reset else 'without'} resets: success {mean} over {len(values)} sequence(s)")
    print(f"tables -> {report.markdown}, {report.csv.name}" + (f", {report.plot.name}" if report.plot else
                                                               " (no plot: matplotlib is not installed)"))
    if report.failed:
        print(f"jaxtrack bench: {len(report.failed)} run(s) failed (listed in {report.markdown.name}; run the same command "
              "again to retry them): " + "; ".join(report.failed[:5]), file=sys.stderr)
        return 1
    return 0


def _fmt(v: float, digits: int) -> str:
    return "n/a" if not np.isfinite(v) else f"{v:.{digits}f}"


def _print_evaluation(ev, per_frame: bool = True) -> None:
    """Markdown tables: per frame, then means / medians / maxima, rates and the status quality."""
    from jaxtrack.track import failure_episodes, precision_recall

    tenth = 0.1 * ev.diameter_mm
    if per_frame:
        print("| im_id | rot (deg) | trans (mm) | ADD (mm) | ADD-S (mm) | 5cm/5° | score | status |")
        print("|---:|---:|---:|---:|---:|:---:|---:|---|")
        for k, im_id in enumerate(ev.im_ids):
            status = "" if ev.status is None else ev.status[k] + (" (reset)" if ev.reset[k] else "")
            ok = "" if not ev.has_gt[k] else ("yes" if ev.success[k] else "NO")
            print(f"| {im_id} | {_fmt(ev.rot_deg[k], 3)} | {_fmt(ev.trans_mm[k], 2)} | {_fmt(ev.add_mm[k], 2)} | "
                  f"{_fmt(ev.adds_mm[k], 2)} | {ok} | {ev.score[k]:.3f} | {status} |")
        print()
    use = ev.has_gt & ~ev.initial
    first = "" if not np.any(ev.has_gt & ev.initial) else " (the first frame, the given initial pose, left out)"
    print(f"{int(use.sum())} tracked frame(s) with ground truth of {len(ev.im_ids)} in the results, view {ev.camera}, "
          f"obj_id {ev.obj_id}{first}; model diameter {ev.diameter_mm:.1f} mm, ADD over {ev.points} vertices")
    if not use.any():
        print("no tracked frame has ground truth: nothing to evaluate")
        return
    print()
    print("| error | mean | median | max |\n|---|---:|---:|---:|")
    for name, v, d in (("rotation (deg)", ev.rot_deg, 3), ("translation (mm)", ev.trans_mm, 2), ("ADD (mm)", ev.add_mm, 2),
                       ("ADD-S (mm)", ev.adds_mm, 2)):
        x = v[use]
        print(f"| {name} | {_fmt(x.mean(), d)} | {_fmt(np.median(x), d)} | {_fmt(x.max(), d)} |")
    print()
    failed = ~ev.success[use]
    print("| rate | value |\n|---|---:|")
    print(f"| 5 cm / 5° success | {np.mean(~failed):.3f} ({int(np.sum(~failed))}/{int(use.sum())}) |")
    print(f"| ADD < 10% diameter ({tenth:.1f} mm) | {np.mean(ev.add_mm[use] < tenth):.3f} |")
    print(f"| ADD-S < 10% diameter | {np.mean(ev.adds_mm[use] < tenth):.3f} |")
    if ev.status is None:
        print("\nno frames.jsonl beside the CSV: status quality not evaluated")
        return
    status = np.array(ev.status)[use]
    lost = np.isin(status, ["LOST", "OUT_OF_VIEW", "NONFINITE"])
    flagged = ~np.isin(status, ["OK", "RECOVERED"])  # RECOVERED: lost, then found (a usable pose)
    print()
    print("| status predicts failure (beyond 5 cm / 5°) | frames flagged | precision | recall |\n|---|---:|---:|---:|")
    for name, pred in (("lost", lost), ("lost or uncertain", flagged)):
        p, r = precision_recall(pred, failed)
        print(f"| {name} | {int(pred.sum())} | {_fmt(p, 3)} | {_fmt(r, 3)} |")
    episodes = failure_episodes(failed)
    if episodes:
        back = [n for n, recovered in episodes if recovered]
        print(f"\nfailures: {len(episodes)} run(s) of frames beyond 5 cm / 5°; back within it after "
              + (f"{_fmt(float(np.median(back)), 1)} frames (median), {max(back)} at most" if back else "-")
              + f"; {sum(not r for _, r in episodes)} never back")
    if ev.reset is not None and ev.reset.any():
        print(f"\nresets (RBOT protocol): {int(ev.reset.sum())}")


def _cmd_eval(args) -> int:
    """Errors of a results CSV against the sequence's ground truth, as markdown tables."""
    from jaxtrack.track import evaluate_tracking

    ev = evaluate_tracking(args.results, args.sequence, obj_id=args.obj_id, camera=args.camera)
    if not np.any(ev.has_gt & ~ev.initial):  # the tables would be empty: say so and fail, not exit 0
        raise ValueError(f"{args.results}: none of its {len(ev.im_ids)} frame(s) after the first has a ground-truth pose "
                         f"of obj_id {ev.obj_id} in {args.sequence} (view {ev.camera}): nothing to evaluate")
    _print_evaluation(ev, per_frame=not args.summary)
    return 0


DEMO_SIZE = (320, 240)  # small frames (the tracker is compile-bound here); 160x120 loses the box
DEMO_SEED = 3


POINTS_FORMAT = ('{"image_points": [[u, v], ...], "model_points": [[x, y, z], ...]} (pixels of the first frame, x to the '
                 'right and y down from the top-left pixel centre; model points in the mesh\'s units, in the same order), '
                 'or a CSV of rows u,v,x,y,z')


def _first_frame(source, frame: int) -> np.ndarray:
    """RGB uint8 frame `frame` of a video file, an image folder or a single image (for `jaxtrack pick`)."""
    import pathlib

    import cv2

    from jaxtrack.io._own_video import IMAGE_SUFFIXES, _image_files

    source = pathlib.Path(source)
    if source.is_dir():
        files = _image_files(source)
        if len(files) <= frame:
            raise ValueError(f"{source}: {len(files)} image(s), no frame {frame}")
        img = cv2.imread(str(files[frame]), cv2.IMREAD_COLOR)
    elif source.is_file() and source.suffix.lower() in IMAGE_SUFFIXES:
        img = cv2.imread(str(source), cv2.IMREAD_COLOR)
    elif source.is_file():
        cap = cv2.VideoCapture(str(source))
        if not cap.isOpened():
            raise ValueError(f"{source}: cannot be opened as a video by OpenCV")
        for _ in range(frame):
            cap.grab()
        ok, img = cap.read()
        cap.release()
        img = img if ok else None
    else:
        raise FileNotFoundError(f"{source}: no such video file, image or folder")
    if img is None:
        raise ValueError(f"{source}: frame {frame} cannot be read")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def _read_model_points(path) -> np.ndarray:
    import json
    import pathlib

    path = pathlib.Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: model points file not found")
    try:
        if path.suffix.lower() == ".json":
            data = json.loads(path.read_text(encoding="utf-8-sig"))
            pts = np.asarray(data["model_points"] if isinstance(data, dict) else data, np.float64)
        else:
            delimiter = "," if path.suffix.lower() == ".csv" else None
            try:
                pts = np.loadtxt(path, delimiter=delimiter, ndmin=2, comments="#")
            except ValueError:  # a header row
                pts = np.loadtxt(path, delimiter=delimiter, ndmin=2, comments="#", skiprows=1)
    except (ValueError, KeyError, TypeError) as e:
        raise ValueError(f"{path}: expected a list of [x, y, z] model points (JSON list, or a CSV / text file of rows "
                         f"x,y,z): {e}") from None
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 4 or not np.all(np.isfinite(pts)):
        raise ValueError(f"{path}: expected at least 4 finite [x, y, z] model points, got shape {pts.shape}")
    return pts


def _cmd_pick(args) -> int:
    """Click the image points of given model points on a frame and write the --init-points file."""
    import json
    import os
    import pathlib

    model = _read_model_points(args.model_points)
    frame = _first_frame(args.input, args.frame)
    out = pathlib.Path(args.out)
    _check_writable(out, "-o/--out")
    try:
        import matplotlib
    except ImportError:
        matplotlib = None
    headless = os.name == "posix" and not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY") and \
        os.uname().sysname != "Darwin"
    if matplotlib is None or headless:
        still = out.with_suffix(".frame.png")
        import cv2

        cv2.imwrite(str(still), cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
        why = "matplotlib is not installed" if matplotlib is None else "no display ($DISPLAY is not set)"
        raise ValueError(f"cannot show a window: {why}. Frame {args.frame} is written to {still}: read the pixel of each of "
                         f"the {len(model)} model points in any image viewer and write {out} by hand as {POINTS_FORMAT}")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(10, 10 * frame.shape[0] / frame.shape[1]))
    ax.imshow(frame)
    clicked = []
    for i, p in enumerate(model):
        ax.set_title(f"click model point #{i} ({p[0]:g}, {p[1]:g}, {p[2]:g})")
        fig.canvas.draw_idle()
        got = plt.ginput(1, timeout=0)
        if not got:
            plt.close(fig)
            raise ValueError(f"the window was closed after {len(clicked)} of {len(model)} points: nothing written")
        clicked.append(got[0])
        ax.plot(*got[0], "r+", markersize=12)
        ax.annotate(str(i), got[0], color="yellow")
    plt.close(fig)
    out.write_text(json.dumps({"image_points": [[float(u), float(v)] for u, v in clicked],
                               "model_points": model.tolist()}, indent=1))
    print(f"{len(clicked)} points -> {out} (use: jaxtrack track {args.input} --init-points {out} ...)")
    return 0


def _cmd_demo(args) -> int:
    """Synthesise a short textured sequence, track it with all cues, print the errors, write an overlay."""
    import pathlib
    import shutil
    import tempfile

    if args.solver_only:
        return _cmd_demo_solver(args)
    from tqdm import tqdm

    from jaxtrack.io import prepare_output_folder, read_sequence
    from jaxtrack.synth import SynthConfig, write_sequence
    from jaxtrack.track import evaluate_tracking

    out = pathlib.Path(args.out) if args.out else pathlib.Path(tempfile.gettempdir()) / "jaxtrack-demo"
    prepare_output_folder(out, "--out")
    seq_dir = out / "sequence"
    if seq_dir.exists():  # a previous demo's sequence: replace it (stale frames would be read as ours)
        if not (seq_dir / "synth_config.json").is_file():
            raise ValueError(f"--out: {seq_dir} exists and is not a jaxtrack demo sequence; choose another --out")
        shutil.rmtree(seq_dir)
    frames = 20 if args.frames is None else args.frames
    W, H = DEMO_SIZE
    cfg = SynthConfig(object="box", appearance="photo", texture_photo="astronaut", size_mm=160, motion="random",
                      step_px=6.0, step_deg=2.0, frames=frames, width=W, height=H, focal=700.0 * W / 640,
                      background="coffee", seed=DEMO_SEED if args.seed is None else args.seed)
    with tqdm(total=frames, desc="rendering", disable=args.quiet) as bar:
        write_sequence(cfg, seq_dir, progress=bar)
    seq = read_sequence(seq_dir)
    track_args = argparse.Namespace(cameras=None, obj_id=None, init_pose=None, reset_on_failure=False, max_frames=None,
                                    cues=args.cues, video=str(out / "overlay.mp4"), fps=10.0, quiet=args.quiet,
                                    no_cache=args.no_cache, joint_limits=False)
    run, csv, jsonl, recorder = _track(track_args, seq, out / "results.csv")
    print(f"jaxtrack demo: a {cfg.size_mm:g} mm photo-textured box, {frames} frames of {W}x{H}, random motion "
          f"(~{cfg.step_px:g} px, {cfg.step_deg:g}° per frame), cues {'+'.join(args.cues)}")
    _tracking_summary(run, seq, args.cues, csv, jsonl, recorder)
    ev = evaluate_tracking(csv, seq)
    print()
    _print_evaluation(ev, per_frame=False)
    bad = ~ev.success[ev.has_gt]
    if bad.any():
        print(f"jaxtrack demo: tracking failed badly: {int(bad.sum())} frame(s) beyond 5 cm / 5°", file=sys.stderr)
        return 1
    return 0


def _number(kind, low=None, high=None, low_open=False, high_open=False):
    """An argparse type: `kind` (int/float) in [low, high] (low / high excluded if low_open / high_open), finite."""

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {'an integer' if kind is int else 'a number'}, got {text!r}") from None
        if kind is float and not np.isfinite(value):
            raise argparse.ArgumentTypeError(f"must be finite, got {text}")
        if low is not None and (value <= low if low_open else value < low) or high is not None and (
                value >= high if high_open else value > high):
            lo = "" if low is None else f"{'>' if low_open else '≥'} {low:g}"
            hi = "" if high is None else f"{'<' if high_open else '≤'} {high:g}"
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
        help="synthesise a short sequence, track it with all cues, print the errors (no files needed)",
        description="Render a short synthetic sequence of a photo-textured box with exact ground truth "
        "(jaxtrack.synth), track it from its first pose with the region, flow and SIFT cues, print the pose "
        "errors and the status counts, and write the results CSV and an overlay video (model contour green, "
        "segmented contour magenta) to --out. Exits 1 when a frame ends beyond 5 cm / 5°. With --solver-only, "
        "the earlier demo: a built-in articulated object solved frame to frame from noisy 2D-3D "
        "correspondences (no images).",
    )
    demo.add_argument("--frames", type=_number(int, 1), default=None,
                      help="number of frames (default 20; 60 with --solver-only)")
    demo.add_argument("--out", help="output folder (default: jaxtrack-demo in the system's temp folder); "
                      "holds sequence/, results.csv, results.frames.jsonl and overlay.mp4")
    demo.add_argument("--cues", type=_cue_list, default=CUE_CHOICES, help="cues to track with (default region,flow,sift)")
    demo.add_argument("--seed", type=_number(int, 0), default=None, help="random seed (default 3; 0 with --solver-only)")
    demo.add_argument("--no-cache", action="store_true", help="do not use the on-disk caches of compiled and traced programs ($JAXTRACK_CACHE_DIR)")
    demo.add_argument("--quiet", action="store_true", help="no progress bars")
    solver = demo.add_argument_group("pose-solver demo (--solver-only)")
    solver.add_argument("--solver-only", action="store_true",
                        help="run the pose-solver demo instead (noisy 2D-3D correspondences, no images)")
    solver.add_argument("--joints", type=_number(int, 0), default=3, help="joints of the built-in chain; 0 = rigid (default 3)")
    solver.add_argument("--branches", type=int, default=1, choices=(1, 2), help="1 = an arm, 2 = a torso with two arms")
    solver.add_argument("--cameras", type=_number(int, 1), default=2, help="cameras around the object (default 2)")
    solver.add_argument("--points", type=_number(int, 1), default=200, help="correspondences per frame (default 200)")
    solver.add_argument("--noise", type=_number(float, 0), default=1.0, help="pixel noise σ in px (default 1.0)")
    demo.set_defaults(func=_cmd_demo)

    track = sub.add_parser(
        "track",
        help="track an object through a BOP-layout sequence; BOP results CSV, frames.jsonl, overlay video",
        description="Track the object of a BOP-layout sequence (see DESIGN.md: SEQ/models/obj_XXXXXX.ply, "
        "SEQ/000000/rgb/, scene_camera.json, scene_gt.json) from the pose of its first frame. Writes the BOP "
        "results CSV (one row per frame and view, score = confidence in [0, 1], time = seconds for that frame) "
        "and NAME.frames.jsonl beside it (status, correspondence counts per cue and camera, stage timings, reset "
        "flag). Every input is checked before compiling. Compiled programs are cached on disk "
        "(~/.cache/jaxtrack/xla or $JAXTRACK_CACHE_DIR).",
    )
    track.add_argument("sequence", metavar="INPUT",
                       help="a BOP sequence folder, or your own footage: a video file (anything OpenCV decodes) or a folder "
                       "of images, with --mesh, --camera and --init-points or --init-pose")
    track.add_argument("-o", "--out", help="results CSV (default: ./<INPUT name>-results.csv)")
    own = track.add_argument_group("your own video or image folder")
    own.add_argument("--mesh", action="append",
                     help="the object's mesh (any file trimesh reads: .ply, .obj, .stl, .glb, .off); repeat it with one "
                     "--init-points (or --init-pose) each to track several objects jointly (objects 1, 2, ... in that order)")
    own.add_argument("--mesh-unit", dest="mesh_unit", choices=("mm", "cm", "m"), default="mm",
                     help="the mesh's length unit (default mm)")
    own.add_argument("--camera", metavar="CALIB",
                     help="OpenCV calibration file (.yaml/.yml/.xml with camera_matrix, distortion_coefficients, "
                     "image_width, image_height, as cv2.FileStorage writes) or a .json with K and dist; frames are "
                     "undistorted as they are read")
    own.add_argument("--init-points", dest="init_points", metavar="POINTS", action="append",
                     help='first pose from ≥ 4 clicked points: a .json {"image_points": [[u, v], ...], "model_points": '
                     '[[x, y, z], ...]} (pixels of the first frame; mesh units) or a .csv of rows u,v,x,y,z; PnP (RANSAC '
                     'beyond 4 points) refined by jaxtrack\'s solver; refused when it reprojects worse than 4 px RMS. '
                     "`jaxtrack pick` writes one")
    track.add_argument("--cues", type=_cue_list, default=CUE_CHOICES, help="comma-separated modalities: region (the configured region modality), flow, sift, levelset or any "
                       "registered modality (default region,flow,sift)")
    track.add_argument("--cameras", type=_index_list, help="comma-separated camera views, e.g. 0,1 (default all)")
    track.add_argument("--obj-id", dest="obj_id", type=_object_ids,
                       help="the object (default: the smallest id with a mesh); several, comma-separated (1,2), or 'all' "
                       "(every object with a first pose): tracked jointly, each hiding the others' lines (rigid only)")
    track.add_argument("--video", help="overlay: an .mp4/.avi/.mov/.mkv file, or else a folder of PNGs (views side by side)")
    track.add_argument("--fps", type=_number(float, 0, low_open=True), default=10.0, help="overlay video frame rate (default 10)")
    track.add_argument("--reset-on-failure", dest="reset_on_failure", action="store_true",
                       help="RBOT protocol: beyond 5 cm / 5° of scene_gt.json, count a failure and restart from the truth")
    track.add_argument("--recover", action=argparse.BooleanOptionalAction, default=None,
                       help="after a LOST frame, search for the object (SIFT keyframes + PnP, then pose hypotheses scored "
                       "on the lines) and restart from what is found (status RECOVERED); rigid objects with the line "
                       "modality; on by default, except with --reset-on-failure and several objects "
                       "(experiments/results/recovery.md)")
    track.add_argument("--init-pose", dest="init_pose", metavar="POSE", action="append",
                       help="first pose, model → first view's camera (mm), instead of scene_gt.json's (or of --init-points): "
                       "a .npy/.json/.txt file or 12 (3x4) / 16 (4x4) numbers, row-major, comma-separated; once per "
                       "object when several are tracked")
    track.add_argument("--max-frames", dest="max_frames", metavar="N", type=_number(int, 1), help="track only the first N frames")
    track.add_argument("--joint-limits", dest="joint_limits", action="store_true",
                       help="articulated (URDF) models: keep the joints within the URDF's limits (off: the method uses no priors)")
    track.add_argument("--region", choices=region_choices(), default=None,
                       help="the region modality that 'region' in --cues means (default auto: the correspondence lines, for a rigid object and a chain; "
                       "levelset: the paper's dense level set)")
    track.add_argument("--working-shape", dest="working_shape", metavar="HxW|native", type=_working_shape, default="default",
                       help="fixed working resolution of the crops (one compiled step whatever the object's size on "
                       "screen), or 'native' for crops at the frame's resolution in size classes (default: the "
                       "tracker's, jaxtrack.track.TrackerConfig.working_shape)")
    track.add_argument("--pose-prior", dest="pose_prior", metavar="R,T[,RA,TA,F]", type=_prior_pair,
                       help="the refinement's pose prior: relative stiffnesses (rotation, translation), optionally "
                       "absolute ones and F = 1 to pull toward each round's start (M3T) instead of the prediction "
                       "(default: jaxtrack.track.DEFAULT_POSE_PRIOR)")
    track.add_argument("--late-rounds", dest="late_rounds", metavar="K,F[,T]", type=_late_rounds,
                       help="the flow and SIFT rows count fully in the refinement's first K rounds and x F after, on frames "
                       "after one of confidence >= T (default: every round, the method; 3,0.3,0.9 is the measured opt-in "
                       "for footage whose contour you trust: README 'The late rounds only after a confident frame')")
    track.add_argument("--no-cache", action="store_true", help="do not use the on-disk caches of compiled and traced programs ($JAXTRACK_CACHE_DIR)")
    track.add_argument("--quiet", action="store_true", help="no progress bar")
    track.set_defaults(func=_cmd_track)

    bench = sub.add_parser(
        "bench",
        help="track every sequence of a dataset (RBOT, BCOT or BOP layout) on Ray workers; tables of the results",
        description="Track each sequence of DATASET from its first ground-truth pose under a protocol and evaluate it: "
        "the success rate at 5 cm / 5° with and without RBOT resets at each frame step S, ADD / ADD-S AUC (0-10 cm) and "
        "ms per frame, per object x variant and overall. Writes OUT/runs/<sequence>/S<S>[-resets].csv (+ frames.jsonl and "
        "the figures), OUT/bench.md, bench.csv and bench.png. Runs on a local Ray instance by default (one process "
        "per CPU, one XLA thread each; pip install 'jaxtrack[bench]'), on a cluster with --address, or in this process "
        "with --workers 0. Resumable: run the same command again and the finished sequences are skipped; a sequence "
        "that fails is reported and the others finish.",
    )
    bench.add_argument("dataset", metavar="DATASET", help="the dataset folder (RBOT's layout, BCOT's, or BOP sequence "
                       "folders; see --layout)")
    bench.add_argument("-o", "--out", help="output folder (default ./bench-<DATASET name>); an earlier bench's folder "
                       "is resumed")
    bench.add_argument("--protocol", choices=("rbot", "bop"), default="rbot",
                       help="rbot: frame steps with and without resets (default); bop: every frame, no resets")
    bench.add_argument("--layout", choices=("auto", "rbot", "bcot", "bop"), default="auto",
                       help="the dataset's layout (default: found from its files)")
    bench.add_argument("--frame-steps", dest="frame_steps", type=_step_list, default=[1], metavar="S[,S...]",
                       help="track every S-th frame (RBOT's frame-rate protocol), e.g. 1,2,3,4 (default 1)")
    bench.add_argument("--resets", choices=("both", "on", "off"),
                       help="RBOT resets (restart from the truth after a frame beyond 5 cm / 5°): both runs, only with, "
                       "only without (default both for rbot, off for bop)")
    bench.add_argument("--objects", type=_name_list, help="only these objects, comma-separated")
    bench.add_argument("--variants", type=_name_list, help="only these variants (RBOT: a_regular, b_dynamiclight, "
                       "c_noisy, d_occlusion; BCOT: scenes; BOP: sequence folders)")
    bench.add_argument("--workers", type=_number(int, 0), help="Ray worker processes (default: one per CPU of this "
                       "machine, or of the cluster with --address); 0: one after another in this process, without Ray")
    bench.add_argument("--address", help="join a running Ray cluster (host:port of `ray start --head`, or auto); every "
                       "node must see DATASET and -o at the same paths")
    bench.add_argument("--timeout-min", dest="timeout_min", type=_number(float, 0, low_open=True), metavar="M",
                       help="on Ray: after M minutes report the runs not finished as failed and stop (run the same "
                       "command again to continue)")
    bench.add_argument("--cues", type=_cue_list, default=CUE_CHOICES, help="as jaxtrack track (default region,flow,sift)")
    bench.add_argument("--region", choices=region_choices(), default=None, help="as jaxtrack track")
    bench.add_argument("--working-shape", dest="working_shape", metavar="HxW|native", type=_working_shape,
                       default="default", help="as jaxtrack track")
    bench.add_argument("--pose-prior", dest="pose_prior", metavar="R,T[,RA,TA,F]", type=_prior_pair, help="as jaxtrack track")
    bench.add_argument("--late-rounds", dest="late_rounds", metavar="K,F[,T]", type=_late_rounds, help="as jaxtrack track")
    bench.add_argument("--recover", action=argparse.BooleanOptionalAction, default=None,
                       help="as jaxtrack track (on by default for the runs without resets)")
    bench.add_argument("--max-frames", dest="max_frames", metavar="N", type=_number(int, 2),
                       help="track only the first N frames of each sequence (after the frame step)")
    bench.add_argument("--no-cache", action="store_true", help="do not use the on-disk caches of compiled and traced programs ($JAXTRACK_CACHE_DIR)")
    bench.add_argument("--quiet", action="store_true", help="no progress bar")
    bench.set_defaults(func=_cmd_bench)

    pick = sub.add_parser(
        "pick",
        help="click the image points of given model points on a frame: writes the file --init-points reads",
        description="Shows a frame of a video file, image folder or image and asks for one click per model point, in "
        f"order; writes {POINTS_FORMAT} as JSON. Needs matplotlib and a display; without them it writes the frame as a PNG "
        "and explains how to write the file by hand.",
    )
    pick.add_argument("input", metavar="INPUT", help="a video file, a folder of images or an image")
    pick.add_argument("--model-points", dest="model_points", required=True, metavar="FILE",
                      help="≥ 4 model points (mesh units): a JSON list of [x, y, z], or a CSV / text file of rows x,y,z")
    pick.add_argument("-o", "--out", required=True, help="the points file to write (.json)")
    pick.add_argument("--frame", type=_number(int, 0), default=0, help="which frame (default 0, the first)")
    pick.set_defaults(func=_cmd_pick)

    evaluate = sub.add_parser(
        "eval",
        help="errors of a results CSV against a sequence's ground truth (markdown tables)",
        description="Per frame and on average: rotation error (deg), translation error (mm), ADD and ADD-S (mm, "
        "and the rate below 10% of the model diameter), the 5 cm / 5° success rate, and how well the tracker's "
        "status (from RESULTS.frames.jsonl, when present) predicted the frames beyond 5 cm / 5°.",
    )
    evaluate.add_argument("results", metavar="RESULTS.csv", help="BOP results CSV (jaxtrack track -o)")
    evaluate.add_argument("sequence", metavar="SEQ", help="the sequence folder with scene_gt.json")
    evaluate.add_argument("--obj-id", dest="obj_id", type=_number(int, 0), help="the object (default: the only one in the CSV)")
    evaluate.add_argument("--camera", type=_number(int, 0), help="view (scene_id) whose rows are evaluated (default: the first)")
    evaluate.add_argument("--summary", action="store_true", help="no per-frame table")
    evaluate.set_defaults(func=_cmd_eval)

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
    synth.add_argument("--appearance", choices=("texture", "photo", "flat", "parts", "suit"),
                       help="rigid: texture | photo | flat; articulated: parts (a colour per part) | photo | suit")
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
    synth.add_argument("--urdf", help="articulated: a URDF robot moving along smooth random joint trajectories")
    synth.add_argument("--package-dir", dest="package_dir", action="append",
                       help="folder that package:// mesh paths of --urdf resolve against (repeatable)")
    synth.add_argument("--geometry", choices=("visual", "collision"), default="visual", help="--urdf meshes to use")
    synth.add_argument("--step-deg", dest="step_deg", type=_number(float, 0), help="--urdf: largest joint change per frame")
    synth.add_argument("--mocap", nargs=2, metavar=("ASF", "AMC"),
                       help="articulated: the 26-DoF body model of a CMU skeleton driven by its motion (4 cameras)")
    synth.add_argument("--fps", type=_number(int, 1), help="--mocap: frame rate to keep of the 120 frames/s motion")
    synth.add_argument("--rbot", type=_name_list, metavar="OBJECTS",
                       help="write a dataset in the RBOT dataset's layout instead (for jaxtrack bench): these objects "
                       "(box, teapot, cracker_box, milk_truck or mesh files, comma-separated) on one trajectory")
    synth.add_argument("--variants", type=_name_list,
                       help="--rbot: which of a_regular, b_dynamiclight, c_noisy (default a_regular,c_noisy)")
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
    flow.add_argument("--eta", type=_number(float, 0, 1, low_open=True, high_open=True), default=cfg.eta, help=f"pyramid factor η (default {cfg.eta})")
    flow.add_argument("--warps", type=_number(int, 1), default=cfg.warps, help=f"warps per level (default {cfg.warps})")
    flow.add_argument("--lagged", type=_number(int, 1), default=cfg.lagged, help=f"lagged-nonlinearity iterations per warp (default {cfg.lagged})")
    flow.add_argument("--sor", type=_number(int, 1), default=cfg.sor_iters, help=f"SOR sweeps per lagged iteration (default {cfg.sor_iters})")
    flow.add_argument("--median", type=int, default=cfg.median, choices=(0, 3, 5), help=f"median filter side, 0 = off (default {cfg.median})")
    flow.add_argument("--median-every-warp", dest="median_every_warp", action=argparse.BooleanOptionalAction,
                      default=cfg.median_every_warp, help="median after every warp instead of after every pyramid level")
    flow.add_argument("--sigma", type=_number(float, 0), default=cfg.presmooth_sigma, help=f"pre-smoothing σ in px (default {cfg.presmooth_sigma})")
    flow.add_argument("--grey", action="store_true", help="convert colour frames to grey first")
    flow.add_argument("--no-cache", action="store_true", help="do not use the on-disk caches of compiled and traced programs ($JAXTRACK_CACHE_DIR)")
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
    except BrokenPipeError:  # output piped into `head` and cut: not a user error (Python docs' recipe)
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1
    except (ValueError, OSError) as e:  # every input check in jaxtrack raises these, naming what is wrong
        print(f"jaxtrack {args.command}: error: {e}", file=sys.stderr)
        return 2
    except StatusError as e:  # the computation ran but reported a failure status
        print(f"jaxtrack {args.command}: {e}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
