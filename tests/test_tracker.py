"""The tracker: one compiled step over a sequence, statuses instead of exceptions, errors at the edge.

One small synthetic sequence (textured box, 160x120) and one compiled configuration shared by the
tests (session fixtures: under xdist the tests using them share the group "small_tracker", so one
worker builds them once even when tests of other modules run in between), so the suite pays the
step's compilation once.
"""

import copy
import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxtrack as jt
from jaxtrack.geometry import make_transform, rotation_error_deg, so3_exp
from jaxtrack.render import make_mesh
from jaxtrack.track import Tracker, TrackerConfig


@pytest.fixture(scope="session")
def sequence():
    from jaxtrack.synth import SynthConfig, render_sequence

    cfg = SynthConfig(object="box", appearance="photo", texture_photo="astronaut", size_mm=160, motion="random",
                      step_px=3, step_deg=1.5, frames=4, width=160, height=120, focal=175, background="coffee", seed=3)
    seq = render_sequence(cfg)
    tm = seq["mesh"]
    return {
        "mesh": make_mesh(tm.vertices, tm.faces),
        "camera": jt.make_camera(seq["K"], 160, 120),
        "images": seq["images"][0].astype(np.float32),
        "T": seq["T_cam_obj"][0],
    }


@pytest.fixture(scope="session")
def tracker(sequence):
    """The paper's configuration: the dense level set with flow and SIFT (the default for rigid objects is the
    line modality, tested on the tea box below)."""
    return Tracker(sequence["mesh"], sequence["camera"], config=TrackerConfig(region_modality="levelset"))


@pytest.fixture(scope="session")
def tracked(sequence, tracker):
    state = tracker.start(sequence["images"][0], sequence["T"][0])
    before = eqx.debug.get_num_traces(jt.track._step.track_step)
    results = []
    for k in range(1, len(sequence["images"])):
        state, result, info = tracker.step(state, sequence["images"][k])
        results.append((result, info))
    traces = eqx.debug.get_num_traces(jt.track._step.track_step) - before
    crop_classes = {info["crop_shape"] for _, info in results}
    return results, traces, crop_classes, state


@pytest.mark.xfail(
    strict=True,
    reason="the region cue cannot segment this 50 px textured box from the similar coffee background at "
    "160x120 (the data term points the right way on only 56-77% of the pixels it should move) and its "
    "rows pull the pose off; measured 5.0° rotation error after the first frame with the default flow factor "
    "0.1 (2.7° at factor 1)",
)
@pytest.mark.xdist_group("small_tracker")
def test_tracks_a_short_textured_sequence(sequence, tracked):
    results, _, _, _ = tracked
    for k, (result, _) in enumerate(results, start=1):
        T = np.asarray(result.T_world_root, np.float64)
        assert int(result.status) in (jt.Status.OK, jt.Status.UNCERTAIN), jt.Status(int(result.status)).name
        assert np.all(np.isfinite(T))
        # Bounds from measurement on this sequence (all cues): well inside 2° / 5 mm.
        assert float(rotation_error_deg(T[:3, :3], sequence["T"][k][:3, :3])) < 2.0
        assert np.linalg.norm(T[:3, 3] - sequence["T"][k][:3, 3]) < 5.0
        counts = np.asarray(result.counts)
        assert counts.shape == (1, 3) and counts[0, 0] > 0 and counts[0, 1] > 0  # region and flow rows
        assert 0.0 <= float(result.confidence) <= 1.0


@pytest.mark.xdist_group("small_tracker")
def test_one_compilation_per_crop_class(tracked):
    _, traces, crop_classes, _ = tracked
    assert traces == len(crop_classes)


@pytest.mark.xdist_group("small_tracker")
def test_the_renders_of_a_closed_mesh_skip_its_back_faces(sequence, tracker, tracked, monkeypatch):
    assert tracker.cull_backfaces and tracker.plan.cull_backfaces
    assert tracker.crop_plan is None or tracker.crop_plan.cull_backfaces
    monkeypatch.setenv("JAXTRACK_CULL_BACKFACES", "0")
    assert not Tracker(sequence["mesh"], sequence["camera"]).cull_backfaces
    v, f = np.asarray(sequence["mesh"].vertices), np.asarray(sequence["mesh"].faces)
    monkeypatch.delenv("JAXTRACK_CULL_BACKFACES")
    assert not Tracker(make_mesh(v, f[:-1]), sequence["camera"]).cull_backfaces  # open: its inside may show


@pytest.mark.xdist_group("small_tracker")
def test_object_leaving_the_image_is_a_status_not_a_crash(sequence, tracker, tracked):
    *_, state = tracked
    # Teleport the state's pose far to the side: the object is no longer in the image.
    shift = make_transform(jnp.eye(3), jnp.array([2000.0, 0.0, 0.0]))
    gone = eqx.tree_at(lambda s: s.T_world_root, state, shift @ state.T_world_root)
    _, result, _ = tracker.step(gone, sequence["images"][-1])
    assert int(result.status) in (jt.Status.OUT_OF_VIEW, jt.Status.LOST)
    assert np.all(np.isfinite(np.asarray(result.T_world_root)))
    # Behind the camera.
    flip = make_transform(so3_exp(jnp.array([0.0, np.pi, 0.0])), jnp.zeros(3))
    behind = eqx.tree_at(lambda s: s.T_world_root, state, flip @ state.T_world_root)
    _, result, _ = tracker.step(behind, sequence["images"][-1])
    assert int(result.status) == jt.Status.OUT_OF_VIEW
    assert np.all(np.isfinite(np.asarray(result.T_world_root)))


@pytest.mark.xdist_group("small_tracker")
def test_bad_input_names_the_problem(sequence, tracker):
    images, T = sequence["images"], sequence["T"]
    with pytest.raises(ValueError, match="frames must have shape"):
        tracker.start(images[0][:100], T[0])
    with pytest.raises(ValueError, match="rigid"):
        tracker.start(images[0], T[0] * 2.0)
    behind = T[0].copy()
    behind[2, 3] = -behind[2, 3]
    with pytest.raises(ValueError, match="behind"):
        tracker.start(images[0], behind)
    with pytest.raises(ValueError, match="non-finite"):
        tracker.start(np.full_like(images[0], np.nan), T[0])
    with pytest.raises(TypeError, match="Mesh"):
        Tracker(np.zeros((3, 3)), sequence["camera"])
    with pytest.raises(ValueError, match="cues"):
        TrackerConfig(cues=("region", "colour"))
    with pytest.raises(ValueError, match="depth_invariance"):
        TrackerConfig(depth_invariance="yes")


def test_a_chain_solves_eq_4_as_it_is_and_refuses_a_depth_scaling_it_would_not_apply(sequence):
    """A chain's solves sum their rows per part once (no depth scaling: `TrackerConfig.depth_invariance` resolves to
    False), so parameters asking for a depth scaling are refused, naming the field, unless the config asks for it."""
    chain = jt.synth.demo_chain(2, dtype=jnp.float32)
    assert TrackerConfig().resolved(articulated=True).depth_invariance is False
    assert TrackerConfig().resolved(articulated=False).depth_invariance is True
    params = jt.track.default_params(chain, (64, 64))
    assert float(params.depth_invariant) == 0.0
    scaled = eqx.tree_at(lambda p: p.depth_invariant, params, jnp.asarray(1.0))
    with pytest.raises(ValueError, match="params.depth_invariant must be 0"):
        Tracker(sequence["mesh"], sequence["camera"], model=chain, params=scaled)
    tracker = Tracker(sequence["mesh"], sequence["camera"], model=chain, params=scaled,
                      config=TrackerConfig(depth_invariance=True))
    assert tracker.config.depth_invariance is True
    # Parameters passed later are checked too (NaN and negative p read as 0, as the solver clips them), and a rigid
    # object's tracker told not to scale has defaults that say so.
    chain_tracker = Tracker(sequence["mesh"], sequence["camera"], model=chain)
    assert chain_tracker._checked(eqx.tree_at(lambda p: p.depth_invariant, params, jnp.asarray(jnp.nan))) is not None
    assert chain_tracker._checked(eqx.tree_at(lambda p: p.depth_invariant, params, jnp.asarray(-1.0))) is not None
    with pytest.raises(ValueError, match="params.depth_invariant must be 0"):
        chain_tracker.step(None, None, params=eqx.tree_at(lambda p: p.depth_invariant, params, jnp.full((3,), 0.5)))
    rigid = Tracker(sequence["mesh"], sequence["camera"], config=TrackerConfig(depth_invariance=False))
    assert float(rigid.params_for((64, 64)).depth_invariant) == 0.0
    assert float(Tracker(sequence["mesh"], sequence["camera"]).params_for((64, 64)).depth_invariant) == 1.0


