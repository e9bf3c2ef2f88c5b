"""Several objects in one scene (`JointTracker`, `track_objects`, `jaxtrack track --obj-id 1,2`).

The scene: two photo-textured boxes crossing, object 1 in front (`jaxtrack.synth.CrossingConfig`); object 2's
contour is half hidden for several frames. Tracked jointly, object 2's hidden lines are left out and both are
tracked; tracked alone, object 2's lines lock onto object 1's outline.
"""

import json
import re

import cv2
import jax.numpy as jnp
import numpy as np
import pytest

import jaxtrack as jt
from jaxtrack.cli import main
from jaxtrack.cues.lines import line_params, unoccluded
from jaxtrack.io import read_bop_results, read_sequence
from jaxtrack.track import JointTracker, evaluate_tracking, track_sequence
from jaxtrack.track._overlay import OBJECT_COLOURS

FRAMES = 24
# One worker runs the module: its fixtures (the scene, the joint run) are made once.
pytestmark = pytest.mark.xdist_group("joint")


@pytest.fixture(scope="module", autouse=True)
def _view_model_642():
    """642 views (the suite's default 162 are 16° apart: on this scene even the unhidden object 1 then loses
    frames 17-19 alone as jointly; the tracker's default is 2562)."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("JAXTRACK_VIEW_SUBDIVISIONS", "3")
        yield


@pytest.fixture(scope="module")
def crossing(tmp_path_factory):
    from jaxtrack.synth import CrossingConfig, write_crossing_sequence

    return write_crossing_sequence(CrossingConfig(frames=FRAMES), tmp_path_factory.mktemp("joint") / "seq")


@pytest.fixture(scope="module")
def joint_run(crossing, tmp_path_factory):
    """`jaxtrack track SEQ --obj-id 1,2` (the line modality), its CSV, frames.jsonl and overlay folder."""
    out = tmp_path_factory.mktemp("joint_out")
    code = main(["track", str(crossing), "--obj-id", "1,2", "--cues", "region", "-o", str(out / "r.csv"),
                 "--video", str(out / "overlay"), "--quiet"])
    return code, out


def test_a_point_behind_an_occluder_is_hidden_and_one_in_front_is_not():
    occ = jnp.full((20, 30), jnp.inf).at[5:10, 10:20].set(500.0)
    centre = jnp.array([[12.0, 7.0], [12.0, 7.0], [2.0, 2.0], [29.6, 19.6]])
    depth = jnp.array([600.0, 510.0, 600.0, 600.0])
    threshold = line_params().model_occlusion_threshold
    assert np.asarray(unoccluded(centre, depth, occ, threshold)).tolist() == [False, True, True, True]


def test_joint_tracking_tracks_both_crossing_objects(crossing, joint_run):
    code, out = joint_run
    assert code == 0
    rows = read_bop_results(out / "r.csv")
    assert sorted({r[2] for r in rows}) == [1, 2] and len(rows) == 2 * FRAMES
    records = [json.loads(line) for line in (out / "r.frames.jsonl").read_text().splitlines()]
    assert sorted({r["obj_id"] for r in records}) == [1, 2]
    assert len(list((out / "overlay").glob("*.png"))) == FRAMES
    first = cv2.imread(str(out / "overlay" / "000000.png"))[..., ::-1]  # each object outlined in its own colour
    assert all(np.all(first == colour, axis=-1).sum() > 50 for colour in OBJECT_COLOURS[:2])
    rates = {}
    for obj in (1, 2):
        ev = evaluate_tracking(out / "r.csv", crossing, obj_id=obj)
        rates[obj] = float(np.mean(ev.success[ev.has_gt]))
        assert float(np.median(ev.rot_deg[1:])) < 3.0, (obj, ev.rot_deg)
    # Measured (642 views, the suite's XLA settings): both 100 %, object 2 up to 3.1° off.
    assert rates[1] == 1.0 and rates[2] >= 0.9, rates


def test_alone_the_hidden_object_is_lost_where_joint_tracking_keeps_it(crossing, joint_run):
    run = track_sequence(crossing, obj_id=2, cues=("region",), progress=False)
    gt = read_sequence(crossing).views[0].T_cam_obj[2]
    err_mm = np.linalg.norm(run.T_cam_obj(0)[:, :3, 3] - gt[:, :3, 3], axis=1)
    ev = evaluate_tracking(joint_run[1] / "r.csv", crossing, obj_id=2)
    # Measured: alone 25 % of the frames within 5 cm / 5°, jointly 100 %.
    assert np.mean(err_mm < 50) < np.mean(ev.success[ev.has_gt]) - 0.3
    assert np.max(err_mm) > 100


def test_joint_tracker_refuses_trackers_on_different_rigs():
    mesh = jt.render.make_mesh(np.eye(3) * 10, np.array([[0, 1, 2]]))
    a = jt.geometry.make_camera(np.array([[100.0, 0, 32], [0, 100, 24], [0, 0, 1]]), 64, 48)
    b = jt.geometry.make_camera(np.array([[120.0, 0, 32], [0, 120, 24], [0, 0, 1]]), 64, 48)
    with pytest.raises(ValueError, match=r"trackers\[1\] has another rig"):
        JointTracker([jt.Tracker(mesh, a), jt.Tracker(mesh, b)])
    with pytest.raises(ValueError, match="at least one"):
        JointTracker([])


def test_joint_tracker_turns_off_the_search_after_a_lost_frame():
    """Each object's `Tracker` recovers by default; in a joint run the search would score lines the other objects
    hide, so `JointTracker` turns it off (and with it the keyframes `start` would take)."""
    mesh = jt.render.make_mesh(np.eye(3) * 10, np.array([[0, 1, 2]]))
    cam = jt.geometry.make_camera(np.array([[100.0, 0, 32], [0, 100, 24], [0, 0, 1]]), 64, 48)
    trackers = [jt.Tracker(mesh, cam), jt.Tracker(mesh, cam)]
    assert all(t.config.recovers() for t in trackers)
    JointTracker(trackers)
    assert not any(t.config.recovers() for t in trackers)
    assert trackers[0].setup().config == jt.Tracker(mesh, cam).setup().config  # the same step program as before


@pytest.mark.parametrize("argv, message", [
    (["--obj-id", "1,2", "--reset-on-failure"], "--reset-on-failure: not available when several objects"),
    (["--obj-id", "1,2", "--init-pose", "1 0 0 0 0 1 0 0 0 0 1 500"], "--init-pose given 1 time"),
    (["--obj-id", "1,3"], "object 3 has no mesh"),
    (["--obj-id", "all", "--cameras", "3"], "--cameras: view 3 out of range"),
])
def test_joint_cli_bad_input_is_refused_before_tracking(crossing, tmp_path, capsys, argv, message):
    assert main(["track", str(crossing), "-o", str(tmp_path / "r.csv"), "--quiet", *argv]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "r.csv").exists()


def test_own_footage_needs_one_first_pose_per_mesh(crossing, tmp_path, capsys):
    calib = tmp_path / "cam.json"
    calib.write_text(json.dumps({"K": [[350, 0, 159.5], [0, 350, 119.5], [0, 0, 1]], "width": 320, "height": 240}))
    points = tmp_path / "p.json"
    points.write_text(json.dumps({"image_points": [[0, 0]] * 4, "model_points": [[0, 0, 0]] * 4}))
    models = crossing / "models"
    argv = ["track", str(crossing / "000000" / "rgb"), "--mesh", str(models / "obj_000001.ply"), "--mesh",
            str(models / "obj_000002.ply"), "--camera", str(calib), "--init-points", str(points), "-o", str(tmp_path / "r.csv")]
    assert main(argv) == 2
    assert "--mesh given 2 time(s), --init-points 1 time(s)" in capsys.readouterr().err


def test_two_objects_experiment_smoke(crossing, tmp_path):
    """experiments/two_objects.py end to end on one short scene (the joint run's programs are compiled already)."""
    import importlib.util
    import pathlib

    path = pathlib.Path(__file__).resolve().parents[1] / "experiments" / "two_objects.py"
    spec = importlib.util.spec_from_file_location("two_objects", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    out = tmp_path / "two.md"
    assert module.main(["--seeds", "0", "--cues", "region", "--frames", "4", "--priors", "m3t", "-o", str(out)]) == 0
    text = out.read_text()
    assert "| region | 2 (behind) | joint, prior m3t |" in text and "| region | 1 (front) | alone, prior m3t |" in text


def test_bop_first_pose_behind_the_camera_and_a_far_principal_point_are_named(crossing, tmp_path, capsys):
    import shutil

    seq = tmp_path / "seq"
    shutil.copytree(crossing, seq)
    gt_path = seq / "000000" / "scene_gt.json"
    gt = json.loads(gt_path.read_text())
    gt["0"][1]["cam_t_m2c"][2] = -700.0
    gt_path.write_text(json.dumps(gt))
    assert main(["track", str(seq), "--obj-id", "2", "-o", str(tmp_path / "r.csv"), "--quiet"]) == 2
    assert re.search(r"scene_gt.json: frame 0, obj_id 2: the pose puts the object behind the camera", capsys.readouterr().err)
    shutil.copy(crossing / "000000" / "scene_gt.json", gt_path)
    cam_path = seq / "000000" / "scene_camera.json"
    cam = json.loads(cam_path.read_text())
    for entry in cam.values():
        entry["cam_K"][2] = 5000.0
    cam_path.write_text(json.dumps(cam))
    assert main(["track", str(seq), "-o", str(tmp_path / "r.csv"), "--quiet"]) == 2
    assert re.search(r"scene_camera.json: frame 0 field 'cam_K' puts the principal point at \(5000, 119.5\), outside the "
                     r"320x240 images", capsys.readouterr().err)


def _rbot_layout(crossing, root, variant="d_occlusion", frames=6):
    """The crossing scene written in the RBOT dataset's layout (object 1 as "box", object 2 as the squirrel)."""
    import shutil

    import trimesh

    seq = read_sequence(crossing)
    view = seq.views[0]
    (root / "box" / "frames").mkdir(parents=True)
    for k in range(frames):
        shutil.copy(view.frame_paths[k], root / "box" / "frames" / f"{variant}{k:04d}.png")
    for name, obj in (("poses_first.txt", 1), ("poses_second.txt", 2)):
        rows = [np.concatenate([T[:3, :3].ravel(), T[:3, 3]]) for T in view.T_cam_obj[obj][:frames]]
        (root / name).write_text("r11\tr12\tr13\tr21\tr22\tr23\tr31\tr32\tr33\ttx\tty\ttz\n"
                                 + "".join("\t".join(f"{v:.9g}" for v in r) + "\n" for r in rows))
    K = view.K
    (root / "camera_calibration.txt").write_text(f"fx\tfy\tcx\tcy\tk1\tk2\tp1\tp2\n{K[0, 0]}\t{K[1, 1]}\t{K[0, 2]}\t{K[1, 2]}"
                                                 "\t0\t0\t0\t0\n")
    trimesh.load(seq.model_paths[1]).export(root / "box" / "box.obj")
    trimesh.load(seq.model_paths[2]).export(root / "squirrel_small.obj")
    return seq


def test_rbot_layout_reads_as_its_bop_twin_and_tracks_both_objects(crossing, tmp_path):
    from jaxtrack.io import read_rbot_sequence
    from jaxtrack.track import track_objects

    bop = _rbot_layout(crossing, tmp_path / "RBOT")
    rbot = read_rbot_sequence(tmp_path / "RBOT", "box", "d_occlusion")
    view, twin = rbot.views[0], bop.views[0]
    assert rbot.num_frames == 6 and sorted(rbot.model_paths) == [1, 2]
    np.testing.assert_allclose(view.K, twin.K)
    for obj in (1, 2):
        np.testing.assert_allclose(view.T_cam_obj[obj], twin.T_cam_obj[obj][:6], atol=1e-6)
    np.testing.assert_array_equal(view.read_frame(3), twin.read_frame(3))
    import equinox as eqx

    from jaxtrack.track import track_step

    traces = []  # traces of the step after each frame: none after the first
    runs = track_objects(rbot, cues=("region",), progress=False,
                         on_frame=lambda records: traces.append(eqx.debug.get_num_traces(track_step)))
    assert len(traces) == 6 and len(set(traces[1:])) == 1, traces
    for run in runs:
        err = np.linalg.norm(run.T_cam_obj(0)[:, :3, 3] - view.T_cam_obj[run.obj_id][:, :3, 3], axis=1)
        assert np.all(err < 20), (run.obj_id, err)


def test_rbot_layout_problems_are_named(crossing, tmp_path):
    from jaxtrack.io import SequenceError, read_rbot_sequence

    root = tmp_path / "RBOT"
    _rbot_layout(crossing, root, "a_regular", frames=4)
    assert sorted(read_rbot_sequence(root, "box").model_paths) == [1]  # no occluder outside d_occlusion
    with pytest.raises(SequenceError, match=r"RBOT.cat.frames: no such RBOT frames folder \(objects in .*\['box'\]\)"):
        read_rbot_sequence(root, "cat")
    with pytest.raises(ValueError, match="RBOT variant must be one of a_regular"):
        read_rbot_sequence(root, "box", "e_fog")
    (root / "box" / "frames" / "a_regular0002.png").unlink()
    with pytest.raises(SequenceError, match=r"a_regular0002.png is missing"):
        read_rbot_sequence(root, "box")
    (root / "box" / "frames" / "a_regular0003.png").unlink()
    lines = (root / "poses_first.txt").read_text().splitlines()
    (root / "poses_first.txt").write_text("\n".join([lines[0], lines[1], "1\t0\t0"]) + "\n")
    with pytest.raises(SequenceError, match=r"poses_first.txt:3: 3 values; a pose is 12 finite numbers"):
        read_rbot_sequence(root, "box")