@pytest.mark.xdist_group("small_tracker")
def test_vmap_over_cue_weights_equals_separate_runs(sequence, tracker, tracked):
    """One compiled step maps over 4 weight settings of the three cues; each equals its own run through
    `Tracker.step` (whose compiled step the `tracked` fixture already built: only the batched program is
    new here)."""
    from jaxtrack.track import default_params, track_step

    state = tracker.start(sequence["images"][0], sequence["T"][0])
    frames = tracker.check_frames(sequence["images"][1])
    offsets, crop_shape = tracker.crop(state.T_world_root, state.theta)
    matches = tracker.matches(state, frames)
    flow = jnp.array([0.5, 4.0, 0.5, 4.0])
    sift = jnp.array([0.5, 0.5, 20.0, 20.0])
    base = default_params(tracker.model, crop_shape, tracker.dtype)
    batched = eqx.tree_at(lambda p: (p.weights.flow, p.weights.sift), base, (flow, sift))
    axes = eqx.tree_at(lambda p: (p.weights.flow, p.weights.sift), jax.tree.map(lambda _: None, base), (0, 0),
                       is_leaf=lambda x: x is None)
    setup = tracker.setup()
    # Compiled with the options the tracker's own programs take (`jaxtrack._exported.compiler_options`: the suite's
    # quick build), which `eqx.filter_jit` cannot pass: the arrays traced, the rest static.
    from jaxtrack._exported import _jit_options, compiler_options

    arrays, rest = eqx.partition((setup, state, jnp.asarray(frames), matches, jnp.asarray(offsets), batched), eqx.is_array)

    @functools.partial(jax.jit, static_argnums=1, **_jit_options(compiler_options()))
    def swept(arrays, rest):
        return jax.vmap(track_step, in_axes=(None, None, None, None, None, axes, None))(*eqx.combine(arrays, rest), crop_shape)

    _, many = swept(arrays, rest)
    poses = []
    for i in range(len(flow)):
        one = eqx.tree_at(lambda p: (p.weights.flow, p.weights.sift), base, (flow[i], sift[i]))
        _, result, info = tracker.step(state, sequence["images"][1], params=one)
        assert info["crop_shape"] == crop_shape
        # float32 with batched reductions in another order, and the region cue's contour pixels are a discrete
        # set: one pixel more or less in a batched program (measured: 118 vs 117 contour rows for one setting)
        # moves this weakly constrained box by up to 4e-4 in a rotation entry (0.02°) and 0.2 mm; 1e-3 and
        # 0.5 mm allowed.
        np.testing.assert_allclose(np.asarray(many.T_world_root[i])[:3, :3], np.asarray(result.T_world_root)[:3, :3], atol=1e-3)
        np.testing.assert_allclose(np.asarray(many.T_world_root[i])[:3, 3], np.asarray(result.T_world_root)[:3, 3], atol=0.5)
        assert int(many.status[i]) == int(result.status)
        poses.append(np.asarray(result.T_world_root))
    # The weights matter: the settings do not all give the same pose.
    assert max(np.abs(p - poses[0]).max() for p in poses) > 1e-3


def _arm_urdf(path):
    """A 3-link, 2-joint arm (boxes 110 / 80 / 70 mm long, revolute about z) written as a URDF."""
    import trimesh

    from jaxtrack.io import RobotDescription, RobotJoint, RobotLink, write_urdf

    links, joints = [], []
    for k, (x0, x1) in enumerate(((-60.0, 50.0), (50.0, 130.0), (130.0, 200.0))):
        side = 2 * (24.0 - 4 * k)
        box = trimesh.creation.box(extents=(x1 - x0, side, side))
        start = 0.0 if k == 0 else (-60.0, 50.0, 130.0)[k]  # the link frame sits on its joint
        box.apply_translation(((x0 + x1) / 2 - start, 0.0, 0.0))
        links.append(RobotLink(f"link{k}", np.asarray(box.vertices), np.asarray(box.faces)))
        if k:
            T = np.eye(4)
            T[0, 3] = 50.0 if k == 1 else 80.0
            joints.append(RobotJoint(f"joint{k}", "revolute", f"link{k - 1}", f"link{k}", T, np.array([0.0, 0.0, 1.0]),
                                     -2.0, 2.0))
    return write_urdf(RobotDescription("arm", tuple(links), tuple(joints)), path)


@pytest.mark.heavy
def test_tracks_a_two_joint_arm_from_urdf_with_two_cameras(tmp_path):
    """Several cameras share one state χ = (ξ, Θ), and a chain is tracked like a rigid object: a 2-joint
    arm read from a URDF, rendered by the independent ray caster (a flat colour per link over the gravel
    photo) for two cameras, tracked by `track_sequence` with region + flow; the joints go to NAME.joints.csv.

    Measured over 4 frames with the correspondence lines (the default for chains): root up to 2.91° / 1.75 mm,
    joints up to 0.13°; with the level set before: 2.70° / 1.57 mm, 3.05° (bounds with a margin). With the level
    set, the same arm with a photo glued to the links (the region cue's weak case, see the xfail above) drifted to
    11.9°, and with flat colours over the red coffee photo the joints to 19°."""
    from jaxtrack.io import read_sequence, read_urdf
    from jaxtrack.synth import ArticulatedSynthConfig, write_articulated_sequence
    from jaxtrack.track import pose_errors, read_joint_results, track_sequence, write_tracking_results

    arm = read_urdf(_arm_urdf(tmp_path / "arm.urdf"))
    assert arm.joint_names == ("joint1", "joint2") and arm.model.num_parts == 3
    T = np.stack([np.asarray(jt.se3_exp(jnp.asarray([3.0 * k, 2.0 * k, 0.0, 0.3 + 0.015 * k, 0.2, 0.1 - 0.01 * k])),
                             np.float64) for k in range(5)])
    theta = np.array([[0.35 + 0.04 * k, -0.4 + 0.03 * k] for k in range(5)])
    cfg = ArticulatedSynthConfig(cameras=2, width=160, height=120, focal=190.0, distance=550.0, appearance="parts",
                                 background="gravel")
    root = write_articulated_sequence(arm, T, theta, cfg, tmp_path / "seq")
    seq = read_sequence(root)
    run = track_sequence(seq, cues=("region", "flow"), progress=False)
    assert all(s in ("OK", "UNCERTAIN") for s in run.status), run.status
    assert np.all(run.counts[1:, :, :2] > 0)  # region and flow rows in both cameras
    write_tracking_results(run, tmp_path / "out" / "arm.csv")
    im_ids, names, joints = read_joint_results(tmp_path / "out" / "arm.joints.csv")
    assert names == arm.joint_names and im_ids == list(range(5))
    rot, trans = pose_errors(run.T_cam_obj(0), seq.views[0].T_cam_obj[1])
    err = np.degrees(np.abs(joints - theta))
    print(f"arm after 4 frames: root {rot[-1]:.2f}° {trans[-1]:.2f} mm, joints {err[-1].round(2)}°")
    assert rot.max() < 4.0 and trans.max() < 4.0 and err.max() < 5.0, (rot, trans, err)


@pytest.mark.heavy
def test_tracks_the_teabox_on_real_video(shared_data):
    """The rendered ViSP tea box (the first 16 of its 49 frames of 640x480) with the default configuration:
    correspondence lines + flow + SIFT.

    Bounds from measurement on this machine (all 49 frames, `experiments/real_sequences.py`: mean 0.61° and
    1.25 mm at the default 96x128 working resolution, 0.45° / 1.13 mm with native crops
    (experiments/results/working_resolution.md), every frame within 5 cm / 5°; the level set with flow and SIFT
    before it: mean 0.59° / 2.46 mm,
    every frame within 0.70° / 3.36 mm; DLR M3T: 0.32° / 2.11 mm mean with ORB keypoints, 0.85° / 2.09 mm
    region only), with a margin. The whole sequence is in the README's tea-box table (`jaxtrack track`).
    """
    from jaxtrack.io import read_sequence
    from jaxtrack.track import pose_errors, track_sequence

    seq = read_sequence(shared_data / "sequences" / "visp_teabox")
    run = track_sequence(seq, progress=False, max_frames=16)
    gt = seq.views[0].T_cam_obj[run.obj_id][:16]
    rot, trans = pose_errors(run.T_cam_obj(0), gt)
    assert len(rot) == 16 and np.all(np.isfinite(rot)) and np.all(np.isfinite(trans))
    assert all(s in ("OK", "UNCERTAIN") for s in run.status), run.status
    # These 16 frames: 1.04° max, 0.79° mean, 1.9 mm max (SIFT detected at 256 px; 1.01° / 0.78° with native SIFT).
    assert rot.max() < 1.25 and trans.max() < 5.0, (rot.max(), trans.max())
    assert rot[1:].mean() < 0.95 and trans[1:].mean() < 3.5, (rot[1:].mean(), trans[1:].mean())
    assert np.all(run.counts[1:, 0, :2] > 0)  # region and flow rows in every frame


@pytest.mark.heavy
def test_line_modality_tracks_the_teabox_in_one_compilation(shared_data):
    """Region only on correspondence lines (a 642-view model), the tea box's first 16 frames: no crop size
    classes (whole frames), one trace for every frame, rows tagged LINES, a confidence from the lines.

    Bounds from measurement (all 49 frames with the default 2562-view model, `experiments/real_sequences.py`:
    0.22° / 1.07 mm mean, every frame within 5 cm / 5°; DLR M3T 0.70° / 2.1 mm region only), with a margin.
    """
    from jaxtrack.cues.lines import LineRegion
    from jaxtrack.io import read_sequence
    from jaxtrack.track import pose_errors, track_sequence

    seq = read_sequence(shared_data / "sequences" / "visp_teabox")
    before = eqx.debug.get_num_traces(jt.track._step.track_step)
    run = track_sequence(seq, config=TrackerConfig(cues=(LineRegion(subdivisions=3),)), progress=False, max_frames=16)
    assert eqx.debug.get_num_traces(jt.track._step.track_step) - before == 1
    assert all(c == (480, 640) for c in run.crops[1:])
    rot, trans = pose_errors(run.T_cam_obj(0), seq.views[0].T_cam_obj[run.obj_id][:16])
    print(f"lines, tea box 16 frames: rot mean {rot[1:].mean():.2f} max {rot.max():.2f}°, trans mean "
          f"{trans[1:].mean():.2f} max {trans.max():.2f} mm, confidence {run.confidence[1:].round(2)}")
    assert rot.max() < 0.8 and trans.max() < 3.0, (rot.max(), trans.max())
    assert rot[1:].mean() < 0.5 and trans[1:].mean() < 2.0, (rot[1:].mean(), trans[1:].mean())
    assert run.counts.shape[1:] == (1, 1) and np.all(run.counts[1:, 0, 0] > 50)
    assert all(s == "OK" for s in run.status) and np.all(run.confidence[1:] > 0.8)


@pytest.fixture(scope="session")
def approaching_sequence(tmp_path_factory):
    """A textured box flying toward the camera: 3x larger on screen after 6 frames (160x120)."""
    from jaxtrack.synth import SynthConfig, render_sequence

    n, distance = 7, 600.0
    eye = np.array([0.0, -0.35 * distance, -distance])  # the synthetic camera's centre (it looks at the origin)
    poses = np.repeat(np.eye(4)[None], n, 0)
    for k in range(n):
        poses[k, :3, :3] = np.asarray(so3_exp(jnp.array([0.3 + 0.02 * k, 0.5, 0.03 * k])))
        poses[k, :3, 3] = (0.67 * k / (n - 1)) * eye
    path = tmp_path_factory.mktemp("approach") / "poses.npy"
    np.save(path, poses)
    cfg = SynthConfig(object="box", appearance="photo", texture_photo="astronaut", size_mm=110, motion="file",
                      pose_file=str(path), frames=n, width=160, height=120, focal=175, distance=distance,
                      background="coffee", seed=3)
    seq = render_sequence(cfg)
    tm = seq["mesh"]
    return {"mesh": make_mesh(tm.vertices, tm.faces), "camera": jt.make_camera(seq["K"], 160, 120),
            "images": seq["images"][0], "T": seq["T_cam_obj"][0]}


def test_working_resolution_one_program_while_the_object_grows_3x(approaching_sequence):
    """With a fixed working resolution the crops are resampled with the scale as data: every frame after the
    first runs the step compiled for frame 1 while the object grows 3x on screen, and it is tracked."""
    seq = approaching_sequence
    # Lines and SIFT: the flow rows of this approach pull the rotation away at any resolution (native crops too:
    # 1.5° → 38° over 6 frames, measured; its smoothness resists the expansion), which is not what this checks.
    tracker = Tracker(seq["mesh"], seq["camera"], config=TrackerConfig(cues=("lines", "sift"), working_shape=(48, 64)))
    state = tracker.start(seq["images"][0], seq["T"][0])
    state, result, info = tracker.step(state, seq["images"][1])
    before = eqx.debug.get_num_traces(jt.track._step.track_step)
    scales, rot, trans = [float(info["scales"][0])], [], []
    for k in range(2, len(seq["images"])):
        state, result, info = tracker.step(state, seq["images"][k])
        scales.append(float(info["scales"][0]))
        T = np.asarray(result.T_world_root)
        rot.append(float(rotation_error_deg(T[:3, :3], seq["T"][k][:3, :3])))
        trans.append(float(np.linalg.norm(T[:3, 3] - seq["T"][k][:3, 3])))
        assert info["crop_shape"] == (48, 64)
    assert eqx.debug.get_num_traces(jt.track._step.track_step) == before  # no compile after the first frame
    from jaxtrack.cues.levelset import projected_boxes

    widths = [float(np.diff(projected_boxes(tracker.mesh, tracker.cameras, jnp.asarray(T, tracker.dtype))[0, ::2])[0])
              for T in (seq["T"][1], seq["T"][-1])]
    print(f"object width {widths[0]:.0f} → {widths[1]:.0f} px, scales {np.round(scales, 2)}, rot {np.round(rot, 2)}°, "
          f"trans {np.round(trans, 1)} mm")
    assert widths[1] > 2.5 * widths[0], widths
    assert scales[-1] > 1.5 * scales[0] and np.all(np.diff(scales) >= 0), scales  # the window followed it
    assert max(rot) < 6.0 and max(trans) < 5.0, (rot, trans)  # measured 4.2° / 2.0 mm at most


@pytest.mark.xdist_group("lines_sift")
def test_working_resolution_at_scale_one_gives_the_native_pose(sequence):
    """The sequence's 50 px box fits a 96x128 working window at scale 1: the resampled crops (float offsets,
    whole-pixel offsets) then hold the native pixels, and lines + SIFT with the occlusion map give the native
    crops' poses within 0.2° / 0.5 mm on every frame (the issue's bound), through the scaled-window code path
    (crop cameras, window ↔ frame mapping, resampled crops, the crops' raster plan). Flow is left out to keep
    the test's two compilations small; it reads the same crops."""
    poses = {}
    for shape in (None, (96, 128)):
        tracker = Tracker(sequence["mesh"], sequence["camera"], config=TrackerConfig(cues=("lines", "sift"), working_shape=shape))
        state = tracker.start(sequence["images"][0], sequence["T"][0])
        poses[shape] = []
        for k in range(1, len(sequence["images"])):
            state, result, info = tracker.step(state, sequence["images"][k])
            poses[shape].append(np.asarray(result.T_world_root, np.float64))
        if shape is not None:
            assert info["scales"] is not None and np.allclose(info["scales"], 1.0)
            assert tracker.crop_plan is not None
    for native, working in zip(poses[None], poses[(96, 128)]):
        assert float(rotation_error_deg(native[:3, :3], working[:3, :3])) < 0.2
        assert np.linalg.norm(native[:3, 3] - working[:3, 3]) < 0.5


def test_the_windows_follow_the_last_motion_and_hold_the_object_at_t_and_where_it_is_carried(sequence):
    """After a 54 px step of a 142 px wide box (the noisy moving camera at 640x480), the next step's windows hold the
    box at t and the box moved on by that motion (constant velocity) with the fixed margin and half the motion around
    them, instead of 1.5x the motion on every side: a smaller scale (more working pixels on the object) for the same
    coverage. Without a last motion the two rules give the same windows, and `follow_motion=False` gives them while
    the motion is kept. Host arithmetic only (no compile)."""
    camera = jt.make_camera(np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]]), 640, 480)
    tracker = Tracker(sequence["mesh"], camera, config=TrackerConfig(cues=("lines", "flow"), working_shape=(96, 128)))
    box = np.array([[200.0, 150.0, 342.0, 250.0]])  # (x0, y0, x1, y1) at t
    motion = np.array([[54.0, 6.0, 54.0, 6.0]])  # the last step's motion of each side

    def window(follows: bool, last_motion):
        tracker.crop_follows_motion = follows
        tracker.record_motion(None, None) if last_motion is None else tracker.record_motion(box, box + last_motion)
        offsets, shape, scales = tracker.windows(None, None, box)
        assert shape == (96, 128)
        (y0, x0), s = offsets[0], float(scales[0])
        return np.array([x0, y0, x0 + s * shape[1] - 1, y0 + s * shape[0] - 1]), s

    def inside(b, w):
        return b[0] >= w[0] - 0.5 and b[1] >= w[1] - 0.5 and b[2] <= w[2] + 0.5 and b[3] <= w[3] + 0.5

    still = [window(f, None) for f in (True, False)]
    assert np.allclose(still[0][0], still[1][0]) and still[0][1] == still[1][1]
    centred, s_centred = window(False, motion)
    follows, s_follows = window(True, motion)
    print(f"scale {s_centred:.2f} (box at t + 1.5x motion) -> {s_follows:.2f} (follows the motion); windows "
          f"{np.round(centred)} -> {np.round(follows)}")
    carried = box[0] + motion[0]
    for w in (centred, follows):
        assert inside(box[0], w) and inside(carried, w)
    assert s_follows < 0.8 * s_centred  # 2.34 (299 px / 128) against 3.24 (311 px / 96)
    assert inside(carried + np.array([-27.0, -27.0, 27.0, 27.0]), follows)  # half the motion more on every side
    shift = (follows[0] + follows[2]) / 2 - (box[0][0] + box[0][2]) / 2
    assert abs((centred[0] + centred[2]) / 2 - (box[0][0] + box[0][2]) / 2) < 1.0 and shift > 0.4 * motion[0][0], shift
    # A step without motion (the recovery's restart on frames t+1 → t+1) asks for the box alone, the motion kept
    tracker.crop_follows_motion = True
    offsets_alone, _, scales_alone = tracker.windows(None, None, box, follow_motion=False)
    (y0, x0), s_alone = offsets_alone[0], scales_alone[0]
    np.testing.assert_array_equal(tracker.last_box_motion, motion)
    assert np.allclose([x0, y0], still[0][0][:2]) and float(s_alone) == still[0][1], ((x0, y0, s_alone), still[0])


def test_working_resolution_flow_reaches_a_large_motion():
    """The flow pyramid at the working resolution reaches the motion of a large frame step. At 96x128 a coarsest
    level of 16 px left 3 levels, and a 12 px shift (the frame-rate experiment's 20 px / 12° step at S = 4, seen at
    scale 1.6) came out as (0.09, -1.15) px: the prediction did not move (frame_rate S = 4: 38 % success). With 8 px
    a 24 px shift (the large-motion experiment's 30 px in a crop at scale 1.25) came out as (-2.88, 1.82) px
    (measured), and the flow + SIFT prediction was worse than none (experiments/large_motion.py: all cues 3/8).
    The tracker's resolved flow settings recover it."""
    import cv2

    from jaxtrack.cues.flow import compute_flow
    from jaxtrack.geometry import rigid_model
    from jaxtrack.track._tracker import default_params

    rng = np.random.default_rng(0)
    texture = cv2.GaussianBlur(rng.uniform(0, 255, (200, 240)).astype(np.float32), (0, 0), 2.0)
    texture = np.clip((texture - texture.mean()) * 4 + 128, 0, 255)
    dy, dx = 10, 24
    first, second = texture[40:136, 40:168], texture[40 - dy:136 - dy, 40 - dx:168 - dx]  # content moves by (dx, dy)
    config = TrackerConfig().resolved(False)
    assert config.working_shape == first.shape
    flow = np.asarray(compute_flow(first, second, default_params(rigid_model(), first.shape).flow, config.flow).flow)
    median = np.median(flow[16:-16, 24:-24].reshape(-1, 2), axis=0)
    print(f"coarsest level {config.flow.min_size} px: median flow {np.round(median, 2)} (truth ({dx}, {dy}))")
    assert np.max(np.abs(median - (dx, dy))) < 0.5, median


@pytest.fixture(scope="module")
def lines_sift(sequence):
    """Lines + SIFT with the occlusion map at 96x128 (the scale-one test's configuration: one compiled step in a
    worker of group "lines_sift"): its confidence is the calibrated one (`TrackerConfig.calibrated_confidence`)."""
    from jaxtrack.track import RecoveryConfig

    config = TrackerConfig(cues=("lines", "sift"), working_shape=(96, 128), recovery=RecoveryConfig(hypotheses=True))
    tracker = Tracker(sequence["mesh"], sequence["camera"], config=config)
    state = tracker.start(sequence["images"][0], sequence["T"][0])
    state, result, _ = tracker.step(state, sequence["images"][1])
    return tracker, state, result


def _turned(state, degrees):
    """The state with its pose turned by `degrees` about a fixed axis through the object's origin."""
    axis = np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2])
    T = np.asarray(state.T_world_root)
    R = np.asarray(so3_exp(jnp.asarray(axis * np.radians(degrees), state.T_world_root.dtype)))
    turned = T.copy()
    turned[:3, :3] = T[:3, :3] @ R
    return eqx.tree_at(lambda s: s.T_world_root, state, jnp.asarray(turned, state.T_world_root.dtype))


@pytest.mark.xdist_group("lines_sift")
def test_a_pose_jump_is_flagged_in_the_frame_it_happens_and_lost_where_the_step_keeps_it(sequence, lines_sift):
    """Issue 24: a pose teleported by a jump the object did not make is flagged in that frame, where the contour
    agreement alone (the confidence up to now) still read 0.9, with a confidence well below the tracked frame's; a
    jump the step cannot pull back (50°: 42.9° left) is LOST. Teleported 40°, the step pulls it back to 10.4° and
    the frame reads UNCERTAIN at confidence 0.340 (LOST is below 0.25; 0.333 in an earlier measurement): with the crop windows that follow the motion
    (01fe831); with the old windows 11.9° and LOST at 0.227, and 11.8° at 0.215 when the Cauchy loss came (a2beddf).
    A 10-12° error whose contour agrees sits at the LOST bound (probe in this suite's settings: 40° then 50°, the
    same tracker state)."""
    tracker, state, tracked = lines_sift
    tracked_error = float(rotation_error_deg(np.asarray(tracked.T_world_root)[:3, :3], sequence["T"][1][:3, :3]))
    assert tracked_error < 5.0 and int(tracked.status) != jt.Status.LOST, (tracked_error, int(tracked.status))
    saved = dict(vars(tracker))  # the group's other tests use this tracker: its motion memory is put back after,
    saved_cache = copy.deepcopy(tracker.host_cache)  # and SIFT's keypoint cache, which the step fills in place
    try:
        outcomes = {}
        for degrees in (40.0, 50.0):
            tracker.last_box_motion = saved["last_box_motion"]
            tracker.host_cache = copy.deepcopy(saved_cache)  # both jumps from the same keypoints of frame t
            _, result, _ = tracker.step(_turned(state, degrees), sequence["images"][2], recover=False)  # its own status
            error = float(rotation_error_deg(np.asarray(result.T_world_root)[:3, :3], sequence["T"][2][:3, :3]))
            evidence = dict(zip(jt.track._step.LOSS_EVIDENCE, np.asarray(result.loss_evidence).round(3)))
            print(f"{degrees:.0f}° jump: error {error:.1f}°, {jt.Status(int(result.status)).name}, confidence "
                  f"{float(result.confidence):.3f}, evidence {evidence}")
            outcomes[degrees] = (error, int(result.status), float(result.confidence))
    finally:
        vars(tracker).clear()
        vars(tracker).update(saved)
        tracker.host_cache = saved_cache
    for degrees, (error, status, confidence) in outcomes.items():
        assert error > 5.0  # the refinement did not undo it: the frame is wrong
        assert status in (jt.Status.LOST, jt.Status.UNCERTAIN), (degrees, jt.Status(status).name)
        assert float(tracked.confidence) > confidence + 0.2, (float(tracked.confidence), confidence)
    assert outcomes[50.0][1] == jt.Status.LOST, jt.Status(outcomes[50.0][1]).name


@pytest.mark.xdist_group("lines_sift")
def test_the_loss_evidence_carries_its_running_average(sequence, lines_sift):
    """The second half of `FrameResult.loss_evidence` is the running average a · (average up to t) + (1 − a) · (the
    frame's own evidence), from zeros at `start` (the fixture's step is the first), kept in the state; the decay a
    is an array parameter (another value: no compile), and the calibrated confidence is the least of its models'
    (`LOSS_WEIGHTS`: the frame's evidence alone, and with the averages)."""
    from jaxtrack.track._step import LOSS_FRAME_EVIDENCE

    tracker, state, first = lines_sift
    n = len(LOSS_FRAME_EVIDENCE)
    params = tracker.params_for(tracker.crop_shape)
    decay = float(params.loss_evidence_decay)
    evidence = np.asarray(first.loss_evidence, np.float64)
    assert evidence.shape == (2 * n,) and np.any(evidence[:n] > 0), evidence
    np.testing.assert_allclose(evidence[n:], (1.0 - decay) * evidence[:n], rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(np.asarray(state.loss_evidence_average), evidence[n:], rtol=1e-6)
    slower = eqx.tree_at(lambda p: p.loss_evidence_decay, params, jnp.asarray(0.9, params.loss_evidence_decay.dtype))
    saved = dict(vars(tracker))  # the group's other tests use this tracker: its motion memory is put back after,
    saved_cache = copy.deepcopy(tracker.host_cache)  # and SIFT's keypoint cache, which the step fills in place
    try:
        new_state, result, _ = tracker.step(state, sequence["images"][2], params=slower, recover=False)
    finally:
        vars(tracker).clear()
        vars(tracker).update(saved)
        tracker.host_cache = saved_cache
    second = np.asarray(result.loss_evidence, np.float64)
    np.testing.assert_allclose(second[n:], 0.9 * evidence[n:] + 0.1 * second[:n], rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(np.asarray(new_state.loss_evidence_average), second[n:], rtol=1e-6)
    w = np.atleast_2d(np.asarray(params.loss_weights, np.float64))  # one logistic model per row: the least counts
    assert w.shape == (2, 1 + 2 * n) and not np.any(w[0, 1 + n:]), w  # the frame's model reads no averages
    per_model = 1.0 / (1.0 + np.exp(w[:, 0] + w[:, 1:] @ second))
    assert abs(per_model[0] - per_model[1]) > 1e-3, per_model  # else the least of them would tell nothing here
    np.testing.assert_allclose(float(result.confidence), np.min(per_model), rtol=1e-4)


@pytest.mark.xdist_group("lines_sift")
def test_the_late_rounds_without_motion_rows_need_a_confident_last_frame(sequence, lines_sift):
    """`TrackerParams.motion_late_above`: the motion rows leave the refinement after `motion_rounds` (× the late factor)
    only when the frame before read at least that confidence (`TrackerState.last_confidence`, 0 at `start`); below
    it the step is the one with the motion rows in every round. The state carries the frame's confidence on. The
    same compiled step for every gate and confidence (arrays)."""
    from jaxtrack.track._step import motion_rounds_for

    tracker, state, first = lines_sift
    assert float(state.last_confidence) == pytest.approx(float(first.confidence))
    params = tracker.params_for(tracker.crop_shape)
    dtype = params.motion_late_factor.dtype
    every = eqx.tree_at(lambda p: p.motion_rounds, params, jnp.asarray(np.inf, dtype))
    split = eqx.tree_at(lambda p: (p.motion_rounds, p.motion_late_factor), params, (jnp.asarray(1.0, dtype), jnp.zeros((), dtype)))
    gated = eqx.tree_at(lambda p: p.motion_late_above, split, jnp.asarray(0.9, dtype))
    assert float(motion_rounds_for(None, gated)) == np.inf and float(motion_rounds_for(None, split)) == 1.0
    assert float(motion_rounds_for(jnp.asarray(0.9), gated)) == 1.0 and float(motion_rounds_for(jnp.asarray(0.89), gated)) == np.inf
    saved = dict(vars(tracker))  # the group's other tests use this tracker: its motion memory is put back after,
    saved_cache = copy.deepcopy(tracker.host_cache)  # and SIFT's keypoint cache, which the step fills in place
    traces = eqx.debug.get_num_traces(jt.track.track_step)
    poses = {}
    try:
        for name, p, last in (("every", every, 0.95), ("split", split, 0.5), ("gated, sure", gated, 0.95),
                              ("gated, unsure", gated, 0.5)):
            tracker.last_box_motion = saved["last_box_motion"]
            tracker.host_cache = copy.deepcopy(saved_cache)
            s = eqx.tree_at(lambda s: s.last_confidence, state, jnp.asarray(last, state.last_confidence.dtype))
            new_state, result, _ = tracker.step(s, sequence["images"][2], params=p, recover=False)
            poses[name] = np.asarray(result.T_world_root)
            assert float(new_state.last_confidence) == pytest.approx(float(result.confidence))
    finally:
        vars(tracker).clear()
        vars(tracker).update(saved)
        tracker.host_cache = saved_cache
    assert eqx.debug.get_num_traces(jt.track.track_step) == traces
    assert np.abs(poses["every"] - poses["split"]).max() > 1e-3  # the split moves the pose: the gate has work to do
    np.testing.assert_array_equal(poses["gated, sure"], poses["split"])
    np.testing.assert_array_equal(poses["gated, unsure"], poses["every"])


@pytest.mark.xdist_group("lines_sift")
def test_confidence_falls_with_a_controlled_misalignment(sequence, lines_sift):
    """With every cue weight 0 the step cannot move the pose (no rows): its evidence and confidence are those of
    the pose it was given, turned by 0-30° from the tracked one on the same frame. The confidence falls
    monotonically with the misalignment."""
    tracker, state, _ = lines_sift
    params = tracker.params_for(tracker.crop_shape)
    frozen = eqx.tree_at(lambda p: p.weights, params, jax.tree.map(jnp.zeros_like, params.weights))  # same avals: no compile
    confidence = []
    for degrees in (0.0, 10.0, 20.0, 30.0):
        _, result, _ = tracker.step(_turned(state, degrees), sequence["images"][1], params=frozen, recover=False)
        assert np.allclose(np.asarray(result.T_world_root)[:3, :3], np.asarray(_turned(state, degrees).T_world_root)[:3, :3], atol=1e-5)
        confidence.append(float(result.confidence))
    print("confidence at 0, 10, 20, 30°:", np.round(confidence, 3))
    # measured 0.975, 0.843, 0.004, 0.000 (saturated; 0.92, 0.34, 0.001, 0.000 with the weights before a2beddf)
    assert np.all(np.diff(confidence) <= 0) and confidence[0] > confidence[1] > confidence[2], confidence
    assert confidence[0] > 0.5 > confidence[-1], confidence


@pytest.mark.xdist_group("lines_sift")
def test_the_recovery_program_is_compiled_before_a_frame_is_lost(sequence, lines_sift):
    """No frame waits for a compile after the first: the first step starts the recovery program's compile in a
    background thread (`Tracker.warm_up_recovery`, off in this suite by $JAXTRACK_RECOVERY_WARMUP=0), and a search
    after it traces nothing new."""
    from jaxtrack.track._recovery import recover_pose

    tracker, state, _ = lines_sift
    saved = dict(vars(tracker))
    saved_keyframes = None if tracker.keyframes is None else (list(tracker.keyframes.keyframes), list(tracker.keyframes.tried))
    try:
        tracker.warm_up_recovery, tracker._recovery_warmup = True, None
        first = eqx.debug.get_num_traces(recover_pose)
        new_state, _, _ = tracker.step(state, sequence["images"][2])
        thread = tracker._recovery_warmup
        assert thread is not None and thread.name == "jaxtrack-recovery-compile"
        thread.join()
        before = eqx.debug.get_num_traces(recover_pose)
        assert before == first + 1  # the warm-up traced it (this group's first use: the test runs before the others)
        found = tracker.recover(new_state, sequence["images"][3])
        assert eqx.debug.get_num_traces(recover_pose) == before
        assert np.all(np.isfinite(np.asarray(found.T_world_root)))
    finally:
        vars(tracker).clear()
        vars(tracker).update(saved)
        if saved_keyframes is not None:  # the shared keyframe model, as it was
            tracker.keyframes.keyframes, tracker.keyframes.tried = saved_keyframes


@pytest.mark.xdist_group("lines_sift")
def test_the_recovery_compile_starts_at_the_first_doubt(sequence, lines_sift):
    """The default warm-up ("doubt"): a frame reported OK starts no background compile of the search; the first frame
    reported UNCERTAIN or LOST does, before its own search (so a run that never doubts pays nothing)."""
    tracker, state, tracked = lines_sift
    saved = dict(vars(tracker))
    saved_keyframes = None if tracker.keyframes is None else (list(tracker.keyframes.keyframes), list(tracker.keyframes.tried))
    try:
        tracker.warm_up_recovery, tracker._recovery_warmup = "doubt", None
        searched_with_warmup = []  # at each search: had the frame started the background compile already?
        search = tracker._search
        tracker._search = lambda *a: (searched_with_warmup.append(tracker._recovery_warmup is not None), search(*a))[1]
        assert int(tracked.status) == jt.Status.OK
        assert not tracker._wants_recovery_warmup(tracked)
        ok_state, ok, _ = tracker.step(state, sequence["images"][2])
        assert int(ok.status) == jt.Status.OK and tracker._recovery_warmup is None
        _, jumped, _ = tracker.step(_turned(ok_state, 50.0), sequence["images"][3], recover=False)
        assert int(jumped.status) in (jt.Status.UNCERTAIN, jt.Status.LOST), jt.Status(int(jumped.status)).name
        assert tracker._recovery_warmup is None  # recover=False: this frame searches nothing, so nothing compiles for it
        _, lost, info = tracker.step(_turned(ok_state, 50.0), sequence["images"][3])
        thread = tracker._recovery_warmup
        assert thread is not None and thread.name == "jaxtrack-recovery-compile"
        assert info["recovery"] is not None or int(lost.status) == jt.Status.UNCERTAIN
        assert searched_with_warmup == ([True] if info["recovery"] is not None else []), searched_with_warmup
        thread.join()
        with pytest.raises(ValueError, match="warm_up_recovery"):
            tracker.warm_up_recovery, tracker._recovery_warmup = "always", None
            tracker._wants_recovery_warmup(lost)
    finally:
        vars(tracker).clear()
        vars(tracker).update(saved)
        if saved_keyframes is not None:
            tracker.keyframes.keyframes, tracker.keyframes.tried = saved_keyframes


@pytest.mark.xdist_group("lines_sift")
def test_the_doubt_warm_up_loads_a_search_kept_on_disk_after_the_first_frame(sequence, lines_sift, monkeypatch):
    """"doubt" with the search's program on disk (an earlier process exported it: a load, not a compile): the first
    frame reported OK starts the background warm-up, so that no first lost frame waits for the load; the disk is asked
    once per tracker, with the arguments the search takes."""
    from jaxtrack.track import _tracker

    tracker, state, _ = lines_sift
    saved = dict(vars(tracker))
    saved_keyframes = None if tracker.keyframes is None else (list(tracker.keyframes.keyframes), list(tracker.keyframes.tried))
    asked = []

    def is_kept(*args):
        asked.append(args)
        return True

    monkeypatch.setattr(_tracker._recover_pose_jit, "is_kept", is_kept)
    try:
        tracker.warm_up_recovery, tracker._recovery_warmup, tracker._recovery_kept_asked = "doubt", None, False
        ok_state, ok, _ = tracker.step(state, sequence["images"][2])
        assert int(ok.status) == jt.Status.OK
        thread = tracker._recovery_warmup
        assert thread is not None and thread.name == "jaxtrack-recovery-compile"
        assert len(asked) == 1 and asked[0][-1] is tracker.config.recovery and asked[0][1].shape == (1, *sequence["images"][2].shape)
        thread.join()
        tracker._recovery_warmup = None
        tracker.step(ok_state, sequence["images"][3])
        assert len(asked) == 1 and tracker._recovery_warmup is None  # asked once: no second warm-up from an OK frame
    finally:
        vars(tracker).clear()
        vars(tracker).update(saved)
        if saved_keyframes is not None:
            tracker.keyframes.keyframes, tracker.keyframes.tried = saved_keyframes


def test_recovery_is_on_by_default_and_the_step_program_does_not_depend_on_it(sequence):
    """Issue 24: without resets the search after a LOST frame is what runs (`TrackerConfig.recovery` on by default;
    `track_sequence` turns it off for the RBOT protocol's oracle resets, and when asked); the compiled step sees a
    config without it, so trackers with and without recovery share one step program (and one on-disk entry)."""
    from jaxtrack.track import RecoveryConfig
    from jaxtrack.track._sequence import _config_from, _recovers

    assert isinstance(TrackerConfig().recovery, RecoveryConfig) and TrackerConfig().recovers()
    assert not TrackerConfig(recovery=None).recovers()
    assert (_recovers(None, False), _recovers(None, True), _recovers(False, False), _recovers(True, True)) == (True, False, False, True)
    assert _config_from(("region", "flow", "sift"), None, "default", recovery=False).recovery is None
    on = Tracker(sequence["mesh"], sequence["camera"])
    off = Tracker(sequence["mesh"], sequence["camera"], config=TrackerConfig(recovery=None))
    assert on.config.recovers() and not off.config.recovers()
    assert on.setup().config.recovery is None and on.setup().config == off.setup().config
    assert hash(on.setup().config) == hash(off.setup().config)
    assert on.setup().config is on.setup().config  # made once per config object


@pytest.mark.xdist_group("lines_sift")
def test_hypothesis_scores_under_vmap_equal_one_at_a_time(sequence, lines_sift):
    """Issue 24: the recovery scores every hypothesis in one vmapped call; each score equals the same pose scored
    alone, and the search's own scores are those (2 references and 232 rotations each)."""
    from jaxtrack.track._recovery import RecoveryConfig, hypothesis_poses, rig_agreement

    tracker, state, _ = lines_sift
    i = tracker.recovery_modality()
    view_model, hist = tracker.prepared[i], state.modalities[i].histograms
    lines = tracker.params_for(tracker.crop_shape).lines
    frames = jnp.asarray(sequence["images"][2][None])
    config = RecoveryConfig()
    refs = jnp.stack([state.T_world_root, _turned(state, 30.0).T_world_root])
    hyps = hypothesis_poses(refs, config.rotation_offsets(), view_model.center)
    assert hyps.shape == (2 * len(config.rotation_offsets()), 4, 4)
    assert np.allclose(hyps[0], refs[0]) and np.allclose(hyps[len(config.rotation_offsets())], refs[1])
    pick = np.array([0, 5, 77, 300, 463])
    score = jax.jit(lambda T: rig_agreement(tracker.cameras, T, view_model, frames, hist, lines, config.score_scale))
    batched = np.asarray(jax.jit(jax.vmap(score))(hyps[pick]))
    alone = np.array([float(score(hyps[k])) for k in pick])
    assert np.allclose(batched, alone, atol=1e-12), (batched, alone)
    found = tracker.recover(state, sequence["images"][2], refs[0])  # references: this pose and the last one reported OK
    own = pick[pick < len(config.rotation_offsets())]
    assert np.allclose(np.asarray(found.scores)[own], alone[: len(own)], atol=1e-5)  # its frames in the tracker's dtype
    assert np.all((0.0 <= alone) & (alone <= 1.0))


@pytest.mark.xdist_group("lines_sift")
def test_an_injected_jump_is_lost_then_recovered(lines_sift):
    """Issue 24: the pose teleported 60° is LOST in its frame; the search (the first frame's SIFT keyframe, PnP) finds
    the pose, and the frame of the jump is RECOVERED within 5°; the next frame tracks on from it (OK). The box is
    nearer than in `sequence` (400 mm): at 600 mm its 22 keypoints left 6 matches, too few for PnP (12 inliers).
    Teleported 40° (as up to a2beddf), the step now pulls most of the jump back by itself (the Cauchy loss on the
    motion rows): 10.3° left, UNCERTAIN at confidence 0.31, no search, then OK at 6.1°."""
    from jaxtrack.synth import SynthConfig, render_sequence

    tracker, _, _ = lines_sift
    cfg = SynthConfig(object="box", appearance="photo", texture_photo="astronaut", size_mm=160, motion="random", step_px=3,
                      step_deg=1.5, frames=4, width=160, height=120, focal=175, background="coffee", seed=3, distance=400)
    seq = render_sequence(cfg)
    images, truth = seq["images"][0].astype(np.float32), seq["T_cam_obj"][0]
    saved = dict(vars(tracker))  # the group's other tests use this tracker: its host state is put back after
    try:
        state = tracker.start(images[0], truth[0])
        state, result, _ = tracker.step(state, images[1])
        assert int(result.status) == jt.Status.OK
        state = _turned(state, 60.0)
        statuses, errors, searched = [], [], []
        for k in (2, 3):
            state, result, info = tracker.step(state, images[k])
            statuses.append(jt.Status(int(result.status)).name)
            errors.append(float(rotation_error_deg(np.asarray(result.T_world_root)[:3, :3], truth[k][:3, :3])))
            searched.append(None if info["recovery"] is None else {key: info["recovery"][key] for key in ("source", "pnp_inliers")})
            if k == 2:  # a recovery is a new start: the running loss evidence starts over from the found pose's frame
                n = len(jt.track._step.LOSS_FRAME_EVIDENCE)
                decay = float(tracker.params_for(tracker.crop_shape).loss_evidence_decay)
                restarted = (np.asarray(state.loss_evidence_average), (1.0 - decay) * np.asarray(result.loss_evidence)[:n])
    finally:
        vars(tracker).clear()
        vars(tracker).update(saved)
    print("statuses", statuses, "errors", np.round(errors, 1), "searches", searched)
    assert searched[0] is not None and searched[0]["source"] == "keyframes"  # LOST, then found by the keyframe's PnP
    assert searched[0]["pnp_inliers"] >= 12, searched
    assert statuses == ["RECOVERED", "OK"], statuses
    assert max(errors) < 5.0, errors
    np.testing.assert_allclose(*restarted, rtol=1e-5, atol=1e-7)


@pytest.mark.xdist_group("lines_sift")
def test_a_frame_lost_while_the_search_still_compiles_does_not_wait_for_it(sequence, lines_sift, monkeypatch):
    """No frame waits for a compile after the first: lost frames wait for the hypotheses' background compile at most
    the tracker's budget (`RECOVERY_COMPILE_WAIT_S` in all; here 0.05 s), and a frame lost while it still compiles
    (a warm-up thread that ends only when released) stays LOST with its search skipped ("compiling"), nothing traced
    for it. A compile that ends within the budget is waited for and searched with; one that raised is not tried
    again in the tracking thread ("compile failed")."""
    import threading

    from jaxtrack.track._recovery import RecoveryResult, recover_pose

    tracker, state, _ = lines_sift
    saved = dict(vars(tracker))
    release = threading.Event()
    compiling = threading.Thread(target=lambda: release.wait(300.0), name="jaxtrack-recovery-compile", daemon=True)
    compiling.start()
    searched = []
    nothing_better = lambda *a, **k: searched.append(True) or RecoveryResult(
        T_world_root=state.T_world_root, score=jnp.asarray(0.5), own_score=jnp.asarray(0.9), index=jnp.asarray(1),
        scores=jnp.zeros(3), status=jnp.asarray(0))
    lost = _turned(state, 50.0)
    try:
        tracker._recovery_warmup, tracker.keyframes, tracker._recovery_wait_left = compiling, None, 0.05
        traces = eqx.debug.get_num_traces(recover_pose)
        _, result, info = tracker.step(lost, sequence["images"][2])
        assert int(result.status) == jt.Status.LOST, jt.Status(int(result.status)).name
        assert info["recovery"] is not None and info["recovery"]["skipped"] == "compiling", info["recovery"]
        assert not info["recovery"]["recovered"] and compiling.is_alive()  # the step returned without it
        assert tracker._recovery_wait_left <= 0.0  # the budget is spent: the next lost frame does not wait
        assert eqx.debug.get_num_traces(recover_pose) == traces

        monkeypatch.setattr(tracker, "recover", nothing_better)
        ending = threading.Thread(target=lambda: release.wait(0.05), name="jaxtrack-recovery-compile", daemon=True)
        ending.start()
        tracker._recovery_warmup, tracker._recovery_wait_left = ending, 60.0
        _, result, info = tracker.step(lost, sequence["images"][2])
        assert searched and "skipped" not in info["recovery"], info["recovery"]  # waited for it, then searched

        searched.clear()
        tracker._recovery_warmup_error = RuntimeError("no memory")
        _, result, info = tracker.step(lost, sequence["images"][2])
        assert not searched and info["recovery"]["skipped"].startswith("compile failed"), info["recovery"]
    finally:
        release.set()
        compiling.join()
        vars(tracker).clear()
        vars(tracker).update(saved)


@pytest.mark.xdist_group("lines_sift")
def test_a_found_pose_near_the_lost_one_needs_no_margin_and_a_flip_does(sequence, lines_sift, monkeypatch):
    """The search's pose is tried (the normal step from it, `_restart`) when it scores no worse than the lost pose's
    own refinement and lies within `RecoveryConfig.near_deg` of the lost pose; turned farther (a symmetric object's
    flips), it must beat that score by `margin`."""
    from jaxtrack.track._recovery import RecoveryResult

    tracker, state, tracked = lines_sift
    config = tracker.config.recovery
    tried = []
    monkeypatch.setattr(tracker, "keyframes", None)
    monkeypatch.setattr(tracker, "_recovery_warmup", None)  # no background compile to wait for
    monkeypatch.setattr(tracker, "_restart", lambda *args: tried.append(True) or (args[1], args[2], args[-1]))

    def search(degrees, gain):
        found = _turned(state, degrees).T_world_root
        monkeypatch.setattr(tracker, "recover", lambda *a, **k: RecoveryResult(
            T_world_root=found, score=jnp.asarray(0.8 + gain), own_score=jnp.asarray(0.8), index=jnp.asarray(1),
            scores=jnp.zeros(3), status=jnp.asarray(0)))
        tried.clear()
        tracker._search(state, state, eqx.tree_at(lambda r: r.T_world_root, tracked, state.T_world_root),
                        sequence["images"][1], None, None)
        return bool(tried)

    near, far = 0.5 * config.near_deg, min(2.0 * config.near_deg, 170.0)
    assert search(near, 0.0) and not search(near, -0.001)
    assert not search(far, 0.0) and not search(far, 0.5 * config.margin)
    assert search(far, 1.5 * config.margin)


@pytest.mark.xdist_group("lines_sift")
def test_a_persistently_lost_object_is_searched_less_and_less_often(sequence, lines_sift):
    """The search's backoff (`RecoveryConfig.max_skip`): of a run of lost frames whose searches find nothing, lost
    frames 1, 2, 4, 8, 16, 25, 34 are searched (after k failed searches min(2^(k-1) - 1, 8) are skipped, each LOST as
    a failed search leaves it); a RECOVERED search, or a frame not LOST, starts the count over."""
    tracker, state, tracked = lines_sift
    calls, outcome = [], {"recovered": False}
    saved = dict(vars(tracker))  # the group's other tests use this tracker: its host state is put back after

    def run(frames):
        searched = []
        for k in range(1, frames + 1):
            before = len(calls)
            _, result, info = tracker._recover(state, state, tracked, sequence["images"][1], None, None)
            searched.append(k) if len(calls) > before else None
            assert len(calls) > before or info["skipped"] == "backoff"
            assert result is tracked
        return searched

    try:
        tracker._failed_searches = tracker._searches_to_skip = 0
        tracker._search = lambda st, lost_state, lost, *a: calls.append(len(calls)) or (
            lost_state, lost, dict(outcome, source=None, windows=None))
        assert run(34) == [1, 2, 4, 8, 16, 25, 34]
        outcome["recovered"] = True  # the 8 skips due, then found: every lost frame after it is searched again
        assert run(11) == [9, 10, 11]
        outcome["recovered"] = False
        run(4)
        assert tracker._searches_to_skip > 0
        _, result, _ = tracker.step(state, sequence["images"][1], recover=False)  # a frame not LOST starts over
        assert int(result.status) != jt.Status.LOST, jt.Status(int(result.status)).name
        assert tracker._searches_to_skip == 0 and run(2) == [1, 2]
    finally:
        vars(tracker).clear()
        vars(tracker).update(saved)


@pytest.mark.xdist_group("lines_sift")
def test_a_refused_restart_leaves_the_host_state_as_it_was(sequence, lines_sift):
    """The step from a found pose (`Tracker._restart`) detects SIFT on the frame again in the found box; when the pose
    is refused (here: the lost frame's evidence set below anything a step reports), the tracker's host state (the
    SIFT keypoints it keeps of that frame for the next step) is the lost step's, as if no search had run."""
    tracker, state, _ = lines_sift
    saved = dict(vars(tracker))
    try:
        _, lost, _ = tracker.step(state, sequence["images"][2], recover=False)
        before = {name: {c: tuple(np.array(a, copy=True) for a in entry) for c, entry in cache.items()}
                  for name, cache in tracker.host_cache.items()}
        assert before, "the SIFT modality keeps frame t+1's keypoints"
        unbeatable = eqx.tree_at(lambda r: r.loss_evidence, lost, -jnp.ones_like(lost.loss_evidence))
        frames = tracker.check_frames(sequence["images"][2][None], "frames")
        frames_j = jnp.asarray(tracker._frames_as_state(frames))
        params = tracker.params_for(tracker.crop_shape)
        found = _turned(state, 20.0).T_world_root
        _, out_result, info = tracker._restart(state, state, unbeatable, frames, frames_j, params, found,
                                               {"recovered": False})
        assert not info.get("recovered") and out_result is unbeatable
        after = tracker.host_cache
        assert set(after) == set(before) and all(set(after[n]) == set(before[n]) for n in before)
        for name, cache in before.items():
            for c, entry in cache.items():
                assert all(np.array_equal(a, b) for a, b in zip(entry, after[name][c])), (name, c)
    finally:
        vars(tracker).clear()
        vars(tracker).update(saved)


@pytest.mark.xdist_group("lines_sift")
def test_a_lost_frame_not_recovered_goes_on_as_without_recovery(sequence, lines_sift):
    """A LOST frame whose search finds nothing (here: due none by the backoff) leaves the state the step made, colour
    histograms and appearance model learnt from it, exactly as `recover=False` does: recovery changes a run only
    where it RECOVERS a frame (kept as they were, the noisy moving camera and the noise table lost frames earlier)."""
    tracker, state, _ = lines_sift
    saved = dict(vars(tracker))
    # SIFT's keypoint cache is a dict the step fills in place: both steps start from the same one (the first would
    # otherwise reuse frame t's keypoints kept by the fixture's step and the second detect them anew: other rows).
    saved_cache = copy.deepcopy(tracker.host_cache)
    try:
        jumped = _turned(state, 50.0)
        plain_state, plain, _ = tracker.step(jumped, sequence["images"][2], recover=False)
        assert int(plain.status) == jt.Status.LOST, jt.Status(int(plain.status)).name
        vars(tracker).clear()
        vars(tracker).update(saved)
        tracker.host_cache = copy.deepcopy(saved_cache)
        tracker._searches_to_skip = 1  # the backoff: this lost frame is due no search
        lost_state, lost, info = tracker.step(jumped, sequence["images"][2])
        assert info["recovery"]["skipped"] == "backoff" and int(lost.status) == jt.Status.LOST
        leaves = jax.tree.leaves(eqx.filter(plain_state, eqx.is_array))
        assert len(leaves) == len(jax.tree.leaves(eqx.filter(lost_state, eqx.is_array)))
        for a, b in zip(leaves, jax.tree.leaves(eqx.filter(lost_state, eqx.is_array))):
            assert np.array_equal(np.asarray(a), np.asarray(b))
        hist = lambda st: st.modalities[tracker.recovery_modality()].histograms
        assert not all(np.array_equal(np.asarray(a), np.asarray(b))
                       for a, b in zip(jax.tree.leaves(hist(lost_state)), jax.tree.leaves(hist(jumped))))  # learnt
    finally:
        vars(tracker).clear()
        vars(tracker).update(saved)
        tracker.host_cache = saved_cache


@pytest.mark.xdist_group("lines_sift")
def test_the_recovery_restart_asks_for_windows_without_the_last_motion(sequence, lines_sift, monkeypatch):
    """The recovery's second step runs frames t+1 → t+1 from a found pose: no motion between a frame and itself, so
    `Tracker._restart` asks for windows around the found box without the last step's motion (`follow_motion=False`)."""
    tracker, state, tracked = lines_sift
    asked = []

    class Asked(Exception):
        pass

    def windows(T, theta, boxes=None, follow_motion=True):
        asked.append(follow_motion)
        raise Asked  # the wiring is what is checked here, not the step after it

    monkeypatch.setattr(tracker, "windows", windows)
    with pytest.raises(Asked):
        tracker._restart(state, state, tracked, sequence["images"][1], None, None, tracked.T_world_root, {})
    assert asked == [False]
